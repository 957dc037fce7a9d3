"""Mocap retargeting onto the cmu_mb rig, pose sets, clip splits, pose pictures."""

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import (
    EULER_ORDER,
    POSE_JOINTS,
    PoseSet,
    find_mocap_dir,
    load_mocap,
    pose_euler,
    render_poses,
    rig_pose,
    split_by_clip,
)
from bodyprior import _mocap as M


def _mocap_dir() -> Path | None:
    # $BODYPRIOR_MOCAP_DIR, else ../shared/data/mocap next to the checkout (CI and this machine)
    found = find_mocap_dir()
    repo_rel = Path(__file__).resolve().parents[2] / "shared/data/mocap"
    if found is None and "BODYPRIOR_MOCAP_DIR" not in os.environ and repo_rel.is_dir():
        return repo_rel
    return found


MOCAP = _mocap_dir()
needs_data = pytest.mark.skipif(MOCAP is None, reason="shared mocap data not found")


@pytest.fixture(scope="module")
def body():
    return bp.load_default_body("cmu_mb")


# --------------------------------------------------------------------------------------------------
# synthetic skeletons built from the rig, with a different rest posture


def _rot(rng, max_deg):
    """Random rotation by up to `max_deg` (Rodrigues, in NumPy)."""
    k = rng.normal(size=3)
    k /= np.linalg.norm(k)
    t = np.deg2rad(rng.uniform(0, max_deg))
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _skeleton(spec, rng, n_frames, perturb_deg=35.0, motion_deg=50.0):
    """A Bvh from `spec` = [(name, parent, bodyprior position, end position or None)].

    Bone directions are rotated by up to `perturb_deg` (so the rest posture differs from the rig's)
    and lengths scaled; channels get random orders (per joint); motion is random.
    """
    names = [s[0] for s in spec]
    parents = [-1 if s[1] is None else names.index(s[1]) for s in spec]
    pos = np.array([s[2] for s in spec])
    offsets, end = np.zeros((len(spec), 3)), np.full((len(spec), 3), np.nan)
    for j, p in enumerate(parents):
        if p >= 0:
            offsets[j] = _rot(rng, perturb_deg) @ (pos[j] - pos[p]) * rng.uniform(0.8, 1.3)
        if spec[j][3] is not None:
            end[j] = _rot(rng, perturb_deg) @ (np.asarray(spec[j][3]) - pos[j])
    offsets, end = offsets @ M._M, end @ M._M  # bodyprior axes -> BVH axes (M^T x)
    perms = ["ZXY", "ZYX"]  # the orders of the real files (test_bvh checks all six)
    channels = []
    for j in range(len(spec)):
        rot = tuple(f"{a}rotation" for a in perms[rng.integers(2)])
        channels.append(("Xposition", "Yposition", "Zposition") + rot if j == 0 else rot)
    C = sum(len(c) for c in channels)
    motion = rng.uniform(-motion_deg, motion_deg, size=(n_frames, C))
    motion[:, :3] = rng.normal(size=(n_frames, 3))
    return bp.Bvh(tuple(names), tuple(parents), offsets, tuple(channels), end, 1 / 120, motion)


def _rig_spec(body):
    """CMU MotionBuilder-named 31-joint skeleton at the rig's rest joints (rig order is DFS)."""
    heads, tails = M._rig_rest(body)
    leaves = {"LeftToeBase", "RightToeBase", "Head", "LThumb", "RThumb"}
    spec = []
    for j, (n, p) in enumerate(zip(body.joint_names, body.parents)):
        name = n.replace("HandFinger1", "HandIndex1")
        parent = None if p < 0 else body.joint_names[p].replace("HandFinger1", "HandIndex1")
        is_end = n in leaves or n.endswith("HandFinger1")
        spec.append((name, parent, heads[j], tails[j] if is_end else None))
    return spec


