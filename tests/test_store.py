"""bodyprior.save / bodyprior.load: populations, pose sets, fits and registrations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import registration, sscape


def _equal(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        assert type(x) is type(y) or (isinstance(x, jax.Array) and isinstance(y, jax.Array))
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        assert np.asarray(x).dtype == np.asarray(y).dtype


def test_round_trips(tmp_path):
    pop = bp.sample_population(2, key=jax.random.PRNGKey(0), progress=False)
    ps = bp.PoseSet(jnp.ones((4, 20, 3)), jnp.array([0, 0, 1, 1]), ("a/01", "b/02"), fps=8.0)
    sim = bp.Similarity(jnp.eye(3), jnp.array([0.1, 0.2, 0.3]), jnp.array(0.05))
    fit = sscape.SScapeFit(
        jnp.zeros(5), jnp.ones((31, 3)), sim, jnp.ones((10, 3)), jnp.ones((10, 3))
    )
    batched = jax.tree_util.tree_map(lambda x: jnp.stack([x, 2 * x]), sim)
    reg = sscape.Registration(np.ones((2, 10, 3)), np.zeros((2, 31, 3)), batched,
                              np.ones((2, 10, 3)), None, np.array([True, False]))  # fmt: skip
    nrd = registration.NRDFit(jnp.ones((6, 3)), jnp.zeros((6, 3, 4)), jnp.ones(6, bool),
                              jnp.arange(6))  # fmt: skip
    for i, obj in enumerate((pop, ps, sim, fit, reg, nrd)):
        path = tmp_path / f"o{i}.bp"
        bp.save(path, obj, info={"i": i})
        back, info = bp.load(path, return_info=True)
        assert type(back) is type(obj) and info == {"i": i}
        _equal(back, obj)
    back = bp.load(tmp_path / "o1.bp")
    assert back.clip_names == ("a/01", "b/02") and back.fps == 8.0
    assert bp.load(tmp_path / "o4.bp").coeffs is None
    assert isinstance(bp.load(tmp_path / "o4.bp").vertices, np.ndarray)  # NumPy stays NumPy


def test_bad_files_and_objects(tmp_path):
    sim = bp.Similarity.identity()
    p = tmp_path / "s.bp"
    bp.save(p, sim)
    raw = bytearray(p.read_bytes())
    i = raw.index(b"arrays.npz") + 200  # a byte inside the stored array member
    raw[i] ^= 0xFF
    (tmp_path / "bad.bp").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="checksum|readable|corrupt"):
        bp.load(tmp_path / "bad.bp")
    with pytest.raises(ValueError, match="no such file"):
        bp.load(tmp_path / "missing.bp")
    sscape.save_model(tmp_path / "m.sscape", sscape.default_space(2))
    with pytest.raises(ValueError, match="not a bodyprior.store file"):
        bp.load(tmp_path / "m.sscape")
    with pytest.raises(ValueError, match="registered types"):
        bp.save(tmp_path / "x.bp", {"a": 1})
    with pytest.raises(ValueError, match="cannot store"):
        bp.save(tmp_path / "x.bp", sscape.Registration(np.ones(2), np.ones(2), {"a": 1}))
    with pytest.raises(ValueError, match="traced"):
        jax.jit(lambda t: bp.save(tmp_path / "x.bp", bp.Similarity(jnp.eye(3), t, t[0])))(
            jnp.zeros(3)
        )
