"""Sparse Cholesky factorisation of small SPD matrices in 3x3 node blocks, compiled (numba).

PARDISO (softbody.linsolve) is the solver for meshes of any size, but on a mesh of a few hundred unknowns its
cost is mostly per call (about 0.13 ms to factorise the 225 unknowns of the 75-node sheet, whose factor takes
2.7e3 block products, 7e4 multiply-adds; this factorisation takes 35 us), and the other libraries measured do no
better there (qdldl 0.24 ms). Our matrices come
in 3x3 blocks, one per pair of nodes, so a left-looking Cholesky over the node graph works on dense 3x3
blocks: one indexed access per nine multiply-adds, no supernode detection, the whole factorisation in one
compiled call. softbody.linsolve uses it (backend "blocks") for systems whose factor is small
(``SMALL_FACTOR``); PARDISO keeps the rest.

The pieces: :func:`minimum_degree` orders the node graph (an exact elimination graph: fine for the few
hundred nodes this path serves), :class:`BlockSymbolic` holds the factor's block pattern and where each
scalar entry of the matrix's upper triangle lands in it, :func:`factorize_blocks` and :func:`solve_blocks` (:func:`solve_block` for one right-hand side)
are the numeric kernels.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from . import compilation
from .kernels import AVAILABLE, _jit

# factor size (BlockSymbolic.multiply_adds: block products, 27 multiply-adds each) up to which the compiled factorisation beats
# PARDISO's on this machine: factorise and solve 42 against 158 us at 2.7e3 (the 75-node sheet), 676 against
# 813 us at 7.0e4 (the 324-node sheet), even at 1.4e5, behind beyond (2.6 against 2.4 ms at 2.9e5)
SMALL_FACTOR = 100_000


def minimum_degree(neighbours: list[set[int]]) -> np.ndarray:
    """A fill-reducing elimination order (N,) of a graph given as neighbour sets: repeatedly the node of least
    degree in the elimination graph (ties to the lowest index, so the order is reproducible)."""
    adj = [set(a) for a in neighbours]
    for i, a in enumerate(adj):
        a.discard(i)
    alive = set(range(len(adj)))
    order = []
    while alive:
        v = min(alive, key=lambda i: (len(adj[i]), i))
        order.append(v)
        nb = adj[v]
        for a in nb:
            adj[a] |= nb
            adj[a].discard(a)
            adj[a].discard(v)
        alive.discard(v)
    return np.array(order, dtype=np.int64)


@dataclass
class BlockSymbolic:
    """The block pattern of L for a 3N x 3N matrix with a 3x3 block structure, after ordering.

    perm (N,): new -> old node; col_ptr (N+1,), row (nnzb,): L's block rows by column, the diagonal first, the
    others ascending; row_ptr (N+1,), row_col (nnzb - N,), row_pos: for each block row j, the columns k < j
    with L_jk != 0 and the position of L_jk; dest, mirror (nnz_up,): where each upper-triangle scalar entry
    of the matrix goes in the flattened blocks (nnzb * 9), and its mirror in a diagonal block (-1: none)."""

    n: int
    perm: np.ndarray
    col_ptr: np.ndarray
    row: np.ndarray
    row_ptr: np.ndarray
    row_col: np.ndarray
    row_pos: np.ndarray
    dest: np.ndarray
    mirror: np.ndarray

    @property
    def multiply_adds(self) -> int:
        """Block products of the factorisation (each 27 multiply-adds): sum over columns of count^2 / 2."""
        counts = np.diff(self.col_ptr)
        return int((counts * (counts - 1) // 2).sum())

    @classmethod
    def of(cls, indptr: np.ndarray, indices: np.ndarray, n: int) -> "BlockSymbolic":
        """From the upper triangle's CSR pattern (indptr (n+1,), indices) of an n x n matrix, n = 3N."""
        if n % 3:
            raise ValueError(f"block Cholesky needs 3x3 node blocks, got n = {n} (not a multiple of 3)")
        N = n // 3
        indptr, indices = np.asarray(indptr, dtype=np.int64), np.asarray(indices, dtype=np.int64)
        r = np.repeat(np.arange(n), np.diff(indptr))
        I, J = r // 3, indices // 3
        neighbours = [set() for _ in range(N)]
        for a, b in set(zip(I.tolist(), J.tolist())):
            if a != b:
                neighbours[a].add(b)
                neighbours[b].add(a)
        perm = minimum_degree(neighbours)
        iperm = np.empty(N, dtype=np.int64)
        iperm[perm] = np.arange(N)
        # the factor's pattern: column j's rows are its neighbours after j, merged into its parent's
        cols = [set() for _ in range(N)]
        for i in range(N):
            for k in neighbours[i]:
                a, b = int(iperm[i]), int(iperm[k])
                if a > b:
                    cols[b].add(a)
        for j in range(N):
            if cols[j]:
                parent = min(cols[j])
                cols[parent] |= cols[j] - {parent}
        rows = [[j] + sorted(c) for j, c in enumerate(cols)]
        col_ptr = np.zeros(N + 1, dtype=np.int64)
        col_ptr[1:] = np.cumsum([len(x) for x in rows])
        row = np.array([i for x in rows for i in x], dtype=np.int64)
        # row structure: for each j, the (k, position of L_jk) with k < j
        by_row: list[list[tuple[int, int]]] = [[] for _ in range(N)]
        for k in range(N):
            for p in range(col_ptr[k] + 1, col_ptr[k + 1]):
                by_row[row[p]].append((k, p))
        row_ptr = np.zeros(N + 1, dtype=np.int64)
        row_ptr[1:] = np.cumsum([len(x) for x in by_row])
        row_col = np.array([k for x in by_row for k, _ in x], dtype=np.int64)
        row_pos = np.array([p for x in by_row for _, p in x], dtype=np.int64)
        # where each scalar entry (r, c), r <= c, lands: block (max, min) of the new indices, transposed if needed
        position = {(int(row[p]), j): p for j in range(N) for p in range(col_ptr[j], col_ptr[j + 1])}
        pI, pJ, a, b = iperm[I], iperm[J], r % 3, indices % 3
        lower = pI >= pJ
        bi, bj = np.where(lower, pI, pJ), np.where(lower, pJ, pI)
        ea, eb = np.where(lower, a, b), np.where(lower, b, a)
        pos = np.array([position[(int(x), int(y))] for x, y in zip(bi, bj)], dtype=np.int64)
        dest = 9 * pos + 3 * ea + eb
        mirror = np.where((pI == pJ) & (a != b), 9 * pos + 3 * eb + ea, -1)
        return cls(n, perm, col_ptr, row, row_ptr, row_col, row_pos, dest, mirror)