def _daz_spec(body):
    """A Daz-friendly-named skeleton (the joints the retargeting uses) at rig positions."""
    heads, tails = M._rig_rest(body)
    h = {n: heads[j] for j, n in enumerate(body.joint_names)}
    t = {n: tails[j] for j, n in enumerate(body.joint_names)}
    spec = [
        ("hip", None, h["Hips"], None),
        ("abdomen", "hip", h["LowerBack"], None),
        ("chest", "abdomen", h["Spine1"], None),
        ("neck", "chest", h["Neck"], None),
        ("head", "neck", h["Head"], t["Head"]),
    ]
    for s, S in (("l", "Left"), ("r", "Right")):
        spec += [
            (f"{s}Collar", "chest", h[f"{S}Shoulder"], None),
            (f"{s}Shldr", f"{s}Collar", h[f"{S}Arm"], None),
            (f"{s}ForeArm", f"{s}Shldr", h[f"{S}ForeArm"], None),
            (f"{s}Hand", f"{s}ForeArm", h[f"{S}Hand"], None),
            (f"{s}Mid1", f"{s}Hand", h[f"{S}HandFinger1"], t[f"{S}HandFinger1"]),
        ]
    for s, S, H in (("r", "Right", "RHipJoint"), ("l", "Left", "LHipJoint")):
        spec += [
            (f"{s}Buttock", "hip", h[H] + (h[f"{S}UpLeg"] - h[H]) * 0.7 + [0, 0, 0.03], None),
            (f"{s}Thigh", f"{s}Buttock", h[f"{S}UpLeg"], None),
            (f"{s}Shin", f"{s}Thigh", h[f"{S}Leg"], None),
            (f"{s}Foot", f"{s}Shin", h[f"{S}Foot"], t[f"{S}ToeBase"]),
        ]
    # depth-first order: children right after their parent's subtree
    order, names = [], [s[0] for s in spec]

    def visit(i):
        order.append(spec[i])
        for k, s in enumerate(spec):
            if s[1] == names[i]:
                visit(k)

    visit(0)
    return order


# --------------------------------------------------------------------------------------------------
# direction check: posed rig bones vs posed mocap bones, in the pelvis frame


def _mocap_positions(bvh, frames):
    """Independent FK of the BVH (bodyprior axes): joints and End Sites per frame."""
    L = bvh.local_rotations(frames)
    T = bvh.local_translations(frames)
    F, J = L.shape[:2]
    G, P = np.empty_like(L), np.zeros((F, J, 3))
    for j, p in enumerate(bvh.parents):
        G[:, j] = L[:, j] if p < 0 else G[:, p] @ L[:, j]
        P[:, j] = T[:, j] if p < 0 else P[:, p] + np.einsum("fab,fb->fa", G[:, p], T[:, j])
    E = P + np.einsum("fjab,jb->fja", G, np.nan_to_num(bvh.end_offsets))
    to_bp = lambda x: x @ M._M.T
    return to_bp(P), to_bp(E), M._M @ G @ M._M.T


@jax.jit
def _rig_fk(body, eul, heads):
    def one(e):
        Rm = jax.vmap(bp.axis_angle_to_matrix)(rig_pose(body, e))
        return bp.world_transforms(body.parents, Rm, heads, jnp.zeros(3, heads.dtype))

    return jax.vmap(one)(eul)


def _direction_errors(bvh, body, frames, table):
    """Angle (degrees) between rig and mocap bone directions, (F, bones checked), and bone names."""
    kind = M.skeleton_kind(bvh)
    if kind == "cmu_3dsmax":
        bvh = M._rename(bvh, M._MAX_TO_MB)
    R = M.retarget_matrices(bvh, body, frames)
    eul = M._to_euler(R)
    P, E, G = _mocap_positions(bvh, frames)
    heads, tails = M._rig_rest(body)
    names = body.joint_names
    root = bvh.joint_index(table["Hips"][0])
    Gr, tr = _rig_fk(body, jnp.asarray(eul), jnp.asarray(heads))
    Gr, tr = np.asarray(Gr), np.asarray(tr)
    errs, checked = [], []
    for n in POSE_JOINTS:
        if n not in table or table[n][1] is None:
            continue
        drv, mend, (kind_end, bone) = table[n]
        d = bvh.joint_index(drv)
        if mend.endswith("/end"):
            if mend[:-4] != drv:
                continue
            tip = E[:, d]
        else:
            e = bvh.joint_index(mend)
            if bvh.parents[e] != d or np.linalg.norm(bvh.offsets[e]) < 1e-6:
                continue  # its direction depends on a zero-length joint in between
            tip = P[:, e]
        vm = np.einsum("fba,fb->fa", G[:, root], tip - P[:, d])  # G_root^T v: pelvis frame
        b = names.index(bone)
        end_pt = tr[:, b] if kind_end == "head" else tr[:, b] + Gr[:, b] @ (tails[b] - heads[b])
        vr = end_pt - tr[:, names.index(n)]
        cos = np.sum(vm * vr, -1) / np.linalg.norm(vm, axis=-1) / np.linalg.norm(vr, axis=-1)
        errs.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
        checked.append(n)
    return np.stack(errs, 1), checked


