"""S-SCAPE registration of simulated raw scans: the paper's Fig. 1 (and the space it learns).

Pishchulin et al. 2017, §4 (`shared/papers/sscape_statistical_shape_spaces.txt`), on the synthetic
population scanned by the virtual laser scanner instead of CAESAR:

1. **Data** (seeded, see `--seed`): one population of `n_init + n_train + n_test` bodies from
   `bodyprior.sample_population(fold_in(key, 0), ...)`, split by index: the first `n_init` bodies
   learn the *initial* S-SCAPE space (the stand-in for the space the paper starts from, learned on a
   smaller, different data set), the next `n_train` are the training scans, the last `n_test` the
   test scans. Scans: `simulate_scans(fold_in(key, 1), ...)` with the default
   [`bodyprior.registration.ScannerConfig`][] (19,347 points, 1 mm noise, 2 % outliers, 7.5 mm
   landmark
   noise, 5 % landmarks missing).
2. **Registration** of every scan (train and test) by the paper's four variants (Fig. 1): S-SCAPE
   fit alone (`fit_sscape_batch` with the initial space), NRD from the static template aligned by
   the landmark similarity, S-SCAPE + NRD (NRD initialised from the S-SCAPE fit) and S-SCAPE + NRD
   CW (constant weights). NRD runs without humanshape's head rule by default (`--head-rule` turns
   it on): the rule exists because CAESAR's heads were replaced by one dummy head, and on the
   simulated scans, which have real heads, it pushes head vertices outwards (measured on the rest
   body's own clean scan from a perfect start: ground-truth error 8.1 mm with it, 5.7 mm without).
   The S-SCAPE fit adds the landmark term to its surface passes and a stronger pose prior than
   the library defaults (`FIT_PRIORS`, `--fit-landmark-weight`, `--fit-pose-prior`; humanshape
   uses neither): on scans of another seed they cut its ground-truth error from 10.4 to 7.1 mm.
   In `--quick` the S-SCAPE fit uses a fixed random subset of 6,449 of the 19,347 scan points
   and 3 passes (it has ~120 unknowns), in `--tiny` 4,000 points and 2 passes; NRD always uses
   all points.
3. **Errors**, per vertex of the 6,449-vertex template, in mm: the paper's definition
   (`fitting_error`: nearest scan point within 50 mm and 60 degrees; vertices without one count as
   failures in the cumulative curves and are left out of the means) and the ground-truth error
   (`gt_error`: distance to the true corresponding vertex, which CAESAR cannot give). Cumulative
   curves 0-20 mm and 0-50 mm (Fig. 1a), mean error per vertex on the body (Fig. 1b).
4. **Learned space**: the S-SCAPE + NRD registrations of the training scans are Procrustes-aligned
   and a space is learned from them; generalization (leave-one-out) and specificity (random samples
   vs nearest training mesh, `fold_in(key, 2)`) per number of components, next to the same measures
   of a space learned from the training bodies' ground-truth meshes. The test bodies' true meshes
   are reconstructed by both spaces (a held-out generalization against ground truth).

Writes `metrics.json` and PNG figures to `--out`. `--quick` (CI, a few minutes on 2 cores) and
`--tiny` (smallest size with 20-component generalization) shrink the sizes; `--n-train`,
`--n-test`, `--n-init` override them.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior import (
    registration,  # noqa: E402
    sscape,  # noqa: E402
)

SIZES = {
    # points: scan points (the paper's 19,347 = 3 x 6,449 everywhere: NRD's point-to-point data term
    # needs more scan points than template vertices); fit_points: the random subset the S-SCAPE
    # fit uses (about 120 unknowns); fit_passes: its pose/shape passes.
    "tiny": dict(
        n_init=24, n_train=22, n_test=2, n_samples=200, points=19347, fit_points=4000, fit_passes=2
    ),
    "quick": dict(
        n_init=30, n_train=24, n_test=4, n_samples=1000, points=19347, fit_points=6449, fit_passes=3
    ),
    "full": dict(
        n_init=100,
        n_train=450,
        n_test=50,
        n_samples=10000,
        points=19347,
        fit_points=19347,
        fit_passes=10,
    ),
}
# The S-SCAPE fit's landmark term and pose prior (FitConfig; humanshape: 0 and none). Chosen on
# 8 scans of a different seed (1; reported runs use 0), 100-body initial space, ground-truth error
# of the S-SCAPE fit / after NRD [mm]: library defaults (0, 1) 10.43 / 10.94; landmarks 0.1 alone
# 7.92 / 9.15; (0.3, 100) 7.09 / 8.26; pose prior 1000 alone 12.50 / 11.07. Landmarks (~77, each
# with 7.5 mm noise) pin where the vertices lie along featureless limbs, which the surface term
# cannot see; the pose prior stops the thighs twisting about their axes.
FIT_PRIORS = dict(landmark_weight=0.3, pose_prior=100.0)
COMPONENTS = (1, 2, 3, 5, 8, 10, 15, 20)
METHODS = ("S-SCAPE", "NRD", "S-SCAPE + NRD", "S-SCAPE + NRD CW", "S-SCAPE + NRD anchored")
KEYS = {"S-SCAPE": "sscape_only", "NRD": "nrd", "S-SCAPE + NRD": "sscape_nrd",
        "S-SCAPE + NRD CW": "sscape_nrd_cw",
        "S-SCAPE + NRD anchored": "sscape_nrd_anchored"}  # fmt: skip
# NRD configurations: the paper's schedule (humanshape), NRD CW, and the refinement that keeps
# the S-SCAPE fit's correspondence (`NRDConfig.preset("anchored")`: point-to-plane data term,
# tangential-motion penalty, landmarks at full weight).
NRD_PRESETS = {"NRD": "paper", "S-SCAPE + NRD": "paper", "S-SCAPE + NRD CW": "paper_cw",
               "S-SCAPE + NRD anchored": "anchored"}  # fmt: skip


def _parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--seed", type=int, default=0, help="master seed (jax.random.PRNGKey)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="CI size (a few minutes on 2 cores)")
    mode.add_argument("--tiny", action="store_true", help="smallest size (22 training scans)")
    ap.add_argument("--n-init", type=int, default=None, help="bodies of the initial space")
    ap.add_argument("--n-train", type=int, default=None, help="training scans")
    ap.add_argument("--n-test", type=int, default=None, help="test scans")
    ap.add_argument("--components", type=int, default=20, help="components of the spaces")
    ap.add_argument("--points", type=int, default=None, help="scan points (default 19,347)")
    ap.add_argument("--fit-points", type=int, default=None, help="scan points the S-SCAPE fit uses")
    ap.add_argument("--fit-passes", type=int, default=None, help="S-SCAPE pose/shape passes")
    ap.add_argument(
        "--fit-landmark-weight",
        type=float,
        default=FIT_PRIORS["landmark_weight"],
        help="S-SCAPE fit: weight of the landmark term in the surface passes (humanshape: 0)",
    )
    ap.add_argument(
        "--fit-pose-prior",
        type=float,
        default=FIT_PRIORS["pose_prior"],
        help="S-SCAPE fit: weight of |theta_j|^2, mm^2 per rad^2 (library default 1)",
    )
    ap.add_argument(
        "--head-rule",
        action="store_true",
        help="NRD with humanshape's head rule (made for CAESAR's dummy heads; off by default)",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    size = dict(SIZES["tiny" if args.tiny else "quick" if args.quick else "full"])
    for k in ("n_init", "n_train", "n_test", "points", "fit_points", "fit_passes"):
        if getattr(args, k) is not None:
            size[k] = getattr(args, k)
    if size["n_train"] < min(args.components, 20) + 2:
        ap.error(f"--n-train must be >= components + 2 = {args.components + 2} for generalization")
    if size["n_init"] <= args.components or size["n_test"] < 1:
        ap.error("--n-init must exceed --components and --n-test must be >= 1")
    args.size = size
    args.mode = "tiny" if args.tiny else "quick" if args.quick else "full"
    return args


def _stack(tree_list):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *tree_list)


def _index(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _subsample(scans, n_points: int, seed: int = 42):
    """The same random subset of `n_points` point slots of every scan (batched Scan)."""
    p = scans.points.shape[1]
    if n_points >= p:
        return scans
    idx = jnp.asarray(np.sort(np.random.default_rng(seed).choice(p, n_points, replace=False)))
    return registration.Scan(
        scans.points[:, idx], scans.normals[:, idx], scans.point_mask[:, idx], scans.landmarks,
        scans.landmark_mask, scans.landmark_names,
    )  # fmt: skip


def register(model, scans, tmpl, *, fit_config=None, fit_points=None, head_rule=False,
             progress=True):  # fmt: skip
    """The four registration variants of Fig. 1 for a batch of scans; returns method -> (N, V, 3)
    fitted template meshes (scan frame) and the per-stage wall times (s). The S-SCAPE fit sees a
    random subset of `fit_points` scan points; NRD always sees all of them."""
    times = {}
    t0 = time.perf_counter()
    fit_config = sscape.FitConfig() if fit_config is None else fit_config
    fit_scans = scans if fit_points is None else _subsample(scans, fit_points)
    n = scans.points.shape[0]
    n_dev = len(jax.devices())
    n_chunks = -(-n // (4 * n_dev))  # about 4 scans per device per call, little padding
    chunk = -(-(-(-n // n_chunks)) // n_dev) * n_dev
    fits = sscape.fit_sscape_batch(
        model,
        fit_scans,
        tmpl,
        config=fit_config,
        chunk_size=chunk,
        progress=progress,
        throw=False,
    ).value
    times["sscape_fit_s"] = time.perf_counter() - t0
    tmpl_v = jnp.asarray(tmpl.vertices, jnp.float64)  # NRD runs in its input's dtype: float64
    lm_tmpl = tmpl_v[tmpl.landmark_index]
    out = {"S-SCAPE": np.asarray(fits.vertices)}
    inits = {
        "NRD": [sscape.fit_similarity(lm_tmpl, _index(scans, i)).apply(tmpl_v) for i in range(n)],
        "S-SCAPE + NRD": [jnp.asarray(fits.vertices[i], jnp.float64) for i in range(n)],
    }
    inits["S-SCAPE + NRD CW"] = inits["S-SCAPE + NRD"]
    inits["S-SCAPE + NRD anchored"] = inits["S-SCAPE + NRD"]
    cfgs = {
        name: registration.NRDConfig.preset(preset, head_rule=head_rule)
        for name, preset in NRD_PRESETS.items()
    }
    for name in NRD_PRESETS:
        t0 = time.perf_counter()
        res = []
        prep = registration.prepare_nrd(tmpl, n_patches=cfgs[name].n_patches)  # once per config
        for i in tqdm(range(n), desc=name, disable=not progress, unit="scan"):
            r = registration.nrd(
                inits[name][i], _index(scans, i), prep, config=cfgs[name], throw=False
            )
            res.append(np.asarray(r.value.vertices))
        out[name] = np.stack(res)
        times[KEYS[name] + "_s"] = time.perf_counter() - t0
    return out, times


def errors(regs, scans, gt, tmpl):
    """Per-vertex errors (mm) of every method: the paper's (with valid mask) and against GT."""
    out = {}
    for name, verts in regs.items():
        fe = registration.fitting_error_batch(jnp.asarray(verts), scans, faces=tmpl.faces)
        out[name] = dict(
            fit=np.asarray(fe.error_mm),
            valid=np.asarray(fe.valid),
            gt=np.asarray(registration.gt_error(jnp.asarray(verts), jnp.asarray(gt))),
        )
    return out


