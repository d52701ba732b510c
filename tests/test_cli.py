"""The ``softbody`` command line as a new user meets it: flags, recording paths, size guard, signals, output."""
from __future__ import annotations

import pytest

from integration import cli, study


def _refused(argv: list[str], capsys) -> str:
    """Run the command line, expect argparse's usage error (exit 2); return its one-line message."""
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


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
    err = _refused(["recommend", "sheet-on-sphere", *argv, "--study", str(out)], capsys)
    assert "argument --tolerance" in err and shown in err, err
    assert not out.exists()
