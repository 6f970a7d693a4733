"""The robe against the performer's body as rendered, measured on triangles (shared by the tests and
`benchmarks/noh_collision.py`), independent of the simulator: nothing here knows of capsules.

Two triangles intersect exactly when an edge of one crosses the other, so a robe triangle goes
through the body when one of its edges crosses a body triangle or a body edge crosses it
(segment-triangle tests, Moller-Trumbore with the segment's parameter in [0, 1]); a robe
triangle lies wholly inside a closed part of the body when one of its vertices does (the
generalized winding number of the part's triangles around the point, |w| > 1/2). The closed parts
are found from the mesh alone: vertices welded (1e-7 m), triangles joined through shared
vertices, a part closed when every edge of its non-degenerate triangles has exactly two faces.

Depth: how far the robe goes into a closed part, the largest distance to the part's surface of
the robe's vertices and of its edges' quarter points that lie inside it (0 when none does).
Everything in float64; each body part is tested against the robe elements near it, vectorized.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from jaxrender.app.scenes.noh import exported_meshes, stage_motion
from jaxrender.app.scenes.noh.performer import performer_mesh, performer_rig
from sims import ClothState, costume_frames
from sims.costume import body_scale, dress_performer

WELD = 1e-7        # m: vertices closer than this are one (seams and poles of the body's parts)


def weld(vertices: np.ndarray, tol: float = WELD) -> np.ndarray:
    """Index of each vertex's welded representative (positions on a `tol` grid)."""
    key = np.round(np.asarray(vertices, np.float64) / tol).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)]


def edges_of(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E 2) of the triangles' corners."""
    t = np.asarray(triangles)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


def parts(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(part of each triangle, whether each part is closed): components of the welded mesh; a part
    is closed when every edge of its non-degenerate triangles is shared by exactly two of them."""
    w = weld(vertices)
    t = w[np.asarray(triangles)]
    n = len(vertices)
    rows = np.concatenate([t[:, 0], t[:, 1]])
    cols = np.concatenate([t[:, 1], t[:, 2]])
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    part = label[t[:, 0]]
    _, part = np.unique(part, return_inverse=True)
    good = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0])
    closed = np.ones(part.max() + 1, bool)
    e = np.sort(np.concatenate([t[good][:, [0, 1]], t[good][:, [1, 2]], t[good][:, [2, 0]]]), axis=1)
    owner = np.concatenate([part[good]] * 3)
    uniq, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    bad = counts[inverse.reshape(-1)] != 2
    closed[np.unique(owner[bad])] = False
    return part, closed


def _bucket(a: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """`a` padded with `fill` to a power of two rows (>= 64): few shapes, few compiles."""
    n = max(64, 1 << int(np.ceil(np.log2(max(len(a), 1)))))
    return np.concatenate([a, np.broadcast_to(fill, (n - len(a),) + a.shape[1:])])


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@jax.jit
def _crossings(seg: jnp.ndarray, tri: jnp.ndarray) -> jnp.ndarray:
    """(S T) whether segment seg[s] = p-q crosses triangle tri[t] = abc (interior or edges).
    Written by components: XLA's CPU backend is slow on sums over a minor axis of 3."""
    p = [seg[:, 0, k][:, None] for k in range(3)]
    d = [(seg[:, 1, k] - seg[:, 0, k])[:, None] for k in range(3)]
    a = [tri[:, 0, k][None] for k in range(3)]
    e1 = [(tri[:, 1, k] - tri[:, 0, k])[None] for k in range(3)]
    e2 = [(tri[:, 2, k] - tri[:, 0, k])[None] for k in range(3)]
    pv = _cross(d, e2)
    det = _dot(e1, pv)
    ok = jnp.abs(det) > 1e-18
    inv = 1.0 / jnp.where(ok, det, 1.0)
    tv = [p[k] - a[k] for k in range(3)]
    u = _dot(tv, pv) * inv
    qv = _cross(tv, e1)
    v = _dot(d, qv) * inv
    s = _dot(e2, qv) * inv
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)


