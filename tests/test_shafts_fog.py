"""Fog with a density grid in every light-shaft method.

Independent references: Mitsuba 3's `gridvolume` (the grid's lookup, value by value), a float64
numpy brute force of the model written here from its definition in docs/fog.md (scipy's
`map_coordinates` for the trilinear grid, midpoint rules for every integral), float64 central
differences for the gradients, and the uniform-fog renderer (a grid of ones must reproduce it).
Every test uses one image size, one grid shape and one object list, so each method compiles once
for the module.
"""

import copy
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from jaxrender.camera import Camera
from jaxrender.geometry import Quads, Spheres
from jaxrender.lights import SpotLight
from jaxrender.shafts import (
    DensityGrid,
    Medium,
    RenderSettings,
    ShaftsScene,
    render_equiangular,
    render_planes,
    render_raymarch,
    segment_optical_depth,
)

_W, _H = 12, 8
_SHAPE = (3, 4, 5)  # (nz, ny, nx)
_ROUNDING = 1e-11  # float64: the same image by two code paths (uniform fog vs a grid of ones)
_SEGMENT_TOL = 1e-8  # exact piecewise Gauss vs a 2 x 10^5-point midpoint rule (error ~ (step)^2 x kinks)
_BRUTE_TOL = 2e-4  # ray march (160 samples in the cone) vs the float64 brute force (measured 2e-5): midpoint
                   # rules of both at the beam's and cone's kinks
_EQ_TOL = 0.03  # equiangular, 24 samples, 24-node volumes vs the ray march: a rough random grid and a sphere's shadow
_PLANES_TOL = 0.03  # sample planes 24 x 4 (g per pixel) vs the ray march, same scene
_F32_TOL = 3e-4  # float32 vs float64 of the equiangular method (volume tables and sums in float32)
_FD_RTOL = 1e-4  # float64 central differences, h = 1e-6 relative, smooth configuration


def _grid(values=None, box=((-2.0, -0.2, -2.5), (2.5, 3.2, 1.5))):
    if values is None:
        values = np.random.default_rng(7).uniform(0.3, 1.8, _SHAPE)
    return DensityGrid(values, *box)


def _scene(grid, *, light_map=None, sphere_center=(0.0, 1.2, 0.0), rho=1.0, kappa=0.25, K=0.008,
           eye=(0.3, 1.5, 6.0), target=(0.0, 1.0, 0.0), up=(0.0, 1.0, 0.0)):
    cam = Camera(eye, target, up, 40.0, width=_W, height=_H)
    light = SpotLight((0.2, 4.0, -0.3), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 24.0, 16.0, (40.0, 30.0, 20.0), light_map)
    spheres = Spheres([sphere_center], [0.45], [[0.8, 0.7, 0.6]])
    floor = Quads([[0.0, 0.0, 0.0]], [[3.0, 0.0, 0.0]], [[0.0, 0.0, -3.0]], [[0.5, 0.5, 0.5]])
    render = RenderSettings(shadow_map=64, s_min=jnp.asarray(0.5), s_max=jnp.asarray(10.0), t_max=jnp.asarray(12.0))
    return ShaftsScene(cam, Medium(rho, kappa, K, grid), [light], spheres, floor, render)


def _uniform(scene):
    return eqx.tree_at(lambda s: s.medium, scene, Medium(scene.medium.rho, scene.medium.kappa, scene.medium.K))


def _fog_part(out):
    image, (surface, fog) = out
    return image, (sum(fog) if isinstance(fog, list) else fog)


# one compiled function per method for the whole module (scenes differ in values only)
_EQ = jax.jit(lambda s: _fog_part(render_equiangular(s, samples=24, shadow_map=64, prune=False, return_parts=True)))
_PL = jax.jit(lambda s: _fog_part(render_planes(s, planes=24, subplanes=4, g_per_pixel=True, tables=False,
                                                prune=False, surface_shadows="rays", return_parts=True)))
_RM = jax.jit(lambda s: _fog_part(render_raymarch(s, samples=160, return_parts=True)))


