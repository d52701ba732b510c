"""Damping that spares rigid motion (FemBody(damp_rigid=False), the default; docs/method.md section 3): alpha M acts
on the velocity relative to the body's rigid motion. Checked against closed forms (free fall, a free spin, classic
Rayleigh's geometric decay), the momenta of the rigid fit, and classic Rayleigh damping where nothing differs (a
body with no momentum, a supported body)."""
import numpy as np
import pytest

import softbody as sb
from softbody import kernels
from softbody.stack import BodyStack

ALPHA, H, G = 0.1, 0.01, 9.81
KINDS = ["tet4", "tet10", "hex8"]


def cube(kind: str, damp_rigid: bool = False, E: float = 1e5, mass: str = "consistent", center=(0, 0, 0)):
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), kind, center=center)
    return sb.FemBody(mesh, sb.LinearElastic(E, 0.3, 1000.0), damping=(ALPHA, 0.001), damp_rigid=damp_rigid,
                      mass=mass)


def momenta(body: sb.FemBody) -> tuple[np.ndarray, np.ndarray]:
    """Linear and angular (about the centre of mass) momentum of the body [kg m/s], [kg m^2/s]."""
    y = body.mass_product(body.velocities)
    c = (body.node_mass[:, None] * body.positions).sum(axis=0) / body.node_mass.sum()
    return y.sum(axis=0), np.cross(body.positions - c, y).sum(axis=0)


@pytest.mark.parametrize("scheme", ["warped", "newton"])
@pytest.mark.parametrize("kind", KINDS)
def test_free_fall_is_nearly_undamped_and_classic_rayleigh_slows_it(kind, scheme):
    """Sparing rigid motion, v_{n+1} = v_n - g h / (1 + h alpha) (the rigid field lagged on v_n: after 1 s 0.1% short
    of backward Euler's undamped -g t at alpha 0.1, h 0.01); classic Rayleigh gives
    v_{n+1} = (v_n - g h) / (1 + h alpha)."""
    n = 100
    for damp_rigid in (False, True):
        body = cube(kind, damp_rigid)
        sim = sb.Simulation([body], dt=H, scheme=scheme)
        for _ in range(n):
            sim.step()
        v = 0.0
        for _ in range(n):
            v = (v - G * H) / (1.0 + H * ALPHA) if damp_rigid else v - G * H / (1.0 + H * ALPHA)
        np.testing.assert_allclose(body.velocities[:, 2], v, rtol=1e-8)
        np.testing.assert_allclose(body.velocities[:, :2], 0.0, atol=1e-9)
        if not damp_rigid:
            assert v == pytest.approx(-G, rel=0.0011)  # within 0.5% of exact free fall (0.1%)
    assert v == pytest.approx(-9.33, abs=0.01)  # what classic Rayleigh damping made of 1 s of free fall


@pytest.mark.parametrize("kind", KINDS)
def test_free_spin_keeps_its_angular_momentum(kind):
    """A cube spinning at 1 rev/s about an oblique axis, no gravity: default damping keeps L over 1 s; classic
    Rayleigh's alpha M takes h alpha L' a step: L_n = L_0 / (1 + h alpha)^n (0.905 L_0). Both to 1e-5 of L_0: the warped
    elastic forces exert a small torque where the element's rotation is not its own polar factor (tet10's
    characteristic tetrahedron: 3e-6 of L_0 in the second; tet4 1e-7, hex8 1e-11)."""
    n = 100
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    for damp_rigid in (False, True):
        body = cube(kind, damp_rigid, E=1e6)
        c = body.positions.mean(axis=0)
        body.velocities = np.cross(2 * np.pi * axis, body.positions - c)
        sim = sb.Simulation([body], dt=H, gravity=(0, 0, 0))
        P0, L0 = momenta(body)
        for _ in range(n):
            sim.step()
        P, L = momenta(body)
        expected = L0 / (1.0 + H * ALPHA) ** n if damp_rigid else L0
        np.testing.assert_allclose(L, expected, rtol=0, atol=1e-5 * np.linalg.norm(L0))
        np.testing.assert_allclose(P, 0.0, atol=1e-9 * np.linalg.norm(L0) / 0.05)


