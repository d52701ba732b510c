"""The benchmark command (experiments/bench.py, ``softbody bench``) runs on a tiny configuration and
writes its JSON, markdown and plot with the expected fields. Timings are not asserted (CI machines are
noisy); only that each figure is there and is a number."""
from __future__ import annotations

import json
import math

import meshio
import numpy as np
import pytest

from experiments import bench
from experiments.cli import main
from softbody import box_mesh
from softbody.errors import InvalidInputError

TABLE_COLUMNS = ["config", "elements", "nodes", "DOFs", "ms/step [min-max]", "floor ms", "step/floor",
                 "pybullet ms per 0.01 s (k)", "ours/pybullet", "overhead %", "peak MB", "kB/node"]


def _number(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def test_run_bench_tiny_writes_json_markdown_plot_profile_and_pybullet(tmp_path):
    results = bench.run_bench(bench.TINY_CONFIGS, steps=2, repeats=2, warmup=12, threads=1, out_dir=tmp_path,
                              include_pybullet=True, record=False, floor_repeats=2, profile_steps=2,
                              pybullet_max_k=2, log=lambda *a, **k: None)
    assert len(results) == 1
    r = results[0]
    assert "error" not in r, r.get("traceback")
    doc = json.loads((tmp_path / "bench.json").read_text())
    assert doc["results"][0]["label"] == r["label"] == "sheet tet4 (4,4,2)"
    assert doc["settings"]["threads"] == 1 and doc["machine"]["cpus"] >= 1
    assert (r["elements"], r["nodes"], r["dofs"]) == (160, 75, 225)
    for key in ("ms_per_step", "ms_per_step_min", "ms_per_step_max", "floor_ms", "floor_factorize_ms",
                "floor_solve_ms", "step_over_floor", "overhead_pct", "peak_rss_mb", "baseline_rss_mb",
                "factorizations_per_step", "contacts_mean"):
        assert _number(r[key]), key
    assert len(r["ms_per_step_blocks"]) == 2
    assert r["ms_per_step_min"] <= r["ms_per_step"] <= r["ms_per_step_max"]
    for phase in ("collision", "rotations", "forces", "assembly", "factorize", "solve", "contact", "total"):
        assert _number(r["phases_ms"][phase]), phase
    assert r["method"] in ("direct", "iterative") and r["threads"] == 1
    assert r["floor_backend"] in ("pardiso", "blocks", "superlu")
    assert r["contacts_max"] >= 1  # 12 warm-up steps: the sheet touches the sphere after about 10
    # the profile: a table on disk and calls per step far below the element count of a per-element loop
    prof = r["profile"]
    assert (tmp_path / "profiles" / "sheet-on-sphere_tet4_4x4x2.txt").read_text().count("ncalls") >= 2
    assert _number(prof["max_calls_per_step"]) and prof["function_calls_per_step"] > 0
    assert 0 < prof["python_calls_per_step"] < prof["function_calls_per_step"]  # C functions counted apart
    # pybullet: the identical mesh was loaded (checked inside), k = 1 and 2 tried
    pb = r["pybullet"]
    assert "error" not in pb, pb.get("traceback")
    assert [t["k"] for t in pb["tried"]][0] == 1 and pb["nodes"] == 75 and pb["tets"] == 160
    for t in pb["tried"]:
        assert isinstance(t["stable"], bool) and _number(t["max_disp_m"])
        assert (t["ms_per_step"] is None) == (not t["stable"])
    if pb["k"] is not None:
        assert _number(pb["ms_per_step"]) and _number(r["ours_over_pybullet"])
        # ours/pybullet from our blocks alternating with pybullet's in one process: one pair per block
        stable = next(t for t in pb["tried"] if t["k"] == pb["k"])
        assert len(stable["paired_ours_ms"]) == len(stable["paired_pybullet_ms"]) == 2
        assert r["ours_over_pybullet"] == pb["paired_ratio"] == pytest.approx(np.median(
            np.array(stable["paired_ours_ms"]) / np.array(stable["paired_pybullet_ms"])), rel=1e-12)
        assert _number(r["ours_over_pybullet_cross_process"])
    md = (tmp_path / "bench.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| config | elements"))
    cells = [c.strip() for c in header.strip("|").split("|")]
    for col in TABLE_COLUMNS:
        assert col in cells, col
    assert "| sheet tet4 (4,4,2) | 160 | 75 | 225 |" in md
    assert (tmp_path / "bench.png").stat().st_size > 1000 and not (tmp_path / "scaling.png").exists()


