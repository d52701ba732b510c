"""Collision detection between soft-body surface nodes and rigid shapes, through pybullet's queries.

Broad phase in numpy: a soft body's surface AABB against each rigid body's AABB (from pybullet),
then only the surface nodes inside the rigid's AABB and its bounding sphere, both grown by the
margin, become candidates. Narrow phase: for links made of primitives (spheres, boxes, capsules,
cylinders, planes) closed-form signed distances of all candidates at once (distance.py); for meshes
pybullet's ``getClosestPoints`` of a point probe at each candidate against the link, which gives the
closest point, the outward normal and the signed distance (for concave triangle meshes the sign comes
from trimesh's inside test). Sharp rigid features (box corners, mesh
vertices) are also tested against the soft surface triangles.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import math

import numpy as np
import pybullet as p
import scipy.sparse as sp
from scipy.spatial import cKDTree

from . import kernels
from .bullet import quat_matrix
from .distance import cross
from .segments import closest_between_segments, edge_normals
from .rigid import RigidLink


# a face point with a barycentric weight above AT_NODE is at that node; above NEAR_TOUCHING it is close
# enough to a node resting on the same link for the node's contact to hold it
AT_NODE = 0.99
NEAR_TOUCHING = 0.8
# a rigid point's travel towards a soft point within the step, times this, widens the contact search (the slack
# covers what pybullet's own step adds to the velocity: gravity, motors, rigid contacts)
RIGID_SLACK = 1.5
# the same for the soft side (its velocity is solved within the step, so it may change more)
SOFT_SLACK = 2.0
# a contact normal and a soft surface's own normal face each other if they make more than ~95 degrees
FACING = -0.1
# a rigid point between nodes (on an edge, or a round part's on a facet) counts only where it lies deeper than the
# node contacts of the nodes around it hold it (their gaps interpolated at the point), by more than this [m]
EDGE_EXPLAINED = 5e-5
# at most this many rigid points (corners) inside one soft triangle
CORNERS_PER_FACET = 4
# an edge's deepest point counts between its nodes only (within this fraction of an end it is the node's contact)
EDGE_END = 0.02
# a soft edge meets a mesh's sharp edge between the ends of both only where they cross at more than ~6 degrees
# (nearly parallel edges are held at their ends, by node and corner contacts), and within this fraction of the
# rigid edge's ends it is that corner's contact on the soft faces
CROSSING_SINE = 0.1
CORNER_END = 1e-6
# a contact normal counts within a sharp edge's cone of outward normals widened by this angle [rad]
CONE_SLACK = 1e-3
# soft edges times a link's sharp edges up to which their boxes are compared all at once (beyond: a k-d tree first)
DENSE_PAIRS = 20_000
# golden-section steps for an edge's deepest point into a part (its signed distance is convex along the edge):
# the bracket shrinks to 0.618^36 ~ 3e-8 of the edge
GOLDEN_STEPS = 36
# the weight of the ends' chord in that search: it only breaks ties (a flat stretch), never moves a deepest point
TIE = 1e-3


@dataclass
class Contacts:
    """Contact candidates as plain arrays (m entries).

    body: soft body index; node: node index; rigid: pybullet body id; point (m, 3): closest point on the
    rigid [m]; normal (m, 3): unit normal out of the rigid towards the node; distance (m,): signed
    distance [m], negative when the node penetrates; link (m,): the rigid's link index (-1: base).
    """

    body: np.ndarray
    node: np.ndarray
    rigid: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    link: np.ndarray | None = None

    FIELDS = ("body", "node", "rigid", "point", "normal", "distance", "link")

    def __post_init__(self):
        if self.link is None:
            self.link = np.full(len(self.node), -1, dtype=np.int64)

    @classmethod
    def empty(cls) -> "Contacts":
        """No contacts (a fresh object over shared read-only empty arrays)."""
        return cls(*_EMPTY_CONTACT_FIELDS)

    def __len__(self) -> int:
        return len(self.node)

    def select(self, mask: np.ndarray) -> "Contacts":
        return Contacts(*(getattr(self, f)[mask] for f in self.FIELDS))

    @classmethod
    def concat(cls, parts: list["Contacts"]) -> "Contacts":
        parts = [c for c in parts if len(c)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:  # nothing to join (contacts are never changed in place)
            return parts[0]
        return cls(*(np.concatenate([getattr(c, f) for c in parts]) for f in cls.FIELDS))


@dataclass(frozen=True)
class Sweep:
    """What one rigid link and one soft body can close within a step of ``h`` [s]: ``margin`` [m] (the contact
    margin), ``velocities`` (N, 3) [m/s] of the soft body's nodes and their ``speeds`` (N,), and the link's
    motion at the start of the step: linear velocity ``v`` (3,) [m/s] of its centre of mass ``centre`` (3,),
    angular velocity ``w`` (3,) [rad/s]; ``radius`` [m] its bounding radius about the centre (inf: unbounded,
    a plane).

    Speculative contact: whatever could meet within the step is a constraint of the step, so that no speed
    tunnels. A soft point at distance d from the link, along the direction n from the rigid point facing it,
    is a candidate if d < margin + h (RIGID_SLACK max(v_p . n, 0) + SOFT_SLACK max(-v_s . n, 0)), v_p the
    rigid point's velocity and v_s the soft point's, and if it lies within the link's bounding sphere swept
    over the step (its centre's path, its radius grown by the spin and by the soft side's travel)."""

    margin: float
    h: float
    velocities: np.ndarray
    speeds: np.ndarray  # (N,) |velocities| [m/s]
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = math.inf

    def soft_travel(self, nodes: np.ndarray | None = None) -> float:
        """The farthest [m] any of the soft ``nodes`` (default: all) may travel within the step, with slack."""
        return SOFT_SLACK * self.h * float((self.speeds if nodes is None else self.speeds[nodes]).max(initial=0.0))

    def rigid_travel(self) -> float:
        """The farthest [m] any point of the link may travel within the step, with slack (0 if unbounded)."""
        spin = _length(self.w) * self.radius if math.isfinite(self.radius) else 0.0
        return RIGID_SLACK * self.h * (_length(self.v) + spin)

    def bound(self, nodes: np.ndarray | None = None) -> float:
        """The largest reach [m] for the soft ``nodes`` (for the broad phase on boxes)."""
        return self.margin + self.soft_travel(nodes) + self.rigid_travel()

    def reach(self, points: np.ndarray, towards: np.ndarray, v_soft: np.ndarray) -> np.ndarray:
        """(m,) the reach [m] at rigid material points (m, 3) whose soft partners lie along unit ``towards``
        (m, 3) from them and move with ``v_soft`` (m, 3): the margin plus what the two close within the step."""
        soft = np.maximum(-np.einsum("ij,ij->i", v_soft, towards), 0.0)
        if not (self.v.any() or self.w.any()):  # a link at rest (most obstacles): the soft side alone
            return self.margin + self.h * (SOFT_SLACK * soft)
        vp = self.v + cross(self.w, points - self.centre)
        rigid = np.maximum(np.einsum("ij,ij->i", vp, towards), 0.0)
        return self.margin + self.h * (RIGID_SLACK * rigid + SOFT_SLACK * soft)

    def swept(self, x: np.ndarray, size: np.ndarray | float = 0.0, travel: float = 0.0) -> np.ndarray:
        """(m,) bool: balls at x (m, 3) of radius ``size`` [m], travelling up to ``travel`` [m], meet the
        link's bounding sphere swept over the step (all True for a link of unbounded extent)."""
        if not math.isfinite(self.radius):
            return np.ones(len(x), dtype=bool)
        path = RIGID_SLACK * self.h * self.v
        length2 = float(path @ path)
        rel = x - self.centre
        gap = rel if length2 == 0 else rel - np.clip(rel @ path / length2, 0.0, 1.0)[:, None] * path
        spin = RIGID_SLACK * self.h * _length(self.w) * self.radius
        reach = self.radius + spin + self.margin + size + travel
        return np.einsum("ij,ij->i", gap, gap) <= reach * reach


def _length(v: np.ndarray) -> float:
    """|v| of one vector (3,) (np.linalg.norm's checks cost more than the sum)."""
    return math.sqrt(float(v @ v))


