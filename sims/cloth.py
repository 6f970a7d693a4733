"""A draped garment: a rectangular cloth hung from two shoulder points, settled by a Verlet
mass-spring simulation (paper 004 section 4.3 uses Verlet integration of a spring-damper cloth).

Particles on an R x C grid (row 0 at the top), joined by structural springs (grid neighbours),
shear springs (diagonals) and bend springs (two apart), under gravity (-y), with velocity
damping. The two shoulder points are small groups of top-row particles pinned at positions
closer together than the cloth is wide, so the cloth falls in folds between and beside them.
Position Verlet, x' = x + (1 - c dt)(x - x_prev) + a dt^2, runs in one jitted `lax.scan`.

Units: metres, seconds, each particle has mass `mass`; spring stiffness in N/m.
Output: vertices (R, C, 3), UVs (u along columns, v along rows, v = 0 at the top row),
triangles (2 (R-1)(C-1), 3) and area-weighted vertex normals (facing +z for the flat sheet).

Motion (paper 004 section 4.3 drives the garment by a motion-captured dance; no capture data
is available here): `drape_garment` settles the cloth as above and returns a `DrapedCloth`, the
rig plus its `ClothState` (positions, previous positions, time). `BodyMotion` is a procedural
dance of the body: a slow turn about the performer's vertical axis and a sideways sway, and the
hands (the two top-row corners, pinned where the settled drape left them) lifting out and up
and down again. `advance_cloth` continues the Verlet simulation from a state for a given time
with the pinned points following the motion at every step (and the body capsule following the
sway); `animate_cloth` runs it frame after frame, each frame starting from the state the
previous one ended in (never re-settled from rest). All motion terms start with zero value and
zero velocity at t = 0, so the settled drape is the first frame and nothing jumps.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.maths import default_float

__all__ = ["ClothMesh", "ClothSprings", "cloth_springs", "cloth_energy", "simulate_cloth", "drape_cloth",
           "grid_triangles", "vertex_normals", "ClothState", "BodyMotion", "DrapedCloth", "drape_garment",
           "advance_cloth", "animate_cloth", "scan_frames", "cloth_mesh"]


class ClothSprings(eqx.Module):
    i: Int[Array, " S"]
    j: Int[Array, " S"]
    rest: Float[Array, " S"]
    stiffness: Float[Array, " S"]
    kind: Int[Array, " S"]  # 0 structural, 1 shear, 2 bend


class ClothMesh(eqx.Module):
    vertices: Float[Array, "R C 3"]
    uv: Float[Array, "R C 2"]
    triangles: Int[Array, "T 3"]
    normals: Float[Array, "R C 3"]


def cloth_springs(rest_positions: Float[Array, "R C 3"], *, k_structural: float, k_shear: float,
                  k_bend: float) -> ClothSprings:
    """Structural, shear and bend springs of a grid, rest lengths from `rest_positions`."""
    r, c = rest_positions.shape[0], rest_positions.shape[1]
    idx = np.arange(r * c).reshape(r, c)
    pairs, kinds = [], []
    for kind, (a, b) in [(0, (idx[:, :-1], idx[:, 1:])), (0, (idx[:-1, :], idx[1:, :])),
                         (1, (idx[:-1, :-1], idx[1:, 1:])), (1, (idx[:-1, 1:], idx[1:, :-1])),
                         (2, (idx[:, :-2], idx[:, 2:])), (2, (idx[:-2, :], idx[2:, :]))]:
        pairs.append(np.stack([a.reshape(-1), b.reshape(-1)], axis=-1))
        kinds.append(np.full(a.size, kind))
    p = np.concatenate(pairs)
    kind = np.concatenate(kinds)
    flat = np.asarray(rest_positions).reshape(-1, 3)
    rest = np.linalg.norm(flat[p[:, 0]] - flat[p[:, 1]], axis=-1)
    k = np.choose(kind, [k_structural, k_shear, k_bend])
    dtype = rest_positions.dtype
    return ClothSprings(jnp.asarray(p[:, 0], dtype=jnp.int32), jnp.asarray(p[:, 1], dtype=jnp.int32),
                        jnp.asarray(rest, dtype=dtype), jnp.asarray(k, dtype=dtype), jnp.asarray(kind, dtype=jnp.int32))


def _spring_forces(x: Float[Array, "N 3"], springs: ClothSprings) -> Float[Array, "N 3"]:
    d = x[springs.j] - x[springs.i]
    length = jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1), 1e-20))
    f = (springs.stiffness * (length - springs.rest) / length)[:, None] * d  # pulls i toward j when stretched
    n = x.shape[0]
    return jax.ops.segment_sum(f, springs.i, num_segments=n) - jax.ops.segment_sum(f, springs.j, num_segments=n)


def cloth_energy(x: Float[Array, "N 3"], x_prev: Float[Array, "N 3"], springs: ClothSprings, *, dt: float,
                 mass: float, gravity: float = 9.81) -> Float[Array, ""]:
    """Kinetic (from the Verlet velocity) + gravitational + spring potential energy (J)."""
    v = (x - x_prev) / dt
    kinetic = 0.5 * mass * jnp.sum(v * v)
    potential = mass * gravity * jnp.sum(x[:, 1])
    d = x[springs.j] - x[springs.i]
    length = jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1), 1e-20))
    elastic = 0.5 * jnp.sum(springs.stiffness * (length - springs.rest) ** 2)
    return kinetic + potential + elastic


def simulate_cloth(x0: Float[Array, "N 3"], springs: ClothSprings, pinned: Float[Array, " N"], *, steps: int,
                   dt: float, mass: float, damping: float, gravity: float = 9.81,
                   record_every: int = 0, capsule: Float[Array, "5"] | None = None
                   ) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"], Float[Array, " E"]]:
    """Run `steps` Verlet steps from rest at `x0`; pinned particles (pinned = 1) never move.

    `capsule` = (x, z, radius, y_min, y_max): a vertical capsule the particles are pushed out of
    after each step (a collision constraint). Returns the final positions, the previous
    positions, and the energy every `record_every` steps (empty when 0).
    """
    g = jnp.zeros_like(x0).at[:, 1].set(-gravity)
    free = (1 - pinned)[:, None]
    keep = 1 - damping * dt

    def step(carry, _):
        x, xp = carry
        a = _spring_forces(x, springs) / mass + g
        xn = x + keep * (x - xp) + a * dt * dt
        if capsule is not None:
            xn = _push_out_of_capsule(xn, capsule)
        xn = free * xn + (1 - free) * x0
        return (xn, x), None

    if record_every:
        def chunk(carry, _):
            carry, _ = jax.lax.scan(step, carry, None, length=record_every)
            return carry, cloth_energy(carry[0], carry[1], springs, dt=dt, mass=mass, gravity=gravity)
        (x, xp), energy = jax.lax.scan(chunk, (x0, x0), None, length=steps // record_every)
    else:
        (x, xp), _ = jax.lax.scan(step, (x0, x0), None, length=steps)
        energy = jnp.zeros((0,), dtype=x0.dtype)
    return x, xp, energy


def _push_out_of_capsule(x: Float[Array, "N 3"], capsule: Float[Array, "5"]) -> Float[Array, "N 3"]:
    cx, cz, radius, y0, y1 = capsule[0], capsule[1], capsule[2], capsule[3], capsule[4]
    axis_point = jnp.stack([jnp.broadcast_to(cx, x[:, 1].shape), jnp.clip(x[:, 1], y0, y1),
                            jnp.broadcast_to(cz, x[:, 1].shape)], axis=-1)
    d = x - axis_point
    dist = jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1), 1e-20))
    inside = dist < radius
    return jnp.where(inside[:, None], axis_point + d * (radius / dist)[:, None], x)


def grid_triangles(rows: int, cols: int) -> Int[Array, "T 3"]:
    """Two counter-clockwise (seen from +z for the flat sheet) triangles per grid cell."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b = idx[:-1, :-1].reshape(-1), idx[:-1, 1:].reshape(-1)
    c, d = idx[1:, :-1].reshape(-1), idx[1:, 1:].reshape(-1)
    # row index grows downward (-y) and column index along +x: (a, c, b) is counter-clockwise from +z
    tris = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    return jnp.asarray(tris, dtype=jnp.int32)


