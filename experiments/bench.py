"""``softbody bench``: cost per step of the canonical scenes, as ratios that survive a noisy machine.

For each configuration (scene, element, cells) a fresh process (multiprocessing, "spawn") with the
thread count pinned before numpy loads builds the scene, steps ``warmup`` steps (into contact), then
times ``repeats`` consecutive blocks of ``steps`` steps. Per block: mean wall ms per step (the cost per
simulated second: the mean, not the median, so that occasional refactorisations count) and the mean
of each phase of ``world.timings``; over blocks: the median and the min..max spread. In the same
process, right after the timed blocks:

* the solver floor: one numeric Cholesky refactorisation plus one solve of a step's own system
  matrix A = c_m M + c_k K'(R), with its constraint set (supports and active contacts), by a fresh
  PARDISO (double precision, backend "auto") solver whose symbolic analysis was done beforehand. The
  system is captured from the step right after the warm-up (run untimed), and ``floor_repeats``
  refactorisations + solves of it are timed within every block, one after each of ``floor_repeats``
  equal parts of its steps (outside the timed steps), so that each block has a floor taken over the
  same seconds: ``step / floor`` is the median over blocks of block ms/step / that block's floor
  (median of its repeats), the headline ratio; ``floor_ms`` is the median of the blocks' floors;
* a cProfile of ``profile_steps`` more steps (top-20 table written to ``out_dir/profiles/``), with the
  largest number of calls per step of any function, to show there is no Python loop per element or node;
* the peak RSS of the process over the build, warm-up and timed steps (Linux's VmHWM, restarted
  after each floor timing so that the floor's own solver does not count).

pybullet's own FEM soft body (neo-Hookean, tets only) runs the same sheet-on-sphere scene on the identical
tet4 mesh in another fresh process, with k = 1, 2, 4, ... substeps of h / k per 0.01 s step, over the same
simulated time as ours (``warmup + repeats * steps`` steps). The smallest stable k is reported (finite
positions, no node more than ``max_disp`` from its start, kinetic energy never more than twice the
potential energy released plus a 1 cm drop: a passive damped body cannot gain more); the search goes on
to the smallest k at which the sheet also stays on the sphere (no node more than 0.5 m from its start).
Wall time of the stepSimulation calls only (positions are read back outside the timed region). In the
same process a fresh build of our scene takes its warm-up after pybullet's and then one block of
``steps`` steps after each of pybullet's timed blocks: ``ours / pybullet`` is the median over these
block pairs of our ms/step over pybullet's ms per 0.01 s, taken seconds apart like step/floor (our
ms/step from the configuration's own process over pybullet's, minutes apart, is kept as
``ours_over_pybullet_cross_process``, and used if the pairs failed: ``ours_over_pybullet_source``). The
paired steps are ``world.step()`` alone (no recorder, even with ``record``). pybullet's process holds
our scene too, so its peak RSS is not pybullet's alone.

``run_bench`` writes ``bench.json``, ``bench.md`` and ``bench.png`` (``scaling.*`` for the scaling ladder, ``large.*`` for
the large bodies):
the plot is ms per step and peak memory against nodes, log-log, with fitted exponents, from every result
in ``out_dir``.
"""
from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable, Sequence

from softbody.linsolve import THREAD_VARS

from integration import quiet_c_output
from .study import _log_axes, environ

# ----------------------------------------------------------------------------------------------- configurations

SHEET = "sheet-on-sphere"

#: the issue's three sizes (paper-converged sheet meshes) plus the 1445-node tet4 mesh for pybullet
DEFAULT_CONFIGS = [(SHEET, "tet4", (16, 16, 4)), (SHEET, "tet4", (24, 24, 6)),
                   (SHEET, "hex8", (20, 20, 5)), (SHEET, "tet10", (9, 9, 2))]
#: the fixed cost of a step (issue 18): small sheets, one small cube on a plane, ten of them in one World
SMALL_CONFIGS = [(SHEET, "tet4", (4, 4, 2)), (SHEET, "tet10", (2, 2, 1)), (SHEET, "tet4", (8, 8, 3)),
                 ("cubes-on-plane", "tet10", (2, 2, 2)), ("ten-cubes-on-plane", "tet10", (2, 2, 2))]
#: a quick check that everything runs (CI)
TINY_CONFIGS = [(SHEET, "tet4", (4, 4, 2))]
#: ms per step against nodes, up to >= 4x the paper's largest sheet mesh (tet4 (26,26,7): 5832 nodes)
SCALING_CONFIGS = [
    (SHEET, "tet4", (8, 8, 3)), (SHEET, "tet4", (16, 16, 4)), (SHEET, "tet4", (24, 24, 6)),
    (SHEET, "tet4", (32, 32, 8)), (SHEET, "tet4", (44, 44, 11)),
    (SHEET, "hex8", (8, 8, 3)), (SHEET, "hex8", (16, 16, 4)), (SHEET, "hex8", (20, 20, 5)),
    (SHEET, "hex8", (32, 32, 8)), (SHEET, "hex8", (44, 44, 11)),
    (SHEET, "tet10", (4, 4, 1)), (SHEET, "tet10", (6, 6, 2)), (SHEET, "tet10", (9, 9, 2)),
    (SHEET, "tet10", (14, 14, 3)), (SHEET, "tet10", (18, 18, 4)), (SHEET, "tet10", (24, 24, 5)),
]
#: large bodies (issue 34): tet4 sheets of 72k, 235k and 549k nodes, through the impact (peak memory per node)
LARGE_CONFIGS = [(SHEET, "tet4", (64, 64, 16)), (SHEET, "tet4", (96, 96, 24)), (SHEET, "tet4", (128, 128, 32))]
#: tet4 meshes that get the pybullet comparison in the default run (1445 and 4375 nodes)
PYBULLET_CELLS = [(16, 16, 4), (24, 24, 6)]

DEFAULTS = dict(steps=50, repeats=3, warmup=20, threads=1)
TINY = dict(steps=5, repeats=2, warmup=12, floor_repeats=3, profile_steps=3, pybullet_max_k=8)
SCALING = dict(steps=10, repeats=1, warmup=15, floor_repeats=3, profile_steps=3)
#: the large ladder: the 12 steps from the sheet's first contact with the sphere (steps 10-21: the impact, its set-ups of
#: the preconditioner among them; a shorter window measured whether one fell in it), no floor (a fresh double-precision
#: factorisation of the 549k-node system needs more memory than the machine has) and no profile
LARGE = dict(steps=12, repeats=1, warmup=9, floor_repeats=0, profile_steps=0)

PHASES = ("collision", "rotations", "forces", "assembly", "factorize", "solve", "contact", "other", "rigid",
          "recording")
SOLVE_PHASES = ("factorize", "solve")


