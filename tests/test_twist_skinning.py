"""Twist-distributed skinning (the PanoMan training-data generator, panoman_v2 §3.2 G3)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import bodyprior as bp

_evaluate = jax.jit(bp.evaluate, static_argnames=("pose_rep", "skinning"))


@pytest.fixture(scope="module")
def body():
    return bp.load_default_body("cmu_mb")


def _forearm(body):
    phen = bp.phenotype_vector()
    _, joints = bp.rest_shape(body, phen)
    idx = {n: i for i, n in enumerate(body.joint_names)}
    fa, hd = idx["LeftForeArm"], idx["LeftHand"]
    d = np.asarray(joints[hd] - joints[fa])
    L = float(np.linalg.norm(d))
    return phen, np.asarray(joints[fa]), d / L, L, hd


def test_swing_twist_angle():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        phi = rng.uniform(-3.0, 3.0)
        swing_axis = np.cross(a, rng.normal(size=3))
        swing_axis /= np.linalg.norm(swing_axis)
        S = Rotation.from_rotvec(swing_axis * rng.uniform(0, 1.5)).as_matrix()
        T = Rotation.from_rotvec(a * phi).as_matrix()
        for R in (S @ T, T @ S):
            assert float(bp.swing_twist_angle(R, a)) == pytest.approx(phi, abs=1e-6)
    g = jax.grad(lambda R: bp.swing_twist_angle(R, jnp.array([0.0, 0.0, 1.0])))
    # a 180° swing about x: the twist about z is undefined; the gradient must stay finite
    R = jnp.asarray(Rotation.from_rotvec([np.pi, 0, 0]).as_matrix())
    assert np.isfinite(np.asarray(g(R))).all()
    assert np.isfinite(np.asarray(g(jnp.eye(3)))).all()


def test_twist_keeps_forearm_area_where_lbs_collapses(body):
    phen, h, a, L, hd = _forearm(body)
    ts = np.arange(0.05, 1.06, 0.05)
    v0, _ = _evaluate(body, phen)
    A0 = bp.cross_section_areas(v0, body.faces, h, a, ts * L)
    assert A0.min() > 1e-3  # 10 cm² and more along the forearm
    pose = np.zeros((body.n_joints, 3))
    pose[hd] = a * np.deg2rad(179.9)  # CMU puts pronation in the wrist channel
    ratio = {}
    for sk in ("lbs", "twist"):
        v, _ = _evaluate(body, phen, pose, skinning=sk)
        ratio[sk] = bp.cross_section_areas(v, body.faces, h, a, ts * L) / A0
    assert ratio["lbs"].min() < 0.15  # candy wrapper
    assert ratio["twist"].min() > 0.9


def test_twist_profile_is_a_ramp_and_the_hand_is_unchanged(body):
    phen, h, a, L, hd = _forearm(body)
    pose = np.zeros((body.n_joints, 3))
    pose[hd] = a * np.deg2rad(120.0)
    x = np.asarray(_evaluate(body, phen)[0])
    v_lbs = np.asarray(_evaluate(body, phen, pose)[0])
    v = np.asarray(_evaluate(body, phen, pose, skinning="twist")[0])
    t = (x - h) @ a / L
    r = np.linalg.norm((x - h) - np.outer((x - h) @ a, a), axis=1)
    for tc in (0.25, 0.75):
        m = (abs(t - tc) < 0.03) & (r < 0.08)
        p0 = (x[m] - h) - np.outer((x[m] - h) @ a, a)
        p1 = (v[m] - h) - np.outer((v[m] - h) @ a, a)
        ang = np.rad2deg(np.median(np.arctan2(np.cross(p0, p1) @ a, (p0 * p1).sum(1))))
        assert ang == pytest.approx(120.0 * tc, abs=12.0)
    far = t > 1.4  # fingers: skinned to the hand only, which is posed exactly as by LBS
    assert far.sum() > 50
    np.testing.assert_allclose(v[far], v_lbs[far], atol=1e-6)


def test_twist_equals_lbs_without_twist(body):
    rng = np.random.default_rng(1)
    phen = bp.phenotype_vector()
    pose = np.zeros((body.n_joints, 3))
    pose[bp.load_default_body("cmu_mb").joint_names.index("Spine1")] = rng.normal(size=3) * 0.3
    v0 = _evaluate(body, phen, pose)[0]
    v1 = _evaluate(body, phen, pose, skinning="twist")[0]
    np.testing.assert_allclose(v1, v0, atol=1e-6)
    # a random full-body pose differs from LBS only on the twist segments, and stays finite
    pose = rng.normal(size=(body.n_joints, 3)) * 0.4
    v2 = np.asarray(_evaluate(body, phen, pose, skinning="twist")[0])
    assert np.isfinite(v2).all()
    grad = jax.grad(lambda p: _evaluate(body, phen, p, skinning="twist")[0].sum())(
        jnp.zeros((body.n_joints, 3))
    )
    assert np.isfinite(np.asarray(grad)).all()


def test_bad_input(body):
    with pytest.raises(ValueError, match="skinning"):
        bp.evaluate(body, bp.phenotype_vector(), skinning="twisted")
    with pytest.raises(ValueError, match="axis"):
        bp.cross_section_areas(
            np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros(3), np.zeros(3), np.zeros(1)
        )
