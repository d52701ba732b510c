"""Sparse symmetric positive definite solves with the symbolic analysis done once per pattern.

Backends, each a :class:`Factorization` (analyse, factorize, solve with one or many right-hand sides): "pardiso"
(Intel MKL PARDISO through pypardiso, real SPD, mtype 2, upper triangle, analysis / numeric factorisation / solve as
separate phases, double or single precision), "blocks" (softbody.cholesky: a compiled Cholesky in 3x3 node blocks,
for small systems, where PARDISO's cost is mostly per call) and "superlu" (scipy, the fallback when MKL is not
installed). :func:`choose_backend` is the one place that picks: ``backend="auto"`` (default: "blocks" for a system
whose factor is small, see :func:`prefers_blocks`, else PARDISO, else SuperLU) or by name. :class:`SpdSolver` wraps
the chosen one with what every backend shares (the first factorisation's analysis, a factor kept for the same
values, its values saved and restored).
"""
from __future__ import annotations

import glob
import importlib.util
import os
import sys
from typing import Protocol

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

BACKENDS = ("auto", "pardiso", "blocks", "superlu", "amg")

HAVE_PYAMG = importlib.util.find_spec("pyamg") is not None  # "amg": algebraic multigrid, the iterative path's

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


class Factorization(Protocol):
    """One backend's factor of SPD matrices of one sparsity pattern (the upper triangle in CSR, size n): a new
    backend is one class of this protocol, registered in FACTORIZATIONS and chosen by :func:`choose_backend`."""

    name: str

    def analyse(self, data: np.ndarray) -> None:
        """Symbolic analysis (fill-reducing ordering) of the pattern, values ``data`` at hand."""
        ...

    def factorize(self, data: np.ndarray) -> None:
        """Numeric factorisation of the upper-triangle values ``data`` (SolverError if not positive definite)."""
        ...

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x (n,) or (n, m) of A x = b for b (n,) or (n, m): several right-hand sides in one call."""
        ...

    #: False for a preconditioner that only approximates A^-1 (the iterative path alone takes it)
    exact: bool

    def costs(self) -> tuple[float, float] | None:
        """(cost of a numeric factorisation, cost of one solve with one right-hand side) in units comparable in
        time, from counts made by the analysis (not timed), or None if the backend does not know them."""
        ...

    @property
    def has_factor(self) -> bool:
        """Whether a successful factorisation is held."""
        ...

    def drop(self) -> None:
        """Forget the numeric factor (solves need a factorisation again)."""
        ...

    def release(self) -> None:
        """Free memory held outside Python (called when the solver goes)."""
        ...


class PardisoFactorization:
    """Intel MKL PARDISO (pypardiso), real SPD (mtype 2), upper triangle, analysis / numeric factorisation / solve as
    separate phases, in double or single precision (iparm 28)."""

    name = "pardiso"
    exact = True
    ORDERINGS = {2: "METIS nested dissection", 0: "minimum degree"}
    #: a factorisation's flop runs this much faster than a solve's (dense supernodal kernels against memory-bound
    #: triangular passes), measured in single precision on the sheet-on-sphere systems: factorisation time over
    #: one PCG iteration's time = (factor flops / solve flops) / 7-11 from 31k to 72k tet4 nodes and 24k tet10
    #: nodes, / 3-6 on systems of a few thousand nodes, where each call's overhead counts (there the model
    #: refactorises somewhat sooner than the times would)
    FACTOR_SPEEDUP = 10.0

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, dtype, symbolic=None):
        self.n, self.dtype = n, dtype
        self._ps = PyPardisoSolver(mtype=2)
        # non-default iparm: no iterative refinement (MKL's default does two refinement steps per solve, which
        # makes it about 4x slower and buys nothing for a Cholesky factor of an SPD matrix), and the factor and
        # solve in the requested precision
        self._ps.iparm[0], self._ps.iparm[1], self._ps.iparm[7] = 1, 2, 0
        self._ps.iparm[27] = 1 if dtype == np.float32 else 0
        self._ps.iparm[34] = 1  # zero-based indices: the pattern's own arrays, no one-based copy (16 MB at 72k nodes)
        # else every solver re-globs sys.prefix (~0.5 s)
        os.environ.setdefault("PYPARDISO_MKL_RT", self._ps.libmkl._name)
        self._ia = np.ascontiguousarray(indptr, dtype=np.int32)  # (views of the caller's int32 arrays: no copy)
        self._ja = np.ascontiguousarray(indices, dtype=np.int32)
        self._data = None
        self._analysed = False

    def _call(self, phase: int, data: np.ndarray, b: np.ndarray) -> np.ndarray:
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

    def analyse(self, data: np.ndarray) -> None:
        """Both orderings are analysed and the one whose factorisation needs fewer floating-point operations (as
        PARDISO counts them) is kept: nested dissection wins on large meshes, minimum degree on small ones. The
        choice is made from the sparsity pattern, not from timings; MKL's METIS carries a random state within a
        process, so the same sequence of analyses gives the same orderings run after run, but two solvers in one
        process may order slightly differently."""
        data = np.ascontiguousarray(data, dtype=float)
        ps = self._ps
        flops = {}
        for order in self.ORDERINGS:
            # iparm[18] < 0: report the factorisation's Mflop; iparm[17] < 0: the factor's nonzeros
            ps.iparm[1], ps.iparm[17], ps.iparm[18] = order, -1, -1
            self._call(11, data, np.zeros(self.n))
            flops[order] = int(ps.iparm[18])
        best = min(flops, key=lambda o: (flops[o], o != 2))
        if best != order:
            ps.iparm[1], ps.iparm[17], ps.iparm[18] = best, -1, -1
            self._call(11, data, np.zeros(self.n))
        self.ordering = self.ORDERINGS[best]
        self.factor_mflop = int(ps.iparm[18])
        self.factor_nonzeros = int(ps.iparm[17])
        self.factor_bytes = 1024 * int(ps.iparm[16])  # PARDISO's memory for the factorisation and solves (its count)
        self._analysed = True

    def costs(self) -> tuple[float, float] | None:
        """PARDISO's own counts: the factorisation's Mflop (/ FACTOR_SPEEDUP), and a solve as a forward and a
        backward pass over the factor's nonzeros (2 flops each)."""
        if not self._analysed or self.factor_nonzeros <= 0:
            return None
        return 1e6 * self.factor_mflop / self.FACTOR_SPEEDUP, 4.0 * self.factor_nonzeros

    def factorize(self, data: np.ndarray) -> None:
        self._data = None
        data = np.ascontiguousarray(data, dtype=self.dtype)  # kept for the solve phase
        self._call(22, data, np.zeros(self.n))
        self._data = data

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._data is None:
            raise SolverError("solve before a successful factorisation")
        return self._call(33, self._data, np.asfortranarray(b))

    @property
    def has_factor(self) -> bool:
        return self._data is not None

    def drop(self) -> None:
        self._data = None

    def release(self) -> None:
        if self._analysed:
            try:
                self._call(-1, np.zeros(1), np.zeros(self.n))
                # MKL keeps what PARDISO let go in its own pool: back to the system (a large body's analysis made only
                # to count its factor, multigrid chosen instead: 89 MB at 72k tet4 nodes; buffers in use stay, and
                # the library solves from one thread)
                self._ps.libmkl.mkl_free_buffers()
            except Exception:
                pass


