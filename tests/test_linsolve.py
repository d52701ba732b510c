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
