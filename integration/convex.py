"""The coupled step of soft bodies, movable rigid bodies and their contacts as one convex problem.

The unknowns of a step are the soft bodies' velocities v (3N per body, the supported components fixed) and the
movable rigid bodies' velocity change du (n, against their free motion over the step). With each soft body's step
system A v = b (softbody.integrator: A = M + h C + h^2 K', SPD) and the rigid mass matrix M_r, the step minimises

    l(v, du) = sum_b (1/2 v_b^T A_b v_b - b_b^T v_b) + 1/2 du^T M_r du + sum_c l_c(vc_c)

over all of them at once, where vc_c = F_c^T (sum_s w_s v[node_s] - v_rigid,c - J_c du) is row c's relative velocity
in its frame F_c = (n, t1, t2) (a soft node or a point of a soft triangle or edge, with weights w, against a rigid
material point, or against another soft body's point with negative weights) and l_c the regularised cost of its
contact law (Castro et al. 2022, "An unconstrained convex formulation of compliant contact", SAP):

    y = R^-1 (v_hat - vc),   gamma = P_F(y) (projection on the Coulomb cone |g_t| <= mu g_n in the R norm),
    l_c = 1/2 gamma^T R gamma,   dl_c/dvc = -gamma,   G = d^2 l_c / dvc^2 (3 x 3, positive semi-definite).

The cone is exact (a second-order cone, not a pyramid); R = diag(R_n, R_t, R_t) makes the contact "near rigid":
R_n = beta^2 / (4 pi^2) w (w: an estimate of the row's Delassus diagonal, so that the contact's period is beta h,
resolved by the step), R_t = sigma w (stiction creeps at sigma w |gamma_t|), and v_hat_n = -phi / h closes the gap
phi (speculative contacts, phi > 0, act only when the step would close them). A bilateral row (an attachment) is
a cost 1/2 |y|_R^2 with gamma = y. Minimising l is the implicit step of one mechanical system whose contact
impulses act on both sides alike: momentum is exchanged exactly, energy cannot grow, and rows beside rows (a
node and a face holding the same point) only share a force.

Newton's method with an exact line search minimises l: each iteration solves

    (A + J_s^T G J_s) dv + J_s^T G J_r ddu = -grad_v,   (M_r + J_r^T G J_r) ddu + J_r^T G J_s dv = -grad_du

by one sparse Cholesky factorisation of the soft part, on the bodies' own block patterns extended by the blocks that
contacts between different bodies (or distant nodes of one) create (:class:`GroupPattern`, analysed once per
pattern and kept while the contacts stay within it), and a Schur complement for the few rigid unknowns. Its cost
follows the contacts linearly: a contact adds a few 3 x 3 blocks, never a dense row of the others.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp

from softbody.assembly import BlockPattern
from softbody.body import FemBody
from softbody.linsolve import SpdSolver

from . import kernels

#: the contact period in steps (Castro et al.'s beta): R_n = BETA^2 / (4 pi^2) w
BETA = 0.03
#: the regularisation of friction relative to the Delassus diagonal: stiction creeps at SIGMA w |gamma_t|
SIGMA = 1e-3
#: Newton stops when the scaled gradient is below REL_TOL times the scaled momentum or impulses
REL_TOL = 1e-8
#: ... or below this absolute scaled gradient [sqrt(kg) m/s]
ABS_TOL = 1e-14
#: at most this many Newton iterations per solve
MAX_ITER = 60
#: a Newton system is solved by conjugate gradients preconditioned by the last factorisation on its pattern in at most
#: this many iterations (each costs a pair of triangular solves and a sparse product), else factorised anew
REUSE_ITERATIONS = 8
#: ... to this residual, relative to the right-hand side's (an inexact Newton direction: the line search follows it)
REUSE_TOL = 1e-6
#: ... in systems of at least this many soft unknowns with rigid unknowns (each solve of the iterations then costs a
#: Schur complement's triangular solves, one per rigid unknown: a smaller system is factorised anew at less cost; the
#: Panda's grasp of a 117-node cube, 351 unknowns: held 7.8-8.2 ms a step factorised, 8.9-9.0 reused), and of at
#: least REUSE_MIN_SOFT without (a settling pile's islands of 1000-1400: 67 ms a step in the tray factorised, 45-50
#: reused)
REUSE_MIN = 3000
REUSE_MIN_SOFT = 300
#: the line search stops where the cost's slope along the step is this small relative to its slope at the start
LINE_TOL = 1e-4
#: ... or when a step no longer lowers the cost by more than this (relative): round-off
COST_TOL = 1e-14
#: where rows slide, the friction bounds are lagged on the normal impulses until Coulomb's law holds with the impulses
#: found to LAG_TOL (relative to the largest friction bound), in at most LAG_ROUNDS rounds of Newton's method
LAG_TOL = 1e-4
LAG_ROUNDS = 8
#: ... and only where the cone's solution would lift a sliding row off its surface by more than this in the step
#: (mu |v_t| h) [m]: a slow slide's lift-off stays below it (a grasp's: under 1 um in 9 steps of 10)
GLIDE_TOL = 1e-6



@dataclass
class Rows:
    """The rows of the convex problem: one per contact or attached node, three equations each.

    parts (m, S): the index of the soft part (problem order) of each slot, -1 for an unused slot; nodes (m, S);
    weights (m, S): the soft point's velocity is sum_s w_s v[node_s] (negative weights: the other side of a soft
    pair); frames (m, 3, 3): columns n, t1, t2 (n out of the other side, towards the weighted point);
    rigid_velocity (m, 3) [m/s]: the other side's point velocity under the free motion (an attachment: the node
    velocity that keeps it on its rigid point); jacobian (m, 3, n): that point's velocity per unit du (None: no
    rigid unknowns); v_hat (m,) [m/s]: the normal velocity at which the row exerts nothing (-phi / h);
    mu (m,); bilateral (m,) bool: all three components held, no cone (attachments)."""

    parts: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    frames: np.ndarray
    rigid_velocity: np.ndarray
    jacobian: np.ndarray | None
    v_hat: np.ndarray
    mu: np.ndarray
    bilateral: np.ndarray

    def __len__(self) -> int:
        return len(self.v_hat)

    @classmethod
    def concat(cls, parts: list["Rows"], n: int) -> "Rows":
        parts = [r for r in parts if r is not None and len(r)]
        slots = max([r.parts.shape[1] for r in parts], default=1)

        def padded(arrays, fill, dtype):
            """The (m_k, S_k) arrays one below the other, each padded to ``slots`` columns with ``fill``."""
            out = np.full((sum(len(a) for a in arrays), slots), fill, dtype=dtype)
            at = 0
            for a in arrays:
                out[at:at + len(a), :a.shape[1]] = a
                at += len(a)
            return out

        if not parts:
            return cls(np.zeros((0, 1), np.int64), np.zeros((0, 1), np.int64), np.zeros((0, 1)), np.zeros((0, 3, 3)),
                       np.zeros((0, 3)), np.zeros((0, 3, n)) if n else None, np.zeros(0), np.zeros(0),
                       np.zeros(0, bool))
        jac = None
        if n:
            jac = np.concatenate([r.jacobian if r.jacobian is not None else np.zeros((len(r), 3, n)) for r in parts])
        return cls(padded([r.parts for r in parts], -1, np.int64), padded([r.nodes for r in parts], 0, np.int64),
                   padded([r.weights for r in parts], 0.0, float), np.concatenate([r.frames for r in parts]),
                   np.concatenate([r.rigid_velocity for r in parts]), jac,
                   np.concatenate([r.v_hat for r in parts]), np.concatenate([r.mu for r in parts]),
                   np.concatenate([r.bilateral for r in parts]))


class MemberBlocks:
    """A stack member's blocks of the stack part's A (block rows of its nodes: blocks lo:hi of ``stack``'s block data),
    assembled with the stack's at the first call; ``ready`` once the stack's are (a product by them is cheaper)."""

    def __init__(self, stack: "SoftPart", lo: int, hi: int):
        self.stack, self.lo, self.hi = stack, lo, hi

    @property
    def ready(self) -> bool:
        return not callable(self.stack.A)

    def __call__(self) -> np.ndarray:
        return self.stack.blocks()[self.lo:self.hi]


@dataclass
class SoftPart:
    """One soft body of the problem: its step system's matrix A (block data (nnzb, 3, 3) on body.pattern, or a function
    that assembles it) and load b (N, 3), the supported components ``held`` (N, 3) bool with their velocities
    ``value`` (N, 3) (identity frames), and the starting guess (N, 3) [m/s]. ``operator``: A applied without
    assembling it (softbody.integrator.WarpedOperator: y (N, 3) -> A y, its ``diagonal()`` blocks, a stack member's
    own), None: from the blocks; ``diagonal``: A's diagonal blocks (N, 3, 3) if known."""

    body: FemBody
    A: np.ndarray | Callable[[], np.ndarray]
    b: np.ndarray
    held: np.ndarray
    value: np.ndarray
    guess: np.ndarray
    operator: Callable[[np.ndarray], np.ndarray] | None = None
    diagonal: np.ndarray | None = None

    def blocks(self) -> np.ndarray:
        """A's block data (nnzb, 3, 3), assembled at the first call if need be (a factorisation's values)."""
        if callable(self.A):
            self.A = self.A()
        return self.A

    def diagonal_blocks(self) -> np.ndarray:
        """(N, 3, 3) A's diagonal blocks."""
        if self.diagonal is None:
            self.diagonal = (self.operator.diagonal() if self.operator is not None and callable(self.A)
                             else self.blocks()[self.body.pattern.diag])
        return self.diagonal

    def apply(self, v: np.ndarray) -> np.ndarray:
        """A v (N, 3) for v (N, 3): by the operator while A is not assembled (nor the stack's it is a slice of), else by
        its blocks."""
        if self.operator is not None and callable(self.A) and not getattr(self.A, "ready", False):
            return self.operator(v)
        return self.body.pattern.product(self.blocks(), v)


