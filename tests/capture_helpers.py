"""Small hand-written captures for the capture, store and ingest tests (written image by image, not
by `fitting.synth`): the design.md manifest of a white board and `lights` lights, 2 exposures each."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import OpenEXR


def write_capture(root: Path, image: Callable[[str], str], *, size: tuple[int, int], ext: str, lights: int,
                  exposures_s: list[float], angle_step: tuple[float, float], response: str = "linear") -> Path:
    """`image(relative_path)` writes one image and returns its path; light i sits at
    (theta, phi) = i * `angle_step` degrees. Returns `root`."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    exposures = range(len(exposures_s))
    manifest = {"format": "jaxrender-capture", "version": 1, "size": list(size), "response": response,
                "exposures_s": list(exposures_s), "view": {"theta_deg": 0, "phi_deg": 0},
                "white": {"reflectance": 0.9, "images": [image(f"images/w{e}.{ext}") for e in exposures]},
                "lights": [{"theta_deg": angle_step[0] * i, "phi_deg": angle_step[1] * i,
                            "images": [image(f"images/l{i}_e{e}.{ext}") for e in exposures]} for i in range(lights)]}
    (root / "capture.json").write_text(json.dumps(manifest))
    return root


def write_foreign_exr(path: Path, image) -> Path:
    """An RGB EXR as another program may write it, NaN and infinities included (the toolkit's own
    `write_exr` refuses values that are not finite): the readers must refuse it."""
    image = np.asarray(image, np.float32)
    channels = {c: np.ascontiguousarray(image[..., i]) for i, c in enumerate("RGB")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(str(path))
    return Path(path)
