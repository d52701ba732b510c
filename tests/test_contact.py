"""Rigid scenes through pybullet: contact, friction, coupling, attachments (issue 3).

Every expectation is physical: free-fall time to first contact, the resting height set by the
sphere's radius, Coulomb's law on an incline, momentum conservation, exact attachment.
"""
import math

import numpy as np
import pybullet as p
import pytest

import softbody as sb
from experiments.scenes import hanging_tube, platform_x, sheet_on_sphere
from integration.world import World
from softbody.errors import InvalidInputError

COARSE = {"tet4": (4, 4, 2), "hex8": (4, 4, 2), "tet10": (2, 2, 1)}


def active_contacts(world) -> int:
    return sum(int(r.active.sum()) for _, r in world.contact_results.values())


@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_sheet_on_sphere(kind):
    scene = sheet_on_sphere(kind, COARSE[kind])
    body, world = scene.body, scene.world
    top = int(np.argmin(np.linalg.norm(body.rest - [0, 0, 0.35], axis=1)))
    assert np.allclose(body.rest[top], [0, 0, 0.35])
    first, worst = None, 0.0

    def check(w):
        nonlocal first, worst
        if first is None and active_contacts(w):
            first = w.t
        worst = max(worst, w.max_penetration())

    scene.run(3.0, check)
    t_hit = math.sqrt(2 * 0.05 / 9.81)
    assert abs(first - t_hit) <= world.dt + 1e-9, (first, t_hit)
    assert worst < 1e-3
    assert abs(body.positions[top, 2] - 0.3) < 2e-3
    assert abs(body.velocities[top]).max() < 0.05  # come to rest on the sphere's top
    corners = np.flatnonzero(np.isclose(np.abs(body.rest[:, 0]), 0.5) & np.isclose(np.abs(body.rest[:, 1]), 0.5)
                             & np.isclose(body.rest[:, 2], 0.35))
    assert len(corners) == 4
    assert np.all(body.positions[corners, 2] < body.positions[top, 2] - 0.02)  # the sheet drapes


def _block_on_plane(mu, tilt_deg=0.0, kind="hex8", damping=(0.0, 0.001)):
    th = math.radians(tilt_deg)
    Ry = np.array([[math.cos(th), 0, math.sin(th)], [0, 1, 0], [-math.sin(th), 0, math.cos(th)]])
    m = sb.box_mesh((0.2, 0.2, 0.1), (2, 2, 1), kind, center=(0, 0, 0.05 + 1e-4))
    m = sb.Mesh(m.nodes @ Ry.T, m.elements, kind)
    body = sb.FemBody(m, sb.LinearElastic(1e6, 0.3, 1000), damping=damping)
    world = World(dt=0.01)
    world.add_plane(normal=Ry @ [0, 0, 1.0])
    world.add_soft(body, friction=mu)
    return world, body, Ry @ [1.0, 0, 0]


def test_incline_sticks_with_enough_friction():
    world, body, downhill = _block_on_plane(0.5, 20)  # tan 20 = 0.36 < 0.5
    world.run(0.2)  # settle onto the plane
    c0 = body.positions.mean(axis=0)
    world.run(2.0)
    creep = abs((body.positions.mean(axis=0) - c0) @ downhill)
    assert creep < 1e-3


@pytest.mark.parametrize("kind", ["hex8", "tet10"])
def test_incline_slides_with_coulomb_acceleration(kind):
    world, body, downhill = _block_on_plane(0.1, 20, kind)
    xs = []
    world.run(1.5, lambda w: xs.append(body.positions.mean(axis=0) @ downhill))
    t = world.dt * np.arange(1, len(xs) + 1)
    accel = 2 * np.polyfit(t[30:], xs[30:], 2)[0]
    expected = 9.81 * (math.sin(math.radians(20)) - 0.1 * math.cos(math.radians(20)))
    assert abs(accel - expected) < 0.1 * expected


