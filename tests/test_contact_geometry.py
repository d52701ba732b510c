"""Contact that never misses, part two (issue 29): contacts where no node of one body lies over the other.

Crossing soft bars whose nodes all lie outside the crossing, a soft bar across a thin box's top edge, a plate
on narrow rails (box, capsule, cylinder) between its rows of nodes, rigid bodies landing on triangles with
fixed nodes, a small box on a coarse slab, soft bodies pushed apart from a starting overlap.

Every depth is measured independently of the library's contact code (tests/geometry.py): soft-soft
interpenetration by the generalized winding number and segment-triangle crossings of the two surfaces,
soft-rigid penetration by points sampled over every surface triangle against the rigid shapes' exact
signed distances (from the shape, pose and size pybullet reports) and the rigid shapes' edges, rims and
corners inside the soft surface. Each test prints what it measured (``pytest -rA`` shows it).
"""
import math
import warnings

import numpy as np
import pybullet as p
import pytest

import geometry as geo
import softbody as sb
from integration import World

DEPTH = 1e-4  # [m]: the deepest interpenetration allowed everywhere below
G = 9.81


# ------------------------------------------------------------------------------------------ the helpers
def test_winding_number_of_a_unit_cube():
    x, tris = geo.box_surface((0.5, 0.5, 0.5))
    rng = np.random.default_rng(1)
    q = rng.uniform(-1.0, 1.0, (3000, 3))
    q = q[np.abs(np.abs(q).max(axis=1) - 0.5) > 1e-6]  # not on the surface
    w = geo.winding_number(q, x, tris)
    truth = np.all(np.abs(q) < 0.5, axis=1)
    assert truth.any() and (~truth).any()
    assert np.abs(w[truth] - 1.0).max() < 1e-9 and np.abs(w[~truth]).max() < 1e-9
    # the depth of inside points: their distance to the nearest face
    d = geo.depth_inside(q, x, tris)
    assert np.allclose(d[truth], 0.5 - np.abs(q[truth]).max(axis=1)) and (d[~truth] == 0).all()
    # outside points: the Euclidean distance to the box
    out = q[~truth]
    assert np.allclose(geo.surface_distance(out, x, tris), np.linalg.norm(np.maximum(np.abs(out) - 0.5, 0), axis=1))


def test_depth_of_two_crossing_boxes_with_no_corner_inside_the_other():
    """Bars along x and y crossing 3 mm deep: no vertex of either lies in the other; the depth comes from the
    edges that cross (the sampled point of a's top edge under b's middle is 3 mm inside b)."""
    xa, ta = geo.box_surface((0.2, 0.02, 0.02))
    for overlap in (0.003, 0.0005):
        xb, tb = geo.box_surface((0.02, 0.2, 0.02), (0, 0, 0.04 - overlap))
        assert not geo.inside(xa, xb, tb).any() and not geo.inside(xb, xa, ta).any()
        assert len(geo.crossing_edges(xa, ta, xb, tb)) and len(geo.crossing_edges(xb, tb, xa, ta))
        assert abs(geo.surface_intersection_depth(xa, ta, xb, tb) - overlap) < 1e-9
        assert abs(geo.surface_intersection_depth(xb, tb, xa, ta) - overlap) < 1e-9
    xb, tb = geo.box_surface((0.02, 0.2, 0.02), (0, 0, 0.0401))  # 0.1 mm apart
    assert geo.surface_intersection_depth(xa, ta, xb, tb) == 0.0


def test_rigid_penetration_of_a_box_surface_into_pybullet_shapes():
    """A 10 cm cube's surface placed 0.5 mm into a box, a capsule and a cylinder (along y): the samples on its
    bottom triangles are 0.5 mm deep (a box's edge dug into a face is found by the edge's samples)."""
    client = p.connect(p.DIRECT)
    try:
        cube, tris = geo.box_surface((0.05, 0.05, 0.05), (0, 0, 0.05 - 0.0005))
        box = p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.2, 0.2, 0.01],
                                                          physicsClientId=client),
                                basePosition=[0, 0, -0.01], physicsClientId=client)
        assert abs(geo.rigid_penetration(client, box, cube, tris) - 0.0005) < 1e-9
        assert abs(geo.pybullet_penetration(client, box, cube, tris) - 0.0005) < 1e-5
        q = p.getQuaternionFromEuler([math.pi / 2, 0, 0])  # axis along y
        for geom in (p.GEOM_CAPSULE, p.GEOM_CYLINDER):
            shape = p.createCollisionShape(geom, radius=0.005, height=0.4, physicsClientId=client)
            rail = p.createMultiBody(0, shape, basePosition=[0.013, 0, -0.005], baseOrientation=q,
                                     physicsClientId=client)
            assert abs(geo.rigid_penetration(client, rail, cube, tris) - 0.0005) < 1e-6
            p.removeBody(rail, physicsClientId=client)
        # a thin box edge (half extents 2 mm) standing 1 mm up into the cube between the cube's corners
        fin = p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.002, 0.2, 0.05],
                                                          physicsClientId=client),
                                basePosition=[0.011, 0, -0.0005 - 0.05 + 0.001], physicsClientId=client)
        assert abs(geo.rigid_penetration(client, fin, cube, tris) - 0.001) < 1e-9
    finally:
        p.disconnect(client)


