"""Host-side input checks.

Every public entry point validates its inputs here, before anything is traced, so that bad input
gets a
`ValueError` naming the argument and the expected shape or range instead of an error from inside
XLA.
Arrays that are tracers (inside a user's `jit`) are only checked for shape and dtype kind.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np


def is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def as_device_array(x, dtype=None) -> jax.Array:
    """`jnp.asarray(x, dtype)`, without a compiled program for host (NumPy) values.

    In jax 0.10 `jnp.asarray` of a NumPy array runs a small jitted program (`stage`, plus
    `convert_element_type` for a dtype change) compiled once per shape and dtype, 10-20 ms each: a
    `bodyprior register` start spent ~0.7 s in ~45 of them (2026-12-07). NumPy values are cast on
    the host and moved with `jax.device_put` (~1 ms; the dtype canonicalised as `jnp.asarray` does,
    float64 -> float32 without x64). Anything else (tracers, JAX arrays, Python scalars and lists)
    goes to `jnp.asarray`.
    """
    if not isinstance(x, (np.ndarray, np.generic)):
        import jax.numpy as jnp

        return jnp.asarray(x, dtype)
    a = np.asarray(x) if dtype is None else np.asarray(x, dtype=np.dtype(dtype))
    return jax.device_put(a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False))


def _shape_str(shape: Sequence[int | str | None]) -> str:
    return (
        "("
        + ", ".join("*" if s is None else str(s) for s in shape)
        + ("," if len(shape) == 1 else "")
        + ")"
    )


def check_array(
    x,
    name: str,
    shape: Sequence[int | str | None],
    *,
    finite: bool = True,
    integer: bool = False,
    dims: dict[str, int] | None = None,
):
    """Checks `x` against a shape spec and returns it unchanged.

    **Arguments:**

    - `x`: array-like (NumPy, JAX, or a tracer).
    - `name`: argument name used in the error message.
    - `shape`: expected shape; entries are ints (exact), `None` (any size), or strings naming a size
      that
      must agree with other arrays sharing `dims`.
    - `finite`: also reject NaN/inf (skipped for tracers).
    - `integer`: require an integer dtype.
    - `dims`: dictionary of named sizes, filled in and checked across calls.

    **Returns:** `x`.
    """
    if not hasattr(x, "shape"):
        x = np.asarray(x)
    xs = tuple(x.shape)
    if len(xs) != len(shape):
        raise ValueError(f"`{name}` must have shape {_shape_str(shape)}, got shape {xs}.")
    dims = {} if dims is None else dims
    for got, want in zip(xs, shape):
        if want is None:
            continue
        if isinstance(want, str):
            if want in dims and dims[want] != got:
                raise ValueError(
                    f"`{name}` must have shape {_shape_str(shape)} with {want}={dims[want]}, "
                    f"got shape {xs}."
                )
            dims[want] = got
        elif got != want:
            raise ValueError(f"`{name}` must have shape {_shape_str(shape)}, got shape {xs}.")
    kind = np.dtype(x.dtype).kind
    if integer and kind not in "iu":
        raise ValueError(f"`{name}` must have an integer dtype, got {x.dtype}.")
    if not integer and kind not in "fiub":
        raise ValueError(f"`{name}` must be a real numeric array, got dtype {x.dtype}.")
    if finite and not integer and not is_tracer(x):
        if not bool(np.all(np.isfinite(np.asarray(x)))):
            raise ValueError(f"`{name}` contains NaN or infinite values.")
    return x


def check_range(x, name: str, lo: float, hi: float):
    """Rejects concrete values outside `[lo, hi]` (tracers pass through)."""
    if not is_tracer(x):
        a = np.asarray(x)
        if a.size and (a.min() < lo or a.max() > hi):
            raise ValueError(
                f"`{name}` must lie in [{lo}, {hi}], got values in [{a.min()}, {a.max()}]."
            )
    return x


def check_positive_int(value, name: str) -> int:
    """A positive Python (or NumPy) int, not a bool; else `ValueError` naming `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"`{name}` must be a positive int, got {value!r}.")
    return int(value)


def named_preset(cls, table: dict[str, dict], name: str, overrides: dict):
    """`cls(**table[name], **overrides)` (overrides win), the `preset` classmethod of the config
    classes; `ValueError` naming `name` and the choices for an unknown preset."""
    if name not in table:
        raise ValueError(f"`name` must be one of {sorted(table)}, got {name!r}.")
    return cls(**{**table[name], **overrides})
