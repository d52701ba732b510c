"""The one-pass soft contact search (softcontact.soft_contacts) against the search pair by pair and direction by
direction (softcontact.pair_contacts_reference): the same contacts, in the same order, for random piles of
overlapping, moving bodies with and without self-contact."""
import numpy as np

from softbody import box_mesh
from integration.softcontact import SoftSurface, pair_contacts_reference, soft_contacts


def test_one_pass_search_finds_what_the_pairwise_search_finds():
    rng = np.random.default_rng(5)

    def body(center, kind):
        m = box_mesh((0.04, 0.04, 0.04), (2, 2, 2), kind, center=center)
        x = m.nodes + 0.002 * rng.standard_normal(m.nodes.shape)  # a little deformed
        v = 0.3 * rng.standard_normal(m.nodes.shape)
        return x, v, SoftSurface.of(m.nodes, m.surface_triangles()), m.nodes.copy()

    found = 0
    for _ in range(20):
        n = int(rng.integers(2, 7))
        bodies = [body(rng.uniform(-0.05, 0.05, 3), ("tet4", "tet10")[int(rng.integers(2))]) for _ in range(n)]
        pairs = [(a, b) for a in range(n) for b in range(a + 1, n)] + [(a, a) for a in range(n) if rng.random() < 0.3]
        order = rng.permutation(len(pairs))
        pairs = [pairs[k] for k in order]
        fast = soft_contacts(bodies, pairs, 0.005, 0.01, 0.025)
        slow = pair_contacts_reference(bodies, pairs, 0.005, 0.01, 0.025)
        found += len(slow)
        for f in ("a", "node", "b", "triangle", "nodes", "weights", "normal", "distance", "key"):
            x, y = getattr(fast, f), getattr(slow, f)
            assert x.shape == y.shape, f
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
