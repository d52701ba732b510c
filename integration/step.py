"""One coupled step's data: the record a step fills as it goes (StepRecord) and the report it publishes at its end
(StepReport).

World._step reads top to bottom: sync the rigid scene, collide, build one contact problem, let pybullet step, prepare
the soft bodies' systems and solve the coupled problem (with contacts found at the end of the step, again), commit.
Everything one step finds and solves lives in its StepRecord, made at its start and dropped at its end, never on the
World; what users, the recorder and saved states read of the last step is the StepReport it published. Both key the
soft bodies by stable handles: a stepped body by its index in ``sim.bodies`` (fixed within a step), a member by its
index in ``World.bodies``, an attachment by its index in ``World.attachments``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from softbody import FemBody
from softbody.integrator import Timings

from .collision import Contacts, FaceHits
from .contact import ContactResult, FaceContacts, NodeContacts, PairContacts, StepSolution
from .convex import JointRows
from .coupling import RigidCoupling
from .softcontact import EdgeHits, SoftHits


@dataclass
class StepRecord:
    """What one step found and built, filled in the step's order (World._step).

    t: the time at the start [s]; bodies: the stepped bodies (``sim.bodies``); h: the step [s]; timings: seconds by phase
    (exclusive, see softbody.integrator.Timings); candidates, face_hits, soft_hits, edge_hits: the contact search's;
    detected: each stepped body's (node contacts, face hits) with rigid links, as found (candidates and face_hits
    join them); member_pairs (k, 2): the soft pairs in contact by member index; coupling: the movable rigid bodies in play;
    contacts, faces, attachments: each stepped body's (by its index) node and face contacts with rigid links and its
    coupled attachments (attachment, nodes (m,), start points (m, 3), Jacobians (m, 3, n)); pairs: the soft contacts;
    poses0: the moving links' poses at the start (key -> (centre (3,), quaternion (4,))); joint_rows: the rows of the
    coupled bodies' motors, joint limits (joints.joint_rows) and user constraints (constraints.constraint_rows, the
    client's ``constraints``), joints: those rows once pybullet stepped (convex.JointRows, or None); solution: the
    contact solve's."""

    t: float
    bodies: list[FemBody]
    h: float
    timings: Timings = field(default_factory=Timings)
    detected: list[tuple[Contacts, FaceHits]] = field(default_factory=list)
    candidates: Contacts = field(default_factory=Contacts.empty)
    face_hits: FaceHits = field(default_factory=FaceHits.empty)
    soft_hits: SoftHits = field(default_factory=SoftHits.empty)
    edge_hits: EdgeHits = field(default_factory=EdgeHits.empty)
    member_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    coupling: RigidCoupling = field(default_factory=lambda: RigidCoupling.of({}))
    contacts: dict[int, NodeContacts] = field(default_factory=dict)
    faces: dict[int, FaceContacts] = field(default_factory=dict)
    attachments: dict[int, list[tuple[Any, np.ndarray, np.ndarray, np.ndarray]]] = field(default_factory=dict)
    pairs: PairContacts | None = None
    poses0: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    joint_rows: JointRows | None = None
    constraints: list = field(default_factory=list)
    joints: JointRows | None = None
    solution: StepSolution | None = None

    @property
    def in_contact(self) -> bool:
        return bool(self.contacts or self.faces or self.pairs is not None)


@dataclass
class StepReport:
    """What the last step found and solved, as World publishes it (``World.report``; the World's ``contacts``,
    ``contact_results``, ... read it).

    candidates, face_hits, soft_hits, edge_hits: the contact search's candidates; member_pairs (k, 2): the soft pairs
    in contact by member index; contact_results, face_results: stepped body index -> (contacts, result) of its node and
    face contacts with rigid links; pair_results: [(soft contacts, result)]; attachment_forces: [(attachment index,
    forces on its nodes (m, 3) [N])]; places: each member's (stepped body index, first node) in that step; timings:
    seconds by phase, and their "total"; iterations: the contact solve's (active-set or Newton) iterations;
    joint_forces: the coupled problem's scalar rows and the force or torque [N or N m] each exerted over the step:
    (kind "motor" / "lower" / "upper", body, joint) -> a motor's along the joint's axis, a limit's magnitude (pushing
    the joint back within it); ("point2point" / "fixed" / "gear", constraint id, row) -> the constraint's on its parent
    (world axes: force rows 0-2, a fixed constraint's torque rows 3-5; a gear's along its row)."""

    candidates: Contacts = field(default_factory=Contacts.empty)
    face_hits: FaceHits = field(default_factory=FaceHits.empty)
    soft_hits: SoftHits = field(default_factory=SoftHits.empty)
    edge_hits: EdgeHits = field(default_factory=EdgeHits.empty)
    member_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    contact_results: dict[int, tuple[NodeContacts, ContactResult]] = field(default_factory=dict)
    face_results: dict[int, tuple[FaceContacts, ContactResult]] = field(default_factory=dict)
    pair_results: list[tuple[PairContacts, ContactResult]] = field(default_factory=list)
    attachment_forces: list[tuple[int, np.ndarray]] = field(default_factory=list)
    places: list[tuple[int, int]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=lambda: {"total": 0.0})
    iterations: int = 0
    joint_forces: dict[tuple[str, int, int], float] = field(default_factory=dict)

    @classmethod
    def of(cls, record: StepRecord, places: list[tuple[int, int]]) -> "StepReport":
        """The report of a finished step's ``record``; places: each member's (stepped index, first node)."""
        sol = record.solution
        contact_results, face_results, pair_results, forces = {}, {}, [], []
        if sol is not None:
            for i, res in enumerate(sol.contacts):
                if res is not None:
                    contact_results[i] = (record.contacts[i], res)
            for i, res in enumerate(sol.faces):
                if res is not None:
                    face_results[i] = (record.faces[i], res)
            pair_results = list(sol.pairs)
            for i, f in enumerate(sol.attachment_forces):
                if f is None:
                    continue
                k = 0
                for a, _, _, _ in record.attachments.get(i, []):
                    forces.append((a.handle, f[k:k + len(a.nodes)]))
                    k += len(a.nodes)
        timings = dict(record.timings)
        timings["total"] = sum(timings.values())
        joint_forces = {}
        if record.joints is not None and sol is not None and len(sol.joint_impulses):
            whole = sol.joint_impulses + (0.0 if record.joints.applied is None else record.joints.applied)
            joint_forces = {label: float(g) for label, g in zip(record.joints.labels, whole / record.h)}
        return cls(record.candidates, record.face_hits, record.soft_hits, record.edge_hits, record.member_pairs,
                   contact_results, face_results, pair_results, forces, places, timings,
                   0 if sol is None else int(sol.iterations), joint_forces)
