"""The coupled step as one convex problem (integration/convex.py): its contact law against finite differences of its
own cost, and its Newton solver against a general-purpose minimiser (scipy's) of the same cost written out densely
here, for soft bodies coupled by rows to each other and to a free rigid body."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize as so

import softbody as sb
from integration import convex
from integration.contact import tangent_frames
from softbody.linsolve import HAVE_PARDISO, SpdSolver
from softbody.solvers import new_solver
from softbody.integrator import step_system


def _random_rows(rng, m):
    vc = rng.normal(size=(m, 3))
    R = np.exp(rng.normal(size=(m, 3)))
    R[:, 2] = R[:, 1]  # isotropic in the tangent plane, as convex.regularization makes it
    v_hat = rng.normal(size=m)
    bound = np.where(rng.random(m) < 0.2, 0.0, np.exp(rng.normal(size=m)))
    bilateral = rng.random(m) < 0.1
    return vc, R, v_hat, bound, bilateral


def test_contact_law_is_the_gradient_and_hessian_of_its_cost():
    """gamma = -d cost / d vc and G = -d gamma / d vc by central differences, at random rows in every regime (apart,
    pushing and sticking, pushing and sliding, frictionless, bilateral); G symmetric positive semi-definite; the
    impulses never pull (unilateral) and never exceed their friction bound."""
    rng = np.random.default_rng(3)
    m = 4000
    vc, R, v_hat, bound, bilateral = _random_rows(rng, m)
    gamma, G, cost, stick = convex.contact_law(vc, R, v_hat, bound, bilateral)
    eps = 1e-7
    for k in range(3):
        step = np.zeros((m, 3))
        step[:, k] = eps
        gp, _, cp, _ = convex.contact_law(vc + step, R, v_hat, bound, bilateral, hessian=False)
        gm, _, cm, _ = convex.contact_law(vc - step, R, v_hat, bound, bilateral, hessian=False)
        scale = 1.0 + np.abs(gamma).max(axis=1)
        # away from the kinks (a regime's boundary within eps), the differences are exact to round-off
        smooth = np.isclose((cp - cm) / (2 * eps), -gamma[:, k], rtol=1e-5, atol=1e-5 * scale)
        assert smooth.mean() > 0.999
        dG = -(gp - gm) / (2 * eps)
        assert (np.abs(dG - G[:, :, k]).max(axis=1) <= 1e-4 * (1.0 + np.abs(G).max(axis=(1, 2)))).mean() > 0.999
    assert np.allclose(G, np.swapaxes(G, 1, 2))
    assert np.linalg.eigvalsh(G).min() >= -1e-9 * np.abs(G).max()
    assert (gamma[~bilateral, 0] >= 0).all()
    assert (np.hypot(gamma[~bilateral, 1], gamma[~bilateral, 2]) <= bound[~bilateral] * (1 + 1e-12) + 1e-15).all()
    # the regimes are all there
    sliding = ~bilateral & (bound > 0) & ~stick & (gamma[:, 0] > 0)
    assert sliding.sum() > 100 and (stick & ~bilateral & (gamma[:, 0] > 0)).sum() > 100 and (gamma[:, 0] == 0).sum() > 100


def _cube(center, kind="tet4"):
    mesh = sb.box_mesh((0.04, 0.04, 0.04), (1, 1, 1), kind, center=center)
    return sb.FemBody(mesh, sb.LinearElastic(2e4, 0.3, 800.0), damping=(0.1, 0.001))


def _problem(rng):
    """Two soft cubes and a free rigid body (6 unknowns) coupled by random rows: node-face rows between the cubes,
    node rows against the rigid body, an attachment, random friction; the lower cube held at two nodes."""
    h = 0.01
    bodies = [_cube((0, 0, 0.02)), _cube((0.005, 0.003, 0.061))]
    parts = []
    for b in bodies:
        b.velocities = 0.05 * rng.normal(size=b.velocities.shape)
        system = step_system(b, h, np.tile([0, 0, -9.81], (b.n_nodes, 1)) * b.node_mass[:, None], new_solver(b),
                             "direct")
        held = np.zeros((b.n_nodes, 3), bool)
        value = np.zeros((b.n_nodes, 3))
        parts.append(convex.SoftPart(b, system.A, system.b, held, value, b.velocities.copy()))
    parts[0].held[[0, 1]] = True
    n = 6
    m = 14
    P, N, W = np.full((m, 4), -1), np.zeros((m, 4), np.int64), np.zeros((m, 4))
    for r in range(m):
        if r < 8:  # node of the upper cube against a point of the lower cube's top
            P[r] = [1, 0, 0, 0]
            N[r] = [rng.integers(8), *rng.choice(8, 3, replace=False)]
            w = rng.dirichlet(np.ones(3))
            W[r] = [1.0, -w[0], -w[1], -w[2]]
        else:  # a node of either against the rigid body
            P[r, 0] = rng.integers(2)
            N[r, 0] = rng.integers(8)
            W[r, 0] = 1.0
    normals = rng.normal(size=(m, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.0
    J = np.zeros((m, 3, n))
    J[8:] = rng.normal(size=(m - 8, 3, n))
    rows = convex.Rows(P, N, W, tangent_frames(normals), 0.1 * rng.normal(size=(m, 3)), J, 0.05 * rng.normal(size=m),
                       rng.uniform(0.0, 0.8, m), np.zeros(m, bool))
    rows.bilateral[-1] = True
    L = rng.normal(size=(n, n))
    M = L @ L.T + n * np.eye(n)
    return parts, rows, M, h


def _dense_cost(parts, rows, M, R, bound):
    """The convex problem's cost and gradient over z = (free soft velocities, du), written out densely: the reference
    for the sparse Newton solver."""
    offs = np.concatenate([[0], np.cumsum([p.body.n_nodes for p in parts])])
    N3 = 3 * offs[-1]
    A = np.zeros((N3, N3))
    b = np.zeros(N3)
    for p, o in zip(parts, offs[:-1]):
        Ab = p.body.pattern.to_csr(p.A).toarray()
        A[3 * o:3 * o + Ab.shape[0], 3 * o:3 * o + Ab.shape[0]] = Ab
        b[3 * o:3 * o + Ab.shape[0]] = p.b.ravel()
    held = np.concatenate([p.held.ravel() for p in parts])
    value = np.concatenate([p.value.ravel() for p in parts])
    free = ~held
    m, n = len(rows), len(M)
    Js = np.zeros((m, 3, N3))
    for r in range(m):
        for s in range(rows.parts.shape[1]):
            if rows.parts[r, s] < 0:
                continue
            g = 3 * (offs[rows.parts[r, s]] + rows.nodes[r, s])
            Js[r, :, g:g + 3] += rows.weights[r, s] * rows.frames[r].T
    Jr = -np.einsum("rji,rjn->rin", rows.frames, rows.jacobian)
    c = -np.einsum("rji,rj->ri", rows.frames, rows.rigid_velocity)

    def split(z):
        V = value.copy()
        V[free] = z[:free.sum()]
        return V, z[free.sum():]

    def f(z):
        V, du = split(z)
        vc = Js @ V + Jr @ du + c
        yn = (rows.v_hat - vc[:, 0]) / R[:, 0]
        gn = np.where(rows.bilateral, yn, np.maximum(yn, 0.0))
        cost = 0.5 * V @ A @ V - b @ V + 0.5 * du @ M @ du + 0.5 * np.sum(R[:, 0] * gn ** 2)
        vt = vc[:, 1:]
        speed = np.linalg.norm(vt, axis=1)
        stick = rows.bilateral | (speed / R[:, 1] <= bound)
        gt = np.where(stick[:, None], -vt / R[:, 1:], -bound[:, None] * vt / np.maximum(speed, 1e-300)[:, None])
        cost += np.sum(np.where(stick, 0.5 * R[:, 1] * (gt ** 2).sum(axis=1), bound * speed - 0.5 * R[:, 1] * bound ** 2))
        gamma = np.column_stack([gn, gt])
        grad_V = A @ V - b - np.einsum("rin,ri->n", Js, gamma)
        grad_u = M @ du - np.einsum("rin,ri->n", Jr, gamma)
        return cost, np.concatenate([grad_V[free], grad_u])

    def z0():
        return np.concatenate([np.concatenate([p.guess.ravel() for p in parts])[free], np.zeros(n)])

    return f, z0, split


def test_newton_finds_the_minimiser_a_general_solver_finds():
    """The sparse Newton solve of two soft bodies and a rigid body coupled by random rows (cross-body blocks, rigid
    Schur complement, supports, friction, an attachment) reaches the minimum that scipy's L-BFGS finds for the same
    cost written out densely (with the friction bounds the solver ended on), to the tolerance of the comparison."""
    rng = np.random.default_rng(11)
    parts, rows, M, h = _problem(rng)
    solver = convex.ConvexSolver(rel_tol=1e-12)
    sol = solver.solve(parts, rows, M, h)
    assert sol.converged and sol.iterations >= 2
    newton = convex._Newton(solver, parts, rows, M, h)
    bound = rows.mu * sol.gamma[:, 0]  # the friction bounds of the final round (Coulomb at the fixed point)
    f, z0, split = _dense_cost(parts, rows, M, newton.R, bound)
    ref = so.minimize(f, z0(), jac=True, method="L-BFGS-B", options={"maxiter": 20000, "ftol": 1e-16, "gtol": 1e-12})
    V_ref, du_ref = split(ref.x)
    V = np.concatenate(sol.velocities).ravel()
    # no higher than the reference's minimum, the points agree as far as the (stiff) reference resolves them, and
    # the dense gradient vanishes at the solution: the minimum of a convex function
    z = np.concatenate([V[np.concatenate([~p.held.ravel() for p in parts])], sol.du])
    cost, grad = f(z)
    assert cost <= ref.fun + 1e-9 * abs(ref.fun)
    assert np.abs(V - V_ref).max() < 1e-4 and np.abs(sol.du - du_ref).max() < 1e-4
    assert np.abs(grad).max() < 1e-7 * np.abs(f(z0())[1]).max()
    # supports stay as prescribed
    assert np.array_equal(sol.velocities[0][parts[0].held], parts[0].value[parts[0].held])


def test_friction_is_lagged_to_coulombs_law():
    """At the solution each row's tangential impulse is within mu times its own normal impulse (not merely the lagged
    bound), and sliding rows slide against their impulse (maximal dissipation)."""
    rng = np.random.default_rng(5)
    parts, rows, M, h = _problem(rng)
    sol = convex.ConvexSolver().solve(parts, rows, M, h)
    g = sol.gamma
    unilateral = ~rows.bilateral
    gt = np.hypot(g[:, 1], g[:, 2])
    cone = rows.mu[unilateral] * g[unilateral, 0]
    assert (gt[unilateral] <= cone + 2 * convex.LAG_TOL * cone.max()).all()  # the solver's tolerance: of the largest
    sliding = unilateral & ~sol.stiction & (g[:, 0] > 0) & (rows.mu > 0)
    assert (np.einsum("mi,mi->m", sol.vc[sliding, 1:], g[sliding, 1:]) <= 1e-12).all()


def test_a_kept_factorisation_solves_the_next_steps_alike():
    """The same problem solved twice by one solver: the second time (mostly) by conjugate gradients preconditioned by
    the first solve's factorisation (Factor), to the same velocities within the Newton tolerance."""
    rng = np.random.default_rng(7)
    parts, rows, M, h = _problem(rng)
    solver = convex.ConvexSolver(rel_tol=1e-12, reuse_min=0, reuse_min_soft=0)  # a small problem: reused all the same
    first = solver.solve(parts, rows, M, h)
    second = solver.solve(parts, rows, M, h)
    factor = next(iter(solver.patterns._held.values())).factor
    assert factor.reused > 0 and factor.iterations > 0
    for a, b in zip(first.velocities, second.velocities):
        assert np.abs(a - b).max() < 1e-9
    # the conjugate gradients' direction comes with A dV summed from their products: A's product of the direction (at
    # the solution, where the kept factorisation serves, for any right-hand side)
    newton = convex._Newton(solver, parts, rows, M, h)
    sol = newton.run()
    _, _, G, *_ = newton._evaluate(np.concatenate(sol.velocities), sol.du)
    gV = np.where(~newton.held, rng.normal(size=(newton.N, 3)), 0.0)
    dV, ddu, AdV = newton._direction(newton.group, G, gV, rng.normal(size=newton.n))
    assert AdV is not None  # (by the conjugate gradients)
    np.testing.assert_allclose(AdV, newton._A_products(dV), rtol=1e-10, atol=1e-12 * np.abs(AdV).max())


