"""The warped step says when its elements turn too far within a step to trust its linearised rotations
(softbody.linearisation, issue 33): the rotation it measures against a rigid spin's exact omega h, the warning against
the shape error measured independently (the rigid residual of a Procrustes fit to the rest shape)."""
import warnings

import numpy as np
import pytest

import softbody as sb
from softbody import kernels
from softbody.linearisation import ROTATION_LIMIT, LinearisationWarning, rotation_per_step

KINDS = ["tet4", "tet10", "hex8"]
AXIS = np.array([1.0, -2.0, 0.7]) / np.linalg.norm([1.0, -2.0, 0.7])
SIZE = 0.2


def spinning_cube(kind: str, rev_per_s: float) -> sb.FemBody:
    mesh = sb.box_mesh((SIZE,) * 3, (2, 2, 2), kind)
    body = sb.FemBody(mesh, sb.LinearElastic(5e6, 0.3, 1000.0), damping=(0.0, 0.0))
    body.velocities = np.cross(2 * np.pi * rev_per_s * AXIS, body.positions)
    return body


def shape_error(rest: np.ndarray, x: np.ndarray) -> float:
    """Largest node distance [per unit size] from the best rigid placement of the rest shape (Kabsch)."""
    a, b = rest - rest.mean(axis=0), x - x.mean(axis=0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(U @ Vt))
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    return float(np.linalg.norm(a @ R - b, axis=1).max()) / SIZE


@pytest.mark.parametrize("compiled", [True, False], ids=["kernels", "numpy"])
@pytest.mark.parametrize("kind", KINDS)
def test_a_rigid_spin_turns_omega_h_per_step(kind, compiled, monkeypatch):
    if not compiled:
        monkeypatch.setattr(kernels, "ENABLED", False)
    elif not kernels.ENABLED:
        pytest.skip("numba not installed")
    body = spinning_cube(kind, 10.0)
    for h in (0.001, 0.01):
        theta, _ = rotation_per_step(body, body.velocities, h)
        assert theta == pytest.approx(2 * np.pi * 10.0 * h, rel=1e-9)
    theta, _ = rotation_per_step(body, np.zeros_like(body.velocities) + [1.0, 2.0, 3.0], 0.01)  # a translation
    assert theta == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(5)  # a deformed body, any velocities: the kernel and its numpy twin agree
    body.positions = body.positions + 0.01 * rng.standard_normal(body.positions.shape)
    v = rng.standard_normal(body.positions.shape)
    monkeypatch.setattr(kernels, "ENABLED", compiled)
    theta, e = rotation_per_step(body, v, 0.01)
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert (theta, e) == pytest.approx(rotation_per_step(body, v, 0.01), rel=1e-12)


def run(kind: str, dt: float, steps: int, scheme: str = "warped") -> tuple[list, float]:
    body = spinning_cube(kind, 10.0)
    sim = sb.Simulation(body, dt, gravity=(0, 0, 0), scheme=scheme)
    worst = 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(steps):
            sim.step()
            worst = max(worst, shape_error(body.rest, body.positions))
    return [w for w in caught if issubclass(w.category, LinearisationWarning)], worst


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dt", [0.01, 0.02])
def test_fast_spin_is_warned_once_and_the_warning_is_true(kind, dt):
    """10 rev/s at dt 0.01 and 0.02 (0.63 and 1.26 rad per step): one warning naming the body, the angle and a step
    that would do; the shape error it announces is there (over 2%, measured apart)."""
    said, worst = run(kind, dt, 20)
    assert len(said) == 1
    msg = str(said[0].message)
    assert msg.startswith("body 0 (") and f"{2 * np.pi * 10 * dt:.2f} rad" in msg and "scheme='newton'" in msg
    assert f"dt <= {dt * ROTATION_LIMIT / (2 * np.pi * 10 * dt):.2g} s" in msg
    assert worst > 0.02


@pytest.mark.parametrize("kind", KINDS)
def test_a_step_small_enough_is_not_warned_and_keeps_the_shape(kind):
    """The step the warning suggests for 10 rev/s (0.2 rad per step, dt 3.2 ms; here 3 ms for 0.19 rad): no warning,
    under 2% out of shape over a full turn."""
    said, worst = run(kind, 0.003, 34)
    assert not said
    assert worst < 0.02


def test_the_newton_scheme_is_not_watched():
    """scheme="newton" updates its rotations within the step: nothing to warn of (and the shape is kept)."""
    said, worst = run("tet4", 0.01, 10, scheme="newton")
    assert not said
    assert worst < 0.02


def _hinged_bar(dt: float) -> tuple[sb.FemBody, sb.Simulation]:
    """A stiff tet10 bar (0.5 x 0.04 x 0.04 m, E = 1e9 Pa, default damping) hinged on its end's centre line (the
    nodes at x = 0, z = 0), released horizontal under gravity: it swings at up to 5 rad/s."""
    mesh = sb.box_mesh((0.5, 0.04, 0.04), (10, 1, 2), "tet10", center=(0.25, 0.0, 0.0))
    body = sb.FemBody(mesh, sb.LinearElastic(1e9, 0.33, 1000.0))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0) & np.isclose(mesh.nodes[:, 2], 0.0)))
    return body, sb.Simulation(body, dt)


@pytest.mark.parametrize("dt", [0.01, 0.002])
def test_a_stiff_body_is_warned_where_the_small_lag_stores_real_energy_and_the_warning_is_true(dt):
    """At dt 0.01 s the bar turns 0.05 rad a step, a quarter of ROTATION_LIMIT, yet the stretch the step leaves holds
    up to 1.2 times the kinetic energy a step: warned, and true: the bar's elastic energy (its swing stores almost
    none: the sag under its weight is 0.1 mm) exceeds its weight times the drop of its centre. At dt 0.002 s neither."""
    body, sim = _hinged_bar(dt)
    mgd = body.total_mass * 9.81 * 0.25
    elastic = 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(int(round(1.5 / dt))):
            sim.step()
            elastic = max(elastic, body.elastic_energy())
    said = [w for w in caught if issubclass(w.category, LinearisationWarning)]
    if dt == 0.01:
        assert len(said) == 1 and "stiff" in str(said[0].message) and "dt <=" in str(said[0].message)
        assert elastic > mgd
    else:
        assert not said
        assert elastic < 0.05 * mgd


def test_a_slow_soft_tet10_body_is_not_warned():
    """A soft tet10 cube whose corners turn slowly (0.001 rad a step, as a contact impulse on them leaves them): its
    stretch holds nothing worth saying. (The kinetic energy is 1/2 v^T M v: a tet10's consistent mass has negative row
    sums at its corners, and their sum once gave a negative 'kinetic energy' and a warning with a complex step.)"""
    from softbody.linearisation import RotationWatch

    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet10"), sb.LinearElastic(5e5, 0.3, 1000.0))
    corners = np.unique(body.mesh.elements[:, :4])
    v = np.zeros_like(body.rest)
    v[corners] = np.cross([0.0, 0.0, 0.1], body.rest[corners] - body.rest.mean(axis=0))
    assert body.node_mass[corners] @ np.einsum("ij,ij->i", v[corners], v[corners]) < 0  # the premise
    with warnings.catch_warnings():
        warnings.simplefilter("error", LinearisationWarning)
        RotationWatch().check(0, body, v, 0.01)