class _HeldFactor:
    """What a backend whose factor is a Python object (``_factor``, None without one) shares."""

    _factor = None
    exact = True

    @property
    def has_factor(self) -> bool:
        return self._factor is not None

    def drop(self) -> None:
        self._factor = None

    def release(self) -> None:
        pass


class BlockCholeskyFactorization(_HeldFactor):
    """softbody.cholesky: a compiled Cholesky in 3x3 node blocks, for small systems, where PARDISO's cost is mostly
    per call (double precision)."""

    name = "blocks"

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, dtype, symbolic=None):
        self.n = n
        self._symbolic = symbolic if symbolic is not None else cholesky.BlockSymbolic.of(indptr, indices, n)
        self._factor = None
        self._where = None

    def analyse(self, data: np.ndarray) -> None:
        pass  # (the symbolic analysis is made with the solver: the "auto" choice reads it)

    def costs(self) -> tuple[float, float] | None:
        """From the symbolic analysis: 27 multiply-adds per block product; a solve passes twice over L's blocks
        (flops of the factorisation taken as PARDISO's, PardisoFactorization.FACTOR_SPEEDUP)."""
        S = self._symbolic
        return 54.0 * S.multiply_adds / PardisoFactorization.FACTOR_SPEEDUP, 36.0 * len(S.row)

    def factorize(self, data: np.ndarray) -> None:
        S = self._symbolic
        factor = self._factor if self._factor is not None else np.empty((len(S.row), 3, 3))
        if self._where is None:
            self._where = np.empty(len(S.perm), dtype=np.int64)
        self._factor = None
        failed = cholesky.factorize_blocks(data, S.dest, S.mirror, S.col_ptr, S.row, S.row_ptr, S.row_col,
                                           S.row_pos, factor, self._where)
        if failed >= 0:
            raise SolverError(f"block Cholesky failed at node {int(S.perm[failed])} (matrix not positive definite)")
        self._factor = factor

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._factor is None:
            raise SolverError("solve before a successful factorisation")
        S, N = self._symbolic, self.n // 3
        if b.ndim == 1 or b.shape[1] == 1:
            x = np.empty((N, 3))
            cholesky.solve_block(self._factor, S.col_ptr, S.row, S.perm, np.ascontiguousarray(b.reshape(N, 3)), x)
        else:
            x = np.empty((N, 3, b.shape[1]))
            cholesky.solve_blocks(self._factor, S.col_ptr, S.row, S.perm, np.ascontiguousarray(b.reshape(N, 3, -1)), x)
        return x.reshape(b.shape)


