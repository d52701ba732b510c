"""Soft bodies stepped as one block-diagonal system (softbody.stack, World(stack=True)) against each body
stepped alone: the same trajectories to the solver's tolerance, the same contact forces, the user's own
changes to a body's state and supports between steps kept."""
import numpy as np
import pytest

import geometry as geo

from softbody import FemBody, LinearElastic, Simulation, box_mesh
from softbody.errors import InvalidInputError
from softbody.stack import BodyStack

from experiments.scenes import cubes_on_plane
from integration.world import World


def _cube(center, E=5e5, kind="tet10", cells=(2, 2, 2)):
    return FemBody(box_mesh((0.1, 0.1, 0.1), cells, kind, center=center), LinearElastic(E, 0.33, 1000.0))


def _pair_of_sims():
    """Two simulations of the same three cantilevered cubes, one stacking them."""
    def bodies():
        out = [_cube((0.3 * k, 0.0, 0.0)) for k in range(3)]
        for b in out:
            b.fix(np.flatnonzero(b.rest[:, 0] < b.rest[:, 0].min() + 1e-9))
        return out
    alone, stacked = bodies(), bodies()
    return alone, Simulation(alone, 0.01), stacked, Simulation([BodyStack(stacked)], 0.01)


def test_stack_steps_like_its_members_alone():
    alone, sa, stacked, ss = _pair_of_sims()
    # a prescribed end and an external load on the second body, a velocity on the third
    for b in (alone[1], stacked[1]):
        ids = np.flatnonzero(b.rest[:, 0] > b.rest[:, 0].max() - 1e-9)
        b.prescribe(ids, lambda t, x0=b.rest[ids].copy(): x0 + [0.0, 0.0, 0.02 * t])
    for b in (alone[2], stacked[2]):
        b.velocities = np.tile([0.0, 0.5, 0.0], (b.n_nodes, 1))
    sa.external_forces[alone[0]] = np.tile([0.0, 1.0, 0.0], (alone[0].n_nodes, 1))
    ss.external_forces[stacked[0]] = np.tile([0.0, 1.0, 0.0], (stacked[0].n_nodes, 1))
    for _ in range(30):
        sa.step()
        ss.step()
    for a, b in zip(alone, stacked):
        assert np.abs(a.positions - b.positions).max() < 1e-12
        assert np.abs(a.velocities - b.velocities).max() < 1e-10
    assert np.abs(alone[1].positions - alone[1].rest).max() > 1e-3  # it moved: the comparison means something


def test_members_state_written_between_steps_reaches_the_stack():
    alone, sa, stacked, ss = _pair_of_sims()
    for _ in range(5):
        sa.step()
        ss.step()
    for bodies in (alone, stacked):
        bodies[1].positions = bodies[1].positions + [0.0, 0.0, 0.003]  # assigned anew
        bodies[2].velocities[:, 1] += 0.2  # written in place
    for _ in range(5):
        sa.step()
        ss.step()
    for a, b in zip(alone, stacked):
        assert np.abs(a.positions - b.positions).max() < 1e-12


def test_stack_refuses_bodies_that_differ():
    with pytest.raises(InvalidInputError, match="agree"):
        BodyStack([_cube((0, 0, 0)), _cube((1, 0, 0), E=1e6)])
    with pytest.raises(InvalidInputError, match="two or more"):
        BodyStack([_cube((0, 0, 0))])


def _groups(world, bodies) -> list[list[int]]:
    """The stepped bodies of ``world`` as the sorted indices into ``bodies`` of their members (a body alone: itself)."""
    return sorted(sorted(next(k for k, b in enumerate(bodies) if b is m) for m in getattr(s, "members", [s]))
                  for s in world.sim.bodies)


def _run(world_stack: bool, steps: int, build):
    world, bodies = build(world_stack)
    for _ in range(steps):
        world.step()
    return world, bodies


