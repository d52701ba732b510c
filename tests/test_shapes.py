"""The rigid shape classes (integration/shapes.py): closed-form distances against pybullet's own closest-point
query, bounding radii against sampled surface points, support points and corners, and the round trip through
pybullet (made from the shape's arguments, read back through the registry)."""
import math

import numpy as np
import pybullet as p
import pytest

from integration.bullet import quat_matrix
from integration.distance import shape_distance
from integration.shapes import BY_GEOM, BY_KIND, Box, Capsule, Cylinder, Mesh, Plane, Sphere, from_pybullet, of_kind

TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
# shape: pybullet's accuracy on the distance [m] (as tests/test_distance.py: GJK/EPA with margins on boxes, cylinders)
PRIMITIVES = {
    "sphere": (Sphere(0.25), 1e-9),
    "box": (Box([0.3, 0.1, 0.2]), 1e-3),
    "capsule": (Capsule(0.1, 0.4), 1e-9),
    "cylinder": (Cylinder(0.1, 0.4), 1e-3),
    "plane": (Plane(np.array([0.0, 0.6, 0.8])), 1e-9),
}
POSITION, ORIENTATION = np.array([0.1, -0.2, 0.3]), p.getQuaternionFromEuler([0.3, -0.5, 0.9])


@pytest.fixture
def client():
    cid = p.connect(p.DIRECT)
    yield cid
    p.disconnect(cid)


def body_of(shape, cid: int, position=POSITION, orientation=ORIENTATION) -> int:
    col = p.createCollisionShape(physicsClientId=cid, **shape.pybullet_args())
    return p.createMultiBody(0, col, basePosition=list(position), baseOrientation=list(orientation),
                             physicsClientId=cid)


def surface_points(shape, n: int = 4000, seed: int = 2) -> np.ndarray:
    """Points (n, 3) on a closed-form shape's surface: the closest points of random points around it."""
    r = shape.bounding_radius()
    x = np.random.default_rng(seed).uniform(-1.3 * r, 1.3 * r, size=(n, 3))
    return shape.distance(x)[0]


@pytest.mark.parametrize("kind", sorted(PRIMITIVES))
def test_closed_form_distances_match_pybullets_query(kind, client):
    shape, tol = PRIMITIVES[kind]
    body = body_of(shape, client)
    probe = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-6, physicsClientId=client)
    R = quat_matrix(ORIENTATION)
    half = 0.5 if kind == "plane" else shape.bounding_radius() + 0.05
    local = np.random.default_rng(5).uniform(-half, half, size=(1000, 3))
    point, normal, dist = shape.distance(local)
    x = local @ R.T + POSITION
    checked = inside = 0
    for i in range(len(x)):
        res = p.getClosestPoints(-1, body, 0.05, collisionShapeA=probe, collisionShapePositionA=x[i].tolist(),
                                 physicsClientId=client)
        if not res:
            assert dist[i] >= 0.05 - tol - 1e-6
            continue
        best = min(res, key=lambda r: r[8])
        assert dist[i] == pytest.approx(best[8] + 1e-6, abs=tol)  # the probe is a sphere of 1e-6
        if abs(dist[i]) > 5 * tol:
            assert (R @ normal[i]) @ np.array(best[7]) > 0.99
        np.testing.assert_allclose(point[i] @ R.T + POSITION, best[6], atol=max(tol, 1e-6) * 3)
        checked += 1
        inside += dist[i] < 0
    assert checked > 100 and inside > 10
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    # distance.shape_distance dispatches through the classes, on a part's kind and size
    for a, b in zip(shape_distance(kind, shape.size, local), (point, normal, dist)):
        assert np.array_equal(a, b)


def test_meshes_have_no_closed_form_distance():
    mesh = Mesh(np.eye(3), np.array([[0, 1, 2]]))
    assert not mesh.closed_form and mesh.code is None
    with pytest.raises(ValueError, match="mesh"):
        mesh.distance(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="mesh"):
        shape_distance("mesh", np.ones(3), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="torus"):
        shape_distance("torus", np.ones(3), np.zeros((1, 3)))


