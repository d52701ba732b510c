"""Two-way coupling of soft bodies and movable rigid bodies, solved in one implicit step.

For a given constraint set (supports, attachments, the active contacts), every constrained velocity
component k of soft body b takes the value c_k = c0_k + G_bk du, where du (n,) is the change of the
movable rigid bodies' generalized velocities (stacked) against their free motion over the step, and
G_b (rows of the constraints' point Jacobians in the constraints' local frames) says how the rigid
point moves. Then

    A_b v_b = b_b + r_b                      soft: the step system, r_b the constraint impulses
    M du    = s - sum_b G_b^T r_b            rigid: the impulses back, s the sliding friction's

The soft solve is linear in the constrained values, so v_b = y0_b + Y_b du and r_b = r0_b + R_b du,
with (y0, r0) the solve at du = 0 and the columns of (Y, R) homogeneous solves (b = 0) with the values
G_b e_j; only columns that some constraint of b touches are solved for. Eliminating v and r,

    (M + sum_b G_b^T R_b) du = s - sum_b G_b^T r0_b,

whose matrix is M plus the soft bodies' stiffness seen at the constraints (symmetric positive
definite): a Schur complement of the whole system, as ArtiSynth and SOFA solve rigid and FEM bodies
together. Both sides then agree on every impulse, so momentum is exchanged exactly and the step is the
implicit step of one mechanical system: light rigid bodies are not overshot.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softbody.integrator import Constraints, LinearSystem


@dataclass
class CoupledPart:
    """One soft body's constraint set for a coupled solve.

    cons: its constraints (supports, attachments, contacts), values at du = 0; G (len(cons), 3, n): the
    derivative of each constrained node's local values with respect to du (None: not coupled); extra
    (N, 3): an extra right-hand side (sliding friction impulses) or None; reuse: the system may keep
    its last factorisation (only values or extra changed since its last solve)."""

    system: LinearSystem
    cons: Constraints
    G: np.ndarray | None = None
    extra: np.ndarray | None = None
    reuse: bool = False

    def key(self) -> tuple[bytes, bytes, bytes]:
        frames = b"" if self.cons.frames is None else np.ascontiguousarray(self.cons.frames).tobytes()
        return self.cons.nodes.tobytes(), self.cons.mask.tobytes(), frames


def generalized(cons: Constraints, r: np.ndarray, G: np.ndarray) -> np.ndarray:
    """G^T r (n,): the generalized impulse of the reactions r (N, 3, local frames) of the constrained
    components of ``cons`` through G (len(cons), 3, n)."""
    return np.einsum("ck,ckn->n", np.where(cons.mask, r[cons.nodes], 0.0), G)


class CoupledSolver:
    """Solves the constraint sets of several soft bodies at once, coupled through movable rigid bodies
    with mass matrix M (n, n) (None or n = 0: nothing is coupled, each body is solved alone).

    Lives for one step: it keeps each body's solve while its constraints, values and loads are unchanged,
    and its homogeneous responses while its constraint set is unchanged, so an active-set iteration costs
    a solve only for the bodies whose contacts changed, plus a small dense solve.
    """

    def __init__(self, M: np.ndarray | None = None):
        self.M = None if M is None or not M.size else np.asarray(M, float)
        self._responses: dict[int, tuple] = {}  # part index -> (key, columns, Y (k, N, 3), R (k, N, 3), system)
        self._bases: dict[int, tuple] = {}  # part index -> (signature, system, (y0, r0))
        self.homogeneous_solves = 0

    @property
    def n(self) -> int:
        return 0 if self.M is None else len(self.M)

    def solve(self, parts: list[CoupledPart], slip: np.ndarray | None = None
              ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """Velocities and reactions (v (N, 3), r (N, 3) local) per part, and du (n,).

        slip (n,): the generalized impulse s of forces on the rigid side that do not depend on du."""
        out = [self._base(i, part) for i, part in enumerate(parts)]
        du = np.zeros(self.n)
        if self.M is None:
            return out, du
        K = self.M.copy()
        rhs = np.zeros(self.n) if slip is None else np.array(slip, dtype=float)
        responses = []
        for i, (part, (y0, r0)) in enumerate(zip(parts, out)):
            if part.G is None or not len(part.cons):
                responses.append(None)
                continue
            cols, Y, R = self._response(i, part)
            responses.append((cols, Y, R))
            if not len(cols):
                continue
            rhs -= generalized(part.cons, r0, part.G)
            for k, j in enumerate(cols):
                K[:, j] += generalized(part.cons, R[k], part.G)
        K = 0.5 * (K + K.T)
        try:
            L = np.linalg.cholesky(K)
            du = np.linalg.solve(L.T, np.linalg.solve(L, rhs))
        except np.linalg.LinAlgError:  # a massless direction no constraint holds: the least-squares answer
            du = np.linalg.lstsq(K, rhs, rcond=None)[0]
        for i, resp in enumerate(responses):
            if resp is None or not len(resp[0]):
                continue
            cols, Y, R = resp
            y0, r0 = out[i]
            w = du[cols]
            out[i] = (y0 + np.tensordot(w, Y, axes=1), r0 + np.tensordot(w, R, axes=1))
        return out, du

    def _base(self, i: int, part: CoupledPart) -> tuple[np.ndarray, np.ndarray]:
        """The solve of part i at du = 0, repeated only if its constraints, values or extra load changed."""
        sig = (part.key(), part.cons.value.tobytes(), None if part.extra is None else part.extra.tobytes())
        cached = self._bases.get(i)
        if cached is not None and cached[0] == sig and cached[1] is part.system:
            return cached[2]
        out = part.system.solve(part.cons, part.extra, reuse=part.reuse)
        self._bases[i] = (sig, part.system, out)
        return out

    def _response(self, i: int, part: CoupledPart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The homogeneous responses (columns, Y (k, N, 3), R (k, N, 3)) of part i, solved anew only when its
        constraint set changed."""
        key = part.key()
        cached = self._responses.get(i)
        if cached is not None and cached[0] == key and cached[4] is part.system:
            return cached[1], cached[2], cached[3]
        G = np.where(part.cons.mask[:, :, None], part.G, 0.0)
        cols = np.flatnonzero(np.abs(G).max(axis=(0, 1), initial=0.0) > 0)
        N = part.system.body.n_nodes
        Y, R = np.zeros((len(cols), N, 3)), np.zeros((len(cols), N, 3))
        for k, j in enumerate(cols):
            cons = Constraints(part.cons.nodes, part.cons.mask, G[:, :, j], part.cons.frames)
            Y[k], R[k] = part.system.solve(cons, reuse=True, homogeneous=True)
            self.homogeneous_solves += 1
        self._responses[i] = (key, cols, Y, R, part.system)
        return cols, Y, R
