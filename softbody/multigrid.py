"""Algebraic multigrid as a preconditioner: pyamg's smoothed-aggregation hierarchy, applied by a V-cycle of our own.

:func:`hierarchy` sets pyamg's hierarchy up from a symmetric positive definite matrix in 3x3 node blocks (aggregates of
whole nodes, the three translations per node as near null space, the tentative prolongator smoothed by energy
minimisation) and keeps of it only what a cycle reads, in single precision. :class:`VCycle` applies one V-cycle: a
forward Gauss-Seidel sweep down, the coarsest level by its dense pseudo-inverse, a backward sweep up (pyamg's compiled
kernels), so that the cycle is a symmetric positive definite approximation of A^-1, as conjugate gradients need.

Why these choices, measured on the 72k-node tet4 sheet during the impact (215k unknowns, one matrix and load of the
step's confirming solve; PCG to 1e-5 / 1e-3 from zero; milliseconds a cycle, single thread), against pyamg's own
cycle (``aspreconditioner``: symmetric Gauss-Seidel before and after, double precision): 96 ms a cycle, 21 / 13
iterations.

- pyamg's cycle also forms the finest residual before and after (it is a stationary solver's step): two products with
  A a cycle that PCG does not read (96 -> 68 ms);
- single precision: the cycle's memory traffic (the smoothers and products are bound by it) less by a third
  (68 -> 52 ms), the iterations the same; PCG stays in double precision (its residual and update);
- the prolongator smoothed by energy minimisation (``smooth="energy"``) instead of one Jacobi step: 14 / 9 iterations
  instead of 21 / 13 at the same cycle cost and operator complexity (1.31); with 2 of its iterations, weighted by the
  diagonal and without pyamg's candidate improvement (the translations are exact), 19 / 12 with the sweeps below and
  a set-up of 1.0 s instead of 2.8 (Jacobi: 0.9 s, 26 / 16);
- one forward sweep before and one backward after, instead of a symmetric sweep (forward and backward) at each:
  half the smoothing (46 -> 29 ms a cycle) for 18 / 11 iterations instead of 14 / 9;
- tried: the rigid rotations in the near null space as well (14 iterations, a hierarchy of operator complexity 2.2 and
  57 ms a cycle), a strength threshold of 0.05 or 0.1 (no fewer iterations; 0.1 27), evolution strength (45 ms,
  18 iterations, set-up 4.5 s), a second smoothing degree of the prolongator (50 ms, 14).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .errors import SolverError


@dataclass(frozen=True)
class Level:
    """One level above the coarsest: its matrix A (n, n) and the prolongator P (n, n_coarse) to it from the next
    coarser level, R = P^T the restriction (CSR, single precision)."""

    A: sp.csr_matrix
    P: sp.csr_matrix
    R: sp.csr_matrix


class VCycle:
    """x = M b for b (n,) or (n, k): one V-cycle of the levels down to ``coarse``, the coarsest matrix's dense
    pseudo-inverse (double precision); the levels' arithmetic in ``dtype`` (single precision), in and out in double.
    With no levels (a system within the coarsest size) the cycle is that inverse: an exact solve."""

    def __init__(self, levels: list[Level], coarse: np.ndarray, dtype=np.float32):
        self.levels, self.coarse, self.dtype = levels, coarse, np.dtype(dtype)
        self.shape = levels[0].A.shape if levels else coarse.shape

    @property
    def nbytes(self) -> int:
        """What the cycle holds [bytes]: the levels' matrices and the coarsest inverse."""
        mats = [m for lv in self.levels for m in (lv.A, lv.P, lv.R)]
        return int(sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in mats) + self.coarse.nbytes)

    def __matmul__(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b)
        if b.ndim == 2:
            return np.column_stack([self @ b[:, j] for j in range(b.shape[1])])
        if b.shape != (self.shape[0],):
            raise SolverError(f"a V-cycle of {self.shape[0]} unknowns applied to a vector of shape {b.shape}")
        from pyamg import amg_core

        rhs = [b.astype(self.dtype)]
        xs = []
        for lv in self.levels:  # down: smooth from zero (forward sweep), restrict the residual
            A, f = lv.A, rhs[-1]
            x = np.zeros_like(f)
            amg_core.gauss_seidel(A.indptr, A.indices, A.data, x, f, 0, len(f), 1)
            xs.append(x)
            rhs.append(lv.R @ (f - A @ x))
        x = self.coarse @ rhs[-1].astype(float)
        if not self.levels:
            return x
        x = x.astype(self.dtype)
        for lv, xf, f in zip(reversed(self.levels), reversed(xs), reversed(rhs[:-1])):  # up: correct, smooth back
            xf += lv.P @ x
            A = lv.A
            amg_core.gauss_seidel(A.indptr, A.indices, A.data, xf, f, len(f) - 1, -1, -1)
            x = xf
        return x.astype(float)