@_jit
def factorize_blocks(data: np.ndarray, dest: np.ndarray, mirror: np.ndarray, col_ptr: np.ndarray, row: np.ndarray,
                     row_ptr: np.ndarray, row_col: np.ndarray, row_pos: np.ndarray, L: np.ndarray,
                     where: np.ndarray) -> int:
    """Left-looking block Cholesky: the matrix's upper-triangle values ``data`` scattered into L (nnzb, 3, 3)
    (dest, mirror), then L overwritten with the factor (diagonal blocks lower triangular). where (N,): scratch.
    Returns -1, or the first block column whose pivot is not positive (the matrix is not positive definite)."""
    N = len(col_ptr) - 1
    flat = L.reshape(-1)
    flat[:] = 0.0
    for e in range(len(data)):
        flat[dest[e]] = data[e]
        if mirror[e] >= 0:
            flat[mirror[e]] = data[e]
    for j in range(N):
        for p in range(col_ptr[j], col_ptr[j + 1]):
            where[row[p]] = p
        for q in range(row_ptr[j], row_ptr[j + 1]):
            k, pj = row_col[q], row_pos[q]
            b00, b01, b02 = L[pj, 0, 0], L[pj, 0, 1], L[pj, 0, 2]
            b10, b11, b12 = L[pj, 1, 0], L[pj, 1, 1], L[pj, 1, 2]
            b20, b21, b22 = L[pj, 2, 0], L[pj, 2, 1], L[pj, 2, 2]
            for p in range(pj, col_ptr[k + 1]):  # rows i >= j of column k: L_ij -= L_ik L_jk^T
                t = where[row[p]]
                for a in range(3):
                    x0, x1, x2 = L[p, a, 0], L[p, a, 1], L[p, a, 2]
                    L[t, a, 0] -= x0 * b00 + x1 * b01 + x2 * b02
                    L[t, a, 1] -= x0 * b10 + x1 * b11 + x2 * b12
                    L[t, a, 2] -= x0 * b20 + x1 * b21 + x2 * b22
        d = col_ptr[j]  # the diagonal block: its lower triangle's Cholesky factor c
        s00 = L[d, 0, 0]
        if not s00 > 0.0:
            return j
        c00 = np.sqrt(s00)
        c10, c20 = L[d, 1, 0] / c00, L[d, 2, 0] / c00
        s11 = L[d, 1, 1] - c10 * c10
        if not s11 > 0.0:
            return j
        c11 = np.sqrt(s11)
        c21 = (L[d, 2, 1] - c20 * c10) / c11
        s22 = L[d, 2, 2] - c20 * c20 - c21 * c21
        if not s22 > 0.0:
            return j
        c22 = np.sqrt(s22)
        L[d, 0, 0], L[d, 0, 1], L[d, 0, 2] = c00, 0.0, 0.0
        L[d, 1, 0], L[d, 1, 1], L[d, 1, 2] = c10, c11, 0.0
        L[d, 2, 0], L[d, 2, 1], L[d, 2, 2] = c20, c21, c22
        for p in range(d + 1, col_ptr[j + 1]):  # L_ij = S_ij c^-T: each row x solves c x^T = s^T
            for a in range(3):
                x0 = L[p, a, 0] / c00
                x1 = (L[p, a, 1] - c10 * x0) / c11
                x2 = (L[p, a, 2] - c20 * x0 - c21 * x1) / c22
                L[p, a, 0], L[p, a, 1], L[p, a, 2] = x0, x1, x2
    return -1


