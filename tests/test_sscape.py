"""Tests for the S-SCAPE subpackage (model, learning, quality measures, serialisation, MPII I/O)."""

import json
import os
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from _toybody import make_toy_model
from helpers import central_difference

import bodyprior as bp
from bodyprior import Similarity, axis_angle_to_matrix, matrix_to_rotation
from bodyprior.sscape import (
    SScapeModel,
    compactness,
    evaluate,
    generalization,
    humanshape_pose,
    learn,
    load_model,
    load_mpii_humanshape,
    procrustes_align,
    rest_joints,
    save_model,
    shape_vertices,
    specificity,
    truncate,
    write_mpii_humanshape,
)

_evaluate = eqx.filter_jit(evaluate)


@pytest.fixture(scope="module")
def model():
    return make_toy_model(5)


def _random_rotation(key):
    return axis_angle_to_matrix(jr.normal(key, (3,)))


@eqx.filter_jit
def _low_rank_meshes(model, key, n=40, rigid=True):
    """Meshes drawn from the model's shape space (coefficients of zero sample mean), each moved by a
    random rigid motion."""
    k1, k2, k3 = jr.split(key, 3)
    coeffs = jr.normal(k1, (n, model.n_components))
    coeffs = coeffs - coeffs.mean(0)
    meshes = jax.vmap(lambda c: shape_vertices(model, c))(coeffs)
    if rigid:
        rots = jax.vmap(_random_rotation)(jr.split(k2, n))
        trans = jr.normal(k3, (n, 3))
        meshes = jnp.einsum("nij,nvj->nvi", rots, meshes) + trans[:, None]
    return meshes, coeffs


# ------------------------------------------------------------------------------------------------
# model and evaluate


def test_zero_pose_zero_shape_is_mean(model):
    v, j = _evaluate(model, jnp.zeros(5), jnp.zeros((4, 3)))
    np.testing.assert_allclose(v, model.mean, atol=1e-12)
    np.testing.assert_allclose(j, rest_joints(model, model.mean), atol=1e-12)
    # Fewer coefficients than components, and the method form.
    v2, _ = _evaluate(model, jnp.zeros(2), jnp.zeros((4, 3)))
    np.testing.assert_allclose(v2, model.mean, atol=1e-12)


def test_shape_coefficients(model, getkey):
    c = jr.normal(getkey(), (3,))
    expected = model.mean + sum(c[k] * model.stddev[k] * model.basis[k] for k in range(3))
    np.testing.assert_allclose(shape_vertices(model, c), expected, atol=1e-12)
    v, _ = _evaluate(model, c, jnp.zeros((4, 3)))
    np.testing.assert_allclose(v, expected, atol=1e-12)
    # basis is orthonormal in the flattened space
    b = model.basis.reshape(model.n_components, -1)
    np.testing.assert_allclose(b @ b.T, np.eye(model.n_components), atol=1e-12)


def test_joints_follow_shape(model, getkey):
    c = 3 * jr.normal(getkey(), (5,))
    verts = shape_vertices(model, c)
    _, joints = _evaluate(model, c, jnp.zeros((4, 3)))
    ring = verts[model.joint_regressor_indices[2]]
    np.testing.assert_allclose(joints[2], ring.mean(0), atol=1e-12)


@pytest.mark.parametrize("rep", ["matrix", "quaternion", "sixd", "euler_ZYX"])
def test_pose_representations_agree(model, getkey, rep):
    aa = 0.5 * jr.normal(getkey(), (4, 3))
    c = jr.normal(getkey(), (5,))
    ref = _evaluate(model, c, aa)
    mats = jax.vmap(axis_angle_to_matrix)(aa)
    other = jax.vmap(lambda m: matrix_to_rotation(m, rep))(mats)
    out = _evaluate(model, c, other, pose_rep=rep)
    for a, b in zip(ref, out):
        np.testing.assert_allclose(a, b, atol=1e-10)


def test_rigid_transform_commutes(model, getkey):
    c = jr.normal(getkey(), (5,))
    pose = 0.4 * jr.normal(getkey(), (4, 3))
    sim = Similarity.from_scale(_random_rotation(getkey()), jr.normal(getkey(), (3,)), 1.3)
    v, j = _evaluate(model, c, pose)
    vt, jt = _evaluate(model, c, pose, sim)
    np.testing.assert_allclose(vt, sim.apply(v), atol=1e-12)
    np.testing.assert_allclose(jt, sim.apply(j), atol=1e-12)
    # root translation is a pure translation
    vr, jr_ = _evaluate(model, c, pose, root_translation=jnp.array([0.1, -0.2, 0.3]))
    np.testing.assert_allclose(
        vr - v, jnp.broadcast_to(jnp.array([0.1, -0.2, 0.3]), v.shape), atol=1e-12
    )


def test_pose_moves_only_distal_segments(model):
    pose = jnp.zeros((4, 3)).at[3].set(jnp.array([1.0, 0.0, 0.0]))
    v, j = _evaluate(model, jnp.zeros(5), pose)
    w = np.zeros((model.n_vertices, model.n_joints))
    np.add.at(
        w,
        (np.arange(model.n_vertices)[:, None], np.asarray(model.skin_indices)),
        model.skin_weights,
    )
    untouched = w[:, 3] == 0
    np.testing.assert_allclose(v[untouched], model.mean[untouched], atol=1e-12)
    assert float(jnp.abs(v - model.mean).max()) > 0.05
    np.testing.assert_allclose(
        j, rest_joints(model, model.mean), atol=1e-12
    )  # joint 3 pivots in place


