"""Gallery section of the desert (paper 001, Figs. 12-18)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from jaxrender.io import write_exr, write_png

from ..scenes.desert import render_desert, to_display


def gallery_section(out_dir: Path, *, quick: bool = False) -> Iterator[dict]:
    """The paper's Figs. 12-18: without/with ripples, without/with dune shadows, without/with
    ripple shadows, with dust and footprints. Writes PNG + EXR files under `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    size = dict(width=240, height=160) if quick else dict(width=720, height=480)
    scene_kw = dict(ripple_size=32, texels=32) if quick else {}
    high, low = 25.0, 12.0
    figures = [
        ("fig12_no_ripples", "Fig. 12: dunes without wind ripples",
         dict(ripples=False, dust=False, sun_elevation=high)),
        ("fig13_ripples", "Fig. 13: dunes with wind ripples and sand grain (LOD, culling)",
         dict(dust=False, sun_elevation=high, dune_shadows=False, ripple_shadows=False)),
        ("fig14_no_shadows", "Fig. 14: low sun, no shadows",
         dict(dust=False, sun_elevation=low, dune_shadows=False, ripple_shadows=False)),
        ("fig15_dune_shadows", "Fig. 15/16: low sun, dune shadows (no ripple shadows)",
         dict(dust=False, sun_elevation=low, ripple_shadows=False)),
        ("fig17_ripple_shadows", "Fig. 17: low sun, dune and ripple shadows", dict(dust=False, sun_elevation=low)),
        ("fig18_dust", "Fig. 18: with sand dust and a trail of footprints (pressed, relaxed to the angle of repose)",
         dict(sun_elevation=high, footprints=True)),
    ]
    if quick:  # every switch combination is its own compilation: quick mode shows two of them
        figures = [f for f in figures if f[0] in ("fig13_ripples", "fig18_dust")]
    for name, title, kw in figures:
        params = dict(size, **scene_kw, **kw)
        if not quick:
            render_desert(**params)  # compile (and grow the fields) outside the timing
        timing: dict = {}
        image = render_desert(timing=timing, **params)
        write_png(out_dir / f"{name}.png", to_display(image), srgb=False)
        write_exr(out_dir / f"{name}.exr", np.asarray(image, np.float32))
        when = "including compilation (quick mode)" if quick else "after compilation"
        caption = (f"{title}. {params['width']}x{params['height']}; frame {timing['frame_s']:.2f} s {when}; "
                   f"visible quads per ripple level (buffer capacities) {timing['capacities']}.")
        yield {"title": title, "images": [f"{name}.png"], "caption": caption,
                        "params": {k: v for k, v in params.items()},
                        "timings": {"frame_s": timing["frame_s"], "plan_s": timing["plan_s"]}}