def read_only(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The arrays, made read-only (shared empty fields: an in-place change fails loudly)."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


_I0, _I03, _F0, _F03 = np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0), np.zeros((0, 3))
_EMPTY_CONTACT_FIELDS = read_only(_I0, _I0, _I0, _F03, _F03, _F0, _I0)
_EMPTY_FACE_FIELDS = read_only(_I0, _I0, _I03, _F03, _F03, _F03, _F0, _I0, _I0, _I0, np.zeros(0, bool), _I0)
_NO_ROWS, _ZERO3 = np.zeros((0, 3)), np.zeros(3)  # the prefilter's sweep arguments when there is no sweep
_NO_ROUND = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))  # no round parts


def _face_contacts_possible(positions: np.ndarray, triangles: np.ndarray, rigid: RigidLink, margin: float,
                            touching: np.ndarray | None, sweep: Sweep | None) -> bool:
    """kernels.face_contacts_possible for CollisionDetector.face_contacts's arguments: False only if it would find
    no face contact."""
    lo, hi = rigid.aabb()
    corners, corner_centres = rigid.corner_points()
    swept = sweep is not None
    return kernels.face_contacts_possible(
        np.ascontiguousarray(positions, dtype=float), np.ascontiguousarray(triangles, dtype=np.int64),
        np.zeros(len(positions), dtype=bool) if touching is None else touching, np.asarray(lo, dtype=float),
        np.asarray(hi, dtype=float), margin, *rigid.round_part_arrays(), rigid.round_parts(),
        np.ascontiguousarray(corners, dtype=float).reshape(-1, 3),
        np.ascontiguousarray(corner_centres, dtype=float).reshape(-1, 3),
        swept, sweep.h if swept else 0.0, RIGID_SLACK, SOFT_SLACK, sweep.velocities if swept else _NO_ROWS,
        *((sweep.v, sweep.w, sweep.centre) if swept else (_ZERO3, _ZERO3, _ZERO3)))