def test_thrown_block_leaves_the_floor_and_lands():
    world, body, _ = _block_on_plane(0.3)
    world.run(0.1)
    assert active_contacts(world) > 0
    body.velocities[:] = [0.0, 0.0, 2.0]
    airborne, lowest = [], []

    def cb(w):
        airborne.append(active_contacts(w) == 0)
        lowest.append(body.positions[:, 2].min())

    world.run(0.6, cb)
    assert all(airborne[:5])  # separates at once: no sticking to the floor
    assert max(lowest) > 0.15  # its lowest point rose ~ v^2 / 2g = 0.2 m
    world.run(1.0)
    assert active_contacts(world) > 0 and world.max_penetration() < 1e-3


@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_two_way_coupling_conserves_momentum(kind):
    ball = sb.ball_mesh(0.1, 3, kind, center=(-0.3, 0, 0))
    body = sb.FemBody(ball, sb.LinearElastic(2e5, 0.3, 1000), damping=(0.0, 0.002))
    world = World(dt=0.005, gravity=(0, 0, 0))
    box = world.add_box((0.1, 0.1, 0.1), position=(0.05, 0, 0), mass=body.total_mass)
    world.add_soft(body)
    body.velocities[:] = [2.0, 0, 0]

    def momentum():
        return body.node_mass @ body.velocities + box.mass * box.velocity()[0]

    p0 = momentum()
    world.run(0.4)
    v_box = box.velocity()[0]
    assert v_box[0] > 0.5  # the box was pushed
    assert np.linalg.norm(momentum() - p0) < 0.01 * np.linalg.norm(p0)


def test_box_corner_pressed_into_slab_does_not_penetrate():
    m = sb.box_mesh((0.4, 0.4, 0.1), (6, 6, 2), "tet4", center=(0, 0, 0.05))
    body = sb.FemBody(m, sb.LinearElastic(1e5, 0.3, 1000))
    body.fix(np.flatnonzero(np.isclose(m.nodes[:, 2], 0)))
    world = World(dt=0.01)
    q = p.getQuaternionFromEuler([math.radians(45), math.atan(1 / math.sqrt(2)), 0])  # a vertex points down
    reach = 0.05 * math.sqrt(3)
    box = world.add_box((0.05, 0.05, 0.05), motion=lambda t: ((0.013, 0.021, 0.11 + reach - 0.04 * min(t, 1.0)), q))
    world.add_soft(body)
    tris = world.entry(body).surface.triangles
    worst = []
    def deepest(w):
        hits = w.detector.face_contacts(0, body.positions, tris, box, 0.05)
        worst.append(min(hits.distance[hits.primary], default=1.0))

    world.run(1.3, deepest)
    assert box.corner_points()[0][:, 2].min() < 0.075  # pressed 2.5 cm below the rest surface
    assert min(worst) > -1e-3


def test_hanging_tube_follows_platform_and_swings():
    scene = hanging_tube("hex8", (8, 1, 4))
    body, world = scene.body, scene.world
    top = np.flatnonzero(np.isclose(body.rest[:, 2], 0.0))
    err = []
    scene_x = []

    def cb(w):
        err.append(np.abs(body.positions[top, 0] - body.rest[top, 0] - platform_x(w.t)).max())
        err.append(np.abs(body.positions[top, 1:] - body.rest[top, 1:]).max())
        scene_x.append(scene.monitored())

    scene.run(3.0, cb)
    assert max(err) < 1e-12
    x = np.array(scene_x) - 0.1
    t = world.dt * np.arange(1, len(x) + 1)
    assert abs(x[t <= 0.5]).max() < 1e-3  # still hanging before the platform moves
    # lags: while the platform moves out, the free end first stays behind (inertia) ...
    assert x[np.isclose(t, 0.75)][0] < 0.5 * platform_x(0.75)
    assert t[np.argmax(x)] > 1.0  # its largest excursion comes after the platform's
    late = x[t >= 1.6]
    assert late.max() > 0.05 and late.min() < -0.05  # swings on both sides after the platform stopped


