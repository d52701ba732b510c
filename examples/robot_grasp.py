"""A Franka Panda (pybullet_data) picks a soft tet10 cube off a table, lifts it 0.2 m, holds it, sets it down.

    python examples/robot_grasp.py [--record [PATH]] [--hold S] [--E PA] [--dt S]

The scene is the user's own pybullet client (table and robot loaded from pybullet_data, position motors,
inverse kinematics); softbody joins it with ``World(client=cid)`` and is stepped inside the user's control
loop. The motors are set through ``World.set_motor`` (pybullet's setJointMotorControl2 arguments): while the hand
holds the cube they act inside the coupled step with their force limits (FINGER_FORCE per finger, whatever the step). Printed per phase: the grip force of each finger [N] (the force the cube exerts on it), the slip of the
cube in the fingers [mm] since the grasp closed, the deepest penetration of a soft node into any rigid link
[mm] (pybullet's own closest-point query), and at the end the cost per step and the real-time factor.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import pybullet as p
import pybullet_data

import softbody as sb
from integration import World

ARM, FINGERS, HAND = list(range(7)), [9, 10], 11  # panda.urdf: arm joints, finger joints, grasp target link
FINGER_FORCE = 5.0  # [N] the finger motors' force limit: the grip on the cube (E = 1e5 Pa, 62 g) once closed
HOME = [0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.785]


def build(E: float = 1e5, dt: float = 0.005, size: float = 0.05, scheme: str = "warped") -> tuple[int, int, World, sb.FemBody]:
    """The user's scene: a table, a Panda on a fixed base, a soft cube on the table; the World joined to it."""
    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(dt, physicsClientId=cid)
    p.loadURDF("table/table.urdf", [0.5, 0, -0.625], physicsClientId=cid)  # top face at z = 0
    panda = p.loadURDF("franka_panda/panda.urdf", [0, 0, 0], useFixedBase=True, physicsClientId=cid)
    for j, q in zip(ARM, HOME):
        p.resetJointState(panda, j, q, physicsClientId=cid)
    for j in FINGERS:
        p.resetJointState(panda, j, 0.04, physicsClientId=cid)
    mesh = sb.box_mesh((size, size, size), (2, 2, 2), "tet10", center=(0.5, 0.0, size / 2 + 0.0015))
    cube = sb.FemBody(mesh, sb.LinearElastic(E, 0.3, 500.0), damping=(1.0, 0.002))
    world = World(client=cid, scheme=scheme)  # time step and gravity from the client
    world.add_soft(cube, friction=1.0)
    return cid, panda, world, cube


class Grasp:
    """The user's control loop: inverse kinematics for the hand, position motors for arm and fingers."""

    def __init__(self, cid: int, panda: int, world: World, cube: sb.FemBody, recorder=None):
        self.cid, self.panda, self.world, self.cube, self.recorder = cid, panda, world, cube, recorder
        self.down = p.getQuaternionFromEuler([np.pi, 0, 0])
        self.grip_ref = None  # the cube's centre in the hand's frame when the grasp closed
        self.slip = 0.0
        self.penetration = 0.0
        self.steps = 0
        self.seconds = 0.0

    def hand(self) -> tuple[np.ndarray, np.ndarray]:
        s = p.getLinkState(self.panda, HAND, computeForwardKinematics=1, physicsClientId=self.cid)
        return np.array(s[4]), np.array(p.getMatrixFromQuaternion(s[5])).reshape(3, 3)

    def cube_in_hand(self) -> np.ndarray:
        pos, R = self.hand()
        return (self.cube.positions.mean(axis=0) - pos) @ R

    def go(self, target, opening: float, seconds: float) -> None:
        """Move the hand to ``target`` (3,) [m] along a smooth (cosine) path over ``seconds``, the fingers
        driven to ``opening`` [m] each."""
        start, target = self.hand()[0], np.asarray(target, float)
        steps = int(round(seconds / self.world.dt))
        for k in range(steps):
            s = 0.5 - 0.5 * np.cos(np.pi * min(1.0, (k + 1) / (0.8 * steps)))  # arrive at 80% of the phase
            q = p.calculateInverseKinematics(self.panda, HAND, (start + s * (target - start)).tolist(), self.down,
                                             maxNumIterations=50, physicsClientId=self.cid)
            # the World's motors, as pybullet's setJointMotorControl2: while the hand holds the cube they are rows of
            # the coupled problem, so that a finger presses with its force limit whatever the step
            self.world.set_motors(self.panda, ARM, "position", [q[j] for j in ARM], forces=200)
            self.world.set_motors(self.panda, FINGERS, "position", [opening] * len(FINGERS), forces=FINGER_FORCE)
            tic = time.perf_counter()
            self.world.step()
            self.seconds += time.perf_counter() - tic
            self.steps += 1
            if self.recorder is not None:
                self.recorder(self.world)
            self.penetration = max(self.penetration, self.world.max_penetration())
            if self.grip_ref is not None:
                self.slip = max(self.slip, float(np.linalg.norm(self.cube_in_hand() - self.grip_ref)))

    def grip(self) -> tuple[float, float]:
        """The force [N] the cube exerts on each finger over the last step."""
        return tuple(float(np.linalg.norm(self.world.contact_force(self.panda, j))) for j in FINGERS)

    def report(self, phase: str) -> dict:
        left, right = self.grip()
        row = {"phase": phase, "t": self.world.t, "cube_z": float(self.cube.positions[:, 2].mean()),
               "grip_left": left, "grip_right": right, "slip_mm": 1e3 * self.slip,
               "penetration_mm": 1e3 * self.penetration}
        print(f"{phase:>9}: t {row['t']:5.2f} s  cube centre z {row['cube_z']:.4f} m  grip {left:5.2f} / {right:5.2f} N"
              f"  slip {row['slip_mm']:5.2f} mm  penetration {row['penetration_mm']:.3f} mm", flush=True)
        return row


