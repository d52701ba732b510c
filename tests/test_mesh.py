"""Mesh builders, surfaces, tet10 refinement and file round trips."""
from __future__ import annotations

import numpy as np
import pytest

import softbody
from conftest import TET10_EDGES_SPEC, box_boundary_mask

# ---------------------------------------------------------------------------- counts


def expected_counts(kind: str, cells) -> tuple[int, int]:
    """(elements, nodes) of the structured box by the formulas of docs/method.md section 5."""
    nx, ny, nz = cells
    if kind == "hex8":
        return nx * ny * nz, (nx + 1) * (ny + 1) * (nz + 1)
    if kind == "tet4":
        return 5 * nx * ny * nz, (nx + 1) * (ny + 1) * (nz + 1)
    return 5 * nx * ny * nz, (2 * nx + 1) * (2 * ny + 1) * (2 * nz + 1) - nx * ny * nz


@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 3, 1), (3, 2, 4)])
def test_box_counts_match_formulas(kind, cells):
    m = softbody.box_mesh((1.0, 1.0, 0.25), cells, kind)
    assert (m.n_elements, m.n_nodes) == expected_counts(kind, cells)
    assert m.elements.shape[1] == {"tet4": 4, "hex8": 8, "tet10": 10}[kind]
    assert m.kind == kind


@pytest.mark.parametrize("kind, cells, n_el, n_nodes", [
    ("tet4", (24, 24, 6), 17280, 4375),
    ("hex8", (20, 20, 5), 2000, 2646),
    ("tet10", (9, 9, 2), 810, 1643),
])
def test_paper_counts(kind, cells, n_el, n_nodes):
    """The element and node counts reported in the paper for the finest sheet meshes."""
    m = softbody.box_mesh((1.0, 1.0, 0.25), cells, kind, center=(0, 0, 0.475))
    assert (m.n_elements, m.n_nodes) == (n_el, n_nodes)
    assert (n_el, n_nodes) == expected_counts(kind, cells)


def test_box_center_and_extent(kind):
    size, center = np.array([1.0, 0.5, 0.25]), np.array([0.1, -2.0, 0.475])
    m = softbody.box_mesh(size, (2, 2, 1), kind, center=center)
    np.testing.assert_allclose(m.nodes.min(axis=0), center - size / 2, atol=1e-15)
    np.testing.assert_allclose(m.nodes.max(axis=0), center + size / 2, atol=1e-15)


# ---------------------------------------------------------------------------- volumes


@pytest.mark.parametrize("cells", [(1, 1, 1), (3, 2, 2)])
def test_box_volume_exact(kind, cells):
    size = (1.0, 0.7, 0.3)
    m = softbody.box_mesh(size, cells, kind)
    assert m.volume() == pytest.approx(np.prod(size), rel=1e-13)
    assert m.element_volumes().min() > 0
    # the 5-tet cut: 4 corner tets of 1/6 of the cell and the inner tet of 1/3
    if kind != "hex8":
        cell = np.prod(size) / np.prod(cells)
        v = np.sort(m.element_volumes().reshape(-1, 5), axis=1)
        np.testing.assert_allclose(v[:, :4], cell / 6, rtol=1e-12)
        np.testing.assert_allclose(v[:, 4], cell / 3, rtol=1e-12)


def polygon_tube_volume(r_o, r_i, length, n_theta):
    """Volume of a tube whose cross-section is the ring between two regular n_theta-gons."""
    return 0.5 * n_theta * np.sin(2 * np.pi / n_theta) * (r_o**2 - r_i**2) * length