@dataclass
class Solution:
    """velocities: per part (N, 3) [m/s]; du (n,); gamma (m, 3) [N s]: each row's impulse in its frame (on the weighted
    point; the other side takes minus it); stiction (m,) bool; iterations: Newton iterations; factorizations; cost:
    l at the solution; residual: the scaled gradient relative to its scale at the end; rounds: how many times the
    friction bounds were lagged; joint_gamma (k,): the joint rows' impulses in the solve (JointRows: beyond those
    applied already) [N s or N m s]."""

    velocities: list[np.ndarray]
    du: np.ndarray
    gamma: np.ndarray
    vc: np.ndarray
    stiction: np.ndarray
    iterations: int
    factorizations: int
    cost: float
    residual: float
    converged: bool
    rounds: int = 1
    joint_gamma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (k,) the joint rows' impulses


# ------------------------------------------------------------------ the contact law of one row


def regularization(w: np.ndarray, bilateral: np.ndarray) -> np.ndarray:
    """R (m, 3) [s/kg] in the rows' frames from the Delassus diagonal estimates w (m, 3) [1/kg] of their three
    directions: near rigid in the normal (period BETA h), SIGMA w in the tangents; a bilateral row near rigid in all
    three. Bounded below by the rows' rms (Drake's choice), so that no direction is stiffer than the others allow."""
    rms = np.sqrt((w * w).sum(axis=1) / 3.0)
    rigid = BETA * BETA / (4.0 * math.pi * math.pi)
    wn = np.maximum(w[:, 0], rms)
    wt = np.maximum(0.5 * (w[:, 1] + w[:, 2]), rms)
    R = np.empty_like(w)
    R[:, 0] = rigid * wn
    R[:, 1] = R[:, 2] = np.where(bilateral, rigid * wt, SIGMA * wt)
    return np.maximum(R, 1e-300)


