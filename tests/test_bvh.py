"""BVH reader/writer: round trip, channel conventions, malformed-file errors."""

import jax
import numpy as np
import pytest

import bodyprior as bp

ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 1.5 0.1
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 2 0
      CHANNELS 3 Yrotation Xrotation Zrotation
      End Site
      {
        OFFSET 0 0.5 0
      }
    }
  }
  JOINT Leg
  {
    OFFSET 1 -1 0
    CHANNELS 2 Xrotation Zrotation
    End Site
    {
      OFFSET 0 -3 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
1 2 3 10 20 30 0 0 0 5 6 7 8 9
-1 -2 -3 -10 -20 -30 1 2 3 -5 -6 -7 -8 -9
"""


def _write(tmp_path, text, name="x.bvh"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _random_bvh(rng, n_frames=5):
    """A random 6-joint skeleton with random channel orders (and position channels on a child)."""
    parents = (-1, 0, 1, 2, 1, 0)
    channels = [("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")]
    for j in range(1, len(parents)):
        axes = [f"{a}rotation" for a in ORDERS[j % 6]]
        channels.append(tuple(axes))
    channels[3] = ("Yrotation", "Xposition", "Zrotation", "Yposition", "Zposition", "Xrotation")
    C = sum(len(c) for c in channels)
    end = np.full((len(parents), 3), np.nan)
    end[3] = rng.normal(size=3)
    end[5] = rng.normal(size=3)
    return bp.Bvh(
        joint_names=("Root", "A", "B", "C", "D", "E"),
        parents=parents,
        offsets=rng.normal(size=(len(parents), 3)),
        channels=tuple(channels),
        end_offsets=end,
        frame_time=1 / 120,
        motion=rng.uniform(-170, 170, size=(n_frames, C)),
    )


def test_round_trip_exact(tmp_path):
    b = _random_bvh(np.random.default_rng(0))
    bp.write_bvh(tmp_path / "a.bvh", b, precision=17)
    c = bp.read_bvh(tmp_path / "a.bvh")
    assert c.joint_names == b.joint_names and c.parents == b.parents
    assert c.channels == b.channels and c.frame_time == b.frame_time
    np.testing.assert_array_equal(c.offsets, b.offsets)
    np.testing.assert_array_equal(c.motion, b.motion)
    np.testing.assert_array_equal(c.end_offsets, b.end_offsets)
    # default precision: 10 significant digits
    bp.write_bvh(tmp_path / "b.bvh", b)
    np.testing.assert_allclose(bp.read_bvh(tmp_path / "b.bvh").motion, b.motion, rtol=1e-9)


def test_small_file_structure(tmp_path):
    b = bp.read_bvh(_write(tmp_path, SMALL))
    assert b.joint_names == ("Hips", "Spine", "Head", "Leg")
    assert b.parents == (-1, 0, 1, 0)
    assert b.channels[3] == ("Xrotation", "Zrotation")
    assert b.n_frames == 2 and b.frame_time == pytest.approx(0.0333333)
    np.testing.assert_array_equal(b.end_offsets[2], [0, 0.5, 0])
    assert np.all(np.isnan(b.end_offsets[[0, 1]]))
    np.testing.assert_allclose(b.rest_positions()[2], [0, 3.5, 0.1])
    np.testing.assert_allclose(b.root_positions(), [[1, 2, 3], [-1, -2, -3]])
    assert bp.read_bvh(_write(tmp_path, SMALL), frame_time=1 / 60).frame_time == 1 / 60


@pytest.mark.parametrize("order", ORDERS)
def test_rotation_channels_match_euler_to_matrix(tmp_path, order):
    """`CHANNELS 3 Zrotation Yrotation Xrotation` means Rz @ Ry @ Rx (bvh11's convention)."""
    rng = np.random.default_rng(1)
    angles = rng.uniform(-170, 170, size=(4, 3))
    chans = " ".join(f"{a}rotation" for a in order)
    text = (
        f"HIERARCHY\nROOT R\n{{\nOFFSET 0 0 0\nCHANNELS 3 {chans}\n}}\nMOTION\nFrames: 4\n"
        "Frame Time: 0.01\n" + "\n".join(" ".join(map(repr, a.tolist())) for a in angles) + "\n"
    )
    R = bp.read_bvh(_write(tmp_path, text)).local_rotations()[:, 0]
    want = jax.vmap(lambda a: bp.euler_to_matrix(a, order))(np.deg2rad(angles))
    np.testing.assert_allclose(R, want, atol=1e-12)
    # the product of elementary rotations in written order, independently
    for k, a in enumerate(np.deg2rad(angles)):
        M = np.eye(3)
        for axis, t in zip(order, a):
            M = M @ _elementary(axis, t)
        np.testing.assert_allclose(R[k], M, atol=1e-12)


def _elementary(axis, t):
    c, s = np.cos(t), np.sin(t)
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def test_two_channel_joint_and_interleaved_positions(tmp_path):
    b = bp.read_bvh(_write(tmp_path, SMALL))
    x, z = np.deg2rad(b.motion[:, 12]), np.deg2rad(b.motion[:, 13])
    R = b.local_rotations()[:, 3]
    for k in range(2):
        np.testing.assert_allclose(
            R[k], _elementary("X", x[k]) @ _elementary("Z", z[k]), atol=1e-12
        )
    # positions written after a rotation are expressed in the rotated frame
    rb = _random_bvh(np.random.default_rng(2), n_frames=3)
    m, s = rb.motion, rb.channel_start[3]
    t = rb.local_translations()[:, 3]
    for k in range(3):
        Ry = _elementary("Y", np.deg2rad(m[k, s]))
        Rz = Ry @ _elementary("Z", np.deg2rad(m[k, s + 2]))
        want = (
            rb.offsets[3] + Ry[:, 0] * m[k, s + 1] + Rz[:, 1] * m[k, s + 3] + Rz[:, 2] * m[k, s + 4]
        )
        np.testing.assert_allclose(t[k], want, atol=1e-12)
    # frame subsets
    np.testing.assert_array_equal(rb.local_rotations([2, 0]), rb.local_rotations()[[2, 0]])


def _broken(text, old, new):
    assert old in text
    return text.replace(old, new, 1)


MOTION_LINE = SMALL.splitlines().index("MOTION") + 1  # 1-based line of "MOTION"


@pytest.mark.parametrize(
    "text, pattern",
    [
        # truncated motion: 'Frames: 2' but only one frame line
        (SMALL.rsplit("-1 -2", 1)[0], rf"x\.bvh:{MOTION_LINE + 3}: truncated motion: 'Frames: 2'"),
        (SMALL + "1 2 3 4 5 6 7 8 9 10 11 12 13 14\n", r"x\.bvh:\d+: extra motion lines"),
        # wrong channel count in a frame
        (
            _broken(SMALL, "-8 -9\n", "-8\n"),
            rf"x\.bvh:{MOTION_LINE + 4}: wrong channel count: frame has 13 values.*14 channels",
        ),
        (_broken(SMALL, "5 6 7", "5 6.x 7"), rf"x\.bvh:{MOTION_LINE + 3}: bad number '6\.x'"),
        (_broken(SMALL, "5 6 7", "5 nan 7"), rf"x\.bvh:{MOTION_LINE + 3}: non-finite value"),
        # CHANNELS count larger than the names given
        (
            _broken(SMALL, "CHANNELS 2 Xrotation", "CHANNELS 3 Xrotation"),
            r"x\.bvh:\d+: joint 'Leg' declares 3 channels but 'End' is not a channel name",
        ),
        (_broken(SMALL, "Zrotation Xrotation Yrotation", "Zrotation Xrot Yrotation"), r"'Xrot'"),
        # missing braces
        (
            _broken(SMALL, "  JOINT Leg\n  {", "  JOINT Leg\n"),
            r"x\.bvh:\d+: expected '\{', got 'OFFSET'",
        ),
        (
            SMALL.replace("}\nMOTION", "MOTION"),
            r"x\.bvh:\d+: unexpected end of HIERARCHY before MOTION.*closing 'Hips'",
        ),
        (
            _broken(SMALL, "OFFSET 0 1.5 0.1", "OFFSET 0 1.5"),
            r"x\.bvh:9: expected a number \(OFFSET z of Spine\), got 'CHANNELS'",
        ),
        ("HIERARCHY\nMOTION\nFrames: 0\nFrame Time: 0.1\n", r"x\.bvh:\d+: no joints"),
        ("", r"x\.bvh:1: file must start with HIERARCHY"),
        (SMALL.split("MOTION")[0], r"x\.bvh:\d+: missing MOTION block"),
        (_broken(SMALL, "Frames: 2", "Frames: two"), r"frame count must be a non-negative integer"),
        (_broken(SMALL, "Frame Time: 0.0333333", "Frame Time: -1"), r"frame time must be positive"),
        (_broken(SMALL, "JOINT Head", "JOINT Spine"), r"duplicate joint name 'Spine'"),
        (SMALL.replace("MOTION", "ROOT B\n{\nOFFSET 0 0 0\n}\nMOTION"), r"only one ROOT"),
    ],
)
def test_malformed_files_raise_with_file_and_line(tmp_path, text, pattern):
    with pytest.raises(ValueError, match=pattern):
        bp.read_bvh(_write(tmp_path, text))


@pytest.mark.bad_input
def test_container_validation_and_writer_args(tmp_path):
    b = bp.read_bvh(_write(tmp_path, SMALL))
    with pytest.raises(ValueError, match=r"depth-first order"):
        bp.Bvh(("a", "b", "c", "d"), (-1, 0, 0, 1), np.zeros((4, 3)), ((),) * 4,
               np.full((4, 3), np.nan), 0.1, np.zeros((1, 0)))  # fmt: skip
    with pytest.raises(ValueError, match=r"`motion` must have shape \(F, 14\)"):
        bp.Bvh(b.joint_names, b.parents, b.offsets, b.channels, b.end_offsets, 0.1, b.motion[:, :3])
    with pytest.raises(ValueError, match="No joint named 'Arm'"):
        b.joint_index("Arm")
    with pytest.raises(ValueError, match="`precision`"):
        bp.write_bvh(tmp_path / "o.bvh", b, precision=0)
    with pytest.raises(ValueError, match="`bvh` must be a bodyprior.Bvh"):
        bp.write_bvh(tmp_path / "o.bvh", "nope")
    with pytest.raises(ValueError, match="`frame_time`"):
        bp.read_bvh(tmp_path / "x.bvh", frame_time=0.0)
