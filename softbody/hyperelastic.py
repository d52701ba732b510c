"""A body's strain energy as a sum over quadrature points of a hyperelastic law (softbody.constitutive).

Psi(x) = sum_e sum_q w_q detJ_q psi(F_eq), F_eq = sum_a x_a (dN_a/dX)(xi_q)^T: the element's deformation gradient at
its quadrature points; the nodal gradient dPsi/dx_a = sum_q w_q detJ_q P(F_q) dN_a/dX and the element Hessian
sum_q w_q detJ_q (dF/dx)^T dP/dF (dF/dx), each point's tangent made positive semi-definite for Newton's method
(constitutive.project_spd). All batched over elements and points (numpy einsum), nothing per element in Python.
"""
from __future__ import annotations

import numpy as np

from .constitutive import Law, project_spd
from .fibres import fibre_energy


class QuadratureEnergy:
    """The energy of ``law`` over elements: G (E, q, k, 3) the shape functions' gradients dN/dX at the quadrature
    points [1/m], weights (E, q) w_q detJ_q [m^3], lam and mu (E,) the Lame parameters per element [Pa]; fibres:
    (directions (E, 3), modulus (E,) [Pa]) of a fibre term E_f / 8 (|F a|^2 - 1)^2 (softbody.fibres), or None."""

    def __init__(self, law: Law, G: np.ndarray, weights: np.ndarray, lam, mu,
                 fibres: tuple[np.ndarray, np.ndarray] | None = None):
        self.fibres = fibres
        E, q = weights.shape
        self.law = law
        self.G = np.ascontiguousarray(G, dtype=float)
        self.weights = np.ascontiguousarray(weights, dtype=float)
        self.lam = np.broadcast_to(np.asarray(lam, float)[..., None], (E, q)) if np.ndim(lam) else \
            np.full((E, q), float(lam))
        self.mu = np.broadcast_to(np.asarray(mu, float)[..., None], (E, q)) if np.ndim(mu) else \
            np.full((E, q), float(mu))

    def deformation_gradients(self, xe: np.ndarray) -> np.ndarray:
        """F (E, q, 3, 3) at element node positions xe (E, k, 3) [m] (taken of xe less its mean: the gradients of a
        point sum to zero, so an offset adds no round-off)."""
        xc = xe - xe.mean(axis=1, keepdims=True)
        return np.einsum("eka,eqkb->eqab", xc, self.G, optimize=True)

    def energy(self, xe: np.ndarray) -> float:
        """Psi [J] at element node positions xe (E, k, 3)."""
        F = self.deformation_gradients(xe)
        psi = self.law.energy(F, self.lam, self.mu)
        if self.fibres is not None:
            psi = psi + fibre_energy(F, *self.fibres)[0]
        return float(np.sum(self.weights * psi))

    def gradients(self, xe: np.ndarray) -> np.ndarray:
        """dPsi_e/dx_e (E, k, 3) [N]."""
        F = self.deformation_gradients(xe)
        P = self.law.stress(F, self.lam, self.mu)
        if self.fibres is not None:
            P = P + fibre_energy(F, *self.fibres)[1]
        P = P * self.weights[:, :, None, None]
        return np.einsum("eqab,eqkb->eka", P, self.G, optimize=True)

    def hessians(self, xe: np.ndarray, project: bool = True) -> np.ndarray:
        """d^2 Psi_e / dx_e^2 (E, 3k, 3k) [N/m], node-major (3 a + i); project: each point's tangent made positive
        semi-definite (then every element's Hessian is)."""
        F = self.deformation_gradients(xe)
        A = self.law.tangent(F, self.lam, self.mu)
        if self.fibres is not None:
            A = A + fibre_energy(F, *self.fibres)[2]
        if project:
            A = project_spd(A)
        A = A * self.weights[:, :, None, None, None, None]
        E, q, k, _ = self.G.shape
        # H[k a, l c] = sum_q sum_bd G[q k b] A[q a b c d] G[q l d], as two batched matrix products (an einsum over
        # all six indices is twenty times slower): AG[q a b l c] = sum_d A[q a b c d] G[q l d], then G's rows
        # against it over (q, b)
        AG = np.swapaxes(A @ np.swapaxes(self.G, -1, -2)[:, :, None, None], -1, -2)  # (E, q, a, b, l, c)
        AG = np.moveaxis(AG, 3, 2).reshape(E, q * 3, 9 * k)  # [(q b), (a l c)]
        H = np.swapaxes(self.G, 1, 2).reshape(E, k, q * 3) @ AG  # [k, (a l c)]
        return H.reshape(E, 3 * k, 3 * k)

    def cauchy_stress(self, F: np.ndarray, lam, mu) -> np.ndarray:
        """Cauchy stress sigma = P F^T / det F (E, 3, 3) [Pa] of the law (and fibres) at one deformation gradient per
        element F (E, 3, 3); det F taken as at least 1e-3 (an element flattened or turned inside out has no Cauchy
        stress: a finite value, not an infinity that would spoil a colour scale)."""
        P = self.law.stress(F, lam, mu)
        if self.fibres is not None:
            P = P + fibre_energy(F[:, None], *self.fibres)[1][:, 0]
        return P @ np.swapaxes(F, -1, -2) / np.maximum(np.linalg.det(F), 1e-3)[..., None, None]
