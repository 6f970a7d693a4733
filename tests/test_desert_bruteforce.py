"""The composed desert frame against a float64 brute-force shading of its pixels from the same inputs.

The reference, written here from the definitions with numpy: each pixel's primary ray (the camera's
ray directions are the input) is marched in small steps against the triangulated dune surface
(diagonal (i, j)-(i+1, j+1), clamped to the grid) and bisected to the first hit; the point is shaded
there, not at texel centres: the dune normal bilinear in the normal map at the point, Lambert under
the sun's (atmosphere-attenuated) irradiance plus the sky term (0.5 + 0.5 n_z) E_sky, albedo / pi;
with dune shadows, a binary march toward the sun over the same surface. The renderer instead casts
coherent rays, shades texture-space tiles at texel centres (16 per quad here), looks them up
bilinearly through an atlas, and antialiases the shadow edge over a texel.

Not covered here (said so in README): the ripple normals, grain and ripple horizon shadows (tested
against their own references in test_desert_render.py / test_desert_shadows.py), the dust billboards
(dust off) and the aerial-perspective haze (haze pushed to 1e12 so that the fade is 1 - 1e-11).
"""

import numpy as np
import pytest
from test_float32_frames import desert_inputs

from jaxrender.app.scenes.desert import SAND_ALBEDO, desert_frame, desert_scene, sky_for_sun
from jaxrender.camera import Camera

# Hit pixels whose radiance is within PIXEL_RTOL of the brute-force shading. Measured on the full
# 120 x 80 frame: without shadows 96.9 % within 1 % (median relative difference 1.6e-5: the texel
# -centre shading interpolated bilinearly; the rest are pixels whose ray grazes a silhouette, where the
# coherent cast and the fine march can land on different dunes, and the clamp at tile borders);
# with dune shadows 95.2 % (the shadow edge is antialiased over a texel, the reference is binary).
PIXEL_RTOL = 0.01
AGREE_MIN = {False: 0.95, True: 0.93}
MEDIAN_RTOL = 1e-3
STRIDE = 3  # every third pixel in each direction: 1/9 of the frame keeps the numpy reference fast
MARCH_STEP = 0.005  # world units (dune quads are 1 wide); then 50 bisections


def triangle_height_np(z, x, y):
    ny, nx = z.shape
    gx, gy = np.clip(x, 0.0, nx - 1.0), np.clip(y, 0.0, ny - 1.0)
    i = np.clip(np.floor(gx).astype(int), 0, nx - 2)
    j = np.clip(np.floor(gy).astype(int), 0, ny - 2)
    fx, fy = gx - i, gy - j
    z00, z10, z01, z11 = z[j, i], z[j, i + 1], z[j + 1, i], z[j + 1, i + 1]
    below_diagonal = z00 + fx * (z10 - z00) + fy * (z11 - z10)  # triangle (00, 10, 11)
    above_diagonal = z00 + fy * (z01 - z00) + fx * (z11 - z01)  # triangle (00, 01, 11)
    return np.where(fx >= fy, below_diagonal, above_diagonal)


def _inside(z, p):
    ny, nx = z.shape
    return (p[..., 0] >= 0) & (p[..., 0] <= nx - 1) & (p[..., 1] >= 0) & (p[..., 1] <= ny - 1)


