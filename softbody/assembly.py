"""Sparse assembly with a fixed pattern: 3x3 node blocks, a precomputed scatter map from element
blocks into the block data, and a precomputed gather into the upper-triangular scalar CSR that the
Cholesky solver factorises. Everything here is built once per mesh; per step only data arrays move.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass
class BlockPattern:
    """Node-level sparsity pattern of a mesh's 3N x 3N matrices.

    n_nodes: N. Blocks are stored in block-CSR order: ``indptr`` (N+1,), ``indices`` (nnzb,).
    ``scatter`` (E, k, k) maps element block (a, b) of element e to its global block index.
    ``diag`` (N,) is the block index of each node's diagonal block; ``mirror`` (nnzb,) the index of the
    block (B, A) for block (A, B). ``scatter_dof`` (E*3k*3k,) maps the
    entries of element matrices in their natural (E, 3k, 3k) layout to ``block_data.reshape(-1)``.
    Upper CSR (for the solver): ``up_indptr``, ``up_indices`` and ``up_gather`` (nnz_up,), the index of
    each upper-triangular scalar entry in ``block_data.reshape(-1)`` (blocks flattened row-major 3x3).
    ``up_row``/``up_col`` give each scalar entry's dof, ``up_diag`` (3N,) the position of each diagonal entry.
    """

    n_nodes: int
    indptr: np.ndarray
    indices: np.ndarray
    scatter: np.ndarray
    scatter_dof: np.ndarray
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
        rows = np.repeat(elements, k, axis=1).ravel()
        cols = np.tile(elements, (1, k)).ravel()
        # every node gets a diagonal block, so that unused nodes can be constrained
        rows = np.concatenate([rows, np.arange(n_nodes)])
        cols = np.concatenate([cols, np.arange(n_nodes)])
        key = rows.astype(np.int64) * n_nodes + cols
        ukey, inv = np.unique(key, return_inverse=True)
        brow, bcol = ukey // n_nodes, ukey % n_nodes
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.add.at(indptr, brow + 1, 1)
        indptr = np.cumsum(indptr)
        scatter = inv[: E * k * k].reshape(E, k, k)
        diag = inv[E * k * k:]
        # scalar entry (e, 3a+i, 3b+j) -> 9 * block(e, a, b) + 3 i + j
        sd = 9 * scatter[:, :, None, :, None] + (3 * np.arange(3))[None, None, :, None, None] \
            + np.arange(3)[None, None, None, None, :]
        scatter_dof = sd.reshape(-1)
        # scalar entries of every block, row-major within the 3x3 block
        nnzb = len(ukey)
        a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        srow = (3 * brow[:, None] + a.ravel()[None]).ravel()
        scol = (3 * bcol[:, None] + b.ravel()[None]).ravel()
        flat = np.arange(nnzb * 9)
        up = scol >= srow
        srow, scol, flat = srow[up], scol[up], flat[up]
        order = np.lexsort((scol, srow))
        srow, scol, flat = srow[order], scol[order], flat[order]
        up_indptr = np.zeros(3 * n_nodes + 1, dtype=np.int64)
        np.add.at(up_indptr, srow + 1, 1)
        up_indptr = np.cumsum(up_indptr)
        up_diag = np.flatnonzero(srow == scol)
        mirror = np.searchsorted(ukey, bcol * n_nodes + brow)
        return cls(n_nodes, indptr, bcol.astype(np.int64), scatter, scatter_dof, diag, mirror, brow.astype(np.int64),
                   up_indptr, scol.astype(np.int64), flat, srow, scol, up_diag)

    def assemble(self, element_matrices: np.ndarray) -> np.ndarray:
        """Sum element matrices (E, 3k, 3k) (interleaved dofs) into block data (nnzb, 3, 3)."""
        return np.bincount(self.scatter_dof, weights=element_matrices.reshape(-1),
                           minlength=9 * self.nnzb).reshape(-1, 3, 3)

    def assemble_scalar(self, element_values: np.ndarray) -> np.ndarray:
        """Sum scalar element blocks (E, k, k) (a multiple of I3 per block) into (nnzb,)."""
        return np.bincount(self.scatter.ravel(), weights=element_values.ravel(), minlength=self.nnzb)

    def to_bsr(self, block_data: np.ndarray) -> sp.bsr_matrix:
        n = 3 * self.n_nodes
        return sp.bsr_matrix((block_data, self.indices, self.indptr), shape=(n, n))

    def to_csr(self, block_data: np.ndarray) -> sp.csr_matrix:
        return self.to_bsr(block_data).tocsr()

    def upper_data(self, block_data: np.ndarray) -> np.ndarray:
        """Values (nnz_up,) of the upper triangle in the order of ``up_indptr``/``up_indices``."""
        return block_data.reshape(-1)[self.up_gather]


@dataclass
class PairAssembly:
    """Assembly of symmetric element matrices given by the 3x3 blocks of their node pairs a <= b.

    Blocks arrive component-major, (P, 3, 3, E) for the P pairs of E elements, and are summed into
    the upper blocks of the pattern (row <= column; a pair whose nodes run the other way goes in
    transposed). ``full`` then mirrors them into the lower blocks. Half the work of whole matrices.
    """

    pattern: BlockPattern
    pairs: np.ndarray  # (P, 2) local nodes a <= b
    scatter: np.ndarray  # (P * 9 * E,) upper-block entry of each (p, i, j, e)
    n_upper: int
    full_from_upper: np.ndarray  # (9 nnzb,) entry of the upper data that each block entry copies

    @classmethod
    def from_elements(cls, pattern: BlockPattern, elements: np.ndarray) -> "PairAssembly":
        E, k = elements.shape
        N = pattern.n_nodes
        pairs = np.stack(np.triu_indices(k), axis=1)
        upper = pattern.block_row <= pattern.indices
        ub = np.cumsum(upper) - 1  # upper-block number of each upper block
        a, b = elements[:, pairs[:, 0]].T, elements[:, pairs[:, 1]].T  # (P, E)
        swap = a > b
        key = np.where(swap, b, a).astype(np.int64) * N + np.where(swap, a, b)
        blk = ub[np.searchsorted(pattern.block_row * N + pattern.indices, key)]
        i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        entry = np.where(swap[:, None, None, :], (3 * j + i)[None, :, :, None], (3 * i + j)[None, :, :, None])
        scatter = (9 * blk[:, None, None, :] + entry).reshape(-1)
        src = np.where(upper, np.arange(pattern.nnzb), pattern.mirror)
        entry = np.where(upper[:, None, None], (3 * i + j)[None], (3 * j + i)[None])
        full_from_upper = (9 * ub[src][:, None, None] + entry).reshape(-1)
        return cls(pattern, pairs, scatter, int(upper.sum()), full_from_upper)

    def assemble(self, blocks: np.ndarray) -> np.ndarray:
        """Upper block data (n_upper, 3, 3) from pair blocks (P, 3, 3, E)."""
        return np.bincount(self.scatter, weights=blocks.reshape(-1), minlength=9 * self.n_upper).reshape(-1, 3, 3)

    def full(self, upper: np.ndarray) -> np.ndarray:
        """Block data (nnzb, 3, 3) of the symmetric matrix with upper block data ``upper``."""
        return upper.reshape(-1)[self.full_from_upper].reshape(-1, 3, 3)
