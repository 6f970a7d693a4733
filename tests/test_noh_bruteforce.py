"""The Noh performance checked independently, both dances simulated once for both checks: the
robe against the body as rendered, and the composed frame against its brute-force reference.

The robe: every robe triangle against the body's triangles (capsules and mask, as `jaxrender noh
--meshes` writes them), in float64, by `robe_contact.contact` (segment-triangle tests both ways and
the winding number of each closed body part around the robe's vertices): nothing of the
simulator's capsule projection is used. `COLLISION_FRAMES` frames spread over each dance (the
built-in dance in 4 s, 2 s of the captured dance where its arms cross the collar:
`noh_reference.motion_of`); the robe still moves. Every 0.1 s frame of the whole dances:
benchmarks/noh_collision.py (benchmarks/RESULTS.md, Noh).

The composed Takigi Noh frame against its float64 brute-force reference (tests/noh_reference.py:
every pixel by ray casting every triangle, exact visibility, the flames' light integrated over their
emitting quads, the floor's reflection traced), for the built-in dance with the sleeve raised before
the face and a captured dance before its hand goes up, the production frame in float64, and the
built-in one in float32 too (a child process without x64, from the same state).

What must match and what may differ (`noh_reference.may_differ`): the frame's soft shadows are PCSS
and single rays toward each flame's centre, not an area light; where a fire is seen in part, or at
a shadow's edge or a shadow terminator (within `RADIUS` pixels, if it gives more than `SHARE` of the
pixel's luminance), and within `GLOW` pixels of a flame's mirror image or a reflected edge (the
floor's gloss: a mip filter there, a cone of rays here), the two may differ; everywhere else they
must match. Tolerances from measurement at 120 x 80 (`python benchmarks/noh_reference.py`,
benchmarks/RESULTS.md, Noh): relative RMS where they must match 0.81-0.90 % in float64 and
0.82-0.91 % in float32 (the target: 2 %), where they may differ 11.8-12.4 %; the performer's
pixels are the same set. The float32 child renders the parent's scene rounded to float32
(`with_float_leaves`), whose values the float32 frame's reference shades.
"""

import jax
import numpy as np
import pytest
from noh_reference import (
    FRAMES,
    case_scene,
    float32_frames,
    may_differ,
    motion_of,
    production_frame,
    reference_inputs,
    relative_rms,
    render_reference,
    robe_states,
    small_scene,
)
from robe_contact import BodyShape, contact, meshes_at

SIZE = (120, 80)
SHADOW_RESOLUTION = 512
RADIUS, SHARE, GLOW = 1, 0.05, 4
MUST_MATCH_RMS = 0.02          # the target: relative RMS where the frame must match, float32 and float64
MAY_DIFFER_RMS = 0.20          # the penumbrae, shadow edges and reflected edges (measured 11.8-12.4 %)
MUST_MATCH_FRACTION = 0.3      # ... of the image at least: the test must look at much of it
# one frame of each motion: the built-in dance with the sleeve raised before the face, the captured
# dance before its hand goes up; float32 on the first (the child builds its own scene, and one proves
# the precision: benchmarks/noh_reference.py renders all of `FRAMES` in both)
TEST_FRAMES = {"built-in": (FRAMES["built-in"][1],), "captured": (FRAMES["captured"][0],)}
FLOAT32_FRAMES = {"built-in": TEST_FRAMES["built-in"]}
CASES = [(label, frame, "float64") for label, frames in TEST_FRAMES.items() for frame in frames] + [
    (label, frame, "float32") for label, frames in FLOAT32_FRAMES.items() for frame in frames]

COLLISION_FRAMES = 10
LARGEST_MOVE = 0.05  # m: the robe's largest vertex move between samples is at least this (measured: see print)
# robe triangles through the body, and robe vertices inside it, in any frame: none in the built-in
# dance (the target); in the captured stretch none (measured; 0-2 a frame before contacts were
# inelastic: the simulation is chaotic, another CPU's rounding moves the frame and the count), and
# over the whole captured dance up to 15 a frame: the target is missed there (benchmarks/RESULTS.md, Noh)
THROUGH = {"built-in": 0, "captured": 9}
INSIDE = {"built-in": 0, "captured": 3}


