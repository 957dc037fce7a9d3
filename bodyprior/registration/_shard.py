"""Running a per-item kernel over a large batch: vmap, spread over devices, in chunks.

[`bodyprior.registration.batch_map`][] is the engine of the batched registration entry points
(`fit_sscape_batch`; NRD and depth fitting can reuse it). The batch is cut into chunks of a fixed
size (the last one padded by repeating its final item, so every chunk has the same shape and the
kernel compiles once per device); every device fits its own slice of each chunk. Items are
independent. Two ways to spread a chunk (`strategy`):

- `"spmd"` (default on accelerators): one jitted call whose inputs are split over a one-axis
  `jax.sharding.Mesh` (axis `"scan"`, `NamedSharding(mesh, PartitionSpec("scan"))`); XLA's SPMD
  partitioner gives every device its slice and compiles once. The partitioned program all-reduces
  the batched loops' stopping predicates in every iteration of every (nested) while loop.
- `"per_device"` (default when all devices are CPUs): every device gets its slice as its own call
  of the same jitted function (`lax.map` over the items on CPUs, `vmap` elsewhere), dispatched
  asynchronously so the devices run concurrently; no
  collectives at all, one compilation per device. On host CPU devices the `"spmd"` program of the
  S-SCAPE fit deadlocked (jax 0.10.2, 2 host devices on 2 cores, chunks of 12 scans: every XLA
  worker thread idle, the caller waiting in `block_until_ready`; neither the GSPMD partitioner,
  `--xla_cpu_multi_thread_eigen=false` nor synchronous CPU dispatch avoided it). `shard_map`
  would state "no communication" directly, but lineax rejects the sharded abstract values inside
  it (lineax issue #185).

**Multi-GPU node:** nothing to do: all local devices are used by default (`devices=None`).

**`jax.distributed` cluster** (several processes, e.g. one per node or one per GPU): call
`jax.distributed.initialize(...)` first in every process, then call the batched entry point in every
process with the *same* full batch (each process may load or simulate all of it, or memory-map it).
Two strategies span processes:

- `"per_process"` (the default when `jax.process_count() > 1`): process `p` of `P` takes the
  contiguous share `[p·⌈B/P⌉, (p+1)·⌈B/P⌉)` of the batch, runs it on its own devices
  (`jax.local_devices()`, with that platform's local strategy), and the shares are gathered to every
  process with `jax.experimental.multihost_utils.process_allgather` (on CPUs over JAX's Gloo
  collectives). The only cross-process traffic is that gather, once per call. Tested with 2 local
  CPU processes on 127.0.0.1 (`tests/test_distributed.py`): equal to the single-process batch.
- `"spmd"`: the mesh spans `jax.devices()` (all processes' devices), every process feeds only the
  slices that live on its own devices (`jax.make_array_from_callback`) and the partitioned program
  all-reduces the loops' stopping predicates across processes in every iteration; the results are
  gathered with `process_allgather`. Not exercised by the test suite.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from .._aot import aot_filter_jit

__all__ = ["batch_map"]

_AXIS = "scan"


def _leading(tree) -> int:
    sizes = {
        x.shape[0] for x in jax.tree_util.tree_leaves(tree) if eqx.is_array_like(x) and np.ndim(x)
    }
    if len(sizes) != 1:
        raise ValueError(
            "`batched` leaves must share one leading (batch) axis, got leading sizes "
            f"{sorted(sizes)}."
        )
    return sizes.pop()


@eqx.filter_jit
def _run_vmap(kernel, replicated, chunk):
    return jax.vmap(kernel, in_axes=(None, 0))(replicated, chunk)


@aot_filter_jit
def _run_map(kernel, replicated, chunk):
    # One item after another: each runs its own number of loop iterations (a vmapped while loop
    # runs every item until the slowest one stops, masked), which on a CPU is the faster choice.
    return jax.lax.map(lambda item: kernel(replicated, item), chunk)


@eqx.filter_jit
def _run_sharded(kernel, sharding, replicated, chunk):
    # The chunk arrives split over the mesh's "scan" axis; XLA's SPMD partitioner keeps the vmapped
    # batch dimension split (each device computes its own items; the only cross-device traffic is
    # the reduction of the batched loops' stopping predicates). `shard_map` would state this
    # directly, but lineax's operator-structure checks fail inside it (jax 0.10 / lineax 0.1.1).
    out = jax.vmap(kernel, in_axes=(None, 0))(replicated, chunk)
    dyn, static = eqx.partition(out, eqx.is_array)
    dyn = jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, sharding), dyn)
    return eqx.combine(dyn, static)


def _place(tree, sharding):
    """Places the array leaves of `tree` (full host values, same in every process) on `sharding`."""

    def put(x):
        if not eqx.is_array(x):
            return x
        if sharding.is_fully_addressable:
            return jax.device_put(x, sharding)
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])

    return jax.tree_util.tree_map(put, tree)


def _to_host(tree):
    leaves = [x for x in jax.tree_util.tree_leaves(tree) if isinstance(x, jax.Array)]
    if leaves and not all(x.is_fully_addressable for x in leaves):
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(lambda x: np.asarray(x) if eqx.is_array(x) else x, tree)


def batch_map(
    kernel: Callable,
    replicated,
    batched,
    *,
    devices: Sequence[jax.Device] | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    desc: str = "batch",
    strategy: str | None = None,
):
    """Applies `kernel(replicated, item)` to every item of a batch: vmap, sharded, in chunks.

    **Arguments:**

    - `kernel`: a pure per-item function `kernel(replicated, item) -> pytree`, jittable; use a
      module-level function so that repeated calls reuse the compiled chunk.
    - `replicated`: pytree given whole to every item (e.g. the model); arrays are copied to every
      device, non-array leaves are static.
    - `batched`: pytree whose array leaves share a leading batch axis B (`None` leaves allowed).
    - `devices`: devices of the one-axis mesh (default `jax.devices()`); one device = plain vmap.
    - `chunk_size`: items per jitted call, rounded up to a multiple of the device count (default
      4 per device, capped at B rounded up).
    - `progress`: tqdm progress bar over items.
    - `desc`: progress-bar label.
    - `strategy`: `"spmd"` (one partitioned program over a device mesh), `"per_device"` (one call
      per device, no collectives; single process only), `"per_process"` (every `jax.distributed`
      process runs its share of the batch on its local devices, then one gather) or `None`
      (`"per_process"` when `jax.process_count() > 1` and `devices` is None, else `"per_device"`
      when every device is a CPU, else `"spmd"`); see the module docstring.

    **Returns:** the stacked outputs (leading axis B) with NumPy leaves on the host.
    """
    n = _leading(batched)
    if strategy not in (None, "spmd", "per_device", "per_process"):
        raise ValueError(
            f"`strategy` must be 'spmd', 'per_device', 'per_process' or None, got {strategy!r}."
        )
    if strategy == "per_process" or (
        strategy is None and devices is None and jax.process_count() > 1
    ):
        if devices is not None:
            raise ValueError(
                "`strategy='per_process'` uses every process's local devices: leave `devices` None."
            )
        return _per_process(kernel, replicated, batched, n, chunk_size, progress, desc)
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("`devices` must name at least one device.")
    n_dev = len(devices)
    on_cpu = all(d.platform == "cpu" for d in devices)
    if strategy is None:
        strategy = "per_device" if on_cpu else "spmd"
    if strategy == "per_device" and any(d.process_index != jax.process_index() for d in devices):
        raise ValueError(
            "`strategy='per_device'` runs in one process: `devices` must be this process's "
            "devices (use strategy='spmd' across a jax.distributed cluster)."
        )
    if chunk_size is None:
        chunk_size = 4 * n_dev
    if (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, (int, np.integer))
        or chunk_size < 1
    ):
        raise ValueError(f"`chunk_size` must be a positive int or None, got {chunk_size!r}.")
    chunk = min(int(chunk_size), n)
    chunk = -(-chunk // n_dev) * n_dev
    n_pad = -(-n // chunk) * chunk

    def pad(x):
        if not eqx.is_array(x):
            return x
        x = np.asarray(x)
        if n_pad == n:
            return x
        return np.concatenate([x, np.repeat(x[-1:], n_pad - n, axis=0)], axis=0)

    batched = jax.tree_util.tree_map(pad, batched)
    mesh = None
    if n_dev > 1 and strategy == "spmd":
        mesh = Mesh(np.asarray(devices), (_AXIS,))
        replicated = _place(replicated, NamedSharding(mesh, PartitionSpec()))
        item_sharding = NamedSharding(mesh, PartitionSpec(_AXIS))
    else:
        # one copy of the replicated arguments per device, placed once
        on_device = [
            jax.tree_util.tree_map(lambda x: jax.device_put(x, d) if eqx.is_array(x) else x,
                                   replicated)
            for d in devices
        ]  # fmt: skip
    per = chunk // n_dev
    # per device: items one after another on CPUs (see `_run_map`), vmapped elsewhere
    run = _run_map if on_cpu else _run_vmap

    outs = []
    with tqdm(total=n, desc=desc, unit="scan", disable=not progress) as bar:
        for s in range(0, n_pad, chunk):
            part = jax.tree_util.tree_map(
                lambda x: x[s : s + chunk] if eqx.is_array(x) else x, batched
            )
            if mesh is None:
                # dispatch every device's slice before waiting for any (asynchronous dispatch)
                pieces = []
                for i, d in enumerate(devices):
                    sl = jax.tree_util.tree_map(
                        lambda x: (
                            jax.device_put(x[i * per : (i + 1) * per], d) if eqx.is_array(x) else x
                        ),
                        part,
                    )
                    pieces.append(run(kernel, on_device[i], sl))
                outs.append(_concat([_to_host(o) for o in pieces]))
            else:
                out = _run_sharded(kernel, item_sharding, replicated, _place(part, item_sharding))
                outs.append(_to_host(out))
            bar.update(min(chunk, n - s))
    return jax.tree_util.tree_map(lambda x: x[:n] if eqx.is_array(x) else x, _concat(outs))


def _per_process(kernel, replicated, batched, n, chunk_size, progress, desc):
    """`strategy="per_process"`: this process's contiguous share, run locally, then one gather."""
    from jax.experimental import multihost_utils

    n_proc, me = jax.process_count(), jax.process_index()
    share = -(-n // n_proc)
    lo, hi = min(me * share, n), min((me + 1) * share, n)
    # every process runs exactly `share` items (same shapes for the gather): a short or empty share
    # is padded by repeating an item, dropped again after the gather
    rows = np.arange(lo, hi) if hi > lo else np.zeros(0, np.int64)
    rows = np.concatenate([rows, np.full(share - len(rows), hi - 1 if hi > lo else 0)])
    local = jax.tree_util.tree_map(lambda x: np.asarray(x)[rows] if eqx.is_array(x) else x, batched)
    out = batch_map(
        kernel,
        replicated,
        local,
        devices=jax.local_devices(),
        chunk_size=chunk_size,
        progress=progress,
        desc=f"{desc} [process {me}/{n_proc}]",
    )
    dyn, static = eqx.partition(out, eqx.is_array)
    dyn = multihost_utils.process_allgather(dyn, tiled=True)  # (n_proc * share, ...) per leaf
    keep = np.concatenate(
        [np.arange(p * share, p * share + max(0, min(n, (p + 1) * share) - p * share))
         for p in range(n_proc)]
    )  # fmt: skip
    dyn = jax.tree_util.tree_map(lambda x: np.asarray(x)[keep], dyn)
    return eqx.combine(dyn, static)


def _concat(trees):
    if len(trees) == 1:
        return trees[0]
    return jax.tree_util.tree_map(
        lambda *xs: np.concatenate(xs, axis=0) if eqx.is_array(xs[0]) else xs[0], *trees
    )
