"""Experiment tooling on top of ``softbody`` and ``integration``: parameter sweeps (sweep.py).

    from experiments import run_sweep, sweep
    rows = sweep("sheet-on-sphere", {"friction": [0.2, 0.8]}, duration=0.3)

``softbody sweep SCENE --param NAME=V1,V2 ...`` is the command line (integration/cli.py).
"""
from .sweep import SweepResult, parse_param, run_sweep, sweep

__all__ = ["SweepResult", "parse_param", "run_sweep", "sweep"]
