"""The benchmarks' peers compute what our kernels compute (so the speed ratios compare equal work):
the numpy horizon peer with slices, the variable-projection scipy fit (its analytic Jacobian
against finite differences, its optimum against the naive 10-parameter fit's), the 2-process EM
pyramid peer against the one-process one."""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import fit_speed  # noqa: E402
from _fit_varpro_scipy import basis_and_derivatives, varpro_fit  # noqa: E402
from horizon_speed import horizon_numpy_slices  # noqa: E402

from jaxrender.shadows import horizon_map  # noqa: E402

FD_TOL = 1e-6  # central differences of a smooth basis at step 1e-6: truncation ~1e-12, rounding ~1e-10


def _directions(n, seed):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.2
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_numpy_slices_peer_equals_horizon_map():
    h = np.random.default_rng(0).random((24, 24)).astype(np.float32)
    ours = np.asarray(horizon_map(jnp.asarray(h), method="search"))
    np.testing.assert_allclose(horizon_numpy_slices(h), ours, rtol=1e-6, atol=1e-7)  # float32 rounding


def test_varpro_basis_derivatives_match_finite_differences():
    dirs, view = _directions(150, 1), np.array([0.0, 0.0, 1.0])
    theta = np.array([0.15, -0.1, np.log(0.12), np.log(0.25)])
    _, dbasis = basis_and_derivatives(theta, dirs, view)
    for k in range(4):
        e = np.zeros(4)
        e[k] = 1e-6
        fd = (basis_and_derivatives(theta + e, dirs, view)[0] - basis_and_derivatives(theta - e, dirs, view)[0]) / 2e-6
        np.testing.assert_allclose(dbasis[k], fd, atol=FD_TOL * max(1.0, np.abs(fd).max()))


def test_varpro_peer_reaches_the_naive_peers_optimum():
    """Same model (fit_speed.numpy_model), same start: the same cost at the optimum."""
    dirs, view = _directions(200, 2), np.array([0.0, 0.0, 1.0])
    x_true = np.array([0.3, 0.2, 0.1, 0.6, 0.5, 0.4, 0.1, -0.2, np.log(0.1), np.log(0.2)])
    ratio = fit_speed.numpy_model(x_true, dirs, view) + 0.002 * np.random.default_rng(3).normal(size=(200, 3))
    weight = np.ones(200)
    x0 = x_true + np.r_[np.zeros(6), 0.05, 0.05, 0.3, -0.3]
    x, sol = varpro_fit(ratio, weight, dirs, view, x0)
    naive = fit_speed.scipy_fit(ratio, weight, dirs, view, x0)
    assert abs(sol.cost - naive.cost) <= 1e-6 * naive.cost  # both converge to the same least-squares optimum
    model = fit_speed.numpy_model(x, dirs, view)
    assert abs(0.5 * np.sum((ratio - model) ** 2) - sol.cost) <= 1e-9 * sol.cost  # x carries the projected rho


def _abort():
    import os

    os.abort()


def _double(x):
    return 2 * x


def test_a_peer_that_aborts_is_reported_unavailable_not_fatal():
    """Mitsuba's LLVM backend can die with SIGABRT (old LLVM, AVX-512): the child process dies, the
    benchmark gets `PeerUnavailable` with the signal, and a dead peer stays dead."""
    import pytest
    from _peers import ChildPeer, PeerUnavailable

    with ChildPeer("test peer") as peer:
        assert peer.call(_double, 21) == 42
        with pytest.raises(PeerUnavailable, match="test peer killed by SIGABRT"):
            peer.call(_abort)
        with pytest.raises(PeerUnavailable, match="SIGABRT"):
            peer.call(_double, 1)


def test_mitsuba_variant_probe_renders_in_a_child():
    from _peers import mitsuba_variant

    variant, note = mitsuba_variant(("no_such_variant", "scalar_rgb"))
    assert variant == "scalar_rgb", note
    assert "FALLBACK" in note and "no_such_variant" in note
