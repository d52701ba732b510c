"""What a pile costs: soft cubes stacked against the same cubes apart, and a pile settling in a tray.

    python benchmarks/piles.py [--steps 60] [--settle 40] [--tray 30] [--tray-steps 150] [--no-tray]

Single thread (OMP/MKL/OPENBLAS_NUM_THREADS=1), in one process, medians over the timed steps:

- **stacked / apart**: twelve tet10 cubes (4 cm, 2x2x2 cells, E = 2e5, 600 kg/m^3, friction 0.5) stacked 2x2x3 on a
  plane (1 mm apart), and the same twelve standing apart on it. After ``--settle`` steps into contact, the next
  ``--steps`` are timed, the two scenes in alternating blocks of 10 steps (a change of the machine's speed hits
  both alike); printed: ms per step of each, their ratio, the soft contacts (node-face and edge-edge) of the stack.
- **tray**: ``--tray`` such cubes dropped as a pile (layers of 3x3, 5 cm apart, from 8 cm up) into pybullet_data's
  tray in the user's own client; ms per step (median and worst over ``--tray-steps`` steps), and at the end the
  deepest interpenetration of any two cubes (intersection.py's segment-against-triangle depth, apart from the
  contact search).

The figures to read against: a pile's step should cost about what its contacts do, linearly (twelve stacked at
most 3x twelve apart; thirty in the tray under 50 ms per step).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("SOFTBODY_COMPILE", "now")

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SIZE = 0.04  # [m]: the cubes' edge


def cube(world, centre) -> object:
    import softbody as sb

    mesh = sb.box_mesh((SIZE,) * 3, (2, 2, 2), "tet10", center=centre)
    return world.add_soft(sb.FemBody(mesh, sb.LinearElastic(2e5, 0.3, 600.0), damping=(0.5, 0.002)), friction=0.5)


def twelve(stacked: bool):
    """(world, cubes): twelve cubes stacked 2x2x3 or standing apart (0.1 m) on a plane."""
    from integration import World

    world = World(dt=0.01)
    world.add_plane()
    cubes = []
    for k in range(12):
        i, j, level = k % 2, (k // 2) % 2, k // 4
        if stacked:
            centre = ((i - 0.5) * (SIZE + 0.001), (j - 0.5) * (SIZE + 0.001), SIZE / 2 + 0.0005 + level * (SIZE + 0.001))
        else:
            centre = ((k % 4) * 0.1, (k // 4) * 0.1, SIZE / 2 + 0.0005)
        cubes.append(cube(world, centre))
    return world, cubes


def timed(world) -> float:
    t0 = time.perf_counter()
    world.step()
    return time.perf_counter() - t0


def soft_rows(world) -> int:
    return len(world.soft_hits) + len(world.edge_hits)


def stacked_vs_apart(steps: int, settle: int) -> dict:
    scenes = {name: twelve(name == "stacked") for name in ("stacked", "apart")}
    for world, _ in scenes.values():
        for _ in tqdm(range(settle), desc="settling", leave=False):
            world.step()
    times = {name: [] for name in scenes}
    with tqdm(total=2 * steps, desc="stacked / apart") as bar:
        for _ in range(0, steps, 10):
            for name, (world, _) in scenes.items():
                for _ in range(10):
                    times[name].append(timed(world))
                    bar.update()
    out = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    out["ratio"] = out["stacked"] / out["apart"]
    out["soft rows"] = soft_rows(scenes["stacked"][0])
    return out


def tray(count: int, steps: int) -> dict:
    import pybullet as p
    import pybullet_data

    from integration import World
    from integration.intersection import intersection_depth

    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(0.01, physicsClientId=cid)
    p.loadURDF("plane.urdf", physicsClientId=cid)
    p.loadURDF("tray/traybox.urdf", [0, 0, 0], useFixedBase=True, physicsClientId=cid)
    world = World(client=cid)
    cubes = [cube(world, (0.05 * (k % 3 - 1), 0.05 * ((k // 3) % 3 - 1), 0.08 + 0.05 * (k // 9))) for k in range(count)]
    times = [timed(world) for _ in tqdm(range(steps), desc=f"{count} cubes in the tray")]
    surfaces = [world.entry(c).surface for c in cubes]
    depth = 0.0
    for a in range(count):
        for b in range(a + 1, count):
            sa, sb_ = surfaces[a], surfaces[b]
            depth = max(depth, intersection_depth(cubes[a].positions, sa.triangles, sa.edges, cubes[b].positions,
                                                  sb_.triangles, sb_.edges))
    p.disconnect(cid)
    settled = times[len(times) // 2:]
    return {"median": 1e3 * float(np.median(settled)), "worst": 1e3 * float(np.max(times)),
            "depth": 1e3 * depth, "soft rows": soft_rows(world)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60, help="timed steps of each twelve-cube scene")
    parser.add_argument("--settle", type=int, default=40, help="steps into contact before timing")
    parser.add_argument("--tray", type=int, default=30, help="cubes dropped into the tray")
    parser.add_argument("--tray-steps", type=int, default=150, help="steps of the tray scene")
    parser.add_argument("--no-tray", action="store_true", help="only the twelve cubes")
    args = parser.parse_args(argv)
    for name, value in (("--steps", args.steps), ("--tray", args.tray), ("--tray-steps", args.tray_steps)):
        if value < 1:
            parser.error(f"{name} must be at least 1, got {value}")
    if args.settle < 0:
        parser.error(f"--settle must be >= 0, got {args.settle}")
    r = stacked_vs_apart(args.steps, args.settle)
    print(f"twelve tet10 cubes: stacked 2x2x3 {r['stacked']:.1f} ms/step, apart {r['apart']:.1f} ms/step, "
          f"ratio {r['ratio']:.1f} (soft contact rows in the stack: {r['soft rows']})")
    if not args.no_tray:
        t = tray(args.tray, args.tray_steps)
        print(f"{args.tray} tet10 cubes in the tray: {t['median']:.1f} ms/step (median of the second half), worst "
              f"{t['worst']:.0f} ms; deepest interpenetration at the end {t['depth']:.3f} mm (soft rows "
              f"{t['soft rows']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
