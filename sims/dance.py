"""The built-in Noh motion: a procedural dance written as a BVH motion (`noh_dance`), so that it
takes the same path as a captured one. Kamae (the basic stance), suriashi (three sliding steps),
a slow turn, and the right sleeve raised before the face and lowered.

The choreography and how the joint angles are found (aiming bones, two-bone leg IK, ZXY Euler
channels): docs/noh.md, "The built-in motion".
"""

from __future__ import annotations

import numpy as np

from jaxrender.io import BVHMotion

from .skeleton import euler_zxy

__all__ = ["noh_dance", "NOH_SKELETON"]

# (name, parent, offset cm): y up, the performer facing +z, its left = +x; arms along +-x
NOH_SKELETON = (
    ("Hips", None, (0.0, 95.0, 0.0)),
    ("Spine", "Hips", (0.0, 10.0, 0.0)),
    ("Chest", "Spine", (0.0, 16.0, 0.0)),
    ("Neck", "Chest", (0.0, 21.0, 0.0)),
    ("Head", "Neck", (0.0, 9.0, 0.0)),
    ("Head_end", "Head", (0.0, 20.0, 0.0)),
    ("Shoulder_L", "Chest", (3.0, 17.0, 0.0)),
    ("UpperArm_L", "Shoulder_L", (14.0, 0.0, 0.0)),
    ("LowerArm_L", "UpperArm_L", (27.0, 0.0, 0.0)),
    ("Hand_L", "LowerArm_L", (24.0, 0.0, 0.0)),
    ("Hand_L_end", "Hand_L", (16.0, 0.0, 0.0)),
    ("Shoulder_R", "Chest", (-3.0, 17.0, 0.0)),
    ("UpperArm_R", "Shoulder_R", (-14.0, 0.0, 0.0)),
    ("LowerArm_R", "UpperArm_R", (-27.0, 0.0, 0.0)),
    ("Hand_R", "LowerArm_R", (-24.0, 0.0, 0.0)),
    ("Hand_R_end", "Hand_R", (-16.0, 0.0, 0.0)),
    ("UpperLeg_L", "Hips", (9.0, -4.0, 0.0)),
    ("LowerLeg_L", "UpperLeg_L", (0.0, -42.0, 0.0)),
    ("Foot_L", "LowerLeg_L", (0.0, -42.0, 0.0)),
    ("Toes_L", "Foot_L", (0.0, -5.0, 13.0)),
    ("Toes_L_end", "Toes_L", (0.0, 0.0, 6.0)),
    ("UpperLeg_R", "Hips", (-9.0, -4.0, 0.0)),
    ("LowerLeg_R", "UpperLeg_R", (0.0, -42.0, 0.0)),
    ("Foot_R", "LowerLeg_R", (0.0, -42.0, 0.0)),
    ("Toes_R", "Foot_R", (0.0, -5.0, 13.0)),
    ("Toes_R_end", "Toes_R", (0.0, 0.0, 6.0)),
)
_UP, _FORWARD = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])


def _smooth(t, t0, t1):
    """0 before t0, 1 after t1, smoothstep between (zero velocity at both ends)."""
    u = np.clip((np.asarray(t, np.float64) - t0) / (t1 - t0), 0.0, 1.0)
    return u * u * (3 - 2 * u)


