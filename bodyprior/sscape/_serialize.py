"""Saving and loading S-SCAPE models.

Format `bodyprior.sscape`, version 1: one zip file (stored, not compressed) holding

- `metadata.json`: `{"format": "bodyprior.sscape", "version": 1, "parents": [...],
  "joint_names": [...], "leaves": {name: {"shape": [...], "dtype": "float64"}, ...},
  "leaves_sha256": "..."}`;
- `leaves.eqx`: the array leaves, in sorted field-name order, written by
  `eqx.tree_serialise_leaves`.

Writes are atomic (temporary file in the target directory, fsync, `os.replace`). Loading validates
the format name, version, shapes, dtypes and checksum and raises `ValueError` on any mismatch; it
never touches the network.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import zipfile

import equinox as eqx
import numpy as np

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


def save_model(path: str | os.PathLike, model: SScapeModel) -> None:
    """Writes `model` to `path` atomically in the `bodyprior.sscape` v1 format.

    **Arguments:**

    - `path`: destination file (conventionally `*.sscape`); its directory must exist.
    - `model`: an [`bodyprior.sscape.SScapeModel`][] with concrete (not traced) arrays.
    """
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise ValueError(f"`path`: directory {directory!r} does not exist.")
    arrays = {name: np.asarray(getattr(model, name)) for name in _LEAVES}
    payload = _leaves_bytes(arrays)
    metadata = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "parents": list(model.parents),
        "joint_names": list(model.joint_names),
        "leaves": {k: {"shape": list(a.shape), "dtype": a.dtype.str} for k, a in arrays.items()},
        "leaves_sha256": hashlib.sha256(payload).hexdigest(),
    }
    fd, tmp = tempfile.mkstemp(
        prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=directory
    )
    try:
        with os.fdopen(fd, "wb") as f:
            with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as zf:
                zf.writestr("metadata.json", json.dumps(metadata, indent=1))
                zf.writestr("leaves.eqx", payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    try:  # make the rename durable
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def load_model(path: str | os.PathLike) -> SScapeModel:
    """Reads a model written by [`bodyprior.sscape.save_model`][], validating it.

    **Raises:** `ValueError` if the file is missing, not a `bodyprior.sscape` file, of another
    version, or corrupted (checksum, shapes or dtypes disagree with the metadata).
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"`path`: no such file {path!r}.")
    try:
        with zipfile.ZipFile(path, "r") as zf:
            names = set(zf.namelist())
            if not {"metadata.json", "leaves.eqx"} <= names:
                raise ValueError(
                    f"{path!r} is not a {FORMAT_NAME} file (missing metadata.json/leaves.eqx)."
                )
            raw_meta = zf.read("metadata.json")
            payload = zf.read("leaves.eqx")
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError) as e:
        raise ValueError(f"{path!r} is not a readable {FORMAT_NAME} file: {e}") from e
    except zipfile.error as e:  # pragma: no cover - other zip errors (e.g. CRC)
        raise ValueError(f"{path!r} is corrupted: {e}") from e
    try:
        meta = json.loads(raw_meta.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path!r}: metadata.json is not valid JSON: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        got = meta.get("format") if isinstance(meta, dict) else meta
        raise ValueError(f"{path!r}: format must be {FORMAT_NAME!r}, got {got!r}.")
    if meta.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"{path!r}: unsupported {FORMAT_NAME} version {meta.get('version')!r}; this bodyprior "
            f"reads "
            f"version {FORMAT_VERSION}."
        )
    if hashlib.sha256(payload).hexdigest() != meta.get("leaves_sha256"):
        raise ValueError(f"{path!r}: checksum mismatch, the array data are corrupted.")
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
        return SScapeModel(parents=meta["parents"], joint_names=meta["joint_names"], **arrays)
    except (KeyError, TypeError) as e:
        raise ValueError(f"{path!r}: invalid metadata: {e}") from e
