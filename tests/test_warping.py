"""Stiffness warping: rigid motions are force free, rotations are proper, a spinning body keeps its shape."""
from __future__ import annotations

import numpy as np
import pytest

import softbody
from conftest import KINDS, distorted_box, rotation_matrix

E, NU, RHO = 5.0e5, 0.33, 1000.0
MAT = softbody.LinearElastic(E, NU, RHO)
SIZE = np.array([0.4, 0.3, 0.2])
AXIS = np.array([1.0, -2.0, 0.7])  # oblique


def _bent(mesh, rng, angle: float) -> np.ndarray:
    """A bent and rotated state of the mesh's nodes (N, 3): jittered by 5% of an element's size (drawn from rng), turned
    by ``angle`` about AXIS, bent along x, so that the element rotations differ from element to element."""
    h = (mesh.volume() / mesh.n_elements) ** (1 / 3)
    x = (mesh.nodes + 0.05 * h * rng.standard_normal(mesh.nodes.shape)) @ rotation_matrix(AXIS, angle).T
    x[:, 2] += 0.3 * (x[:, 0] - x[:, 0].mean()) ** 2
    return x


def _force_scale(mesh) -> float:
    """Force of a unit strain on one element's face: E * h^2 with h a typical element edge."""
    h = (mesh.volume() / mesh.n_elements) ** (1 / 3)
    return E * h**2


@pytest.mark.parametrize("kind", KINDS)
def test_rigid_rotation_is_force_free_with_warping(kind):
    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=2)
    Q = rotation_matrix(AXIS, np.pi / 2)
    x = mesh.nodes @ Q.T + np.array([0.3, -1.2, 2.0])
    scale = _force_scale(mesh)
    for hex_rotation in ("average", "single"):
        body = softbody.FemBody(mesh, MAT, warping=True, hex_rotation=hex_rotation)
        f = body.elastic_forces(x)
        assert np.abs(f).max() <= 1e-10 * scale, hex_rotation
        # the recovered element rotation is the applied one
        np.testing.assert_allclose(body.rotations(x), np.broadcast_to(Q, (mesh.n_elements, 3, 3)), atol=1e-12)
        # round-off only: the energy of a uniform strain of 1e-6 is ~1e-12 E V
        assert body.elastic_energy(x) <= 1e-12 * E * mesh.volume()
        np.testing.assert_allclose(body.strain(x), 0.0, atol=1e-12)
    # without warping the same motion is seen as a huge deformation (strain of order 1)
    plain = softbody.FemBody(mesh, MAT, warping=False)
    f_plain = plain.elastic_forces(x)
    assert np.abs(f_plain).max() > 0.05 * scale
    assert np.abs(plain.strain(x)).max() > 0.5
    # ... but a pure translation is force free either way
    np.testing.assert_allclose(plain.elastic_forces(mesh.nodes + [1.0, 2.0, 3.0]), 0.0, atol=1e-10 * scale)


@pytest.mark.parametrize("kind", KINDS)
def test_rotation_then_stretch_equals_unrotated_stretch(kind):
    """Objectivity: x = Q (X + u) gives forces Q f(X + u) for a small deformation u."""
    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=3)
    rng = np.random.default_rng(0)
    u = 1e-3 * rng.standard_normal(mesh.nodes.shape) * SIZE.min()
    Q = rotation_matrix(AXIS, 2.0)
    body = softbody.FemBody(mesh, MAT, warping=True)
    f0 = body.elastic_forces(mesh.nodes + u)
    f1 = body.elastic_forces((mesh.nodes + u) @ Q.T + 5.0)
    np.testing.assert_allclose(f1, f0 @ Q.T, atol=1e-9 * np.abs(f0).max())
    assert body.elastic_energy((mesh.nodes + u) @ Q.T) == pytest.approx(body.elastic_energy(mesh.nodes + u), rel=1e-9)


def _check_proper_rotations(R):
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("kind, hex_rotation", [("tet4", "average"), ("tet10", "average"),
                                                ("hex8", "average"), ("hex8", "single")])
