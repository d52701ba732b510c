"""Bad input raises a clear ValueError subclass naming the offending value; odd-but-legal input works."""
from __future__ import annotations


import numpy as np
import pytest

import softbody
from conftest import KINDS, raises_naming

MAT = softbody.LinearElastic(5.0e5, 0.33, 1000.0)

UNIT_HEX = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                     [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=float)


# ---------------------------------------------------------------------------- material


@pytest.mark.parametrize("nu, shown", [(0.5, "0.5"), (0.7, "0.7"), (-1.0, "-1.0"), (-1.5, "-1.5"), (float("nan"), "nan")])
def test_bad_poisson_ratio(nu, shown):
    raises_naming(shown, call=lambda: softbody.LinearElastic(1e5, nu, 1000.0), exc=softbody.InvalidInputError)


@pytest.mark.parametrize("E, shown", [(0.0, "0.0"), (-5.0, "-5.0"), (float("nan"), "nan"), (float("inf"), "inf")])
def test_bad_young_modulus(E, shown):
    msg = raises_naming(shown, call=lambda: softbody.LinearElastic(E, 0.3, 1000.0), exc=softbody.InvalidInputError)
    assert "E" in msg


@pytest.mark.parametrize("rho, shown", [(0.0, "0.0"), (-1000.0, "-1000.0")])
def test_bad_density(rho, shown):
    msg = raises_naming(shown, call=lambda: softbody.LinearElastic(1e5, 0.3, rho), exc=softbody.InvalidInputError)
    assert "density" in msg


def test_valid_extreme_materials():
    softbody.LinearElastic(1e5, 0.4999, 1.0)
    softbody.LinearElastic(1e5, -0.999, 1.0)


# ---------------------------------------------------------------------------- time step and options


def _body(kind="hex8"):
    return softbody.FemBody(softbody.box_mesh((1, 1, 1), (1, 1, 1), kind), MAT)


@pytest.mark.parametrize("dt, shown", [(0.0, "0.0"), (-0.01, "-0.01"), (float("nan"), "nan"), (float("inf"), "inf")])
def test_bad_time_step(dt, shown):
    raises_naming(shown, call=lambda: softbody.Simulation(_body(), dt=dt), exc=softbody.InvalidInputError)


def test_bad_options_are_named():
    mesh = softbody.box_mesh((1, 1, 1), (1, 1, 1), "hex8")
    raises_naming("'diagonal'", call=lambda: softbody.FemBody(mesh, MAT, mass="diagonal"), exc=softbody.InvalidInputError)
    raises_naming("'both'", call=lambda: softbody.FemBody(mesh, MAT, hex_rotation="both"), exc=softbody.InvalidInputError)
    raises_naming("-0.1", call=lambda: softbody.FemBody(mesh, MAT, damping=(-0.1, 0.0)), exc=ValueError)
    raises_naming(call=lambda: softbody.Simulation(_body(), dt=0.01, gravity=(0, 0, float("nan"))), exc=ValueError)


# ---------------------------------------------------------------------------- meshes


def test_unknown_kind():
    raises_naming("'tet5'", call=lambda: softbody.Mesh(UNIT_HEX, [list(range(8))], "tet5"), exc=softbody.InvalidInputError)
    raises_naming("'hex20'", call=lambda: softbody.box_mesh((1, 1, 1), (1, 1, 1), "hex20"), exc=softbody.InvalidInputError)
    raises_naming("'wedge'", call=lambda: softbody.tube_mesh(0.1, 0.05, 1, (4, 1, 1), "wedge"), exc=softbody.InvalidInputError)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_coordinates(bad):
    nodes = np.vstack([UNIT_HEX, [[2.0, 2.0, 2.0]]])
    nodes[5, 1] = bad
    raises_naming("5", call=lambda: softbody.Mesh(nodes, [list(range(8))], "hex8"), exc=softbody.MeshError)


def _tet_box():
    return softbody.box_mesh((1, 1, 2), (1, 1, 2), "tet4")  # 10 tets, 12 nodes


def test_element_index_out_of_range():
    m = _tet_box()
    el = m.elements.copy()
    el[7, 2] = 99
    # names the element and the bad index
    raises_naming("7", "99", call=lambda: softbody.Mesh(m.nodes, el, "tet4"), exc=softbody.MeshError)
    el = m.elements.copy()
    el[6, 0] = -3
    raises_naming("6", "-3", call=lambda: softbody.Mesh(m.nodes, el, "tet4"), exc=softbody.MeshError)


