"""DSPP priors inside least-squares fitters (issue 4, §4).

Two ways to use a trained [`bodyprior.dspp.ShapePrior`][] (or [`bodyprior.dspp.PosePrior`][]) when
fitting a body to sparse or noisy data:

1. **As a regulariser** of any fitter whose unknowns produce vertices (e.g. S-SCAPE shape
   coefficients): [`bodyprior.dspp.shape_prior_residual`][] returns a residual function `r(x)` to
   append to the fitter's residual vector, with

       ||r(x)||² = weight · softplus(-D(E(x)))  [+ reconstruction_weight · ||x - Dec(E(x))||² / V]

   where `E` is the prior's encoder, `D` its latent discriminator (logit) and `Dec` its decoder.
   `softplus(-D) = -log sigmoid(D)` is the non-saturating generator loss of the paper (eq. 3-4):
   the negative log-probability that the discriminator calls the encoded shape real. It is
   non-saturating: its gradient does not vanish when the discriminator is confident the shape is
   fake. The optional reconstruction term is the squared distance of `x` to the auto-encoder's
   manifold (mean over vertices, m²). `E` is many-to-one, so the discriminator term alone cannot
   see directions the encoder ignores; the reconstruction term can.
2. **As a parameterisation**: optimise a latent code `z` and take vertices `Dec(z)`
   ([`bodyprior.dspp.fit_latent_to_landmarks`][]), regularised by a Gaussian on `z` (moments of the
   training codes, [`bodyprior.dspp.latent_statistics`][]) and optionally by `softplus(-D(z))`.

[`bodyprior.dspp.fit_shape_space_to_landmarks`][] is the linear-space fitter used as the baseline
and as the host of (1): S-SCAPE shape coefficients from landmark positions, with a Gaussian prior on
the coefficients and any extra residual. Both fitters solve in float64 with optimistix
Levenberg-Marquardt (they require `jax_enable_x64`), are jitted at library level, work on one body
(vmap over bodies, with `throw=False`) and return a [`bodyprior.Solution`][] whose `value` is a
[`bodyprior.dspp.ShapeFit`][].
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int

from .._solution import RESULTS, Solution, _check
from .._validate import check_array, is_tracer
from ..sscape import SScapeModel, shape_vertices
from ._nets import PosePrior, ShapePrior

__all__ = [
    "PriorResidual",
    "ShapeFit",
    "fit_latent_to_landmarks",
    "fit_shape_space_to_landmarks",
    "latent_statistics",
    "pose_prior_residual",
    "shape_prior_residual",
]


# --------------------------------------------------------------------------------------------------
# helpers


def _require_x64(what: str) -> None:
    if jnp.result_type(float) != jnp.float64:
        raise ValueError(
            f"{what} solves in float64: enable it with `jax.config.update('jax_enable_x64', True)`."
        )


def _to_float64(tree):
    return jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float64) if eqx.is_inexact_array(x) else x, tree
    )


def _sqrt_nll(logit: Float[Array, ""]) -> Float[Array, ""]:
    """`sqrt(softplus(-logit))`, finite with finite gradient for every logit (softplus underflows to
    0 in float64 above ~745, where a plain sqrt would have an infinite derivative)."""
    big = logit > 30.0
    tail = jnp.exp(-0.5 * jnp.where(big, logit, 30.0))  # softplus(-l) = e^-l (1 + O(e^-l))
    body = jnp.sqrt(jax.nn.softplus(-jnp.where(big, 0.0, logit)))
    return jnp.where(big, tail, body)


def _check_weight(w, name: str):
    if not hasattr(w, "shape"):
        w = np.asarray(w, dtype=np.float64)
    check_array(w, name, ())
    if not is_tracer(w) and float(w) < 0:
        raise ValueError(f"`{name}` must be non-negative, got {float(w)}.")
    return jnp.asarray(w, dtype=jnp.result_type(float))


def _check_prior(prior, name: str = "prior", cls=(ShapePrior, PosePrior)):
    if not isinstance(prior, cls):
        names = " or ".join(c.__name__ for c in (cls if isinstance(cls, tuple) else (cls,)))
        raise ValueError(f"`{name}` must be a {names}, got {type(prior).__name__}.")
    return prior


# --------------------------------------------------------------------------------------------------
# (1) the prior as a residual


class PriorResidual(eqx.Module):
    """A DSPP prior as a least-squares residual (see the module docstring for the energy).

    Callable on one item: `r(x) -> (R,)`, `R = 1` (discriminator term), plus `x.size` when the
    reconstruction term is on. A PyTree: the weights are array leaves, so changing them does not
    recompile a jitted fitter that takes the residual as an argument. Build it with
    [`bodyprior.dspp.shape_prior_residual`][] / [`bodyprior.dspp.pose_prior_residual`][].

    **Fields:** `prior`; `weight`, `reconstruction_weight` (scalars); static `reconstruction`
    (whether the reconstruction block is present).
    """

    prior: ShapePrior | PosePrior
    weight: Float[Array, ""]
    reconstruction_weight: Float[Array, ""]
    reconstruction: bool = eqx.field(static=True)

    def __call__(self, x: Float[ArrayLike, "*item 3"]) -> Float[Array, " R"]:
        z = self.prior.encode(x)
        r = (jnp.sqrt(self.weight) * _sqrt_nll(self.prior.latent_logit(z)))[None]
        if not self.reconstruction:
            return r
        x = jnp.asarray(x).astype(self.prior.mean.dtype)
        d = (x - self.prior.decode(z)).reshape(-1)
        n = self.prior.mean.shape[0]
        return jnp.concatenate([r, jnp.sqrt(self.reconstruction_weight / n) * d])

    def energy(self, x: Float[ArrayLike, "*item 3"]) -> Float[Array, ""]:
        """`||r(x)||²`."""
        r = self(x)
        return jnp.sum(r * r)


def _prior_residual(prior, weight, reconstruction_weight, reconstruction, kind) -> PriorResidual:
    _check_prior(prior, cls=kind)
    w = _check_weight(weight, "weight")
    wr = _check_weight(reconstruction_weight, "reconstruction_weight")
    if reconstruction is None:
        # Leave the block out only for a concrete zero weight.
        on = is_tracer(reconstruction_weight) or float(np.asarray(reconstruction_weight)) != 0.0
    elif isinstance(reconstruction, bool):
        on = reconstruction
    else:
        raise ValueError(f"`reconstruction` must be None or a bool, got {reconstruction!r}.")
    return PriorResidual(prior, w, wr, on)


def shape_prior_residual(
    prior: ShapePrior,
    weight: float | Float[ArrayLike, ""],
    *,
    reconstruction_weight: float | Float[ArrayLike, ""] = 0.0,
    reconstruction: bool | None = None,
) -> PriorResidual:
    """The shape prior as a residual for least-squares fitters.

    **Arguments:**

    - `prior`: a trained [`bodyprior.dspp.ShapePrior`][].
    - `weight`: `w >= 0` of the discriminator term `w · softplus(-D(E(x)))` (nats).
    - `reconstruction_weight`: `w_r >= 0` of `w_r · ||x - Dec(E(x))||² / V` (`x` in metres, so
      `w_r = 1 / s²` makes a mean squared distance of `s` metres cost 1).
    - `reconstruction`: include the reconstruction block (`R = 1 + 3V`); default: only when
      `reconstruction_weight` is not a concrete 0. Pass `True` to keep one residual structure
      (one compilation) while searching over `reconstruction_weight`, 0 included.

    **Returns:** a [`bodyprior.dspp.PriorResidual`][] `r`; `r(x)` for vertices `x` `(V, 3)` metres
    returns the residual vector, `||r(x)||²` the energy. Differentiable; jit/vmap it as you like.

    **Raises:** `ValueError` for a wrong prior type or a negative or non-scalar weight.
    """
    return _prior_residual(prior, weight, reconstruction_weight, reconstruction, ShapePrior)


def pose_prior_residual(
    prior: PosePrior,
    weight: float | Float[ArrayLike, ""],
    *,
    reconstruction_weight: float | Float[ArrayLike, ""] = 0.0,
    reconstruction: bool | None = None,
) -> PriorResidual:
    """The pose prior as a residual: as [`bodyprior.dspp.shape_prior_residual`][] for Euler-angle
    poses `(20, 3)` (radians, `bodyprior.EULER_ORDER`); `reconstruction_weight` multiplies
    the mean squared angle difference per joint (rad²)."""
    return _prior_residual(prior, weight, reconstruction_weight, reconstruction, PosePrior)


# --------------------------------------------------------------------------------------------------
# fit results


class ShapeFit(eqx.Module):
    """The fitted body of a landmark fit (one body; the `value` of its [`bodyprior.Solution`][],
    whose `result` is the solve's, promoted to [`bodyprior.RESULTS`][], and whose `stats` are
    `landmark_rms` (root-mean-square 3-D distance of the fitted landmarks to the targets, metres),
    `energy` (final total energy, the sum of squared residuals) and `num_steps` (solver steps)).

    **Fields:**

    - `vertices`: fitted mesh, shape `(V, 3)`, metres (float64).
    - `params`: fitted unknowns, shape `(P,)`: shape coefficients in standard deviations
      (`fit_shape_space_to_landmarks`) or the latent code (`fit_latent_to_landmarks`).
    """

    vertices: Float[Array, "V 3"]
    params: Float[Array, " P"]


def _shape_solution(x, params, idx, targets, r, sol) -> Solution:
    rms = jnp.sqrt(jnp.mean(jnp.sum((x[idx] - targets) ** 2, axis=-1)))
    stats = {"landmark_rms": rms, "energy": jnp.sum(r * r), "num_steps": sol.stats["num_steps"]}
    return Solution(ShapeFit(x, params), RESULTS.promote(sol.result), stats)


def _check_landmarks(landmark_index, targets, n_vertices: int):
    dims: dict[str, int] = {}
    check_array(landmark_index, "landmark_index", ("L",), integer=True, dims=dims)
    check_array(targets, "targets", (dims["L"], 3), dims=dims)
    if dims["L"] < 1:
        raise ValueError("`landmark_index` must hold at least one landmark.")
    if not is_tracer(landmark_index):
        li = np.asarray(landmark_index)
        if li.min() < 0 or li.max() >= n_vertices:
            raise ValueError(
                f"`landmark_index` must lie in [0, {n_vertices - 1}], got [{li.min()}, {li.max()}]."
            )


def _check_solver_args(noise_sigma, max_steps, rtol, atol):
    if not float(noise_sigma) > 0:
        raise ValueError(f"`noise_sigma` must be positive (metres), got {noise_sigma!r}.")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int, got {max_steps!r}.")
    if not (float(rtol) > 0 and float(atol) > 0):
        raise ValueError(f"`rtol` and `atol` must be positive, got {rtol!r}, {atol!r}.")


def _solve(residuals, y0, args, max_steps: int, rtol: float, atol: float):
    # Damped steps by the normal equations (Cholesky): the Jacobians are tall (up to 3V + 3L rows,
    # at most ~50 columns) and well conditioned by the Tikhonov rows, and this is ~9x cheaper than
    # the default QR of the 19k x 40 Jacobian (measured, same solution).
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    return optx.least_squares(residuals, solver, y0, args, max_steps=max_steps, throw=False)


# --------------------------------------------------------------------------------------------------
# linear shape space (+ optional prior residual)


@eqx.filter_jit
def _fit_space_kernel(model, idx, targets, sigma, coeff_weight, regulariser, max_steps, rtol, atol):
    model, regulariser = _to_float64((model, regulariser))
    targets = jnp.asarray(targets, jnp.float64)
    # Landmark rows of the basis only (coefficients in standard deviations, as shape_vertices).
    lm_mean = model.mean[idx]
    lm_basis = model.basis[:, idx] * model.stddev[:, None, None]

    def shape(c):
        return shape_vertices(model, c)

    def residuals(c, args):
        lm = lm_mean + jnp.tensordot(c, lm_basis, axes=1)
        parts = [((lm - targets) / sigma).reshape(-1), jnp.sqrt(coeff_weight) * c]
        if regulariser is not None:
            parts.append(regulariser(shape(c)))
        return jnp.concatenate(parts)

    c0 = jnp.zeros(model.n_components, jnp.float64)
    sol = _solve(residuals, c0, None, max_steps, rtol, atol)
    c = sol.value
    return _shape_solution(shape(c), c, idx, targets, residuals(c, None), sol)


def fit_shape_space_to_landmarks(
    model: SScapeModel,
    landmark_index: Int[ArrayLike, " L"],
    targets: Float[ArrayLike, "L 3"],
    *,
    noise_sigma: float = 0.01,
    coeff_weight: float | Float[ArrayLike, ""] = 1.0,
    regulariser: Callable[[Array], Array] | None = None,
    max_steps: int = 100,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    throw: bool = True,
) -> Solution:
    """Shape coefficients of a linear shape space from landmark positions (MAP under a Gaussian
    prior), optionally with an extra prior residual such as
    [`bodyprior.dspp.shape_prior_residual`][].

    Minimises, over coefficients `c` in standard deviations (`x(c) = mean + Σ_k c_k σ_k B_k`),

        Σ_l ||x(c)[i_l] - t_l||² / σ²  +  coeff_weight · ||c||²  +  ||regulariser(x(c))||²

    `coeff_weight = 1` is the exact MAP estimate for the model's Gaussian `c ~ N(0, I)` and
    independent Gaussian landmark noise of standard deviation `σ` per coordinate. Without a
    regulariser the problem is linear and one Levenberg-Marquardt step solves it. The model's rest
    shape is fitted in its own frame (no rigid alignment, no posing): the targets must be given in
    the frame of the data the model was learned from.

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][] (e.g. from [`bodyprior.sscape.learn`][] with
      `align=False`).
    - `landmark_index`: vertex index of each landmark on the model's topology, shape `(L,)`.
    - `targets`: observed landmark positions, shape `(L, 3)`, metres.
    - `noise_sigma`: landmark noise standard deviation `σ` per coordinate, metres.
    - `coeff_weight`: `>= 0`, weight of the Gaussian coefficient prior (a traced scalar: changing
      it does not recompile).
    - `regulariser`: optional residual function of the vertices `(V, 3) -> (R,)`; an `eqx.Module`
      (like [`bodyprior.dspp.PriorResidual`][]) is traced, so its weights can change without
      recompiling.
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt limits and tolerances.
    - `throw`: raise if the result is not `RESULTS.successful` (the solver failed, or stopped at
      `max_steps` without meeting `rtol`/`atol`: a failure, [`bodyprior.Solution`][]'s rule); use
      `False` under `jax.vmap` and check `sol.result`.

    **Returns:** a [`bodyprior.Solution`][]: `value` a [`bodyprior.dspp.ShapeFit`][] (`params` =
    coefficients `(K,)`); `stats` `landmark_rms`, `energy`, `num_steps`.

    **Raises:** `ValueError` for bad shapes or ranges, a non-callable regulariser, or x64 off.
    """
    _require_x64("fit_shape_space_to_landmarks")
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    if model.n_components < 1:
        raise ValueError("`model` must have at least one shape component.")
    _check_landmarks(landmark_index, targets, model.n_vertices)
    _check_solver_args(noise_sigma, max_steps, rtol, atol)
    cw = _check_weight(coeff_weight, "coeff_weight")
    if regulariser is not None and not callable(regulariser):
        raise ValueError(f"`regulariser` must be callable, got {type(regulariser).__name__}.")
    sol = _fit_space_kernel(
        model, jnp.asarray(landmark_index), targets, float(noise_sigma), cw, regulariser,
        int(max_steps), float(rtol), float(atol),
    )  # fmt: skip
    return _check(sol, bool(throw), "fit_shape_space_to_landmarks")


# --------------------------------------------------------------------------------------------------
# (2) latent parameterisation


@eqx.filter_jit
def _latent_stats_kernel(prior, data, chunk: int):
    z = jax.lax.map(prior.encode, data, batch_size=chunk)
    return z.mean(0), z.std(0)


def latent_statistics(
    prior: ShapePrior | PosePrior, data: Float[ArrayLike, "N *item 3"], *, chunk_size: int = 64
) -> tuple[Float[Array, " d"], Float[Array, " d"]]:
    """Mean and standard deviation of the codes `E(x)` of training items, per latent dimension
    (for the Gaussian latent regulariser of [`bodyprior.dspp.fit_latent_to_landmarks`][]).

    **Arguments:** `prior`; `data` `(N, V, 3)` shapes (metres) or `(N, 20, 3)` poses, `N >= 2`;
    `chunk_size`: items encoded per vectorised step.

    **Returns:** `(mean, std)`, shapes `(d,)` each (in the prior's dtype).
    """
    _check_prior(prior)
    check_array(data, "data", (None, *prior.mean.shape))
    if np.shape(data)[0] < 2:
        raise ValueError("`data` must hold at least 2 items.")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive int, got {chunk_size!r}.")
    data = jnp.asarray(data)
    return _latent_stats_kernel(prior, data, min(chunk_size, data.shape[0]))


def _landmark_decoder(prior: ShapePrior, idx: Int[Array, " L"]) -> Callable[[Array], Array]:
    """`z -> prior.decode(z)[idx]` computing only the decoder's output rows of the landmarks (the
    last layer is `3V` wide; restricting it makes each residual and Jacobian ~V/L times cheaper)."""
    dec = prior.decoder
    last = dec.layers[-1]
    rows = (3 * idx[:, None] + jnp.arange(3)[None]).reshape(-1)
    w, b = last.weight[rows], None if last.bias is None else last.bias[rows]
    mean = prior.mean[idx]

    def f(z):
        h = z.astype(prior.mean.dtype)
        for layer, act in zip(dec.layers[:-1], dec.activations):
            h = act(layer(h))
        u = w @ h if b is None else w @ h + b
        return mean + prior.scale * u.reshape(-1, 3)

    return f


@eqx.filter_jit
def _fit_latent_kernel(prior, idx, targets, sigma, mu, sd, latent_weight, score_weight, z0,
                       max_steps, rtol, atol):  # fmt: skip
    prior, mu, sd, z0 = _to_float64((prior, mu, sd, z0))
    targets = jnp.asarray(targets, jnp.float64)

    decode_lm = _landmark_decoder(prior, idx)

    def residuals(z, args):
        parts = [
            ((decode_lm(z) - targets) / sigma).reshape(-1),
            jnp.sqrt(latent_weight) * (z - mu) / sd,
            (jnp.sqrt(score_weight) * _sqrt_nll(prior.latent_logit(z)))[None],
        ]
        return jnp.concatenate(parts)

    sol = _solve(residuals, z0, None, max_steps, rtol, atol)
    z = sol.value
    return _shape_solution(prior.decode(z), z, idx, targets, residuals(z, None), sol)


def fit_latent_to_landmarks(
    prior: ShapePrior,
    landmark_index: Int[ArrayLike, " L"],
    targets: Float[ArrayLike, "L 3"],
    *,
    latent_mean: Float[ArrayLike, " d"],
    latent_std: Float[ArrayLike, " d"],
    noise_sigma: float = 0.01,
    latent_weight: float | Float[ArrayLike, ""] = 1.0,
    score_weight: float | Float[ArrayLike, ""] = 0.0,
    z0: Float[ArrayLike, " d"] | None = None,
    max_steps: int = 100,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    throw: bool = True,
) -> Solution:
    """Fits a body to landmarks in the DSPP prior's latent space: vertices are `Dec(z)`.

    Minimises over the code `z`

        Σ_l ||Dec(z)[i_l] - t_l||² / σ²  +  latent_weight · ||(z - μ) / s||²
        +  score_weight · softplus(-D(z))

    with `μ, s` the moments of the training codes ([`bodyprior.dspp.latent_statistics`][]) and `D`
    the latent discriminator (non-saturating log-score). Nonlinear; Levenberg-Marquardt from `z0`
    (default `μ`). The network runs in float64 here (its float32 weights are cast).

    **Arguments:**

    - `prior`: a trained [`bodyprior.dspp.ShapePrior`][].
    - `landmark_index`, `targets`, `noise_sigma`: as in
      [`bodyprior.dspp.fit_shape_space_to_landmarks`][].
    - `latent_mean`, `latent_std`: `(d,)` each, `latent_std > 0`.
    - `latent_weight`, `score_weight`: `>= 0` (traced scalars).
    - `z0`: optional initial code `(d,)`.
    - `max_steps`, `rtol`, `atol`, `throw`: as in `fit_shape_space_to_landmarks`.

    **Returns:** a [`bodyprior.Solution`][]: `value` a [`bodyprior.dspp.ShapeFit`][] (`params` =
    the code `(d,)`); `stats` as `fit_shape_space_to_landmarks`.

    **Raises:** `ValueError` for bad shapes or ranges, or x64 off.
    """
    _require_x64("fit_latent_to_landmarks")
    _check_prior(prior, cls=ShapePrior)
    d = prior.latent_dim
    _check_landmarks(landmark_index, targets, prior.n_vertices)
    _check_solver_args(noise_sigma, max_steps, rtol, atol)
    check_array(latent_mean, "latent_mean", (d,))
    check_array(latent_std, "latent_std", (d,))
    if not is_tracer(latent_std) and not np.all(np.asarray(latent_std) > 0):
        raise ValueError("`latent_std` must be positive in every dimension.")
    lw = _check_weight(latent_weight, "latent_weight")
    sw = _check_weight(score_weight, "score_weight")
    mu = jnp.asarray(latent_mean)
    z0 = mu if z0 is None else jnp.asarray(check_array(z0, "z0", (d,)))
    sol = _fit_latent_kernel(
        prior, jnp.asarray(landmark_index), targets, float(noise_sigma), mu,
        jnp.asarray(latent_std), lw, sw, z0, int(max_steps), float(rtol), float(atol),
    )  # fmt: skip
    return _check(sol, bool(throw), "fit_latent_to_landmarks")
