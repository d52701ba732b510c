"""What acts on a robot's joints inside the coupled step: joint motors with their force limits, and joint limits, as
scalar rows of the convex problem (convex.JointRows) on the movable bodies' generalized velocities (pybullet's user
constraints between bodies: constraints.py).

pybullet runs a motor (``setJointMotorControl2``, POSITION_CONTROL or VELOCITY_CONTROL) as a velocity constraint of
its own step (btMultiBodyJointMotor): it drives the joint's velocity to

    v* = kp (q* - q) / h + qd + kd (qd* - qd)       (VELOCITY_CONTROL: kp = 0; by default kd = 1: v* = qd*)

(q, qd the joint's position and velocity at the start of the step, kp and kd pybullet's positionGain and velocityGain,
|v*| at most maxVelocity, q* within the joint's limits) with an impulse of at most F h (F its force limit). (pybullet
takes qd after the step's external forces, before its constraints: with kd other than 1 and a force along the joint,
its target differs from this one by (1 - kd) h qdd.) Run there alone, before the soft
bodies' reactions are known, a motor pressing through a soft body reaches its target velocity within its limit, and
the coupled solve, which sees the joints free, then takes that velocity away: the grip settles at m kp (q - q*) /
h^2, not at F. A motor registered with the World (``World.set_motor``) is also a row of the coupled problem whenever
its body is in it: the same target v*, and the rest of its force limit, -F h - g_pb <= gamma <= F h - g_pb, beyond the
impulse g_pb pybullet's step applied (its reported motor torque times h), so that the motor's whole impulse stays
within its limit, and a motor pressing through a soft body exerts its limit at any step. pybullet keeps running the
motor in its own step: its free motion starts the solve near its answer, and the motor acts on pybullet's own
contacts (a rigid table) as before.

A joint limit (the URDF's lower < upper) is a one-sided row: q + h u stays within [lower, upper] at the end of the
step (pybullet enforces it within its own step, before the coupled correction, which could otherwise carry the joint
beyond it).

Motors are keyed by (pybullet body id, joint index): stable handles, as pybullet's own.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from softbody.errors import InvalidInputError

from .convex import JointRows
from .coupling import RigidCoupling

#: pybullet's own defaults (pybullet.setJointMotorControl2)
DEFAULT_FORCE = 100000.0
DEFAULT_POSITION_GAIN = 0.1
DEFAULT_VELOCITY_GAIN = 1.0

MODES = ("position", "velocity")


@dataclass(frozen=True)
class Motor:
    """A joint motor as pybullet runs it: ``mode`` "position" (drives the joint to ``position`` [m or rad] with
    ``position_gain`` kp and ``velocity_gain`` kd towards ``velocity``) or "velocity" (drives it to ``velocity`` [m/s
    or rad/s]); ``force`` [N or N m] its limit; ``max_velocity``: the largest |v*| (inf: none)."""

    body: int
    joint: int
    mode: str
    position: float = 0.0
    velocity: float = 0.0
    force: float = DEFAULT_FORCE
    position_gain: float = DEFAULT_POSITION_GAIN
    velocity_gain: float = DEFAULT_VELOCITY_GAIN
    max_velocity: float = math.inf

    def __post_init__(self):
        if self.mode not in MODES:
            raise InvalidInputError(f"motor mode must be one of {MODES}, got {self.mode!r}")
        for name in ("position", "velocity", "force", "position_gain", "velocity_gain"):
            if not math.isfinite(getattr(self, name)):
                raise InvalidInputError(f"motor {name} must be finite, got {getattr(self, name)}")
        for name in ("force", "position_gain", "velocity_gain", "max_velocity"):
            if getattr(self, name) < 0:
                raise InvalidInputError(f"motor {name} must be >= 0, got {getattr(self, name)}")

    def target(self, q: float, qd: float, h: float, limits: tuple[float, float] | None = None) -> float:
        """The velocity v* the motor drives the joint to over a step h [s] from position q and velocity qd
        (btMultiBodyJointMotor's right-hand side); ``limits`` (lower, upper): the joint's, which pybullet clamps a
        position target to."""
        v = qd + self.velocity_gain * (self.velocity - qd)
        if self.mode == "position":
            goal = self.position if limits is None else min(max(self.position, limits[0]), limits[1])
            v += self.position_gain * (goal - q) / h
        return float(np.clip(v, -self.max_velocity, self.max_velocity))

    def pybullet_args(self, p) -> tuple[int, dict]:
        """(controlMode, keyword arguments) of pybullet.setJointMotorControl2 for this motor."""
        kw = {"targetVelocity": self.velocity, "force": self.force}
        if self.mode == "position":
            kw.update(targetPosition=self.position, positionGain=self.position_gain, velocityGain=self.velocity_gain)
            if math.isfinite(self.max_velocity):
                kw["maxVelocity"] = self.max_velocity
            return p.POSITION_CONTROL, kw
        kw["velocityGain"] = self.velocity_gain
        return p.VELOCITY_CONTROL, kw


class Motors:
    """The motors registered with a World, keyed by (body, joint)."""

    def __init__(self):
        self._held: dict[tuple[int, int], Motor] = {}

    def __len__(self) -> int:
        return len(self._held)

    def set(self, motor: Motor) -> None:
        self._held[(motor.body, motor.joint)] = motor

    def get(self, body: int, joint: int) -> Motor | None:
        return self._held.get((body, joint))

    def forget(self, body: int) -> None:
        """Drop the motors of a removed body."""
        self._held = {k: m for k, m in self._held.items() if k[0] != body}

    def of(self, bodies) -> list[Motor]:
        """The motors of ``bodies`` (ids), in (body, joint) order."""
        bodies = set(bodies)
        return [m for k, m in sorted(self._held.items()) if k[0] in bodies]


def joint_rows(coupling: RigidCoupling, motors: list[Motor], limits: dict[int, tuple[np.ndarray, np.ndarray]],
               h: float) -> JointRows:
    """The rows of ``motors`` and of the joint ``limits`` (body -> (lower (j,), upper (j,)) per movable joint, lower >=
    upper: none) of the bodies in ``coupling`` over a step h [s], at their start configuration (their values under
    the free motion not yet known: :func:`at_free_motion`); labels ("motor", body, joint) or ("lower" / "upper",
    body, joint)."""
    C, target, lo, hi, labels = [], [], [], [], []
    n = coupling.n
    for m in motors:
        dyn = coupling.dynamics.get(m.body)
        if dyn is None or m.joint not in dyn.joints:
            continue
        j = dyn.joints.index(m.joint)
        col = coupling.offset[m.body] + (6 if dyn.free_base else 0) + j
        row = np.zeros(n)
        row[col] = 1.0
        C.append(row)
        lower, upper = limits.get(m.body, (np.zeros(0), np.zeros(0)))
        bounds = (float(lower[j]), float(upper[j])) if len(lower) and lower[j] < upper[j] else None
        target.append(m.target(float(dyn.q[j]), float(dyn.u[col - coupling.offset[m.body]]), h, bounds))
        lo.append(-m.force * h)
        hi.append(m.force * h)
        labels.append(("motor", m.body, m.joint))
    for b, (lower, upper) in limits.items():
        dyn = coupling.dynamics.get(b)
        if dyn is None:
            continue
        base = coupling.offset[b] + (6 if dyn.free_base else 0)
        for j in np.flatnonzero(lower < upper).tolist():
            q = float(dyn.q[j])
            for side, sign, bound in (("lower", 1.0, lower[j]), ("upper", -1.0, upper[j])):
                row = np.zeros(n)
                row[base + j] = sign  # lower: u >= (lower - q) / h; upper: -u >= (q - upper) / h
                C.append(row)
                target.append(sign * (bound - q) / h)
                lo.append(0.0)
                hi.append(math.inf)
                labels.append((side, b, dyn.joints[j]))
    if not C:
        return JointRows.concat([], n)
    return JointRows(np.array(C), np.zeros(len(C)), np.array(target), np.array(lo), np.array(hi), labels)


def at_free_motion(rows: JointRows, u_free: np.ndarray, applied: np.ndarray) -> JointRows | None:
    """``rows`` once pybullet has stepped: their values C u_free under the free motion u_free (n,), the impulses
    ``applied`` (k,) [N s or N m s] pybullet's step gave them (its motors', its constraints'). None: no rows."""
    if not len(rows):
        return None
    return replace(rows, free=rows.coefficients @ u_free, applied=np.asarray(applied, float))


def applied_impulses(rows: JointRows, torques, h: float) -> np.ndarray:
    """The impulses (k,) [N s or N m s] pybullet's last step of h [s] gave the motor rows of ``rows`` (joint_rows),
    from ``torques(body, joints)``: each joint's reported motor force or torque [N or N m]; zero for the others."""
    labels = rows.labels
    out = np.zeros(len(labels))
    by_body: dict[int, list[int]] = {}
    for r, (kind, body, _) in enumerate(labels):
        if kind == "motor":
            by_body.setdefault(body, []).append(r)
    for body, rs in by_body.items():
        out[rs] = torques(body, [labels[r][2] for r in rs])
    return out * h
