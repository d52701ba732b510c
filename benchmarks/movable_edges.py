"""What the rows of soft edges against links the coupled solve moves cost and buy, for this checkout and others.

    git worktree add /tmp/softbody-base <commit>
    python benchmarks/movable_edges.py [/tmp/softbody-base ...] [--steps 200] [--off]

Two scenes, each checkout in a fresh process of its own (single thread):

- **box**: a 2 kg, 7.5 cm dynamic box set on a soft tet10 block (10 cm, 2x2x2 cells, E = 1e5), its rim across the
  block's faces between nodes (tests/test_plugin.py's heaviest box, near an edge);
- **capsule**: a 1 kg capsule (radius 1 cm, 20 cm long) lying across a soft tet4 slab (30 x 30 x 4 cm, 8x8x2 cells,
  E = 1e5), between its node rows.

``--off`` adds this checkout with ``World(movable_edges=False)`` (those rows left out).

Printed per scene: ms per step (median of the second half of ``--steps`` steps), the deepest the soft surface and
the rigid body interpenetrate at the end by tests/geometry.py's independent test (triangle samples against the
shape's exact distance, the shape's edge points inside the soft surface by winding number), and the rigid body's
height.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

RUN = r"""
import json, os, sys, time
sys.path.insert(0, os.getcwd())
sys.path.insert(0, TESTS)
import numpy as np
import pybullet as p
import softbody as sb
from integration import World
from geometry import rigid_penetration


def box():
    world = World(dt=0.01, **OPTIONS)
    world.add_plane()
    mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05))
    soft = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
    world.add_soft(soft, friction=0.5)
    rigid = world.add_box((0.0375,) * 3, position=(0.00625, 0, 0.1 + 0.0375 + 0.001), mass=2.0)
    return world, soft, rigid.id


def capsule():
    world = World(dt=0.01, **OPTIONS)
    world.add_plane()
    mesh = sb.box_mesh((0.3, 0.3, 0.04), (8, 8, 2), "tet4", center=(0, 0, 0.02))
    soft = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 1000.0))
    world.add_soft(soft, friction=0.5)
    shape = p.createCollisionShape(p.GEOM_CAPSULE, radius=0.01, height=0.2, physicsClientId=world.client)
    q = p.getQuaternionFromEuler([0, np.pi / 2, 0.3])
    rigid = p.createMultiBody(1.0, shape, -1, [0.013, 0.011, 0.0505], q, physicsClientId=world.client)
    return world, soft, rigid


out = {}
for name, make in (("box", box), ("capsule", capsule)):
    world, soft, rigid = make()
    times = []
    for _ in range(STEPS):
        t0 = time.perf_counter()
        world.step()
        times.append(time.perf_counter() - t0)
    depth = rigid_penetration(world.client, rigid, soft.positions, soft.mesh.surface_triangles())
    z = p.getBasePositionAndOrientation(rigid, physicsClientId=world.client)[0][2]
    out[name] = (1e3 * float(np.median(times[len(times) // 2:])), 1e3 * depth, z)
print("RESULT " + json.dumps(out))
"""


def run(checkout: Path, steps: int, options: str = "{}") -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "SOFTBODY_COMPILE": "now"}
    code = RUN.replace("TESTS", repr(str(ROOT / "tests"))).replace("STEPS", str(steps)).replace("OPTIONS", options)
    done = subprocess.run([sys.executable, "-c", code], cwd=checkout, env=env, capture_output=True, text=True)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        raise SystemExit(f"{checkout}: the run failed\n{done.stderr[-2000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("others", nargs="*", type=Path, help="other checkouts (git worktrees) to compare with")
    parser.add_argument("--steps", type=int, default=200, help="steps of each scene")
    parser.add_argument("--off", action="store_true", help="also this checkout with World(movable_edges=False)")
    args = parser.parse_args(argv)
    if args.steps < 2:
        parser.error(f"--steps must be at least 2, got {args.steps}")
    print("| checkout | scene | ms/step | deepest interpenetration mm | rigid body z m |")
    print("|---|---|---:|---:|---:|")
    runs = [(ROOT, "{}", str(ROOT))] + ([(ROOT, "{'movable_edges': False}", f"{ROOT}, movable_edges=False")]
                                        if args.off else [])
    runs += [(Path(other), "{}", str(other)) for other in args.others]
    for checkout, options, label in runs:
        for scene, (ms, depth, z) in run(checkout.resolve(), args.steps, options).items():
            print(f"| {label} | {scene} | {ms:.1f} | {depth:.3f} | {z:.5f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
