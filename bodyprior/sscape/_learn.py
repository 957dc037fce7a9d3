"""Learning an S-SCAPE shape space from registered meshes, and its statistical quality measures.

Follows the humanshape learning pipeline (Pishchulin et al. 2017, §3–5; humanshape `learnPCA.m`,
`GeneralizedProcrustes.cpp`, `ErrorEvaluation.cpp`): rigid generalised Procrustes alignment, then
PCA of the flattened vertex coordinates; compactness, generalization and specificity as defined by
the humanshape evaluation code.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._kinematics import Similarity, umeyama
from .._rig import Rig
from .._stats import pca_host as _pca_host
from .._validate import check_array, check_positive_int
from ._model import SScapeModel

# --------------------------------------------------------------------------------------------------
# Generalised Procrustes alignment


def _sq_energy(aligned, mean):
    return jnp.sum((aligned - mean[None]) ** 2)


@eqx.filter_jit
def _align_to(meshes, reference, scale: bool):
    transforms = jax.vmap(lambda x: umeyama(x, reference, with_scale=scale))(meshes)
    aligned = jax.vmap(lambda t, x: t.apply(x))(transforms, meshes)
    return transforms, aligned


@eqx.filter_jit
def _gpa(meshes, reference, scale: bool, n_iter: int, tol):
    ref_size = jnp.sqrt(jnp.sum((reference - reference.mean(0)) ** 2))

    def step(ref):
        _, aligned = _align_to(meshes, ref, scale)
        mean = aligned.mean(0)
        if scale:  # fix the size of the mean so that the iteration cannot shrink everything to zero
            mean = mean * ref_size / jnp.sqrt(jnp.sum((mean - mean.mean(0)) ** 2))
        return mean, _sq_energy(aligned, mean)

    def cond(state):
        i, _, e_prev, e = state
        return (i < n_iter) & (jnp.abs(e_prev - e) > tol * jnp.maximum(e, jnp.finfo(e.dtype).tiny))

    def body(state):
        i, ref, _, e = state
        mean, e_new = step(ref)
        return i + 1, mean, e, e_new

    mean0, e0 = step(reference)
    inf = jnp.asarray(jnp.inf, dtype=e0.dtype)
    _, mean, _, _ = jax.lax.while_loop(cond, body, (jnp.asarray(1), mean0, inf, e0))
    return _align_to(meshes, mean, scale)


def procrustes_align(
    meshes: Float[ArrayLike, "N V 3"],
    *,
    reference: Float[ArrayLike, "V 3"] | None = None,
    scale: bool = False,
    n_iter: int = 100,
    tol: float = 1e-10,
) -> tuple[Float[Array, "N V 3"], Similarity]:
    """Generalised Procrustes alignment of meshes in vertex correspondence.

    With `reference=None` this is generalised Procrustes analysis: start from the first mesh
    (centred at its vertex centroid), then repeat "align every mesh to the current mean
    (Umeyama/Kabsch), take the new mean" until the relative change of the energy `sum_i ||X_i -
    mean||_F^2` is below `tol` or `n_iter` rounds have run. The result keeps the first mesh's
    orientation with the mean centred at the origin. With a `reference`, every mesh is aligned once
    to that fixed shape (ordinary Procrustes; no iteration).

    Rigid (rotation + translation) by default, as humanshape: its `GeneralizedProcrustes.cpp`
    centres each mesh at its vertex centroid and then, per round and per mesh, fits a 3x3 linear map
    by least squares to the leave-one-out mean of the other meshes, projects it to the nearest
    orthogonal matrix (SVD, `U V^T`), *skips* the mesh for that round if the determinant is
    negative, and stops when the change of `sum_{i<j} ||X_i - X_j||_F` is at most 1e-5 or after 100
    rounds. Differences here: the full mean (not leave-one-out) is the target, the optimal proper
    rotation (Kabsch with the reflection fix) is used instead of projecting a least-squares linear
    map, and the energy is the squared Frobenius form. All converge to the same alignment up to a
    global rigid motion for well-posed data. `scale=True` adds a per-mesh scale (similarity GPA)
    with the mean's size fixed to that of the initial reference.

    **Arguments:**

    - `meshes`: shape `(N, V, 3)`.
    - `reference`: optional fixed target shape `(V, 3)`.
    - `scale`: also estimate a per-mesh scale.
    - `n_iter`: maximum number of GPA rounds.
    - `tol`: relative energy-change stopping tolerance.

    **Returns:** `(aligned, transforms)`: aligned meshes `(N, V, 3)` and a batched `Similarity`
    (leaves with a leading `N` axis) with `aligned[i] = transforms[i].apply(meshes[i])`.
    """
    dims: dict[str, int] = {}
    check_array(meshes, "meshes", ("N", "V", 3), dims=dims)
    if dims["N"] < 1:
        raise ValueError("`meshes` must hold at least one mesh.")
    if isinstance(n_iter, bool) or not isinstance(n_iter, (int, np.integer)) or n_iter < 1:
        raise ValueError(f"`n_iter` must be a positive int, got {n_iter!r}.")
    meshes = jnp.asarray(meshes)
    if reference is not None:
        check_array(reference, "reference", (dims["V"], 3))
        transforms, aligned = _align_to(
            meshes, jnp.asarray(reference, dtype=meshes.dtype), bool(scale)
        )
    else:
        ref = meshes[0] - meshes[0].mean(0)
        transforms, aligned = _gpa(meshes, ref, bool(scale), int(n_iter), float(tol))
    return aligned, transforms


# --------------------------------------------------------------------------------------------------
# PCA


def _choose_components(ratio: np.ndarray, n_components, explained_variance) -> int:
    r = ratio.shape[0]
    if n_components is not None and explained_variance is not None:
        raise ValueError("Pass at most one of `n_components` and `explained_variance`.")
    if n_components is not None:
        if isinstance(n_components, bool) or not isinstance(n_components, (int, np.integer)):
            raise ValueError(f"`n_components` must be an int, got {type(n_components).__name__}.")
        if not 0 <= n_components <= r:
            raise ValueError(
                f"`n_components` must lie in [0, {r}] (at most N-1 for N meshes), got "
                f"{n_components}."
            )
        return int(n_components)
    if explained_variance is not None:
        ev = float(explained_variance)
        if not 0.0 < ev <= 1.0:
            raise ValueError(f"`explained_variance` must lie in (0, 1], got {explained_variance}.")
        cum = np.cumsum(ratio)
        return int(min(np.searchsorted(cum, ev - 1e-12) + 1, r))
    return r


_LEGACY_RIG = {  # learn()'s former rig keywords -> Rig fields
    "parents": "parents",
    "joint_names": "joint_names",
    "joint_regressor_indices": "regressor_indices",
    "joint_regressor_weights": "regressor_weights",
    "skin_indices": "skin_indices",
    "skin_weights": "skin_weights",
}


def learn(
    meshes: Float[ArrayLike, "N V 3"],
    faces,
    *,
    n_components: int | None = None,
    explained_variance: float | None = None,
    template: SScapeModel | None = None,
    rig: Rig | None = None,
    align: bool = True,
    scale: bool = False,
    n_iter: int = 100,
    observed: Bool[ArrayLike, "N V"] | None = None,
    em_iterations: int = 50,
    **legacy_rig,
) -> SScapeModel:
    """Learns an S-SCAPE shape space from meshes in vertex correspondence.

    Steps (humanshape `learnPCA.m`): optional rigid generalised Procrustes alignment
    ([`bodyprior.sscape.procrustes_align`][]); PCA by SVD of the centred, flattened data in float64
    on the host; `stddev = singular values / sqrt(N - 1)` (unbiased; humanshape's `evalues` use
    `1/N`). With a `template`, the aligned data are moved rigidly so that their mean best fits the
    template's mean (humanshape `createModel.m` aligns the new mean to the old template), and the
    template's rig is reused. Without a template, the rig is `rig`; if none is given, a single root
    joint at the vertex centroid with every vertex bound to it is used.

    **Arguments:**

    - `meshes`: training meshes `(N, V, 3)`, `N >= 2`, metres.
    - `faces`: triangles `(F, 3)`, 0-based.
    - `n_components`: number of components to keep (at most `N - 1`), or
    - `explained_variance`: keep the fewest components whose cumulative explained variance ratio
      reaches this fraction in `(0, 1]`. Neither: keep all `min(N - 1, 3V)` components.
    - `template`: optional model whose rig and frame are reused.
    - `rig`: a [`bodyprior.Rig`][] over the `V` vertices, e.g. `body.rig` of the default body or
      `template.rig` of the registration template.
    - `align`: run Procrustes alignment first (rigid unless `scale=True`).
    - `n_iter`: maximum number of GPA rounds.
    - `observed`: optional `(N, V)` bool, the vertices each mesh actually measured (e.g. a
      registration's vertices near scan points; the rest were filled in by the fitter's prior).
      Then the space is PCA **with missing data**: after the alignment (on all vertices), the
      unobserved coordinates are re-estimated `em_iterations` times from the current components
      fitted to each mesh's observed coordinates (EM for PCA, Roweis 1998), so the components
      and the mean come from measured geometry only; needs `n_components`. Every vertex must be
      observed in at least one mesh.

    The former rig keywords (`parents`, `joint_names`, `joint_regressor_indices`,
    `joint_regressor_weights`, `skin_indices`, `skin_weights`, all or none) still work, with a
    `DeprecationWarning`.

    **Returns:** an [`bodyprior.sscape.SScapeModel`][] whose `explained_variance` leaf holds each
    kept component's fraction of the total training variance.
    """
    dims: dict[str, int] = {}
    check_array(meshes, "meshes", ("N", "V", 3), dims=dims)
    check_array(faces, "faces", (None, 3), integer=True)
    n, v = dims["N"], dims["V"]
    if n < 2:
        raise ValueError(f"`meshes` must hold at least 2 meshes, got {n}.")
    unknown = sorted(set(legacy_rig) - set(_LEGACY_RIG))
    if unknown:
        raise TypeError(f"learn() got unexpected keyword arguments {unknown}.")
    given = [k for k, a in legacy_rig.items() if a is not None]
    if given:
        if len(given) != len(_LEGACY_RIG):
            missing = sorted(set(_LEGACY_RIG) - set(given))
            raise ValueError(
                f"An explicit rig needs all of {sorted(_LEGACY_RIG)}; missing {missing}."
            )
        if rig is not None:
            raise ValueError(
                f"Pass either `rig` or the former rig keywords, not both (got {given})."
            )
        warnings.warn(
            f"learn()'s rig keywords {sorted(_LEGACY_RIG)} are deprecated: pass "
            "`rig=bodyprior.Rig(...)` (e.g. `rig=body.rig` or `rig=template.rig`).",
            DeprecationWarning,
            stacklevel=2,
        )
        rig = Rig(**{_LEGACY_RIG[k]: a for k, a in legacy_rig.items()})
    if rig is not None and not isinstance(rig, Rig):
        raise ValueError(f"`rig` must be a bodyprior.Rig, got {type(rig).__name__}.")
    if template is not None:
        if not isinstance(template, SScapeModel):
            raise ValueError(f"`template` must be an SScapeModel, got {type(template).__name__}.")
        if rig is not None:
            raise ValueError("Pass either `template` or an explicit rig, not both.")
        if template.n_vertices != v:
            raise ValueError(
                f"`template` has {template.n_vertices} vertices but `meshes` have {v}."
            )
        rig = template.rig
    elif rig is None:
        rig = Rig(
            parents=(-1,),
            joint_names=("root",),
            regressor_indices=np.arange(v, dtype=np.int32)[None],
            regressor_weights=np.full((1, v), 1.0 / v),
            skin_indices=np.zeros((v, 1), np.int32),
            skin_weights=np.ones((v, 1)),
        )
    if rig.n_vertices != v:
        raise ValueError(f"`rig` skins {rig.n_vertices} vertices but `meshes` have {v}.")

    if observed is not None:  # checked before the alignment's work
        if n_components is None:
            raise ValueError("`observed` needs `n_components` (the rank of the EM fill).")
        observed = _check_observed(observed, n, v)
        em_iterations = check_positive_int(em_iterations, "em_iterations")
    x = jnp.asarray(meshes)
    if align:
        x, _ = procrustes_align(x, scale=scale, n_iter=n_iter)
    x = np.asarray(x, dtype=np.float64)
    if template is not None:
        mean_t = np.asarray(template.mean, dtype=np.float64)
        t, _ = _align_to(jnp.asarray(x.mean(0))[None], jnp.asarray(mean_t), False)
        t = jax.tree_util.tree_map(lambda a: a[0], t)
        x = np.asarray(jax.vmap(t.apply)(jnp.asarray(x)), dtype=np.float64)

    if observed is not None:
        x = _em_fill(x, observed, int(min(n_components, n - 1)), em_iterations)
    mu, comps, s = _pca_host(x.reshape(n, v * 3))
    var = s**2
    total = var.sum()
    ratio = var / total if total > 0 else np.zeros_like(var)
    k = _choose_components(ratio, n_components, explained_variance)
    dtype = jnp.asarray(meshes).dtype
    return SScapeModel(
        mean=jnp.asarray(mu.reshape(v, 3), dtype=dtype),
        basis=jnp.asarray(comps[:k].reshape(k, v, 3), dtype=dtype),
        stddev=jnp.asarray(s[:k] / np.sqrt(n - 1), dtype=dtype),
        explained_variance=jnp.asarray(ratio[:k], dtype=dtype),
        faces=faces,
        rig=rig,
    )


def _check_observed(observed, n: int, v: int) -> np.ndarray:
    check_array(observed, "observed", (n, v))
    obs = np.asarray(observed)
    if obs.dtype != np.bool_:
        raise ValueError(f"`observed` must be bool, got dtype {obs.dtype}.")
    if not obs.any(axis=0).all():
        raise ValueError(
            f"`observed`: {int((~obs.any(axis=0)).sum())} vertices are observed in no mesh."
        )
    return obs


def _em_fill(x: np.ndarray, observed: np.ndarray, k: int, n_iter: int) -> np.ndarray:
    """EM for PCA with missing data (Roweis 1998) on the host: `x` `(N, V, 3)` aligned meshes,
    `observed` `(N, V)`; returns `x` with its unobserved vertices replaced by the rank-`k`
    reconstruction from each mesh's observed coordinates, iterated `n_iter` times."""
    n, v, _ = x.shape
    X = x.reshape(n, v * 3).copy()
    obs = np.repeat(observed, 3, axis=1)  # (N, 3V)
    # start: each unobserved coordinate at its mean over the meshes that observed it, so the
    # result depends on the observed coordinates only (not on what filled the holes)
    col_mean = np.where(obs, X, 0.0).sum(0) / obs.sum(0)
    X = np.where(obs, X, col_mean)
    for _ in range(n_iter):
        mu, comps, _ = _pca_host(X)
        C = comps[:k]  # (k, 3V)
        for i in range(n):
            m = ~obs[i]
            if not m.any():
                continue
            # least squares on the observed coordinates, by the normal equations: the rows of C
            # are orthonormal, so C_o C_oᵀ = I − C_m C_mᵀ (k × k from the few missing ones)
            Cm = C[:, m]
            d = X[i] - mu
            coef = np.linalg.solve(np.eye(k) - Cm @ Cm.T + 1e-12 * np.eye(k),
                                   C @ d - Cm @ d[m])  # fmt: skip
            X[i, m] = mu[m] + coef @ Cm
    return X.reshape(n, v, 3)


# --------------------------------------------------------------------------------------------------
# Quality measures (humanshape ErrorEvaluation.cpp; Styner et al. 2003)


class Compactness(NamedTuple):
    """Compactness curve; entry `M - 1` describes the first `M` components."""

    ratio: Array
    """Cumulative explained-variance ratio `sum_{k<=M} lambda_k / sum_k lambda_k` (unitless), shape
    `(K,)`."""
    variance: Array
    """Styner's `C(M) = sum_{k<=M} lambda_k` (model variances `stddev**2`, in the model's length
    unit squared: m^2 for bodyprior models), shape `(K,)`."""
    std_error: Array
    """Styner's `sigma_C(M) = sqrt(2 / n) C(M)` (same unit as `variance`; NaN when `n_samples` is
    not given), shape `(K,)`."""


class Generalization(NamedTuple):
    """Leave-one-out generalization error per number of components; errors in **millimetres**."""

    n_components: tuple[int, ...]
    mean: Array
    """`G(M)`: mean over left-out meshes of the mean vertex error, mm, shape
    `(len(n_components),)`."""
    std: Array
    """Standard deviation over left-out meshes, mm."""
    std_error: Array
    """Styner's `sigma_G = std / sqrt(N - 1)`, mm."""
    errors: Array
    """Per left-out mesh errors, mm, shape `(N, len(n_components))`."""


class Specificity(NamedTuple):
    """Specificity per number of components; distances in **millimetres**."""

    n_components: tuple[int, ...]
    mean: Array
    """`S(M)`: mean over samples of the mean vertex distance to the nearest training mesh, mm."""
    variance: Array
    """Variance over samples, mm^2 (humanshape's mex returns this first, then the mean; named
    here)."""
    std_error: Array
    """Styner's `sigma_S = std / sqrt(S - 1)`, mm."""
    distances: Array
    """Per-sample nearest-neighbour distances, mm, shape `(n_samples, len(n_components))`."""


M_TO_MM = 1000.0
"""Millimetres per metre: the quality measures report errors in mm for meshes in metres."""


def mean_vertex_distance(
    a: Float[ArrayLike, "V 3"], b: Float[ArrayLike, "V 3"]
) -> Float[Array, ""]:
    """`D(a, b) = (1/V) sum_v ||a_v - b_v||_2`, the distance used by all quality measures, in the
    meshes' unit (the measures below convert metres to mm)."""
    return jnp.mean(jnp.linalg.norm(a - b, axis=-1))


def compactness(model: SScapeModel, n_samples: int | None = None) -> Compactness:
    """Compactness of a learned shape space (humanshape evalMode 0, fixed).

    humanshape's code returns `ratio(M) * sqrt(2/n)`, Styner's standard-error factor misapplied;
    this returns the cumulative explained-variance ratio (what should be plotted) and Styner's
    `C(M)` with `sigma_C` separately. Model variances are `stddev**2`, in the model's length unit
    squared (m^2 for bodyprior models); the ratio is unitless.

    **Arguments:**

    - `model`: a learned [`bodyprior.sscape.SScapeModel`][].
    - `n_samples`: number of training meshes `n`, for `std_error`.
    """
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    ratio = jnp.cumsum(model.explained_variance)
    var = jnp.cumsum(model.stddev**2)
    if n_samples is None:
        se = jnp.full_like(var, jnp.nan)
    else:
        if int(n_samples) < 1:
            raise ValueError(f"`n_samples` must be a positive int, got {n_samples}.")
        se = jnp.sqrt(2.0 / int(n_samples)) * var
    return Compactness(ratio, var, se)


def _check_ms(n_components, upper: int, what: str) -> tuple[int, ...]:
    if isinstance(n_components, (int, np.integer)):
        n_components = (int(n_components),)
    ms = tuple(int(m) for m in n_components)
    if not ms:
        raise ValueError("`n_components` must list at least one number of components.")
    for m in ms:
        if not 0 <= m <= upper:
            raise ValueError(f"`n_components` entries must lie in [0, {upper}] ({what}), got {m}.")
    return ms


@eqx.filter_jit
def _generalization_gram(x):
    n, v, _ = x.shape
    flat = x.reshape(n, v * 3)
    flat = flat - flat.mean(0)  # global centring keeps the Gram-matrix centring well conditioned
    return flat, flat @ flat.T  # (N, N), computed once for all left-out meshes


@eqx.filter_jit
def _generalization_kernel(flat, gram, js, train_idx, ms: tuple[int, ...], chunk_size: int):
    n = flat.shape[0]
    v = flat.shape[1] // 3
    m_max = max(ms)

    def one(j, idx):
        # PCA of the training subset `idx` via its centred Gram matrix (sliced from `gram`, so the
        # per-mesh cost is O(T^3 + N D M) instead of O(T^2 D)).
        t = idx.shape[0]
        gs = gram[idx][:, idx]
        row = gs.mean(1)
        k = gs - row[:, None] - row[None, :] + row.mean()
        lam, u = jnp.linalg.eigh(0.5 * (k + k.T))
        lam, u = lam[::-1][:m_max], u[:, ::-1][:, :m_max]
        tiny = jnp.finfo(lam.dtype).eps * t * 100 * jnp.maximum(lam[0], 0) if m_max else 0.0
        valid = lam > tiny
        inv_s = jnp.where(valid, 1.0 / jnp.sqrt(jnp.where(valid, lam, 1.0)), 0.0)
        weights = jnp.zeros((n,), flat.dtype).at[idx].add(1.0 / t)
        mu = weights @ flat  # (D,) training mean
        scatter = jnp.zeros((n, m_max), flat.dtype).at[idx].set(u)
        # E = Y^T U / s with Y = flat[idx] - mu: orthonormal columns, shape (D, m_max).
        e = (flat.T @ scatter - mu[:, None] * u.sum(0)[None]) * inv_s
        d = flat[j] - mu
        b = e.T @ d
        out = []
        for m in ms:
            r = d - e[:, :m] @ b[:m]
            out.append(jnp.mean(jnp.linalg.norm(r.reshape(v, 3), axis=-1)))
        return jnp.stack(out)

    return jax.lax.map(lambda a: one(*a), (js, train_idx), batch_size=chunk_size)


# Items per jitted call when a progress bar is shown (the last block is padded: one compile).
_PROGRESS_BLOCK = 64


def _blocked(fn, items: tuple[np.ndarray, ...], progress: bool, desc: str, unit: str):
    """`fn(*items)` in one call, or with `progress` in blocks of `_PROGRESS_BLOCK` leading rows
    (the last block padded by repeating its last row, dropped again) under a tqdm bar; the rows are
    independent, so the result is the same."""
    n = items[0].shape[0]
    if not progress or n <= _PROGRESS_BLOCK:
        return fn(*items)
    from tqdm.auto import tqdm

    outs = []
    with tqdm(total=n, desc=desc, unit=unit) as bar:
        for lo in range(0, n, _PROGRESS_BLOCK):
            rows = np.minimum(np.arange(lo, lo + _PROGRESS_BLOCK), n - 1)
            outs.append(fn(*(a[rows] for a in items))[: min(_PROGRESS_BLOCK, n - lo)])
            bar.update(min(_PROGRESS_BLOCK, n - lo))
    return jnp.concatenate(outs)


def generalization(
    meshes: Float[ArrayLike, "N V 3"],
    n_components: int | Sequence[int],
    *,
    n_train: int | None = None,
    seed: int = 42,
    chunk_size: int = 8,
    progress: bool = False,
) -> Generalization:
    """Leave-one-out generalization error (humanshape evalMode 1; Pishchulin et al. 2017 §5.1).

    For each left-out mesh `x_j` and each `M`: PCA on the other meshes (all `N - 1`, or a random
    subset of size `n_train` drawn with `seed`), `b = E_M^T (x_j - mu)`, `x_hat = mu + E_M b`, and
    `g_j(M) = D(x_j, x_hat)` with `D` the mean per-vertex Euclidean distance, reported in
    **millimetres** (meshes in metres, bodyprior's unit). The meshes must
    already be aligned (e.g. by [`bodyprior.sscape.procrustes_align`][] on all of them); as in
    humanshape the left-out mesh is not re-aligned. PCA uses the training set's Gram matrix,
    sliced from the Gram matrix of all meshes (computed once), so each left-out mesh costs
    `O(T^3 + N D M)` (use float64 for large sets: components whose eigenvalue is below
    `100 T eps λ_1` count as zero, which in float32 (`eps` 1.2e-7) drops every component past
    ~20 of a body population, so G(M) stays flat beyond there; float64 does not). Memory per
    left-out mesh is `O(T^2 + D M)`.
    Jitted; left-out meshes are processed `chunk_size` at a time under `vmap`.

    **Arguments:**

    - `meshes`: aligned meshes `(N, V, 3)`, metres, `N >= 2`.
    - `n_components`: one or several numbers of components `M`, each in `[0, T - 1]` where `T` is
      the training-set size.
    - `n_train`: optional training subset size (`<= N - 1`).
    - `seed`: NumPy seed for the subsets.
    - `chunk_size`: left-out meshes per vmapped batch.
    - `progress`: a tqdm bar over the left-out meshes (then computed 64 per jitted call; same
      result).

    **Returns:** a [`bodyprior.sscape.Generalization`][], errors in mm.
    """
    dims: dict[str, int] = {}
    check_array(meshes, "meshes", ("N", "V", 3), dims=dims)
    n = dims["N"]
    if n < 2:
        raise ValueError(f"`meshes` must hold at least 2 meshes, got {n}.")
    if n_train is None:
        t = n - 1
        base = np.arange(n - 1)
        idx = np.stack([base + (base >= j) for j in range(n)])
    else:
        t = int(n_train)
        if not 1 <= t <= n - 1:
            raise ValueError(f"`n_train` must lie in [1, {n - 1}], got {n_train}.")
        rng = np.random.default_rng(seed)
        idx = np.stack(
            [np.sort(rng.choice(np.delete(np.arange(n), j), t, replace=False)) for j in range(n)]
        )
    ms = _check_ms(n_components, t - 1, "at most the training-set size minus one")
    flat, gram = _generalization_gram(jnp.asarray(meshes))
    cs = max(1, int(chunk_size))
    errors = _blocked(
        lambda js, ix: _generalization_kernel(flat, gram, jnp.asarray(js), jnp.asarray(ix), ms, cs),
        (np.arange(n, dtype=np.int32), np.asarray(idx, dtype=np.int32)),
        bool(progress),
        "generalization",
        "mesh",
    )
    mean = errors.mean(0)
    std = errors.std(0, ddof=1) if n > 1 else jnp.zeros_like(mean)
    se = std / np.sqrt(max(n - 1, 1))
    # metres -> mm last, on each statistic (so G(M) is exactly 1000 x the metre value)
    return Generalization(ms, mean * M_TO_MM, std * M_TO_MM, se * M_TO_MM, errors * M_TO_MM)


@eqx.filter_jit
def _specificity_samples(coeffs, z):
    # ML Gaussian (1/n) of the training coefficients, sampled as m + U Lambda^{1/2} z.
    m = coeffs.mean(0)
    c = coeffs - m
    cov = c.T @ c / coeffs.shape[0]
    lam, u = jnp.linalg.eigh(cov)
    # Canonical eigenvector signs (largest-magnitude entry positive), so samples are reproducible.
    pivot = jnp.take_along_axis(u, jnp.argmax(jnp.abs(u), axis=0)[None], axis=0)[0]
    u = u * jnp.where(pivot < 0, -1.0, 1.0)
    return m + (z * jnp.sqrt(jnp.maximum(lam, 0.0))) @ u.T  # (S, m_max)


@eqx.filter_jit
def _specificity_kernel(mean, basis, samples, x, ms: tuple[int, ...], chunk_size: int):
    def nearest(b):
        recon = jnp.stack(
            [mean + jnp.tensordot(b[:k], basis[:k], axes=1) for k in ms]
        )  # (nM, V, 3)
        d = jax.lax.map(
            lambda xi: jnp.mean(jnp.linalg.norm(recon - xi[None], axis=-1), axis=-1),
            x,
            batch_size=chunk_size,
        )  # (N, nM)
        return d.min(0)

    return jax.lax.map(nearest, samples, batch_size=chunk_size)


def specificity(
    model: SScapeModel,
    meshes: Float[ArrayLike, "N V 3"],
    n_components: int | Sequence[int],
    *,
    key,
    n_samples: int = 1000,
    chunk_size: int = 32,
    progress: bool = False,
) -> Specificity:
    """Specificity of a shape space (humanshape evalMode 2; Pishchulin et al. 2017 §5.1).

    The training meshes are projected onto the first `M_max = max(n_components)` components; a
    Gaussian (ML mean and full covariance, `1/n`) is fitted to those coefficients and `n_samples`
    samples `m + U Lambda^{1/2} z`, `z ~ N(0, I)`, are drawn. Each sample is reconstructed with its
    first `M` coefficients only, and `s_i(M) = min_j D(y_i, x_j)` over all training meshes. For a
    model learned from `meshes` this equals `b_k ~ N(0, lambda_k)` with `lambda_k` the `1/n`
    variances. The paper uses 10,000 samples. Jitted; samples and meshes are processed
    `chunk_size` at a time. Distances are reported in **millimetres** (model and meshes in
    metres, bodyprior's unit).

    **Arguments:**

    - `model`: the shape space (usually learned from `meshes`).
    - `meshes`: the aligned training meshes `(N, V, 3)`, metres, in the model's frame.
    - `n_components`: one or several `M` in `[0, model.n_components]`.
    - `key`: JAX PRNG key for the samples.
    - `n_samples`: number of samples `S`.
    - `chunk_size`: batch size for the chunked loops.
    - `progress`: a tqdm bar over the samples (then computed 64 per jitted call; same result).

    **Returns:** a [`bodyprior.sscape.Specificity`][], distances in mm.
    """
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    check_array(meshes, "meshes", (None, model.n_vertices, 3))
    ms = _check_ms(n_components, model.n_components, "the model's number of components")
    s = int(n_samples)
    if s < 2:
        raise ValueError(f"`n_samples` must be at least 2, got {n_samples}.")
    x = jnp.asarray(meshes)
    m_max = max(ms)
    basis = model.basis[:m_max]
    coeffs = jnp.einsum("nvd,kvd->nk", x - model.mean[None], basis)
    z = jr.normal(key, (s, m_max), dtype=model.mean.dtype)
    samples = _specificity_samples(coeffs, z)
    cs = max(1, int(chunk_size))
    dist = _blocked(
        lambda b: _specificity_kernel(model.mean, basis, jnp.asarray(b), x, ms, cs),
        (np.asarray(samples),),
        bool(progress),
        "specificity",
        "sample",
    )
    mean = dist.mean(0)
    var = dist.var(0)
    se = jnp.sqrt(dist.var(0, ddof=1)) / np.sqrt(s - 1)
    # metres -> mm last, on each statistic (so S(M) is exactly 1000 x the metre value)
    return Specificity(ms, mean * M_TO_MM, var * M_TO_MM**2, se * M_TO_MM, dist * M_TO_MM)


# --------------------------------------------------------------------------------------------------
# Held-out reconstruction (generalization to meshes outside the training set)


@eqx.filter_jit
def _reconstruction_kernel(mean, basis, x, ms: tuple[int, ...]):
    def one(xi):
        b = jnp.einsum("kvd,vd->k", basis, xi - mean)
        out = []
        for m in ms:
            r = mean + jnp.tensordot(b[:m], basis[:m], axes=1)
            out.append(jnp.mean(jnp.linalg.norm(r - xi, axis=-1)))
        return jnp.stack(out)

    return jax.lax.map(one, x, batch_size=8)


def reconstruction_error(
    model, meshes: Float[ArrayLike, "N V 3"], n_components, *, align: bool = True
) -> np.ndarray:
    """Generalization to held-out meshes: each mesh is rigidly aligned to the model's mean
    (Kabsch, no scale) and projected onto the first `M` components; the error is the mean
    per-vertex distance `D(x, x_hat)` of [`bodyprior.sscape.generalization`][], in
    **millimetres** (meshes in metres).

    Unlike the leave-one-out `generalization`, the space is learned once and the meshes are not in
    its training set (e.g. ground-truth bodies of test scans).

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][].
    - `meshes`: `(N, V, 3)` meshes in the model's topology, metres.
    - `n_components`: one or several `M` in `[0, model.n_components]`.
    - `align`: rigidly align each mesh to the model mean first.

    **Returns:** NumPy `(N, len(n_components))` errors, mm.
    """
    dims: dict[str, int] = {}
    check_array(meshes, "meshes", ("N", model.n_vertices, 3), dims=dims)
    ms = (int(n_components),) if np.ndim(n_components) == 0 else tuple(int(m) for m in n_components)
    if not ms or min(ms) < 0 or max(ms) > model.n_components:
        raise ValueError(
            f"`n_components` entries must lie in [0, {model.n_components}], got {list(ms)}."
        )
    x = jnp.asarray(meshes, model.mean.dtype)
    if align:
        x, _ = procrustes_align(x, reference=model.mean)
    m_max = max(ms)
    return np.asarray(_reconstruction_kernel(model.mean, model.basis[:m_max], x, ms)) * M_TO_MM
