"""Closed-form signed distances from points to primitive rigid shapes, vectorised over the points.

For a shape in its own frame (a sphere of radius r at the origin; a box of half extents h; a capsule or a
cylinder of radius r and length L along z, centred; a plane through the origin with unit normal n), and
points p (m, 3) in that frame: the closest points on the surface (m, 3), the unit normals out of the shape
towards the points (m, 3), and the signed distances (m,) (negative inside). These are exact; pybullet's
own query (GJK/EPA with collision margins) agrees to round-off on spheres, capsules and planes and to about
a millimetre on boxes and cylinders (tests/test_distance.py), and remains the query for meshes.
"""
from __future__ import annotations

import numpy as np

Result = tuple[np.ndarray, np.ndarray, np.ndarray]  # closest (m, 3), normal (m, 3), distance (m,)


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross products of (..., 3) arrays, broadcast together (np.cross's general machinery costs several
    times more at the sizes of a contact search: tens of rows)."""
    u, v = np.asarray(u, dtype=float), np.asarray(v, dtype=float)
    # component i = u[i+1] v[i+2] - u[i+2] v[i+1] (indices mod 3): four gathers and three products in all
    return u.take(_NEXT, axis=-1) * v.take(_AFTER, axis=-1) - u.take(_AFTER, axis=-1) * v.take(_NEXT, axis=-1)


_NEXT, _AFTER = np.array([1, 2, 0]), np.array([2, 0, 1])


def _unit(v: np.ndarray, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (m, 3) of v (m, 3) and their lengths (m,); ``fallback`` (3,) where a length is zero."""
    norm = np.sqrt(np.einsum("ij,ij->i", v, v))
    safe = norm > 1e-300
    u = np.where(safe[:, None], v / np.where(safe, norm, 1.0)[:, None], fallback)
    return u, norm


def sphere(p: np.ndarray, r: float) -> Result:
    n, norm = _unit(p, np.array([0.0, 0.0, 1.0]))
    return r * n, n, norm - r


def capsule(p: np.ndarray, r: float, length: float) -> Result:
    axis = np.zeros_like(p)
    axis[:, 2] = np.clip(p[:, 2], -0.5 * length, 0.5 * length)
    closest, n, d = sphere(p - axis, r)
    return closest + axis, n, d


def box(p: np.ndarray, half: np.ndarray) -> Result:
    half = np.asarray(half, float)
    q = np.abs(p) - half
    outside = (q > 0).any(axis=1)
    clipped = np.clip(p, -half, half)
    n_out, d_out = _unit(p - clipped, np.array([0.0, 0.0, 1.0]))
    # inside: the nearest face
    k = np.argmax(q, axis=1)
    rows = np.arange(len(p))
    sign = np.where(p[rows, k] >= 0, 1.0, -1.0)
    n_in = np.zeros_like(p)
    n_in[rows, k] = sign
    c_in = p.copy()
    c_in[rows, k] = sign * half[k]
    closest = np.where(outside[:, None], clipped, c_in)
    normal = np.where(outside[:, None], n_out, n_in)
    return closest, normal, np.where(outside, d_out, q[rows, k])


def cylinder(p: np.ndarray, r: float, length: float) -> Result:
    h = 0.5 * length
    radial = p.copy()
    radial[:, 2] = 0.0
    u, rho = _unit(radial, np.array([1.0, 0.0, 0.0]))
    dr, dz = rho - r, np.abs(p[:, 2]) - h
    sz = np.where(p[:, 2] >= 0, 1.0, -1.0)
    ez = np.zeros_like(p)
    ez[:, 2] = sz
    side = np.column_stack([r * u[:, 0], r * u[:, 1], p[:, 2]])  # the nearest point of the side
    cap = np.column_stack([p[:, 0], p[:, 1], sz * h])  # of the cap
    rim = np.column_stack([r * u[:, 0], r * u[:, 1], sz * h])
    # the regions: inside (nearest of side and cap), beside the side, above a cap, beyond the rim
    use_side = np.where((dr <= 0) & (dz <= 0), dr > dz, (dr > 0) & (dz <= 0))
    use_cap = np.where((dr <= 0) & (dz <= 0), dr <= dz, (dr <= 0) & (dz > 0))
    n_rim, d_rim = _unit(p - rim, np.array([0.0, 0.0, 1.0]))
    closest = np.where(use_side[:, None], side, np.where(use_cap[:, None], cap, rim))
    normal = np.where(use_side[:, None], u, np.where(use_cap[:, None], ez, n_rim))
    dist = np.where(use_side, dr, np.where(use_cap, dz, d_rim))
    return closest, normal, dist


def plane(p: np.ndarray, normal: np.ndarray) -> Result:
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    d = p @ n
    return p - d[:, None] * n, np.broadcast_to(n, p.shape).copy(), d


def shape_distance(kind: str, size, p: np.ndarray) -> Result:
    """The distance of the shape class of ``kind`` (integration.shapes: sphere, box, capsule, cylinder, plane)
    of a part's ``size``: (radius,), half extents, (radius, length), or the plane's normal."""
    from .shapes import BY_KIND  # shapes.py builds on this module

    cls = BY_KIND.get(kind)
    if cls is None or not cls.closed_form:
        raise ValueError(f"no closed-form distance for shape {kind!r}")
    return cls.from_size(size).distance(p)
