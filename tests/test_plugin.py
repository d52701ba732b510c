"""The World as a plugin for the user's pybullet scene, and its two-way coupling (issue 13).

Independent truths: pybullet's own link velocities and kinetic energy (the adapter's Jacobians and mass
matrices), pybullet's closest-point query (penetration), a static FEM solution written here with scipy (a
rigid box on a soft block), the compound pendulum and statics (a soft block on a hinged rod), conservation of
linear momentum, and energy that never grows.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pybullet as p
import pybullet_data
import pytest
import scipy.sparse as sparse
import scipy.sparse.linalg as spla

import geometry as geo

import softbody as sb
from integration import World
from integration.bullet import BulletAdapter, quat_matrix
from softbody.errors import InvalidInputError, SimulationDiverged


def energy_never_grows(energies, rel=1e-9) -> float:
    """The largest step-to-step increase of a sequence of total energies, relative to its largest value."""
    e = np.asarray(energies)
    return float(np.max(np.diff(e), initial=0.0) / max(np.abs(e).max(), 1.0))


# ---------------------------------------------------------------------------------------------- the adapter
@pytest.mark.parametrize("urdf, fixed", [("r2d2.urdf", False), ("kuka_iiwa/model.urdf", True),
                                         ("franka_panda/panda.urdf", True), ("laikago/laikago.urdf", False)])
def test_adapter_jacobians_and_mass_matrix_agree_with_pybullet(urdf, fixed):
    """J u gives every link's point velocities as pybullet reports them, and u^T M u / 2 the kinetic energy
    summed over the links from pybullet's own velocities and inertias, for free and fixed bases."""
    ad = BulletAdapter()
    try:
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=ad.client)
        b = p.loadURDF(urdf, [0, 0, 1], useFixedBase=fixed, physicsClientId=ad.client)
        rng = np.random.default_rng(3)
        movable, _ = ad.joints(b)
        for j in movable:
            p.resetJointState(b, j, rng.uniform(-0.5, 0.5), rng.uniform(-1, 1), physicsClientId=ad.client)
        if not fixed:
            p.resetBasePositionAndOrientation(b, [0.3, 0.2, 1], p.getQuaternionFromEuler(rng.uniform(-1, 1, 3)),
                                              physicsClientId=ad.client)
            p.resetBaseVelocity(b, rng.uniform(-1, 1, 3).tolist(), rng.uniform(-1, 1, 3).tolist(),
                                physicsClientId=ad.client)
        ad.invalidate()
        dyn = ad.dynamics(b)
        assert dyn.n == len(movable) + (0 if fixed else 6)
        kinetic = 0.0
        scale = 0.0
        for link in range(-1, ad.num_links(b)):
            com, orn, v, w = ad.state(b, link)
            pts = com + rng.normal(size=(4, 3)) * 0.1
            J = ad.point_jacobians(dyn, link, pts)
            truth = v + np.cross(w, pts - com)
            np.testing.assert_allclose(J @ dyn.u, truth, atol=1e-6)
            m, I = ad.inertia(b, link)
            R = quat_matrix(orn)
            kinetic += 0.5 * m * v @ v + 0.5 * w @ (R * I) @ R.T @ w
            scale = max(scale, np.abs(truth).max())
        assert scale > 0.1  # the state really moves
        assert 0.5 * dyn.u @ dyn.M @ dyn.u == pytest.approx(kinetic, rel=1e-9)
    finally:
        ad.close()


def test_impulse_through_the_adapter_changes_momentum_by_the_impulse():
    """A velocity change du = M^-1 J^T F at a point of a free two-link body changes its linear momentum by F."""
    ad = BulletAdapter()
    try:
        cid = ad.client
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.05] * 3, physicsClientId=cid)
        b = p.createMultiBody(1.0, col, basePosition=[0, 0, 0], baseOrientation=p.getQuaternionFromEuler([0.3, 0.2, 0.1]),
                              linkMasses=[0.7], linkCollisionShapeIndices=[col], linkVisualShapeIndices=[-1],
                              linkPositions=[[0.12, 0, 0.02]], linkOrientations=[[0, 0, 0, 1]],
                              linkInertialFramePositions=[[0, 0, 0]], linkInertialFrameOrientations=[[0, 0, 0, 1]],
                              linkParentIndices=[0], linkJointTypes=[p.JOINT_REVOLUTE], linkJointAxis=[[0, 0, 1]],
                              physicsClientId=cid)
        p.resetJointState(b, 0, 0.4, 0.3, physicsClientId=cid)
        p.resetBaseVelocity(b, [0.1, 0.2, -0.1], [0.3, -0.2, 0.5], physicsClientId=cid)

        def momentum():
            ad.invalidate()
            return 1.0 * ad.velocity(b, -1)[0] + 0.7 * ad.velocity(b, 0)[0]

        for link in (-1, 0):
            ad.invalidate()
            dyn = ad.dynamics(b)
            point = ad.pose(b, link)[0] + [0.02, -0.03, 0.04]
            F = np.array([0.5, -0.2, 0.3])
            J = ad.point_jacobians(dyn, link, point[None])[0]
            before = momentum()
            ad.change_velocity(dyn, np.linalg.solve(dyn.M, J.T @ F), 0.0)
            np.testing.assert_allclose(momentum() - before, F, atol=1e-9)
    finally:
        ad.close()