def _rel(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


# -- the grid itself -------------------------------------------------------------------------------
def test_grid_lookup_matches_mitsuba_gridvolume():
    """Voxel centres, trilinear weights, clamping near the faces and the (z, y, x) layout: our
    lookup against Mitsuba 3's `gridvolume` (trilinear, clamp, to_world onto the box) at random
    points of the box, its faces included."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    grid = _grid()
    lo, hi = np.asarray(grid.box_min), np.asarray(grid.box_max)
    vol = mi.load_dict({"type": "gridvolume", "grid": mi.VolumeGrid(np.asarray(grid.values, np.float32)),
                        "to_world": mi.ScalarTransform4f().translate(lo.tolist()).scale((hi - lo).tolist()),
                        "filter_type": "trilinear", "wrap_mode": "clamp"})
    rng = np.random.default_rng(0)
    pts = lo + rng.uniform(0, 1, (200, 3)) * (hi - lo)
    pts[:6] = [lo, hi, [lo[0], hi[1], lo[2]], lo + 1e-9, hi - 1e-9, (lo + hi) / 2]
    it = mi.Interaction3f()
    theirs = []
    for p in pts:
        it.p = mi.ScalarPoint3f(*p)
        theirs.append(vol.eval_1(it))
    np.testing.assert_allclose(np.asarray(grid.at(pts)), theirs, rtol=1e-6, atol=1e-6)  # Mitsuba stores float32
    assert float(grid.at(jnp.asarray([hi + 1e-6]))[0]) == 0.0 and float(grid.at(jnp.asarray([lo - 1e-6]))[0]) == 0.0


_LOOKUP_FD_RTOL = 1e-6  # float64 central differences of a piecewise-trilinear lookup (h = 1e-6), away from kinks


def _central(f, x, h=1e-6):
    """Elementwise central differences of f (outputs independent per element of x)."""
    return (np.asarray(f(x + h)) - np.asarray(f(x - h))) / (2 * h)


def test_lookup_gradients_match_central_differences():
    """The lookups' own reverse passes (one scatter of all corners into the table, the fractions'
    slopes to the coordinates): the grid's d(P) by its values, box and the points' coordinates,
    and a depth volume's tau by its table and frustum coordinates, against float64 central
    differences at random points inside the box, in its clamped margin and outside it."""
    from jaxrender.shafts import DepthVolume

    grid = _grid()
    lo, hi = np.asarray(grid.box_min), np.asarray(grid.box_max)
    pts = lo - 0.1 * (hi - lo) + np.random.default_rng(4).uniform(0, 1.2, (300, 3)) * (hi - lo)
    w = np.random.default_rng(5).uniform(0.5, 1.5, 300)

    def loss(values, box_min, box_max, points):
        return jnp.sum(w * DensityGrid(values, box_min, box_max).at(points))

    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(grid.values, grid.box_min, grid.box_max, jnp.asarray(pts))
    args = [np.asarray(grid.values), lo, hi]
    for k in range(3):
        fd = np.zeros_like(args[k])
        for idx in np.ndindex(fd.shape):
            def at(v, k=k, idx=idx):
                moved = [a.copy() for a in args]
                moved[k][idx] = v
                return float(loss(*moved, pts))
            fd[idx] = (at(args[k][idx] + 1e-6) - at(args[k][idx] - 1e-6)) / 2e-6
        np.testing.assert_allclose(np.asarray(grads[k]), fd, rtol=_LOOKUP_FD_RTOL, atol=1e-9, err_msg=str(k))
    for axis in range(3):
        def at(c, axis=axis):
            moved = np.concatenate([pts[:, :axis], c[:, None], pts[:, axis + 1:]], 1)
            return w * np.asarray(grid.at(jnp.asarray(moved)))
        np.testing.assert_allclose(np.asarray(grads[3])[:, axis], _central(at, pts[:, axis]), rtol=_LOOKUP_FD_RTOL,
                                   atol=1e-9, err_msg=f"point axis {axis}")
    assert np.count_nonzero(np.asarray(grads[3])) > 300  # the points inside move the lookup

    rng = np.random.default_rng(6)
    table = rng.uniform(0.0, 2.0, (4, 5, 6))
    abs_ = [rng.uniform(-1.1, 1.1, 200), rng.uniform(-1.1, 1.1, 200), rng.uniform(0.5, 3.5, 200)]

    def tau(table, a, b, s):
        vol = DepthVolume(table=table, origin=jnp.zeros(3), rotation=jnp.eye(3), tan_x=jnp.asarray(0.5),
                          tan_y=jnp.asarray(0.4), s_lo=jnp.asarray(1.0), s_hi=jnp.asarray(3.0))
        return vol.lookup(a, b, s)

    g_table, *g_abs = jax.grad(lambda *x: jnp.sum(tau(*x)), argnums=(0, 1, 2, 3))(table, *abs_)
    fd = np.zeros_like(table)
    for idx in np.ndindex(table.shape):
        plus, minus = table.copy(), table.copy()
        plus[idx] += 1e-6
        minus[idx] -= 1e-6
        fd[idx] = float(jnp.sum(tau(plus, *abs_)) - jnp.sum(tau(minus, *abs_))) / 2e-6
    np.testing.assert_allclose(np.asarray(g_table), fd, rtol=_LOOKUP_FD_RTOL, atol=1e-9)
    for k in range(3):
        def at(c, k=k):
            return tau(table, *[c if j == k else abs_[j] for j in range(3)])
        np.testing.assert_allclose(np.asarray(g_abs[k]), _central(at, abs_[k]), rtol=_LOOKUP_FD_RTOL, atol=1e-9,
                                   err_msg=f"frustum coordinate {k}")


def _numpy_density(values, lo, hi, pts):
    """Trilinear at voxel centres, clamped, 0 outside: scipy's map_coordinates (order 1, nearest)."""
    n = np.array(values.shape[::-1], float)  # (nx, ny, nz)
    g = (pts - lo) / (hi - lo) * n - 0.5
    coords = np.stack([g[..., 2], g[..., 1], g[..., 0]]).reshape(3, -1)
    d = map_coordinates(values, coords, order=1, mode="nearest").reshape(pts.shape[:-1])
    inside = np.all((pts >= lo) & (pts <= hi), axis=-1)
    return np.where(inside, d, 0.0)


