"""Backward Euler dynamics: free fall, energy, prescribed and fixed nodes (docs/method.md section 3)."""
from __future__ import annotations

import numpy as np
import pytest

import softbody
from conftest import KINDS

MAT = softbody.LinearElastic(5.0e5, 0.33, 1000.0)
G = np.array([0.0, 0.0, -9.81])


def small_box(kind):
    return softbody.box_mesh((0.4, 0.3, 0.2), (2, 2, 1), kind, center=(0.1, 0.2, 1.0))


@pytest.mark.parametrize("mass", ["consistent", "lumped"])
@pytest.mark.parametrize("kind", KINDS)
def test_free_fall_without_damping_is_exact_backward_euler(kind, mass):
    """With alpha = 0: v_n = n h g and x_n = X + h^2 g n (n + 1) / 2 = X + g t^2/2 + g h t/2, for every node."""
    mesh = small_box(kind)
    body = softbody.FemBody(mesh, MAT, damping=(0.0, 0.01), mass=mass)  # beta does not act on rigid motion
    h = 0.01
    sim = softbody.Simulation(body, dt=h, gravity=G)
    for n in range(1, 51):
        sim.step()
        assert sim.t == pytest.approx(n * h, rel=1e-12)
        np.testing.assert_allclose(body.velocities, np.broadcast_to(n * h * G, body.velocities.shape), rtol=0, atol=1e-10)
        np.testing.assert_allclose(body.positions, mesh.nodes + h * h * G * n * (n + 1) / 2, rtol=0, atol=1e-10)
    t = sim.t
    np.testing.assert_allclose(body.positions, mesh.nodes + G * t**2 / 2 + G * h * t / 2, rtol=0, atol=1e-10)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("alpha", [0.5, 3.0])
@pytest.mark.parametrize("damp_rigid", [True, False], ids=["classic", "sparing"])
def test_free_fall_with_mass_damping_is_exact_backward_euler(kind, alpha, damp_rigid):
    """Classic Rayleigh alpha acts on rigid motion: M v' (1 + h alpha) = M v + h M g, so (1 + h alpha) v_{n+1} =
    v_n + h g, tending to the terminal velocity g / alpha. Sparing rigid motion (the default) adds h alpha M v_n:
    v_{n+1} = v_n + h g / (1 + h alpha), no terminal velocity."""
    mesh = small_box(kind)
    body = softbody.FemBody(mesh, MAT, damping=(alpha, 0.02), damp_rigid=damp_rigid)
    v0 = np.array([0.3, -0.2, 1.5])
    body.velocities[:] = v0
    h = 0.005
    sim = softbody.Simulation(body, dt=h, gravity=G)
    v, x = v0.copy(), np.zeros(3)
    for _ in range(60):
        sim.step()
        v = (v + h * G) / (1 + h * alpha) if damp_rigid else v + h * G / (1 + h * alpha)
        x = x + h * v
        np.testing.assert_allclose(body.velocities, np.broadcast_to(v, body.velocities.shape), rtol=0, atol=1e-10)
        np.testing.assert_allclose(body.positions, mesh.nodes + x, rtol=0, atol=1e-10)
    if damp_rigid:  # the discrete velocity tends to the terminal velocity g / alpha
        v_inf = G / alpha
        v_n = v_inf + (v0 - v_inf) / (1 + h * alpha) ** 60
        np.testing.assert_allclose(body.velocities[0], v_n, atol=1e-10)


def cantilever(kind, cells):
    mesh = softbody.box_mesh((1.0, 0.1, 0.1), cells, kind, center=(0.5, 0, 0))
    return mesh, np.isclose(mesh.nodes[:, 0], 0.0)