# ------------------------------------------------------------------------------------------ scenes' parts
def bar_mesh(kind: str, axis: int, center) -> sb.Mesh:
    """A 0.4 x 0.04 x 0.04 m bar along ``axis`` (0: x, 1: y) with no node within 30 mm of the plane through
    its centre across it (the crossing footprint of a 40 mm bar is 20 mm either side): tet4 5 cells (nodes
    every 80 mm, at +-40 mm around the centre); tet10 4 cells whose corner nodes lie at -200, -115, -30, 90,
    200 mm along it (mid-edge nodes at -157.5, -72.5, 30, 145 mm; the geometry is that of the uniform bar)."""
    size = [0.04, 0.04, 0.04]
    size[axis] = 0.4
    cells = [1, 1, 1]
    cells[axis] = 5 if kind == "tet4" else 4
    mesh = sb.box_mesh(size, cells, "tet4")
    if kind == "tet10":
        nodes = mesh.nodes.copy()
        stations = np.array([-0.2, -0.115, -0.03, 0.09, 0.2])
        nodes[:, axis] = stations[np.rint((nodes[:, axis] + 0.2) / 0.1).astype(int)]
        mesh = sb.to_tet10(sb.Mesh(nodes, mesh.elements, "tet4"))
    return mesh.translated(center)


def soft(world: World, mesh: sb.Mesh, E: float = 1e6, friction: float = 0.5) -> sb.FemBody:
    body = sb.FemBody(mesh, sb.LinearElastic(E, 0.3, 1000.0), damping=(0.1, 0.001))
    world.add_soft(body, friction=friction)
    return body


def surface(body: sb.FemBody) -> tuple[np.ndarray, np.ndarray]:
    return body.positions, body.mesh.surface_triangles()


def soft_depth(a: sb.FemBody, b: sb.FemBody) -> float:
    return geo.surface_intersection_depth(*surface(a), *surface(b))


def _over(points: np.ndarray, V: np.ndarray):
    """(holds (P, T), l1, l2): whether each triangle V (T, 3, 3) holds each point's (x, y), and its barycentric
    coordinates there."""
    a, b, c = (V[None, :, k, :2] - points[:, None, :2] for k in range(3))
    det = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    ok = np.abs(det) > 1e-14
    den = np.where(ok, det, 1.0)
    l1 = (-a[..., 0] * (c[..., 1] - a[..., 1]) + a[..., 1] * (c[..., 0] - a[..., 0])) / den
    l2 = (-(b[..., 0] - a[..., 0]) * a[..., 1] + (b[..., 1] - a[..., 1]) * a[..., 0]) / den
    return ok & (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9), l1, l2


