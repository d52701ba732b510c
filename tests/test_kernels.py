"""The compiled kernels (softbody.kernels, numba) against their numpy references and against independent truth."""
import numpy as np
import pytest

from softbody import kernels, rotation


def _numpy_path(monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", False)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_polar_kernel_equals_the_numpy_iteration_and_the_svd(monkeypatch):
    """Random well-shaped, inverted and degenerate F: the compiled rotations equal the numpy iteration's to its
    tolerance, are proper rotations, and equal U V^T of the SVD for every F with det F > 0."""
    rng = np.random.default_rng(7)
    n = 3000
    F = np.eye(3) + 0.6 * rng.standard_normal((n, 3, 3))
    F[:50, :, 0] *= -1.0  # inverted
    F[50:60, 2] = F[50:60, 0]  # degenerate: two equal rows
    F9 = np.ascontiguousarray(F.reshape(n, 9).T)
    R = rotation.polar_rotation_components(F9)
    with monkeypatch.context() as m:
        _numpy_path(m)
        R0 = rotation.polar_rotation_components(F9)
    assert np.abs(R - R0).max() < 1e-11
    Rm = R.T.reshape(n, 3, 3)
    assert np.abs(Rm @ np.swapaxes(Rm, 1, 2) - np.eye(3)).max() < 1e-12
    assert np.all(np.linalg.det(Rm) > 0.999999)
    good = np.linalg.det(F) > 1e-3
    U, _, Vt = np.linalg.svd(F[good])
    assert np.abs(Rm[good] - U @ Vt).max() < 1e-9


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_warped_stiffness_kernels_equal_numpy_and_the_rotated_element_matrices(kind, monkeypatch):
    """A randomly deformed box: the warped stiffness K' = sum_e R_e K_e R_e^T and the warped rest loads made by the
    compiled passes (tet4: softbody.kernels.warped_pairs, element by element, and the diagonal blocks from their
    rows; every kind: the isotropic map in closed form; the system's blocks c_m M + c_k K' made from them) equal
    numpy's (sparse products, a bincount, a matrix product) to round-off, and K' equals the assembly of the rotated
    element matrices themselves (independent of the pair layout and its diagonal-from-rows rule)."""
    from softbody import FemBody, LinearElastic, box_mesh

    rng = np.random.default_rng(3)
    body = FemBody(box_mesh((1.0, 0.6, 0.3), (5, 3, 2), kind), LinearElastic(1e6, 0.3, 1000.0))
    body.positions = body.positions + 0.05 * rng.standard_normal(body.positions.shape)
    R = body.rotations()
    K, load = body.warped_stiffness_upper(R)
    A = body.system_blocks(K, 1.3, 1e-3)
    with monkeypatch.context() as m:
        _numpy_path(m)
        K0, load0 = body.warped_stiffness_upper(R)
        A0 = body.system_blocks(K, 1.3, 1e-3)
    np.testing.assert_array_equal(A, A0)  # the system's blocks from K (kernels.system_blocks): the same arithmetic
    np.testing.assert_allclose(K, K0, rtol=0, atol=1e-12 * np.abs(K0).max())
    np.testing.assert_allclose(load, load0, rtol=0, atol=1e-12 * np.abs(load0).max())
    k = body.mesh.elements.shape[1]
    Rb = np.zeros((len(R), 3 * k, 3 * k))  # block-diagonal R per element, interleaved dofs
    for a in range(k):
        Rb[:, 3 * a:3 * a + 3, 3 * a:3 * a + 3] = R
    reference = body.pattern.assemble(Rb @ body.Ke @ np.swapaxes(Rb, 1, 2))
    full = body._upper.full(K)
    assert np.abs(full - reference).max() < 1e-9 * np.abs(reference).max()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
@pytest.mark.parametrize("kind", ["sphere", "capsule", "cylinder", "box"])
def test_round_face_prefilter_changes_no_face_contact(kind, monkeypatch):
    """Round parts and a box at random poses in and over a bumpy soft surface, at rest and moving (sweeps): the face
    contacts found with the compiled early-out (kernels.face_contacts_possible) and prefilter are those found
    without them, field by field; the early-out skips the search in some poses and never where contacts are."""
    import pybullet as p

    from integration import World
    from integration import kernels as contact_kernels
    from integration.collision import CollisionDetector, Sweep, _face_contacts_possible
    from softbody import FemBody, LinearElastic, box_mesh

    rng = np.random.default_rng(11)
    world = World()
    cid = world.client
    body = FemBody(box_mesh((0.4, 0.4, 0.1), (6, 6, 2), "tet4"), LinearElastic(1e6, 0.3, 1000.0))
    x = body.positions + 0.004 * rng.standard_normal(body.positions.shape)
    tris = body.mesh.surface_triangles()
    shape = {"sphere": dict(shapeType=p.GEOM_SPHERE, radius=0.05),
             "capsule": dict(shapeType=p.GEOM_CAPSULE, radius=0.03, height=0.12),
             "cylinder": dict(shapeType=p.GEOM_CYLINDER, radius=0.04, height=0.1),
             "box": dict(shapeType=p.GEOM_BOX, halfExtents=[0.04, 0.03, 0.02])}[kind]
    col = p.createCollisionShape(physicsClientId=cid, **shape)
    radius = shape.get("radius", 0.03)
    found, skipped = 0, 0
    for trial in range(60):
        pos = [rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), 0.05 + radius + rng.uniform(-0.015, 0.01)]
        orn = p.getQuaternionFromEuler(rng.uniform(-np.pi, np.pi, 3).tolist())
        rb = world.rigid(p.createMultiBody(0, col, basePosition=pos, baseOrientation=orn, physicsClientId=cid))
        touching = rng.random(len(x)) < 0.2
        touch_normal = np.where(touching[:, None], [0.0, 0.0, -1.0], 0.0)
        sweep = None
        if trial % 2:
            vel = 0.5 * rng.standard_normal(x.shape)
            sweep = Sweep(0.01, 0.01, vel, np.linalg.norm(vel, axis=1), rng.standard_normal(3), 3 * rng.standard_normal(3),
                          rb.pose()[0], rb.bounding_radius())
        args = (0, x, tris, rb, 0.01, touching, touch_normal, None, sweep)
        with_kernel = CollisionDetector.face_contacts(*args)
        possible = _face_contacts_possible(x, tris, rb, 0.01, touching, sweep)
        skipped += not possible
        assert possible or not len(with_kernel)
        with monkeypatch.context() as m:
            m.setattr(contact_kernels, "ENABLED", False)
            without = CollisionDetector.face_contacts(*args)
        for f in with_kernel.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(with_kernel, f), getattr(without, f), err_msg=f)
        found += len(with_kernel)
    assert found > 20 and skipped > 3  # the poses made contacts to compare, and some the early-out skipped
    world.close()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_normals_at_contact_nodes_equal_the_whole_surfaces():
    """The compiled normals at a few nodes (integration.kernels.node_normals_at) are the rows of the whole surface's
    area-weighted normals (numpy, both sums), on a randomly deformed tet10 box."""
    from integration.collision import node_incidence, node_normals, vertex_normals
    from softbody import box_mesh

    rng = np.random.default_rng(4)
    mesh = box_mesh((0.3, 0.2, 0.1), (3, 2, 2), "tet10")
    x = mesh.nodes + 0.01 * rng.standard_normal(mesh.nodes.shape)
    tris = mesh.surface_triangles()
    inc = node_incidence(tris, len(x))
    nodes = rng.choice(np.unique(tris), 40)
    full = vertex_normals(x, tris)
    np.testing.assert_allclose(vertex_normals(x, tris, inc), full, atol=1e-15)
    np.testing.assert_allclose(node_normals(x, tris, nodes, inc), full[nodes], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(full[nodes], axis=1), 1.0, atol=1e-12)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_node_frames_kernel_equals_numpy(monkeypatch):
    """Per-node frames of a tet10 box whose elements alternate between two rotations half a turn apart, so that at
    nodes with as many elements of each the sums' first two columns cancel (the polar fallback), and a few elements
    with the deformed mesh's own rotations: compiled and numpy paths agree, and every frame is a proper rotation."""
    from softbody import FemBody, LinearElastic, box_mesh

    rng = np.random.default_rng(8)
    body = FemBody(box_mesh((0.3, 0.2, 0.1), (3, 2, 2), "tet10"), LinearElastic(1e6, 0.3, 1000.0))
    body.positions = body.positions + 0.02 * rng.standard_normal(body.positions.shape)
    R = np.array(body.rotations())
    turn = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    turn *= np.linalg.det(turn)  # a proper rotation
    R[0::2] = turn
    R[1::2] = turn @ np.diag([-1.0, -1.0, 1.0])  # every other element half a turn from it (about its z)
    R[:6] = np.array(body.rotations())[:6]  # and a few as the deformed mesh gives them
    S9 = (body._incidence @ R.reshape(len(R), 9)).T  # the sums of the adjacent elements' rotations, (9, N)
    a, b = S9[[0, 3, 6]], S9[[1, 4, 7]]
    small = 1e-3 * np.linalg.norm(S9, axis=0)
    assert ((np.linalg.norm(a, axis=0) <= small) | (np.linalg.norm(b, axis=0) <= small)).any()  # fallback reached
    Q = body.node_frames(R)
    with monkeypatch.context() as m:
        _numpy_path(m)
        Q0 = body.node_frames(R)
    np.testing.assert_allclose(Q, Q0, atol=1e-14)
    np.testing.assert_allclose(Q @ np.swapaxes(Q, 1, 2), np.broadcast_to(np.eye(3), Q.shape), atol=1e-12)
    assert np.all(np.linalg.det(Q) > 0.999999)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_contact_loop_steps_as_the_numpy_one(monkeypatch):
    """The compiled parts of the contact solve (tangent frames, the active set's start, friction update and
    results) against their numpy references, end to end: a soft cube sliding down a 30 degree incline (mu 0.5 <
    tan 30: its contacts slide) and the sheet-on-sphere scene (contacts added and released), stepped with and
    without them, give the same trajectories and contact forces, bit for bit, and the same count of sliding
    contacts."""
    from types import SimpleNamespace

    from experiments.scenes import sheet_on_sphere
    from integration import World
    from integration import contact
    from softbody import FemBody, LinearElastic, Mesh, box_mesh

    def incline():
        world = World(dt=0.005)
        n = np.array([-np.sin(np.pi / 6), 0.0, np.cos(np.pi / 6)])
        world.add_plane(normal=n)
        flat = box_mesh((0.1, 0.1, 0.1), (2, 2, 2), "tet4")  # turned onto the incline, resting on it
        turn = np.array([[np.cos(np.pi / 6), 0.0, -np.sin(np.pi / 6)], [0.0, 1.0, 0.0],
                         [np.sin(np.pi / 6), 0.0, np.cos(np.pi / 6)]])
        mesh = Mesh(flat.nodes @ turn.T + 0.0501 * n, flat.elements, "tet4")
        cube = world.add_soft(FemBody(mesh, LinearElastic(2e5, 0.3, 1000.0), damping=(0.1, 0.001)), friction=0.5)
        return world, cube

    def sheet():
        scene = sheet_on_sphere("tet4", (4, 4, 2))
        return scene.world, scene.world.bodies[0]

    for build, steps in ((incline, 40), (sheet, 45)):
        runs = []
        for enabled in (True, False):
            with monkeypatch.context() as m:  # the contact solve's kernels only (the search keeps its own)
                if not enabled:
                    m.setattr(contact, "kernels", SimpleNamespace(ENABLED=False))
                world, body = build()
                slipping, forces = 0, []
                for _ in range(steps):
                    world.step()
                    slipping += sum(int(np.sum(res.active & ~res.stick)) for _, res in world.contact_results.values())
                    forces += [res.force for _, res in world.contact_results.values()]
                runs.append((body.positions.copy(), slipping, np.concatenate(forces)))
                world.close()
        np.testing.assert_array_equal(runs[0][0], runs[1][0])  # the same arithmetic: bit for bit
        np.testing.assert_array_equal(runs[0][2], runs[1][2])  # the contact forces too
        assert runs[0][1] == runs[1][1]
        if build is incline:
            assert runs[0][1] > 0  # contacts slid at some step


