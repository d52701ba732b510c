"""Parameter sweeps: one scene run over the full grid of the given parameters, one row of metrics per run.

A *scene* is a canonical scene name (experiments.scenes: sheet-on-sphere, hanging-tube, cantilever, or one
added with register_scene) or the path of a Python file that defines ``scene(**params)`` returning a
``World`` and, optionally, ``monitor(world) -> float`` (a value recorded after every step),
``metrics(world) -> dict`` (extra columns, evaluated once at the end) and ``DURATION`` (its default run
length [s]). The file's text travels with every run, so workers (local processes or a Dask cluster) need
softbody but not the file.

Every run is a pure function of its inputs (:func:`run_point`, one BLAS / MKL thread), so its row is
bit-identical wherever it ran, apart from the timing columns (TIMING). Runs go through the executors of
experiments.study (local worker processes, in this process, or a Dask cluster). A run that fails -- a bad
value, a diverging simulation, an exception in the user's scene -- is a row with its status and error text,
never a crashed sweep.

Layout of a sweep directory (all but runs/ rewritten from the cached runs on every call)::

    DIR/runs/<label>-<hash>.npz        one run: its row and monitored trajectory (the cache; resumable)
    DIR/results.csv                    one row per run: its parameters, then the metrics (COLUMNS), then the
                                       largest contact force on each rigid body, then the user's metrics
    DIR/summary.md                     the grid, failures, the table, and each parameter's effect
    DIR/plots/<param>.png              every metric against that parameter, one line per combination of the others
    DIR/trajectories.png               the monitored value against time, one line per run
    DIR/recordings/<label>-<hash>.rrd  with record=True: a rerun recording of each run made
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import hashlib
import inspect
import itertools
import json
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from softbody.errors import InvalidInputError, SimulationDiverged

FORMAT = 1  # version of the cached run files; bump to invalidate old caches

COLUMNS = ("status", "diverged", "error", "steps", "t_end_s", "dt_s", "ms_per_step", "wall_s", "max_penetration_mm",
           "monitor_end", "monitor_min", "monitor_max", "travel_xy_mm", "slip_mm", "energy_start_J", "energy_drift_J",
           "energy_max_rise_J")
COLUMN_DOCS = {
    "status": "ok, diverged (SimulationDiverged: the run stopped early) or error (any other exception)",
    "diverged": "1 if the simulation diverged, else 0",
    "error": "the exception's type and message, empty for ok",
    "steps": "steps taken",
    "t_end_s": "simulated time reached [s]",
    "dt_s": "the world's time step [s]",
    "ms_per_step": "median wall-clock ms per World.step (varies between runs of the same inputs)",
    "wall_s": "wall-clock time of the whole run, building included [s] (varies between runs)",
    "max_penetration_mm": "deepest penetration of a soft surface node into a rigid link over the run [mm]",
    "monitor_end": "the monitored value at the end (canonical scenes: the monitored node's coordinate [m])",
    "monitor_min": "its smallest value over the run, the start included",
    "monitor_max": "its largest value over the run, the start included",
    "travel_xy_mm": "horizontal distance the centroid of the soft bodies' nodes moved, start to end [mm]",
    "slip_mm": "tangential sliding of the soft bodies against the rigid links they touch: per step the mean over "
               "the active contacts (nodes on links, links' points on soft triangles) of the tangential relative "
               "speed times dt, summed over the steps [mm] (0 while everything sticks)",
    "energy_start_J": "the scene's total energy at the start [J] (World.energy: soft and rigid, kinetic, elastic, "
                      "gravitational)",
    "energy_drift_J": "total energy at the end minus at the start [J] (damping and friction make it negative; "
                      "driven bodies add work)",
    "energy_max_rise_J": "largest rise of the total energy above its start over the run [J] (> 0 in a scene "
                         "without driven bodies is energy gained: a sign of instability)",
    "max_force_N[NAME]": "largest magnitude over the steps of the force the soft bodies exerted on rigid body "
                         "NAME [N] (World.contact_force)",
}
TIMING = ("ms_per_step", "wall_s")  # columns that differ between runs of the same inputs
FORCE_PREFIX = "max_force_N["
PLOT_METRICS = ("max_penetration_mm", "ms_per_step", "monitor_end", "monitor_min", "monitor_max", "travel_xy_mm", "slip_mm",
                "energy_drift_J", "energy_max_rise_J")


# ---------------------------------------------------------------------------------------- parameters
_CELLS = re.compile(r"^\d+x\d+x\d+$")


def parse_value(text: str) -> Any:
    """A parameter value from the command line: an integer, a float, true/false, cells (6x6x2 -> (6, 6, 2))
    or else the text itself."""
    t = text.strip()
    if _CELLS.match(t):
        return tuple(int(c) for c in t.split("x"))
    if t.lower() in ("true", "false"):
        return t.lower() == "true"
    for cast in (int, float):
        with contextlib.suppress(ValueError):
            return cast(t)
    return t


def parse_param(text: str) -> tuple[str, list]:
    """``NAME=V1,V2,...`` -> (NAME, [values]) (values by :func:`parse_value`)."""
    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not re.match(r"^[A-Za-z_]\w*$", name):
        raise InvalidInputError(f"--param takes NAME=V1,V2,... with NAME a Python identifier, got {text!r}")
    items = [v for v in values.split(",")]
    if not values.strip() or any(not v.strip() for v in items):
        raise InvalidInputError(f"--param {name}: give one or more comma-separated values, got {values!r}")
    return name, [parse_value(v) for v in items]


def value_text(v: Any) -> str:
    """A parameter value as written in the CSV and labels (cells as 6x6x2)."""
    if isinstance(v, (tuple, list)):
        return "x".join(str(c) for c in v)
    return str(v)


def _from_json(v: Any) -> Any:
    """A parameter value read back from JSON: its lists as tuples (cells (6, 6, 2) as given)."""
    return tuple(_from_json(c) for c in v) if isinstance(v, list) else v


def _jsonable(v: Any) -> Any:
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, (tuple, list)):
        return [_jsonable(c) for c in v]
    if isinstance(v, dict):
        return {str(k): _jsonable(c) for k, c in v.items()}
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    raise InvalidInputError(f"parameter values must be numbers, strings, booleans or sequences of them, got {v!r}")


# ---------------------------------------------------------------------------------------- scenes
@dataclass(frozen=True)
class SceneSpec:
    """What a run builds: a canonical scene ``name`` (source None), or a user file's ``source`` text
    (``name``: its stem, ``path``: where it was read)."""

    name: str
    source: str | None = None
    path: str | None = None

    @property
    def digest(self) -> str:
        return hashlib.sha256((self.source or self.name).encode()).hexdigest()


_NAMESPACES: dict[str, dict] = {}


def _namespace(spec: SceneSpec) -> dict:
    """The user file's module namespace, executed once per process."""
    key = spec.digest
    if key not in _NAMESPACES:
        ns: dict = {"__name__": f"softbody_sweep_{spec.name}", "__file__": spec.path or "<sweep scene>"}
        try:
            exec(compile(spec.source, spec.path or "<sweep scene>", "exec"), ns)  # noqa: S102 - the user's own file
        except Exception as exc:  # noqa: BLE001 - named, with the file
            raise InvalidInputError(f"the scene file {spec.path} failed to load: {type(exc).__name__}: {exc}") from exc
        if not callable(ns.get("scene")):
            raise InvalidInputError(f"{spec.path}: a sweep scene file must define scene(**params) returning a World")
        _NAMESPACES[key] = ns
    return _NAMESPACES[key]


