"""Tests for bodyprior._kinematics: forward kinematics over a parent tree, Similarity, Umeyama."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bodyprior import (
    Similarity,
    axis_angle_to_matrix,
    forward_kinematics,
    kinematic_levels,
    umeyama,
    validate_parents,
    world_transforms,
)

SETTINGS = settings(deadline=None, max_examples=25)


def random_tree(rng, J):
    """Random tree with root 0 whose labels are shuffled, so parents[j] < j does not always hold."""
    canon = [-1] + [int(rng.integers(0, i)) for i in range(1, J)]
    perm = np.concatenate([[0], 1 + rng.permutation(J - 1)])  # canonical node c -> label perm[c]
    parents = [0] * J
    for c in range(J):
        parents[perm[c]] = -1 if canon[c] < 0 else int(perm[canon[c]])
    return tuple(parents)


def naive_fk(parents, R, h, trans):
    """Per-joint recursive reference in NumPy."""
    J = len(parents)
    G, t = [None] * J, [None] * J

    def visit(j):
        if G[j] is not None:
            return
        p = parents[j]
        if p < 0:
            G[j], t[j] = R[j], trans + h[j]
        else:
            visit(p)
            G[j] = G[p] @ R[j]
            t[j] = t[p] + G[p] @ (h[j] - h[p])

    for j in range(J):
        visit(j)
    A = np.zeros((J, 4, 4))
    for j in range(J):
        A[j, :3, :3] = G[j]
        A[j, :3, 3] = t[j] - G[j] @ h[j]
        A[j, 3, 3] = 1.0
    return A, np.stack(t)


def random_pose(rng, J, scale=1.0):
    return Rotation.from_rotvec(scale * rng.normal(size=(J, 3))).as_matrix()


# --------------------------------------------------------------------------------------------------
# forward kinematics

fk = jax.jit(forward_kinematics, static_argnums=0)


def test_zero_pose_gives_identity_transforms():
    rng = np.random.default_rng(0)
    parents = random_tree(rng, 12)
    h = rng.normal(size=(12, 3))
    eye = np.broadcast_to(np.eye(3), (12, 3, 3))
    A, t = fk(parents, eye, h, np.zeros(3))
    np.testing.assert_allclose(A, np.broadcast_to(np.eye(4), (12, 4, 4)), atol=1e-15)
    np.testing.assert_allclose(t, h, atol=1e-15)
    trans = np.array([0.1, -2.0, 0.5])
    A, t = fk(parents, eye, h, trans)
    np.testing.assert_allclose(t, h + trans, atol=1e-15)
    np.testing.assert_allclose(A[:, :3, :3], eye, atol=1e-15)
    np.testing.assert_allclose(A[:, :3, 3], np.broadcast_to(trans, (12, 3)), atol=1e-15)


def test_hand_computed_chain():
    parents = (-1, 0, 1)
    h = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    Rz90 = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    R = np.stack([Rz90, Rz90, np.eye(3)])
    A, t = fk(parents, R, h, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(t, [[0, 0, 1], [0, 1, 1], [-1, 1, 1]], atol=1e-15)
    Rz180 = Rz90 @ Rz90
    np.testing.assert_allclose(A[2, :3, :3], Rz180, atol=1e-15)
    np.testing.assert_allclose(A[2, :3, 3], [1, 1, 1], atol=1e-15)
    # a point one metre beyond joint 2 along +X at rest
    p = A[2] @ np.array([3.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(p[:3], [-2, 1, 1], atol=1e-15)
    np.testing.assert_allclose(A[:, 3], np.broadcast_to([0, 0, 0, 1.0], (3, 4)))


@pytest.mark.parametrize("seed", range(2))
def test_matches_naive_loop_on_random_31_joint_tree(seed):
    rng = np.random.default_rng(seed)
    J = 31
    parents = random_tree(rng, J)
    assert any(p > j for j, p in enumerate(parents))
    R = random_pose(rng, J)
    h = rng.normal(size=(J, 3))
    trans = rng.normal(size=3)
    A, t = fk(parents, R, h, trans)
    A_ref, t_ref = naive_fk(parents, R, h, trans)
    np.testing.assert_allclose(A, A_ref, atol=1e-12)
    np.testing.assert_allclose(t, t_ref, atol=1e-12)
    # A_j maps the rest head to the posed head, and world_transforms agrees.
    np.testing.assert_allclose(
        np.einsum("jab,jb->ja", A[:, :3, :3], h) + A[:, :3, 3], t, atol=1e-12
    )
    G, t2 = jax.jit(world_transforms, static_argnums=0)(parents, R, h, trans)
    np.testing.assert_allclose(G, A[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_kinematic_levels():
    rng = np.random.default_rng(3)
    parents = random_tree(rng, 31)
    levels = kinematic_levels(parents)
    assert kinematic_levels(list(parents)) is levels  # cached per tuple
    np.testing.assert_array_equal(levels[0], [0])
    np.testing.assert_array_equal(np.sort(np.concatenate(levels)), np.arange(31))
    for d in range(1, len(levels)):
        assert set(np.asarray(parents)[levels[d]]) <= set(levels[d - 1].tolist())
    chain = kinematic_levels((-1, 0, 1, 2))
    assert [lv.tolist() for lv in chain] == [[0], [1], [2], [3]]


@pytest.mark.parametrize(
    "bad, match",
    [
        ((), "at least one"),
        ((0, 0), r"parents\[0\]"),
        ((1, -1), r"parents\[0\]"),
        ((-1, -1), "one root"),
        ((-1, 5), "must lie in"),
        ((-1, -2), "one root|must lie in"),
        ((-1, 1), "own parent"),
        ((-1, 2, 1), "cycle"),
        ((-1, 0, 3, 4, 2), "cycle"),
        ((-1, 0.0), "ints"),
        ("abc", "sequence"),
    ],
)
@pytest.mark.bad_input
def test_bad_parents(bad, match):
    with pytest.raises(ValueError, match=match):
        validate_parents(bad)
    with pytest.raises(ValueError):
        forward_kinematics(
            bad, np.zeros((max(len(bad), 1), 3, 3)), np.zeros((max(len(bad), 1), 3)), np.zeros(3)
        )


def test_validate_parents_accepts_numpy():
    assert validate_parents(np.array([-1, 0, 0, 2])) == (-1, 0, 0, 2)
    assert validate_parents([-1, np.int64(0)]) == (-1, 0)


@pytest.mark.bad_input
def test_wrong_shapes():
    parents = (-1, 0, 1)
    R, h, tr = np.broadcast_to(np.eye(3), (3, 3, 3)), np.zeros((3, 3)), np.zeros(3)
    with pytest.raises(ValueError, match="rotations"):
        forward_kinematics(parents, np.zeros((3, 3)), h, tr)  # axis-angle instead of matrices
    with pytest.raises(ValueError, match="rotations"):
        forward_kinematics(parents, R[:2], h, tr)
    with pytest.raises(ValueError, match="rest_joints"):
        forward_kinematics(parents, R, np.zeros((4, 3)), tr)
    with pytest.raises(ValueError, match="root_translation"):
        forward_kinematics(parents, R, h, np.zeros((1, 3)))


def test_no_recompilation_and_vmap():
    rng = np.random.default_rng(1)
    parents = random_tree(rng, 10)

    @eqx.debug.assert_max_traces(max_traces=1)
    def posed_joints(aa, h, trans):
        R = jax.vmap(axis_angle_to_matrix)(aa)
        return forward_kinematics(parents, R, h, trans)[1]

    f = jax.jit(jax.vmap(posed_joints, in_axes=(0, None, 0)))
    h = rng.normal(size=(10, 3))
    for _ in range(2):
        aa, trans = rng.normal(size=(5, 10, 3)), rng.normal(size=(5, 3))
        out = f(aa, h, trans)
        for b in range(5):
            _, ref = naive_fk(parents, Rotation.from_rotvec(aa[b]).as_matrix(), h, trans[b])
            np.testing.assert_allclose(out[b], ref, atol=1e-12)


def test_gradient_through_fk_at_zero_pose_is_finite():
    rng = np.random.default_rng(2)
    parents = random_tree(rng, 8)
    h = rng.normal(size=(8, 3))
    target = rng.normal(size=(8, 3))

    def loss(aa):
        A, t = forward_kinematics(parents, jax.vmap(axis_angle_to_matrix)(aa), h, jnp.zeros(3))
        return jnp.sum((t - target) ** 2) + jnp.sum(A**2)

    g = jax.jit(jax.grad(loss))(jnp.zeros((8, 3)))
    assert np.all(np.isfinite(g)) and np.any(g != 0)


def test_float32_dtype_preserved():
    parents = (-1, 0)
    A, t = fk(
        parents,
        jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (2, 3, 3)),
        jnp.zeros((2, 3), jnp.float32),
        jnp.zeros(3, jnp.float32),
    )
    assert A.dtype == jnp.float32 and t.dtype == jnp.float32


# --------------------------------------------------------------------------------------------------
# Similarity / Umeyama


def random_similarity(rng):
    return Similarity.from_scale(
        Rotation.from_rotvec(rng.normal(size=3)).as_matrix(),
        rng.normal(size=3),
        np.exp(rng.normal() * 0.5),
    )


@pytest.mark.bad_input
def test_similarity_algebra():
    rng = np.random.default_rng(0)
    a, b = random_similarity(rng), random_similarity(rng)
    x = rng.normal(size=(6, 3))
    np.testing.assert_allclose(a.apply(b.apply(x)), a.compose(b).apply(x), atol=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-12)
    np.testing.assert_allclose(a.compose(a.inverse()).as_matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(Similarity.identity().apply(x), x)
    M = np.asarray(a.as_matrix())
    np.testing.assert_allclose((M[:3, :3] @ x.T).T + M[:3, 3], a(x), atol=1e-12)
    np.testing.assert_allclose(a.apply(x[0]), a.apply(x)[0], atol=1e-12)
    with pytest.raises(ValueError, match="points"):
        a.apply(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="rotation"):
        Similarity(np.eye(2), np.zeros(3), 0.0)


@SETTINGS
@given(st.integers(0, 2**31 - 1), st.sampled_from([3, 17]))
def test_umeyama_recovers_exact_similarity(seed, n):
    rng = np.random.default_rng(seed)
    sim = random_similarity(rng)
    src = rng.normal(size=(n, 3))
    est = _umeyama(src, sim.apply(src), None)
    np.testing.assert_allclose(est.rotation, sim.rotation, atol=1e-8)
    np.testing.assert_allclose(est.translation, sim.translation, atol=1e-8)
    np.testing.assert_allclose(est.log_scale, sim.log_scale, atol=1e-8)
    np.testing.assert_allclose(np.linalg.det(est.rotation), 1.0, atol=1e-10)


_umeyama = jax.jit(umeyama, static_argnames="with_scale")


def test_umeyama_with_noise_weights_and_rigid():
    rng = np.random.default_rng(7)
    sim = random_similarity(rng)
    src = rng.normal(size=(200, 3))
    dst = np.asarray(sim.apply(src)) + 1e-3 * rng.normal(size=(200, 3))
    est = umeyama(src, dst)
    np.testing.assert_allclose(est.rotation, sim.rotation, atol=1e-3)
    np.testing.assert_allclose(est.scale, sim.scale, rtol=1e-3)
    np.testing.assert_allclose(est.translation, sim.translation, atol=2e-3)
    # weighted: an outlier with zero weight is ignored
    dst_out = np.array(sim.apply(src))
    dst_out[0] += 100.0
    w = np.ones(200)
    w[0] = 0.0
    est = umeyama(src, dst_out, weights=w)
    np.testing.assert_allclose(est.apply(src[1:]), dst_out[1:], atol=1e-9)
    # rigid: scale fixed to 1
    rigid = Similarity(sim.rotation, sim.translation, 0.0)
    est = umeyama(src, rigid.apply(src), with_scale=False)
    assert est.log_scale == 0.0
    np.testing.assert_allclose(est.apply(src), rigid.apply(src), atol=1e-10)


@pytest.mark.bad_input
def test_umeyama_is_reflection_safe_and_vmaps():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    est = umeyama(src, src * np.array([1.0, 1.0, -1.0]))
    np.testing.assert_allclose(np.linalg.det(est.rotation), 1.0, atol=1e-10)
    sims = [random_similarity(rng) for _ in range(3)]
    dst = np.stack([s.apply(src) for s in sims])
    batch = jax.vmap(umeyama, in_axes=(None, 0))(src, dst)
    for i, s in enumerate(sims):
        np.testing.assert_allclose(batch.rotation[i], s.rotation, atol=1e-8)
    with pytest.raises(ValueError, match="dst"):
        umeyama(src, src[:5])
    with pytest.raises(ValueError, match="weights"):
        umeyama(src, src, weights=np.ones(5))
