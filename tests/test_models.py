"""Elastic models (issue 32): the hyperelastic laws of softbody.constitutive and the bodies made of them.

Truth: finite differences of each law's energy and stress; the isotropic elasticity tensor at rest; rotation
invariance; the nonlinear patch test (a homogeneous deformation is an equilibrium of any law on any mesh); and an
independent finite element code, scikit-fem, solving the same neo-Hookean cantilever with its own assembly and its
own form of the tangent (the cofactor's derivative as d(J F^-T), not the Levi-Civita contraction).
"""
from __future__ import annotations

import numpy as np
import pytest

import softbody as sb
from softbody.constitutive import LAWS, project_spd
from softbody.errors import InvalidInputError

LAM, MU = 2.0e5, 1.0e5
HYPER = ("corotated", "neo-hookean")
MODELS = ("warped", "linear") + HYPER


def _rotation(angle: float, axis) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _fd(fun, F: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of fun (..., [3, 3]) by F (n, 3, 3): (n, [3, 3,] 3, 3)."""
    cols = []
    for k in range(3):
        for m in range(3):
            d = np.zeros((3, 3))
            d[k, m] = h
            cols.append((fun(F + d) - fun(F - d)) / (2 * h))
    out = np.stack(cols, axis=-1)
    return out.reshape(out.shape[:-1] + (3, 3))


@pytest.mark.parametrize("name", sorted(LAWS))
def test_law_stress_and_tangent_are_the_derivatives(name):
    law = LAWS[name]
    F = np.eye(3) + 0.3 * np.random.default_rng(1).standard_normal((20, 3, 3))
    P, A = law.stress(F, LAM, MU), law.tangent(F, LAM, MU)
    assert np.abs(P - _fd(lambda G: law.energy(G, LAM, MU), F)).max() < 1e-8 * np.abs(P).max()
    assert np.abs(A - _fd(lambda G: law.stress(G, LAM, MU), F)).max() < 1e-8 * np.abs(A).max()


@pytest.mark.parametrize("name", sorted(LAWS))
def test_law_at_rest_is_the_linear_material(name):
    law = LAWS[name]
    I = np.eye(3)[None]
    d = np.eye(3)
    C = MU * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)) + LAM * np.einsum("ij,kl->ijkl", d, d)
    assert abs(law.energy(I, LAM, MU)[0]) < 1e-9 * MU
    assert np.abs(law.stress(I, LAM, MU)).max() < 1e-9 * MU
    np.testing.assert_allclose(law.tangent(I, LAM, MU)[0], C, rtol=0, atol=1e-9 * MU)


@pytest.mark.parametrize("name", HYPER)
def test_invariant_laws_turn_with_the_body_and_survive_inversion(name):
    law = LAWS[name]
    rng = np.random.default_rng(2)
    F = np.eye(3) + 0.3 * rng.standard_normal((10, 3, 3))
    Q = _rotation(1.1, (1.0, -2.0, 0.5))
    np.testing.assert_allclose(law.energy(Q @ F, LAM, MU), law.energy(F, LAM, MU), rtol=1e-10, atol=1e-6)
    np.testing.assert_allclose(law.stress(Q @ F, LAM, MU), Q @ law.stress(F, LAM, MU), rtol=0, atol=1e-7 * MU)
    np.testing.assert_allclose(law.stress(Q[None], LAM, MU), 0.0, atol=1e-9 * MU)  # a rigid turn stores nothing
    inverted = F * np.array([-1.0, 1.0, 1.0])  # det F < 0: an element turned inside out
    flat = F.copy()
    flat[:, :, 2] = 0.0  # flattened to a plane: det F = 0
    for G in (inverted, flat):
        assert np.isfinite(law.energy(G, LAM, MU)).all() and np.isfinite(law.tangent(G, LAM, MU)).all()
    P = law.stress(inverted, LAM, MU)  # and its derivatives hold there too
    assert np.abs(P - _fd(lambda G: law.energy(G, LAM, MU), inverted)).max() < 1e-8 * np.abs(P).max()
    A = law.tangent(inverted, LAM, MU)
    assert np.abs(A - _fd(lambda G: law.stress(G, LAM, MU), inverted)).max() < 1e-8 * np.abs(A).max()


def test_projection_keeps_positive_tangents_and_removes_negative_directions():
    F = np.eye(3) + 0.5 * np.random.default_rng(3).standard_normal((50, 3, 3))
    A = LAWS["neo-hookean"].tangent(F, LAM, MU)
    P = project_spd(A).reshape(-1, 9, 9)
    lam_A = np.linalg.eigvalsh(0.5 * (A.reshape(-1, 9, 9) + np.swapaxes(A.reshape(-1, 9, 9), 1, 2)))
    lam_P = np.linalg.eigvalsh(P)
    assert lam_A.min() < 0 and lam_P.min() > -1e-9 * MU
    np.testing.assert_allclose(lam_P, np.maximum(lam_A, 0.0), atol=1e-8 * MU)


def _body(kind: str, model: str, cells=(3, 2, 2), size=(0.3, 0.2, 0.2), **kw) -> sb.FemBody:
    return sb.FemBody(sb.box_mesh(size, cells, kind), sb.LinearElastic(2.6e5, 0.3, 1000.0), model=model, **kw)


@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
@pytest.mark.parametrize("model", MODELS)
def test_body_energy_gradient_and_hessian_agree(kind, model):
    """Every model: no force at rest; none under a rigid motion (the linear model: a translation only); the gradient
    the finite difference of the energy, the Hessian that of the gradient."""
    body = _body(kind, model)
    X = body.rest
    assert np.abs(body.energy_gradient(X)).max() < 1e-9 * MU * 0.01
    Q = _rotation(0.8, (0.3, 1.0, -0.4)) if model != "linear" else np.eye(3)
    rigid = X @ Q.T + np.array([0.4, -1.0, 2.0])
    assert np.abs(body.energy_gradient(rigid)).max() < 1e-8 * MU * 0.01
    assert abs(body.elastic_energy(rigid)) < 1e-10 * MU * 0.01
    rng = np.random.default_rng(4)
    x = X @ _rotation(0.5, (1, 1, 0)).T + 0.02 * rng.standard_normal(X.shape)
    g = body.energy_gradient(x)
    d = rng.standard_normal(X.shape)
    h = 1e-6
    slope = (body.elastic_energy(x + h * d) - body.elastic_energy(x - h * d)) / (2 * h)
    assert abs(slope - np.sum(g * d)) < 1e-6 * np.abs(g).sum() * np.abs(d).max()
    if model in HYPER:  # the analytic Hessian (the warped models' is itself a difference of gradients)
        H = body.pattern.to_csr(body.energy_hessian_blocks(x, project=False))
        dg = (body.energy_gradient(x + h * d) - body.energy_gradient(x - h * d)) / (2 * h)
        np.testing.assert_allclose(H @ d.reshape(-1), dg.reshape(-1), rtol=0, atol=1e-6 * np.abs(dg).max())


@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
@pytest.mark.parametrize("model", HYPER)
def test_nonlinear_patch_test(kind, model):
    """A homogeneous deformation x = F0 X (stretch, shear and a turn, 20-30 %) held on the boundary: every interior
    node settles on it, on a distorted mesh, and the energy is the volume times psi(F0)."""
    base = sb.box_mesh((0.3, 0.2, 0.2), (3, 3, 3), "hex8" if kind == "hex8" else "tet4")
    nodes = base.nodes.copy()
    lo, hi = nodes.min(axis=0) + 1e-9, nodes.max(axis=0) - 1e-9
    inside = np.all((nodes > lo) & (nodes < hi), axis=1)
    nodes[inside] += 0.015 * np.random.default_rng(5).uniform(-1, 1, (int(inside.sum()), 3))
    mesh = sb.Mesh(nodes, base.elements, base.kind)
    if kind == "tet10":  # its mid-edge nodes on the distorted edges' midpoints
        mesh = sb.to_tet10(mesh)
    interior = np.all((mesh.nodes > lo) & (mesh.nodes < hi), axis=1)
    body = sb.FemBody(mesh, sb.LinearElastic(2.6e5, 0.3, 1000.0), model=model)
    F0 = _rotation(0.4, (0, 0, 1)) @ np.array([[1.25, 0.15, 0.0], [0.0, 0.85, 0.1], [0.05, 0.0, 0.9]])
    target = mesh.nodes @ F0.T
    boundary = np.flatnonzero(~interior)
    body.prescribe(boundary, lambda t, p=target[boundary]: p)
    u = sb.solve_equilibrium(body, gravity=(0, 0, 0), tol=1e-11)
    np.testing.assert_allclose(mesh.nodes + u, target, rtol=0, atol=1e-9)
    lam, mu = body.material.lame
    psi = float(LAWS[model].energy(F0[None], lam, mu)[0])
    assert body.elastic_energy(mesh.nodes + u) == pytest.approx(0.3 * 0.2 * 0.2 * psi, rel=1e-9)


def _skfem_cantilever(mesh: sb.Mesh, E: float, nu: float, rho: float, load_steps: int = 2) -> np.ndarray:
    """The static displacements (N, 3) of the stable neo-Hookean cantilever (clamped at x = 0, its weight) by
    scikit-fem on the same mesh and quadrature: its own assembly, Newton's method with its own tangent."""
    skfem = pytest.importorskip("skfem")
    from scipy.spatial import cKDTree
    from skfem.helpers import ddot, det, grad, inv, mul, transpose

    from softbody.elements import tet10_stiffness_rule

    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    mu_s, lam_s = 4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu  # Smith et al. 2018, eq. 14 and section 3.4
    a = 1.0 + mu / lam_s
    eye = np.eye(3)[:, :, None, None]

    def kinematics(u):
        F = grad(u) + eye
        return F, ddot(F, F), det(F), transpose(inv(F))

    @skfem.LinearForm
    def internal(v, w):
        F, Ic, J, Fit = kinematics(w["u"])
        return ddot(mu_s * (1 - 1 / (Ic + 1)) * F + lam_s * (J - a) * J * Fit, grad(v))

    @skfem.BilinearForm
    def tangent(du, v, w):
        F, Ic, J, Fit = kinematics(w["u"])
        dF = grad(du)
        dJ = ddot(J * Fit, dF)
        dC = dJ * Fit - J * mul(mul(Fit, transpose(dF)), Fit)  # d(J F^-T)
        dP = (mu_s * (1 - 1 / (Ic + 1)) * dF + 2 * mu_s / (Ic + 1) ** 2 * ddot(F, dF) * F + lam_s * dJ * J * Fit
              + lam_s * (J - a) * dC)
        return ddot(dP, grad(v))

    @skfem.LinearForm
    def weight(v, w):
        return -rho * 9.81 * v[2]

    corners = np.unique(mesh.elements[:, :4])
    index = -np.ones(mesh.n_nodes, int)
    index[corners] = np.arange(len(corners))
    m = skfem.MeshTet(mesh.nodes[corners].T.copy(), index[mesh.elements[:, :4]].T.copy())
    if mesh.kind == "tet10":
        xi, wq = tet10_stiffness_rule()
        basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP2()), quadrature=(xi.T.copy(), wq))
        per_node = np.stack([np.concatenate([basis.nodal_dofs[c], basis.edge_dofs[c]]) for c in range(3)], axis=1)
    else:
        basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
        per_node = basis.nodal_dofs.T
    _, at = cKDTree(basis.doflocs[:, per_node[:, 0]].T).query(mesh.nodes)
    dofs = per_node[at]  # (N, 3): scikit-fem's degrees of freedom of each of our nodes
    f = skfem.asm(weight, basis)
    fixed = dofs[mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 1e-9].ravel()
    u = np.zeros(basis.N)
    for k in range(1, load_steps + 1):
        for _ in range(30):
            uw = basis.interpolate(u)
            r = skfem.asm(internal, basis, u=uw) - k / load_steps * f
            du = skfem.solve(*skfem.condense(skfem.asm(tangent, basis, u=uw), -r, D=fixed))
            u += du
            if np.abs(du).max() < 1e-13:
                break
    return u[dofs]