def resolve_scene(scene: str | os.PathLike) -> SceneSpec:
    """A canonical scene name or the path of a Python scene file -> :class:`SceneSpec` (file read and
    checked here)."""
    from experiments.scenes import SCENES

    if isinstance(scene, str) and scene in SCENES:
        return SceneSpec(scene)
    path = Path(scene)
    if path.suffix == ".py" and path.is_file():
        spec = SceneSpec(path.stem, path.read_text(), str(path.resolve()))
        _namespace(spec)
        return spec
    raise InvalidInputError(f"unknown scene {str(scene)!r}: a canonical scene ({', '.join(sorted(SCENES))}) or the "
                            "path of a Python file defining scene(**params) that returns a World")


def _builder(spec: SceneSpec) -> Callable:
    if spec.source is None:
        from experiments.scenes import SCENES

        return SCENES[spec.name]
    return _namespace(spec)["scene"]


def scene_parameters(spec: SceneSpec) -> tuple[list[str], bool]:
    """The parameter names the scene's builder takes, and whether it takes any (``**kwargs``)."""
    sig = inspect.signature(_builder(spec))
    names = [k for k, p in sig.parameters.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    return names, any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values())


def _choices() -> dict[str, tuple[str, ...]]:
    """The values the canonical scenes' text parameters take (a user's file may mean anything by its own)."""
    from softbody.elements import ELEMENT_TYPES
    from softbody.linsolve import BACKENDS
    from integration.world import WORLD_SCHEMES

    return {"element": tuple(sorted(ELEMENT_TYPES)), "scheme": WORLD_SCHEMES, "solver": tuple(BACKENDS)}


