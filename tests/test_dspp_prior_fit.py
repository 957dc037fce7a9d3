"""DSPP priors in least-squares fitters (bodyprior.dspp._fitting) and the prior-fit experiment.

Library tests use a small random mesh set (V = 40) with the real `ShapePrior` class (freshly
initialised, so no training compile is needed); the experiment runs in-process in `--quick` mode
with tiny sizes.
"""

import json
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import dspp
from bodyprior.dspp._fitting import _landmark_decoder, _sqrt_nll

V = 40


def _f64(tree):
    return jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float64) if eqx.is_inexact_array(x) else x, tree
    )


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    # Meshes with 6 directions of variation around a random template.
    base = rng.normal(size=(V, 3))
    modes = rng.normal(size=(6, V, 3)) * np.array([0.3, 0.2, 0.15, 0.1, 0.05, 0.02])[:, None, None]
    meshes = base + np.einsum("nk,kvd->nvd", rng.normal(size=(50, 6)), modes)
    faces = np.stack([np.arange(V - 2), np.arange(1, V - 1), np.arange(2, V)], 1).astype(np.int32)
    model = bp.sscape.learn(meshes, faces, n_components=6, align=False)
    cfg = dspp.DSPPConfig(latent_dim=4, noise_dim=4, ae_hidden=(16,), generator_hidden=(8,),
                          discriminator_hidden=(8,))  # fmt: skip
    scale = float(np.sqrt(np.mean((meshes - meshes.mean(0)) ** 2)))
    prior = dspp.init_aegan("shape", meshes.mean(0), scale, cfg, key=jax.random.PRNGKey(1))
    return dict(meshes=meshes, model=model, prior=prior, idx=np.arange(0, V, 3, dtype=np.int32))


@eqx.filter_jit
def _energy(r, x):
    return r.energy(x)


@eqx.filter_jit
def _energy_grad(r, x):
    return jax.grad(r.energy)(x)


