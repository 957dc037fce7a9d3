"""Skinning: linear blend skinning (LBS) with sparse top-k weights, and dual-quaternion skinning
(DQS), and twist-distributed LBS.

Skinning weights are stored sparsely: each vertex has `K` (joint index, weight) pairs, `K` small
(typically 4–8), instead of a dense `(V, J)` matrix. Transforms are the `(J, 4, 4)` skinning
transforms `A_j` of [`bodyprior.forward_kinematics`][]. Kernels work on one mesh; `jax.vmap` over
bodies.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._rotations import _as_float, matrix_to_quaternion, quaternion_multiply, quaternion_to_matrix
from ._validate import check_array, is_tracer

__all__ = [
    "dense_weights_to_topk",
    "dqs",
    "lbs",
    "swing_twist_angle",
    "twist_lbs",
    "transform_to_dual_quaternion",
]


def _check_skinning_inputs(rest_vertices, weight_indices, weights, transforms):
    dims: dict[str, int] = {}
    check_array(rest_vertices, "rest_vertices", ("V", 3), finite=False, dims=dims)
    check_array(weight_indices, "weight_indices", ("V", "K"), integer=True, dims=dims)
    check_array(weights, "weights", ("V", "K"), finite=False, dims=dims)
    check_array(transforms, "transforms", ("J", 4, 4), finite=False, dims=dims)
    if not is_tracer(weight_indices):
        idx = np.asarray(weight_indices)
        if idx.size and (idx.min() < 0 or idx.max() >= dims["J"]):
            raise ValueError(
                f"`weight_indices` must lie in [0, {dims['J'] - 1}] (J = {dims['J']} transforms), "
                f"got "
                f"values in [{idx.min()}, {idx.max()}]."
            )
    x = _as_float(rest_vertices)
    w = _as_float(weights)
    T = _as_float(transforms)
    dtype = jnp.result_type(x, w, T)
    return x.astype(dtype), jnp.asarray(weight_indices), w.astype(dtype), T.astype(dtype)


def lbs(
    rest_vertices: Float[ArrayLike, "V 3"],
    weight_indices: Int[ArrayLike, "V K"],
    weights: Float[ArrayLike, "V K"],
    transforms: Float[ArrayLike, "J 4 4"],
) -> Float[Array, "V 3"]:
    r"""Linear blend skinning with sparse top-k weights.

    $v'_i = \left(\sum_k w_{ik} A_{j_{ik}}\right) [v_i; 1]$: the `K` gathered `3 × 4` transforms of
    each vertex are blended first, then applied. Weights are used as given (normally each row sums
    to 1; a row summing to 1 makes the result invariant to a global rigid transform).

    **Arguments:**

    - `rest_vertices`: rest-pose vertices, shape `(V, 3)`, metres.
    - `weight_indices`: joint index per (vertex, slot), integer shape `(V, K)`, in `[0, J)`.
    - `weights`: weight per (vertex, slot), shape `(V, K)`.
    - `transforms`: skinning transforms `A_j`, shape `(J, 4, 4)` (only the top `3 × 4` is used).

    **Returns:** posed vertices, shape `(V, 3)`, metres.

    **Raises:** `ValueError` for mismatched shapes, a non-integer `weight_indices`, or (for concrete
    arrays) indices outside `[0, J)`.
    """
    x, idx, w, T = _check_skinning_inputs(rest_vertices, weight_indices, weights, transforms)
    # One row gather per weight slot, accumulated elementwise: XLA fuses this into a single loop.
    # The
    # equivalent `einsum("vk,vkab->vab", w, T[idx])` lowers to a (V, K, 3, 4) gather plus V tiny
    # matmuls
    # and is ~100x slower under vmap on CPU.
    T12 = T[:, :3, :].reshape(T.shape[0], 12)
    M = w[:, 0:1] * T12[idx[:, 0]]
    for k in range(1, idx.shape[1]):
        M = M + w[:, k : k + 1] * T12[idx[:, k]]
    M = M.reshape(-1, 3, 4)
    return M[:, :, 0] * x[:, 0:1] + M[:, :, 1] * x[:, 1:2] + M[:, :, 2] * x[:, 2:3] + M[:, :, 3]


def dense_weights_to_topk(
    weights: Float[ArrayLike, "V J"], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Converts dense skinning weights to sparse top-`k` form (host-side, NumPy).

    Keeps the `k` largest weights of each vertex, sorted in decreasing order (so slot 0 is the
    dominant joint), and renormalises them to sum to 1.

    **Arguments:**

    - `weights`: dense non-negative weights, shape `(V, J)`.
    - `k`: number of joints kept per vertex, `1 <= k <= J`.

    **Returns:** a tuple `(indices, weights)` of NumPy arrays, shapes `(V, k)` (`int32`) and `(V,
    k)` (same float dtype as the input, or float64).

    **Raises:** `ValueError` for a bad shape, bad `k`, negative weights, or a vertex whose kept
    weights sum to zero.
    """
    W = np.asarray(weights)
    if W.ndim != 2:
        raise ValueError(f"`weights` must have shape (V, J), got shape {W.shape}.")
    if not np.issubdtype(W.dtype, np.floating):
        W = W.astype(np.float64)
    V, J = W.shape
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= J:
        raise ValueError(f"`k` must be an int in [1, {J}], got {k!r}.")
    if not np.all(np.isfinite(W)):
        raise ValueError("`weights` contains NaN or infinite values.")
    if np.any(W < 0):
        raise ValueError(f"`weights` must be non-negative, got minimum {W.min()}.")
    order = np.argsort(-W, axis=1, kind="stable")[:, :k]
    top = np.take_along_axis(W, order, axis=1)
    total = top.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        bad = int(np.flatnonzero(total[:, 0] <= 0)[0])
        raise ValueError(f"`weights` row {bad} has no positive weight among its top {k}.")
    return order.astype(np.int32), top / total