def test_jit_vmap_batch(model, getkey):
    f = eqx.filter_jit(evaluate)
    cs = jr.normal(getkey(), (8, 5))
    poses = 0.3 * jr.normal(getkey(), (8, 4, 3))
    vb, jb = eqx.filter_jit(eqx.filter_vmap(lambda c, p: evaluate(model, c, p)))(cs, poses)
    assert vb.shape == (8, model.n_vertices, 3) and jb.shape == (8, 4, 3)
    v3, j3 = f(model, cs[3], poses[3])
    np.testing.assert_allclose(vb[3], v3, atol=1e-12)
    np.testing.assert_allclose(jb[3], j3, atol=1e-12)


def test_no_recompilation(model, getkey):
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(m, c, p):
        return evaluate(m, c, p)

    f(model, jr.normal(getkey(), (5,)), jr.normal(getkey(), (4, 3)))
    f(model, jr.normal(getkey(), (5,)), jr.normal(getkey(), (4, 3)))
    f(model, jr.normal(getkey(), (5,)), jr.normal(getkey(), (4, 3)))


def test_gradients_match_finite_differences(model, getkey):
    c0 = jr.normal(getkey(), (5,))
    p0 = 0.5 * jr.normal(getkey(), (4, 3))
    target = jr.normal(getkey(), (model.n_vertices, 3))

    def loss(c, p):
        v, j = evaluate(model, c, p)
        return jnp.sum(v * target) + jnp.sum(j**2)

    loss = jax.jit(loss)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))
    gc, gp = grad(c0, p0)
    assert np.all(np.isfinite(gc)) and np.all(np.isfinite(gp))
    dc, dp = jr.normal(getkey(), c0.shape), jr.normal(getkey(), p0.shape)
    fd = central_difference(lambda t: loss(c0 + t * dc, p0 + t * dp), 0.0, 1.0)
    np.testing.assert_allclose(jnp.sum(gc * dc) + jnp.sum(gp * dp), fd, rtol=1e-6, atol=1e-7)
    # finite gradient at the zero pose (degenerate axis-angle)
    _, gp0 = grad(c0, jnp.zeros((4, 3)))
    assert np.all(np.isfinite(gp0))