def test_rotations_proper_for_inverted_elements(kind, hex_rotation):
    mesh = softbody.box_mesh(SIZE, (2, 2, 1), kind)
    body = softbody.FemBody(mesh, MAT, hex_rotation=hex_rotation)
    # mirror one element's nodes through a plane through its centroid: that element is inverted
    e = 3
    ids = mesh.elements[e]
    n = np.array([0.3, 0.9, -0.2])
    n /= np.linalg.norm(n)
    c = mesh.nodes[ids].mean(axis=0)
    x = mesh.nodes.copy()
    x[ids] = x[ids] - 2 * np.outer((x[ids] - c) @ n, n)
    def tet_det(p):
        q = p[ids[:4]] if kind != "hex8" else p[ids[[0, 2, 5, 7]]]
        return np.linalg.det(np.column_stack([q[1] - q[0], q[2] - q[0], q[3] - q[0]]))

    assert tet_det(x) * tet_det(mesh.nodes) < 0  # really inverted
    R = body.rotations(x)
    _check_proper_rotations(R)
    assert np.all(np.isfinite(body.elastic_forces(x)))
    # the whole mesh mirrored: every element inverted
    xm = mesh.nodes - 2 * np.outer(mesh.nodes @ n, n)
    _check_proper_rotations(body.rotations(xm))
    # a collapsed (flat) configuration must not break it either
    xf = mesh.nodes.copy()
    xf[:, 2] = 0.0
    _check_proper_rotations(body.rotations(xf))


def _best_fit_rigid(X, x):
    """Kabsch: rotation Q and translation t minimising |Q X + t - x|; returns the residual per node."""
    cX, cx = X.mean(axis=0), x.mean(axis=0)
    H = (X - cX).T @ (x - cx)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    Q = Vt.T @ np.diag([1, 1, d]) @ U.T
    return np.linalg.norm((X - cX) @ Q.T + cx - x, axis=1)


@pytest.mark.parametrize("kind", KINDS)
def test_free_spinning_body_keeps_its_shape(kind):
    """A cube spinning at 2 rev/s about an oblique axis through its centre, no gravity, no damping, for 1 s.

    Step h = 0.005 s. The scheme of docs/method.md section 3 moves nodes along straight lines x + h v, so every
    step of a rotation by omega h stretches the body by about (omega h)^2 / 2 across the axis before the
    elastic forces pull it back; at h = 0.01 s (omega h = 0.126) that alone stores ~15% of the kinetic
    energy as strain energy for E = 5e5 Pa (measured; it scales like h^2 E), so the energy criterion needs
    the smaller step. The shape criterion holds at both.
    """
    L = 0.2
    mesh = softbody.box_mesh((L, L, L), (2, 2, 2), kind)
    omega = 2 * 2 * np.pi * AXIS / np.linalg.norm(AXIS)
    h = 0.005

    def spin(warping, steps):
        body = softbody.FemBody(mesh, MAT, warping=warping, damping=(0.0, 0.0))
        body.velocities = np.cross(omega, mesh.nodes)
        sim = softbody.Simulation(body, dt=h, gravity=(0, 0, 0))
        ke0 = body.kinetic_energy()
        dev, ratio = [], []
        for _ in range(steps):
            sim.step()
            dev.append(_best_fit_rigid(mesh.nodes, body.positions).max())
            ratio.append(body.elastic_energy() / body.kinetic_energy())
        return body, np.array(dev), np.array(ratio), ke0

    body, dev, ratio, ke0 = spin(True, 200)
    assert np.all(np.isfinite(body.positions))
    assert dev.max() < 0.01 * L, dev.max()
    assert ratio.max() < 0.05, ratio.max()
    # it kept spinning: angular momentum about the centre of mass is nearly unchanged in direction and size
    c = body.positions.mean(axis=0)
    m = body.node_mass
    Lmom = np.sum(m[:, None] * np.cross(body.positions - c, body.velocities), axis=0)
    Lmom0 = np.sum(m[:, None] * np.cross(mesh.nodes, np.cross(omega, mesh.nodes)), axis=0)
    assert np.dot(Lmom, Lmom0) / np.linalg.norm(Lmom0) ** 2 > 0.95
    assert body.kinetic_energy() > 0.95 * ke0
    # without warping, the infinitesimal-rotation field is a zero-energy mode of linear elasticity: the
    # body does not rotate but inflates along it (x = X + t omega x X), so the same check fails badly
    _, dev_plain, _, _ = spin(False, 50)
    assert dev_plain.max() > 0.5 * L


