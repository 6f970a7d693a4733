"""A Noh costume on a motion-captured performer (paper 004 section 4.3): body volumes around the
skeleton's bones (`body_volumes`), a kosode-cut robe with a collar and wide sleeves made around
the first pose (`dress_performer`), and its Verlet simulation following the motion
(`advance_costume`): spring-dampers between vertices, the collar, chest and waist vertices fixed
to the skeleton, every other vertex kept outside the body's volumes.

The garment's cut, the volumes, the constraints and the uv layout: docs/noh.md, "The costume".
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.errors import InputError
from jaxrender.maths import default_float, dot

from .cloth import ClothSprings, ClothState, scan_frames, vertex_normals
from .skeleton import SkeletonMotion

__all__ = ["JOINT_NAMES", "BodyVolumes", "Costume", "performer_joints", "body_volumes", "dress_performer",
           "advance_costume", "costume_frames", "fixed_positions", "volume_penetration", "costume_normals",
           "COSTUME_LAYOUT", "body_scale", "fit_shoulders", "ROBE_MARGIN"]

# role -> accepted joint names (Bandai Namco, CMU, Mixamo without its "mixamorig:" prefix)
JOINT_NAMES = {
    "hips": ("Hips", "hip", "pelvis"),
    "spine": ("Spine", "LowerBack", "abdomen"),
    "chest": ("Chest", "Spine1", "Spine2", "chest", "UpperChest"),
    "neck": ("Neck", "neck", "Neck1"),
    "head": ("Head", "head"),
    **{f"{part}_{s}": names for s, side in (("L", "Left"), ("R", "Right")) for part, names in (
        ("shoulder", (f"Shoulder_{s}", f"{side}Shoulder", f"{s.lower()}Collar")),
        ("upper_arm", (f"UpperArm_{s}", f"{side}Arm", f"{side}UpperArm", f"{s.lower()}Shldr")),
        ("lower_arm", (f"LowerArm_{s}", f"{side}ForeArm", f"{side}LowerArm", f"{s.lower()}ForeArm")),
        ("hand", (f"Hand_{s}", f"{side}Hand", f"{s.lower()}Hand")),
        ("upper_leg", (f"UpperLeg_{s}", f"{side}UpLeg", f"{side}UpperLeg", f"{s.lower()}Thigh")),
        ("lower_leg", (f"LowerLeg_{s}", f"{side}Leg", f"{side}LowerLeg", f"{s.lower()}Shin")),
        ("foot", (f"Foot_{s}", f"{side}Foot", f"{s.lower()}Foot")),
        ("toes", (f"Toes_{s}", f"{side}ToeBase", f"{side}Toe", f"{s.lower()}Toe")),
    )},
}
_OPTIONAL = {"shoulder_L", "shoulder_R", "toes_L", "toes_R"}

# where each piece's own (s, t) in [0, 1]^2 lies in the garment's uv: (u0, v0, du, dv)
COSTUME_LAYOUT = {"body": (0.0, 0.0, 0.5, 0.62), "sleeve_L": (0.52, 0.0, 0.46, 0.3),
                  "sleeve_R": (0.52, 0.32, 0.46, 0.3)}
COLLAR_ROWS = 2     # the body's top rows: the collar band (fixed to the chest)
ROBE_MARGIN = 0.012  # m: how far outside the body's volumes the robe's vertices are kept


def performer_joints(names: tuple[str, ...], *, source: str | None = None) -> dict[str, int]:
    """Joint index of every body role (`JOINT_NAMES`); `InputError` naming `source` if one is missing."""
    plain = [n.split(":")[-1] for n in names]
    out = {}
    for role, candidates in JOINT_NAMES.items():
        found = next((plain.index(c) for c in candidates if c in plain), None)
        if found is None and role not in _OPTIONAL:
            raise InputError(source, f"no joint for the {role.replace('_', ' ')} (looked for {', '.join(candidates)})")
        if found is not None:
            out[role] = found
    return out


class BodyVolumes(eqx.Module):
    """Capsules around the bones' centre lines: end k of capsule b is joint `joint_k[b]` plus
    `local_k[b]` in that joint's frame (0 for a joint itself); radius in metres."""

    joint_a: Int[Array, " B"]
    local_a: Float[Array, "B 3"]
    joint_b: Int[Array, " B"]
    local_b: Float[Array, "B 3"]
    radius: Float[Array, " B"]
    names: tuple[str, ...] = eqx.field(static=True)

    def ends(self, positions: Float[Array, "J 3"], rotations: Float[Array, "J 3 3"]
             ) -> tuple[Float[Array, "B 3"], Float[Array, "B 3"]]:
        a = positions[self.joint_a] + jnp.einsum("bij,bj->bi", rotations[self.joint_a], self.local_a)
        b = positions[self.joint_b] + jnp.einsum("bij,bj->bi", rotations[self.joint_b], self.local_b)
        return a, b


def body_scale(motion: SkeletonMotion, joints: dict[str, int]) -> float:
    """The performer's size relative to a 1.65 m figure: neck height above the ankles at frame 0 / 1.28 m."""
    p = np.asarray(motion.positions[0])
    ankle = min(p[joints["foot_L"], 1], p[joints["foot_R"], 1])
    return float((p[joints["neck"], 1] - ankle) / 1.28)


