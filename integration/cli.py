"""The ``softbody`` command line: run canonical scenes (study, recommend and bench build on it)."""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Sequence

import numpy as np

from softbody.elements import ELEMENT_TYPES
from softbody.errors import InvalidInputError

from .scenes import SCENES, Scene, build_scene


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return v


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def add_scene_arguments(parser: argparse.ArgumentParser, scene: str | None = None) -> None:
    """Flags shared by ``softbody run`` and the example scripts."""
    if scene is None:
        parser.add_argument("scene", help=f"scene name: {', '.join(sorted(SCENES))}")
    parser.add_argument("--element", choices=sorted(ELEMENT_TYPES), default=None,
                        help="element type (default: the scene's, tet10)")
    parser.add_argument("--cells", type=_positive_int, nargs=3, metavar=("NX", "NY", "NZ"), default=None,
                        help="grid cells (for the tube: n_theta n_r n_z)")
    parser.add_argument("--duration", type=_positive_float, default=None, help="simulated time [s] (default: the scene's)")
    parser.add_argument("--dt", type=_positive_float, default=None, help="time step [s] (default 0.01)")
    parser.add_argument("--record", nargs="?", const="", default=None, metavar="PATH",
                        help="write a rerun recording (default path: logs/<scene>_<element>_<cells>_<time>.rrd)")
    parser.add_argument("--record-every", type=_positive_int, default=1, metavar="K", help="record every K-th step")
    parser.add_argument("--print-every", type=_positive_float, default=0.1, metavar="S",
                        help="print the monitored node every S simulated seconds")
    parser.add_argument("--progress", action="store_true", help="show a progress bar instead of the trajectory")


def run_scene(args: argparse.Namespace, scene_name: str) -> Scene:
    """Build the scene from parsed flags, run it (recording on request) and print its trajectory."""
    scene = build_scene(scene_name, element=args.element, cells=args.cells, dt=args.dt)
    duration = args.duration if args.duration is not None else scene.duration
    axis = "xyz"[scene.axis]
    body = scene.body
    print(f"# {scene.name}: {body.mesh.kind} cells {scene.meta['cells']}, {body.mesh.n_elements} elements, "
          f"{body.mesh.n_nodes} nodes, dt {scene.world.dt} s, {duration} s")
    print(f"# monitored node {scene.monitor} (rest {np.round(body.rest[scene.monitor], 4).tolist()}), coordinate {axis}")
    recorder = None
    if args.record is not None:
        from .recording import Recorder

        recorder = Recorder.attach(scene, path=args.record or None, every=args.record_every)
    every = max(1, int(round(args.print_every / scene.world.dt)))
    step_times: list[float] = []
    max_contacts = 0
    if not args.progress:
        print(f"{'t [s]':>8} {axis + ' [m]':>10} {'contacts':>8} {'ms/step':>8}")

    def callback(world):
        nonlocal max_contacts
        step_times.append(sum(world.timings.values()))
        active = sum(int(r.active.sum()) for _, r in world.contact_results.values())
        max_contacts = max(max_contacts, active)
        if recorder is not None:
            recorder(world)
        n = int(round(world.t / world.dt))
        if not args.progress and n % every == 0:
            print(f"{world.t:8.3f} {scene.monitored():10.5f} {active:8d} {1e3 * step_times[-1]:8.1f}", flush=True)

    try:
        scene.world.run(duration, callback, progress=args.progress)
    finally:
        if recorder is not None:
            recorder.close()
            print(f"# recording: {recorder.path}  (open it with: rerun {recorder.path})")
    if step_times:
        print(f"# {len(step_times)} steps, median {1e3 * float(np.median(step_times)):.1f} ms/step, "
              f"max active contacts {max_contacts}, max penetration {1e3 * scene.world.max_penetration():.3f} mm")
    return scene


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="softbody", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a canonical scene and print the monitored node")
    add_scene_arguments(run)
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            run_scene(args, args.scene)
    except InvalidInputError as exc:
        parser.exit(2, f"softbody: error: {exc}\n")
    except KeyboardInterrupt:
        print("\n# interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
