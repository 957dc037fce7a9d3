"""Sparse localized decomposition (bodyprior.panoman.splocs) on planted components."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.optimize import linear_sum_assignment

import bodyprior as bp
from bodyprior import panoman as pm

jax.config.update("jax_enable_x64", True)

K_TRUE = 4


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)  # 642 vertices, 1,920 edges
    v = np.asarray(m.vertices)
    return v, bp.Topology.from_faces(np.asarray(m.faces), v.shape[0])


def _planted(v, top, kind, seed, n=200, noise=1e-3):
    """`K_TRUE` components with disjoint compact supports (geodesic radius 0.35 m on the unit
    sphere), random signed weights, plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    pos = v if kind == "vertices" else 0.5 * (v[top.edges[:, 0]] + v[top.edges[:, 1]])
    pos = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    centres = [0]
    while len(centres) < K_TRUE:  # centres far apart so the supports do not overlap
        c = int(rng.integers(v.shape[0]))
        if all(np.arccos(np.clip(v[c] @ v[o], -1, 1)) > 1.0 for o in centres):
            centres.append(c)
    d = 3 if kind == "vertices" else 1
    comps = []
    for c in centres:
        ang = np.arccos(np.clip(pos @ v[c], -1, 1))
        bump = np.clip(1 - ang / 0.35, 0, None) ** 2
        comps.append(bump[:, None] * rng.normal(size=d)[None])
    C = np.stack(comps)
    W = rng.uniform(-1, 1, size=(n, K_TRUE))
    X = np.einsum("nk,ksd->nsd", W, C) + noise * rng.normal(size=(n,) + C.shape[1:])
    return X, C


def _support_overlap(found, true_c):
    """Best one-to-one IoU of supports (a site is in a support where its norm exceeds 1 % of the
    component's maximum)."""
    st = np.linalg.norm(true_c, axis=-1)
    st = st > 1e-2 * st.max(axis=1, keepdims=True)
    sf = np.asarray(found.supports(1e-2))
    iou = (sf[:, None] & st[None]).sum(-1) / np.maximum((sf[:, None] | st[None]).sum(-1), 1)
    r, c = linear_sum_assignment(-iou)
    return iou[r, c]


@pytest.mark.parametrize("kind", ["vertices", "edges"])
def test_planted_supports_recovered_and_energy_monotone(sphere, kind):
    v, top = sphere
    X, C = _planted(v, top, kind, seed=0 if kind == "vertices" else 1)
    data = X if kind == "vertices" else X[..., 0]
    errs = []
    for K in (1, 2, K_TRUE):
        sol = pm.splocs(
            data, v, top, n_components=K, d_min=0.1, d_max=0.6, dtype=jnp.float64, progress=False
        )
        e = sol.stats["energy"]
        assert np.all(np.diff(e) <= 1e-12 * e[0]), np.diff(e).max()
        dec = sol.value
        rec = pm.splocs_reconstruct(dec, dec.weights)
        errs.append(float(jnp.linalg.norm(rec - X) / np.linalg.norm(X - X.mean(0))))
        w = np.asarray(dec.weights)
        assert np.abs(w).max() <= 1 + 1e-12
        np.testing.assert_allclose(np.abs(w).max(axis=0), 1.0, atol=1e-12)
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < 0.05, errs
    overlap = _support_overlap(dec, C)
    assert overlap.min() >= 0.9, overlap
    assert dec.site_kind == kind and dec.components.shape == (K_TRUE,) + C.shape[1:]


def test_adaptive_rule_nonnegative_and_projection(sphere):
    v, top = sphere
    X, C = _planted(v, top, "vertices", seed=2)
    sol = pm.splocs(
        X, v, top, n_components=10, d_min=0.1, d_max=0.6, adaptive_tol=1e-2,
        dtype=jnp.float64, progress=False,
    )  # fmt: skip
    assert sol.stats["n_components"] == K_TRUE, sol.stats["explained"]
    # Least-squares projection of the training data returns its weights (noise and box aside).
    w = pm.splocs_project(sol.value, X)
    np.testing.assert_allclose(w, sol.value.weights, atol=0.05)  # the box |w| <= 1 binds a little
    assert pm.splocs_project(sol.value, X[0]).shape == (K_TRUE,)
    # The original constraint 0 <= w <= 1 (signed planted weights: a component per sign).
    nn = pm.splocs(
        X, v, top, n_components=8, d_min=0.1, d_max=0.6, nonnegative=True,
        dtype=jnp.float64, progress=False,
    )  # fmt: skip
    w = np.asarray(nn.value.weights)
    assert w.min() >= 0 and w.max() <= 1
    assert np.all(np.diff(nn.stats["energy"]) <= 1e-12 * nn.stats["energy"][0])


def test_bad_input(sphere):
    v, top = sphere
    X = np.zeros((5, top.n_vertices, 3))
    kw = dict(n_components=2, d_min=0.1, d_max=0.5, progress=False)
    with pytest.raises(ValueError, match="per edge"):
        pm.splocs(np.zeros((5, 7)), v, top, **kw)
    with pytest.raises(ValueError, match="d_max"):
        pm.splocs(X, v, top, **{**kw, "d_max": 0.05})
    with pytest.raises(ValueError, match="sites"):
        pm.splocs(X, v, top, sites="faces", **kw)
    with pytest.raises(ValueError, match="rest_vertices"):
        pm.splocs(X, v[:10], top, **kw)
    with pytest.raises(ValueError, match="d_min"):
        pm.splocs(X, v, top, **{**kw, "d_min": np.zeros(3)})
    with pytest.raises(ValueError, match="NaN"):
        pm.splocs(np.full_like(X, np.nan), v, top, **kw)