# ---------------------------------------------------------------------------------------- the user's world
def _user_scene(dt=0.01):
    """plane, tray and a KUKA iiwa under position motors, all from pybullet_data, in the user's own client."""
    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(dt, physicsClientId=cid)
    plane = p.loadURDF("plane.urdf", physicsClientId=cid)
    tray = p.loadURDF("tray/traybox.urdf", [0.6, 0, 0], physicsClientId=cid)
    kuka = p.loadURDF("kuka_iiwa/model.urdf", [0, 0, 0], useFixedBase=True, physicsClientId=cid)
    q0 = [0, 0.6, 0, -1.2, 0, 0.6, 0]
    for j in range(7):
        p.resetJointState(kuka, j, q0[j], physicsClientId=cid)
    return cid, plane, tray, kuka, q0


def test_world_joins_the_users_client_with_a_robot_and_a_tray():
    cid, plane, tray, kuka, q0 = _user_scene()
    try:
        world = World(client=cid)
        assert world.dt == pytest.approx(0.01) and np.allclose(world.gravity, [0, 0, -9.81])
        # every link with a collision shape is a rigid link of its own; the arm's links move (motors, joints)
        assert {(kuka, link) for link in range(-1, 7)} <= set(world.rigids)
        assert world.rigid(kuka, 4).movable and not world.rigid(plane).movable
        block = sb.FemBody(sb.box_mesh((0.08, 0.08, 0.08), (2, 2, 2), "tet10", center=(0.6, 0, 0.15)),
                           sb.LinearElastic(1e5, 0.3, 500))
        world.add_soft(block, friction=0.5)
        lo, hi = p.getAABB(kuka, 4, physicsClientId=cid)
        centre = 0.5 * (np.array(lo) + np.array(hi))
        block2 = sb.FemBody(sb.box_mesh((0.06, 0.06, 0.06), (2, 2, 2), "tet10", center=(centre[0], centre[1], hi[2] + 0.05)),
                            sb.LinearElastic(1e5, 0.3, 500))
        world.add_soft(block2, friction=0.8)
        late = p.loadURDF("sphere_small.urdf", [2.0, 2.0, 0.5], physicsClientId=cid)  # loaded after the World
        worst = 0.0
        for _ in range(150):
            for j in range(7):  # the user's own control loop around World.step()
                p.setJointMotorControl2(kuka, j, p.POSITION_CONTROL, targetPosition=q0[j], force=300, physicsClientId=cid)
            world.step()
            worst = max(worst, world.max_penetration())
        assert (late, -1) in world.rigids  # seen at the next step
        tray_floor = 0.015  # the tray's bottom box: 0.02 m thick, centred 0.005 m above its base
        assert abs(block.positions[:, 2].min() - tray_floor) < 1e-3
        assert np.abs(block.velocities).max() < 0.01 and np.abs(block2.velocities).max() < 0.02
        # block2 rests on the arm: the arm's links carry its weight
        weight = block2.total_mass * 9.81
        carried = sum(world.contact_force(kuka, link) for link in range(-1, 7))
        assert carried[2] == pytest.approx(-weight, rel=0.05)
        assert worst < 1e-3
        world.close()
        assert p.isConnected(cid)  # the World leaves the user's client alone
    finally:
        p.disconnect(cid)