@dataclass(frozen=True)
class Config:
    scene: str
    element: str
    cells: tuple[int, int, int]

    @property
    def label(self) -> str:
        short = {"sheet-on-sphere": "sheet", "hanging-tube": "tube"}.get(self.scene, self.scene)
        return f"{short} {self.element} ({','.join(str(c) for c in self.cells)})"

    @property
    def slug(self) -> str:
        return f"{self.scene}_{self.element}_{'x'.join(str(c) for c in self.cells)}"


def parse_config(item) -> Config:
    """A Config from a Config, a (scene, element, cells) tuple, a dict, or text ``[scene:]element:NXxNYxNZ``."""
    from softbody.errors import InvalidInputError

    if isinstance(item, Config):
        return item
    if isinstance(item, dict):
        item = (item.get("scene", SHEET), item["element"], item["cells"])
    if isinstance(item, str):
        parts = item.split(":")
        if len(parts) == 2:
            parts = [SHEET] + parts
        if len(parts) != 3:
            raise InvalidInputError(f"config {item!r}: expected [scene:]element:NXxNYxNZ, e.g. tet4:24x24x6")
        try:
            cells = tuple(int(c) for c in parts[2].lower().replace(",", "x").split("x"))
        except ValueError:
            raise InvalidInputError(f"config {item!r}: cells must be integers like 24x24x6") from None
        item = (parts[0], parts[1], cells)
    scene, element, cells = item
    cells = tuple(int(c) for c in cells)
    if len(cells) != 3 or min(cells) < 1:
        raise InvalidInputError(f"config {item!r}: cells must be three positive integers")
    from softbody.elements import ELEMENT_TYPES

    from .scenes import SCENES

    if scene not in SCENES:
        raise InvalidInputError(f"config {item!r}: unknown scene {scene!r}; available: {sorted(SCENES)}")
    if element not in ELEMENT_TYPES:
        raise InvalidInputError(f"config {item!r}: unknown element {element!r}; available: {sorted(ELEMENT_TYPES)}")
    return Config(scene, element, cells)


# ----------------------------------------------------------------------------------------------- child processes

def kb_per_node(result: dict) -> float | None:
    """A configuration's peak memory above the imports per node [kB/node] (peak_rss_mb - baseline_rss_mb, in KiB,
    over its nodes): what the body, its solver and the step hold at their peak; None without the figures."""
    peak, base, nodes = result.get("peak_rss_mb"), result.get("baseline_rss_mb"), result.get("nodes")
    if peak is None or base is None or not nodes:
        return None
    return 1024.0 * (peak - base) / nodes


def _rss_mb() -> float:
    """Peak resident set size of this process [MB]: since the last ``_reset_peak_rss`` where Linux's
    VmHWM allows it, else since the start (``ru_maxrss``; Linux reports KiB, macOS bytes)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0


def _reset_peak_rss() -> bool:
    """Restart the peak RSS (VmHWM) from the current RSS (Linux >= 4.0), so that the floor's solver,
    which lives only while it is timed, does not count in the step's peak. False where that fails."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _child(conn, func_name: str, spec: dict, threads: int) -> None:
    """Entry point of a spawned measurement process: pin threads, run ``func_name(spec)``, send the result."""
    try:
        for var in THREAD_VARS:  # already set by the parent before the spawn; kept for direct callers
            os.environ[var] = str(threads)
        import numpy  # noqa: F401  (after the environment is pinned)

        from softbody.linsolve import set_threads

        set_threads(threads)
        result = globals()[func_name](spec)
    except BaseException as exc:  # report, never hang the parent
        import traceback

        result = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    conn.send(result)
    conn.close()