def _four_primitives(cid: int, rng: np.random.Generator, scale: float) -> int:
    """pybullet's compound collision shape of a sphere, a box, a capsule and a cylinder [m, times ``scale``], each
    turned at random and offset from the link's centre."""
    import pybullet as p

    return p.createCollisionShapeArray(
        [p.GEOM_SPHERE, p.GEOM_BOX, p.GEOM_CAPSULE, p.GEOM_CYLINDER], radii=[scale * r for r in (0.1, 0.0, 0.05, 0.07)],
        halfExtents=[[0, 0, 0], [scale * e for e in (0.1, 0.05, 0.08)], [0, 0, 0], [0, 0, 0]],
        lengths=[scale * h for h in (0.0, 0.0, 0.2, 0.15)],
        collisionFramePositions=[[scale * c for c in pos] for pos in ([0.2, 0, 0], [-0.2, 0, 0.05], [0, 0.2, 0],
                                                                      [0, -0.2, -0.05])],
        collisionFrameOrientations=[p.getQuaternionFromEuler(rng.uniform(-1, 1, 3).tolist()) for _ in range(4)],
        physicsClientId=cid)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_primitive_distances_equal_numpys(monkeypatch):
    """A link of four primitives (sphere, box, capsule, cylinder, each turned and offset; pybullet's compound
    shape) and a tilted plane: the compiled closest points, normals and signed distances of random points in and
    around them (the nearest part's) equal distance.py's, which tests/test_distance.py checks against pybullet."""
    import pybullet as p

    from integration import World
    from integration import kernels as contact_kernels
    from integration.collision import primitive_distances

    world = World()
    cid = world.client
    rng = np.random.default_rng(12)
    col = _four_primitives(cid, rng, 1.0)
    body = p.createMultiBody(0, col, basePosition=[0.1, 0.2, 0.3],
                             baseOrientation=p.getQuaternionFromEuler([0.4, -0.2, 0.7]), physicsClientId=cid)
    links = [world.rigid(body), world.add_plane(normal=(0.3, -0.2, 1.0), point=(0, 0, -0.1))]
    assert [part.shape.kind for part in links[0].primitive_parts()] == ["sphere", "box", "capsule", "cylinder"]
    for rb in links:
        lo, hi = rb.aabb()
        lo, hi = np.maximum(lo, -1.0), np.minimum(hi, 1.0)
        x = rng.uniform(lo - 0.1, hi + 0.1, size=(3000, 3))
        got = primitive_distances(rb, rb.primitive_parts(), x)
        with monkeypatch.context() as m:
            m.setattr(contact_kernels, "ENABLED", False)
            want = primitive_distances(rb, rb.primitive_parts(), x)
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, atol=1e-12, rtol=0)
        assert (got[2] < 0).sum() > 20  # points inside were compared too
    world.close()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_node_contacts_equal_numpys(monkeypatch):
    """Node contacts of a bumpy soft surface against a compound link of four primitives and a plane, at rest and
    moving (random link velocity and spin, random node velocities): the compiled pass (box, swept sphere, closest
    parts and reach node by node, kernels.primitive_node_contacts) finds the nodes numpy's chain finds, with the
    same points, normals and distances, and counts the same candidates."""
    import pybullet as p

    from integration import World
    from integration import kernels as contact_kernels
    from integration.collision import CollisionDetector, Sweep
    from softbody import FemBody, LinearElastic, box_mesh

    world = World()
    cid = world.client
    rng = np.random.default_rng(31)
    col = _four_primitives(cid, rng, 0.5)
    soft = FemBody(box_mesh((0.5, 0.5, 0.1), (8, 8, 2), "tet4"), LinearElastic(1e6, 0.3, 1000.0))
    x = soft.positions + 0.004 * rng.standard_normal(soft.positions.shape)
    surface = np.unique(soft.mesh.surface_triangles())
    detector = CollisionDetector(cid)
    plane = world.add_plane(normal=(0.1, -0.2, 1.0), point=(0, 0, -0.04))
    found = 0
    for trial in range(40):
        if trial % 4 == 3:
            rb = plane
        else:
            pos = [rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), 0.05 + rng.uniform(-0.04, 0.03)]
            orn = p.getQuaternionFromEuler(rng.uniform(-np.pi, np.pi, 3).tolist())
            rb = world.rigid(p.createMultiBody(0, col, basePosition=pos, baseOrientation=orn, physicsClientId=cid))
        vel = 0.5 * rng.standard_normal(x.shape)
        moving = trial % 2 == 1
        motion = (rng.standard_normal(3), 3 * rng.standard_normal(3)) if moving else (np.zeros(3), np.zeros(3))
        sweep = Sweep(0.01, 0.01, vel, np.linalg.norm(vel, axis=1), *motion, rb.pose()[0], rb.bounding_radius())
        bound = sweep.bound(surface)
        before = detector.last_candidates
        got = detector.node_contacts(0, x, surface, rb, bound, sweep)
        between = detector.last_candidates
        with monkeypatch.context() as m:
            m.setattr(contact_kernels, "ENABLED", False)
            want = detector.node_contacts(0, x, surface, rb, bound, sweep)
        assert between - before == detector.last_candidates - between
        np.testing.assert_array_equal(got.node, want.node)
        for f in ("body", "rigid", "link"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
        for f in ("point", "normal", "distance"):
            np.testing.assert_allclose(getattr(got, f), getattr(want, f), rtol=0, atol=1e-12)
        found += len(got)
    assert found > 100
    world.close()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_one_call_per_primitive_link_detects_as_numpy(monkeypatch):
    """CollisionDetector.detect on a bumpy soft surface with some nodes supported, against a compound link of four
    primitives, a box, a sphere and a plane, far off, near and overlapping, at rest and moving: the one compiled call
    per link (kernels.primitive_link_contacts: broad phase, node contacts, facing test, resting nodes, face-search
    early-out) gives numpy's node contacts and face contacts, field by field, and counts the same candidates."""
    import pybullet as p

    from integration import World
    from integration import kernels as contact_kernels
    from integration.collision import CollisionDetector, Sweep, node_incidence
    from softbody import FemBody, LinearElastic, box_mesh

    world = World()
    cid = world.client
    rng = np.random.default_rng(37)
    shapes = [_four_primitives(cid, rng, 0.5), p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.06, 0.04, 0.03],
                                                                      physicsClientId=cid),
              p.createCollisionShape(p.GEOM_SPHERE, radius=0.05, physicsClientId=cid)]
    soft = FemBody(box_mesh((0.5, 0.5, 0.1), (8, 8, 2), "tet4"), LinearElastic(1e6, 0.3, 1000.0))
    x = soft.positions + 0.004 * rng.standard_normal(soft.positions.shape)
    tris = soft.mesh.surface_triangles()
    incidence = node_incidence(tris, soft.n_nodes)
    surface = np.unique(tris)
    supported = np.zeros(soft.n_nodes, dtype=bool)
    supported[rng.choice(soft.n_nodes, 6, replace=False)] = True
    plane = world.add_plane(normal=(0.1, -0.2, 1.0), point=(0, 0, -0.04))
    detector = CollisionDetector(cid)
    nodes = faces = far = 0
    for trial in range(48):
        if trial % 6 == 5:
            rb = plane
        else:
            lift = 0.5 if trial % 6 == 4 else rng.uniform(-0.04, 0.03)  # now and then far above the sheet
            pos = [rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), 0.05 + lift]
            orn = p.getQuaternionFromEuler(rng.uniform(-np.pi, np.pi, 3).tolist())
            rb = world.rigid(p.createMultiBody(0, shapes[trial % 3], basePosition=pos, baseOrientation=orn,
                                               physicsClientId=cid))
        vel = 0.5 * rng.standard_normal(x.shape)
        motion = (rng.standard_normal(3), 3 * rng.standard_normal(3)) if trial % 2 else (np.zeros(3), np.zeros(3))
        sweep = Sweep(0.01, 0.01, vel, np.linalg.norm(vel, axis=1), *motion, rb.pose()[0], rb.bounding_radius())
        args = (0, x, surface, tris, supported, [rb], [sweep], 0.001, incidence)
        before = detector.last_candidates
        got, got_faces = detector.detect(*args)
        between = detector.last_candidates
        with monkeypatch.context() as m:
            m.setattr(contact_kernels, "ENABLED", False)
            want, want_faces = detector.detect(*args)
        assert between - before == detector.last_candidates - between
        for f in ("body", "node", "rigid", "link"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f)
        for f in ("point", "normal", "distance"):
            np.testing.assert_allclose(getattr(got, f), getattr(want, f), rtol=0, atol=1e-12, err_msg=f)
        for f in got_faces.__dataclass_fields__:
            np.testing.assert_allclose(getattr(got_faces, f), getattr(want_faces, f), rtol=0, atol=1e-12, err_msg=f)
        nodes, faces, far = nodes + len(got), faces + len(got_faces), far + (between == before)
    assert nodes > 100 and faces > 10 and far >= 8  # contacts of both kinds to compare, and links far off
    world.close()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_a_zero_normal_gives_the_numpy_paths_nan_frame_not_an_error(monkeypatch):
    """The kernels divide as numpy does (error_model "numpy"): a zero-length contact normal (a degenerate query)
    gives the same NaN frame as the numpy path instead of raising ZeroDivisionError."""
    from integration import contact

    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.95, 0.1, 0.3]])
    with np.errstate(invalid="ignore", divide="ignore"):
        F = contact.tangent_frames(normals)
        with monkeypatch.context() as m:
            m.setattr(contact, "kernels", type("Off", (), {"ENABLED": False}))
            F0 = contact.tangent_frames(normals)
    np.testing.assert_array_equal(F, F0)  # NaN where NaN, the same bits elsewhere
    assert np.isnan(F[1]).all() and np.isfinite(F[[0, 2]]).all()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_per_node_frames_kernels_equal_numpy(monkeypatch):
    """Dense per-node frames applied to vectors both ways (integrator.to_local, to_global) and the products of two
    stacks of frames (the preconditioner's node rotations), compiled against numpy's einsum and matmul."""
    from softbody import integrator

    rng = np.random.default_rng(21)
    T = np.linalg.qr(rng.standard_normal((300, 3, 3)))[0]
    x = rng.standard_normal((300, 3))
    out = integrator.to_local(T, x), integrator.to_global(T, x)
    with monkeypatch.context() as m:
        _numpy_path(m)
        ref = integrator.to_local(T, x), integrator.to_global(T, x)
    for a, b in zip(out, ref):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)
    np.testing.assert_allclose(integrator.to_global(T, integrator.to_local(T, x)), x, atol=1e-14)
    Q = np.linalg.qr(rng.standard_normal((300, 3, 3)))[0]
    G = np.empty_like(Q)
    kernels.frame_products(Q, T, G)
    np.testing.assert_allclose(G, Q @ np.swapaxes(T, 1, 2), rtol=0, atol=1e-15)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