class SuperLUFactorization(_HeldFactor):
    """scipy's SuperLU (the fallback without MKL), symmetric mode on the whole matrix, in the solver's precision."""

    name = "superlu"

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, dtype, symbolic=None):
        self.n, self.dtype, self.indptr, self.indices = n, dtype, indptr, indices
        self._factor = None

    def analyse(self, data: np.ndarray) -> None:
        pass  # (SuperLU orders at each factorisation)

    def costs(self) -> None:
        return None  # SuperLU orders and counts only while it factorises

    def factorize(self, data: np.ndarray) -> None:
        self._factor = None
        U = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        A = (U + sp.triu(U, 1).T).tocsc()
        try:
            self._factor = spla.splu(A.astype(self.dtype), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                     options=dict(SymmetricMode=True))
        except RuntimeError as exc:
            raise SolverError(f"SuperLU factorisation failed: {exc}") from exc

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._factor is None:
            raise SolverError("solve before a successful factorisation")
        return self._factor.solve(b.astype(self.dtype)).astype(np.float64, copy=False)


class AMGFactorization(_HeldFactor):
    """Algebraic multigrid (softbody.multigrid: pyamg's smoothed aggregation, our V-cycle in single precision) as the
    iterative path's preconditioner: no factor, so its memory stays a few times A's (a factor of a large 3-D body grows
    as N^4/3 and beyond); ``solve`` applies one V-cycle, a fixed symmetric positive definite approximation of A^-1
    (a forward Gauss-Seidel sweep down, a backward one up), as PCG needs. The near null space is the three translations
    per node (pattern only; the rotations as well cut the iterations from 18 to 14 on the 72k-node sheet but double
    the hierarchy's size and the cycle's cost)."""

    name = "amg"
    exact = False
    #: a set-up's price in V-cycles for the refactorisation rule (Preconditioner.refactor_cost): chosen by the tet4
    #: sheet through the impact (72k nodes, steps 10-30: 1.36 / 1.31 / 1.99 s a step with 40 / 80 / 160; a set-up
    #: takes 1.3 s there, 40-45 cycles, but also restores the convergence rate that the bending sheet's changing
    #: matrix wears down, 0.45 -> 0.62 per iteration over nine steps)
    SETUP_CYCLES = 80.0
    #: unknowns of the coarsest level, solved exactly (a system this small is one level: an exact solve)
    MAX_COARSE = 1000

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, dtype, symbolic=None):
        self.n, self.indptr, self.indices = n, indptr, indices
        self._factor = None

    def analyse(self, data: np.ndarray) -> None:
        pass  # (the aggregation follows the values, at each set-up)

    def costs(self) -> tuple[float, float]:
        return self.SETUP_CYCLES, 1.0

    def factorize(self, data: np.ndarray) -> None:
        from . import multigrid

        self._factor = None
        upper = sp.csr_matrix((np.asarray(data, dtype=float), self.indices, self.indptr), shape=(self.n, self.n))
        self._factor = multigrid.hierarchy(upper, self.MAX_COARSE)

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._factor is None:
            raise SolverError("solve before a successful multigrid set-up")
        return self._factor @ b


