"""Element matrices of tet4 / hex8 / tet10 against analytic truth.

Stiffness: symmetry, the 6 rigid-body modes as exact null space, the patch test, and element matrices
recomputed here from first principles (closed form for tet4, a plainly written 2x2x2 Gauss rule for
the hex8 cube, a high-order collapsed Gauss rule for tet10). Mass: total mass, positivity, and the
element matrices against closed forms / exact quadrature.
"""
from __future__ import annotations

import numpy as np
import pytest

import softbody
from conftest import (KINDS, TET10_EDGES_SPEC, box_boundary_mask, dense, distorted_box, elasticity_matrix,
                      lame, rigid_modes, voigt_strain)

E, NU, RHO = 2.0e6, 0.3, 1200.0
SIZE = np.array([1.0, 0.8, 0.6])
MAT = softbody.LinearElastic(E, NU, RHO)


@pytest.fixture(scope="module", params=KINDS)
def distorted(request):
    kind = request.param
    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=1)
    return kind, mesh


# ---------------------------------------------------------------------------- stiffness: global properties

def test_distorted_mesh_is_really_distorted(distorted):
    kind, mesh = distorted
    regular = softbody.box_mesh(SIZE, (2, 2, 2), kind)
    assert mesh.nodes.shape == regular.nodes.shape
    assert np.abs(mesh.nodes - regular.nodes).max() > 0.02  # interior nodes moved


def test_stiffness_symmetric(distorted):
    kind, mesh = distorted
    K = dense(softbody.FemBody(mesh, MAT).stiffness_matrix())
    assert K.shape == (3 * mesh.n_nodes, 3 * mesh.n_nodes)
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()


def test_stiffness_null_space_is_the_six_rigid_modes(distorted):
    kind, mesh = distorted
    K = dense(softbody.FemBody(mesh, MAT).stiffness_matrix())
    lam = np.linalg.eigvalsh(K)
    rel = lam / lam.max()
    # exactly six zero eigenvalues, a clear gap to the seventh, none negative
    assert np.all(np.abs(rel[:6]) < 1e-11), rel[:8]
    assert rel[6] > 1e-5, rel[:8]
    assert rel.min() > -1e-11
    # ... and the rigid modes lie in the null space; they are 6 independent vectors, so they span it
    modes = rigid_modes(mesh.nodes)
    assert np.linalg.matrix_rank(modes) == 6
    for m in modes:
        assert np.linalg.norm(K @ m) <= 1e-11 * np.linalg.norm(K, 2) * np.linalg.norm(m)


def test_stiffness_matrix_is_rest_matrix_regardless_of_warping(distorted):
    kind, mesh = distorted
    Kw = dense(softbody.FemBody(mesh, MAT, warping=True).stiffness_matrix())
    Kl = dense(softbody.FemBody(mesh, MAT, warping=False).stiffness_matrix())
    np.testing.assert_allclose(Kw, Kl, rtol=0, atol=1e-12 * np.abs(Kl).max())


# ---------------------------------------------------------------------------- mass: global properties

@pytest.mark.parametrize("mass", ["consistent", "lumped"])
def test_total_mass_is_density_times_volume(distorted, mass):
    kind, mesh = distorted
    M = dense(softbody.FemBody(mesh, MAT, mass=mass).mass_matrix())
    total = RHO * np.prod(SIZE)  # interior distortion keeps the box volume
    for d in range(3):
        t = np.zeros((mesh.n_nodes, 3))
        t[:, d] = 1.0
        t = t.ravel()
        assert t @ M @ t == pytest.approx(total, rel=1e-12)
        # the unit translation in d produces momentum only in d
        Mt = (M @ t).reshape(-1, 3)
        np.testing.assert_allclose(Mt.sum(axis=0), total * np.eye(3)[d], rtol=0, atol=1e-12 * total)


def test_lumped_mass_is_diagonal_and_positive(distorted):
    kind, mesh = distorted
    M = dense(softbody.FemBody(mesh, MAT, mass="lumped").mass_matrix())
    assert np.count_nonzero(M - np.diag(np.diag(M))) == 0
    assert np.diag(M).min() > 0
    # the three components of a node carry the same mass
    d = np.diag(M).reshape(-1, 3)
    np.testing.assert_array_equal(d[:, 0], d[:, 1])
    np.testing.assert_array_equal(d[:, 0], d[:, 2])


