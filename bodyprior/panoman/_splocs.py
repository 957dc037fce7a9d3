"""Sparse localized deformation components (SPLOCS; Neumann et al., SIGGRAPH Asia 2013) of data
living on the sites of a mesh, as PanoMan decomposes its RLA features (paper §4.2, eq. 3).

A data set `X` `(N, S, d)` of `N` samples over `S` sites with a `d`-vector per site — PanoMan:
one scalar per **edge** (relative lengths and relative angles are decomposed separately, `d = 1`);
the original SPLOCS: one 3-vector per **vertex** — is written `X ≈ X̄ + W C` with `K` components
`C` `(K, S, d)` and weights `W` `(N, K)`, minimising

    E(W, C) = ½ ‖X̃ − W C‖²_F + Σ_k Σ_i Λ_ki ‖C_k,i‖₂            |W_nk| ≤ 1   (W ≥ 0 optional)

on the centred data scaled to unit standard deviation (`X̃ = (X − X̄)/σ`, so `sparsity` means the
same on any data). The group norm over the `d` entries of a site is the sparsity term; the
**support map** `Λ_ki = λ · clip((δ_k(i) − d_min)/(d_max − d_min), 0, 1)` makes it free within
`d_min` of the component's centre and full beyond `d_max`, with `δ_k` the shortest-path distance
on the rest mesh (Dijkstra on the edge graph weighted by edge length, in metres; an edge site sits
at its midpoint: the mean of its end points' distances). Radii are metres, per centre site if
given per site (per body part: a hand is ~10 % of body height; the reference code's unit-box
defaults make hand and face components global).

**Algorithm.** Greedy initialisation (the site of largest residual energy, the leading singular
vector of its residual as the weights, the support-masked least-squares component, the residual
updated), then outer iterations of three steps that each never raise `E`:

1. weights: accelerated projected gradient on the box (restarted whenever the objective would
   rise, so monotone), built from two matrix products (`X̃ Cᵀ` and `C Cᵀ`) in place of the
   reference's per-component rank-1 updates (memory-bound: ~113 s per outer iteration at the body
   size); then each column is rescaled to `max_n |W_nk| = 1` with `C_k` scaled back (the product is
   unchanged and the sparsity term can only fall, as `|W| ≤ 1`);
2. support maps: each component's centre moves to its site of largest `‖C_k,i‖`; the new map is
   kept only where it does not raise that component's sparsity term;
3. components: ADMM on the split `C = Z` (`(WᵀW + ρI) C = WᵀX̃ + ρ(Z − U)`, group shrinkage
   `Z = prox_{Λ/ρ}(C + U)`, the dual `U` carried across outer iterations), its `Z` kept if it
   lowers `E`, then proximal-gradient (ISTA) steps, each monotone.

`E` is recorded after every step (`stats["energy"]`); all the large products are GEMMs with the
data (`X̃ Cᵀ`, `WᵀX̃`), so one outer iteration at the body size (6,000 × 40,134, `K = 250`) costs
two passes over the data (`docs/benchmarks.md`).

**Number of components (adaptive rule).** Liu et al. 2019's adaptive rule is not available. With
`adaptive_tol=τ` the greedy initialisation stops adding components once the next one would
explain less than `τ` of the centred data's energy (`‖X̃‖²`), up to `n_components`; components
that the optimisation shrinks to zero are removed from the result. With `adaptive_tol=None`
(default) `K = n_components` exactly (PanoMan picks K from error-vs-K curves, its Fig. 7).

Weights are signed by default (PanoMan needs to reach its neutral coefficients, which a
non-negative code may not); `nonnegative=True` is the original SPLOCS constraint. Runs in
`dtype` (float32 by default: half the memory and twice the GEMM rate of float64; the small
`K × K` systems are solved in float64).
"""

from __future__ import annotations

import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from scipy.sparse.csgraph import dijkstra
from tqdm.auto import tqdm

from .._solution import RESULTS, Solution, _check
from .._topology import Topology
from .._validate import check_array, check_positive_int
from ._rla import _check_topology

__all__ = ["Splocs", "splocs", "splocs_project", "splocs_reconstruct"]


