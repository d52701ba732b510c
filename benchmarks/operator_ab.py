"""Step time of the sheet-on-sphere scene with K' assembled against matrix-free, alternating in one process.

    python benchmarks/operator_ab.py [--configs tet10:9x9x2 hex8:20x20x5] [--steps 150] [--warmup 20]

Two copies of the scene (SPEC.md; with contact) step in turn, one with IterativeSettings(operator=
"assembled"), one with "matrix-free", so that a change of the machine's speed hits both alike: the
median of the per-step ratios is the figure to read. Also printed: the largest difference of their node
positions at the end [m] (both solve to the same PCG tolerance).
"""
import argparse
import os
import time

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import numpy as np

from integration.scenes import sheet_on_sphere
from softbody import linsolve
from softbody.integrator import IterativeSettings

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", nargs="+", default=["tet10:9x9x2"])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--warmup", type=int, default=20)
    args = ap.parse_args()
    linsolve.set_threads(1)
    print("| config | assembled ms/step | matrix-free ms/step | matrix-free / assembled (median of ratios) "
          "| PCG its/step a, mf | max position difference m |")
    print("|---|---:|---:|---:|---|---:|")
    for cfg in args.configs:
        kind, cells = cfg.split(":")
        cells = tuple(int(c) for c in cells.split("x"))
        scenes = {}
        for op in ("assembled", "matrix-free"):
            sc = sheet_on_sphere(kind, cells)
            sim = sc.world.sim
            sim.settings = IterativeSettings(tol=sim.settings.tol, operator=op)
            for _ in range(args.warmup):
                sc.world.step()
            scenes[op] = sc
        times = {op: [] for op in scenes}
        its0 = {op: sc.body._preconditioner.iterations for op, sc in scenes.items()}
        for _ in range(args.steps):
            for op, sc in scenes.items():
                tic = time.perf_counter()
                sc.world.step()
                times[op].append(time.perf_counter() - tic)
        a, m = np.array(times["assembled"]), np.array(times["matrix-free"])
        diff = np.abs(scenes["assembled"].body.positions - scenes["matrix-free"].body.positions).max()
        print(f"| {kind} {cells} | {1e3 * np.median(a):.2f} | {1e3 * np.median(m):.2f} | {np.median(m / a):.3f} "
              f"| {', '.join(f'{(sc.body._preconditioner.iterations - its0[op]) / args.steps:.2f}' for op, sc in scenes.items())} "
              f"| {diff:.1e} |", flush=True)