def _finite(obj):
    """NaN/inf floats -> None (JSON has no NaN), recursively."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _mean(x) -> float:
    return float(np.mean(x)) if np.size(x) else float("nan")


def _summary(e) -> dict:
    fit, valid, gt = e["fit"], e["valid"], e["gt"]
    c20 = registration.cumulative_curve(fit, [5.0, 10.0, 20.0], valid=valid)
    g = registration.cumulative_curve(gt, [5.0, 10.0, 20.0])
    return dict(
        gt_error_mm_mean=float(gt.mean()),
        gt_error_mm_median=float(np.median(gt)),
        gt_error_mm_p95=float(np.percentile(gt, 95)),
        gt_frac_below_5mm=float(g[0]),
        gt_frac_below_10mm=float(g[1]),
        gt_frac_below_20mm=float(g[2]),
        fit_error_mm_mean=_mean(fit[valid]),
        fit_valid_fraction=float(valid.mean()),
        fit_frac_below_5mm=float(c20[0]),
        fit_frac_below_10mm=float(c20[1]),
        fit_frac_below_20mm=float(c20[2]),
        per_scan_gt_error_mm=[float(x) for x in gt.mean(axis=1)],
    )


def learned_space_quality(train_meshes, test_meshes, tmpl, k, key, n_samples):
    """Procrustes-align, learn a k-component space; generalization, specificity and test
    reconstruction error (mm) per number of components."""
    aligned, _ = sscape.procrustes_align(jnp.asarray(train_meshes))
    k = min(k, len(train_meshes) - 1)  # PCA of N meshes has at most N - 1 components
    space = sscape.learn(aligned, tmpl.faces, n_components=k, align=False, rig=tmpl.rig)
    comps = tuple(c for c in COMPONENTS if c <= k)
    gen = sscape.generalization(aligned, comps)
    spec = sscape.specificity(space, aligned, comps, key=key, n_samples=n_samples)
    # Held-out test bodies: align each to the space's mean, project on the first M components.
    test_al, _ = sscape.procrustes_align(jnp.asarray(test_meshes), reference=space.mean)
    basis = np.asarray(space.basis).reshape(space.basis.shape[0], -1)  # (K, 3V), orthonormal rows
    d = np.asarray(test_al).reshape(len(test_meshes), -1) - np.asarray(space.mean).reshape(1, -1)
    rec = []
    for m in comps:
        b = basis[:m]
        x = np.asarray(space.mean).reshape(1, -1) + (d @ b.T) @ b
        err = np.linalg.norm(
            (x - np.asarray(test_al).reshape(len(test_meshes), -1)).reshape(
                len(test_meshes), -1, 3
            ),
            axis=-1,
        ).mean(axis=1)
        rec.append(float(err.mean() * 1000))
    return dict(
        components=list(comps),
        generalization_mm=[float(x) for x in np.asarray(gen.mean)],  # already mm
        specificity_mm=[float(x) for x in np.asarray(spec.mean)],
        test_reconstruction_mm=rec,
        explained_variance=[float(x) for x in np.cumsum(np.asarray(space.explained_variance))],
    )


def _plot_space(path, quality: dict):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.4), dpi=100)
    FigureCanvasAgg(fig)
    for ax, key, title in zip(
        fig.subplots(1, 3),
        ("generalization_mm", "specificity_mm", "test_reconstruction_mm"),
        ("Generalization (leave-one-out)", "Specificity", "Test bodies (ground truth)"),
    ):
        for label, q in quality.items():
            ax.plot(q["components"], q[key], marker="o", ms=3, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("number of components")
        ax.set_ylabel("mean vertex error [mm]")
        ax.grid(alpha=0.3)
    fig.axes[0].legend(fontsize=8)
    fig.tight_layout()
    with bp.atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")


def _coverage_png(path, scan_truth, vertices, faces):
    """Scan coverage on the true body: points per area relative to the body's mean (holes dark)."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces)
    face = np.asarray(scan_truth.face)
    face = face[face >= 0]
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    cnt = np.zeros(len(v))
    np.add.at(cnt, f[face].ravel(), 1.0 / 3.0)
    varea = np.zeros(len(v))
    np.add.at(varea, f.ravel(), np.repeat(area / 3.0, 3))
    rel = np.clip(cnt / np.maximum(varea, 1e-12) / (len(face) / area.sum()), 0.0, 2.0)
    imgs = [
        bp.render_vertex_colors(v, f, rel, vmin=0, vmax=2, view=vw, size=(420, 300), cmap="magma")
        for vw in ("front", "back", (90.0, -35.0), (0.0, 60.0))
    ]
    bp.figure_with_colorbar(
        np.concatenate(imgs, axis=1), vmin=0, vmax=2, cmap="magma", path=path,
        label="scan points per area / body mean", title="Simulated scan coverage (holes dark)",
    )  # fmt: skip


