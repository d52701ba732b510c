"""The ``softbody`` command line: run canonical scenes, convergence studies of them, recommendations, parameter sweeps
(experiments.sweep) and benchmarks."""
from __future__ import annotations

import argparse
import contextlib
import math
import re
import signal
import sys
import threading
from typing import Callable, Iterator, Sequence

import numpy as np

from softbody.elements import ELEMENT_TYPES
from softbody.errors import InvalidInputError

from .scenes import SCENES, Scene, build_scene, scene_grid
from .sizing import check_run_size


_ROLE = re.compile(r":[\w:.-]+:`~?([^`]+)`")  # :func:`run_point`, :class:`~softbody.FemBody`
_LITERAL = re.compile(r"``([^`]+)``")
_TICKS = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"(?<![\w*])\*\*(\w(?:[^*\n]*\w)?)\*\*(?![\w*])")  # **bold**, not scene(**params)
_LINK = re.compile(r"\[([^\]\n]+)\]\(([^)\s]+)\)")  # markdown [text](target)


def plain_text(text: str | None) -> str | None:
    """``text`` (a docstring or help) without its reST and markdown markup, for ``--help``: roles, literals and
    backticks as their text, bold as its text, links as "text (target)", a literal block's "::" as ":"."""
    if text is None:
        return None
    for pattern, repl in ((_ROLE, r"\1"), (_LITERAL, r"\1"), (_TICKS, r"\1"), (_BOLD, r"\1"), (_LINK, r"\1 (\2)")):
        text = pattern.sub(repl, text)
    return re.sub(r"(\S)::$", r"\1:", text, flags=re.M)


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
    parser.add_argument("--scheme", choices=("warped", "newton"), default=None,
                        help="the step: warped (the paper's single solve, default) or newton (the nonlinear "
                             "backward Euler step: exact where elements turn far within a step, several solves)")
    add_material_arguments(parser)
    parser.add_argument("--record", nargs="?", const="", default=None, metavar="PATH",
                        help="write a rerun recording to PATH, or into the directory PATH (an existing one, or "
                             "ending in /) as <scene>_<element>_<cells>_<time>.rrd (default: into logs/)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --record file")
    parser.add_argument("--record-every", type=_positive_int, default=1, metavar="K", help="record every K-th step")
    parser.add_argument("--stress-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                        help="the recording's colour range of von Mises stress [kPa] (default: 0 .. the run's largest)")
    parser.add_argument("--color-mode", choices=("element", "nodal"), default="element",
                        help="stress colours per element face (default) or averaged to the surface nodes")
    parser.add_argument("--print-every", type=_positive_float, default=0.1, metavar="S",
                        help="print the monitored node every S simulated seconds")
    parser.add_argument("--progress", action="store_true", help="show a progress bar instead of the trajectory")