def test_explicit_step_and_gravity_are_set_on_the_joined_client():
    cid = p.connect(p.DIRECT)
    try:
        world = World(client=cid, dt=0.005, gravity=(0, 0, -3.0))
        prm = p.getPhysicsEngineParameters(physicsClientId=cid)
        assert prm["fixedTimeStep"] == pytest.approx(0.005) and prm["gravityAccelerationZ"] == pytest.approx(-3.0)
        world.close()
        with pytest.raises(InvalidInputError, match="client"):
            World(client=12345)
        with pytest.raises(InvalidInputError, match="gui"):
            World(client=cid, gui=True)
    finally:
        p.disconnect(cid)


def test_ignored_bodies_do_not_collide():
    world = World(dt=0.01)
    box = world.add_box((0.5, 0.5, 0.05), position=(0, 0, -0.05))
    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8", center=(0, 0, 0.1)), sb.LinearElastic(1e5, 0.3, 500))
    world.add_soft(body, ignore=[box.id])
    world.run(0.3)
    assert body.positions[:, 2].max() < -0.2  # fell through the box it ignores
    with pytest.raises(InvalidInputError, match="ignore"):
        world.add_soft(sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "hex8"), sb.LinearElastic(1e5, 0.3, 500)),
                       ignore=["box"])


# ------------------------------------------------------------------------------------------- rigid on soft
HALF = 0.0375  # the box's half extent [m]: a 7.5 cm box on a 10 cm block, its edges between node lines


def static_box_on_block(mass: float, offset: float, E: float = 1e5, nu: float = 0.3, rho: float = 1000.0) -> float:
    """Sag [m] of a rigid box (6 dof, small rotations about its bottom centre c) resting on a soft block fixed
    at its bottom, in linear elasticity: unilateral, sticking contact at the top nodes strictly under the box,
    at the box's bottom corners (points of the top surface triangles with barycentric weights) and where its
    bottom rim crosses the top surface's edges (points of the edges); one sparse
    KKT system (scipy), the contact set by an active set on the normal reactions."""
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05))
    X = mesh.nodes
    body = sb.FemBody(mesh, sb.LinearElastic(E, nu, rho))
    K = body.stiffness_matrix().tocsr()
    N = len(X)
    f = np.zeros(3 * N)
    f[2::3] = -9.81 * body.node_mass
    c = np.array([offset, 0.0, 0.1])
    inside = np.flatnonzero(np.isclose(X[:, 2], 0.1) & np.all(np.abs(X[:, :2] - c[:2]) < HALF - 1e-9, axis=1))
    points = [([n], [1.0], X[n]) for n in inside]
    tris = mesh.surface_triangles()
    tris = tris[np.all(np.isclose(X[tris][:, :, 2], 0.1), axis=1)]
    for sx in (-HALF, HALF):
        for sy in (-HALF, HALF):
            q = c + np.array([sx, sy, 0.0])
            for t in tris:
                a, b, d = X[t][:, :2]
                l1, l2 = np.linalg.solve(np.column_stack([b - a, d - a]), q[:2] - a)
                w = np.array([1 - l1 - l2, l1, l2])
                if (w >= -1e-9).all():
                    points.append((list(t), list(w), q))
                    break
    # and where the box's rim crosses the top surface's edges between their nodes (a rigid edge across a soft face)
    edges = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    corners = [c + np.array([sx, sy, 0.0]) for sx, sy in ((-HALF, -HALF), (HALF, -HALF), (HALF, HALF), (-HALF, HALF))]
    for k in range(4):
        r0, r1 = corners[k][:2], corners[(k + 1) % 4][:2]
        for i, j in edges:
            a, b = X[i, :2], X[j, :2]
            A = np.column_stack([b - a, r0 - r1])
            if abs(np.linalg.det(A)) < 1e-12:
                continue  # parallel
            t, s = np.linalg.solve(A, r0 - a)
            if 1e-6 < t < 1 - 1e-6 and 1e-6 < s < 1 - 1e-6:
                points.append(([i, j], [1 - t, t], np.r_[a + t * (b - a), 0.1]))
    bottom = np.flatnonzero(np.isclose(X[:, 2], 0.0))
    active = np.ones(len(points), dtype=bool)
    seen: dict[bytes, float] = {}  # active set -> sag: a tilting box may cycle between two sets that agree
    for _ in range(50):
        solved_with = active.tobytes()
        rows, cols, vals, r = [], [], [], 0
        for k, (nodes, w, q) in enumerate(points):
            if not active[k]:
                continue
            for ax in range(3):  # sum_i w_i u_i = U + theta x (q - c)   (stick)
                e = np.eye(3)[ax]
                for node, wi in zip(nodes, w):
                    rows.append(r); cols.append(3 * node + ax); vals.append(wi)
                rows.append(r); cols.append(3 * N + ax); vals.append(-1.0)
                g = np.cross(q - c, e)
                for j in range(3):
                    rows.append(r); cols.append(3 * N + 3 + j); vals.append(-g[j])
                r += 1
        for node in bottom:
            for ax in range(3):
                rows.append(r); cols.append(3 * node + ax); vals.append(1.0)
                r += 1
        C = sparse.csr_matrix((vals, (rows, cols)), shape=(r, 3 * N + 6))
        Kb = sparse.block_diag([K, sparse.csr_matrix((6, 6))])
        rhs = np.r_[f, 0, 0, -mass * 9.81, 0, 0, 0, np.zeros(r)]  # the box's weight acts above c: no moment
        # rows beside rows (rim points on edges of nodes held too) are redundant: a compliance of 1e-12 m/N makes
        # the system regular and leaves the sag unchanged (forces of tens of N: 1e-11 m)
        sol = spla.spsolve(sparse.bmat([[Kb, C.T], [C, -1e-12 * sparse.eye(r)]]).tocsc(), rhs)
        u, U, theta, lam = sol[:3 * N].reshape(-1, 3), sol[3 * N:3 * N + 3], sol[3 * N + 3:3 * N + 6], sol[3 * N + 6:]
        seen[solved_with] = -U[2]
        act = np.flatnonzero(active)
        push = lam[2:3 * len(act):3]  # > 0: the box pushes the soft point down
        pulls = push < -1e-9 * np.abs(push).max()
        changed = bool(pulls.any())
        active[act[pulls]] = False
        for k in np.flatnonzero(~active):
            nodes, w, q = points[k]
            z_soft = sum(wi * (X[node, 2] + u[node, 2]) for node, wi in zip(nodes, w))
            if z_soft > 0.1 + U[2] + np.cross(theta, q - c)[2] + 1e-10:
                active[k] = changed = True
        if not changed:
            return -U[2]
        if active.tobytes() in seen:  # a cycle: fine if its sets give the same sag
            cycle = [seen[active.tobytes()], -U[2]]
            assert abs(cycle[0] - cycle[1]) <= 1e-3 * abs(cycle[1]), cycle  # the test allows 10%
            return float(np.mean(cycle))
    raise AssertionError("no consistent contact set")


