"""Ripple automaton (paper 001 eqs. 1-4) against an independent float64 loop reference written
here from the equations, plus conservation, creep properties, vmap, gradients and wavelength."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sims import RippleParams, creep, dominant_wavelength, init_ripples, ripple_step, simulate_ripples
from sims._transport import sand_quantum

_STEP_TOL = 1e-12  # float64, a few dozen additions per cell
_MASS_TOL = 1e-14  # float64 over 3000 steps: sand moves on a fixed-point grid, so the total changes only when
# the field is rounded onto a coarser grid (its top height crossing a power of two); measured 0.7-2.4e-15
_WAVELENGTH_ON_BIN_RTOL = 3e-3  # whole periods per grid (an FFT bin): measured 1.5e-4, 1.1e-3 with the noise
_WAVELENGTH_OFF_BIN_RTOL = 0.035  # between two FFT bins, the parabola through the log power: measured <= 3.1 %
_GRAD_RTOL = 1e-6  # the split hop is piecewise linear: central differences are exact away from kinks


def reference_step(h, *, L0, q, b, D, wind_deg, hop):
    """Eqs. 1-4 cell by cell (float64 loops): hop (split bilinear / nearest), then creep."""
    h = np.asarray(h, np.float64)
    ny, nx = h.shape
    cx, cy = math.cos(math.radians(wind_deg)), math.sin(math.radians(wind_deg))
    cx, cy = (0.0 if abs(cx) < 1e-9 else cx), (0.0 if abs(cy) < 1e-9 else cy)
    mid = h - q
    for y in range(ny):
        for x in range(nx):
            L = L0 + b * h[y, x]
            tx, ty = x + L * cx, y + L * cy
            if hop == "nearest":
                mid[int(round(ty)) % ny, int(round(tx)) % nx] += q
                continue
            x0, y0 = math.floor(tx), math.floor(ty)
            fx, fy = tx - x0, ty - y0
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    mid[(y0 + dy) % ny, (x0 + dx) % nx] += q * wy * wx
    return reference_creep(mid, D)


def reference_creep(h, D):
    ny, nx = h.shape
    out = np.empty_like(h)
    for y in range(ny):
        for x in range(nx):
            nn = sum(h[(y + dy) % ny, (x + dx) % nx] for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)))
            nnn = sum(h[(y + dy) % ny, (x + dx) % nx] for dy, dx in ((-1, -1), (-1, 1), (1, -1), (1, 1)))
            out[y, x] = h[y, x] + D * (nn / 6.0 + nnn / 12.0 - h[y, x])
    return out


@pytest.mark.parametrize("hop", ["split", "nearest"])
@pytest.mark.parametrize("wind_deg", [0.0, 90.0, 33.0, 200.0])
def test_step_matches_loop_reference(hop, wind_deg):
    h = init_ripples(jax.random.key(1), (7, 9), low=0.0, high=3.0)  # non-square: catches swapped axes
    params = RippleParams(L0=2.3, q=0.4, b=1.7, D=0.6, wind_deg=wind_deg, hop=hop)
    ours = np.asarray(jax.jit(ripple_step)(h, params))
    ref = reference_step(np.asarray(h), L0=2.3, q=0.4, b=1.7, D=0.6, wind_deg=wind_deg, hop=hop)
    np.testing.assert_allclose(ours, ref, atol=_STEP_TOL, rtol=0)
    if wind_deg == 33.0:  # no-jit (op by op) gives the same; once per hop mode, it is slow
        np.testing.assert_allclose(np.asarray(ripple_step(h, params)), ref, atol=_STEP_TOL, rtol=0)


def test_paper_defaults_and_long_hops():
    assert (RippleParams().L0, RippleParams().q, RippleParams().b, RippleParams().D) == (7.3, 0.6, 2.0, 0.8)
    # hops longer than the grid wrap around (periodic)
    h = init_ripples(jax.random.key(2), (5, 6), low=1.0, high=1.5)
    ours = np.asarray(jax.jit(ripple_step)(h, RippleParams()))
    ref = reference_step(np.asarray(h), L0=7.3, q=0.6, b=2.0, D=0.8, wind_deg=0.0, hop="split")
    np.testing.assert_allclose(ours, ref, atol=_STEP_TOL, rtol=0)


@pytest.mark.parametrize("hop,wind_deg", [("split", 0.0), ("nearest", 0.0), ("split", 30.0)])
def test_total_sand_conserved(hop, wind_deg):
    h0 = init_ripples(jax.random.key(3), (24, 32))
    h = simulate_ripples(h0, RippleParams(hop=hop, wind_deg=wind_deg), steps=3000)
    assert float(jnp.std(h)) > 0.3  # ripples have grown: the hops did move sand around
    drift = abs(float(jnp.sum(h)) - float(jnp.sum(h0))) / float(jnp.sum(h0))
    assert drift < _MASS_TOL


def exact_total(field) -> float:
    """The exact sum of the cells (math.fsum of their float64 values, exact for float32 cells)."""
    return math.fsum(np.asarray(field, np.float64).ravel().tolist())


def assert_steps_conserve_bit_for_bit(step, h0, amount, steps):
    """Run `steps` steps; every step whose sand grid is not coarser than the last one's leaves the
    exact total unchanged, bit for bit; a step whose grid coarsened (the top height crossed a power
    of two) rounds the field onto it: at most half a quantum per cell. `amount(h)`: what cells send."""
    h, total = h0, exact_total(h0)
    grid_before = float(jnp.max(sand_quantum(h0, amount(h0))))
    exact_steps = 0
    for _ in range(steps):
        grid = float(jnp.max(sand_quantum(h, amount(h))))
        h = step(h)
        new_total = exact_total(h)
        if grid <= grid_before:
            assert new_total == total
            exact_steps += 1
        else:
            assert abs(new_total - total) <= 0.5 * grid * h.size
        total, grid_before = new_total, grid
    assert exact_steps >= steps // 2
    return h


@pytest.mark.parametrize("hop,wind_deg", [("split", 0.0), ("nearest", 0.0), ("split", 30.0), ("split", 90.0)])
def test_step_conserves_sand_bit_for_bit_float32(hop, wind_deg):
    """In float32 what leaves a cell is what arrives elsewhere, bit for bit. The field is
    first put on a coarse binary grid (2^-12), finer grids contain it, so the first step rounds
    nothing; then every step whose sand grid did not coarsen keeps the exact total."""
    h0 = init_ripples(jax.random.key(11), (24, 40), dtype=jnp.float32)
    h0 = jnp.round(h0 * 4096.0) / 4096.0
    params = RippleParams(L0=9.0, hop=hop, wind_deg=wind_deg)
    step = jax.jit(lambda h: ripple_step(h, params))
    h1 = step(h0)
    assert h1.dtype == jnp.float32 and float(jnp.max(jnp.abs(h1 - h0))) > 0.1  # sand did move
    assert exact_total(h1) == exact_total(h0)
    assert_steps_conserve_bit_for_bit(step, h1, lambda h: 0.6, 40)


def test_creep_constant_symmetric_and_vs_stencil():
    const = jnp.full((6, 8), 1.25)
    np.testing.assert_allclose(np.asarray(creep(const, 0.8)), 1.25, atol=_STEP_TOL, rtol=0)
    h = init_ripples(jax.random.key(4), (6, 8), low=0.0, high=2.0)
    out = np.asarray(creep(h, 0.7))
    np.testing.assert_allclose(out, reference_creep(np.asarray(h), 0.7), atol=_STEP_TOL, rtol=0)
    # isotropic: commutes with transposition and mirror flips
    np.testing.assert_allclose(np.asarray(creep(h.T, 0.7)), out.T, atol=_STEP_TOL, rtol=0)
    np.testing.assert_allclose(np.asarray(creep(h[::-1, ::-1], 0.7)), out[::-1, ::-1], atol=_STEP_TOL, rtol=0)
    # a smoothing: conserves the total and lowers the variance
    assert abs(out.sum() - float(jnp.sum(h))) < _STEP_TOL * h.size
    assert out.var() < float(jnp.var(h))


def test_batch_and_vmap_equal_loop():
    h0 = init_ripples(jax.random.key(5), (3, 10, 12))
    params = RippleParams(wind_deg=45.0)
    looped = np.stack([np.asarray(simulate_ripples(h, params, steps=20)) for h in h0])
    batched = np.asarray(simulate_ripples(h0, params, steps=20))
    vmapped = np.asarray(jax.vmap(lambda h: simulate_ripples(h, params, steps=20))(h0))
    np.testing.assert_allclose(batched, looped, atol=_STEP_TOL, rtol=0)
    np.testing.assert_allclose(vmapped, looped, atol=_STEP_TOL, rtol=0)


def test_gradient_wrt_hop_parameters_vs_central_differences():
    h0 = init_ripples(jax.random.key(6), (8, 10))

    @jax.jit
    def loss(L0, b, q):
        h = simulate_ripples(h0, RippleParams(L0=L0, b=b, q=q), steps=5)
        return jnp.sum(jnp.sin(h) * jnp.arange(h.size, dtype=h.dtype).reshape(h.shape) / h.size)

    args = (jnp.array(3.37), jnp.array(1.21), jnp.array(0.43))
    grad = jax.grad(loss, argnums=(0, 1, 2))(*args)
    fwd = jax.jacfwd(loss, argnums=(0, 1, 2))(*args)
    eps = 1e-6
    for i in range(3):
        plus = list(args)
        minus = list(args)
        plus[i] = plus[i] + eps
        minus[i] = minus[i] - eps
        fd = (float(loss(*plus)) - float(loss(*minus))) / (2 * eps)
        assert abs(fd) > 1e-3  # the loss does depend on the parameter
        assert np.isfinite(float(grad[i]))
        np.testing.assert_allclose(float(grad[i]), fd, rtol=_GRAD_RTOL)
        np.testing.assert_allclose(float(fwd[i]), fd, rtol=_GRAD_RTOL)


def test_wavelength_grows_linearly_with_L0():
    """Small version of benchmarks/ripples_wavelength.py (128x128, 3000 steps): 32x128, 1500 steps."""
    L0s = jnp.array([2.0, 3.5, 5.0, 6.5, 8.0, 9.5])
    h0 = init_ripples(jax.random.key(0), (32, 128))
    fields = jax.jit(jax.vmap(lambda L0: simulate_ripples(h0, RippleParams(L0=L0), steps=1500)))(L0s)
    lam = np.asarray(dominant_wavelength(fields))
    slope, intercept = np.polyfit(np.asarray(L0s), lam, 1)
    r2 = 1 - np.sum((np.polyval((slope, intercept), L0s) - lam) ** 2) / np.sum((lam - lam.mean()) ** 2)
    assert r2 >= 0.9
    assert slope > 1.0  # grows with L0 (about 1.8 cells per unit of L0 here)
    assert np.all(np.diff(lam) > 0)


@pytest.mark.parametrize("wavelength,rtol", [(16.0, _WAVELENGTH_ON_BIN_RTOL), (12.8, _WAVELENGTH_ON_BIN_RTOL),
                                             (8.0, _WAVELENGTH_ON_BIN_RTOL), (7.3, _WAVELENGTH_OFF_BIN_RTOL),
                                             (11.1, _WAVELENGTH_OFF_BIN_RTOL), (20.0, _WAVELENGTH_OFF_BIN_RTOL),
                                             (42.0, _WAVELENGTH_OFF_BIN_RTOL)])
def test_dominant_wavelength_of_known_waves(wavelength, rtol):
    """`dominant_wavelength` (behind the wavelength-vs-L0 result) on synthetic fields of known
    wavelength: along x and, transposed, along y; with noise (std 0.2 of a unit wave) and in a
    batch. 16, 12.8 and 8 cells are whole numbers of periods in 128 cells (an FFT bin), the
    others fall between bins (20 cells is 6.4 periods, the worst case of the parabolic refinement)."""
    n = 128
    x = np.arange(n)
    wave = np.sin(2 * np.pi * x / wavelength + 0.3)[None, :] * (1.0 + 0.1 * np.cos(np.arange(32) / 5.0))[:, None]
    noisy = wave + 0.2 * np.random.default_rng(0).normal(size=wave.shape)
    for field, axis in ((wave, -1), (wave.T, -2), (noisy, -1)):
        np.testing.assert_allclose(float(dominant_wavelength(jnp.asarray(field), axis=axis)), wavelength, rtol=rtol)
    batch = np.stack([wave, np.roll(noisy, 5, axis=-1), 3.0 * wave + 1.0])
    np.testing.assert_allclose(np.asarray(dominant_wavelength(jnp.asarray(batch))), wavelength, rtol=rtol)


def test_no_retrace_for_new_parameter_values():
    """Numeric parameters are traced pytree leaves: new values reuse the compiled scan."""
    h0 = init_ripples(jax.random.key(8), (6, 8))
    simulate_ripples(h0, RippleParams(L0=3.0), steps=3)
    size = simulate_ripples._cache_size()
    for L0 in (3.5, 4.0, 4.5):
        simulate_ripples(h0, RippleParams(L0=L0, q=0.5, b=1.0, D=0.5), steps=3)
    assert simulate_ripples._cache_size() == size
