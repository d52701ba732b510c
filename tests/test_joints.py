"""Joint motors and joint limits inside the coupled step (integration/joints.py): a motor's target is pybullet's own,
a position motor pressing through a soft pad exerts its force limit at any dt (as against a rigid block in plain
pybullet), a joint limit holds in soft contact, and a motor set in pybullet directly is warned about."""
from __future__ import annotations

import warnings

import numpy as np
import pybullet as p
import pytest

import softbody as sb
from integration import World
from integration.joints import Motor

URDF = """<?xml version="1.0"?>
<robot name="finger">
  <link name="base"/>
  <link name="finger">
    <inertial><mass value="{mass}"/><inertia ixx="1e-5" iyy="1e-5" izz="1e-5" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><box size="{size} {size} {size}"/></geometry></collision>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="base"/><child link="finger"/><axis xyz="1 0 0"/>
    <limit lower="{lower}" upper="{upper}" effort="1000" velocity="100"/>
  </joint>
</robot>
"""
SIZE = 0.024  # [m] the finger's cube; its face's rim lies between the pad's nodes (1 cm apart)
HEIGHT = 0.1


def _finger(cid: int, tmp_path, lower: float = -1.0, upper: float = 1.0, mass: float = 0.1, size: float = SIZE) -> int:
    """A 0.1 kg cube on a prismatic joint along x (a fixed base at (0, 0, HEIGHT)): pybullet body id."""
    path = tmp_path / "finger.urdf"
    path.write_text(URDF.format(mass=mass, size=size, lower=lower, upper=upper))
    body = p.loadURDF(str(path), [0, 0, HEIGHT], useFixedBase=True, physicsClientId=cid)
    p.changeDynamics(body, 0, linearDamping=0, angularDamping=0, jointDamping=0, physicsClientId=cid)
    return body


def _pad(world: World, E: float = 1e6, size: float = SIZE) -> sb.FemBody:
    """A 2 x 4 x 4 cm soft pad 0.2 mm in front of the face of a finger of ``size`` (x), its back face fixed."""
    x0 = size / 2 + 0.0002
    mesh = sb.box_mesh((0.02, 0.04, 0.04), (2, 4, 4), "tet4", center=(x0 + 0.01, 0, HEIGHT))
    pad = sb.FemBody(mesh, sb.LinearElastic(E, 0.3, 1000.0), damping=(0.1, 0.002))
    pad.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], mesh.nodes[:, 0].max())))
    world.add_soft(pad)
    return pad


@pytest.mark.parametrize("mode", ["position", "velocity"])
def test_a_motors_target_is_pybullets_own(tmp_path, mode):
    """Motor.target, the velocity a motor drives its joint to over a step, against pybullet's own motor: the finger
    in plain pybullet (no gravity along the joint, a force limit that does not bind) from a given position and
    velocity, one step; and a force limit that binds changes the velocity by exactly F h / m."""
    h = 0.01
    cid = p.connect(p.DIRECT)
    try:
        p.setTimeStep(h, physicsClientId=cid)
        body = _finger(cid, tmp_path)
        for q, qd, F in ((0.01, 0.2, 1e4), (-0.02, -0.1, 1e4), (0.01, 0.0, 0.5)):
            motor = Motor(body, 0, mode, position=0.03, velocity=0.4, force=F, position_gain=0.3, velocity_gain=0.7)
            p.resetJointState(body, 0, q, qd, physicsClientId=cid)
            control, kw = motor.pybullet_args(p)
            p.setJointMotorControl2(body, 0, control, physicsClientId=cid, **kw)
            p.stepSimulation(physicsClientId=cid)
            v = p.getJointState(body, 0, physicsClientId=cid)[1]
            want = motor.target(q, qd, h)
            if F > 1e3:
                assert v == pytest.approx(want, rel=1e-6, abs=1e-9)
            else:
                assert v == pytest.approx(qd + np.sign(want - qd) * F * h / 0.1, rel=1e-6)
    finally:
        p.disconnect(cid)