class Splocs(eqx.Module):
    """A sparse localized decomposition `X ≈ mean + weights @ components` (module docstring).

    **Fields** (data units: the units of the decomposed data, e.g. dimensionless relative lengths,
    radians, or metres for vertex displacements):

    - `mean` `(S, d)`: the average subtracted before decomposing (zero with `center=False`).
    - `components` `(K, S, d)`: the components, each zero outside its support.
    - `weights` `(N, K)`: the training samples' weights, `|w| ≤ 1` with `max_n |w_nk| = 1` for
      every non-zero component.
    - `centers` `(K,)`: each component's support centre (a site index); `d_min`, `d_max` `(K,)`
      its support radii in metres.
    - `scale`: the data's standard deviation `σ` that the energy is measured in.
    - `site_kind`: static, `"edges"` or `"vertices"`.
    """

    mean: Float[Array, "S d"]
    components: Float[Array, "K S d"]
    weights: Float[Array, "N K"]
    centers: Int[Array, " K"]
    d_min: Float[Array, " K"]
    d_max: Float[Array, " K"]
    scale: Float[Array, ""]
    site_kind: str = eqx.field(static=True)

    @property
    def n_components(self) -> int:
        return self.components.shape[0]

    def supports(self, rtol: float = 1e-6) -> Bool[Array, "K S"]:
        """Bool `(K, S)`: sites where a component's group norm exceeds `rtol` × its maximum."""
        g = jnp.linalg.norm(self.components, axis=-1)
        return g > rtol * jnp.max(g, axis=1, keepdims=True)


def splocs_reconstruct(decomp: Splocs, weights: ArrayLike) -> Float[Array, "*N S d"]:
    """`mean + weights @ components`: weights `(K,)` / `(N, K)` give `(S, d)` / `(N, S, d)`."""
    w = jnp.asarray(weights)
    if w.shape[-1:] != (decomp.n_components,) or w.ndim > 2:
        raise ValueError(
            f"`weights` must have shape (K,) or (N, K) with K={decomp.n_components}, "
            f"got shape {w.shape}."
        )
    return decomp.mean + jnp.tensordot(w, decomp.components, axes=1)


def splocs_project(decomp: Splocs, data: ArrayLike) -> Float[Array, "*N K"]:
    """Least-squares weights of new samples `(S, d)` / `(N, S, d)` (or `(S,)` / `(N, S)` for
    `d = 1`): `argmin_w ‖data − mean − w C‖²`, unconstrained (PanoMan's projection, §4.2 of
    `panoman_v2`). Rank-deficient components (zeroed) get zero weight."""
    x = jnp.asarray(data)
    S, d = decomp.mean.shape
    if x.shape[-1] == S and d == 1:
        x = x[..., None]
    if x.shape[-2:] != (S, d) or x.ndim > 3:
        raise ValueError(f"`data` must have shape (*N, {S}, {d}), got shape {x.shape}.")
    c = decomp.components.reshape(decomp.n_components, -1)
    r = (x - decomp.mean).reshape(*x.shape[:-2], -1)
    sol = jnp.linalg.lstsq(c.T, jnp.moveaxis(r, -1, 0) if r.ndim == 2 else r)[0]
    return sol.T if r.ndim == 2 else sol


# --------------------------------------------------------------------------------------------------
# Host side: support maps from mesh distances


class _Sites:
    """Shortest-path distances from a site to every site, on the rest mesh's edge graph."""

    def __init__(self, rest: np.ndarray, topology: Topology, kind: str, limit: float):
        e = np.asarray(topology.edges)
        length = np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)
        V = topology.n_vertices
        self.graph = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(V, V)).tocsr()
        self.edges = e
        self.kind = kind
        self.limit = float(limit) + float(length.max())
        self._cache: dict[int, np.ndarray] = {}

    def distance(self, site: int) -> np.ndarray:
        d = self._cache.get(site)
        if d is None:
            src = [site] if self.kind == "vertices" else list(self.edges[site])
            dv = dijkstra(self.graph, directed=False, indices=src, limit=self.limit, min_only=True)
            if self.kind == "edges":  # an edge sits at its midpoint
                dv = 0.5 * (dv[self.edges[:, 0]] + dv[self.edges[:, 1]])
            d = self._cache[site] = dv
        return d

    def ramp(self, site: int, d_min: float, d_max: float) -> np.ndarray:
        """`clip((δ − d_min)/(d_max − d_min), 0, 1)` over all sites (1 beyond the search limit)."""
        d = self.distance(site)
        with np.errstate(invalid="ignore"):
            r = (d - d_min) / (d_max - d_min)
        return np.clip(np.nan_to_num(r, nan=1.0, posinf=1.0), 0.0, 1.0)


