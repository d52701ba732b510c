"""Fibres: a transversely isotropic material as an isotropic matrix reinforced along a direction per element
(docs/materials.md, "Fibres").

``FemBody(mesh, material, fibres=Fibres(directions, modulus))``: on top of the isotropic material (the matrix), the
strain along the unit fibre direction a stores psi_f = E_f / 2 (a . eps a)^2 [J/m^3] (small strain: a stress
E_f eps_aa a a^T, the matrix's Young's modulus raised by E_f along a and unchanged across it). A material of three of
the five constants of transverse isotropy (lam, mu and E_f), the usual linear model of fibre-reinforced tissue.

With rotations (the warped model) the fibre turns with its element: the strain along R a in the element's rotated
frame. Per quadrature point the fibre strain is b^T u with b_c = (g_c . a) a for the element's nodes c (g_c the
shape gradients), so an element's fibre stiffness is M_e (x) a a^T, M_e = sum_q w detJ E_f s s^T (k, k) and
s_c = g_c . a: a scalar matrix made once at rest times the rank-one 3x3 of the (rotated) fibre. The hyperelastic
models take psi_f = E_f / 8 (|F a|^2 - 1)^2, whose small-strain limit is the same.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InvalidInputError


@dataclass(frozen=True, eq=False)
class Fibres:
    """Fibre directions (3,) for every element or (E, 3) one per element (any length > 0: normalised), and their
    modulus E_f [Pa] >= 0, one number or (E,) per element."""

    directions: np.ndarray
    modulus: float | np.ndarray

    def __post_init__(self) -> None:
        try:
            d = np.array(self.directions, dtype=float)
            m = np.array(self.modulus, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"Fibres(directions, modulus): numbers expected, got {self.directions!r} and "
                                    f"{self.modulus!r}") from None
        if d.ndim not in (1, 2) or d.shape[-1] != 3:
            raise InvalidInputError(f"Fibres directions must be (3,) or (E, 3), got shape {d.shape}")
        norm = np.linalg.norm(d, axis=-1)
        if not np.isfinite(d).all() or np.any(norm <= 0):
            raise InvalidInputError("Fibres directions must be finite and non-zero")
        if m.ndim > 1 or not np.isfinite(m).all() or np.any(m < 0):
            raise InvalidInputError(f"Fibres modulus must be a number >= 0 [Pa] or (E,) of them, got {self.modulus!r}")
        d = d / norm[..., None]
        for a in (d, m):
            a.flags.writeable = False
        object.__setattr__(self, "directions", d)
        object.__setattr__(self, "modulus", m)

    def per_element(self, n_elements: int) -> tuple[np.ndarray, np.ndarray]:
        """(directions (E, 3), modulus (E,)) for a body of ``n_elements`` elements."""
        for name, a, shape in (("directions", self.directions, (n_elements, 3)),
                               ("modulus", self.modulus, (n_elements,))):
            if a.ndim == len(shape) and a.shape != shape:
                raise InvalidInputError(f"Fibres {name}: one per element, {n_elements}, got {a.shape[0]}")
        return (np.broadcast_to(self.directions, (n_elements, 3)).copy(),
                np.broadcast_to(self.modulus, (n_elements,)).copy())


def fibre_matrices(G: np.ndarray, weights: np.ndarray, a: np.ndarray, modulus: np.ndarray) -> np.ndarray:
    """M_e = sum_q w_q detJ_q E_f s s^T (E, k, k) [N/m], s_c = g_c . a: the scalar factor of each element's fibre
    stiffness M_e (x) a a^T; G (E, q, k, 3) the shape gradients [1/m], weights (E, q) [m^3], a (E, 3), modulus (E,)."""
    s = np.einsum("eqkc,ec->eqk", G, a)
    return np.einsum("eq,eqk,eql->ekl", weights * modulus[:, None], s, s)


def fibre_element_matrices(M: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The fibre stiffness M_e (x) n n^T (E, 3k, 3k), interleaved dofs, of fibre directions n (E, 3)."""
    E, k, _ = M.shape
    nn = n[:, :, None] * n[:, None, :]
    return np.einsum("ekl,ecd->ekcld", M, nn).reshape(E, 3 * k, 3 * k)


def fibre_energy(F: np.ndarray, a: np.ndarray, modulus: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hyperelastic fibre term psi_f = E_f / 8 (|F a|^2 - 1)^2 at deformation gradients F (E, q, 3, 3) for fibres
    a (E, 3), modulus (E,): (psi (E, q) [J/m^3], P (E, q, 3, 3) [Pa], dP/dF (E, q, 3, 3, 3, 3) [Pa])."""
    Fa = np.einsum("eqij,ej->eqi", F, a)
    c = (np.einsum("eqi,eqi->eq", Fa, Fa) - 1.0)  # I4 - 1
    Ef = modulus[:, None]
    psi = Ef / 8.0 * c * c
    P = (Ef / 2.0 * c)[..., None, None] * Fa[..., :, None] * a[:, None, None, :]
    aa = a[:, :, None] * a[:, None, :]  # (E, 3, 3)
    eye = np.eye(3)
    A = ((Ef / 2.0 * c)[..., None, None, None, None] * np.einsum("ik,ejl->eijkl", eye, aa)[:, None]
         + Ef[..., None, None, None, None] * np.einsum("eqi,ej,eqk,el->eqijkl", Fa, a, Fa, a))
    return psi, P, A
