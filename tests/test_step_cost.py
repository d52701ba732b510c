"""The fixed cost of a step in Python calls (issue 18): a few hundred calls of functions written in Python for one soft
and one rigid body, whatever the contacts, and a few more per extra body. Counted by the interpreter's profile hook
("call" events: every Python frame entered, comprehensions included), not timed."""
from __future__ import annotations

import statistics
import sys

import pytest

from softbody import kernels

from experiments.scenes import cubes_on_plane, sheet_on_sphere

pytestmark = pytest.mark.skipif(not kernels.ENABLED, reason="the counts are the compiled path's (numba)")

# a few hundred: one soft body and one rigid, in contact (measured 323-404 per step on the scenes below when set;
# 409-450 since the damping that spares rigid motion (9 calls) and the warped step's rotation watch (6))
ONE_BODY_CALLS = 470
# each extra body of a World, once its bodies are stepped as one (measured 5)
PER_BODY_CALLS = 10


def python_calls_per_step(world, steps: int = 10) -> float:
    count = 0

    def hook(frame, event, arg):
        nonlocal count
        if event == "call":
            count += 1

    sys.setprofile(hook)
    try:
        for _ in range(steps):
            world.step()
    finally:
        sys.setprofile(None)
    return count / steps


def _settled(scene, steps: int = 25):
    for _ in range(steps):  # into contact: the sheets land on the sphere after about 10 steps
        scene.world.step()
    return scene.world


@pytest.mark.parametrize("kind, cells", [("tet4", (4, 4, 2)), ("tet10", (2, 2, 1)), ("tet4", (8, 8, 3))])
def test_a_sheet_on_a_sphere_steps_in_a_few_hundred_python_calls(kind, cells):
    world = _settled(sheet_on_sphere(kind, cells))
    assert len(world.contacts) > 0
    calls = statistics.median(python_calls_per_step(world) for _ in range(3))
    assert calls <= ONE_BODY_CALLS


def test_each_extra_body_adds_a_few_python_calls():
    def calls(count: int) -> float:
        world = _settled(cubes_on_plane("tet10", (2, 2, 2), count=count))
        return statistics.median(python_calls_per_step(world) for _ in range(3))

    one, two, four = calls(1), calls(2), calls(4)  # four: 1404 unknowns, still the direct path
    assert one <= ONE_BODY_CALLS
    assert two <= ONE_BODY_CALLS + 100  # bodies stepped as one: the stack's gather and scatter, soft contact search
    assert (four - two) / 2 <= PER_BODY_CALLS