class CollisionDetector:
    """Finds node contacts of soft bodies against rigid bodies within ``margin`` [m]."""

    def __init__(self, client: int):
        self.client = client
        self._probe = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-6, physicsClientId=client)
        self.last_candidates = 0

    def detect(self, body_index: int, positions: np.ndarray, surface: np.ndarray, triangles: np.ndarray,
               supported: np.ndarray, links: list[RigidLink], sweeps: list[Sweep], touch: float,
               incidence: sp.spmatrix | None = None, edges: tuple[np.ndarray, np.ndarray] | None = None,
               movable_edges: bool = True) -> tuple["Contacts", "FaceHits"]:
        """Contact candidates of one soft body (positions (N, 3), surface nodes (s,), surface triangles (T, 3),
        supported (N,) bool) against ``links``: node contacts within each link's reach (``sweeps``, one per link:
        what the two sides may close within the step), one per node (the deepest), rigid points on its triangles
        between nodes (face contacts; a node within ``touch`` of a link rests on it) and, given the surface's
        ``edges`` (E, 2) with the triangles each bounds (E, 2), the points of its edges deepest into links of
        primitive parts, between nodes (edge_contacts; for links the coupled solve moves only if ``movable_edges``).
        A supported node has contacts only with movable links (a
        support wins over contact, but a rigid body resting on it must be held). Far links cost no query (broad
        phase on boxes). ``incidence``: the triangles' node_incidence, if at hand (for the surface normals)."""
        if not len(surface):
            return Contacts.empty(), FaceHits.empty()
        lo0 = hi0 = None  # the surface's box, made when first needed
        parts, faces = [], []
        boxes = touching = touch_normal = None  # made when first needed
        any_support = bool(supported.any())
        for rb, sweep in zip(links, sweeps):
            # supports count as resting nodes for immovable links only: a face point next to a supported node is
            # that node's business then, but against a movable link the support is a rigid surface to be held
            held = supported if any_support and not rb.movable else np.zeros(len(positions), dtype=bool)
            if kernels.ENABLED and incidence is not None and rb.primitive_parts() is not None:
                if touching is None:
                    touching, touch_normal = np.zeros(len(positions), dtype=bool), np.zeros((len(positions), 3))
                status, margin, found = self._primitive_link(body_index, positions, surface, triangles, held,
                                                             rb, sweep, touch, incidence, touching, touch_normal)
                if status == 0:
                    continue
                if any_support and not rb.movable and len(found):
                    found = found.select(~supported[found.node])
                if len(found):
                    parts.append(found)
                with_edges = edges is not None and (movable_edges or not rb.movable) and _edge_parts(rb)
                gap = node_gaps(found, len(positions)) if status == 2 or with_edges else None
                if status == 2:  # face contacts possible: the numpy search decides
                    if boxes is None:
                        boxes = triangle_boxes(positions, triangles)
                    faces.append(self.face_contacts(body_index, positions, triangles, rb, margin, touching,
                                                    touch_normal, boxes, sweep, possible=True, node_gap=gap))
                if with_edges:
                    faces.append(edge_contacts(body_index, positions, triangles, edges, rb, sweep, gap))
                continue
            if lo0 is None:
                lo0, hi0 = box_of(positions.take(surface, axis=0))
            margin = sweep.bound(surface)
            rlo, rhi = rb.aabb()
            if np.any(rlo > hi0 + margin) or np.any(rhi < lo0 - margin):
                continue  # broad phase: far apart, no query at all
            found = self.node_contacts(body_index, positions, surface, rb, margin, sweep)
            if any_support and not rb.movable and len(found):
                found = found.select(~supported[found.node])
            if len(found):
                # a rigid face must face the soft surface at the node: a node lying in the plane of a box's bottom,
                # beside its edge, is no contact with the side face beyond (the box slides over it, it does not
                # plough into it); a node inside the link always is
                normals = node_normals(positions, triangles, found.node, incidence)
                facing = np.einsum("ij,ij->i", found.normal, normals) < FACING
                found = found.select(facing | (found.distance <= 0))
                parts.append(found)
            gap = node_gaps(found, len(positions))
            if edges is not None and (movable_edges or not rb.movable):
                if _edge_parts(rb):
                    faces.append(edge_contacts(body_index, positions, triangles, edges, rb, sweep, gap))
                elif len(rb.feature_edges()[0]):  # a link with a mesh part: its sharp edges
                    faces.append(mesh_edge_contacts(body_index, positions, triangles, edges, rb, sweep, gap))
            if not len(rb.round_parts()) and not len(rb.corner_points()[0]):
                continue  # a plane: no face contacts (CollisionDetector.face_contacts)
            if touching is None:
                touching, touch_normal = np.zeros(len(positions), dtype=bool), np.zeros((len(positions), 3))
            touching[:] = False
            touch_normal[:] = 0.0
            resting = found.distance <= touch
            touching[found.node[resting]] = True
            touch_normal[found.node[resting]] = found.normal[resting]
            touching[held] = True
            if kernels.ENABLED and not _face_contacts_possible(positions, triangles, rb, margin, touching, sweep):
                continue  # nothing near (face_contacts would say the same, after the triangles' boxes)
            if boxes is None:
                boxes = triangle_boxes(positions, triangles)
            faces.append(self.face_contacts(body_index, positions, triangles, rb, margin, touching, touch_normal, boxes,
                                            sweep, node_gap=gap))
        found = Contacts.concat(parts)
        if len(parts) == 1 and np.all(found.node[1:] > found.node[:-1]):
            pass  # one link's contacts, one per node and in node order already
        elif len(found):
            order = np.lexsort((found.distance, found.node))  # one contact per node: the deepest
            found = found.select(order[run_starts(found.node[order])])
        return found, FaceHits.concat(faces)

    def _primitive_link(self, body_index: int, positions: np.ndarray, surface: np.ndarray, triangles: np.ndarray,
                        supported: np.ndarray, rigid: RigidLink, sweep: Sweep, touch: float, incidence: sp.csr_matrix,
                        touching: np.ndarray, touch_normal: np.ndarray) -> tuple[int, float, "Contacts"]:
        """:meth:`detect`'s work for one link of primitive parts up to the face search, in one compiled call
        (kernels.primitive_link_contacts): (0 far apart / 1 no face search / 2 face search needed, the reach [m],
        the node contacts); touching and touch_normal filled as detect fills them for the face search."""
        c, q = rigid.pose()
        Rl = quat_matrix(q)
        kinds, sizes, R, pos = rigid.primitive_arrays()
        lo, hi = rigid.aabb()
        smooth = rigid.round_parts()
        corners, corner_centres = rigid.corner_points()
        faces = bool(len(smooth) or len(corners))
        if faces:
            round_kinds, round_sizes, round_R, round_pos = rigid.round_part_arrays((c, Rl))
        else:
            round_kinds, round_sizes, round_R, round_pos = _NO_ROUND
        status, count, margin, node, point, normal, dist = kernels.primitive_link_contacts(
            np.ascontiguousarray(positions, dtype=float), np.asarray(surface, dtype=np.int64),
            np.ascontiguousarray(triangles, dtype=np.int64), incidence.indptr, incidence.indices, supported,
            np.asarray(lo, dtype=float), np.asarray(hi, dtype=float), sweep.margin, sweep.h, RIGID_SLACK, SOFT_SLACK,
            sweep.velocities, sweep.speeds, sweep.v, sweep.w, sweep.centre, sweep.radius, kinds, sizes, Rl @ R,
            c + pos @ Rl.T, FACING, touch, faces, round_kinds, round_sizes, round_R, round_pos, smooth,
            np.ascontiguousarray(corners, dtype=float).reshape(-1, 3),
            np.ascontiguousarray(corner_centres, dtype=float).reshape(-1, 3), touching, touch_normal)
        self.last_candidates += count
        n = len(node)
        return status, margin, Contacts(np.full(n, body_index), node, np.full(n, rigid.id), point, normal, dist,
                                        np.full(n, rigid.link))

    def node_contacts(self, body_index: int, positions: np.ndarray, surface_nodes: np.ndarray,
                      rigid: RigidLink, margin: float, sweep: Sweep | None = None) -> Contacts:
        """Contacts of the given surface nodes (ids into positions (N, 3)) against one rigid body within
        ``margin`` [m] (and, given a ``sweep``, within its reach of the rigid point facing them)."""
        parts = rigid.primitive_parts()
        if parts is not None and sweep is not None and kernels.ENABLED:  # the lines below, node by node
            c, q = rigid.pose()
            Rl = quat_matrix(q)
            kinds, sizes, R, pos = rigid.primitive_arrays()
            lo, hi = rigid.aabb()
            count, node, point, normal, dist = kernels.primitive_node_contacts(
                positions, surface_nodes, np.asarray(lo, dtype=float), np.asarray(hi, dtype=float), margin,
                sweep.margin, sweep.h, RIGID_SLACK, SOFT_SLACK, sweep.velocities, sweep.speeds, sweep.v, sweep.w,
                sweep.centre, sweep.radius, kinds, sizes, Rl @ R, c + pos @ Rl.T)
            self.last_candidates += count
            n = len(node)
            return Contacts(np.full(n, body_index), node, np.full(n, rigid.id), point, normal, dist,
                            np.full(n, rigid.link))
        x = positions.take(surface_nodes, axis=0)
        lo, hi = rigid.aabb()
        inside = np.all((x >= lo - margin) & (x <= hi + margin), axis=1)
        reach = rigid.bounding_radius() + margin
        if sweep is not None:  # and inside the bounding sphere's sweep over the step
            inside &= sweep.swept(x, travel=sweep.soft_travel(surface_nodes))
        elif np.isfinite(reach):  # and inside the shape's bounding sphere (for a sphere: exact)
            c, _ = rigid.pose()
            inside &= np.einsum("ij,ij->i", x - c, x - c) <= reach * reach
        cand = surface_nodes[inside]
        self.last_candidates += len(cand)
        if not len(cand):
            return Contacts.empty()
        if parts is not None:  # primitives: closed-form distances, all candidates at once
            point, normal, dist = primitive_distances(rigid, parts, positions.take(cand, axis=0))
            near = dist < (margin if sweep is None else sweep.reach(point, normal, sweep.velocities[cand]))
            n = int(near.sum())
            return Contacts(np.full(n, body_index), cand[near], np.full(n, rigid.id), point[near], normal[near],
                            dist[near], np.full(n, rigid.link))
        rows = []
        for node, xi in zip(cand.tolist(), positions[cand].tolist()):
            res = p.getClosestPoints(-1, rigid.id, margin, linkIndexB=rigid.link, collisionShapeA=self._probe,
                                     collisionShapePositionA=xi, physicsClientId=self.client)
            if res:
                best = min(res, key=lambda r: r[8])
                rows.append((node, *best[6], *best[7], best[8]))
        if not rows:
            return Contacts.empty()
        a = np.array(rows)
        node = a[:, 0].astype(np.int64)
        point, normal, dist = a[:, 1:4], a[:, 4:7], a[:, 7]
        if rigid.concave:  # triangle soup: pybullet's distance is unsigned, its normal points at the node
            inside_mesh = rigid._trimesh.contains(rigid.to_local(positions[node]))
            normal = np.where(inside_mesh[:, None], -normal, normal)
            dist = np.where(inside_mesh, -dist, dist)
        if sweep is not None:
            near = dist < sweep.reach(point, normal, sweep.velocities[node])
            node, point, normal, dist = node[near], point[near], normal[near], dist[near]
        n = len(node)
        return Contacts(np.full(n, body_index), node, np.full(n, rigid.id), point, normal, dist,
                        np.full(n, rigid.link))

    @staticmethod
    def face_contacts(body_index: int, positions: np.ndarray, triangles: np.ndarray, rigid: RigidLink,
                      margin: float, touching: np.ndarray | None = None,
                      touch_normal: np.ndarray | None = None,
                      boxes: tuple[np.ndarray, np.ndarray] | None = None, sweep: Sweep | None = None,
                      possible: bool = False, node_gap: np.ndarray | None = None) -> "FaceHits":
        """Points of a rigid link inside (or within ``margin`` of) soft surface triangles, between their nodes.

        The candidates are the link's corners (box corners, mesh vertices) and, for every soft triangle
        near the link, the points of its round parts deepest into the triangle's plane (support points
        along the inward normal: a sphere's, and both ends' of a capsule or cylinder). A candidate counts
        if it projects into the triangle (barycentric weights >= 0, and not at a node: see ``at_node``), lies within ``margin`` of the plane on either side, and the triangle is the
        soft surface nearest to it (so a rigid point above a soft body's top face never counts against its
        side faces).

        ``touching`` (N,) bool marks the nodes resting on the link and supports, ``touch_normal`` (N, 3) the
        normals of those node contacts. A triangle whose nodes all rest on one face of the link (one
        normal, facing the triangle) follows the link through their node contacts: a corner on a facet
        lying flat on a box face adds nothing. A smooth part (sphere, capsule) counts only on triangles
        none of whose nodes touches it: with a node on it, the facet's chord under the curved surface is
        the discretisation, not a penetration, and a second constraint on nearly the same spot would only
        make the contact forces ill-determined; and, where the triangle's nodes have contacts with the link
        (``node_gap`` (N,): their gaps [m], inf where a node has none), only deeper than they hold it
        (interpolated at the point, less EDGE_EXPLAINED). Sharp parts (box corners, cylinder rims, mesh vertices)
        count on partly touching triangles too: they poke between nodes that rest on the part's faces; up to
        four of them inside one triangle (a small box on a coarse facet stands on its four corners).
        ``boxes``: the triangles' bounds (triangle_boxes), if already at hand. ``sweep``: a point outside a
        triangle's plane counts only within its reach (what it closes along the normal within the step).
        ``possible``: the compiled early-out (kernels.face_contacts_possible) has said already that contacts may
        be found (not asked again).
        """
        if not len(rigid.round_parts()) and not len(rigid.corner_points()[0]):
            return FaceHits.empty()  # a plane: no point of it lies between the nodes of a triangle outside it
        if kernels.ENABLED and not possible and not _face_contacts_possible(positions, triangles, rigid, margin,
                                                                              touching, sweep):
            return FaceHits.empty()  # most calls: nothing comes near, said by one compiled pass
        if boxes is None:
            boxes = triangle_boxes(positions, triangles)
        tlo, thi = boxes[0] - margin, boxes[1] + margin
        rlo, rhi = rigid.aabb()
        around = np.flatnonzero((thi[:, 0] >= rlo[0]) & (thi[:, 1] >= rlo[1]) & (thi[:, 2] >= rlo[2])
                                & (tlo[:, 0] <= rhi[0]) & (tlo[:, 1] <= rhi[1]) & (tlo[:, 2] <= rhi[2]))
        reach = rigid.bounding_radius()
        if len(around) and sweep is not None:  # and whose bounding spheres meet its sweep
            mid = 0.5 * (boxes[0][around] + boxes[1][around])
            half = 0.5 * (boxes[1][around] - boxes[0][around])
            travel = sweep.soft_travel(triangles[around])
            around = around[sweep.swept(mid, np.sqrt(np.einsum("ij,ij->i", half, half)), travel)]
        elif len(around) and np.isfinite(reach):  # and whose bounding spheres meet the link's
            centre, _ = rigid.pose()
            mid = 0.5 * (tlo[around] + thi[around])
            half = 0.5 * (thi[around] - tlo[around])
            gap = np.sqrt(np.einsum("ij,ij->i", mid - centre, mid - centre)) - np.sqrt(np.einsum("ij,ij->i", half, half))
            around = around[gap <= reach]
        if not len(around):
            return FaceHits.empty()
        tri_nodes = triangles[around]
        xt = positions.take(tri_nodes, axis=0)  # (T, 3, 3), the triangles around the link
        tlo, thi = tlo[around], thi[around]
        tri_touch = None if touching is None else touching[tri_nodes]  # (T, 3)
        # round parts: on triangles none of whose nodes touches the link, one support point each
        round_tris = np.arange(len(around))
        if tri_touch is not None:
            round_tris = round_tris[~tri_touch.any(axis=1)] if rigid.round_parts().all() else round_tris
        # corners: each against the triangles whose boxes hold it, not on facets lying flat on a face
        corners, corner_centres = rigid.corner_points()
        if len(corners):  # only those near the soft surface at all
            near_body = np.all((corners >= tlo.min(axis=0)) & (corners <= thi.max(axis=0)), axis=1)
            corner_ids = np.flatnonzero(near_body)
            corners, corner_centres = corners[corner_ids], corner_centres[corner_ids]
        vi = vt = np.zeros(0, dtype=np.int64)
        if len(corners):
            inside = np.all((corners[:, None] >= tlo[None]) & (corners[:, None] <= thi[None]), axis=2)
            vi, vt = np.nonzero(inside)
        in_play = np.zeros(len(around), dtype=bool)  # the triangles (indices into around) in play
        in_play[round_tris] = True
        in_play[vt] = True
        used = np.flatnonzero(in_play)
        if not len(used):
            return FaceHits.empty()
        a, b, c = (np.zeros((len(around), 3)) for _ in range(3))
        nrm, area2 = np.zeros((len(around), 3)), np.ones(len(around))
        a[used], b[used], c[used] = xt[used, 0], xt[used, 1], xt[used, 2]
        cr = cross(b[used] - a[used], c[used] - a[used])
        area2[used] = np.sqrt(np.einsum("ij,ij->i", cr, cr))
        nrm[used] = cr / area2[used, None]
        if len(vt) and tri_touch is not None:  # facets lying flat on a face of the link
            flat = tri_touch[vt].all(axis=1)
            if touch_normal is not None:
                facing = np.einsum("tki,ti->tk", touch_normal[triangles[around[vt]]], -nrm[vt])
                flat &= (facing > 1.0 - 1e-6).all(axis=1)
            vi, vt = vi[~flat], vt[~flat]
        S = len(rigid.round_parts())
        if S and len(round_tris):
            pts = rigid.support_points(-nrm[round_tris])  # (T, S, 3)
            keep = np.ones((len(round_tris), S), dtype=bool)
            if tri_touch is not None:  # a smooth part reaches between nodes only where none touches it
                keep &= ~rigid.round_parts()[None] | ~tri_touch[round_tris].any(axis=1)[:, None]
            centres = rigid.support_centres()
            if kernels.ENABLED:  # most support points drop out of the tests below: a compiled prefilter first
                swept = sweep is not None
                kernels.round_face_prefilter(
                    a, b, c, nrm, area2, round_tris, pts, centres, keep, margin, swept, sweep.h if swept else 0.0,
                    RIGID_SLACK, SOFT_SLACK, tri_nodes, sweep.velocities if swept else _NO_ROWS,
                    *((sweep.v, sweep.w, sweep.centre) if swept else (_ZERO3, _ZERO3, _ZERO3)))
            else:  # only support points within the margin of their triangle's plane go on (most do not)
                keep &= np.abs(np.einsum("tsi,ti->ts", pts - a[round_tris, None], nrm[round_tris])) < margin
            tk, sk = np.nonzero(keep)
            ti, q = round_tris[tk], pts[tk, sk]
            feature = sk  # which part or corner, the same from step to step
            centre = centres[sk]
        else:
            ti, q, feature = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)
            centre = np.zeros((0, 3))
        if not len(ti) and not len(vi):
            return FaceHits.empty()
        centre = np.concatenate([centre, corner_centres[vi]])
        corner_q = corners[vi]
        if len(vi) and rigid.primitive_parts() is None:  # a mesh's corner: where pybullet's surface lies (its margin)
            corner_q = corner_q - rigid.corner_rounding()[corner_ids[vi], None] * nrm[vt]
        ti, q = np.concatenate([ti, vt]), np.concatenate([q, corner_q])
        # which rigid point: a corner is one (numbered after the round parts' points, below), a round part's point
        # is named by its position once the candidates are few (round entries -1 until then)
        group = np.concatenate([np.full(len(feature), -1), len(round_tris) * S + vi])
        feature = np.concatenate([feature, S + (corner_ids[vi] if len(vi) else vi)])
        # the part must lie on the outer side of the triangle's plane: a box on a soft block's top face
        # never presses on its side faces through the edge they share (a concave mesh's vertices: no test)
        outer = np.einsum("ij,ij->i", centre - a[ti], nrm[ti])
        ok = np.isnan(outer) | (outer > 0)
        ti, q, group, feature = ti[ok], q[ok], group[ok], feature[ok]
        if not len(ti):
            return FaceHits.empty()
        d = np.einsum("ij,ij->i", q - a[ti], nrm[ti])  # > 0 outside the soft body (outward triangles)
        near_plane = np.abs(d) < margin
        if sweep is not None and near_plane.any():  # the triangle's velocity: its nodes' mean
            at = np.flatnonzero(near_plane)
            near_plane[at] = d[at] < sweep.reach(q[at], -nrm[ti[at]],
                                                 sweep.velocities[triangles[around[ti[at]]]].mean(axis=1))
        ti, q, d, group, feature = ti[near_plane], q[near_plane], d[near_plane], group[near_plane], feature[near_plane]
        A, B, C, n = a[ti], b[ti], c[ti], nrm[ti]
        proj = q - d[:, None] * n
        bary = barycentric(proj, A, B, C, n * area2[ti, None])
        # a lower bound of each point's distance to its triangle, from its distance d to the plane and, beside the
        # triangle, to the line of the edge it lies beyond (-w times that edge's altitude, area2 / edge length):
        # points it puts beyond the margin need no closest point (most of them, over a curved surface)
        edge = np.sqrt(np.stack([np.einsum("ij,ij->i", C - B, C - B), np.einsum("ij,ij->i", A - C, A - C),
                                 np.einsum("ij,ij->i", B - A, B - A)], axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            beside = (np.maximum(-bary, 0.0) * (area2[ti, None] / edge)).max(axis=1)
            maybe = ~(d * d + beside * beside >= margin * margin)  # NaN (a degenerate triangle) stays in
        if node_gap is not None:  # a round part's point only where deeper than the nodes' contacts hold it
            held = held_gap(bary, node_gap[tri_nodes[ti]])
            maybe &= (group >= 0) | (d < held - EDGE_EXPLAINED)
        if not maybe.any():
            return FaceHits.empty()
        if not maybe.all():
            ti, q, d, group, feature, A, B, C, n, bary = (ti[maybe], q[maybe], d[maybe], group[maybe], feature[maybe],
                                                          A[maybe], B[maybe], C[maybe], n[maybe], bary[maybe])
        round_pt = group < 0
        if round_pt.any():
            # the rigid point's identity: triangles in one plane share their support point (a sphere over a flat
            # sheet), which must be one rigid point, so that it takes one of them (two contacts on one spot make
            # the contact forces ill-determined: the friction problem is singular, and its solution gained energy)
            group[round_pt] = row_groups(np.column_stack([feature[round_pt],
                                                          np.round(q[round_pt] / (1e-9 + 1e-6 * margin))]))
        if kernels.ENABLED:  # the same closest points, row by row (integration.kernels)
            closest = np.empty(q.shape)
            kernels.closest_points(*(np.ascontiguousarray(v, dtype=float) for v in (q, A, B, C)), closest)
        else:
            closest = closest_on_triangles(q, A, B, C)
        reach = np.linalg.norm(q - closest, axis=1)
        inside = (bary >= -1e-9).all(axis=1)
        ok = (reach < margin) & ~(inside & self_at_node(bary, ti, tri_touch))
        if not ok.any():
            return FaceHits.empty()
        ti, q, d, bary, group, inside, closest, feature = (ti[ok], q[ok], d[ok], bary[ok], group[ok], inside[ok],
                                                           closest[ok], feature[ok])
        # per triangle, the four deepest points inside it (a box's face on a coarse facet: its corners) and the
        # deepest outside only: a flat rigid face over a triangle (many mesh vertices at one depth) is a few
        # contacts, not one per vertex
        order = np.lexsort((d, ~inside, ti))
        starts = run_starts(ti[order], inside[order])
        run = np.cumsum(starts) - 1
        rank = np.arange(len(order)) - np.flatnonzero(starts)[run]
        keep = np.zeros(len(ti), dtype=bool)
        keep[order] = rank < np.where(inside[order], CORNERS_PER_FACET, 1)
        ti, q, d, bary, group, inside, closest, feature = (ti[keep], q[keep], d[keep], bary[keep], group[keep],
                                                           inside[keep], closest[keep], feature[keep])
        # a point inside a triangle counts there (primary) only if that triangle is the soft surface nearest to
        # it (of all triangles around the link); one such triangle per rigid point
        primary = inside.copy()
        if primary.any():
            qi = q[primary]
            if kernels.ENABLED:  # the same distances, point by point (integration.kernels)
                dist = np.empty(len(qi))
                kernels.nearest_triangle_distances(np.ascontiguousarray(qi, dtype=float),
                                                   np.ascontiguousarray(xt, dtype=float), dist)
            else:
                nearest = closest_on_triangles(qi[:, None], xt[None, :, 0], xt[None, :, 1], xt[None, :, 2])
                dist = np.sqrt(((nearest - qi[:, None]) ** 2).sum(axis=2)).min(axis=1)
            primary[primary] = np.abs(d[primary]) <= dist + 1e-9
        order = np.lexsort((~primary, group))
        first = run_starts(group[order])
        primary[order[~first]] = False
        # neighbours: triangles the point is not on now but may cross into (or come nearest to) within the
        # step; their weights are those of the triangle's point nearest to the rigid point
        out = ~primary
        if out.any():
            bary[out] = barycentric(closest[out], a[ti[out]], b[ti[out]], c[ti[out]])
            # a neighbour whose nearest point is (almost) one of its nodes is that node's contact
            at_node = out & self_at_node(bary, ti, tri_touch)
            if at_node.any():
                keep = ~at_node
                ti, q, d, bary, group, primary, feature = (ti[keep], q[keep], d[keep], bary[keep], group[keep],
                                                           primary[keep], feature[keep])
        tri = around[ti]
        m = len(tri)
        # a key that names the same contact in the next step: triangle, feature, rigid link
        key = (tri.astype(np.int64) << 28) | ((feature % 4096) << 16) | ((rigid.id * 64 + rigid.link + 1) & 0xFFFF)
        return FaceHits(np.full(m, body_index), tri, triangles[tri], bary, q, -nrm[ti], d, np.full(m, rigid.id),
                        np.full(m, rigid.link), group, primary, key)


def _edge_parts(rigid: RigidLink) -> list:
    """The link's parts (index, Part) a soft edge can meet between its nodes (RigidShape.between_nodes); none for a
    link with a mesh part. Made once per link."""
    if "_edge_parts" not in rigid.__dict__:
        rigid._edge_parts = ([] if rigid.primitive_parts() is None else
                             [(k, part) for k, part in enumerate(rigid.parts) if part.shape.between_nodes])
    return rigid._edge_parts


def _edge_part_frames(rigid: RigidLink, parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rotations (P, 3, 3), origins (P, 3) in the link's frame and half extents (P, 3) of the link's ``parts``
    (_edge_parts), made once per link."""
    if "_edge_part_frames" not in rigid.__dict__:
        rigid._edge_part_frames = (np.array([R for _, (_, R, _) in parts]), np.array([p for _, (_, _, p) in parts]),
                                   np.array([s.extent() for _, (s, _, _) in parts]))
    return rigid._edge_part_frames


def node_gaps(found: Contacts, n_nodes: int) -> np.ndarray:
    """(N,) the gaps [m] the node contacts ``found`` (of one link) hold, inf at nodes without one."""
    gap = np.full(n_nodes, np.inf)
    gap[found.node] = found.distance
    return gap


def held_gap(weights: np.ndarray, gaps: np.ndarray) -> np.ndarray:
    """(m,) the gap the nodes' contacts hold at points with weights (m, k) over nodes with gaps (m, k) (inf:
    no contact): the weights clipped to the element and interpolated (inf if a node with weight has none)."""
    w = np.clip(weights, 0.0, None)
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    with np.errstate(invalid="ignore"):  # 0 * inf where a node without a contact has no weight
        return np.where(w > 0, w * gaps, 0.0).sum(axis=1)


def edge_contacts(body_index: int, positions: np.ndarray, triangles: np.ndarray,
                  edges: tuple[np.ndarray, np.ndarray], rigid: RigidLink, sweep: Sweep, node_gap: np.ndarray
                  ) -> "FaceHits":
    """Points of soft surface edges deepest into a link's boxes, capsules and cylinders, between their nodes: where a
    box's edge or side, a capsule or a cylinder lies across an edge whose nodes are outside it (a bar across a thin
    box, a plate on a rail) (RigidShape.between_nodes: no planes, no spheres).

    ``edges``: the surface's edges (E, 2) and the triangles each bounds (E, 2); ``node_gap`` (N,): the gaps [m] the
    link's node contacts hold (inf where none). For every edge near a part (their boxes in the part's frame, not
    where the distance is linear along it: RigidShape.linear_between), the point of least signed distance (convex
    along the edge: golden-section search; on a flat stretch, such as under a box's face, the one farthest below
    the chord of the ends' distances) counts if it lies between the ends (EDGE_END), within reach (margin plus
    closing within the step), the part faces the edge (its normal against the edge's outward normal, FACING; inside
    it too) and, for an immovable link, it lies nearer to the part than either end and than the ends' node
    contacts hold it (interpolated), by EDGE_EXPLAINED (a box lying on a soft face with an edge past its rim adds
    nothing until the rim digs in). A link the coupled solve moves gets the row whenever it is within reach: the
    convex solve shares the load between rows beside rows, and a row that came only once the rim dug in, and went
    once it held, made a 2 kg box on a soft block rock and the scene gain 1e-3 of its energy in a step. Each is a
    face hit with weights (1 - t, t, 0) over the edge's nodes and the third of a triangle it bounds, its own rigid
    point (group), primary, ``edge`` set."""
    parts = _edge_parts(rigid)
    if not parts or not len(edges[0]):
        return FaceHits.empty()
    E, edge_tris = edges
    x0, x1 = positions.take(E[:, 0], axis=0), positions.take(E[:, 1], axis=0)
    lo, hi = rigid.aabb()
    bound = sweep.bound()
    cand = np.flatnonzero(((np.maximum(x0, x1) >= lo - bound) & (np.minimum(x0, x1) <= hi + bound)).all(axis=1))
    if len(cand) and math.isfinite(sweep.radius):
        mid, half = 0.5 * (x0[cand] + x1[cand]), 0.5 * np.linalg.norm(x1[cand] - x0[cand], axis=1)
        cand = cand[sweep.swept(mid, half, sweep.soft_travel(E[cand]))]
    if not len(cand):
        return FaceHits.empty()
    a, b = x0[cand], x1[cand]
    c, q = rigid.pose()
    Rl = quat_matrix(q)
    # the parts an edge's box may meet, all parts at once (their frames' boxes grown by the reach and a hair, so that
    # this only skips what the test part by part below would: a tray's walls are far from most edges inside it)
    Rs, origins, extents = _edge_part_frames(rigid, parts)
    grown = extents + bound + 1e-9 * (1.0 + np.abs(extents + bound))
    W, O = Rl @ Rs, (c + origins @ Rl.T)[:, None, :]  # (P, 3, 3), (P, 1, 3): the parts' frames in the world
    ends_a, ends_b = (a - O) @ W, (b - O) @ W  # (P, m, 3): the edges in each part's frame
    meets = ((np.maximum(ends_a, ends_b) >= -grown[:, None])
             & (np.minimum(ends_a, ends_b) <= grown[:, None])).all(axis=2).any(axis=1)
    out = []
    for (k, (shape, R, pos)), meet in zip(parts, meets.tolist()):
        if not meet:
            continue
        Rw, origin = Rl @ R, c + Rl @ pos
        la, lb = (a - origin) @ Rw, (b - origin) @ Rw  # the edges in the part's frame
        # only edges whose box in the part's frame meets the part's, grown by the reach (a tray's wall is no
        # candidate for the edges of everything inside the tray), and not those along which the distance is
        # linear (a soft face lying on a box's face): deepest at an end, no point between
        ext = shape.extent() + bound
        near = ((np.maximum(la, lb) >= -ext) & (np.minimum(la, lb) <= ext)).all(axis=1)
        near[near] = ~shape.linear_between(la[near], lb[near])
        if not near.any():
            continue
        la, lb, e_near = la[near], lb[near], cand[near]
        d_a, d_b = shape.distance(la)[2], shape.distance(lb)[2]

        def f(t):  # the distance, ties (a flat stretch) going to the point farthest below the ends' chord
            return shape.distance(la + t[:, None] * (lb - la))[2] - TIE * ((1 - t) * d_a + t * d_b)

        t = _golden(f, len(e_near))
        closest, normal, d = shape.distance(la + t[:, None] * (lb - la))
        which = np.zeros(len(e_near), np.int64)
        spanned = np.zeros(len(e_near), dtype=bool)  # rows at a face's rims (face_span)
        outward = edge_normals(positions, triangles, edge_tris[e_near]) @ Rw  # the edges' outward normals, part frame
        span = shape.face_span(la, lb, la + t[:, None] * (lb - la), outward)
        if span is not None:  # across a flat face: rows at both its rims, held by the face's plane
            (lo_t, hi_t), face_n, offset = span[0].T, span[1], span[2]
            across = np.flatnonzero(np.isfinite(lo_t) & (hi_t - lo_t > 2 * EDGE_END))
            if len(across):
                keep = np.setdiff1d(np.arange(len(t)), across)
                t2 = np.concatenate([lo_t[across], hi_t[across]])
                idx = np.concatenate([across, across])
                pts = la[idx] + t2[:, None] * (lb[idx] - la[idx])
                d2 = np.einsum("ij,ij->i", pts, face_n[idx]) - offset[idx]
                t = np.concatenate([t[keep], t2])
                d = np.concatenate([d[keep], d2])
                normal = np.concatenate([normal[keep], face_n[idx]])
                closest = np.concatenate([closest[keep], pts - d2[:, None] * face_n[idx]])
                which = np.concatenate([which[keep], np.zeros(len(across), np.int64), np.ones(len(across), np.int64)])
                spanned = np.concatenate([spanned[keep], np.ones(2 * len(across), dtype=bool)])
                e_near, la, lb, d_a, d_b = (np.concatenate([v[keep], v[idx]]) for v in (e_near, la, lb, d_a, d_b))
        held = held_gap(np.column_stack([1 - t, t]), node_gap[E[e_near]])
        # the part lies between the nodes: the point nearer to it than either end, and than the ends' contacts hold
        # (a movable link: always, see above; the convex solve takes rows beside rows)
        ok = (t > EDGE_END) & (t < 1 - EDGE_END)
        # a face's rim at a node that the node's own contact does not hold against that face (a node on the line of
        # a box's rim, held by the side beside it, while the face has pushed the node's neighbours on: the surface
        # between them lies inside the box): the rim row, deeper than the node's contacts hold it
        ok |= spanned & (d < held - EDGE_EXPLAINED)
        if not rigid.movable:
            ok &= d < np.minimum(np.minimum(d_a, d_b), held) - EDGE_EXPLAINED
        if not ok.any():
            continue
        e, t, d, which = e_near[ok], t[ok], d[ok], which[ok]
        point, normal = closest[ok] @ Rw.T + origin, normal[ok] @ Rw.T
        v_soft = (1 - t)[:, None] * sweep.velocities[E[e, 0]] + t[:, None] * sweep.velocities[E[e, 1]]
        near = d < sweep.reach(point, normal, v_soft)
        facing = np.einsum("ij,ij->i", normal, edge_normals(positions, triangles, edge_tris[e])) < FACING
        ok = near & facing  # inside, too: near a rim the nearest face may be a side, which would push it sideways
        if ok.any():
            out.append((k, e[ok], t[ok], d[ok], point[ok], normal[ok], which[ok]))
    if not out:
        return FaceHits.empty()
    part = np.concatenate([np.full(len(o[1]), o[0]) for o in out])
    e, t, d, point, normal, which = (np.concatenate([o[i] for o in out]) for i in range(1, 7))
    m = len(e)
    tri = triangles[edge_tris[e, 0]]  # the edge's nodes first, the triangle's third node (weight 0) last
    third = np.where((tri != E[e, 0:1]) & (tri != E[e, 1:2]), tri, -1).max(axis=1)
    nodes = np.column_stack([E[e, 0], E[e, 1], third])
    key = ((1 << 62) | (which << 61) | (e.astype(np.int64) << 28) | ((part % 4096) << 16)
           | ((rigid.id * 64 + rigid.link + 1) & 0xFFFF)).astype(np.int64)
    return FaceHits(np.full(m, body_index), edge_tris[e, 0], nodes, np.column_stack([1 - t, t, np.zeros(m)]), point,
                    normal, d, np.full(m, rigid.id), np.full(m, rigid.link), np.arange(m), np.ones(m, dtype=bool), key,
                    np.ones(m, dtype=bool))


def mesh_edge_contacts(body_index: int, positions: np.ndarray, triangles: np.ndarray,
                       edges: tuple[np.ndarray, np.ndarray], rigid: RigidLink, sweep: Sweep, node_gap: np.ndarray
                       ) -> "FaceHits":
    """Points of soft surface edges against the sharp edges of a link's meshes (RigidLink.feature_edges: a URDF's
    convex hulls, a concave mesh's ridges and rim), where the two cross between the ends of both: a robot's finger
    edge pressed across a soft edge, a soft bar across a mesh's ridge. The vertex of one and the faces of the other
    are node and corner contacts; this is the rest of a pair of surfaces' features.

    ``edges``: the soft surface's edges (E, 2) and the triangles each bounds (E, 2); ``node_gap`` (N,): the gaps [m]
    the link's node contacts hold (inf where none). A soft edge and a rigid edge near each other (their boxes grown
    by the reach) give their closest points (segments.closest_between_segments); these count if they lie between
    both edges' ends (EDGE_END on the soft edge, CORNER_END on the rigid one), the edges cross (CROSSING_SINE), the
    normal along their cross product, turned out of the link, lies in the rigid edge's cone of outward normals
    (CONE_SLACK; else a face of the link is nearer, and the soft edge's nodes hold it) and faces the soft edge's
    outward normal (FACING), the soft point is within reach (margin plus closing within the step) and, for an
    immovable link, deeper than the edge's node contacts hold it (interpolated, less EDGE_EXPLAINED). Each is a face
    hit as in edge_contacts: weights (1 - s, s, 0) over the soft edge's nodes and the third of a triangle it bounds,
    the rigid point on pybullet's surface (the edge's point moved out along the normal by the collision margin
    pybullet keeps around a convex mesh, RigidLink.edge_rounding, where the node contacts also find it), its own
    group, primary, ``edge`` set; the key names the soft and the rigid edge."""
    local, middle, cosine = rigid.feature_edges()
    E, edge_tris = edges
    if not len(local) or not len(E):
        return FaceHits.empty()
    x0, x1 = positions.take(E[:, 0], axis=0), positions.take(E[:, 1], axis=0)
    lo, hi = rigid.aabb()
    bound = sweep.bound()
    cand = np.flatnonzero(((np.maximum(x0, x1) >= lo - bound) & (np.minimum(x0, x1) <= hi + bound)).all(axis=1))
    if len(cand) and math.isfinite(sweep.radius):  # and within the link's bounding sphere swept over the step
        mid, half = 0.5 * (x0[cand] + x1[cand]), 0.5 * np.linalg.norm(x1[cand] - x0[cand], axis=1)
        cand = cand[sweep.swept(mid, half, sweep.soft_travel(E[cand]))]
    if not len(cand):
        return FaceHits.empty()
    a, b = x0[cand], x1[cand]
    slo, shi = np.minimum(a, b) - bound, np.maximum(a, b) + bound  # the soft edges' boxes, grown by the reach
    c, q = rigid.pose()
    Rl = quat_matrix(q)
    r0, r1 = local[:, 0] @ Rl.T + c, local[:, 1] @ Rl.T + c
    rlo, rhi = np.minimum(r0, r1), np.maximum(r0, r1)
    near = np.flatnonzero(((rhi >= slo.min(axis=0)) & (rlo <= shi.max(axis=0))).all(axis=1))
    if not len(near):
        return FaceHits.empty()
    # the pairs whose boxes meet: all at once where they are few (a finger's few dozen edges against the soft edges
    # around it), else the pairs of midpoints within reach of each other (a k-d tree) first
    if len(cand) * len(near) <= DENSE_PAIRS:
        i, k = np.nonzero(((rhi[near][None] >= slo[:, None]) & (rlo[near][None] <= shi[:, None])).all(axis=2))
    else:
        sm, rm = 0.5 * (a + b), 0.5 * (r0[near] + r1[near])
        radius = 0.5 * (float(np.linalg.norm(b - a, axis=1).max()) + float(np.linalg.norm(r1 - r0, axis=1)[near].max()))
        found = cKDTree(sm).sparse_distance_matrix(cKDTree(rm), radius + math.sqrt(3.0) * bound,
                                                   output_type="ndarray")
        i, k = found["i"].astype(np.int64), found["j"].astype(np.int64)
        meet = ((rhi[near[k]] >= slo[i]) & (rlo[near[k]] <= shi[i])).all(axis=1)
        i, k = i[meet], k[meet]
    if not len(i):
        return FaceHits.empty()
    j = near[k]
    pa, pb, qa, qb = a[i], b[i], r0[j], r1[j]
    s, t = closest_between_segments(pa, pb, qa, qb)
    ds, dr = pb - pa, qb - qa
    n = cross(ds, dr)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = ((s > EDGE_END) & (s < 1 - EDGE_END) & (t > CORNER_END) & (t < 1 - CORNER_END)
          & (length > CROSSING_SINE * np.sqrt(np.einsum("ij,ij->i", ds, ds) * np.einsum("ij,ij->i", dr, dr))))
    if not ok.any():
        return FaceHits.empty()
    i, j, s, t, ds, dr, n, length = i[ok], j[ok], s[ok], t[ok], ds[ok], dr[ok], n[ok], length[ok]
    e = cand[i]
    n /= length[:, None]
    soft_out = edge_normals(positions, triangles, edge_tris[e])  # the soft edges' outward normals
    mid = middle[j] @ Rl.T
    # out of the link: along the edge's cone; a rim's cone holds both sides of its face, which the soft edge's
    # own outward normal decides
    towards = np.einsum("ij,ij->i", n, mid)
    side = np.where(np.abs(towards) > CONE_SLACK, towards, -np.einsum("ij,ij->i", n, soft_out))
    n *= np.where(side < 0, -1.0, 1.0)[:, None]
    point_s = a[i] + s[:, None] * ds
    round_by = rigid.edge_rounding()[j]  # pybullet's surface lies that far out of the edge (its collision margin)
    point_r = r0[j] + t[:, None] * dr + round_by[:, None] * n
    d = np.einsum("ij,ij->i", n, point_s - point_r)
    v_soft = (1 - s)[:, None] * sweep.velocities[E[e, 0]] + s[:, None] * sweep.velocities[E[e, 1]]
    widened = np.cos(np.minimum(np.arccos(np.clip(cosine[j], -1.0, 1.0)) + CONE_SLACK, math.pi))
    ok = ((np.einsum("ij,ij->i", n, mid) >= widened) & (np.einsum("ij,ij->i", n, soft_out) < FACING)
          & (d < sweep.reach(point_r, n, v_soft)))
    if not rigid.movable:  # an immovable link: only where the edge's nodes do not hold it already
        ok &= d < held_gap(np.column_stack([1 - s, s]), node_gap[E[e]]) - EDGE_EXPLAINED
    # behind the edge: only a soft point inside the edge's convex part (grown by pybullet's margin; a soft edge far
    # behind a finger, across the cube it grips, is no crossing) and by less than the reach
    behind = np.flatnonzero(ok & (d < 0))
    if len(behind):
        ok[behind] = d[behind] > -sweep.bound()
        planes, part = rigid.edge_part_planes(), rigid.edge_part[j[behind]]
        local_s = (point_s[behind] - c) @ Rl
        for k in np.unique(part).tolist():
            if planes[k] is not None:
                at = part == k
                normals, offsets = planes[k]
                ok[behind[at]] &= (local_s[at] @ normals.T - offsets).max(axis=1) < round_by[behind[at]]
    if not ok.any():
        return FaceHits.empty()
    e, j, s, d, point_r, n = e[ok], j[ok], s[ok], d[ok], point_r[ok], n[ok]
    m = len(e)
    tri = triangles[edge_tris[e, 0]]  # the edge's nodes first, the triangle's third node (weight 0) last
    third = np.where((tri != E[e, 0:1]) & (tri != E[e, 1:2]), tri, -1).max(axis=1)
    nodes = np.column_stack([E[e, 0], E[e, 1], third])
    key = ((1 << 62) | (e.astype(np.int64) << 28) | ((j.astype(np.int64) % 4096) << 16)
           | ((rigid.id * 64 + rigid.link + 1) & 0xFFFF)).astype(np.int64)
    return FaceHits(np.full(m, body_index), edge_tris[e, 0], nodes, np.column_stack([1 - s, s, np.zeros(m)]),
                    point_r, n, d, np.full(m, rigid.id), np.full(m, rigid.link), np.arange(m), np.ones(m, dtype=bool),
                    key, np.ones(m, dtype=bool))


def _golden(f, m: int) -> np.ndarray:
    """The minimisers t (m,) in [0, 1] of m convex functions evaluated together, f(t (m,)) -> (m,): golden-section
    search, GOLDEN_STEPS steps."""
    g = 0.5 * (math.sqrt(5.0) - 1.0)
    t_lo, t_hi = np.zeros(m), np.ones(m)
    t1, t2 = t_hi - g, t_lo + g
    f1, f2 = f(t1), f(t2)
    for _ in range(GOLDEN_STEPS):
        left = f1 < f2  # the minimum lies in [t_lo, t2]
        t_hi = np.where(left, t2, t_hi)
        t_lo = np.where(left, t_lo, t1)
        t_new = np.where(left, t_hi - g * (t_hi - t_lo), t_lo + g * (t_hi - t_lo))
        f_new = f(t_new)
        t1, t2, f1, f2 = (np.where(left, t_new, t2), np.where(left, t1, t_new), np.where(left, f_new, f2),
                          np.where(left, f1, f_new))
    return 0.5 * (t_lo + t_hi)


def primitive_distances(rigid: RigidLink, parts: list, x: np.ndarray, pose: tuple | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points, outward normals and signed distances of world points x (m, 3) to a link made of
    primitive parts (RigidLink.primitive_parts), the nearest part for each point, in world coordinates; with
    the link at ``pose`` (centre of mass (3,), quaternion (4,)), default its current one."""
    c, q = rigid.pose() if pose is None else pose
    Rl = quat_matrix(q)
    if kernels.ENABLED:  # the same closed forms point by point (integration.kernels)
        own = parts is rigid.primitive_parts()  # the link's own parts: their arrays are kept with it
        kinds, sizes, R, pos = rigid.primitive_arrays() if own else kernels.part_arrays(parts)
        x = np.ascontiguousarray(x, dtype=float)
        point, normal, dist = np.empty_like(x), np.empty_like(x), np.empty(len(x))
        kernels.primitive_distances(kinds, sizes, Rl @ R, c + pos @ Rl.T, x, point, normal, dist)
        return point, normal, dist
    best = None
    for shape, R, pos in parts:
        Rw = Rl @ R  # part frame -> world
        origin = c + Rl @ pos
        cl, nl, d = shape.distance((x - origin) @ Rw)
        if best is None:
            best = [cl @ Rw.T + origin, nl @ Rw.T, d]
        else:
            closer = d < best[2]
            best[0] = np.where(closer[:, None], cl @ Rw.T + origin, best[0])
            best[1] = np.where(closer[:, None], nl @ Rw.T, best[1])
            best[2] = np.where(closer, d, best[2])
    return best[0], best[1], best[2]


