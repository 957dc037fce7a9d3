"""The sparse-input pose-fit experiment (experiments/dspp_pose_fit.py, issue 15 §6): its skeleton
and observation sets (fast), and the whole run in `--quick --tiny` mode (slow: the LM fitter's
compile through the rig and the prior networks takes minutes on 2 cores)."""

import importlib.util
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp

REPO = Path(__file__).resolve().parents[1]
MOCAP = REPO.parent / "shared" / "data" / "mocap"


def _load():
    path = os.path.join(REPO, "experiments", "dspp_pose_fit.py")
    spec = importlib.util.spec_from_file_location("dspp_pose_fit", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["dspp_pose_fit"] = mod  # equinox Modules defined in it need their module
    spec.loader.exec_module(mod)
    return mod


def test_skeleton_and_observation_sets():
    exp = _load()
    body = bp.load_default_body("cmu_mb")
    bones = body.bones
    skel = exp.Skeleton(jnp.asarray(bones.head_template), jnp.asarray(bones.tail_template),
                        tuple(body.parents), tuple(body.joint_names))  # fmt: skip
    J = body.n_joints
    zero = jnp.zeros((20, 3))
    pts = np.asarray(skel.all_points(zero))
    np.testing.assert_allclose(pts[:J], np.asarray(body.bones.head_template), atol=1e-6)
    np.testing.assert_allclose(pts[J:], np.asarray(body.bones.tail_template), atol=1e-6)
    sets = exp._observation_sets(body.joint_names)
    (si, sm), (ji, jm) = sets["sparse"], sets["joints"]
    assert si.shape == ji.shape and float(sm.sum()) == 5 and float(jm.sum()) == J + 5
    # the sparse set is the head top, the wrists and the ankles
    names = body.joint_names
    want = [J + names.index("Head"), names.index("LeftHand"), names.index("RightHand"),
            names.index("LeftFoot"), names.index("RightFoot")]  # fmt: skip
    assert np.asarray(si)[:5].tolist() == want
    # the same rotations as bodyprior.rig_pose (the library's Euler pose -> rig pose)
    e = 0.4 * np.random.default_rng(0).standard_normal((20, 3))
    R = jax.vmap(bp.axis_angle_to_matrix)(bp.rig_pose(body, jnp.asarray(e)))
    _, t = bp.forward_kinematics(body.parents, R, bones.head_template, jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(skel.all_points(jnp.asarray(e)))[:J], np.asarray(t),
                               atol=1e-6)  # fmt: skip
    # bending the left elbow moves the left wrist and nothing on the right side
    e = np.zeros((20, 3))
    e[bp.POSE_JOINTS.index("LeftForeArm"), 0] = 0.8
    moved = np.linalg.norm(np.asarray(skel.all_points(jnp.asarray(e))) - pts, axis=1)
    assert moved[names.index("LeftHand")] > 0.05 and moved[names.index("RightHand")] < 1e-9


@pytest.mark.slow
@pytest.mark.skipif(not MOCAP.is_dir(), reason="needs ../shared/data/mocap")
def test_pose_fit_experiment_tiny(tmp_path):
    exp = _load()
    out = tmp_path / "pf"
    exp.main(["--quick", "--tiny", "--out", str(out), "--no-progress", "--max-steps", "20",
              "--mocap", str(MOCAP)])  # fmt: skip
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "tiny"
    assert m["observations"] == {"sparse": 5, "joints": 36, "depth": 100}
    assert m["depth_setup"]["icp_rounds"] == 5 and m["depth_setup"]["lm_steps_per_round"] == 4
    for s in ("sparse", "joints", "depth"):
        for meth in exp.METHODS:
            r = m[f"{s}_{meth}"]
            assert 0.0 < r["angle_deg_mean"] < 120.0 and 0.0 < r["point_mm_mean"] < 500.0
    # observing every joint pins the joint positions far better than five trackers
    assert m["joints_none"]["point_mm_mean"] < 0.5 * m["sparse_none"]["point_mm_mean"]
    assert (out / "pose_fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "pose_prior.dspp").exists()


def test_depth_view_pieces():
    """The single-depth-view set: the skinned mesh matches the rig, a rendered view lies on the
    posed surface, the occlusion test keeps the front and drops the back, and the start picker
    finds the true pose among decoys."""
    exp = _load()
    body = bp.load_default_body("cmu_mb")
    bones = body.bones
    skel = exp.Skeleton(jnp.asarray(bones.head_template, jnp.float64),
                        jnp.asarray(bones.tail_template, jnp.float64), tuple(body.parents),
                        tuple(body.joint_names))  # fmt: skip
    mesh = exp.skinned_mesh(body, 300)
    assert np.unique(np.asarray(mesh.sample)).size == 300
    zero = jnp.zeros((20, 3))
    np.testing.assert_allclose(np.asarray(mesh.vertices(skel, zero)),
                               np.asarray(body.template), atol=1e-9)  # fmt: skip
    e = 0.3 * np.random.default_rng(1).standard_normal((2, 20, 3))
    V = mesh.vertices(skel, jnp.asarray(e[0]))
    rows = jnp.asarray([5, 700, 9000])
    np.testing.assert_allclose(np.asarray(mesh.vertices(skel, jnp.asarray(e[0]), rows)),
                               np.asarray(V[rows]), atol=1e-12)  # fmt: skip
    # a rendered view lies on the posed mesh (Kinect noise ~9 mm at 2.5 m)
    pts, masks = exp.depth_views(skel, mesh, np.asarray(body.faces), e, 200, jax.random.PRNGKey(0))
    assert pts.shape == (2, 200, 3) and float(masks.min()) == 1.0
    cam = exp.depth_camera(mesh)
    rows, back, vis = exp._correspondences(skel, mesh, cam, jnp.asarray(e[0]), pts[0],
                                           masks[0])  # fmt: skip
    d = np.linalg.norm(np.asarray(V[rows] - pts[0]), axis=1)
    assert np.median(d) < 0.015 and np.percentile(d, 95) < 0.04
    # at rest the camera (at -Y) sees the front: visible vertices face -Y, the back is hidden
    vis0 = np.asarray(exp._visible(cam, mesh.rest, mesh.faces))
    N = np.asarray(bp.vertex_normals(mesh.rest, mesh.faces))
    assert (N[vis0, 1] < 0.2).mean() > 0.95 and not vis0[N[:, 1] > 0.5].any()
    assert 0.25 < vis0.mean() < 0.6
    # the picker ranks the true pose first among random decoys
    decoys = 0.5 * np.random.default_rng(2).standard_normal((6, 20, 3))
    cand = jnp.asarray(np.concatenate([decoys, e[:1]]))
    top = np.asarray(exp.pick_starts(skel, mesh, cam, cand, pts[:1], masks[:1], 2))
    assert top.shape == (1, 2, 20, 3)
    np.testing.assert_allclose(top[0, 0], e[0])
