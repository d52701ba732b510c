"""Hyperelastic constitutive laws: energy density, first Piola-Kirchhoff stress and its tangent at a deformation
gradient (docs/materials.md: the models, which a scene needs, and their tests).

A law is a small object (:class:`Law`) evaluated at quadrature points: F (..., 3, 3) the deformation gradients
(F_ij = dx_i / dX_j), lam and mu (...) the Lame parameters [Pa] of the isotropic LinearElastic material, each law
parametrised so that its small-strain limit is that material (its tangent at F = I is the isotropic elasticity
tensor of lam and mu, tested):

- :class:`SmallStrain` ("linear"): psi = mu |eps|^2 + lam/2 tr(eps)^2, eps = sym(F) - I. Not invariant under
  rotation: a turned body stores energy. The law of FemBody(model="linear"), which steps it by its own fast path
  (a constant matrix); here for reference and the contract tests.
- :class:`Corotated` ("corotated", the fixed corotated model of Stomakhin et al. 2012): psi = mu |F - R|^2 +
  lam/2 (J - 1)^2, R the polar rotation of F, J = det F. Rotation invariant, defined for inverted F.
- :class:`StableNeoHookean` ("neo-hookean", Smith, de Goes and Kim 2018): psi = mu'/2 (I_C - 3) + lam'/2 (J - a)^2
  - mu'/2 log(I_C + 1) - psi_0 with I_C = |F|^2, mu' = 4/3 mu, lam' = lam + 5/6 mu, a = 1 + mu / lam' (rest
  stress free) and psi_0 its value at rest. Rotation invariant, smooth and finite for inverted and flattened
  elements (no log J), stiffening in compression where a linear model does not.

The tangents are analytic; :func:`project_spd` makes them positive semi-definite per point for Newton's method.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from .rotation import polar_rotation

# Levi-Civita symbol: the second derivative of det F is eps_ikm eps_jln F_mn
_LEVI = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI[_i, _j, _k], _LEVI[_i, _k, _j] = 1.0, -1.0
_DET_HESSIAN = np.einsum("ikm,jln->ijklmn", _LEVI, _LEVI).reshape(81, 9)  # (ijkl, mn)
_I3 = np.eye(3)
_AXIAL = -np.einsum("pil->ilp", _LEVI).reshape(3, 9)  # (i, (l p)): -eps_pil
_CROSS = -_LEVI.reshape(3, 9)  # (n, (j m)): [w]x_jm = -eps_jmn w_n
_II = np.einsum("ik,jl->ijkl", _I3, _I3)  # d F_ij / d F_kl


def cofactor(F: np.ndarray) -> np.ndarray:
    """cof F = det(F) F^-T (..., 3, 3), the derivative of det F by F; its columns are cross products of F's."""
    C = np.empty_like(F)
    C[..., :, 0] = np.cross(F[..., :, 1], F[..., :, 2])
    C[..., :, 1] = np.cross(F[..., :, 2], F[..., :, 0])
    C[..., :, 2] = np.cross(F[..., :, 0], F[..., :, 1])
    return C


def det_hessian(F: np.ndarray) -> np.ndarray:
    """d^2 det F / dF_ij dF_kl = eps_ikm eps_jln F_mn, (..., 3, 3, 3, 3)."""
    return (F.reshape(F.shape[:-2] + (9,)) @ _DET_HESSIAN.T).reshape(F.shape[:-2] + (3, 3, 3, 3))


