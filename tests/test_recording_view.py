"""What a reviewer sees in a recording (issue 19): the blueprint's camera frames the scene, one colour range for
the whole recording, explicit distinct series colours, the Newton scheme's plots, and a picture from rerun's own
viewer running headless (skipped where it cannot start: no Vulkan driver)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from integration.recording import (  # noqa: E402
    EYE_DIRECTION, SCENE_ASPECT, VIEW_FOV, Recorder, frames, three_quarter_eye)
from experiments.scenes import hanging_tube, sheet_on_sphere  # noqa: E402
from test_recording import read  # noqa: E402


def static_components(path: Path) -> dict[str, dict[str, list]]:
    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            batch = chunk.to_record_batch()
            out.setdefault(chunk.entity_path, {}).update(
                {n: batch.column(n).to_pylist()[-1] for n in batch.schema.names if ":" in n})
    return out


def test_three_quarter_eye_frames_what_it_is_given():
    rng = np.random.default_rng(3)
    for _ in range(20):
        pts = rng.normal(size=(12, 3)) * rng.uniform(0.1, 5, size=3)
        radii = rng.uniform(0, 0.5, size=12)
        for aspect in (0.7, 1.0, 1.6):
            eye, target = three_quarter_eye(pts, radii, aspect=aspect)
            assert frames(eye, target, pts, radii, VIEW_FOV, aspect)
            # and tightly: 20% closer, something is cut
            assert not frames(target + 0.8 * (eye - target), target, pts, radii, VIEW_FOV, aspect)
    with pytest.raises(Exception, match="finite"):
        three_quarter_eye(np.array([[0, 0, np.nan]]))


def test_blueprint_camera_frames_the_sheet_and_the_swinging_tube(tmp_path):
    sheet = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(sheet, path=tmp_path / "sheet.rrd", content=("mesh", "rigid")) as rec:
        eye, target = rec.camera
        sheet.run(0.1, rec)
    lo, hi = rec.bounds
    assert np.all(lo <= [-0.5, -0.5, -0.3]) and np.all(hi >= [0.5, 0.5, 0.6])  # the sheet and the whole sphere
    assert frames(eye, target, *rec.framing(), VIEW_FOV, SCENE_ASPECT)
    view = (eye - target) / np.linalg.norm(eye - target)
    np.testing.assert_allclose(view, EYE_DIRECTION, atol=1e-12)
    elevation = math.degrees(math.asin(view[2]))
    azimuth = math.degrees(math.atan2(view[1], view[0]))
    assert 20 <= elevation <= 45 and 30 <= abs(azimuth) % 90 <= 60  # three-quarter, not side-on or top-down
    # the tube: the platform's scripted path over the scene's duration is framed from the start, and at close the
    # camera frames every position the tube took
    tube = hanging_tube("tet4", (8, 1, 2))
    seen = [tube.body.positions.min(axis=0), tube.body.positions.max(axis=0)]

    def track(world):
        rec2(world)
        seen[0] = np.minimum(seen[0], tube.body.positions.min(axis=0))
        seen[1] = np.maximum(seen[1], tube.body.positions.max(axis=0))

    with Recorder.attach(tube, path=tmp_path / "tube.rrd", content=("mesh", "rigid")) as rec2:
        lo0, hi0 = rec2.bounds
        assert hi0[0] >= 0.5 + 0.15 and lo0[2] <= -1.0  # the platform reaches x = 0.5 m at 1 s; the tip hangs at -1
        tube.run(1.2, track)
    lo, hi = rec2.bounds
    assert np.all(lo <= seen[0] + 1e-12) and np.all(hi >= seen[1] - 1e-12)
    assert frames(*rec2.camera, *rec2.framing(), VIEW_FOV, SCENE_ASPECT)
    assert RrdReader(rec2.path).blueprints()


def test_one_colour_range_for_the_whole_recording(tmp_path):
    """Every frame's colours are its element stresses on one scale, 0 .. the run's largest (sent again at close)."""
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    stresses = []
    with Recorder.attach(scene, path=tmp_path / "one.rrd", content=("mesh", "colors")) as rec:
        stresses.append(scene.body.von_mises())

        def cb(world):
            rec(world)
            stresses.append(scene.body.von_mises())

        scene.run(0.3, cb)
    e_of, f_of = scene.body.mesh.boundary_faces()
    k = scene.body.mesh.element_type.faces.shape[1]
    hi = max(1e-3 * scene.body.material.E, max(float(s[e_of].max()) for s in stresses))
    lut = (np.asarray(__import__("matplotlib").colormaps["viridis"](np.linspace(0, 1, 256))) * 255 + 0.5
           ).astype(np.uint32)
    packed = (lut[:, 0] << 24) | (lut[:, 1] << 16) | (lut[:, 2] << 8) | lut[:, 3]
    data, _ = read(rec.path)
    colors = data["/world/soft/body0"]["Mesh3D:vertex_colors"]
    assert len(colors) == len(stresses) == 31
    for c, s in zip(colors, stresses):
        expect = packed[np.clip(np.repeat(s[e_of], k).astype(np.float32) * (255.0 / hi), 0, 255).astype(int)]
        assert np.mean(np.array(c, dtype=np.uint32) == expect) > 0.99
    # a range the user sets is the range
    with Recorder.attach(scene, path=tmp_path / "fixed.rrd", content=("mesh", "colors"), color_range=(0, 2e3)) as r2:
        pass
    c = np.array(read(r2.path)[0]["/world/soft/body0"]["Mesh3D:vertex_colors"][0], dtype=np.uint32)
    s = scene.body.von_mises()
    assert np.mean(c == packed[np.clip(np.repeat(s[e_of], k) * (255.0 / 2e3), 0, 255).astype(int)]) > 0.99
    assert r2._color_scale(0.0, grow=False) == (0.0, 2e3)
    # the colour bar and the legend name the map and give the range in kPa
    static = static_components(rec.path)
    assert "/colorbar" in static
    legend = static["/legend"]["TextDocument:text"][0]
    assert "viridis" in legend and f"{1e-3 * hi:.4g} kPa" in legend and "per element" in legend.replace("each element", "per element")


def test_series_colours_are_explicit_and_distinct(tmp_path):
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(scene, path=tmp_path / "plots.rrd") as rec:
        scene.run(0.03, rec)
    static = static_components(rec.path)
    colours = []
    for entity, comps in static.items():
        if entity.startswith("/plots/"):
            got = comps.get("SeriesLines:colors") or comps.get("SeriesPoints:colors")
            names = comps.get("SeriesLines:names") or comps.get("SeriesPoints:names")
            assert got is not None and len(got) == len(names), entity
            colours += got
    assert len(colours) >= 10 and len(set(colours)) == len(colours)
    assert "/plots/monitored" in static  # the monitored coordinate has a plot of its own
    assert static["/plots/monitored"]["SeriesLines:names"] == ["z [mm]"]


def test_newton_scheme_logs_iterations_and_residual(tmp_path):
    scene = sheet_on_sphere("tet4", (2, 2, 1), scheme="newton")
    with Recorder.attach(scene, path=tmp_path / "newton.rrd", content=("mesh", "diagnostics")) as rec:
        scene.run(0.05, rec)
    data, _ = read(rec.path)
    its = np.array(data["/plots/newton/iterations"]["Scalars:scalars"])[:, 0]
    res = np.array(data["/plots/newton/residual"]["Scalars:scalars"])[:, 0]
    assert len(its) == len(res) == 5 and np.all(its >= 1)
    assert res[-1] == pytest.approx(math.log10(scene.world.sim.newton_report.residual))
    assert its[-1] == scene.world.sim.newton_report.iterations
    warped = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(warped, path=tmp_path / "warped.rrd", content=("mesh", "diagnostics")) as rec2:
        warped.run(0.02, rec2)
    assert not any(e.startswith("/plots/newton") for e in read(rec2.path)[0])


def viewers() -> set[int]:
    """Pids of headless rerun viewers bound to 127.0.0.1 (as integration.render starts them)."""
    out = set()
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"--headless" in cmd and b"127.0.0.1" in cmd and any(c.endswith(b"rerun") for c in cmd[:1]):
            out.add(int(proc.name))
    return out


def test_headless_render_shows_the_sheet(tmp_path):
    """A picture of the scene view from rerun's own viewer (headless, software Vulkan): the sheet's stress colours
    cover a sensible share of it, and nothing of them touches its edges (not cropped)."""
    from integration.render import RenderUnavailable, render

    PIL = pytest.importorskip("PIL.Image")
    if not list(Path("/usr/share/vulkan/icd.d").glob("*.json")) and not list(Path("/etc/vulkan/icd.d").glob("*.json")):
        pytest.skip("no Vulkan driver (install mesa-vulkan-drivers for the software one)")
    scene = sheet_on_sphere("tet4", (4, 4, 2))
    with Recorder.attach(scene, path=tmp_path / "pic.rrd") as rec:
        scene.run(0.5, rec)
    before = viewers()
    try:
        (png,) = render(rec.path, [0.5], tmp_path / "pic", view="scene", settle=1.0)
    except RenderUnavailable as exc:
        pytest.skip(f"the headless viewer cannot run here: {exc}")
    finally:
        assert viewers() <= before, "the headless viewer was left running"
    img = np.asarray(PIL.open(png).convert("RGB")).astype(float) / 255
    assert img.shape[0] > 300 and img.shape[1] > 400
    mx, mn = img.max(axis=2), img.min(axis=2)
    coloured = (mx - mn > 0.12) & (mx > 0.12)  # viridis is saturated; background, grid and sphere are grey
    share = coloured.mean()
    assert 0.08 < share < 0.8, share
    rows, cols = np.flatnonzero(coloured.any(axis=1)), np.flatnonzero(coloured.any(axis=0))
    assert rows[0] > 2 and cols[0] > 2 and rows[-1] < img.shape[0] - 3 and cols[-1] < img.shape[1] - 3


def test_command_line_sets_the_stress_range(tmp_path, capsys):
    from experiments import cli

    path = tmp_path / "cli.rrd"
    run = ["run", "cantilever", "--element", "tet4", "--cells", "2", "1", "1", "--duration", "0.02"]
    assert cli.main([*run, "--record", str(path), "--stress-range", "0", "50", "--color-mode", "nodal"]) == 0
    legend = static_components(path)["/legend"]["TextDocument:text"][0]
    assert "a fixed range 0 .. 50 kPa" in legend and "volume-weighted mean" in legend
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli.main([*run, "--record", str(tmp_path / "bad.rrd"), "--stress-range", "50", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "--stress-range needs LO < HI" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "bad.rrd").exists()


def test_many_series_stay_distinct_and_a_memory_budget_is_said(tmp_path, monkeypatch):
    """Past the 16 named colours, series get distinct hues; frames past the colour memory budget are named in the
    legend, not silently left on a smaller range."""
    import integration.recording as recording

    monkeypatch.setattr(recording, "FIELD_BUDGET", 1)  # keep nothing
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(scene, path=tmp_path / "many.rrd", monitor=list(range(12))) as rec:
        scene.run(0.2, rec)
    static = static_components(rec.path)
    colours = [c for e, comps in static.items() if e.startswith("/plots/")
               for c in (comps.get("SeriesLines:colors") or comps.get("SeriesPoints:colors"))]
    assert len(colours) > 40 and len(set(colours)) == len(colours)
    legend = static["/legend"]["TextDocument:text"][0]
    assert "past the recorder's memory budget" in legend


def test_contacts_view_frames_the_rigid_links_and_the_arrows(tmp_path):
    from integration.recording import CONTACTS_ASPECT

    scene = sheet_on_sphere("tet4", (2, 2, 1))
    world = scene.world
    with Recorder.attach(scene, path=tmp_path / "contacts.rrd") as rec:
        while world.t < 0.15 or not any(r.active.any() for _, r in world.contact_results.values()):
            assert world.t < 1.0, "the sheet never touched the sphere"
            world.step()
            rec(world)
    pts, radii = rec.framing(soft=False)
    lo, hi = (pts - radii[:, None]).min(axis=0), (pts + radii[:, None]).max(axis=0)
    np.testing.assert_allclose(lo[:2], [-0.3, -0.3], atol=1e-9)  # the sphere, not the sheet
    data, _ = read(rec.path)
    p = np.array(data["/world/contacts/points"]["Points3D:positions"][-1])
    v = np.array(data["/world/contacts/arrows"]["Arrows3D:vectors"][-1])
    assert len(p) and np.all(p + v >= lo - 1e-6) and np.all(p + v <= hi + 1e-6)
    # the arrows point out of the sphere, their length the force times the scale (weight: half the sheet's size)
    assert np.all(np.einsum("ij,ij->i", v, p) > 0)
    force = sum(r.force[r.active].sum(axis=0) for _, r in scene.world.contact_results.values())
    np.testing.assert_allclose(v.sum(axis=0), force * rec.force_scale, rtol=1e-5, atol=1e-9)
    weight = scene.body.total_mass * 9.81
    assert rec.force_scale == pytest.approx(0.5 * 1.0 / weight, rel=0.05)
    assert frames(*three_quarter_eye(pts, radii, aspect=CONTACTS_ASPECT), pts, radii, VIEW_FOV, CONTACTS_ASPECT)


def test_frame_soft_frames_a_small_body_in_a_large_scene(tmp_path):
    """Recorder(frame="soft"): a 5 cm soft cube on a 2 m table is framed with room of its own size around it,
    not the table (which frame="all" takes in); a bad value is refused."""
    import softbody as sb
    from integration import World

    def scene():
        world = World(dt=0.01)
        world.add_box((1.0, 0.6, 0.02), position=(0, 0, -0.02), name="table")
        cube = sb.FemBody(sb.box_mesh((0.05, 0.05, 0.05), (1, 1, 1), "tet4", center=(0.3, 0.1, 0.0251)),
                          sb.LinearElastic(1e5, 0.3, 500.0))
        world.add_soft(cube)
        return world, cube

    world, cube = scene()
    with Recorder(world, path=tmp_path / "soft.rrd", content=("mesh", "rigid"), frame="soft") as rec:
        lo, hi = rec.bounds
        assert frames(*rec.camera, *rec.framing(), VIEW_FOV, SCENE_ASPECT)
    c_lo, c_hi = cube.positions.min(axis=0), cube.positions.max(axis=0)
    assert np.all(lo <= c_lo) and np.all(hi >= c_hi) and np.all(hi - lo <= 3 * 0.05 + 1e-9)
    world, _ = scene()
    with Recorder(world, path=tmp_path / "all.rrd", content=("mesh", "rigid")) as rec:
        assert np.all(rec.bounds[1] - rec.bounds[0] >= [2.0, 1.2, 0.04])  # the table whole
    with pytest.raises(Exception, match="frame"):
        Recorder(world, path=tmp_path / "bad.rrd", frame="table")
