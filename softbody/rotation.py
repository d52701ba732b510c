"""Batched polar decomposition: the rotation of F = R P with det R = +1."""
from __future__ import annotations

import numpy as np


def _svd_rotation(F: np.ndarray) -> np.ndarray:
    """Rotation by SVD (n, 3, 3); the reflection of an inverted F goes to its smallest singular direction."""
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = np.linalg.det(R) < 0.0
    if np.any(flip):
        U[flip, :, 2] *= -1.0
        R[flip] = U[flip] @ Vt[flip]
    return R


def _det3(F: np.ndarray) -> np.ndarray:
    """Determinants of (n, 3, 3) matrices by cofactors (much faster than a batched LU for 3x3)."""
    return (F[:, 0, 0] * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
            - F[:, 0, 1] * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
            + F[:, 0, 2] * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))


def _newton_rotation(F: np.ndarray, tol: float, max_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """Scaled Newton iteration R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3), on components.

    F: (n, 3, 3) with det F > 0. Returns R and a mask of the matrices that converged.
    """
    a = [[F[:, i, j].copy() for j in range(3)] for i in range(3)]
    for _ in range(max_iter):
        c = [[a[(i + 1) % 3][(j + 1) % 3] * a[(i + 2) % 3][(j + 2) % 3]
              - a[(i + 1) % 3][(j + 2) % 3] * a[(i + 2) % 3][(j + 1) % 3] for j in range(3)] for i in range(3)]
        d = a[0][0] * c[0][0] + a[0][1] * c[0][1] + a[0][2] * c[0][2]  # det; c / d = R^-T
        g = np.abs(d) ** (-1.0 / 3.0)
        gi = 0.5 / (g * d)
        g *= 0.5
        err = np.zeros_like(d)
        for i in range(3):
            for j in range(3):
                new = g * a[i][j] + gi * c[i][j]
                err = np.maximum(err, np.abs(new - a[i][j]))
                a[i][j] = new
        if err.max(initial=0.0) < tol:
            break
    R = np.stack([np.stack(row, axis=-1) for row in a], axis=-2)
    return R, err < tol


def polar_rotation(F: np.ndarray, tol: float = 1e-12, max_iter: int = 30) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R P, batched over leading axes.

    F: (..., 3, 3). Returns R (..., 3, 3), orthonormal with det R = +1, also for inverted
    (det F < 0) and degenerate F (Irving et al. 2006: the reflection goes to the smallest
    singular direction). Well-shaped F use a scaled Newton iteration (quadratic convergence,
    a few element-wise numpy operations); inverted, degenerate or non-converged ones use SVD.
    """
    shape = F.shape
    F = np.asarray(F, dtype=float).reshape(-1, 3, 3)
    det = _det3(F)
    scale = np.abs(F).max(axis=(1, 2))
    good = det > 1e-6 * scale**3
    if good.all():  # the usual case: no copies
        R, ok = _newton_rotation(F, tol, max_iter)
        if not ok.all():
            R[~ok] = _svd_rotation(F[~ok])
        return R.reshape(shape)
    R = np.empty_like(F)
    if good.any():
        Rg, ok = _newton_rotation(F[good], tol, max_iter)
        R[good] = Rg
        redo = np.flatnonzero(good)[~ok]
        if redo.size:
            R[redo] = _svd_rotation(F[redo])
    if (~good).any():
        R[~good] = _svd_rotation(F[~good])
    return R.reshape(shape)
