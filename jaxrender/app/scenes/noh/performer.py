"""The performer as one triangle mesh per frame: the robe (`sims.costume`), the body's volumes as
capsules (hands, white tabi, the wig, the inner kimono at the collar), and a modelled Noh mask
(a ko-omote: a face surface with brow, nose, cheeks, mouth and chin) bound to the head, painted.

Its texture space has two pages: v in [0, 1) is the robe's label mask, v in [1, 2) the body page
(the painted mask, hair, skin, white). Shapes and the painting: docs/noh.md, "The performer".
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.io import srgb_to_linear
from jaxrender.maths import default_float, normalize
from sims import ClothState, SkeletonMotion
from sims.cloth import vertex_normals
from sims.costume import Costume, costume_normals

from .mask import LABELS

# regions of the body page, (u0, v0, du, dv) in the page's own [0, 1]^2
BODY_PAGE = {"face": (0.0, 0.0, 0.5, 0.75), "hair": (0.5, 0.0, 0.25, 0.5), "skin": (0.75, 0.0, 0.25, 0.25),
             "white": (0.75, 0.25, 0.25, 0.25), "inner": (0.5, 0.5, 0.5, 0.25)}
# which region each body volume wears
_VOLUME_REGION = {"head": "hair", "hand": "skin", "foot": "white", "toes": "white"}
_AROUND, _RINGS, _SEGMENTS = 10, 3, 4     # capsule tessellation: around, rings per cap, cylinder pieces
# the volumes that can be seen (the others stay inside the robe whatever the dance does)
SHOWN = ("chest", "neck", "head", "upper_arm", "lower_arm", "hand", "shin", "foot", "toes")


class PerformerRig(eqx.Module):
    """Everything that makes the performer's mesh from a pose and the robe's vertices."""

    costume: Costume
    motion: SkeletonMotion
    shown: Int[Array, " S"]                   # the volumes drawn as capsules
    capsule_uv: Float[Array, "S Vc 2"]        # each one's template uv on the body page (+ page 1)
    mask_joint: int = eqx.field(static=True)
    mask_local: Float[Array, "M 3"]           # the mask's vertices in the head joint's frame
    mask_uv: Float[Array, "M 2"]
    mask_triangles: Int[Array, "Tm 3"]


class PerformerMesh(eqx.Module):
    vertices: Float[Array, "V 3"]
    normals: Float[Array, "V 3"]
    uv: Float[Array, "V 2"]
    triangles: Int[Array, "T 3"]


class ExportedMesh(NamedTuple):
    """A mesh for other tools: each point once (`triangles` into `vertices`), the texture's
    coordinates by corner (`uv_triangles` into `uv`: a point on a seam has two)."""

    vertices: np.ndarray      # V 3, world space, metres, y up
    triangles: np.ndarray     # T 3
    uv: np.ndarray            # U 2
    uv_triangles: np.ndarray  # T 3


def _capsule_template() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit capsule along +z from 0 to 1 (radius 1 in x, y): (along, offset direction, triangles,
    uv). A vertex lies at a + along (b - a) + radius * direction (in the capsule's frame). The
    cylinder between the caps is cut into `_SEGMENTS` so that no triangle is long on screen."""
    rings = []
    for k in range(_RINGS + 1):          # the hemisphere at a: from its pole to its equator
        th = np.pi / 2 * k / _RINGS
        rings.append((0.0, -np.cos(th), np.sin(th)))
    for k in range(1, _SEGMENTS):        # along the cylinder
        rings.append((k / _SEGMENTS, 0.0, 1.0))
    for k in range(_RINGS + 1):          # the hemisphere at b: equator to pole
        th = np.pi / 2 * k / _RINGS
        rings.append((1.0, np.sin(th), np.cos(th)))
    phi = 2 * np.pi * np.arange(_AROUND + 1) / _AROUND
    along, direction, ring_v = [], [], []
    for r, (a, z, rho) in enumerate(rings):
        for p in phi:
            along.append(a)
            direction.append((rho * np.cos(p), rho * np.sin(p), z))
            ring_v.append(r / (len(rings) - 1))
    n_r, n_c = len(rings), _AROUND + 1
    idx = np.arange(n_r * n_c).reshape(n_r, n_c)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)])
    uv = np.stack([np.tile(phi / (2 * np.pi), n_r), np.asarray(ring_v)], -1)
    return np.asarray(along), np.asarray(direction), tris, uv


