"""The sparse SPD solver: answers against scipy's independent sparse LU, precision of the single-precision
path, and the reproducible choice of PARDISO's fill-reducing ordering."""
from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import softbody
from softbody.linsolve import HAVE_PARDISO, SpdSolver
from softbody.meshing import box_mesh

pardiso = pytest.mark.skipif(not HAVE_PARDISO, reason="PARDISO (pypardiso / MKL) not installed")


def _system(kind: str, cells):
    """Upper-triangle data of M + h^2 K for a box mesh (SPD: the mass term removes the rigid modes)."""
    body = softbody.FemBody(box_mesh((0.4, 0.3, 0.2), cells, kind), softbody.LinearElastic(1e6, 0.3, 1000.0))
    K, _ = body.warped_stiffness_blocks(None)
    blocks = body.M_blocks + 1e-4 * K
    p = body.pattern
    return p, p.upper_data(blocks), p.to_csr(blocks), body.n_dofs


@pardiso
@pytest.mark.parametrize("kind, cells", [("tet4", (6, 5, 4)), ("tet10", (3, 3, 2)), ("hex8", (6, 5, 4))])
def test_solutions_match_scipy_and_the_single_precision_path_is_close(kind, cells):
    p, data, A, n = _system(kind, cells)
    b = np.random.default_rng(0).standard_normal(n)
    ref = spla.spsolve(A.tocsc(), b)
    for precision, tol in (("double", 1e-10), ("single", 1e-4)):
        s = SpdSolver(p.up_indptr, p.up_indices, n, "pardiso", precision=precision)
        s.factorize(data)
        x = s.solve(b)
        assert np.linalg.norm(x - ref) <= tol * np.linalg.norm(ref), precision
    s = SpdSolver(p.up_indptr, p.up_indices, n, "superlu")
    s.factorize(data)
    assert np.linalg.norm(s.solve(b) - ref) <= 1e-10 * np.linalg.norm(ref)


@pardiso
@pytest.mark.parametrize("kind, cells", [("tet10", (4, 4, 2)), ("hex8", (14, 14, 6))])
def test_the_ordering_with_fewer_factorisation_flops_is_kept_reproducibly(kind, cells):
    # (with this machine's MKL: minimum degree for the first, METIS for the second)
    p, data, _, n = _system(kind, cells)
    flops = {}
    for order in SpdSolver.ORDERINGS:
        only = SpdSolver(p.up_indptr, p.up_indices, n, "pardiso")
        only.ORDERINGS = {order: SpdSolver.ORDERINGS[order]}
        only.analyse(data)
        flops[order] = only.factor_mflop
    chosen = SpdSolver(p.up_indptr, p.up_indices, n, "pardiso")
    chosen.analyse(data)
    assert chosen.factor_mflop <= 1.2 * min(flops.values())  # (METIS's random state: see SpdSolver.analyse)
    assert chosen.ordering == SpdSolver.ORDERINGS[min(flops, key=lambda o: (flops[o], o != 2))]
    # the choice depends on the pattern only: a second solver chooses the same (bit-identical runs across
    # processes are checked by the study tests)
    b = np.arange(n, dtype=float)
    again = SpdSolver(p.up_indptr, p.up_indices, n, "pardiso")
    chosen.factorize(data)
    again.factorize(data)
    assert again.ordering == chosen.ordering
    np.testing.assert_allclose(again.solve(b), chosen.solve(b), rtol=1e-11)


def test_pypardiso_is_pointed_at_mkl_in_this_environment(tmp_path, monkeypatch):
    """MKL's runtime in the environment's lib directory is handed to pypardiso (which would otherwise search all of
    sys.prefix), the shortest name first; a path the user gave is kept; no library, no hint."""
    from softbody import linsolve

    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "libmkl_rt.so.3").write_bytes(b"")
    (tmp_path / "lib" / "libmkl_rt.so.3.debug").write_bytes(b"")
    monkeypatch.setattr(linsolve.sys, "prefix", str(tmp_path))
    monkeypatch.delenv("PYPARDISO_MKL_RT", raising=False)
    linsolve._point_pypardiso_at_mkl()
    assert os.environ["PYPARDISO_MKL_RT"] == str(tmp_path / "lib" / "libmkl_rt.so.3")
    monkeypatch.setenv("PYPARDISO_MKL_RT", "/somewhere/libmkl_rt.so")
    linsolve._point_pypardiso_at_mkl()
    assert os.environ["PYPARDISO_MKL_RT"] == "/somewhere/libmkl_rt.so"
    monkeypatch.delenv("PYPARDISO_MKL_RT")
    monkeypatch.setattr(linsolve.sys, "prefix", str(tmp_path / "empty"))
    linsolve._point_pypardiso_at_mkl()
    assert "PYPARDISO_MKL_RT" not in os.environ


