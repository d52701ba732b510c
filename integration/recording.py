"""Rerun recordings of soft-body runs: meshes with stress colours, rigid bodies, contacts, trajectories.

    with Recorder.attach(scene) as rec:          # a Scene, a World or a softbody.Simulation
        scene.run(1.0, rec)                      # rec(world) after each step records it
    print(rec.path)                              # logs/sheet-on-sphere_tet4_8x8x3_20250101-120000.rrd

Open the file with ``rerun <file>.rrd``. Everything is logged on the ``sim_time`` timeline [s]:

    world/soft/body<i>        Mesh3D: surface triangles once (static); vertex positions, normals and colours
                              per frame (von Mises: one colour per element face, its vertices duplicated per
                              face; color_mode="nodal": a volume-weighted nodal average on shared vertices)
    world/rigid/<name>        the rigid shape once (static, body frame, smooth meshes with normals) and its
                              Transform3D pose per frame
    world/contacts/points     active node contacts: points on the rigid surfaces
    world/contacts/arrows     their forces on the soft body (out of the rigid body, length force * force_scale)
                              or unit normals (contact_arrows="normal")
    world/contacts/faces/...  the same for rigid points on soft triangles (face contacts)
    world/contacts/soft/...   and for soft-soft and self contacts (points on the triangles)
    world/attachments         attached soft nodes
    world/monitor             the monitored nodes as points
    plots/monitored           the scene's monitored coordinate [mm], a plot of its own
    plots/monitor/<node>/x    x, y and z (also /y, /z) of each monitored node [mm], a plot each (one axis of
                              mm for all three would flatten a coordinate that moves little next to one that
                              moves far, and hide one under another that moves alike)
    plots/energy              energies [J]: soft kinetic, elastic, gravitational, rigid kinetic and
                              gravitational (World), and their total, which damping and contact lower
    plots/step_time           wall time of each step from the second on [ms]
    plots/setup_time          wall time of the first step [ms] (symbolic analysis, first factorisation)
    plots/contacts            number of active contacts, and of candidates within reach but not touching
    plots/newton/*            schemes "newton" and "bdf2": iterations and log10 of the final relative residual per step
    plots/color_range         the frame's min and max of the colour field (kPa or mm)
    colorbar                  the colour bar: an image with the map's name, numbers and unit
    legend                    a text note: which field, how it is drawn, colour map and its range, set-up time

The colour range is one for the whole recording: ``color_range`` if given, else 0 .. the largest value of
the run (at least a floor), re-sent for every frame when the recorder closes (a viewer following the file
live sees the range grow until then). The blueprint's 3D views look at every body from a three-quarter view
computed from the bounds of the scene (kinematic links over the scene's duration), and again from the bounds
over the whole run when the recorder closes; a second 3D view shows the contacts with the soft bodies hidden.

Frames are buffered and sent with ``send_columns`` in batches (a few log calls per batch instead of
a dozen per step); ``close()`` (also from ``__exit__``, ``finally`` blocks and ``atexit``) sends the
rest and finishes the file, so a run that raises or is interrupted with Ctrl-C still leaves a
valid recording of every frame before the fault. A hard kill loses at most the unsent batch.

The FEM core never imports rerun; this module only reads the bodies' public state.
"""
from __future__ import annotations

import atexit
import math
import os
import tempfile
import time
import uuid
from datetime import datetime
from pathlib import Path
from typing import Iterable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import scipy.sparse as sp

from softbody import FemBody, Simulation
from softbody.errors import InvalidInputError

TIMELINE = "sim_time"
CONTENT = ("mesh", "colors", "rigid", "contacts", "attachments", "monitor", "diagnostics")
#: colour field -> (name, display unit, display unit per SI unit)
COLOR_FIELDS = {"von_mises": ("von Mises stress", "kPa", 1e-3), "displacement": ("displacement magnitude", "mm", 1e3)}
COLOR_MODES = ("element", "nodal")
#: the 3D views' vertical field of view assumed for framing [rad] (rerun's default eye has 55 degrees)
VIEW_FOV = math.radians(50.0)
#: memory [bytes] for the colour sources kept until close (to redraw frames on the run's final range); beyond
#: it later frames are not kept, and the legend says from when on frames may be drawn on a smaller range
FIELD_BUDGET = 256 * 2**20
#: width / height assumed for the scene view and the contacts view of the blueprint (a 1600 x 1000 viewer gives
#: about 960 x 690 and 640 x 380 px)
SCENE_ASPECT, CONTACTS_ASPECT = 1.3, 1.6
#: where a plot with several series shows its legend: top right, as a settling curve starts at the top left or
#: the bottom left; a plot of one series has none (its view's name says what it is)
PLOT_LEGEND_CORNER = rrb.Corner2D.RightTop
#: the blueprint's left column: scene view over the colour bar and legend row, by height; and that row's split
#: between colour bar and legend (the legend's text fits in its share of a 1600 x 1000 viewer)
LEFT_ROW_SHARES, UNDER_COLUMN_SHARES = (5.0, 1.8), (1.0, 1.0)
#: direction from the scene's centre to the eye of the three-quarter view (azimuth -55 deg, elevation 30 deg)
EYE_DIRECTION = np.array([math.cos(math.radians(30)) * math.cos(math.radians(-55)),
                          math.cos(math.radians(30)) * math.sin(math.radians(-55)), math.sin(math.radians(30))])
#: explicit series colours (matplotlib's tab10, then tab20's light tones): distinct within and across plots
SERIES_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
                 (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (174, 199, 232), (255, 187, 120),
                 (152, 223, 138), (255, 152, 150), (197, 176, 213), (196, 156, 148)]
#: the colour map starts at 0 and reaches at least this fraction of the smallest Young's modulus (von Mises)
#: or of the smallest body's largest extent (displacement), so that a body at rest shows no colours
COLOR_FLOOR_FRACTION = 1e-3

_SOFT_ALBEDO = (150, 180, 220, 255)
_RIGID_COLOR = (170, 170, 170, 255)
_CONTACT_COLOR = (230, 40, 40, 255)
_ARROW_COLOR = (255, 150, 30, 255)
# entity path of each contact kind -> (point colour, arrow colour): node, face and soft contacts apart
CONTACT_KINDS = {"world/contacts": (_CONTACT_COLOR, _ARROW_COLOR),
                 "world/contacts/faces": ((200, 40, 200, 255), (240, 120, 240, 255)),
                 "world/contacts/soft": ((40, 120, 230, 255), (80, 200, 255, 255))}
_ATTACH_COLOR = (40, 200, 80, 255)
_MONITOR_COLOR = (255, 0, 255, 255)


def _colormap(name: str) -> np.ndarray:
    """A (256, 4) uint8 lookup table of a matplotlib colour map."""
    import matplotlib

    return (np.asarray(matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))) * 255 + 0.5).astype(np.uint8)