_ANNOTATED = {"float": float, "int": int, "bool": bool, "str": str}


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def _is_number(v: Any) -> bool:
    return _is_int(v) or isinstance(v, (float, np.floating))


def _kind(p: inspect.Parameter) -> tuple[str, Callable[[Any], bool]] | None:
    """What a builder's parameter takes, from its annotation (float, int, bool, str) or else its default (an
    integer default takes any number: ``height=0`` may mean a length): a description and a test; None when
    neither tells (no check)."""
    ann = p.annotation if isinstance(p.annotation, str) else getattr(p.annotation, "__name__", "")
    base = _ANNOTATED.get(str(ann).replace(" ", "").removesuffix("|None"))
    d = p.default
    if base is bool or (base is None and isinstance(d, (bool, np.bool_))):
        return "true or false", lambda v: isinstance(v, (bool, np.bool_))
    if base is int:
        return "an integer", _is_int
    if base is float or (base is None and _is_number(d)):
        return "a number", _is_number
    if base is str or (base is None and isinstance(d, str)):
        return "text", lambda v: isinstance(v, str)
    if isinstance(d, (tuple, list)) and d and all(_is_int(c) for c in d):
        n = len(d)
        return (f"{n} integers ({'x'.join(['N'] * n)} on the command line)",
                lambda v: isinstance(v, (tuple, list)) and len(v) == n and all(_is_int(c) for c in v))
    return None


def check_values(spec: SceneSpec, grid: Mapping[str, Sequence]) -> None:
    """Refuse, before anything runs, a value of the wrong kind for the scene's builder (text for a number,
    a number for true/false, cells of the wrong length: from the builder's defaults or annotations) and, for a
    canonical scene, an element, scheme or solver it does not have. InvalidInputError naming the parameter,
    the value and what is valid."""
    params = inspect.signature(_builder(spec)).parameters
    choices = _choices() if spec.source is None else {}
    for name, values in grid.items():
        p = params.get(name)
        kind = _kind(p) if p is not None else None
        for v in values:
            if kind is not None and not kind[1](v):
                d = p.default
                default = ("" if d is p.empty or d is None else
                           f" (its default: {str(d).lower() if isinstance(d, bool) else value_text(d)})")
                raise InvalidInputError(f"scene {spec.name!r}: parameter {name} takes {kind[0]}{default}, got {v!r}")
            if name in choices and v not in choices[name]:
                raise InvalidInputError(f"scene {spec.name!r}: parameter {name} takes one of "
                                        f"{', '.join(choices[name])}, got {v!r}")


# ---------------------------------------------------------------------------------------- one run
@dataclass
class Point:
    """One run: ``params`` as given, ``row`` (its parameters, as given, and metrics: the CSV row), ``times``
    (n,) [s] and ``values`` (n,) of the monitored value (empty without a monitor)."""

    params: dict
    row: dict
    times: np.ndarray
    values: np.ndarray

    def save(self, path: Path) -> None:
        from experiments.study import save_cached_run

        save_cached_run(path, self.times, self.values, {"params": _jsonable(self.params),
                                                         "row": {**self.row, **_jsonable(self.params)}}, FORMAT)

    @classmethod
    def load(cls, path: Path) -> "Point":
        from experiments.study import load_cached_run

        times, values, meta = load_cached_run(path, FORMAT)
        params = {k: _from_json(v) for k, v in meta["params"].items()}
        return cls(params, {**meta["row"], **params}, times, values)  # the row's parameters typed, as given


