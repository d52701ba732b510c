"""Edges of triangle surfaces and closest points between segments, vectorised over pairs.

A surface's edges are the sides of its triangles, each once, with the (one or two) triangles it bounds; an
edge's outward normal is the normalised sum of those triangles' unit normals. The closest points between two
segments are Ericson's (Real-Time Collision Detection, 5.1.9), parameter by parameter clamped to the segments.
"""
from __future__ import annotations

import numpy as np

from .distance import cross


def surface_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges of a triangle surface (T, 3): nodes (E, 2) (the smaller node first, sorted) and the triangles
    (E, 2) each bounds (-1 where an open surface's edge bounds one only; a third triangle at a non-manifold edge
    is left out)."""
    triangles = np.asarray(triangles, dtype=np.int64)
    T = len(triangles)
    sides = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    sides.sort(axis=1)
    owner = np.tile(np.arange(T), 3)
    edges, first, inverse = np.unique(sides, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    tris = np.full((len(edges), 2), -1, dtype=np.int64)
    tris[:, 0] = owner[first]
    other = owner != tris[inverse, 0]  # the side's triangle is not the edge's first: its second
    tris[inverse[other], 1] = owner[other]
    return edges.astype(np.int64), tris


def edge_normals(x: np.ndarray, triangles: np.ndarray, edge_tris: np.ndarray) -> np.ndarray:
    """Outward unit normals (E, 3) of edges bounding ``edge_tris`` (E, 2) of outward triangles (T, 3) (-1: none) at
    node positions x (N, 3): the normalised sum of the (one or two) triangles' unit normals, from those triangles
    only."""
    P = x.take(triangles.take(np.maximum(edge_tris, 0), axis=0), axis=0)  # (E, 2, 3, 3)
    n = cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0])
    n /= np.maximum(np.sqrt(np.einsum("eki,eki->ek", n, n)), 1e-300)[:, :, None]
    s = n[:, 0] + np.where(edge_tris[:, 1:] >= 0, n[:, 1], 0.0)
    return s / np.maximum(np.sqrt(np.einsum("ij,ij->i", s, s)), 1e-300)[:, None]


def closest_between_segments(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (s (m,), t (m,)) in [0, 1] of the closest points p0 + s (p1 - p0) and q0 + t (q1 - q0) between
    segments (m, 3 each); for parallel segments one of the closest pairs."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    b = np.einsum("ij,ij->i", d1, d2)
    c = np.einsum("ij,ij->i", d1, r)
    f = np.einsum("ij,ij->i", d2, r)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12 * a * e, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = (b * s + f) / e
        s = np.where(t < 0.0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s))
    return s, np.clip(t, 0.0, 1.0)