def test_sliding_rows_do_not_lift_off_beyond_glide_tol(monkeypatch):
    """Castro et al.'s cone lifts a sliding row off its surface by about mu |v_t| h; where that passes GLIDE_TOL the
    solve refines the rows by Coulomb's law, after which a sliding row's normal velocity is at most its target
    (non-penetration without gliding). With the refinement turned off the cone's lift-off shows."""
    rng = np.random.default_rng(3)
    parts, rows, M, h = _problem(rng)

    def lift_off(sol):
        sliding = (rows.mu > 0) & ~rows.bilateral & ~sol.stiction & (sol.gamma[:, 0] > 0)
        assert sliding.sum() >= 2
        return float(((sol.vc[:, 0] - rows.v_hat) * h)[sliding].max())

    tol = convex.GLIDE_TOL
    refined = convex.ConvexSolver().solve(parts, rows, M, h)
    assert refined.rounds > 1 and lift_off(refined) <= tol
    monkeypatch.setattr(convex, "GLIDE_TOL", np.inf)  # the cone's solution as it is
    cone = convex.ConvexSolver().solve(parts, rows, M, h)
    assert cone.rounds == 1 and lift_off(cone) > 10 * tol


def test_box_law_is_the_gradient_of_its_cost():
    """The joint rows' law (motors, limits, equalities): gamma = -d cost / d y and the curvature d^2 cost / dy^2 by
    central differences, in every regime (within the bounds, at the upper and at the lower bound, a one-sided row
    apart, unbounded rows); the impulses never leave their bounds."""
    rng = np.random.default_rng(13)
    k = 3000
    y, target = rng.normal(size=k), rng.normal(size=k)
    R = np.exp(rng.normal(size=k))
    kind = rng.integers(3, size=k)  # 0: a motor (-F h, F h), 1: a limit (0, inf), 2: an equality (-inf, inf)
    F = np.exp(rng.normal(size=k))
    lo = np.where(kind == 0, -F, np.where(kind == 1, 0.0, -np.inf))
    hi = np.where(kind == 0, F, np.inf)
    gamma, curvature, cost = convex.box_law(y, R, target, lo, hi)
    eps = 1e-7
    gp, cp_, costp = convex.box_law(y + eps, R, target, lo, hi)
    gm, cm_, costm = convex.box_law(y - eps, R, target, lo, hi)
    away = np.isclose((costp - costm) / (2 * eps), -gamma, rtol=1e-5, atol=1e-6)
    assert away.mean() > 0.999
    assert (np.abs(-(gp - gm) / (2 * eps) - curvature) <= 1e-4 * (1 + curvature)).mean() > 0.999
    assert (gamma >= lo).all() and (gamma <= hi).all() and np.isfinite(cost).all() and (cost >= 0).all()
    assert ((gamma == F) & (kind == 0)).sum() > 100 and ((gamma == -F) & (kind == 0)).sum() > 100
    assert ((gamma == 0) & (kind == 1)).sum() > 100 and (curvature[kind == 2] > 0).all()


