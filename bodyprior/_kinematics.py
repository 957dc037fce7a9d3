"""Forward kinematics over a static parent tree, and the `Similarity` transform.

The convention (docs/architecture.md, same as anny's `local-ref` parameterisation and SMPL): joint
`j` has rest head position `h_j` and a local rotation `R_j` expressed in world-aligned axes at rest.
With `parents[0] == -1`,

    G_0 = R_0,            t_0 = root_translation + h_0
    G_j = G_p R_j,        t_j = t_p + G_p (h_j - h_p)
    A_j = [G_j | t_j - G_j h_j]       (skinning transform)

The tree is a static tuple of ints. Its depth levels are computed once on the host (cached per
tuple) and the composition runs as one batched matmul per level, as in MJX's `scan.body_tree`, so a
24-joint SMPL tree needs about 9 sequential steps rather than 24.
"""

import functools
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._rotations import _as_float
from ._store import register_type
from ._validate import check_array

__all__ = [
    "Similarity",
    "forward_kinematics",
    "kinematic_levels",
    "umeyama",
    "validate_parents",
    "world_transforms",
]


# --------------------------------------------------------------------------------------------------
# tree structure (host side)


@functools.lru_cache(maxsize=256)
def _validate_parents_cached(parents: tuple) -> tuple[int, ...]:
    J = len(parents)
    if J == 0:
        raise ValueError("`parents` must contain at least one joint, got an empty sequence.")
    out = []
    for j, p in enumerate(parents):
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)):
            raise ValueError(f"`parents` must contain Python ints, got {p!r} at index {j}.")
        out.append(int(p))
    if out[0] != -1:
        raise ValueError(f"`parents[0]` must be -1 (joint 0 is the root), got {out[0]}.")
    for j, p in enumerate(out[1:], start=1):
        if p == -1:
            raise ValueError(
                f"`parents` must have exactly one root (parents[0] == -1); joint {j} also has -1."
            )
        if not 0 <= p < J:
            raise ValueError(f"`parents[{j}]` must lie in [0, {J - 1}], got {p}.")
        if p == j:
            raise ValueError(f"`parents[{j}]` is {j}: a joint cannot be its own parent.")
    _depths(out)  # every joint must reach the root
    return tuple(out)


def _depths(parents: Sequence[int]) -> list[int]:
    """Depth of every joint (root 0); raises on a cycle (a walk longer than J steps)."""
    J = len(parents)
    depth = [-1] * J
    depth[0] = 0
    for j in range(J):
        path = []
        k = j
        while depth[k] < 0:
            path.append(k)
            k = parents[k]
            if len(path) > J:
                raise ValueError(f"`parents` contains a cycle through joint {j}.")
        d = depth[k]
        for k in reversed(path):
            d += 1
            depth[k] = d
    return depth


def validate_parents(parents: Sequence[int | np.integer] | Int[ArrayLike, " J"]) -> tuple[int, ...]:
    """Checks a kinematic tree given as a parent list.

    **Arguments:**

    - `parents`: sequence of `J` ints. `parents[0] == -1` (joint 0 is the only root); every other
      entry is the index of the joint's parent, in `[0, J)`. Parents need **not** precede their
      children.

    **Returns:** `parents` as a tuple of Python ints.

    **Raises:** `ValueError` for an empty list, non-integer entries, a missing or second root,
    out-of-range indices, self-parents, or cycles.
    """
    if isinstance(parents, (str, bytes)) or not isinstance(parents, (Sequence, np.ndarray)):
        raise ValueError(f"`parents` must be a sequence of ints, got {type(parents).__name__}.")
    if isinstance(parents, np.ndarray):
        if parents.ndim != 1 or parents.dtype.kind not in "iu":
            raise ValueError(
                f"`parents` must be a 1-D integer sequence, got array of dtype {parents.dtype} "
                f"and shape {parents.shape}."
            )
        parents = parents.tolist()
    return _validate_parents_cached(tuple(parents))


