"""DSPP on a curved shape population (issue 15 §2): can a non-linear prior beat Gaussian PCA where
the data are not linear-Gaussian?

The adult population sampler (ages 18-65) is nearly linear-Gaussian: Gaussian PCA matches it
(1-NNA 0.50) and no prior can win there. MakeHuman's full age range is not: age drives height,
head-to-body proportions and limb lengths non-linearly (a one-year-old is not a scaled adult), so
the bodies lie on a curved manifold and a Gaussian over its linear span also produces bodies nobody
has (a toddler's head on an adult's trunk, ...). This experiment measures that and whether the DSPP
shape AE-GAN does better.

Populations (both sexes, `bodyprior.sample_population` with the default body, exact rest posture,
decimated 6,449-vertex topology; bodies split at random into train / validation (monitor) / test):
`full_age` (ages `--age-min`..`--age-max`, default 1-90 years) and `adult` (18-65, the reference).

Generators per population: `pca` (Gaussian over 32 PCA components of the training bodies, as many
as the AE's latent size), `aegan` (the DSPP shape prior, `DSPPConfig.preset("shape")`, 8,000 cycles,
last model), `ae_gauss` (a Gaussian fitted to the AE's training codes, decoded: separates the
auto-encoder's manifold from its latent GAN), and `train` (real training bodies: the score of a
perfect model of the training set).

Metrics against the held-out test bodies (`bp.generative_metrics`, mean vertex distance in mm):
1-NNA (0.5 ideal), COV, MMD, specificity (mean distance of a sample to its nearest training body)
and diversity; `outlier_frac`: the fraction of samples farther from every training body than 95 %
of the real test bodies are (the bodies "no member resembles"; 0.05 for a perfect model); and the
heights (m) of the samples against the test bodies' (range, and the fraction below the shortest
training body).

Reconstruction (issue 15 §2's second question: the shape AE reconstructs worse than PCA-32): the
test bodies' mean vertex error through PCA with K = 8/16/32/64 components and through each AE
variant on `full_age`: `aegan` (latent 32, hidden (128, 64), 8,000 cycles), `aegan_long` (x3
cycles), `aegan_wide` (hidden (512, 256)), `aegan_latent64` (latent 64); the adult population's
default AE as the reference.

Usage: `python experiments/dspp_curved.py --out out/dspp_curved [--quick]` (full: 3,000 training
bodies per population, about 30 min on 2 cores; `--quick`: tiny networks and sizes for the test).
Writes `metrics.json`, `samples_<population>.png` (contact sheets of samples) and
`heights.png` (histograms).
"""

from __future__ import annotations

import argparse
import json
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

SIZES = {
    "full": dict(n_train=3000, n_val=300, n_test=600, n_eval=600, cycles=8000, monitor=1000,
                 spc=500, batch=16, net={}),
    "quick": dict(n_train=64, n_val=16, n_test=32, n_eval=32, cycles=40, monitor=20, spc=20,
                  batch=4, net=dict(latent_dim=8, noise_dim=8, ae_hidden=(32,),
                                    generator_hidden=(32,), discriminator_hidden=(32,))),
}  # fmt: skip
# AE variants (trained on full_age; the adult population gets `aegan` only).
VARIANTS = {
    "aegan": dict(),
    "aegan_long": dict(cycles_factor=3),
    "aegan_wide": dict(ae_hidden=(512, 256)),
    "aegan_latent64": dict(latent_dim=64, noise_dim=64),
}
PCA_KS = (8, 16, 32, 64)


