"""Batched polar decomposition: the rotation of F = R P with det R = +1."""
from __future__ import annotations

import numpy as np


def polar_rotation(F: np.ndarray) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R P, batched over leading axes.

    F: (..., 3, 3). Returns R: (..., 3, 3) with R^T R = I and det R = +1, also for
    inverted (det F < 0) and degenerate F: the sign flip goes to the direction of the
    smallest singular value, as in Irving et al. 2006.
    """
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = np.linalg.det(R) < 0.0
    if np.any(flip):
        U = U.copy()
        U[flip, :, 2] *= -1.0
        R[flip] = U[flip] @ Vt[flip]
    return R
