"""Joint limits learned from mocap poses, and the fraction of sampled poses that break them.

Definition (per joint, per Euler angle, in the pose convention of [`bodyprior.PoseSet`][]):

1. Every pose is first brought to **canonical Euler angles**: angles -> rotation matrix -> angles
   with [`bodyprior.matrix_to_euler`][] (middle angle in `[-π/2, π/2]` for Tait-Bryan orders, outer
   angles in `(-π, π]`). A rotation has two Euler triples (`(a, b, c)` and `(a + π, π - b, c + π)`),
   and a generator need not output the canonical one; without this step the same rotation could be
   inside or outside the limits depending on how it was written.
2. The **circular mean** `μ = atan2(mean sin θ, mean cos θ)` of each angle over the training poses
   is the centre; angles are unwrapped into `(μ - π, μ + π]` so that a range straddling ±π (e.g. a
   forearm twist near 180°) stays one interval instead of covering the whole circle.
3. The limits are the `quantile` and `1 - quantile` empirical quantiles of the unwrapped angles
   (default 0.5 %: robust to mocap glitches and retargeting flips while keeping 99 % of the data
   inside on every axis).

A sample violates the limits if any of its joints has a canonical angle outside its interval (the
test is done modulo 2π around the interval's centre). Independent per-angle intervals are a box in
Euler space: they ignore correlations between axes and joints, so "no violation" is necessary, not
sufficient, for a plausible pose. They are the standard, inspectable definition used by
joint-limit checks in animation rigs and the one the issue asks for ("limits derived from the mocap
data").
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._mocap import EULER_ORDER
from .._rotations import EULER_ORDERS, euler_to_matrix, matrix_to_euler
from .._validate import check_array

__all__ = ["joint_limit_violation", "joint_limits"]


def _order(order: str | None) -> str:
    if order is None:
        return EULER_ORDER
    if order not in EULER_ORDERS:
        raise ValueError(f"`order` must be one of {', '.join(EULER_ORDERS)}, got {order!r}.")
    return order


def _wrap(x: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(x), np.cos(x))


@functools.partial(jax.jit, static_argnames="order")
def _canonical_kernel(euler, order: str):
    return jax.vmap(jax.vmap(lambda e: matrix_to_euler(euler_to_matrix(e, order), order)))(euler)


def _canonical(euler: np.ndarray, order: str) -> np.ndarray:
    return np.asarray(_canonical_kernel(jnp.asarray(euler), order), dtype=np.float64)


def joint_limits(
    euler: Float[ArrayLike, "N J 3"],
    *,
    quantile: float = 0.005,
    order: str | None = None,
) -> Float[Array, "J 3 2"]:
    """Per-joint, per-Euler-angle ranges of motion from training poses (definition: module docs).

    **Arguments:**

    - `euler`: training poses, shape `(N, J, 3)`, radians (e.g. `PoseSet.euler` of the training
      clips, `J = 20`).
    - `quantile`: tail mass cut on each side of each angle, in `[0, 0.5)`; 0 gives the full
      observed range.
    - `order`: Euler order of `euler`; default `bodyprior.EULER_ORDER`.

    **Returns:** `(J, 3, 2)` array of `(lower, upper)` limits in radians, `upper - lower < 2π`; the
    bounds may lie outside `(-π, π]` when an interval straddles ±π.

    **Raises:** `ValueError` for a wrong shape, non-finite angles, fewer than 2 poses, or a
    `quantile` outside `[0, 0.5)`.
    """
    order = _order(order)
    check_array(euler, "euler", (None, None, 3))
    if np.shape(euler)[0] < 2:
        raise ValueError(f"`euler` must hold at least 2 poses, got {np.shape(euler)[0]}.")
    q = float(quantile)
    if not 0.0 <= q < 0.5:
        raise ValueError(f"`quantile` must lie in [0, 0.5), got {quantile!r}.")
    x = _canonical(np.asarray(euler, dtype=np.float64), order)  # (N, J, 3)
    mu = np.arctan2(np.sin(x).mean(0), np.cos(x).mean(0))  # (J, 3)
    d = _wrap(x - mu[None])  # in (-π, π]
    lo = mu + np.quantile(d, q, axis=0)
    hi = mu + np.quantile(d, 1.0 - q, axis=0)
    return jnp.asarray(np.stack([lo, hi], axis=-1), dtype=jnp.result_type(float))


def joint_limit_violation(
    samples: Float[ArrayLike, "S J 3"],
    limits: Float[ArrayLike, "J 3 2"],
    *,
    order: str | None = None,
) -> float:
    """Fraction of poses with at least one joint angle outside `limits`.

    Each sample is brought to canonical Euler angles (module docs) and every angle is compared with
    its interval modulo 2π: `|wrap(θ - c)| > h` with centre `c = (lower + upper) / 2` and half-width
    `h = (upper - lower) / 2`.

    **Arguments:**

    - `samples`: poses, shape `(S, J, 3)`, radians, Euler order `order`.
    - `limits`: `(J, 3, 2)` from [`bodyprior.dspp.joint_limits`][].
    - `order`: Euler order of `samples`; default `bodyprior.EULER_ORDER`.

    **Returns:** the violating fraction in `[0, 1]` (Python float).

    **Raises:** `ValueError` for mismatched shapes, non-finite values or inverted limits.
    """
    order = _order(order)
    dims: dict[str, int] = {}
    check_array(samples, "samples", ("S", "J", 3), dims=dims)
    check_array(limits, "limits", (dims["J"], 3, 2))
    if dims["S"] < 1:
        raise ValueError("`samples` must hold at least one pose.")
    lim = np.asarray(limits, dtype=np.float64)
    if np.any(lim[..., 1] < lim[..., 0]):
        raise ValueError("`limits` must satisfy lower <= upper for every joint and axis.")
    x = _canonical(np.asarray(samples, dtype=np.float64), order)
    c = 0.5 * (lim[..., 0] + lim[..., 1])
    h = 0.5 * (lim[..., 1] - lim[..., 0])
    d = np.abs(_wrap(x - c[None]))
    # A tiny slack so that the training extremes themselves (quantile 0) never count as outside.
    outside = d > h[None] + 1e-9
    return float(np.mean(np.any(outside, axis=(1, 2))))