def run_in_fresh_process(func_name: str, spec: dict, threads: int = 1, timeout: float | None = None) -> dict:
    """Run ``func_name(spec)`` of this module in a new 'spawn' process whose OMP/MKL/OPENBLAS thread
    variables are ``threads`` from its start (before numpy is imported). Returns the child's dict, or
    {"error": ...} if it failed, crashed (e.g. a segfault in a C extension) or timed out."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    with environ(**{v: str(threads) for v in THREAD_VARS}):  # set before the child imports numpy
        proc = ctx.Process(target=_child, args=(send, func_name, spec, threads), daemon=True)
        proc.start()
    send.close()
    start = time.monotonic()
    result = None
    while result is None:
        if recv.poll(0.5):
            try:
                result = recv.recv()
            except EOFError:
                result = {"error": f"measurement process exited with code {proc.exitcode} without a result"}
        elif not proc.is_alive():
            proc.join()
            if recv.poll(0.1):
                continue
            result = {"error": f"measurement process exited with code {proc.exitcode} without a result"
                               + (" (a crash: signal %d)" % -proc.exitcode if proc.exitcode and proc.exitcode < 0 else "")}
        elif timeout is not None and time.monotonic() - start > timeout:
            proc.kill()
            result = {"error": f"measurement process timed out after {timeout:.0f} s"}
    proc.join(5)
    return result


# ----------------------------------------------------------------------------------------------- our step

def _median(xs):
    import numpy as np

    return float(np.median(xs)) if len(xs) else float("nan")


def _build(cfg: dict):
    from .scenes import build_scene

    scene = build_scene(cfg["scene"], element=cfg["element"], cells=tuple(cfg["cells"]))
    if cfg.get("method"):
        scene.world.sim.method = cfg["method"]
    return scene


def _count_calls(obj, name: str, counter: list) -> None:
    """Wrap obj.name (an instance attribute) so that each call adds 1 to counter[0]."""
    f = getattr(obj, name)

    def counted(*a, **kw):
        counter[0] += 1
        return f(*a, **kw)

    setattr(obj, name, counted)


def _pcg_counters(sim, body) -> tuple[int, int]:
    """(factorisations, iterations) so far of the body's iterative-path preconditioner in the Simulation ``sim``
    (0, 0 if it has none)."""
    pre = sim.solvers.held_preconditioner(body, sim.solvers.solver(body, sim.solver_backend).backend)
    return (int(getattr(pre, "factorizations", 0)), int(getattr(pre, "iterations", 0))) if pre is not None else (0, 0)


def measure_config(spec: dict) -> dict:
    """One configuration in this process (call it through :func:`run_in_fresh_process`)."""
    import numpy as np

    from . import scenes  # noqa: F401  (pybullet, trimesh: imported before the baseline is read)

    t_start = time.perf_counter()
    baseline = _rss_mb()  # interpreter + numpy/scipy/MKL + pybullet, before the scene exists
    scene = _build(spec)
    world = scene.world
    body = world.stepped(scene.body)  # a scene of several bodies: the stack that steps them (softbody.stack)
    out = {"scene": spec["scene"], "element": spec["element"], "cells": list(spec["cells"]),
           "elements": int(body.mesh.n_elements), "nodes": int(body.n_nodes), "dofs": int(body.n_dofs),
           "threads": spec["threads"], "steps": spec["steps"], "repeats": spec["repeats"], "warmup": spec["warmup"],
           "method_setting": world.sim.method, "baseline_rss_mb": baseline}
    direct_factorizations = [0]
    recorder = None
    if spec.get("record"):
        from integration.recording import Recorder

        rec_dir = Path(spec["out_dir"]) / "recordings"
        rec_dir.mkdir(parents=True, exist_ok=True)
        recorder = Recorder.attach(scene, path=rec_dir / f"{Config(spec['scene'], spec['element'], tuple(spec['cells'])).slug}.rrd",
                                   every=1)

    moved = [0.0]  # largest distance of any node from its rest position so far [m] (outside the timed region)

    def one_step() -> tuple[float, dict, int]:
        tic = time.perf_counter()
        world.step()
        phases = dict(world.timings)
        if recorder is not None:
            t0 = time.perf_counter()
            recorder(world)
            phases["recording"] = time.perf_counter() - t0
        wall = time.perf_counter() - tic
        active = sum(int(r.active.sum()) for _, r in world.contact_results.values())
        moved[0] = max(moved[0], float(np.sqrt(((body.positions - body.rest) ** 2).sum(axis=1)).max()))
        return wall, phases, active

    try:
        for _ in range(spec["warmup"]):
            one_step()
        # the stepped body after the warm-up (bodies that came into contact may have been stacked anew)
        body = world.stepped(scene.body)
        _count_calls(world.sim.solvers.solver(body, world.sim.solver_backend), "factorize", direct_factorizations)
        peak = _rss_mb()  # build and warm-up
        floor = capture_floor(world, body) if spec.get("floor_repeats", 0) > 0 else None
        peak_resets = [_reset_peak_rss()]
        pre_f0, pre_i0 = _pcg_counters(world.sim, body)
        direct0 = direct_factorizations[0]
        blocks = []
        contacts = []
        # the floor's timings are spread over each block: one after each of floor_repeats equal parts
        # of it (outside the timed steps; the state is not touched), so that they sample the machine's
        # speed over the same seconds as the block's steps
        n_floor = spec.get("floor_repeats", 0) if floor is not None else 0
        floor_after = {round((j + 1) * spec["steps"] / n_floor) for j in range(n_floor)} if n_floor else set()
        for _ in range(spec["repeats"]):
            walls, phase_sums, floors = [], {}, []
            for i in range(spec["steps"]):
                wall, phases, active = one_step()
                walls.append(wall)
                contacts.append(active)
                for k, v in phases.items():
                    phase_sums[k] = phase_sums.get(k, 0.0) + v
                if i + 1 in floor_after:
                    peak = max(peak, _rss_mb())
                    floors.append(floor.time(1))
                    peak_resets.append(_reset_peak_rss())
            n = len(walls)
            blocks.append({"ms_per_step": 1e3 * sum(walls) / n,
                           "phases_ms": {k: 1e3 * v / n for k, v in phase_sums.items()}})
            peak = max(peak, _rss_mb())
            if floors:
                blocks[-1]["floor"] = (_median([f for f, _ in floors]), _median([s_ for _, s_ in floors]))
        out["peak_rss_mb"] = peak  # import + build + warm-up + timed steps, without the floor's solver
        out["peak_rss_excludes_floor"] = all(peak_resets)  # else (no VmHWM reset) it includes it
        n_timed = spec["steps"] * spec["repeats"]
        pre_f1, pre_i1 = _pcg_counters(world.sim, body)
        pcg_factorizations, pcg_iterations = pre_f1 - pre_f0, pre_i1 - pre_i0
        iterative = pcg_factorizations > 0 or pcg_iterations > 0
        out["method"] = "iterative" if iterative else "direct"
        out["factorizations_per_step"] = (direct_factorizations[0] - direct0 + pcg_factorizations) / n_timed
        out["pcg_iterations_per_step"] = pcg_iterations / n_timed if iterative else None
        per_block = [b["ms_per_step"] for b in blocks]
        out["ms_per_step"] = _median(per_block)
        out["ms_per_step_min"] = float(min(per_block))
        out["ms_per_step_max"] = float(max(per_block))
        out["ms_per_step_blocks"] = per_block
        names = sorted({k for b in blocks for k in b["phases_ms"]})
        out["phases_ms"] = {k: _median([b["phases_ms"].get(k, 0.0) for b in blocks]) for k in names}
        total = out["phases_ms"].get("total", 0.0) + out["phases_ms"].get("recording", 0.0)
        out["phases_total_ms"] = total
        solve = sum(out["phases_ms"].get(k, 0.0) for k in SOLVE_PHASES)
        out["overhead_pct"] = 100.0 * (total - solve) / total if total > 0 else None
        out["contacts_mean"] = float(np.mean(contacts)) if contacts else 0.0
        out["contacts_max"] = int(max(contacts)) if contacts else 0
        out["sim_time_s"] = world.t
        out["max_node_displacement_m"] = moved[0]
        if floor is not None:
            fl = [b["floor"] for b in blocks]
            out.update(floor.info, floor_repeats=spec["floor_repeats"],
                       floor_ms=_median([f + s for f, s in fl]), floor_factorize_ms=_median([f for f, _ in fl]),
                       floor_solve_ms=_median([s for _, s in fl]), floor_ms_blocks=[f + s for f, s in fl],
                       step_over_floor=_median([b["ms_per_step"] / (f + s) for b, (f, s) in zip(blocks, fl)]))
        if spec.get("profile_steps", 0) > 0:
            out["profile"] = profile_steps(world, body, spec["profile_steps"], spec.get("out_dir"),
                                           Config(spec["scene"], spec["element"], tuple(spec["cells"])).slug)
    finally:
        if recorder is not None:
            recorder.close()
            out["recording_path"] = str(recorder.path)
        world.close()
    out["child_seconds"] = time.perf_counter() - t_start
    return out


@dataclass
class Floor:
    """A captured step system, for timing the solver floor on it."""

    body: object
    A: object
    b: object
    cons: object
    info: dict

    def time(self, repeats: int) -> tuple[float, float]:
        """Medians over ``repeats`` of one numeric refactorisation and one solve [ms], by a fresh
        double-precision solver (backend "auto": PARDISO when available) whose analysis and first
        factorisation run untimed; the solver is released afterwards."""
        from softbody.integrator import DirectSystem
        from softbody.linsolve import SpdSolver

        pat = self.body.pattern
        solver = SpdSolver(pat.up_indptr, pat.up_indices, self.body.n_dofs, "auto", precision="double")
        first = {}
        DirectSystem(self.body, self.A, self.b, solver, timings=first).solve(self.cons)  # analysis + a first factorisation
        self.info.setdefault("floor_first_ms", 1e3 * (first.get("factorize", 0.0) + first.get("solve", 0.0)))
        self.info["floor_backend"] = solver.backend
        fact, solv = [], []
        for _ in range(repeats):
            t = {}
            DirectSystem(self.body, self.A, self.b, solver, timings=t).solve(self.cons)
            fact.append(t["factorize"])
            solv.append(t["solve"])
        del solver
        return 1e3 * _median(fact), 1e3 * _median(solv)


def capture_floor(world, body) -> Floor:
    """The next step's own system matrix and constraint set, for timing the solver floor.

    The next step runs as usual (untimed) while its system and the last constraint set given to its
    solve are captured (``Floor.time`` then times them; ``floor_first_ms``: the first factorisation with
    the analysis, for reference).
    """
    captured = {}
    solve_velocities = world._solve_velocities  # the World's contact solve, which the step hands its systems

    def capture(record, systems, supports):
        for b, system in zip(record.bodies, systems):
            inner = system.solve

            def solve(cons, *a, _b=b, _system=system, _inner=inner, **kw):
                if not kw.get("homogeneous"):
                    captured[id(_b)] = (_system, cons)
                return _inner(cons, *a, **kw)

            system.solve = solve
        return solve_velocities(record, systems, supports)

    world._solve_velocities = capture  # for this one step (an attribute of the instance over the method)
    try:
        world.step()
    finally:
        del world._solve_velocities
    system, cons = captured[id(body)]
    A = getattr(system, "A", None)  # DirectSystem: the assembled block data
    if A is None:  # IterativeSystem: its assembled c_m M + c_k K'(R)
        A = system.assemble()
    return Floor(body, A, system.b, cons, {"floor_constraints": int(len(cons))})


def profile_steps(world, body, steps: int, out_dir, slug: str) -> dict:
    """cProfile of ``steps`` steps: the top-20 table by own time, and the largest calls per step of any
    function (a Python loop per element or node would show as >= n_elements or n_nodes calls per step)."""
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    for _ in range(steps):
        world.step()
    prof.disable()
    stats = pstats.Stats(prof)
    text = io.StringIO()
    pstats.Stats(prof, stream=text).strip_dirs().sort_stats("tottime").print_stats(20)
    text.write("\n# the same, by cumulative time\n")
    pstats.Stats(prof, stream=text).strip_dirs().sort_stats("cumulative").print_stats(20)
    worst_calls, worst_name, total_calls, python_calls = 0, "", 0, 0
    for (fname, line, func), (cc, nc, tt, ct, callers) in stats.stats.items():
        total_calls += nc
        python_calls += nc if fname != "~" else 0  # "~": C functions and methods (len, np.empty, ...)
        if nc > worst_calls:
            worst_calls, worst_name = nc, f"{Path(fname).name}:{line}({func})"
    res = {"steps": steps, "max_calls_per_step": worst_calls / steps, "max_calls_function": worst_name,
           "function_calls_per_step": total_calls / steps, "python_calls_per_step": python_calls / steps,
           "elements": int(body.mesh.n_elements), "nodes": int(body.n_nodes)}
    if out_dir is not None:
        d = Path(out_dir) / "profiles"
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"{slug}.txt"
        path.write_text(f"# cProfile of {steps} steps of {slug} ({body.mesh.n_elements} elements, {body.n_nodes} nodes)\n"
                        f"# most calls per step: {worst_calls / steps:.0f} ({worst_name}); all calls per step: "
                        f"{total_calls / steps:.0f}, of functions written in Python: {python_calls / steps:.0f}\n"
                        "# top 20 by own time\n" + text.getvalue())
        res["file"] = str(path)
    return res


# ----------------------------------------------------------------------------------------------- pybullet

def write_tet_vtk(path, nodes, tets) -> None:
    """Legacy ASCII VTK unstructured grid of 4-node tets (CELL_TYPES 10): one point and one cell per line,
    the layout pybullet's line-based reader expects."""
    with open(path, "w") as f:
        f.write("# vtk DataFile Version 2.0\nsoftbody tet4 mesh\nASCII\nDATASET UNSTRUCTURED_GRID\n")
        f.write(f"POINTS {len(nodes)} double\n")
        f.writelines(f"{float(x):.17g} {float(y):.17g} {float(z):.17g}\n" for x, y, z in nodes)
        f.write(f"\nCELLS {len(tets)} {5 * len(tets)}\n")
        f.writelines(f"4 {int(a)} {int(b)} {int(c)} {int(d)}\n" for a, b, c, d in tets)
        f.write(f"\nCELL_TYPES {len(tets)}\n")
        f.writelines("10\n" for _ in range(len(tets)))


