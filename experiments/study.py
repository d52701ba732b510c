"""Convergence studies: the speed/accuracy trade of element type and resolution, measured.

A *study* runs one scene at every rung of a resolution *ladder* for each element type, plus one
*reference* run finer than every rung, and reports for each run its size (elements, nodes, DOFs),
its cost (median ms per step, peak memory) and its error: the RMS difference [m] of the monitored
coordinate against the reference over the common time grid (:func:`rms_error`).

Runs are independent, pure functions of their inputs (:func:`run_configuration`), so they go to an
executor: local worker processes by default, or a Dask distributed cluster (``cluster=ADDRESS``)
through the same ``concurrent.futures`` interface. Workers pin BLAS / MKL / OpenMP to one thread,
so a trajectory is bit-identical wherever it ran.

Layout of a study directory (every file is rewritten from the cached runs on each call)::

    DIR/trajectories/<element>_<nx>x<ny>x<nz>.npz   one run: times, values, meta (the cache)
    DIR/results.csv                                 one row per run (reference included, role column)
    DIR/table.md                                    the same as a markdown table, with the metric
    DIR/trajectories.png                            monitored coordinate per resolution, per element
    DIR/time_vs_nodes.png                           median ms per step against nodes (log-log)
    DIR/pareto.png                                  error against ms per step, with the Pareto front

:func:`recommend` reads a study and returns the cheapest configuration within a tolerance;
:func:`recommend_shipped` does the same from the published studies shipped in ``experiments/data/``
(no run), and :func:`recommend_steps` weighs the scheme and the time step too (a study per scheme and dt).
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import gc
import json
import math
import os
import queue
import sys
import threading
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from softbody.body import MODELS
from softbody.errors import InvalidInputError, SimulationDiverged, SolverError
from softbody.linsolve import THREAD_VARS as THREAD_ENV

FORMAT = 2  # version of the cached run files; bump to invalidate old caches
SCHEMES = ("warped", "newton")  # the World's (integration.world.WORLD_SCHEMES): the scenes are Worlds
ELEMENTS = ("tet4", "hex8", "tet10")


def solve_methods() -> tuple[str, ...]:
    """The linear-solve methods softbody.Simulation accepts (e.g. auto, direct, iterative)."""
    from softbody import simulation

    methods = getattr(simulation, "METHODS", None)
    return tuple(methods) if methods else tuple(dict.fromkeys((default_method(), "direct")))


CSV_COLUMNS = ("scene", "role", "element", "cells", "elements", "nodes", "dofs", "steps", "duration_s",
               "dt_s", "scheme", "method", "median_ms_per_step", "median_cpu_ms_per_step", "peak_mem_mb", "wall_s", "error_m", "status",
               "external_load", "material")
# the elastic models a body takes, and those that only an iterated scheme steps (the hyperelastic laws)
ITERATED_MODELS = tuple(m for m in MODELS if m not in ("warped", "linear"))


@dataclass(frozen=True)
class Material:
    """The material of a study's runs: Young's modulus E [Pa], Poisson ratio nu and the elastic model
    (softbody.MODELS); None keeps the scene's own (docs/method.md's canonical values, the warped model)."""

    E: float | None = None
    nu: float | None = None
    model: str | None = None

    def __post_init__(self) -> None:
        if self.E is not None and not (isinstance(self.E, (int, float)) and math.isfinite(self.E) and self.E > 0):
            raise InvalidInputError(f"E must be a finite number > 0 [Pa], got {self.E!r}")
        if self.nu is not None and not (isinstance(self.nu, (int, float)) and -1.0 < self.nu < 0.5):
            raise InvalidInputError(f"nu must satisfy -1 < nu < 0.5, got {self.nu!r}")
        if self.model is not None and self.model not in MODELS:
            raise InvalidInputError(f"model must be one of {MODELS}, got {self.model!r}")

    @property
    def default(self) -> bool:
        return self.E is None and self.nu is None and self.model in (None, "warped")

    def options(self) -> dict:
        """The scene builder's keyword arguments (E, nu, model) that differ from its own."""
        return {k: v for k, v in (("E", self.E), ("nu", self.nu), ("model", self.model)) if v is not None}

    @property
    def tag(self) -> str:
        """'' for the scenes' own material, else e.g. 'E1e+05_nu0.45_neo-hookean' (the study directory's suffix and
        the results' material column)."""
        return "_".join(f"{k}{v:g}" if isinstance(v, float) else f"{v}" for k, v in self.options().items()
                        if not (k == "model" and v == "warped"))

    def check_scheme(self, scheme: str) -> None:
        """A hyperelastic model needs the Newton scheme (the warped step refuses it): said before any run."""
        if self.model in ITERATED_MODELS and scheme != "newton":
            raise InvalidInputError(f"model {self.model!r} is stepped by the Newton scheme only (--scheme newton), "
                                    f"got scheme {scheme!r}")

WAITED = 1.3  # wall / CPU time per step above this: the run waited for a core
BUSY_CORES = 0.25  # cores kept busy by processes outside the study above which that wait is the machine's load


def step_cost_ms(wall_ms: float, cpu_ms: float) -> float:
    """A run's cost per step [ms] for ranking: its wall time, or its CPU time where the wall time is more than
    WAITED x that (the run waited for a core, so its wall time says more about the machine than about it)."""
    return cpu_ms if wall_ms > WAITED * cpu_ms else wall_ms


def shared_core(wall_ms: float, cpu_ms: float, external_load: float) -> bool:
    """Whether a run waited for a core (wall > WAITED x CPU) while processes outside the study kept more than
    BUSY_CORES cores busy (NaN load, no /proc: the wait alone). A wait the study's own workers cause is not
    the machine's load."""
    waited = wall_ms > WAITED * cpu_ms
    return waited and (math.isnan(external_load) or external_load > BUSY_CORES)

Cells = tuple[int, int, int]


# ---------------------------------------------------------------------------------------- ladders
@dataclass(frozen=True)
class Ladder:
    """Resolutions to run, per element type, and the reference run the errors are measured against.

    rungs: element -> cells, coarse to fine; reference: (element, cells), finer than every rung;
    duration: simulated time [s] (None: the scene's default).
    """

    rungs: dict[str, tuple[Cells, ...]]
    reference: tuple[str, Cells]
    duration: float | None = None
    note: str = ""


