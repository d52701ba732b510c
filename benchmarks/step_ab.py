"""Step time of two checkouts of softbody, alternating in one process.

    git worktree add /tmp/softbody-base <commit>
    python benchmarks/step_ab.py /tmp/softbody-base [--mode scene|free] [--steps 60] [--block 10]

Both versions (this checkout's ``softbody`` and ``integration``, and the other's, loaded under other
module names) build the same configurations and step them in alternating blocks, so that a change of
the machine's speed hits both alike: the median of the per-block ratios is the figure to read.

- ``--mode scene`` (default): the canonical sheet-on-sphere scene with contact through a World (the
  bench configurations of ``softbody bench``), after ``--warmup`` steps into the impact;
- ``--mode free``: the bare Simulation of the same sheets in free fall (no World, no contact).

A configuration ``cubes:N`` is N soft cubes (tet10, 2x2x2 cells, 0.1 m, 0.15 m apart) settling on a plane in one
World (issue 18's many-body scene, built here with each version's World, as older versions lack its scene).

Also printed: the largest difference of the monitored trajectories [m] (0 when the change keeps the
numbers).
"""
import argparse
import importlib
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

import numpy as np

# this checkout importable by name throughout: numba's on-disk cache (softbody.kernels) imports the module
# by name when it loads a compiled kernel, after load() has put sys.modules back
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CONFIGS = [("tet4", (16, 16, 4)), ("tet4", (24, 24, 6)), ("hex8", (20, 20, 5)), ("tet10", (9, 9, 2))]
PACKAGES = ("softbody", "integration", "experiments")


def load(root: Path) -> dict:
    """The packages of checkout ``root`` imported afresh, returned as {name: module}; sys.modules is left
    as it was (each version's modules keep references to their own siblings)."""
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] in PACKAGES}
    for k in saved:
        del sys.modules[k]
    sys.path.insert(0, str(root))
    try:
        mods = {"softbody": importlib.import_module("softbody"), "world": importlib.import_module("integration.world"),
                "scenes": importlib.import_module("experiments.scenes" if (root / "experiments" / "scenes.py").exists()
                                                  else "integration.scenes")}  # before the move to experiments/
    finally:
        sys.path.remove(str(root))
        for k in [k for k in sys.modules if k.split(".")[0] in PACKAGES]:
            del sys.modules[k]
        sys.modules.update(saved)
    return mods


def cubes(mods: dict, count: int):
    """(step, monitored) of ``count`` tet10 cubes settling on a plane, 1 mm above it at the start."""
    sb = mods["softbody"]
    world = mods["world"].World(dt=0.01)
    world.add_plane()
    bodies = []
    for k in range(count):
        mesh = sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0.15 * k, 0.0, 0.051))
        bodies.append(world.add_soft(sb.FemBody(mesh, sb.LinearElastic(5e5, 0.33, 1000.0), damping=(0.1, 0.001)),
                                     friction=0.5))
    return world.step, lambda: float(bodies[0].positions[:, 2].min())


def build(mods: dict, mode: str, kind: str, cells):
    """(step function, monitored value function) of one configuration."""
    if kind == "cubes":
        return cubes(mods, cells[0])
    if mode == "free":
        sb = mods["softbody"]
        mesh = sb.box_mesh((1.0, 1.0, 0.25), cells, kind, center=(0, 0, 0.475))
        sim = sb.Simulation(sb.FemBody(mesh, sb.LinearElastic(5e5, 0.33, 1000.0)), 0.01, method="iterative")
        return sim.step, lambda: float(sim.bodies[0].positions[:, 2].min())
    scene = mods["scenes"].sheet_on_sphere(kind, cells)
    return scene.world.step, scene.monitored


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("base", type=Path, help="root of the other checkout (holding softbody/ and integration/)")
    ap.add_argument("--mode", choices=("scene", "free"), default="scene")
    ap.add_argument("--steps", type=int, default=60, help="timed steps per configuration and version")
    ap.add_argument("--block", type=int, default=10, help="steps per block (the versions alternate by block)")
    ap.add_argument("--warmup", type=int, default=20, help="untimed steps first (20: into the sheet's impact)")
    ap.add_argument("--configs", nargs="*", default=None, metavar="KIND:NXxNYxNZ",
                    help="configurations, e.g. tet10:9x9x2 or cubes:10 (default: the bench's four)")
    args = ap.parse_args()
    if not (args.base / "softbody" / "__init__.py").exists():
        sys.exit(f"{args.base} holds no softbody/ package")
    configs = CONFIGS if not args.configs else [
        (c.split(":")[0], tuple(int(n) for n in c.split(":")[1].split("x"))) for c in args.configs]  # cubes:10
    versions = {"this": load(Path(__file__).resolve().parents[1]), "base": load(args.base)}
    versions["this"]["softbody"].linsolve.set_threads(1)
    print(f"mode: {args.mode}; {args.steps} steps in blocks of {args.block} after {args.warmup} warm-up steps")
    print("| element | cells | this ms/step | base ms/step | this / base (median of block ratios) [min-max] | "
          "max trajectory difference m |")
    print("|---|---|---:|---:|---:|---:|")
    for kind, cells in configs:
        runs = {name: build(mods, args.mode, kind, cells) for name, mods in versions.items()}
        traj = {name: [] for name in runs}
        for name, (step, mon) in runs.items():
            for _ in range(args.warmup):
                step()
                traj[name].append(mon())
        times = {name: [] for name in runs}
        for _ in range(max(1, args.steps // args.block)):
            for name, (step, mon) in runs.items():
                tic = time.perf_counter()
                for _ in range(args.block):
                    step()
                times[name].append((time.perf_counter() - tic) / args.block)
                traj[name].append(mon())
        a, b = np.array(times["this"]), np.array(times["base"])
        r = a / b
        diff = float(np.abs(np.array(traj["this"]) - np.array(traj["base"])).max())
        print(f"| {kind} | {cells} | {1e3 * np.median(a):.2f} | {1e3 * np.median(b):.2f} | "
              f"{np.median(r):.3f} [{r.min():.3f}-{r.max():.3f}] | {diff:.1e} |", flush=True)
