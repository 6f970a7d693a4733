"""The garment that moves: Verlet cloth continued frame to frame, pins driven by a body motion."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from sims.cloth import BodyMotion, ClothState, advance_cloth, animate_cloth, cloth_mesh, drape_garment

_REF_TOL_F64 = 1e-10   # m: the same arithmetic in another order, 60 steps
_REF_TOL_F32 = 2e-4    # m: float32 Verlet over 60 steps of a 0.6 m cloth (positions ~1, dt^2 terms ~1e-6)
_STRAIN_TOL = 0.08     # mean structural stretch while dancing (5 % at rest under gravity, plus the motion)
_SMALL = dict(rows=6, cols=5, width=0.6, height=0.6, shoulder_span=0.4, body_radius=0.05, top=1.0, steps=1500)


def _motion():
    return BodyMotion(turn=math.radians(30.0), turn_period=1.0, sway=0.05, sway_period=0.5, arm_lift=0.1,
                      arm_period=0.8, ramp=0.1, axis_z=-0.14)


def _reference(cloth, motion, steps, *, gravity=9.81):
    """Float64 numpy: position Verlet with damping, capsule push-out, pins set to the closed-form motion."""
    x = np.asarray(cloth.state.x, np.float64)
    xp = np.asarray(cloth.state.x_prev, np.float64)
    i, j = np.asarray(cloth.springs.i), np.asarray(cloth.springs.j)
    rest, k = np.asarray(cloth.springs.rest, np.float64), np.asarray(cloth.springs.stiffness, np.float64)
    pins = np.asarray(cloth.pin_index)
    pin_rest = np.asarray(cloth.pin_rest, np.float64)
    hand = np.asarray(cloth.hand, np.float64)
    cx0, cz, radius, y0, y1 = np.asarray(cloth.capsule, np.float64)
    dt, mass = cloth.dt, cloth.mass
    for n in range(steps):
        t = (n + 1) * dt
        u = min(max(t / motion.ramp, 0.0), 1.0)
        r = u * u * (3 - 2 * u)
        theta = motion.turn * r * math.sin(2 * math.pi * t / motion.turn_period)
        sway = motion.sway * r * math.sin(2 * math.pi * t / motion.sway_period)
        lift = motion.arm_lift * 0.5 * (1 - math.cos(2 * math.pi * t / motion.arm_period))
        d = x[j] - x[i]
        length = np.linalg.norm(d, axis=-1)
        f = (k * (length - rest) / length)[:, None] * d
        force = np.zeros_like(x)
        np.add.at(force, i, f)
        np.add.at(force, j, -f)
        acc = force / mass + np.asarray([0.0, -gravity, 0.0])
        xn = x + (1 - cloth.damping * dt) * (x - xp) + acc * dt * dt
        axis_pt = np.stack([np.full(len(x), cx0 + sway), np.clip(xn[:, 1], y0, y1), np.full(len(x), cz)], -1)
        off = xn - axis_pt
        dist = np.linalg.norm(off, axis=-1)
        inside = dist < radius
        xn[inside] = axis_pt[inside] + off[inside] * (radius / dist[inside])[:, None]
        for p, idx in enumerate(pins):
            q = pin_rest[p] + hand[p] * np.asarray([0.5 * lift * np.sign(pin_rest[p, 0]), lift, 0.0])
            q = q - np.asarray([0.0, 0.0, cz])
            q = np.asarray([math.cos(theta) * q[0] + math.sin(theta) * q[2], q[1],
                            -math.sin(theta) * q[0] + math.cos(theta) * q[2]])
            xn[idx] = q + np.asarray([sway, 0.0, cz])
        x, xp = xn, x
    return x


def test_motion_starts_at_rest_and_pins_follow_it():
    m = _motion()
    rest = jnp.asarray([[0.2, 1.0, 0.0], [-0.3, 1.0, 0.05]])
    hand = jnp.asarray([0.0, 1.0])
    np.testing.assert_allclose(m.pins(rest, hand, jnp.asarray(0.0)), rest, atol=1e-15)
    # zero velocity at t = 0: a central difference around 0 of the eased motion vanishes to O(h^2)
    h = 1e-5
    v = (m.pins(rest, hand, jnp.asarray(h)) - m.pins(rest, hand, jnp.asarray(0.0))) / h
    assert float(jnp.max(jnp.abs(v))) < 1e-3
    # a shoulder pin keeps its height and its distance from the body axis (a turn plus a sway along x)
    t = jnp.asarray(0.37)
    theta, sway, lift = (float(a) for a in m.pose(t))
    p = np.asarray(m.pins(rest, hand, t))
    q = p[0] - np.asarray([sway, 0.0, -0.14])
    np.testing.assert_allclose(q[1], 1.0, atol=1e-12)
    np.testing.assert_allclose(np.hypot(q[0], q[2]), np.hypot(0.2, 0.14), atol=1e-12)
    np.testing.assert_allclose(math.atan2(-(q[2]), q[0]) - math.atan2(-0.14, 0.2), theta, atol=1e-12)
    np.testing.assert_allclose(p[1, 1], 1.0 + lift, atol=1e-12)   # the hand rose


def test_advance_matches_a_float64_reference_and_float32():
    cloth = drape_garment(**_SMALL)
    m = _motion()
    ref = _reference(cloth, m, 60)
    got = jax.jit(lambda c: advance_cloth(c, c.state, m, steps=60))(cloth)
    np.testing.assert_allclose(np.asarray(got.x), ref, atol=_REF_TOL_F64)
    np.testing.assert_allclose(float(got.time), 60 * cloth.dt, rtol=1e-12)
    c32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, cloth)
    got32 = jax.jit(lambda c: advance_cloth(c, c.state, m, steps=60))(c32)
    assert got32.x.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got32.x, np.float64), ref, atol=_REF_TOL_F32)
    assert np.abs(ref - np.asarray(cloth.state.x)).max() > 1e-3   # the cloth did move in 0.03 s


def test_frames_continue_from_the_previous_state():
    """Two frames in one call equal one frame, then a second one started from its end state
    (the simulation is continued, not re-settled); the pinned points sit on the motion."""
    cloth = drape_garment(**_SMALL)
    m = _motion()
    frame_dt = 0.02
    xs, last = jax.jit(lambda c: animate_cloth(c, m, frames=2, frame_dt=frame_dt))(cloth)
    one = advance_cloth(cloth, cloth.state, m, steps=40)
    two = advance_cloth(cloth, one, m, steps=40)
    np.testing.assert_allclose(xs[0], one.x, atol=1e-12)
    np.testing.assert_allclose(xs[1], two.x, atol=1e-12)
    np.testing.assert_allclose(last.x_prev, two.x_prev, atol=1e-12)
    # re-settling would start from zero velocity: a continued state carries the motion's velocity
    restart = advance_cloth(cloth, ClothState(one.x, one.x, one.time), m, steps=40)
    assert np.abs(np.asarray(restart.x) - np.asarray(two.x)).max() > 1e-4
    for f, x in enumerate(np.asarray(xs)):
        t = jnp.asarray((f + 1) * 40 * cloth.dt)
        np.testing.assert_allclose(x[np.asarray(cloth.pin_index)], m.pins(cloth.pin_rest, cloth.hand, t), atol=1e-12)


def test_dancing_garment_stays_a_garment():
    """A second of the slow turn and sway: finite, stretched little, turning with the body."""
    cloth = drape_garment(**_SMALL)
    m = BodyMotion(turn=math.radians(30.0), turn_period=4.0, sway=0.05, sway_period=2.0, arm_lift=0.1, ramp=0.3,
                   axis_z=-0.14)
    xs, last = jax.jit(lambda c: animate_cloth(c, m, frames=10, frame_dt=0.1))(cloth)
    x = np.asarray(xs)
    assert np.all(np.isfinite(x))
    springs = cloth.springs
    structural = np.asarray(springs.kind) == 0
    d = x[-1][np.asarray(springs.j)] - x[-1][np.asarray(springs.i)]
    strain = np.linalg.norm(d, axis=-1) / np.asarray(springs.rest) - 1
    assert np.abs(strain[structural]).mean() < _STRAIN_TOL
    # at t = 1 s the body has turned by +30 deg sin(pi/2): the hem (free) follows the same way,
    # its mean angle about the body axis having moved the same sign
    def angle(p):
        return np.arctan2(-(p[..., 2] + 0.14), p[..., 0])
    hem0, hem1 = np.asarray(cloth.state.x)[-5:], x[-1][-5:]
    turned = np.mean(angle(hem1) - angle(hem0))
    assert turned > 0.1 * math.radians(30.0), turned
    mesh = cloth_mesh(cloth, last.x)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(mesh.normals), axis=-1), 1.0, atol=1e-9)