def test_world_stacks_cubes_on_a_plane_with_the_same_answer():
    """Four cubes settling on a plane (contacts, friction) in one stack against four stepped alone: the same
    positions to the contact and solver tolerances, each cube carried by the plane with its own weight."""
    def build(stack):
        scene = cubes_on_plane(count=4, gap=0.002)
        scene.world._stack = stack
        return scene.world, scene.world.bodies
    (ws, bs), (wa, ba) = _run(True, 40, build), _run(False, 40, build)
    assert len(ws.sim.bodies) == 1 and isinstance(ws.sim.bodies[0], BodyStack) and len(wa.sim.bodies) == 4
    plane = next(iter(ws.rigids.values())).id
    for a, b in zip(ba, bs):
        assert np.abs(a.positions - b.positions).max() < 1e-6
        weight = b.total_mass * 9.81
        f = ws.contact_force(plane, soft=b)
        assert f[2] == pytest.approx(-weight, rel=1e-3)
        assert np.allclose(f, wa.contact_force(plane, soft=a), atol=1e-6 * weight)
    assert ws.max_penetration() < 1e-5


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_world_stack_keeps_soft_contact_and_attachments(mu):
    """A cube dropped onto another (soft-soft contact: stacked with the others until they touch, then the two a stack
    of their own)
    and a third held to a fixed box by an attachment: the same motion as the bodies stepped alone, the held one to round-off, the two in contact to what
    the contact solver's stated tolerances leave open.

    The active set adds a contact whose gap closes faster than velocity_tol [m/s]: a decision taken at that threshold
    moves a node by at most velocity_tol * dt per step. Which contacts carry an impact, and with friction which ones
    stick (a stick/slip change after the step's friction_switches iterations waits for the next step; a contact
    within cone_tol of the cone's edge goes either way), is decided at those thresholds, so the round-off of a larger
    system may tip a decision: a node then slides, or does not, for one step, at most its sliding speed times dt,
    and a frictionless cube keeps the sideways speed its impact gave it (it slides on a cube, with nothing to stop
    it). The bound sums both over the run, the sliding speed measured (the bodies' largest horizontal node speed of
    each step, in either run); found (25 steps): 1e-13 m compiled and 2e-5 m on the numpy path frictionless, 1.3e-4 m
    with friction, within bounds of 6e-4 to 7e-4 m."""
    def build(stack):
        world = World(dt=0.01, stack=stack)
        world.add_plane()
        low, high, held = _cube((0, 0, 0.051)), _cube((0.0, 0, 0.17)), _cube((0.5, 0, 0.3))
        post = world.add_box((0.02, 0.02, 0.02), position=(0.5, 0, 0.37))
        for b in (low, high, held):  # all ignore the post (one key): the attachment does not split the stack
            world.add_soft(b, friction=mu, ignore=[post])
        top = np.flatnonzero(held.rest[:, 2] > held.rest[:, 2].max() - 1e-9)
        world.attach(held, top, post)
        return world, [low, high, held]
    (ws, bs), (wa, ba) = build(True), build(False)
    cs = ws.contact_solver
    bound = 0.0
    for _ in range(25):
        ws.step()
        wa.step()
        # one decision per step tipped the other way, at the fastest slide of either run
        bound += cs.velocity_tol * ws.dt + ws.dt * max(float(np.hypot(*b.velocities[:, :2].T).max())
                                                         for b in (*bs[:2], *ba[:2]))
    # the two in soft contact step as one stack of their own (their coupled group), the held one alone (its own
    # key: attached)
    stacks = [s for s in ws.sim.bodies if isinstance(s, BodyStack)]
    assert len(stacks) == 1 and list(stacks[0].members) == bs[:2] and bs[2] in ws.sim.bodies
    assert any(r.active.any() for _, r in ws.pair_results)  # the falling cube rests on the lower one
    assert np.abs(ba[2].positions - bs[2].positions).max() < 1e-12  # no contact: the same arithmetic
    for a, b in zip(ba[:2], bs[:2]):
        assert np.abs(a.positions - b.positions).max() <= bound
    assert bound < 2e-3  # far below the cubes' size (0.1 m): a broken stack moves them by centimetres
    # resting on it, not in or through it (independent geometry: segments of each surface against the other's
    # triangles, tests/geometry.py)
    tris = [b.mesh.surface_triangles() for b in bs[:2]]
    assert geo.surface_intersection_depth(bs[0].positions, tris[0], bs[1].positions, tris[1]) < 1e-4
    assert bs[1].positions[:, 2].mean() > bs[0].positions[:, 2].mean() + 0.09