@pytest.mark.parametrize("compiled", [True, False], ids=["kernels", "numpy"])
@pytest.mark.parametrize("mass", ["consistent", "lumped"])
@pytest.mark.parametrize("kind", KINDS)
def test_rigid_fit_is_its_own_fit_and_keeps_the_momenta(kind, mass, compiled, monkeypatch):
    """rigid_velocity(M v) returns a rigid field v itself; for any momenta y its field v_r carries them:
    sum M v_r = sum y and sum r x M v_r = sum r x y."""
    if not compiled:
        monkeypatch.setattr(kernels, "ENABLED", False)
    elif not kernels.ENABLED:
        pytest.skip("numba not installed")
    body = cube(kind, mass=mass)
    rng = np.random.default_rng(3)
    body.positions = body.positions + 0.01 * rng.standard_normal(body.positions.shape)  # deformed
    c = (body.node_mass[:, None] * body.positions).sum(axis=0) / body.node_mass.sum()
    rigid = np.array([0.3, -1.0, 2.0]) + np.cross([1.5, -0.5, 4.0], body.positions - c)
    np.testing.assert_allclose(body.rigid_velocity(body.mass_product(rigid)), rigid, rtol=1e-10, atol=1e-12)
    y = rng.standard_normal(body.positions.shape)
    fit = body.mass_product(body.rigid_velocity(y))
    np.testing.assert_allclose(fit.sum(axis=0), y.sum(axis=0), atol=1e-12)
    r = body.positions - c
    np.testing.assert_allclose(np.cross(r, fit).sum(axis=0), np.cross(r, y).sum(axis=0), atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_no_momentum_no_difference(kind):
    """A free cube released stretched with no momentum at all (and no gravity): its rigid field is zero, so its
    vibration decays exactly as under classic Rayleigh damping, step for step."""
    runs = []
    for damp_rigid in (False, True):
        body = cube(kind, damp_rigid)
        body.positions = body.positions * np.array([1.1, 0.95, 0.95])
        sim = sb.Simulation([body], dt=H, gravity=(0, 0, 0))
        e0 = body.elastic_energy()
        for _ in range(50):
            sim.step()
        runs.append(body.positions.copy())
        assert body.elastic_energy() < 0.5 * e0  # the vibration decays
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-12)


def test_a_supported_body_keeps_classic_rayleigh_damping():
    """A cantilever clamped at one end has no free rigid motion: the same trajectory either way, to the bit."""
    runs = []
    for damp_rigid in (False, True):
        mesh = sb.box_mesh((0.5, 0.05, 0.05), (5, 1, 1), "tet10", center=(0.25, 0, 0))
        body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), damping=(ALPHA, 0.001), damp_rigid=damp_rigid)
        body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
        sim = sb.Simulation([body], dt=H)
        for _ in range(30):
            sim.step()
        runs.append(body.positions.copy())
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_stack_spares_each_free_member_alone():
    """A BodyStack of a falling cube and a clamped one: the free member falls as alone (v = -g n h / (1 + h alpha)),
    the clamped one moves as it does stepped alone with classic damping."""
    free, held = cube("tet4", center=(0, 0, 1.0)), cube("tet4", center=(1.0, 0, 1.0))
    held.fix(np.flatnonzero(np.isclose(held.positions[:, 2], held.positions[:, 2].min())))
    alone = cube("tet4", damp_rigid=True, center=(1.0, 0, 1.0))
    alone.fix(np.flatnonzero(np.isclose(alone.positions[:, 2], alone.positions[:, 2].min())))
    stack = BodyStack([free, held])
    sim, sim_alone = sb.Simulation([stack], dt=H), sb.Simulation([alone], dt=H)
    for _ in range(30):
        sim.step()
        sim_alone.step()
    np.testing.assert_allclose(free.velocities[:, 2], -G * H * 30 / (1.0 + H * ALPHA), rtol=1e-8)
    np.testing.assert_allclose(held.positions, alone.positions, rtol=0, atol=1e-9)


