"""BVH motion capture: the reader (hierarchy, offsets, channel orders, frame time), its one-line
errors, the round trip through `write_bvh`, and the forward kinematics in JAX against an
independent numpy float64 evaluation (scipy's Euler angles, a recursive walk of the tree)."""

import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxrender.io import InputError, read_bvh, write_bvh
from sims import forward_kinematics, noh_dance, skeleton_from_bvh

MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"))

_FK_TOL_F64 = 1e-9    # m: the same products in another order (scale 0.01, bones <= 1 m, 6 levels deep)
_FK_TOL_F32 = 2e-5    # m: float32 rounding of angles (degrees -> radians) and of 6 matrix products

# A small file with every feature the reader must get right: two roots, an end site, a joint
# without channels, 6 channels on a child (its position channels replace its offset), a
# rotation-only joint in another order (X Y Z), a position channel alone (Z), blank lines.
SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
    JOINT Arm
    {
      OFFSET 5 0 1
      CHANNELS 3 Xrotation Yrotation Zrotation
      JOINT Fixed
      {
        OFFSET 0 0 7
        JOINT Slide
        {
          OFFSET 2 0 0
          CHANNELS 1 Zposition
          End Site
          {
            OFFSET 0 3 0
          }
        }
      }
    }
  }
}
ROOT Prop
{
  OFFSET 4 0 0
  CHANNELS 3 Yrotation Xrotation Zrotation
}
MOTION
Frames: 3
Frame Time: 0.05