def run_scene(args: argparse.Namespace, scene_name: str) -> Scene:
    """Build the scene from parsed flags, run it (recording on request) and print its trajectory."""
    record_file = record_dir = None
    if args.record is not None:  # checked before anything is built or run
        from integration.recording import record_target

        record_file, record_dir = record_target(args.record, overwrite=args.force)
    stress_range = getattr(args, "stress_range", None)
    if stress_range is not None and not (np.all(np.isfinite(stress_range)) and stress_range[1] > stress_range[0]):
        raise InvalidInputError(f"--stress-range needs LO < HI [kPa], got {stress_range[0]:g} {stress_range[1]:g}")
    grid = scene_grid(scene_name, args.element, args.cells, args.dt)
    if grid is not None:  # memory and time estimated from the mesh size, before anything is built
        element, cells, dt, layout = grid
        duration = args.duration if args.duration is not None else layout.duration
        check_run_size(scene_name, element, cells, max(1, round(duration / dt)), layout.periodic_first)
    material = material_of(args)
    material.check_scheme(args.scheme or "warped")
    scene = build_scene(scene_name, element=args.element, cells=args.cells, dt=args.dt, scheme=args.scheme,
                        **material.options())
    from softbody import compilation

    started_pending = compilation.pending  # an empty numba cache (softbody.compilation)
    duration = args.duration if args.duration is not None else scene.duration
    axis = "xyz"[scene.axis]
    body = scene.body
    print(f"# {scene.name}: {body.mesh.kind} cells {scene.meta['cells']}, {body.mesh.n_elements} elements, "
          f"{body.mesh.n_nodes} nodes, dt {scene.world.dt} s, {duration} s; {body.model} model, "
          f"E {float(np.min(body.material.E)):g} Pa, nu {float(np.max(body.material.nu)):g}")
    print(f"# monitored node {scene.monitor} (rest {np.round(body.rest[scene.monitor], 4).tolist()}), coordinate {axis}")
    recorder = None
    if args.record is not None:
        from integration.recording import Recorder

        recorder = Recorder.attach(scene, path=record_file, directory=record_dir, every=args.record_every,
                                   overwrite=args.force, color_mode=getattr(args, "color_mode", "element"),
                                   color_range=None if stress_range is None else (1e3 * stress_range[0],
                                                                                  1e3 * stress_range[1]))
    every = max(1, int(round(args.print_every / scene.world.dt)))
    step_times: list[float] = []
    max_contacts = 0
    newton = scene.world.sim.scheme == "newton"
    if not args.progress:
        print(f"{'t [s]':>8} {axis + ' [m]':>10} {'contacts':>8} {'ms/step':>8}"
              + (f" {'newton it':>9} {'residual':>9}" if newton else ""))

    def callback(world):
        nonlocal max_contacts
        step_times.append(world.timings["total"])
        active = sum(int(r.active.sum()) for _, r in world.contact_results.values())
        max_contacts = max(max_contacts, active)
        if recorder is not None:
            recorder(world)
        n = int(round(world.t / world.dt))
        if not args.progress and n % every == 0:
            report = world.sim.newton_report
            print(f"{world.t:8.3f} {scene.monitored():10.5f} {active:8d} {1e3 * step_times[-1]:8.1f}"
                  + (f" {report.iterations:9d} {report.residual:9.1e}" if newton else ""), flush=True)

    try:
        scene.world.run(duration, callback, progress=args.progress)
    finally:
        if recorder is not None:
            recorder.close()
            print(f"# recording: {recorder.path}  (open it with: rerun {recorder.path})")
    if step_times:
        print(f"# {len(step_times)} steps, median {1e3 * float(np.median(step_times)):.1f} ms/step, "
              f"max active contacts {max_contacts}, max penetration {1e3 * scene.world.max_penetration():.3f} mm")
    if started_pending:
        from softbody import kernels

        print("# a first run after an install: the numpy code stepped " + (
            "until the compiled kernels were ready" if kernels.ENABLED else
            "while a background process compiles the kernels (later runs step faster)" if compilation.pending else
            "throughout: the background compilation failed (see the warning above)"))
    return scene


LENGTH_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}  # suffix -> metres; "m" last, as "mm" and "cm" end in it


def _length(text: str) -> float:
    """A length > 0 with its unit, e.g. 2mm, 0.5cm, 0.002m; returns metres. A bare number is refused: it
    is ambiguous (2 would be 2 m, the coarsest mesh of any study)."""
    t = text.strip().lower().replace(" ", "")
    unit = next((u for u in LENGTH_UNITS if t.endswith(u)), None)
    number = t[: -len(unit)] if unit else t
    try:
        v = float(number)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a length with a unit (mm, cm or m), e.g. 2mm, got {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite length > 0, got {text!r}")
    if unit is None:
        raise argparse.ArgumentTypeError(f"{text!r} has no unit: write {number}mm, {number}cm or {number}m")
    return v * LENGTH_UNITS[unit]


def _attach_negative_values(argv: Sequence[str], options: Sequence[str] = ("--tolerance",)) -> list[str]:
    """``--tolerance -1mm`` as ``--tolerance=-1mm``: argparse takes a value starting with '-' that is not
    a plain number for an option, and would answer "expected one argument" instead of naming the value."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a in options:
            nxt = next(it, None)
            if nxt is not None and len(nxt) > 1 and nxt[0] == "-" and (nxt[1].isdigit() or nxt[1] == "."):
                out.append(f"{a}={nxt}")
                continue
            out.append(a)
            if nxt is not None:
                out.append(nxt)
        else:
            out.append(a)
    return out


def _nonnegative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = -1
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def add_material_arguments(parser: argparse.ArgumentParser) -> None:
    """--E, --nu, --model: the soft body's material and elastic model (default: the scene's own)."""
    from .study import MODELS

    parser.add_argument("--E", type=_positive_float, default=None, metavar="PA",
                        help="Young's modulus [Pa] (default: the scene's)")
    parser.add_argument("--nu", type=float, default=None, help="Poisson ratio, -1 < nu < 0.5 (default: the scene's)")
    parser.add_argument("--model", choices=MODELS, default=None,
                        help="elastic model (default warped; corotated and neo-hookean need --scheme newton; "
                             "docs/materials.md)")


def material_of(args: argparse.Namespace):
    """The study.Material of the parsed --E, --nu, --model (InvalidInputError for values out of range)."""
    from .study import Material

    return Material(E=getattr(args, "E", None), nu=getattr(args, "nu", None), model=getattr(args, "model", None))


def study_dir(scene: str, args: argparse.Namespace) -> str:
    """studies/SCENE, or studies/SCENE-<material> for another material than the scene's."""
    tag = material_of(args).tag
    return f"studies/{scene}" + (f"-{tag}" if tag else "")


