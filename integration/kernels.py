"""Compiled kernels (numba, through softbody.kernels: cached on disk, ``SOFTBODY_NO_NUMBA=1`` turns them off)
for the contact search, where numpy would spread a little arithmetic over dozens of calls or over a whole surface:

- ``face_contacts_possible`` and ``round_face_prefilter``: the tests of face contacts, as a conservative early-out
  for a whole link and a prefilter of candidates in front of the numpy code that decides (collision.py): they only
  skip what that code would drop (their thresholds are wider by a relative 1e-9), so the contacts found are the
  same with them and without them;
- ``primitive_node_contacts`` (and ``primitive_distances``): node contacts against links of primitive parts, the
  closed-form distances of distance.py point by point; ``primitive_link_contacts``: all of the contact search's
  work for such a link before the face search (broad phase, node contacts, facing test, resting nodes, the face
  search's early-out) in one call;
- ``node_normals_at``: surface normals at the nodes in contact only (numpy computes them everywhere);
- ``tangent_frames``, ``contact_start``, ``friction_update``, ``contact_finish``: the contact set's arithmetic in
  the active-set loop (contact.py), contact by contact, bit for bit numpy's;
- ``face_eligible``: which face contacts may carry an impulse after a solve (contact._FaceSet.eligible);
- ``law_slopes``: the convex problem's line search, the contact cost's slopes along a step (convex.py);
- ``triangle_spheres``, ``centre_grid``, ``soft_candidates``, ``first_pass_among``, ``soft_deep_candidates``: the
  soft-soft search's triangle bounds and broad phase (its two passes; the first among candidates kept from an
  earlier step)
  over one uniform grid of all bodies' triangle centres (numpy: a k-d tree per body), node by node;
- ``soft_nearest``: the soft-soft search's narrow phase (softcontact.soft_contacts), candidate pair by pair;
- ``edges_near``, ``edge_candidates``, ``edge_narrow``: the edge search's broad phase, which edges may meet another
  body and which pairs of them (one grid over all midpoints), and its narrow phase, candidate pair by pair
  (softcontact.edge_contacts);
- ``delassus_diagonal``, ``cone_law``, ``scatter_rows``, ``gather_rows``, ``slot_pair_keys``: the convex coupled
  solve's row-by-row arithmetic (convex.py): the rows' Delassus estimates, their contact law, the products of the
  rows' weights with node and row quantities, and the node pairs the rows join.

Each is compared with its numpy reference in tests/test_kernels.py (the soft search's in
tests/test_soft_search.py)."""
from __future__ import annotations

import math
import sys

import numpy as np

from softbody import compilation
from softbody.kernels import AVAILABLE, _inline, _jit

__all__ = ["ENABLED", "centre_grid", "cone_law", "contact_finish", "contact_start", "delassus_diagonal",
           "edge_candidates", "edge_depths", "edge_narrow", "edges_near", "face_contacts_possible", "face_eligible",
           "first_pass_among", "frame_hessians", "friction_update", "gather_rows", "law_slopes", "node_normals_at",
           "part_arrays", "primitive_distances", "primitive_link_contacts", "primitive_node_contacts",
           "round_face_prefilter", "row_velocities", "scatter_rows", "slot_pair_keys", "soft_candidates",
           "soft_deep_candidates", "soft_nearest", "tangent_frames", "triangle_distances", "triangle_spheres"]

#: the prefilter's thresholds are wider than the decisions' by this (relative): round-off never drops a contact
SLACK = 1e-9


@_jit
def _face_point_may_touch(q0: float, q1: float, q2: float, a: tuple, b: tuple, c: tuple, n0: float, n1: float,
                          n2: float, A2: float, k0: float, k1: float, k2: float, margin: float, swept: bool, h: float,
                          rigid_slack: float, soft_slack: float, vs: float, moving: bool, v: np.ndarray, w: np.ndarray,
                          centre: np.ndarray) -> bool:
    """Whether rigid point q may touch a triangle (vertices a, b, c (3-tuples), unit outward normal n, |2 area| A2),
    by the tests of collision.CollisionDetector.face_contacts with thresholds wider by SLACK (False only where that
    code drops the point): within ``margin`` [m] of the plane; its part's centre k not on the inner side; within
    what the two sides close within the step (``swept``: the triangle's mean normal velocity vs, the link's
    velocity v and spin w about ``centre`` if ``moving``; slacks as collision.RIGID_SLACK and SOFT_SLACK); and
    within the margin by the lower bound of its plane distance and its distance to the line of the edge it lies
    beyond. A degenerate triangle (A2 not > 0) may always touch: the numpy code decides."""
    lim = margin * (1.0 + SLACK) + 1e-300
    a0, a1, a2 = a
    d = (q0 - a0) * n0 + (q1 - a1) * n1 + (q2 - a2) * n2
    if not abs(d) < lim:
        return False
    outer = (k0 - a0) * n0 + (k1 - a1) * n1 + (k2 - a2) * n2
    if not (math.isnan(outer) or outer > -SLACK * margin):
        return False
    if swept:  # what the two sides close along -n within the step
        reach = margin + h * soft_slack * max(vs, 0.0)
        if moving:
            r0, r1, r2 = q0 - centre[0], q1 - centre[1], q2 - centre[2]
            p0 = v[0] + w[1] * r2 - w[2] * r1
            p1 = v[1] + w[2] * r0 - w[0] * r2
            p2 = v[2] + w[0] * r1 - w[1] * r0
            reach += h * rigid_slack * max(-(p0 * n0 + p1 * n1 + p2 * n2), 0.0)
        if not d < reach * (1.0 + SLACK) + SLACK * margin:
            return False
    if not A2 > 0.0:
        return True
    # barycentric weights of the projection, and the lower bound beside the triangle
    p0, p1, p2 = q0 - d * n0, q1 - d * n1, q2 - d * n2
    beside = 0.0
    for e in range(3):  # edge e opposite vertex e: from vertex e+1 to e+2
        if e == 0:
            (u0, u1, u2), (o0, o1, o2) = b, c
        elif e == 1:
            (u0, u1, u2), (o0, o1, o2) = c, a
        else:
            (u0, u1, u2), (o0, o1, o2) = a, b
        e0, e1, e2 = o0 - u0, o1 - u1, o2 - u2
        f0, f1, f2 = p0 - u0, p1 - u1, p2 - u2
        # weight of vertex e: ((edge) x (p - start)) . n / area2 (n unit)
        wgt = ((e1 * f2 - e2 * f1) * n0 + (e2 * f0 - e0 * f2) * n1 + (e0 * f1 - e1 * f0) * n2) / A2
        if wgt < 0.0:
            length = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            if length > 0.0:
                beside = max(beside, -wgt * A2 / length)
    return d * d + beside * beside < lim * lim


@_jit
def _is_moving(v: np.ndarray, w: np.ndarray) -> bool:
    return v[0] != 0.0 or v[1] != 0.0 or v[2] != 0.0 or w[0] != 0.0 or w[1] != 0.0 or w[2] != 0.0


@_jit
def round_face_prefilter(a: np.ndarray, b: np.ndarray, c: np.ndarray, nrm: np.ndarray, area2: np.ndarray,
                         tris: np.ndarray, pts: np.ndarray, centres: np.ndarray, keep: np.ndarray, margin: float,
                         swept: bool, h: float, rigid_slack: float, soft_slack: float, nodes: np.ndarray,
                         velocities: np.ndarray, v: np.ndarray, w: np.ndarray, centre: np.ndarray) -> None:
    """Clear keep[t, s] (T, S) where support point pts[t, s] (3,) of round part s cannot touch triangle tris[t]
    (vertices a, b, c (.., 3), unit outward normal nrm, |2 area| area2, indices into these arrays; the triangle's
    velocity the mean of its ``nodes`` (.., 3) rows of ``velocities``): _face_point_may_touch, with the part's
    centre ``centres[s]``."""
    moving = _is_moving(v, w)
    for k in range(tris.shape[0]):
        t = tris[k]
        n0, n1, n2 = nrm[t, 0], nrm[t, 1], nrm[t, 2]
        vs = 0.0
        if swept:
            for j in range(3):
                i = nodes[t, j]
                vs += (velocities[i, 0] * n0 + velocities[i, 1] * n1 + velocities[i, 2] * n2) / 3.0
        va, vb, vc = (a[t, 0], a[t, 1], a[t, 2]), (b[t, 0], b[t, 1], b[t, 2]), (c[t, 0], c[t, 1], c[t, 2])
        for s in range(keep.shape[1]):
            if keep[k, s] and not _face_point_may_touch(
                    pts[k, s, 0], pts[k, s, 1], pts[k, s, 2], va, vb, vc, n0, n1, n2, area2[t], centres[s, 0],
                    centres[s, 1], centres[s, 2], margin, swept, h, rigid_slack, soft_slack, vs, moving, v, w, centre):
                keep[k, s] = False


@_jit
def face_contacts_possible(positions: np.ndarray, triangles: np.ndarray, touching: np.ndarray, lo: np.ndarray,
                           hi: np.ndarray, margin: float, round_kinds: np.ndarray, round_sizes: np.ndarray,
                           round_R: np.ndarray, round_pos: np.ndarray, smooth: np.ndarray, corners: np.ndarray,
                           corner_centres: np.ndarray, swept: bool, h: float, rigid_slack: float, soft_slack: float,
                           velocities: np.ndarray, v: np.ndarray, w: np.ndarray, centre: np.ndarray) -> bool:
    """Whether collision.CollisionDetector.face_contacts may find anything for a link (False only where it finds
    nothing, so that the caller can skip it): some candidate point passes _face_point_may_touch on some surface
    triangle (T, 3) of nodes at ``positions`` (N, 3) whose box, grown by ``margin``, meets the link's box lo, hi
    (3,). Candidates: the support points of the round parts along each triangle's inward normal (round_kinds
    (P,): 0 sphere, 2 capsule, 3 cylinder; round_sizes (P, >= 2) radius and length; round_R (P, 3, 3) and round_pos
    (P, 3) in the world), not on triangles with a ``touching`` (N,) node where the point's part is ``smooth`` (S,)
    (RigidLink.round_parts); and the ``corners`` (K, 3) [with their parts' centres (K, 3)] inside the triangle's
    grown box. Its tests are those of face_contacts (wider by SLACK) less the ones that only ever drop more."""
    moving = _is_moving(v, w)
    grow = margin * (1.0 + SLACK)
    for t in range(triangles.shape[0]):
        ia, ib, ic = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        far = False
        for j in range(3):
            top = max(positions[ia, j], positions[ib, j], positions[ic, j]) + grow
            bottom = min(positions[ia, j], positions[ib, j], positions[ic, j]) - grow
            if top < lo[j] or bottom > hi[j]:
                far = True
        if far:
            continue
        u0, u1, u2 = (positions[ib, 0] - positions[ia, 0], positions[ib, 1] - positions[ia, 1],
                      positions[ib, 2] - positions[ia, 2])
        e0, e1, e2 = (positions[ic, 0] - positions[ia, 0], positions[ic, 1] - positions[ia, 1],
                      positions[ic, 2] - positions[ia, 2])
        c0, c1, c2 = u1 * e2 - u2 * e1, u2 * e0 - u0 * e2, u0 * e1 - u1 * e0
        A2 = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if not A2 > 0.0:
            return True  # degenerate: the numpy code decides
        n0, n1, n2 = c0 / A2, c1 / A2, c2 / A2
        vs = 0.0
        if swept:
            for j in range(3):
                i = triangles[t, j]
                vs += (velocities[i, 0] * n0 + velocities[i, 1] * n1 + velocities[i, 2] * n2) / 3.0
        touched = touching[ia] or touching[ib] or touching[ic]
        va = (positions[ia, 0], positions[ia, 1], positions[ia, 2])
        vb = (positions[ib, 0], positions[ib, 1], positions[ib, 2])
        vc = (positions[ic, 0], positions[ic, 1], positions[ic, 2])
        s = 0
        for p in range(round_kinds.shape[0]):
            kind = round_kinds[p]
            R = round_R[p]
            k0, k1, k2 = round_pos[p, 0], round_pos[p, 1], round_pos[p, 2]
            r, length = round_sizes[p, 0], round_sizes[p, 1]
            for end in range(1 if kind == 0 else 2):
                if smooth[s] and touched:
                    s += 1
                    continue
                d0, d1, d2 = -n0, -n1, -n2  # the support point along the inward normal (RigidLink.support_points)
                if kind == 0 or kind == 2:
                    q0, q1, q2 = k0 + r * d0, k1 + r * d1, k2 + r * d2
                else:  # a cylinder's rim: the direction's part across the axis, scaled to the radius
                    l0 = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
                    l1 = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
                    norm = math.sqrt(l0 * l0 + l1 * l1)
                    f = r / norm if norm > 1e-12 else 0.0
                    q0 = k0 + f * (l0 * R[0, 0] + l1 * R[0, 1])
                    q1 = k1 + f * (l0 * R[1, 0] + l1 * R[1, 1])
                    q2 = k2 + f * (l0 * R[2, 0] + l1 * R[2, 1])
                if kind != 0:
                    z = 0.5 * length if end == 0 else -0.5 * length
                    q0, q1, q2 = q0 + z * R[0, 2], q1 + z * R[1, 2], q2 + z * R[2, 2]
                if _face_point_may_touch(q0, q1, q2, va, vb, vc, n0, n1, n2, A2, k0, k1, k2, margin, swept, h,
                                         rigid_slack, soft_slack, vs, moving, v, w, centre):
                    return True
                s += 1
        for k in range(corners.shape[0]):
            inside = True
            for j in range(3):
                top = max(positions[ia, j], positions[ib, j], positions[ic, j]) + grow
                bottom = min(positions[ia, j], positions[ib, j], positions[ic, j]) - grow
                if corners[k, j] < bottom or corners[k, j] > top:
                    inside = False
            if inside and _face_point_may_touch(corners[k, 0], corners[k, 1], corners[k, 2], va, vb, vc, n0, n1, n2,
                                                A2, corner_centres[k, 0], corner_centres[k, 1], corner_centres[k, 2],
                                                margin, swept, h, rigid_slack, soft_slack, vs, moving, v, w, centre):
                return True
    return False