LADDERS: dict[str, dict[str, Ladder]] = {
    "sheet-on-sphere": {
        # docs/method.md section 5: exactly the paper's element and node counts (Fig. 9, 10).
        "full": Ladder(
            {"tet4": ((4, 4, 2), (8, 8, 3), (16, 16, 4), (20, 20, 5), (24, 24, 6), (26, 26, 7)),
             "hex8": ((4, 4, 2), (8, 8, 3), (12, 12, 4), (16, 16, 4), (18, 18, 5), (20, 20, 5)),
             "tet10": ((2, 2, 1), (4, 4, 1), (6, 6, 2), (8, 8, 2), (9, 9, 2))},
            ("tet10", (12, 12, 3)), None, "the paper's ladders (docs/method.md section 5)"),
        "small": Ladder(
            {"tet4": ((4, 4, 2), (8, 8, 3)), "hex8": ((4, 4, 2), (8, 8, 3)), "tet10": ((2, 2, 1), (4, 4, 1))},
            ("tet10", (6, 6, 2)), 0.5, "coarse rungs, 0.5 s (tests, CI)"),
    },
    "hanging-tube": {
        # cells are (n_theta, n_r, n_z). tet4 and hex8 use two radial cells and reproduce the paper's
        # element counts of Fig. 8 (hex8 48, 160, 280, 432, 616; tet4 5x those and 1200, 1920); tet10 uses
        # one radial cell as the paper's counts imply, with n_theta even (checkerboard cut around the tube).
        "full": Ladder(
            {"tet4": ((6, 2, 4), (8, 2, 10), (10, 2, 14), (12, 2, 18), (12, 2, 20), (14, 2, 22), (16, 2, 24)),
             "hex8": ((6, 2, 4), (8, 2, 10), (10, 2, 14), (12, 2, 18), (14, 2, 22)),
             "tet10": ((6, 1, 1), (10, 1, 2), (8, 1, 4), (10, 1, 5))},
            ("tet10", (16, 2, 10)), None, "element counts of the paper's Fig. 8 (n_theta, n_r, n_z)"),
        "small": Ladder(
            {"tet4": ((6, 2, 4), (8, 2, 10)), "hex8": ((6, 2, 4), (8, 2, 10)), "tet10": ((6, 1, 1), (10, 1, 2))},
            ("tet10", (10, 1, 5)), 1.0, "coarse rungs, 1.0 s (tests, CI)"),
    },
    "cantilever": {
        # tet4 and hex8 keep ny, nz even so that the monitored tip centre (1, 0, 0) is a node at every rung
        # (tet10 has it as a mid-edge node with one cell through the section).
        "full": Ladder(
            {"tet4": ((4, 2, 2), (8, 2, 2), (16, 2, 2), (24, 4, 4), (32, 4, 4), (48, 6, 6)),
             "hex8": ((4, 2, 2), (8, 2, 2), (16, 2, 2), (24, 4, 4), (32, 4, 4)),
             "tet10": ((2, 1, 1), (4, 1, 1), (8, 1, 1), (12, 2, 2), (16, 2, 2))},
            ("tet10", (24, 3, 3)), None, "halving the cell size along the beam, then through the section"),
        "small": Ladder(
            {"tet4": ((4, 2, 2), (8, 2, 2), (16, 2, 2)), "hex8": ((4, 2, 2), (8, 2, 2), (16, 2, 2)),
             "tet10": ((2, 1, 1), (4, 1, 1), (8, 1, 1))},
            ("tet10", (16, 2, 2)), 0.3, "coarse rungs, 0.3 s: about one period of the first bending mode"),
    },
}


def register_ladder(scene: str, name: str, ladder: Ladder) -> None:
    """Make ``softbody study SCENE --ladder NAME`` available (e.g. for a scene added by register_scene)."""
    LADDERS.setdefault(scene, {})[name] = ladder


def get_ladder(scene: str, name: str = "full") -> Ladder:
    if scene not in LADDERS:
        raise InvalidInputError(f"no resolution ladder for scene {scene!r}; scenes with ladders: {sorted(LADDERS)} "
                                f"(add one with experiments.study.register_ladder)")
    if name not in LADDERS[scene]:
        raise InvalidInputError(f"no ladder {name!r} for scene {scene!r}; available: {sorted(LADDERS[scene])}")
    return LADDERS[scene][name]


def cells_text(cells: Sequence[int]) -> str:
    return "x".join(str(int(c)) for c in cells)


def parse_cells(text: str) -> Cells:
    parts = tuple(int(c) for c in str(text).split("x"))
    if len(parts) != 3:
        raise InvalidInputError(f"cells must look like NXxNYxNZ, got {text!r}")
    return parts  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------- one run
@dataclass
class RunResult:
    """One configuration run. ``times`` (n,) [s] and ``values`` (n,) [m] are the monitored coordinate
    after each step (the first entry is t = 0); sizes are of the mesh; ``dofs`` counts the free DOFs
    (3 per node not fixed or attached); ``median_ms_per_step`` is the median over steps of the wall-clock
    time of World.step (collision, soft step with contacts, rigid step), ``median_cpu_ms_per_step`` the
    same in CPU time of the running thread (with one BLAS / MKL thread it is the whole step's CPU time,
    and it hardly grows when other processes compete for the cores); ``peak_mem_mb`` is the peak increase of the
    process's resident memory while building and running the scene [MiB]. ``status`` is "ok" or the
    reason the run stopped early (its trajectory is then partial). ``external_load`` is the number of cores
    that processes outside the study kept busy on average while the run stepped (:class:`_ExternalLoad`;
    NaN where /proc is missing). ``warnings`` holds the distinct warnings the run raised ("Category: message";
    recorded, not printed, so that they do not garble progress bars: :func:`warning_summary`), and
    ``cycled_steps`` the Newton steps accepted on contacts switching between iterates (0 for the warped step)."""

    scene: str
    element: str
    cells: Cells
    duration: float
    dt: float
    method: str
    times: np.ndarray
    values: np.ndarray
    elements: int
    nodes: int
    dofs: int
    steps: int
    median_ms_per_step: float
    median_cpu_ms_per_step: float
    peak_mem_mb: float
    wall_s: float
    status: str = "ok"
    meta: dict = field(default_factory=dict)
    external_load: float = math.nan
    scheme: str = "warped"
    warnings: list[str] = field(default_factory=list)
    cycled_steps: int = 0
    material: str = ""  # Material.tag: '' for the scene's own

    @property
    def key(self) -> str:
        return f"{self.element}_{cells_text(self.cells)}"

    @property
    def cost_ms(self) -> float:
        """Cost per step for ranking [ms] (:func:`step_cost_ms`)."""
        return step_cost_ms(self.median_ms_per_step, self.median_cpu_ms_per_step)

    def summary(self) -> dict:
        d = asdict(self)
        d.pop("times"), d.pop("values")
        d["cells"] = list(self.cells)
        return d

    def save(self, path: Path) -> None:
        save_cached_run(path, self.times, self.values, self.summary(), FORMAT)

    @classmethod
    def load(cls, path: Path) -> "RunResult":
        times, values, meta = load_cached_run(path, FORMAT)
        meta["cells"] = tuple(meta["cells"])
        return cls(times=times, values=values, **meta)


def save_cached_run(path: Path, times: np.ndarray, values: np.ndarray, meta: dict, version: int) -> None:
    """Write a cached run (times, values and a JSON ``meta`` tagged with the cache ``version``) to ``path``
    (.npz) atomically: a run cut short leaves no half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, times=times, values=values, meta=np.array(json.dumps({"format": version, **meta})))
    os.replace(tmp, path)


def load_cached_run(path: Path, version: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """(times, values, meta) of a run cached by :func:`save_cached_run`; ValueError if it has another version."""
    with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f["meta"]))
        times, values = f["times"].copy(), f["values"].copy()
    if meta.pop("format", None) != version:
        raise ValueError(f"{path}: cached run of another format")
    return times, values, meta


def pin_threads(n: int = 1) -> None:
    """Pin BLAS, MKL (PARDISO) and OpenMP to ``n`` threads in this process, for reproducible results.

    Environment variables act on libraries loaded later (and on child processes); MKL is also set at run
    time (softbody.linsolve.set_threads does both)."""
    from softbody import linsolve

    linsolve.set_threads(n)


def _rss_bytes() -> int:
    """Current resident set size of this process [bytes]."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):  # no /proc: fall back to the lifetime peak
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return int(r if sys.platform == "darwin" else r * 1024)


def _release_memory() -> None:
    gc.collect()
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)


class _PeakRss:
    """Context manager sampling the RSS every ``interval`` s in a thread; ``.increase`` [bytes] is the
    peak over the block minus the RSS at its start (after a garbage collection and malloc_trim)."""

    def __init__(self, interval: float = 0.005):
        self.interval = interval
        self.increase = 0

    def __enter__(self) -> "_PeakRss":
        _release_memory()
        self.base = self.peak = _rss_bytes()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, _rss_bytes())

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())
        self.increase = self.peak - self.base


