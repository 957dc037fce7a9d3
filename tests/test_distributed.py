"""Scale-out on JAX's own multi-process runtime: 2 local CPU processes joined by
`jax.distributed.initialize` on 127.0.0.1 run the batched NRD (`batch_map`'s `"per_process"`
strategy: every process fits its share of the batch, one `process_allgather`) and must equal the
single-process batch (one vmapped call in one process)."""

import os
import pickle
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

_HERE = Path(__file__).resolve().parent

# One process of the cluster: argv = port, process id, number of processes, output path.
_WORKER = r"""
import sys
port, pid, n_proc, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
import jax
jax.config.update("jax_enable_x64", True)
jax.distributed.initialize(
    f"127.0.0.1:{port}", num_processes=n_proc, process_id=pid, initialization_timeout=300
)
sys.path.insert(0, sys.argv[5])
import pickle
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import test_nrd as T
from bodyprior.registration import nrd_batch

tmpl = T._toy_template()
truth = T._true_body(np.asarray(tmpl.vertices))
scans = [T._scan(jr.PRNGKey(k), truth, np.asarray(tmpl.faces), tmpl, n=3000) for k in range(3)]
init = np.stack([np.asarray(T._aligned_template(tmpl, s)) for s in scans])
batch = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *scans)
assert jax.process_count() == n_proc and len(jax.local_devices()) == 1
dist = nrd_batch(init, batch, tmpl, config=T.CFG, progress=False)
res = dict(dist=(np.asarray(dist.value.vertices), np.asarray(dist.value.matches),
                 np.asarray(dist.result._value)))
if pid == 0:  # the single-process batch: one vmapped call on this process's own device
    one = nrd_batch(init, batch, tmpl, config=T.CFG, devices=jax.local_devices())
    res["single"] = (np.asarray(one.value.vertices), np.asarray(one.value.matches),
                     np.asarray(one.result._value))
    res["truth"], res["init"] = truth, init
with open(out, "wb") as f:
    pickle.dump(res, f)
jax.distributed.shutdown()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_nrd_batch_equals_single_process(tmp_path):
    n_proc, port = 2, _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)  # one CPU device per process
    outs = [tmp_path / f"out{p}.pkl" for p in range(n_proc)]
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _WORKER, str(port), str(p), str(n_proc), str(outs[p]),
             str(_HERE)],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )
        for p in range(n_proc)
    ]  # fmt: skip
    logs = []
    try:
        for proc in procs:
            logs.append(proc.communicate(timeout=900)[0].decode())
    finally:
        for proc in procs:
            proc.kill()
    for proc, log in zip(procs, logs):
        assert proc.returncode == 0, log[-3000:]
    res = [pickle.loads(o.read_bytes()) for o in outs]
    single = res[0]["single"]
    for r in res:  # every process holds the whole gathered batch, in batch order
        v, matches, result = r["dist"]
        assert v.shape == single[0].shape == (3, *res[0]["truth"].shape)
        np.testing.assert_allclose(v, single[0], atol=1e-8)
        np.testing.assert_array_equal(matches, single[1])
        np.testing.assert_array_equal(result, 0)
    # and the fits are real: every registration is much closer to the truth than its start
    err = lambda v: np.linalg.norm(v - res[0]["truth"], axis=-1).mean(axis=1)
    assert np.all(err(single[0]) < 0.7 * err(res[0]["init"])), (err(single[0]), err(res[0]["init"]))


@pytest.mark.bad_input
def test_per_process_strategy_rejects_devices():
    import jax

    from bodyprior.registration import batch_map

    with pytest.raises(ValueError, match="leave `devices` None"):
        batch_map(lambda r, x: x, None, np.zeros((2, 3)), devices=jax.devices(),
                  strategy="per_process")  # fmt: skip
    with pytest.raises(ValueError, match="`strategy` must be"):
        batch_map(lambda r, x: x, None, np.zeros((2, 3)), strategy="nope")


def test_per_process_strategy_in_one_process_is_the_plain_batch():
    import jax.numpy as jnp

    from bodyprior.registration import batch_map

    x = np.arange(15.0).reshape(5, 3)
    out = batch_map(_square_sum, 2.0, x, strategy="per_process", progress=False)
    np.testing.assert_allclose(out, np.asarray(jnp.sum(x**2, axis=1) * 2.0))


def _square_sum(scale, item):
    import jax.numpy as jnp

    return scale * jnp.sum(item**2)