@pytest.mark.parametrize("kind,cells", [("tet4", (10, 1, 1)), ("tet10", (4, 1, 1))])
def test_neo_hookean_cantilever_equals_scikit_fem(kind, cells):
    mesh = sb.box_mesh((1.0, 0.1, 0.1), cells, kind)
    body = sb.FemBody(mesh, sb.LinearElastic(2e6, 0.3, 1000.0), model="neo-hookean")
    body.fix(np.flatnonzero(mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 1e-9))
    ours = sb.solve_equilibrium(body, tol=1e-10, max_iter=80)
    reference = _skfem_cantilever(mesh, 2e6, 0.3, 1000.0)
    tip = np.abs(reference[:, 2]).max()
    assert tip > 0.2  # large: a quarter of the length, where the small-strain solve is off by 3 %
    assert np.abs(sb.solve_static(body)[:, 2]).max() > 1.02 * tip
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-8 * tip)


@pytest.mark.parametrize("scheme", ["newton", "bdf2"])
@pytest.mark.parametrize("model", HYPER)
def test_damped_steps_settle_at_the_models_equilibrium(scheme, model):
    mesh = sb.box_mesh((1.0, 0.1, 0.1), (8, 1, 1), "tet4")
    body = sb.FemBody(mesh, sb.LinearElastic(3e6, 0.3, 1000.0), model=model, damping=(10.0, 0.01))
    body.fix(np.flatnonzero(mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 1e-9))
    sim = sb.Simulation(body, 0.01, scheme=scheme)
    for _ in range(250):
        sim.step()
    u = sb.solve_equilibrium(body, tol=1e-10)
    assert np.abs(body.positions - body.rest - u).max() < 1e-3 * np.abs(u).max()
    assert np.abs(u[:, 2]).max() > 0.05