def run(hold: float = 2.0, E: float = 1e5, dt: float = 0.005, record: str | None = None,
        overwrite: bool = False, scheme: str = "warped") -> list[dict]:
    """The whole pick-and-place; returns the report rows of its phases. record: a recording's file or
    directory ("" for logs/); overwrite: replace an existing file; scheme: the soft step ("warped" or "newton")."""
    if record is not None:
        from integration.recording import record_target

        record_target(record, overwrite)  # before the scene is built
    cid, panda, world, cube = build(E, dt, scheme=scheme)
    recorder = None
    if record is not None:
        from integration import Recorder

        recorder = Recorder(world, path=record, overwrite=overwrite, frame="soft",  # the cube and the fingers
                            monitor=[(0, int(np.argmax(cube.positions[:, 2])))])
    size = np.ptp(cube.positions[:, 2])
    ctrl = Grasp(cid, panda, world, cube, recorder)
    rows = []
    try:
        ctrl.go([0.5, 0, 0.2], 0.04, 1.0)
        rows.append(ctrl.report("approach"))
        ctrl.go([0.5, 0, size / 2], 0.04, 1.0)
        rows.append(ctrl.report("descend"))
        ctrl.go([0.5, 0, size / 2], 0.015, 0.5)
        ctrl.grip_ref = ctrl.cube_in_hand()
        rows.append(ctrl.report("close"))
        ctrl.go([0.5, 0, size / 2 + 0.2], 0.015, 1.0)
        rows.append(ctrl.report("lift"))
        ctrl.go([0.5, 0, size / 2 + 0.2], 0.015, hold)
        rows.append(ctrl.report("hold"))
        ctrl.go([0.5, 0, size / 2 + 0.003], 0.015, 1.0)
        rows.append(ctrl.report("set down"))
        ctrl.grip_ref = None
        ctrl.go([0.5, 0, size / 2 + 0.003], 0.04, 0.5)
        rows.append(ctrl.report("release"))
    finally:
        if recorder is not None:
            recorder.close()
            print(f"recording: {recorder.path}")
        world.close()
        p.disconnect(cid)
    ms = 1e3 * ctrl.seconds / ctrl.steps
    print(f"{ctrl.steps} steps of {dt} s: {ms:.1f} ms per step, real-time factor {dt / (ms / 1e3):.2f}")
    rows.append({"phase": "cost", "ms_per_step": ms, "realtime": dt / (ms / 1e3)})
    return rows


if __name__ == "__main__":
    from experiments.cli import plain_text

    ap = argparse.ArgumentParser(description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hold", type=float, default=2.0, help="seconds to hold the cube up (default 2)")
    ap.add_argument("--E", type=float, default=1e5, help="the cube's Young's modulus [Pa] (default 1e5)")
    ap.add_argument("--dt", type=float, default=0.005, help="time step [s] (default 0.005)")
    ap.add_argument("--record", nargs="?", const="", default=None, metavar="PATH",
                    help="write a rerun recording to PATH or into the directory PATH (default: into logs/)")
    ap.add_argument("--force", action="store_true", help="overwrite an existing --record file")
    ap.add_argument("--scheme", choices=("warped", "newton"), default="warped", help="the soft body's step (default warped)")
    args = ap.parse_args()
    try:
        run(args.hold, args.E, args.dt, args.record, args.force, args.scheme)
    except sb.InvalidInputError as exc:
        ap.exit(2, f"{ap.prog}: error: {exc}\n")
