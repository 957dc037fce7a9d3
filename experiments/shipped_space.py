"""The shipped S-SCAPE space (`bodyprior.sscape.default_space`) on held-out simulated scans: what
`bodyprior register` delivers with its presets, against the ground truth.

Bodies: `--n-scans` adults of the population (CAESAR scheme, posture jitter, local changes) drawn
with key `fold_in(PRNGKey(seed), 7)` (the shipped space was learned from `PRNGKey(2026)`, so these
are other bodies), scanned by the virtual laser scanner (19,347 points, noise, holes, outliers).
Each scan is registered exactly as `bodyprior register` does (`register_sscape_nrd` with the CLI
preset's `FitConfig` / `NRDConfig`) with `K` components of the shipped space, for every `K` of
`--components` and every preset of `--presets`. Reported per run: the paper's fitting error
(mean over valid vertices) and the true-correspondence (GT) error of the S-SCAPE fit and of the
refined registration, mm; and the space's own reconstruction error of the bodies' true rest
shapes (its generalization to these bodies) per `K`.

Writes `metrics.json` and `gt_error.png` (GT error per preset and K) to `--out`.
`--quick`: 3 scans, K in (10, 20), the default preset.

Usage: `python experiments/shipped_space.py --out out/shipped [--n-scans 20] [--quick]`.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np

import bodyprior as bp
from bodyprior import registration, sscape

PRESETS = {  # as bodyprior register's --preset (bodyprior/_cli_jobs.py REGISTER_PRESETS)
    "default": ("default", "anchored"),
    "paper": ("humanshape", "paper"),
}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-scans", type=int, default=20)
    ap.add_argument("--components", type=int, nargs="+", default=[10, 20, 50])
    ap.add_argument("--presets", nargs="+", choices=tuple(PRESETS), default=list(PRESETS))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.n_scans, args.components, args.presets = 3, [10, 20], ["default"]
    os.makedirs(args.out, exist_ok=True)
    progress = not args.no_progress
    t_start = time.perf_counter()
    key = jax.random.fold_in(jax.random.PRNGKey(args.seed), 7)
    body = bp.load_default_body("cmu_mb", local_changes=True)
    tmpl = registration.registration_template()
    pop = bp.sample_population(args.n_scans, body=body, key=key, progress=progress)
    full = np.asarray(pop.vertices, np.float64)
    gt = np.asarray(tmpl.restrict(full))
    rest = jax.vmap(lambda p, c: bp.rest_shape(body, p, c)[0])(pop.phenotypes, pop.local_changes)
    rest = jnp.asarray(tmpl.restrict(np.asarray(rest, np.float64)))
    scans, _ = registration.simulate_scans(
        full, body.faces, body.landmark_index, body.landmark_names, registration.ScannerConfig(),
        key=jax.random.fold_in(key, 1), progress=progress,
    )  # fmt: skip
    space_info = sscape.default_space(50, return_info=True)[1]
    runs = {}
    recon = {}
    for k in args.components:
        model = sscape.default_space(k)
        # The space's own reach: the bodies' true rest shapes projected on it.
        recon[str(k)] = float(np.mean(sscape.reconstruction_error(model, rest, (k,))))
        for preset in args.presets:
            fit_name, nrd_name = PRESETS[preset]
            t0 = time.perf_counter()
            reg = sscape.register_sscape_nrd(
                model, scans, tmpl, fit_config=sscape.FitConfig.preset(fit_name),
                nrd_config=registration.NRDConfig.preset(nrd_name), progress=progress,
            )  # fmt: skip
            secs = time.perf_counter() - t0
            row = {"seconds": round(secs, 1), "successful": int(np.sum(reg.successful))}
            for stage, verts in (("sscape", reg.fit_vertices), ("refined", reg.vertices)):
                fe = registration.fitting_error_batch(jnp.asarray(verts), scans, faces=tmpl.faces)
                e, v = np.asarray(fe.error_mm), np.asarray(fe.valid)
                g = np.asarray(registration.gt_error(jnp.asarray(verts), jnp.asarray(gt)))
                row[f"{stage}_fit_error_mm"] = float(e[v].mean())
                row[f"{stage}_gt_error_mm"] = float(g.mean())
                row[f"{stage}_gt_error_mm_per_scan"] = [float(x) for x in g.mean(axis=1)]
            runs[f"{preset}_k{k}"] = row
            print(f"{preset} K={k}: GT {row['sscape_gt_error_mm']:.2f} -> "
                  f"{row['refined_gt_error_mm']:.2f} mm, fitting error "
                  f"{row['refined_fit_error_mm']:.2f} mm ({secs:.0f} s)")  # fmt: skip
    metrics = {
        "mode": "quick" if args.quick else "full",
        "seed": args.seed,
        "n_scans": args.n_scans,
        "components": args.components,
        "presets": args.presets,
        "space": {k: space_info[k] for k in ("population", "n_components")},
        "space_reconstruction_mm": recon,
        "runs": runs,
        "seconds": round(time.perf_counter() - t_start, 1),
    }
    _plot(os.path.join(args.out, "gt_error.png"), metrics)
    bp.atomic_write_json(os.path.join(args.out, "metrics.json"), metrics)
    return metrics


def _plot(path, m):
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 3.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ks = m["components"]
    for preset in m["presets"]:
        for stage, style in (("sscape", "--"), ("refined", "-")):
            ys = [m["runs"][f"{preset}_k{k}"][f"{stage}_gt_error_mm"] for k in ks]
            ax.plot(ks, ys, style, marker="o", label=f"{preset}: {stage}")
    ax.plot(ks, [m["space_reconstruction_mm"][str(k)] for k in ks], ":", color="k",
            label="space reconstruction of the truth")  # fmt: skip
    ax.set_xlabel("components K")
    ax.set_ylabel("mean GT error [mm]")
    ax.set_title(f"shipped space, {m['n_scans']} held-out simulated scans", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    bp.atomic_write_bytes(path, buf.getvalue())


if __name__ == "__main__":
    main()