class _OurBlocks:
    """Our own scene (a fresh build of the same configuration), stepped in blocks between pybullet's
    blocks in the same process: ours/pybullet is then a median of ratios of blocks run seconds apart,
    and a change of the machine's speed cancels (as for step/floor)."""

    def __init__(self, spec: dict):
        self.scene = _build(spec)

    def run(self, steps: int) -> float:
        """``steps`` steps of ``world.step()``; returns ms per step."""
        tic = time.perf_counter()
        for _ in range(steps):
            self.scene.world.step()
        return 1e3 * (time.perf_counter() - tic) / max(steps, 1)

    def close(self) -> None:
        self.scene.world.close()


def _pybullet_run(p, vtk: str, spec: dict, nodes, k: int, n_steps: int, timed_from: int,
                  ours: _OurBlocks | None = None) -> dict:
    """One pybullet deformable run with k substeps per 0.01 s step; stops early when it goes unstable.

    With ``ours``: after pybullet's warm-up (``timed_from`` steps) our scene takes as many warm-up
    steps, and after every block of ``spec["steps"]`` timed pybullet steps it takes one block of as
    many steps (ours/pybullet per block pair: ``paired_ratio``, the median)."""
    import numpy as np

    h = spec["dt"]
    E, nu, rho = spec["E"], spec["nu"], spec["density"]
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    mass = rho * spec["volume"]
    cid = p.connect(p.DIRECT)
    try:
        p.resetSimulation(p.RESET_USE_DEFORMABLE_WORLD, physicsClientId=cid)
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        p.setTimeStep(h / k, physicsClientId=cid)
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=spec["sphere_radius"], physicsClientId=cid)
        p.createMultiBody(0, col, basePosition=[0, 0, 0], physicsClientId=cid)
        with quiet_c_output():  # pybullet prints the mesh sizes when it loads a VTK file
            sb = p.loadSoftBody(vtk, basePosition=[0, 0, 0], scale=1, mass=mass, useNeoHookean=1,
                                NeoHookeanMu=mu, NeoHookeanLambda=lam, NeoHookeanDamping=spec["pb_damping"],
                                useSelfCollision=0, frictionCoeff=spec["friction"],
                                collisionMargin=spec["pb_margin"], useFaceContact=1, physicsClientId=cid)
        n, x = p.getMeshData(sb, flags=p.MESH_DATA_SIMULATION_MESH, physicsClientId=cid)
        x0 = np.asarray(x, float)
        if x0.shape != nodes.shape or np.abs(x0 - nodes).max() > 1e-6:
            raise RuntimeError(f"pybullet read the mesh wrongly: {x0.shape} nodes vs {nodes.shape}, max offset "
                               f"{np.abs(x0 - nodes).max() if x0.shape == nodes.shape else float('nan'):.3g} m")
        g, m_node = 9.81, mass / len(x0)  # pybullet spreads the total mass evenly over the nodes
        zc0 = x0[:, 2].mean()
        xp = x0
        wall, reason, max_disp, max_ke, steps_done = 0.0, "", 0.0, 0.0, 0
        block, pb_blocks, our_blocks, paired_error = 0.0, [], [], None
        for s in range(n_steps):
            if ours is not None and s == timed_from:
                # our warm-up, untimed, right before the timed blocks (at least one step: the first
                # carries the symbolic analysis and the first factorisation)
                ours.run(max(timed_from, 1))
            tic = time.perf_counter()
            for _ in range(k):
                p.stepSimulation(physicsClientId=cid)
            dt_wall = time.perf_counter() - tic
            if s >= timed_from:
                wall += dt_wall
                block += dt_wall
            x = np.asarray(p.getMeshData(sb, flags=p.MESH_DATA_SIMULATION_MESH, physicsClientId=cid)[1], float)
            steps_done = s + 1
            if x.shape != x0.shape or not np.isfinite(x).all():
                reason = f"non-finite positions at t = {(s + 1) * h:.2f} s"
                break
            disp = float(np.sqrt(((x - x0) ** 2).sum(axis=1)).max())
            ke = 0.5 * m_node * float((((x - xp) / h) ** 2).sum())
            max_disp, max_ke = max(max_disp, disp), max(max_ke, ke)
            released = mass * g * max(zc0 - x[:, 2].mean(), 0.0)
            if disp > spec["max_disp"]:
                reason = f"a node moved {disp:.2f} m from its start at t = {(s + 1) * h:.2f} s"
                break
            if ke > 2.0 * released + mass * g * 0.01:
                reason = (f"kinetic energy {ke:.3g} J > twice the potential energy released ({released:.3g} J) "
                          f"at t = {(s + 1) * h:.2f} s")
                break
            xp = x
            if s >= timed_from and (s + 1 - timed_from) % spec["steps"] == 0:
                pb_blocks.append(1e3 * block / spec["steps"])
                block = 0.0
                if ours is not None:
                    try:
                        our_blocks.append(ours.run(spec["steps"]))
                    except Exception as exc:  # keep pybullet's measurement; no pairs
                        ours, our_blocks = None, []
                        paired_error = f"our scene failed: {type(exc).__name__}: {exc}"
        timed = max(steps_done - timed_from, 0)
        paired = {"paired_error": paired_error} if paired_error else {}
        if our_blocks and not reason:
            ratios = [o / b for o, b in zip(our_blocks, pb_blocks)]
            paired = {"paired_ratio": float(np.median(ratios)), "paired_ratios": ratios,
                      "paired_ours_ms": our_blocks, "paired_pybullet_ms": pb_blocks}
        return paired | {"k": k, "stable": not reason, "reason": reason, "steps": steps_done,
                "on_sphere": not reason and max_disp <= spec["on_sphere_disp"],
                "max_disp_m": max_disp, "max_kinetic_energy_j": max_ke,
                "final_center_z_m": float(x[:, 2].mean()) if np.isfinite(x).all() else None,
                "final_min_z_m": float(x[:, 2].min()) if np.isfinite(x).all() else None,
                "ms_per_step": 1e3 * wall / timed if timed and not reason else None}
    finally:
        p.disconnect(cid)


