"""Figures for the contact kinds (docs/contact.md): per scene the deepest penetration, the energy drift, the
time per step and the share of it spent in collision detection.

    python benchmarks/contact_kinds_report.py

The scenes are those of tests/test_contact_kinds.py (imported from there); penetrations are measured as the
tests do, independently of the library (pybullet's closest-point query against rigid bodies, trimesh's
signed distance between soft surfaces).
"""
import math
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT)]

from test_contact_kinds import (dropped_blocks_scene, fast_sphere_scene, pybullet_penetration,  # noqa: E402
                                soft_incline_scene, soft_overlap, squeezed_tube, stack_scene)


class Meter:
    """Per step: the scene's total energy, the step's wall time and its collision phase, and a penetration."""

    def __init__(self, world, penetration):
        self.world, self.penetration = world, penetration
        self.energy = [world.energy()["total"]]
        self.ms, self.collision, self.worst = [], [], 0.0

    def step(self, world=None):
        w = self.world
        if world is None:
            tic = time.perf_counter()
            w.step()
            self.ms.append(1e3 * (time.perf_counter() - tic))
        else:  # stepped by someone else: the World's own timing
            self.ms.append(1e3 * w.timings["total"])
        self.collision.append(1e3 * w.timings.get("collision", 0.0))
        self.energy.append(w.energy()["total"])
        self.worst = max(self.worst, self.penetration())

    def row(self, name: str) -> str:
        e = np.array(self.energy)
        rise = float(np.diff(e).max())
        return (f"| {name} | {1e3 * self.worst:.3f} | {rise:+.1e} | {e[-1] - e[0]:+.3g} of {abs(e[0]):.3g} | "
                f"{np.median(self.ms):.1f} | {100 * np.sum(self.collision) / np.sum(self.ms):.0f}% |")


class Follow:
    """A callback that meters a World stepped by someone else, from its first step on."""

    meter: Meter | None = None

    def __call__(self, world) -> None:
        if self.meter is None:
            self.meter = Meter(world, lambda: 0.0)
        self.meter.step(world)


def main() -> None:
    print("| scene | deepest penetration [mm] | largest energy rise in a step [J] | energy change [J] | ms/step "
          "(median) | collision share |")
    print("|---|---:|---:|---:|---:|---:|")
    for mass in (0.5, 4.0):
        for dt in (0.01, 0.001):
            world, slab, ball = fast_sphere_scene(mass, dt)
            m = Meter(world, lambda: pybullet_penetration(world, slab, ball))
            for _ in range(int(round(0.1 / dt))):
                m.step()
            print(m.row(f"30 m/s sphere {mass} kg into a tet10 slab, dt {dt} s"), flush=True)
    for kind in ("tet4", "hex8", "tet10"):
        world, low, high = dropped_blocks_scene(kind)
        m = Meter(world, lambda: max(soft_overlap(high, low), soft_overlap(low, high)))
        for _ in range(100):
            m.step()
        print(m.row(f"{kind} block dropped on a {kind} block"), flush=True)
    world, blocks = stack_scene()
    m = Meter(world, lambda: max(soft_overlap(a, b) for a in blocks for b in blocks if a is not b))
    for _ in range(150):
        m.step()
    print(m.row("stack of three tet10 blocks"), flush=True)
    for mu in (0.5, 0.1):
        world, block, downhill = soft_incline_scene(mu)
        incline = world.bodies[0]
        m = Meter(world, lambda: max(soft_overlap(block, incline), soft_overlap(incline, block)))
        xs = []
        for _ in range(80):
            m.step()
            xs.append(block.positions.mean(axis=0) @ downhill)
        t = world.dt * np.arange(1, len(xs) + 1)
        accel = 2 * np.polyfit(t[30:], xs[30:], 2)[0]
        expected = max(9.81 * (math.sin(math.radians(20)) - mu * math.cos(math.radians(20))), 0.0)
        print(m.row(f"block on a soft incline, mu {mu}: acceleration {accel:.3f} m/s^2 (Coulomb {expected:.3f})"),
              flush=True)
    for self_contact in (True, False):
        follow = Follow()
        worst = squeezed_tube(self_contact, callback=follow)
        follow.meter.worst = worst
        print(follow.meter.row(f"tube squeezed flat, self-contact {'on' if self_contact else 'off'} (penetration: "
                               "of its own inner surface, from the first step on)"), flush=True)


if __name__ == "__main__":
    main()
