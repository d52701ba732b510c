"""Mesh builders (structured box and tube), tet4 -> tet10 refinement, and file reading through meshio."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import warnings

import numpy as np

from .elements import ELEMENT_TYPES, TET10_EDGES
from .errors import InvalidInputError, MeshError
from .mesh import Mesh, _list_some, reorient

# Freudenthal 5-tet cuts of a hex cell (hex8 local node order). Cut A has the inner tet {0, 2, 5, 7},
# cut B {1, 3, 4, 6}; alternating them in a checkerboard makes the face diagonals of neighbours match.
_CUT_A = np.array([[1, 0, 2, 5], [3, 0, 2, 7], [4, 0, 5, 7], [6, 2, 5, 7], [0, 2, 5, 7]])
_CUT_B = np.array([[0, 1, 3, 4], [2, 1, 3, 6], [5, 1, 4, 6], [7, 3, 4, 6], [1, 3, 4, 6]])


def _check_cells(cells: Sequence[int], name: str = "cells") -> tuple[int, int, int]:
    try:
        c = tuple(int(v) for v in cells)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be three positive integers, got {cells!r}") from None
    if len(c) != 3 or min(c) < 1 or any(float(a) != float(b) for a, b in zip(c, cells)):
        raise InvalidInputError(f"{name} must be three positive integers, got {cells!r}")
    return c


def _check_kind(kind: str) -> str:
    if kind not in ELEMENT_TYPES:
        raise InvalidInputError(f"unknown element kind {kind!r}; valid kinds are {sorted(ELEMENT_TYPES)}")
    return kind


def _check_center(center) -> np.ndarray:
    try:
        c = np.asarray(center, dtype=float)
    except (TypeError, ValueError):
        c = None
    if c is None or c.shape != (3,) or not np.all(np.isfinite(c)):
        raise InvalidInputError(f"center must be three finite numbers [m], got {center!r}")
    return c


def _orient_tets(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    X = nodes[tets]
    det = np.linalg.det(np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2))
    tets = tets.copy()
    neg = det < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2], tets[neg, 1].copy()
    return tets


def cells_to_mesh(nodes: np.ndarray, hexes: np.ndarray, parity: np.ndarray, kind: str) -> Mesh:
    """Build a mesh of ``kind`` from hex cells (C, 8) in VTK order.

    tet4/tet10 cut every cell into 5 tets, cut A where parity is even, cut B where odd.
    """
    if kind == "hex8":
        return Mesh(nodes, hexes, "hex8")
    tets = np.where((parity % 2 == 0)[:, None, None], hexes[:, _CUT_A], hexes[:, _CUT_B]).reshape(-1, 4)
    mesh = Mesh(nodes, _orient_tets(nodes, tets), "tet4")
    return to_tet10(mesh) if kind == "tet10" else mesh


def grid_mesh_size(cells: Sequence[int], kind: str = "tet4", periodic_first: bool = False) -> tuple[int, int]:
    """(nodes, elements) of the structured mesh ``box_mesh`` builds (``tube_mesh`` with ``periodic_first``:
    the first axis closes on itself), without building it. tet10 adds a node on every grid edge and on one
    diagonal of every cell face (the 5-tet cut uses face diagonals only)."""
    _check_kind(kind)
    nx, ny, nz = _check_cells(cells)
    n_cells = nx * ny * nz
    if kind == "tet10":
        return (2 * nx if periodic_first else 2 * nx + 1) * (2 * ny + 1) * (2 * nz + 1) - n_cells, 5 * n_cells
    nodes = (nx if periodic_first else nx + 1) * (ny + 1) * (nz + 1)
    return nodes, n_cells if kind == "hex8" else 5 * n_cells


def box_mesh(size: Sequence[float], cells: Sequence[int], kind: str = "tet4", center=(0.0, 0.0, 0.0)) -> Mesh:
    """Structured box of size (Lx, Ly, Lz) [m] centred at ``center`` with cells (nx, ny, nz).

    hex8 uses the cells; tet4 cuts each cell into 5 tets in a checkerboard; tet10 adds mid-edge nodes.
    """
    _check_kind(kind)
    nx, ny, nz = _check_cells(cells)
    size = np.asarray(size, dtype=float)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise InvalidInputError(f"size must be three positive lengths, got {size!r}")
    axes = [np.linspace(-s / 2, s / 2, n + 1) for s, n in zip(size, (nx, ny, nz))]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    nodes = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]) + _check_center(center)
    nid = np.arange(len(nodes)).reshape(nz + 1, ny + 1, nx + 1)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    k, j, i = k.ravel(), j.ravel(), i.ravel()
    hexes = np.stack([nid[k, j, i], nid[k, j, i + 1], nid[k, j + 1, i + 1], nid[k, j + 1, i],
                      nid[k + 1, j, i], nid[k + 1, j, i + 1], nid[k + 1, j + 1, i + 1], nid[k + 1, j + 1, i]], axis=1)
    return cells_to_mesh(nodes, hexes, i + j + k, kind)


def _cube_to_ball(p: np.ndarray) -> np.ndarray:
    """The smooth map of the cube [-1, 1]^3 onto the unit ball (its faces onto the sphere), points (n, 3)."""
    x, y, z = p.T
    return np.column_stack([x * np.sqrt(1 - y**2 / 2 - z**2 / 2 + y**2 * z**2 / 3),
                            y * np.sqrt(1 - z**2 / 2 - x**2 / 2 + z**2 * x**2 / 3),
                            z * np.sqrt(1 - x**2 / 2 - y**2 / 2 + x**2 * y**2 / 3)])


def ball_mesh(radius: float, cells: int, kind: str = "tet4", center=(0.0, 0.0, 0.0)) -> Mesh:
    """A ball of ``radius`` [m]: a cube grid of cells^3 cells mapped onto the sphere (smooth cube-to-ball map).

    tet10: the midside nodes of surface edges are moved radially onto the sphere (the faces curve with it),
    the others stay at their edges' midpoints. Volume against the sphere's: -0.64% at 2 cells, -0.15% at 3,
    -0.05% at 4 (tet4 and hex8, flat faces: -11% at 3 cells, -6% at 4)."""
    _check_kind(kind)
    if not (isinstance(radius, (int, float, np.number)) and np.isfinite(radius) and radius > 0):
        raise InvalidInputError(f"radius must be > 0, got {radius!r}")
    center = _check_center(center)
    n = _check_cells((cells, cells, cells))[0]
    cube = box_mesh((2.0, 2.0, 2.0), (n, n, n), "hex8" if kind == "hex8" else "tet4")
    mesh = Mesh(radius * _cube_to_ball(cube.nodes), cube.elements, cube.kind)
    if kind == "tet10":
        mesh = to_tet10(mesh)
        surface = mesh.surface_nodes()
        mid = surface[surface >= cube.n_nodes]  # midside nodes of surface edges: onto the sphere, radially
        nodes = mesh.nodes.copy()
        nodes[mid] *= radius / np.linalg.norm(nodes[mid], axis=1)[:, None]
        mesh = Mesh(nodes, mesh.elements, "tet10")
    return mesh.translated(center)


def tube_mesh(r_outer: float, r_inner: float, length: float, cells: Sequence[int], kind: str = "tet4") -> Mesh:
    """Hollow circular tube about the z axis, z in [-length, 0] (top ring at z = 0).

    cells = (n_theta, n_r, n_z); n_theta must be even (>= 4) for the tet checkerboard to close.
    """
    _check_kind(kind)
    nt, nr, nz = _check_cells(cells)
    if not (np.isfinite([r_outer, r_inner, length]).all() and 0 < r_inner < r_outer and length > 0):
        raise InvalidInputError(
            f"tube needs 0 < r_inner < r_outer and length > 0, got r_inner={r_inner}, r_outer={r_outer}, length={length}")
    if nt < 4 or (kind != "hex8" and nt % 2):
        raise InvalidInputError(f"n_theta must be >= 4 (and even for tets), got {nt}")
    theta = 2 * np.pi * np.arange(nt) / nt
    r = np.linspace(r_inner, r_outer, nr + 1)
    z = np.linspace(-length, 0.0, nz + 1)
    zz, tt, rr = np.meshgrid(z, theta, r, indexing="ij")
    nodes = np.column_stack([(rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), zz.ravel()])
    nid = np.arange(len(nodes)).reshape(nz + 1, nt, nr + 1)
    k, t, i = np.meshgrid(np.arange(nz), np.arange(nt), np.arange(nr), indexing="ij")
    k, t, i = k.ravel(), t.ravel(), i.ravel()
    t1 = (t + 1) % nt
    # local axes (r, theta, z) are right-handed, so the hex has positive Jacobian
    hexes = np.stack([nid[k, t, i], nid[k, t, i + 1], nid[k, t1, i + 1], nid[k, t1, i],
                      nid[k + 1, t, i], nid[k + 1, t, i + 1], nid[k + 1, t1, i + 1], nid[k + 1, t1, i]], axis=1)
    return cells_to_mesh(nodes, hexes, i + t + k, kind)


def to_tet10(mesh: Mesh) -> Mesh:
    """Quadratic tets from a tet4 mesh: one new node at the midpoint of every edge, shared by its tets."""
    if mesh.kind != "tet4":
        raise InvalidInputError(f"to_tet10 needs a tet4 mesh, got {mesh.kind}")
    edges = np.sort(mesh.elements[:, TET10_EDGES].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mids = 0.5 * (mesh.nodes[unique[:, 0]] + mesh.nodes[unique[:, 1]])
    nodes = np.vstack([mesh.nodes, mids])
    mid_ids = mesh.n_nodes + inverse.reshape(mesh.n_elements, 6)
    return Mesh(nodes, np.hstack([mesh.elements, mid_ids]), "tet10")


_MESHIO_KINDS = {"tetra": "tet4", "hexahedron": "hex8", "tetra10": "tet10"}


def read_mesh(path: str | Path, strict: bool = False) -> Mesh:
    """Read a volume mesh through meshio (VTK, VTU, Gmsh, ...). The file must hold exactly one of
    tetra / hexahedron / tetra10 cell blocks (surface cells are ignored).

    Elements inverted everywhere (a mirrored node order, as some exporters write) are re-oriented with a
    warning that counts them; ``strict=True`` refuses them instead (MeshError). Tangled elements (Jacobians
    of both signs) and flat ones are always refused."""
    import meshio

    path = Path(path)
    if not path.exists():
        raise InvalidInputError(f"mesh file {str(path)!r} does not exist")
    try:
        m = meshio.read(str(path))
    except Exception as exc:  # meshio raises many types
        raise MeshError(f"meshio could not read {str(path)!r}: {exc}") from exc
    blocks: dict[str, list[np.ndarray]] = {}
    for cb in m.cells:
        if cb.type in _MESHIO_KINDS:
            blocks.setdefault(_MESHIO_KINDS[cb.type], []).append(cb.data)
    if len(blocks) != 1:
        found = sorted({cb.type for cb in m.cells})
        raise MeshError(f"{str(path)!r} must hold exactly one volume cell type out of "
                        f"{sorted(_MESHIO_KINDS)}; it has {found}")
    kind, data = next(iter(blocks.items()))
    pts = np.asarray(m.points, dtype=float)
    if pts.shape[1] == 2:
        raise MeshError(f"{str(path)!r} has 2-D points; a volume mesh needs 3-D coordinates")
    elements = np.vstack(data)
    if strict:
        return Mesh(pts, elements, kind)
    try:
        Mesh(pts, elements, kind)
    except MeshError as exc:
        if "inverted" not in str(exc):
            raise
    else:
        return Mesh(pts, elements, kind)
    fixed, flipped = reorient(pts, elements, kind)
    mesh = Mesh(pts, fixed, kind)  # still refuses tangled elements
    warnings.warn(f"{str(path)!r}: re-oriented {len(flipped)} of {len(elements)} inverted {kind} elements "
                  f"(mirrored node order; elements {_list_some(flipped)}); read_mesh(..., strict=True) refuses them",
                  stacklevel=2)
    return mesh
