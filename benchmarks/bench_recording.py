"""Overhead and file size of rerun recordings (integration.recording.Recorder).

    python benchmarks/bench_recording.py [--element tet4] [--cells 8 8 3] [--duration 3.0] [--repeats 3]

The sheet-on-sphere scene is run from scratch with and without a recorder attached (alternating,
``--repeats`` times each). Per step the wall time of ``world.step()`` plus the recorder call is
measured; the first ``--warmup`` steps of each run are left out. Overhead is

    (median step time with recording - median without) / median without

(the mean-based figure, which includes the batched sends, and the process CPU time per step, which
includes rerun's writer threads and ignores other processes on a shared machine, are printed too).
The file size per
simulated second comes from the recorded runs. One extra run records every 10th step.
CPU-heavy: a few tens of seconds at the defaults.
"""
from __future__ import annotations

import os
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from integration.recording import Recorder
from experiments.scenes import sheet_on_sphere


def one_run(element: str, cells, duration: float, warmup: int, path: Path | None, every: int = 1):
    scene = sheet_on_sphere(element, cells)
    world = scene.world
    n = int(round(duration / world.dt))
    rec = Recorder.attach(scene, path=path, every=every) if path is not None else None
    times = []
    try:
        for i in range(n):
            if i == warmup:
                cpu0 = time.process_time()
            t0 = time.perf_counter()
            world.step()
            if rec is not None:
                rec(world)
            times.append(time.perf_counter() - t0)
    finally:
        if rec is not None:
            t0 = time.perf_counter()
            rec.close()
            times[-1] += time.perf_counter() - t0  # the final send counts too
    cpu = (time.process_time() - cpu0) / max(n - warmup, 1)  # all threads of the process (rerun's writers too)
    size = path.stat().st_size if path is not None else 0
    return np.array(times[warmup:]), size, world.t, scene, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--element", default="tet4")
    ap.add_argument("--cells", type=int, nargs=3, default=(8, 8, 3))
    ap.add_argument("--duration", type=float, default=3.0, help="simulated seconds per run (scene default 3.0)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=10, help="steps left out of the timing at the start of each run")
    args = ap.parse_args(argv)

    off, on, sizes, cpu_off, cpu_on = [], [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = None
        for r in range(args.repeats):
            order = ("off", "on") if r % 2 == 0 else ("on", "off")  # alternate, so drifting load hits both
            for mode in order:
                path = tmp / f"run{r}.rrd" if mode == "on" else None
                t, size, t_end, scene, cpu = one_run(args.element, args.cells, args.duration, args.warmup, path)
                (on if mode == "on" else off).append(t)
                (cpu_on if mode == "on" else cpu_off).append(cpu)
                if mode == "on":
                    sizes.append(size / t_end)
                print(f"  repeat {r} {mode:>3}: median {1e3 * np.median(t):7.2f} ms/step, "
                      f"mean {1e3 * t.mean():7.2f} ms/step, CPU {1e3 * cpu:7.2f} ms/step" + (f", {size / 1e6:.2f} MB" if size else ""),
                      file=sys.stderr)
        t10, size10, t_end10, _, cpu10 = one_run(args.element, args.cells, args.duration, args.warmup,
                                          tmp / "every10.rrd", every=10)

    m_off = statistics.median(float(np.median(t)) for t in off)
    m_on = statistics.median(float(np.median(t)) for t in on)
    a_off = statistics.median(float(t.mean()) for t in off)
    a_on = statistics.median(float(t.mean()) for t in on)
    body, steps_per_s = scene.body, 1.0 / scene.world.dt
    print(f"\nsheet-on-sphere {args.element} cells {tuple(args.cells)}: {body.mesh.n_elements} elements, "
          f"{body.mesh.n_nodes} nodes, {len(np.unique(body.mesh.surface_triangles()))} surface vertices; "
          f"{args.repeats} repeats x {args.duration} s simulated ({steps_per_s:.0f} steps/s), "
          f"{args.warmup} warm-up steps left out")
    c_off, c_on = statistics.median(cpu_off), statistics.median(cpu_on)
    print(f"{'':28}{'median ms/step':>16}{'mean ms/step':>14}{'CPU ms/step':>13}")
    print(f"{'without recording':28}{1e3 * m_off:16.2f}{1e3 * a_off:14.2f}{1e3 * c_off:13.2f}")
    print(f"{'recording every step':28}{1e3 * m_on:16.2f}{1e3 * a_on:14.2f}{1e3 * c_on:13.2f}")
    print(f"{'overhead':28}{100 * (m_on - m_off) / m_off:15.1f}%{100 * (a_on - a_off) / a_off:13.1f}%"
          f"{100 * (c_on - c_off) / c_off:12.1f}%")
    print(f"{'recording every 10th step':28}{1e3 * float(np.median(t10)):16.2f}{1e3 * float(t10.mean()):14.2f}"
          f"{1e3 * cpu10:13.2f}")
    print("(wall times depend on the machine's load; CPU time counts every thread of this process only)")
    print(f"file size per simulated second: {statistics.median(sizes) / 1e6:.2f} MB/s (every step), "
          f"{size10 / t_end10 / 1e6:.3f} MB/s (every 10th step)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