def default_path(scene=None, target=None, directory: str | Path = "logs") -> Path:
    """logs/<scene>_<element>_<nx>x<ny>x<nz>_<YYYYmmdd-HHMMSS>.rrd (a numbered suffix if it exists)."""
    parts = []
    if scene is not None:
        parts.append(scene.name)
        meta = scene.meta or {}
        if "element" in meta:
            parts.append(str(meta["element"]))
        if "cells" in meta:
            parts.append("x".join(str(int(c)) for c in meta["cells"]))
    else:
        bodies = _bodies_of(target) if target is not None else []
        parts.append("world")
        if bodies:
            parts.append("-".join(sorted({b.mesh.kind for b in bodies})))
            parts.append(f"{sum(b.mesh.n_elements for b in bodies)}el")
    parts.append(datetime.now().strftime("%Y%m%d-%H%M%S"))
    directory = Path(directory)
    stem = "_".join(p.replace("/", "-").replace(" ", "-") for p in parts)
    path = directory / f"{stem}.rrd"
    k = 1
    while path.exists():
        path = directory / f"{stem}-{k}.rrd"
        k += 1
    return path


def record_target(path: str | Path | None, overwrite: bool = True,
                  directory: str | Path = "logs") -> tuple[Path | None, Path]:
    """Where a recording goes, checked before anything runs: (file, directory), file None for a
    :func:`default_path` name in directory.

    path None or "": a default name under ``directory``; an existing directory or a path ending in a
    separator: a default (timestamped) name inside it; anything else is the file (".rrd" appended to
    another suffix). Raises InvalidInputError naming the path if the file exists and not ``overwrite``,
    or if its directory cannot be created or written to."""
    text = "" if path is None else str(path)
    if not text:
        file, folder = None, Path(directory)
    elif text.endswith(("/", os.sep)) or Path(text).is_dir():
        file, folder = None, Path(text)
    else:
        file = Path(text)
        if file.suffix != ".rrd":
            file = file.with_name(file.name + ".rrd")
        folder = file.parent
        if file.exists() and not overwrite:
            raise InvalidInputError(f"the recording {file} already exists: overwrite it (--force, or "
                                    "Recorder(overwrite=True)) or give another path")
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    reason = None
    if not existing.is_dir():
        reason = f"{existing} is not a directory"
    else:
        try:
            tempfile.TemporaryFile(dir=existing).close()
        except OSError as exc:
            reason = f"{existing} is not writable ({exc.strerror or exc})"
    if reason is None and file is not None and file.exists() and not os.access(file, os.W_OK):
        reason = f"{file} is not writable"
    if reason is not None:
        raise InvalidInputError(f"cannot write a recording to {file or folder}: {reason}; give another path")
    return file, folder


def _link_visuals(rb) -> list:
    """Archetypes drawing a URDF link in its inertial frame: its visual shapes (boxes, spheres, capsules,
    cylinders, meshes read by trimesh) in their colours, or its collision shapes where it has none."""
    shapes = rb.adapter.visual_shapes(rb.id).get(rb.link) or rb.shapes
    out = []
    for sh in shapes:
        pose = (np.asarray(sh.position, float), np.asarray(sh.quaternion, float))
        # planes are not drawn; nor meshes without a file trimesh reads
        drawn = sh.geometry.draw(tuple(int(round(255 * c)) for c in sh.rgba), pose)
        if drawn is not None:
            out.append(drawn)
    return out


def _bodies_of(target) -> list[FemBody]:
    return list(getattr(target, "bodies", []))


def three_quarter_eye(points, radii=None, fov: float = VIEW_FOV, direction: np.ndarray = EYE_DIRECTION,
                      aspect: float = 1.0, margin: float = 0.06) -> tuple[np.ndarray, np.ndarray]:
    """The eye position (3,) and look target (3,) [m] of a view that shows every ball (points (n, 3) [m], radii
    (n,) [m], default 0) whole: the target is the centre of their box, the eye along ``direction`` (unit, towards
    the eye), as close as it can be with everything inside the field of view ``fov`` [rad] (vertical;
    horizontal: widened by ``aspect`` = width / height) shrunk by ``margin`` on each side."""
    points = np.asarray(points, float).reshape(-1, 3)
    radii = np.zeros(len(points)) if radii is None else np.broadcast_to(np.asarray(radii, float), (len(points),))
    if not len(points) or not (np.all(np.isfinite(points)) and np.all(np.isfinite(radii))):
        raise InvalidInputError(f"the view needs finite points (n, 3) and radii (n,), got {points!r}, {radii!r}")
    lo, hi = (points - radii[:, None]).min(axis=0), (points + radii[:, None]).max(axis=0)
    center = 0.5 * (lo + hi)
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    inner = 2 * math.atan((1 - 2 * margin) * math.tan(0.5 * fov))
    near, far = 0.0, 1.0 + 4 * float(np.linalg.norm(hi - lo)) / math.tan(0.5 * inner) / min(aspect, 1.0)
    for _ in range(50):  # bisection on the distance: the nearest eye that shows everything
        mid = 0.5 * (near + far)
        if frames(center + mid * d, center, points, radii, inner, aspect):
            far = mid
        else:
            near = mid
    return center + far * d, center


