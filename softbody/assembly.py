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
    ``diag`` (N,) is the block index of each node's diagonal block. ``scatter_dof`` (E*3k*3k,) maps the
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
        return cls(n_nodes, indptr, bcol.astype(np.int64), scatter, scatter_dof, diag, brow.astype(np.int64),
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

    def matvec(self, block_data: np.ndarray, x: np.ndarray) -> np.ndarray:
        """y = A x for A given by block data and x (N, 3); returns (N, 3)."""
        contrib = np.einsum("bij,bj->bi", block_data, x[self.indices])
        y = np.zeros((self.n_nodes, 3))
        for c in range(3):
            y[:, c] = np.bincount(self.block_row, weights=contrib[:, c], minlength=self.n_nodes)
        return y
