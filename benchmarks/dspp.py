"""Benchmark: DSPP sampling and training speed (issue 4 §5).

- `sample_pair_ms_b1`: one jitted call that samples one shape (`z -> generator -> decoder`, 6,449
  decimated vertices) and one pose (20 x 3 Euler angles) from the AE-GAN priors;
  `sample_pair_ms_b256`: the same for 256 pairs in one vmapped call, per pair.
- `train_step_ms_b1`: one jitted training cycle (AE step, discriminator step, generator step) of the
  shape AND the pose system together, batch 1 (the paper's one pair per cycle), one call per cycle;
  `train_step_ms_b64`: batch 64. `*_scan` keys: the same per cycle inside a 20-cycle `lax.scan`
  (how `train_*_prior` runs it: no per-cycle dispatch).
- `compile_s_*`: first-call time (trace + compile) of each function.

The networks are freshly initialised with the default `DSPPConfig` (speed does not depend on the
weights); float32; all CPU threads. The paper's figures (PyTorch 1.1, GTX 1080): 70 ms per training
step, 5 ms per sampled pair. No public implementation of the paper exists to run side by side.

`--quick`: the same measurements with 3 repeats, sampling batch 16 instead of 256, training batches
1 and 8 instead of 1 and 64, and a 5-cycle scan (keys named after those sizes; compilation
dominates); the JSON says `"mode": "quick"`.

Usage: `python benchmarks/dspp.py --json out/dspp.json [--repeats 30] [--quick]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import bodyprior as bp
from bodyprior import internal
from bodyprior.dspp import DSPPConfig, init_aegan


def _median_ms(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def _first_s(fn) -> float:
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True, help="output JSON path")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="small batches, 3 repeats (see docstring)")
    args = ap.parse_args(argv)
    n_sample, train_batches, n_scan = 256, (1, 64), 20
    if args.quick:
        args.repeats, n_sample, train_batches, n_scan = 3, 16, (1, 8), 5

    body = bp.load_default_body("cmu_mb")
    vmap_idx, _ = bp.load_decimated()
    mean_shape = np.asarray(body.template)[vmap_idx]
    cfg = DSPPConfig()
    shape = init_aegan("shape", mean_shape, 0.05, cfg, key=jr.PRNGKey(0))
    pose = init_aegan("pose", np.zeros((20, 3)), 0.3, cfg, key=jr.PRNGKey(1))
    out: dict = {
        "mode": "quick" if args.quick else "full",
        "config": cfg.to_dict(),
        "n_vertices": int(mean_shape.shape[0]),
    }

    # --- sampling -------------------------------------------------------------------------------
    @eqx.filter_jit
    def pair1(sp, pp, key):
        k1, k2 = jr.split(key)
        return sp.sample(k1), pp.sample(k2)

    @eqx.filter_jit
    def pair_b(sp, pp, keys):
        return jax.vmap(lambda k: pair1.__wrapped__(sp, pp, k))(keys)

    key = jr.PRNGKey(2)
    keys = jr.split(key, n_sample)
    out["compile_s_sample_b1"] = _first_s(lambda: pair1(shape, pose, key))
    out["sample_pair_ms_b1"] = _median_ms(lambda: pair1(shape, pose, key), args.repeats)
    out[f"compile_s_sample_b{n_sample}"] = _first_s(lambda: pair_b(shape, pose, keys))
    out[f"sample_pair_ms_b{n_sample}"] = (
        _median_ms(lambda: pair_b(shape, pose, keys), args.repeats) / n_sample
    )

    # --- training -------------------------------------------------------------------------------
    rng = np.random.default_rng(0)
    n_data = 256
    u_shape = jnp.asarray(rng.normal(size=(n_data, mean_shape.size)), jnp.float32)
    u_pose = jnp.asarray(rng.normal(size=(n_data, 60)), jnp.float32)

    # The state is donated: the step updates ~5 M float32 parameters and their Adam moments in
    # place instead of allocating fresh 10 MB buffers every call (as inside `lax.scan`).
    @eqx.filter_jit(donate="all-except-first")
    def step(data, ts_s, ts_p, cfg):
        us, up = data
        ts_s, rs = internal.dspp_aegan_cycle(ts_s, us, cfg)
        ts_p, rp = internal.dspp_aegan_cycle(ts_p, up, cfg)
        return ts_s, ts_p, rs, rp

    @eqx.filter_jit
    def scan20(ts_s, ts_p, us, up, cfg):
        def body_fn(c, _):
            a, b = c
            a, ra = internal.dspp_aegan_cycle(a, us, cfg)
            b, rb = internal.dspp_aegan_cycle(b, up, cfg)
            return (a, b), (ra, rb)

        return jax.lax.scan(body_fn, (ts_s, ts_p), None, length=n_scan)

    for b in train_batches:
        c = DSPPConfig(batch_size=b)
        ts_s = internal.dspp_init_state("shape", "aegan", mean_shape, 0.05, c, jr.PRNGKey(3))
        ts_p = internal.dspp_init_state("pose", "aegan", np.zeros((20, 3)), 0.3, c, jr.PRNGKey(4))
        state = [ts_s, ts_p]

        def one():
            s, p, rs, rp = step((u_shape, u_pose), state[0], state[1], c)
            state[0], state[1] = s, p
            return rs, rp

        out[f"compile_s_train_b{b}"] = _first_s(one)
        out[f"train_step_ms_b{b}"] = _median_ms(one, args.repeats)
        st = [state[0], state[1]]

        def twenty():
            (s, p), r = scan20(st[0], st[1], u_shape, u_pose, c)
            st[0], st[1] = s, p
            return r

        out[f"compile_s_train_scan_b{b}"] = _first_s(twenty)
        out[f"train_step_ms_b{b}_scan"] = _median_ms(twenty, max(3, args.repeats // 5)) / n_scan

    out["goals"] = {"sample_pair_ms_b1": 1.0, "train_step_ms_b1": 20.0}
    out["paper"] = {
        "train_step_ms": 70.0,
        "sample_pair_ms": 5.0,
        "hardware": "GTX 1080, PyTorch 1.1",
    }
    out["machine"] = {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "load_average": os.getloadavg(),
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    bp.atomic_write_json(args.json, out)
    print(json.dumps({k: v for k, v in out.items() if k not in ("config", "machine")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