def test_rotation_memo_is_exact_and_read_only():
    """rotations() remembers its last result for identical positions, recomputes for any change."""
    import softbody as sb

    body = sb.FemBody(sb.box_mesh((1, 1, 0.5), (2, 2, 1), "tet4"), sb.LinearElastic(1e5, 0.3, 1000))
    fresh = sb.FemBody(body.mesh, body.material)
    x = body.rest + 0.01 * np.random.default_rng(0).standard_normal(body.rest.shape)
    R1 = body.rotations(x)
    assert body.rotations(x.copy()) is R1
    np.testing.assert_array_equal(R1, fresh.rotations(x))
    y = x.copy()
    y[0, 0] += 1e-9
    assert body.rotations(y) is not R1
    np.testing.assert_array_equal(body.rotations(y), fresh.rotations(y))
    x[1, 1] += 1e-3  # mutating the caller's array must not fool the memo
    np.testing.assert_array_equal(body.rotations(x), fresh.rotations(x))
    with pytest.raises(ValueError):
        body.rotations(y)[0, 0, 0] = 1.0


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("hex_rotation", ["average", "single"])
def test_assembled_warped_stiffness_and_loads_match_rotated_element_matrices(kind, hex_rotation):
    """The step's K' (rest formula with rotated gradients, assembled per node pair or Gram matrix) equals
    sum_e R_e K_e R_e^T assembled from the element matrices, its rest loads equal sum_e R_e K_e X_e, and
    the forces -K'(x - c) + loads equal the per-element warped forces (independent code paths)."""
    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=3)
    body = softbody.FemBody(mesh, MAT, warping=True, hex_rotation=hex_rotation)
    rng = np.random.default_rng(4)
    x = _bent(mesh, rng, 0.7)
    R = body.rotations(x)
    assert np.ptp(R, axis=0).max() > 0.05  # the rotations really vary
    K, load = body.warped_stiffness_blocks(R)
    ref = body.pattern.assemble(body.warped_stiffness(R))
    np.testing.assert_allclose(K, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    Rb = np.einsum("eij,eaj->eai", R, (body.Ke @ mesh.nodes[mesh.elements].reshape(mesh.n_elements, -1, 1))
                   .reshape(mesh.n_elements, -1, 3))
    load_ref = body.scatter_nodal(Rb)
    np.testing.assert_allclose(load, load_ref, rtol=0, atol=1e-11 * np.abs(load_ref).max())
    u = x - x.mean(axis=0)
    f = load - (body.pattern.to_bsr(K) @ u.ravel()).reshape(-1, 3)
    f_ref = body.elastic_forces(x)
    np.testing.assert_allclose(f, f_ref, rtol=0, atol=1e-9 * _force_scale(mesh))
    # warping off: the rest matrix, cached and read-only
    plain = softbody.FemBody(mesh, MAT, warping=False)
    K0, _ = plain.warped_stiffness_blocks(None)
    np.testing.assert_allclose(K0, plain.pattern.assemble(plain.Ke), rtol=0, atol=1e-12 * np.abs(K0).max())
    assert plain.warped_stiffness_blocks(None)[0] is K0 and not K0.flags.writeable


@pytest.mark.parametrize("kind", KINDS)
def test_matrix_free_product_matches_rotated_element_matrices(kind):
    """FemBody.warped_product (stresses from rotated gradients, no K') applies sum_e R_e K_e R_e^T as
    assembled from the element matrices K_e = sum_q B^T D B (an independent code path), for a bent,
    rotated state and for R = None (K); the rest loads likewise come out as sum_e R_e K_e X_e."""
    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=5)
    body = softbody.FemBody(mesh, MAT, warping=True)
    rng = np.random.default_rng(6)
    x = _bent(mesh, rng, 1.1)
    R = body.rotations(x)
    assert np.ptp(R, axis=0).max() > 0.05
    y = rng.standard_normal(mesh.nodes.shape)
    for rot in (R, None):
        ref = (body.pattern.to_bsr(body.pattern.assemble(body.warped_stiffness(rot))) @ y.ravel()).reshape(-1, 3)
        got = body.warped_product(body.rotated_gradients(rot), y)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    # symmetric (an energy's Hessian) and blind to rigid translations
    z = rng.standard_normal(mesh.nodes.shape)
    g = body.rotated_gradients(R)
    assert abs(np.vdot(z, body.warped_product(g, y)) - np.vdot(y, body.warped_product(g, z))) < 1e-12 * np.abs(
        ref).max() * np.abs(z).sum()
    np.testing.assert_allclose(body.warped_product(g, np.broadcast_to([0.3, -1.0, 2.0], y.shape)), 0.0,
                               atol=1e-12 * np.abs(ref).max())
    # rest loads sum_e R_e K_e X_e, from the element matrices
    load_ref = body.scatter_nodal(np.einsum("eij,eaj->eai", R, (body.Ke @ mesh.nodes[mesh.elements].reshape(
        mesh.n_elements, -1, 1)).reshape(mesh.n_elements, -1, 3)))
    np.testing.assert_allclose(body.rest_loads(R), load_ref, rtol=0, atol=1e-11 * np.abs(load_ref).max())


