"""The Noh stage (paper 004 section 4.1): the square hinoki floor raised above white gravel, its
four pillars and the rear ones, the roof on its beams, the back wall (kagami-ita) with its
painted pine and the side wall with bamboo, the bridge (hashigakari) with its railing and roof,
and the iron stands of the four bonfires (kagaribi); all as quads, ray cast once per sequence.

Dimensions, materials and what is precomputed (the stage and the camera stand still): docs/noh.md,
"The stage".
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.maths import default_float

__all__ = ["StageGeometry", "StageHits", "build_stage", "cast_stage", "stage_occluded", "basket_hides", "is_hidden",
           "hidden_length", "FIRE_SITES",
           "FLAME_SIZE", "FLAME_BASE", "BASKET", "MATERIALS"]

HALF = 2.95            # the main stage's half width (3 ken = 5.9 m)
BACK = -5.2            # the back wall (behind the musicians' area)
RAISE = 0.9            # the stage floor above the gravel
PILLAR = 0.12          # half side of a pillar
BEAM = 4.3             # underside of the ceiling
FIRE_SITES = ((-3.3, 4.0), (3.3, 4.0), (-4.4, 0.2), (4.4, 0.4))   # (x, z) of the kagaribi
FLAME_SIZE = (0.55, 0.8)                                          # width, height (m)
FLAME_BASE = 0.75                                                 # the baskets' rim above the stage floor
BASKET = (0.2, 0.25)                                              # a basket's half side and depth below its rim (m)
MATERIALS = ("floor", "pillar", "pine_wall", "dark_wood", "roof", "gravel", "skirt", "bamboo_wall", "iron",
             "rail")


class StageGeometry(eqx.Module):
    """Quads: centre, half-extent vectors u, v (orthogonal), material (index into MATERIALS),
    whether they shadow the sky (`occluder`) and whether they are polished (`coat`)."""

    center: Float[Array, "Q 3"]
    u: Float[Array, "Q 3"]
    v: Float[Array, "Q 3"]
    material: Int[Array, " Q"]
    occluder: tuple[bool, ...] = eqx.field(static=True)


class StageHits(eqx.Module):
    """Per ray: distance (inf: sky), point, normal facing the ray, material, albedo, polish."""

    t: Float[Array, " N"]
    position: Float[Array, "N 3"]
    normal: Float[Array, "N 3"]
    material: Int[Array, " N"]
    rho_d: Float[Array, "N 3"]
    coat: Float[Array, " N"]


def _box(quads: list, lo, hi, material: str, faces: str = "xXyYzZ", occluder: bool = True) -> None:
    """The faces (x: the -x face, X: the +x face, ...) of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    e = np.eye(3)
    for f in faces:
        k = "xyz".index(f.lower())
        sign = 1.0 if f.isupper() else -1.0
        a, b = [i for i in range(3) if i != k]
        quads.append((c + sign * h[k] * e[k], h[a] * e[a], h[b] * e[b], material, occluder))


