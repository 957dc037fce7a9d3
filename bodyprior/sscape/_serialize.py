"""Saving and loading S-SCAPE models.

Format `bodyprior.sscape`, version 1: one zip file (stored, not compressed) holding

- `metadata.json`: `{"format": "bodyprior.sscape", "version": 1, "parents": [...],
  "joint_names": [...], "leaves": {name: {"shape": [...], "dtype": "float64"}, ...},
  "leaves_sha256": "..."}`;
- `leaves.eqx`: the array leaves, in sorted field-name order, written by
  `eqx.tree_serialise_leaves`. The rig's arrays keep the names they had as fields of the model
  before it held a [`bodyprior.Rig`][] (`skin_indices`, `skin_weights`,
  `joint_regressor_indices`, `joint_regressor_weights`), so files written before and after that
  change are the same format and load alike.

Writes are atomic (temporary file in the target directory, fsync, `os.replace`). Loading validates
the format name, version, shapes, dtypes and checksum and raises `ValueError` on any mismatch; it
never touches the network.
"""

from __future__ import annotations

import io
import json
import os

import equinox as eqx
import numpy as np

from .._io import _read_zip, _write_zip
from .._rig import Rig
from ._model import SScapeModel

FORMAT_NAME = "bodyprior.sscape"
FORMAT_VERSION = 1

_LEAVES = (
    "basis",
    "explained_variance",
    "faces",
    "joint_regressor_indices",
    "joint_regressor_weights",
    "mean",
    "skin_indices",
    "skin_weights",
    "stddev",
)


def _leaves_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, arrays)
    return buf.getvalue()


def save_model(path: str | os.PathLike, model: SScapeModel, *, info: dict | None = None) -> None:
    """Writes `model` to `path` atomically in the `bodyprior.sscape` v1 format.

    **Arguments:**

    - `path`: destination file (conventionally `*.sscape`); its directory must exist.
    - `model`: an [`bodyprior.sscape.SScapeModel`][] with concrete (not traced) arrays.
    - `info`: optional JSON-serialisable provenance (how the model was made), stored in the
      metadata under `"info"` and returned by `load_model(path, return_info=True)`.
    """
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    if info is not None:
        if not isinstance(info, dict):
            raise ValueError(f"`info` must be a dict or None, got {type(info).__name__}.")
        try:
            json.dumps(info)
        except (TypeError, ValueError) as e:
            raise ValueError(f"`info` must be JSON-serialisable: {e}") from None
    arrays = {name: np.asarray(getattr(model, name)) for name in _LEAVES}
    payload = _leaves_bytes(arrays)
    metadata = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "parents": list(model.parents),
        "joint_names": list(model.joint_names),
        "leaves": {k: {"shape": list(a.shape), "dtype": a.dtype.str} for k, a in arrays.items()},
    }
    if info is not None:
        metadata["info"] = info
    _write_zip(path, metadata, {"leaves.eqx": payload})


def load_model(path: str | os.PathLike, *, return_info: bool = False):
    """Reads a model written by [`bodyprior.sscape.save_model`][], validating it.

    **Returns:** the [`bodyprior.sscape.SScapeModel`][], or `(model, info)` with
    `return_info=True` (`info`: the dict given to `save_model`, `{}` if none).

    **Raises:** `ValueError` if the file is missing, not a `bodyprior.sscape` file, of another
    version, or corrupted (checksum, shapes or dtypes disagree with the metadata).
    """
    path = os.fspath(path)
    meta, data = _read_zip(path, FORMAT_NAME, FORMAT_VERSION, ("leaves.eqx",))
    payload = data["leaves.eqx"]
    spec = meta.get("leaves")
    if not isinstance(spec, dict) or set(spec) != set(_LEAVES):
        raise ValueError(f"{path!r}: metadata must describe exactly the leaves {list(_LEAVES)}.")
    try:
        like = {
            k: np.zeros(tuple(spec[k]["shape"]), dtype=np.dtype(spec[k]["dtype"])) for k in _LEAVES
        }
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"{path!r}: invalid leaf shape/dtype in metadata: {e}") from e
    try:
        arrays = eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    except Exception as e:  # noqa: BLE001 - any parse failure is a corrupt file
        raise ValueError(f"{path!r}: could not read the array data: {e}") from e
    for k in _LEAVES:
        a = arrays[k]
        if a.shape != like[k].shape or a.dtype != like[k].dtype:
            raise ValueError(
                f"{path!r}: leaf {k!r} has shape {a.shape} dtype {a.dtype}, metadata says "
                f"{like[k].shape} {like[k].dtype}."
            )
    try:
        rig = Rig(
            parents=meta["parents"],
            joint_names=meta["joint_names"],
            skin_indices=arrays.pop("skin_indices"),
            skin_weights=arrays.pop("skin_weights"),
            regressor_indices=arrays.pop("joint_regressor_indices"),
            regressor_weights=arrays.pop("joint_regressor_weights"),
        )
        model = SScapeModel(rig=rig, **arrays)
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path!r}: invalid metadata: {e}") from e
    if not return_info:
        return model
    info = meta.get("info", {})
    if not isinstance(info, dict):
        raise ValueError(f"{path!r}: metadata 'info' must be an object, got {type(info).__name__}.")
    return model, info