def body_volumes(motion: SkeletonMotion, joints: dict[str, int]) -> BodyVolumes:
    """The performer's volumes (docs/noh.md): torso, neck and head, clavicles, arms and hands,
    legs and feet, and two bars across the shoulders and the hips for the body's width; radii
    scaled by `body_scale`. A bone end the skeleton lacks (a head top, a hand's end) is placed
    along its bone's direction at frame 0 and carried in that joint's frame."""
    s = body_scale(motion, joints)
    p0, r0 = np.asarray(motion.positions[0], np.float64), np.asarray(motion.rotations[0], np.float64)
    rows = []

    def joint_end(j):
        return (j, np.zeros(3))

    def beyond(j, from_j, length):
        d = p0[j] - p0[from_j]
        d = d / max(np.linalg.norm(d), 1e-9) * length
        return (j, r0[j].T @ d)

    def add(name, a, b, radius):
        rows.append((name, a, b, radius * s))

    add("pelvis", joint_end(joints["hips"]), joint_end(joints["spine"]), 0.11)
    add("belly", joint_end(joints["spine"]), joint_end(joints["chest"]), 0.11)
    add("chest", joint_end(joints["chest"]), joint_end(joints["neck"]), 0.10)
    add("neck", joint_end(joints["neck"]), joint_end(joints["head"]), 0.05)
    head, head_length, head_radius = joints["head"], 0.11, 0.09
    add("head", joint_end(head), beyond(head, joints["neck"], head_length * s), head_radius)
    # the face: around the Noh mask that the performer's rig binds at this capsule's middle (its
    # nose 7.7 cm before it, its rim inside the head's volume), so that the robe stays off the mask
    up = p0[head] - p0[joints["neck"]]
    up /= max(np.linalg.norm(up), 1e-9)
    forward = np.cross(p0[joints["upper_leg_L"]] - p0[joints["upper_leg_R"]], up)
    forward /= max(np.linalg.norm(forward), 1e-9)
    # the head's middle, 12 mm down and 3.5 cm inside its front
    face = p0[head] + (head_length / 2 - 0.012) * s * up + (head_radius - 0.035) * s * forward
    at_head = lambda point: (head, r0[head].T @ (point - p0[head]))  # noqa: E731
    add("face", at_head(face - 0.05 * s * up), at_head(face + 0.05 * s * up), 0.08)
    add("shoulders", joint_end(joints["upper_arm_L"]), joint_end(joints["upper_arm_R"]), 0.05)
    add("hip_bar", joint_end(joints["upper_leg_L"]), joint_end(joints["upper_leg_R"]), 0.085)
    for side in ("L", "R"):
        if f"shoulder_{side}" in joints:
            add(f"clavicle_{side}", joint_end(joints[f"shoulder_{side}"]), joint_end(joints[f"upper_arm_{side}"]), 0.05)
        add(f"upper_arm_{side}", joint_end(joints[f"upper_arm_{side}"]), joint_end(joints[f"lower_arm_{side}"]), 0.045)
        add(f"lower_arm_{side}", joint_end(joints[f"lower_arm_{side}"]), joint_end(joints[f"hand_{side}"]), 0.037)
        add(f"hand_{side}", joint_end(joints[f"hand_{side}"]),
            beyond(joints[f"hand_{side}"], joints[f"lower_arm_{side}"], 0.09 * s), 0.03)
        add(f"thigh_{side}", joint_end(joints[f"upper_leg_{side}"]), joint_end(joints[f"lower_leg_{side}"]), 0.07)
        add(f"shin_{side}", joint_end(joints[f"lower_leg_{side}"]), joint_end(joints[f"foot_{side}"]), 0.05)
        foot = joints[f"foot_{side}"]
        toes = joints.get(f"toes_{side}")
        tip = beyond(toes, foot, 0.06 * s) if toes is not None else beyond(foot, joints[f"lower_leg_{side}"], 0.0)
        if toes is not None:
            add(f"foot_{side}", joint_end(foot), joint_end(toes), 0.04)
            add(f"toes_{side}", joint_end(toes), tip, 0.035)
        else:
            add(f"foot_{side}", joint_end(foot), (foot, r0[foot].T @ (0.15 * s * _forward(p0, joints))), 0.04)
    dtype = default_float()
    return BodyVolumes(jnp.asarray([r[1][0] for r in rows], jnp.int32), jnp.asarray([r[1][1] for r in rows], dtype),
                       jnp.asarray([r[2][0] for r in rows], jnp.int32), jnp.asarray([r[2][1] for r in rows], dtype),
                       jnp.asarray([r[3] for r in rows], dtype), tuple(r[0] for r in rows))


def fit_shoulders(motion: SkeletonMotion, joints: dict[str, int], parents: tuple[int, ...]) -> SkeletonMotion:
    """The motion with each arm moved out to the body's shoulder width: where a skeleton's
    shoulder joint lies closer to the chest's centre line at frame 0 than the chest's and the
    upper arm's radii plus room for the robe between them (2 x `ROBE_MARGIN`), that arm's joints
    (the upper arm and everything below it in `parents`) are shifted outwards, away from the
    chest's centre line, by the difference at every frame; rotations are kept. A narrow-shouldered
    capture (dance-short_normal_001.bvh: 10 cm from the centre line where the volumes need 16 cm)
    would otherwise hang its upper arms 5 cm inside the chest's volume, leaving the sleeve no
    room between them (docs/noh.md, "The costume"). A skeleton as wide as its volumes is
    returned unchanged."""
    volumes = body_volumes(motion, joints)
    radius = dict(zip(volumes.names, np.asarray(volumes.radius, np.float64)))
    p = np.asarray(motion.positions, np.float64)
    axis = p[:, joints["neck"]] - p[:, joints["chest"]]
    axis /= np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    left = p[:, joints["upper_leg_L"]] - p[:, joints["upper_leg_R"]]    # the fallback on the centre line
    shifted = p.copy()
    for side, sign in (("L", 1.0), ("R", -1.0)):
        arm = [joints[f"upper_arm_{side}"]]
        for j in range(arm[0] + 1, len(parents)):                       # parents come before children
            if parents[j] in arm:
                arm.append(j)
        out = p[:, arm[0]] - p[:, joints["chest"]]
        out -= np.sum(out * axis, -1, keepdims=True) * axis             # F 3: from the centre line
        width = np.linalg.norm(out, axis=-1)
        lack = radius["chest"] + radius[f"upper_arm_{side}"] + 2 * ROBE_MARGIN - width[0]
        if lack <= 0:
            continue
        away = np.where(width[:, None] > 1e-6, out, sign * left)
        away /= np.maximum(np.linalg.norm(away, axis=-1, keepdims=True), 1e-12)
        shifted[:, arm] += lack * away[:, None]
    if np.array_equal(shifted, p):
        return motion
    return SkeletonMotion(jnp.asarray(shifted, motion.positions.dtype), motion.rotations, motion.frame_time)