@pytest.mark.parametrize("model", HYPER)
def test_free_spin_keeps_its_shape(model):
    """An undamped stiff cube spinning at 2 rev/s under the Newton scheme: no stretch (the centrifugal one is below
    1e-5), and the angular momentum the warped model keeps under the same scheme (the scheme's own dissipation)."""
    def spin(name):
        body = sb.FemBody(sb.box_mesh((0.3, 0.2, 0.2), (3, 2, 2), "tet4"), sb.LinearElastic(1e8, 0.3, 1000.0),
                          model=name, damping=(0.0, 0.0))
        w = np.array([0.3, 0.0, 4 * np.pi])
        body.velocities = np.cross(w, body.rest - body.rest.mean(axis=0))
        sim = sb.Simulation(body, 0.005, gravity=(0, 0, 0), scheme="newton")
        for _ in range(50):
            sim.step()
        r = body.positions - body.positions.mean(axis=0)
        m = body.node_mass
        return r, m @ np.cross(r, body.velocities)

    def distances(x):
        return np.linalg.norm(x[:, None] - x[None], axis=2)

    d_rest = distances(sb.box_mesh((0.3, 0.2, 0.2), (3, 2, 2), "tet4").nodes)
    (r, L), (r_warped, L_warped) = spin(model), spin("warped")
    for x in (r, r_warped):
        assert np.abs(distances(x) - d_rest).max() < 1e-4 * d_rest.max()
    assert np.linalg.norm(L) > 0.5 * np.linalg.norm(L_warped)
    np.testing.assert_allclose(L, L_warped, rtol=1e-3, atol=1e-3 * np.linalg.norm(L_warped))


