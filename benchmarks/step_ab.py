"""Free-fall step time of two checkouts of softbody, alternating in one process (no contact, no World).

    git worktree add /tmp/softbody-base <commit>
    python benchmarks/step_ab.py /tmp/softbody-base [--steps 20]

Both versions (this checkout's ``softbody`` and the other's, loaded under another module name) build
the same sheet meshes of SPEC.md and take alternating iterative steps after 5 warm-up steps each, so a
change of the machine's speed hits both alike: the median of the per-step ratios is the figure to read.
Also printed: the largest difference of their node positions at the end [m].
"""
import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import numpy as np

CONFIGS = [("tet4", (24, 24, 6)), ("hex8", (20, 20, 5)), ("tet10", (9, 9, 2))]


def load(name: str, root: Path):
    """The package ``root/softbody`` imported as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, root / "softbody" / "__init__.py",
                                                  submodule_search_locations=[str(root / "softbody")])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("base", type=Path, help="root of the other checkout (holding softbody/)")
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    if not (args.base / "softbody" / "__init__.py").exists():
        sys.exit(f"{args.base} holds no softbody/ package")
    versions = {"this": load("softbody", Path(__file__).resolve().parents[1]), "base": load("softbody_base", args.base)}
    versions["this"].linsolve.set_threads(1)
    print(f"| element | cells | nodes | this ms/step | base ms/step | this / base (median of ratios) | max position difference m |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for kind, cells in CONFIGS:
        sims = {}
        for name, sb in versions.items():
            mesh = sb.box_mesh((1.0, 1.0, 0.25), cells, kind, center=(0, 0, 0.475))
            sims[name] = sb.Simulation(sb.FemBody(mesh, sb.LinearElastic(5e5, 0.33, 1000.0)), 0.01, method="iterative")
            for _ in range(5):
                sims[name].step()
        times = {name: [] for name in sims}
        for _ in range(args.steps):
            for name, sim in sims.items():
                tic = time.perf_counter()
                sim.step()
                times[name].append(time.perf_counter() - tic)
        a, b = np.array(times["this"]), np.array(times["base"])
        diff = np.abs(sims["this"].bodies[0].positions - sims["base"].bodies[0].positions).max()
        print(f"| {kind} | {cells} | {sims['this'].bodies[0].n_nodes} | {1e3 * np.median(a):.1f} | {1e3 * np.median(b):.1f} | "
              f"{np.median(a / b):.2f} | {diff:.1e} |", flush=True)