def test_world_stacks_only_bodies_that_agree():
    world = World(dt=0.01)
    world.add_plane()
    soft = [_cube((0, 0, 0.06)), _cube((0.2, 0, 0.06)), _cube((0.4, 0, 0.06), E=2e6), _cube((0.6, 0, 0.06))]
    for k, b in enumerate(soft):
        world.add_soft(b, friction=0.5 if k < 3 else 0.1)
    world.step()
    sizes = sorted(len(getattr(s, "members", [s])) for s in world.sim.bodies)
    assert sizes == [1, 1, 2]  # the stiffer cube and the one of other friction alone
    assert world.bodies == soft


def test_divergence_in_a_stack_names_the_member():
    from softbody.errors import SimulationDiverged

    bodies = [_cube((0.3 * k, 0.0, 0.0)) for k in range(2)]
    sim = Simulation([BodyStack(bodies)], 0.01, max_energy=1.0)
    c = bodies[1].rest.mean(axis=0)
    bodies[1].positions = c + 1.5 * (bodies[1].rest - c)  # stretched by half: far above 1 J of elastic energy
    with pytest.raises(SimulationDiverged, match="member 1"):
        sim.step()
    assert np.array_equal(bodies[0].positions, bodies[0].rest)  # the state kept


def test_bodies_in_soft_contact_are_stacked_apart_from_the_others():
    """Four cubes on a plane, a fifth dropped on the first: once they touch, the two step as a stack of their own
    (their soft contact needs the coupled contact solve, which would otherwise cover every stacked cube's contacts)
    and the three others in a stack; the motion is that of the cubes stepped alone."""
    def build(stack):
        world = World(dt=0.01, stack=stack)
        world.add_plane()
        cubes = [_cube((0.3 * k, 0.0, 0.051)) for k in range(4)] + [_cube((0.0, 0.0, 0.16))]
        for b in cubes:
            world.add_soft(b, friction=0.5)
        return world, cubes
    (ws, bs), (wa, ba) = _run(True, 30, build), _run(False, 30, build)
    groups = _groups(ws, bs)
    assert groups == [[0, 4], [1, 2, 3]]
    assert any(r.active.any() for _, r in ws.pair_results)
    for a, b in zip(ba, bs):
        assert np.abs(a.positions - b.positions).max() < 1e-4


def test_separate_contact_groups_step_as_one_stack_and_solve_as_islands():
    """Two cubes dropped on two others far apart: two coupled contact groups, stepped as one stack (one step system
    and one rigid search for the four) and solved as two islands (integration/islands.py: each its own pattern), with
    the motion of the cubes stepped alone; the fifth cube, touching only the plane, in a stack of its own."""
    def build(stack):
        world = World(dt=0.01, stack=stack)
        world.add_plane()
        cubes = ([_cube((0.0, 0.0, 0.051)), _cube((0.5, 0.0, 0.051)), _cube((1.0, 0.0, 0.051))]
                 + [_cube((0.0, 0.0, 0.16)), _cube((0.5, 0.0, 0.16))])
        for b in cubes:
            world.add_soft(b, friction=0.5)
        return world, cubes
    (ws, bs), (wa, ba) = _run(True, 30, build), _run(False, 30, build)
    groups = _groups(ws, bs)
    assert groups == [[0, 1, 3, 4], [2]]
    held = ws.contact_solver.convex.patterns._held
    islands = [sorted(bs.index(b) for b in key) for key in held]  # the islands' patterns (and, for the first
    assert [0, 3] in islands and [1, 4] in islands and [0, 1, 3, 4] not in islands  # contact's step, the fifth's)
    for a, b in zip(ba, bs):
        assert np.abs(a.positions - b.positions).max() < 1e-4


def test_contact_force_per_body_survives_a_restack_between_steps():
    world = World(dt=0.01)
    plane = world.add_plane()
    first = world.add_soft(_cube((0.0, 0.0, 0.0505)), friction=0.5)
    for _ in range(10):
        world.step()
    world.add_soft(_cube((0.3, 0.0, 0.0505)), friction=0.5)
    world.energy()  # restacks now (the recorder calls it after every step)
    assert world.contact_force(plane, soft=first)[2] == pytest.approx(-first.total_mass * 9.81, rel=1e-3)
    assert np.all(world.contact_force(plane, soft=world.bodies[1]) == 0.0)  # no step taken yet


