"""Every Python block of the README runs on its own (in a fresh namespace, from the repository's root)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)


def test_the_readme_has_python_blocks():
    assert len(BLOCKS) >= 3


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_runs_on_its_own(index, monkeypatch):
    monkeypatch.chdir(ROOT)
    code = compile(BLOCKS[index], f"README.md python block {index + 1}", "exec")
    exec(code, {"__name__": "__readme__"})


DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_linked_file_is_in_the_repository(doc):
    """A fresh clone has every file the README and docs link to (no project-external paths)."""
    text = doc.read_text()
    assert "../shared" not in text
    for target in re.findall(r"\]\(([^)#\s]+)", text):
        if not target.startswith(("http://", "https://")):
            assert (doc.parent / target).exists(), f"{doc.name} links to {target}, which is not in the repository"


def test_the_method_is_documented_in_the_repository():
    text = (ROOT / "docs" / "method.md").read_text()
    assert "docs/method.md" in (ROOT / "README.md").read_text()
    for needle in ("(M + h C + h^2 K) v_{n+1}", "VTK_QUADRATIC_TETRA", "{0, 2, 5, 7}", "sheet-on-sphere",
                   "hanging-tube", "cantilever", "5.0e5 Pa"):
        assert needle in text, needle


def test_the_command_tables_run_row_names_every_scene_and_every_flag_of_run():
    """The README's `softbody run` row against the code: every scene of experiments.scenes.SCENES, every
    option of the run parser (cli.add_scene_arguments) and every choice of those that have choices."""
    import argparse

    from experiments import cli
    from experiments.scenes import SCENES

    rows = [line for line in (ROOT / "README.md").read_text().splitlines() if line.startswith("| `softbody run ")]
    assert len(rows) == 1
    row = rows[0]
    for name in SCENES:
        assert f"`{name}`" in row, f"scene {name} is missing from the README's run row"
    parser = argparse.ArgumentParser()
    cli.add_scene_arguments(parser)
    actions = [a for a in parser._actions if a.option_strings and "--help" not in a.option_strings]
    assert len(actions) >= 12
    for action in actions:
        flag = max(action.option_strings, key=len)
        assert re.search(re.escape(flag) + r"(?![\w-])", row), f"{flag} is missing from the README's run row"
        for choice in action.choices or ():
            assert re.search(rf"[ |`]{re.escape(choice)}(?![\w-])", row), f"{flag} {choice} is missing"
