"""Depth camera, depth rendering, back-projection and front/back depth fitting (sscape)."""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import bodyprior as bp
from bodyprior.registration import (
    DepthCamera,
    depth_normals,
    depth_scan_truth,
    depth_to_scan,
    kinect_pair,
    registration_template,
    render_depth,
)
from bodyprior.sscape import DepthFitConfig, FitConfig, fit_depth

ROOT = Path(__file__).resolve().parents[1]


def _quad(y=0.0, half=2.0, slope=0.0):
    """A square in the plane y = y0 + slope * x (two triangles), facing -Y."""
    v = np.array([[-half, 0, -half], [half, 0, -half], [half, 0, half], [-half, 0, half]], float)
    v[:, 1] = y + slope * v[:, 0]
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    v = lo + c * (hi - lo)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
    return v, np.array(f)


def test_camera_intrinsics_and_projection_round_trip():
    cam = DepthCamera([0.3, -2.0, 0.5], [0.3, 0.0, 0.5])
    assert (cam.width, cam.height, cam.fx, cam.fy) == (512, 424, 365.0, 365.0)
    assert (cam.cx, cam.cy) == (256.0, 212.0)
    r = np.asarray(cam.rotation)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[2], [0, 1, 0], atol=1e-12)  # looks along +Y
    np.testing.assert_allclose(r[1], [0, 0, -1], atol=1e-12)  # image down = world -Z
    p = np.random.default_rng(0).normal(size=(50, 3)) * 0.4 + [0.3, 0.5, 0.5]
    uvz = np.asarray(cam.project(p))
    back = np.asarray(cam.backproject(uvz[:, 0], uvz[:, 1], uvz[:, 2]))
    np.testing.assert_allclose(back, p, atol=1e-12)
    # The target is on the optical axis: it projects to the principal point.
    np.testing.assert_allclose(np.asarray(cam.project(np.array([[0.3, 0.0, 0.5]])))[0, :2],
                               [256.0, 212.0], atol=1e-9)  # fmt: skip


SMALL = dict(width=128, height=106, fx=91.25, fy=91.25)  # the Kinect field of view, 4x coarser


def test_plane_depth_is_exact_and_back_projects_onto_the_plane():
    cam = DepthCamera([0.1, -2.0, 0.2], [0.1, 0.0, 0.2], **SMALL)
    v, f = _quad()
    depth, truth = render_depth(v, f, cam)
    assert depth.shape == (106, 128) and np.all(depth > 0)
    np.testing.assert_allclose(depth, 2.0, atol=1e-12)
    # A tilted plane y = 0.5 x: every back-projected pixel lies on it (exact first-hit depth).
    v2, f2 = _quad(slope=0.5)
    d2, t2 = render_depth(v2, f2, cam, max_incidence_deg=None)
    p = np.asarray(cam.pixel_points(d2)).reshape(-1, 3)[d2.ravel() > 0]
    assert p.shape[0] > 10_000
    np.testing.assert_allclose(p[:, 1], 0.5 * p[:, 0], atol=1e-9)
    # The barycentric ground truth reproduces the hit points.
    hit = np.asarray(t2.face) >= 0
    q = np.einsum("pk,pkc->pc", np.asarray(t2.bary)[hit], v2[f2[np.asarray(t2.face)[hit]]])
    np.testing.assert_allclose(q, np.asarray(cam.pixel_points(d2))[hit], atol=1e-9)
    # Normals from the depth gradients of a plane are the plane normal, facing the camera.
    n = depth_normals(d2, cam)[hit]
    expect = np.array([0.5, -1.0, 0.0]) / np.sqrt(1.25)
    np.testing.assert_allclose(n, np.broadcast_to(expect, n.shape), atol=1e-6)


def test_box_occlusion_range_and_incidence():
    cam = DepthCamera([0.0, -3.0, 0.0], [0.0, 0.0, 0.0])
    box, bf = _box([-0.2, -1.2, -0.2], [0.2, -0.8, 0.2])  # front face at y = -1.2: depth 1.8
    wall, wf = _quad(y=1.0, half=4.0)  # depth 4.0 behind it
    v = np.concatenate([box, wall])
    f = np.concatenate([bf, wf + len(box)])
    depth, truth = render_depth(v, f, cam)
    c = depth[212, 256]
    assert c == pytest.approx(1.8, abs=1e-12)
    assert depth[5, 5] == pytest.approx(4.0, abs=1e-12)
    assert int(truth.face[212, 256]) < len(bf) <= int(truth.face[5, 5])
    # Outside [near, far] there is no return.
    d_far, t_far = render_depth(v, f, cam, far=3.0)
    assert d_far[5, 5] == 0.0 and int(t_far.face[5, 5]) == -1 and d_far[212, 256] > 0
    # The box's side faces are seen edge-on (incidence 90 deg): never returned; the 10 % pixel
    # border of the front face is exact.
    cols = np.nonzero(depth[212] < 2.0)[0]
    u_edge = 365.0 * 0.2 / 1.8
    assert cols.min() == int(np.ceil(256 - u_edge - 0.5)) and cols.max() == int(256 + u_edge - 0.5)


