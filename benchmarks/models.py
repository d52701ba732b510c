"""Which elastic model a scene needs: each model against a converged neo-Hookean reference in stretch, compression
and bending, and what a step of each costs (issue 32, item 5; docs/materials.md, "Which model a scene needs").

Scenes (1000 kg/m^3):

- stretch / compression: a 0.2 x 0.1 x 0.1 m block (E 1e5 Pa, nu 0.3), both end faces clamped, the far one moved
  along the block to a stretch of 1.1, 1.25, 1.5 (stretch) or 0.9, 0.75, 0.6 (compression; the block is too short
  to buckle); the end force [N] (the reaction on the moved face); tet10 (4, 2, 2), reference tet10 (12, 6, 6);
- bending: a 1 x 0.1 x 0.1 m cantilever (E 1e7 Pa, nu 0.3) clamped at one end, under its weight times 1, 3 and 6
  (tip sags of 15, 39 and 61 % of its length); the tip's vertical displacement [m]; tet10 (10, 1, 1),
  reference tet10 (30, 3, 3).

Each model on the same mesh: "linear" (small strain, no rotation: solve_static), "warped" (the
minimum of the paper's warped energy, solve_equilibrium(model="energy"): where scheme="newton" comes to rest; the
warped step's own balance, solve_equilibrium's default, is within 0.6 mm of it on the bent cantilever), "corotated"
and "neo-hookean" (their energies' minima). Reference: neo-Hookean on the fine mesh, the same quantity. The cost:
median ms per step of the cantilever swinging from rest under its weight (E 1e6 Pa, tet10 (20, 2, 2), dt 0.01, 30 steps
after 5) for each model and each scheme that steps it, single thread.

    python benchmarks/models.py [--out docs/bench/models.md]      (about 15 minutes)
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import softbody as sb  # noqa: E402

BLOCK, BAR = (0.2, 0.1, 0.1), (1.0, 0.1, 0.1)
STRETCHES = (1.1, 1.25, 1.5)
COMPRESSIONS = (0.9, 0.75, 0.6)
LOADS = (1.0, 3.0, 6.0)
MODELS = ("linear", "warped", "corotated", "neo-hookean")


def bar(model: str, cells, nu: float, size=BLOCK, E: float = 1e5) -> sb.FemBody:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sb.FemBody(sb.box_mesh(size, cells, "tet10"), sb.LinearElastic(E, nu, 1000.0), model=model)


def equilibrium(body: sb.FemBody, gravity) -> np.ndarray:
    """The positions where the body's model rests (the linear model: solve_static)."""
    if body.model == "linear":
        return body.rest + sb.solve_static(body, gravity)
    return body.rest + sb.solve_equilibrium(body, gravity, model="energy", load_steps=10, tol=1e-8, max_iter=60)


def end_force(model: str, cells, stretch: float) -> float:
    """The force [N] on the moved end face at the given stretch."""
    body = bar(model, cells, 0.3, BLOCK)
    x = body.rest[:, 0]
    near, far = np.flatnonzero(x < x.min() + 1e-9), np.flatnonzero(x > x.max() - 1e-9)
    body.fix(near)
    moved = body.rest[far] + np.array([(stretch - 1.0) * BLOCK[0], 0.0, 0.0])
    body.prescribe(far, lambda t, p=moved: p)
    pos = equilibrium(body, (0.0, 0.0, 0.0))
    return float(-body.elastic_forces(pos)[far, 0].sum())


def tip_sag(model: str, cells, load: float) -> float:
    """The tip's vertical displacement [m] of the cantilever under ``load`` times its weight."""
    body = bar(model, cells, 0.3, BAR, 1e7)
    x = body.rest[:, 0]
    body.fix(np.flatnonzero(x < x.min() + 1e-9))
    pos = equilibrium(body, (0.0, 0.0, -9.81 * load))
    return float((pos - body.rest)[x > x.max() - 1e-9, 2].mean())


def step_cost(model: str, scheme: str, repeats: int = 30) -> float:
    """Median ms per step of the cantilever swinging from rest under its weight."""
    body = bar(model, (20, 2, 2), 0.3, BAR, 1e6)
    body.fix(np.flatnonzero(body.rest[:, 0] < body.rest[:, 0].min() + 1e-9))
    sim = sb.Simulation(body, 0.01, scheme=scheme)
    for _ in range(5):
        sim.step()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        sim.step()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="write the tables (markdown) here")
    args = ap.parse_args()
    lines = ["# Elastic models against a converged neo-Hookean reference", "",
             "`python benchmarks/models.py` (module doc: the scenes). Each cell: the model's value on the coarse tet10 "
             "mesh and its error against neo-Hookean on the fine one.", ""]
    for title, fun, params, label, coarse, fine in (
            ("Stretch: end force [N]", end_force, STRETCHES, "stretch", (4, 2, 2), (12, 6, 6)),
            ("Compression: end force [N]", end_force, COMPRESSIONS, "stretch", (4, 2, 2), (12, 6, 6)),
            ("Bending: tip sag [m]", tip_sag, LOADS, "weight x", (10, 1, 1), (30, 3, 3))):
        ref = [fun("neo-hookean", fine, p) for p in params]
        lines += [f"## {title}", "", "| model | " + " | ".join(f"{label} {p:g}" for p in params) + " |",
                  "|---|" + "---:|" * len(params),
                  f"| reference (neo-Hookean, {'x'.join(map(str, fine))}) | " + " | ".join(f"{r:.4g}" for r in ref)
                  + " |"]
        for model in MODELS:
            vals = [fun(model, coarse, p) for p in params]
            lines.append(f"| {model} | " + " | ".join(f"{v:.4g} ({100 * (v / r - 1):+.1f} %)"
                                                      for v, r in zip(vals, ref)) + " |")
            print(lines[-1], flush=True)
        lines.append("")
    lines += ["## Cost per step", "", "The cantilever swinging from rest under its weight, tet10 (20, 2, 2), E 1e6 Pa, "
              "dt 0.01, single thread: median ms per step over 30 steps.", "", "| model | scheme | ms/step |",
              "|---|---|---:|"]
    for model, scheme in (("linear", "warped"), ("warped", "warped"), ("warped", "newton"), ("corotated", "newton"),
                          ("neo-hookean", "newton"), ("neo-hookean", "bdf2")):
        lines.append(f"| {model} | {scheme} | {step_cost(model, scheme):.1f} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
