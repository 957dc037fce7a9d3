"""The shipped DSPP priors (`bodyprior/assets/dspp_shape.dspp`, `bodyprior/assets/dspp_pose.dspp`).

Training a prior costs minutes (shape ~6, pose ~6 on 2 cores), so the package ships one of each,
trained by the full mode of `experiments/dspp.py` with the library's presets:

- **shape** ([`default_shape_prior`][]): 4,308 bodies (CAESAR's size) sampled by
  [`bodyprior.sample_population`][] from the default body (`cmu_mb`, CAESAR phenotype scheme, ages
  18-65, exact rest posture), key `PRNGKey(2026)`, on the 6,449-vertex decimated topology
  ([`bodyprior.load_decimated`][]); 10 % of the bodies are the collapse monitor's validation set,
  the rest are trained on; `DSPPConfig.preset("shape")`, 8,000 cycles at batch 16, the last model
  (`select="last"`: the shape AE-GAN does not collapse and its auto-encoder keeps improving).
- **pose** ([`default_pose_prior`][]): every BVH clip of the CMU mocap folder
  ([`bodyprior.find_mocap_dir`][]) retargeted onto `cmu_mb` by [`bodyprior.load_mocap`][] at 4
  frames/s; 10 % of the clips (whole clips, seed 2026) are the monitor's validation set;
  `DSPPConfig.preset("pose")`, 100,000 cycles at batch 64, the monitored model closest to
  validation 1-NNA 0.5 (`select="best"`).

Each file's metadata records that provenance, the checksums of the default-body assets (shape) or of
every BVH file (pose) it was trained on, the training log's summary and the rebuild command,
`python -m bodyprior.dspp.build_priors` (the pose prior needs the mocap folder: `--mocap DIR` or
`$BODYPRIOR_MOCAP_DIR`); the file's payload checksum is verified on load. How well these priors
sample (1-NNA, coverage, diversity against held-out data) is measured by `experiments/dspp.py` with
the same recipe on a train/test split: docs/results_dspp.md.
"""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

from ..registration import template_sources
from ._checkpoint import load_prior, save_prior
from ._nets import DSPPConfig, PosePrior, ShapePrior

PRIOR_FILES = {"shape": "dspp_shape.dspp", "pose": "dspp_pose.dspp"}
SEED = 2026
N_BODIES = 4308
VALIDATION_FRACTION = 0.1
FPS = 4.0
# (cycles, batch, monitor_every, steps_per_call) of experiments/dspp.py's full mode
RECIPES = {"shape": (8000, 16, 1000, 500), "pose": (100_000, 64, 5000, 5000)}
_REBUILD = "rebuild it with `python -m bodyprior.dspp.build_priors`"


def prior_path(kind: str) -> str:
    """Path of the shipped prior file of `kind` ("shape" or "pose")."""
    from ..assets import asset_path

    if kind not in PRIOR_FILES:
        raise ValueError(f"`kind` must be 'shape' or 'pose', got {kind!r}.")
    return os.path.join(os.path.dirname(asset_path()), PRIOR_FILES[kind])


def _load(kind: str, return_info: bool):
    path = prior_path(kind)
    if not os.path.exists(path):
        raise ValueError(f"the shipped DSPP {kind} prior is missing at {path!r}; {_REBUILD}.")
    prior, info = load_prior(path, return_info=True)
    if kind == "shape" and info.get("sources") != template_sources():
        warnings.warn(
            f"{path!r} was trained on other default-body assets than the installed ones; "
            f"{_REBUILD}.",
            stacklevel=3,
        )
    return (prior, info) if return_info else prior


def default_shape_prior(*, return_info: bool = False) -> ShapePrior | tuple[ShapePrior, dict]:
    """The shipped DSPP shape prior (module docstring): samples `(6449, 3)` bodies in metres on the
    decimated topology, rest posture. `return_info=True` also returns its provenance dict.

    **Raises:** `ValueError` if the file is missing or corrupted."""
    return _load("shape", return_info)


def default_pose_prior(*, return_info: bool = False) -> PosePrior | tuple[PosePrior, dict]:
    """The shipped DSPP pose prior (module docstring): samples `(20, 3)` Euler angles in radians
    (`bodyprior.EULER_ORDER`, joints `bodyprior.POSE_JOINTS`; `bodyprior.rig_pose` turns them into
    a `cmu_mb` pose). `return_info=True` also returns its provenance dict.

    **Raises:** `ValueError` if the file is missing or corrupted."""
    return _load("pose", return_info)