@pytest.mark.parametrize("kind", ["tet4", "hex8", "tet10"])
def test_matrix_free_product_kernel_equals_numpy_and_the_assembled_matrix(kind, monkeypatch):
    """K' y element by element (softbody.kernels.warped_product, the stress in closed form) equals numpy's path
    (batched products with the stress map, a sparse scatter) to round-off and the product with the assembled
    warped stiffness, on a randomly deformed box and on a stack of two bodies (whose elements are offset); the
    compiled mass product (kernels.scalar_product) equals the product with the assembled mass blocks."""
    from softbody import FemBody, LinearElastic, box_mesh
    from softbody.stack import BodyStack

    rng = np.random.default_rng(23)
    mat = LinearElastic(1e6, 0.3, 1000.0)
    body = FemBody(box_mesh((1.0, 0.6, 0.3), (4, 3, 2), kind), mat)
    other = FemBody(box_mesh((0.5, 0.5, 0.5), (2, 2, 2), kind, center=(2.0, 0.0, 0.0)), mat)
    for b in (body, BodyStack([body, other])):
        b.positions = b.positions + 0.05 * rng.standard_normal(b.positions.shape)
        R = b.rotations()
        g = b.rotated_gradients(R)
        y = rng.standard_normal(b.positions.shape)
        got = b.warped_product(g, y)
        with monkeypatch.context() as m:
            _numpy_path(m)
            ref = b.warped_product(g, y)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
        K = b.pattern.to_bsr(b.stiffness_blocks(b.warped_stiffness_upper(R)[0]))
        np.testing.assert_allclose(got, (K @ y.ravel()).reshape(-1, 3), rtol=0, atol=1e-11 * np.abs(ref).max())
        M = b.pattern.to_bsr(b.system_blocks(np.zeros((b._upper.n_upper, 9)), 1.0, 0.0))  # the mass matrix, blocks
        np.testing.assert_allclose(b.mass_product(y), (M @ y.ravel()).reshape(-1, 3), rtol=0,
                                   atol=1e-14 * np.abs(M.data).max() * np.abs(y).max())


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_constrained_factorisation_data_equals_numpys(monkeypatch):
    """integrator.factorize_constrained with nodes turned into random frames and some of their components
    eliminated: the compiled passes (kernels.rotate_blocks, kernels.constrained_upper) hand the solver the values
    numpy's products, gather and masking give, and return the same rotated blocks and scale; with no frames too."""
    from softbody import FemBody, LinearElastic, box_mesh
    from softbody.integrator import NodeFrames, factorize_constrained

    class Keep:  # a solver that keeps what it is given
        def factorize(self, data):
            self.data = data.copy()

    rng = np.random.default_rng(41)
    body = FemBody(box_mesh((1.0, 0.6, 0.3), (4, 3, 2), "tet4"), LinearElastic(1e6, 0.3, 1000.0))
    A = body.system_blocks(body.warped_stiffness_upper(body.rotations())[0], 1.0, 1e-4)
    nodes = rng.choice(body.n_nodes, 12, replace=False)
    T = NodeFrames(nodes, np.linalg.qr(rng.standard_normal((12, 3, 3)))[0])
    mask = np.zeros((body.n_nodes, 3), dtype=bool)
    mask[nodes[:8], 0] = True
    mask[nodes[:3]] = True
    for frames in (T, None):
        got, ref = Keep(), Keep()
        out = factorize_constrained(body, A, frames, mask, got)
        with monkeypatch.context() as m:
            _numpy_path(m)
            want = factorize_constrained(body, A, frames, mask, ref)
        np.testing.assert_allclose(out[0], want[0], rtol=0, atol=1e-14 * np.abs(A).max())
        assert out[1] == pytest.approx(want[1], rel=1e-14)
        np.testing.assert_allclose(got.data, ref.data, rtol=0, atol=1e-14 * np.abs(A).max())
        assert (got.data == 0).sum() > 0.05 * len(got.data)  # the eliminated rows and columns are in the test


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_direct_solve_with_constrained_products_equals_numpys(monkeypatch):
    """DirectSystem.solve with some nodes turned into frames (one of them the identity) and some of their
    components held at values, with an extra load, and its homogeneous form: the compiled passes
    (kernels.local_constraints, frames_apply, constrained_rhs, constrained_finish: products over the held nodes'
    blocks) give numpy's velocities and reactions (whole sparse products); the held components take their values,
    and only they have reactions."""
    from softbody import FemBody, LinearElastic, box_mesh
    from softbody.integrator import Constraints, DirectSystem
    from softbody.linsolve import SpdSolver

    rng = np.random.default_rng(43)
    body = FemBody(box_mesh((1.0, 0.6, 0.3), (4, 3, 2), "tet4"), LinearElastic(1e6, 0.3, 1000.0))
    A = body.system_blocks(body.warped_stiffness_upper(body.rotations())[0], 1.0, 1e-4)
    b = rng.standard_normal((body.n_nodes, 3))
    nodes = rng.choice(body.n_nodes, 10, replace=False)
    mask = rng.random((10, 3)) < 0.5
    mask[0] = True
    frames = np.linalg.qr(rng.standard_normal((10, 3, 3)))[0]
    frames[1] = np.eye(3)
    cons = Constraints(nodes, mask, rng.standard_normal((10, 3)), frames)
    extra = rng.standard_normal((body.n_nodes, 3))
    pat = body.pattern
    for c, kwargs in ((cons, {}), (cons, dict(extra_rhs=extra)), (cons, dict(extra_rhs=extra, homogeneous=True)),
                      (Constraints(nodes, mask, cons.value), {})):
        out = []
        for compiled in (True, False):
            with monkeypatch.context() as m:
                if not compiled:
                    _numpy_path(m)
                system = DirectSystem(body, A, b, SpdSolver(pat.up_indptr, pat.up_indices, 3 * body.n_nodes))
                out.append(system.solve(c, **kwargs))
        (y, r), (y0, r0) = out
        np.testing.assert_allclose(y, y0, rtol=0, atol=1e-12 * np.abs(y0).max())
        np.testing.assert_allclose(r, r0, rtol=0, atol=1e-12 * np.abs(r0).max())
        turn = c.frames if c.frames is not None else np.broadcast_to(np.eye(3), (10, 3, 3))
        local = np.einsum("mji,mj->mi", turn, y[nodes])  # the held components took their values
        np.testing.assert_allclose(local[mask], c.value[mask], atol=1e-12)
        assert np.abs(r[nodes][mask]).max() > 0 and not r[np.setdiff1d(np.arange(body.n_nodes), nodes)].any()


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_face_eligibility_equals_numpys(monkeypatch):
    """Face contacts after a solve: which may carry an impulse (their rigid point inside its triangle at the end of
    the step, the nearest of its group, not nearly parallel to an active contact of that point, the first per
    point), compiled (kernels.face_eligible) and numpy (contact._FaceSet.eligible's own lines), on random triangles
    with several contacts per rigid point."""
    from types import SimpleNamespace

    from integration import contact

    rng = np.random.default_rng(53)
    some = 0
    for trial in range(40):
        m, groups, N = 40, 12, 30
        positions = rng.uniform(-1.0, 1.0, (N, 3))
        nodes = np.array([rng.choice(N, 3, replace=False) for _ in range(m)])
        weights = rng.dirichlet(np.ones(3), m) * 1.2 - 0.066  # mostly inside, some outside
        point = np.einsum("ms,msi->mi", weights, positions[nodes]) + 0.01 * rng.standard_normal((m, 3))
        normal = rng.standard_normal((m, 3))
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        group = rng.integers(0, groups, m)
        normal[1::4] = normal[0::4][: len(normal[1::4])]  # some contacts of a point share a face's normal
        c = SimpleNamespace(nodes=nodes, rigid_velocity=0.1 * rng.standard_normal((m, 3)), jacobian=None,
                            point=point, group=group, normal=normal)
        fake = SimpleNamespace(c=c, h=0.01, x_tri=positions[nodes], part=0, active=rng.random(m) < 0.3)
        vs = [0.1 * rng.standard_normal((N, 3))]
        got = contact._FaceSet.eligible(fake, vs, np.zeros(0))
        with monkeypatch.context() as mp:
            mp.setattr(contact, "kernels", SimpleNamespace(ENABLED=False))
            want = contact._FaceSet.eligible(fake, vs, np.zeros(0))
        np.testing.assert_array_equal(got, want)
        some += int(want.sum())
    assert some > 40


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_row_values_equal_numpys(monkeypatch):
    """coupling.Rows.values (the rows' velocities along their directions from one body's velocity fields, for one
    field and for a stack of them), compiled (kernels.row_values) against numpy's einsum, on rows whose slots lie
    on two bodies and unused slots; and the coupled system's combination of responses against tensordot."""
    from integration import coupling
    from integration import kernels as contact_kernels

    rng = np.random.default_rng(59)
    m, s, N, k = 50, 3, 40, 7
    part = rng.integers(-1, 2, (m, s))
    rows = coupling.Rows(part, rng.integers(0, N, (m, s)), rng.standard_normal((m, s)), rng.standard_normal((m, 3)),
                         np.zeros((m, 0)), np.zeros(m))
    v, V = rng.standard_normal((N, 3)), rng.standard_normal((k, N, 3))
    for which in (0, 1):
        got = rows.values(which, v), rows.values(which, V)
        with monkeypatch.context() as mp:
            mp.setattr(contact_kernels, "ENABLED", False)
            want = rows.values(which, v), rows.values(which, V)
        for a, b in zip(got, want):
            assert a.shape == b.shape
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
        assert np.abs(want[0]).max() > 0.1
    Y, R = rng.standard_normal((k, N, 3)), rng.standard_normal((k, N, 3))
    system = coupling.CoupledSystem(np.eye(k), np.zeros(k), [(np.zeros((N, 3)), np.ones((N, 3)))],
                                    [(list(range(k)), Y, R)], 0)
    z = rng.standard_normal(k)
    (y, r), = system.combine(z)
    np.testing.assert_allclose(y, np.tensordot(z, Y, axes=1), rtol=0, atol=1e-13)
    np.testing.assert_allclose(r, 1.0 + np.tensordot(z, R, axes=1), rtol=0, atol=1e-13)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_compiled_closest_points_on_triangles_equal_numpys():
    """Closest points of random points on random triangles (every Voronoi region, and degenerate triangles: a
    repeated vertex, three in a line), compiled row by row (kernels.closest_points) and as distances to the
    nearest of many triangles (kernels.nearest_triangle_distances), against collision.closest_on_triangles, bit for
    bit; and on proper triangles each closest point is no farther than any point of its triangle (random samples)."""
    from integration import kernels as contact_kernels
    from integration.collision import closest_on_triangles

    rng = np.random.default_rng(61)
    m = 2000
    a, b, c, q = (rng.standard_normal((m, 3)) for _ in range(4))
    b[:20] = a[:20]  # degenerate: a repeated vertex
    c[20:40] = 0.5 * (a[20:40] + b[20:40])  # three in a line
    got = np.empty((m, 3))
    contact_kernels.closest_points(q, a, b, c, got)
    want = closest_on_triangles(q, a, b, c)
    np.testing.assert_array_equal(got, want)
    w = rng.dirichlet(np.ones(3), (m, 50))
    samples = w[..., :1] * a[:, None] + w[..., 1:2] * b[:, None] + w[..., 2:] * c[:, None]
    proper = slice(40, None)  # (on a degenerate triangle both give a vertex, not the nearest point of the segment)
    assert np.all(np.linalg.norm(q - got, axis=1)[proper]
                  <= np.linalg.norm(q[:, None] - samples, axis=2).min(axis=1)[proper] + 1e-12)
    x = np.stack([a[:300], b[:300], c[:300]], axis=1)
    dist = np.empty(100)
    contact_kernels.nearest_triangle_distances(q[:100], x, dist)
    ref = np.sqrt(((closest_on_triangles(q[:100, None], x[None, :, 0], x[None, :, 1], x[None, :, 2])
                    - q[:100, None]) ** 2).sum(axis=2)).min(axis=1)
    np.testing.assert_array_equal(dist, ref)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
