"""The performer's visible points and their shading under K light samples (paper 004, eqs. 2-4):
the costume and body by their BTF pyramids (`jaxrender.fabric.shade_fabric`), the environment's
samples shared by all points, the firelight's samples with each fire's PCSS visibility."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxrender.fabric import GBuffer, MaterialSet, Pinhole, shade_fabric, tangent_frames
from jaxrender.lights import QuadLightSamples
from jaxrender.maths import dot, normalize
from jaxrender.shadows import ShadowMap, pcss

from .mask import LABELS, TAKES_COLOUR
from .performer import PerformerMesh
from .stage import FLAME_SIZE, basket_hides, is_hidden


class PerformerPoints(eqx.Module):
    """The performer's visible pixels (`index` into the flattened image) and their surface data."""

    index: Int[Array, " G"]
    position: Float[Array, "G 3"]
    frame: Float[Array, "G 3 3"]        # tangent, bitangent, normal (facing the viewer)
    wo: Float[Array, "G 3"]
    uv: Float[Array, "G 2"]             # BTF texture coordinates (uv x tiles) and their footprint
    duv_dx: Float[Array, "G 2"]
    duv_dy: Float[Array, "G 2"]
    material: Int[Array, " G"]           # index into LABELS
    colour: Float[Array, "G 3"]         # the page's colour: rho_d of the plain weave and the painted body
    use_colour: Float[Array, " G"]       # 1 where the material takes that colour


class SurfaceLight(eqx.Module):
    """K light samples per point: directions toward the light and radiance x geometry / pdf."""

    direction: Float[Array, "N K 3"]
    weight: Float[Array, "N K 3"]


def shared_light(directions: Float[Array, "K 3"], weights: Float[Array, "K 3"], n: int) -> SurfaceLight:
    """The same K distant samples for all n points (the environment)."""
    k = directions.shape[0]
    return SurfaceLight(jnp.broadcast_to(directions[None], (n, k, 3)), jnp.broadcast_to(weights[None], (n, k, 3)))


def with_light(a: SurfaceLight, b: SurfaceLight) -> SurfaceLight:
    """Two sets of samples at the same points as one (one shading pass)."""
    return SurfaceLight(jnp.concatenate([a.direction, b.direction], 1), jnp.concatenate([a.weight, b.weight], 1))


def _flat(a: Array) -> Array:
    return a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:])


def performer_points(ph: Pinhole, mesh: PerformerMesh, labels: Int[Array, "Hm Wm"], colours: Float[Array, "Hm Wm 3"],
                     tiles: float, gb: GBuffer, index: Int[Array, " G"]) -> PerformerPoints:
    """Position, shading frame (tangent along the uv's u), BTF uv footprint and material of the
    rasterized pixels `index`; the material from the two-page atlas (v in [0, 2))."""
    tri = _flat(gb.triangle)[index]
    bary = _flat(gb.barycentric)[index]
    vid = mesh.triangles[tri]
    n = sum(bary[:, i:i + 1] * mesh.normals[vid[:, i]] for i in range(3))
    p0, p1, p2 = (mesh.vertices[vid[:, i]] for i in range(3))
    t0, t1, t2 = (mesh.uv[vid[:, i]] for i in range(3))
    e1, e2, d1, d2 = p1 - p0, p2 - p0, t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = jnp.where(jnp.abs(det) > 1e-12, det, 1e-12)
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    pos = _flat(gb.position)[index]
    wo = normalize(ph.origin[None, :] - pos)
    n = normalize(n)
    n = jnp.where((jnp.sum(n * wo, -1) < 0)[:, None], -n, n)   # two-sided: face the viewer
    uv = _flat(gb.uv)[index]
    hm, wm = labels.shape[0] // 2, labels.shape[1]
    col = jnp.clip(jnp.floor(uv[:, 0] * wm).astype(jnp.int32), 0, wm - 1)
    row = jnp.clip(jnp.floor(uv[:, 1] * hm).astype(jnp.int32), 0, 2 * hm - 1)
    material = labels[row, col]
    use_colour = sum((material == LABELS.index(m)).astype(pos.dtype) for m in TAKES_COLOUR)
    return PerformerPoints(index, pos, tangent_frames(n, dpdu), wo, uv * tiles, _flat(gb.duv_dx)[index] * tiles,
                           _flat(gb.duv_dy)[index] * tiles, material, colours[row, col], use_colour)


