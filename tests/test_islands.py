"""The coupled problem split into islands (integration/islands.py): which bodies an island holds, a stack's members as
the bodies they are, and the islands' minima together the minimum of the whole problem."""
from __future__ import annotations

import dataclasses

import numpy as np

import softbody as sb
from integration import convex
from integration.contact import ContactSolver, tangent_frames
from integration.islands import Islands, components
from softbody.integrator import step_system
from softbody.solvers import new_solver
from softbody.stack import BodyStack

H = 0.01


def _cube(center, kind="tet4"):
    mesh = sb.box_mesh((0.04, 0.04, 0.04), (1, 1, 1), kind, center=center)
    return sb.FemBody(mesh, sb.LinearElastic(2e4, 0.3, 800.0), damping=(0.1, 0.001))


def _part(body, rng):
    body.velocities = 0.05 * rng.normal(size=body.velocities.shape)
    f = np.tile([0.0, 0.0, -9.81], (body.n_nodes, 1)) * body.node_mass[:, None]
    system = step_system(body, H, f, new_solver(body), "direct")
    return convex.SoftPart(body, system.A, system.b, np.zeros((body.n_nodes, 3), bool), np.zeros((body.n_nodes, 3)),
                           body.velocities.copy())


def _problem(rng, kind="tet4"):
    """Four cubes stepped as one BodyStack and a free rigid body (6 unknowns): rows join members 0 and 1 (node
    against face), member 2 and the rigid body, and hold member 3 against a fixed surface; member 0 is held at a
    node. Three islands: {0, 1}, {2, rigid}, {3}."""
    members = [_cube((0.1 * k, 0.0, 0.02), kind) for k in range(4)]
    stack = BodyStack(members)
    part = _part(stack, rng)
    part.held[0] = True
    off = stack.offsets
    n = 6
    specs = []  # (slots [(member, node, weight)], rigid)
    for _ in range(4):  # member 1's node against a point of member 0's face
        w = rng.dirichlet(np.ones(3))
        specs.append(([(1, rng.integers(8), 1.0)] + [(0, k, -wk) for k, wk in zip(rng.choice(8, 3, replace=False), w)],
                      False))
    specs += [([(2, rng.integers(8), 1.0)], True) for _ in range(3)]
    specs += [([(3, rng.integers(8), 1.0)], False) for _ in range(2)]
    m = len(specs)
    P, N, W = np.full((m, 4), -1), np.zeros((m, 4), np.int64), np.zeros((m, 4))
    J = np.zeros((m, 3, n))
    for r, (slots, rigid) in enumerate(specs):
        for s, (member, node, w) in enumerate(slots):
            P[r, s], N[r, s], W[r, s] = 0, off[member] + node, w
        if rigid:
            J[r] = rng.normal(size=(3, n))
    normals = rng.normal(size=(m, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.0
    rows = convex.Rows(P, N, W, tangent_frames(normals), 0.1 * rng.normal(size=(m, 3)), J, 0.05 * rng.normal(size=m),
                       rng.uniform(0.0, 0.8, m), np.zeros(m, bool))
    L = rng.normal(size=(n, n))
    return members, [part], rows, L @ L.T + n * np.eye(n)


def test_islands_hold_what_rows_join_and_a_members_blocks_are_its_own():
    rng = np.random.default_rng(2)
    members, parts, rows, M = _problem(rng)
    islands = Islands.of(parts, rows, True)
    held = [(island.units.tolist(), island.rows.tolist(), island.rigid) for island in islands.islands]
    assert held == [([0, 1], [0, 1, 2, 3], False), ([2], [4, 5, 6], True), ([3], [7, 8], False)]
    # a member's unit: the stack's rows of its nodes, its block data the member's own system's (stepped alone)
    for k, (member, unit) in enumerate(zip(members, islands.units)):
        alone = _part(member, np.random.default_rng(0))
        member.velocities = parts[0].body.velocities[parts[0].body.rows(k)]
        alone = step_system(member, H, np.tile([0.0, 0.0, -9.81], (member.n_nodes, 1)) * member.node_mass[:, None],
                            new_solver(member), "direct")
        assert unit.body is member
        np.testing.assert_allclose(unit.A, alone.A, rtol=1e-12, atol=1e-12 * np.abs(alone.A).max())
        np.testing.assert_allclose(unit.b, alone.b, rtol=1e-12, atol=1e-12 * np.abs(alone.b).max())
    sub_parts, sub_rows = islands.problem(islands.islands[0], rows)
    assert [p.body for p in sub_parts] == members[:2]
    assert np.array_equal(sub_rows.parts[0], [1, 0, 0, 0]) and np.array_equal(sub_rows.nodes, rows.nodes[:4]
                                                                              - np.where(sub_rows.parts == 1,
                                                                                         members[0].n_nodes, 0))


def test_the_islands_minima_are_the_minimum_of_the_whole_problem():
    """Solved island by island (ContactSolver._solve_islands) and as one problem (convex.ConvexSolver), to tight
    tolerances (Newton's, and Coulomb's law between the lagged friction bounds and the impulses): the same velocities,
    rigid velocity change and impulses; each island converged."""
    rng = np.random.default_rng(4)
    _, parts, rows, M = _problem(rng)
    tight = dict(rel_tol=1e-12, lag_tol=1e-12, lag_rounds=200)
    whole = convex.ConvexSolver(**tight).solve(parts, rows, M, H)
    solver = ContactSolver()
    solver.convex = convex.ConvexSolver(**tight)
    split = solver._solve_islands(parts, rows, M, H, None, None)
    assert whole.converged and split.converged
    assert len(solver.convex.patterns._held) == 3  # each island its own pattern
    scale = np.abs(whole.velocities[0]).max()
    assert np.abs(split.velocities[0] - whole.velocities[0]).max() < 1e-7 * scale
    assert np.abs(split.du - whole.du).max() < 1e-7 * np.abs(whole.du).max()
    assert np.abs(split.gamma - whole.gamma).max() < 1e-6 * np.abs(whole.gamma).max()
    assert np.array_equal(split.velocities[0][parts[0].held], parts[0].value[parts[0].held])


def test_a_pattern_no_island_asks_for_is_let_go():
    """GroupPatterns.forget_idle: the islands' patterns stay while asked for, and go IDLE solves after the last ask."""
    rng = np.random.default_rng(6)
    _, parts, rows, M = _problem(rng)
    solver = ContactSolver()
    solver._solve_islands(parts, rows, M, H, None, None)
    patterns = solver.convex.patterns
    assert len(patterns._held) == 3
    for _ in range(patterns.IDLE - 1):  # (the solve above counted one)
        patterns.forget_idle()
    assert len(patterns._held) == 3
    patterns.forget_idle()
    assert not patterns._held


def test_a_world_of_islands_continues_from_its_saved_state_to_the_bit():
    """Two stacked pairs of cubes far apart (one stack, two islands of its members): saved while settling, the run
    continued, restored and continued again gives the same positions to the bit; the islands' patterns are saved
    by their members' handles."""
    from integration.world import World

    def cube(center):
        return sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=center),
                          sb.LinearElastic(5e5, 0.33, 1000.0))

    world = World(dt=0.01)
    world.add_plane()
    cubes = [cube((0.0, 0.0, 0.051)), cube((0.5, 0.0, 0.051)), cube((0.0, 0.0, 0.16)), cube((0.5, 0.0, 0.16))]
    for b in cubes:
        world.add_soft(b, friction=0.5)

    def run(steps):
        for _ in range(steps):
            world.step()
        return np.concatenate([b.positions for b in cubes])

    run(25)
    state = world.save_state()
    assert sorted(state.patterns) == [((0,), (2,)), ((1,), (3,))]  # each island's pattern, by its members' handles
    first = run(15)
    world.restore_state(state)
    assert np.array_equal(run(15), first)


