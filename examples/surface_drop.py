"""A soft body from a triangle surface: pybullet_data's Stanford bunny, tetrahedralized and dropped on a plane.

    python examples/surface_drop.py [--model bunny.obj] [--scale 0.1] [--size 0.01] [--kind tet10] [--record]

The model (a file of pybullet_data, or any STL/OBJ/PLY path) is scaled to metres, filled with tets by
softbody.tetrahedralize (gmsh: pip install "softbody[mesh]") at the target edge length ``size``, and dropped
from 5 cm onto a plane. Prints the mesh, its volume against the surface's, and the drop.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    import pybullet_data
    import trimesh

    import softbody as sb
    from experiments.cli import plain_text
    from integration import World

    parser = argparse.ArgumentParser(description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="bunny.obj", help="a file of pybullet_data, or a path")
    parser.add_argument("--scale", type=float, default=0.1, help="model units to metres (bunny.obj: 0.1 -> 20 cm)")
    parser.add_argument("--size", type=float, default=0.02, help="target edge length [m] (0.01: -0.8%% volume, 8533 nodes, 0.24 s per step)")
    parser.add_argument("--kind", choices=("tet4", "tet10"), default="tet10")
    parser.add_argument("--duration", type=float, default=1.0, help="simulated time [s]")
    parser.add_argument("--record", action="store_true", help="write a rerun recording into logs/")
    args = parser.parse_args(argv)

    path = Path(args.model)
    if not path.exists():
        path = Path(pybullet_data.getDataPath()) / args.model
    surface = trimesh.load(str(path), force="mesh", process=False)
    surface = trimesh.Trimesh(np.asarray(surface.vertices) * args.scale, surface.faces)  # metres; seams merged
    tic = time.perf_counter()
    mesh = sb.tetrahedralize(surface, args.size, args.kind)
    print(f"# {path.name}: {len(surface.faces)} triangles, {np.ptp(surface.vertices, axis=0).round(3).tolist()} m; "
          f"{mesh} in {time.perf_counter() - tic:.1f} s; volume {1e6 * mesh.volume():.1f} cm^3, the surface's "
          f"{1e6 * surface.volume:.1f} cm^3 ({100 * (mesh.volume() / surface.volume - 1):+.1f}%)")
    mesh = mesh.translated((0.0, 0.0, 0.05 - mesh.nodes[:, 2].min()))
    body = sb.FemBody(mesh, sb.LinearElastic(1e5, 0.3, 500), damping=(0.0, 0.005))
    world = World(dt=0.005)
    floor = world.add_plane(name="floor")
    world.add_soft(body, friction=0.5)
    recorder = None
    if args.record:
        from integration import Recorder

        recorder = Recorder.attach(world)
    lowest, force, ms = [], [], []

    def callback(w) -> None:
        lowest.append(float(body.positions[:, 2].min()))
        force.append(float(-w.contact_force(floor)[2]))
        ms.append(w.timings["total"])
        if recorder is not None:
            recorder(w)

    try:
        world.run(args.duration, callback, progress=True)
    finally:
        if recorder is not None:
            recorder.close()
            print(f"# recording: {recorder.path}")
    weight = float(body.mass_matrix().sum() / 3 * 9.81)
    touch = next((i for i, z in enumerate(lowest) if z < 1e-3), None)
    print(f"# dropped 5 cm: first touch at t = {(touch + 1) * world.dt if touch is not None else float('nan'):.3f} s "
          f"(free fall: {np.sqrt(2 * 0.05 / 9.81):.3f} s), largest force on the floor {max(force):.1f} N, at the end "
          f"{force[-1]:.2f} N against its weight {weight:.2f} N; max penetration {1e3 * world.max_penetration():.3f} mm; "
          f"{1e3 * float(np.median(ms)):.1f} ms per step")
    world.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
