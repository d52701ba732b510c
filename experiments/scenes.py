"""The canonical scenes of docs/method.md section 5, built on a World (every builder takes the time step dt
[s], the step's scheme, "warped" or "newton", see softbody.newton, and the material: E [Pa], nu, density and the
elastic model, softbody.MODELS, None: "warped", or "linear" with warping=False).

Each builder returns a :class:`Scene`: the world, its soft body, the monitored node and axis,
the default duration, and metadata (scene name, element kind, cells) for logs and studies.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from softbody import FemBody, LinearElastic, box_mesh, tube_mesh
from softbody.errors import InvalidInputError

from integration.world import World

E_DEFAULT, NU_DEFAULT, RHO_DEFAULT = 5.0e5, 0.33, 1000.0
DAMPING = (0.1, 0.001)


@dataclass(frozen=True)
class GridLayout:
    """How a scene meshes its ``cells``, for estimates before building: ``periodic_first`` if the first axis
    closes on itself (a tube's n_theta), and the scene's default ``duration`` [s]."""

    periodic_first: bool
    duration: float


GRIDS: dict[str, GridLayout] = {"sheet-on-sphere": GridLayout(False, 3.0), "hanging-tube": GridLayout(True, 4.0),
                                "cantilever": GridLayout(False, 2.0), "cubes-on-plane": GridLayout(False, 1.0),
                                "ten-cubes-on-plane": GridLayout(False, 1.0)}


@dataclass
class Scene:
    """A ready-to-run scene: ``world`` holds ``body``; ``monitor`` is the node whose coordinate ``axis``
    (0, 1, 2) is the scene's reported trajectory; ``duration`` [s] is the default run length."""

    name: str
    world: World
    body: FemBody
    monitor: int
    axis: int
    duration: float
    meta: dict = field(default_factory=dict)

    def monitored(self) -> float:
        return float(self.body.positions[self.monitor, self.axis])

    def run(self, duration: float | None = None, callback=None, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Run the scene; returns the times (n,) and the monitored coordinate (n,) after each step."""
        ts, xs = [self.world.t], [self.monitored()]

        def cb(world):
            ts.append(world.t)
            xs.append(self.monitored())
            if callback is not None:
                callback(world)

        self.world.run(self.duration if duration is None else duration, cb, progress=progress)
        return np.array(ts), np.array(xs)


def _nearest(nodes: np.ndarray, point) -> int:
    return int(np.argmin(np.linalg.norm(nodes - np.asarray(point, float), axis=1)))


def sheet_on_sphere(element: str = "tet10", cells: Sequence[int] = (6, 6, 2), dt: float = 0.01,
                    E: float = E_DEFAULT, nu: float = NU_DEFAULT, density: float = RHO_DEFAULT,
                    friction: float = 1.0, warping: bool = True, model: str | None = None, solver: str = "auto",
                    scheme: str = "warped",
                    height: float = 0.05, offset: float = 0.0) -> Scene:
    """A 1.0 x 1.0 x 0.25 m sheet, bottom at z = 0.35 m, falling onto a fixed sphere of radius 0.3 m at the origin.
    Monitored: z of the bottom corner node at rest position (-0.5, -0.5, 0.35).

    height: the drop, the gap between the sheet's bottom and the sphere's top [m] (0.05: the paper's);
    offset: the sheet's centre along x [m] (0: centred; off-centre it lands on the sphere's flank and slides
    unless friction holds it). The monitored corner moves with them: (offset - 0.5, -0.5, 0.3 + height).

    friction defaults to 1.0 (docs/method.md leaves it open): the sheet balances on the sphere's top, and
    with little or no friction any asymmetry (the checkerboard tet cut is not mirror-symmetric,
    round-off, an iterative solver's tolerance) makes it slide sideways, so its rest shape depends on
    the resolution. Measured at 3 s, tet10 6x6x2: with mu = 0.3 the centre drifts 2.2 mm and the four
    corners rest between 0.221 and 0.238 m; with mu = 1.0 it stays centred and the corners agree, and
    all element types and resolutions end within 5 mm of each other."""
    if not (np.isfinite(height) and height >= 0):
        raise InvalidInputError(f"height must be a gap >= 0 [m] above the sphere, got {height!r}")
    if not np.isfinite(offset):
        raise InvalidInputError(f"offset must be a finite length [m], got {offset!r}")
    bottom = 0.3 + float(height)
    mesh = box_mesh((1.0, 1.0, 0.25), cells, element, center=(float(offset), 0.0, bottom + 0.125))
    body = FemBody(mesh, LinearElastic(E, nu, density), warping=warping, damping=DAMPING, model=model)
    world = World(dt=dt, solver=solver, scheme=scheme)
    world.add_sphere(0.3, position=(0, 0, 0), name="sphere")
    world.add_soft(body, friction=friction)
    return Scene("sheet-on-sphere", world, body, _nearest(mesh.nodes, (offset - 0.5, -0.5, bottom)), 2,
                 GRIDS["sheet-on-sphere"].duration,
                 {"element": element, "cells": tuple(int(c) for c in cells), "dt": dt, "scheme": scheme})


def platform_x(t: float) -> float:
    """Half-sawtooth of the hanging tube's platform [m]: 0 until 0.5 s, up to 0.5 m at 1.0 s, back to 0 at 1.5 s."""
    if t <= 0.5 or t >= 1.5:
        return 0.0
    return (t - 0.5) if t <= 1.0 else (1.5 - t)


def hanging_tube(element: str = "tet10", cells: Sequence[int] = (8, 1, 6), dt: float = 0.01,
                 E: float = E_DEFAULT, nu: float = NU_DEFAULT, density: float = RHO_DEFAULT,
                 warping: bool = True, model: str | None = None, solver: str = "auto", scheme: str = "warped",
                 friction: float = 0.0) -> Scene:
    """A hollow tube (r 0.1 / 0.06 m, 1.0 m long, z in [-1, 0]) hanging from a kinematic platform that
    moves along x with the half-sawtooth of docs/method.md. Monitored: x of the outer bottom node at +x.
    friction: the tube's against the platform (its top is attached, so contact with the platform is off:
    it matters only if a user adds obstacles)."""
    mesh = tube_mesh(0.1, 0.06, 1.0, cells, element)
    body = FemBody(mesh, LinearElastic(E, nu, density), warping=warping, damping=DAMPING, model=model)
    world = World(dt=dt, solver=solver, scheme=scheme)
    platform = world.add_box((0.15, 0.15, 0.01), position=(0, 0, 0.01), name="platform",
                             motion=lambda t: (platform_x(t), 0.0, 0.01))
    world.add_soft(body, friction=friction)
    top = np.flatnonzero(np.isclose(mesh.nodes[:, 2], 0.0))
    world.attach(body, top, platform)
    return Scene("hanging-tube", world, body, _nearest(mesh.nodes, (0.1, 0.0, -1.0)), 0, GRIDS["hanging-tube"].duration,
                 {"element": element, "cells": tuple(int(c) for c in cells), "dt": dt, "scheme": scheme})


def cantilever(element: str = "tet10", cells: Sequence[int] = (10, 1, 1), dt: float = 0.01,
               E: float = 5.0e7, nu: float = NU_DEFAULT, density: float = RHO_DEFAULT,
               warping: bool = True, model: str | None = None, solver: str = "auto", scheme: str = "warped",
               friction: float = 0.0) -> Scene:
    """A 1.0 x 0.1 x 0.1 m beam along x, nodes at x = 0 fixed, sagging under gravity (no rigid bodies,
    so no pybullet work). Monitored: z of the node at the tip centre (1, 0, 0), or the nearest.
    friction: the beam's against rigid bodies a user adds (it touches none here)."""
    mesh = box_mesh((1.0, 0.1, 0.1), cells, element, center=(0.5, 0.0, 0.0))
    body = FemBody(mesh, LinearElastic(E, nu, density), warping=warping, damping=DAMPING, model=model)
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    world = World(dt=dt, solver=solver, scheme=scheme)
    world.add_soft(body, friction=friction)
    return Scene("cantilever", world, body, _nearest(mesh.nodes, (1.0, 0.0, 0.0)), 2, GRIDS["cantilever"].duration,
                 {"element": element, "cells": tuple(int(c) for c in cells), "dt": dt, "scheme": scheme})


def cubes_on_plane(element: str = "tet10", cells: Sequence[int] = (2, 2, 2), dt: float = 0.01, count: int = 1,
                   E: float = E_DEFAULT, nu: float = NU_DEFAULT, density: float = RHO_DEFAULT,
                   friction: float = 0.5, warping: bool = True, model: str | None = None, solver: str = "auto",
                   scheme: str = "warped",
                   size: float = 0.1, gap: float = 0.001) -> Scene:
    """``count`` soft cubes of side ``size`` [m] in a row along x (0.5 * size apart), their bottoms ``gap``
    [m] above a fixed plane z = 0, settling onto it: the small-body, many-body scene of a robot's table (issue
    18's cost of a step). Monitored: z of the first cube's bottom corner at (-size/2, -size/2, gap)."""
    count = int(count)
    if count < 1:
        raise InvalidInputError(f"count must be a number of cubes >= 1, got {count!r}")
    world = World(dt=dt, solver=solver, scheme=scheme)
    world.add_plane(name="plane")
    bodies = []
    for k in range(count):
        mesh = box_mesh((size, size, size), cells, element, center=(1.5 * size * k, 0.0, gap + 0.5 * size))
        body = FemBody(mesh, LinearElastic(E, nu, density), warping=warping, damping=DAMPING, model=model)
        world.add_soft(body, friction=friction)
        bodies.append(body)
    return Scene("cubes-on-plane", world, bodies[0], _nearest(bodies[0].mesh.nodes, (-0.5 * size, -0.5 * size, gap)),
                 2, GRIDS["cubes-on-plane"].duration,
                 {"element": element, "cells": tuple(int(c) for c in cells), "dt": dt, "scheme": scheme,
                  "count": count})


def ten_cubes_on_plane(element: str = "tet10", cells: Sequence[int] = (2, 2, 2), dt: float = 0.01, **options) -> Scene:
    """:func:`cubes_on_plane` with ten cubes (the many-body scene of ``softbody bench``)."""
    scene = cubes_on_plane(element, cells, dt, count=10, **options)
    scene.name = "ten-cubes-on-plane"
    return scene


SCENES: dict[str, Callable[..., Scene]] = {
    "sheet-on-sphere": sheet_on_sphere,
    "hanging-tube": hanging_tube,
    "cantilever": cantilever,
    "cubes-on-plane": cubes_on_plane,
    "ten-cubes-on-plane": ten_cubes_on_plane,
}


def register_scene(name: str, builder: Callable[..., Scene], grid: GridLayout | None = None) -> None:
    """Make a scene builder available to the ``softbody`` command line under ``name``; ``grid`` (if it meshes
    ``cells`` like box_mesh or tube_mesh) lets the command line estimate a run's size before building it."""
    SCENES[name] = builder
    if grid is not None:
        GRIDS[name] = grid


def scene_grid(name: str, element: str | None = None, cells: Sequence[int] | None = None,
               dt: float | None = None) -> tuple[str, tuple[int, ...], float, GridLayout] | None:
    """The element, cells and time step [s] that ``build_scene(name, ...)`` would use (the builder's defaults
    for None) and the scene's grid layout; None for a scene without a known layout."""
    if name not in SCENES or name not in GRIDS:
        return None
    defaults = {k: p.default for k, p in inspect.signature(SCENES[name]).parameters.items()}
    return (element or defaults["element"], tuple(cells or defaults["cells"]), float(dt or defaults["dt"]),
            GRIDS[name])


def build_scene(name: str, **options) -> Scene:
    if name not in SCENES:
        raise InvalidInputError(f"unknown scene {name!r}; available: {sorted(SCENES)}")
    return SCENES[name](**{k: v for k, v in options.items() if v is not None})
