"""DSPP networks, training, checkpoints and sampling (bodyprior.dspp, H-core)."""

import dataclasses
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import dspp
from bodyprior.dspp._nets import LatentDiscriminator, PointNetDiscriminator

V = 40  # toy "mesh" size: same code paths as the 6,449-vertex topology, a fraction of the cost
TINY = dict(latent_dim=4, noise_dim=4, ae_hidden=(16,), generator_hidden=(16,),
            discriminator_hidden=(16,), pointnet_hidden=(8,), pointnet_head_hidden=(8,),
            pointnet_points=16, geometry_pose_hidden=(16,),
            geometry_generator_hidden=(16,))  # fmt: skip


def _cfg(**kw):
    return dspp.DSPPConfig(**{**TINY, "n_steps": 20, "batch_size": 2, "steps_per_call": 5,
                              "checkpoint_every": 10, **kw})  # fmt: skip


def _shapes(n=12, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(V, 3))
    # a 2-parameter family (scale + a bump), so that there is structure to learn
    a, b = rng.uniform(0.8, 1.2, n), rng.normal(size=n)
    bump = np.zeros((V, 3))
    bump[: V // 2, 2] = 0.3
    return a[:, None, None] * base[None] + b[:, None, None] * bump[None]


def _poses(n=30, seed=1):
    return np.random.default_rng(seed).normal(scale=0.4, size=(n, 20, 3))


def test_network_shapes(getkey):
    cfg = _cfg()
    sp = dspp.init_aegan("shape", np.zeros((V, 3)), 1.0, cfg, key=getkey())
    pp = dspp.init_aegan("pose", np.zeros((20, 3)), 1.0, cfg, key=getkey())
    assert isinstance(sp, dspp.ShapePrior) and isinstance(pp, dspp.PosePrior)
    x = jnp.ones((V, 3))
    z = sp.encode(x)
    assert z.shape == (4,) and z.dtype == jnp.float32 and sp.latent_dim == 4
    assert sp.decode(z).shape == (V, 3) and sp.sample(getkey()).shape == (V, 3)
    assert sp.latent_logit(z).shape == () and sp.n_vertices == V
    assert pp.sample(getkey()).shape == (20, 3) and pp.encode(jnp.zeros((20, 3))).shape == (4,)
    for kind, item in (("shape", (V, 3)), ("pose", (20, 3))):
        g = dspp.init_geometry_gan(kind, np.zeros(item), 1.0, cfg, key=getkey())
        assert g.sample(getkey()).shape == item and g.logit(jnp.zeros(item)).shape == ()
    # discriminators: every linear map is spectrally normalised
    d, _ = eqx.nn.make_with_state(PointNetDiscriminator)((8, 16), (8,), key=getkey())

    def count(cls):
        leaves = jax.tree_util.tree_leaves(d, is_leaf=lambda x: isinstance(x, cls))
        return sum(isinstance(x, cls) for x in leaves)

    n_sn, n_lin = count(eqx.nn.SpectralNorm), count(eqx.nn.Linear)
    assert n_sn == n_lin == 4


def test_spectral_norm_bounds_lipschitz(getkey):
    disc, state = eqx.nn.make_with_state(LatentDiscriminator)(6, (32, 32), key=getkey())
    # Move the weights far from norm 1 and away from the singular vectors the layer was built with:
    # the power iteration must track the new largest singular value.
    rng = np.random.default_rng(0)
    disc = jax.tree_util.tree_map(
        lambda w: (
            7.0 * w + jnp.asarray(rng.normal(size=w.shape), w.dtype)
            if getattr(w, "ndim", 0) == 2
            else w
        ),
        disc,
    )
    call = eqx.filter_jit(lambda d, z, s: d(z, s))
    z = jnp.ones(6, jnp.float32)
    for _ in range(60):  # power iterations, one per training call
        _, state = call(disc, z, state)
    sig = np.asarray(dspp.spectral_norms(disc, state))
    np.testing.assert_allclose(sig, 1.0, atol=2e-3)
    # ReLU network with unit-norm layers is 1-Lipschitz (up to the power-iteration error).
    x, y = jr.normal(getkey(), (2, 200, 6), jnp.float32)
    f = jax.vmap(lambda a: disc(a, state, inference=True)[0])
    ratio = np.abs(np.asarray(f(x) - f(y))) / np.linalg.norm(np.asarray(x - y), axis=1)
    assert ratio.max() <= 1.0 + 3e-3
    # without normalisation the same network is far from 1-Lipschitz
    raw = [lyr.layer.weight for lyr in disc.mlp.layers]
    assert np.prod([np.linalg.norm(np.asarray(w), 2) for w in raw]) > 10.0


def test_training_decreases_ae_loss_and_is_deterministic(getkey):
    data = _shapes()
    cfg = _cfg(n_steps=300, batch_size=4, steps_per_call=100, checkpoint_every=300)
    sol = dspp.train_shape_prior(data, key=jr.PRNGKey(3), config=cfg, progress=False)
    assert sol.result == bp.RESULTS.successful
    prior, log = sol.value, sol.aux
    assert log.n_steps == 300 and log.finite
    assert np.mean(log.ae_loss[-20:]) < 0.2 * np.mean(log.ae_loss[:20])
    assert np.all((log.d_real > 0) & (log.d_real < 1)) and np.all(np.isfinite(log.g_loss))
    # reconstruction on the training items improves over the untrained auto-encoder
    rec = jax.vmap(prior.reconstruct)(jnp.asarray(data, jnp.float32))
    assert float(jnp.mean(jnp.linalg.norm(rec - data, axis=-1))) < 0.5 * float(
        np.mean(np.linalg.norm(data - data.mean(0), axis=-1))
    )
    sol2 = dspp.train_shape_prior(data, key=jr.PRNGKey(3), config=cfg, progress=False)
    prior2, log2 = sol2.value, sol2.aux
    assert eqx.tree_equal(eqx.filter(prior, eqx.is_array), eqx.filter(prior2, eqx.is_array))
    np.testing.assert_array_equal(log.ae_loss, log2.ae_loss)


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))]