def _log(msg: str) -> None:
    print(f"[dspp_curved {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _population(age_range, n, seed, vertex_map):
    pop = bp.sample_population(n, key=jr.PRNGKey(seed), age_range=age_range, pose_jitter_deg=0.0,
                               progress=False)  # fmt: skip
    x = np.asarray(pop.vertices[:, vertex_map], np.float32)
    return x, np.asarray(pop.age_years), np.asarray(pop.sex)


def _height(x):
    return x[..., 2].max(-1) - x[..., 2].min(-1)


def _nearest(a, b, chunk=64):
    """Mean-vertex distance of each item of `a` to its nearest item of `b` (m)."""
    f = jax.jit(
        lambda ai: jnp.min(jnp.mean(jnp.linalg.norm(jnp.asarray(b) - ai[None], axis=-1), -1))
    )
    return np.array([float(f(jnp.asarray(ai))) for ai in a])


def _pca_recon(train, test, ks):
    x = train.reshape(len(train), -1).astype(np.float64)
    mu = x.mean(0)
    _, _, vt = np.linalg.svd(x - mu, full_matrices=False)
    y = test.reshape(len(test), -1).astype(np.float64) - mu
    out = {}
    for k in ks:
        k = min(k, vt.shape[0])
        r = y - (y @ vt[:k].T) @ vt[:k]
        out[k] = float(np.linalg.norm(r.reshape(len(test), -1, 3), axis=-1).mean() * 1e3)
    return out


def _ae_recon(prior, test):
    recon = np.asarray(jax.jit(jax.vmap(prior.reconstruct))(jnp.asarray(test)))
    return float(np.linalg.norm(recon - test, axis=-1).mean() * 1e3)


def _ae_gauss(prior, train, n, key):
    codes = np.asarray(jax.jit(jax.vmap(prior.encode))(jnp.asarray(train)), np.float64)
    mu, cov = codes.mean(0), np.cov(codes.T)
    z = np.random.default_rng(int(jr.randint(key, (), 0, 2**30))).multivariate_normal(mu, cov, n)
    return np.asarray(jax.jit(jax.vmap(prior.decode))(jnp.asarray(z, np.float32)))


def _scores(name, gen, test, train, ref_nearest_q95, unit=1e3) -> dict:
    m = bp.generative_metrics(gen, test, bp.mean_vertex_distance_metric, train=train)
    nn = _nearest(gen, train)
    h = _height(gen)
    return {
        f"{name}_1nna": m["one_nna"], f"{name}_cov": m["coverage"],
        f"{name}_mmd_mm": m["mmd"] * unit,
        f"{name}_specificity_mm": m["specificity"] * unit,
        f"{name}_diversity_mm": m["diversity"] * unit,
        f"{name}_outlier_frac": float(np.mean(nn > ref_nearest_q95)),
        f"{name}_height_min_m": float(h.min()), f"{name}_height_max_m": float(h.max()),
        f"{name}_height_below_train_frac": float(np.mean(h < _height(train).min())),
    }  # fmt: skip


def run(args) -> dict:
    mode = "quick" if args.quick else "full"
    S = SIZES[mode]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    vertex_map, faces = bp.load_decimated()
    vertex_map, faces = np.asarray(vertex_map), np.asarray(faces)
    metrics: dict = {"mode": mode, "seed": args.seed}
    metrics["age_range_full"] = [args.age_min, args.age_max]
    heights = {}
    n_all = S["n_train"] + S["n_val"] + S["n_test"]
    pops = {"full_age": (args.age_min, args.age_max), "adult": (18.0, 65.0)}
    for p_i, (pop_name, ages) in enumerate(pops.items()):
        x, years, _ = _population(ages, n_all, args.seed + 17 * p_i, vertex_map)
        perm = np.random.default_rng(args.seed).permutation(n_all)
        tr = x[perm[: S["n_train"]]]
        va = x[perm[S["n_train"] : S["n_train"] + S["n_val"]]]
        te = x[perm[S["n_train"] + S["n_val"] :]]
        heights[pop_name] = _height(te)
        P = f"{pop_name}"
        metrics[f"{P}_n_train"], metrics[f"{P}_n_test"] = len(tr), len(te)
        metrics[f"{P}_test_height_range_m"] = [float(_height(te).min()), float(_height(te).max())]
        h_all = _height(x)
        metrics[f"{P}_height_range_m"] = [float(h_all.min()), float(h_all.max())]
        metrics[f"{P}_age_range_years"] = [float(years.min()), float(years.max())]
        # real test bodies' distance to their nearest training body: the reference for "resembles"
        ref_nn = _nearest(te, tr)
        q95 = float(np.quantile(ref_nn, 0.95))
        metrics[f"{P}_test_nearest_train_mm_mean"] = float(ref_nn.mean() * 1e3)
        metrics[f"{P}_test_nearest_train_mm_q95"] = q95 * 1e3
        k_eval = jr.PRNGKey(args.seed + 100 + p_i)
        n_eval = min(S["n_eval"], len(te))
        te_eval = te[:n_eval]
        # PCA
        latent = S["net"].get("latent_dim", 32)
        pca = dspp.fit_pca_prior(tr, min(latent, len(tr) - 1))
        gens = {"pca": np.asarray(dspp.sample(pca, n_eval, key=jr.fold_in(k_eval, 0)))}
        gens["train"] = tr[np.random.default_rng(args.seed + 1).choice(len(tr), n_eval, False)]
        recon = _pca_recon(tr, te, PCA_KS)
        for k, v in recon.items():
            metrics[f"{P}_recon_pca{k}_mm"] = v
        variants = VARIANTS if pop_name == "full_age" else {"aegan": {}}
        if args.variants is None and mode == "quick":  # same network shapes: no extra compiles
            variants = {k: v for k, v in variants.items() if k in ("aegan", "aegan_long")}
        if args.variants is not None:
            variants = {k: v for k, v in variants.items() if k in args.variants or k == "aegan"}
        for v_name, v in variants.items():
            net = {**S["net"], **{k: val for k, val in v.items() if k != "cycles_factor"}}
            cycles = S["cycles"] * v.get("cycles_factor", 1)
            cfg = dspp.DSPPConfig.preset(
                "shape", n_steps=cycles, batch_size=S["batch"], steps_per_call=S["spc"],
                monitor_every=S["monitor"], monitor_samples=min(256, len(va)), **net,
            )  # fmt: skip
            t = time.perf_counter()
            sol = dspp.train_shape_prior(tr, key=jr.PRNGKey(args.seed + 7), config=cfg,
                                         validation=va, select="last",
                                         progress=not args.no_progress)  # fmt: skip
            metrics[f"{P}_{v_name}_train_s"] = time.perf_counter() - t
            prior = sol.value
            metrics[f"{P}_recon_{v_name}_mm"] = _ae_recon(prior, te)
            metrics[f"{P}_recon_{v_name}_train_mm"] = _ae_recon(prior, tr[: len(te)])
            _log(f"{pop_name} {v_name}: {cycles} cycles in "
                 f"{metrics[f'{P}_{v_name}_train_s']:.0f} s, test reconstruction "
                 f"{metrics[f'{P}_recon_{v_name}_mm']:.2f} mm")  # fmt: skip
            if v_name == "aegan":
                gens["aegan"] = np.asarray(dspp.sample(prior, n_eval, key=jr.fold_in(k_eval, 1)))
                gens["ae_gauss"] = _ae_gauss(prior, tr, n_eval, jr.fold_in(k_eval, 2))
        for g_name, g in gens.items():
            metrics.update(_scores(f"{P}_{g_name}", g, te_eval, tr, q95))
        _log(f"{pop_name}: " + ", ".join(
            f"{g} 1-NNA {metrics[f'{P}_{g}_1nna']:.3f} "
            f"outliers {metrics[f'{P}_{g}_outlier_frac']:.2f}" for g in gens))  # fmt: skip
        # contact sheet: 4 samples of each generator
        meshes, labels = [], []
        for g_name in ("train", "pca", "aegan", "ae_gauss"):
            for i in range(4):
                meshes.append(gens[g_name][i])
                labels.append(f"{g_name} {i}")
        sheet = bp.contact_sheet(meshes, faces, ncols=4, labels=labels, cell_size=(200, 240))
        bp.save_png(out / f"samples_{pop_name}.png", sheet)
        heights[f"{pop_name}_pca"] = _height(gens["pca"])
        heights[f"{pop_name}_aegan"] = _height(gens["aegan"])
    _plot_heights(heights, out / "heights.png")
    metrics["total_s"] = time.perf_counter() - t0
    with open(out / "metrics.json", "w") as f:
        json.dump(metrics, f, indent=1)
    return metrics


def _plot_heights(h, path):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), dpi=100)
    for ax, pop in zip(axes, ("full_age", "adult")):
        bins = np.linspace(0.5, 2.2, 50)
        ax.hist(h[pop], bins, alpha=0.5, label="test bodies", density=True)
        ax.hist(h[f"{pop}_pca"], bins, histtype="step", lw=2, label="PCA samples", density=True)
        ax.hist(h[f"{pop}_aegan"], bins, histtype="step", lw=2, label="AE-GAN samples",
                density=True)  # fmt: skip
        ax.set_title(pop.replace("_", " "))
        ax.set_xlabel("height (m)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--age-min", type=float, default=1.0)
    ap.add_argument("--age-max", type=float, default=90.0)
    ap.add_argument("--variants", nargs="*", default=None, help="AE variants to train (full_age)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    m = run(args)
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in m.items()},
                     indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
