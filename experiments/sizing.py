"""A size guard for scene runs: peak memory and time per step estimated from the mesh size, before anything
is built, against the memory the machine has available.

The model is measured (``python benchmarks/memory_model.py``: sheet-on-sphere, one thread, a fresh process
per size, peak RSS over the build and the first steps into the impact) for N nodes:

    peak memory [MB] = 40 + a (N / 1000)^p          ms per step = 2 + b (N / 1000)^q

Memory is within 10% of the measured peaks from 4000 to 106000 nodes (45-60 MB per 1000 nodes); the time
is that of steps in the impact on this 2-core machine (free fall is 2-8x faster; other scenes and
machines differ), a guide to the order of magnitude.
"""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass
from typing import Sequence

from softbody.errors import InvalidInputError
from softbody.meshing import grid_mesh_size

#: element -> (a [MB], p, b [ms], q), fitted by benchmarks/memory_model.py over runs of 4000-106000 nodes
MODEL = {"tet4": (44.0, 1.014, 1.46, 1.93), "hex8": (48.7, 1.040, 1.61, 1.94), "tet10": (56.0, 0.976, 2.80, 1.84)}
#: element -> (nodes, MB, MB per 1000 nodes): from this many nodes on, "auto" preconditions with multigrid instead of a
#: factor (softbody.solvers.MULTIGRID_FACTOR_BYTES: the tet4 sheet's factor passes 7 kB per node near 62k nodes),
#: and memory grows linearly: the peaks above the imports of the tet4 sheets of 72k, 235k and 549k nodes through the
#: impact, 0.94, 2.52 and 5.79 GB (docs/benchmarks.md, "Large bodies", 2026-12-06), fitted within 4%. Other
#: elements: no measurement yet, the factor's model above stands
MULTIGRID = {"tet4": (62_000, 174.0, 10.20)}
BASE_MB, BASE_MS = 40.0, 2.0
WARN_MB = 2000.0  # warn above this estimate [MB]
REFUSE_FRACTION = 0.9  # refuse above this fraction of the available memory (the model's error is about 10%)
SUGGEST_FRACTION = 0.5  # suggested cells need at most this fraction of it


@dataclass(frozen=True)
class SizeEstimate:
    """Mesh size and the model's peak memory [MB] and time per step [ms] of a run."""

    element: str
    cells: tuple[int, int, int]
    nodes: int
    elements: int
    memory_mb: float
    ms_per_step: float


def estimate(element: str, cells: Sequence[int], periodic_first: bool = False) -> SizeEstimate:
    """The model's estimate for a structured grid of ``cells`` (``periodic_first``: a tube's n_theta)."""
    if element not in MODEL:
        raise InvalidInputError(f"no size model for element {element!r}; known: {sorted(MODEL)}")
    nodes, elements = grid_mesh_size(cells, element, periodic_first)
    a, p, b, q = MODEL[element]
    k = nodes / 1000.0
    memory = BASE_MB + a * k**p
    if element in MULTIGRID and nodes >= MULTIGRID[element][0]:
        memory = MULTIGRID[element][1] + MULTIGRID[element][2] * k
    return SizeEstimate(element, tuple(int(c) for c in cells), nodes, elements, memory, BASE_MS + b * k**q)


def available_memory_mb() -> float | None:
    """Memory available to a new allocation [MB]: MemAvailable of /proc/meminfo, else free physical pages;
    None if neither can be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (ValueError, OSError, AttributeError):
        return None


def _size(mb: float) -> str:
    return f"{mb / 1024:.1f} GB" if mb >= 1024 else f"{mb:.0f} MB"


def _duration(seconds: float) -> str:
    for unit, s in (("h", 3600.0), ("min", 60.0)):
        if seconds >= s:
            return f"{seconds / s:.1f} {unit}"
    return f"{seconds:.1f} s" if seconds >= 1 else f"{1e3 * seconds:.0f} ms"


def fitting_cells(element: str, cells: Sequence[int], budget_mb: float, periodic_first: bool = False
                  ) -> SizeEstimate | None:
    """The largest grid of the same proportions whose estimate is within ``budget_mb`` [MB] (a tube's
    n_theta kept even and >= 4 for tets), or None if not even the coarsest fits."""
    s = 1.0
    while True:
        c = [max(1, math.floor(v * s)) for v in cells]
        if periodic_first:
            c[0] = max(4, c[0] - (c[0] % 2 if element != "hex8" else 0))
        e = estimate(element, c, periodic_first)
        if e.memory_mb <= budget_mb:
            return e
        if c == [4 if periodic_first else 1, 1, 1]:
            return None
        s *= 0.97


def check_run_size(scene: str, element: str, cells: Sequence[int], steps: int, periodic_first: bool = False,
                   available_mb: float | None = None) -> SizeEstimate:
    """Estimate a run of ``steps`` steps before anything is built. Raises InvalidInputError (with the estimate
    and cells that fit) above REFUSE_FRACTION of the available memory [MB] (default: read now); warns on
    stderr above WARN_MB. Returns the estimate."""
    e = estimate(element, cells, periodic_first)
    available = available_memory_mb() if available_mb is None else available_mb
    cells_text = "x".join(str(c) for c in e.cells)
    what = (f"{scene} {element} cells {cells_text} ({e.nodes:,} nodes, {e.elements:,} elements) needs about "
            f"{_size(e.memory_mb)} of memory and {_duration(1e-3 * e.ms_per_step)} per step "
            f"({steps} steps: {_duration(1e-3 * e.ms_per_step * steps)})")
    if available is not None and e.memory_mb > REFUSE_FRACTION * available:
        fit = fitting_cells(element, cells, SUGGEST_FRACTION * available, periodic_first)
        hint = (f"; --cells {' '.join(str(c) for c in fit.cells)} would need about {_size(fit.memory_mb)}"
                if fit is not None else "")
        raise InvalidInputError(f"{what}, but {_size(available)} are available{hint}")
    if e.memory_mb > WARN_MB:
        print(f"# warning: {what}", file=sys.stderr, flush=True)
    return e