0.5 90 -1 10 20 30 0 10 0 -40 15 60 25 -35 45 1.5 170 -80 5
0 95 0 0 0 0 0.5 9.5 0.2 0 0 0 0 0 0 0 0 0 0
-2 80 3 -170 89 -45 0 10 0 120 -60 5 -90 10 0 -3 45 45 180
"""


def reference_fk(bvh, frame: int, scale: float):
    """World positions and rotations by a recursive walk (numpy float64, scipy's intrinsic Euler
    angles: 'ZXY' uppercase = R = Rz Rx Ry, the BVH reading)."""
    cols = bvh.channel_columns()
    children = {}
    for j, p in enumerate(bvh.parents):
        children.setdefault(p, []).append(j)
    pos, rot = {}, {}

    def visit(j, parent_r, parent_t):
        values = bvh.motion[frame, list(cols[j])]
        t = np.array(bvh.offsets[j], np.float64)
        order, angles = "", []
        for name, v in zip(bvh.channels[j], values):
            if name.endswith("position"):
                t["XYZ".index(name[0])] = v
            else:
                order += name[0]
                angles.append(v)
        r = Rotation.from_euler(order, angles, degrees=True).as_matrix() if order else np.eye(3)
        rot[j] = parent_r @ r
        pos[j] = parent_t + parent_r @ (t * scale)
        for c in children.get(j, []):
            visit(c, rot[j], pos[j])

    for root in children[-1]:
        visit(root, np.eye(3), np.zeros(3))
    n = len(bvh.names)
    return np.stack([pos[j] for j in range(n)]), np.stack([rot[j] for j in range(n)])


@pytest.fixture
def small(tmp_path):
    path = tmp_path / "small.bvh"
    path.write_text(SMALL)
    return path


def test_reader_reads_hierarchy_offsets_channels_and_frame_time(small):
    bvh = read_bvh(small)
    assert bvh.names == ("Hips", "Spine", "Arm", "Fixed", "Slide", "Slide_end", "Prop")
    assert bvh.parents == (-1, 0, 1, 2, 3, 4, -1)
    assert bvh.end_site == (False,) * 5 + (True, False)
    assert bvh.channels[2] == ("Xrotation", "Yrotation", "Zrotation") and bvh.channels[3] == ()
    assert bvh.channels[4] == ("Zposition",) and bvh.channels[6] == ("Yrotation", "Xrotation", "Zrotation")
    np.testing.assert_array_equal(bvh.offsets[4], [2, 0, 0])
    np.testing.assert_array_equal(bvh.offsets[5], [0, 3, 0])
    assert bvh.frame_time == 0.05 and bvh.motion.shape == (3, 19)
    assert [list(c) for c in bvh.channel_columns()][4] == [15]


def test_round_trip_gives_the_same_file_content(small, tmp_path):
    bvh = read_bvh(small)
    again = read_bvh(write_bvh(tmp_path / "again.bvh", bvh))
    for field in ("names", "parents", "channels", "end_site", "frame_time"):
        assert getattr(again, field) == getattr(bvh, field), field
    np.testing.assert_array_equal(again.offsets, bvh.offsets)
    np.testing.assert_array_equal(again.motion, bvh.motion)    # 17 significant digits: exact


def test_forward_kinematics_matches_numpy_float64_and_float32(small):
    bvh = read_bvh(small)
    skeleton = skeleton_from_bvh(bvh)
    fk = jax.jit(lambda s, c: forward_kinematics(s, c, scale=0.01))
    pos, rot = fk(skeleton, jnp.asarray(bvh.motion))
    assert pos.dtype == jnp.float64
    s32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), skeleton)
    pos32, _ = fk(s32, jnp.asarray(bvh.motion, jnp.float32))
    assert pos32.dtype == jnp.float32
    for f in range(bvh.frames):
        ref_pos, ref_rot = reference_fk(bvh, f, 0.01)
        np.testing.assert_allclose(np.asarray(pos[f]), ref_pos, atol=_FK_TOL_F64)
        np.testing.assert_allclose(np.asarray(rot[f]), ref_rot, atol=_FK_TOL_F64)
        np.testing.assert_allclose(np.asarray(pos32[f], np.float64), ref_pos, atol=_FK_TOL_F32)
    # the 6-channel child reads its position channels instead of its offset: frame 1 moves
    # Spine by (0.5, 9.5, 0.2) cm from the (unrotated) Hips, not by offset + channels
    np.testing.assert_allclose(np.asarray(pos[1, 1] - pos[1, 0]), [0.005, 0.095, 0.002], atol=1e-12)


def test_forward_kinematics_of_a_captured_clip_matches_numpy():
    """Every frame of the captured bow (6 channels on every joint) against the numpy walk."""
    bvh = read_bvh(MOCAP / "bow_normal_001.bvh")
    assert all(len(c) == 6 for c, end in zip(bvh.channels, bvh.end_site) if not end)
    pos, _ = jax.jit(lambda s, c: forward_kinematics(s, c, scale=0.01))(skeleton_from_bvh(bvh), jnp.asarray(bvh.motion))
    for f in range(0, bvh.frames, 7):
        np.testing.assert_allclose(np.asarray(pos[f]), reference_fk(bvh, f, 0.01)[0], atol=_FK_TOL_F64)
    hips, head = bvh.index("Hips"), bvh.index("Head")
    assert 0.8 < float(pos[0, hips, 1]) < 1.0 and 1.3 < float(pos[0, head, 1]) < 1.6   # metres, standing


def test_built_in_noh_motion_round_trips_and_its_angles_give_its_pose(tmp_path):
    """The procedural dance is a BVH motion like any other: written and read back unchanged, and
    its forward kinematics agrees with the numpy walk."""
    bvh = noh_dance(duration=1.0)
    again = read_bvh(write_bvh(tmp_path / "noh.bvh", bvh))
    np.testing.assert_array_equal(again.motion, bvh.motion)
    pos, _ = jax.jit(lambda s, c: forward_kinematics(s, c, scale=0.01))(skeleton_from_bvh(again),
                                                                        jnp.asarray(again.motion))
    for f in (0, bvh.frames // 2, bvh.frames - 1):
        np.testing.assert_allclose(np.asarray(pos[f]), reference_fk(bvh, f, 0.01)[0], atol=_FK_TOL_F64)


@pytest.mark.parametrize("edit, line, needle", [
    (lambda s: s.replace("HIERARCHY", "HIERARCHIE"), 1, "expected HIERARCHY"),
    (lambda s: s.replace("OFFSET 5 0 1", "OFFSET 5 zero 1"), 12, "'zero' is not a number"),
    (lambda s: s.replace("CHANNELS 3 Xrotation", "CHANNELS 3 Wrotation"), 13, "unknown channel 'Wrotation'"),
    (lambda s: s.replace("Frames: 3", "Frames: three"), 36, "not a whole number"),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: -1"), 37, "must be 1e-06 to 3600 s"),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: 1e-300"), 37, "must be 1e-06 to 3600 s"),
    (lambda s: s.replace("OFFSET 5 0 1", "OFFSET 5 1e39 1"), 12, "beyond float32"),
    (lambda s: s.replace("0 95 0 0 0 0 0.5", "0 95 0 0 0 0 1e39"), 40, "beyond float32"),
    (lambda s: s.replace("0 95 0 0 0 0 0.5", "0 95 0 0 0 0.5"), 40, "expected 19 channel values, got 18"),
    (lambda s: s.replace("0 95 0 0 0 0 0.5", "0 95 0 0 x 0 0.5"), 40, "'x' is not a number"),
    (lambda s: s.replace("Frames: 3", "Frames: 4"), 41, "ends after 3 motion lines"),
    (lambda s: s.replace("  JOINT Spine", "  JOIN Spine"), 6, "expected JOINT, End Site"),
])
def test_malformed_file_names_the_file_and_the_line(tmp_path, edit, line, needle):
    path = tmp_path / "bad.bvh"
    path.write_text(edit(SMALL))
    with pytest.raises(InputError) as error:
        read_bvh(path)
    message = str(error.value)
    assert message.startswith(f"{path}: line {line}: ") and needle in message and "\n" not in message, message


def test_cli_exits_2_with_one_line_for_a_bad_motion_file(tmp_path, capsys):
    from jaxrender.app.cli.programs import jaxrender_main as main

    bad = tmp_path / "bad.bvh"
    bad.write_text(SMALL.replace("Frames: 3", "Frames: 4"))
    out = tmp_path / "out"
    assert main(["noh", "--out", str(out), "--motion", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.bvh: line 41" in err[0] and not out.exists()
    assert main(["noh", "--out", str(out), "--motion", str(tmp_path / "missing.bvh")]) == 2
    assert "missing.bvh: no such file" in capsys.readouterr().err


def test_euler_zxy_inverts_the_channel_rotation():
    from sims.skeleton import euler_zxy

    rng = np.random.default_rng(0)
    angles = np.stack([rng.uniform(-170, 170, 50), rng.uniform(-80, 80, 50), rng.uniform(-170, 170, 50)], -1)
    matrices = Rotation.from_euler("ZXY", angles, degrees=True).as_matrix()
    np.testing.assert_allclose(euler_zxy(matrices), angles, atol=1e-9)
    assert math.isclose(float(np.abs(matrices[0] @ matrices[0].T - np.eye(3)).max()), 0.0, abs_tol=1e-12)


def test_a_chain_of_any_depth_reads(tmp_path):
    """1000 joints, each the child of the one before: read without recursion, posed in float64."""
    n = 1000
    lines = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0", "CHANNELS 6 Xposition Yposition Zposition Zrotation "
             "Xrotation Yrotation"]
    for i in range(1, n):
        lines += [f"JOINT j{i}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    lines += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * n
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.1", " ".join(["0"] * (6 + 3 * (n - 1)))]
    path = tmp_path / "chain.bvh"
    path.write_text("\n".join(lines) + "\n")
    bvh = read_bvh(path)
    assert len(bvh.names) == n + 1 and bvh.parents[-1] == n - 1 and bvh.parents[5] == 4
