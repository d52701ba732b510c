"""Batched polar decomposition: the rotation of F = R P with det R = +1.

Two layouts: ``polar_rotation`` takes matrices (..., 3, 3); ``polar_rotation_components`` takes
them component-major, a (9, n) array whose row 3 i + j holds entry (i, j) of every matrix. The
second is what the step uses: every operation of the Newton iteration is then one numpy call on
a contiguous row of n numbers.
"""
from __future__ import annotations

import numpy as np

from . import kernels


def _svd_rotation(F: np.ndarray) -> np.ndarray:
    """Rotation by SVD (n, 3, 3); the reflection of an inverted F goes to its smallest singular direction."""
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = np.linalg.det(R) < 0.0
    if np.any(flip):
        U[flip, :, 2] *= -1.0
        R[flip] = U[flip] @ Vt[flip]
    return R


def _comp(A: np.ndarray, i: int, j: int) -> np.ndarray:
    """Row of component (i mod 3, j mod 3) of a component-major (9, n) array."""
    return A[3 * (i % 3) + j % 3]


def _cofactors(A: np.ndarray, C: np.ndarray, t: np.ndarray) -> None:
    """Cofactor matrices of A (9, n) into C (9, n) (C / det A = A^-T); t (n,) is scratch."""
    for i in range(3):
        for j in range(3):
            c = C[3 * i + j]
            np.multiply(_comp(A, i + 1, j + 1), _comp(A, i + 2, j + 2), out=c)
            np.multiply(_comp(A, i + 1, j + 2), _comp(A, i + 2, j + 1), out=t)
            c -= t


def _det(A: np.ndarray, C: np.ndarray, out: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Determinants (n,) from A and its cofactors C (first-row expansion)."""
    np.multiply(A[0], C[0], out=out)
    for j in (1, 2):
        np.multiply(A[j], C[j], out=t)
        out += t
    return out


def _newton_rotation(F9: np.ndarray, tol: float, max_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """Scaled Newton iteration R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3), component-major.

    F9: (9, n) with det F > 0. Convergence is quadratic: once an update changes R by less than
    sqrt(tol) (largest entry), the remaining error is of the order of tol, and the iteration stops. The first two
    updates are not checked (they are never that small unless F is already a rotation). Every
    operation writes into a buffer. Returns R (9, n) and a mask (n,) of the converged matrices.
    """
    n = F9.shape[1]
    A = np.array(F9, dtype=float)
    new, C = np.empty_like(A), np.empty_like(A)
    d, g, gi, t = (np.empty(n) for _ in range(4))
    err = np.full(n, np.inf)
    step_tol = np.sqrt(tol)
    for it in range(max_iter):
        _cofactors(A, C, t)
        _det(A, C, d, t)
        np.abs(d, out=g)
        np.cbrt(g, out=g)
        np.reciprocal(g, out=g)  # g = |det|^(-1/3)
        np.multiply(g, d, out=gi)
        np.divide(0.5, gi, out=gi)
        g *= 0.5
        np.multiply(A, g, out=new)
        C *= gi
        new += C
        check = it >= 2 or it == max_iter - 1
        if check:
            np.subtract(new, A, out=C)
            np.abs(C, out=C)
            C.max(axis=0, out=err)
        A, new = new, A
        if check and err.max(initial=0.0) < step_tol:
            break
    return A, err < step_tol


def polar_rotation_components(F9: np.ndarray, tol: float = 1e-12, max_iter: int = 30) -> np.ndarray:
    """Rotation factors R (9, n) of the polar decompositions F = R P, component-major (see module doc).

    R is orthonormal with det R = +1, also for inverted (det F < 0) and degenerate F (Irving et al.
    2006: the reflection goes to the smallest singular direction). Well-shaped F use a scaled Newton
    iteration (quadratic convergence, a few element-wise numpy operations) to an error below tol;
    inverted, degenerate or non-converged ones use SVD.
    """
    F9 = np.asarray(F9, dtype=float)
    n = F9.shape[1]
    if kernels.ENABLED:  # the same iteration, compiled, element by element (softbody.kernels)
        R, ok = np.empty_like(F9), np.empty(n, dtype=bool)
        kernels.polar_newton(F9, tol, max_iter, R, ok)
        bad = np.flatnonzero(~ok)
        if bad.size:
            R[:, bad] = _svd_rotation(F9[:, bad].T.reshape(-1, 3, 3)).reshape(-1, 9).T
        return R
    C, t = np.empty_like(F9), np.empty(n)
    _cofactors(F9, C, t)
    det = _det(F9, C, np.empty(n), t)
    scale = np.abs(F9).max(axis=0)
    good = det > 1e-6 * scale**3
    if good.all():  # the usual case: no copies
        R, ok = _newton_rotation(F9, tol, max_iter)
        bad = np.flatnonzero(~ok)
    else:
        R = np.empty_like(F9)
        idx = np.flatnonzero(good)
        R[:, idx], ok = _newton_rotation(F9[:, idx], tol, max_iter)
        bad = np.concatenate([np.flatnonzero(~good), idx[~ok]])
    if bad.size:
        R[:, bad] = _svd_rotation(F9[:, bad].T.reshape(-1, 3, 3)).reshape(-1, 9).T
    return R


def polar_rotation(F: np.ndarray, tol: float = 1e-12, max_iter: int = 30) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R P, batched over leading axes.

    F: (..., 3, 3). Returns R (..., 3, 3); see :func:`polar_rotation_components`.
    """
    shape = F.shape
    F9 = np.ascontiguousarray(np.asarray(F, dtype=float).reshape(-1, 9).T)
    return np.ascontiguousarray(polar_rotation_components(F9, tol, max_iter).T).reshape(shape)
