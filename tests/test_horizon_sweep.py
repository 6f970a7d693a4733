"""The O(N) convex-hull horizon sweep against the full search of `horizon_map`, a plain brute force
and the numba peers of the benchmarks (a compiled scan and a compiled sweep, written apart).
float64 is on in the tests (conftest.py); float32 inputs are cast explicitly."""

import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.shadows import _horizon, horizon_directions, horizon_map

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _horizon_numba import horizon_scan_numba, horizon_sweep_numba  # noqa: E402

REL_TOL = 1e-6  # the sweep equals the search "within float rounding"; both evaluate one formula
F32_TOL = 1e-6  # float32: same formula per sample, so the same rounding (a few ulps at most)


def _sweep(h, directions=8, texel_size=1.0):
    return np.asarray(horizon_map(jnp.asarray(h), directions=directions, texel_size=texel_size, method="sweep"))


def _search(h, directions=8, texel_size=1.0):
    return np.asarray(horizon_map(jnp.asarray(h), directions=directions, texel_size=texel_size, method="search"))


def _plain_bruteforce(h, directions, texel):
    """Every step of every lattice path, np.roll per step (independent of the kernels)."""
    n = h.shape[0]
    out = np.zeros((directions,) + h.shape)
    for d, (ex, ey) in enumerate(horizon_directions(directions)):
        for k in range(1, n):
            ahead = np.roll(h, (-k * int(ey), -k * int(ex)), axis=(0, 1))
            out[d] = np.maximum(out[d], (ahead - h) / (k * math.hypot(ex, ey) * texel))
    return out


def _assert_rel(a, b, tol):
    scale = np.maximum(np.abs(b), np.finfo(b.dtype).tiny)
    assert np.all(np.abs(a - b) <= tol * scale), float(np.max(np.abs(a - b) / scale))


@pytest.mark.parametrize("size", [5, 16])
@pytest.mark.parametrize("directions", [4, 8])
def test_sweep_equals_search_float64(size, directions):
    h = np.random.default_rng(size + directions).random((size, size))
    sweep, search = _sweep(h, directions, 0.5), _search(h, directions, 0.5)
    assert sweep.dtype == np.float64
    _assert_rel(sweep, search, REL_TOL)
    _assert_rel(sweep, _plain_bruteforce(h, directions, 0.5), REL_TOL)


def test_sweep_equals_search_with_ties_and_ripples():
    """Plateaus (many equal heights: ties in the hull walk) and a smooth ripple field."""
    rng = np.random.default_rng(7)
    steps = np.round(rng.random((16, 16)) * 3.0)  # 4 height levels
    y, x = np.mgrid[0:16, 0:16] / 16 * 2 * np.pi
    ripples = (np.sin(5 * x + 0.7 * np.sin(2 * y)) + 0.3 * np.sin(9 * x + 3 * y)
               + 0.02 * rng.standard_normal((16, 16)))
    for h in (steps, ripples, np.zeros((16, 16))):  # one shape: the kernels compile once per module
        _assert_rel(_sweep(h, 8, 0.5), _search(h, 8, 0.5), REL_TOL)


def test_sweep_float32_matches_float64_search():
    h = np.random.default_rng(3).random((16, 16))
    sweep32 = _sweep(h.astype(np.float32), 8, 0.5)
    assert sweep32.dtype == np.float32
    _assert_rel(sweep32, _search(h.astype(np.float32), 8, 0.5), F32_TOL)
    ref = _search(h, 8, 0.5)
    np.testing.assert_allclose(sweep32, ref, rtol=1e-5, atol=1e-6)  # float32 heights in [0, 1): rounding of h


def test_numba_peers_equal_the_kernels():
    """The benchmark's peers compute the same maps (so their timings compare equal work)."""
    h = np.random.default_rng(11).random((16, 16))
    ref = _search(h, 8, 0.5)
    _assert_rel(horizon_scan_numba(h, 8, 0.5), ref, REL_TOL)
    _assert_rel(horizon_sweep_numba(h, 8, 0.5), ref, REL_TOL)


def test_sweep_gradient_matches_finite_differences():
    """The slopes are computed from the tangent vertices with a differentiable formula."""
    h = jnp.asarray(np.random.default_rng(5).random((16, 16)))
    w = jnp.asarray(np.random.default_rng(6).random((8, 16, 16)))

    @jax.jit
    def loss(a):
        return jnp.sum(w * horizon_map(a, directions=8, texel_size=0.5, method="sweep"))

    grad = jax.jit(jax.grad(loss))(h)
    eps = 1e-6  # piecewise linear: central differences are exact away from switches of the argmax
    for idx in [(0, 0), (5, 7), (15, 3)]:
        e = jnp.zeros_like(h).at[idx].set(eps)
        fd = (loss(h + e) - loss(h - e)) / (2 * eps)
        assert abs(float(fd) - float(grad[idx])) <= 1e-6 * max(1.0, abs(float(fd)))


def test_auto_uses_the_sweep_from_the_threshold(monkeypatch):
    h = jnp.asarray(np.random.default_rng(2).random((16, 16)), jnp.float32)
    calls = []
    real = _horizon.lattice_sweep
    monkeypatch.setattr(_horizon, "lattice_sweep", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(_horizon, "SWEEP_MIN_SIZE", 16)
    _horizon._horizon_map(h, directions=8)  # traced eagerly: the dispatch is plain Python
    assert calls == [1]
    monkeypatch.setattr(_horizon, "SWEEP_MIN_SIZE", 17)
    _horizon._horizon_map(h, directions=8)
    assert calls == [1]


def test_sweep_rejects_what_it_cannot_do():
    with pytest.raises(ValueError, match="square"):
        horizon_map(jnp.zeros((8, 10)), method="sweep")
    with pytest.raises(ValueError, match="4 or 8"):
        horizon_map(jnp.zeros((8, 8)), directions=6, method="sweep")
    with pytest.raises(ValueError, match="method"):
        horizon_map(jnp.zeros((8, 8)), method="fast")
