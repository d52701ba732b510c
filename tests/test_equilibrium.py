"""Static equilibrium with large rotations (softbody.solve_equilibrium, issue 33), against independent truth: an
independently written corotational tet4 energy (its gradient by finite differences vanishes at the solution), the
warped dynamics brought to rest, the linear solve in the small-load limit, and rotation invariance."""
import numpy as np
import pytest

import softbody as sb
from softbody.errors import InvalidInputError, SolverError

G = np.array([0.0, 0.0, -9.81])


def cantilever(kind: str, E: float = 2e6, cells=(5, 1, 1), rotation: np.ndarray | None = None) -> sb.FemBody:
    """The soft 1.0 x 0.1 x 0.1 m beam clamped at x = 0 (its tip sags 0.13-0.53 m under gravity), optionally turned by
    ``rotation`` (3, 3) about the origin."""
    mesh = sb.box_mesh((1.0, 0.1, 0.1), cells, kind, center=(0.5, 0, 0))
    clamped = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0))
    if rotation is not None:
        mesh = sb.Mesh(mesh.nodes @ rotation.T, mesh.elements, mesh.kind)
    body = sb.FemBody(mesh, sb.LinearElastic(E, 0.3, 1000.0), damping=(8.0, 0.01))
    body.fix(clamped)
    return body


def corotational_tet4_energy(X: np.ndarray, tets: np.ndarray, E: float, nu: float):
    """Psi(x) = sum_e vol_e (mu eps:eps + lam/2 tr(eps)^2), eps the symmetric part of the displacement gradient of
    R_e^T x - X, R_e the polar rotation of F_e (by SVD): written here from the definitions, apart from softbody."""
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    Dm = np.stack([X[tets[:, k]] - X[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    Dinv = np.linalg.inv(Dm)
    vol = np.abs(np.linalg.det(Dm)) / 6
    grad = np.concatenate([-Dinv.sum(axis=1, keepdims=True), Dinv], axis=1)  # (E, 4, 3): the shape functions'

    def energy(x: np.ndarray) -> float:
        F = np.einsum("eai,eaj->eij", x[tets], grad)
        U, _, Vt = np.linalg.svd(F)
        U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
        H = np.einsum("eai,eaj->eij", np.einsum("eai,eij->eaj", x[tets], U @ Vt) - X[tets], grad)
        eps = 0.5 * (H + np.swapaxes(H, 1, 2))
        tr = np.trace(eps, axis1=1, axis2=2)
        return float(np.sum(vol * (mu * np.einsum("eij,eij->e", eps, eps) + 0.5 * lam * tr * tr)))

    return energy


def test_the_energy_equilibrium_is_stationary_for_an_independent_corotational_energy():
    body = cantilever("tet4")
    u = sb.solve_equilibrium(body, model="energy")
    X = body.rest
    assert -u[:, 2].min() > 0.1  # a large deflection: the linear answer is off by 1.2%, the rotations by 0.1 rad
    energy = corotational_tet4_energy(X, body.mesh.elements, 2e6, 0.3)
    assert energy(X + u) == pytest.approx(body.elastic_energy(X + u), rel=1e-10)
    f = body.node_mass[:, None] * G
    free = np.flatnonzero(~body.supported())
    x, h = X + u, 1e-7
    grad = np.zeros((len(free), 3))
    for a, n in enumerate(free):
        for i in range(3):
            xp, xm = x.copy(), x.copy()
            xp[n, i] += h
            xm[n, i] -= h
            grad[a, i] = (energy(xp) - energy(xm)) / (2 * h) - f[n, i]
    assert np.abs(grad).max() < 1e-5 * np.abs(f).max()


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_the_warped_equilibrium_is_where_the_warped_dynamics_come_to_rest(kind):
    body = cantilever(kind, cells=(5, 1, 1) if kind != "tet10" else (3, 1, 1))
    u = sb.solve_equilibrium(body)
    sim = sb.Simulation(body, 0.02)
    for _ in range(400):
        sim.step()
    assert np.abs(body.velocities).max() < 1e-9  # at rest
    np.testing.assert_allclose(body.positions - body.rest, u, rtol=0, atol=1e-8)
    if kind == "tet4":  # the warped force is the gradient of tet4's warped energy: both equilibria agree
        np.testing.assert_allclose(sb.solve_equilibrium(body, model="energy"), u, rtol=0, atol=1e-8)


@pytest.mark.parametrize("model", ["warped", "energy"])
def test_small_loads_give_the_linear_solution(model):
    body = cantilever("hex8")
    g = 1e-3 * G  # a tip sag of 0.3 mm: the rotations' effect is of second order
    u, lin = sb.solve_equilibrium(body, g, model=model), sb.solve_static(body, g)
    assert np.abs(u - lin).max() < 2e-3 * np.abs(lin).max()
    assert np.abs(sb.solve_equilibrium(body, model=model) - sb.solve_static(body)).max() > 0.01  # unlike full load


@pytest.mark.parametrize("model", ["warped", "energy"])
def test_equilibrium_turns_with_the_problem(model):
    c, s = np.cos(0.7), np.sin(0.7)
    Q = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    u = sb.solve_equilibrium(cantilever("hex8"), model=model)
    u_turned = sb.solve_equilibrium(cantilever("hex8", rotation=Q), Q @ G, model=model)
    np.testing.assert_allclose(u_turned, u @ Q.T, rtol=0, atol=1e-9)


def test_bad_input_and_no_convergence_are_said():
    body = cantilever("tet4")
    with pytest.raises(InvalidInputError, match="model"):
        sb.solve_equilibrium(body, model="neo-hookean")
    with pytest.raises(InvalidInputError, match="load_steps"):
        sb.solve_equilibrium(body, load_steps=0)
    with pytest.raises(SolverError, match="did not converge.*residuals"):
        sb.solve_equilibrium(body, load_steps=1, max_iter=1)
    free = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4"), sb.LinearElastic(1e5, 0.3, 1000.0))
    with pytest.raises(InvalidInputError, match="supports"):
        sb.solve_equilibrium(free)


def test_the_warped_balance_converges_where_the_cantilever_bends_far():
    """A soft hex8 cantilever sagging 65 % of its length (the warped force's fixed-point iteration diverged here):
    Newton's method on the warped force balance converges, the warped force balances the load, and the damped
    warped step settles there."""
    mesh = sb.box_mesh((1.0, 0.1, 0.1), (10, 1, 1), "hex8")
    body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), damping=(10.0, 0.01))
    x = mesh.nodes[:, 0]
    body.fix(np.flatnonzero(x < x.min() + 1e-9))
    u = sb.solve_equilibrium(body)
    assert np.abs(u[:, 2]).max() > 0.6
    free = ~body.supported()
    load = body.node_mass[:, None] * np.array([0.0, 0.0, -9.81])
    unbalanced = (body.elastic_forces(body.rest + u) + load)[free]
    assert np.abs(unbalanced).max() < 1e-6 * np.abs(load).max()
    sim = sb.Simulation(body, 0.01)
    for _ in range(300):
        sim.step()
    assert np.abs(body.positions - body.rest - u).max() < 1e-4 * np.abs(u).max()
