"""Compiled kernels (numba) for the per-element work that numpy cannot batch without dozens of calls.

On a small mesh a step's numpy work is dominated by the cost of each call (1-5 us), not by the arithmetic:
the polar decomposition of the warping rotations, for instance, is about fifty numpy calls per Newton
iteration whatever the number of elements. These kernels do the same arithmetic in one compiled loop.
They are compiled once and cached on disk (numba's ``cache=True``, next to this file in ``__pycache__``); a
first run after an install compiles them in a background process while the numpy code runs
(softbody.compilation).

Every kernel has a numpy reference in the module that uses it; the tests compare the two.
``AVAILABLE`` is False when numba is missing or ``SOFTBODY_NO_NUMBA=1`` is set; ``ENABLED`` (read at each call
site) is whether the kernels run now: AVAILABLE, and in background mode the cache warm (softbody.compilation).
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np

from . import compilation as _compilation

try:  # a dependency (pyproject.toml); the numpy paths remain for environments without it
    import numba
except ImportError:  # pragma: no cover - numba is installed with the package
    numba = None

AVAILABLE = numba is not None and os.environ.get("SOFTBODY_NO_NUMBA", "") not in ("1", "true", "yes")
ENABLED = AVAILABLE  # decided at the end of this module (softbody.compilation.register)
_NO_FLAGS = np.zeros(0, dtype=np.bool_)  # _row_product's flags when every block counts


def _jit(f):
    """numba.njit with the kernels' options (also for integration/kernels.py). numba's disk cache is invalidated by a
    change of the module file that holds a kernel, not of these options: after changing them, delete the
    ``kernels.*.nbi``/``.nbc`` files and the ``*.softbody-warm`` stamps (softbody.compilation) in softbody/__pycache__
    and integration/__pycache__."""
    # error_model "numpy": a division by zero gives inf or NaN, as in the numpy code the kernels mirror, not an error
    return numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")(f) if AVAILABLE else f


def _inline(f):
    """numba.njit with the kernels' options, inlined into its callers in numba's own IR (``inline="always"``): a
    small helper shared by kernels, whose constant arguments then fold away as if written out in each."""
    return numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy", inline="always")(f) if AVAILABLE else f


@_jit
def polar_newton(F9: np.ndarray, tol: float, max_iter: int, R9: np.ndarray, ok: np.ndarray) -> None:
    """Rotation factors of F (component-major (9, n), row 3 i + j: F_ij) by the scaled Newton iteration
    R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3), into R9 (9, n); ok (n,) False where det F is not clearly
    positive (inverted or degenerate: the caller uses SVD) or the iteration did not converge. The same
    iteration and stopping rule as softbody.rotation._newton_rotation, element by element."""
    n = F9.shape[1]
    step_tol = math.sqrt(tol)
    for e in range(n):  # the nine entries in scalars (registers), row-major: a_3i+j = F_ij
        a0, a1, a2, a3, a4, a5, a6, a7, a8 = (F9[0, e], F9[1, e], F9[2, e], F9[3, e], F9[4, e], F9[5, e], F9[6, e],
                                              F9[7, e], F9[8, e])
        scale = max(abs(a0), abs(a1), abs(a2), abs(a3), abs(a4), abs(a5), abs(a6), abs(a7), abs(a8))
        det = a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6)
        if not det > 1e-6 * scale * scale * scale:
            ok[e] = False
            for k in range(9):
                R9[k, e] = 0.0
            continue
        converged = False
        for it in range(max_iter):
            # cofactors: c_ij = A_(i+1)(j+1) A_(i+2)(j+2) - A_(i+1)(j+2) A_(i+2)(j+1), indices mod 3
            c0, c1, c2 = a4 * a8 - a5 * a7, a5 * a6 - a3 * a8, a3 * a7 - a4 * a6
            c3, c4, c5 = a7 * a2 - a8 * a1, a8 * a0 - a6 * a2, a6 * a1 - a7 * a0
            c6, c7, c8 = a1 * a5 - a2 * a4, a2 * a3 - a0 * a5, a0 * a4 - a1 * a3
            d = a0 * c0 + a1 * c1 + a2 * c2
            g = 1.0 / np.cbrt(abs(d))
            gi = 0.5 / (g * d)
            g *= 0.5
            n0, n1, n2 = g * a0 + gi * c0, g * a1 + gi * c1, g * a2 + gi * c2
            n3, n4, n5 = g * a3 + gi * c3, g * a4 + gi * c4, g * a5 + gi * c5
            n6, n7, n8 = g * a6 + gi * c6, g * a7 + gi * c7, g * a8 + gi * c8
            err = max(abs(n0 - a0), abs(n1 - a1), abs(n2 - a2), abs(n3 - a3), abs(n4 - a4), abs(n5 - a5),
                      abs(n6 - a6), abs(n7 - a7), abs(n8 - a8))
            a0, a1, a2, a3, a4, a5, a6, a7, a8 = n0, n1, n2, n3, n4, n5, n6, n7, n8
            if (it >= 2 or it == max_iter - 1) and err < step_tol:
                converged = True
                break
        ok[e] = converged
        R9[0, e], R9[1, e], R9[2, e], R9[3, e], R9[4, e] = a0, a1, a2, a3, a4
        R9[5, e], R9[6, e], R9[7, e], R9[8, e] = a5, a6, a7, a8


@_jit
def warped_pairs(R9: np.ndarray, G: np.ndarray, P: np.ndarray, elements: np.ndarray, pairs: np.ndarray,
                 target: np.ndarray, out: np.ndarray, loads: np.ndarray) -> None:
    """One pass over the elements of a one-point mesh (tet4): the rotated gradients g_a = R_e G_ea (R component-major
    (9, E), G (E, k, 3)), their pair blocks g_a g_b^T for the node pairs (P, 2) added into out at the pair's block
    (out flat, target (E, P): UpperAssembly.element_scatter, the block's offset, or -offset - 1 for the block
    transposed), and the warped rest loads R_e P_ea (P (E, k, 3))
    added into loads (N, 3) at the element's nodes (E, k). The sums of FemBody.warped_stiffness_upper's numpy path
    (a sparse product, a bincount and another sparse product), element by element: equal to round-off."""
    E, k = elements.shape
    g = np.empty((k, 3))
    for e in range(E):
        for a in range(k):
            node = elements[e, a]
            for i in range(3):
                s = 0.0
                t = 0.0
                for j in range(3):
                    r = R9[3 * i + j, e]
                    s += r * G[e, a, j]
                    t += r * P[e, a, j]
                g[a, i] = s
                loads[node, i] += t
        for p in range(pairs.shape[0]):
            a, b = pairs[p, 0], pairs[p, 1]
            t = target[e, p]
            if t >= 0:
                for i in range(3):
                    for j in range(3):
                        out[t + 3 * i + j] += g[a, i] * g[b, j]
            else:
                t = -t - 1
                for i in range(3):
                    for j in range(3):
                        out[t + 3 * j + i] += g[a, i] * g[b, j]


@_jit
def warped_gram(R9: np.ndarray, G: np.ndarray, P: np.ndarray, elements: np.ndarray, pairs: np.ndarray,
                target: np.ndarray, out: np.ndarray, loads: np.ndarray) -> None:
    """warped_pairs for elements with q quadrature points (tet10, hex8): the rotated weighted gradients
    g_qa = R_e G_eqa (G (E, q, k, 3)), the Gram blocks sum_q g_qa g_qb^T of the node pairs a <= b (P, 2) added into
    out at the pair's block (UpperAssembly.element_scatter of the "matrices" layout), and the warped rest loads
    R_e P_ea (P (E, k, 3)) into loads (N, 3). FemBody.warped_stiffness_upper's batched Gram matrices, their
    summation product and the rest loads' sparse product, element by element: equal to round-off."""
    E, q, k = G.shape[0], G.shape[1], G.shape[2]
    g = np.empty((k, 3, q))  # quadrature points innermost: the pair sums run along memory
    for e in range(E):
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = (R9[0, e], R9[1, e], R9[2, e], R9[3, e], R9[4, e], R9[5, e], R9[6, e],
                                              R9[7, e], R9[8, e])
        for a in range(k):
            for p_ in range(q):
                x0, x1, x2 = G[e, p_, a, 0], G[e, p_, a, 1], G[e, p_, a, 2]
                g[a, 0, p_] = r0 * x0 + r1 * x1 + r2 * x2
                g[a, 1, p_] = r3 * x0 + r4 * x1 + r5 * x2
                g[a, 2, p_] = r6 * x0 + r7 * x1 + r8 * x2
            node = elements[e, a]
            x0, x1, x2 = P[e, a, 0], P[e, a, 1], P[e, a, 2]
            loads[node, 0] += r0 * x0 + r1 * x1 + r2 * x2
            loads[node, 1] += r3 * x0 + r4 * x1 + r5 * x2
            loads[node, 2] += r6 * x0 + r7 * x1 + r8 * x2
        for p in range(pairs.shape[0]):
            a, b = pairs[p, 0], pairs[p, 1]
            t = target[e, p]
            ti, tj = 3, 1  # the entry (i, j) of the pair's block at t + 3 i + j, or transposed at t + 3 j + i
            if t < 0:
                t, ti, tj = -t - 1, 1, 3
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for p_ in range(q):
                        s += g[a, i, p_] * g[b, j, p_]
                    out[t + ti * i + tj * j] += s