def test_tube_geometry(kind):
    r_o, r_i, L, cells = 0.1, 0.06, 1.0, (8, 2, 3)
    m = softbody.tube_mesh(r_o, r_i, L, cells, kind)
    assert m.volume() == pytest.approx(polygon_tube_volume(r_o, r_i, L, cells[0]), rel=1e-12)
    assert m.nodes[:, 2].min() == pytest.approx(-L) and m.nodes[:, 2].max() == pytest.approx(0.0)
    vertices_ids = np.unique(m.elements[:, :4 if kind != "hex8" else 8])
    r = np.hypot(m.nodes[vertices_ids, 0], m.nodes[vertices_ids, 1])
    assert r.min() == pytest.approx(r_i) and r.max() == pytest.approx(r_o)
    # straight-sided quadratic tets: mid-edge nodes of chords lie inside the circle (cos(pi/n_theta) r)
    r_all = np.hypot(m.nodes[:, 0], m.nodes[:, 1])
    assert r_all.min() == pytest.approx(r_i * (np.cos(np.pi / cells[0]) if kind == "tet10" else 1.0), rel=1e-12)
    # the +x outer node of the bottom ring exists (the hanging-tube monitor of docs/method.md)
    assert np.any(np.all(np.isclose(m.nodes, [r_o, 0, -L], atol=1e-12), axis=1))
    # node count of the structured tube: the theta direction closes on itself
    nt, nr, nz = cells
    vertices = nt * (nr + 1) * (nz + 1)
    if kind == "tet10":
        edges = m.n_nodes - vertices
        assert m.n_nodes == len(np.unique(np.round(m.nodes, 12), axis=0))
        assert edges > 0
    else:
        assert m.n_nodes == vertices
    assert m.n_elements == (1 if kind == "hex8" else 5) * nt * nr * nz


# ---------------------------------------------------------------------------- faces and surfaces


