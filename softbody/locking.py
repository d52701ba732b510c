"""Volumetric locking: linear tets (tet4) and trilinear hexahedra (hex8, full 2x2x2 quadrature) grow too stiff as
the Poisson ratio nears 0.5, where quadratic tets (tet10) do not (benchmarks/locking.py, docs/materials.md: a
cantilever under its own weight deflects 0.57 (hex8, 40x4x4) and 0.30 (tet4, tetrahedralized) of the converged value
at nu = 0.499, tet10 20x2x2 0.97). The library warns when a body is made of such elements and material."""
from __future__ import annotations

import warnings

#: the Poisson ratio from which tet4 and hex8 bodies are warned of (their cantilever 5-8% stiffer than at nu 0.3)
LOCKING_NU = 0.45
LOCKING_ELEMENTS = ("tet4", "hex8")


class LockingWarning(UserWarning):
    """A body's elements lock at its material's Poisson ratio: it bends and compresses too little."""


def check_locking(kind: str, nu: float, stacklevel: int = 3, bbar: bool = True) -> None:
    """Warn (LockingWarning) when elements of ``kind`` lock at Poisson ratio ``nu``; ``bbar``: whether the body could
    take B-bar instead (the linear models; a hyperelastic one cannot: then only tet10 is named)."""
    if kind in LOCKING_ELEMENTS and nu >= LOCKING_NU:
        warnings.warn(LockingWarning(
            f"{kind} elements with Poisson ratio nu = {nu:g} lock: the body bends and compresses too little (a "
            f"cantilever deflects {'0.92, 0.80 and 0.57' if kind == 'hex8' else '0.81, 0.64 and 0.30 (tetrahedralized)'}"
            " of the converged value at nu 0.45, 0.49 and 0.499, docs/materials.md). "
            + ("FemBody(..., volumetric='mean') (B-bar) does not lock (0.998 at 0.499), nor do tet10 elements"
               if kind == "hex8" and bbar else "tet10 elements do not lock at this nu (0.97 at 0.499)")
            + ": box_mesh(..., 'tet10'), tetrahedralize(..., kind='tet10') or to_tet10(mesh)"),
            stacklevel=stacklevel)