def _joint_rows(rng, n, k=6):
    """Random scalar rows on n rigid unknowns: motors (tight force limits, so that some saturate), limits and an
    equality."""
    C = rng.normal(size=(k, n))
    F = np.exp(rng.normal(size=k) - 3.0)
    kind = np.arange(k) % 3
    return convex.JointRows(C, 0.2 * rng.normal(size=k), 0.2 * rng.normal(size=k),
                            np.where(kind == 0, -F, np.where(kind == 1, 0.0, -np.inf)), np.where(kind == 0, F, np.inf))


def test_joint_rows_join_the_coupled_minimum():
    """Motors, limits and an equality on the rigid unknowns of the random coupled problem: the sparse Newton solve
    reaches the minimum scipy's L-BFGS finds for the dense cost with their costs added, and each row's impulse obeys
    its law at the solution (a motor within its force limit, at the limit only where its target is not reached)."""
    rng = np.random.default_rng(17)
    parts, rows, M, h = _problem(rng)
    joints = _joint_rows(rng, len(M))
    solver = convex.ConvexSolver(rel_tol=1e-12)
    sol = solver.solve(parts, rows, M, h, joints)
    assert sol.converged
    newton = convex._Newton(solver, parts, rows, M, h, joints)
    f0, z0, _ = _dense_cost(parts, rows, M, newton.R, rows.mu * sol.gamma[:, 0])
    n = len(M)

    def f(z):
        cost, grad = f0(z)
        du = z[-n:]
        g, _, c = convex.box_law(joints.free + joints.coefficients @ du, newton.Rj, joints.target, joints.lo, joints.hi)
        grad = grad.copy()
        grad[-n:] -= joints.coefficients.T @ g
        return cost + c.sum(), grad

    # the near-rigid joint rows make the dense cost too stiff for L-BFGS to resolve the point (it stops at its
    # evaluation limit short of it): the minimum is where the dense gradient vanishes, and no lower cost is found
    ref = so.minimize(f, z0(), jac=True, method="L-BFGS-B", options={"maxiter": 20000, "ftol": 1e-16, "gtol": 1e-12})
    V = np.concatenate(sol.velocities).ravel()
    z = np.concatenate([V[np.concatenate([~p.held.ravel() for p in parts])], sol.du])
    cost, grad = f(z)
    assert cost <= ref.fun + 1e-9 * abs(ref.fun)
    assert np.abs(grad).max() < 1e-6 * np.abs(f(z0())[1]).max()
    y = joints.free + joints.coefficients @ sol.du
    g = sol.joint_gamma
    assert (g >= joints.lo - 1e-15).all() and (g <= joints.hi + 1e-15).all()
    inside = (g > joints.lo) & (g < joints.hi)
    assert np.allclose(y[inside], (joints.target - newton.Rj * g)[inside], atol=1e-9)  # near rigid: on target
    assert (np.abs(g[inside]) * newton.Rj[inside] < 1e-3).all()
    saturated = np.isfinite(joints.hi) & (np.abs(g) == joints.hi)
    assert saturated.any() and (np.sign(joints.target - y)[saturated] == np.sign(g[saturated])).all()


