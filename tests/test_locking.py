"""Volumetric locking (softbody/locking.py): tet4 and hex8 bodies of a nearly incompressible material are warned of,
and the warning's premise holds against beam theory (a cantilever under its own weight): they deflect far less
than Timoshenko's beam as nu nears 0.5, where tet10 stays close to it."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import softbody as sb

E, RHO, L, B = 5.0e7, 1000.0, 1.0, 0.1


def _timoshenko(nu: float) -> float:
    q, inertia, area = RHO * 9.81 * B * B, B**4 / 12, B * B
    return q * L**4 / (8 * E * inertia) + q * L**2 / (2 * 5 / 6 * (E / (2 * (1 + nu))) * area)


def _tip(kind: str, cells, nu: float) -> float:
    mesh = sb.box_mesh((L, B, B), cells, kind, center=(L / 2, 0, 0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", sb.LockingWarning)
        body = sb.FemBody(mesh, sb.LinearElastic(E, nu, RHO))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    u = sb.solve_static(body)
    return -float(u[np.isclose(mesh.nodes[:, 0], L), 2].mean())


@pytest.mark.parametrize("kind", ["tet4", "hex8"])
def test_locking_elements_of_a_nearly_incompressible_material_are_warned_of(kind):
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), kind)
    way_out = "volumetric='mean'" if kind == "hex8" else "tet10 elements do not lock"
    with pytest.warns(sb.LockingWarning, match=way_out):
        sb.FemBody(mesh, sb.LinearElastic(1e5, 0.49, 1000.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", sb.LockingWarning)
        sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0))  # compressible: no warning
        sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet10"), sb.LinearElastic(1e5, 0.49, 1000.0))


def test_hex8_locks_where_tet10_does_not():
    """At nu 0.3 hex8 and tet10 (20 x 2 x 2) deflect within 15% of Timoshenko's beam; at nu 0.499 hex8 deflects less
    than half of the beam's, tet10 still within 10% of it (its clamped root, which the beam does not model, stiffens a
    nearly incompressible beam by a few per cent)."""
    for nu in (0.3, 0.499):
        beam = _timoshenko(nu)
        hex8, tet10 = _tip("hex8", (20, 2, 2), nu) / beam, _tip("tet10", (20, 2, 2), nu) / beam
        assert 0.9 < tet10 < 1.0
        assert (hex8 > 0.85) if nu == 0.3 else (hex8 < 0.5)


def test_a_material_whose_elasticity_is_not_its_lame_parameters_is_refused():
    """The warped step uses the Lame parameters alone: a material with another elasticity matrix (the static solve
    used to take it, the dynamic step not) is refused, naming it."""

    class Stiffer(sb.LinearElastic):
        def elasticity_matrix(self):
            return 2.0 * super().elasticity_matrix()

    with pytest.raises(sb.InvalidInputError, match="Stiffer: its elasticity matrix is not the isotropic"):
        sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4"), Stiffer(1e5, 0.3, 1000.0))


# ----------------------------------------------------------------------------------------------- B-bar hex8
def _mean_body(mesh, nu=0.499):
    return sb.FemBody(mesh, sb.LinearElastic(E, nu, RHO), volumetric="mean")


def test_mean_dilatation_hex8_does_not_lock():
    """volumetric='mean' (B-bar): hex8 (20 x 2 x 2) deflects within 10% of Timoshenko's beam at nu 0.3, 0.49 and
    0.499 (the full form: 0.38 of it at 0.499), and builds without a LockingWarning."""
    mesh = sb.box_mesh((L, B, B), (20, 2, 2), "hex8", center=(L / 2, 0, 0))
    for nu in (0.3, 0.49, 0.499):
        with warnings.catch_warnings():
            warnings.simplefilter("error", sb.LockingWarning)
            body = _mean_body(mesh, nu)
        body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
        tip = -float(sb.solve_static(body)[np.isclose(mesh.nodes[:, 0], L), 2].mean())
        assert 0.9 < tip / _timoshenko(nu) < 1.0


def test_mean_dilatation_passes_the_patch_test_and_keeps_rigid_modes():
    """On a distorted hex8 mesh, the B-bar stiffness gives zero force on every node for the six rigid motions
    (translations, small rotations), and zero force on the interior nodes for any linear displacement field (a
    uniform strain: the patch test)."""
    mesh = sb.box_mesh((0.3, 0.2, 0.2), (3, 2, 2), "hex8")
    x = mesh.nodes.copy()
    inner = np.flatnonzero((np.abs(x) < np.array([0.15, 0.1, 0.1]) - 1e-9).all(axis=1))
    x[inner] += np.random.default_rng(2).uniform(-0.02, 0.02, size=(len(inner), 3))  # distorted
    body = _mean_body(sb.Mesh(x, mesh.elements, "hex8"), nu=0.49)
    K = body.pattern.to_csr(body.pattern.assemble(body.Ke))
    scale = abs(K).max() * np.abs(x).max()
    for w in np.eye(3):
        assert np.abs(K @ np.tile(w, len(x))).max() < 1e-9 * scale
        assert np.abs(K @ np.cross(w, x).ravel()).max() < 1e-9 * scale
    strain = np.random.default_rng(3).normal(size=(3, 3))
    f = (K @ (x @ strain.T).ravel()).reshape(-1, 3)
    assert np.abs(f[inner]).max() < 1e-9 * scale


def test_mean_dilatation_dynamics_settle_at_the_static_solution():
    """A nearly incompressible B-bar hex8 cantilever stepped (warped, damped) from rest comes to rest where the
    static solve puts it (small deflection: the two agree to 1% at the tip)."""
    mesh = sb.box_mesh((L, B, B), (10, 1, 1), "hex8", center=(L / 2, 0, 0))
    clamp = np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0))
    static = _mean_body(mesh, 0.49)
    static.fix(clamp)
    tip = np.isclose(mesh.nodes[:, 0], L)
    want = float(sb.solve_static(static)[tip, 2].mean())
    body = sb.FemBody(mesh, sb.LinearElastic(E, 0.49, RHO), damping=(20.0, 0.001), volumetric="mean")
    body.fix(clamp)
    sb.Simulation(body, 0.005).run(2.0)
    got = float((body.positions - mesh.nodes)[tip, 2].mean())
    assert got == pytest.approx(want, rel=0.01)


def test_volumetric_names_bad_input():
    with pytest.raises(sb.InvalidInputError, match="'full' or 'mean'"):
        sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8"), sb.LinearElastic(1e5, 0.3, 1000.0),
                   volumetric="reduced")
    for kind in ("tet4", "tet10"):
        with pytest.raises(sb.InvalidInputError, match="is for hex8 elements"):
            sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), kind), sb.LinearElastic(1e5, 0.3, 1000.0),
                       volumetric="mean")


def _distorted_hex8(seed=2):
    mesh = sb.box_mesh((0.3, 0.2, 0.2), (3, 2, 2), "hex8")
    x = mesh.nodes.copy()
    inner = np.flatnonzero((np.abs(x) < np.array([0.15, 0.1, 0.1]) - 1e-9).all(axis=1))
    x[inner] += np.random.default_rng(seed).uniform(-0.02, 0.02, size=(len(inner), 3))
    return sb.Mesh(x, mesh.elements, "hex8")


def test_mean_dilatation_element_matrices_are_the_textbook_b_bar():
    """K_e of volumetric='mean' against Hughes' B-bar written out here point by point on a distorted mesh: B_bar_q =
    B_q + m (b_mean - b_q) / 3 (m = (1, 1, 1, 0, 0, 0), b the divergence row), K_e = sum_q w detJ B_bar^T D B_bar with
    the full isotropic D."""
    from softbody.body import strain_displacement
    from softbody.elements import shape_gradients

    mesh = _distorted_hex8()
    material = sb.LinearElastic(1e6, 0.49, 1000.0)
    body = sb.FemBody(mesh, material, volumetric="mean")
    xi, w = mesh.element_type.stiffness_rule
    G, detJ = shape_gradients(mesh.element_type, mesh.nodes[mesh.elements], xi)
    B = strain_displacement(G)  # (E, q, 6, 24)
    b = B[:, :, :3].sum(axis=2)  # the divergence rows (E, q, 24)
    b_mean = np.einsum("eq,eqj->ej", detJ * w, b) / (detJ * w).sum(axis=1)[:, None]
    m = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    B_bar = B + m[None, None, :, None] * (b_mean[:, None, None, :] - b[:, :, None, :]) / 3.0
    want = np.einsum("eq,eqia,ij,eqjb->eab", detJ * w, B_bar, material.elasticity_matrix(), B_bar)
    assert np.abs(body.Ke - want).max() < 1e-12 * np.abs(want).max()
    # and its strain output: the volume change is the element's mean, b_mean . u, not the centre's
    u = np.random.default_rng(5).normal(scale=1e-3, size=mesh.nodes.shape)
    body.positions = mesh.nodes + u
    eps = body.strain()
    R = body.rotations(body.positions)
    local = body.local_displacements(body.positions, R)
    assert np.allclose(eps[:, :3].sum(axis=1), np.einsum("ej,ej->e", b_mean, local), rtol=1e-10, atol=1e-15)
