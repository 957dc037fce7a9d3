"""Whole-algorithm programs kept across processes with `jax.export`: no re-tracing in a new one.

JAX's persistent compilation cache ([`bodyprior.enable_compilation_cache`][]) skips XLA's compile
in a second process, but every process still traces the Python program and lowers it to StableHLO
to compute the cache key: for the S-SCAPE fit of `bodyprior register` that is ~4 s of a ~14 s start
on 2 cores (trace 3.2 s + lowering 1.0 s, measured 2026-12-07), more than the fit itself.

[`aot_filter_jit`][] wraps a whole-algorithm entry point like `equinox.filter_jit`. While an
export directory is set (`set_export_directory`, done by `enable_compilation_cache`), the first call
with a new *signature* traces the function once with `jax.export.export`, stores the serialized
program, and every later call, in this process or a new one, deserializes it and runs it: no Python
tracing, no lowering, and its XLA compile is served by the persistent compilation cache.

A signature is everything `equinox.filter_jit` would specialise on, described stably across
processes, plus what the program text depends on:

- the argument tree structure (with `equinox.Module` static fields) and, per leaf, an array's shape,
  dtype and weak type, or a non-array leaf's value (numbers, strings, enums, dataclass configs,
  functions of this package by module and qualified name, closures and `functools.partial` by what
  they hold);
- a digest of this package's Python sources and the versions of jax, jaxlib, equinox, optimistix,
  lineax; the backend, `jax_enable_x64` and the numeric-behaviour flags of `jax.config`.

Anything that cannot be described stably (a function from outside this package, a closure over an
array, an object whose repr holds a memory address), more than one device, or a program that
`jax.export` refuses (host callbacks) falls back to plain `equinox.filter_jit`, so results are the
same with or without the directory. Files are written atomically; an entry that does not load (a
truncated file, another format) is rebuilt. The directory holds pickled output skeletons: point it
only at a directory you own, as for JAX's cache.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import importlib.metadata
import os
import pickle
import re
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ._io import atomic_write_bytes

__all__ = ["aot_filter_jit", "export_directory", "set_export_directory"]

_FORMAT = 1
_PACKAGE = "bodyprior"
_DEPENDENCIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax")
_FLAGS = (
    "jax_enable_x64",
    "jax_default_matmul_precision",
    "jax_numpy_rank_promotion",
    "jax_numpy_dtype_promotion",
    "jax_default_prng_impl",
    "jax_threefry_partitionable",
)
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+|object at|<locals>")


@dataclasses.dataclass
class _Settings:
    """The export directory and the digest of what every program depends on (sources, versions)."""

    directory: str | None = None
    salt: str = ""


_settings = _Settings()


def _source_digest() -> str:
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    for name in _DEPENDENCIES:
        try:
            h.update(f"{name}=={importlib.metadata.version(name)}".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}==?".encode())
    return h.hexdigest()


def set_export_directory(path: str | os.PathLike | None) -> str | None:
    """Sets (or with `None` clears) the directory of exported whole-algorithm programs used by
    [`aot_filter_jit`][] functions; [`bodyprior.enable_compilation_cache`][] sets it to
    `<cache>/exported`. Creates the directory. **Returns:** the absolute path, or `None`."""
    if path is None:
        _settings.directory = None
        return None
    path = os.path.abspath(os.path.expanduser(os.fspath(path)))
    os.makedirs(path, exist_ok=True)
    _settings.salt = _source_digest()
    _settings.directory = path
    return path


def export_directory() -> str | None:
    """The directory set by [`set_export_directory`][] (`None`: exports are off)."""
    return _settings.directory


# --------------------------------------------------------------------------------------------------
# Stable descriptions of static arguments
# --------------------------------------------------------------------------------------------------


class _Unstable(Exception):
    pass


def _own_function(fn) -> bool:
    mod = getattr(fn, "__module__", None) or ""
    return mod == _PACKAGE or mod.startswith(_PACKAGE + ".")


def _describe(x, depth: int = 0) -> str:
    """A string equal across processes exactly when `x` specialises a traced program the same way;
    raises `_Unstable` when there is none."""
    if depth > 20:
        raise _Unstable("too deep")
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, enum.Enum):
        return f"enum:{type(x).__module__}.{type(x).__qualname__}.{x.name}"
    if isinstance(x, np.dtype) or (isinstance(x, type) and issubclass(x, np.generic)):
        return f"dtype:{np.dtype(x).str}"
    if isinstance(x, (tuple, list)):
        inner = ",".join(_describe(v, depth + 1) for v in x)
        return f"{type(x).__name__}({inner})"
    if isinstance(x, dict):
        items = sorted((repr(k), _describe(v, depth + 1)) for k, v in x.items())
        return f"dict({items})"
    if isinstance(x, functools.partial):
        args = _describe(tuple(x.args), depth + 1)
        kw = _describe(dict(x.keywords), depth + 1)
        return f"partial({_describe(x.func, depth + 1)},{args},{kw})"
    if isinstance(x, types.FunctionType):
        if getattr(x, "__wrapped__", None) is not None:
            # a `functools.wraps` decorator (the run-time type checks of jaxtyping, a jit): what
            # the traced program depends on is the wrapped function
            return f"wrapped({_describe(x.__wrapped__, depth + 1)})"
        if not _own_function(x):
            raise _Unstable(f"function {x.__module__}.{x.__qualname__} is not this package's")
        parts = [x.__module__, x.__qualname__]
        if "<lambda>" in x.__qualname__ or "<locals>" in x.__qualname__:
            # nested: its code is in the source digest only by file; pin the code object too
            parts.append(hashlib.sha256(x.__code__.co_code).hexdigest()[:16])
        for cell in x.__closure__ or ():
            parts.append(_describe(cell.cell_contents, depth + 1))
        for d in x.__defaults__ or ():
            parts.append(_describe(d, depth + 1))
        return "fn(" + ",".join(parts) + ")"
    if isinstance(x, type) and _own_function(x):
        return f"type:{x.__module__}.{x.__qualname__}"
    if dataclasses.is_dataclass(x) and not isinstance(x, type) and _own_function(type(x)):
        fields = [
            f"{f.name}={_describe(getattr(x, f.name), depth + 1)}" for f in dataclasses.fields(x)
        ]
        return f"{type(x).__module__}.{type(x).__qualname__}(" + ",".join(fields) + ")"
    raise _Unstable(f"no stable description of a {type(x).__name__}")


def _signature(fn: Callable, leaves: list, treedef) -> str | None:
    """The hex key of a call, or `None` when some part of it has no stable description."""
    structure = str(treedef)
    if _ADDRESS.search(structure):
        return None
    code = getattr(fn, "__code__", None)
    code_id = "" if code is None else hashlib.sha256(code.co_code).hexdigest()[:16]
    parts = [_settings.salt, f"{fn.__module__}.{fn.__qualname__}", code_id, structure]
    parts.append(jax.default_backend())
    parts += [f"{f}={getattr(jax.config, f, None)!r}" for f in _FLAGS]
    try:
        for x in leaves:
            if eqx.is_array(x):
                weak = bool(getattr(x, "weak_type", False))
                parts.append(f"A{tuple(np.shape(x))}{np.dtype(x.dtype).str}{'w' if weak else ''}")
            else:
                parts.append(_describe(x))
    except _Unstable:
        return None
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


# --------------------------------------------------------------------------------------------------
# Exported programs
# --------------------------------------------------------------------------------------------------


class _Slot:
    """Marks where an output array goes in a stored output skeleton."""


@dataclasses.dataclass(frozen=True)
class _Program:
    call: Callable
    skeleton: Any


def _fill(skeleton, arrays):
    it = iter(arrays)
    leaves, treedef = jax.tree_util.tree_flatten(skeleton)
    return jax.tree_util.tree_unflatten(
        treedef, [next(it) if isinstance(x, _Slot) else x for x in leaves]
    )


class aot_filter_jit:
    """`equinox.filter_jit(fn)` whose traced programs are exported to, and loaded from, the
    directory of [`set_export_directory`][] (see the module docstring); without one, exactly
    `equinox.filter_jit`. Use it on whole-algorithm entry points whose tracing costs seconds.

    **Arguments:**

    - `fn`: the function (arguments: pytrees; array leaves traced, other leaves static).
    """

    def __init__(self, fn: Callable):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._jit = eqx.filter_jit(fn)
        self._programs: dict[str, _Program | None] = {}

    def __call__(self, *args):
        if _settings.directory is None or jax.device_count() != 1 or jax.process_count() != 1:
            return self._jit(*args)
        leaves, treedef = jax.tree_util.tree_flatten(args)
        key = _signature(self._fn, leaves, treedef)
        if key is None:
            return self._jit(*args)
        if key not in self._programs:
            path = os.path.join(_settings.directory, f"{self._fn.__qualname__}-{key[:32]}.jexp")
            prog = _load(path, key)
            if prog is None:
                prog = self._export(path, key, leaves, treedef)
            self._programs[key] = prog  # None: not exportable; not tried again in this process
        prog = self._programs[key]
        if prog is None:
            return self._jit(*args)
        return _fill(prog.skeleton, prog.call(*[x for x in leaves if eqx.is_array(x)]))

    def _export(self, path: str, key: str, leaves: list, treedef) -> _Program | None:
        is_arr = [eqx.is_array(x) for x in leaves]
        specs = [
            jax.ShapeDtypeStruct(np.shape(x), x.dtype,
                                 weak_type=bool(getattr(x, "weak_type", False)))
            for x, a in zip(leaves, is_arr) if a
        ]  # fmt: skip
        box: dict[str, Any] = {}

        def flat(*arrays):
            it = iter(arrays)
            full = [next(it) if a else x for x, a in zip(leaves, is_arr)]
            out = self._fn(*jax.tree_util.tree_unflatten(treedef, full))
            box["skeleton"] = jax.tree_util.tree_map(
                lambda x: _Slot() if eqx.is_array(x) else x, out
            )
            return [x for x in jax.tree_util.tree_leaves(out) if eqx.is_array(x)]

        try:
            exported = jax.export.export(jax.jit(flat))(*specs)
            blob = pickle.dumps(
                dict(format=_FORMAT, key=key, exported=bytes(exported.serialize()),
                     skeleton=box["skeleton"]),
                protocol=pickle.HIGHEST_PROTOCOL,
            )  # fmt: skip
        except Exception:  # host callbacks, unpicklable outputs: not exportable, use filter_jit
            return None
        atomic_write_bytes(path, blob)
        return _Program(jax.jit(exported.call), box["skeleton"])


def _load(path: str, key: str) -> _Program | None:
    """The stored program at `path` if it is a valid entry for `key`, else `None`."""
    try:
        with open(path, "rb") as f:
            d = pickle.load(f)
        if not isinstance(d, dict) or d.get("format") != _FORMAT or d.get("key") != key:
            return None
        exported = jax.export.deserialize(bytearray(d["exported"]))
    except Exception:  # missing, truncated or foreign: rebuilt by the caller
        return None
    return _Program(jax.jit(exported.call), d["skeleton"])
