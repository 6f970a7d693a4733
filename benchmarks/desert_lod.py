"""Paper 001 section 4: LOD vs no LOD (mean |difference| of the two images, paper 3.92 / 255) and
the time of bump mapping without culling, with culling, with culling + LOD (paper 15 s -> 9.7 s
-> 1.5 s on a Pentium III; shadows not included).

"Bump mapping" here is the texture-space shading of the dune quads (`jaxrender.terrain.shade_quads`:
ripple normal tilted into the dune frame, grain, Lambert + sky ambient), timed apart from the ray
cast to the screen; the full frame (shading + ray cast + sky) is timed too.

    python benchmarks/desert_lod.py [--quick]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _results import cpu_description, write_results  # (benchmarks/ is on sys.path when run as a script)
from _timing import timed

from jaxrender.app.scenes import desert as D
from jaxrender.terrain import plan_quads, quad_capacities, shade_quads

FIG = Path(__file__).parent / "figures"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="120x80, 8x8 dunes, 8 texels per quad, 1 repeat, the LOD frame only")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.quick:
        w, h, size = 120, 80, dict(dune_size=8, ripple_size=8, texels=8)
        args.repeats = 1
    else:
        w, h, size = 720, 480, dict(dune_size=64, ripple_size=64, texels=64)
    print(f"# desert LOD, {w}x{h}; {cpu_description()}, load average {os.getloadavg()[0]:.1f} at start", flush=True)
    scene = D.desert_scene(**size)
    camera = D.default_camera(scene, width=w, height=h)
    elevation, azimuth = 22.0, 200.0
    sun, env, sky_irr = D.sky_for_sun(elevation, azimuth)
    albedo = jnp.asarray(D.SAND_ALBEDO, scene.maps.z.dtype)
    rows = []
    images = {}
    configs = [("no culling, no LOD", False, False), ("culling", False, True), ("culling + LOD", True, True)]
    for name, lod, culling in configs[2:] if args.quick else configs:  # quick: each configuration is 2 compiles
        visible, level = plan_quads(scene.maps, camera, lod=lod, culling=culling)
        caps = quad_capacities(visible, level, scene.maps.levels)
        shade = jax.jit(lambda v, l, caps=caps: shade_quads(scene.maps, v, l, sun, albedo, sky_irr, capacities=caps,
                                                           dune_shadows=False, ripple_shadows=False)[0])
        c_shade, t_shade = timed(lambda: shade(visible, level), args.repeats)
        kw = dict(sun_elevation=elevation, sun_azimuth=azimuth, lod=lod, culling=culling, dune_shadows=False,
                  ripple_shadows=False, dust=False)
        c_frame, t_frame = timed(lambda: D.desert_frame(scene, camera, **kw), args.repeats)
        images[name] = D.to_display(D.desert_frame(scene, camera, **kw))
        texels = sum(c * (scene.maps.texels // 2**l) ** 2 for l, c in enumerate(caps))
        rows.append((name, caps, texels, c_shade, t_shade, t_frame))
        print(f"{name}: capacities {caps}, texels {texels}, shading {t_shade:.3f} s, frame {t_frame:.3f} s", flush=True)
    lod_img = images["culling + LOD"]
    ref = images.get("no culling, no LOD", lod_img)  # (--quick renders only the LOD frame: the differences are 0)
    diff = np.abs(lod_img - ref) * 255
    same_cull = float(np.max(np.abs(images.get("culling", ref) - ref)) * 255)
    print()
    print(f"{w}x{h}, {size['dune_size']}x{size['dune_size']} dune quads, "
          f"ripple maps up to {size['texels']}^2 per quad, levels {[size['texels'] // 2**l for l in range(4)]}")
    print("| configuration | quads per level (capacity) | texels shaded | bump mapping (s) | frame (s) "
          "| bump-mapping speed-up |")
    print("|---|---|---|---|---|---|")
    base = rows[0][4]
    for name, caps, texels, c_shade, t_shade, t_frame in rows:
        print(f"| {name} | {caps} | {texels:,} | {t_shade:.3f} | {t_frame:.3f} | {base / t_shade:.1f}x |")
    print()
    print(f"mean |LOD - no LOD| over the image: {diff.mean():.2f} / 255 (paper: 3.92 / 255); "
          f"max |culling - no culling|: {same_cull:.4f} / 255")
    speed = {name: (t_shade, t_frame) for name, _, _, _, t_shade, t_frame in rows}
    timing = "" if args.quick else (
        "; bump mapping " + " / ".join(f"{speed[n][0]:.3f}" for n, _, _ in configs) + " s without culling / with "
        f"culling / culling + LOD (paper 15 / 9.7 / 1.5 s), wall at load {os.getloadavg()[0]:.1f}")
    write_results("desert_lod", [dict(
        area="desert", target="LOD image within 3.92/255 of full resolution",
        measured=f"mean |LOD - no LOD| {diff.mean():.2f}/255 over the {w}x{h} sRGB display image (paper 3.92/255); "
                 f"culling alone changes it by at most {same_cull:.3f}/255" + timing,
        status="met" if diff.mean() <= 3.92 else "missed",
        notes="sun 22 deg, no shadows, no dust, as the paper's figs. 12-13; figure benchmarks/figures/desert_lod.png",
        figures={"mean_abs_diff_255": float(diff.mean()), "max_culling_diff_255": same_cull,
                 **{f"{n}: shading_s, frame_s": list(speed[n]) for n in speed}})],
        quick=args.quick)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 3.6))
    ax[0].imshow(ref)
    ax[0].set_title("no culling, no LOD")
    ax[1].imshow(lod_img)
    ax[1].set_title("culling + LOD")
    im = ax[2].imshow(diff.mean(-1), cmap="magma", vmin=0, vmax=32)
    ax[2].set_title(f"|difference| (mean {diff.mean():.2f}/255)")
    fig.colorbar(im, ax=ax[2])
    for a in ax:
        a.axis("off")
    FIG.mkdir(exist_ok=True)
    fig.savefig(FIG / ("desert_lod_quick.png" if args.quick else "desert_lod.png"), dpi=80, bbox_inches="tight")


if __name__ == "__main__":
    main()
