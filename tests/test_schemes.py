"""The BDF2 scheme (softbody.schemes): second order against an exact modal solution, free fall against the
parabola, momentum, a spin's shape and angular momentum against backward Euler's, supports, restarts, large steps."""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

import softbody as sb
from softbody.errors import InvalidInputError


def _cube(kind: str = "tet10", E: float = 1e7, rev: float = 0.0, damping=(0.0, 0.0)) -> sb.FemBody:
    mesh = sb.box_mesh((0.2, 0.2, 0.2), (2, 2, 2), kind)
    body = sb.FemBody(mesh, sb.LinearElastic(E, 0.33, 1000.0), damping=damping)
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    body.velocities[:] = np.cross(2 * math.pi * rev * axis, mesh.nodes)
    return body


def _angular_momentum(body: sb.FemBody) -> np.ndarray:
    """sum_i (x_i - c) x (M v)_i [kg m^2/s] about the centre of mass c, with the consistent mass matrix."""
    centre = body.node_mass @ body.positions / body.node_mass.sum()
    return np.cross(body.positions - centre, body.mass_product(body.velocities)).sum(axis=0)


def _run(body: sb.FemBody, scheme: str, dt: float, duration: float, gravity=(0.0, 0.0, 0.0)) -> sb.Simulation:
    sim = sb.Simulation(body, dt, gravity=gravity, scheme=scheme)
    sim.run(duration)
    return sim


def _modal_bar():
    """A linear (unwarped) tet4 bar fixed at x = 0, no damping, no gravity, started in its first bending mode at
    0.1 m/s: its exact motion from the generalised eigenproblem K phi = w^2 M phi on the free unknowns."""
    mesh = sb.box_mesh((0.4, 0.05, 0.05), (8, 1, 1), "tet4", center=(0.2, 0.0, 0.0))
    body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), warping=False, damping=(0.0, 0.0))
    fixed = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0))
    K = body.pattern.to_bsr(body.pattern.assemble(body.Ke)).toarray()
    M = body.mass_matrix().toarray()
    free = np.setdiff1d(np.arange(K.shape[0]), (3 * fixed[:, None] + np.arange(3)).ravel())
    w2, phi = scipy.linalg.eigh(K[np.ix_(free, free)], M[np.ix_(free, free)])
    w = math.sqrt(w2[0])
    shape = np.zeros(K.shape[0])
    shape[free] = phi[:, 0] * 0.1 / np.abs(phi[:, 0]).max()
    v0 = shape.reshape(-1, 3)

    def exact(t: float) -> np.ndarray:
        return mesh.nodes + v0 * math.sin(w * t) / w

    return mesh, fixed, v0, exact, w


def _bar_error(scheme: str, dt: float, duration: float) -> float:
    mesh, fixed, v0, exact, _ = _modal_bar()
    body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), warping=False, damping=(0.0, 0.0))
    body.fix(fixed)
    body.velocities[:] = v0
    _run(body, scheme, dt, duration)
    return float(np.abs(body.positions - exact(duration)).max())


def test_bdf2_is_second_order_against_the_exact_modal_solution_and_backward_euler_first():
    _, _, _, _, w = _modal_bar()
    T = 2 * math.pi / w  # one period of the first mode
    dts = [T / 40, T / 80, T / 160]
    bdf2 = [_bar_error("bdf2", dt, 1.25 * T) for dt in dts]  # at the swing's far end: amplitude and phase
    euler = [_bar_error("newton", dt, 1.25 * T) for dt in dts]
    bdf2_orders = [math.log2(a / b) for a, b in zip(bdf2, bdf2[1:])]
    euler_orders = [math.log2(a / b) for a, b in zip(euler, euler[1:])]
    assert min(bdf2_orders) > 1.8, bdf2_orders
    assert max(euler_orders) < 1.3, euler_orders
    assert bdf2[-1] < 0.1 * euler[-1]


def test_bdf2_falls_as_the_parabola():
    body = _cube("tet4")
    body.velocities[:] = (0.3, 0.0, 1.0)
    x0 = body.positions.copy()
    _run(body, "bdf2", 0.01, 1.0, gravity=(0.0, 0.0, -9.81))
    exact = x0 + np.array([0.3, 0.0, 1.0]) - np.array([0.0, 0.0, 9.81 / 2])
    # the start is a backward Euler step (h^2 g / 2 = 0.5 mm off), which BDF2 carries on as a constant lag: 2.6 mm
    # of the 4.9 m drop (backward Euler: g h t / 2 = 49 mm, growing with t)
    assert np.abs(body.positions - exact).max() < 3e-3
    assert np.abs(body.velocities - (0.3, 0.0, 1.0 - 9.81)).max() < 1e-6
    euler = _cube("tet4")
    euler.velocities[:] = (0.3, 0.0, 1.0)
    _run(euler, "newton", 0.01, 1.0, gravity=(0.0, 0.0, -9.81))
    assert np.abs(euler.positions - exact).max() > 0.04  # g h t / 2