def _log_summary(sol, select: str) -> dict:
    log = sol.aux
    tail = max(1, log.n_steps // 10)
    best = int(sol.stats["best_step"])
    out = {
        "cycles": int(log.n_steps),
        "kept_step": best if select == "best" else int(log.n_steps),  # the shipped model's cycle
        "monitor_best_step": best,
        "final_d_loss": round(float(np.mean(log.d_loss[-tail:])), 5),
        "final_g_loss": round(float(np.mean(log.g_loss[-tail:])), 5),
        "wall_time_s": round(float(log.wall_time_s), 1),
    }
    if log.monitor_step.size:
        out["monitor_step"] = log.monitor_step.astype(int).tolist()
        out["monitor_validation_1nna"] = [round(float(x), 4) for x in log.monitor_one_nna]
        out["monitor_diversity"] = [round(float(x), 5) for x in log.monitor_diversity]
        out["monitor_diversity_validation"] = round(float(log.monitor_diversity_ref[-1]), 5)
    return out


def _config(kind: str, **overrides) -> DSPPConfig:
    n, batch, monitor, spc = RECIPES[kind]
    kw = dict(n_steps=n, batch_size=batch, monitor_every=monitor, steps_per_call=spc)
    kw.update(overrides)
    return DSPPConfig.preset(kind, **kw)


def build_default_shape_prior(
    path: str | None = None, *, progress: bool = True, log=print, n_bodies: int = N_BODIES,
    **config_overrides,
) -> dict:  # fmt: skip
    """Trains the shipped shape prior (module docstring) and writes it atomically to `path`
    (default: the shipped location). `n_bodies` and `config_overrides` (fields of `DSPPConfig`)
    exist for quick checks; the shipped file uses the defaults. **Returns:** the provenance dict."""
    from .. import load_decimated, sample_population
    from ._train import train_shape_prior

    path = os.path.abspath(path or prior_path("shape"))
    t0 = time.perf_counter()
    vertex_map, _ = load_decimated()
    pop = sample_population(n_bodies, key=jr.PRNGKey(SEED), progress=progress)
    x = np.asarray(pop.vertices[:, np.asarray(vertex_map)], np.float32)
    del pop
    perm = np.random.default_rng(SEED).permutation(n_bodies)
    n_val = max(2, int(round(VALIDATION_FRACTION * n_bodies)))
    train, val = x[perm[n_val:]], x[perm[:n_val]]
    cfg = _config("shape", **config_overrides)
    sol = train_shape_prior(
        train, key=jr.PRNGKey(SEED), config=cfg, validation=val, select="last", progress=progress
    )
    info = {
        "built_by": "bodyprior.dspp._default.build_default_shape_prior "
        "(python -m bodyprior.dspp.build_priors --which shape)",
        "data": {
            "generator": "bodyprior.sample_population (default body, cmu_mb, scheme caesar, "
            "ages 18-65, rest posture), decimated topology",
            "n_bodies": int(n_bodies),
            "n_train": int(train.shape[0]),
            "n_validation": int(val.shape[0]),
            "n_vertices": int(x.shape[1]),
            "seed": SEED,
        },
        "preset": "shape",
        "select": "last",
        "training": _log_summary(sol, "last"),
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "sources": template_sources(),
        "build_seconds": round(time.perf_counter() - t0, 1),
    }
    save_prior(path, sol.value, info=info)
    log(f"{path}: shape prior, {train.shape[0]} bodies, {info['training']['cycles']} cycles "
        f"({info['build_seconds']} s, {os.path.getsize(path) / 2**20:.1f} MiB)")  # fmt: skip
    return info


def build_default_pose_prior(
    path: str | None = None, *, mocap_dir=None, progress: bool = True, log=print,
    **config_overrides,
) -> dict:  # fmt: skip
    """Trains the shipped pose prior (module docstring) on every BVH clip under `mocap_dir`
    (default [`bodyprior.find_mocap_dir`][]) and writes it atomically to `path` (default: the
    shipped location). **Returns:** the provenance dict.

    **Raises:** `ValueError` if no mocap folder is found."""
    from .. import find_mocap_dir, load_mocap, mocap_checksums, split_by_clip
    from ._train import train_pose_prior

    root = Path(mocap_dir) if mocap_dir is not None else find_mocap_dir()
    if root is None or not Path(root).is_dir():
        raise ValueError(
            "`mocap_dir`: no CMU mocap folder found; pass --mocap DIR or set $BODYPRIOR_MOCAP_DIR."
        )
    root = Path(root)
    path = os.path.abspath(path or prior_path("pose"))
    t0 = time.perf_counter()
    poses = load_mocap(str(root), fps=FPS, progress=progress)
    train, val = split_by_clip(poses, VALIDATION_FRACTION, seed=SEED)
    cfg = _config("pose", **config_overrides)
    sol = train_pose_prior(
        np.asarray(train.euler, np.float32), key=jr.PRNGKey(SEED), config=cfg,
        validation=np.asarray(val.euler, np.float32), select="best", progress=progress,
    )  # fmt: skip
    info = {
        "built_by": "bodyprior.dspp._default.build_default_pose_prior "
        "(python -m bodyprior.dspp.build_priors --which pose [--mocap DIR])",
        "data": {
            "source": "CMU motion capture (BVH), retargeted onto cmu_mb by bodyprior.load_mocap",
            "fps": FPS,
            "n_clips": len(poses.clip_names),
            "n_poses": int(poses.n_poses),
            "n_train": int(train.n_poses),
            "n_validation": int(val.n_poses),
            "validation_clips": sorted(val.clip_names[i] for i in np.unique(np.asarray(val.clip))),
            "bvh": mocap_checksums(root),
            "seed": SEED,
        },
        "preset": "pose",
        "select": "best",
        "training": _log_summary(sol, "best"),
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "build_seconds": round(time.perf_counter() - t0, 1),
    }
    save_prior(path, sol.value, info=info)
    log(f"{path}: pose prior, {train.n_poses} poses from {len(poses.clip_names)} clips, kept cycle "
        f"{info['training']['kept_step']} ({info['build_seconds']} s, "
        f"{os.path.getsize(path) / 2**20:.2f} MiB)")  # fmt: skip
    return info
