"""softbody.multigrid: the V-cycle against its definition in dense double precision, and what PCG needs of it."""
import numpy as np
import pytest
import scipy.sparse as sp

import softbody
from softbody import box_mesh

pytest.importorskip("pyamg")
from softbody import multigrid  # noqa: E402


def _upper(kind="tet4", cells=(6, 5, 4)):
    """The upper triangle (CSR) of M + h^2 K of a box mesh, and the whole matrix (dense)."""
    body = softbody.FemBody(box_mesh((0.4, 0.3, 0.2), cells, kind), softbody.LinearElastic(1e6, 0.3, 1000.0))
    K, _ = body.warped_stiffness_blocks(None)
    blocks = body.M_blocks + 1e-4 * K
    A = body.pattern.to_csr(blocks)
    return sp.triu(A).tocsr(), A.toarray()


def _dense_cycle(levels, coarse_A, b):
    """A V-cycle written from its definition in dense double precision: forward Gauss-Seidel from zero
    ((D + L)^-1 b), the residual restricted by P^T, the same cycle one level down (the coarsest solved exactly), the
    correction prolongated, a backward sweep ((D + U)^-1 of the residual)."""
    if not levels:
        return np.linalg.solve(coarse_A, b)
    A, P = levels[0]
    x = np.linalg.solve(np.tril(A), b)
    x = x + P @ _dense_cycle(levels[1:], coarse_A, P.T @ (b - A @ x))
    return x + np.linalg.solve(np.triu(A), b - A @ x)


def test_the_cycle_is_its_definition():
    """VCycle @ b equals the dense definition on the hierarchy's own matrices (to single precision), for one and many
    right-hand sides; with two levels and more."""
    U, A = _upper()
    b = np.random.default_rng(1).standard_normal((len(A), 2))
    for coarse in (120, 30):
        cycle = multigrid.hierarchy(U, coarse)
        assert cycle.levels and cycle.coarse.shape[0] <= coarse
        levels = [(lv.A.toarray().astype(float), lv.P.toarray().astype(float)) for lv in cycle.levels]
        coarse_A = np.linalg.pinv(cycle.coarse)
        np.testing.assert_allclose(levels[0][0], A, rtol=0, atol=1e-6 * np.abs(A).max())  # the finest level is A
        for lv, (Ad, Pd) in zip(cycle.levels[1:], levels):  # each coarser matrix is P^T A P of the one above
            np.testing.assert_allclose(lv.A.toarray(), Pd.T @ Ad @ Pd, rtol=0, atol=1e-5 * np.abs(Ad).max())
        expected = np.column_stack([_dense_cycle(levels, coarse_A, b[:, j]) for j in range(2)])
        got = cycle @ b
        assert got.dtype == np.float64
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
        np.testing.assert_allclose(cycle @ b[:, 0], got[:, 0], rtol=0, atol=0)
    assert len(multigrid.hierarchy(U, 30).levels) >= 2


def test_the_cycle_preconditions_conjugate_gradients():
    """Symmetric positive definite to single precision, a contraction (x += M (b - A x) converges), no exact solve, and
    PCG with it reaches 1e-8 in far fewer iterations than CG alone."""
    U, A = _upper("tet4", (8, 6, 4))
    cycle = multigrid.hierarchy(U, 60)
    n = len(A)
    M = cycle @ np.eye(n)
    np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-6 * np.abs(M).max())
    assert np.linalg.eigvalsh(0.5 * (M + M.T)).min() > 0
    assert np.abs(np.linalg.eigvals(np.eye(n) - M @ A)).max() < 1
    assert np.abs(M @ A - np.eye(n)).max() > 1e-3

    def cg(precondition):
        b = np.ones(n)
        x, r = np.zeros(n), b.copy()
        z = precondition(r)
        d, rz = z.copy(), r @ z
        for it in range(1, 2000):
            Ad = A @ d
            a = rz / (d @ Ad)
            x += a * d
            r -= a * Ad
            if np.linalg.norm(r) <= 1e-8 * np.linalg.norm(b):
                return it
            z = precondition(r)
            rz, rz_old = r @ z, rz
            d = z + (rz / rz_old) * d
        return 2000

    with_cycle, plain = cg(lambda r: cycle @ r), cg(lambda r: r)
    assert with_cycle * 4 < plain, (with_cycle, plain)


def test_a_small_system_is_one_exact_level_and_bad_input_is_named():
    U, A = _upper("tet4", (2, 1, 1))
    cycle = multigrid.hierarchy(U, 1000)
    assert not cycle.levels
    b = np.arange(len(A), dtype=float)
    np.testing.assert_allclose(cycle @ b, np.linalg.solve(A, b), rtol=0, atol=1e-9 * np.abs(np.linalg.solve(A, b)).max())
    with pytest.raises(softbody.errors.SolverError, match="shape"):
        cycle @ np.ones(len(A) + 1)
    with pytest.raises(softbody.errors.SolverError, match="multiple of 3"):
        multigrid.hierarchy(sp.identity(4, format="csr"), 1)
