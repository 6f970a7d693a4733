"""Solving in lanes (`fitting.lanes`): a batch of texels stepped P at a time, a lane taking the next
texel when its own is done, gives every texel exactly the result of its own solve run alone (the
backend's one-texel while loop), bit for bit, for both stepping backends; and a texel's result does
not depend on the batch it is in (its place, the other texels, the batch size).

96 texels of the toolkit's BRDF under 64 of the paper's lights (1 % noise), float32 (multiples of
the 16 float32 lanes of a vector: the one-texel solves, vmapped, run in full vectors too)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting import lm_native, lm_optimistix
from fitting._varpro import lights_of
from fitting.lanes import solve_in_lanes
from fitting.lm import _initial_theta, _prepare, default_tolerances
from fitting.residual import Problem, VarProResidual
from fitting.synth import paper_light_directions, stratified_light_subset
from jaxrender.brdf import BTFTexel, reflectance

N, MAX_STEPS = 96, 40   # more texels than lanes (64): lanes are refilled
ROUNDING = 1e-3
LIGHTS = jnp.asarray(paper_light_directions()[stratified_light_subset(jax.random.key(0), 64)], jnp.float32)
VIEW = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    tilt, az = rng.uniform(0, 0.5, N), rng.uniform(0, 2 * np.pi, N)
    normal = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], -1)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    texels = BTFTexel.single(f32(rng.uniform(0.1, 0.6, (N, 3))), f32(rng.uniform(0, 1, (N, 3))), f32(normal),
                             f32(rng.uniform(0.05, 0.4, N)), f32(rng.uniform(0.05, 0.4, N)))
    ratio = jax.vmap(lambda t: jax.vmap(lambda wi: reflectance(t, wi, VIEW))(LIGHTS))(texels)
    ratio = ratio * (1 + 0.01 * f32(rng.normal(size=ratio.shape)))
    return ratio, jnp.ones(ratio.shape[:2], jnp.float32)


def _solves(module, ratio, weight, lanes_only=False, active=None):
    r, w, _ = jax.vmap(_prepare)(ratio, weight)
    lights = lights_of(LIGHTS, VIEW)
    theta0 = jax.vmap(lambda a, b: _initial_theta(a, b, lights, "reciprocal"))(r, w)
    rtol, atol = default_tolerances(jnp.float32)

    def make(p):
        return Problem(p[0], p[1], lights, None, None)

    lanes = solve_in_lanes(module.Steps("reciprocal", MAX_STEPS, rtol, atol), theta0, (r, w), make, active)
    if lanes_only:
        return lanes
    alone = jax.vmap(lambda th, a, b: module.solve(VarProResidual("reciprocal"), th, make((a, b)), MAX_STEPS, rtol,
                                                   atol))(theta0, r, w)
    return lanes, alone


@pytest.mark.parametrize("module", [lm_native, lm_optimistix], ids=["native", "optimistix"])
def test_lanes_give_each_texel_its_own_solve(data, module):
    with jax.enable_x64(False):   # a float32 program (optimistix's constants follow the x64 switch)
        (theta, ok, steps), (theta1, ok1, steps1) = jax.jit(lambda r, w: _solves(module, r, w))(*data)
    if module is lm_native:   # bit for bit
        np.testing.assert_array_equal(np.asarray(theta), np.asarray(theta1))
        np.testing.assert_array_equal(np.asarray(steps), np.asarray(steps1))
    else:   # optimistix's linear solves (lineax) round differently in another batch shape: the same
        # iterates to rounding (measured 1.1e-4 at most in theta, 5e-5 relative)
        np.testing.assert_allclose(np.asarray(theta), np.asarray(theta1), rtol=ROUNDING, atol=ROUNDING)
    np.testing.assert_array_equal(np.asarray(ok), np.asarray(ok1))
    assert np.ptp(np.asarray(steps)) > 0   # texels of different lengths: lanes were refilled


def test_a_texel_does_not_depend_on_its_batch(data):
    """A texel's result, bit for bit, whatever its place in a batch of the same size and whatever
    the other texels (shuffled, half of them replaced by copies of others). The engine fits tiles
    of one shape on every device (`fitting.engine.LANES_TILE`), as XLA may compile a batch of
    another size into other roundings."""
    ratio, weight = data
    fn = jax.jit(lambda r, w: _solves(lm_native, r, w, lanes_only=True))
    rng = np.random.default_rng(1)
    order = rng.permutation(N)
    order[N // 2:] = order[rng.integers(0, N // 2, N - N // 2)]
    with jax.enable_x64(False):
        whole = fn(ratio, weight)
        other = fn(ratio[order], weight[order])
    for a, b in zip(other, whole):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[order])


@pytest.mark.parametrize("active", [0, 40, N])
def test_only_the_active_texels_are_solved(data, active):
    """A batch's padding is not solved: with `active` = k the first k texels get the results they
    get in the whole batch, bit for bit, and the rest are left at zero, no step taken."""
    ratio, weight = data
    with jax.enable_x64(False):
        whole = jax.jit(lambda r, w: _solves(lm_native, r, w, lanes_only=True))(ratio, weight)
        part = jax.jit(lambda r, w, k: _solves(lm_native, r, w, lanes_only=True, active=k))(ratio, weight, active)
    for a, b in zip(part, whole):
        np.testing.assert_array_equal(np.asarray(a)[:active], np.asarray(b)[:active])
        assert not np.any(np.asarray(a)[active:])
    assert np.all(np.asarray(whole[2]) > 0)   # every texel of the whole batch took steps
