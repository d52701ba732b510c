"""The fast solver path (PCG preconditioned by a reused single-precision factorisation, Simulation method
"iterative") and a plain direct solve (factorise every solve, method "direct") give the
same trajectory on a short sheet-on-sphere run with contact, for each element type.

Tolerance: 1e-5 m on every node at every step. The iterative solve stops at a residual of 1e-5 of
the right-hand side or of the terms it is made of (IterativeSettings.tol), so each step's velocity
differs from the direct one by about 1e-5 of |v| (~1 m/s at impact), i.e. ~1e-7 m of position per
0.01 s step; over 50 steps, through the contact active-set loop, the measured differences are
2e-7 .. 3.5e-7 m (tet4 2.7e-7, hex8 2.1e-7, tet10 3.5e-7). 1e-5 m leaves a margin of 25x for other
machines and BLAS builds and is still 1e-4 of the sheet's 0.05-0.1 m motion, far below any visible or
physically meaningful difference (the mesh spacing is 0.06-0.25 m).
"""
from __future__ import annotations

import numpy as np
import pytest

from experiments.scenes import sheet_on_sphere

TOL = 1e-5  # [m], see the module docstring
DURATION = 0.5  # [s]: falls 0.05 m onto the sphere at ~0.1 s, then 0.4 s in contact


def _trajectory(kind, cells, method, operator="auto"):
    from softbody.integrator import IterativeSettings

    scene = sheet_on_sphere(kind, cells)
    scene.world.sim.method = method
    scene.world.sim.settings = IterativeSettings(tol=scene.world.sim.settings.tol, operator=operator)
    xs, contacts = [], 0
    try:
        for _ in range(int(round(DURATION / scene.world.dt))):
            scene.world.step()
            xs.append(scene.body.positions.copy())
            contacts = max(contacts, sum(int(r.active.sum()) for _, r in scene.world.contact_results.values()))
        sim = scene.world.sim
        pre = sim.solvers.held_preconditioner(scene.body, sim.solvers.solver(scene.body, sim.solver_backend).backend)
        return np.array(xs), contacts, pre
    finally:
        scene.world.close()


@pytest.mark.parametrize("kind, cells", [("tet4", (4, 4, 2)), ("hex8", (4, 4, 2)), ("tet10", (2, 2, 1))])
def test_iterative_and_direct_solves_give_the_same_sheet_trajectory(kind, cells):
    """For both ways the PCG applies A: K' assembled, and matrix-free (FemBody.warped_product), and for
    the default "auto", which switches between them from step to step."""
    direct, contacts, pre_direct = _trajectory(kind, cells, "direct")
    assert pre_direct is None  # the direct run never touched the iterative path
    assert contacts > 0  # the comparison covers the contact solve
    moved = np.abs(direct[-1] - direct[0]).max()
    assert moved > 0.03  # the sheet fell and draped: not a trivial comparison
    for operator in ("assembled", "matrix-free", "auto"):
        iterative, _, pre = _trajectory(kind, cells, "iterative", operator)
        assert pre is not None and pre.iterations > 0  # the fast run really iterated
        assert pre.factorizations < len(iterative)  # reusing its preconditioner, not refactorising every step
        diff = np.abs(direct - iterative).max()
        assert diff < TOL, (f"{kind} {cells} ({operator}): iterative and direct trajectories differ by "
                            f"{diff:.3g} m (> {TOL} m)")


