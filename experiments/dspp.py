"""DSPP experiment (issue 4 §3, §5): deep shape and pose priors (AE-GAN) vs geometry-space GANs.

Trains the AE-GAN priors and geometry-space GAN baselines, samples them, and measures realism and
diversity against held-out real data, alongside PCA baselines fitted to the same training data.

Data. Shapes: `bodyprior.sample_population` (the CAESAR stand-in, seed `--seed`) on the decimated
6,449-vertex topology; the bodies are split at random (seed) into train (80 %) and test (20 %).
Poses: every BVH clip under `--mocap` (default `../shared/data/mocap`) through
`bp.load_mocap` at 4 frames/s, split by whole clips (`split_by_clip`, 20 % test).

Methods: (a) `aegan` the DSPP prior; (b) `geomgan` a GAN whose discriminator sees geometry (PointNet
for shapes, MLP on Euler angles for poses); both trained with the library's presets
(`DSPPConfig.preset`: "shape", "pose", "geometry_pose"), and for poses also with the paper's recipe
as printed (`aegan_paper`, `geomgan_paper`: preset "paper", which collapses on pose codes; see
docs/results_dspp.md); (c) `pca` Gaussian sampling of a PCA space with as many
components as the AE-GAN latent dimension; (d) `pca3sigma` the same PCA with every coefficient at
one of its +-3 sigma extremes (random signs); plus `pcauniform` (coefficients uniform in
[-3 sigma, 3 sigma]) and `train`, a random draw of *real training items*: the score a perfect
generator of the training distribution would get against the test set (the reference row).

Collapse monitor: 10 % of the training clips (poses) and 10 % of the training bodies (shapes) are
held out as validation items; every `monitor_every` cycles training scores a fixed set of samples
against them (1-NNA, diversity). The pose systems return the monitored model closest to 1-NNA 0.5
(`select="best"`); the shape systems return their last model (`select="last"`): they do not
collapse, their auto-encoder keeps improving (8,000 cycles are not enough), and in the first full
run the best-by-validation shape model (cycle 3,000 of 8,000; 1-NNA differences of ~0.03 between
checks, the noise of 256 samples) reconstructed at 12.6 mm instead of 8.2. Keys
`monitor_*_<job>` and `best_step_<job>`; the loss plots show it.

Metrics (H-metrics' `bodyprior.generative_metrics`): MMD, COV, 1-NNA (0.5 ideal), specificity (mean
distance to the nearest training item), diversity (average pairwise distance); shapes with the mean
vertex distance (reported in mm), poses with the mean per-joint geodesic angle (reported in
degrees); poses also the fraction of samples outside the joint limits derived from the training
mocap (`joint_limits`: the full training range; `_q005`: 0.5 % quantiles; `_tol5deg`: the full
range widened by 5 degrees).
Keys: `<shape|pose>_<metric>_<method>`.

Usage: `python experiments/dspp.py --quick --out out/dspp_quick [--seed 0]` (a few minutes; tests
use `--quick --tiny`) or `python experiments/dspp.py --out out/dspp` (full; sized for about 25 min
on 2 shared cores). Writes `metrics.json`, loss curves `loss_*.png`, sample renderings
`shape_samples.png`, `pose_samples.png`, and the trained priors `*.dspp`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import bodyprior as bp
from bodyprior import dspp

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MOCAP = REPO.parent / "shared" / "data" / "mocap"

# Sizes per mode: training cycles, batch sizes and cycles per jitted call of the four GANs. The
# paper trains 100,000 cycles at batch 1; the shape systems get fewer cycles (on 2 shared cores a
# shape cycle costs 25-50 ms, a pose cycle about 1 ms) and the AE-GAN a larger batch instead.
SIZES = {
    "full": dict(n_bodies=4308, n_eval=300, n_train_ref=600, n_eval_pose=800,
                 n_train_ref_pose=1500, render=8, mocap=None,
                 steps=dict(aegan_shape=8000, geomgan_shape=4000, aegan_pose=100000,
                            geomgan_pose=100000),
                 monitor=dict(aegan_shape=1000, geomgan_shape=500, aegan_pose=5000,
                              geomgan_pose=5000),
                 batch=dict(aegan_shape=16, geomgan_shape=2, aegan_pose=64, geomgan_pose=16),
                 spc=dict(aegan_shape=500, geomgan_shape=500, aegan_pose=5000, geomgan_pose=5000)),
    "quick": dict(n_bodies=400, n_eval=64, n_train_ref=128, n_eval_pose=128,
                  n_train_ref_pose=256, render=4,
                  mocap=("cmu_3dsmax-friendly_yuki-koyama-bvh11",
                         "cmu_daz-friendly_papagina-acLSTM/indian_dance"),
                  steps=dict(aegan_shape=1000, geomgan_shape=300, aegan_pose=3000,
                             geomgan_pose=3000),
                  monitor=dict(aegan_shape=250, geomgan_shape=100, aegan_pose=1000,
                               geomgan_pose=1000),
                  batch=dict(aegan_shape=8, geomgan_shape=2, aegan_pose=16, geomgan_pose=16),
                  spc=dict(aegan_shape=250, geomgan_shape=100, aegan_pose=1000, geomgan_pose=1000)),
    "tiny": dict(n_bodies=120, n_eval=24, n_train_ref=48, n_eval_pose=32, n_train_ref_pose=32,
                 render=2,
                 mocap=("cmu_3dsmax-friendly_yuki-koyama-bvh11",),
                 steps=dict(aegan_shape=200, geomgan_shape=100, aegan_pose=400, geomgan_pose=400),
                 monitor=dict(aegan_shape=100, geomgan_shape=100, aegan_pose=200, geomgan_pose=200),
                 batch=dict(aegan_shape=8, geomgan_shape=2, aegan_pose=16, geomgan_pose=16),
                 spc=dict(aegan_shape=100, geomgan_shape=100, aegan_pose=200, geomgan_pose=200)),
}  # fmt: skip

METHODS = ("aegan", "geomgan", "pca", "pca3sigma", "pcauniform", "train")
N_DRAWS = 5  # draws of (samples, test subset) for the pose rows' 1-NNA mean and spread
PAPER_METHODS = ("aegan_paper", "geomgan_paper")  # poses only: the paper's recipe (it collapses)
# Training jobs: (name, the SIZES entry it uses, preset).
JOBS = (("aegan_shape", "aegan_shape", "shape"), ("geomgan_shape", "geomgan_shape", "shape"),
        ("aegan_pose", "aegan_pose", "pose"), ("geomgan_pose", "geomgan_pose", "geometry_pose"),
        ("aegan_pose_paper", "aegan_pose", "paper"),
        ("geomgan_pose_paper", "geomgan_pose", "paper"))  # fmt: skip


def _log(msg: str) -> None:
    print(f"[dspp {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _shape_data(seed: int, n: int, progress: bool):
    vertex_map, faces = bp.load_decimated()
    pop = bp.sample_population(n, progress=progress, key=jr.PRNGKey(seed))
    x = np.asarray(pop.vertices[:, np.asarray(vertex_map)], np.float32)
    perm = np.random.default_rng(seed).permutation(n)
    n_test = max(2, int(round(0.2 * n)))
    n_val = max(2, int(round(0.1 * (n - n_test))))
    train, val = perm[n_test + n_val :], perm[n_test : n_test + n_val]
    return x[train], x[val], x[perm[:n_test]], np.asarray(faces)


def _pose_data(mocap: Path, subdirs, seed: int, progress: bool):
    paths = [mocap / s for s in subdirs] if subdirs else [mocap]
    poses = bp.load_mocap([str(p) for p in paths], fps=4.0, progress=progress)
    train, test = bp.split_by_clip(poses, 0.2, seed=seed)
    train, val = bp.split_by_clip(train, 0.1, seed=seed)
    return (np.asarray(train.euler, np.float32), np.asarray(val.euler, np.float32),
            np.asarray(test.euler, np.float32), poses.n_poses, len(poses.clip_names))  # fmt: skip


def _subset(x: np.ndarray, n: int, rng) -> np.ndarray:
    return x[rng.choice(x.shape[0], size=min(n, x.shape[0]), replace=False)]


def _evaluate(domain, samples, test_ref, train_ref, metric, unit):
    out = {}
    for method, gen in samples.items():
        m = bp.generative_metrics(gen, test_ref, metric, train=train_ref)
        out[f"{domain}_1nna_{method}"] = m["one_nna"]
        out[f"{domain}_cov_{method}"] = m["coverage"]
        out[f"{domain}_mmd_{method}"] = m["mmd"] * unit
        out[f"{domain}_specificity_{method}"] = m["specificity"] * unit
        out[f"{domain}_diversity_{method}"] = m["diversity"] * unit
        out[f"{domain}_diversity_ref"] = m["diversity_ref"] * unit
    return out


def run(args) -> dict:
    mode = "tiny" if args.tiny else ("quick" if args.quick else "full")
    S = SIZES[mode]
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt = out_dir / "checkpoints"
    ckpt.mkdir(exist_ok=True)
    progress = not args.no_progress
    t_start = time.perf_counter()
    key = jr.PRNGKey(args.seed)
    k_shape, k_geo_s, k_pose, k_geo_p, k_eval = jr.split(key, 5)
    rng = np.random.default_rng(args.seed)
    metrics: dict = {"mode": mode, "seed": args.seed}
    timings: dict = {}

    # ---------------------------------------------------------------- data
    t = time.perf_counter()
    x_train, x_val, x_test, faces = _shape_data(args.seed, S["n_bodies"], progress)
    timings["shape_data_s"] = time.perf_counter() - t
    t = time.perf_counter()
    p_train, p_val, p_test, n_poses, n_clips = _pose_data(
        Path(args.mocap), S["mocap"], args.seed, progress
    )
    timings["pose_data_s"] = time.perf_counter() - t
    metrics.update(
        shape_n_train=int(x_train.shape[0]), shape_n_val=int(x_val.shape[0]),
        shape_n_test=int(x_test.shape[0]), shape_n_vertices=int(x_train.shape[1]),
        pose_n_train=int(p_train.shape[0]), pose_n_val=int(p_val.shape[0]),
        pose_n_test=int(p_test.shape[0]), pose_n_clips=n_clips,
    )  # fmt: skip
    _log(f"shapes {x_train.shape[0]}/{x_test.shape[0]} train/test; poses {p_train.shape[0]}/"
         f"{p_test.shape[0]} from {n_clips} clips")  # fmt: skip

    def cfg(job):
        _, name, preset = next(j for j in JOBS if j[0] == job)
        kw = {}
        if mode == "tiny":  # fewer/smaller layers: same code paths, a fraction of the compile time
            kw = dict(latent_dim=16, noise_dim=16, ae_hidden=(64,), generator_hidden=(64,),
                      discriminator_hidden=(64,), pointnet_hidden=(32,),
                      pointnet_head_hidden=(32,), pointnet_points=256, geometry_pose_hidden=(64,),
                      geometry_generator_hidden=(64,))  # fmt: skip
        return dspp.DSPPConfig.preset(
            preset, n_steps=S["steps"][name], batch_size=S["batch"][name],
            steps_per_call=S["spc"][name], checkpoint_every=S["spc"][name] * 4,
            monitor_every=S["monitor"][name], **kw,
        )  # fmt: skip

    # ---------------------------------------------------------------- training
    models, logs = {}, {}
    train_keys = {
        "aegan_shape": k_shape,
        "geomgan_shape": k_geo_s,
        "aegan_pose": k_pose,
        "geomgan_pose": k_geo_p,
        "aegan_pose_paper": k_pose,
        "geomgan_pose_paper": k_geo_p,
    }

    def train(job):
        # the paper-recipe runs use the same key (initialisation, batches) as the presets' runs
        data, val = (x_train, x_val) if job.endswith("shape") else (p_train, p_val)
        kw = dict(key=train_keys[job], config=cfg(job), validation=val, checkpoint_dir=ckpt / job,
                  select="last" if job.endswith("shape") else "best",
                  progress=progress)  # fmt: skip
        (ckpt / job).mkdir(exist_ok=True)
        if job == "aegan_shape":
            return dspp.train_shape_prior(data, **kw)
        if job.startswith("aegan"):
            return dspp.train_pose_prior(data, **kw)
        return dspp.train_geometry_gan(data, kind="shape" if job.endswith("shape") else "pose",
                                       **kw)  # fmt: skip

    jobs = [(job, lambda job=job: train(job)) for job, _, _ in JOBS]
    for name, job in jobs:
        t = time.perf_counter()
        sol = job()
        models[name], logs[name] = sol.value, sol.aux
        timings[f"train_{name}_s"] = time.perf_counter() - t
        log = logs[name]
        metrics[f"train_steps_{name}"] = log.n_steps
        tail = max(1, log.n_steps // 10)
        metrics[f"final_d_loss_{name}"] = float(np.mean(log.d_loss[-tail:]))
        metrics[f"final_g_loss_{name}"] = float(np.mean(log.g_loss[-tail:]))
        metrics[f"best_step_{name}"] = int(sol.stats["best_step"])
        metrics[f"monitor_step_{name}"] = log.monitor_step.astype(int).tolist()
        metrics[f"monitor_1nna_{name}"] = log.monitor_one_nna.tolist()
        metrics[f"monitor_diversity_{name}"] = log.monitor_diversity.tolist()
        metrics[f"monitor_diversity_ref_{name}"] = float(log.monitor_diversity_ref[-1])
        bp_path = out_dir / f"{name}.dspp"
        dspp.save_prior(bp_path, models[name])
        dspp.plot_train_log(log, out_dir / f"loss_{name}.png", title=name.replace("_", " "))
        _log(f"trained {name}: {log.n_steps} cycles in {timings[f'train_{name}_s']:.0f} s")

    # ---------------------------------------------------------------- baselines + samples
    d = models["aegan_shape"].latent_dim
    keys = jr.split(k_eval, 16)
    samples = {"shape": {}, "pose": {}}
    train_refs, pca_fits = {}, {}
    for i, (domain, xtr) in enumerate((("shape", x_train), ("pose", p_train))):
        n_eval = S["n_eval"] if domain == "shape" else S["n_eval_pose"]
        n_ref = S["n_train_ref"] if domain == "shape" else S["n_train_ref_pose"]
        t = time.perf_counter()
        pca = dspp.fit_pca_prior(xtr, min(d, xtr.shape[0] - 1))
        timings[f"pca_{domain}_s"] = time.perf_counter() - t
        pcas = {m: pca.with_mode(mode_) for m, mode_ in (("pca", "gaussian"),
                ("pca3sigma", "pm3sigma"), ("pcauniform", "uniform3sigma"))}  # fmt: skip
        pca_fits[domain] = pca
        gens = {"aegan": models[f"aegan_{domain}"], "geomgan": models[f"geomgan_{domain}"], **pcas}
        if domain == "pose":
            gens.update(aegan_paper=models["aegan_pose_paper"],
                        geomgan_paper=models["geomgan_pose_paper"])  # fmt: skip
            pose_models = {**gens, "train": None}
        for j, (m, model) in enumerate(gens.items()):
            samples[domain][m] = np.asarray(dspp.sample(model, n_eval, key=keys[8 * i + j]))
        # Real training items as a "generator" (reference row); disjoint from the items that the
        # specificity is measured against.
        perm = rng.permutation(xtr.shape[0])
        samples[domain]["train"] = xtr[perm[:n_eval]]
        train_refs[domain] = xtr[perm[n_eval:][:n_ref]]

    # Reconstruction quality of the auto-encoders vs PCA with the same number of components.
    for domain, xte in (("shape", x_test), ("pose", p_test)):
        prior = models[f"aegan_{domain}"]
        rec = np.asarray(jax.jit(jax.vmap(prior.reconstruct))(jnp.asarray(xte)))
        pca = pca_fits[domain]
        u = (xte - np.asarray(pca.mean)).reshape(len(xte), -1)
        b = np.asarray(pca.basis)
        rec_pca = (np.asarray(pca.mean).reshape(-1) + (u @ b.T) @ b).reshape(xte.shape)
        if domain == "shape":
            err = lambda r: float(np.mean(np.linalg.norm(r - xte, axis=-1)) * 1e3)  # noqa: E731
            metrics["shape_recon_mm_aegan"], metrics["shape_recon_mm_pca"] = err(rec), err(rec_pca)
        else:
            err = lambda r: float(np.degrees(np.sqrt(np.mean((r - xte) ** 2))))  # noqa: E731
            metrics["pose_recon_rms_deg_aegan"] = err(rec)
            metrics["pose_recon_rms_deg_pca"] = err(rec_pca)

    # ---------------------------------------------------------------- metrics
    t = time.perf_counter()
    shape_ref = _subset(x_test, S["n_eval"], rng)
    metrics.update(_evaluate("shape", samples["shape"], shape_ref, train_refs["shape"],
                             bp.mean_vertex_distance_metric, 1e3))  # fmt: skip
    pose_ref = _subset(p_test, S["n_eval_pose"], rng)
    metrics.update(_evaluate("pose", samples["pose"], pose_ref, train_refs["pose"],
                             bp.pose_geodesic_metric, float(np.degrees(1.0))))  # fmt: skip
    # 1-NNA of one draw of samples against one draw of test poses moves by ~0.01-0.03 between draws
    # (0.856 and 0.829 for one model in an earlier run): the pose rows also get `N_DRAWS` - 1 more
    # draws (fresh samples, a fresh test subset) and their mean and standard deviation.
    for j, (m, gen) in enumerate(pose_models.items()):
        draws = [metrics[f"pose_1nna_{m}"]]
        for r in range(1, N_DRAWS):
            ref = _subset(p_test, S["n_eval_pose"], np.random.default_rng(1000 * r + j))
            if m == "train":
                x = _subset(p_train, S["n_eval_pose"], np.random.default_rng(2000 * r + j))
            else:
                x = np.asarray(
                    dspp.sample(gen, S["n_eval_pose"], key=jr.fold_in(keys[15], 64 * r + j))
                )
            draws.append(bp.generative_metrics(x, ref, bp.pose_geodesic_metric)["one_nna"])
        metrics[f"pose_1nna_draws_{m}"] = draws
        metrics[f"pose_1nna_mean_{m}"] = float(np.mean(draws))
        metrics[f"pose_1nna_sd_{m}"] = float(np.std(draws, ddof=1))
    # Joint limits = the full range of each Euler angle over the training mocap (quantile 0), so
    # real poses violate them only where the test clips leave the training range (key `_test`);
    # `_q005` keys: limits at the 0.5 %/99.5 % quantiles (stricter; ~45 % of in-distribution poses
    # have at least one of their 60 angles in some tail).
    # `_tol5deg` keys: the full training range widened by 5 degrees on each side (a few angles,
    # e.g. the shoulders' X and Z, are nearly constant in the mocap, so any reconstruction error
    # leaves their exact range).
    for suffix, q, tol in (("", 0.0, 0.0), ("_q005", 0.005, 0.0), ("_tol5deg", 0.0, 5.0)):
        limits = np.asarray(dspp.joint_limits(p_train, quantile=q))
        limits = limits + np.radians(tol) * np.array([-1.0, 1.0])
        for m, gen in {**samples["pose"], "test": p_test}.items():
            metrics[f"pose_joint_limit_violation_{m}{suffix}"] = dspp.joint_limit_violation(
                gen, limits
            )
    timings["metrics_s"] = time.perf_counter() - t
    metrics["units"] = {"shape_mmd/specificity/diversity/recon": "mm (mean vertex distance)",
                        "pose_mmd/specificity/diversity": "deg (mean per-joint geodesic angle)",
                        "pose_recon_rms_deg": "deg (RMS Euler-angle error)"}  # fmt: skip

    # ---------------------------------------------------------------- pictures
    t = time.perf_counter()
    nr = S["render"]
    show = ("train", "aegan", "geomgan", "pca", "pca3sigma")
    shapes = np.concatenate([samples["shape"][m][:nr] for m in show])
    labels = [f"{m} {i + 1}" if m != "train" else f"real {i + 1}" for m in show for i in range(nr)]
    img = bp.contact_sheet(shapes, faces, ncols=nr, labels=labels, cell_size=(200, 110),
                           antialias=1)  # fmt: skip
    bp.save_png(out_dir / "shape_samples.png", img)
    body = bp.load_default_body("cmu_mb")
    show = (*show, "aegan_paper")
    labels = [f"{m} {i + 1}" if m != "train" else f"real {i + 1}" for m in show for i in range(nr)]
    poses = np.concatenate([samples["pose"][m][:nr] for m in show])
    bp.render_poses(body, poses, out_dir / "pose_samples.png", labels=labels, ncols=nr,
                      cell_size=(200, 130))  # fmt: skip
    timings["render_s"] = time.perf_counter() - t

    timings["total_s"] = time.perf_counter() - t_start
    metrics["timings"] = timings
    metrics["config"] = {job: cfg(job).to_dict() for job, _, _ in JOBS}
    bp.atomic_write_json(out_dir / "metrics.json", metrics)
    _log(f"done in {timings['total_s']:.0f} s -> {out_dir / 'metrics.json'}")
    return metrics


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="small run (minutes)")
    ap.add_argument(
        "--tiny", action="store_true", help="smallest run, for the tests (implies quick)"
    )
    ap.add_argument("--mocap", default=str(DEFAULT_MOCAP), help="directory of CMU BVH clips")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    if not Path(args.mocap).is_dir():
        ap.error(f"--mocap: no such directory {args.mocap}")
    metrics = run(args)
    keys = ("shape_1nna_aegan", "shape_1nna_geomgan", "shape_1nna_pca", "pose_1nna_aegan",
            "pose_1nna_aegan_paper", "pose_1nna_geomgan", "pose_1nna_geomgan_paper",
            "pose_1nna_pca", "pose_diversity_aegan", "pose_diversity_aegan_paper",
            "pose_diversity_ref", "pose_joint_limit_violation_aegan")  # fmt: skip
    for k in keys:
        print(f"{k}: {metrics[k]:.3f}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
