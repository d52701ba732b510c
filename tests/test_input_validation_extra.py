"""Input validation beyond tests/test_validation.py: every place a user passes data (materials, meshes,
simulation options, prescribed motions at run time, the World's methods, scene builders, CLI flags)
rejects bad values with a ValueError subclass (softbody.InvalidInputError) that names the value."""
from __future__ import annotations


import numpy as np
import pytest

import softbody as sb
from conftest import raises_naming
from experiments import scenes
from integration.world import World

MAT = sb.LinearElastic(1e5, 0.3, 1000.0)
CUBE = sb.box_mesh((1, 1, 1), (1, 1, 1), "hex8")


# ---------------------------------------------------------------------------- materials and meshes


@pytest.mark.parametrize("args, shown", [(("abc", 0.3, 1000.0), "'abc'"), ((None, 0.3, 1000.0), "None"),
                                         ((1e5, "x", 1000.0), "'x'"), ((1e5, 0.3, "dense"), "'dense'")])
def test_material_non_numeric(args, shown):
    raises_naming(shown, call=lambda: sb.LinearElastic(*args))


def test_mesh_non_numeric():
    raises_naming("nodes", call=lambda: sb.Mesh([["a", "b", "c"]] * 8, [list(range(8))], "hex8"), exc=sb.MeshError)
    raises_naming("<U1", call=lambda: sb.Mesh(CUBE.nodes, [list("01234567")], "hex8"), exc=sb.MeshError)


@pytest.mark.parametrize("center, shown", [((0.0, 0.0), "(0.0, 0.0)"), ((np.nan, 0.0, 0.0), "nan"), ("here", "'here'")])
def test_mesh_builder_center(center, shown):
    raises_naming("center", shown, call=lambda: sb.box_mesh((1, 1, 1), (1, 1, 1), "tet4", center=center))
    raises_naming("center", shown, call=lambda: sb.ball_mesh(0.1, 1, "tet4", center=center))


@pytest.mark.parametrize("radius, shown", [("big", "'big'"), (0.0, "0.0"), (float("inf"), "inf")])
def test_ball_radius(radius, shown):
    raises_naming("radius", shown, call=lambda: sb.ball_mesh(radius, 2))


def test_tube_arguments():
    raises_naming("r_inner=0.2", call=lambda: sb.tube_mesh(0.1, 0.2, 1.0, (4, 1, 1)))
    raises_naming("5", call=lambda: sb.tube_mesh(0.1, 0.05, 1.0, (5, 1, 1), "tet4"))
    raises_naming("(4, 0, 1)", call=lambda: sb.tube_mesh(0.1, 0.05, 1.0, (4, 0, 1)))


# ---------------------------------------------------------------------------- simulation options


def _body():
    return sb.FemBody(CUBE, MAT)


@pytest.mark.parametrize("bound, shown", [(-1.0, "-1.0"), (0.0, "0.0"), (float("nan"), "nan"),
                                          (float("inf"), "inf"), ("big", "'big'")])
def test_max_energy(bound, shown):
    raises_naming("max_energy", shown, call=lambda: sb.Simulation(_body(), 0.01, max_energy=bound))


def test_simulation_arguments():
    raises_naming("'abc'", call=lambda: sb.Simulation(_body(), "abc"))
    raises_naming("'cholmod'", call=lambda: sb.Simulation(_body(), 0.01, solver="cholmod"))
    raises_naming("'cholmod'", call=lambda: sb.Simulation([], 0.01, solver="cholmod"))  # no bodies yet
    raises_naming("(0, 0)", call=lambda: sb.Simulation(_body(), 0.01, gravity=(0, 0)))
    raises_naming("str", call=lambda: sb.Simulation(["body"], 0.01))
    raises_naming("nan", call=lambda: sb.Simulation(_body(), 0.01).run(float("nan")))


def test_solve_static_forces():
    body = _body()
    body.fix([0, 1, 2, 3])
    raises_naming("(7, 3)", call=lambda: sb.solve_static(body, forces=np.zeros((7, 3))))
    bad = np.zeros((8, 3))
    bad[5, 2] = np.inf
    raises_naming("non-finite", call=lambda: sb.solve_static(body, forces=bad))
    u = sb.solve_static(body, forces=np.zeros(24))  # a flat (3N,) array is fine
    assert np.isfinite(u).all()


