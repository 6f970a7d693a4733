"""Generates examples/real_capture.ipynb (run: python examples/_make_real_capture_notebook.py)."""

from pathlib import Path

import nbformat as nbf
from _notebook import write_notebook

cells = [
    nbf.v4.new_markdown_cell("""# Fitting a real capture: a DiLiGenT object

A measured multi-light capture, not a render: the *cat* of the DiLiGenT photometric-stereo
benchmark (Shi et al., CVPR 2016 / TPAMI 2019; research use), 96 calibrated LEDs, 16-bit linear
photographs, laser-scanned ground-truth normals. We write a capture manifest that refers to the
images in place, merge it, fit it with every 6th light held out, and compare: the fitted normals
with the ground truth, and each held-out photograph with its prediction, beside the least-squares
Lambertian fit of the same lights (the benchmark's baseline).

For speed the notebook keeps **every 3rd row and column** of the object (about 1/9 of its
texels); `benchmarks/real_captures.py` fits whole objects through the command line.
The data are read from `$JAXRENDER_DILIGENT`, else `../shared/data/diligent` beside the checkout."""),
    nbf.v4.new_code_cell("""import json, os, tempfile, time
from pathlib import Path
import numpy as np
import jax, jax.numpy as jnp
import matplotlib.pyplot as plt
import fitting
from fitting.evaluate import (angular_error_deg, heldout_split, lambertian_fit, read_normal_map, relative_rms,
                              select_lights)
from jaxrender.io import linear_to_srgb

root = Path(os.environ.get("JAXRENDER_DILIGENT", Path.cwd().resolve().parent.parent / "shared" / "data" / "diligent"))
folder = root / "catPNG"
assert folder.is_dir(), f"DiLiGenT data not found at {root}: set JAXRENDER_DILIGENT"
work = Path(tempfile.mkdtemp())
fitting.write_folder_manifest(folder, work / "capture.json")   # = `fitting manifest catPNG --out .../capture.json`
full = fitting.merge_capture(fitting.load_capture(work), progress=False)   # observation = code / 65535 / intensity

STRIDE = 3   # every 3rd row and column: a smaller capture, same lights
every = lambda x: None if x is None else x[::STRIDE, ::STRIDE]
obs = fitting.Observations(ratio=every(full.ratio), weight=every(full.weight), light_dirs=full.light_dirs,
                           view_dir=full.view_dir, n_valid=every(full.n_valid), n_saturated=every(full.n_saturated),
                           n_dark=every(full.n_dark), mask=every(full.mask))
mask = np.asarray(obs.mask, bool)
truth = every(read_normal_map(folder / "Normal_gt.mat"))
print(f"{obs.size[0]} x {obs.size[1]} texels, {int(mask.sum())} in the mask, {obs.n_lights} lights")"""),
    nbf.v4.new_markdown_cell("""## Fit without every 6th light
`fit_maps` uses the default, robust method: a material table estimated from a sample of texels
gives each texel's lobe a prior, shadows and highlights the model cannot explain are down-weighted,
and the slopes are refitted on every observation (docs/fitting.md, "Real captures")."""),
    nbf.v4.new_code_cell("""fitted_lights, held = heldout_split(obs.n_lights, 6)
train, test = select_lights(obs, fitted_lights), select_lights(obs, held)
t0 = time.perf_counter()
maps = fitting.fit_maps(train, progress=False)
seconds = time.perf_counter() - t0
lambert = lambertian_fit(train)
print(f"fit of {len(fitted_lights)} lights (compilation included): {seconds:.1f} s")"""),
    nbf.v4.new_markdown_cell("## Normals against the laser scan"),
    nbf.v4.new_code_cell("""err, err_map = angular_error_deg(maps.normal, truth, mask)
err_l, err_map_l = angular_error_deg(np.asarray(lambert.normal), truth, mask)
show = lambda n: np.where(mask[..., None], 0.5 * (np.asarray(n) + 1), 1.0)
fig, axes = plt.subplots(1, 4, figsize=(13, 3.6))
for ax, img, title in zip(axes[:3], (truth, maps.normal, lambert.normal),
                          ("ground truth", f"fit: {err:.2f} deg", f"Lambertian: {err_l:.2f} deg")):
    ax.imshow(show(img), interpolation="nearest"); ax.set_title(title); ax.axis("off")
im = axes[3].imshow(err_map, vmin=0, vmax=30, cmap="magma", interpolation="nearest")
axes[3].set_title("fit's angular error (deg)"); axes[3].axis("off"); fig.colorbar(im, ax=axes[3], shrink=0.8)
fig.tight_layout()"""),
    nbf.v4.new_markdown_cell("""## A held-out photograph and its predictions
The light below was not in the fit. The BTF is rendered under it (`fitting.relight`), as is the
Lambertian fit; the error is the relative RMS over the valid mask pixels of every held-out light."""),
    nbf.v4.new_code_cell("""texels = jax.tree.map(jnp.asarray, maps).texel()
predicted = jnp.stack([fitting.relight(texels, d, obs.view_dir) for d in np.asarray(test.light_dirs)], axis=2)
predicted_l = lambert.predict(test.light_dirs)
heldout, heldout_l = relative_rms(predicted, test), relative_rms(predicted_l, test)
k = 4   # one of the held-out lights
photo = np.asarray(test.ratio[:, :, k])
scale = 1.0 / np.percentile(photo[mask], 99)
view = lambda x: np.asarray(linear_to_srgb(np.clip(np.asarray(x) * scale, 0, 1))) * mask[..., None]
fig, axes = plt.subplots(1, 3, figsize=(10, 3.6))
for ax, img, title in zip(axes, (photo, predicted[:, :, k], predicted_l[:, :, k]),
                          (f"photograph (light {held[k] + 1}, held out)", f"fit: {100 * heldout:.1f} %",
                           f"Lambertian: {100 * heldout_l:.1f} %")):
    ax.imshow(view(img), interpolation="nearest"); ax.set_title(title); ax.axis("off")
fig.tight_layout()
summary = {"texels": int(mask.sum()), "normals_deg": err, "lambertian_normals_deg": err_l, "heldout": heldout,
           "heldout_lambertian": heldout_l, "fit_seconds": seconds}
print(json.dumps(summary))"""),
]
write_notebook(cells, Path(__file__).with_name("real_capture.ipynb"))
