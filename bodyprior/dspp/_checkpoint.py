"""Saving DSPP priors and training checkpoints.

Both are one zip file (stored, not compressed) written atomically (`bodyprior.atomic_open`):

- `metadata.json`: format name and version, what is stored (class, kind, network config), array
  shapes, and the sha256 of the payload;
- `leaves.eqx`: every array leaf of the PyTree, written by `eqx.tree_serialise_leaves`;
- checkpoints only: `records.npy`, the per-cycle loss record so far.

Loading rebuilds the PyTree skeleton from the stored config and fills it in, validating format,
version, checksum and the structure; any mismatch raises `ValueError`. A checkpoint also stores the
training key and a fingerprint of the (normalised) training data, and is only resumed for the same
data, key and network sizes.
"""

from __future__ import annotations

import hashlib
import io
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._io import _read_zip, _write_zip
from ._nets import (
    _V1_DEFAULTS,
    DSPPConfig,
    GeometryGAN,
    PosePrior,
    ShapePrior,
    init_aegan,
    init_geometry_gan,
)

PRIOR_FORMAT = "bodyprior.dspp.prior"
CHECKPOINT_FORMAT = "bodyprior.dspp.checkpoint"
FORMAT_VERSION = 1

_CLASSES = {"ShapePrior": ShapePrior, "PosePrior": PosePrior, "GeometryGAN": GeometryGAN}


def _serialise(tree) -> bytes:
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, tree)
    return buf.getvalue()


def _deserialise(payload: bytes, like, path: str):
    try:
        return eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    except Exception as e:  # shape/dtype mismatch or truncated payload
        raise ValueError(f"{path!r}: stored arrays do not match the expected structure: {e}") from e


def _skeleton(cls_name: str, kind: str, item_shape, config: DSPPConfig):
    mean = jnp.zeros(tuple(item_shape), jnp.float32)
    key = jax.random.PRNGKey(0)
    if cls_name == "GeometryGAN":
        return init_geometry_gan(kind, mean, 1.0, config, key=key)
    return init_aegan(kind, mean, 1.0, config, key=key)


# --------------------------------------------------------------------------------------------------
# Priors


def save_prior(
    path: str | os.PathLike,
    prior: ShapePrior | PosePrior | GeometryGAN,
    *,
    info: dict | None = None,
) -> None:
    """Writes a trained prior ([`bodyprior.dspp.ShapePrior`][], [`bodyprior.dspp.PosePrior`][] or
    [`bodyprior.dspp.GeometryGAN`][]) to `path` atomically (format `bodyprior.dspp.prior` v1).
    `info`: an optional JSON-serialisable provenance dict stored with it (training data, seed,
    build command), returned by `load_prior(path, return_info=True)`."""
    if info is not None and not isinstance(info, dict):
        raise ValueError(f"`info` must be a dict or None, got {type(info).__name__}.")
    cls_name = type(prior).__name__
    if cls_name not in _CLASSES or not isinstance(prior, _CLASSES[cls_name]):
        raise ValueError(
            f"`prior` must be a ShapePrior, PosePrior or GeometryGAN, got {type(prior).__name__}."
        )
    kind = prior.kind if isinstance(prior, GeometryGAN) else (
        "shape" if isinstance(prior, ShapePrior) else "pose"
    )  # fmt: skip
    payload = _serialise(prior)
    meta = {
        "format": PRIOR_FORMAT,
        "version": FORMAT_VERSION,
        "class": cls_name,
        "kind": kind,
        "item_shape": list(prior.mean.shape),
        "config": prior.config.to_dict(),
    }
    if info is not None:
        meta["info"] = info
    _write_zip(os.fspath(path), meta, {"leaves.eqx": payload})


def load_prior(path: str | os.PathLike, *, return_info: bool = False):
    """Reads a prior written by [`bodyprior.dspp.save_prior`][], validating it.

    **Returns:** the `ShapePrior`, `PosePrior` or `GeometryGAN`; with `return_info=True`,
    `(prior, info)` where `info` is the provenance dict stored by `save_prior` (`{}` if none).

    **Raises:** `ValueError` if the file is missing, of another format/version, or corrupted."""
    path = os.fspath(path)
    meta, data = _read_zip(path, PRIOR_FORMAT, FORMAT_VERSION, ("leaves.eqx",))
    cls_name, kind = meta.get("class"), meta.get("kind")
    if cls_name not in _CLASSES or kind not in ("shape", "pose"):
        raise ValueError(f"{path!r}: unknown class/kind {cls_name!r}/{kind!r}.")
    try:
        config = DSPPConfig.from_dict(meta.get("config"))
        item_shape = tuple(int(s) for s in meta.get("item_shape"))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path!r}: invalid metadata: {e}") from e
    # The skeleton's shapes only (no initialisation compiled: ~6 s -> 0.1 s per new process).
    like = eqx.filter_eval_shape(_skeleton, cls_name, kind, item_shape, config)
    prior = _deserialise(data["leaves.eqx"], like, path)
    return (prior, dict(meta.get("info") or {})) if return_info else prior


