"""The one-pass soft contact search (softcontact.soft_contacts) against the search pair by pair and direction by
direction (softcontact.pair_contacts_reference): the same contacts, in the same order, for random piles of
overlapping, moving bodies with and without self-contact; with the compiled narrow phase (integration.kernels) to
round-off, with numpy's bit for bit."""
import numpy as np
import pytest

from softbody import box_mesh
from integration import kernels
from integration.softcontact import SoftSurface, pair_contacts_reference, soft_contacts


def _pile(rng, spread: float, most: int, turned: bool = False):
    """(bodies, pairs): 2 to most - 1 tet4 or tet10 cubes (4 cm), a little deformed and moving, centred within
    +-spread [m] of the origin (``turned``: each turned at random, so that edges cross at all angles), all pairs and
    some self-contact."""
    def body(center, kind):
        m = box_mesh((0.04, 0.04, 0.04), (2, 2, 2), kind, center=center)
        x = m.nodes
        if turned:
            R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
            x = (m.nodes - center) @ R.T + center
        x = x + 0.002 * rng.standard_normal(m.nodes.shape)  # a little deformed
        v = 0.3 * rng.standard_normal(m.nodes.shape)
        return x, v, SoftSurface.of(m.nodes, m.surface_triangles()), m.nodes.copy()

    n = int(rng.integers(2, most))
    bodies = [body(rng.uniform(-spread, spread, 3), ("tet4", "tet10")[int(rng.integers(2))]) for _ in range(n)]
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)] + [(a, a) for a in range(n) if rng.random() < 0.3]
    return bodies, pairs


@pytest.mark.parametrize("compiled", [True, False])
def test_one_pass_search_finds_what_the_pairwise_search_finds(compiled, monkeypatch):
    if compiled and not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    monkeypatch.setattr(kernels, "ENABLED", compiled)
    rng = np.random.default_rng(5)
    found = 0
    for _ in range(20):
        bodies, pairs = _pile(rng, 0.05, 7)
        order = rng.permutation(len(pairs))
        pairs = [pairs[k] for k in order]
        fast = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025)
        slow = pair_contacts_reference(bodies, pairs, 0.005, 0.01, 0.025)
        found += len(slow)
        for f in ("a", "node", "b", "triangle", "nodes", "weights", "normal", "distance", "key"):
            x, y = getattr(fast, f), getattr(slow, f)
            assert x.shape == y.shape, f
            if compiled and x.dtype.kind == "f":  # the same arithmetic in another order: round-off
                np.testing.assert_allclose(x, y, rtol=0, atol=1e-13, err_msg=f)
            else:
                np.testing.assert_array_equal(x, y, err_msg=f)
    assert found > 200  # the piles overlap: the comparison is not between two empty sets


def test_bodies_joined_only_by_edge_edge_rows_solve_together():
    """contact._groups: an edge-edge row's slots are (a, a, b, b), a node-face row's (a, b, b, b); both join a and b
    (reading the first two slots only left bodies joined by edge rows in different solves)."""
    from integration.contact import _groups

    class Rows:
        parts = np.array([[0, 0, 2, 2], [3, 1, 1, 1]])

        def __len__(self):
            return len(self.parts)

    label = _groups(5, Rows())
    assert label[0] == label[2] and label[1] == label[3]
    assert len({label[0], label[1], label[4]}) == 3


def test_edge_search_finds_what_every_pair_of_edges_finds(monkeypatch):
    """softcontact.edge_contacts with the compiled broad and narrow phases (kernels.edges_near, edge_candidates,
    edge_narrow), with numpy's (softcontact.edges_near, edge_candidates, edge_narrow) and with no broad phase at all
    (softcontact.edge_contacts_reference: every pair of edges through numpy's narrow phase): the same edge crossings
    in the same order (to round-off in the weights, normals and distances) in random piles of overlapping, turned,
    moving bodies with and without self-contact, with and without the node contacts that explain edges."""
    from integration.softcontact import edge_contacts, edge_contacts_reference

    rng = np.random.default_rng(11)
    modes = (True, False) if kernels.ENABLED else (False,)
    found = 0
    for _ in range(30):
        bodies, pairs = _pile(rng, 0.04, 6, turned=True)
        pairs = [pairs[k] for k in rng.permutation(len(pairs))]
        hits = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025)
        for explained in (None, hits):
            out = {"reference": edge_contacts_reference(bodies, pairs, 0.005, 0.01, 0.005, explained)}
            for compiled in modes:
                monkeypatch.setattr(kernels, "ENABLED", compiled)
                out[compiled] = edge_contacts(bodies, pairs, 0.005, 0.01, 0.005, explained)
            found += len(out["reference"])
            for which in out:
                for f in ("a", "b", "nodes", "key"):
                    np.testing.assert_array_equal(getattr(out[which], f), getattr(out["reference"], f),
                                                  err_msg=f"{which} {f}")
                for f in ("weights", "normal", "distance"):
                    np.testing.assert_allclose(getattr(out[which], f), getattr(out["reference"], f), rtol=0,
                                               atol=1e-13, err_msg=f"{which} {f}")
    assert found > 50  # crossings were found: the comparison is not between two empty sets


