"""Independent geometry for the contact tests (issue 29): numpy only, plus pybullet's own reports of its bodies.

Nothing here uses the library's contact code. It answers, for closed triangle surfaces (a soft body's
``mesh.surface_triangles()`` at its current ``positions``) and pybullet's rigid shapes:

- ``winding_number``: the generalized winding number of a closed surface at query points (the sum of the
  signed solid angles of its triangles, Van Oosterom and Strackee's formula, over 4 pi): 1 inside, 0 outside
  for outward-facing triangles; ``inside`` thresholds it at 0.5;
- ``surface_distance``: the unsigned distance of points to a triangle surface (closest point on each
  triangle, Ericson's regions), and ``depth_inside``: that distance for the points inside, 0 for the others;
- ``crossing_edges``: which edges of one surface cross triangles of another (segment against triangle);
- ``surface_intersection_depth``: how deep two closed surfaces interpenetrate (nodes inside the other, and
  the deepest sampled point of each crossing edge);
- ``rigid_shapes`` / ``rigid_penetration``: the penetration of a soft surface into a pybullet body (points
  sampled on every surface triangle against the shapes' exact signed distances; the rigid shape's edges,
  corners and surface points inside the soft surface by the winding number). pybullet's own closest-point
  query rounds box edges and corners by its collision margin (a probe 0.1 mm inside a 5 mm box near its edge
  is reported 0.3 mm *outside*), so primitives are measured in closed form here from the shape, pose and
  size pybullet reports (getCollisionShapeData, getBasePositionAndOrientation); meshes (and the cross-check
  ``pybullet_penetration``) use pybullet's query with a tiny sphere probe.
"""
from __future__ import annotations

import math

import numpy as np
import pybullet as p

# ------------------------------------------------------------------------------------------ surfaces


def surface_edges(tris: np.ndarray) -> np.ndarray:
    """The unique edges (E, 2) of triangles (T, 3), each as (smaller, larger) node index."""
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def winding_number(points: np.ndarray, x: np.ndarray, tris: np.ndarray, chunk: int = 2_000_000) -> np.ndarray:
    """Generalized winding number (P,) of the triangle surface (x[tris], outward-facing) at ``points`` (P, 3).

    Each triangle's signed solid angle seen from a point, tan(Omega / 2) = a.(b x c) / (|a||b||c| + (a.b)|c|
    + (a.c)|b| + (b.c)|a|) with a, b, c the corners relative to the point (Van Oosterom and Strackee 1983),
    summed and divided by 4 pi: 1 inside a closed surface, 0 outside, 1/2 on it."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    V = np.asarray(x, dtype=float)[np.asarray(tris)]  # (T, 3, 3)
    out = np.empty(len(points))
    step = max(1, chunk // max(len(V), 1))
    for s in range(0, len(points), step):
        q = points[s:s + step]
        a, b, c = (V[None, :, k, :] - q[:, None, :] for k in range(3))
        la, lb, lc = (np.sqrt((v * v).sum(-1)) for v in (a, b, c))
        det = (a * np.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
        out[s:s + step] = (2.0 * np.arctan2(det, den)).sum(-1) / (4.0 * math.pi)
    return out


def inside(points: np.ndarray, x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Boolean (P,): the points whose winding number with respect to the closed surface exceeds 1/2."""
    return winding_number(points, x, tris) > 0.5


