"""Loading and validating light-shaft scene files (design.md, "Scene file for light shafts").

Every problem raises `jaxrender.io.InputError(file, "FIELD: problem")`, e.g.
`scene.json: spotlights[0].cutoff_deg: expected a number`. A medium with 8*pi*K > kappa
(scattering more than it extinguishes) gives a `ShaftsSceneWarning`.
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
from jaxrender.io import InputError, read_image
from jaxrender.lights import SpotLight
from jaxrender.shafts import Medium, RenderSettings, ShaftsScene

__all__ = ["load_shafts_scene", "shafts_scene_from_dict", "ShaftsSceneWarning", "RENDER_DEFAULTS"]

RENDER_DEFAULTS = {"shadow_map": 1024, "shadow_bias": 0.002, "table_size": 256, "spp": 1, "s_min": 0.05,
                   "s_max": 20.0, "t_max": 20.0, "display_white": 1.0}


class ShaftsSceneWarning(UserWarning):
    """A scene that loads but is physically suspicious (e.g. `8*pi*K > kappa`)."""


class _Reader:
    def __init__(self, source):
        self.source = source

    def fail(self, field: str, problem: str):
        raise InputError(self.source, f"{field}: {problem}")

    def obj(self, d: Any, field: str) -> dict:
        if not isinstance(d, dict):
            self.fail(field, "expected an object")
        return d

    def get(self, d: dict, key: str, field: str, default=None, required=True):
        if key not in d:
            if required:
                self.fail(f"{field}.{key}" if field else key, "missing field")
            return default
        return d[key]

    def number(self, value: Any, field: str, *, lo=None, hi=None, lo_open=False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(field, "expected a number")
        value = float(value)
        if lo is not None and (value < lo or (lo_open and value == lo)):
            self.fail(field, f"must be {'>' if lo_open else '>='} {lo:g}, got {value:g}")
        if hi is not None and value > hi:
            self.fail(field, f"must be <= {hi:g}, got {value:g}")
        return value

    def integer(self, value: Any, field: str, *, lo=1) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(field, "expected an integer")
        if value < lo:
            self.fail(field, f"must be >= {lo}, got {value}")
        return int(value)

    def vec3(self, value: Any, field: str) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) != 3:
            self.fail(field, "expected a list of 3 numbers")
        return np.array([self.number(v, f"{field}[{i}]") for i, v in enumerate(value)])

    def rgb(self, value: Any, field: str) -> np.ndarray:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return np.full(3, self.number(value, field, lo=0.0))
        out = self.vec3(value, field)
        if np.any(out < 0):
            self.fail(field, "must be non-negative")
        return out


def _parallel(a: np.ndarray, b: np.ndarray) -> bool:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return True
    return np.linalg.norm(np.cross(a / na, b / nb)) < 1e-6


def _light_map(reader: _Reader, value: Any, field: str, base_dir: Path) -> np.ndarray:
    if not isinstance(value, str) or not value:
        reader.fail(field, "expected a file name")
    path = Path(value)
    if not path.is_absolute():
        path = base_dir / path
    try:
        image = read_image(path)
    except InputError as error:
        reader.fail(field, f"cannot read light map {value!r} ({error.problem})")
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image[..., :3], dtype=np.float64)


def shafts_scene_from_dict(d: Any, *, base_dir: str | os.PathLike = ".",
                           source: str | os.PathLike = "<scene>") -> ShaftsScene:
    """Validate a parsed scene (design.md contract) and build a `ShaftsScene`.

    `base_dir`: where relative light-map paths are resolved; `source`: the file named in errors.
    """
    r = _Reader(os.fspath(source))
    base_dir = Path(base_dir)
    d = r.obj(d, "scene")
    for key in ("camera", "medium", "spotlights", "objects"):
        r.get(d, key, "")

    cam_d = r.obj(d["camera"], "camera")
    eye = r.vec3(r.get(cam_d, "eye", "camera"), "camera.eye")
    target = r.vec3(r.get(cam_d, "target", "camera"), "camera.target")
    up = r.vec3(r.get(cam_d, "up", "camera", default=[0.0, 1.0, 0.0], required=False), "camera.up")
    fov = r.number(r.get(cam_d, "fov_y_deg", "camera"), "camera.fov_y_deg", lo=0.0, hi=179.0, lo_open=True)
    width = r.integer(r.get(cam_d, "width", "camera"), "camera.width")
    height = r.integer(r.get(cam_d, "height", "camera"), "camera.height")
    if np.linalg.norm(target - eye) == 0:
        r.fail("camera.target", "equals camera.eye")
    if _parallel(up, target - eye):
        r.fail("camera.up", "parallel to the viewing direction")
    camera = Camera(eye, target, up, fov, width=width, height=height)

    med_d = r.obj(d["medium"], "medium")
    rho = r.number(r.get(med_d, "rho", "medium"), "medium.rho", lo=0.0)
    kappa = r.number(r.get(med_d, "kappa", "medium"), "medium.kappa", lo=0.0)
    K = r.number(r.get(med_d, "K", "medium"), "medium.K", lo=0.0)
    if 8 * math.pi * K > kappa:
        warnings.warn(f"{r.source}: medium: 8*pi*K = {8 * math.pi * K:.4g} > kappa = {kappa:.4g}: the fog scatters "
                      "more light than it extinguishes", ShaftsSceneWarning, stacklevel=2)
    medium = Medium(rho, kappa, K)

    ren_d = r.obj(d.get("render", {}), "render")
    settings = dict(RENDER_DEFAULTS)
    for key in ("shadow_map", "table_size"):
        if key in ren_d:
            settings[key] = r.integer(ren_d[key], f"render.{key}", lo=2)
    if "spp" in ren_d:  # samples per pixel: a k x k sub-pixel grid (an extension of design.md's format)
        settings["spp"] = r.integer(ren_d["spp"], "render.spp", lo=1)
        if math.isqrt(settings["spp"]) ** 2 != settings["spp"]:
            r.fail("render.spp", f"must be a perfect square (1, 4, 9, 16, ...), got {settings['spp']}")
    for key in ("shadow_bias", "s_min", "s_max", "t_max", "display_white"):
        if key in ren_d:
            settings[key] = r.number(ren_d[key], f"render.{key}", lo=0.0, lo_open=key != "shadow_bias")
    if settings["s_max"] <= settings["s_min"]:
        r.fail("render.s_max", f"must exceed render.s_min ({settings['s_min']:g})")
    render = RenderSettings(shadow_map=settings["shadow_map"], table_size=settings["table_size"], spp=settings["spp"],
                            **{k: jnp.asarray(settings[k], dtype=float)
                               for k in ("shadow_bias", "s_min", "s_max", "t_max", "display_white")})

    lights_d = r.get(d, "spotlights", "")
    if not isinstance(lights_d, list):
        r.fail("spotlights", "expected a list")
    lights = []
    for i, ld in enumerate(lights_d):
        f = f"spotlights[{i}]"
        ld = r.obj(ld, f)
        pos = r.vec3(r.get(ld, "position", f), f"{f}.position")
        tgt = r.vec3(r.get(ld, "target", f), f"{f}.target")
        lup = r.vec3(r.get(ld, "up", f, default=[0.0, 1.0, 0.0], required=False), f"{f}.up")
        cutoff = r.number(r.get(ld, "cutoff_deg", f), f"{f}.cutoff_deg", lo=0.0, hi=89.0, lo_open=True)
        beam = ld.get("beam_width_deg")
        beam = 0.75 * cutoff if beam is None else r.number(beam, f"{f}.beam_width_deg", lo=0.0, hi=cutoff)
        intensity = r.rgb(r.get(ld, "intensity", f), f"{f}.intensity")
        if np.linalg.norm(tgt - pos) == 0:
            r.fail(f"{f}.target", "equals the light's position")
        if _parallel(lup, tgt - pos):
            r.fail(f"{f}.up", "parallel to the light's direction")
        lmap = None
        if ld.get("light_map") is not None:
            lmap = _light_map(r, ld["light_map"], f"{f}.light_map", base_dir)
        lights.append(SpotLight(pos, tgt, lup, cutoff, beam, intensity, lmap))
    if not lights:
        r.fail("spotlights", "at least one spot light is needed")

    objs = r.get(d, "objects", "")
    if not isinstance(objs, list):
        r.fail("objects", "expected a list")
    spheres: dict[str, list] = {"center": [], "radius": [], "albedo": []}
    quads: dict[str, list] = {"center": [], "u": [], "v": [], "albedo": []}
    for i, od in enumerate(objs):
        f = f"objects[{i}]"
        od = r.obj(od, f)
        kind = r.get(od, "type", f)
        albedo = r.rgb(od.get("albedo", 0.5), f"{f}.albedo")
        if kind == "sphere":
            spheres["center"].append(r.vec3(r.get(od, "center", f), f"{f}.center"))
            spheres["radius"].append(r.number(r.get(od, "radius", f), f"{f}.radius", lo=0.0, lo_open=True))
            spheres["albedo"].append(albedo)
        elif kind == "quad":
            quads["center"].append(r.vec3(r.get(od, "center", f), f"{f}.center"))
            u = r.vec3(r.get(od, "u", f), f"{f}.u")
            v = r.vec3(r.get(od, "v", f), f"{f}.v")
            if _parallel(u, v):
                r.fail(f"{f}.v", "parallel to u (degenerate quad)")
            quads["u"].append(u)
            quads["v"].append(v)
            quads["albedo"].append(albedo)
        else:
            r.fail(f"{f}.type", f"unknown object type {kind!r} (expected 'sphere' or 'quad')")

    def rows(values, n_cols):
        return np.asarray(values, dtype=float).reshape((-1, n_cols) if n_cols else (-1,))

    sph = Spheres(rows(spheres["center"], 3), rows(spheres["radius"], 0), rows(spheres["albedo"], 3))
    qd = Quads(rows(quads["center"], 3), rows(quads["u"], 3), rows(quads["v"], 3), rows(quads["albedo"], 3))
    return ShaftsScene(camera, medium, lights, sph, qd, render, source=os.fspath(source))


def load_shafts_scene(path: str | os.PathLike) -> ShaftsScene:
    """Read and validate a light-shaft scene file (JSON, design.md); light maps are relative to it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise InputError(path, f"not valid JSON (line {error.lineno}, column {error.colno}: {error.msg})") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(path, f"cannot read ({error})") from None
    return shafts_scene_from_dict(data, base_dir=path.parent, source=path)