def add_study_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of ``softbody study`` (``recommend`` uses them when it has to make the study)."""
    add_material_arguments(parser)
    parser.add_argument("--elements", nargs="+", choices=sorted(ELEMENT_TYPES), default=None,
                        help="element types to study (default: all three); the reference always runs")
    parser.add_argument("--ladder", default="full", help="resolution ladder: full (default) or small")
    parser.add_argument("--quick", action="store_true", help="the small ladder with its short duration (= --ladder small)")
    parser.add_argument("--duration", type=_positive_float, default=None,
                        help="simulated time [s] of every run (default: the ladder's, else the scene's)")
    parser.add_argument("--dt", type=_positive_float, default=0.01, help="time step [s] (default 0.01)")
    parser.add_argument("--scheme", choices=("warped", "newton"), default="warped",
                        help="the step of every run: warped (the paper's, default) or newton")
    from .study import solve_methods

    parser.add_argument("--method", choices=solve_methods(), default=None,
                        help="linear solve per step (default: the Simulation's; direct factorises every step, "
                             "as the paper did)")
    parser.add_argument("--workers", type=_nonnegative_int, default=None,
                        help="local worker processes (default 1: one run at a time, the fastest here and with undisturbed "
                             "timings; 0: in this process)")
    parser.add_argument("--cluster", default=None, metavar="ADDRESS",
                        help="run on a Dask distributed scheduler, e.g. tcp://host:8786 (workers need softbody)")
    parser.add_argument("--force", action="store_true", help="rerun cached runs")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _study(args: argparse.Namespace, out):
    from .study import run_study

    ladder = "small" if args.quick else args.ladder
    return run_study(args.scene, out, elements=args.elements, ladder=ladder, duration=args.duration, dt=args.dt,
                     method=args.method, workers=args.workers, cluster=args.cluster, force=args.force,
                     progress=not args.no_progress, scheme=args.scheme, material=material_of(args))


def study_command(args: argparse.Namespace) -> None:
    out = args.out or study_dir(args.scene, args)
    study = _study(args, out)
    cached = len(study.runs) + 1 - len(study.executed)
    print((study.out / "table.md").read_text())
    print(f"# {len(study.executed)} runs made, {cached} from the cache; written to {study.out}/: results.csv, "
          f"table.md, trajectories/, trajectories.png, time_vs_nodes.png, pareto.png")


def recommend_command(args: argparse.Namespace) -> None:
    """softbody recommend: the cheapest configuration within --tolerance, from the scene's shipped study results
    (at once, nothing run), from a study run here (--recompute, --study DIR, or a scene without shipped results),
    or from one study per scheme and dt against a Newton reference at half the smallest dt (--schemes / --dts)."""
    from pathlib import Path

    from . import study as studies

    def before_timed_runs() -> None:  # the kernels compiled first: no timing is the numpy code of a first run
        import integration.kernels  # noqa: F401  (registered before the question)
        from softbody import compilation

        compilation.ensure_ready(lambda text: print(text, file=sys.stderr, flush=True))

    scene = args.scene
    compare_steps = args.schemes is not None or args.dts is not None
    if compare_steps and args.study is not None:
        raise InvalidInputError("--study DIR is one study (one scheme and dt) and --schemes/--dts compare one study per "
                                "scheme and dt under studies/SCENE/: give one or the other")
    material = material_of(args)
    shipped = studies.shipped_results(scene) if material.default else None  # shipped: the scene's own material
    if compare_steps or args.recompute or shipped is None:  # a study to run: a scene without a ladder said at once
        studies.get_ladder(scene, "small" if args.quick else args.ladder)
    if compare_steps:  # a study per scheme and step, against one Newton reference: the time step weighed too
        schemes = args.schemes or list(studies.SCHEMES)
        dts = args.dts or [0.01, 0.02]
        before_timed_runs()
        rec = studies.recommend_steps(scene, Path(study_dir(scene, args)), args.tolerance, schemes=schemes, dts=dts,
                                      material=material,
                                      elements=args.elements, ladder="small" if args.quick else args.ladder,
                                      duration=args.duration, method=args.method, workers=args.workers,
                                      cluster=args.cluster, force=args.force, progress=not args.no_progress)
    elif args.study is not None or args.recompute or shipped is None:  # one study, run (or cached) here
        out = Path(args.study or study_dir(scene, args))
        if args.recompute or args.study is None or not (out / "results.csv").exists():
            if args.study is not None and not args.recompute:
                print(f"# no study at {out}: running it first (softbody study {scene} --out {out})", file=sys.stderr)
            elif not material.default and not args.recompute:
                print(f"# the shipped study results are of the scene's own material: running the study of "
                      f"{material.tag} here into {out} (runs cached there)", file=sys.stderr)
            elif shipped is None and not args.recompute:
                print(f"# no shipped study results for {scene} (shipped: {', '.join(studies.shipped_scenes())}): "
                      f"running its study here into {out} (runs cached there)", file=sys.stderr)
            before_timed_runs()
            _study(args, out)
        rec = studies.recommend(out, args.tolerance, scene=scene, elements=args.elements)
    else:  # the published study, shipped with the package: nothing runs
        ref = next(r for r in studies.read_results(shipped) if r["role"] == "reference")
        run_only = [flag for flag, given in (
            ("--quick", args.quick), ("--ladder", args.ladder != "full"),
            ("--duration", args.duration is not None and args.duration != ref["duration_s"]),
            ("--dt", args.dt != ref["dt_s"]), ("--scheme", args.scheme != ref["scheme"]),
            ("--method", args.method is not None and args.method != ref["method"]), ("--force", args.force),
            ("--workers", args.workers is not None), ("--cluster", args.cluster is not None)) if given]
        if run_only:
            raise InvalidInputError(
                f"{', '.join(run_only)} only appl{'ies' if len(run_only) == 1 else 'y'} to a study run on this machine: "
                f"add --recompute (without it the answer comes from the shipped study results of {scene}: the full "
                f"ladder, {ref['scheme']}, dt {ref['dt_s']:g} s, {ref['duration_s']:g} s, {ref['method']} solves)")
        rec = studies.recommend_shipped(scene, args.tolerance, elements=args.elements)
    c = rec.choice
    print(f"# {scene}: the cheapest configuration per simulated second within {1e3 * args.tolerance:g} mm, from "
          f"{rec.source}")
    if rec.basis:
        print(f"# error: {rec.basis}")
    if shipped is not None and not (compare_steps or args.study is not None or args.recompute):
        print(f"# nothing was run: --recompute runs this study on this machine (its timings, cached under "
              f"studies/{scene}); --schemes warped newton --dts 0.01 0.02 weighs the scheme and the time step too "
              f"(a study per scheme and dt here, against a Newton reference at half the smallest dt: tens of minutes)")
    print(rec.table())
    print(f"\nrecommended: --element {c['element']} --cells {c['cells'].replace('x', ' ')} --scheme {c['scheme']} "
          f"--dt {c['dt_s']:g}  ({c['cost_ms_per_step']:.1f} ms/step, {c['cost_ms_per_s']:.0f} ms per simulated "
          f"second, error {1e3 * c['error_m']:.3f} mm)")


def sweep_command(args: argparse.Namespace) -> int:
    """softbody sweep: runs the grid, prints its table; exit status 1 if every run failed (0 otherwise)."""
    from pathlib import Path

    from experiments.sweep import parse_param, run_sweep, value_text

    params: dict[str, list] = {}
    for text in args.param:
        name, values = parse_param(text)
        if name in params:
            raise InvalidInputError(f"--param {name} is given twice; put all its values in one flag")
        params[name] = values
    out = args.out or f"sweeps/{Path(args.scene).stem}"
    result = run_sweep(args.scene, params, out, duration=args.duration, dt=args.dt, workers=args.workers,
                       cluster=args.cluster, record=args.record, force=args.force, progress=not args.no_progress)
    rows = result.rows
    shown = list(result.grid) + ["status", "steps", "ms_per_step", "max_penetration_mm", "monitor_end", "slip_mm"]
    print("| " + " | ".join(shown) + " |")
    for row in rows:
        print("| " + " | ".join(value_text(row[c]) if c in result.grid else f"{row[c]:.4g}" if isinstance(row[c], float)
                                else str(row[c]) for c in shown) + " |")
    failed = sum(r["status"] != "ok" for r in rows)
    print(f"# {len(rows)} runs ({len(result.executed)} made, {len(rows) - len(result.executed)} from the cache"
          f"{f', {failed} failed: see summary.md' if failed else ''}); written to {result.out}/: results.csv, "
          "summary.md, plots/, trajectories.png" + (", recordings/" if args.record else ""))
    if rows and failed == len(rows):
        print(f"softbody sweep: every run failed; the first: {rows[0]['status']}: {rows[0]['error'][:300]}",
              file=sys.stderr)
        return 1
    return 0


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: raised in the main thread so that ``finally`` blocks (closing a recording)
    run. A BaseException, like KeyboardInterrupt, so that no ``except Exception`` swallows it."""

    def __init__(self, signum: int):
        super().__init__(f"terminated by {signal.Signals(signum).name}")
        self.signum = signum