# --------------------------------------------------------------------------------------------------
# Device side: the three steps (pure, jitted; the outer loop runs on the host with progress)


def _group_norm(c, d):
    return jnp.sqrt(jnp.sum(c.reshape(c.shape[0], -1, d) ** 2, axis=-1))


def _sparsity(c, lam, d):
    return jnp.sum(lam.astype(jnp.float64) * _group_norm(c, d).astype(jnp.float64))


def _prox(c, thresh, d):
    """Group soft-thresholding of `c` `(K, S·d)` by `thresh` `(K, S)` (NaN-free at zero groups)."""
    g = c.reshape(c.shape[0], -1, d)
    n = jnp.sqrt(jnp.sum(g**2, axis=-1))
    shrink = jnp.maximum(0.0, 1.0 - thresh / jnp.where(n > 0, n, 1.0)) * (n > 0)
    return (g * shrink[..., None].astype(g.dtype)).reshape(c.shape)


def _data_energy(xx, cross, quad):
    """`½‖X − WC‖² = ½(‖X‖² − 2⟨X, WC⟩ + ⟨WC, WC⟩)` from its three inner products (float64)."""
    return 0.5 * (xx - 2.0 * cross + quad)


@eqx.filter_jit
def _greedy_step(x, w_all, c_all, m, site, keep, k, d: int, nonnegative: bool):
    """Adds component `k` at `site` with support mask `keep` `(S,)`; returns the next site."""
    f64 = jnp.float64
    cols = site * d + jnp.arange(d)
    r = x[:, cols] - w_all @ c_all[:, cols]  # (N, d) residual at the site
    if d == 1:
        w = r[:, 0]
    else:
        _, vec = jnp.linalg.eigh((r.T @ r).astype(f64))
        w = r @ vec[:, -1].astype(r.dtype)
    if nonnegative:
        wp, wn = jnp.maximum(w, 0), jnp.maximum(-w, 0)
        w = jnp.where(jnp.sum(wp**2) >= jnp.sum(wn**2), wp, wn)
    a = jnp.max(jnp.abs(w))
    w = jnp.where(a > 0, w / jnp.where(a > 0, a, 1), 0)
    ww = jnp.sum(w.astype(f64) ** 2)
    # `w @ x`, not `x.T @ w`: XLA:CPU runs the transposed GEMV 17x slower (0.71 vs 0.04 s here).
    rtw = w @ x - (w @ w_all) @ c_all  # (S·d,)
    mask = jnp.repeat(keep, d).astype(x.dtype)
    c = jnp.where(ww > 0, rtw * mask / jnp.where(ww > 0, ww, 1).astype(x.dtype), 0)
    gain = 2.0 * jnp.sum((c * rtw).astype(f64)) - ww * jnp.sum(c.astype(f64) ** 2)
    m = m - 2.0 * c * rtw + ww.astype(x.dtype) * c**2
    w_all = w_all.at[:, k].set(w)
    c_all = c_all.at[k].set(c)
    nxt = jnp.argmax(jnp.sum(jnp.maximum(m, 0).reshape(-1, d), axis=1))
    return w_all, c_all, m, gain, nxt


@eqx.filter_jit
def _weight_step(x, xx, w, c, lam, lo, n_steps: int, d: int):
    """Monotone accelerated projected gradient on `½‖X − WC‖²` over the box `[lo, 1]`, then the
    column rescale to `max |w| = 1`. Returns `(W, C, data energy, total energy)`."""
    f64 = jnp.float64
    p = x @ c.T  # (N, K)
    h = c @ c.T  # (K, K)
    L = jnp.maximum(jnp.linalg.eigvalsh(h.astype(f64))[-1], 1e-30).astype(x.dtype)

    def f(wv):  # ½⟨W, W H⟩ − ⟨W, P⟩ in float64
        return 0.5 * jnp.sum((wv @ h).astype(f64) * wv) - jnp.sum(p.astype(f64) * wv)

    def body(_, s):
        wk, y, t, fk = s
        wn = jnp.clip(y - (y @ h - p) / L, lo, 1.0)
        fn = f(wn)
        ok = fn <= fk
        tn = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * t * t))
        yn = wn + ((t - 1.0) / tn) * (wn - wk)
        # Restart (plain projected-gradient step from wk, which never rises) when f would rise.
        return (
            jnp.where(ok, wn, wk),
            jnp.where(ok, yn, wk),
            jnp.where(ok, tn, 1.0),
            jnp.where(ok, fn, fk),
        )

    w, _, _, fw = jax.lax.fori_loop(0, n_steps, body, (w, w, jnp.asarray(1.0, x.dtype), f(w)))
    s = jnp.max(jnp.abs(w), axis=0)
    s = jnp.where(s > 0, s, 1.0)
    w = w / s
    c = c * s[:, None]
    data = 0.5 * xx + fw
    return w, c, data, data + _sparsity(c, lam, d)