def test_body_arguments():
    raises_naming("'x'", call=lambda: sb.FemBody(CUBE, MAT, damping="x"))
    raises_naming("nan", call=lambda: sb.FemBody(CUBE, MAT, damping=(float("nan"), 0.0)))
    body = _body()
    raises_naming("(3, 3)", call=lambda: body.elastic_forces(np.zeros((3, 3))))
    raises_naming("float64", call=lambda: body.fix([0.5]))
    raises_naming("(8,)", "(3,)", call=lambda: body.fix(np.array([True, False, True])))


# ---------------------------------------------------------------------------- prescribed motion at run time


@pytest.mark.parametrize("name", ["positions", "velocities"])
def test_state_assignment_is_checked(name):
    """Assigning body.positions / body.velocities refuses NaN, inf and wrong shapes, naming the first nodes;
    in-place writes (what the library and the tests do) keep working on a writable array."""
    body = sb.FemBody(sb.box_mesh((1, 1, 1), (2, 2, 2), "tet4"), MAT)
    good = getattr(body, name).copy() + 0.25
    x = good.copy()
    x[[4, 11, 12, 13, 20, 21, 26], 1] = [np.nan, np.inf, np.nan, np.nan, -np.inf, np.nan, np.nan]
    msg = raises_naming(name, "[4, 11, 12, 13, 20]", "7 of 27", call=lambda: setattr(body, name, x))
    assert "finite" in msg
    raises_naming(name, "(27, 3)", "(3, 3)", call=lambda: setattr(body, name, np.zeros((3, 3))))
    raises_naming(name, "(27, 3)", "(81,)", call=lambda: setattr(body, name, np.zeros(81)))
    raises_naming(name, "str", call=lambda: setattr(body, name, "origin"))
    assert np.all(np.isfinite(getattr(body, name)))  # refused assignments change nothing
    setattr(body, name, good.tolist())  # any (N, 3) array-like of numbers
    np.testing.assert_array_equal(getattr(body, name), good)
    getattr(body, name)[:] = 0.0
    getattr(body, name)[3] += 1.0
    assert getattr(body, name).sum() == 3.0 and getattr(body, name).flags.writeable


def test_prescribed_motion_checked_every_step():
    body = _body()
    top = np.flatnonzero(np.isclose(CUBE.nodes[:, 2], 0.5))
    Xt = CUBE.nodes[top]
    body.prescribe(top, lambda t: Xt if t < 0.015 else Xt[:2])  # wrong shape from t = 0.02 on
    sim = sb.Simulation(body, 0.01)
    sim.step()
    raises_naming("(4, 3)", "(2, 3)", "0.02", call=sim.step)
    assert sim.steps == 1

    body = _body()
    body.prescribe(top, lambda t: Xt.T if t > 0 else Xt)  # (3, 4): same size, wrong layout, never reshaped
    sim = sb.Simulation(body, 0.01)
    raises_naming("(3, 4)", call=sim.step)

    body = _body()
    body.prescribe(top, lambda t: None if t > 0 else Xt)
    raises_naming("0.01", call=sb.Simulation(body, 0.01).step)

    body = _body()
    raises_naming("nan", call=lambda: body.prescribe(top, lambda t: Xt * np.nan))
    assert not body.prescribed


def test_nan_motion_names_nodes():
    body = _body()
    top = np.flatnonzero(np.isclose(CUBE.nodes[:, 2], 0.5))
    Xt = CUBE.nodes[top].copy()

    def motion(t):
        p = Xt.copy()
        if t > 0.005:
            p[2, 0] = np.inf
        return p

    body.prescribe(top, motion)
    x = body.positions.copy()
    msg = raises_naming(str(top[2]), "0.01", call=sb.Simulation(body, 0.01).step)
    assert "non-finite" in msg
    np.testing.assert_array_equal(body.positions, x)


# ---------------------------------------------------------------------------- World


@pytest.fixture
def world():
    with World(dt=0.01) as w:
        yield w


def test_world_constructor():
    raises_naming("0.0", call=lambda: World(dt=0.0))
    raises_naming("nan", call=lambda: World(gravity=(0, 0, float("nan"))))
    raises_naming("-1.0", call=lambda: World(contact_margin=-1))
    raises_naming("'nope'", call=lambda: World(solver="nope"))