@pytest.mark.parametrize("kind", ["tet4", "tet10", "hex8"])
def test_block_product_and_characteristic_gradient_kernels_equal_numpy(kind, monkeypatch):
    """BlockPattern.product (kernels.block_product) equals scipy's BSR product bit for bit; the characteristic
    gradients of displaced positions far from the origin (kernels.characteristic_gradients, element by element)
    equal numpy's to round-off, and those of a rigid rotation are that rotation."""
    from softbody import FemBody, LinearElastic, box_mesh

    rng = np.random.default_rng(47)
    body = FemBody(box_mesh((0.5, 0.3, 0.2), (3, 2, 2), kind), LinearElastic(1e6, 0.3, 1000.0))
    A = body.system_blocks(body.warped_stiffness_upper(body.rotations())[0], 1.0, 1e-4)
    y = rng.standard_normal((body.n_nodes, 3))
    np.testing.assert_array_equal(body.pattern.product(A, y),
                                  (body.pattern.to_bsr(A) @ y.reshape(-1)).reshape(-1, 3))
    x = body.positions + 0.01 * rng.standard_normal(body.positions.shape) + [100.0, -50.0, 20.0]
    got = body.characteristic_gradient(x)
    with monkeypatch.context() as m:
        _numpy_path(m)
        want = body.characteristic_gradient(x)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    F = body.characteristic_gradient(body.positions @ Q.T + [3.0, 1.0, -2.0])
    np.testing.assert_allclose(F.T.reshape(-1, 3, 3), np.broadcast_to(Q, (body.mesh.n_elements, 3, 3)), atol=1e-12)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