@contextlib.contextmanager
def signals_as_exceptions(signums: Sequence[int] = (signal.SIGTERM, signal.SIGHUP)) -> Iterator[None]:
    """Inside the block, the first of ``signums`` raises :class:`Terminated` (later ones are ignored while the
    program cleans up); the previous handlers are restored after. Does nothing outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame) -> None:
        for s in signums:
            signal.signal(s, signal.SIG_IGN)
        raise Terminated(signum)

    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def signal_in(exc: BaseException | None) -> BaseException | None:
    """The Terminated or KeyboardInterrupt that ``exc`` is or was raised from (its causes and contexts, in turn):
    a signal that arrives while C code calls back into Python (numba loading a compiled kernel from its cache,
    for one) surfaces as a SystemError caused by the exception the handler raised; None if there is none."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (Terminated, KeyboardInterrupt)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _dispatch(parser: argparse.ArgumentParser, command: Callable[[], object]) -> int:
    """Run a command: its exit status is what it returns if an int (else 0); an InvalidInputError is a one-line
    usage error (exit 2); Ctrl-C exits 130, SIGTERM and
    SIGHUP 128 + the signal number, after the command's ``finally`` blocks (e.g. a recording closed), also when
    the signal arrived inside C code that turned it into a SystemError (:func:`signal_in`)."""
    try:
        with signals_as_exceptions():
            status = command()
    except InvalidInputError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    except (KeyboardInterrupt, Terminated, SystemError) as exc:
        sig = signal_in(exc)
        if sig is None:
            raise
        if isinstance(sig, KeyboardInterrupt):
            print("\n# interrupted", file=sys.stderr)
            return 130
        print(f"\n# {sig}", file=sys.stderr)
        return 128 + sig.signum
    return status if isinstance(status, int) else 0


