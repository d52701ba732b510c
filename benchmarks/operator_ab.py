"""Step time of the sheet-on-sphere scene with two IterativeSettings.operator choices, alternating in one process.

    python benchmarks/operator_ab.py [--configs tet10:9x9x2 hex8:20x20x5] [--steps 150] [--warmup 20]
                                     [--operators assembled matrix-free]

Two copies of the scene (docs/method.md; with contact) step in turn, one with each operator (default: K'
assembled against matrix-free), so that a change of the machine's speed hits both alike: the median of
the per-step ratios (second / first) is the figure to read. Also printed: PCG iterations per step and the
largest difference of their node positions at the end [m] (both solve to the same PCG tolerance; where
a contact switches on in one run and not in the other, they part by more).
"""
import argparse
import os
import time

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

import numpy as np

from experiments.scenes import sheet_on_sphere
from softbody import linsolve
from softbody.integrator import IterativeSettings

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", nargs="+", default=["tet10:9x9x2"])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--operators", nargs=2, default=["assembled", "matrix-free"])
    args = ap.parse_args()
    linsolve.set_threads(1)
    first, second = args.operators
    if first == second:
        ap.error(f"--operators needs two different operators, got {first!r} twice")
    print(f"| config | {first} ms/step | {second} ms/step | {second} / {first} (median of ratios) "
          f"| PCG its/step ({first}, {second}) | max position difference m |")
    print("|---|---:|---:|---:|---|---:|")
    for cfg in args.configs:
        kind, cells = cfg.split(":")
        cells = tuple(int(c) for c in cells.split("x"))
        scenes = {}
        for op in (first, second):
            sc = sheet_on_sphere(kind, cells)
            sim = sc.world.sim
            sim.method = "iterative"  # the operator matters only there (small meshes default to direct)
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
        a, m = np.array(times[first]), np.array(times[second])
        diff = np.abs(scenes[first].body.positions - scenes[second].body.positions).max()
        print(f"| {kind} {cells} | {1e3 * np.median(a):.2f} | {1e3 * np.median(m):.2f} | {np.median(m / a):.3f} "
              f"| {', '.join(f'{(sc.body._preconditioner.iterations - its0[op]) / args.steps:.2f}' for op, sc in scenes.items())} "
              f"| {diff:.1e} |", flush=True)