def test_noise_grows_with_depth_squared():
    v, f = _quad(y=0.0, half=3.0)
    for dist in (1.5, 3.0):
        cam = DepthCamera([0.0, -dist, 0.0], [0.0, 0.0, 0.0], **SMALL)
        d0, _ = render_depth(v, f, cam)
        d1, truth = render_depth(v, f, cam, key=jr.PRNGKey(1), noise_sigma=0.0015)
        np.testing.assert_array_equal(np.asarray(truth.true_depth), d0)
        s = np.std(d1 - d0)
        assert s == pytest.approx(0.0015 * dist**2, rel=0.02)
    with pytest.raises(ValueError, match="noise_sigma"):
        render_depth(v, f, cam, noise_sigma=-1.0)


def test_depth_to_scan_round_trip_padding_and_truth():
    cam = DepthCamera([0.0, -2.0, 0.0], [0.0, 0.0, 0.0], width=64, height=48, fx=40, fy=40)
    v, f = _box([-0.3, -0.2, -0.3], [0.3, 0.2, 0.3])
    depth, truth = render_depth(v, f, cam)
    n_valid = int((depth > 0).sum())
    scan = depth_to_scan(depth, cam)
    assert scan.points.shape == (n_valid, 3) and bool(scan.point_mask.all())
    np.testing.assert_allclose(np.asarray(scan.points)[:, 1], -0.2, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(scan.normals), np.tile([0, -1.0, 0], (n_valid, 1)), atol=1e-9
    )
    big = depth_to_scan(depth, cam, n_points=n_valid + 10)
    assert int(big.point_mask.sum()) == n_valid and big.points.shape[0] == n_valid + 10
    small = depth_to_scan(depth, cam, n_points=50, seed=3)
    st = depth_scan_truth(truth, depth, cam, n_points=50, seed=3)
    np.testing.assert_allclose(np.asarray(st.true_points), np.asarray(small.points), atol=1e-12)
    q = np.einsum("pk,pkc->pc", np.asarray(st.bary), v[f[np.asarray(st.face)]])
    np.testing.assert_allclose(q, np.asarray(small.points), atol=1e-12)


