"""After the step: do two closed soft surfaces intersect, and how deep? A geometric check apart from the contact
search (segment against triangle), for what the contact rows could not resolve.

Every edge of one surface is tested against the triangles of the other near it (Moller-Trumbore). Along an edge,
its crossings with the other surface bound the stretches that lie inside it (from an entry to the next exit, or
to an end of the edge); each stretch's depth is measured at a few points (its middle, an end inside, and the point
deepest behind both planes it crosses) as their distance to the nearest triangle of the other surface. The
largest over both surfaces' edges is the intersection's depth: a node inside the other body shows as the end of
its edges, two edges crossing through each other as the stretches of each.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import kernels
from .collision import closest_on_triangles
from .distance import cross


def segment_triangle_crossings(p0: np.ndarray, p1: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Which segments p0-p1 (m, 3) cross triangles (a, b, c) (m, 3 each), and where (the parameter (m,) along the
    segment; NaN where it does not cross)."""
    d = p1 - p0
    e1, e2 = b - a, c - a
    pv = cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / det
        tv = p0 - a
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = cross(tv, e1)
        v = np.einsum("ij,ij->i", d, qv) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        hit = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    return hit, np.where(hit, t, np.nan)


def _edge_depths(xa: np.ndarray, edges_a: np.ndarray, xb: np.ndarray, tris_b: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray) -> float:
    """The deepest [m] any edge (E, 2) of surface a at xa reaches inside the closed surface b (triangles (T, 3)
    outward at xb), edges and triangles within the box lo, hi (3,) only."""
    p0, p1 = xa.take(edges_a[:, 0], axis=0), xa.take(edges_a[:, 1], axis=0)
    sel = ((np.maximum(p0, p1) >= lo) & (np.minimum(p0, p1) <= hi)).all(axis=1)
    P = xb.take(tris_b, axis=0)
    tsel = ((P.max(axis=1) >= lo) & (P.min(axis=1) <= hi)).all(axis=1)
    e, t = np.flatnonzero(sel), np.flatnonzero(tsel)
    if not len(e) or not len(t):
        return 0.0
    p0, p1, P = p0[e], p1[e], P[t]
    if kernels.ENABLED:  # the lines below, edge by edge and triangle by triangle (integration.kernels)
        return kernels.edge_depths(np.ascontiguousarray(p0), np.ascontiguousarray(p1), np.ascontiguousarray(P))
    centre = P.mean(axis=1)
    radius = np.sqrt(((P - centre[:, None]) ** 2).sum(axis=2).max(axis=1))
    mid, half = 0.5 * (p0 + p1), 0.5 * np.sqrt(np.einsum("ij,ij->i", p1 - p0, p1 - p0))
    found = cKDTree(mid).sparse_distance_matrix(cKDTree(centre), half.max() + radius.max(), output_type="ndarray")
    if not len(found):
        return 0.0
    i, j = found["i"].astype(np.int64), found["j"].astype(np.int64)
    close = found["v"] <= half[i] + radius[j]
    i, j = i[close], j[close]
    hit, s = segment_triangle_crossings(p0[i], p1[i], P[j, 0], P[j, 1], P[j, 2])
    i, j, s = i[hit], j[hit], s[hit]
    if not len(i):
        return 0.0
    n = cross(P[j, 1] - P[j, 0], P[j, 2] - P[j, 0])
    n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-300)[:, None]
    rate = -np.einsum("ij,ij->i", p1[i] - p0[i], n)  # how fast the edge goes behind the plane [m per unit s]
    order = np.lexsort((s, i))
    i, s, rate = i[order], s[order], rate[order]
    first = np.ones(len(i), dtype=bool)
    first[1:] = i[1:] != i[:-1]
    last = np.ones(len(i), dtype=bool)
    last[:-1] = i[1:] != i[:-1]
    # the points to measure: of a stretch from an entry (rate > 0) to the next crossing, an exit (rate < 0), its
    # middle and the point deepest behind both planes; of a stretch to an end (the edge's last crossing an entry,
    # or its first an exit) that end and the middle
    pair = ~last & (rate > 0) & (np.roll(rate, -1) < 0)
    k = np.flatnonzero(pair)
    r1, r2 = rate[k], -rate[k + 1]
    wedge = (r1 * s[k] + r2 * s[k + 1]) / np.maximum(r1 + r2, 1e-300)
    end, start = np.flatnonzero(last & (rate > 0)), np.flatnonzero(first & (rate < 0))
    edge = np.concatenate([i[k], i[k], i[end], i[end], i[start], i[start]])
    at = np.concatenate([wedge, 0.5 * (s[k] + s[k + 1]), np.ones(len(end)), 0.5 * (1 + s[end]), np.zeros(len(start)),
                         0.5 * s[start]])
    if not len(edge):
        return 0.0
    q = p0[edge] + at[:, None] * (p1[edge] - p0[edge])
    # their depth: the distance to the nearest triangle of b (they lie inside it)
    near = closest_on_triangles(q[:, None], P[None, :, 0], P[None, :, 1], P[None, :, 2])
    dist = np.sqrt(((near - q[:, None]) ** 2).sum(axis=2)).min(axis=1)
    return float(dist.max())


def intersection_depth(xa: np.ndarray, tris_a: np.ndarray, edges_a: np.ndarray, xb: np.ndarray, tris_b: np.ndarray,
                       edges_b: np.ndarray) -> float:
    """The depth [m] to which two closed soft surfaces (node positions (N, 3), outward triangles (T, 3), edges
    (E, 2) each) intersect (the module's doc), 0 if they do not: only what lies in both boxes is tested."""
    lo = np.maximum(xa.min(axis=0), xb.min(axis=0))
    hi = np.minimum(xa.max(axis=0), xb.max(axis=0))
    if np.any(lo > hi):
        return 0.0
    return max(_edge_depths(xa, edges_a, xb, tris_b, lo, hi), _edge_depths(xb, edges_b, xa, tris_a, lo, hi))