def _rigid_names(world) -> dict[int, str]:
    names: dict[int, str] = {}
    for rb in world.rigids.values():
        if rb.id not in names or (rb.name and names[rb.id].startswith("body")):
            names[rb.id] = rb.name or f"body{rb.id}"
    seen: dict[str, int] = {}
    for bid in sorted(names):  # two bodies of one name: the second gets its id
        n = names[bid]
        names[bid] = n if n not in seen else f"{n}#{bid}"
        seen.setdefault(n, bid)
    return names


def _centroid(world) -> np.ndarray:
    bodies = world.bodies
    if not bodies:
        return np.full(3, np.nan)
    return np.vstack([b.positions for b in bodies]).mean(axis=0)


def _slip(world) -> float:
    """Mean over the active contacts of the last step (node and face contacts with rigid links) of the
    tangential speed of the soft point relative to the rigid point [m/s] (0 without contacts)."""
    bodies = world.sim.bodies  # the stepped bodies (stacks among them): the results are keyed by their index
    speeds = []
    for results in (world.contact_results, world.face_results):
        for key, (c, res) in results.items():
            if key >= len(bodies) or not res.active.any():
                continue
            a = res.active
            vel = bodies[key].velocities
            if getattr(c, "nodes", None) is not None:  # a point of a triangle: its nodes' weighted velocity
                soft = np.einsum("mk,mkd->md", c.weights[a], vel[c.nodes[a]])
            else:
                soft = vel[c.node[a]]
            v = soft - c.rigid_velocity[a]
            n = c.normal[a]
            speeds.append(np.linalg.norm(v - np.sum(v * n, axis=1, keepdims=True) * n, axis=1))
    return float(np.concatenate(speeds).mean()) if speeds else 0.0