@pytest.mark.bad_input
def test_bad_input_errors():
    cam = DepthCamera([0.0, -2.0, 0.0], [0.0, 0.0, 0.0], width=32, height=24)
    with pytest.raises(ValueError, match="target"):
        DepthCamera([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="up"):
        DepthCamera([0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="width"):
        DepthCamera([0, -1, 0], [0, 0, 0], width=0)
    with pytest.raises(ValueError, match="camera"):
        render_depth(*_quad(), "front")
    with pytest.raises(ValueError, match="depth"):
        depth_to_scan(np.zeros((10, 10)), cam)
    with pytest.raises(ValueError, match="no valid pixel"):
        depth_to_scan(np.zeros((24, 32)), cam)
    with pytest.raises(ValueError, match="millimetres"):
        depth_to_scan(np.full((24, 32), 2000.0), cam)
    with pytest.raises(ValueError, match="n_points"):
        depth_to_scan(np.full((24, 32), 2.0), cam, n_points=0)
    with pytest.raises(ValueError, match="DepthFitConfig.max_rounds"):
        DepthFitConfig(max_rounds=0)


# --------------------------------------------------------------------------------------------------
# Fitting (one compile shared by the recovery test and the experiment's quick run)

K_TEST = 4


@pytest.fixture(scope="module")
def problem():
    tmpl = registration_template()
    body = bp.load_default_body("cmu_mb")
    phen = jr.uniform(jr.PRNGKey(3), (12, 11), minval=0.2, maxval=0.8)
    rest = jax.vmap(lambda p: bp.rest_shape(body, p)[0])(phen)
    model = bp.sscape.learn(tmpl.restrict(rest).astype(jnp.float64), tmpl.faces,
                            n_components=K_TEST, rig=tmpl.rig)  # fmt: skip
    return tmpl, model


def _model_scans(tmpl, model, coeffs, poses, key):
    """Noise-free front/back depth scans of a body generated by the model itself."""
    front, back = kinect_pair(distance=2.4)
    scans, truth = [], []
    names = tmpl.landmark_names
    sub = ("Vertex", "Rt. Acromion", "Lt. Acromion", "Rt. Radial Styloid", "Lt. Radial Styloid",
           "Rt. Trochanterion", "Lt. Trochanterion", "Rt. Lateral Malleolus",
           "Lt. Lateral Malleolus", "Crotch")  # fmt: skip
    for cam, pose in zip((front, back), poses):
        v, _ = bp.sscape.evaluate(model, coeffs, pose)
        v = np.asarray(v)
        depth, _ = render_depth(v, tmpl.faces, cam)
        lm = v[np.asarray(tmpl.landmark_index)]
        mask = np.array([n in sub for n in names])
        scans.append(depth_to_scan(depth, cam, n_points=2048, seed=0, landmarks=lm,
                                   landmark_mask=mask, landmark_names=names))  # fmt: skip
        truth.append(v)
    return scans, truth


# The experiment's fit settings (`experiments/sscape_depth.py` FIT): one compile for both tests.
FAST = DepthFitConfig(fit=FitConfig(landmark_steps=30, shape_prior=1.0), max_rounds=4, pose_steps=8,
                      shape_steps=8)  # fmt: skip


# ~70 s on an idle 2-core machine (fitter compile); kept in the default suite so the depth
# experiment's quick path runs in CI.
def test_fit_depth_recovers_shape_and_pose(problem):
    tmpl, model = problem
    J = model.n_joints
    names = model.joint_names
    coeffs = jnp.array([1.2, -0.8, 0.6, -0.5])
    poses = np.zeros((2, J, 3))
    poses[0, names.index("LeftArm"), 1] = -0.5
    poses[0, names.index("RightArm"), 1] = 0.3
    poses[1, names.index("LeftArm"), 1] = -0.2
    poses[1, names.index("RightArm"), 1] = 0.6
    poses[1, 0, 2] = 0.1
    scans, truth = _model_scans(tmpl, model, coeffs, jnp.asarray(poses), jr.PRNGKey(0))
    sol = fit_depth(model, scans[0], scans[1], tmpl, config=FAST)
    fit = sol.value
    assert fit.vertices.shape == (2, model.n_vertices, 3) and fit.poses.shape == (2, J, 3)
    hand = np.asarray(tmpl.hand_mask)
    # Posed error (hands excluded): the back image cannot see the toes (their pose is a guess), so
    # its bound is looser. Measured: 6.0 mm front, 13.2-16.0 mm back (toes ~60 mm), 4.9 mm rest.
    for k, bound in ((0, 8.0), (1, 20.0)):
        err = np.asarray(bp.registration.gt_error(fit.vertices[k], truth[k]))[~hand]
        assert err.mean() < bound, (k, err.mean())
    rest_true = np.asarray(bp.sscape.shape_vertices(model, coeffs))
    rest_err = np.linalg.norm(np.asarray(fit.rest_vertices) * float(fit.scale) - rest_true, axis=1)
    assert rest_err.mean() * 1000 < 6.0
    # (The coefficients themselves are not compared: this 12-body space has near-degenerate small
    # components, so different coefficients give the same surface to within the noise.)
    assert float(sol.stats["data_term"][0]) > float(sol.stats["data_term"][sol.stats["rounds"]])
    assert np.all(np.asarray(sol.stats["valid_fraction"]) > 0.8)


@pytest.mark.bad_input
def test_fit_depth_bad_input():
    tmpl = registration_template()
    v0 = jnp.asarray(tmpl.vertices, jnp.float64)
    model = bp.sscape.learn(jnp.stack([v0, 1.02 * v0, 0.97 * v0]), tmpl.faces, n_components=1,
                            rig=tmpl.rig)  # fmt: skip
    cam = DepthCamera([0.0, -2.4, 0.0], [0.0, 0.0, 0.0])
    v = np.asarray(model.mean)
    depth, _ = render_depth(v, tmpl.faces, cam)
    no_lm = depth_to_scan(depth, cam, n_points=512)
    with pytest.raises(ValueError, match="landmark"):
        fit_depth(model, no_lm, no_lm, tmpl)
    with pytest.raises(ValueError, match="front_scan"):
        fit_depth(model, "scan", no_lm, tmpl)
    with pytest.raises(ValueError, match="config"):
        fit_depth(model, no_lm, no_lm, tmpl, config=FitConfig())


# shares the compiled fitter with the test above
@pytest.mark.typecheck_off
def test_experiment_quick_run(tmp_path, problem):
    sys.path.insert(0, str(ROOT / "experiments"))
    try:
        import sscape_depth
    finally:
        sys.path.pop(0)
    out = tmp_path / "depth"
    sscape_depth.main(["--quick", "--tiny", "--out", str(out), "--seed", "0", "--no-progress"])
    m = json.loads((out / "metrics.json").read_text())
    for key in (
        "spaces",
        "components",
        "train_sizes",
        "normalizations",
        "thresholds_mm",
        "timing_s",
    ):
        assert key in m
    assert len(m["spaces"]) >= 2
    for s in m["spaces"]:
        assert 0.0 < s["rest_error_mm_mean"] < 100.0
        assert 0.0 <= s["rest_frac_below_20mm"] <= 1.0
        assert len(s["rest_curve"]) == len(m["thresholds_mm"])
        assert np.all(np.diff(s["rest_curve"]) >= 0)
    for png in ("fig5_depth_cumulative.png", "depth_images.png", "fitted_body.png"):
        assert (out / png).stat().st_size > 1000