@_jit
def node_frames(S9: np.ndarray, Q: np.ndarray, bad: np.ndarray) -> None:
    """Per-node frames Q (N, 3, 3) from the sums S (component-major (9, N)) of the adjacent elements' rotations:
    Gram-Schmidt of S's first two columns a, b, and a x b; bad (N,) True where a or b is shorter than 1e-3 |S|
    (the caller uses the polar factor there). The same arithmetic as FemBody.node_frames's numpy path."""
    for i in range(S9.shape[1]):
        a0, a1, a2 = S9[0, i], S9[3, i], S9[6, i]
        b0, b1, b2 = S9[1, i], S9[4, i], S9[7, i]
        na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        s = na if na > 0 else 1.0
        a0, a1, a2 = a0 / s, a1 / s, a2 / s
        ab = a0 * b0 + a1 * b1 + a2 * b2
        b0, b1, b2 = b0 - ab * a0, b1 - ab * a1, b2 - ab * a2
        nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        s = nb if nb > 0 else 1.0
        b0, b1, b2 = b0 / s, b1 / s, b2 / s
        Q[i, 0, 0], Q[i, 1, 0], Q[i, 2, 0] = a0, a1, a2
        Q[i, 0, 1], Q[i, 1, 1], Q[i, 2, 1] = b0, b1, b2
        Q[i, 0, 2], Q[i, 1, 2], Q[i, 2, 2] = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        norm2 = 0.0
        for k in range(9):
            norm2 += S9[k, i] * S9[k, i]
        scale = 1e-3 * math.sqrt(norm2)
        bad[i] = na <= scale or nb <= scale