def test_repeated_index_in_element():
    m = _tet_box()
    el = m.elements.copy()
    el[7, 3] = el[7, 1]
    raises_naming("7", call=lambda: softbody.Mesh(m.nodes, el, "tet4"), exc=softbody.MeshError)


@pytest.mark.parametrize("kind, k", [("tet4", 5), ("hex8", 4), ("tet10", 8)])
def test_wrong_node_count_for_kind(kind, k):
    nodes = np.random.default_rng(0).uniform(size=(20, 3))
    raises_naming(kind, str(k), call=lambda: softbody.Mesh(nodes, [list(range(k))], kind), exc=softbody.MeshError)


def test_zero_volume_element():
    m = _tet_box()
    nodes = np.vstack([m.nodes, [[5.0, 0, 0], [6.0, 0, 0], [7.0, 0, 0], [5.0, 1, 0]]])  # 4 coplanar points
    n = len(m.nodes)
    el = np.vstack([m.elements, [[n, n + 1, n + 3, n + 2]]])
    raises_naming("10", call=lambda: softbody.Mesh(nodes, el, "tet4"), exc=softbody.MeshError)
    # a hex collapsed onto its bottom face
    flat = UNIT_HEX.copy()
    flat[4:, 2] = 0.0
    raises_naming("0", call=lambda: softbody.Mesh(flat, [list(range(8))], "hex8"), exc=softbody.MeshError)


@pytest.mark.parametrize("kind", KINDS)
def test_inverted_element_named(kind):
    m = softbody.box_mesh((1, 1, 2), (1, 1, 2), kind)
    el = m.elements.copy()
    bad = 7 if kind != "hex8" else 1
    if kind == "hex8":
        el[bad] = el[bad][[4, 5, 6, 7, 0, 1, 2, 3]]  # top and bottom swapped: mirrored
    else:
        el[bad, [1, 2]] = el[bad, [2, 1]]
        if kind == "tet10":  # keep the mid-edge nodes on their (renamed) edges: 0-1 <-> 0-2, 1-3 <-> 2-3
            el[bad, [4, 6]] = el[bad, [6, 4]]
            el[bad, [8, 9]] = el[bad, [9, 8]]
    msg = raises_naming(str(bad), call=lambda: softbody.Mesh(m.nodes, el, kind), exc=softbody.MeshError)
    assert "invert" in msg


def test_fix_nonexistent_node():
    body = _body()
    raises_naming("1000000", call=lambda: body.fix([0, 1000000]), exc=softbody.InvalidInputError)
    raises_naming("-1", call=lambda: body.fix([-1]), exc=softbody.InvalidInputError)
    raises_naming("8", call=lambda: body.prescribe([8], lambda t: np.zeros((1, 3))), exc=softbody.InvalidInputError)
    assert not body.fixed.any()  # nothing was half-applied


def test_prescribe_wrong_shape():
    body = _body()
    raises_naming("(2, 3)", call=lambda: body.prescribe([0, 1], lambda t: np.zeros(3)), exc=softbody.InvalidInputError)


# ---------------------------------------------------------------------------- degenerate but legal


@pytest.mark.parametrize("kind", KINDS)
def test_single_element_mesh(kind):
    base = softbody.Mesh(UNIT_HEX, [list(range(8))], "hex8") if kind == "hex8" else None
    if kind != "hex8":
        tet = softbody.Mesh(UNIT_HEX[[0, 1, 3, 4]], [[0, 1, 2, 3]], "tet4")
        base = tet if kind == "tet4" else softbody.to_tet10(tet)
    body = softbody.FemBody(base, MAT)
    assert body.mass_matrix().shape == (3 * base.n_nodes,) * 2
    bottom = np.isclose(base.nodes[:, 2], 0.0)
    body.fix(bottom)
    u = softbody.solve_static(body, gravity=(0, 0, -9.81))
    assert np.all(u[bottom] == 0) and np.all(u[~bottom, 2] < 0)
    sim = softbody.Simulation(body, dt=0.01)
    sim.run(0.05)
    assert np.all(np.isfinite(body.positions)) and sim.t == pytest.approx(0.05)
    assert np.all(body.positions[~bottom, 2] < base.nodes[~bottom, 2])


