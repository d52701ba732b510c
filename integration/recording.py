"""Rerun recordings of soft-body runs: meshes with stress colours, rigid bodies, contacts, trajectories.

    with Recorder.attach(scene) as rec:          # a Scene, a World or a softbody.Simulation
        scene.run(1.0, rec)                      # rec(world) after each step records it
    print(rec.path)                              # logs/sheet-on-sphere_tet4_8x8x3_20250101-120000.rrd

Open the file with ``rerun <file>.rrd``. Everything is logged on the ``sim_time`` timeline [s]:

    world/soft/body<i>        Mesh3D: surface triangles once (static), vertex positions and colours per frame
    world/rigid/<name>        the rigid shape once (static, body frame) and its Transform3D pose per frame
    world/contacts/points     active node contacts: points on the rigid surfaces
    world/contacts/arrows     their normals (or forces, contact_arrows="force")
    world/contacts/faces/...  the same for rigid points on soft triangles (face contacts)
    world/contacts/soft/...   and for soft-soft and self contacts (points on the triangles)
    world/attachments         attached soft nodes
    world/monitor             the monitored nodes as points
    plots/monitor/<node>      x, y, z of each monitored node (Scalars)
    plots/energy              energies [J]: soft kinetic, elastic, gravitational, rigid kinetic and
                              gravitational (World), and their total, which damping and contact can only lower
    plots/step_time           wall time of each step from the second on [ms]
    plots/setup_time          wall time of the first step [ms] (symbolic analysis, first factorisation)
    plots/contacts            number of active contacts (and candidates)
    plots/color_range         the colour map's range and the frame's min and max of the colour field
    legend                    a text note: which field, units, colour map and its range, set-up time

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

from .bullet import quat_matrix

TIMELINE = "sim_time"
CONTENT = ("mesh", "colors", "rigid", "contacts", "attachments", "monitor", "diagnostics")
COLOR_FIELDS = {"von_mises": ("von Mises stress", "Pa"), "displacement": ("displacement magnitude", "m")}
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
        pos, quat = np.asarray(sh.position, float), np.asarray(sh.quaternion, float)
        R = quat_matrix(quat)
        color = tuple(int(round(255 * c)) for c in sh.rgba)
        if sh.kind == "box":
            out.append(rr.Boxes3D(half_sizes=[sh.size], centers=[pos], quaternions=[rr.Quaternion(xyzw=quat)],
                                  colors=color, fill_mode="solid"))
        elif sh.kind == "sphere":
            out.append(rr.Ellipsoids3D(half_sizes=[[sh.size[0]] * 3], centers=[pos], colors=color, fill_mode="solid"))
        elif sh.kind == "capsule":  # rerun's capsule runs from its origin along +z: start it half a length down
            r, length = sh.size
            out.append(rr.Capsules3D(lengths=[length], radii=[r], translations=[pos - 0.5 * length * R[:, 2]],
                                     quaternions=[rr.Quaternion(xyzw=quat)], colors=color))
        elif sh.kind == "cylinder":
            r, length = sh.size
            out.append(rr.Cylinders3D(lengths=[length], radii=[r], centers=[pos], quaternions=[rr.Quaternion(xyzw=quat)],
                                      colors=color, fill_mode="solid"))
        elif sh.kind == "mesh" and sh.mesh_file:
            try:
                import trimesh

                tm = trimesh.load(sh.mesh_file, force="mesh")
                verts = (np.asarray(tm.vertices) * np.asarray(sh.size)) @ R.T + pos
                normals = trimesh.Trimesh(verts, tm.faces, process=False).vertex_normals
            except Exception:  # a file trimesh cannot read: the link is drawn without this shape
                continue
            out.append(rr.Mesh3D(vertex_positions=verts, triangle_indices=np.asarray(tm.faces), vertex_normals=normals,
                                 albedo_factor=color))
    return out


def _bodies_of(target) -> list[FemBody]:
    return list(getattr(target, "bodies", []))


class _SoftChannel:
    """Per soft body: the surface vertices, the triangle indices into them, the nodal averaging."""

    def __init__(self, index: int, body: FemBody, need_stress: bool):
        self.index = index
        self.body = body
        self.path = f"world/soft/body{index}"
        tris = body.mesh.surface_triangles()
        self.surface = np.unique(tris)  # global ids of the surface vertices
        self.triangles = np.searchsorted(self.surface, tris).astype(np.uint32)
        self.average = None
        if need_stress:  # element -> surface node mean over the elements that touch the node
            elems = body.mesh.elements
            E, k = elems.shape
            local = np.searchsorted(self.surface, elems.ravel())
            hit = (local < len(self.surface)) & (self.surface[np.minimum(local, len(self.surface) - 1)] == elems.ravel())
            rows, cols = local[hit], np.repeat(np.arange(E), k)[hit]
            A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(self.surface), E))
            A.sum_duplicates()
            A.data[:] = 1.0  # an element counts once per node (tet10 faces list no node twice, but be safe)
            counts = np.asarray(A.sum(axis=1)).ravel()
            self.average = sp.diags(1.0 / np.maximum(counts, 1)) @ A


class Recorder:
    """Records a run to a rerun ``.rrd`` file; attach with :meth:`attach`, then call it after each step.

    target: a :class:`integration.scenes.Scene`, an :class:`integration.world.World` or a
    :class:`softbody.Simulation`. path: the ``.rrd`` file, or a directory for a :func:`default_path` name in it
    (default: under ``directory``, logs/); checked by :func:`record_target` (``overwrite=False`` refuses an
    existing file).
    every: record every k-th step (step counter of the simulation; the state at attach time is frame 0).
    content: what to record, a subset of CONTENT: "mesh" (soft surfaces), "colors" (vertex colours
    by ``color_by``), "rigid" (shapes and poses), "contacts" (active contact points and arrows),
    "attachments", "monitor" (trajectories of the monitored nodes), "diagnostics" (energies, step
    time, contact count). Nothing is computed for content that is off.
    color_by: "von_mises" (element stress averaged to the nodes, Pa) or "displacement" (|x - X|, m).
    color_range: fixed (lo, hi) of the colour map; None: from 0 to the largest value so far, at least
    COLOR_FLOOR_FRACTION of the smallest E [Pa] (or of the smallest body's extent [m]), so that the scale
    only grows and a body at rest stays dark (logged under plots/color_range). colormap: a matplotlib
    colour map name.
    monitor: node ids of body 0, or (body index, node id) pairs; default the scene's monitored node.
    contact_arrows: "normal" (unit normals times ``arrow_length`` [m]) or "force" (force times
    ``force_scale`` [m/N]). plane_size [m]: edge of the square drawn for infinite planes.
    batch: frames buffered before they are sent; flush_seconds: also send when the oldest buffered
    frame is older than this (so a viewer following the file stays current).
    """

    def __init__(self, target, path: str | Path | None = None, *, every: int = 1,
                 content: Iterable[str] = CONTENT, color_by: str = "von_mises",
                 color_range: tuple[float, float] | None = None, colormap: str = "viridis",
                 monitor=None, scene=None, contact_arrows: str = "normal", arrow_length: float = 0.05,
                 force_scale: float = 0.01, plane_size: float = 4.0, batch: int = 50,
                 flush_seconds: float = 1.0, blueprint: bool = True,
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
        unknown = self.content - set(CONTENT)
        if unknown:
            raise InvalidInputError(f"unknown content {sorted(unknown)}; choose from {CONTENT}")
        if color_by not in COLOR_FIELDS:
            raise InvalidInputError(f"color_by must be one of {sorted(COLOR_FIELDS)}, got {color_by!r}")
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
        self.force_scale = float(force_scale)
        self.plane_size = float(plane_size)
        self.batch = max(1, int(batch))
        self.flush_seconds = float(flush_seconds)
        if not self.is_world:
            self.content -= {"rigid", "contacts", "attachments"}

        bodies = _bodies_of(target)
        need_stress = "colors" in self.content and color_by == "von_mises"
        self._soft = [_SoftChannel(i, b, need_stress) for i, b in enumerate(bodies)]
        self._lut = _colormap(colormap) if "colors" in self.content else None
        self._color_floor = self._color_high = 0.0
        if "colors" in self.content and bodies and color_range is None:
            sizes = [b.material.E for b in bodies] if color_by == "von_mises" else \
                [float(np.ptp(b.rest, axis=0).max()) for b in bodies]
            self._color_floor = self._color_high = COLOR_FLOOR_FRACTION * min(sizes)
        self._setup_ms: float | None = None  # wall time of the first step [ms]
        self._monitor = self._resolve_monitor(monitor, scene, bodies) if "monitor" in self.content else []
        self._moving = []  # rigid bodies whose pose changes (dynamic or kinematic)
        if "rigid" in self.content:
            self._moving = [rb for rb in target.rigids.values() if rb.mode != "fixed"]
        self._attach = self._attachments() if "attachments" in self.content else []

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
        """Send the buffered frames and finish the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        atexit.unregister(self.close)
        try:
            self._flush()
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

    def _plots(self) -> list[tuple[str, str]]:
        plots = [(f"plots/monitor/{self._node_label(b, n)}", f"node {n} [m]") for b, n in self._monitor]
        if "diagnostics" in self.content:
            plots += [("plots/energy", "energy [J]"), ("plots/step_time", "step time from the second step [ms]")]
            if self.is_world:
                plots.append(("plots/contacts", "contacts"))
        if "colors" in self.content:
            name, unit = COLOR_FIELDS[self.color_by]
            plots.append(("plots/color_range", f"colour range: {name} [{unit}]"))
        return plots

    def _blueprint(self) -> rrb.Blueprint:
        left = [rrb.Spatial3DView(origin="/world", name="scene")]
        shares = [6]
        if self.content & {"colors", "diagnostics"}:
            left.append(rrb.TextDocumentView(origin="/legend", name="legend"))
            shares.append(1)
        plots = [rrb.TimeSeriesView(origin="/" + path, name=name) for path, name in self._plots()]
        if not plots:
            return rrb.Blueprint(left[0], collapse_panels=True)
        return rrb.Blueprint(
            rrb.Horizontal(rrb.Vertical(*left, row_shares=shares), rrb.Vertical(*plots), column_shares=[3, 2]),
            collapse_panels=True)

    def _log_static(self) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if "mesh" in self.content:
            for s in self._soft:
                static = rr.Mesh3D.from_fields(triangle_indices=s.triangles)
                if "colors" not in self.content:
                    static = rr.Mesh3D.from_fields(triangle_indices=s.triangles, albedo_factor=_SOFT_ALBEDO)
                rec.log(s.path, static, static=True)
        self._log_legend()
        if "colors" in self.content:
            unit = COLOR_FIELDS[self.color_by][1]
            rec.log("plots/color_range", rr.SeriesLines(names=[f"map low [{unit}]", f"map high [{unit}]",
                                                               f"frame min [{unit}]", f"frame max [{unit}]"]),
                    static=True)
        for b, n in self._monitor:
            rec.log(f"plots/monitor/{self._node_label(b, n)}", rr.SeriesLines(names=["x", "y", "z"]), static=True)
        if self._monitor and "mesh" in self.content:
            rec.log("world/monitor", rr.Points3D.from_fields(colors=_MONITOR_COLOR, radii=0.012), static=True)
        if "diagnostics" in self.content:
            rec.log("plots/energy", rr.SeriesLines(names=list(self._energy_names())), static=True)
            rec.log("plots/step_time", rr.SeriesLines(names=["step"]), static=True)
            rec.log("plots/setup_time", rr.SeriesPoints(names=["first step"]), static=True)
            if self.is_world:
                rec.log("plots/contacts", rr.SeriesLines(names=["active", "candidates"]), static=True)
        if "contacts" in self.content:
            for path, (point, arrow) in CONTACT_KINDS.items():
                rec.log(f"{path}/points", rr.Points3D.from_fields(colors=point, radii=0.006), static=True)
                rec.log(f"{path}/arrows", rr.Arrows3D.from_fields(colors=arrow, radii=0.002), static=True)
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

    def _log_legend(self) -> None:
        """The legend (static, rewritten once the first step's time is known): colour field, map and range."""
        lines = []
        if "colors" in self.content:
            name, unit = COLOR_FIELDS[self.color_by]
            src = "element values averaged to the nodes" if self.color_by == "von_mises" else "|x - X| per node"
            if self.color_range:
                how = f"fixed range {self.color_range[0]:.4g} .. {self.color_range[1]:.4g} {unit}"
            else:
                basis = "Young's modulus" if self.color_by == "von_mises" else "body extent"
                how = (f"from 0 to the largest value so far, at least {self._color_floor:.4g} {unit} "
                       f"({COLOR_FLOOR_FRACTION:g} x the smallest {basis}): the range only grows")
            lines.append(f"**Vertex colours**: {name} [{unit}], {src}. Colour map: low (dark) to high (bright), "
                         f"{how}; map range and frame min/max in `plots/color_range`.")
        if "diagnostics" in self.content:
            setup = "" if self._setup_ms is None else f": {self._setup_ms:.1f} ms"
            lines.append(f"**Set-up** (the first step: symbolic analysis, first factorisation){setup}, in "
                         "`plots/setup_time`, not in `plots/step_time`.")
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
            return 1e3 * self.target.timings.get("total", 0.0)
        return 1e3 * (now - self._last_end)

    @staticmethod
    def _rigid_path(rb) -> str:
        link = "" if rb.link < 0 else f"_{rb.link}"
        return f"world/rigid/{rr.escape_entity_path_part(rb.name or rb.shape)}_{rb.id}{link}"

    def _rigid_shape(self, rb):
        """The rigid body's shape in its own frame."""
        if rb.shape == "sphere":
            r = float(rb.params["radius"])
            return rr.Ellipsoids3D(half_sizes=[[r, r, r]], colors=_RIGID_COLOR, fill_mode="solid")
        if rb.shape == "box":
            return rr.Boxes3D(half_sizes=[rb.params["half_extents"]], colors=_RIGID_COLOR, fill_mode="solid")
        if rb.shape == "plane":
            n = np.asarray(rb.params["normal"], float)
            helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
            t1 = np.cross(n, helper)
            t1 /= np.linalg.norm(t1)
            t2 = np.cross(n, t1)
            h = 0.5 * self.plane_size
            quad = np.array([-t1 - t2, t1 - t2, t1 + t2, -t1 + t2]) * h
            return rr.Mesh3D(vertex_positions=quad, triangle_indices=[[0, 1, 2], [0, 2, 3]],
                             vertex_normals=np.tile(n, (4, 1)), albedo_factor=_RIGID_COLOR)
        if rb.shape == "mesh":
            return rr.Mesh3D(vertex_positions=np.asarray(rb.params["vertices"]),
                             triangle_indices=np.asarray(rb.params["faces"]), albedo_factor=_RIGID_COLOR)
        raise InvalidInputError(f"cannot record rigid shape {rb.shape!r}")

    # ------------------------------------------------------------------ per frame
    def _color_field(self, s: _SoftChannel) -> np.ndarray:
        """The colour field on the surface vertices: von Mises [Pa] (element values averaged to the nodes,
        with the warping rotations the next step reuses) or |x - X| [m]."""
        body = s.body
        if self.color_by == "von_mises":
            return s.average @ body.von_mises()
        d = body.positions[s.surface] - body.rest[s.surface]
        return np.sqrt(np.einsum("ij,ij->i", d, d))

    def _color_scale(self, frame_max: float) -> tuple[float, float]:
        """The colour map's (lo, hi): the fixed range, or 0 .. the largest value so far (at least the floor)."""
        if self.color_range:
            return self.color_range
        self._color_high = max(self._color_high, frame_max)
        return 0.0, self._color_high

    def _colors(self, field: np.ndarray, lo: float, hi: float) -> np.ndarray:
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        return self._lut[np.clip((field - lo) * scale, 0, 255).astype(np.intp)]

    def _record(self) -> None:
        """Collect one frame into the buffer (a single append, so an interrupt never leaves half a frame)."""
        tic = time.perf_counter()
        target, content = self.target, self.content
        f: dict[str, object] = {}
        fields = {}
        for s in self._soft:
            if "mesh" in content:
                f[s.path] = s.body.positions[s.surface].astype(np.float32)
                if "colors" in content:
                    fields[s.path] = self._color_field(s)
        if fields:
            frame_min = min(float(v.min()) for v in fields.values())
            frame_max = max(float(v.max()) for v in fields.values())
            lo, hi = self._color_scale(frame_max)
            for path, field in fields.items():
                f[path + "#colors"] = self._colors(field, lo, hi)
            f["plots/color_range"] = (lo, hi, frame_min, frame_max)
        if self._monitor:
            xs = np.array([self._soft[b].body.positions[n] for b, n in self._monitor])
            for (b, n), x in zip(self._monitor, xs):
                f[f"plots/monitor/{self._node_label(b, n)}"] = x
            if "mesh" in content:
                f["world/monitor"] = xs
        for rb in self._moving:
            f[self._rigid_path(rb)] = rb.pose()
        if "contacts" in content:
            kinds = {"world/contacts": target.contact_results.values(), "world/contacts/faces": target.face_results.values(),
                     "world/contacts/soft": target.pair_results}
            for path, results in kinds.items():
                pts, vec = [], []
                for c, res in results:
                    a = res.active
                    pts.append(c.point[a])
                    vec.append(c.normal[a] * self.arrow_length if self.contact_arrows == "normal"
                               else res.force[a] * self.force_scale)
                f[f"{path}/points"] = np.concatenate(pts) if pts else np.zeros((0, 3))
                f[f"{path}/arrows"] = np.concatenate(vec) if vec else np.zeros((0, 3))
        if self._attach:
            f["world/attachments"] = np.concatenate([b.positions[ids] for b, ids in self._attach])
        if "diagnostics" in content:
            f["plots/energy"] = self._energies()
            if self.is_world:
                active = sum(int(np.count_nonzero(r.active)) for _, r in
                             [*target.contact_results.values(), *target.face_results.values(), *target.pair_results])
                f["plots/contacts"] = (active, len(target.contacts) + len(target.face_hits) + len(target.soft_hits))
            if self.sim.steps > self._steps0 + 1:  # the first step is set-up (plots/setup_time, from __call__)
                f["plots/step_time"] = (self._step_ms(tic),)
        self._frames.append((float(target.t), f))
        self._last_step = self.sim.steps
        self.frames += 1
        if self._oldest is None:
            self._oldest = tic
        if len(self._frames) >= self.batch or time.perf_counter() - self._oldest > self.flush_seconds:
            self._flush()

    def _flush(self) -> None:
        frames, self._frames = self._frames, []
        self._oldest = None
        if not frames:
            return
        rec = self.rec
        # whole nanoseconds, rounded (a float sum of steps like 0.09999999999999999 s reads as 0.1 s)
        times = np.round(np.array([t for t, _ in frames]) * 1e9).astype(np.int64).astype("timedelta64[ns]")
        index = [rr.TimeColumn(TIMELINE, duration=times)]
        keys = dict.fromkeys(k for _, f in frames for k in f)
        for key in keys:
            if key.endswith("#colors"):
                continue
            if not all(key in f for _, f in frames):  # a plot of some frames only (step and set-up time)
                self._send_scalars(key, [(t, f[key]) for t, f in frames if key in f])
                continue
            values = [f[key] for _, f in frames]
            if key.startswith("world/soft/"):
                pos = np.concatenate(values)
                lens = [len(v) for v in values]
                if key + "#colors" in frames[0][1]:
                    cols = np.concatenate([f[key + "#colors"] for _, f in frames])
                    columns = rr.Mesh3D.columns(vertex_positions=pos, vertex_colors=cols).partition(lens)
                else:
                    columns = rr.Mesh3D.columns(vertex_positions=pos).partition(lens)
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


    def _send_scalars(self, key: str, rows: list[tuple[float, tuple[float, ...]]]) -> None:
        """Send one plot's rows (sim time [s], values) as a column."""
        times = np.round(np.array([t for t, _ in rows]) * 1e9).astype(np.int64).astype("timedelta64[ns]")
        self.rec.send_columns(key, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                              columns=rr.Scalars.columns(scalars=np.array([v for _, v in rows], dtype=float
                                                                          ).reshape(len(rows), -1)))


def record(target, duration: float, path: str | Path | None = None, progress: bool = False, **options) -> Path:
    """Run ``target`` (Scene or World) for ``duration`` [s] while recording; returns the file's path."""
    with Recorder.attach(target, path, **options) as rec:
        target.run(duration, rec, progress=progress)
    return rec.path
