"""Bodies of several materials (softbody.Regions: a material per element): a two-region bar pulled at its end
stretches as the two springs in series say, its mass is the regions', the warped step settles at the static
solution, and the split stiffness (shear and bulk parts apart) rotates with its elements."""
from __future__ import annotations

import numpy as np
import pytest

import softbody as sb

L, A_SIDE, F = 1.0, 0.1, 50.0  # bar length and side [m], end load [N]


def _bar(kind="hex8", cells=(10, 2, 2), E=(1e6, 4e6), nu=0.0, rho=(1000.0, 3000.0), volumetric="full"):
    """A bar along x, its first half (x < L / 2) of material 0, the rest of material 1, clamped at x = 0."""
    mesh = sb.box_mesh((L, A_SIDE, A_SIDE), cells, kind, center=(L / 2, 0, 0))
    centres = mesh.nodes[mesh.elements].mean(axis=1)
    labels = (centres[:, 0] > L / 2).astype(int)
    regions = sb.Regions([sb.LinearElastic(E[0], nu, rho[0]), sb.LinearElastic(E[1], nu, rho[1])], labels)
    body = sb.FemBody(mesh, regions, volumetric=volumetric)
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    return mesh, body


def _end_load(mesh: sb.Mesh, cells) -> np.ndarray:
    """A uniform traction F / A on the x = L face as consistent nodal forces of its bilinear faces (N, 3)."""
    f = np.zeros((mesh.n_nodes, 3))
    end = np.flatnonzero(np.isclose(mesh.nodes[:, 0], L))
    y, z = mesh.nodes[end, 1], mesh.nodes[end, 2]
    ny, nz = cells[1], cells[2]
    on_y = np.isclose(np.abs(y), A_SIDE / 2)
    on_z = np.isclose(np.abs(z), A_SIDE / 2)
    share = np.where(on_y, 0.5, 1.0) * np.where(on_z, 0.5, 1.0)  # corners 1/4, edges 1/2, inside 1 of a cell's
    f[end, 0] = F * share / (ny * nz)
    return f


def test_a_two_region_bar_stretches_as_springs_in_series():
    """nu = 0, a uniform end traction: the exact solution is linear in each region (the strain F / (E_r A)), so
    hex8 reproduces it: the tip moves F L1 / (E1 A) + F L2 / (E2 A) to round-off, and the interface F L1 / (E1 A)."""
    cells = (10, 2, 2)
    mesh, body = _bar(cells=cells)
    u = sb.solve_static(body, gravity=(0, 0, 0), forces=_end_load(mesh, cells))
    area = A_SIDE ** 2
    mid, tip = np.isclose(mesh.nodes[:, 0], L / 2), np.isclose(mesh.nodes[:, 0], L)
    assert u[mid, 0] == pytest.approx(F * (L / 2) / (1e6 * area), rel=1e-9)
    assert u[tip, 0] == pytest.approx(F * (L / 2) / (1e6 * area) + F * (L / 2) / (4e6 * area), rel=1e-9)
    assert body.total_mass == pytest.approx((1000.0 + 3000.0) * area * L / 2, rel=1e-12)


@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
def test_the_warped_step_settles_where_the_static_solve_does(kind):
    """Each element type with regions (nu 0.3): the damped warped step from rest under gravity comes to rest at the
    static solution (small deflection: the tips agree to 1%)."""
    cells = (10, 1, 1)
    mesh, body = _bar(kind, cells, E=(2e8, 8e8), nu=0.3)  # a tip deflection of about 1 cm
    tip = np.isclose(mesh.nodes[:, 0], L)
    want = float(sb.solve_static(body)[tip, 2].mean())
    body.damping = (20.0, 0.001)
    sb.Simulation(body, 0.005).run(2.0)
    assert float((body.positions - mesh.nodes)[tip, 2].mean()) == pytest.approx(want, rel=0.01)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("regions, volumetric", [(True, "full"), (True, "mean"), (False, "mean")])
def test_split_stiffness_rotates_with_its_elements(regions, volumetric, compiled, monkeypatch):
    """The warped stiffness and rest loads of a split stiffness (two regions, B-bar, or both) equal R K R^T and R K X
    of its element matrices, for the compiled kernels and their numpy twins alike."""
    from softbody import kernels

    if not compiled:
        monkeypatch.setattr(kernels, "ENABLED", False)
    if regions:
        mesh, body = _bar("hex8", (3, 2, 2), nu=0.45, volumetric=volumetric)
    else:
        mesh = sb.box_mesh((0.3, 0.2, 0.1), (3, 2, 2), "hex8")
        body = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.49, 1000.0), volumetric=volumetric)
    K = body.stiffness_matrix().toarray()
    R = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    Kw, load = body.warped_stiffness_upper(np.broadcast_to(R, (mesh.n_elements, 3, 3)).copy())
    T = np.kron(np.eye(mesh.n_nodes), R)
    assert np.abs(body.pattern.to_csr(body.stiffness_blocks(Kw)).toarray() - T @ K @ T.T).max() < 1e-12 * np.abs(K).max()
    assert np.abs(load.ravel() - T @ K @ mesh.nodes.ravel()).max() < 1e-12 * np.abs(load).max()


