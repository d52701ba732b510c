"""Numerical stability at the extremes, and no silent failure (issue 5).

A CI-sized subset of ``benchmarks/stability_sweep.py`` (whose case functions these tests call; the
full sweep and its published table are ``python benchmarks/stability_sweep.py`` -> docs/stability.md):
the material / time-step matrix on the cantilever and a free cube, a fast spin, element inversion,
a 20 m/s impact, a long swinging beam, divergence detection and degenerate-but-legal input.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import softbody as sb
from conftest import KINDS

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stability_sweep as sw  # noqa: E402

STRICT = 1.0 + 1e-6  # backward Euler is dissipative: energy <= initial energy + work of gravity

# (nu, E [Pa], dt [s]): every nu, E from 1e2 to 1e9, dt from 1e-4 to 0.1, each at least once.
CANTILEVER_CASES = [(0.0, 1e2, 0.1), (0.3, 1e5, 1e-3), (0.45, 1e7, 1e-2), (0.49, 1e9, 0.1),
                    (0.499, 1e9, 1e-4), (0.499, 1e2, 1e-3)]
# The free cube spins at 1 rev/s: at dt = 0.1 (0.63 rad per step) the method no longer holds (see
# test_rotation_per_step_limit_is_detected), so the matrix stops at dt = 1e-2 there.
CUBE_CASES = [(0.0, 1e2, 1e-2), (0.3, 1e5, 1e-3), (0.45, 1e7, 1e-2), (0.49, 1e9, 1e-2),
              (0.499, 1e9, 1e-4), (0.499, 1e2, 1e-3)]


def _id(case):
    nu, E, dt = case
    return f"nu{nu}-E{E:.0e}-dt{dt:g}"


# ---------------------------------------------------------------------------- the matrix


@pytest.mark.parametrize("case", CANTILEVER_CASES, ids=_id)
@pytest.mark.parametrize("kind", KINDS)
def test_cantilever_matrix_is_stable(kind, case):
    nu, E, dt = case
    r = sw.cantilever(kind, nu, E, dt, steps=30)
    assert r.stable, r.error
    assert r.steps == 30
    assert 0.0 < r.energy_ratio <= STRICT, r.energy_ratio
    # it moved (the energy check is not vacuous) and stayed finite
    assert r.extra["tip_peak"] > 0.0
    if E >= 1e7:  # small strain: no element comes near inversion
        assert r.min_volume > 0.9, r.min_volume


@pytest.mark.parametrize("case", CUBE_CASES, ids=_id)
@pytest.mark.parametrize("kind", KINDS)
def test_free_cube_matrix_is_stable(kind, case):
    nu, E, dt = case
    r = sw.free_cube(kind, nu, E, dt, steps=30)
    assert r.stable, r.error
    # a cube so soft that the spin flattens it (E = 1e2: shape change 0.8-0.9) gains 2-3e-4 of its energy in 30 steps
    # from the warped step's linearised rotations, with no mass damping as with mass damping that spares the spin
    # (the default); classic Rayleigh damping's toll on the spin (0.1% a step) used to hide it (docs/method.md 3)
    assert r.energy_ratio <= (STRICT if E >= 1e5 else 1.0 + 1e-3), r.energy_ratio
    if E >= 1e5:  # stiff enough to hold together against the spin: stays near its (rest) shape
        assert r.extra["shape_change"] < 0.1, r.extra
        assert r.min_volume > 0.9


def _free_dofs(body):
    free = np.repeat(~body.supported(), 3)
    K = body.stiffness_matrix().toarray()[np.ix_(free, free)]
    M = body.mass_matrix().toarray()[np.ix_(free, free)]
    return K, M


@pytest.mark.parametrize("kind", KINDS)
def test_cantilever_accuracy_period_and_static_limit(kind):
    """Accuracy where the method should be accurate (small strain, E = 1e8 Pa):
    - with dt = T1 / 200 and no damping the tip reaches its first lowest point after T1 / 2, T1 the first
      natural period from the generalized eigenproblem K phi = w^2 M phi of the same mesh;
    - with dt = 0.1 s (6x the period) backward Euler damps the vibration within a few steps and the beam
      sits at the static solution K u = f."""
    E, nu = 1e8, 0.3
    body = sw.beam_body(kind, E, nu, damping=(0.0, 0.0))
    body.fix(np.isclose(body.rest[:, 0], 0.0))
    K, M = _free_dofs(body)
    w1 = math.sqrt(scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[0, 0])[0])
    T1 = 2 * math.pi / w1
    dt = T1 / 200
    tip = sw.tip_nodes(body)
    sim = sb.Simulation(body, dt, gravity=sw.G)
    t_low = None
    prev_v = 0.0
    for _ in range(150):
        sim.step()
        v = float(body.velocities[tip, 2].mean())
        if prev_v < 0.0 <= v:
            t_low = sim.t - dt / 2
            break
        prev_v = v
    assert t_low is not None
    assert t_low == pytest.approx(T1 / 2, rel=0.03), (t_low, T1 / 2)

    u_static = sb.solve_static(body, gravity=sw.G)
    r = sw.cantilever(kind, nu, E, 0.1, steps=30)
    d_static = float(-u_static[tip, 2].mean())
    assert r.extra["tip_end"] == pytest.approx(d_static, rel=0.01)


# ---------------------------------------------------------------------------- large rotations


@pytest.mark.parametrize("kind", KINDS)
def test_fast_spin_keeps_shape(kind):
    """A cube spinning at 10 rev/s about an oblique axis (no gravity, no damping, warping on), dt = 1 ms:
    it keeps its shape, the strain does not grow, and it keeps spinning."""
    r = sw.spin(kind, rev_per_s=10.0, E=5e6, dt=1e-3, duration=0.2, cells=(1, 1, 1) if kind == "tet10" else (2, 2, 2))
    ex = r.extra
    assert r.error == "" and r.steps == 200
    assert r.energy_ratio <= 1.01, r.energy_ratio  # the (omega h)^2 excess of the linearised rotation only
    assert ex["shape_first"] < 0.01 and ex["shape_second"] < 0.01, ex
    assert ex["strain_second"] <= 1.05 * ex["strain_first"], ex  # no growth
    assert ex["strain_first"] < 0.02, ex  # spurious strain energy below 2 % of the kinetic energy
    assert 0.97 < r.min_volume and ex["max_volume"] < 1.03, (r.min_volume, ex)
    assert 0.98 < ex["ke_ratio"] <= 1.0, ex


# ---------------------------------------------------------------------------- inversion


@pytest.mark.parametrize("kind", KINDS)
def test_crushed_flat_and_released_recovers(kind):
    """Top nodes driven down by a plate to 5 % of the height (bottom fixed), held, released: the cube springs
    back to its rest shape. tet10's mid-edge nodes bulge and invert elements on the way (volume < 0)."""
    r = sw.crush(kind, "plate", release=0.5)
    ex = r.extra
    assert r.stable, r.error
    assert ex["height_crushed"] == pytest.approx(0.05, abs=1e-9)  # plate gap / height
    assert r.min_volume < 0.1, r.min_volume  # near-zero or negative element volumes
    assert ex["shape_at_release"] > 0.4
    assert ex["shape_end"] < 1e-3, ex
    assert ex["volume_end"] == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("kind", KINDS)