@pytest.mark.parametrize("kind", ["sphere", "box", "capsule", "cylinder"])
def test_bounding_radius_holds_the_surface(kind):
    shape, _ = PRIMITIVES[kind]
    reach = np.linalg.norm(surface_points(shape), axis=1)
    assert reach.max() <= shape.bounding_radius() + 1e-12
    assert reach.max() >= 0.9 * shape.bounding_radius()  # and close (a capsule's: hypot(r, L / 2) + r)


def test_bounding_radius_of_planes_and_meshes(tmp_path):
    assert math.isinf(Plane([0, 0, 1]).bounding_radius()) and not Plane([0, 0, 1]).bounded
    verts = np.random.default_rng(0).normal(size=(30, 3))
    mesh = Mesh(verts, np.array([[0, 1, 2]]))
    assert mesh.bounding_radius() == pytest.approx(np.linalg.norm(verts, axis=1).max(), abs=0)
    assert math.isinf(Mesh(file=str(tmp_path / "a.obj")).bounding_radius())  # a file's extent: the link's box
    assert Mesh(file="a.obj").bounded


@pytest.mark.parametrize("kind", ["sphere", "capsule", "cylinder"])
def test_support_points_are_the_furthest_surface_points(kind):
    shape, _ = PRIMITIVES[kind]
    R, centre = quat_matrix(ORIENTATION), POSITION
    d = np.random.default_rng(3).normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.stack(shape.support_points(d, R, centre), axis=1)  # (T, S, 3)
    assert pts.shape == (40, len(shape.round), 3)
    # in the shape or on it (a capsule's end facing away: inside), the furthest of them on the surface and the
    # furthest of all surface points along its direction
    dist = shape.distance(((pts - centre) @ R).reshape(-1, 3))[2].reshape(pts.shape[:2])
    along = np.einsum("tsk,tk->ts", pts, d)
    assert dist.max() < 1e-12 and np.abs(dist[np.arange(len(d)), along.argmax(axis=1)]).max() < 1e-12
    surface = surface_points(shape, 20000) @ R.T + centre
    best = along.max(axis=1)
    assert np.all(best >= (surface @ d.T).max(axis=0) - 1e-12)
    assert np.all(best <= (surface @ d.T).max(axis=0) + 0.02)


def test_round_flags_and_corners():
    assert Sphere(1).round == (True,) and Capsule(1, 1).round == (True, True) and Cylinder(1, 1).round == (False, False)
    assert Box([1, 1, 1]).round == () == Plane([0, 0, 1]).round == Mesh(np.eye(3), None).round
    box = Box([0.1, 0.2, 0.3])
    corners, centre = box.corners()
    assert corners.shape == (8, 3) and np.allclose(np.abs(corners), box.half_extents) and not centre.any()
    assert np.linalg.norm(corners, axis=1).max() == box.bounding_radius()
    verts = np.random.default_rng(0).normal(size=(10, 3))
    corners, centre = Mesh(verts, None).corners()
    assert np.array_equal(corners, verts) and np.allclose(centre, verts.mean(axis=0))
    corners, centre = Mesh(verts, np.array([[0, 1, 2]]), concave=True).corners()
    assert len(corners) == 10 and np.isnan(centre).all()  # a concave mesh's vertices belong to no convex part
    for shape in (Sphere(1), Capsule(1, 1), Cylinder(1, 1), Plane([0, 0, 1]), Mesh(file="missing.obj")):
        assert len(shape.corners()[0]) == 0
    assert Plane([0, 0, 1]).convex_part() is None and Mesh(verts, None, concave=True).convex_part() is None


@pytest.mark.parametrize("kind", sorted(PRIMITIVES))
def test_pybullet_round_trip(kind, client):
    shape, _ = PRIMITIVES[kind]
    body = body_of(shape, client)
    (data,) = p.getCollisionShapeData(body, -1, physicsClientId=client)
    back = from_pybullet(data[2], data[3], data[4])
    assert type(back) is type(shape) and back.kind == kind
    assert np.array_equal(back.size, shape.size)
    if kind != "plane":  # pybullet has no visual plane
        vis = p.createVisualShape(physicsClientId=client, **shape.pybullet_args(visual=True))
        body = p.createMultiBody(0, -1, vis, physicsClientId=client)
        (data,) = p.getVisualShapeData(body, physicsClientId=client)
        back = from_pybullet(data[2], data[3], data[4])
        assert type(back) is type(shape) and np.array_equal(back.size, shape.size)