@pytest.mark.skipif(not softbody.kernels.ENABLED, reason="the block backend is compiled (numba)")
@pytest.mark.parametrize("kind, cells", [("tet4", (4, 4, 2)), ("tet10", (2, 2, 1)), ("hex8", (3, 2, 2))])
def test_the_block_cholesky_solves_like_scipy_for_one_and_many_right_hand_sides(kind, cells):
    p, data, A, n = _system(kind, cells)
    rng = np.random.default_rng(1)
    s = SpdSolver(p.up_indptr, p.up_indices, n, "blocks")
    s.factorize(data)
    for b in (rng.standard_normal(n), rng.standard_normal((n, 4)), np.asfortranarray(rng.standard_normal((n, 3)))):
        ref = spla.spsolve(A.tocsc(), b)
        x = s.solve(b)
        assert x.shape == b.shape
        assert np.linalg.norm(x - ref) <= 1e-12 * np.linalg.norm(ref)
    # refactorised with other values on the same pattern (the symbolic analysis is kept)
    s.factorize(2.0 * data)
    b = rng.standard_normal(n)
    np.testing.assert_allclose(s.solve(b), 0.5 * spla.spsolve(A.tocsc(), b), rtol=1e-10, atol=1e-14)


@pytest.mark.skipif(not softbody.kernels.ENABLED, reason="the block backend is compiled (numba)")
def test_the_block_factor_is_a_permuted_cholesky_factor_and_rejects_an_indefinite_matrix():
    from softbody import cholesky

    p, data, A, n = _system("tet4", (3, 2, 2))
    S = cholesky.BlockSymbolic.of(p.up_indptr, p.up_indices, n)
    N = n // 3
    assert sorted(S.perm.tolist()) == list(range(N))
    s = SpdSolver(p.up_indptr, p.up_indices, n, "blocks")
    s.factorize(data)
    L = np.zeros((n, n))  # L L^T must equal P^T A P, entry by entry
    for j in range(N):
        for q in range(S.col_ptr[j], S.col_ptr[j + 1]):
            i = S.row[q]
            L[3 * i:3 * i + 3, 3 * j:3 * j + 3] = s.factorization._factor[q]
    dofs = (3 * S.perm[:, None] + np.arange(3)).ravel()
    PAP = A.toarray()[np.ix_(dofs, dofs)]
    np.testing.assert_allclose(L @ L.T, PAP, rtol=0, atol=1e-12 * np.abs(PAP).max())
    assert np.all(np.triu(L, 1) == 0)
    bad = data.copy()
    bad[p.up_diag[7]] = -1.0  # one negative pivot
    with pytest.raises(softbody.errors.SolverError, match="not positive definite"):
        s.factorize(bad)
    with pytest.raises(softbody.errors.SolverError, match="before a successful"):
        s.solve(np.ones(n))


@pytest.mark.skipif(not softbody.kernels.ENABLED, reason="the block backend is compiled (numba)")
def test_auto_picks_the_block_backend_for_small_systems_only():
    from softbody import cholesky

    small, _, _, n_small = _system("tet4", (4, 4, 2))
    assert SpdSolver(small.up_indptr, small.up_indices, n_small).backend == "blocks"
    large, data, _, n_large = _system("tet4", (16, 16, 4))  # 1445 nodes: beyond BLOCKS_MAX_UNKNOWNS
    assert SpdSolver(large.up_indptr, large.up_indices, n_large).backend in ("pardiso", "superlu")
    mid, _, _, n_mid = _system("hex8", (10, 10, 3))  # few enough unknowns, too large a factor
    assert cholesky.BlockSymbolic.of(mid.up_indptr, mid.up_indices, n_mid).multiply_adds > cholesky.SMALL_FACTOR
    assert SpdSolver(mid.up_indptr, mid.up_indices, n_mid).backend in ("pardiso", "superlu")
    with pytest.raises(softbody.errors.InvalidInputError, match="multiple of 3"):
        SpdSolver(np.array([0, 1, 2, 3, 4]), np.arange(4), 4, "blocks")


@pytest.mark.parametrize("backend", ["auto", "superlu", "blocks"] + (["pardiso"] if HAVE_PARDISO else []))
def test_a_body_without_warping_is_factorised_once_and_steps_as_if_factorised_every_step(backend):
    """Without warping the step matrix M + h C + h^2 K is constant: the solver keeps its factor when given the same
    values again (softbody.linsolve.SpdSolver.factorize), to the bit the trajectory of a solver made to factorise
    every step; a warped body's matrix changes with its rotations and is factorised every step."""
    runs = {}
    for warping, forget in ((False, False), (False, True), (True, False)):
        mesh = box_mesh((0.6, 0.1, 0.1), (6, 1, 1), "tet10", center=(0.3, 0.0, 0.0))
        body = softbody.FemBody(mesh, softbody.LinearElastic(1e6, 0.3, 1000.0), warping=warping)
        body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
        sim = softbody.Simulation(body, 0.01, solver=backend, method="direct")
        solver = sim.solvers.solver(body, backend)
        for _ in range(20):
            if forget:
                solver._values = None  # as if the factor were lost: factorise again
            sim.step()
        runs[warping, forget] = (body.positions.copy(), solver.refactorizations, getattr(solver, "kept", 0))
    assert runs[False, False][1:] == (1, 19)
    assert runs[False, True][1:] == (20, 0)
    assert np.array_equal(runs[False, False][0], runs[False, True][0])
    assert runs[True, False][1:] == (20, 0)
    assert np.abs(runs[True, False][0] - runs[False, False][0]).max() > 1e-4  # the sag turns the elements: they differ