def test_unused_nodes_are_harmless():
    mesh = softbody.box_mesh((1, 1, 1), (1, 1, 1), "tet4")
    nodes = np.vstack([mesh.nodes, [[10.0, 10.0, 10.0], [-3.0, 0.0, 0.0]]])
    m = softbody.Mesh(nodes, mesh.elements, "tet4")
    body = softbody.FemBody(m, MAT, damping=(0.0, 0.0))
    h = 0.01
    sim = softbody.Simulation(body, dt=h, gravity=(0, 0, -9.81))
    for n in range(1, 11):
        sim.step()
    used = np.arange(mesh.n_nodes)
    # the used nodes fall exactly as backward Euler predicts, the unused ones stay put
    np.testing.assert_allclose(body.positions[used, 2], mesh.nodes[:, 2] - 9.81 * h * h * 10 * 11 / 2, atol=1e-10)
    np.testing.assert_array_equal(body.positions[-2:], nodes[-2:])
    assert np.all(np.isfinite(body.velocities))


def test_all_nodes_fixed():
    mesh = softbody.box_mesh((1, 1, 1), (2, 1, 1), "tet10")
    body = softbody.FemBody(mesh, MAT)
    body.fix(np.arange(mesh.n_nodes))
    sim = softbody.Simulation(body, dt=0.01)
    sim.run(0.03)
    np.testing.assert_array_equal(body.positions, mesh.nodes)
    np.testing.assert_array_equal(body.velocities, 0.0)
    assert sim.t == pytest.approx(0.03)


@pytest.mark.parametrize("kind", KINDS)
def test_no_gravity_body_at_rest_stays_at_rest(kind):
    mesh = softbody.box_mesh((1, 0.5, 0.5), (2, 1, 1), kind)
    body = softbody.FemBody(mesh, MAT)
    sim = softbody.Simulation(body, dt=0.01, gravity=(0, 0, 0))
    sim.run(0.1)
    np.testing.assert_allclose(body.positions, mesh.nodes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(body.velocities, 0.0, atol=1e-10)


def test_zero_duration_run_and_bodies_list():
    a, b = _body("tet4"), _body("hex8")
    sim = softbody.Simulation([a, b], dt=0.01)
    sim.run(0.0)
    assert sim.t == 0.0
    sim.run(0.02)
    assert sim.t == pytest.approx(0.02)
    # both bodies fall the same way (backward Euler free fall, default alpha damping aside, equal for both)
    np.testing.assert_allclose(a.positions[:, 2].mean() - a.rest[:, 2].mean(),
                               b.positions[:, 2].mean() - b.rest[:, 2].mean(), rtol=1e-10)


def test_external_forces_are_checked_when_set_and_move_a_free_body_by_newton():
    """sim.external_forces[body] = f (N, 3) [N]: a wrong shape, a non-finite entry or a key that is not a body is an
    InvalidInputError at once (not a numpy error at step time); a uniform force per unit mass on a free body in zero
    gravity gives its momentum exactly F t (Newton's second law; the elastic forces sum to zero; undamped)."""
    import softbody as sb

    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10"), sb.LinearElastic(1e6, 0.3, 1000),
                      damping=(0.0, 0.0))  # Rayleigh's mass term would damp the free motion too
    sim = sb.Simulation(body, 0.01, gravity=(0, 0, 0))
    for bad, match in ((np.ones((3, 3)), r"\(117, 3\) array"), (np.full((body.n_nodes, 3), np.nan), "non-finite")):
        with pytest.raises(sb.InvalidInputError, match=match):
            sim.external_forces[body] = bad
    with pytest.raises(sb.InvalidInputError, match="keyed by the body"):
        sim.external_forces[id(body)] = np.zeros((body.n_nodes, 3))
    f = body.node_mass[:, None] * np.array([2.0, 0.0, 0.0])  # 2 m/s^2 on every node
    sim.external_forces[body] = f
    assert body in sim.external_forces and np.array_equal(sim.external_forces[body], f)
    for _ in range(10):
        sim.step()
    momentum = (body.node_mass[:, None] * body.velocities).sum(axis=0)
    assert momentum == pytest.approx(f.sum(axis=0) * 0.1, rel=1e-9, abs=1e-12)
    del sim.external_forces[body]
    assert len(sim.external_forces) == 0
    with pytest.raises(sb.InvalidInputError, match=r"\(117, 3\) array"):  # a whole mapping is checked too
        sim.external_forces = {body: np.ones((3, 3))}
    sim.external_forces = {body: f}
    assert np.array_equal(sim.external_forces[body], f)