def test_segment_optical_depth_is_exact():
    grid = _grid()
    lo, hi, vals = np.asarray(grid.box_min), np.asarray(grid.box_max), np.asarray(grid.values)
    p0 = np.array([[-3.0, 0.1, -3.0], [0.2, 0.4, 0.3], [2.6, 3.3, 1.6], [-1.0, 1.0, -1.0]])
    p1 = np.array([[3.0, 2.9, 2.0], [1.3, 2.0, -1.9], [-2.1, -0.3, -2.6], [-1.0, 1.0, -1.0]])
    ours = np.asarray(segment_optical_depth(grid, p0, p1))
    lam = (np.arange(200_000) + 0.5) / 200_000
    for k in range(3):  # the midpoint rule inside the box only (its faces are jumps of d)
        d = p1[k] - p0[k]
        a = np.max(np.minimum((lo - p0[k]) / d, (hi - p0[k]) / d))
        b = np.min(np.maximum((lo - p0[k]) / d, (hi - p0[k]) / d))
        a, b = max(a, 0.0), min(b, 1.0)
        pts = p0[k] + (a + (b - a) * lam)[:, None] * d
        ref = _numpy_density(vals, lo, hi, pts).mean() * (b - a) * np.linalg.norm(d)
        assert abs(ours[k] - ref) <= _SEGMENT_TOL * max(ref, 1.0), (k, ours[k], ref)
    assert ours[3] == 0.0  # zero length


# -- a grid of ones is uniform fog ------------------------------------------------------------------
@pytest.mark.parametrize("method", ["equiangular", "planes", "raymarch"])
def test_grid_of_ones_is_uniform_fog(method):
    """A box holding the eye, the light and every object, filled with d = 1: every method renders
    today's uniform fog to float rounding (image and in-scattered part)."""
    fn = {"equiangular": _EQ, "planes": _PL, "raymarch": _RM}[method]
    lmap = np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    scene = _scene(_grid(np.ones(_SHAPE), ((-9.0, -3.0, -9.0), (9.0, 9.0, 9.0))), light_map=lmap)
    grid_img, grid_fog = fn(scene)
    uni_img, uni_fog = fn(_uniform(scene))
    assert float(jnp.max(uni_fog)) > 0
    np.testing.assert_allclose(np.asarray(grid_img), np.asarray(uni_img), rtol=_ROUNDING, atol=_ROUNDING)
    np.testing.assert_allclose(np.asarray(grid_fog), np.asarray(uni_fog), rtol=_ROUNDING, atol=_ROUNDING)


