"""Shared helpers for the softbody test suite.

Everything here is written independently of softbody's internals (own elasticity matrix, own rigid
modes, own Voigt convention), so that tests compare the library against an outside truth.
"""
from __future__ import annotations

import os
import re

# the kernels compile in this process at first use (softbody.compilation): a test comparing a kernel with its numpy
# code must know which one runs, whatever the state of numba's cache (tests/test_compilation.py tests the default)
os.environ["SOFTBODY_COMPILE"] = "now"

import numpy as np
import pytest

import softbody

KINDS = ["tet4", "hex8", "tet10"]

# docs/method.md section 2: tet10 mid-edge nodes 4..9 sit on these vertex pairs.
TET10_EDGES_SPEC = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]


def lame(E: float, nu: float) -> tuple[float, float]:
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def elasticity_matrix(E: float, nu: float) -> np.ndarray:
    """docs/method.md eq. 3 written out entry by entry."""
    lam, mu = lame(E, nu)
    a = lam + 2 * mu
    return np.array([
        [a, lam, lam, 0, 0, 0],
        [lam, a, lam, 0, 0, 0],
        [lam, lam, a, 0, 0, 0],
        [0, 0, 0, mu, 0, 0],
        [0, 0, 0, 0, mu, 0],
        [0, 0, 0, 0, 0, mu],
    ], dtype=float)


def voigt_strain(A: np.ndarray) -> np.ndarray:
    """Small strain of the displacement gradient A = du/dX in docs/method.md's Voigt order (engineering shear)."""
    return np.array([A[0, 0], A[1, 1], A[2, 2],
                     A[0, 1] + A[1, 0], A[1, 2] + A[2, 1], A[0, 2] + A[2, 0]])


def rigid_modes(X: np.ndarray) -> np.ndarray:
    """The 6 rigid-body modes (6, 3N), interleaved DOFs: 3 translations, 3 infinitesimal rotations w x X."""
    N = len(X)
    modes = []
    for d in range(3):
        t = np.zeros((N, 3))
        t[:, d] = 1.0
        modes.append(t.ravel())
    c = X - X.mean(axis=0)
    for d in range(3):
        w = np.zeros(3)
        w[d] = 1.0
        modes.append(np.cross(w, c).ravel())
    return np.array(modes)


def rotation_matrix(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def box_boundary_mask(nodes: np.ndarray, lo, hi, tol: float = 1e-12) -> np.ndarray:
    """Nodes on the boundary planes of the axis-aligned box [lo, hi] (independent of surface_triangles)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return (np.isclose(nodes, lo, atol=tol) | np.isclose(nodes, hi, atol=tol)).any(axis=1)


def distorted_box(kind: str, cells=(2, 2, 2), size=(1.0, 0.8, 0.6), amp: float = 0.2, seed: int = 0) -> softbody.Mesh:
    """A box mesh whose interior vertices are randomly moved by up to ``amp`` of a cell size in each direction.

    tet10 is built from the distorted tet4 mesh, so its elements stay straight-sided (mid-edge nodes at
    edge midpoints). Boundary nodes stay on the box faces. softbody.Mesh validates orientation, so the
    result is a valid mesh.
    """
    base_kind = "tet4" if kind == "tet10" else kind
    m = softbody.box_mesh(size, cells, base_kind)
    size = np.asarray(size, float)
    h = size / np.asarray(cells)
    inner = ~box_boundary_mask(m.nodes, -size / 2, size / 2)
    assert inner.any(), "need at least one interior node"
    rng = np.random.default_rng(seed)
    nodes = m.nodes.copy()
    nodes[inner] += amp * h * rng.uniform(-1, 1, size=(inner.sum(), 3))
    m = softbody.Mesh(nodes, m.elements, base_kind)
    return softbody.to_tet10(m) if kind == "tet10" else m


def dense(a) -> np.ndarray:
    return a.toarray() if hasattr(a, "toarray") else np.asarray(a)


@pytest.fixture(params=KINDS)
def kind(request) -> str:
    return request.param


def raises_naming(*names, call, exc=softbody.InvalidInputError):
    """Assert ``call()`` raises exc (a ValueError subclass) whose message contains every name as a whole token."""
    assert issubclass(exc, ValueError)
    with pytest.raises(exc) as info:
        call()
    msg = str(info.value)
    for name in names:
        assert re.search(r"(?<![\w.])" + re.escape(str(name)) + r"(?![\w])", msg), f"{name!r} not named in: {msg}"
    return msg