def hierarchy(upper: sp.csr_matrix, max_coarse: int, dtype=np.float32) -> VCycle:
    """The V-cycle of pyamg's smoothed-aggregation hierarchy for A (n, n) symmetric positive definite, given by its
    upper triangle ``upper`` (CSR, the diagonal included), n a multiple of 3 (node-interleaved components), down to at
    most ``max_coarse`` unknowns. pyamg draws its spectral-radius estimates
    from numpy's global random numbers: seeded here (the same cycle from the same values, as a restored state needs),
    the caller's random state put back."""
    import pyamg

    n = upper.shape[0]
    if n % 3:
        raise SolverError(f"multigrid aggregates 3x3 node blocks: {n} unknowns is not a multiple of 3")
    if n // 3 <= max(1, max_coarse // 3):  # within the coarsest level: its dense inverse alone (double precision)
        return VCycle([], np.linalg.pinv((upper + sp.triu(upper, 1).T).toarray()), dtype)
    # the set-up in single precision as well: its peak is the energy smoother's temporaries (72k tet4 nodes: 246 MB
    # above the start instead of 390, the same iterations; the coarsest level inverted in double precision)
    upper = sp.csr_matrix((upper.data.astype(dtype), upper.indices, upper.indptr), shape=upper.shape)
    A = upper + upper.T.tocsr()  # the whole matrix (the lower triangle's CSR is the upper's CSC), its diagonal twice
    A.setdiag(upper.diagonal())  # (in place: every diagonal entry is there)
    del upper
    A = A.tobsr(blocksize=(3, 3))  # (the set-up holds only this copy besides the caller's upper triangle)
    B = np.tile(np.eye(3, dtype=dtype), (n // 3, 1))  # the translations, node by node
    levels: list[Level] = []
    state = np.random.get_state()
    np.random.seed(0)
    try:
        # one level at a time (pyamg's solver asked for two levels, the coarse one fed to the next call): each level's
        # matrix (A, then P^T A P), sorted by scipy's compiled kernel, is marked canonical (neither a sum nor a product
        # has duplicate entries), which neither scipy's conversion nor pyamg's own loop does, so that scipy's
        # pure-Python BSR sum_duplicates ran at each abs() of the energy smoother (549k tet4 nodes: 5.9 s of a 20 s
        # set-up)
        while A.shape[0] // 3 > max(1, max_coarse // 3):  # (pyamg counts the block matrix's nodes)
            A.sort_indices()
            A.has_canonical_format = True
            # aggregated node by node (3x3 blocks: a node's three components in one aggregate)
            ml = pyamg.smoothed_aggregation_solver(A, B=B, symmetry="symmetric",
                                                   strength=("symmetric", {"theta": 0.0}),
                                                   smooth=("energy", {"maxiter": 2, "weighting": "diagonal"}),
                                                   improve_candidates=None,
                                                   presmoother=None, postsmoother=None, max_levels=2,
                                                   max_coarse=max(1, max_coarse // 3))
            if len(ml.levels) < 2:  # (no coarser level could be made)
                break
            fine, coarse = ml.levels
            P = fine.P.tocsr().astype(dtype, copy=False)
            levels.append(Level(A.tocsr().astype(dtype, copy=False), P, P.T.tocsr()))
            A, B = coarse.A.tobsr(blocksize=(3, 3)), coarse.B
            del ml, fine, coarse, P  # (pyamg's copies go as soon as ours are made: the set-up's peak)
    finally:
        np.random.set_state(state)
    # the coarsest level (a system within max_coarse is only that): its dense pseudo-inverse, as pyamg's "pinv"
    return VCycle(levels, np.linalg.pinv(A.toarray().astype(float)), dtype)