def test_damp_rigid_bodies_do_not_share_a_stack():
    with pytest.raises(sb.errors.InvalidInputError, match="damping"):
        BodyStack([cube("tet4"), cube("tet4", damp_rigid=True, center=(1, 0, 0))])


def test_a_node_no_element_uses_is_no_support():
    """Meshes read from files may carry points no element uses (held at rest, massless): the body is still free, and
    falls as the same body without them."""
    runs = []
    for orphan in (False, True):
        mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4")
        if orphan:
            mesh = sb.Mesh(np.vstack([mesh.nodes, [[1.0, 1.0, 1.0]]]), mesh.elements, mesh.kind)
        body = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0), damping=(ALPHA, 0.001))
        sim = sb.Simulation([body], dt=H)
        for _ in range(100):
            sim.step()
        runs.append(body.velocities[:8, 2].copy())
    np.testing.assert_allclose(runs[1], runs[0], rtol=1e-12)
    np.testing.assert_allclose(runs[0], -G * H * 100 / (1.0 + H * ALPHA), rtol=1e-8)


@pytest.mark.parametrize("scheme", ["newton", "bdf2"])
def test_the_newton_schemes_damping_spares_a_fast_spin(scheme):
    """The Newton schemes measure beta's strain rate from the unrotated displacements (softbody.newton), not as
    beta K'_n v: the chord a turning node follows is not tangent to the start's rotation, and K'_n of it damped a
    cube spinning at 2 rev/s to 10 % of its angular momentum in 1 s (0.49 without damping). Now the default damping
    leaves the spin exactly what the scheme's own numerical damping leaves it."""
    kept = []
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    for damping in ((0.0, 0.0), (ALPHA, 0.001)):
        mesh = sb.box_mesh((0.2, 0.2, 0.2), (2, 2, 2), "tet10")
        body = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.33, 1000.0), damping=damping)
        body.velocities = np.cross(2 * np.pi * 2.0 * axis, body.positions)
        _, L0 = momenta(body)
        sb.Simulation([body], dt=H, gravity=(0, 0, 0), scheme=scheme).run(1.0)
        kept.append(float(momenta(body)[1] @ L0 / (L0 @ L0)))
    assert kept[1] == pytest.approx(kept[0], abs=1e-3)
    assert kept[0] > (0.45 if scheme == "newton" else 0.95)


@pytest.mark.parametrize("scheme", ["newton", "bdf2"])
def test_the_newton_schemes_damping_still_damps_vibration_as_rayleigh(scheme):
    """A clamped bar vibrating in its first bending mode, beta only, small steps (the schemes' own damping
    small): its energy decays as the warped step's beta K' v makes it (the two measure the same strain rate where
    nothing turns): to 2 % for backward Euler, 5 % for BDF2 (backward Euler's own damping of the higher modes the
    start excites takes 3 % more: 0.460 against 0.476)."""
    decays = {}
    for s in ("warped", scheme):
        mesh = sb.box_mesh((0.4, 0.04, 0.04), (8, 1, 1), "tet10", center=(0.2, 0, 0))
        body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), damping=(0.0, 0.02))
        body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
        body.velocities[:, 2] = 0.2 * (mesh.nodes[:, 0] / 0.4) ** 2
        e0 = body.kinetic_energy()
        sb.Simulation([body], dt=0.001, gravity=(0, 0, 0), scheme=s).run(0.5)
        decays[s] = (body.kinetic_energy() + body.elastic_energy()) / e0
    assert decays[scheme] < 0.7  # it damps (modal damping ratio beta w / 2 = 0.08: exp(-0.64) of it)
    assert decays[scheme] == pytest.approx(decays["warped"], rel=0.02 if scheme == "newton" else 0.05)