_STUDY_ROOT: int | None = None  # the study's main process, in a local worker (set by _init_worker)


def _machine_busy_seconds() -> float | None:
    """CPU time [s] the whole machine spent busy since boot (all cores; steal counts: cores taken from us),
    from /proc/stat; None without it."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    user, nice, system, idle, iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def _tree_cpu_seconds(root: int) -> float:
    """CPU time [s] (user + system) of process ``root`` and all its descendants, from /proc/<pid>/stat."""
    parent, cpu = {}, {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat") as f:
                rest = f.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
        except (OSError, IndexError):
            continue
        pid = int(entry.name)
        parent[pid] = int(rest[1])
        cpu[pid] = int(rest[11]) + int(rest[12])
    children: dict[int, list[int]] = {}
    for pid, ppid in parent.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += cpu.get(pid, 0)
        todo += children.get(pid, [])
    return total / os.sysconf("SC_CLK_TCK")


class _ExternalLoad:
    """Context manager: ``.cores`` is the number of cores that processes outside the study kept busy on
    average over the block, the machine's busy CPU time minus that of the study's processes (its main
    process and all its descendants: the workers) over the wall time; NaN without /proc."""

    def __enter__(self) -> "_ExternalLoad":
        self.cores = math.nan
        self.root = _STUDY_ROOT or os.getpid()
        self.busy = _machine_busy_seconds()
        if self.busy is not None:
            self.own = _tree_cpu_seconds(self.root)
        self.wall = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        wall = time.perf_counter() - self.wall
        busy = _machine_busy_seconds()
        if busy is None or self.busy is None or wall <= 0:
            return
        own = _tree_cpu_seconds(self.root) - self.own
        self.cores = max(0.0, (busy - self.busy - own) / wall)


_WARM: set[str] = set()


def _warm_up(scene: str) -> None:
    """Load the libraries a run of ``scene`` touches (MKL, pybullet, lazily imported modules) once per
    process, so that neither the first run's memory nor its time pays for them."""
    if scene in _WARM:
        return
    from .scenes import build_scene

    for ladder in LADDERS.get(scene, {}).values():
        for element, rungs in ladder.rungs.items():
            s = build_scene(scene, element=element, cells=rungs[0])
            try:
                s.world.run(2 * s.world.dt)
            finally:
                s.world.close()
        break
    _WARM.add(scene)


def default_method() -> str:
    """The linear solve softbody.Simulation uses by default ("direct" where it has no choice)."""
    import inspect

    from softbody import Simulation

    p = inspect.signature(Simulation.__init__).parameters.get("method")
    return "direct" if p is None or p.default is inspect.Parameter.empty else str(p.default)


StepReport = Callable[[str, int, int], object]  # (run key, steps done, steps in all)
STEP_REPORT_S = 0.5  # a run reports its steps at most this often [s] (and at its last step)
_STEP_SINK: StepReport | None = None  # in a local worker: puts the reports on the study's queue (_init_worker)


def run_configuration(scene: str, element: str, cells: Sequence[int], duration: float | None = None,
                      dt: float = 0.01, method: str | None = None, threads: int | None = 1,
                      scheme: str = "warped", on_step: StepReport | None = None,
                      material: Material | None = None) -> RunResult:
    """Build ``scene`` with ``element`` and ``cells``, run it for ``duration`` [s] (default: the scene's)
    with step ``dt`` [s] and the step's ``scheme`` ("warped" or "newton"), and return its monitored
    trajectory, sizes, cost and peak memory.

    method: the step's linear solve, one of softbody.Simulation's methods (:func:`solve_methods`: "direct"
    factorises every step, as the paper did; "iterative" is preconditioned CG), or None for the
    Simulation's default (:func:`default_method`).
    A pure function of its arguments, for worker processes: the same inputs give bit-identical
    trajectories in any process, local or remote (one BLAS / MKL thread; both methods are deterministic).
    ``threads`` pins BLAS / MKL / OpenMP for the process (None leaves them as they are).
    ``on_step(key, done, total)`` hears of the steps made, at most every STEP_REPORT_S seconds (outside the
    timed part of a step); in a local worker of :func:`open_executor` with a step queue they go to the queue.
    Warnings raised by the run are recorded in the result (``warnings``), not shown. ``material``: the body's E, nu
    and elastic model (:class:`Material`; None: the scene's own)."""
    from .scenes import build_scene

    material = material or Material()
    material.check_scheme(scheme)
    method = default_method() if method is None else method
    if method not in solve_methods():
        raise InvalidInputError(f"method must be one of {solve_methods()}, got {method!r}")
    if threads is not None:
        pin_threads(threads)
    cells = tuple(int(c) for c in cells)
    report = on_step if on_step is not None else _STEP_SINK
    key = f"{element}_{cells_text(cells)}"
    with warnings.catch_warnings(record=True) as caught:
        _warm_up(scene)
        wall = time.perf_counter()
        steps_ms: list[float] = []
        cpu_ms: list[float] = []
        status = "ok"
        with _PeakRss() as mem:
            sc = build_scene(scene, element=element, cells=cells, dt=dt, scheme=scheme, **material.options())
            try:
                sim = sc.world.sim
                if hasattr(sim, "method"):
                    sim.method = method
                elif method != "direct":
                    raise InvalidInputError(f"this softbody's Simulation has no {method!r} method")
                body = sc.body
                duration = float(sc.duration if duration is None else duration)
                ts, xs = [sc.world.t], [sc.monitored()]
                tic = [0.0, 0.0]
                total = int(round(duration / sc.world.dt))
                reported = [time.perf_counter()]

                def callback(world) -> None:
                    toc, ctoc = time.perf_counter(), time.thread_time()
                    steps_ms.append(1e3 * (toc - tic[0]))
                    cpu_ms.append(1e3 * (ctoc - tic[1]))
                    ts.append(world.t)
                    xs.append(sc.monitored())
                    if report is not None and (toc - reported[0] >= STEP_REPORT_S or len(steps_ms) == total):
                        report(key, len(steps_ms), total)
                        reported[0] = toc
                    tic[0], tic[1] = time.perf_counter(), time.thread_time()

                try:
                    with _ExternalLoad() as load:
                        tic[0], tic[1] = time.perf_counter(), time.thread_time()
                        sc.world.run(duration, callback)
                except (SimulationDiverged, SolverError) as exc:
                    status = f"{type(exc).__name__}: {exc}"
                result = RunResult(
                    scene=scene, element=element, cells=cells, duration=duration, dt=float(sc.world.dt), method=method,
                    times=np.array(ts), values=np.array(xs), elements=int(body.mesh.n_elements),
                    nodes=int(body.mesh.n_nodes), dofs=int(3 * (~body.supported()).sum()), steps=len(steps_ms),
                    median_ms_per_step=float(np.median(steps_ms)) if steps_ms else math.nan,
                    median_cpu_ms_per_step=float(np.median(cpu_ms)) if cpu_ms else math.nan,
                    peak_mem_mb=0.0, wall_s=0.0, status=status, external_load=load.cores, scheme=scheme,
                    meta={"monitor": int(sc.monitor), "axis": "xyz"[sc.axis],
                          "monitor_rest": [float(v) for v in body.rest[sc.monitor]]},
                    cycled_steps=int(getattr(getattr(sim, "newton", None), "cycled_steps", 0) or 0),
                    material=material.tag)
            finally:
                sc.world.close()
    result.warnings = list(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))[:20]
    result.peak_mem_mb = mem.increase / 2**20
    result.wall_s = time.perf_counter() - wall
    return result