@pytest.fixture(scope="module")
def dances():
    """For each dance: its scene at the comparison's size and the robe's state at every 0.1 s
    frame of the whole dance ([f]: the state frame f starts from)."""
    out = {}
    with jax.numpy_rank_promotion("allow"):
        for label in TEST_FRAMES:
            scene = case_scene(label, *SIZE, **small_scene())
            out[label] = scene, robe_states(scene, round(motion_of(label)[1] / 0.1))
    return out


@pytest.mark.parametrize("label", ["built-in", "captured"])
def test_robe_triangles_stay_out_of_the_body(dances, label):
    scene, states = dances[label]
    stride = (len(states) - 1) // COLLISION_FRAMES
    with jax.numpy_rank_promotion("allow"):
        meshes = list(meshes_at(scene.performer, states[stride::stride]))
    shape, previous, counts, moved = None, None, [], 0.0
    for body, robe in meshes:
        assert robe.vertices.dtype == np.float64 and np.all(np.isfinite(robe.vertices))
        shape = BodyShape(body.vertices, body.triangles) if shape is None else shape.moved(body.vertices)
        c = contact(robe.vertices, robe.triangles, shape)
        counts.append((c.triangles, c.crossing_edges, c.inside_vertices, c.depth))
        if previous is not None:
            moved = max(moved, float(np.linalg.norm(robe.vertices - previous, axis=-1).max()))
        previous = robe.vertices
    print(label, "per frame (through, crossing edges, inside vertices, depth m):", counts, "largest move", moved)
    assert len(counts) == COLLISION_FRAMES
    assert shape.closed.sum() == 15 and len(shape.closed) == 16     # the capsules closed, the mask open
    assert max(c[0] for c in counts) <= THROUGH[label]
    assert max(c[2] for c in counts) <= INSIDE[label]
    assert moved > LARGEST_MOVE


@pytest.fixture(scope="module")
def compared(dances, tmp_path_factory):
    """For every case: the production frame (float64, and float32 for `FLOAT32_FRAMES`) and the
    reference of its state."""
    out, states, scenes = {}, {}, {}
    with jax.numpy_rank_promotion("allow"):
        for label, frames in TEST_FRAMES.items():
            scene, robe = dances[label]
            scenes[label] = scene
            for frame in frames:
                state = robe[frame]
                states.update({f"{label}_{frame}_{k}": np.asarray(getattr(state, k))
                               for k in ("x", "x_prev", "time")})
                image, new_state, counts = production_frame(scene, frame, state, shadow_resolution=SHADOW_RESOLUTION)
                ref = render_reference(scene, reference_inputs(scene, frame, new_state))
                out[(label, frame, "float64")] = image, ref, np.asarray(counts.performer_mask)
        spec = dict(width=SIZE[0], height=SIZE[1], shadow_resolution=SHADOW_RESOLUTION, cases=FLOAT32_FRAMES)
        for (label, frame), (image, fr, scene32) in float32_frames(spec, states, scenes,
                                                                    tmp_path_factory.mktemp("noh32")).items():
            out[(label, frame, "float32")] = image, render_reference(scene32, fr), None
    return out


@pytest.mark.parametrize("label, frame, dtype", CASES)
def test_noh_frame_matches_its_bruteforce_reference(compared, label, frame, dtype):
    image, ref, mask = compared[(label, frame, dtype)]
    assert image.shape == ref.image.shape == (SIZE[1], SIZE[0], 3) and np.all(np.isfinite(image))
    differ = may_differ(ref, radius=RADIUS, share=SHARE, glow=GLOW)
    must = ~differ
    must_rms, may_rms = relative_rms(image, ref.image, must), relative_rms(image, ref.image, differ)
    print(f"{label} frame {frame} {dtype}: must match {must.mean():.2f} of the image, relative RMS {must_rms:.4f}; "
          f"may differ {may_rms:.4f}; performer {relative_rms(image, ref.image, ref.performer):.4f}")
    assert must.mean() > MUST_MATCH_FRACTION and (must & ref.floor).sum() > 100
    assert ref.performer.sum() > 50                              # the performer is in the picture
    if mask is not None:                                         # the same performer pixels: no window cut a sleeve
        np.testing.assert_array_equal(mask, ref.performer)
    assert must_rms <= MUST_MATCH_RMS
    assert may_rms <= MAY_DIFFER_RMS