def test_triangle_distances_are_those_of_the_closest_points_on_the_triangles():
    """kernels.triangle_distances (the kept first pass's pruning) against collision.closest_on_triangles (numpy), for
    points in every Voronoi region of random triangles, degenerate ones too."""
    from integration.collision import closest_on_triangles

    if not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    rng = np.random.default_rng(9)
    X = rng.normal(size=(60, 3))
    X[50:] = X[40:50]  # some triangles with repeated corners
    tris = rng.integers(0, 60, size=(80, 3))
    tris[:5, 1] = tris[:5, 0]
    xs = rng.normal(size=(400, 3))
    i, t = rng.integers(0, 400, 20000), rng.integers(0, 80, 20000)
    got = np.empty(len(i))
    kernels.triangle_distances(xs, X, tris, i, t, got)
    P = X[tris[t]]
    want = np.linalg.norm(xs[i] - closest_on_triangles(xs[i], P[:, 0], P[:, 1], P[:, 2]), axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


def test_the_warm_up_runs_every_soft_search_kernel(monkeypatch):
    """integration.warmup.soft_search reaches every compiled kernel of the soft search (the background warm-up
    compiles what it runs; a kernel it missed would compile during a user's step)."""
    from integration import warmup

    if not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    names = ("triangle_spheres", "centre_grid", "soft_candidates", "first_pass_among", "soft_deep_candidates",
             "soft_nearest", "triangle_distances", "edges_near", "edge_candidates", "edge_narrow", "edge_depths")
    called = set()
    for name in names:
        def wrapped(*args, _f=getattr(kernels, name), _name=name):
            called.add(_name)
            return _f(*args)
        monkeypatch.setattr(kernels, name, wrapped)
    warmup.soft_search()
    assert called == set(names)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("nodes", [True, False])
def test_edge_pairs_kept_from_step_to_step_find_what_a_search_of_each_step_finds(compiled, nodes, monkeypatch):
    """softcontact.EdgePass: a pile of turned bodies moving a little from step to step, now and then a body moved
    beyond the skin or heading for the others (its reach grown beyond the skin), with node contacts coming and going
    (``nodes``; else none) searched for edge crossings with the candidate pairs kept, and searched afresh every step:
    the same crossings at every step, the kept pairs serving some steps and found anew at others."""
    from integration.softcontact import EdgePass, SoftLayout, edge_contacts

    if compiled and not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    monkeypatch.setattr(kernels, "ENABLED", compiled)
    rng = np.random.default_rng(21)
    kept = EdgePass()
    found = 0
    bodies, pairs = _pile(rng, 0.03, 6, turned=True)
    bodies = [(x.copy(), 0.01 * v, sf, r) for x, v, sf, r in bodies]
    layout = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs)
    centre = np.mean([x.mean(axis=0) for x, _, _, _ in bodies], axis=0)
    for step in range(60):
        scale = EdgePass.SKIN * 0.02  # within the skin
        bodies = [(x + scale * rng.standard_normal(x.shape), v, sf, r) for x, v, sf, r in bodies]
        k = step % len(bodies)
        x, v, sf, r = bodies[k]
        towards = (centre - x.mean(axis=0)) / np.linalg.norm(centre - x.mean(axis=0))
        if step % 10 == 9:  # a body moves 3 mm towards the others: beyond the skin
            bodies[k] = (x + 0.003 * towards, v, sf, r)
        if step % 10 == 4:  # a body heads for the others at 0.2 m/s without moving: its reach grows beyond the skin
            bodies[k] = (x, v + 0.2 * towards, sf, r)
        hits = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025) if nodes else None
        if nodes and step % 7 == 3:  # node contacts gone: the edges they excluded are candidates again
            hits = hits.select(np.arange(len(hits)) % 2 == 0)
        fresh = edge_contacts(bodies, pairs, 0.005, 0.01, 0.005, hits)
        again = edge_contacts(bodies, pairs, 0.005, 0.01, 0.005, hits, layout, kept)
        found += len(fresh)
        for f in ("a", "b", "nodes", "key"):
            np.testing.assert_array_equal(getattr(again, f), getattr(fresh, f), err_msg=f)
        for f in ("weights", "normal", "distance"):
            np.testing.assert_allclose(getattr(again, f), getattr(fresh, f), rtol=0, atol=1e-13, err_msg=f)
    assert kept.served >= 15 and kept.found >= 4 and found > 100