@pytest.mark.parametrize("cone", [True, False])
def test_line_search_slopes_equal_the_laws_impulses_and_hessians(cone):
    """integration.kernels.law_slopes against convex.cone_law / contact_law: rows in every region (stiction, sliding,
    apart, frictionless, bilateral), at several points along a step."""
    from integration import convex
    from integration import kernels as contact_kernels

    rng = np.random.default_rng(3)
    m = 400
    vc0 = rng.normal(scale=0.05, size=(m, 3))
    dvc = rng.normal(scale=0.05, size=(m, 3))
    R = np.repeat(10.0 ** rng.uniform(-4, 0, size=(m, 1)), 3, axis=1)
    R[:, 0] *= 10.0 ** rng.uniform(-1, 1, size=m)  # normal and tangential entries differ
    v_hat = rng.normal(scale=0.01, size=m)
    mu = np.where(rng.random(m) < 0.2, 0.0, rng.uniform(0.1, 1.0, size=m))
    bilateral = rng.random(m) < 0.1
    param = mu if cone else mu * np.abs(rng.normal(scale=0.05, size=m))
    stuck = slid = 0
    for alpha in (0.0, 0.3, 1.0, 1.5):
        vc = vc0 + alpha * dvc
        law = convex.cone_law(vc, R, v_hat, mu, bilateral) if cone else convex.contact_law(vc, R, v_hat, param,
                                                                                           bilateral)
        gamma, G, _, stick = law
        stuck += int(stick.sum())
        slid += int((~stick & (np.abs(gamma[:, 1:]).sum(axis=1) > 0)).sum())
        want1 = float(np.sum(dvc * gamma))
        want2 = float(np.einsum("mi,mij,mj->", dvc, G, dvc))
        s1, s2 = contact_kernels.law_slopes(vc0, dvc, alpha, R, v_hat, param, bilateral, cone)
        assert s1 == pytest.approx(want1, rel=1e-10, abs=1e-12 * np.abs(dvc * gamma).sum())
        assert s2 == pytest.approx(want2, rel=1e-10)
    assert stuck > 50 and slid > 50  # both regions were tried