def test_preconditioner_follows_node_rotations_and_frames_exactly():
    """If the system matrix is the factorised one turned by per-node rotations Qrel = Q1 Q0^T (lumped
    mass, so M is unchanged) and the constraint frames are turned with it, the conjugated
    preconditioner C^T P^-1 C is the exact inverse: PCG converges in one iteration, to the direct answer."""
    import softbody
    from scipy.spatial.transform import Rotation
    from softbody.integrator import Constraints, DirectSystem, IterativeSettings, IterativeSystem, Preconditioner
    from softbody.linsolve import SpdSolver
    from softbody.meshing import box_mesh

    body = softbody.FemBody(box_mesh((0.4, 0.3, 0.2), (3, 3, 2), "tet4"), softbody.LinearElastic(1e6, 0.3, 1000.0),
                            mass="lumped")
    n, rng = body.n_nodes, np.random.default_rng(5)
    K0, _ = body.warped_stiffness_blocks(None)
    Q0, Q1 = (Rotation.random(n, random_state=s).as_matrix() for s in (1, 2))
    Qrel = Q1 @ np.swapaxes(Q0, 1, 2)
    p = body.pattern
    K1 = Qrel[p.block_row] @ K0 @ np.swapaxes(Qrel[p.indices], 1, 2)
    nodes = np.array([0, 5, 9])
    T0 = Rotation.random(3, random_state=3).as_matrix()
    mask = np.array([[True, False, False], [True, True, True], [True, False, True]])
    value = rng.standard_normal((3, 3))
    pre = Preconditioner(SpdSolver(p.up_indptr, p.up_indices, body.n_dofs, precision="double"), None, None)
    b = rng.standard_normal((n, 3))
    c_m, c_k = 1.0, 1e-3
    first = IterativeSystem(body, c_m * body.M_blocks + c_k * K0, b, np.zeros((n, 3)), pre, IterativeSettings(tol=1e-10), Q=Q0)
    first.solve(Constraints(nodes, mask, value, T0))
    assert pre.factorizations == 1 and not pre.stale
    turned = IterativeSystem(body, c_m * body.M_blocks + c_k * K1, b, np.zeros((n, 3)), pre, IterativeSettings(tol=1e-10), Q=Q1)
    cons = Constraints(nodes, mask, value, Qrel[nodes] @ T0)
    y, _ = turned.solve(cons)
    assert pre.factorizations == 1 and turned.stats["iterations"] == 1
    solver = SpdSolver(p.up_indptr, p.up_indices, body.n_dofs)
    A1 = c_m * body.M_blocks + c_k * K1
    y_direct, _ = DirectSystem(body, A1, b, solver).solve(cons)
    np.testing.assert_allclose(y, y_direct, rtol=0, atol=1e-9 * np.abs(y_direct).max())


def test_iterative_solve_leaves_the_warm_start_untouched():
    """The warm start (the body's velocities on a step's first solve) is not written into, also when
    the constraint frames are all identity (no frame copy hides the aliasing)."""
    import softbody
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem, Preconditioner
    from softbody.linsolve import SpdSolver
    from softbody.meshing import box_mesh

    body = softbody.FemBody(box_mesh((0.4, 0.3, 0.2), (3, 3, 2), "tet4"), softbody.LinearElastic(1e6, 0.3, 1000.0))
    p, n = body.pattern, body.n_nodes
    K, _ = body.warped_stiffness_blocks(None)
    x0 = np.random.default_rng(6).standard_normal((n, 3))
    before = x0.copy()
    pre = Preconditioner(SpdSolver(p.up_indptr, p.up_indices, body.n_dofs), None, None)
    system = IterativeSystem(body, body.M_blocks + 1e-3 * K, np.zeros((n, 3)), x0, pre, IterativeSettings())
    nodes = np.array([0, 1, 2])
    system.solve(Constraints(nodes, np.ones((3, 3), bool), np.full((3, 3), 7.0), np.broadcast_to(np.eye(3), (3, 3, 3))))
    assert np.array_equal(x0, before)


def _small_system(seed: int = 7):
    import softbody
    from softbody.linsolve import SpdSolver
    from softbody.meshing import box_mesh
    from softbody.preconditioner import Preconditioner

    body = softbody.FemBody(box_mesh((0.4, 0.3, 0.2), (3, 3, 2), "tet4"), softbody.LinearElastic(1e6, 0.3, 1000.0))
    p = body.pattern
    K, _ = body.warped_stiffness_blocks(None)
    pre = Preconditioner(SpdSolver(p.up_indptr, p.up_indices, body.n_dofs, precision="double"), None, None)
    return body, K, pre, np.random.default_rng(seed)


def _direct(body, K, c_m, c_k, b, cons):
    from softbody.integrator import DirectSystem
    from softbody.linsolve import SpdSolver

    p = body.pattern
    y, r = DirectSystem(body, c_m * body.M_blocks + c_k * K, b, SpdSolver(p.up_indptr, p.up_indices, body.n_dofs)).solve(cons)
    return y, r