def vertex_normals(vertices: Float[Array, "N 3"], triangles: Int[Array, "T 3"]) -> Float[Array, "N 3"]:
    p0, p1, p2 = vertices[triangles[:, 0]], vertices[triangles[:, 1]], vertices[triangles[:, 2]]
    fn = jnp.cross(p1 - p0, p2 - p0)  # area-weighted
    n = jnp.zeros_like(vertices)
    for k in range(3):
        n = n.at[triangles[:, k]].add(fn)
    length = jnp.sqrt(jnp.maximum(jnp.sum(n * n, axis=-1, keepdims=True), 1e-30))
    return n / length


class ClothState(eqx.Module):
    """Where the simulation stands: positions, previous positions (the Verlet velocity is their
    difference over dt) and the time since the motion began (s)."""

    x: Float[Array, "N 3"]
    x_prev: Float[Array, "N 3"]
    time: Float[Array, ""]


class BodyMotion(eqx.Module):
    """A procedural dance of the body that carries the garment's pinned points.

    At time t (s), with r(t) = smoothstep(t / `ramp`) easing the motion in:
    turn angle  theta(t) = `turn` r(t) sin(2 pi t / `turn_period`)     (radians, about +y through
                           the body axis at x = `axis_x`, z = `axis_z`),
    sway        s(t)     = `sway` r(t) sin(2 pi t / `sway_period`)     (metres along x),
    hand lift   a(t)     = `arm_lift` (1 - cos(2 pi t / `arm_period`)) / 2 (metres: the hands go
                           up by a(t) and out by a(t) / 2, and come back).
    A pin p (rest position, hand = 1 for a hand pin) moves to
        R_y(theta) (p + hand (sign(p_x - axis_x) a / 2, a, 0) - axis) + axis + (s, 0, 0).
    Every term is 0 with zero velocity at t = 0."""

    turn: float = eqx.field(static=True, default=math.radians(25.0))
    turn_period: float = eqx.field(static=True, default=4.0)
    sway: float = eqx.field(static=True, default=0.06)
    sway_period: float = eqx.field(static=True, default=2.0)
    arm_lift: float = eqx.field(static=True, default=0.25)
    arm_period: float = eqx.field(static=True, default=3.0)
    ramp: float = eqx.field(static=True, default=0.5)
    axis_x: float = eqx.field(static=True, default=0.0)
    axis_z: float = eqx.field(static=True, default=0.0)

    def pose(self, t: Float[Array, ""]) -> tuple[Array, Array, Array]:
        """(turn angle, sway, hand lift) at time t."""
        u = jnp.clip(t / self.ramp, 0.0, 1.0)
        r = u * u * (3.0 - 2.0 * u)
        theta = self.turn * r * jnp.sin(2 * jnp.pi * t / self.turn_period)
        sway = self.sway * r * jnp.sin(2 * jnp.pi * t / self.sway_period)
        lift = self.arm_lift * 0.5 * (1.0 - jnp.cos(2 * jnp.pi * t / self.arm_period))
        return theta, sway, lift

    def pins(self, rest: Float[Array, "P 3"], hand: Float[Array, " P"], t: Float[Array, ""]) -> Float[Array, "P 3"]:
        """Positions of the pinned points at time t (class docstring)."""
        theta, sway, lift = self.pose(t)
        dtype = rest.dtype
        axis = jnp.asarray([self.axis_x, 0.0, self.axis_z], dtype)
        side = jnp.sign(rest[:, 0] - self.axis_x)
        p = rest + hand[:, None] * jnp.stack([0.5 * lift * side, lift * jnp.ones_like(side), jnp.zeros_like(side)], -1)
        c, s = jnp.cos(theta), jnp.sin(theta)
        d = p - axis[None, :]
        rotated = jnp.stack([c * d[:, 0] + s * d[:, 2], d[:, 1], -s * d[:, 0] + c * d[:, 2]], -1)
        shift = axis + jnp.stack([sway, jnp.zeros_like(sway), jnp.zeros_like(sway)]).astype(dtype)
        return rotated + shift[None, :]

    def capsule(self, rest: Float[Array, "5"], t: Float[Array, ""]) -> Float[Array, "5"]:
        """The body capsule (x, z, radius, y_min, y_max) at time t: its axis sways with the body
        (the turn is about the body's own axis, which a capsule does not see)."""
        _, sway, _ = self.pose(t)
        return rest.at[0].add(sway)