# --------------------------------------------------------------------------------------------------
# dual quaternions


def transform_to_dual_quaternion(transform: Float[ArrayLike, "4 4"]) -> Float[Array, "8"]:
    """Rigid transform to unit dual quaternion `(q_r, q_d)`, both `wxyz`.

    `q_r` is the rotation (with `w >= 0`), `q_d = ½ (0, t) ⊗ q_r`.

    **Arguments:**

    - `transform`: rigid transform, shape `(4, 4)` (or `(3, 4)`); the rotation block must be a
      rotation matrix.

    **Returns:** shape `(8,)`: `concatenate([q_r, q_d])`.
    """
    T = _as_float(transform)
    if T.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"`transform` must have shape (4, 4) or (3, 4), got shape {T.shape}.")
    qr = matrix_to_quaternion(T[:3, :3])
    tq = jnp.concatenate([jnp.zeros((1,), T.dtype), T[:3, 3]])
    qd = 0.5 * quaternion_multiply(tq, qr)
    return jnp.concatenate([qr, qd])


def _dq_apply(dq: Float[Array, "8"], x: Float[Array, "3"]) -> Float[Array, "3"]:
    qr, qd = dq[:4], dq[4:]
    conj = qr * jnp.array([1, -1, -1, -1], dtype=qr.dtype)
    t = 2.0 * quaternion_multiply(qd, conj)[1:]
    return quaternion_to_matrix(qr) @ x + t