def _forward(p0: np.ndarray, joints: dict[str, int]) -> np.ndarray:
    """The performer's facing direction at frame 0 (horizontal): left (hip to hip) x up."""
    left = p0[joints["upper_leg_L"]] - p0[joints["upper_leg_R"]]
    left[1] = 0.0
    left /= max(np.linalg.norm(left), 1e-9)
    return np.cross(left, [0.0, 1.0, 0.0])


class Costume(eqx.Module):
    """The robe's simulation rig (`dress_performer`). Simulated vertices N; the rendered mesh
    duplicates the vertices along the uv seams (`render_index` maps each rendered vertex to its
    simulated one) so that uv never wraps inside a triangle."""

    state: ClothState
    springs: ClothSprings
    fixed_index: Int[Array, " P"]        # vertices fixed to the skeleton
    fixed_joint: Int[Array, " P"]
    fixed_local: Float[Array, "P 3"]     # ... their position in that joint's frame
    body: BodyVolumes
    render_index: Int[Array, " R"]
    uv: Float[Array, "R 2"]
    triangles: Int[Array, "T 3"]         # into the rendered vertices
    sim_triangles: Int[Array, "T 3"]     # the same triangles, into the simulated vertices
    edges: Int[Array, "E 2"]             # the triangles' edges (simulated vertices), kept outside the volumes
    inverse_mass: Float[Array, " N"]     # 1 for a free vertex, 0 for a fixed one (the edges' pushes)
    dt: float = eqx.field(static=True)
    mass: float = eqx.field(static=True)
    damping: float = eqx.field(static=True)          # air drag, 1/s
    spring_damping: float = eqx.field(static=True)   # along each spring, N s / m
    margin: float = eqx.field(static=True)           # the cloth keeps this far outside the volumes (m)
    floor: float = eqx.field(static=True)


class _Piece:
    """A grid of vertices (rows x cols, optionally closed around the columns) with kept cells."""

    def __init__(self, points: np.ndarray, st: np.ndarray, closed: bool, keep: np.ndarray, layout):
        self.points, self.st, self.closed, self.keep, self.layout = points, st, closed, keep, layout


def _profile(controls: list[tuple[float, float, float]], rows: int) -> np.ndarray:
    """(y, a, b) at `rows` points equally spaced in arc length along the side silhouette (y, a)."""
    c = np.asarray(controls, np.float64)
    seg = np.hypot(np.diff(c[:, 0]), np.diff(c[:, 1]))
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.linspace(0.0, arc[-1], rows)
    return np.stack([np.interp(at, arc, c[:, k]) for k in range(3)], -1), at


def _body_piece(p0: np.ndarray, joints: dict[str, int], s: float, rows: int, cols: int) -> tuple[_Piece, dict]:
    y = {k: p0[joints[k], 1] for k in ("hips", "spine", "chest", "neck")}
    ankle = min(p0[joints["foot_L"], 1], p0[joints["foot_R"], 1])
    y_neck, y_hips = y["neck"], y["hips"]
    y_chest = y_hips + 0.75 * (y_neck - y_hips)
    y_waist = y_hips + 0.38 * (y_neck - y_hips)
    controls = [(y_neck + 0.02 * s, 0.075 * s, 0.075 * s), (y_neck - 0.05 * s, 0.2 * s, 0.125 * s),
                (y_chest, 0.155 * s, 0.145 * s), (y_waist, 0.15 * s, 0.14 * s),
                (y_hips - 0.1 * s, 0.2 * s, 0.165 * s), (ankle + 0.45 * (y_hips - ankle), 0.22 * s, 0.18 * s),
                (ankle + 0.02 * s, 0.235 * s, 0.19 * s)]
    prof, arc = _profile(controls, rows)
    forward = _forward(p0, joints)
    left = np.cross([0.0, 1.0, 0.0], forward)
    # the torso's centre at each height: along hips - spine - chest - neck, below the hips the hips
    chain = np.stack([p0[joints[k]] for k in ("hips", "spine", "chest", "neck")])
    centre = np.stack([np.interp(prof[:, 0], chain[:, 1], chain[:, k]) for k in (0, 2)], -1)
    phi = np.pi + 2 * np.pi * np.arange(cols + 1) / cols      # from the back centre, through the left side
    # the V of the crossed collar: the front of the top rows dips toward the chest
    dip = 0.11 * s * np.maximum(np.cos(phi), 0.0) ** 3
    fade = np.clip(1 - (prof[0, 0] - prof[:, 0]) / (0.25 * s), 0, 1)
    yy = prof[:, None, 0] - fade[:, None] * dip[None, :]
    sin, cos = np.sin(phi)[None, :], np.cos(phi)[None, :]
    x = centre[:, None, 0] + prof[:, None, 1] * sin * left[0] + prof[:, None, 2] * cos * forward[0]
    z = centre[:, None, 1] + prof[:, None, 1] * sin * left[2] + prof[:, None, 2] * cos * forward[2]
    points = np.stack([x, yy, z], -1)                                        # rows, cols + 1 (seam repeated)
    st = np.stack(np.meshgrid(np.arange(cols + 1) / cols, arc / arc[-1], indexing="xy"), -1)
    keep = np.ones((rows - 1, cols), bool)
    row_of = lambda h: int(np.argmin(np.abs(prof[:, 0] - h)))  # noqa: E731
    r_shoulder, r_chest, r_waist = row_of(y_neck - 0.05 * s), row_of(y_chest), row_of(y_waist)
    centre_phi = 0.5 * (phi[:-1] + phi[1:])
    # side openings from the shoulder to the waist: the arms pass through them into the sleeves
    around = np.mod(centre_phi, 2 * np.pi)
    side = np.minimum(np.abs(around - np.pi / 2), np.abs(around - 1.5 * np.pi))
    keep[r_shoulder + 1:r_waist - 1, side < 0.33] = False
    # ... and wherever an arm's bone passes through the cut at the first pose (a narrow armhole):
    # a cell an arm threads through could never be pushed off it
    arms = [(p0[joints[f"upper_arm_{k}"]], p0[joints[f"lower_arm_{k}"]]) for k in ("L", "R")]
    keep &= ~_threaded_cells(points, arms)
    rings = {"collar": list(range(COLLAR_ROWS)), "chest": [r_chest], "waist": [r_waist, r_waist + 1]}
    return _Piece(points, st, True, keep, COSTUME_LAYOUT["body"]), rings