#: the backends by name (BACKENDS less "auto"): a new one is a Factorization class added here
FACTORIZATIONS: dict[str, type] = {"pardiso": PardisoFactorization, "blocks": BlockCholeskyFactorization,
                                   "superlu": SuperLUFactorization, "amg": AMGFactorization}


def choose_backend(indptr: np.ndarray, indices: np.ndarray, n: int, backend: str = "auto"
                   ) -> tuple[str, cholesky.BlockSymbolic | None]:
    """The one place a backend is chosen: ``backend`` checked (InvalidInputError naming what is missing), and
    "auto" resolved: "blocks" for a system whose factor is small (:func:`prefers_blocks`), else PARDISO, else
    SuperLU. Returns the name and, for "blocks", its symbolic analysis."""
    if backend not in BACKENDS:
        raise InvalidInputError(f"unknown solver backend {backend!r}; valid: {BACKENDS}")
    if backend == "pardiso" and not HAVE_PARDISO:
        raise InvalidInputError("backend 'pardiso' needs pypardiso (pip install pypardiso)")
    if backend == "amg":
        if not HAVE_PYAMG:
            raise InvalidInputError("backend 'amg' needs pyamg (pip install pyamg)")
        if n % 3:
            raise InvalidInputError(f"backend 'amg' needs 3x3 node blocks: n a multiple of 3, got {n}")
    if backend == "blocks" and n % 3:
        raise InvalidInputError(f"backend 'blocks' needs 3x3 node blocks: n a multiple of 3, got {n}")
    if backend == "blocks" and not kernels.AVAILABLE:  # named by the user: compiled at first use, warm-up or not
        raise InvalidInputError("backend 'blocks' is compiled: it needs numba, and SOFTBODY_NO_NUMBA unset")
    if backend == "blocks":
        return "blocks", cholesky.BlockSymbolic.of(indptr, indices, n)
    if backend == "auto":
        symbolic = prefers_blocks(indptr, indices, n)
        if symbolic is not None:
            return "blocks", symbolic
        return ("pardiso" if HAVE_PARDISO else "superlu"), None
    return backend, None


