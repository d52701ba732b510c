"""The coupled step as a pipeline (integration.step): exclusive phase timings that add up to the step's wall time,
and a report the step publishes, which the World's results and saved states read."""
from __future__ import annotations

import time

import numpy as np
import pytest

from softbody import FemBody, LinearElastic, box_mesh
from softbody.integrator import Timings, timed

from integration import World


def test_nested_phases_count_to_the_innermost_only():
    t = Timings()
    tic = time.perf_counter()
    with timed(t, "outer"):
        time.sleep(0.02)
        with timed(t, "inner"):
            time.sleep(0.03)
        time.sleep(0.01)
    wall = time.perf_counter() - tic
    # exclusive: the outer phase is its own 30 ms, not 60 ms; together they are the wall time
    assert t["inner"] == pytest.approx(0.03, abs=0.015)
    assert t["outer"] == pytest.approx(0.03, abs=0.015)
    assert wall - 1e-3 <= t["inner"] + t["outer"] <= wall
    plain = {}  # a plain dict: inclusive, as before
    with timed(plain, "outer"):
        with timed(plain, "inner"):
            time.sleep(0.01)
    assert plain["outer"] >= plain["inner"]


def _cube(z: float) -> FemBody:
    """A 4 cm tet4 cube, its bottom at height z [m]."""
    return FemBody(box_mesh((0.04, 0.04, 0.04), (2, 2, 2), "tet4", center=(0.0, 0.0, z + 0.02)),
                   LinearElastic(1e5, 0.3, 500.0))


def test_a_steps_phases_add_up_to_its_wall_time_and_its_report_holds_its_results():
    with World(dt=0.005) as w:
        floor = w.add_plane()
        box = w.add_box((0.02, 0.02, 0.01), position=(0, 0, 0.0925), mass=0.05)
        w.add_soft(_cube(0.0005), friction=0.5)
        w.add_soft(_cube(0.0415), friction=0.5)  # resting on the first: soft contact
        for _ in range(30):
            tic = time.perf_counter()
            w.step()
            wall = time.perf_counter() - tic
        t = w.timings
        phases = {k: v for k, v in t.items() if k != "total"}
        assert {"collision", "rigid", "contact", "other"} <= set(phases)
        assert all(v >= 0 for v in phases.values())
        assert t["total"] == pytest.approx(sum(phases.values()))
        # nothing is counted twice (exclusive phases inside one step) and little is left out
        assert t["total"] <= wall
        assert t["total"] >= 0.5 * wall
        report = w.report
        assert w.contact_results is report.contact_results and w.pair_results is report.pair_results
        assert len(report.pair_results) and len(report.contact_results)
        # the report's places are the members' in sim.bodies: each result's key is a stepped body
        for k, (where, first) in enumerate(report.places):
            assert 0 <= where < len(w.sim.bodies) and first >= 0
        # the cubes and the box carry their weight through the floor: the forces of the report are the step's
        weight = 9.81 * (sum(float(b.node_mass.sum()) for b in w.bodies) + 0.05)
        assert w.contact_force(floor)[2] == pytest.approx(-weight, rel=0.05)
        assert w.contact_force(box)[2] == pytest.approx(9.81 * 0.05, rel=0.05)  # the cube holds the box up
        state = w.save_state()
        assert state.results is not w.report  # a copy
        forces = [w.contact_force(floor, soft=b) for b in w.bodies]
        w.step()
        w.restore_state(state)
        for b, f in zip(w.bodies, forces):
            np.testing.assert_array_equal(w.contact_force(floor, soft=b), f)


def test_a_kept_stack_takes_up_what_its_members_ignore_since():
    """Two cubes stepped as one stack, then both attached to the box under them without collision (attach's
    default): the stack, kept as it was, ignores the box from then on, as each member does (no contact found)."""
    with World(dt=0.005) as w:
        box = w.add_box((0.1, 0.1, 0.01), position=(0, 0, -0.0095))
        a, b = _cube(0.001), _cube(0.001)
        w.add_soft(a)
        w.add_soft(b)
        b.positions = b.positions + np.array([0.06, 0.0, 0.0])
        w.step()
        stack = w.stepped(a)
        assert stack is w.stepped(b) and stack is not a  # one stack of both
        assert (w.contacts.rigid == box.id).any()  # resting on the box
        for cube in (a, b):
            w.attach(cube, [int(np.argmin(cube.positions[:, 2]))], box)
        w.step()
        assert w.stepped(a) is stack  # the same stack, kept
        assert not (w.contacts.rigid == box.id).any()
        assert not any((c.rigid == box.id).any() for c, _ in w.contact_results.values())
