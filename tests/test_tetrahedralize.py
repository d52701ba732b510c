"""softbody.tetrahedralize: closed triangle surfaces filled with tets through gmsh."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import softbody
from softbody.elements import TET10_EDGES, jacobians

pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")

R = 0.1
SPHERE = 4 / 3 * np.pi * R**3


@pytest.fixture(scope="module")
def ico():
    return trimesh.creation.icosphere(3, radius=R)  # 642 vertices, 0.86% short of the sphere's volume


def no_inverted(mesh: softbody.Mesh) -> bool:
    et = mesh.element_type
    return bool((np.linalg.det(jacobians(et, mesh.nodes[mesh.elements], et.check_points)) > 0).all())


@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_an_icosphere_becomes_a_ball_within_3_percent_of_the_sphere(ico, kind):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean sphere needs no repair and no pulled-back midside node
        m = softbody.tetrahedralize(ico, 0.02, kind)
    assert m.kind == kind and no_inverted(m)
    assert m.volume() == pytest.approx(SPHERE, rel=0.03)
    surf = m.surface_nodes()
    r = np.linalg.norm(m.nodes[surf], axis=1)
    assert r.max() <= R * (1 + 1e-9) and r.min() > 0.98 * R  # on the icosphere, inscribed in the sphere
    edges = np.linalg.norm(np.diff(m.nodes[m.elements[:, :4]][:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]]
                                   .reshape(-1, 2, 3), axis=1), axis=1)
    assert 0.5 * 0.02 < np.median(edges) < 1.5 * 0.02  # the target edge length
    if kind == "tet10":  # surface midside nodes projected onto the input surface: its volume, not the chords'
        assert m.volume() == pytest.approx(ico.volume, rel=2e-3)
        mids = m.elements[:, 4:]
        straight = np.isclose(m.nodes[mids], m.nodes[m.elements[:, TET10_EDGES]].mean(axis=2), rtol=0, atol=1e-12)
        assert not straight.all()
        inner = ~np.isin(mids, surf)
        assert straight.all(axis=2)[inner].all()  # interior midside nodes at their edges' midpoints


def test_inputs_arrays_and_files_give_the_same_mesh(ico, tmp_path):
    a = softbody.tetrahedralize((ico.vertices, ico.faces), 0.04)
    for suffix in (".stl", ".obj", ".ply"):
        path = tmp_path / f"ico{suffix}"
        ico.export(path)
        b = softbody.tetrahedralize(path, 0.04)
        # (STL stores float32 and its own vertex order: gmsh's mesh may differ in a few elements)
        assert b.n_elements == pytest.approx(a.n_elements, rel=0.1) and b.volume() == pytest.approx(a.volume(), rel=0.01), suffix
    # inward winding is turned outward
    c = softbody.tetrahedralize((ico.vertices, ico.faces[:, ::-1]), 0.04)
    assert c.volume() == pytest.approx(a.volume(), rel=1e-6)


def test_remesh_false_keeps_the_input_triangles(ico):
    m = softbody.tetrahedralize(ico, 0.05, remesh=False)
    assert m.volume() == pytest.approx(ico.volume, rel=1e-12)
    assert len(m.surface_triangles()) == len(ico.faces)


def test_a_small_hole_is_filled_with_a_warning_a_large_one_is_an_error():
    ico = trimesh.creation.icosphere(2, radius=R)
    with pytest.warns(UserWarning, match="had holes: filled with 1 triangles"):
        m = softbody.tetrahedralize((ico.vertices, ico.faces[1:]), 0.04)
    assert no_inverted(m) and m.volume() == pytest.approx(ico.volume, rel=0.05)
    with pytest.raises(softbody.MeshError, match="not closed: 20 edges belong to one triangle only"):
        softbody.tetrahedralize((ico.vertices, ico.faces[40:]), 0.04)
    with pytest.raises(softbody.MeshError, match="not closed"):
        softbody.tetrahedralize((ico.vertices, ico.faces[1:]), 0.04, repair=False)


def test_a_self_intersecting_surface_is_an_error_naming_it():
    ico = trimesh.creation.icosphere(2, radius=R)
    v = ico.vertices.copy()
    v[np.argmax(v[:, 2])] = (0.0, 0.0, -1.5 * R)  # the top vertex pushed out through the bottom
    with pytest.raises(softbody.MeshError, match="intersects itself"):
        softbody.tetrahedralize((v, ico.faces), 0.04)


def test_several_shells_and_bad_arguments_are_refused():
    ico = trimesh.creation.icosphere(1, radius=R)
    two = trimesh.util.concatenate([ico, ico.copy().apply_translation([0.5, 0, 0])])
    with pytest.raises(softbody.MeshError, match="2 separate shells"):
        softbody.tetrahedralize(two, 0.05)
    for size in (0, -1.0, np.nan, "1", True):
        with pytest.raises(softbody.InvalidInputError, match="size"):
            softbody.tetrahedralize(ico, size)
    with pytest.raises(softbody.InvalidInputError, match="larger than the surface"):
        softbody.tetrahedralize(ico, 1.0)
    with pytest.raises(softbody.InvalidInputError, match="'tet4' or 'tet10'"):
        softbody.tetrahedralize(ico, 0.05, "hex8")
    with pytest.raises(softbody.InvalidInputError, match="does not exist"):
        softbody.tetrahedralize("nope.stl", 0.05)
    with pytest.raises(softbody.InvalidInputError, match="trimesh.Trimesh"):
        softbody.tetrahedralize(42, 0.05)
    with pytest.raises(softbody.InvalidInputError, match="outside"):
        softbody.tetrahedralize((ico.vertices, ico.faces + 1), 0.05)