class SpdSolver:
    """Factorise and solve A x = b for SPD matrices sharing one sparsity pattern.

    indptr, indices: the upper triangle (including the diagonal) of A in CSR with sorted indices,
    size n. ``factorize(data)`` takes the matching values; the symbolic analysis (ordering) runs on
    the first call only. ``solve(b)`` takes b of shape (n,) or (n, m). precision "single" factorises and
    solves in single precision (PARDISO) or in double (the other backends). The backend's own work is a
    :class:`Factorization` (``factorization``), chosen once by :func:`choose_backend`.
    """

    ORDERINGS = PardisoFactorization.ORDERINGS

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, backend: str = "auto",
                 precision: str = "double"):
        if precision not in ("double", "single"):
            raise InvalidInputError(f"precision must be 'double' or 'single', got {precision!r}")
        self.n = int(n)
        self.indptr = np.asarray(indptr, dtype=np.int32)
        self.indices = np.asarray(indices, dtype=np.int32)
        self.backend, symbolic = choose_backend(self.indptr, self.indices, self.n, backend)
        self.precision = precision
        self.dtype = np.float64 if precision == "double" or self.backend != "pardiso" else np.float32
        self.factorization: Factorization = FACTORIZATIONS[self.backend](self.indptr, self.indices, self.n,
                                                                        self.dtype, symbolic)
        self._analysed = False

    @property
    def ordering(self) -> str | None:
        """The fill-reducing ordering the analysis chose (PARDISO's), else None."""
        return getattr(self.factorization, "ordering", None)

    @property
    def factor_mflop(self) -> int | None:
        """The factorisation's cost in Mflop as PARDISO counts it, else None."""
        return getattr(self.factorization, "factor_mflop", None)

    def costs(self) -> tuple[float, float] | None:
        """(cost of a factorisation, cost of a one-column solve) as the backend counts them (Factorization.costs),
        None before the analysis or where the backend has no count."""
        return self.factorization.costs() if self._analysed else None

    @property
    def exact(self) -> bool:
        """False if the backend only approximates A^-1 (a preconditioner: the iterative path alone takes it)."""
        return self.factorization.exact

    def analyse(self, data: np.ndarray) -> None:
        """Symbolic analysis (fill-reducing ordering); called automatically on first factorisation (PARDISO: the
        ordering of fewer factorisation flops, PardisoFactorization.analyse; ``ORDERINGS`` those tried)."""
        f = self.factorization
        if isinstance(f, PardisoFactorization) and self.ORDERINGS is not f.ORDERINGS:
            f.ORDERINGS = self.ORDERINGS  # (a caller may narrow the orderings tried: the tests do)
        f.analyse(data)
        self._analysed = True

    def factorize(self, data: np.ndarray) -> None:
        """Numeric factorisation of the matrix with upper-triangle values ``data``; the values of the current factor
        again keep it (a body without warping, whose step matrix is constant, is factorised once: ``refactorizations``
        counts the factorisations done, ``kept`` those skipped)."""
        data = np.ascontiguousarray(data, dtype=float)
        kept = self.__dict__.get("_values")
        if kept is not None and kept.shape == data.shape and np.array_equal(kept, data) \
                and self.factorization.has_factor:
            self.kept = self.__dict__.get("kept", 0) + 1
            return
        if not np.all(np.isfinite(data)):
            raise SolverError("system matrix has non-finite entries")
        self.refactorizations = self.__dict__.get("refactorizations", 0) + 1
        if not self._analysed:
            self.analyse(data)
        self._values = None  # set again once this factorisation succeeds
        self.factorization.factorize(data)
        self._values = data  # kept, not copied: callers pass an array of their own (see factor_values)

    def factor_values(self) -> np.ndarray | None:
        """A copy of the upper-triangle values (float64) of the current factorisation, None without one: what
        :meth:`refactorize` needs to rebuild the same factor (a saved state, softbody.state)."""
        values = self.__dict__.get("_values")
        if values is None or not self.factorization.has_factor:
            return None
        return values.copy()

    def refactorize(self, values: np.ndarray | None) -> None:
        """Factorise ``values`` (from :meth:`factor_values`) again: with this solver's analysis, the same factor to
        the bit; None drops the factor (solves then need a factorisation first)."""
        if values is None:
            self._values = None
            self.factorization.drop()
            return
        values = np.asarray(values, dtype=float)
        if values.shape != self.indices.shape:
            raise InvalidInputError(f"factor values of shape {values.shape} for a pattern of {len(self.indices)} "
                                    "upper-triangle entries: saved from another body or mesh")
        self.factorize(values.copy())

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x of A x = b, b (n,) or (n, m) [several right-hand sides in one call]."""
        return self.factorization.solve(np.asarray(b, dtype=float))

    def __del__(self):  # release the backend's memory for this factorisation (MKL's)
        f = self.__dict__.get("factorization")
        if f is not None:
            f.release()