def first_hit(z, eye, dirs, *, t_max=60.0):
    """Distance to the first point below the surface along each ray (inf: a miss), bisected."""
    t_hit = np.full(dirs.shape[0], np.inf)
    steps = np.arange(MARCH_STEP, t_max, MARCH_STEP)
    for start in range(0, len(steps), 400):
        t = steps[start:start + 400]
        p = eye[None, None, :] + dirs[:, None, :] * t[None, :, None]
        below = _inside(z, p) & (p[..., 2] < triangle_height_np(z, p[..., 0], p[..., 1]))
        new = np.isinf(t_hit) & below.any(axis=1)
        t_hit[new] = t[np.argmax(below, axis=1)[new]]
    hit = np.isfinite(t_hit)
    lo, hi = np.where(hit, t_hit - MARCH_STEP, 0.0), np.where(hit, t_hit, 0.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        p = eye[None, :] + dirs * mid[:, None]
        under = p[:, 2] < triangle_height_np(z, p[:, 0], p[:, 1])
        hi, lo = np.where(under, mid, hi), np.where(under, lo, mid)
    return np.where(hit, hi, np.inf), hit


def sunlit(z, p, light, bias):
    """Binary: no surface point above the ray from p toward the light (the renderer's bias)."""
    lit = np.ones(p.shape[0], bool)
    top = z.max()
    for s in np.arange(MARCH_STEP, (top - p[:, 2].min()) / light[2] + 1.0, MARCH_STEP):
        q = p + s * light[None, :]
        blocked = _inside(z, q) & (q[:, 2] <= top) & (triangle_height_np(z, q[:, 0], q[:, 1]) - bias > q[:, 2])
        lit &= ~blocked
    return lit


def bilinear_nodes(grid, x, y):
    """Bilinear interpolation of values at integer nodes (x along columns), clamped."""
    h, w = grid.shape[:2]
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0, y0 = np.clip(np.floor(x).astype(int), 0, w - 2), np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = grid[y0, x0] * (1 - fx) + grid[y0, x0 + 1] * fx
    bottom = grid[y0 + 1, x0] * (1 - fx) + grid[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


@pytest.mark.parametrize("dune_shadows", [False, True])
def test_desert_frame_pixels_match_bruteforce_shading(dune_shadows):
    dunes, ripples, spec = desert_inputs()
    scene = desert_scene(dune_field=dunes, ripple_field=ripples, texels=spec["texels"], seed=1)
    camera = Camera(*spec["camera"], width=spec["width"], height=spec["height"])
    elevation, azimuth = spec["frame"]["sun_elevation"], spec["frame"]["sun_azimuth"]
    image = np.asarray(desert_frame(scene, camera, sun_elevation=elevation, sun_azimuth=azimuth, ripples=False,
                                    ripple_shadows=False, dust=False, lod=False, dune_shadows=dune_shadows,
                                    haze=1e12))
    assert image.dtype == np.float64
    sun, _, sky_irradiance = sky_for_sun(elevation, azimuth)  # the inputs the frame is lit by
    z, normals = np.asarray(scene.maps.z), np.asarray(scene.maps.normals)
    assert scene.maps.spacing == 1.0 and normals.shape[:2] == z.shape
    dirs = np.asarray(camera.primary_rays())[::STRIDE, ::STRIDE].reshape(-1, 3)
    eye = np.asarray(camera.eye)
    t, hit = first_hit(z, eye, dirs)
    assert 0.3 < hit.mean() < 0.95  # the frame shows dunes and sky
    p = eye[None, :] + dirs[hit] * t[hit, None]
    n = bilinear_nodes(normals, p[:, 0], p[:, 1])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    light = np.asarray(sun.direction)
    lit = sunlit(z, p, light, 1e-3 * scene.maps.spacing) if dune_shadows else np.ones(len(p), bool)
    if dune_shadows:
        assert 0.2 < 1 - lit.mean() < 0.8  # shadows are in the picture
    direct = (np.maximum(n @ light, 0.0) * lit)[:, None] * np.asarray(sun.irradiance)[None, :]
    ambient = (0.5 + 0.5 * n[:, 2:3]) * np.asarray(sky_irradiance)[None, :]
    reference = np.asarray(SAND_ALBEDO)[None, :] / np.pi * (direct + ambient)
    ours = image[::STRIDE, ::STRIDE].reshape(-1, 3)[hit]
    rel = np.abs(ours - reference).max(axis=1) / reference.max(axis=1)
    assert np.median(rel) < MEDIAN_RTOL, np.median(rel)
    assert np.mean(rel < PIXEL_RTOL) >= AGREE_MIN[dune_shadows], np.mean(rel < PIXEL_RTOL)
