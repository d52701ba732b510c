"""Mesh: node coordinates and element connectivity of one element kind, validated on construction."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .elements import ElementType, element_type, jacobians
from .errors import MeshError


def _list_some(idx: np.ndarray, limit: int = 10) -> str:
    idx = np.asarray(idx).ravel()
    s = ", ".join(str(int(i)) for i in idx[:limit])
    return s + (f", ... ({len(idx)} in all)" if len(idx) > limit else "")


# Node permutations that mirror an element (an inverted element becomes a positive one): tet4 and tet10
# swap vertices 1 and 2 (and tet10's midside nodes with them: edges 01 <-> 02, 13 <-> 23, 12 stays);
# hex8 swaps its bottom and top faces.
MIRROR = {"tet4": np.array([0, 2, 1, 3]), "tet10": np.array([0, 2, 1, 3, 6, 5, 4, 7, 9, 8]),
          "hex8": np.array([4, 5, 6, 7, 0, 1, 2, 3])}


def reorient(nodes: np.ndarray, elements: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Mirror the node order of the elements that are inverted everywhere (negative Jacobian at every check
    point of their kind), so that they are positive.

    nodes (N, 3) [m], elements (E, k) in VTK order; returns (elements (E, k), indices of the flipped
    elements). Elements with Jacobians of both signs (tangled, not merely mirrored) are left as they are:
    :class:`Mesh` refuses them."""
    et = element_type(kind)
    elements = np.asarray(elements).astype(np.int64)
    detJ = np.linalg.det(jacobians(et, np.asarray(nodes, float)[elements], et.check_points))
    flip = np.flatnonzero((detJ < 0).all(axis=1))
    if flip.size:
        elements = elements.copy()
        elements[flip] = elements[flip][:, MIRROR[et.name]]
    return elements, flip


class Mesh:
    """A volumetric mesh of a single element kind.

    nodes: (N, 3) float rest coordinates [m]; elements: (E, k) int node indices in VTK order;
    kind: "tet4" | "hex8" | "tet10". Raises :class:`MeshError` (a ValueError) naming the
    offending entries for non-finite coordinates, out-of-range or repeated indices, a wrong
    node count, and zero-volume or inverted elements.
    """

    def __init__(self, nodes: np.ndarray, elements: np.ndarray, kind: str):
        self.element_type: ElementType = element_type(kind)
        self.kind = self.element_type.name
        try:
            nodes = np.array(nodes, dtype=float)
        except (TypeError, ValueError) as exc:
            raise MeshError(f"nodes must be an (N, 3) array of numbers: {exc}") from None
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise MeshError(f"nodes must have shape (N, 3), got {nodes.shape}")
        bad = np.flatnonzero(~np.isfinite(nodes).all(axis=1))
        if bad.size:
            raise MeshError(f"nodes have NaN or infinite coordinates at node indices {_list_some(bad)}")
        elements = np.asarray(elements)
        k = self.element_type.n_nodes
        if elements.ndim != 2 or elements.shape[1] != k:
            raise MeshError(f"a {kind} mesh needs elements of shape (E, {k}), got {elements.shape}")
        if elements.shape[0] == 0:
            raise MeshError("the mesh has no elements")
        if not np.issubdtype(elements.dtype, np.integer):
            if elements.dtype.kind not in "fb":
                raise MeshError(f"element node indices must be integers, got dtype {elements.dtype}")
            if not np.all(np.isfinite(elements)) or np.any(elements != np.round(elements)):
                raise MeshError("element node indices must be integers")
        elements = elements.astype(np.int64)
        out = np.flatnonzero(((elements < 0) | (elements >= len(nodes))).any(axis=1))
        if out.size:
            raise MeshError(f"elements {_list_some(out)} reference node indices {_list_some(np.unique(elements[out][(elements[out] < 0) | (elements[out] >= len(nodes))]))} outside [0, {len(nodes) - 1}]")
        s = np.sort(elements, axis=1)
        rep = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
        if rep.size:
            raise MeshError(f"elements {_list_some(rep)} repeat a node index")
        self.nodes = nodes
        self.elements = elements
        self._check_orientation()

    def _check_orientation(self) -> None:
        et = self.element_type
        J = jacobians(et, self.nodes[self.elements], et.check_points)
        detJ = np.linalg.det(J)
        scale = np.abs(detJ).max(axis=1, initial=0.0)
        tiny = np.abs(detJ).min(axis=1) <= 1e-12 * max(scale.max(), 1e-300)
        flat = np.flatnonzero(tiny)
        if flat.size:
            raise MeshError(f"elements {_list_some(flat)} have (near) zero volume")
        inv = np.flatnonzero((detJ <= 0).any(axis=1))
        if inv.size:
            raise MeshError(
                f"elements {_list_some(inv)} are inverted (negative Jacobian); "
                f"{self.kind} node order must follow VTK with positive orientation")

    # ------------------------------------------------------------------ properties
    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.elements)

    def __repr__(self) -> str:
        return f"Mesh(kind={self.kind!r}, nodes={self.n_nodes}, elements={self.n_elements})"

    def element_volumes(self) -> np.ndarray:
        """Rest volume of each element (E,) [m^3], by the stiffness quadrature (exact for these elements)."""
        et = self.element_type
        xi, w = et.mass_rule
        detJ = np.linalg.det(jacobians(et, self.nodes[self.elements], xi))
        return detJ @ w

    def volume(self) -> float:
        return float(self.element_volumes().sum())

    def used_nodes(self) -> np.ndarray:
        """Boolean mask (N,) of nodes referenced by at least one element."""
        used = np.zeros(self.n_nodes, dtype=bool)
        used[self.elements.ravel()] = True
        return used

    def boundary_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """(element index, local face index) of every face that belongs to one element only."""
        et = self.element_type
        E, F = self.n_elements, len(et.faces)
        corners = self.elements[:, et.faces[:, : et.n_face_corners]].reshape(E * F, -1)
        key = np.sort(corners, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        once = np.flatnonzero(counts[inverse.ravel()] == 1)
        return once // F, once % F

    def surface_triangles(self) -> np.ndarray:
        """Boundary faces as outward-facing triangles (T, 3) of global node indices.

        Quadratic (tet10) faces are split into 4 triangles, hex faces into 2.
        """
        e, f = self.boundary_faces()
        tris = self.element_type.face_triangles[f]  # (B, t, 3) local indices
        return self.elements[e[:, None, None], tris].reshape(-1, 3)

    def surface_nodes(self) -> np.ndarray:
        """Sorted indices of all nodes on the boundary surface."""
        return np.unique(self.surface_triangles())

    def translated(self, offset) -> "Mesh":
        return Mesh(self.nodes + np.asarray(offset, dtype=float), self.elements, self.kind)

    def write(self, path: str | Path, **point_data: np.ndarray) -> None:
        """Write the mesh (and optional per-node arrays) through meshio; the format follows the suffix (.vtu, .vtk, .msh, ...)."""
        import meshio

        meshio.write(str(path), meshio.Mesh(self.nodes, [(self.element_type.meshio_name, self.elements)],
                                            point_data=point_data or None),
                     file_format="gmsh" if Path(path).suffix.lower() == ".msh" else None)  # meshio's default for .msh is ANSYS
