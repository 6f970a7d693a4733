"""A motion-captured skeleton: its forward kinematics in JAX for every frame of a BVH motion, and
the posed joints sampled at any time between frames.

How BVH channels are read (position channels replace the offset, rotations compose in the
listed order): docs/noh.md, "Motion capture".
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrender.io import BVHMotion
from jaxrender.maths import default_float

__all__ = ["Skeleton", "SkeletonMotion", "skeleton_from_bvh", "forward_kinematics", "pose_motion", "place_motion",
           "euler_zxy"]

_AXIS = {"X": 0, "Y": 1, "Z": 2}


class Skeleton(eqx.Module):
    """The hierarchy and where each joint reads its channels (columns of a motion row; -1: none).

    A joint's local translation is its offset, with each component that has a position channel
    replaced by that channel; its local rotation is the product of its rotation channels' axis
    rotations in the order listed (`Zrotation Xrotation Yrotation`: R = Rz Rx Ry)."""

    names: tuple[str, ...] = eqx.field(static=True)
    parents: tuple[int, ...] = eqx.field(static=True)
    position_column: tuple[tuple[int, int, int], ...] = eqx.field(static=True)
    rotation_column: tuple[tuple[int, ...], ...] = eqx.field(static=True)   # padded with -1
    rotation_axis: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    offsets: Float[Array, "J 3"]

    @property
    def joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)


class SkeletonMotion(eqx.Module):
    """The posed skeleton at every frame: world positions and rotations of the joints."""

    positions: Float[Array, "F J 3"]
    rotations: Float[Array, "F J 3 3"]
    frame_time: float = eqx.field(static=True)

    @property
    def frames(self) -> int:
        return self.positions.shape[0]

    @property
    def duration(self) -> float:
        return (self.frames - 1) * self.frame_time

    def at(self, t: Float[Array, ""]) -> tuple[Float[Array, "J 3"], Float[Array, "J 3 3"]]:
        """(positions, rotations) at time t (s): linear between the two frames around t, the
        first/last frame before/after the motion. Exactly the frame's pose at t = k frame_time."""
        f = jnp.clip(t / self.frame_time, 0.0, self.frames - 1)
        i0 = jnp.clip(jnp.floor(f).astype(jnp.int32), 0, max(self.frames - 2, 0))
        i1 = jnp.minimum(i0 + 1, self.frames - 1)
        w = (f - i0.astype(f.dtype)).astype(self.positions.dtype)
        pos = (1 - w) * self.positions[i0] + w * self.positions[i1]
        rot = (1 - w) * self.rotations[i0] + w * self.rotations[i1]
        return pos, rot


def skeleton_from_bvh(bvh: BVHMotion) -> Skeleton:
    """The skeleton of a BVH file (offsets in the file's unit)."""
    position, rot_col, rot_axis = [], [], []
    width = max([sum(c.endswith("rotation") for c in ch) for ch in bvh.channels] + [1])
    for cols, channels in zip(bvh.channel_columns(), bvh.channels):
        pos = [-1, -1, -1]
        rc, ra = [], []
        for col, name in zip(cols, channels):
            if name.endswith("position"):
                pos[_AXIS[name[0]]] = col
            else:
                rc.append(col)
                ra.append(_AXIS[name[0]])
        position.append(tuple(pos))
        rot_col.append(tuple(rc + [-1] * (width - len(rc))))
        rot_axis.append(tuple(ra + [0] * (width - len(ra))))
    return Skeleton(bvh.names, bvh.parents, tuple(position), tuple(rot_col), tuple(rot_axis),
                    jnp.asarray(bvh.offsets, default_float()))


def _axis_rotation(axis: Array, angle: Array) -> Array:
    """Rotation matrices (... 3 3) by `angle` (radians) about the coordinate axis `axis` (0, 1, 2)."""
    e = jax.nn.one_hot(axis, 3, dtype=angle.dtype)                         # ... 3
    c, s = jnp.cos(angle)[..., None, None], jnp.sin(angle)[..., None, None]
    cross = jnp.stack([jnp.stack([jnp.zeros_like(e[..., 0]), -e[..., 2], e[..., 1]], -1),
                       jnp.stack([e[..., 2], jnp.zeros_like(e[..., 0]), -e[..., 0]], -1),
                       jnp.stack([-e[..., 1], e[..., 0], jnp.zeros_like(e[..., 0])], -1)], -2)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=angle.dtype), cross.shape)
    return c * eye + s * cross + (1 - c) * e[..., :, None] * e[..., None, :]


