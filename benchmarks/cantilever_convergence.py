"""Cantilever (docs/method.md section 5) static tip deflection under refinement, for each element type.

    python benchmarks/cantilever_convergence.py

Prints a markdown table: element, cells, nodes, tip deflection [mm] and its ratio to Timoshenko's
beam value q L^4 / (8 E I) + q L^2 / (2 kappa G A) (kappa = 5/6), which the FEM approaches from below.
"""

import os
os.environ.setdefault("SOFTBODY_COMPILE", "now")  # timed runs: kernels compiled in-process (softbody.compilation)
import numpy as np

import softbody as sb

E, NU, RHO, L, B = 5.0e7, 0.33, 1000.0, 1.0, 0.1
LADDER = {
    "tet4": [(10, 1, 1), (20, 2, 2), (40, 4, 4), (60, 6, 6), (80, 8, 8)],
    "hex8": [(10, 1, 1), (20, 2, 2), (40, 4, 4), (60, 6, 6)],
    "tet10": [(5, 1, 1), (10, 1, 1), (20, 2, 2), (40, 4, 4)],
}


def timoshenko() -> float:
    q, I, A = RHO * 9.81 * B * B, B**4 / 12, B * B
    G = E / (2 * (1 + NU))
    return q * L**4 / (8 * E * I) + q * L**2 / (2 * 5 / 6 * G * A)


def tip_deflection(kind: str, cells) -> tuple[int, float]:
    mesh = sb.box_mesh((L, B, B), cells, kind, center=(L / 2, 0, 0))
    body = sb.FemBody(mesh, sb.LinearElastic(E, NU, RHO))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    u = sb.solve_static(body)
    return mesh.n_nodes, -float(u[np.isclose(mesh.nodes[:, 0], L), 2].mean())


if __name__ == "__main__":
    ref = timoshenko()
    print(f"Timoshenko: {1e3 * ref:.2f} mm (Euler-Bernoulli alone {1e3 * RHO * 9.81 * B * B * L**4 / (8 * E * B**4 / 12):.2f} mm)\n")
    print("| element | cells | nodes | tip deflection [mm] | / Timoshenko |")
    print("|---|---|---:|---:|---:|")
    for kind, ladder in LADDER.items():
        for cells in ladder:
            n, d = tip_deflection(kind, cells)
            print(f"| {kind} | {cells} | {n} | {1e3 * d:.2f} | {d / ref:.3f} |", flush=True)