@pytest.mark.parametrize("which", ["aegan_pose", "geomgan_shape"])
def test_checkpoint_resume_is_bitwise_identical(tmp_path, which):
    if which == "aegan_pose":

        def train(cfg, ckpt, key=5):
            sol = dspp.train_pose_prior(_poses(), key=jr.PRNGKey(key), config=cfg,
                                        checkpoint_dir=ckpt, progress=False)  # fmt: skip
            return sol.value, sol.aux
    else:

        def train(cfg, ckpt, key=5):
            sol = dspp.train_geometry_gan(_shapes(), kind="shape", key=jr.PRNGKey(key),
                                          config=cfg, checkpoint_dir=ckpt,
                                          progress=False)  # fmt: skip
            return sol.value, sol.aux

    full, log_full = train(_cfg(n_steps=20), None)
    half, _ = train(_cfg(n_steps=10), tmp_path)  # "interrupted" after step 10
    assert (tmp_path / f"{which}.ckpt").exists()
    resumed, log_res = train(_cfg(n_steps=20), tmp_path)
    for a, b in zip(_leaves(full), _leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(log_full.d_loss, log_res.d_loss)
    assert log_res.n_steps == 20
    # the two halves really differ (the resume did continue training)
    assert any(not np.array_equal(a, b) for a, b in zip(_leaves(half), _leaves(full)))
    # a checkpoint of another run is refused, not silently resumed
    with pytest.raises(ValueError, match="another `key`"):
        train(_cfg(), tmp_path, key=6)
    ck = tmp_path / f"{which}.ckpt"
    raw = bytearray(ck.read_bytes())
    raw[-200] ^= 0xFF
    ck.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="checksum|corrupt|readable"):
        train(_cfg(n_steps=30), tmp_path)