@pytest.mark.bad_input
def test_input_validation(model):
    with pytest.raises(ValueError, match="shape_coeffs"):
        evaluate(model, jnp.zeros(6), jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="pose"):
        evaluate(model, jnp.zeros(5), jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        evaluate(model, jnp.full(5, jnp.nan), jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="pose"):
        evaluate(model, jnp.zeros(5), jnp.zeros((4, 3)).at[0, 0].set(jnp.inf))
    with pytest.raises(ValueError, match="pose_rep"):
        evaluate(model, jnp.zeros(5), jnp.zeros((4, 3)), pose_rep="euler")
    with pytest.raises(ValueError, match="root_translation"):
        evaluate(model, jnp.zeros(5), jnp.zeros((4, 3)), root_translation=jnp.zeros(2))
    with pytest.raises(ValueError, match="transform"):
        evaluate(model, jnp.zeros(5), jnp.zeros((4, 3)), transform=jnp.eye(4))
    with pytest.raises(ValueError, match="basis"):
        eqx.tree_at(lambda m: m.basis, model, model.basis[:, :10]).__check_init__()
    with pytest.raises(ValueError, match="skin_indices"):
        _with_rig(model, skin_indices=model.rig.skin_indices + 10)
    with pytest.raises(ValueError, match="joint_names"):
        _with_rig(model, joint_names=("a",))
    with pytest.raises(ValueError, match="regressor_indices"):
        _with_rig(model, regressor_indices=model.rig.regressor_indices + model.n_vertices)
    with pytest.raises(ValueError, match="`rig` must skin"):
        small = bp.Rig(**{**_rig_fields(model.rig), "skin_indices": model.rig.skin_indices[:10],
                          "skin_weights": model.rig.skin_weights[:10],
                          "regressor_indices": model.rig.regressor_indices % 10})  # fmt: skip
        SScapeModel(**{f: getattr(model, f) for f in _FIELDS[:5]}, rig=small)
    with pytest.raises(ValueError, match="`rig` must be"):
        SScapeModel(**{f: getattr(model, f) for f in _FIELDS[:5]}, rig=None)


# The leaves of a saved model, under their file (and former field) names.
_FIELDS = [
    "mean", "basis", "stddev", "explained_variance", "faces", "joint_regressor_indices",
    "joint_regressor_weights", "skin_indices", "skin_weights", "parents", "joint_names",
]  # fmt: skip
_RIG_FIELDS = (
    "parents", "joint_names", "skin_indices", "skin_weights", "regressor_indices",
    "regressor_weights",
)  # fmt: skip


def _rig_fields(rig):
    return {f: getattr(rig, f) for f in _RIG_FIELDS}


def _with_rig(model, **changes):
    rig = bp.Rig(**{**_rig_fields(model.rig), **changes})
    return SScapeModel(**{f: getattr(model, f) for f in _FIELDS[:5]}, rig=rig)


def test_rig_module(model):
    rig = model.rig
    assert isinstance(rig, bp.Rig) and rig.n_joints == 4 and rig.n_vertices == model.n_vertices
    # the former field names read the rig
    assert model.parents == rig.parents and model.joint_names == rig.joint_names
    assert model.skin_indices is rig.skin_indices and model.skin_weights is rig.skin_weights
    assert model.joint_regressor_indices is rig.regressor_indices
    assert model.joint_regressor_weights is rig.regressor_weights
    assert rig.skin_indices.dtype == jnp.int32 and rig.regressor_indices.dtype == jnp.int32
    v = model.shape_vertices(jnp.ones(2))
    np.testing.assert_array_equal(rig.regress_joints(v), model.rest_joints(v))
    a = jnp.broadcast_to(jnp.eye(4), (4, 4, 4)).at[2, :3, 3].set(jnp.array([0.1, 0.0, 0.0]))
    np.testing.assert_array_equal(rig.skin(v, a), bp.lbs(v, rig.skin_indices, rig.skin_weights, a))
    moved = np.asarray(rig.skin(v, a, method="dqs")) - np.asarray(v)
    assert np.abs(moved[:, 0]).max() > 0.09 and np.abs(moved[:, 1:]).max() < 1e-9
    with pytest.raises(ValueError, match="method"):
        rig.skin(v, a, method="xyz")
    with pytest.raises(ValueError, match="parents"):
        bp.Rig(**{**_rig_fields(rig), "parents": (-1, 0, 1, -1)})
    assert rig.astype(jnp.float32).skin_weights.dtype == jnp.float32


def test_truncate(model):
    t = truncate(model, 2)
    assert t.n_components == 2 and t.stddev.shape == (2,) and t.explained_variance.shape == (2,)
    np.testing.assert_allclose(t.basis, model.basis[:2])
    with pytest.raises(ValueError, match="n_components"):
        truncate(model, 6)


# ------------------------------------------------------------------------------------------------
# learning


def _principal_angles(a, b):
    qa, _ = np.linalg.qr(np.asarray(a).reshape(a.shape[0], -1).T)
    qb, _ = np.linalg.qr(np.asarray(b).reshape(b.shape[0], -1).T)
    s = np.linalg.svd(qa.T @ qb, compute_uv=False)
    return np.arccos(np.clip(s, -1, 1))


def test_procrustes_recovers_rigid_motion(model, getkey):
    meshes, _ = _low_rank_meshes(model, getkey(), n=10)
    aligned, t = procrustes_align(meshes)
    # aligned[i] = t[i](meshes[i]) and all aligned meshes share one frame: the aligned set,
    # re-aligned,
    # is unchanged.
    np.testing.assert_allclose(jax.vmap(lambda s, x: s.apply(x))(t, meshes), aligned, atol=1e-10)
    again, _ = procrustes_align(aligned, reference=aligned.mean(0))
    np.testing.assert_allclose(again, aligned, atol=1e-6)
    np.testing.assert_allclose(aligned.mean(axis=(0, 1)), 0, atol=1e-10)
    # exact copies under rigid motion align onto each other
    base = model.mean
    rots = jax.vmap(_random_rotation)(jr.split(getkey(), 5))
    copies = jnp.einsum("nij,vj->nvi", rots, base) + jr.normal(getkey(), (5, 1, 3))
    al, _ = procrustes_align(copies)
    np.testing.assert_allclose(al - al[0], 0, atol=1e-9)


def test_learn_recovers_subspace_and_variances(model, getkey):
    n = 100
    meshes, coeffs = _low_rank_meshes(model, getkey(), n=n)
    learned = learn(meshes, model.faces, n_components=5, template=model)
    angles = _principal_angles(learned.basis, model.basis)
    assert angles.max() < 1e-6  # arccos resolves ~1e-8 near 0
    # Sample variances of the generating coefficients, projected onto the learned directions.
    expected = np.sort(np.linalg.eigvalsh(np.cov(np.asarray(coeffs * model.stddev).T)))[::-1]
    np.testing.assert_allclose(learned.stddev**2, expected, rtol=1e-6)
    np.testing.assert_allclose(learned.explained_variance.sum(), 1.0, atol=1e-8)
    # Frame and rig come from the template: the learned mean sits on the template mean.
    np.testing.assert_allclose(learned.mean, model.mean, atol=1e-9)
    assert learned.parents == model.parents
    np.testing.assert_array_equal(learned.skin_indices, model.skin_indices)
    # 5 true components out of n-1 possible: the rest explain nothing.
    full = learn(meshes, model.faces, template=model)
    assert full.n_components == n - 1
    np.testing.assert_allclose(full.explained_variance[5:], 0, atol=1e-10)


def test_learn_with_missing_data_recovers_the_space(model, getkey):
    # meshes of the model's 5-D space with a block of vertices per mesh replaced by junk (what a
    # fitter's prior fills in over a scan hole): PCA on every vertex learns the junk, PCA with
    # missing data (EM over the unobserved vertices) recovers the space from the observed ones
    n, v = 40, model.n_vertices
    meshes, _ = _low_rank_meshes(model, getkey(), n=n, rigid=False)
    rng = np.random.default_rng(0)
    observed = np.ones((n, v), bool)
    for i in range(n):
        start = rng.integers(0, v - v // 5)
        observed[i, start : start + v // 5] = False  # a fifth of the mesh unseen
    junk = np.where(observed[..., None], np.asarray(meshes), rng.normal(0, 0.02, (n, v, 3)))
    plain = learn(junk, model.faces, n_components=5, align=False)
    em = learn(junk, model.faces, n_components=5, align=False, observed=observed)
    assert _principal_angles(plain.basis, model.basis).max() > 0.1
    assert _principal_angles(em.basis, model.basis).max() < 1e-4
    np.testing.assert_allclose(em.mean, np.asarray(meshes).mean(0), atol=1e-6)


@pytest.mark.bad_input
def test_learn_with_missing_data_bad_input(model, getkey):
    n, v = 6, model.n_vertices
    junk, _ = _low_rank_meshes(model, getkey(), n=n, rigid=False)
    observed = np.ones((n, v), bool)
    with pytest.raises(ValueError, match="n_components"):
        learn(junk, model.faces, align=False, observed=observed)
    with pytest.raises(ValueError, match="observed"):
        learn(junk, model.faces, n_components=5, observed=observed[:, :10])
    with pytest.raises(ValueError, match="observed"):
        learn(junk, model.faces, n_components=5, observed=observed.astype(float))
    none_seen = observed.copy()
    none_seen[:, 0] = False
    with pytest.raises(ValueError, match="observed in no mesh"):
        learn(junk, model.faces, n_components=5, observed=none_seen)


def test_learn_explained_variance_selection(model, getkey):
    meshes, _ = _low_rank_meshes(model, getkey(), n=30, rigid=False)
    full = learn(meshes, model.faces, align=False)
    cum = np.cumsum(np.asarray(full.explained_variance))
    for thr in (0.5, 0.9, 0.99, 1.0):
        m = learn(meshes, model.faces, explained_variance=thr, align=False)
        k = m.n_components
        assert cum[k - 1] >= thr - 1e-9 and (k == 1 or cum[k - 2] < thr)
    # no rig given: one root joint at the centroid carrying every vertex
    assert full.parents == (-1,) and full.skin_weights.shape == (model.n_vertices, 1)
    with pytest.raises(ValueError, match="at most one"):
        learn(meshes, model.faces, n_components=2, explained_variance=0.9)
    with pytest.raises(ValueError, match="n_components"):
        learn(meshes, model.faces, n_components=30)
    with pytest.raises(ValueError, match="explained_variance"):
        learn(meshes, model.faces, explained_variance=1.5)
    with pytest.raises(ValueError, match="meshes"):
        learn(meshes[:1], model.faces)


# ------------------------------------------------------------------------------------------------
# quality measures


def test_compactness(model):
    c = compactness(model, n_samples=100)
    np.testing.assert_allclose(c.ratio, np.cumsum(model.explained_variance))
    np.testing.assert_allclose(c.std_error, np.sqrt(2 / 100) * np.cumsum(model.stddev**2))
    assert np.all(np.diff(c.ratio) >= 0)


def test_generalization(model, getkey):
    meshes, _ = _low_rank_meshes(model, getkey(), n=16, rigid=False)
    noisy = meshes + 1e-3 * jr.normal(getkey(), meshes.shape)
    g = generalization(noisy, [0, 1, 2, 3, 5, 8], chunk_size=4)
    assert g.errors.shape == (16, 6)
    assert np.all(np.diff(np.asarray(g.mean)) < 0)
    # Noise-free data of rank 5: leave-one-out reconstruction with 5 components is exact.
    g0 = generalization(meshes, [2, 5])
    assert float(g0.mean[1]) / 1e3 < 1e-9 < float(g0.mean[0]) / 1e3  # mm -> m
    # Brute-force check of one left-out mesh against a direct SVD.
    x = np.asarray(noisy).reshape(16, -1)
    others = np.delete(x, 3, axis=0)
    mu = others.mean(0)
    _, _, vt = np.linalg.svd(others - mu, full_matrices=False)
    r = (x[3] - mu) - vt[:2].T @ (vt[:2] @ (x[3] - mu))
    np.testing.assert_allclose(
        g.errors[3, 2] / 1e3, np.linalg.norm(r.reshape(-1, 3), axis=1).mean(), rtol=1e-8
    )  # errors in mm, meshes in metres
    gs = generalization(noisy, 3, n_train=8)
    assert gs.errors.shape == (16, 1)
    with pytest.raises(ValueError, match="n_components"):
        generalization(noisy, [15])


def test_quality_measures_report_mm(model, getkey):
    """Regression: generalization / specificity / reconstruction_error returned metres while every
    other reported error is in mm. With M = 0 the reconstruction is the mean, so each is 1000 x a
    mean vertex distance computed here in metres."""
    from bodyprior.sscape import reconstruction_error

    meshes, _ = _low_rank_meshes(model, getkey(), n=6, rigid=False)
    x = np.asarray(meshes)
    d = lambda a, b: np.linalg.norm(a - b, axis=-1).mean()  # noqa: E731
    g = generalization(meshes, [0])
    loo = [d(x[j], np.delete(x, j, 0).mean(0)) for j in range(6)]
    np.testing.assert_allclose(g.errors[:, 0], 1e3 * np.asarray(loo), rtol=1e-10)
    np.testing.assert_allclose(g.mean, 1e3 * np.mean(loo), rtol=1e-10)
    learned = learn(meshes, model.faces, align=False)
    s = specificity(learned, meshes, [0, 1], key=getkey(), n_samples=3)
    mu = np.asarray(learned.mean)
    np.testing.assert_allclose(s.mean[0], 1e3 * min(d(mu, xi) for xi in x), rtol=1e-10)
    r = reconstruction_error(learned, meshes, [0], align=False)
    np.testing.assert_allclose(r[:, 0], 1e3 * np.array([d(xi, mu) for xi in x]), rtol=1e-10)


def test_specificity(model, getkey):
    meshes, _ = _low_rank_meshes(model, getkey(), n=30, rigid=False)
    learned = learn(meshes, model.faces, align=False)
    key = getkey()
    s = specificity(learned, meshes, [0, 1, 3, 5], key=key, n_samples=64, chunk_size=16)
    assert s.distances.shape == (64, 4)
    # M = 0: every sample is the mean
    d_mean = jnp.min(
        jax.vmap(lambda x: jnp.mean(jnp.linalg.norm(x - learned.mean, axis=-1)))(meshes)
    )
    np.testing.assert_allclose(s.distances[:, 0] / 1e3, d_mean, rtol=1e-10)  # mm -> m
    # Brute force for a few samples: ML Gaussian of the projected training data, nearest neighbour.
    x = np.asarray(meshes).reshape(30, -1)
    b = np.asarray(learned.basis).reshape(learned.n_components, -1)[:5]
    coeffs = (x - np.asarray(learned.mean).reshape(-1)) @ b.T
    lam, u = np.linalg.eigh(np.cov(coeffs.T, bias=True))
    u = u * np.where(u[np.argmax(np.abs(u), axis=0), np.arange(5)] < 0, -1.0, 1.0)
    z = np.asarray(jr.normal(key, (64, 5)))
    samples = coeffs.mean(0) + (z * np.sqrt(np.maximum(lam, 0))) @ u.T
    for i in range(0, 64, 21):
        for col, m in enumerate((0, 1, 3, 5)):
            y = np.asarray(learned.mean).reshape(-1) + samples[i, :m] @ b[:m]
            d = np.linalg.norm((x - y).reshape(30, -1, 3), axis=-1).mean(-1)
            np.testing.assert_allclose(s.distances[i, col] / 1e3, d.min(), rtol=1e-8)
    # A sample that is a training shape is at distance zero: a model whose samples all coincide with
    # the one training mesh it was built from.
    one = learn(jnp.stack([meshes[0], meshes[0]]), model.faces, align=False)
    s1 = specificity(one, meshes[:1], [0, 1], key=key, n_samples=4)
    np.testing.assert_allclose(s1.mean / 1e3, 0, atol=1e-12)
    with pytest.raises(ValueError, match="n_components"):
        specificity(learned, meshes, [learned.n_components + 1], key=getkey())


def test_progress_blocks_give_the_same_result(model, getkey, capsys):
    """`progress=True` runs generalization and specificity in padded blocks of 64 rows under a tqdm
    bar: the same numbers as the single call (70 rows: one full block and one padded block)."""
    meshes, _ = _low_rank_meshes(model, getkey(), n=70, rigid=False)
    noisy = meshes + 1e-3 * jr.normal(getkey(), meshes.shape)
    g0 = generalization(noisy, [1, 4], chunk_size=8)
    g1 = generalization(noisy, [1, 4], chunk_size=8, progress=True)
    np.testing.assert_allclose(g1.errors, g0.errors, rtol=1e-10)
    learned = learn(noisy, model.faces, align=False)
    key = getkey()
    s0 = specificity(learned, noisy, [0, 3], key=key, n_samples=70, chunk_size=16)
    s1 = specificity(learned, noisy, [0, 3], key=key, n_samples=70, chunk_size=16, progress=True)
    np.testing.assert_allclose(s1.distances, s0.distances, rtol=1e-10)
    err = capsys.readouterr().err
    assert "generalization" in err and "specificity" in err and "70/70" in err


# ------------------------------------------------------------------------------------------------
# serialisation


def test_save_load_round_trip(model, tmp_path):
    path = tmp_path / "toy.sscape"
    save_model(path, model)
    loaded = load_model(path)
    assert loaded.parents == model.parents and loaded.joint_names == model.joint_names
    for f in _FIELDS[:9]:
        a, b = np.asarray(getattr(model, f)), np.asarray(getattr(loaded, f))
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), f
    assert sorted(os.listdir(tmp_path)) == ["toy.sscape"]  # no temp files left behind
    assert isinstance(loaded.rig, bp.Rig)
    save_model(path, truncate(model, 2))  # overwrite atomically
    assert load_model(path).n_components == 2
    assert sorted(os.listdir(tmp_path)) == ["toy.sscape"]


def test_load_file_written_before_the_rig_module(tmp_path):
    """`tests/data/sscape_v1_toy.sscape` was written by `save_model` before SScapeModel held a Rig
    (commit 35d51cb, `make_toy_model(2, n_around=6, n_rings=6, n_joints=3)`); it loads into the
    same model, and today's writer writes the same leaves and metadata."""
    path = os.path.join(os.path.dirname(__file__), "data", "sscape_v1_toy.sscape")
    old = load_model(path)
    now = make_toy_model(2, n_around=6, n_rings=6, n_joints=3)
    assert isinstance(old.rig, bp.Rig) and old.parents == now.parents == (-1, 0, 1)
    assert old.joint_names == now.joint_names
    for f in _FIELDS[:9]:
        a, b = np.asarray(getattr(old, f)), np.asarray(getattr(now, f))
        assert a.dtype == b.dtype and a.shape == b.shape, f
        # Float leaves to rounding: the toy model is rebuilt on this CPU, and XLA's vector width
        # (AVX2 vs AVX-512) changes the last bits (seen: byte-equal on one machine, not another).
        if a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13, err_msg=f)
        else:
            np.testing.assert_array_equal(a, b, err_msg=f)
    with zipfile.ZipFile(path) as z:
        old_meta, old_leaves = json.loads(z.read("metadata.json")), z.read("leaves.eqx")
    save_model(tmp_path / "again.sscape", old)
    with zipfile.ZipFile(tmp_path / "again.sscape") as z:
        assert json.loads(z.read("metadata.json")) == old_meta
        assert z.read("leaves.eqx") == old_leaves


@pytest.mark.bad_input
def test_learn_rig_argument_and_deprecated_spellings(model, getkey):
    meshes, _ = _low_rank_meshes(model, getkey(), n=6)
    ref = learn(meshes, model.faces, n_components=2, rig=model.rig)
    assert ref.rig is model.rig
    old = {"parents": model.parents, "joint_names": model.joint_names,
           "joint_regressor_indices": model.joint_regressor_indices,
           "joint_regressor_weights": model.joint_regressor_weights,
           "skin_indices": model.skin_indices, "skin_weights": model.skin_weights}  # fmt: skip
    with pytest.warns(DeprecationWarning, match="rig"):
        legacy = learn(meshes, model.faces, n_components=2, **old)
    assert eqx.tree_equal(legacy.rig, model.rig) and legacy.parents == model.parents
    np.testing.assert_array_equal(legacy.basis, ref.basis)
    with pytest.raises(ValueError, match="missing"):
        learn(meshes, model.faces, parents=model.parents)
    with pytest.raises(ValueError, match="not both"):
        learn(meshes, model.faces, rig=model.rig, template=model)
    with pytest.raises(ValueError, match="`rig` must be"):
        learn(meshes, model.faces, rig=dict(parents=(-1,)))
    with pytest.raises(TypeError, match="unexpected"):
        learn(meshes, model.faces, skin=1)


def _rewrite(path, out, *, meta=None, payload=None):
    with zipfile.ZipFile(path) as zf:
        m, p = zf.read("metadata.json"), zf.read("leaves.eqx")
    if meta is not None:
        d = json.loads(m)
        meta(d)
        m = json.dumps(d).encode()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("metadata.json", m)
        zf.writestr("leaves.eqx", p if payload is None else payload(p))


def test_load_rejects_bad_files(model, tmp_path):
    path = tmp_path / "toy.sscape"
    save_model(path, model)
    bad = tmp_path / "bad.sscape"
    _rewrite(path, bad, meta=lambda d: d.update(version=2))
    with pytest.raises(ValueError, match="version"):
        load_model(bad)
    _rewrite(path, bad, meta=lambda d: d.update(format="other.format"))
    with pytest.raises(ValueError, match="format"):
        load_model(bad)
    _rewrite(path, bad, payload=lambda p: p[:100] + bytes([p[100] ^ 0xFF]) + p[101:])
    with pytest.raises(ValueError, match="checksum"):
        load_model(bad)
    _rewrite(path, bad, meta=lambda d: d["leaves"]["stddev"].update(shape=[4]))
    with pytest.raises(ValueError, match="stddev"):
        load_model(bad)
    _rewrite(path, bad, meta=lambda d: d["leaves"]["stddev"].update(dtype="<f4"))
    with pytest.raises(ValueError, match="stddev"):
        load_model(bad)
    _rewrite(path, bad, meta=lambda d: d.update(parents=[-1, 0]))
    with pytest.raises(ValueError, match="parents"):
        load_model(bad)
    bad.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError):
        load_model(bad)
    with pytest.raises(ValueError, match="no such file"):
        load_model(tmp_path / "missing.sscape")


