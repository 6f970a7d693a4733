"""The garment's label mask (paper 004, Fig. 7): which BTF each region of the garment's uv wears.

By the mask's 8-bit colour, gold (255, 255, 0) = `brocade` (kinran), green (0, 255, 0) = `hexagon`
(tortoise-shell kikko weave), cyan (0, 255, 255) = `satin` (the underlayer); any other colour is
the plain `pattern` weave whose rho_d is that colour (sRGB-decoded).
"""

from __future__ import annotations

import numpy as np

from jaxrender.io import srgb_to_linear

LABELS = ("brocade", "hexagon", "satin", "pattern")
PALETTE = {"brocade": (255, 255, 0), "hexagon": (0, 255, 0), "satin": (0, 255, 255)}
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


def default_mask(size: int = 256) -> np.ndarray:
    """The built-in 8-bit RGB mask over the garment's uv (row 0 = the shoulders): dan-gawari
    blocks alternating gold brocade and hexagon weave, flower roundels in the plain weave's
    colours, and a satin underlayer showing at the hem."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    out = np.zeros((size, size, 3), np.uint8)
    block = (np.floor(u * 2).astype(int) + np.floor(v * 3).astype(int)) % 2
    out[block == 0] = PALETTE["brocade"]
    out[block == 1] = PALETTE["hexagon"]
    # flower roundels on a staggered lattice: five petals around a centre
    cells = 5
    cu, cv = u * cells, v * cells * 1.5
    row = np.floor(cv)
    cu = cu + 0.5 * (row % 2)
    fu, fv = cu - np.floor(cu) - 0.5, cv - row - 0.5
    r = np.hypot(fu, fv)
    ang = np.arctan2(fv, fu)
    petal = r < 0.22 + 0.12 * np.cos(5 * ang)
    idx = (np.floor(cu).astype(int) * 7 + row.astype(int) * 3) % len(_PATTERN_COLOURS)
    colours = np.asarray(_PATTERN_COLOURS, np.uint8)[idx]
    out[petal] = colours[petal]
    centre = r < 0.07
    out[centre] = (235, 200, 60)  # a golden-yellow centre painted in the plain weave
    out[v > 0.9] = PALETTE["satin"]
    return out