@_jit
def node_normals_at(positions: np.ndarray, triangles: np.ndarray, indptr: np.ndarray, indices: np.ndarray,
                    nodes: np.ndarray, out: np.ndarray) -> None:
    """Area-weighted unit normals out (m, 3) at ``nodes`` (m,) of a surface: the sum of (b - a) x (c - a) over the
    triangles (T, 3) at each node (its row of the node-triangle incidence, CSR ``indptr``/``indices``), in the
    incidence's order, normalised (zero where it vanishes); positions (N, 3). The rows of
    collision.vertex_normals at those nodes, without the normals of the rest of the surface."""
    for k in range(nodes.shape[0]):
        i = nodes[k]
        s0 = s1 = s2 = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            t = indices[jj]
            ia, ib, ic = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            u0 = positions[ib, 0] - positions[ia, 0]
            u1 = positions[ib, 1] - positions[ia, 1]
            u2 = positions[ib, 2] - positions[ia, 2]
            v0 = positions[ic, 0] - positions[ia, 0]
            v1 = positions[ic, 1] - positions[ia, 1]
            v2 = positions[ic, 2] - positions[ia, 2]
            s0 += u1 * v2 - u2 * v1
            s1 += u2 * v0 - u0 * v2
            s2 += u0 * v1 - u1 * v0
        norm = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        if norm > 0.0:
            out[k, 0], out[k, 1], out[k, 2] = s0 / norm, s1 / norm, s2 / norm
        else:
            out[k, 0] = out[k, 1] = out[k, 2] = 0.0


@_jit
def tangent_frames(normals: np.ndarray, F: np.ndarray) -> None:
    """Orthonormal frames F (m, 3, 3) with the unit normals (m, 3) as first column, t1 = n x e_x (n x e_y where
    n is nearly along x) normalised, t2 = n x t1: contact.tangent_frames's arithmetic, contact by contact."""
    for k in range(normals.shape[0]):
        x, y, z = normals[k, 0], normals[k, 1], normals[k, 2]
        norm = math.sqrt(x * x + y * y + z * z)
        x, y, z = x / norm, y / norm, z / norm
        if abs(x) >= 0.9:
            a, b, c = -z, 0.0, x
        else:
            a, b, c = 0.0, z, -y
        t = math.sqrt(a * a + b * b + c * c)
        a, b, c = a / t, b / t, c / t
        F[k, 0, 0], F[k, 1, 0], F[k, 2, 0] = x, y, z
        F[k, 0, 1], F[k, 1, 1], F[k, 2, 1] = a, b, c
        F[k, 0, 2], F[k, 1, 2], F[k, 2, 2] = y * c - z * b, z * a - x * c, x * b - y * a


@_jit
def friction_update(rl: np.ndarray, vrel: np.ndarray, gap: np.ndarray, h: float, active: np.ndarray,
                    stick: np.ndarray, released: np.ndarray, restuck: np.ndarray, friction: np.ndarray, mu: np.ndarray,
                    slip_force: np.ndarray, eligible: np.ndarray, it: int, lock_after: int, switches: int,
                    last_slip: np.ndarray,
                    velocity_tol: float, cone_tol: float, slip_tol: float, gap_rate: np.ndarray, mag: np.ndarray,
                    d_stick: np.ndarray, new_slip: np.ndarray, want_slip: np.ndarray, want_stick: np.ndarray,
                    new_active: np.ndarray, new_stick: np.ndarray) -> bool:
    """One read of the active-set loop (contact._ContactSet.update, the same rules and arithmetic, contact by
    contact): forces rl (m, 3) [N] and relative velocities vrel (m, 3) in the contact frames, gaps (m,) [m],
    the state active, stick, released, restuck (stopped sliding in this step: it does not slip again in it),
    friction (m,) bool, mu (m,), slip_force (m, 3) and the contacts ``eligible`` to be added; last_slip (1,): the
    sliding forces' change at the last read that changed nothing else (inf: none), in place. Fills gap_rate, mag
    (m,), d_stick, new_slip (m, 2), want_slip, want_stick (m,); ``released`` and ``restuck`` in place; returns
    whether the set changed, and then the new state in new_active, new_stick and slip_force (in place)."""
    m = rl.shape[0]
    switching = it <= switches
    changed = False
    any_cont = False
    top_mag = 0.0
    slip_change = 0.0
    for k in range(m):
        lam = rl[k, 0]
        gap_rate[k] = vrel[k, 0] + gap[k] / h
        release = active[k] and lam < 0 and not (released[k] and it > lock_after)
        add = (not active[k]) and gap_rate[k] < -velocity_tol and eligible[k]
        if release:
            released[k] = True
        if release or add:
            changed = True
        f1, f2 = rl[k, 1], rl[k, 2]
        ftn = math.sqrt(f1 * f1 + f2 * f2)
        lam_pos = max(lam, 0.0)
        want_slip[k] = active[k] and stick[k] and ftn > mu[k] * lam_pos * (1 + cone_tol)
        to_slip = switching and want_slip[k] and not restuck[k]
        v1, v2 = vrel[k, 1], vrel[k, 2]
        vtn = math.sqrt(v1 * v1 + v2 * v2)
        o1, o2 = slip_force[k, 1], slip_force[k, 2]
        reversed_ = v1 * o1 + v2 * o2 > 0
        want_stick[k] = active[k] and not stick[k] and friction[k] and (reversed_ or vtn < velocity_tol)
        to_stick = switching and want_stick[k]
        if to_stick:
            restuck[k] = True
        if ftn > 0:
            d_stick[k, 0], d_stick[k, 1] = f1 / ftn, f2 / ftn
        else:
            d_stick[k, 0] = d_stick[k, 1] = 0.0
        if vtn > 0:
            s1, s2 = -v1 / vtn, -v2 / vtn
        else:
            s1 = s2 = 0.0
        mag[k] = mu[k] * lam_pos
        top_mag = max(top_mag, mag[k])
        n1 = n2 = 0.0
        if to_slip:
            n1, n2 = mag[k] * d_stick[k, 0], mag[k] * d_stick[k, 1]
        cont = active[k] and not stick[k] and friction[k] and not to_stick
        if cont:
            n1, n2 = mag[k] * s1, mag[k] * s2
            any_cont = True
        new_slip[k, 0], new_slip[k, 1] = n1, n2
        slip_change = max(slip_change, abs(n1 - o1), abs(n2 - o2))
        if to_slip or to_stick:
            changed = True
        new_active[k] = (active[k] and not release) or add
        new_stick[k] = (stick[k] and not to_slip) or to_stick
    structural = changed
    if (it <= switches + 1) and slip_change > slip_tol * max(1e-12, top_mag) and any_cont and (
            structural or slip_change < last_slip[0]):
        changed = True
    last_slip[0] = math.inf if structural else slip_change
    if changed:  # the sliding forces of the new state (the loop above left slip_force as it was)
        for k in range(m):
            cont = active[k] and not stick[k] and friction[k] and not (switching and want_stick[k])
            to_slip = switching and want_slip[k] and not restuck[k]
            if new_active[k] and (to_slip or cont):
                slip_force[k, 1], slip_force[k, 2] = new_slip[k, 0], new_slip[k, 1]
            else:
                slip_force[k, 1] = slip_force[k, 2] = 0.0
            if not new_active[k]:
                slip_force[k, 0] = 0.0
    return changed