def closest_points_on_triangles(q: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Closest points (..., 3) on triangles (A, B, C) to points q, all broadcast together (Ericson,
    Real-Time Collision Detection, 5.1.5: the Voronoi region of a vertex, an edge or the face)."""
    ab, ac, ap = B - A, C - A, q - A
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = q - B
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = q - C
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_face, w_face = vb / denom, vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    face = A + v_face[..., None] * ab + w_face[..., None] * ac
    out = face
    # the regions, the later overriding (their conditions are exclusive except at degenerate triangles)
    r_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    out = np.where(r_bc[..., None], B + np.nan_to_num(t_bc)[..., None] * (C - B), out)
    r_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(r_ac[..., None], A + np.nan_to_num(t_ac)[..., None] * ac, out)
    r_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(r_ab[..., None], A + np.nan_to_num(t_ab)[..., None] * ab, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], C, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], B, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], A, out)
    return out


def surface_distance(points: np.ndarray, x: np.ndarray, tris: np.ndarray, chunk: int = 1_000_000) -> np.ndarray:
    """Unsigned distance (P,) of points to the triangle surface x[tris]."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    V = np.asarray(x, dtype=float)[np.asarray(tris)]
    out = np.empty(len(points))
    step = max(1, chunk // max(len(V), 1))
    for s in range(0, len(points), step):
        q = points[s:s + step, None, :]
        c = closest_points_on_triangles(q, V[None, :, 0], V[None, :, 1], V[None, :, 2])
        out[s:s + step] = np.sqrt(((c - q) ** 2).sum(-1)).min(axis=1)
    return out


def depth_inside(points: np.ndarray, x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(P,): the distance to the closed surface x[tris] of the points inside it (winding number > 1/2), 0 for
    the points outside."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    out = np.zeros(len(points))
    k = np.flatnonzero(inside(points, x, tris))
    if len(k):
        out[k] = surface_distance(points[k], x, tris)
    return out


def segments_cross_triangles(p0: np.ndarray, p1: np.ndarray, x: np.ndarray, tris: np.ndarray,
                             chunk: int = 2_000_000) -> np.ndarray:
    """Boolean (S,): whether segment p0[s]-p1[s] crosses any triangle of x[tris] (Moeller and Trumbore's
    ray-triangle test with the ray parameter within [0, 1]; touching counts)."""
    p0, p1 = np.atleast_2d(p0).astype(float), np.atleast_2d(p1).astype(float)
    V = np.asarray(x, dtype=float)[np.asarray(tris)]
    e1, e2 = V[:, 1] - V[:, 0], V[:, 2] - V[:, 0]
    out = np.zeros(len(p0), dtype=bool)
    step = max(1, chunk // max(len(V), 1))
    for s in range(0, len(p0), step):
        o = p0[s:s + step, None, :]
        d = (p1 - p0)[s:s + step, None, :]
        h = np.cross(d, e2[None])
        a = (e1[None] * h).sum(-1)
        ok = np.abs(a) > 1e-300
        f = np.where(ok, 1.0 / np.where(ok, a, 1.0), 0.0)
        sv = o - V[None, :, 0]
        u = f * (sv * h).sum(-1)
        qv = np.cross(sv, e1[None])
        v = f * (d * qv).sum(-1)
        t = f * (e2[None] * qv).sum(-1)
        tol = 1e-12
        hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t >= -tol) & (t <= 1 + tol)
        out[s:s + step] = hit.any(axis=1)
    return out


def crossing_edges(xa: np.ndarray, tris_a: np.ndarray, xb: np.ndarray, tris_b: np.ndarray) -> np.ndarray:
    """The edges (E, 2) of surface a (node indices into xa) that cross a triangle of surface b."""
    edges = surface_edges(np.asarray(tris_a))
    lo, hi = xb.min(axis=0), xb.max(axis=0)
    ea, eb = xa[edges[:, 0]], xa[edges[:, 1]]
    near = np.all(np.minimum(ea, eb) <= hi, axis=1) & np.all(np.maximum(ea, eb) >= lo, axis=1)  # bounding boxes
    edges = edges[near]
    if not len(edges):
        return edges
    return edges[segments_cross_triangles(xa[edges[:, 0]], xa[edges[:, 1]], xb, tris_b)]


def _one_way_depth(xa, tris_a, xb, tris_b, samples: int) -> float:
    """Deepest [m] surface a reaches into closed surface b: its nodes inside b, and the points (``samples``
    along each) of its edges crossing b's surface that lie inside b, by their distance to b's surface."""
    nodes = np.unique(np.asarray(tris_a))
    worst = float(depth_inside(xa[nodes], xb, tris_b).max(initial=0.0))
    edges = crossing_edges(xa, tris_a, xb, tris_b)
    if len(edges):
        s = np.linspace(0.0, 1.0, samples)
        pts = (xa[edges[:, 0], None, :] * (1 - s)[None, :, None] + xa[edges[:, 1], None, :] * s[None, :, None])
        worst = max(worst, float(depth_inside(pts.reshape(-1, 3), xb, tris_b).max(initial=0.0)))
    return worst


def surface_intersection_depth(xa: np.ndarray, tris_a: np.ndarray, xb: np.ndarray, tris_b: np.ndarray,
                               samples: int = 21) -> float:
    """The largest depth [m] by which the closed surfaces xa[tris_a] and xb[tris_b] interpenetrate: the
    deepest of a's nodes inside b and b's inside a (their distance to the other's surface), and of the
    points sampled (``samples`` per edge) on a's edges that cross b's surface and lie inside b, and the
    same of b's edges in a. 0 when they are apart (or touch)."""
    xa, xb = np.asarray(xa, dtype=float), np.asarray(xb, dtype=float)
    return max(_one_way_depth(xa, tris_a, xb, tris_b, samples), _one_way_depth(xb, tris_b, xa, tris_a, samples))


def triangle_samples(x: np.ndarray, tris: np.ndarray, level: int = 6) -> np.ndarray:
    """Points (n, 3) on every triangle of x[tris]: the barycentric grid of ``level`` (level 6: the corners,
    5 points on each edge among them the midpoint, and 10 interior points), duplicates between triangles
    removed."""
    ijk = np.array([(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)], dtype=float)
    w = ijk / level  # (S, 3)
    pts = np.einsum("sk,tkd->tsd", w, np.asarray(x, dtype=float)[np.asarray(tris)]).reshape(-1, 3)
    return np.unique(np.round(pts, 12), axis=0)


# ------------------------------------------------------------------------------------------ rigid shapes
def _quat_matrix(q) -> np.ndarray:
    return np.array(p.getMatrixFromQuaternion(list(q))).reshape(3, 3)


class Shape:
    """One collision shape of a pybullet link at its current pose: ``kind`` (box, sphere, capsule, cylinder,
    plane, mesh), its size in metres (box: half extents; sphere: radius; capsule, cylinder: radius and length
    of the axis, along the local z; plane: its normal), position (3,) and rotation R (3, 3) (columns: the
    shape's axes in world coordinates)."""

    def __init__(self, kind: str, size, position, R):
        self.kind, self.size = kind, np.asarray(size, dtype=float)
        self.position, self.R = np.asarray(position, dtype=float), np.asarray(R, dtype=float)

    def local(self, points: np.ndarray) -> np.ndarray:
        return (np.atleast_2d(points) - self.position) @ self.R

    def world(self, local: np.ndarray) -> np.ndarray:
        return local @ self.R.T + self.position

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Exact signed distance (P,) of world points to the shape (negative inside)."""
        q = self.local(points)
        if self.kind == "sphere":
            return np.linalg.norm(q, axis=1) - self.size[0]
        if self.kind == "box":
            d = np.abs(q) - self.size
            return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
        if self.kind == "capsule":
            r, L = self.size
            z = np.clip(q[:, 2], -L / 2, L / 2)
            return np.linalg.norm(q - np.column_stack([0 * z, 0 * z, z]), axis=1) - r
        if self.kind == "cylinder":
            r, L = self.size
            d = np.column_stack([np.hypot(q[:, 0], q[:, 1]) - r, np.abs(q[:, 2]) - L / 2])
            return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
        if self.kind == "plane":
            return q @ self.size
        raise ValueError(f"no closed-form distance for a {self.kind}")

    def surface_samples(self, spacing: float = 1e-3) -> np.ndarray:
        """Points (n, 3) on the shape's surface, in world coordinates, at most about ``spacing`` apart along
        its edges and rims: a box's 12 edges (corners included) and a grid on its faces, a capsule's or
        cylinder's rings (a cylinder's rims and cap discs among them, a capsule's hemispheres), points over a
        sphere. A plane has none (it is infinite)."""
        if self.kind == "plane" or self.kind == "mesh":
            return np.zeros((0, 3))
        if self.kind == "box":
            h = self.size
            pts = []
            for axis in range(3):
                n = max(2, int(math.ceil(2 * h[axis] / spacing)) + 1)
                t = np.linspace(-h[axis], h[axis], n)
                for s1 in (-1, 1):
                    for s2 in (-1, 1):
                        e = np.zeros((n, 3))
                        e[:, axis] = t
                        o = [a for a in range(3) if a != axis]
                        e[:, o[0]], e[:, o[1]] = s1 * h[o[0]], s2 * h[o[1]]
                        pts.append(e)
                o = [a for a in range(3) if a != axis]  # the two faces normal to this axis: a 9 x 9 grid
                u, v = np.meshgrid(np.linspace(-h[o[0]], h[o[0]], 9), np.linspace(-h[o[1]], h[o[1]], 9))
                for s in (-1, 1):
                    f = np.zeros((u.size, 3))
                    f[:, axis], f[:, o[0]], f[:, o[1]] = s * h[axis], u.ravel(), v.ravel()
                    pts.append(f)
            return self.world(np.concatenate(pts))
        if self.kind == "sphere":
            r = self.size[0]
            n = max(200, int(4 * math.pi * r * r / spacing ** 2))
            k = np.arange(n) + 0.5
            phi, theta = np.arccos(1 - 2 * k / n), math.pi * (1 + 5 ** 0.5) * k
            unit = np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])
            return self.world(r * unit)
        r, L = self.size
        n_ang = max(16, int(math.ceil(2 * math.pi * r / spacing)))
        ang = np.linspace(0, 2 * math.pi, n_ang, endpoint=False)
        zs = np.linspace(-L / 2, L / 2, max(2, int(math.ceil(L / spacing)) + 1))
        rings = [np.column_stack([r * np.cos(ang), r * np.sin(ang), np.full(n_ang, z)]) for z in zs]
        if self.kind == "cylinder":
            for rho in np.linspace(0, r, 5)[:-1]:
                for z in (-L / 2, L / 2):
                    rings.append(np.column_stack([rho * np.cos(ang), rho * np.sin(ang), np.full(n_ang, z)]))
        else:
            for lat in np.linspace(0, math.pi / 2, 9)[1:]:
                for sgn in (-1, 1):
                    rings.append(np.column_stack([r * math.cos(lat) * np.cos(ang), r * math.cos(lat) * np.sin(ang),
                                                  np.full(n_ang, sgn * (L / 2 + r * math.sin(lat)))]))
        return self.world(np.concatenate(rings))


_KIND = {p.GEOM_SPHERE: "sphere", p.GEOM_BOX: "box", p.GEOM_CAPSULE: "capsule", p.GEOM_CYLINDER: "cylinder",
         p.GEOM_PLANE: "plane", p.GEOM_MESH: "mesh"}


def rigid_shapes(client: int, body: int, link: int = -1) -> list[Shape]:
    """The collision shapes of pybullet body ``body``'s link at its current pose, as pybullet reports them
    (getCollisionShapeData: sizes and the shape's frame relative to the link's centre-of-mass frame)."""
    if link == -1:
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
    else:
        pos, orn = p.getLinkState(body, link, physicsClientId=client)[:2]
    out = []
    for d in p.getCollisionShapeData(body, link, physicsClientId=client):
        kind, dims, lpos, lorn = _KIND.get(d[2], "mesh"), d[3], d[5], d[6]
        wpos, worn = p.multiplyTransforms(pos, orn, lpos, lorn)
        if kind == "box":
            size = [0.5 * v for v in dims]
        elif kind == "sphere":
            size = [dims[0]]
        elif kind in ("capsule", "cylinder"):
            size = [dims[1], dims[0]]  # pybullet reports (length, radius)
        elif kind == "plane":
            size = list(dims[:3])  # the normal, in the shape's frame
        else:
            size = []
        out.append(Shape(kind, size, wpos, _quat_matrix(worn)))
    return out


def pybullet_point_distances(client: int, body: int, points: np.ndarray, link: int = -1,
                             reach: float = 0.01) -> np.ndarray:
    """pybullet's own signed distance (P,) of points to a body's link (a sphere probe of 1 micrometre, its
    radius added back), +reach where it reports nothing within ``reach``."""
    # (left in the client: pybullet's removeCollisionShape of a shape no body uses only prints a warning)
    probe = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-6, physicsClientId=client)
    out = np.full(len(points), reach)
    for k, q in enumerate(np.asarray(points, dtype=float).tolist()):
        for r in p.getClosestPoints(-1, body, reach, linkIndexB=link, collisionShapeA=probe,
                                    collisionShapePositionA=q, physicsClientId=client):
            out[k] = min(out[k], r[8] + 1e-6)
    return out


def rigid_penetration(client: int, body: int, x: np.ndarray, tris: np.ndarray, link: int = -1,
                      spacing: float = 1e-3, exclude=None) -> float:
    """Deepest [m] the soft surface x[tris] and pybullet body ``body`` (one link) interpenetrate:

    - points sampled on every surface triangle (``triangle_samples``: corners, edge points, 10 interior
      points) inside the rigid shape: their depth (exact signed distance for primitives, pybullet's query
      for meshes);
    - points on the rigid shape (box edges and corners, capsule and cylinder rings and rims, sphere points;
      ``Shape.surface_samples``) inside the soft surface by the winding number: their distance to it.

    exclude: node ids (e.g. fixed ones) whose triangles are left out of the first part."""
    x = np.asarray(x, dtype=float)
    tris = np.asarray(tris)
    own = tris if exclude is None else tris[~np.isin(tris, np.asarray(exclude)).all(axis=1)]
    pts = triangle_samples(x, own)
    worst = 0.0
    for sh in rigid_shapes(client, body, link):
        if sh.kind == "mesh":
            d = pybullet_point_distances(client, body, pts, link)
        else:
            d = sh.signed_distance(pts)
        worst = max(worst, float(-d.min(initial=0.0)))
        samples = sh.surface_samples(spacing)
        if len(samples):
            lo, hi = x.min(axis=0) - 1e-9, x.max(axis=0) + 1e-9
            samples = samples[np.all((samples >= lo) & (samples <= hi), axis=1)]
            if len(samples):
                worst = max(worst, float(depth_inside(samples, x, tris).max(initial=0.0)))
    return worst


def pybullet_penetration(client: int, body: int, x: np.ndarray, tris: np.ndarray, link: int = -1) -> float:
    """The cross-check: deepest [m] of the triangle samples inside the body by pybullet's own query alone
    (rounded box edges and corners: shallower than the closed form there)."""
    d = pybullet_point_distances(client, body, triangle_samples(np.asarray(x, float), np.asarray(tris)), link)
    return float(max(-d.min(initial=0.0), 0.0))


def convex_mesh_vertices(client: int, body: int, link: int = -1) -> np.ndarray:
    """World positions (k, 3) of the vertices pybullet keeps for a link's convex mesh shape (getMeshData, which gives
    them in the link's centre-of-mass frame), at the link's current pose."""
    _, vertices = p.getMeshData(body, link, physicsClientId=client)
    if link == -1:
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=client)
    else:
        pos, orn = p.getLinkState(body, link, physicsClientId=client)[:2]
    return np.asarray(vertices, dtype=float) @ _quat_matrix(orn).T + np.asarray(pos, dtype=float)


def hull_depth(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(P,): how deep points lie inside the convex hull of ``vertices`` (scipy's Qhull): inside a convex polytope the
    distance to its surface is the least distance to its face planes, exactly; 0 for the points outside."""
    from scipy.spatial import ConvexHull

    eq = ConvexHull(vertices).equations  # unit outward normals and offsets: n . x + c <= 0 inside
    return np.maximum(-(np.atleast_2d(points) @ eq[:, :3].T + eq[:, 3]).max(axis=1), 0.0)


def hull_edge_samples(vertices: np.ndarray, spacing: float = 1e-3) -> np.ndarray:
    """Points (n, 3) on every edge of the convex hull of ``vertices`` (its triangulated facets' sides, the diagonals of
    a flat facet among them: they lie on the surface too), at most ``spacing`` [m] apart, ends included."""
    from scipy.spatial import ConvexHull

    tri = ConvexHull(vertices).simplices
    edges = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    n = int(max(2, math.ceil(float(np.linalg.norm(b - a, axis=1).max()) / spacing) + 1))
    t = np.linspace(0.0, 1.0, n)[None, :, None]
    return (a[:, None] * (1 - t) + b[:, None] * t).reshape(-1, 3)


def convex_mesh_penetration(client: int, body: int, x: np.ndarray, tris: np.ndarray, link: int = -1) -> float:
    """Deepest [m] a soft surface x[tris] and a link's convex mesh interpenetrate, from the mesh's own vertices
    (pybullet's getMeshData) alone: the surface's triangle samples inside the vertices' convex hull (exact, by its
    face planes) and the hull's edges inside the surface (by the winding number). pybullet's query (in
    ``pybullet_penetration``) measures against the hull grown by its collision margin, ~1 mm."""
    v = convex_mesh_vertices(client, body, link)
    soft_in = float(hull_depth(triangle_samples(x, tris), v).max(initial=0.0))
    edges = hull_edge_samples(v)
    lo, hi = x.min(axis=0) - 1e-9, x.max(axis=0) + 1e-9
    edges = edges[np.all((edges >= lo) & (edges <= hi), axis=1)]
    rigid_in = float(depth_inside(edges, x, tris).max(initial=0.0)) if len(edges) else 0.0
    return max(soft_in, rigid_in)


# ------------------------------------------------------------------------------------------ reference shapes
def box_surface(half_extents, center=(0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (8, 3), outward triangles (12, 3)) of an axis-aligned box."""
    h = np.asarray(half_extents, dtype=float)
    v = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)], dtype=float) * h
    v += np.asarray(center, dtype=float)
    # corners: index = (sx > 0) + 2 (sy > 0) + 4 (sz > 0)
    t = np.array([[0, 2, 3], [0, 3, 1],  # z-
                  [4, 5, 7], [4, 7, 6],  # z+
                  [0, 1, 5], [0, 5, 4],  # y-
                  [2, 6, 7], [2, 7, 3],  # y+
                  [0, 4, 6], [0, 6, 2],  # x-
                  [1, 3, 7], [1, 7, 5]])  # x+
    return v, t
