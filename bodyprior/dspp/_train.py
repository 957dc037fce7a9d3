"""Training DSPP priors (paper §3.3) and the geometry-space GAN baselines.

One training cycle, as the paper: (1) an auto-encoder step on a random real sample (eq. 1 / 2,
squared Frobenius reconstruction error); (2) a discriminator step on the *updated* encoder's codes
of those samples against generated codes; (3) a generator step against the *updated* discriminator
with the non-saturating loss `-E log D(G(n))` (eqs. 3-4). Three Adam optimisers with default
settings (lr 1e-3, betas 0.9/0.999, eps 1e-8; optax). The geometry baselines skip (1) and
discriminate geometry instead of codes.

The whole cycle is one pure function; `steps_per_call` cycles run in one jitted `lax.scan`;
progress (tqdm) and checkpoints happen between calls. Everything is a deterministic function of the
key, and the call boundaries are a fixed function of the step (multiples of `steps_per_call` and of
`checkpoint_every`), so a run resumed from a checkpoint performs exactly the same jitted calls on
the same state as an uninterrupted one and ends with bitwise-identical parameters.

Networks run in float32 whatever `jax_enable_x64` says; data are normalised on the host in float64
(`(x - mean) / scale`, with `scale` the RMS coordinate deviation of the training set).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float
from tqdm.auto import tqdm

from .._solution import RESULTS, Solution, _check
from .._validate import check_array
from ._nets import (
    DSPPConfig,
    GeometryGAN,
    PosePrior,
    ShapePrior,
    geometry_disc_input,
    init_aegan,
    init_geometry_gan,
)

__all__ = ["TrainLog", "train_shape_prior", "train_pose_prior", "train_geometry_gan"]

# Columns of the per-step record.
_COLUMNS = ("ae_loss", "d_loss", "g_loss", "d_real", "d_fake")


class TrainLog(eqx.Module):
    """Per-cycle training record (host NumPy arrays, one entry per cycle), and the collapse
    monitor's evaluations.

    **Fields:**

    - `ae_loss`: reconstruction loss, eq. (1)/(2): squared Frobenius norm per sample (m² for shapes,
      rad² for poses), batch mean; shape `(S,)` (NaN for the geometry baselines, which have no AE).
    - `d_loss`: discriminator loss `-log D(real) - log(1 - D(fake))`, batch means, `(S,)`.
    - `g_loss`: non-saturating generator loss `-log D(G(n))`, `(S,)`.
    - `d_real`, `d_fake`: mean discriminator probabilities on the real and generated batch, `(S,)`.
    - `wall_time_s`: seconds spent training in this call (not the time of runs before a resume).
    - `finite`: whether every recorded loss is finite.
    - `monitor`: the collapse monitor, `(M, 4)` rows `(cycle, one_nna, diversity,
      diversity_ref)` (empty without `validation`): 1-NNA of `config.monitor_samples` generated
      items, always from the same noise, against as many fixed validation items (0.5 ideal, 1 = a
      collapse), the generated items' diversity (average pairwise distance) and the validation
      items' (diversity in degrees of mean per-joint geodesic angle for poses, mm of mean vertex
      distance for shapes). Properties `monitor_step`, `monitor_one_nna`, `monitor_diversity`,
      `monitor_diversity_ref` give the columns.
    """

    ae_loss: np.ndarray
    d_loss: np.ndarray
    g_loss: np.ndarray
    d_real: np.ndarray
    d_fake: np.ndarray
    wall_time_s: float = eqx.field(static=True)
    finite: bool = eqx.field(static=True)
    monitor: np.ndarray = eqx.field(default_factory=lambda: np.zeros((0, 4)))

    @property
    def n_steps(self) -> int:
        return int(self.d_loss.shape[0])

    @property
    def monitor_step(self) -> np.ndarray:
        return self.monitor[:, 0].astype(np.int64)

    @property
    def monitor_one_nna(self) -> np.ndarray:
        return self.monitor[:, 1]

    @property
    def monitor_diversity(self) -> np.ndarray:
        return self.monitor[:, 2]

    @property
    def monitor_diversity_ref(self) -> np.ndarray:
        return self.monitor[:, 3]

    @staticmethod
    def from_records(records: np.ndarray, wall_time_s: float, monitor=None) -> TrainLog:
        cols = [np.asarray(records[:, i], np.float64) for i in range(len(_COLUMNS))]
        finite = bool(np.all(np.isfinite(records[:, 1:])) and np.all(~np.isinf(records[:, 0])))
        mon = np.zeros((0, 4)) if monitor is None else np.asarray(monitor, np.float64)
        return TrainLog(*cols, wall_time_s=float(wall_time_s), finite=finite, monitor=mon)


class _Monitor:
    """Host-side collapse monitor: 1-NNA and diversity of a fixed generated sample (the same noise
    at every evaluation) against fixed validation items, in the kind's distance (degrees for
    poses, mm for shapes). Keeps the model with the validation 1-NNA closest to 0.5."""

    def __init__(self, validation: np.ndarray, kind: str, cfg: DSPPConfig, key):
        from .._metrics import mean_vertex_distance_metric, pose_geodesic_metric

        n = min(cfg.monitor_samples, validation.shape[0])
        rng = np.random.default_rng(np.asarray(key).astype(np.int64).tolist())
        self.ref = validation[rng.choice(validation.shape[0], n, replace=False)]
        self.n = n
        self.key = jr.fold_in(key, 0x6D6F6E)  # not a key the training loop ever draws
        pose = kind == "pose"
        self.metric = pose_geodesic_metric if pose else mean_vertex_distance_metric
        self.unit = float(np.degrees(1.0)) if pose else 1e3
        self.rows: list[np.ndarray] = []
        self.best = None
        self.best_step = -1

    def restore(self, rows: np.ndarray, best, best_step: int) -> None:
        self.rows = [r for r in np.asarray(rows, np.float64)]
        self.best, self.best_step = best, int(best_step)

    def __call__(self, model, step: int) -> np.ndarray:
        from .._metrics import generative_metrics
        from ._sample import sample

        gen = np.asarray(sample(model, self.n, key=self.key), np.float64)
        if not np.all(np.isfinite(gen)):
            row = np.array([step, 1.0, np.nan, np.nan])
        else:
            m = generative_metrics(gen, self.ref, self.metric)
            row = np.array([step, m["one_nna"], m["diversity"] * self.unit,
                            m["diversity_ref"] * self.unit])  # fmt: skip
        score = abs(row[1] - 0.5)
        if self.best is None or score < abs(self.rows_array()[:, 1] - 0.5).min():
            self.best, self.best_step = model, int(step)
        self.rows.append(row)
        return row

    def rows_array(self) -> np.ndarray:
        return np.stack(self.rows) if self.rows else np.zeros((0, 4))


class _TrainState(eqx.Module):
    model: ShapePrior | PosePrior | GeometryGAN
    opt_ae: optax.OptState | None
    opt_d: optax.OptState
    opt_g: optax.OptState
    key: Array
    step: Array
    gen_ema: Any = None  # the averaged generator (`generator_ema` > 0), else None

    def output_model(self):
        """The model to sample: with the averaged generator when there is one."""
        if self.gen_ema is None:
            return self.model
        return dataclasses.replace(self.model, generator=self.gen_ema)


def _ema_update(ts: _TrainState, gen, cfg: DSPPConfig):
    if ts.gen_ema is None:
        return None
    d = cfg.generator_ema
    avg = jax.tree_util.tree_map(
        lambda e, g: d * e + (1.0 - d) * g, _params(ts.gen_ema), _params(gen)
    )
    return eqx.combine(avg, gen)


def _adam(cfg: DSPPConfig, part: str) -> optax.GradientTransformation:
    """Adam of one part: "ae" (defaults), "d" / "g" (first-moment decay `gan_b1`; the generator's
    step size `generator_learning_rate` when set)."""
    if part == "ae":
        return optax.adam(cfg.learning_rate)
    lr = cfg.learning_rate
    if part == "g" and cfg.generator_learning_rate is not None:
        lr = cfg.generator_learning_rate
    return optax.adam(lr, b1=cfg.gan_b1)


def _params(tree):
    return eqx.filter(tree, eqx.is_inexact_array)


def _vmap_disc(disc, state, inference):
    # One power iteration per call, whatever the batch size: the SN state does not depend on the
    # input, so it leaves the vmap unbatched.
    return jax.vmap(lambda x: disc(x, state, inference=inference), out_axes=(0, None))


def _d_loss(disc, state, real_in, fake_in):
    logits, state = _vmap_disc(disc, state, False)(jnp.concatenate([real_in, fake_in]))
    b = real_in.shape[0]
    lr, lf = logits[:b], logits[b:]
    loss = -jnp.mean(jax.nn.log_sigmoid(lr)) - jnp.mean(jax.nn.log_sigmoid(-lf))
    return loss, (state, jnp.mean(jax.nn.sigmoid(lr)), jnp.mean(jax.nn.sigmoid(lf)))


def _aegan_cycle(ts: _TrainState, data: Float[Array, "N D"], cfg: DSPPConfig):
    m = ts.model
    gain = cfg.disc_input_gain
    key, k_idx, k_d, k_g = jr.split(ts.key, 4)
    b = cfg.batch_size
    x = data[jr.randint(k_idx, (b,), 0, data.shape[0])]

    # (1) auto-encoder step on real samples
    def ae_loss(ed):
        enc, dec = ed
        xr = jax.vmap(lambda u: dec(enc(u)))(x)
        return jnp.mean(jnp.sum((xr - x) ** 2, axis=-1))

    l_ae, g = eqx.filter_value_and_grad(ae_loss)((m.encoder, m.decoder))
    upd, opt_ae = _adam(cfg, "ae").update(g, ts.opt_ae)
    enc, dec = eqx.apply_updates((m.encoder, m.decoder), upd)

    # (2) discriminator step: updated embeddings vs generated codes
    z_real = jax.lax.stop_gradient(jax.vmap(enc)(x))
    noise = jr.normal(k_d, (b, cfg.noise_dim), x.dtype)
    z_fake = jax.lax.stop_gradient(jax.vmap(m.generator)(noise))
    (l_d, (state, p_real, p_fake)), g = eqx.filter_value_and_grad(_d_loss, has_aux=True)(
        m.discriminator, m.disc_state, gain * z_real, gain * z_fake
    )
    upd, opt_d = _adam(cfg, "d").update(g, ts.opt_d)
    disc = eqx.apply_updates(m.discriminator, upd)

    # (3) generator step against the updated discriminator (its SN state frozen for this step)
    noise = jr.normal(k_g, (b, cfg.noise_dim), x.dtype)

    def g_loss(gen):
        logits, _ = _vmap_disc(disc, state, True)(gain * jax.vmap(gen)(noise))
        return -jnp.mean(jax.nn.log_sigmoid(logits))

    l_g, g = eqx.filter_value_and_grad(g_loss)(m.generator)
    upd, opt_g = _adam(cfg, "g").update(g, ts.opt_g)
    gen = eqx.apply_updates(m.generator, upd)

    # dataclasses.replace, not tree_at: the old SN state object is spent and must not be flattened.
    m = dataclasses.replace(
        m, encoder=enc, decoder=dec, generator=gen, discriminator=disc, disc_state=state
    )
    rec = jnp.stack([l_ae * m.scale**2, l_d, l_g, p_real, p_fake]).astype(jnp.float32)
    return _TrainState(m, opt_ae, opt_d, opt_g, key, ts.step + 1, _ema_update(ts, gen, cfg)), rec


def _geometry_cycle(ts: _TrainState, data: Float[Array, "N D"], cfg: DSPPConfig):
    m = ts.model
    key, k_idx, k_d, k_g = jr.split(ts.key, 4)
    b = cfg.batch_size
    x = data[jr.randint(k_idx, (b,), 0, data.shape[0])]
    # Not the bound method m._disc_input: m's SN state is spent after the discriminator step.
    geo_in = functools.partial(geometry_disc_input, m.kind, m.mean, m.scale, m.centre, m.radius)

    def disc_in(u):
        return cfg.disc_input_gain * geo_in(u)

    to_disc = jax.vmap(disc_in)
    n_vert = m.mean.shape[0]
    if m.kind == "shape" and cfg.pointnet_points < n_vert:
        # PointNet sees a random vertex subset, the same for the real and the generated shapes.
        key, k_pts = jr.split(key)
        pts = jr.choice(k_pts, n_vert, (cfg.pointnet_points,), replace=False)
        to_disc = jax.vmap(lambda u: disc_in(u)[pts])

    noise = jr.normal(k_d, (b, cfg.noise_dim), x.dtype)
    u_fake = jax.lax.stop_gradient(jax.vmap(m.generator)(noise))
    (l_d, (state, p_real, p_fake)), g = eqx.filter_value_and_grad(_d_loss, has_aux=True)(
        m.discriminator, m.disc_state, to_disc(x), to_disc(u_fake)
    )
    upd, opt_d = _adam(cfg, "d").update(g, ts.opt_d)
    disc = eqx.apply_updates(m.discriminator, upd)

    noise = jr.normal(k_g, (b, cfg.noise_dim), x.dtype)

    def g_loss(gen):
        logits, _ = _vmap_disc(disc, state, True)(to_disc(jax.vmap(gen)(noise)))
        return -jnp.mean(jax.nn.log_sigmoid(logits))

    l_g, g = eqx.filter_value_and_grad(g_loss)(m.generator)
    upd, opt_g = _adam(cfg, "g").update(g, ts.opt_g)
    gen = eqx.apply_updates(m.generator, upd)

    m = dataclasses.replace(m, generator=gen, discriminator=disc, disc_state=state)
    nan = jnp.full((), jnp.nan, jnp.float32)
    rec = jnp.stack([nan, l_d, l_g, p_real, p_fake]).astype(jnp.float32)
    return _TrainState(m, None, opt_d, opt_g, key, ts.step + 1, _ema_update(ts, gen, cfg)), rec


@eqx.filter_jit
def _run_chunk(ts: _TrainState, data, n: int, cfg: DSPPConfig, cycle):
    def body(carry, _):
        return cycle(carry, data, cfg)

    return jax.lax.scan(body, ts, None, length=n)


def _raw_key(key) -> Array:
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jr.key_data(key)
    if key.shape != (2,) or key.dtype != jnp.uint32:
        raise ValueError(
            "`key` must be a jax.random key (PRNGKey: uint32 shape (2,)), got "
            f"{key.dtype} {key.shape}."
        )
    return key


def _init_state(kind: str, model_kind: str, mean, scale, cfg: DSPPConfig, key) -> _TrainState:
    k_init, k_train = jr.split(key)
    if model_kind == "aegan":
        model = init_aegan(kind, mean, scale, cfg, key=k_init)
    else:
        model = init_geometry_gan(kind, mean, scale, cfg, key=k_init)
    opt_ae = None
    if model_kind == "aegan":
        opt_ae = _adam(cfg, "ae").init(_params((model.encoder, model.decoder)))
    return _TrainState(
        model, opt_ae, _adam(cfg, "d").init(_params(model.discriminator)),
        _adam(cfg, "g").init(_params(model.generator)), k_train, jnp.zeros((), jnp.int32),
        model.generator if cfg.generator_ema > 0 else None,
    )  # fmt: skip


def _prepare(data, name: str, item_shape: tuple) -> tuple[np.ndarray, np.ndarray, float]:
    check_array(data, name, (None, *item_shape))
    x = np.asarray(data, np.float64)
    if x.shape[0] < 2:
        raise ValueError(f"`{name}` must hold at least 2 samples, got {x.shape[0]}.")
    mean = x.mean(0)
    scale = float(np.sqrt(np.mean((x - mean) ** 2)))
    if not scale > 0:
        raise ValueError(f"`{name}`: all samples are identical; nothing to learn.")
    u = ((x - mean) / scale).reshape(x.shape[0], -1).astype(np.float32)
    return u, mean, scale


def _train(
    data, kind: str, model_kind: str, *, key, config, checkpoint_dir, progress, throw, name: str,
    validation=None, select: str = "best",
):  # fmt: skip
    from ._checkpoint import load_checkpoint, save_checkpoint  # circular-free lazy import

    if not isinstance(config, DSPPConfig):
        raise ValueError(f"`config` must be a DSPPConfig, got {type(config).__name__}.")
    if select not in ("best", "last"):
        raise ValueError(f"`select` must be 'best' or 'last', got {select!r}.")
    key = _raw_key(key)
    item_shape = (None, 3) if kind == "shape" else (20, 3)
    u, mean, scale = _prepare(data, name, item_shape)
    monitor = None
    if validation is not None:
        check_array(validation, "validation", (None, *np.shape(data)[1:]))
        if np.shape(validation)[0] < 2:
            raise ValueError(
                f"`validation` must hold at least 2 items, got {np.shape(validation)[0]}."
            )
        monitor = _Monitor(np.asarray(validation, np.float64), kind, config, key)
    cfg = config
    ts = _init_state(kind, model_kind, mean, scale, cfg, key)
    records = np.zeros((0, len(_COLUMNS)), np.float32)
    tag = f"{model_kind}_{kind}"
    if checkpoint_dir is not None:
        restored = load_checkpoint(checkpoint_dir, tag, ts, cfg, key, u)
        if restored is not None:
            ts, records, mon_rows, best, best_step = restored
            if monitor is not None:
                monitor.restore(mon_rows, best, best_step)
    u_dev = jnp.asarray(u)
    step = int(ts.step)
    if step > cfg.n_steps:
        raise ValueError(
            f"The checkpoint in {checkpoint_dir!r} is at step {step}, beyond `n_steps` "
            f"{cfg.n_steps}."
        )
    every = max(
        cfg.steps_per_call, (cfg.checkpoint_every // cfg.steps_per_call) * cfg.steps_per_call
    )
    mon_every = max(
        cfg.steps_per_call, (cfg.monitor_every // cfg.steps_per_call) * cfg.steps_per_call
    )
    cycle = _aegan_cycle if model_kind == "aegan" else _geometry_cycle
    chunks = [records]
    result = RESULTS.successful
    t0 = time.perf_counter()
    with tqdm(total=cfg.n_steps, initial=step, desc=f"training {tag}", disable=not progress,
              unit="step") as bar:  # fmt: skip
        while step < cfg.n_steps:
            # Call boundaries depend on the step only, never on where a run was interrupted.
            n = min(cfg.steps_per_call - step % cfg.steps_per_call, every - step % every,
                    cfg.n_steps - step)  # fmt: skip
            ts, rec = _run_chunk(ts, u_dev, n, cfg, cycle)
            rec = np.asarray(rec)
            chunks.append(rec)
            step += n
            bar.update(n)
            if progress:
                bar.set_postfix(
                    {k: f"{v:.3g}" for k, v in zip(_COLUMNS[:3], rec[-min(n, 100):].mean(0))
                     if model_kind == "aegan" or k != "ae_loss"}
                )  # fmt: skip
            bad = not np.all(np.isfinite(rec[:, 1:])) or (
                model_kind == "aegan" and not np.all(np.isfinite(rec[:, 0]))
            )
            if bad:
                result = RESULTS.nonfinite_loss
                # Raises here (the one throw rule); with throw=False training stops here.
                _check(Solution(ts.model, result, {}), throw,
                       f"training {tag} (non-finite loss in steps {step - n}..{step})")  # fmt: skip
                break
            if monitor is not None and (step % mon_every == 0 or step == cfg.n_steps):
                row = monitor(ts.output_model(), step)
                if progress:
                    bar.write(f"{tag} cycle {step}: validation 1-NNA {row[1]:.3f}, diversity "
                              f"{row[2]:.1f} (validation {row[3]:.1f})")  # fmt: skip
            if checkpoint_dir is not None and (step % every == 0 or step == cfg.n_steps):
                mon = (monitor.rows_array(), monitor.best, monitor.best_step) if monitor else None
                save_checkpoint(checkpoint_dir, tag, ts, cfg, key, u, np.concatenate(chunks),
                                monitor=mon)  # fmt: skip
    mon_rows = monitor.rows_array() if monitor is not None else None
    log = TrainLog.from_records(np.concatenate(chunks), time.perf_counter() - t0, mon_rows)
    value, best_step = ts.output_model(), -1
    if monitor is not None and monitor.best is not None:
        best_step = monitor.best_step
        if select == "best":
            value = monitor.best
    stats = {"num_steps": np.asarray(log.n_steps), "best_step": np.asarray(best_step)}
    return Solution(value, result, stats, log)


def train_shape_prior(
    data: Float[ArrayLike, "N V 3"],
    *,
    key,
    config: DSPPConfig | None = None,
    checkpoint_dir=None,
    progress: bool = True,
    throw: bool = True,
    validation=None,
    select: str = "best",
) -> Solution:
    """Trains a DSPP shape prior (shape auto-encoder + GAN in its latent space).

    **Arguments:**

    - `data`: training shapes `(N, V, 3)` in vertex correspondence, metres (e.g. a population on the
      decimated topology, `pop.vertices[:, vertex_map]`).
    - `key`: a `jax.random` key; the result is a deterministic function of it, `data` and `config`.
    - `config`: a [`bodyprior.dspp.DSPPConfig`][] (sizes, `n_steps`, `batch_size`, ...); `None`
      is `DSPPConfig.preset("shape")`, the paper's recipe.
    - `checkpoint_dir`: optional existing directory. A checkpoint `aegan_shape.ckpt` is written
      atomically every `config.checkpoint_every` cycles and at the end; if one is there (same
      data, key and network sizes), training resumes from it. `n_steps` may be raised to continue.
    - `validation`: optional held-out items shaped like `data` for the collapse monitor: every
      `config.monitor_every` cycles and at the end, `config.monitor_samples` items generated from
      fixed noise are scored against as many fixed validation items (1-NNA, diversity; in
      `log.monitor` and the progress bar). Not used for training.
    - `select`: with `validation`, `"best"` (default) returns the monitored model whose validation
      1-NNA is closest to 0.5 (`stats["best_step"]` says which cycle), `"last"` the final one.
    - `progress`: show a tqdm progress bar.
    - `throw`: raise on a non-finite loss (`RESULTS.nonfinite_loss`, the rule of
      [`bodyprior.Solution`][]); with `False` training stops there, `sol.result` is
      `RESULTS.nonfinite_loss` and the log says `finite=False`. Running all `n_steps` is success.

    **Returns:** a [`bodyprior.Solution`][]: `value` the [`bodyprior.dspp.ShapePrior`][], `aux`
    the [`bodyprior.dspp.TrainLog`][], `stats` `{"num_steps": cycles recorded, "best_step": the
    monitor's best cycle (validation 1-NNA closest to 0.5; the returned model's cycle only with
    `select="best"`; with `"last"` the returned model is the last cycle's) or -1 without
    `validation`}`.
    """
    config = DSPPConfig.preset("shape") if config is None else config
    return _train(data, "shape", "aegan", key=key, config=config, checkpoint_dir=checkpoint_dir,
                  progress=progress, throw=throw, name="data", validation=validation,
                  select=select)  # fmt: skip


def train_pose_prior(
    data: Float[ArrayLike, "N 20 3"],
    *,
    key,
    config: DSPPConfig | None = None,
    checkpoint_dir=None,
    progress: bool = True,
    throw: bool = True,
    validation=None,
    select: str = "best",
) -> Solution:
    """Trains a DSPP pose prior on Euler angles `(N, 20, 3)` (radians, `EULER_ORDER`, joints
    `POSE_JOINTS`, e.g. `PoseSet.euler`). Arguments and checkpointing (`aegan_pose.ckpt`) as
    [`bodyprior.dspp.train_shape_prior`][]; `config=None` is `DSPPConfig.preset("pose")` (the
    paper's recipe, `DSPPConfig()`, collapses to one pose on mocap: docs/results_dspp.md).
    **Returns:** a [`bodyprior.Solution`][] (`value` the `PosePrior`, `aux` the `TrainLog`)."""
    config = DSPPConfig.preset("pose") if config is None else config
    return _train(data, "pose", "aegan", key=key, config=config, checkpoint_dir=checkpoint_dir,
                  progress=progress, throw=throw, name="data", validation=validation,
                  select=select)  # fmt: skip


def train_geometry_gan(
    data,
    *,
    kind: str,
    key,
    config: DSPPConfig | None = None,
    checkpoint_dir=None,
    progress: bool = True,
    throw: bool = True,
    validation=None,
    select: str = "best",
) -> Solution:
    """Trains the geometry-space GAN baseline (paper Fig. 4): a generator that outputs geometry,
    against a discriminator on the geometry (PointNet for `kind="shape"`, data `(N, V, 3)`; MLP on
    Euler angles for `kind="pose"`, data `(N, 20, 3)`). Same cycle minus the auto-encoder step;
    other arguments and checkpointing (`geomgan_<kind>.ckpt`) as
    [`bodyprior.dspp.train_shape_prior`][]; `config=None` is `DSPPConfig.preset("shape")` or
    `DSPPConfig.preset("geometry_pose")`. **Returns:** a [`bodyprior.Solution`][] (`value` the
    `GeometryGAN`, `aux` the `TrainLog`; `log.ae_loss` is NaN)."""
    if kind not in ("shape", "pose"):
        raise ValueError(f"`kind` must be 'shape' or 'pose', got {kind!r}.")
    if config is None:
        config = DSPPConfig.preset("shape" if kind == "shape" else "geometry_pose")
    return _train(data, kind, "geomgan", key=key, config=config, checkpoint_dir=checkpoint_dir,
                  progress=progress, throw=throw, name="data", validation=validation,
                  select=select)  # fmt: skip


def plot_train_log(log: TrainLog, path, *, title: str = "", smooth: int = 0) -> None:
    """Saves the loss curves of one training run as a PNG (paper Figs. 5-6): the reconstruction loss
    (log scale, when there is one), the discriminator / generator losses against the cycle, and,
    when the log has one, the collapse monitor (validation 1-NNA and diversity).
    `smooth`: moving-average window (0 = about 1% of the run)."""
    import matplotlib

    matplotlib.use("Agg")
    import io

    import matplotlib.pyplot as plt

    from .._io import atomic_write_bytes

    if not isinstance(log, TrainLog):
        raise ValueError(f"`log` must be a TrainLog, got {type(log).__name__}.")
    s = log.n_steps
    if s == 0:
        raise ValueError("`log` is empty (0 steps).")
    w = int(smooth) if smooth else max(1, s // 100)
    steps = np.arange(1, s + 1)

    def ma(y):
        if w <= 1:
            return y
        c = np.cumsum(np.insert(np.nan_to_num(y), 0, 0.0))
        out = (c[w:] - c[:-w]) / w
        return np.concatenate([np.full(w - 1, np.nan), out])

    has_ae = bool(np.any(np.isfinite(log.ae_loss)))
    has_mon = log.monitor.shape[0] > 0
    n_ax = 1 + has_ae + has_mon
    fig, axes = plt.subplots(1, n_ax, figsize=(4.5 * n_ax, 3.2), dpi=90, squeeze=False)
    axes = list(axes[0])
    if has_mon:
        ax = axes.pop()
        st = log.monitor_step
        ax.plot(st, log.monitor_one_nna, "o-", color="C0", ms=3, lw=1.2, label="1-NNA")
        ax.axhline(0.5, color="0.5", lw=0.6, ls="--")
        ax.set_ylim(0.4, 1.02)
        ax.set_xlabel("training cycle")
        ax.set_ylabel("validation 1-NNA (0.5 ideal)", color="C0")
        ax2 = ax.twinx()
        ax2.plot(st, log.monitor_diversity, "s-", color="C1", ms=3, lw=1.2, label="samples")
        ax2.plot(st, log.monitor_diversity_ref, color="C1", lw=0.8, ls=":", label="validation")
        ax2.set_ylabel("diversity", color="C1")
        ax2.set_ylim(bottom=0)
        ax2.legend(fontsize=7, loc="lower right")
        ax.set_title("collapse monitor")
    if has_ae:
        ax = axes[0]
        ax.plot(steps, log.ae_loss, color="0.8", lw=0.5)
        ax.plot(steps, ma(log.ae_loss), color="C0", lw=1.2)
        ax.set_yscale("log")
        ax.set_xlabel("training cycle")
        ax.set_ylabel("reconstruction loss (eq. 1/2)")
        ax.set_title("encoder / decoder")
    ax = axes[-1]
    for y, c, lab in ((log.d_loss, "C3", "discriminator"), (log.g_loss, "C2", "generator")):
        ax.plot(steps, y, color=c, lw=0.3, alpha=0.25)
        ax.plot(steps, ma(y), color=c, lw=1.2, label=lab)
    ax.axhline(2 * np.log(2), color="0.5", lw=0.6, ls="--")
    ax.axhline(np.log(2), color="0.5", lw=0.6, ls=":")
    ax.set_xlabel("training cycle")
    ax.set_ylabel("GAN loss (nats)")
    ax.set_title("discriminator / generator")
    ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
