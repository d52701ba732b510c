"""Closed-form distances to primitive shapes (integration/distance.py) against pybullet's own closest-point
query on random points around each primitive, turned and moved, inside and outside."""
import numpy as np
import pybullet as p
import pytest

from integration import World
from integration.collision import primitive_distances

SHAPES = {
    # kind: (createCollisionShape keywords, pybullet's accuracy on the distance [m])
    "sphere": ({"shapeType": p.GEOM_SPHERE, "radius": 0.25}, 1e-9),
    "capsule": ({"shapeType": p.GEOM_CAPSULE, "radius": 0.1, "height": 0.4}, 1e-9),
    "box": ({"shapeType": p.GEOM_BOX, "halfExtents": [0.3, 0.1, 0.2]}, 1e-3),  # GJK/EPA with margins
    "cylinder": ({"shapeType": p.GEOM_CYLINDER, "radius": 0.1, "height": 0.4}, 1e-3),
}


@pytest.mark.parametrize("kind", sorted(SHAPES))
def test_closed_form_distances_match_pybullets_query(kind):
    world = World()
    cid = world.client
    kw, tol = SHAPES[kind]
    col = p.createCollisionShape(physicsClientId=cid, **kw)
    body = p.createMultiBody(0, col, basePosition=[0.1, -0.2, 0.3], baseOrientation=p.getQuaternionFromEuler([0.3, -0.5, 0.9]),
                             physicsClientId=cid)
    rb = world.rigid(body)
    assert rb.primitive_parts()[0].shape.kind == kind  # the link's shape data, read back from pybullet
    lo, hi = rb.aabb()
    rng = np.random.default_rng(5)
    x = rng.uniform(lo - 0.05, hi + 0.05, size=(1500, 3))
    point, normal, dist = primitive_distances(rb, rb.primitive_parts(), x)
    probe = world.detector._probe
    checked = inside = 0
    for i in range(len(x)):
        res = p.getClosestPoints(-1, body, 0.05, collisionShapeA=probe, collisionShapePositionA=x[i].tolist(),
                                 physicsClientId=cid)
        if not res:
            assert dist[i] >= 0.05 - tol - 1e-6
            continue
        best = min(res, key=lambda r: r[8])
        assert dist[i] == pytest.approx(best[8] + 1e-6, abs=tol)  # pybullet's probe is a sphere of 1e-6
        if abs(dist[i]) > 5 * tol:  # away from the surface the normals agree
            assert normal[i] @ np.array(best[7]) > 0.99
        np.testing.assert_allclose(point[i], best[6], atol=max(tol, 1e-6) * 3)
        checked += 1
        inside += dist[i] < 0
    assert checked > 100 and inside > 10  # both sides of the surface were sampled
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    world.close()


def test_plane_distance_is_the_height_above_it():
    world = World()
    plane = world.add_plane(normal=(0, 0.6, 0.8), point=(0, 0, -0.1))
    x = np.random.default_rng(1).uniform(-1, 1, size=(200, 3))
    point, normal, dist = primitive_distances(plane, plane.primitive_parts(), x)
    n = np.array([0, 0.6, 0.8])
    np.testing.assert_allclose(dist, (x - [0, 0, -0.1]) @ n, atol=1e-12)
    np.testing.assert_allclose(point, x - dist[:, None] * n, atol=1e-12)
    world.close()


def test_row_groups_equal_numpys_unique_rows():
    from integration.collision import row_groups

    rng = np.random.default_rng(3)
    for m in (1, 7, 300):
        rows = np.c_[rng.integers(0, 3, m), rng.integers(-2, 2, (m, 3)).astype(float)]
        _, inverse = np.unique(rows, axis=0, return_inverse=True)
        assert np.array_equal(row_groups(rows), inverse.reshape(-1))
    assert len(row_groups(np.zeros((0, 4)))) == 0
