"""Element types: shape functions, quadrature rules, faces and characteristic tetrahedra.

Node orders follow VTK (docs/method.md section 2). Natural coordinates are xi = (xi1, xi2, xi3):
for tetrahedra the unit simplex (vertex 0 at the origin, vertices 1..3 on the axes; the
barycentric coordinates are (1 - xi1 - xi2 - xi3, xi1, xi2, xi3)), for hexahedra the cube [-1, 1]^3.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from scipy.special import roots_jacobi

from .errors import InvalidInputError

Rule = tuple[np.ndarray, np.ndarray]  # points (q, 3) in natural coordinates, weights (q,)


@dataclass(frozen=True)
class ElementType:
    """Everything that is specific to one kind of element.

    shape(xi) -> (q, k) values; grad(xi) -> (q, k, 3) derivatives d N / d xi.
    Weights of the rules integrate over the reference element (volume 1/6 for tets, 8 for hexes).
    faces: boundary faces as local node lists (corners first), outward for a positively oriented element.
    face_triangles: per face, its split into triangles (local node indices), outward.
    char_tets: (c, 4) local nodes of the characteristic tetrahedra (their F is averaged).
    """

    name: str
    vtk_id: int
    meshio_name: str
    n_nodes: int
    natural_nodes: np.ndarray
    shape: Callable[[np.ndarray], np.ndarray]
    grad: Callable[[np.ndarray], np.ndarray]
    stiffness_rule: Rule
    mass_rule: Rule
    faces: np.ndarray
    face_triangles: np.ndarray
    n_face_corners: int
    char_tets: np.ndarray
    centroid: np.ndarray
    check_points: np.ndarray  # where the Jacobian must be positive


# ---------------------------------------------------------------- quadrature

def tet_rule(n: int) -> Rule:
    """Conical-product Gauss rule on the unit tetrahedron, exact for polynomials of degree 2n - 1."""
    pts, wts = [], []
    for a in (2, 1, 0):
        x, w = roots_jacobi(n, a, 0)  # weight (1 - x)^a on [-1, 1]
        pts.append((x + 1.0) / 2.0)
        wts.append(w / 2.0 ** (a + 1))
    t1, t2, t3 = np.meshgrid(*pts, indexing="ij")
    w = np.einsum("i,j,k->ijk", *wts).ravel()
    t1, t2, t3 = t1.ravel(), t2.ravel(), t3.ravel()
    xi = np.stack([t1, t2 * (1 - t1), t3 * (1 - t1) * (1 - t2)], axis=1)
    return xi, w


def hex_rule(n: int) -> Rule:
    """Tensor Gauss-Legendre rule with n points per direction on [-1, 1]^3."""
    x, w = np.polynomial.legendre.leggauss(n)
    g = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    return g, np.einsum("i,j,k->ijk", w, w, w).ravel()


def tet10_stiffness_rule() -> Rule:
    """The 4-point rule of docs/method.md: barycentric (a, b, b, b) and permutations, weight 1/4 of the volume."""
    a = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0
    b = (5.0 - np.sqrt(5.0)) / 20.0
    bary = np.full((4, 4), b)
    np.fill_diagonal(bary, a)
    return bary[:, 1:].copy(), np.full(4, 1.0 / 24.0)


# ---------------------------------------------------------------- shape functions

def _tet4_shape(xi: np.ndarray) -> np.ndarray:
    return np.column_stack([1.0 - xi.sum(axis=1), xi])


def _tet4_grad(xi: np.ndarray) -> np.ndarray:
    g = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    return np.broadcast_to(g, (len(xi), 4, 3)).copy()


TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])


def _bary(xi: np.ndarray) -> np.ndarray:
    return np.column_stack([1.0 - xi.sum(axis=1), xi])


_DL = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])  # d L_i / d xi


def _tet10_shape(xi: np.ndarray) -> np.ndarray:
    L = _bary(xi)
    corners = L * (2.0 * L - 1.0)
    mids = 4.0 * L[:, TET10_EDGES[:, 0]] * L[:, TET10_EDGES[:, 1]]
    return np.concatenate([corners, mids], axis=1)


def _tet10_grad(xi: np.ndarray) -> np.ndarray:
    L = _bary(xi)
    corners = (4.0 * L - 1.0)[:, :, None] * _DL[None]
    i, j = TET10_EDGES[:, 0], TET10_EDGES[:, 1]
    mids = 4.0 * (L[:, j, None] * _DL[i][None] + L[:, i, None] * _DL[j][None])
    return np.concatenate([corners, mids], axis=1)


HEX8_NATURAL = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)


def _hex8_shape(xi: np.ndarray) -> np.ndarray:
    return np.prod(1.0 + xi[:, None, :] * HEX8_NATURAL[None], axis=2) / 8.0


def _hex8_grad(xi: np.ndarray) -> np.ndarray:
    f = 1.0 + xi[:, None, :] * HEX8_NATURAL[None]  # (q, 8, 3)
    g = np.empty_like(f)
    g[..., 0] = HEX8_NATURAL[:, 0] * f[..., 1] * f[..., 2]
    g[..., 1] = HEX8_NATURAL[:, 1] * f[..., 0] * f[..., 2]
    g[..., 2] = HEX8_NATURAL[:, 2] * f[..., 0] * f[..., 1]
    return g / 8.0


# ---------------------------------------------------------------- faces

TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])


def _tet10_faces() -> tuple[np.ndarray, np.ndarray]:
    edge_node = {frozenset(e): 4 + n for n, e in enumerate(TET10_EDGES.tolist())}
    faces, tris = [], []
    for a, b, c in TET_FACES.tolist():
        ab, bc, ca = edge_node[frozenset((a, b))], edge_node[frozenset((b, c))], edge_node[frozenset((c, a))]
        faces.append([a, b, c, ab, bc, ca])
        tris.append([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]])
    return np.array(faces), np.array(tris)


_T10_FACES, _T10_TRIS = _tet10_faces()

TET4 = ElementType(
    name="tet4", vtk_id=10, meshio_name="tetra", n_nodes=4,
    natural_nodes=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
    shape=_tet4_shape, grad=_tet4_grad,
    stiffness_rule=(np.array([[0.25, 0.25, 0.25]]), np.array([1.0 / 6.0])),
    mass_rule=tet_rule(2),
    faces=TET_FACES, face_triangles=TET_FACES[:, None, :], n_face_corners=3,
    char_tets=np.array([[0, 1, 2, 3]]),
    centroid=np.array([0.25, 0.25, 0.25]),
    check_points=np.array([[0.25, 0.25, 0.25]]),
)

TET10 = ElementType(
    name="tet10", vtk_id=24, meshio_name="tetra10", n_nodes=10,
    natural_nodes=np.vstack([TET4.natural_nodes,
                             TET4.natural_nodes[TET10_EDGES].mean(axis=1)]),
    shape=_tet10_shape, grad=_tet10_grad,
    stiffness_rule=tet10_stiffness_rule(),
    mass_rule=tet_rule(3),
    faces=_T10_FACES, face_triangles=_T10_TRIS, n_face_corners=3,
    char_tets=np.array([[0, 1, 2, 3]]),
    centroid=np.array([0.25, 0.25, 0.25]),
    check_points=np.vstack([tet10_stiffness_rule()[0], [[0.25, 0.25, 0.25]],
                            TET4.natural_nodes, TET4.natural_nodes[TET10_EDGES].mean(axis=1)]),
)

HEX8 = ElementType(
    name="hex8", vtk_id=12, meshio_name="hexahedron", n_nodes=8,
    natural_nodes=HEX8_NATURAL,
    shape=_hex8_shape, grad=_hex8_grad,
    stiffness_rule=hex_rule(2),
    mass_rule=hex_rule(3),
    faces=HEX_FACES, face_triangles=HEX_FACES[:, [[0, 1, 2], [0, 2, 3]]], n_face_corners=4,
    # inner tetrahedra of the two Freudenthal cuts; their deformation gradients are averaged
    char_tets=np.array([[0, 2, 5, 7], [1, 3, 4, 6]]),
    centroid=np.zeros(3),
    check_points=np.vstack([hex_rule(2)[0], HEX8_NATURAL, np.zeros((1, 3))]),
)

ELEMENT_TYPES: dict[str, ElementType] = {e.name: e for e in (TET4, HEX8, TET10)}


@lru_cache(maxsize=None)
def element_type(kind: str) -> ElementType:
    """The :class:`ElementType` called ``kind`` ("tet4", "hex8" or "tet10")."""
    try:
        return ELEMENT_TYPES[kind]
    except (KeyError, TypeError):
        raise InvalidInputError(
            f"unknown element kind {kind!r}; valid kinds are {sorted(ELEMENT_TYPES)}") from None


def jacobians(et: ElementType, X: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Jacobians J[e, q, d, j] = d X_d / d xi_j of elements with node coordinates X (E, k, 3) at points xi (q, 3)."""
    return np.einsum("ekd,qkj->eqdj", X, et.grad(xi), optimize=True)


def shape_gradients(et: ElementType, X: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical shape-function gradients dN/dX (E, q, k, 3) and det J (E, q) at points xi."""
    J = jacobians(et, X, xi)
    detJ = np.linalg.det(J)
    Jinv = np.linalg.inv(J)
    G = np.einsum("qkj,eqjd->eqkd", et.grad(xi), Jinv, optimize=True)
    return G, detJ