class DrapedCloth(eqx.Module):
    """A settled garment and everything needed to keep simulating it (`drape_garment`)."""

    state: ClothState
    springs: ClothSprings
    pin_index: Int[Array, " P"]        # the pinned particles: two shoulders, then two hands
    pin_rest: Float[Array, "P 3"]     # their positions at t = 0
    hand: Float[Array, " P"]           # 1 for a hand pin, 0 for a shoulder
    capsule: Float[Array, "5"]        # the body at t = 0
    uv: Float[Array, "R C 2"]
    triangles: Int[Array, "T 3"]
    rows: int = eqx.field(static=True)
    cols: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    mass: float = eqx.field(static=True)
    damping: float = eqx.field(static=True)


def drape_garment(*, rows: int = 40, cols: int = 32, width: float = 1.4, height: float = 1.5,
                  shoulder_span: float = 0.6, shoulder_u: float = 0.2, top: float = 1.75, fold_depth: float = 0.03,
                  folds: int = 4, body_radius: float = 0.16, body_z: float = -0.14, mass: float = 0.002,
                  k_structural: float = 1500.0, k_shear: float = 300.0, k_bend: float = 30.0,
                  damping: float = 4.0, dt: float = 5e-4, steps: int = 6000) -> DrapedCloth:
    """The settled garment: an R x C sheet (`width` x `height` m) whose top row is pinned at
    columns u = `shoulder_u` and 1 - `shoulder_u` to two shoulder points `shoulder_span` apart
    (closer than the cloth between them, so the neckline sags in a swag) at height `top`, hanging
    in front of a vertical capsule (the performer's body: radius `body_radius`, axis at x = 0,
    z = `body_z`) that the cloth cannot enter. It starts gathered onto the span with a ripple
    of `folds` folds (depth `fold_depth`) and settles into folds for `steps` steps of `dt`.
    The two top-row corners become the hands: pinned, from the end of the settling on, where
    the drape left them.

    Defaults: 1280 particles of 2 g (a 2.6 kg robe); springs stiff enough that the cloth
    stretches by a few percent on average under its weight.
    """
    dtype = default_float()
    u = np.linspace(0.0, 1.0, cols)
    v = np.linspace(0.0, 1.0, rows)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    rest = np.stack([(uu - 0.5) * width, top - vv * height, np.zeros_like(uu)], axis=-1)
    gather = shoulder_span / ((1 - 2 * shoulder_u) * width)
    x0 = np.stack([(uu - 0.5) * width * gather, top - vv * height * 0.98,
                   fold_depth * np.cos(2 * np.pi * folds * (uu - 0.5)) * (0.3 + vv)], axis=-1)
    shoulders = [int(round(centre * (cols - 1))) for centre in (shoulder_u, 1 - shoulder_u)]
    pinned = np.zeros((rows, cols))
    pinned[0, shoulders] = 1.0
    springs = cloth_springs(jnp.asarray(rest, dtype=dtype), k_structural=k_structural, k_shear=k_shear, k_bend=k_bend)
    body = jnp.asarray([0.0, body_z, body_radius, top - 1.2 * height, top - body_radius - 0.1], dtype=dtype)
    x, xp, _ = _simulate_jit(jnp.asarray(x0.reshape(-1, 3), dtype=dtype), springs,
                             jnp.asarray(pinned.reshape(-1), dtype=dtype), steps, dt, mass, damping, body)
    hands = [0, cols - 1] if shoulders != [0, cols - 1] else []
    pin_index = jnp.asarray(shoulders + hands, dtype=jnp.int32)
    hand = jnp.asarray([0.0] * len(shoulders) + [1.0] * len(hands), dtype=dtype)
    uv = jnp.asarray(np.stack([uu, vv], axis=-1), dtype=dtype)
    return DrapedCloth(ClothState(x, xp, jnp.zeros((), dtype)), springs, pin_index, x[pin_index], hand, body, uv,
                       grid_triangles(rows, cols), rows, cols, dt, mass, damping)