_ALONG, _DIRECTION, _CAPSULE_TRIS, _CAPSULE_UV = _capsule_template()


def _capsule_weld() -> np.ndarray:
    """Each template vertex's representative where the template repeats a point for its uv: the
    seam's last column is its first, each pole's ring is one point (the closed capsule)."""
    idx = np.arange(len(_ALONG)).reshape(-1, _AROUND + 1)
    idx[:, -1] = idx[:, 0]
    idx[0, :], idx[-1, :] = idx[0, 0], idx[-1, 0]
    return idx.ravel()


_CAPSULE_WELD = _capsule_weld()


def _region_uv(region: str, st: np.ndarray) -> np.ndarray:
    """Page coordinates (v + 1: the body page) of points `st` in [0, 1]^2 of a body-page region."""
    u0, v0, du, dv = BODY_PAGE[region]
    return np.stack([u0 + du * (0.05 + 0.9 * st[..., 0]), 1.0 + v0 + dv * (0.05 + 0.9 * st[..., 1])], -1)


def _mask_shape(rows: int = 24, cols: int = 18) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ko-omote in its own frame (x right, y up, z out of the face; metres for a 1.65 m
    figure): (vertices, st in [0, 1]^2 for the painting, triangles). About 800 triangles."""
    s, t = np.meshgrid(np.linspace(-1, 1, cols), np.linspace(1, -1, rows), indexing="xy")
    a, b = 0.068, 0.105                                        # half width and height of the face
    x = a * s * np.sqrt(1 - 0.5 * t ** 2)
    y = b * t * np.sqrt(1 - 0.5 * s ** 2)
    cap = np.sqrt(np.clip(1 - (x / (1.25 * a)) ** 2 - (y / (1.3 * b)) ** 2, 0, 1))
    g = lambda cx, cy, sx, sy: np.exp(-((x - cx) / sx) ** 2 - ((y - cy) / sy) ** 2)  # noqa: E731
    z = 0.055 * cap
    z += 0.016 * np.exp(-(x / 0.011) ** 2) * np.clip((0.035 - y) / 0.05, 0, 1) * np.clip((y + 0.035) / 0.02, 0, 1)
    z += 0.006 * g(0.0, -0.03, 0.012, 0.01)                    # the nose tip
    z -= 0.009 * (g(0.028, 0.012, 0.018, 0.01) + g(-0.028, 0.012, 0.018, 0.01))   # eye sockets
    z += 0.005 * (g(0.038, -0.03, 0.022, 0.025) + g(-0.038, -0.03, 0.022, 0.025))  # cheeks
    z -= 0.004 * g(0.0, -0.058, 0.014, 0.006)                  # the mouth
    z += 0.004 * g(0.0, -0.088, 0.02, 0.012)                   # the chin
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    st = np.stack([(s + 1) / 2, (1 - t) / 2], -1).reshape(-1, 2)
    idx = np.arange(rows * cols).reshape(rows, cols)
    q0, q1, q2, q3 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([q0, q2, q1], -1), np.stack([q1, q2, q3], -1)])
    return verts, st, tris


def performer_rig(costume: Costume, motion: SkeletonMotion, joints: dict[str, int], scale: float) -> PerformerRig:
    """Bind the mask to the head (its middle at the middle of the face's volume at frame 0,
    facing the body's forward direction) and give every capsule its body-page region."""
    body = costume.body
    dtype = default_float()
    regions, shown = [], []
    for k, name in enumerate(body.names):
        base = name[:-2] if name[-2:] in ("_L", "_R") else name
        if base in SHOWN:
            shown.append(k)
            regions.append(_VOLUME_REGION.get(base, "inner"))
    capsule_uv = np.stack([_region_uv(r, _CAPSULE_UV) for r in regions])
    p0 = np.asarray(motion.positions[0], np.float64)
    r0 = np.asarray(motion.rotations[0], np.float64)
    head = joints["head"]
    k = body.names.index("face")                        # along the head, around the mask
    a, b = (np.asarray(e[k], np.float64) for e in body.ends(motion.positions[0], motion.rotations[0]))
    up = (b - a) / np.linalg.norm(b - a)
    left = p0[joints["upper_leg_L"]] - p0[joints["upper_leg_R"]]
    forward = np.cross(left, up)
    forward /= np.linalg.norm(forward)
    right = np.cross(up, forward)
    verts, st, tris = _mask_shape()
    centre = 0.5 * (a + b)
    world = centre + scale * (verts[:, :1] * -right + verts[:, 1:2] * up + verts[:, 2:3] * forward)
    local = (world - p0[head]) @ r0[head]            # R^T (p - joint), row vectors
    return PerformerRig(costume, motion, jnp.asarray(shown, jnp.int32), jnp.asarray(capsule_uv, dtype), head,
                        jnp.asarray(local, dtype),
                        jnp.asarray(_region_uv("face", st), dtype), jnp.asarray(tris, jnp.int32))


def _capsule_frames(a: Array, b: Array) -> Array:
    """An orthonormal frame (rows x, y, z) per capsule with z along b - a."""
    z = normalize(b - a)
    helper = jnp.where(jnp.abs(z[:, 1:2]) < 0.9, jnp.asarray([[0.0, 1.0, 0.0]], z.dtype),
                       jnp.asarray([[1.0, 0.0, 0.0]], z.dtype))
    x = normalize(jnp.cross(helper, z))
    return jnp.stack([x, jnp.cross(z, x), z], 1)


def performer_mesh(rig: PerformerRig, state: ClothState) -> PerformerMesh:
    """The performer at the time of `state` (the robe's vertices and the skeleton's pose then)."""
    costume = rig.costume
    x = state.x
    dtype = x.dtype
    pos, rot = rig.motion.at(state.time)
    a, b = costume.body.ends(pos, rot)
    a, b, radius = a[rig.shown], b[rig.shown], costume.body.radius[rig.shown]
    frames = _capsule_frames(a, b)                                             # B 3 3
    along = jnp.asarray(_ALONG, dtype)
    direction = jnp.asarray(_DIRECTION, dtype)
    world_dir = jnp.einsum("vk,bkc->bvc", direction, frames)                   # B Vc 3
    cap_v = a[:, None] + along[None, :, None] * (b - a)[:, None] + radius[:, None, None] * world_dir
    n_caps, n_cv = cap_v.shape[0], cap_v.shape[1]
    cap_t = (jnp.asarray(_CAPSULE_TRIS, jnp.int32)[None] + (jnp.arange(n_caps, dtype=jnp.int32) * n_cv)[:, None, None])
    mask_v = pos[rig.mask_joint] + rig.mask_local @ rot[rig.mask_joint].T
    mask_n = vertex_normals(mask_v, rig.mask_triangles)
    robe_v = x[costume.render_index]
    n_robe = robe_v.shape[0]
    vertices = jnp.concatenate([robe_v, cap_v.reshape(-1, 3), mask_v])
    normals = jnp.concatenate([costume_normals(costume, x), world_dir.reshape(-1, 3), mask_n])
    uv = jnp.concatenate([costume.uv, rig.capsule_uv.reshape(-1, 2), rig.mask_uv])
    triangles = jnp.concatenate([costume.triangles, cap_t.reshape(-1, 3) + n_robe,
                                 rig.mask_triangles + n_robe + n_caps * n_cv])
    return PerformerMesh(vertices, normals, uv, triangles)


def _welded(mesh: PerformerMesh, triangles: np.ndarray, same: np.ndarray) -> ExportedMesh:
    """The `triangles` of `mesh` with the vertices `same` maps to one representative made one
    point (the triangles that collapse dropped)."""
    t = np.asarray(triangles)
    w = same[t]
    keep = (w[:, 0] != w[:, 1]) & (w[:, 1] != w[:, 2]) & (w[:, 2] != w[:, 0])
    points, point_tris = np.unique(w[keep], return_inverse=True)
    corners, uv_tris = np.unique(t[keep], return_inverse=True)
    return ExportedMesh(np.asarray(mesh.vertices, np.float64)[points], point_tris.reshape(-1, 3),
                        np.asarray(mesh.uv, np.float64)[corners], uv_tris.reshape(-1, 3))


def exported_meshes(mesh: PerformerMesh, rig: PerformerRig) -> tuple[ExportedMesh, ExportedMesh]:
    """(body, robe) of `performer_mesh(rig, state)` as rendered, for other tools: the body is the
    capsules (each a closed mesh: its seam and poles welded) and the mask (an open surface); the
    robe is its simulated vertices (the rendered ones repeat those on the pattern's seams)."""
    render_index = np.asarray(rig.costume.render_index)
    n_robe, n_robe_tris = len(render_index), rig.costume.triangles.shape[0]
    _, first, inverse = np.unique(render_index, return_index=True, return_inverse=True)
    n_caps, n_cv = int(rig.shown.shape[0]), len(_ALONG)
    caps = (n_robe + np.arange(n_caps)[:, None] * n_cv + _CAPSULE_WELD[None]).ravel()
    n = mesh.vertices.shape[0]
    same = np.concatenate([first[inverse.reshape(-1)], caps, np.arange(n_robe + caps.size, n)])
    triangles = np.asarray(mesh.triangles)
    return _welded(mesh, triangles[n_robe_tris:], same), _welded(mesh, triangles[:n_robe_tris], same)


def _smooth(x, e0, e1):
    u = np.clip((x - e0) / (e1 - e0), 0, 1)
    return u * u * (3 - 2 * u)


def body_page(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(labels int32, colour linear RGB) of the body page, `size` x `size`: the mask painted
    (gofun white, hikimayu brows high on the forehead, narrow eyes, red lips with blackened
    teeth, the hair's painted strands from the centre parting), black hair, skin, white, and
    the inner kimono's colour."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    labels = np.full((size, size), LABELS.index("painted"), np.int32)
    srgb = np.zeros((size, size, 3))

    def inside(region):
        u0, v0, du, dv = BODY_PAGE[region]
        return (u >= u0) & (u < u0 + du) & (v >= v0) & (v < v0 + dv)

    srgb[inside("skin")] = (232, 205, 180)
    srgb[inside("white")] = (240, 238, 230)
    srgb[inside("inner")] = (236, 232, 222)
    hair = inside("hair")
    labels[hair] = LABELS.index("hair")
    srgb[hair] = (14, 12, 12)
    face = inside("face")
    u0, v0, du, dv = BODY_PAGE["face"]
    s = ((u - u0) / du - 0.05) / 0.9 * 2 - 1                 # the mask's own coordinates, s right, t up
    t = 1 - ((v - v0) / dv - 0.05) / 0.9 * 2
    paint = np.broadcast_to(np.asarray([246.0, 240.0, 226.0]), s.shape + (3,)).copy()   # gofun white

    def blend(weight, colour):
        paint[...] = paint * (1 - weight[..., None]) + np.asarray(colour, float) * weight[..., None]

    blend(0.25 * np.exp(-((np.abs(s) - 0.45) / 0.2) ** 2 - ((t + 0.25) / 0.2) ** 2), (236, 170, 160))   # cheeks
    brow = np.exp(-((np.abs(s) - 0.33) / 0.16) ** 2 - ((t - 0.62) / 0.06) ** 2)
    blend(0.85 * brow, (60, 55, 55))                                                  # hikimayu
    eye = (np.abs(t - 0.14 + 0.12 * (np.abs(s) - 0.33)) < 0.035 * (1 - ((np.abs(s) - 0.33) / 0.17) ** 2)) & (
        np.abs(np.abs(s) - 0.33) < 0.17)
    blend(eye.astype(float), (10, 8, 8))
    lips = ((s / 0.2) ** 2 + ((t + 0.56) / 0.07) ** 2) < 1
    blend(lips.astype(float), (178, 30, 35))
    teeth = (np.abs(s) < 0.1) & (np.abs(t + 0.555) < 0.012)
    blend(teeth.astype(float), (20, 15, 15))
    # the painted hair: strands from the centre parting, sweeping down both sides of the forehead
    for k in range(5):
        centre = 0.02 + 0.09 * k
        curve = centre + 0.35 * (1 - t) ** 2 * (0.4 + 0.15 * k)
        strand = np.exp(-((np.abs(s) - curve) / 0.012) ** 2) * _smooth(t, 0.55 + 0.06 * k, 0.75 + 0.05 * k)
        blend(np.clip(strand, 0, 1), (12, 10, 10))
    blend(_smooth(t, 0.88, 0.97), (12, 10, 10))                                       # hairline at the top
    srgb[face] = paint[face]
    colour = np.asarray(srgb_to_linear(srgb / 255.0), np.float32)
    return labels, colour
