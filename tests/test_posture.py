"""Posture normalization (NH, WSX) on the synthetic skinned tube with known rest shapes, poses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toybody import make_toy_model

import bodyprior as bp
from bodyprior.sscape import (
    learn_normalized,
    normalize_posture_nh,
    normalize_posture_nh_batch,
    normalize_posture_wsx,
    normalize_posture_wsx_batch,
    posture_rig,
    unpose_lbs,
)


@pytest.fixture(scope="module")
def toy():
    model = make_toy_model(5, n_rings=30, n_joints=4)
    rng = np.random.default_rng(0)
    n = 4
    coeffs = rng.normal(size=(n, 5))
    # Bends of 10-25 degrees at each joint about random horizontal axes (the tube stands along Z).
    axes = rng.normal(size=(n, model.n_joints, 3))
    axes[..., 2] = 0.0
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    poses = axes * np.deg2rad(rng.uniform(10, 25, size=(n, model.n_joints, 1)))
    poses[:, 0] = 0.0  # no global rotation: compare without alignment
    rest = np.asarray(jax.vmap(model.shape_vertices)(jnp.asarray(coeffs)))
    posed = np.asarray(
        jax.jit(jax.vmap(lambda c, p: model.evaluate(c, p)[0]))(jnp.asarray(coeffs), poses)
    )
    return model, rest, posed, poses


def _err_mm(a, b):
    return 1000 * np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1).mean(-1)


def _aligned_err_mm(a, b):
    out = []
    for ai, bi in zip(np.asarray(a), np.asarray(b)):
        s = bp.umeyama(jnp.asarray(ai), jnp.asarray(bi), with_scale=False)
        out.append(1000 * np.linalg.norm(np.asarray(s.apply(jnp.asarray(ai))) - bi, axis=-1).mean())
    return np.asarray(out)


def test_nh_inverse_lbs_recovers_rest_shape(toy):
    model, rest, posed, poses = toy
    base = _aligned_err_mm(posed, rest)
    assert base.min() > 10.0  # the poses are far from rest
    u = normalize_posture_nh_batch(posed, poses, model, laplacian=False)
    assert _err_mm(u, rest).max() < 0.01  # exact in the limit (LBS with the same weights)
    one = unpose_lbs(posed[0], poses[0], model)
    np.testing.assert_allclose(np.asarray(one), u[0], atol=1e-9)
    # With the Laplacian surface deformation: close to the truth, far better than un-normalized.
    x = normalize_posture_nh_batch(posed, poses, model)
    assert np.all(_err_mm(x, rest) < 0.1 * base)
    assert np.all(_err_mm(x, rest) < 5.0)


def test_nh_undoes_the_similarity(toy):
    model, rest, posed, poses = toy
    rot = np.asarray(bp.axis_angle_to_matrix(jnp.array([0.3, -0.2, 1.1])))
    sim = bp.Similarity.from_scale(rot, jnp.array([0.5, -1.0, 0.2]), 1.07)
    scanned = np.asarray(sim.apply(jnp.asarray(posed[1])))
    x = normalize_posture_nh(scanned, poses[1], model, similarity=sim, laplacian=False)
    assert _err_mm(x, 1.07 * rest[1]) < 0.01  # model frame, the subject's own size


def test_nh_with_known_rest_joints(toy):
    model, rest, posed, poses = toy
    joints = np.stack([np.asarray(model.rest_joints(r)) for r in rest])
    u = normalize_posture_nh_batch(posed, poses, model, laplacian=False, rest_joints=joints)
    assert _err_mm(u, rest).max() < 1e-3


def test_wsx_recovers_rest_posture(toy):
    model, rest, posed, _ = toy
    base = _aligned_err_mm(posed, rest)
    ref = np.asarray(model.mean)  # the mean shape in the rest posture
    z = normalize_posture_wsx_batch(posed, model, reference=ref)
    err = _aligned_err_mm(z, rest)
    assert np.all(err < 0.25 * base), (err, base)
    # Identity: a mesh already in the reference posture and shape comes back unchanged.
    same = normalize_posture_wsx(rest[2], model, reference=rest[2])
    np.testing.assert_allclose(np.asarray(same), rest[2], atol=1e-9)
    # Default reference (Procrustes mean of the batch) runs and keeps the shapes close to rest.
    zd = normalize_posture_wsx_batch(posed, model)
    assert np.all(_aligned_err_mm(zd, rest) < base)


def test_posture_rig_carries_its_precomputation(toy):
    """The PostureRig holds the topology, the float64 rig and the factorised NH system; passing it
    gives exactly what passing the model gives, and separately built rigs share compiled kernels."""
    model, rest, posed, poses = toy
    rig = posture_rig(model)
    assert isinstance(rig.rig, bp.Rig) and rig.rig.skin_weights.dtype == jnp.float64
    assert rig.parents == model.parents and rig.topology.n_vertices == model.n_vertices
    np.testing.assert_array_equal(rig.faces, model.faces)
    assert isinstance(rig.nh_solver, bp.sscape.LaplacianSolver)
    assert (rig.anchor_threshold, rig.anchor_weight) == (0.8, 10.0)
    x_model = normalize_posture_nh_batch(posed, poses, model)
    np.testing.assert_array_equal(normalize_posture_nh_batch(posed, poses, rig), x_model)
    np.testing.assert_array_equal(
        normalize_posture_wsx_batch(posed, rig), normalize_posture_wsx_batch(posed, model)
    )
    # other anchor parameters than the rig's: a system factorised for the call, as from scratch
    other = normalize_posture_nh_batch(posed, poses, rig, anchor_weight=3.0)
    fresh = posture_rig(model, anchor_weight=3.0)
    assert fresh.nh_solver is not rig.nh_solver
    np.testing.assert_array_equal(
        other, normalize_posture_nh_batch(posed, poses, fresh, anchor_weight=3.0)
    )
    assert np.abs(other - x_model).max() > 1e-6
    # the jitted kernels see the rig without its solver: equal structure for separate rigs
    traced = rig._traced()
    assert traced.nh_solver is None
    assert jax.tree_util.tree_structure(rig) != jax.tree_util.tree_structure(traced)
    for other_rig in (fresh, posture_rig(model), posture_rig(model, factorize=False)):
        assert jax.tree_util.tree_structure(other_rig._traced()) == jax.tree_util.tree_structure(
            traced
        )
    assert posture_rig(model, factorize=False).nh_solver is None


@pytest.mark.bad_input
def test_learn_normalized_and_errors(toy):
    model, rest, posed, poses = toy
    m, norm = learn_normalized(posed, model, "nh", poses=poses, n_components=2)
    assert m.n_components == 2 and norm.shape == posed.shape
    with pytest.raises(ValueError, match="poses"):
        normalize_posture_nh_batch(posed, poses[:2], model)
    with pytest.raises(ValueError, match="meshes"):
        normalize_posture_wsx_batch(posed[:, :-1], model)
    with pytest.raises(ValueError, match="template"):
        posture_rig(object())
    with pytest.raises(ValueError, match="anchor_threshold"):
        posture_rig(model, anchor_threshold=1.5)

    with pytest.raises(ValueError, match="method"):
        learn_normalized(posed, model, "xyz")
    assert not np.any(np.isnan(jax.device_get(norm)))
