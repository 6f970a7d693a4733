"""The Takigi Noh scene assembled (metres, y up, the stage floor at y = 0, the audience toward +z):
the performer (a motion placed on the stage, its robe and body, `.performer`), the stage
(`.stage`), four bonfires whose flames are the frames of `sims.fire_frames`, the costume's
materials by its mask, the environment, the camera."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxrender.brdf import BTFTexel
from jaxrender.camera import Camera
from jaxrender.fabric import MaterialSet, stack_materials
from jaxrender.io import BVHMotion, InputError
from jaxrender.lights import EnvMap, QuadLights
from jaxrender.maths import default_float
from sims import SkeletonMotion, fire_frames, noh_dance, place_motion, pose_motion
from sims.costume import body_scale, body_volumes, dress_performer, fit_shoulders, performer_joints

from .environment import default_environment
from .mask import LABELS, default_mask, mask_from_rgb
from .materials import default_btfs
from .performer import PerformerRig, body_page, performer_rig
from .stage import FIRE_SITES, FLAME_BASE, FLAME_SIZE, StageGeometry, build_stage

STAGE_SPOT = (0.0, 0.6)                               # where the performer's path is centred (x, z)
MAX_REACH = 20.0   # m: the farthest a joint may be from the path's centre (the stage is about 6 m across)
CAMERA = ((2.0, 1.6, 7.2), (-0.45, 1.1, -0.2), 40.0)   # eye, target, vertical field of view (deg)
ATLAS = 512                                           # each texture page's side (texels)
SKY_IRRADIANCE = 0.02                                 # the dusk sky on the open ground (the bonfires dominate)


class NohScene(eqx.Module):
    camera: Camera
    fires: QuadLights                       # emission: the flame sequences, F_fires x frames x H x W x 3
    flames: Float[Array, "Q N H W 3"]
    labels: Int[Array, "Hm Wm"]             # two pages stacked: the robe's mask, the body page
    colours: Float[Array, "Hm Wm 3"]
    mats: MaterialSet
    env: EnvMap
    stage: StageGeometry
    performer: PerformerRig
    tiles: float = eqx.field(static=True)


def motion_units(bvh: BVHMotion, *, source=None) -> float:
    """Metres per unit of the file: the one of m, cm, mm, inch that makes the hips 0.5-1.5 m high."""
    motion = pose_motion(bvh, scale=1.0)
    joints = performer_joints(bvh.names, source=source)
    p = np.asarray(motion.positions[0])
    feet = min(p[joints["foot_L"], 1], p[joints["foot_R"], 1])
    height = abs(float(p[joints["neck"], 1] - feet))
    return min((1.0, 0.01, 0.0254, 0.001), key=lambda u: abs(math.log(max(height * u, 1e-9) / 1.28)))


def stage_motion(bvh: BVHMotion, *, duration: float, source=None) -> tuple[SkeletonMotion, dict[str, int]]:
    """The motion in metres, turned to face the audience at its first frame, its path over
    `duration` seconds centred on `STAGE_SPOT`, its lowest foot on the floor at frame 0, its arms
    moved out to the body's shoulder width (`sims.costume.fit_shoulders`)."""
    joints = performer_joints(bvh.names, source=source)
    motion = fit_shoulders(pose_motion(bvh, scale=motion_units(bvh, source=source)), joints, bvh.parents)
    p = np.asarray(motion.positions, np.float64)
    left = p[0, joints["upper_leg_L"]] - p[0, joints["upper_leg_R"]]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    yaw = -math.atan2(forward[0], forward[2])
    turned = place_motion(motion, yaw=yaw, shift=(0.0, 0.0, 0.0))
    used = min(motion.frames, int(round(duration / motion.frame_time)) + 1)
    hips = np.asarray(turned.positions[:used, joints["hips"]], np.float64)
    centre = 0.5 * (hips.min(axis=0) + hips.max(axis=0))
    volumes = body_volumes(turned, joints)
    a, b = (np.asarray(e) for e in volumes.ends(turned.positions[0], turned.rotations[0]))
    feet = [i for i, n in enumerate(volumes.names) if n.startswith(("foot", "toes", "shin"))]
    lowest = float(np.min(np.minimum(a[feet, 1], b[feet, 1]) - np.asarray(volumes.radius)[feet]))
    shift = (STAGE_SPOT[0] - centre[0], 0.004 - lowest, STAGE_SPOT[1] - centre[2])
    placed = place_motion(turned, yaw=0.0, shift=shift)
    _check_reach(placed, bvh.names, used, source)
    return placed, joints


