"""Rotation representations and conversions.

Every function here works on **one** rotation: a `(3,)` axis-angle vector, a `(4,)` unit quaternion
in `wxyz` order (scalar first), a `(3, 3)` rotation matrix acting on column vectors, a `(6,)` 6D
vector (the first two *columns* of the matrix, Zhou et al. 2019), or `(3,)` Euler angles in a named
order. Batch with `jax.vmap`. Angles are in radians.

Values **and** gradients are NaN-free at the degenerate configurations (zero rotation, rotation by
π): small-angle Taylor branches are combined with a safe value substituted inside `jnp.where`, as in
`jaxlie/_so3.py::exp` (Sophus `so3.hpp`). Nothing here is jitted; jit the surrounding computation.
"""

import functools

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._validate import check_array

__all__ = [
    "EULER_ORDERS",
    "ROTATION_REPS",
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "euler_to_matrix",
    "matrix_to_axis_angle",
    "matrix_to_euler",
    "matrix_to_quaternion",
    "matrix_to_rotation",
    "matrix_to_sixd",
    "project_to_rotation",
    "quaternion_conjugate",
    "quaternion_multiply",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "rotation_shape",
    "rotation_to_matrix",
    "sixd_to_matrix",
]

EULER_ORDERS: tuple[str, ...] = (
    "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX",
    "XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ",
)  # fmt: skip
"""The 12 valid Euler orders: 6 Tait-Bryan (three distinct axes) and 6 proper Euler (first ==
last)."""

ROTATION_REPS: tuple[str, ...] = ("axis_angle", "quaternion", "matrix", "sixd")
"""Rotation representations accepted by [`bodyprior.rotation_to_matrix`][] (plus
`"euler_<ORDER>"`)."""

_AXIS = {"X": 0, "Y": 1, "Z": 2}


# --------------------------------------------------------------------------------------------------
# helpers


def _as_float(x) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _taylor_threshold(dtype) -> float:
    """Squared-angle threshold below which the Taylor branches are used (≈ sqrt of machine eps)."""
    return float(jnp.finfo(dtype).eps) ** 0.5


