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
    with pytest.warns(sb.LockingWarning, match="tet10 elements do not lock"):
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

    with pytest.raises(sb.InvalidInputError, match="Stiffer: its elasticity matrix is not the isotropic one"):
        sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4"), Stiffer(1e5, 0.3, 1000.0))
