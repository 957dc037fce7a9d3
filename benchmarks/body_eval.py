"""Benchmark: shape + pose + LBS evaluation of the full-resolution default body, bodyprior vs anny.

Both sides do the same work in the same run: phenotypes -> rest mesh (13,380 body vertices) ->
forward
kinematics on the 31-bone `cmu_mb` rig -> linear blend skinning, float32, on all CPU threads (XLA's
pool and
`torch.set_num_threads(os.cpu_count())`). anny is built with `rig="cmu_mb"`, topology
`anny-noeyes-notongue`
(its body-only mesh), dense `lbs` skinning, `local-ref` pose parameterisation, default (compact)
phenotype
blendshapes, under `torch.inference_mode()`. Times are medians over repeats; bodyprior's compile
time is
reported separately (`compile_s`).

`--quick`: the same comparison with 5 repeats and batches 1 and 16 (seconds); the JSON says
`"mode": "quick"`. Without anny/torch installed the peer side is skipped and the JSON says why
(`anny_skipped`).

Usage: `python benchmarks/body_eval.py --json out/body_eval.json [--repeats 30] [--quick]`.
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


# The six phenotypes anny exposes by default; the others stay at 0.5 on both sides.
ANNY_PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")


def make_inputs(B: int, seed: int = 0):
    rng = np.random.default_rng(seed + B)
    phen6 = rng.uniform(0, 1, (B, 6)).astype(np.float32)
    aa = rng.normal(0, 0.3, (B, 31, 3)).astype(np.float32)
    return phen6, aa


def bench_bodyprior(batches, repeats):
    import bodyprior as bp

    body = bp.load_default_body("cmu_mb")
    out = {}

    # The body is passed as an argument (a PyTree of arrays), as user code would, not baked in as
    # constants.
    @jax.jit
    def run_b(body, phen, pose):
        return jax.vmap(lambda p, q: bp.evaluate(body, p, q)[0])(phen, pose)

    @jax.jit
    def run_1(body, phen, pose):  # batch 1 = one body, no vmap
        return bp.evaluate(body, phen, pose)[0]

    def run(phen, pose):
        return run_b(body, phen, pose)

    def run1(phen, pose):
        return run_1(body, phen, pose)

    for B in batches:
        phen6, aa = make_inputs(B)
        phen = np.full((B, 11), 0.5, np.float32)
        phen[:, :6] = phen6  # bodyprior.PHENOTYPES starts with the same six, in the same order
        phen, pose = jnp.asarray(phen), jnp.asarray(aa)
        if B == 1:
            phen, pose = phen[0], pose[0]
        f = run1 if B == 1 else run
        t = time.perf_counter()
        verts = f(phen, pose).block_until_ready()
        first = time.perf_counter() - t
        ms = _median_ms(lambda: f(phen, pose), repeats, lambda x: x.block_until_ready())
        verts = verts.reshape(B, -1, 3)
        out[B] = dict(ms=ms, compile_s=first - ms / 1e3, vertices=np.asarray(verts))
    return out


def bench_anny(batches, repeats):
    import anny
    import roma
    import torch

    torch.set_num_threads(os.cpu_count())
    model = anny.Anny(rig="cmu_mb", topology="anny-noeyes-notongue", skinning_method="lbs")
    assert tuple(model.phenotype_labels) == ANNY_PHENOTYPES
    J = len(model.bone_labels)
    out = {}
    for B in batches:
        phen6, aa = make_inputs(B)
        phen = {k: torch.as_tensor(phen6[:, i]) for i, k in enumerate(ANNY_PHENOTYPES)}
        pose = torch.eye(4).repeat(B, J, 1, 1)
        pose[..., :3, :3] = roma.rotvec_to_rotmat(torch.as_tensor(aa))
        with torch.inference_mode():
            rest = model(pose_parameters=None, phenotype_kwargs=phen)["rest_bone_poses"]
            rest_root = rest[:, 0, :3, 3]
            pose[:, 0, :3, 3] = rest_root  # anny puts the root head at the delta translation
            verts = model(pose_parameters=pose, phenotype_kwargs=phen)["vertices"]
            ms = _median_ms(
                lambda: model(pose_parameters=pose, phenotype_kwargs=phen)["vertices"],
                repeats,
                lambda x: x,
            )
        out[B] = dict(
            ms=ms, vertices=verts.numpy(), map=model.base_mesh_vertex_indices.numpy(), bones=J
        )
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True, help="where to write the results")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 128])
    ap.add_argument("--quick", action="store_true", help="5 repeats, batches 1 and 16 (seconds)")
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.batches = 5, [1, 16]
    b1, bN = args.batches[0], args.batches[-1]
    res = dict(
        mode="quick" if args.quick else "full",
        machine=dict(
            cpus=os.cpu_count(),
            platform=platform.platform(),
            python=sys.version.split()[0],
            jax=jax.__version__,
            device=str(jax.devices()[0]),
        ),
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
        res["anny_skipped"] = f"anny/torch not installed ({e}); no side-by-side numbers"
        an = None
    if an is not None:
        import anny  # noqa: F401
        import torch

        res["anny_version"] = "0.6.2"
        res["torch_version"] = torch.__version__
        res["anny_vertices"] = int(an[b1]["map"].shape[0])
        res["anny_ms_b1"] = an[b1]["ms"]
        res[f"anny_ms_per_body_b{bN}"] = an[bN]["ms"] / bN
        res["speedup_b1"] = res["anny_ms_b1"] / res["bodyprior_ms_b1"]
        # Agreement on the same inputs (float32 on both sides), on the 13,348 vertices anny keeps.
        err = np.abs(bp_res[bN]["vertices"][:, an[bN]["map"]] - an[bN]["vertices"]).max()
        res[f"max_posed_vertex_difference_m_b{bN}"] = float(err)
        res[f"speedup_b{bN}"] = res[f"anny_ms_per_body_b{bN}"] / res[f"bodyprior_ms_per_body_b{bN}"]
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(res, f, indent=2, sort_keys=True)
    print(json.dumps(res, indent=2, sort_keys=True))


if __name__ == "__main__":
    main()
