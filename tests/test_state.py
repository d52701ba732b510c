"""Saved states (Simulation.save_state / World.save_state): continuing from a restored state is the same to the bit
as continuing the original, in this process and in a new one with the same scene built; the hidden state they
carry (preconditioners, contact warm starts, friction states, pybullet's contact points) is shown to matter."""
from __future__ import annotations

import copy
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data
import pytest

import softbody as sb
from integration import World, WorldState
from softbody.errors import InvalidInputError

HERE = Path(__file__).resolve()


def _bar(scheme: str = "warped") -> tuple[sb.FemBody, sb.Simulation]:
    """A cantilevered tet4 bar of 3075 unknowns: the iterative path, with its preconditioner kept across steps."""
    mesh = sb.box_mesh((1.0, 0.1, 0.1), cells=(40, 4, 4), kind="tet4", center=(0.5, 0, 0))
    body = sb.FemBody(mesh, sb.LinearElastic(E=1e6, nu=0.33, density=1000), damping=(0.1, 0.001))
    body.fix(np.flatnonzero(mesh.nodes[:, 0] == 0.0))
    return body, sb.Simulation(body, dt=0.01, scheme=scheme)


def _trajectory(sim: sb.Simulation, body: sb.FemBody, steps: int) -> np.ndarray:
    out = []
    for _ in range(steps):
        sim.step()
        out.append(np.concatenate([body.positions.ravel(), body.velocities.ravel()]))
    return np.array(out)


@pytest.mark.parametrize("scheme", ["warped", "newton", "bdf2"])
def test_a_simulation_continues_from_its_saved_state_to_the_bit(scheme, tmp_path):
    body, sim = _bar(scheme)
    assert sim.linear_method(body) == "iterative"
    _trajectory(sim, body, 15)
    state = sim.save_state()
    original = _trajectory(sim, body, 20)
    t_end = sim.t
    sim.restore_state(state)
    assert sim.t == pytest.approx(0.15) and sim.steps == 15
    assert np.array_equal(_trajectory(sim, body, 20), original)
    assert sim.t == t_end
    # the preconditioner is state: restoring positions and velocities alone continues elsewhere
    sim.restore_state(state)
    sim.solvers.load_state(sim.bodies, {})
    assert np.abs(_trajectory(sim, body, 20) - original).max() > 0
    # on disk, into a new Simulation of the same body
    state.write(tmp_path / "bar.state")
    body2, sim2 = _bar(scheme)
    sim2.restore_state(tmp_path / "bar.state")
    assert np.array_equal(_trajectory(sim2, body2, 20), original)


def test_a_simulation_refuses_another_bodys_state_and_copies():
    body, sim = _bar()
    state = sim.save_state()
    other = sb.Simulation(sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet4"), sb.LinearElastic(1e6, 0.3, 1000)),
                          0.01)
    with pytest.raises(InvalidInputError, match="build the same scene"):
        other.restore_state(state)
    with pytest.raises(InvalidInputError, match="restore_state takes"):
        sim.restore_state(42)
    for attempt in (copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="save_state"):
            attempt(sim)


def _scene(client: int | None = None, friction: tuple = (0.4, 0.4, 0.4)) -> tuple[World, list[sb.FemBody], int, int]:
    """Three soft tet10 cubes on a plane (two stacked: soft contact, friction), a dynamic box on the third (two-way
    coupling), and pybullet_data's KUKA iiwa in the user's own client, its motors driven by the loop."""
    cid = p.connect(p.DIRECT) if client is None else client
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(0.01, physicsClientId=cid)
    p.loadURDF("plane.urdf", physicsClientId=cid)
    kuka = p.loadURDF("kuka_iiwa/model.urdf", [0.0, -0.6, 0.0], useFixedBase=True, physicsClientId=cid)
    box = p.createMultiBody(0.2, p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.03] * 3, physicsClientId=cid),
                            basePosition=[0.4, 0.0, 0.14], physicsClientId=cid)
    world = World(client=cid)
    cubes = [sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10", center=c), sb.LinearElastic(5e5, 0.33, 1000))
             for c in [(0, 0, 0.051), (0.0, 0.01, 0.17), (0.4, 0, 0.051)]]
    for b, mu in zip(cubes, friction):
        world.add_soft(b, friction=mu)
    return world, cubes, box, kuka


