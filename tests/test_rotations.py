"""Tests for bodyprior._rotations: round trips, degenerate configurations, gradients, dispatch."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation

from bodyprior import (
    EULER_ORDERS,
    ROTATION_REPS,
    axis_angle_to_matrix,
    axis_angle_to_quaternion,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
    matrix_to_quaternion,
    matrix_to_rotation,
    matrix_to_sixd,
    project_to_rotation,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    rotation_shape,
    rotation_to_matrix,
    sixd_to_matrix,
)

SETTINGS = settings(deadline=None, max_examples=25)

# jitted once per test session; shapes never change, so each compiles once.
aa2R = jax.jit(axis_angle_to_matrix)
R2aa = jax.jit(matrix_to_axis_angle)
aa2q = jax.jit(axis_angle_to_quaternion)
q2aa = jax.jit(quaternion_to_axis_angle)
q2R = jax.jit(quaternion_to_matrix)
R2q = jax.jit(matrix_to_quaternion)
e2R = jax.jit(euler_to_matrix, static_argnums=1)
R2e = jax.jit(matrix_to_euler, static_argnums=1)
jac_aa2R = jax.jit(jax.jacrev(axis_angle_to_matrix))
jac_R2aa = jax.jit(jax.jacrev(matrix_to_axis_angle))
jac_R2e = jax.jit(jax.jacfwd(matrix_to_euler), static_argnums=1)


def vec(n, lo=-3.0, hi=3.0):
    return hnp.arrays(np.float64, (n,), elements=st.floats(lo, hi, allow_nan=False, width=64))


def axis_angles(max_angle=np.pi - 1e-3):
    """Axis-angle vectors with angle in [0, max_angle]: a unit axis times an angle."""

    @st.composite
    def _draw(draw):
        v = draw(vec(3, -1, 1))
        n = np.linalg.norm(v)
        axis = v / n if n > 1e-3 else np.array([0.0, 0.0, 1.0])
        return axis * draw(st.floats(0.0, max_angle))

    return _draw()


def assert_rotation(R, atol=1e-10):
    R = np.asarray(R)
    assert np.all(np.isfinite(R))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=atol)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=atol)


def assert_same_quaternion(p, q, atol=1e-10):
    p, q = np.asarray(p), np.asarray(q)
    assert min(np.abs(p - q).max(), np.abs(p + q).max()) < atol, (p, q)


# --------------------------------------------------------------------------------------------------
# round trips


@SETTINGS
@given(axis_angles())
def test_axis_angle_matrix_round_trip(aa):
    R = aa2R(aa)
    assert_rotation(R)
    np.testing.assert_allclose(R, Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(R2aa(R), aa, atol=1e-9)


@SETTINGS
@given(axis_angles())
def test_quaternion_round_trips(aa):
    q = aa2q(aa)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-12)
    assert q[0] >= 0
    np.testing.assert_allclose(q2R(q), aa2R(aa), atol=1e-12)
    assert_same_quaternion(R2q(aa2R(aa)), q)
    np.testing.assert_allclose(q2aa(q), aa, atol=1e-9)
    # SciPy uses xyzw.
    assert_same_quaternion(q, np.roll(Rotation.from_rotvec(aa).as_quat(), 1))


@SETTINGS
@given(vec(4, -1, 1).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_random_quaternion_to_matrix_and_back(v):
    q = v / np.linalg.norm(v)
    R = q2R(q)
    assert_rotation(R)
    back = R2q(R)
    assert back[0] >= 0
    assert_same_quaternion(back, q)
    # quaternion_to_matrix is scale invariant
    np.testing.assert_allclose(q2R(3.0 * q), R, atol=1e-12)
    # q -> aa -> R goes the same way
    np.testing.assert_allclose(aa2R(q2aa(q)), R, atol=1e-10)


@SETTINGS
@given(axis_angles(), axis_angles())
def test_quaternion_multiply_matches_matrix_product(a, b):
    p, q = aa2q(a), aa2q(b)
    np.testing.assert_allclose(q2R(quaternion_multiply(p, q)), aa2R(a) @ aa2R(b), atol=1e-12)
    ident = quaternion_multiply(p, quaternion_conjugate(p))
    np.testing.assert_allclose(ident, [1.0, 0.0, 0.0, 0.0], atol=1e-12)


@SETTINGS
@given(axis_angles(), vec(6, -0.05, 0.05))
def test_sixd_round_trip_and_projection(aa, noise):
    R = aa2R(aa)
    d6 = matrix_to_sixd(R)
    np.testing.assert_allclose(d6, np.concatenate([R[:, 0], R[:, 1]]))
    np.testing.assert_allclose(sixd_to_matrix(d6), R, atol=1e-12)
    # Any (non-degenerate) 6-vector maps to a rotation whose first column is the normalised a1.
    R2 = sixd_to_matrix(d6 * 2.0 + noise)
    assert_rotation(R2)
    a1 = np.asarray(d6[:3] * 2.0 + noise[:3])
    np.testing.assert_allclose(R2[:, 0], a1 / np.linalg.norm(a1), atol=1e-12)


def euler_angles(order, margin=1e-2):
    """Angles away from gimbal lock for `order`."""
    lo, hi = (
        (margin, np.pi - margin)
        if order[0] == order[2]
        else (-np.pi / 2 + margin, np.pi / 2 - margin)
    )
    outer = st.floats(-np.pi + margin, np.pi - margin)
    return st.tuples(outer, st.floats(lo, hi), outer).map(np.array)


@pytest.mark.parametrize("order", EULER_ORDERS)
def test_euler_round_trip_all_orders(order):
    @SETTINGS
    @given(euler_angles(order))
    def check(angles):
        R = e2R(angles, order)
        assert_rotation(R)
        # BVH convention == intrinsic rotations in the written order == SciPy upper case.
        np.testing.assert_allclose(R, Rotation.from_euler(order, angles).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(R2e(R, order), angles, atol=1e-8)

    check()


def test_euler_bvh_convention_explicit():
    a, b, c = 0.3, -0.7, 1.1
    Rz = Rotation.from_rotvec([0, 0, a]).as_matrix()
    Ry = Rotation.from_rotvec([0, b, 0]).as_matrix()
    Rx = Rotation.from_rotvec([c, 0, 0]).as_matrix()
    np.testing.assert_allclose(
        euler_to_matrix(jnp.array([a, b, c]), "ZYX"), Rz @ Ry @ Rx, atol=1e-14
    )


@pytest.mark.parametrize("order", EULER_ORDERS)
def test_euler_gimbal_lock_is_finite(order):
    middle = 0.0 if order[0] == order[2] else np.pi / 2
    for b in (middle, -middle, np.pi if order[0] == order[2] else -np.pi / 2):
        angles = np.array([0.4, b, -0.9])
        R = e2R(angles, order)
        back = R2e(R, order)
        assert np.all(np.isfinite(back))
        np.testing.assert_allclose(e2R(back, order), R, atol=1e-7)
        if order in ("XYZ", "ZYX", "ZXZ", "YXY"):  # gradients: a few orders (compile time)
            assert np.all(np.isfinite(jac_R2e(R, order)))


@pytest.mark.parametrize("bad", ["xyz", "XXY", "XY", "ABC", 3, "XYZZ"])
@pytest.mark.bad_input
def test_euler_bad_order(bad):
    with pytest.raises(ValueError, match="order"):
        euler_to_matrix(jnp.zeros(3), bad)
    with pytest.raises(ValueError, match="order"):
        matrix_to_euler(jnp.eye(3), bad)


# --------------------------------------------------------------------------------------------------
# degenerate configurations and gradients


def _generators():
    G = np.zeros((3, 3, 3))
    for i in range(3):
        e = np.eye(3)[i]
        G[:, :, i] = np.cross(np.eye(3), e).T * -1.0  # hat(e_i)
    return G


def test_generators_helper():
    G = _generators()
    v = np.array([0.3, -0.2, 0.5])
    np.testing.assert_allclose(G @ v @ np.array([1.0, 2.0, 3.0]), np.cross(v, [1.0, 2.0, 3.0]))


def test_axis_angle_to_matrix_at_zero_value_and_gradient():
    z = jnp.zeros(3)
    np.testing.assert_array_equal(axis_angle_to_matrix(z), np.eye(3))
    J = jac_aa2R(z)  # (3, 3, 3): dR/daa_i = hat(e_i)
    np.testing.assert_allclose(J, _generators(), atol=1e-15)
    np.testing.assert_allclose(
        jax.jit(jax.jacfwd(axis_angle_to_matrix))(z), _generators(), atol=1e-15
    )
    Jq = jax.jit(jax.jacrev(axis_angle_to_quaternion))(z)
    np.testing.assert_allclose(Jq, np.vstack([np.zeros((1, 3)), 0.5 * np.eye(3)]), atol=1e-15)


def test_matrix_to_axis_angle_at_identity_value_and_gradient():
    Id = jnp.eye(3)
    np.testing.assert_array_equal(matrix_to_axis_angle(Id), np.zeros(3))
    J = jac_R2aa(Id)  # aa ≈ vee((R - Rᵀ)/2) near I
    expected = np.zeros((3, 3, 3))
    for i, (a, b) in enumerate([(2, 1), (0, 2), (1, 0)]):
        expected[i, a, b], expected[i, b, a] = 0.5, -0.5
    np.testing.assert_allclose(J, expected, atol=1e-15)
    Jq = jax.jit(jax.jacrev(quaternion_to_axis_angle))(jnp.array([1.0, 0, 0, 0]))
    np.testing.assert_allclose(Jq, np.hstack([np.zeros((3, 1)), 2 * np.eye(3)]), atol=1e-15)
    # composed: log(exp(w)) has identity Jacobian at 0
    Jc = jax.jit(jax.jacrev(lambda w: matrix_to_axis_angle(axis_angle_to_matrix(w))))(jnp.zeros(3))
    np.testing.assert_allclose(Jc, np.eye(3), atol=1e-15)


@pytest.mark.parametrize("theta", [1e-12, 1e-8, 1e-5, 1.2e-4, 3e-4, 1e-3, 0.1])
def test_small_angles_across_taylor_threshold(theta):
    aa = theta * np.array([0.6, -0.8, 0.0])
    np.testing.assert_allclose(aa2R(aa), Rotation.from_rotvec(aa).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(R2aa(aa2R(aa)), aa, rtol=1e-7, atol=1e-15)
    np.testing.assert_allclose(q2aa(aa2q(aa)), aa, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("eps", [0.0, 1e-12, 1e-7, 1e-4])
def test_near_pi(eps):
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    aa = (np.pi - eps) * axis
    R = aa2R(aa)
    back = R2aa(R)
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(np.linalg.norm(back), np.pi - eps, atol=1e-9)
    np.testing.assert_allclose(aa2R(back), R, atol=1e-10)
    J = jac_R2aa(R)
    assert np.all(np.isfinite(J))


@functools.partial(jax.jit, static_argnums=0)
def _jvp(f, x, v):
    return jax.jvp(f, (x,), (v,))


@jax.jit
def _logmap_jvp(R, w, v):
    # log on the manifold: perturb R along a tangent direction
    return jax.jvp(lambda w: matrix_to_axis_angle(axis_angle_to_matrix(w) @ R), (w,), (v,))


_EULER_FNS = {o: functools.partial(euler_to_matrix, order=o) for o in EULER_ORDERS}


@SETTINGS
@given(axis_angles(np.pi - 0.05), vec(3, -1, 1))
def test_jvps_against_finite_differences(aa, v):
    aa, v = jnp.asarray(aa), jnp.asarray(v)
    _, jvp = _jvp(aa2R, aa, v)
    np.testing.assert_allclose(jvp, central_difference(aa2R, aa, v), atol=1e-7)

    R = aa2R(aa)

    _, jvp = _logmap_jvp(R, jnp.zeros(3), v)
    np.testing.assert_allclose(
        jvp, central_difference(lambda w: R2aa(aa2R(w) @ R), jnp.zeros(3), v), atol=1e-6
    )

    q = aa2q(aa)
    _, jvp = _jvp(q2R, q, jnp.concatenate([v, v[:1]]))
    np.testing.assert_allclose(
        jvp, central_difference(q2R, q, jnp.concatenate([v, v[:1]])), atol=1e-7
    )

    d6 = matrix_to_sixd(R) + 0.1
    v6 = jnp.concatenate([v, -v])
    _, jvp = _jvp(sixd_to_matrix, d6, v6)
    np.testing.assert_allclose(jvp, central_difference(sixd_to_matrix, d6, v6), atol=1e-6)

    for order in ("ZYX", "XZX"):
        e = R2e(R, order)
        f = _EULER_FNS[order]
        _, jvp = _jvp(f, e, v)
        np.testing.assert_allclose(jvp, central_difference(f, e, v), atol=1e-7)


def test_float32_is_preserved_and_finite():
    z = jnp.zeros(3, jnp.float32)
    I32 = jnp.eye(3, dtype=jnp.float32)
    assert aa2R(z).dtype == jnp.float32
    assert R2aa(I32).dtype == jnp.float32
    assert R2e(I32, "XYZ").dtype == jnp.float32
    assert np.all(np.isfinite(jac_aa2R(z)))
    assert np.all(np.isfinite(jac_R2aa(I32)))
    aa = jnp.array([0.3, -0.2, 0.1], jnp.float32)
    np.testing.assert_allclose(R2aa(aa2R(aa)), aa, atol=1e-6)


def test_vmap_over_joints():
    aa = np.random.default_rng(0).normal(size=(7, 3))
    R = jax.jit(jax.vmap(axis_angle_to_matrix))(aa)
    np.testing.assert_allclose(R, Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.vmap(matrix_to_axis_angle))(R), aa, atol=1e-9)


# --------------------------------------------------------------------------------------------------
# dispatch, projection, errors


REPS = list(ROTATION_REPS) + ["euler_ZYX", "euler_YXY"]


@pytest.mark.parametrize("rep", REPS)
def test_dispatch_round_trip(rep):
    R = aa2R(np.array([0.4, -0.3, 0.8]))
    x = matrix_to_rotation(R, rep)
    assert x.shape == rotation_shape(rep)
    np.testing.assert_allclose(rotation_to_matrix(x, rep), R, atol=1e-12)


def test_dispatch_errors():
    with pytest.raises(ValueError, match="rep"):
        rotation_to_matrix(jnp.zeros(3), "rotvec")
    with pytest.raises(ValueError, match="rep"):
        matrix_to_rotation(jnp.eye(3), "euler_xyz")
    with pytest.raises(ValueError, match=r"\(4,\)"):
        rotation_to_matrix(jnp.zeros(3), "quaternion")


@pytest.mark.parametrize(
    "fn, bad",
    [
        (axis_angle_to_matrix, jnp.zeros(4)),
        (axis_angle_to_matrix, jnp.zeros((2, 3))),
        (matrix_to_axis_angle, jnp.zeros(9)),
        (quaternion_to_matrix, jnp.zeros(3)),
        (matrix_to_quaternion, jnp.zeros((3, 4))),
        (sixd_to_matrix, jnp.zeros(5)),
        (project_to_rotation, jnp.zeros(3)),
    ],
)
@pytest.mark.bad_input
def test_wrong_shapes_raise(fn, bad):
    with pytest.raises(ValueError, match="must have shape"):
        fn(bad)


@SETTINGS
@given(axis_angles(), vec(9, -0.1, 0.1), st.floats(0.2, 5.0))
def test_project_to_rotation(aa, noise, scale):
    R = np.asarray(aa2R(aa))
    np.testing.assert_allclose(project_to_rotation(scale * R), R, atol=1e-10)
    P = project_to_rotation(R + noise.reshape(3, 3))
    assert_rotation(P)
    # a reflection is mapped to a proper rotation
    assert_rotation(project_to_rotation(R @ np.diag([1.0, 1.0, -1.0])))