def main(argv=None) -> dict:
    args = _parse(argv)
    size = args.size
    out = args.out
    os.makedirs(out, exist_ok=True)
    progress = not args.no_progress
    t_start = time.perf_counter()
    key = jax.random.PRNGKey(args.seed)
    body = bp.load_default_body("cmu_mb", local_changes=True)
    tmpl = registration.registration_template()
    n_init, n_train, n_test = size["n_init"], size["n_train"], size["n_test"]
    n_all = n_init + n_train + n_test
    t0 = time.perf_counter()
    pop = bp.sample_population(n_all, body=body, progress=progress, key=jax.random.fold_in(key, 0))
    t_pop = time.perf_counter() - t0
    full = np.asarray(pop.vertices, np.float64)
    gt_all = np.asarray(tmpl.restrict(full))
    init_meshes = gt_all[:n_init]
    scan_bodies = slice(n_init, n_all)
    gt = gt_all[scan_bodies]

    t0 = time.perf_counter()
    cfg = registration.ScannerConfig(n_points=size["points"])
    scans, truths = registration.simulate_scans(
        full[scan_bodies], body.faces, body.landmark_index,
        body.landmark_names, cfg, progress=progress, key=jax.random.fold_in(key, 1),
    )  # fmt: skip
    t_scan = time.perf_counter() - t0
    registration.check_scan(scans)

    k = args.components
    model0 = sscape.learn(jnp.asarray(init_meshes), tmpl.faces, n_components=k, rig=tmpl.rig)
    fit_config = sscape.FitConfig(
        max_passes=size["fit_passes"],
        landmark_weight=args.fit_landmark_weight,
        pose_prior=args.fit_pose_prior,
    )
    regs, times = register(
        model0, scans, tmpl, fit_config=fit_config, fit_points=size["fit_points"],
        head_rule=args.head_rule, progress=progress,
    )  # fmt: skip
    errs = errors(regs, scans, gt, tmpl)
    # The paper's error of the true meshes themselves: a vertex exactly on the true surface is
    # about half a point spacing from its nearest scan *sample*, so no truthful registration can
    # score much below this; lower values mean vertices sit on samples instead.
    truth_err = errors({"truth": gt}, scans, gt, tmpl)["truth"]
    np.savez_compressed(
        os.path.join(out, "registrations.npz"),
        gt=gt, **{KEYS[m]: regs[m] for m in METHODS},
        **{f"{KEYS[m]}_{k}": v for m in METHODS for k, v in errs[m].items()},
    )  # fmt: skip

    # Figures: cumulative curves (Fig. 1a) by both definitions and both ranges.
    for kind, label in (("fit", "paper's fitting error"), ("gt", "ground-truth error")):
        ranges = ((registration.THRESHOLDS_20MM, "20mm"), (registration.THRESHOLDS_50MM, "50mm"))
        for thr, tag in ranges:
            curves = {
                m: registration.cumulative_curve(
                    errs[m][kind], thr, valid=errs[m]["valid"] if kind == "fit" else None
                )
                for m in METHODS
            }
            registration.plot_cumulative_curves(
                curves, thr, os.path.join(out, f"cumulative_{kind}_{tag}.png"),
                title=f"{label}, {len(gt)} simulated scans",
            )  # fmt: skip
    # Mean error per vertex on the body (Fig. 1b).
    for m in METHODS:
        for kind in ("fit", "gt"):
            e = errs[m][kind]
            mv = registration.mean_vertex_error(e, errs[m]["valid"] if kind == "fit" else None)
            mv = np.where(np.isfinite(mv), mv, 0.0)
            registration.error_colormap_png(
                os.path.join(out, f"mean_error_{kind}_{KEYS[m]}.png"), tmpl.vertices, tmpl.faces,
                mv, vmax=20.0, title=f"{m}: mean {'fitting' if kind == 'fit' else 'GT'} error [mm]",
            )  # fmt: skip
    cov_path = os.path.join(out, "scan_coverage.png")
    _coverage_png(cov_path, _index(truths, 0), full[n_init], body.faces)

    # Spaces learned from the registrations vs from the ground truth.
    sl = slice(0, n_train)
    quality = {
        "from S-SCAPE + NRD registrations": learned_space_quality(
            regs["S-SCAPE + NRD"][sl], gt[n_train:], tmpl, k, jax.random.fold_in(key, 2),
            size["n_samples"],
        ),
        "from ground-truth meshes": learned_space_quality(
            gt[sl], gt[n_train:], tmpl, k, jax.random.fold_in(key, 2), size["n_samples"]
        ),
    }  # fmt: skip
    _plot_space(os.path.join(out, "space_quality.png"), quality)

    summ = {m: _summary(errs[m]) for m in METHODS}
    reg_q, gt_q = quality["from S-SCAPE + NRD registrations"], quality["from ground-truth meshes"]
    i20 = reg_q["components"].index(k) if k in reg_q["components"] else -1
    n_scans = len(gt)
    metrics = dict(
        mode=args.mode,
        seed=args.seed,
        n_init=n_init,
        n_train=n_train,
        n_test=n_test,
        n_scans=n_scans,
        components=k,
        scan_points=int(scans.points.shape[1]),
        fit_points=size["fit_points"],
        fit_passes=size["fit_passes"],
        fit_landmark_weight=args.fit_landmark_weight,
        fit_pose_prior=args.fit_pose_prior,
        nrd_head_rule=bool(args.head_rule),
        scan_config={f: getattr(cfg, f) for f in cfg.__dataclass_fields__},
        nrd_gt_error_mm_mean=summ["NRD"]["gt_error_mm_mean"],
        nrd_frac_below_10mm=summ["NRD"]["gt_frac_below_10mm"],
        nrd_fit_frac_below_10mm=summ["NRD"]["fit_frac_below_10mm"],
        sscape_only_gt_error_mm_mean=summ["S-SCAPE"]["gt_error_mm_mean"],
        sscape_nrd_gt_error_mm_mean=summ["S-SCAPE + NRD"]["gt_error_mm_mean"],
        sscape_nrd_cw_gt_error_mm_mean=summ["S-SCAPE + NRD CW"]["gt_error_mm_mean"],
        sscape_nrd_anchored_gt_error_mm_mean=summ["S-SCAPE + NRD anchored"]["gt_error_mm_mean"],
        truth_fit_error_mm_mean=_mean(truth_err["fit"][truth_err["valid"]]),
        nrd_presets={
            KEYS[m]: registration.NRDConfig.preset(p).__repr__() for m, p in NRD_PRESETS.items()
        },
        generalization_mm_at_20=reg_q["generalization_mm"][i20],
        specificity_mm_at_20=reg_q["specificity_mm"][i20],
        gt_space_generalization_mm_at_20=gt_q["generalization_mm"][i20],
        gt_space_specificity_mm_at_20=gt_q["specificity_mm"][i20],
        methods={KEYS[m]: summ[m] for m in METHODS},
        spaces=quality,
        timings_s=dict(
            population=t_pop,
            scanning=t_scan,
            scans_per_s=n_scans / t_scan,
            **times,
            registration_scans_per_min=60.0 * n_scans / sum(times.values()),
            total=time.perf_counter() - t_start,
        ),
        note=(
            "generalization/specificity keys are for the space learned from the S-SCAPE + NRD "
            "registrations of the training scans, at `components` components (mm)."
        ),
    )
    bp.atomic_write_json(os.path.join(out, "metrics.json"), _finite(metrics))
    return metrics


if __name__ == "__main__":
    m = main()
    print(
        f"S-SCAPE {m['sscape_only_gt_error_mm_mean']:.2f} mm, "
        f"NRD {m['nrd_gt_error_mm_mean']:.2f} mm, "
        f"S-SCAPE + NRD {m['sscape_nrd_gt_error_mm_mean']:.2f} mm, "
        f"anchored {m['sscape_nrd_anchored_gt_error_mm_mean']:.2f} mm (GT error); "
        f"G(20) {m['generalization_mm_at_20']:.2f} mm, S(20) {m['specificity_mm_at_20']:.2f} mm; "
        f"{m['timings_s']['total']:.0f} s"
    )