def _threaded_cells(points: np.ndarray, segments: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(rows - 1, cols) whether any of the segments crosses the cell's quad (its two triangles)."""
    a, b, c, d = points[:-1, :-1], points[:-1, 1:], points[1:, :-1], points[1:, 1:]
    out = np.zeros(a.shape[:2], bool)
    for p, q in segments:
        for t0, t1, t2 in ((a, c, b), (b, c, d)):
            e1, e2, dq = t1 - t0, t2 - t0, q - p
            pv = np.cross(dq, e2)
            det = np.sum(e1 * pv, -1)
            inv = 1.0 / np.where(np.abs(det) > 1e-12, det, np.inf)
            tv = p - t0
            u = np.sum(tv * pv, -1) * inv
            qv = np.cross(tv, e1)
            v = np.sum(dq * qv, -1) * inv
            t = np.sum(e2 * qv, -1) * inv
            out |= (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    return out


def _sleeve_piece(p0: np.ndarray, joints: dict[str, int], s: float, side: str, body_a: float, rows: int,
                  cols: int) -> _Piece:
    ua, la, hand = (p0[joints[f"{k}_{side}"]] for k in ("upper_arm", "lower_arm", "hand"))
    hips = p0[joints["hips"]]
    # along the arm (shoulder - elbow - wrist) from where it leaves the robe's side to the wrist
    d_h = np.hypot(*(la - ua)[[0, 2]])
    start = ua + (la - ua) * float(np.clip((body_a - np.hypot(*(ua - hips)[[0, 2]])) / max(d_h, 1e-6), 0.0, 0.6))
    knots = np.stack([start, la, hand])
    seg = np.linalg.norm(np.diff(knots, axis=0), axis=-1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    along = np.linspace(0.0, 1.0, rows)
    at = along * arc[-1]
    centre = np.stack([np.interp(at, arc, knots[:, k]) for k in range(3)], -1)
    dirs = np.diff(knots, axis=0) / seg[:, None]
    bend = np.clip((at - arc[1]) / (0.25 * min(seg)) + 0.5, 0.0, 1.0)[:, None]     # the elbow, smoothed
    e = (1 - bend) * dirs[0] + bend * dirs[1]
    e /= np.linalg.norm(e, axis=-1, keepdims=True)
    down = np.array([0.0, -1.0, 0.0]) - e * (-e[:, 1:2])
    behind = -_forward(p0, joints)
    behind = behind - e * np.sum(behind * e, -1, keepdims=True)
    weak = np.linalg.norm(down, axis=-1, keepdims=True) < 0.3     # an arm hanging down: the depth goes behind it
    down = np.where(weak, behind, down)
    down /= np.linalg.norm(down, axis=-1, keepdims=True)
    across = np.cross(e, down)
    r_top, depth = 0.085 * s, 0.36 * s
    phi = 1.5 * np.pi + 2 * np.pi * np.arange(cols + 1) / cols               # from the sleeve's bottom seam
    w = r_top * np.cos(phi)
    h = np.where(np.sin(phi) >= 0, r_top * np.sin(phi), depth * np.sin(phi))
    points = centre[:, None] + w[None, :, None] * across[:, None] + (-h)[None, :, None] * down[:, None]
    st = np.stack(np.meshgrid(np.arange(cols + 1) / cols, along, indexing="xy"), -1)
    return _Piece(points, st, True, np.ones((rows - 1, cols), bool), COSTUME_LAYOUT[f"sleeve_{side}"])


def _assemble(pieces: list[_Piece]):
    """Simulated vertices (the seam column of each closed piece merged with its first), rendered
    vertices (all used), triangles of the kept cells, and springs: structural and shear along
    kept cells, bend two apart. Returns numpy arrays and each piece's simulated index grid."""
    sim_pts, uv, render_index, tris, grids = [], [], [], [], []
    pairs = {0: set(), 1: set(), 2: set()}
    n_sim = n_render = 0
    for pc in pieces:
        rows, cols1 = pc.points.shape[:2]
        cols = cols1 - 1 if pc.closed else cols1
        used = np.zeros((rows, cols1), bool)
        for dr in (0, 1):
            for dc in (0, 1):
                used[dr:rows - 1 + dr, dc:cols1 - 1 + dc] |= pc.keep
        sim_used = used[:, :cols].copy()
        if pc.closed:
            sim_used[:, 0] |= used[:, cols]
        sim = -np.ones((rows, cols), np.int64)
        sim[sim_used] = n_sim + np.arange(int(sim_used.sum()))
        n_sim += int(sim_used.sum())
        sim_pts.append(pc.points[:, :cols][sim_used])
        grid = np.concatenate([sim, sim[:, :1]], axis=1) if pc.closed else sim     # rows x cols1
        rend = -np.ones((rows, cols1), np.int64)
        rend[used] = n_render + np.arange(int(used.sum()))
        n_render += int(used.sum())
        render_index.append(grid[used])
        u0, v0, du, dv = pc.layout
        uv.append(np.stack([u0 + du * pc.st[..., 0], v0 + dv * pc.st[..., 1]], -1)[used])
        for r, c in zip(*np.nonzero(pc.keep)):
            a, b, cc, d = rend[r, c], rend[r, c + 1], rend[r + 1, c], rend[r + 1, c + 1]
            tris += [(a, cc, b), (b, cc, d)]
            sa, sb, sc, sd = grid[r, c], grid[r, c + 1], grid[r + 1, c], grid[r + 1, c + 1]
            for i, j in ((sa, sb), (sa, sc), (sb, sd), (sc, sd)):
                pairs[0].add((min(i, j), max(i, j)))
            for i, j in ((sa, sd), (sb, sc)):
                pairs[1].add((min(i, j), max(i, j)))
        for r in range(rows):            # bend along the rows (around a closed piece)
            for c in range(cols if pc.closed else cols - 2):
                i, m, j = sim[r, c], sim[r, (c + 1) % cols], sim[r, (c + 2) % cols]
                if min(i, m, j) >= 0 and i != j:
                    pairs[2].add((min(i, j), max(i, j)))
        for r in range(rows - 2):        # ... and down the columns
            for c in range(cols):
                i, m, j = sim[r, c], sim[r + 1, c], sim[r + 2, c]
                if min(i, m, j) >= 0:
                    pairs[2].add((min(i, j), max(i, j)))
        grids.append(grid)
    return (np.concatenate(sim_pts), np.concatenate(uv), np.concatenate(render_index), np.asarray(tris, np.int64),
            pairs, grids)


def dress_performer(motion: SkeletonMotion, joints: dict[str, int], *, rows: int = 30, cols: int = 28,
                    sleeve_rows: int = 8, sleeve_cols: int = 16, mass: float = 2.4, k_structural: float = 1200.0,
                    k_shear: float = 250.0, k_bend: float = 25.0, k_seam: float = 1200.0, damping: float = 1.5,
                    spring_damping: float = 0.01, margin: float = ROBE_MARGIN, dt: float = 5e-4,
                    settle_steps: int = 3000) -> Costume:
    """The robe made around the performer's pose at frame 0 (docs/noh.md, "The costume"):
    `rows` x `cols` body tube with side openings, two `sleeve_rows` x `sleeve_cols` sleeves seamed
    to it, the collar, chest and waist rings fixed to the skeleton; `mass` kg in all; then
    `settle_steps` steps at the first pose so that it hangs. Stiffness in N/m per spring."""
    p0 = np.asarray(motion.positions[0], np.float64)
    r0 = np.asarray(motion.rotations[0], np.float64)
    s = body_scale(motion, joints)
    body, rings = _body_piece(p0, joints, s, rows, cols)
    r_shoulder_a = 0.2 * s
    sleeves = [_sleeve_piece(p0, joints, s, side, r_shoulder_a, sleeve_rows, sleeve_cols) for side in ("L", "R")]
    pts, uv, render_index, tris, pairs, grids = _assemble([body] + sleeves)
    n = pts.shape[0]
    # the cut wraps the body: pushed out of its volumes first, so that it starts unstressed
    volumes = body_volumes(motion, joints)
    a, b = (np.asarray(e, np.float64) for e in volumes.ends(motion.positions[0], motion.rotations[0]))
    ends = [jnp.asarray(a), jnp.asarray(b), jnp.asarray(np.asarray(volumes.radius, np.float64) + margin)]
    for _ in range(3):
        pts = np.asarray(_push_out_jit(jnp.asarray(pts, ends[0].dtype), *ends), np.float64)
    # seams: the top of each sleeve's inner ring to the nearest body vertex on the side opening
    body_ids = grids[0][grids[0] >= 0]
    seam = []
    for grid in grids[1:]:
        ring = grid[0, :-1]
        for v in ring:
            d = np.linalg.norm(pts[body_ids] - pts[v], axis=-1)
            k = int(np.argmin(d))
            if d[k] < 0.09 * s:
                seam.append((int(v), int(body_ids[k])))
    kinds = [(pair, kind) for kind in (0, 1, 2) for pair in sorted(pairs[kind])] + [(p, 3) for p in seam]
    i = np.asarray([p[0] for p, _ in kinds])
    j = np.asarray([p[1] for p, _ in kinds])
    kind = np.asarray([k for _, k in kinds])
    rest = np.linalg.norm(pts[i] - pts[j], axis=-1)
    stiff = np.choose(kind, [k_structural, k_shear, k_bend, k_seam])
    dtype = default_float()
    springs = ClothSprings(jnp.asarray(i, jnp.int32), jnp.asarray(j, jnp.int32), jnp.asarray(rest, dtype),
                           jnp.asarray(stiff, dtype), jnp.asarray(np.minimum(kind, 2), jnp.int32))
    # fixed: the collar, chest and waist rings of the body, each to its nearest torso bone's joint
    fixed = sorted({int(v) for name in ("collar", "chest", "waist") for r in rings[name] for v in grids[0][r]
                    if v >= 0})
    torso = [joints[k] for k in ("hips", "spine", "chest", "neck")]
    seg_a, seg_b = p0[torso[:-1]], p0[torso[1:]]
    fixed_joint = []
    for v in fixed:
        t = np.clip(np.sum((pts[v] - seg_a) * (seg_b - seg_a), -1) / np.sum((seg_b - seg_a) ** 2, -1), 0, 1)
        dist = np.linalg.norm(seg_a + t[:, None] * (seg_b - seg_a) - pts[v], axis=-1)
        fixed_joint.append(torso[int(np.argmin(dist))])
    fixed_joint = np.asarray(fixed_joint, np.int64)
    local = np.einsum("pji,pj->pi", r0[fixed_joint], pts[fixed] - p0[fixed_joint])
    sim_tris = render_index[tris]
    edges = np.unique(np.sort(np.concatenate([sim_tris[:, [0, 1]], sim_tris[:, [1, 2]], sim_tris[:, [2, 0]]]), axis=1),
                      axis=0)
    inverse_mass = np.ones(n)
    inverse_mass[fixed] = 0.0
    x0 = jnp.asarray(pts, dtype)
    costume = Costume(ClothState(x0, x0, jnp.zeros((), dtype)), springs, jnp.asarray(fixed, jnp.int32),
                      jnp.asarray(fixed_joint, jnp.int32), jnp.asarray(local, dtype), volumes,
                      jnp.asarray(render_index, jnp.int32), jnp.asarray(uv, dtype), jnp.asarray(tris, jnp.int32),
                      jnp.asarray(sim_tris, jnp.int32), jnp.asarray(edges, jnp.int32), jnp.asarray(inverse_mass, dtype),
                      dt, mass / n, damping, spring_damping, margin, 0.004)
    if settle_steps:
        still = SkeletonMotion(motion.positions[:1], motion.rotations[:1], motion.frame_time)
        settled = _settle_jit(costume, still, settle_steps)
        costume = eqx.tree_at(lambda c: c.state, costume, ClothState(settled.x, settled.x, jnp.zeros((), dtype)))
    return costume


_push_out_jit = jax.jit(lambda x, a, b, r: _push_out(x, a, b, r))   # eagerly, ~25 capsules compile op by op
_settle_jit = eqx.filter_jit(lambda c, m, steps: advance_costume(c, c.state, m, steps=steps))


def fixed_positions(costume: Costume, positions: Float[Array, "J 3"], rotations: Float[Array, "J 3 3"]
                    ) -> Float[Array, "P 3"]:
    """Where the fixed vertices are for a pose: each joint's rotation and position applied to its
    vertices' bound positions."""
    return positions[costume.fixed_joint] + jnp.einsum("pij,pj->pi", rotations[costume.fixed_joint],
                                                       costume.fixed_local)


def _push_out(x: Float[Array, "N 3"], a: Float[Array, "B 3"], b: Float[Array, "B 3"], radius: Float[Array, " B"]
              ) -> Float[Array, "N 3"]:
    """Each vertex moved to the surface of every capsule it is inside, one capsule after the
    other (unrolled: ~24 fused elementwise updates run 2-3x faster than a scan or a vectorized
    deepest-capsule push on XLA's CPU backend; docs/noh.md)."""
    for k in range(a.shape[0]):
        ak, ab = a[k][None], (b[k] - a[k])[None]
        t = jnp.clip(jnp.sum((x - ak) * ab, -1) / jnp.maximum(jnp.sum(ab * ab), 1e-12), 0.0, 1.0)
        c = ak + t[:, None] * ab
        d = x - c
        dist = jnp.sqrt(jnp.maximum(jnp.sum(d * d, -1), 1e-20))
        x = jnp.where((dist < radius[k])[:, None], c + d * (radius[k] / dist)[:, None], x)
    return x


def _push_edges_out(x: Float[Array, "N 3"], edges: Int[Array, "E 2"], inverse_mass: Float[Array, " N"],
                    a: Float[Array, "B 3"], b: Float[Array, "B 3"], radius: Float[Array, " B"]) -> Float[Array, "N 3"]:
    """Every edge moved out of the capsules it is inside: the closest points of the edge and
    the capsule's axis (segment to segment), the edge's point carried to radius from the axis by
    moving its two ends in proportion to their share of it (and to their inverse mass: a fixed
    end does not move), each vertex by the mean of the moves its edges ask. Vertices outside the
    capsules can still leave an edge between them crossing a thin one (an arm through a robe's
    opening): this keeps the triangles, not only their corners, out of the body."""
    p, q = x[edges[:, 0]], x[edges[:, 1]]                      # E 3
    d1 = [(q[:, k] - p[:, k])[:, None] for k in range(3)]      # by components: E B
    d2 = [(b[:, k] - a[:, k])[None] for k in range(3)]
    r = [p[:, k][:, None] - a[:, k][None] for k in range(3)]
    dot = lambda u, v: u[0] * v[0] + u[1] * v[1] + u[2] * v[2]  # noqa: E731
    aa = jnp.maximum(dot(d1, d1), 1e-20)
    ee = jnp.maximum(dot(d2, d2), 1e-20)
    f, c, bb = dot(d2, r), dot(d1, r), dot(d1, d2)
    denom = aa * ee - bb * bb
    s = jnp.where(denom > 1e-12 * aa * ee, jnp.clip((bb * f - c * ee) / jnp.maximum(denom, 1e-30), 0.0, 1.0), 0.0)
    t = (bb * s + f) / ee
    s = jnp.where(t < 0, jnp.clip(-c / aa, 0.0, 1.0), jnp.where(t > 1, jnp.clip((bb - c) / aa, 0.0, 1.0), s))
    t = jnp.clip(t, 0.0, 1.0)
    gap = [r[k] + s * d1[k] - t * d2[k] for k in range(3)]    # axis point -> edge point
    dist = jnp.sqrt(jnp.maximum(dot(gap, gap), 1e-20))
    depth = jnp.maximum(radius[None] - dist, 0.0)              # > 0: the edge is inside
    push = [depth * g / dist for g in gap]                     # the edge point's move out of each capsule
    w0 = (1 - s) * inverse_mass[edges[:, 0]][:, None]
    w1 = s * inverse_mass[edges[:, 1]][:, None]
    scale = 1.0 / jnp.maximum((1 - s) * w0 + s * w1, 0.5)   # a point near a fixed end: at most 2 x depth
    move0 = jnp.stack([jnp.sum(w0 * scale * m, axis=1) for m in push], -1)
    move1 = jnp.stack([jnp.sum(w1 * scale * m, axis=1) for m in push], -1)
    inside = jnp.sum(depth, axis=1) > 0
    move = jnp.concatenate([move0, move1])
    ends = jnp.concatenate([edges[:, 0], edges[:, 1]])
    active = jnp.concatenate([inside & (inverse_mass[edges[:, 0]] > 0), inside & (inverse_mass[edges[:, 1]] > 0)])
    n = x.shape[0]
    total = jax.ops.segment_sum(move, ends, num_segments=n)
    count = jax.ops.segment_sum(active.astype(x.dtype), ends, num_segments=n)
    return x + total / jnp.maximum(count, 1.0)[:, None]


def _push_triangles_out(x: Float[Array, "N 3"], triangles: Int[Array, "T 3"], inverse_mass: Float[Array, " N"],
                        a: Float[Array, "B 3"], b: Float[Array, "B 3"], radius: Float[Array, " B"]
                        ) -> Float[Array, "N 3"]:
    """Every triangle moved off the capsule ends that poke into it: where an end of a capsule's
    axis lies within radius of a triangle's plane and projects inside the triangle, the triangle's
    point there is carried to radius along the plane's normal, away from the end, by moving its
    three corners in proportion to their barycentric share (and inverse mass), each vertex by the
    mean of the moves its triangles ask. With its corners and edges outside (the pushes before
    this one), a triangle larger than a capsule's section can still have a hand's or an elbow's
    end through its middle. An axis that crosses the triangle is left to the edges."""
    p0, p1, p2 = (x[triangles[:, k]] for k in range(3))
    e1, e2 = p1 - p0, p2 - p0
    normal = jnp.cross(e1, e2)
    area = jnp.sqrt(jnp.maximum(jnp.sum(normal * normal, -1), 1e-30))[:, None]   # T 1 (twice the area)
    n = normal / area
    # height over the plane and barycentric (w1, w2) of a point's projection: each a dot product
    # with a vector of the triangle, less its value at p0: one small matrix product for all pairs
    basis = jnp.stack([n, jnp.cross(e2, n) / area, jnp.cross(n, e1) / area], 1)     # T 3 3
    offset = jnp.einsum("tjk,tk->tj", basis, p0)                                    # T 3
    ha, w1a, w2a = jnp.einsum("tjk,bk->jtb", basis, a) - offset.T[:, :, None]     # each T B
    hb, w1b, w2b = jnp.einsum("tjk,bk->jtb", basis, b) - offset.T[:, :, None]
    t = ha / jnp.where(ha == hb, 1.0, ha - hb)
    w1t, w2t = (1 - t) * w1a + t * w1b, (1 - t) * w2a + t * w2b                   # where the axis meets the plane
    pierced = (ha * hb < 0) & (w1t >= 0) & (w2t >= 0) & (w1t + w2t <= 1)
    free = [inverse_mass[triangles[:, k]][:, None] for k in range(3)]            # 3 x T 1
    coef, hit = [0.0, 0.0, 0.0], False
    for h, w1, w2 in ((ha, w1a, w2a), (hb, w1b, w2b)):
        bary = (1 - w1 - w2, w1, w2)                                             # each T B
        within = (bary[0] >= 0) & (w1 >= 0) & (w2 >= 0) & ~pierced
        depth = jnp.where(within, jnp.maximum(radius[None] - jnp.abs(h), 0.0), 0.0)   # T B
        # the point moves by depth: its corners by their shares, scaled so that the shares' sum does
        scale = 1.0 / jnp.maximum(sum(bk * bk * fk for bk, fk in zip(bary, free)), 1.0 / 3.0)
        g = scale * -jnp.sign(h) * depth
        coef = [ck + fk[:, 0] * jnp.sum(bk * g, axis=1) for ck, bk, fk in zip(coef, bary, free)]   # T: along n
        hit = hit | jnp.any(depth > 0, axis=1)
    coef = jnp.stack(coef, -1)                                                   # T 3
    corners = triangles.reshape(-1)
    move = (coef[..., None] * n[:, None]).reshape(-1, 3)
    active = (hit[:, None] & (jnp.concatenate(free, -1) > 0)).reshape(-1).astype(x.dtype)
    total = jax.ops.segment_sum(move, corners, num_segments=x.shape[0])
    count = jax.ops.segment_sum(active, corners, num_segments=x.shape[0])
    return x + total / jnp.maximum(count, 1.0)[:, None]


def _after_contact(x: Float[Array, "N 3"], free: Float[Array, "N 3"], pushed: Float[Array, "N 3"],
                   inverse_mass: Float[Array, " N"]) -> Float[Array, "N 3"]:
    """The previous positions that the next Verlet step reads velocity from, after the pushes
    (`free`: where the step took the vertices, `pushed`: where the pushes left them). A push is an
    inelastic contact: it removes the step's move into the body (its component against the push)
    and does not itself become velocity. Left as Verlet has it (`x`), a push of a few millimetres
    is a velocity of metres per second out of the body at the next step, which the springs bring
    back in: at a still pose the robe then never comes to rest (the edge push against the collar's
    springs kept vertices moving 3-7 m/s after 1.5 s of settling)."""
    move, push = free - x, pushed - free
    size = jnp.sqrt(jnp.maximum(jnp.sum(push * push, -1, keepdims=True), 1e-30))
    normal = push / size
    into = jnp.minimum(jnp.sum(move * normal, -1, keepdims=True), 0.0)
    contact = (size > 1e-12) & (inverse_mass[:, None] > 0)
    return jnp.where(contact, pushed - (move - into * normal), x)


def advance_costume(costume: Costume, state: ClothState, motion: SkeletonMotion, *, steps: int,
                    gravity: float = 9.81, passes: int = 2) -> ClothState:
    """Continue the robe's Verlet simulation from `state` for `steps` steps of `costume.dt`
    following `motion`: springs with dampers along them, air drag, gravity; after each step every
    free vertex is pushed out of the body's volumes (`passes` sweeps, to radius + margin), every
    edge too (`_push_edges_out`), and above the floor, each push an inelastic contact
    (`_after_contact`), and the fixed vertices are set on the skeleton, pushed out of the volumes.
    Jittable (`steps` static)."""
    x0 = state.x
    dtype = x0.dtype
    dt = costume.dt
    sp = costume.springs
    g = jnp.zeros_like(x0).at[:, 1].set(-gravity)
    keep = 1 - costume.damping * dt
    n = x0.shape[0]
    body = costume.body

    def step(carry, k):
        x, xp = carry
        t = state.time + (k + 1).astype(dtype) * dt
        v = (x - xp) / dt
        d = x[sp.j] - x[sp.i]
        length = jnp.sqrt(jnp.maximum(dot(d, d), 1e-20))   # written out: XLA's reductions over 3 are slow on CPU
        u = d / length[:, None]
        closing = dot(v[sp.j] - v[sp.i], u)
        f = (sp.stiffness * (length - sp.rest) + costume.spring_damping * closing)[:, None] * u
        force = jax.ops.segment_sum(f, sp.i, num_segments=n) - jax.ops.segment_sum(f, sp.j, num_segments=n)
        free = x + keep * (x - xp) + (force / costume.mass + g) * dt * dt
        pos, rot = motion.at(t)
        a, b = body.ends(pos, rot)
        xn = free
        for _ in range(passes):
            xn = _push_out(xn, a, b, body.radius + costume.margin)
        xn = _push_edges_out(xn, costume.edges, costume.inverse_mass, a, b, body.radius + costume.margin)
        xn = _push_triangles_out(xn, costume.sim_triangles, costume.inverse_mass, a, b, body.radius + costume.margin)
        xn = xn.at[:, 1].set(jnp.maximum(xn[:, 1], costume.floor))
        # the fixed vertices on the skeleton, pushed aside by a volume that moves into them (an arm
        # swinging into the collar or the chest ring, the head bowed into the collar): pinned, they
        # would stay inside it
        fixed = _push_out(fixed_positions(costume, pos, rot), a, b, body.radius + costume.margin)
        xn = xn.at[costume.fixed_index].set(fixed)
        return (xn, _after_contact(x, free, xn, costume.inverse_mass)), None

    (x, xp), _ = jax.lax.scan(step, (state.x, state.x_prev), jnp.arange(steps))
    return ClothState(x, xp, state.time + jnp.asarray(steps * dt, dtype))


def costume_frames(costume: Costume, motion: SkeletonMotion, *, frames: int, frame_dt: float,
                   state: ClothState | None = None) -> tuple[Float[Array, "F N 3"], ClothState]:
    """`frames` frames `frame_dt` apart, each continuing from the previous one's state: the
    positions at each frame's end and the last state."""
    steps = max(1, int(round(frame_dt / costume.dt)))
    state = costume.state if state is None else state
    return scan_frames(lambda st: advance_costume(costume, st, motion, steps=steps), state, frames)


def volume_penetration(costume: Costume, x: Float[Array, "N 3"], positions: Float[Array, "J 3"],
                       rotations: Float[Array, "J 3 3"]) -> Float[Array, " N"]:
    """How deep each vertex lies inside the body's volumes (m; 0 outside): max over capsules of
    radius - distance to the centre line."""
    a, b = costume.body.ends(positions, rotations)
    ab = b - a
    t = jnp.clip(jnp.einsum("nbk,bk->nb", x[:, None, :] - a[None], ab) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-12),
                 0.0, 1.0)
    c = a[None] + t[..., None] * ab[None]
    dist = jnp.sqrt(jnp.sum((x[:, None, :] - c) ** 2, -1))
    return jnp.maximum(jnp.max(costume.body.radius[None] - dist, axis=1), 0.0)


def costume_normals(costume: Costume, x: Float[Array, "N 3"]) -> Float[Array, "R 3"]:
    """Vertex normals of the rendered mesh (computed on the simulated vertices: no seam in them)."""
    return vertex_normals(x, costume.sim_triangles)[costume.render_index]
