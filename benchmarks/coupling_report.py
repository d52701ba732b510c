"""The two-way coupling's figures (docs/coupling.md): rigid boxes on a soft block against the static FEM
solution, a hinged rod with a soft block against the compound pendulum and statics, and the robot grasp.

    python benchmarks/coupling_report.py [--quick]

The scenes and the static reference are those of tests/test_plugin.py (imported from there).
"""

import os
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)
import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import pybullet as p

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "examples"), str(ROOT)]

import softbody as sb  # noqa: E402
from integration import World  # noqa: E402
from test_plugin import HALF, _hinged_rod, static_box_on_block  # noqa: E402


def box_on_block(mass: float, dt: float, offset: float) -> dict:
    world = World(dt=dt)
    world.add_plane()
    block = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=(0, 0, 0.05)),
                       sb.LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
    world.add_soft(block, friction=0.5)
    box = world.add_box((HALF,) * 3, position=(offset, 0, 0.1 + HALF + 0.001), mass=mass)
    z0 = box.pose()[0][2]
    energies, highest, tic = [world.energy()["total"]], z0, time.perf_counter()
    steps = int(round(2.0 / dt))
    for _ in range(steps):
        world.step()
        energies.append(world.energy()["total"])
        highest = max(highest, box.pose()[0][2])
    ms = 1e3 * (time.perf_counter() - tic) / steps
    sag = 0.1 - (box.pose()[0][2] - HALF)
    static = static_box_on_block(mass, offset)
    return {"mass": mass, "dt": dt, "offset": offset, "speed": float(np.linalg.norm(box.velocity()[0])),
            "rise_mm": 1e3 * (highest - z0), "sag_mm": 1e3 * sag, "static_mm": 1e3 * static,
            "dE": float(np.max(np.diff(energies))), "ms": ms}


def pendulum(dt: float) -> tuple[float, float, float]:
    """(measured period, compound-pendulum period, bare rod's period) [s]."""
    world = World(dt=dt)
    L, s, m_r, pivot = 0.5, 0.1, 1.0, np.array([0, 0, 1.0])
    rod = _hinged_rod(world, L, mass=m_r, pivot=tuple(pivot))
    mesh = sb.box_mesh((s, s, s), (2, 2, 2), "tet10", center=(0, 0, pivot[2] - L - s / 2))
    block = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), damping=(0.0, 0.0005))
    world.add_soft(block)
    world.attach(block, np.flatnonzero(np.isclose(mesh.nodes[:, 2], pivot[2] - L)), rod, link=0)
    m_b, d = block.total_mass, L + s / 2
    theory = 2 * math.pi * math.sqrt((m_r * L ** 2 / 3 + m_b * s ** 2 / 6 + m_b * d ** 2) / (9.81 * (m_r * L / 2 + m_b * d)))
    theta = math.radians(5)
    p.resetJointState(rod, 0, theta, 0, physicsClientId=world.client)
    R = np.array([[math.cos(theta), 0, math.sin(theta)], [0, 1, 0], [-math.sin(theta), 0, math.cos(theta)]])
    block.positions[:] = (block.positions - pivot) @ R.T + pivot
    angles = []
    for _ in range(int(round(6.0 / dt))):
        world.step()
        angles.append(p.getJointState(rod, 0, physicsClientId=world.client)[0])
    a = np.array(angles)
    t = dt * np.arange(1, len(a) + 1)
    z = np.flatnonzero((a[:-1] > 0) & (a[1:] <= 0))
    crossings = t[z] + dt * a[z] / (a[z] - a[z + 1])
    return float(np.diff(crossings).mean()), theory, 2 * math.pi * math.sqrt(2 * L / (3 * 9.81))


def tilt(offset: float = 0.03) -> tuple[float, float]:
    """(measured rest angle, statics) [deg] of the rod with an off-centre block."""
    world = World(dt=0.01)
    L, s, m_r, pivot = 0.5, 0.1, 1.0, np.array([0, 0, 1.0])
    rod = _hinged_rod(world, L, mass=m_r, pivot=tuple(pivot))
    mesh = sb.box_mesh((s, s, s), (2, 2, 2), "tet10", center=(offset, 0, pivot[2] - L - s / 2))
    block = sb.FemBody(mesh, sb.LinearElastic(1e7, 0.3, 1000.0), damping=(2.0, 0.002))
    world.add_soft(block)
    X = mesh.nodes
    world.attach(block, np.flatnonzero(np.isclose(X[:, 2], pivot[2] - L) & (np.abs(X[:, 0]) <= 0.025 + 1e-9)), rod, link=0)
    world.run(6.0)
    statics = math.atan2(block.total_mass * offset, m_r * L / 2 + block.total_mass * (L + s / 2))
    return math.degrees(p.getJointState(rod, 0, physicsClientId=world.client)[0]), math.degrees(statics)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only dt = 0.01 s for the boxes, no grasp")
    args = ap.parse_args()
    print("| box mass [kg] | dt [s] | placed | speed after 2 s [m/s] | highest rise [mm] | sag [mm] | static FEM [mm] "
          "| sag / static | largest energy increase per step [J] | ms/step |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for mass in (0.1, 0.5, 2.0):
        for dt in ((0.01,) if args.quick else (0.01, 0.002)):
            for offset in (0.0, 0.00625):
                r = box_on_block(mass, dt, offset)
                print(f"| {mass} | {dt} | {'centred' if offset == 0 else 'near edge'} | {r['speed']:.1e} | "
                      f"{r['rise_mm']:.3f} | {r['sag_mm']:.3f} | {r['static_mm']:.3f} | {r['sag_mm'] / r['static_mm']:.3f} "
                      f"| {r['dE']:.1e} | {r['ms']:.1f} |", flush=True)
    for dt in (0.01, 0.002):
        measured, theory, bare = pendulum(dt)
        print(f"pendulum dt {dt}: period {measured:.4f} s, compound pendulum {theory:.4f} s "
              f"({100 * (measured / theory - 1):+.2f}%), bare rod {bare:.4f} s", flush=True)
    measured, statics = tilt()
    print(f"off-centre block: rest angle {measured:.3f} deg, statics {statics:.3f} deg", flush=True)
    if not args.quick:
        import robot_grasp

        robot_grasp.run()
