"""The costume's label mask (paper 004, Fig. 7): which BTF each region of the robe's uv wears.

By the mask's 8-bit colour, gold (255, 255, 0) = `brocade` (kinran), green (0, 255, 0) = `hexagon`
(tortoise-shell kikko weave), cyan (0, 255, 255) = `satin` (the underlayer); any other colour is
the plain `pattern` weave whose rho_d is that colour (sRGB-decoded). `painted` and `hair` dress
the performer's body page (`.performer`). The robe's uv layout: docs/noh.md, "The costume".
"""

from __future__ import annotations

import numpy as np

from jaxrender.io import srgb_to_linear
from sims.costume import COLLAR_ROWS, COSTUME_LAYOUT

LABELS = ("brocade", "hexagon", "satin", "pattern", "painted", "hair")
PALETTE = {"brocade": (255, 255, 0), "hexagon": (0, 255, 0), "satin": (0, 255, 255)}
TAKES_COLOUR = ("pattern", "painted")     # labels whose rho_d is the mask's colour
_PATTERN_COLOURS = ((190, 30, 40), (235, 230, 215), (40, 60, 140), (230, 120, 40))   # sRGB 8-bit


def mask_from_rgb(rgb8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels H W int32 indices into LABELS, pattern colour H W 3 linear) from an 8-bit RGB mask."""
    rgb8 = np.asarray(rgb8)
    labels = np.full(rgb8.shape[:2], LABELS.index("pattern"), np.int32)
    for name, colour in PALETTE.items():
        hit = np.all(np.abs(rgb8[..., :3].astype(np.int32) - np.asarray(colour)) <= 2, axis=-1)
        labels[hit] = LABELS.index(name)
    colour = np.asarray(srgb_to_linear(rgb8[..., :3].astype(np.float64) / 255.0), np.float32)
    return labels, colour


def default_mask(size: int = 512, *, body_rows: int = 30) -> np.ndarray:
    """The built-in 8-bit RGB mask over the robe's uv (`sims.costume.COSTUME_LAYOUT`): dan-gawari
    blocks alternating gold brocade and hexagon weave (left and right halves of the body swapped
    at each third of its height, each sleeve the other weave than the shoulder beside it), flower
    roundels in the plain weave's colours, and the satin underlayer at the collar band and hem."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    out = np.zeros((size, size, 3), np.uint8)
    out[...] = PALETTE["hexagon"]
    weaves = (PALETTE["brocade"], PALETTE["hexagon"])
    u0, v0, du, dv = COSTUME_LAYOUT["body"]
    s, t = (u - u0) / du, (v - v0) / dv
    body = (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    block = ((s >= 0.5).astype(int) + np.floor(np.clip(t, 0, 0.999) * 3).astype(int)) % 2
    for k in (0, 1):
        out[body & (block == k)] = weaves[k]
    for side, first in (("sleeve_L", 0), ("sleeve_R", 1)):     # s >= 0.5 is the left half's top block (0)
        u0, v0, du, dv = COSTUME_LAYOUT[side]
        inside = (u >= u0) & (u <= u0 + du) & (v >= v0) & (v <= v0 + dv)
        out[inside] = weaves[first]
    # flower roundels on a staggered lattice: five petals around a centre
    cells = 9
    cu, cv = u * cells, v * cells * 1.2
    row = np.floor(cv)
    cu = cu + 0.5 * (row % 2)
    fu, fv = cu - np.floor(cu) - 0.5, cv - row - 0.5
    r = np.hypot(fu, fv)
    ang = np.arctan2(fv, fu)
    petal = r < 0.2 + 0.1 * np.cos(5 * ang)
    idx = (np.floor(cu).astype(int) * 7 + row.astype(int) * 3) % len(_PATTERN_COLOURS)
    colours = np.asarray(_PATTERN_COLOURS, np.uint8)[idx]
    out[petal] = colours[petal]
    out[r < 0.06] = (235, 200, 60)   # a golden-yellow centre painted in the plain weave
    collar = body & (t < (COLLAR_ROWS - 0.5) / (body_rows - 1))
    out[collar | (body & (t > 0.95))] = PALETTE["satin"]
    return out