def node_incidence(triangles: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """(N, T) sparse: 1 where node i is a corner of triangle t (triangles (T, 3) over N nodes)."""
    T = len(triangles)
    return sp.csr_matrix((np.ones(3 * T), (np.asarray(triangles).ravel(), np.repeat(np.arange(T), 3))),
                         shape=(n_nodes, T))


def vertex_normals(positions: np.ndarray, triangles: np.ndarray, incidence: sp.spmatrix | None = None
                   ) -> np.ndarray:
    """Area-weighted unit normals (N, 3) of a surface's nodes for positions (N, 3) and outward triangles
    (T, 3) (zero at nodes on no triangle); ``incidence``: their node_incidence, if at hand (a surface's
    fixed topology: the sum over triangles is then one sparse product)."""
    P = positions.take(triangles, axis=0)
    n = cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    if incidence is None:  # one sum over (triangle, corner, component) into node * 3 + component
        slots = (3 * triangles[:, :, None] + np.arange(3)).ravel()
        out = np.bincount(slots, weights=np.broadcast_to(n[:, None, :], (len(n), 3, 3)).ravel(),
                          minlength=3 * len(positions)).reshape(-1, 3)
    else:
        out = incidence @ n
    norm = np.sqrt(np.einsum("ij,ij->i", out, out))[:, None]
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def run_starts(*keys: np.ndarray) -> np.ndarray:
    """(m,) bool: where a run of equal entries starts in sorted keys (m,) each (several: a run of equal tuples),
    True at the first entry and wherever any key differs from the entry before."""
    out = np.empty(len(keys[0]), dtype=bool)
    out[:1] = True
    diff = out[1:]
    np.not_equal(keys[0][1:], keys[0][:-1], out=diff)
    for k in keys[1:]:
        diff |= k[1:] != k[:-1]
    return out


def node_normals(positions: np.ndarray, triangles: np.ndarray, nodes: np.ndarray,
                 incidence: sp.csr_matrix | None = None) -> np.ndarray:
    """vertex_normals at ``nodes`` (m,) only, (m, 3): with the surface's node_incidence at hand, a compiled loop
    over each node's triangles (integration.kernels) instead of the normals of the whole surface."""
    if incidence is None or not kernels.ENABLED:
        return vertex_normals(positions, triangles, incidence)[nodes]
    out = np.empty((len(nodes), 3))
    kernels.node_normals_at(positions, triangles, incidence.indptr, incidence.indices, np.asarray(nodes, np.int64), out)
    return out


def row_groups(rows: np.ndarray) -> np.ndarray:
    """(m,) the index of each row of ``rows`` (m, k) among the distinct rows, in their sorted order (what
    np.unique(rows, axis=0, return_inverse=True) gives, at a fraction of its cost for small m)."""
    if not len(rows):
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort(rows.T[::-1])
    s = rows[order]
    new = run_starts(*s.T)
    group = np.empty(len(rows), dtype=np.int64)
    group[order] = np.cumsum(new) - 1
    return group


def box_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box (lo (3,), hi (3,)) of points (m, 3), m > 0 (reduced along a contiguous axis: numpy's
    reductions over the first axis of an (m, 3) array cost several times more)."""
    xt = np.ascontiguousarray(points.T)
    return xt.min(axis=1), xt.max(axis=1)


def triangle_boxes(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo (T, 3), hi (T, 3)) of triangles (T, 3) over node positions (N, 3)."""
    a, b, c = (positions.take(t, axis=0) for t in triangles.T)  # take: a quarter of indexing's cost on (N, 3)
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                n: np.ndarray | None = None) -> np.ndarray:
    """Barycentric coordinates (m, 3) of points p (m, 3) in the planes of triangles (a, b, c) (m, 3 each);
    n: the triangles' (b - a) x (c - a), if at hand."""
    n = cross(b - a, c - a) if n is None else n
    nn = np.einsum("ij,ij->i", n, n)
    w_a = np.einsum("ij,ij->i", cross(c - b, p - b), n) / nn
    w_b = np.einsum("ij,ij->i", cross(a - c, p - c), n) / nn
    return np.column_stack([w_a, w_b, 1.0 - w_a - w_b])