def test_mirrored_inverted_cube_recovers(kind):
    """Every element inverted (z -> -0.05 z): a reflection would call this force free; det R = +1 rotations
    give a restoring force, and the released cube returns to its rest shape."""
    r = sw.crush(kind, "mirror", release=0.5)
    ex = r.extra
    assert r.stable, r.error
    assert r.min_volume == pytest.approx(-0.05, rel=1e-6)
    assert ex["restoring"] == 1.0
    assert ex["shape_end"] < 1e-3, ex
    assert ex["volume_end"] == pytest.approx(1.0, abs=1e-3)
    assert r.energy_ratio <= STRICT


# ---------------------------------------------------------------------------- impact


@pytest.mark.parametrize("kind", KINDS)
def test_ball_at_20_m_per_s_bounces_without_tunnelling(kind):
    r = sw.impact(kind, speed=20.0, E=1e6, dt=1e-3, duration=0.06)
    ex = r.extra
    assert r.stable, r.error
    assert ex["contact_steps"] > 0
    assert ex["max_penetration"] < 1e-3, ex  # never through the plane
    assert ex["lowest"] > -1e-3
    assert ex["end_height"] > 0.0 and ex["end_velocity"] > 2.0, ex  # bounced back up
    assert r.energy_ratio <= STRICT
    assert r.min_volume > 0.2  # squashed, not inverted


# ---------------------------------------------------------------------------- long run


@pytest.mark.parametrize("kind", KINDS)
def test_swinging_beam_energy_bounded_no_shape_drift(kind):
    """A beam hinged at one end swings under gravity (10 s here, 60 s in the sweep): energy stays within the
    budget (up to the (omega h)^2 excess of the linearised rotation), the shape does not drift."""
    r = sw.swing(kind, duration=10.0, dt=0.01)
    ex = r.extra
    assert r.stable, r.error
    assert r.energy_ratio <= 1.01, r.energy_ratio
    assert ex["max_angle"] > 150.0  # it really swings through large rotations
    assert ex["shape_max"] < 3e-3 and ex["shape_end"] < 3e-3, ex
    assert r.min_volume > 0.99


