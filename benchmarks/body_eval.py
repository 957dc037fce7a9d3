"""Benchmark: shape + pose + LBS evaluation of the full-resolution default body, bodyprior vs anny.

Both sides do the same work in the same run: phenotypes -> rest mesh (13,380 body vertices) -> forward
kinematics on the 31-bone `cmu_mb` rig -> linear blend skinning, float32, on all CPU threads (XLA's pool and
`torch.set_num_threads(os.cpu_count())`). anny is built with `rig="cmu_mb"`, topology `anny-noeyes-notongue`
(its body-only mesh), dense `lbs` skinning, `local-ref` pose parameterisation, default (compact) phenotype
blendshapes, under `torch.inference_mode()`. Times are medians over repeats; bodyprior's compile time is
reported separately (`compile_s`).

Usage: `python benchmarks/body_eval.py --json out/body_eval.json [--repeats 30]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def _median_ms(fn, repeats: int, block) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        block(fn())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def bench_bodyprior(batches, repeats, seed=0):
    import equinox as eqx

    import bodyprior as bp

    body = bp.load_default_body("cmu_mb")
    J = body.n_joints
    out = {}

    @eqx.filter_jit
    def run(phen, pose):
        return jax.vmap(lambda p, q: bp.evaluate(body, p, q)[0])(phen, pose)

    rng = np.random.default_rng(seed)
    for B in batches:
        phen = jnp.asarray(rng.uniform(0, 1, (B, 11)), jnp.float32)
        pose = jnp.asarray(rng.normal(0, 0.3, (B, J, 3)), jnp.float32)
        t = time.perf_counter()
        run(phen, pose).block_until_ready()
        first = time.perf_counter() - t
        ms = _median_ms(lambda: run(phen, pose), repeats, lambda x: x.block_until_ready())
        out[B] = dict(ms=ms, compile_s=first - ms / 1e3)
    return out


def bench_anny(batches, repeats, seed=0):
    import anny
    import roma
    import torch

    torch.set_num_threads(os.cpu_count())
    model = anny.Anny(rig="cmu_mb", topology="anny-noeyes-notongue", skinning_method="lbs")
    J = len(model.bone_labels)
    rng = np.random.default_rng(seed)
    out = {}
    labels = model.phenotype_labels
    for B in batches:
        phen = {k: torch.as_tensor(rng.uniform(0, 1, B), dtype=torch.float32) for k in labels}
        aa = torch.as_tensor(rng.normal(0, 0.3, (B, J, 3)), dtype=torch.float32)
        pose = torch.eye(4).repeat(B, J, 1, 1)
        pose[..., :3, :3] = roma.rotvec_to_rotmat(aa)
        with torch.inference_mode():
            model(pose_parameters=pose, phenotype_kwargs=phen)
            ms = _median_ms(lambda: model(pose_parameters=pose, phenotype_kwargs=phen)["vertices"], repeats, lambda x: x)
        out[B] = dict(ms=ms, vertices=int(model.template_vertices.shape[0]), bones=J)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True, help="where to write the results")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 128])
    args = ap.parse_args(argv)
    b1, bN = args.batches[0], args.batches[-1]
    res = dict(
        machine=dict(cpus=os.cpu_count(), platform=platform.platform(), python=sys.version.split()[0],
                     jax=jax.__version__, device=str(jax.devices()[0])),
        repeats=args.repeats,
        vertices=13380,
        rig="cmu_mb (31 bones)",
        dtype="float32",
    )
    bp_res = bench_bodyprior(args.batches, args.repeats)
    res["bodyprior_ms_b1"] = bp_res[b1]["ms"]
    res[f"bodyprior_ms_per_body_b{bN}"] = bp_res[bN]["ms"] / bN
    res["compile_s"] = bp_res[b1]["compile_s"]
    res[f"compile_s_b{bN}"] = bp_res[bN]["compile_s"]
    try:
        an = bench_anny(args.batches, args.repeats)
    except ImportError as e:
        print(f"anny not installed ({e}); install the `compare` extra for the side-by-side numbers")
        an = None
    if an is not None:
        import anny  # noqa: F401
        import torch

        res["anny_version"] = "0.6.2"
        res["torch_version"] = torch.__version__
        res["anny_vertices"] = an[b1]["vertices"]
        res["anny_ms_b1"] = an[b1]["ms"]
        res[f"anny_ms_per_body_b{bN}"] = an[bN]["ms"] / bN
        res["speedup_b1"] = res["anny_ms_b1"] / res["bodyprior_ms_b1"]
        res[f"speedup_b{bN}"] = res[f"anny_ms_per_body_b{bN}"] / res[f"bodyprior_ms_per_body_b{bN}"]
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(res, f, indent=2, sort_keys=True)
    print(json.dumps(res, indent=2, sort_keys=True))


if __name__ == "__main__":
    main()
