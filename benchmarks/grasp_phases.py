"""Cost per step of the Panda pick-and-place (examples/robot_grasp.py), phase by phase, for this checkout and others.

    git worktree add /tmp/softbody-base <commit>
    python benchmarks/grasp_phases.py [/tmp/softbody-base ...] [--rounds 2]

Each checkout runs the example's scene and control loop in a fresh process (its own ``examples/robot_grasp.py``),
the checkouts one after the other, ``--rounds`` times (alternating, so that a slow spell of the machine hits each
alike); printed: ms per World.step in each phase (approach, descend, close, lift, hold, set down, release) and over
the whole run, per round and the median over rounds, with the cube's final height as a check that the runs agree.
The grasped phases (close to set down) are where the dense coupled contact solve runs: the fingers are movable
bodies pressing on the soft cube.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

PHASES = ["approach", "descend", "close", "lift", "hold", "set down", "release"]

RUN = r"""
import json, os, sys, time
sys.path.insert(0, os.getcwd()); sys.path.insert(0, os.path.join(os.getcwd(), "examples"))
import numpy as np
import robot_grasp as rg
import softbody
softbody.linsolve.set_threads(1)
cid, panda, world, cube = rg.build()
ctrl = rg.Grasp(cid, panda, world, cube)
size = float(np.ptp(cube.positions[:, 2]))
plan = [([0.5, 0, 0.2], 0.04, 1.0), ([0.5, 0, size / 2], 0.04, 1.0), ([0.5, 0, size / 2], 0.015, 0.5),
        ([0.5, 0, size / 2 + 0.2], 0.015, 1.0), ([0.5, 0, size / 2 + 0.2], 0.015, 2.0),
        ([0.5, 0, size / 2 + 0.003], 0.015, 1.0), ([0.5, 0, size / 2 + 0.003], 0.04, 0.5)]
ms = []
for target, opening, seconds in plan:
    s0, n0 = ctrl.seconds, ctrl.steps
    ctrl.go(target, opening, seconds)
    ms.append(1e3 * (ctrl.seconds - s0) / (ctrl.steps - n0))
print(json.dumps({"ms": ms, "all": 1e3 * ctrl.seconds / ctrl.steps, "z": float(cube.positions[:, 2].mean())}))
"""


def run(root: Path) -> dict:
    """One run of the scene in checkout ``root`` (a fresh process, one thread)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", RUN], cwd=root, env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("others", nargs="*", help="other checkouts to compare with this one")
    parser.add_argument("--rounds", type=int, default=2, help="runs per checkout, alternating (default 2)")
    args = parser.parse_args(argv)
    roots = [Path(__file__).resolve().parents[1]] + [Path(p).resolve() for p in args.others]
    for root in roots:
        if not (root / "examples" / "robot_grasp.py").exists():
            parser.error(f"{root} has no examples/robot_grasp.py")
    results: dict[Path, list[dict]] = {root: [] for root in roots}
    for r in range(args.rounds):
        for root in roots:
            res = run(root)
            results[root].append(res)
            print(f"# round {r + 1} {root}: " + ", ".join(f"{p} {v:.2f}" for p, v in zip(PHASES, res["ms"]))
                  + f"; all {res['all']:.2f} ms per step; cube z {res['z']:.5f} m", flush=True)
    print("\n| checkout | " + " | ".join(PHASES) + " | whole run | cube z m |")
    print("|---|" + "---:|" * (len(PHASES) + 2))
    for root, runs in results.items():
        ms = np.median([r["ms"] for r in runs], axis=0)
        print(f"| {root} | " + " | ".join(f"{v:.2f}" for v in ms)
              + f" | {np.median([r['all'] for r in runs]):.2f} | {runs[-1]['z']:.5f} |")


if __name__ == "__main__":
    main()
