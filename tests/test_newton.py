"""The Newton scheme (softbody.newton): the exact backward Euler step of the warped energy.

Checked against independent truth: finite differences of the energy for its gradient and Hessian, rigid
rotation (a spinning body keeps its shape), the warped scheme where both must agree (small steps), energy
that never grows with damping, and the contact scenes' own physics (Coulomb's law on an incline).
"""
import math

import numpy as np
import pytest

import softbody as sb
from integration import World
from softbody.errors import InvalidInputError, SimulationDiverged

KINDS = ["tet4", "hex8", "tet10"]


def _distorted(kind: str, seed: int = 1):
    """A one-cell body turned by a large rotation and strained at random, and its positions (N, 3)."""
    rng = np.random.default_rng(seed)
    mesh = sb.box_mesh((0.2, 0.2, 0.1), (1, 1, 1), kind)
    body = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    Q = np.eye(3) + math.sin(1.0) * K + (1 - math.cos(1.0)) * K @ K
    return body, mesh.nodes @ Q.T + 0.01 * rng.normal(size=mesh.nodes.shape)


@pytest.mark.parametrize("kind", KINDS)
def test_energy_gradient_is_the_derivative_of_the_energy(kind):
    """Central differences of FemBody.elastic_energy; the warped forces are the gradient for linear tets
    only (the others' rotation is their characteristic tet's)."""
    body, x = _distorted(kind)
    g = body.energy_gradient(x)
    eps, fd = 1e-7, np.zeros_like(x)
    for i in range(len(x)):
        for c in range(3):
            e = np.zeros_like(x)
            e[i, c] = eps
            fd[i, c] = (body.elastic_energy(x + e) - body.elastic_energy(x - e)) / (2 * eps)
    scale = np.abs(fd).max()
    assert np.abs(g - fd).max() < 1e-7 * scale
    warped = np.abs(-body.elastic_forces(x) - fd).max() / scale
    assert (warped < 1e-7) if kind == "tet4" else (warped > 1e-3)


@pytest.mark.parametrize("kind", KINDS)
def test_exact_tangent_is_the_derivative_of_the_gradient_and_positive(kind):
    body, x = _distorted(kind)
    rng = np.random.default_rng(3)
    d = rng.normal(size=x.shape)
    eps = 1e-6
    fd = ((body.energy_gradient(x + eps * d) - body.energy_gradient(x - eps * d)) / (2 * eps)).reshape(-1)
    H = body.pattern.to_csr(body.energy_hessian_blocks(x, project=False)).toarray()
    assert np.abs(H @ d.reshape(-1) - fd).max() < 1e-5 * np.abs(fd).max()
    assert np.abs(H - H.T).max() < 1e-9 * np.abs(H).max()
    Hp = body.pattern.to_csr(body.energy_hessian_blocks(x)).toarray()
    assert np.linalg.eigvalsh(Hp).min() > -1e-9 * np.abs(Hp).max()  # projected: positive semi-definite
    assert np.linalg.eigvalsh(H).min() < 0  # (the unprojected one is not, strained and turned like this)


def _spinning_cube(kind: str, h: float, scheme: str, duration: float = 0.3) -> float:
    """A 0.2 m cube (E = 1e7, no damping, zero gravity) spinning at 10 rev/s about an oblique axis; the
    largest relative change of any node-to-node distance over the run."""
    cells = (2, 2, 2) if kind == "tet10" else (3, 3, 3)
    mesh = sb.box_mesh((0.2, 0.2, 0.2), cells, kind)
    body = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.33, 1000.0), damping=(0.0, 0.0))
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    body.velocities[:] = np.cross(2 * math.pi * 10 * axis, mesh.nodes)
    sim = sb.Simulation(body, h, gravity=(0, 0, 0), scheme=scheme)
    iu = np.triu_indices(mesh.n_nodes, 1)
    d0 = np.linalg.norm(mesh.nodes[:, None] - mesh.nodes[None], axis=2)[iu]
    worst = 0.0
    for _ in range(int(round(duration / h))):
        sim.step()
        x = body.positions
        worst = max(worst, float(np.abs(np.linalg.norm(x[:, None] - x[None], axis=2)[iu] / d0 - 1).max()))
    return worst


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("h", [0.01, 0.03])
def test_spinning_cube_keeps_its_shape_under_newton(kind, h):
    assert _spinning_cube(kind, h, "newton") < 0.01


