"""Rerun recordings: written by integration.recording.Recorder, read back with rerun's own reader
(rerun.chunk.RrdReader) and checked with the ``rerun rrd verify`` command line."""
from __future__ import annotations

import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

import softbody  # noqa: E402
from integration.recording import Recorder, default_path  # noqa: E402
from experiments.scenes import hanging_tube, sheet_on_sphere  # noqa: E402

DURATION = 0.3  # 30 steps of 0.01 s


def rerun_cli() -> list[str] | None:
    """The rerun binary shipped with rerun-sdk: next to the interpreter, in rerun_cli, or ``python -m rerun``."""
    exe = Path(sys.executable).parent / ("rerun.exe" if sys.platform == "win32" else "rerun")
    if exe.exists():
        return [str(exe)]
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / exe.name
        if exe.exists():
            return [str(exe)]
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found:
        return [found]
    probe = subprocess.run([sys.executable, "-m", "rerun", "--version"], capture_output=True, text=True)
    return [sys.executable, "-m", "rerun"] if probe.returncode == 0 else None


def verify(path: Path) -> None:
    cli = rerun_cli()
    if cli is None:
        pytest.skip("the rerun command line (rerun rrd verify) is not available in this environment")
    out = subprocess.run([*cli, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, f"rerun rrd verify rejected {path}:\n{out.stdout}\n{out.stderr}"


def read(path: Path) -> tuple[dict[str, dict[str, list]], set[str]]:
    """Temporal rows per entity and component column (sorted by sim_time, as python lists; where a column was
    sent again for the same time, as the colours are at close, the later value, as the viewer shows it), with
    the entity's times under "sim_time" [s]; and the static entity paths."""
    rows: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    static = set()
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
            continue
        batch = chunk.to_record_batch()
        if "sim_time" not in batch.schema.names:
            continue
        times = (np.array(batch.column("sim_time").cast("int64").to_pylist())).tolist()  # [ns]
        for name in batch.schema.names:
            if name == "sim_time" or not name.split(":")[0][:1].isupper():
                continue
            for t, v in zip(times, batch.column(name).to_pylist()):
                if v is not None:
                    rows[chunk.entity_path][name].append((t, v))
    out = {}
    for entity, cols in rows.items():
        out[entity] = {}
        all_times = set()
        for name, tv in cols.items():
            latest = dict(tv)  # the later row at the same time wins
            ts = sorted(latest)
            all_times.update(ts)
            out[entity][name] = [latest[t] for t in ts]
        out[entity]["sim_time"] = (np.array(sorted(all_times)) * 1e-9).tolist()
    return out, static


def seconds(col) -> np.ndarray:
    return np.asarray(col, dtype=float)


def run_recorded(tmp_path: Path, every: int = 1, fail_after: int | None = None, **options):
    """sheet-on-sphere tet4 (2,2,1) recorded for DURATION; returns the recorder and the (t, x) of the
    monitored node after every step, collected independently of the recorder."""
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    truth = [(scene.world.t, scene.body.positions[scene.monitor].copy())]
    path = tmp_path / "run.rrd"

    def callback(world):
        if fail_after is not None and world.sim.steps > fail_after:
            raise RuntimeError("fault injected by the test")
        rec(world)
        truth.append((world.t, scene.body.positions[scene.monitor].copy()))

    with Recorder.attach(scene, path=path, every=every, **options) as rec:
        scene.run(DURATION, callback)
    return rec, scene, truth


def test_recording_round_trip(tmp_path):
    rec, scene, truth = run_recorded(tmp_path)
    assert rec.closed and rec.path.exists()
    verify(rec.path)
    data, static = read(rec.path)
    node = f"plots/monitor/node{scene.monitor}"
    for entity in ["world/soft/body0", "world/contacts/points", "world/contacts/arrows", *(f"{node}/{a}" for a in "xyz"),
                   "world/monitor", "plots/energy", "plots/step_time", "plots/setup_time", "plots/contacts", "plots/color_range"]:
        assert "/" + entity in data, f"{entity} missing; have {sorted(data)}"
    for entity in ["world", "world/soft/body0", "world/rigid/sphere_0", "legend"]:
        assert "/" + entity in static, f"static {entity} missing; have {sorted(static)}"
    # frame 0 (state at attach) + one frame per step, on sim_time
    steps = int(round(DURATION / scene.world.dt))
    mesh = data["/world/soft/body0"]
    assert len(mesh["sim_time"]) == steps + 1 == rec.frames
    t_true = np.array([t for t, _ in truth])
    np.testing.assert_allclose(seconds(mesh["sim_time"]), t_true, atol=1e-9)
    # the stored trajectory is exactly what the simulation produced, in mm; the monitored coordinate has a plot
    # of its own
    x_true = np.array([x for _, x in truth])
    for i, axis in enumerate("xyz"):  # a plot each
        traj = data[f"/{node}/{axis}"]
        np.testing.assert_allclose(seconds(traj["sim_time"]), t_true, atol=1e-9)
        np.testing.assert_array_equal(np.array(traj["Scalars:scalars"])[:, 0], 1e3 * x_true[:, i])
    own = np.array(data["/plots/monitored"]["Scalars:scalars"])[:, 0]
    np.testing.assert_array_equal(own, 1e3 * np.array([x[scene.axis] for _, x in truth]))
    # the sheet really falls: the monitored z goes down
    assert truth[-1][1][2] < truth[0][1][2] - 0.01
    # mesh vertices: every boundary face of an element has vertices of its own (tet4: 3), coloured by that
    # element's von Mises stress in one range for the whole recording: 0 .. the run's largest (at least 1e-3 E)
    body = scene.body
    e_of, f_of = body.mesh.boundary_faces()
    faces = body.mesh.element_type.faces[f_of]
    vertex_nodes = body.mesh.elements[e_of[:, None], faces].ravel()
    last = np.array(mesh["Mesh3D:vertex_positions"][-1])
    np.testing.assert_allclose(last, body.positions[vertex_nodes], atol=1e-6)
    normals = np.array(mesh["Mesh3D:vertex_normals"][-1])
    assert normals.shape == last.shape and len(mesh["Mesh3D:vertex_normals"]) == steps + 1
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    outward = np.einsum("ij,ij->i", normals, last - body.positions.mean(axis=0))
    assert np.mean(outward > 0) > 0.9  # normals point out of the body
    vm = body.von_mises()
    ranges = np.array(data["/plots/color_range"]["Scalars:scalars"])
    np.testing.assert_allclose(ranges[-1], 1e-3 * np.array([vm[e_of].min(), vm[e_of].max()]), rtol=1e-6)
    hi = max(1e-3 * body.material.E, 1e3 * ranges[:, 1].max())  # [Pa]
    assert hi > 1e-3 * body.material.E  # the impact loaded the sheet above the floor
    lut = (np.asarray(__import__("matplotlib").colormaps["viridis"](np.linspace(0, 1, 256))) * 255 + 0.5
           ).astype(np.uint32)
    packed = (lut[:, 0] << 24) | (lut[:, 1] << 16) | (lut[:, 2] << 8) | lut[:, 3]  # rerun's 0xRRGGBBAA
    expect = packed[np.clip(vm[np.repeat(e_of, faces.shape[1])].astype(np.float32) * (255.0 / hi), 0, 255
                            ).astype(int)]
    colors = np.array(mesh["Mesh3D:vertex_colors"][-1], dtype=np.uint32)
    assert np.mean(colors == expect) > 0.99 and len(np.unique(colors)) > 1
    for k in (1, len(mesh["Mesh3D:vertex_colors"]) // 2):  # early frames too: in the final range, re-sent at close
        index = np.array([np.flatnonzero(packed == c)[0] for c in mesh["Mesh3D:vertex_colors"][k]])
        assert index.max() <= 255 * 1e3 * ranges[k, 1] / hi + 1
    # diagnostics agree with the World's own energies at the end; the total is there to check
    energy = np.array(data["/plots/energy"]["Scalars:scalars"])
    e = scene.world.energy()
    np.testing.assert_allclose(energy[-1], [e["soft_kinetic"], e["elastic"], e["soft_potential"], e["rigid_kinetic"],
                                            e["rigid_potential"], e["total"]], rtol=1e-9)
    np.testing.assert_allclose(energy[:, 5], energy[:, :5].sum(axis=1), rtol=1e-12)
    assert energy[0, 2] == pytest.approx(-body.node_mass @ (body.rest @ scene.world.gravity))  # at rest: all potential
    assert np.all(np.diff(energy[:, 5]) <= 1e-9 * abs(energy[0, 5]))  # damping and contact only take energy out
    # the first step (set-up) is logged apart; the step-time series starts at the second step
    setup = data["/plots/setup_time"]
    assert seconds(setup["sim_time"]) == pytest.approx([0.01]) and setup["Scalars:scalars"][0][0] > 0
    step_times = data["/plots/step_time"]
    np.testing.assert_allclose(seconds(step_times["sim_time"]), t_true[2:], atol=1e-9)
    active, _ = data["/plots/contacts"]["Scalars:scalars"][-1]
    assert active == sum(int(r.active.sum()) for _, r in scene.world.contact_results.values())
    # a blueprint travels with the recording
    assert RrdReader(rec.path).blueprints()


@pytest.mark.parametrize("every", [3, 7])
def test_every_kth_step(tmp_path, every):
    rec, scene, truth = run_recorded(tmp_path, every=every, content=("mesh", "monitor"))
    verify(rec.path)
    data, _ = read(rec.path)
    steps = int(round(DURATION / scene.world.dt))
    expected = [truth[0]] + [truth[k] for k in range(every, steps + 1, every)]
    for i, axis in enumerate("xyz"):
        traj = data[f"/plots/monitor/node{scene.monitor}/{axis}"]
        assert len(traj["sim_time"]) == len(data["/world/soft/body0"]["sim_time"]) == 1 + steps // every
        np.testing.assert_allclose(seconds(traj["sim_time"]), [t for t, _ in expected], atol=1e-9)
        np.testing.assert_array_equal(np.array(traj["Scalars:scalars"])[:, 0],
                                      1e3 * np.array([x[i] for _, x in expected]))
    # content that is off is neither computed nor logged
    assert not any(e.startswith(("/plots/energy", "/world/contacts", "/world/rigid")) for e in data)


def static_series(path: Path) -> dict[str, list[str]]:
    """The series names logged (static SeriesLines / SeriesPoints) per entity path of a recording."""
    out: dict[str, list[str]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            batch = chunk.to_record_batch()
            for name in ("SeriesLines:names", "SeriesPoints:names"):
                if name in batch.schema.names:
                    out[chunk.entity_path] = batch.column(name).to_pylist()[-1]
    return out


def walk(item, around=()):
    """(view, names of the containers around it) for every view of a blueprint or container, depth first."""
    import rerun.blueprint as rrb

    if isinstance(item, rrb.Blueprint):
        item = item.root_container
    if isinstance(item, rrb.Container):
        for child in item.contents:
            yield from walk(child, (*around, item.name))
    else:
        yield item, around


def test_blueprint_plots_one_series_without_a_legend_several_with_it_top_right(tmp_path):
    """The monitored coordinate and each of x, y and z have a plot of their own, without a legend (the view's
    name says what it is); a plot of several series has its legend top right, away from a settling curve's
    start (the sheet's corner falls from the top left)."""
    import rerun.blueprint as rrb

    from integration.recording import PLOT_LEGEND_CORNER

    rec, scene, truth = run_recorded(tmp_path)
    series = static_series(rec.path)
    views = [(v, around) for v, around in walk(rec._blueprint()) if isinstance(v, rrb.TimeSeriesView)]
    assert len(views) >= 7
    for view, _ in views:
        names = series[view.origin]
        legend = view.properties["PlotLegend"]
        shown = legend.visible.as_arrow_array().to_pylist() == [True]
        assert shown == (len(names) > 1), (view.name, names)
        if shown:
            assert legend.corner.as_arrow_array().to_pylist() == [PLOT_LEGEND_CORNER.value] == [
                rrb.Corner2D.RightTop.value], view.name
    by_origin = {v.origin: (v, around) for v, around in views}
    monitored, _ = by_origin["/plots/monitored"]
    assert monitored.name == f"z of node {scene.monitor} [mm]" and series["/plots/monitored"] == ["z [mm]"]
    node = f"/plots/monitor/node{scene.monitor}"
    xyz = [by_origin[f"{node}/{a}"] for a in "xyz"]  # one view per coordinate, side by side in one tab
    assert [v.name for v, _ in xyz] == [f"node {scene.monitor}: {a} [mm]" for a in "xyz"]
    assert all(series[f"{node}/{a}"] == [f"{a} [mm]"] for a in "xyz")
    assert len({around for _, around in xyz}) == 1 and xyz[0][1][-1] == f"node {scene.monitor}: x, y, z [mm]"
    # the reason: the corner's x and y move alike (the sheet is square) and far less than z
    x = np.array([p for _, p in truth])
    np.testing.assert_allclose(x[:, 0] - x[0, 0], x[:, 1] - x[0, 1], atol=2e-3)
    assert np.ptp(x[:, 2]) > 5 * np.ptp(x[:, 0])


def test_the_legend_text_fits_its_view(tmp_path):
    """The legend's three paragraphs (colours, contacts, set-up) fit their view of a 1600 x 1000 viewer: the
    text wrapped at the view's width in characters of rerun's font (7 px on average, measured on the pictures
    of docs/recording.md at 6.3 px), 17 px a line (measured 15.5), a blank line between paragraphs."""
    import re

    import textwrap

    from integration.recording import LEFT_ROW_SHARES, UNDER_COLUMN_SHARES

    rec, _, _ = run_recorded(tmp_path)
    text = None
    for chunk in RrdReader(rec.path).stream():
        if chunk.is_static and chunk.entity_path == "/legend":
            text = chunk.to_record_batch().column("TextDocument:text").to_pylist()[-1][0]
    assert text is not None
    paragraphs = text.split("\n\n")
    assert [p.split("**")[1] for p in paragraphs] == ["Colours", "Contacts", "Set-up"]
    width = 1600 * 3 / 5 * UNDER_COLUMN_SHARES[1] / sum(UNDER_COLUMN_SHARES) - 20  # the right column: 2 / 5
    height = (1000 - 70) * LEFT_ROW_SHARES[1] / sum(LEFT_ROW_SHARES) - 24 - 16  # bars, view title, padding
    plain = [re.sub(r"[*`]", "", p) for p in paragraphs]
    lines = sum(len(textwrap.wrap(p, int(width / 7))) for p in plain) + len(plain) - 1
    assert lines * 17 <= height, (lines, height, text)


def test_interrupted_run_leaves_valid_recording(tmp_path):
    fail_after = 12
    with pytest.raises(RuntimeError, match="fault injected"):
        run_recorded(tmp_path, fail_after=fail_after, batch=5)  # faults between two batches
    path = tmp_path / "run.rrd"
    verify(path)
    data, _ = read(path)
    times = seconds(data["/world/soft/body0"]["sim_time"])
    assert len(times) == fail_after + 1  # frame 0 and every step before the fault
    np.testing.assert_allclose(times, 0.01 * np.arange(fail_after + 1), atol=1e-9)
    assert len(data["/plots/energy"]["sim_time"]) == fail_after + 1


def test_keyboard_interrupt_is_not_swallowed(tmp_path):
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    path = tmp_path / "ctrl-c.rrd"

    def callback(world):
        rec(world)
        if world.sim.steps == 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with Recorder.attach(scene, path=path) as rec:
            scene.run(DURATION, callback)
    verify(path)
    data, _ = read(path)
    assert len(data["/world/soft/body0"]["sim_time"]) == 5


def test_recording_does_not_change_the_simulation(tmp_path):
    a = sheet_on_sphere("tet4", (2, 2, 1))
    a.run(0.1)
    b = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(b, path=tmp_path / "same.rrd") as rec:
        b.run(0.1, rec)
    # equal up to the threaded factorisation's round-off
    np.testing.assert_allclose(b.body.positions, a.body.positions, rtol=0, atol=1e-9)
    with pytest.raises(RuntimeError, match="closed"):
        rec(b.world)


def test_rigid_shapes_attachments_and_two_recordings(tmp_path):
    """A kinematic box with attached nodes (hanging tube) recorded next to a second recording."""
    tube = hanging_tube("tet4", (8, 1, 2))
    sheet = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(tube, path=tmp_path / "tube.rrd", color_by="displacement") as r1, \
            Recorder.attach(sheet, path=tmp_path / "sheet.rrd", content=("mesh",)) as r2:
        for _ in range(5):
            tube.world.step()
            r1(tube.world)
            sheet.world.step()
            r2(sheet.world)
    for r in (r1, r2):
        verify(r.path)
    data, static = read(r1.path)
    platform = next(e for e in data if e.startswith("/world/rigid/platform"))
    assert len(data[platform]["Transform3D:translation"]) == 6
    np.testing.assert_allclose(data[platform]["Transform3D:translation"][-1][0], tube.world.rigid(0).pose()[0], atol=1e-6)
    attached = data["/world/attachments"]["Points3D:positions"][-1]
    ids = tube.world.attachments[0].nodes
    np.testing.assert_allclose(attached, tube.body.positions[ids], atol=1e-6)
    data2, _ = read(r2.path)
    assert sorted(data2) == ["/world/soft/body0"]
    assert len(data2["/world/soft/body0"]["sim_time"]) == 6


@pytest.mark.parametrize("color_by", ["von_mises", "displacement"])
def test_a_body_at_rest_shows_no_colours(color_by, tmp_path):
    """The t = 0 frame of an unloaded sheet (stresses of round-off size) is all at the bottom of the colour map,
    whose range is 0 .. 1e-3 of E (or of the sheet's size), not its own min..max."""
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    with Recorder.attach(scene, path=tmp_path / "rest.rrd", color_by=color_by, content=("mesh", "colors")) as rec:
        pass
    data, static = read(rec.path)
    colors = np.array(data["/world/soft/body0"]["Mesh3D:vertex_colors"][0], dtype=np.uint32)
    lut = (np.asarray(__import__("matplotlib").colormaps["viridis"](0.0)) * 255 + 0.5).astype(np.uint32)
    low = (lut[0] << 24) | (lut[1] << 16) | (lut[2] << 8) | lut[3]  # rerun packs colours as 0xRRGGBBAA
    assert np.all(colors == low), np.unique(colors)
    floor = 1e-3 * (scene.body.material.E if color_by == "von_mises" else 1.0)  # the sheet is 1 m wide
    fmin, fmax = data["/plots/color_range"]["Scalars:scalars"][0]  # in kPa or mm
    assert fmax < 1e-6 * floor * (1e-3 if color_by == "von_mises" else 1e3)  # [Pa] -> kPa, [m] -> mm
    assert rec._color_scale(0.0, grow=False) == (0.0, pytest.approx(floor))


def test_default_path_is_descriptive(tmp_path):
    scene = sheet_on_sphere("tet4", (2, 2, 1))
    p = default_path(scene, directory=tmp_path / "logs")
    assert p.parent == tmp_path / "logs" and p.suffix == ".rrd"
    assert p.name.startswith("sheet-on-sphere_tet4_2x2x1_")
    with Recorder.attach(scene, directory=tmp_path / "logs", content=("mesh",)) as rec:
        pass
    assert rec.path.parent == tmp_path / "logs" and rec.path.exists()
    assert rec.path.name.startswith("sheet-on-sphere_tet4_2x2x1_")


def test_bare_simulation_and_overlapping_recorders(tmp_path):
    """A softbody.Simulation (no World) recorded twice at once; recorders closed in either order."""
    mesh = softbody.box_mesh((1.0, 0.1, 0.1), (4, 1, 1), "tet4", center=(0.5, 0, 0))
    body = softbody.FemBody(mesh, softbody.LinearElastic(5e6, 0.3, 1000.0))
    body.fix(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    sim = softbody.Simulation(body, 0.01)
    r1 = Recorder.attach(sim, path=tmp_path / "a.rrd", monitor=[int(np.argmax(mesh.nodes[:, 0]))])
    r2 = Recorder.attach(sim, path=tmp_path / "b.rrd", every=2, color_by="displacement")

    def both(s):
        r1(s)
        r2(s)

    sim.run(0.1, both)
    r1.close()  # the older recorder first
    sim.run(0.02, r2)
    r2.close()
    for r, frames in ((r1, 11), (r2, 7)):
        verify(r.path)
        data, _ = read(r.path)
        assert len(data["/world/soft/body0"]["sim_time"]) == frames
        assert not any(e.startswith(("/world/rigid", "/world/contacts", "/plots/contacts")) for e in data)
    ke, ee, pe, total = data["/plots/energy"]["Scalars:scalars"][-1]
    assert ke == pytest.approx(body.kinetic_energy(), rel=1e-9) and ee == pytest.approx(body.elastic_energy(), rel=1e-9)
    assert pe == pytest.approx(body.gravitational_energy(sim.gravity), rel=1e-9) and total == pytest.approx(ke + ee + pe)
    # every second step recorded: frame 0 has no step time, the set-up step is not a frame
    assert seconds(data["/plots/step_time"]["sim_time"]) == pytest.approx(0.02 * np.arange(1, frames))
    assert seconds(data["/plots/setup_time"]["sim_time"]) == pytest.approx([0.01])


SCRIPT = """
import sys
from integration.recording import Recorder
from experiments.scenes import sheet_on_sphere
scene = sheet_on_sphere("tet4", (2, 2, 1))
rec = Recorder.attach(scene, path=sys.argv[1], batch=1000)  # nothing sent before exit
def callback(world):
    rec(world)
    if world.sim.steps == 6:
        raise RuntimeError("uncaught fault, no context manager")
scene.run(1.0, callback)
"""


def test_uncaught_exception_without_context_manager(tmp_path):
    """The process dies of an uncaught exception; atexit still completes the recording."""
    path = tmp_path / "crash.rrd"
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(path)], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode != 0 and "uncaught fault" in out.stderr
    verify(path)
    data, _ = read(path)
    assert len(data["/world/soft/body0"]["sim_time"]) == 7