def build_stage() -> StageGeometry:
    """The stage's quads (module docstring; docs/noh.md)."""
    q: list = []
    mid = (HALF + BACK) / 2
    depth = (HALF - BACK) / 2
    q.append(((0, 0, mid), (HALF, 0, 0), (0, 0, depth), "floor", True))
    _box(q, (-HALF, -RAISE, BACK), (HALF, 0, HALF), "skirt", "xXZ")
    q.append(((0, -RAISE, 0), (40, 0, 0), (0, 0, 40), "gravel", False))
    for x in (-HALF + PILLAR, HALF - PILLAR):
        for z in (HALF - PILLAR, -HALF + PILLAR, BACK + PILLAR):
            _box(q, (x - PILLAR, 0, z - PILLAR), (x + PILLAR, BEAM, z + PILLAR), "pillar", "xXzZ")
    q.append(((0, 1.95, BACK), (HALF, 0, 0), (0, 1.95, 0), "pine_wall", True))
    q.append(((HALF, 1.95, (BACK - HALF) / 2), (0, 0, (-HALF - BACK) / 2), (0, 1.95, 0), "bamboo_wall", True))
    _box(q, (-HALF, 3.9, BACK), (HALF, BEAM, BACK + 0.2), "dark_wood", "zy")
    _box(q, (-HALF - 0.05, 3.95, HALF - 0.25), (HALF + 0.05, BEAM, HALF), "dark_wood", "Zy")
    for x0, x1 in ((-HALF, -HALF + 0.25), (HALF - 0.25, HALF)):
        _box(q, (x0, 3.95, BACK), (x1, BEAM, HALF), "dark_wood", "xXy")
    q.append(((0, BEAM, mid), (HALF, 0, 0), (0, 0, depth), "dark_wood", True))          # the ceiling
    eave, ridge = np.array([HALF + 1.3, 4.45, HALF + 1.2]), np.array([0.0, 7.2, mid])
    for zsign in (1.0, -1.0):
        z_eave = mid + zsign * (depth + 1.2)
        a, b = np.array([0, eave[1], z_eave]), np.array([0, ridge[1], ridge[2]])
        q.append(((a + b) / 2, (eave[0], 0, 0), (b - a) / 2, "roof", True))
        q.append(((0, eave[1] - 0.12, z_eave), (eave[0], 0, 0), (0, 0.12, 0), "rail", True))   # the fascia
    # the bridge (hashigakari): from the back-left corner, going left and back
    start = np.array([-HALF, 0.0, BACK + 1.3])
    d = np.array([-1.0, 0.0, -0.32])
    d /= np.linalg.norm(d)
    side = np.cross([0.0, 1.0, 0.0], d)             # toward the audience
    length, half_w = 13.0, 0.9
    centre = start + d * length / 2
    q.append((centre, d * length / 2, side * half_w, "floor", True))
    q.append((centre + side * half_w - np.array([0, RAISE / 2, 0]), d * length / 2, (0, RAISE / 2, 0), "skirt", True))
    for off, height in ((half_w, 0.75), (-half_w, 0.75)):
        rail = centre + side * off + np.array([0, height, 0])
        q.append((rail, d * length / 2, (0, 0.04, 0), "rail", True))
        q.append((rail + np.array([0, 0.04, 0]), d * length / 2, side * 0.04, "rail", True))
    q.append((centre - side * (half_w + 0.05) + np.array([0, 1.4, 0]), d * length / 2, (0, 1.4, 0), "dark_wood", True))
    for k in range(6):
        post = start + d * (0.6 + 2.4 * k) + side * half_w
        q.append((post + np.array([0, 1.6, 0]), side * 0.06, (0, 1.6, 0), "pillar", True))
    roof_c = centre + np.array([0, 3.35, 0]) - side * 0.1
    q.append((roof_c, d * length / 2, side * (half_w + 0.5) + np.array([0, 0.25, 0]), "dark_wood", True))
    # the bonfires' iron stands: three legs and a basket
    for x, z in FIRE_SITES:
        base = np.array([x, -RAISE, z])
        top = FLAME_BASE
        for k in range(3):
            ang = 2 * np.pi * k / 3
            foot = base + 0.35 * np.array([np.cos(ang), 0, np.sin(ang)])
            head = np.array([x, top - 0.25, z]) + 0.12 * np.array([np.cos(ang), 0, np.sin(ang)])
            along = (head - foot) / 2
            width = np.cross(along, [0.0, 0.0, 1.0] if abs(np.sin(ang)) < 0.7 else [1.0, 0.0, 0.0])
            width = 0.025 * width / np.linalg.norm(width)
            q.append(((foot + head) / 2, along, width, "iron", False))
        half, depth = BASKET
        _box(q, (x - half, top - depth, z - half), (x + half, top, z + half), "iron", "xXzZ", occluder=False)
    dtype = default_float()
    return StageGeometry(jnp.asarray(np.asarray([e[0] for e in q], float), dtype),
                         jnp.asarray(np.asarray([e[1] for e in q], float), dtype),
                         jnp.asarray(np.asarray([e[2] for e in q], float), dtype),
                         jnp.asarray([MATERIALS.index(e[3]) for e in q], jnp.int32), tuple(bool(e[4]) for e in q))