def test_models_are_chosen_by_name_and_bad_choices_are_said():
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    mat = sb.LinearElastic(1e5, 0.3, 1000.0)
    assert sb.FemBody(mesh, mat).model == "warped" and sb.FemBody(mesh, mat, warping=False).model == "linear"
    assert not sb.FemBody(mesh, mat, model="linear").warping
    with pytest.raises(InvalidInputError, match="model must be one of"):
        sb.FemBody(mesh, mat, model="mooney")
    with pytest.raises(InvalidInputError, match="warping=False"):
        sb.FemBody(mesh, mat, warping=False, model="neo-hookean")
    with pytest.raises(InvalidInputError, match="B-bar"):
        sb.FemBody(mesh, mat, model="neo-hookean", volumetric="mean")
    body = sb.FemBody(mesh, mat, model="neo-hookean")
    with pytest.raises(InvalidInputError, match="scheme='newton'"):
        sb.Simulation(body, 0.01)
    with pytest.raises(InvalidInputError, match="model='energy'"):
        sb.solve_equilibrium(body, model="warped")


def test_stress_and_strain_of_a_homogeneous_deformation():
    """Under x = F0 X every element centre has the Green strain (F0^T F0 - I) / 2 and the Cauchy stress of the
    traction on a cut: sigma n da = P N dA (Nanson), both in Voigt order (xx, yy, zz, xy, yz, zx)."""
    body = _body("hex8", "neo-hookean")
    F0 = np.array([[1.3, 0.2, 0.0], [0.05, 0.9, 0.1], [0.0, -0.1, 0.95]])
    x = body.rest @ F0.T
    lam, mu = body.material.lame
    P = LAWS["neo-hookean"].stress(F0[None], lam, mu)[0]
    J = np.linalg.det(F0)
    order = ([0, 1, 2, 0, 1, 2], [0, 1, 2, 1, 2, 0])
    for N in np.eye(3):  # a cut of normal N at rest: n da = J F0^-T N dA
        nda = J * np.linalg.solve(F0.T, N)
        sigma = body.stress(x)[0]
        S = np.zeros((3, 3))
        S[order] = sigma
        S[order[1], order[0]] = sigma
        np.testing.assert_allclose(S @ nda, P @ N, rtol=1e-10, atol=1e-10 * np.abs(P).max())
    green = 0.5 * (F0.T @ F0 - np.eye(3))
    expected = green[order] * np.array([1, 1, 1, 2, 2, 2])
    np.testing.assert_allclose(body.strain(x), np.broadcast_to(expected, (body.mesh.n_elements, 6)), atol=1e-12)


