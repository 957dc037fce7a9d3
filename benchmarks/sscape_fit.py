"""Benchmark: S-SCAPE fitting of simulated laser scans (`bodyprior.sscape.fit_sscape[_batch]`).

An initial space is learned from `--n-train` population bodies (seed `--seed`); `--batch` other
bodies (seed `--seed + 1`) are scanned by the virtual scanner (`simulate_scans`, `--n-points`
points each, default 19,347 as humanshape) and fitted with the default `FitConfig`. In float64:

- single scan (`fit_sscape`): compile time (first call minus the median of the later calls) and
  the median time per scan over `--repeats`;
- batch on one device (`fit_sscape_batch(devices=[cpu0])`, vmap) and sharded over all host devices
  (`XLA_FLAGS=--xla_force_host_platform_device_count=N` is set to the core count unless given):
  compile time and scans per minute;
- the mean per-vertex error against the true template-topology body (all vertices and without hands)
  and the fitting statistics.

`--quick`: the same measurements with a 24-body, 8-component space, a batch of 2 scans of 6,449
points and one timed repeat (a minute or two, mostly compilation); the JSON says `"mode": "quick"`.

Usage: `python benchmarks/sscape_fit.py --json out/sscape_fit.json [--batch 4 --repeats 3]
[--quick]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

if "XLA_FLAGS" not in os.environ:
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={os.cpu_count() or 1}"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    ap.add_argument("--n-train", type=int, default=100)
    ap.add_argument("--components", type=int, default=20)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--n-points", type=int, default=19347)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="small space and batch (see docstring)")
    args = ap.parse_args(argv)
    if args.quick:
        args.n_train, args.components, args.batch, args.n_points, args.repeats = 24, 8, 2, 6449, 1

    import bodyprior as bp
    from bodyprior.registration import ScannerConfig, simulate_scans
    from bodyprior.sscape import FitConfig, fit_sscape, fit_sscape_batch

    cfg = FitConfig.preset("humanshape")  # the configuration the recorded figures used
    tmpl = bp.registration.registration_template()
    body = bp.load_default_body("cmu_mb", local_changes=True)
    pop0 = bp.sample_population(args.n_train, body=body, progress=False, key=jr.PRNGKey(args.seed))
    model = bp.sscape.learn(
        tmpl.restrict(pop0.vertices), tmpl.faces, n_components=args.components, rig=tmpl.rig
    )
    pop1 = bp.sample_population(
        args.batch, body=body, progress=False, key=jr.PRNGKey(args.seed + 1)
    )
    scans, _ = simulate_scans(
        pop1.vertices,
        body.faces,
        body.landmark_index,
        body.landmark_names,
        ScannerConfig(n_points=args.n_points),
        progress=False,
        key=jr.PRNGKey(args.seed + 2),
    )
    truth = np.asarray(tmpl.restrict(pop1.vertices))
    hand = np.asarray(tmpl.hand_mask)
    one = jax.tree_util.tree_map(lambda x: x[0], scans)

    # single scan
    times = []
    for _ in range(args.repeats + 1):
        t = time.perf_counter()
        fit = fit_sscape(model, one, tmpl, config=cfg)
        jax.block_until_ready(fit.value.vertices)
        times.append(time.perf_counter() - t)
    single_s = float(np.median(times[1:]))
    out = {
        "mode": "quick" if args.quick else "full",
        "n_points": args.n_points,
        "n_train": args.n_train,
        "components": args.components,
        "batch": args.batch,
        "config": {k: getattr(cfg, k) for k in ("schedule", "max_passes", "point_to_plane")},
        "single_s": single_s,
        "single_compile_s": float(times[0] - single_s),
        "single_scans_per_min": 60.0 / single_s,
        "single_passes": int(fit.stats["passes"]),
        "single_solver_steps": int(fit.stats["num_steps"]),
    }

    def batched(devices, key):
        ts = []
        for _ in range(2):
            t = time.perf_counter()
            fits = fit_sscape_batch(
                model,
                scans,
                tmpl,
                config=cfg,
                devices=devices,
                chunk_size=args.batch,
                progress=False,
                throw=False,
            )
            ts.append(time.perf_counter() - t)
        out[f"{key}_s_per_batch"] = ts[1]
        out[f"{key}_compile_s"] = ts[0] - ts[1]
        out[f"{key}_scans_per_min"] = 60.0 * args.batch / ts[1]
        return fits

    fits = batched([jax.devices()[0]], "batch_1dev")
    if len(jax.devices()) > 1:
        fits_sh = batched(jax.devices(), f"batch_{len(jax.devices())}dev")
        diff = np.abs(fits_sh.value.vertices - fits.value.vertices)
        out["sharded_max_diff_m"] = float(diff.max())

    err = 1000 * np.linalg.norm(np.asarray(fits.value.vertices) - truth, axis=-1)
    out.update(
        gt_error_mm_mean=float(err.mean()),
        gt_error_mm_mean_no_hands=float(err[:, ~hand].mean()),
        gt_error_mm_median=float(np.median(err)),
        gt_error_mm_per_scan=err[:, ~hand].mean(1).tolist(),
        mean_distance_mm=np.asarray(fits.stats["final_mean_distance_mm"]).tolist(),
        passes=np.asarray(fits.stats["passes"]).tolist(),
        results=np.asarray(fits.result._value).tolist(),
        devices=len(jax.devices()),
        cpu_count=os.cpu_count(),
        machine=platform.processor() or platform.machine(),
        jax=jax.__version__,
        load_average=os.getloadavg(),
    )
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    bp.atomic_write_json(args.json, out)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
