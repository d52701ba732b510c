"""Calibrate experiments.sizing: peak memory and time per step of the sheet-on-sphere scene against its size.

Each configuration runs in a fresh interpreter (one at a time): after the imports the command line does
(experiments.scenes: numpy, scipy, pybullet), the scene is built and stepped ``--steps`` times (into the
impact on the sphere, at 0.1 s), and the child reports the peak RSS increase over the RSS after the imports
(Linux VmHWM) [MB] and the median wall time of the steps from the 16th on, into the impact, where steps
cost most [ms] (of the steps after the first if there are fewer). The fit per element type,
mem = M0 + a (N / 1000)^p and ms = b (N / 1000)^q over the configurations with at least ``--fit-from`` nodes,
is what experiments/sizing.py uses.

    python benchmarks/memory_model.py [--steps 25] [--max-nodes 50000] [--json out.json]
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

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {
    "tet4": [(8, 8, 3), (16, 16, 4), (24, 24, 6), (32, 32, 8), (44, 44, 11), (56, 56, 14)],
    "hex8": [(8, 8, 3), (16, 16, 4), (24, 24, 6), (32, 32, 8), (44, 44, 11), (56, 56, 14)],
    "tet10": [(4, 4, 1), (9, 9, 2), (14, 14, 3), (18, 18, 4), (24, 24, 5), (30, 30, 6)],
}
CHILD = """
import json, sys, time
import numpy as np
from experiments.scenes import build_scene
from experiments.bench import _rss_mb
element, cells, steps = sys.argv[1], tuple(int(c) for c in sys.argv[2].split("x")), int(sys.argv[3])
base = _rss_mb()
tic = time.perf_counter()
scene = build_scene("sheet-on-sphere", element=element, cells=cells)
build_s = time.perf_counter() - tic
ms = []
for _ in range(steps):
    tic = time.perf_counter()
    scene.world.step()
    ms.append(1e3 * (time.perf_counter() - tic))
print(json.dumps({"element": element, "cells": list(cells), "nodes": scene.body.n_nodes,
                  "elements": scene.body.mesh.n_elements, "peak_mb": _rss_mb() - base, "base_mb": base,
                  "build_s": build_s, "first_ms": ms[0], "free_fall_ms": float(np.median(ms[1:10])),
                  "ms_per_step": float(np.median(ms[15:] if len(ms) > 15 else ms[1:]))}))
"""


def measure(element: str, cells, steps: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", CHILD, element, "x".join(map(str, cells)), str(steps)], cwd=ROOT,
                         env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def fit(rows: list[dict], key: str, offset: float = 0.0) -> tuple[float, float]:
    """(coefficient, exponent) of rows[key] - offset = c (nodes / 1000)^p, least squares in logs."""
    n = np.array([r["nodes"] / 1000 for r in rows])
    y = np.array([r[key] - offset for r in rows])
    p, logc = np.polyfit(np.log(n), np.log(y), 1)
    return float(np.exp(logc)), float(p)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--max-nodes", type=int, default=50000)
    ap.add_argument("--fit-from", type=int, default=4000, help="fit on configurations with at least this many nodes")
    ap.add_argument("--offset-mb", type=float, default=40.0, help="M0: the increase of the smallest runs [MB]")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from softbody.meshing import grid_mesh_size

    results = []
    for element, ladder in CONFIGS.items():
        for cells in ladder:
            if grid_mesh_size(cells, element)[0] > args.max_nodes:
                continue
            r = measure(element, cells, args.steps)
            results.append(r)
            print(f"{element:5s} {'x'.join(map(str, cells)):>9s} {r['nodes']:7d} nodes {r['elements']:7d} elements  "
                  f"peak +{r['peak_mb']:7.0f} MB  {r['ms_per_step']:8.1f} ms/step (free fall {r['free_fall_ms']:.1f}, "
                  f"first {r['first_ms']:.0f} ms)  "
                  f"build {r['build_s']:.1f} s", flush=True)
    print("\nfit over runs with at least", args.fit_from, "nodes:")
    for element in CONFIGS:
        rows = [r for r in results if r["element"] == element and r["nodes"] >= args.fit_from]
        if len(rows) >= 2:
            a, p = fit(rows, "peak_mb", args.offset_mb)
            b, q = fit(rows, "ms_per_step")
            print(f'    "{element}": ({a:.1f}, {p:.3f}, {b:.2f}, {q:.3f}),  # MB = {args.offset_mb:g} + a (N/1000)^p, '
                  f"ms = b (N/1000)^q; MB per 1000 nodes at the largest: "
                  f"{rows[-1]['peak_mb'] / rows[-1]['nodes'] * 1000:.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