# dt 0.002 costs 20-50 s a case: the heavy box stays in the default run, the lighter two are slow (-m slow)
BOX_CASES = [pytest.param(dt, mass, marks=pytest.mark.slow if dt == 0.002 and mass < 2.0 else (), id=f"{dt}-{mass}")
             for dt in (0.01, 0.002) for mass in (0.1, 0.5, 2.0)]


@pytest.mark.parametrize("dt, mass", BOX_CASES)
@pytest.mark.parametrize("offset", [0.0, 0.00625], ids=["centred", "near-edge"])
def test_light_and_heavy_boxes_settle_on_a_soft_block(mass, dt, offset):
    """Boxes of 0.1 to 2 kg set 1 mm above a 1 kg soft block (E = 1e5) on a plane: each settles, never rises,
    sags as the static FEM solution says, its rim does not dig in between the nodes, and the scene never gains
    energy."""
    world = World(dt=dt)
    world.add_plane()
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05))
    block = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
    world.add_soft(block, friction=0.5)
    box = world.add_box((HALF,) * 3, position=(offset, 0, 0.1 + HALF + 0.001), mass=mass)
    z0 = box.pose()[0][2]
    energies, highest = [world.energy()["total"]], z0
    for _ in range(int(round(2.0 / dt))):
        world.step()
        energies.append(world.energy()["total"])
        highest = max(highest, box.pose()[0][2])
    assert np.linalg.norm(box.velocity()[0]) < 0.01  # settled
    assert highest <= z0 + 1e-9  # never thrown up
    sag = 0.1 - (box.pose()[0][2] - HALF)
    assert sag == pytest.approx(static_box_on_block(mass, offset), rel=0.10)
    assert energy_never_grows(energies) <= 1e-9
    assert world.max_penetration() < 1e-3
    # the box's bottom rim lies across soft faces between their nodes: by an independent test (triangle samples
    # against the box's exact distance, the box's edge points inside the soft surface), it does not dig in
    assert geo.rigid_penetration(world.client, box.id, block.positions, mesh.surface_triangles()) < 1e-4



