"""Collision detection between soft-body surface nodes and rigid shapes, through pybullet's queries.

Broad phase in numpy: a soft body's surface AABB against each rigid body's AABB (from pybullet),
then only the surface nodes inside the rigid's AABB and its bounding sphere, both grown by the
margin, become candidates. Narrow
phase: pybullet's ``getClosestPoints`` of a point probe at each candidate against the rigid body,
which gives the closest point, the outward normal and the signed distance (for concave triangle
meshes the sign comes from trimesh's inside test). Sharp rigid features (box corners, mesh
vertices) are also tested against the soft surface triangles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p

from .rigid import RigidLink


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
        z = np.zeros(0, dtype=np.int64)
        return cls(z, z.copy(), z.copy(), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), z.copy())

    def __len__(self) -> int:
        return len(self.node)

    def select(self, mask: np.ndarray) -> "Contacts":
        return Contacts(*(getattr(self, f)[mask] for f in self.FIELDS))

    @classmethod
    def concat(cls, parts: list["Contacts"]) -> "Contacts":
        parts = [c for c in parts if len(c)]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(c, f) for c in parts]) for f in cls.FIELDS))


class CollisionDetector:
    """Finds node contacts of soft bodies against rigid bodies within ``margin`` [m]."""

    def __init__(self, client: int):
        self.client = client
        self._probe = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-6, physicsClientId=client)
        self.last_candidates = 0

    def node_contacts(self, body_index: int, positions: np.ndarray, surface_nodes: np.ndarray,
                      rigid: RigidLink, margin: float) -> Contacts:
        """Contacts of the given surface nodes (ids into positions (N, 3)) against one rigid body."""
        x = positions[surface_nodes]
        lo, hi = rigid.aabb()
        inside = np.all((x >= lo - margin) & (x <= hi + margin), axis=1)
        reach = rigid.bounding_radius() + margin
        if np.isfinite(reach):  # and inside the shape's bounding sphere (for a sphere: exact)
            c, _ = rigid.pose()
            inside &= np.einsum("ij,ij->i", x - c, x - c) <= reach * reach
        cand = surface_nodes[inside]
        self.last_candidates += len(cand)
        if not len(cand):
            return Contacts.empty()
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
        n = len(node)
        return Contacts(np.full(n, body_index), node, np.full(n, rigid.id), point, normal, dist,
                        np.full(n, rigid.link))

    @staticmethod
    def vertex_contacts(body_index: int, positions: np.ndarray, triangles: np.ndarray,
                        rigid: RigidLink, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sharp rigid vertices that touch or penetrate the soft surface.

        Returns (vertex (m, 3), triangle index (m,), barycentric (m, 3), signed distance (m,)) for every
        rigid vertex within ``margin`` of the plane of a soft triangle it projects into, on its inner side
        or less than margin outside.
        """
        verts = rigid.surface_vertices()
        empty = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0))
        if not len(verts) or not len(triangles):
            return empty
        xt = positions[triangles]  # (T, 3, 3)
        lo, hi = xt.min(axis=(0, 1)) - margin, xt.max(axis=(0, 1)) + margin
        verts = verts[np.all((verts >= lo) & (verts <= hi), axis=1)]
        if not len(verts):
            return empty
        tlo, thi = xt.min(axis=1) - margin, xt.max(axis=1) + margin
        near = np.all((verts[:, None] >= tlo[None]) & (verts[:, None] <= thi[None]), axis=2)
        vi, ti = np.nonzero(near)
        if not len(vi):
            return empty
        a, b, c = xt[ti, 0], xt[ti, 1], xt[ti, 2]
        nrm = np.cross(b - a, c - a)
        area2 = np.linalg.norm(nrm, axis=1)
        nrm /= area2[:, None]
        q = verts[vi]
        d = np.einsum("ij,ij->i", q - a, nrm)  # > 0 outside the soft body (outward triangles)
        proj = q - d[:, None] * nrm
        w_a = np.einsum("ij,ij->i", np.cross(c - b, proj - b), nrm) / area2
        w_b = np.einsum("ij,ij->i", np.cross(a - c, proj - c), nrm) / area2
        bary = np.column_stack([w_a, w_b, 1 - w_a - w_b])
        ok = (bary >= -1e-9).all(axis=1) & (d < margin) & (d > -margin)
        return q[ok], ti[ok], bary[ok], d[ok]