@eqx.filter_jit
def _component_step(x, xx, w, c, u, lam, rho, n_admm: int, n_ista: int, d: int):
    """ADMM (kept only if it lowers `E`), then monotone ISTA steps. Returns `(C, U, data, E)`."""
    f64 = jnp.float64
    b = w.T @ x  # (K, S·d)
    g = (w.T @ w).astype(f64)
    K = g.shape[0]
    a_inv = jax.scipy.linalg.cho_solve(
        jax.scipy.linalg.cho_factor(g + rho * jnp.eye(K, dtype=f64)), jnp.eye(K, dtype=f64)
    ).astype(x.dtype)
    gx = g.astype(x.dtype)

    def energy(cv):
        data = _data_energy(
            xx, jnp.sum((b * cv).astype(f64)), jnp.sum(((gx @ cv) * cv).astype(f64))
        )
        return data, data + _sparsity(cv, lam, d)

    def admm(_, s):
        z, uu = s
        cc = a_inv @ (b + rho * (z - uu))
        zn = _prox(cc + uu, lam / rho, d)
        return zn, uu + cc - zn

    z, u = jax.lax.fori_loop(0, n_admm, admm, (c, u))
    e_c, e_z = energy(c)[1], energy(z)[1]
    c = jnp.where(e_z <= e_c, z, c)
    L = jnp.maximum(jnp.linalg.eigvalsh(g)[-1], 1e-30).astype(x.dtype)

    def ista(_, s):
        cc, ec = s
        cn = _prox(cc - (gx @ cc - b) / L, lam / L, d)
        en = energy(cn)[1]
        ok = en <= ec
        return jnp.where(ok, cn, cc), jnp.where(ok, en, ec)

    c, _ = jax.lax.fori_loop(0, n_ista, ista, (c, jnp.minimum(e_c, e_z)))
    data, e = energy(c)
    return c, u, data, e


# --------------------------------------------------------------------------------------------------
# Entry point


