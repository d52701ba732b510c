"""The main job's contact set settles (issue 19, item 6).

The number of active contacts of sheet-on-sphere (tet10 6x6x2) switches between 5 and 9 every ~0.2 s until
about 3.4 s. That is no cycle of the contact solve: the sheet's lowest bending mode (period ~0.38 s, damped by
Rayleigh damping and backward Euler alone) lifts the second ring of nodes around the top of the sphere off it
and sets it down again, by up to 1.2 mm at 2 s, 0.4 mm at 2.5-3 s; at rest those nodes hover 88 um above the
sphere, so the set settles once the swing is smaller than that. The same happens without friction. These tests
pin that down: every switch is a real lift-off or landing (no flicker of a node that stays put), the
scene's energy never rises across a switch, and once the swing has died out the set is constant.
"""
from __future__ import annotations

import numpy as np
import pytest

from experiments.scenes import sheet_on_sphere


@pytest.fixture(scope="module")
def settled_run():
    scene = sheet_on_sphere()  # the main job: tet10 (6, 6, 2), dt 0.01 s, mu 1
    rows = []

    def callback(world):
        sets, gaps = [], {}
        for c, r in world.contact_results.values():
            sets += c.node[r.active].tolist()
            gaps.update(zip(c.node.tolist(), c.distance.tolist()))
        rows.append((world.t, frozenset(sets), gaps, world.energy()["total"]))

    scene.world.run(4.5, callback)
    return rows


def test_active_set_settles(settled_run):
    """Constant over the last second once the bending swing has died out (4.5 s run: 3.5 .. 4.5 s)."""
    last = [s for t, s, _, _ in settled_run if t >= 3.5 - 1e-9]
    assert len(last) >= 100 and all(s == last[0] for s in last), sorted({len(s) for s in last})
    assert len(last[0]) == 5  # the node at the top of the sphere and the ring around it


def test_every_switch_is_a_real_lift(settled_run):
    """A node leaving the set moves off the sphere by more than 50 um before it lands again (no flicker), and
    the total energy (975 J) never rises by more than 1e-6 of it across a switch (the warped step's own
    linearisation error is below that: at most 1.4e-4 J in a step)."""
    max_gap = {}
    for k in range(1, len(settled_run)):
        t, s, gaps, e = settled_run[k]
        _, s0, _, e0 = settled_run[k - 1]
        for n in s0 - s:
            max_gap[n] = 0.0
        for n in list(max_gap):
            if n in gaps:
                max_gap[n] = max(max_gap[n], gaps[n])
            if n in s:  # landed again: it was really off
                assert max_gap.pop(n) > 50e-6, (t, n)
        if s != s0:
            assert e <= e0 + 1e-6 * abs(e0), (t, e - e0)
