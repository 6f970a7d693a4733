"""One entry point for every light-shaft method, with antialiasing.

    image = shafts.render(scene)                                   # adaptive (default), 1 sample per pixel
    image = shafts.render(scene, method="planes", samples_per_pixel=16, planes=30, subplanes=6)
    image = shafts.render(scene, target_error=0.02)                # counts chosen for 2 % (`choose_counts`)

`samples_per_pixel` = k*k renders a regular k x k grid of sub-pixel positions per pixel and
averages them (a box filter, as Mitsuba's `box` reconstruction filter): the scene is rendered at
k times its width and height, whose pixel (k i + a, k j + b) has its centre at sub-pixel position
((b + 1/2) / k, (a + 1/2) / k) of pixel (i, j), and each k x k block is averaged. So every method
gets it unchanged (its shadow maps and tables are built once, not per sub-pixel), it is
deterministic, and differentiable like the method itself.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
from jaxtyping import Array, Float

from ._adaptive import render_adaptive
from ._equiangular import render_equiangular
from ._error_target import choose_counts
from ._planes import render_planes
from ._raymarch import render_raymarch
from ._scene import ShaftsScene

__all__ = ["render", "supersample", "METHODS", "DEFAULT_METHOD"]

METHODS: dict[str, Callable] = {
    "adaptive": render_adaptive,  # equiangular in-scattering where it is needed, interpolated between
    "equiangular": render_equiangular,  # fast single scattering (angle steps seen from the light), every pixel
    "planes": render_planes,  # the paper's sample planes (8-bit emulation available)
    "raymarch": render_raymarch,  # the exact reference: shadow rays, uniform steps
}
DEFAULT_METHOD = "adaptive"


def grid_side(samples_per_pixel: int) -> int:
    """k for samples_per_pixel = k*k; ValueError for anything else."""
    n = int(samples_per_pixel)
    k = math.isqrt(max(n, 0))
    if n < 1 or k * k != n:
        raise ValueError(f"samples_per_pixel must be a perfect square >= 1 (1, 4, 9, 16, ...), got {samples_per_pixel}")
    return k


def _box_down(x: Array, k: int) -> Array:
    h, w = x.shape[0] // k, x.shape[1] // k
    return x.reshape((h, k, w, k) + x.shape[2:]).mean(axis=(1, 3))


def supersample(render_fn: Callable[[ShaftsScene], object], scene: ShaftsScene, samples_per_pixel: int = 1):
    """render_fn(scene) with `samples_per_pixel` (= k*k) regular sub-pixel samples per pixel,
    box-filtered. render_fn returns an (H, W, C) image or a pytree of such images (e.g. a
    method's return_parts), each averaged the same way."""
    k = grid_side(samples_per_pixel)
    if k == 1:
        return render_fn(scene)
    cam = scene.camera
    out = render_fn(scene.with_size(cam.width * k, cam.height * k))
    return jax.tree_util.tree_map(lambda x: _box_down(x, k), out)


def _frame(method: str, samples_per_pixel: int, options: dict):
    """scene -> the frame of `method` with `options`, supersampled."""
    fn = METHODS[method]
    return lambda s: supersample(lambda t: fn(t, **options), s, samples_per_pixel)


@functools.lru_cache(maxsize=16)
def _jitted(method: str, samples_per_pixel: int, options: tuple):
    return jax.jit(_frame(method, samples_per_pixel, dict(options)))


def render(scene: ShaftsScene, *, method: str = DEFAULT_METHOD, samples_per_pixel: int = 1,
           target_error: float | None = None, **options) -> Float[Array, "H W 3"]:
    """Render `scene` with `method` ("adaptive", "equiangular", "planes" or "raymarch"; its keyword options
    pass through, e.g. samples=, planes=, quantize_bits=) and `samples_per_pixel` (k*k).

    The frame is rendered jitted (one compiled program per method, samples per pixel and options,
    reused by later calls; inside the caller's own `jax.jit` or `jax.grad` it is traced with them;
    an array among the options is rendered op by op).

    target_error: instead of given counts, the cheapest counts predicted to keep the in-scattered
    light within this relative RMS of the converged result (`choose_counts`: an estimate on a small
    proxy of the scene). Needs concrete values: call it outside `jax.jit` (or call `choose_counts`
    there and pass its options)."""
    if method not in METHODS:
        raise ValueError(f"unknown shafts method {method!r}: use one of {', '.join(METHODS)}")
    if target_error is not None:
        choice = choose_counts(scene, target_error, method=method, **options)
        options = {**options, **choice.options}
    key = tuple(sorted(options.items()))
    try:
        hash(key)
    except TypeError:                     # an array among the options: as it is, op by op
        return _frame(method, samples_per_pixel, options)(scene)
    return _jitted(method, samples_per_pixel, key)(scene)