def frames(eye: np.ndarray, target: np.ndarray, points, radii=None, fov: float = VIEW_FOV,
           aspect: float = 1.0) -> bool:
    """True if every ball (points (n, 3), radii (n,) [m]) lies whole inside the view from ``eye`` towards
    ``target`` (up +z) with the vertical field of view ``fov`` [rad] and width / height ``aspect``."""
    points = np.asarray(points, float).reshape(-1, 3)
    radii = np.zeros(len(points)) if radii is None else np.broadcast_to(np.asarray(radii, float), (len(points),))
    fwd = np.asarray(target, float) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    rel = points - eye
    depth = rel @ fwd
    ty, tx = math.tan(0.5 * fov), aspect * math.tan(0.5 * fov)
    # a ball is inside a side plane of the frustum if its centre is at least r from it
    inside_y = np.abs(rel @ up) * np.cos(math.atan(ty)) + radii <= depth * np.sin(math.atan(ty))
    inside_x = np.abs(rel @ right) * np.cos(math.atan(tx)) + radii <= depth * np.sin(math.atan(tx))
    return bool(np.all(depth > radii) and np.all(inside_y) and np.all(inside_x))


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners (8, 3) of the box lo..hi."""
    return np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T


def colorbar_png(colormap: str, lo: float, hi: float, label: str, width: int = 700, height: int = 300) -> bytes:
    """A horizontal colour bar of ``colormap`` over lo..hi with numbered ticks and ``label``, as PNG bytes (its
    default shape about that of its view in a 1600 x 1000 viewer, so that its text is drawn near full size)."""
    import io

    import matplotlib

    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes((0.04, 0.4, 0.92, 0.22))
    norm = matplotlib.colors.Normalize(lo, hi)
    fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=colormap), cax=ax, orientation="horizontal")
    ax.tick_params(labelsize=16)
    ax.set_title(label, fontsize=16, pad=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", facecolor="white")
    return buf.getvalue()


class _SoftChannel:
    """Per soft body: the drawn vertices (their nodes), the triangles over them, the colour source and the
    vertex-normal operator.

    mode "element": every boundary face of an element gets vertices of its own (all its nodes: 3 for tet4, 6 for
    tet10, 4 for hex8), coloured by that element's value; "nodal": one vertex per surface node, coloured by
    the node's value (von Mises: volume-weighted mean of the elements at the node)."""

    def __init__(self, index: int, body: FemBody, need_stress: bool, mode: str = "nodal"):
        self.index = index
        self.body = body
        self.path = f"world/soft/body{index}"
        mesh = body.mesh
        et = mesh.element_type
        tris = mesh.surface_triangles()
        self.surface = np.unique(tris)  # global ids of the surface nodes
        self.element = None  # (V,) the element of each drawn vertex (mode "element")
        if mode == "element":
            e, f = mesh.boundary_faces()
            faces = np.asarray(et.faces)  # (F, k) local nodes of each face
            k = faces.shape[1]
            self.vertices = mesh.elements[e[:, None], faces[f]].reshape(-1)  # (B k,) node of each vertex
            slot = np.full((len(faces), et.n_nodes), -1)  # local node -> its place in the face's node list
            slot[np.arange(len(faces))[:, None], faces] = np.arange(k)
            local = np.asarray(et.face_triangles)[f]  # (B, t, 3) local nodes
            self.triangles = (slot[f[:, None, None], local] + k * np.arange(len(f))[:, None, None]
                              ).reshape(-1, 3).astype(np.uint32)
            self.element = np.repeat(e, k)
        else:
            self.vertices = self.surface
            self.triangles = np.searchsorted(self.surface, tris).astype(np.uint32)
        # area-weighted vertex normals: node normal = sum of the cross products of the triangles at the node
        tri_nodes = np.searchsorted(self.surface, tris)
        self._tri_nodes = tri_nodes
        T = len(tris)
        self._node_of_tri = sp.csr_matrix((np.ones(3 * T), (tri_nodes.ravel(), np.repeat(np.arange(T), 3))),
                                          shape=(len(self.surface), T))
        self._vertex_slot = np.searchsorted(self.surface, self.vertices)
        self.average = None
        if need_stress and mode == "nodal":  # element -> surface node: volume-weighted mean of the elements at it
            elems = mesh.elements
            E, kk = elems.shape
            local = np.searchsorted(self.surface, elems.ravel())
            hit = (local < len(self.surface)) & (self.surface[np.minimum(local, len(self.surface) - 1)] == elems.ravel())
            rows, cols = local[hit], np.repeat(np.arange(E), kk)[hit]
            A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(self.surface), E))
            A.sum_duplicates()
            A.data[:] = 1.0  # an element counts once per node
            A = A @ sp.diags(mesh.element_volumes())
            weight = np.asarray(A.sum(axis=1)).ravel()
            self.average = sp.diags(1.0 / np.where(weight > 0, weight, 1.0)) @ A

    def positions(self) -> np.ndarray:
        """(V, 3) float32 positions of the drawn vertices [m]."""
        return self.body.positions[self.vertices].astype(np.float32)

    def normals(self) -> np.ndarray:
        """(V, 3) float32 unit normals of the drawn vertices: area-weighted over the surface triangles at each node
        (smooth shading; the colours stay per face in mode "element")."""
        x = self.body.positions[self.surface]
        a, b, c = (x[self._tri_nodes[:, j]] for j in range(3))
        n = self._node_of_tri @ np.cross(b - a, c - a)
        n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-300)[:, None]
        return n[self._vertex_slot].astype(np.float32)


