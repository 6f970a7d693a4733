"""Shared pieces of the light-shaft benchmarks (paper 000, section 5): scenes, timing, display levels.

Scenes are dicts in the scene-file contract of design.md, so that the same dict can be rendered by
our renderer (`jaxrender.app.scenes.shafts_scene_from_dict`) and by Mitsuba 3 (`tests/mitsuba_scene.py`).
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FIGURES = HERE / "figures"
REPO = HERE.parent

PAPER_W, PAPER_H = 720, 480


def machine() -> str:
    import jax
    from _results import cpu_description

    return (f"{os.cpu_count()} CPU cores of {cpu_description()}, JAX {jax.__version__} on {jax.default_backend()}, "
            f"load average {os.getloadavg()[0]:.1f} at start")


def polka_dots(n: int = 64, *, dots: int = 4, radius: float = 0.32, floor: float = 0.08) -> np.ndarray:
    """An n x n RGB light map of `dots` x `dots` round bright dots on a dim background."""
    c = (np.arange(n) + 0.5) / n * dots
    fy, fx = np.meshgrid(c - np.floor(c) - 0.5, c - np.floor(c) - 0.5, indexing="ij")
    r = np.sqrt(fx**2 + fy**2)
    soft = 1.5 * dots / n  # one-and-a-half texels of anti-aliased edge
    inside = np.clip((radius - r) / soft + 0.5, 0.0, 1.0)
    img = floor + (1.0 - floor) * inside
    return np.repeat(img[..., None], 3, axis=-1).astype(np.float32)


def write_light_map(directory: Path, name: str, img: np.ndarray) -> str:
    from jaxrender.io import write_exr

    write_exr(directory / name, img)
    return name


def _camera(width: int, height: int) -> dict:
    return {"eye": [0.0, 1.6, 7.0], "target": [0.0, 1.2, 0.0], "up": [0.0, 1.0, 0.0], "fov_y_deg": 36.0,
            "width": width, "height": height}


# Fog: sigma_t = 0.1 /m, albedo 8*pi*K/kappa = 0.88 (<= 1, so Mitsuba's medium is physical too).
MEDIUM = {"rho": 1.0, "kappa": 0.1, "K": 0.0035}
# 8-bit tables are scaled by their maxima (design.md), so h = rho exp(-sigma (s+t)) / s^2 must be
# tabulated over the distances the scene really has: with the default s_min = 0.05 m, h(0.05) is
# 10^4 times h(5 m) and every sample farther than ~1.1 m from the light would round to 0.
# The benchmark scenes keep the lights above the frame, >= 1 m from any visible fog.
RENDER = {"shadow_map": 1024, "shadow_bias": 0.002, "table_size": 256, "s_min": 1.0, "s_max": 10.0,
          "t_max": 12.0, "display_white": 1.0}


def spot_scene(width: int = PAPER_W, height: int = PAPER_H) -> dict:
    """Fig. 4: one spot light shining down through fog onto a dark floor."""
    return {
        "camera": _camera(width, height),
        "medium": dict(MEDIUM),
        "render": dict(RENDER),
        "spotlights": [{"position": [0.0, 4.8, -0.5], "target": [0.3, 0.0, 0.3], "up": [0.0, 0.0, 1.0],
                        "cutoff_deg": 24.0, "beam_width_deg": 16.0, "intensity": [900.0, 900.0, 900.0]}],
        "objects": [{"type": "quad", "center": [0.0, 0.0, 0.0], "u": [4.0, 0.0, 0.0], "v": [0.0, 0.0, -4.0],
                     "albedo": [0.12, 0.12, 0.12]}],
    }


def sphere_scene(width: int = PAPER_W, height: int = PAPER_H) -> dict:
    """Fig. 5 / 6(b) / section 5.1: a sphere under one spot light, its shadow shaft in the fog, a floor.
    The sphere blocks about half of the cone, so the shadow shaft is large (as in the paper's fig. 6)."""
    d = spot_scene(width, height)
    d["spotlights"][0].update({"position": [0.0, 4.8, -0.5], "target": [0.0, 0.0, 0.2]})
    d["objects"].insert(0, {"type": "sphere", "center": [0.0, 2.3, -0.25], "radius": 0.65,
                            "albedo": [0.6, 0.6, 0.6]})
    return d


def stage_scene(lights: int = 5, width: int = PAPER_W, height: int = PAPER_H, *, base_dir: Path) -> dict:
    """Fig. 7: a stage (floor, back wall, a few spheres) under up to five coloured spot lights, two of
    them projecting polka-dot light maps (written into `base_dir`)."""
    dots = write_light_map(base_dir, "dots.exr", polka_dots(64, dots=4))
    dots_fine = write_light_map(base_dir, "dots_fine.exr", polka_dots(64, dots=7, radius=0.3))
    spots = [
        {"position": [-3.0, 5.0, 1.0], "target": [-1.2, 0.0, -0.5], "intensity": [900, 300, 250]},
        {"position": [3.0, 5.0, 1.0], "target": [1.2, 0.0, -0.5], "intensity": [250, 350, 900]},
        {"position": [0.0, 5.5, 0.5], "target": [0.0, 0.0, -0.8], "intensity": [800, 800, 700],
         "light_map": dots},
        {"position": [-1.5, 5.2, 2.0], "target": [-0.3, 0.0, 0.8], "intensity": [300, 800, 300],
         "light_map": dots_fine},
        {"position": [1.5, 5.2, 2.0], "target": [0.6, 0.0, 0.9], "intensity": [800, 700, 200]},
    ][:lights]
    for s in spots:
        s.update({"up": [0.0, 0.0, 1.0], "cutoff_deg": 18.0, "beam_width_deg": 13.0})
        s["intensity"] = [float(x) for x in s["intensity"]]
    return {
        "camera": {"eye": [0.0, 2.0, 8.0], "target": [0.0, 1.5, 0.0], "up": [0.0, 1.0, 0.0], "fov_y_deg": 42.0,
                   "width": width, "height": height},
        "medium": dict(MEDIUM),
        "render": dict(RENDER),
        "spotlights": spots,
        "objects": [
            {"type": "quad", "center": [0.0, 0.0, 0.0], "u": [6.0, 0.0, 0.0], "v": [0.0, 0.0, -4.0],
             "albedo": [0.15, 0.12, 0.1]},
            {"type": "quad", "center": [0.0, 3.0, -4.0], "u": [6.0, 0.0, 0.0], "v": [0.0, 3.0, 0.0],
             "albedo": [0.1, 0.1, 0.12]},
            {"type": "sphere", "center": [-1.3, 0.6, -0.6], "radius": 0.6, "albedo": [0.7, 0.6, 0.5]},
            {"type": "sphere", "center": [1.2, 0.45, -0.4], "radius": 0.45, "albedo": [0.5, 0.6, 0.7]},
            {"type": "sphere", "center": [0.0, 2.6, -0.9], "radius": 0.3, "albedo": [0.8, 0.8, 0.8]},
        ],
    }


def load(scene: dict, base_dir: Path | None = None):
    from jaxrender.app.scenes import shafts_scene_from_dict

    return shafts_scene_from_dict(scene, base_dir=base_dir if base_dir is not None else Path(tempfile.gettempdir()))


def timed(fn, *args, repeats: int = 3):
    """(result as numpy, compile+first-run seconds, median wall seconds of `repeats` further runs).

    Also records `timed.cpu`: the median CPU seconds (this process, all threads) of those runs,
    which other processes competing for the cores disturb much less than wall time."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    timed.cpu = statistics.median(cpu) if cpu else float("nan")
    return np.asarray(out), first, statistics.median(times) if times else float("nan")


timed.cpu = float("nan")


def alternate(calls, repeats: int) -> list[tuple[float, float]]:
    """(median wall s, median CPU s) of each (fn, args) in `calls` (compiled beforehand), run in
    turn `repeats` rounds: the machine's speed drifts over minutes, and a ratio of two timings is
    only fair when both were taken at the same moments."""
    import jax

    wall, cpu = [[] for _ in calls], [[] for _ in calls]
    for _ in range(repeats):
        for k, (fn, args) in enumerate(calls):
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    return [(statistics.median(w), statistics.median(c)) for w, c in zip(wall, cpu)]


def levels(img: np.ndarray, white: float = 1.0) -> np.ndarray:
    """Display levels 0..255 of a linear image (what an 8-bit frame buffer shows, unrounded)."""
    return np.clip(np.asarray(img, dtype=np.float64) / white, 0.0, 1.0) * 255.0


def table(header: list[str], rows: list[list]) -> str:
    """A Markdown table (numbers formatted by the caller)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def mitsuba_path() -> None:
    """Make `tests/mitsuba_scene.py` importable (the Mitsuba converter shared with the tests)."""
    tests = str(REPO / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)


def save_figure(fig, name: str, *, quick: bool = False) -> Path:
    """Save under benchmarks/figures/; `--quick` runs write NAME_quick.png (the committed full-size
    figures stay untouched)."""
    FIGURES.mkdir(parents=True, exist_ok=True)
    if quick:
        name = name.replace(".png", "_quick.png")
    path = FIGURES / name
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


def fog_density(shape: tuple[int, int, int] = (16, 24, 32), *, seed: int = 0, drift: float = 0.0) -> np.ndarray:
    """A smooth non-uniform fog (nz, ny, nx) on the unit cube: a ground layer thinning with height
    (e-folding at a quarter of the box), a few soft blobs and a gentle wave, values 0.05-3; `drift`
    moves the pattern along x (in box widths) for animation."""
    nz, ny, nx = shape
    z, y, x = np.meshgrid(*((np.arange(n) + 0.5) / n for n in shape), indexing="ij")
    rng = np.random.default_rng(seed)
    d = 0.25 + 1.6 * np.exp(-y / 0.25) * (1.0 + 0.45 * np.sin(2 * np.pi * (1.5 * (x - drift) + z) + 0.7))
    for _ in range(5):
        c = rng.uniform(0.15, 0.85, 3)
        r = rng.uniform(0.08, 0.18)
        cx = (c[0] + drift) % 1.0
        d += rng.uniform(0.6, 1.4) * np.exp(-((x - cx) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * r * r))
    return np.clip(d, 0.05, None)


FOG_BOX = ([-4.6, -0.05, -4.3], [4.6, 4.2, 2.6])  # the fog bank: floor, wall and spheres inside, eye and lights outside


def fog_scene(width: int = PAPER_W, height: int = PAPER_H, *, base_dir: Path, shape=(16, 24, 32),
              uniform: bool = False) -> dict:
    """The grid-fog scene: three spot lights (one projecting the polka-dot light map), two
    spheres and a small one casting shadow shafts, a floor and a back wall, in a fog bank given by
    `fog_density` on the box FOG_BOX (written to base_dir/fog_density.npy). The eye and the lights
    are outside the box, every object inside (Mitsuba's surfaces take one medium per side).
    `uniform`: the same scene in uniform fog (no grid), for the frame-time ratio."""
    dots = write_light_map(base_dir, "dots.exr", polka_dots(64, dots=4))
    spots = [
        {"position": [-2.6, 5.6, 1.0], "target": [-1.0, 0.0, -1.0], "intensity": [420, 260, 160]},
        {"position": [0.3, 6.0, 0.0], "target": [0.2, 0.0, -1.6], "intensity": [380, 380, 340], "light_map": dots},
        {"position": [2.8, 5.6, 0.8], "target": [1.2, 0.0, -0.6], "intensity": [150, 240, 420]},
    ]
    for s in spots:
        s.update({"up": [0.0, 0.0, 1.0], "cutoff_deg": 20.0, "beam_width_deg": 14.0})
        s["intensity"] = [float(x) for x in s["intensity"]]
    medium = {"rho": 1.0, "kappa": 0.12, "K": 0.004}
    if not uniform:
        np.save(base_dir / "fog_density.npy", fog_density(shape))
        medium["density"] = {"grid": "fog_density.npy", "box_min": FOG_BOX[0], "box_max": FOG_BOX[1]}
    return {
        "camera": {"eye": [0.0, 1.8, 8.0], "target": [0.0, 1.4, 0.0], "up": [0.0, 1.0, 0.0], "fov_y_deg": 42.0,
                   "width": width, "height": height},
        "medium": medium,
        "render": dict(RENDER),
        "spotlights": spots,
        "objects": [
            {"type": "quad", "center": [0.0, 0.0, -1.0], "u": [4.5, 0.0, 0.0], "v": [0.0, 0.0, -3.2],
             "albedo": [0.35, 0.32, 0.3]},
            {"type": "quad", "center": [0.0, 2.0, -4.2], "u": [4.5, 0.0, 0.0], "v": [0.0, 2.0, 0.0],
             "albedo": [0.25, 0.25, 0.3]},
            {"type": "sphere", "center": [-1.1, 0.7, -1.0], "radius": 0.7, "albedo": [0.8, 0.7, 0.6]},
            {"type": "sphere", "center": [1.3, 0.5, -0.5], "radius": 0.5, "albedo": [0.6, 0.7, 0.8]},
            {"type": "sphere", "center": [0.25, 2.6, -1.4], "radius": 0.3, "albedo": [0.85, 0.85, 0.85]},
        ],
    }