@pytest.mark.parametrize("dt", [0.01, 1 / 240, 1 / 1000])
def test_a_motor_presses_through_a_soft_pad_with_its_force_limit(tmp_path, dt):
    """A position motor (force limit 20 N) driving the finger far into a soft pad whose back is fixed: at rest the pad
    pushes back with the motor's limit, 20 N within 1%, at dt 0.01, 1/240 and 1/1000 (as the same motor does
    against a rigid block in plain pybullet). Measured on the contact side (World.contact_force), not the motor's."""
    world = World(dt=dt, gravity=(0, 0, -9.81))
    finger = _finger(world.client, tmp_path)
    pad = _pad(world)
    world.set_motor(finger, 0, "position", target_position=0.05, force=20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning: nothing lagged, nothing intersecting
        world.run(0.3)
    force = world.contact_force(finger, 0)
    assert force[0] == pytest.approx(-20.0, rel=0.01)
    assert world.motor_force(finger, 0) == pytest.approx(20.0, rel=1e-6)  # at its limit, pushing
    assert np.abs(pad.velocities).max() < 1e-3  # at rest


def test_a_motor_set_in_pybullet_directly_is_warned_about(tmp_path):
    """The same motor set with pybullet's setJointMotorControl2 acts in pybullet's step, before the soft contacts:
    at dt 0.01 it presses with about m kp (q* - q) / dt^2 (5 N here, for a 20 N limit), and the World says so."""
    world = World(dt=0.01)
    finger = _finger(world.client, tmp_path)
    _pad(world)
    p.setJointMotorControl2(finger, 0, p.POSITION_CONTROL, targetPosition=0.05, force=20.0,
                            physicsClientId=world.client)
    with pytest.warns(UserWarning, match="set in pybullet directly"):
        world.run(0.3)
    q = p.getJointState(finger, 0, physicsClientId=world.client)[0]
    lagged = 0.1 * 0.1 * (0.05 - q) / 0.01 ** 2
    assert -world.contact_force(finger, 0)[0] == pytest.approx(lagged, rel=0.05)
    assert lagged < 10.0


def test_a_position_target_beyond_the_limits_is_clamped_as_pybullet_does(tmp_path):
    """pybullet clamps a position motor's target to the joint's URDF limits: one step from rest towards a target 0.5
    m beyond the upper limit 0.02 m gives the velocity Motor.target gives with the limits, not without them."""
    h = 0.01
    cid = p.connect(p.DIRECT)
    try:
        p.setTimeStep(h, physicsClientId=cid)
        body = _finger(cid, tmp_path, lower=-0.02, upper=0.02)
        motor = Motor(body, 0, "position", position=0.5, force=1e4)
        p.resetJointState(body, 0, 0.01, 0.0, physicsClientId=cid)
        control, kw = motor.pybullet_args(p)
        p.setJointMotorControl2(body, 0, control, physicsClientId=cid, **kw)
        p.stepSimulation(physicsClientId=cid)
        v = p.getJointState(body, 0, physicsClientId=cid)[1]
        assert v == pytest.approx(motor.target(0.01, 0.0, h, (-0.02, 0.02)), rel=1e-6)
        assert v != pytest.approx(motor.target(0.01, 0.0, h), rel=0.1)
    finally:
        p.disconnect(cid)


def test_a_joint_limit_holds_when_a_soft_body_pushes_the_joint_into_it(tmp_path):
    """A free soft block (no gravity) hits the finger, whose joint is free (a motor of force 0) and has its lower limit
    1 mm behind: the push reaches the finger only in the coupled solve (pybullet's step sees no contact), and the
    limit's row stops the joint at its limit (to 1 um) at the end of every step, instead of pybullet pulling it back
    a step later; the block bounces off."""
    lower = -0.001
    world = World(dt=0.005, gravity=(0, 0, 0))
    finger = _finger(world.client, tmp_path, lower=lower)
    world.set_motor(finger, 0, "velocity", force=0.0)
    x0 = SIZE / 2 + 0.0005
    mesh = sb.box_mesh((0.02, 0.03, 0.03), (2, 3, 3), "tet4", center=(x0 + 0.01, 0, HEIGHT))
    block = sb.FemBody(mesh, sb.LinearElastic(1e6, 0.3, 1000.0), damping=(0.0, 0.001))
    block.velocities[:] = (-0.5, 0.0, 0.0)
    world.add_soft(block)
    lowest = np.inf
    for _ in range(60):
        world.step()
        lowest = min(lowest, p.getJointState(finger, 0, physicsClientId=world.client)[0])
    assert lowest == pytest.approx(lower, abs=1e-6)  # pushed to the limit, not beyond
    assert block.velocities[:, 0].mean() > 0.0  # bounced off
    assert world.report.joint_forces.get(("lower", finger, 0), 0.0) >= 0.0


def test_set_motor_names_bad_input(tmp_path):
    world = World(dt=0.01)
    finger = _finger(world.client, tmp_path)
    with pytest.raises(sb.InvalidInputError, match="no pybullet body 99"):
        world.set_motor(99, 0)
    with pytest.raises(sb.InvalidInputError, match="joint 3 of body"):
        world.set_motor(finger, 3)
    with pytest.raises(sb.InvalidInputError, match="force must be"):
        world.set_motor(finger, 0, force=-1.0)
    with pytest.raises(sb.InvalidInputError, match="torque control"):
        world.set_motor(finger, 0, mode=p.TORQUE_CONTROL)
    with pytest.raises(sb.InvalidInputError, match="mode must be one of"):
        world.set_motor(finger, 0, mode="torque")
    with pytest.raises(sb.InvalidInputError, match="max_velocity must be"):
        world.set_motor(finger, 0, max_velocity=-1.0)


def test_set_motors_sets_each_joint_as_set_motor_does(tmp_path):
    """set_motors (setJointMotorControlArray's form): one Motor per joint with its own target and the shared force;
    a list of the wrong length is refused, naming it."""
    world = World(dt=0.01)
    finger = _finger(world.client, tmp_path)
    motors = world.set_motors(finger, [0], "velocity", target_velocities=[0.3], forces=7.0)
    assert motors == [world.motors.get(finger, 0)] and motors[0].velocity == 0.3 and motors[0].force == 7.0
    assert motors[0] == Motor(finger, 0, "velocity", 0.0, 0.3, 7.0)
    with pytest.raises(sb.InvalidInputError, match="forces needs one value per joint"):
        world.set_motors(finger, [0], forces=[1.0, 2.0])


def test_set_motors_gives_each_joint_its_own_target():
    """The KUKA iiwa's seven joints in one call: seven Motors, each with its own target and the shared force; a
    joint that is not revolute or prismatic is refused before any is set."""
    import pybullet_data

    world = World(dt=0.01)
    cid = world.client
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    kuka = p.loadURDF("kuka_iiwa/model.urdf", useFixedBase=True, physicsClientId=cid)
    targets = [0.1 * j for j in range(7)]
    motors = world.set_motors(kuka, range(7), "position", targets, forces=300)
    assert [m.position for m in motors] == targets and all(m.force == 300 for m in motors)
    assert [world.motors.get(kuka, j) for j in range(7)] == motors
    with pytest.raises(sb.InvalidInputError, match=r"joints \[7\] of body"):
        world.set_motors(kuka, [0, 7], "position", [1.0, 1.0])
    assert world.motors.get(kuka, 0).position == 0.0  # untouched


def test_a_finger_whose_rim_lies_on_the_pads_node_lines_does_not_cut_in(tmp_path):
    """A 2 cm finger on the 1 cm grid of the pad: its face's rim lies exactly on lines of the pad's nodes, which its
    side faces then hold sideways. The pad's faces from those nodes inward used to slide into the finger (1.4 mm deep);
    the rows at the face's rims hold them: pressing with its 20 N limit, nothing is inside the finger by 0.1 mm
    (measured apart from the contact search: triangle samples against the box, its edge points inside the pad)."""
    import geometry as geo

    world = World(dt=0.01)
    finger = _finger(world.client, tmp_path, size=0.02)
    pad = _pad(world, size=0.02)
    world.set_motor(finger, 0, "position", target_position=0.05, force=20.0)
    world.run(0.4)
    assert world.contact_force(finger, 0)[0] == pytest.approx(-20.0, rel=0.01)
    depth = geo.rigid_penetration(world.client, finger, pad.positions, pad.mesh.surface_triangles(), link=0)
    assert depth < 1e-4
