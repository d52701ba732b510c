"""Contact between soft bodies, and of a soft body with itself: surface nodes against surface triangles.

A contact holds a node of body a against a point of a surface triangle of body b (barycentric weights w),
along the triangle's outward normal n; d = n . (x_a - sum_i w_i x_bi) is the signed distance (negative: the
node is inside b). The condition at the end of the step, n . (v_a - sum_i w_i v_bi) >= -d / h, and Coulomb
friction are those of the rigid contacts (contact.py); the impulse acts on both bodies, equal and opposite.
Both directions are searched (a's nodes on b's triangles, b's nodes on a's), so a corner pressing into a face
is caught from either side, and both contacts are kept (rows beside rows share a force in the coupled problem,
convex.py). Edges crossing between nodes: :func:`edge_contacts`.

A node counts against a triangle only inside the triangle's prism (its projection falls on the triangle,
not on the plane of an extended one), within reach (the margin plus what the two sides close along the
normal within the step, as collision.Sweep), and against the nearest such triangle of each other body that
faces it (a node lying in the plane of the other body's face, beside its edge, is no contact with the side face
beyond; a node of a face resting rim on rim on a face of the same size is held by that face, not by the side face
beyond the rim that lies nearer once the rims press in). Self-contact (a == b) also leaves out the node's own
surroundings (triangles within one rest edge length of it), and never pulls a node through the body: only
nodes on the outer side of a triangle count.

Broad phase: the bodies' boxes against each other's grown by their reach (one vectorised test), the nodes of
the bodies that meet a box against that box, then per body a k-d tree (scipy's cKDTree) over its triangles'
centres, queried with the nodes of the other bodies in its box; narrow phase vectorised over the candidate pairs
of all bodies at once (a pile of small bodies costs one query per body in reach of another, not one per pair and
direction). With the compiled kernels (integration.kernels), the same pairs from one uniform grid over all bodies'
triangle centres, node by node, and the narrow phases candidate by candidate; the numpy code is their reference
(tests/test_soft_search.py).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from . import kernels
from .collision import FACING, SOFT_SLACK, barycentric, node_incidence, read_only, run_starts, vertex_normals
from .distance import cross
from .segments import closest_between_segments, edge_normals, surface_edges

# a node's projection may fall this far outside a triangle (in barycentric weight) and still count on it, so
# that a node above the shared edge of two triangles is held by one of them
PRISM_TOL = 0.02
# key layout: node | (a * 1024 + b) << NODE_BITS, unique per contact and stable
NODE_BITS = 21


@dataclass
class SoftSurface:
    """A soft body's surface, fixed at construction: triangles (T, 3) outward, nodes (s,) (sorted), the
    triangles' longest rest edge (T,) [m], the node-triangle incidence (N, T) (for normals), and its edges
    (E, 2) with the triangles each bounds (E, 2) (segments.surface_edges)."""

    triangles: np.ndarray
    nodes: np.ndarray
    rest_edge: np.ndarray
    incidence: sp.csr_matrix
    edges: np.ndarray | None = None
    edge_tris: np.ndarray | None = None

    @classmethod
    def of(cls, rest: np.ndarray, triangles: np.ndarray) -> "SoftSurface":
        """The surface of a body with rest positions (N, 3) [m] and outward surface triangles (T, 3)."""
        triangles = np.asarray(triangles, np.int64)
        P = rest[triangles]
        longest = np.linalg.norm(P - np.roll(P, 1, axis=1), axis=2).max(axis=1)
        edges, edge_tris = surface_edges(triangles) if len(triangles) else (np.zeros((0, 2), np.int64),) * 2
        return cls(triangles, np.unique(triangles), longest, node_incidence(triangles, len(rest)), edges, edge_tris)

    def node_normals(self, x: np.ndarray) -> np.ndarray:
        """Area-weighted unit normals (N, 3) at the surface nodes for positions x (N, 3) (zero elsewhere)."""
        return vertex_normals(x, self.triangles, self.incidence)


_EMPTY_FIELDS = read_only(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                          np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                          np.zeros(0, np.int64))  # shared by every empty SoftHits


@dataclass
class SoftHits:
    """Node-against-triangle contacts between soft bodies (m entries): node (m,) of body a (m,) against the point
    with weights (m, 3) of triangle (m,) (its nodes (m, 3)) of body b (m,); normal (m, 3): the triangle's outward
    unit normal (from b towards a's node); distance (m,) signed [m]; key (m,): names the contact from step to
    step."""

    a: np.ndarray
    node: np.ndarray
    b: np.ndarray
    triangle: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    key: np.ndarray

    @classmethod
    def empty(cls) -> "SoftHits":
        """No hits (a fresh object over shared read-only empty arrays: made every step)."""
        return cls(*_EMPTY_FIELDS)

    def __len__(self) -> int:
        return len(self.node)

    def select(self, keep: np.ndarray) -> "SoftHits":
        return SoftHits(*(getattr(self, f.name)[keep] for f in fields(self)))

    @classmethod
    def concat(cls, parts: list["SoftHits"]) -> "SoftHits":
        parts = [h for h in parts if len(h)]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(h, f.name) for h in parts]) for f in fields(cls)))


def node_triangle_contacts(xa: np.ndarray, va: np.ndarray, nodes: np.ndarray, surface_a: SoftSurface,
                           xb: np.ndarray, vb: np.ndarray, surface: SoftSurface, margin: float, h: float,
                           depth: float, rest: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, ...]:
    """Nodes ``nodes`` of a body at xa (N_a, 3) moving with va (its surface ``surface_a``) against the surface
    triangles of a body at xb (N_b, 3) moving with vb: per node the nearest triangle that faces the node's own
    surface (normals more than ~95 degrees apart) and whose prism holds it, with a signed distance in
    (-depth, reach) [m] (reach: ``margin`` plus what the two close along the normal within the step h [s]).

    rest: (rest positions of a, rest positions of b) for self-contact (the same body): leaves out triangles
    within one rest edge length of the node, and nodes more than the margin inside (never pulled through a
    wall).
    Returns (node (m,), triangle (m,), weights (m, 3), normal (m, 3), distance (m,))."""
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    tris = surface.triangles
    if not len(nodes) or not len(tris):
        return none
    P = xb[tris]  # (T, 3, 3)
    centre = P.mean(axis=1)
    radius = np.sqrt(((P - centre[:, None]) ** 2).sum(axis=2).max(axis=1))
    speed_b = np.sqrt((vb[tris] ** 2).sum(axis=2).max(axis=1))
    speed_a = np.sqrt((va[nodes] ** 2).sum(axis=1))
    travel_a, travel_b = SOFT_SLACK * h * speed_a, SOFT_SLACK * h * speed_b
    reach_max = margin + depth + radius.max() + travel_a.max() + travel_b.max()
    x = xa[nodes]
    pairs = cKDTree(x).sparse_distance_matrix(cKDTree(centre), reach_max, output_type="ndarray")
    if not len(pairs):
        return none
    i, t = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    ok = pairs["v"] <= margin + depth + radius[t] + travel_a[i] + travel_b[t]
    i, t = i[ok], t[ok]
    if rest is not None:  # self-contact: not against the node's own surroundings
        ra, rb = rest
        gap = ra[nodes[i]] - np.clip(ra[nodes[i]], rb[tris[t]].min(axis=1), rb[tris[t]].max(axis=1))
        far = np.einsum("ij,ij->i", gap, gap) > (1.01 * surface.rest_edge[t]) ** 2
        i, t = i[far], t[far]
    if not len(i):
        return none
    A, B, C = P[t, 0], P[t, 1], P[t, 2]
    nrm = cross(B - A, C - A)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    xi = x[i]
    d = np.einsum("ij,ij->i", xi - A, nrm)
    w = barycentric(xi - d[:, None] * nrm, A, B, C)
    inside = (w >= -PRISM_TOL).all(axis=1)
    w = np.clip(w, 0.0, None)
    w /= w.sum(axis=1, keepdims=True)
    # surfaces facing each other only: a node on a face lying in the plane of the other body's face, next to
    # its edge (a block sliding over another's surface), is no contact with the side face beyond that edge; and a
    # node of a face resting on a face of the same size, rim on rim, is held by that face, not by the side face
    # beyond the rim that may lie nearer once the rims press into each other
    facing = np.einsum("ij,ij->i", surface_a.node_normals(xa)[nodes[i]], nrm) < FACING
    ok = inside & facing if rest is not None else inside  # self-contact: facing triangles only
    i, t, w, nrm, d, facing = i[ok], t[ok], w[ok], nrm[ok], d[ok], facing[ok]
    if not len(i):
        return none
    first = nearest_facing(i, t, d, facing, margin)
    i, t, w, nrm, d, facing = i[first], t[first], w[first], nrm[first], d[first], facing[first]
    v_rel = va[nodes[i]] - np.einsum("ms,msi->mi", w, vb[tris[t]])
    closing = np.maximum(-np.einsum("ij,ij->i", v_rel, nrm), 0.0)
    ok = facing & (d < margin + SOFT_SLACK * h * closing) & (d > (-margin if rest is not None else -depth))
    return nodes[i[ok]], t[ok], w[ok], nrm[ok], d[ok]


def nearest_facing(group: np.ndarray, t: np.ndarray, d: np.ndarray, facing: np.ndarray, margin: float) -> np.ndarray:
    """Per group (a node, against one other body) of candidate triangles t with signed distances d and whether they
    face the node: the index of the nearest facing one, if it lies within ``margin`` of the nearest of all (which
    decides whether the node is inside: a node below a body is no contact with its far top face; a node of a face
    resting rim on rim on another is held by that face, not by the side face beyond the rim that may lie nearer once
    the rims press in). Ties go to the smaller triangle index."""
    order = np.lexsort((t, np.abs(d), group))
    starts = run_starts(group[order])
    run = np.cumsum(starts) - 1
    nearest = np.abs(d[order])[starts][run]  # the nearest of its group, for each candidate in order
    ok = facing[order] & (np.abs(d[order]) <= nearest + margin)
    cand = order[ok]
    return cand[run_starts(group[cand])] if len(cand) else cand


@dataclass(frozen=True)
class SoftLayout:
    """What the soft search needs of its bodies' surfaces and pairs, fixed while they are: the ``used`` bodies (B,)
    (those in some pair, ascending), ``rank`` (B, B) the output order of each searched direction (p's nodes against
    q's triangles; -1: not searched), their surface node counts ``s_of`` (B,), each surface node's body ``node_b``
    and each body's first surface node ``starts`` (B,) in the concatenation of their surface nodes; the used bodies'
    first nodes ``node_off`` (B,) in the concatenation of all their nodes, their surface nodes ``nodes`` (S,) and
    triangles ``tris`` (T, 3) in that numbering (each body's first ``t_off`` (B,), their bodies ``tri_b`` (T,),
    longest rest edges ``rest_edge`` (T,) and node-triangle ``incidence`` (all nodes, T)); for the edge search,
    their edges ``edges`` (E, 2) (each body's own node numbering), ``edge_b`` (E,) (rows of ``used``), ``edge_of``
    (E,) (the index among its body's edges) and ``edge_tris`` (E, 2) (rows of ``tris``, -1: none). No used bodies
    (``used`` empty) when a body in a pair has no surface."""

    used: np.ndarray
    rank: np.ndarray
    s_of: np.ndarray
    node_b: np.ndarray
    starts: np.ndarray
    node_off: np.ndarray | None = None
    nodes: np.ndarray | None = None
    tris: np.ndarray | None = None
    t_off: np.ndarray | None = None
    tri_b: np.ndarray | None = None
    rest_edge: np.ndarray | None = None
    incidence: sp.csr_matrix | None = None
    edges: np.ndarray | None = None
    edge_b: np.ndarray | None = None
    edge_of: np.ndarray | None = None
    edge_tris: np.ndarray | None = None

    @classmethod
    def of(cls, surfaces: list[SoftSurface], pairs: list[tuple[int, int]]) -> "SoftLayout":
        """The layout of the bodies with ``surfaces`` for the index ``pairs`` (a, b) (see soft_contacts)."""
        P_ = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        used = np.unique(P_)
        row = np.full(len(surfaces), -1)
        row[used] = np.arange(len(used))
        B = len(used)
        rank = np.full((B, B), -1)
        k2 = 2 * np.arange(len(P_))
        rank[row[P_[:, 1]], row[P_[:, 0]]] = k2 + 1
        rank[row[P_[:, 0]], row[P_[:, 1]]] = k2
        s_of = np.array([len(surfaces[k].nodes) for k in used.tolist()], dtype=np.int64)
        if not s_of.all():
            used = used[:0]
        starts = np.concatenate([[0], np.cumsum(s_of)[:-1]]).astype(np.int64)
        sfs = [surfaces[k] for k in used.tolist()]
        n_of = np.array([sf.incidence.shape[0] for sf in sfs], dtype=np.int64)
        node_off = np.concatenate([[0], np.cumsum(n_of)[:-1]]).astype(np.int64)
        t_off = np.concatenate([[0], np.cumsum([len(sf.triangles) for sf in sfs])[:-1]]).astype(np.int64)
        tris = (np.concatenate([sf.triangles + o for sf, o in zip(sfs, node_off)]) if sfs
                else np.zeros((0, 3), np.int64))
        nodes = np.concatenate([sf.nodes + o for sf, o in zip(sfs, node_off)]) if sfs else np.zeros(0, np.int64)
        edge_sets = [sf.edges if sf.edges is not None else np.zeros((0, 2), np.int64) for sf in sfs]
        edges = np.concatenate(edge_sets) if sfs else np.zeros((0, 2), np.int64)
        edge_b = np.repeat(np.arange(B), [len(e) for e in edge_sets]).astype(np.int64)
        edge_of = np.concatenate([np.arange(len(e)) for e in edge_sets]).astype(np.int64) if sfs else edge_b
        edge_tris = (np.concatenate([np.where(sf.edge_tris >= 0, sf.edge_tris + o, -1) if sf.edge_tris is not None
                                     else np.zeros((0, 2), np.int64) for sf, o in zip(sfs, t_off)])
                     if sfs else np.zeros((0, 2), np.int64))
        t_of = np.array([len(sf.triangles) for sf in sfs], dtype=np.int64)
        rest_edge = np.concatenate([sf.rest_edge for sf in sfs]) if sfs else np.zeros(0)
        incidence = node_incidence(tris, int(n_of.sum()))
        return cls(used, rank, s_of, np.repeat(np.arange(B), s_of), starts, node_off, nodes, tris, t_off,
                   np.repeat(np.arange(B), t_of), rest_edge, incidence, edges, edge_b, edge_of, edge_tris)


class FirstPass:
    """The compiled node-face search's first-pass candidates kept from step to step (soft_contacts' ``kept``, the
    caller's to hold): found with every reach widened by SKIN and the state they were found in (the surface nodes'
    positions, their travels, the bodies' means' travels, the triangles' largest travels), they hold every candidate a
    later step's search would find while the nodes have moved by D and the travels grown by dT with 4.2 D + dT <=
    SKIN (a candidate's node and triangle centre close by at most 2 D, the triangle's radius grows by at most 2 D,
    times 1.1), and are filtered by that step's exact conditions: the same contacts as a search of that step, without
    its grid (a resting pile searches it once). Only the pairs that can give a node its nearest triangle within the
    first pass's reach are kept: a triangle whose prism holds the node (to PRISM_TOL) with |d| within the reach lies
    within |d| + 2 PRISM_TOL L of it (L its longest edge), and the distance changes by at most 2 D (a resting stack:
    19,000 pairs -> 7,000). Made anew, for the layout it was found for only."""

    #: the reach added to the first pass's when its candidates are found [m]
    SKIN = 1e-3

    def __init__(self) -> None:
        self.layout = None
        self.found = 0  # grid searches made
        self.served = 0  # steps served from the kept candidates

    def serves(self, layout, xs: np.ndarray, travel_a: np.ndarray, between: np.ndarray, tb_max: np.ndarray) -> bool:
        """Whether the kept candidates hold every candidate of a search of ``layout`` in this state."""
        if self.layout is not layout or self.xs.shape != xs.shape:
            return False
        moved = float(np.sqrt(np.einsum("ij,ij->i", xs - self.xs, xs - self.xs).max(initial=0.0)))
        grown = sum(float(np.max(now - then, initial=0.0)) for now, then in
                    ((travel_a, self.travel_a), (between, self.between), (tb_max, self.tb_max)))
        return 4.2 * moved + grown <= self.SKIN

    def keep(self, layout, xs, travel_a, between, tb_max, i: np.ndarray, t: np.ndarray) -> None:
        self.layout, self.xs, self.travel_a, self.between, self.tb_max = layout, xs.copy(), travel_a, between, tb_max
        self.i, self.t = i, t


def soft_contacts(bodies: list[tuple[np.ndarray, np.ndarray, SoftSurface, np.ndarray]], pairs: list[tuple[int, int]],
                  margin: float, h: float, depth: float, layout: SoftLayout | None = None,
                  kept: FirstPass | None = None) -> SoftHits:
    """Contacts between the soft bodies ``bodies`` (positions (N, 3), velocities (N, 3), surface, rest
    positions (N, 3)) for the index ``pairs`` (a, b) (a == b: self-contact), both directions of each pair of
    distinct bodies, in one pass over all of them (one query per body that other nodes reach, one narrow phase
    for all; compiled: one grid over all triangles, see the module doc). The same contacts, in the same order, as
    :func:`pair_contacts_reference` (a search per pair and direction, kept for the tests). ``layout``:
    SoftLayout.of their surfaces and pairs, if kept from an earlier step (the caller's to renew when they change);
    ``kept``: the compiled first pass's candidates from step to step (FirstPass; None: searched anew)."""
    if not pairs:
        return SoftHits.empty()
    layout = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs) if layout is None else layout
    if not len(layout.used):
        return SoftHits.empty()
    rank, s_of, node_b, starts = layout.rank, layout.s_of, layout.node_b, layout.starts
    B = len(layout.used)
    data = [bodies[k] for k in layout.used.tolist()]
    # every body's box, grown by its reach: a node counts against a body only inside its box
    xs = np.concatenate([x.take(sf.nodes, axis=0) for x, _, sf, _ in data])
    vs = np.concatenate([v.take(sf.nodes, axis=0) for _, v, sf, _ in data])
    # motions relative to each body's mean (a pile falling together closes nothing): a node's travel against another
    # body's triangle is bounded by its own about its body's mean, the triangle's about its, and the two means'
    mean_v = np.add.reduceat(vs, starts) / s_of[:, None]
    rel = vs - np.repeat(mean_v, s_of, axis=0)
    travel_a = SOFT_SLACK * h * np.sqrt(np.einsum("ij,ij->i", rel, rel))
    own = np.maximum.reduceat(travel_a, starts)  # per body, its nodes' largest travel about its mean
    between = SOFT_SLACK * h * np.sqrt(((mean_v[:, None] - mean_v[None]) ** 2).sum(axis=2))  # (B, B)
    grow = margin + depth + own[:, None] + own[None] + between  # (B, B): p's nodes against q's triangles
    plo, phi = np.minimum.reduceat(xs, starts), np.maximum.reduceat(xs, starts)  # the nodes' boxes

    def meeting(g: np.ndarray) -> np.ndarray:
        """(B, B), p by q: the directions that can meet, searched and p's nodes' box within q's grown by g (B, B)."""
        return (rank >= 0) & ~((plo[:, None] > phi[None] + g[:, :, None])
                               | (phi[:, None] < plo[None] - g[:, :, None])).any(axis=2)

    meet = meeting(grow)
    reached = np.flatnonzero(meet.any(axis=0))
    if not len(reached):
        return SoftHits.empty()
    # all bodies' arrays, one numbering (node ids offset by the bodies before)
    off, nodes, tris, t_off, tri_b = layout.node_off, layout.nodes, layout.tris, layout.t_off, layout.tri_b
    X = np.concatenate([x for x, _, _, _ in data])
    V = np.concatenate([v for _, v, _, _ in data])
    t_of = np.diff(np.append(t_off, len(tris)))
    # broad phase: per body q, the nodes of the bodies searched against it that lie in its grown box, against a
    # k-d tree of its triangles' bounding spheres (bodies with no such nodes cost nothing more), in two passes.
    # The first reaches a node's own margin and closing only (rho: the triangles within rho of it, all of them);
    # where it finds a triangle whose prism holds the node within rho, that triangle is the node's nearest (any
    # nearer lies within rho too). Only the nodes left, inside q's box (a node outside it cannot be inside q),
    # are searched again as deep as a node may lie inside (depth): in a pile, the few that are. Compiled: one
    # uniform grid over all bodies' triangle centres, node by node (kernels.soft_candidates), the same pairs.
    R = np.concatenate([r for _, _, _, r in data])
    rest_edge = layout.rest_edge
    vnormals = None

    def query(q: int, sel: np.ndarray, first: bool) -> tuple[np.ndarray, np.ndarray]:
        """Candidates (node, triangle) of nodes sel against q's triangles: within the reach of a contact as deep as
        depth; in the first pass also within rho (+ q's travel) of the triangle (1.1 radius: the prism's slack)."""
        span = slice(t_off[q], t_off[q] + t_of[q])
        centre_q, radius_q, travel_q = centre[span], radius[span], travel_b[span]
        ta = travel_a[sel] + between[node_b[sel], q]  # the nodes' travel against q
        reach = margin + depth + radius_q.max() + ta.max() + travel_q.max()
        if first:
            rho = margin + ta + travel_q.max()
            reach = min(reach, rho.max() + 1.1 * radius_q.max())
        found = cKDTree(xs[sel]).sparse_distance_matrix(cKDTree(centre_q), reach, output_type="ndarray")
        k, t = found["i"], found["j"].astype(np.int64)
        i = sel[k]
        ok = found["v"] <= margin + depth + radius_q[t] + ta[k] + travel_q[t]
        if first:
            ok &= found["v"] <= rho[k] + 1.1 * radius_q[t]
        return i[ok], t[ok] + t_off[q]

    def nearest(i: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per node and other body, the nearest facing triangle whose prism holds it."""
        nonlocal vnormals
        if kernels.ENABLED:  # the lines below, candidate by candidate (integration.kernels)
            if vnormals is None:  # the surface normals at the nodes in question only
                vnormals = np.zeros((len(X), 3))
            mark = np.zeros(len(X), dtype=bool)
            mark[nodes[i]] = True
            at = np.flatnonzero(mark)
            found = np.empty((len(at), 3))
            kernels.node_normals_at(X, tris, layout.incidence.indptr, layout.incidence.indices, at, found)
            vnormals[at] = found
            m = len(i)
            w, nrm, d, facing = np.empty((m, 3)), np.empty((m, 3)), np.empty(m), np.empty(m, dtype=bool)
            k = kernels.soft_nearest(xs, X, tris, nodes, node_b, tri_b, R, rest_edge, vnormals, i, t, margin,
                                     len(bodies), PRISM_TOL, FACING, w, nrm, d, facing)
            i, t = i[k], t[k]
            pb, qb = node_b[i], tri_b[t]
            return i, t, pb, qb, pb == qb, w[k], nrm[k], d[k], facing[k]
        if vnormals is None:
            vnormals = vertex_normals(X, tris, layout.incidence)
        pb, qb = node_b[i], tri_b[t]
        same = pb == qb
        if same.any():  # self-contact: not against the node's own surroundings
            rn, rt = R[nodes[i[same]]], R[tris[t[same]]]
            gap = rn - np.clip(rn, rt.min(axis=1), rt.max(axis=1))
            far = np.ones(len(i), dtype=bool)
            far[same] = np.einsum("ij,ij->i", gap, gap) > (1.01 * rest_edge[t[same]]) ** 2
            i, t, pb, qb, same = i[far], t[far], pb[far], qb[far], same[far]
        P = X[tris[t]]
        A, Bv, C = P[:, 0], P[:, 1], P[:, 2]
        nrm = cross(Bv - A, C - A)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        xi = xs[i]
        d = np.einsum("ij,ij->i", xi - A, nrm)
        w = barycentric(xi - d[:, None] * nrm, A, Bv, C)
        inside = (w >= -PRISM_TOL).all(axis=1)
        w = np.clip(w, 0.0, None)
        w /= w.sum(axis=1, keepdims=True)
        facing = np.einsum("ij,ij->i", vnormals[nodes[i]], nrm) < FACING
        ok = inside & (facing | ~same)  # self-contact: facing triangles only
        i, t, pb, qb, same, w, nrm, d, facing = (a[ok] for a in (i, t, pb, qb, same, w, nrm, d, facing))
        first = nearest_facing(i.astype(np.int64) * len(bodies) + qb, t, d, facing, margin)
        return tuple(a[first] for a in (i, t, pb, qb, same, w, nrm, d, facing))

    # every triangle's bounding sphere and largest travel about its body's mean (one pass over all bodies)
    if kernels.ENABLED:
        centre, radius, travel_b = np.empty((len(tris), 3)), np.empty(len(tris)), np.empty(len(tris))
        extent = kernels.triangle_spheres(X, V, tris, tri_b, mean_v, SOFT_SLACK * h, centre, radius, travel_b)
    else:
        P = X[tris]  # (T, 3, 3)
        centre = P.mean(axis=1)
        radius = np.sqrt(((P - centre[:, None]) ** 2).sum(axis=2).max(axis=1))
        travel_b = SOFT_SLACK * h * np.sqrt(((V[tris] - mean_v[tri_b][:, None]) ** 2).sum(axis=2).max(axis=1))
    tb_max = np.maximum.reduceat(travel_b, t_off)  # per body, its triangles' largest travel about its mean
    grid = None
    if kernels.ENABLED:  # both passes node by node over one grid of all triangles' centres (integration.kernels)
        def made_grid(widen: float) -> tuple:
            cell = margin + widen + 1.1 * float(radius.max()) + float(tb_max.max())  # a resting node's first-pass reach
            cell = max(cell, extent / (2 ** 21 - 2), 1e-9)  # 21 bits a key per axis
            return (cell,) + kernels.centre_grid(centre, cell)

        if kept is not None and kept.serves(layout, xs, travel_a, between, tb_max):
            kept.served += 1
            # this step's candidates among them, and the deep pass's nodes, as soft_candidates finds them
            first_i, first_t, deep_i, deep_q = kernels.first_pass_among(
                kept.i, kept.t, xs, node_b, travel_a, between, meet, grow, plo, phi, centre, radius, travel_b, tri_b,
                tb_max, margin, depth)
        elif kept is not None:  # every reach widened: the candidates of later steps too (FirstPass)
            widen = kept.SKIN
            grid = made_grid(widen)
            first_i, first_t, deep_i, deep_q = kernels.soft_candidates(
                xs, node_b, travel_a, between, meeting(grow + widen), grow + widen, plo, phi, centre, radius,
                travel_b, tri_b, tb_max, margin + widen, depth, *grid)
            kept.found += 1
            # only the triangles that can be a node's nearest within the first pass's reach while they serve: a
            # triangle whose prism holds the node (to PRISM_TOL) within |d| lies within |d| + 2 PRISM_TOL L of it
            dist = np.empty(len(first_i))
            kernels.triangle_distances(xs, X, tris, first_i, first_t, dist)
            P = X[tris]
            longest = np.sqrt(np.max([np.einsum("ij,ij->i", P[:, j] - P[:, j - 1], P[:, j] - P[:, j - 1])
                                      for j in range(3)], axis=0))
            qb = tri_b[first_t]
            reach = (margin + travel_a[first_i] + between[node_b[first_i], qb] + tb_max[qb]
                     + 2.0 * PRISM_TOL * longest[first_t] + widen)
            near = dist <= reach
            kept.keep(layout, xs, travel_a, between, tb_max, first_i[near], first_t[near])
            first_i, first_t, _, _ = kernels.first_pass_among(  # this step's among them
                kept.i, kept.t, xs, node_b, travel_a, between, meet, grow, plo, phi, centre, radius, travel_b,
                tri_b, tb_max, margin, depth)
        else:
            grid = made_grid(0.0)
            first_i, first_t, deep_i, deep_q = kernels.soft_candidates(
                xs, node_b, travel_a, between, meet, grow, plo, phi, centre, radius, travel_b, tri_b, tb_max,
                margin, depth, *grid)
        if not len(first_i) and not len(deep_i):
            return SoftHits.empty()
    else:
        first_i, first_t, deep_i, deep_q = [], [], [], []
        for q in reached.tolist():
            near = np.flatnonzero(meet[:, q])  # the bodies whose nodes may lie in q's grown box, and those nodes
            sel = np.concatenate([np.arange(starts[p], starts[p] + s_of[p]) for p in near.tolist()])
            g = grow[node_b[sel], q][:, None]
            sel = sel[((xs[sel] >= plo[q] - g) & (xs[sel] <= phi[q] + g)).all(axis=1)]
            if not len(sel):
                continue
            i, t = query(q, sel, True)
            first_i.append(i)
            first_t.append(t)
            inbox = sel[(node_b[sel] != q) & ((xs[sel] >= plo[q]) & (xs[sel] <= phi[q])).all(axis=1)]
            deep_i.append(inbox)
            deep_q.append(np.full(len(inbox), q))
        if not first_i:
            return SoftHits.empty()
        first_i, first_t, deep_i, deep_q = (np.concatenate(z) for z in (first_i, first_t, deep_i, deep_q))
    i, t, pb, qb, same, w, nrm, d, facing = nearest(first_i, first_t)
    # the nodes to search again: inside a body's box and not settled by the first pass (a first-pass nearest
    # farther than rho is no contact: outside the box the node is not inside the body, and beyond its reach)
    settled = np.abs(d) <= margin + travel_a[i] + between[pb, qb] + tb_max[qb]
    i, t, pb, qb, same, w, nrm, d, facing = (a[settled] for a in (i, t, pb, qb, same, w, nrm, d, facing))
    if len(deep_i):  # not those the first pass settled against that body
        settled_at = np.zeros((len(xs), B), dtype=bool)
        settled_at[i, qb] = True
        deep = ~settled_at[deep_i, deep_q]
        deep_i, deep_q = deep_i[deep], deep_q[deep]
    if len(deep_i):
        if kernels.ENABLED:
            grid = made_grid(0.0) if grid is None else grid
            again = kernels.soft_deep_candidates(xs, node_b, travel_a, between, deep_i, deep_q, centre, radius,
                                                 travel_b, tri_b, margin, depth, *grid)
        else:
            again = [np.concatenate(z) for z in zip(*(query(q, deep_i[deep_q == q], False)
                                                      for q in np.unique(deep_q).tolist()))]
        second = nearest(*again)
        i, t, pb, qb, same, w, nrm, d, facing = (np.concatenate([a, b]) for a, b in
                                                 zip((i, t, pb, qb, same, w, nrm, d, facing), second))
    if not len(i):
        return SoftHits.empty()
    v_rel = V[nodes[i]] - np.einsum("ms,msi->mi", w, V[tris[t]])
    closing = np.maximum(-np.einsum("ij,ij->i", v_rel, nrm), 0.0)
    ok = facing & (d < margin + SOFT_SLACK * h * closing) & (d > np.where(same, -margin, -depth))
    i, t, pb, qb, w, nrm, d = (a[ok] for a in (i, t, pb, qb, w, nrm, d))
    node = nodes[i] - off[pb]
    order = np.lexsort((node, rank[pb, qb]))  # pair by pair as given, each direction by node
    i, t, pb, qb, w, nrm, d, node = (a[order] for a in (i, t, pb, qb, w, nrm, d, node))
    a, b = layout.used[pb], layout.used[qb]
    # a contact is a node against the other body (its nearest triangle may change from step to step as it
    # slides; its friction state goes on)
    key = node | ((a * 1024 + b) << NODE_BITS)
    return SoftHits(a, node, b, t - t_off[qb], tris[t] - off[qb][:, None], w, nrm, d, key)


def pair_contacts_reference(bodies: list[tuple[np.ndarray, np.ndarray, SoftSurface, np.ndarray]],
                            pairs: list[tuple[int, int]], margin: float, h: float, depth: float) -> SoftHits:
    """:func:`soft_contacts` pair by pair and direction by direction (node_triangle_contacts for each): the
    reference the one-pass search is tested against."""
    out = []
    for a, b in pairs:
        for p, q in ((a, b), (b, a)) if a != b else ((a, a),):
            xp, vp, sp, rp = bodies[p]
            xq, vq, sq, rq = bodies[q]
            xs_q, vs_q = xq[sq.nodes], vq[sq.nodes]
            grow = margin + depth + SOFT_SLACK * h * float(np.sqrt(np.einsum("ij,ij->i", vs_q, vs_q).max(initial=0.0)))
            lo, hi = xs_q.min(axis=0) - grow, xs_q.max(axis=0) + grow
            cand = sp.nodes[np.all((xp[sp.nodes] >= lo) & (xp[sp.nodes] <= hi), axis=1)]
            node, tri, w, nrm, d = node_triangle_contacts(xp, vp, cand, sp, xq, vq, sq, margin, h, depth,
                                                          (rp, rq) if p == q else None)
            m = len(node)
            if m:
                key = node | (np.int64(p * 1024 + q) << NODE_BITS)
                out.append(SoftHits(np.full(m, p), node, np.full(m, q), tri, sq.triangles[tri], w, nrm, d, key))
    return SoftHits.concat(out)


# an edge crossing counts between the ends of both edges only (within this fraction of an end it is the node's own
# node-against-face contact), and between edges more than ~6 degrees apart (the closest points of nearly parallel
# edges are their nodes', held by those nodes' contacts)
EDGE_END = 0.02
EDGE_SIN = 0.1
EDGE_BITS = 21  # edge-edge key: 1 << 62 | (a * 1024 + b) << 2 EDGE_BITS | edge of a << EDGE_BITS | edge of b

_EMPTY_EDGE_FIELDS = read_only(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4), np.int64),
                               np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


@dataclass
class EdgeHits:
    """Edge-against-edge contacts between soft bodies (m entries): a point of an edge of body a (m,) against a point
    of an edge of body b (m,); nodes (m, 4): a's edge's two nodes, then b's; weights (m, 4): (1 - s, s, -(1 - t),
    -t) for the points' parameters s, t along the edges, so that a row's value is the velocity of a's point
    relative to b's; normal (m, 3): unit, from b's edge towards a's (along their cross product); distance (m,)
    signed [m] (negative: crossed); key (m,): names the crossing from step to step."""

    a: np.ndarray
    b: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    key: np.ndarray

    @classmethod
    def empty(cls) -> "EdgeHits":
        return cls(*_EMPTY_EDGE_FIELDS)

    def __len__(self) -> int:
        return len(self.a)


def _node_gaps(explained: SoftHits | tuple[np.ndarray, np.ndarray] | None, node: np.ndarray, a: np.ndarray,
               b: np.ndarray) -> np.ndarray:
    """The signed gaps [m] of nodes ``node`` of bodies ``a`` to bodies ``b`` (broadcast together) that
    node-against-face contacts in ``explained`` hold, inf where there is none (``explained`` may be given as its
    keys sorted and their distances, :func:`_gap_table`, when asked many times)."""
    want = np.asarray(node | ((a * 1024 + b) << NODE_BITS), dtype=np.int64)
    out = np.full(want.shape, np.inf)
    if explained is None or not want.size:
        return out
    keys, dist = explained if isinstance(explained, tuple) else _gap_table(explained)
    if not len(keys):
        return out
    at = np.clip(np.searchsorted(keys, want), 0, len(keys) - 1)
    found = keys[at] == want
    out[found] = dist[at[found]]
    return out


def _gap_table(explained: SoftHits) -> tuple[np.ndarray, np.ndarray]:
    """The keys of the contacts ``explained`` sorted, and their distances in that order (for _node_gaps)."""
    order = np.argsort(explained.key, kind="stable")
    return explained.key[order], explained.distance[order]


def edges_near(edges: np.ndarray, edge_b: np.ndarray, X: np.ndarray, node_off: np.ndarray, lo: np.ndarray,
               hi: np.ndarray, meet: np.ndarray, between: np.ndarray, keys: np.ndarray, used: np.ndarray,
               node_bits: int = NODE_BITS) -> np.ndarray:
    """(E,) whether an edge of ``edges`` (E, 2) (its body's node numbering) of body ``edge_b`` (E,) (rows of the
    bodies' boxes lo, hi (B, 3)) at positions X (its node offset node_off[body] into X) has its box meet the box of a
    body q it meets (meet (B, B)) grown by between[p, q] [m], with neither end in a node contact with q (``keys``: the
    node contacts' keys sorted, _gap_table's; empty: none; the keys name bodies by ``used`` (B,)): edge_contacts'
    broad phase (integration.kernels.edges_near, edge by edge; ``node_bits``: the keys' layout, NODE_BITS, which
    this numpy twin takes as given)."""
    off = node_off[edge_b]
    e0, e1 = X[edges[:, 0] + off], X[edges[:, 1] + off]
    elo, ehi = np.minimum(e0, e1), np.maximum(e0, e1)
    near = np.zeros(len(edges), dtype=bool)
    table = (keys, np.zeros(len(keys))) if len(keys) else None
    for q in range(len(lo)):
        mine = meet[edge_b, q] & ~near
        if not mine.any():
            continue
        g = between[edge_b, q][:, None]
        inside = np.flatnonzero(mine & ((elo <= hi[q] + g) & (ehi >= lo[q] - g)).all(axis=1))
        if len(inside) and table is not None:
            # not where an end has a node contact with q already (edge_narrow drops those pairs with q): in a stack
            # or a pile, most edges near a neighbour lie in the faces that touch it
            free = np.isinf(_node_gaps(table, edges[inside], used[edge_b[inside]][:, None], used[q]))
            inside = inside[free.all(axis=1)]
        near[inside] = True
    return near


def edge_candidates(mid: np.ndarray, body: np.ndarray, rank: np.ndarray, meet: np.ndarray, slack: np.ndarray,
                    radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pairs (i, j) of edges with midpoints mid (E, 3) of bodies ``body`` (E,) (rows of rank (B, B)):
    for each searched pair of bodies (p, q) (rank[p, q] even: listed as (p, q); p == q: self-contact, i < j) that
    meet (meet (B, B)), the midpoints within radius + slack[p, q] [m] of each other; ordered by the pair's rank, then
    i, then j (integration.kernels.edge_candidates over one grid of all midpoints; here a k-d tree per body)."""
    out_i, out_j, out_r = [], [], []
    trees: dict[int, cKDTree] = {}
    where = {int(p): np.flatnonzero(body == p) for p in np.unique(body).tolist()}

    def tree(p):
        if p not in trees:
            trees[p] = cKDTree(mid[where[p]])
        return trees[p]

    for p, q in zip(*np.nonzero((rank >= 0) & (rank % 2 == 0) & meet)):
        p, q = int(p), int(q)
        if p not in where or q not in where:
            continue
        if p == q:
            got = tree(p).query_pairs(radius + slack[p, q], output_type="ndarray")
            fi, fj = got[:, 0], got[:, 1]
        else:
            got = tree(p).sparse_distance_matrix(tree(q), radius + slack[p, q], output_type="ndarray")
            fi, fj = got["i"], got["j"]
        out_i.append(where[p][fi.astype(np.int64)])
        out_j.append(where[q][fj.astype(np.int64)])
        out_r.append(np.full(len(fi), rank[p, q]))
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j, r = np.concatenate(out_i), np.concatenate(out_j), np.concatenate(out_r)
    order = np.lexsort((j, i, r))
    return i[order], j[order]


def edge_narrow(i: np.ndarray, j: np.ndarray, P0: np.ndarray, P1: np.ndarray, V0: np.ndarray, V1: np.ndarray,
                N: np.ndarray, R0: np.ndarray, R1: np.ndarray, half: np.ndarray, travel: np.ndarray,
                body_of: np.ndarray, ends: np.ndarray, mean_v: np.ndarray, keys: np.ndarray, node_bits: int,
                margin: float, reach: float, depth: float, slack_h: float, edge_sin: float = EDGE_SIN,
                edge_end: float = EDGE_END) -> tuple[np.ndarray, ...]:
    """edge_contacts' narrow phase over the candidate edge pairs (i, j) (m,) (edges with ends P0, P1 (E, 3), their
    velocities about their body's mean V0, V1, outward normals N, rest ends R0, R1, half lengths, travels, bodies
    body_of (E,), nodes ends (E, 2); the bodies' mean velocities mean_v (B, 3), indexed by body; the node contacts'
    keys sorted): within reach, not the edge's own surroundings (self-contact), no end in a node contact with the
    other body, not nearly parallel, closest points between the ends of both, facing, within reach and less than
    depth crossed. Returns (the kept candidates (k,), s (k,), t (k,), normal (k, 3) from b's edge towards a's,
    distance (k,) signed [m]) (integration.kernels.edge_narrow, pair by pair; ``node_bits``: the keys' layout,
    NODE_BITS, which this numpy twin takes as given)."""
    explained = (keys, np.zeros(len(keys))) if len(keys) else None
    idx = np.arange(len(i))
    mid = 0.5 * (P0 + P1)
    gap = mid[i] - mid[j]
    means = mean_v[body_of[i]] - mean_v[body_of[j]]  # the bodies' mean velocities' difference, per pair
    ok = (np.sqrt(np.einsum("ij,ij->i", gap, gap)) <= half[i] + half[j] + reach + travel[i] + travel[j]
          + slack_h * np.sqrt(np.einsum("ij,ij->i", means, means)))
    i, j, idx = i[ok], j[ok], idx[ok]
    same = body_of[i] == body_of[j]
    if same.any():  # self-contact: not against the edge's own surroundings at rest
        k = np.flatnonzero(same)
        rs, rt = closest_between_segments(R0[i[k]], R1[i[k]], R0[j[k]], R1[j[k]])
        between = (R0[i[k]] + rs[:, None] * (R1[i[k]] - R0[i[k]])) - (R0[j[k]] + rt[:, None] * (R1[j[k]] - R0[j[k]]))
        longest = np.maximum(np.linalg.norm(R1[i[k]] - R0[i[k]], axis=1), np.linalg.norm(R1[j[k]] - R0[j[k]], axis=1))
        near = np.einsum("ij,ij->i", between, between) <= (1.01 * longest) ** 2
        keep = np.ones(len(i), dtype=bool)
        keep[k[near]] = False
        i, j, idx = i[keep], j[keep], idx[keep]
    # what costs nothing first: a node of either edge already in contact with the other body (its faces and nodes
    # are in touch there, and the node contacts hold the crossing: rows for crossings next to them gained energy in
    # settling stacks), edges nearly parallel, or whose outward normals cannot both face the normal between them
    a, b = body_of[i], body_of[j]
    ok = (np.isinf(_node_gaps(explained, ends[i], a[:, None], b[:, None])).all(axis=1)
          & np.isinf(_node_gaps(explained, ends[j], b[:, None], a[:, None])).all(axis=1))
    i, j, idx = i[ok], j[ok], idx[ok]
    da, db = P1[i] - P0[i], P1[j] - P0[j]
    cr = cross(da, db)
    crn = np.sqrt(np.einsum("ij,ij->i", cr, cr))
    ci, cj = np.einsum("ij,ij->i", cr, N[i]), np.einsum("ij,ij->i", cr, N[j])
    ok = ((crn > edge_sin * 4.0 * half[i] * half[j]) & (ci * cj < 0)
          & (np.abs(ci) > 0.05 * crn) & (np.abs(cj) > 0.05 * crn))
    i, j, idx, da, db, cr, crn = (z[ok] for z in (i, j, idx, da, db, cr, crn))
    s, t = closest_between_segments(P0[i], P1[i], P0[j], P1[j])
    ok = (s > edge_end) & (s < 1 - edge_end) & (t > edge_end) & (t < 1 - edge_end)
    i, j, idx, s, t, da, db, cr, crn = (z[ok] for z in (i, j, idx, s, t, da, db, cr, crn))
    n = cr / crn[:, None]
    n *= np.where(np.einsum("ij,ij->i", n, N[j]) < 0.0, -1.0, 1.0)[:, None]  # out of b's edge
    d = np.einsum("ij,ij->i", n, (P0[i] + s[:, None] * da) - (P0[j] + t[:, None] * db))
    v_rel = (((1 - s)[:, None] * V0[i] + s[:, None] * V1[i]) - ((1 - t)[:, None] * V0[j] + t[:, None] * V1[j])
             + mean_v[body_of[i]] - mean_v[body_of[j]])
    closing = np.maximum(-np.einsum("ij,ij->i", v_rel, n), 0.0)
    facing = (np.einsum("ij,ij->i", n, N[j]) > 0.05) & (np.einsum("ij,ij->i", n, N[i]) < -0.05)
    deepest = np.where(body_of[i] == body_of[j], -margin, -depth)  # within one body: never pulled through
    ok = facing & (d < margin + slack_h * closing) & (d > deepest)
    return idx[ok], s[ok], t[ok], n[ok], d[ok]


class EdgePass:
    """The edge search's candidate pairs kept from step to step (edge_contacts' ``kept``, the caller's to hold): found
    with every reach widened by SKIN and pruned to the pairs that can become contacts within it (their segments no
    farther apart than a contact's reach plus SKIN, no end in a node contact with the other body), with the state
    they were found in (the surface nodes' positions and travels, the bodies' means' travels, the node contacts'
    keys). They hold every pair a later step's search would keep while the node contacts found then are still
    there (so the ends excluded then are excluded now) and the nodes have moved by D and the travels grown by dT
    (per node) and dB (between bodies' means) with 2 D + 2 dT + dB <= SKIN (two segments' distance changes by at
    most 2 D, a contact's reach by 2 dT + dB); each step filters them by its own broad phase's edges and narrow
    phase: the same contacts as a fresh search (a resting pile searches its grid once). Made anew, for the layout
    it was found for only."""

    #: the reach added to the search's when the candidates are found [m]
    SKIN = 1e-3

    def __init__(self) -> None:
        self.layout = None
        self.found = 0  # searches made
        self.served = 0  # steps served from the kept candidates

    def serves(self, layout, xs: np.ndarray, travel: np.ndarray, between: np.ndarray, keys: np.ndarray) -> bool:
        """Whether the kept pairs hold every pair a search of ``layout`` in this state keeps (``keys``: the node
        contacts' keys now, sorted)."""
        if self.layout is not layout or self.xs.shape != xs.shape:
            return False
        if len(self.keys):  # every node contact of then still there
            at = np.minimum(np.searchsorted(keys, self.keys), max(len(keys) - 1, 0))
            if not len(keys) or not np.array_equal(keys[at], self.keys):
                return False
        moved = float(np.sqrt(np.einsum("ij,ij->i", xs - self.xs, xs - self.xs).max(initial=0.0)))
        grown = (2.0 * float(np.max(travel - self.travel, initial=0.0))
                 + float(np.max(between - self.between, initial=0.0)))
        return 2.0 * moved + grown <= self.SKIN

    def keep(self, layout, xs, travel, between, keys, e: np.ndarray, i: np.ndarray, j: np.ndarray) -> None:
        """Keep the pairs (e[i], e[j]) of layout.edges (e (k,) sorted, i, j (m,) into it) found in this state."""
        self.layout, self.xs, self.travel, self.between, self.keys = layout, xs.copy(), travel, between, keys.copy()
        self.e, self.i, self.j = e, i, j


def edge_contacts(bodies: list[tuple[np.ndarray, np.ndarray, SoftSurface, np.ndarray]], pairs: list[tuple[int, int]],
                  margin: float, h: float, depth: float, explained: SoftHits | None = None,
                  layout: SoftLayout | None = None, kept: EdgePass | None = None) -> EdgeHits:
    """Edge-against-edge contacts between soft bodies ``bodies`` (positions (N, 3), velocities (N, 3),
    surface, rest positions) for the index ``pairs`` (a, b) (a == b: self-contact, as soft_contacts: not between
    edges whose rest positions lie within one rest edge length of each other, the edge's own surroundings, and
    never more than the margin crossed, so never pulled through the body): two surface
    edges whose closest points lie between the ends of both, facing each other (the normal along the edges' cross
    product makes more than ~87 degrees with both edges' outward normals), within reach (the margin plus what the
    two points close along the normal within the step h [s], as soft_contacts) and less than ``depth`` [m]
    crossed, and none of the four ends in a node contact with the other
    body (``explained``: soft_contacts' hits; where one is, the two surfaces touch by faces and nodes there). Node
    against face both ways round and this cover every way two closed surfaces can meet.

    All bodies at once: their boxes grown by their reach (``layout``: SoftLayout.of their surfaces and pairs, if
    kept), the pairs of bodies whose boxes meet, the edges whose boxes meet such a partner's and whose ends have no
    node contact with it (:func:`edges_near`), the pairs of those edges whose midpoints lie within reach
    (:func:`edge_candidates`), pair by pair of bodies in the order given, and the narrow phase on them
    (:func:`edge_narrow`). With the compiled kernels each of the three edge by edge or pair by pair, the candidates
    from one uniform grid over all midpoints (kernels.edges_near, edge_candidates, edge_narrow). ``kept``: the
    candidate pairs from step to step (EdgePass; None: searched anew), the same contacts.
    :func:`edge_contacts_reference` is the same search with every pair of edges a candidate (the tests')."""
    if not pairs:
        return EdgeHits.empty()
    layout = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs) if layout is None else layout
    if not len(layout.used) or not len(layout.edges):
        return EdgeHits.empty()
    explained = None if explained is None or not len(explained) else _gap_table(explained)
    keys = np.zeros(0, np.int64) if explained is None else explained[0]  # the node contacts' keys, sorted
    used = layout.used
    data = [bodies[k] for k in used.tolist()]
    X = np.concatenate([x for x, _, _, _ in data])
    V = np.concatenate([v for _, v, _, _ in data])
    xs, vs = X[layout.nodes], V[layout.nodes]
    # every body's box grown by what it may close within the step (a crossing already made lies in both boxes),
    # motions relative to each body's mean (soft_contacts' rule: a pile falling together closes nothing)
    starts = layout.starts
    mean_v = np.add.reduceat(vs, starts) / layout.s_of[:, None]
    rel = vs - np.repeat(mean_v, layout.s_of, axis=0)
    travel_n = SOFT_SLACK * h * np.sqrt(np.einsum("ij,ij->i", rel, rel))  # per surface node
    own = np.maximum.reduceat(travel_n, starts)
    between = SOFT_SLACK * h * np.sqrt(((mean_v[:, None] - mean_v[None]) ** 2).sum(axis=2))  # (B, B)
    lo, hi = np.minimum.reduceat(xs, starts), np.maximum.reduceat(xs, starts)

    def meeting(widen: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the pairs of bodies whose boxes meet (B, B), the boxes' corners (B, 3) each), every reach widened."""
        blo, bhi = lo - (margin + own + widen)[:, None], hi + (margin + own + widen)[:, None]
        gap = between[:, :, None]
        apart = ((blo[:, None] - gap > bhi[None]) | (blo[None] - gap > bhi[:, None])).any(axis=2)
        return (layout.rank >= 0) & ~apart, blo, bhi

    meet, blo, bhi = meeting(0.0)
    if not meet.any():
        return EdgeHits.empty()
    table = np.zeros((int(used.max()) + 1, 3))  # the bodies' mean velocities, by body
    table[used] = mean_v
    R = np.concatenate([r for _, _, _, r in data])
    reach = margin + depth

    def edge_data(e: np.ndarray) -> tuple[np.ndarray, ...]:
        """The edges e's (ends, bodies (rows of used), P0, P1, V0, V1 (about the body's mean), R0, R1, outward
        normals, half lengths, travels)."""
        ends, eb = layout.edges[e], layout.edge_b[e]
        g0, g1 = ends[:, 0] + layout.node_off[eb], ends[:, 1] + layout.node_off[eb]
        P0, P1 = X[g0], X[g1]
        V0, V1 = V[g0] - mean_v[eb], V[g1] - mean_v[eb]  # about the body's mean (the means' own travel: per pair)
        N = edge_normals(X, layout.tris, layout.edge_tris[e])
        half = 0.5 * np.sqrt(np.einsum("ij,ij->i", P1 - P0, P1 - P0))
        travel = SOFT_SLACK * h * np.sqrt(np.maximum(np.einsum("ij,ij->i", V0, V0), np.einsum("ij,ij->i", V1, V1)))
        return ends, eb, P0, P1, V0, V1, R[g0], R[g1], N, half, travel

    near_of = kernels.edges_near if kernels.ENABLED else edges_near
    if kept is not None and kept.serves(layout, xs, travel_n, between, keys):
        kept.served += 1
        e, i, j = kept.e, kept.i, kept.j
    else:
        widen = 0.0 if kept is None else kept.SKIN
        wide_meet, wlo, whi = meeting(widen) if kept is not None else (meet, blo, bhi)
        e = np.flatnonzero(near_of(layout.edges, layout.edge_b, X, layout.node_off, wlo, whi, wide_meet, between,
                                   keys, used, NODE_BITS))
        if not len(e):
            return EdgeHits.empty()
        ends, eb, P0, P1, V0, V1, R0, R1, N, half, travel = edge_data(e)
        mid = 0.5 * (P0 + P1)
        radius = 2.0 * (half.max() + travel.max()) + reach + widen  # and, per pair of bodies, the means' travel
        if kernels.ENABLED:
            cell = max(radius + float(between[wide_meet].max()), float(np.ptp(mid, axis=0).max()) / (2 ** 21 - 2),
                       1e-9)
            i, j = kernels.edge_candidates(mid, eb, layout.rank, wide_meet, between, radius, cell,
                                           *kernels.centre_grid(mid, cell))  # unordered: the crossings found are sorted
        else:
            i, j = edge_candidates(mid, eb, layout.rank, wide_meet, between, radius)
        if kept is not None:  # only the pairs that can become contacts while the candidates serve
            s, t = closest_between_segments(P0[i], P1[i], P0[j], P1[j])
            gap = (P0[i] + s[:, None] * (P1[i] - P0[i])) - (P0[j] + t[:, None] * (P1[j] - P0[j]))
            a, b = used[eb[i]], used[eb[j]]
            bound = np.maximum(depth, margin + travel[i] + travel[j] + between[eb[i], eb[j]]) + widen
            gaps = (keys, np.zeros(len(keys))) if len(keys) else None  # (the node contacts as _node_gaps reads them)
            free = (np.isinf(_node_gaps(gaps, ends[i], a[:, None], b[:, None])).all(axis=1)
                    & np.isinf(_node_gaps(gaps, ends[j], b[:, None], a[:, None])).all(axis=1))
            ok = free & (np.einsum("ij,ij->i", gap, gap) <= bound * bound)
            ge, back = np.unique(np.concatenate([e[i[ok]], e[j[ok]]]), return_inverse=True)
            i, j, e = back[:ok.sum()], back[ok.sum():], ge
            kept.found += 1
            kept.keep(layout, xs, travel_n, between, keys, e, i, j)
    if kept is not None:  # this step's broad phase among the kept edges: those near a body now, as a search finds
        if not len(e):
            return EdgeHits.empty()
        near = near_of(layout.edges[e], layout.edge_b[e], X, layout.node_off, blo, bhi, meet, between, keys, used,
                       NODE_BITS)
        ok = near[i] & near[j]
        i, j = i[ok], j[ok]
        ends, eb, P0, P1, V0, V1, R0, R1, N, half, travel = edge_data(e)
    if not len(i):
        return EdgeHits.empty()
    body_of = used[eb]
    k, s, t, n, d = (kernels.edge_narrow if kernels.ENABLED else edge_narrow)(
        i, j, P0, P1, V0, V1, N, R0, R1, half, travel, body_of, ends, table, keys, NODE_BITS, margin, reach, depth,
        SOFT_SLACK * h, EDGE_SIN, EDGE_END)
    if not len(k):
        return EdgeHits.empty()
    i, j = i[k], j[k]
    if kernels.ENABLED or kept is not None:  # by pair of bodies, edge and edge (the narrow phase keeps order)
        order = np.lexsort((j, i, layout.rank[eb[i], eb[j]]))
        i, j, s, t, n, d = i[order], j[order], s[order], t[order], n[order], d[order]
    a, b = body_of[i], body_of[j]
    edge_of = layout.edge_of[e]
    key = ((1 << 62) | ((a * 1024 + b) << (2 * EDGE_BITS)) | (edge_of[i] << EDGE_BITS) | edge_of[j]).astype(np.int64)
    return EdgeHits(a, b, np.column_stack([ends[i], ends[j]]), np.column_stack([1 - s, s, -(1 - t), -t]), n, d, key)


def edge_contacts_reference(bodies: list[tuple[np.ndarray, np.ndarray, SoftSurface, np.ndarray]],
                            pairs: list[tuple[int, int]], margin: float, h: float, depth: float,
                            explained: SoftHits | None = None) -> EdgeHits:
    """:func:`edge_contacts` without its broad phase: every pair of edges of each pair of bodies (each pair once within
    a body) through the narrow phase (numpy's edge_narrow), pair by pair in the order given, by edge index: the
    reference the tests hold the broad phase to."""
    layout = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs)
    explained = None if explained is None or not len(explained) else _gap_table(explained)
    keys = np.zeros(0, np.int64) if explained is None else explained[0]
    used = layout.used
    data = [bodies[k] for k in used.tolist()]
    X = np.concatenate([x for x, _, _, _ in data])
    V = np.concatenate([v for _, v, _, _ in data])
    R = np.concatenate([r for _, _, _, r in data])
    vs = V[layout.nodes]
    mean_v = np.add.reduceat(vs, layout.starts) / layout.s_of[:, None]
    ends, eb = layout.edges, layout.edge_b
    g0, g1 = ends[:, 0] + layout.node_off[eb], ends[:, 1] + layout.node_off[eb]
    P0, P1, V0, V1 = X[g0], X[g1], V[g0] - mean_v[eb], V[g1] - mean_v[eb]
    N = edge_normals(X, layout.tris, layout.edge_tris)
    half = 0.5 * np.sqrt(np.einsum("ij,ij->i", P1 - P0, P1 - P0))
    travel = SOFT_SLACK * h * np.sqrt(np.maximum(np.einsum("ij,ij->i", V0, V0), np.einsum("ij,ij->i", V1, V1)))
    table = np.zeros((int(used.max()) + 1, 3))
    table[used] = mean_v
    row = {int(k): r for r, k in enumerate(used.tolist())}
    out = []
    for a, b in pairs:
        ea, e_b = np.flatnonzero(eb == row[a]), np.flatnonzero(eb == row[b])
        i, j = np.repeat(ea, len(e_b)), np.tile(e_b, len(ea))
        if a == b:
            i, j = i[i < j], j[i < j]
        k, s, t, n, d = edge_narrow(i, j, P0, P1, V0, V1, N, R[g0], R[g1], half, travel, used[eb], ends, table, keys,
                                    NODE_BITS, margin, margin + depth, depth, SOFT_SLACK * h, EDGE_SIN, EDGE_END)
        i, j = i[k], j[k]
        key = ((1 << 62) | ((a * 1024 + b) << (2 * EDGE_BITS)) | (layout.edge_of[i] << EDGE_BITS)
               | layout.edge_of[j]).astype(np.int64)
        out.append(EdgeHits(np.full(len(k), a), np.full(len(k), b), np.column_stack([ends[i], ends[j]]),
                            np.column_stack([1 - s, s, -(1 - t), -t]), n, d, key))
    parts = [hh for hh in out if len(hh)]
    if not parts:
        return EdgeHits.empty()
    return EdgeHits(*(np.concatenate([getattr(hh, f.name) for hh in parts]) for f in fields(EdgeHits)))
