"""A worked experiment: a soft ball launched down an incline, swept over launch speed and friction.

    python examples/friction_sweep.py [--out DIR] [--workers N] [--figure PNG] [--quick]

This file is also the sweep's scene file: it defines ``scene(**params)`` (returning the World),
``monitor(world)`` (the distance the ball's centre travelled down the slope [m]) and ``metrics(world)``
(extra columns), so the same experiment runs from the command line:

    softbody sweep examples/friction_sweep.py --param speed=0.5,1,2 --param friction=0,0.05,0.1,0.2,0.5

A rigid ball on an incline of angle theta rolls without slipping when mu >= (2/7) tan(theta) (0.104 at 20
degrees): it then accelerates at (5/7) g sin(theta) whatever mu is; below that it slides, accelerating at
g (sin(theta) - mu cos(theta)) while it spins up. A ball launched sliding (no spin) slips until friction has
spun it up, sooner on a rougher slope. The sweep measures this on the soft ball (tet10, E = 0.2 MPa):
distance down the slope, the rolling fraction (|omega| r / |v| at the end: 1 rolling, 0 sliding), the slip
the sweep measures at the contacts, and the largest force on the incline. docs/sweeps.md shows the figure.
"""
from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

import numpy as np

import softbody as sb
from integration import World

ANGLE = 20.0  # incline [deg]
RADIUS = 0.05  # ball [m]
DURATION = 0.6  # default run length [s]