def test_atomic_write_failure_leaves_no_temp(model, tmp_path, monkeypatch):
    path = tmp_path / "toy.sscape"
    save_model(path, model)
    before = path.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        save_model(path, truncate(model, 1))
    assert sorted(os.listdir(tmp_path)) == ["toy.sscape"]
    assert path.read_bytes() == before


# ------------------------------------------------------------------------------------------------
# MPII humanshape format


@pytest.fixture(scope="module")
def tiny():
    # 6 x 8 rings + 2 caps = 50 vertices, 3 components, 4 joints
    return make_toy_model(3, n_around=6, n_rings=8, n_joints=4, seed=1)


def _overlap_regressor(model):
    w = np.zeros((model.n_vertices, model.n_joints))
    np.add.at(
        w,
        (np.arange(model.n_vertices)[:, None], np.asarray(model.skin_indices)),
        np.asarray(model.skin_weights),
    )
    rows = []
    for j, p in enumerate(model.parents):
        r = w[:, j] if p < 0 else np.minimum(w[:, j], w[:, p])
        rows.append(r / r.sum())
    return np.stack(rows)


def test_mpii_round_trip(tiny, tmp_path):
    axes = np.eye(3)[[0, 0, 1, 2]] * 1.0
    write_mpii_humanshape(tmp_path, tiny, axes=axes)
    assert sorted(os.listdir(tmp_path)) == [
        "evalues.mat",
        "evectors.mat",
        "meanShape.mat",
        "model.dat",
    ]
    with open(tmp_path / "model.dat") as f:
        assert f.readline().split() == ["50", str(tiny.faces.shape[0]), "4", "2"]
    loaded, rig = load_mpii_humanshape(tmp_path, center=False, return_rig=True)
    assert loaded.n_vertices == 50 and loaded.n_components == 3 and loaded.n_joints == 4
    np.testing.assert_allclose(loaded.mean, tiny.mean, atol=1e-12)
    np.testing.assert_allclose(loaded.basis, tiny.basis, atol=1e-12)
    np.testing.assert_allclose(loaded.stddev, tiny.stddev, rtol=1e-12)
    np.testing.assert_array_equal(loaded.faces, tiny.faces)
    assert loaded.parents == tiny.parents
    np.testing.assert_array_equal(rig.ids, [1, 2, 3, 4])
    np.testing.assert_allclose(rig.axes, axes)

    # Skin weights, densified, agree; the regressor is humanshape's overlap rule.
    def dense(idx, w, nj):
        d = np.zeros((idx.shape[0], nj))
        np.add.at(d, (np.arange(idx.shape[0])[:, None], np.asarray(idx)), np.asarray(w))
        return d

    np.testing.assert_allclose(
        dense(loaded.skin_indices, loaded.skin_weights, 4),
        dense(tiny.skin_indices, tiny.skin_weights, 4),
        atol=1e-8,
    )
    np.testing.assert_allclose(
        dense(loaded.joint_regressor_indices, loaded.joint_regressor_weights, 50),
        _overlap_regressor(tiny),
        atol=1e-8,
    )
    # centred load (humanshape's frame), truncated to 2 components, mm -> m
    centred = load_mpii_humanshape(tmp_path, n_components=2)
    np.testing.assert_allclose(centred.mean.mean(0), 0, atol=1e-9)
    assert centred.n_components == 2
    np.testing.assert_allclose(
        centred.explained_variance, tiny.stddev[:2] ** 2 / np.sum(tiny.stddev**2)
    )