def test_contact_set_changes_need_no_refactorisation():
    """The factorisation eliminates the supports only; other constrained nodes are removed from the
    preconditioner exactly (Schur complement on cached columns of P^-1). So with the matrix unchanged, a
    solve whose contact set differs from the one at factorisation (a node released, two added, another
    frame) still converges in one iteration, to the direct answer, without refactorising."""
    from scipy.spatial.transform import Rotation
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system()
    body.fix([3])
    n = body.n_nodes
    b = rng.standard_normal((n, 3))
    c_m, c_k = 1.0, 1e-3
    settings = IterativeSettings(tol=1e-10)

    def contacts(nodes, mask, seed):
        frames = Rotation.random(len(nodes), random_state=seed).as_matrix()
        value = rng.standard_normal((len(nodes), 3))
        return Constraints(np.r_[3, nodes], np.r_[[[True] * 3], mask], np.r_[[[0.0] * 3], value],
                           np.r_[[np.eye(3)], frames])

    first = contacts(np.array([0, 5, 9]), np.array([[True, False, False], [True, True, True], [True, False, True]]), 1)
    A = c_m * body.M_blocks + c_k * K
    IterativeSystem(body, A, b, np.zeros((n, 3)), pre, settings).solve(first)
    assert pre.factorizations == 1
    assert pre.eliminated[3] and not pre.eliminated[[0, 5, 9]].any()  # the support only
    changed = contacts(np.array([5, 9, 14, 20]), np.array([[True, True, True], [True, False, False],
                                                            [True, True, True], [True, False, False]]), 2)
    system = IterativeSystem(body, A, b, np.zeros((n, 3)), pre, settings)
    y, r = system.solve(changed)
    assert pre.factorizations == 1 and system.stats["iterations"] == 1
    y_direct, r_direct = _direct(body, K, c_m, c_k, b, changed)
    np.testing.assert_allclose(y, y_direct, rtol=0, atol=1e-9 * np.abs(y_direct).max())
    np.testing.assert_allclose(r, r_direct, rtol=0, atol=1e-8 * np.abs(r_direct).max())


def test_more_contacts_than_the_correction_takes_are_eliminated_in_the_factorisation():
    """Beyond max_corrected_nodes constrained nodes, the factorisation eliminates them all (as a
    direct solve does) and the answer is the direct one."""
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system(8)
    n = body.n_nodes
    b = rng.standard_normal((n, 3))
    nodes = np.array([1, 4, 7, 11])
    cons = Constraints(nodes, np.ones((4, 3), bool), rng.standard_normal((4, 3)))
    system = IterativeSystem(body, body.M_blocks + 1e-3 * K, b, np.zeros((n, 3)), pre,
                             IterativeSettings(tol=1e-10, max_corrected_nodes=2))
    y, _ = system.solve(cons)
    assert pre.factorizations == 1 and pre.eliminated[nodes].all()
    assert system.stats["iterations"] == 1
    y_direct, _ = _direct(body, K, 1.0, 1e-3, b, cons)
    np.testing.assert_allclose(y, y_direct, rtol=0, atol=1e-9 * np.abs(y_direct).max())


def test_a_bad_warm_start_does_not_loosen_the_tolerance():
    """The PCG's tolerance is relative to the load and its terms, not to the initial residual: a warm
    start far off (a stale extrapolation, velocities reset by the user) costs iterations, not accuracy."""
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system(9)
    n = body.n_nodes
    terms = (rng.standard_normal((n, 3)), rng.standard_normal((n, 3)))
    b = terms[0] + terms[1]
    cons = Constraints(np.array([2, 6]), np.ones((2, 3), bool), np.zeros((2, 3)))
    # factorise a stiffer matrix first, so that the preconditioner is not exact for A and PCG iterates
    IterativeSystem(body, 30.0 * body.M_blocks + 1e-3 * K, b, np.zeros((n, 3)), pre, IterativeSettings()).solve(cons)
    A = body.M_blocks + 1e-3 * K
    y_direct, _ = _direct(body, K, 1.0, 1e-3, b, cons)
    free = np.ones((n, 3), bool)
    free[[2, 6]] = False
    settings = IterativeSettings(tol=1e-6, refactor_after=1000)  # keep the inexact factorisation
    for x0 in (np.zeros((n, 3)), 1e4 * rng.standard_normal((n, 3))):
        system = IterativeSystem(body, A, b, x0, pre, settings, terms=terms)
        y, _ = system.solve(cons)
        assert system.stats["iterations"] > 1 and pre.factorizations == 1
        r = (b - (body.pattern.to_bsr(A) @ y.reshape(-1)).reshape(-1, 3))[free]
        scale = max(np.linalg.norm(b[free]), sum(np.linalg.norm(t[free]) for t in terms))
        assert np.linalg.norm(r) <= 1.01 * settings.tol * scale
        np.testing.assert_allclose(y, y_direct, rtol=0, atol=1e-4 * np.abs(y_direct).max())