# ---------------------------------------------------------------------------- divergence is never silent


def _state(body):
    return body.positions.copy(), body.velocities.copy()


def test_infinite_force_raises_diverged_and_keeps_state():
    body = sw.beam_body("tet10", 5e7, 0.3)
    body.fix(np.isclose(body.rest[:, 0], 0.0))
    sim = sb.Simulation(body, 0.01, gravity=sw.G)
    sim.run(0.03)
    x, v = _state(body)
    node = int(sw.tip_nodes(body)[0])
    force = np.zeros_like(body.positions)
    force[node, 2] = np.inf
    with pytest.raises(sb.InvalidInputError, match="non-finite"):  # refused when set, naming the node
        sim.external_forces[body] = force
    # the step's own guard, for whatever else makes a state non-finite: the load slipped past the check
    sim.external_forces._loads[id(body)] = (body, force)
    with pytest.raises(sb.SimulationDiverged) as info:
        sim.step()
    err = info.value
    assert err.step == 4 and err.time == pytest.approx(0.04)
    assert err.element is not None and 0 <= err.element < body.mesh.n_elements
    msg = str(err)
    assert "step 4" in msg and "0.04" in msg and f"element {err.element}" in msg
    # nothing of the failed step leaked into the state
    np.testing.assert_array_equal(body.positions, x)
    np.testing.assert_array_equal(body.velocities, v)
    assert sim.steps == 3 and sim.t == pytest.approx(0.03)
    # and the simulation can go on once the cause is removed
    del sim.external_forces[body]
    sim.step()
    assert sim.steps == 4 and np.isfinite(body.positions).all()


def test_rotation_per_step_limit_is_detected():
    """A case that truly blows up: the stiff, nearly incompressible free cube spinning at 1 rev/s with
    dt = 0.1 s (0.63 rad per step). Its energy grows by orders of magnitude (the stretch of the linearised
    rotation meets the bulk modulus); with an energy bound the step that crosses it raises, naming step,
    time and worst element, and the state before that step is kept."""
    body = sw.cube_body("hex8", 1e9, 0.499)
    body.positions = body.rest * np.array([1.10, 0.95, 1.0])
    body.velocities = np.cross(2 * np.pi * sw.AXIS, body.positions)
    e0 = body.kinetic_energy() + body.elastic_energy()
    sim = sb.Simulation(body, 0.1, gravity=(0, 0, 0), max_energy=10 * e0)
    states = []
    with pytest.raises(sb.SimulationDiverged) as info:
        for _ in range(40):
            states.append(_state(body))
            sim.step()
    err = info.value
    assert err.step == len(states) and err.time == pytest.approx(0.1 * err.step)
    assert 0 <= err.element < body.mesh.n_elements
    assert "exceeds the bound" in str(err) and f"step {err.step}" in str(err)
    x, v = states[-1]
    np.testing.assert_array_equal(body.positions, x)
    np.testing.assert_array_equal(body.velocities, v)
    assert body.kinetic_energy() + body.elastic_energy() <= 10 * e0
    # without the bound the same run is not stable by the sweep's criterion
    r = sw.free_cube("hex8", 0.499, 1e9, 0.1, steps=40)
    assert not r.stable and r.energy_ratio > 10


def test_nan_motion_script_is_refused_before_the_step():
    body = sw.cube_body("tet4", 1e5, 0.3)
    top = np.flatnonzero(np.isclose(body.rest[:, 2], sw.CUBE / 2))
    Xt = body.rest[top].copy()
    body.prescribe(top, lambda t: Xt if t < 0.015 else Xt * np.nan)
    sim = sb.Simulation(body, 0.01)
    sim.step()
    x, v = _state(body)
    with pytest.raises(sb.InvalidInputError, match=r"non-finite.*t = 0\.02"):
        sim.step()
    np.testing.assert_array_equal(body.positions, x)
    np.testing.assert_array_equal(body.velocities, v)
    assert sim.steps == 1