def dqs(
    rest_vertices: Float[ArrayLike, "V 3"],
    weight_indices: Int[ArrayLike, "V K"],
    weights: Float[ArrayLike, "V K"],
    transforms: Float[ArrayLike, "J 4 4"],
) -> Float[Array, "V 3"]:
    """Dual-quaternion skinning (Kavan, Collins, Žára, O'Sullivan 2007).

    Each bone's rigid transform becomes a unit dual quaternion
    ([`bodyprior.transform_to_dual_quaternion`][]). Per vertex, the `K` gathered dual quaternions
    are sign-aligned to the one of the vertex's **dominant** (largest-weight) bone (antipodality:
    `q` and `-q` are the same rotation), blended linearly, normalised by the norm of the real part,
    and applied. Avoids LBS's "candy-wrapper" volume loss. With identity transforms it returns the
    rest mesh, with finite gradients.

    **Arguments:** as for [`bodyprior.lbs`][]; `transforms` must be rigid (rotation + translation).

    **Returns:** posed vertices, shape `(V, 3)`, metres.

    **Raises:** as for [`bodyprior.lbs`][].
    """
    x, idx, w, T = _check_skinning_inputs(rest_vertices, weight_indices, weights, transforms)
    dq = jax.vmap(transform_to_dual_quaternion)(T)  # (J, 8)
    g = dq[idx]  # (V, K, 8)
    pivot = jnp.take_along_axis(g, jnp.argmax(w, axis=1)[:, None, None], axis=1)  # (V, 1, 8)
    dots = jnp.sum(g[..., :4] * pivot[..., :4], axis=-1)  # (V, K)
    sign = jnp.where(dots < 0, -1.0, 1.0).astype(w.dtype)
    b = jnp.einsum("vk,vkd->vd", w * sign, g)  # (V, 8)
    n2 = jnp.sum(b[:, :4] ** 2, axis=-1, keepdims=True)
    b = b / jnp.sqrt(jnp.maximum(n2, jnp.finfo(b.dtype).tiny ** 0.5))
    return jax.vmap(_dq_apply)(b, x)


def swing_twist_angle(
    rotation: Float[ArrayLike, "3 3"], axis: Float[ArrayLike, " 3"]
) -> Float[Array, ""]:
    """The twist angle of `rotation` about the unit `axis` (swing–twist decomposition).

    With `q = (w, v)` the rotation's unit quaternion, the twist is the rotation about `axis` by
    `φ = 2 atan2(v·axis, w)`, wrapped to `(−π, π]`; the swing is the rest. The angle is the same for
    the swing-then-twist (`R = S T`) and twist-then-swing (`R = T S`) splits. **Returns:** `φ`,
    radians. NaN-free gradients (also at a 180° swing, where the twist is undefined: `φ = 0`).
    """
    q = matrix_to_quaternion(_as_float(rotation))
    a = _as_float(axis).astype(q.dtype)
    y = jnp.dot(q[1:], a)
    x = q[0]
    tiny = jnp.finfo(q.dtype).eps
    degenerate = (jnp.abs(x) + jnp.abs(y)) < tiny
    phi = 2.0 * jnp.arctan2(jnp.where(degenerate, 0.0, y), jnp.where(degenerate, 1.0, x))
    phi = jnp.where(phi > jnp.pi, phi - 2 * jnp.pi, phi)
    return jnp.where(phi <= -jnp.pi, phi + 2 * jnp.pi, phi)


def _axis_rotation(axis, angle):
    """Rodrigues: `(..., 3, 3)` rotations by `angle (...)` about the unit `axis (3,)`."""
    K = jnp.array(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], axis.dtype
    )
    c, s = jnp.cos(angle)[..., None, None], jnp.sin(angle)[..., None, None]
    return jnp.eye(3, dtype=axis.dtype) + s * K + (1.0 - c) * (K @ K)