def test_components_are_scipys_connected_components():
    """islands.components (union-find over the distinct edges) labels each node by the smallest node of its component:
    the partition scipy's connected components finds, on random graphs with repeated, mirrored and self edges."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(4)
    for count in (1, 2, 7, 40, 200):
        for density in (0.0, 0.3, 1.0, 3.0):
            k = int(density * count)
            a, b = rng.integers(0, count, k), rng.integers(0, count, k)
            a, b = np.concatenate([a, b[: k // 3]]), np.concatenate([b, a[: k // 3]])  # some mirrored
            label = components(count, a, b)
            _, want = connected_components(csr_matrix((np.ones(len(a)), (a, b)), shape=(count, count)),
                                           directed=False)
            same = want[:, None] == want[None]
            np.testing.assert_array_equal(label[:, None] == label[None], same)
            np.testing.assert_array_equal(label, [np.flatnonzero(same[x])[0] for x in range(count)])


def test_a_stack_applied_without_assembling_its_matrix_solves_as_assembled():
    """A stack's system given as its matrix-free operator (softbody.integrator.WarpedOperator: A y by the rotated
    gradients, its diagonal blocks likewise, the blocks assembled only for a factorisation) and as assembled blocks:
    island by island (each member its own operator, a slice of the stack's gradients) and whole, the same velocities
    and impulses to Newton's tolerance; a solve served by the kept factorisations (conjugate gradients) never
    assembles it."""
    from softbody.integrator import WarpedOperator

    rng = np.random.default_rng(6)
    _, parts, rows, M = _problem(rng, "tet10")
    p = parts[0]
    stack = p.body
    axes = rng.normal(size=(stack.mesh.n_elements, 3))
    R = np.array([_rotation(a, 0.2 * np.linalg.norm(a)) for a in axes])  # each element turned up to ~0.5 rad
    c_m, c_k = 1.0 + H * stack.damping[0], H * stack.damping[1] + H * H
    blocks = stack.system_blocks(stack.warped_stiffness_upper(R)[0], c_m, c_k)

    def assembled(guess=p.guess):
        return convex.SoftPart(stack, blocks, p.b, p.held, p.value, guess)

    def matrix_free(guess=p.guess):
        return convex.SoftPart(stack, lambda: stack.system_blocks(stack.warped_stiffness_upper(R)[0], c_m, c_k),
                               p.b, p.held, p.value, guess, WarpedOperator(stack, stack.rotated_gradients(R), c_m, c_k))

    units = Islands.of([matrix_free()], rows, True).units
    assert all(isinstance(u.operator, WarpedOperator) and u.operator.body is m for u, m in zip(units, stack.members))
    tight = dict(rel_tol=1e-12, lag_tol=1e-12, lag_rounds=200, reuse_min=0, reuse_min_soft=0)
    frictionless = dataclasses.replace(rows, mu=np.zeros(len(rows)))  # (no lagged rounds: the kept factor serves)
    out = {}
    for name, make in (("assembled", assembled), ("matrix-free", matrix_free)):
        solver = ContactSolver()
        solver.convex = convex.ConvexSolver(**tight)
        first = solver._solve_islands([assembled()], frictionless, M, H, None, None)  # patterns, factorisations kept
        part = make(first.velocities[0])
        again = solver._solve_islands([part], frictionless, M, H, None, first.du)  # from its solution: served by them
        out[name] = (first, again, convex.ConvexSolver(**tight).solve([make()], rows, M, H))
        if name == "matrix-free":
            assert callable(part.A) and again.factorizations == 0  # never assembled
    for k in range(3):
        a, f = out["assembled"][k], out["matrix-free"][k]
        assert a.converged and f.converged
        assert np.abs(f.velocities[0] - a.velocities[0]).max() < 1e-8 * np.abs(a.velocities[0]).max()
        assert np.abs(f.gamma - a.gamma).max() < 1e-7 * np.abs(a.gamma).max()


def _rotation(axis, angle):
    """The rotation by ``angle`` about ``axis`` (3,) (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K
