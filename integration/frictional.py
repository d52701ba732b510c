"""The frictional contact problem of one step on a small dense system (the Delassus form).

m contacts, each with an impulse gamma_i = (g_n, g_t1, g_t2) [N s] in its frame (n, t1, t2) and a relative
velocity w_i (soft point minus rigid point, same frame) at the end of the step, linear in all impulses:

    w = w0 + D gamma        (D (3m, 3m) symmetric positive definite: the response; contact-major order)

Sought: for every contact g_n >= 0, w_n + b >= 0 (b = gap / h) and g_n (w_n + b) = 0 (non-penetration and
separation), and Coulomb friction: sticking (w_t = 0, |g_t| <= mu g_n) or sliding (g_t = mu g_n d, d opposite
to the sliding velocity w_t).

Solved as a fixed point on the friction state around a convex problem: with the sticking contacts' tangents
free and the sliding contacts' friction impulses given, the impulses minimise the convex quadratic
1/2 gamma^T D gamma + gamma^T (w0 + b) under g_n >= 0, whose optimality conditions are exactly the normal
conditions above and w_t = 0 on the sticking contacts. A projected Newton method solves it (monotone,
finitely many active-set changes for a strictly convex quadratic). Between solves, a sticking contact
whose force leaves the cone turns to sliding, a sliding one whose velocity reverses or stops turns to
sticking, sliding impulses follow the new normal impulses and sliding directions. Non-penetration holds
exactly after every solve, whatever the friction iteration ends on.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import kernels


@dataclass
class ContactState:
    """active (m,), stick (m,) (of the active ones, with friction), direction (m, 2): the unit tangential
    direction of a sliding contact's friction force in its frame."""

    active: np.ndarray
    stick: np.ndarray
    direction: np.ndarray


def bounded_quadratic(Q: np.ndarray, c: np.ndarray, bounded: np.ndarray, x0: np.ndarray | None = None,
                      tol: float = 1e-12, max_iter: int = 200) -> tuple[np.ndarray, int]:
    """argmin 1/2 x^T Q x + c^T x subject to x_i >= 0 where ``bounded`` (n,) bool, for Q symmetric positive
    definite (n, n): Bertsekas' projected Newton method with an Armijo search along the projected arc.
    Returns x (n,) and the number of Newton steps."""
    if kernels.ENABLED:  # the same method, compiled (integration.kernels)
        x0 = np.zeros(len(c)) if x0 is None else x0
        a = np.ascontiguousarray
        return kernels.bounded_quadratic(a(Q, dtype=float), a(c, dtype=float), a(bounded, dtype=bool),
                                         a(x0, dtype=float), float(tol), int(max_iter))
    n = len(c)
    x = np.zeros(n) if x0 is None else np.where(bounded, np.maximum(x0, 0.0), x0)

    def f(y):
        return 0.5 * y @ (Q @ y) + c @ y

    fx = f(x)
    scale = max(np.abs(c).max(initial=0.0), 1e-300)
    for it in range(1, max_iter + 1):
        g = Q @ x + c
        # the bound variables held at zero by a gradient pushing outwards
        eps = min(1e-12 * max(np.abs(x).max(initial=0.0), 1.0), np.linalg.norm(np.where(bounded, x - np.maximum(x - g, 0.0), g)))
        held = bounded & (x <= eps) & (g > 0)
        free = ~held
        # optimality: the projected gradient vanishes
        pg = np.where(bounded, x - np.maximum(x - g, 0.0), g)
        if np.abs(pg).max(initial=0.0) <= tol * scale:
            return x, it - 1
        d = np.zeros(n)
        Qf = Q[np.ix_(free, free)]
        try:
            d[free] = -np.linalg.solve(Qf, g[free])
        except np.linalg.LinAlgError:
            d[free] = -np.linalg.lstsq(Qf, g[free], rcond=None)[0]
        alpha = 1.0
        for _ in range(40):
            y = x + alpha * d
            y = np.where(bounded, np.maximum(y, 0.0), y)
            fy = f(y)
            # Armijo on the projected arc (Bertsekas 1982)
            if fy <= fx + 1e-4 * (g[free] @ (y - x)[free]) + 1e-4 * (g[held] @ (y - x)[held]):
                break
            alpha *= 0.5
        else:
            return x, it
        x, fx = y, fy
    return x, max_iter