@_jit
def solve_blocks(L: np.ndarray, col_ptr: np.ndarray, row: np.ndarray, perm: np.ndarray, b: np.ndarray,
                 x: np.ndarray) -> None:
    """x = A^-1 b for the factor L of :func:`factorize_blocks`; b, x (N, 3, m): m right-hand sides, the loops over
    them innermost (along memory)."""
    N, m = len(col_ptr) - 1, b.shape[2]
    y = np.empty((N, 3, m))
    for j in range(N):
        y[j] = b[perm[j]]
    for j in range(N):  # forward: L y = b, by columns
        d = col_ptr[j]
        c00, c10, c11, c20, c21, c22 = L[d, 0, 0], L[d, 1, 0], L[d, 1, 1], L[d, 2, 0], L[d, 2, 1], L[d, 2, 2]
        for c in range(m):
            y0 = y[j, 0, c] / c00
            y1 = (y[j, 1, c] - c10 * y0) / c11
            y[j, 0, c], y[j, 1, c], y[j, 2, c] = y0, y1, (y[j, 2, c] - c20 * y0 - c21 * y1) / c22
        for p in range(d + 1, col_ptr[j + 1]):
            i = row[p]
            for a in range(3):
                l0, l1, l2 = L[p, a, 0], L[p, a, 1], L[p, a, 2]
                for c in range(m):
                    y[i, a, c] -= l0 * y[j, 0, c] + l1 * y[j, 1, c] + l2 * y[j, 2, c]
    for j in range(N - 1, -1, -1):  # backward: L^T x = y
        d = col_ptr[j]
        for p in range(d + 1, col_ptr[j + 1]):
            i = row[p]
            for a in range(3):
                l0, l1, l2 = L[p, 0, a], L[p, 1, a], L[p, 2, a]
                for c in range(m):
                    y[j, a, c] -= l0 * y[i, 0, c] + l1 * y[i, 1, c] + l2 * y[i, 2, c]
        c00, c10, c11, c20, c21, c22 = L[d, 0, 0], L[d, 1, 0], L[d, 1, 1], L[d, 2, 0], L[d, 2, 1], L[d, 2, 2]
        for c in range(m):
            x2 = y[j, 2, c] / c22
            x1 = (y[j, 1, c] - c21 * x2) / c11
            y[j, 0, c], y[j, 1, c], y[j, 2, c] = (y[j, 0, c] - c10 * x1 - c20 * x2) / c00, x1, x2
    for j in range(N):
        x[perm[j]] = y[j]


@_jit
def solve_block(L: np.ndarray, col_ptr: np.ndarray, row: np.ndarray, perm: np.ndarray, b: np.ndarray,
                x: np.ndarray) -> None:
    """:func:`solve_blocks` for one right-hand side b, x (N, 3) (without the loops over right-hand sides: half the
    time at one)."""
    N = len(col_ptr) - 1
    y = np.empty((N, 3))
    for j in range(N):
        y[j, 0], y[j, 1], y[j, 2] = b[perm[j], 0], b[perm[j], 1], b[perm[j], 2]
    for j in range(N):  # forward: L y = b, by columns
        d = col_ptr[j]
        y0 = y[j, 0] / L[d, 0, 0]
        y1 = (y[j, 1] - L[d, 1, 0] * y0) / L[d, 1, 1]
        y2 = (y[j, 2] - L[d, 2, 0] * y0 - L[d, 2, 1] * y1) / L[d, 2, 2]
        y[j, 0], y[j, 1], y[j, 2] = y0, y1, y2
        for p in range(d + 1, col_ptr[j + 1]):
            i = row[p]
            for a in range(3):
                y[i, a] -= L[p, a, 0] * y0 + L[p, a, 1] * y1 + L[p, a, 2] * y2
    for j in range(N - 1, -1, -1):  # backward: L^T x = y
        d = col_ptr[j]
        s0, s1, s2 = y[j, 0], y[j, 1], y[j, 2]
        for p in range(d + 1, col_ptr[j + 1]):
            i = row[p]
            z0, z1, z2 = y[i, 0], y[i, 1], y[i, 2]
            s0 -= L[p, 0, 0] * z0 + L[p, 1, 0] * z1 + L[p, 2, 0] * z2
            s1 -= L[p, 0, 1] * z0 + L[p, 1, 1] * z1 + L[p, 2, 1] * z2
            s2 -= L[p, 0, 2] * z0 + L[p, 1, 2] * z1 + L[p, 2, 2] * z2
        x2 = s2 / L[d, 2, 2]
        x1 = (s1 - L[d, 2, 1] * x2) / L[d, 1, 1]
        x0 = (s0 - L[d, 1, 0] * x1 - L[d, 2, 0] * x2) / L[d, 0, 0]
        y[j, 0], y[j, 1], y[j, 2] = x0, x1, x2
    for j in range(N):
        x[perm[j], 0], x[perm[j], 1], x[perm[j], 2] = y[j, 0], y[j, 1], y[j, 2]


ENABLED = compilation.register(sys.modules[__name__], AVAILABLE)