def compile_command() -> None:
    """softbody compile: the warm-up scenes of integration.warmup in the foreground (numba's cache filled)."""
    import integration.kernels  # noqa: F401  (registers integration's kernels and their warm-up)
    from softbody import compilation
    from softbody.kernels import AVAILABLE

    if not AVAILABLE:
        print("numba is not installed or SOFTBODY_NO_NUMBA is set: nothing to compile")
        return
    print("compiling softbody's kernels into numba's cache (about 40 s) ...", flush=True)
    seconds = compilation.compile_now()
    print(f"done in {seconds:.0f} s; later runs load them from the cache")


def scene_main(scene: str, description: str | None = None, argv: Sequence[str] | None = None) -> int:
    """The command line of an example script running one scene (the flags of ``softbody run``)."""
    parser = argparse.ArgumentParser(description=plain_text(description),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, scene=scene)
    args = parser.parse_args(argv)
    return _dispatch(parser, lambda: run_scene(args, scene))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="softbody", description=plain_text(__doc__))
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a canonical scene and print the monitored node")
    add_scene_arguments(run)
    study = sub.add_parser("study", help="convergence study: the resolution ladder per element type, "
                                         "with cost, error, CSV, table and plots")
    study.add_argument("scene", help=f"scene name: {', '.join(sorted(SCENES))}")
    study.add_argument("--out", default=None, metavar="DIR", help="study directory (default: studies/SCENE)")
    add_study_arguments(study)
    rec = sub.add_parser("recommend", help="the cheapest element type and resolution within a tolerance, from the "
                                           "shipped study results (at once; --recompute runs the study here), or "
                                           "the scheme and time step too (--schemes / --dts: studies run here)")
    rec.add_argument("scene", help=f"scene name: {', '.join(sorted(SCENES))}")
    rec.add_argument("--tolerance", type=_length, required=True, metavar="TOL",
                     help="largest RMS error of the monitored trajectory against the reference, with its unit: "
                          "2mm, 0.5cm, 0.002m")
    rec.add_argument("--study", default=None, metavar="DIR",
                     help="one study directory to choose from (made first if it has no results.csv, or with "
                          "--recompute); without it and --recompute, the scene's shipped study results")
    rec.add_argument("--recompute", action="store_true",
                     help="run the study on this machine (cached under studies/SCENE, or --study DIR; its timings) "
                          "instead of answering from the shipped results of the published study")
    rec.add_argument("--schemes", nargs="+", choices=("warped", "newton"), default=None,
                     help="weigh the scheme and the time step too: one study per scheme and dt run here under "
                          "studies/SCENE/, errors against the reference mesh with the Newton scheme at half the "
                          "smallest dt, so they hold the time discretisation error (default with --dts: both)")
    rec.add_argument("--dts", nargs="+", type=_positive_float, default=None, metavar="DT",
                     help="time steps [s] to weigh (see --schemes; default with --schemes: 0.01 0.02)")
    add_study_arguments(rec)
    sweep = sub.add_parser("sweep", help="a parameter sweep: the full grid over --param NAME=V1,V2,..., one row of "
                                         "metrics per run: CSV, plots, summary (docs/sweeps.md)")
    sweep.add_argument("scene", help=f"a scene name ({', '.join(sorted(SCENES))}) or the path of a Python file "
                                     "defining scene(**params) -> World (optionally monitor(world) -> float and "
                                     "metrics(world) -> dict)")
    sweep.add_argument("--param", action="append", required=True, metavar="NAME=V1,V2,...",
                       help="a swept parameter and its values (repeat the flag for more; cells as 6x6x2)")
    sweep.add_argument("--duration", type=_positive_float, default=None, help="simulated time of every run [s] "
                                                                             "(default: the scene's)")
    sweep.add_argument("--dt", type=_positive_float, default=None, help="time step of every run [s] (default: the "
                                                                       "scene's)")
    sweep.add_argument("--out", default=None, metavar="DIR", help="sweep directory (default: sweeps/<scene>)")
    where = sweep.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_nonnegative_int, default=None,
                       help="local worker processes (default 1; 0: in this process)")
    where.add_argument("--cluster", default=None, metavar="ADDRESS",
                       help="run on a Dask distributed scheduler, e.g. tcp://host:8786 (workers need softbody)")
    sweep.add_argument("--record", action="store_true", help="a rerun recording of every run in DIR/recordings/")
    sweep.add_argument("--force", action="store_true", help="rerun cached runs")
    sweep.add_argument("--no-progress", action="store_true", help="no progress bar")
    from .bench import add_bench_arguments

    bench = sub.add_parser("bench", help="benchmark: ms per step with its breakdown, the solver floor, pybullet's "
                                         "soft body, memory and scaling; JSON + markdown + plot")
    add_bench_arguments(bench)
    sub.add_parser("compile", help="compile the kernels into numba's disk cache now (a first run otherwise does it in "
                                   "a background process while the numpy code runs)")
    args = parser.parse_args(_attach_negative_values(sys.argv[1:] if argv is None else argv))

    def command() -> int | None:
        if args.command in ("study", "sweep", "bench"):  # timed: never the numpy code of a first run (recommend:
            # in recommend_command, where it runs something)
            import integration.kernels  # noqa: F401  (registered before the question)
            from softbody import compilation

            compilation.ensure_ready(lambda text: print(text, file=sys.stderr, flush=True))
        if args.command == "run":
            run_scene(args, args.scene)
        elif args.command == "study":
            study_command(args)
        elif args.command == "recommend":
            recommend_command(args)
        elif args.command == "sweep":
            return sweep_command(args)
        elif args.command == "compile":
            compile_command()
        elif args.command == "bench":
            from .bench import bench_command

            bench_command(args)

    return _dispatch(parser, command)


if __name__ == "__main__":
    sys.exit(main())