def test_movable_edges_off_lets_the_rim_dig_in():
    """World(movable_edges=False) leaves out the rows of a dynamic box's rim across soft faces (a cheaper step): the
    2 kg box's rim then lies inside the block between its nodes, by the independent test, where with them (the
    default, test_light_and_heavy_boxes_settle_on_a_soft_block) it does not."""
    depth = {}
    for on in (True, False):
        world = World(dt=0.01, movable_edges=on)
        world.add_plane()
        mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05))
        block = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
        world.add_soft(block, friction=0.5)
        box = world.add_box((HALF,) * 3, position=(0.00625, 0, 0.1 + HALF + 0.001), mass=2.0)
        world.run(1.0)
        depth[on] = geo.rigid_penetration(world.client, box.id, block.positions, mesh.surface_triangles())
    assert depth[True] < 1e-4 < 2e-4 < depth[False]

# ----------------------------------------------------------------------------------------------- pendulum
def _hinged_rod(world: World, L=0.5, a=0.02, mass=1.0, pivot=(0, 0, 1.0)) -> int:
    """A rod of length L hanging from a revolute joint (axis y) at ``pivot``, a pybullet multibody."""
    cid = world.client
    rod = p.createCollisionShape(p.GEOM_BOX, halfExtents=[a / 2, a / 2, L / 2], collisionFramePosition=[0, 0, -L / 2],
                                 physicsClientId=cid)
    body = p.createMultiBody(0, -1, basePosition=pivot, linkMasses=[mass], linkCollisionShapeIndices=[rod],
                             linkVisualShapeIndices=[-1], linkPositions=[[0, 0, 0]], linkOrientations=[[0, 0, 0, 1]],
                             linkInertialFramePositions=[[0, 0, -L / 2]], linkInertialFrameOrientations=[[0, 0, 0, 1]],
                             linkParentIndices=[0], linkJointTypes=[p.JOINT_REVOLUTE], linkJointAxis=[[0, 1, 0]],
                             physicsClientId=cid)
    p.changeDynamics(body, 0, linearDamping=0, angularDamping=0, jointDamping=0, physicsClientId=cid)
    p.setJointMotorControl2(body, 0, p.VELOCITY_CONTROL, force=0, physicsClientId=cid)
    return body


def test_pendulum_with_an_attached_soft_block_swings_with_the_compound_period():
    world = World(dt=0.01)
    L, s, m_r, pivot = 0.5, 0.1, 1.0, np.array([0, 0, 1.0])
    rod = _hinged_rod(world, L, mass=m_r, pivot=tuple(pivot))
    mesh = sb.box_mesh((s, s, s), (2, 2, 2), "tet10", center=(0, 0, pivot[2] - L - s / 2))
    block = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), damping=(0.0, 0.0005))
    world.add_soft(block)
    world.attach(block, np.flatnonzero(np.isclose(mesh.nodes[:, 2], pivot[2] - L)), rod, link=0)
    m_b, d = block.total_mass, L + s / 2
    inertia = m_r * L ** 2 / 3 + m_b * s ** 2 / 6 + m_b * d ** 2
    period = 2 * math.pi * math.sqrt(inertia / (9.81 * (m_r * L / 2 + m_b * d)))
    bare = 2 * math.pi * math.sqrt(2 * L / (3 * 9.81))
    assert period / bare > 1.15  # the block matters
    theta = math.radians(5)
    p.resetJointState(rod, 0, theta, 0, physicsClientId=world.client)
    R = np.array([[math.cos(theta), 0, math.sin(theta)], [0, 1, 0], [-math.sin(theta), 0, math.cos(theta)]])
    block.positions[:] = (block.positions - pivot) @ R.T + pivot
    angles = []
    for _ in range(300):
        world.step()
        angles.append(p.getJointState(rod, 0, physicsClientId=world.client)[0])
    a = np.array(angles)
    t = world.dt * np.arange(1, len(a) + 1)
    z = np.flatnonzero((a[:-1] > 0) & (a[1:] <= 0))
    crossings = t[z] + world.dt * a[z] / (a[z] - a[z + 1])
    assert abs(np.diff(crossings).mean() - period) < 0.03 * period
    # the block's weight loads the rod through the attachment
    assert np.linalg.norm(world.contact_force(rod, link=0)) > 0.5 * m_b * 9.81