def test_node_frames_are_rotations_that_follow_the_elements():
    """FemBody.node_frames: proper rotations; equal to R0 when every element turns by R0; within the
    elements' spread of the polar factor of their sum; finite where adjacent elements turn apart."""
    from scipy.spatial.transform import Rotation
    from softbody.rotation import polar_rotation

    body = softbody.FemBody(softbody.box_mesh((0.4, 0.3, 0.2), (3, 2, 2), "tet10"), softbody.LinearElastic(1e6, 0.3, 1000.0))
    E = body.mesh.n_elements
    R0 = Rotation.random(random_state=3).as_matrix()
    np.testing.assert_allclose(body.node_frames(np.broadcast_to(R0, (E, 3, 3))), np.broadcast_to(R0, (body.n_nodes, 3, 3)),
                               atol=1e-14)
    wobble = Rotation.from_rotvec(0.01 * np.random.default_rng(4).standard_normal((E, 3))).as_matrix()
    R = R0 @ wobble
    Q = body.node_frames(R)
    np.testing.assert_allclose(Q @ np.swapaxes(Q, 1, 2), np.broadcast_to(np.eye(3), Q.shape), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-13)
    S = np.zeros((body.n_nodes, 3, 3))
    np.add.at(S, body.mesh.elements, np.repeat(R[:, None], body.mesh.elements.shape[1], axis=1))
    assert np.abs(Q - polar_rotation(S)).max() < 0.03  # within the 0.01 rad spread, not exact
    # a node whose two elements turn by 180 degrees apart: S is singular there
    mesh = softbody.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1.0]]),
                   np.array([[0, 1, 2, 3], [0, 2, 1, 4]]), "tet4")
    two = softbody.FemBody(mesh, softbody.LinearElastic(1e6, 0.3, 1000.0))
    Q = two.node_frames(np.stack([np.eye(3), Rotation.from_euler("z", np.pi).as_matrix()]))
    assert np.isfinite(Q).all()
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-12)


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_system_blocks_and_the_force_product_taken_from_them(kind):
    """A = c_m M + c_k K' from the upper blocks equals the sum of the whole matrices, and K' u taken from
    A as (A u - c_m M u) / c_k (what the step does while c_m M is not over 1e4 x c_k K') matches K' u."""
    from scipy.spatial.transform import Rotation

    body = softbody.FemBody(softbody.box_mesh((0.4, 0.3, 0.2), (3, 2, 2), kind), softbody.LinearElastic(1e6, 0.3, 1000.0))
    R = Rotation.random(body.mesh.n_elements, random_state=2).as_matrix()
    K_up, _ = body.warped_stiffness_upper(R)
    K = body.stiffness_blocks(K_up)
    c_m, c_k = 1.001, 1.1e-4
    A = body.system_blocks(K_up, c_m, c_k)
    np.testing.assert_allclose(A, c_m * body.M_blocks + c_k * K, rtol=0, atol=1e-14 * np.abs(A).max())
    u = body.positions - body.positions.mean(axis=0)
    Ku = (body.pattern.to_bsr(K) @ u.ravel()).reshape(-1, 3)
    via_A = ((body.pattern.to_bsr(A) @ u.ravel()).reshape(-1, 3) - c_m * body.mass_product(u)) / c_k
    assert c_m * body.mass_scale <= 1e4 * c_k * np.abs(K_up[body.diagonal_upper][:, [0, 4, 8]]).max()
    np.testing.assert_allclose(via_A, Ku, rtol=0, atol=1e-11 * np.abs(Ku).max())


@pytest.mark.parametrize("kind, volumetric", [("tet10", "full"), ("hex8", "full"), ("hex8", "mean"), ("tet4", "full")])
def test_warped_diagonal_is_the_diagonal_of_the_assembled_warped_stiffness(kind, volumetric, monkeypatch):
    """FemBody.warped_diagonal (from the rotated gradients, compiled and numpy) equals the diagonal blocks of
    sum_e R_e K_e R_e^T assembled from the element matrices (warped_stiffness), for a bent, rotated state and for
    R = None; a B-bar body's (a split stiffness: its bulk part's gradients too) alike."""
    from softbody import kernels

    mesh = distorted_box(kind, cells=(2, 2, 2), size=SIZE, seed=7)
    body = softbody.FemBody(mesh, MAT, warping=True, volumetric=volumetric)
    rng = np.random.default_rng(8)
    x = _bent(mesh, rng, 0.7)
    R = body.rotations(x)
    for rot in (R, None):
        want = body.pattern.assemble(body.warped_stiffness(rot))[body.pattern.diag]
        g = body.rotated_gradients(rot)
        for compiled in ((True, False) if kernels.ENABLED else (False,)):
            monkeypatch.setattr(kernels, "ENABLED", compiled)
            np.testing.assert_allclose(body.warped_diagonal(g), want, rtol=0, atol=1e-12 * np.abs(want).max())