def test_bad_input_is_rejected_clearly(tmp_path):
    world = World()
    body = world.add_soft(sb.FemBody(sb.box_mesh((1, 1, 1), (1, 1, 1), "hex8"), sb.LinearElastic(1e5, 0.3, 1000)))
    with pytest.raises(InvalidInputError, match="unknown rigid body id 42"):
        world.rigid(42)
    with pytest.raises(InvalidInputError, match="unknown rigid body id 42"):
        world.attach(body, [0], 42)
    sphere = world.add_sphere(0.1)
    with pytest.raises(InvalidInputError, match=r"node ids \[99\] do not exist"):
        world.attach(body, [0, 99], sphere)
    with pytest.raises(InvalidInputError, match="friction"):
        world.add_soft(sb.FemBody(sb.box_mesh((1, 1, 1), (1, 1, 1), "hex8"), sb.LinearElastic(1e5, 0.3, 1000)),
                       friction=-0.5)
    with pytest.raises(InvalidInputError, match="friction"):
        world.add_box((1, 1, 1), friction=-1.0)
    with pytest.raises(InvalidInputError, match="radius"):
        world.add_sphere(-1.0)
    with pytest.raises(InvalidInputError, match="does not exist"):
        world.add_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "garbage.stl"
    bad.write_bytes(b"\x00\x01 definitely not a mesh")
    with pytest.raises(InvalidInputError, match="garbage.stl"):
        world.add_mesh(bad)
    world.close()


def test_mesh_obstacle_from_trimesh_holds_a_block():
    import trimesh

    world = World(dt=0.01)
    world.add_mesh(trimesh.creation.box((1.0, 1.0, 0.2)), position=(0, 0, -0.1))  # top face at z = 0
    m = sb.box_mesh((0.2, 0.2, 0.1), (2, 2, 1), "tet4", center=(0, 0, 0.06))
    body = world.add_soft(sb.FemBody(m, sb.LinearElastic(1e6, 0.3, 1000)))
    world.run(0.6)
    assert world.max_penetration() < 1e-3
    assert abs(body.positions[:, 2].min()) < 2e-3  # resting on the mesh's top face (pybullet margin ~1 mm)


def test_scene_without_rigid_bodies_does_no_collision_work():
    world = World()
    m = sb.box_mesh((1, 0.1, 0.1), (4, 1, 1), "hex8", center=(0.5, 0, 0))
    body = world.add_soft(sb.FemBody(m, sb.LinearElastic(5e7, 0.3, 1000)))
    body.fix(np.flatnonzero(np.isclose(m.nodes[:, 0], 0)))
    world.run(0.05)
    assert world.detector.last_candidates == 0 and len(world.contacts) == 0


def test_bounding_sphere_broad_phase_keeps_every_contact():
    """The broad phase culls candidates by the rigid's AABB and bounding sphere (grown by the margin);
    every point pybullet finds within the margin of a sphere, a turned box or a mesh is still found, with
    the same distance (to pybullet's own accuracy on a box: it works with collision margins)."""
    import pybullet as p
    import trimesh
    from scipy.spatial.transform import Rotation

    world = World()
    rigids = [world.add_sphere(0.3, position=(0.1, -0.2, 0.05)),
              world.add_box((0.3, 0.1, 0.2), position=(-0.1, 0.2, 0.0),
                            orientation=Rotation.from_euler("xyz", [0.3, -0.5, 0.9]).as_quat()),
              world.add_mesh(trimesh.creation.icosphere(subdivisions=1, radius=0.25), position=(0.3, 0.1, -0.1))]
    margin = 0.05
    rng = np.random.default_rng(11)
    for rb, tol in zip(rigids, (1e-9, 1e-3, 1e-12)):
        lo, hi = rb.aabb()
        pts = rng.uniform(lo - 2 * margin, hi + 2 * margin, size=(3000, 3))
        found = world.detector.node_contacts(0, pts, np.arange(len(pts)), rb, margin)
        brute = {}
        for i, x in enumerate(pts.tolist()):
            res = p.getClosestPoints(-1, rb.id, margin, collisionShapeA=world.detector._probe,
                                     collisionShapePositionA=x, physicsClientId=world.client)
            if res:
                brute[i] = min(r[8] for r in res) + (1e-6 if rb.shape != "mesh" else 0.0)  # pybullet's probe radius
        assert len(brute) > 50  # the test samples the margin layer, not only empty space
        ours = dict(zip(found.node.tolist(), found.distance.tolist()))
        # the same points, but for those within pybullet's own error of the margin's edge
        edge = {i for i, d in {**brute, **ours}.items() if abs(d - margin) <= tol + 1e-6}
        assert set(ours) - edge == set(brute) - edge, rb.shape
        if not rb.concave:
            common = sorted(set(ours) & set(brute))
            np.testing.assert_allclose([ours[i] for i in common], [brute[i] for i in common], atol=tol)
        lo_m, hi_m = lo - margin, hi + margin
        in_aabb = int(np.all((pts >= lo_m) & (pts <= hi_m), axis=1).sum())
        assert world.detector.last_candidates < in_aabb  # the bounding sphere culled beyond the AABB
        world.detector.last_candidates = 0
    world.close()


