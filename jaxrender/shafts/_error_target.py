"""Sample counts chosen from an error target (paper 000's open question of choosing the
numbers of planes and sub-planes): `choose_counts(scene, E)` picks the cheapest counts whose
in-scattered light is predicted to lie within relative RMS E of the converged result.

The estimate renders a proxy of the scene, the same camera and lights at ~`proxy_rays` rays
(1/170 of a 720 x 480 frame), at a few counts and at a high reference count, in one jitted call
(the proxy's maps and volumes computed once, the ladder's counts sharing one compiled kernel),
and measures each count's relative RMS against the reference. A method's error comes from the
quadrature along the rays (it falls as the counts grow) while its fixed parts (shadow-map and
light-map texels, a grid's volumes) change little with them, so:
- adaptive, equiangular and raymarch (`samples`): the error at 8, 16, 24, 32, 48 samples against
  96 (the adaptive method's: its equiangular rays, with its light-map taps, at every pixel of
  the proxy; its interpolation's error is held by its own `tolerance`); the
  smallest whose error is within 0.9 E (the fixed parts' error is not in the proxy's). The error
  of a count is measured, not modelled: where a light map's pattern beats with the sample spacing
  it is not even monotone in the count. Beyond 48, a power law e = c n^-p through the
  measurements (p from log-log least squares within [0.5, 2], c their envelope) extends them.
  Counts are multiples of 8 (`SAMPLE_STEP`): XLA vectorizes the samples axis, and a count between
  two multiples costs more than the next one (720 x 480 on 2 AVX-512 cores: 12 samples 0.25 s,
  16 samples 0.20 s on the fog-bank grid scene; 0.061 against 0.050 s on the spot scene);
- planes (`planes`, `subplanes`): e^2 = a / n^4 + b / (n m)^2 fitted (non-negative least
  squares) to the errors at (6, 2), (12, 2), (6, 8), (12, 8), (24, 4) against (64, 8) (the pairs
  share one compiled kernel): the smooth g sampled on n planes, shadows and light maps on n m
  sub-planes; the pair of least cost n (2 + m) predicted to reach E.
The proxy measures the error of the method against its own high count; the fixed parts' error
(a few tenths of a percent) is not in it. How good the prediction is: benchmarks/RESULTS.md,
"Sample counts from an error target" (predicted against achieved over uniform, stage and grid
scenes).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from ._adaptive import MAP_TAPS as ADAPTIVE_MAP_TAPS
from ._equiangular import equiangular_ladder
from ._planes import render_planes
from ._raymarch import render_raymarch
from ._scene import ShaftsScene, shadow_maps

__all__ = ["CountChoice", "choose_counts", "proxy_scene", "PROXY_RAYS"]

PROXY_RAYS = 2048
SAMPLE_STEP = 8  # counts of samples are multiples of this (module docstring: no cheaper in between)
_GROUPS = ((8, 16, 24), (32, 48))  # the counts measured on the proxy; each group one kernel
_REFERENCE = 96
_MARGIN = 0.9  # aim below E: the proxy cannot see the fixed parts' error (shadow-map texels, volumes)
_PLANE_LADDER = ((6, 2), (12, 2), (6, 8), (12, 8), (24, 4))
_PLANE_REFERENCE = (64, 8)
_MAX_SAMPLES, _MAX_PLANES, _MAX_SUBPLANES = 256, 128, 16
_PLANE_COST = 2.0  # a plane's g costs about two sub-plane samples (mesh or per-pixel geometry, tables)


@dataclasses.dataclass(frozen=True)
class CountChoice:
    """What `choose_counts` chose: `options` (samples=, or planes= and subplanes=) for the method,
    the error predicted for them, and what the proxy measured ((options, error) pairs)."""

    method: str
    options: dict
    predicted_error: float
    target_error: float
    proxy_size: tuple[int, int]
    measured: tuple
    seconds: float

    @property
    def reached(self) -> bool:
        return self.predicted_error <= self.target_error

    def describe(self) -> str:
        counts = ", ".join(f"{k} {v}" for k, v in self.options.items())
        return (f"error target {100 * self.target_error:g} %: {self.method} with {counts} (predicted "
                f"{100 * self.predicted_error:.2f} % on a {self.proxy_size[0]} x {self.proxy_size[1]} proxy; "
                f"estimate {self.seconds:.2f} s, its compilation included on first use)")


def proxy_scene(scene: ShaftsScene, rays: int = PROXY_RAYS) -> ShaftsScene:
    """The scene seen by the same camera at about `rays` pixels (aspect kept; a small image gets
    a larger proxy: the error is a statistic over rays, and a few dozen estimate it badly)."""
    cam = scene.camera
    scale = math.sqrt(rays / (cam.width * cam.height))
    return scene.with_size(max(8, round(cam.width * scale)), max(6, round(cam.height * scale)))


def _in_scattering(out):
    _, (_, fog) = out
    return sum(fog) if isinstance(fog, list) else fog


@functools.lru_cache(maxsize=32)
def _ladder_fn(method: str, counts: tuple, options: tuple):
    opts = dict(options)
    if method in ("adaptive", "equiangular"):  # the adaptive method's rays are equiangular rays
        if method == "adaptive":
            opts.setdefault("map_taps", ADAPTIVE_MAP_TAPS)

        def ladder(s):
            images, ref = equiangular_ladder(s, _GROUPS, counts[-1], **opts)
            return [*images, ref]

        return jax.jit(ladder)
    if method == "raymarch":
        return jax.jit(lambda s: [_in_scattering(render_raymarch(s, samples=n, return_parts=True, **opts))
                                  for n in counts])
    cap_n, cap_m = (max(c[i] for c in counts[:-1]) for i in (0, 1))

    def ladder(s):
        maps = shadow_maps(s, s.render.shadow_map)  # shared by every pair

        def at(nm):
            return _in_scattering(render_planes(s, planes=cap_n, subplanes=cap_m, maps=maps, counts=(nm[0], nm[1]),
                                                return_parts=True, **opts))

        pairs = jnp.asarray(counts[:-1], dtype=s.camera.eye.dtype)
        ref = _in_scattering(render_planes(s, planes=counts[-1][0], subplanes=counts[-1][1], maps=maps,
                                           return_parts=True, **opts))
        return [*jax.lax.map(at, pairs), ref]

    return jax.jit(ladder)


def _errors(images, reference) -> list[float]:
    ref = np.asarray(reference, np.float64)
    norm = np.linalg.norm(ref)
    if norm == 0:
        return [0.0 for _ in images]
    return [float(np.linalg.norm(np.asarray(x, np.float64) - ref) / norm) for x in images]


def _power_law(counts, errors) -> tuple[float, float]:
    """(c, p) of e = c n^-p: p from a least-squares fit in log-log (clamped to [0.5, 2]: between
    shadow edges, 1/n, and smooth integrands, 1/n^2), c raised so that the curve lies on or above
    every measurement (a proxy's few thousand rays make the errors a little noisy)."""
    x = np.log(np.asarray(counts, float))
    y = np.log(np.maximum(np.asarray(errors, float), 1e-12))
    p = float(np.clip(-np.polyfit(x, y, 1)[0], 0.5, 2.0))
    return float(np.max(np.exp(y + p * x))), p


def _choose_samples(counts, errors, target):
    if max(errors) == 0.0:
        return counts[0], 0.0
    for n, e in zip(counts, errors):
        if e <= _MARGIN * target:
            return n, e
    c, p = _power_law(counts, errors)
    n = max(math.ceil((c / (_MARGIN * target)) ** (1.0 / p)), counts[-1] + 1)
    n = min(SAMPLE_STEP * math.ceil(n / SAMPLE_STEP), _MAX_SAMPLES)
    return n, c * n ** -p


def _choose_planes(pairs, errors, target):
    if max(errors) == 0.0:
        return (4, 1), 0.0
    A = np.array([[n ** -4.0, (n * m) ** -2.0] for n, m in pairs])
    b = np.asarray(errors, float) ** 2
    coef = _nnls2(A, b)
    best = None
    for n in range(2, _MAX_PLANES + 1):
        for m in range(1, _MAX_SUBPLANES + 1):
            predicted = math.sqrt(coef[0] * n ** -4.0 + coef[1] * (n * m) ** -2.0)
            cost = n * (_PLANE_COST + m)
            if predicted <= target and (best is None or cost < best[0]):
                best = (cost, (n, m), predicted)
    if best is None:
        n, m = _MAX_PLANES, _MAX_SUBPLANES
        return (n, m), math.sqrt(coef[0] * n ** -4.0 + coef[1] * (n * m) ** -2.0)
    return best[1], best[2]


def _nnls2(A, b):
    """Non-negative least squares with two unknowns: the unconstrained solution, or the best of
    the two one-variable fits."""
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    if np.all(sol >= 0):
        return sol
    best, best_res = np.zeros(2), np.inf
    for j in range(2):
        col = A[:, j]
        c = max(float(col @ b) / float(col @ col), 0.0)
        res = float(np.sum((col * c - b) ** 2))
        if res < best_res:
            best, best_res = np.eye(2)[j] * c, res
    return best


def choose_counts(scene: ShaftsScene, target_error: float, *, method: str = "adaptive",
                  proxy_rays: int = PROXY_RAYS, **options) -> CountChoice:
    """The cheapest counts of `method` predicted to render `scene`'s in-scattered light within
    relative RMS `target_error` of the converged result (module docstring). `options`: the
    method's other keyword options (shadow_map=, fog_nodes=, mesh=, ...), used for the proxy too.
    Runs jitted code on concrete values: call it outside `jax.jit`."""
    if not 0 < target_error < 1:
        raise ValueError(f"target_error must be a relative error in (0, 1), got {target_error}")
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(scene)):
        raise ValueError("target_error needs concrete scene values: choose the counts with choose_counts() "
                         "outside jax.jit, then render with them")
    if method not in ("adaptive", "equiangular", "planes", "raymarch"):
        raise ValueError(f"unknown shafts method {method!r}")
    proxy = proxy_scene(scene, proxy_rays)
    start = time.perf_counter()
    if method == "planes":
        counts = _PLANE_LADDER + (_PLANE_REFERENCE,)
    else:
        counts = tuple(n for group in _GROUPS for n in group) + (_REFERENCE,)
    fixed = tuple(sorted((k, v) for k, v in options.items() if k not in ("samples", "planes", "subplanes")))
    images = jax.block_until_ready(_ladder_fn(method, counts, fixed)(proxy))
    errors = _errors(images[:-1], images[-1])
    if method == "planes":
        (n, m), predicted = _choose_planes(counts[:-1], errors, target_error)
        chosen = {"planes": n, "subplanes": m}
    else:
        n, predicted = _choose_samples(counts[:-1], errors, target_error)
        chosen = {"samples": n}
    return CountChoice(method, chosen, predicted, float(target_error),
                       (proxy.camera.width, proxy.camera.height), tuple(zip(counts[:-1], errors)),
                       time.perf_counter() - start)

