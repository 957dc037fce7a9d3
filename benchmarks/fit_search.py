"""Benchmark: `fit_sscape` with the grid template -> scan search against the brute force, same run.

A 24-body, 20-component space (seed 0), 4 scans of other bodies (6,449 points), `max_passes=3` and
the registration experiment's priors. The brute force (`bodyprior.internal.
sscape_compatible_search_brute_force`, the float32 search the fit used before, in blocks of 512
queries, the former `FitConfig.chunk_size` default) then the gate is swapped in for the second half
(`bodyprior.internal.swap_sscape_fit_correspondences`). Per-scan medians of 3 scans after one
compile call; GT error per scan in mm.

`--quick`: the same comparison on a 12-body, 8-component space with 1 compile scan and 2 timed
scans (seconds to a minute or two of compilation); the JSON says `"mode": "quick"`.

Usage: `python benchmarks/fit_search.py --json out/fit_search.json [--quick]`.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior import (
    internal,  # noqa: E402
    registration,  # noqa: E402
    sscape,  # noqa: E402
)

BRUTE_FORCE_CHUNK = 512  # queries per block of the brute force (the former FitConfig.chunk_size)


def brute_force(verts, normals, scan_points, scan_normals, scan_mask, exclude, cfg):
    """The fit's former correspondences: float32 brute force over all points, then the gate."""
    cos_min = float(np.cos(np.deg2rad(cfg.max_angle_deg)))
    idx, found = internal.sscape_compatible_search_brute_force(
        verts, normals, scan_points, scan_normals, scan_mask, cos_min, BRUTE_FORCE_CHUNK
    )
    diff = verts - scan_points[idx]
    dist = jnp.sqrt(jnp.where(found, jnp.sum(diff * diff, -1), 0.0))
    valid = found & (dist <= cfg.max_dist) & ~exclude
    return idx, valid.astype(verts.dtype), jax.lax.stop_gradient(dist)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    ap.add_argument("--quick", action="store_true", help="small space, 2 timed scans (seconds)")
    args = ap.parse_args(argv)
    n_train, n_comp, n_scans = (12, 8, 3) if args.quick else (24, 20, 4)
    tmpl = registration.registration_template()
    body = bp.load_default_body("cmu_mb", local_changes=True)
    pop = bp.sample_population(
        n_train + n_scans, body=body, progress=False, key=jax.random.PRNGKey(0)
    )
    gt = np.asarray(tmpl.restrict(pop.vertices), np.float64)
    model = sscape.learn(
        jnp.asarray(gt[:n_train]), tmpl.faces, n_components=n_comp, rig=tmpl.rig
    )
    scans, _ = registration.simulate_scans(
        np.asarray(pop.vertices[n_train:]), body.faces, body.landmark_index,
        body.landmark_names, registration.ScannerConfig(n_points=6449), progress=False,
        key=jax.random.PRNGKey(5),
    )  # fmt: skip
    cfg = sscape.FitConfig(max_passes=3, landmark_weight=0.3, pose_prior=100.0)
    take = lambda i: jax.tree_util.tree_map(lambda a: a[i], scans)  # noqa: E731
    res = {"mode": "quick" if args.quick else "full", "n_train": n_train, "components": n_comp,
           "timed_scans": n_scans - 1}  # fmt: skip
    for name, fn in (("grid", internal.sscape_fit_correspondences), ("brute_force", brute_force)):
        with internal.swap_sscape_fit_correspondences(fn):
            t = time.perf_counter()
            jax.block_until_ready(sscape.fit_sscape(model, take(0), tmpl, config=cfg))
            first = time.perf_counter() - t
            ts, errs = [], []
            for i in range(1, n_scans):
                t = time.perf_counter()
                r = jax.block_until_ready(sscape.fit_sscape(model, take(i), tmpl, config=cfg))
                ts.append(time.perf_counter() - t)
                e = np.linalg.norm(np.asarray(r.value.vertices) - gt[n_train + i], axis=1)
                errs.append(float(1000 * e.mean()))
        res[name] = dict(first_s=first, per_scan_s=ts, median_s=float(np.median(ts)),
                         gt_error_mm=errs)  # fmt: skip
        print(name, res[name], flush=True)
    res["speedup"] = res["brute_force"]["median_s"] / res["grid"]["median_s"]
    bp.atomic_write_json(args.json, res)


if __name__ == "__main__":
    main()