@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
def test_bdf2_keeps_a_spin_where_backward_euler_slows_it(kind):
    kept = {}
    for scheme in ("newton", "bdf2"):
        body = _cube(kind, rev=2.0)
        body.velocities += (0.5, -0.2, 0.1)  # a drift too: linear momentum is exact under either
        p0, L0 = body.mass_product(body.velocities).sum(axis=0), _angular_momentum(body)
        d0 = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)
        _run(body, scheme, 0.01, 1.0)
        assert np.abs(body.mass_product(body.velocities).sum(axis=0) - p0).max() < 1e-9 * np.abs(p0).max()
        L = _angular_momentum(body)
        kept[scheme] = float(np.dot(L, L0) / np.dot(L0, L0))
        d = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)
        off = d0 > 0
        assert np.abs(d[off] / d0[off] - 1).max() < 0.005  # the shape: both iterate on the rotations
    assert kept["newton"] < 0.8  # backward Euler: 23 % of the spin gone in 1 s
    assert kept["bdf2"] > 0.97
    assert 1 - kept["bdf2"] < 0.1 * (1 - kept["newton"])


def test_bdf2_holds_prescribed_and_fixed_nodes_on_their_motion():
    mesh = sb.box_mesh((0.4, 0.05, 0.05), (8, 1, 1), "tet10", center=(0.2, 0.0, 0.0))
    body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0))
    left = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0))
    right = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.4))
    body.fix(left)
    body.prescribe(right, lambda t: mesh.nodes[right] + (0.0, 0.0, 0.05 * math.sin(4 * t)))
    sim = sb.Simulation(body, 0.01, scheme="bdf2")
    for _ in range(60):
        sim.step()
        assert np.abs(body.positions[left] - mesh.nodes[left]).max() < 1e-12
        assert np.abs(body.positions[right, 2] - mesh.nodes[right, 2] - 0.05 * math.sin(4 * sim.t)).max() < 1e-12


def _pair(rev: float = 1.0) -> tuple[sb.FemBody, sb.Simulation, sb.FemBody, sb.Simulation]:
    """A body stepped by BDF2 and a twin stepped by backward Euler (scheme "newton")."""
    a, b = _cube("tet4", rev=rev), _cube("tet4", rev=rev)
    return a, sb.Simulation(a, 0.01, gravity=(0, 0, -9.81), scheme="bdf2"), b, \
        sb.Simulation(b, 0.01, gravity=(0, 0, -9.81), scheme="newton")


def _restarts(a: sb.FemBody, sa: sb.Simulation, b: sb.FemBody, sb_: sb.Simulation) -> None:
    """The next step of sa is a backward Euler step (as its twin's from the same state), the one after BDF2."""
    b.positions, b.velocities = a.positions.copy(), a.velocities.copy()
    sa.step()
    sb_.step()
    assert np.abs(a.positions - b.positions).max() < 1e-12
    sa.step()
    sb_.step()
    assert np.abs(a.positions - b.positions).max() > 1e-7


@pytest.mark.parametrize("change", ["assigned positions", "velocities changed in place", "positions changed in place",
                                    "another step size"])
def test_bdf2_restarts_with_a_backward_euler_step_when_the_state_is_changed_from_outside(change):
    a, sa, b, sb_ = _pair()
    for _ in range(5):
        sa.step()
    if change == "assigned positions":
        a.positions = a.positions + (0.0, 0.0, 0.1)
    elif change == "velocities changed in place":
        a.velocities += (0.0, 0.0, 1.0)
    elif change == "positions changed in place":
        a.positions[:, 2] += 0.1
    else:
        sa.dt = sb_.dt = 0.005
    _restarts(a, sa, b, sb_)