def _frame(angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The incline's outward normal and its down-slope direction (unit (3,) each); it descends towards +x."""
    a = math.radians(angle_deg)
    return np.array([math.sin(a), 0.0, math.cos(a)]), np.array([math.cos(a), 0.0, -math.sin(a)])


def scene(speed: float = 1.0, friction: float = 0.3, angle: float = ANGLE, element: str = "tet10", cells: int = 2,
          E: float = 2e5, nu: float = 0.3, density: float = 1000.0, dt: float = 0.005, scheme: str = "warped") -> World:
    """The ball (radius 5 cm, ``cells`` per axis of ball_mesh) 2 mm above an incline of ``angle`` [deg],
    launched down the slope at ``speed`` [m/s] without spin."""
    normal, down = _frame(angle)
    mesh = sb.ball_mesh(RADIUS, cells, element, center=(RADIUS + 0.002) * normal)
    body = sb.FemBody(mesh, sb.LinearElastic(E, nu, density), damping=(0.0, 0.002))  # no mass-proportional damping: it would drag the free ball
    body.velocities = np.tile(speed * down, (mesh.n_nodes, 1))
    world = World(dt=dt, scheme=scheme)
    world.add_plane(normal=normal, name="incline")
    world.add_soft(body, friction=friction)
    world.angle = angle  # for monitor() and metrics()
    world.start = body.positions.mean(axis=0)
    return world


def _centre(world: World) -> tuple[np.ndarray, np.ndarray]:
    body = world.bodies[0]
    return body.positions.mean(axis=0), body.velocities.mean(axis=0)


def monitor(world: World) -> float:
    """Distance the ball's centre travelled down the slope [m]. Called after every step (and once before the
    first), it also sums the impulses of the contact force on the incline, normal and tangential, for
    metrics()."""
    normal = _frame(world.angle)[0]
    if world.t > 0:
        incline = next(rb for rb in world.rigids.values() if rb.name == "incline")
        f = world.contact_force(incline.id)
        fn = float(f @ normal)
        world.impulse = getattr(world, "impulse", np.zeros(2)) + world.dt * np.array(
            [abs(fn), float(np.linalg.norm(f - fn * normal))])
    return float((_centre(world)[0] - world.start) @ _frame(world.angle)[1])


def metrics(world: World) -> dict:
    """speed_end_m_s: the centre's speed at the end; rolling: |omega| r / |v| at the end (omega fitted to the
    nodes' velocities about the centre: 1 rolling without slipping, 0 sliding without spin); friction_ratio:
    the tangential over the normal impulse of the contact force on the incline over the run (Coulomb's law
    bounds it by mu, the contacts all sharing the incline's normal)."""
    body = world.bodies[0]
    c, v = _centre(world)
    r = body.positions - c
    rel = body.velocities - v
    # rel_i = omega x r_i = -[r_i]x omega: least squares over the nodes
    skew = np.zeros((len(r), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    skew -= skew.transpose(0, 2, 1)
    omega = np.linalg.lstsq(-skew.reshape(-1, 3), rel.ravel(), rcond=None)[0]
    speed = float(np.linalg.norm(v))
    normal_impulse, tangential_impulse = getattr(world, "impulse", np.zeros(2))
    return {"speed_end_m_s": speed, "rolling": float(np.linalg.norm(omega)) * RADIUS / speed if speed > 1e-9 else 0.0,
            "friction_ratio": tangential_impulse / normal_impulse if normal_impulse > 0 else 0.0}


def figure(result, path: Path) -> Path:
    """distance, rolling fraction and slip against friction, one line per launch speed, with the rigid ball's
    rolling threshold."""
    from matplotlib.figure import Figure

    rows = [r for r in result.rows if r["status"] == "ok"]
    speeds = sorted({float(r["speed"]) for r in rows})
    mu_star = 2 / 7 * math.tan(math.radians(ANGLE))
    fig = Figure(figsize=(15.0, 3.9), dpi=110, layout="constrained")
    axes = fig.subplots(1, 4)
    cols = [("monitor_end", "distance down the slope [m]"), ("rolling", "rolling fraction |omega| r / |v| at the end"),
            ("slip_mm", "slip at the contacts [mm]"), ("friction_ratio", "tangential / normal impulse on the incline")]
    for ax, (col, title) in zip(axes, cols):
        for s in speeds:
            sel = sorted((r for r in rows if float(r["speed"]) == s), key=lambda r: float(r["friction"]))
            ax.plot([float(r["friction"]) for r in sel], [r[col] for r in sel], marker="o", label=f"launched at {s:g} m/s")
        ax.axvline(mu_star, color="k", ls=":", lw=1)
        ax.set_xlabel("friction coefficient mu")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    mus = sorted({float(r["friction"]) for r in rows})
    axes[3].plot(mus, mus, "k--", lw=1, label="Coulomb's bound: mu")
    axes[0].legend(fontsize=8)
    axes[3].legend(fontsize=8)
    axes[1].text(mu_star, 0.05, " rigid ball rolls\n from mu = 2/7 tan(20 deg)", fontsize=8)
    fig.suptitle(f"Soft ball (r 5 cm, tet10, E 0.2 MPa) launched down a {ANGLE:g} deg incline: "
                 f"{result.points[0].times[-1]:.2g} s later")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def main(argv=None) -> int:
    from experiments import run_sweep
    from experiments.cli import plain_text

    parser = argparse.ArgumentParser(description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="sweeps/friction_sweep", help="sweep directory (cache, CSV, plots)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes (default 1)")
    parser.add_argument("--figure", default=None, metavar="PNG", help="also copy the figure here (docs/img/...)")
    parser.add_argument("--quick", action="store_true", help="2 speeds x 3 frictions, 0.3 s")
    args = parser.parse_args(argv)
    grid = ({"speed": [0.5, 2.0], "friction": [0.0, 0.1, 0.5]} if args.quick else
            {"speed": [0.5, 1.0, 2.0], "friction": [0.0, 0.05, 0.1, 0.2, 0.5]})
    result = run_sweep(__file__, grid, args.out, duration=0.3 if args.quick else None, workers=args.workers)
    print("| speed [m/s] | mu | status | distance [m] | rolling | slip [mm] | speed at end [m/s] | max force on incline [N] "
          "| Ft/Fn impulse | ms/step |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in result.rows:
        num = lambda k: f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k])  # noqa: E731
        print(f"| {r['speed']} | {r['friction']} | {r['status']} | {num('monitor_end')} | {num('rolling')} | "
              f"{num('slip_mm')} | {num('speed_end_m_s')} | {num('max_force_N[incline]')} | {num('friction_ratio')} | {num('ms_per_step')} |")
    path = figure(result, Path(args.out) / "friction_sweep.png")
    print(f"# figure: {path}; all of the sweep in {args.out}/ (results.csv, summary.md, plots/)")
    if args.figure:
        shutil.copyfile(path, args.figure)
        print(f"# copied to {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