def test_first_pass_kept_from_step_to_step_finds_what_a_search_of_each_step_finds(monkeypatch):
    """softcontact.FirstPass: a pile whose bodies move a little from step to step (some steps within the skin, some
    beyond it, and one body sped up) searched with the first pass's candidates kept, and searched afresh every step:
    the same contacts at every step, the kept candidates serving some steps and found anew at others."""
    from integration.softcontact import FirstPass, SoftLayout

    if not kernels.ENABLED:
        pytest.skip("the compiled kernels are off here")
    rng = np.random.default_rng(8)
    kept = FirstPass()
    found = 0
    bodies, pairs = _pile(rng, 0.03, 6)
    bodies = [(x.copy(), 0.01 * v, sf, r) for x, v, sf, r in bodies]
    layout = SoftLayout.of([sf for _, _, sf, _ in bodies], pairs)  # kept candidates serve the layout they were for
    for step in range(40):
        scale = FirstPass.SKIN * (0.02 if step % 10 else 1.0)  # mostly within the skin, now and then beyond it
        bodies = [(x + scale * rng.standard_normal(x.shape), v, sf, r) for x, v, sf, r in bodies]
        if step == 25:  # a body speeds up: its travels grow
            x, v, sf, r = bodies[0]
            bodies[0] = (x, 30 * v, sf, r)
        fresh = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025)
        again = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025, layout, kept)
        found += len(fresh)
        for f in ("a", "node", "b", "triangle", "nodes", "key"):
            np.testing.assert_array_equal(getattr(again, f), getattr(fresh, f), err_msg=f)
        for f in ("weights", "normal", "distance"):
            np.testing.assert_allclose(getattr(again, f), getattr(fresh, f), rtol=0, atol=1e-13, err_msg=f)
    assert kept.served >= 20 and kept.found >= 4 and found > 100
    # two cubes 30 mm apart, beyond the first pass's reach at rest: no contact; then one closes on the other at 2 m/s
    # without having moved: within the step's reach, its nodes are contacts (the kept candidates, found at rest, do not
    # serve)
    m = box_mesh((0.04, 0.04, 0.04), (4, 4, 4), "tet4")
    surface = SoftSurface.of(m.nodes, m.surface_triangles())
    pair = [(m.nodes.copy(), np.zeros_like(m.nodes), surface, m.nodes.copy()),
            (m.nodes + (0.07, 0.0, 0.0), np.zeros_like(m.nodes), surface, m.nodes.copy())]
    layout, kept = SoftLayout.of([surface, surface], [(0, 1)]), FirstPass()
    assert not len(soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025, layout, kept))
    pair[0] = (pair[0][0], np.tile([2.0, 0.0, 0.0], (len(m.nodes), 1)), surface, m.nodes.copy())
    closing = soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025, layout, kept)
    assert len(closing) and np.array_equal(closing.key, soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025).key)
    # the same cubes at rest 0.2 mm beyond the margin: no contact, the kept candidates pruned to what can come within
    # it while they serve; one moved 0.22 mm closer (within the skin: served) is in contact, as a fresh search finds
    # (1 cm cubes: their triangles' prism tolerance, 2 PRISM_TOL L = 0.14 mm, is less than the 0.2 mm)
    m = box_mesh((0.01, 0.01, 0.01), (4, 4, 4), "tet4")
    surface = SoftSurface.of(m.nodes, m.surface_triangles())
    pair = [(m.nodes.copy(), np.zeros_like(m.nodes), surface, m.nodes.copy()),
            (m.nodes + (0.0152, 0.0, 0.0), np.zeros_like(m.nodes), surface, m.nodes.copy())]
    layout, kept = SoftLayout.of([surface, surface], [(0, 1)]), FirstPass()
    assert not len(soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025, layout, kept))
    pair[0] = (m.nodes + (0.00022, 0.0, 0.0), *pair[0][1:])
    near = soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025, layout, kept)
    assert kept.served == 1 and len(near) >= 25
    assert np.array_equal(near.key, soft_contacts(pair, [(0, 1)], 0.005, 0.01, 0.025).key)