def _yaw(angle):
    """Rotations about +y by `angle` (radians, array): (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _about(axis, angle):
    """Rotations by `angle` (radians, array F) about the unit vectors `axis` (F 3), Rodrigues."""
    k = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    c, s = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    cross = np.zeros(k.shape[:-1] + (3, 3))
    cross[..., 0, 1], cross[..., 0, 2], cross[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    cross = cross - np.swapaxes(cross, -1, -2)
    return c * np.eye(3) + s * cross + (1 - c) * k[..., :, None] * k[..., None, :]


def _aim(rest_dir, rest_ref, target, ref):
    """The rotations (F 3 3) taking the unit `rest_dir` to the direction `target` (F 3), turning
    `rest_ref` toward `ref` (F 3) about it (both references made orthogonal to their directions)."""
    def frame(d, r):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        r = r - np.sum(r * d, -1, keepdims=True) * d
        r = r / np.linalg.norm(r, axis=-1, keepdims=True)
        return np.stack([d, r, np.cross(d, r)], -1)                     # columns
    rest = frame(np.broadcast_to(rest_dir, target.shape), np.broadcast_to(rest_ref, target.shape))
    return frame(target, ref) @ np.swapaxes(rest, -1, -2)


def _lerp_dir(a, b, w):
    d = (1 - w)[:, None] * a + w[:, None] * b
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _leg(hip, ankle, forward, thigh, shin):
    """Two-bone IK: the knee (F 3) with the knee bending toward `forward`."""
    d_vec = ankle - hip
    d = np.clip(np.linalg.norm(d_vec, axis=-1), 1e-6, 0.999 * (thigh + shin))
    u = d_vec / np.linalg.norm(d_vec, axis=-1, keepdims=True)
    k = forward - np.sum(forward * u, -1, keepdims=True) * u
    k = k / np.linalg.norm(k, axis=-1, keepdims=True)
    cos_a = np.clip((thigh ** 2 + d ** 2 - shin ** 2) / (2 * thigh * d), -1.0, 1.0)
    return hip + thigh * (cos_a[:, None] * u + np.sqrt(1 - cos_a ** 2)[:, None] * k)


def noh_dance(*, duration: float = 8.0, fps: float = 30.0, step: float = 0.28, turn_deg: float = 80.0,
              crouch: float = 6.0, lean_deg: float = 8.0) -> BVHMotion:
    """The built-in Noh motion (module docstring) as a BVH motion in centimetres at `fps`:
    three suriashi steps of `step` x 100 cm from 0.6 s, a slow turn of `turn_deg` to the left
    from 3 s (and back from 6.3 s), the right sleeve raised before the face from 4.2 s and
    lowered by 7 s; the hips `crouch` cm low and the body leaning `lean_deg` forward (kamae).
    Times scale with `duration` / 8."""
    names = [n for n, _, _ in NOH_SKELETON]
    index = {n: i for i, n in enumerate(names)}
    offsets = {n: np.asarray(o) for n, _, o in NOH_SKELETON}
    n_frames = int(round(duration * fps)) + 1
    k = duration / 8.0
    t = np.arange(n_frames) / fps / k                                   # the 8-second score
    # suriashi: right foot, left foot (passing it), right foot closing; the hips between the feet
    s = 100 * step
    right = s * (_smooth(t, 0.6, 1.4) + 0.5 * _smooth(t, 2.2, 3.0))
    left = 1.5 * s * _smooth(t, 1.4, 2.2)
    lift = np.sin(np.pi * np.clip((t - 0.6) / 2.4 * 3, 0, 3)) ** 2 * (t < 3.0)   # toes rise at each slide's end
    body_z = 0.5 * (right + left)
    yaw = np.radians(turn_deg) * (_smooth(t, 3.0, 5.0) - _smooth(t, 6.3, 8.0))
    raise_w = _smooth(t, 4.2, 5.4) - _smooth(t, 6.0, 7.0)
    turn = _yaw(yaw)
    hips_y = offsets["Hips"][1] - crouch
    hips = np.stack([np.zeros_like(t), np.full_like(t, hips_y), body_z], -1)

    def world(local):   # body-local points (F 3) -> world, turned about the hips' vertical axis
        rel = local - hips * np.array([1.0, 0.0, 1.0])
        return hips * np.array([1.0, 0.0, 1.0]) + np.einsum("fab,fb->fa", turn, rel)

    forward = turn @ _FORWARD
    left_axis = turn @ np.array([1.0, 0.0, 0.0])
    rot = {}
    lean = np.radians(lean_deg)
    rot["Hips"] = turn
    rot["Spine"] = turn @ _about(np.broadcast_to([1.0, 0.0, 0.0], (len(t), 3)), np.full_like(t, 0.4 * lean))
    rot["Chest"] = turn @ _about(np.broadcast_to([1.0, 0.0, 0.0], (len(t), 3)), np.full_like(t, lean))
    rot["Neck"] = turn @ _about(np.broadcast_to([1.0, 0.0, 0.0], (len(t), 3)), np.full_like(t, 0.3 * lean))
    rot["Head"] = turn @ _about(np.broadcast_to([1.0, 0.0, 0.0], (len(t), 3)), -0.2 * raise_w * lean)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        rot[f"Shoulder_{side}"] = rot["Chest"]
        out = sign * left_axis
        down = -np.broadcast_to(_UP, forward.shape)
        upper = _lerp_dir(0.45 * out + down + 0.35 * forward, 0.0 * out, np.zeros_like(t))
        lower = _lerp_dir(0.05 * out + 0.5 * down + 0.8 * forward, 0.0 * out, np.zeros_like(t))
        if side == "R":   # the sleeve raised: the elbow up before the shoulder, the hand before the face
            upper = _lerp_dir(upper, 0.5 * out + 0.35 * _UP + 0.75 * forward, raise_w)
            lower = _lerp_dir(lower, -0.5 * out + 0.65 * _UP + 0.45 * forward, raise_w)
        hand = _lerp_dir(lower, down, np.full_like(t, 0.25))
        rest = np.array([sign, 0.0, 0.0])
        rot[f"UpperArm_{side}"] = _aim(rest, _FORWARD, upper, forward + 0.5 * down)
        rot[f"LowerArm_{side}"] = _aim(rest, _FORWARD, lower, -down + 0.1 * forward)
        rot[f"Hand_{side}"] = _aim(rest, _FORWARD, hand, -down + 0.1 * forward)
        rot[f"Hand_{side}_end"] = rot[f"Hand_{side}"]
        # the leg: hip joint from the pelvis, ankle on the floor at this foot's slide
        foot_z = right if side == "R" else left
        hip = hips + np.einsum("fab,b->fa", turn, offsets[f"UpperLeg_{side}"])
        ankle_y = offsets["Hips"][1] + offsets[f"UpperLeg_{side}"][1] + 2 * offsets[f"LowerLeg_{side}"][1]
        ankle = world(np.stack([np.full_like(t, sign * 9.0), np.full_like(t, ankle_y), foot_z], -1))
        thigh, shin = -offsets[f"LowerLeg_{side}"][1], -offsets[f"Foot_{side}"][1]
        knee = _leg(hip, ankle, forward, thigh, shin)
        rot[f"UpperLeg_{side}"] = _aim(np.array([0.0, -1.0, 0.0]), _FORWARD, knee - hip, forward)
        rot[f"LowerLeg_{side}"] = _aim(np.array([0.0, -1.0, 0.0]), _FORWARD, ankle - knee, forward)
        toe_lift = 0.2 * lift * (np.abs(np.gradient(foot_z)) > 1e-3)
        rot[f"Foot_{side}"] = turn @ _about(np.broadcast_to([1.0, 0.0, 0.0], (len(t), 3)), -toe_lift)
        rot[f"Toes_{side}"] = rot[f"Foot_{side}"]
        rot[f"Toes_{side}_end"] = rot[f"Foot_{side}"]
    rot["Head_end"] = rot["Head"]
    columns, channels, parents = [], [], []
    for name, parent, _ in NOH_SKELETON:
        parents.append(-1 if parent is None else index[parent])
        if name.endswith("_end"):
            channels.append(())
            continue
        local = rot[name] if parent is None else np.swapaxes(rot[parent], -1, -2) @ rot[name]
        angles = euler_zxy(local)
        if parent is None:
            columns.append(hips)
            channels.append(("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"))
        else:
            channels.append(("Zrotation", "Xrotation", "Yrotation"))
        columns.append(angles)
    motion = np.concatenate(columns, axis=1)
    return BVHMotion(tuple(names), tuple(parents), np.asarray([o for _, _, o in NOH_SKELETON], np.float64),
                     tuple(channels), tuple(n.endswith("_end") for n in names), 1.0 / fps, motion)
