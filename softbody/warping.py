"""Linear operators of stiffness warping, built once per mesh as sparse matrices.

Per step, warping needs (i) each element's deformation gradient F (from its characteristic
tetrahedra), (ii) the shape-function gradients rotated by each element's R, and (iii) the warped
rest loads sum_e R_e K_e X_e. Each is linear in the positions or in the rotations, so each can be
one precomputed sparse matrix and one product per step, with no per-element Python work. (FemBody
uses (ii) for one-point elements, whose rotated gradients it wants component-major; for the others
one batched matmul is faster.)

Rotations and deformation gradients are component-major: a (9, E) array whose row 3 i + j holds
entry (i, j) of every element's matrix (see :mod:`softbody.rotation`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def deformation_gradient_operator(nodes: np.ndarray, grads: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Sparse D (9E, 3N) with (D x).reshape(9, E) = F, F_ij = sum_a x_{node a, i} grads_{a, j}.

    nodes: (E, m) global node of each of the m contributing nodes; grads: (E, m, 3) their gradients.
    """
    E, m = nodes.shape
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")  # (3, 3)
    rows = (3 * i + j)[None, None] * E + np.arange(E)[:, None, None, None]  # (E, 1, 3, 3)
    cols = 3 * nodes[:, :, None, None] + i[None, None]  # (E, m, 3, 3)
    vals = np.broadcast_to(grads[:, :, None, :], (E, m, 3, 3))
    rows = np.broadcast_to(rows, cols.shape)
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(9 * E, 3 * n_nodes))


def rotated_gradient_operator(G: np.ndarray) -> sp.csr_matrix:
    """Sparse P (E q k 3, 9E) with (P R9).reshape(q, k, 3, E) = R_e G_eqa (each gradient rotated by its
    element's R), component-major.

    G: (E, q, k, 3) gradients (any weighting folded in).
    """
    E, q, k, _ = G.shape
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = np.arange(E * q * k * 3).reshape(q, k, 3, E).transpose(3, 0, 1, 2)[..., None]  # (E, q, k, 3 (i), 1)
    cols = (3 * i + j)[None, None, None] * E + np.arange(E)[:, None, None, None, None]  # (E, 1, 1, 3, 3)
    vals = G[:, :, :, None, :]  # (E, q, k, 1, 3 (j))
    shape = (E, q, k, 3, 3)
    return sp.csr_matrix((np.broadcast_to(vals, shape).ravel(),
                          (np.broadcast_to(rows, shape).ravel(), np.broadcast_to(cols, shape).ravel())),
                         shape=(E * q * k * 3, 9 * E))


def rest_load_operator(elements: np.ndarray, P: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Sparse L (3N, 9E) with L R9 = sum_e R_e p_e scattered to the nodes, for per-element nodal
    vectors P (E, k, 3): (L R9)_{node a, i} = sum_{e, j} R_e,ij P_e,a,j."""
    E, k = elements.shape
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = 3 * elements[:, :, None, None] + i[None, None]  # (E, k, 3, 3)
    cols = np.broadcast_to((3 * i + j)[None, None] * E + np.arange(E)[:, None, None, None], rows.shape)
    vals = np.broadcast_to(P[:, :, None, :], rows.shape)
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n_nodes, 9 * E))


def isotropic_matrix(lam: float, mu: float) -> np.ndarray:
    """The (9, 9) map L with K = L S for 3x3 blocks flattened row-major (entry 3 i + j holds (i, j)):
    K = lam S + mu S^T + mu tr(S) I.

    With S_ab = sum_q w detJ g_a g_b^T (g: shape-function gradients), K is the isotropic small-strain
    stiffness block K_ab; it is linear in S, so it applies after assembly, to each assembled block.
    """
    L = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            L[3 * i + j, 3 * i + j] += lam
            L[3 * i + j, 3 * j + i] += mu
        for m in range(3):
            L[4 * i, 4 * m] += mu
    return L


def isotropic_blocks(S: np.ndarray, L: np.ndarray) -> np.ndarray:
    """K = S @ L^T for blocks stacked as rows, S (n, 9) -> K (n, 9), L from ``isotropic_matrix``.

    The product runs in slices of 2048 rows, each below the size at which multithreaded BLAS wakes
    its thread pool: with the default thread counts, the pool woken by one tall, thin product then
    competed with PARDISO's for the two cores (measured: 20 against 8.7 ms per step on the tet10
    (6,6,2) sheet). Elementwise operations would avoid BLAS too, but their temporaries cost 2-10x the
    product here.
    """
    return sliced_matmul(np.ascontiguousarray(S, dtype=float), L.T.copy())


def sliced_matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B for a tall A (n, m) and a small B (m, p), in slices of 2048 rows: below the size at which
    multithreaded BLAS wakes its thread pool (see ``isotropic_blocks``)."""
    out = np.empty((len(A), B.shape[1]))
    for start in range(0, len(A), 2048):
        np.matmul(A[start:start + 2048], B, out=out[start:start + 2048])
    return out