def cloth_mesh(cloth: DrapedCloth, x: Float[Array, "N 3"]) -> ClothMesh:
    """The mesh (vertices, uv, triangles, normals) of the cloth at positions `x`."""
    normals = vertex_normals(x, cloth.triangles)
    return ClothMesh(x.reshape(cloth.rows, cloth.cols, 3), cloth.uv, cloth.triangles,
                     normals.reshape(cloth.rows, cloth.cols, 3))


def drape_cloth(**kwargs) -> ClothMesh:
    """The settled garment's mesh (`drape_garment`'s keywords)."""
    cloth = drape_garment(**kwargs)
    return cloth_mesh(cloth, cloth.state.x)


def advance_cloth(cloth: DrapedCloth, state: ClothState, motion: BodyMotion, *, steps: int,
                  gravity: float = 9.81) -> ClothState:
    """Continue the Verlet simulation from `state` for `steps` steps of `cloth.dt`: at every step
    the pinned points are set to `motion`'s pins at the step's end time and the free particles
    are pushed out of the moving body capsule. Jittable (`steps` static)."""
    x0 = state.x
    dtype = x0.dtype
    dt = cloth.dt
    g = jnp.zeros_like(x0).at[:, 1].set(-gravity)
    keep = 1 - cloth.damping * dt
    free = jnp.ones((x0.shape[0], 1), dtype).at[cloth.pin_index].set(0.0)

    def step(carry, k):
        x, xp = carry
        t = state.time + (k + 1).astype(dtype) * dt
        a = _spring_forces(x, cloth.springs) / cloth.mass + g
        xn = x + keep * (x - xp) + a * dt * dt
        xn = _push_out_of_capsule(xn, motion.capsule(cloth.capsule, t))
        xn = free * xn
        xn = xn.at[cloth.pin_index].set(motion.pins(cloth.pin_rest, cloth.hand, t))
        return (xn, x), None

    (x, xp), _ = jax.lax.scan(step, (state.x, state.x_prev), jnp.arange(steps))
    return ClothState(x, xp, state.time + jnp.asarray(steps * dt, dtype))


