"""Contact figures of the sheet-on-sphere scene: contacts at rest, penetration, time shares.

    python benchmarks/contact_report.py [--configs tet4:16x16x4 tet10:6x6x2] [--duration 3.0]

Runs each configuration for the full scene duration and prints a markdown table: active contacts
at the end (at rest), the deepest penetration of any surface node over the whole run, and the
share of the step time in collision detection (pybullet queries + broad phase), in the contact
loop's own work, and in the linear solves (which the contact loop drives), medians over the run.
"""

import os
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)
import argparse

import numpy as np

from experiments.scenes import sheet_on_sphere

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--configs", nargs="+", default=["tet4:16x16x4", "tet10:6x6x2"])
    ap.add_argument("--duration", type=float, default=3.0)
    args = ap.parse_args()
    print("| config | active contacts at rest | max penetration [mm] | collision % | contact loop % "
          "| linear solves % | median ms/step |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for cfg in args.configs:
        kind, cells = cfg.split(":")
        cells = tuple(int(c) for c in cells.split("x"))
        scene = sheet_on_sphere(kind, cells)
        worst, rows = 0.0, []

        def cb(world):
            global worst
            worst = max(worst, world.max_penetration())
            t = world.timings
            lin = t.get("assembly", 0) + t.get("factorize", 0) + t.get("solve", 0)
            rows.append((t["collision"] / t["total"], t["contact"] / t["total"], lin / t["total"], t["total"]))

        scene.run(args.duration, cb)
        rest = sum(int(r.active.sum()) for _, r in scene.world.contact_results.values())
        med = np.median(np.array(rows), axis=0)
        print(f"| sheet {kind} {cells} | {rest} | {1e3 * worst:.3f} | {100 * med[0]:.1f} | {100 * med[1]:.1f} "
              f"| {100 * med[2]:.1f} | {1e3 * med[3]:.1f} |", flush=True)
