"""Stored maps of the fit on two small captures (`tests/data/fit_golden.npz`), to hold the engine to
its results while its code is restructured (`tests/test_fit_golden.py`).

    python tests/fit_golden.py          # record the maps of the code as it stands (x64 on, as in the tests)

Captures: a 16 x 16 synthetic fabric under 96 stratified lights (8-bit sensor noise) and the
DiLiGenT cat, every 12th row and column of its mask, 96 lights. Every method is fitted in memory
(`fitting.fit_maps`) with chunks of one padded shape.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

import fitting
from fitting import LIGHT_DIRECTIONS, FitSettings, fit_maps, stratified_light_subset, synth_maps, synth_observations

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "data" / "fit_golden.npz"
FIELDS = ("rho_d", "rho_s", "normal", "sigma_x", "sigma_y", "residual", "cost", "converged", "num_steps", "n_valid",
          "material")
CHUNK = 256        # every fit here: one padded shape (that of tests/test_robust_fit.py: one compilation)
CAT_STRIDE = 12


def diligent_root() -> Path:
    env = os.environ.get("JAXRENDER_DILIGENT")
    return Path(env) if env else HERE.parents[1] / "shared" / "data" / "diligent"


def synthetic_observations():
    """16 x 16 texels of the synthetic fabric under 96 stratified lights, float32."""
    maps = synth_maps(jax.random.key(11), (16, 16))
    maps = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), maps)
    dirs = LIGHT_DIRECTIONS[stratified_light_subset(jax.random.key(12), 96)].astype(np.float32)
    obs = synth_observations(jax.random.key(13), maps, dirs)
    return _float32(obs)


def cat_observations(tmp: Path):
    """The DiLiGenT cat, every `CAT_STRIDE`-th row and column of its mask (the rest masked out)."""
    folder = diligent_root() / "catPNG"
    if not folder.is_dir():
        raise FileNotFoundError(f"DiLiGenT data not found at {folder.parent}: set JAXRENDER_DILIGENT")
    fitting.write_folder_manifest(folder, tmp / "capture.json")
    obs = fitting.merge_capture(fitting.load_capture(tmp), progress=False)
    keep = np.zeros(obs.size, bool)
    keep[::CAT_STRIDE, ::CAT_STRIDE] = True
    obs = _float32(obs)
    return type(obs)(ratio=obs.ratio, weight=obs.weight, light_dirs=obs.light_dirs, view_dir=obs.view_dir,
                     n_valid=obs.n_valid, n_saturated=obs.n_saturated, n_dark=obs.n_dark,
                     mask=jnp.asarray(np.asarray(obs.mask, bool) & keep))


def _float32(obs):
    return type(obs)(ratio=jnp.asarray(obs.ratio, jnp.float32), weight=jnp.asarray(obs.weight, jnp.float32),
                     light_dirs=jnp.asarray(obs.light_dirs, jnp.float32),
                     view_dir=jnp.asarray(obs.view_dir, jnp.float32),
                     n_valid=obs.n_valid, n_saturated=obs.n_saturated, n_dark=obs.n_dark, mask=obs.mask)


def record(path: Path = GOLDEN) -> None:
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    jax.config.update("jax_numpy_dtype_promotion", "strict")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        captures = {"synth": synthetic_observations(), "cat": cat_observations(Path(tmp))}
        for name, obs in captures.items():
            out[f"{name}.mask"] = np.ones(obs.size, bool) if obs.mask is None else np.asarray(obs.mask, bool)
            for method in ("plain", "robust"):
                maps = fit_maps(obs, FitSettings(method=method, chunk=CHUNK), progress=False)
                for field in FIELDS:
                    out[f"{name}.{method}.{field}"] = np.asarray(getattr(maps, field))
    out["recorded_on"] = np.asarray(machine())
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    print(f"{path}: {len(out)} arrays, recorded on {out['recorded_on']}")


def machine() -> str:
    """What the last bits of XLA's CPU code depend on: the CPU model and its vector extensions, the
    jax and jaxlib versions, an instruction-set limit set in XLA_FLAGS."""
    model, flags = platform.processor() or platform.machine(), []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = sorted(f for f in value.split() if f.startswith(("avx", "sse", "fma", "asimd", "sve")))
    except OSError:
        pass
    isa = [f for f in os.environ.get("XLA_FLAGS", "").split() if "max_isa" in f]
    return f"{platform.machine()} {model} [{' '.join(flags + isa)}] jax {jax.__version__} jaxlib {jaxlib.__version__}"


if __name__ == "__main__":
    record(Path(sys.argv[1]) if len(sys.argv) > 1 else GOLDEN)
