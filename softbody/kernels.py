"""Compiled kernels (numba) for the per-element work that numpy cannot batch without dozens of calls.

On a small mesh a step's numpy work is dominated by the cost of each call (1-5 us), not by the arithmetic:
the polar decomposition of the warping rotations, for instance, is about fifty numpy calls per Newton
iteration whatever the number of elements. These kernels do the same arithmetic in one compiled loop.
They are compiled on first use and cached on disk (numba's ``cache=True``, next to this file in
``__pycache__``), so only the first run after an install pays the compilation (a few seconds, once).

Every kernel has a numpy reference in the module that uses it; the tests compare the two.
``ENABLED`` is False when numba is missing or ``SOFTBODY_NO_NUMBA=1`` is set: then the numpy code runs.
"""
from __future__ import annotations

import math
import os

import numpy as np

try:  # a dependency (pyproject.toml); the numpy paths remain for environments without it
    import numba
except ImportError:  # pragma: no cover - numba is installed with the package
    numba = None

ENABLED = numba is not None and os.environ.get("SOFTBODY_NO_NUMBA", "") not in ("1", "true", "yes")


def _jit(f):
    return numba.njit(cache=True, nogil=True, fastmath=False)(f) if ENABLED else f


@_jit
def polar_newton(F9: np.ndarray, tol: float, max_iter: int, R9: np.ndarray, ok: np.ndarray) -> None:
    """Rotation factors of F (component-major (9, n), row 3 i + j: F_ij) by the scaled Newton iteration
    R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3), into R9 (9, n); ok (n,) False where det F is not clearly
    positive (inverted or degenerate: the caller uses SVD) or the iteration did not converge. The same
    iteration and stopping rule as softbody.rotation._newton_rotation, element by element."""
    n = F9.shape[1]
    step_tol = math.sqrt(tol)
    a = np.empty(9)
    c = np.empty(9)
    for e in range(n):
        scale = 0.0
        for k in range(9):
            a[k] = F9[k, e]
            scale = max(scale, abs(a[k]))
        det = (a[0] * (a[4] * a[8] - a[5] * a[7]) - a[1] * (a[3] * a[8] - a[5] * a[6])
               + a[2] * (a[3] * a[7] - a[4] * a[6]))
        if not det > 1e-6 * scale * scale * scale:
            ok[e] = False
            for k in range(9):
                R9[k, e] = 0.0
            continue
        converged = False
        for it in range(max_iter):
            # cofactors: c_ij = A_(i+1)(j+1) A_(i+2)(j+2) - A_(i+1)(j+2) A_(i+2)(j+1), indices mod 3
            for i in range(3):
                i1, i2 = 3 * ((i + 1) % 3), 3 * ((i + 2) % 3)
                for j in range(3):
                    j1, j2 = (j + 1) % 3, (j + 2) % 3
                    c[3 * i + j] = a[i1 + j1] * a[i2 + j2] - a[i1 + j2] * a[i2 + j1]
            d = a[0] * c[0] + a[1] * c[1] + a[2] * c[2]
            g = 1.0 / np.cbrt(abs(d))
            gi = 0.5 / (g * d)
            g *= 0.5
            err = 0.0
            for k in range(9):
                new = g * a[k] + gi * c[k]
                err = max(err, abs(new - a[k]))
                a[k] = new
            if (it >= 2 or it == max_iter - 1) and err < step_tol:
                converged = True
                break
        ok[e] = converged
        for k in range(9):
            R9[k, e] = a[k]


@_jit
def pair_outer_sum(g: np.ndarray, pairs: np.ndarray, target: np.ndarray, out: np.ndarray) -> None:
    """out[target[p, i, j, e]] += g[pairs[p, 0], i, e] * g[pairs[p, 1], j, e] for gradients g (k, 3, E), node
    pairs (P, 2) and targets (P, 3, 3, E) into out (flat): the outer products of the pair blocks summed in
    place, in the order of np.bincount over the flattened (P, 3, 3, E) products (so the same sums, bit for
    bit), without the (P, 3, 3, E) temporary (softbody.assembly.UpperAssembly.assemble_pairs)."""
    P = pairs.shape[0]
    E = g.shape[2]
    for p in range(P):
        a, b = pairs[p, 0], pairs[p, 1]
        for i in range(3):
            for j in range(3):
                for e in range(E):
                    out[target[p, i, j, e]] += g[a, i, e] * g[b, j, e]
