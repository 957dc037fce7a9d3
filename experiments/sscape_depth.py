"""Body shape from a front and a back depth image (Pishchulin et al. 2017, §6, Figs. 5-6).

Protocol (after Helten et al. 2013, as the paper follows it), on simulated data:

1. **Test subjects.** Population bodies (`bodyprior.sample_population`, a seed separate from the
   training population), half male and half female, each captured twice, from the front and from the
   back, in two different non-trivial poses (`bodyprior.registration.capture_poses`: arms spread and
   raised, elbows bent, legs apart, turned by up to 10 degrees).
2. **Depth images.** A Kinect-like camera (512 x 424, fx = fy = 365 px) 2.4 m away renders the exact
   depth of the full-resolution posed body with depth noise sigma = 1.5 mm * z^2 (8.6 mm at 2.4 m)
   and no returns at grazing angles (> 80 degrees); the depth points are back-projected with normals
   from the smoothed depth gradients and sub-sampled to a fixed count. 14 landmarks per image with
   10 mm placement noise stand in for the paper's 14 hand-placed ones.
3. **Shape spaces.** S-SCAPE spaces learned (`bodyprior.sscape.learn`) from the *ground-truth*
   template-topology meshes of a training population (registering 1000+ simulated scans first is too
   slow for this run; the registration experiment covers that step), with 100 / 1000 / all training
   bodies, without posture normalization and with NH or WSX (`bodyprior.sscape.learn_normalized`,
   NH with the true poses of the training bodies), truncated to 10 / 20 / 50 components. A
   "baseline" space stands in for the older MPI space of Jain et al. that the paper compares with:
   trained on few (50) bodies from a different, less representative distribution (anny's phenotype
   sampler, `scheme="anny"`).
4. **Fitting.** `bodyprior.sscape.fit_depth`: independent fits per image, then one shared shape and
   a pose per image.
5. **Error.** Per-vertex Euclidean distance (mm, `bodyprior.registration.gt_error`) between the
  fitted
   *rest shape* (the shared shape in the model's zero pose, times the fitted scale, rigidly aligned
   to the truth) and the subject's true rest shape restricted to the template; this is the shape
   accuracy Helten et al. measure against the laser-scan fit. Also reported: the error of the fitted
   *posed* meshes against the true posed bodies in each image's frame (hands excluded: their pose is
   not fitted). Cumulative curves (`bodyprior.registration.cumulative_curve`, 0-50 mm) are the
   paper's
   Fig. 5; per-vertex error maps of one male and one female subject are Fig. 6.

Run: `python experiments/sscape_depth.py --quick --out out/depth` (minutes) or `--full`.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior.registration import (
    capture_poses,
    cumulative_curve,
    gt_error,
    kinect_pair,
    registration_template,
    simulate_depth_scan,
)
from bodyprior.sscape import (
    DepthFitConfig,
    FitConfig,
    fit_depth,
    learn,
    learn_normalized,
    truncate,
)

THRESHOLDS = np.linspace(0.0, 50.0, 51)


@dataclasses.dataclass(frozen=True)
class Setting:
    n_train: int  # the "all" training set
    sizes: tuple[int, ...]
    components: tuple[int, ...]
    norms: tuple[str, ...]
    n_test: int
    n_points: int
    baseline: int  # training bodies of the baseline space (0 = none)
    config: DepthFitConfig


#: The depth-fit settings of every mode (rounds of the joint stage and solver steps kept small: on
#: the shared 2-core machine one fit costs tens of seconds and each component count compiles anew).
FIT = DepthFitConfig(fit=FitConfig(landmark_steps=30, shape_prior=1.0), max_rounds=4, pose_steps=8,
                     shape_steps=8)  # fmt: skip
#: `--preset paper`: the same without the shape prior (humanshape and the paper have none).
FIT_PAPER = dataclasses.replace(FIT, fit=dataclasses.replace(FIT.fit, shape_prior=0.0))

SETTINGS = {
    "tiny": Setting(12, (12,), (4,), ("none", "nh", "wsx"), 1, 2048, 0, FIT),
    "quick": Setting(60, (30, 60), (5, 10), ("none", "nh", "wsx"), 2, 2048, 20, FIT),
    "full": Setting(1000, (100, 1000), (10, 20, 50), ("none", "nh", "wsx"), 2, 2048, 50, FIT),
}


def _pad(model, k_max: int):
    """The model with zero components appended up to `k_max` (zero basis and stddev: the shape
    space is unchanged; the fitter's extra unknowns have zero Jacobian columns and stay at 0 under
    the Levenberg-Marquardt damping). Every space then has the same array shapes, so the fitter
    compiles once for all component counts instead of once per count."""
    extra = k_max - model.n_components
    if extra <= 0:
        return model
    z = jnp.zeros((extra,), model.stddev.dtype)
    basis = jnp.concatenate([model.basis, jnp.zeros((extra, *model.basis.shape[1:]))], 0)
    return eqx.tree_at(
        lambda m: (m.basis, m.stddev, m.explained_variance),
        model,
        (basis, jnp.concatenate([model.stddev, z]), jnp.concatenate([model.explained_variance, z])),
    )


# The result codes of metrics.json: under the one result convention (`bodyprior.Solution`) a fit
# that used all `max_rounds` is `RESULTS.successful` with `stats["converged"]` False; the metrics
# keep the code the earlier convention gave it.
_NOT_CONVERGED = "The data term was still changing after `max_passes` passes (the fit is usable)."


def _result_code(sol) -> str:
    if not bool(sol.result == bp.RESULTS.successful):
        return bp.RESULTS[sol.result]
    return "successful" if bool(sol.stats["converged"]) else _NOT_CONVERGED


def _rest_error(fit_rest, scale, true_rest):
    """Per-vertex error (mm) of the scaled fitted rest shape after rigid alignment to the truth."""
    x = np.asarray(fit_rest, np.float64) * float(scale)
    sim = bp.umeyama(x, true_rest, with_scale=False)
    return np.asarray(gt_error(sim.apply(x), true_rest))


def _subjects(key, body, tmpl, n, n_points, progress):
    """Test subjects: true rest/posed meshes and their front/back depth scans."""
    pool = bp.sample_population(max(4 * n, 8), body=body, progress=False, key=key)
    sex = np.asarray(pool.sex)
    males, females = np.flatnonzero(sex == 0), np.flatnonzero(sex == 1)
    pick = []
    for i in range(n):  # alternate male, female
        src = males if i % 2 == 0 else females
        if len(src) <= i // 2:
            src = np.arange(len(sex))
        pick.append(int(src[i // 2]))
    cams = kinect_pair(distance=2.4)
    faces = np.asarray(body.faces)
    lm_index = np.asarray(body.landmark_index)
    rest_joints = np.asarray(body.bones.head_template)
    out = []
    for s, i in enumerate(tqdm(pick, desc="depth captures", disable=not progress)):
        kp, ks = jr.split(jr.fold_in(key, 1000 + s))
        poses = capture_poses(body.joint_names, rest_joints, 2, key=kp)
        lc = pool.local_changes[i]
        rest, _ = bp.rest_shape(body, pool.phenotypes[i], lc)
        subj = dict(index=i, sex=int(sex[i]), rest=np.asarray(tmpl.restrict(rest), np.float64),
                    posed=[], scans=[], depth=[], poses=poses)  # fmt: skip
        for k, cam in enumerate(cams):
            v, _ = bp.evaluate(body, pool.phenotypes[i], jnp.asarray(poses[k]), local_changes=lc)
            v = np.asarray(v, np.float64)
            scan, _, depth = simulate_depth_scan(
                v, faces, cam, v[lm_index], body.landmark_names,
                n_points=n_points, key=jr.fold_in(ks, k),
            )  # fmt: skip
            subj["posed"].append(np.asarray(tmpl.restrict(v)))
            subj["scans"].append(scan)
            subj["depth"].append(depth)
        out.append(subj)
    return out, cams


def _spaces(key, body, tmpl, st: Setting, progress):
    """(name, norm, n_train, model with max components) for every training set and normalization."""
    train = bp.sample_population(st.n_train, body=body, progress=progress, key=key)
    meshes = np.asarray(tmpl.restrict(train.vertices), np.float64)
    poses = np.asarray(train.poses, np.float64)
    kmax = max(st.components)
    spaces, times = [], {}
    for n in st.sizes:
        for norm in st.norms:
            t0 = time.perf_counter()
            k = min(kmax, n - 1)
            model, _ = learn_normalized(jnp.asarray(meshes[:n]), tmpl, norm,
                                        poses=jnp.asarray(poses[:n]), n_components=k)  # fmt: skip
            times[f"{norm}_{n}"] = time.perf_counter() - t0
            spaces.append((norm, n, model))
    if st.baseline:
        base = bp.sample_population(st.baseline, body=body, scheme="anny",
                                    progress=False, key=jr.fold_in(key, 7))  # fmt: skip
        bm = np.asarray(tmpl.restrict(base.vertices), np.float64)
        k = min(kmax, st.baseline - 1)
        spaces.append(("baseline", st.baseline, learn(jnp.asarray(bm), tmpl.faces, n_components=k,
                                                      rig=tmpl.rig)))  # fmt: skip
    return spaces, times


def _plot_fig5(path, results, st: Setting):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    sizes = list(st.sizes)
    comps = list(st.components)
    fig = Figure(figsize=(3.2 * len(comps), 2.6 * len(sizes)), dpi=90)
    FigureCanvasAgg(fig)
    colors = {"baseline": "tab:gray", "none": "tab:blue", "wsx": "tab:green", "nh": "tab:red"}
    labels = {"baseline": "baseline (50, anny)", "none": "ours", "wsx": "ours + WSX",
              "nh": "ours + NH"}  # fmt: skip
    for r, n in enumerate(sizes):
        for c, k in enumerate(comps):
            ax = fig.add_subplot(len(sizes), len(comps), r * len(comps) + c + 1)
            for s in results:
                if s["n_components"] != k or (s["norm"] != "baseline" and s["n_train"] != n):
                    continue
                ax.plot(THRESHOLDS, 100 * np.asarray(s["rest_curve"]), color=colors[s["norm"]],
                        label=labels[s["norm"]], lw=1.4)  # fmt: skip
            ax.set_xlim(0, THRESHOLDS[-1])
            ax.set_ylim(0, 100)
            ax.grid(alpha=0.3)
            ax.set_title(f"{k} components, {n} training", fontsize=8)
            ax.tick_params(labelsize=7)
            if r == len(sizes) - 1:
                ax.set_xlabel("error threshold [mm]", fontsize=8)
            if c == 0:
                ax.set_ylabel("vertices below [%]", fontsize=8)
            if r == 0 and c == 0:
                ax.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    _save_fig(fig, path)


def _save_fig(fig, path):
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with bp.atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def _plot_depth(path, subj, cams):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.6), dpi=90)
    FigureCanvasAgg(fig)
    for k, name in enumerate(("front", "back")):
        ax = fig.add_subplot(1, 2, k + 1)
        d = subj["depth"][k]
        im = ax.imshow(np.where(d > 0, d, np.nan), cmap="viridis", interpolation="nearest")
        ax.set_title(f"{name} depth [m] (512x424, noisy)", fontsize=9)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.04)
    fig.tight_layout()
    _save_fig(fig, path)


def _plot_fitted(path, fit, subj, faces):
    fitted = np.asarray(fit.vertices)
    imgs = []
    for k, view in enumerate(("front", "back")):
        box = bp.mesh_bounds(fitted[k], subj["posed"][k])
        a = bp.render_mesh(subj["posed"][k], faces, view=view, size=(360, 270), fit=box,
                           color=(0.85, 0.75, 0.7), antialias=1)  # fmt: skip
        b = bp.render_mesh(fitted[k], faces, view=view, size=(360, 270), fit=box, antialias=1)
        imgs += [a, b]
    bp.save_png(path, np.concatenate(imgs, axis=1))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="small run (minutes)")
    g.add_argument("--full", action="store_true", help="paper-sized grid (default)")
    ap.add_argument("--tiny", action="store_true", help="with --quick: the test suite's size")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--preset", choices=("default", "paper"), default="default",
                    help="fit settings: the library default (Gaussian shape prior, 1 mm^2 per "
                         "sd^2) or the paper's (no shape prior)")  # fmt: skip
    ap.add_argument("--budget-s", type=float, default=0.0,
                    help="start no new fit after this many seconds (0 = no limit)")  # fmt: skip
    args = ap.parse_args(argv)
    mode = ("tiny" if args.tiny else "quick") if args.quick else "full"
    st = SETTINGS[mode]
    if args.preset == "paper":
        st = dataclasses.replace(st, config=FIT_PAPER)
    progress = not args.no_progress
    os.makedirs(args.out, exist_ok=True)
    t_start = time.perf_counter()
    key = jr.PRNGKey(args.seed)
    tmpl = registration_template()
    body = bp.load_default_body("cmu_mb", local_changes=True)
    faces = np.asarray(tmpl.faces)
    hand = np.asarray(tmpl.hand_mask)

    t0 = time.perf_counter()
    subjects, cams = _subjects(jr.fold_in(key, 2), body, tmpl, st.n_test, st.n_points, progress)
    t_capture = time.perf_counter() - t0
    t0 = time.perf_counter()
    spaces, learn_times = _spaces(jr.fold_in(key, 1), body, tmpl, st, progress)
    t_learn = time.perf_counter() - t0

    results, fits_kept, fit_times = [], {}, []
    # Jobs ordered so that a time-limited run covers every space at the middle component count
    # first; the baseline's components are capped at its training size - 1.
    order = sorted(st.components, key=lambda k: (k != 20, k))
    jobs = [(norm, n, model, k) for k in order for norm, n, model in spaces]
    k_max = max(st.components)
    bar = tqdm(total=len(jobs) * len(subjects), desc="depth fits", disable=not progress)
    skipped = []
    for norm, n, model, k in jobs:
        if args.budget_s and time.perf_counter() - t_start > args.budget_s:
            skipped.append(dict(norm=norm, n_train=n, n_components=k))
            continue
        m = _pad(truncate(model, min(k, model.n_components)), k_max)
        rest_err, posed_err, rounds, codes = [], [], [], []
        for s, subj in enumerate(subjects):
            t0 = time.perf_counter()
            sol = fit_depth(m, subj["scans"][0], subj["scans"][1], tmpl, config=st.config,
                            throw=False)  # fmt: skip
            fit = sol.value
            jax.block_until_ready(fit.vertices)
            fit_times.append(time.perf_counter() - t0)
            rest_err.append(_rest_error(fit.rest_vertices, fit.scale, subj["rest"]))
            posed_err.append(np.concatenate(
                [np.asarray(gt_error(fit.vertices[v], subj["posed"][v]))[~hand] for v in (0, 1)]
            ))  # fmt: skip
            rounds.append(int(sol.stats["rounds"]))
            codes.append(_result_code(sol))
            fits_kept[(norm, n, k, s)] = fit
            bar.update(1)
        re, pe = np.stack(rest_err), np.stack(posed_err)
        curve = cumulative_curve(re, THRESHOLDS)
        results.append(dict(
            norm=norm, n_train=n, n_components=k,
            n_components_used=min(k, model.n_components),
            rest_error_mm_mean=float(re.mean()), rest_error_mm_median=float(np.median(re)),
            rest_error_mm_per_subject=[float(e.mean()) for e in re],
            rest_frac_below_10mm=float(curve[10]), rest_frac_below_20mm=float(curve[20]),
            rest_frac_below_30mm=float(curve[30]), rest_curve=curve.tolist(),
            posed_error_mm_mean=float(pe.mean()),
            posed_frac_below_20mm=float(cumulative_curve(pe, [20.0])[0]),
            posed_curve=cumulative_curve(pe, THRESHOLDS).tolist(),
            rounds=rounds, results=codes,
        ))  # fmt: skip
        partial = dict(mode=mode, seed=args.seed, partial=True, spaces=results,
                       thresholds_mm=THRESHOLDS.tolist(), fit_times_s=fit_times)  # fmt: skip
        bp.atomic_write_json(os.path.join(args.out, "metrics_partial.json"), partial)
    bar.close()

    # Figures: Fig. 5 grid, a depth image pair, a fitted body, Fig. 6 error maps.
    _plot_fig5(os.path.join(args.out, "fig5_depth_cumulative.png"), results, st)
    _plot_depth(os.path.join(args.out, "depth_images.png"), subjects[0], cams)
    n_all, k_fig = max(st.sizes), (20 if 20 in st.components else st.components[-1])
    ref = fits_kept.get(("none", n_all, k_fig, 0), next(iter(fits_kept.values())))
    _plot_fitted(os.path.join(args.out, "fitted_body.png"), ref, subjects[0], faces)
    fig6 = {}
    for s in range(min(2, len(subjects))):
        sex = "male" if subjects[s]["sex"] == 0 else "female"
        for norm in [*st.norms, *(["baseline"] if st.baseline else [])]:
            n = st.baseline if norm == "baseline" else n_all
            f = fits_kept.get((norm, n, k_fig, s))
            if f is None:
                continue
            e = _rest_error(f.rest_vertices, f.scale, subjects[s]["rest"])
            name = f"fig6_{sex}_{norm}.png"
            title = f"{sex}, {norm}: mean {e.mean():.1f} mm"
            path = os.path.join(args.out, name)
            bp.registration.error_colormap_png(
                path, subjects[s]["rest"], faces, e, vmax=30.0, title=title
            )
            fig6[name] = float(e.mean())

    metrics = dict(
        mode=mode, seed=args.seed, thresholds_mm=THRESHOLDS.tolist(),
        components=list(st.components), train_sizes=list(st.sizes),
        normalizations=list(st.norms), baseline_train=st.baseline, n_test=len(subjects),
        test_sexes=[s["sex"] for s in subjects], n_points=st.n_points,
        camera=dict(width=cams[0].width, height=cams[0].height, fx=cams[0].fx, fy=cams[0].fy,
                    distance_m=2.4, noise="sigma(z) = 1.5 mm * z^2",
                    max_incidence_deg=80.0),  # fmt: skip
        depth_points=[[int(np.asarray(c.point_mask).sum()) for c in s["scans"]] for s in subjects],
        valid_pixels=[[int((d > 0).sum()) for d in s["depth"]] for s in subjects],
        preset=args.preset, config=repr(st.config), spaces=results, skipped_for_time=skipped,
        fig6_mean_error_mm=fig6,
        timing_s=dict(capture=t_capture, learn=t_learn, learn_per_space=learn_times,
                      fit_first=fit_times[0], fit_median=float(np.median(fit_times)),
                      fits=len(fit_times), total=time.perf_counter() - t_start),  # fmt: skip
        error_definition="rest: fitted rest shape x scale, rigidly aligned to the true rest shape; "
        "posed: fitted posed meshes vs true posed bodies, hands excluded",
    )  # fmt: skip
    bp.atomic_write_json(os.path.join(args.out, "metrics.json"), metrics)
    if progress:
        for s in results:
            print(f"{s['norm']:>8} n={s['n_train']:<5} K={s['n_components']:<3} rest mean "
                  f"{s['rest_error_mm_mean']:6.2f} mm, <20 mm "
                  f"{100 * s['rest_frac_below_20mm']:5.1f} %; posed mean "
                  f"{s['posed_error_mm_mean']:6.2f} mm")  # fmt: skip
    return metrics


if __name__ == "__main__":
    main(sys.argv[1:])