def run_point(spec: SceneSpec, params: Mapping[str, Any], duration: float | None = None, dt: float | None = None,
              record: str | None = None, threads: int | None = 1) -> Point:
    """Build the scene with ``params`` (and ``dt`` [s] if given and the scene takes it), run it for
    ``duration`` [s] (None: the scene's default; a user file's DURATION, else 1 s) and measure the metrics of
    COLUMN_DOCS. Never raises for a failing run: its row has status "diverged" or "error" and the error text,
    with the metrics of the steps it took. ``record``: a path for a rerun recording of the run."""
    if threads is not None:
        from experiments.study import pin_threads

        pin_threads(threads)
    wall0 = time.perf_counter()
    params = dict(params)
    row: dict[str, Any] = dict(params)
    row.update({c: math.nan for c in COLUMNS})
    row.update(status="ok", diverged=0, error="", steps=0)
    times: list[float] = []
    values: list[float] = []
    world = recorder = None
    monitor: Callable[[], float] | None = None
    metrics_fn = None
    step_ms: list[float] = []
    forces: dict[int, float] = {}
    try:
        kwargs = dict(params)
        names, anything = scene_parameters(spec)
        if dt is not None and "dt" not in kwargs and ("dt" in names or anything):
            kwargs["dt"] = dt
        if spec.source is None:
            from experiments.scenes import build_scene

            sc = build_scene(spec.name, **kwargs)
            world, monitor, default = sc.world, sc.monitored, sc.duration
        else:
            ns = _namespace(spec)
            world = ns["scene"](**kwargs)
            if not (hasattr(world, "step") and hasattr(world, "rigids") and hasattr(world, "bodies")):
                raise InvalidInputError(f"scene() of {spec.path} must return an integration.World, got "
                                        f"{type(world).__name__}")
            if callable(ns.get("monitor")):
                user_monitor = ns["monitor"]
                monitor = lambda: float(user_monitor(world))  # noqa: E731
            metrics_fn = ns.get("metrics") if callable(ns.get("metrics")) else None
            default = float(ns.get("DURATION", 1.0))
            sc = world
        row["dt_s"] = float(world.dt)
        run_for = float(default if duration is None else duration)
        if record is not None:
            from integration.recording import Recorder

            recorder = Recorder(sc, path=record, overwrite=True)
        names_of = _rigid_names(world)
        forces = {bid: 0.0 for bid in names_of}
        e0 = world.energy()["total"]
        row["energy_start_J"] = e0
        rise = [0.0]
        e_last = [e0]
        depth = [0.0]
        slip = [0.0]
        c0 = _centroid(world)
        if monitor is not None:
            times.append(world.t)
            values.append(monitor())
        tic = [0.0]

        def callback(w) -> None:
            step_ms.append(1e3 * (time.perf_counter() - tic[0]))
            if recorder is not None:
                recorder(w)
            if monitor is not None:
                times.append(w.t)
                values.append(monitor())
            for bid, name in _rigid_names(w).items():  # bodies may appear during the run
                forces[bid] = max(forces.get(bid, 0.0), float(np.linalg.norm(w.contact_force(bid))))
                names_of.setdefault(bid, name)
            depth[0] = max(depth[0], w.max_penetration())
            slip[0] += _slip(w) * w.dt
            e_last[0] = w.energy()["total"]
            rise[0] = max(rise[0], e_last[0] - e0)
            tic[0] = time.perf_counter()

        try:
            tic[0] = time.perf_counter()
            world.run(run_for, callback)
        finally:
            row["steps"] = len(step_ms)
            row["t_end_s"] = float(world.t)
            row["max_penetration_mm"] = 1e3 * depth[0]
            row["energy_drift_J"] = e_last[0] - e0
            row["energy_max_rise_J"] = rise[0]
            row["travel_xy_mm"] = 1e3 * float(np.linalg.norm((_centroid(world) - c0)[:2]))
            row["slip_mm"] = 1e3 * slip[0]
            for bid, f in forces.items():
                row[f"{FORCE_PREFIX}{names_of[bid]}]"] = f
        if metrics_fn is not None:
            user = metrics_fn(world)
            if not isinstance(user, Mapping):
                raise InvalidInputError(f"metrics() of {spec.path} must return a dict, got {type(user).__name__}")
            for k, v in user.items():
                key = str(k) if str(k) not in row else f"user_{k}"
                row[key] = float(v) if isinstance(v, (int, float, np.number)) and not isinstance(v, bool) else str(v)
    except SimulationDiverged as exc:
        row.update(status="diverged", diverged=1, error=f"SimulationDiverged: {exc}")
    except Exception as exc:  # noqa: BLE001 - a failing run is a row, not a crashed sweep
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    finally:
        if recorder is not None:
            with contextlib.suppress(Exception):
                recorder.close()
        if world is not None:
            with contextlib.suppress(Exception):
                world.close()
    if values:
        row.update(monitor_end=values[-1], monitor_min=min(values), monitor_max=max(values))
    row["ms_per_step"] = float(np.median(step_ms)) if step_ms else math.nan
    row["wall_s"] = time.perf_counter() - wall0
    row["error"] = " ".join(str(row["error"]).split())  # one line in the CSV
    return Point(params, row, np.array(times, float), np.array(values, float))


# ---------------------------------------------------------------------------------------- the sweep
@dataclass
class SweepResult:
    """The runs of a sweep in grid order: ``rows`` (dicts, the CSV's), ``points`` (with trajectories),
    ``columns`` (the CSV's header), ``executed`` (labels of the runs made by this call; the rest came
    from the cache), ``out`` (None without a directory)."""

    scene: str
    grid: dict[str, list]
    points: list[Point]
    columns: list[str]
    out: Path | None = None
    executed: list[str] = field(default_factory=list)
    duration: float | None = None
    dt: float | None = None

    @property
    def rows(self) -> list[dict]:
        return [{c: p.row.get(c, math.nan if c not in self.grid else "") for c in self.columns} for p in self.points]


def label(params: Mapping[str, Any]) -> str:
    """A run's readable name, e.g. friction=0.2_element=tet4 (file-name safe)."""
    text = "_".join(f"{k}={value_text(v)}" for k, v in params.items()) or "default"
    return re.sub(r"[^\w=.,+-]", "-", text)[:120]


def run_key(spec: SceneSpec, params: Mapping[str, Any], duration: float | None, dt: float | None) -> str:
    blob = json.dumps({"format": FORMAT, "scene": spec.name, "source": spec.digest, "params": _jsonable(dict(params)),
                       "duration": duration, "dt": dt}, sort_keys=True)
    return f"{label(params)}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}"