# --------------------------------------------------------------------------------------------------
# Training checkpoints


def _resume_config(cfg: DSPPConfig) -> dict:
    # Everything that changes the computation; `n_steps` may grow between runs.
    d = cfg.to_dict()
    d.pop("n_steps")
    return d


def _fingerprint(u: np.ndarray) -> str:
    h = hashlib.sha256(np.ascontiguousarray(u).view(np.uint8))
    h.update(repr(u.shape).encode())
    return h.hexdigest()


def checkpoint_path(checkpoint_dir, tag: str) -> str:
    return os.path.join(os.fspath(checkpoint_dir), f"{tag}.ckpt")


def _npy(a, dtype) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(a, dtype), allow_pickle=False)
    return buf.getvalue()


def save_checkpoint(
    checkpoint_dir, tag, ts, cfg: DSPPConfig, key, u, records, monitor=None
) -> None:
    """`monitor`: optional `(rows (M, 4), best model, best step)` of the collapse monitor, stored
    as the members `monitor.npy` and `best.eqx` (absent in checkpoints without a monitor)."""
    payload = _serialise(ts)
    meta = {
        "format": CHECKPOINT_FORMAT,
        "version": FORMAT_VERSION,
        "tag": tag,
        "step": int(ts.step),
        "config": _resume_config(cfg),
        "key": [int(k) for k in np.asarray(key)],
        "data_sha256": _fingerprint(u),
    }
    members = {"leaves.eqx": payload, "records.npy": _npy(records, np.float32)}
    if monitor is not None and monitor[1] is not None:
        rows, best, best_step = monitor
        meta["best_step"] = int(best_step)
        members["monitor.npy"] = _npy(rows, np.float64)
        members["best.eqx"] = _serialise(best)
    _write_zip(checkpoint_path(checkpoint_dir, tag), meta, members)


def load_checkpoint(checkpoint_dir, tag, like, cfg: DSPPConfig, key, u):
    """Returns `(train_state, records, monitor_rows, best_model, best_step)` from
    `checkpoint_dir/<tag>.ckpt`, or `None` if there is no checkpoint (`monitor_rows` `(0, 4)`,
    `best_model` `None` and `best_step` -1 for a checkpoint without a collapse monitor, e.g. any
    written before it existed). Raises `ValueError` if it belongs to another run (data, key,
    sizes) or is corrupt."""
    d = os.fspath(checkpoint_dir)
    if not os.path.isdir(d):
        raise ValueError(f"`checkpoint_dir`: no such directory {d!r}.")
    path = checkpoint_path(d, tag)
    if not os.path.exists(path):
        return None
    meta, data = _read_zip(path, CHECKPOINT_FORMAT, FORMAT_VERSION, ("leaves.eqx", "records.npy"),
                           optional=("monitor.npy", "best.eqx"))  # fmt: skip
    if meta.get("tag") != tag:
        raise ValueError(f"{path!r}: checkpoint of {meta.get('tag')!r}, expected {tag!r}.")
    stored = meta.get("config")
    if isinstance(stored, dict):  # written before the newer config fields: the paper's values
        stored = {k: v for k, v in {**_V1_DEFAULTS, **stored}.items() if k != "n_steps"}
    if stored != _resume_config(cfg):
        raise ValueError(
            f"{path!r}: the checkpoint was written with another config {meta.get('config')}; "
            "use a fresh `checkpoint_dir` or the same config."
        )
    if meta.get("key") != [int(k) for k in np.asarray(key)]:
        raise ValueError(f"{path!r}: the checkpoint was written with another `key`.")
    if meta.get("data_sha256") != _fingerprint(u):
        raise ValueError(f"{path!r}: the checkpoint was written for other training data.")
    ts = _deserialise(data["leaves.eqx"], like, path)
    try:
        records = np.load(io.BytesIO(data["records.npy"]), allow_pickle=False)
    except ValueError as e:
        raise ValueError(f"{path!r}: records.npy is corrupted: {e}") from e
    if records.shape != (int(ts.step), 5) or int(ts.step) != meta.get("step"):
        raise ValueError(f"{path!r}: step count and loss record disagree.")
    rows, best, best_step = np.zeros((0, 4)), None, -1
    if "best.eqx" in data and "monitor.npy" in data:
        try:
            rows = np.load(io.BytesIO(data["monitor.npy"]), allow_pickle=False)
        except ValueError as e:
            raise ValueError(f"{path!r}: monitor.npy is corrupted: {e}") from e
        if rows.ndim != 2 or rows.shape[1] != 4:
            raise ValueError(f"{path!r}: monitor.npy must have shape (M, 4), got {rows.shape}.")
        best = _deserialise(data["best.eqx"], like.model, path)
        best_step = int(meta.get("best_step", -1))
    return ts, records, rows, best, best_step
