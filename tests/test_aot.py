"""Whole-algorithm programs exported with `jax.export` and reused across processes (`_aot`)."""

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bodyprior import _aot
from bodyprior._aot import aot_filter_jit, set_export_directory
from bodyprior._validate import as_device_array
from bodyprior.registration import _shard


@pytest.fixture
def export_dir(tmp_path):
    path = set_export_directory(tmp_path / "exported")
    try:
        yield path
    finally:
        set_export_directory(None)


def _entries(path):
    return sorted(f for f in os.listdir(path) if f.endswith(".jexp"))


class _Out(eqx.Module):
    y: jax.Array
    n: int = eqx.field(static=True)
    label: str = "x"


def test_aot_round_trip_skips_tracing(export_dir):
    traced = []

    def f(x, cfg):
        traced.append(1)
        scale, label = cfg
        return _Out(x * scale + jnp.sum(x**2), x.shape[0], label)

    g = aot_filter_jit(f)
    x = np.linspace(-1.0, 1.0, 5)
    ref = eqx.filter_jit(f)(x, (2.0, "a"))
    traced.clear()
    out = g(x, (2.0, "a"))
    assert len(traced) == 1 and len(_entries(export_dir)) == 1
    assert isinstance(out, _Out) and out.n == 5 and out.label == "a"
    np.testing.assert_allclose(out.y, ref.y, rtol=0, atol=1e-15)
    # A new process: nothing in memory, the program comes from the file without tracing.
    g2 = aot_filter_jit(f)
    out2 = g2(x + 1.0, (2.0, "a"))
    assert len(traced) == 1
    np.testing.assert_allclose(out2.y, eqx.filter_jit(f)(x + 1.0, (2.0, "a")).y, atol=1e-15)
    # Every static value, shape and dtype is part of the signature.
    g2(x, (3.0, "a"))
    g2(x[:4], (3.0, "a"))
    g2(x.astype(np.float32), (3.0, "a"))
    assert len(_entries(export_dir)) == 4
    np.testing.assert_allclose(g2(x, (3.0, "a")).y, eqx.filter_jit(f)(x, (3.0, "a")).y, atol=1e-15)


def test_aot_rebuilds_a_bad_entry(export_dir):
    g = aot_filter_jit(lambda x: jnp.cumsum(x) * 2.0)
    x = np.arange(6.0)
    g(x)
    (name,) = _entries(export_dir)
    with open(os.path.join(export_dir, name), "wb") as f:
        f.write(b"truncated")
    g2 = aot_filter_jit(g.__wrapped__)
    np.testing.assert_array_equal(g2(x), np.cumsum(x) * 2.0)
    with open(os.path.join(export_dir, name), "rb") as f:
        assert f.read() != b"truncated"


def test_aot_falls_back_without_a_stable_signature(export_dir):
    def apply(fn, x):
        return fn(x) + 1.0

    g = aot_filter_jit(apply)
    x = np.arange(3.0)
    # A function from outside the package has no stable description: plain filter_jit.
    np.testing.assert_array_equal(g(lambda v: v * 3.0, x), x * 3.0 + 1.0)
    np.testing.assert_allclose(g(jnp.sin, x), np.sin(x) + 1.0, atol=1e-15)
    assert _entries(export_dir) == []
    # One of the package's functions does have one.
    from bodyprior._geometry import vertex_normals

    assert "fn(bodyprior._geometry,vertex_normals" in _aot._describe(vertex_normals)
    with pytest.raises(_aot._Unstable):
        _aot._describe(object())


def test_aot_falls_back_for_host_callbacks(export_dir):
    seen = []

    def f(x):
        jax.debug.callback(lambda v: seen.append(np.asarray(v)), x)
        return x * 2.0

    g = aot_filter_jit(f)
    np.testing.assert_array_equal(g(np.ones(3)), 2.0 * np.ones(3))
    assert _entries(export_dir) == [] and len(seen) == 1
    # the refusal is remembered: the next call neither exports nor re-traces
    tries = []
    orig = g._export
    g._export = lambda *a: tries.append(1) or orig(*a)
    np.testing.assert_array_equal(g(np.ones(3)), 2.0 * np.ones(3))
    assert tries == [] and len(seen) == 2


def test_aot_off_is_filter_jit():
    assert _aot.export_directory() is None
    calls = []

    def f(x):
        calls.append(1)
        return x + 1

    g = aot_filter_jit(f)
    g(np.ones(2))
    g(np.ones(2))
    assert calls == [1]


def test_batch_map_exported_equals_plain(export_dir, monkeypatch):
    # The registration engine's per-chunk program (`_run_map`) through the export directory; the
    # kernel is this file's, which the package's functions are not, so accept it here.
    from bodyprior._geometry import vertex_normals

    monkeypatch.setattr(_aot, "_own_function", lambda fn: True)

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(3, 10, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8], [8, 9, 0]], np.int32)
    kernel = _shard_kernel
    out = _shard.batch_map(kernel, faces, verts, progress=False)
    assert len(_entries(export_dir)) == 1
    set_export_directory(None)
    plain = _shard.batch_map(kernel, faces, verts, progress=False)
    np.testing.assert_allclose(out, plain, atol=1e-15)
    np.testing.assert_allclose(out[1], vertex_normals(verts[1], faces), atol=1e-12)


def _shard_kernel(faces, verts):
    from bodyprior._geometry import vertex_normals

    return vertex_normals(verts, faces)


@pytest.mark.parametrize(
    "x",
    [np.arange(4.0), np.arange(4), np.array([True, False]), np.float64(2.5), np.zeros((2, 0))],
)
def test_as_device_array_matches_asarray(x):
    for dtype in (None, np.float32, jnp.int32):
        a, b = as_device_array(x, dtype), jnp.asarray(x, dtype)
        assert isinstance(a, jax.Array)
        assert (a.dtype, a.shape, a.weak_type) == (b.dtype, b.shape, b.weak_type)
        np.testing.assert_array_equal(a, b)


def test_as_device_array_passes_tracers_and_lists():
    out = jax.jit(lambda v: as_device_array(v, jnp.float32) * 2)(np.arange(3.0))
    assert out.dtype == jnp.float32
    np.testing.assert_array_equal(as_device_array([1.0, 2.0]), jnp.asarray([1.0, 2.0]))
