"""When the warped step's linearisation is poor: how far its elements rotate within one step.

The warped step (docs/method.md section 4) takes each element's rotation at the start of the step and moves the nodes
along straight lines x + h v. An element that turns by theta within the step is stretched by its own rotation, about
theta^2 / 2, before the next step's rotation sees it: a cube spinning at 10 rev/s with dt = 0.01 s (0.63 rad per step)
stays 12-16% out of shape (benchmarks/stability_sweep.py's ``spin``, measured for tet4, tet10 and hex8 alike: the
rigid residual, relative to the body's size, is 0.4% at 0.063 rad per step, 1.3% at 0.157, 4.2% at 0.314, 16% at
0.63 and 52% at 1.26; about 0.42 theta^2 from 0.15 to 0.7 rad, the range the warning speaks of).

:class:`RotationWatch` measures theta after every warped step from the new velocities: per element the spin of the
velocity gradient of its characteristic tetrahedron, omega = axial(skew(dF/dt R^T)) (R the rotation the step used),
theta = |omega| h. Beyond ``limit`` (ROTATION_LIMIT, 0.2 rad: about 1.7% out of shape) it warns once per body with the
distortion to expect and what to change (a step of at most h limit / theta, or ``scheme="newton"``, whose rotations
follow the iterate and which keeps the spinning cube's shape to 0.02%).

A small theta can still matter: the stretch, about 0.42 theta^2 of the body's size, stores up to E V (0.42 theta^2)^2
/ 2 of elastic energy, which grows as E and falls as h^4. Where that is more than LAG_ENERGY (5%) of the body's kinetic
energy, the watch warns as well: a stiff bar (E = 1e9 Pa) swinging from a hinge at up to 5 rad/s turns only 0.05 rad a
step of 0.01 s, yet the warped step gathers several times its swing's energy in its vibration within a second (8.8 times
its m g d in 1.5 s; 0.66 times at dt 0.005 s; tests/test_linearisation.py); the stress it shows is then the step's.
"""
from __future__ import annotations

import math
import warnings
import weakref

import numpy as np

from . import kernels
from .body import FemBody

#: rotation per step [rad] beyond which the warped step warns (its shape error is about SHAPE_PER_RAD2 theta^2: 1.7%)
ROTATION_LIMIT = 0.2
#: the warped step's rigid residual per unit size and per rad^2 of rotation per step (spin at 10 rev/s, measured from
#: 0.15 to 0.7 rad per step; it overstates beyond: 52%, not 67%, at 1.26 rad)
SHAPE_PER_RAD2 = 0.42
#: the stretch energy a step's rotation lag can hold, E V (SHAPE_PER_RAD2 theta^2)^2 / 2, beyond which fraction of the
#: body's kinetic energy the warped step warns though theta is small: a stiff body (a steel-like bar swinging at
#: 5 rad/s, dt 0.01 s: 0.05 rad a step) gathers that energy as vibration, several times its swing's (docs/stability.md)
LAG_ENERGY = 0.05


class LinearisationWarning(UserWarning):
    """The warped step's rotations lag the motion by more than ROTATION_LIMIT per step (see softbody.linearisation)."""


def rotation_per_step(body: FemBody, v: np.ndarray, h: float, R: np.ndarray | None = None) -> tuple[float, int]:
    """(theta [rad], element): the largest angle any element turns through in a step of h [s] at velocities v (N, 3),
    and where (omega = axial(skew(dF/dt R^T)) of its characteristic tetrahedron, R (E, 3, 3) its rotation: the step's
    own if given, else at the body's current positions)."""
    R = body.rotations(body.positions) if R is None else R
    Fdot = body.characteristic_gradient(v)  # (9, E), row 3 i + j: dF_ij / dt
    if kernels.ENABLED:  # the same arithmetic element by element (softbody.kernels)
        speed2, e = kernels.max_spin(Fdot, R)
        return math.sqrt(max(speed2, 0.0)) * h, int(e)
    # L = dF/dt R^T; its skew part's axial vector: (L_21 - L_12, L_02 - L_20, L_10 - L_01) / 2
    L = np.einsum("ije,ekj->eik", Fdot.reshape(3, 3, -1), R)
    w = 0.5 * np.stack([L[:, 2, 1] - L[:, 1, 2], L[:, 0, 2] - L[:, 2, 0], L[:, 1, 0] - L[:, 0, 1]], axis=1)
    speed = np.einsum("ij,ij->i", w, w)
    e = int(speed.argmax())
    return float(np.sqrt(speed[e])) * h, e