def self_at_node(weights: np.ndarray, tri: np.ndarray, touch: np.ndarray | None) -> np.ndarray:
    """(m,) whether face points with barycentric ``weights`` (m, 3) on triangles ``tri`` (indices into the
    rows of ``touch`` (T, 3): which of each triangle's nodes rests on the link) are that node's business: at
    a node (a weight above AT_NODE), or close to a node that rests on the link (above NEAR_TOUCHING), whose
    node contact already holds the point; a second contact there would only split the force arbitrarily."""
    top = weights.argmax(axis=1)
    w = weights[np.arange(len(top)), top]
    out = w >= AT_NODE
    if touch is not None:
        out |= (w >= NEAR_TOUCHING) & touch[tri, top]
    return out


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p, all (..., 3) broadcast together (Ericson,
    Real-Time Collision Detection, 5.1.5, by Voronoi regions)."""
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + v[..., None] * ab + w[..., None] * ac  # inside the face
        # edges
        t_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        t_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        t_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    out = np.where(on_bc[..., None], b + t_bc[..., None] * (c - b), out)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(on_ac[..., None], a + t_ac[..., None] * ac, out)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(on_ab[..., None], a + t_ab[..., None] * ab, out)
    # vertices
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return out


@dataclass
class FaceHits:
    """Rigid points on soft triangles (m entries): body (soft body index), triangle (index into the body's
    surface triangles), nodes (m, 3) its nodes, weights (m, 3) barycentric, point (m, 3) the rigid point,
    normal (m, 3) unit, out of the rigid towards the soft body (minus the triangle's outward normal),
    distance (m,) signed (negative: inside the soft body), rigid (m,) and link (m,); group (m,): which
    rigid point (entries of one group are one point against several triangles); primary (m,): the
    point projects into this triangle, the soft surface nearest to it (else a neighbour it may cross
    into within the step, with the weights of the triangle's point nearest to it); key (m,): names the
    same contact (triangle, corner or part, link) from step to step; edge (m,): the point lies on an edge of
    the triangle (weights (1 - t, t, 0) over nodes (i, j, i), see edge_contacts), it holds there whatever the
    triangles around do (None: none does)."""

    body: np.ndarray
    triangle: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    rigid: np.ndarray
    link: np.ndarray
    group: np.ndarray
    primary: np.ndarray
    key: np.ndarray
    edge: np.ndarray | None = None

    def __post_init__(self):
        if self.edge is None:
            self.edge = np.zeros(len(self.triangle), dtype=bool)

    @classmethod
    def empty(cls) -> "FaceHits":
        """No hits (a fresh object over shared read-only empty arrays: made every step for every link)."""
        return cls(*_EMPTY_FACE_FIELDS)

    def __len__(self) -> int:
        return len(self.triangle)

    @classmethod
    def concat(cls, parts: list["FaceHits"]) -> "FaceHits":
        """The hits of several links (or bodies) in one, their groups kept apart."""
        parts = [h for h in parts if len(h)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:  # nothing to join (hits are never changed in place)
            return parts[0]
        offsets = np.cumsum([0] + [int(h.group.max()) + 1 for h in parts[:-1]])
        fields = {f: np.concatenate([getattr(h, f) for h in parts]) for f in cls.__dataclass_fields__}
        fields["group"] = np.concatenate([h.group + o for h, o in zip(parts, offsets)])
        return cls(**fields)
