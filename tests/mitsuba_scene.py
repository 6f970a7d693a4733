"""Light-shaft scene dicts (the JSON contract of shared/design.md) rendered by Mitsuba 3.

A test utility, deliberately independent of the `jaxrender` renderer: it reads only the scene
*dict* (and light maps through `jaxrender.io.read_image`, the shared file reader), and builds the
Mitsuba 3 scene that design.md declares equivalent:

- integrator `volpath`, `max_depth` 2 (single scattering in the fog + direct light on surfaces);
- one homogeneous medium with `sigma_t` = rho*kappa and float `albedo` = 8*pi*K/kappa, so that
  sigma_s = rho*8*pi*K; phase `tabphase` tabulating 1 + 9((1+mu)/2)^8 on a regular mu grid over
  [-1, 1]. Mitsuba's tabphase uses the *physics* convention (mu = 1 is forward scattering, i.e.
  the light's propagation direction equals the direction toward the eye; see the plugin notes in
  mitsuba3/src/phase/tabphase.cpp: "cos theta = 1 corresponds to forward scattering"), which is the
  paper's alpha = 0 (cos^16(alpha/2) = ((1+cos alpha)/2)^8). Mitsuba normalizes the table to a pdf:
  the integral of 1 + 9((1+mu)/2)^8 over the sphere is 2*pi*4 = 8*pi, so sigma_s * p(mu) =
  rho*8*pi*K * (1 + 9(...)^8)/(8*pi) = rho*F(alpha): the paper's scattering per unit length and
  steradian;
- the sensor and every shape (as interior and exterior) and the spot emitters in that medium;
- `spot` emitters: `to_world` = look_at(position, target, up) (Mitsuba's frame x = normalize(up x z),
  y = z x x, the frame of design.md), `cutoff_angle`, `beam_width` (default 0.75*cutoff, as Mitsuba),
  RGB `intensity`, and the light map as a raw (linear) `bitmap` texture with `wrap_mode` clamp and
  bilinear filtering. Mitsuba's spot uv is 0.5 + 0.5*(x, y)/(z*tan(cutoff)) (spot.cpp,
  `direction_to_uv`), and its bitmap texture puts texel centres at (i+1/2)/W with row 0 of the array
  at v = 0: exactly design.md's uv;
- two-sided `diffuse` BSDFs; spheres as `sphere`, quads as `rectangle` with to_world columns
  (u, v, normalize(u x v), centre) (Mitsuba's rectangle spans [-1, 1]^2 in its local xy plane);
- `perspective` sensor, `fov_axis` "y", `to_world` = look_at(eye, target, up); `hdrfilm` with a box
  reconstruction filter (each Mitsuba pixel is the *average* over its area, not a point sample at
  its centre: compare against a supersampled render, or block means);
- `independent` sampler (independent samples make per-pixel variance estimates honest).

Fog with a density grid (`medium.density`): a `heterogeneous` medium whose `sigma_t` is
a `gridvolume` of the grid (trilinear, wrap_mode clamp; its data (nz, ny, nx) is Mitsuba's
(z, y, x) layout, x fastest, and its unit cube is mapped onto [box_min, box_max] by `to_world` =
translate(box_min) scale(box_max - box_min), voxel centres at (i + 1/2)/n as in our DensityGrid:
checked value by value in tests/test_shafts_fog.py) scaled by `scale` = rho*kappa, the same
albedo and tabphase; the box is a null-BSDF `cube` with the fog inside and nothing outside, so
there is no fog outside the box. The sensor, the emitters and the shapes inside the box get the
fog as their medium, those outside none; a shape that straddles the box's faces cannot be
expressed (one medium per side of a surface): ValueError.

With `moments=True` the integrator is wrapped in Mitsuba's `moment` integrator so one render
returns the per-pixel mean and the per-pixel variance of a single sample's luminance, from which
the standard error of any pixel's or block's mean luminance follows (`block_standard_error`).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

PHASE_POINTS = 1025  # tabphase nodes; linear interpolation error of 9((1+mu)/2)^8 is < 2e-5 relative


def phase_table(n: int = PHASE_POINTS) -> np.ndarray:
    """1 + 9((1+mu)/2)^8 at n regularly spaced mu in [-1, 1] (mu = 1: forward scattering)."""
    mu = np.linspace(-1.0, 1.0, n)
    return 1.0 + 9.0 * ((1.0 + mu) / 2.0) ** 8


def _vec(x) -> list[float]:
    return [float(c) for c in x]


def _load_light_map(path: Path) -> np.ndarray:
    from jaxrender.io import read_image

    img = np.asarray(read_image(path, srgb=True), dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return np.ascontiguousarray(img[..., :3])


def _quad_matrix(center, u, v) -> list[list[float]]:
    c, u, v = (np.asarray(x, dtype=float) for x in (center, u, v))
    n = np.cross(u, v)
    n = n / np.linalg.norm(n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, n, c
    return m.tolist()


def _density_grid(density: dict, base_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    values = np.load(base_dir / density["grid"], allow_pickle=False).astype(np.float32)
    return values, np.asarray(density["box_min"], float), np.asarray(density["box_max"], float)


def _inside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=-1)


def _object_points(obj: dict) -> np.ndarray:
    c = np.asarray(obj["center"], float)
    if obj["type"] == "sphere":
        r = float(obj["radius"])
        return c + r * np.concatenate([np.eye(3), -np.eye(3)])  # inside an axis-aligned box iff these are
    u, v = np.asarray(obj["u"], float), np.asarray(obj["v"], float)
    return np.stack([c + a * u + b * v for a in (-1, 1) for b in (-1, 1)])


def mitsuba_scene_dict(
    scene: dict,
    *,
    base_dir: str | os.PathLike = ".",
    spp: int = 64,
    width: int | None = None,
    height: int | None = None,
    moments: bool = False,
    phase_points: int = PHASE_POINTS,
) -> dict:
    """The Mitsuba 3 `load_dict` description of a light-shaft scene dict.

    Call after `mitsuba.set_variant(...)` (light maps become `mitsuba.Bitmap`s of that variant).
    `width`/`height` override the camera's. Raises ValueError for a medium Mitsuba cannot express
    (scattering without extinction).
    """
    import mitsuba as mi

    base_dir = Path(base_dir)
    cam = scene["camera"]
    w = int(width if width is not None else cam["width"])
    h = int(height if height is not None else cam["height"])
    med = scene.get("medium", {"rho": 0.0, "kappa": 0.0, "K": 0.0})
    rho, kappa, k_phase = float(med["rho"]), float(med["kappa"]), float(med["K"])
    sigma_t = rho * kappa
    fog = sigma_t > 0.0
    if not fog and rho * k_phase > 0.0:
        raise ValueError("medium scatters (rho*K > 0) without extinction (rho*kappa = 0): Mitsuba "
                         "needs sigma_t > 0 for a scattering medium")
    ref = {"type": "ref", "id": "fog"}
    box = _density_grid(med["density"], base_dir) if fog and med.get("density") else None

    def medium_at(points) -> bool:
        """Whether the fog surrounds these points (all inside the box, or no box at all)."""
        if box is None:
            return fog
        inside = _inside(np.atleast_2d(np.asarray(points, float)), box[1], box[2])
        if inside.all():
            return True
        if inside.any():
            raise ValueError("a shape straddles the density grid's box: Mitsuba's surfaces take one medium per side")
        return False

    d: dict = {"type": "scene"}
    phase = {"type": "tabphase", "values": ", ".join(f"{x:.9g}" for x in phase_table(phase_points))}
    if box is not None:
        values, lo, hi = box
        d["fog"] = {
            "type": "heterogeneous",
            "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(values),
                        "to_world": mi.ScalarTransform4f().translate(_vec(lo)).scale(_vec(hi - lo)),
                        "filter_type": "trilinear", "wrap_mode": "clamp"},
            "scale": sigma_t,
            "albedo": 8.0 * math.pi * k_phase / kappa,
            "phase": phase,
        }
        d["fog_box"] = {"type": "cube", "bsdf": {"type": "null"}, "interior": ref,
                        "to_world": mi.ScalarTransform4f().translate(_vec((lo + hi) / 2)).scale(_vec((hi - lo) / 2))}
    elif fog:
        d["fog"] = {
            "type": "homogeneous",
            "sigma_t": sigma_t,
            "albedo": 8.0 * math.pi * k_phase / kappa,
            "phase": phase,
        }
    nested = {"type": "volpath", "max_depth": 2, "rr_depth": 100}
    d["integrator"] = {"type": "moment", "nested": nested} if moments else nested

    sensor = {
        "type": "perspective",
        "fov_axis": "y",
        "fov": float(cam["fov_y_deg"]),
        "near_clip": 1e-3,
        "far_clip": 1e4,
        "to_world": mi.ScalarTransform4f().look_at(origin=_vec(cam["eye"]), target=_vec(cam["target"]),
                                                 up=_vec(cam["up"])),
        "film": {"type": "hdrfilm", "width": w, "height": h, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }
    if medium_at(cam["eye"]):
        sensor["medium"] = ref
    d["sensor"] = sensor

    for i, spot in enumerate(scene.get("spotlights", [])):
        cutoff = float(spot["cutoff_deg"])
        e = {
            "type": "spot",
            "to_world": mi.ScalarTransform4f().look_at(origin=_vec(spot["position"]),
                                                     target=_vec(spot["target"]),
                                                     up=_vec(spot.get("up", [0, 1, 0]))),
            "cutoff_angle": cutoff,
            "beam_width": float(spot.get("beam_width_deg", 0.75 * cutoff)),
            "intensity": {"type": "rgb", "value": _vec(spot["intensity"])},
        }
        if spot.get("light_map"):
            e["texture"] = {"type": "bitmap",
                            "bitmap": mi.Bitmap(_load_light_map(base_dir / spot["light_map"])),
                            "raw": True, "wrap_mode": "clamp", "filter_type": "bilinear"}
        if medium_at(spot["position"]):
            e["medium"] = ref
        d[f"spot_{i}"] = e

    for i, obj in enumerate(scene.get("objects", [])):
        bsdf = {"type": "twosided",
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": _vec(obj["albedo"])}}}
        if obj["type"] == "sphere":
            s = {"type": "sphere", "center": _vec(obj["center"]), "radius": float(obj["radius"])}
        elif obj["type"] == "quad":
            s = {"type": "rectangle",
                 "to_world": mi.ScalarTransform4f(_quad_matrix(obj["center"], obj["u"], obj["v"]))}
        else:
            raise ValueError(f"objects[{i}]: unknown type {obj['type']!r}")
        s["bsdf"] = bsdf
        if medium_at(_object_points(obj)):
            s["interior"] = ref
            s["exterior"] = ref
        d[f"shape_{i}"] = s
    return d


def render_mitsuba(
    scene: dict,
    *,
    base_dir: str | os.PathLike = ".",
    spp: int,
    seed: int = 0,
    variant: str = "scalar_rgb",
    width: int | None = None,
    height: int | None = None,
    moments: bool = False,
):
    """Render a light-shaft scene dict with Mitsuba 3.

    Returns the `H W 3` float64 image, or with `moments=True` the pair (mean image `H W 3`,
    per-sample variance of its luminance `H W`): the variance of one sample's Y in each pixel, so
    the standard error of the pixel's mean luminance is sqrt(var/spp). Mitsuba's `moment`
    integrator records its moments as AOVs in CIE XYZ after the RGB image (channels nested.X/Y/Z,
    then m2_nested.X/Y/Z); Y is the luminance 0.2127 R + 0.7152 G + 0.0722 B of the linear image.
    """
    import mitsuba as mi

    mi.set_variant(variant)
    mscene = mi.load_dict(mitsuba_scene_dict(scene, base_dir=base_dir, spp=spp, width=width,
                                            height=height, moments=moments))
    img = np.array(mi.render(mscene, spp=int(spp), seed=int(seed)), dtype=np.float64)
    if not moments:
        return img[..., :3]
    names = mscene.integrator().aov_names()
    y, m2_y = img[..., 3 + names.index("nested.Y")], img[..., 3 + names.index("m2_nested.Y")]
    return img[..., :3], np.maximum(m2_y - y**2, 0.0)


def block_means(img: np.ndarray, block: int) -> np.ndarray:
    """Means over non-overlapping `block x block` pixel blocks of an `H W C` image (H, W divisible)."""
    h, w, c = img.shape
    return img.reshape(h // block, block, w // block, block, c).mean(axis=(1, 3))


def block_standard_error(var: np.ndarray, spp: int, block: int) -> np.ndarray:
    """Standard error of each block mean of a Monte Carlo image rendered with `spp` independent
    samples per pixel whose per-sample variance is `var` (`H W C`, pixels independent)."""
    h, w, c = var.shape
    summed = var.reshape(h // block, block, w // block, block, c).sum(axis=(1, 3))
    return np.sqrt(summed / spp) / (block * block)
