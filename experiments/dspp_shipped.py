"""The shipped DSPP priors (`bp.dspp.default_shape_prior()`, `default_pose_prior()`), measured.

The shipped priors were trained on all of their data (bodyprior/dspp/_default.py), so this measures
them against data they were not trained on:

- **shape**: `--n-eval` fresh bodies from the same population generator with another key
  (`PRNGKey(--seed)`, the prior's was 2026), on the decimated topology, against as many prior
  samples; the training bodies (key 2026) are the specificity reference. Also the
  auto-encoder's reconstruction error of the fresh bodies (mm).
- **pose**: the monitor's validation clips (held out of training; they chose the kept cycle,
  so this is the selection score, mildly optimistic), against as many prior samples; the training
  clips are the specificity reference.

Beside each: a Gaussian PCA prior with as many components as the latent size, fitted to the same
training data (`bp.dspp.fit_pca_prior`), and real training items as the reference row.
Metrics: `bp.generative_metrics` (1-NNA 0.5 ideal, COV, MMD, specificity, diversity), shapes in mm
(mean vertex distance), poses in degrees (mean per-joint geodesic angle); joint-limit violations
of pose samples (`bp.dspp.joint_limit_violation` with 5 degrees tolerance).

Usage: `python experiments/dspp_shipped.py --out out/dspp_shipped [--quick]` (full: 400 bodies
and 600 poses, a few minutes; `--quick`: 48 and 64). Writes `metrics.json`, `samples.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

import bodyprior as bp
from bodyprior import dspp


def _metrics(prefix, gen, ref, train, metric, unit) -> dict:
    m = bp.generative_metrics(gen, ref, metric, train=train)
    return {
        f"{prefix}_1nna": m["one_nna"],
        f"{prefix}_cov": m["coverage"],
        f"{prefix}_mmd": m["mmd"] * unit,
        f"{prefix}_specificity": m["specificity"] * unit,
        f"{prefix}_diversity": m["diversity"] * unit,
        f"{prefix}_diversity_ref": m["diversity_ref"] * unit,
    }


def run(args) -> dict:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n_shape, n_pose = (48, 64) if args.quick else (400, 600)
    t0 = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    metrics: dict = {"mode": "quick" if args.quick else "full", "seed": args.seed}

    # ------------------------------------------------------------------ shapes
    shape_prior, sinfo = dspp.default_shape_prior(return_info=True)
    vmap_, faces = bp.load_decimated()
    vmap_ = np.asarray(vmap_)
    fresh = bp.sample_population(n_shape, key=jr.PRNGKey(args.seed), progress=False)
    test = np.asarray(fresh.vertices[:, vmap_], np.float32)
    n_train_ref = n_shape
    train_pop = bp.sample_population(n_train_ref, key=jr.PRNGKey(sinfo["data"]["seed"]),
                                  progress=False)  # fmt: skip
    train = np.asarray(train_pop.vertices[:, vmap_], np.float32)
    gen = np.asarray(dspp.sample(shape_prior, n_shape, key=jr.PRNGKey(args.seed + 1)))
    unit = 1e3
    metrics.update(_metrics("shape_aegan", gen, test, train, bp.mean_vertex_distance_metric, unit))
    pca = dspp.fit_pca_prior(train, min(shape_prior.latent_dim, train.shape[0] - 1))
    gen_pca = np.asarray(dspp.sample(pca, n_shape, key=jr.PRNGKey(args.seed + 2)))
    metrics.update(_metrics("shape_pca", gen_pca, test, train, bp.mean_vertex_distance_metric,
                            unit))  # fmt: skip
    recon = np.asarray(jax.jit(jax.vmap(shape_prior.reconstruct))(test))
    metrics["shape_reconstruction_mm"] = float(np.linalg.norm(recon - test, axis=-1).mean() * 1e3)
    metrics["shape_n_eval"] = n_shape
    metrics["shape_prior_training"] = sinfo["training"]

    # ------------------------------------------------------------------ poses
    pose_prior, pinfo = dspp.default_pose_prior(return_info=True)
    mocap = Path(args.mocap) if args.mocap else bp.find_mocap_dir()
    if mocap is None:
        raise SystemExit("no CMU mocap folder: pass --mocap DIR")
    poses = bp.load_mocap(str(mocap), fps=pinfo["data"]["fps"], progress=False)
    # the prior's own validation clips (recorded in its provenance) are the held-out poses
    names = np.asarray(poses.clip_names)[np.asarray(poses.clip)]
    held = np.isin(names, pinfo["data"]["validation_clips"])
    euler = np.asarray(poses.euler, np.float32)
    val_e, tr_e = euler[held], euler[~held]
    n_p = min(n_pose, val_e.shape[0])
    ref = val_e[rng.choice(val_e.shape[0], n_p, replace=False)]
    train_ref = tr_e[rng.choice(tr_e.shape[0], min(n_pose, tr_e.shape[0]), replace=False)]
    deg = float(np.degrees(1.0))
    gen_p = np.asarray(dspp.sample(pose_prior, n_p, key=jr.PRNGKey(args.seed + 3)))
    metrics.update(_metrics("pose_aegan", gen_p, ref, train_ref, bp.pose_geodesic_metric, deg))
    pca_p = dspp.fit_pca_prior(tr_e, min(pose_prior.latent_dim, tr_e.shape[0] - 1))
    gen_pp = np.asarray(dspp.sample(pca_p, n_p, key=jr.PRNGKey(args.seed + 4)))
    metrics.update(_metrics("pose_pca", gen_pp, ref, train_ref, bp.pose_geodesic_metric, deg))
    real = tr_e[rng.choice(tr_e.shape[0], n_p, replace=False)]
    metrics.update(_metrics("pose_train", real, ref, train_ref, bp.pose_geodesic_metric, deg))
    limits = np.asarray(dspp.joint_limits(tr_e, quantile=0.0))
    limits = limits + np.radians(5.0) * np.array([-1.0, 1.0])  # widened by 5 degrees each side
    for name, g in (("aegan", gen_p), ("pca", gen_pp), ("train", real)):
        metrics[f"pose_limit_violation_{name}"] = float(dspp.joint_limit_violation(g, limits))
    metrics["pose_n_eval"] = n_p
    metrics["pose_prior_training"] = pinfo["training"]

    # ------------------------------------------------------------------ figure
    body = bp.load_default_body("cmu_mb")
    k = 4 if args.quick else 8
    bp.render_poses(body, gen_p[:k], out / "samples.png",
                    labels=[f"prior sample {i}" for i in range(k)])  # fmt: skip
    metrics["total_s"] = time.perf_counter() - t0
    with open(out / "metrics.json", "w") as f:
        json.dump(metrics, f, indent=1)
    return metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mocap", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    m = run(args)
    ends = ("_1nna", "_cov", "_diversity", "_diversity_ref", "_reconstruction_mm")
    keys = [k for k in m if k.endswith(ends) or k.startswith("pose_limit_violation")]
    print(json.dumps({k: round(m[k], 4) for k in keys}, indent=1))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
