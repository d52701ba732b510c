"""Parameter sweeps (experiments/sweep.py, `softbody sweep`).

One small sweep of the canonical sheet-on-sphere (friction x element, coarse meshes, 0.3 s) is made once per
module on two local worker processes and shared by the tests; one test makes it again on a local two-worker
Dask cluster (as tests/test_study.py does for studies).
"""
from __future__ import annotations

import csv
import itertools
import math
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

from experiments import parse_param, run_sweep, sweep
from experiments.sweep import COLUMNS, TIMING, read_results
from experiments import cli
from softbody.errors import InvalidInputError

GRID = {"friction": [0.0, 0.2, 0.8], "element": ["tet4", "tet10"], "cells": [(4, 4, 2)]}
DURATION = 0.3


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep_sheet")
    return run_sweep("sheet-on-sphere", GRID, out, duration=DURATION, workers=2, progress=False)


def csv_rows(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_parse_param_types_values_and_refuses_bad_flags():
    assert parse_param("friction=0.2,0.8") == ("friction", [0.2, 0.8])
    assert parse_param("element=tet4,tet10") == ("element", ["tet4", "tet10"])
    assert parse_param("cells=6x6x2,8x8x2") == ("cells", [(6, 6, 2), (8, 8, 2)])
    assert parse_param("n=3") == ("n", [3]) and parse_param("warping=false") == ("warping", [False])
    for bad in ("friction", "=1,2", "friction=", "friction=0.2,", "1x=2"):
        with pytest.raises(InvalidInputError, match="--param"):
            parse_param(bad)


def test_a_canonical_sweep_has_one_row_per_run_in_grid_order_with_its_metrics(sheet):
    rows = csv_rows(sheet.out)
    assert len(rows) == 6 and len(sheet.rows) == 6
    header = list(rows[0])
    assert header[:3] == ["friction", "element", "cells"]
    assert header[3:3 + len(COLUMNS)] == list(COLUMNS)
    assert "max_force_N[sphere]" in header
    assert [(r["friction"], r["element"]) for r in rows] == [(f, e) for f in ("0.0", "0.2", "0.8") for e in ("tet4", "tet10")]
    for r in sheet.rows:
        assert r["status"] == "ok" and r["error"] == "" and r["diverged"] == 0
        assert r["steps"] == 30 and r["t_end_s"] == pytest.approx(DURATION) and r["dt_s"] == 0.01
        assert r["cells"] == (4, 4, 2)
        assert 0 < r["ms_per_step"] < 1e3 and r["wall_s"] > 0
        assert 0 <= r["max_penetration_mm"] < 5
        # the monitored corner (rest z = 0.35 m) fell: its end and extremes are consistent
        assert r["monitor_max"] == pytest.approx(0.35, abs=1e-9)
        assert r["monitor_min"] <= r["monitor_end"] <= r["monitor_max"] and r["monitor_end"] < 0.35
        # the sheet (250 kg) lands on the sphere within 0.3 s: at least its weight on the sphere at some step
        assert r["max_force_N[sphere]"] > 250 * 9.81
        assert r["energy_drift_J"] < 0 and r["energy_max_rise_J"] < 1.0  # damping and contact take energy
    for element in ("tet4", "tet10"):  # a higher friction never lets the sheet slide further
        slips = [r["slip_mm"] for r in sheet.rows if r["element"] == element]
        assert all(a >= b - 1e-9 for a, b in zip(slips, slips[1:])), (element, slips)
    tet10 = [r["slip_mm"] for r in sheet.rows if r["element"] == "tet10"]
    assert tet10[0] > 1.0 and tet10[-1] < 0.1  # frictionless it slides mm, at mu = 0.8 it sticks


def test_rows_carry_the_parameters_as_given_fresh_from_the_cache_and_from_the_csv(sheet):
    grid = [dict(zip(GRID, values)) for values in itertools.product(*GRID.values())]
    cached = run_sweep("sheet-on-sphere", GRID, sheet.out, duration=DURATION, workers=0, progress=False, plots=False)
    assert cached.executed == []
    for how, rows in (("fresh", sheet.rows), ("cache", cached.rows), ("csv", read_results(sheet.out))):
        params = [{k: r[k] for k in GRID} for r in rows]
        assert params == grid, how
        for got, given in zip(params, grid):
            assert {k: type(v) for k, v in got.items()} == {k: type(v) for k, v in given.items()}, how
    assert csv_rows(sheet.out)[0]["cells"] == "4x4x2"  # the CSV writes cells as on the command line


def test_outputs_plots_summary_and_the_cache(sheet):
    out = sheet.out
    for name in ("friction.png", "element.png"):
        assert (out / "plots" / name).stat().st_size > 10_000
    assert not (out / "plots" / "cells.png").exists()  # one value: nothing to plot against
    assert (out / "trajectories.png").exists()
    summary = (out / "summary.md").read_text()
    assert "# Sweep: sheet-on-sphere" in summary and "6 ok, 0 diverged, 0 failed" in summary
    assert "## Effect of friction" in summary and "## Effect of element" in summary
    assert len(list((out / "runs").glob("*.npz"))) == 6
    again = run_sweep("sheet-on-sphere", GRID, out, duration=DURATION, workers=0, progress=False)
    assert again.executed == [] and again.rows == sheet.rows  # all from the cache, identical
    back = read_results(out)
    assert [r["slip_mm"] for r in back] == [r["slip_mm"] for r in sheet.rows]  # the CSV round-trips floats
    # resumable: a lost run is made again, the others come from the cache
    victim = sorted((out / "runs").glob("friction=0.2_element=tet10*.npz"))[0]
    victim.unlink()
    resumed = run_sweep("sheet-on-sphere", GRID, out, duration=DURATION, workers=1, progress=False)
    assert len(resumed.executed) == 1 and "friction=0.2_element=tet10" in resumed.executed[0]
    strip = lambda rows: [{k: v for k, v in r.items() if k not in TIMING} for r in rows]  # noqa: E731
    assert strip(resumed.rows) == strip(sheet.rows)


def test_a_failing_run_is_a_row_with_its_error_not_a_crashed_sweep(tmp_path):
    rows = sweep("cantilever", {"nu": [0.3, 0.5], "cells": [(4, 1, 1)]}, out=tmp_path, duration=0.05,
                 workers=0, progress=False)
    ok, bad = rows
    assert ok["status"] == "ok" and ok["steps"] == 5
    assert bad["status"] == "error" and bad["diverged"] == 0 and bad["steps"] == 0
    assert "InvalidInputError" in bad["error"] and "nu must satisfy" in bad["error"]  # LinearElastic's refusal
    assert math.isnan(bad["ms_per_step"]) and math.isnan(bad["monitor_end"])
    assert "## Failed runs" in (tmp_path / "summary.md").read_text()
    assert csv_rows(tmp_path)[1]["status"] == "error"


def test_a_diverging_run_is_a_row_marked_diverged(tmp_path):
    scene = tmp_path / "blowup.py"
    scene.write_text(textwrap.dedent('''
        import softbody as sb
        from integration import World

        def scene(E=1e5, max_energy=1e9):
            world = World(dt=0.01, max_energy=max_energy)
            body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4", center=(0, 0, 1.0)),
                              sb.LinearElastic(E, 0.3, 1000))
            world.add_soft(body)
            return world
    '''))
    rows = sweep(scene, {"max_energy": [1e9, 1e-6]}, duration=0.05, workers=0, progress=False)
    assert [r["status"] for r in rows] == ["ok", "diverged"]
    assert rows[1]["diverged"] == 1 and rows[1]["error"].startswith("SimulationDiverged:")
    assert rows[1]["steps"] == 0


USER_SCENE = '''
"""A soft cube dropped on a plane; the sweep's test scene."""
import softbody as sb
from integration import World

DURATION = 0.2

def scene(friction=0.5, height=0.05, E=2e5, dt=0.01, fail=False):
    if fail:
        raise RuntimeError("this run fails on purpose")
    world = World(dt=dt)
    world.add_plane(name="floor")
    body = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet4", center=(0, 0, 0.05 + height)),
                      sb.LinearElastic(E, 0.3, 1000), damping=(0.5, 0.001))
    world.add_soft(body, friction=friction)
    return world

def monitor(world):
    return float(world.bodies[0].positions[:, 2].min())

def metrics(world):
    return {"final_top_m": float(world.bodies[0].positions[:, 2].max()), "kind": world.bodies[0].mesh.kind}
'''


def test_a_user_scene_file_with_monitor_and_metrics(tmp_path):
    path = tmp_path / "cube_drop.py"
    path.write_text(USER_SCENE)
    result = run_sweep(path, {"height": [0.0, 0.05], "fail": [False, True]}, tmp_path / "out", workers=0, progress=False)
    rows = result.rows
    assert result.scene == "cube_drop" and len(rows) == 4
    assert [r["status"] for r in rows] == ["ok", "error", "ok", "error"]
    assert "RuntimeError: this run fails on purpose" in rows[1]["error"]
    for r in (rows[0], rows[2]):
        assert r["steps"] == 20  # DURATION of the file
        assert r["monitor_min"] < 0.002 and r["monitor_end"] == pytest.approx(0.0, abs=2e-3)  # on the floor
        assert 0.09 < r["final_top_m"] < 0.105 and r["kind"] == "tet4"  # the user's metrics, as columns
        assert r["max_force_N[floor]"] > 1000 * 1e-3 * 9.81  # at least the cube's weight (1 kg)
    assert rows[2]["monitor_max"] == pytest.approx(0.05)  # dropped from 5 cm
    assert rows[2]["max_force_N[floor]"] > rows[0]["max_force_N[floor]"]  # an impact beats a set-down
    header = list(csv_rows(tmp_path / "out")[0])
    assert header[-3:] == ["max_force_N[floor]", "final_top_m", "kind"]
    # the file's text is part of the cache key: an edited scene is run again
    path.write_text(USER_SCENE.replace("damping=(0.5, 0.001)", "damping=(0.6, 0.001)"))
    again = run_sweep(path, {"height": [0.0]}, tmp_path / "out", workers=0, progress=False)
    assert len(again.executed) == 1


def test_bad_sweeps_are_usage_errors_naming_what_is_valid(tmp_path):
    with pytest.raises(InvalidInputError, match="takes no parameter 'frction'; its parameters: element, cells"):
        run_sweep("sheet-on-sphere", {"frction": [0.1]}, workers=0, progress=False)
    with pytest.raises(InvalidInputError, match="unknown scene 'nope'"):
        run_sweep("nope", {"friction": [0.1]}, workers=0, progress=False)
    with pytest.raises(InvalidInputError, match="dt is both swept"):
        run_sweep("cantilever", {"dt": [0.01]}, dt=0.01, workers=0, progress=False)
    with pytest.raises(InvalidInputError, match="no values"):
        run_sweep("cantilever", {"E": []}, workers=0, progress=False)
    not_a_scene = tmp_path / "x.py"
    not_a_scene.write_text("x = 1\n")
    with pytest.raises(InvalidInputError, match="must define scene"):
        run_sweep(not_a_scene, {"a": [1]}, workers=0, progress=False)
    broken = tmp_path / "broken.py"
    broken.write_text("import no_such_module_here\n")
    with pytest.raises(InvalidInputError, match="broken.py failed to load: ModuleNotFoundError"):
        run_sweep(broken, {"a": [1]}, workers=0, progress=False)
    with pytest.raises(SystemExit) as exc:
        cli.main(["sweep", "cantilever", "--param", "E=1e5", "--param", "E=2e5"])
    assert exc.value.code == 2


@pytest.mark.parametrize("scene, grid, message", [
    ("cantilever", {"E": [5e6, "abc"]}, "parameter E takes a number (its default: 50000000.0), got 'abc'"),
    ("cantilever", {"cells": [(4, 1)]}, "parameter cells takes 3 integers (NxNxN on the command line)"),
    ("sheet-on-sphere", {"warping": [1]}, "parameter warping takes true or false"),
    ("sheet-on-sphere", {"element": ["tet5"]}, "parameter element takes one of hex8, tet10, tet4, got 'tet5'"),
    ("cantilever", {"scheme": ["implicit"]}, "parameter scheme takes one of warped, newton"),
    ("cubes-on-plane", {"count": [2.5]}, "parameter count takes an integer"),
])
def test_a_value_the_scene_cannot_take_is_refused_before_any_run(scene, grid, message, tmp_path):
    with pytest.raises(InvalidInputError, match=re.escape(message)):
        run_sweep(scene, grid, tmp_path, workers=0, progress=False)
    assert not (tmp_path / "runs").exists()  # nothing ran


def test_a_user_files_parameters_are_checked_against_its_defaults(tmp_path):
    path = tmp_path / "cube_drop.py"
    path.write_text(USER_SCENE)
    with pytest.raises(InvalidInputError, match="parameter fail takes true or false"):
        run_sweep(path, {"fail": ["no"]}, workers=0, progress=False)
    with pytest.raises(InvalidInputError, match="parameter height takes a number"):
        run_sweep(path, {"height": ["high"]}, workers=0, progress=False)


def test_the_command_line_exits_2_on_a_bad_value_and_1_when_every_run_failed(tmp_path, capsys):
    base = ["--param", "cells=4x1x1", "--duration", "0.02", "--workers", "0", "--no-progress"]
    with pytest.raises(SystemExit) as exc:
        cli.main(["sweep", "cantilever", "--param", "E=abc", "--out", str(tmp_path / "a"), *base])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "parameter E takes a number" in err and "'abc'" in err
    assert not (tmp_path / "a").exists()
    # nu = 0.5 is a number, which LinearElastic refuses when the run builds its body: both runs fail
    assert cli.main(["sweep", "cantilever", "--param", "nu=0.5,0.6", "--out", str(tmp_path / "b"), *base]) == 1
    err = capsys.readouterr().err
    assert "every run failed" in err and "nu must satisfy" in err
    assert [r["status"] for r in read_results(tmp_path / "b")] == ["error", "error"]
    # one run of two failing is a sweep with a failure, not a failed command
    assert cli.main(["sweep", "cantilever", "--param", "nu=0.3,0.5", "--out", str(tmp_path / "c"), *base]) == 0


def test_the_command_line(tmp_path, capsys):
    out = tmp_path / "cli"
    code = cli.main(["sweep", "cantilever", "--param", "E=5e6,5e7", "--param", "cells=4x1x1", "--duration", "0.05",
                     "--out", str(out), "--workers", "0", "--no-progress"])
    assert code == 0
    text = capsys.readouterr().out
    assert "| E | cells | status |" in text and "2 runs (2 made, 0 from the cache)" in text
    rows = csv_rows(out)
    assert [r["E"] for r in rows] == ["5000000.0", "50000000.0"] and all(r["status"] == "ok" for r in rows)
    assert [(r["E"], r["cells"]) for r in read_results(out)] == [(5e6, (4, 1, 1)), (5e7, (4, 1, 1))]
    # a softer beam sags further at its tip
    assert float(rows[0]["monitor_min"]) < float(rows[1]["monitor_min"])


def test_record_writes_one_recording_per_run_made(tmp_path):
    result = run_sweep("cantilever", {"E": [5e6, 5e7], "cells": [(4, 1, 1)]}, tmp_path, duration=0.03, workers=0,
                       record=True, progress=False)
    files = sorted((tmp_path / "recordings").glob("*.rrd"))
    assert len(files) == 2 and all(f.stat().st_size > 1000 for f in files)
    assert [f.stem for f in files] == sorted(result.executed)
    with pytest.raises(InvalidInputError, match="record=True needs an out directory"):
        run_sweep("cantilever", {"E": [5e6]}, record=True, workers=0, progress=False)


def test_contact_force_of_one_soft_body(tmp_path):
    import softbody as sb
    from integration import World

    world = World(dt=0.01)
    floor = world.add_plane()
    a = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4", center=(0, 0, 0.05)), sb.LinearElastic(1e5, 0.3, 1000))
    b = sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (1, 1, 1), "tet4", center=(0.5, 0, 0.05)), sb.LinearElastic(1e5, 0.3, 2000))
    world.add_soft(a)
    world.add_soft(b)
    world.run(0.5)
    fa, fb = world.contact_force(floor, soft=a), world.contact_force(floor, soft=b)
    np.testing.assert_allclose(fa + fb, world.contact_force(floor), rtol=1e-12, atol=1e-12)
    assert fb[2] == pytest.approx(2 * fa[2], rel=0.05) and fa[2] == pytest.approx(-1.0 * 9.81, rel=0.05)
    with pytest.raises(InvalidInputError, match="soft must be a soft body of this World"):
        world.contact_force(floor, soft=sb.FemBody(a.mesh, sb.LinearElastic(1e5, 0.3, 1000)))
    world.close()


def test_local_and_two_worker_dask_sweeps_give_identical_rows(sheet, tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = run_sweep("sheet-on-sphere", GRID, tmp_path, duration=DURATION, cluster=cluster.scheduler_address,
                           progress=False)
    assert len(remote.executed) == 6
    for p, q in zip(remote.rows, sheet.rows):  # bit-identical: == on every float but the timings
        differ = {k: (p[k], q[k]) for k in p if k not in TIMING and p[k] != q[k]}
        assert not differ, (p["friction"], p["element"], differ)
    for p, q in zip(remote.points, sheet.points):
        assert np.array_equal(p.times, q.times) and np.array_equal(p.values, q.values)
