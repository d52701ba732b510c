"""Energy and momentum: what each scheme keeps of a spin and a pendulum's swing, what a step costs, and whether it
holds at a step of 0.1 s (softbody.schemes).

    python benchmarks/energy_schemes.py --out docs/energy_schemes.md --plot docs/img/energy_schemes.png

Two undamped scenes on the core Simulation (no contact; the schemes "warped", "newton", "bdf2"), over a ladder of
steps h:

- spin: a 0.2 m tet10 cube (2x2x2 cells, E = 1e7 Pa, no gravity) spinning at 5 rev/s about an oblique axis, for
  1 s. Kept: its angular momentum about the centre of mass (L . L0 / |L0|^2, the consistent mass matrix), its
  energy (kinetic + elastic, end over start); the largest relative change of any node-to-node distance.
- pendulum: a 0.5 x 0.04 x 0.04 m tet10 bar (10x1x2 cells, E = 1e9 Pa: within 0.1 deg of rigid) hinged on the
  line of nodes x = 0, z = 0 (about y), released horizontal, for 3 s. The largest difference of the angle of
  its centre of mass from the rigid compound pendulum's (scipy's solve_ivp, rtol 1e-10: the independent
  reference) [deg], and the energy lost [% of m g d, d the hinge to centre distance].

Plus, on the spin only, the two schemes tried and not offered, built here from the public API: the implicit
midpoint rule (a Newton backward Euler step of h/2, then x_{n+1} = 2 x_{n+1/2} - x_n, v_{n+1} = 2 v_m - v_n)
and the trapezoidal rule (a half step x_n + h/2 v_n, then a Newton backward Euler step of h/2 under the start's
elastic forces as a load). A run that raises is reported as such. Median wall time per step, one thread.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from pathlib import Path

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "1")
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import softbody as sb  # noqa: E402

LADDER = (0.005, 0.01, 0.02, 0.05, 0.1)
SCHEMES = ("warped", "newton", "bdf2")
NOT_OFFERED = ("midpoint", "trapezoidal")
SPIN_REV, SPIN_E, SPIN_T = 5.0, 1e7, 1.0
BAR = (0.5, 0.04, 0.04)
BAR_E, PENDULUM_T = 1e9, 3.0


# ------------------------------------------------------------------ scenes
def spin_body() -> sb.FemBody:
    mesh = sb.box_mesh((0.2, 0.2, 0.2), (2, 2, 2), "tet10")
    body = sb.FemBody(mesh, sb.LinearElastic(SPIN_E, 0.33, 1000.0), damping=(0.0, 0.0))
    axis = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    body.velocities[:] = np.cross(2 * math.pi * SPIN_REV * axis, mesh.nodes)
    return body


def pendulum_body() -> sb.FemBody:
    mesh = sb.box_mesh(BAR, (10, 1, 2), "tet10", center=(BAR[0] / 2, 0.0, 0.0))
    body = sb.FemBody(mesh, sb.LinearElastic(BAR_E, 0.33, 1000.0), damping=(0.0, 0.0))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0) & np.isclose(mesh.nodes[:, 2], 0.0)))
    return body


def angular_momentum(body: sb.FemBody) -> np.ndarray:
    c = body.node_mass @ body.positions / body.node_mass.sum()
    return np.cross(body.positions - c, body.mass_product(body.velocities)).sum(axis=0)


def energy(body: sb.FemBody, g: np.ndarray) -> float:
    """Kinetic + elastic + gravitational energy [J]."""
    return body.kinetic_energy() + body.elastic_energy() + body.gravitational_energy(g)


def angle(body: sb.FemBody) -> float:
    """The angle of the bar's centre of mass below the horizontal through the hinge [rad]."""
    c = body.node_mass @ body.positions / body.node_mass.sum()
    return math.atan2(-c[2], c[0])


def rigid_pendulum(times: np.ndarray) -> np.ndarray:
    """The rigid compound pendulum's angle [rad] at ``times``: I theta'' = m g d cos(theta) from rest at 0."""
    from scipy.integrate import solve_ivp

    L, _, a = BAR
    d = L / 2
    inertia = (L * L + a * a) / 12 + d * d  # per unit mass, about the hinge (y)
    sol = solve_ivp(lambda t, y: (y[1], 9.81 * d * math.cos(y[0]) / inertia), (0.0, float(times[-1])), (0.0, 0.0),
                    t_eval=times, rtol=1e-10, atol=1e-12)
    return sol.y[0]