def test_sampling_jit_vmap_and_save_load(tmp_path, getkey):
    cfg = _cfg()
    sp = dspp.init_aegan("shape", _shapes().mean(0), 0.5, cfg, key=getkey())
    key = jr.PRNGKey(9)
    xs = dspp.sample(sp, 5, key=key)
    assert xs.shape == (5, V, 3)
    one = jnp.stack([sp.sample(k) for k in jr.split(key, 5)])
    np.testing.assert_allclose(np.asarray(xs), np.asarray(one), rtol=1e-5, atol=1e-6)
    path = tmp_path / "shape.dspp"
    dspp.save_prior(path, sp)
    back = dspp.load_prior(path)
    assert isinstance(back, dspp.ShapePrior) and back.config == sp.config
    np.testing.assert_array_equal(np.asarray(dspp.sample(back, 5, key=key)), np.asarray(xs))
    z = sp.encode(jnp.zeros((V, 3)))
    assert float(back.latent_logit(z)) == float(sp.latent_logit(z))
    g = dspp.init_geometry_gan("pose", np.zeros((20, 3)), 1.0, cfg, key=getkey())
    dspp.save_prior(tmp_path / "g.dspp", g)
    g2 = dspp.load_prior(tmp_path / "g.dspp")
    assert g2.kind == "pose"
    np.testing.assert_array_equal(np.asarray(g2.sample(key)), np.asarray(g.sample(key)))
    (tmp_path / "bad.dspp").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="readable"):
        dspp.load_prior(tmp_path / "bad.dspp")


def test_pca_baselines():
    data = _poses(n=50)
    for mode in dspp.PCA_MODES:
        pca = dspp.fit_pca_prior(data, 6, mode=mode)
        x = np.asarray(dspp.sample(pca, 400, key=jr.PRNGKey(0)), np.float64)
        c = (x - np.asarray(pca.mean)).reshape(400, -1) @ np.asarray(pca.basis).T
        c /= np.asarray(pca.stddev)
        if mode == "gaussian":
            assert abs(c.std() - 1.0) < 0.08 and abs(c.mean()) < 0.08
        elif mode == "pm3sigma":
            np.testing.assert_allclose(np.abs(c), 3.0, rtol=1e-4)
        else:
            assert np.abs(c).max() <= 3.0 + 1e-4 and abs(c.std() - np.sqrt(3.0)) < 0.1
    # the top-k (Lanczos) path used for large data agrees with the exact SVD
    from bodyprior._stats import pca_host as _pca_host
    from bodyprior.dspp._sample import _pca_top

    flat = data.reshape(50, -1)
    _, c_ex, s_ex = _pca_host(flat)
    _, c_top, s_top = _pca_top(flat, 6)
    np.testing.assert_allclose(s_top, s_ex[:6], rtol=1e-9)
    np.testing.assert_allclose(c_top, c_ex[:6], atol=1e-7)
    # stddev matches the data's variance along the components (unbiased)
    pca = dspp.fit_pca_prior(data, 6)
    proj = (data - data.mean(0)).reshape(50, -1) @ np.asarray(pca.basis, np.float64).T
    np.testing.assert_allclose(proj.std(0, ddof=1), np.asarray(pca.stddev), rtol=1e-5)