def test_world_rigid_bodies(world):
    raises_naming("0.0", call=lambda: world.add_sphere(0.0))
    raises_naming("nan", call=lambda: world.add_sphere(0.1, position=(float("nan"), 0, 0)))
    raises_naming("-1.0", call=lambda: world.add_sphere(0.1, mass=-1))
    raises_naming("-1.0", call=lambda: world.add_sphere(0.1, friction=-1.0))
    raises_naming("'rough'", call=lambda: world.add_sphere(0.1, friction="rough"))
    raises_naming("(1, -1, 1)", call=lambda: world.add_box((1, -1, 1)))
    raises_naming("(0, 0, 0, 0)", call=lambda: world.add_box((1, 1, 1), orientation=(0, 0, 0, 0)))
    raises_naming("mass", call=lambda: world.add_box((1, 1, 1), mass=1.0, motion=lambda t: (0, 0, 0)))
    raises_naming("nan", call=lambda: world.add_box((1, 1, 1), motion=lambda t: (float("nan"), 0, 0)))
    raises_naming("normal", call=lambda: world.add_plane(normal=(0, 0, 0)))
    raises_naming("'/nonexistent.obj'", call=lambda: world.add_mesh("/nonexistent.obj"))
    raises_naming("99", call=lambda: world.rigid(99))


def test_world_kinematic_script_failing_later(world):
    """A kinematic script that returns NaN mid-run: the step refuses before moving anything."""
    body = sb.FemBody(sb.box_mesh((0.2, 0.2, 0.2), (1, 1, 1), "tet4", center=(0, 0, 1.0)), MAT)
    world.add_box((0.1, 0.1, 0.1), position=(2, 0, 0), motion=lambda t: (2.0, 0.0, 0.0) if t < 0.015 else (np.nan, 0, 0))
    world.add_soft(body)
    world.step()
    x = body.positions.copy()
    raises_naming("nan", call=world.step)
    np.testing.assert_array_equal(body.positions, x)
    assert world.t == pytest.approx(0.01)


def test_world_soft_bodies(world):
    body = _body()
    raises_naming("str", call=lambda: world.add_soft("body"))
    raises_naming("-1.0", call=lambda: world.add_soft(body, friction=-1))
    raises_naming("'x'", call=lambda: world.add_soft(body, friction="x"))
    raises_naming("add_soft", call=lambda: world.attach(body, [0], 0))
    world.add_soft(body)
    raises_naming("already", call=lambda: world.add_soft(body))
    sphere = world.add_sphere(0.1, position=(5, 5, 5))
    raises_naming("100", call=lambda: world.attach(body, [100], sphere))
    raises_naming("nan", call=lambda: world.run(float("nan")))


# ---------------------------------------------------------------------------- scenes


@pytest.mark.parametrize("builder, kwargs, shown", [
    ("cantilever", dict(cells=(0, 1, 1)), "(0, 1, 1)"),
    ("cantilever", dict(element="hex20"), "'hex20'"),
    ("cantilever", dict(dt=-0.01), "-0.01"),
    ("cantilever", dict(E=-5.0), "-5.0"),
    ("sheet-on-sphere", dict(nu=0.5), "0.5"),
    ("sheet-on-sphere", dict(friction=-0.1), "-0.1"),
    ("sheet-on-sphere", dict(density=0.0), "0.0"),
    ("hanging-tube", dict(cells=(5, 1, 2)), "5"),
])
def test_scene_builders(builder, kwargs, shown):
    raises_naming(shown, call=lambda: scenes.build_scene(builder, **kwargs))


def test_unknown_scene():
    raises_naming("'nope'", "cantilever", call=lambda: scenes.build_scene("nope"))


# ---------------------------------------------------------------------------- CLI flags


@pytest.mark.parametrize("argv, shown", [
    (["run", "cantilever", "--dt", "-1"], "'-1'"),
    (["run", "cantilever", "--dt", "nan"], "'nan'"),
    (["run", "cantilever", "--dt", "fast"], "'fast'"),
    (["run", "cantilever", "--cells", "0", "1", "1"], "'0'"),
    (["run", "cantilever", "--cells", "2.5", "1", "1"], "'2.5'"),
    (["run", "cantilever", "--element", "hex20"], "'hex20'"),
    (["run", "cantilever", "--duration", "-3"], "'-3'"),
    (["run", "no-such-scene"], "'no-such-scene'"),
])
def test_cli_flags(argv, shown, capsys):
    from experiments.cli import main

    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert shown in err, err