def _check_grid(spec: SceneSpec, params: Mapping[str, Sequence], dt: float | None) -> dict[str, list]:
    if not isinstance(params, Mapping):
        raise InvalidInputError(f"params must map parameter names to lists of values, got {type(params).__name__}")
    grid: dict[str, list] = {}
    for name, values in params.items():
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
            values = [values]
        values = list(values)
        if not values:
            raise InvalidInputError(f"parameter {name!r} has no values")
        [_jsonable(v) for v in values]
        grid[str(name)] = values
    names, anything = scene_parameters(spec)
    unknown = [n for n in grid if n not in names]
    if unknown and not anything:
        raise InvalidInputError(f"scene {spec.name!r} takes no parameter {', '.join(map(repr, unknown))}; "
                                f"its parameters: {', '.join(names)}")
    if dt is not None and "dt" in grid:
        raise InvalidInputError("dt is both swept (a parameter) and fixed (dt=...): give it once")
    check_values(spec, grid)
    return grid


def run_sweep(scene: str | os.PathLike, params: Mapping[str, Sequence], out: str | os.PathLike | None = None,
              duration: float | None = None, dt: float | None = None, workers: int | None = None, cluster=None,
              record: bool = False, force: bool = False, progress: bool = True, plots: bool = True) -> SweepResult:
    """Run ``scene`` (a canonical name or a scene file, see the module doc) over the full grid of ``params``
    (name -> values; the last name varies fastest), each run for ``duration`` [s] (None: the scene's) with
    ``dt`` [s] (None: the scene's).

    out: the sweep directory (cache, results.csv, summary.md, plots); None keeps nothing on disk (no cache,
    no plots, no recordings). workers / cluster: where the runs go (experiments.study.open_executor: default
    one local worker process; 0: this process; cluster: a Dask scheduler address or Client). record: a rerun
    recording of each run under out/recordings/. force: rerun cached runs. Returns a :class:`SweepResult`
    (``.rows`` are the CSV's rows)."""
    from experiments.study import open_executor

    spec = resolve_scene(scene)
    grid = _check_grid(spec, params, dt)
    for what, v in (("duration", duration), ("dt", dt)):
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise InvalidInputError(f"{what} must be a finite number > 0 [s], got {v!r}")
    if record and out is None:
        raise InvalidInputError("record=True needs an out directory for the recordings")
    if cluster is not None and workers is not None:
        raise InvalidInputError("give workers (local processes) or cluster (a Dask scheduler), not both")
    combos = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    out_dir = Path(out) if out is not None else None
    keys = [run_key(spec, p, duration, dt) for p in combos]
    points: dict[str, Point] = {}
    if out_dir is not None and not force:
        for key in keys:
            path = out_dir / "runs" / f"{key}.npz"
            if path.exists():
                with contextlib.suppress(Exception):
                    points[key] = Point.load(path)
    pending = [(k, p) for k, p in zip(keys, combos) if k not in points]
    executed: list[str] = []
    if pending:
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(pending), desc=f"sweep {spec.name}", unit="run")
        try:
            with open_executor(workers, cluster) as ex:
                futures = {}
                for key, p in pending:
                    rec = str(out_dir / "recordings" / f"{key}.rrd") if record else None  # key: unique
                    futures[ex.submit(run_point, spec, p, duration, dt, rec, 1)] = key
                for fut in cf.as_completed(futures):
                    key = futures[fut]
                    point = fut.result()
                    if out_dir is not None:
                        point.save(out_dir / "runs" / f"{key}.npz")
                    points[key] = point
                    executed.append(key)
                    if bar is not None:
                        bar.set_postfix_str(f"{label(point.params)}: {point.row['status']}", refresh=False)
                        bar.update()
        finally:
            if bar is not None:
                bar.close()
    ordered = [points[k] for k in keys]
    columns = list(grid) + list(COLUMNS)
    extra = sorted({c for p in ordered for c in p.row if c.startswith(FORCE_PREFIX)})
    user = [c for p in ordered for c in p.row if c not in columns and c not in extra]
    columns += extra + list(dict.fromkeys(user))
    result = SweepResult(spec.name, grid, ordered, columns, out_dir, executed, duration, dt)
    if out_dir is not None:
        write_results(result)
        if plots:
            write_plots(result)
        write_summary(result)
    return result


