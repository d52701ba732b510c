"""Every Python block of the README runs on its own (in a fresh namespace, from the repository's root)."""
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)


def test_the_readme_has_python_blocks():
    assert len(BLOCKS) >= 3


def check_sheet_on_sphere(ns: dict) -> None:
    """The sheet (1 x 1 x 0.25 m, 1000 kg/m^3) rests on the sphere (top at 0.3 m) after 3 s: the force on the
    sphere is its weight, downwards, and its corners droop below the sphere's top."""
    weight = 1.0 * 1.0 * 0.25 * 1000 * 9.81
    force = ns["world"].contact_force(ns["sphere"])
    assert force[2] == pytest.approx(-weight, rel=0.05) and np.hypot(force[0], force[1]) < 0.01 * weight
    assert 0.15 < ns["sheet"].positions[:, 2].min() < 0.3


def check_arm_on_block(ns: dict) -> None:
    """The arm presses on the soft block: the block is squeezed (shorter than its 80 mm) and pushes the arm
    up with about the force of its stiffness over that squeeze (E A strain; a factor 2 either way for the
    coarse mesh, the friction on its faces holding its sides and the flange covering its top)."""
    z = ns["block"].positions[:, 2]
    squeeze = 0.08 - (z.max() - z.min())
    force = ns["force"]
    assert squeeze > 1e-3 and force[2] > 0
    stiff = 1e5 * 0.08 * 0.08 * squeeze / 0.08  # E A strain [N]
    assert 0.5 * stiff < np.linalg.norm(force) < 2 * stiff, (force, stiff)


CHECKS = {"world.add_sphere(0.3)": check_sheet_on_sphere, "kuka_iiwa/model.urdf": check_arm_on_block}


def test_the_checked_blocks_are_in_the_readme():
    for needle in CHECKS:
        assert sum(needle in block for block in BLOCKS) == 1, needle


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_runs_on_its_own(index, monkeypatch):
    """Each block runs in a fresh namespace; the blocks of CHECKS then give what their comments say."""
    monkeypatch.chdir(ROOT)
    code = compile(BLOCKS[index], f"README.md python block {index + 1}", "exec")
    ns = {"__name__": "__readme__"}
    exec(code, ns)
    for needle, check in CHECKS.items():
        if needle in BLOCKS[index]:
            check(ns)


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