# ------------------------------------------------------------------ stepping
class Reference:
    """The implicit midpoint and trapezoidal rules from the public API (module doc): per step one Newton backward
    Euler step of h/2, then an extrapolation (midpoint), or after a half explicit step (trapezoidal)."""

    def __init__(self, body: sb.FemBody, dt: float, rule: str, gravity):
        self.body, self.dt, self.rule = body, dt, rule
        self.half = sb.Simulation(body, dt / 2, gravity=gravity, scheme="newton")

    def step(self) -> None:
        b, h = self.body, self.dt
        x0, v0 = b.positions.copy(), b.velocities.copy()
        if self.rule == "midpoint":
            self.half.step()  # x_n + h/2 v_m, v_m
            b.positions, b.velocities = 2.0 * b.positions - x0, 2.0 * b.velocities - v0
        else:
            self.half.external_forces[b] = b.node_mass[:, None] * self.half.gravity - b.energy_gradient(x0)  # f(x_n)
            b.positions = x0 + 0.5 * h * v0
            self.half.step()  # M (u - v_n) = h/2 (f_n + f(x_n + h/2 v_n + h/2 u))


def run_spin(scheme: str, dt: float) -> dict:
    body = spin_body()
    g = np.zeros(3)
    stepper = (Reference(body, dt, scheme, g) if scheme in NOT_OFFERED
               else sb.Simulation(body, dt, gravity=g, scheme=scheme))
    L0, e0 = angular_momentum(body), energy(body, g)
    pairs = np.triu_indices(body.n_nodes, 1)
    d0 = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)[pairs]
    ms, shape, failed = [], 0.0, ""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the warped step's LinearisationWarning: its distortion is a column here
        try:
            for _ in range(int(round(SPIN_T / dt))):
                tic = time.perf_counter()
                stepper.step()
                ms.append(1e3 * (time.perf_counter() - tic))
                d = np.linalg.norm(body.positions[:, None] - body.positions[None], axis=2)[pairs]
                shape = max(shape, float(np.abs(d / d0 - 1).max()))
        except sb.SimulationDiverged as exc:
            failed = str(exc).split(":")[0]
    L = angular_momentum(body)
    return {"ms": float(np.median(ms)) if ms else math.nan, "failed": failed,
            "L": float(L @ L0 / (L0 @ L0)), "energy": energy(body, g) / e0, "shape": shape,
            "finite": bool(np.isfinite(body.positions).all())}


def run_pendulum(scheme: str, dt: float) -> dict:
    body = pendulum_body()
    g = np.array([0.0, 0.0, -9.81])
    sim = sb.Simulation(body, dt, gravity=g, scheme=scheme)
    mass = body.node_mass.sum()
    e0 = energy(body, g)
    times, angles, ms, failed = [0.0], [angle(body)], [], ""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            for n in range(int(round(PENDULUM_T / dt))):
                tic = time.perf_counter()
                sim.step()
                ms.append(1e3 * (time.perf_counter() - tic))
                times.append((n + 1) * dt)
                angles.append(angle(body))
        except sb.SimulationDiverged as exc:
            failed = str(exc).split(":")[0]
    ref = rigid_pendulum(np.array(times))
    return {"ms": float(np.median(ms)) if ms else math.nan, "failed": failed,
            "angle": math.degrees(float(np.abs(np.unwrap(angles) - ref).max())),
            "lost": 100 * (e0 - energy(body, g)) / (mass * 9.81 * BAR[0] / 2),
            "finite": bool(np.isfinite(body.positions).all())}