def test_spinning_cube_stretches_under_the_warped_step():
    """The control of the test above: the paper's step stretches it (the failure the scheme cures)."""
    assert _spinning_cube("tet4", 0.01, "warped", duration=0.2) > 0.05


def _beam(kind: str, E: float, h: float, scheme: str, **options):
    cells = (4, 1, 1) if kind == "tet10" else (8, 2, 2)
    mesh = sb.box_mesh((1.0, 0.1, 0.1), cells, kind, center=(0.5, 0, 0))
    body = sb.FemBody(mesh, sb.LinearElastic(E, 0.33, 1000.0), damping=(0.1, 0.001))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0)))
    return body, sb.Simulation(body, h, scheme=scheme, method="direct", **options)


@pytest.mark.parametrize("kind", KINDS)
def test_the_schemes_agree_at_small_steps(kind):
    """A stiff cantilever (E = 5e7) released under gravity, h = 1e-4 s for 0.02 s: trajectories within 1e-6 m."""
    runs = []
    for scheme in ("warped", "newton"):
        body, sim = _beam(kind, 5e7, 1e-4, scheme)
        traj = []
        for _ in range(200):
            sim.step()
            traj.append(body.positions.copy())
        runs.append(np.array(traj))
    assert np.abs(runs[0] - runs[1]).max() < 1e-6
    assert np.abs(runs[1][-1] - body.rest).max() > 1e-3  # it did sag


@pytest.mark.parametrize("kind", KINDS)
def test_energy_never_grows_under_newton(kind):
    """A soft cantilever (E = 5e5) swinging through large deflections with Rayleigh damping, h = 0.01 s: the
    total energy (kinetic, elastic, gravitational) never increases, where the warped step's tet10 does."""
    body, sim = _beam(kind, 5e5, 0.01, "newton")
    g = np.array([0.0, 0.0, -9.81])

    def energy():
        return body.kinetic_energy() + body.elastic_energy() + body.gravitational_energy(g)

    energies = [energy()]
    for _ in range(100):
        sim.step()
        energies.append(energy())
        assert sim.newton_report.residual <= 1e-5
    assert np.diff(energies).max() <= 1e-9 * abs(min(energies))
    assert body.positions[:, 2].min() < -0.3  # large deflections


def test_residuals_fall_fast_with_the_exact_tangent():
    """With the exact tangent each solve cuts the residual by far more than the warped tangent's linear rate."""
    body, sim = _beam("tet10", 5e5, 0.01, "newton", newton_tol=1e-7)
    sim.newton.settings.tangent = "exact"
    for _ in range(40):  # into the swing, where the warped tangent crawls (rate 0.7 to 0.95 per solve)
        sim.step()
    r = np.array(sim.newton_report.residuals)
    assert len(r) >= 3 and r[-1] < 1e-7
    fast = r[:-1] > 1e-7  # above the finite-difference tangent's noise floor (about 1e-8 here)
    assert fast.sum() >= 2 and (r[1:][fast] / r[:-1][fast]).max() < 0.1


