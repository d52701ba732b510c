"""The coupled problem split into islands: the soft bodies (a stack's members apart) that its rows join, directly or
through the movable rigid bodies, each a convex problem of its own.

The coupled step (convex.py) minimises one convex function of all soft velocities and the rigid velocity change, a
sum of the bodies' own terms and the rows' terms. Bodies that no row joins, directly or through other bodies or the
rigid unknowns, share no term: the minimum splits into the minima of the islands, each found by its own Newton
iterations on its own sparse pattern and factorisation. A pile settling as nine columns is nine islands: a column
whose contacts change state is refactorised alone (1/9 of the work), its Newton iterations and conjugate gradients
stop when it has converged, not when the slowest column has, and a contact leaving a column's pattern re-analyses that
column only. (All rows on rigid unknowns, and the rigid bodies' own rows, join one island: the rigid unknowns are
coupled through their mass matrix and joints.)

The islands are found anew every step (:func:`components` over the distinct pairs of bodies the rows join); a
BodyStack's members
are units of their own, their blocks of the stack's system the members' own patterns (a stack's matrices are
block-diagonal by member, softbody.stack).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .convex import MemberBlocks, Rows, SoftPart, Solution


def components(count: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(count,) the connected components of the undirected graph of ``count`` nodes and the edges (a (k,), b (k,)),
    each node labelled by the smallest node of its component: union-find over the distinct edges (a pile's thousands
    of rows join a few hundred pairs of bodies at most)."""
    label = np.arange(count)
    if not len(a):
        return label
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    parent = list(range(count))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for key in np.unique(np.minimum(a, b) * count + np.maximum(a, b)).tolist():
        x, y = root(key // count), root(key % count)
        if x != y:
            parent[max(x, y)] = min(x, y)
    return np.array([root(x) for x in range(count)], dtype=np.int64)


@dataclass
class Island:
    """One island: its ``units`` (indices into Islands.units), its ``rows`` (indices into the problem's rows) and
    whether it holds the rigid unknowns (``rigid``)."""

    units: np.ndarray
    rows: np.ndarray
    rigid: bool


def _units_of(p: SoftPart) -> list[SoftPart]:
    """The units of part p: itself, or a stack's members each as a SoftPart of its rows (its own operator and the
    stack's blocks' slice if the stack's A is applied matrix-free, else its blocks)."""
    members = getattr(p.body, "members", None)
    if members is None:
        return [p]
    off, ip = p.body.offsets, p.body.pattern.indptr
    free = p.operator is not None and callable(p.A) and hasattr(p.operator, "member")  # not assembled
    diagonal = p.diagonal_blocks() if free else None
    A = None if free else p.blocks()
    out = []
    for k, member in enumerate(members):
        a, b = int(off[k]), int(off[k + 1])
        if free:  # the member's own operator; its blocks of the stack's, if a factorisation asks for them
            out.append(SoftPart(member, MemberBlocks(p, int(ip[a]), int(ip[b])), p.b[a:b], p.held[a:b],
                                p.value[a:b], p.guess[a:b], p.operator.member(k), diagonal[a:b]))
        else:
            out.append(SoftPart(member, A[ip[a]:ip[b]], p.b[a:b], p.held[a:b], p.value[a:b], p.guess[a:b]))
    return out


def _unit_of(parts: np.ndarray, nodes: np.ndarray, starts: list[np.ndarray], part_units: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """(unit, node) of slots of ``parts`` and ``nodes`` (any shape): the unit each slot's node belongs to (-1 for an
    unused slot, part -1) and its node in that unit (part p's units start at part_units[p], its nodes at starts[p])."""
    unit = np.full(parts.shape, -1, dtype=np.int64)
    node = np.zeros(nodes.shape, dtype=np.int64)
    used = parts >= 0
    for p, st in enumerate(starts):
        on = used & (parts == p)
        if not on.any():
            continue
        k = np.searchsorted(st, nodes[on], side="right") - 1
        unit[on] = part_units[p] + k
        node[on] = nodes[on] - st[k]
    return unit, node


@dataclass
class Islands:
    """The problem of soft ``parts`` and ``rows`` as islands.

    parts: the problem's parts; units: the parts with a stack's members apart (SoftPart views of the stack's system:
    its block data or operator, load, supports and guess restricted to the member); part_units (P + 1,): part p's units
    are units[part_units[p]:part_units[p + 1]]; starts: each part's units' first nodes; islands: the islands, those
    with units or rows, in the order of their first unit (the rigid island last if it has none)."""

    parts: list[SoftPart]
    part_units: np.ndarray
    starts: list[np.ndarray]
    islands: list[Island]

    def slots(self, rows: Rows) -> tuple[np.ndarray, np.ndarray]:
        """(unit (m, S), node (m, S)): each of ``rows``' slots' unit (-1: unused) and its node in that unit."""
        if "_slots" not in self.__dict__:
            self._slots = _unit_of(rows.parts, rows.nodes, self.starts, self.part_units)
        return self._slots

    @property
    def units(self) -> list[SoftPart]:
        """The units (a part, or a stack part's members each as a SoftPart of its rows), made at the first use (a
        problem of one island is solved whole: it needs none)."""
        if "_units" not in self.__dict__:
            self._units = [u for p in self.parts for u in _units_of(p)]
        return self._units

    @classmethod
    def of(cls, parts: list[SoftPart], rows: Rows, rigid: bool) -> "Islands":
        """The islands of soft ``parts`` joined by ``rows``; ``rigid``: there are rigid unknowns (the rows on them,
        and they themselves, one island)."""
        part_units, starts = [0], []
        for p in parts:
            members = getattr(p.body, "members", None)
            starts.append(np.array([0, p.body.n_nodes]) if members is None else np.asarray(p.body.offsets))
            part_units.append(part_units[-1] + (1 if members is None else len(members)))
        part_units = np.asarray(part_units)
        m = len(rows)
        # a row joins at most two units: its first slot's (body a's) and its last used slot's (body b's, or a's)
        last = np.maximum((rows.parts >= 0).sum(axis=1) - 1, 0) if m else np.zeros(0, np.int64)
        ends = (np.column_stack([rows.parts[:, 0], rows.parts[np.arange(m), last]]),
                np.column_stack([rows.nodes[:, 0], rows.nodes[np.arange(m), last]]))
        end_unit = _unit_of(ends[0], ends[1], starts, part_units)[0]
        U = int(part_units[-1])
        # the graph of units (and the rigid unknowns, node U) that rows join; every row's first slot is used
        first = end_unit[:, 0]
        pairs = [end_unit[end_unit[:, 0] != end_unit[:, 1]]]
        if rigid and rows.jacobian is not None and len(rows):
            on = np.abs(rows.jacobian).reshape(len(rows), -1).max(axis=1) > 0
            pairs.append(np.column_stack([first[on], np.full(int(on.sum()), U)]))
        pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
        label = components(U + 1, pairs[:, 0], pairs[:, 1])
        row_label = label[first] if len(rows) else np.zeros(0, np.int64)
        order = np.argsort(label[:U], kind="stable")
        islands, seen = [], set()
        for u in order.tolist():  # in the order of their first unit
            c = int(label[u])
            if c in seen:
                continue
            seen.add(c)
            islands.append(Island(np.flatnonzero(label[:U] == c), np.flatnonzero(row_label == c),
                                  bool(rigid and c == label[U])))
        if rigid and int(label[U]) not in seen:  # the rigid bodies alone (their joints)
            islands.append(Island(np.zeros(0, np.int64), np.zeros(0, np.int64), True))
        return cls(parts, part_units, starts, islands)

    def __len__(self) -> int:
        return len(self.islands)

    def problem(self, island: Island, rows: Rows) -> tuple[list[SoftPart], Rows]:
        """The units and rows of ``island`` (rows: the whole problem's), its rows' slots renumbered to its units."""
        local = np.full(len(self.units), -1, dtype=np.int64)
        local[island.units] = np.arange(len(island.units))
        r = island.rows
        unit, node = (a[r] for a in self.slots(rows))
        sub = Rows(np.where(unit >= 0, local[np.maximum(unit, 0)], -1), node, rows.weights[r],
                   rows.frames[r], rows.rigid_velocity[r], None if rows.jacobian is None else rows.jacobian[r],
                   rows.v_hat[r], rows.mu[r], rows.bilateral[r])
        return [self.units[u] for u in island.units.tolist()], sub

    def merge(self, solutions: list[Solution], m: int, n: int, joints: int) -> Solution:
        """One Solution of the whole problem (m rows, n rigid unknowns, ``joints`` joint rows) from the islands'
        (in the order of ``islands``): velocities per part, each row's impulse, velocity and stiction in place, du
        and the joint rows' impulses from the rigid island; iterations and rounds the most of any island,
        factorizations and costs summed, the residual the largest, converged if all are."""
        velocities: list = [None] * len(self.units)
        gamma, vc, stick = np.zeros((m, 3)), np.zeros((m, 3)), np.zeros(m, dtype=bool)
        du, joint_gamma = np.zeros(n), np.zeros(joints)
        for island, sol in zip(self.islands, solutions):
            for u, v in zip(island.units.tolist(), sol.velocities):
                velocities[u] = v
            gamma[island.rows], vc[island.rows], stick[island.rows] = sol.gamma, sol.vc, sol.stiction
            if island.rigid:
                du, joint_gamma = sol.du, sol.joint_gamma
        per_part = [velocities[a] if b - a == 1 else np.concatenate(velocities[a:b])
                    for a, b in zip(self.part_units[:-1].tolist(), self.part_units[1:].tolist())]
        return Solution(per_part, du, gamma, vc, stick, max((s.iterations for s in solutions), default=0),
                        sum(s.factorizations for s in solutions), float(sum(s.cost for s in solutions)),
                        max((s.residual for s in solutions), default=0.0), all(s.converged for s in solutions),
                        max((s.rounds for s in solutions), default=1), joint_gamma)
