"""Sparse symmetric positive definite solves with the symbolic analysis done once per pattern.

Backends: "pardiso" (Intel MKL PARDISO through pypardiso, real SPD, mtype 2, upper triangle,
analysis / numeric factorisation / solve as separate phases), "blocks" (softbody.cholesky: a compiled
Cholesky in 3x3 node blocks, for small systems, where PARDISO's cost is mostly per call) and "superlu"
(scipy, the fallback when MKL is not installed). Pick with ``backend="auto"`` (default: "blocks" for a
system whose factor is small, see :func:`prefers_blocks`, else PARDISO, else SuperLU) or by name.
"""
from __future__ import annotations

import glob
import os
import sys

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import cholesky, kernels
from .errors import InvalidInputError, SolverError


def _point_pypardiso_at_mkl() -> None:
    """Tell pypardiso where MKL's runtime is when pip put it in this environment's lib (or Library/bin) directory:
    else, when the system's loader cannot find it, pypardiso searches all of sys.prefix recursively for it, about
    0.5 s per search and two at its import. A path given in PYPARDISO_MKL_RT is left alone."""
    if "PYPARDISO_MKL_RT" in os.environ:
        return
    for folder in (os.path.join(sys.prefix, "lib"), os.path.join(sys.prefix, "Library", "bin")):
        found = sorted(glob.glob(os.path.join(folder, "*mkl_rt*")), key=len)
        if found:
            os.environ["PYPARDISO_MKL_RT"] = found[0]
            return


_point_pypardiso_at_mkl()
try:  # pragma: no cover - availability depends on the machine
    from pypardiso.pardiso_wrapper import PyPardisoSolver

    HAVE_PARDISO = True
except Exception:  # ImportError, or mkl_rt missing
    HAVE_PARDISO = False

BACKENDS = ("auto", "pardiso", "blocks", "superlu")

# systems of at most this many unknowns are considered for the "blocks" backend (its symbolic analysis, a
# minimum-degree ordering in Python, takes about 50 ms at this size; far below it the factor decides)
BLOCKS_MAX_UNKNOWNS = 1800


def prefers_blocks(indptr: np.ndarray, indices: np.ndarray, n: int) -> cholesky.BlockSymbolic | None:
    """The block factor's symbolic analysis if "auto" should pick the "blocks" backend for this pattern (small, in
    3x3 blocks, a factor of at most cholesky.SMALL_FACTOR block products, numba available), else None."""
    if not kernels.ENABLED or n % 3 or n > BLOCKS_MAX_UNKNOWNS:
        return None
    symbolic = cholesky.BlockSymbolic.of(indptr, indices, n)
    return symbolic if symbolic.multiply_adds <= cholesky.SMALL_FACTOR else None


THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS")


def set_threads(n: int) -> None:
    """Pin the solver's and BLAS's threads to n >= 1: MKL at run time, and the environment variables
    (THREAD_VARS) that act on libraries loaded later and on child processes."""
    if n < 1:
        raise InvalidInputError(f"threads must be >= 1, got {n}")
    for var in THREAD_VARS:
        os.environ[var] = str(n)
    if HAVE_PARDISO:
        PyPardisoSolver().libmkl.MKL_Set_Num_Threads(int(n))


