"""The speed/accuracy trade of the two schemes (softbody.newton): time per step and trajectory error against a
small-step reference, over a ladder of step sizes, for the canonical scenes and a spinning cube.

    python benchmarks/scheme_trade.py --out docs/scheme_trade.md --plot docs/img/scheme_trade.png

Per scene and scheme and step h: the largest difference of the monitored coordinate [mm] from the reference
run (Newton at h = 1 ms, interpolated to the run's times) over the run, the median wall time per step [ms]
(one thread), and for the spinning cube the largest relative change of any node-to-node distance (a rigid
spin keeps them; the warped step stretches the cube). A run that raises (SimulationDiverged) is reported
as such.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import softbody as sb  # noqa: E402
from integration.scenes import cantilever, hanging_tube, sheet_on_sphere  # noqa: E402

LADDER = (0.005, 0.01, 0.02, 0.04)
REFERENCE_DT = 0.001


class Spin:
    """A 0.2 m tet10 cube (E = 1e7, no damping, no gravity) spinning at 5 rev/s about an oblique axis;
    monitored: x of a corner node. Shaped like integration.scenes.Scene for this script."""

    def __init__(self, dt: float, scheme: str):
        mesh = sb.box_mesh((0.2, 0.2, 0.2), (2, 2, 2), "tet10")
        self.body = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.33, 1000.0), damping=(0.0, 0.0))
        axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
        self.body.velocities[:] = np.cross(2 * math.pi * 5 * axis, mesh.nodes)
        self.sim = sb.Simulation(self.body, dt, gravity=(0, 0, 0), scheme=scheme)
        self.monitor = int(np.argmax(mesh.nodes.sum(axis=1)))
        self._pairs = np.triu_indices(mesh.n_nodes, 1)
        self._d0 = self._distances(mesh.nodes)

    def _distances(self, x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(x[:, None] - x[None], axis=2)[self._pairs]

    def monitored(self) -> float:
        return float(self.body.positions[self.monitor, 0])

    def shape_change(self) -> float:
        """The largest relative change of any node-to-node distance now (a rigid spin keeps them all)."""
        return float(np.abs(self._distances(self.body.positions) / self._d0 - 1).max())


SCENES = {
    "sheet-on-sphere tet10 4x4x1": (lambda dt, scheme: sheet_on_sphere("tet10", (4, 4, 1), dt=dt, scheme=scheme), 1.5),
    "hanging-tube tet10 8x1x6": (lambda dt, scheme: hanging_tube("tet10", (8, 1, 6), dt=dt, scheme=scheme), 2.0),
    "cantilever tet10 10x1x1": (lambda dt, scheme: cantilever("tet10", (10, 1, 1), dt=dt, scheme=scheme), 1.0),
    "spinning cube tet10 2x2x2, 5 rev/s": (lambda dt, scheme: Spin(dt, scheme), 0.5),
}


def run(build, dt: float, scheme: str, duration: float) -> tuple[np.ndarray, np.ndarray, float, float, str]:
    """(times, monitored values, median ms per step, largest shape change (NaN but for the spin), error text)
    of one run."""
    scene = build(dt, scheme)
    step = scene.world.step if hasattr(scene, "world") else scene.sim.step
    ts, xs, ms, shape = [0.0], [scene.monitored()], [], 0.0 if hasattr(scene, "shape_change") else math.nan
    try:
        for n in range(int(round(duration / dt))):
            tic = time.perf_counter()
            step()
            ms.append(1e3 * (time.perf_counter() - tic))
            ts.append((n + 1) * dt)
            xs.append(scene.monitored())
            if hasattr(scene, "shape_change"):
                shape = max(shape, scene.shape_change())
    except sb.SimulationDiverged as exc:
        return np.array(ts), np.array(xs), float(np.median(ms)) if ms else math.nan, shape, str(exc).split(":")[0]
    return np.array(ts), np.array(xs), float(np.median(ms)), shape, ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/scheme_trade.md")
    ap.add_argument("--plot", default="docs/img/scheme_trade.png")
    args = ap.parse_args(argv)
    rows, curves = [], {}
    for name, (build, duration) in SCENES.items():
        t_ref, x_ref, _, _, err = run(build, REFERENCE_DT, "newton", duration)
        if err:
            raise SystemExit(f"the reference run of {name} failed: {err}")
        for scheme in ("warped", "newton"):
            for dt in LADDER:
                t, x, ms, shape, err = run(build, dt, scheme, duration)
                error = float(np.abs(x - np.interp(t, t_ref, x_ref)).max())
                if err or not np.isfinite(error):
                    rows.append((name, scheme, dt, ms, math.nan, shape, err or "non-finite"))
                else:
                    rows.append((name, scheme, dt, ms, error, shape, ""))
                    curves.setdefault((name, scheme), []).append((ms, 1e3 * error, dt))
                print(rows[-1], flush=True)
    lines = ["| scene | scheme | h [s] | ms/step | largest error [mm] | largest shape change (spin) |",
             "|---|---|---:|---:|---:|---:|"]
    for name, scheme, dt, ms, error, shape, err in rows:
        lines.append(f"| {name} | {scheme} | {dt:g} | {ms:.1f} | "
                     + (f"{1e3 * error:.3g}" if not err else f"failed: {err}")
                     + (f" | {100 * shape:.2f}% |" if np.isfinite(shape) else " | - |"))
    Path(args.out).write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SCENES), figsize=(4.2 * len(SCENES), 3.8))
    for ax, name in zip(axes, SCENES):
        for scheme, style in (("warped", "o-"), ("newton", "s--")):
            pts = curves.get((name, scheme), [])
            if pts:
                ms, err, dts = zip(*pts)
                ax.loglog(ms, err, style, label=scheme)
                for m, e, d in pts:
                    ax.annotate(f"{d:g}", (m, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("ms per step")
        ax.set_ylabel("largest error [mm]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Time per step against error (labels: h [s]); reference: newton at h = 1 ms", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=110)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