def test_consistent_mass_positive_definite_and_symmetric(distorted):
    kind, mesh = distorted
    M = dense(softbody.FemBody(mesh, MAT, mass="consistent").mass_matrix())
    assert np.abs(M - M.T).max() <= 1e-14 * np.abs(M).max()
    lam = np.linalg.eigvalsh(M)
    assert lam.min() > 1e-6 * lam.max(), (lam.min(), lam.max())


# ---------------------------------------------------------------------------- patch test

def _affine_field(seed: int, scale: float):
    rng = np.random.default_rng(seed)
    A = scale * rng.uniform(-1, 1, (3, 3))
    c = rng.uniform(-1, 1, 3)
    return A, c


def _interior(mesh):
    return ~box_boundary_mask(mesh.nodes, -SIZE / 2, SIZE / 2)


def test_patch_test_linear(distorted):
    """u = A X + c: exact constant strain and stress in every element, zero force on interior nodes."""
    kind, mesh = distorted
    body = softbody.FemBody(mesh, MAT, warping=False)
    A, c = _affine_field(7, 1e-2)
    u = mesh.nodes @ A.T + c
    x = mesh.nodes + u
    eps = voigt_strain(A)
    np.testing.assert_allclose(body.strain(x), np.broadcast_to(eps, (mesh.n_elements, 6)),
                               rtol=0, atol=1e-12 * np.abs(eps).max())
    sig = elasticity_matrix(E, NU) @ eps
    np.testing.assert_allclose(body.stress(x), np.broadcast_to(sig, (mesh.n_elements, 6)),
                               rtol=0, atol=1e-11 * np.abs(sig).max())
    # K u is zero on interior nodes (the patch); on the boundary it is the traction, which sums to zero
    K = body.stiffness_matrix()
    f = (K @ u.ravel()).reshape(-1, 3)
    inner = _interior(mesh)
    assert inner.sum() >= 1
    scale = np.abs(f).max()
    assert scale > 0
    assert np.abs(f[inner]).max() <= 1e-10 * scale
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-10 * scale)
    # elastic_forces without warping is -K u
    np.testing.assert_allclose(body.elastic_forces(x), -f, rtol=0, atol=1e-10 * scale)


def test_patch_test_boundary_forces_carry_the_stress(distorted):
    """The nodal forces of the patch test are the consistent loads of the constant stress sigma:
    sum_a f_a X_a^T = integral of sigma dV = sigma * V (since sum_a X_a grad N_a^T = I)."""
    kind, mesh = distorted
    body = softbody.FemBody(mesh, MAT, warping=False)
    A, c = _affine_field(3, 1e-3)
    u = mesh.nodes @ A.T + c
    f = (body.stiffness_matrix() @ u.ravel()).reshape(-1, 3)
    s = elasticity_matrix(E, NU) @ voigt_strain(A)
    sig = np.array([[s[0], s[3], s[5]], [s[3], s[1], s[4]], [s[5], s[4], s[2]]])
    np.testing.assert_allclose(f.T @ mesh.nodes, sig * np.prod(SIZE), rtol=0, atol=1e-9 * np.abs(sig).max())


@pytest.mark.parametrize("scale", [1e-4, 0.3])
def test_patch_test_warped(distorted, scale):
    """With warping, an affine deformation x = F X + c (F = I + A) is unrotated by F's polar rotation R: the
    element strain is sym(P - I) with P = R^T F, and interior nodes feel no force, for any A."""
    kind, mesh = distorted
    for hex_rotation in (["average", "single"] if kind == "hex8" else ["average"]):
        _check_warped_patch(mesh, scale, hex_rotation)


def _check_warped_patch(mesh, scale, hex_rotation):
    body = softbody.FemBody(mesh, MAT, warping=True, hex_rotation=hex_rotation)
    A, c = _affine_field(11, scale)
    F = np.eye(3) + A
    assert np.linalg.det(F) > 0
    x = mesh.nodes @ F.T + c
    # polar decomposition computed independently: P = sqrt(F^T F), R = F P^-1
    w, V = np.linalg.eigh(F.T @ F)
    P = V @ np.diag(np.sqrt(w)) @ V.T
    R = F @ np.linalg.inv(P)
    np.testing.assert_allclose(body.rotations(x), np.broadcast_to(R, (mesh.n_elements, 3, 3)), atol=1e-12)
    eps = voigt_strain(P - np.eye(3))
    # round-off: strain is a difference of O(1 m) coordinates over O(0.3 m) elements, so ~1e-15 absolute
    np.testing.assert_allclose(body.strain(x), np.broadcast_to(eps, (mesh.n_elements, 6)),
                               rtol=0, atol=1e-11 * np.abs(eps).max() + 1e-13)
    f = body.elastic_forces(x)
    inner = _interior(mesh)
    scale_f = np.abs(f).max()
    assert scale_f > 0
    assert np.abs(f[inner]).max() <= 1e-10 * scale_f
    if scale < 1e-3:  # small A: the warped force is the linear one to first order
        f_lin = -(body.stiffness_matrix() @ (x - mesh.nodes).ravel()).reshape(-1, 3)
        assert np.abs(f - f_lin).max() <= 1e-2 * scale_f