def solve_contacts(D: np.ndarray, w0: np.ndarray, bias: np.ndarray, mu: np.ndarray, state: ContactState,
                   eligible: Callable[[np.ndarray], np.ndarray] | None = None, velocity_tol: float = 1e-7,
                   cone_tol: float = 1e-3, direction_tol: float = 1e-3, max_friction: int = 12
                   ) -> tuple[np.ndarray, ContactState, int]:
    """Solve the contact problem of the module doc from the warm start ``state`` (changed in place).

    D (3m, 3m), w0 (3m,), bias (m,) [m/s], mu (m,); eligible(gamma (m, 3)) -> (m,) bool: which contacts
    may carry an impulse after a solve that gave gamma (None: all). Returns gamma (m, 3) [N s], the state and
    the number of Newton steps taken."""
    m = len(bias)
    st = state
    friction = mu > 0
    st.stick &= st.active & friction
    allowed = np.ones(m, dtype=bool) if eligible is None else (st.active | eligible(np.zeros((m, 3))))
    gamma = np.zeros((m, 3))
    gn_prev = np.zeros(m)
    steps = 0

    def solve(slide: np.ndarray, stuck: np.ndarray, gn_used: np.ndarray, gamma: np.ndarray) -> tuple[np.ndarray, int]:
        """The convex problem with the sticking contacts' tangents free and the sliding ones' friction given
        (mu gn_used along their directions); returns gamma (m, 3) and the Newton steps."""
        if kernels.ENABLED:  # the lines below and bounded_quadratic in one compiled call (integration.kernels)
            c = np.ascontiguousarray
            return kernels.friction_subproblem(c(D, dtype=float), c(w0, dtype=float), c(bias, dtype=float),
                                               c(mu, dtype=float), c(st.direction, dtype=float), c(slide), c(stuck),
                                               c(allowed), c(gn_used, dtype=float), c(gamma, dtype=float), 1e-12, 200)
        normal = np.flatnonzero(allowed)
        stick = np.flatnonzero(stuck & allowed)
        idx = np.concatenate([3 * normal, (3 * stick[:, None] + np.array([1, 2])).ravel()])
        bounded = np.r_[np.ones(len(normal), bool), np.zeros(2 * len(stick), bool)]
        fixed = np.zeros((m, 3))
        fixed[slide, 1:] = (mu[slide] * gn_used[slide])[:, None] * st.direction[slide]
        c = (w0 + D @ fixed.ravel()).copy()
        c[0::3] += bias
        x, k = bounded_quadratic(D[np.ix_(idx, idx)], c[idx], bounded, gamma.ravel()[idx])
        out = fixed.ravel()
        out[idx] = x
        return out.reshape(m, 3), k

    for _ in range(max_friction):
        slide = st.active & friction & ~st.stick
        # the sliding contacts' friction impulses, given: mu g_n (of the last solve) along their directions
        gn_used = np.maximum(np.where(gn_prev > 0, gn_prev, gamma[:, 0]), 0.0)
        gamma, k = solve(slide, st.stick, gn_used, gamma)
        steps += k
        gn_prev = gamma[:, 0].copy()
        w = (w0 + D @ gamma.ravel()).reshape(m, 3)
        active = gamma[:, 0] > 0
        # face contacts that the solution moved off their triangles carry nothing; others may join
        if eligible is not None:
            ok = eligible(gamma)
            new_allowed = (allowed & (active | ok)) | (ok & (w[:, 0] + bias < -velocity_tol))
        else:
            new_allowed = allowed
        # the friction state
        gt = gamma[:, 1:]
        gtn = np.linalg.norm(gt, axis=1)
        wt = w[:, 1:]
        wtn = np.linalg.norm(wt, axis=1)
        was_stick = st.stick & active
        to_slip = was_stick & (gtn > mu * gamma[:, 0] * (1 + cone_tol))
        sliding = slide & active
        along = np.einsum("mi,mi->m", wt, st.direction) > 0  # sliding along its friction force: it stopped
        to_stick = sliding & (along | (wtn < velocity_tol))
        with np.errstate(invalid="ignore", divide="ignore"):
            new_dir = np.where(wtn[:, None] > 0, -wt / wtn[:, None], st.direction)
        turn = sliding & ~to_stick & (np.abs(new_dir - st.direction).max(axis=1) > direction_tol)
        # a new contact starts sticking, unless its surfaces slide past each other: then sliding, against that
        # (starting to stick would stop a sliding body dead until the iteration lets it go)
        joined = active & friction & ~st.active
        joined_sliding = joined & (wtn > velocity_tol)
        left = st.active & ~active
        # a sliding contact's friction followed the normal impulse of the solve before: go on while it moved
        regrip = sliding & ~to_stick & (np.abs(gamma[:, 0] - gn_used) > direction_tol * max(gamma[:, 0].max(initial=0.0),
                                                                                           1e-300))
        changed = to_slip.any() or to_stick.any() or turn.any() or joined.any() or left.any() or regrip.any() \
            or (new_allowed != allowed).any()
        with np.errstate(invalid="ignore", divide="ignore"):
            st.direction = np.where(to_slip[:, None], gt / np.maximum(gtn, 1e-300)[:, None], st.direction)
        st.direction = np.where((turn | joined_sliding)[:, None], new_dir, st.direction)
        st.stick = ((st.stick & ~to_slip) | to_stick | (joined & ~joined_sliding)) & active & friction
        st.active = active
        allowed = new_allowed
        if not changed:
            break
    # an iteration cut short may leave friction inconsistent with the last solve: an impulse without pressure
    # (sliding at the normal impulse of the solve before, or sticking with its tangents free), or a sticking
    # impulse outside the cone. Solve again with those sliding at the cone's edge (or free, without pressure)
    # until none is left; non-penetration holds after every solve.
    # So is friction that drives the slide it should resist (the friction iteration found the slide reversed but
    # had no solve left to stick it): it would feed energy into the scene; such contacts stick, and a sticking
    # contact the last solve did not hold (its state changed after it) is solved again.
    for _ in range(2 * m):
        gn, gtn = gamma[:, 0], np.linalg.norm(gamma[:, 1:], axis=1)
        w = (w0 + D @ gamma.ravel()).reshape(m, 3)
        wtn = np.linalg.norm(w[:, 1:], axis=1)
        loose = (gn <= 0) & (gtn > 0)
        over = st.stick & (gn > 0) & (gtn > mu * gn * (1 + cone_tol))
        stale = ~st.stick & (gn > 0) & (np.abs(gtn - mu * gn) > cone_tol * mu * gn)  # sliding at an old pressure
        driving = ~st.stick & friction & (gn > 0) & (np.einsum("mi,mi->m", w[:, 1:], gamma[:, 1:])
                                                       > velocity_tol * gtn)
        unheld = st.stick & (gn > 0) & ~over & (wtn > max(velocity_tol, 1e-9) * 10)
        if not (loose.any() or over.any() or stale.any() or driving.any() or unheld.any()):
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            st.direction = np.where(over[:, None], gamma[:, 1:] / np.maximum(gtn, 1e-300)[:, None], st.direction)
        st.stick = (st.stick & ~(loose | over)) | driving
        st.active = gn > 0
        slide = st.active & friction & ~st.stick
        gamma, k = solve(slide, st.stick, np.where(slide, gn, 0.0), gamma)
        steps += k
    st.active = gamma[:, 0] > 0
    st.stick &= st.active
    return gamma, st, steps
