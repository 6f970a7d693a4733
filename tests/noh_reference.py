"""A brute-force float64 reference of the composed Takigi Noh frame (shared by
tests/test_noh_bruteforce.py and benchmarks/noh_reference.py).

From the frame's scene state (the stage's quads, the performer's mesh at the frame, the flames'
emission that frame, the sky, the camera) and the light samples the frame drew (the sky's K
directions and the fires' K points), every pixel is found by casting rays against every triangle:
the stage's quads (two triangles each) and the performer's. No shadow map, PCSS, raster window,
capacity or precomputed term:
- primary rays through the pixel centres (`Camera.ray_direction`), the nearest triangle wins; the
  flames' quads, which do not occlude, add their emission (bilinear) where a ray meets them
  before the surface;
- a stage point (albedo `stage_albedo` at its quad's own coordinates) is lit by the sky's K
  samples, each cast for its visibility, and by each fire: its flame quad cut into
  `FIRE_ROWS` rows of equal emitted power (thin where the flame is bright) x `FIRE_COLUMNS`
  columns, each cell's exact mean emission times the point's cosine over r^2 times the cell's
  area (the flame a billboard, as in the scene: no cosine at the flame), each cell's centre
  cast for its visibility;
- a performer point (barycentric normal, tangent along u, two-sided, its label and colour from
  the atlas, uv derivatives where the rays through the neighbouring pixel centres meet its
  triangle's plane) is shaded by `jaxrender.fabric.shade_fabric` (the toolkit's one BTF
  evaluation) under the frame's K sky and K fire samples, each sample cast for its visibility;
- a polished floor point (Fresnel: Schlick, F0 = `STAGE_F0`) adds the radiance of `GLOSS` x
  `GLOSS` mirrored rays spread over a square cone `roughness` radians wide (the floor's
  roughness), each traced as a primary ray (stage, performer at its nearest mip level, flames,
  sky; no second reflection); its diffuse part is weighted by 1 - F.

What may differ: the frame's soft shadows are PCSS (the performer's, at its points and, at half
resolution, on the stage) and single rays toward each flame's centre (the stage's own), neither
an area light's penumbra nor its edge. `may_differ` marks the pixels where more than a given
share of the luminance comes from fires seen in part (some of the flame's cells hidden by the
performer or the stage, some not) or at a shadow's edge (a neighbouring pixel sees the fire
differently), within a given radius, at the points a pixel shows directly or mirrored. The
baskets are left out of that: the frame takes the part of a flame its own basket hides exactly
(`stage.basket_hides`), so that must match.

Fast without approximating: the triangles are grouped in bounding boxes, two levels (`GROUP`,
`CLUSTER`); each ray is tested against the triangles of the boxes its segment enters (slab
tests first), as (ray, cluster) pairs in one vectorized pass, padded to powers of two.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.app.scenes.noh import default_btfs, noh_scene
from jaxrender.app.scenes.noh.mask import LABELS, TAKES_COLOUR
from jaxrender.app.scenes.noh.motion import STAGE_F0, grown, noh_frame_jit
from jaxrender.app.scenes.noh.performer import performer_mesh
from jaxrender.app.scenes.noh.rig import STAGE_ROUGHNESS, prepare_rig
from jaxrender.app.scenes.noh.stage import BASKET, FLAME_BASE, MATERIALS, stage_albedo
from jaxrender.fabric import fresnel_schlick, shade_fabric
from jaxrender.io import BVHMotion, read_bvh
from jaxrender.lights import env_radiance, sample_envmap, sample_quad_lights
from jaxrender.textures import bilinear
from sims import costume_frames, noh_dance

FIRE_ROWS, FIRE_COLUMNS = 64, 8   # cells over each flame: rows of equal emitted power x columns
FIRE_BLOCKS = (8, 2)              # ... grouped in blocks: the shadows of all but its basket, per block
GLOSS = 2              # mirrored rays per floor pixel: GLOSS x GLOSS over the roughness cone
EPS = 1e-6             # m: secondary rays start this far along the normal
GROUP, CLUSTER = 512, 32   # triangles per bounding box: groups of clusters
_LUM = np.asarray([0.2126, 0.7152, 0.0722])

_shade = eqx.filter_jit(shade_fabric)
_albedo = jax.jit(stage_albedo)
_sky = jax.jit(lambda env, d: env_radiance(env, d, filter="mitsuba"))
_bilinear = jax.jit(lambda tex, uv: bilinear(tex, uv, wrap="clamp"))


# ------------------------------------------------------------------------------ ray casting

def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _moller(o, d, tri):
    """Rays (P 3) against their own triangles (P S 3 3): t, barycentrics b1, b2 and whether the ray
    meets the triangle (Moller-Trumbore), by components (XLA's CPU backend is slow on minor axes
    of 3)."""
    oc = [o[:, k][:, None] for k in range(3)]
    dc = [d[:, k][:, None] for k in range(3)]
    a = [tri[:, :, 0, k] for k in range(3)]
    e1 = [tri[:, :, 1, k] - tri[:, :, 0, k] for k in range(3)]
    e2 = [tri[:, :, 2, k] - tri[:, :, 0, k] for k in range(3)]
    pv = _cross(dc, e2)
    det = _dot(e1, pv)
    ok = jnp.abs(det) > 1e-14
    inv = 1.0 / jnp.where(ok, det, 1.0)
    tv = [oc[k] - a[k] for k in range(3)]
    b1 = _dot(tv, pv) * inv
    qv = _cross(tv, e1)
    b2 = _dot(dc, qv) * inv
    t = _dot(e2, qv) * inv
    return t, b1, b2, ok & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t > 0)


_PAIRS = 4096


def _over_pairs(fn, *arrays):
    """`fn` over chunks of `_PAIRS` pairs (a multiple of it, by `_bucket`)."""
    shaped = [a.reshape((-1, _PAIRS) + a.shape[1:]) for a in arrays]
    out = jax.lax.map(lambda xs: fn(*xs), tuple(shaped))
    return jax.tree_util.tree_map(lambda r: r.reshape((-1,) + r.shape[2:]), out)


@jax.jit
def _nearest_pairs(o, d, tmax, cluster, packed):
    def one(o, d, tmax, cluster):
        t, b1, b2, hit = _moller(o, d, packed[cluster])
        t = jnp.where(hit & (t < tmax[:, None]), t, jnp.inf)
        k = jnp.argmin(t, axis=1)
        take = lambda a: jnp.take_along_axis(a, k[:, None], axis=1)[:, 0]  # noqa: E731
        return take(t), k, take(b1), take(b2)
    return _over_pairs(one, o, d, tmax, cluster)


@jax.jit
def _blocked_pairs(o, d, tmax, cluster, packed):
    def one(o, d, tmax, cluster):
        t, _, _, hit = _moller(o, d, packed[cluster])
        return jnp.any(hit & (t < tmax[:, None]), axis=1)
    return _over_pairs(one, o, d, tmax, cluster)


@jax.jit
def _boxes(o, d, tmax, lo, hi):
    """(R C) whether each ray's segment [0, tmax] enters each box (slab test)."""
    t0 = jnp.zeros((o.shape[0], lo.shape[0]), o.dtype)
    t1 = jnp.broadcast_to(tmax[:, None], t0.shape)
    for k in range(3):
        inv = 1.0 / jnp.where(jnp.abs(d[:, k]) > 1e-300, d[:, k], 1e-300)[:, None]
        a = (lo[:, k][None] - o[:, k][:, None]) * inv
        b = (hi[:, k][None] - o[:, k][:, None]) * inv
        t0 = jnp.maximum(t0, jnp.minimum(a, b))
        t1 = jnp.minimum(t1, jnp.maximum(a, b))
    return t0 <= t1