def test_a_step_that_does_not_converge_raises_with_its_residuals_and_keeps_the_state():
    body, sim = _beam("tet4", 5e5, 0.05, "newton", newton_tol=1e-12, newton_max_iter=2)
    x0 = body.positions.copy()
    with pytest.raises(SimulationDiverged, match=r"did not converge in 2 solves .* residuals \d"):
        sim.step()
    assert np.array_equal(body.positions, x0) and sim.steps == 0
    with pytest.raises(InvalidInputError, match="scheme"):
        sb.Simulation(body, 0.01, scheme="implicit")
    with pytest.raises(InvalidInputError, match="newton tol"):
        sb.Simulation(body, 0.01, scheme="newton", newton_tol=0)


def test_contact_scenes_under_newton():
    """Sheet on sphere: the corner's height agrees with the warped step within 2 mm, nothing penetrates; a
    block on an incline slides with Coulomb's acceleration."""
    from experiments.scenes import sheet_on_sphere

    z = {}
    for scheme in ("warped", "newton"):
        sc = sheet_on_sphere("tet4", (4, 4, 2), scheme=scheme)
        sc.world.run(1.0)
        z[scheme] = sc.monitored()
        assert sc.world.max_penetration() < 1e-4
    assert abs(z["newton"] - z["warped"]) < 2e-3
    th = math.radians(20)
    Ry = np.array([[math.cos(th), 0, math.sin(th)], [0, 1, 0], [-math.sin(th), 0, math.cos(th)]])
    m = sb.box_mesh((0.2, 0.2, 0.1), (2, 2, 1), "hex8", center=(0, 0, 0.05 + 1e-4))
    body = sb.FemBody(sb.Mesh(m.nodes @ Ry.T, m.elements, "hex8"), sb.LinearElastic(1e6, 0.3, 1000),
                      damping=(0.0, 0.001))
    world = World(dt=0.01, scheme="newton")
    world.add_plane(normal=Ry @ [0, 0, 1.0])
    world.add_soft(body, friction=0.1)
    xs = []
    world.run(1.0, lambda w: xs.append(body.positions.mean(axis=0) @ (Ry @ [1.0, 0, 0])))
    t = world.dt * np.arange(1, len(xs) + 1)
    accel = 2 * np.polyfit(t[30:], xs[30:], 2)[0]
    assert accel == pytest.approx(9.81 * (math.sin(th) - 0.1 * math.cos(th)), rel=0.1)


def test_cycling_residuals_are_told_from_converging_ones():
    """The pattern a Newton step with switching contacts is accepted on (newton.cycling): residuals repeating
    with period 2 near the tolerance; not a falling sequence, nor a cycle far above the bound."""
    from softbody.newton import cycling

    assert cycling([1e-3, 3e-4, 2.0e-4, 3e-4, 2.0e-4, 3e-4, 2.0e-4], 1e-3)
    assert cycling([1e-3, 4.17e-3, 4.22e-3, 4.17e-3, 4.22e-3, 4.17e-3, 4.22e-3], 1e-2)
    assert not cycling([1e-3, 5e-4, 3e-4, 2.0e-4, 1e-4, 5e-5], 1e-3)
    assert not cycling([1e-1, 3e-2, 2.0e-2, 3e-2, 2.0e-2, 3e-2, 2.0e-2], 1e-3)
    assert not cycling([3e-4, 2e-4, 3e-4], 1e-3)  # too short to tell


def test_newton_settings_refuse_what_cannot_work():
    """A line search with min_step <= 0 would halve to 0 and burn every iteration; armijo outside (0, 0.5) is no
    sufficient decrease: refused by name; a numpy float tolerance is a number."""
    from softbody.newton import NewtonSettings

    assert NewtonSettings(tol=np.float32(1e-4)).tol == np.float32(1e-4)
    for kwargs, name in [({"min_step": 0.0}, "min_step"), ({"min_step": 1.5}, "min_step"), ({"armijo": 0.0}, "armijo"),
                         ({"armijo": 0.7}, "armijo"), ({"tol": 2.0}, "tol"), ({"max_iter": 0}, "max_iter")]:
        with pytest.raises(InvalidInputError, match=name):
            NewtonSettings(**kwargs)
