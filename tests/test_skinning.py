"""Tests for bodyprior._skinning: sparse LBS, top-k conversion, dual-quaternion skinning."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bodyprior import (
    axis_angle_to_matrix,
    dense_weights_to_topk,
    dqs,
    forward_kinematics,
    lbs,
    transform_to_dual_quaternion,
)

SETTINGS = settings(deadline=None, max_examples=25)
PARENTS = (-1, 0, 1, 0, 3, 2)  # small tree
J, V, K = len(PARENTS), 40, 3

lbs_j = jax.jit(lbs)
dqs_j = jax.jit(dqs)


def rigid(rng, scale=1.0):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(scale * rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def setup(seed, k=K):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(V, 3))
    idx, w = dense_weights_to_topk(rng.random((V, J)) ** 3, k)
    h = rng.normal(size=(J, 3))
    return rng, x, idx, w, h


@jax.jit
def posed_transforms(aa, h):
    return forward_kinematics(PARENTS, jax.vmap(axis_angle_to_matrix)(aa), h, jnp.zeros(3))[0]


def dense_lbs_reference(x, idx, w, T):
    W = np.zeros((x.shape[0], T.shape[0]))
    np.put_along_axis(W, idx, w, axis=1)
    M = np.einsum("vj,jab->vab", W, T)
    return np.einsum("vab,vb->va", M[:, :3, :3], x) + M[:, :3, 3]


def test_zero_pose_gives_rest_mesh():
    _, x, idx, w, h = setup(0)
    A = posed_transforms(jnp.zeros((J, 3)), h)
    np.testing.assert_allclose(lbs_j(x, idx, w, A), x, atol=1e-14)
    np.testing.assert_allclose(dqs_j(x, idx, w, A), x, atol=1e-14)


@SETTINGS
@given(st.integers(0, 2**31 - 1))
def test_lbs_matches_dense_reference_and_commutes_with_rigid(seed):
    rng, x, idx, w, h = setup(seed)
    A = np.asarray(posed_transforms(rng.normal(size=(J, 3)), h))
    out = lbs_j(x, idx, w, A)
    np.testing.assert_allclose(out, dense_lbs_reference(x, idx, w, A), atol=1e-12)
    T = rigid(rng)
    moved = lbs_j(x, idx, w, np.einsum("ab,jbc->jac", T, A))
    np.testing.assert_allclose(moved, np.asarray(out) @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    # DQS commutes with a global rigid transform too
    out_d = dqs_j(x, idx, w, A)
    moved_d = dqs_j(x, idx, w, np.einsum("ab,jbc->jac", T, A))
    np.testing.assert_allclose(moved_d, np.asarray(out_d) @ T[:3, :3].T + T[:3, 3], atol=1e-10)


def test_k1_is_rigid_per_bone():
    rng, x, idx, w, _ = setup(1, k=1)
    np.testing.assert_allclose(w, 1.0)
    T = np.stack([rigid(rng) for _ in range(J)])
    expected = np.einsum("vab,vb->va", T[idx[:, 0], :3, :3], x) + T[idx[:, 0], :3, 3]
    np.testing.assert_allclose(lbs_j(x, idx, w, T), expected, atol=1e-12)
    np.testing.assert_allclose(dqs_j(x, idx, w, T), expected, atol=1e-12)


def test_dqs_equals_lbs_for_shared_transform_and_single_bone():
    rng, x, idx, w, _ = setup(2)
    T = rigid(rng, scale=2.0)
    A = np.broadcast_to(T, (J, 4, 4))
    np.testing.assert_allclose(dqs_j(x, idx, w, A), lbs_j(x, idx, w, A), atol=1e-12)
    one = np.zeros((V, 2), np.int32)
    half = np.full((V, 2), 0.5)
    np.testing.assert_allclose(
        dqs_j(x, one, half, T[None]), lbs_j(x, one, half, T[None]), atol=1e-12
    )


def test_dqs_antipodal_blend_and_volume():
    # Two bones at the origin rotating by +170° and -170° about Z: canonical quaternions are nearly
    # antipodal; without sign alignment the blend would collapse to the identity.
    T = np.stack([np.eye(4), np.eye(4)])
    T[0, :3, :3] = Rotation.from_rotvec([0, 0, np.deg2rad(170)]).as_matrix()
    T[1, :3, :3] = Rotation.from_rotvec([0, 0, np.deg2rad(190)]).as_matrix()
    x = np.array([[1.0, 0.0, 0.0]])
    idx = np.array([[0, 1]], np.int32)
    w = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(dqs_j(x, idx, w, T), [[-1.0, 0.0, 0.0]], atol=1e-12)
    # twist: DQS keeps the distance to the axis, LBS collapses it ("candy wrapper")
    T[0, :3, :3] = Rotation.from_rotvec([0, 0, np.deg2rad(80)]).as_matrix()
    T[1, :3, :3] = Rotation.from_rotvec([0, 0, np.deg2rad(-80)]).as_matrix()
    np.testing.assert_allclose(np.linalg.norm(dqs_j(x, idx, w, T)), 1.0, atol=1e-12)
    assert np.linalg.norm(lbs_j(x, idx, w, T)) < 0.2


@pytest.mark.bad_input
def test_transform_to_dual_quaternion():
    rng = np.random.default_rng(3)
    T = rigid(rng)
    dq = transform_to_dual_quaternion(T)
    qr, qd = np.asarray(dq[:4]), np.asarray(dq[4:])
    np.testing.assert_allclose(np.linalg.norm(qr), 1.0, atol=1e-12)
    np.testing.assert_allclose(qr @ qd, 0.0, atol=1e-12)  # unit dual quaternion
    np.testing.assert_array_equal(transform_to_dual_quaternion(np.eye(4)), [1, 0, 0, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="transform"):
        transform_to_dual_quaternion(np.eye(3))


def test_gradients_finite_at_identity_and_random_pose():
    rng, x, idx, w, h = setup(4)
    target = rng.normal(size=(V, 3))

    def loss(aa):
        A = forward_kinematics(PARENTS, jax.vmap(axis_angle_to_matrix)(aa), h, jnp.zeros(3))[0]
        return jnp.sum((lbs(x, idx, w, A) - target) ** 2) + jnp.sum(
            (dqs(x, idx, w, A) - target) ** 2
        )

    grad = jax.jit(jax.grad(loss))
    for aa in (jnp.zeros((J, 3)), jnp.asarray(rng.normal(size=(J, 3)))):
        g = grad(aa)
        assert np.all(np.isfinite(g)) and np.any(g != 0)


def test_no_recompilation_on_new_values():
    _, x, idx, w, h = setup(5)

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(aa, x):
        A = posed_transforms(aa, h)
        return lbs(x, idx, w, A) + dqs(x, idx, w, A)

    rng = np.random.default_rng(0)
    for _ in range(3):
        assert np.all(np.isfinite(f(rng.normal(size=(J, 3)), rng.normal(size=(V, 3)))))


def test_vmap_over_bodies():
    rng, x, idx, w, h = setup(6)
    A = jax.vmap(posed_transforms, in_axes=(0, None))(rng.normal(size=(3, J, 3)), h)
    out = jax.jit(jax.vmap(lbs, in_axes=(None, None, None, 0)))(x, idx, w, A)
    for b in range(3):
        np.testing.assert_allclose(
            out[b], dense_lbs_reference(x, idx, w, np.asarray(A[b])), atol=1e-12
        )


@pytest.mark.bad_input
def test_dense_weights_to_topk():
    rng = np.random.default_rng(7)
    W = rng.random((10, 6))
    idx, w = dense_weights_to_topk(W, 2)
    assert idx.shape == (10, 2) and idx.dtype == np.int32 and w.shape == (10, 2)
    np.testing.assert_allclose(w.sum(1), 1.0)
    assert np.all(w[:, 0] >= w[:, 1])
    np.testing.assert_array_equal(idx[:, 0], W.argmax(1))
    # k = J keeps everything: sparse LBS equals dense LBS with normalised weights
    idx, w = dense_weights_to_topk(W, 6)
    T = np.stack([rigid(rng) for _ in range(6)])
    x = rng.normal(size=(10, 3))
    Wn = W / W.sum(1, keepdims=True)
    M = np.einsum("vj,jab->vab", Wn, T)
    np.testing.assert_allclose(
        lbs_j(x, idx, w, T), np.einsum("vab,vb->va", M[:, :3, :3], x) + M[:, :3, 3]
    )
    for bad_k in (0, 7, 1.5, True):
        with pytest.raises(ValueError, match="`k`"):
            dense_weights_to_topk(W, bad_k)
    with pytest.raises(ValueError, match="non-negative"):
        dense_weights_to_topk(-W, 2)
    with pytest.raises(ValueError, match="row 0"):
        dense_weights_to_topk(np.vstack([np.zeros(6), W]), 2)
    with pytest.raises(ValueError, match=r"\(V, J\)"):
        dense_weights_to_topk(W[0], 2)


@pytest.mark.bad_input
def test_wrong_inputs_raise():
    _, x, idx, w, _ = setup(8)
    T = np.broadcast_to(np.eye(4), (J, 4, 4))
    for fn in (lbs, dqs):
        with pytest.raises(ValueError, match="rest_vertices"):
            fn(x[:, :2], idx, w, T)
        with pytest.raises(ValueError, match="weights"):
            fn(x, idx, w[:, :2], T)
        with pytest.raises(ValueError, match="weight_indices"):
            fn(x, idx.astype(float), w, T)
        with pytest.raises(ValueError, match="weight_indices"):
            fn(x, idx + J, w, T)
        with pytest.raises(ValueError, match="transforms"):
            fn(x, idx, w, T[:, :3])