@jax.jit
def _irradiance(p, n, centres, emission, area, clear):
    """(N Q 3) each fire's irradiance at the points from its cells (cosine over r^2 x area x mean
    emission), where seen and unshadowed (chunks of 256 points)."""
    def chunk(args):
        p, n, clear = args
        d = centres[None] - p[:, None, None]
        g = jnp.maximum(jnp.einsum("nqmc,nc->nqm", d, n), 0.0) / jnp.sum(d * d, -1) ** 1.5 * area[None]
        return jnp.einsum("nqm,qmc->nqc", g * clear.astype(g.dtype), emission), jnp.einsum("nqm,qmc->nqc", g, emission)
    k = p.shape[0]
    pad = (-k) % 256
    grow = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], pad, axis=0)]).reshape((-1, 256) + a.shape[1:])  # noqa: E731
    lit, unlit = jax.lax.map(chunk, (grow(p), grow(n), grow(clear)))
    return lit.reshape((-1,) + lit.shape[2:])[:k], unlit.reshape((-1,) + unlit.shape[2:])[:k]


@jax.jit
def _clear_of(points, targets, baskets):
    """(N Q M) whether the segment from each point to each target of fire q (Q M 3) misses the
    triangles of fire q (Q T 3 3): dense, for a few triangles (a fire's own basket)."""
    def per_fire(tgt, tri):
        def chunk(p):
            o = jnp.repeat(p, tgt.shape[0], axis=0)
            to = jnp.tile(tgt, (p.shape[0], 1)) - o
            t, _, _, hit = _moller(o, to, jnp.broadcast_to(tri, (o.shape[0],) + tri.shape))
            return ~jnp.any(hit & (t < 1 - 1e-9), axis=1).reshape(p.shape[0], tgt.shape[0])
        n = points.shape[0]
        pad = (-n) % 64
        padded = jnp.concatenate([points, jnp.repeat(points[:1], pad, axis=0)]).reshape(-1, 64, 3)
        return jax.lax.map(chunk, padded).reshape(-1, tgt.shape[0])[:n]
    return jnp.stack([per_fire(targets[f], baskets[f]) for f in range(targets.shape[0])], 1)


def _bucket(n: int) -> int:
    return max(_PAIRS, 1 << int(np.ceil(np.log2(max(n, 1)))))


def _padded(a: np.ndarray, n: int, fill=0) -> np.ndarray:
    return np.concatenate([a, np.broadcast_to(np.asarray(fill, a.dtype), (n - len(a),) + a.shape[1:])])