def sweep(scene: str | os.PathLike, params: Mapping[str, Sequence], **options) -> list[dict]:
    """The rows of :func:`run_sweep` (one dict per run, in grid order: the parameters as given, e.g. E 5e6
    and cells (6, 6, 2), then the metrics as numbers, NaN where a failed run has none). With local workers (the
    default, one process) a script calling it needs the ``if __name__ == "__main__":`` guard of multiprocessing;
    ``workers=0`` runs in the calling process."""
    return run_sweep(scene, params, **options).rows


# ---------------------------------------------------------------------------------------- outputs
def _cell(v: Any) -> Any:
    if isinstance(v, float) and math.isnan(v):
        return ""
    return v


def write_results(result: SweepResult) -> Path:
    out = result.out
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=result.columns)
        w.writeheader()
        for row in result.rows:
            w.writerow({k: value_text(v) if k in result.grid else _cell(v) for k, v in row.items()})
    return path


def read_results(path: str | os.PathLike) -> list[dict]:
    """The rows of a sweep's results.csv (a directory or the file), numbers converted, empty cells NaN; the
    parameters parsed as on the command line (:func:`parse_value`: cells 6x6x2 as (6, 6, 2))."""
    path = Path(path)
    path = path / "results.csv" if path.is_dir() else path
    if not path.exists():
        raise InvalidInputError(f"no sweep results at {path}")
    rows = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rows.append({k: (math.nan if v == "" and k != "error" else parse_value(v) if k not in ("error", "status")
                             else v) for k, v in row.items()})
    return rows


def _numeric(rows: list[dict], column: str) -> np.ndarray | None:
    vals = []
    for r in rows:
        v = r.get(column)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
            return None
        vals.append(float(v))
    arr = np.array(vals)
    return arr if np.isfinite(arr).any() else None


def plot_metrics(result: SweepResult) -> list[str]:
    """The numeric metric columns worth plotting (PLOT_METRICS, the force columns, numeric user metrics)."""
    rows = result.rows
    candidates = [c for c in result.columns if c not in result.grid and c not in COLUMNS] + list(PLOT_METRICS)
    ordered = list(PLOT_METRICS) + [c for c in candidates if c not in PLOT_METRICS]
    return [c for c in ordered if _numeric(rows, c) is not None]


