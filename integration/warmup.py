"""The integration layer's warm-up: small scenes through the compiled kernels (``python -m integration.warmup``
fills numba's cache for softbody's and integration's kernels; softbody.compilation starts it in the background on
a first run, ``softbody compile`` in the foreground).

The scenes: softbody.warmup's bars; a sheet of each element type dropped on a sphere (node contacts, the
active set body by body); soft cubes on a plane, one under a dynamic box (the coupled solve of a movable body), one
under a dynamic convex mesh (the mesh links of a user's robot), a third stacked on the first (soft-soft contacts);
two soft cubes overlapping, turned, through the soft search (every pass and kind of its kernels, which a settled
stack need not reach)."""
from __future__ import annotations

import numpy as np
import trimesh

from softbody import FemBody, LinearElastic, box_mesh, compilation
from softbody import warmup as fem_warmup

from .world import World


def _soft(kind: str, size: tuple[float, float, float], cells: tuple[int, int, int],
          center: tuple[float, float, float], E: float = 5e5) -> FemBody:
    """A soft box of ``kind`` elements, ``size`` [m] in ``cells``, centred at ``center`` [m], Young's modulus E [Pa]."""
    return FemBody(box_mesh(size, cells, kind, center=center), LinearElastic(E, 0.33, 1000.0), damping=(0.1, 0.001))


def sheets(steps: int = 12) -> None:
    """A small sheet of every element type landing on a fixed sphere (node contacts, friction)."""
    for kind in fem_warmup.KINDS:
        world = World(dt=0.01)
        world.add_sphere(0.3)
        world.add_soft(_soft(kind, (0.6, 0.6, 0.15), (2, 2, 1), (0.0, 0.0, 0.31 + 0.075)), friction=1.0)
        for _ in range(steps):
            world.step()


def cubes(steps: int = 12) -> None:
    """Soft cubes on a plane: one under a dynamic box, one under a dynamic convex mesh, one stacked on the first
    (every contact kind)."""
    world = World(dt=0.01)
    world.add_plane()
    for kind, x in (("tet10", 0.0), ("tet4", 0.3), ("tet10", 0.6)):
        world.add_soft(_soft(kind, (0.1, 0.1, 0.1), (2, 2, 2), (x, 0.0, 0.051)), friction=0.5)
    world.add_box((0.03, 0.03, 0.02), position=(0.3, 0.0, 0.123), mass=0.2)
    world.add_mesh(trimesh.creation.icosphere(1, 0.03), position=(0.6, 0.0, 0.133), mass=0.2)
    world.add_soft(_soft("tet10", (0.1, 0.1, 0.1), (2, 2, 2), (0.0, 0.0, 0.153)), friction=0.5)
    for _ in range(steps):
        world.step()


def soft_search() -> None:
    """Two soft cubes overlapping (3 mm, one turned, the other moving) and each with self-contact, through the soft
    search (softcontact.soft_contacts and edge_contacts: both passes of the node-face search, searched and from kept
    candidates, the edge search) and the check after the step (intersection.intersection_depth)."""
    from .intersection import intersection_depth
    from .softcontact import FirstPass, SoftLayout, SoftSurface, edge_contacts, soft_contacts

    bodies = []
    for k, kind in enumerate(("tet4", "tet10")):
        m = box_mesh((0.04, 0.04, 0.04), (2, 2, 2), kind)
        c, s = np.cos(0.5 * k), np.sin(0.5 * k)
        x = m.nodes @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + (0.0, 0.0, 0.037 * k)
        bodies.append((x, np.full(x.shape, 0.1 * k), SoftSurface.of(m.nodes, m.surface_triangles()), m.nodes))
    pairs = [(0, 1), (0, 0), (1, 1)]
    layout, kept = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs), FirstPass()
    for _ in range(2):  # found, then served from the kept candidates
        hits = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025, layout, kept)
    edge_contacts(bodies, pairs, 0.005, 0.01, 0.005, hits)
    (xa, _, sa, _), (xb, _, sb, _) = bodies  # and the check after the step
    intersection_depth(xa, sa.triangles, sa.edges, xb, sb.triangles, sb.edges)


def run() -> None:
    """Every warm-up scene: the FEM core's, then the World's."""
    fem_warmup.run()
    sheets()
    cubes()
    soft_search()


if __name__ == "__main__":
    compilation.warm_up(run)