class SpdSolver:
    """Factorise and solve A x = b for SPD matrices sharing one sparsity pattern.

    indptr, indices: the upper triangle (including the diagonal) of A in CSR with sorted indices,
    size n. ``factorize(data)`` takes the matching values; the symbolic analysis (ordering) runs on
    the first call only. ``solve(b)`` takes b of shape (n,) or (n, m). precision "single" factorises and
    solves in single precision (PARDISO) or in double (the other backends).
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, backend: str = "auto",
                 precision: str = "double"):
        if backend not in BACKENDS:
            raise InvalidInputError(f"unknown solver backend {backend!r}; valid: {BACKENDS}")
        if backend == "pardiso" and not HAVE_PARDISO:
            raise InvalidInputError("backend 'pardiso' needs pypardiso (pip install pypardiso)")
        if backend == "blocks" and n % 3:
            raise InvalidInputError(f"backend 'blocks' needs 3x3 node blocks: n a multiple of 3, got {n}")
        if backend == "blocks" and not kernels.AVAILABLE:  # named by the user: compiled at first use, warm-up or not
            raise InvalidInputError("backend 'blocks' is compiled: it needs numba, and SOFTBODY_NO_NUMBA unset")
        self._blocks = prefers_blocks(indptr, indices, n) if backend == "auto" else None
        if backend == "blocks":
            self._blocks = cholesky.BlockSymbolic.of(indptr, indices, n)
        if self._blocks is not None:
            self.backend = "blocks"
        else:
            self.backend = "pardiso" if backend == "auto" and HAVE_PARDISO else ("superlu" if backend == "auto" else backend)
        if precision not in ("double", "single"):
            raise InvalidInputError(f"precision must be 'double' or 'single', got {precision!r}")
        self.precision = precision
        self.dtype = np.float64 if precision == "double" else np.float32
        self.n = int(n)
        self.indptr = np.asarray(indptr, dtype=np.int32)
        self.indices = np.asarray(indices, dtype=np.int32)
        self._analysed = False
        self._factor = None
        if self.backend == "pardiso":
            self._ps = PyPardisoSolver(mtype=2)
            # non-default iparm: no iterative refinement (MKL's default does two refinement
            # steps per solve, which makes it about 4x slower and buys nothing for a Cholesky factor of an SPD
            # matrix), and the factor and solve in the requested precision
            self._ps.iparm[0], self._ps.iparm[1], self._ps.iparm[7] = 1, 2, 0
            self._ps.iparm[27] = 1 if precision == "single" else 0
            os.environ.setdefault("PYPARDISO_MKL_RT", self._ps.libmkl._name)  # else every solver re-globs sys.prefix (~0.5 s)
            self._ia = self.indptr + 1  # Fortran indexing, built once
            self._ja = self.indices + 1
            self._matrix = sp.csr_matrix((np.ones(len(self.indices)), self.indices, self.indptr), shape=(n, n))

    def _pardiso(self, phase: int, data: np.ndarray, b: np.ndarray) -> np.ndarray:
        import ctypes

        ps = self._ps
        data = np.ascontiguousarray(data, dtype=self.dtype)
        b = np.asfortranarray(b, dtype=self.dtype)
        x = np.zeros_like(b)
        err = ctypes.c_int32(0)
        f64 = ctypes.c_void_p
        if "_fixed_args" not in self.__dict__:  # pointers to arrays that live as long as the solver
            i32 = ctypes.POINTER(ctypes.c_int32)
            self._fixed_args = (ps.pt.ctypes.data_as(ctypes.POINTER(ps._pt_type[0])), self._ia.ctypes.data_as(i32),
                                self._ja.ctypes.data_as(i32), ps.perm.ctypes.data_as(i32),
                                ps.iparm.ctypes.data_as(i32))
        pt, ia, ja, perm, iparm = self._fixed_args
        one = ctypes.byref(ctypes.c_int32(1))
        ps._mkl_pardiso(pt, one, one, ctypes.byref(ctypes.c_int32(2)), ctypes.byref(ctypes.c_int32(phase)),
                        ctypes.byref(ctypes.c_int32(self.n)), f64(data.ctypes.data), ia, ja, perm,
                        ctypes.byref(ctypes.c_int32(1 if b.ndim == 1 else b.shape[1])),
                        iparm, ctypes.byref(ctypes.c_int32(0)),
                        f64(b.ctypes.data), f64(x.ctypes.data), ctypes.byref(err))
        if err.value != 0:
            raise SolverError(f"PARDISO phase {phase} failed with error {err.value}"
                              + (" (matrix not positive definite)" if err.value == -4 else ""))
        return x.astype(np.float64, copy=False)

    ORDERINGS = {2: "METIS nested dissection", 0: "minimum degree"}

    def analyse(self, data: np.ndarray) -> None:
        """Symbolic analysis (fill-reducing ordering); called automatically on first factorisation.

        PARDISO: both orderings are analysed and the one whose factorisation needs fewer floating-point
        operations (as PARDISO counts them) is kept: nested dissection wins on large meshes, minimum
        degree on small ones. The choice is made from the sparsity pattern, not from timings; MKL's
        METIS carries a random state within a process, so the same sequence of analyses gives the same
        orderings run after run, but two solvers in one process may order slightly differently.
        """
        if self.backend == "pardiso":
            data = np.ascontiguousarray(data, dtype=float)
            ps = self._ps
            flops = {}
            for order in self.ORDERINGS:
                ps.iparm[1], ps.iparm[18] = order, -1  # iparm[18] < 0: report the factorisation's Mflop
                self._pardiso(11, data, np.zeros(self.n))
                flops[order] = int(ps.iparm[18])
            best = min(flops, key=lambda o: (flops[o], o != 2))
            if best != order:
                ps.iparm[1], ps.iparm[18] = best, -1
                self._pardiso(11, data, np.zeros(self.n))
            self.ordering = self.ORDERINGS[best]
            self.factor_mflop = int(ps.iparm[18])
        self._analysed = True

    def factorize(self, data: np.ndarray) -> None:
        """Numeric factorisation of the matrix with upper-triangle values ``data``; the values of the current factor
        again keep it (a body without warping, whose step matrix is constant, is factorised once: ``refactorizations``
        counts the factorisations done, ``kept`` those skipped)."""
        data = np.ascontiguousarray(data, dtype=float)
        kept = self.__dict__.get("_values")
        if kept is not None and kept.shape == data.shape and np.array_equal(kept, data) \
                and (self.backend != "blocks" or self._factor is not None):
            self.kept = self.__dict__.get("kept", 0) + 1
            return
        if not np.all(np.isfinite(data)):
            raise SolverError("system matrix has non-finite entries")
        self.refactorizations = self.__dict__.get("refactorizations", 0) + 1
        if not self._analysed:
            self.analyse(data)
        self._values = None  # set again once this factorisation succeeds
        if self.backend == "pardiso":
            self._data = np.ascontiguousarray(data, dtype=self.dtype)  # kept for the solve phase
            self._pardiso(22, self._data, np.zeros(self.n))
        elif self.backend == "blocks":
            S = self._blocks
            if self._factor is None:
                self._factor = np.empty((len(S.row), 3, 3))
                self._where = np.empty(len(S.perm), dtype=np.int64)
            failed = cholesky.factorize_blocks(data, S.dest, S.mirror, S.col_ptr, S.row, S.row_ptr, S.row_col,
                                               S.row_pos, self._factor, self._where)
            if failed >= 0:
                self._factor = None
                raise SolverError(f"block Cholesky failed at node {int(S.perm[failed])} (matrix not positive definite)")
        else:
            U = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
            A = (U + sp.triu(U, 1).T).tocsc()
            try:
                self._factor = spla.splu(A.astype(self.dtype), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                         options=dict(SymmetricMode=True))
            except RuntimeError as exc:
                raise SolverError(f"SuperLU factorisation failed: {exc}") from exc
        self._values = data  # kept, not copied: callers pass an array of their own (see factor_values)

    def factor_values(self) -> np.ndarray | None:
        """A copy of the upper-triangle values (float64) of the current factorisation, None without one: what
        :meth:`refactorize` needs to rebuild the same factor (a saved state, softbody.state)."""
        values = self.__dict__.get("_values")
        if values is None or (self.backend == "blocks" and self._factor is None):
            return None
        return values.copy()

    def refactorize(self, values: np.ndarray | None) -> None:
        """Factorise ``values`` (from :meth:`factor_values`) again: with this solver's analysis, the same factor to
        the bit; None drops the factor (solves then need a factorisation first)."""
        if values is None:
            self._values = None
            if self.backend != "pardiso":
                self._factor = None
            return
        values = np.asarray(values, dtype=float)
        if values.shape != self.indices.shape:
            raise InvalidInputError(f"factor values of shape {values.shape} for a pattern of {len(self.indices)} "
                                    "upper-triangle entries: saved from another body or mesh")
        self.factorize(values.copy())

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=float)
        if self.backend == "pardiso":
            return self._pardiso(33, self._data, np.asfortranarray(b))
        if self.backend == "blocks":
            if self._factor is None:
                raise SolverError("solve before a successful factorisation")
            S, N = self._blocks, self.n // 3
            if b.ndim == 1 or b.shape[1] == 1:
                x = np.empty((N, 3))
                cholesky.solve_block(self._factor, S.col_ptr, S.row, S.perm, np.ascontiguousarray(b.reshape(N, 3)), x)
            else:
                x = np.empty((N, 3, b.shape[1]))
                cholesky.solve_blocks(self._factor, S.col_ptr, S.row, S.perm, np.ascontiguousarray(b.reshape(N, 3, -1)),
                                      x)
            return x.reshape(b.shape)
        return self._factor.solve(b.astype(self.dtype)).astype(np.float64, copy=False)

    def __del__(self):  # release MKL's memory for this factorisation
        if getattr(self, "backend", None) == "pardiso" and self._analysed:
            try:
                self._pardiso(-1, np.zeros(1), np.zeros(self.n))
            except Exception:
                pass
