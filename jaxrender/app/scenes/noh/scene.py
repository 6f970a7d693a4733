"""The Noh scene assembled (metres, y up, the stage floor at y = 0): a garment hung from two
shoulder points (`sims.drape_garment`, Verlet mass-spring) in front of the camera, four bonfires
around the stage, each a flame quad whose emission texture is the current frame of
`sims.fire_frames`, the garment's materials by its mask, and the environment."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxrender.brdf import BTFTexel
from jaxrender.camera import Camera
from jaxrender.fabric import MaterialSet, stack_materials
from jaxrender.lights import EnvMap, QuadLights
from jaxrender.maths import default_float
from sims import DrapedCloth, cloth_mesh, drape_garment, fire_frames

from .environment import default_environment
from .mask import LABELS, default_mask, mask_from_rgb
from .materials import default_btfs


@functools.lru_cache(maxsize=2)
def garment_rig(rows: int, cols: int) -> DrapedCloth:
    """The settled garment and its simulation rig (the moving sequence continues from it)."""
    return drape_garment(rows=rows, cols=cols, top=1.6, height=1.5, shoulder_span=1.0, shoulder_u=0.08,
                         body_radius=0.12, body_z=-0.16, folds=5, fold_depth=0.05)


def _cloth(rows: int, cols: int):
    rig = garment_rig(rows, cols)
    return cloth_mesh(rig, rig.state.x)


class NohScene(eqx.Module):
    camera: Camera
    vertices: Float[Array, "V 3"]
    vertex_normals: Float[Array, "V 3"]
    uv: Float[Array, "V 2"]
    triangles: Int[Array, "T 3"]
    fires: QuadLights                       # emission: the flame sequences, F_fires x frames x H x W x 3
    flames: Float[Array, "Q N H W 3"]
    labels: Int[Array, "Hm Wm"]
    colours: Float[Array, "Hm Wm 3"]
    mats: MaterialSet
    env: EnvMap
    tiles: float = eqx.field(static=True)


FIRE_POSITIONS = ((-1.25, 0.9), (1.25, 0.9), (-1.6, -1.3), (1.6, -1.3))   # (x, z) of the four bonfires
FIRE_SIZE = (0.55, 0.8)                                                    # width, height (m)
FIRE_BASE = 0.95                                                           # flames burn in baskets on stands (m)


def noh_scene(*, width: int = 720, height: int = 480, frames: int = 20, key: PRNGKeyArray | None = None,
              mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
              env: EnvMap | None = None, cloth_rows: int = 40, cloth_cols: int = 32, tiles: float = 6.0,
              flame_size: tuple[int, int] = (128, 64), fire_intensity: float = 12.0, btf_size: int = 32,
              pyramid: str = "em") -> NohScene:
    """Assemble the scene; every input not given is the built-in one (module docstring)."""
    key = jax.random.key(2024) if key is None else key
    dtype = default_float()
    cam = Camera((0.9, 1.2, 3.4), (0.0, 0.82, 0.0), (0.0, 1.0, 0.0), 40.0, width=width, height=height)
    cloth = _cloth(cloth_rows, cloth_cols)
    verts = cloth.vertices.reshape(-1, 3).astype(dtype)
    normals = cloth.normals.reshape(-1, 3).astype(dtype)
    uv = cloth.uv.reshape(-1, 2).astype(dtype)
    centers, us, vs = [], [], []
    w, h = FIRE_SIZE
    for x, z in FIRE_POSITIONS:
        to_cam = np.asarray([float(cam.eye[0]) - x, 0.0, float(cam.eye[2]) - z])
        to_cam /= np.linalg.norm(to_cam)
        right = np.cross([0.0, 1.0, 0.0], to_cam)
        centers.append([x, FIRE_BASE + h / 2, z])
        us.append(right * w / 2)
        vs.append([0.0, h / 2, 0.0])
    keys = jax.random.split(key, len(FIRE_POSITIONS))
    flames = jnp.stack([fire_frames(k, frames=frames, height=flame_size[0], width=flame_size[1],
                                    intensity=fire_intensity) for k in keys]).astype(dtype)
    fires = QuadLights(jnp.asarray(centers, dtype=dtype), jnp.asarray(np.asarray(us), dtype=dtype),
                       jnp.asarray(vs, dtype=dtype), flames[:, 0])
    labels, colours = mask_from_rgb(default_mask() if mask_rgb is None else mask_rgb)
    btfs = default_btfs(size=btf_size, pyramid=pyramid) if btfs is None else btfs
    missing = [name for name in LABELS if name not in btfs]
    if missing:
        fallback = default_btfs(size=btf_size, pyramid=pyramid)
        btfs = {**{n: fallback[n] for n in missing}, **btfs}
    mats = stack_materials([btfs[name] for name in LABELS])
    env = default_environment() if env is None else env
    return NohScene(cam, verts, normals, uv, jnp.asarray(cloth.triangles), fires, flames,
                    jnp.asarray(labels), jnp.asarray(colours, dtype=dtype), mats, env, float(tiles))
