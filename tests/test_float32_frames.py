"""The showcase frames in float32, the dtype users run, against the same frame in float64.

The suite runs in float64 (conftest); the float32 frame is rendered by a child Python process
without x64 (as the command line runs), from the same inputs written to disk: given dune and ripple
fields (the automata themselves are chaotic, so their float32 and float64 fields differ as any two
seeds do, and are tested in test_ripples / test_dunes), the same camera and sun. Dust is off in
the desert comparison: its particles come from random draws whose bits depend on the dtype.

The Takigi Noh frame's float32 check is tests/test_noh_bruteforce.py: the float32 frame against the
float64 brute-force reference of its own state, within the same tolerance as the float64 frame.
"""

import json
import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np

from jaxrender.app.scenes.desert import desert_frame, desert_scene, to_display
from jaxrender.camera import Camera

# float32 vs float64 desert frame, in display units (what the PNG shows, 1 = full scale): mean of the
# per-pixel max |diff| over RGB measured 1.0e-3 (a quarter of an 8-bit level: float32 rounding through
# the sky model, the ray cast, the texture-space shading and the tone map; max 8.8e-3); pixels whose
# primary ray grazes a dune crest or whose shading straddles a shadow edge may take the other branch
# of a discrete decision, so the tail is bounded by a fraction of pixels, not by a maximum.
DESERT_MEAN_TOL = 3e-3
DESERT_PIXEL_TOL = 2.0 / 255  # two 8-bit levels
DESERT_OUTLIER_FRACTION = 0.01  # measured 0.05 % of the pixels beyond two levels

_DESERT_CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    import jax
    assert not jax.config.jax_enable_x64
    from jaxrender.app.scenes.desert import desert_frame, desert_scene
    from jaxrender.camera import Camera
    data = np.load(sys.argv[1])
    spec = json.loads(sys.argv[2])
    scene = desert_scene(dune_field=data["dunes"], ripple_field=data["ripples"], texels=spec["texels"], seed=1)
    assert scene.maps.z.dtype == np.float32
    camera = Camera(*spec["camera"], width=spec["width"], height=spec["height"])
    image = desert_frame(scene, camera, **spec["frame"])
    assert image.dtype == np.float32
    np.save(sys.argv[3], np.asarray(image))
""")


def desert_inputs():
    """Small dune and ripple fields (smooth, periodic) and a camera that sees dunes, their shadows
    and the sky."""
    n = 16
    y, x = np.mgrid[0:n, 0:n] / n * 2 * np.pi
    dunes = 3.0 * np.maximum(np.sin(x + 0.4 * np.sin(y)), 0.0) ** 2 + 0.3 * np.cos(2 * y) + 0.2 * np.sin(2 * x + y)
    r = 16
    ry, rx = np.mgrid[0:r, 0:r] / r * 2 * np.pi
    ripples = np.sin(3 * rx + 0.5 * np.sin(ry)) + 0.2 * np.sin(6 * rx)
    spec = dict(texels=16, width=120, height=80,
                camera=[[2.0, 1.0, 4.0], [9.0, 10.0, 0.0], [0.0, 0.0, 1.0], 45.0],
                frame=dict(sun_elevation=14.0, sun_azimuth=200.0, dust=False, lod=True, culling=True))
    return dunes, ripples, spec


def render_float32_child(tmp_path, code: str, arrays: dict, spec: dict) -> np.ndarray:
    """Run `code` in a child Python without x64 (float32, as users run); it saves its image."""
    np.savez(tmp_path / "inputs.npz", **arrays)
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)
    out = tmp_path / "image32.npy"
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path / "inputs.npz"), json.dumps(spec), str(out)],
                          capture_output=True, text=True, env=env, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return np.load(out)


def test_desert_frame_float32_matches_float64(tmp_path):
    dunes, ripples, spec = desert_inputs()
    image32 = render_float32_child(tmp_path, _DESERT_CHILD, {"dunes": dunes, "ripples": ripples}, spec)
    scene = desert_scene(dune_field=dunes, ripple_field=ripples, texels=spec["texels"], seed=1)
    assert scene.maps.z.dtype == jnp.float64
    camera = Camera(*spec["camera"], width=spec["width"], height=spec["height"])
    image64 = np.asarray(desert_frame(scene, camera, **spec["frame"]))
    assert image32.shape == image64.shape == (80, 120, 3)
    assert np.all(np.isfinite(image32))
    shown32, shown64 = to_display(image32.astype(np.float64)), to_display(image64)
    diff = np.abs(shown32 - shown64).max(axis=-1)
    assert shown64.std() > 0.05  # a picture with dunes, shadows and sky, not a flat one
    assert diff.mean() < DESERT_MEAN_TOL, diff.mean()
    assert np.mean(diff > DESERT_PIXEL_TOL) < DESERT_OUTLIER_FRACTION, np.mean(diff > DESERT_PIXEL_TOL)