def test_off_centre_block_tilts_the_rod_as_statics_says():
    world = World(dt=0.01)
    L, s, m_r, off, pivot = 0.5, 0.1, 1.0, 0.03, np.array([0, 0, 1.0])
    rod = _hinged_rod(world, L, mass=m_r, pivot=tuple(pivot))
    mesh = sb.box_mesh((s, s, s), (2, 2, 2), "tet10", center=(off, 0, pivot[2] - L - s / 2))
    # classic Rayleigh damping settles the swing within the run (the default spares the block's rigid motion, which
    # the swing is, and the rod has no damping of its own)
    block = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), damping=(2.0, 0.002), damp_rigid=True)
    world.add_soft(block)
    X = mesh.nodes
    world.attach(block, np.flatnonzero(np.isclose(X[:, 2], pivot[2] - L) & (np.abs(X[:, 0]) <= 0.025 + 1e-9)), rod, link=0)
    world.run(6.0)
    m_b = block.total_mass
    statics = math.atan2(m_b * off, m_r * L / 2 + m_b * (L + s / 2))
    angle = p.getJointState(rod, 0, physicsClientId=world.client)[0]
    assert angle == pytest.approx(statics, rel=0.05)


def test_block_attached_flush_against_a_swinging_rod_is_stable():
    """A block whose face touches the rod it is attached to: the contacts with that link are off by default,
    so nothing feeds back; the swing keeps its energy bounded."""
    world = World(dt=0.01)
    L, a, pivot = 0.5, 0.02, np.array([0, 0, 1.0])
    rod = _hinged_rod(world, L, a=a, mass=1.0, pivot=tuple(pivot))
    mesh = sb.box_mesh((0.06, 0.06, 0.06), (2, 2, 2), "tet10", center=(a / 2 + 0.03, 0, pivot[2] - L + 0.05))
    block = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0))
    world.add_soft(block)
    world.attach(block, np.flatnonzero(np.isclose(mesh.nodes[:, 0], a / 2)), rod, link=0)
    p.resetJointState(rod, 0, 0.5, 0, physicsClientId=world.client)
    R = np.array([[math.cos(0.5), 0, math.sin(0.5)], [0, 1, 0], [-math.sin(0.5), 0, math.cos(0.5)]])
    block.positions[:] = (block.positions - pivot) @ R.T + pivot
    energies = [world.energy()["total"]]
    spin = 0.0
    for _ in range(200):
        world.step()
        energies.append(world.energy()["total"])
        spin = max(spin, abs(p.getJointState(rod, 0, physicsClientId=world.client)[1]))
    assert spin < 5.0  # a 0.5 rad swing of a 0.5 m pendulum: about 2 rad/s at the bottom
    # pybullet integrates the rod by symplectic Euler, whose energy oscillates by about 1e-3 of itself (the bare
    # rod here: up to 8e-3 J above its start over 2 s; rod and block with no mass damping at all, 1.10e-3 of it, as
    # with the default damping, which spares the block's rigid motion): no more than that, and none gained over the run
    e = np.asarray(energies)
    assert e.max() - e[0] <= 1.5e-3 * abs(e[0]) and e[-1] < e[0]


# ----------------------------------------------------------------------------------------------- momentum
@pytest.mark.parametrize("target", ["free box", "free two-link body"])
def test_momentum_is_exchanged_exactly(target):
    """In zero gravity a soft ball hits a free box or a free two-link body (base and a link on a prismatic
    joint: pybullet itself conserves the momentum of such a body exactly, not of a spinning revolute one):
    the total linear momentum stays put to 1e-9, so the reactions land on the right links."""
    world = World(dt=0.005, gravity=(0, 0, 0))
    cid = world.client
    ball = sb.FemBody(sb.ball_mesh(0.08, 3, "tet4", center=(-0.25, 0, 0)), sb.LinearElastic(2e5, 0.3, 1000),
                      damping=(0.0, 0.002))
    world.add_soft(ball, friction=0.3)
    if target == "free box":
        rid = world.add_box((0.06, 0.06, 0.06), position=(0.0, 0.02, 0.01), mass=1.5).id
        links = [(-1, 1.5)]
    else:
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.05] * 3, physicsClientId=cid)
        rid = p.createMultiBody(1.0, col, basePosition=[0.0, 0.0, 0.0], linkMasses=[0.7], linkCollisionShapeIndices=[col],
                                linkVisualShapeIndices=[-1], linkPositions=[[0.12, 0, 0.0]], linkOrientations=[[0, 0, 0, 1]],
                                linkInertialFramePositions=[[0, 0, 0]], linkInertialFrameOrientations=[[0, 0, 0, 1]],
                                linkParentIndices=[0], linkJointTypes=[p.JOINT_PRISMATIC], linkJointAxis=[[1, 0, 0]],
                                physicsClientId=cid)
        for link in (-1, 0):
            p.changeDynamics(rid, link, linearDamping=0, angularDamping=0, physicsClientId=cid)
        p.setJointMotorControl2(rid, 0, p.VELOCITY_CONTROL, force=0, physicsClientId=cid)
        links = [(-1, 1.0), (0, 0.7)]
    ball.velocities[:] = [3.0, 0.0, 0.0]

    def momentum():
        world.adapter.invalidate()
        return ball.node_mass @ ball.velocities + sum(m * world.adapter.velocity(rid, link)[0] for link, m in links)

    p0, worst, pushed = momentum(), 0.0, 0.0
    for _ in range(200):
        world.step()
        worst = max(worst, np.linalg.norm(momentum() - p0) / np.linalg.norm(p0))
        pushed = max(pushed, np.linalg.norm(world.contact_force(rid)))
    assert pushed > 10.0  # a real collision
    assert worst < 1e-9