def shade_performer(mats: MaterialSet, points: PerformerPoints, light: SurfaceLight, *,
                    blend: str = "shading") -> Float[Array, "G 3"]:
    return shade_fabric(mats, points.material, points.uv, points.duv_dx, points.duv_dy, points.frame, points.wo,
                        light.direction, light.weight, diffuse_override=points.colour,
                        use_override=points.use_colour, blend=blend)


def fire_light(samples: QuadLightSamples, points: Float[Array, "N 3"], vis: Float[Array, "N Q"],
               fire_xz: Float[Array, "Q 2"]) -> SurfaceLight:
    """The K flame samples seen from each point, weighted by that fire's visibility there and
    by whether the fire's basket hides the sample from the point (`stage.basket_hides`)."""
    n_fires = fire_xz.shape[0]
    k = samples.position.shape[0]
    onehot = (samples.light[:, None] == jnp.arange(n_fires, dtype=jnp.int32)[None, :]).astype(points.dtype)   # K Q
    lo, hi = basket_hides(points, samples.position, fire_xz[samples.light])
    open_ = 1.0 - is_hidden(lo, hi, jnp.broadcast_to(samples.position[:, 1], lo.shape[:2])).astype(points.dtype)
    d = samples.position[None, :, :] - points[:, None, :]
    r2 = jnp.maximum(jnp.sum(d * d, -1), 1e-8)
    g = (vis @ onehot.T) * open_ / (r2 * samples.pdf_area[None, :] * k)          # billboard flames: |cos_y| = 1
    return SurfaceLight(d / jnp.sqrt(r2)[..., None], samples.radiance[None, :, :] * g[..., None])


def fire_visibility(maps: ShadowMap, points: Array, near: float) -> Float[Array, "N Q"]:
    """PCSS per fire (`maps` with a leading fire axis), light size = the flame's width, blockers
    no nearer than `near`."""
    return jax.vmap(lambda sm: pcss(sm, points, light_size=float(FLAME_SIZE[0]), near=near, bias=0.02))(maps).T


def quad_hits(center: Float[Array, "Q 3"], u: Float[Array, "Q 3"], v: Float[Array, "Q 3"], eye: Float[Array, "3"],
              rays: Float[Array, "H W 3"]
              ) -> tuple[Float[Array, "Q H W"], Float[Array, "Q H W 2"], Bool[Array, "Q H W"]]:
    """Each quad (centre, half-edge vectors u, v) against the rays from `eye`: the ray distance
    to its plane, the quad's uv there (u right, v up -> rows down) and whether it lies inside."""
    ts, uvs, ins = [], [], []
    for q in range(center.shape[0]):  # four fires: unrolled
        nrm = normalize(jnp.cross(u[q], v[q]))
        safe = jnp.where(jnp.abs(dot(rays, nrm)) > 1e-9, dot(rays, nrm), 1e-9)
        t = dot(center[q] - eye, nrm) / safe
        p = t[..., None] * rays + jnp.reshape(eye - center[q], (1, 1, 3))   # hit point relative to the centre
        a = dot(p, u[q]) / dot(u[q], u[q])
        b = dot(p, v[q]) / dot(v[q], v[q])
        ts.append(t)
        uvs.append(jnp.stack([(a + 1) / 2, (1 - b) / 2], -1))
        ins.append((jnp.abs(a) <= 1) & (jnp.abs(b) <= 1))
    return jnp.stack(ts), jnp.stack(uvs), jnp.stack(ins)