def _split(tri: np.ndarray, idx: np.ndarray, size: int) -> list[np.ndarray]:
    """Groups of at most `size` of the triangles `idx`: split at the median of their centroids
    along the longest side of each group's extent (a k-d split)."""
    centre = tri.mean(axis=1)
    out, todo = [], [idx]
    while todo:
        idx = todo.pop()
        if len(idx) <= size:
            out.append(idx)
            continue
        c = centre[idx]
        order = idx[np.argsort(c[:, int(np.argmax(np.ptp(c, axis=0)))], kind="stable")]
        todo += [order[:len(order) // 2], order[len(order) // 2:]]
    return out


def _box_of(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = tri.reshape(-1, 3)
    return corners.min(axis=0) - 1e-9, corners.max(axis=0) + 1e-9


class Triangles:
    """Triangles (T 3 3) in a two-level hierarchy of bounding boxes (groups of at most `GROUP`,
    then clusters of at most `CLUSTER`), for nearest hits and shadow rays."""

    def __init__(self, tri: np.ndarray):
        tri = np.asarray(tri, np.float64)
        self.groups = []                 # (box lo, box hi, clusters' lo, hi, first cluster)
        clusters = []
        for g in _split(tri, np.arange(len(tri)), GROUP):
            leaves = _split(tri, g, CLUSTER)
            boxes = [_box_of(tri[c]) for c in leaves]
            self.groups.append((*_box_of(tri[g]), jnp.asarray(np.stack([b[0] for b in boxes])),
                                jnp.asarray(np.stack([b[1] for b in boxes])), len(clusters)))
            clusters += leaves
        self.top_lo = jnp.asarray(np.stack([g[0] for g in self.groups]))
        self.top_hi = jnp.asarray(np.stack([g[1] for g in self.groups]))
        self.packed = jnp.asarray(np.stack([_padded(tri[c], CLUSTER, 0.0) for c in clusters]))   # degenerate pads
        self.index = np.stack([_padded(c, CLUSTER, -1) for c in clusters])

    @staticmethod
    def _enter(o, d, tmax, lo, hi) -> np.ndarray:
        m = max(256, 1 << int(np.ceil(np.log2(max(len(o), 1)))))
        return np.asarray(_boxes(jnp.asarray(_padded(o, m)), jnp.asarray(_padded(d, m, 1.0)),
                                 jnp.asarray(_padded(tmax, m)), lo, hi))[:len(o)]

    def _pairs(self, o, d, tmax):
        """(ray, cluster) for every cluster box a ray's segment enters (through its group's box)."""
        rays, clusters = [], []
        top = self._enter(o, d, tmax, self.top_lo, self.top_hi)
        for g, (_, _, lo, hi, first) in enumerate(self.groups):
            r = np.flatnonzero(top[:, g])
            if r.size:
                rr, cc = np.nonzero(self._enter(o[r], d[r], tmax[r], lo, hi))
                rays.append(r[rr])
                clusters.append(cc + first)
        if not rays:
            return np.zeros(0, int), np.zeros(0, int)
        return np.concatenate(rays), np.concatenate(clusters)

    def _run(self, kernel, o, d, tmax, rays, clusters):
        m = _bucket(len(rays))
        return [np.asarray(a)[:len(rays)] for a in jax.tree_util.tree_leaves(kernel(
            jnp.asarray(_padded(o[rays], m)), jnp.asarray(_padded(d[rays], m, 1.0)),
            jnp.asarray(_padded(tmax[rays], m)), jnp.asarray(_padded(clusters, m)), self.packed))]

    def nearest(self, o: np.ndarray, d: np.ndarray):
        """(t, triangle, b1, b2) of the nearest triangle along each ray (inf, -1 where none)."""
        tmax = np.full(len(o), np.inf)
        t_best, k_best, b_best = np.full(len(o), np.inf), np.full(len(o), -1), np.zeros((len(o), 2))
        rays, clusters = self._pairs(o, d, tmax)
        if len(rays):
            t, k, b1, b2 = self._run(_nearest_pairs, o, d, tmax, rays, clusters)
            order = np.lexsort((t, rays))
            first = order[np.r_[True, rays[order][1:] != rays[order][:-1]]]
            hit = np.isfinite(t[first])
            r = rays[first][hit]
            t_best[r], k_best[r] = t[first][hit], self.index[clusters[first][hit], k[first][hit]]
            b_best[r] = np.stack([b1[first][hit], b2[first][hit]], -1)
        return t_best, k_best, b_best[:, 0], b_best[:, 1]

    def blocked(self, o: np.ndarray, d: np.ndarray, tmax: np.ndarray, batch: int = 1 << 16) -> np.ndarray:
        """Whether a triangle lies along each ray before `tmax`."""
        out = np.zeros(len(o), bool)
        for s in range(0, len(o), batch):
            sl = slice(s, min(s + batch, len(o)))
            rays, clusters = self._pairs(o[sl], d[sl], tmax[sl])
            if len(rays):
                (hit,) = self._run(_blocked_pairs, o[sl], d[sl], tmax[sl], rays, clusters)
                out[s + rays[hit]] = True
        return out


# ------------------------------------------------------------------------------ the frame

@dataclass
class Frame:
    """What the reference needs of a frame, as numpy float64: the performer's mesh, the flames'
    emission, the sky's K samples (direction; radiance / (K pdf), 0 below the horizon) and the
    fires' K samples (position, radiance, area pdf, which fire)."""

    vertices: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    emission: np.ndarray
    env_direction: np.ndarray
    env_weight: np.ndarray
    fire_position: np.ndarray
    fire_radiance: np.ndarray
    fire_pdf: np.ndarray
    fire_light: np.ndarray


def frame_inputs(scene, state, emission, *, fire_key, env_key, k_fire: int = 20, k_env: int = 20) -> Frame:
    """The `Frame` of the production frame that left the robe in `state`, lit by `emission`, with
    the sky samples `prepare_rig(key=env_key)` drew and the fire samples `noh_frame(key=fire_key)`
    drew."""
    mesh = eqx.filter_jit(performer_mesh)(scene.performer, state)
    fires = sample_quad_lights(eqx.tree_at(lambda f: f.emission, scene.fires, emission), fire_key, k_fire)
    env = sample_envmap(scene.env, env_key, k_env)
    up = (np.asarray(env.direction)[:, 1] > 0) / (k_env * np.asarray(env.pdf, np.float64))
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    return Frame(f64(mesh.vertices), f64(mesh.normals), f64(mesh.uv), np.asarray(mesh.triangles), f64(emission),
                 f64(env.direction), f64(env.radiance) * up[:, None], f64(fires.position), f64(fires.radiance),
                 f64(fires.pdf_area), np.asarray(fires.light))


@dataclass
class Reference:
    """The reference image and, per pixel and fire, the luminance the fire would give it
    unshadowed and the fire's state (0: no cell of the flame seen, 1: all, 2: some, baskets aside,
    or a shadow terminator; -1: no surface) at the point the pixel shows (`direct_*`) and at the
    points its mirrored rays show (`mirror_*`, the luminance weighted by F; the state 2 also
    where they disagree)."""

    image: np.ndarray        # H W 3 linear radiance
    direct_lum: np.ndarray   # H W Q
    direct_state: np.ndarray
    direct_surface: np.ndarray  # H W: the stage quad shown, -2 the performer, -1 none
    mirror_lum: np.ndarray
    mirror_state: np.ndarray
    mirror_surface: np.ndarray  # ... mirrored (-3: the mirrored rays meet several)
    mirror_total: np.ndarray    # H W: the luminance the floor's reflection adds (F x the mirrored rays' mean)
    performer: np.ndarray    # H W: pixels showing the performer
    mirrored_performer: np.ndarray  # H W: floor pixels some of whose mirrored rays meet the performer
    flames: np.ndarray       # H W: pixels a flame adds light to
    mirrored_flames: np.ndarray     # H W: floor pixels some of whose mirrored rays meet a flame
    floor: np.ndarray        # H W: polished pixels


def _grow(mask: np.ndarray, radius: int) -> np.ndarray:
    """`mask` (H W ...) dilated by a square of `radius` pixels."""
    h, w = mask.shape[:2]
    pad = np.pad(mask, ((radius, radius), (radius, radius)) + ((0, 0),) * (mask.ndim - 2))
    out = np.zeros_like(mask)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            out |= pad[dy:dy + h, dx:dx + w]
    return out


def may_differ(ref: Reference, *, radius: int, share: float, glow: int) -> np.ndarray:
    """H W: the pixels where the frame may differ from the reference (module docstring): those
    where the fires seen in part or at a shadow's edge (a neighbouring pixel on the same surface
    sees the fire differently) within `radius` pixels would give more than `share` of the luminance unshadowed;
    and where more than `share` comes from a reflection within `glow` pixels of a reflected edge (a
    neighbour's mirrored rays meet another surface) or of a flame's mirror image (the floor's
    gloss is a mip filter of the mirrored image in the frame, a cone of rays here: they blur an
    edge differently), and the flames themselves."""
    lum = ref.image @ _LUM
    uncertain = np.zeros(lum.shape)
    for fire_lum, state, surface in ((ref.direct_lum, ref.direct_state, ref.direct_surface),
                                     (ref.mirror_lum, ref.mirror_state, ref.mirror_surface)):
        h, w = state.shape[:2]
        edge = state == 2
        pad = np.pad(state, ((1, 1), (1, 1), (0, 0)), constant_values=-1)
        pad_surface = np.pad(surface, 1, constant_values=-1)
        for dy in range(3):
            for dx in range(3):
                nb = pad[dy:dy + h, dx:dx + w]
                same = (pad_surface[dy:dy + h, dx:dx + w] == surface)[..., None]
                edge |= same & (state >= 0) & (nb >= 0) & (nb != state)
        uncertain += np.sum(fire_lum * _grow(edge, radius), axis=-1)
    h, w = lum.shape
    surface = ref.mirror_surface
    pad = np.pad(surface, 1, constant_values=-1)
    seam = (surface == -3) | ref.mirrored_flames
    for dy in range(3):
        for dx in range(3):
            seam |= ref.floor & (pad[dy:dy + h, dx:dx + w] != surface)
    uncertain += ref.mirror_total * _grow(seam, glow)
    return (uncertain > share * np.maximum(lum, 1e-30)) | ref.flames | _grow(ref.mirrored_flames, glow)


def _norm(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _f64(tree):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating)
                                  else a, tree)


class _World:
    """A frame's geometry and light, numpy float64."""

    def __init__(self, scene, fr: Frame):
        st = scene.stage
        self.center, self.u, self.v = (np.asarray(a, np.float64) for a in (st.center, st.u, st.v))
        self.material = np.asarray(st.material)
        fl = scene.fires
        self.f_center, self.f_u, self.f_v = (np.asarray(a, np.float64) for a in (fl.center, fl.u, fl.v))
        self.camera = scene.camera
        self.labels, self.colours = np.asarray(scene.labels), np.asarray(scene.colours, np.float64)
        self.tiles = float(scene.tiles)
        self.mats, self.env = _f64(scene.mats), _f64(scene.env)
        self.fr = fr
        c, u, v = self.center, self.u, self.v
        quads = np.concatenate([np.stack([c - u - v, c + u - v, c + u + v], 1),
                                np.stack([c - u - v, c + u + v, c - u + v], 1)])
        self.n_stage = len(quads)
        performer = fr.vertices[fr.triangles]
        basket = (self.material == MATERIALS.index("iron")) & (np.abs(c[:, 1] - (FLAME_BASE - BASKET[1] / 2)) < 1e-9)
        owner = np.argmin(np.linalg.norm(c[:, None, [0, 2]] - self.f_center[None, :, [0, 2]], axis=-1), axis=1)
        owner = np.tile(np.where(basket, owner, -1), 2)           # the fire whose basket a triangle is, -1: none
        self.everything = Triangles(np.concatenate([quads, performer]))
        # per fire: everything but its own basket (for its blocks), and its own basket (for its cells)
        self.but_own = [Triangles(np.concatenate([quads[owner != f], performer])) for f in range(len(self.f_center))]
        self.own = jnp.asarray(np.stack([quads[owner == f] for f in range(len(self.f_center))]))
        self.cells = self._flame_cells()

    def _flame_cells(self):
        """Each flame's cells (`FIRE_ROWS` rows of equal power x `FIRE_COLUMNS`): centres (Q M 3),
        exact mean emission (Q M 3), areas (Q M) and block (M); and its blocks' centres (Q B 3,
        `FIRE_BLOCKS` rows x columns of cells grouped)."""
        em = self.fr.emission
        q, hf, wf = em.shape[:3]
        rows = em.mean(axis=2)                                                   # Q Hf 3
        power = np.cumsum(np.concatenate([np.zeros((q, 1)), rows @ _LUM], 1), axis=1)
        power /= power[:, -1:]
        br, bc = FIRE_BLOCKS
        top, bottom = np.arange(hf) / hf, (np.arange(hf) + 1) / hf
        col_edge = np.arange(FIRE_COLUMNS + 1) / FIRE_COLUMNS
        left, right = np.arange(wf) / wf, (np.arange(wf) + 1) / wf

        def overlap(a0, a1, b0, b1):       # (len(a0) x len(b0)) overlaps of intervals
            return np.clip(np.minimum(a1[:, None], b1[None]) - np.maximum(a0[:, None], b0[None]), 0, None)

        col_share = overlap(col_edge[:-1], col_edge[1:], left, right) * FIRE_COLUMNS          # C Wf
        s = 0.5 * (col_edge[1:] + col_edge[:-1])
        out = [], [], [], []
        for f in range(q):
            edge = np.interp(np.linspace(0, 1, FIRE_ROWS + 1), power[f], np.arange(hf + 1) / hf)
            height = np.diff(edge)
            row_share = overlap(edge[:-1], edge[1:], top, bottom) / np.maximum(height, 1e-12)[:, None]   # R Hf
            emission = np.einsum("rh,cw,hwx->rcx", row_share, col_share, em[f]).reshape(-1, 3)
            t = 0.5 * (edge[1:] + edge[:-1])
            tt, ss = (g.reshape(-1) for g in np.meshgrid(t, s, indexing="ij"))
            at = lambda ss, tt: (self.f_center[f] + (2 * ss - 1)[:, None] * self.f_u[f]  # noqa: E731
                                 + (1 - 2 * tt)[:, None] * self.f_v[f])
            full = 4 * np.linalg.norm(np.cross(self.f_u[f], self.f_v[f]))
            b_edge = edge[::FIRE_ROWS // br]
            bt, bs = (g.reshape(-1) for g in np.meshgrid(0.5 * (b_edge[1:] + b_edge[:-1]), (np.arange(bc) + 0.5) / bc,
                                                         indexing="ij"))
            for k, v in enumerate((at(ss, tt), emission, np.repeat(height, FIRE_COLUMNS) * full / FIRE_COLUMNS,
                                   at(bs, bt))):
                out[k].append(v)
        r, c = np.meshgrid(np.arange(FIRE_ROWS), np.arange(FIRE_COLUMNS), indexing="ij")
        block = ((r // (FIRE_ROWS // br)) * bc + c // (FIRE_COLUMNS // bc)).reshape(-1)
        centres, emission, area, blocks = (np.stack(v) for v in out)
        return centres, emission, area, block, blocks

    def _fire_visibility(self, p, n):
        """(N Q M) whether each point (lifted along n) sees each flame cell, and (N Q B) whether it
        sees each block's centre past everything but the fire's own basket."""
        centres, _, _, block, blocks = self.cells
        q, b = blocks.shape[:2]
        lifted = p + EPS * n
        seen_blocks = np.stack([self._seen(self.but_own[f], lifted, blocks[f]) for f in range(q)], 1)
        past_basket = np.asarray(_clear_of(jnp.asarray(lifted), jnp.asarray(centres), self.own))
        return seen_blocks[:, :, block] & past_basket, seen_blocks

    def _samples_seen(self, o):
        """(N K) whether each origin sees each of the frame's K fire samples."""
        return self._seen(self.everything, o, self.fr.fire_position)

    @staticmethod
    def _seen(tris, o, targets):
        """(N M) whether each origin sees each of the targets (M 3) past `tris`."""
        m = len(targets)
        oo = np.repeat(o, m, axis=0)
        to = np.tile(targets, (len(o), 1)) - oo
        dist = np.linalg.norm(to, axis=-1)
        return ~tris.blocked(oo, to / dist[:, None], dist * (1 - 1e-9)).reshape(len(o), m)

    def _sky_visible(self, p, n):
        k = len(self.fr.env_direction)
        o = np.repeat(p + EPS * n, k, axis=0)
        d = np.tile(self.fr.env_direction, (len(p), 1))
        return ~self.everything.blocked(o, d, np.full(len(o), np.inf)).reshape(len(p), k)

    @staticmethod
    def _states(seen):
        """(N Q) from (N Q B) blocks seen: 0 none, 1 all, 2 some."""
        return np.where(seen.all(axis=2), 1, np.where(seen.any(axis=2), 2, 0))

    def _fire_states(self, p, n, shading):
        """`_states` at performer points (lifted along the geometric normal n); 2 also where a
        block lies behind the point's triangle but before its shading normal (the shadow
        terminator: a shadow map's bias lights it, a ray hits the triangle's neighbours)."""
        _, seen = self._fire_visibility(p, n)
        to = self.cells[4][None] - p[:, None, None]
        terminator = np.any((np.einsum("nqbc,nc->nqb", to, n) < 0) & (np.einsum("nqbc,nc->nqb", to, shading) > 0), -1)
        return np.where(terminator, 2, self._states(seen))

    def stage_radiance(self, p, n, quad):
        """Radiance (N 3) of stage points (albedo / pi x irradiance), the luminance each fire would
        give them unshadowed (N Q) and the fires' states (`_states`)."""
        u_len, v_len = np.linalg.norm(self.u, axis=-1), np.linalg.norm(self.v, axis=-1)
        rel = p - self.center[quad]
        la = np.sum(rel * self.u[quad], -1) / u_len[quad]
        lb = np.sum(rel * self.v[quad], -1) / v_len[quad]
        rho = np.asarray(_albedo(jnp.asarray(self.material[quad]), jnp.asarray(la), jnp.asarray(lb), jnp.asarray(p)))
        e_env = (np.maximum(n @ self.fr.env_direction.T, 0.0) * self._sky_visible(p, n)) @ self.fr.env_weight
        centres, emission, area = self.cells[:3]
        clear, seen = self._fire_visibility(p, n)
        lit, unlit = (np.asarray(a) for a in _irradiance(jnp.asarray(p), jnp.asarray(n), jnp.asarray(centres),
                                                          jnp.asarray(emission), jnp.asarray(area), jnp.asarray(clear)))
        unshadowed = rho[:, None] / np.pi * unlit @ _LUM                                   # N Q
        return rho / np.pi * (e_env + lit.sum(axis=1)), unshadowed, self._states(seen)

    def performer_radiance(self, o, tri, b1, b2, neighbours, blend):
        """Radiance toward the origins `o` of the performer points hit there, the luminance each fire
        would give them unshadowed and the fires' states (`_states`); `neighbours`: the rays
        (origins, directions) through the pixel centres right of and below each one's pixel (for
        the uv derivatives)."""
        fr = self.fr
        vid = fr.triangles[tri]
        p0, p1, p2 = (fr.vertices[vid[:, k]] for k in range(3))
        t0, t1, t2 = (fr.uv[vid[:, k]] for k in range(3))
        bary = np.stack([1 - b1 - b2, b1, b2], -1)
        pos = bary[:, :1] * p0 + bary[:, 1:2] * p1 + bary[:, 2:] * p2
        uv = bary[:, :1] * t0 + bary[:, 1:2] * t1 + bary[:, 2:] * t2
        nrm = _norm(sum(bary[:, k:k + 1] * fr.normals[vid[:, k]] for k in range(3)))
        wo = _norm(o - pos)
        nrm = np.where((np.sum(nrm * wo, -1) < 0)[:, None], -nrm, nrm)       # two-sided: toward the viewer
        e1, e2, d1, d2 = p1 - p0, p2 - p0, t1 - t0, t2 - t0
        plane = np.cross(e1, e2)
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / np.where(np.abs(det) > 1e-12, det, 1e-12)[:, None]
        tangent = dpdu - np.sum(dpdu * nrm, -1, keepdims=True) * nrm
        helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        helper = helper - np.sum(helper * nrm, -1, keepdims=True) * nrm
        tangent = _norm(np.where(np.sum(tangent * tangent, -1, keepdims=True) > 1e-16, tangent, helper))
        frame = np.stack([tangent, np.cross(nrm, tangent), nrm], 1)

        def uv_along(oo, dd):                   # where a ray meets the triangle's plane, in uv
            x = oo + (np.sum((p0 - oo) * plane, -1) / np.sum(dd * plane, -1))[:, None] * dd
            w = np.stack([np.cross(p2 - p1, x - p1), np.cross(p0 - p2, x - p2), np.cross(p1 - p0, x - p0)], 1)
            w = np.sum(w * plane[:, None], -1) / np.sum(plane * plane, -1)[:, None]
            return w[:, :1] * t0 + w[:, 1:2] * t1 + w[:, 2:] * t2

        duv = [uv_along(*ray) - uv for ray in neighbours]
        hm, wm = self.labels.shape[0] // 2, self.labels.shape[1]
        col = np.clip(np.floor(uv[:, 0] * wm).astype(int), 0, wm - 1)
        row = np.clip(np.floor(uv[:, 1] * hm).astype(int), 0, 2 * hm - 1)
        material = self.labels[row, col]
        use = np.isin(material, [LABELS.index(m) for m in TAKES_COLOUR]).astype(np.float64)
        # the frame's K sky and K fire samples, each with its visibility, cast from the point moved
        # onto the smooth surface its shading normals describe (Hanika 2021, "Hacking the shadow
        # terminator"): from the flat triangle, light the shading normal faces can lie behind the
        # triangle's own plane, where a ray would hit the triangle itself
        bent = sum(bary[:, k:k + 1] * (pos - np.sum((pos - v) * nv, -1, keepdims=True) * nv)
                   for k, (v, nv) in enumerate(zip((p0, p1, p2), (fr.normals[vid[:, k]] for k in range(3)))))
        geo = _norm(plane) * np.sign(np.sum(plane * nrm, -1, keepdims=True))
        origin = np.where(np.sum((bent - pos) * geo, -1, keepdims=True) > 0, bent, pos)
        env_w = fr.env_weight[None] * self._sky_visible(origin, geo)[..., None]
        to = fr.fire_position[None] - pos[:, None]
        r2 = np.sum(to * to, -1)
        clear = self._samples_seen(origin + EPS * geo)
        fire_w = fr.fire_radiance[None] * (clear / (r2 * fr.fire_pdf[None] * len(fr.fire_pdf)))[..., None]
        k_env = len(fr.env_direction)
        wi = np.concatenate([np.broadcast_to(fr.env_direction, (len(pos), k_env, 3)), to / np.sqrt(r2)[..., None]], 1)
        args = (self.mats, jnp.asarray(material), jnp.asarray(uv * self.tiles), jnp.asarray(duv[0] * self.tiles),
                jnp.asarray(duv[1] * self.tiles), jnp.asarray(frame), jnp.asarray(wo), jnp.asarray(wi))
        colour = dict(diffuse_override=jnp.asarray(self.colours[row, col]), use_override=jnp.asarray(use), blend=blend)
        rad = np.asarray(_shade(*args, jnp.asarray(np.concatenate([env_w, fire_w], 1)), **colour), np.float64)
        unshadowed = fr.fire_radiance[None] * (1 / (r2 * fr.fire_pdf[None] * len(fr.fire_pdf)))[..., None]
        fire_lum = np.stack([np.asarray(_shade(*args, jnp.asarray(np.concatenate(
            [0 * env_w, unshadowed * (fr.fire_light == q)[None, :, None]], 1)), **colour)) @ _LUM
            for q in range(len(self.f_center))], -1)
        return rad, fire_lum, self._fire_states(origin, geo, nrm)

    def flames_along(self, o, d, t_stop):
        """The flames' emission (bilinear, clamped) where each ray meets a flame quad before `t_stop`."""
        out = np.zeros((len(o), 3))
        for q in range(len(self.f_center)):
            c, u, v = self.f_center[q], self.f_u[q], self.f_v[q]
            n = _norm(np.cross(u, v))
            den = d @ n
            ok = np.abs(den) > 1e-12
            t = np.where(ok, ((c - o) @ n) / np.where(ok, den, 1.0), -1.0)
            rel = o + t[:, None] * d - c
            a, b = rel @ u / (u @ u), rel @ v / (v @ v)
            hit = ok & (t > 0) & (t < t_stop) & (np.abs(a) <= 1) & (np.abs(b) <= 1)
            if hit.any():
                uv = np.stack([(a + 1) / 2, (1 - b) / 2], -1)[hit]
                out[hit] += np.asarray(_bilinear(jnp.asarray(self.fr.emission[q]), jnp.asarray(uv)))
        return out

    def shade(self, o, d, neighbours, blend):
        """Along rays: the radiance arriving at the origins (without the floors' reflection), the
        luminance each fire would give it unshadowed (N Q), the fires' states there (`_states`; -1: no surface),
        which rays met the performer, which a polished floor, their distance, and which a flame
        adds to."""
        t, k, b1, b2 = self.everything.nearest(o, d)
        q = len(self.f_center)
        rad = np.array(_sky(self.env, jnp.asarray(d)), np.float64)
        fire_lum, state = np.zeros((len(o), q)), np.full((len(o), q), -1)
        stage = (k >= 0) & (k < self.n_stage)
        perf = k >= self.n_stage
        quad = np.where(stage, k % len(self.center), 0)
        if stage.any():
            sq, dq = quad[stage], d[stage]
            n = _norm(np.cross(self.u[sq], self.v[sq]))
            n = np.where((np.sum(n * dq, -1) > 0)[:, None], -n, n)
            rad[stage], fire_lum[stage], state[stage] = self.stage_radiance(o[stage] + t[stage, None] * dq, n, sq)
        if perf.any():
            rad[perf], fire_lum[perf], state[perf] = self.performer_radiance(
                o[perf], k[perf] - self.n_stage, b1[perf], b2[perf], [(no[perf], nd[perf]) for no, nd in neighbours],
                blend)
        flames = self.flames_along(o, d, t)
        polished = stage & (self.material[quad] == MATERIALS.index("floor"))
        surface = np.where(stage, quad, np.where(perf, -2, -1))
        return rad + flames, fire_lum, state, surface, perf, polished, t, np.any(flames > 0, axis=-1)


def _mirror(d):
    return d * np.asarray([1.0, -1.0, 1.0])


def _spread(d, roughness):
    """GLOSS x GLOSS directions (N G 3) over a square cone `roughness` radians wide around each d."""
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    a = _norm(np.cross(d, helper))
    b = np.cross(d, a)
    off = ((np.arange(GLOSS) + 0.5) / GLOSS - 0.5) * roughness
    oa, ob = (g.reshape(-1) for g in np.meshgrid(off, off, indexing="ij"))
    return _norm(d[:, None] + oa[None, :, None] * a[:, None] + ob[None, :, None] * b[:, None])


def render_reference(scene, frame: Frame, *, roughness: float = STAGE_ROUGHNESS) -> Reference:
    """The reference frame (module docstring)."""
    world = _World(scene, frame)
    cam = scene.camera
    h, w = cam.height, cam.width
    rows, cols = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    pixel = np.stack([cols, rows], -1).reshape(-1, 2)
    ray = lambda px: np.asarray(cam.ray_direction(jnp.asarray(px)), np.float64)  # noqa: E731
    d, right, below = ray(pixel), ray(pixel + [1.0, 0.0]), ray(pixel + [0.0, 1.0])
    eye = np.asarray(cam.eye, np.float64)
    o = np.broadcast_to(eye, d.shape).copy()
    rad, lum, state, surface, perf, polished, t, flames = world.shade(o, d, [(o, right), (o, below)], "shading")
    image, mirrored_perf, mirrored_flames = rad.copy(), np.zeros(len(d), bool), np.zeros(len(d), bool)
    q = lum.shape[1]
    m_lum, m_state, m_surface = np.zeros_like(lum), np.full_like(state, -1), np.full_like(surface, -1)
    m_total = np.zeros(len(d))
    idx = np.flatnonzero(polished)
    if idx.size:
        dirs = _spread(_mirror(d[idx]), roughness)                             # N G 3
        g = dirs.shape[1]
        origin = np.repeat(o[idx] + t[idx, None] * d[idx] + [0.0, EPS, 0.0], g, axis=0)
        # the uv derivatives of what is mirrored: the neighbouring pixels' rays, mirrored where they meet y = 0
        nb = [(np.repeat(eye + (-eye[1] / nd[idx, 1])[:, None] * nd[idx], g, axis=0), np.repeat(_mirror(nd[idx]), g, 0))
              for nd in (right, below)]
        r_rad, r_lum, r_state, r_surface, r_perf, _, _, r_flames = world.shade(origin, dirs.reshape(-1, 3), nb,
                                                                               "nearest")
        f = np.asarray(fresnel_schlick(jnp.asarray(np.clip(-d[idx, 1], 0.0, 1.0)), STAGE_F0), np.float64)[:, None]
        image[idx] = rad[idx] * (1 - f) + f * r_rad.reshape(-1, g, 3).mean(axis=1)
        m_total[idx] = (f * r_rad.reshape(-1, g, 3).mean(axis=1)) @ _LUM
        lum[idx] *= 1 - f
        m_lum[idx] = f * r_lum.reshape(-1, g, q).mean(axis=1)
        r_state = r_state.reshape(-1, g, q)
        valid = r_state >= 0
        hi = np.max(np.where(valid, r_state, -1), axis=1)
        lo = np.min(np.where(valid, r_state, 3), axis=1)
        m_state[idx] = np.where(hi < 0, -1, np.where(hi == lo, hi, 2))
        r_surface = r_surface.reshape(-1, g)
        m_surface[idx] = np.where(np.all(r_surface == r_surface[:, :1], axis=1), r_surface[:, 0], -3)
        mirrored_perf[idx] = r_perf.reshape(-1, g).any(axis=1)
        mirrored_flames[idx] = r_flames.reshape(-1, g).any(axis=1)
    grid = lambda a: a.reshape((h, w) + a.shape[1:])  # noqa: E731
    return Reference(grid(image), grid(lum), grid(state), grid(surface), grid(m_lum), grid(m_state),
                     grid(m_surface), grid(m_total), grid(perf), grid(mirrored_perf), grid(flames),
                     grid(mirrored_flames), grid(polished))


# ------------------------------------------------------------------------------ the cases compared

MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"))
CAPTURED = "dance-short_normal_001.bvh"
CAPTURED_ROWS = slice(360, 421)     # 2 s of the captured dance: the right hand rises above the head
FRAMES = {"built-in": (3, 27), "captured": (2, 13)}   # 27: the sleeve raised before the face; 13: the hand up
SEED = 11


def motion_of(label: str) -> tuple[BVHMotion, float]:
    """The motion of a case and the seconds it lasts: the built-in dance in 4 s (the sleeve raised
    from 2.1 s to 3.5 s), or 2 s of the captured dance."""
    if label == "built-in":
        return noh_dance(duration=4.0), 4.0
    bvh = read_bvh(MOCAP / CAPTURED)
    return BVHMotion(bvh.names, bvh.parents, bvh.offsets, bvh.channels, bvh.end_site, bvh.frame_time,
                     bvh.motion[CAPTURED_ROWS]), 2.0


def case_scene(label: str, width: int, height: int, **small):
    """The scene of a case (`small`: `noh_scene` keywords, e.g. level-0 BTFs and small flames)."""
    motion, duration = motion_of(label)
    return noh_scene(width=width, height=height, frames=2, key=jax.random.key(SEED), motion=motion,
                     duration=duration, **small)


def keys(frame: int):
    """(sky samples' key, frame key) of `render_sequence` with seed `SEED`."""
    k_env, k_frames = jax.random.split(jax.random.key(SEED + 1))
    return k_env, jax.random.fold_in(k_frames, frame)


def robe_states(scene, frames: int) -> list:
    """The robe's states over `frames` frames of 0.1 s from the settled robe: [f] is the state frame
    f starts from ([0] the settled one), each frame one call of the same compiled frame."""
    costume, motion = scene.performer.costume, scene.performer.motion
    states = [costume.state]
    for _ in range(frames):
        states.append(_robe_frame(costume, motion, states[-1]))
    return states


_robe_frame = eqx.filter_jit(lambda c, m, s: costume_frames(c, m, frames=1, frame_dt=0.1, state=s)[1])


def state_before(scene, frame: int):
    """The robe's state the frame starts from: `frame` frames of 0.1 s from the settled robe."""
    return robe_states(scene, frame)[frame]


def production_frame(scene, frame: int, state, *, shadow_resolution: int):
    """The production frame (`noh_frame`, its buffers grown as `render_sequence` grows them) from
    `state`: (linear image, the robe's new state, the frame's counts)."""
    k_env, key = keys(frame)
    rig = prepare_rig(scene, key=k_env, shadow_resolution=shadow_resolution, frame_dt=0.1)
    emission = scene.flames[:, frame % scene.flames.shape[1]]
    while True:
        image, new_state, counts = noh_frame_jit(scene, rig, state, emission, key)
        bigger = grown(rig, counts)
        if bigger is None:
            return np.asarray(image, np.float64), new_state, counts
        rig = bigger


def reference_inputs(scene, frame: int, new_state) -> Frame:
    k_env, key = keys(frame)
    return frame_inputs(scene, new_state, scene.flames[:, frame % scene.flames.shape[1]], fire_key=key, env_key=k_env)


# the float32 frames: rendered by a child Python without x64 (as users run), of the parent's scene
# rounded to float32 (its robe unsettled until the parent's settled one replaces it), from the
# float64 states the frames start from; it saves each image and the Frame of its state and samples
FLOAT32_CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    import jax
    assert not jax.config.jax_enable_x64
    sys.path.insert(0, sys.argv[3])
    import noh_reference as nr
    from sims import ClothState
    spec = json.loads(sys.argv[2])
    data = np.load(sys.argv[1])
    out = {}
    for label, frames in spec["cases"].items():
        scene = nr.case_scene(label, spec["width"], spec["height"], **nr.small_scene(), robe={"settle_steps": 0})
        count = sum(k.startswith(f"{label}_scene_") for k in data.files)
        scene = nr.with_float_leaves(scene, [data[f"{label}_scene_{i}"] for i in range(count)])
        for f in frames:
            x, xp, t = (data[f"{label}_{f}_{k}"] for k in ("x", "x_prev", "time"))
            state = ClothState(*(jax.numpy.asarray(a, jax.numpy.float32) for a in (x, xp, t)))
            image, new_state, _ = nr.production_frame(scene, f, state, shadow_resolution=spec["shadow_resolution"])
            fr = nr.reference_inputs(scene, f, new_state)
            out[f"{label}_{f}_image"] = np.asarray(image, np.float32)
            for k, v in vars(fr).items():
                out[f"{label}_{f}_{k}"] = v
    np.savez(sys.argv[4], **out)
""")


def _is_float(leaf) -> bool:
    return isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jnp.floating)


def float_leaves(scene) -> list:
    """The scene's floating-point arrays, in tree order."""
    return [leaf for leaf in jax.tree_util.tree_leaves(scene) if _is_float(leaf)]


def with_float_leaves(scene, leaves: list):
    """`scene` with its floating-point arrays replaced by `leaves` (cast to each array's dtype):
    the parent's scene in the float32 child."""
    flat, tree = jax.tree_util.tree_flatten(scene)
    if len(leaves) != sum(map(_is_float, flat)):
        raise ValueError(f"{len(leaves)} arrays for a scene of {sum(map(_is_float, flat))}")
    values = iter(leaves)
    flat = [jnp.asarray(next(values), leaf.dtype) if _is_float(leaf) else leaf for leaf in flat]
    return jax.tree_util.tree_unflatten(tree, flat)


def small_scene() -> dict:
    """The scene's detail for the comparison (what it proves does not need more): level-0 BTFs of
    8 texels, 32 x 16 flame textures; the robe as rendered."""
    return dict(btfs=default_btfs(size=8, pyramid="none"), flame_size=(32, 16))


def float32_frames(spec: dict, states: dict, scenes: dict, workdir: Path) -> dict:
    """Run `FLOAT32_CHILD` (`spec`: width, height, shadow_resolution, cases {label: frames};
    `states`: {label_frame_x|x_prev|time: array}; `scenes`: {label: the parent's scene}); returns
    {(label, frame): (image, Frame, the scene the child rendered: the parent's rounded to float32,
    in the parent's precision)}."""
    leaves = {f"{label}_scene_{i}": np.asarray(leaf) for label in spec["cases"]
              for i, leaf in enumerate(float_leaves(scenes[label]))}
    np.savez(workdir / "states.npz", **states, **leaves)
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)
    proc = subprocess.run([sys.executable, "-c", FLOAT32_CHILD, str(workdir / "states.npz"), json.dumps(spec),
                           str(Path(__file__).resolve().parent), str(workdir / "float32.npz")],
                          capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-4000:])
    data = np.load(workdir / "float32.npz")
    out = {}
    for label, frames in spec["cases"].items():
        scene = scenes[label]
        scene = with_float_leaves(scene, [np.asarray(leaf, np.float32) for leaf in float_leaves(scene)])
        for f in frames:
            fields = {k: np.asarray(data[f"{label}_{f}_{k}"]) for k in Frame.__dataclass_fields__}
            fields = {k: (v.astype(np.float64) if v.dtype.kind == "f" else v) for k, v in fields.items()}
            out[(label, f)] = (np.asarray(data[f"{label}_{f}_image"], np.float64), Frame(**fields), scene)
    return out


def relative_rms(image: np.ndarray, reference: np.ndarray, where: np.ndarray) -> float:
    """sqrt(sum |image - reference|^2 / sum |reference|^2) over the pixels `where` (RGB)."""
    d = (image - reference)[where]
    return float(np.sqrt(np.sum(d * d) / np.sum(reference[where] ** 2)))