HEADER = """# Energy and momentum: the three schemes

Generated by `python benchmarks/energy_schemes.py --out docs/energy_schemes.md --plot docs/img/energy_schemes.png`
(one thread, a shared 2-core machine; the scenes and columns are described in the script's docstring). No
damping anywhere: what is lost is the scheme's own numerical damping. The damping a body is given (Rayleigh,
`FemBody(damping=...)`) spares rigid motion in every scheme: a spin and a free fall lose nothing to it
(tests/test_damping.py).

How to read it:

- **newton** (backward Euler): keeps the spinning cube's shape, but loses most of the spin (22 % of the angular
  momentum left after 1 s at h = 0.01 s) and of the pendulum's swing (75 % of its energy gone in 3 s): its
  numerical damping falls only as h does.
- **bdf2** (second order, `Simulation(..., scheme="bdf2")`): the same shape, the same cost per step (a Newton
  backward Euler step of 2h/3 from a combination of the two last states: 2-3 iterations), and it keeps the motion
  far better: 76 % of the spin and 98 % of the swing's energy at h = 0.01 s, 93 % and 99.7 % at 0.005 s. It still
  damps what a step cannot resolve: at h = 0.1 s, where the cube turns 3.1 rad a step, every scheme loses most of
  the spin, and none gains energy (stable).
- **warped** (the default): the cheapest, and its momentum is exact (its rotations are frozen over the step), but
  it does not keep the energy: the spinning cube stretches by 1-230 % and gains 2-5000 times its energy, and the
  swinging stiff bar swings at the right angle (1-3 deg off at h <= 0.02 s) while its own vibration gains several
  times the swing's energy (the linearised rotation of each step pumps it; Rayleigh damping takes it out only in
  part). Its LinearisationWarning names both: the spin's angle per step, and the stiff bar's small one (0.05 rad) that
  still leaves it a stretch holding more than 5 % of its kinetic energy.
- **midpoint** and **trapezoidal**, the two schemes that keep a linear body's energy exactly, tried here and not
  offered: on the spinning warped body they swap energy in and out of a spurious stretch every other step until
  their Newton iterations fail, within 0.4 s at every step tried.

World refuses "bdf2": its coupled contact solve is a backward Euler solve over dt. BDF2 across the stability
matrix (960 cases, dt up to 0.1 s): none unstable, docs/stability_bdf2.md.

![spin and pendulum kept against h](img/energy_schemes.png)"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/energy_schemes.md")
    ap.add_argument("--plot", default="docs/img/energy_schemes.png")
    args = ap.parse_args(argv)
    spin, pend = {}, {}
    for scheme in SCHEMES + NOT_OFFERED:
        for dt in LADDER:
            if scheme in NOT_OFFERED and dt not in (0.005, 0.01, 0.02):
                continue
            spin[scheme, dt] = run_spin(scheme, dt)
            print("spin", scheme, dt, spin[scheme, dt], flush=True)
    for scheme in SCHEMES:
        for dt in LADDER:
            pend[scheme, dt] = run_pendulum(scheme, dt)
            print("pendulum", scheme, dt, pend[scheme, dt], flush=True)

    def failed(r: dict) -> str:
        return f"failed: {r['failed']}" if r["failed"] else ""

    lines = [HEADER, "", f"## Spin: tet10 cube at {SPIN_REV:g} rev/s, E = {SPIN_E:g} Pa, {SPIN_T:g} s", "",
             "| scheme | h [s] | ms/step | angular momentum kept | energy kept | largest shape change |",
             "|---|---:|---:|---:|---:|---:|"]
    for (scheme, dt), r in spin.items():
        if r["failed"]:
            lines.append(f"| {scheme} | {dt:g} | {r['ms']:.1f} | {failed(r)} | | |")
        else:
            lines.append(f"| {scheme} | {dt:g} | {r['ms']:.1f} | {r['L']:.4f} | {r['energy']:.4f} | "
                         f"{100 * r['shape']:.2f}% |")
    lines += ["", f"## Pendulum: tet10 bar hinged at one end, released horizontal, {PENDULUM_T:g} s", "",
              "| scheme | h [s] | ms/step | largest angle error [deg] | energy lost [% of m g d] |",
              "|---|---:|---:|---:|---:|"]
    for (scheme, dt), r in pend.items():
        if r["failed"]:
            lines.append(f"| {scheme} | {dt:g} | {r['ms']:.1f} | {failed(r)} | |")
        else:
            lines.append(f"| {scheme} | {dt:g} | {r['ms']:.1f} | {r['angle']:.3g} | {r['lost']:.3g} |")
    Path(args.out).write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8))
    styles = {"warped": "o-", "newton": "s--", "bdf2": "^-", "midpoint": "x:", "trapezoidal": "+:"}
    for scheme in SCHEMES + NOT_OFFERED:
        pts = [(dt, r["L"]) for (s, dt), r in spin.items() if s == scheme and not r["failed"]]
        if pts:
            axes[0].semilogx(*zip(*pts), styles[scheme], label=scheme)
        pts = [(dt, r["angle"]) for (s, dt), r in pend.items() if s == scheme and not r["failed"]]
        if pts:
            axes[1].loglog(*zip(*pts), styles[scheme], label=scheme)
    axes[0].set(xlabel="h [s]", ylabel="angular momentum kept after 1 s", title=f"spin, {SPIN_REV:g} rev/s")
    axes[1].set(xlabel="h [s]", ylabel="largest angle error [deg]", title="pendulum against the rigid one")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=110)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