# ------------------------------------------------------------------------------------------ guard, forces
def test_energy_guard_raises_and_keeps_the_state_of_soft_and_rigid_bodies():
    world = World(dt=0.01, max_energy=0.05)
    world.add_plane()
    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.06)), sb.LinearElastic(1e5, 0.3, 500))
    world.add_soft(body)
    box = world.add_box((0.02, 0.02, 0.02), position=(0, 0, 0.3), mass=0.2)
    with pytest.raises(SimulationDiverged, match="max_energy"):
        for _ in range(100):
            before = (body.positions.copy(), box.pose()[0].copy(), world.t)
            world.step()  # the falling box gains kinetic energy above the bound
    world.adapter.invalidate()
    np.testing.assert_array_equal(body.positions, before[0])
    np.testing.assert_allclose(box.pose()[0], before[1], atol=1e-12)
    assert world.t == before[2]


@pytest.mark.parametrize("mu", [0.1, 0.5])
def test_dynamic_box_on_a_soft_incline_slides_or_sticks_by_coulomb(mu):
    """A free box on a soft slab tilted 20 degrees (two-way coupled: the dense contact problem with friction):
    mu = 0.1 slides down with g (sin - mu cos), mu = 0.5 (> tan 20) stays. Its corners cross the slab's
    triangles on the way: no bump (a corner is never held back by a face its neighbour holds)."""
    th = math.radians(20)
    Ry = np.array([[math.cos(th), 0, math.sin(th)], [0, 1, 0], [-math.sin(th), 0, math.cos(th)]])
    world = World(dt=0.01)
    base = sb.box_mesh((1.6, 0.4, 0.05), (16, 4, 1), "hex8", center=(0, 0, -0.025))
    incline = sb.FemBody(sb.Mesh(base.nodes @ Ry.T, base.elements, "hex8"), sb.LinearElastic(1e7, 0.3, 1000.0))
    incline.fix(np.flatnonzero(np.isclose(base.nodes[:, 2], -0.05)))
    world.add_soft(incline, friction=mu)
    box = world.add_box((0.05, 0.05, 0.025), position=(Ry @ [-0.6, 0, 0.025 + 1e-4]).tolist(),
                        orientation=p.getQuaternionFromEuler([0, th, 0]), mass=0.5)
    p.changeDynamics(box.id, -1, linearDamping=0, angularDamping=0, physicsClientId=world.client)
    down = Ry @ [1.0, 0, 0]
    v = []
    for _ in range(70):
        world.step()
        v.append(np.array(box.velocity()[0]) @ down)
    expected = max(9.81 * (math.sin(th) - mu * math.cos(th)), 0.0)
    accel = np.polyfit(world.dt * np.arange(10, 70), v[10:], 1)[0]
    assert accel == pytest.approx(expected, abs=0.02 * 9.81 * math.sin(th))
    assert np.diff(v[10:]).min() > -1e-3  # never held back