def forward_kinematics(skeleton: Skeleton, channels: Float[Array, "F C"], *, scale: float = 1.0
                       ) -> tuple[Float[Array, "F J 3"], Float[Array, "F J 3 3"]]:
    """World positions and rotations of every joint at every frame (`channels`: a BVH motion,
    degrees); lengths times `scale`. Parents are composed before children (file order)."""
    dtype = skeleton.offsets.dtype
    channels = jnp.asarray(channels, dtype)
    n_frames = channels.shape[0]
    padded = jnp.concatenate([channels, jnp.zeros((n_frames, 1), dtype)], axis=1)   # column -1: zero
    pos_col = jnp.asarray(skeleton.position_column, jnp.int32)                      # J 3
    local_t = jnp.where(pos_col[None] >= 0, padded[:, pos_col], skeleton.offsets[None]) * scale   # F J 3
    rot_col = jnp.asarray(skeleton.rotation_column, jnp.int32)                      # J R
    angles = jnp.deg2rad(padded[:, rot_col])                                         # F J R (padding: 0)
    axes = jnp.broadcast_to(jnp.asarray(skeleton.rotation_axis, jnp.int32)[None], angles.shape)
    each = _axis_rotation(axes, angles)                                              # F J R 3 3
    local_r = each[:, :, 0]
    for k in range(1, each.shape[2]):
        local_r = local_r @ each[:, :, k]
    n_joints = skeleton.joints
    parents = jnp.asarray([p if p >= 0 else n_joints for p in skeleton.parents], jnp.int32)
    world_r = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (n_joints + 1, n_frames, 3, 3))
    world_t = jnp.zeros((n_joints + 1, n_frames, 3), dtype)

    def joint(carry, j):
        wr, wt = carry
        p = parents[j]
        r = wr[p] @ local_r[:, j]
        t = wt[p] + jnp.einsum("fab,fb->fa", wr[p], local_t[:, j])
        return (wr.at[j].set(r), wt.at[j].set(t)), None

    (world_r, world_t), _ = jax.lax.scan(joint, (world_r, world_t), jnp.arange(n_joints))
    return jnp.swapaxes(world_t[:n_joints], 0, 1), jnp.swapaxes(world_r[:n_joints], 0, 1)


def pose_motion(bvh: BVHMotion, *, scale: float = 1.0) -> SkeletonMotion:
    """Forward kinematics of every frame of `bvh` (jitted), lengths times `scale`."""
    skeleton = skeleton_from_bvh(bvh)
    positions, rotations = _fk_jit(skeleton, jnp.asarray(bvh.motion, default_float()), scale)
    return SkeletonMotion(positions, rotations, float(bvh.frame_time))


_fk_jit = eqx.filter_jit(lambda s, c, scale: forward_kinematics(s, c, scale=scale))


def place_motion(motion: SkeletonMotion, *, yaw: float, shift: tuple[float, float, float]) -> SkeletonMotion:
    """The motion turned by `yaw` (radians, about +y) and then moved by `shift`."""
    c, s = np.cos(yaw), np.sin(yaw)
    dtype = motion.positions.dtype
    turn = jnp.asarray([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype)
    positions = motion.positions @ turn.T + jnp.asarray(shift, dtype)
    return SkeletonMotion(positions, jnp.einsum("ab,fjbc->fjac", turn, motion.rotations), motion.frame_time)


def euler_zxy(rotation: np.ndarray) -> np.ndarray:
    """Angles (degrees) (z, x, y) with rotation = Rz(z) Rx(x) Ry(y), for `... 3 3` matrices (numpy):
    the channels `Zrotation Xrotation Yrotation` that give this rotation."""
    r = np.asarray(rotation, np.float64)
    x = np.arcsin(np.clip(r[..., 2, 1], -1.0, 1.0))
    z = np.arctan2(-r[..., 0, 1], r[..., 1, 1])
    y = np.arctan2(-r[..., 2, 0], r[..., 2, 2])
    return np.degrees(np.stack([z, x, y], -1))
