"""pybullet's user constraints inside the coupled step (integration/constraints.py): a rod hung by a point-to-point
or a fixed constraint, with a soft block attached to it, comes to rest where statics says; the constraint holds."""
from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

import softbody as sb
from integration import World

L, S, M_ROD, OFF = 0.5, 0.1, 1.0, 0.03  # rod length, block size [m], rod mass [kg], the block's offset [m]
PIVOT = np.array([0.0, 0.0, 1.0])


def _rod(cid: int) -> int:
    """A free 1 kg rod (a single-body multibody), its top at PIVOT, hanging."""
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.01, 0.01, L / 2], physicsClientId=cid)
    return p.createMultiBody(M_ROD, shape, basePosition=(PIVOT - [0, 0, L / 2]).tolist(), physicsClientId=cid)


def _block(world: World, rod: int) -> sb.FemBody:
    """A stiff soft block (E 1e7) under the rod, OFF to the side, attached by its top nodes near the rod's end."""
    mesh = sb.box_mesh((S, S, S), (2, 2, 2), "tet10", center=(OFF, 0, PIVOT[2] - L - S / 2))
    block = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), damping=(2.0, 0.002), damp_rigid=True)
    world.add_soft(block)
    X = mesh.nodes
    world.attach(block, np.flatnonzero(np.isclose(X[:, 2], PIVOT[2] - L) & (np.abs(X[:, 0]) <= 0.025 + 1e-9)), rod)
    return block


def _tilt(cid: int, rod: int) -> float:
    """The rod's angle from the vertical [rad]."""
    _, q = p.getBasePositionAndOrientation(rod, physicsClientId=cid)
    axis = np.array(p.getMatrixFromQuaternion(q)).reshape(3, 3)[:, 2]
    return math.atan2(math.hypot(axis[0], axis[1]), axis[2])


def test_a_rod_hung_by_a_point_to_point_constraint_tilts_as_statics_says():
    """The rod hangs from the world by pybullet's point-to-point constraint at its top; the attached block pulls it
    aside: at rest the angle is statics' atan(m_b off / (m_r L / 2 + m_b (L + s / 2))) within 0.1 degrees, and the
    pivot has stayed at its place (when the coupled solve saw the rod as free, the block's weight pulled it 5.07 mm
    below its pivot every step, pybullet pulling it back the next)."""
    world = World(dt=0.01)
    cid = world.client
    rod = _rod(cid)
    p.createConstraint(rod, -1, -1, -1, p.JOINT_POINT2POINT, [0, 0, 0], [0, 0, L / 2], PIVOT.tolist(),
                       physicsClientId=cid)
    block = _block(world, rod)
    world.run(6.0)
    m_b = block.total_mass
    statics = math.atan2(m_b * OFF, M_ROD * L / 2 + m_b * (L + S / 2))
    assert math.degrees(_tilt(cid, rod)) == pytest.approx(math.degrees(statics), abs=0.1)
    c, q = p.getBasePositionAndOrientation(rod, physicsClientId=cid)
    top = np.asarray(c) + np.array(p.getMatrixFromQuaternion(q)).reshape(3, 3) @ [0, 0, L / 2]
    assert np.linalg.norm(top - PIVOT) < 1e-4
    assert np.abs(block.velocities).max() < 1e-3


def test_a_rod_held_by_a_fixed_constraint_stays_put():
    """A fixed constraint holds the rod's top to the world: the attached block's weight does not turn it (the tilt
    stays within 0.01 degrees), and the constraint carries rod and block: their weight, and the block's moment about
    the pivot, m_b g OFF (pybullet's share and the coupled solve's together)."""
    world = World(dt=0.01)
    cid = world.client
    rod = _rod(cid)
    p.createConstraint(rod, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, L / 2], PIVOT.tolist(), physicsClientId=cid)
    block = _block(world, rod)
    world.run(2.0)
    assert math.degrees(_tilt(cid, rod)) < 0.01
    weight = (M_ROD + block.total_mass) * 9.81
    assert abs(block.positions[:, 2].mean() - (PIVOT[2] - L - S / 2)) < 1e-3
    forces = world.report.joint_forces
    lift = sum(f for (kind, _, row), f in forces.items() if kind == "fixed" and row == 2)
    assert lift == pytest.approx(weight, rel=0.01)
    torque = sum(f for (kind, _, row), f in forces.items() if kind == "fixed" and row == 4)
    assert torque == pytest.approx(-block.total_mass * 9.81 * OFF, rel=0.02)


def test_a_gear_holds_while_a_soft_block_turns_one_wheel():
    """Two wheels on revolute joints (horizontal axes) geared by pybullet's gear constraint (ratio 2: qd_0 + 2 qd_1 =
    0); a soft block attached off-axis to wheel 1 turns it by its weight: the gear holds at the end of every step
    (to 1e-4 of the speeds: the rows are near rigid, not rigid), though only the coupled solve sees the block."""
    world = World(dt=0.01)
    cid = world.client
    disc = p.createCollisionShape(p.GEOM_CYLINDER, radius=0.05, height=0.02, physicsClientId=cid)
    y_axis = p.getQuaternionFromEuler([np.pi / 2, 0, 0])
    wheels = p.createMultiBody(0, -1, basePosition=[0, 0, 1.0], linkMasses=[1.0, 1.0],
                               linkCollisionShapeIndices=[disc, disc], linkVisualShapeIndices=[-1, -1],
                               linkPositions=[[0, 0, 0], [0.3, 0, 0]], linkOrientations=[y_axis] * 2,
                               linkInertialFramePositions=[[0, 0, 0]] * 2,
                               linkInertialFrameOrientations=[[0, 0, 0, 1]] * 2, linkParentIndices=[0, 0],
                               linkJointTypes=[p.JOINT_REVOLUTE] * 2, linkJointAxis=[[0, 0, 1]] * 2,
                               physicsClientId=cid)
    for j in range(2):
        p.setJointMotorControl2(wheels, j, p.VELOCITY_CONTROL, force=0, physicsClientId=cid)
    gear = p.createConstraint(wheels, 0, wheels, 1, p.JOINT_GEAR, [0, 0, 1], [0, 0, 0], [0, 0, 0],
                              physicsClientId=cid)
    p.changeConstraint(gear, gearRatio=2.0, maxForce=1000, physicsClientId=cid)
    mesh = sb.box_mesh((0.04, 0.04, 0.04), (1, 1, 1), "tet4", center=(0.3 + 0.08, 0, 1.0))
    block = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0))
    world.add_soft(block)
    world.attach(block, np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.36)), wheels, link=1)
    worst, fastest = 0.0, 0.0
    for _ in range(30):
        world.step()
        qd = [s[1] for s in p.getJointStates(wheels, [0, 1], physicsClientId=cid)]
        worst = max(worst, abs(qd[0] + 2.0 * qd[1]))
        fastest = max(fastest, abs(qd[1]))
    assert fastest > 0.5  # the block's weight turns the wheels
    assert worst < 1e-4 * fastest