def test_every_backend_is_a_factorization_chosen_in_one_place(monkeypatch):
    """Each backend answers the same protocol (analyse, factorize, solve with one and many right-hand sides, drop)
    with the same solution; choose_backend names what a missing one needs. (Multigrid with a coarsest level of 30
    unknowns: a real hierarchy on this small a system, not one exact level.)"""
    from softbody import linsolve

    monkeypatch.setattr(linsolve.AMGFactorization, "MAX_COARSE", 30)

    p, data, A, n = _system("tet4", (3, 2, 2))
    b = np.arange(2 * n, dtype=float).reshape(n, 2)
    ref = np.linalg.solve(A.toarray(), b)
    names = [name for name in linsolve.FACTORIZATIONS
             if (name != "pardiso" or linsolve.HAVE_PARDISO) and (name != "blocks" or softbody.kernels.AVAILABLE)]
    names = [name for name in names if name != "amg" or linsolve.HAVE_PYAMG]
    assert "superlu" in names
    dense = A.toarray()
    for name in names:
        s = SpdSolver(p.up_indptr, p.up_indices, n, name)
        assert s.backend == name and s.factorization.name == name
        s.factorize(data)
        if s.exact:
            np.testing.assert_allclose(s.solve(b), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
            np.testing.assert_allclose(s.solve(b[:, 0]), ref[:, 0], rtol=0, atol=1e-10 * np.abs(ref).max())
        else:  # a preconditioner (multigrid): a fixed SPD operator M ~ A^-1 whose iteration x += M (b - A x) converges
            Mop = s.solve(np.eye(n))  # (its levels in single precision: symmetric to their round-off)
            np.testing.assert_allclose(Mop, Mop.T, rtol=0, atol=1e-6 * np.abs(Mop).max())
            assert np.linalg.eigvalsh(0.5 * (Mop + Mop.T)).min() > 0
            assert np.abs(np.linalg.eigvals(np.eye(n) - Mop @ dense)).max() < 1
            np.testing.assert_allclose(s.solve(b)[:, 0], s.solve(b[:, 0]), rtol=0, atol=1e-12 * np.abs(ref).max())
            assert np.abs(Mop @ dense - np.eye(n)).max() > 1e-3  # a V-cycle, not an exact solve
        s.refactorize(None)
        assert not s.factorization.has_factor
        with pytest.raises(softbody.errors.SolverError, match="before a successful"):
            s.solve(b)
    with pytest.raises(softbody.InvalidInputError, match="valid"):
        linsolve.choose_backend(p.up_indptr, p.up_indices, n, "cholmod")


@pytest.mark.parametrize("kind, cells", [("tet4", (3, 2, 2)), ("hex8", (2, 2, 1)), ("tet10", (2, 1, 1))])
def test_block_pattern_upper_triangle_is_scipys(kind, cells):
    """The solver's upper-triangle CSR (made row by row from arithmetic, softbody.assembly._upper_scalars) is scipy's
    triu of the whole matrix: the same row pointers, columns and values, the diagonal first in each row."""
    import scipy.sparse as sp
    from softbody.assembly import BlockPattern

    mesh = softbody.box_mesh((0.3, 0.2, 0.1), cells, kind)
    p = BlockPattern.from_elements(mesh.elements, mesh.n_nodes)
    data = np.random.default_rng(3).uniform(1.0, 2.0, (p.nnzb, 3, 3))
    U = sp.triu(p.to_bsr(data).tocsr()).tocsr()
    U.sort_indices()
    np.testing.assert_array_equal(p.up_indptr, U.indptr)
    np.testing.assert_array_equal(p.up_indices, U.indices)
    np.testing.assert_array_equal(p.upper_data(data), U.data)
    np.testing.assert_array_equal(p.up_indices[p.up_diag], np.arange(3 * mesh.n_nodes))
    np.testing.assert_array_equal(p.up_row, np.repeat(np.arange(3 * mesh.n_nodes), np.diff(U.indptr)))


def test_multigrid_set_up_is_reproducible_and_leaves_the_random_state_alone(monkeypatch):
    """pyamg draws its spectral-radius estimates from numpy's global random numbers: the set-up is seeded, so the same
    values give the same V-cycle to the bit (a restored state needs it), and the caller's random sequence goes on
    as if no set-up had run."""
    pytest.importorskip("pyamg")
    from softbody import linsolve

    monkeypatch.setattr(linsolve.AMGFactorization, "MAX_COARSE", 30)
    p, data, A, n = _system("tet4", (4, 3, 2))
    b = np.arange(n, dtype=float)
    np.random.seed(5)
    expected = np.random.rand(3)
    np.random.seed(5)
    answers = []
    for _ in range(2):
        s = SpdSolver(p.up_indptr, p.up_indices, n, "amg")
        s.factorize(data)
        answers.append(s.solve(b))
    np.testing.assert_array_equal(answers[0], answers[1])
    np.testing.assert_array_equal(np.random.rand(3), expected)
