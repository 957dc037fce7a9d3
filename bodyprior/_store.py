"""Saving and loading results: populations, pose sets, fits, registrations (`bodyprior.save` /
`bodyprior.load`).

Format `bodyprior.store`, version 1: one zip file (stored, written atomically) holding

- `metadata.json`: `{"format": "bodyprior.store", "version": 1, "tree": ..., "info": {...},
  "leaves_sha256": "..."}`, where `tree` describes the object: a registered type
  `{"type": NAME, "fields": {field: tree}}`, an array `{"array": KEY, "jax": bool}`, a plain
  value `{"value": v}` (None, bool, int, float, str, or a tuple/list of them, `"tuple": true`);
- `arrays.npz`: the arrays (NumPy `.npz`, no pickles), checksummed.

Only registered types load (no code runs from a file): `Population`, `PoseSet`, `Similarity`,
`Measurements` of the core, and what the families register (`bodyprior.sscape.SScapeFit`,
`bodyprior.sscape.Registration`, `bodyprior.registration.NRDFit`, ...). A type registers itself
with `register_type(cls)` when its module is imported; `import bodyprior` imports them all.
Loading rebuilds the object through its constructor, so a Module's own validation runs.
"""

from __future__ import annotations

import dataclasses
import io
import os
from typing import Any

import jax
import numpy as np

from ._io import _read_zip, _write_zip

FORMAT_NAME = "bodyprior.store"
FORMAT_VERSION = 1
_PAYLOAD = "arrays.npz"
_TYPES: dict[str, type] = {}


def register_type(cls: type, name: str | None = None) -> type:
    """Lets [`bodyprior.save`][] write and [`bodyprior.load`][] rebuild `cls` (an `eqx.Module`,
    dataclass or NamedTuple whose fields are arrays, plain values or registered types).
    Returns `cls`, so it can decorate a class."""
    key = name or f"{cls.__module__.split('.')[0]}.{cls.__qualname__}"
    if _TYPES.get(key, cls) is not cls:
        raise ValueError(f"type name {key!r} is already registered to another class.")
    _TYPES[key] = cls
    cls.__bodyprior_store_name__ = key
    return cls


def _fields(obj) -> list[str]:
    if hasattr(obj, "_fields") and isinstance(obj, tuple):  # NamedTuple
        return list(obj._fields)
    return [f.name for f in dataclasses.fields(obj)]


def _plain(v) -> bool:
    return v is None or isinstance(v, (bool, int, float, str))


def _encode(obj, where: str, arrays: dict) -> dict:
    name = getattr(type(obj), "__bodyprior_store_name__", None)
    if name is not None and _TYPES.get(name) is type(obj):
        return {
            "type": name,
            "fields": {f: _encode(getattr(obj, f), f"{where}.{f}", arrays) for f in _fields(obj)},
        }
    if isinstance(obj, (jax.Array, np.ndarray, np.generic)) and not isinstance(obj, np.bool_):
        if isinstance(obj, jax.core.Tracer):
            raise ValueError(f"`obj`: {where} is a traced array; save concrete values.")
        key = f"a{len(arrays)}"
        arrays[key] = np.asarray(obj)
        return {"array": key, "jax": isinstance(obj, jax.Array)}
    if isinstance(obj, np.bool_):
        return {"value": bool(obj)}
    if _plain(obj):
        return {"value": obj}
    if isinstance(obj, (tuple, list)) and all(_plain(v) for v in obj):
        return {"value": list(obj), "tuple": isinstance(obj, tuple)}
    raise ValueError(
        f"`obj`: {where} is a {type(obj).__name__}, which bodyprior.save cannot store (arrays, "
        f"plain values and the registered types {sorted(_TYPES)} only)."
    )


def _decode(node, arrays, path: str, where: str):
    if not isinstance(node, dict):
        raise ValueError(f"{path!r}: corrupted tree at {where}.")
    if "type" in node:
        cls = _TYPES.get(node["type"])
        if cls is None:
            raise ValueError(
                f"{path!r}: {where} has type {node['type']!r}, which is not registered (import "
                "the module that defines it, or a newer bodyprior)."
            )
        fields = node.get("fields")
        if not isinstance(fields, dict):
            raise ValueError(f"{path!r}: corrupted tree at {where}.")
        kwargs = {k: _decode(v, arrays, path, f"{where}.{k}") for k, v in fields.items()}
        try:
            return cls(**kwargs)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path!r}: could not rebuild {node['type']} at {where}: {e}") from e
    if "array" in node:
        key = node["array"]
        if key not in arrays:
            raise ValueError(f"{path!r}: array {key!r} of {where} is missing.")
        a = arrays[key]
        return jax.numpy.asarray(a) if node.get("jax") else a
    if "value" in node:
        v = node["value"]
        return tuple(v) if node.get("tuple") else v
    raise ValueError(f"{path!r}: corrupted tree at {where}.")


def save(path: str | os.PathLike, obj: Any, *, info: dict | None = None) -> None:
    """Writes a result object to `path` atomically (format `bodyprior.store` v1, see the module
    docstring).

    **Arguments:**

    - `path`: destination file (conventionally `*.bp`); its directory must exist.
    - `obj`: a registered object: a [`bodyprior.Population`][], [`bodyprior.PoseSet`][],
      [`bodyprior.Similarity`][], [`bodyprior.sscape.SScapeFit`][],
      [`bodyprior.sscape.Registration`][], ... (concrete arrays, not traced).
    - `info`: optional JSON-serialisable dict stored alongside (returned by `load(...,
      return_info=True)`).

    **Raises:** `ValueError` naming the field that cannot be stored.
    """
    import json

    if getattr(type(obj), "__bodyprior_store_name__", None) is None:
        raise ValueError(
            f"`obj` must be one of the registered types {sorted(_TYPES)}, got {type(obj).__name__}."
        )
    if info is not None:
        if not isinstance(info, dict):
            raise ValueError(f"`info` must be a dict or None, got {type(info).__name__}.")
        try:
            json.dumps(info)
        except (TypeError, ValueError) as e:
            raise ValueError(f"`info` must be JSON-serialisable: {e}") from None
    arrays: dict[str, np.ndarray] = {}
    tree = _encode(obj, type(obj).__name__, arrays)
    if any(a.dtype == object for a in arrays.values()):
        raise ValueError("`obj` holds an object array; only numeric and bool arrays are stored.")
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "tree": tree, "info": info or {}}
    _write_zip(path, meta, {_PAYLOAD: buf.getvalue()}, payload=_PAYLOAD)


def load(path: str | os.PathLike, *, return_info: bool = False):
    """Reads an object written by [`bodyprior.save`][], validating format, version and checksum.

    **Returns:** the object (JAX arrays where it held JAX arrays), or `(obj, info)`.

    **Raises:** `ValueError` for a missing, foreign or corrupted file, or an unregistered type.
    """
    path = os.fspath(path)
    meta, data = _read_zip(path, FORMAT_NAME, FORMAT_VERSION, (_PAYLOAD,), payload=_PAYLOAD)
    try:
        with np.load(io.BytesIO(data[_PAYLOAD]), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError) as e:
        raise ValueError(f"{path!r}: could not read the arrays: {e}") from e
    obj = _decode(meta.get("tree"), arrays, path, "obj")
    info = meta.get("info", {})
    return (obj, info) if return_info else obj
