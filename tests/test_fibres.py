"""Fibres (issue 32, item 3): a transversely isotropic material, an isotropic matrix reinforced along a direction per
element, in the warped step, the static solve and the hyperelastic models.

Truth: a block stretched along and across its fibres (nu = 0: the end force is (E + E_f) A strain along, E A strain
across, exactly on any mesh); the warped step's assembled stiffness and rest loads against the dense sum of
R_e K_e R_e^T; the fibre turning with its element (a rotated body with rotated fibres answers rotated); the
hyperelastic fibre term's derivatives against finite differences and its small-strain limit the linear one.
"""
from __future__ import annotations

import numpy as np
import pytest

import softbody as sb
from softbody.errors import InvalidInputError
from softbody.fibres import fibre_energy


def _rotation(angle: float, axis) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_stretch_along_and_across_the_fibres(kind):
    mesh = sb.box_mesh((0.4, 0.1, 0.1), (4, 2, 2), kind)
    x = mesh.nodes[:, 0]
    near, far = np.flatnonzero(x < x.min() + 1e-9), np.flatnonzero(x > x.max() - 1e-9)
    for direction, modulus in (((1.0, 0.0, 0.0), 1e5 + 3e5), ((0.0, 2.0, 0.0), 1e5), ((0.0, 1.0, 1.0), 1e5)):
        body = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.0, 1000.0), fibres=sb.Fibres(direction, 3e5))
        body.fix(near)
        body.prescribe(far, lambda t, p=mesh.nodes[far] + [0.004, 0.0, 0.0]: p)
        u = sb.solve_static(body, (0.0, 0.0, 0.0))
        force = (body.stiffness_matrix() @ u.reshape(-1)).reshape(-1, 3)[far, 0].sum()
        if direction[2] == 0:  # along or across: a uniaxial state, exact on any mesh
            assert force == pytest.approx(modulus * 0.01 * 0.01, rel=1e-10)
        else:  # at 45 degrees across the pull: no fibre strain either (nu = 0)
            assert force == pytest.approx(1e5 * 0.01 * 0.01, rel=1e-10)
        s = body.stress(body.rest + u)
        assert np.allclose(s[:, 0], modulus * 0.01 if direction[2] == 0 else 1e5 * 0.01, rtol=1e-9)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_warped_fibre_stiffness_is_the_rotated_element_stiffness(kind, compiled, monkeypatch):
    if not compiled:  # the numpy path (the compiled kernels' loads are the isotropic parts': the fibres added apart)
        monkeypatch.setattr(sb.kernels, "ENABLED", False)
    rng = np.random.default_rng(0)
    mesh = sb.box_mesh((0.3, 0.1, 0.1), (3, 1, 1), kind)
    E = mesh.n_elements
    body = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0),
                      fibres=sb.Fibres(rng.standard_normal((E, 3)), rng.uniform(0.0, 2e5, E)))
    w = np.linalg.eigvalsh(body.Ke)
    assert w.min() > -1e-12 * w.max()  # positive semi-definite, and the translations cost nothing:
    assert np.abs(body.Ke @ np.tile(np.eye(3), (1, mesh.elements.shape[1])).T).max() < 1e-9 * w.max()
    x = body.rest + 0.05 * rng.standard_normal(body.rest.shape)
    R = body.rotations(x)
    K, load = body.warped_stiffness_upper(R)
    dense = body.pattern.assemble(body.warped_stiffness(R))
    np.testing.assert_allclose(body.stiffness_blocks(K), dense, rtol=0, atol=1e-12 * np.abs(dense).max())
    k = mesh.elements.shape[1]
    KX = (body.Ke @ body.rest[mesh.elements].reshape(E, -1)[:, :, None]).reshape(E, k, 3)
    expected = body.scatter_nodal(KX @ np.swapaxes(R, 1, 2))
    np.testing.assert_allclose(load, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_fibres_turn_with_the_body():
    """The same block and fibres turned by Q at rest: under the turned deformation, Q times the forces (warped)."""
    rng = np.random.default_rng(1)
    mesh = sb.box_mesh((0.3, 0.1, 0.1), (3, 1, 1), "hex8")
    a = rng.standard_normal((mesh.n_elements, 3))
    mat, Q = sb.LinearElastic(1e5, 0.3, 1000.0), _rotation(0.9, (1.0, 2.0, -1.0))
    body = sb.FemBody(mesh, mat, fibres=sb.Fibres(a, 2e5))
    turned = sb.FemBody(sb.Mesh(mesh.nodes @ Q.T, mesh.elements, "hex8"), mat, fibres=sb.Fibres(a @ Q.T, 2e5))
    x = mesh.nodes @ _rotation(0.5, (0, 0, 1)).T + 0.01 * rng.standard_normal(mesh.nodes.shape)
    np.testing.assert_allclose(turned.elastic_forces(x @ Q.T), body.elastic_forces(x) @ Q.T, rtol=0,
                               atol=1e-9 * np.abs(body.elastic_forces(x)).max())


def test_warped_step_settles_where_the_fibres_hold_it():
    """A cantilever with stiff fibres along it sags less; the damped warped step settles at the static solution."""
    mesh = sb.box_mesh((1.0, 0.1, 0.1), (10, 1, 1), "hex8")
    x = mesh.nodes[:, 0]
    sags = []
    for fibres in (None, sb.Fibres((1.0, 0.0, 0.0), 4e7)):
        body = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), fibres=fibres, damping=(10.0, 0.01))
        body.fix(np.flatnonzero(x < x.min() + 1e-9))
        sim = sb.Simulation(body, 0.01)
        for _ in range(300):
            sim.step()
        u = sb.solve_equilibrium(body)
        assert np.abs(body.positions - body.rest - u).max() < 1e-3 * np.abs(u).max()
        sags.append(np.abs(u[:, 2]).max())
    assert 0.15 < sags[1] / sags[0] < 0.3  # bending stiffness about E + E_f = 5 E (the fibres fill the section)