@jax.jit
def _winding(points: jnp.ndarray, tri: jnp.ndarray) -> jnp.ndarray:
    """The winding number of the triangles around each point (Van Oosterom and Strackee's solid
    angle of each triangle, summed, / 4 pi; a degenerate triangle adds 0)."""
    a, b, c = ([tri[:, j, k][None] - points[:, k][:, None] for k in range(3)] for j in range(3))
    la, lb, lc = (jnp.sqrt(_dot(v, v)) for v in (a, b, c))
    num = _dot(a, _cross(b, c))
    den = la * lb * lc + _dot(a, b) * lc + _dot(a, c) * lb + _dot(b, c) * la
    return jnp.sum(2 * jnp.arctan2(num, den), axis=1) / (4 * jnp.pi)


def _segment_point_distance(p: np.ndarray, q: np.ndarray, x: np.ndarray) -> np.ndarray:
    d = q - p
    t = np.clip(np.sum((x - p) * d, -1) / np.maximum(np.sum(d * d, -1), 1e-300), 0, 1)
    return np.linalg.norm(p + t[..., None] * d - x, axis=-1)


def _point_triangle_distance(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N T) distance from each point to each triangle (to its plane where the foot lies inside
    it, else to its nearest edge)."""
    a, b, c = (tri[None, :, k] for k in range(3))
    p = x[:, None]
    n = np.cross(b - a, c - a)
    nn = np.maximum(np.sum(n * n, -1), 1e-300)
    h = np.sum((p - a) * n, -1) / nn
    foot = p - h[..., None] * n

    def left_of(u, v):
        return np.sum(np.cross(v - u, foot - u) * n, -1) >= 0

    inside = left_of(a, b) & left_of(b, c) & left_of(c, a)
    edge = np.minimum(np.minimum(_segment_point_distance(a, b, p), _segment_point_distance(b, c, p)),
                      _segment_point_distance(c, a, p))
    return np.where(inside, np.abs(h) * np.sqrt(nn), edge)


@dataclass
class Contact:
    """One frame's measure: robe triangles through or inside the body, and the depth (m)."""

    triangles: int
    depth: float
    crossing_edges: int
    inside_vertices: int
    by_part: np.ndarray      # robe triangles through each part of the body (one triangle can count for two)