def heights_under(points: np.ndarray, x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The height (P,) of the highest triangle of x[tris] on the vertical line through each point (-inf: none)."""
    V = x[tris]
    hit, l1, l2 = _over(points, V)
    z = V[None, :, 0, 2] + l1 * (V[None, :, 1, 2] - V[None, :, 0, 2]) + l2 * (V[None, :, 2, 2] - V[None, :, 0, 2])
    return np.where(hit, z, -np.inf).max(axis=1)


def run(world: World, duration: float, each=None) -> None:
    for _ in range(int(round(duration / world.dt))):
        world.step()
        if each is not None:
            each()


def pybullet_body(world: World, geom: int, mass: float, position, orientation=(0, 0, 0, 1), **size) -> int:
    """A body made in the World's client with pybullet's own calls (the World picks it up at its next step)."""
    shape = p.createCollisionShape(geom, physicsClientId=world.client, **size)
    return p.createMultiBody(mass, shape, basePosition=list(position), baseOrientation=list(orientation),
                             physicsClientId=world.client)


ALONG_Y = p.getQuaternionFromEuler([math.pi / 2, 0, 0])  # a capsule's or cylinder's axis (z) along y


# --------------------------------------------------------------------------------------- 1. crossing bars
def crossing_bars_scene(kind: str, E: float):
    """(world, lower, upper): a soft bar along y on a plane, another along x dropped from 3 mm above across it."""
    world = World(dt=0.01)
    world.add_plane()
    lower = soft(world, bar_mesh(kind, 1, (0, 0, 0.02)), E)
    upper = soft(world, bar_mesh(kind, 0, (0, 0, 0.04 + 0.003 + 0.02)), E)
    return world, lower, upper


@pytest.mark.parametrize("E", [1e5, 1e6])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_crossing_bars_rest_on_each_other(kind, E):
    """No node of either bar lies in the 40 x 40 mm crossing: after 1 s the upper bar rests on the lower one (the
    lowest point of its surface over the crossing is above the lower bar's top surface under it, less 0.1 mm, and
    within 1 mm of it), and the bars interpenetrate less than 0.1 mm."""
    world, lower, upper = crossing_bars_scene(kind, E)
    for body, axis in ((lower, 1), (upper, 0)):  # the premise: every node outside the crossing
        assert (np.abs(body.rest[:, axis]) > 0.025).all()
    during = []
    run(world, 1.0, lambda: during.append(soft_depth(lower, upper)) if world.sim.steps % 10 == 0 else None)
    depth = soft_depth(lower, upper)
    pts = geo.triangle_samples(*surface(upper))
    pts = pts[(np.abs(pts[:, 0]) < 0.02) & (np.abs(pts[:, 1]) < 0.02)]  # over the crossing
    gaps = pts[:, 2] - heights_under(pts, *surface(lower))
    gap = float(gaps.min()) if len(gaps) else np.inf
    print(f"measured: {kind} E={E:g}: depth {1e3 * depth:.3f} mm, gap over the crossing {1e3 * gap:.3f} mm, "
          f"upper bar's lowest point {upper.positions[:, 2].min():.4f} m, lower bar's top "
          f"{lower.positions[:, 2].max():.4f} m; depth every 10th step {np.round(1e3 * np.array(during), 3)} mm")
    assert gap > -DEPTH  # on top of the lower bar, not in or through it
    assert gap < 1e-3  # resting on it
    assert depth < DEPTH


def test_crossing_bars_of_one_body_rest_on_each_other_by_self_contact():
    """The crossing bars above as one body (one mesh of two parts, self_contact=True), the upper part dropped from
    120 mm (self-contact leaves out what lies within an edge's length at rest): its edges crossing between the
    nodes of both are a self-contact; the upper part rests on the lower one (interpenetration < 0.1 mm, the same
    independent depth)."""
    lower, upper = bar_mesh("tet4", 1, (0, 0, 0.02)), bar_mesh("tet4", 0, (0, 0, 0.04 + 0.12 + 0.02))
    both = sb.Mesh(np.vstack([lower.nodes, upper.nodes]),
                   np.vstack([lower.elements, upper.elements + len(lower.nodes)]), "tet4")
    world = World(dt=0.01)
    world.add_plane()
    body = sb.FemBody(both, sb.LinearElastic(1e5, 0.3, 1000.0), damping=(0.1, 0.001))
    world.add_soft(body, friction=0.5, self_contact=True)
    run(world, 1.0)
    n = len(lower.nodes)
    tris = both.surface_triangles()
    parts = [tris[(tris < n).all(axis=1)], tris[(tris >= n).all(axis=1)]]
    depth = geo.surface_intersection_depth(body.positions, parts[0], body.positions, parts[1])
    pts = geo.triangle_samples(body.positions, parts[1])
    pts = pts[(np.abs(pts[:, 0]) < 0.02) & (np.abs(pts[:, 1]) < 0.02)]  # over the crossing
    gaps = pts[:, 2] - heights_under(pts, body.positions, parts[0])
    gap = float(gaps.min()) if len(gaps) else np.inf
    print(f"measured: one body's crossing parts: depth {1e3 * depth:.3f} mm, gap over the crossing {1e3 * gap:.3f} mm")
    assert -DEPTH < gap < 1e-3 and depth < DEPTH  # resting on the lower part, not in or through it


# --------------------------------------------------------------------------------------- 2. thin box edge
def bar_on_edge_scene(kind: str, half_thickness: float, mesh: bool = False):
    """(world, box, bar): a fixed box (half extents (t, 0.1, 0.05)) standing on a plane, its top edge along y at
    0.1 m (``mesh``: the same box as a triangle mesh, World.add_mesh); a soft bar (E = 1e6) along x across it, dropped
    from 3 mm."""
    world = World(dt=0.01)
    world.add_plane()
    if mesh:
        import trimesh

        box = world.add_mesh(trimesh.creation.box((2 * half_thickness, 0.2, 0.1)), position=(0, 0, 0.05), name="fin")
    else:
        box = world.add_box((half_thickness, 0.1, 0.05), position=(0, 0, 0.05), name="fin")
    bar = soft(world, bar_mesh(kind, 0, (0, 0, 0.1 + 0.003 + 0.02)), 1e6)
    return world, box, bar


@pytest.mark.parametrize("half_thickness", [0.002, 0.01])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_bar_rests_across_a_thin_box_edge(kind, half_thickness):
    """No node of the bar lies over the box's top: after 1 s it hangs on the box (does not reach the floor), the
    box carries its weight (within 5%) and the bar and the box interpenetrate less than 0.1 mm."""
    world, box, bar = bar_on_edge_scene(kind, half_thickness)
    assert (np.abs(bar.rest[:, 0]) > half_thickness).all()  # the premise
    run(world, 1.0)
    weight = bar.total_mass * G
    carried = -float(world.contact_force(box)[2])
    depth = geo.rigid_penetration(world.client, box.id, *surface(bar))
    pb = geo.pybullet_penetration(world.client, box.id, *surface(bar))
    print(f"measured: {kind} box {2e3 * half_thickness:.0f} mm: box carries {carried / weight:.4f} m g, penetration "
          f"{1e3 * depth:.3f} mm (pybullet's query {1e3 * pb:.3f} mm), bar's lowest point "
          f"{bar.positions[:, 2].min():.4f} m")
    assert bar.positions[:, 2].min() > 0.05  # hanging on the box, not on the floor
    assert abs(carried - weight) < 0.05 * weight
    assert depth < DEPTH


# ------------------------------------------------------------------------------------ 2b. mesh links' edges
@pytest.mark.parametrize("half_thickness", [0.002, 0.01])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_bar_rests_across_a_thin_mesh_edge(kind, half_thickness):
    """The thin box of test_bar_rests_across_a_thin_box_edge as a triangle mesh (pybullet collides with its convex
    hull; the World offers its sharp edges against soft edges): after 1 s the bar hangs on it, the fin carries the bar's
    weight (within 5%), and nothing is more than 0.1 mm inside anything, both against the mesh's own hull (its
    vertices from pybullet, the bar's triangle samples by the hull's planes and the hull's edges inside the bar by the
    winding number) and by pybullet's own query (the hull grown by pybullet's collision margin, which the contacts
    keep to). Before the mesh's edges were rows the bar fell through onto the floor (3 mm deep at t = 0.1 s)."""
    world, fin, bar = bar_on_edge_scene(kind, half_thickness, mesh=True)
    assert (np.abs(bar.rest[:, 0]) > half_thickness).all()  # the premise: no node over the fin
    run(world, 1.0)
    weight = bar.total_mass * G
    carried = -float(world.contact_force(fin)[2])
    own = geo.convex_mesh_penetration(world.client, fin.id, *surface(bar))
    pb = geo.pybullet_penetration(world.client, fin.id, *surface(bar))
    print(f"measured: {kind} mesh fin {2e3 * half_thickness:.0f} mm: carries {carried / weight:.4f} m g, penetration "
          f"{1e3 * own:.3f} mm (pybullet's query {1e3 * pb:.3f} mm), bar's lowest point {bar.positions[:, 2].min():.4f} m")
    assert bar.positions[:, 2].min() > 0.05
    assert abs(carried - weight) < 0.05 * weight
    assert own < DEPTH and pb < DEPTH


