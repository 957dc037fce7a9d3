"""Shape-space evaluation: bootstrapping, training-set size, posture normalization (paper §4.5, §5,
Figs. 2-4).

Pishchulin et al. 2017 on the synthetic population scanned by the virtual laser scanner instead of
CAESAR (`shared/papers/sscape_statistical_shape_spaces.txt`):

1. **Data** (seeded, `--seed`): one population `bodyprior.sample_population(fold_in(key, 0), ...)`
   (4 deg standing-posture jitter, like CAESAR's "standard posture"), split by index into `n_init`
   bodies for the *initial* space (ground-truth meshes, the stand-in for the paper's MPI Human Shape
   space), `n_boot` bodies that are scanned (`simulate_scans`, default scanner) and registered, and
   `n_test` scanned test bodies, never registered or learned from: their scans and ground-truth
   meshes calibrate the gate (`calibrate_gate`: thresholds only) and their true meshes are the
   held-out shapes of the generalization tests. A second, larger ground-truth pool
   (`fold_in(key, 3)`) serves the training-set-size sweep.
2. **Bootstrapping** (§3.3, §4.5, Fig. 2; `--init-space anny` starts from a space of bodies drawn
   by anny's phenotype sampler instead, a mismatched data set like the paper's MPI space, and
   `--bootstrap-only` stops after this step): `bootstrap` with S-SCAPE + NRD registration
   (`fit_sscape_batch`, `nrd`) and the calibrated `registration_gate` for `n_passes` passes; per
   pass the accepted count, the fitting-error and ground-truth-error curves of all registrations,
   and the space learned from the accepted ones. Spaces per pass are compared as in §5.2:
   generalization to the *test bodies' ground-truth meshes* (held out; the paper, without ground
   truth, used the last pass's registrations) and specificity against the last pass's registrations.
3. **Training-set size** (§5.3, Fig. 3b): spaces from random subsets of 50, 100, 1000 and all
   ground-truth pool meshes; generalization to held-out pool meshes, specificity against all pool
   meshes. Registering 1000+ simulated scans is beyond this 2-core machine in the time allowed, so
   this sweep uses ground-truth meshes - it measures the effect of the sample count alone (the
   registrations' own effect is the bootstrapping sweep).
4. **Posture normalization** (§3.4, §5.4, Figs. 3c, 4): the last pass's accepted registrations as
   is, NH-normalized (poses of the S-SCAPE fits) and WSX-normalized; each space's leave-one-out
   generalization and specificity against its own normalized training set (the paper's protocol),
   compactness, and the reconstruction of the test bodies' true *rest-posture* shapes. The same on
   `n_posture` ground-truth pool meshes (true poses for NH), a larger set. PCA modes at +-3 sd.

Writes `metrics.json` and PNG figures to `--out`. `--quick` is the CI size.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pickle
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior import (
    registration,  # noqa: E402
    sscape,  # noqa: E402
)
from bodyprior.sscape import FitConfig  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
# The registration experiment's S-SCAPE fit priors (landmark term, pose prior; chosen there).
from sscape_registration import FIT_PRIORS  # noqa: E402

SIZES = {
    "quick": dict(n_init=12, n_boot=6, n_test=2, n_passes=2, points=6449, fit_passes=2,
                  pool=60, sizes=(10, 20, 40), n_eval=10, n_posture=16, spec_samples=200,
                  spec_samples_big=200, spec_samples_posture=200, components=(1, 2, 3, 5),
                  n_init_components=5),
    "full": dict(n_init=30, n_boot=60, n_test=6, n_passes=5, points=9674, fit_passes=3,
                 pool=1100, sizes=(50, 100, 1000), n_eval=100, n_posture=200,
                 spec_samples=10000, spec_samples_big=200, spec_samples_posture=500,
                 components=(1, 2, 3, 5, 8, 10, 15, 20), n_init_components=20),
}  # fmt: skip


def _mm(x):
    """Millimetre values (the sscape quality measures already report mm), rounded to 1 um."""
    return np.asarray(x, np.float64).round(3).tolist()


def _ms(components, n_train):
    return tuple(m for m in components if m <= n_train - 1)


def space_measures(meshes, faces, rig, components, key, n_samples, *, loo=True):
    """Learns a space from aligned `meshes` and returns (model, aligned, generalization (LOO),
    specificity, compactness) with errors in mm."""
    aligned, _ = sscape.procrustes_align(jnp.asarray(meshes))
    model = sscape.learn(aligned, faces, align=False, rig=rig)
    # Leave-one-out trains on N - 1 meshes, so at most N - 2 components.
    ms = _ms(components, meshes.shape[0] - 1)
    out = {"n_train": int(meshes.shape[0]), "components": list(ms)}
    if loo:
        g = sscape.generalization(aligned, ms)
        out["generalization_mm"] = _mm(g.mean)
        out["generalization_se_mm"] = _mm(g.std_error)
    s = sscape.specificity(model, aligned, ms, key=key, n_samples=n_samples)
    out["specificity_mm"] = _mm(s.mean)
    out["specificity_se_mm"] = _mm(s.std_error)
    out["compactness"] = np.asarray(sscape.compactness(model).ratio)[: max(ms)].round(5).tolist()
    return model, aligned, out


def plot_curves(path, series, xlabel, ylabel, title):
    """Line plot of label -> (x, y) to a PNG (matplotlib Agg)."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.2, 3.8), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for label, (x, y) in series.items():
        ax.plot(x, y, marker="o", ms=3, lw=1.5, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with bp.atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def modes_png(path, models, labels, faces, n_modes=5):
    """Fig. 4: the first `n_modes` components of each space at -3 sd / +3 sd (rows = spaces;
    labels "<space> <component><sign>")."""
    meshes, names = [], []
    for model, label in zip(models, labels):
        for k in range(min(n_modes, model.n_components)):
            for sgn in (-3.0, 3.0):
                c = np.zeros(k + 1)
                c[k] = sgn
                meshes.append(np.asarray(model.shape_vertices(jnp.asarray(c))))
                names.append(f"{label} {k + 1}{'+' if sgn > 0 else '-'}")
    sheet = bp.contact_sheet(
        meshes, faces, ncols=2 * n_modes, labels=names, cell_size=(160, 96), antialias=1
    )
    bp.save_png(path, sheet)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI size (a few minutes)")
    ap.add_argument("--full", action="store_true", help="full size (default)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--resume", action="store_true", help="reuse the bootstrapping checkpoint")
    ap.add_argument(
        "--init-space", choices=("gt", "anny"), default="gt",
        help="initial space: ground-truth meshes of the population (default) or bodies from "
        "anny's phenotype sampler (a mismatched data set, as the paper's MPI space)",
    )  # fmt: skip
    ap.add_argument("--bootstrap-only", action="store_true", help="stop after bootstrapping")
    ap.add_argument("--init-bodies", type=int, default=None,
                    help="initial space from only the first N of its bodies")
    ap.add_argument("--init-components", type=int, default=None,
                    help="components of the initial space (default: the size's)")
    ap.add_argument(
        "--nrd",
        choices=("anchored", "paper"),
        default="anchored",
        help="NRD preset of the S-SCAPE + NRD registrations (NRDConfig.preset)",
    )
    ap.add_argument(
        "--correspondence", choices=("frozen", "first_accepted", "none"), default="frozen",
        help="bootstrap(correspondence=...): keep each scan's first accepted registration and stop "
        "at the fixed point (default), re-sample later registrations at it, or the paper's loop",
    )  # fmt: skip
    ap.add_argument("--landmark-gate", type=float, default=1.1,
                    help="calibrate the gate's landmark test at this factor over the references "
                         "largest landmark RMS (0 = off)")  # fmt: skip
    args = ap.parse_args(argv)
    size = SIZES["quick" if args.quick else "full"]
    out = args.out
    os.makedirs(out, exist_ok=True)
    progress = not args.no_progress
    t_start = time.perf_counter()
    times = {}
    key = jax.random.PRNGKey(args.seed)
    body = bp.load_default_body("cmu_mb", local_changes=True)
    tmpl = registration.registration_template()
    rig = tmpl.rig
    comps = size["components"]
    metrics: dict = {"mode": "quick" if args.quick else "full", "seed": args.seed, "sizes": {
        k: (list(v) if isinstance(v, tuple) else v) for k, v in size.items()}}  # fmt: skip

    # ---- data
    t0 = time.perf_counter()
    n_init, n_boot, n_test = size["n_init"], size["n_boot"], size["n_test"]
    pop = bp.sample_population(
        n_init + n_boot + n_test, body=body, progress=progress, key=jax.random.fold_in(key, 0)
    )
    full = np.asarray(pop.vertices, np.float64)
    gt = np.asarray(tmpl.restrict(full))
    rest_all = jax.jit(jax.vmap(lambda p, c: bp.rest_shape(body, p, c)[0]))(
        pop.phenotypes, pop.local_changes
    )
    rest = np.asarray(tmpl.restrict(rest_all), np.float64)
    scan_idx = np.arange(n_init, n_init + n_boot + n_test)
    scans, _ = registration.simulate_scans(
        full[scan_idx], body.faces, body.landmark_index,
        body.landmark_names, registration.ScannerConfig(n_points=size["points"]), progress=progress,
        key=jax.random.fold_in(key, 1),
    )  # fmt: skip
    boot = np.arange(n_boot)  # indices into the scans
    test = np.arange(n_boot, n_boot + n_test)
    take = lambda tree, idx: jax.tree_util.tree_map(lambda a: a[idx], tree)  # noqa: E731
    boot_scans, test_scans = take(scans, boot), take(scans, test)
    gt_boot, gt_test = gt[scan_idx[boot]], gt[scan_idx[test]]
    rest_test = rest[scan_idx[test]]
    times["data_s"] = time.perf_counter() - t0

    # ---- gate calibration: the test bodies' ground-truth meshes are perfect registrations of their
    # scans; they set the thresholds only (the test scans are never used for learning).
    gate = sscape.calibrate_gate(gt_test, test_scans, tmpl,
                                 landmark_factor=args.landmark_gate or None)  # fmt: skip
    gcal = sscape.registration_gate(gt_boot, boot_scans, tmpl, config=gate)
    metrics["gate"] = {
        "config": dataclasses.asdict(gate),
        "ground_truth_of_bootstrap_scans": {
            "accepted": int(gcal.accepted.sum()), "n": int(len(gcal.accepted)),
            "fraction_within_10mm": np.round(gcal.fraction, 4).tolist(),
            "worst_part_fraction": np.round(gcal.worst_part_fraction, 4).tolist(),
            "p99_mm": np.round(gcal.p99_mm, 2).tolist(),
        },
    }  # fmt: skip

    # ---- bootstrapping (Fig. 2, §5.2)
    t0 = time.perf_counter()
    if args.init_space == "gt":
        init_meshes = gt[:n_init]
    else:
        # The paper's setting: an initial space from another, less representative data set (the
        # MPI Human Shape space before CAESAR); here bodies from anny's phenotype sampler.
        other = bp.sample_population(n_init, body=body, scheme="anny", progress=progress,
                                     key=jax.random.fold_in(key, 7))  # fmt: skip
        init_meshes = np.asarray(tmpl.restrict(other.vertices), np.float64)
    # a weaker initial space (fewer bodies / components) that fails on some scans, to see the
    # loop add them; the scans stay the same
    init_meshes = init_meshes[: args.init_bodies or n_init]
    k_init = int(min(args.init_components or size["n_init_components"], len(init_meshes) - 1))
    metrics["initial_space"] = {"source": args.init_space, "n_train": int(len(init_meshes)),
                                "n_components": k_init}  # fmt: skip
    init_model = sscape.learn(jnp.asarray(init_meshes), tmpl.faces, n_components=k_init, rig=rig)
    # The registration experiment's settings: its fit priors (landmark term, pose prior) and NRD
    # without humanshape's head rule (the simulated heads are real; see docs/results_sscape.md).
    fit_config = FitConfig(max_passes=size["fit_passes"], **FIT_PRIORS)
    nrd_config = registration.NRDConfig.preset(args.nrd, head_rule=False)
    metrics["registration_config"] = {"fit": {"max_passes": size["fit_passes"], **FIT_PRIORS},
                                      "nrd": {"preset": args.nrd, "head_rule": False,
                                              "config": repr(nrd_config)},
                                      "landmark_gate_factor": args.landmark_gate,
                                      "correspondence": args.correspondence}  # fmt: skip

    def register(model, s):
        return sscape.register_sscape_nrd(
            model, s, tmpl, fit_config=fit_config, nrd_config=nrd_config, progress=progress
        )

    def on_pass(r, p):
        print(f"pass {r}: {p.n_accepted}/{n_boot} accepted", flush=True)

    ckpt = os.path.join(out, "bootstrap_checkpoint.pkl")
    if args.resume and os.path.exists(ckpt):  # debugging aid: skip the registrations
        with open(ckpt, "rb") as f:
            res = pickle.load(f)
    else:
        res = sscape.bootstrap(
            init_model, boot_scans, tmpl, n_passes=size["n_passes"], n_components=max(comps),
            gate=gate, register=register, callback=on_pass, progress=progress,
            correspondence=args.correspondence,
        )  # fmt: skip
        with bp.atomic_open(ckpt, "wb") as f:
            pickle.dump(res, f)
    times["bootstrap_s"] = time.perf_counter() - t0
    last = res.passes[-1]
    boot_m: dict = {"accepted_per_pass": res.accepted_per_pass, "n_scans": n_boot,
                    "paper_accepted_per_pass": [1771, 3253, 3641, 4237, 4301],
                    "paper_n_scans": 4308, "passes": []}  # fmt: skip
    curves_fit, curves_gt = {}, {}
    final_aligned, _ = sscape.procrustes_align(jnp.asarray(last.registration.vertices))
    spaces = [p.model for p in res.passes[1:]] + [res.model]
    for r, p in enumerate(res.passes):
        fe = registration.fitting_error_batch(p.registration.vertices, boot_scans, faces=tmpl.faces)
        ge = np.asarray(registration.gt_error(p.registration.vertices, gt_boot))
        curves_fit[f"iteration {r}"] = registration.cumulative_curve(fe.error_mm, valid=fe.valid)
        curves_gt[f"iteration {r}"] = registration.cumulative_curve(ge)
        valid = np.asarray(fe.valid)
        seen = sscape.observed_vertices(p.registration.vertices, boot_scans)
        space = spaces[r]  # learned from this pass's accepted registrations
        ms = _ms(comps, space.n_components + 1)
        gen = sscape.reconstruction_error(space, gt_test, ms).mean(0)
        # The last pass's registrations, rigidly aligned into this space's frame.
        final_here, _ = sscape.procrustes_align(final_aligned, reference=space.mean)
        spec = sscape.specificity(
            space, final_here, ms, key=jax.random.fold_in(key, 10 + r),
            n_samples=size["spec_samples"],
        )  # fmt: skip
        boot_m["passes"].append({
            "accepted": p.n_accepted,
            "fitting_error_mm_mean": float(np.asarray(fe.error_mm)[valid].mean()),
            "fitting_frac_below_10mm": float(registration.cumulative_curve(fe.error_mm, [10.0],
                                                                     valid=fe.valid)[0]),
            "gt_error_mm_mean": float(ge.mean()),
            "gt_frac_below_10mm": float((ge <= 10.0).mean()),
            # true error where the scan saw the surface, and over its holes (filled by the space)
            "gt_error_observed_mm_mean": float(ge[seen].mean()),
            "gt_error_unobserved_mm_mean": float(ge[~seen].mean()) if (~seen).any() else 0.0,
            "unobserved_fraction": float((~seen).mean()),
            "gate_fraction_mean": float(p.gate.fraction.mean()),
            "gate_landmark_rms_mm_mean": float(np.nanmean(p.gate.landmark_rms_mm)),
            "accepted_gt_error_mm_mean": float(ge[p.gate.accepted].mean())
            if p.n_accepted else float("nan"),
            "space_components": list(ms),
            "space_generalization_test_gt_mm": _mm(gen),
            "space_specificity_vs_last_pass_mm": _mm(spec.mean),
        })  # fmt: skip
    registration.plot_cumulative_curves(
        curves_fit, registration.THRESHOLDS_20MM, os.path.join(out, "bootstrap_fitting_error.png"),
        title=f"fitting error per bootstrapping pass ({n_boot} scans)", inset=(5, 15),
    )  # fmt: skip
    registration.plot_cumulative_curves(
        curves_gt, registration.THRESHOLDS_20MM, os.path.join(out, "bootstrap_gt_error.png"),
        title=f"ground-truth error per bootstrapping pass ({n_boot} scans)", inset=(5, 15),
    )  # fmt: skip
    bl = boot_m["passes"]
    plot_curves(
        os.path.join(out, "bootstrap_spaces.png"),
        {f"gen., after pass {r}": (b["space_components"], b["space_generalization_test_gt_mm"])
         for r, b in enumerate(bl)}
        | {f"spec., after pass {r}": (b["space_components"], b["space_specificity_vs_last_pass_mm"])
           for r, b in enumerate(bl)},
        "number of components", "error [mm]", "spaces per bootstrapping pass (Fig. 3a)",
    )  # fmt: skip
    metrics["bootstrapping"] = boot_m
    if args.bootstrap_only:
        return _finish(metrics, times, t_start, out, "bootstrapping only")

    # ---- training-set size (Fig. 3b) on ground-truth meshes
    t0 = time.perf_counter()
    pool_pop = bp.sample_population(size["pool"], body=body,
                                    progress=progress, key=jax.random.fold_in(key, 3))  # fmt: skip
    pool = np.asarray(tmpl.restrict(pool_pop.vertices), np.float64)
    pool_aligned, _ = sscape.procrustes_align(jnp.asarray(pool))
    pool_aligned = np.asarray(pool_aligned)
    rng = np.random.default_rng(args.seed)
    perm = rng.permutation(size["pool"])
    eval_idx, train_pool = perm[: size["n_eval"]], perm[size["n_eval"] :]
    size_m = {
        "note": "ground-truth meshes (not registrations): registering 1000+ scans does not fit "
        "the 2-core budget",
        "n_eval_held_out": int(size["n_eval"]),
        "by_size": {},
    }
    series_g, series_s = {}, {}
    for n in list(size["sizes"]) + [len(train_pool)]:
        idx = rng.choice(train_pool, n, replace=False) if n < len(train_pool) else train_pool
        model = sscape.learn(jnp.asarray(pool_aligned[idx]), tmpl.faces, align=False, rig=rig)
        ms = _ms(comps, n)
        gen = sscape.reconstruction_error(model, pool_aligned[eval_idx], ms, align=False).mean(0)
        spec = sscape.specificity(model, pool_aligned, ms, key=jax.random.fold_in(key, 20 + n),
                                  n_samples=size["spec_samples_big"], chunk_size=16)  # fmt: skip
        label = "all" if n == len(train_pool) else str(n)
        size_m["by_size"][label] = {"n_train": int(n), "components": list(ms),
                                    "generalization_mm": _mm(gen),
                                    "specificity_mm": _mm(spec.mean)}  # fmt: skip
        series_g[f"gen., {label} ({n})"] = (list(ms), _mm(gen))
        series_s[f"spec., {label} ({n})"] = (list(ms), _mm(spec.mean))
        print(f"size {n}: gen {_mm(gen)[-1]} mm, spec {_mm(spec.mean)[-1]} mm", flush=True)
    plot_curves(
        os.path.join(out, "size_generalization.png"),
        series_g,
        "number of components",
        "generalization error [mm]",
        "training-set size (Fig. 3b), held-out meshes",
    )
    plot_curves(os.path.join(out, "size_specificity.png"), series_s, "number of components",
                "specificity error [mm]", "training-set size (Fig. 3b)")  # fmt: skip
    metrics["training_size"] = size_m
    times["training_size_s"] = time.perf_counter() - t0

    # ---- posture normalization (Fig. 3c, Fig. 4)
    t0 = time.perf_counter()
    acc = last.gate.accepted if last.n_accepted >= 3 else np.ones(n_boot, bool)
    regs = last.registration.vertices[acc]
    poses = last.registration.poses[acc]
    sims = jax.tree_util.tree_map(lambda a: np.asarray(a)[acc], last.registration.similarities)
    prig = sscape.posture_rig(tmpl)  # topology, Laplacian weights, NH factorisation: built once
    sets = {
        "none": np.asarray(regs, np.float64),
        "NH": sscape.normalize_posture_nh_batch(regs, poses, prig, similarities=sims),
        "WSX": sscape.normalize_posture_wsx_batch(regs, prig),
    }
    pn_key = jax.random.fold_in(key, 40)
    post_m = {
        "registrations_used": "accepted in the last pass"
        if last.n_accepted >= 3
        else "all of the last pass (fewer than 3 accepted)",
        "registrations": {},
        "ground_truth_pool": {},
    }
    models = {}
    for name, meshes in sets.items():
        model, _, m = space_measures(meshes, tmpl.faces, rig, comps, pn_key, size["spec_samples"])
        ms = m["components"]
        m["test_rest_shape_reconstruction_mm"] = _mm(
            sscape.reconstruction_error(model, rest_test, ms).mean(0)
        )
        post_m["registrations"][name] = m
        models[name] = model
    # The same on a larger set of ground-truth meshes (true poses for NH).
    npst = min(size["n_posture"], size["pool"])
    gsets = {
        "none": pool[:npst],
        "NH": sscape.normalize_posture_nh_batch(pool[:npst], pool_pop.poses[:npst], prig),
        "WSX": sscape.normalize_posture_wsx_batch(pool[:npst], prig),
    }
    pool_rest = np.asarray(tmpl.restrict(jax.jit(jax.vmap(
        lambda p, c: bp.rest_shape(body, p, c)[0]))(pool_pop.phenotypes[:npst],
                                                    pool_pop.local_changes[:npst])))  # fmt: skip
    gmodels = {}
    for name, meshes in gsets.items():
        model, _, m = space_measures(
            meshes, tmpl.faces, rig, comps, pn_key, size["spec_samples_posture"]
        )
        err = []
        for a, b in zip(meshes, pool_rest):
            s = bp.umeyama(jnp.asarray(a), jnp.asarray(b), with_scale=False)
            err.append(
                1000 * np.linalg.norm(np.asarray(s.apply(jnp.asarray(a))) - b, axis=1).mean()
            )
        m["normalized_vs_true_rest_mm"] = float(np.mean(err))
        m["test_rest_shape_reconstruction_mm"] = _mm(
            sscape.reconstruction_error(model, rest_test, m["components"]).mean(0)
        )
        post_m["ground_truth_pool"][name] = m
        gmodels[name] = model
    metrics["posture"] = post_m
    for tag, src in (("registrations", post_m["registrations"]),
                     ("gt", post_m["ground_truth_pool"])):  # fmt: skip
        plot_curves(
            os.path.join(out, f"posture_{tag}.png"),
            {f"gen. {k}": (v["components"], v["generalization_mm"]) for k, v in src.items()}
            | {f"spec. {k}": (v["components"], v["specificity_mm"]) for k, v in src.items()},
            "number of components", "error [mm]",
            f"posture normalization (Fig. 3c), {tag}, n={next(iter(src.values()))['n_train']}",
        )  # fmt: skip
    modes_png(
        os.path.join(out, "pca_modes.png"),
        [init_model, gmodels["none"], gmodels["WSX"], gmodels["NH"]],
        ["initial", "ours", "WSX", "NH"], tmpl.faces,
    )  # fmt: skip
    times["posture_s"] = time.perf_counter() - t0

    # Headline numbers at 10 components (or the largest available).
    def at(m, key_, c=10):
        ms = m["components"]
        return m[key_][ms.index(c)] if c in ms else m[key_][-1]

    metrics["summary"] = {
        "accepted_per_pass": res.accepted_per_pass,
        "generalization_mm_at_10": {k: at(v, "generalization_mm")
                                    for k, v in post_m["ground_truth_pool"].items()},
        "specificity_mm_at_10": {k: at(v, "specificity_mm")
                                 for k, v in post_m["ground_truth_pool"].items()},
    }  # fmt: skip
    return _finish(metrics, times, t_start, out, "all")


def _finish(metrics, times, t_start, out, what):
    """Records the timings, writes `metrics.json` to `out` and returns the metrics."""
    times["total_s"] = time.perf_counter() - t_start
    metrics["times"] = {k: round(v, 1) for k, v in times.items()}
    bp.atomic_write_json(os.path.join(out, "metrics.json"), metrics)
    print(f"done ({what}) in {times['total_s']:.0f} s -> {out}")
    return metrics


if __name__ == "__main__":
    main()