def test_bdf2_restarts_when_a_member_of_a_stack_is_assigned():
    from softbody.stack import BodyStack

    members = [_cube("tet4", rev=1.0), _cube("tet4", rev=0.5)]
    for k, m in enumerate(members):
        m.positions = m.positions + (0.5 * k, 0.0, 0.0)
    stack = BodyStack(members)
    sim = sb.Simulation(stack, 0.01, gravity=(0, 0, 0), scheme="bdf2")
    for _ in range(4):
        sim.step()
    members[1].velocities = members[1].velocities + (0.0, 0.0, 1.0)
    x = stack.positions.copy()
    sim.step()  # a backward Euler step from the member's new state: its centre moves by h (v + 0)
    moved = (members[1].node_mass @ (members[1].positions - x[stack.offsets[1]:stack.offsets[2]])
             / members[1].node_mass.sum())
    assert moved[2] == pytest.approx(0.01 * 1.0, rel=1e-6)


def test_bdf2_continues_from_the_last_committed_step_after_an_uncommitted_one():
    a, sa = _cube("tet4", rev=1.0), None
    sa = sb.Simulation(a, 0.01, gravity=(0, 0, -9.81), scheme="bdf2")
    b = _cube("tet4", rev=1.0)
    sref = sb.Simulation(b, 0.01, gravity=(0, 0, -9.81), scheme="bdf2")
    for _ in range(5):
        sa.step()
        sref.step()
    sa.solve_step()  # solved, never committed: the state stays where the fifth step left it
    for _ in range(3):
        sa.step()
        sref.step()
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.velocities, b.velocities)


@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
def test_the_newton_damping_gradient_is_the_derivative_of_its_potential(kind):
    """The Newton schemes' damping potential beta/(2h) sum |u_e(x) - u_e,start|^2_K (softbody.newton) and the gradient
    they step with agree by central differences, on a turned and strained body (the rotations' derivatives in)."""
    from softbody.newton import NewtonStepper

    rng = np.random.default_rng(3)
    body = _cube(kind, E=1e6, damping=(0.0, 0.01))
    angle = 0.4
    Q = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    body.positions = body.positions @ Q.T + 1e-3 * rng.standard_normal(body.positions.shape)
    body.velocities = 0.5 * rng.standard_normal(body.positions.shape)
    h = 0.01
    step = NewtonStepper._start(body, h, np.zeros((body.n_nodes, 3)))
    v = body.velocities + 0.3 * rng.standard_normal(body.positions.shape)
    d = rng.standard_normal(v.shape)
    eps = 1e-6
    slope = (step.potential(v + eps * d, h) - step.potential(v - eps * d, h)) / (2 * eps)
    g, _ = step.gradient(v, h)
    assert float(np.sum(g * d)) == pytest.approx(slope, rel=1e-6)
    # and a rigid turn over the step is not damped: the damped body's gradient is the undamped twin's
    twin = _cube(kind, E=1e6, damping=(0.0, 0.0))
    twin.positions, twin.velocities = body.positions.copy(), body.velocities.copy()
    spin = (body.positions @ (Q.T - np.eye(3))) / h  # x + h v = Q x: the strained body turned by 0.4 rad
    g_damped = NewtonStepper._start(body, h, np.zeros((body.n_nodes, 3))).gradient(spin, h)[0]
    g_twin = NewtonStepper._start(twin, h, np.zeros((body.n_nodes, 3))).gradient(spin, h)[0]
    np.testing.assert_allclose(g_damped, g_twin, atol=1e-9 * np.abs(g_twin).max())


@pytest.mark.parametrize("E", [1e5, 1e8])
def test_bdf2_is_stable_at_a_tenth_of_a_second(E):
    """A cube spinning at 2 rev/s turns 1.26 rad in a step of 0.1 s, far past what the step resolves: the energy
    never rises above its start (a free body's energy cannot), the shape holds, nothing diverges."""
    body = _cube("tet10", E=E, rev=2.0)
    e0 = body.kinetic_energy() + body.elastic_energy()
    d0 = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)
    sim = sb.Simulation(body, 0.1, gravity=(0.0, 0.0, 0.0), scheme="bdf2")
    energies = []
    for _ in range(30):
        sim.step()
        energies.append(body.kinetic_energy() + body.elastic_energy())
    assert np.all(np.isfinite(body.positions))
    assert max(energies) <= e0
    d = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)
    off = d0 > 0
    assert np.abs(d[off] / d0[off] - 1).max() < 0.05


def test_world_refuses_bdf2_and_names_where_it_runs():
    from integration.world import World

    with pytest.raises(InvalidInputError, match="Simulation"):
        World(dt=0.01, scheme="bdf2")
    with pytest.raises(InvalidInputError, match="scheme"):
        sb.Simulation(_cube("tet4"), 0.01, scheme="midpoint")