@pytest.mark.parametrize("kind", ["cmu_mb", "cmu_3dsmax", "daz"])
def test_retarget_synthetic_bone_directions(body, kind):
    rng = np.random.default_rng({"cmu_mb": 0, "cmu_3dsmax": 1, "daz": 2}[kind])
    if kind == "daz":
        bvh = _skeleton(_daz_spec(body), rng, 3)
        table = M._MAPS["daz"]
    else:
        bvh = _skeleton(_rig_spec(body), rng, 3)
        table = M._MAPS["cmu"]
        if kind == "cmu_3dsmax":
            inv = {v: k for k, v in M._MAX_TO_MB.items()}
            bvh = M._rename(bvh, inv)
    assert M.skeleton_kind(bvh) == kind
    err, checked = _direction_errors(bvh, body, np.arange(3), table)
    expect = 17 if kind == "daz" else 19
    assert len(checked) == expect, checked
    assert err.max() < 0.05, dict(zip(checked, err.max(0)))


def test_retarget_rest_pose_is_swing_only(body):
    """At the mocap rest pose (all channels zero) each rig joint only swings, with no twist about
    its bone (the rest compensation is carried down the tree): an elbow unbends about its hinge."""
    rng = np.random.default_rng(3)
    bvh = _skeleton(_rig_spec(body), rng, 1)
    bvh = bp.Bvh(bvh.joint_names, bvh.parents, bvh.offsets, bvh.channels, bvh.end_offsets, 0.01,
                 np.zeros_like(bvh.motion))  # fmt: skip
    R = M.retarget_matrices(bvh, body, [0])[0]
    heads, _ = M._rig_rest(body)
    names = body.joint_names
    for k, n in enumerate(POSE_JOINTS):
        entry = M._MAPS["cmu"][n]
        child = entry[2][1]
        if entry[2][0] != "head":
            continue
        b = heads[names.index(child)] - heads[names.index(n)]
        b /= np.linalg.norm(b)
        w = np.array([R[k][2, 1] - R[k][1, 2], R[k][0, 2] - R[k][2, 0], R[k][1, 0] - R[k][0, 1]])
        assert abs(w @ b) < 1e-9, n  # rotation axis (∝ w) perpendicular to the bone: a swing


def test_find_mocap_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("BODYPRIOR_MOCAP_DIR", str(tmp_path))
    assert find_mocap_dir() == tmp_path
    monkeypatch.setenv("BODYPRIOR_MOCAP_DIR", str(tmp_path / "absent"))
    assert find_mocap_dir() is None


@pytest.mark.bad_input
def test_skeleton_kind_rejects_unknown(tmp_path, body):
    b = bp.Bvh(("a",), (-1,), np.zeros((1, 3)), (("Xrotation",),), np.full((1, 3), np.nan), 0.1,
               np.zeros((2, 1)))  # fmt: skip
    with pytest.raises(ValueError, match="unknown skeleton"):
        M.skeleton_kind(b)
    bp.write_bvh(tmp_path / "odd.bvh", b)
    with pytest.raises(ValueError, match=r"odd\.bvh: unknown skeleton"):
        load_mocap(tmp_path, progress=False, body=body)
    with pytest.raises(ValueError, match="neither a file nor a directory"):
        load_mocap(tmp_path / "missing", progress=False, body=body)