# -- against the brute force and the ray march ------------------------------------------------------
def _numpy_brute_force(scene_grid, *, steps=1000, light_steps=32):
    """In-scattered light per pixel of `_scene` with the sphere moved out of the way: eq. 2 with
    rho d(P) F exp(-rho kappa (tau_view + tau_light)) / s^2, a float64 midpoint rule along each view
    ray inside the box (up to the floor), tau_view by the same rule from the box's entry and
    tau_light by a midpoint rule along the light's path inside the box."""
    grid = scene_grid.medium.density
    lo, hi, vals = np.asarray(grid.box_min), np.asarray(grid.box_max), np.asarray(grid.values)
    eye, L = np.array([0.3, 1.5, 6.0]), np.array([0.2, 4.0, -0.3])
    axis = -L / np.linalg.norm(L)
    cut, beam = np.radians(24.0), np.radians(16.0)
    rho, kappa, K = 1.0, 0.25, 0.008
    dirs = np.asarray(scene_grid.camera.primary_rays(), np.float64)

    def box_span(o, d):
        with np.errstate(divide="ignore"):
            ta, tb = (lo - o) / d, (hi - o) / d
        return max(np.max(np.minimum(ta, tb)), 0.0), np.min(np.maximum(ta, tb))

    out = np.zeros(dirs.shape[:2] + (3,))
    for r in range(_H):
        for c in range(_W):
            d = dirs[r, c]
            a, b = box_span(eye, d)
            t_floor = -eye[1] / d[1] if d[1] < 0 else np.inf
            p_floor = eye + t_floor * d
            if np.isfinite(t_floor) and abs(p_floor[0]) <= 3 and abs(p_floor[2]) <= 3:
                b = min(b, t_floor)
            if b <= a:
                continue
            dt = (b - a) / steps
            t = a + (np.arange(steps) + 0.5) * dt
            P = eye + t[:, None] * d
            dens = _numpy_density(vals, lo, hi, P)
            tau_v = np.cumsum(dens) * dt - 0.5 * dens * dt
            w = P - L
            s = np.linalg.norm(w, axis=1)
            theta = np.arccos(np.clip(w @ axis / s, -1, 1))
            fall = np.where(theta <= beam, 1.0, np.clip((cut - theta) / (cut - beam), 0.0, 1.0))
            u = w / s[:, None]  # the light's path to each sample, clipped to the box
            with np.errstate(divide="ignore", invalid="ignore"):
                ta, tb = (lo - L) / u, (hi - L) / u
            la = np.maximum(np.max(np.minimum(ta, tb), axis=1), 0.0)
            lb = np.minimum(np.min(np.maximum(ta, tb), axis=1), s)
            span = np.maximum(lb - la, 0.0)
            along = la[:, None] + (np.arange(light_steps) + 0.5)[None, :] / light_steps * span[:, None]
            q = L + along[..., None] * u[:, None]
            tau_l = _numpy_density(vals, lo, hi, q).sum(axis=1) * span / light_steps
            F = K * (1 + 9 * ((1 + (w / s[:, None]) @ -d) / 2) ** 8)
            val = np.sum(fall * rho * dens * F * np.exp(-rho * kappa * (tau_v + tau_l)) / s**2) * dt
            out[r, c] = val * np.array([40.0, 30.0, 20.0])
    return out


@pytest.fixture(scope="module")
def open_scene():
    """The random grid, no occluder in the light (the sphere moved far away): the brute force's scene."""
    return _scene(_grid(), sphere_center=(30.0, 30.0, 30.0))


@pytest.fixture(scope="module")
def raymarch_open(open_scene):
    return _RM(open_scene)


def test_raymarch_matches_float64_brute_force(open_scene, raymarch_open):
    ref = _numpy_brute_force(open_scene)
    _, ours = raymarch_open
    assert np.count_nonzero(ref[..., 0] > 1e-4) >= 20
    assert _rel(ours, ref) < _BRUTE_TOL, _rel(ours, ref)


def test_equiangular_and_planes_agree_with_raymarch():
    """The random grid with the sphere's shadow shaft and a light map: the fast methods (24
    angle steps; 24 x 4 planes) against the ray march, and without the grid's optical-depth
    volumes the agreement would be far worse (the grid's variation matters)."""
    lmap = np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    scene = _scene(_grid(), light_map=lmap)
    _, ref = _RM(scene)
    _, eq = _EQ(scene)
    _, pl = _PL(scene)
    assert _rel(eq, ref) < _EQ_TOL, _rel(eq, ref)
    assert _rel(pl, ref) < _PLANES_TOL, _rel(pl, ref)
    _, ones = _EQ(eqx.tree_at(lambda s: s.medium.density.values, scene, jnp.ones(_SHAPE)))
    assert _rel(ones, ref) > 5 * _EQ_TOL  # the grid is far from uniform fog: the test has teeth