def _check_reach(motion: SkeletonMotion, names, used: int, source) -> None:
    """A motion whose joints leave the stage (a joint flung metres away: a file whose channels mean
    something else) is refused: it cannot be danced there, and no frame buffer could hold it."""
    p = np.asarray(motion.positions[:used], np.float64)
    spot = np.asarray([STAGE_SPOT[0], 0.0, STAGE_SPOT[1]])
    reach = np.linalg.norm(np.nan_to_num(p - spot, nan=np.inf), axis=-1)
    frame, joint = np.unravel_index(np.argmax(reach), reach.shape)
    if not reach[frame, joint] <= MAX_REACH:
        raise InputError(source, f"joint {names[joint]!r} is {reach[frame, joint]:.3g} m from the middle of the stage "
                                 f"at frame {frame} (in metres as read: the Noh stage holds a performer within "
                                 f"{MAX_REACH:g} m)")


def noh_scene(*, width: int = 720, height: int = 480, frames: int = 20, key: PRNGKeyArray | None = None,
              mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
              env: EnvMap | None = None, motion: BVHMotion | None = None, motion_source=None,
              duration: float = 6.0, robe: dict | None = None, tiles: float = 10.0,
              flame_size: tuple[int, int] = (128, 64), fire_intensity: float = 60.0, btf_size: int = 32,
              pyramid: str = "em") -> NohScene:
    """Assemble the scene; every input not given is the built-in one (module docstring). `motion`:
    a BVH motion (default `sims.noh_dance`); `robe`: `sims.costume.dress_performer` keywords."""
    key = jax.random.key(2024) if key is None else key
    dtype = default_float()
    eye, target, fov = CAMERA
    cam = Camera(eye, target, (0.0, 1.0, 0.0), fov, width=width, height=height)
    placed, joints = stage_motion(noh_dance() if motion is None else motion, duration=duration, source=motion_source)
    costume = dress_performer(placed, joints, **(robe or {}))
    performer = performer_rig(costume, placed, joints, body_scale(placed, joints))
    centers, us, vs = [], [], []
    w, h = FLAME_SIZE
    for x, z in FIRE_SITES:
        to_cam = np.asarray([eye[0] - x, 0.0, eye[2] - z])
        to_cam /= np.linalg.norm(to_cam)
        right = np.cross([0.0, 1.0, 0.0], to_cam)
        centers.append([x, FLAME_BASE + h / 2, z])
        us.append(right * w / 2)
        vs.append([0.0, h / 2, 0.0])
    keys = jax.random.split(key, len(FIRE_SITES))
    flames = jnp.stack([fire_frames(k, frames=frames, height=flame_size[0], width=flame_size[1],
                                    intensity=fire_intensity) for k in keys]).astype(dtype)
    fires = QuadLights(jnp.asarray(centers, dtype=dtype), jnp.asarray(np.asarray(us), dtype=dtype),
                       jnp.asarray(vs, dtype=dtype), flames[:, 0])
    robe_rgb = default_mask(ATLAS, body_rows=(robe or {}).get("rows", 30)) if mask_rgb is None else mask_rgb
    rows = (np.arange(ATLAS) * robe_rgb.shape[0]) // ATLAS
    cols = (np.arange(ATLAS) * robe_rgb.shape[1]) // ATLAS
    robe_labels, robe_colours = mask_from_rgb(np.asarray(robe_rgb)[rows][:, cols])
    body_labels, body_colours = body_page(ATLAS)
    labels = np.concatenate([robe_labels, body_labels])
    colours = np.concatenate([robe_colours, body_colours])
    btfs = default_btfs(size=btf_size, pyramid=pyramid) if btfs is None else btfs
    missing = [name for name in LABELS if name not in btfs]
    if missing:
        fallback = default_btfs(size=btf_size, pyramid=pyramid)
        btfs = {**{n: fallback[n] for n in missing}, **btfs}
    mats = stack_materials([btfs[name] for name in LABELS])
    env = default_environment(irradiance=SKY_IRRADIANCE) if env is None else env
    return NohScene(cam, fires, flames, jnp.asarray(labels), jnp.asarray(colours, dtype=dtype), mats, env,
                    build_stage(), performer, float(tiles))