@_jit
def isotropic_blocks(S: np.ndarray, lam: float, mu: float, K: np.ndarray) -> None:
    """K = lam S + mu S^T + mu tr(S) I block by block, for blocks S (n, 9) flattened row-major, into K (n, 9): the
    map softbody.warping.isotropic_matrix applies by a matrix product (warping.isotropic_blocks)."""
    for r in range(S.shape[0]):
        tr = S[r, 0] + S[r, 4] + S[r, 8]
        for i in range(3):
            for j in range(3):
                K[r, 3 * i + j] = lam * S[r, 3 * i + j] + mu * S[r, 3 * j + i]
            K[r, 4 * i] += mu * tr


@_jit
def frame_products(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    """A_n B_n^T for stacks of 3x3 matrices A, B (N, 3, 3) into out (N, 3, 3) (numpy's stacked matmul of small
    matrices costs about ten times this)."""
    for n in range(A.shape[0]):
        for i in range(3):
            for j in range(3):
                out[n, i, j] = A[n, i, 0] * B[n, j, 0] + A[n, i, 1] * B[n, j, 1] + A[n, i, 2] * B[n, j, 2]


@_inline
def _gradient(nodes: np.ndarray, g: np.ndarray, e: int, c: int, y: np.ndarray, m0: float, m1: float, m2: float):
    """sum_a (y_a - m) g_a^T over the slots a of element e: nodes (E, k) and gradients g (E, k, >= c + 3), the three
    from column c; y (N, 3), m (3,) subtracted from each y_a. Its nine entries, row-major (H_ij = sum y_a,i g_a,j)."""
    h00 = h01 = h02 = h10 = h11 = h12 = h20 = h21 = h22 = 0.0
    for a in range(nodes.shape[1]):
        n = nodes[e, a]
        y0, y1, y2 = y[n, 0] - m0, y[n, 1] - m1, y[n, 2] - m2
        g0, g1, g2 = g[e, a, c], g[e, a, c + 1], g[e, a, c + 2]
        h00 += y0 * g0
        h01 += y0 * g1
        h02 += y0 * g2
        h10 += y1 * g0
        h11 += y1 * g1
        h12 += y1 * g2
        h20 += y2 * g0
        h21 += y2 * g1
        h22 += y2 * g2
    return h00, h01, h02, h10, h11, h12, h20, h21, h22


@_jit
def warped_product(g: np.ndarray, elements: np.ndarray, lam: float, mu: float, y: np.ndarray, out: np.ndarray) -> None:
    """K' y into out (N, 3), zeroed first, element by element: g (E, k, 3q) the rotated weighted gradients
    (FemBody.rotated_gradients), elements (E, k), y (N, 3). Per quadrature point p the weighted displacement
    gradient H_ij = sum_a y_a,i g_a,3p+j, the isotropic stress sigma = lam tr(H) I + mu (H + H^T) in closed form
    (softbody.warping.stress_map as a matrix), and the forces g_a,3p+j sigma_ji added at the element's nodes: the
    sums of softbody.warping.warped_product, whose batched products of small matrices cost several times this."""
    E, k, q3 = g.shape
    out[:] = 0.0
    for e in range(E):
        for p in range(q3 // 3):
            h00, h01, h02, h10, h11, h12, h20, h21, h22 = _gradient(elements, g, e, 3 * p, y, 0.0, 0.0, 0.0)
            tr = lam * (h00 + h11 + h22)
            s00, s11, s22 = tr + 2.0 * mu * h00, tr + 2.0 * mu * h11, tr + 2.0 * mu * h22
            s01, s02, s12 = mu * (h01 + h10), mu * (h02 + h20), mu * (h12 + h21)
            for a in range(k):
                node = elements[e, a]
                g0, g1, g2 = g[e, a, 3 * p], g[e, a, 3 * p + 1], g[e, a, 3 * p + 2]
                out[node, 0] += g0 * s00 + g1 * s01 + g2 * s02
                out[node, 1] += g0 * s01 + g1 * s11 + g2 * s12
                out[node, 2] += g0 * s02 + g1 * s12 + g2 * s22


@_jit
def warped_diagonal(g: np.ndarray, elements: np.ndarray, lam: float, mu: float, out: np.ndarray) -> None:
    """The diagonal blocks of K' into out (N, 3, 3), zeroed first, element by element: per node slot a and quadrature
    point p, with g_a the rotated weighted gradient there (g (E, k, 3q), FemBody.rotated_gradients), the block
    (lam + mu) g_a g_a^T + mu |g_a|^2 I (warped_product's K' y for y at node a alone): softbody.warping
    .warped_diagonal, node by node."""
    E, k, q3 = g.shape
    out[:] = 0.0
    lm = lam + mu
    for e in range(E):
        for a in range(k):
            node = elements[e, a]
            for p in range(q3 // 3):
                g0, g1, g2 = g[e, a, 3 * p], g[e, a, 3 * p + 1], g[e, a, 3 * p + 2]
                gg = mu * (g0 * g0 + g1 * g1 + g2 * g2)
                out[node, 0, 0] += lm * g0 * g0 + gg
                out[node, 1, 1] += lm * g1 * g1 + gg
                out[node, 2, 2] += lm * g2 * g2 + gg
                out[node, 0, 1] += lm * g0 * g1
                out[node, 0, 2] += lm * g0 * g2
                out[node, 1, 2] += lm * g1 * g2
    for n in range(out.shape[0]):
        out[n, 1, 0], out[n, 2, 0], out[n, 2, 1] = out[n, 0, 1], out[n, 0, 2], out[n, 1, 2]


@_jit
def rotate_blocks(A: np.ndarray, block_row: np.ndarray, indices: np.ndarray, where: np.ndarray, R: np.ndarray,
                  out: np.ndarray) -> None:
    """T^T A T for block data A (nnzb, 3, 3) into out (a copy of A where neither node turns): block k of row node
    block_row[k] and column node indices[k] becomes R_r^T A_k R_c, with R (m, 3, 3) the frames of the turned nodes
    (where (N,): a node's row in R, -1 for the identity). softbody.integrator.factorize_constrained's two batched
    products (the rows, then the columns), block by block."""
    for k in range(A.shape[0]):
        r, c = where[block_row[k]], where[indices[k]]
        for i in range(3):
            for j in range(3):
                out[k, i, j] = A[k, i, j]
        if r >= 0:
            for j in range(3):
                a0, a1, a2 = out[k, 0, j], out[k, 1, j], out[k, 2, j]
                for i in range(3):
                    out[k, i, j] = R[r, 0, i] * a0 + R[r, 1, i] * a1 + R[r, 2, i] * a2
        if c >= 0:
            for i in range(3):
                a0, a1, a2 = out[k, i, 0], out[k, i, 1], out[k, i, 2]
                for j in range(3):
                    out[k, i, j] = a0 * R[c, 0, j] + a1 * R[c, 1, j] + a2 * R[c, 2, j]


@_jit
def constrained_upper(flat: np.ndarray, gather: np.ndarray, up_row: np.ndarray, up_col: np.ndarray,
                      up_diag: np.ndarray, mask: np.ndarray, data: np.ndarray) -> float:
    """The upper-triangle values data (nnz_up,) = flat[gather] of block data (flattened) with the constrained dofs
    (mask (3N,) bool) eliminated: their rows and columns zero and their diagonal the mean diagonal entry (the
    scale, returned). softbody.integrator.factorize_constrained's gather and masking in one pass."""
    scale = 0.0
    for d in range(up_diag.shape[0]):
        scale += flat[gather[up_diag[d]]]
    scale /= up_diag.shape[0]
    for k in range(gather.shape[0]):
        data[k] = 0.0 if mask[up_row[k]] or mask[up_col[k]] else flat[gather[k]]
    for d in range(up_diag.shape[0]):
        if mask[d]:
            data[up_diag[d]] = scale
    return scale


@_jit
def part_moments(parts: np.ndarray, x: np.ndarray, m: np.ndarray, y: np.ndarray, mass: np.ndarray, P: np.ndarray,
                 L: np.ndarray, r: np.ndarray) -> None:
    """Per node range k of ``parts`` (offsets (k + 1,)): its mass (k,) (node masses m (N,)), the sums P (k, 3) of the
    momenta y (N, 3) and L (k, 3) of r x y about its centre of mass, r (N, 3) = x - that centre (FemBody.rigid_velocity's
    first half)."""
    for k in range(parts.shape[0] - 1):
        mk = c0 = c1 = c2 = 0.0
        for i in range(parts[k], parts[k + 1]):
            mk += m[i]
            c0 += m[i] * x[i, 0]
            c1 += m[i] * x[i, 1]
            c2 += m[i] * x[i, 2]
        c0, c1, c2 = c0 / mk, c1 / mk, c2 / mk
        p0 = p1 = p2 = l0 = l1 = l2 = 0.0
        for i in range(parts[k], parts[k + 1]):
            r0, r1, r2 = x[i, 0] - c0, x[i, 1] - c1, x[i, 2] - c2
            r[i, 0], r[i, 1], r[i, 2] = r0, r1, r2
            y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
            p0 += y0
            p1 += y1
            p2 += y2
            l0 += r1 * y2 - r2 * y1
            l1 += r2 * y0 - r0 * y2
            l2 += r0 * y1 - r1 * y0
        mass[k] = mk
        P[k, 0], P[k, 1], P[k, 2] = p0, p1, p2
        L[k, 0], L[k, 1], L[k, 2] = l0, l1, l2


@_jit
def rigid_field(parts: np.ndarray, free: np.ndarray, r: np.ndarray, Mr: np.ndarray, mass: np.ndarray, P: np.ndarray,
                L: np.ndarray, out: np.ndarray) -> None:
    """The rigid field V + omega x r into out (N, 3) per node range k of ``parts``: V = P_k / mass_k, omega the
    solution of I omega = L_k with I = tr(S) 1 - S^T, S = sum_i r_i (M r)_i^T (r, Mr (N, 3)); zero where not free[k]
    (FemBody.rigid_velocity's second half)."""
    for k in range(parts.shape[0] - 1):
        if not free[k]:
            for i in range(parts[k], parts[k + 1]):
                out[i, 0] = out[i, 1] = out[i, 2] = 0.0
            continue
        s00 = s01 = s02 = s10 = s11 = s12 = s20 = s21 = s22 = 0.0
        for i in range(parts[k], parts[k + 1]):
            s00 += r[i, 0] * Mr[i, 0]
            s01 += r[i, 0] * Mr[i, 1]
            s02 += r[i, 0] * Mr[i, 2]
            s10 += r[i, 1] * Mr[i, 0]
            s11 += r[i, 1] * Mr[i, 1]
            s12 += r[i, 1] * Mr[i, 2]
            s20 += r[i, 2] * Mr[i, 0]
            s21 += r[i, 2] * Mr[i, 1]
            s22 += r[i, 2] * Mr[i, 2]
        t = s00 + s11 + s22
        a00, a01, a02 = t - s00, -s10, -s20  # I = tr(S) 1 - S^T
        a10, a11, a12 = -s01, t - s11, -s21
        a20, a21, a22 = -s02, -s12, t - s22
        c00, c01, c02 = a11 * a22 - a12 * a21, a02 * a21 - a01 * a22, a01 * a12 - a02 * a11  # adjugate rows
        c10, c11, c12 = a12 * a20 - a10 * a22, a00 * a22 - a02 * a20, a02 * a10 - a00 * a12
        c20, c21, c22 = a10 * a21 - a11 * a20, a01 * a20 - a00 * a21, a00 * a11 - a01 * a10
        det = a00 * c00 + a01 * c10 + a02 * c20
        l0, l1, l2 = L[k, 0], L[k, 1], L[k, 2]
        w0 = (c00 * l0 + c01 * l1 + c02 * l2) / det
        w1 = (c10 * l0 + c11 * l1 + c12 * l2) / det
        w2 = (c20 * l0 + c21 * l1 + c22 * l2) / det
        v0, v1, v2 = P[k, 0] / mass[k], P[k, 1] / mass[k], P[k, 2] / mass[k]
        for i in range(parts[k], parts[k + 1]):
            r0, r1, r2 = r[i, 0], r[i, 1], r[i, 2]
            out[i, 0] = v0 + w1 * r2 - w2 * r1
            out[i, 1] = v1 + w2 * r0 - w0 * r2
            out[i, 2] = v2 + w0 * r1 - w1 * r0


@_jit
def max_spin(Fdot9: np.ndarray, R: np.ndarray) -> tuple[float, int]:
    """(|omega|^2, element) of the fastest-turning element: omega = axial(skew(dF/dt R^T)) from dF/dt (component-major
    (9, E), row 3 i + j) and the rotations R (E, 3, 3) (softbody.linearisation.rotation_per_step)."""
    best, where = -1.0, 0
    for e in range(Fdot9.shape[1]):
        # L_ik = sum_j dF_ij R_kj, only the off-diagonal entries the skew part needs
        l01 = Fdot9[0, e] * R[e, 1, 0] + Fdot9[1, e] * R[e, 1, 1] + Fdot9[2, e] * R[e, 1, 2]
        l02 = Fdot9[0, e] * R[e, 2, 0] + Fdot9[1, e] * R[e, 2, 1] + Fdot9[2, e] * R[e, 2, 2]
        l10 = Fdot9[3, e] * R[e, 0, 0] + Fdot9[4, e] * R[e, 0, 1] + Fdot9[5, e] * R[e, 0, 2]
        l12 = Fdot9[3, e] * R[e, 2, 0] + Fdot9[4, e] * R[e, 2, 1] + Fdot9[5, e] * R[e, 2, 2]
        l20 = Fdot9[6, e] * R[e, 0, 0] + Fdot9[7, e] * R[e, 0, 1] + Fdot9[8, e] * R[e, 0, 2]
        l21 = Fdot9[6, e] * R[e, 1, 0] + Fdot9[7, e] * R[e, 1, 1] + Fdot9[8, e] * R[e, 1, 2]
        w0, w1, w2 = 0.5 * (l21 - l12), 0.5 * (l02 - l20), 0.5 * (l10 - l01)
        s = w0 * w0 + w1 * w1 + w2 * w2
        if s > best:
            best, where = s, e
    return best, where


@_jit
def scalar_product(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
    """M y into out (N, 3) for a scalar CSR matrix M (N, N) (indptr, indices, data) and y (N, 3): the mass matrix's
    product (FemBody.mass_product; scipy's sparse-times-dense costs several times this on a small mesh)."""
    for i in range(indptr.shape[0] - 1):
        s0 = s1 = s2 = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j, m = indices[k], data[k]
            s0 += m * y[j, 0]
            s1 += m * y[j, 1]
            s2 += m * y[j, 2]
        out[i, 0], out[i, 1], out[i, 2] = s0, s1, s2


@_jit
def diagonal_from_rows(U: np.ndarray, rows: np.ndarray, cols: np.ndarray, diag: np.ndarray, sums: np.ndarray) -> None:
    """Set the diagonal blocks diag (N,) of upper block data U (n_upper, 9) (blocks (rows[k], cols[k]), row-major)
    to minus the sums of the other blocks of their block row: those right of the diagonal as they are, those above
    it transposed (UpperAssembly.with_diagonal's sparse product, summed in its order). sums (2N, 9) is scratch."""
    sums[:] = 0.0
    N = diag.shape[0]
    for k in range(U.shape[0]):
        r, c = rows[k], cols[k]
        for e in range(9):
            sums[r, e] += U[k, e]
            sums[N + c, e] += U[k, e]
    for n in range(N):
        d = diag[n]
        for i in range(3):
            for j in range(3):
                U[d, 3 * i + j] = -(sums[n, 3 * i + j] + sums[N + n, 3 * j + i])


@_jit
def system_blocks(K: np.ndarray, mass: np.ndarray, c_m: float, c_k: float, source: np.ndarray,
                  transposed: np.ndarray, out: np.ndarray) -> None:
    """Block data out (nnzb, 3, 3) of c_m M + c_k K from the upper blocks K (n_upper, 9) (row-major) and the mass's
    upper blocks (n_upper,) (multiples of I3): block k copies upper block source[k], transposed where
    ``transposed[k]`` (FemBody.system_blocks's scaled copy, the mass added on the diagonals, and
    UpperAssembly.full's gather, in one pass)."""
    for k in range(source.shape[0]):
        s = source[k]
        m = c_m * mass[s]
        for i in range(3):
            for j in range(3):
                v = c_k * (K[s, 3 * j + i] if transposed[k] else K[s, 3 * i + j])
                out[k, i, j] = v + m if i == j else v


@_jit
def local_constraints(nodes: np.ndarray, cmask: np.ndarray, cvalue: np.ndarray, frames: np.ndarray,
                      frame_of: np.ndarray, mask: np.ndarray, value: np.ndarray) -> int:
    """integrator.Constraints.dense for m constraints (nodes (m,), cmask (m, 3), cvalue (m, 3), frames (m, 3, 3) or
    (0, 3, 3) for identity frames) among N nodes, into frame_of (N,) (a node's row in frames, -1 for the identity:
    also where its frame is the identity), mask (N, 3) and value (N, 3) (zero where not held). Returns how many
    nodes turn."""
    frame_of[:] = -1
    mask[:] = False
    value[:] = 0.0
    turned = 0
    for k in range(nodes.shape[0]):
        n = nodes[k]
        for a in range(3):
            mask[n, a] = cmask[k, a]
            value[n, a] = cvalue[k, a] if cmask[k, a] else 0.0
        if frames.shape[0]:
            for i in range(3):
                for j in range(3):
                    if frames[k, i, j] != (1.0 if i == j else 0.0):
                        if frame_of[n] < 0:
                            turned += 1
                        frame_of[n] = k
    return turned


@_jit
def frames_apply(frame_of: np.ndarray, R: np.ndarray, x: np.ndarray, transpose: bool, out: np.ndarray) -> None:
    """out (N, 3) = R_f^T x (transpose) or R_f x per node, f = frame_of[node] (-1: the identity, out = x); per-node
    frames T (N, 3, 3) with frame_of = arange(N) (softbody.integrator.to_local and to_global)."""
    for n in range(x.shape[0]):
        f = frame_of[n]
        x0, x1, x2 = x[n, 0], x[n, 1], x[n, 2]
        if f < 0:
            out[n, 0], out[n, 1], out[n, 2] = x0, x1, x2
        elif transpose:
            for i in range(3):
                out[n, i] = R[f, 0, i] * x0 + R[f, 1, i] * x1 + R[f, 2, i] * x2
        else:
            for i in range(3):
                out[n, i] = R[f, i, 0] * x0 + R[f, i, 1] * x1 + R[f, i, 2] * x2


@_inline
def _row_product(A: np.ndarray, indptr: np.ndarray, indices: np.ndarray, i: int, x: np.ndarray, only: np.ndarray,
                 every: bool):
    """Block row i of A x for a block matrix (BSR: blocks A (nnzb, 3, 3), indptr, indices) and x (N, 3), over every
    block or (``every`` False) those whose column node is flagged in ``only`` (N,): its three sums, each summed term
    by term in scipy's BSR order."""
    s0, s1, s2 = 0.0, 0.0, 0.0
    for k in range(indptr[i], indptr[i + 1]):
        j = indices[k]
        if every or only[j]:
            x0, x1, x2 = x[j, 0], x[j, 1], x[j, 2]
            s0 = s0 + A[k, 0, 0] * x0 + A[k, 0, 1] * x1 + A[k, 0, 2] * x2
            s1 = s1 + A[k, 1, 0] * x0 + A[k, 1, 1] * x1 + A[k, 1, 2] * x2
            s2 = s2 + A[k, 2, 0] * x0 + A[k, 2, 1] * x1 + A[k, 2, 2] * x2
    return s0, s1, s2


@_jit
def constrained_rhs(A: np.ndarray, indptr: np.ndarray, indices: np.ndarray, mask: np.ndarray, value: np.ndarray,
                    b: np.ndarray, scale: float, held: np.ndarray, rhs: np.ndarray) -> None:
    """The right-hand side (N, 3) of the eliminated system: b - A value over the blocks of the held nodes' columns
    (held (N,) bool, set here from mask (N, 3)), and scale * value on the held components (DirectSystem.solve)."""
    N = mask.shape[0]
    for n in range(N):
        held[n] = mask[n, 0] or mask[n, 1] or mask[n, 2]
    for i in range(N):
        s0, s1, s2 = _row_product(A, indptr, indices, i, value, held, False)
        rhs[i, 0], rhs[i, 1], rhs[i, 2] = b[i, 0] - s0, b[i, 1] - s1, b[i, 2] - s2
        for a in range(3):
            if mask[i, a]:
                rhs[i, a] = scale * value[i, a]


@_jit
def constrained_finish(A: np.ndarray, indptr: np.ndarray, indices: np.ndarray, mask: np.ndarray, value: np.ndarray,
                       held: np.ndarray, b: np.ndarray, y: np.ndarray, reaction: np.ndarray) -> None:
    """After the eliminated solve: the held components of y (N, 3, local) set to their values exactly, and the
    reactions (N, 3) = A y - b on them (zero elsewhere), summed over every block of the held nodes' rows."""
    N = mask.shape[0]
    for n in range(N):
        for a in range(3):
            if mask[n, a]:
                y[n, a] = value[n, a]
    for i in range(N):
        reaction[i, 0], reaction[i, 1], reaction[i, 2] = 0.0, 0.0, 0.0
        if not held[i]:
            continue
        s0, s1, s2 = _row_product(A, indptr, indices, i, y, held, True)
        if mask[i, 0]:
            reaction[i, 0] = s0 - b[i, 0]
        if mask[i, 1]:
            reaction[i, 1] = s1 - b[i, 1]
        if mask[i, 2]:
            reaction[i, 2] = s2 - b[i, 2]


@_jit
def block_product(A: np.ndarray, indptr: np.ndarray, indices: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """out (N, 3) = A x for a block matrix (BSR: blocks A (nnzb, 3, 3), indptr, indices) and x (N, 3), each entry
    summed term by term in scipy's BSR order (BlockPattern.product)."""
    for i in range(indptr.shape[0] - 1):
        out[i, 0], out[i, 1], out[i, 2] = _row_product(A, indptr, indices, i, x, _NO_FLAGS, True)


@_jit
def characteristic_gradients(nodes: np.ndarray, grads: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """The deformation gradients F_e = sum_a (x_a - mean x) g_a^T (component-major out (9, E), row 3 i + j: F_ij) of
    the characteristic tetrahedra: nodes (E, m) and gradients (E, m, 3) of their m node slots, positions x (N, 3).
    FemBody.characteristic_gradient's sparse product, element by element (a node's position read once per slot)."""
    N = x.shape[0]
    m0 = m1 = m2 = 0.0
    for i in range(N):
        m0 += x[i, 0]
        m1 += x[i, 1]
        m2 += x[i, 2]
    m0, m1, m2 = m0 / N, m1 / N, m2 / N
    for e in range(nodes.shape[0]):
        f0, f1, f2, f3, f4, f5, f6, f7, f8 = _gradient(nodes, grads, e, 0, x, m0, m1, m2)
        out[0, e], out[1, e], out[2, e] = f0, f1, f2
        out[3, e], out[4, e], out[5, e] = f3, f4, f5
        out[6, e], out[7, e], out[8, e] = f6, f7, f8


ENABLED = _compilation.register(sys.modules[__name__], AVAILABLE, warmup="softbody.warmup")