def twist_lbs(
    rest_vertices: Float[ArrayLike, "V 3"],
    weight_indices: Int[ArrayLike, "V K"],
    weights: Float[ArrayLike, "V K"],
    transforms: Float[ArrayLike, "J 4 4"],
    twist_bones: Int[ArrayLike, " B"],
    heads: Float[ArrayLike, "B 3"],
    axes: Float[ArrayLike, "B 3"],
    lengths: Float[ArrayLike, " B"],
    angles: Float[ArrayLike, " B"],
) -> Float[Array, "V 3"]:
    r"""Twist-distributed linear blend skinning: LBS for the swing, a rotation ramp for the twist.

    For each twist bone `b` (a limb segment from its head `h_b` along the unit rest `axis a_b` to
    its child's head, length `L_b`), `transforms[b]` must carry the bone's **full** twist `φ_b`
    (`angles[b]`) about `a_b`. A vertex skinned to `b` uses instead

    $A_b \, Gig(\mathrm{Rot}(a_b, \mathrm{offset}_b - (1 - s)\,φ_b), h_big)$,
    $s = \mathrm{clip}((x - h_b)·a_b / L_b, 0, 1)$,

    where `G(R, h)` rotates about the axis through `h` in the rest frame: the twist turns from 0 at
    the head to `φ_b` at the child's head, rigidly per cross-section (the "ideal" twist field of
    panoman_v2 §4.1), so the candy-wrapper collapse of plain LBS does not occur. Other bones skin as
    in [`bodyprior.lbs`][]. [`bodyprior.evaluate`][] with `skinning="twist"` builds the inputs.

    **Arguments:** `rest_vertices`, `weight_indices`, `weights`, `transforms` as
    [`bodyprior.lbs`][]; `twist_bones (B,)` int bone indices; `heads (B, 3)` rest heads (m);
    `axes (B, 3)` unit rest axes; `lengths (B,)` segment lengths (m, > 0); `angles (B,)` twist
    angles (rad).

    **Returns:** posed vertices `(V, 3)`, metres.
    """
    x, idx, w, T = _check_skinning_inputs(rest_vertices, weight_indices, weights, transforms)
    B = int(np.shape(twist_bones)[0])
    for name, a, shp in (
        ("heads", heads, (B, 3)),
        ("axes", axes, (B, 3)),
        ("lengths", lengths, (B,)),
        ("angles", angles, (B,)),
    ):
        check_array(a, name, shp, finite=False)
    dt = x.dtype
    h = jnp.asarray(heads, dt)
    a = jnp.asarray(axes, dt)
    L = jnp.asarray(lengths, dt)
    phi = jnp.asarray(angles, dt)
    J = T.shape[0]
    slot = (
        jnp.full((J,), B, jnp.int32)
        .at[jnp.asarray(twist_bones, jnp.int32)]
        .set(jnp.arange(B, dtype=jnp.int32))
    )

    def correction(hb, ab, Lb, pb):
        s = jnp.clip((x - hb) @ ab / Lb, 0.0, 1.0)  # (V,)
        R = _axis_rotation(ab, -(1.0 - s) * pb)  # (V, 3, 3)
        t = hb - jnp.einsum("vab,b->va", R, hb)
        return jnp.concatenate([R, t[:, :, None]], axis=-1)  # (V, 3, 4)

    C = jax.vmap(correction)(h, a, L, phi)  # (B, V, 3, 4)
    eye = jnp.broadcast_to(jnp.eye(3, 4, dtype=dt), (1, x.shape[0], 3, 4))
    C = jnp.concatenate([C, eye])  # (B + 1, V, 3, 4); slot B = no correction
    T34 = T[:, :3, :]
    M = jnp.zeros((x.shape[0], 3, 4), dt)
    rows = jnp.arange(x.shape[0])
    for k in range(idx.shape[1]):
        j = idx[:, k]
        Ck = C[slot[j], rows]  # (V, 3, 4)
        Ak = T34[j]
        Mk = jnp.concatenate(
            [Ak[:, :, :3] @ Ck[:, :, :3], (Ak[:, :, :3] @ Ck[:, :, 3:]) + Ak[:, :, 3:]], axis=-1
        )
        M = M + w[:, k, None, None] * Mk
    return M[:, :, 0] * x[:, 0:1] + M[:, :, 1] * x[:, 1:2] + M[:, :, 2] * x[:, 2:3] + M[:, :, 3]