def test_float32_matches_float64():
    lmap = np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    _, f64 = _EQ(_scene(_grid(), light_map=lmap))
    with jax.enable_x64(False):
        scene32 = _scene(_grid(), light_map=lmap)
        _, f32 = jax.jit(lambda s: _fog_part(render_equiangular(s, samples=24, shadow_map=64, prune=False,
                                                                return_parts=True)))(scene32)
        assert f32.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(f32)))
    assert _rel(np.asarray(f32, np.float64), f64) < _F32_TOL


# -- gradients ---------------------------------------------------------------------------------------
def _params(scene):
    light = scene.lights[0]
    return dict(values=scene.medium.density.values, rho=scene.medium.rho, kappa=scene.medium.kappa,
                K=scene.medium.K, intensity=light.intensity, position=light.position)


def _with(scene, p):
    scene = eqx.tree_at(lambda s: (s.medium.density.values, s.medium.rho, s.medium.kappa, s.medium.K), scene,
                        (p["values"], p["rho"], p["kappa"], p["K"]))
    return eqx.tree_at(lambda s: (s.lights[0].intensity, s.lights[0].position), scene, (p["intensity"], p["position"]))


_LOSS_W = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (_H, _W, 3)))
_GRAD = jax.jit(jax.grad(lambda p, s, w: jnp.sum(w * _EQ(_with(s, p))[0])))


def test_gradients_match_central_differences():
    """Default method, image loss: d/d(every grid value, rho, kappa, K, intensity, light position)
    against float64 central differences. Smooth configuration (design.md): no occluder in the
    cone (the sphere moved away), no light map, beam width < cutoff."""
    scene = _scene(_grid(), sphere_center=(30.0, 30.0, 30.0))
    p0 = _params(scene)
    grad = _GRAD(p0, scene, _LOSS_W)
    w = np.asarray(_LOSS_W)

    def loss(p):
        return float(np.sum(w * np.asarray(_EQ(_with(scene, p))[0])))

    for name, base in p0.items():
        base = np.asarray(base, float)
        fd = np.zeros_like(base)
        for idx in np.ndindex(base.shape):
            h = 1e-6 * max(abs(base[idx]), 1.0)
            plus, minus = base.copy(), base.copy()
            plus[idx] += h
            minus[idx] -= h
            fd[idx] = (loss({**p0, name: jnp.asarray(plus)}) - loss({**p0, name: jnp.asarray(minus)})) / (2 * h)
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=_FD_RTOL, atol=1e-7 * np.abs(fd).max(),
                                   err_msg=name)
    assert np.count_nonzero(np.asarray(grad["values"])) >= 0.5 * np.prod(_SHAPE)  # the grid reaches the image