# --------------------------------------------------------------------------------------------------
# loading, resampling, frame rates


def test_load_mocap_resamples_and_drops_rest_frame(tmp_path, body):
    rng = np.random.default_rng(4)
    bvh = _skeleton(_rig_spec(body), rng, 241)  # MotionBuilder names: frame 0 is the T-pose
    (tmp_path / "salsa_like").mkdir()
    (tmp_path / "walks").mkdir()
    bp.write_bvh(tmp_path / "salsa_like/a.bvh", bvh, precision=17)
    bp.write_bvh(tmp_path / "walks/b.bvh", bvh, precision=17)
    short = bp.Bvh(*[getattr(bvh, f) for f in ("joint_names", "parents", "offsets", "channels",
                     "end_offsets", "frame_time")], bvh.motion[:100])  # fmt: skip
    bp.write_bvh(tmp_path / "walks/short.bvh", short)  # 99 motion frames = 0.82 s: skipped
    ps = load_mocap(tmp_path, progress=False, body=body, frame_rates={"salsa": 60.0})
    assert ps.clip_names == ("salsa_like/a", "walks/b")
    assert ps.joint_names == POSE_JOINTS and ps.fps == 4.0
    # 240 motion frames: at 60 fps 239/60 s -> 16 poses; at the header's 120 fps -> 8 poses
    np.testing.assert_array_equal(ps.poses_per_clip(), [16, 8])
    want = M._to_euler(M.retarget_matrices(bvh, body, 1 + 15 * np.arange(16)))
    np.testing.assert_allclose(ps.euler[:16], want, atol=1e-12)
    want_b = M._to_euler(M.retarget_matrices(bvh, body, 1 + 30 * np.arange(8)))
    np.testing.assert_allclose(ps.euler[16:], want_b, atol=1e-12)
    ps2 = load_mocap(tmp_path / "walks/b.bvh", fps=8.0, progress=False, body=body)
    assert ps2.n_poses == 16 and ps2.fps == 8.0
    with pytest.raises(ValueError, match="none of the 1 BVH files has enough motion"):
        load_mocap(tmp_path / "walks/short.bvh", progress=False, body=body)
    with pytest.raises(ValueError, match="`fps`"):
        load_mocap(tmp_path, fps=0.0, progress=False, body=body)


def test_plausible_drops_flipped_heads():
    R = np.broadcast_to(np.eye(3), (3, 20, 3, 3)).copy()
    flip = np.diag([-1.0, -1.0, 1.0])  # 180 degrees about Z
    R[1, POSE_JOINTS.index("Head")] = flip
    R[2, POSE_JOINTS.index("LeftArm")] = flip  # limbs are not bounded
    np.testing.assert_array_equal(M.plausible(R), [True, False, True])


# --------------------------------------------------------------------------------------------------
# rig_pose / pose_euler


@jax.jit
def _round_trip(body, e):
    pose = jax.vmap(lambda x: rig_pose(body, x))(e)
    back = jax.vmap(lambda p: pose_euler(body, p))(pose)
    idx = np.array([body.joint_names.index(j) for j in POSE_JOINTS])
    R = jax.vmap(bp.axis_angle_to_matrix)(pose[0, idx])
    R_e = jax.vmap(lambda x: bp.euler_to_matrix(x, EULER_ORDER))(e[0])
    g = jax.grad(lambda x: jnp.sum(rig_pose(body, x) ** 2))(jnp.zeros((20, 3), e.dtype))
    return pose, back, R, R_e, g