def animate_cloth(cloth: DrapedCloth, motion: BodyMotion, *, frames: int, frame_dt: float,
                  state: ClothState | None = None) -> tuple[Float[Array, "F N 3"], ClothState]:
    """`frames` frames `frame_dt` apart, each continuing from the previous one's state (from the
    settled drape when `state` is None): the positions at each frame's end and the last state."""
    steps = max(1, int(round(frame_dt / cloth.dt)))
    state = cloth.state if state is None else state
    return scan_frames(lambda s: advance_cloth(cloth, s, motion, steps=steps), state, frames)


def scan_frames(advance: Callable[[ClothState], ClothState], state: ClothState,
                frames: int) -> tuple[Float[Array, "F N 3"], ClothState]:
    """`advance` applied `frames` times from `state` (one `lax.scan`): the positions after each
    application and the last state. The frame loop of `animate_cloth` and `sims.costume_frames`."""
    def frame(s, _):
        s = advance(s)
        return s, s.x

    state, xs = jax.lax.scan(frame, state, None, length=frames)
    return xs, state


@eqx.filter_jit
def _simulate_jit(x0, springs, pinned, steps, dt, mass, damping, body):
    x, xp, energy = simulate_cloth(x0, springs, pinned, steps=steps, dt=dt, mass=mass, damping=damping, capsule=body)
    return x, xp, energy