@pytest.mark.parametrize("warping", [True, False])
@pytest.mark.parametrize("kind, cells", [("tet4", (10, 2, 2)), ("hex8", (10, 2, 2)), ("tet10", (5, 1, 1))])
def test_undamped_vibration_energy_never_increases(kind, cells, warping):
    """Release a statically deflected cantilever with gravity off and no damping: kinetic + elastic energy
    is non-increasing step to step (backward Euler is dissipative), yet the beam really oscillates."""
    mesh, clamp = cantilever(kind, cells)
    body = softbody.FemBody(mesh, softbody.LinearElastic(5e7, 0.33, 1000.0), warping=warping, damping=(0.0, 0.0))
    body.fix(clamp)
    u = softbody.solve_static(body, gravity=(0, 0, -9.81))
    body.positions = mesh.nodes + u
    sim = softbody.Simulation(body, dt=0.002, gravity=(0, 0, 0))
    tip = np.isclose(mesh.nodes[:, 0], 1.0)
    energy = [body.kinetic_energy() + body.elastic_energy()]
    ke, tip_z = [], []
    for _ in range(150):
        sim.step()
        ke.append(body.kinetic_energy())
        energy.append(ke[-1] + body.elastic_energy())
        tip_z.append(body.positions[tip, 2].mean())
    energy = np.array(energy)
    assert energy[0] > 0
    increase = np.diff(energy)
    assert increase.max() <= 1e-12 * energy[0], increase.max() / energy[0]
    # not trivially satisfied: the energy turns into motion and the tip swings up past its rest position
    assert max(ke) > 0.3 * energy[0]
    assert max(tip_z) > 0.1 * abs(u[tip, 2].mean())
    assert energy[-1] < energy[0]


@pytest.mark.parametrize("kind", KINDS)
def test_prescribed_nodes_follow_their_motion_exactly(kind):
    mesh, clamp = cantilever(kind, (5, 1, 1))
    body = softbody.FemBody(mesh, MAT)
    tip = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 1.0))
    fixed_ids = np.flatnonzero(clamp)
    body.fix(fixed_ids)
    rest_tip = mesh.nodes[tip].copy()

    def motion(t):
        return rest_tip + np.outer(np.ones(len(tip)), [0.0, 0.02 * np.sin(2 * np.pi * 3 * t), 0.05 * np.sin(2 * np.pi * 2 * t)])

    body.prescribe(tip, motion)
    sim = softbody.Simulation(body, dt=0.01, gravity=G)
    seen = []

    def check(s):
        assert s is sim
        np.testing.assert_allclose(body.positions[tip], motion(s.t), rtol=0, atol=1e-12)
        assert np.array_equal(body.positions[fixed_ids], mesh.nodes[fixed_ids])  # exactly, not approximately
        assert np.all(body.velocities[fixed_ids] == 0.0)
        seen.append(s.t)

    sim.run(0.5, callback=check)
    assert len(seen) == 50 and seen[-1] == pytest.approx(0.5)
    # the free nodes did move (gravity and the driven tip)
    free = ~clamp
    free[tip] = False
    assert np.abs(body.positions[free] - mesh.nodes[free]).max() > 1e-3


def test_fixed_nodes_never_move_under_gravity():
    mesh, clamp = cantilever("hex8", (10, 1, 1))
    body = softbody.FemBody(mesh, MAT)
    body.fix(clamp)
    sim = softbody.Simulation(body, dt=0.01, gravity=G)
    for _ in range(30):
        sim.step()
        assert np.array_equal(body.positions[clamp], mesh.nodes[clamp])
    assert body.positions[~clamp, 2].min() < mesh.nodes[:, 2].min() - 1e-3


def test_damped_cantilever_settles_at_static_solution():
    """With damping, the dynamic beam comes to rest at the static deflection (small deflection: warped and
    linear statics agree)."""
    mesh, clamp = cantilever("hex8", (10, 2, 2))
    mat = softbody.LinearElastic(5e7, 0.33, 1000.0)
    body = softbody.FemBody(mesh, mat, damping=(5.0, 0.002))
    body.fix(clamp)
    u_static = softbody.solve_static(body, gravity=G)
    sim = softbody.Simulation(body, dt=0.02, gravity=G)
    sim.run(3.0)
    tip = np.isclose(mesh.nodes[:, 0], 1.0)
    d_dyn = (body.positions - mesh.nodes)[tip, 2].mean()
    d_stat = u_static[tip, 2].mean()
    assert d_dyn == pytest.approx(d_stat, rel=0.01)
    assert np.abs(body.velocities).max() < 1e-3