def _radii(value, name, S):
    a = np.asarray(value, np.float64)
    if a.ndim == 0:
        a = np.full(S, float(a))
    if a.shape != (S,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(
            f"`{name}` must be a non-negative radius in metres, a scalar or one per site ({S},), "
            f"got shape {a.shape}."
        )
    return a


def splocs(
    data: ArrayLike,
    rest_vertices: ArrayLike,
    topology: Topology,
    *,
    n_components: int,
    d_min: float | ArrayLike,
    d_max: float | ArrayLike,
    sites: str | None = None,
    sparsity: float = 2.0,
    n_iterations: int = 10,
    weight_steps: int = 30,
    admm_steps: int = 10,
    ista_steps: int = 5,
    rho: float = 10.0,
    nonnegative: bool = False,
    center: bool = True,
    adaptive_tol: float | None = None,
    rtol: float = 1e-6,
    dtype=jnp.float32,
    progress: bool = True,
    throw: bool = True,
) -> Solution:
    """Sparse localized decomposition of `data` on a mesh (module docstring for the energy and the
    algorithm).

    **Arguments:**

    - `data`: `(N, S)` (one scalar per site) or `(N, S, d)`; `S` is the number of edges
      (PanoMan's RLA features) or of vertices (e.g. displacements in metres) of `topology`.
    - `rest_vertices` `(V, 3)` metres: the mesh on which support distances are measured.
    - `topology`: a [`bodyprior.Topology`][].
    - `n_components`: `K` (the cap with `adaptive_tol`).
    - `d_min`, `d_max`: support radii in metres (scalars, or `(S,)` per centre site for per-part
      radii); `0 ≤ d_min < d_max`.
    - `sites`: `"edges"` or `"vertices"`; inferred from `S` when `None`.
    - `sparsity`: `λ`, relative to the data scaled to unit standard deviation.
    - `n_iterations`: outer iterations (stops early when `E` falls by less than `rtol` relative).
    - `weight_steps`, `admm_steps`, `ista_steps`, `rho`: inner iteration counts and the ADMM
      penalty.
    - `nonnegative`: the original SPLOCS weight constraint `0 ≤ w ≤ 1` (default: signed).
    - `center`: subtract the sample mean first (PanoMan's `X̄`, eq. 3).
    - `adaptive_tol`: the adaptive rule for `K` (module docstring); `None` keeps `K` fixed.
    - `dtype`: working precision of the data products.
    - `progress`: tqdm bars over the greedy components and the outer iterations.

    **Returns:** a [`bodyprior.Solution`][] with `value` a [`bodyprior.panoman.Splocs`][] and
    `stats`: `energy` (`E` after initialisation and after every step, non-increasing), `data_energy`
    and `sparsity_energy` at the end, `explained` `(K_init,)` the fraction of `‖X̃‖²` each greedy
    component explained, `n_iterations`, `converged` (the `rtol` test met), `n_components` (after
    the adaptive rule), `init_s` and `iteration_s` (wall seconds of the greedy initialisation and
    of each outer iteration; the first ones include compilation). `result` is
    `RESULTS.nonfinite` if the decomposition is not finite.
    """
    _check_topology(topology)
    x = np.asarray(data)
    if x.ndim == 2:
        x = x[..., None]
    check_array(x, "data", (None, None, None))
    N, S, d = x.shape
    rest = np.asarray(check_array(rest_vertices, "rest_vertices", (topology.n_vertices, 3)))
    if sites is None:
        sites = {topology.n_edges: "edges", topology.n_vertices: "vertices"}.get(S)
        if sites is None:
            raise ValueError(
                f"`data` must have one entry per edge (S={topology.n_edges}) or per vertex "
                f"(S={topology.n_vertices}) of `topology`, got S={S}."
            )
    if sites not in ("edges", "vertices"):
        raise ValueError(f"`sites` must be 'edges' or 'vertices', got {sites!r}.")
    want = topology.n_edges if sites == "edges" else topology.n_vertices
    if S != want:
        raise ValueError(f"`data` must have S={want} {sites} of `topology`, got S={S}.")
    K = check_positive_int(n_components, "n_components")
    if N < 2:
        raise ValueError(f"`data` needs at least 2 samples, got N={N}.")
    dmin, dmax = _radii(d_min, "d_min", S), _radii(d_max, "d_max", S)
    if np.any(dmax <= dmin):
        raise ValueError("`d_max` must exceed `d_min` at every site.")
    if not (math.isfinite(sparsity) and sparsity >= 0):
        raise ValueError(f"`sparsity` must be a finite number >= 0, got {sparsity!r}.")
    if not (math.isfinite(rho) and rho > 0):
        raise ValueError(f"`rho` must be a finite number > 0, got {rho!r}.")
    n_iterations = int(n_iterations)
    if n_iterations < 0:
        raise ValueError(f"`n_iterations` must be >= 0, got {n_iterations}.")
    if adaptive_tol is not None and not (0.0 <= adaptive_tol < 1.0):
        raise ValueError(f"`adaptive_tol` must lie in [0, 1) or be None, got {adaptive_tol!r}.")

    # Centre and scale on the host in float64, then move to the working dtype.
    mean = x.mean(axis=0) if center else np.zeros((S, d))
    xc = x - mean
    scale = float(np.std(xc))
    scale = scale if scale > 0 else 1.0
    xd = jnp.asarray((xc / scale).reshape(N, S * d), dtype)
    del xc
    xx = _sumsq(xd)
    graph = _Sites(rest, topology, sites, float(dmax.max()))

    # Greedy initialisation.
    w_all = jnp.zeros((N, K), dtype)
    c_all = jnp.zeros((K, S * d), dtype)
    m = jnp.sum(xd**2, axis=0)
    site = int(jnp.argmax(jnp.sum(m.reshape(S, d), axis=1)))
    centers, explained = [], []
    total = float(xx)
    t0 = time.perf_counter()
    for k in tqdm(range(K), desc="splocs init", unit="comp", disable=not progress):
        keep = 1.0 - graph.ramp(site, dmin[site], dmax[site])
        w_new, c_new, m_new, gain, nxt = _greedy_step(
            xd,
            w_all,
            c_all,
            m,
            jnp.asarray(site),
            jnp.asarray(keep, dtype),
            jnp.asarray(k),
            d,
            nonnegative,
        )
        frac = float(gain) / total if total > 0 else 0.0
        if adaptive_tol is not None and frac < adaptive_tol and k > 0:
            break
        w_all, c_all, m = w_new, c_new, m_new
        centers.append(site)
        explained.append(frac)
        site = int(nxt)
    init_s = time.perf_counter() - t0
    K = len(centers)
    w_all, c_all = w_all[:, :K], c_all[:K]
    centers = np.asarray(centers, np.int64)
    lam_np = np.stack([sparsity * graph.ramp(int(s), dmin[s], dmax[s]) for s in centers])
    lam = jnp.asarray(lam_np, dtype)

    energy = [float(_data_energy_only(xd, xx, w_all, c_all) + _sparsity(c_all, lam, d))]
    u = jnp.zeros_like(c_all)
    lo = 0.0 if nonnegative else -1.0
    converged = False
    it = 0
    bar = tqdm(range(n_iterations), desc="splocs", unit="it", disable=not progress)
    iter_s = []
    for it in bar:
        t0 = time.perf_counter()
        e_start = energy[-1]
        w_all, c_all, data_w, e = _weight_step(xd, xx, w_all, c_all, lam, lo, weight_steps, d)
        energy.append(float(e))
        # Support maps: move each centre to its component's largest site if that does not raise E.
        gn = np.asarray(_group_norm(c_all, d), np.float64)
        best = gn.argmax(axis=1)
        for k in np.flatnonzero(best != centers):
            s = int(best[k])
            row = sparsity * graph.ramp(s, dmin[s], dmax[s])
            if row @ gn[k] <= lam_np[k] @ gn[k]:
                lam_np[k], centers[k] = row, s
        lam = jnp.asarray(lam_np, dtype)
        energy.append(float(data_w + _sparsity(c_all, lam, d)))
        c_all, u, _, e = _component_step(
            xd, xx, w_all, c_all, u, lam, rho, admm_steps, ista_steps, d
        )
        energy.append(float(e))
        iter_s.append(time.perf_counter() - t0)
        bar.set_postfix(E=f"{energy[-1]:.6g}")
        if e_start - energy[-1] <= rtol * abs(e_start):
            converged = True
            break
    n_done = it + 1 if n_iterations else 0

    # The adaptive rule's pruning: drop the components the C-step shrank to zero.
    gn = np.asarray(_group_norm(c_all, d))
    active = gn.max(axis=1) > 0
    if adaptive_tol is not None and not active.all() and active.any():
        idx = np.flatnonzero(active)
        w_all, c_all, centers = w_all[:, idx], c_all[idx], centers[idx]
        lam_np = lam_np[idx]
        lam = jnp.asarray(lam_np, dtype)
    data_e = float(_data_energy_only(xd, xx, w_all, c_all))
    sparse_e = float(_sparsity(c_all, lam, d))
    comps = np.asarray(c_all, np.float64).reshape(-1, S, d) * scale
    value = Splocs(
        mean=jnp.asarray(mean),
        components=jnp.asarray(comps),
        weights=jnp.asarray(w_all, jnp.float64),
        centers=jnp.asarray(centers, jnp.int32),
        d_min=jnp.asarray(dmin[centers]),
        d_max=jnp.asarray(dmax[centers]),
        scale=jnp.asarray(scale),
        site_kind=sites,
    )
    finite = np.isfinite(comps).all() and np.isfinite(np.asarray(w_all)).all()
    result = RESULTS.successful if finite else RESULTS.nonfinite
    stats = {
        "energy": np.asarray(energy),
        "data_energy": data_e,
        "sparsity_energy": sparse_e,
        "explained": np.asarray(explained),
        "n_iterations": n_done,
        "converged": converged,
        "n_components": int(c_all.shape[0]),
        "init_s": init_s,
        "iteration_s": np.asarray(iter_s),
    }
    return _check(Solution(value, result, stats), throw, "splocs")


@jax.jit
def _sumsq(x):
    return jnp.sum(jnp.sum(x.astype(jnp.float64) ** 2, axis=1))


@jax.jit
def _data_energy_only(x, xx, w, c):
    cross = jnp.sum((w.T @ x).astype(jnp.float64) * c)
    quad = jnp.sum(((w.T @ w) @ c).astype(jnp.float64) * c)
    return _data_energy(xx, cross, quad)
