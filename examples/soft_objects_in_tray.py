"""Many small soft objects in a user's pybullet scene: soft cubes dropped into pybullet_data's tray.

    python examples/soft_objects_in_tray.py [--count 20] [--duration 1.5] [--no-stack] [--record]

The scene is the user's own client (a plane and ``tray/traybox.urdf`` from pybullet_data), joined by a World.
``count`` soft tet10 cubes of 4 cm (117 nodes each) fall from a 4 x 4 grid of layers above the tray (20: sixteen
land on its floor, four on top of them). They share material and friction, so the World steps them as one block-diagonal system
(softbody.BodyStack); ``--no-stack`` steps each alone, for the comparison. Prints the cost per step, the
force the cubes put on the tray against their weight, and their deepest penetration of the tray.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def build(count: int, stack: bool):
    import pybullet as p
    import pybullet_data

    import softbody as sb
    from integration import World

    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(0.01, physicsClientId=cid)
    p.loadURDF("plane.urdf", physicsClientId=cid)
    tray = p.loadURDF("tray/traybox.urdf", [0, 0, 0], useFixedBase=True, physicsClientId=cid)
    world = World(client=cid, stack=stack)
    side = int(np.ceil(np.sqrt(count)))
    cubes = []
    for k in range(count):
        i, j, level = k % side, (k // side) % side, k // (side * side)
        centre = (0.07 * (i - (side - 1) / 2), 0.07 * (j - (side - 1) / 2), 0.08 + 0.06 * level)
        mesh = sb.box_mesh((0.04, 0.04, 0.04), (2, 2, 2), "tet10", center=centre)
        cubes.append(world.add_soft(sb.FemBody(mesh, sb.LinearElastic(2e5, 0.3, 600), damping=(0.5, 0.002)),
                                    friction=0.5))
    return p, cid, world, tray, cubes


def main(argv=None) -> int:
    from experiments.cli import plain_text

    parser = argparse.ArgumentParser(description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=20, help="soft cubes (default 20)")
    parser.add_argument("--duration", type=float, default=1.5, help="simulated time [s]")
    parser.add_argument("--no-stack", action="store_true", help="step every cube alone (World(stack=False))")
    parser.add_argument("--record", action="store_true", help="write a rerun recording into logs/")
    args = parser.parse_args(argv)
    if args.count < 1:
        parser.error(f"--count must be at least 1, got {args.count}")
    p, cid, world, tray, cubes = build(args.count, not args.no_stack)
    recorder = None
    if args.record:
        from integration import Recorder

        recorder = Recorder.attach(world)
    weight = sum(c.total_mass for c in cubes) * 9.81
    ms = []

    def callback(w) -> None:
        ms.append(1e3 * w.timings["total"])
        if recorder is not None:
            recorder(w)

    tic = time.perf_counter()
    world.run(args.duration, callback, progress=True)
    wall = time.perf_counter() - tic
    force = -world.contact_force(tray)[2]
    stepped = len(world.sim.bodies)
    print(f"# {args.count} soft cubes ({sum(c.n_nodes for c in cubes)} nodes) stepped as {stepped} bod"
          f"{'y' if stepped == 1 else 'ies'}: {np.median(ms):.1f} ms per step (median), {wall:.1f} s for "
          f"{args.duration} s")
    print(f"# force on the tray {force:.3f} N against their weight {weight:.3f} N; deepest penetration "
          f"{1e3 * world.max_penetration():.3f} mm; lowest node {1e3 * min(c.positions[:, 2].min() for c in cubes):.1f} mm")
    if recorder is not None:
        recorder.close()
        print(recorder.path)
    world.close()
    p.disconnect(cid)
    return 0


if __name__ == "__main__":
    sys.exit(main())