def measure_pybullet(spec: dict) -> dict:
    """pybullet's neo-Hookean FEM on our tet4 sheet mesh: the smallest stable substep count and its cost."""
    import numpy as np
    import pybullet as p

    t_start = time.perf_counter()
    scene = _build(spec)
    body = scene.body
    mat = body.material
    nodes = np.asarray(body.mesh.nodes, float)
    tets = np.asarray(body.mesh.elements)
    sphere = next(rb for rb in scene.world.rigids.values() if rb.shape == "sphere")
    run_spec = dict(spec, E=mat.E, nu=mat.nu, density=mat.density, volume=float(body.mesh.volume()),
                    sphere_radius=float(sphere.params["radius"]), dt=scene.world.dt,
                    friction=float(scene.world.entry(body).friction))
    scene.world.close()
    n_steps = spec["warmup"] + spec["steps"] * spec["repeats"]
    tried, k = [], 1
    with tempfile.TemporaryDirectory(prefix="softbody-bench-") as tmp:
        vtk = Path(tmp) / f"{Config(spec['scene'], spec['element'], tuple(spec['cells'])).slug}.vtk"
        write_tet_vtk(vtk, nodes, tets)
        while k <= spec["pybullet_max_k"]:
            ours = _OurBlocks(spec)  # from rest, like pybullet's run
            try:
                r = _pybullet_run(p, str(vtk), run_spec, nodes, k, n_steps, spec["warmup"], ours)
            finally:
                ours.close()
                ours = None  # released before the next k's scene is built
            tried.append(r)
            if r["on_sphere"]:
                break
            k *= 2
    stable = next((r for r in tried if r["stable"]), None)
    on = next((r for r in tried if r["on_sphere"]), None)
    return {"nodes": int(len(nodes)), "tets": int(len(tets)), "sim_time_s": n_steps * run_spec["dt"],
            "timed_steps": n_steps - spec["warmup"], "mu": mat.E / (2 * (1 + mat.nu)),
            "lambda": mat.E * mat.nu / ((1 + mat.nu) * (1 - 2 * mat.nu)), "mass_kg": mat.density * run_spec["volume"],
            "damping": spec["pb_damping"], "collision_margin": spec["pb_margin"], "friction": run_spec["friction"],
            "k": stable["k"] if stable else None, "ms_per_step": stable["ms_per_step"] if stable else None,
            "k_on_sphere": on["k"] if on else None, "ms_per_step_on_sphere": on["ms_per_step"] if on else None,
            "paired_ratio": stable.get("paired_ratio") if stable else None,
            "paired_ratio_on_sphere": on.get("paired_ratio") if on else None,
            "tried": tried, "peak_rss_mb": _rss_mb(), "child_seconds": time.perf_counter() - t_start}


# ----------------------------------------------------------------------------------------------- the suite