@pytest.mark.bad_input
def test_rig_pose_round_trip_jit_vmap(body, getkey):
    n = 5
    k1, k2 = jax.random.split(getkey())
    outer = jax.random.uniform(k1, (n, 20, 2), minval=-3.0, maxval=3.0)
    mid = jax.random.uniform(k2, (n, 20), minval=-1.4, maxval=1.4)
    e = jnp.stack([outer[..., 0], mid, outer[..., 1]], -1)
    pose, back, R, R_e, g = _round_trip(body, e)
    assert pose.shape == (n, body.n_joints, 3)
    idx = [body.joint_names.index(j) for j in POSE_JOINTS]
    others = np.setdiff1d(np.arange(body.n_joints), idx)
    assert np.all(np.asarray(pose)[:, others] == 0)
    np.testing.assert_allclose(back, e, atol=1e-9)
    np.testing.assert_allclose(R, R_e, atol=1e-9)  # the rotation of the Euler angles
    assert np.all(np.isfinite(np.asarray(g)))  # finite gradient at the identity
    with pytest.raises(ValueError, match=r"`euler` must have shape \(20, 3\)"):
        rig_pose(body, jnp.zeros((19, 3)))
    with pytest.raises(ValueError, match=r"must have the cmu_mb rig.*missing \['LeftUpLeg'"):
        M._pose_index(tuple(n for n in body.joint_names if n != "LeftUpLeg"))


# --------------------------------------------------------------------------------------------------
# split


def _poses(counts):
    clip = np.repeat(np.arange(len(counts)), counts).astype(np.int32)
    e = np.random.default_rng(0).normal(size=(len(clip), 20, 3))
    return PoseSet(jnp.asarray(e), jnp.asarray(clip), tuple(f"c{i}" for i in range(len(counts))))


def test_split_by_clip_no_clip_in_both():
    ps = _poses([30, 5, 12, 40, 8, 25, 17, 3, 60, 10])
    tr, te = split_by_clip(ps, 0.2, seed=0)
    a, b = set(np.asarray(tr.clip).tolist()), set(np.asarray(te.clip).tolist())
    assert not a & b and a | b == set(range(10))
    assert tr.n_poses + te.n_poses == ps.n_poses
    assert te.n_poses >= 0.2 * ps.n_poses
    # the test set stops at the first clip that reaches the target fraction
    assert te.n_poses - min(ps.poses_per_clip()[list(b)]) < 0.2 * ps.n_poses + 60
    assert tr.clip_names == ps.clip_names and te.joint_names == POSE_JOINTS
    rows = {tuple(r) for r in np.asarray(te.euler).reshape(te.n_poses, -1).round(12)}
    assert len(rows) == te.n_poses
    tr2, te2 = split_by_clip(ps, 0.2, seed=0)
    np.testing.assert_array_equal(te2.clip, te.clip)
    splits = {tuple(sorted(set(np.asarray(split_by_clip(ps, 0.2, seed=s)[1].clip).tolist())))
              for s in range(5)}  # fmt: skip
    assert len(splits) > 1
    with pytest.raises(ValueError, match="test_fraction"):
        split_by_clip(ps, 1.0)
    with pytest.raises(ValueError, match="at least two non-empty clips"):
        split_by_clip(_poses([10]), 0.2)


# --------------------------------------------------------------------------------------------------
# real data (skipped when the shared data is absent)


@needs_data
@pytest.mark.parametrize(
    "rel, frames",
    [
        (
            "cmu_3dsmax-friendly_yuki-koyama-bvh11/131_michael_jackson_styled/131_01.bvh",
            [0, 400, 900],
        ),
        ("cmu_daz-friendly_papagina-acLSTM/salsa_couple/01.bvh", [1, 800, 1600]),
        ("cmu_daz-friendly_papagina-acLSTM/martial_arts/05.bvh", [1, 1200]),
        ("cmu_mb_motionbuilder-friendly_una-dinosauria-cmu-mocap/02_06_first3frames.bvh", [1, 2]),
    ],
)
def test_retarget_real_clips_bone_directions(body, rel, frames):
    bvh = bp.read_bvh(MOCAP / rel)
    kind = M.skeleton_kind(bvh)
    table = M._MAPS[M._KIND_INFO[kind][0]]
    err, checked = _direction_errors(bvh, body, np.array(frames), table)
    assert len(checked) >= 13
    assert err.max() < 2.0, dict(zip(checked, err.max(0)))