def _hat(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Skew-symmetric cross-product matrix, `hat(w) @ v == cross(w, v)`."""
    z = jnp.zeros((), w.dtype)
    return jnp.stack(
        [
            jnp.stack([z, -w[2], w[1]]),
            jnp.stack([w[2], z, -w[0]]),
            jnp.stack([-w[1], w[0], z]),
        ]
    )


def _safe_normalize(v: Float[Array, " n"]) -> Float[Array, " n"]:
    """`v / |v|` with the norm clamped away from zero, so value and gradient stay finite."""
    tiny = jnp.finfo(v.dtype).tiny
    n2 = jnp.sum(v * v)
    return v * jnp.reciprocal(jnp.sqrt(jnp.maximum(n2, tiny**0.5)))


# --------------------------------------------------------------------------------------------------
# axis-angle


def axis_angle_to_matrix(aa: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    r"""Rodrigues' formula: axis-angle vector to rotation matrix.

    $R = I + \frac{\sin\theta}{\theta} K + \frac{1 - \cos\theta}{\theta^2} K^2$ with $K =
    [\omega]_\times$ and $\theta = |\omega|$. Below $\theta^2 \approx \sqrt{\epsilon}$ the
    coefficients use their Taylor series, and the norm is taken of a safe value substituted inside
    `jnp.where`, so the value and the gradient are exact and finite at `aa = 0` (see
    `jaxlie/_so3.py::exp`).

    **Arguments:**

    - `aa`: axis-angle vector, shape `(3,)`: unit axis times angle in radians.

    **Returns:** rotation matrix, shape `(3, 3)`, acting on column vectors.
    """
    aa = _as_float(check_array(aa, "aa", (3,), finite=False))
    theta2 = jnp.sum(aa * aa)
    small = theta2 < _taylor_threshold(aa.dtype)
    safe_theta2 = jnp.where(small, jnp.ones_like(theta2), theta2)
    theta = jnp.sqrt(safe_theta2)
    half = 0.5 * theta
    sinc = jnp.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, jnp.sin(theta) / theta)
    # (1 - cos θ) / θ² written as 2 sin²(θ/2) / θ² to avoid cancellation.
    cosc = jnp.where(
        small,
        0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0,
        2.0 * jnp.sin(half) ** 2 / safe_theta2,
    )
    K = _hat(aa)
    return jnp.eye(3, dtype=aa.dtype) + sinc * K + cosc * (K @ K)


def axis_angle_to_quaternion(aa: Float[ArrayLike, "3"]) -> Float[Array, "4"]:
    r"""Axis-angle vector to unit quaternion `(w, x, y, z)`.

    $q = (\cos\frac{\theta}{2}, \frac{\sin(\theta/2)}{\theta}\,\omega)$, with a Taylor branch at
    small
    $\theta$ (NaN-free gradient at zero).

    **Arguments:**

    - `aa`: axis-angle vector, shape `(3,)`, radians.

    **Returns:** unit quaternion, shape `(4,)`, `wxyz` (scalar first), with `w >= 0`.
    """
    aa = _as_float(check_array(aa, "aa", (3,), finite=False))
    theta2 = jnp.sum(aa * aa)
    small = theta2 < _taylor_threshold(aa.dtype)
    safe_theta2 = jnp.where(small, jnp.ones_like(theta2), theta2)
    theta = jnp.sqrt(safe_theta2)
    w = jnp.where(small, 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0, jnp.cos(0.5 * theta))
    s = jnp.where(
        small, 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0, jnp.sin(0.5 * theta) / theta
    )
    return jnp.concatenate([w[None], s * aa])


def quaternion_to_axis_angle(q: Float[ArrayLike, "4"]) -> Float[Array, "3"]:
    r"""Unit quaternion `(w, x, y, z)` to axis-angle vector with angle in `[0, π]`.

    The quaternion is first flipped to `w >= 0` (q and -q are the same rotation). Then
    $\omega = 2\,\mathrm{atan2}(|v|, w)\, v / |v|$, with the Taylor series of $2\,\mathrm{atan2}(n,
    w)/n$ near $n = 0$ so that the gradient at the identity is finite. Scale-invariant in `q`.

    **Arguments:**

    - `q`: quaternion, shape `(4,)`, `wxyz` (scalar first).

    **Returns:** axis-angle vector, shape `(3,)`, radians.
    """
    q = _as_float(check_array(q, "q", (4,), finite=False))
    q = jnp.where(q[0] < 0, -q, q)
    w, v = q[0], q[1:]
    n2 = jnp.sum(v * v)
    small = n2 < _taylor_threshold(q.dtype)
    safe_n2 = jnp.where(small, jnp.ones_like(n2), n2)
    n = jnp.sqrt(safe_n2)
    safe_w = jnp.where(small, w, jnp.ones_like(w))
    factor = jnp.where(
        small,
        2.0 / safe_w - 2.0 * n2 / (3.0 * safe_w**3),
        2.0 * jnp.arctan2(n, w) / n,
    )
    return factor * v


def matrix_to_axis_angle(R: Float[ArrayLike, "3 3"]) -> Float[Array, "3"]:
    """Rotation matrix to axis-angle vector (the SO(3) logarithm), angle in `[0, π]`.

    Goes through [`bodyprior.matrix_to_quaternion`][] (Shepperd's method), which is well conditioned
    everywhere including near π, then [`bodyprior.quaternion_to_axis_angle`][]. Value and gradient
    are finite at the identity and near a half turn.

    **Arguments:**

    - `R`: rotation matrix, shape `(3, 3)`.

    **Returns:** axis-angle vector, shape `(3,)`, radians.
    """
    R = check_array(R, "R", (3, 3), finite=False)
    return quaternion_to_axis_angle(matrix_to_quaternion(R))


# --------------------------------------------------------------------------------------------------
# quaternions


def quaternion_to_matrix(q: Float[ArrayLike, "4"]) -> Float[Array, "3 3"]:
    """Quaternion `(w, x, y, z)` to rotation matrix.

    Uses `s = 2 / |q|²`, so a non-unit (non-zero) quaternion gives the rotation of its
    normalisation.

    **Arguments:**

    - `q`: quaternion, shape `(4,)`, `wxyz` (scalar first).

    **Returns:** rotation matrix, shape `(3, 3)`.
    """
    q = _as_float(check_array(q, "q", (4,), finite=False))
    w, x, y, z = q[0], q[1], q[2], q[3]
    n2 = jnp.maximum(jnp.sum(q * q), jnp.finfo(q.dtype).tiny)
    s = 2.0 / n2
    return jnp.stack(
        [
            jnp.stack([1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)]),
            jnp.stack([s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)]),
            jnp.stack([s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)]),
        ]
    )


def matrix_to_quaternion(R: Float[ArrayLike, "3 3"]) -> Float[Array, "4"]:
    """Rotation matrix to unit quaternion `(w, x, y, z)` by Shepperd's method, branch-free.

    The four candidate formulas are the rows of the symmetric matrix `K = 4 q qᵀ` built linearly
    from `R`; the row with the largest diagonal entry `4 q_i²` is picked by `argmax` (no Python
    branch), and divided by `4 |q_i|` (clamped, so value and gradient are finite everywhere). The
    result is normalised and its sign chosen so that `w >= 0`.

    **Arguments:**

    - `R`: rotation matrix, shape `(3, 3)`.

    **Returns:** unit quaternion, shape `(4,)`, `wxyz` (scalar first), `w >= 0`.
    """
    R = _as_float(check_array(R, "R", (3, 3), finite=False))
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    tr = r00 + r11 + r22
    # For an exact rotation K = 4 q qᵀ; row i is 4 q_i q and the diagonal holds 4 q_i² (the largest
    # is >= 1). Shepperd: take the row with the largest diagonal entry and divide by 4 |q_i|.
    K = jnp.stack(
        [
            jnp.stack([1 + tr, r21 - r12, r02 - r20, r10 - r01]),
            jnp.stack([r21 - r12, 1 + 2 * r00 - tr, r01 + r10, r02 + r20]),
            jnp.stack([r02 - r20, r01 + r10, 1 + 2 * r11 - tr, r12 + r21]),
            jnp.stack([r10 - r01, r02 + r20, r12 + r21, 1 + 2 * r22 - tr]),
        ]
    )
    i = jnp.argmax(jnp.diagonal(K))
    # K[i, i] >= 1 for a rotation; the clamp only guards far-from-orthogonal input.
    q = K[i] / (2.0 * jnp.sqrt(jnp.maximum(K[i, i], 0.25)))
    q = q / jnp.sqrt(jnp.sum(q * q))
    return jnp.where(q[0] < 0, -q, q)


def quaternion_multiply(p: Float[ArrayLike, "4"], q: Float[ArrayLike, "4"]) -> Float[Array, "4"]:
    """Hamilton product `p ⊗ q` of two `wxyz` quaternions.

    `quaternion_to_matrix(p ⊗ q) == quaternion_to_matrix(p) @ quaternion_to_matrix(q)`.

    **Arguments:**

    - `p`, `q`: quaternions, shape `(4,)` each, `wxyz`.

    **Returns:** quaternion, shape `(4,)`.
    """
    p = _as_float(check_array(p, "p", (4,), finite=False))
    q = _as_float(check_array(q, "q", (4,), finite=False))
    pw, px, py, pz = p[0], p[1], p[2], p[3]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quaternion_conjugate(q: Float[ArrayLike, "4"]) -> Float[Array, "4"]:
    """Quaternion conjugate `(w, -x, -y, -z)`: the inverse rotation for a unit quaternion.

    **Arguments:**

    - `q`: quaternion, shape `(4,)`, `wxyz`.

    **Returns:** quaternion, shape `(4,)`.
    """
    q = _as_float(check_array(q, "q", (4,), finite=False))
    return q * jnp.array([1, -1, -1, -1], dtype=q.dtype)


# --------------------------------------------------------------------------------------------------
# 6D


def sixd_to_matrix(d6: Float[ArrayLike, "6"]) -> Float[Array, "3 3"]:
    """6D representation to rotation matrix by Gram–Schmidt (Zhou et al., CVPR 2019).

    `d6 = (a1, a2)` holds two 3-vectors that are (approximately) the first two **columns** of the
    matrix: `b1 = a1/|a1|`, `b2 = normalise(a2 - (b1·a2) b1)`, `b3 = b1 × b2`, `R = [b1 b2 b3]`.
    Norms are clamped away from zero.

    **Arguments:**

    - `d6`: shape `(6,)`, `concatenate([R[:, 0], R[:, 1]])`.

    **Returns:** rotation matrix, shape `(3, 3)`.
    """
    d6 = _as_float(check_array(d6, "d6", (6,), finite=False))
    a1, a2 = d6[:3], d6[3:]
    b1 = _safe_normalize(a1)
    b2 = _safe_normalize(a2 - jnp.dot(b1, a2) * b1)
    b3 = jnp.cross(b1, b2)
    return jnp.stack([b1, b2, b3], axis=-1)


def matrix_to_sixd(R: Float[ArrayLike, "3 3"]) -> Float[Array, "6"]:
    """Rotation matrix to 6D representation: its first two columns, concatenated.

    **Arguments:**

    - `R`: rotation matrix, shape `(3, 3)`.

    **Returns:** shape `(6,)`, `concatenate([R[:, 0], R[:, 1]])`.
    """
    R = _as_float(check_array(R, "R", (3, 3), finite=False))
    return jnp.concatenate([R[:, 0], R[:, 1]])


# --------------------------------------------------------------------------------------------------
# Euler angles


@functools.cache
def _parse_euler_order(order) -> tuple[int, int, int]:
    if not isinstance(order, str) or order not in EULER_ORDERS:
        raise ValueError(
            f"`order` must be one of {', '.join(EULER_ORDERS)} (upper case, intrinsic, applied in "
            f"the "
            f"written order), got {order!r}."
        )
    return tuple(_AXIS[c] for c in order)


def _elementary(axis: int, angle: Float[Array, ""]) -> Float[Array, "3 3"]:
    c, s = jnp.cos(angle), jnp.sin(angle)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    if axis == 0:
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == 1:
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return jnp.stack([jnp.stack(r) for r in rows])


def euler_to_matrix(angles: Float[ArrayLike, "3"], order: str) -> Float[Array, "3 3"]:
    """Euler angles to rotation matrix, applied as in a BVH channel list.

    For `order = "ZYX"` and `angles = (a, b, c)` the result is `Rz(a) @ Ry(b) @ Rx(c)`: intrinsic
    rotations in the written order (equivalently, extrinsic rotations in the reverse order; SciPy's
    `Rotation.from_euler("ZYX", angles)` with upper-case letters). All 12 orders in
    [`bodyprior.EULER_ORDERS`][] are supported, Tait-Bryan (`"XYZ"`, ...) and proper Euler (`"ZXZ"`,
    ...).

    **Arguments:**

    - `angles`: shape `(3,)`, radians, one per letter of `order`.
    - `order`: static Python string, one of the 12 orders (upper case).

    **Returns:** rotation matrix, shape `(3, 3)`.

    **Raises:** `ValueError` for an unknown `order`.
    """
    i, j, k = _parse_euler_order(order)
    angles = _as_float(check_array(angles, "angles", (3,), finite=False))
    return _elementary(i, angles[0]) @ _elementary(j, angles[1]) @ _elementary(k, angles[2])


def _safe_atan2(y, x, use):
    """atan2 whose inputs are replaced by (0, 1) where `use` is False (finite gradient there)."""
    return jnp.arctan2(jnp.where(use, y, 0.0), jnp.where(use, x, 1.0))


def matrix_to_euler(R: Float[ArrayLike, "3 3"], order: str) -> Float[Array, "3"]:
    """Rotation matrix to Euler angles; the inverse of [`bodyprior.euler_to_matrix`][].

    Ranges: for Tait-Bryan orders the middle angle is in `[-π/2, π/2]`, for proper Euler orders in
    `[0, π]`; the outer angles are in `(-π, π]`. At gimbal lock (middle-angle cosine, resp. sine,
    below ~`sqrt(eps)`) the last angle is set to 0 and the first absorbs the whole rotation; values
    and gradients stay finite there.

    **Arguments:**

    - `R`: rotation matrix, shape `(3, 3)`.
    - `order`: static Python string, one of the 12 orders in [`bodyprior.EULER_ORDERS`][].

    **Returns:** angles, shape `(3,)`, radians.

    **Raises:** `ValueError` for an unknown `order`.
    """
    i, j, k = _parse_euler_order(order)
    R = _as_float(check_array(R, "R", (3, 3), finite=False))
    proper = i == k
    if proper:
        k = 3 - i - j
    # +1 if (i, j, k) is a cyclic permutation of (0, 1, 2), else -1.
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    thresh = _taylor_threshold(R.dtype)
    if proper:
        # R = R_i(a) R_j(b) R_i(c):  R[i,i] = cos b, R[i,j] = sin b sin c,
        # R[i,k] = sign sin b cos c, R[j,i] = sin a sin b, R[k,i] = -sign cos a sin b.
        other2 = R[i, j] ** 2 + R[i, k] ** 2  # sin² b
        ok = other2 > thresh**2
        other = jnp.sqrt(jnp.where(ok, other2, 1.0))
        b = jnp.where(ok, jnp.arctan2(other, R[i, i]), jnp.where(R[i, i] > 0, 0.0, jnp.pi))
        c = _safe_atan2(R[i, j], sign * R[i, k], ok)
        a = _safe_atan2(R[j, i], -sign * R[k, i], ok)
    else:
        # R = R_i(a) R_j(b) R_k(c):  R[i,k] = sign sin b, R[i,i] = cos b cos c,
        # R[i,j] = -sign cos b sin c, R[k,k] = cos a cos b, R[j,k] = -sign sin a cos b.
        other2 = R[i, i] ** 2 + R[i, j] ** 2  # cos² b
        ok = other2 > thresh**2
        other = jnp.sqrt(jnp.where(ok, other2, 1.0))
        b = jnp.where(
            ok,
            jnp.arctan2(sign * R[i, k], other),
            jnp.where(sign * R[i, k] > 0, 0.5 * jnp.pi, -0.5 * jnp.pi),
        )
        c = _safe_atan2(-sign * R[i, j], R[i, i], ok)
        a = _safe_atan2(-sign * R[j, k], R[k, k], ok)
    # Gimbal lock: c = 0, and R e_j = R_i(a) e_j = cos a e_j + sign sin a e_k.
    a_lock = _safe_atan2(sign * R[k, j], R[j, j], ~ok)
    a = jnp.where(ok, a, a_lock)
    c = jnp.where(ok, c, jnp.zeros_like(c))
    return jnp.stack([a, b, c]).astype(R.dtype)


# --------------------------------------------------------------------------------------------------
# dispatch


def rotation_shape(rep: str) -> tuple[int, ...]:
    """Shape of one rotation in representation `rep`.

    **Arguments:**

    - `rep`: `"axis_angle"`, `"quaternion"`, `"matrix"`, `"sixd"` or `"euler_<ORDER>"` (e.g.
      `"euler_ZYX"`).

    **Returns:** `(3,)`, `(4,)`, `(3, 3)`, `(6,)` or `(3,)`.

    **Raises:** `ValueError` for an unknown representation.
    """
    if rep == "axis_angle":
        return (3,)
    if rep == "quaternion":
        return (4,)
    if rep == "matrix":
        return (3, 3)
    if rep == "sixd":
        return (6,)
    if isinstance(rep, str) and rep.startswith("euler_") and rep[6:] in EULER_ORDERS:
        return (3,)
    raise ValueError(
        f"`rep` must be one of {', '.join(ROTATION_REPS)} or 'euler_<ORDER>' with ORDER one of "
        f"{', '.join(EULER_ORDERS)}, got {rep!r}."
    )


def rotation_to_matrix(x: Float[ArrayLike, "..."], rep: str) -> Float[Array, "3 3"]:
    """Converts one rotation in representation `rep` to a `(3, 3)` matrix.

    **Arguments:**

    - `x`: one rotation, shape [`bodyprior.rotation_shape`][]`(rep)`.
    - `rep`: static string: `"axis_angle"`, `"quaternion"` (`wxyz`), `"matrix"`, `"sixd"`, or
      `"euler_<ORDER>"` (e.g. `"euler_ZYX"`, see [`bodyprior.euler_to_matrix`][]).

    **Returns:** rotation matrix, shape `(3, 3)`.

    **Raises:** `ValueError` for an unknown `rep` or a wrong shape.
    """
    shape = rotation_shape(rep)
    x = check_array(x, "x", shape, finite=False)
    if rep == "axis_angle":
        return axis_angle_to_matrix(x)
    if rep == "quaternion":
        return quaternion_to_matrix(x)
    if rep == "matrix":
        return _as_float(x)
    if rep == "sixd":
        return sixd_to_matrix(x)
    return euler_to_matrix(x, rep[6:])


def matrix_to_rotation(R: Float[ArrayLike, "3 3"], rep: str) -> Float[Array, "..."]:
    """Converts a `(3, 3)` rotation matrix to representation `rep`; inverse of
    [`bodyprior.rotation_to_matrix`][].

    **Arguments:**

    - `R`: rotation matrix, shape `(3, 3)`.
    - `rep`: static string, as in [`bodyprior.rotation_to_matrix`][].

    **Returns:** one rotation, shape [`bodyprior.rotation_shape`][]`(rep)`.

    **Raises:** `ValueError` for an unknown `rep` or a wrong shape.
    """
    rotation_shape(rep)
    R = check_array(R, "R", (3, 3), finite=False)
    if rep == "axis_angle":
        return matrix_to_axis_angle(R)
    if rep == "quaternion":
        return matrix_to_quaternion(R)
    if rep == "matrix":
        return _as_float(R)
    if rep == "sixd":
        return matrix_to_sixd(R)
    return matrix_to_euler(R, rep[6:])


def project_to_rotation(M: Float[ArrayLike, "3 3"]) -> Float[Array, "3 3"]:
    """Nearest rotation matrix (Frobenius norm) to a `3 × 3` matrix, by SVD with a determinant fix.

    With `M = U S Vᵀ`, returns `U diag(1, 1, d) Vᵀ`, `d = sign(det(U Vᵀ))`, so the result is a
    proper rotation (`det = +1`) even when `M` is a reflection or rank-deficient. This is the
    orthogonal Procrustes / Kabsch solution when `M` is a cross-covariance.

    !!! warning

        The gradient of an SVD is undefined where singular values coincide (e.g. `M` a multiple of
        the identity); differentiate through this only for generic `M`.

    **Arguments:**

    - `M`: shape `(3, 3)`.

    **Returns:** rotation matrix, shape `(3, 3)`.
    """
    M = _as_float(check_array(M, "M", (3, 3), finite=False))
    U, _, Vt = jnp.linalg.svd(M)
    d = jnp.sign(jnp.linalg.det(U @ Vt))
    d = jnp.where(d == 0, jnp.ones_like(d), d)
    D = jnp.ones(3, dtype=M.dtype).at[2].set(d)
    return (U * D) @ Vt