def test_rolling_contacts_hold_no_more_friction_than_coulomb():
    """A soft ball launched down a 20 degree incline at mu = 0.05 (below the rigid ball's rolling threshold
    2/7 tan(20 deg) = 0.104) slides: the friction impulse on the incline is mu times the normal one, and the
    centre ends at v0 + g (sin(theta) - mu cos(theta)) t. Contacts touching down each step used to start
    sticking and hold 4x Coulomb's bound for a step (stick/slip settled only in the first iteration)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "friction_sweep.py"
    spec = importlib.util.spec_from_file_location("friction_sweep", path)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    mu, v0, t_end = 0.05, 0.5, 0.3
    world = ex.scene(speed=v0, friction=mu)
    ex.monitor(world)
    for _ in range(int(round(t_end / world.dt))):
        world.step()
        ex.monitor(world)
    m = ex.metrics(world)
    theta = math.radians(ex.ANGLE)
    assert m["friction_ratio"] == pytest.approx(mu, rel=0.03)
    # (the first 20 ms, a 2 mm fall onto the incline, are frictionless: +0.5% of the end speed)
    assert m["speed_end_m_s"] == pytest.approx(v0 + 9.81 * (math.sin(theta) - mu * math.cos(theta)) * t_end, rel=0.01)


def test_node_contacts_alone_step_as_the_coupled_active_set(monkeypatch):
    """ContactSolver._solve_nodes (node contacts only, no rows: each body's active set on its own, a body solved
    again only while its set changes) against the general loop through the coupled solver (_solve_rows) on the
    same problems: the sheet-on-sphere scene (contacts added and released) and three cubes stepped alone on a
    plane with friction (several bodies, their sets settling at different iterations) give the same trajectories,
    contact forces and active-set iterations."""
    from experiments.scenes import sheet_on_sphere
    from integration import World, contact
    from softbody import FemBody, LinearElastic, box_mesh

    def sheet():
        return sheet_on_sphere("tet4", (4, 4, 2)).world

    def cubes():
        world = World(dt=0.01, stack=False)
        world.add_plane()
        for k in range(3):
            mesh = box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0.15 * k, 0.0, 0.06 + 0.01 * k))
            world.add_soft(FemBody(mesh, LinearElastic(5e5, 0.33, 1000.0), damping=(0.1, 0.001)), friction=0.5)
        return world

    def general(self, steps, prepared, nodes, index, results):
        return self._solve_rows(steps, prepared, index, results, nodes, [None] * len(steps), None)

    for build, steps in ((sheet, 45), (cubes, 30)):
        runs = []
        for fast in (True, False):
            with monkeypatch.context() as m:
                if not fast:
                    m.setattr(contact.ContactSolver, "_solve_nodes", general)
                world = build()
                forces, iterations = [], []
                for _ in range(steps):
                    world.step()
                    forces += [res.force for _, res in world.contact_results.values()]
                    iterations.append(world.report.iterations)
                runs.append(([b.positions.copy() for b in world.bodies], np.concatenate(forces), iterations))
                world.close()
        (x1, f1, i1), (x2, f2, i2) = runs
        assert len(f1) > 10 and i1 == i2
        for a, b in zip(x1, x2):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        np.testing.assert_allclose(f1, f2, rtol=0, atol=1e-9 * np.abs(f2).max())


@pytest.mark.parametrize("compiled", [True, False])
def test_a_contact_that_stopped_sliding_does_not_slip_again_in_the_step(compiled, monkeypatch):
    """The active set's friction rules, on one node contact read by hand (contact._NodeSet, compiled and numpy): the
    force its stick needs leaves the cone (it slips, the friction along that force), its velocity then runs along the
    friction (it stopped: it sticks), and the stick again needs more than the cone. It stays sticking for the rest of
    the step, the set standing (near the cone's edge stick and slip took turns until the switch cap), with its wish to
    slip carried to the next step. A second contact slides on throughout."""
    from integration import contact, kernels

    monkeypatch.setattr(kernels, "ENABLED", compiled and kernels.AVAILABLE)
    h, mu = 0.01, 0.5
    c = contact.NodeContacts(np.array([0, 1]), np.tile([0.0, 0.0, 1.0], (2, 1)), np.zeros(2), np.zeros((2, 3)),
                             np.full(2, mu), np.zeros(2, np.int64), np.zeros((2, 3)))
    keys = set(c.node.tolist())
    s = contact._NodeSet(contact.ContactSolver(), c, (keys, keys, {}), h, 2)  # both active and sticking
    F = s.frames  # (2, 3, 3): columns normal, tangent 1, tangent 2

    def read(v_local, force_local, it):
        v = np.einsum("mij,mj->mi", F, np.asarray(v_local, float))
        return s.read(v, h * np.asarray(force_local, float), np.zeros(0), it)

    beyond = [[1.0, 0.8, 0.0], [1.0, 0.8, 0.0]]  # 0.8 N needed, the cone 0.5 N
    assert read([[0.0, 0.0, 0.0]] * 2, beyond, 1)
    assert not s.stick.any() and np.allclose(s.slip_force[:, 1:], [[mu, 0.0]] * 2)
    # node 0 runs along its friction (stopped: sticks); node 1 slides against it
    assert read([[0.0, 0.01, 0.0], [0.0, -0.01, 0.0]], [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], 2)
    assert s.stick.tolist() == [True, False]
    # node 0's stick needs more than the cone again: it stays sticking in this step and wants to slip in the next
    changed = read([[0.0, 0.0, 0.0], [0.0, -0.01, 0.0]], [[1.0, 0.8, 0.0], [1.0, 0.0, 0.0]], 3)
    assert not changed and s.stick.tolist() == [True, False] and s.want_slip.tolist() == [True, False]
    _, (active, stick, slip) = s.result(3)
    assert active == {0, 1} and stick == set() and set(slip) == {0, 1}


@pytest.mark.parametrize("compiled", [True, False])
def test_after_end_switching_friction_waits_for_the_next_step_and_contacts_do_not(compiled, monkeypatch):
    """_ContactSet.end_switching (a confirmed set on the multigrid path, compiled and numpy): a stick that needs more
    than the cone, or a slide that stopped, no longer switches in the step (its wish carried to the next) and sliding
    forces that changed no longer ask for another solve; a contact that pulls is still released. Before it, the
    same reads switch."""
    from integration import contact, kernels

    monkeypatch.setattr(kernels, "ENABLED", compiled and kernels.AVAILABLE)
    h, mu = 0.01, 0.5
    c = contact.NodeContacts(np.array([0, 1, 2]), np.tile([0.0, 0.0, 1.0], (3, 1)), np.zeros(3), np.zeros((3, 3)),
                             np.full(3, mu), np.zeros(3, np.int64), np.zeros((3, 3)))
    beyond = [[1.0, 0.8, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]  # node 0's stick needs 0.8 N, the cone 0.5 N

    def make():  # nodes 0 and 2 active and sticking, node 1 sliding, its friction mu N along t1 (world y)
        s = contact._NodeSet(contact.ContactSolver(), c, ({0, 1, 2}, {0, 2}, {1: np.array([0.0, mu, 0.0])}), h, 3)
        return s, s.frames

    def read(s, F, v_local, force_local, it):
        v = np.einsum("mij,mj->mi", F, np.asarray(v_local, float))
        return s.read(v, h * np.asarray(force_local, float), np.zeros(0), it)

    moving = [[0.0, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.0]]  # node 1 runs along its friction: it stopped
    s, F = make()
    assert read(s, F, moving, beyond, 2) and s.stick.tolist() == [False, True, True]  # both switch
    s, F = make()
    s.end_switching(2)
    assert not read(s, F, moving, beyond, 2)
    assert s.stick.tolist() == [True, False, True] and s.want_slip.tolist() == [True, False, False]
    assert s.want_stick.tolist() == [False, True, False]
    _, (active, stick, slip) = s.result(2)
    assert active == {0, 1, 2} and stick == {1, 2} and set(slip) == {0}  # the wishes, for the next step
    # node 1 slides on, turned by 45 degrees: its force would be refined by another solve, but not after the end
    turned = [[0.0, 0.0, 0.0], [0.0, -0.01, -0.01], [0.0, 0.0, 0.0]]
    inside = [[1.0, 0.1, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    s, F = make()
    assert read(s, F, turned, inside, 2)
    s, F = make()
    s.end_switching(2)
    assert not read(s, F, turned, inside, 2)
    # a pulling contact is released all the same
    s, F = make()
    s.end_switching(2)
    pulling = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]
    assert read(s, F, [[0.0, 0.0, 0.0], [0.0, -0.01, 0.0], [0.0, 0.0, 0.0]], pulling, 2)
    assert s.active.tolist() == [True, True, False]


@pytest.mark.parametrize("compiled", [True, False])
def test_the_sliding_forces_fixed_point_stops_where_its_change_grows(compiled, monkeypatch):
    """The sliding friction of a node contact follows its velocity from solve to solve (a fixed point, contact._NodeSet,
    compiled and numpy): while the forces' change shrinks the set is read again; where it grows (the velocities'
    round-off turning it round near the tolerance) the set stands with the forces it had."""
    from integration import contact, kernels

    monkeypatch.setattr(kernels, "ENABLED", compiled and kernels.AVAILABLE)
    h, mu = 0.01, 0.5
    c = contact.NodeContacts(np.array([0]), np.array([[0.0, 0.0, 1.0]]), np.zeros(1), np.zeros((1, 3)),
                             np.full(1, mu), np.zeros(1, np.int64), np.zeros((1, 3)))
    s = contact._NodeSet(contact.ContactSolver(), c, ({0}, {0}, {}), h, 1)
    F = s.frames

    def read(angle, it, force=(1.0, 0.0, 0.0)):  # sliding at 1 m/s against the direction (cos, sin)
        v = np.einsum("mij,mj->mi", F, np.array([[0.0, -math.cos(angle), -math.sin(angle)]]))
        return s.read(v, h * np.array([force]), np.zeros(0), it)

    assert read(0.0, 1, force=(1.0, 0.8, 0.0))  # the stick leaves the cone: it slips (the set changed)
    directions = []
    for it, angle in enumerate((0.3, 0.2, 0.15), start=2):  # changes 0.15, 0.05, 0.025 of the force: read on
        assert read(angle, it)
        directions.append(s.slip_force[0, 1:] / mu)
    np.testing.assert_allclose(directions[-1], [math.cos(0.15), math.sin(0.15)], atol=1e-12)
    kept = s.slip_force.copy()
    assert not read(0.5, 5)  # a change of 0.17 after 0.025: the set stands, its forces as they were
    np.testing.assert_array_equal(s.slip_force, kept)