def test_prior_residual_energy_and_gradient(setup):
    prior, x = _f64(setup["prior"]), jnp.asarray(setup["meshes"][0])
    logit = eqx.filter_jit(lambda p, y: p.latent_logit(p.encode(y)))(prior, x)
    nll = jax.nn.softplus(-logit)
    r = dspp.shape_prior_residual(prior, 2.5)
    assert r(x).shape == (1,)
    np.testing.assert_allclose(_energy(r, x), 2.5 * nll, rtol=1e-12)
    rr = dspp.shape_prior_residual(prior, 2.5, reconstruction_weight=7.0)
    assert jax.eval_shape(rr, x).shape == (1 + 3 * V,)
    rec = eqx.filter_jit(lambda p, y: jnp.sum((y - p.reconstruct(y)) ** 2) / V)(prior, x)
    np.testing.assert_allclose(_energy(rr, x), 2.5 * nll + 7.0 * rec, rtol=1e-10)
    # Gradient of the energy against central finite differences.
    d = jnp.asarray(np.random.default_rng(2).normal(size=(V, 3)))
    g = jnp.vdot(_energy_grad(rr, x), d)
    eps = 1e-6
    fd = (_energy(rr, x + eps * d) - _energy(rr, x - eps * d)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    # The square root of the non-saturating loss stays finite with finite slope at any logit.
    ls = jnp.array([-1e3, -30.0, 0.0, 29.9, 30.1, 800.0, 1e4])
    vals, grads = jax.jit(jax.vmap(jax.value_and_grad(_sqrt_nll)))(ls)
    assert np.all(np.isfinite(vals)) and np.all(np.isfinite(grads))
    np.testing.assert_allclose(vals[:5] ** 2, jax.nn.softplus(-ls[:5]), rtol=1e-9)


def test_space_fit_is_the_map_estimate(setup):
    model, idx, meshes = setup["model"], setup["idx"], setup["meshes"]
    rng = np.random.default_rng(3)
    ts = np.stack([meshes[3][idx], meshes[4][idx]]) + 0.01 * rng.normal(size=(2, len(idx), 3))
    # Batched over bodies with vmap (throw=False).
    sols = jax.vmap(lambda t: dspp.fit_shape_space_to_landmarks(
        model, idx, t, noise_sigma=0.02, coeff_weight=0.7, throw=False)
    )(jnp.asarray(ts))  # fmt: skip
    assert np.all(np.asarray(sols.result == bp.RESULTS.successful))
    fits = sols.value
    # Closed form: (A^T A / s^2 + w I) c = A^T (t - m) / s^2 with A the landmark rows of the basis.
    A = (np.asarray(model.basis)[:, idx] * np.asarray(model.stddev)[:, None, None]).reshape(6, -1).T
    for k in range(2):
        b = (ts[k] - np.asarray(model.mean)[idx]).reshape(-1)
        c = np.linalg.solve(A.T @ A / 0.02**2 + 0.7 * np.eye(6), A.T @ b / 0.02**2)
        np.testing.assert_allclose(fits.params[k], c, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(fits.vertices[k], bp.sscape.shape_vertices(model, c), atol=1e-8)
    # With the prior residual (one compiled structure for every weight): a zero weight changes
    # nothing; a positive one lowers its own term and the total energy it is part of, compared with
    # the plain fit.
    prior = setup["prior"]

    def fit_with(w, wr):
        reg = dspp.shape_prior_residual(prior, w, reconstruction_weight=wr, reconstruction=True)
        sol = dspp.fit_shape_space_to_landmarks(model, idx, ts[0], noise_sigma=0.02,
                                                coeff_weight=0.7, regulariser=reg)  # fmt: skip
        assert sol.result == bp.RESULTS.successful
        return sol, _f64(reg)

    fit0, _ = fit_with(0.0, 0.0)
    np.testing.assert_allclose(fit0.value.params, fits.params[0], atol=1e-7)
    fit1, r1 = fit_with(50.0, 1e3)
    plain = fits.vertices[0]
    assert fit1.stats["energy"] < sols.stats["energy"][0] + r1.energy(plain) - 1e-9
    assert r1.energy(fit1.value.vertices) < r1.energy(plain)


def test_latent_fit_recovers_decoded_shape(setup):
    prior = setup["prior"]
    idx = jnp.arange(V, dtype=jnp.int32)
    mu, sd = dspp.latent_statistics(prior, setup["meshes"][:20], chunk_size=8)
    assert mu.shape == sd.shape == (4,) and np.all(np.asarray(sd) > 0)
    p64 = _f64(prior)
    z_true = _f64(mu) + 0.5 * _f64(sd) * jnp.array([1.0, -1.0, 0.5, 0.0])
    np.testing.assert_allclose(_landmark_decoder(p64, idx[::3])(z_true),
                               p64.decode(z_true)[::3], rtol=1e-12)  # fmt: skip
    target = p64.decode(z_true)
    sol = dspp.fit_latent_to_landmarks(prior, idx, target, latent_mean=mu, latent_std=sd,
                                       noise_sigma=0.01, latent_weight=1e-10, score_weight=0.0,
                                       max_steps=200)  # fmt: skip
    assert sol.result == bp.RESULTS.successful
    assert float(sol.stats["landmark_rms"]) < 1e-5 * float(prior.scale)


@pytest.mark.bad_input
def test_fitting_errors(setup):
    model, prior, idx = setup["model"], setup["prior"], setup["idx"]
    t = setup["meshes"][0][idx]
    with pytest.raises(ValueError, match="`model` must be an SScapeModel"):
        dspp.fit_shape_space_to_landmarks(prior, idx, t)
    with pytest.raises(ValueError, match=r"`targets` must have shape \(14, 3\)"):
        dspp.fit_shape_space_to_landmarks(model, idx, t[:5])
    with pytest.raises(ValueError, match=r"`landmark_index` must lie in \[0, 39\]"):
        dspp.fit_shape_space_to_landmarks(model, idx + 30, t)
    with pytest.raises(ValueError, match="`coeff_weight` must be non-negative"):
        dspp.fit_shape_space_to_landmarks(model, idx, t, coeff_weight=-1.0)
    with pytest.raises(ValueError, match="`noise_sigma` must be positive"):
        dspp.fit_shape_space_to_landmarks(model, idx, t, noise_sigma=0.0)
    with pytest.raises(ValueError, match="`regulariser` must be callable"):
        dspp.fit_shape_space_to_landmarks(model, idx, t, regulariser=3.0)
    with pytest.raises(ValueError, match="`prior` must be a PosePrior"):
        dspp.pose_prior_residual(prior, 1.0)
    with pytest.raises(ValueError, match="`weight` must be non-negative"):
        dspp.shape_prior_residual(prior, -2.0)
    mu = jnp.zeros(4)
    with pytest.raises(ValueError, match="`latent_std` must be positive"):
        dspp.fit_latent_to_landmarks(prior, idx, t, latent_mean=mu, latent_std=jnp.zeros(4))
    with pytest.raises(ValueError, match=r"`latent_mean` must have shape \(4,\)"):
        dspp.fit_latent_to_landmarks(prior, idx, t, latent_mean=jnp.zeros(3), latent_std=mu + 1)


@pytest.mark.typecheck_off
def test_experiment_quick(tmp_path):
    import importlib.util

    path = os.path.join(os.path.dirname(__file__), "..", "experiments", "dspp_prior_fit.py")
    spec = importlib.util.spec_from_file_location("dspp_prior_fit", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # A real (untrained, tiny) ShapePrior on the decimated topology, passed with --prior: the
    # training path is H-core's and tested in test_dspp.py; skipping it keeps this test short.
    vertex_map, _ = bp.load_decimated()
    mean = np.asarray(bp.load_default_body("cmu_mb").template)[vertex_map]
    cfg = dspp.DSPPConfig(latent_dim=8, noise_dim=8, ae_hidden=(16,), generator_hidden=(16,),
                          discriminator_hidden=(16,))  # fmt: skip
    prior_path = tmp_path / "prior.eqx"
    prior = dspp.init_aegan("shape", mean, 0.05, cfg, key=jax.random.PRNGKey(0))
    dspp.save_prior(prior_path, prior)
    out = tmp_path / "out"
    m = mod.main(["--quick", "--out", str(out), "--no-progress", "--n-train", "16", "--n-val", "2",
                  "--n-test", "2", "--n-components", "4", "--max-steps", "8",
                  "--prior", str(prior_path)])  # fmt: skip
    with open(out / "metrics.json") as f:
        saved = json.load(f)
    assert saved == json.loads(json.dumps(m))
    assert set(saved["results"]) == {"pca", "pca_dspp", "dspp_latent"}
    for r in saved["results"].values():
        e = r["vertex_error_mm"]
        assert 0.0 < e["mean"] < 500.0 and np.isfinite(e["std"])
    # Weights are chosen on validation data: the chosen entry is the grid minimum.
    for k, g in saved["validation_grids"].items():
        best = min(x["val_error_mm"] for x in g)
        assert saved["results"][k]["chosen"]["val_error_mm"] == best
    assert saved["sizes"]["n_landmarks"] == 77 and saved["sizes"]["n_vertices"] == 6449
    assert saved["prior"]["source"].endswith("prior.eqx")
    png = out / saved["figure"]
    assert png.exists() and 0 < png.stat().st_size < 400_000
