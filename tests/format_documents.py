"""Documents generated from each format's description (hypothesis strategies): light-shaft scene
files (design.md, docs/fog.md), capture directories (docs/formats.md), DiLiGenT-format folders
and BVH files (docs/noh.md). A valid document exercises every optional part, present and absent,
and legal extremes; `broken_*` applies one mutation that the format forbids. Each strategy draws a
`Document`: what to write (`write(folder) -> path`) and, for a broken one, what it breaks.

Used by tests/test_formats_generated.py (a small budget, derandomized) and
benchmarks/format_fuzz.py (a larger one through the command lines).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import assume
from hypothesis import strategies as st

F32 = float(np.finfo(np.float32).max)


@dataclasses.dataclass
class Document:
    write: Callable[[Path], Path]   # writes the document (and its files) into a folder; returns what to pass
    breaks: str = ""                # for a broken document: the mutation


# ---------------------------------------------------------------- numbers
def magnitudes(lo: float = 0.0, hi: float = F32, *, lo_open: bool = False) -> st.SearchStrategy[float]:
    """Numbers in [lo, hi], biased to everyday sizes and the extremes of the range."""
    everyday = st.floats(max(lo, 1e-3) if lo_open else lo, min(hi, 1e3), allow_nan=False)
    extreme = st.sampled_from([v for v in (hi, min(hi, 1e30), min(hi, 1e12), max(lo, 1e-30) if lo_open else lo)
                               if lo <= v <= hi and not (lo_open and v == lo)])
    anywhere = st.floats(lo, hi, allow_nan=False, exclude_min=lo_open)
    return st.one_of(everyday, extreme, anywhere)


def coordinates(scale: float = 1e6) -> st.SearchStrategy[float]:
    return st.one_of(st.floats(-10, 10, allow_nan=False), st.floats(-scale, scale, allow_nan=False),
                     st.sampled_from([0.0, scale, -scale]))


vectors = st.lists(coordinates(), min_size=3, max_size=3)


def _parallel(a, b) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return na == 0 or nb == 0 or np.linalg.norm(np.cross(a / na, b / nb)) < 1e-3


def rgb(lo: float = 0.0, hi: float = F32, *, lo_open: bool = False):
    value = magnitudes(lo, hi, lo_open=lo_open)
    return st.one_of(value, st.lists(value, min_size=3, max_size=3))


# ---------------------------------------------------------------- images
@st.composite
def image_arrays(draw, size: tuple[int, int], *, channels=(1, 3, 4)) -> np.ndarray:
    """Values in [0, 1], `H W C`."""
    c = draw(st.sampled_from(channels))
    seed = draw(st.integers(0, 2**31 - 1))
    return np.random.default_rng(seed).random(size + (c,))


def write_png(path: Path, image: np.ndarray, bits: int) -> Path:
    import imagecodecs

    scale = 255 if bits == 8 else 65535
    codes = np.round(np.clip(image, 0, 1) * scale).astype(np.uint8 if bits == 8 else np.uint16)
    path.write_bytes(imagecodecs.png_encode(codes[..., 0] if codes.shape[-1] == 1 else codes))
    return path


def write_tiff(path: Path, image: np.ndarray, bits: int) -> Path:
    import tifffile

    scale = 255 if bits == 8 else 65535
    codes = np.round(np.clip(image, 0, 1) * scale).astype(np.uint8 if bits == 8 else np.uint16)
    tifffile.imwrite(path, codes[..., 0] if codes.shape[-1] == 1 else codes)
    return path


def write_exr(path: Path, image: np.ndarray, scale: float = 1.0) -> Path:
    from jaxrender.io import write_exr as exr

    rgb_ = np.repeat(image[..., :1], 3, -1) if image.shape[-1] == 1 else image[..., :3]
    return exr(path, np.asarray(rgb_ * scale, np.float32))


# ---------------------------------------------------------------- light-shaft scene files
MAX_RENDER = {"shadow_map": 16384, "table_size": 16384}


@st.composite
def look_at(draw, *, up_optional: bool = True) -> dict:
    origin = draw(vectors)
    offset = draw(st.lists(st.one_of(st.floats(-10, 10, allow_nan=False), st.sampled_from([1e4, -1e4])),
                           min_size=3, max_size=3))
    target = [o + d for o, d in zip(origin, offset)]
    assume(np.linalg.norm(np.subtract(target, origin)) > 0)
    out = {"origin": origin, "target": target}
    up = draw(st.one_of(st.none(), vectors) if up_optional else vectors)
    if up is not None:
        assume(not _parallel(up, np.subtract(target, origin)))
        out["up"] = up
    else:
        assume(not _parallel([0, 1, 0], np.subtract(target, origin)))
    return out


@st.composite
def scene_documents(draw, *, renderable: bool = False) -> Document:
    """A valid scene file and the files it names. `renderable`: maps, tables and images small enough
    to render in a test (the legal extremes of those sizes are drawn only when False)."""
    cam = draw(look_at())
    side = st.integers(1, 64) if renderable else st.one_of(st.integers(1, 64), st.sampled_from([1, 16384]))
    width, height = draw(side), draw(side)
    assume(width * height <= 2**26)   # the renderer's sample budget (design: MAX_SAMPLES)
    camera = {"eye": cam["origin"], "target": cam["target"], "fov_y_deg": draw(magnitudes(0.0, 179.0, lo_open=True)),
              "width": width, "height": height}
    if "up" in cam:
        camera["up"] = cam["up"]
    files: dict[str, Callable[[Path], None]] = {}
    medium = {"rho": draw(magnitudes()), "kappa": draw(magnitudes()), "K": draw(magnitudes())}
    peak = 1.0
    if draw(st.booleans()):
        shape = tuple(draw(st.lists(st.integers(1, 4), min_size=3, max_size=3)))
        grid = np.random.default_rng(draw(st.integers(0, 99))).random(shape) * draw(magnitudes(0.0, 1e30))
        peak = float(grid.max())
        lo = draw(vectors)
        hi = [a + draw(magnitudes(0.0, 1e3, lo_open=True)) for a in lo]
        assume(all(b > a for a, b in zip(lo, hi)))
        files["fog.npy"] = lambda folder, g=grid: np.save(folder / "fog.npy", g)
        medium["density"] = {"grid": "fog.npy", "box_min": lo, "box_max": hi}
    # the coefficients the renderer forms are float32 numbers too (docs/formats.md)
    assume(medium["rho"] * medium["kappa"] * peak <= F32 and 10 * medium["rho"] * medium["K"] * peak <= F32
           and 10 * medium["K"] * max(peak, 1.0) <= F32)
    doc = {"camera": camera, "medium": medium}
    if draw(st.booleans()):   # render: optional, and each of its fields
        render = {}
        small = st.integers(2, 64) if renderable else st.one_of(st.integers(2, 64), st.just(16384))
        for key in ("shadow_map", "table_size"):
            if draw(st.booleans()):
                render[key] = draw(small)
        if draw(st.booleans()):
            k = draw(st.integers(1, 4 if renderable else 32))
            assume(width * height * k * k <= 2**26)
            render["spp"] = k * k
        if draw(st.booleans()):
            render["shadow_bias"] = draw(magnitudes(0.0, 1e3))
        s_min = draw(magnitudes(0.0, 1e6, lo_open=True))
        if draw(st.booleans()):
            render["s_min"] = s_min
        if draw(st.booleans()):
            render["s_max"] = draw(st.floats(s_min * 1.01, s_min * 1e3 + 10))
        elif "s_min" in render:
            assume(s_min < 20.0)  # the default s_max
        for key in ("t_max", "display_white"):
            if draw(st.booleans()):
                render[key] = draw(magnitudes(0.0, lo_open=True))
        doc["render"] = render
    lights = []
    for i in range(draw(st.integers(1, 3))):
        frame = draw(look_at())
        cutoff = draw(magnitudes(0.0, 89.0, lo_open=True))
        light = {"position": frame["origin"], "target": frame["target"], "cutoff_deg": cutoff,
                 "intensity": draw(rgb())}
        if "up" in frame:
            light["up"] = frame["up"]
        if draw(st.booleans()):
            light["beam_width_deg"] = draw(st.floats(0.0, cutoff))
        if draw(st.booleans()):
            name = f"map{i}.{draw(st.sampled_from(['png', 'exr']))}"
            size = (draw(st.integers(1, 8)), draw(st.integers(1, 8)))
            image = draw(image_arrays(size))
            bits = draw(st.sampled_from([8, 16]))
            files[name] = (lambda folder, n=name, im=image, b=bits:
                           write_png(folder / n, im, b) if n.endswith(".png") else write_exr(folder / n, im, 4.0))
            light["light_map"] = name
        lights.append(light)
    doc["spotlights"] = lights
    if draw(st.booleans()):
        objects = []
        for _ in range(draw(st.integers(0, 3))):
            obj = {"type": draw(st.sampled_from(["sphere", "quad"])), "center": draw(vectors)}
            if obj["type"] == "sphere":
                obj["radius"] = draw(magnitudes(0.0, 1e6, lo_open=True))
            else:
                obj["u"], obj["v"] = draw(vectors), draw(vectors)
                assume(not _parallel(obj["u"], obj["v"]))
            if draw(st.booleans()):
                obj["albedo"] = draw(rgb(0.0, 1.0))
            objects.append(obj)
        doc["objects"] = objects

    indent = draw(st.sampled_from([None, 1]))

    def write(folder: Path) -> Path:
        for make in files.values():
            make(folder)
        path = folder / "scene.json"
        path.write_text(json.dumps(doc, indent=indent))
        return path

    return Document(write)


SCENE_BREAKS = {   # one forbidden change each: (what, how)
    "no camera": lambda d: d.pop("camera"),
    "no medium": lambda d: d.pop("medium"),
    "no spot light": lambda d: d.update(spotlights=[]),
    "fov 0": lambda d: d["camera"].update(fov_y_deg=0),
    "fov 180": lambda d: d["camera"].update(fov_y_deg=180),
    "width 0": lambda d: d["camera"].update(width=0),
    "width a string": lambda d: d["camera"].update(width="720"),
    "eye of 2 numbers": lambda d: d["camera"].update(eye=[0, 1]),
    "target at the eye": lambda d: d["camera"].update(target=list(d["camera"]["eye"])),
    "negative rho": lambda d: d["medium"].update(rho=-1),
    "rho beyond float32": lambda d: d["medium"].update(rho=1e39),
    "extinction beyond float32": lambda d: d["medium"].update(rho=1e20, kappa=1e20),
    "phase function beyond float32": lambda d: d["medium"].update(rho=1e-40, K=1e38),
    "rho NaN": lambda d: d["medium"].update(rho=float("nan")),
    "unknown medium field": lambda d: d["medium"].update(sigma=1),
    "cutoff 90": lambda d: d["spotlights"][0].update(cutoff_deg=90),
    "beam wider than cutoff": lambda d: d["spotlights"][0].update(beam_width_deg=d["spotlights"][0]["cutoff_deg"] + 1),
    "negative intensity": lambda d: d["spotlights"][0].update(intensity=[-1, 1, 1]),
    "intensity beyond float32": lambda d: d["spotlights"][0].update(intensity=1e39),
    "missing light map": lambda d: d["spotlights"][0].update(light_map="nowhere.png"),
    "up along the beam": lambda d: d["spotlights"][0].update(
        up=list(np.subtract(d["spotlights"][0]["target"], d["spotlights"][0]["position"]))),
    "spp not a square": lambda d: d.setdefault("render", {}).update(spp=2),
    "s_max below s_min": lambda d: d.setdefault("render", {}).update(s_min=2.0, s_max=1.0),
    "shadow map of 1": lambda d: d.setdefault("render", {}).update(shadow_map=1),
    "unknown object": lambda d: d.setdefault("objects", []).append({"type": "cone", "center": [0, 0, 0]}),
    "sphere of radius 0": lambda d: d.setdefault("objects", []).append({"type": "sphere", "center": [0, 0, 0],
                                                                        "radius": 0}),
    "flat quad": lambda d: d.setdefault("objects", []).append({"type": "quad", "center": [0, 0, 0], "u": [1, 0, 0],
                                                               "v": [2, 0, 0]}),
    "unknown top-level field": lambda d: d.update(lights=[]),
    "density grid missing": lambda d: d["medium"].update(density={"grid": "nowhere.npy", "box_min": [0, 0, 0],
                                                                  "box_max": [1, 1, 1]}),
    "too many pixels": lambda d: d["camera"].update(width=16384, height=16384),
}


@st.composite
def broken_scene_documents(draw) -> Document:
    valid = draw(scene_documents(renderable=True))
    what = draw(st.sampled_from(sorted(SCENE_BREAKS) + ["not JSON"]))

    def write(folder: Path) -> Path:
        path = valid.write(folder)
        if what == "not JSON":
            path.write_text(path.read_text()[:-2])
            return path
        doc = json.loads(path.read_text())
        SCENE_BREAKS[what](doc)
        path.write_text(json.dumps(doc))
        return path

    return Document(write, what)


# ---------------------------------------------------------------- BVH
ROTATIONS = ("Xrotation", "Yrotation", "Zrotation")
POSITIONS = ("Xposition", "Yposition", "Zposition")


@st.composite
def bvh_documents(draw, *, max_joints: int = 30, max_frames: int = 8) -> Document:
    """A valid BVH file: a random tree (chains as deep as `max_joints`), 0, 3 or 6 channels per
    joint in any order and case, End Sites or not, several roots, blank lines, tabs, CRLF and a
    byte-order mark, Frame Time from 1 us to an hour, legal extreme values."""
    n = draw(st.integers(1, max_joints))
    lowest = draw(st.sampled_from([0, -1]))   # -1: several roots
    parents = [-1] + [draw(st.one_of(st.just(i - 1), st.integers(lowest, i - 1))) for i in range(1, n)]
    channels = []
    for i in range(n):
        kind = draw(st.sampled_from(["none", "rot", "pos+rot", "pos"]))
        names = {"none": (), "rot": ROTATIONS, "pos": POSITIONS, "pos+rot": POSITIONS + ROTATIONS}[kind]
        names = draw(st.permutations(names)) if names else []
        case = draw(st.sampled_from([str, str.lower, str.upper]))
        channels.append([case(c) for c in names])
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)
    end_sites = {j: draw(st.booleans()) for j in range(n)}
    number = st.one_of(st.floats(-1e3, 1e3, allow_nan=False), st.sampled_from([0.0, -0.0, 1e6, -1e6, 1e-30]))
    eol = draw(st.sampled_from(["\n", "\r\n"]))
    sep = draw(st.sampled_from([" ", "\t", "  "]))
    lines = ["HIERARCHY"]
    # an explicit stack: a chain of any depth (the reader must take it too)
    stack: list[tuple[str, int, int]] = [("open", j, 0) for j in reversed(children[-1])]
    while stack:
        action, j, depth = stack.pop()
        pad = sep * depth
        if action == "close":
            lines.append(f"{pad}}}")
            continue
        kind = "ROOT" if parents[j] < 0 else "JOINT"
        offset = sep.join(repr(draw(number)) for _ in range(3))
        lines += [f"{pad}{kind} joint{j}", f"{pad}{{", f"{pad}{sep}OFFSET{sep}{offset}"]
        if channels[j] or draw(st.booleans()):
            lines.append(f"{pad}{sep}CHANNELS {len(channels[j])} {sep.join(channels[j])}".rstrip())
        stack.append(("close", j, depth))
        if end_sites[j]:
            lines += [f"{pad}{sep}End Site", f"{pad}{sep}{{", f"{pad}{sep}{sep}OFFSET 0 1 0", f"{pad}{sep}}}"]
        stack += [("open", c, depth + 1) for c in reversed(children.get(j, []))]
    frames = draw(st.integers(1, max_frames))
    frame_time = draw(st.one_of(st.floats(1e-6, 3600.0), st.sampled_from([1e-6, 1 / 30, 3600.0])))
    lines += ["MOTION", f"Frames:{sep}{frames}", f"Frame Time:{sep}{frame_time!r}"]
    width = sum(len(c) for c in channels)
    for _ in range(frames):
        lines.append(sep.join(repr(draw(number)) for _ in range(width)))
    if draw(st.booleans()):
        lines.append("")
    text = eol.join(lines) + eol
    bom = draw(st.booleans())

    def write(folder: Path) -> Path:
        path = folder / "motion.bvh"
        path.write_bytes(("\ufeff" if bom else "").encode() + text.encode())
        return path

    return Document(write)


BVH_BREAKS = {
    "no HIERARCHY": lambda t: t.replace("HIERARCHY", "HIERARCH", 1),
    "no MOTION": lambda t: t.replace("MOTION", "MOTIONS", 1),
    "a brace missing": lambda t: t.replace("{", "", 1),
    "unknown channel": lambda t: re.sub("rotation", "spin", t, count=1, flags=re.I) if "rotation" in t.lower()
    else t.replace("OFFSET", "OFFSETT", 1),
    "frames 0": lambda t: _replace_header(t, "Frames:", "0"),
    "frame time 0": lambda t: _replace_header(t, "Frame Time:", "0"),
    "frame time 1e-300": lambda t: _replace_header(t, "Frame Time:", "1e-300"),
    "a value beyond float32": lambda t: re.sub(r"OFFSET(\s+)(\S+)", r"OFFSET\g<1>1e39", t, count=1),
    "a word in the motion": lambda t: t.rstrip() + " x\n",
    "one more frame than Frames": lambda t: _replace_header(t, "Frames:", str(_frames(t) - 1)) if _frames(t) > 1
    else _replace_header(t, "Frames:", "2"),
    "a joint name twice": lambda t: t.replace("joint1", "joint0") if "joint1" in t else t.replace("HIERARCHY", "H"),
    "not text": lambda t: "\x00\xff\xfe" + t,
}


def _header_line(text: str, key: str) -> str:
    return next(line for line in text.splitlines() if line.strip().lstrip("\ufeff").startswith(key))


def _replace_header(text: str, key: str, value: str) -> str:
    line = _header_line(text, key)
    return text.replace(line, f"{key} {value}", 1)


def _frames(text: str) -> int:
    return int(_header_line(text, "Frames:").split(":")[1])


@st.composite
def broken_bvh_documents(draw) -> Document:
    valid = draw(bvh_documents(max_joints=6, max_frames=3))
    what = draw(st.sampled_from(sorted(BVH_BREAKS)))

    def write(folder: Path) -> Path:
        path = valid.write(folder)
        text = path.read_bytes().decode("utf-8-sig")
        broken = BVH_BREAKS[what](text)
        path.write_bytes(broken.encode("latin-1") if what == "not text" else broken.encode())
        return path

    return Document(write, what)


# ---------------------------------------------------------------- capture directories
def _unit(theta: float, phi: float) -> list[float]:
    t, p = math.radians(theta), math.radians(phi)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


@st.composite
def direction_entry(draw) -> dict:
    theta, phi = draw(st.floats(0.0, 89.0)), draw(st.floats(-720.0, 720.0))
    if draw(st.booleans()):
        return {"theta_deg": theta, "phi_deg": phi}
    return {"direction": [round(x, 12) for x in _unit(theta, phi)]}


@st.composite
def capture_documents(draw) -> Document:
    """A valid capture directory: size, exposures, response, view (angles or direction), white board
    or per-light intensities or both, 8/16-bit PNG, TIFF or EXR images, mask, saturation, encoding."""
    size = (draw(st.integers(1, 5)), draw(st.integers(1, 5)))
    exposures = sorted(draw(st.sets(st.sampled_from([0.001, 0.004, 0.01, 0.05, 0.25, 1.0]), min_size=1,
                                    max_size=3)))
    kind = draw(st.sampled_from(["png8", "png16", "tiff8", "tiff16", "exr"]))
    ext = {"png8": "png", "png16": "png", "tiff8": "tif", "tiff16": "tif", "exr": "exr"}[kind]
    n_lights = draw(st.integers(1, 5))
    with_intensity = draw(st.booleans())
    with_white = draw(st.booleans()) or not with_intensity
    images: dict[str, np.ndarray] = {}

    def bracket(stem: str) -> list[str]:
        names = []
        for e in range(len(exposures)):
            name = f"images/{stem}_e{e}.{ext}"
            images[name] = draw(image_arrays(size, channels=(1, 3, 4) if ext != "exr" else (3,)))
            names.append(name)
        return names

    manifest = {"format": "jaxrender-capture", "version": 1, "size": list(size),
                "response": draw(st.sampled_from(["linear", "srgb"])), "exposures_s": exposures,
                "view": draw(direction_entry())}
    if with_white:
        manifest["white"] = {"reflectance": draw(rgb(1e-3, 1e3, lo_open=True)), "images": bracket("white")}
    lights = []
    for i in range(n_lights):
        entry = draw(direction_entry())
        if with_intensity:
            entry["intensity"] = draw(rgb(1e-6, 1e6, lo_open=True))
        entry["images"] = bracket(f"l{i}")
        lights.append(entry)
    manifest["lights"] = lights
    mask = None
    if draw(st.booleans()):
        mask = np.random.default_rng(draw(st.integers(0, 99))).random(size) > 0.5
        mask.flat[draw(st.integers(0, mask.size - 1))] = True   # at least one texel to fit
        manifest["mask"] = "mask.png"
    if ext == "exr":
        if draw(st.booleans()):
            manifest["saturation"] = draw(magnitudes(0.0, 1e6, lo_open=True))
        if draw(st.booleans()):
            manifest["encoding"] = draw(st.sampled_from(["codes", "radiance"]))
    bits = 16 if kind.endswith("16") else 8

    def write(folder: Path) -> Path:
        (folder / "images").mkdir(parents=True, exist_ok=True)
        for name, image in images.items():
            if ext == "png":
                write_png(folder / name, image, bits)
            elif ext == "tif":
                write_tiff(folder / name, image, bits)
            else:
                write_exr(folder / name, image, 2.0)
        if mask is not None:
            write_png(folder / "mask.png", mask[..., None].astype(float), 8)
        (folder / "capture.json").write_text(json.dumps(manifest, indent=1))
        return folder

    return Document(write)


CAPTURE_BREAKS = {
    "wrong format": lambda m, f: m.update(format="something"),
    "version 2": lambda m, f: m.update(version=2),
    "size of 1 number": lambda m, f: m.update(size=[4]),
    "unknown response": lambda m, f: m.update(response="gamma"),
    "no exposures": lambda m, f: m.update(exposures_s=[]),
    "light below the horizon": lambda m, f: m["lights"][0].update(theta_deg=95, phi_deg=0) or m["lights"][0].pop(
        "direction", None),
    "direction not unit": lambda m, f: m["lights"][0].update(direction=[0, 0, 2]) or m["lights"][0].pop(
        "theta_deg", None) or m["lights"][0].pop("phi_deg", None),
    "an image too few": lambda m, f: m["lights"][0]["images"].pop(),
    "missing image": lambda m, f: (f / m["lights"][0]["images"][0]).unlink(),
    "image of another size": lambda m, f: write_png(f / m["lights"][0]["images"][0],
                                                    np.zeros((m["size"][0] + 1, m["size"][1], 3)), 8)
    if m["lights"][0]["images"][0].endswith(".png") else (f / m["lights"][0]["images"][0]).write_bytes(b"junk"),
    "a corrupt image": lambda m, f: (f / m["lights"][0]["images"][0]).write_bytes(b"\x89PNG\r\n\x1a\njunk"),
    "no lights": lambda m, f: m.update(lights=[]),
    "negative intensity": lambda m, f: m["lights"][0].update(intensity=-1),
    "reflectance 0": lambda m, f: m.setdefault("white", {"images": []}).update(reflectance=0),
    "mask of another size": lambda m, f: (write_png(f / "mask.png", np.ones((m["size"][0] + 2, 1, 1)), 8),
                                          m.update(mask="mask.png")),
}


@st.composite
def broken_capture_documents(draw) -> Document:
    valid = draw(capture_documents())
    what = draw(st.sampled_from(sorted(CAPTURE_BREAKS)))

    def write(folder: Path) -> Path:
        valid.write(folder)
        manifest = json.loads((folder / "capture.json").read_text())
        CAPTURE_BREAKS[what](manifest, folder)
        (folder / "capture.json").write_text(json.dumps(manifest))
        return folder

    return Document(write, what)


# ---------------------------------------------------------------- DiLiGenT-format folders
@st.composite
def diligent_documents(draw) -> Document:
    """A valid DiLiGenT-format folder: 16-bit (or 8-bit) PNGs named in filenames.txt, unit light
    directions and positive intensities (numbers in any layout: spaces, tabs, commas, exponents,
    blank lines), optionally mask.png."""
    size = (draw(st.integers(1, 6)), draw(st.integers(1, 6)))
    n = draw(st.integers(1, 6))
    names = [draw(st.sampled_from(["{:03d}.png", "img_{}.png", "L{:04d}.PNG"])).format(i + 1) for i in range(n)]
    assume(len(set(names)) == n)
    dirs = [_unit(draw(st.floats(0.0, 89.0)), draw(st.floats(0.0, 360.0))) for _ in range(n)]
    intensities = [[draw(magnitudes(1e-6, 1e6, lo_open=True)) for _ in range(3)] for _ in range(n)]
    sep = draw(st.sampled_from([" ", "\t", ", ", "  "]))
    fmt = draw(st.sampled_from(["{:.9f}", "{!r}", "{:.6e}"]))
    bits = draw(st.sampled_from([8, 16]))
    images = [draw(image_arrays(size, channels=(1, 3, 4))) for _ in range(n)]
    mask = None
    if draw(st.booleans()):
        mask = np.random.default_rng(draw(st.integers(0, 99))).random(size) > 0.3
        mask.flat[0] = True

    def table(rows):
        return "\n".join(sep.join(fmt.format(float(x)) for x in row) for row in rows) + "\n"

    def write(folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "filenames.txt").write_text("\n".join(names) + "\n")
        (folder / "light_directions.txt").write_text(table(dirs))
        (folder / "light_intensities.txt").write_text(table(intensities))
        for name, image in zip(names, images):
            write_png(folder / name, image, bits)
        if mask is not None:
            write_png(folder / "mask.png", mask[..., None].astype(float), 8)
        return folder

    return Document(write)


DILIGENT_BREAKS = {
    "no filenames.txt": lambda f: (f / "filenames.txt").unlink(),
    "no light_directions.txt": lambda f: (f / "light_directions.txt").unlink(),
    "a row too many": lambda f: (f / "light_intensities.txt").write_text((f / "light_intensities.txt").read_text()
                                                                          + "1 1 1\n"),
    "direction not unit": lambda f: _first_row(f / "light_directions.txt", "0 0 2"),
    "direction downward": lambda f: _first_row(f / "light_directions.txt", "0 0 -1"),
    "intensity 0": lambda f: _first_row(f / "light_intensities.txt", "0 1 1"),
    "two numbers on a line": lambda f: _first_row(f / "light_intensities.txt", "1 1"),
    "missing image": lambda f: (f / (f / "filenames.txt").read_text().split()[0]).unlink(),
    "image of another size": lambda f: (write_png(f / "mask.png", np.ones(_size(f) + (1,)), 8),
                                        write_png(f / (f / "filenames.txt").read_text().split()[0],
                                                  np.zeros((9, 9, 3)), 16)),
    "all-zero mask": lambda f: write_png(f / "mask.png", np.zeros(_size(f) + (1,)), 8),
    "mask of another size": lambda f: write_png(f / "mask.png", np.ones((9, 9, 1)), 8),
}


def _first_row(path: Path, row: str) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join([row] + lines[1:]) + "\n")


def _size(folder: Path) -> tuple[int, int]:
    from jaxrender.io import read_image

    return read_image(folder / (folder / "filenames.txt").read_text().split()[0]).shape[:2]


@st.composite
def broken_diligent_documents(draw) -> Document:
    valid = draw(diligent_documents())
    what = draw(st.sampled_from(sorted(DILIGENT_BREAKS)))

    def write(folder: Path) -> Path:
        valid.write(folder)
        DILIGENT_BREAKS[what](folder)
        return folder

    return Document(write, what)
