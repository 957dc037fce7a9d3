"""Benchmark: `fit_sscape` with the grid template -> scan search against the brute force, same run.

A 24-body, 20-component space (seed 0), 4 scans of other bodies (6,449 points), `max_passes=3` and
the registration experiment's priors. The brute force (`_fit._compatible_search_jit`, the search
the fit used before, still used by the depth fit) is swapped in for the second half. Per-scan
medians of 3 scans after one compile call; GT error per scan in mm.

Usage: `python benchmarks/fit_search.py --json out/fit_search.json`.
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
    registration,  # noqa: E402
    sscape,  # noqa: E402
)
from bodyprior.sscape import _fit  # noqa: E402


def brute_force(verts, normals, scan_points, scan_normals, scan_mask, exclude, cfg):
    """The fit's former correspondences: float32 brute force over all points, then the gate."""
    cos_min = float(np.cos(np.deg2rad(cfg.max_angle_deg)))
    idx, found = _fit._compatible_search_jit(
        verts, normals, scan_points, scan_normals, scan_mask, cos_min, cfg.chunk_size
    )
    diff = verts - scan_points[idx]
    dist = jnp.sqrt(jnp.where(found, jnp.sum(diff * diff, -1), 0.0))
    valid = found & (dist <= cfg.max_dist) & ~exclude
    return idx, valid.astype(verts.dtype), jax.lax.stop_gradient(dist)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    tmpl = registration.registration_template()
    body = bp.load_default_body("cmu_mb", local_changes=True)
    pop = bp.sample_population(28, body=body, progress=False, key=jax.random.PRNGKey(0))
    gt = np.asarray(tmpl.restrict(pop.vertices), np.float64)
    model = sscape.learn(jnp.asarray(gt[:24]), tmpl.faces, n_components=20, **tmpl.rig_kwargs())
    scans, _ = registration.simulate_scans(
        np.asarray(pop.vertices[24:28]), body.faces, body.landmark_index,
        body.landmark_names, registration.ScannerConfig(n_points=6449), progress=False,
        key=jax.random.PRNGKey(5),
    )  # fmt: skip
    cfg = _fit.FitConfig(max_passes=3, landmark_weight=0.3, pose_prior=100.0)
    take = lambda i: jax.tree_util.tree_map(lambda a: a[i], scans)  # noqa: E731
    res = {}
    for name, fn in (("grid", _fit._correspondences), ("brute_force", brute_force)):
        _fit._correspondences = fn
        jax.clear_caches()
        t = time.perf_counter()
        jax.block_until_ready(sscape.fit_sscape(model, take(0), tmpl, config=cfg))
        first = time.perf_counter() - t
        ts, errs = [], []
        for i in range(1, 4):
            t = time.perf_counter()
            r = jax.block_until_ready(sscape.fit_sscape(model, take(i), tmpl, config=cfg))
            ts.append(time.perf_counter() - t)
            e = np.linalg.norm(np.asarray(r.value.vertices) - gt[24 + i], axis=1)
            errs.append(float(1000 * e.mean()))
        res[name] = dict(first_s=first, per_scan_s=ts, median_s=float(np.median(ts)),
                         gt_error_mm=errs)  # fmt: skip
        print(name, res[name], flush=True)
    res["speedup"] = res["brute_force"]["median_s"] / res["grid"]["median_s"]
    bp.atomic_write_json(args.json, res)


if __name__ == "__main__":
    main()
