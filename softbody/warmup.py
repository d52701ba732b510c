"""The FEM core's warm-up: small simulations through the compiled kernels of softbody (``python -m softbody.warmup``
fills numba's cache; softbody.compilation starts it in the background on a first run).

Each element type steps a cantilever with the warped stiffness, by the direct solver (the small systems' block
Cholesky), by PCG and by the Newton scheme, and the same bar free: the kernels then compile for the argument types
of real use."""
from __future__ import annotations

import numpy as np

from . import compilation
from .body import FemBody
from .material import LinearElastic
from .meshing import box_mesh
from .simulation import Simulation

KINDS = ("tet4", "hex8", "tet10")


def cantilever(kind: str) -> FemBody:
    """A soft 0.2 x 0.05 x 0.05 m bar of ``kind`` elements, clamped at x = 0."""
    mesh = box_mesh((0.2, 0.05, 0.05), (4, 1, 1), kind, center=(0.1, 0.0, 0.0))
    body = FemBody(mesh, LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
    body.fix(np.flatnonzero(mesh.nodes[:, 0] == 0.0))
    return body


def run(steps: int = 3) -> None:
    """Step a cantilever of every element type by each linear method and scheme, and a free one (the damping that
    spares rigid motion, FemBody.rigid_velocity, runs for free bodies only)."""
    for kind in KINDS:
        for options in ({}, {"method": "iterative"}, {"scheme": "newton"}):
            sim = Simulation(cantilever(kind), dt=0.01, **options)
            for _ in range(steps):
                sim.step()
        free = cantilever(kind)
        free.fixed[:] = False
        sim = Simulation(free, dt=0.01)
        for _ in range(steps):
            sim.step()


if __name__ == "__main__":
    compilation.warm_up(run)