def stress_map(lam: float, mu: float, q: int) -> np.ndarray:
    """(9q, 9q) matrix S with sigma = H @ S for the displacement gradients H of one element at its q
    quadrature points, flattened (i, q, j) (entry H_q,ij), into the stresses flattened (q, j, i):
    sigma_q = lam tr(H_q) I + mu (H_q + H_q^T), the isotropic small-strain stress (symmetric, so
    the (q, j, i) layout is also sigma_q,ij)."""
    S = np.zeros((3, q, 3, q, 3, 3))  # [i, q, j] in, [q', j', i'] out
    for p in range(q):
        for i in range(3):
            for j in range(3):
                S[i, p, j, p, j, i] += mu
                S[j, p, i, p, j, i] += mu
            for m in range(3):
                S[m, p, m, p, i, i] += lam
    return S.reshape(9 * q, 9 * q)


def warped_product(g: np.ndarray, elements: np.ndarray, stress: np.ndarray, scatter: sp.csr_matrix,
                   y: np.ndarray) -> np.ndarray:
    """K' y (N, 3) for y (N, 3), K' = sum_e R_e K_e R_e^T, without forming K'.

    g: (E, k, 3q) rotated weighted gradients sqrt(w detJ) R_e dN_a/dX at each quadrature point, entry
    (e, a, 3 q + j); elements (E, k); stress: ``stress_map`` (9q, 9q); scatter: the 0/1 (N, E k) sum of
    element-node vectors into nodes. Per element: H = Y^T g (the rotated displacement gradients,
    weighted), sigma = H S, f = g sigma: two small batched matmuls and one product with a (9q, 9q).
    """
    E, k, _ = g.shape
    Y = np.take(y, elements, axis=0)  # (E, k, 3)
    H = np.swapaxes(Y, 1, 2) @ g  # (E, 3, 3q)
    sigma = sliced_matmul(H.reshape(E, -1), stress).reshape(E, -1, 3)  # (E, 3q, 3)
    return scatter @ (g @ sigma).reshape(-1, 3)


def warped_diagonal(g: np.ndarray, lam: float, mu: float, scatter: sp.csr_matrix) -> np.ndarray:
    """The diagonal blocks (N, 3, 3) of K' = sum_e R_e K_e R_e^T without forming K': g (E, k, 3q) the rotated weighted
    gradients (as warped_product), lam, mu the Lame parameters, scatter the 0/1 (N, E k) sum of element-node values into
    nodes. At a node slot a, K' y for y at that node alone is sum_q [(lam + mu) g_qa g_qa^T + mu |g_qa|^2 I] y."""
    E, k, q3 = g.shape
    g4 = g.reshape(E, k, q3 // 3, 3)
    S = np.einsum("ekpi,ekpj->ekij", g4, g4)  # (E, k, 3, 3)
    blocks = (lam + mu) * S + mu * np.trace(S, axis1=2, axis2=3)[:, :, None, None] * np.eye(3)
    return np.asarray(scatter @ blocks.reshape(E * k, 9)).reshape(-1, 3, 3)