@pytest.mark.bad_input
def test_bad_inputs(tmp_path, getkey):
    cfg = _cfg()
    with pytest.raises(ValueError, match=r"`data` must have shape \(\*, \*, 3\)"):
        dspp.train_shape_prior(np.zeros((5, V)), key=jr.PRNGKey(0), config=cfg)
    with pytest.raises(ValueError, match=r"`data` must have shape \(\*, 20, 3\)"):
        dspp.train_pose_prior(np.zeros((5, 19, 3)), key=jr.PRNGKey(0), config=cfg)
    bad = _shapes()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        dspp.train_shape_prior(bad, key=jr.PRNGKey(0), config=cfg)
    with pytest.raises(ValueError, match="identical"):
        dspp.train_shape_prior(np.ones((4, V, 3)), key=jr.PRNGKey(0), config=cfg)
    with pytest.raises(ValueError, match="`kind`"):
        dspp.train_geometry_gan(_shapes(), kind="mesh", key=jr.PRNGKey(0), config=cfg)
    with pytest.raises(ValueError, match="`config`"):
        dspp.train_shape_prior(_shapes(), key=jr.PRNGKey(0), config={"n_steps": 3})
    with pytest.raises(ValueError, match="batch_size"):
        dspp.DSPPConfig(batch_size=0)
    with pytest.raises(ValueError, match="ae_hidden"):
        dspp.DSPPConfig(ae_hidden=(0,))
    with pytest.raises(ValueError, match="`key`"):
        dspp.train_shape_prior(_shapes(), key=3, config=cfg)
    with pytest.raises(ValueError, match="checkpoint_dir"):
        dspp.train_shape_prior(_shapes(), key=jr.PRNGKey(0), config=cfg,
                               checkpoint_dir=tmp_path / "missing")  # fmt: skip
    sp = dspp.init_aegan("shape", np.zeros((V, 3)), 1.0, cfg, key=getkey())
    with pytest.raises(ValueError, match=r"`x` must have shape \(40, 3\)"):
        sp.encode(jnp.zeros((V + 1, 3)))
    with pytest.raises(ValueError, match=r"`z` must have shape \(4,\)"):
        sp.decode(jnp.zeros(5))
    with pytest.raises(ValueError, match="`n` must be a positive int"):
        dspp.sample(sp, 0, key=jr.PRNGKey(0))
    with pytest.raises(ValueError, match="`model`"):
        dspp.sample("prior", 2, key=jr.PRNGKey(0))
    with pytest.raises(ValueError, match="`n_components`"):
        dspp.fit_pca_prior(_poses(n=5), 5)
    with pytest.raises(ValueError, match="`mode`"):
        dspp.fit_pca_prior(_poses(n=5), 2, mode="laplace")
    with pytest.raises(ValueError, match="`prior`"):
        dspp.save_prior(tmp_path / "x.dspp", object())
    with pytest.raises(ValueError, match="no such file"):
        dspp.load_prior(tmp_path / "none.dspp")


# Files written by the code before the collapse fix (commit 0e2e7e5, x64 on as in this suite):
# `train_pose_prior(_v1_poses(), key=jr.PRNGKey(0), config=DSPPConfig(**V1_CFG, n_steps=20),
# checkpoint_dir=...)` -> the .ckpt,
# `save_prior` of its result -> the .dspp, `dspp.sample(prior, 3, key=jr.PRNGKey(1))` -> the .npy.
DATA = Path(__file__).parent / "data"
V1_CFG = dict(latent_dim=4, noise_dim=4, ae_hidden=(8,), generator_hidden=(8,),
              discriminator_hidden=(8,), batch_size=2, steps_per_call=10,
              checkpoint_every=10)  # fmt: skip


def _v1_poses():
    return (0.3 * np.random.default_rng(0).standard_normal((40, 20, 3))).astype(np.float32)