def test_no_nan_gradient_at_box_faces_and_zero_density():
    """The eye and the light exactly on the box's faces, a floor lying on the bottom face, half the
    grid zero and the rest of it where the box's faces cut the cone: every gradient is finite."""
    values = np.random.default_rng(3).uniform(0.0, 1.0, _SHAPE)
    values[:, :2, :] = 0.0
    scene = _scene(_grid(values, ((-2.0, 0.0, -2.5), (2.5, 4.0, 6.0))), eye=(0.3, 1.5, 6.0))
    p0 = _params(scene)
    for weights in (_LOSS_W, jnp.zeros((_H, _W, 3)).at[_H // 2, _W // 2].set(1.0)):
        grad = _GRAD(p0, scene, weights)
        for name, g in grad.items():
            assert np.all(np.isfinite(np.asarray(g))), name
    zero = eqx.tree_at(lambda s: s.medium.density.values, scene, jnp.zeros(_SHAPE))
    for name, g in _GRAD(_params(zero), zero, _LOSS_W).items():
        assert np.all(np.isfinite(np.asarray(g))), name


# -- the scene file ----------------------------------------------------------------------------------
def _scene_file(tmp_path, density) -> dict:
    d = json.loads((__import__("pathlib").Path(__file__).parents[1] / "examples/scenes/spot_sphere.json").read_text())
    d["camera"].update(width=16, height=12)
    d["medium"]["density"] = density
    return d


@pytest.mark.parametrize("case", ["negative", "nan", "rank", "missing", "empty box", "not npy", "unknown key"])
def test_bad_grid_is_one_line_exit_2(tmp_path, capsys, case):
    from jaxrender.app.cli.programs import jaxrender_main as main

    good = np.ones((2, 3, 4))
    arrays = {"negative": -good, "nan": np.full_like(good, np.nan), "rank": np.ones((3, 4))}
    if case in arrays:
        np.save(tmp_path / "grid.npy", arrays[case])
    elif case == "not npy":
        (tmp_path / "grid.npy").write_text("0 1 2")
    elif case != "missing":
        np.save(tmp_path / "grid.npy", good)
    density = {"grid": "grid.npy", "box_min": [-3, -1, -3], "box_max": [3, 4, 3]}
    if case == "empty box":
        density["box_max"] = [3, -1, 3]
    if case == "unknown key":
        density["gird"] = "grid.npy"
    (tmp_path / "s.json").write_text(json.dumps(_scene_file(tmp_path, density)))
    assert main(["shafts", str(tmp_path / "s.json"), "--out", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s.json" in err[0] and "medium.density" in err[0], err
    assert not (tmp_path / "o.png").exists()


def test_scene_file_grid_is_read_relative_to_the_file(tmp_path):
    from jaxrender.app.scenes import load_shafts_scene

    values = np.random.default_rng(0).uniform(0, 2, (2, 3, 4)).astype(np.float32)
    (tmp_path / "fog").mkdir()
    np.save(tmp_path / "fog" / "d.npy", values)
    d = _scene_file(tmp_path, {"grid": "fog/d.npy", "box_min": [-3, -1, -3], "box_max": [3, 4, 3]})
    (tmp_path / "s.json").write_text(json.dumps(d))
    scene = load_shafts_scene(tmp_path / "s.json")
    grid = scene.medium.density
    np.testing.assert_array_equal(np.asarray(grid.values), values.astype(np.float64))
    np.testing.assert_array_equal(np.asarray(grid.box_max), [3, 4, 3])
    plain = copy.deepcopy(d)
    del plain["medium"]["density"]
    (tmp_path / "p.json").write_text(json.dumps(plain))
    assert load_shafts_scene(tmp_path / "p.json").medium.density is None


# -- sample counts from an error target -------------------------------------------------------------------
_TARGET = 0.04
_TARGET_SLACK = 1.25  # the target's 2.5 % for a 2 % error: the fixed parts' error is not in the estimate


def test_target_error_chooses_counts_that_reach_it():
    """render(target_error=E): the counts chosen on the proxy (here the scene itself: it is small)
    keep the in-scattered light within 1.25 E of the ray march, and fewer samples would not do."""
    from jaxrender.shafts import choose_counts, render

    lmap = np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    scene = _scene(_grid(), light_map=lmap)
    _, ref = _RM(scene)
    _, (_, fog) = render(scene, target_error=_TARGET, shadow_map=64, return_parts=True)  # the default method
    assert _rel(fog[0], ref) <= _TARGET_SLACK * _TARGET, _rel(fog[0], ref)
    choice = choose_counts(scene, _TARGET, shadow_map=64)
    assert choice.reached and 2 <= choice.options["samples"] < 64
    assert [n for n, _ in choice.measured] == [8, 16, 24, 32, 48]
    assert choice.options["samples"] % 8 == 0  # counts between multiples of 8 are no cheaper
    errors = [e for _, e in choice.measured]
    assert errors[0] > errors[-1]  # the ladder's errors fall with the count


def test_cli_error_option(tmp_path, capsys):
    """`jaxrender shafts SCENE --error E` prints its choice and renders; bad uses are one line, exit 2."""
    from jaxrender.app.cli.programs import jaxrender_main as main
    from jaxrender.io import read_image

    np.save(tmp_path / "grid.npy", np.random.default_rng(1).uniform(0.5, 1.5, (2, 3, 4)))
    d = _scene_file(tmp_path, {"grid": "grid.npy", "box_min": [-3, -1, -3], "box_max": [3, 4, 3]})
    d["camera"].update(width=8, height=6)
    (tmp_path / "s.json").write_text(json.dumps(d))
    for bad in (["--error", "2"], ["--error", "0.02", "--samples", "8"]):
        assert main(["shafts", str(tmp_path / "s.json"), "--out", str(tmp_path / "x.exr"), *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--error" in err[0], err
    assert main(["shafts", str(tmp_path / "s.json"), "--out", str(tmp_path / "x.exr"), "--error", "0.05"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("error target 5 %: adaptive with samples "), line
    image = read_image(tmp_path / "x.exr")
    assert image.shape[:2] == (6, 8) and np.all(np.isfinite(image)) and image.max() > 0