def write_plots(result: SweepResult) -> list[Path]:
    """plots/<param>.png for every parameter with more than one value, and trajectories.png."""
    from experiments.study import _figure

    out = result.out
    (out / "plots").mkdir(parents=True, exist_ok=True)
    rows = result.rows
    metrics = plot_metrics(result)
    paths = []
    for param, values in result.grid.items():
        if len(values) < 2 or not metrics:
            continue
        texts = [value_text(v) for v in values]
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        xs = [float(v) for v in values] if numeric else list(range(len(values)))
        others = [k for k in result.grid if k != param and len(result.grid[k]) > 1]  # (one value: no line of its own)
        groups: dict[tuple, list] = {}
        for r in rows:
            groups.setdefault(tuple(value_text(r[k]) for k in others), []).append(r)
        ncols = min(4, len(metrics))
        nrows = math.ceil(len(metrics) / ncols)
        fig = _figure(3.4 * ncols, 2.8 * nrows + 0.6)
        axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
        for ax, metric in zip(axes, metrics):
            for gi, (group, grows) in enumerate(groups.items()):
                by = {value_text(r[param]): r.get(metric) for r in grows}
                ys = [by.get(t, math.nan) for t in texts]
                ys = [float(y) if isinstance(y, (int, float)) and not isinstance(y, bool) else math.nan for y in ys]
                failed = [x for x, t in zip(xs, texts)
                          if any(value_text(r[param]) == t and r["status"] != "ok" for r in grows)]
                lab = ", ".join(f"{k}={v}" for k, v in zip(others, group)) or None
                line, = ax.plot(xs, ys, marker="o", ms=4, lw=1.2, label=lab)
                for x in failed:
                    ax.axvline(x, color=line.get_color(), ls=":", lw=1.0)
            ax.set_title(metric, fontsize=9)
            ax.set_xlabel(param)
            if not numeric:
                ax.set_xticks(xs, texts)
            ax.grid(alpha=0.3)
        for ax in axes[len(metrics):]:
            ax.set_visible(False)
        if others and len(groups) <= 12:
            handles, labels = axes[0].get_legend_handles_labels()
            fig.legend(handles, labels, loc="outside lower center", ncol=min(4, len(groups)), fontsize=8)
        fig.suptitle(f"{result.scene}: metrics against {param} (dotted: a run that failed)")
        paths.append(out / "plots" / f"{param}.png")
        fig.savefig(paths[-1])
    with_traj = [p for p in result.points if len(p.values)]
    if with_traj:
        fig = _figure(7.0, 4.4)
        ax = fig.subplots()
        for p in with_traj:
            ax.plot(p.times, p.values, lw=1.0, ls="-" if p.row["status"] == "ok" else "--",
                    label=label(p.params).replace("_", ", "))
        ax.set_xlabel("time [s]")
        ax.set_ylabel("monitored value")
        ax.grid(alpha=0.3)
        if len(with_traj) <= 16:
            ax.legend(fontsize=7, ncol=2)
        ax.set_title(f"{result.scene}: the monitored value per run (dashed: stopped early)")
        paths.append(out / "trajectories.png")
        fig.savefig(paths[-1])
    return paths


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def write_summary(result: SweepResult) -> Path:
    """summary.md: what ran, the failures, the table of runs and each parameter's effect (mean of each metric
    at each of its values, over the other parameters' values; ok runs only)."""
    out, rows = result.out, result.rows
    n_ok = sum(r["status"] == "ok" for r in rows)
    lines = [f"# Sweep: {result.scene}", "",
             "Grid: " + "; ".join(f"{k} = {', '.join(value_text(v) for v in vs)}" for k, vs in result.grid.items())
             + f" ({len(rows)} runs). Duration: {'the scene default' if result.duration is None else f'{result.duration:g} s'}"
             + f", dt: {'the scene default' if result.dt is None else f'{result.dt:g} s'}.",
             f"{n_ok} ok, {sum(r['status'] == 'diverged' for r in rows)} diverged, "
             f"{sum(r['status'] == 'error' for r in rows)} failed with an error; {len(result.executed)} run now, "
             f"{len(rows) - len(result.executed)} from the cache.", ""]
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        lines += ["## Failed runs", ""]
        lines += [f"- {', '.join(f'{k}={value_text(r[k])}' for k in result.grid)}: {r['status']} after {r['steps']} steps: "
                  f"{r['error'][:300]}" for r in failed] + [""]
    shown = [c for c in result.columns if c not in ("error", "diverged", "wall_s", "energy_start_J")]
    lines += ["## Runs", "", "| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    lines += ["| " + " | ".join(value_text(r[c]) if c in result.grid else _fmt(r[c]) for c in shown) + " |" for r in rows]
    metrics = plot_metrics(result)
    ok = [r for r in rows if r["status"] == "ok"]
    for param, values in result.grid.items():
        if len(values) < 2 or not ok:
            continue
        lines += ["", f"## Effect of {param}", "", f"Mean over the ok runs at each value of {param}"
                  + (f" (over {', '.join(k for k in result.grid if k != param)})" if len(result.grid) > 1 else "") + ".",
                  "", f"| {param} | runs | " + " | ".join(metrics) + " |", "|---|---:|" + "---:|" * len(metrics)]
        for v in values:
            sel = [r for r in ok if value_text(r[param]) == value_text(v)]
            means = []
            for m in metrics:
                arr = _numeric(sel, m) if sel else None
                means.append(_fmt(float(np.nanmean(arr))) if arr is not None else "")
            lines.append(f"| {value_text(v)} | {len(sel)} | " + " | ".join(means) + " |")
    lines += ["", "## Columns", ""] + [f"- `{k}`: {v}" for k, v in COLUMN_DOCS.items()]
    if result.out is not None and (out / "plots").exists():
        lines += ["", "Plots: " + ", ".join(f"[{p.name}](plots/{p.name})" for p in sorted((out / "plots").glob("*.png")))]
    path = out / "summary.md"
    path.write_text("\n".join(lines) + "\n")
    return path
