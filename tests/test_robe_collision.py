"""`robe_contact.contact`, the independent check of the robe against the body as rendered, on
hand-made shapes; the robe of both dances against the body: tests/test_noh_bruteforce.py (it
shares their simulation with the frame's reference)."""

import numpy as np
from robe_contact import BodyShape, contact


def _cube(centre, half):
    """A closed cube's vertices and outward triangles."""
    corners = np.asarray([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * half + centre
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return corners, np.asarray([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def test_through_triangles_counted_per_body_part():
    """Two cubes 1 m apart: a robe triangle pierced by the first cube's edges, one long thin
    triangle whose edge goes through both, one wholly inside the second (its corners inside),
    one outside both: 3 through, by part 2 and 2 (the long one counts for both)."""
    (v0, t0), (v1, t1) = _cube(np.zeros(3), 0.1), _cube(np.asarray([1.0, 0.0, 0.0]), 0.1)
    shape = BodyShape(np.concatenate([v0, v1]), np.concatenate([t0, t1 + 8]))
    robe = np.asarray([[-0.3, 0.0, -0.3], [0.3, 0.0, -0.3], [0.0, 0.0, 0.3],          # a sheet across cube 0
                       [-0.5, 0.02, 0.05], [1.5, 0.02, 0.05], [0.5, 0.5, 0.05],     # an edge through both
                       [0.95, 0.0, 0.0], [1.05, 0.0, 0.0], [1.0, 0.05, 0.0],        # inside cube 1
                       [0.4, 1.0, 0.0], [0.6, 1.0, 0.0], [0.5, 1.2, 0.0]])          # clear of both
    c = contact(robe, np.arange(12).reshape(4, 3), shape)
    first = int(np.argmin(np.linalg.norm([s[0] for s in shape.sphere], axis=-1)))
    assert c.triangles == 3 and c.inside_vertices == 3
    assert list(c.by_part[[first, 1 - first]]) == [2, 2]