def test_cli_bench_tiny_without_pybullet(tmp_path, capsys):
    assert main(["bench", "--tiny", "--no-pybullet", "--out", str(tmp_path), "--steps", "2", "--repeats", "1",
                 "--profile-steps", "0", "--floor-repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "| sheet tet4 (4,4,2) |" in out and "step/floor" in out
    doc = json.loads((tmp_path / "bench.json").read_text())
    r = doc["results"][0]
    assert "pybullet" not in r and "profile" not in r and _number(r["floor_ms"])
    assert doc["settings"]["steps"] == 2 and doc["settings"]["repeats"] == 1
    assert (tmp_path / "bench.md").exists() and (tmp_path / "bench.png").exists()


def test_cli_bench_large_runs_the_large_ladder_without_floor_profile_or_pybullet(tmp_path, monkeypatch):
    """``softbody bench --large``: the tet4 sheets of issue 34 (72k, 235k and 549k nodes: (n+1)^2 (n/4+1) corners), the
    steps into the impact, no floor (a fresh double-precision factor of the largest does not fit), no profile, no
    pybullet, into large.json (here the measurement is replaced by a recorder of its arguments)."""
    seen = {}

    def fake(configs, **kw):
        seen.update(kw, configs=[bench.parse_config(c) for c in configs])
        return []

    monkeypatch.setattr(bench, "run_bench", fake)
    assert main(["bench", "--large", "--out", str(tmp_path)]) == 0
    cells = [c.cells for c in seen["configs"]]
    assert [(a + 1) * (b + 1) * (c + 1) for a, b, c in cells] == [71_825, 235_225, 549_153]
    assert {c.element for c in seen["configs"]} == {"tet4"}
    assert seen["name"] == "large" and seen["floor_repeats"] == 0 and seen["profile_steps"] == 0
    assert seen["pybullet_cells"] == []
    # the timed steps hold the impact: the sheet falls 5 cm onto the sphere, sqrt(2 0.05 / 9.81) = 0.101 s (step 10 or
    # 11), and a window of at least ten steps from there (a set-up of the preconditioner falls in it or not)
    first = math.ceil(math.sqrt(2 * 0.05 / 9.81) / 0.01)
    assert seen["warmup"] < first and seen["warmup"] + seen["steps"] >= first + 10


def test_parse_config_forms():
    c = bench.parse_config("tet4:24x24x6")
    assert c == bench.Config("sheet-on-sphere", "tet4", (24, 24, 6)) and c.label == "sheet tet4 (24,24,6)"
    assert bench.parse_config("hanging-tube:tet10:8x1x6").cells == (8, 1, 6)
    assert bench.parse_config(("sheet-on-sphere", "hex8", [20, 20, 5])).element == "hex8"
    assert bench.parse_config({"element": "tet10", "cells": (9, 9, 2)}).scene == "sheet-on-sphere"
    for bad in ("tet4", "tet5:2x2x2", "tet4:2x2", "nowhere:tet4:2x2x2", "tet4:axbxc", "tet4:0x2x2"):
        with pytest.raises(InvalidInputError):
            bench.parse_config(bad)


def test_tet_vtk_round_trip(tmp_path):
    """The legacy ASCII file pybullet reads: the same points and 4-node tets (meshio reads it back)."""
    mesh = box_mesh((1.0, 1.0, 0.25), (2, 2, 1), "tet4", center=(0, 0, 0.475))
    path = tmp_path / "m.vtk"
    bench.write_tet_vtk(path, mesh.nodes, mesh.elements)
    back = meshio.read(path)
    np.testing.assert_array_equal(back.points, mesh.nodes)
    np.testing.assert_array_equal(back.cells_dict["tetra"], mesh.elements)
    lines = path.read_text().splitlines()
    start = lines.index(f"POINTS {mesh.n_nodes} double")
    assert all(len(lines[start + 1 + i].split()) == 3 for i in range(mesh.n_nodes))  # one point per line


def test_a_failing_measurement_process_reports_instead_of_hanging():
    r = bench.run_in_fresh_process("no_such_measurement", {}, threads=1, timeout=120)
    assert "error" in r and "no_such_measurement" in r["error"]


def test_markdown_and_fits_tolerate_failed_and_partial_results():
    ok = {"label": "sheet tet4 (2,2,1)", "element": "tet4", "nodes": 18, "elements": 20, "dofs": 54,
          "method": "direct", "ms_per_step": 2.0, "ms_per_step_min": 1.0, "ms_per_step_max": 3.0, "floor_ms": 0.5,
          "step_over_floor": 4.0, "overhead_pct": 50.0, "peak_rss_mb": 100.0, "baseline_rss_mb": 90.0,
          "phases_ms": {"solve": 1.0, "total": 2.0}, "phases_total_ms": 2.0, "contacts_mean": 1.0,
          "contacts_max": 1, "factorizations_per_step": 1.0, "pcg_iterations_per_step": None}
    big = dict(ok, label="sheet tet4 (4,4,2)", nodes=72, ms_per_step=8.0, floor_ms=2.0, peak_rss_mb=110.0)
    doc = {"name": "bench", "created": "now", "machine": {}, "settings": {"threads": 1, "warmup": 1, "steps": 1,
                                                                         "repeats": 1, "pybullet_max_k": 4},
           "results": [ok, big, {"label": "sheet hex8 (9,9,9)", "element": "hex8", "error": "MemoryError: boom"}]}
    md = bench.markdown(doc)
    assert "failed: MemoryError: boom" in md and "ms/step ~ N^" in md
    fit = bench.fit_scaling(doc["results"][:2])["tet4"]
    assert fit["time_exponent"] == pytest.approx(1.0) and fit["floor_exponent"] == pytest.approx(1.0)


def test_the_plot_of_one_tiny_result_is_named_for_its_run_with_plain_number_ticks(tmp_path, monkeypatch):
    """One configuration (bench --tiny): bench.png, and every axis has at least two ticks read as plain numbers."""
    from matplotlib.figure import Figure

    r = {"label": "sheet tet4 (4,4,2)", "scene": "sheet-on-sphere", "element": "tet4", "nodes": 75, "ms_per_step": 2.4,
         "floor_ms": 0.6, "peak_rss_mb": 104.0, "baseline_rss_mb": 100.0}
    (tmp_path / "bench.json").write_text(json.dumps({"results": [r]}))
    figures = []
    save = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **kw: (figures.append(fig), save(fig, *a, **kw)))
    assert bench.plot_scaling(tmp_path, "bench") == tmp_path / "bench.png"
    fig, = figures
    fig.canvas.draw()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            shown = [(t, lab.get_text()) for t, lab in zip(axis.get_majorticklocs(), axis.get_majorticklabels())
                     if lo <= t <= hi]
            assert len(shown) >= 2, shown
            for t, text in shown:
                assert float(text) == pytest.approx(t), (text, t)  # "4", "0.5", "200": no 4x10^0
            assert not any(lab.get_text() for lab in axis.get_minorticklabels())


def test_memory_per_node_is_the_peak_above_the_imports_over_the_nodes():
    assert bench.kb_per_node({"peak_rss_mb": 300.0, "baseline_rss_mb": 200.0, "nodes": 1024}) == pytest.approx(100.0)
    assert bench.kb_per_node({"peak_rss_mb": 300.0, "nodes": 1024}) is None