def test_a_prescription_moved_to_other_nodes_is_seen_by_the_stack():
    bodies = [_cube((0.3 * k, 0.0, 0.0)) for k in range(2)]
    sim = Simulation([BodyStack(bodies)], 0.01, gravity=(0, 0, 0))
    ids = np.flatnonzero(bodies[1].rest[:, 0] < bodies[1].rest[:, 0].min() + 1e-9)
    held = {"at": bodies[1].rest[ids] + [0.0, 0.0, 0.01]}
    motion = lambda t: held["at"]  # noqa: E731
    bodies[1].prescribe(ids, motion)
    sim.step()
    other = np.flatnonzero(bodies[1].rest[:, 0] > bodies[1].rest[:, 0].max() - 1e-9)
    assert len(other) == len(ids)
    held["at"] = bodies[1].rest[other] + [0.0, 0.0, 0.01]
    bodies[1].prescribed[0] = (other, motion)  # the same motion object and count, other nodes
    sim.step()
    np.testing.assert_allclose(bodies[1].positions[other], bodies[1].rest[other] + [0.0, 0.0, 0.01], atol=1e-12)


def test_supports_set_on_the_stack_itself_last_until_a_member_changes_its_own():
    """A node fixed through the stack (World.stepped(body) returns it) stays fixed across gathers and steps, and
    stays so while the members' supports are unchanged; a member that fixes nodes of its own is read anew."""
    bodies = [_cube((0.3 * k, 0.0, 0.0)) for k in range(2)]
    stack = BodyStack(bodies)
    sim = Simulation([stack], 0.01)
    stack.fix([0])
    stack.gather()
    sim.step()
    assert stack.fixed[0] and stack.supported()[0]
    np.testing.assert_array_equal(stack.positions[0], stack.rest[0])  # held where it was
    bodies[1].fix([0])
    stack.gather()
    assert stack.fixed[stack.offsets[1]] and not stack.fixed[0]  # the members' supports, read anew


def test_soft_objects_in_the_users_tray(capsys):
    """examples/soft_objects_in_tray.py in a short form: cubes dropped into pybullet_data's tray, in the user's own
    client, end up stepped as one stack, resting on the tray floor with the tray carrying their weight."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "soft_objects_in_tray.py"
    spec = importlib.util.spec_from_file_location("soft_objects_in_tray", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    p, cid, world, tray, cubes = example.build(6, True)
    try:
        for _ in range(60):
            world.step()
        assert len(world.sim.bodies) == 1 and len(world.sim.bodies[0].members) == 6
        weight = sum(c.total_mass for c in cubes) * 9.81
        assert -world.contact_force(tray)[2] == pytest.approx(weight, rel=0.02)
        assert world.max_penetration() < 1e-4
        floor = 0.015  # the tray's floor box: 2 cm thick at z = 0.005
        assert min(c.positions[:, 2].min() for c in cubes) > floor - 1e-4
    finally:
        world.close()
        p.disconnect(cid)


def test_newton_on_a_stack_predicts_each_member_rigidly():
    """Two cubes flying apart, stepped with the Newton scheme: the stack's first iterate is each member's own
    rigid motion, so it converges in the iterations each body alone takes (one), to the same states."""
    runs = {}
    for stack in (False, True):
        bodies = [_cube((0.0, 0.0, 0.0)), _cube((0.0, 0.3, 0.0))]
        bodies[0].velocities = np.tile([3.0, 0.0, 0.0], (bodies[0].n_nodes, 1))
        bodies[1].velocities = np.tile([-3.0, 0.0, 0.0], (bodies[1].n_nodes, 1))
        sim = Simulation([BodyStack(bodies)] if stack else bodies, 0.02, gravity=(0, 0, 0), scheme="newton")
        iterations = []
        for _ in range(5):
            sim.step()
            iterations.append(sim.newton_report.iterations)
        runs[stack] = (iterations, [b.positions.copy() for b in bodies])
    assert runs[True][0] == runs[False][0] == [1] * 5
    for a, b in zip(runs[False][1], runs[True][1]):
        assert np.abs(a - b).max() < 1e-10
