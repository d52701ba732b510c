"""The ``softbody`` command line as a new user meets it: flags, recording paths, size guard, signals, output."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import softbody
from experiments import cli, sizing, study


def _refused(argv: list[str], capsys) -> str:
    """Run the command line, expect a usage error (exit 2); return what it wrote to stderr."""
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    return capsys.readouterr().err.strip()


# ---------------------------------------------------------------------------- recommend --tolerance
@pytest.mark.parametrize("text, metres", [("2mm", 0.002), ("0.5cm", 0.005), ("0.002m", 0.002), ("2 MM", 0.002),
                                          ("1e-1mm", 1e-4)])
def test_tolerance_with_a_unit_is_in_metres(text, metres):
    assert cli._length(text) == pytest.approx(metres, rel=1e-12)


@pytest.mark.parametrize("argv, shown", [
    (["--tolerance", "2"], "'2' has no unit: write 2mm, 2cm or 2m"),
    (["--tolerance", "0.002"], "'0.002' has no unit"),
    (["--tolerance=-1mm"], "expected a finite length > 0, got '-1mm'"),
    (["--tolerance", "-1mm"], "expected a finite length > 0, got '-1mm'"),
    (["--tolerance", "-.5cm"], "expected a finite length > 0, got '-.5cm'"),
    (["--tolerance", "0mm"], "expected a finite length > 0, got '0mm'"),
    (["--tolerance", "2km"], "with a unit (mm, cm or m)"),
])
def test_bad_tolerance_is_refused_before_any_study_runs(argv, shown, capsys, tmp_path, monkeypatch):
    def no_study(*a, **kw):
        raise AssertionError("a study ran before the tolerance was checked")

    monkeypatch.setattr(study, "run_study", no_study)
    out = tmp_path / "study"
    err = _refused(["recommend", "sheet-on-sphere", *argv, "--study", str(out)], capsys).splitlines()[-1]
    assert "argument --tolerance" in err and shown in err, err
    assert not out.exists()


# ---------------------------------------------------------------------------- run --record PATH
RUN = ["run", "cantilever", "--element", "tet4", "--cells", "2", "1", "1", "--duration", "0.02"]


def _no_build(*a, **kw):
    raise AssertionError("the scene was built before the --record path was checked")


def test_record_into_a_directory_writes_a_timestamped_file_inside(tmp_path, capsys):
    folder = tmp_path / "recordings"
    folder.mkdir()
    assert cli.main([*RUN, "--record", str(folder)]) == 0
    inside = list(folder.iterdir())
    assert len(inside) == 1 and inside[0].name.startswith("cantilever_tet4_2x1x1_") and inside[0].suffix == ".rrd"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recordings"]  # no recordings.rrd beside it
    assert str(inside[0]) in capsys.readouterr().out
    # a path ending in a separator is a directory too, made if need be
    assert cli.main([*RUN, "--record", str(tmp_path / "new") + "/"]) == 0
    made = list((tmp_path / "new").iterdir())
    assert len(made) == 1 and made[0].name.startswith("cantilever_tet4_2x1x1_")


def test_an_existing_recording_is_kept_without_force(tmp_path, capsys, monkeypatch):
    path = tmp_path / "run.rrd"
    path.write_bytes(b"an earlier recording")
    with monkeypatch.context() as m:
        m.setattr(cli, "build_scene", _no_build)
        err = _refused([*RUN, "--record", str(path)], capsys)
    assert err.startswith(f"softbody: error: the recording {path} already exists") and "--force" in err, err
    assert path.read_bytes() == b"an earlier recording"
    assert cli.main([*RUN, "--record", str(path), "--force"]) == 0
    from rerun.chunk import RrdReader

    assert any(c.entity_path == "/world/soft/body0" for c in RrdReader(path).stream())


@pytest.mark.parametrize("where", ["below a file", "proc"])
def test_an_unwritable_record_path_is_one_line_before_the_run(where, tmp_path, capsys, monkeypatch):
    if where == "below a file":
        (tmp_path / "notes.txt").write_text("")
        path, reason = tmp_path / "notes.txt" / "x.rrd", f"{tmp_path / 'notes.txt'} is not a directory"
    else:
        import os
        import tempfile

        if not os.path.isdir("/proc"):
            pytest.skip("no /proc")
        try:
            tempfile.TemporaryFile(dir="/proc").close()
            pytest.skip("/proc is writable here")
        except OSError:
            pass
        path, reason = "/proc/x.rrd", "/proc is not writable"
    monkeypatch.setattr(cli, "build_scene", _no_build)
    err = _refused([*RUN, "--record", str(path)], capsys)
    assert err.startswith(f"softbody: error: cannot write a recording to {path}: ") and "\n" not in err, err
    assert reason in err


# ---------------------------------------------------------------------------- output
ROOT = Path(__file__).resolve().parents[1]


def _python(*args: str, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60, **kw)


def test_help_has_no_pybullet_banner():
    out = _python("-m", "softbody", "--help")
    assert out.returncode == 0 and out.stdout.startswith("usage: softbody")
    assert "pybullet build time" not in out.stdout + out.stderr, out.stdout + out.stderr
    # the banner is real: pybullet imported on its own prints it
    bare = _python("-c", "import pybullet")
    assert "pybullet build time" in bare.stdout + bare.stderr


def test_quiet_c_output_restores_the_descriptors(capfd):
    from integration import quiet_c_output

    with quiet_c_output():
        os.write(1, b"hidden out\n")
        os.write(2, b"hidden err\n")
    os.write(1, b"shown out\n")
    out, err = capfd.readouterr()
    assert out == "shown out\n" and err == ""


# ---------------------------------------------------------------------------- signals
def test_a_signal_turned_into_a_system_error_by_c_code_still_terminates(capsys):
    """A SIGTERM whose exception surfaced as a SystemError (it arrived while C code called back into Python: numba
    loading a compiled kernel from its cache does) exits with 128 + the signal number, and Ctrl-C likewise with 130;
    a SystemError of any other cause is not swallowed."""
    import argparse

    from experiments.cli import Terminated, _dispatch

    def raising(first: BaseException):
        def command():
            try:
                raise first
            except BaseException as exc:  # what CPython does when a C function returns with an exception set
                raise SystemError("<function _numba_unpickle> returned a result with an exception set") from exc
        return command

    parser = argparse.ArgumentParser(prog="softbody")
    assert _dispatch(parser, raising(Terminated(signal.SIGTERM))) == 128 + signal.SIGTERM
    assert "terminated by SIGTERM" in capsys.readouterr().err
    assert _dispatch(parser, raising(KeyboardInterrupt())) == 130
    with pytest.raises(SystemError):
        _dispatch(parser, raising(ValueError("not a signal")))


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_termination_during_run_record_leaves_a_verified_recording(signum, tmp_path):
    """SIGTERM / SIGHUP during `softbody run --record`: the recording is flushed and closed (rerun verifies it,
    with every printed time in it), and the exit code is 128 + the signal number."""
    from test_recording import read, verify

    path = tmp_path / "x.rrd"
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "softbody", "run", "sheet-on-sphere", "--cells", "2", "2", "1",
                             "--element", "tet4", "--duration", "100", "--record", str(path)],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        printed = []
        for line in proc.stdout:
            if not line.startswith("#") and not line.lstrip().startswith("t ["):
                printed.append(float(line.split()[0]))
            if len(printed) == 3:
                break
        assert len(printed) == 3, proc.stderr.read()
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signum, err
    assert f"terminated by {signal.Signals(signum).name}" in err and "Traceback" not in err, err
    assert f"# recording: {path}" in out
    verify(path)
    data, _ = read(path)
    times = data["/world/soft/body0"]["sim_time"]
    assert times[0] == 0.0 and times[-1] >= printed[-1] - 1e-9


# ---------------------------------------------------------------------------- size guard
def test_a_run_too_big_for_the_memory_is_refused_before_anything_is_built(capsys, monkeypatch):
    monkeypatch.setattr(sizing, "available_memory_mb", lambda: 8000.0)
    monkeypatch.setattr(cli, "build_scene", _no_build)
    tic = time.perf_counter()
    err = _refused(["run", "sheet-on-sphere", "--cells", "100", "100", "30"], capsys)  # tet10, the scene's default
    assert time.perf_counter() - tic < 2.0
    assert "\n" not in err and "tet10 cells 100x100x30 (2,164,461 nodes, 1,500,000 elements)" in err, err
    assert "but 7.8 GB are available" in err
    memory = float(re.search(r"needs about ([\d.]+) GB of memory", err).group(1))
    assert memory > 50  # 45-60 MB per 1000 nodes
    cells = [int(c) for c in re.search(r"--cells (\d+) (\d+) (\d+) would need", err).groups()]
    fit = sizing.estimate("tet10", cells)
    assert fit.memory_mb <= 0.5 * 8000.0 and sizing.estimate("tet10", [c + 1 for c in cells]).memory_mb > 0.5 * 8000.0
    assert cells[0] == cells[1] and cells[2] < cells[0]  # the grid's proportions kept


def test_a_large_run_is_warned_about_before_it_is_built(capsys, monkeypatch):
    monkeypatch.setattr(sizing, "available_memory_mb", lambda: 1e6)

    def built(*a, **kw):
        raise softbody.InvalidInputError("stopped where the scene would be built")

    monkeypatch.setattr(cli, "build_scene", built)
    err = _refused(["run", "hanging-tube", "--element", "tet4", "--cells", "40", "12", "100", "--duration", "1"], capsys)
    warning, stop = err.splitlines()
    assert warning.startswith("# warning: hanging-tube tet4 cells 40x12x100 (52,520 nodes, 240,000 elements) needs about")
    assert "(100 steps: " in warning and stop.endswith("stopped where the scene would be built")


def test_the_memory_estimate_matches_a_measured_run(monkeypatch):
    """benchmarks/memory_model.py's measurement of a fresh process: the model is within 25% of its peak."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from memory_model import measure

    r = measure("hex8", (24, 24, 6), steps=12)
    e = sizing.estimate("hex8", (24, 24, 6))
    assert (e.nodes, e.elements) == (r["nodes"], r["elements"])
    assert 0.75 < e.memory_mb / r["peak_mb"] < 1.25, (e.memory_mb, r["peak_mb"])


def test_a_run_takes_the_material_and_says_what_a_model_needs(capsys):
    """--E, --nu, --model reach the body; a hyperelastic model without --scheme newton is one line, before the run."""
    argv = ["run", "cantilever", "--element", "hex8", "--cells", "4", "1", "1", "--duration", "0.05"]
    err = _refused([*argv, "--model", "neo-hookean"], capsys)
    assert "--scheme newton" in err and "Traceback" not in err
    assert cli.main([*argv, "--model", "neo-hookean", "--scheme", "newton", "--E", "2e7", "--nu", "0.4"]) == 0
    assert "neo-hookean model, E 2e+07 Pa, nu 0.4" in capsys.readouterr().out
    err = _refused([*argv, "--nu", "0.5"], capsys)
    assert "nu" in err and "Traceback" not in err
