"""The frictional contact problem of one step on a small dense system (the Delassus form).

m contacts, each with an impulse gamma_i = (g_n, g_t1, g_t2) in its frame (n, t1, t2) and a relative
velocity w_i (soft point minus rigid point, same frame) at the end of the step, linear in all impulses:

    w = w0 + D gamma        (D (3m, 3m): the soft bodies' and rigid bodies' response; contact-major order)

Sought: for every contact, either inactive (gamma_i = 0, w_n + b >= 0, b = gap / h), or active with
w_n + b = 0 and g_n >= 0, and then sticking (w_t = 0, |g_t| <= mu g_n) or sliding (g_t = mu g_n d with d
opposite to the sliding velocity w_t).

The solver is exact for the contact state it settles on: an active set on the normals (all violations
flipped at once while that makes progress; one at a time, the worst first, once a set repeats), inside a
fixed point on the friction state (stick turns to slip when the needed force leaves the cone, slip to
stick when the sliding reverses or stops, sliding directions follow the sliding velocity). Each iteration
is one dense solve of the active unknowns: cheap next to the sparse solves that built D.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class ContactState:
    """active (m,), stick (m,) (of the active ones, with friction), direction (m, 2): the unit tangential
    direction of a sliding contact's friction force in its frame."""

    active: np.ndarray
    stick: np.ndarray
    direction: np.ndarray


def _solve_set(D: np.ndarray, w0: np.ndarray, bias: np.ndarray, mu: np.ndarray, st: ContactState) -> np.ndarray:
    """Impulses gamma (m, 3) with the normals of the active contacts closing their gaps, the sticking ones'
    tangents zero, the sliding ones' friction mu g_n along their directions, the inactive ones zero."""
    m = len(bias)
    act = np.flatnonzero(st.active)
    stick = act[st.stick[act]]
    slide = act[~st.stick[act] & (mu[act] > 0)]
    # unknowns: the active normals, then the sticking tangents (two each)
    unknown = np.concatenate([3 * act, (3 * stick[:, None] + np.array([1, 2])).ravel()])
    k = len(unknown)
    gamma = np.zeros(3 * m)
    if not k:
        return gamma.reshape(m, 3)
    T = np.zeros((3 * m, k))  # gamma = T x
    T[unknown, np.arange(k)] = 1.0
    col = {int(i): j for j, i in enumerate(act)}
    for i in slide.tolist():
        T[3 * i + 1:3 * i + 3, col[i]] = mu[i] * st.direction[i]
    E = unknown  # the equations: the same components of w (+ b on the normals) vanish
    rhs = -w0[E].copy()
    rhs[:len(act)] -= bias[act]
    A = D[E] @ T
    try:
        x = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(A, rhs, rcond=None)[0]
    return (T @ x).reshape(m, 3)


def solve_contacts(D: np.ndarray, w0: np.ndarray, bias: np.ndarray, mu: np.ndarray, state: ContactState,
                   eligible: Callable[[np.ndarray], np.ndarray] | None = None, velocity_tol: float = 1e-7,
                   cone_tol: float = 1e-3, direction_tol: float = 1e-3, max_friction: int = 20
                   ) -> tuple[np.ndarray, ContactState, int]:
    """Solve the contact problem of the module doc from the warm start ``state`` (changed in place).

    D (3m, 3m), w0 (3m,), bias (m,) [m/s], mu (m,); eligible(gamma (m, 3)) -> (m,) bool: which inactive
    contacts may be added (None: all). Returns gamma (m, 3) [N s], the state and the number of solves."""
    m = len(bias)
    st = state
    st.stick &= st.active & (mu > 0)
    solves = 0
    gamma = np.zeros((m, 3))
    for _ in range(max_friction):
        # the normals: an active set with the friction state fixed
        seen: set[bytes] = set()
        single = False
        for _ in range(4 * m + 20):
            gamma = _solve_set(D, w0, bias, mu, st)
            solves += 1
            w = (w0 + D @ gamma.ravel()).reshape(m, 3)
            gap = w[:, 0] + bias
            pull = st.active & (gamma[:, 0] < 0)
            close = ~st.active & (gap < -velocity_tol)
            if eligible is not None and close.any():
                close &= eligible(gamma)
            if not pull.any() and not close.any():
                break
            key = st.active.tobytes()
            if key in seen:
                single = True  # the set repeats: flip one contact at a time from now on
            seen.add(key)
            if single:
                score = np.where(pull, -gamma[:, 0] / max(np.abs(gamma[:, 0]).max(), 1e-300), 0.0)
                score = np.maximum(score, np.where(close, -gap / max(np.abs(gap).max(), 1e-300), 0.0))
                i = int(np.argmax(score))
                pull, close = np.zeros(m, bool), np.zeros(m, bool)
                (pull if st.active[i] else close)[i] = True
            st.active = (st.active & ~pull) | close
            st.stick = (st.stick & st.active) | (close & (mu > 0))
        # the friction state
        act = st.active & (mu > 0)
        gn = np.maximum(gamma[:, 0], 0.0)
        gt = gamma[:, 1:]
        gtn = np.linalg.norm(gt, axis=1)
        wt = w[:, 1:]
        wtn = np.linalg.norm(wt, axis=1)
        to_slip = act & st.stick & (gtn > mu * gn * (1 + cone_tol))
        sliding = act & ~st.stick
        along = np.einsum("mi,mi->m", wt, st.direction) > 0  # sliding along the friction force: it stopped
        to_stick = sliding & (along | (wtn < velocity_tol))
        with np.errstate(invalid="ignore", divide="ignore"):
            new_dir = np.where(wtn[:, None] > 0, -wt / wtn[:, None], st.direction)
        turn = sliding & ~to_stick & (np.abs(new_dir - st.direction).max(axis=1) > direction_tol)
        if not (to_slip.any() or to_stick.any() or turn.any()):
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            st.direction = np.where(to_slip[:, None], gt / np.maximum(gtn, 1e-300)[:, None], st.direction)
        st.direction = np.where(turn[:, None], new_dir, st.direction)
        st.stick = (st.stick & ~to_slip) | to_stick
    return gamma, st, solves