def test_iterative_settings_are_checked():
    from softbody.errors import InvalidInputError
    from softbody.integrator import IterativeSettings

    for bad in (dict(tol=0.0), dict(tol=2.0), dict(max_iter=0), dict(refactor_after=-1), dict(max_corrected_nodes=-3),
                dict(max_corrected_nodes=2.5), dict(operator="dense"), dict(matrix_free_max_products=-1)):
        with pytest.raises(InvalidInputError, match="IterativeSettings"):
            IterativeSettings(**bad)


def test_auto_operator_is_matrix_free_for_tet10_until_the_products_grow():
    """IterativeSettings.operator "auto": matrix-free for tet10 with warping (FemBody.prefers_matrix_free)
    while the last step took at most matrix_free_max_products products with A and no refactorisation is
    due, assembled otherwise; tet4, hex8 and tet10 without warping assembled; "matrix-free" and
    "assembled" force either. The products are counted: one for the forces, then one per solve (its
    initial residual) and one per PCG iteration."""
    import softbody
    from softbody.integrator import Constraints, IterativeSettings, step_system
    from softbody.solvers import BodySolvers

    fixed = Constraints.full(np.array([0]), np.zeros((1, 3)))
    solvers = BodySolvers()  # what a Simulation keeps per body from step to step

    def step(body, settings):
        solver = solvers.solver(body)
        return step_system(body, 0.01, np.zeros((body.n_nodes, 3)), solver, "iterative", settings,
                           pre=solvers.preconditioner(body, solver))

    def pre_of(body):
        return solvers.preconditioner(body, solvers.solver(body))

    def system(kind, settings, products=None, warping=True):
        body = softbody.FemBody(softbody.box_mesh((0.4, 0.3, 0.2), (2, 2, 1), kind), softbody.LinearElastic(1e6, 0.3, 1000.0),
                                warping=warping)
        if products is not None:  # as if a step had run: factorised, and that many products
            step(body, settings).solve(fixed)
            pre_of(body).products = products
        return body, step(body, settings)

    auto = IterativeSettings()
    assert not system("tet10", auto)[1].matrix_free  # the first step factorises: it needs A anyway
    assert system("tet10", auto, products=auto.matrix_free_max_products)[1].matrix_free
    assert not system("tet10", auto, products=auto.matrix_free_max_products + 1)[1].matrix_free
    assert not system("tet10", auto, products=1, warping=False)[1].matrix_free  # K' assembled once, kept
    assert not system("tet4", auto, products=1)[1].matrix_free and not system("hex8", auto, products=1)[1].matrix_free
    assert system("hex8", IterativeSettings(operator="matrix-free"), products=100)[1].matrix_free
    assert not system("tet10", IterativeSettings(operator="assembled"), products=1)[1].matrix_free
    # a refactorisation due (stale) for a system its PCG solves -> assembled
    body, current = system("tet10", auto, products=1)
    current.solve(fixed)
    pre_of(body).stale = True
    assert not step(body, auto).matrix_free
    # ... unless the last step's system was not solved by its PCG (a coupled solve took it whole): none is due for it;
    # its A is applied matrix-free, its diagonal blocks are the assembled A's, and it is assembled if asked for
    body, taken = system("tet10", auto, products=1)
    pre_of(body).stale = True
    again = step(body, auto)  # (taken not solved)
    op = again.operator
    assert again.matrix_free and op is not None
    y = np.random.default_rng(0).normal(size=(body.n_nodes, 3))
    D, Ay = op.diagonal(), op(y)
    A = again.assemble()
    np.testing.assert_allclose(D, A[body.pattern.diag], rtol=1e-12, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(Ay, body.pattern.product(A, y), rtol=1e-10, atol=1e-10 * np.abs(A).max())
    assert again.operator is None  # assembled: the blocks serve
    again.solve(fixed)
    pre_of(body).stale = True
    assert not step(body, auto).matrix_free  # solved by its PCG again, and stale: assembled
    # the count: 1 (forces) + 1 (initial residual) + the iterations of the one solve
    body, _ = system("tet10", auto, products=1)
    body.positions = body.positions + 1e-3 * np.random.default_rng(0).standard_normal(body.positions.shape)
    moved = step(body, auto)
    assert moved.matrix_free
    before = pre_of(body).iterations
    moved.solve(fixed)
    assert pre_of(body).iterations > before
    assert pre_of(body).products == 2 + pre_of(body).iterations - before


@pytest.mark.parametrize("warping, mass", [(True, "consistent"), (False, "lumped")])
def test_matrix_free_and_assembled_step_systems_agree(warping, mass):
    """The same step (tet10, a bent and moving state) built matrix-free and assembled: the same
    right-hand side, the same products with A, the same A when assembled for a refactorisation, and the
    same solution; also without warping and with lumped mass."""
    import softbody
    from softbody.integrator import Constraints, IterativeSettings, step_system
    from softbody.linsolve import SpdSolver

    rng = np.random.default_rng(7)
    systems = {}
    for op in ("matrix-free", "assembled"):
        body = softbody.FemBody(softbody.box_mesh((0.4, 0.3, 0.2), (2, 2, 1), "tet10"),
                                softbody.LinearElastic(1e6, 0.3, 1000.0), warping=warping, mass=mass)
        gen = np.random.default_rng(8)
        body.positions = body.positions + 0.02 * gen.standard_normal(body.positions.shape)
        body.velocities = 0.1 * gen.standard_normal(body.positions.shape)
        p = body.pattern
        systems[op] = step_system(body, 0.01, np.tile([0.0, 0.0, -9.81], (body.n_nodes, 1)),
                                  SpdSolver(p.up_indptr, p.up_indices, body.n_dofs), "iterative",
                                  IterativeSettings(operator=op, tol=1e-12))
    mf, asm = systems["matrix-free"], systems["assembled"]
    assert mf.matrix_free and not asm.matrix_free
    scale = np.abs(asm.b).max()
    np.testing.assert_allclose(mf.b, asm.b, rtol=0, atol=1e-12 * scale)
    y = rng.standard_normal(asm.b.shape)
    Ay = asm.apply(y)
    np.testing.assert_allclose(mf.apply(y), Ay, rtol=0, atol=1e-12 * np.abs(Ay).max())
    np.testing.assert_allclose(mf.assemble(), asm.assemble(), rtol=0, atol=1e-12 * np.abs(asm.assemble()).max())
    fixed = Constraints.full(np.array([0, 1]), np.zeros((2, 3)))
    v_mf, r_mf = mf.solve(fixed)
    v_asm, r_asm = asm.solve(fixed)
    np.testing.assert_allclose(v_mf, v_asm, rtol=0, atol=1e-9 * np.abs(v_asm).max())
    np.testing.assert_allclose(r_mf, r_asm, rtol=0, atol=1e-9 * np.abs(r_asm).max())


def test_a_refactorisation_is_bought_once_the_iterations_it_saves_have_cost_as_much():
    """The rent-or-buy rule (IterativeSystem._charge): each solve's iterations beyond what a fresh factor needs
    (``refactor_after``) add to the work spent; a refactorisation is due once that reaches its cost
    (Preconditioner.refactor_cost, here set to 40 iterations), not after the first slow solve."""
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system(11)
    n = body.n_nodes
    cons = Constraints(np.array([2, 6]), np.ones((2, 3), bool), np.zeros((2, 3)))
    settings = IterativeSettings(tol=1e-8, refactor_after=2)
    IterativeSystem(body, 30.0 * body.M_blocks + 1e-3 * K, rng.standard_normal((n, 3)), np.zeros((n, 3)), pre,
                    settings).solve(cons)  # factorised for a stiffer matrix: inexact for A below
    pre.refactor_cost = lambda: 40.0
    A = body.M_blocks + 1e-3 * K
    spent, counts = 0.0, []
    while True:
        system = IterativeSystem(body, A, rng.standard_normal((n, 3)), np.zeros((n, 3)), pre, settings)
        system.solve(cons)
        its = system.stats["iterations"]
        assert its > 2  # the old rule (its > refactor_after) would refactorise after each of these
        spent += its - 2
        counts.append(its)
        assert pre.spent == spent and pre.stale == (spent >= 40.0)
        if pre.stale:
            break
        assert len(counts) < 50
    assert len(counts) > 1 and pre.factorizations == 1
    system = IterativeSystem(body, A, rng.standard_normal((n, 3)), np.zeros((n, 3)), pre, settings)
    system.solve(cons)
    assert pre.factorizations == 2 and system.stats["iterations"] <= 2 and pre.spent == 0.0  # fresh: exact for A


def test_backends_count_their_costs_from_the_analysis():
    """PARDISO's costs are its own counts (the factor's nonzeros, at least those of A's upper triangle; the Mflop),
    the block Cholesky's its symbolic analysis's; SuperLU has none (the iteration count then decides alone)."""
    from softbody.linsolve import HAVE_PARDISO, PardisoFactorization, SpdSolver
    from softbody.preconditioner import REFACTOR_HORIZON, Preconditioner

    body, K, _, _ = _small_system()
    p = body.pattern
    data = p.upper_data(body.M_blocks + 1e-3 * K)
    backends = ["blocks", "superlu"] + (["pardiso"] if HAVE_PARDISO else [])
    for backend in backends:
        solver = SpdSolver(p.up_indptr, p.up_indices, body.n_dofs, backend)
        assert solver.costs() is None  # nothing counted before the analysis
        solver.factorize(data)
        costs = solver.costs()
        if backend == "superlu":
            assert costs is None and Preconditioner(solver, None, None).refactor_cost() is None
            continue
        factor, solve = costs
        assert solve >= 4 * len(p.up_indices) - 4 * body.n_dofs  # L holds at least A's lower part
        if backend == "blocks":
            assert factor > 0
        pre = Preconditioner(solver, None, None)
        assert pre.refactor_cost() == max(1.0, factor / solve / REFACTOR_HORIZON)  # in iterations, from the counts
        if backend == "pardiso":  # (its Mflop is a whole number: 0 for this small a system)
            f = solver.factorization
            assert solve == 4.0 * f.factor_nonzeros and factor == 1e6 * f.factor_mflop / PardisoFactorization.FACTOR_SPEEDUP


def test_multigrid_preconditioner_gives_the_direct_trajectory(monkeypatch):
    """Backend "amg" (pyamg's smoothed aggregation, a V-cycle per PCG iteration, contacts projected, no factor; a
    coarsest level of 60 unknowns, so that this small sheet has a real hierarchy): the sheet-on-sphere run through
    contact agrees with the direct solves to the iterative path's tolerance (module docstring), without a set-up
    per solve; it refuses the direct method, and static solves with it are exact."""
    pytest.importorskip("pyamg")
    from softbody import Simulation, solve_static
    from softbody.errors import InvalidInputError
    from softbody.linsolve import AMGFactorization

    monkeypatch.setattr(AMGFactorization, "MAX_COARSE", 60)

    direct, contacts, _ = _trajectory("tet4", (4, 4, 2), "direct")
    assert contacts > 0
    scene = sheet_on_sphere("tet4", (4, 4, 2), solver="amg")
    sim = scene.world.sim
    xs = []
    try:
        for _ in range(len(direct)):
            scene.world.step()
            xs.append(scene.body.positions.copy())
        pre = sim.solvers.held_preconditioner(scene.body, sim.solvers.solver(scene.body, "amg").backend)
        assert pre.solver.backend == "amg" and not pre.solver.exact and pre.iterations > 0
        assert pre.factorizations < len(xs) / 4  # set up again now and then, not for every solve
    finally:
        scene.world.close()
    diff = np.abs(direct - np.array(xs)).max()
    assert diff < TOL, f"multigrid and direct trajectories differ by {diff:.3g} m"
    with pytest.raises(InvalidInputError, match="amg"):
        Simulation(scene.body, 0.01, solver="amg", method="direct")
    body = scene.body
    body.positions = body.rest.copy()
    body.fix(np.flatnonzero(body.rest[:, 0] < body.rest[:, 0].min() + 1e-9))
    np.testing.assert_array_equal(solve_static(body, solver="amg"), solve_static(body, solver="auto"))


def test_a_coarse_tolerance_is_taken():
    """Simulation(tol) above the trial solves' defaults (1e-3 with a factor, 5e-2 with multigrid): the trials take the
    tolerance itself."""
    from softbody import Simulation

    scene = sheet_on_sphere("tet4", (4, 4, 2))
    try:
        sim = Simulation(scene.body, 0.01, tol=0.01)
        assert sim.settings.loose(True) == 0.01 and sim.settings.loose(False) == 0.05
        assert Simulation(scene.body, 0.01, tol=0.1).settings.loose(False) == 0.1
        assert Simulation(scene.body, 0.01).settings.loose(True) == 1e-3
    finally:
        scene.world.close()


def test_auto_preconditioner_is_multigrid_where_the_factor_would_be_large(monkeypatch):
    pytest.importorskip("pyamg")
    import softbody
    from softbody import solvers
    from softbody.linsolve import HAVE_PARDISO

    if not HAVE_PARDISO:
        pytest.skip("the factor's size is PARDISO's count")
    body = softbody.FemBody(softbody.box_mesh((0.4, 0.3, 0.2), (10, 10, 5), "tet4"), softbody.LinearElastic(1e6, 0.3, 1e3))
    monkeypatch.setattr(solvers, "MULTIGRID_MIN_DOFS", 0)
    factor = solvers.new_preconditioner(body, "pardiso").solver
    factor.ORDERINGS = {2: factor.ORDERINGS[2]}  # as "auto" analyses (nested dissection)
    factor.analyse(body.pattern.upper_data(body.M_blocks))
    per_node = factor.factorization.factor_bytes / body.n_nodes  # PARDISO's count
    assert per_node > 0
    # (two analyses in one process may order a little differently: MKL's METIS keeps a random state)
    monkeypatch.setattr(solvers, "MULTIGRID_FACTOR_BYTES", 1.5 * per_node)
    assert solvers.new_preconditioner(body, "auto").solver.backend == "pardiso"
    monkeypatch.setattr(solvers, "MULTIGRID_FACTOR_BYTES", 0.5 * per_node)
    assert solvers.new_preconditioner(body, "auto").solver.backend == "amg"
    assert solvers.new_preconditioner(body, "pardiso").solver.backend == "pardiso"  # named: kept


def test_the_corrections_columns_stay_within_their_cap():
    """With a backend that counts its costs, contacts beyond the correction's reach are projected, not a reason to
    refactorise, and the cached columns never pass Preconditioner.column_cap, however many nodes come and go; the
    answer stays the direct one."""
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system(12)
    pre.refactor_cost = lambda: 1e9  # counted, and never worth a refactorisation here
    n = body.n_nodes
    A = body.M_blocks + 1e-3 * K
    settings = IterativeSettings(tol=1e-10, max_corrected_nodes=6)  # each set within reach, all of them not
    cap = pre.column_cap(6)
    assert cap < 8 * 5
    for trial in range(8):
        nodes = np.sort(rng.choice(n, 5, replace=False))
        cons = Constraints(nodes, np.ones((5, 3), bool), rng.standard_normal((5, 3)))
        b = rng.standard_normal((n, 3))
        y, _ = IterativeSystem(body, A, b, np.zeros((n, 3)), pre, settings).solve(cons)
        assert pre.cached_nodes <= cap and pre.factorizations == 1
        y_direct, _ = _direct(body, K, 1.0, 1e-3, b, cons)
        np.testing.assert_allclose(y, y_direct, rtol=0, atol=1e-8 * np.abs(y_direct).max())


def test_multigrid_is_not_set_up_again_for_its_own_iteration_count(monkeypatch):
    """Multigrid needs more iterations than a fresh factor (its V-cycle approximates A^-1): those are its baseline
    (its own first count after a set-up), not work to buy a new set-up with. The same system solved again and again
    keeps its one set-up."""
    pytest.importorskip("pyamg")
    import softbody
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem
    from softbody.linsolve import AMGFactorization, SpdSolver
    from softbody.preconditioner import Preconditioner

    monkeypatch.setattr(AMGFactorization, "MAX_COARSE", 30)
    body = softbody.FemBody(softbody.box_mesh((1.0, 0.1, 0.1), (40, 3, 3), "tet4"), softbody.LinearElastic(1e6, 0.3, 1e3))
    p, n = body.pattern, body.n_nodes
    K, _ = body.warped_stiffness_blocks(None)
    pre = Preconditioner(SpdSolver(p.up_indptr, p.up_indices, body.n_dofs, "amg"), None, None)
    A = body.M_blocks + 1e-3 * K
    cons = Constraints(np.arange(16), np.ones((16, 3), bool), np.zeros((16, 3)))
    rng = np.random.default_rng(4)
    counts = []
    for _ in range(6):
        system = IterativeSystem(body, A, rng.standard_normal((n, 3)), np.zeros((n, 3)), pre, IterativeSettings())
        system.solve(cons)
        counts.append(system.stats["iterations"])
    assert min(counts) > IterativeSettings().refactor_after + 2  # more than a factor would need
    assert pre.factorizations == 1, counts


def test_a_loose_solve_stops_at_its_own_tolerance():
    """IterativeSystem.solve(loose=True) (an active set's trial) stops at IterativeSettings.loose_tol of the load, a full
    one at tol; both from the same inexact preconditioner."""
    from softbody.integrator import Constraints, IterativeSettings, IterativeSystem

    body, K, pre, rng = _small_system(13)
    n = body.n_nodes
    b = rng.standard_normal((n, 3))
    cons = Constraints(np.array([2, 6]), np.ones((2, 3), bool), np.zeros((2, 3)))
    IterativeSystem(body, 30.0 * body.M_blocks + 1e-3 * K, b, np.zeros((n, 3)), pre, IterativeSettings()).solve(cons)
    A = body.M_blocks + 1e-3 * K
    settings = IterativeSettings(tol=1e-9, loose_tol=1e-2, refactor_after=1000)
    free = np.ones((n, 3), bool)
    free[[2, 6]] = False
    its = {}
    for loose in (True, False):
        system = IterativeSystem(body, A, b, np.zeros((n, 3)), pre, settings)
        y, _ = system.solve(cons, loose=loose)
        r = np.linalg.norm((b - (body.pattern.to_bsr(A) @ y.reshape(-1)).reshape(-1, 3))[free])
        tol = settings.loose_tol if loose else settings.tol
        assert r <= 1.01 * tol * np.linalg.norm(b[free])
        its[loose] = system.stats["iterations"]
    assert its[True] < its[False]


def test_trial_solves_end_on_a_full_solve(monkeypatch):
    """With trial solves forced on for every body (IterativeSystem.trials_pay) and made very loose (a residual of 0.3
    of the load), the node contacts' active set still ends on a full solve: the sheet's trajectory equals the direct
    one to the iterative path's tolerance."""
    from softbody.integrator import IterativeSystem

    direct, contacts, _ = _trajectory("tet4", (4, 4, 2), "direct")
    assert contacts > 0
    monkeypatch.setattr(IterativeSystem, "trials_pay", property(lambda self: True))
    monkeypatch.setattr(IterativeSystem, "solve", _counting(IterativeSystem.solve))
    trials, _, _ = _trajectory("tet4", (4, 4, 2), "iterative")
    assert _counting.loose > 0  # the trials ran
    diff = np.abs(direct - trials).max()
    assert diff < TOL, f"with trial solves the trajectory differs from the direct one by {diff:.3g} m"


def _counting(solve):
    def counted(self, *args, loose=False, **kwargs):
        _counting.loose += bool(loose)
        self.settings.loose_tol = 0.3
        return solve(self, *args, loose=loose, **kwargs)
    _counting.loose = 0
    return counted


@pytest.mark.parametrize("gather", [True, False])
def test_the_correction_is_the_inverse_restricted_to_the_free_directions(gather, monkeypatch):
    """Preconditioner.correction applied to P^-1 g gives (P restricted to the complement of the constrained
    directions)^-1 g, against the dense inverse of that restriction: from a copy of the nodes' own columns (gather) or
    from the product over every cached column (more cached than used: the others' coefficients zero)."""
    from softbody import preconditioner

    body, K, pre, rng = _small_system(5)
    n3 = body.n_dofs
    P = (body.M_blocks + 1e-3 * K)
    up = body.pattern.upper_data(P)
    pre.solver.factorize(up)
    pre.factorized(None, None, np.zeros(body.n_nodes, bool))
    Pd = body.pattern.to_bsr(P).toarray()
    monkeypatch.setattr(preconditioner, "GATHER_BYTES", 2**40 if gather else 0)
    pre.columns(np.arange(body.n_nodes)[::3], cap=body.n_nodes)  # more nodes cached than the correction uses
    nodes = np.array([1, 4, 7, 9])
    mask = np.array([[True, False, False], [True, True, True], [False, True, True], [True, False, True]])
    Q, _ = np.linalg.qr(rng.standard_normal((len(nodes), 3, 3)))  # each node's axes, orthonormal columns
    fix = pre.correction(nodes, mask, Q)
    assert (fix.cols is None) == gather
    E = np.zeros((n3, int(mask.sum())))  # the constrained unit directions, in columns
    for c, (j, i) in enumerate(zip(*np.nonzero(mask))):
        E[3 * nodes[j]:3 * nodes[j] + 3, c] = Q[j, :, i]
    Z = np.linalg.svd(E, full_matrices=True)[0][:, E.shape[1]:]  # an orthonormal basis of their complement
    g = rng.standard_normal(n3)
    expected = Z @ np.linalg.solve(Z.T @ Pd @ Z, Z.T @ g)
    got = fix.apply(pre.solver.solve(g.copy()))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