def test_mesh_round_trip(client, tmp_path):
    obj = tmp_path / "tetra.obj"
    obj.write_text(TETRA)
    scale = np.array([2.0, 1.0, 1.5])
    # a URDF's collision mesh keeps its file and scale (a createCollisionShape mesh reports "unknown_file")
    urdf = tmp_path / "tetra.urdf"
    urdf.write_text(f"""<robot name="tetra"><link name="base"><inertial><mass value="0"/>
        <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial><collision><geometry>
        <mesh filename="{obj}" scale="{scale[0]} {scale[1]} {scale[2]}"/></geometry></collision></link></robot>""")
    body = p.loadURDF(str(urdf), physicsClientId=client)
    (data,) = p.getCollisionShapeData(body, -1, physicsClientId=client)
    back = from_pybullet(data[2], data[3], data[4])
    assert type(back) is Mesh and back.file == str(obj) and np.array_equal(back.scale, scale)
    corners = np.loadtxt(obj, usecols=(1, 2, 3), max_rows=4) * scale  # the tetrahedron is its own hull
    np.testing.assert_allclose(np.sort(back.hull, axis=0), np.sort(corners, axis=0))
    vis = p.createVisualShape(physicsClientId=client, **Mesh(file=str(obj), scale=scale).pybullet_args(visual=True))
    (data,) = p.getVisualShapeData(p.createMultiBody(0, -1, vis, physicsClientId=client), physicsClientId=client)
    back = from_pybullet(data[2], data[3], data[4])
    assert back.file == str(obj) and np.array_equal(back.scale, scale)
    # a mesh of vertices: pybullet keeps neither vertices nor a file
    verts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], float)
    for concave in (False, True):
        mesh = Mesh(verts, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]), concave=concave)
        (data,) = p.getCollisionShapeData(body_of(mesh, client), -1, physicsClientId=client)
        back = from_pybullet(data[2], data[3], data[4])
        assert type(back) is Mesh and back.file == "" and np.array_equal(back.scale, np.ones(3))


def test_registry():
    assert set(BY_KIND) == {"sphere", "box", "capsule", "cylinder", "plane", "mesh"}
    assert {cls.geom for cls in BY_KIND.values()} == set(BY_GEOM)
    for kind, cls in BY_KIND.items():  # a closed form has its number in the compiled kernels
        assert of_kind(kind) is cls and cls.closed_form == (cls.code is not None)
    # (the compiled kernels number them by RigidShape.code: test_kernels compares them with the closed forms)
    assert type(from_pybullet(p.GEOM_HEIGHTFIELD, (1.0, 1.0, 1.0), b"")) is Mesh  # any other type: a mesh
    with pytest.raises(ValueError, match="torus"):
        of_kind("torus")
    for shape in (Sphere(0.2), Box([0.1, 0.2, 0.3]), Plane(np.array([0.0, 0.0, 1.0])),
                  Mesh(np.eye(3), np.array([[0, 1, 2]]), concave=True)):
        back = type(shape).from_params(shape.params(), shape.concave)
        assert all(np.array_equal(a, b) for a, b in zip(back.params().values(), shape.params().values()))
        assert back.concave == shape.concave


def test_drawing():
    import rerun as rr

    pose = (POSITION, np.array(ORIENTATION))
    for shape, _ in PRIMITIVES.values():
        drawn = shape.draw((200, 200, 200, 255), pose, plane_size=2.0)
        assert drawn is not None and isinstance(drawn, rr.AsComponents)
    assert Plane([0, 0, 1]).draw((1, 1, 1, 255), pose) is None  # no size: planes are not drawn
    assert Mesh(file="missing.obj").draw((1, 1, 1, 255), pose) is None
    assert Mesh(np.eye(3), np.array([[0, 1, 2]])).draw((1, 1, 1, 255)) is not None