@functools.lru_cache(maxsize=256)
def _levels_cached(parents: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    depth_arr = np.asarray(_depths(parents))
    levels = tuple(
        np.flatnonzero(depth_arr == d).astype(np.int32) for d in range(depth_arr.max() + 1)
    )
    for lvl in levels:
        lvl.setflags(write=False)
    return levels


def kinematic_levels(parents: Sequence[int]) -> tuple[np.ndarray, ...]:
    """Groups joints by depth in the tree (host-side, cached per parent tuple).

    **Arguments:**

    - `parents`: parent list, as in [`bodyprior.validate_parents`][].

    **Returns:** a tuple of read-only NumPy `int32` index arrays; entry `d` lists (in increasing
    order) the joints at depth `d`. Entry 0 is `[0]`. Every joint's parent is in the previous entry.

    **Raises:** `ValueError` for an invalid tree.
    """
    return _levels_cached(validate_parents(parents))


# --------------------------------------------------------------------------------------------------
# forward kinematics


def _check_fk_inputs(parents, rotations, rest_joints, root_translation):
    parents = validate_parents(parents)
    J = len(parents)
    dims = {"J": J}
    check_array(rotations, "rotations", ("J", 3, 3), finite=False, dims=dims)
    check_array(rest_joints, "rest_joints", ("J", 3), finite=False, dims=dims)
    check_array(root_translation, "root_translation", (3,), finite=False)
    return parents


def world_transforms(
    parents: Sequence[int],
    rotations: Float[ArrayLike, "J 3 3"],
    rest_joints: Float[ArrayLike, "J 3"],
    root_translation: Float[ArrayLike, "3"],
) -> tuple[Float[Array, "J 3 3"], Float[Array, "J 3"]]:
    """World orientation `G_j` and posed head position `t_j` of every joint.

    See [`bodyprior.forward_kinematics`][] for the convention. One batched matmul per depth level.

    **Arguments:** as for [`bodyprior.forward_kinematics`][].

    **Returns:** a tuple `(G, t)`: world rotations, shape `(J, 3, 3)`, and posed joint positions,
    shape `(J, 3)`, metres, world frame.
    """
    parents = _check_fk_inputs(parents, rotations, rest_joints, root_translation)
    levels = _levels_cached(parents)
    R = _as_float(rotations)
    h = _as_float(rest_joints)
    trans = _as_float(root_translation)
    dtype = jnp.result_type(R, h, trans)
    R, h, trans = R.astype(dtype), h.astype(dtype), trans.astype(dtype)
    parr = np.asarray(parents)

    G = R  # the root entry G_0 = R_0 is already right; other entries are overwritten level by level
    t = jnp.zeros_like(h).at[0].set(trans + h[0])
    for lvl in levels[1:]:
        par = parr[lvl]
        Gp = G[par]
        G = G.at[lvl].set(Gp @ R[lvl])
        t = t.at[lvl].set(t[par] + jnp.einsum("nij,nj->ni", Gp, h[lvl] - h[par]))
    return G, t


def forward_kinematics(
    parents: Sequence[int],
    rotations: Float[ArrayLike, "J 3 3"],
    rest_joints: Float[ArrayLike, "J 3"],
    root_translation: Float[ArrayLike, "3"],
) -> tuple[Float[Array, "J 4 4"], Float[Array, "J 3"]]:
    """Forward kinematics: skinning transforms and posed joint positions.

    With `p = parents[j]`:

        G_0 = R_0,            t_0 = root_translation + h_0
        G_j = G_p R_j,        t_j = t_p + G_p (h_j - h_p)
        A_j = [G_j | t_j - G_j h_j]

    so that `A_j` maps a rest-pose point rigidly attached to joint `j` to its posed position. Zero
    rotations (identity matrices) and zero translation give `A_j = I` and `t = rest_joints`.

    The tree is grouped by depth on the host ([`bodyprior.kinematic_levels`][], cached) and each
    level is one batched matmul. Works on one skeleton; `jax.vmap` over bodies (with `parents`
    closed over).

    **Arguments:**

    - `parents`: static parent list of `J` ints, `parents[0] == -1` (see
      [`bodyprior.validate_parents`][]); parents need not precede children.
    - `rotations`: local joint rotations `R_j`, shape `(J, 3, 3)`, in world-aligned axes at rest.
    - `rest_joints`: rest head positions `h_j`, shape `(J, 3)`, metres, world frame.
    - `root_translation`: translation added to the root, shape `(3,)`, metres.

    **Returns:** a tuple `(A, t)`: skinning transforms, shape `(J, 4, 4)` (homogeneous, last row
    `[0, 0, 0, 1]`), and posed joint positions, shape `(J, 3)`, metres, world frame.

    **Raises:** `ValueError` for an invalid tree or mismatched shapes (e.g. `(J, 3)` axis-angle
    rotations: convert them with `jax.vmap(bodyprior.axis_angle_to_matrix)` first).
    """
    G, t = world_transforms(parents, rotations, rest_joints, root_translation)
    h = _as_float(rest_joints).astype(G.dtype)
    offset = t - jnp.einsum("jab,jb->ja", G, h)
    top = jnp.concatenate([G, offset[:, :, None]], axis=-1)  # (J, 3, 4)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], dtype=G.dtype), (G.shape[0], 1, 4))
    return jnp.concatenate([top, bottom], axis=1), t


# --------------------------------------------------------------------------------------------------
# similarity transforms


class Similarity(eqx.Module):
    """A similarity transform `x -> s R x + t` (uniform scale, rotation, translation).

    One transform; `jax.vmap` over a batch. The scale is stored as its logarithm so it stays
    positive under unconstrained optimisation.

    !!! example

        ```python
        sim = bodyprior.umeyama(src, dst)
        aligned = sim.apply(src)          # (N, 3)
        back = sim.inverse().apply(aligned)
        ```
    """

    rotation: Float[Array, "3 3"] = eqx.field(converter=jnp.asarray)
    """Rotation matrix `R`, shape `(3, 3)`."""
    translation: Float[Array, "3"] = eqx.field(converter=jnp.asarray)
    """Translation `t`, shape `(3,)`, metres."""
    log_scale: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    """`log(s)`, shape `()`."""

    def __check_init__(self):
        if self.rotation.shape[-2:] != (3, 3):
            raise ValueError(f"`rotation` must have shape (3, 3), got {self.rotation.shape}.")
        if self.translation.shape[-1:] != (3,):
            raise ValueError(f"`translation` must have shape (3,), got {self.translation.shape}.")

    @classmethod
    def identity(cls, dtype=None) -> "Similarity":
        """The identity transform (`R = I`, `t = 0`, `s = 1`) in `dtype` (default float type)."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        return cls(jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype=dtype), jnp.zeros((), dtype=dtype))

    @classmethod
    def from_scale(
        cls,
        rotation: Float[ArrayLike, "3 3"],
        translation: Float[ArrayLike, "3"],
        scale: Float[ArrayLike, ""] = 1.0,
    ) -> "Similarity":
        """Builds a transform from a (positive) linear `scale` instead of its log."""
        rotation = jnp.asarray(rotation)
        return cls(
            rotation, jnp.asarray(translation), jnp.log(jnp.asarray(scale, dtype=rotation.dtype))
        )

    @property
    def scale(self) -> Float[Array, ""]:
        """The scale factor `s = exp(log_scale)`."""
        return jnp.exp(self.log_scale)

    def apply(self, points: Float[ArrayLike, "*N 3"]) -> Float[Array, "*N 3"]:
        """Applies `x -> s R x + t` to each row.

        **Arguments:**

        - `points`: shape `(N, 3)` (or `(3,)` for one point), metres.

        **Returns:** transformed points, same shape.
        """
        points = jnp.asarray(points)
        if points.shape[-1:] != (3,) or points.ndim not in (1, 2):
            raise ValueError(f"`points` must have shape (N, 3) or (3,), got shape {points.shape}.")
        return self.scale * (points @ self.rotation.T) + self.translation

    def __call__(self, points: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
        """Same as [`bodyprior.Similarity.apply`][]."""
        return self.apply(points)

    def inverse(self) -> "Similarity":
        """The inverse transform `y -> (1/s) Rᵀ (y - t)`."""
        Rt = self.rotation.T
        return Similarity(Rt, -jnp.exp(-self.log_scale) * (Rt @ self.translation), -self.log_scale)

    def compose(self, other: "Similarity") -> "Similarity":
        """`self ∘ other`: the transform `x -> self.apply(other.apply(x))`."""
        return Similarity(
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
            self.log_scale + other.log_scale,
        )

    def as_matrix(self) -> Float[Array, "4 4"]:
        """Homogeneous `(4, 4)` matrix `[[s R, t], [0, 1]]`."""
        top = jnp.concatenate([self.scale * self.rotation, self.translation[:, None]], axis=1)
        bottom = jnp.array([[0, 0, 0, 1]], dtype=top.dtype)
        return jnp.concatenate([top, bottom], axis=0)


register_type(Similarity)


def umeyama(
    src: Float[ArrayLike, "N 3"],
    dst: Float[ArrayLike, "N 3"],
    weights: Float[ArrayLike, " N"] | None = None,
    with_scale: bool = True,
) -> Similarity:
    r"""Least-squares similarity aligning `src` to `dst` (Umeyama 1991 / Horn 1987), closed form.

    Minimises $\sum_n w_n \| s R\, \mathrm{src}_n + t - \mathrm{dst}_n \|^2$ over rotations $R$
    (never reflections: the smallest singular direction is flipped when `det < 0`), scales $s > 0$
    and translations $t$.

    !!! warning

        Gradients through the SVD are undefined for degenerate point sets (coincident singular
        values, e.g. symmetric configurations); the value is still well defined.

    **Arguments:**

    - `src`: source points, shape `(N, 3)`, metres.
    - `dst`: target points, shape `(N, 3)`, metres.
    - `weights`: optional non-negative weights, shape `(N,)` (normalised internally); `None` =
      uniform.
    - `with_scale`: static bool; if `False` the scale is fixed to 1 (rigid alignment / Kabsch).

    **Returns:** a [`bodyprior.Similarity`][] with `sim.apply(src) ≈ dst`.

    **Raises:** `ValueError` for mismatched shapes.
    """
    dims: dict[str, int] = {}
    check_array(src, "src", ("N", 3), finite=False, dims=dims)
    check_array(dst, "dst", ("N", 3), finite=False, dims=dims)
    src, dst = _as_float(src), _as_float(dst)
    dtype = jnp.result_type(src, dst)
    src, dst = src.astype(dtype), dst.astype(dtype)
    if weights is None:
        w = jnp.full(src.shape[0], 1.0 / src.shape[0], dtype=dtype)
    else:
        check_array(weights, "weights", ("N",), finite=False, dims=dims)
        w = _as_float(weights).astype(dtype)
        w = w / jnp.maximum(jnp.sum(w), jnp.finfo(dtype).tiny)
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    cov = (xd * w[:, None]).T @ xs  # (3, 3) = sum_n w_n xd_n xs_nᵀ
    U, D, Vt = jnp.linalg.svd(cov)
    d = jnp.sign(jnp.linalg.det(U) * jnp.linalg.det(Vt))
    d = jnp.where(d == 0, jnp.ones_like(d), d)
    S = jnp.ones(3, dtype=dtype).at[2].set(d)
    R = (U * S) @ Vt
    if with_scale:
        var_s = jnp.sum(w * jnp.sum(xs * xs, axis=-1))
        tiny = jnp.finfo(dtype).tiny
        s = jnp.sum(D * S) / jnp.maximum(var_s, tiny)
        log_s = jnp.log(jnp.maximum(s, tiny))
    else:
        s = jnp.ones((), dtype)
        log_s = jnp.zeros((), dtype)
    t = mu_d - s * (R @ mu_s)
    return Similarity(R, t, log_s)
