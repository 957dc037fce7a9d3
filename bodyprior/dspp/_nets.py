"""DSPP networks (Hu, Shum & Mucherino 2019, §3.3 and Figs. 2-4) in equinox.

Every network here works on ONE example (batch with `jax.vmap`). Encoders, decoders and generators
are fully connected with PReLU activations (one learnable slope per layer, PyTorch's `nn.PReLU()`
default, initial slope 0.25); discriminators use ReLU and wrap **every** linear map in
`eqx.nn.SpectralNorm` (Miyato et al. 2018, one power iteration per training call), so they are
stateful: they take and return an `eqx.nn.State` holding the power-iteration vectors.

Layer sizes. The paper gives them only in its Figures 2-4, which the available text lost, so these
are our choices (all configurable through [`bodyprior.dspp.DSPPConfig`][]):

| network | default layers |
|---|---|
| shape encoder | 3V -> 128 -> 64 -> 32 (V = 6,449 decimated vertices) |
| shape decoder | 32 -> 64 -> 128 -> 3V |
| pose encoder / decoder | 60 -> 128 -> 64 -> 32 / mirrored |
| generators (shape, pose) | N(0, I_32) -> 128 -> 128 -> 32 |
| latent discriminators | 32 -> 128 -> 128 -> 1 (ReLU, SN) |
| baseline shape disc. | PointNet: per-vertex 3 -> 64 -> 128 shared MLP, max-pool, 128 -> 128 -> 1 |
| (training input) | 1,024 random vertices per cycle (all vertices in `GeometryGAN.logit`) |
| baseline pose discriminator | 60 -> 256 -> 256 -> 1 on the Euler angles |
| baseline generators | N(0, I_32) -> 128 -> 256 -> 3V (or 60): like a generator + a decoder |

The widths are small because the shape encoder's first and the decoder's last layer dominate the
cost (3V x 128 = 2.5 M weights each): one training cycle at batch 1 is memory-bound on these two
matrices (forward, backward and the Adam update stream them several times), about 2.5x slower with
256 (see `docs/benchmarks.md`). The bottleneck is the 32-dimensional code either way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._validate import check_array, is_tracer, named_preset


class PReLU(eqx.Module):
    """Parametric ReLU with one learnable slope (He et al. 2015; PyTorch `nn.PReLU()`)."""

    slope: Float[Array, ""]

    def __init__(self, init: float = 0.25, dtype=jnp.float32):
        self.slope = jnp.asarray(init, dtype=dtype)

    def __call__(self, x: Array) -> Array:
        return jnp.where(x >= 0, x, self.slope * x)


class PReLUMLP(eqx.Module):
    """Fully connected network `sizes[0] -> ... -> sizes[-1]` with PReLU after every hidden layer
    (the output layer is linear). Used for encoders, decoders and generators."""

    layers: tuple[eqx.nn.Linear, ...]
    activations: tuple[PReLU, ...]

    def __init__(self, sizes: Sequence[int], *, key: PRNGKeyArray, dtype=jnp.float32):
        sizes = tuple(int(s) for s in sizes)
        if len(sizes) < 2 or min(sizes) < 1:
            raise ValueError(f"`sizes` must hold at least two positive ints, got {sizes}.")
        keys = jr.split(key, len(sizes) - 1)
        self.layers = tuple(
            eqx.nn.Linear(a, b, key=k, dtype=dtype) for a, b, k in zip(sizes[:-1], sizes[1:], keys)
        )
        self.activations = tuple(PReLU(dtype=dtype) for _ in sizes[1:-1])

    def __call__(self, x: Float[ArrayLike, " n_in"]) -> Float[Array, " n_out"]:
        for layer, act in zip(self.layers[:-1], self.activations):
            x = act(layer(x))
        return self.layers[-1](x)


class SNMLP(eqx.Module):
    """Fully connected ReLU network whose every linear map is spectrally normalised.

    `__call__(x, state, *, inference=None) -> (y, state)`: in training mode (`inference=False`) each
    call runs one power iteration per layer and returns the updated state; with `inference=True` the
    stored singular vectors are used as they are.
    """

    layers: tuple[eqx.nn.SpectralNorm, ...]
    final_relu: bool = eqx.field(static=True)

    def __init__(
        self,
        sizes: Sequence[int],
        *,
        key: PRNGKeyArray,
        final_relu: bool = False,
        dtype=jnp.float32,
    ):
        sizes = tuple(int(s) for s in sizes)
        if len(sizes) < 2 or min(sizes) < 1:
            raise ValueError(f"`sizes` must hold at least two positive ints, got {sizes}.")
        keys = jr.split(key, 2 * (len(sizes) - 1))
        self.layers = tuple(
            eqx.nn.SpectralNorm(
                eqx.nn.Linear(a, b, key=keys[2 * i], dtype=dtype), "weight", key=keys[2 * i + 1]
            )
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:]))
        )
        self.final_relu = final_relu

    def __call__(self, x: Float[ArrayLike, " n_in"], state: eqx.nn.State, *, inference=None):
        n = len(self.layers)
        for i, layer in enumerate(self.layers):
            x, state = layer(x, state, inference=inference)
            if i < n - 1 or self.final_relu:
                x = jax.nn.relu(x)
        return x, state


class LatentDiscriminator(eqx.Module):
    """Discriminator in an auto-encoding space: code `(d,)` -> logit `()` (higher = more real)."""

    mlp: SNMLP

    def __init__(self, latent_dim: int, hidden: Sequence[int], *, key, dtype=jnp.float32):
        self.mlp = SNMLP((latent_dim, *hidden, 1), key=key, dtype=dtype)

    def __call__(self, z: Float[ArrayLike, " d"], state, *, inference=None):
        y, state = self.mlp(z, state, inference=inference)
        return y[0], state


class PointNetDiscriminator(eqx.Module):
    """Geometry-space shape discriminator (paper Fig. 4 left; Qi et al. 2017): a shared per-point
    MLP, max-pooling over the points for global context, then an MLP to one logit. Input: points
    `(V, 3)` (already normalised by the caller)."""

    point_mlp: SNMLP
    head: SNMLP

    def __init__(
        self, point_hidden: Sequence[int], head_hidden: Sequence[int], *, key, dtype=jnp.float32
    ):
        k1, k2 = jr.split(key)
        self.point_mlp = SNMLP((3, *point_hidden), key=k1, final_relu=True, dtype=dtype)
        self.head = SNMLP((point_hidden[-1], *head_hidden, 1), key=k2, dtype=dtype)

    def __call__(self, points: Float[ArrayLike, "V 3"], state, *, inference=None):
        # The power iteration does not depend on the input, so the state leaving the vmap over
        # points is unbatched (out_axes None), exactly one iteration per call.
        feats, state = jax.vmap(
            lambda p: self.point_mlp(p, state, inference=inference), out_axes=(0, None)
        )(points)
        y, state = self.head(jnp.max(feats, axis=0), state, inference=inference)
        return y[0], state


class MLPDiscriminator(eqx.Module):
    """Geometry-space pose discriminator (paper Fig. 4 right): an SN-ReLU MLP on the flattened Euler
    angles `(20 * 3,)` -> logit."""

    mlp: SNMLP

    def __init__(self, n_in: int, hidden: Sequence[int], *, key, dtype=jnp.float32):
        self.mlp = SNMLP((n_in, *hidden, 1), key=key, dtype=dtype)

    def __call__(self, x: Float[ArrayLike, " n"], state, *, inference=None):
        y, state = self.mlp(x, state, inference=inference)
        return y[0], state


def spectral_norms(disc: eqx.Module, state: eqx.nn.State) -> Float[Array, " L"]:
    """The exact largest singular value (by SVD) of every spectrally normalised weight
    `W / sigma(W)` in `disc`, with `sigma` from the current power-iteration state; all 1 when the
    iteration has converged. Host/diagnostic use."""
    out = []
    for sn in jax.tree_util.tree_leaves(disc, is_leaf=lambda x: isinstance(x, eqx.nn.SpectralNorm)):
        if not isinstance(sn, eqx.nn.SpectralNorm):
            continue
        u, v = state.get(sn.uv_index)
        w = getattr(sn.layer, sn.weight_name)
        w = w.reshape(w.shape[0], -1)
        sigma = jnp.einsum("i,ij,j->", u, w, v)
        out.append(jnp.linalg.svd(w / sigma, compute_uv=False)[0])
    return jnp.stack(out)


# --------------------------------------------------------------------------------------------------
# Configuration and the trained containers


@dataclasses.dataclass(frozen=True)
class DSPPConfig:
    """Sizes and training schedule of the DSPP networks and baselines (hashable; static under jit).

    **Fields:**

    - `latent_dim`: size `d` of the auto-encoding space (shape and pose). Default 32.
    - `noise_dim`: size of the generators' standard-normal input. Default 32.
    - `ae_hidden`: encoder hidden widths, input side first; the decoder mirrors them.
    - `generator_hidden`, `discriminator_hidden`: latent generator / discriminator hidden widths.
    - `pointnet_hidden`, `pointnet_head_hidden`: baseline PointNet shared-MLP widths and the head
      after max-pooling.
    - `pointnet_points`: vertices the PointNet discriminator sees per training cycle (a fresh random
      subset each cycle, the same for real and generated shapes; PointNet itself trains on 1,024
      sampled points). Default 1,024; at least the mesh size = all vertices.
    - `geometry_pose_hidden`: baseline pose-discriminator widths (MLP on Euler angles).
    - `geometry_generator_hidden`: baseline generator widths (noise -> ... -> geometry).
    - `n_steps`: training cycles (paper: 100,000).
    - `batch_size`: real samples (and as many generated ones) per cycle (paper: 1).
    - `learning_rate`: Adam step size; betas (0.9, 0.999), eps 1e-8 (PyTorch's defaults = paper's).
    - `steps_per_call`: cycles per jitted `lax.scan` call (progress and checkpoints happen between
      calls).
    - `checkpoint_every`: cycles between checkpoints when a checkpoint directory is given (rounded
      to a multiple of `steps_per_call`).
    - `disc_input_gain`: fixed factor on every discriminator input (codes for the AE-GANs,
      normalised geometry for the baselines); the discriminator is `D(gain * z)`, a
      `gain`-Lipschitz function of its input instead of a 1-Lipschitz one. 1 is the paper's recipe.
      Spectral normalisation makes a discriminator 1-Lipschitz in its input, so with codes of
      per-dimension std ~1.3 (the pose AE's) its logits stay within ~0.2 of each other, its loss
      sits at log 4, and Adam piles the constant gradient into one singular direction until the
      generator gets no signal: the pose prior collapses to one pose (docs/results_dspp.md). The
      gain fixes the latent scale that the paper leaves free. Default 1 (the paper's);
      `DSPPConfig.preset("pose")` uses 20.
    - `generator_learning_rate`: Adam step size of the generator; `None` = `learning_rate`.
    - `gan_b1`: Adam's first-moment decay for the discriminator and the generator (the auto-encoder
      keeps 0.9). Default 0.9 (PyTorch's and the paper's); 0.5 is the DCGAN choice.
    - `monitor_every`: cycles between collapse-monitor evaluations when training gets
      `validation` data (rounded to a multiple of `steps_per_call`).
    - `monitor_samples`: generated (and validation) items per monitor evaluation.
    - `generator_ema`: decay of an exponential moving average of the generator's weights, updated
      after every generator step; the averaged generator is the one sampled, monitored and
      returned (Yazici et al. 2019, "The unusual effectiveness of averaging in GAN training";
      StyleGAN, BigGAN). Averaging the iterates damps the oscillation of the two-player game
      around its equilibrium. Default 0 (off, the paper's recipe).

    Named presets: [`bodyprior.dspp.DSPPConfig.preset`][].
    """

    latent_dim: int = 32
    noise_dim: int = 32
    ae_hidden: tuple[int, ...] = (128, 64)
    generator_hidden: tuple[int, ...] = (128, 128)
    discriminator_hidden: tuple[int, ...] = (128, 128)
    pointnet_hidden: tuple[int, ...] = (64, 128)
    pointnet_head_hidden: tuple[int, ...] = (128,)
    pointnet_points: int = 1024
    geometry_pose_hidden: tuple[int, ...] = (256, 256)
    geometry_generator_hidden: tuple[int, ...] = (128, 256)
    n_steps: int = 100_000
    batch_size: int = 1
    learning_rate: float = 1e-3
    steps_per_call: int = 1000
    checkpoint_every: int = 10_000
    disc_input_gain: float = 1.0
    generator_learning_rate: float | None = None
    gan_b1: float = 0.9
    monitor_every: int = 5000
    monitor_samples: int = 256
    generator_ema: float = 0.0

    def __post_init__(self):
        ints = ("latent_dim", "noise_dim", "n_steps", "batch_size", "steps_per_call",
                "checkpoint_every", "pointnet_points", "monitor_every",
                "monitor_samples")  # fmt: skip
        for name in ints:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "n_steps" else 1):
                raise ValueError(f"DSPPConfig.`{name}` must be a positive int, got {v!r}.")
        widths = ("ae_hidden", "generator_hidden", "discriminator_hidden", "pointnet_hidden",
                  "pointnet_head_hidden", "geometry_pose_hidden",
                  "geometry_generator_hidden")  # fmt: skip
        for name in widths:
            v = getattr(self, name)
            if (
                not isinstance(v, tuple)
                or not v
                or any(isinstance(s, bool) or not isinstance(s, int) or s < 1 for s in v)
            ):
                raise ValueError(
                    f"DSPPConfig.`{name}` must be a non-empty tuple of positive ints, got {v!r}."
                )
        if not (isinstance(self.learning_rate, float) and 0.0 < self.learning_rate < 1.0):
            raise ValueError(
                f"DSPPConfig.`learning_rate` must be a float in (0, 1), got {self.learning_rate!r}."
            )
        glr = self.generator_learning_rate
        if glr is not None and not (isinstance(glr, float) and 0.0 < glr < 1.0):
            raise ValueError(
                "DSPPConfig.`generator_learning_rate` must be None or a float in (0, 1), got "
                f"{glr!r}."
            )
        if not (isinstance(self.gan_b1, float) and 0.0 <= self.gan_b1 < 1.0):
            raise ValueError(f"DSPPConfig.`gan_b1` must be a float in [0, 1), got {self.gan_b1!r}.")
        g = self.disc_input_gain
        if isinstance(g, bool) or not isinstance(g, (int, float)) or not 0.0 < g < 1e6:
            raise ValueError(f"DSPPConfig.`disc_input_gain` must be a positive float, got {g!r}.")
        object.__setattr__(self, "disc_input_gain", float(g))  # 20 and 20.0: one static config
        ema = self.generator_ema
        if isinstance(ema, bool) or not isinstance(ema, (int, float)) or not 0.0 <= ema < 1.0:
            raise ValueError(f"DSPPConfig.`generator_ema` must be a float in [0, 1), got {ema!r}.")
        object.__setattr__(self, "generator_ema", float(ema))
        if self.monitor_samples < 2:
            raise ValueError(
                f"DSPPConfig.`monitor_samples` must be at least 2, got {self.monitor_samples}."
            )

    @classmethod
    def preset(cls, name: str, **overrides) -> DSPPConfig:
        """A named configuration, with any field overridden by keyword.

        - `"paper"`: the printed recipe (Adam defaults for all three parts, a 1-Lipschitz SN
          discriminator on the raw codes); equal to `DSPPConfig()`.
        - `"shape"`: the shape prior's default, the paper's recipe (it does not collapse: the shape
          codes are ~5x larger than the pose codes).
        - `"pose"`: the pose prior's default: `disc_input_gain=20`, `generator_learning_rate=2e-4`
          (measured against the paper's recipe in docs/results_dspp.md).
        - `"geometry_pose"`: the geometry-space pose GAN baseline: `disc_input_gain=5`.
        """
        table = {
            "paper": {},
            "shape": {},
            "pose": dict(disc_input_gain=20.0, generator_learning_rate=2e-4),
            "geometry_pose": dict(disc_input_gain=5.0),
        }
        return named_preset(cls, table, name, overrides)

    def to_dict(self) -> dict:
        return {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_dict(cls, d: dict) -> DSPPConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        if isinstance(d, dict):
            # Files written before these fields existed were trained with the paper's values.
            d = {**_V1_DEFAULTS, **d}
        if not isinstance(d, dict) or set(d) != names:
            raise ValueError(f"A DSPPConfig dict must have exactly the keys {sorted(names)}.")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


# Fields added after format version 1 and the values every earlier file was trained with.
_V1_DEFAULTS = dict(disc_input_gain=1.0, generator_learning_rate=None, gan_b1=0.9,
                    monitor_every=5000, monitor_samples=256, generator_ema=0.0)  # fmt: skip


def _check_input(x, name: str, shape: tuple[int, ...]):
    if not hasattr(x, "shape") or tuple(x.shape) != shape:
        got = getattr(x, "shape", type(x).__name__)
        raise ValueError(f"`{name}` must have shape {shape}, got {got}.")
    if not is_tracer(x):
        check_array(x, name, shape)


class _AEGANPrior(eqx.Module):
    encoder: PReLUMLP
    decoder: PReLUMLP
    generator: PReLUMLP
    discriminator: LatentDiscriminator
    disc_state: eqx.nn.State
    mean: Float[Array, "*item 3"]
    scale: Float[Array, ""]
    config: DSPPConfig = eqx.field(static=True)

    @property
    def latent_dim(self) -> int:
        return self.config.latent_dim

    @property
    def noise_dim(self) -> int:
        return self.config.noise_dim

    def _normalise(self, x) -> Float[Array, " D"]:
        return ((jnp.asarray(x).astype(self.mean.dtype) - self.mean) / self.scale).reshape(-1)

    def _denormalise(self, u) -> Array:
        return self.mean + self.scale * u.reshape(self.mean.shape)

    def encode(self, x) -> Float[Array, " d"]:
        """Code `(d,)` of one real item (shape `(V, 3)` metres, or pose `(20, 3)` radians)."""
        _check_input(x, "x", tuple(self.mean.shape))
        return self.encoder(self._normalise(x))

    def decode(self, z: Float[ArrayLike, " d"]) -> Array:
        """Item (`(V, 3)` metres or `(20, 3)` radians) decoded from a code `(d,)`."""
        _check_input(z, "z", (self.latent_dim,))
        return self._denormalise(self.decoder(jnp.asarray(z).astype(self.mean.dtype)))

    def reconstruct(self, x) -> Array:
        """`decode(encode(x))`."""
        return self.decode(self.encode(x))

    def generate(self, key: PRNGKeyArray) -> Float[Array, " d"]:
        """A code drawn from the learned latent distribution: `generator(n)`, `n ~ N(0, I)`."""
        return self.generator(jr.normal(key, (self.noise_dim,), self.mean.dtype))

    def sample(self, key: PRNGKeyArray) -> Array:
        """One random item: `decode(generator(n))` with `n ~ N(0, I)`. Jittable; vmap over keys."""
        return self._denormalise(self.decoder(self.generate(key)))

    def latent_logit(self, z: Float[ArrayLike, " d"]) -> Float[Array, ""]:
        """Discriminator logit of a code (higher = judged more real; `sigmoid` = probability).
        Uses the trained spectral-norm state (inference mode); differentiable in `z`."""
        _check_input(z, "z", (self.latent_dim,))
        z = self.config.disc_input_gain * jnp.asarray(z).astype(self.mean.dtype)
        logit, _ = self.discriminator(z, self.disc_state, inference=True)
        return logit


class ShapePrior(_AEGANPrior):
    """A trained DSPP shape prior: shape encoder/decoder, latent generator and discriminator, with
    the data normalisation (`mean` `(V, 3)` metres and a scalar `scale`, metres: the networks see
    `(x - mean) / scale`). Methods (one item; vmap for batches): `encode((V,3)) -> (d,)`,
    `decode((d,)) -> (V,3)`, `sample(key) -> (V,3)`, `latent_logit((d,)) -> ()`, `reconstruct`,
    `generate(key) -> (d,)`. Build with [`bodyprior.dspp.train_shape_prior`][]."""

    @property
    def n_vertices(self) -> int:
        return self.mean.shape[0]


class PosePrior(_AEGANPrior):
    """A trained DSPP pose prior over Euler angles `(20, 3)` (radians, `bodyprior.EULER_ORDER`,
    joints `POSE_JOINTS`); same methods as [`bodyprior.dspp.ShapePrior`][]. Build with
    [`bodyprior.dspp.train_pose_prior`][]."""


class GeometryGAN(eqx.Module):
    """Baseline: a GAN whose discriminator works in the original geometry space (paper Fig. 4).

    `kind="shape"`: generator `N(0, I) -> (V, 3)` vertices, PointNet discriminator on the vertices
    (normalised by the mean shape's centroid `centre` and RMS radius `radius`); `kind="pose"`:
    generator `-> (20, 3)` Euler angles, MLP discriminator on them. `sample(key)` draws one item;
    `logit(x)` is the discriminator's logit. Build with [`bodyprior.dspp.train_geometry_gan`][].
    """

    generator: PReLUMLP
    discriminator: PointNetDiscriminator | MLPDiscriminator
    disc_state: eqx.nn.State
    mean: Float[Array, "*item 3"]
    scale: Float[Array, ""]
    centre: Float[Array, " 3"]
    radius: Float[Array, ""]
    kind: str = eqx.field(static=True)
    config: DSPPConfig = eqx.field(static=True)

    @property
    def noise_dim(self) -> int:
        return self.config.noise_dim

    def _disc_input(self, u: Float[Array, " D"]) -> Array:
        return geometry_disc_input(self.kind, self.mean, self.scale, self.centre, self.radius, u)

    def sample(self, key: PRNGKeyArray) -> Array:
        """One random item, `(V, 3)` metres or `(20, 3)` radians."""
        u = self.generator(jr.normal(key, (self.noise_dim,), self.mean.dtype))
        return self.mean + self.scale * u.reshape(self.mean.shape)

    def logit(self, x) -> Float[Array, ""]:
        """Discriminator logit of one item (higher = judged more real)."""
        _check_input(x, "x", tuple(self.mean.shape))
        u = ((jnp.asarray(x).astype(self.mean.dtype) - self.mean) / self.scale).reshape(-1)
        y, _ = self.discriminator(
            self.config.disc_input_gain * self._disc_input(u), self.disc_state, inference=True
        )
        return y


def geometry_disc_input(kind: str, mean, scale, centre, radius, u: Float[ArrayLike, " D"]) -> Array:
    """Discriminator input of a geometry GAN from normalised geometry `u = (x - mean) / scale`
    (flattened): vertices relative to the mean shape's centroid in units of its RMS radius `(V, 3)`
    for shapes, `u` itself for poses."""
    if kind == "shape":
        return (mean + scale * u.reshape(mean.shape) - centre) / radius
    return u


def init_aegan(kind: str, mean, scale, config: DSPPConfig, *, key) -> _AEGANPrior:
    """Freshly initialised (untrained) [`bodyprior.dspp.ShapePrior`][] (`kind="shape"`) or
    [`bodyprior.dspp.PosePrior`][] (`kind="pose"`) for items shaped like `mean`, float32."""
    cls = {"shape": ShapePrior, "pose": PosePrior}.get(kind)
    if cls is None:
        raise ValueError(f"`kind` must be 'shape' or 'pose', got {kind!r}.")
    mean = jnp.asarray(mean, jnp.float32)
    n_in = int(np.prod(mean.shape))
    c = config
    ke, kd, kg, kdis = jr.split(key, 4)
    enc = PReLUMLP((n_in, *c.ae_hidden, c.latent_dim), key=ke)
    dec = PReLUMLP((c.latent_dim, *reversed(c.ae_hidden), n_in), key=kd)
    gen = PReLUMLP((c.noise_dim, *c.generator_hidden, c.latent_dim), key=kg)
    disc, state = eqx.nn.make_with_state(LatentDiscriminator)(
        c.latent_dim, c.discriminator_hidden, key=kdis
    )
    return cls(enc, dec, gen, disc, state, mean, jnp.asarray(scale, jnp.float32), c)


def init_geometry_gan(kind: str, mean, scale, config: DSPPConfig, *, key) -> GeometryGAN:
    """Freshly initialised [`bodyprior.dspp.GeometryGAN`][] of `kind` `"shape"` or `"pose"`."""
    if kind not in ("shape", "pose"):
        raise ValueError(f"`kind` must be 'shape' or 'pose', got {kind!r}.")
    mean = jnp.asarray(mean, jnp.float32)
    n_in = int(np.prod(mean.shape))
    c = config
    kg, kd = jr.split(key)
    gen = PReLUMLP((c.noise_dim, *c.geometry_generator_hidden, n_in), key=kg)
    if kind == "shape":
        disc, state = eqx.nn.make_with_state(PointNetDiscriminator)(
            c.pointnet_hidden, c.pointnet_head_hidden, key=kd
        )
        centre = jnp.mean(mean, axis=0)
        radius = jnp.sqrt(jnp.mean(jnp.sum((mean - centre) ** 2, axis=-1)))
    else:
        disc, state = eqx.nn.make_with_state(MLPDiscriminator)(n_in, c.geometry_pose_hidden, key=kd)
        centre, radius = jnp.zeros(3, jnp.float32), jnp.ones((), jnp.float32)
    return GeometryGAN(gen, disc, state, mean, jnp.asarray(scale, jnp.float32), centre, radius,
                       kind, c)  # fmt: skip