class RotationWatch:
    """After each warped step, whether a body's elements turned too far to trust the linearisation; a warning once per
    body (kept here, by the body itself: the stepper owns this object)."""

    def __init__(self, limit: float = ROTATION_LIMIT):
        self.limit = float(limit)
        self.warned: weakref.WeakSet[FemBody] = weakref.WeakSet()  # a body (or stack) let go of is forgotten
        # per body sum_e E_e V_e [J] (Young's modulus times volume), made at its first check: it does not change
        self._stiffness: weakref.WeakKeyDictionary[FemBody, float] = weakref.WeakKeyDictionary()

    def check(self, index: int, body: FemBody, v: np.ndarray, h: float, R: np.ndarray | None = None) -> None:
        """Warn (LinearisationWarning) if ``body`` (the ``index``-th stepped) turns by more than the limit in this step
        of h [s] to velocities v (N, 3), R (E, 3, 3) the step's rotations (None: at its positions); at most once per
        body."""
        if not body.warping or body in self.warned:
            return
        theta, e = rotation_per_step(body, v, h, R)
        shape = SHAPE_PER_RAD2 * theta * theta
        if theta <= self.limit:
            self._check_stiff(index, body, v, h, theta, e, shape)
            return
        self.warned.add(body)
        warnings.warn(
            f"body {index} ({_where(body, e)}) turns {theta:.2f} rad in one step of {h:g} s ({theta / h:.1f} rad/s): the warped "
            f"step's rotations lag it and leave it about {100 * shape:.0f}% out of shape (softbody.linearisation). "
            f"Take dt <= {h * self.limit / theta:.2g} s (about {100 * SHAPE_PER_RAD2 * self.limit ** 2:.1f}%), or "
            f"scheme='newton' (or 'bdf2' without contact). Said once per body.", LinearisationWarning, stacklevel=4)

    def _check_stiff(self, index: int, body: FemBody, v: np.ndarray, h: float, theta: float, e: int,
                     shape: float) -> None:
        """Warn where theta is small but the body so stiff that the stretch it leaves, E V shape^2 / 2 at most, holds
        more than LAG_ENERGY of the body's kinetic energy (it returns as vibration and as stress of the step's own)."""
        EV = self._stiffness.get(body)
        if EV is None:
            EV = self._stiffness[body] = float(np.sum(np.asarray(body.material.E, float) * body.volumes))
        lag = 0.5 * EV * shape * shape
        if lag == 0.0:
            return
        kinetic = body.kinetic_energy(v)  # 1/2 v^T M v (the consistent mass's row sums, a tet10's, can be negative)
        if lag <= LAG_ENERGY * kinetic:
            return
        self.warned.add(body)
        dt = h * (LAG_ENERGY * kinetic / lag) ** 0.25  # the lag energy falls as theta^4, h^4 at a given motion
        warnings.warn(
            f"body {index} ({_where(body, e)}) turns {theta:.3f} rad in one step of {h:g} s: little, but the body is "
            f"stiff (E up to {float(np.max(body.material.E)):.3g} Pa): the stretch the warped step's straight moves "
            f"leave, about {100 * shape:.2g}% of its size, holds up to {lag:.3g} J a step, {lag / kinetic:.0%} of its "
            f"kinetic energy; it comes back as vibration and as stress that belongs to the step, not to the body "
            f"(softbody.linearisation). Take dt <= {dt:.2g} s, or scheme='newton' (or 'bdf2' without contact). Said "
            "once per body.", LinearisationWarning, stacklevel=5)


def _where(body: FemBody, e: int) -> str:
    """Element e of ``body`` as a user knows it: in a BodyStack, its member and its element there."""
    offsets = getattr(body, "element_offsets", None)
    if offsets is None:
        return f"element {e}"
    k = int(np.searchsorted(offsets, e, side="right") - 1)
    return f"member {k}, element {e - int(offsets[k])}"