def test_contact_force_on_a_resting_box_is_its_weight():
    world = World(dt=0.01)
    world.add_plane()
    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05)),
                      sb.LinearElastic(1e5, 0.3, 1000), damping=(0.1, 0.001))
    world.add_soft(body, friction=0.5)
    box = world.add_box((HALF,) * 3, position=(0, 0, 0.1 + HALF + 0.001), mass=0.5)
    world.run(1.5)
    np.testing.assert_allclose(world.contact_force(box), [0, 0, 0.5 * 9.81], atol=0.02)


def test_package_level_api():
    import integration

    assert integration.World is World
    from integration import Recorder, RigidLink  # noqa: F401
    with pytest.raises(AttributeError):
        integration.Nope  # noqa: B018


def test_grasp_example_picks_the_cube_and_records_the_robot(tmp_path):
    """examples/robot_grasp.py in a short form: a Panda from pybullet_data lifts a soft cube 0.2 m off a table
    and sets it down; the recording holds every link of the robot in its real shape."""
    import importlib.util
    from pathlib import Path

    sys_path = Path(__file__).resolve().parents[1] / "examples" / "robot_grasp.py"
    spec = importlib.util.spec_from_file_location("robot_grasp", sys_path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    path = tmp_path / "grasp.rrd"
    rows = {r["phase"]: r for r in example.run(hold=0.2, dt=0.01, record=str(path))}
    assert rows["close"]["cube_z"] < 0.03 < 0.2 < rows["hold"]["cube_z"]  # picked up about 0.2 m
    # held by both fingers with their motors' force limit (motors set through World.set_motor, rows of the coupled
    # problem: at dt 0.01 pybullet's own motors gripped with 1.1 of 20 N)
    for side in ("grip_left", "grip_right"):
        assert rows["hold"][side] == pytest.approx(example.FINGER_FORCE, rel=0.05)
    assert rows["hold"]["slip_mm"] < 3.0
    assert max(r.get("penetration_mm", 0.0) for r in rows.values()) < 1.0
    assert rows["release"]["cube_z"] < 0.03  # back on the table
    from test_recording import read, verify

    verify(path)
    data, static = read(path)
    links = {e for e in data if e.startswith("/world/rigid/panda")}
    assert len(links) == 11  # the base and the ten links with a collision shape move, each with its pose
    assert sum(e.startswith("/world/rigid/panda") and e.endswith("shape0") for e in static) == 11


@pytest.mark.slow  # about two minutes: 4,400 steps
def test_grasp_grips_with_the_motors_limit_at_a_small_step_too():
    """The grasp at dt 0.001: the grip is the finger motors' force limit as at dt 0.01 (within 5%), so whether the cube
    slips does not depend on the step (pybullet's own motors gripped with 1.1 of 20 N at dt 0.01, 3.7 at 0.005)."""
    import importlib.util
    from pathlib import Path

    sys_path = Path(__file__).resolve().parents[1] / "examples" / "robot_grasp.py"
    spec = importlib.util.spec_from_file_location("robot_grasp", sys_path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    rows = {r["phase"]: r for r in example.run(hold=0.2, dt=0.001)}
    for side in ("grip_left", "grip_right"):
        assert rows["hold"][side] == pytest.approx(example.FINGER_FORCE, rel=0.05)
    assert rows["hold"]["cube_z"] > 0.2


@pytest.mark.slow  # about a minute: the Newton step costs several solves per step
def test_grasp_example_with_the_newton_step():
    """The same pick-and-place with scheme="newton": the grasp holds as with the warped step. Friction between the
    fingers and the cube can make the iterates alternate between stick/slip states at the start of the lift; such a
    step is accepted on that cycle (NewtonReport.cycled) with one warning instead of refusing the run. (With the
    damping of the strain over the step, softbody.newton, this grasp's iterations converge: no step cycles.)"""
    import importlib.util
    from pathlib import Path

    sys_path = Path(__file__).resolve().parents[1] / "examples" / "robot_grasp.py"
    spec = importlib.util.spec_from_file_location("robot_grasp", sys_path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = {r["phase"]: r for r in example.run(hold=0.2, dt=0.01, scheme="newton")}
    assert len([w for w in caught if "stalled on contacts" in str(w.message)]) <= 1  # said once, if at all
    assert rows["close"]["cube_z"] < 0.03 < 0.2 < rows["hold"]["cube_z"]
    assert min(rows["hold"]["grip_left"], rows["hold"]["grip_right"]) > 0.5
    assert rows["hold"]["slip_mm"] < 3.0
    assert max(r.get("penetration_mm", 0.0) for r in rows.values()) < 1.0
    assert rows["release"]["cube_z"] < 0.03
