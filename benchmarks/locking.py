"""Volumetric locking: a cantilever's static tip deflection against beam theory as the Poisson ratio nears 0.5.

    python benchmarks/locking.py [--nu 0.3 0.45 0.49 0.499 0.4999]

The cantilever of docs/method.md section 5 (1 x 0.1 x 0.1 m, clamped at x = 0, its own weight, E = 5e7 Pa, 1000
kg/m^3), solved statically (softbody.solve_static) for each element and mesh: structured boxes (box_mesh) and, for
tet4, the box tetrahedralized by softbody.tetrahedralize (unstructured). Printed: a markdown table of the tip
deflection over the reference's, the finest tet10 mesh (40 x 4 x 4, quadratic elements lock little), and a last row
with that reference over Timoshenko's beam value q L^4 / (8 E I) + q L^2 / (2 kappa G A) (kappa = 5/6, G = E / (2 (1
+ nu))), the independent check of the reference (the clamped root, which the beam does not model, stiffens the
nearly incompressible beam a little). A locking element's ratio falls as nu nears 0.5. The table of
docs/materials.md is this script's output.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

os.environ.setdefault("SOFTBODY_COMPILE", "now")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import softbody as sb  # noqa: E402

E, RHO, L, B = 5.0e7, 1000.0, 1.0, 0.1
MESHES = [("hex8", (20, 2, 2), "full"), ("hex8", (40, 4, 4), "full"), ("hex8", (20, 2, 2), "mean"),
          ("hex8", (40, 4, 4), "mean"), ("tet4", (20, 2, 2), "full"), ("tet4", (40, 4, 4), "full"),
          ("tet4", "tetrahedralized", "full"), ("tet10", (10, 1, 1), "full"), ("tet10", (20, 2, 2), "full")]


def timoshenko(nu: float) -> float:
    """The beam's tip deflection [m] under its own weight (Timoshenko: bending and shear)."""
    q, inertia, area = RHO * 9.81 * B * B, B**4 / 12, B * B
    G = E / (2 * (1 + nu))
    return q * L**4 / (8 * E * inertia) + q * L**2 / (2 * 5 / 6 * G * area)


def mesh_of(kind: str, cells) -> sb.Mesh:
    if cells == "tetrahedralized":
        import trimesh

        box = trimesh.creation.box((L, B, B))
        box.apply_translation((L / 2, 0, 0))
        return sb.tetrahedralize(box, B / 4)
    return sb.box_mesh((L, B, B), cells, kind, center=(L / 2, 0, 0))


def tip(mesh: sb.Mesh, nu: float, volumetric: str = "full") -> float:
    """The cantilever's tip deflection [m] (positive down); volumetric: FemBody's ("mean": B-bar, hex8)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the locking warning: measured here
        body = sb.FemBody(mesh, sb.LinearElastic(E, nu, RHO), volumetric=volumetric)
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    u = sb.solve_static(body)
    end = np.isclose(mesh.nodes[:, 0], L)
    return -float(u[end, 2].mean())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.45, 0.49, 0.499, 0.4999])
    args = parser.parse_args(argv)
    print("| element | mesh | volumetric | nodes | " + " | ".join(f"nu {nu:g}" for nu in args.nu) + " |")
    print("|---|---|---|---:|" + "---:|" * len(args.nu))
    reference = mesh_of("tet10", (40, 4, 4))
    ref = [tip(reference, nu) for nu in args.nu]
    for kind, cells, volumetric in MESHES:
        mesh = mesh_of(kind, cells)
        ratios = [tip(mesh, nu, volumetric) / r for nu, r in zip(args.nu, ref)]
        label = "tetrahedralized" if cells == "tetrahedralized" else "x".join(map(str, cells))
        print(f"| {kind} | {label} | {volumetric} | {mesh.n_nodes} | " + " | ".join(f"{r:.3f}" for r in ratios)
              + " |", flush=True)
    print(f"| reference / Timoshenko | tet10 40x4x4 | full | {reference.n_nodes} | "
          + " | ".join(f"{r / timoshenko(nu):.3f}" for nu, r in zip(args.nu, ref)) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