@needs_data
def test_load_real_clips_frame_rates_and_skips(body):
    info = {}
    ps = load_mocap(
        [
            MOCAP / "cmu_daz-friendly_papagina-acLSTM/salsa_couple/01.bvh",
            MOCAP / "cmu_3dsmax-friendly_yuki-koyama-bvh11/131_michael_jackson_styled/131_01.bvh",
            MOCAP / "cmu_daz-friendly_papagina-acLSTM/salsa_couple/06.bvh",
            MOCAP / "cmu_daz-friendly_papagina-acLSTM/standard.bvh",
            MOCAP / "cmu_mb_motionbuilder-friendly_una-dinosauria-cmu-mocap",
        ],
        progress=False,
        body=body,
        info=info,
    )
    assert ps.clip_names == ("salsa_couple/01", "131_michael_jackson_styled/131_01")
    # salsa: 2,235 motion frames (after rest + blend) at 60 fps = 37.2 s; 131_01: 994 frames at
    # 120 fps = 8.3 s
    np.testing.assert_array_equal(ps.poses_per_clip(), [149, 34])
    stats = {Path(k).name: v for k, v in info.items()}
    assert stats["01.bvh"]["source_fps"] == 60.0 and stats["131_01.bvh"]["source_fps"] == 120.0
    assert stats["06.bvh"]["poses"] == 0 and stats["06.bvh"]["dropped"] == 118  # upside-down head
    assert stats["standard.bvh"]["skipped"] and stats["02_06_first3frames.bvh"]["skipped"]
    assert np.all(np.isfinite(np.asarray(ps.euler)))
    # most joints move, and the poses are not all the same
    assert float(jnp.std(ps.euler, axis=0).mean()) > 0.05


# --------------------------------------------------------------------------------------------------
# pictures


@pytest.mark.bad_input
def test_render_poses(tmp_path, body):
    e = np.zeros((2, 20, 3))
    e[1, POSE_JOINTS.index("LeftArm"), 1] = 1.0
    img = render_poses(body, e, tmp_path / "p.png", labels=["rest", "arm"], cell_size=(64, 48))
    assert img.dtype == np.uint8 and img.shape[1] == 96
    assert (tmp_path / "p.png").stat().st_size > 0
    with pytest.raises(ValueError, match="`euler`"):
        render_poses(body, np.zeros((2, 19, 3)), tmp_path / "q.png")


# --------------------------------------------------------------------------------------------------
# public retargeting: Retargeter, retarget, poses_to_bvh, 2008 CMU names

_MB_3FRAMES = "cmu_mb_motionbuilder-friendly_una-dinosauria-cmu-mocap/02_06_first3frames.bvh"


def _cmu_2008_file(tmp_path) -> Path:
    """CMU 02_06 (the shared 3-frame excerpt of the MotionBuilder-friendly conversion) with its
    finger joints renamed to the 2008 release's names (`LeftHandIndex1` -> `LFingers`,
    `RightHandIndex1` -> `RFingers`), as in CMU 01_01 of that release; made from the shared data
    at test time, so no mocap file is committed."""
    src = bp.read_bvh(MOCAP / _MB_3FRAMES)
    path = tmp_path / "cmu_mb2008_02_06_3frames.bvh"
    bp.write_bvh(path, M._rename(src, {v: k for k, v in M._MB2008_TO_MB.items()}))
    return path


def _angle(a, b):
    Ra = jax.vmap(bp.axis_angle_to_matrix)(jnp.asarray(a.reshape(-1, 3)))
    Rb = jax.vmap(bp.axis_angle_to_matrix)(jnp.asarray(b.reshape(-1, 3)))
    cos = (jnp.trace(jnp.swapaxes(Ra, -1, -2) @ Rb, axis1=-2, axis2=-1) - 1) / 2
    return np.arccos(np.clip(np.asarray(cos), -1, 1))


