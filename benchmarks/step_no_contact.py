"""Median time per step of the sheet-on-sphere meshes of docs/method.md without contact (free fall, no World).

    python benchmarks/step_no_contact.py [--steps 20] [--threads 1]

Both solver paths are timed (direct: assemble + factorise every step; iterative: PCG with a reused
factorisation), after 5 warm-up steps; the median over the timed steps is printed.
"""

import os
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)
import argparse
import time

import numpy as np

import softbody as sb
from softbody.linsolve import set_threads

CONFIGS = [("tet4", (24, 24, 6)), ("hex8", (20, 20, 5)), ("tet10", (9, 9, 2))]

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    set_threads(args.threads)
    print(f"| element | cells | elements | nodes | method | median ms/step |  ({args.threads} thread(s))")
    print("|---|---|---:|---:|---|---:|")
    for kind, cells in CONFIGS:
        mesh = sb.box_mesh((1.0, 1.0, 0.25), cells, kind, center=(0, 0, 0.475))
        for method in ("direct", "iterative"):
            body = sb.FemBody(mesh, sb.LinearElastic(5e5, 0.33, 1000.0))
            sim = sb.Simulation(body, 0.01, method=method)
            for _ in range(5):
                sim.step()
            times = []
            for _ in range(args.steps):
                tic = time.perf_counter()
                sim.step()
                times.append(time.perf_counter() - tic)
            print(f"| {kind} | {cells} | {mesh.n_elements} | {mesh.n_nodes} | {method} | "
                  f"{1e3 * np.median(times):.1f} |", flush=True)