# ---------------------------------------------------------------------------------------- metric
def rms_error(times: np.ndarray, values: np.ndarray, ref_times: np.ndarray, ref_values: np.ndarray) -> float:
    """RMS difference [m] of a trajectory against the reference, over the run's samples within the
    reference's time span (the reference is linearly interpolated; with the same dt the grids coincide
    and no interpolation happens)."""
    times, values = np.asarray(times, float), np.asarray(values, float)
    inside = (times >= ref_times[0] - 1e-9) & (times <= ref_times[-1] + 1e-9)
    if not inside.any():
        raise InvalidInputError("the run and the reference share no time span")
    ref = np.interp(times[inside], ref_times, ref_values)
    return float(np.sqrt(np.mean((values[inside] - ref) ** 2)))


# ---------------------------------------------------------------------------------------- executors
@contextlib.contextmanager
def environ(**values: str) -> Iterator[None]:
    """Set environment variables inside the block, restore them after (for spawning workers)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _InProcessExecutor(cf.Executor):
    """Runs each submitted call at once in this process (``workers=0``)."""

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller through the future
            fut.set_exception(exc)
        return fut


def _init_worker(steps=None) -> None:
    """A local worker's start: one BLAS thread, the study's process noted, run step reports to the queue
    ``steps`` (a multiprocessing queue, or None)."""
    global _STUDY_ROOT, _STEP_SINK
    pin_threads(1)
    parent = _STUDY_ROOT = os.getppid()
    if steps is not None:
        _STEP_SINK = lambda key, done, total: steps.put((key, done, total))  # noqa: E731

    def watch() -> None:  # a killed study must not leave its workers running
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


@contextlib.contextmanager
def open_executor(workers: int | None = None, cluster=None, step_queue: bool = False) -> Iterator[cf.Executor]:
    """A ``concurrent.futures.Executor`` running study runs.

    cluster None: ``workers`` local processes (default 1: one run at a time, as fast as two on a 2-core machine
    and with timings no other run disturbs), started fresh (spawn) with one BLAS / MKL / OpenMP thread each; a script calling this needs the ``if __name__ == "__main__":``
    guard of multiprocessing. ``workers=0``: run in this process, one run at a time (pins its threads). cluster an address (``tcp://host:8786``) or a
    ``distributed.Client``: the Dask cluster's workers, through ``Client.get_executor``; they need
    softbody installed. Either way, results come back as futures of :class:`RunResult`.
    step_queue: local worker processes report the steps of their runs (:func:`run_configuration`'s
    ``on_step``) as (key, done, total) on a multiprocessing queue, the executor's ``step_queue`` attribute
    (None elsewhere: in this process pass ``on_step``; Dask workers report nothing)."""
    if cluster is None and workers == 0:
        ex = _InProcessExecutor()
        ex.step_queue = None
        yield ex
        return
    if cluster is None:
        import multiprocessing

        n = workers or 1
        ctx = multiprocessing.get_context("spawn")
        steps = ctx.Queue() if step_queue else None
        # (no MALLOC_MMAP_THRESHOLD_ here: mapping every array over 64 KB afresh turned each step's large
        # temporaries into page faults and doubled the time per step; a reused worker's memory is
        # trimmed before each run instead, see _PeakRss)
        env = {var: "1" for var in THREAD_ENV}
        with environ(**env):
            ex = cf.ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_worker, initargs=(steps,))
            ex.step_queue = steps
            try:
                yield ex
            finally:
                ex.shutdown(wait=True, cancel_futures=True)
                if steps is not None:
                    steps.close()
        return
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - the dependency is declared
        raise InvalidInputError('--cluster needs Dask distributed: pip install "dask[distributed]"') from exc
    client = cluster if isinstance(cluster, Client) else Client(cluster)
    try:
        ex = client.get_executor(pure=False)
        ex.step_queue = None
        try:
            yield ex
        finally:
            ex.shutdown(wait=True)
    finally:
        if client is not cluster:
            client.close()


# ---------------------------------------------------------------------------------------- the study
@dataclass
class Study:
    """The runs of a study (ladder rungs and reference), with their errors; see :func:`run_study`."""

    scene: str
    out: Path
    runs: list[RunResult]
    reference: RunResult
    errors: dict[str, float]
    executed: list[str] = field(default_factory=list)  # keys run by this call (the rest came from the cache)

    def rows(self) -> list[dict]:
        rows = []
        for r in self.runs + [self.reference]:
            role = "reference" if r is self.reference else "ladder"
            rows.append({
                "scene": self.scene, "role": role, "element": r.element, "cells": cells_text(r.cells),
                "elements": r.elements, "nodes": r.nodes, "dofs": r.dofs, "steps": r.steps,
                "duration_s": r.duration, "dt_s": r.dt, "scheme": r.scheme, "method": r.method,
                "median_ms_per_step": round(r.median_ms_per_step, 4),
                "median_cpu_ms_per_step": round(r.median_cpu_ms_per_step, 4),
                "peak_mem_mb": round(r.peak_mem_mb, 2), "wall_s": round(r.wall_s, 3),
                "error_m": "" if role == "reference" else f"{self.errors[r.key]:.6e}", "status": r.status,
                "external_load": round(r.external_load, 3), "material": r.material})
        return rows

    def run(self, element: str, cells: Sequence[int]) -> RunResult:
        key = f"{element}_{cells_text(cells)}"
        for r in self.runs + [self.reference]:
            if r.key == key:
                return r
        raise KeyError(key)


def _default_duration(scene: str, lad: Ladder) -> float:
    from .scenes import build_scene

    element, rungs = next(iter(lad.rungs.items()))
    sc = build_scene(scene, element=element, cells=rungs[0])
    sc.world.close()
    return float(sc.duration)


def _expected_cost(spec: tuple[str, Cells]) -> float:
    """Rough relative cost of a run (for submitting the longest first): nodes^1.3."""
    element, (a, b, c) = spec
    nodes = {"tet4": (a + 1) * (b + 1) * (c + 1), "hex8": (a + 1) * (b + 1) * (c + 1),
             "tet10": (2 * a + 1) * (2 * b + 1) * (2 * c + 1) - a * b * c}[element]
    return nodes ** 1.3


NEWTON_CYCLE_WARNING = "RuntimeWarning: Newton's step"  # how softbody.newton's warning on an accepted cycle starts


def warning_summary(runs: Sequence[RunResult]) -> list[str]:
    """Lines ("# ...") saying what ``runs`` warned about, for after a progress bar: the Newton steps accepted on
    contacts switching between iterates (counted per run), and each other distinct warning with its runs."""
    lines = []
    cycled = [r for r in runs if r.cycled_steps]
    if cycled:
        n = sum(r.cycled_steps for r in cycled)
        lines.append(f"# {n} Newton step{'s' if n != 1 else ''} accepted on contacts switching between iterates "
                     f"(residual above the Newton tolerance, as softbody.newton allows) in {len(cycled)} "
                     f"run{'s' if len(cycled) != 1 else ''}: "
                     + ", ".join(f"{r.key} ({r.scheme}, dt {r.dt:g} s): {r.cycled_steps}" for r in cycled)
                     + "; a smaller dt lets them converge")
    others: dict[str, list[str]] = {}
    for r in runs:
        for w in r.warnings:
            if not (r.cycled_steps and w.startswith(NEWTON_CYCLE_WARNING)):
                others.setdefault(w, []).append(f"{r.key} ({r.scheme}, dt {r.dt:g} s)")
    lines += [f"# warning in {', '.join(keys)}: {w}" for w, keys in others.items()]
    return lines


def run_study(scene: str, out: str | Path, elements: Iterable[str] | None = None, ladder: str | Ladder = "full",
              duration: float | None = None, dt: float = 0.01, method: str | None = None,
              workers: int | None = None, cluster=None,
              force: bool = False, progress: bool = True, plots: bool = True, scheme: str = "warped",
              label: str | None = None, material: Material | None = None) -> Study:
    """Run (or load from ``out``'s cache) the ladder of ``scene`` for ``elements`` and its reference, then
    write results.csv, table.md and the plots to ``out``. ``duration`` overrides the ladder's; ``method``
    is the linear solve, ``scheme`` the step (see :func:`run_configuration`); ``force``
    reruns cached runs; ``workers`` / ``cluster`` choose where runs go (see :func:`open_executor`).

    progress: a tqdm bar on stderr named ``label`` (default "study SCENE (SCHEME, dt DT s)") counting the runs,
    with the steps of the runs in flight (local workers and workers=0; a Dask cluster's runs only tick the
    clock); the warnings the runs raised are summarised after it (:func:`warning_summary`), and emitted as
    one warning without a bar. ``material``: the runs' E, nu and elastic model (:class:`Material`; None: the scene's
    own), recorded with each run (a cached run of another material is run again)."""
    from .scenes import SCENES

    material = material or Material()
    if scene not in SCENES:
        raise InvalidInputError(f"unknown scene {scene!r}; available: {sorted(SCENES)}")
    lad = ladder if isinstance(ladder, Ladder) else get_ladder(scene, ladder)
    elements = list(ELEMENTS if elements is None else elements)
    bad = [e for e in elements if e not in lad.rungs]
    if bad or not elements:
        raise InvalidInputError(f"elements {bad or elements} not in the ladder; valid: {sorted(lad.rungs)}")
    method = default_method() if method is None else method
    if method not in solve_methods():
        raise InvalidInputError(f"method must be one of {solve_methods()}, got {method!r}")
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise InvalidInputError(f"dt must be a finite number > 0 [s], got {dt!r}")
    if scheme not in SCHEMES:
        raise InvalidInputError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    material.check_scheme(scheme)
    if duration is None:
        duration = lad.duration if lad.duration is not None else _default_duration(scene, lad)
    duration = float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise InvalidInputError(f"duration must be a finite number > 0 [s], got {duration!r}")
    out = Path(out)
    specs: list[tuple[str, Cells]] = [(e, tuple(c)) for e in elements for c in lad.rungs[e]]
    ref_spec = (lad.reference[0], tuple(lad.reference[1]))
    todo = specs + ([ref_spec] if ref_spec not in specs else [])

    results: dict[tuple[str, Cells], RunResult] = {}
    pending = []
    for spec in todo:
        path = out / "trajectories" / f"{spec[0]}_{cells_text(spec[1])}.npz"
        cached = None
        if path.exists() and not force:
            with contextlib.suppress(Exception):
                cached = RunResult.load(path)
            if cached is not None and (cached.scene != scene or cached.duration != duration or cached.dt != dt
                                       or cached.method != method or cached.scheme != scheme
                                       or cached.material != material.tag):
                cached = None  # a run that stopped early (status) is a deterministic result: kept
        if cached is None:
            pending.append(spec)
        else:
            results[spec] = cached

    executed = []
    if pending:
        pending.sort(key=_expected_cost, reverse=True)  # longest first: the pool ends together
        bar = None
        running: dict[str, tuple[int, int]] = {}  # run key -> (steps done, steps in all), runs in flight
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(pending), desc=label or f"study {scene} ({scheme}, dt {dt:g} s"
                       + (f", {material.tag})" if material.tag else ")"), unit="run",
                       file=sys.stderr)

        def show(*first: str, refresh: bool = True) -> None:
            if bar is not None:
                bar.set_postfix_str(", ".join(list(first) + [f"{k} step {d}/{t}" for k, (d, t) in running.items()]),
                                    refresh=refresh)

        def on_step(key: str, done: int, total: int) -> None:
            if key not in executed:  # (a report still queued when its run returned)
                running[key] = (done, total)
                show()

        def finish(fut: cf.Future, spec: tuple[str, Cells]) -> None:
            res = fut.result()
            res.save(out / "trajectories" / f"{res.key}.npz")
            results[spec] = res
            executed.append(res.key)
            running.pop(res.key, None)
            if bar is not None:
                show(f"{res.key} {res.median_ms_per_step:.1f} ms/step", refresh=False)
                bar.update()

        try:
            with open_executor(workers, cluster, step_queue=bar is not None) as ex:
                args = (duration, dt, method, 1, scheme)
                if isinstance(ex, _InProcessExecutor):  # one run at a time, here: finished as it returns
                    for e, c in pending:
                        finish(ex.submit(run_configuration, scene, e, c, *args,
                                         on_step=on_step if bar is not None else None, material=material), (e, c))
                futures = {ex.submit(run_configuration, scene, e, c, *args, material=material): (e, c)
                           for e, c in pending if (e, c) not in results}
                waiting, steps = set(futures), ex.step_queue
                while waiting:
                    done, waiting = cf.wait(waiting, timeout=STEP_REPORT_S, return_when=cf.FIRST_COMPLETED)
                    while steps is not None:
                        try:
                            on_step(*steps.get_nowait())
                        except queue.Empty:
                            break
                    for fut in done:
                        finish(fut, futures[fut])
                    if bar is not None and not done:
                        bar.refresh()  # the clock ticks while a long run has nothing new to say
        finally:
            if bar is not None:
                bar.close()
        notes = warning_summary([results[s] for s in pending if s in results])
        if notes and progress:
            print("\n".join(notes), file=sys.stderr)
        elif notes:
            warnings.warn(" ".join(n.lstrip("# ") for n in notes), RuntimeWarning, stacklevel=2)

    reference = results[ref_spec]
    if reference.status != "ok":
        raise SolverError(f"the reference run {reference.key} failed: {reference.status}")
    runs = [results[s] for s in specs]
    errors = {r.key: (rms_error(r.times, r.values, reference.times, reference.values) if r.status == "ok"
                      else math.inf) for r in runs}
    study = Study(scene, out, runs, reference, errors, executed)
    write_results(study, lad)
    if plots:
        write_plots(study)
    return study


# ---------------------------------------------------------------------------------------- outputs
def write_results(study: Study, ladder: Ladder | None = None) -> None:
    out = study.out
    out.mkdir(parents=True, exist_ok=True)
    rows = study.rows()
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    ref = study.reference
    axis = ref.meta.get("axis", "?")
    lines = [f"# Study: {study.scene}", "",
             f"Monitored: {axis} of node {ref.meta.get('monitor')} "
             f"(rest {[round(v, 6) + 0.0 for v in ref.meta.get('monitor_rest', [])]}), "
             f"{ref.duration:g} s at dt = {ref.dt:g} s, {ref.method} linear solves.",
             f"Reference: {ref.element} cells {cells_text(ref.cells)} ({ref.elements} elements, {ref.nodes} nodes).",
             "Error: RMS difference of the monitored coordinate against the reference over the common time "
             "grid, in metres (shown in mm).",
             "Cost: median wall-clock ms per step of World.step (collision, soft step with contacts, rigid step); "
             "memory: peak increase of the worker's resident memory while building and running the scene "
             "(a pybullet connection alone is about 28 MiB).", ""]
    if ladder is not None and ladder.note:
        lines += [f"Ladder: {ladder.note}.", ""]
    load = [r.external_load for r in study.runs + [study.reference] if not math.isnan(r.external_load)]
    if load and float(np.median(load)) > 2 * BUSY_CORES:
        lines += [f"**Loaded machine**: processes outside the study kept {float(np.median(load)):.1f} cores busy "
                  f"(median over runs, of {os.cpu_count()}): where a run waited for a core (*), its ms/step is "
                  "inflated and CPU ms/step is the steadier figure. Rerun on a quiet machine (--force).", ""]
    lines += ["| element | cells | elements | nodes | DOFs | ms/step | CPU ms/step | peak MiB | error [mm] |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        err = "reference" if row["role"] == "reference" else f"{1e3 * float(row['error_m']):.3f}"
        if row["status"] != "ok":
            err += f" ({row['status']})"
        busy = shared_core(row["median_ms_per_step"], row["median_cpu_ms_per_step"], row["external_load"])
        lines.append(f"| {row['element']} | {row['cells']} | {row['elements']} | {row['nodes']} | {row['dofs']} | "
                     f"{row['median_ms_per_step']:.1f}{' *' if busy else ''} | {row['median_cpu_ms_per_step']:.1f} | "
                     f"{row['peak_mem_mb']:.1f} | {err} |")
    if any(shared_core(row["median_ms_per_step"], row["median_cpu_ms_per_step"], row["external_load"]) for row in rows):
        lines += ["", f"\\* wall-clock time more than {WAITED}x the CPU time while processes outside the study kept "
                      f"more than {BUSY_CORES} core busy: the run shared its core with other work; it is ranked by its "
                      "CPU time."]
    lines += equal_fidelity_lines(study)
    (out / "table.md").write_text("\n".join(lines) + "\n")


def equal_fidelity(study: Study, base: str = "tet4") -> list[dict]:
    """For each rung of ``base`` (as a tolerance: its error), the cheapest run of every element type whose
    error is within it: the paper's "efficiency at equal fidelity" (ratio of ms per step)."""
    ok = [r for r in study.runs if r.status == "ok"]
    out = []
    for b in sorted((r for r in ok if r.element == base), key=lambda r: r.nodes):
        tol = study.errors[b.key]
        row = {"tolerance_m": tol, "base": b.key, "cheapest": {}}
        for e in ELEMENTS:
            within = [r for r in ok if r.element == e and study.errors[r.key] <= tol]
            if within:
                row["cheapest"][e] = min(within, key=lambda r: r.cost_ms)
        out.append(row)
    return out


def equal_fidelity_lines(study: Study) -> list[str]:
    rows = equal_fidelity(study)
    elements = [e for e in ELEMENTS if any(r.element == e for r in study.runs)]
    if not rows or "tet4" not in elements:
        return []
    lines = ["", "Speed at equal fidelity: for each tet4 rung's error as a tolerance, the cheapest run of each "
                 "element type within it (cells, ms/step), and how many times faster than the cheapest tet4 run.", "",
             "| tolerance [mm] (tet4 rung) | " + " | ".join(elements) + " | "
             + " | ".join(f"tet4 / {e}" for e in elements if e != "tet4") + " |",
             "|---|" + "---|" * (2 * len(elements) - 1)]
    for row in rows:
        ch = row["cheapest"]
        cells = [f"{cells_text(ch[e].cells)}, {ch[e].cost_ms:.1f}" if e in ch else "-" for e in elements]
        ratios = [f"{ch['tet4'].cost_ms / ch[e].cost_ms:.1f}x" if e in ch else "-"
                  for e in elements if e != "tet4"]
        lines.append(f"| {1e3 * row['tolerance_m']:.3f} ({row['base'].split('_')[1]}) | " + " | ".join(cells)
                     + " | " + " | ".join(ratios) + " |")
    return lines


COLORS = {"tet4": "tab:blue", "hex8": "tab:orange", "tet10": "tab:green"}
MARKERS = {"tet4": "o", "hex8": "s", "tet10": "^"}


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # no pyplot: no global backend change
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _log_axes(ax) -> None:
    """Log-log axes with plain-number tick labels (2, 50, 0.5; never 4x10^0): at 1, 2, 5 x 10^k, at 10^k only
    on an axis of more than four decades (the labels would run into each other), or at every integer multiple of
    10^k on an axis too short for two of those. Call it after plotting."""
    from matplotlib import ticker

    ax.set_xscale("log")
    ax.set_yscale("log")
    plain = ticker.FuncFormatter(lambda v, _: f"{v:g}")
    for axis in (ax.xaxis, ax.yaxis):
        lo, hi = sorted(axis.get_view_interval())
        locator = ticker.LogLocator(subs=(1.0,) if hi > 1e4 * lo > 0 else (1.0, 2.0, 5.0))
        if sum(lo <= t <= hi for t in locator.tick_values(lo, hi)) < 2:
            locator = ticker.LogLocator(subs=tuple(range(1, 10)))
        axis.set_major_locator(locator)
        axis.set_major_formatter(plain)
        axis.set_minor_formatter(ticker.NullFormatter())
    ax.grid(alpha=0.3, which="both")


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points (cost, error) not dominated by another (cheaper and no worse, or no dearer
    and better), sorted by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def write_plots(study: Study) -> list[Path]:
    """trajectories.png (Figures 8 / 9 of the paper), time_vs_nodes.png (Figure 10), pareto.png."""
    import matplotlib.cm as cm

    out, ref = study.out, study.reference
    axis = ref.meta.get("axis", "?")
    elements = [e for e in ELEMENTS if any(r.element == e for r in study.runs)]
    paths = []

    fig = _figure(4.2 * len(elements), 5.2)
    axes = fig.subplots(1, len(elements), sharey=True, squeeze=False)[0]
    for ax, e in zip(axes, elements):
        runs = sorted((r for r in study.runs if r.element == e), key=lambda r: r.nodes)
        for k, r in enumerate(runs):
            c = cm.viridis(k / max(1, len(runs) - 1) * 0.9)
            ax.plot(r.times, r.values, color=c, lw=1.2, label=f"{cells_text(r.cells)} ({r.elements}, {r.nodes})")
        ax.plot(ref.times, ref.values, "k--", lw=1.0,
                label=f"reference {ref.element} {cells_text(ref.cells)} ({ref.elements}, {ref.nodes})")
        ax.set_title(f"{e}")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, title="cells (#elements, #nodes)", title_fontsize=7, ncol=2,
                  loc="upper center", bbox_to_anchor=(0.5, -0.16))
    axes[0].set_ylabel(f"monitored {axis} [m]")
    fig.suptitle(f"{study.scene}: monitored node per resolution")
    paths.append(out / "trajectories.png")
    fig.savefig(paths[-1])

    fig = _figure(5.5, 4.2)
    ax = fig.subplots()
    for e in elements:
        runs = sorted((r for r in study.runs if r.element == e), key=lambda r: r.nodes)
        ax.plot([r.nodes for r in runs], [r.cost_ms for r in runs], marker=MARKERS[e],
                  color=COLORS[e], label=e)
    ax.set_xlabel("nodes")
    ax.set_ylabel("median ms per step (CPU if it waited for a core)")
    ax.set_title(f"{study.scene}: cost per step against nodes")
    _log_axes(ax)
    ax.legend()
    paths.append(out / "time_vs_nodes.png")
    fig.savefig(paths[-1])

    fig = _figure(5.5, 4.2)
    ax = fig.subplots()
    ok = [r for r in study.runs if math.isfinite(study.errors[r.key]) and study.errors[r.key] > 0]
    for e in elements:
        runs = sorted((r for r in ok if r.element == e), key=lambda r: r.nodes)
        ax.plot([r.cost_ms for r in runs], [1e3 * study.errors[r.key] for r in runs],
                  marker=MARKERS[e], color=COLORS[e], label=e, lw=0.8)
        for r in runs:
            ax.annotate(cells_text(r.cells), (r.cost_ms, 1e3 * study.errors[r.key]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
    if ok:
        pts = [(r.cost_ms, study.errors[r.key]) for r in ok]
        front = pareto_front(pts)
        ax.step([pts[i][0] for i in front], [1e3 * pts[i][1] for i in front], where="post", color="k",
                lw=1.5, alpha=0.35, label="Pareto front")
    ax.set_xlabel("median ms per step (CPU if it waited for a core)")
    ax.set_ylabel(f"RMS error of {axis} vs reference [mm]")
    ax.set_title(f"{study.scene}: error against cost")
    _log_axes(ax)
    ax.legend()
    paths.append(out / "pareto.png")
    fig.savefig(paths[-1])
    return paths


# ---------------------------------------------------------------------------------------- reading back
def read_results(study_dir: str | Path) -> list[dict]:
    """The rows of DIR/results.csv (or of a results file given by its path, ending in .csv), numbers converted
    (error_m is NaN for the reference)."""
    path = Path(study_dir)
    path = path if path.suffix == ".csv" else path / "results.csv"
    if not path.exists():
        raise InvalidInputError(f"no study at {study_dir}: {path} does not exist (run `softbody study` first)")
    rows = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            for k in ("elements", "nodes", "dofs", "steps"):
                row[k] = int(row[k])
            for k in ("duration_s", "dt_s", "median_ms_per_step", "median_cpu_ms_per_step", "peak_mem_mb", "wall_s"):
                row[k] = float(row[k])
            row["error_m"] = float(row["error_m"]) if row["error_m"] else math.nan
            row["external_load"] = float(row.get("external_load") or "nan")  # absent in older studies
            row["scheme"] = row.get("scheme") or "warped"
            row["material"] = row.get("material") or ""  # absent in older studies: the scene's own
            row["cost_ms_per_step"] = step_cost_ms(row["median_ms_per_step"], row["median_cpu_ms_per_step"])
            rows.append(row)
    return rows


def load_trajectory(study_dir: str | Path, element: str, cells: Sequence[int]) -> RunResult:
    return RunResult.load(Path(study_dir) / "trajectories" / f"{element}_{cells_text(cells)}.npz")


@dataclass
class Recommendation:
    """The cheapest ladder configuration within ``tolerance`` [m] and every candidate, cheapest first;
    ``reference`` is the row of the run the errors are measured against (None if it is not a row), ``basis``
    says what the errors are (against what, which discretisation error), ``source`` where rows and costs
    come from."""

    scene: str
    tolerance: float
    candidates: list[dict]
    choice: dict | None
    reference: dict | None = None
    basis: str = ""
    source: str = ""

    def table(self) -> str:
        lines = [f"| rank | element | cells | nodes | scheme | dt [s] | ms/step (CPU if it waited) | ms per simulated s "
                 f"| peak MiB | error [mm] | within {1e3 * self.tolerance:g} mm |",
                 "|---:|---|---|---:|---|---:|---:|---:|---:|---:|---|"]
        for i, row in enumerate(self.candidates, 1):
            ok = row["error_m"] <= self.tolerance
            mark = " **<- recommended**" if row is self.choice else ""
            lines.append(f"| {i} | {row['element']} | {row['cells']} | {row['nodes']} | {row['scheme']} | {row['dt_s']:g} "
                         f"| {row['cost_ms_per_step']:.1f} | {row['cost_ms_per_s']:.0f} | {row['peak_mem_mb']:.1f} "
                         f"| {1e3 * row['error_m']:.3f} | {'yes' if ok else 'no'}{mark} |")
        return "\n".join(lines)


class NoConfigurationWithinTolerance(InvalidInputError):
    """No configuration of the study has an error within the requested tolerance."""

    def __init__(self, message: str, recommendation: Recommendation):
        super().__init__(message)
        self.recommendation = recommendation


def _tolerance(tolerance: float) -> float:
    tolerance = float(tolerance)
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise InvalidInputError(f"tolerance must be a finite length > 0 [m], got {tolerance!r}")
    return tolerance


def spatial_basis(reference: dict, monitored: str | None = None) -> str:
    """What the errors of a one-scheme, one-dt study are: the RMS against its reference row [m], run at the same
    scheme and dt as every rung, so the spatial discretisation error alone; ``monitored`` names the coordinate."""
    what = f"the monitored trajectory ({monitored})" if monitored else "the monitored trajectory"
    return (f"RMS difference of {what} over {reference['duration_s']:g} s against the reference "
            f"{reference['element']} {reference['cells']} ({reference['scheme']}, dt {reference['dt_s']:g} s), run at "
            f"the same scheme and dt as every row: the spatial discretisation error at that scheme and dt (backward "
            f"Euler's time discretisation error is not in it: --schemes/--dts weigh the time step)")


def recommend(study_dir: str | Path, tolerance: float, scene: str | None = None,
              elements: Sequence[str] | None = None, *, where: str | None = None,
              monitored: str | None = None) -> Recommendation:
    """The cheapest configuration (lowest :func:`step_cost_ms`: median wall ms per step, CPU ms for a run that
    waited for a core) of a study (a directory with results.csv, or a results file) whose error is <=
    ``tolerance`` [m], among ``elements`` (None: all). Raises :class:`NoConfigurationWithinTolerance` (with the
    table) if none qualifies. ``where`` names the study in messages and ``source`` (default "the study at
    DIR"); ``monitored`` names the coordinate in ``basis``."""
    tolerance = _tolerance(tolerance)
    rows = read_results(study_dir)
    scenes = {r["scene"] for r in rows}
    if scene is not None and scenes != {scene}:
        raise InvalidInputError(f"the study at {study_dir} is of {sorted(scenes)}, not {scene!r}")
    ladder = [r for r in rows if r["role"] == "ladder"]
    if elements is not None:
        bad = sorted(set(elements) - {r["element"] for r in ladder})
        if bad:
            raise InvalidInputError(f"elements {bad} are not in the study at {study_dir}; it has "
                                    f"{sorted({r['element'] for r in ladder})}")
        ladder = [r for r in ladder if r["element"] in elements]
    reference = next((r for r in rows if r["role"] == "reference"), None)
    where = where or f"the study at {study_dir}"
    return _cheapest(rows[0]["scene"], tolerance, ladder, where, reference=reference,
                     basis=spatial_basis(reference, monitored) if reference else "", source=where)


def _cheapest(scene: str, tolerance: float, rows: list[dict], where: str, hint: str | None = None,
              **about) -> Recommendation:
    """The Recommendation of ``rows`` (ladder runs with error_m, cost_ms_per_step, dt_s): the cheapest per
    simulated second within ``tolerance`` [m]; ``about``: its reference, basis and source. ``hint`` ends the
    message when none qualifies (default: refine the ladder or loosen the tolerance)."""
    for r in rows:
        r["cost_ms_per_s"] = r["cost_ms_per_step"] / r["dt_s"]
    candidates = sorted((r for r in rows if r["status"] == "ok"), key=lambda r: (r["cost_ms_per_s"], r["error_m"]))
    within = [r for r in candidates if r["error_m"] <= tolerance]
    rec = Recommendation(scene, tolerance, candidates, within[0] if within else None, **about)
    if rec.choice is None:
        best = min(candidates, key=lambda r: r["error_m"]) if candidates else None
        text = (f"; the most accurate is {best['element']} {best['cells']} ({best['scheme']}, dt {best['dt_s']:g} s) at "
                f"{1e3 * best['error_m']:.3f} mm" if best else "")
        text += f" ({hint or 'refine the ladder or loosen the tolerance'})"
        raise NoConfigurationWithinTolerance(
            f"no configuration of {where} is within {1e3 * tolerance:g} mm{text}\n{rec.table()}", rec)
    return rec


# ---------------------------------------------------------------------------------------- shipped studies
DATA = Path(__file__).with_name("data")  # package data: the published studies' results.csv, <scene>-results.csv


def shipped_results(scene: str) -> Path | None:
    """The shipped results file of ``scene``'s published study (experiments/data/<scene>-results.csv), or None."""
    path = DATA / f"{scene}-results.csv"
    return path if path.is_file() else None


def shipped_scenes() -> list[str]:
    """Scenes with shipped study results."""
    return sorted(p.name[: -len("-results.csv")] for p in DATA.glob("*-results.csv"))


def shipped_source(scene: str) -> dict:
    """Where ``scene``'s shipped results come from: keys published (the file or table they are), measured (date,
    git, machine) and monitored (the coordinate), from experiments/data/sources.json; {} if not listed."""
    path = DATA / "sources.json"
    return dict(json.loads(path.read_text()).get(scene, {})) if path.is_file() else {}


def recommend_shipped(scene: str, tolerance: float, elements: Sequence[str] | None = None) -> Recommendation:
    """:func:`recommend` from the published study of ``scene`` shipped with the package (no run: an answer in
    milliseconds). Errors [m] are against the study's reference at the same scheme and dt (the spatial
    discretisation error); costs are the ms per step of the published run, on the machine that made it."""
    path = shipped_results(scene)
    if path is None:
        raise InvalidInputError(f"no shipped study results for scene {scene!r}; scenes with shipped results: "
                                f"{shipped_scenes()} (run its study here: softbody recommend {scene} --recompute ...)")
    src = shipped_source(scene)
    where = (f"the shipped study results ({src.get('published', f'experiments/data/{path.name}')}; measured "
             f"{src.get('measured', 'at an unrecorded date')}; costs are that run's ms per step)")
    return recommend(path, tolerance, scene=scene, elements=elements, where=where,
                     monitored=src.get("monitored"))


def recommend_steps(scene: str, out: str | Path, tolerance: float, schemes: Sequence[str] = SCHEMES,
                    dts: Sequence[float] = (0.01, 0.02), **study) -> Recommendation:
    """The cheapest configuration -- element type, resolution, scheme and time step -- whose error is within
    ``tolerance`` [m], from one study per scheme and step under ``out``/<scheme>_dt<dt> (run, or loaded from
    their caches, with the options ``study`` of :func:`run_study`). Errors are RMS differences from one
    reference for all: the ladder's reference configuration run with the Newton scheme at half the
    smallest step, so they hold backward Euler's time discretisation error as well as the spatial one;
    costs are per simulated second (ms per step / dt), since a longer step needs fewer.

    With progress (the default) every stage has its named bar: "[i/n] study SCENE (SCHEME, dt DT s)" per
    study, and the reference run its own, in steps; warnings are summarised after each bar."""
    from .scenes import SCENES

    tolerance = _tolerance(tolerance)
    if scene not in SCENES:
        raise InvalidInputError(f"unknown scene {scene!r}; available: {sorted(SCENES)}")
    bad = [s for s in schemes if s not in SCHEMES]
    if bad or not schemes:
        raise InvalidInputError(f"schemes must be among {SCHEMES}, got {list(schemes)!r}")
    if not dts or not all(isinstance(d, (int, float)) and math.isfinite(d) and d > 0 for d in dts):
        raise InvalidInputError(f"dts must be finite steps > 0 [s], got {list(dts)!r}")
    out = Path(out)
    progress = study.get("progress", True)
    combos = [(scheme, float(dt)) for scheme in dict.fromkeys(schemes) for dt in sorted(set(dts))]
    stages = len(combos) + 1
    studies = [run_study(scene, out / f"{scheme}_dt{dt:g}", dt=dt, scheme=scheme,
                         label=f"[{i}/{stages}] study {scene} ({scheme}, dt {dt:g} s)", **study)
               for i, (scheme, dt) in enumerate(combos, 1)]
    lad_ref = studies[0].reference
    ref_dt = min(dts) / 2
    ref_label = f"[{stages}/{stages}] reference {lad_ref.key} (newton, dt {ref_dt:g} s)"
    path = out / f"reference_newton_dt{ref_dt:g}" / f"{lad_ref.key}.npz"
    reference = None
    if path.exists() and not study.get("force"):
        with contextlib.suppress(Exception):
            reference = RunResult.load(path)
        if reference is not None and (reference.duration != lad_ref.duration or reference.scheme != "newton"
                                      or reference.material != (study.get("material") or Material()).tag):
            reference = None
    if reference is None:
        reference = _run_reference(scene, lad_ref, ref_dt, ref_label, progress, study.get("material"))
        reference.save(path)
    elif progress:
        print(f"{ref_label}: from the cache {path}", file=sys.stderr)
    if reference.status != "ok":
        raise SolverError(f"the reference run {reference.key} (newton, dt {ref_dt:g} s) failed: {reference.status}")
    rows = []
    for st in studies:
        for row, r in zip(st.rows(), st.runs):  # rows() lists the ladder runs first, in the same order
            row.update(cost_ms_per_step=r.cost_ms, error_m=(rms_error(r.times, r.values, reference.times,
                                                                      reference.values) if r.status == "ok" else math.inf))
            rows.append(row)
    # the time discretisation error alone: the reference mesh at each scheme and dt against the reference
    time_errors = {(st.reference.scheme, st.reference.dt): rms_error(st.reference.times, st.reference.values,
                                                                     reference.times, reference.values)
                   for st in studies if st.reference.status == "ok"}
    hint = None
    if time_errors:
        hint = ("backward Euler's time discretisation error against this reference, on the reference mesh "
                f"{lad_ref.key}: " + ", ".join(f"{s} dt {d:g} s {1e3 * e:.3f} mm" for (s, d), e in time_errors.items())
                + f"; a tolerance below that needs a smaller dt (--dts {min(dts) / 2:g} ...), or compare meshes "
                "alone (spatial error, without --schemes/--dts)")
    basis = (f"RMS difference of the monitored trajectory over {reference.duration:g} s against the "
             f"reference {reference.element} {cells_text(reference.cells)} (newton, dt {ref_dt:g} s: half the "
             f"smallest step): each error holds backward Euler's time discretisation error at its dt as well as "
             f"the spatial one")
    ref_row = {"element": reference.element, "cells": cells_text(reference.cells), "scheme": "newton",
               "dt_s": reference.dt, "duration_s": reference.duration}
    return _cheapest(scene, tolerance, rows, f"the studies under {out}", hint=hint, reference=ref_row, basis=basis,
                     source=f"the studies under {out} (schemes {', '.join(dict.fromkeys(schemes))}; dt "
                            f"{', '.join(f'{d:g}' for d in sorted(set(dts)))} s), run on this machine")


def _run_reference(scene: str, lad_ref: RunResult, dt: float, label: str, progress: bool,
                   material: Material | None = None) -> RunResult:
    """The Newton reference of :func:`recommend_steps` (``lad_ref``'s configuration at step ``dt`` [s]), run in
    this process, with a bar in steps named ``label`` and its warnings summarised after it."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=int(round(lad_ref.duration / dt)), desc=label, unit="step", file=sys.stderr)

    def on_step(key: str, done: int, total: int) -> None:
        bar.update(done - bar.n)

    try:
        reference = run_configuration(scene, lad_ref.element, lad_ref.cells, lad_ref.duration, dt, lad_ref.method,
                                      scheme="newton", on_step=on_step if bar is not None else None, material=material)
    finally:
        if bar is not None:
            bar.close()
    notes = warning_summary([reference])
    if notes and progress:
        print("\n".join(notes), file=sys.stderr)
    elif notes:
        warnings.warn(" ".join(n.lstrip("# ") for n in notes), RuntimeWarning, stacklevel=3)
    return reference
