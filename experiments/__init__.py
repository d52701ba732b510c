"""Experiment tooling on top of ``softbody`` (the FEM core) and ``integration`` (the coupling layer): the
canonical scenes (scenes.py), resolution studies and ``recommend`` (study.py), parameter sweeps (sweep.py),
the benchmark (bench.py), the run-size guard (sizing.py) and the command line ``softbody`` (cli.py).

    from experiments import build_scene, sweep
    scene = build_scene("sheet-on-sphere", element="tet10", cells=(6, 6, 2))
    rows = sweep("sheet-on-sphere", {"friction": [0.2, 0.8]}, duration=0.3)

The scenes' and studies' names are imported on first use; the sweep's at once (the function ``sweep``
shares its name with its module, which importing the module would otherwise put in its place).
"""
from __future__ import annotations

import importlib

from .sweep import SweepResult, parse_param, run_sweep, sweep

_EXPORTS = {
    "Scene": "scenes", "build_scene": "scenes", "register_scene": "scenes", "SCENES": "scenes",
    "run_study": "study", "recommend": "study", "recommend_steps": "study",
}

__all__ = sorted([*_EXPORTS, "SweepResult", "parse_param", "run_sweep", "sweep"])


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module 'experiments' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
