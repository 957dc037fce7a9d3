"""Shared linear-algebra kernels: preconditioned conjugate gradients for SPD normal equations.

Used by NRD (`bodyprior.registration.nrd`, the per-round template system) and by the PanoMan
decoder (`bodyprior.panoman.rla_decode`, the frame system). Pure functions of traced arrays,
usable under `jit`, `vmap` and inside `jax.lax.custom_linear_solve`.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

__all__ = ["pcg"]


def pcg(
    matvec: Callable[[Array], Array],
    precondition: Callable[[Array], Array],
    rhs: Float[ArrayLike, "*n k"],
    x0: Float[ArrayLike, "*n k"],
    *,
    rtol: float | Float[ArrayLike, ""],
    max_steps: int,
    rounding_level: Float[Array, " k"] | None = None,
) -> tuple[Float[Array, "*n k"], Int[Array, ""], Float[Array, ""]]:
    """Preconditioned CG for `A X = rhs`, one independent recursion per right-hand side.

    `A` (`matvec`) must be symmetric positive (semi-)definite and act on arrays shaped like `rhs`;
    `precondition` applies `M⁻¹ ≈ A⁻¹` (symmetric positive definite). The **last axis** of `rhs`
    indexes independent right-hand sides that share `A` (inner products sum over all other axes),
    e.g. the three world coordinates of a vertex system.

    Stops when the preconditioned residual norm `sqrt(rᵀ M⁻¹ r)` of every column is at most `rtol`
    times that at the start: with `M ≈ A` this is the error in the energy norm, so the remaining
    energy gap is about `rtol²` of the gap at the (warm) start. Residuals at rounding level (a
    start at the solution) count as converged: rounding level is `64 ε` times the preconditioned
    norm of `rhs`, or `64 ε · sqrt(rounding_level)` where given (per column: the squared size of
    the terms that cancel in the residual, for systems whose `rhs` is much smaller than them).

    **Returns:** `(X, steps, ratio)`: the solution, the number of CG steps taken (`int32`) and the
    final ratio of the true residual's preconditioned norm to the starting one (the worst column);
    `ratio <= rtol` unless the step limit stopped it.
    """
    axes = tuple(range(rhs.ndim - 1))

    def dot(a, b):
        return jnp.sum(a * b, axis=axes)

    tiny = jnp.finfo(x0.dtype).tiny
    r = rhs - matvec(x0)
    z = precondition(r)
    rz = dot(r, z)
    ref = dot(rhs, precondition(rhs)) if rounding_level is None else rounding_level
    floor = (64 * jnp.finfo(x0.dtype).eps) ** 2 * ref
    rz0 = jnp.where(rz > floor, rz, 0.0)

    def ratio(rz):
        return jnp.sqrt(
            jnp.max(jnp.where(rz0 > 0, jnp.maximum(rz, 0.0) / jnp.maximum(rz0, tiny), 0.0))
        )

    def cond(s):
        k, _, _, _, rz = s
        return (k < max_steps) & (ratio(rz) > rtol)

    def body(s):
        k, x, r, p, rz = s
        ap = matvec(p)
        pap = dot(p, ap)
        alpha = jnp.where(pap > 0, rz / jnp.where(pap > 0, pap, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        rz_new = dot(r, z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return k + 1, x, r, z + beta * p, rz_new

    k, x, _, _, rz = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), x0, r, z, rz))
    r = rhs - matvec(x)  # the true residual, not the recursive one
    return x, k, ratio(dot(r, precondition(r)))