def _plane_hits(stage: StageGeometry, o: Array, d: Array) -> tuple[Array, Array, Array]:
    """(t, a, b) of every ray (N 3) against every quad's plane (N Q; t = inf outside the quad).
    Written out by components: XLA's CPU backend is slow on sums over a minor axis of 3."""
    n = jnp.cross(stage.u, stage.v)
    row = lambda m, k: m[:, k][None, :]  # noqa: E731
    col = lambda m, k: m[:, k][:, None]  # noqa: E731
    denom = sum(col(d, k) * row(n, k) for k in range(3))
    ok = jnp.abs(denom) > 1e-12
    t = sum((row(stage.center, k) - col(o, k)) * row(n, k) for k in range(3)) / jnp.where(ok, denom, 1.0)
    p = [col(o, k) + t * col(d, k) - row(stage.center, k) for k in range(3)]
    uu = jnp.sum(stage.u * stage.u, -1)[None, :]
    vv = jnp.sum(stage.v * stage.v, -1)[None, :]
    a = sum(p[k] * row(stage.u, k) for k in range(3)) / uu
    b = sum(p[k] * row(stage.v, k) for k in range(3)) / vv
    inside = ok & (t > 1e-4) & (jnp.abs(a) <= 1) & (jnp.abs(b) <= 1)
    return jnp.where(inside, t, jnp.inf), a, b


def _hits(stage: StageGeometry, o: Array, d: Array) -> tuple[Array, Array, Array, Array]:
    """(t, quad, a, b) of the nearest quad along each ray (N 3 origins and directions)."""
    t, a, b = _plane_hits(stage, o, d)
    k = jnp.argmin(t, axis=1)
    take = lambda x: jnp.take_along_axis(x, k[:, None], axis=1)[:, 0]  # noqa: E731
    return take(t), k.astype(jnp.int32), take(a), take(b)


def _chunked(fn, *arrays, chunk: int = 8192):
    """`fn` over the leading axis in chunks (bounded memory: rays x quads per chunk)."""
    n = arrays[0].shape[0]
    pad = (-n) % chunk
    padded = [jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a for a in arrays]
    shaped = [a.reshape((-1, chunk) + a.shape[1:]) for a in padded]
    out = jax.lax.map(lambda xs: fn(*xs), tuple(shaped))
    return jax.tree_util.tree_map(lambda r: r.reshape((-1,) + r.shape[2:])[:n], out)


