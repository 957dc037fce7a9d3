"""Benchmark: start-up of `bodyprior register` in a new process, with and without JAX's persistent
compilation cache (the CLI's default).

One body of the population (seed `--seed`) is scanned by the virtual scanner and written as PLY +
CAESAR `.lnd`; then `bodyprior register` runs in fresh subprocesses:

- `no_cache`: `--no-cache` (every program compiled in the process; the pre-cache behaviour);
- `cold`: with an empty cache directory (compiles and writes the cache);
- `warm`: with that cache filled (the second process on a machine), `--repeats` times.

The cache directory holds JAX's compiled programs and, under `exported/`, the whole-algorithm
programs exported with `jax.export` (the fit, NRD, fitting error), which a warm process loads
without tracing them (`bodyprior/_aot.py`).

Reported per run: the process wall time, and from the job's own report the time to read the scan
and to fit + refine it. `time_to_first_fit_s` is the wall time minus the writing of the outputs
after the fit (the registered mesh, JSON, error map), i.e. from process start to the refined fit.
The peer is the same CLI without the cache, in the same run.

`--quick`: a 4,000-point scan and one warm repeat.

Usage: `python benchmarks/cli_start.py --json out/cli_start.json [--repeats 3] [--quick]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np


def _run(scan: str, out: str, cache: str | None, env: dict) -> dict:
    cmd = [sys.executable, "-m", "bodyprior.cli"]
    if cache is None:
        cmd.append("--no-cache")
    cmd += ["register", scan, "--out", out, "--no-progress"]
    e = dict(env)
    if cache is not None:
        e["BODYPRIOR_CACHE"] = cache
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=e, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    rep = json.load(open(os.path.join(out, "report.json")))
    s = rep["seconds"]
    after_fit = s["total"] - s["read"] - s["fit_and_refine"]
    return dict(
        wall_s=round(wall, 2),
        read_s=s["read"],
        fit_and_refine_s=s["fit_and_refine"],
        time_to_first_fit_s=round(wall - after_fit, 2),
        fitting_error_mm=rep["scans"][0]["fitting_error"]["mean_mm"],
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--n-points", type=int, default=19347)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.n_points = 1, 4000

    import bodyprior as bp
    from bodyprior import registration

    work = tempfile.mkdtemp(prefix="bodyprior-cli-start-")
    body = bp.load_default_body("cmu_mb", local_changes=True)
    pop = bp.sample_population(1, body=body, key=jax.random.PRNGKey(args.seed), progress=False)
    scans, _ = registration.simulate_scans(
        np.asarray(pop.vertices), body.faces, body.landmark_index, body.landmark_names,
        registration.ScannerConfig(n_points=args.n_points), key=jax.random.PRNGKey(args.seed + 1),
        progress=False,
    )  # fmt: skip
    scan = os.path.join(work, "scan.ply")
    registration.write_scan(scan, jax.tree_util.tree_map(lambda a: a[0], scans),
                            landmarks_path=os.path.join(work, "scan.lnd"))  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "BODYPRIOR_CACHE"}
    env.setdefault("JAX_PLATFORMS", "cpu")
    cache = os.path.join(work, "cache")
    res = {
        "mode": "quick" if args.quick else "full",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "jax_version": jax.__version__,
        "scan_points": args.n_points,
        "no_cache": _run(scan, os.path.join(work, "o0"), None, env),
        "cold": _run(scan, os.path.join(work, "o1"), cache, env),
    }
    warm = [_run(scan, os.path.join(work, f"w{i}"), cache, env) for i in range(args.repeats)]
    res["warm_runs"] = warm
    res["warm"] = {k: float(np.median([w[k] for w in warm])) for k in warm[0]}
    sizes = {
        os.path.relpath(os.path.join(d, f), cache): os.path.getsize(os.path.join(d, f))
        for d, _, files in os.walk(cache) for f in files
    }  # fmt: skip
    res["cache_mb"] = round(sum(sizes.values()) / 2**20, 2)
    res["exported_mb"] = round(
        sum(v for k, v in sizes.items() if k.startswith("exported" + os.sep)) / 2**20, 2
    )
    res["speedup_first_fit_warm_vs_no_cache"] = round(
        res["no_cache"]["time_to_first_fit_s"] / res["warm"]["time_to_first_fit_s"], 2
    )
    with open(args.json, "w") as f:
        json.dump(res, f, indent=1)
    print(
        json.dumps(
            {k: res[k] for k in ("no_cache", "cold", "warm", "cache_mb", "exported_mb")}, indent=1
        )
    )


if __name__ == "__main__":
    main()