def test_world_divergence_keeps_world_state():
    """Through integration.world: a soft body resting on a plane, then an infinite load: World.step raises
    SimulationDiverged, the soft state and the world time stay at the last good step."""
    from integration.world import World

    body = sb.FemBody(sb.box_mesh((0.2, 0.2, 0.2), (1, 1, 1), "hex8", center=(0, 0, 0.1)),
                      sb.LinearElastic(1e5, 0.3, 1000.0))
    with World(dt=0.01) as world:
        world.add_plane()
        world.add_soft(body)
        world.run(0.05)
        x, v = _state(body)
        f = np.zeros_like(body.positions)
        f[3] = (np.nan, 0.0, 0.0)
        with pytest.raises(sb.InvalidInputError, match="non-finite"):  # refused when set
            world.sim.external_forces[body] = f
        world.sim.external_forces._loads[id(body)] = (body, f)  # past the check: the step's own guard
        with pytest.raises(sb.SimulationDiverged) as info:
            world.step()
        assert info.value.step == 6
        np.testing.assert_array_equal(body.positions, x)
        np.testing.assert_array_equal(body.velocities, v)
        assert world.t == pytest.approx(0.05)


# ---------------------------------------------------------------------------- degenerate but legal


@pytest.mark.parametrize("kind", KINDS)
def test_single_free_element_extreme_parameters(kind):
    """One element, no supports, extreme E / nu / dt: free fall stays exact (elastic forces vanish)."""
    if kind == "hex8":
        mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    else:
        tet = sb.Mesh(np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], float), [[0, 1, 2, 3]], "tet4")
        mesh = tet if kind == "tet4" else sb.to_tet10(tet)
    for E, nu, dt in ((1e2, 0.0, 0.1), (1e9, 0.499, 1e-4)):
        body = sb.FemBody(mesh, sb.LinearElastic(E, nu, 1000.0), damping=(0.0, 0.0))
        sim = sb.Simulation(body, dt, gravity=sw.G, max_energy=1e6)
        for _ in range(5):
            sim.step()
        n = 5
        np.testing.assert_allclose(body.positions, mesh.nodes + sw.G * dt * dt * n * (n + 1) / 2, atol=1e-9)


def test_all_nodes_fixed_in_a_world_with_contact():
    from integration.world import World

    mesh = sb.box_mesh((0.2, 0.2, 0.2), (1, 1, 1), "tet10", center=(0, 0, 0.05))  # pokes through the plane
    body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.45, 1000.0))
    body.fix(np.arange(mesh.n_nodes))
    with World(dt=0.01) as world:
        world.add_plane()
        world.add_soft(body)
        world.run(0.03)
    np.testing.assert_array_equal(body.positions, mesh.nodes)
    np.testing.assert_array_equal(body.velocities, 0.0)


def test_unused_nodes_with_extreme_material_and_prescribed_motion():
    mesh = sb.box_mesh((0.2, 0.2, 0.2), (2, 1, 1), "hex8")
    nodes = np.vstack([mesh.nodes, [[5.0, 5.0, 5.0]]])
    m = sb.Mesh(nodes, mesh.elements, "hex8")
    body = sb.FemBody(m, sb.LinearElastic(1e9, 0.499, 1000.0))
    left = np.flatnonzero(np.isclose(nodes[:, 0], -0.1))
    body.prescribe(left, lambda t: nodes[left] + [0.0, 0.0, 0.01 * t])
    sim = sb.Simulation(body, 1e-3, gravity=(0, 0, 0), max_energy=1e3)
    sim.run(0.01)
    np.testing.assert_array_equal(body.positions[-1], nodes[-1])  # the unused node stays put
    np.testing.assert_allclose(body.positions[left, 2], nodes[left, 2] + 1e-4, atol=1e-12)
    assert np.isfinite(body.positions).all()


def test_iterative_solver_with_only_prescribed_motion():
    body = sw.cube_body("hex8", 1e5, 0.3, damping=(2.0, 0.01))
    X = body.rest
    top = np.flatnonzero(np.isclose(X[:, 2], sw.CUBE / 2))
    body.fix(np.isclose(X[:, 2], -sw.CUBE / 2))
    body.prescribe(top, lambda t: X[top] - [0.0, 0.0, 0.1 * t])
    sim = sb.Simulation(body, 5e-3, gravity=(0, 0, 0), method="iterative")
    sim.run(0.02)
    ref = sw.cube_body("hex8", 1e5, 0.3, damping=(2.0, 0.01))
    ref.fix(np.isclose(X[:, 2], -sw.CUBE / 2))
    ref.prescribe(top, lambda t: X[top] - [0.0, 0.0, 0.1 * t])
    sb.Simulation(ref, 5e-3, gravity=(0, 0, 0), method="direct").run(0.02)
    np.testing.assert_allclose(body.positions, ref.positions, atol=1e-9)
