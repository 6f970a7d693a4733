"""Loading and validating light-shaft scene files (design.md, "Scene file for light shafts", and
its extensions: `render.spp` (README) and `medium.density` (docs/fog.md)).

`medium.density` = {"grid": "density.npy", "box_min": [x, y, z], "box_max": [x, y, z]}: a float
.npy array (nz, ny, nx) of values >= 0 at voxel centres, relative to the scene file
(`jaxrender.shafts.DensityGrid`).

Every problem of a file is reported at once (`jaxrender.io.InputErrors`, read by
`jaxrender.io.Fields`), one line each: `scene.json: spotlights[0].cutoff_deg: expected a number,
got 'wide'`; unknown keys are problems too. A medium with 8*pi*K > kappa (scattering more than it extinguishes) gives a
`ShaftsSceneWarning`.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrender.camera import Camera
from jaxrender.geometry import Quads, Spheres
from jaxrender.io import FLOAT32_MAX, Fields, InputError, read_image
from jaxrender.lights import SpotLight
from jaxrender.shafts import DensityGrid, Medium, RenderSettings, ShaftsScene

__all__ = ["load_shafts_scene", "shafts_scene_from_dict", "ShaftsSceneWarning", "RENDER_DEFAULTS", "check_image_size",
           "MAX_SIDE", "MAX_SAMPLES", "MAX_VOXELS"]

MAX_SIDE = 16384  # pixels a side (and texels of a shadow map or table)
MAX_SAMPLES = 2**26  # width * height * spp: per-sample arrays of up to ~30 values keep int32 indices below 2^31
MAX_VOXELS = 2**27  # density grid values (flat int32 indices with room to spare; 1 GiB as float64)
RENDER_DEFAULTS = {"shadow_map": 1024, "shadow_bias": 0.002, "table_size": 256, "spp": 1, "s_min": 0.05,
                   "s_max": 20.0, "t_max": 20.0, "display_white": 1.0}


class ShaftsSceneWarning(UserWarning):
    """A scene that loads but is physically suspicious (e.g. `8*pi*K > kappa`)."""


def _parallel(a: np.ndarray, b: np.ndarray) -> bool:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return True
    return np.linalg.norm(np.cross(a / na, b / nb)) < 1e-6


def check_image_size(width: int, height: int, spp: int = 1, *, source=None) -> None:
    """Refuse images whose samples the renderer cannot index (`InputError`): width * height * spp
    above `MAX_SAMPLES`, or a side above `MAX_SIDE`."""
    if max(width, height) > MAX_SIDE or width * height * spp > MAX_SAMPLES:
        raise InputError(source, f"image of {width} x {height} pixels at {spp} samples per pixel is beyond what the "
                                 f"renderer indexes (at most {MAX_SIDE} pixels a side and {MAX_SAMPLES} samples)")


def _look_at_ok(f: Fields, origin, target, up, *, origin_name: str, view_name: str) -> bool:
    """A look-at frame (camera or spot light) exists: target apart from the origin, up not along the view."""
    if np.linalg.norm(target - origin) == 0:
        f.problem("target", f"equals {origin_name}")
        return False
    if _parallel(up, target - origin):
        if f.has("up"):
            f.problem("up", f"parallel to {view_name}")
        else:
            f.problem("up", f"not given, and the default up [0, 1, 0] is parallel to {view_name}: give an up "
                            "vector across it (e.g. [0, 0, 1])")
        return False
    return True


def _camera(f: Fields) -> Camera | None:
    f.known(("eye", "target", "up", "fov_y_deg", "width", "height"))
    eye, target = f.vector("eye"), f.vector("target")
    up = f.vector("up", default=[0.0, 1.0, 0.0])
    fov = f.number("fov_y_deg", lo=0.0, hi=179.0, lo_open=True)
    width, height = f.integer("width", lo=1, hi=MAX_SIDE), f.integer("height", lo=1, hi=MAX_SIDE)
    if eye is None or target is None or up is None or not _look_at_ok(
            f, eye, target, up, origin_name="camera.eye", view_name="the viewing direction"):
        return None
    return None if None in (fov, width, height) else Camera(eye, target, up, fov, width=width, height=height)


def _grid_values(f: Fields, base_dir: Path) -> np.ndarray | None:
    """The `grid` array of a density section: a readable .npy of finite values >= 0, shape (nz, ny, nx)."""
    name = f.string("grid")
    if name is None:
        return None
    path = Path(name) if Path(name).is_absolute() else base_dir / name
    if not path.is_file():
        f.problem("grid", f"cannot read density grid {name!r} (no such file)")
        return None
    try:
        with open(path, "rb") as stream:
            if stream.read(6) != b"\x93NUMPY":
                f.problem("grid", f"density grid {name!r} is not a .npy file (write it with numpy.save)")
                return None
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        f.problem("grid", f"cannot read density grid {name!r} as a .npy array ({error})")
        return None
    if not isinstance(array, np.ndarray) or not (np.issubdtype(array.dtype, np.floating)
                                                 or np.issubdtype(array.dtype, np.integer)):
        f.problem("grid", f"density grid {name!r} must hold real numbers, not {getattr(array, 'dtype', type(array))}")
        return None
    if array.ndim != 3:
        f.problem("grid", f"density grid {name!r} must be a 3-D array (nz, ny, nx), got shape {tuple(array.shape)}")
        return None
    if array.size == 0 or array.size > MAX_VOXELS:
        f.problem("grid", f"density grid {name!r} has {array.size} values, expected 1 to {MAX_VOXELS}")
        return None
    values = np.asarray(array, dtype=np.float64)
    if np.any(np.abs(values[np.isfinite(values)]) > FLOAT32_MAX):
        f.problem("grid", f"density grid {name!r} has values beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), "
                          "in which the toolkit computes")
        return None
    if not np.all(np.isfinite(values)):
        f.problem("grid", f"density grid {name!r} has {int(np.count_nonzero(~np.isfinite(values)))} NaN or infinite "
                          "values")
        return None
    if np.any(values < 0):
        f.problem("grid", f"density grid {name!r} has {int(np.count_nonzero(values < 0))} negative values "
                          f"(minimum {values.min():.4g}); densities must be >= 0")
        return None
    return values


def _density(f: Fields, base_dir: Path) -> DensityGrid | None:
    f.known(("grid", "box_min", "box_max"))
    values = _grid_values(f, base_dir)
    lo, hi = f.vector("box_min"), f.vector("box_max")
    if lo is not None and hi is not None and np.any(hi <= lo):
        f.problem("box_max", f"must exceed box_min in x, y and z (an empty box: {hi.tolist()} vs {lo.tolist()})")
        return None
    if values is None or lo is None or hi is None:
        return None
    return DensityGrid(values, lo, hi)


def _medium(f: Fields, base_dir: Path) -> Medium | None:
    f.known(("rho", "kappa", "K", "density"))
    rho, kappa, K = (f.number(key, lo=0.0) for key in ("rho", "kappa", "K"))
    has_density = f.raw("density", default=None) is not None
    density = _density(f.section("density"), base_dir) if has_density else None
    if None in (rho, kappa, K) or (has_density and density is None):
        return None
    # the coefficients the renderer forms (extinction rho kappa d, the phase function's peak 10 rho K d,
    # and 10 K d, which the kernels form before rho multiplies in) must be float32 numbers too
    peak = 1.0 if density is None else float(np.max(density.values))
    for name, value in (("rho * kappa", rho * kappa * peak), ("10 * rho * K", 10 * rho * K * peak),
                        ("10 * K", 10 * K * max(peak, 1.0))):
        if value > FLOAT32_MAX:
            f.problem(None, f"{name}{' * the largest density' if density is not None else ''} = {value:.4g} is "
                            f"beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), in which the toolkit computes")
            return None
    if 8 * math.pi * K > kappa:
        warnings.warn(f"{f.source}: medium: 8*pi*K = {8 * math.pi * K:.4g} > kappa = {kappa:.4g}: the fog scatters "
                      "more light than it extinguishes", ShaftsSceneWarning, stacklevel=3)
    return Medium(rho, kappa, K, density)


def _render(f: Fields) -> RenderSettings | None:
    f.known(tuple(RENDER_DEFAULTS))
    values = {key: f.integer(key, default=RENDER_DEFAULTS[key], lo=2, hi=MAX_SIDE)
              for key in ("shadow_map", "table_size")}
    # samples per pixel: a k x k sub-pixel grid (an extension of design.md's format)
    values["spp"] = f.integer("spp", default=RENDER_DEFAULTS["spp"], lo=1, hi=1024)
    if values["spp"] is not None and math.isqrt(values["spp"]) ** 2 != values["spp"]:
        f.problem("spp", f"must be a perfect square (1, 4, 9, 16, ...), got {values['spp']}")
        values["spp"] = None
    for key in ("shadow_bias", "s_min", "s_max", "t_max", "display_white"):
        values[key] = f.number(key, default=RENDER_DEFAULTS[key], lo=0.0, lo_open=key != "shadow_bias")
    if None in values.values():
        return None
    if values["s_max"] <= values["s_min"]:
        f.problem("s_max", f"must exceed render.s_min ({values['s_min']:g})")
        return None
    return RenderSettings(shadow_map=values["shadow_map"], table_size=values["table_size"], spp=values["spp"],
                          **{k: jnp.asarray(values[k], dtype=float)
                             for k in ("shadow_bias", "s_min", "s_max", "t_max", "display_white")})


def _light_map(f: Fields, base_dir: Path) -> np.ndarray | None:
    name = f.string("light_map")
    if name is None:
        return None
    path = Path(name) if Path(name).is_absolute() else base_dir / name
    try:
        image = read_image(path)
    except InputError as error:
        f.problem("light_map", f"cannot read light map {name!r} ({error.problem})")
        return None
    if not np.all(np.isfinite(image)):
        f.problem("light_map", f"light map {name!r} has NaN or infinite values")
        return None
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image[..., :3], dtype=np.float64)


def _spotlight(f: Fields, base_dir: Path) -> SpotLight | None:
    f.known(("position", "target", "up", "cutoff_deg", "beam_width_deg", "intensity", "light_map"))
    position, target = f.vector("position"), f.vector("target")
    up = f.vector("up", default=[0.0, 1.0, 0.0])
    cutoff = f.number("cutoff_deg", lo=0.0, hi=89.0, lo_open=True)
    beam = f.number("beam_width_deg", default=None, lo=0.0, hi=cutoff)
    intensity = f.rgb("intensity")
    light_map = _light_map(f, base_dir) if f.raw("light_map", default=None) is not None else None
    if position is None or target is None or up is None or not _look_at_ok(
            f, position, target, up, origin_name="the light's position", view_name="the light's direction"):
        return None
    if cutoff is None or intensity is None:
        return None
    beam = 0.75 * cutoff if beam is None else beam  # Mitsuba's default
    return SpotLight(position, target, up, cutoff, beam, intensity, light_map)


_OBJECT_FIELDS = {"sphere": ("type", "center", "radius", "albedo"), "quad": ("type", "center", "u", "v", "albedo")}


def _objects(items: list[Fields]) -> tuple[Spheres, Quads]:
    spheres: dict[str, list] = {"center": [], "radius": [], "albedo": []}
    quads: dict[str, list] = {"center": [], "u": [], "v": [], "albedo": []}
    for f in items:
        kind = f.raw("type")
        if not isinstance(kind, str) or kind not in _OBJECT_FIELDS:
            if kind is not None:
                f.problem("type", f"unknown object type {kind!r} (expected 'sphere' or 'quad')")
            continue
        f.known(_OBJECT_FIELDS[kind])
        values = {"center": f.vector("center"), "albedo": f.rgb("albedo", default=0.5)}
        if kind == "sphere":
            values["radius"] = f.number("radius", lo=0.0, lo_open=True)
        else:
            values["u"], values["v"] = f.vector("u"), f.vector("v")
            if values["u"] is not None and values["v"] is not None and _parallel(values["u"], values["v"]):
                f.problem("v", "parallel to u (degenerate quad)")
                values["v"] = None
        if not any(v is None for v in values.values()):
            for key, value in values.items():
                (spheres if kind == "sphere" else quads)[key].append(value)

    def rows(values, n_cols):
        return np.asarray(values, dtype=float).reshape((-1, n_cols) if n_cols else (-1,))

    return (Spheres(rows(spheres["center"], 3), rows(spheres["radius"], 0), rows(spheres["albedo"], 3)),
            Quads(rows(quads["center"], 3), rows(quads["u"], 3), rows(quads["v"], 3), rows(quads["albedo"], 3)))


def shafts_scene_from_dict(d: Any, *, base_dir: str | os.PathLike = ".",
                           source: str | os.PathLike = "<scene>") -> ShaftsScene:
    """Validate a parsed scene (design.md contract) and build a `ShaftsScene`.

    `base_dir`: where relative light-map and density-grid paths are resolved; `source`: the file named in errors.
    Every problem is reported at once (`jaxrender.io.InputErrors`, one `FILE: field: problem` line each).
    """
    doc = Fields.document(d, os.fspath(source))
    doc.known(("camera", "medium", "render", "spotlights", "objects"))
    camera = _camera(doc.section("camera"))
    medium = _medium(doc.section("medium"), Path(base_dir))
    render = _render(doc.section("render", required=False, defaults=True))
    light_items = doc.items("spotlights")
    lights = [_spotlight(f, Path(base_dir)) for f in light_items]
    if doc.has("spotlights") and isinstance(doc.raw("spotlights"), list) and not doc.raw("spotlights"):
        doc.problem("spotlights", "at least one spot light is needed")
    spheres, quads = _objects(doc.items("objects", required=False))  # none: shafts in empty fog
    doc.problems.check()
    check_image_size(camera.width, camera.height, render.spp, source=source)
    return ShaftsScene(camera, medium, lights, spheres, quads, render, source=os.fspath(source))


def load_shafts_scene(path: str | os.PathLike) -> ShaftsScene:
    """Read and validate a light-shaft scene file (JSON, design.md); light maps and density grids
    are relative to it."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder, not a scene file")
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise InputError(path, f"not valid JSON (line {error.lineno}, column {error.colno}: {error.msg})") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(path, f"cannot read ({error})") from None
    return shafts_scene_from_dict(data, base_dir=path.parent, source=path)
