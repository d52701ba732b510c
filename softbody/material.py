"""Isotropic small-strain linear elastic material (docs/method.md section 1)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InvalidInputError, finite_number


def isotropic_elasticity(lam: float, mu: float) -> np.ndarray:
    """The (6, 6) isotropic elasticity matrix of Lame parameters lam, mu [Pa] (Voigt order, engineering shear)."""
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[[0, 1, 2], [0, 1, 2]] = lam + 2.0 * mu
    D[[3, 4, 5], [3, 4, 5]] = mu
    return D


@dataclass(frozen=True)
class LinearElastic:
    """Isotropic linear elasticity.

    E: Young's modulus [Pa] > 0; nu: Poisson ratio, -1 < nu < 0.5; density [kg/m^3] > 0.
    """

    E: float
    nu: float
    density: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "E", finite_number(self.E, "Young's modulus E", 0.0))
        object.__setattr__(self, "density", finite_number(self.density, "density", 0.0))
        try:
            nu = float(self.nu)
        except (TypeError, ValueError):
            nu = math.nan
        if not math.isfinite(nu) or not (-1.0 < nu < 0.5):
            raise InvalidInputError(f"Poisson ratio nu must satisfy -1 < nu < 0.5, got {self.nu!r}")
        object.__setattr__(self, "nu", nu)

    @property
    def lame(self) -> tuple[float, float]:
        """Lame parameters (lambda, mu) in Pa."""
        lam = self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        mu = self.E / (2.0 * (1.0 + self.nu))
        return lam, mu

    def elasticity_matrix(self) -> np.ndarray:
        """The (6, 6) matrix D mapping Voigt strain (xx, yy, zz, xy, yz, zx; engineering shear) to stress [Pa]."""
        return isotropic_elasticity(*self.lame)

    def wave_speed(self) -> float:
        """Dilatational (P-)wave speed sqrt((lam + 2 mu) / rho) in m/s."""
        lam, mu = self.lame
        return math.sqrt((lam + 2.0 * mu) / self.density)