def test_regions_of_a_hyperelastic_model_sum_their_energies():
    """Two regions under a homogeneous deformation: the energy is each region's volume times its own psi(F0)."""
    mesh = sb.box_mesh((0.3, 0.2, 0.2), (4, 2, 2), "tet10")
    soft, stiff = sb.LinearElastic(1e5, 0.3, 1000.0), sb.LinearElastic(4e5, 0.45, 1200.0)
    labels = (mesh.nodes[mesh.elements].mean(axis=1)[:, 0] > 0).astype(int)
    body = sb.FemBody(mesh, sb.Regions([soft, stiff], labels), model="neo-hookean")
    F0 = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.0], [0.0, 0.05, 1.1]])
    psi = [float(LAWS["neo-hookean"].energy(F0[None], *m.lame)[0]) for m in (soft, stiff)]
    volume = [body.volumes[labels == r].sum() for r in (0, 1)]
    assert body.elastic_energy(mesh.nodes @ F0.T) == pytest.approx(volume[0] * psi[0] + volume[1] * psi[1], rel=1e-10)


def test_appended_bodies_are_refused_by_the_warped_step_too():
    sim = sb.Simulation([], 0.01)
    sim.bodies.append(_body("tet4", "corotated"))
    with pytest.raises(InvalidInputError, match="scheme='newton'"):
        sim.step()


def test_locking_warning_names_what_a_hyperelastic_body_can_take():
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    with pytest.warns(sb.LockingWarning) as caught:
        sb.FemBody(mesh, sb.LinearElastic(1e5, 0.45, 1000.0), model="neo-hookean")
    text = str(caught[0].message)
    assert "tet10" in text and "volumetric" not in text  # B-bar is the linear models' only
    with pytest.warns(sb.LockingWarning, match="volumetric='mean'"):
        sb.FemBody(mesh, sb.LinearElastic(1e5, 0.45, 1000.0))