@pytest.mark.parametrize("layout, kind", [("pairs", "tet4"), ("matrices", "hex8")])
def test_the_upper_assembly_sums_what_a_dense_assembly_sums(layout, kind, monkeypatch):
    """UpperAssembly keeps one signed block offset per element pair (element_scatter: a pair whose global nodes run the
    other way goes in transposed); numpy's assembly through the scatter it expands from them, mirrored by ``full``,
    equals element blocks summed into a dense matrix: each pair's block at (a, b) and its transpose at (b, a), the
    "pairs" layout's diagonal blocks minus the rest of their block row."""
    from softbody import box_mesh
    from softbody.assembly import BlockPattern, UpperAssembly

    mesh = box_mesh((0.3, 0.2, 0.2), (3, 2, 2), kind)
    pattern = BlockPattern.from_elements(mesh.elements, mesh.n_nodes)
    ua = UpperAssembly.from_elements(pattern, mesh.elements, layout)
    assert ua.element_scatter().shape == (len(mesh.elements), len(ua.pairs))
    rng = np.random.default_rng(9)
    E, k = mesh.elements.shape
    n = mesh.n_nodes
    dense = np.zeros((n, 3, n, 3))
    if layout == "pairs":
        c = rng.standard_normal((len(ua.pairs), 3, 3, E))
        for e in range(E):
            for p, (a, b) in enumerate(ua.pairs):
                A, B = mesh.elements[e, a], mesh.elements[e, b]
                dense[A, :, B] += c[p, :, :, e]
                dense[B, :, A] += c[p, :, :, e].T
        for A in range(n):  # block rows sum to zero
            dense[A, :, A] = -dense[A].sum(axis=1)
    else:
        c = rng.standard_normal((E, 3 * k, 3 * k))
        c = c + np.swapaxes(c, 1, 2)
        for e in range(E):
            nodes = mesh.elements[e]
            dense[nodes[:, None], :, nodes[None, :], :] += c[e].reshape(k, 3, k, 3).transpose(0, 2, 1, 3)
    monkeypatch.setattr(kernels, "ENABLED", False)
    got = pattern.to_bsr(ua.full(ua.assemble(c.copy()))).toarray()
    np.testing.assert_allclose(got, dense.reshape(3 * n, 3 * n), rtol=0, atol=1e-12 * np.abs(dense).max())
