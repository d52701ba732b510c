"""Convergence studies (experiments/study.py, `softbody study` / `softbody recommend`).

One small study (the cantilever's small ladder: 3 rungs per element type, 0.3 s, about one period of
the first bending mode) is made once per module on local worker processes and shared by the tests;
one test makes the same study again on a local two-worker Dask cluster.
"""
from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import softbody
from experiments import cli
from experiments import study as study_module
from experiments.study import (CSV_COLUMNS, LADDERS, NoConfigurationWithinTolerance, RunResult, Study,
                               load_trajectory, open_executor, pareto_front, recommend, rms_error, run_study,
                               write_results)

SCENE = "cantilever"
PNGS = ("trajectories.png", "time_vs_nodes.png", "pareto.png")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study_local")
    return run_study(SCENE, out, ladder="small", workers=2, progress=False)


def csv_rows(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------------------------- metric
def test_rms_error_is_the_rms_difference_in_metres_on_the_common_grid():
    t = np.linspace(0.0, 1.0, 101)
    ref = 0.01 * np.sin(2 * np.pi * t)
    assert rms_error(t, ref, t, ref) == 0.0
    assert rms_error(t, ref + 0.002, t, ref) == pytest.approx(0.002, rel=1e-12)
    # a coarser run time grid: the reference is interpolated onto it
    tc = t[::4]
    assert rms_error(tc, np.interp(tc, t, ref) - 0.003, t, ref) == pytest.approx(0.003, rel=1e-12)
    # a run longer than the reference is compared only where the reference exists
    tl = np.linspace(0.0, 2.0, 201)
    assert rms_error(tl, np.where(tl <= 1.0, 0.0, 5.0), t, np.zeros_like(t)) == 0.0


def test_pareto_front_keeps_only_undominated_points():
    pts = [(1.0, 10.0), (2.0, 5.0), (3.0, 6.0), (4.0, 1.0), (2.5, 5.0)]
    assert pareto_front(pts) == [0, 1, 3]


# ---------------------------------------------------------------------------------------- ladders
PAPER_SHEET = {  # docs/method.md section 5 / the paper's Fig. 9: (#elements, #nodes) per rung
    "tet4": [(160, 75), (960, 324), (5120, 1445), (10000, 2646), (17280, 4375), (23660, 5832)],
    "hex8": [(32, 75), (192, 324), (576, 845), (1024, 1445), (1620, 2166), (2000, 2646)],
    "tet10": [(20, 71), (80, 227), (360, 773), (640, 1317), (810, 1643)],
}


def test_sheet_ladder_is_the_papers():
    lad = LADDERS["sheet-on-sphere"]["full"]
    for kind, counts in PAPER_SHEET.items():
        got = []
        for cells in lad.rungs[kind]:
            m = softbody.box_mesh((1.0, 1.0, 0.25), cells, kind)
            got.append((m.n_elements, m.n_nodes))
        assert got == counts, kind


def test_tube_ladder_has_the_papers_element_counts():
    lad = LADDERS["hanging-tube"]["full"]
    hex_counts = [48, 160, 280, 432, 616]  # the paper's Fig. 8
    assert [a * b * c for a, b, c in lad.rungs["hex8"]] == hex_counts
    assert [5 * a * b * c for a, b, c in lad.rungs["tet4"]] == [240, 800, 1400, 2160, 2400, 3080, 3840]
    assert all(c[0] % 2 == 0 for rungs in lad.rungs.values() for c in rungs)


MONITOR = {"sheet-on-sphere": (-0.5, -0.5, 0.35), "hanging-tube": (0.1, 0.0, -1.0), "cantilever": (1.0, 0.0, 0.0)}


def _mesh(scene: str, kind: str, cells) -> softbody.Mesh:
    if scene == "sheet-on-sphere":
        return softbody.box_mesh((1.0, 1.0, 0.25), cells, kind, center=(0.0, 0.0, 0.475))
    if scene == "hanging-tube":
        return softbody.tube_mesh(0.1, 0.06, 1.0, cells, kind)
    return softbody.box_mesh((1.0, 0.1, 0.1), cells, kind, center=(0.5, 0.0, 0.0))


@pytest.mark.parametrize("scene", sorted(LADDERS))
def test_every_rung_has_the_monitored_point_as_a_node(scene):
    """Errors compare one material point: every rung and the reference must have a node exactly there.
    Rungs go coarse to fine, and the reference is beyond the top of its element type's ladder (at least
    as many cells in every direction, more in one)."""
    for name, lad in LADDERS[scene].items():
        ref_kind, ref_cells = lad.reference
        ref = _mesh(scene, ref_kind, ref_cells)
        for kind, rungs in lad.rungs.items():
            assert list(rungs) == sorted(rungs, key=lambda c: _mesh(scene, kind, c).n_nodes), (name, kind)
            for cells in rungs:
                m = _mesh(scene, kind, cells)
                assert np.linalg.norm(m.nodes - MONITOR[scene], axis=1).min() < 1e-12, (name, kind, cells)
        assert np.linalg.norm(ref.nodes - MONITOR[scene], axis=1).min() < 1e-12, (name, "reference")
        top = lad.rungs[ref_kind][-1]
        assert all(r >= t for r, t in zip(ref_cells, top)) and tuple(ref_cells) != tuple(top), name


# ---------------------------------------------------------------------------------------- the small study
def test_small_study_writes_csv_table_trajectories_and_plots(study):
    out = study.out
    rows = csv_rows(out)
    lad = LADDERS[SCENE]["small"]
    assert len(rows) == sum(len(r) for r in lad.rungs.values()) + 1
    assert tuple(rows[0]) == CSV_COLUMNS
    assert [r["role"] for r in rows].count("reference") == 1
    for r in rows:
        assert r["status"] == "ok"
        cells = [int(c) for c in r["cells"].split("x")]
        mesh = _mesh(SCENE, r["element"], cells)
        assert (int(r["elements"]), int(r["nodes"])) == (mesh.n_elements, mesh.n_nodes)
        assert int(r["dofs"]) == 3 * int((mesh.nodes[:, 0] > 1e-12).sum())  # the x = 0 face is fixed
        assert float(r["median_ms_per_step"]) > 0 and float(r["peak_mem_mb"]) >= 0
        assert int(r["steps"]) == 30 and float(r["duration_s"]) == 0.3
        traj = load_trajectory(out, r["element"], cells)
        assert traj.times.shape == traj.values.shape == (31,)
    table = (out / "table.md").read_text()
    assert "RMS difference" in table and "| tet10 | 16x2x2 |" in table and table.count("\n| ") >= len(rows) + 1
    for name in PNGS:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name


def test_small_study_errors_decrease_monotonically_with_refinement(study):
    rows = [r for r in csv_rows(study.out) if r["role"] == "ladder"]
    for kind, rungs in LADDERS[SCENE]["small"].rungs.items():
        errors = [float(next(r["error_m"] for r in rows if r["element"] == kind and r["cells"] == "x".join(map(str, c))))
                  for c in rungs]
        assert all(e > 0 for e in errors), (kind, errors)
        assert all(a > b for a, b in zip(errors, errors[1:])), (kind, errors)


def test_small_study_is_reused_from_the_cache(study):
    again = run_study(SCENE, study.out, ladder="small", workers=2, progress=False, plots=False)
    assert again.executed == []
    for r in study.runs + [study.reference]:
        assert np.array_equal(again.run(r.element, r.cells).values, r.values)


def _cost(row: dict) -> float:
    """ms per step for ranking: the CPU time of a run whose wall time is more than 1.3x it, else the wall time."""
    wall, cpu = float(row["median_ms_per_step"]), float(row["median_cpu_ms_per_step"])
    return cpu if wall > 1.3 * cpu else wall


def _brute_force(out: Path, tol: float):
    """The cheapest run per simulated second within tol, the more accurate of equal costs (CPU times are counted in
    clock ticks, so two runs can cost the same)."""
    best = None
    for r in csv_rows(out):
        if r["role"] != "ladder" or r["status"] != "ok" or float(r["error_m"]) > tol:
            continue
        key = (_cost(r) / float(r["dt_s"]), float(r["error_m"]))
        if best is None or key < best[0]:
            best = (key, r)
    return None if best is None else best[1]


def test_recommend_picks_what_a_brute_force_check_of_the_csv_picks(study):
    errors = sorted(float(r["error_m"]) for r in csv_rows(study.out) if r["role"] == "ladder")
    tolerances = [e * 1.0001 for e in errors] + [1.0]
    for tol in tolerances:
        rec = recommend(study.out, tol, scene=SCENE)
        expect = _brute_force(study.out, tol)
        assert (rec.choice["element"], rec.choice["cells"]) == (expect["element"], expect["cells"]), tol
        assert rec.choice["error_m"] <= tol
        costs = [_cost(c) for c in rec.candidates]
        assert costs == sorted(costs)
        assert "recommended" in rec.table()
    with pytest.raises(NoConfigurationWithinTolerance, match="no configuration"):
        recommend(study.out, errors[0] / 2)


def test_cli_study_and_recommend_use_the_cached_study(study, capsys):
    assert cli.main(["study", SCENE, "--quick", "--out", str(study.out), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "0 runs made" in out and "| tet4 | 4x2x2 |" in out
    tol = sorted(float(r["error_m"]) for r in csv_rows(study.out) if r["role"] == "ladder")[2]
    assert cli.main(["recommend", SCENE, "--tolerance", f"{1e3 * tol * 1.0001}mm", "--study", str(study.out)]) == 0
    out = capsys.readouterr().out
    expect = _brute_force(study.out, tol * 1.0001)
    assert f"recommended: --element {expect['element']} --cells {expect['cells'].replace('x', ' ')}" in out
    with pytest.raises(SystemExit) as exc:
        cli.main(["recommend", SCENE, "--tolerance", "1e-6mm", "--study", str(study.out)])
    assert exc.value.code == 2
    assert "no configuration" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------- where runs run
def test_study_on_a_local_dask_cluster_gives_identical_trajectories(study, tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = run_study(SCENE, tmp_path, ladder="small", cluster=cluster.scheduler_address, progress=False)
    assert sorted(remote.executed) == sorted(r.key for r in study.runs + [study.reference])
    for r in study.runs + [study.reference]:
        other = remote.run(r.element, r.cells)
        assert np.array_equal(other.times, r.times) and np.array_equal(other.values, r.values), r.key
    assert remote.errors == study.errors


# ---------------------------------------------------------------------------------------- machine load
def _run(element: str, cells, wall: float, cpu: float, load: float) -> RunResult:
    return RunResult(SCENE, element, cells, 0.3, 0.01, "auto", np.zeros(2), np.zeros(2), 10, 10, 30, 30, wall, cpu,
                     1.0, 1.0, external_load=load)


def _table(tmp_path, runs: list[RunResult], errors: list[float]) -> str:
    ref = _run("tet10", (16, 2, 2), 5.0, 5.0, runs[0].external_load)
    write_results(Study(SCENE, tmp_path, runs, ref, {r.key: e for r, e in zip(runs, errors)}))
    return (tmp_path / "table.md").read_text()


def test_a_wait_the_study_causes_itself_is_not_machine_load_and_waits_rank_by_cpu_time(tmp_path):
    """Runs that waited for a core (wall 2x CPU) while nothing outside the study ran (its own workers on every
    core): no star, no "loaded machine"; all the same, a run that waited is ranked by its CPU time."""
    runs = [_run("tet4", (4, 2, 2), 10.0, 5.0, 0.02), _run("hex8", (4, 2, 2), 6.0, 6.0, 0.02)]
    table = _table(tmp_path, runs, [1e-3, 1e-3])
    assert "Loaded machine" not in table and " * |" not in table and "\\*" not in table
    rec = recommend(tmp_path, 2e-3)
    assert rec.choice["element"] == "tet4" and rec.choice["cost_ms_per_step"] == 5.0  # 5 ms CPU beats 6 ms


def test_load_from_outside_the_study_is_flagged(tmp_path):
    runs = [_run("tet4", (4, 2, 2), 10.0, 5.0, 1.1), _run("hex8", (4, 2, 2), 6.0, 6.0, 1.1)]
    table = _table(tmp_path, runs, [1e-3, 1e-3])
    assert "**Loaded machine**: processes outside the study kept 1.1 cores busy" in table
    assert "| 10.0 * | 5.0 |" in table and "| 6.0 | 6.0 |" in table  # the hex8 run did not wait: no star


def test_the_external_load_leaves_out_the_study_s_own_processes(monkeypatch):
    """_ExternalLoad: the machine's busy CPU time minus that of the study's process tree, per wall second."""
    clock = {"machine": 100.0, "tree": 10.0, "wall": 0.0}
    monkeypatch.setattr(study_module, "_machine_busy_seconds", lambda: clock["machine"])
    monkeypatch.setattr(study_module, "_tree_cpu_seconds", lambda root: clock["tree"])
    monkeypatch.setattr(study_module.time, "perf_counter", lambda: clock["wall"])
    with study_module._ExternalLoad() as load:
        clock.update(machine=104.0, tree=13.0, wall=2.0)  # 3 of the 4 busy seconds were the study's
    assert load.cores == pytest.approx(0.5)


def test_the_study_s_process_tree_holds_its_workers():
    """A busy child of this process (a worker) counts in the study's CPU time, so not as machine load."""
    child = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                                                    "while time.process_time() - t < 0.6: pass\ntime.sleep(5)"])
    try:
        before = study_module._tree_cpu_seconds(os.getpid())
        deadline = time.monotonic() + 20
        while study_module._tree_cpu_seconds(os.getpid()) - before < 0.5 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert study_module._tree_cpu_seconds(os.getpid()) - before >= 0.5
    finally:
        child.kill()


def test_local_studies_run_one_configuration_at_a_time_by_default():
    with open_executor() as ex:
        pids = {ex.submit(os.getpid).result() for _ in range(3)}
    assert len(pids) == 1 and os.getpid() not in pids


def test_recommend_across_schemes_and_steps_picks_the_cheapest_per_simulated_second(tmp_path):
    """recommend_steps: one study per (scheme, dt), errors against one reference (Newton at half the smallest
    step); its choice is what a brute-force pass over the rows picks, with cost = ms per step / dt."""
    from experiments.study import recommend_steps

    rec = recommend_steps(SCENE, tmp_path, 1.0, schemes=("warped", "newton"), dts=(0.01, 0.02),
                          elements=["tet10"], ladder="small", duration=0.1, workers=0, progress=False, plots=False)
    rows = rec.candidates
    assert {(r["scheme"], r["dt_s"]) for r in rows} == {("warped", 0.01), ("warped", 0.02), ("newton", 0.01),
                                                       ("newton", 0.02)}
    for r in rows:
        assert r["cost_ms_per_s"] == pytest.approx(r["cost_ms_per_step"] / r["dt_s"])
    tol = sorted(r["error_m"] for r in rows)[len(rows) // 2]  # half of them qualify
    rec = recommend_steps(SCENE, tmp_path, tol, schemes=("warped", "newton"), dts=(0.01, 0.02), elements=["tet10"],
                          ladder="small", duration=0.1, workers=0, progress=False, plots=False)  # from the caches
    best = min((r for r in rec.candidates if r["error_m"] <= tol), key=lambda r: r["cost_ms_per_s"])
    assert rec.choice["element"] == best["element"] and rec.choice["cells"] == best["cells"]
    assert (rec.choice["scheme"], rec.choice["dt_s"]) == (best["scheme"], best["dt_s"])
    assert (tmp_path / "reference_newton_dt0.005").is_dir() and (tmp_path / "newton_dt0.02" / "results.csv").exists()
    with pytest.raises(softbody.InvalidInputError, match="schemes"):
        recommend_steps(SCENE, tmp_path, tol, schemes=("implicit",))


# ---------------------------------------------------------------------------------------- shipped studies
DOCS_IMG = Path(__file__).resolve().parents[1] / "docs" / "img"


def _shipped_rows(scene: str) -> list[dict]:
    with open(study_module.shipped_results(scene), newline="") as f:
        return list(csv.DictReader(f))


def _cheapest_within(rows: list[dict], tol: float) -> dict:
    """The published run with the lowest ms per step whose error is <= tol [m] (a brute-force pass over the CSV)."""
    ok = [r for r in rows if r["role"] == "ladder" and r["error_m"] and float(r["error_m"]) <= tol]
    return min(ok, key=lambda r: (float(r["median_ms_per_step"]), float(r["error_m"])))


def test_published_study_results_are_shipped_with_the_package():
    """The package carries the results of every published study (experiments/data/, package data): the sheet's and
    the tube's are docs/img's CSV files byte for byte, the cantilever's is docs/studies.md's table."""
    assert study_module.shipped_scenes() == ["cantilever", "hanging-tube", "sheet-on-sphere"]
    for scene in ("sheet-on-sphere", "hanging-tube"):
        assert study_module.shipped_results(scene).read_bytes() == (DOCS_IMG / f"{scene}-results.csv").read_bytes()
    doc = (DOCS_IMG.parent / "studies.md").read_text()
    for r in _shipped_rows("cantilever"):
        err = "reference" if r["role"] == "reference" else f"{1e3 * float(r['error_m']):.3f}"
        assert (f"| {r['element']} | {r['cells']} | {r['elements']} | {r['nodes']} | {r['dofs']} | "
                f"{float(r['median_ms_per_step']):.1f} | {float(r['median_cpu_ms_per_step']):.1f} | "
                f"{float(r['peak_mem_mb']):.1f} | {err} |") in doc, r
    for scene in study_module.shipped_scenes():
        src = study_module.shipped_source(scene)
        assert src["published"] and src["measured"] and src["monitored"], scene
    assert study_module.shipped_results("cubes-on-plane") is None


@pytest.mark.parametrize("scene, tol", [("sheet-on-sphere", 2e-3), ("sheet-on-sphere", 6e-3), ("hanging-tube", 50e-3),
                                        ("cantilever", 2e-3)])
def test_recommend_answers_from_the_shipped_results_without_running_anything(scene, tol, capsys, monkeypatch):
    def no_run(*a, **kw):
        raise AssertionError("recommend ran something")

    monkeypatch.setattr(study_module, "run_study", no_run)
    monkeypatch.setattr(study_module, "run_configuration", no_run)
    rows = _shipped_rows(scene)
    assert all(float(r["median_ms_per_step"]) <= 1.3 * float(r["median_cpu_ms_per_step"]) for r in rows)  # no waits
    expect = _cheapest_within(rows, tol)
    ref = next(r for r in rows if r["role"] == "reference")
    t = time.perf_counter()
    assert cli.main(["recommend", scene, "--tolerance", f"{1e3 * tol:g}mm"]) == 0
    assert time.perf_counter() - t < 5.0
    out = capsys.readouterr().out
    assert f"recommended: --element {expect['element']} --cells {expect['cells'].replace('x', ' ')} " in out
    assert f"against the reference {ref['element']} {ref['cells']} (warped, dt 0.01 s)" in out
    assert "spatial discretisation error" in out and "shipped study results" in out and "--recompute" in out
    assert study_module.shipped_source(scene)["measured"] in out


def test_the_readme_recommend_command_answers_in_seconds_from_anywhere(tmp_path):
    """`softbody recommend sheet-on-sphere --tolerance 2mm` (the README's example): from the shipped results, the
    run the published table implies (tet10 8x8x2, 1.827 mm), naming its reference; nothing written."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", "import sys; from experiments.cli import main; sys.exit(main())",
                           "recommend", "sheet-on-sphere", "--tolerance", "2mm"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    wall = time.perf_counter() - t
    assert proc.returncode == 0, proc.stderr
    expect = _cheapest_within(_shipped_rows("sheet-on-sphere"), 2e-3)
    assert (expect["element"], expect["cells"]) == ("tet10", "8x8x2")
    assert "recommended: --element tet10 --cells 8 8 2 --scheme warped --dt 0.01" in proc.stdout
    assert "error 1.827 mm" in proc.stdout and "reference tet10 12x12x3 (warped, dt 0.01 s)" in proc.stdout
    assert wall < 30.0, wall  # about 1.5 s here, most of it importing softbody
    assert list(tmp_path.iterdir()) == []


def test_options_of_a_run_without_recompute_are_refused(capsys):
    err = _refused_cli(["recommend", "sheet-on-sphere", "--tolerance", "2mm", "--quick", "--dt", "0.02"], capsys)
    assert "--quick, --dt only apply to a study run on this machine: add --recompute" in err
    err = _refused_cli(["recommend", "sheet-on-sphere", "--tolerance", "2mm", "--schemes", "warped", "--study", "x"],
                       capsys)
    assert "give one or the other" in err


def _refused_cli(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    return capsys.readouterr().err


def test_recompute_runs_the_study_here_with_a_named_bar_and_step_reports(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["recommend", SCENE, "--tolerance", "50mm", "--recompute", "--quick", "--workers", "0",
                     "--elements", "tet10"]) == 0
    captured = capsys.readouterr()
    assert f"study {SCENE} (warped, dt 0.01 s)" in captured.err and " step " in captured.err
    assert "from the study at studies/cantilever" in captured.out and "reference tet10 16x2x2" in captured.out
    rows = csv_rows(tmp_path / "studies" / SCENE)
    expect = _cheapest_within(rows, 50e-3)  # (workers 0: nothing else ran, so no run waited for a core)
    assert f"recommended: --element tet10 --cells {expect['cells'].replace('x', ' ')} " in captured.out


def test_warnings_of_runs_are_summarised_after_the_bar(tmp_path, capsys, monkeypatch):
    """A warning raised inside a run is recorded with it (RunResult.warnings) and printed once the bar is closed,
    never in the middle of it."""
    import warnings

    monkeypatch.setattr(study_module, "_warm_up", lambda scene: warnings.warn("a test warning", RuntimeWarning))
    st = run_study(SCENE, tmp_path, elements=["tet10"], ladder="small", duration=0.05, workers=0, plots=False)
    err = capsys.readouterr().err
    assert all(r.warnings == ["RuntimeWarning: a test warning"] for r in st.runs + [st.reference])
    bar_end = err.rindex(f"study {SCENE} (warped, dt 0.01 s)")
    note = err.index("# warning in ")
    assert note > bar_end and "a test warning" in err[note:] and "tet10_2x1x1 (warped, dt 0.01 s)" in err[note:]
    assert err.count("a test warning") == 1
    with pytest.warns(RuntimeWarning, match="a test warning"):  # without a bar: one warning with the summary
        run_study(SCENE, tmp_path, elements=["tet10"], ladder="small", duration=0.05, workers=0, plots=False,
                  progress=False, force=True)


def test_warning_summary_counts_newton_steps_accepted_on_cycling():
    runs = [_run("tet10", (4, 1, 1), 1.0, 1.0, 0.0), _run("tet10", (8, 1, 1), 1.0, 1.0, 0.0),
            _run("tet4", (4, 2, 2), 1.0, 1.0, 0.0)]
    for r, n in zip(runs, (3, 7, 0)):
        r.scheme, r.cycled_steps = "newton", n
        r.warnings = [study_module.NEWTON_CYCLE_WARNING + " 12 (t = 0.12 s) stalled ...: accepted"] if n else []
    runs[2].warnings = ["UserWarning: other"]
    lines = study_module.warning_summary(runs)
    assert lines[0].startswith("# 10 Newton steps accepted on contacts switching between iterates")
    assert "in 2 runs: tet10_4x1x1 (newton, dt 0.01 s): 3, tet10_8x1x1 (newton, dt 0.01 s): 7" in lines[0]
    assert lines[1:] == ["# warning in tet4_4x2x2 (newton, dt 0.01 s): UserWarning: other"]


def test_recommend_across_steps_names_every_stage_and_explains_the_time_error(tmp_path, capsys):
    """--schemes/--dts: a named bar per study ("[i/n] study ..."), the Newton reference its own bar in steps; none
    within a tolerance below the time discretisation error: the message gives that error and asks for a smaller dt."""
    from experiments.study import recommend_steps

    with pytest.raises(NoConfigurationWithinTolerance) as info:
        recommend_steps(SCENE, tmp_path, 1e-9, schemes=("warped",), dts=(0.02,), elements=["tet10"], ladder="small",
                        duration=0.1, workers=0, plots=False)
    err = capsys.readouterr().err
    assert f"[1/2] study {SCENE} (warped, dt 0.02 s)" in err
    assert "[2/2] reference tet10_16x2x2 (newton, dt 0.01 s)" in err and "10/10" in err and "step" in err
    msg = str(info.value)
    assert "backward Euler's time discretisation error against this reference, on the reference mesh tet10_16x2x2: " \
           "warped dt 0.02 s" in msg and "needs a smaller dt (--dts 0.01" in msg
    rec = info.value.recommendation
    assert "newton, dt 0.01 s" in rec.basis and "time discretisation error" in rec.basis


def test_a_material_is_checked_tagged_and_refused_where_its_model_cannot_run():
    from experiments.study import Material

    assert Material().default and Material().tag == "" and Material(model="warped").default
    assert Material(E=1e5, nu=0.45, model="neo-hookean").tag == "E100000_nu0.45_neo-hookean"
    for bad in ({"E": -1.0}, {"nu": 0.5}, {"model": "mooney"}):
        with pytest.raises(softbody.InvalidInputError):
            Material(**bad)
    with pytest.raises(softbody.InvalidInputError, match="--scheme newton"):
        Material(model="corotated").check_scheme("warped")
    with pytest.raises(softbody.InvalidInputError, match="--scheme newton"):
        run_study(SCENE, "/nonexistent", ladder="small", material=Material(model="neo-hookean"), progress=False)


def test_a_study_of_another_material_runs_it_and_keeps_it_apart(tmp_path):
    """The same small study with the cantilever's E halved: every run is made again (the cache knows the material),
    the results say which, and the beam sags about twice as far (the small-deflection regime: sag ~ 1 / E)."""
    from experiments.study import Material

    kw = dict(elements=["hex8"], ladder="small", duration=0.3, workers=0, plots=False, progress=False)
    base = run_study(SCENE, tmp_path, **kw)
    soft = run_study(SCENE, tmp_path, material=Material(E=2.5e7), **kw)
    assert sorted(soft.executed) == sorted(r.key for r in soft.runs + [soft.reference])  # none from the cache
    rows = csv_rows(tmp_path)
    assert {r["material"] for r in rows} == {"E2.5e+07"}
    ref0, ref1 = base.reference, soft.reference
    sag0 = ref0.values.min() - ref0.values[0]
    sag1 = ref1.values.min() - ref1.values[0]
    assert 1.8 < sag1 / sag0 < 2.2
    newton = run_study(SCENE, tmp_path / "nh", material=Material(model="neo-hookean"), scheme="newton", **kw)
    assert newton.reference.material == "neo-hookean" and newton.reference.status == "ok"
    # the neo-Hookean beam at the cantilever's small strain moves as the warped one under the same scheme
    warped = run_study(SCENE, tmp_path / "w", scheme="newton", **kw)
    assert np.abs(newton.reference.values - warped.reference.values).max() < 0.02 * abs(sag0)