def rotation_derivative(R: np.ndarray, F: np.ndarray) -> np.ndarray:
    """dR_ij / dF_kl (..., 3, 3, 3, 3) of the polar rotation R of F. With S = R^T F and dF = e_k e_l^T:
    R^T dR = [w]x, w = (tr(S) I - S)^-1 axial(R^T dF - dF^T R), and axial(R^T e_k e_l^T - e_l e_k^T R)_p =
    -eps_pil R_ki ([b]x_ij = -eps_ijn b_n). Where tr(S) I - S is singular (two singular values summing to zero, an
    element flattened and turned inside out) the rotation's change is left out there."""
    lead = F.shape[:-2]
    S = np.swapaxes(R, -1, -2) @ F
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    trS = np.trace(S, axis1=-2, axis2=-1)
    T = trS[..., None, None] * _I3 - S
    a = (R @ _AXIAL).reshape(lead + (9, 3))  # a[(k l), p] = -sum_i R_ki eps_pil
    ok = np.abs(np.linalg.det(T)) > 1e-12 * np.abs(trS) ** 3 + 1e-300
    Tinv = np.linalg.inv(np.where(ok[..., None, None], T, _I3)) * ok[..., None, None]
    w = a @ np.swapaxes(Tinv, -1, -2)  # (..., 9, 3): w for each direction (k l)
    W = (w @ _CROSS).reshape(lead + (9, 3, 3))  # [w]x
    dR = R[..., None, :, :] @ W  # (..., (k l), i, m)
    return np.moveaxis(dR.reshape(lead + (3, 3, 3, 3)), (-4, -3), (-2, -1))


def project_spd(A: np.ndarray) -> np.ndarray:
    """The tangents A (..., 3, 3, 3, 3) made symmetric positive semi-definite as (9, 9) matrices: their negative
    eigenvalues set to zero."""
    shape = A.shape
    M = A.reshape(-1, 9, 9)
    lam, V = np.linalg.eigh(0.5 * (M + np.swapaxes(M, -1, -2)))  # (about 12 us a point on this machine)
    return ((V * np.maximum(lam, 0.0)[..., None, :]) @ np.swapaxes(V, -1, -2)).reshape(shape)


class Law(Protocol):
    """A hyperelastic constitutive law: the strain energy density psi(F) [J/m^3], the first Piola-Kirchhoff stress
    P = dpsi/dF [Pa] and its tangent dP_ij/dF_kl [Pa], of F (..., 3, 3) with the Lame parameters lam, mu (...)
    [Pa]. ``name``: how FemBody(model=...) names it; ``rotation_invariant``: psi(Q F) = psi(F) for any rotation Q."""

    name: str
    rotation_invariant: bool

    def energy(self, F: np.ndarray, lam: np.ndarray, mu: np.ndarray) -> np.ndarray: ...

    def stress(self, F: np.ndarray, lam: np.ndarray, mu: np.ndarray) -> np.ndarray: ...

    def tangent(self, F: np.ndarray, lam: np.ndarray, mu: np.ndarray) -> np.ndarray: ...


def _bc(p, F: np.ndarray, extra: int = 0) -> np.ndarray:
    """A parameter (...) broadcast against F's leading axes, with ``extra`` trailing axes of one."""
    p = np.asarray(p, dtype=float)
    return np.broadcast_to(p, F.shape[:-2]).reshape(F.shape[:-2] + (1,) * extra)


class SmallStrain:
    """psi = mu |eps|^2 + lam/2 tr(eps)^2 with eps = sym(F) - I: small-strain linear elasticity (no rotation)."""

    name = "linear"
    rotation_invariant = False

    @staticmethod
    def _strain(F: np.ndarray) -> np.ndarray:
        return 0.5 * (F + np.swapaxes(F, -1, -2)) - _I3

    def energy(self, F, lam, mu):
        eps = self._strain(F)
        tr = np.trace(eps, axis1=-2, axis2=-1)
        return _bc(mu, F) * np.sum(eps * eps, axis=(-2, -1)) + 0.5 * _bc(lam, F) * tr * tr

    def stress(self, F, lam, mu):
        eps = self._strain(F)
        tr = np.trace(eps, axis1=-2, axis2=-1)
        return 2.0 * _bc(mu, F, 2) * eps + (_bc(lam, F) * tr)[..., None, None] * _I3

    def tangent(self, F, lam, mu):
        sym = _II + np.einsum("il,jk->ijkl", _I3, _I3)
        return _bc(mu, F, 4) * sym + _bc(lam, F, 4) * np.einsum("ij,kl->ijkl", _I3, _I3)


