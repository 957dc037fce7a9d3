"""Does a DSPP shape prior help a fitter with sparse, noisy input? (issue 4, §4)

Task: recover the full body shape of held-out population bodies (6,449-vertex decimated topology)
from its 77 CAESAR landmarks only, observed with Gaussian noise (`--noise-mm` per coordinate,
default 10 mm). Three fitters, all optimistix Levenberg-Marquardt in float64:

- `pca`: S-SCAPE/PCA shape space learned on the training bodies (`bodyprior.sscape.learn`, no
  alignment: bodies and landmarks share the population's world frame), coefficients fitted with a
  Gaussian (Tikhonov) prior `coeff_weight · ||c||²` (`bodyprior.dspp.fit_shape_space_to_landmarks`);
- `pca_dspp`: the same plus the DSPP prior residual (`bodyprior.dspp.shape_prior_residual`: the
  latent discriminator's non-saturating log-score of the encoded shape, and optionally the distance
  to the auto-encoder's manifold);
- `dspp_latent`: the DSPP latent parameterisation, vertices = `decode(z)`, with a Gaussian on `z`
  fitted to the training codes and optionally the discriminator score
  (`bodyprior.dspp.fit_latent_to_landmarks`).

Data: one population (`bodyprior.sample_population`, key `--seed`), split in order into train /
validation / test bodies (the sampler draws bodies i.i.d., so the split is random). The PCA space
and the DSPP prior are trained on the training bodies only; every weight is chosen on the
validation bodies (grid search, lowest mean vertex error); the test bodies are used once, at the
end. A landmark whose full-mesh vertex was removed by the decimation is mapped to the nearest kept
vertex on the rest template (the rule of `bodyprior.registration.registration_template`, whose
landmark
indices these equal).

Outputs in `--out`: `metrics.json` (errors in mm per method, the validation grids, the chosen
weights, prior training statistics) and `dspp_prior_fit.png` (mean per-vertex test error of each
method as a colour map on the mean shape).

Usage: `python experiments/dspp_prior_fit.py --quick --out out/dspp_prior_fit` (a few minutes) or
without `--quick` for the full run (~15 minutes on 2 shared CPU cores).
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior import dspp  # noqa: E402

QUICK = dict(n_train=40, n_val=4, n_test=4, n_components=8, prior_steps=100, prior_batch=8,
             coeff_weights=(0.3, 1.0), score_weights=(1.0, 30.0), recon_weights=(0.0, 1e5),
             latent_weights=(0.3, 3.0), latent_score_weights=(0.0,), max_steps=40)  # fmt: skip
FULL = dict(n_train=600, n_val=16, n_test=48, n_components=40, prior_steps=4000, prior_batch=16,
            coeff_weights=(0.3, 1.0, 3.0), score_weights=(10.0, 30.0), recon_weights=(0.0, 1e5),
            latent_weights=(0.3, 1.0, 3.0, 10.0), latent_score_weights=(0.0, 10.0, 100.0),
            max_steps=60)  # fmt: skip
FIT_BATCH = 8  # bodies solved per vectorised step (bounds the memory of the Jacobians)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes (minutes; used by the tests)")
    p.add_argument("--full", action="store_true", help="full sizes (default unless --quick)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=4, help="population / noise / training seed")
    p.add_argument("--noise-mm", type=float, default=10.0, help="landmark noise std per coordinate")
    p.add_argument("--prior", default=None,
                   help="a saved ShapePrior (bodyprior.dspp.save_prior) to use instead of "
                        "training one; trained on bodies disjoint from these")  # fmt: skip
    for k in ("n_train", "n_val", "n_test", "n_components", "prior_steps", "prior_batch",
              "max_steps"):  # fmt: skip
        p.add_argument("--" + k.replace("_", "-"), type=int, default=None, help="override")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.quick and args.full:
        p.error("pass at most one of --quick and --full")
    cfg = dict(QUICK if args.quick else FULL)
    for k in ("n_train", "n_val", "n_test", "n_components", "prior_steps", "prior_batch",
              "max_steps"):  # fmt: skip
        if getattr(args, k) is not None:
            cfg[k] = getattr(args, k)
    if cfg["n_val"] < 1 or cfg["n_test"] < 1 or cfg["n_train"] < cfg["n_components"] + 1:
        p.error("need n_val >= 1, n_test >= 1 and n_train > n_components")
    if not args.noise_mm >= 0:
        p.error("--noise-mm must be non-negative")
    args.cfg = cfg
    return args


def landmarks_on_decimated(body, vertex_map: np.ndarray) -> np.ndarray:
    """Decimated-mesh vertex of each landmark: the vertex itself if kept, else the nearest kept
    vertex on the rest template (as `bodyprior.registration.registration_template`)."""
    tmpl = np.asarray(body.template, np.float64)
    lm = tmpl[np.asarray(body.landmark_index)]
    d = np.linalg.norm(lm[:, None] - tmpl[vertex_map][None], axis=-1)
    return d.argmin(1).astype(np.int32)


# --------------------------------------------------------------------------------------------------
# batched fits (one compilation per static structure; weights are traced)


@eqx.filter_jit
def _fit_space_batch(model, idx, targets, sigma: float, coeff_weight, reg, max_steps: int):
    def one(t):
        f = dspp.fit_shape_space_to_landmarks(
            model, idx, t, noise_sigma=sigma, coeff_weight=coeff_weight, regulariser=reg,
            max_steps=max_steps, throw=False,
        )  # fmt: skip
        return f.value.vertices, f.result == bp.RESULTS.successful, f.stats["num_steps"]

    return jax.lax.map(one, targets, batch_size=min(FIT_BATCH, targets.shape[0]))


@eqx.filter_jit
def _fit_latent_batch(prior, idx, targets, sigma: float, mu, sd, lw, sw, max_steps: int):
    def one(t):
        f = dspp.fit_latent_to_landmarks(
            prior, idx, t, latent_mean=mu, latent_std=sd, noise_sigma=sigma, latent_weight=lw,
            score_weight=sw, max_steps=max_steps, throw=False,
        )  # fmt: skip
        return f.value.vertices, f.result == bp.RESULTS.successful, f.stats["num_steps"]

    return jax.lax.map(one, targets, batch_size=min(FIT_BATCH, targets.shape[0]))


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(f"[dspp_prior_fit {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _since(t0: tuple[float, float]) -> dict:
    """Wall and process CPU seconds since `t0` (CPU time is the useful number on a shared
    machine)."""
    w, c = _clock()
    return dict(wall=round(w - t0[0], 3), cpu=round(c - t0[1], 3))


def _errors_mm(fitted, truth) -> np.ndarray:
    """Per-body mean vertex error (mm) and per-vertex errors (mm)."""
    per_vertex = 1e3 * np.linalg.norm(np.asarray(fitted) - truth, axis=-1)
    return per_vertex.mean(1), per_vertex


def _summary(err: np.ndarray) -> dict:
    return dict(mean=float(err.mean()), median=float(np.median(err)), std=float(err.std(ddof=1))
                if err.size > 1 else 0.0, max=float(err.max()))  # fmt: skip


def main(argv=None) -> dict:
    args = parse_args(argv)
    cfg = args.cfg
    os.makedirs(args.out, exist_ok=True)
    progress = not args.no_progress
    t_start = _clock()
    timings = {}
    sigma = max(args.noise_mm, 1.0) * 1e-3  # noise model of the fitters (>= 1 mm if noise-free)

    # ---- data
    t0 = _clock()
    n_train, n_val, n_test = cfg["n_train"], cfg["n_val"], cfg["n_test"]
    key = jax.random.PRNGKey(args.seed)
    k_pop, k_noise, k_prior = jax.random.split(key, 3)
    body = bp.load_default_body("cmu_mb")
    vertex_map, faces = bp.load_decimated()
    pop = bp.sample_population(n_train + n_val + n_test, progress=progress, key=k_pop)
    verts = np.asarray(pop.vertices, np.float64)[:, vertex_map]
    del pop
    train, val, test = np.split(verts, [n_train, n_train + n_val])
    lm_idx = landmarks_on_decimated(body, np.asarray(vertex_map))
    noise = (
        args.noise_mm
        * 1e-3
        * np.asarray(jax.random.normal(k_noise, (n_val + n_test, len(lm_idx), 3), jnp.float64))
    )
    val_t = val[:, lm_idx] + noise[:n_val]
    test_t = test[:, lm_idx] + noise[n_val:]
    timings["data_s"] = _since(t0)
    _log(progress, f"data ready: {timings['data_s']}")

    # ---- models
    t0 = _clock()
    model = bp.sscape.learn(train, faces, n_components=cfg["n_components"], align=False)
    timings["pca_s"] = _since(t0)
    _log(progress, f"PCA space learned: {timings['pca_s']}")
    t0 = _clock()
    if args.prior is not None:
        prior = dspp.load_prior(args.prior)
        if not isinstance(prior, dspp.ShapePrior) or prior.n_vertices != train.shape[1]:
            raise SystemExit(
                f"--prior {args.prior!r} is not a ShapePrior on {train.shape[1]} vertices"
            )
        prior_info = dict(source=os.path.abspath(args.prior))
    else:
        pcfg = dspp.DSPPConfig(n_steps=cfg["prior_steps"], batch_size=cfg["prior_batch"],
                               steps_per_call=min(500, cfg["prior_steps"]))  # fmt: skip
        sol = dspp.train_shape_prior(train, key=k_prior, config=pcfg, progress=progress)
        prior, log = sol.value, sol.aux
        tail = max(1, log.n_steps // 10)
        prior_info = dict(
            source="trained here", config=pcfg.to_dict(), train_wall_s=log.wall_time_s,
            final_ae_loss_m2=float(np.mean(log.ae_loss[-tail:])),
            final_d_real=float(np.mean(log.d_real[-tail:])),
            final_d_fake=float(np.mean(log.d_fake[-tail:])),
        )  # fmt: skip
    timings["prior_s"] = _since(t0)
    _log(progress, f"prior ready: {timings['prior_s']}")
    mu, sd = dspp.latent_statistics(prior, train)
    recon = np.asarray(jax.lax.map(prior.reconstruct, jnp.asarray(test), batch_size=16))
    prior_info["test_reconstruction_error_mm"] = float(
        1e3 * np.linalg.norm(recon - test, axis=-1).mean()
    )
    proj = np.einsum("nvd,kvd->nk", test - np.asarray(model.mean), np.asarray(model.basis))
    pca_rec = np.asarray(model.mean) + np.einsum("nk,kvd->nvd", proj, np.asarray(model.basis))
    pca_floor = float(1e3 * np.linalg.norm(pca_rec - test, axis=-1).mean())

    idx = jnp.asarray(lm_idx)
    ms = int(cfg["max_steps"])

    def run_space(targets, cw, reg=None):
        v, res, steps = _fit_space_batch(model, idx, jnp.asarray(targets), sigma,
                                         jnp.asarray(cw, jnp.float64), reg, ms)  # fmt: skip
        return np.asarray(v), np.asarray(res), np.asarray(steps)

    def run_latent(targets, lw, sw):
        v, res, steps = _fit_latent_batch(prior, idx, jnp.asarray(targets), sigma, mu, sd,
                                          jnp.asarray(lw, jnp.float64),
                                          jnp.asarray(sw, jnp.float64), ms)  # fmt: skip
        return np.asarray(v), np.asarray(res), np.asarray(steps)

    def reg_for(w, wr):
        # The reconstruction block is always present (weight possibly 0): one compilation.
        return dspp.shape_prior_residual(prior, w, reconstruction_weight=wr, reconstruction=True)

    # ---- validation grids
    t0 = _clock()
    grids: dict[str, list] = {"pca": [], "pca_dspp": [], "dspp_latent": []}
    bar = tqdm(desc="validation grid", disable=not progress, unit="fit-set")
    for cw in cfg["coeff_weights"]:
        v, res, _ = run_space(val_t, cw)
        e = float(_errors_mm(v, val)[0].mean())
        grids["pca"].append(dict(coeff_weight=cw, val_error_mm=e))
        bar.update()
        _log(progress, f"pca grid point {cw}: {e:.2f} mm")
    best_pca = min(grids["pca"], key=lambda r: r["val_error_mm"])
    cw = best_pca["coeff_weight"]
    for w, wr in itertools.product(cfg["score_weights"], cfg["recon_weights"]):
        v, res, _ = run_space(val_t, cw, reg_for(w, wr))
        e = float(_errors_mm(v, val)[0].mean())
        grids["pca_dspp"].append(
            dict(coeff_weight=cw, score_weight=w, reconstruction_weight=wr, val_error_mm=e)
        )
        bar.update()
        _log(progress, f"pca_dspp grid point {w}, {wr}: {e:.2f} mm")
    for lw, sw in itertools.product(cfg["latent_weights"], cfg["latent_score_weights"]):
        v, res, _ = run_latent(val_t, lw, sw)
        e = float(_errors_mm(v, val)[0].mean())
        grids["dspp_latent"].append(dict(latent_weight=lw, score_weight=sw, val_error_mm=e))
        bar.update()
        _log(progress, f"latent grid point {lw}, {sw}: {e:.2f} mm")
    bar.close()
    chosen = {k: min(g, key=lambda r: r["val_error_mm"]) for k, g in grids.items()}
    timings["validation_s"] = _since(t0)
    _log(progress, f"validation done: {timings['validation_s']}; chosen {chosen}")

    # ---- test (used once)
    t0 = _clock()
    c = chosen["pca_dspp"]
    fits = {
        "pca": run_space(test_t, cw),
        "pca_dspp": run_space(test_t, cw, reg_for(c["score_weight"], c["reconstruction_weight"])),
        "dspp_latent": run_latent(test_t, chosen["dspp_latent"]["latent_weight"],
                                  chosen["dspp_latent"]["score_weight"]),
    }  # fmt: skip
    timings["test_s"] = _since(t0)
    errors, per_vertex, results = {}, {}, {}
    for name, (v, res, steps) in fits.items():
        e, pv = _errors_mm(v, test)
        lm_rms = 1e3 * np.sqrt(np.mean(np.sum((v[:, lm_idx] - test[:, lm_idx]) ** 2, -1), 1))
        errors[name] = e
        per_vertex[name] = pv.mean(0)
        results[name] = dict(
            vertex_error_mm=_summary(e), landmark_error_mm=_summary(lm_rms),
            chosen=chosen[name], solver_success=float(np.mean(res)),
            mean_steps=float(np.mean(steps)),
        )  # fmt: skip
    for name in ("pca_dspp", "dspp_latent"):
        diff = errors[name] - errors["pca"]
        results[name]["vs_pca"] = dict(
            mean_difference_mm=float(diff.mean()),
            std_error_mm=float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else 0.0,
            fraction_better=float(np.mean(diff < 0)),
        )  # fmt: skip

    # ---- figure: mean per-vertex test error of each method on the PCA mean shape
    t0 = _clock()
    mean_shape = np.asarray(model.mean)
    vmax = float(np.percentile(np.concatenate(list(per_vertex.values())), 98))
    panels = [
        bp.render_vertex_colors(
            mean_shape, faces, per_vertex[k], vmin=0.0, vmax=vmax, cmap="magma", size=(420, 230)
        )  # fmt: skip
        for k in per_vertex
    ]
    image = np.concatenate(panels, axis=1)
    title = " | ".join(f"{k}: {results[k]['vertex_error_mm']['mean']:.1f} mm" for k in per_vertex)
    png = os.path.join(args.out, "dspp_prior_fit.png")
    bp.figure_with_colorbar(image, vmin=0.0, vmax=vmax, cmap="magma", label="mean error [mm]",
                            title=title, path=png)  # fmt: skip
    timings["figure_s"] = _since(t0)
    timings["total_s"] = _since(t_start)

    metrics = dict(
        experiment="dspp_prior_fit",
        mode="quick" if args.quick else "full",
        seed=args.seed,
        sizes=dict(
            n_train=n_train,
            n_val=n_val,
            n_test=n_test,
            n_vertices=int(train.shape[1]),
            n_landmarks=int(len(lm_idx)),
            n_components=int(model.n_components),
        ),  # fmt: skip
        noise_mm_per_coordinate=args.noise_mm,
        fitter_noise_sigma_m=sigma,
        solver="optimistix.LevenbergMarquardt, float64",
        prior=prior_info,
        pca_projection_floor_mm=pca_floor,
        results=results,
        validation_grids=grids,
        timings_s=timings,
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            jax=jax.__version__,
            note="shared 2-core machine; timings are indicative",
        ),  # fmt: skip
        figure=os.path.basename(png),
    )
    bp.atomic_write_json(os.path.join(args.out, "metrics.json"), metrics)
    if progress:
        for k, r in results.items():
            print(f"{k:12s} vertex error {r['vertex_error_mm']['mean']:.2f} mm "
                  f"(median {r['vertex_error_mm']['median']:.2f})", file=sys.stderr)  # fmt: skip
    return metrics


if __name__ == "__main__":
    main()