@pytest.mark.parametrize("reversed_winding", [False, True])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_bar_rests_across_the_ridge_of_an_open_concave_mesh(kind, reversed_winding):
    """A fixed open triangle soup (World.add_mesh(..., convex=False)): a roof of two faces meeting at a ridge along y at
    0.1 m, its eaves 20 mm either side at 0.06 m (open: its rim edges bound one face each; its triangles facing up, or
    down: a ridge seen from behind its faces). The soft bar of the
    thin-box test dropped across the ridge, no node within 30 mm of it: after 1 s it hangs on the ridge (its lowest
    point above the eaves), the roof carries its weight (within 5%), and no point of the ridge is more than 0.1 mm
    inside the bar (the winding number)."""
    import trimesh

    v = np.array([[-0.02, -0.1, 0.06], [0.0, -0.1, 0.1], [0.02, -0.1, 0.06],
                  [-0.02, 0.1, 0.06], [0.0, 0.1, 0.1], [0.02, 0.1, 0.06]])
    f = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])  # outward: up and to the sides
    roof = trimesh.Trimesh(v, f[:, ::-1] if reversed_winding else f, process=False)
    # the premise: open, facing up (or down: pybullet's triangle soup is two-sided, and so is the ridge)
    assert not roof.is_watertight and (np.sign(roof.face_normals[:, 2]) == (-1 if reversed_winding else 1)).all()
    world = World(dt=0.01)
    world.add_plane()
    ridge = world.add_mesh(roof, convex=False, name="roof")
    bar = soft(world, bar_mesh(kind, 0, (0, 0, 0.1 + 0.003 + 0.02)), 1e6)
    run(world, 1.0)
    weight = bar.total_mass * G
    carried = -float(world.contact_force(ridge)[2])
    t = np.linspace(0.0, 1.0, 401)[:, None]
    line = (1 - t) * v[1] + t * v[4]  # the ridge
    depth = float(geo.depth_inside(line, *surface(bar)).max())
    print(f"measured: {kind} bar on an open roof's ridge: carries {carried / weight:.4f} m g, ridge {1e3 * depth:.3f} mm "
          f"inside the bar, bar's lowest point {bar.positions[:, 2].min():.4f} m")
    assert bar.positions[:, 2].min() > 0.06
    assert abs(carried - weight) < 0.05 * weight
    assert depth < DEPTH


