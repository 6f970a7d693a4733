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
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.maths import default_float

__all__ = ["ClothMesh", "ClothSprings", "cloth_springs", "cloth_energy", "simulate_cloth", "drape_cloth",
           "grid_triangles", "vertex_normals"]


class ClothSprings(eqx.Module):
    i: Int[Array, "S"]
    j: Int[Array, "S"]
    rest: Float[Array, "S"]
    stiffness: Float[Array, "S"]
    kind: Int[Array, "S"]  # 0 structural, 1 shear, 2 bend


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


def simulate_cloth(x0: Float[Array, "N 3"], springs: ClothSprings, pinned: Float[Array, "N"], *, steps: int,
                   dt: float, mass: float, damping: float, gravity: float = 9.81,
                   record_every: int = 0, capsule: Float[Array, "5"] | None = None) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"], Float[Array, "E"]]:
    """Run `steps` Verlet steps from rest at `x0`; pinned particles (pinned = 1) never move.

    `capsule` = (x, z, radius, y_min, y_max): a vertical capsule the particles are pushed out of
    after each step (a collision constraint). Returns the final positions, the previous positions, and the energy every `record_every`
    steps (empty when 0).
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


def drape_cloth(*, rows: int = 40, cols: int = 32, width: float = 1.4, height: float = 1.5,
                shoulder_span: float = 0.6, shoulder_u: float = 0.2, top: float = 1.75, fold_depth: float = 0.03,
                folds: int = 4, body_radius: float = 0.16, body_z: float = -0.14, mass: float = 0.002,
                k_structural: float = 1500.0, k_shear: float = 300.0, k_bend: float = 30.0,
                damping: float = 4.0, dt: float = 5e-4, steps: int = 6000) -> ClothMesh:
    """The settled garment: an R x C sheet (`width` x `height` m) whose top row is pinned at
    columns u = `shoulder_u` and 1 - `shoulder_u` to two shoulder points `shoulder_span` apart
    (closer than the cloth between them, so the neckline sags in a swag) at height `top`, hanging
    in front of a vertical capsule (the performer's body: radius `body_radius`, axis at x = 0,
    z = `body_z`) that the cloth cannot enter. It starts gathered onto the span with a ripple
    of `folds` folds (depth `fold_depth`) and settles into folds.

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
    pinned = np.zeros((rows, cols))
    for centre in (shoulder_u, 1 - shoulder_u):
        pinned[0, int(round(centre * (cols - 1)))] = 1.0
    springs = cloth_springs(jnp.asarray(rest, dtype=dtype), k_structural=k_structural, k_shear=k_shear, k_bend=k_bend)
    body = jnp.asarray([0.0, body_z, body_radius, top - 1.2 * height, top - body_radius - 0.1], dtype=dtype)
    x, _, _ = _simulate_jit(jnp.asarray(x0.reshape(-1, 3), dtype=dtype), springs,
                            jnp.asarray(pinned.reshape(-1), dtype=dtype), steps, dt, mass, damping, body)
    tris = grid_triangles(rows, cols)
    normals = vertex_normals(x, tris)
    uv = jnp.asarray(np.stack([uu, vv], axis=-1), dtype=dtype)
    return ClothMesh(x.reshape(rows, cols, 3), uv, tris, normals.reshape(rows, cols, 3))


@eqx.filter_jit
def _simulate_jit(x0, springs, pinned, steps, dt, mass, damping, body):
    return simulate_cloth(x0, springs, pinned, steps=steps, dt=dt, mass=mass, damping=damping, capsule=body)
