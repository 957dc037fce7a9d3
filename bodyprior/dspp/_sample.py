"""Sampling DSPP priors and the linear baselines.

- [`bodyprior.dspp.sample`][]: `n` items from a trained [`bodyprior.dspp.ShapePrior`][] /
  [`bodyprior.dspp.PosePrior`][] (`z ~ N(0, I) -> generator -> decoder`), a
  [`bodyprior.dspp.GeometryGAN`][] or a [`bodyprior.dspp.PCAPrior`][], jitted and vmapped over keys.
- [`bodyprior.dspp.PCAPrior`][] / [`bodyprior.dspp.fit_pca_prior`][]: the linear baselines (issue 4
  §3 c, d) from the same training data: PCA (float64 SVD on the host, the S-SCAPE learner's
  `_pca_host`) with `mode="gaussian"` (coefficients `c_k ~ N(0, sigma_k^2)`), `mode="pm3sigma"`
  (every coefficient at one of its +-3 sigma extremes, `c_k = 3 sigma_k s_k` with random signs
  `s_k = +-1`: the corners of the 3-sigma box, far from the centre where the paper says linear
  spaces produce unrealistic humans) or `mode="uniform3sigma"` (`c_k ~ U(-3 sigma_k, 3 sigma_k)`).

Pictures of sampled poses on the default body: `bodyprior.render_poses` (Euler -> `rig_pose` ->
posed default body).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._stats import pca_host as _pca_host
from .._validate import check_array
from ._nets import GeometryGAN, PosePrior, ShapePrior

PCA_MODES = ("gaussian", "pm3sigma", "uniform3sigma")


class PCAPrior(eqx.Module):
    """Linear baseline: `x = mean + sum_k c_k basis_k`, coefficients drawn per `mode` (see the
    module docstring).

    **Fields:** `mean` (item shape, e.g. `(V, 3)` metres or `(20, 3)` radians), `basis` `(K, D)`
    orthonormal rows (D = item size), `stddev` `(K,)` (unbiased, `s_k / sqrt(N - 1)`), static
    `mode`.
    """

    mean: Float[Array, "*item 3"]
    basis: Float[Array, "K D"]
    stddev: Float[Array, " K"]
    mode: str = eqx.field(static=True)

    def with_mode(self, mode: str) -> PCAPrior:
        """The same PCA space sampled in another `mode` (one of `PCA_MODES`)."""
        if mode not in PCA_MODES:
            raise ValueError(f"`mode` must be one of {PCA_MODES}, got {mode!r}.")
        return dataclasses.replace(self, mode=mode)

    def sample(self, key: PRNGKeyArray) -> Array:
        """One item shaped like `mean`."""
        k = self.stddev.shape[0]
        dt = self.stddev.dtype
        if self.mode == "gaussian":
            c = jr.normal(key, (k,), dt)
        elif self.mode == "pm3sigma":
            c = 3.0 * jr.rademacher(key, (k,), dt)
        else:
            c = jr.uniform(key, (k,), dt, -3.0, 3.0)
        return self.mean + (c * self.stddev @ self.basis).reshape(self.mean.shape)


# Above this many rows/columns (both), only the top components are computed (ARPACK Lanczos, scipy
# `svds`): the thin SVD of 3,446 x 19,347 population data costs ~1 TFLOP, the Lanczos top-32 a few.
_EXACT_SVD_MAX = 1500


def _pca_top(x: np.ndarray, k: int):
    """Top-`k` PCA of `(N, D)` float64 data: mean, components `(k, D)`, singular values `(k,)`, with
    the same deterministic sign rule as the S-SCAPE learner (largest-magnitude entry positive)."""
    from scipy.sparse.linalg import svds

    mu = x.mean(axis=0)
    xc = x - mu
    # A fixed start vector makes the result a deterministic function of the data.
    _, s, vt = svds(xc, k=k, v0=np.ones(min(xc.shape)), tol=1e-10, maxiter=20000)
    order = np.argsort(s)[::-1]
    s, vt = s[order], vt[order]
    pivot = np.argmax(np.abs(vt), axis=1)
    signs = np.sign(vt[np.arange(k), pivot])
    signs[signs == 0] = 1.0
    return mu, vt * signs[:, None], s


def fit_pca_prior(data, n_components: int, *, mode: str = "gaussian") -> PCAPrior:
    """Fits the PCA baseline to training items `data` `(N, *item)` (shapes `(N, V, 3)` or poses
    `(N, 20, 3)`), keeping `n_components` (at most `min(N - 1, D)`). No alignment: the data are
    used in the frame they come in, as the networks see them. Float64 on the host: the exact thin
    SVD of the S-SCAPE learner for small data, the top components only (Lanczos) when both `N` and
    `D` exceed 1,500. The returned arrays are float32 (like the networks); use
    `PCAPrior.with_mode` for the other sampling modes of the same fit."""
    if mode not in PCA_MODES:
        raise ValueError(f"`mode` must be one of {PCA_MODES}, got {mode!r}.")
    check_array(data, "data", (None, None, 3))
    x = np.asarray(data, np.float64)
    n = x.shape[0]
    if n < 2:
        raise ValueError(f"`data` must hold at least 2 items, got {n}.")
    d = int(np.prod(x.shape[1:]))
    if (
        isinstance(n_components, bool)
        or not isinstance(n_components, (int, np.integer))
        or not (1 <= n_components <= min(n - 1, d))
    ):
        raise ValueError(
            f"`n_components` must be an int in [1, {min(n - 1, d)}], got {n_components!r}."
        )
    k = int(n_components)
    flat = x.reshape(n, d)
    if min(n, d) <= _EXACT_SVD_MAX:
        mu, comps, s = _pca_host(flat)
    else:
        mu, comps, s = _pca_top(flat, k)
    f32 = jnp.float32
    return PCAPrior(jnp.asarray(mu.reshape(x.shape[1:]), f32), jnp.asarray(comps[:k], f32),
                    jnp.asarray(s[:k] / np.sqrt(n - 1), f32), mode)  # fmt: skip


_SAMPLERS = (ShapePrior, PosePrior, GeometryGAN, PCAPrior)


@eqx.filter_jit
def _sample_jit(model, keys):
    return jax.vmap(model.sample)(keys)


def sample(model, n: int, *, key) -> Array:
    """Draws `n` items from a prior, jitted and vmapped over `n` independent keys split from `key`.

    **Arguments:**

    - `model`: a [`bodyprior.dspp.ShapePrior`][], [`bodyprior.dspp.PosePrior`][],
      [`bodyprior.dspp.GeometryGAN`][] or [`bodyprior.dspp.PCAPrior`][].
    - `key`: a `jax.random` key.
    - `n`: number of samples (one compilation per distinct `n`).

    **Returns:** `(n, V, 3)` vertices (metres) or `(n, 20, 3)` Euler angles (radians).
    """
    if not isinstance(model, _SAMPLERS):
        raise ValueError(
            "`model` must be a ShapePrior, PosePrior, GeometryGAN or PCAPrior, got "
            f"{type(model).__name__}."
        )
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"`n` must be a positive int, got {n!r}.")
    return _sample_jit(model, jr.split(key, int(n)))