def _machine() -> dict:
    info = {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count()}
    try:
        info["load_average"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        info["git_commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                            cwd=Path(__file__).resolve().parent, timeout=5).stdout.strip() or None
    except Exception:
        pass
    try:
        import pybullet  # noqa: F401
        from importlib.metadata import version

        info["pybullet"] = version("pybullet")
        info["numpy"] = version("numpy")
    except Exception:
        pass
    return info


def run_bench(configs: Iterable = DEFAULT_CONFIGS, steps: int = 50, repeats: int = 3, warmup: int = 20,
              threads: int = 1, out_dir: str | Path = "logs/bench", include_pybullet: bool = True, record: bool = False,
              *, name: str = "bench", method: str | None = None, floor_repeats: int = 5, profile_steps: int = 10,
              pybullet_cells: Sequence[Sequence[int]] | None = None, pybullet_max_k: int = 128,
              pybullet_damping: float = 0.001, pybullet_margin: float = 0.002, max_disp: float = 2.0,
              timeout: float | None = None, log=print) -> list[dict]:
    """Measure each configuration in its own fresh process; write ``name``.json and ``name``.md to ``out_dir``
    and draw ``name``.png from every result there; print the markdown table; return the result dicts.

    pybullet runs for tet4 sheet configurations whose cells are in ``pybullet_cells`` (default: every
    tet4 sheet configuration) when ``include_pybullet``. ``method`` forces Simulation.method (None: the
    library's choice). ``timeout`` [s] bounds each child process.
    """
    from softbody.errors import InvalidInputError

    for label, v in (("steps", steps), ("repeats", repeats), ("threads", threads)):
        if int(v) < 1:
            raise InvalidInputError(f"{label} must be >= 1, got {v!r}")
    if int(warmup) < 0 or int(floor_repeats) < 0 or int(profile_steps) < 0:
        raise InvalidInputError("warmup, floor_repeats and profile_steps must be >= 0")
    configs = [parse_config(c) for c in configs]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    base = dict(steps=int(steps), repeats=int(repeats), warmup=int(warmup), threads=int(threads), record=bool(record),
                method=method, floor_repeats=int(floor_repeats), profile_steps=int(profile_steps),
                out_dir=str(out.resolve()))
    machine = _machine()
    results = []
    for i, c in enumerate(configs, 1):
        log(f"# [{i}/{len(configs)}] {c.label}: {steps} steps x {repeats} after {warmup} warm-up steps, "
            f"{threads} thread(s) ...", flush=True)
        spec = dict(base, scene=c.scene, element=c.element, cells=list(c.cells))
        r = run_in_fresh_process("measure_config", spec, threads, timeout)
        r.update(label=c.label, scene=c.scene, element=c.element, cells=list(c.cells))
        if "error" in r:
            log(f"#   failed: {r['error']}", flush=True)
        else:
            log(f"#   {r['ms_per_step']:.2f} ms/step ({r['method']}), floor {r.get('floor_ms', float('nan')):.2f} ms, "
                f"peak {r['peak_rss_mb']:.0f} MB", flush=True)
        wants_pb = include_pybullet and c.scene == SHEET and c.element == "tet4" and (
            pybullet_cells is None or tuple(c.cells) in {tuple(x) for x in pybullet_cells})
        if wants_pb:
            log(f"#   pybullet's FEM soft body on the same mesh: substeps 1, 2, 4, ... up to {pybullet_max_k} ...",
                flush=True)
            pspec = dict(spec, pybullet_max_k=int(pybullet_max_k), pb_damping=float(pybullet_damping),
                         pb_margin=float(pybullet_margin), max_disp=float(max_disp), on_sphere_disp=0.5)
            pb = run_in_fresh_process("measure_pybullet", pspec, threads, timeout)
            r["pybullet"] = pb
            # the headline ratio: blocks of ours and pybullet's alternating in pybullet's process (paired);
            # also kept: our ms/step above over pybullet's, taken in two processes minutes apart
            if pb.get("ms_per_step") and r.get("ms_per_step"):
                r["ours_over_pybullet_cross_process"] = r["ms_per_step"] / pb["ms_per_step"]
                r["ours_over_pybullet"] = pb.get("paired_ratio") or r["ours_over_pybullet_cross_process"]
                r["ours_over_pybullet_source"] = "paired" if pb.get("paired_ratio") else "cross-process"
            if pb.get("ms_per_step_on_sphere") and r.get("ms_per_step"):
                r["ours_over_pybullet_on_sphere"] = (pb.get("paired_ratio_on_sphere")
                                                     or r["ms_per_step"] / pb["ms_per_step_on_sphere"])
            if "error" in pb:
                log(f"#   pybullet failed: {pb['error']}", flush=True)
            else:
                log(f"#   pybullet: stable from k = {pb['k']} ({_fmt(pb['ms_per_step'])} ms per 0.01 s), on the sphere "
                    f"from k = {pb['k_on_sphere']}", flush=True)
        results.append(r)
    doc = {"name": name, "created": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": machine,
           "settings": {k: v for k, v in base.items() if k != "out_dir"} | {
               "include_pybullet": include_pybullet, "pybullet_max_k": pybullet_max_k,
               "pybullet_damping": pybullet_damping, "pybullet_margin": pybullet_margin, "max_disp": max_disp},
           "results": results}
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1, default=_json_default))
    md = markdown(doc)
    (out / f"{name}.md").write_text(md)
    try:
        plot_scaling(out, name)
    except Exception as exc:  # a plot must not lose the measurements
        log(f"# scaling plot failed: {type(exc).__name__}: {exc}")
    log(md)
    return results


def _json_default(o):
    import numpy as np

    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ----------------------------------------------------------------------------------------------- reports

def _fmt(v, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, int):
        return str(v)
    if abs(v) >= 100:
        return f"{v:.0f}"
    return f"{v:.{digits}f}"