class Recorder:
    """Records a run to a rerun ``.rrd`` file; attach with :meth:`attach`, then call it after each step.

    target: a :class:`experiments.scenes.Scene`, an :class:`integration.world.World` or a
    :class:`softbody.Simulation`. path: the ``.rrd`` file, or a directory for a :func:`default_path` name in it
    (default: under ``directory``, logs/); checked by :func:`record_target` (``overwrite=False`` refuses an
    existing file).
    every: record every k-th step (step counter of the simulation; the state at attach time is frame 0).
    content: what to record, a subset of CONTENT: "mesh" (soft surfaces), "colors" (vertex colours
    by ``color_by``), "rigid" (shapes and poses), "contacts" (active contact points and arrows),
    "attachments", "monitor" (trajectories of the monitored nodes), "diagnostics" (energies, step
    time, contact count). Nothing is computed for content that is off.
    color_by: "von_mises" (element stress, kPa) or "displacement" (|x - X|, mm). color_mode: "element" (von
    Mises' default: one colour per element face, the element's value, no averaging) or "nodal" (one colour per
    surface node: von Mises averaged over the elements at the node by volume; displacement's only mode, its
    field being nodal).
    color_range: fixed (lo, hi) of the colour map [Pa or m]; None: from 0 to the largest value of the run, at least
    COLOR_FLOOR_FRACTION of the smallest E [Pa] (or of the smallest body's extent [m]), one range for the whole
    recording (re-sent for every frame at close). colormap: a matplotlib colour map name (named on the colour bar).
    monitor: node ids of body 0, or (body index, node id) pairs; default the scene's monitored node.
    contact_arrows: "force" (the contact force on the soft body, out of the rigid body, times ``force_scale``
    [m/N]; None: the soft bodies' weight draws half their size) or "normal" (unit normals times
    ``arrow_length`` [m]). plane_size [m]: edge of the square drawn for infinite planes.
    frame: what the scene view frames, "all" (every soft body and rigid link over the run) or "soft" (the soft
    bodies over the run, with a margin of their own size: a small object in a large scene, e.g. a robot's grasp).
    batch: frames buffered before they are sent; flush_seconds: also send when the oldest buffered
    frame is older than this (so a viewer following the file stays current).
    """

    def __init__(self, target, path: str | Path | None = None, *, every: int = 1,
                 content: Iterable[str] = CONTENT, color_by: str = "von_mises",
                 color_range: tuple[float, float] | None = None, colormap: str = "viridis",
                 color_mode: str | None = None, monitor=None, scene=None, contact_arrows: str = "force",
                 arrow_length: float = 0.05, force_scale: float | None = None, plane_size: float = 4.0, batch: int = 50,
                 flush_seconds: float = 1.0, blueprint: bool = True, frame: str = "all",
                 application_id: str = "softbody", directory: str | Path = "logs", overwrite: bool = True):
        if hasattr(target, "world") and hasattr(target, "body") and hasattr(target, "monitor"):
            scene = target if scene is None else scene
            target = target.world
        if not (hasattr(target, "bodies") and hasattr(target, "step") and hasattr(target, "t")):
            raise InvalidInputError(f"Recorder needs a Scene, World or Simulation, got {type(target).__name__}")
        self.target = target
        self.scene = scene
        self.sim: Simulation = getattr(target, "sim", target)
        self.is_world = hasattr(target, "rigids")
        every = int(every)
        if every < 1:
            raise InvalidInputError(f"every must be a positive integer, got {every!r}")
        self.every = every
        self.content = {content} if isinstance(content, str) else set(content)
        if frame not in ("all", "soft"):
            raise InvalidInputError(f"frame must be 'all' or 'soft', got {frame!r}")
        self.frame = frame
        unknown = self.content - set(CONTENT)
        if unknown:
            raise InvalidInputError(f"unknown content {sorted(unknown)}; choose from {CONTENT}")
        if color_by not in COLOR_FIELDS:
            raise InvalidInputError(f"color_by must be one of {sorted(COLOR_FIELDS)}, got {color_by!r}")
        if color_mode is None:
            color_mode = "element" if color_by == "von_mises" else "nodal"
        if color_mode not in COLOR_MODES or (color_by == "displacement" and color_mode != "nodal"):
            raise InvalidInputError(f"color_mode must be one of {COLOR_MODES} ('nodal' for displacement), "
                                    f"got {color_mode!r}")
        self.color_mode = color_mode
        if "colors" in self.content and "mesh" in self.content:
            import matplotlib

            if colormap not in matplotlib.colormaps:
                raise InvalidInputError(f"colormap {colormap!r} is not a matplotlib colour map, e.g. 'viridis', "
                                        "'magma'")
        self.colormap = colormap
        if "mesh" not in self.content:
            self.content.discard("colors")
        if contact_arrows not in ("normal", "force"):
            raise InvalidInputError(f"contact_arrows must be 'normal' or 'force', got {contact_arrows!r}")
        if color_range is not None:
            lo, hi = (float(c) for c in color_range)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise InvalidInputError(f"color_range must be (lo, hi) with lo < hi, got {color_range!r}")
            color_range = (lo, hi)
        self.color_by = color_by
        self.color_range = color_range
        self.contact_arrows = contact_arrows
        self.arrow_length = float(arrow_length)
        self.force_scale = None if force_scale is None else float(force_scale)
        self.plane_size = float(plane_size)
        self.batch = max(1, int(batch))
        self.flush_seconds = float(flush_seconds)
        if not self.is_world:
            self.content -= {"rigid", "contacts", "attachments"}

        bodies = _bodies_of(target)
        need_stress = "colors" in self.content and color_by == "von_mises"
        mode = color_mode if "colors" in self.content else "nodal"
        self._soft = [_SoftChannel(i, b, need_stress, mode) for i, b in enumerate(bodies)]
        self._fields: list[tuple[float, dict[str, np.ndarray], float]] = []  # per frame: colour sources, hi
        self._field_bytes = 0
        self._unkept: list[tuple[float, float]] = []  # (time, hi) of frames past FIELD_BUDGET
        self._stale_from: float | None = None  # the first frame left on a smaller range at close (past the budget)
        self._bar_range: tuple[float, float] | None = None
        self._lut = _colormap(colormap) if "colors" in self.content else None
        self._color_floor = self._color_high = 0.0
        if "colors" in self.content and bodies and color_range is None:
            sizes = [getattr(b.material, "softest", b.material.E) for b in bodies] if color_by == "von_mises" else \
                [float(np.ptp(b.rest, axis=0).max()) for b in bodies]
            self._color_floor = self._color_high = COLOR_FLOOR_FRACTION * min(sizes)
        self._setup_ms: float | None = None  # wall time of the first step [ms]
        self._monitor = self._resolve_monitor(monitor, scene, bodies) if "monitor" in self.content else []
        self._moving = []  # rigid bodies whose pose changes (dynamic or kinematic)
        if "rigid" in self.content:
            self._moving = [rb for rb in target.rigids.values() if rb.mode != "fixed"]
        self._attach = self._attachments() if "attachments" in self.content else []
        self._newton = getattr(getattr(self.sim, "stepper", None), "iterates", False) and "diagnostics" in self.content
        self._series = 0  # explicit series colours, handed out in order (_colors_of)
        # what the 3D views frame [m]: the soft bodies' box, and per rigid link the box of its centre's path and
        # its bounding radius; from the scene at attach (kinematic links over its duration), grown per frame
        self._soft_box, self._link_paths = self._start_bounds()
        self._contact_box = [np.full(3, np.inf), np.full(3, -np.inf)]
        self.start_framing = (self.framing(), self.framing(soft=False))
        if self.force_scale is None:
            weight = sum(b.total_mass for b in bodies) * float(np.linalg.norm(getattr(self.sim, "gravity", 9.81)))
            extent = float(np.max(self._soft_box[1] - self._soft_box[0])) if bodies else 1.0
            self.force_scale = 0.5 * extent / max(weight, 1e-12)
        self._with_blueprint = blueprint

        file, folder = record_target(path, overwrite, directory)
        self.path = file or default_path(scene, target, folder)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(application_id, recording_id=str(uuid.uuid4()))
        self.rec.save(self.path, default_blueprint=self._blueprint() if blueprint else None)
        self.rec.send_recording_name(self.path.stem)
        self.closed = False
        self.frames = 0
        self._frames: list[tuple[float, dict]] = []
        self._oldest = None
        self._last_step = None
        self._last_end = time.perf_counter()
        self._steps0 = self.sim.steps
        self._log_static()
        self._record()  # frame 0: the state at attach time
        atexit.register(self.close)

    # ------------------------------------------------------------------ public API
    @classmethod
    def attach(cls, target, path: str | Path | None = None, **options) -> "Recorder":
        """A recorder of ``target`` (Scene, World or Simulation); use it as the run's callback."""
        return cls(target, path, **options)

    def __call__(self, _=None) -> None:
        """Record the current state if the step counter is a multiple of ``every`` (callback of run())."""
        if self.closed:
            raise RuntimeError(f"recorder of {self.path} is closed")
        steps = self.sim.steps
        if self._setup_ms is None and steps > self._steps0 and "diagnostics" in self.content:
            self._setup_ms = self._step_ms(time.perf_counter())
            self._send_scalars("plots/setup_time", [(float(self.target.t), (self._setup_ms,))])
            self._log_legend()
        if steps % self.every == 0 and steps != self._last_step:
            self._record()
        self._last_end = time.perf_counter()

    def close(self) -> None:
        """Send the buffered frames, the colours of every frame in the run's one colour range, the colour bar,
        legend and the blueprint framed on the run's bounds; finish the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        atexit.unregister(self.close)
        try:
            self._flush()
            self._final_colors()
            if self._with_blueprint:
                self.rec.send_blueprint(self._blueprint((self.framing(), self.framing(soft=False))),
                                        make_active=True, make_default=True)
        finally:
            self.rec.flush()
            self.rec.disconnect()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False  # never swallow the exception

    # ------------------------------------------------------------------ setup
    @staticmethod
    def _resolve_monitor(monitor, scene, bodies) -> list[tuple[int, int]]:
        if monitor is None:
            if scene is None:
                return []
            b = next(i for i, body in enumerate(bodies) if body is scene.body)
            return [(b, int(scene.monitor))]
        items = [monitor] if np.isscalar(monitor) else list(monitor)
        out = []
        for m in items:
            b, n = (0, m) if np.isscalar(m) else m
            b, n = int(b), int(n)
            if not (0 <= b < len(bodies)) or not (0 <= n < bodies[b].n_nodes):
                raise InvalidInputError(f"monitor entry {m!r} is not a node of a body in the recording")
            out.append((b, n))
        return out

    def _attachments(self) -> list[tuple[FemBody, np.ndarray]]:
        return [(a.body, np.asarray(a.nodes)) for a in getattr(self.target, "attachments", [])]

    def _node_label(self, b: int, n: int) -> str:
        return f"node{n}" if len(self._soft) == 1 else f"body{b}_node{n}"

    def _start_bounds(self) -> tuple[list[np.ndarray], dict]:
        """At attach time: the soft bodies' box [lo, hi] [m], and per rigid link (planes left out) [lo, hi, r]: the box
        of its centre's path (kinematic links: over the scene's duration) and its bounding radius [m]. Soft bodies
        are taken to be carried along by the kinematic links' motion (a body hanging from a moving platform)."""
        bodies = _bodies_of(self.target)
        if bodies:
            soft = [np.min([b.positions.min(axis=0) for b in bodies], axis=0),
                    np.max([b.positions.max(axis=0) for b in bodies], axis=0)]
        else:
            soft = [np.full(3, np.inf), np.full(3, -np.inf)]
        links = {}
        if self.is_world:
            duration = getattr(self.scene, "duration", None) if self.scene is not None else None
            for rb in self.target.rigids.values():
                r = rb.bounding_radius()
                if not math.isfinite(r):
                    continue
                c, _ = rb.pose()
                path = c[None, :]
                if rb.motion is not None and duration:
                    ts = float(self.target.t) + np.linspace(0.0, float(duration), 41)
                    path = np.vstack([path, [rb.scripted_pose(t)[0] for t in ts]])
                    if bodies:
                        shift = path - c
                        soft = [np.minimum(soft[0], soft[0] + shift.min(axis=0)),
                                np.maximum(soft[1], soft[1] + shift.max(axis=0))]
                links[rb.key] = [path.min(axis=0), path.max(axis=0), r]
        return soft, links

    def framing(self, soft: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """What the 3D views frame: points (n, 3) and radii (n,) [m] (the corners of the soft bodies' box, the
        corners of each rigid link's path box with its bounding radius), so far; soft=False: the rigid links only
        (the contacts view; everything if there are none)."""
        if not soft and self._link_paths:
            boxes = [(lo, hi, r) for lo, hi, r in self._link_paths.values()]
            if np.all(np.isfinite(self._contact_box[0])):  # the contact points and their arrows so far
                boxes.append((*self._contact_box, 0.0))
            return (np.concatenate([box_corners(lo, hi) for lo, hi, _ in boxes]),
                    np.concatenate([np.full(8, r) for _, _, r in boxes]))
        pts, rad = [], []
        if np.all(np.isfinite(self._soft_box[0])):
            pts.append(box_corners(*self._soft_box))
            rad.append(np.zeros(8))
            if self.frame == "soft":  # the soft bodies' box, with room around it of its own size
                return pts[0], np.full(8, float(np.max(self._soft_box[1] - self._soft_box[0])))
        for lo, hi, r in self._link_paths.values():
            pts.append(box_corners(lo, hi))
            rad.append(np.full(8, r))
        if not pts:
            return np.array([[-1.0, -1, -1], [1, 1, 1]]), np.zeros(2)
        return np.concatenate(pts), np.concatenate(rad)

    @property
    def camera(self) -> tuple[np.ndarray, np.ndarray]:
        """The scene view's eye position and look target (3,) [m] for everything framed so far (the blueprint's at
        attach, and at close)."""
        return three_quarter_eye(*self.framing(), aspect=SCENE_ASPECT)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The box lo, hi (3,) [m] of everything framed so far."""
        pts, rad = self.framing()
        return (pts - rad[:, None]).min(axis=0), (pts + rad[:, None]).max(axis=0)

    def _colors_of(self, n: int) -> list[tuple[int, int, int]]:
        """The next n series colours: SERIES_COLORS, then hues spaced by the golden ratio (distinct)."""
        import colorsys

        out = []
        for i in range(self._series, self._series + n):
            if i < len(SERIES_COLORS):
                out.append(SERIES_COLORS[i])
            else:
                rgb = colorsys.hsv_to_rgb((0.13 + 0.618034 * i) % 1.0, 0.55 + 0.3 * (i % 2), 0.95 - 0.2 * (i % 3 == 0))
                out.append(tuple(int(round(255 * c)) for c in rgb))
        self._series += n
        return out

    def _plots(self) -> list[tuple[str, list[tuple[str, str, int]]]]:
        """The time-series views, the monitored coordinate first: (name, views) per view or group of views side
        by side (each monitored node's x, y and z), a view as (entity, title, number of series)."""
        plots = []
        if self.scene is not None and self._monitor:
            title = f"{'xyz'[self.scene.axis]} of node {self.scene.monitor} [mm]"
            plots.append((title, [("plots/monitored", title, 1)]))
        for b, n in self._monitor:
            label = self._node_label(b, n)
            plots.append((f"node {n}: x, y, z [mm]",
                          [(f"plots/monitor/{label}/{axis}", f"node {n}: {axis} [mm]", 1) for axis in "xyz"]))
        single = [("plots/energy", "energy [J]", len(self._energy_names()))] if "diagnostics" in self.content else []
        if "diagnostics" in self.content:
            if self.is_world:
                single.append(("plots/contacts", "contacts", 2))
            single.append(("plots/step_time", "step time from the second step [ms]", 1))
            if self._newton:
                single += [("plots/newton/iterations", "Newton iterations per step", 1),
                           ("plots/newton/residual", "Newton: log10 final relative residual", 1)]
        if "colors" in self.content:
            name, unit, _ = COLOR_FIELDS[self.color_by]
            single.append(("plots/color_range", f"{name}: frame min and max [{unit}]", 2))
        return plots + [(title, [(path, title, n)]) for path, title, n in single]

    @staticmethod
    def _series_view(path: str, title: str, series: int) -> rrb.TimeSeriesView:
        """A time-series view of ``path``; with more than one series its legend at PLOT_LEGEND_CORNER, else none."""
        legend = rrb.PlotLegend(corner=PLOT_LEGEND_CORNER, visible=True) if series > 1 else \
            rrb.PlotLegend(visible=False)
        return rrb.TimeSeriesView(origin="/" + path, name=title, plot_legend=legend)

    def _blueprint(self, framing: tuple | None = None) -> rrb.Blueprint:
        """Scene view framed three-quarter on ``framing`` (everything, the rigid links: each points and radii, see
        :meth:`framing`; default: the scene's at attach), colour bar and legend under it; on the right the
        contacts (soft bodies hidden, framed on the rigid links), the monitored coordinate and the other plots in
        tabs (each monitored node's x, y and z side by side in one; :meth:`_series_view` for the legends)."""
        framing = self.start_framing if framing is None else framing

        def eye_controls(aspect: float, which: int = 0):
            eye, target = three_quarter_eye(*framing[which], aspect=aspect)
            return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye, look_target=target, eye_up=(0, 0, 1))

        scene = rrb.Spatial3DView(origin="/world", name="scene", eye_controls=eye_controls(SCENE_ASPECT),
                                  contents=["+ /world/**", "- /world/contacts/**"])  # contacts: their own view
        left, shares = [scene], [LEFT_ROW_SHARES[0]]
        under = []
        if "colors" in self.content:
            under.append(rrb.Spatial2DView(origin="/colorbar", name="colour bar"))
        if self.content & {"colors", "diagnostics"}:
            under.append(rrb.TextDocumentView(origin="/legend", name="legend"))
        if under:
            left.append(rrb.Horizontal(*under, column_shares=list(UNDER_COLUMN_SHARES)) if len(under) > 1
                        else under[0])
            shares.append(LEFT_ROW_SHARES[1])
        right, rshares = [], []
        if self.is_world and "contacts" in self.content:
            right.append(rrb.Spatial3DView(origin="/world", name="contacts (soft bodies hidden)",
                                           contents=["+ /world/**", "- /world/soft/**", "- /world/monitor"],
                                           eye_controls=eye_controls(CONTACTS_ASPECT, 1)))
            rshares.append(3)
        listed = self._plots()
        plots = [self._series_view(*views[0]) if len(views) == 1 else
                 rrb.Horizontal(*(self._series_view(*v) for v in views), name=name) for name, views in listed]
        if listed and listed[0][1][0][0] == "plots/monitored":  # the monitored coordinate: a view of its own
            right.append(plots.pop(0))
            rshares.append(2)
        if plots:
            right.append(rrb.Tabs(*plots) if len(plots) > 1 else plots[0])
            rshares.append(2)
        main = rrb.Vertical(*left, row_shares=shares) if len(left) > 1 else left[0]
        if not right:
            return rrb.Blueprint(main, collapse_panels=True)
        return rrb.Blueprint(rrb.Horizontal(main, rrb.Vertical(*right, row_shares=rshares), column_shares=[3, 2]),
                             collapse_panels=True)

    def _series_lines(self, path: str, names: list[str], **kw) -> None:
        self.rec.log(path, rr.SeriesLines(names=names, colors=self._colors_of(len(names)), **kw), static=True)

    def _log_static(self) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if "mesh" in self.content:
            for s in self._soft:
                if "colors" in self.content:
                    static = rr.Mesh3D.from_fields(triangle_indices=s.triangles)
                else:
                    static = rr.Mesh3D.from_fields(triangle_indices=s.triangles, albedo_factor=_SOFT_ALBEDO)
                rec.log(s.path, static, static=True)
        self._log_legend()
        if "colors" in self.content:
            name, unit, _ = COLOR_FIELDS[self.color_by]
            self._series_lines("plots/color_range", [f"frame min [{unit}]", f"frame max [{unit}]"])
            self._log_colorbar(*self._color_scale(0.0, grow=False))
        if self.scene is not None and self._monitor:
            self._series_lines("plots/monitored", [f"{'xyz'[self.scene.axis]} [mm]"], widths=2.0)
        for b, n in self._monitor:
            for axis in "xyz":
                self._series_lines(f"plots/monitor/{self._node_label(b, n)}/{axis}", [f"{axis} [mm]"])
        if self._monitor and "mesh" in self.content:
            rec.log("world/monitor", rr.Points3D.from_fields(colors=_MONITOR_COLOR, radii=0.012), static=True)
        if "diagnostics" in self.content:
            self._series_lines("plots/energy", list(self._energy_names()))
            self._series_lines("plots/step_time", ["step [ms]"])
            rec.log("plots/setup_time", rr.SeriesPoints(names=["first step [ms]"], colors=self._colors_of(1)),
                    static=True)
            if self.is_world:
                self._series_lines("plots/contacts", ["active", "candidates within reach, not touching"])
            if self._newton:
                self._series_lines("plots/newton/iterations", ["iterations"])
                self._series_lines("plots/newton/residual", ["log10 residual"])
        if "contacts" in self.content:
            for path, (point, arrow) in CONTACT_KINDS.items():
                rec.log(f"{path}/points", rr.Points3D.from_fields(colors=point, radii=0.008), static=True)
                rec.log(f"{path}/arrows", rr.Arrows3D.from_fields(colors=arrow, radii=0.004), static=True)
        if self._attach:
            rec.log("world/attachments", rr.Points3D.from_fields(colors=_ATTACH_COLOR, radii=0.008), static=True)
        if "rigid" in self.content:
            for rb in self.target.rigids.values():
                path = self._rigid_path(rb)
                if rb.shape == "urdf":  # a link of the user's body: one child entity per shape
                    for k, shape in enumerate(_link_visuals(rb)):
                        rec.log(f"{path}/shape{k}", shape, static=True)
                else:
                    rec.log(path, self._rigid_shape(rb), static=True)
                if rb.mode == "fixed":
                    pos, quat = rb.pose()
                    rec.log(path, rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=quat)), static=True)

    def _log_colorbar(self, lo: float, hi: float) -> None:
        """The colour bar image (static; rewritten at close with the run's range)."""
        if self._bar_range == (lo, hi):
            return
        self._bar_range = (lo, hi)
        name, unit, k = COLOR_FIELDS[self.color_by]
        how = "per element face" if self.color_mode == "element" else "nodal average" if self.color_by == "von_mises" \
            else "per node"
        label = f"{name} [{unit}], {how}; colour map: {self.colormap}"
        self.rec.log("colorbar", rr.EncodedImage(contents=colorbar_png(self.colormap, lo * k, hi * k, label),
                                                 media_type="image/png"), static=True)

    def _log_legend(self) -> None:
        """The legend (static, rewritten once the first step's time is known and at close): colour field, how it
        is drawn, colour map and range, contact arrows, set-up time. Short: it fits its view in a 1600 x 1000
        viewer (LEFT_ROW_SHARES, UNDER_COLUMN_SHARES)."""
        lines = []
        if "colors" in self.content:
            name, unit, k = COLOR_FIELDS[self.color_by]
            if self.color_by == "displacement":
                src = "per node"
            elif self.color_mode == "element":
                src = "per element face (each element's value at its centre, not averaged)"
            else:
                src = "the volume-weighted mean of the elements at each surface node"
            if self.color_range:
                how = f"a fixed range {k * self.color_range[0]:.4g} .. {k * self.color_range[1]:.4g} {unit}"
            else:
                final = "the run's largest" if self.closed else "the largest so far"
                how = (f"one range for the whole recording, 0 .. {k * self._color_high:.4g} {unit} ({final}, at "
                       f"least {k * self._color_floor:.4g} {unit})")
                if self._stale_from is not None:
                    how += (f"; frames from t = {self._stale_from:g} s on, past the recorder's memory budget, may be "
                            "on a smaller one")
            lines.append(f"**Colours**: {name} [{unit}], {src}; map **{self.colormap}**, {how}.")
        if "contacts" in self.content and self.is_world:
            what = (f"forces on the soft body, {1e3 * self.force_scale:.3g} mm per N"
                    if self.contact_arrows == "force" else f"unit normals, {self.arrow_length:g} m long")
            lines.append(f"**Contacts** (own view): red points on the rigid surfaces, arrows: {what} (face "
                         "contacts magenta, soft-soft blue).")
        if "diagnostics" in self.content:
            setup = "" if self._setup_ms is None else f": {self._setup_ms:.1f} ms"
            lines.append(f"**Set-up** (the first step, not in *step time*){setup}.")
        if lines:
            self.rec.log("legend", rr.TextDocument("\n\n".join(lines), media_type="text/markdown"), static=True)

    def _energy_names(self) -> tuple[str, ...]:
        if self.is_world:
            return ("soft kinetic", "elastic", "soft gravitational", "rigid kinetic", "rigid gravitational", "total")
        return ("kinetic", "elastic", "gravitational", "total")

    def _energies(self) -> tuple[float, ...]:
        """The energies of :meth:`_energy_names` [J] (gravitational: zero at the origin)."""
        if self.is_world:
            e = self.target.energy()
            return (e["soft_kinetic"], e["elastic"], e["soft_potential"], e["rigid_kinetic"], e["rigid_potential"],
                    e["total"])
        g = self.sim.gravity
        k = sum(b.kinetic_energy() for b in self.sim.bodies)
        el = sum(b.elastic_energy() for b in self.sim.bodies)
        pot = sum(b.gravitational_energy(g) for b in self.sim.bodies)
        return k, el, pot, k + el + pot

    def _step_ms(self, now: float) -> float:
        """Wall time of the last step [ms]: the World's own timing, else the time since the recorder last returned."""
        if self.is_world:
            return 1e3 * self.target.report.timings.get("total", 0.0)
        return 1e3 * (now - self._last_end)

    @staticmethod
    def _rigid_path(rb) -> str:
        link = "" if rb.link < 0 else f"_{rb.link}"
        return f"world/rigid/{rr.escape_entity_path_part(rb.name or rb.shape)}_{rb.id}{link}"

    def _rigid_shape(self, rb):
        """The rigid body's shape (a World's own body) in its own frame."""
        shape = rb.geometry
        drawn = None if shape is None else shape.draw(_RIGID_COLOR, plane_size=self.plane_size, subdivisions=4)
        if drawn is None:
            raise InvalidInputError(f"cannot record rigid shape {rb.shape!r}")
        return drawn

    # ------------------------------------------------------------------ per frame
    def _color_field(self, s: _SoftChannel) -> np.ndarray:
        """The colour source, float32 [Pa or m]: von Mises per element ("element") or per surface node
        ("nodal", volume-weighted mean of the elements at the node), with the warping rotations the next step
        reuses; or |x - X| per surface node."""
        body = s.body
        if self.color_by == "von_mises":
            vm = body.von_mises()
            return (vm if s.element is not None else s.average @ vm).astype(np.float32)
        d = body.positions[s.surface] - body.rest[s.surface]
        return np.sqrt(np.einsum("ij,ij->i", d, d)).astype(np.float32)

    @staticmethod
    def _per_vertex(s: _SoftChannel, field: np.ndarray) -> np.ndarray:
        """The colour source of :meth:`_color_field` on the drawn vertices."""
        return field[s.element] if s.element is not None else field

    def _color_scale(self, frame_max: float, grow: bool = True) -> tuple[float, float]:
        """The colour map's (lo, hi): the fixed range, or 0 .. the largest value so far (at least the floor)."""
        if self.color_range:
            return self.color_range
        if grow:
            self._color_high = max(self._color_high, frame_max)
        return 0.0, self._color_high

    def _colors(self, field: np.ndarray, lo: float, hi: float) -> np.ndarray:
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        return self._lut[np.clip((field - lo) * scale, 0, 255).astype(np.intp)]

    def _grow_bounds(self, box: list[np.ndarray], points: np.ndarray) -> None:
        """Grow box [lo, hi] in place to hold points (n, 3)."""
        np.minimum(box[0], points.min(axis=0), out=box[0])
        np.maximum(box[1], points.max(axis=0), out=box[1])

    def _record(self) -> None:
        """Collect one frame into the buffer (a single append, so an interrupt never leaves half a frame)."""
        tic = time.perf_counter()
        target, content = self.target, self.content
        f: dict[str, object] = {}
        fields = {}
        for s in self._soft:
            if "mesh" in content:
                f[s.path] = s.positions()
                f[s.path + "#normals"] = s.normals()
                if "colors" in content:
                    fields[s.path] = self._color_field(s)
            self._grow_bounds(self._soft_box, s.body.positions)
        if fields:
            frame_min = min(float(v.min()) for v in fields.values())
            frame_max = max(float(v.max()) for v in fields.values())
            lo, hi = self._color_scale(frame_max)
            for s in self._soft:
                f[s.path + "#colors"] = self._colors(self._per_vertex(s, fields[s.path]), lo, hi)
            k = COLOR_FIELDS[self.color_by][2]
            f["plots/color_range"] = (k * frame_min, k * frame_max)
            if not self.color_range:  # kept for the final range at close (float32, one value per element or node)
                size = sum(v.nbytes for v in fields.values())
                if self._field_bytes + size <= FIELD_BUDGET:
                    self._fields.append((float(target.t), fields, hi))
                    self._field_bytes += size
                else:
                    self._unkept.append((float(target.t), hi))
        if self._monitor:
            xs = np.array([self._soft[b].body.positions[n] for b, n in self._monitor])
            for (b, n), x in zip(self._monitor, xs):
                for axis, value in zip("xyz", x):
                    f[f"plots/monitor/{self._node_label(b, n)}/{axis}"] = (1e3 * float(value),)
            if self.scene is not None:
                f["plots/monitored"] = (1e3 * float(xs[0, self.scene.axis]),)
            if "mesh" in content:
                f["world/monitor"] = xs
        for rb in self._moving:
            f[self._rigid_path(rb)] = pose = rb.pose()
            if rb.key in self._link_paths:
                self._grow_bounds(self._link_paths[rb.key], pose[0][None, :])
        report = target.report if self.is_world else None  # what the World's last step published (integration.step)
        if "contacts" in content:
            kinds = {"world/contacts": report.contact_results.values(), "world/contacts/faces": report.face_results.values(),
                     "world/contacts/soft": report.pair_results}
            for path, results in kinds.items():
                pts, vec = [], []
                for c, res in results:
                    a = res.active
                    pts.append(c.point[a])
                    vec.append(c.normal[a] * self.arrow_length if self.contact_arrows == "normal"
                               else res.force[a] * self.force_scale)
                f[f"{path}/points"] = p = np.concatenate(pts) if pts else np.zeros((0, 3))
                f[f"{path}/arrows"] = v = np.concatenate(vec) if vec else np.zeros((0, 3))
                if len(p):
                    self._grow_bounds(self._contact_box, np.concatenate([p, p + v]))
        if self._attach:
            f["world/attachments"] = np.concatenate([b.positions[ids] for b, ids in self._attach])
        if "diagnostics" in content:
            f["plots/energy"] = self._energies()
            if self.is_world:
                active = sum(int(np.count_nonzero(r.active)) for _, r in
                             [*report.contact_results.values(), *report.face_results.values(), *report.pair_results])
                found = len(report.candidates) + len(report.face_hits) + len(report.soft_hits) + len(report.edge_hits)
                f["plots/contacts"] = (active, max(found - active, 0))
            if self.sim.steps > self._steps0 + 1:  # the first step is set-up (plots/setup_time, from __call__)
                f["plots/step_time"] = (self._step_ms(tic),)
            if self._newton and self.sim.steps > self._steps0:
                report = self.sim.newton_report
                f["plots/newton/iterations"] = (float(report.iterations),)
                res = report.residual
                f["plots/newton/residual"] = (math.log10(res) if res > 0 else float("nan"),)
        self._frames.append((float(target.t), f))
        self._last_step = self.sim.steps
        self.frames += 1
        if self._oldest is None:
            self._oldest = tic
        if len(self._frames) >= self.batch or time.perf_counter() - self._oldest > self.flush_seconds:
            self._flush()

    @staticmethod
    def _time_index(times) -> list:
        # whole nanoseconds, rounded (a float sum of steps like 0.09999999999999999 s reads as 0.1 s)
        ns = np.round(np.asarray(times, float) * 1e9).astype(np.int64).astype("timedelta64[ns]")
        return [rr.TimeColumn(TIMELINE, duration=ns)]

    def _flush(self) -> None:
        frames, self._frames = self._frames, []
        self._oldest = None
        if not frames:
            return
        rec = self.rec
        index = self._time_index([t for t, _ in frames])
        keys = dict.fromkeys(k for _, f in frames for k in f)
        for key in keys:
            if "#" in key:
                continue
            if not all(key in f for _, f in frames):  # a plot of some frames only (step and set-up time)
                self._send_scalars(key, [(t, f[key]) for t, f in frames if key in f])
                continue
            values = [f[key] for _, f in frames]
            if key.startswith("world/soft/"):
                pos = np.concatenate(values)
                lens = [len(v) for v in values]
                extra = {"vertex_normals": np.concatenate([f[key + "#normals"] for _, f in frames])}
                if key + "#colors" in frames[0][1]:
                    extra["vertex_colors"] = np.concatenate([f[key + "#colors"] for _, f in frames])
                columns = rr.Mesh3D.columns(vertex_positions=pos, **extra).partition(lens)
            elif key.startswith("world/rigid/"):
                columns = rr.Transform3D.columns(translation=np.array([v[0] for v in values]),
                                                 quaternion=np.array([v[1] for v in values]))
            elif key.startswith("world/contacts") and key.endswith("/arrows"):
                origins = [f[key[:-len("arrows")] + "points"] for _, f in frames]
                columns = rr.Arrows3D.columns(vectors=np.concatenate(values).reshape(-1, 3),
                                              origins=np.concatenate(origins).reshape(-1, 3)
                                              ).partition([len(v) for v in values])
            elif (key.startswith("world/contacts") and key.endswith("/points")) or key in ("world/attachments",
                                                                                           "world/monitor"):
                columns = rr.Points3D.columns(positions=np.concatenate(values).reshape(-1, 3)
                                              ).partition([len(v) for v in values])
            elif key.startswith("plots/"):
                columns = rr.Scalars.columns(scalars=np.array(values, dtype=float).reshape(len(values), -1))
            else:  # pragma: no cover - every key above is produced by _record
                raise AssertionError(key)
            rec.send_columns(key, indexes=index, columns=columns)

    def _final_colors(self) -> None:
        """At close: one colour range for the whole recording. If the range grew after a frame was sent, every
        frame's vertex colours are sent again in the final range (later rows at the same time replace the
        earlier ones), and the colour bar and legend are rewritten with it."""
        if "colors" not in self.content:
            return
        frames, self._fields = self._fields, []
        lo, hi = self._color_scale(0.0, grow=False)
        self._stale_from = next((t for t, used in self._unkept if used != hi), None)
        for s in self._soft:
            stale = [(t, fl[s.path]) for t, fl, used in frames if used != hi]
            if not stale:
                continue
            cols = [self._colors(self._per_vertex(s, v), lo, hi) for _, v in stale]
            self.rec.send_columns(s.path, indexes=self._time_index([t for t, _ in stale]),
                                  columns=rr.Mesh3D.columns(vertex_colors=np.concatenate(cols)
                                                            ).partition([len(c) for c in cols]))
        self._log_colorbar(lo, hi)
        self._log_legend()

    def _send_scalars(self, key: str, rows: list[tuple[float, tuple[float, ...]]]) -> None:
        """Send one plot's rows (sim time [s], values) as a column."""
        self.rec.send_columns(key, indexes=self._time_index([t for t, _ in rows]),
                              columns=rr.Scalars.columns(scalars=np.array([v for _, v in rows], dtype=float
                                                                          ).reshape(len(rows), -1)))


def record(target, duration: float, path: str | Path | None = None, progress: bool = False, **options) -> Path:
    """Run ``target`` (Scene or World) for ``duration`` [s] while recording; returns the file's path."""
    with Recorder.attach(target, path, **options) as rec:
        target.run(duration, rec, progress=progress)
    return rec.path