def _close(world: World) -> None:
    """Close the World and the client _scene opened for it."""
    cid = world.client
    world.close()
    p.disconnect(cid)


def _run(world: World, cubes: list[sb.FemBody], box: int, kuka: int, steps: int) -> np.ndarray:
    """Each step's soft states, the box's pose and velocity and the arm's joints."""
    c = world.client
    out = []
    for _ in range(steps):
        for j in range(7):
            p.setJointMotorControl2(kuka, j, p.POSITION_CONTROL, 0.4 * np.sin(world.t + j), force=200, physicsClientId=c)
        world.step()
        pose, vel = p.getBasePositionAndOrientation(box, physicsClientId=c), p.getBaseVelocity(box, physicsClientId=c)
        joints = [s[:2] for s in p.getJointStates(kuka, range(7), physicsClientId=c)]
        out.append(np.concatenate([*(b.positions.ravel() for b in cubes), *(b.velocities.ravel() for b in cubes),
                                   *pose, *vel, np.ravel(joints)]))
    return np.array(out)


def test_a_world_continues_from_its_saved_state_to_the_bit(tmp_path):
    world, cubes, box, kuka = _scene()
    _run(world, cubes, box, kuka, 20)
    assert any(r.active.any() for _, r in world.pair_results)  # soft contact, warm-started from step to step
    state = world.save_state(tmp_path / "scene.state")
    force = world.contact_force(box)
    original = _run(world, cubes, box, kuka, 30)
    force_after = world.contact_force(box)
    world.restore_state(state)
    assert np.array_equal(world.contact_force(box), force)  # the last step's results come back too
    assert world.t == pytest.approx(0.2)
    assert np.array_equal(_run(world, cubes, box, kuka, 30), original)
    assert np.array_equal(world.contact_force(box), force_after)
    # the warm starts and friction states are state: restored as saved (active and sticking contacts, sliding
    # forces), per body (the solver keys them by the stepped body, the state by its handle)
    world.restore_state(state)
    kept = {k: v for k, v in world.contact_solver.previous.items() if v[0] or v[1] or v[2]}
    assert kept and any(k[0] == "soft" for k in kept)
    handle = {b: tuple(h) for b, h in zip(world.sim.bodies, state.layout)}
    assert len(world.contact_solver.previous) == len(state.previous)
    for (kind, key), value in world.contact_solver.previous.items():
        want = state.previous[(kind, key if kind == "soft" else handle[key])]
        assert value[0] == want[0] and value[1] == want[1]
        assert value[2].keys() == want[2].keys() and all(np.array_equal(value[2][k], want[2][k]) for k in want[2])
    # from disk into the same scene built again (in this process; a new process: the test below)
    w2, cubes2, box2, kuka2 = _scene()
    w2.restore_state(tmp_path / "scene.state")
    assert np.array_equal(_run(w2, cubes2, box2, kuka2, 30), original)
    _close(w2)
    for attempt in (copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="save_state"):
            attempt(world)
    assert isinstance(pickle.loads(pickle.dumps(state)), WorldState)
    _close(world)


def test_a_saved_world_restores_in_a_new_process(tmp_path):
    world, cubes, box, kuka = _scene()
    _run(world, cubes, box, kuka, 20)
    world.save_state(tmp_path / "scene.state")
    original = _run(world, cubes, box, kuka, 30)
    env = dict(os.environ, PYTHONPATH=str(HERE.parents[1]))
    subprocess.run([sys.executable, str(HERE), str(tmp_path / "scene.state"), str(tmp_path / "continued.npy")],
                   check=True, env=env, cwd=HERE.parents[1], timeout=300)
    assert np.array_equal(np.load(tmp_path / "continued.npy"), original)
    _close(world)