def markdown(doc: dict) -> str:
    """The tables of one bench document: main table, breakdown, pybullet search, profiles, fits."""
    res = doc["results"]
    s, m = doc["settings"], doc["machine"]
    lines = [f"## softbody bench ({doc['name']}): {doc['created']}", "",
             f"Machine: {m.get('cpu', '?')}, {m.get('cpus', '?')} CPUs, load average at start "
             f"{m.get('load_average', '?')}; {s['threads']} thread(s); git {m.get('git_commit', '?')}. "
             f"Per configuration: {s['warmup']} warm-up steps, then {s['repeats']} blocks of {s['steps']} steps "
             f"(h = 0.01 s); ms/step is the median over blocks of the mean per block [min-max over blocks].", "",
             "| config | elements | nodes | DOFs | method | ms/step [min-max] | floor ms | step/floor | "
             "pybullet ms per 0.01 s (k) | ours/pybullet | overhead % | peak MB | kB/node |",
             "|---|---:|---:|---:|---|---|---:|---:|---|---:|---:|---:|---:|"]
    for r in res:
        if "error" in r:
            lines.append(f"| {r['label']} | | | | | failed: {r['error'].splitlines()[0][:80]} | | | | | | | |")
            continue
        pb = r.get("pybullet") or {}
        if pb.get("error"):
            pbt = "failed"
        elif pb:
            none = ">" + str(s.get("pybullet_max_k"))
            pbt = f"{_fmt(pb.get('ms_per_step'))} (k={pb.get('k') or none})"
            if pb.get("k_on_sphere") != pb.get("k"):
                pbt += f"; on sphere {_fmt(pb.get('ms_per_step_on_sphere'))} (k={pb.get('k_on_sphere') or none})"
        else:
            pbt = "-"
        ratio = _fmt(r.get("ours_over_pybullet"), 3)
        if pb and pb.get("k_on_sphere") != pb.get("k"):
            ratio += f"; {_fmt(r.get('ours_over_pybullet_on_sphere'), 3)}"
        lines.append(
            f"| {r['label']} | {r['elements']} | {r['nodes']} | {r['dofs']} | {r['method']} | "
            f"{_fmt(r['ms_per_step'])} [{_fmt(r['ms_per_step_min'])}-{_fmt(r['ms_per_step_max'])}] | "
            f"{_fmt(r.get('floor_ms'))} | {_fmt(r.get('step_over_floor'))} | {pbt} | "
            f"{ratio} | {_fmt(r.get('overhead_pct'), 1)} | {_fmt(r.get('peak_rss_mb'), 0)} | "
            f"{_fmt(kb_per_node(r), 1)} |")
    ok = [r for r in res if "error" not in r]
    if ok:
        names = [n for n in PHASES if any(n in r["phases_ms"] for r in ok)]
        lines += ["", "Step breakdown, ms per step (median over blocks of the per-block mean); contact detection = "
                      "collision, contact solve = contact; factorisations and PCG iterations per step:", "",
                  "| config | " + " | ".join(names) + " | sum | contacts (mean/max) | factorisations | PCG its |",
                  "|---|" + "---:|" * (len(names) + 4)]
        for r in ok:
            ph = r["phases_ms"]
            lines.append(f"| {r['label']} | " + " | ".join(_fmt(ph.get(n), 3) for n in names)
                         + f" | {_fmt(r['phases_total_ms'], 3)} | {r['contacts_mean']:.0f}/{r['contacts_max']} | "
                           f"{_fmt(r['factorizations_per_step'], 3)} | {_fmt(r.get('pcg_iterations_per_step'), 1)} |")
    pbs = [r for r in ok if r.get("pybullet") and not r["pybullet"].get("error")]
    if pbs:
        lines += ["", "pybullet's FEM soft body (loadSoftBody, neo-Hookean, same tet4 mesh, sphere, friction, "
                      "gravity; k substeps of 0.01/k s per 0.01 s step; same simulated time as ours):", "",
                  "| config | k | stable | on sphere | max node displacement m | max kinetic energy J | "
                  "ms per 0.01 s | note |", "|---|---:|---|---|---:|---:|---:|---|"]
        for r in pbs:
            for t in r["pybullet"]["tried"]:
                lines.append(f"| {r['label']} | {t['k']} | {'yes' if t['stable'] else 'no'} | "
                             f"{'yes' if t['on_sphere'] else 'no'} | {_fmt(t['max_disp_m'], 3)} | "
                             f"{_fmt(t['max_kinetic_energy_j'], 1)} | {_fmt(t['ms_per_step'])} | {t['reason']} |")
        for r in pbs:
            pb = r["pybullet"]
            lines.append(f"\n{r['label']} (ours: largest node displacement {_fmt(r.get('max_node_displacement_m'), 3)} m): "
                         f"stable from k = {pb['k']}, ours/pybullet = {_fmt(r.get('ours_over_pybullet'), 3)}; "
                         f"stays on the sphere from k = {pb['k_on_sphere']}, ours/pybullet = "
                         f"{_fmt(r.get('ours_over_pybullet_on_sphere'), 3)}.")
            st = next((t for t in pb["tried"] if t.get("k") == pb.get("k")), {})
            if st.get("paired_ratios"):
                lines.append(f"Per block pair (ours and pybullet's blocks alternating in one process): ours "
                             f"{', '.join(_fmt(v) for v in st['paired_ours_ms'])} ms, pybullet "
                             f"{', '.join(_fmt(v) for v in st['paired_pybullet_ms'])} ms per 0.01 s, ratios "
                             f"{', '.join(_fmt(v, 3) for v in st['paired_ratios'])}; ours in its own process "
                             f"over pybullet's: {_fmt(r.get('ours_over_pybullet_cross_process'), 3)}.")
    prof = [r for r in ok if r.get("profile")]
    if prof:
        lines += ["", "Python calls per step on the step path (cProfile): a loop per element or node would show "
                      "as calls per step of the order of the element or node count. All calls count C functions and "
                      "methods too (len, np.empty, ...); Python-level calls only those of functions written in Python:",
                  "", "| config | elements | nodes | all calls per step | Python-level calls per step | most calls per "
                      "step (function) | profile |",
                  "|---|---:|---:|---:|---:|---|---|"]
        for r in prof:
            p_ = r["profile"]
            py = p_.get("python_calls_per_step")
            lines.append(f"| {r['label']} | {p_['elements']} | {p_['nodes']} | {p_['function_calls_per_step']:.0f} | "
                         f"{'-' if py is None else f'{py:.0f}'} | "
                         f"{p_['max_calls_per_step']:.0f} ({p_['max_calls_function']}) | "
                         f"{Path(p_['file']).name if p_.get('file') else '-'} |")
    fits = fit_scaling(ok)
    if fits:
        lines += ["", "Fits over nodes N (least squares in log-log; memory linear in N):", ""]
        for kind, f in sorted(fits.items()):
            parts = []
            if f.get("time_exponent") is not None:
                parts.append(f"ms/step ~ N^{f['time_exponent']:.2f}")
            if f.get("floor_exponent") is not None:
                parts.append(f"floor ~ N^{f['floor_exponent']:.2f}")
            if f.get("mb_per_1000_nodes") is not None:
                parts.append(f"peak RSS ~ {f['rss_intercept_mb']:.0f} MB + {f['mb_per_1000_nodes']:.1f} MB per 1000 nodes")
            if f.get("rss_exponent") is not None:
                parts.append(f"peak RSS above the imports ~ N^{f['rss_exponent']:.2f}")
            lines.append(f"- {kind} ({f['points']} sizes, {f['nodes_min']}-{f['nodes_max']} nodes): " + "; ".join(parts))
    return "\n".join(lines) + "\n"


def fit_scaling(results: list[dict]) -> dict:
    """Per element type with >= 2 sizes: exponents of ms/step, floor and (peak - baseline) RSS against nodes N,
    and the linear fit peak RSS = a + b N."""
    import numpy as np

    fits = {}
    by = {}
    for r in results:
        if "error" not in r and r.get("ms_per_step"):
            by.setdefault(r["element"], {})[r["nodes"]] = r  # one point per size (the last wins)
    for kind, pts in by.items():
        if len(pts) < 2:
            continue
        rs = [pts[n] for n in sorted(pts)]
        N = np.array([r["nodes"] for r in rs], float)
        f = {"points": len(rs), "nodes_min": int(N.min()), "nodes_max": int(N.max())}
        f["time_exponent"] = float(np.polyfit(np.log(N), np.log([r["ms_per_step"] for r in rs]), 1)[0])
        fl = [r.get("floor_ms") for r in rs]
        if all(fl):
            f["floor_exponent"] = float(np.polyfit(np.log(N), np.log(fl), 1)[0])
        rss = [r.get("peak_rss_mb") for r in rs]
        if all(rss):
            b, a = np.polyfit(N, rss, 1)
            f["mb_per_1000_nodes"], f["rss_intercept_mb"] = float(1000 * b), float(a)
            above = np.array([r["peak_rss_mb"] - r.get("baseline_rss_mb", 0.0) for r in rs])
            if (above > 0).all():
                f["rss_exponent"] = float(np.polyfit(np.log(N), np.log(above), 1)[0])
        fits[kind] = f
    return fits