def test_one_region_is_the_single_material():
    """Regions with one material for every element: the same element matrices and mass as the material alone."""
    mesh = sb.box_mesh((0.3, 0.2, 0.1), (3, 2, 2), "tet10")
    m = sb.LinearElastic(1e6, 0.3, 1200.0)
    one = sb.FemBody(mesh, sb.Regions([m], np.zeros(mesh.n_elements, int)))
    plain = sb.FemBody(mesh, m)
    assert np.allclose(one.Ke, plain.Ke, rtol=1e-12, atol=1e-12 * np.abs(plain.Ke).max())
    assert np.allclose(one.M_data, plain.M_data, rtol=1e-14)
    assert np.allclose(one.stress(mesh.nodes + 0.01 * mesh.nodes ** 2), plain.stress(mesh.nodes + 0.01 * mesh.nodes ** 2))


def test_regions_name_bad_input():
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    m = sb.LinearElastic(1e6, 0.3, 1000.0)
    with pytest.raises(sb.InvalidInputError, match="one per element, 1, got 2"):
        sb.FemBody(mesh, sb.Regions([m], np.zeros(2, int)))
    with pytest.raises(sb.InvalidInputError, match=r"must lie in \[0, 1\)"):
        sb.Regions([m], np.array([1]))
    with pytest.raises(sb.InvalidInputError, match="non-empty list of LinearElastic"):
        sb.Regions([], np.array([0]))
    with pytest.raises(sb.InvalidInputError, match="1-D integer array"):
        sb.Regions([m], np.array([0.5]))


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("kind, volumetric", [("tet10", "full"), ("hex8", "mean"), ("tet4", "full")])
def test_the_matrix_free_product_of_a_split_stiffness_is_the_assembled_one(kind, volumetric, compiled, monkeypatch):
    """K' y element by element (rotated_gradients, warped_product: the shear and bulk parts' products summed) equals
    the assembled K' times y, rotated elements, for the compiled kernels and their numpy twins."""
    from softbody import kernels

    if not compiled:
        monkeypatch.setattr(kernels, "ENABLED", False)
    mesh, body = _bar(kind, (3, 2, 2), nu=0.3, volumetric=volumetric)
    R = np.linalg.qr(np.random.default_rng(5).normal(size=(mesh.n_elements, 3, 3)))[0]
    R *= np.sign(np.linalg.det(R))[:, None, None]
    y = np.random.default_rng(6).normal(size=(mesh.n_nodes, 3))
    K = body.pattern.to_csr(body.stiffness_blocks(body.warped_stiffness_upper(R)[0]))
    Ky = body.warped_product(body.rotated_gradients(R), y)
    assert np.abs(Ky.ravel() - K @ y.ravel()).max() < 1e-10 * np.abs(K @ y.ravel()).max()


def test_each_region_has_its_materials_element_matrices():
    """nu 0.3 and 0.45, tet10 and B-bar hex8: every element's K_e and mass of the body of regions equal those of a
    body made of that element's material alone."""
    for kind, volumetric in (("tet10", "full"), ("hex8", "mean")):
        mesh = sb.box_mesh((0.3, 0.2, 0.1), (3, 2, 2), kind)
        labels = np.arange(mesh.n_elements) % 2
        mats = [sb.LinearElastic(1e6, 0.3, 1000.0), sb.LinearElastic(3e6, 0.45, 2500.0)]
        both = sb.FemBody(mesh, sb.Regions(mats, labels), volumetric=volumetric)
        for r, m in enumerate(mats):
            alone = sb.FemBody(mesh, m, volumetric=volumetric)
            on = labels == r
            assert np.allclose(both.Ke[on], alone.Ke[on], rtol=1e-12, atol=1e-12 * np.abs(alone.Ke).max())
            assert np.allclose(both.Me[on], alone.Me[on], rtol=1e-14)


def test_regions_labels_are_read_only_and_their_materials_isotropic():
    m = sb.LinearElastic(1e6, 0.3, 1000.0)
    regions = sb.Regions([m], np.zeros(8, int))
    with pytest.raises(ValueError):
        regions.labels[:] = 1

    class Stiffer(sb.LinearElastic):
        def elasticity_matrix(self):
            return 2.0 * super().elasticity_matrix()

    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8")
    with pytest.raises(sb.InvalidInputError, match="Stiffer: its elasticity matrix is not the isotropic"):
        sb.FemBody(mesh, sb.Regions([m, Stiffer(1e6, 0.3, 1000.0)], np.array([1])))