def test_humanshape_pose_mapping(tiny, tmp_path, getkey):
    axes = np.array([[0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    write_mpii_humanshape(tmp_path, tiny, axes=axes)
    model, rig = load_mpii_humanshape(tmp_path, return_rig=True)
    vec = jnp.concatenate(
        [
            0.3 * jr.normal(getkey(), (3,)),
            100 * jr.normal(getkey(), (3,)),
            jnp.array([0.7]),
            0.5 * jr.normal(getkey(), (3,)),
            jnp.array([1.2]),
        ]
    )
    pose, sim = humanshape_pose(rig, vec)
    assert pose.shape == (4, 3)
    np.testing.assert_allclose(pose[0], 0)  # root: zero axis, dummy angle
    np.testing.assert_allclose(pose[2], vec[8] * axes[2])
    # Product of exponentials of rest-frame hinge twists (humanshape's kinematics), by hand.
    c = jnp.zeros(3)
    rest = shape_vertices(model, c)
    q = rest_joints(model, rest)
    ms = []
    for j in range(4):
        rj = axis_angle_to_matrix(pose[j])
        g = jnp.eye(4).at[:3, :3].set(rj).at[:3, 3].set((jnp.eye(3) - rj) @ q[j])
        ms.append(g if j == 0 else ms[model.parents[j]] @ g)
    w = np.zeros((50, 4))
    np.add.at(
        w, (np.arange(50)[:, None], np.asarray(model.skin_indices)), np.asarray(model.skin_weights)
    )
    hom = jnp.concatenate([rest, jnp.ones((50, 1))], axis=1)
    blended = jnp.einsum("vj,jab,vb->va", w, jnp.stack(ms), hom)[:, :3]
    s = vec[-1]
    expected = s * (blended @ axis_angle_to_matrix(vec[:3]).T + vec[3:6] * 1e-3)
    v, _ = _evaluate(model, c, pose, sim)
    np.testing.assert_allclose(v, expected, atol=1e-12)
    with pytest.raises(ValueError, match="pose_vector"):
        humanshape_pose(rig, jnp.zeros(5))


# humanshape's released 25-joint tree (1-based id: parent id) and its 15 skinned segments.
_HS_PARENTS = {
    1: 0, 24: 1, 2: 24, 3: 2, 4: 3, 5: 4, 23: 1, 6: 23, 7: 6, 8: 7, 9: 8, 10: 1, 25: 10, 11: 25,
    12: 11, 13: 11, 14: 13, 15: 14, 16: 15, 17: 16, 18: 11, 19: 18, 20: 19, 21: 20, 22: 21,
}  # fmt: skip
_HS_SEGMENTS = {1: 0, 3: 1, 4: 3, 5: 4, 7: 1, 8: 7, 9: 8, 11: 1, 12: 11, 15: 11, 16: 15, 17: 16,
                20: 11, 21: 20, 22: 21}  # fmt: skip  (segment: nearest skinned ancestor)


def _write_synthetic_humanshape(directory, seed=0):
    """A humanshape-format directory with the released rig's joint tree (synthetic geometry)."""
    import scipy.io

    rng = np.random.default_rng(seed)
    pairs = []  # per vertex: [(id, w), (id, w)]
    for seg, par in _HS_SEGMENTS.items():
        for _ in range(6):
            pairs.append([(seg, 1.0), (1, 0.0)])
        if par:
            for w in (0.3, 0.5, 0.7):
                pairs.append([(seg, w), (par, 1.0 - w)])
    nv = len(pairs)
    verts = rng.normal(0.0, 300.0, (nv, 3))
    faces = np.stack([np.arange(nv), np.roll(np.arange(nv), 1), np.roll(np.arange(nv), 2)], 1)
    lines = [f"{nv} {nv} 25 2"]
    for v, pr in zip(verts, pairs):
        lines.append(" ".join(f"{x:f}" for x in v) + " " + " ".join(f"{j} {w}" for j, w in pr))
    lines += [f"{a} {b} {c}" for a, b, c in faces]
    for jid in range(1, 26):
        ax = rng.normal(size=3)
        ax /= np.linalg.norm(ax)
        q = rng.normal(0.0, 300.0, 3)
        lines.append(f"{jid} {ax[0]} {ax[1]} {ax[2]} {q[0]} {q[1]} {q[2]} {_HS_PARENTS[jid]}")
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, "model.dat"), "w") as f:
        f.write("\n".join(lines) + "\n")
    q, _ = np.linalg.qr(rng.normal(size=(3 * nv, 3)))
    scipy.io.savemat(os.path.join(directory, "evectors.mat"), {"evectors": q.T})
    scipy.io.savemat(os.path.join(directory, "evalues.mat"), {"evalues": [[900.0, 400.0, 100.0]]})


def test_mpii_round_trip_keeps_humanshape_ids(tmp_path):
    """Regression: the writer renumbered joints as model index + 1, so a humanshape model read
    back with its joints relabelled (e.g. thorax_z as l_hip_x)."""

    def dense(idx, w, n):
        d = np.zeros((idx.shape[0], n))
        np.add.at(d, (np.arange(idx.shape[0])[:, None], np.asarray(idx)), np.asarray(w))
        return d

    _write_synthetic_humanshape(tmp_path / "src")
    a, rig_a = load_mpii_humanshape(tmp_path / "src", return_rig=True)
    assert a.joint_names[1] == "thorax_z" and rig_a.ids[1] == 10
    for kwargs in ({}, {"ids": rig_a.ids}):  # ids from the joint names, or given
        out = tmp_path / f"out{len(kwargs)}"
        write_mpii_humanshape(out, a, axes=rig_a.axes, **kwargs)
        b, rig_b = load_mpii_humanshape(out, return_rig=True)
        assert b.joint_names == a.joint_names
        assert b.parents == a.parents
        np.testing.assert_array_equal(rig_b.ids, rig_a.ids)
        np.testing.assert_allclose(rig_b.axes, rig_a.axes, atol=1e-12)
        nv = a.n_vertices
        np.testing.assert_allclose(
            dense(b.joint_regressor_indices, b.joint_regressor_weights, nv),
            dense(a.joint_regressor_indices, a.joint_regressor_weights, nv),
            atol=1e-12,
        )
        np.testing.assert_allclose(
            dense(b.skin_indices, b.skin_weights, 25),
            dense(a.skin_indices, a.skin_weights, 25),
            atol=1e-12,
        )
        np.testing.assert_allclose(b.mean, a.mean, atol=1e-8)
        np.testing.assert_allclose(b.basis, a.basis, atol=1e-12)
        np.testing.assert_allclose(b.stddev, a.stddev, rtol=1e-12)
    # A model of another tree that happens to have 25 joints is not given humanshape's roles.
    chain = make_toy_model(2, n_around=6, n_rings=30, n_joints=25, seed=2)
    write_mpii_humanshape(tmp_path / "chain", chain)
    c = load_mpii_humanshape(tmp_path / "chain")
    assert c.joint_names == tuple(f"joint{i}" for i in range(1, 26))
    with pytest.raises(ValueError, match="permutation"):
        write_mpii_humanshape(tmp_path / "bad", a, ids=np.arange(25))
    with pytest.raises(ValueError, match="depth-first"):
        write_mpii_humanshape(tmp_path / "bad", a, ids=np.arange(25, 0, -1))


def test_mpii_malformed(tiny, tmp_path):
    write_mpii_humanshape(tmp_path, tiny)
    dat = (tmp_path / "model.dat").read_text()
    (tmp_path / "model.dat").write_text(dat[: len(dat) // 2])
    with pytest.raises(ValueError, match="truncated"):
        load_mpii_humanshape(tmp_path)
    (tmp_path / "model.dat").write_text(dat.replace("50 ", "x50 ", 1))
    with pytest.raises(ValueError, match="non-numeric"):
        load_mpii_humanshape(tmp_path)
    (tmp_path / "model.dat").write_text(dat)
    import scipy.io

    scipy.io.savemat(tmp_path / "evectors.mat", {"evectors": np.ones((3, 10))})
    with pytest.raises(ValueError, match="evectors"):
        load_mpii_humanshape(tmp_path)
    scipy.io.savemat(tmp_path / "evectors.mat", {"wrong_name": np.ones((3, 150))})
    with pytest.raises(ValueError, match="no variable"):
        load_mpii_humanshape(tmp_path)
    (tmp_path / "evectors.mat").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 600)
    with pytest.raises(ValueError, match="v7.3|HDF5"):
        load_mpii_humanshape(tmp_path)
    (tmp_path / "evectors.mat").write_bytes(b"garbage" * 20)
    with pytest.raises(ValueError, match="evectors.mat"):
        load_mpii_humanshape(tmp_path)
    os.remove(tmp_path / "evectors.mat")
    with pytest.raises(ValueError, match="Missing"):
        load_mpii_humanshape(tmp_path)
    with pytest.raises(ValueError, match="directory"):
        load_mpii_humanshape(tmp_path / "nope")


@pytest.mark.bad_input
def test_evaluate_subset_equals_full_rows(model, getkey):
    c = jr.normal(getkey(), (5,))
    pose = 0.4 * jr.normal(getkey(), (4, 3))
    sim = Similarity.from_scale(_random_rotation(getkey()), jr.normal(getkey(), (3,)), 0.9)
    idx = jnp.array([0, 3, 3, model.n_vertices - 1])
    v, j = evaluate(model, c, pose, sim)
    vs, js = evaluate(model, c, pose, sim, subset=idx)
    assert vs.shape == (4, 3)
    np.testing.assert_allclose(vs, v[idx], atol=1e-12)
    np.testing.assert_allclose(js, j, atol=1e-12)
    with pytest.raises(ValueError, match="subset"):
        evaluate(model, c, pose, subset=jnp.array([0.5, 1.0]))