def test_a_state_saved_while_the_stacks_regroup_keeps_the_last_results():
    """Saved right after the step at which the soft bodies first touched (their stacks regroup at the next step): the
    restored World reports the same contact forces and continues to the bit."""
    world, cubes, box, kuka = _scene()
    for k in range(12):
        _run(world, cubes, box, kuka, 1)
        if world._restack_due:
            break
    assert world._restack_due, "no regrouping within 12 steps: the scene no longer tests it"
    plane = 0
    force = world.contact_force(plane)
    state = world.save_state()
    assert state.restack_due
    original = _run(world, cubes, box, kuka, 10)
    world.restore_state(state)
    assert np.array_equal(world.contact_force(plane), force) and force[2] < 0  # the cubes press on the plane
    assert np.array_equal(_run(world, cubes, box, kuka, 10), original)
    _close(world)


def test_a_refused_restore_changes_nothing():
    """A state of a scene whose soft bodies stack otherwise (another friction), of another time step, or with a
    pybullet body more: refused with what differs, the World untouched (rigid poses, soft states, time). Saved
    after 2 steps, before anything touches (then the three cubes step as one stack; in contact, each alone)."""
    world, cubes, box, kuka = _scene()
    _run(world, cubes, box, kuka, 2)
    assert any(len(getattr(s, "members", ())) == 3 for s in world.sim.bodies)  # the premise: one stack of three
    state = world.save_state()
    other, cubes2, box2, kuka2 = _scene(friction=(0.4, 0.1, 0.4))  # cube 1 no longer stacks with cube 0
    _run(other, cubes2, box2, kuka2, 3)
    before = (_pose(other, box2), [c.positions.copy() for c in cubes2], other.t)
    with pytest.raises(InvalidInputError, match="stepped as one stack"):
        other.restore_state(state)
    assert _pose(other, box2) == before[0] and other.t == before[2]
    assert all(np.array_equal(c.positions, x) for c, x in zip(cubes2, before[1]))
    _close(other)
    third, cubes3, box3, kuka3 = _scene()
    p.createMultiBody(0.1, p.createCollisionShape(p.GEOM_SPHERE, radius=0.02, physicsClientId=third.client),
                      basePosition=[1, 1, 0.5], physicsClientId=third.client)
    with pytest.raises(InvalidInputError, match="pybullet bodies"):
        third.restore_state(state)
    _close(third)
    fourth = World(dt=0.005)
    with pytest.raises(InvalidInputError, match="dt 0.01 s"):
        fourth.restore_state(state)
    fourth.close()
    _close(world)


def _pose(world: World, body: int) -> tuple:
    return p.getBasePositionAndOrientation(body, physicsClientId=world.client)


def test_a_world_refuses_a_state_of_another_scene(tmp_path):
    world, cubes, box, kuka = _scene()
    world.step()
    state = world.save_state()
    other = World(dt=0.01)
    other.add_soft(sb.FemBody(sb.box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet10"), sb.LinearElastic(5e5, 0.33, 1000)))
    with pytest.raises(InvalidInputError, match="soft bodies of"):
        other.restore_state(state)
    (tmp_path / "junk.state").write_bytes(b"not a state")
    with pytest.raises(InvalidInputError, match="not a saved state"):
        world.restore_state(tmp_path / "junk.state")
    with pytest.raises(InvalidInputError, match="no saved state"):
        world.restore_state(tmp_path / "missing.state")
    other.close()
    _close(world)


if __name__ == "__main__":  # the new process of test_a_saved_world_restores_in_a_new_process
    w, cs, bx, kk = _scene()
    w.restore_state(sys.argv[1])
    np.save(sys.argv[2], _run(w, cs, bx, kk, 30))


def test_a_hyperelastic_body_continues_to_the_bit_and_its_state_fits_no_other_model():
    def sim(model):
        body = sb.FemBody(sb.box_mesh((0.3, 0.1, 0.1), (3, 1, 1), "tet4"), sb.LinearElastic(2e5, 0.3, 1000.0),
                          model=model)
        body.fix(np.flatnonzero(body.rest[:, 0] < body.rest[:, 0].min() + 1e-9))
        return sb.Simulation(body, 0.01, scheme="newton")

    a = sim("neo-hookean")
    for _ in range(3):
        a.step()
    saved = a.save_state()
    for _ in range(3):
        a.step()
    b = sim("neo-hookean")
    b.restore_state(saved)
    for _ in range(3):
        b.step()
    assert np.array_equal(a.bodies[0].positions, b.bodies[0].positions)
    with pytest.raises(sb.InvalidInputError, match="models"):
        sim("warped").restore_state(saved)