def _all_results(out: Path) -> list[dict]:
    res = {}
    for name in ("large", "scaling", "bench"):  # bench.json wins for a configuration in two
        path = out / f"{name}.json"
        if path.exists():
            try:
                for r in json.loads(path.read_text()).get("results", []):
                    if "error" not in r:
                        res[(r["element"], r["nodes"], r.get("scene"))] = r
            except (OSError, ValueError):
                continue
    return list(res.values())


def plot_scaling(out_dir: str | Path, name: str = "scaling") -> Path | None:
    """``name``.png in out_dir: ms/step (solid) and floor (dashed) against nodes per element type, and the peak
    RSS above the RSS after imports, from every result in out_dir; log-log with plain-number ticks, fitted
    exponents in the legends."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out = Path(out_dir)
    res = [r for r in _all_results(out) if r.get("scene", SHEET) == SHEET]
    if not res:
        return None
    fits = fit_scaling(res)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    colors = {"tet4": "tab:blue", "hex8": "tab:orange", "tet10": "tab:green"}
    for kind in sorted({r["element"] for r in res}):
        rs = sorted((r for r in res if r["element"] == kind), key=lambda r: r["nodes"])
        N = np.array([r["nodes"] for r in rs])
        c = colors.get(kind)
        f = fits.get(kind, {})
        lab = kind + (f" (N^{f['time_exponent']:.2f})" if f.get("time_exponent") is not None else "")
        ax.loglog(N, [r["ms_per_step"] for r in rs], "o-", color=c, label=lab)
        fl = [r.get("floor_ms") or np.nan for r in rs]
        if np.isfinite(fl).any():
            lab = f"{kind} floor" + (f" (N^{f['floor_exponent']:.2f})" if f.get("floor_exponent") is not None else "")
            ax.loglog(N, fl, "s--", color=c, alpha=0.6, label=lab)
        above = [(r.get("peak_rss_mb") or np.nan) - (r.get("baseline_rss_mb") or 0.0) for r in rs]
        lab = kind + (f" (N^{f['rss_exponent']:.2f}; +{f['mb_per_1000_nodes']:.0f} MB/1000 nodes)"
                      if f.get("rss_exponent") is not None else "")
        ax2.loglog(N, np.maximum(above, 1e-3), "o-", color=c, label=lab)
    pbs = [r for r in res if (r.get("pybullet") or {}).get("ms_per_step")]
    if pbs:
        ax.loglog([r["nodes"] for r in pbs], [r["pybullet"]["ms_per_step"] for r in pbs], "k^:",
                  label="pybullet FEM per 0.01 s (tet4)")
    ax.set_xlabel("nodes")
    ax.set_ylabel("ms per step (h = 0.01 s)")
    ax.set_title("sheet-on-sphere: cost per step")
    ax.legend(fontsize=8)
    ax2.set_xlabel("nodes")
    ax2.set_ylabel("peak RSS - RSS after imports [MB]")
    ax2.set_title("peak memory of the run (fresh process)")
    ax2.legend(fontsize=8)
    for a in (ax, ax2):
        _log_axes(a)
    fig.tight_layout()
    path = out / f"{name}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------- command line

def add_bench_arguments(parser) -> None:
    """Flags of ``softbody bench`` (and benchmarks/bench.py)."""
    parser.add_argument("--tiny", action="store_true",
                        help="one tiny configuration (tet4 (4,4,2)), a few steps: checks that everything runs")
    parser.add_argument("--scaling", action="store_true",
                        help="the scaling ladder (each element type up to >= 4x the paper's largest mesh), fewer steps; "
                             "writes scaling.json / scaling.md")
    parser.add_argument("--large", action="store_true",
                        help="large bodies: tet4 sheets of 72k, 235k and 549k nodes through the impact (the 12 steps after 9; "
                             "no floor, no profile; about 25 min, 11 GB at the largest); writes large.json / large.md")
    parser.add_argument("--configs", nargs="+", default=None, metavar="CFG",
                        help="configurations [scene:]element:NXxNYxNZ, e.g. tet4:24x24x6 hex8:20x20x5")
    parser.add_argument("--steps", type=int, default=None, help="timed steps per block (default 50; scaling 10)")
    parser.add_argument("--repeats", type=int, default=None, help="timed blocks (default 3; scaling 1)")
    parser.add_argument("--warmup", type=int, default=None, help="warm-up steps, into contact (default 20)")
    parser.add_argument("--threads", type=int, default=1, help="solver threads (OMP/MKL/OpenBLAS), default 1")
    parser.add_argument("--out", default="logs/bench", metavar="DIR",
                        help="output directory (default: logs/bench, not tracked by git; docs/bench for the README)")
    parser.add_argument("--no-pybullet", action="store_true", help="skip pybullet's soft body comparison")
    parser.add_argument("--pybullet-max-k", type=int, default=None, help="largest pybullet substep count tried (default 128)")
    parser.add_argument("--record", action="store_true", help="record every step with rerun (the recording phase)")
    parser.add_argument("--method", choices=("auto", "direct", "iterative"), default=None,
                        help="force the linear solve (default: the library's choice)")
    parser.add_argument("--floor-repeats", type=int, default=None, help="refactorisations timed for the floor (default 5)")
    parser.add_argument("--profile-steps", type=int, default=None, help="steps under cProfile per config (default 10; 0: none)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds allowed per measurement process")


def bench_command(args) -> list[dict]:
    if args.tiny:
        configs, preset, name, pb_cells = TINY_CONFIGS, dict(TINY), "bench", None
    elif getattr(args, "large", False):
        configs, preset, name, pb_cells = LARGE_CONFIGS, dict(LARGE), "large", []
    elif args.scaling:
        configs, preset, name, pb_cells = SCALING_CONFIGS, dict(SCALING), "scaling", []
    else:
        configs, preset, name, pb_cells = DEFAULT_CONFIGS + SMALL_CONFIGS, {}, "bench", PYBULLET_CELLS
    if args.configs:
        configs, pb_cells = args.configs, None
    kw = dict(steps=DEFAULTS["steps"], repeats=DEFAULTS["repeats"], warmup=DEFAULTS["warmup"])
    kw.update(preset)
    for key in ("steps", "repeats", "warmup", "floor_repeats", "profile_steps", "pybullet_max_k"):
        if getattr(args, key, None) is not None:
            kw[key] = getattr(args, key)
    return run_bench(configs, threads=args.threads, out_dir=args.out, include_pybullet=not args.no_pybullet,
                     record=args.record, name=name, method=None if args.method in (None, "auto") else args.method,
                     pybullet_cells=pb_cells, timeout=args.timeout, **kw)
