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


@dataclass(frozen=True, eq=False)
class Regions:
    """Isotropic linear elastic materials by element: a body of several regions. ``materials`` (R,) LinearElastic;
    ``labels`` (E,) int: each element's region (0 <= label < R). ``E``, ``nu``, ``density``: the per-element arrays
    (E,) of the regions' values (``softest`` and ``largest_nu``: what one number stands for, in colour scales and the
    locking warning)."""

    materials: tuple
    labels: np.ndarray

    def __post_init__(self) -> None:
        mats = tuple(self.materials) if isinstance(self.materials, (list, tuple)) else None
        if not mats or not all(isinstance(m, LinearElastic) for m in mats):
            raise InvalidInputError("Regions(materials, labels): materials must be a non-empty list of LinearElastic, "
                                    f"got {self.materials!r}")
        labels = np.asarray(self.labels)
        if labels.ndim != 1 or not np.issubdtype(labels.dtype, np.integer):
            raise InvalidInputError(f"Regions labels must be a 1-D integer array (one region per element), got shape "
                                    f"{labels.shape} of {labels.dtype}")
        if len(labels) and (labels.min() < 0 or labels.max() >= len(mats)):
            raise InvalidInputError(f"Regions labels must lie in [0, {len(mats)}) (one per material), got "
                                    f"{labels.min()} to {labels.max()}")
        labels = labels.astype(np.int64)  # a copy, read-only: a body's element matrices were made of it
        labels.flags.writeable = False
        object.__setattr__(self, "materials", mats)
        object.__setattr__(self, "labels", labels)

    def _per_element(self, name: str) -> np.ndarray:
        return np.array([getattr(m, name) for m in self.materials], float)[self.labels]

    @property
    def E(self) -> np.ndarray:
        return self._per_element("E")

    @property
    def nu(self) -> np.ndarray:
        return self._per_element("nu")

    @property
    def density(self) -> np.ndarray:
        return self._per_element("density")

    @property
    def lame(self) -> tuple[np.ndarray, np.ndarray]:
        """Lame parameters (lambda (E,), mu (E,)) per element [Pa]."""
        lm = np.array([m.lame for m in self.materials], float)[self.labels]
        return lm[:, 0], lm[:, 1]

    @property
    def softest(self) -> float:
        return float(min(m.E for m in self.materials))

    @property
    def largest_nu(self) -> float:
        return float(max(m.nu for m in self.materials))
