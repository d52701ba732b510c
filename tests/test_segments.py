"""Edges, closest points between segments and the after-step intersection depth, against brute force and analytic
cases."""
import numpy as np
import pytest

import softbody as sb
from integration.intersection import intersection_depth
from integration.segments import closest_between_segments, surface_edges
from integration.softcontact import SoftSurface


def test_closest_points_between_segments_equal_a_brute_force_search():
    rng = np.random.default_rng(3)
    p0, p1, q0, q1 = (rng.uniform(-1, 1, (200, 3)) for _ in range(4))
    s, t = closest_between_segments(p0, p1, q0, q1)
    got = np.linalg.norm((p0 + s[:, None] * (p1 - p0)) - (q0 + t[:, None] * (q1 - q0)), axis=1)
    grid = np.linspace(0, 1, 401)
    P = p0[:, None] + grid[None, :, None] * (p1 - p0)[:, None]
    Q = q0[:, None] + grid[None, :, None] * (q1 - q0)[:, None]
    brute = np.linalg.norm(P[:, :, None] - Q[:, None], axis=3).min(axis=(1, 2))
    assert np.all(got <= brute + 1e-12)  # never farther than any sampled pair
    assert np.all(brute - got < 5e-3)  # and the grid's spacing finds no nearer one


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_a_closed_surface_has_one_and_a_half_edges_per_triangle_each_bounding_two(kind):
    m = sb.box_mesh((0.1, 0.2, 0.3), (2, 3, 2), kind)
    tris = m.surface_triangles()
    edges, owners = surface_edges(tris)
    assert 2 * len(edges) == 3 * len(tris) and (owners >= 0).all()
    # Euler: V - E + F = 2 for the sphere-like surface
    assert len(np.unique(tris)) - len(edges) + len(tris) == 2


@pytest.fixture(params=["compiled", "numpy"])
def paths(request, monkeypatch):
    """The check after the step both ways: its compiled kernel (integration.kernels.edge_depths) and numpy's."""
    from integration import kernels

    if request.param == "compiled" and not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    monkeypatch.setattr(kernels, "ENABLED", request.param == "compiled")
    return request.param


@pytest.mark.parametrize("depth", [0.0, 0.0005, 0.002, 0.01])
def test_intersection_depth_of_two_offset_cubes(depth, paths):
    a = sb.box_mesh((0.05,) * 3, (2, 2, 2), "tet4", center=(0, 0, 0))
    b = sb.box_mesh((0.05,) * 3, (2, 2, 2), "tet4", center=(0.01, 0.005, 0.05 - depth))
    sa, sb_ = (SoftSurface.of(m.nodes, m.surface_triangles()) for m in (a, b))
    got = intersection_depth(a.nodes, sa.triangles, sa.edges, b.nodes, sb_.triangles, sb_.edges)
    assert got == pytest.approx(depth, abs=1e-12)


def test_intersection_depth_of_crossing_bars_with_no_node_inside_the_other(paths):
    a = sb.box_mesh((0.4, 0.04, 0.04), (1, 1, 1), "tet4", center=(0, 0, 0))
    b = sb.box_mesh((0.04, 0.4, 0.04), (1, 1, 1), "tet4", center=(0, 0, 0.04 - 0.003))
    sa, sb_ = (SoftSurface.of(m.nodes, m.surface_triangles()) for m in (a, b))
    # no node of either lies inside the other: only the edges' stretches show the 3 mm
    got = intersection_depth(a.nodes, sa.triangles, sa.edges, b.nodes, sb_.triangles, sb_.edges)
    assert got == pytest.approx(0.003, rel=1e-9)


def test_compiled_intersection_depth_equals_numpys(monkeypatch):
    """Turned, deformed cubes overlapping at random: the compiled check (kernels.edge_depths) and numpy's give the same
    depth to round-off."""
    from integration import kernels

    if not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    rng = np.random.default_rng(2)
    deep = 0
    for _ in range(30):
        x = []
        for k in range(2):
            m = sb.box_mesh((0.04,) * 3, (2, 2, 2), ("tet4", "tet10")[k])
            R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
            x.append((m.nodes @ R.T + rng.uniform(-0.02, 0.02, 3) * k + 0.001 * rng.standard_normal(m.nodes.shape),
                      SoftSurface.of(m.nodes, m.surface_triangles())))
        (xa, sa), (xb, sb_) = x
        got = {}
        for compiled in (True, False):
            monkeypatch.setattr(kernels, "ENABLED", compiled)
            got[compiled] = intersection_depth(xa, sa.triangles, sa.edges, xb, sb_.triangles, sb_.edges)
        assert got[True] == pytest.approx(got[False], rel=1e-12, abs=1e-15)
        deep += got[False] > 1e-3
    assert deep > 10
