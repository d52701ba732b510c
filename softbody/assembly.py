"""Sparse assembly with a fixed pattern: 3x3 node blocks, a precomputed scatter map from element
blocks into the block data, and a precomputed gather into the upper-triangular scalar CSR that the
Cholesky solver factorises. Everything here is built once per mesh; per step only data arrays move.
"""
from __future__ import annotations

from dataclasses import dataclass

import copy

import numpy as np
import scipy.sparse as sp

from . import kernels


@dataclass
class BlockPattern:
    """Node-level sparsity pattern of a mesh's 3N x 3N matrices.

    n_nodes: N. Blocks are stored in block-CSR order: ``indptr`` (N+1,), ``indices`` (nnzb,).
    ``scatter`` (E, k, k) maps element block (a, b) of element e to its global block index.
    ``diag`` (N,) is the block index of each node's diagonal block; ``mirror`` (nnzb,) the index of the
    block (B, A) for block (A, B). ``scatter_dof`` (E*3k*3k,), made on first use, maps the
    entries of element matrices in their natural (E, 3k, 3k) layout to ``block_data.reshape(-1)``.
    Upper CSR (for the solver): ``up_indptr``, ``up_indices`` and ``up_gather`` (nnz_up,), the index of
    each upper-triangular scalar entry in ``block_data.reshape(-1)`` (blocks flattened row-major 3x3).
    ``up_row``/``up_col`` give each scalar entry's dof, ``up_diag`` (3N,) the position of each diagonal entry.
    """

    n_nodes: int
    indptr: np.ndarray
    indices: np.ndarray
    scatter: np.ndarray
    diag: np.ndarray
    mirror: np.ndarray
    block_row: np.ndarray
    up_indptr: np.ndarray
    up_indices: np.ndarray
    up_gather: np.ndarray
    up_row: np.ndarray
    up_col: np.ndarray
    up_diag: np.ndarray

    @property
    def nnzb(self) -> int:
        return len(self.indices)

    @classmethod
    def from_elements(cls, elements: np.ndarray, n_nodes: int) -> "BlockPattern":
        E, k = elements.shape
        # every node gets a diagonal block, so that unused nodes can be constrained
        e = elements.astype(np.int64)
        key = np.concatenate([(e[:, :, None] * n_nodes + e[:, None, :]).ravel(),
                              np.arange(n_nodes, dtype=np.int64) * (n_nodes + 1)])
        del e
        ukey, inv = np.unique(key, return_inverse=True)
        del key
        brow, bcol = ukey // n_nodes, ukey % n_nodes
        itype = np.int32 if 9 * len(ukey) < 2**31 else np.int64
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.add.at(indptr, brow + 1, 1)
        indptr = np.cumsum(indptr)
        scatter = inv[: E * k * k].reshape(E, k, k).astype(itype)
        diag = inv[E * k * k:].copy()  # (a view would hold all of inv: 40 MB at 72k nodes)
        del inv
        mirror = np.searchsorted(ukey, bcol * n_nodes + brow)
        del ukey
        up_indptr, up_col, up_gather, up_row, up_diag = _upper_scalars(indptr, brow, bcol, n_nodes, itype)
        return cls(n_nodes, indptr, bcol.astype(np.int64), scatter, diag, mirror, brow.astype(np.int64),
                   up_indptr, up_col, up_gather, up_row, up_col, up_diag)

    @classmethod
    def from_keys(cls, keys: np.ndarray, n_nodes: int) -> "BlockPattern":
        """The pattern of the blocks with sorted unique keys row * n_nodes + col (k,), symmetric (each block's mirror
        among them) and holding every diagonal block (else a ValueError): no elements (``scatter`` empty: not for
        :meth:`assemble`). The same pattern as :meth:`from_elements` of those blocks as 2-node elements, without
        sorting them again (a coupled problem's pattern: its bodies' own patterns side by side, already sorted, and
        the few blocks contacts add)."""
        keys = np.asarray(keys, dtype=np.int64)
        brow, bcol = keys // n_nodes, keys % n_nodes
        itype = np.int32 if 9 * len(keys) < 2**31 else np.int64
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.cumsum(np.bincount(brow, minlength=n_nodes), out=indptr[1:])
        diagonal = np.arange(n_nodes, dtype=np.int64) * (n_nodes + 1)
        diag = np.searchsorted(keys, diagonal)
        mirror = np.searchsorted(keys, bcol * n_nodes + brow)
        if (len(keys) > 1 and not np.all(keys[1:] > keys[:-1])) or not (
                np.array_equal(keys[np.minimum(diag, len(keys) - 1)], diagonal)
                and np.array_equal(keys[np.minimum(mirror, len(keys) - 1)], bcol * n_nodes + brow)):
            raise ValueError(f"block keys for a pattern of {n_nodes} nodes must be sorted, unique, symmetric and hold "
                             "every diagonal block")
        up_indptr, up_col, up_gather, up_row, up_diag = _upper_scalars(indptr, brow, bcol, n_nodes, itype)
        return cls(n_nodes, indptr, bcol, np.zeros((0, 2, 2), dtype=itype), diag, mirror, brow,
                   up_indptr, up_col, up_gather, up_row, up_col, up_diag)

    @property
    def scatter_dof(self) -> np.ndarray:
        """(E*3k*3k,): scalar entry (e, 3a+i, 3b+j) -> 9 * block(e, a, b) + 3 i + j (made on first use:
        only whole element matrices need it, not the step)."""
        if "_scatter_dof" not in self.__dict__:
            s = self.scatter
            self._scatter_dof = (9 * s[:, :, None, :, None] + (3 * np.arange(3))[:, None, None]
                                 + np.arange(3)).reshape(-1)
        return self._scatter_dof

    def assemble(self, element_matrices: np.ndarray) -> np.ndarray:
        """Sum element matrices (E, 3k, 3k) (interleaved dofs) into block data (nnzb, 3, 3)."""
        return np.bincount(self.scatter_dof, weights=element_matrices.reshape(-1),
                           minlength=9 * self.nnzb).reshape(-1, 3, 3)

    def assemble_scalar(self, element_values: np.ndarray) -> np.ndarray:
        """Sum scalar element blocks (E, k, k) (a multiple of I3 per block) into (nnzb,)."""
        return np.bincount(self.scatter.ravel(), weights=element_values.ravel(), minlength=self.nnzb)

    def to_bsr(self, block_data: np.ndarray) -> sp.bsr_matrix:
        """The BSR matrix of block data (nnzb, 3, 3) on this pattern (sharing the data, no copy): a shallow copy
        of one checked matrix with its data swapped, 6 us against scipy's 85 us of format checks."""
        kept = self.__dict__.get("_bsr_template")  # (the template, the data's shape and dtype it was checked with)
        data = np.asarray(block_data)
        if kept is None or data.shape != kept[1] or data.dtype != kept[2]:
            n = 3 * self.n_nodes
            template = sp.bsr_matrix((np.zeros_like(data), self.indices.copy(), self.indptr.copy()), shape=(n, n))
            if data.shape != (self.nnzb, 3, 3):
                return sp.bsr_matrix((data, self.indices, self.indptr), shape=(n, n))  # scipy's error for bad data
            # every matrix made here shares these: read-only, so that an in-place change of the structure
            # (eliminate_zeros, sort_indices) fails loudly instead of corrupting the next ones
            template.indices.flags.writeable = False
            template.indptr.flags.writeable = False
            template.data = np.empty((0, 3, 3), dtype=data.dtype)  # each copy takes its own (72k nodes: 62 MB)
            kept = self._bsr_template = (template, data.shape, data.dtype)
        template = kept[0]
        matrix = copy.copy(template)
        matrix.data = data
        return matrix

    def product(self, block_data: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A y (N, 3) for the matrix of block data (nnzb, 3, 3) on this pattern and y (N, 3): compiled
        (kernels.block_product, summed as scipy's BSR product sums) or through :meth:`to_bsr`."""
        if kernels.ENABLED:
            out = np.empty((self.n_nodes, 3))
            kernels.block_product(np.ascontiguousarray(block_data, dtype=float), self.indptr, self.indices,
                                  np.ascontiguousarray(y, dtype=float), out)
            return out
        return (self.to_bsr(block_data) @ np.reshape(y, -1)).reshape(-1, 3)

    def to_csr(self, block_data: np.ndarray) -> sp.csr_matrix:
        return self.to_bsr(block_data).tocsr()

    def upper_data(self, block_data: np.ndarray) -> np.ndarray:
        """Values (nnz_up,) of the upper triangle in the order of ``up_indptr``/``up_indices``."""
        return block_data.reshape(-1)[self.up_gather]


def _upper_scalars(indptr: np.ndarray, brow: np.ndarray, bcol: np.ndarray, n_nodes: int, itype
                   ) -> tuple[np.ndarray, ...]:
    """The upper triangle's scalar CSR of a block pattern (block rows ``indptr`` (N+1,), each block's row and
    column (nnzb,), columns ascending within a row), made row by row from arithmetic, not by sorting every
    scalar entry: row 3A+i holds its diagonal block's entries j >= i, then 3 per upper block (A, B > A) in
    order. Returns up_indptr (3N+1,), up_col, up_gather (the entry's index in the flattened block data), up_row
    (nnz_up,) and up_diag (3N,)."""
    # the diagonal block's position in each block row (columns ascending: after the row's lower blocks)
    lower = np.bincount(brow[bcol < brow], minlength=n_nodes)
    dpos = indptr[:-1] + lower  # (N,)
    upper_count = indptr[1:] - dpos  # blocks (A, B >= A) per block row, the diagonal included
    i = np.tile(np.arange(3), n_nodes)
    A = np.repeat(np.arange(n_nodes), 3)
    length = 3 * (upper_count[A] - 1) + (3 - i)  # entries of scalar row 3A+i
    up_indptr = np.zeros(3 * n_nodes + 1, dtype=np.int64)
    np.cumsum(length, out=up_indptr[1:])
    n_up = int(up_indptr[-1])
    up_row = np.repeat(np.arange(3 * n_nodes, dtype=itype), length)
    o = np.arange(n_up, dtype=itype) - up_indptr[:-1].astype(itype)[up_row]  # offset within the row
    Ar, ir = up_row // 3, up_row % 3
    in_diag = o < 3 - ir
    q = o - (3 - ir)  # past the diagonal block: 3 per upper block
    block = np.where(in_diag, dpos.astype(itype)[Ar], dpos.astype(itype)[Ar] + 1 + q // 3)
    j = np.where(in_diag, ir + o, q % 3)
    del o, q, in_diag
    up_col = (3 * bcol.astype(itype)[block] + j).astype(itype)
    up_gather = (9 * block + 3 * ir + j).astype(itype)
    up_diag = up_indptr[:-1] + 0  # the diagonal entry is each row's first
    return up_indptr, up_col, up_gather, up_row, up_diag


@dataclass
class UpperAssembly:
    """Assembly of symmetric element matrices into the upper blocks (row <= column) of the pattern.

    Only the node pairs a <= b of each element contribute: about half the entries of whole element
    matrices. The result is the upper block data (n_upper, 9), each block row-major (a pair whose
    global nodes run the other way goes in transposed), so that a per-block linear map (an isotropic
    material's stiffness, see :func:`softbody.warping.isotropic_blocks`) applies block by block.
    ``full`` then mirrors the upper blocks into block data (nnzb, 3, 3).

    Two input layouts, fixed at construction:
    - "pairs": the 3x3 blocks of the node pairs a < b, component-major (P, 3, 3, E) (one-point
      elements), summed by ``np.bincount``. The diagonal blocks are not assembled: each is set to minus
      the sum of the other blocks of its block row. That is exact for matrices whose block rows sum to
      zero, as every stiffness (and Gram) matrix of shape-function gradients does (the gradients of a
      partition of unity sum to zero: translations cost no energy), and it saves 4 of tet4's 10 pairs;
    - "matrices": whole element matrices (E, 3k, 3k) (interleaved dofs), of which the pairs a <= b are
      picked and summed by one product with a 0/1 summation matrix (CSR, a row per upper entry): its
      gathers run along the element matrices' rows, measured 1.5-2x faster than a gather and a bincount.
      Their diagonal pairs are computed anyway, so they are summed rather than rebuilt from the rows. (With
      numba, softbody.kernels.warped_gram adds each pair's blocks through ``blocks`` element by element instead,
      and the summation matrix is never made.)
    """

    pattern: BlockPattern
    layout: str
    pairs: np.ndarray  # (P, 2) local nodes a < b ("pairs") or a <= b ("matrices")
    scatter: np.ndarray | None  # target in (n_upper, 9).ravel() of each pair's block entries (P 3 3 E,); made at first
    # use (pair_scatter: numpy's paths)
    summation: sp.csr_matrix | None  # "matrices": (9 n_upper, E (3k)^2), made at first use (_summation)
    n_upper: int
    upper: np.ndarray  # (nnzb,) bool: block (A, B) with A <= B
    diag: np.ndarray  # (N,) upper-block number of each node's diagonal block
    row_col_sums: sp.csr_matrix | None  # "pairs": (2N, n_upper) 0/1, sums of the upper blocks per block row / column
    sources: tuple[np.ndarray, np.ndarray]  # (nnzb,) the upper block each block copies, and (nnzb,) bool: transposed
    blocks: np.ndarray  # (E, P) each pair's block offset 9 * block in (n_upper, 9).ravel(), -offset - 1 if transposed

    @classmethod
    def from_elements(cls, pattern: BlockPattern, elements: np.ndarray, layout: str) -> "UpperAssembly":
        if layout not in ("pairs", "matrices"):
            raise ValueError(f"layout must be 'pairs' or 'matrices', got {layout!r}")
        E, k = elements.shape
        N = pattern.n_nodes
        pairs = np.stack(np.triu_indices(k, 1 if layout == "pairs" else 0), axis=1)
        upper = pattern.block_row <= pattern.indices
        n_upper = int(upper.sum())
        ub = np.cumsum(upper) - 1  # upper-block number of each upper block
        a, b = elements[:, pairs[:, 0]].T, elements[:, pairs[:, 1]].T  # (P, E)
        swap = a > b
        key = np.where(swap, b, a).astype(np.int64) * N + np.where(swap, a, b)
        blk = ub[np.searchsorted(pattern.block_row * N + pattern.indices, key)]  # (P, E)
        itype = np.int32 if 9 * max(n_upper, k * k * E) < 2**31 else np.int64
        # each pair's block offset 9 * block in (n_upper, 9).ravel(), element-major (E, P); a swapped pair (its
        # global nodes the other way: the block transposed) as -(offset) - 1 (pair_scatter expands it entry by entry)
        blocks = 9 * blk.astype(itype)
        blocks = np.ascontiguousarray(np.where(swap, -blocks - 1, blocks).T)
        del blk, swap, key, a, b
        sums = None
        if layout == "pairs":
            rows, cols = pattern.block_row[upper], pattern.indices[upper]
            sums = sp.csr_matrix((np.ones(2 * n_upper), (np.r_[rows, N + cols], np.tile(np.arange(n_upper), 2))),
                                 shape=(2 * N, n_upper))
        # each block's upper block (its mirror's for a lower one, read transposed)
        sources = (ub[np.where(upper, np.arange(pattern.nnzb), pattern.mirror)].astype(itype), ~upper)
        return cls(pattern, layout, pairs, None, None, n_upper, upper, ub[pattern.diag], sums, sources, blocks)

    def assemble(self, contributions: np.ndarray) -> np.ndarray:
        """Upper block data (n_upper, 9) from pair blocks (P, 3, 3, E) ("pairs") or element matrices
        (E, 3k, 3k) ("matrices")."""
        w = contributions.reshape(-1)
        if self.layout == "matrices":
            return (self._summation() @ w).reshape(-1, 9)
        return self.with_diagonal(np.bincount(self.pair_scatter(), weights=w, minlength=9 * self.n_upper).reshape(-1, 9))

    def _summation(self) -> sp.csr_matrix:
        """"matrices" layout: the 0/1 summation matrix (9 n_upper, E (3k)^2), a row per upper entry, made at first
        use (the compiled pass, kernels.warped_gram, sums through ``blocks`` instead): entry (e, 3 a + i, 3 b + j) of
        the element matrices, the CSR built directly, rows sorted."""
        if self.summation is None:
            scatter = self.pair_scatter()
            E, k = scatter.size // (9 * len(self.pairs)), int(self.pairs.max()) + 1
            i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
            itype = scatter.dtype
            pairs = self.pairs
            within = ((3 * pairs[:, 0, None, None] + i) * 3 * k + 3 * pairs[:, 1, None, None] + j).astype(itype)
            order = np.argsort(scatter, kind="stable")
            cols = (within.reshape(-1, 1) + (9 * k * k) * np.arange(E, dtype=itype)).reshape(-1)[order]
            indptr = np.zeros(9 * self.n_upper + 1, dtype=itype)
            np.cumsum(np.bincount(scatter, minlength=9 * self.n_upper), out=indptr[1:])
            self.summation = sp.csr_matrix((np.ones(len(cols)), cols, indptr), shape=(9 * self.n_upper, 9 * k * k * E))
        return self.summation

    def with_diagonal(self, U: np.ndarray) -> np.ndarray:
        """U (n_upper, 9) with its diagonal blocks (still zero) set: minus the sums of the other blocks of their
        row, the blocks right of it in the upper data and the transposes of those above it ("pairs")."""
        N = self.pattern.n_nodes
        if kernels.ENABLED:  # the same sums block by block (softbody.kernels)
            if "_upper_rows" not in self.__dict__:  # the upper blocks' row and column nodes, made once
                self._upper_rows = (self.pattern.block_row[self.upper], self.pattern.indices[self.upper])
            kernels.diagonal_from_rows(U, *self._upper_rows, self.diag, np.empty((2 * N, 9)))
            return U
        s = self.row_col_sums @ U
        U[self.diag] = -(s[:N] + s[N:, [0, 3, 6, 1, 4, 7, 2, 5, 8]])
        return U

    def element_scatter(self) -> np.ndarray:
        """Each element pair's block (E, P), element-major: its offset 9 * block in (n_upper, 9).ravel(), or
        -offset - 1 where the pair's global nodes run the other way (its 3x3 block added transposed): for a pass over
        the elements (softbody.kernels.warped_pairs, warped_gram), one integer a pair (9 entries' targets took 9x
        the memory: 67 MB at 330k tet4 elements)."""
        return self.blocks

    def pair_scatter(self) -> np.ndarray:
        """The scatter pair-major (P 3 3 E,): the target in (n_upper, 9).ravel() of each contribution (p, i, j, e)
        (numpy's paths; made at first use from ``blocks`` and kept)."""
        if self.scatter is None:
            b = self.blocks.T  # (P, E)
            swap = b < 0
            base = np.where(swap, -b - 1, b)
            i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
            target = base[:, None, None, :] + (3 * i + j).astype(b.dtype)[None, :, :, None]
            target += np.where(swap[:, None, None, :], (2 * (j - i)).astype(b.dtype)[None, :, :, None], b.dtype.type(0))
            self.scatter = target.reshape(-1)  # 3j+i where transposed
        return self.scatter

    def full_sources(self) -> tuple[np.ndarray, np.ndarray]:
        """What ``full`` copies block by block: the upper block (nnzb,) of each block, and whether transposed (nnzb,)
        (for softbody.kernels.system_blocks)."""
        return self.sources

    def full(self, upper: np.ndarray) -> np.ndarray:
        """Block data (nnzb, 3, 3) of the symmetric matrix with upper block data ``upper`` (n_upper, 9)."""
        source, transposed = self.sources
        out = upper.reshape(-1, 3, 3)[source]
        out[transposed] = out[transposed].transpose(0, 2, 1)
        return out