def cast_stage(stage: StageGeometry, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"]) -> StageHits:
    """The stage seen along each ray: nearest quad, its point, normal (toward the ray's origin),
    material, albedo (`stage_albedo`) and polish (1 on the hinoki floors)."""
    t, k, a, b = _chunked(lambda o, d: _hits(stage, o, d), origins, directions)
    hit = jnp.isfinite(t)
    pos = origins + jnp.where(hit, t, 0.0)[:, None] * directions
    n = jnp.cross(stage.u, stage.v)[k]
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    n = jnp.where((jnp.sum(n * directions, -1) > 0)[:, None], -n, n)
    mat = stage.material[k]
    la = a * jnp.linalg.norm(stage.u, axis=-1)[k]
    lb = b * jnp.linalg.norm(stage.v, axis=-1)[k]
    rho = stage_albedo(mat, la, lb, pos)
    coat = (hit & (mat == MATERIALS.index("floor"))).astype(t.dtype)
    return StageHits(t, pos, n, jnp.where(hit, mat, -1), jnp.where(hit[:, None], rho, 0.0), coat)


def stage_occluded(stage: StageGeometry, origins: Float[Array, "N 3"], directions: Float[Array, "N 3"],
                   max_t: Float[Array, " N"], *, occluders_only: bool = False) -> Float[Array, " N"]:
    """1 where a quad (only those that shadow the sky, if `occluders_only`) lies along the ray
    before `max_t`, else 0."""
    if occluders_only:
        keep = np.flatnonzero(np.asarray(stage.occluder))
        stage = StageGeometry(stage.center[keep], stage.u[keep], stage.v[keep], stage.material[keep],
                              tuple(stage.occluder[i] for i in keep))
    hit = _chunked(lambda o, d, m: jnp.any(_plane_hits(stage, o, d)[0] < m[:, None], axis=1), origins, directions,
                   max_t)
    return hit.astype(origins.dtype)


def basket_hides(points: Float[Array, "N 3"], targets: Float[Array, "M 3"], fire_xz: Float[Array, "M 2"]
                 ) -> tuple[Float[Array, "N M 4"], Float[Array, "N M 4"]]:
    """(lo, hi), N x M x 4: for each of the four vertical sides of the basket (`BASKET`, its rim at
    `FLAME_BASE`) of the fire at `fire_xz`, the heights h for which it hides the point (x, h, z)
    of target m's vertical line from point n (none where lo > hi). Exact: the segment from a
    point to (x, h, z) crosses a side's plane at a fraction lambda of its length that does not
    depend on h (the plane is vertical), at the height p_y + lambda (h - p_y); the side hides the
    h that put that height between the basket's bottom and its rim. The basket is open at the top
    and the bottom, so a segment can pass under it, through it and out over the rim: the sides'
    intervals need not touch (`hidden_length`, `is_hidden`; docs/noh.md, "The stage")."""
    half, depth = BASKET
    p = [points[:, k][:, None] for k in range(3)]
    f = [targets[:, k][None] for k in range(3)]
    centre = {0: fire_xz[:, 0][None], 2: fire_xz[:, 1][None]}
    lo, hi = [], []
    for axis, other in ((0, 2), (2, 0)):
        for sign in (-1.0, 1.0):
            plane = centre[axis] + sign * half
            step = f[axis] - p[axis]
            lam = (plane - p[axis]) / jnp.where(jnp.abs(step) > 1e-12, step, 1e-12)
            across = p[other] + lam * (f[other] - p[other])
            ok = (lam > 0) & (lam < 1) & (jnp.abs(across - centre[other]) <= half)
            safe = jnp.where(ok, lam, 1.0)
            lo.append(jnp.where(ok, p[1] + (FLAME_BASE - depth - p[1]) / safe, jnp.inf))
            hi.append(jnp.where(ok, p[1] + (FLAME_BASE - p[1]) / safe, -jnp.inf))
    return jnp.stack(lo, -1), jnp.stack(hi, -1)


def is_hidden(lo: Array, hi: Array, h: Array) -> Array:
    """Whether height h lies in one of the sides' intervals (`basket_hides`; the last axis)."""
    return jnp.any((h[..., None] >= lo) & (h[..., None] <= hi), axis=-1)


def hidden_length(lo: Array, hi: Array, bottom: Array, top: Array) -> Array:
    """The length of [bottom, top] inside the union of the sides' intervals (`basket_hides`; the
    last axis): the sum of each one's part less the pairs' common parts (a segment crosses at most
    two sides of the square basket: exact)."""
    def part(a, b, low, high):
        return jnp.clip(jnp.minimum(b, high) - jnp.maximum(a, low), 0.0, None)

    total = jnp.sum(part(lo, hi, bottom[..., None], top[..., None]), axis=-1)
    for i in range(4):
        for j in range(i + 1, 4):
            total = total - part(jnp.maximum(lo[..., i], lo[..., j]), jnp.minimum(hi[..., i], hi[..., j]), bottom, top)
    return total


def _noise(x: Array, y: Array, seed: float) -> Array:
    """A cheap smooth value in [-1, 1] from sines (grain, stains, needles)."""
    return (jnp.sin(x * 1.7 + seed) * jnp.sin(y * 2.3 - 0.7 * seed) + 0.5 * jnp.sin(x * 4.1 - y * 3.7 + seed)) / 1.5


def stage_albedo(material: Int[Array, " N"], a: Float[Array, " N"], b: Float[Array, " N"],
                 pos: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    """rho_d (linear RGB) of each hit by its material, from the quad-local coordinates (a, b in
    metres along u, v) and the world point: planked hinoki, weathered pillars, the painted pine
    on pale boards, dark beams, cypress-bark roof, white gravel, the bamboo wall, iron, rails."""
    x, y, z = pos[:, 0], pos[:, 1], pos[:, 2]
    ones = jnp.ones_like(x)
    rgb = lambda r, g, bl: jnp.stack([r * ones, g * ones, bl * ones], -1)  # noqa: E731
    plank = jnp.floor(x / 0.3)
    grain = 0.85 + 0.15 * jnp.sin(z * 7.0 + plank * 1.7 + 2.0 * jnp.sin(z * 1.3 + plank))
    seam = jnp.clip(jnp.abs(x / 0.3 - jnp.round(x / 0.3)) * 40, 0.3, 1.0)
    tone = 0.8 + 0.2 * jnp.sin(plank * 12.9898) ** 2
    floor = rgb(0.36, 0.23, 0.12) * (grain * seam * tone)[:, None]
    pillar = rgb(0.30, 0.20, 0.11) * (0.85 + 0.15 * jnp.sin(b * 9.0 + 3 * jnp.sin(a * 20)))[:, None]
    # the kagami-ita: pale vertical boards; an old pine, its trunk leaning in from the left, and
    # clouds of needles along its branches
    board = jnp.clip(jnp.abs(x / 0.35 - jnp.round(x / 0.35)) * 30, 0.5, 1.0)
    wall = rgb(0.46, 0.37, 0.24) * (board * (0.92 + 0.08 * _noise(x * 3, y * 0.5, 1.0)))[:, None]
    trunk_x = -0.9 + 0.5 * jnp.sin(y * 0.9) - 0.25 * y
    trunk = jnp.abs(x - trunk_x) < 0.22 - 0.03 * y
    branch = (jnp.abs(y - (2.35 + 0.25 * jnp.sin(x * 1.3))) < 0.07) & (x > trunk_x) & (x < 2.0)
    branch |= (jnp.abs(y - (1.55 - 0.15 * (x + 0.5))) < 0.05) & (x > trunk_x) & (x < 1.2)
    needles = jnp.zeros_like(x, dtype=bool)
    for cx, cy, rx, ry in ((-0.6, 3.05, 1.2, 0.42), (0.9, 2.6, 1.0, 0.36), (1.9, 2.2, 0.8, 0.32),
                           (-1.8, 2.2, 0.7, 0.3), (0.6, 1.75, 0.75, 0.28), (-0.2, 2.35, 0.6, 0.25)):
        r = ((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 + 0.25 * _noise(x * 9, y * 9, cx)
        needles |= r < 1.0
    pine = jnp.where(needles[:, None], rgb(0.05, 0.14, 0.05) * (0.8 + 0.2 * _noise(x * 30, y * 30, 2.0))[:, None],
                     jnp.where((trunk | branch)[:, None], rgb(0.13, 0.08, 0.05), wall))
    dark = rgb(0.10, 0.065, 0.04) * (0.9 + 0.1 * _noise(a * 5, b * 5, 3.0))[:, None]
    roof = rgb(0.09, 0.07, 0.06) * (0.8 + 0.2 * jnp.abs(jnp.sin(b * 40)))[:, None]
    gravel = rgb(0.55, 0.54, 0.50) * (0.85 + 0.15 * _noise(x * 23, z * 29, 4.0))[:, None]
    skirt = rgb(0.07, 0.05, 0.04)
    stalk = (jnp.abs(jnp.sin(z * 2.2 + 0.4)) < 0.12) & (jnp.sin(y * 3.0 + z) < 0.93)
    bamboo = jnp.where(stalk[:, None], rgb(0.10, 0.20, 0.07), wall)
    iron, rail = rgb(0.03, 0.03, 0.03), rgb(0.26, 0.17, 0.09)
    table = jnp.stack([floor, pillar, pine, dark, roof, gravel, skirt, bamboo, iron, rail])   # M N 3
    return jnp.take_along_axis(table, jnp.clip(material, 0, len(MATERIALS) - 1)[None, :, None], axis=0)[0]
