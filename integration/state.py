"""A World's saved state: the soft side (softbody.state.SimulationState), pybullet's world, and what the coupling
carries from one step to the next (contact warm starts and friction states, the stacking of the soft bodies, the
reactions lagged to the next step, the last step's results), keyed by stable handles (a soft body by its index in
``World.bodies``, a stepped body by the indices of its members, an attachment by its index), so that a state
written to disk restores into the same scene built again in another process.

pybullet's part is the bytes of its ``saveBullet`` (BulletAdapter.save_world; restored with ``restoreState`` by
BulletAdapter.restore_world, in this process or another). What pybullet does not save stays as it is: motor targets and gains set with
``setJointMotorControl2``, user constraints and changed dynamics (the scene, not its state).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from softbody.state import FORMAT, SimulationState, write_state

from .step import StepReport


@dataclass
class WorldState:
    """What :meth:`integration.World.save_state` saved after the World's step ``sim.steps`` (time ``sim.t``).

    sim: the soft bodies' state; scene: what the World must find again to restore it (the soft bodies' node counts,
    dt, gravity, pybullet's bodies); layout: the stepped bodies as tuples of member indices; bullet: pybullet's
    saveBullet bytes; the other fields: the coupling's state (see World.save_state).
    """

    sim: SimulationState
    scene: dict
    attachments: int
    layout: list[tuple[int, ...]]
    dense_group: dict[int, int]
    restack_due: bool
    started: list[int]
    previous: dict[tuple, Any]
    lagged: list
    results: StepReport  # the last step's (integration.step)
    bullet: bytes
    format: int = FORMAT
    patterns: dict[tuple, Any] = field(default_factory=dict)  # the coupled problem's sparse patterns (their extra blocks)
    rigid_warm: dict[int, Any] = field(default_factory=dict)  # the coupled solve's last du per rigid body (its id)

    def write(self, path: str | Path) -> Path:
        """Write this state to ``path`` (pickle); ``World.restore_state(path)`` reads it back, also in a new process
        with the same scene built."""
        return write_state(self, path)