@pytest.mark.parametrize("model", ["corotated", "neo-hookean"])
def test_hyperelastic_fibres(model):
    rng = np.random.default_rng(2)
    F = np.eye(3) + 0.3 * rng.standard_normal((4, 2, 3, 3))
    a = rng.standard_normal((4, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    Ef = np.array([1e5, 2e5, 0.0, 5e4])
    psi, P, A = fibre_energy(F, a, Ef)
    h = 1e-6
    for k in range(3):
        for m in range(3):
            d = np.zeros((3, 3))
            d[k, m] = h
            p1, P1, _ = fibre_energy(F + d, a, Ef)
            p0, P0, _ = fibre_energy(F - d, a, Ef)
            assert np.abs((p1 - p0) / (2 * h) - P[..., k, m]).max() < 1e-7 * np.abs(P).max()
            assert np.abs((P1 - P0) / (2 * h) - A[..., k, m]).max() < 1e-7 * np.abs(A).max()
    mesh = sb.box_mesh((1.0, 0.1, 0.1), (6, 1, 1), "tet10")
    fibres = sb.Fibres((1.0, 0.0, 1.0), 3e6)
    bodies = [sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), model=m, fibres=fibres) for m in (model, "warped")]
    for body in bodies:
        body.fix(np.flatnonzero(mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 1e-9))
    g = (0.0, 0.0, -0.000981)  # a tip sag of 0.1 mm: the small-strain limit
    u_model, u_linear = sb.solve_equilibrium(bodies[0], g, tol=1e-6), sb.solve_static(bodies[1], g)
    assert np.abs(u_model - u_linear).max() < 2e-3 * np.abs(u_linear).max()
    x = bodies[0].rest + 0.02 * rng.standard_normal(bodies[0].rest.shape)
    d = rng.standard_normal(x.shape)
    H = bodies[0].pattern.to_csr(bodies[0].energy_hessian_blocks(x, project=False))
    dg = (bodies[0].energy_gradient(x + h * d) - bodies[0].energy_gradient(x - h * d)) / (2 * h)
    np.testing.assert_allclose(H @ d.reshape(-1), dg.reshape(-1), rtol=0, atol=1e-6 * np.abs(dg).max())


def test_bad_fibres_are_said():
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    mat = sb.LinearElastic(1e5, 0.3, 1000.0)
    with pytest.raises(InvalidInputError, match="non-zero"):
        sb.Fibres((0.0, 0.0, 0.0), 1e5)
    with pytest.raises(InvalidInputError, match="modulus"):
        sb.Fibres((1.0, 0.0, 0.0), -1.0)
    with pytest.raises(InvalidInputError, match="one per element"):
        sb.FemBody(mesh, mat, fibres=sb.Fibres(np.ones((5, 3)), 1e5))
    with pytest.raises(InvalidInputError, match="Fibres"):
        sb.FemBody(mesh, mat, fibres=(1.0, 0.0, 0.0))
    a = sb.FemBody(mesh, mat, fibres=sb.Fibres((1.0, 0.0, 0.0), 1e5))
    b = sb.FemBody(mesh, mat, fibres=sb.Fibres((1.0, 0.0, 0.0), 1e5))
    assert sb.stack_key(a) != sb.stack_key(b)  # stacked with none: their directions are their own meshes'