def test_presets_and_v1_files_load(tmp_path):
    data_dir = DATA
    assert dspp.DSPPConfig.preset("paper") == dspp.DSPPConfig()
    assert dspp.DSPPConfig.preset("shape") == dspp.DSPPConfig()
    pose = dspp.DSPPConfig.preset("pose", n_steps=7)
    assert pose.disc_input_gain == 20.0 and pose.generator_learning_rate == 2e-4
    assert pose.n_steps == 7 and dspp.DSPPConfig.preset("geometry_pose").disc_input_gain == 5.0
    assert dspp.DSPPConfig.from_dict(pose.to_dict()) == pose
    # a prior saved before the fix loads with the paper's values and samples as it did
    prior = dspp.load_prior(data_dir / "dspp_v1_pose_tiny.dspp")
    assert prior.config.disc_input_gain == 1.0 and prior.config.generator_learning_rate is None
    want = np.load(data_dir / "dspp_v1_pose_tiny_samples.npy")
    got = np.asarray(dspp.sample(prior, 3, key=jr.PRNGKey(1)))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)  # float32 ulps across CPUs
    # the gain-1 path of the new training cycle is the old cycle: retraining the fixture's run
    # reproduces the old prior (to float32 ulps: the fixture was written on another CPU)
    cfg = dspp.DSPPConfig(**V1_CFG, n_steps=20)
    fresh = dspp.train_pose_prior(_v1_poses(), key=jr.PRNGKey(0), config=cfg, progress=False)
    for a, b in zip(_leaves(fresh.value), _leaves(prior)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # a checkpoint written before the fix resumes (its config gets the paper's values)
    (tmp_path / "aegan_pose.ckpt").write_bytes(
        (data_dir / "dspp_v1_aegan_pose_tiny.ckpt").read_bytes()
    )
    cfg = dataclasses.replace(cfg, n_steps=30)
    resumed = dspp.train_pose_prior(_v1_poses(), key=jr.PRNGKey(0), config=cfg,
                                    checkpoint_dir=tmp_path, progress=False)  # fmt: skip
    assert resumed.aux.n_steps == 30 and resumed.aux.finite
    np.testing.assert_allclose(resumed.aux.d_loss[:20], fresh.aux.d_loss, rtol=1e-5)
    fresh = dspp.train_pose_prior(_v1_poses(), key=jr.PRNGKey(0), config=cfg, progress=False)
    # the gain is not a no-op: the same run with the pose preset's gain trains differently
    gained = dspp.train_pose_prior(_v1_poses(), key=jr.PRNGKey(0), progress=False,
                                   config=dspp.DSPPConfig(**V1_CFG, n_steps=30,
                                                          disc_input_gain=20.0))  # fmt: skip
    assert not np.array_equal(gained.aux.d_loss, fresh.aux.d_loss)


def test_collapse_monitor_selects_and_resumes(tmp_path):
    data, val = _poses(n=30), _poses(n=12, seed=7)
    cfg = _cfg(monitor_every=5, monitor_samples=8)

    def train(select="best", validation=val, ckpt=None, **kw):
        c = dataclasses.replace(cfg, **kw)
        return dspp.train_pose_prior(data, key=jr.PRNGKey(2), config=c, validation=validation,
                                     select=select,
                                     checkpoint_dir=ckpt, progress=False)  # fmt: skip

    sol = train()
    log = sol.aux
    np.testing.assert_array_equal(log.monitor_step, [5, 10, 15, 20])
    assert np.all((log.monitor_one_nna >= 0) & (log.monitor_one_nna <= 1))
    assert np.all(log.monitor_diversity > 0) and np.all(log.monitor_diversity_ref > 0)
    # diversity_ref is the validation items' own spread (degrees): the same at every check
    assert np.ptp(log.monitor_diversity_ref) == 0
    best = int(sol.stats["best_step"])
    i = list(log.monitor_step).index(best)
    assert np.abs(log.monitor_one_nna[i] - 0.5) == np.min(np.abs(log.monitor_one_nna - 0.5))
    # monitoring never changes training: "last" is the run without validation, bitwise
    last = train(select="last")
    plain = train(validation=None)
    assert plain.aux.monitor.shape == (0, 4) and int(plain.stats["best_step"]) == -1
    for a, b in zip(_leaves(last.value), _leaves(plain.value)):
        np.testing.assert_array_equal(a, b)
    # "best" is the model after `best_step` cycles
    short = train(validation=None, n_steps=best)
    for a, b in zip(_leaves(sol.value), _leaves(short.value)):
        np.testing.assert_array_equal(a, b)
    # an interrupted monitored run resumes with its monitor rows and best model
    train(ckpt=tmp_path, n_steps=10)
    res = train(ckpt=tmp_path)
    np.testing.assert_array_equal(res.aux.monitor, log.monitor)
    assert int(res.stats["best_step"]) == best
    for a, b in zip(_leaves(res.value), _leaves(sol.value)):
        np.testing.assert_array_equal(a, b)
    dspp.plot_train_log(log, tmp_path / "log.png", title="monitor")
    assert (tmp_path / "log.png").stat().st_size > 10_000


@pytest.mark.bad_input
def test_bad_monitor_and_preset_inputs():
    with pytest.raises(ValueError, match="disc_input_gain"):
        dspp.DSPPConfig(disc_input_gain=0.0)
    with pytest.raises(ValueError, match="gan_b1"):
        dspp.DSPPConfig(gan_b1=1.0)
    with pytest.raises(ValueError, match="generator_learning_rate"):
        dspp.DSPPConfig(generator_learning_rate=-1.0)
    with pytest.raises(ValueError, match="monitor_every"):
        dspp.DSPPConfig(monitor_every=0)
    with pytest.raises(ValueError, match="generator_ema"):
        dspp.DSPPConfig(generator_ema=1.0)
    with pytest.raises(ValueError, match="generator_ema"):
        dspp.DSPPConfig(generator_ema=True)
    with pytest.raises(ValueError, match="`name`"):
        dspp.DSPPConfig.preset("vposer")
    cfg = _cfg()
    with pytest.raises(ValueError, match="`select`"):
        dspp.train_pose_prior(_poses(), key=jr.PRNGKey(0), config=cfg, select="first")
    with pytest.raises(ValueError, match=r"`validation` must have shape \(\*, 20, 3\)"):
        dspp.train_pose_prior(_poses(), key=jr.PRNGKey(0), config=cfg,
                              validation=np.zeros((4, 19, 3)))  # fmt: skip
    with pytest.raises(ValueError, match="at least 2"):
        dspp.train_pose_prior(_poses(), key=jr.PRNGKey(0), config=cfg,
                              validation=np.zeros((1, 20, 3)))  # fmt: skip


@pytest.mark.parametrize("which", ["aegan_pose", "geomgan_pose"])
def test_generator_ema_averages_without_changing_training(tmp_path, which):
    # generator_ema = d: the returned generator is d * (before) + (1 - d) * (after the step) per
    # weight after one cycle, the rest of the model is the plain run's, and a resumed run equals
    # an uninterrupted one (the average is in the checkpoint).
    def train(steps, ema, ckpt=None):
        cfg = _cfg(n_steps=steps, generator_ema=ema, steps_per_call=1, checkpoint_every=1)
        if which == "aegan_pose":
            sol = dspp.train_pose_prior(_poses(), key=jr.PRNGKey(3), config=cfg,
                                        checkpoint_dir=ckpt, progress=False)  # fmt: skip
        else:
            sol = dspp.train_geometry_gan(_poses(), kind="pose", key=jr.PRNGKey(3), config=cfg,
                                          checkpoint_dir=ckpt, progress=False)  # fmt: skip
        return sol.value

    init, plain, avg = train(0, 0.0), train(1, 0.0), train(1, 0.3)
    for g0, g1, ge in zip(_leaves(init.generator), _leaves(plain.generator),
                          _leaves(avg.generator)):  # fmt: skip
        np.testing.assert_allclose(ge, 0.3 * g0 + 0.7 * g1, rtol=1e-6, atol=1e-7)
    assert any(not np.array_equal(a, b) for a, b in
               zip(_leaves(init.generator), _leaves(plain.generator)))  # fmt: skip
    for a, b in zip(_leaves(plain.discriminator), _leaves(avg.discriminator)):
        np.testing.assert_array_equal(a, b)
    full = train(3, 0.5)
    train(2, 0.5, tmp_path)
    resumed = train(3, 0.5, tmp_path)
    for a, b in zip(_leaves(full), _leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    # the field round-trips through a prior file
    dspp.save_prior(tmp_path / "p.dspp", full)
    assert dspp.load_prior(tmp_path / "p.dspp").config.generator_ema == 0.5