def test_mesh_edge_search_finds_the_same_pairs_through_its_k_d_tree():
    """collision.mesh_edge_contacts compares the boxes of few soft-edge / sharp-edge pairs all at once and, beyond
    DENSE_PAIRS, those of the pairs a k-d tree over their midpoints finds: the same contacts either way (the bar
    pressed into the fin's edge, by the open roof's ridge: both kinds of mesh)."""
    import trimesh

    from integration import collision

    world = World(dt=0.01)
    world.add_plane()
    fin = world.add_mesh(trimesh.creation.box((0.004, 0.2, 0.1)), position=(0, 0, 0.05), name="fin")
    bar = soft(world, bar_mesh("tet10", 0, (0, 0, 0.1 + 0.003 + 0.02)), 1e6)
    run(world, 0.3)
    sf = world.entry(bar).surface
    v = bar.velocities
    sweep = collision.Sweep(world.contact_margin, world.dt, v, np.linalg.norm(v, axis=1))
    args = (0, bar.positions, sf.triangles, (sf.edges, sf.edge_tris), world.rigid(fin.id), sweep,
            np.full(bar.n_nodes, np.inf))
    dense = collision.mesh_edge_contacts(*args)
    kept = collision.DENSE_PAIRS
    try:
        collision.DENSE_PAIRS = 0
        tree = collision.mesh_edge_contacts(*args)
    finally:
        collision.DENSE_PAIRS = kept
    assert len(dense) > 0
    a, b = np.argsort(dense.key), np.argsort(tree.key)
    assert np.array_equal(dense.key[a], tree.key[b]) and np.allclose(dense.distance[a], tree.distance[b])