def cone_law(vc: np.ndarray, R: np.ndarray, v_hat: np.ndarray, mu: np.ndarray, bilateral: np.ndarray,
             hessian: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """Castro et al.'s law (SAP) of rows with relative velocities vc (m, 3) (frames n, t1, t2) [m/s], regularisation R
    (m, 3) (equal tangential entries), normal bias v_hat (m,), friction mu (m,): gamma = P_F(y), the projection of
    y = R^-1 (v_hat e_n - vc) on the Coulomb cone |g_t| <= mu g_n in the R norm, the cost's Hessian G (None unless
    ``hessian``), the costs 1/2 gamma^T R gamma (m,) and whether each row sticks (m,).

    Regions (y_r = |y_t|, mu_hat = mu R_t / R_n): stiction y_r <= mu y_n (gamma = y), sliding -mu_hat y_r < y_n
    < y_r / mu (gamma_n = (y_n + mu_hat y_r) / (1 + mu mu_hat), gamma_t = mu gamma_n y_t / y_r), apart otherwise.
    Normal and tangents are coupled where a row slides: Newton's model sees the slip resisted, and converges in a few
    iterations, but a sliding row lifts off its surface by about mu |v_t| h per step (the convex relaxation of
    Coulomb's law): where that exceeds GLIDE_TOL the solve refines such rows with :func:`contact_law`
    (ConvexSolver)."""
    m = len(vc)
    inv = 1.0 / R
    y = -vc * inv
    y[:, 0] += v_hat * inv[:, 0]
    yn, yt = y[:, 0], y[:, 1:]
    yr = np.sqrt(yt[:, 0] * yt[:, 0] + yt[:, 1] * yt[:, 1])
    mu_hat = mu * R[:, 1] * inv[:, 0]
    factor = 1.0 / (1.0 + mu * mu_hat)
    rough = ~bilateral & (mu > 0)
    smooth = ~bilateral & (mu == 0) & (yn > 0)  # frictionless: along the normal only
    stick = bilateral | (rough & (yr <= mu * yn))
    slide = rough & ~stick & (yn > -mu_hat * yr)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_hat = np.where(yr[:, None] > 0, yt / yr[:, None], 0.0)
    gn = (yn + mu_hat * yr) * factor
    gamma = np.zeros((m, 3))
    gamma[stick] = y[stick]
    gamma[slide, 0] = gn[slide]
    gamma[slide, 1:] = (mu * gn)[slide, None] * t_hat[slide]
    gamma[smooth, 0] = yn[smooth]
    cost = 0.5 * np.einsum("mi,mi,mi->m", gamma, R, gamma)
    if not hessian:
        return gamma, None, cost, stick
    G = np.zeros((m, 3, 3))
    for k in range(3):
        G[stick, k, k] = inv[stick, k]
    G[smooth, 0, 0] = inv[smooth, 0]
    s = np.flatnonzero(slide)
    if len(s):
        f, th, ms, mh = factor[s], t_hat[s], mu[s], mu_hat[s]
        P = th[:, :, None] * th[:, None, :]
        dP = np.empty((len(s), 3, 3))  # d gamma / d y, rows and columns (n, t1, t2)
        dP[:, 0, 0] = f
        dP[:, 0, 1:] = (mh * f)[:, None] * th
        dP[:, 1:, 0] = (ms * f)[:, None] * th
        dP[:, 1:, 1:] = ms[:, None, None] * ((gn[s] / yr[s])[:, None, None] * (np.eye(2) - P) + (mh * f)[:, None, None] * P)
        Gs = dP * inv[s, None, :]  # times R^-1 from the right: symmetric in exact arithmetic
        G[s] = 0.5 * (Gs + np.swapaxes(Gs, 1, 2))
    return gamma, G, cost, stick


def _compiled_cone_law(vc: np.ndarray, R: np.ndarray, v_hat: np.ndarray, mu: np.ndarray, bilateral: np.ndarray,
                       hessian: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """:func:`cone_law` row by row (integration.kernels.cone_law)."""
    m = len(vc)
    gamma, cost, stick = np.empty((m, 3)), np.empty(m), np.empty(m, dtype=bool)
    G = np.empty((m, 3, 3)) if hessian else np.empty((0, 3, 3))
    kernels.cone_law(np.ascontiguousarray(vc, dtype=float), np.ascontiguousarray(R, dtype=float),
                     np.ascontiguousarray(v_hat, dtype=float), np.ascontiguousarray(mu, dtype=float),
                     np.ascontiguousarray(bilateral, dtype=bool), hessian, gamma, G, cost, stick)
    return gamma, (G if hessian else None), cost, stick


def contact_law(vc: np.ndarray, R: np.ndarray, v_hat: np.ndarray, bound: np.ndarray, bilateral: np.ndarray,
                hessian: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """The law of rows with relative velocities vc (m, 3) (frames n, t1, t2) [m/s], regularisation R (m, 3) (equal
    tangential entries), normal bias v_hat (m,) and friction bound (m,) [N s] (mu times the normal impulse it is
    lagged on): impulses gamma (m, 3) [N s], the cost's Hessian G = -d gamma / d vc (m, 3, 3) (None unless
    ``hessian``), the costs (m,) and whether each row sticks (m,) (bilateral, or tangentially within its bound).

    Normal: gamma_n = max(y_n, 0), y_n = (v_hat - vc_n) / R_n, cost 1/2 R_n gamma_n^2 (a bilateral row: gamma = y in
    all three, y = R^-1 (v_hat e_n - vc)). Tangents, separate from the normal so that sliding lifts nothing:
    stiction gamma_t = -vc_t / R_t while |gamma_t| <= bound (cost 1/2 R_t |gamma_t|^2), else sliding
    gamma_t = -bound vc_t / |vc_t| (cost bound |vc_t| - 1/2 R_t bound^2): a convex function of vc_t whose
    gradient is minus the impulse, Coulomb's maximal dissipation for the given bound."""
    m = len(vc)
    inv = 1.0 / R
    yn = (v_hat - vc[:, 0]) * inv[:, 0]
    pushing = bilateral | (yn > 0)
    gamma = np.zeros((m, 3))
    gamma[:, 0] = np.where(pushing, yn, 0.0)
    vt = vc[:, 1:]
    speed = np.sqrt(vt[:, 0] * vt[:, 0] + vt[:, 1] * vt[:, 1])
    stick = bilateral | ((bound > 0) & (speed * inv[:, 1] <= bound))
    with np.errstate(invalid="ignore", divide="ignore"):
        slide_scale = np.where(speed > 0, bound / speed, 0.0)  # |gamma_t| / |vc_t| when sliding
    t_scale = np.where(stick, inv[:, 1], slide_scale)
    gamma[:, 1:] = -t_scale[:, None] * vt
    cost = 0.5 * R[:, 0] * gamma[:, 0] ** 2 + np.where(stick, 0.5 * R[:, 1] * (gamma[:, 1] ** 2 + gamma[:, 2] ** 2),
                                                       bound * speed - 0.5 * R[:, 1] * bound * bound)
    if not hessian:
        return gamma, None, cost, stick
    G = np.zeros((m, 3, 3))
    G[:, 0, 0] = np.where(pushing, inv[:, 0], 0.0)
    G[:, 1, 1] = G[:, 2, 2] = t_scale
    sliding = ~stick & (speed > 0)
    if sliding.any():  # curvature across the sliding direction only: (bound / |vc_t|) (I - t t^T)
        t = vt[sliding] / speed[sliding, None]
        G[sliding, 1:, 1:] -= slide_scale[sliding, None, None] * t[:, :, None] * t[:, None, :]
    return gamma, G, cost, stick


@dataclass
class JointRows:
    """Scalar rows on the rigid unknowns alone (k of them): joint motors, joint limits, pybullet's user constraints.
    Row r's value is y_r = C_r . u, u = u_free + du the rigid bodies' generalized velocity at the end of the step, and
    its impulse on u, along C_r, is gamma_r = clip((target_r - y_r) / R_r, lo_r, hi_r) (:func:`box_law`): a motor with
    force limit F drives y to its target with at most F h (lo = -F h, hi = F h), a joint limit pushes only (lo = 0,
    hi = inf), an equality holds both ways (lo = -inf, hi = inf).

    coefficients (k, n); free (k,): C u_free, the rows' values under the free motion; target (k,) [the generalized
    velocity's units]; lo, hi (k,) [N s or N m s]: the bounds of the row's whole impulse, ``applied`` (k,) (what the
    free motion holds already: pybullet's own motor in its step) plus the solve's gamma; labels: what each row is, for
    the caller (its own keys)."""

    coefficients: np.ndarray
    free: np.ndarray
    target: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    labels: list = field(default_factory=list)
    applied: np.ndarray | None = None

    @classmethod
    def concat(cls, parts: list["JointRows"], n: int) -> "JointRows":
        """The rows of ``parts`` (on n rigid unknowns) together."""
        parts = [r for r in parts if len(r)]
        if not parts:
            return cls(np.zeros((0, n)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
        applied = (None if all(r.applied is None for r in parts) else
                   np.concatenate([np.zeros(len(r)) if r.applied is None else r.applied for r in parts]))
        return cls(*(np.concatenate([getattr(r, f) for r in parts]) for f in ("coefficients", "free", "target", "lo",
                                                                             "hi")),
                   [lab for r in parts for lab in r.labels], applied)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounds (lo, hi) (k,) of the solve's own impulses gamma: the whole impulse's less the applied one."""
        if self.applied is None:
            return self.lo, self.hi
        return self.lo - self.applied, self.hi - self.applied

    def __len__(self) -> int:
        return len(self.target)


def box_law(y: np.ndarray, R: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The law of scalar rows with values y (k,), regularisation R (k,) [s/kg or s/(kg m^2)], targets (k,) and impulse
    bounds lo <= 0 <= hi (k,): the impulses gamma = clip(z, lo, hi), z = (target - y) / R, the cost's curvature
    d^2 l / dy^2 (k,) (1 / R where the impulse is within its bounds, else 0) and the costs (k,): R (gamma z -
    gamma^2 / 2), a convex function of y whose derivative is -gamma (quadratic within the bounds, linear beyond: a
    motor at its force limit pushes with the limit however far from its target)."""
    z = (target - y) / R
    gamma = np.clip(z, lo, hi)
    curvature = np.where((z > lo) & (z < hi), 1.0 / R, 0.0)
    with np.errstate(invalid="ignore"):
        cost = R * (gamma * z - 0.5 * gamma * gamma)
    return gamma, curvature, np.where(gamma == 0.0, 0.0, cost)


# ------------------------------------------------------------------ the sparse Newton system


@dataclass
class Factor:
    """The last factorisation made on a group pattern: the values factorised (upper data) and the components they
    eliminated, kept from Newton iteration to iteration and from step to step. A later Newton system on the same
    pattern and eliminated components is solved by conjugate gradients preconditioned by it (the system changes
    little from one iteration or step to the next: contacts switching state, the bodies turning), up to
    REUSE_ITERATIONS iterations, else factorised anew: a fixed count, not a timing, so that runs repeat anywhere."""

    values: np.ndarray | None = None
    held: np.ndarray | None = None
    made: int = 0  # factorisations
    reused: int = 0  # solves by the kept factor
    iterations: int = 0  # conjugate gradient iterations, over all reuses

    def usable(self, held: np.ndarray) -> bool:
        return self.values is not None and self.held is not None and np.array_equal(self.held, held)


@dataclass
class GroupPattern:
    """The block pattern of the problem's soft unknowns: the parts' own patterns side by side (``offsets`` (P+1,) their
    first nodes) and the ``extra`` blocks (k, 2) (global node pairs, i < j) that rows between parts or between nodes
    no element joins create; ``maps[p]`` (nnzb_p,) places part p's blocks; ``solver`` factorises on it."""

    pattern: BlockPattern
    offsets: np.ndarray
    extra: np.ndarray
    maps: list[np.ndarray]
    solver: SpdSolver
    keys: np.ndarray  # the pattern's blocks as sorted row * N + col
    factor: Factor = field(default_factory=Factor)
    held_keys: np.ndarray | None = None  # the last keys holds_keys found held

    @classmethod
    def of(cls, patterns: list[BlockPattern], extra: np.ndarray, backend: str) -> "GroupPattern":
        offsets = np.concatenate([[0], np.cumsum([p.n_nodes for p in patterns])]).astype(np.int64)
        N = int(offsets[-1])
        # the parts' blocks side by side are sorted already (block CSR, parts in order): the extra blocks and their
        # mirrors merge into them by a stable sort of one long sorted run and a short one
        own = [(p.block_row + o) * N + (p.indices + o) for p, o in zip(patterns, offsets[:-1])]
        extra = np.asarray(extra, dtype=np.int64).reshape(-1, 2)
        keys = np.sort(np.concatenate(own + [extra[:, 0] * N + extra[:, 1], extra[:, 1] * N + extra[:, 0]]),
                       kind="stable")
        keys = keys[np.r_[True, keys[1:] != keys[:-1]]]
        pattern = BlockPattern.from_keys(keys, N)
        maps = [np.searchsorted(keys, k) for k in own]
        solver = SpdSolver(pattern.up_indptr, pattern.up_indices, 3 * N, backend)
        return cls(pattern, offsets, extra, maps, solver, keys)

    def holds(self, pairs: np.ndarray) -> bool:
        """Whether the block pairs (k, 2) (global nodes) all lie in this pattern."""
        if not len(pairs):
            return True
        return self.holds_keys(pairs[:, 0] * self.pattern.n_nodes + pairs[:, 1])

    def holds_keys(self, key: np.ndarray) -> bool:
        """Whether the blocks of keys row * N + col (k,) (any order, repeats allowed) all lie in this pattern (the last
        keys found held are kept: a resting pile's rows ask with the same keys step after step)."""
        if not len(key):
            return True
        if self.held_keys is not None and np.array_equal(self.held_keys, key):
            return True
        at = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        held = bool(np.all(self.keys[at] == key))
        if held:
            self.held_keys = key.copy()
        return held

    def blocks(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The block indices of (rows, cols) (global nodes, every pair in the pattern)."""
        return np.searchsorted(self.keys, rows * self.pattern.n_nodes + cols)


class GroupPatterns:
    """The group patterns kept from step to step, keyed by the parts' bodies: a pattern is reused while a step's extra
    blocks lie within it, else made anew with the union of its extra blocks and the new ones (so that contacts coming
    and going settle on one pattern), unless that union has grown to more than GROW times what the step needs. A
    pattern made anew for the same bodies is nearly the old one: it is analysed with the ordering the old one's
    analysis chose (one analysis, not one per ordering tried: a pile of 30 cubes settling in a tray makes its pattern
    anew every fourth step or so, at 128 ms each, 30 ms now). (Widening a pattern by the neighbours within the patches
    in contact, so that sliding contacts stay within it, cut the tray's 30 analyses in 150 steps to 4 but made the
    factors and products dearer: a resting stack 11-15% a step.)"""

    GROW = 4
    #: a pattern not asked for in this many solves (forget_idle) is let go: its island has merged or split
    IDLE = 50

    def __init__(self, backend: str = "auto"):
        self.backend = backend
        self._held: dict[tuple, GroupPattern] = {}
        self._asked: dict[tuple, int] = {}  # key -> the solve it was last asked for in
        self.solves = 0
        self.analyses = 0

    def kept(self, bodies: tuple[FemBody, ...], keys: np.ndarray) -> GroupPattern | None:
        """The kept pattern of ``bodies`` if it holds the blocks of ``keys`` (row * N + col, any order, repeats allowed:
        every block the rows join, a part's own ones too), else None (then :meth:`get`, with the blocks beyond the
        parts' own patterns)."""
        key = tuple(bodies)
        held = self._held.get(key)
        if held is None or held.pattern.n_nodes != sum(b.n_nodes for b in bodies) or not held.holds_keys(keys):
            return None
        self._asked[key] = self.solves
        return held

    def get(self, bodies: tuple[FemBody, ...], extra: np.ndarray) -> GroupPattern:
        key = tuple(bodies)
        self._asked[key] = self.solves
        held = self._held.get(key)
        if held is not None and held.holds(extra):
            return held
        ordering = None
        if held is not None and len(held.extra) + len(extra) <= self.GROW * max(len(extra), 16):
            extra = np.unique(np.concatenate([held.extra, extra]), axis=0)
            ordering = held.solver.ordering  # (a pattern made from the step's blocks alone chooses again)
        made = self._make(bodies, extra, ordering)
        self._held = {k: v for k, v in self._held.items() if k != key}
        self._held[key] = made
        self.analyses += 1
        return made

    def _make(self, bodies: tuple[FemBody, ...], extra: np.ndarray, ordering: str | None) -> GroupPattern:
        """The pattern of ``bodies`` with the ``extra`` blocks, analysed with the fill-reducing ``ordering`` (its name;
        None: the solver's choice among those it tries)."""
        made = GroupPattern.of([b.pattern for b in bodies], extra, self.backend)
        made.bodies = bodies  # kept alive with its key
        chosen = {k: v for k, v in made.solver.ORDERINGS.items() if v == ordering}
        if chosen:
            made.solver.ORDERINGS = chosen
        return made

    def save_state(self, handle) -> dict[tuple, tuple]:
        """The extra blocks of every kept pattern, its factorisation, its ordering and how many solves ago it was last
        asked for, keyed by its bodies' handles (``handle(body)``, None: not saved): a pattern depends on the contacts
        of earlier steps, its factorisation's round-off on the pattern and its ordering, and when it is let go
        (forget_idle) on when it was asked for."""
        out = {}
        for k, held in self._held.items():
            key = tuple(handle(b) for b in held.bodies)
            if None not in key:
                f = held.factor
                out[key] = (held.extra.copy(), None if f.values is None else (f.values.copy(), f.held.copy()),
                            held.solver.ordering, int(self.solves - self._asked.get(k, self.solves)))
        return out

    def load_state(self, state: dict[tuple, tuple], body) -> None:
        """Make the patterns of :meth:`save_state` again (``body(handle)``: the body of a handle) in place of the kept
        ones."""
        self._held, self._asked = {}, {}
        for key, (extra, kept, *more) in state.items():
            bodies = tuple(body(k) for k in key)
            extra = np.asarray(extra, dtype=np.int64).reshape(-1, 2)
            # the ordering: a name among the further entries (older states hold none, or the blocks a pattern was made
            # for), and the solves since it was asked for (older states: none, now)
            ordering = next((x for x in more if isinstance(x, str)), None)
            idle = next((int(x) for x in more if isinstance(x, (int, np.integer)) and not isinstance(x, bool)), 0)
            made = self._make(bodies, extra, ordering)
            if kept is not None:  # the same factor again, from the same values
                made.solver.factorize(kept[0].copy())
                made.factor = Factor(kept[0].copy(), kept[1].copy())
            self._held[tuple(bodies)] = made
            self._asked[tuple(bodies)] = self.solves - idle

    def forget_idle(self) -> None:
        """End of a solve (all its islands): let go of the patterns not asked for in the last IDLE solves."""
        self.solves += 1
        idle = [k for k, at in self._asked.items() if self.solves - at > self.IDLE]
        for k in idle:
            self._held.pop(k, None)
            del self._asked[k]


# ------------------------------------------------------------------ the solver


class ConvexSolver:
    """Newton's method on the convex problem of the module doc, for soft parts coupled through rows and rigid unknowns.

    Keeps, from step to step, the group patterns and their symbolic analyses (GroupPatterns). ``rel_tol``,
    ``max_iter``: the stopping rule (the gradient scaled by diag(A)^-1/2 below rel_tol times the scaled momentum or
    impulses)."""

    def __init__(self, rel_tol: float = REL_TOL, max_iter: int = MAX_ITER, backend: str = "auto",
                 lag_tol: float = LAG_TOL, lag_rounds: int = LAG_ROUNDS, reuse_min: int = REUSE_MIN,
                 reuse_min_soft: int = REUSE_MIN_SOFT):
        self.rel_tol = rel_tol
        # the kept factorisation serves systems of at least this many soft unknowns, with and without rigid unknowns
        self.reuse_min, self.reuse_min_soft = reuse_min, reuse_min_soft
        self.max_iter = max_iter
        self.lag_tol = lag_tol
        self.lag_rounds = lag_rounds
        self.patterns = GroupPatterns(backend)

    def solve(self, parts: list[SoftPart], rows: Rows, M: np.ndarray | None, h: float,
              joints: JointRows | None = None, du_guess: np.ndarray | None = None) -> Solution:
        """Minimise the step's cost for the soft ``parts``, the ``rows``, the rigid mass matrix M (n, n) (None: no
        rigid unknowns) and the scalar ``joints`` rows on the rigid unknowns (motors, limits, user constraints),
        Newton starting from the parts' guesses and ``du_guess`` (n,) (None: 0). Returns the Solution."""
        return _Newton(self, parts, rows, M, h, joints).run(du_guess)


class _Newton:
    """One solve: the problem's fixed data (offsets, global slots, the rows' regularisation) and its iterations."""

    def __init__(self, owner: ConvexSolver, parts: list[SoftPart], rows: Rows, M: np.ndarray | None, h: float,
                 joints: JointRows | None = None):
        self.owner, self.parts, self.rows, self.h = owner, parts, rows, h
        self.n = 0 if M is None else len(M)
        self.M = M
        self.joints = joints if joints is not None and len(joints) and self.n else None
        self.offsets = np.concatenate([[0], np.cumsum([p.body.n_nodes for p in parts])]).astype(np.int64)
        self.N = int(self.offsets[-1])
        used = rows.parts >= 0
        self.gnodes = np.where(used, self.offsets[np.maximum(rows.parts, 0)] + rows.nodes, 0)
        self.w = np.where(used, rows.weights, 0.0)
        self._scatter = self._gather = None  # numpy's (N, m) and (m, N) matrices of the slots' weights (_to_nodes)
        self.held = np.concatenate([p.held for p in parts]) if parts else np.zeros((0, 3), bool)
        self.Minv = None if not self.n else np.linalg.pinv(M)
        self.R = regularization(self._delassus_diagonal(), rows.bilateral)
        if self.joints is not None:  # near rigid on the rigid side's own inertia, as the contacts' normals
            self.joint_bounds = self.joints.bounds()
            C = self.joints.coefficients
            w = np.einsum("kn,nl,kl->k", C, self.Minv, C)
            self.Rj = BETA * BETA / (4.0 * math.pi * math.pi) * np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
        self.factorizations = 0

    # -- the rows' geometry
    def _delassus_diagonal(self) -> np.ndarray:
        """(m, 3) an estimate of the Delassus operator's diagonal in the rows' directions: the soft slots through the
        inverses of their nodes' diagonal blocks of A (a held component moves not), the rigid side exactly."""
        rows = self.rows
        m = len(rows)
        out = np.zeros((m, 3))
        if not m:
            return out
        if kernels.ENABLED:  # the lines below, row by row (integration.kernels)
            D = np.concatenate([p.diagonal_blocks() for p in self.parts])
            kernels.delassus_diagonal(self.gnodes, self.w, np.ascontiguousarray(rows.frames, dtype=float), D,
                                      np.ascontiguousarray(self.held), out)
        else:
            self._delassus_soft(out)
        if self.n and rows.jacobian is not None:
            JF = np.einsum("mij,mik->mkj", rows.jacobian, rows.frames)  # (m, 3 directions, n)
            out += np.einsum("mkj,jl,mkl->mk", JF, self.Minv, JF)
        return out

    def _delassus_soft(self, out: np.ndarray) -> None:
        """_delassus_diagonal's soft part, added into out (m, 3) (numpy; integration.kernels.delassus_diagonal)."""
        rows = self.rows
        # the inverses of the diagonal blocks of the nodes the rows touch, the held components fixed (zero)
        touched = np.unique(self.gnodes[self.w != 0])
        part = np.searchsorted(self.offsets, touched, side="right") - 1
        D = np.empty((len(touched), 3, 3))
        free = np.empty((len(touched), 3), bool)
        for p in np.unique(part).tolist():
            on = part == p
            local = touched[on] - self.offsets[p]
            D[on] = self.parts[p].diagonal_blocks()[local]
            free[on] = ~self.parts[p].held[local]
        both = free[:, :, None] & free[:, None, :]
        Dinv = np.linalg.inv(np.where(both, D, 0.0) + (~free)[:, :, None] * np.eye(3)) * both
        inv_blocks = np.zeros((self.N, 3, 3))
        inv_blocks[touched] = Dinv
        F = rows.frames
        for s in range(self.gnodes.shape[1]):
            BF = inv_blocks[self.gnodes[:, s]] @ F
            out += (self.w[:, s] ** 2)[:, None] * np.einsum("mik,mik->mk", F, BF)

    def _point_velocities(self, V: np.ndarray) -> np.ndarray:
        """sum_s w_s V[node_s] (m, 3) for global soft velocities V (N, 3)."""
        if kernels.ENABLED:
            out = np.empty((len(self.w), 3))
            kernels.gather_rows(self.gnodes, self.w, np.ascontiguousarray(V, dtype=float), out)
            return out
        return np.einsum("ms,msi->mi", self.w, V[self.gnodes])

    def _to_nodes(self, f: np.ndarray) -> np.ndarray:
        """sum over the rows' slots of w f[row] on the slot's node (N, k) for row quantities f (m, k)."""
        if kernels.ENABLED:
            out = np.empty((self.N, f.shape[1]))
            kernels.scatter_rows(self.gnodes, self.w, np.ascontiguousarray(f, dtype=float), out)
            return out
        return np.asarray(self._matrices()[0] @ f)

    def _at_rows(self, X: np.ndarray) -> np.ndarray:
        """sum_s w_s X[node_s] (m, k) for node quantities X (N, k)."""
        if kernels.ENABLED:
            out = np.empty((len(self.w), X.shape[1]))
            kernels.gather_rows(self.gnodes, self.w, np.ascontiguousarray(X, dtype=float), out)
            return out
        return np.asarray(self._matrices()[1] @ X)

    def _matrices(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """The slots' weights as sparse matrices (N, m) and (m, N) (numpy's products), made once a solve."""
        if self._scatter is None:
            m, slots = len(self.w), self.gnodes.shape[1] if self.gnodes.ndim == 2 else 0
            self._scatter = sp.csr_matrix((self.w.ravel(), (self.gnodes.ravel(), np.repeat(np.arange(m), slots))),
                                          shape=(self.N, m))
            self._gather = self._scatter.T.tocsr()
        return self._scatter, self._gather

    def velocities(self, V: np.ndarray, du: np.ndarray) -> np.ndarray:
        """vc (m, 3) in the rows' frames for soft velocities V (N, 3) and du (n,)."""
        if kernels.ENABLED and not (self.n and self.rows.jacobian is not None):  # the lines below, row by row
            out = np.empty((len(self.w), 3))
            kernels.row_velocities(self.gnodes, self.w, np.ascontiguousarray(V, dtype=float),
                                   np.ascontiguousarray(self.rows.rigid_velocity, dtype=float),
                                   np.ascontiguousarray(self.rows.frames, dtype=float), out)
            return out
        rel = self._point_velocities(V) - self.rows.rigid_velocity
        if self.n and self.rows.jacobian is not None:
            rel -= self.rows.jacobian @ du
        return np.einsum("mji,mj->mi", self.rows.frames, rel)

    def _impulses_on_soft(self, gamma: np.ndarray) -> np.ndarray:
        """J_s^T gamma (N, 3): the rows' impulses on the soft nodes."""
        return self._to_nodes(np.einsum("mij,mj->mi", self.rows.frames, gamma))

    def _impulse_on_rigid(self, gamma: np.ndarray) -> np.ndarray:
        """J_r^T gamma (n,): the impulse the rows exert on the rigid unknowns (minus the soft side's)."""
        if not self.n or self.rows.jacobian is None:
            return np.zeros(self.n)
        f = np.einsum("mij,mj->mi", self.rows.frames, gamma)
        return -np.einsum("mi,min->n", f, self.rows.jacobian)

    # -- the soft parts' own terms
    def _split(self, V: np.ndarray) -> list[np.ndarray]:
        return [V[o:o2] for o, o2 in zip(self.offsets[:-1], self.offsets[1:])]

    def _A_products(self, V: np.ndarray) -> np.ndarray:
        return np.concatenate([p.apply(v) for p, v in zip(self.parts, self._split(V))]) \
            if self.parts else np.zeros((0, 3))

    def _loads(self) -> np.ndarray:
        return np.concatenate([p.b for p in self.parts]) if self.parts else np.zeros((0, 3))

    # -- the Newton system
    def _slot_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every row's pairs of used slots: (row (k,), node a (k,), node b (k,) (global nodes, both orders), the
        product of their weights (k,))."""
        used = self.w != 0
        r, s, t = np.nonzero(used[:, :, None] & used[:, None, :])
        return r, self.gnodes[r, s], self.gnodes[r, t], self.w[r, s] * self.w[r, t]

    def _extra_pairs(self) -> np.ndarray:
        """The block pairs (k, 2) i < j (global nodes) that rows create beyond the parts' own patterns."""
        if not len(self.rows) or self.gnodes.shape[1] < 2:
            return np.zeros((0, 2), np.int64)
        if kernels.ENABLED:
            pairs = np.unique(kernels.slot_pair_keys(self.gnodes, self.w, self.N))
        else:
            _, a, b, _ = self._slot_pairs()
            keep = a < b
            pairs = np.unique(a[keep] * self.N + b[keep])
        if not len(pairs):
            return np.zeros((0, 2), np.int64)
        i, j = pairs // self.N, pairs % self.N
        # those in a part's own pattern need nothing: its blocks' keys row * n + col are sorted (block CSR)
        part_i = np.searchsorted(self.offsets, i, side="right") - 1
        part_j = np.searchsorted(self.offsets, j, side="right") - 1
        inside = np.zeros(len(pairs), bool)
        for p in np.unique(part_i[part_i == part_j]).tolist():
            sel = np.flatnonzero((part_i == p) & (part_j == p))
            pat, o = self.parts[p].body.pattern, self.offsets[p]
            keys = pat.block_row * pat.n_nodes + pat.indices
            want = (i[sel] - o) * pat.n_nodes + (j[sel] - o)
            at = np.minimum(np.searchsorted(keys, want), len(keys) - 1)
            inside[sel] = keys[at] == want
        return np.column_stack([i[~inside], j[~inside]])

    def _system(self, group: GroupPattern, G: np.ndarray) -> tuple[np.ndarray, float]:
        """The upper values of A + J_s^T G J_s on the group pattern with the held components eliminated (their rows and
        columns zeroed, ``scale`` on the diagonal), and the scale."""
        pat = group.pattern
        if getattr(self, "_blocks", None) is None or self._blocks[0] is not group:  # fixed within the solve
            base = np.zeros((pat.nnzb, 9))
            for p, where in zip(self.parts, group.maps):
                base[where] += p.blocks().reshape(-1, 9)
            blocks = None
            if len(self.rows):  # the rows' slot pairs onto the pattern's blocks, as a sparse (nnzb, m) matrix
                r, a, b, ww = self._slot_pairs()
                blocks = sp.csr_matrix((ww, (group.blocks(a, b), r)), shape=(pat.nnzb, len(self.rows)))
            self._blocks = (group, base, blocks)
        _, base, blocks = self._blocks
        data = base.copy()
        if blocks is not None:
            data += blocks @ self._frame_hessians(G).reshape(-1, 9)
        up = data.reshape(-1)[pat.up_gather]
        scale = float(np.mean(up[pat.up_diag])) if len(pat.up_diag) else 1.0
        mflat = self.held.ravel()
        if mflat.any():
            up = up.copy()
            up[mflat[pat.up_row] | mflat[pat.up_col]] = 0.0
            up[pat.up_diag[mflat]] = scale
        return up, scale

    def _frame_hessians(self, G: np.ndarray) -> np.ndarray:
        """F G F^T (m, 3, 3): the rows' Hessians in world axes (F: the rows' frames), once per G."""
        if getattr(self, "_fgf", None) is None or self._fgf[0] is not G:
            F = self.rows.frames
            if kernels.ENABLED:  # the product below, row by row
                out = np.empty((len(F), 3, 3))
                kernels.frame_hessians(np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(G, dtype=float), out)
                self._fgf = (G, out)
            else:
                self._fgf = (G, F @ G @ np.swapaxes(F, 1, 2))
        return self._fgf[1]

    def _rigid_blocks(self, G: np.ndarray, joint_curvature: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """H_sr (3N, n) = J_s^T G J_r-part and H_rr (n, n) = M + J_r^T G J_r (+ C^T diag(joint curvatures) C) of the
        Newton system (held rows zeroed)."""
        n, rows = self.n, self.rows
        Hsr = np.zeros((self.N, 3, n))
        Hrr = self.M.copy()
        if joint_curvature is not None:
            C = self.joints.coefficients
            Hrr += C.T @ (joint_curvature[:, None] * C)
        if len(rows) and rows.jacobian is not None:
            FGF = self._frame_hessians(G)
            C = -(FGF @ rows.jacobian)  # d (J_s^T gamma-gradient) / d du per row, (m, 3, n)
            Hsr = self._to_nodes(C.reshape(len(rows), -1)).reshape(self.N, 3, n)
            Hrr = Hrr + np.einsum("min,mik->nk", rows.jacobian, FGF @ rows.jacobian)
        Hsr = Hsr.reshape(3 * self.N, n)
        Hsr[self.held.ravel()] = 0.0
        return Hsr, Hrr

    def _direction(self, group: GroupPattern | None, G: np.ndarray, gV: np.ndarray, gu: np.ndarray,
                   joint_curvature: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The Newton step (dV (N, 3), ddu (n,), A dV (N, 3) if the conjugate gradients made it, else None) for the
        gradients gV (N, 3) (held components zero) and gu (n,): by conjugate gradients preconditioned by the pattern's
        kept factorisation where it serves (Factor), else by a new factorisation of the soft part and a Schur complement
        for the rigid unknowns (no soft part, group None: the rigid unknowns' own dense system)."""
        Hsr, Hrr = (self._rigid_blocks(G, joint_curvature) if self.n
                    else (np.zeros((3 * self.N, 0)), np.zeros((0, 0))))
        if group is None:
            try:
                return np.zeros((0, 3)), np.linalg.solve(Hrr, -gu), None
            except np.linalg.LinAlgError:
                return np.zeros((0, 3)), np.linalg.lstsq(Hrr, -gu, rcond=None)[0], None
        rhs = np.concatenate([-gV.reshape(-1), -gu])
        factor = group.factor
        if 3 * self.N >= (self.owner.reuse_min if self.n else self.owner.reuse_min_soft) and factor.usable(self.held):
            done = self._reuse(group, G, Hsr, Hrr, rhs)
            if done is not None:
                factor.reused += 1
                z, Az = done
                return z[:3 * self.N].reshape(-1, 3), z[3 * self.N:], Az
        up, _ = self._system(group, G)
        group.solver.factorize(up)
        factor.values, factor.held = up, self.held.copy()
        factor.made += 1
        self.factorizations += 1
        z = self._schur_solve(group.solver, Hsr, Hrr, rhs[:, None])[:, 0]
        return z[:3 * self.N].reshape(-1, 3), z[3 * self.N:], None

    def _schur_solve(self, solver: SpdSolver, Hsr: np.ndarray, Hrr: np.ndarray, R: np.ndarray,
                     Y: np.ndarray | None = None, S: np.ndarray | None = None) -> np.ndarray:
        """Solve [[F, Hsr], [Hsr^T, Hrr]] z = R (3N + n, k) with F the soft part ``solver`` factorised (held
        components eliminated) by the Schur complement S = Hrr - Hsr^T F^-1 Hsr (Y = F^-1 Hsr and S given, or made)."""
        n3 = 3 * self.N
        held = self.held.ravel()
        if not self.n:
            x = solver.solve(R[:n3]).reshape(n3, -1)
            x[held] = 0.0
            return x
        if Y is None:
            Y = solver.solve(Hsr).reshape(n3, -1)
            Y[held] = 0.0
            S = Hrr - Hsr.T @ Y
            S = 0.5 * (S + S.T)
        y = solver.solve(R[:n3]).reshape(n3, -1)
        y[held] = 0.0
        r = R[n3:] - Hsr.T @ y
        try:
            du = np.linalg.solve(S, r)
        except np.linalg.LinAlgError:
            du = np.linalg.lstsq(S, r, rcond=None)[0]
        return np.concatenate([y - Y @ du, du])

    def _reuse(self, group: GroupPattern, G: np.ndarray, Hsr: np.ndarray, Hrr: np.ndarray, rhs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray] | None:
        """The Newton system H z = rhs solved by conjugate gradients preconditioned by the kept factorisation (with the
        current rigid blocks in a Schur complement), or None if REUSE_ITERATIONS do not reach REUSE_TOL; returns z and
        A z's soft part (N, 3) (summed from the iterations' products, for the line search). The soft part of H is
        applied without assembling it, A x + J_s^T G J_s x (its held components' rows are dropped from each product
        and its iterates vanish there, so their columns add nothing)."""
        n3 = 3 * self.N
        FGF = self._frame_hessians(G)
        free = np.concatenate([~self.held.ravel(), np.ones(self.n, dtype=bool)])

        def H(z):
            x = z[:n3]
            X = x.reshape(-1, 3)
            out = np.empty_like(z)
            AX = self._A_products(X)
            out[:n3] = (AX + self._to_nodes(np.einsum("mij,mj->mi", FGF, self._at_rows(X)))).reshape(-1)
            if self.n:
                out[:n3] += Hsr @ z[n3:]
                out[n3:] = Hsr.T @ x + Hrr @ z[n3:]
            return np.where(free, out, 0.0), AX

        Y = S = None
        if self.n:
            Y = group.solver.solve(Hsr).reshape(n3, -1)
            Y[self.held.ravel()] = 0.0
            S = Hrr - Hsr.T @ Y
            S = 0.5 * (S + S.T)

        def precondition(r):
            return self._schur_solve(group.solver, Hsr, Hrr, r[:, None], Y, S)[:, 0]

        b = np.where(free, rhs, 0.0)
        target = REUSE_TOL * float(np.linalg.norm(b))
        z = np.zeros_like(b)
        Az = np.zeros((self.N, 3))  # A z's soft part, along the iterations
        r = b.copy()
        y = precondition(r)
        d = y.copy()
        ry = float(r @ y)
        for it in range(1, REUSE_ITERATIONS + 1):
            Hd, Ad = H(d)
            dHd = float(d @ Hd)
            if not dHd > 0:
                return None
            a = ry / dHd
            z += a * d
            Az += a * Ad
            r -= a * Hd
            group.factor.iterations += 1
            if float(np.linalg.norm(r)) <= target:
                return z, Az
            y = precondition(r)
            ry_new = float(r @ y)
            d = y + (ry_new / ry) * d
            ry = ry_new
        return None

    # -- the iteration
    def run(self, du_guess: np.ndarray | None = None) -> Solution:
        """Newton's method on Castro et al.'s cone (:func:`cone_law`); where rows slide fast enough to lift off by more
        than GLIDE_TOL in the step, again on Coulomb's law with the friction bounds lagged on the normal impulses
        (:func:`contact_law`), until the bounds hold with the impulses found (to LAG_TOL) or LAG_ROUNDS rounds, each
        round from the last one's velocities."""
        parts, rows = self.parts, self.rows
        V = np.concatenate([np.where(p.held, p.value, p.guess) for p in parts]) if parts else np.zeros((0, 3))
        du = np.zeros(self.n) if du_guess is None else np.array(du_guess, dtype=float)
        self.group = None
        if parts:
            bodies = tuple(p.body for p in parts)
            if kernels.ENABLED and len(rows) and self.gnodes.shape[1] > 1:  # the kept pattern, if it holds every block
                self.group = self.owner.patterns.kept(bodies, kernels.slot_pair_keys(self.gnodes, self.w, self.N))
            if self.group is None:
                self.group = self.owner.patterns.get(bodies, self._extra_pairs())
        self.b = self._loads()
        free = ~self.held
        # diag(A)^-1/2, the stopping rule's scaling (SAP's)
        dA = (np.concatenate([p.diagonal_blocks()[:, [0, 1, 2], [0, 1, 2]] for p in parts]) if parts
              else np.zeros((0, 3)))
        self.scale_s = np.where(free, 1.0 / np.sqrt(np.maximum(dA, 1e-300)), 0.0)
        self.scale_r = 1.0 / np.sqrt(np.maximum(np.diag(self.M), 1e-300)) if self.n else np.zeros(0)
        friction = (rows.mu > 0) & ~rows.bilateral
        # first Castro et al.'s cone (Newton converges in a few iterations): where no row slides, its solution is
        # Coulomb's (a sticking row's impulse is the same under both laws)
        law = _compiled_cone_law if kernels.ENABLED else cone_law
        self.law = lambda vc, R, hessian=True: law(vc, R, rows.v_hat, rows.mu, rows.bilateral, hessian)
        self.cone = True
        V, du, gamma, vc, stick, its, converged, residual, cost = self._newton(V, du, self.owner.rel_tol,
                                                                              self.owner.max_iter)
        iterations, rounds = its, 1
        sliding = friction & ~stick & (gamma[:, 0] > 0)
        glide = float((rows.mu * np.hypot(vc[:, 1], vc[:, 2]))[sliding].max(initial=0.0)) * self.h
        if glide > GLIDE_TOL:
            # where rows slide, the cone lifts them off by mu |v_t| h: Coulomb's law again with the friction bounds
            # lagged on the normal impulses, from the cone's solution, until the bounds hold with the impulses found
            lag = np.maximum(gamma[:, 0], 0.0)
            self.law = lambda vc, R, hessian=True: contact_law(vc, R, rows.v_hat, self.bound, rows.bilateral, hessian)
            self.cone = False
            for rounds in range(2, self.owner.lag_rounds + 2):
                self.bound = rows.mu * lag
                V, du, gamma, vc, stick, its, converged, residual, cost = self._newton(V, du, self.owner.rel_tol,
                                                                                      self.owner.max_iter)
                iterations += its
                gn = np.maximum(gamma[:, 0], 0.0)
                if self._coulomb(gamma, stick, friction) and converged:
                    break  # Coulomb's law holds with the impulses found: the bounds need not move
                lag = gn.copy()
        joint_gamma = self._joint_law(du)[0] if self.joints is not None else np.zeros(0)
        return Solution(self._split(V), du, gamma, vc, stick, iterations, self.factorizations, cost, residual,
                        converged, rounds, joint_gamma)

    def _joint_law(self, du: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The joint rows' (impulses (k,), curvatures (k,), costs (k,)) at du (box_law)."""
        j = self.joints
        return box_law(j.free + j.coefficients @ du, self.Rj, j.target, *self.joint_bounds)

    def _coulomb(self, gamma: np.ndarray, stick: np.ndarray, friction: np.ndarray) -> bool:
        """Whether the impulses gamma (m, 3) obey Coulomb's law with their own normal impulses, to LAG_TOL: a sliding
        row's friction mu g_n (its bound lagged on the same g_n), a sticking row's within mu g_n."""
        gn = np.maximum(gamma[:, 0], 0.0)
        gt = np.hypot(gamma[:, 1], gamma[:, 2])
        cone = self.rows.mu * gn
        scale = self.owner.lag_tol * max(float(cone.max(initial=0.0)), 1e-300)
        sliding = friction & ~stick
        return bool(np.all(np.abs(self.bound - cone)[sliding] <= scale) and np.all((gt - cone)[friction & stick] <= scale))

    def _evaluate(self, V: np.ndarray, du: np.ndarray, hessian: bool = True, vc: np.ndarray | None = None,
                  AV: np.ndarray | None = None):
        """(vc, gamma, G, stick, A V, cost, joint) at (V, du) under the current law (self.law); joint: the joint rows'
        (impulses, curvatures) or None. ``vc``, ``AV``: the rows' velocities and A V there if known."""
        vc = self.velocities(V, du) if vc is None else vc
        gamma, G, cost_c, stick = self.law(vc, self.R, hessian)
        AV = self._A_products(V) if AV is None else AV
        cost = 0.5 * float(np.vdot(V, AV)) - float(np.vdot(self.b, V)) + float(cost_c.sum())
        if self.n:
            cost += 0.5 * float(du @ self.M @ du)
        joint = None
        if self.joints is not None:
            gj, cj, cost_j = self._joint_law(du)
            cost += float(cost_j.sum())
            joint = (gj, cj)
        return vc, gamma, G, stick, AV, cost, joint

    def _newton(self, V: np.ndarray, du: np.ndarray, rel_tol: float, max_iter: int):
        """Newton's method from (V, du) under the current bounds; returns (V, du, gamma, vc, stick, iterations,
        converged, residual, cost). Stops when the scaled gradient is below rel_tol times the scaled momentum or
        impulses, or when a full-length step, or two steps in a row, no longer lower the cost beyond round-off (a
        direction that round-off in the gradient spoils gets only a vanishing step from the line search)."""
        free = ~self.held
        vc, gamma, G, stick, AV, cost, joint = self._evaluate(V, du)
        it, converged, residual, flat = 0, False, np.inf, False
        for it in range(max_iter + 1):
            jc = self._impulses_on_soft(gamma)
            jr = self._impulse_on_rigid(gamma)
            if joint is not None:
                jr = jr + self.joints.coefficients.T @ joint[0]
            gV = np.where(free, AV - self.b - jc, 0.0)
            gu = self.M @ du - jr if self.n else np.zeros(0)
            grad = math.hypot(float(np.linalg.norm(gV * self.scale_s)), float(np.linalg.norm(gu * self.scale_r)))
            mom = math.hypot(float(np.linalg.norm(AV * self.scale_s)),
                             float(np.linalg.norm(self.M @ du * self.scale_r)) if self.n else 0.0)
            imp = math.hypot(float(np.linalg.norm(jc * self.scale_s)), float(np.linalg.norm(jr * self.scale_r)))
            residual = grad / max(mom, imp, 1e-300)
            if grad <= ABS_TOL + rel_tol * max(mom, imp) or (not len(self.rows) and joint is None and it > 0):
                converged = True
                break
            if it == max_iter:
                break
            dV, ddu, AdV = self._direction(self.group, G, gV, gu, None if joint is None else joint[1])
            alpha, AdV, dvc = self._line_search(V, du, dV, ddu, AV, gamma, None if joint is None else joint[0], vc,
                                                AdV)
            V = V + alpha * dV
            du = du + alpha * ddu
            previous = cost
            # A V and the rows' velocities are affine in (V, du): along the step from the line search's
            vc, gamma, G, stick, AV, cost, joint = self._evaluate(V, du, vc=None if dvc is None else vc + alpha * dvc,
                                                                  AV=AV + alpha * AdV)
            still = abs(previous - cost) <= COST_TOL * max(abs(cost), abs(previous), 1e-300)
            if still and (alpha > 0.5 or flat):
                converged = True  # at round-off: the cost no longer falls
                it += 1
                break
            flat = still
        return V, du, gamma, vc, stick, it, converged, residual, cost

    def _line_search(self, V, du, dV, ddu, AV, gamma, joint_gamma=None, vc=None, AdV=None
                     ) -> tuple[float, np.ndarray, np.ndarray | None]:
        """The minimiser alpha in (0, 1.5] of the (convex, piecewise smooth) cost along the step, to where its slope is
        LINE_TOL of the slope at the start: Newton on dl/dalpha safeguarded by bisection (Castro et al.'s line
        search). Returns (alpha, A dV, the rows' velocities' change per unit alpha (None: no rows)); ``vc``, ``AdV``:
        the rows' velocities at (V, du) and A dV if known."""
        rows = self.rows
        AdV = self._A_products(dV) if AdV is None else AdV
        dAd = float(np.vdot(dV, AdV)) + (float(ddu @ self.M @ ddu) if self.n else 0.0)
        g0 = float(np.vdot(dV, AV - self.b)) + (float(ddu @ self.M @ du) if self.n else 0.0)
        dvc = None
        if not len(rows) and self.joints is None:
            return 1.0, AdV, dvc
        if len(rows):
            vc0 = self.velocities(V, du) if vc is None else vc
            # velocities() is affine in (V, du): its constant part, the rigid side's free motion, added back
            dvc = self.velocities(dV, ddu) + np.einsum("mji,mj->mi", rows.frames, rows.rigid_velocity)
            d0 = g0 - float(np.sum(dvc * gamma))
            if kernels.ENABLED:  # the slopes row by row (integration.kernels), without the impulses and Hessians
                vc0, dvc = np.ascontiguousarray(vc0), np.ascontiguousarray(dvc)
                param = np.ascontiguousarray(rows.mu if self.cone else self.bound, dtype=float)
                R, v_hat, bilateral = np.ascontiguousarray(self.R), np.ascontiguousarray(rows.v_hat), rows.bilateral

                def row_slopes(alpha):
                    return kernels.law_slopes(vc0, dvc, float(alpha), R, v_hat, param, bilateral, self.cone)
            else:
                def row_slopes(alpha):
                    gamma_a, G_a, _, _ = self.law(vc0 + alpha * dvc, self.R)
                    return float(np.sum(dvc * gamma_a)), float(np.einsum("mi,mij,mj->", dvc, G_a, dvc))
        else:
            d0 = g0

            def row_slopes(alpha):
                return 0.0, 0.0
        if self.joints is not None:  # the joint rows' slopes along the step (few rows: numpy)
            j = self.joints
            y0, dy = j.free + j.coefficients @ du, j.coefficients @ ddu
            d0 -= float(joint_gamma @ dy)

            def derivatives(alpha):
                s1, s2 = row_slopes(alpha)
                gj, cj, _ = box_law(y0 + alpha * dy, self.Rj, j.target, *self.joint_bounds)
                return g0 + alpha * dAd - s1 - float(gj @ dy), dAd + s2 + float(cj @ (dy * dy))
        else:
            def derivatives(alpha):
                s1, s2 = row_slopes(alpha)
                return g0 + alpha * dAd - s1, dAd + s2

        lo, hi = 0.0, 1.5
        d_hi, _ = derivatives(hi)
        if d_hi <= 0:
            return hi, AdV, dvc
        d1, d2 = derivatives(1.0)
        if abs(d1) <= LINE_TOL * abs(d0):
            return 1.0, AdV, dvc
        alpha = 1.0
        if d1 < 0:
            lo = 1.0
        else:
            hi = 1.0
        for _ in range(100):
            step = alpha - d1 / d2 if d2 > 0 else 0.5 * (lo + hi)
            alpha = step if lo < step < hi else 0.5 * (lo + hi)
            d1, d2 = derivatives(alpha)
            if abs(d1) <= LINE_TOL * abs(d0) or hi - lo <= 1e-12:
                break
            if d1 < 0:
                lo = alpha
            else:
                hi = alpha
        return alpha, AdV, dvc