class BodyShape:
    """The body's triangles of one frame prepared for `contact`: its parts (found once), each
    part's triangles padded to one size with degenerate ones, edges and bounding sphere."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, part: np.ndarray | None = None,
                 closed: np.ndarray | None = None):
        self.vertices = np.asarray(vertices, np.float64)
        self.triangles = np.asarray(triangles)
        if part is None:
            part, closed = parts(self.vertices, self.triangles)
        self.part, self.closed = part, closed
        size = int(np.bincount(part).max())
        self.tri, self.edges, self.sphere = [], [], []
        for k in range(len(closed)):
            t = self.triangles[part == k]
            corners = self.vertices[t]
            self.tri.append(np.concatenate([corners, np.zeros((size - len(t), 3, 3))]))
            self.edges.append(self.vertices[edges_of(t)])
            pts = corners.reshape(-1, 3)
            centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            self.sphere.append((centre, float(np.linalg.norm(pts - centre, axis=-1).max())))

    def moved(self, vertices: np.ndarray) -> BodyShape:
        """The same body (the same parts) at other vertex positions."""
        return BodyShape(vertices, self.triangles, self.part, self.closed)


def contact(robe_vertices: np.ndarray, robe_triangles: np.ndarray, body: BodyShape) -> Contact:
    """How the robe (its triangles) meets the body of the same frame (module docstring), in
    float64 whatever JAX's default. Each body part is tested only against the robe's edges,
    triangles and points that reach into its bounding sphere (the rest cannot touch it)."""
    with jax.enable_x64(True):
        return _contact(robe_vertices, robe_triangles, body)


def _contact(robe_vertices: np.ndarray, robe_triangles: np.ndarray, body: BodyShape) -> Contact:
    rv = np.asarray(robe_vertices, np.float64)
    rt = np.asarray(robe_triangles)
    n = len(rv)
    edges = edges_of(rt)
    p, q = rv[edges[:, 0]], rv[edges[:, 1]]
    tri = rv[rt]
    tri_c = tri.mean(axis=1)
    tri_r = np.linalg.norm(tri - tri_c[:, None], axis=-1).max(axis=1)
    s = np.asarray([0.25, 0.5, 0.75])
    samples = np.concatenate([rv, (p[:, None] * (1 - s[:, None]) + q[:, None] * s[:, None]).reshape(-1, 3)])
    edge_hit = np.zeros(len(edges), bool)
    inside = np.zeros(len(samples), bool)
    depth = 0.0
    zero_seg, zero_tri = np.zeros((2, 3)), np.zeros((3, 3))
    tri_keys = np.sort(np.stack([rt[:, [0, 1]], rt[:, [1, 2]], rt[:, [2, 0]]], 1), axis=-1)   # T 3 2
    tri_keys = tri_keys[..., 0] * n + tri_keys[..., 1]
    through = np.zeros((len(body.sphere), len(rt)), bool)     # part x robe triangle
    for k, (centre, radius) in enumerate(body.sphere):
        near = np.flatnonzero(_segment_point_distance(p, q, centre) <= radius)
        if near.size:
            hit = np.asarray(_crossings(_bucket(np.stack([p[near], q[near]], 1), zero_seg), body.tri[k]))
            crossing = near[hit[:len(near)].any(axis=1)]
            edge_hit[crossing] = True
            through[k] |= np.isin(tri_keys, edges[crossing, 0] * n + edges[crossing, 1]).any(axis=1)
        close = np.flatnonzero(np.linalg.norm(tri_c - centre, axis=-1) <= radius + tri_r)
        if close.size:
            hit = np.asarray(_crossings(_bucket(body.edges[k], zero_seg), _bucket(tri[close], zero_tri)))
            through[k, close] |= hit[:len(body.edges[k]), :len(close)].any(axis=0)
        if not body.closed[k]:
            continue
        there = np.flatnonzero(np.linalg.norm(samples - centre, axis=-1) <= radius)
        if there.size:
            w = np.asarray(_winding(_bucket(samples[there], centre), body.tri[k]))[:len(there)]
            deep = there[np.abs(w) > 0.5]
            inside[deep] = True
            through[k] |= np.isin(rt, deep[deep < n]).any(axis=1)
            if deep.size:
                dist = _point_triangle_distance(samples[deep], body.tri[k][np.any(body.tri[k] != 0, axis=(1, 2))])
                depth = max(depth, float(dist.min(axis=1).max()))
    return Contact(int(through.any(axis=0).sum()), depth, int(edge_hit.sum()), int(inside[:n].sum()),
                   through.sum(axis=1))


def dance_performer(bvh, *, duration: float):
    """The performer of `jaxrender noh` dancing `bvh` (placed on the stage, `duration` s long) in
    its robe (dressed and settled), as `noh_scene` makes it."""
    placed, joints = stage_motion(bvh, duration=duration)
    return performer_rig(dress_performer(placed, joints), placed, joints, body_scale(placed, joints))


def performer_frames(performer, frames: int, frame_dt: float = 0.1):
    """Each frame's (body, robe) `ExportedMesh` as `jaxrender noh --meshes` writes them (the robe
    simulated from its settled state, `frame_dt` s a frame, in the default precision)."""
    xs, _ = jax.jit(lambda c, m: costume_frames(c, m, frames=frames, frame_dt=frame_dt))(performer.costume,
                                                                                          performer.motion)
    step = round(frame_dt / performer.costume.dt) * performer.costume.dt
    yield from meshes_at(performer, (ClothState(xs[f], xs[f], jnp.asarray((f + 1) * step, xs.dtype))
                                     for f in range(frames)))


def meshes_at(performer, states):
    """The (body, robe) `ExportedMesh` of each of the robe's `states` (the body at its time)."""
    mesh_of = jax.jit(performer_mesh)
    for state in states:
        yield exported_meshes(mesh_of(performer, state), performer)
