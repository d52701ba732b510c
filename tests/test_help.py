"""--help is plain text: no reST or markdown markup (``literals``, `backticks`, **bold**, :func:`roles`,
[links](target)) in the descriptions and help of ``softbody``, its subcommands and the example scripts."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from experiments import cli

ROOT = Path(__file__).resolve().parents[1]
MARKUP = {"backtick": re.compile(r"`"), "bold": re.compile(r"\*\*\w[^*\n]*\*\*"),
          "role": re.compile(r":[a-z]+:\S"), "link": re.compile(r"\]\(")}


def markup_in(text: str) -> dict[str, list[str]]:
    """The lines of ``text`` with markup, by kind."""
    found = {kind: [line for line in text.splitlines() if pattern.search(line)] for kind, pattern in MARKUP.items()}
    return {kind: lines for kind, lines in found.items() if lines}


def help_of(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        cli.main([*argv, "--help"])
    assert exc.value.code == 0
    return capsys.readouterr().out


def test_the_markup_patterns_find_markup():
    assert set(markup_in("The ``softbody`` line, **bold**, :func:`run_point`, [docs](docs/x.md)")) == set(MARKUP)
    assert markup_in("scene(**params) -> World; 6x6x2; 0.5 m: a ratio (docs/sweeps.md)") == {}


def test_softbody_and_every_subcommand_help_is_plain_text(capsys):
    top = help_of([], capsys)
    commands = re.search(r"\{([\w,-]+)\}", top).group(1).split(",")
    assert {"run", "study", "recommend", "sweep", "bench", "compile"} <= set(commands)
    assert "The softbody command line" in top  # the module docstring, its ``softbody`` as plain text
    for argv in ([], *([c] for c in commands)):
        text = top if not argv else help_of(argv, capsys)
        assert markup_in(text) == {}, (argv, markup_in(text))


def test_plain_text_keeps_the_words():
    text = "The ``softbody`` line: :func:`run_point`, :class:`~softbody.FemBody`, **two-way** `x` [docs](d.md)::"
    assert cli.plain_text(text) == "The softbody line: run_point, softbody.FemBody, two-way x docs (d.md):"
    assert cli.plain_text("scene(**params), f(x, **a, **b)") == "scene(**params), f(x, **a, **b)"


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "examples").glob("*.py")))
def test_every_example_scripts_help_is_plain_text(script):
    done = subprocess.run([sys.executable, str(ROOT / "examples" / script), "--help"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "usage:" in done.stdout
    assert markup_in(done.stdout) == {}, markup_in(done.stdout)