def test_a_motor_alone_reaches_its_target_or_pushes_with_its_limit():
    """No soft part: a body of mass m (one unknown) moving at u_free, a motor driving it to v*: within its force
    limit it reaches v* (to the near-rigid regularisation), beyond it the velocity changes by exactly F h / m."""
    m, h = 2.0, 0.01
    for F, expect in ((1e3, 0.5), (10.0, 0.1 + 10.0 * h / m)):
        joints = convex.JointRows(np.ones((1, 1)), np.array([0.1]), np.array([0.5]), np.array([-F * h]),
                                  np.array([F * h]))
        rows = convex.Rows.concat([], 1)
        sol = convex.ConvexSolver().solve([], rows, np.array([[m]]), h, joints)
        assert sol.converged
        assert abs(0.1 + sol.du[0] - expect) < 1e-3 * expect
        assert abs(sol.joint_gamma[0] - m * sol.du[0]) < 1e-9 * abs(sol.joint_gamma[0])  # the impulse is the momentum


def test_group_pattern_equals_the_pattern_of_all_its_blocks_as_elements():
    """GroupPattern.of merges the extra blocks into its parts' sorted patterns (BlockPattern.from_keys): the same
    pattern as BlockPattern.from_elements of every block (and its mirror) as a 2-node element, field by field, and
    each part's blocks mapped onto it."""
    from softbody.assembly import BlockPattern

    rng = np.random.default_rng(3)
    meshes = [sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), kind) for kind in ("tet4", "tet10", "hex8")]
    patterns = [sb.FemBody(m, sb.LinearElastic(1e5, 0.3, 1000.0)).pattern for m in meshes]
    offsets = np.concatenate([[0], np.cumsum([p.n_nodes for p in patterns])])
    N = int(offsets[-1])
    i, j = rng.integers(0, N, 40), rng.integers(0, N, 40)
    extra = np.unique(np.column_stack([np.minimum(i, j), np.maximum(i, j)])[i != j], axis=0)
    group = convex.GroupPattern.of(patterns, extra, "auto")
    rows = np.concatenate([p.block_row + o for p, o in zip(patterns, offsets[:-1])] + [extra[:, 0], extra[:, 1]])
    cols = np.concatenate([p.indices + o for p, o in zip(patterns, offsets[:-1])] + [extra[:, 1], extra[:, 0]])
    pairs = np.column_stack([rows, cols])
    want = BlockPattern.from_elements(np.concatenate([pairs, pairs[:, ::-1]]), N)
    for name in ("indptr", "indices", "diag", "mirror", "block_row", "up_indptr", "up_indices", "up_gather", "up_row",
                 "up_col", "up_diag"):
        np.testing.assert_array_equal(getattr(group.pattern, name), getattr(want, name), err_msg=name)
    for p, o, where in zip(patterns, offsets[:-1], group.maps):
        np.testing.assert_array_equal(group.pattern.block_row[where], p.block_row + o)
        np.testing.assert_array_equal(group.pattern.indices[where], p.indices + o)
    assert group.holds(extra) and group.holds(extra[:, ::-1])
    # a block beyond the pattern is not held, also right after the same keys but that one were found held (holds_keys
    # keeps the last keys it found held)
    outside = np.setdiff1d(np.arange(N * N), group.keys)[:3]
    asked = np.concatenate([group.keys[::7], group.keys[:5]])
    assert group.holds_keys(asked) and group.holds_keys(asked)
    for k in outside:
        changed = asked.copy()
        changed[len(changed) // 2] = k
        assert not group.holds_keys(changed)
        assert not group.holds_keys(np.append(asked, k))
    assert group.holds_keys(asked[::-1]) and not group.holds_keys(outside)


@pytest.mark.skipif(not HAVE_PARDISO, reason="PARDISO (pypardiso / MKL) not installed: no orderings to choose")
def test_a_pattern_made_anew_keeps_its_ordering_and_a_saved_one_comes_back_alike():
    """GroupPatterns: a pattern made anew for the same bodies (contacts beyond the kept one) is analysed with the
    ordering the kept one's analysis chose, the one ordering; a saved pattern comes back with its blocks, its
    ordering and its factorisation (the same values again)."""
    patterns = convex.GroupPatterns("pardiso")
    meshes = [sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet4", center=(0.0, 0.0, 0.1 * k)) for k in range(2)]
    bodies = tuple(sb.FemBody(m, sb.LinearElastic(1e5, 0.3, 1000.0)) for m in meshes)
    n0 = bodies[0].n_nodes
    first = patterns.get(bodies, np.array([[0, n0]]))
    solver = first.solver
    K = first.pattern
    values = np.where(K.up_row == K.up_col, 10.0, 0.0) + 1e-3 * (K.up_row != K.up_col)  # diagonally dominant: SPD
    solver.factorize(values)
    first.factor = convex.Factor(values, np.zeros((K.n_nodes, 3), bool))
    chosen = solver.ordering
    assert chosen is not None and patterns.get(bodies, np.array([[0, n0]])) is first  # within it: kept
    second = patterns.get(bodies, np.array([[1, n0 + 1]]))  # beyond it: made anew, with both pairs
    assert second is not first and second.holds(np.array([[0, n0], [1, n0 + 1]]))
    assert list(second.solver.ORDERINGS.values()) == [chosen]
    # the first pattern saved (a set holding only it) and made again
    again = convex.GroupPatterns("pardiso")
    again._held = {bodies: first}
    state = again.save_state({b: k for k, b in enumerate(bodies)}.get)
    loaded = convex.GroupPatterns("pardiso")
    loaded.load_state(state, lambda k: bodies[k])
    back = loaded._held[bodies]
    np.testing.assert_array_equal(back.extra, first.extra)
    assert list(back.solver.ORDERINGS.values()) == [chosen] and back.solver.ordering == chosen
    np.testing.assert_array_equal(back.factor.values, values)
    b = np.arange(3.0 * K.n_nodes)
    np.testing.assert_array_equal(back.solver.solve(b), first.solver.solve(b))
    # states saved before the ordering was kept (no third entry, or an array of blocks there) load with the solver's
    # own choice of ordering
    for old in ((first.extra, None), (first.extra, None, first.extra.copy())):
        loaded.load_state({(0, 1): old}, lambda k: bodies[k])
        assert len(loaded._held[bodies].solver.ORDERINGS) == len(SpdSolver.ORDERINGS)


@pytest.mark.skipif(not convex.kernels.ENABLED, reason="numba not installed")
def test_the_row_kernels_equal_their_numpy_twins(monkeypatch):
    """integration.kernels' row-by-row arithmetic of the convex solve against convex.py's numpy code on the problem of
    _problem (held components, slots over two bodies, a rigid side): the Delassus estimates, the cone law in every
    regime (impulses, Hessians, costs, stiction), the products of the slots' weights with row and node quantities,
    and the node pairs the rows join."""
    rng = np.random.default_rng(5)
    parts, rows, M, h = _problem(rng)
    newton = convex._Newton(convex.ConvexSolver(), parts, rows, M, h)
    kernels = convex.kernels
    f = rng.normal(size=(len(rows), 7))
    X = rng.normal(size=(newton.N, 5))
    V = rng.normal(size=(newton.N, 3))
    G = rng.normal(size=(len(rows), 3, 3))
    soft_only = convex._Newton(convex.ConvexSolver(), parts, rows, None, h)  # (the rows' velocities without du)

    def products():
        newton._fgf = None
        return (newton._delassus_diagonal(), newton._to_nodes(f), newton._at_rows(X), newton._frame_hessians(G),
                soft_only.velocities(V, np.zeros(0)), newton._extra_pairs())

    compiled = products()
    monkeypatch.setattr(kernels, "ENABLED", False)
    reference = products()
    np.testing.assert_allclose(compiled[0], reference[0], rtol=1e-12)
    for a, b in zip(compiled[1:5], reference[1:5]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * np.abs(b).max())
    assert np.array_equal(compiled[5], reference[5]) and len(reference[5])
    # the cone law on random rows in every regime
    vc, R, v_hat, bound, bilateral = _random_rows(rng, 4000)
    mu = np.where(rng.random(4000) < 0.2, 0.0, rng.uniform(0.1, 1.0, 4000))
    want = convex.cone_law(vc, R, v_hat, mu, bilateral)
    monkeypatch.setattr(kernels, "ENABLED", True)
    got = convex._compiled_cone_law(vc, R, v_hat, mu, bilateral)
    for a, b in zip(got[:3], want[:3]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * np.abs(b).max())
    assert np.array_equal(got[3], want[3])
    slide = ~want[3] & (np.abs(want[0][:, 1:]).sum(axis=1) > 0)
    assert want[3].sum() > 100 and slide.sum() > 100 and (want[0][:, 0] == 0).sum() > 100
    assert convex._compiled_cone_law(vc, R, v_hat, mu, bilateral, hessian=False)[1] is None