def test_panda_mesh_fingers_gripping_hard_do_not_cut_into_the_cube():
    """pybullet_data's Panda (convex-hull mesh fingers) grips examples/robot_grasp.py's soft cube (E = 1e5) with 20 N per
    finger and lifts it: the fingers' edges press across the cube's edges between its nodes. Nothing is more than
    0.1 mm inside anything, against each finger's own hull (pybullet's getMeshData vertices) and by pybullet's own
    query, and the grip is the motors' limit. Before the fingers' edges were rows they cut 1.5-1.7 mm into the cube
    (2.2 mm by pybullet's query)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "robot_grasp.py"
    spec = importlib.util.spec_from_file_location("robot_grasp", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    example.FINGER_FORCE = 20.0
    cid, panda, world, cube = example.build(dt=0.01)
    try:
        grasp = example.Grasp(cid, panda, world, cube)
        size = np.ptp(cube.positions[:, 2])
        grasp.go([0.5, 0, 0.2], 0.04, 1.0)
        grasp.go([0.5, 0, size / 2], 0.04, 1.0)
        grasp.go([0.5, 0, size / 2], 0.015, 0.5)
        worst = pb = 0.0
        for k in range(3):  # closed, then lifting
            grasp.go([0.5, 0, size / 2 + 0.05 * k], 0.015, 0.1)
            for finger in example.FINGERS:
                x, tris = surface(cube)
                worst = max(worst, geo.convex_mesh_penetration(cid, panda, x, tris, finger))
                pb = max(pb, geo.pybullet_penetration(cid, panda, x, tris, finger))
        grip = grasp.grip()
        print(f"measured: Panda fingers at 20 N: penetration {1e3 * worst:.3f} mm (pybullet's query {1e3 * pb:.3f} "
              f"mm), grip {grip[0]:.2f} / {grip[1]:.2f} N, cube centre z {cube.positions[:, 2].mean():.4f} m")
        assert worst < DEPTH and pb < DEPTH
        assert grip == pytest.approx((20.0, 20.0), rel=0.05)
        assert cube.positions[:, 2].mean() > size / 2 + 0.05  # lifted with the hand
    finally:
        world.close()
        p.disconnect(cid)


# --------------------------------------------------------------------------------------------- 3. rails
def rails_scene(kind: str, shape: str):
    """(world, rails, plate): two fixed rails along y (box of half thickness 5 mm, or capsule or cylinder of radius
    5 mm, 0.4 m long) at x = +-0.1 m, their tops at 0.1 m; a soft plate 0.3 x 0.3 x 0.02 m (E = 1e6) dropped from
    2 mm, its rows of nodes at x = +-0.05, +-0.15 (tet4, 3 x 3 cells) or 0, +-0.075, +-0.15 (tet10, 2 x 2)."""
    world = World(dt=0.01)
    world.add_plane()
    rails = []
    for x in (-0.1, 0.1):
        if shape == "box":
            rails.append(world.add_box((0.005, 0.2, 0.005), position=(x, 0, 0.095)).id)
        else:
            geom = p.GEOM_CAPSULE if shape == "capsule" else p.GEOM_CYLINDER
            rails.append(pybullet_body(world, geom, 0.0, (x, 0, 0.095), ALONG_Y, radius=0.005, height=0.4))
    cells = (3, 3, 1) if kind == "tet4" else (2, 2, 1)
    plate = soft(world, sb.box_mesh((0.3, 0.3, 0.02), cells, kind, center=(0, 0, 0.1 + 0.002 + 0.01)), 1e6)
    return world, rails, plate


@pytest.mark.parametrize("shape", ["box", "capsule", "cylinder"])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_plate_rests_on_narrow_rails_between_its_nodes(kind, shape):
    """After 1 s the plate lies on the rails (its lowest point well above the floor), the rails carry its weight
    (within 3%), and nothing of it is more than 0.1 mm inside them."""
    world, rails, plate = rails_scene(kind, shape)
    assert (np.abs(np.abs(plate.rest[:, 0]) - 0.1) > 0.02).all()  # the premise: no row of nodes over a rail
    run(world, 1.0)
    weight = plate.total_mass * G
    carried = -sum(float(world.contact_force(r)[2]) for r in rails)
    depth = max(geo.rigid_penetration(world.client, r, *surface(plate)) for r in rails)
    pb = max(geo.pybullet_penetration(world.client, r, *surface(plate)) for r in rails)
    print(f"measured: {kind} {shape} rails: rails carry {carried / weight:.4f} m g, penetration {1e3 * depth:.3f} mm "
          f"(pybullet's query {1e3 * pb:.3f} mm), plate's lowest point {plate.positions[:, 2].min():.4f} m")
    assert plate.positions[:, 2].min() > 0.05  # on the rails, not fallen through
    assert abs(carried - weight) < 0.03 * weight
    assert depth < DEPTH


# ------------------------------------------------------------------------------------ 4. fixed triangles
def rim_scene(kind: str, shape: str):
    """(world, slab, body id, half size): a soft slab 0.4 x 0.4 x 0.05 m (E = 1e6; tet4 4 x 4 cells, tet10 2 x 2)
    held by the nodes of its four side faces, and a 25 mm rigid body of 0.1 kg (a box of 25 mm edges, a sphere
    of 25 mm diameter, a capsule of 12.5 mm radius and 25 mm axis lying along y) dropped from 5 mm onto its top
    40 mm from its edge, where the triangles under it have fixed nodes."""
    world = World(dt=0.01)
    mesh = sb.box_mesh((0.4, 0.4, 0.05), (4, 4, 1) if kind == "tet4" else (2, 2, 1), kind, center=(0, 0, 0.025))
    slab = soft(world, mesh, 1e6)
    slab.fix(np.flatnonzero(np.isclose(np.abs(mesh.nodes[:, :2]), 0.2).any(axis=1)))
    h, at = 0.0125, (0.2 - 0.04, 0.03)
    z = 0.05 + 0.005 + h
    if shape == "box":
        bid = world.add_box((h, h, h), position=(*at, z), mass=0.1).id
    elif shape == "sphere":
        bid = world.add_sphere(h, position=(*at, z), mass=0.1).id
    else:
        bid = pybullet_body(world, p.GEOM_CAPSULE, 0.1, (*at, z), ALONG_Y, radius=h, height=0.025)
    return world, slab, bid, h


@pytest.mark.parametrize("shape", ["box", "sphere", "capsule"])
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_rigid_body_landing_on_triangles_with_fixed_nodes_does_not_fall_through(kind, shape):
    """Over 0.5 s the body's centre stays above the slab's top less its half size; at the end it is less than
    0.1 mm inside the slab."""
    world, slab, bid, h = rim_scene(kind, shape)
    tris = slab.mesh.surface_triangles()
    top = tris[np.isclose(slab.rest[tris][:, :, 2], 0.05).all(axis=1)]
    for corner in np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * h + [0.16, 0.03]:  # the premise: the top
        holding = top[_over(np.array([[*corner, 1.0]]), slab.rest[top])[0][0]]  # triangles
        assert slab.supported()[holding].any()  # under the body's footprint have fixed nodes
    lowest = [np.inf]
    run(world, 0.5, lambda: lowest.__setitem__(0, min(lowest[0], p.getBasePositionAndOrientation(
        bid, physicsClientId=world.client)[0][2])))
    depth = geo.rigid_penetration(world.client, bid, *surface(slab))
    print(f"measured: {kind} {shape}: lowest centre {lowest[0]:.4f} m (limit {0.05 - h:.4f}), final centre "
          f"{p.getBasePositionAndOrientation(bid, physicsClientId=world.client)[0][2]:.4f} m, penetration "
          f"{1e3 * depth:.3f} mm")
    assert lowest[0] > 0.05 - h
    assert depth < DEPTH


# ------------------------------------------------------------------------------------ 5. coarse triangles
def coarse_slab_scene(kind: str):
    """(world, box): a 25 mm, 50 g rigid box set down (1 mm above) on a free soft slab of 200 mm cells
    (0.4 x 0.4 x 0.05 m, 2 x 2 x 1, E = 1e6) lying on a plane, between the nodes."""
    world = World(dt=0.01)
    world.add_plane()
    soft(world, sb.box_mesh((0.4, 0.4, 0.05), (2, 2, 1), kind, center=(0, 0, 0.025)), 1e6)
    box = world.add_box((0.0125,) * 3, position=(0.1, 0.09, 0.05 + 0.0125 + 0.001), mass=0.05)
    return world, box


def yaw(q) -> float:
    R = np.array(p.getMatrixFromQuaternion(list(q))).reshape(3, 3)
    return math.atan2(R[1, 0], R[0, 0])


@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_small_box_comes_to_rest_on_coarse_triangles(kind):
    """After 3 s the box is at rest: |omega| < 0.05 rad/s, speed < 1 cm/s, and it has turned less than 0.01 rad
    about the vertical."""
    world, box = coarse_slab_scene(kind)
    yaw0 = yaw(box.pose()[1])
    run(world, 3.0)
    v, w = (np.asarray(a) for a in box.velocity())
    drift = abs(yaw(box.pose()[1]) - yaw0)
    print(f"measured: {kind}: |omega| {np.linalg.norm(w):.4g} rad/s, speed {np.linalg.norm(v):.4g} m/s, yaw drift "
          f"{drift:.4g} rad, centre z {box.pose()[0][2]:.4f} m")
    assert np.linalg.norm(w) < 0.05
    assert np.linalg.norm(v) < 0.01
    assert drift < 0.01


# ----------------------------------------------------------------------------------------- 6. soft-soft
@pytest.mark.parametrize("kind", ["tet4", "tet10"])
def test_soft_cubes_placed_overlapping_are_separated(kind):
    """Two 10 cm cubes (E = 1e6), the upper placed 2 mm into the lower (offset 20, 10 mm sideways), the lower on
    a plane (the World pushes such a starting overlap out, with a warning): after 1 s they interpenetrate less
    than 0.1 mm."""
    world = World(dt=0.01)
    world.add_plane()
    cells = (3, 3, 3) if kind == "tet4" else (2, 2, 2)
    low = soft(world, sb.box_mesh((0.1,) * 3, cells, kind, center=(0, 0, 0.05)), 1e6)
    high = soft(world, sb.box_mesh((0.1,) * 3, cells, kind, center=(0.02, 0.01, 0.15 - 0.002)), 1e6)
    assert abs(soft_depth(low, high) - 0.002) < 1e-9  # the premise
    during = []
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(world, 1.0, lambda: during.append(soft_depth(low, high)) if world.sim.steps % 10 == 0 else None)
    depth = soft_depth(low, high)
    print(f"measured: {kind}: depth {1e3 * depth:.3f} mm after 1 s (every 10th step: "
          f"{np.round(1e3 * np.array(during), 3)} mm); upper cube's lowest point {high.positions[:, 2].min():.4f} m; "
          f"warnings: {[str(w.message)[:80] for w in said]}")
    assert high.positions[:, 2].min() > 0.09  # still on the lower cube
    assert depth < DEPTH


def test_pile_of_small_soft_cubes_does_not_interpenetrate():
    """Four 5 cm tet4 cubes (E = 1e5, nodes 25 mm apart), each dropped 5 mm above the one below, every other one
    offset (12, 8) mm sideways so that no node lies over a node, on a plane:
    after 1 s they still stand as a pile (each cube's lowest point within 5 mm of 5 cm above the one below's) and
    no two of them interpenetrate by more than 0.1 mm."""
    world = World(dt=0.01)
    world.add_plane()
    centers = [(0.012 * (k % 2), 0.008 * (k % 2), 0.025 + 0.055 * k) for k in range(4)]
    cubes = [soft(world, sb.box_mesh((0.05,) * 3, (2, 2, 2), "tet4", center=c), 1e5) for c in centers]
    run(world, 1.0)
    depths = {(i, j): soft_depth(cubes[i], cubes[j]) for i in range(4) for j in range(i + 1, 4)}
    print(f"measured: pile: depths [mm] {({k: round(1e3 * d, 3) for k, d in depths.items()})}, tops "
          f"{[round(float(c.positions[:, 2].max()), 4) for c in cubes]}")
    assert all(c.positions[:, 2].min() > 0.05 * k - 0.005 for k, c in enumerate(cubes))
    assert max(depths.values()) < DEPTH


# ------------------------------------------------------------------------------------------ 7. said
def test_an_intersection_that_cannot_be_resolved_is_said_naming_both_bodies():
    """A soft cube held by all its nodes and another moved into it by all its nodes (prescribed, 5 cm/s from 1 mm
    above, 9 mm deep after 0.2 s): no contact can separate them, and a warning names both soft bodies."""
    world = World(dt=0.01, gravity=(0, 0, 0))
    a = soft(world, sb.box_mesh((0.05,) * 3, (2, 2, 2), "tet4", center=(0, 0, 0)), 1e6)
    a.fix(np.arange(a.n_nodes))
    b = soft(world, sb.box_mesh((0.05,) * 3, (2, 2, 2), "tet4", center=(0.01, 0.005, 0.05 + 0.001)), 1e6)
    rest = b.rest.copy()
    b.prescribe(np.arange(b.n_nodes), lambda t: rest - np.array([0.0, 0.0, 0.05 * t]))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(world, 0.2)
    depth = soft_depth(a, b)
    messages = [str(w.message) for w in said]
    print(f"measured: depth {1e3 * depth:.3f} mm; warnings: {messages}")
    assert depth > 0.005  # the premise: they do intersect
    both = [m for m in messages if ("soft bodies 0 and 1" in m or ("soft body 0" in m and "soft body 1" in m))]
    assert both, f"no warning names soft bodies 0 and 1: {messages}"


def held_slab(world: World) -> sb.FemBody:
    """A coarse soft slab (0.4 x 0.4 x 0.04 m, 200 mm tet4 cells, E = 1e6) held by all its nodes, top at z = 0.02."""
    slab = soft(world, sb.box_mesh((0.4, 0.4, 0.04), (2, 2, 1), "tet4", center=(0, 0, 0)), 1e6)
    slab.fix(np.arange(slab.n_nodes))
    return slab


def intersect_warnings(world: World, duration: float) -> list[str]:
    """Run the world for ``duration`` [s]; the warnings said about intersecting bodies."""
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(world, duration)
    return [str(w.message) for w in said if "intersect" in str(w.message)]


def test_a_rigid_edge_driven_through_a_held_slab_between_its_nodes_is_said_naming_both():
    """A coarse slab (200 mm tet4 cells) held by all its nodes and a thin kinematic blade (4 mm) driven down
    through it between its nodes at 5 cm/s: no contact can stop either (supports win; the blade's path is
    prescribed) and no node of the slab ends inside the blade, so only its edges cross the slab's faces. The
    check after the step finds it (the independent depth: the blade's edges inside the slab's surface) and a
    warning names the blade and the soft body. A box dropped on such a slab rests on it (rows on held nodes that
    move a rigid body: the support is a rigid surface to it) and is not warned about."""
    world = World(dt=0.01, gravity=(0, 0, 0))
    slab = held_slab(world)
    world.add_box((0.002, 0.3, 0.05), motion=lambda t: ((0.05, 0.0, 0.071 - 0.05 * t), (0, 0, 0, 1)), name="blade")
    messages = intersect_warnings(world, 0.3)
    blade = world.rigids[next(k for k, rb in world.rigids.items() if rb.name == "blade")]
    x, tris = surface(slab)
    depth = geo.rigid_penetration(world.client, blade.id, x, tris)
    inside = geo.inside(blade.to_world(geo.box_surface((0.002, 0.3, 0.05))[0]), x, tris)
    print(f"measured: blade {1e3 * depth:.2f} mm deep, blade corners inside: {int(inside.sum())}; warnings: {messages}")
    assert depth > 0.005  # the premise: the blade is through the slab's top
    assert any("'blade'" in m and "soft body 0" in m for m in messages), messages

    world = World(dt=0.01)
    slab = held_slab(world)
    world.add_box((0.0125, 0.0125, 0.0125), position=(0.05, 0.03, 0.0326), mass=0.05, name="box")
    messages = intersect_warnings(world, 0.3)
    box = next(rb for rb in world.rigids.values() if rb.name == "box")
    x, tris = surface(slab)
    rest = geo.rigid_penetration(world.client, box.id, x, tris)
    print(f"measured: box on the held slab at z {box.pose()[0][2]:.5f} m (resting: 0.0325), {1e3 * rest:.4f} mm deep")
    assert rest < DEPTH and abs(box.pose()[0][2] - 0.0325) < DEPTH  # held by the slab's held nodes
    assert not messages


def test_a_sphere_driven_through_a_held_slab_between_its_nodes_is_said_but_not_a_sheet_resting_on_one():
    """A sphere (radius 80 mm) driven down at 5 cm/s through a coarse held slab (200 mm cells) into the middle of a
    facet, no node of the slab inside it: the check warns naming both. A sheet resting on a sphere, whose facets
    sag through it between the nodes on it by the mesh's discretisation (R - sqrt(R^2 - L^2/4), not modelled),
    is not warned about: the canonical sheet-on-sphere scene (tet10 6 x 6 x 2) after 1 s."""
    world = World(dt=0.01, gravity=(0, 0, 0))
    slab = held_slab(world)
    world.add_sphere(0.08, motion=lambda t: ((0.1, 0.1, 0.101 - 0.05 * t), (0, 0, 0, 1)), name="ball")
    messages = intersect_warnings(world, 0.3)
    ball = next(rb for rb in world.rigids.values() if rb.name == "ball")
    x, tris = surface(slab)
    depth = geo.rigid_penetration(world.client, ball.id, x, tris)
    print(f"measured: ball {1e3 * depth:.2f} mm deep, nearest node {np.linalg.norm(x - ball.pose()[0], axis=1).min():.3f} "
          f"m from its centre; warnings: {messages}")
    assert depth > 0.005 and np.linalg.norm(x - ball.pose()[0], axis=1).min() > 0.08  # the premise
    assert any("'ball'" in m and "soft body 0" in m for m in messages), messages

    from experiments.scenes import sheet_on_sphere

    scene = sheet_on_sphere()
    assert not intersect_warnings(scene.world, 1.0)


def test_a_world_of_rigid_bodies_only_steps_past_the_checks():
    """No soft body at all: the checks after the step (every CHECK_EVERY-th) have nothing to check; a box falls
    onto the plane as in plain pybullet (free fall to the plane's contact, then at rest on it)."""
    world = World(dt=0.01)
    world.add_plane()
    box = world.add_box((0.05, 0.05, 0.05), position=(0, 0, 0.3), mass=1.0)
    run(world, 1.0)
    assert world.sim.steps == 100 and abs(box.pose()[0][2] - 0.05) < 2e-3