@needs_data
def test_cmu_2008_names_retarget_like_2010(tmp_path, body):
    path08 = _cmu_2008_file(tmp_path)
    b08 = bp.read_bvh(path08)
    assert M.skeleton_kind(b08) == "cmu_mb2008"
    b10 = M._rename(b08, M._MB2008_TO_MB)
    assert M.skeleton_kind(b10) == "cmu_mb"
    p08, t08 = bp.retarget(b08, body, [1, 2], keep_root_rotation=True, keep_root_translation=True)
    p10, _ = bp.retarget(b10, body, [1, 2], keep_root_rotation=True, keep_root_translation=True)
    np.testing.assert_array_equal(p08, p10)
    assert p08.shape == (2, body.n_joints, 3) and np.all(np.isfinite(p08))
    assert abs(t08[0, 2] + body_root_height(body) - 1.0) < 0.1  # CMU hips about 1 m high
    ps = load_mocap(path08, progress=False, body=body,
                    min_duration=0.0)  # fmt: skip
    assert ps.n_poses == 1 and np.all(np.abs(np.asarray(ps.euler)) < np.pi)
    # a missing joint is named as in the file (RFingers, not RightHandIndex1)
    bad = dataclasses_replace_names(b08, {"RFingers": "RFinger"})
    with pytest.raises(ValueError, match="No joint named 'RFingers'"):
        bp.Retargeter.from_bvh(bad, body)


def body_root_height(body):
    return M._rig_rest(body)[0][0, 2]


def dataclasses_replace_names(bvh, mapping):
    return M._rename(bvh, mapping)


def test_missing_joint_error_names_3dsmax_joint(body):
    bvh = _skeleton(_rig_spec(body), np.random.default_rng(5), 2)
    bvh = M._rename(bvh, {v: k for k, v in M._MAX_TO_MB.items()})
    bvh = M._rename(bvh, {"LFingers": "LFinger"})
    assert M.skeleton_kind(bvh) == "cmu_3dsmax"
    with pytest.raises(ValueError, match="No joint named 'LFingers'"):
        bp.retarget(bvh, body)


def test_retarget_frames_and_export_round_trip(tmp_path, body):
    bvh = _skeleton(_rig_spec(body), np.random.default_rng(6), 6)
    rt = bp.Retargeter.from_bvh(bvh, body)
    pose, trans = rt(bvh, slice(1, None), keep_root_rotation=True, keep_root_translation=True)
    assert pose.shape == (5, body.n_joints, 3) and trans.shape == (5, 3)
    # any frames: the same as the matching rows of all frames; the DSPP pose is the same
    p2, _ = rt(bvh, [4, -5], keep_root_rotation=True)
    np.testing.assert_allclose(p2, pose[[3, 0]], atol=1e-12)
    R = rt.local_matrices(bvh, [2])
    np.testing.assert_allclose(M._to_euler(R)[0], pose_euler(body, pose[1]), atol=1e-9)
    with pytest.raises(ValueError, match="`frames` must index the 6 frames"):
        rt(bvh, [6])
    with pytest.raises(ValueError, match="`frames`"):
        rt(bvh, np.zeros((2, 2), int))
    # export, read back, retarget onto the same body: the same poses and translations
    out = tmp_path / "rig.bvh"
    bp.poses_to_bvh(body, pose, trans, fps=30.0, path=out)
    back = bp.read_bvh(out)
    assert M.skeleton_kind(back) == "rig" and back.frame_time == pytest.approx(1 / 30)
    p3, t3 = bp.retarget(back, body, keep_root_rotation=True, keep_root_translation=True)
    assert _angle(p3, pose).max() < 1e-6
    np.testing.assert_allclose(t3, trans, atol=1e-7)
    phen = jnp.asarray(bp.phenotype_vector())
    j1 = np.asarray(bp.evaluate(body, phen, jnp.asarray(pose[2]), jnp.asarray(trans[2]))[1])
    j3 = np.asarray(bp.evaluate(body, phen, jnp.asarray(p3[2]), jnp.asarray(t3[2]))[1])
    np.testing.assert_allclose(j3, j1, atol=1e-5)
    with pytest.raises(ValueError, match="`fps`"):
        bp.poses_to_bvh(body, pose, fps=0.0)
    with pytest.raises(ValueError, match="`poses`"):
        bp.poses_to_bvh(body, pose[:, :3], fps=30.0)
    with pytest.raises(ValueError, match="skeleton this Retargeter was built for"):
        rt(back)