class Corotated:
    """The fixed corotated model: psi = mu |F - R|^2 + lam/2 (J - 1)^2 (Stomakhin et al. 2012)."""

    name = "corotated"
    rotation_invariant = True

    def energy(self, F, lam, mu):
        R = polar_rotation(F)
        J = np.linalg.det(F)
        return _bc(mu, F) * np.sum((F - R) ** 2, axis=(-2, -1)) + 0.5 * _bc(lam, F) * (J - 1.0) ** 2

    def stress(self, F, lam, mu):
        R = polar_rotation(F)
        J = np.linalg.det(F)
        return 2.0 * _bc(mu, F, 2) * (F - R) + (_bc(lam, F) * (J - 1.0))[..., None, None] * cofactor(F)

    def tangent(self, F, lam, mu):
        R = polar_rotation(F)
        J = np.linalg.det(F)
        C = cofactor(F)
        lam4 = _bc(lam, F, 4)
        return (2.0 * _bc(mu, F, 4) * (_II - rotation_derivative(R, F))
                + lam4 * np.einsum("...ij,...kl->...ijkl", C, C)
                + lam4 * (J - 1.0)[..., None, None, None, None] * det_hessian(F))


class StableNeoHookean:
    """The stable neo-Hookean model of Smith, de Goes and Kim (2018), in the Lame parameters of its small-strain
    limit (module doc)."""

    name = "neo-hookean"
    rotation_invariant = True

    @staticmethod
    def parameters(lam, mu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mu', lam', a) of the energy from the Lame parameters of its linearisation."""
        lam, mu = np.asarray(lam, float), np.asarray(mu, float)
        lam_s = lam + 5.0 / 6.0 * mu
        mu_s = 4.0 / 3.0 * mu
        return mu_s, lam_s, 1.0 + mu / lam_s

    def energy(self, F, lam, mu):
        mu_s, lam_s, a = (_bc(p, F) for p in self.parameters(lam, mu))
        Ic = np.sum(F * F, axis=(-2, -1))
        J = np.linalg.det(F)
        rest = 0.5 * lam_s * (1.0 - a) ** 2 - 0.5 * mu_s * np.log(4.0)
        return 0.5 * mu_s * (Ic - 3.0) + 0.5 * lam_s * (J - a) ** 2 - 0.5 * mu_s * np.log1p(Ic) - rest

    def stress(self, F, lam, mu):
        mu_s, lam_s, a = (_bc(p, F) for p in self.parameters(lam, mu))
        Ic = np.sum(F * F, axis=(-2, -1))
        J = np.linalg.det(F)
        return ((mu_s * (1.0 - 1.0 / (Ic + 1.0)))[..., None, None] * F
                + (lam_s * (J - a))[..., None, None] * cofactor(F))

    def tangent(self, F, lam, mu):
        mu_s, lam_s, a = (_bc(p, F) for p in self.parameters(lam, mu))
        Ic = np.sum(F * F, axis=(-2, -1))
        J = np.linalg.det(F)
        C = cofactor(F)
        e = (..., None, None, None, None)
        return ((mu_s * (1.0 - 1.0 / (Ic + 1.0)))[e] * _II
                + (2.0 * mu_s / (Ic + 1.0) ** 2)[e] * np.einsum("...ij,...kl->...ijkl", F, F)
                + lam_s[e] * np.einsum("...ij,...kl->...ijkl", C, C)
                + (lam_s * (J - a))[e] * det_hessian(F))


LAWS: dict[str, Law] = {law.name: law for law in (SmallStrain(), Corotated(), StableNeoHookean())}