# ---------------------------------------------------------------------------- element matrices from first principles

def _single(kind_nodes, elems, kind, material=MAT, **kw):
    mesh = softbody.Mesh(kind_nodes, elems, kind)
    return mesh, softbody.FemBody(mesh, material, **kw)


def _random_tet(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    while True:
        X = rng.uniform(-1, 1, (4, 3))
        d = np.linalg.det(np.column_stack([X[1] - X[0], X[2] - X[0], X[3] - X[0]]))
        if abs(d) > 0.2:
            if d < 0:
                X[[1, 2]] = X[[2, 1]]
            return X


def _barycentric_gradients(X: np.ndarray) -> tuple[np.ndarray, float]:
    """Gradients g_a (4, 3) of the barycentric coordinates of tet X and its volume."""
    T = np.vstack([np.ones(4), X.T])  # [1; x; y; z] = T L
    Tinv = np.linalg.inv(T)  # L = Tinv [1; x; y; z]
    return Tinv[:, 1:], np.linalg.det(T) / 6.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tet4_stiffness_closed_form(seed):
    X = _random_tet(seed)
    mesh, body = _single(X, [[0, 1, 2, 3]], "tet4")
    g, V = _barycentric_gradients(X)
    assert V > 0
    lam, mu = lame(E, NU)
    K = np.zeros((12, 12))
    for a in range(4):
        for b in range(4):
            K[3 * a:3 * a + 3, 3 * b:3 * b + 3] = V * (lam * np.outer(g[a], g[b]) + mu * np.outer(g[b], g[a])
                                                       + mu * (g[a] @ g[b]) * np.eye(3))
    Kb = dense(body.stiffness_matrix())
    np.testing.assert_allclose(Kb, K, rtol=0, atol=1e-12 * np.abs(K).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_tet4_mass_closed_form(seed):
    X = _random_tet(seed)
    mesh, body = _single(X, [[0, 1, 2, 3]], "tet4")
    _, V = _barycentric_gradients(X)
    m = RHO * V / 20.0 * (np.ones((4, 4)) + np.eye(4))  # integral of L_a L_b = V (1 + delta_ab) / 20
    np.testing.assert_allclose(dense(body.mass_matrix()), np.kron(m, np.eye(3)), rtol=1e-13, atol=0)
    ml = dense(softbody.FemBody(mesh, MAT, mass="lumped").mass_matrix())
    np.testing.assert_allclose(ml, np.eye(12) * RHO * V / 4, rtol=1e-13)


def _hex_corner_signs():
    return np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)


def _hex8_stiffness_plain(a: float, b: float, c: float, npts: int) -> np.ndarray:
    """B^T D B of a rectangular brick [0,a]x[0,b]x[0,c] with an npts^3 Gauss rule, written out plainly."""
    s = _hex_corner_signs()
    x1, w1 = np.polynomial.legendre.leggauss(npts)
    D = elasticity_matrix(E, NU)
    K = np.zeros((24, 24))
    for i in range(npts):
        for j in range(npts):
            for k in range(npts):
                r, t, z = x1[i], x1[j], x1[k]
                w = w1[i] * w1[j] * w1[k]
                B = np.zeros((6, 24))
                for n in range(8):
                    # dN/dr etc. of N = (1 + s0 r)(1 + s1 t)(1 + s2 z) / 8; dr/dx = 2/a, ...
                    dx = s[n, 0] * (1 + s[n, 1] * t) * (1 + s[n, 2] * z) / 8 * 2 / a
                    dy = s[n, 1] * (1 + s[n, 0] * r) * (1 + s[n, 2] * z) / 8 * 2 / b
                    dz = s[n, 2] * (1 + s[n, 0] * r) * (1 + s[n, 1] * t) / 8 * 2 / c
                    B[0, 3 * n] = dx
                    B[1, 3 * n + 1] = dy
                    B[2, 3 * n + 2] = dz
                    B[3, 3 * n], B[3, 3 * n + 1] = dy, dx
                    B[4, 3 * n + 1], B[4, 3 * n + 2] = dz, dy
                    B[5, 3 * n], B[5, 3 * n + 2] = dz, dx
                K += B.T @ D @ B * w * (a * b * c / 8)
    return K


@pytest.mark.parametrize("dims", [(1.0, 1.0, 1.0), (1.0, 2.0, 0.5)])
def test_hex8_brick_stiffness_plain_gauss(dims):
    a, b, c = dims
    X = (_hex_corner_signs() + 1) / 2 * np.array(dims)
    mesh, body = _single(X, [list(range(8))], "hex8")
    K = _hex8_stiffness_plain(a, b, c, 2)
    # the integrand is quadratic per direction on a brick, so 2x2x2 Gauss is exact: a 4x4x4 rule agrees
    np.testing.assert_allclose(_hex8_stiffness_plain(a, b, c, 4), K, rtol=0, atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(dense(body.stiffness_matrix()), K, rtol=0, atol=1e-12 * np.abs(K).max())


def test_hex8_unit_cube_known_entries():
    """Two entries of the unit cube stiffness known in closed form: K_00 = (lam + 2mu)/9 + 2 mu/9 = (lam + 4 mu)/9
    for a corner's own x-dof, and the sum of a row is zero."""
    X = (_hex_corner_signs() + 1) / 2
    _, body = _single(X, [list(range(8))], "hex8")
    K = dense(body.stiffness_matrix())
    lam, mu = lame(E, NU)
    # diagonal: integral over the unit cube of (lam+2mu) (dN/dx)^2 + mu (dN/dy)^2 + mu (dN/dz)^2, each integral 1/9
    assert K[0, 0] == pytest.approx((lam + 2 * mu) / 9 + 2 * mu / 9, rel=1e-13)
    np.testing.assert_allclose(K.sum(axis=1), 0.0, atol=1e-12 * K[0, 0])


def test_hex8_cube_mass_tensor_product():
    """Consistent mass of a brick = rho * (1D mass matrices h/6 [[2,1],[1,2]]) tensor product."""
    dims = np.array([0.5, 1.0, 2.0])
    s = _hex_corner_signs()
    X = (s + 1) / 2 * dims
    mesh, body = _single(X, [list(range(8))], "hex8")
    m = np.zeros((8, 8))
    for p in range(8):
        for q in range(8):
            v = RHO
            for d in range(3):
                v *= dims[d] / 6 * (2 if s[p, d] == s[q, d] else 1)
            m[p, q] = v
    np.testing.assert_allclose(dense(body.mass_matrix()), np.kron(m, np.eye(3)), rtol=1e-13)
    ml = dense(softbody.FemBody(mesh, MAT, mass="lumped").mass_matrix())
    np.testing.assert_allclose(np.diag(ml), RHO * np.prod(dims) / 8, rtol=1e-13)


def _collapsed_gauss(n: int):
    """Points (q, 3) and weights of the unit tetrahedron {xi >= 0, sum xi <= 1} from Gauss-Legendre on the
    cube through the Duffy collapse xi1 = u, xi2 = v (1-u), xi3 = w (1-u)(1-v), Jacobian (1-u)^2 (1-v)."""
    t, w = np.polynomial.legendre.leggauss(n)
    t, w = (t + 1) / 2, w / 2
    pts, wts = [], []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                u, v, s = t[i], t[j], t[k]
                pts.append([u, v * (1 - u), s * (1 - u) * (1 - v)])
                wts.append(w[i] * w[j] * w[k] * (1 - u) ** 2 * (1 - v))
    return np.array(pts), np.array(wts)


def test_collapsed_gauss_rule_sanity():
    pts, wts = _collapsed_gauss(4)
    assert wts.sum() == pytest.approx(1 / 6, rel=1e-14)
    # integral of xi1^2 xi2 over the unit tet = 2! 1! / 6! ... = 2 * 1 / 720 * ... (Dirichlet formula)
    # int L1^a L2^b L3^c L0^d = a! b! c! d! 3! / (a+b+c+d+3)! * vol; vol = 1/6
    assert np.sum(wts * pts[:, 0] ** 2 * pts[:, 1]) == pytest.approx(2 * 1 * 6 / 720 / 6, rel=1e-13)


def _tet10_matrices_highorder(X10: np.ndarray, n: int = 4):
    """Stiffness (30, 30) and scalar mass (10, 10) of a straight-sided tet10 by my own quadratic shape
    functions in barycentric coordinates and a high-order collapsed Gauss rule."""
    g, V = _barycentric_gradients(X10[:4])
    pts, wts = _collapsed_gauss(n)
    D = elasticity_matrix(E, NU)
    K = np.zeros((30, 30))
    M = np.zeros((10, 10))
    for xi, w in zip(pts, wts):
        L = np.array([1 - xi.sum(), xi[0], xi[1], xi[2]])
        N = [L[i] * (2 * L[i] - 1) for i in range(4)] + [4 * L[i] * L[j] for i, j in TET10_EDGES_SPEC]
        G = [(4 * L[i] - 1) * g[i] for i in range(4)] + [4 * (L[i] * g[j] + L[j] * g[i]) for i, j in TET10_EDGES_SPEC]
        B = np.zeros((6, 30))
        for a, (gx, gy, gz) in enumerate(G):
            B[0, 3 * a], B[1, 3 * a + 1], B[2, 3 * a + 2] = gx, gy, gz
            B[3, 3 * a], B[3, 3 * a + 1] = gy, gx
            B[4, 3 * a + 1], B[4, 3 * a + 2] = gz, gy
            B[5, 3 * a], B[5, 3 * a + 2] = gz, gx
        dV = w * 6 * V  # reference volume 1/6 maps to V
        K += B.T @ D @ B * dV
        M += RHO * np.outer(N, N) * dV
    return K, M


@pytest.mark.parametrize("seed", [0, 3])
def test_tet10_affine_element_matches_high_order_quadrature(seed):
    X4 = _random_tet(seed)
    tet10 = softbody.to_tet10(softbody.Mesh(X4, [[0, 1, 2, 3]], "tet4"))
    X10 = tet10.nodes[tet10.elements[0]]
    for n, (i, j) in enumerate(TET10_EDGES_SPEC):  # node order of docs/method.md
        np.testing.assert_allclose(X10[4 + n], (X4[i] + X4[j]) / 2, atol=1e-15)
    K_ref, M_ref = _tet10_matrices_highorder(X10, 4)
    K_ref5, M_ref5 = _tet10_matrices_highorder(X10, 5)  # the reference itself is converged
    np.testing.assert_allclose(K_ref5, K_ref, rtol=0, atol=1e-13 * np.abs(K_ref).max())
    np.testing.assert_allclose(M_ref5, M_ref, rtol=0, atol=1e-13 * np.abs(M_ref).max())

    # global DOFs of the single-element mesh follow the element's node ids
    perm = np.concatenate([[3 * a, 3 * a + 1, 3 * a + 2] for a in tet10.elements[0]])
    body = softbody.FemBody(tet10, MAT)
    K = dense(body.stiffness_matrix())[np.ix_(perm, perm)]
    np.testing.assert_allclose(K, K_ref, rtol=0, atol=1e-10 * np.abs(K_ref).max())
    # the consistent mass (degree-4 integrand) must be integrated exactly too
    M = dense(body.mass_matrix())[np.ix_(perm, perm)]
    np.testing.assert_allclose(M, np.kron(M_ref, np.eye(3)), rtol=0, atol=1e-12 * np.abs(M_ref).max())


def test_tet10_mass_closed_form_row_sums():
    """Row sums of the exact tet10 consistent mass: corners carry -1/20 of the element mass, mid-edge nodes 1/5.
    (This is why plain row-sum lumping fails for quadratic tets.) HRZ lumping keeps every entry positive."""
    X4 = _random_tet(5)
    tet10 = softbody.to_tet10(softbody.Mesh(X4, [[0, 1, 2, 3]], "tet4"))
    _, V = _barycentric_gradients(X4)
    m = RHO * V
    body = softbody.FemBody(tet10, MAT)
    M = dense(body.mass_matrix())
    rows = M.sum(axis=1).reshape(-1, 3)[:, 0]
    el = tet10.elements[0]
    np.testing.assert_allclose(rows[el[:4]], -m / 20, rtol=1e-12)
    np.testing.assert_allclose(rows[el[4:]], m / 5, rtol=1e-12)
    # HRZ: diagonal scaled to the total; integral N_corner^2 = V/70, N_mid^2 = 8V/105
    ml = np.diag(dense(softbody.FemBody(tet10, MAT, mass="lumped").mass_matrix())).reshape(-1, 3)[:, 0]
    dc, dm = 1 / 70, 8 / 105
    tot = 4 * dc + 6 * dm
    np.testing.assert_allclose(ml[el[:4]], m * dc / tot, rtol=1e-12)
    np.testing.assert_allclose(ml[el[4:]], m * dm / tot, rtol=1e-12)
    assert ml.min() > 0