def test_tet4_faces_conforming():
    """Every triangular face is shared by exactly two tets, except faces on the box boundary (exactly one)."""
    size = np.array([1.0, 0.8, 0.6])
    m = softbody.box_mesh(size, (3, 4, 2), "tet4")
    faces = np.sort(m.elements[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(counts.tolist()) <= {1, 2}
    single = uniq[counts == 1]
    # a face used once must lie in one of the six boundary planes (all three corners on it)
    P = m.nodes[single]  # (F, 3 corners, 3)
    on_plane = np.zeros(len(single), dtype=bool)
    for d in range(3):
        for s in (-1, 1):
            on_plane |= np.all(np.isclose(P[:, :, d], s * size[d] / 2), axis=1)
    assert on_plane.all(), f"{(~on_plane).sum()} interior faces have no neighbour"
    # the boundary is covered by 2 triangles per boundary cell face
    nx, ny, nz = 3, 4, 2
    assert len(single) == 2 * 2 * (nx * ny + ny * nz + nx * nz)


def _triangle_geometry(nodes, tris):
    a, b, c = nodes[tris[:, 0]], nodes[tris[:, 1]], nodes[tris[:, 2]]
    n2 = np.cross(b - a, c - a)  # 2 * area * unit normal
    return (a + b + c) / 3, n2


def surface_area(nodes, tris):
    _, n2 = _triangle_geometry(nodes, tris)
    return 0.5 * np.linalg.norm(n2, axis=1).sum()


def divergence_volume(nodes, tris):
    """Volume enclosed by a closed, outward triangulated surface: sum(centroid . n * area) / 3."""
    cen, n2 = _triangle_geometry(nodes, tris)
    return np.einsum("ij,ij->", cen, n2) / 6.0


@pytest.mark.parametrize("cells", [(1, 1, 1), (3, 2, 2)])
def test_box_surface_area_and_orientation(kind, cells):
    size = np.array([1.0, 0.7, 0.3])
    m = softbody.box_mesh(size, cells, kind, center=(0.3, -0.2, 1.0))
    tris = m.surface_triangles()
    assert tris.ndim == 2 and tris.shape[1] == 3
    box_area = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    assert surface_area(m.nodes, tris) == pytest.approx(box_area, rel=1e-12)
    assert divergence_volume(m.nodes, tris) == pytest.approx(np.prod(size), rel=1e-12)
    # every surface triangle's normal points away from the box centre, and all surface nodes lie on the boundary
    cen, n2 = _triangle_geometry(m.nodes, tris)
    assert np.all(np.einsum("ij,ij->i", cen - np.array([0.3, -0.2, 1.0]), n2) > 0)
    surf = np.unique(tris)
    lo, hi = np.array([0.3, -0.2, 1.0]) - size / 2, np.array([0.3, -0.2, 1.0]) + size / 2
    assert np.array_equal(np.sort(surf), np.flatnonzero(box_boundary_mask(m.nodes, lo, hi)))
    # triangles per cell face: tets 2 (tet4) / 8 (tet10, each split in 4), hex 2 per quad
    n_faces = 2 * (cells[0] * cells[1] + cells[1] * cells[2] + cells[0] * cells[2])
    assert len(tris) == n_faces * {"tet4": 2, "hex8": 2, "tet10": 8}[kind]


def test_tube_surface_closed_and_outward(kind):
    r_o, r_i, L, cells = 0.1, 0.06, 1.0, (8, 2, 3)
    m = softbody.tube_mesh(r_o, r_i, L, cells, kind)
    tris = m.surface_triangles()
    vol = polygon_tube_volume(r_o, r_i, L, cells[0])
    assert divergence_volume(m.nodes, tris) == pytest.approx(vol, rel=1e-12)
    # closed: every triangle edge appears exactly twice, once in each direction
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    assert len(fwd) == len(e)
    assert all((b, a) in fwd for a, b in fwd)
    # lateral area of the two polygonal prisms plus the two annular caps
    side = cells[0] * 2 * np.sin(np.pi / cells[0]) * (r_o + r_i) * L
    caps = 2 * 0.5 * cells[0] * np.sin(2 * np.pi / cells[0]) * (r_o**2 - r_i**2)
    assert surface_area(m.nodes, tris) == pytest.approx(side + caps, rel=1e-12)


def test_surface_triangles_of_a_distorted_single_tet():
    X = np.array([[0, 0, 0], [1, 0, 0], [0.2, 1, 0], [0.1, 0.3, 0.8]], float)
    m = softbody.Mesh(X, [[0, 1, 2, 3]], "tet4")
    tris = m.surface_triangles()
    assert len(tris) == 4
    vol = np.linalg.det(np.column_stack([X[1] - X[0], X[2] - X[0], X[3] - X[0]])) / 6
    assert divergence_volume(m.nodes, tris) == pytest.approx(vol, rel=1e-13)


# ---------------------------------------------------------------------------- tet10 refinement


def test_to_tet10_shares_midpoints():
    base = softbody.box_mesh((1.0, 0.8, 0.6), (2, 3, 2), "tet4")
    m = softbody.to_tet10(base)
    assert m.kind == "tet10" and m.n_elements == base.n_elements
    # vertices are kept, in order
    np.testing.assert_array_equal(m.nodes[: base.n_nodes], base.nodes)
    np.testing.assert_array_equal(m.elements[:, :4], base.elements)
    # one new node per unique edge of the tet4 mesh
    edges = np.sort(base.elements[:, TET10_EDGES_SPEC].reshape(-1, 2), axis=1)
    n_edges = len(np.unique(edges, axis=0))
    assert m.n_nodes == base.n_nodes + n_edges
    # no two nodes coincide (shared edges share their mid node) and every node is used
    assert len(np.unique(m.nodes, axis=0)) == m.n_nodes
    assert m.used_nodes().all()
    # mid-edge nodes sit exactly at the midpoints of the edge order of docs/method.md
    for n, (i, j) in enumerate(TET10_EDGES_SPEC):
        mid = 0.5 * (m.nodes[m.elements[:, i]] + m.nodes[m.elements[:, j]])
        np.testing.assert_array_equal(m.nodes[m.elements[:, 4 + n]], mid)
    # the same edge in two elements maps to the same node id
    key = {}
    for el in m.elements:
        for n, (i, j) in enumerate(TET10_EDGES_SPEC):
            e = tuple(sorted((el[i], el[j])))
            assert key.setdefault(e, el[4 + n]) == el[4 + n]


def test_to_tet10_equals_box_tet10():
    a = softbody.to_tet10(softbody.box_mesh((1, 1, 1), (2, 2, 2), "tet4"))
    b = softbody.box_mesh((1, 1, 1), (2, 2, 2), "tet10")
    np.testing.assert_array_equal(a.nodes, b.nodes)
    np.testing.assert_array_equal(a.elements, b.elements)


def test_to_tet10_rejects_other_kinds():
    with pytest.raises(ValueError, match="tet4"):
        softbody.to_tet10(softbody.box_mesh((1, 1, 1), (1, 1, 1), "hex8"))


# ---------------------------------------------------------------------------- files


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_write_read_round_trip(kind, suffix, tmp_path):
    rng = np.random.default_rng(4)
    m = softbody.box_mesh((1.0, 0.8, 0.6), (2, 2, 1), kind)
    # non-representable coordinates, to catch precision loss in text formats
    nodes = m.nodes + 1e-3 * rng.standard_normal(m.nodes.shape) * ~box_boundary_mask(m.nodes, -0.5, 0.5)[:, None]
    m = softbody.Mesh(nodes, m.elements, kind)
    path = tmp_path / f"mesh{suffix}"
    m.write(path)
    if suffix == ".msh":  # Gmsh, not the ANSYS format meshio also maps .msh to
        assert path.read_bytes().startswith(b"$MeshFormat")
    r = softbody.read_mesh(path)
    assert r.kind == kind
    np.testing.assert_array_equal(r.elements, m.elements)
    np.testing.assert_array_equal(r.nodes, m.nodes)
    assert r.volume() == pytest.approx(m.volume(), rel=1e-14)


def test_read_tube_round_trip(tmp_path):
    m = softbody.tube_mesh(0.1, 0.06, 1.0, (8, 1, 2), "tet10")
    m.write(tmp_path / "tube.vtu")
    r = softbody.read_mesh(tmp_path / "tube.vtu")
    np.testing.assert_array_equal(r.elements, m.elements)
    np.testing.assert_array_equal(r.nodes, m.nodes)


def test_read_missing_file(tmp_path):
    with pytest.raises(ValueError, match="nope.vtu"):
        softbody.read_mesh(tmp_path / "nope.vtu")


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_grid_mesh_size_counts_without_building(kind):
    """grid_mesh_size (the size guard's input) gives the node and element counts of box_mesh and tube_mesh."""
    from softbody.meshing import grid_mesh_size

    for cells in [(1, 1, 1), (2, 3, 1), (4, 4, 2), (5, 2, 3)]:
        m = softbody.box_mesh((1, 1, 1), cells, kind)
        assert grid_mesh_size(cells, kind) == (m.n_nodes, m.n_elements), cells
    for cells in [(4, 1, 1), (8, 2, 3), (6, 1, 5)]:
        m = softbody.tube_mesh(0.1, 0.06, 1.0, cells, kind)
        assert grid_mesh_size(cells, kind, periodic_first=True) == (m.n_nodes, m.n_elements), cells


# ---------------------------------------------------------------------------- ball, re-orientation
def test_ball_mesh_tet10_has_its_surface_midside_nodes_on_the_sphere():
    r, c = 0.1, np.array([0.3, -0.2, 1.0])
    m = softbody.ball_mesh(r, 3, "tet10", center=c)
    surf = m.surface_nodes()
    np.testing.assert_allclose(np.linalg.norm(m.nodes[surf] - c, axis=1), r, rtol=1e-12)
    assert m.volume() == pytest.approx(4 / 3 * np.pi * r**3, rel=5e-3)
    assert abs(softbody.ball_mesh(r, 3, "tet4").volume() / (4 / 3 * np.pi * r**3) - 1) > 0.05  # flat faces


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_read_mesh_reorients_mirrored_elements_with_a_warning_and_strict_refuses(kind, suffix, tmp_path):
    import meshio

    from softbody.mesh import MIRROR

    m = softbody.box_mesh((1.0, 0.8, 0.6), (2, 2, 1), kind)
    bad = m.elements.copy()
    flip = np.arange(0, m.n_elements, 3)
    bad[flip] = bad[flip][:, MIRROR[kind]]
    path = tmp_path / f"mirrored{suffix}"
    meshio.write(str(path), meshio.Mesh(m.nodes, [(m.element_type.meshio_name, bad)]),
                 file_format="gmsh" if suffix == ".msh" else None)
    with pytest.warns(UserWarning, match=f"re-oriented {len(flip)} of {m.n_elements} inverted {kind}"):
        r = softbody.read_mesh(path)
    assert r.volume() == pytest.approx(m.volume(), rel=1e-12)
    assert (r.element_volumes() > 0).all()
    # the same element, its nodes in an order that is positive: the same set of nodes per element
    np.testing.assert_array_equal(np.sort(r.elements, axis=1), np.sort(m.elements, axis=1))
    with pytest.raises(softbody.MeshError, match="inverted"):
        softbody.read_mesh(path, strict=True)


def test_read_mesh_still_refuses_tangled_elements(tmp_path):
    import meshio

    m = softbody.box_mesh((1.0, 1.0, 1.0), (1, 1, 1), "tet10")
    nodes = m.nodes.copy()
    e0 = m.elements[0]
    nodes[e0[4]] = nodes[e0[0]] + 3.0 * (nodes[e0[1]] - nodes[e0[0]])  # a midside node far past its edge's end
    path = tmp_path / "tangled.vtu"
    meshio.write(str(path), meshio.Mesh(nodes, [("tetra10", m.elements)]))
    with pytest.raises(softbody.MeshError, match="inverted|zero volume"):
        softbody.read_mesh(path)