def part_arrays(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Primitive parts (rigid.Part: shape, rotation, position; RigidLink.primitive_parts) as arrays for
    kernels.primitive_distances: kinds (P,) (RigidShape.code: 0 sphere, 1 box, 2 capsule, 3 cylinder, 4 plane),
    sizes (P, 3) (RigidShape.size: a sphere's radius, a box's half extents, a capsule's or cylinder's radius and
    length, a plane's normal; zero-padded), rotations (P, 3, 3) and positions (P, 3) in the link's frame."""
    sizes = np.zeros((len(parts), 3))
    for i, (shape, _, _) in enumerate(parts):
        sizes[i, :len(shape.size)] = shape.size
    return (np.array([shape.code for shape, _, _ in parts], dtype=np.int64), sizes,
            np.array([R for _, R, _ in parts], dtype=float).reshape(-1, 3, 3),
            np.array([pos for _, _, pos in parts], dtype=float).reshape(-1, 3))


@_jit
def _unit3(x: float, y: float, z: float, fx: float, fy: float, fz: float):
    """(unit vector, length) of (x, y, z); the fallback (fx, fy, fz) where the length is zero (distance._unit)."""
    norm = math.sqrt(x * x + y * y + z * z)
    if norm > 1e-300:
        return x / norm, y / norm, z / norm, norm
    return fx, fy, fz, norm


@_jit
def _shape(kind: int, s0: float, s1: float, s2: float, px: float, py: float, pz: float):
    """Closest point, outward normal and signed distance of point p to a primitive in its own frame (distance.py:
    sphere (s0 = r), box (half extents), capsule and cylinder (s0 = r, s1 = length, along z), plane (normal))."""
    if kind == 0:
        nx, ny, nz, norm = _unit3(px, py, pz, 0.0, 0.0, 1.0)
        return s0 * nx, s0 * ny, s0 * nz, nx, ny, nz, norm - s0
    if kind == 2:
        az = min(max(pz, -0.5 * s1), 0.5 * s1)
        nx, ny, nz, norm = _unit3(px, py, pz - az, 0.0, 0.0, 1.0)
        return s0 * nx, s0 * ny, s0 * nz + az, nx, ny, nz, norm - s0
    if kind == 1:
        qx, qy, qz = abs(px) - s0, abs(py) - s1, abs(pz) - s2
        if qx > 0 or qy > 0 or qz > 0:
            cx, cy, cz = min(max(px, -s0), s0), min(max(py, -s1), s1), min(max(pz, -s2), s2)
            nx, ny, nz, norm = _unit3(px - cx, py - cy, pz - cz, 0.0, 0.0, 1.0)
            return cx, cy, cz, nx, ny, nz, norm
        k = 0  # the nearest face: the first largest q
        if qy > qx:
            k = 1
        if qz > (qy if k == 1 else qx):
            k = 2
        if k == 0:
            sg = 1.0 if px >= 0 else -1.0
            return sg * s0, py, pz, sg, 0.0, 0.0, qx
        if k == 1:
            sg = 1.0 if py >= 0 else -1.0
            return px, sg * s1, pz, 0.0, sg, 0.0, qy
        sg = 1.0 if pz >= 0 else -1.0
        return px, py, sg * s2, 0.0, 0.0, sg, qz
    if kind == 3:
        h = 0.5 * s1
        ux, uy, uz, rho = _unit3(px, py, 0.0, 1.0, 0.0, 0.0)
        dr, dz = rho - s0, abs(pz) - h
        sz = 1.0 if pz >= 0 else -1.0
        if dr <= 0 and dz <= 0:
            use_side, use_cap = dr > dz, dr <= dz
        else:
            use_side, use_cap = dr > 0 and dz <= 0, dr <= 0 and dz > 0
        if use_side:
            return s0 * ux, s0 * uy, pz, ux, uy, uz, dr
        if use_cap:
            return px, py, sz * h, 0.0, 0.0, sz, dz
        rx, ry, rz = s0 * ux, s0 * uy, sz * h
        nx, ny, nz, norm = _unit3(px - rx, py - ry, pz - rz, 0.0, 0.0, 1.0)
        return rx, ry, rz, nx, ny, nz, norm
    # plane through the origin with normal (s0, s1, s2)
    ln = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    nx, ny, nz = s0 / ln, s1 / ln, s2 / ln
    d = px * nx + py * ny + pz * nz
    return px - d * nx, py - d * ny, pz - d * nz, nx, ny, nz, d


@_jit
def _nearest_part(kinds: np.ndarray, sizes: np.ndarray, Rw: np.ndarray, origins: np.ndarray, x0: float, x1: float,
                  x2: float):
    """Closest point (3 floats), outward normal (3) and signed distance of world point x to the nearest of the parts
    (primitive_distances's arguments); the first part wins a tie."""
    bx = by = bz = mx = my = mz = 0.0
    best = np.inf
    for j in range(kinds.shape[0]):
        R = Rw[j]
        rx, ry, rz = x0 - origins[j, 0], x1 - origins[j, 1], x2 - origins[j, 2]
        px = rx * R[0, 0] + ry * R[1, 0] + rz * R[2, 0]  # (x - origin) @ Rw
        py = rx * R[0, 1] + ry * R[1, 1] + rz * R[2, 1]
        pz = rx * R[0, 2] + ry * R[1, 2] + rz * R[2, 2]
        cx, cy, cz, nx, ny, nz, d = _shape(kinds[j], sizes[j, 0], sizes[j, 1], sizes[j, 2], px, py, pz)
        if j == 0 or d < best:
            best = d
            # back to the world: c @ Rw.T + origin, n @ Rw.T
            bx = R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz + origins[j, 0]
            by = R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz + origins[j, 1]
            bz = R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz + origins[j, 2]
            mx = R[0, 0] * nx + R[0, 1] * ny + R[0, 2] * nz
            my = R[1, 0] * nx + R[1, 1] * ny + R[1, 2] * nz
            mz = R[2, 0] * nx + R[2, 1] * ny + R[2, 2] * nz
    return bx, by, bz, mx, my, mz, best


@_jit
def primitive_distances(kinds: np.ndarray, sizes: np.ndarray, Rw: np.ndarray, origins: np.ndarray, x: np.ndarray,
                        point: np.ndarray, normal: np.ndarray, dist: np.ndarray) -> None:
    """collision.primitive_distances point by point: for world points x (m, 3) the closest point, outward normal
    and signed distance on the nearest of P parts (kinds (P,) as RigidShape.code, sizes (P, 3), part-to-world rotations
    Rw (P, 3, 3), origins (P, 3)), into point, normal (m, 3) and dist (m,); the first part wins a tie."""
    for i in range(x.shape[0]):
        (point[i, 0], point[i, 1], point[i, 2], normal[i, 0], normal[i, 1], normal[i, 2],
         dist[i]) = _nearest_part(kinds, sizes, Rw, origins, x[i, 0], x[i, 1], x[i, 2])


@_jit
def primitive_node_contacts(positions: np.ndarray, surface: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                            bound: float, margin: float, h: float, rigid_slack: float, soft_slack: float,
                            velocities: np.ndarray, speeds: np.ndarray, v: np.ndarray, w: np.ndarray,
                            centre: np.ndarray, radius: float, kinds: np.ndarray, sizes: np.ndarray, Rw: np.ndarray,
                            origins: np.ndarray):
    """collision.CollisionDetector.node_contacts for a link of primitive parts and a sweep, node by node: the
    ``surface`` nodes (s,) at ``positions`` (N, 3) inside the link's box lo, hi (3,) grown by ``bound`` [m] and
    inside its bounding sphere (``radius``, about ``centre``) swept over the step (Sweep.swept, the soft nodes'
    travel from their ``speeds`` (N,)); of those, the ones nearer the parts (primitive_distances's arguments) than
    their reach (Sweep.reach: ``margin`` plus what the link's velocity v and spin w and the nodes' ``velocities``
    (N, 3) close within h, with the slacks). Returns (candidates that passed the box and sphere, the contacts'
    nodes (m,), points, normals (m, 3), distances (m,))."""
    s = surface.shape[0]
    travel = 0.0
    for k in range(s):
        travel = max(travel, speeds[surface[k]])
    travel = soft_slack * h * travel
    finite = math.isfinite(radius)
    p0, p1, p2 = rigid_slack * h * v[0], rigid_slack * h * v[1], rigid_slack * h * v[2]
    length2 = p0 * p0 + p1 * p1 + p2 * p2
    reach = radius + rigid_slack * h * math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * radius + margin + travel
    moving = _is_moving(v, w)
    nodes = np.empty(s, dtype=np.int64)
    point, normal, dist = np.empty((s, 3)), np.empty((s, 3)), np.empty(s)
    candidates = m = 0
    for k in range(s):
        i = surface[k]
        x0, x1, x2 = positions[i, 0], positions[i, 1], positions[i, 2]
        if not (x0 >= lo[0] - bound and x1 >= lo[1] - bound and x2 >= lo[2] - bound
                and x0 <= hi[0] + bound and x1 <= hi[1] + bound and x2 <= hi[2] + bound):
            continue
        if finite:
            r0, r1, r2 = x0 - centre[0], x1 - centre[1], x2 - centre[2]
            if length2 != 0.0:
                t = min(max((r0 * p0 + r1 * p1 + r2 * p2) / length2, 0.0), 1.0)
                r0, r1, r2 = r0 - t * p0, r1 - t * p1, r2 - t * p2
            if not r0 * r0 + r1 * r1 + r2 * r2 <= reach * reach:
                continue
        candidates += 1
        cx, cy, cz, nx, ny, nz, d = _nearest_part(kinds, sizes, Rw, origins, x0, x1, x2)
        soft = max(-(velocities[i, 0] * nx + velocities[i, 1] * ny + velocities[i, 2] * nz), 0.0)
        if moving:
            q0, q1, q2 = cx - centre[0], cy - centre[1], cz - centre[2]
            u0 = v[0] + (w[1] * q2 - w[2] * q1)
            u1 = v[1] + (w[2] * q0 - w[0] * q2)
            u2 = v[2] + (w[0] * q1 - w[1] * q0)
            limit = margin + h * (rigid_slack * max(u0 * nx + u1 * ny + u2 * nz, 0.0) + soft_slack * soft)
        else:
            limit = margin + h * (soft_slack * soft)
        if d < limit:
            nodes[m] = i
            point[m, 0], point[m, 1], point[m, 2] = cx, cy, cz
            normal[m, 0], normal[m, 1], normal[m, 2] = nx, ny, nz
            dist[m] = d
            m += 1
    return candidates, nodes[:m], point[:m], normal[:m], dist[:m]


@_jit
def contact_start(frames: np.ndarray, rigid_velocity: np.ndarray, distance: np.ndarray, may_start: np.ndarray,
                  carried: np.ndarray, floor: float, h: float, mu: np.ndarray, was_active: np.ndarray,
                  in_stick: np.ndarray, vr_free: np.ndarray, gap: np.ndarray, target: np.ndarray, active: np.ndarray,
                  friction: np.ndarray, stick: np.ndarray) -> None:
    """The start of an active-set loop (contact._ContactSet.__init__'s arithmetic, contact by contact): from the
    contact frames (m, 3, 3), the rigid points' velocities (m, 3), the distances (m,), ``may_start`` and
    ``carried`` (m,) bool, the deepest penetration undone in one step ``floor`` = -push_speed h [m], friction mu
    (m,) and last step's state (was_active, in_stick (m,) bool), fill: the rigid velocities in the contact frames
    vr_free (m, 3), the gaps (m,) to close, the target velocities (m, 3), and active, friction, stick (m,) bool."""
    for k in range(frames.shape[0]):
        for i in range(3):
            vr_free[k, i] = (frames[k, 0, i] * rigid_velocity[k, 0] + frames[k, 1, i] * rigid_velocity[k, 1]
                             + frames[k, 2, i] * rigid_velocity[k, 2])
        g = distance[k] if may_start[k] else max(distance[k], 0.0)
        gap[k] = g if carried[k] else max(g, floor)
        target[k, 0] = vr_free[k, 0] - gap[k] / h
        target[k, 1], target[k, 2] = vr_free[k, 1], vr_free[k, 2]
        active[k] = (distance[k] <= 0 and may_start[k]) or was_active[k]
        friction[k] = mu[k] > 0
        stick[k] = friction[k] and (in_stick[k] or not was_active[k])


@_jit
def contact_finish(frames: np.ndarray, rl: np.ndarray, slip_force: np.ndarray, active: np.ndarray,
                   stick: np.ndarray, friction: np.ndarray, want_slip: np.ndarray, want_stick: np.ndarray,
                   mag: np.ndarray, d_stick: np.ndarray, new_slip: np.ndarray, force: np.ndarray,
                   next_stick: np.ndarray, next_slip: np.ndarray, slip_world: np.ndarray) -> None:
    """The end of an active-set loop (contact._ContactSet.result's arithmetic, contact by contact): the world
    forces (m, 3) [N] on the soft points from the last solve's forces rl (m, 3) in the contact frames (m, 3, 3)
    (zero where inactive; the sliding friction slip_force (m, 3) where sliding; no tangential part without
    friction), and the friction state for the next step: next_stick, next_slip (m,) bool and the sliding forces
    in the world slip_world (m, 3), from the switches wanted but not made (want_slip, want_stick) and mag (m, 1),
    d_stick, new_slip (m, 2) of the last read."""
    for k in range(frames.shape[0]):
        f0 = f1 = f2 = 0.0
        if active[k]:
            f0, f1, f2 = rl[k, 0], rl[k, 1], rl[k, 2]
            if not stick[k] and friction[k]:
                f1, f2 = slip_force[k, 1], slip_force[k, 2]
            if not friction[k]:
                f1 = f2 = 0.0
        for i in range(3):
            force[k, i] = frames[k, i, 0] * f0 + frames[k, i, 1] * f1 + frames[k, i, 2] * f2
        next_stick[k] = active[k] and friction[k] and ((stick[k] and not want_slip[k]) or want_stick[k])
        next_slip[k] = active[k] and friction[k] and not next_stick[k]
        if want_slip[k]:
            s1, s2 = mag[k, 0] * d_stick[k, 0], mag[k, 0] * d_stick[k, 1]
        else:
            s1, s2 = new_slip[k, 0], new_slip[k, 1]
        for i in range(3):
            slip_world[k, i] = frames[k, i, 0] * 0.0 + frames[k, i, 1] * s1 + frames[k, i, 2] * s2


@_jit
def _closest_on_triangle(p0: float, p1: float, p2: float, a0: float, a1: float, a2: float, b0: float, b1: float,
                         b2: float, c0: float, c1: float, c2: float):
    """collision.closest_on_triangles for one point and triangle (Ericson's Voronoi regions, the same arithmetic)."""
    ab0, ab1, ab2 = b0 - a0, b1 - a1, b2 - a2
    ac0, ac1, ac2 = c0 - a0, c1 - a1, c2 - a2
    ap0, ap1, ap2 = p0 - a0, p1 - a1, p2 - a2
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    bp0, bp1, bp2 = p0 - b0, p1 - b1, p2 - b2
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    cp0, cp1, cp2 = p0 - c0, p1 - c1, p2 - c2
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    if d1 <= 0 and d2 <= 0:  # the vertex regions, then the edges', then the face (the numpy code's precedence)
        return a0, a1, a2
    if d3 >= 0 and d4 <= d3:
        return b0, b1, b2
    if d6 >= 0 and d5 <= d6:
        return c0, c1, c2
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        t = d1 / (d1 - d3) if d1 - d3 != 0 else 0.0
        return a0 + t * ab0, a1 + t * ab1, a2 + t * ab2
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        t = d2 / (d2 - d6) if d2 - d6 != 0 else 0.0
        return a0 + t * ac0, a1 + t * ac1, a2 + t * ac2
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        den = (d4 - d3) + (d5 - d6)
        t = (d4 - d3) / den if den != 0 else 0.0
        return b0 + t * (c0 - b0), b1 + t * (c1 - b1), b2 + t * (c2 - b2)
    denom = va + vb + vc
    v = vb / denom if denom != 0 else 0.0
    w = vc / denom if denom != 0 else 0.0
    return a0 + v * ab0 + w * ac0, a1 + v * ab1 + w * ac1, a2 + v * ab2 + w * ac2


@_jit
def face_eligible(x: np.ndarray, q: np.ndarray, group: np.ndarray, normal: np.ndarray, active: np.ndarray,
                  same_face: float, out: np.ndarray) -> None:
    """contact._FaceSet.eligible's tests, contact by contact: out (m,) True for the contacts whose rigid point q
    (m, 3) projects into its triangle x (m, 3, 3) (barycentric weights >= -1e-9) and has it as the nearest of its
    ``group`` (m,) (to 1e-9 m), none of whose normals (m, 3) is within ``same_face`` (a cosine) of an ``active``
    (m,) contact's of the same group, the first such contact of each group."""
    m = q.shape[0]
    dist = np.empty(m)
    ok = np.empty(m, dtype=np.bool_)
    groups = 0
    for k in range(m):
        groups = max(groups, group[k] + 1)
        a0, a1, a2 = x[k, 0, 0], x[k, 0, 1], x[k, 0, 2]
        b0, b1, b2 = x[k, 1, 0], x[k, 1, 1], x[k, 1, 2]
        c0, c1, c2 = x[k, 2, 0], x[k, 2, 1], x[k, 2, 2]
        p0, p1, p2 = q[k, 0], q[k, 1], q[k, 2]
        # barycentric weights (collision.barycentric): n = (b - a) x (c - a)
        u0, u1, u2, v0, v1, v2 = b0 - a0, b1 - a1, b2 - a2, c0 - a0, c1 - a1, c2 - a2
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        nn = n0 * n0 + n1 * n1 + n2 * n2
        e0, e1, e2, f0, f1, f2 = c0 - b0, c1 - b1, c2 - b2, p0 - b0, p1 - b1, p2 - b2
        wa = ((e1 * f2 - e2 * f1) * n0 + (e2 * f0 - e0 * f2) * n1 + (e0 * f1 - e1 * f0) * n2) / nn
        e0, e1, e2, f0, f1, f2 = a0 - c0, a1 - c1, a2 - c2, p0 - c0, p1 - c1, p2 - c2
        wb = ((e1 * f2 - e2 * f1) * n0 + (e2 * f0 - e0 * f2) * n1 + (e0 * f1 - e1 * f0) * n2) / nn
        ok[k] = wa >= -1e-9 and wb >= -1e-9 and 1.0 - wa - wb >= -1e-9
        r0, r1, r2 = _closest_on_triangle(p0, p1, p2, a0, a1, a2, b0, b1, b2, c0, c1, c2)
        dist[k] = math.sqrt((p0 - r0) ** 2 + (p1 - r1) ** 2 + (p2 - r2) ** 2)
    nearest = np.full(groups, np.inf)
    for k in range(m):
        nearest[group[k]] = min(nearest[group[k]], dist[k])
    taken = np.zeros(groups, dtype=np.bool_)
    for k in range(m):
        good = ok[k] and dist[k] <= nearest[group[k]] + 1e-9
        if good:  # across a crease only: not nearly parallel to an active contact of the same rigid point
            for j in range(m):
                if active[j] and group[j] == group[k] and (normal[k, 0] * normal[j, 0] + normal[k, 1] * normal[j, 1]
                                                          + normal[k, 2] * normal[j, 2]) > same_face:
                    good = False
                    break
        out[k] = good and not taken[group[k]]
        if out[k]:
            taken[group[k]] = True


@_jit
def row_values(which: int, part: np.ndarray, node: np.ndarray, weight: np.ndarray, direction: np.ndarray,
               V: np.ndarray, out: np.ndarray) -> None:
    """coupling.Rows.values for k velocity fields V (k, N, 3) of soft body ``which``: out (m, k) = sum over the
    row's slots on that body (part (m, s) == which) of weight (m, s) times the slot node's velocity along the
    row's direction (m, 3)."""
    m, s = part.shape
    for r in range(m):
        d0, d1, d2 = direction[r, 0], direction[r, 1], direction[r, 2]
        for j in range(V.shape[0]):
            total = 0.0
            for slot in range(s):
                if part[r, slot] == which:
                    i = node[r, slot]
                    total += weight[r, slot] * (V[j, i, 0] * d0 + V[j, i, 1] * d1 + V[j, i, 2] * d2)
            out[r, j] = total


@_jit
def closest_points(q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, out: np.ndarray) -> None:
    """collision.closest_on_triangles row by row: the closest points out (m, 3) of triangles (a, b, c) (m, 3 each)
    to points q (m, 3)."""
    for k in range(q.shape[0]):
        out[k, 0], out[k, 1], out[k, 2] = _closest_on_triangle(
            q[k, 0], q[k, 1], q[k, 2], a[k, 0], a[k, 1], a[k, 2], b[k, 0], b[k, 1], b[k, 2], c[k, 0], c[k, 1], c[k, 2])


@_jit
def nearest_triangle_distances(q: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """The distance out (P,) from each point q (P, 3) to the nearest of the triangles x (T, 3, 3) (their closest
    points by collision.closest_on_triangles)."""
    for k in range(q.shape[0]):
        p0, p1, p2 = q[k, 0], q[k, 1], q[k, 2]
        best = np.inf
        for t in range(x.shape[0]):
            r0, r1, r2 = _closest_on_triangle(p0, p1, p2, x[t, 0, 0], x[t, 0, 1], x[t, 0, 2], x[t, 1, 0],
                                              x[t, 1, 1], x[t, 1, 2], x[t, 2, 0], x[t, 2, 1], x[t, 2, 2])
            best = min(best, math.sqrt((r0 - p0) ** 2 + (r1 - p1) ** 2 + (r2 - p2) ** 2))
        out[k] = best


@_jit
def edge_depths(p0: np.ndarray, p1: np.ndarray, P: np.ndarray) -> float:
    """intersection._edge_depths after its box test, edge by edge: for edges p0-p1 (E, 3 each) and triangles P
    (T, 3, 3) (outward) of the other surface, the crossings of each edge with the triangles whose bounding spheres
    its own meets (Moller-Trumbore), in order along the edge; the points where the stretches inside lie deepest (of a
    stretch from an entry to the next crossing, an exit: its middle and the point deepest behind both planes; of a
    stretch to an end: that end and the middle), and the largest of their distances to the nearest triangle [m]."""
    E, T = p0.shape[0], P.shape[0]
    centre = np.empty((T, 3))
    radius = np.empty(T)
    normal = np.empty((T, 3))
    for t in range(T):
        r2 = 0.0
        for j in range(3):
            centre[t, j] = (P[t, 0, j] + P[t, 1, j] + P[t, 2, j]) / 3.0
        for k in range(3):
            d0, d1, d2 = P[t, k, 0] - centre[t, 0], P[t, k, 1] - centre[t, 1], P[t, k, 2] - centre[t, 2]
            r2 = max(r2, d0 * d0 + d1 * d1 + d2 * d2)
        radius[t] = math.sqrt(r2)
        u0, u1, u2 = P[t, 1, 0] - P[t, 0, 0], P[t, 1, 1] - P[t, 0, 1], P[t, 1, 2] - P[t, 0, 2]
        v0, v1, v2 = P[t, 2, 0] - P[t, 0, 0], P[t, 2, 1] - P[t, 0, 1], P[t, 2, 2] - P[t, 0, 2]
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        ln = max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), 1e-300)
        normal[t, 0], normal[t, 1], normal[t, 2] = n0 / ln, n1 / ln, n2 / ln
    deepest = 0.0
    s_at = np.empty(8)
    rate = np.empty(8)
    points = np.empty(8)
    for i in range(E):
        m0, m1, m2 = 0.5 * (p0[i, 0] + p1[i, 0]), 0.5 * (p0[i, 1] + p1[i, 1]), 0.5 * (p0[i, 2] + p1[i, 2])
        d0, d1, d2 = p1[i, 0] - p0[i, 0], p1[i, 1] - p0[i, 1], p1[i, 2] - p0[i, 2]
        half = 0.5 * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        n_hit = 0
        for t in range(T):
            g0, g1, g2 = m0 - centre[t, 0], m1 - centre[t, 1], m2 - centre[t, 2]
            if math.sqrt(g0 * g0 + g1 * g1 + g2 * g2) > half + radius[t]:
                continue
            a0, a1, a2 = P[t, 0, 0], P[t, 0, 1], P[t, 0, 2]
            e10, e11, e12 = P[t, 1, 0] - a0, P[t, 1, 1] - a1, P[t, 1, 2] - a2
            e20, e21, e22 = P[t, 2, 0] - a0, P[t, 2, 1] - a1, P[t, 2, 2] - a2
            pv0, pv1, pv2 = d1 * e22 - d2 * e21, d2 * e20 - d0 * e22, d0 * e21 - d1 * e20
            det = e10 * pv0 + e11 * pv1 + e12 * pv2
            if not abs(det) > 1e-300:
                continue
            inv = 1.0 / det
            tv0, tv1, tv2 = p0[i, 0] - a0, p0[i, 1] - a1, p0[i, 2] - a2
            u = (tv0 * pv0 + tv1 * pv1 + tv2 * pv2) * inv
            qv0, qv1, qv2 = tv1 * e12 - tv2 * e11, tv2 * e10 - tv0 * e12, tv0 * e11 - tv1 * e10
            v = (d0 * qv0 + d1 * qv1 + d2 * qv2) * inv
            s = (e20 * qv0 + e21 * qv1 + e22 * qv2) * inv
            if not (u >= 0 and v >= 0 and u + v <= 1 and s >= 0 and s <= 1):
                continue
            if n_hit == s_at.shape[0]:
                s_at, rate = np.concatenate((s_at, np.empty(n_hit))), np.concatenate((rate, np.empty(n_hit)))
            s_at[n_hit] = s
            rate[n_hit] = -(d0 * normal[t, 0] + d1 * normal[t, 1] + d2 * normal[t, 2])
            n_hit += 1
        if n_hit == 0:
            continue
        order = np.argsort(s_at[:n_hit], kind="mergesort")
        ss, rr = s_at[:n_hit][order], rate[:n_hit][order]
        if points.shape[0] < 2 * n_hit + 4:
            points = np.empty(2 * n_hit + 4)
        n_pt = 0
        for k in range(n_hit - 1):  # a stretch from an entry to an exit
            if rr[k] > 0 and rr[k + 1] < 0:
                r1, r2 = rr[k], -rr[k + 1]
                points[n_pt] = (r1 * ss[k] + r2 * ss[k + 1]) / max(r1 + r2, 1e-300)
                points[n_pt + 1] = 0.5 * (ss[k] + ss[k + 1])
                n_pt += 2
        if rr[n_hit - 1] > 0:  # the last crossing an entry: the stretch to the end
            points[n_pt] = 1.0
            points[n_pt + 1] = 0.5 * (1.0 + ss[n_hit - 1])
            n_pt += 2
        if rr[0] < 0:  # the first an exit: the stretch from the start
            points[n_pt] = 0.0
            points[n_pt + 1] = 0.5 * ss[0]
            n_pt += 2
        for k in range(n_pt):
            a = points[k]
            q0, q1, q2 = p0[i, 0] + a * d0, p0[i, 1] + a * d1, p0[i, 2] + a * d2
            best = np.inf
            for t in range(T):
                c0, c1, c2 = _closest_on_triangle(q0, q1, q2, P[t, 0, 0], P[t, 0, 1], P[t, 0, 2], P[t, 1, 0],
                                                  P[t, 1, 1], P[t, 1, 2], P[t, 2, 0], P[t, 2, 1], P[t, 2, 2])
                best = min(best, math.sqrt((c0 - q0) ** 2 + (c1 - q1) ** 2 + (c2 - q2) ** 2))
            deepest = max(deepest, best)
    return deepest


@_jit
def primitive_link_contacts(positions: np.ndarray, surface: np.ndarray, triangles: np.ndarray, inc_indptr: np.ndarray,
                            inc_indices: np.ndarray, supported: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                            margin: float, h: float, rigid_slack: float, soft_slack: float, velocities: np.ndarray,
                            speeds: np.ndarray, v: np.ndarray, w: np.ndarray, centre: np.ndarray, radius: float,
                            kinds: np.ndarray, sizes: np.ndarray, Rw: np.ndarray, origins: np.ndarray,
                            facing: float, touch: float, faces: bool, round_kinds: np.ndarray,
                            round_sizes: np.ndarray, round_R: np.ndarray, round_pos: np.ndarray, smooth: np.ndarray,
                            corners: np.ndarray, corner_centres: np.ndarray, touching: np.ndarray,
                            touch_normal: np.ndarray):
    """One link of primitive parts in collision.CollisionDetector.detect, in one call: the broad phase on boxes
    (the surface nodes' box (s,) against the link's lo, hi (3,), grown by Sweep.bound), the node contacts
    (primitive_node_contacts), those whose rigid face does not face the surface at the node dropped (the dot of the
    contact normal with the surface normal node_normals_at, over the node-triangle incidence inc_indptr/inc_indices,
    not below ``facing``, unless the node is inside), and, for a link with face candidates (``faces``: round parts
    or corners), the nodes resting on it (within ``touch``, or ``supported`` (N,)) into touching (N,) and
    touch_normal (N, 3) and face_contacts_possible. Returns (status: 0 far apart, 1 no face search needed, 2 face
    search needed; the candidates, the bound [m], the contacts' nodes, points, normals and distances)."""
    s = surface.shape[0]
    top = 0.0  # the fastest surface node's speed (Sweep.soft_travel)
    for k in range(s):
        top = max(top, speeds[surface[k]])
    lo0, hi0 = np.empty(3), np.empty(3)  # the surface's box (collision.box_of)
    for j in range(3):
        a = b = positions[surface[0], j]
        for k in range(1, s):
            x = positions[surface[k], j]
            a, b = min(a, x), max(b, x)
        lo0[j], hi0[j] = a, b
    spin = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * radius if math.isfinite(radius) else 0.0
    bound = margin + soft_slack * h * top + rigid_slack * h * (math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
                                                              + spin)
    for j in range(3):
        if lo[j] > hi0[j] + bound or hi[j] < lo0[j] - bound:
            return 0, 0, bound, np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty((0, 3)), np.empty(0)
    count, node, point, normal, dist = primitive_node_contacts(
        positions, surface, lo, hi, bound, margin, h, rigid_slack, soft_slack, velocities, speeds, v, w, centre,
        radius, kinds, sizes, Rw, origins)
    m = node.shape[0]
    if m:
        nn = np.empty((m, 3))
        node_normals_at(positions, triangles, inc_indptr, inc_indices, node, nn)
        keep = np.empty(m, dtype=np.bool_)
        for k in range(m):
            keep[k] = (normal[k, 0] * nn[k, 0] + normal[k, 1] * nn[k, 1] + normal[k, 2] * nn[k, 2] < facing
                       or dist[k] <= 0.0)
        if not keep.all():
            node, point, normal, dist = node[keep], point[keep], normal[keep], dist[keep]
            m = node.shape[0]
    if not faces:
        return 1, count, bound, node, point, normal, dist
    touching[:] = False
    touch_normal[:] = 0.0
    for k in range(m):
        if dist[k] <= touch:
            touching[node[k]] = True
            touch_normal[node[k], 0], touch_normal[node[k], 1], touch_normal[node[k], 2] = (normal[k, 0], normal[k, 1],
                                                                                             normal[k, 2])
    for i in range(supported.shape[0]):
        if supported[i]:
            touching[i] = True
    possible = face_contacts_possible(positions, triangles, touching, lo, hi, bound, round_kinds, round_sizes, round_R,
                                      round_pos, smooth, corners, corner_centres, True, h, rigid_slack, soft_slack,
                                      velocities, v, w, centre)
    return 2 if possible else 1, count, bound, node, point, normal, dist


@_jit
def node_read(v: np.ndarray, r: np.ndarray, nodes: np.ndarray, frames: np.ndarray, h: float, vr_free: np.ndarray,
              rl: np.ndarray, vrel: np.ndarray) -> None:
    """A body's solve read at its node contacts (contact._NodeSet.read, no rigid body moved): the contact forces
    rl (m, 3) = r[nodes] / h [N] (reactions r (N, 3) already in the contact frames) and the relative velocities
    vrel (m, 3) = frames^T v[nodes] - vr_free in the contact frames (frames (m, 3, 3), axes as columns)."""
    for k in range(nodes.shape[0]):
        n = nodes[k]
        v0, v1, v2 = v[n, 0], v[n, 1], v[n, 2]
        for i in range(3):
            rl[k, i] = r[n, i] / h
            vrel[k, i] = (frames[k, 0, i] * v0 + frames[k, 1, i] * v1 + frames[k, 2, i] * v2) - vr_free[k, i]


@_jit
def law_slopes(vc0: np.ndarray, dvc: np.ndarray, alpha: float, R: np.ndarray, v_hat: np.ndarray, param: np.ndarray,
               bilateral: np.ndarray, cone: bool) -> tuple:
    """The line search's slopes of the convex problem's contact cost along a step (convex._Newton._line_search), row
    by row without the (m, 3) impulses or (m, 3, 3) Hessians: at vc = vc0 + alpha dvc (m, 3) [m/s], the sums over
    the rows of dvc . gamma(vc) and dvc^T G(vc) dvc, under Castro et al.'s cone (``cone``: param = mu,
    convex.cone_law) or the bounded law (param = the friction bounds [N s], convex.contact_law)."""
    s1 = 0.0
    s2 = 0.0
    for k in range(vc0.shape[0]):
        d0, d1, d2 = dvc[k, 0], dvc[k, 1], dvc[k, 2]
        v0, v1, v2 = vc0[k, 0] + alpha * d0, vc0[k, 1] + alpha * d1, vc0[k, 2] + alpha * d2
        i0, i1, i2 = 1.0 / R[k, 0], 1.0 / R[k, 1], 1.0 / R[k, 2]
        if cone:
            mu = param[k]
            y0, y1, y2 = (v_hat[k] - v0) * i0, -v1 * i1, -v2 * i2
            yr = math.sqrt(y1 * y1 + y2 * y2)
            if bilateral[k] or (mu > 0 and yr <= mu * y0):  # stiction: gamma = y, G = R^-1
                s1 += d0 * y0 + d1 * y1 + d2 * y2
                s2 += i0 * d0 * d0 + i1 * d1 * d1 + i2 * d2 * d2
            elif mu > 0:
                mh = mu * R[k, 1] * i0
                if y0 > -mh * yr:  # sliding
                    f = 1.0 / (1.0 + mu * mh)
                    gn = (y0 + mh * yr) * f
                    t1, t2 = y1 / yr, y2 / yr
                    s1 += gn * (d0 + mu * (t1 * d1 + t2 * d2))
                    # d^T (dP R^-1) d, dP as in convex.cone_law
                    e0, e1, e2 = i0 * d0, i1 * d1, i2 * d2
                    te = t1 * e1 + t2 * e2
                    td = t1 * d1 + t2 * d2
                    q = d0 * (f * e0 + mh * f * te) + td * mu * f * e0
                    q += mu * ((gn / yr) * (d1 * e1 + d2 * e2 - td * te) + mh * f * td * te)
                    s2 += q
            elif y0 > 0:  # frictionless, pushing
                s1 += d0 * y0
                s2 += i0 * d0 * d0
        else:
            bound = param[k]
            yn = (v_hat[k] - v0) * i0
            if bilateral[k] or yn > 0:
                s1 += d0 * yn
                s2 += i0 * d0 * d0
            speed = math.sqrt(v1 * v1 + v2 * v2)
            if bilateral[k] or (bound > 0 and speed * i1 <= bound):
                s1 -= i1 * (d1 * v1 + d2 * v2)
                s2 += i1 * (d1 * d1 + d2 * d2)
            elif speed > 0:
                scale = bound / speed
                s1 -= scale * (d1 * v1 + d2 * v2)
                td = (v1 * d1 + v2 * d2) / speed
                s2 += scale * (d1 * d1 + d2 * d2 - td * td)
    return s1, s2


@_jit
def soft_nearest(xs: np.ndarray, X: np.ndarray, tris: np.ndarray, nodes: np.ndarray, node_b: np.ndarray,
                 tri_b: np.ndarray, R: np.ndarray, rest_edge: np.ndarray, vnormals: np.ndarray, cand_i: np.ndarray,
                 cand_t: np.ndarray, margin: float, n_bodies: int, prism_tol: float, facing_cos: float,
                 w: np.ndarray, nrm: np.ndarray, d: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """softcontact.soft_contacts' narrow phase candidate by candidate: for the candidate pairs (surface node cand_i
    (m,) in the concatenation xs (S, 3), triangle cand_t (m,) of tris (T, 3) over X (N, 3)), the signed distance d
    (m,), clipped barycentric weights w (m, 3), unit normal nrm (m, 3) and whether the triangle faces the node's
    own surface (facing (m,)), written in place; returns the chosen candidates (ascending by node * n_bodies + the
    triangle's body): per node and other body the nearest facing triangle whose prism holds the node, if it lies
    within ``margin`` of the nearest of all (softcontact.nearest_facing; ties to the smaller triangle). Pairs
    within one body (self-contact) leave out triangles within one rest edge length (rest_edge (T,)) of the node's
    rest position (R (N, 3)) and count facing triangles only."""
    m = cand_i.shape[0]
    ok = np.zeros(m, dtype=np.bool_)
    key = np.empty(m, dtype=np.int64)
    # per triangle, once (a triangle serves several nodes): its unit normal and the gradients of two barycentric
    # weights, wa = (x - b) . ga and wb = (x - c) . gb (ga = n x (c - b) / |n|^2 is orthogonal to n: a point and its
    # projection on the plane have the same weights)
    T = tris.shape[0]
    frame = np.empty((T, 9))
    done = np.zeros(T, dtype=np.bool_)
    for k in range(m):
        i, t = cand_i[k], cand_t[k]
        g = nodes[i]
        same = node_b[i] == tri_b[t]
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        key[k] = i * n_bodies + tri_b[t]
        if same:  # self-contact: not against the node's own surroundings at rest
            gap2 = 0.0
            for j in range(3):
                lo = min(R[a, j], R[b, j], R[c, j])
                hi = max(R[a, j], R[b, j], R[c, j])
                r = R[g, j]
                e = r - min(max(r, lo), hi)
                gap2 += e * e
            if not gap2 > (1.01 * rest_edge[t]) ** 2:
                continue
        if not done[t]:
            u0, u1, u2 = X[b, 0] - X[a, 0], X[b, 1] - X[a, 1], X[b, 2] - X[a, 2]
            v0, v1, v2 = X[c, 0] - X[a, 0], X[c, 1] - X[a, 1], X[c, 2] - X[a, 2]
            n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
            nn = n0 * n0 + n1 * n1 + n2 * n2
            ln = math.sqrt(nn)
            frame[t, 0], frame[t, 1], frame[t, 2] = n0 / ln, n1 / ln, n2 / ln
            c0, c1, c2 = X[c, 0] - X[b, 0], X[c, 1] - X[b, 1], X[c, 2] - X[b, 2]  # ga = n x (c - b) / nn
            frame[t, 3], frame[t, 4], frame[t, 5] = ((n1 * c2 - n2 * c1) / nn, (n2 * c0 - n0 * c2) / nn,
                                                     (n0 * c1 - n1 * c0) / nn)
            c0, c1, c2 = X[a, 0] - X[c, 0], X[a, 1] - X[c, 1], X[a, 2] - X[c, 2]  # gb = n x (a - c) / nn
            frame[t, 6], frame[t, 7], frame[t, 8] = ((n1 * c2 - n2 * c1) / nn, (n2 * c0 - n0 * c2) / nn,
                                                     (n0 * c1 - n1 * c0) / nn)
            done[t] = True
        e0, e1, e2 = frame[t, 0], frame[t, 1], frame[t, 2]
        x0, x1, x2 = xs[i, 0], xs[i, 1], xs[i, 2]
        dk = (x0 - X[a, 0]) * e0 + (x1 - X[a, 1]) * e1 + (x2 - X[a, 2]) * e2
        # barycentric weights of the projection (collision.barycentric)
        wa = (x0 - X[b, 0]) * frame[t, 3] + (x1 - X[b, 1]) * frame[t, 4] + (x2 - X[b, 2]) * frame[t, 5]
        wb = (x0 - X[c, 0]) * frame[t, 6] + (x1 - X[c, 1]) * frame[t, 7] + (x2 - X[c, 2]) * frame[t, 8]
        wc = 1.0 - wa - wb
        if not (wa >= -prism_tol and wb >= -prism_tol and wc >= -prism_tol):
            continue
        fk = vnormals[g, 0] * e0 + vnormals[g, 1] * e1 + vnormals[g, 2] * e2 < facing_cos
        if same and not fk:
            continue
        wa, wb, wc = max(wa, 0.0), max(wb, 0.0), max(wc, 0.0)
        s = wa + wb + wc
        w[k, 0], w[k, 1], w[k, 2] = wa / s, wb / s, wc / s
        nrm[k, 0], nrm[k, 1], nrm[k, 2] = e0, e1, e2
        d[k] = dk
        facing[k] = fk
        ok[k] = True
    idx = np.flatnonzero(ok)
    order = idx[np.argsort(key[idx], kind="mergesort")]
    chosen = np.empty(len(order), dtype=np.int64)
    count = 0
    start = 0
    while start < len(order):
        stop = start + 1
        while stop < len(order) and key[order[stop]] == key[order[start]]:
            stop += 1
        nearest = np.inf
        best = -1
        for r in range(start, stop):
            k = order[r]
            ad = abs(d[k])
            nearest = min(nearest, ad)
            if facing[k] and (best < 0 or ad < abs(d[best]) or (ad == abs(d[best]) and cand_t[k] < cand_t[best])):
                best = k
        if best >= 0 and abs(d[best]) <= nearest + margin:
            chosen[count] = best
            count += 1
        start = stop
    return chosen[:count]


@_inline
def _explained(keys: np.ndarray, node: int, tag: int) -> bool:
    """Whether node ``node`` has a node contact keyed node | tag among the sorted ``keys``."""
    nk = keys.shape[0]
    if not nk:
        return False
    want = node | tag
    at = min(np.searchsorted(keys, want), nk - 1)
    return keys[at] == want


@_jit
def edges_near(edges: np.ndarray, edge_b: np.ndarray, X: np.ndarray, node_off: np.ndarray, lo: np.ndarray,
               hi: np.ndarray, meet: np.ndarray, between: np.ndarray, keys: np.ndarray, used: np.ndarray,
               node_bits: int) -> np.ndarray:
    """softcontact.edge_contacts' broad phase edge by edge (softcontact.edges_near): (E,) whether an edge of ``edges``
    (E, 2) of body edge_b (E,) at X (node offsets node_off) has its box meet the box (lo, hi) (B, 3) of a body q it
    meets (meet (B, B)) grown by between[p, q] [m], with neither end in a node contact with q (keys: the node
    contacts' keys, sorted, softcontact._gap_table; empty: none; bodies named by ``used`` (B,))."""
    E = edges.shape[0]
    B = lo.shape[0]
    near = np.zeros(E, dtype=np.bool_)
    for e in range(E):
        p = edge_b[e]
        a, b = edges[e, 0], edges[e, 1]
        ga, gb = a + node_off[p], b + node_off[p]
        for q in range(B):
            if not meet[p, q]:
                continue
            g = between[p, q]
            meets = True
            for j in range(3):
                elo = min(X[ga, j], X[gb, j])
                ehi = max(X[ga, j], X[gb, j])
                if not (elo <= hi[q, j] + g and ehi >= lo[q, j] - g):
                    meets = False
                    break
            if not meets:
                continue
            tag = (used[p] * 1024 + used[q]) << node_bits
            if _explained(keys, a, tag) or _explained(keys, b, tag):
                continue
            near[e] = True
            break
    return near


@_jit
def centre_grid(centre: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A uniform grid of cell size ``cell`` [m] over points ``centre`` (T, 3): (the lowest cell and the highest
    relative to it (2, 3), the points' cell keys sorted (T,), the points in that order (T,)); a cell's points are a
    run of equal keys (21 bits per axis: the caller's cell spans the points' extent in fewer than 2^21 cells)."""
    T = centre.shape[0]
    bounds = np.zeros((2, 3), dtype=np.int64)
    for j in range(3):
        lo, hi = np.inf, -np.inf
        for t in range(T):
            lo = min(lo, centre[t, j])
            hi = max(hi, centre[t, j])
        if T:
            bounds[0, j] = int(math.floor(lo / cell))
            bounds[1, j] = int(math.floor(hi / cell)) - bounds[0, j]
    keys = np.empty(T, dtype=np.int64)
    for t in range(T):
        c0 = int(math.floor(centre[t, 0] / cell)) - bounds[0, 0]
        c1 = int(math.floor(centre[t, 1] / cell)) - bounds[0, 1]
        c2 = int(math.floor(centre[t, 2] / cell)) - bounds[0, 2]
        keys[t] = (c0 << 42) | (c1 << 21) | c2
    order = np.argsort(keys, kind="mergesort")
    return bounds, keys[order], order


@_inline
def _grid_range(x: float, r: float, cell: float, bounds: np.ndarray, j: int) -> tuple[int, int]:
    """The occupied cells along axis j (relative to the lowest, centre_grid's bounds) within r of x."""
    lo = max(int(math.floor((x - r) / cell)) - bounds[0, j], 0)
    hi = min(int(math.floor((x + r) / cell)) - bounds[0, j], bounds[1, j])
    return lo, hi


@_inline
def _grid_box(x0: float, x1: float, x2: float, r: float, cell: float, bounds: np.ndarray
              ) -> tuple[int, int, int, int, int, int]:
    """The occupied cells (first and last along each axis) within r of the point (x0, x1, x2)."""
    a0, b0 = _grid_range(x0, r, cell, bounds, 0)
    a1, b1 = _grid_range(x1, r, cell, bounds, 1)
    a2, b2 = _grid_range(x2, r, cell, bounds, 2)
    return a0, b0, a1, b1, a2, b2


@_inline
def _column(keys: np.ndarray, c0: int, c1: int, a2: int, b2: int) -> tuple[int, int]:
    """The run [begin, end) of centre_grid's sorted keys in the cells (c0, c1, a2..b2)."""
    k0 = (c0 << 42) | (c1 << 21)
    return np.searchsorted(keys, k0 | a2), np.searchsorted(keys, k0 | b2, side="right")


@_inline
def _room(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with room for an entry at index n: twice as long if full."""
    return np.concatenate((a, np.empty(n, dtype=a.dtype))) if n == a.shape[0] else a


@_jit
def triangle_spheres(X: np.ndarray, V: np.ndarray, tris: np.ndarray, tri_b: np.ndarray, mean_v: np.ndarray,
                     slack_h: float, centre: np.ndarray, radius: np.ndarray, travel: np.ndarray) -> float:
    """softcontact.soft_contacts' triangle bounds, triangle by triangle: each triangle's (tris (T, 3) over X (N, 3))
    centre (T, 3) (its corners' mean), bounding radius (T,) about it and largest corner travel slack_h |V - mean_v
    of its body tri_b| (T,), in place; returns the centres' largest extent along an axis [m]."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        m = mean_v[tri_b[t]]
        r2 = 0.0
        v2 = 0.0
        for j in range(3):
            centre[t, j] = (X[a, j] + X[b, j] + X[c, j]) / 3.0
            lo[j] = min(lo[j], centre[t, j])
            hi[j] = max(hi[j], centre[t, j])
        for n in (a, b, c):
            d0, d1, d2 = X[n, 0] - centre[t, 0], X[n, 1] - centre[t, 1], X[n, 2] - centre[t, 2]
            r2 = max(r2, d0 * d0 + d1 * d1 + d2 * d2)
            u0, u1, u2 = V[n, 0] - m[0], V[n, 1] - m[1], V[n, 2] - m[2]
            v2 = max(v2, u0 * u0 + u1 * u1 + u2 * u2)
        radius[t] = math.sqrt(r2)
        travel[t] = slack_h * math.sqrt(v2)
    extent = 0.0
    for j in range(3):
        if hi[j] >= lo[j]:
            extent = max(extent, hi[j] - lo[j])
    return extent


@_jit
def soft_candidates(xs: np.ndarray, node_b: np.ndarray, travel_a: np.ndarray, between: np.ndarray,
                    meet: np.ndarray, grow: np.ndarray, plo: np.ndarray, phi: np.ndarray, centre: np.ndarray,
                    radius: np.ndarray, travel_b: np.ndarray, tri_b: np.ndarray, tb_max: np.ndarray, margin: float,
                    depth: float, cell: float, base: np.ndarray, keys: np.ndarray, order: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """softcontact.soft_contacts' broad phase, first pass, for all surface nodes xs (S, 3) (of bodies node_b (S,))
    against all triangles (centres (T, 3) in the grid centre_grid(centre, cell) = (base, keys, order), bounding
    radii (T,), travels about their body's mean (T,), bodies tri_b (T,)): the pairs (node, triangle) where the
    direction (p, q) is searched and meets (meet (B, B)), the node lies in q's box (plo, phi) (B, 3) grown by
    grow[p, q], and the centres lie within both margin + depth + radius + the node's travel against q + the
    triangle's, and margin + that travel + tb_max[q] + 1.1 radius (the node's own reach; the k-d tree query's
    conditions). Also the pairs (node, body q != p) to search as deep as depth where the first pass leaves the node
    unsettled: the node inside q's box. Returns (node, triangle, deep node, deep body)."""
    S, B = xs.shape[0], meet.shape[0]
    r_max = 0.0
    for t in range(radius.shape[0]):
        r_max = max(r_max, radius[t])
    tb_all = 0.0
    for q in range(B):
        tb_all = max(tb_all, tb_max[q])
    cap = max(16, 8 * S)
    out_i = np.empty(cap, dtype=np.int64)
    out_t = np.empty(cap, dtype=np.int64)
    deep_i = np.empty(S, dtype=np.int64)
    deep_q = np.empty(S, dtype=np.int64)
    n_out = 0
    n_deep = 0
    searched = np.zeros(B, dtype=np.bool_)
    qs = np.empty(B, dtype=np.int64)
    for i in range(S):
        p = node_b[i]
        x0, x1, x2 = xs[i, 0], xs[i, 1], xs[i, 2]
        n_q = 0
        ta_max = 0.0
        for q in range(B):
            if not meet[p, q]:
                continue
            g = grow[p, q]
            if (x0 >= plo[q, 0] - g and x1 >= plo[q, 1] - g and x2 >= plo[q, 2] - g
                    and x0 <= phi[q, 0] + g and x1 <= phi[q, 1] + g and x2 <= phi[q, 2] + g):
                searched[q] = True
                qs[n_q] = q
                n_q += 1
                ta_max = max(ta_max, travel_a[i] + between[p, q])
                if q != p and (x0 >= plo[q, 0] and x1 >= plo[q, 1] and x2 >= plo[q, 2]
                               and x0 <= phi[q, 0] and x1 <= phi[q, 1] and x2 <= phi[q, 2]):
                    deep_i, deep_q = _room(deep_i, n_deep), _room(deep_q, n_deep)
                    deep_i[n_deep] = i
                    deep_q[n_deep] = q
                    n_deep += 1
        if n_q == 0:
            continue
        reach = min(margin + depth + r_max + ta_max + tb_all, margin + ta_max + tb_all + 1.1 * r_max)
        a0, b0, a1, b1, a2, b2 = _grid_box(x0, x1, x2, reach, cell, base)
        for c0 in range(a0, b0 + 1):
            for c1 in range(a1, b1 + 1):
                begin, end = _column(keys, c0, c1, a2, b2)
                for at in range(begin, end):
                    t = order[at]
                    q = tri_b[t]
                    if not searched[q]:
                        continue
                    ta = travel_a[i] + between[p, q]
                    v = math.sqrt((x0 - centre[t, 0]) ** 2 + (x1 - centre[t, 1]) ** 2 + (x2 - centre[t, 2]) ** 2)
                    if (v <= margin + depth + radius[t] + ta + travel_b[t]
                            and v <= (margin + ta + tb_max[q]) + 1.1 * radius[t]):
                        out_i, out_t = _room(out_i, n_out), _room(out_t, n_out)
                        out_i[n_out] = i
                        out_t[n_out] = t
                        n_out += 1
        for r in range(n_q):
            searched[qs[r]] = False
    return out_i[:n_out], out_t[:n_out], deep_i[:n_deep], deep_q[:n_deep]


@_jit
def first_pass_among(cand_i: np.ndarray, cand_t: np.ndarray, xs: np.ndarray, node_b: np.ndarray, travel_a: np.ndarray,
                     between: np.ndarray, meet: np.ndarray, grow: np.ndarray, plo: np.ndarray, phi: np.ndarray,
                     centre: np.ndarray, radius: np.ndarray, travel_b: np.ndarray, tri_b: np.ndarray,
                     tb_max: np.ndarray, margin: float, depth: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """soft_candidates' first pass among candidate pairs (cand_i, cand_t) found earlier with wider reaches
    (softcontact.FirstPass): those that meet its conditions now (in their order), and its deep pass's pairs (node,
    body), found as it finds them (node by node, bodies in order). The arguments are soft_candidates'."""
    m = cand_i.shape[0]
    keep = np.empty(m, dtype=np.bool_)
    for k in range(m):
        i, t = cand_i[k], cand_t[k]
        p, q = node_b[i], tri_b[t]
        ok = meet[p, q]
        if ok:
            g = grow[p, q]
            for j in range(3):
                if not (xs[i, j] >= plo[q, j] - g and xs[i, j] <= phi[q, j] + g):
                    ok = False
                    break
        if ok:
            ta = travel_a[i] + between[p, q]
            v = math.sqrt((xs[i, 0] - centre[t, 0]) ** 2 + (xs[i, 1] - centre[t, 1]) ** 2
                          + (xs[i, 2] - centre[t, 2]) ** 2)
            ok = v <= margin + depth + radius[t] + ta + travel_b[t] and v <= (margin + ta + tb_max[q]) + 1.1 * radius[t]
        keep[k] = ok
    S, B = xs.shape[0], meet.shape[0]
    deep_i = np.empty(S, dtype=np.int64)
    deep_q = np.empty(S, dtype=np.int64)
    n_deep = 0
    for i in range(S):
        p = node_b[i]
        x0, x1, x2 = xs[i, 0], xs[i, 1], xs[i, 2]
        for q in range(B):
            if q == p or not meet[p, q]:
                continue
            if (x0 >= plo[q, 0] and x1 >= plo[q, 1] and x2 >= plo[q, 2]
                    and x0 <= phi[q, 0] and x1 <= phi[q, 1] and x2 <= phi[q, 2]):
                deep_i, deep_q = _room(deep_i, n_deep), _room(deep_q, n_deep)
                deep_i[n_deep] = i
                deep_q[n_deep] = q
                n_deep += 1
    idx = np.flatnonzero(keep)
    return cand_i[idx], cand_t[idx], deep_i[:n_deep], deep_q[:n_deep]


@_jit
def triangle_distances(xs: np.ndarray, X: np.ndarray, tris: np.ndarray, cand_i: np.ndarray, cand_t: np.ndarray,
                       out: np.ndarray) -> None:
    """The distance [m] from node cand_i (rows of xs (S, 3)) to triangle cand_t (rows of tris (T, 3) over X (N, 3)),
    pair by pair, into out (m,): collision.closest_on_triangles' closest point (Ericson, by Voronoi regions)."""
    for k in range(cand_i.shape[0]):
        i, t = cand_i[k], cand_t[k]
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ab0, ab1, ab2 = X[b, 0] - X[a, 0], X[b, 1] - X[a, 1], X[b, 2] - X[a, 2]
        ac0, ac1, ac2 = X[c, 0] - X[a, 0], X[c, 1] - X[a, 1], X[c, 2] - X[a, 2]
        p0, p1, p2 = xs[i, 0], xs[i, 1], xs[i, 2]
        ap0, ap1, ap2 = p0 - X[a, 0], p1 - X[a, 1], p2 - X[a, 2]
        d1, d2 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2, ac0 * ap0 + ac1 * ap1 + ac2 * ap2
        bp0, bp1, bp2 = p0 - X[b, 0], p1 - X[b, 1], p2 - X[b, 2]
        d3, d4 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2, ac0 * bp0 + ac1 * bp1 + ac2 * bp2
        cp0, cp1, cp2 = p0 - X[c, 0], p1 - X[c, 1], p2 - X[c, 2]
        d5, d6 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2, ac0 * cp0 + ac1 * cp1 + ac2 * cp2
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        if d1 <= 0.0 and d2 <= 0.0:  # vertex a
            q0, q1, q2 = X[a, 0], X[a, 1], X[a, 2]
        elif d3 >= 0.0 and d4 <= d3:  # vertex b
            q0, q1, q2 = X[b, 0], X[b, 1], X[b, 2]
        elif d6 >= 0.0 and d5 <= d6:  # vertex c
            q0, q1, q2 = X[c, 0], X[c, 1], X[c, 2]
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge ab
            s = d1 / (d1 - d3) if d1 != d3 else 0.0
            q0, q1, q2 = X[a, 0] + s * ab0, X[a, 1] + s * ab1, X[a, 2] + s * ab2
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge ac
            s = d2 / (d2 - d6) if d2 != d6 else 0.0
            q0, q1, q2 = X[a, 0] + s * ac0, X[a, 1] + s * ac1, X[a, 2] + s * ac2
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:  # edge bc
            den = (d4 - d3) + (d5 - d6)
            s = (d4 - d3) / den if den != 0.0 else 0.0
            q0 = X[b, 0] + s * (X[c, 0] - X[b, 0])
            q1 = X[b, 1] + s * (X[c, 1] - X[b, 1])
            q2 = X[b, 2] + s * (X[c, 2] - X[b, 2])
        else:  # inside the face
            den = va + vb + vc
            v = vb / den if den != 0.0 else 0.0
            w = vc / den if den != 0.0 else 0.0
            q0, q1, q2 = X[a, 0] + v * ab0 + w * ac0, X[a, 1] + v * ab1 + w * ac1, X[a, 2] + v * ab2 + w * ac2
        out[k] = math.sqrt((p0 - q0) ** 2 + (p1 - q1) ** 2 + (p2 - q2) ** 2)


@_jit
def soft_deep_candidates(xs: np.ndarray, node_b: np.ndarray, travel_a: np.ndarray, between: np.ndarray,
                         nodes: np.ndarray, bodies: np.ndarray, centre: np.ndarray, radius: np.ndarray,
                         travel_b: np.ndarray, tri_b: np.ndarray, margin: float, depth: float, cell: float,
                         base: np.ndarray, keys: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """softcontact.soft_contacts' broad phase, second pass: for each (node, body q) of ``nodes`` (k,) and
    ``bodies`` (k,), the triangles of q whose centres lie within margin + depth + radius + the node's travel against
    q + the triangle's (soft_candidates' grid and arrays). Returns (node, triangle)."""
    r_max = 0.0
    tb_all = 0.0
    for t in range(radius.shape[0]):
        r_max = max(r_max, radius[t])
        tb_all = max(tb_all, travel_b[t])
    n = nodes.shape[0]
    cap = max(16, 32 * n)
    out_i = np.empty(cap, dtype=np.int64)
    out_t = np.empty(cap, dtype=np.int64)
    n_out = 0
    for r in range(n):
        i, q = nodes[r], bodies[r]
        p = node_b[i]
        x0, x1, x2 = xs[i, 0], xs[i, 1], xs[i, 2]
        ta = travel_a[i] + between[p, q]
        reach = margin + depth + r_max + ta + tb_all
        a0, b0, a1, b1, a2, b2 = _grid_box(x0, x1, x2, reach, cell, base)
        for c0 in range(a0, b0 + 1):
            for c1 in range(a1, b1 + 1):
                begin, end = _column(keys, c0, c1, a2, b2)
                for at in range(begin, end):
                    t = order[at]
                    if tri_b[t] != q:
                        continue
                    v = math.sqrt((x0 - centre[t, 0]) ** 2 + (x1 - centre[t, 1]) ** 2 + (x2 - centre[t, 2]) ** 2)
                    if v <= margin + depth + radius[t] + ta + travel_b[t]:
                        out_i, out_t = _room(out_i, n_out), _room(out_t, n_out)
                        out_i[n_out] = i
                        out_t[n_out] = t
                        n_out += 1
    return out_i[:n_out], out_t[:n_out]


@_jit
def edge_candidates(mid: np.ndarray, body: np.ndarray, rank: np.ndarray, meet: np.ndarray, slack: np.ndarray,
                    radius: float, cell: float, base: np.ndarray, keys: np.ndarray, order: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """softcontact.edge_candidates over the grid centre_grid(mid, cell) = (base, keys, order) of the midpoints mid
    (E, 3) of edges of bodies ``body`` (E,): the pairs (i, j), i of p and j of q, for rank[p, q] even (the pair
    listed as (p, q); p == q: i < j) and meet[p, q], whose midpoints lie within radius + slack[p, q] [m] (unordered:
    the caller sorts them)."""
    E = mid.shape[0]
    B = rank.shape[0]
    reach = np.zeros(B)
    for p in range(B):
        for q in range(B):
            if meet[p, q] and rank[p, q] >= 0 and rank[p, q] % 2 == 0:
                reach[p] = max(reach[p], radius + slack[p, q])
    cap = max(16, 4 * E)
    out_i = np.empty(cap, dtype=np.int64)
    out_j = np.empty(cap, dtype=np.int64)
    n_out = 0
    for i in range(E):
        p = body[i]
        if reach[p] == 0.0:
            continue
        x0, x1, x2 = mid[i, 0], mid[i, 1], mid[i, 2]
        a0, b0, a1, b1, a2, b2 = _grid_box(x0, x1, x2, reach[p], cell, base)
        for c0 in range(a0, b0 + 1):
            for c1 in range(a1, b1 + 1):
                begin, end = _column(keys, c0, c1, a2, b2)
                for at in range(begin, end):
                    j = order[at]
                    q = body[j]
                    if not meet[p, q] or rank[p, q] < 0 or rank[p, q] % 2 != 0 or (p == q and j <= i):
                        continue
                    r = radius + slack[p, q]
                    if (x0 - mid[j, 0]) ** 2 + (x1 - mid[j, 1]) ** 2 + (x2 - mid[j, 2]) ** 2 <= r * r:
                        out_i, out_j = _room(out_i, n_out), _room(out_j, n_out)
                        out_i[n_out] = i
                        out_j[n_out] = j
                        n_out += 1
    return out_i[:n_out], out_j[:n_out]


@_inline
def _segment_params(p0, p1, p2, e0, e1, e2, q0, q1, q2, f0, f1, f2) -> tuple[float, float]:
    """segments.closest_between_segments for one pair: the parameters (s, t) of the closest points of the segments
    from p to e and from q to f."""
    d10, d11, d12 = e0 - p0, e1 - p1, e2 - p2
    d20, d21, d22 = f0 - q0, f1 - q1, f2 - q2
    r0, r1, r2 = p0 - q0, p1 - q1, p2 - q2
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    b = d10 * d20 + d11 * d21 + d12 * d22
    c = d10 * r0 + d11 * r1 + d12 * r2
    f = d20 * r0 + d21 * r1 + d22 * r2
    denom = a * e - b * b
    s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        s = min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        s = min(max((b - c) / a, 0.0), 1.0)
    return s, min(max(t, 0.0), 1.0)


@_jit
def edge_narrow(ci: np.ndarray, cj: np.ndarray, P0: np.ndarray, P1: np.ndarray, V0: np.ndarray, V1: np.ndarray,
                N: np.ndarray, R0: np.ndarray, R1: np.ndarray, half: np.ndarray, travel: np.ndarray,
                body_of: np.ndarray, ends: np.ndarray, mean_v: np.ndarray, keys: np.ndarray, node_bits: int,
                margin: float, reach: float, depth: float, slack_h: float, edge_sin: float, edge_end: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """softcontact.edge_contacts' narrow phase pair by pair, for candidate edge pairs (ci, cj) (m,) (edges with ends
    P0, P1 (E, 3), their velocities about their body's mean V0, V1, outward normals N, rest ends R0, R1, half lengths,
    travels, bodies body_of (E,) and nodes ends (E, 2); the bodies' mean velocities mean_v (B, 3); the node contacts'
    sorted keys): the same tests in the same order (reach, self-contact's own surroundings, ends in node contact,
    near-parallel or unfacing edges, closest points between the ends, facing, within reach and less than depth
    crossed). Returns (kept pair indices (k,), s (k,), t (k,), normal (k, 3), distance (k,))."""
    m = ci.shape[0]
    keep = np.empty(m, dtype=np.int64)
    s_out = np.empty(m)
    t_out = np.empty(m)
    n_out = np.empty((m, 3))
    d_out = np.empty(m)
    count = 0
    for k in range(m):
        i, j = ci[k], cj[k]
        a, b = body_of[i], body_of[j]
        g0 = 0.5 * (P0[i, 0] + P1[i, 0]) - 0.5 * (P0[j, 0] + P1[j, 0])
        g1 = 0.5 * (P0[i, 1] + P1[i, 1]) - 0.5 * (P0[j, 1] + P1[j, 1])
        g2 = 0.5 * (P0[i, 2] + P1[i, 2]) - 0.5 * (P0[j, 2] + P1[j, 2])
        m0, m1, m2 = mean_v[a, 0] - mean_v[b, 0], mean_v[a, 1] - mean_v[b, 1], mean_v[a, 2] - mean_v[b, 2]
        if not (math.sqrt(g0 * g0 + g1 * g1 + g2 * g2) <= half[i] + half[j] + reach + travel[i] + travel[j]
                + slack_h * math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)):
            continue
        if a == b:  # self-contact: not against the edge's own surroundings at rest
            rs, rt = _segment_params(R0[i, 0], R0[i, 1], R0[i, 2], R1[i, 0], R1[i, 1], R1[i, 2],
                                     R0[j, 0], R0[j, 1], R0[j, 2], R1[j, 0], R1[j, 1], R1[j, 2])
            w2 = 0.0
            li, lj = 0.0, 0.0
            for x in range(3):
                di, dj = R1[i, x] - R0[i, x], R1[j, x] - R0[j, x]
                w = (R0[i, x] + rs * di) - (R0[j, x] + rt * dj)
                w2 += w * w
                li += di * di
                lj += dj * dj
            if w2 <= (1.01 * max(math.sqrt(li), math.sqrt(lj))) ** 2:
                continue
        tag_a, tag_b = (a * 1024 + b) << node_bits, (b * 1024 + a) << node_bits
        if (_explained(keys, ends[i, 0], tag_a) or _explained(keys, ends[i, 1], tag_a)
                or _explained(keys, ends[j, 0], tag_b) or _explained(keys, ends[j, 1], tag_b)):
            continue
        da0, da1, da2 = P1[i, 0] - P0[i, 0], P1[i, 1] - P0[i, 1], P1[i, 2] - P0[i, 2]
        db0, db1, db2 = P1[j, 0] - P0[j, 0], P1[j, 1] - P0[j, 1], P1[j, 2] - P0[j, 2]
        c0, c1, c2 = da1 * db2 - da2 * db1, da2 * db0 - da0 * db2, da0 * db1 - da1 * db0
        crn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        cni = c0 * N[i, 0] + c1 * N[i, 1] + c2 * N[i, 2]
        cnj = c0 * N[j, 0] + c1 * N[j, 1] + c2 * N[j, 2]
        if not (crn > edge_sin * 4.0 * half[i] * half[j] and cni * cnj < 0 and abs(cni) > 0.05 * crn
                and abs(cnj) > 0.05 * crn):
            continue
        s, t = _segment_params(P0[i, 0], P0[i, 1], P0[i, 2], P1[i, 0], P1[i, 1], P1[i, 2],
                               P0[j, 0], P0[j, 1], P0[j, 2], P1[j, 0], P1[j, 1], P1[j, 2])
        if not (s > edge_end and s < 1 - edge_end and t > edge_end and t < 1 - edge_end):
            continue
        n0, n1, n2 = c0 / crn, c1 / crn, c2 / crn
        if n0 * N[j, 0] + n1 * N[j, 1] + n2 * N[j, 2] < 0.0:  # out of b's edge
            n0, n1, n2 = -n0, -n1, -n2
        d = (n0 * ((P0[i, 0] + s * da0) - (P0[j, 0] + t * db0)) + n1 * ((P0[i, 1] + s * da1) - (P0[j, 1] + t * db1))
             + n2 * ((P0[i, 2] + s * da2) - (P0[j, 2] + t * db2)))
        v0 = ((1 - s) * V0[i, 0] + s * V1[i, 0]) - ((1 - t) * V0[j, 0] + t * V1[j, 0]) + mean_v[a, 0] - mean_v[b, 0]
        v1 = ((1 - s) * V0[i, 1] + s * V1[i, 1]) - ((1 - t) * V0[j, 1] + t * V1[j, 1]) + mean_v[a, 1] - mean_v[b, 1]
        v2 = ((1 - s) * V0[i, 2] + s * V1[i, 2]) - ((1 - t) * V0[j, 2] + t * V1[j, 2]) + mean_v[a, 2] - mean_v[b, 2]
        closing = max(-(v0 * n0 + v1 * n1 + v2 * n2), 0.0)
        facing = ((n0 * N[j, 0] + n1 * N[j, 1] + n2 * N[j, 2] > 0.05)
                  and (n0 * N[i, 0] + n1 * N[i, 1] + n2 * N[i, 2] < -0.05))
        deepest = -margin if a == b else -depth
        if facing and d < margin + slack_h * closing and d > deepest:
            keep[count] = k
            s_out[count], t_out[count] = s, t
            n_out[count, 0], n_out[count, 1], n_out[count, 2] = n0, n1, n2
            d_out[count] = d
            count += 1
    return keep[:count], s_out[:count], t_out[:count], n_out[:count], d_out[:count]


# ------------------------------------------------------------------ the convex coupled solve (convex.py)


@_jit
def delassus_diagonal(gnodes: np.ndarray, w: np.ndarray, F: np.ndarray, D: np.ndarray, held: np.ndarray,
                      out: np.ndarray) -> None:
    """convex._Newton._delassus_diagonal's soft part, row by row: out (m, 3) = sum over the row's slots of w^2 times
    F_k^T D_n^-1 F_k for each direction k (F (m, 3, 3): the rows' frames, columns n, t1, t2), D_n the diagonal block
    (N, 3, 3) of the slot's node (gnodes (m, S), weights w (m, S)) inverted on its free components (held (N, 3):
    those rows and columns left out, their inverse entries zero)."""
    m, S = gnodes.shape
    inv = np.empty((3, 3))
    for r in range(m):
        o0 = o1 = o2 = 0.0
        for s in range(S):
            ws = w[r, s]
            if ws == 0.0:
                continue
            n = gnodes[r, s]
            f0, f1, f2 = not held[n, 0], not held[n, 1], not held[n, 2]
            # the block with held rows and columns replaced by the identity's
            a00 = D[n, 0, 0] if f0 else 1.0
            a11 = D[n, 1, 1] if f1 else 1.0
            a22 = D[n, 2, 2] if f2 else 1.0
            a01 = D[n, 0, 1] if (f0 and f1) else 0.0
            a10 = D[n, 1, 0] if (f0 and f1) else 0.0
            a02 = D[n, 0, 2] if (f0 and f2) else 0.0
            a20 = D[n, 2, 0] if (f0 and f2) else 0.0
            a12 = D[n, 1, 2] if (f1 and f2) else 0.0
            a21 = D[n, 2, 1] if (f1 and f2) else 0.0
            c00 = a11 * a22 - a12 * a21
            c01 = a02 * a21 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            det = a00 * c00 + a10 * c01 + a20 * c02
            inv[0, 0], inv[0, 1], inv[0, 2] = c00 / det, c01 / det, c02 / det
            inv[1, 0] = (a12 * a20 - a10 * a22) / det
            inv[1, 1] = (a00 * a22 - a02 * a20) / det
            inv[1, 2] = (a02 * a10 - a00 * a12) / det
            inv[2, 0] = (a10 * a21 - a11 * a20) / det
            inv[2, 1] = (a01 * a20 - a00 * a21) / det
            inv[2, 2] = (a00 * a11 - a01 * a10) / det
            free = (f0, f1, f2)
            for i in range(3):
                for j in range(3):
                    if not (free[i] and free[j]):
                        inv[i, j] = 0.0
            w2 = ws * ws
            for k in range(3):
                x0, x1, x2 = F[r, 0, k], F[r, 1, k], F[r, 2, k]
                q = (x0 * (inv[0, 0] * x0 + inv[0, 1] * x1 + inv[0, 2] * x2)
                     + x1 * (inv[1, 0] * x0 + inv[1, 1] * x1 + inv[1, 2] * x2)
                     + x2 * (inv[2, 0] * x0 + inv[2, 1] * x1 + inv[2, 2] * x2))
                if k == 0:
                    o0 += w2 * q
                elif k == 1:
                    o1 += w2 * q
                else:
                    o2 += w2 * q
        out[r, 0], out[r, 1], out[r, 2] = o0, o1, o2


@_jit
def cone_law(vc: np.ndarray, R: np.ndarray, v_hat: np.ndarray, mu: np.ndarray, bilateral: np.ndarray, hessian: bool,
             gamma: np.ndarray, G: np.ndarray, cost: np.ndarray, stick: np.ndarray) -> None:
    """convex.cone_law row by row: the impulses gamma (m, 3), the cost's Hessian G (m, 3, 3) (if ``hessian``), the
    costs (m,) and whether each row sticks (m,) of rows with relative velocities vc (m, 3), regularisation R (m, 3),
    normal bias v_hat (m,), friction mu (m,), bilateral (m,) (Castro et al.'s projection on the Coulomb cone)."""
    for r in range(vc.shape[0]):
        i0, i1, i2 = 1.0 / R[r, 0], 1.0 / R[r, 1], 1.0 / R[r, 2]
        yn = -vc[r, 0] * i0 + v_hat[r] * i0
        y1, y2 = -vc[r, 1] * i1, -vc[r, 2] * i2
        yr = math.sqrt(y1 * y1 + y2 * y2)
        m_ = mu[r]
        mh = m_ * R[r, 1] * i0
        f = 1.0 / (1.0 + m_ * mh)
        bil = bilateral[r]
        rough = (not bil) and m_ > 0
        st = bil or (rough and yr <= m_ * yn)
        stick[r] = st
        g0 = g1 = g2 = 0.0
        sl = False
        if st:
            g0, g1, g2 = yn, y1, y2
        elif rough and yn > -mh * yr:
            sl = True
            gn = (yn + mh * yr) * f
            t1, t2 = (y1 / yr, y2 / yr) if yr > 0 else (0.0, 0.0)
            g0, g1, g2 = gn, m_ * gn * t1, m_ * gn * t2
        elif (not bil) and m_ == 0 and yn > 0:
            g0 = yn
        gamma[r, 0], gamma[r, 1], gamma[r, 2] = g0, g1, g2
        cost[r] = 0.5 * (g0 * R[r, 0] * g0 + g1 * R[r, 1] * g1 + g2 * R[r, 2] * g2)
        if not hessian:
            continue
        for i in range(3):
            for j in range(3):
                G[r, i, j] = 0.0
        if st:
            G[r, 0, 0], G[r, 1, 1], G[r, 2, 2] = i0, i1, i2
        elif sl:
            gn = g0
            t1, t2 = (y1 / yr, y2 / yr) if yr > 0 else (0.0, 0.0)
            # d gamma / d y (rows and columns n, t1, t2), times R^-1 from the right, symmetrised
            d00 = f
            d01, d02 = mh * f * t1, mh * f * t2
            d10, d20 = m_ * f * t1, m_ * f * t2
            c = gn / yr
            e = mh * f
            d11 = m_ * (c * (1.0 - t1 * t1) + e * t1 * t1)
            d12 = m_ * (c * (-t1 * t2) + e * t1 * t2)
            d21 = m_ * (c * (-t2 * t1) + e * t2 * t1)
            d22 = m_ * (c * (1.0 - t2 * t2) + e * t2 * t2)
            G[r, 0, 0] = d00 * i0
            G[r, 1, 1] = d11 * i1
            G[r, 2, 2] = d22 * i2
            G[r, 0, 1] = G[r, 1, 0] = 0.5 * (d01 * i1 + d10 * i0)
            G[r, 0, 2] = G[r, 2, 0] = 0.5 * (d02 * i2 + d20 * i0)
            G[r, 1, 2] = G[r, 2, 1] = 0.5 * (d12 * i2 + d21 * i1)
        elif (not bil) and m_ == 0 and yn > 0:
            G[r, 0, 0] = i0


@_jit
def scatter_rows(gnodes: np.ndarray, w: np.ndarray, f: np.ndarray, out: np.ndarray) -> None:
    """The rows' quantities f (m, k) onto their slots' nodes: out (N, k) = sum over rows and slots of w f[row] at
    gnodes (m, S) (zeroed first): convex._Newton's J_s^T products."""
    out[:] = 0.0
    m, S = gnodes.shape
    k = f.shape[1]
    for r in range(m):
        for s in range(S):
            ws = w[r, s]
            if ws == 0.0:
                continue
            n = gnodes[r, s]
            for j in range(k):
                out[n, j] += ws * f[r, j]


@_jit
def gather_rows(gnodes: np.ndarray, w: np.ndarray, X: np.ndarray, out: np.ndarray) -> None:
    """The nodes' values X (N, k) at the rows' points: out (m, k) = sum over the row's slots of w X[gnodes] (convex
    ._Newton's J_s products, its point velocities)."""
    m, S = gnodes.shape
    k = X.shape[1]
    for r in range(m):
        for j in range(k):
            total = 0.0
            for s in range(S):
                ws = w[r, s]
                if ws != 0.0:
                    total += ws * X[gnodes[r, s], j]
            out[r, j] = total


@_jit
def row_velocities(gnodes: np.ndarray, w: np.ndarray, V: np.ndarray, rigid_velocity: np.ndarray, frames: np.ndarray,
                   out: np.ndarray) -> None:
    """The rows' relative velocities in their frames: out (m, 3) = F^T (sum over the row's slots of w V[gnodes] -
    rigid_velocity) for soft velocities V (N, 3) (convex._Newton.velocities without the rigid unknowns)."""
    m, S = gnodes.shape
    for r in range(m):
        p0, p1, p2 = -rigid_velocity[r, 0], -rigid_velocity[r, 1], -rigid_velocity[r, 2]
        for s in range(S):
            ws = w[r, s]
            if ws != 0.0:
                n = gnodes[r, s]
                p0 += ws * V[n, 0]
                p1 += ws * V[n, 1]
                p2 += ws * V[n, 2]
        for j in range(3):
            out[r, j] = frames[r, 0, j] * p0 + frames[r, 1, j] * p1 + frames[r, 2, j] * p2


@_jit
def frame_hessians(F: np.ndarray, G: np.ndarray, out: np.ndarray) -> None:
    """out (m, 3, 3) = F G F^T per row, for the rows' frames F (m, 3, 3) and Hessians in them G (m, 3, 3)
    (convex._Newton._frame_hessians)."""
    m = F.shape[0]
    for r in range(m):
        for i in range(3):
            a0 = F[r, i, 0] * G[r, 0, 0] + F[r, i, 1] * G[r, 1, 0] + F[r, i, 2] * G[r, 2, 0]
            a1 = F[r, i, 0] * G[r, 0, 1] + F[r, i, 1] * G[r, 1, 1] + F[r, i, 2] * G[r, 2, 1]
            a2 = F[r, i, 0] * G[r, 0, 2] + F[r, i, 1] * G[r, 1, 2] + F[r, i, 2] * G[r, 2, 2]
            for j in range(3):
                out[r, i, j] = a0 * F[r, j, 0] + a1 * F[r, j, 1] + a2 * F[r, j, 2]


@_jit
def slot_pair_keys(gnodes: np.ndarray, w: np.ndarray, N: int) -> np.ndarray:
    """The node pairs the rows' slots join, as keys i * N + j with i < j (unsorted, repeats kept): the blocks the
    rows add to the Newton matrix off its diagonal (convex._Newton._extra_pairs)."""
    m, S = gnodes.shape
    out = np.empty(m * S * (S - 1) // 2 if S > 1 else 0, dtype=np.int64)
    n = 0
    for r in range(m):
        for s in range(S):
            if w[r, s] == 0.0:
                continue
            a = gnodes[r, s]
            for t in range(s + 1, S):
                if w[r, t] == 0.0:
                    continue
                b = gnodes[r, t]
                if a < b:
                    out[n] = a * N + b
                    n += 1
                elif b < a:
                    out[n] = b * N + a
                    n += 1
    return out[:n]


ENABLED = compilation.register(sys.modules[__name__], AVAILABLE, warmup="integration.warmup")
