"""The PanoMan model (paper eqs. 2–5): shape space, six sparse localized decompositions, neutral
coefficients, the correction MLP R(β_B) and the β(θ) MLP; its training, evaluation, save and load.

    B_S(α)   = V̄ + S α                                                   (2, vertex PCA, 10 PCs)
    X_Y(α,β) = X̄_YB + X̄_YF + X̄_YH + M_YB β_YB + M_YF β_YF + M_YH β_YH + R_Y(β_B)   (3, 5)
    B_P(α,β) = g(X_L(α,β), X_A(α,β), B_S(α))                            (4, 5)

for Y ∈ {L (relative lengths), A (angle changes)} and the parts B (body), F (face), H (hands).
Each part's average and components come from a SPLOCS decomposition of its subset of the training
set ([`bodyprior.panoman.splocs`][]) with support radii in metres per part. Because the mean is a
*sum* of three averages, a body pose with β_F = β_H = 0 would carry the average expression and
gesture: the model stores **neutral coefficients** `β⁰_YZ = argmin ‖X̄_YZ + M_YZ β‖` per part and
type (`neutral_coefficients`), the coefficients of "no motion in this part".

The correction R (eq. 5) is an MLP with one hidden layer of ReLU units on the body coefficients
`(β_LB, β_AB)`, regressed on the body training meshes' residuals `X − (X̄ + Mβ̂)`; its output is
restricted to the edges the body components touch and may be low rank (`1500 → r → 2|E_out|`),
the two size reductions of panoman_v2 §3.6. β(θ) is an MLP (hidden 400, 600, ReLU) from the
`cmu_mb` pose (axis-angle of the 20 pose joints, radians) to the body coefficients.
"""

from __future__ import annotations

import io
import json
import math
import os
import time
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, Int
from tqdm.auto import tqdm

from .._body import load_default_body
from .._io import atomic_write_bytes
from .._mocap import POSE_JOINTS
from .._solution import RESULTS, Solution
from .._topology import Topology
from .._validate import check_array, check_positive_int
from ._data import PanomanData
from ._decode import Decoder, _decode, decoder_with_reference, prepare_decoder
from ._rla import RLA, _check_topology, rla_encode, rla_encode_unwrapped
from ._splocs import splocs

__all__ = [
    "MLP",
    "PARTS",
    "PanoManModel",
    "encode_panoman_data",
    "evaluate",
    "fit_mlp",
    "load_panoman",
    "model_targets",
    "pose_features",
    "save_panoman",
    "train_panoman",
]

PARTS = ("body", "face", "hand")
FORMAT = "bodyprior.panoman_model"
FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------------
# MLPs


class MLP(eqx.Module):
    """A multilayer perceptron on standardised inputs and outputs.

    `y = y_mean + y_scale · f((x − x_mean) / x_scale)`, with `f` the layers in `weights`/`biases`
    (ReLU after every layer listed in `relu`, linear otherwise; a `None` bias is no bias, used for
    the low-rank bottleneck). Works on one sample `(n_in,)`; `jax.vmap` for batches.
    """

    weights: tuple[Array, ...]
    biases: tuple[Array | None, ...]
    x_mean: Float[Array, " n_in"]
    x_scale: Float[Array, " n_in"]
    y_mean: Float[Array, " n_out"]
    y_scale: Float[Array, ""]
    relu: tuple[bool, ...] = eqx.field(static=True)

    def __call__(self, x: Float[ArrayLike, " n_in"]) -> Float[Array, " n_out"]:
        h = (jnp.asarray(x, self.x_mean.dtype) - self.x_mean) / self.x_scale
        for W, b, r in zip(self.weights, self.biases, self.relu):
            h = h @ W
            if b is not None:
                h = h + b
            if r:
                h = jax.nn.relu(h)
        return self.y_mean + self.y_scale * h

    @property
    def n_parameters(self) -> int:
        return int(
            sum(w.size for w in self.weights) + sum(b.size for b in self.biases if b is not None)
        )


def _init_mlp(key, sizes, relu, bias, x, y, x_scale_floor=0.0) -> MLP:
    keys = jax.random.split(key, len(sizes) - 1)
    Ws, bs = [], []
    for k, (a, b), has_b in zip(keys, zip(sizes[:-1], sizes[1:]), bias):
        Ws.append(jax.random.normal(k, (a, b), jnp.float32) * math.sqrt(2.0 / a))
        bs.append(jnp.zeros(b, jnp.float32) if has_b else None)
    Ws[-1] = Ws[-1] * 0.1  # start near the mean output
    x_mean = jnp.mean(x, 0)
    # inputs (nearly) constant in training get a unit scale: a tiny scale would turn a new
    # input's small deviation there into a huge activation (e.g. an IK pose moving a joint the
    # training poses never move)
    sd = jnp.std(x, 0)
    x_scale = jnp.where(sd > 1e-2 * jnp.max(sd), jnp.maximum(sd, x_scale_floor), 1.0)
    y_mean = jnp.mean(y, 0)
    y_scale = jnp.maximum(jnp.std(y - y_mean), 1e-12)
    return MLP(tuple(Ws), tuple(bs), x_mean, x_scale, y_mean, y_scale, tuple(relu))


@eqx.filter_jit
def _train(mlp: MLP, x, y, key, n_steps, batch, lr, weight_decay):
    """AdamW over the weights and biases only (the standardisation stays fixed); one scan."""
    sched = optax.cosine_decay_schedule(lr, n_steps)
    opt = optax.adamw(sched, weight_decay=weight_decay)
    params = (mlp.weights, mlp.biases)
    state = opt.init(params)
    n = x.shape[0]

    def loss(p, xb, yb):
        m = eqx.tree_at(lambda q: (q.weights, q.biases), mlp, p, is_leaf=lambda a: a is None)
        pred = jax.vmap(m)(xb)
        return jnp.mean(((pred - yb) / mlp.y_scale) ** 2)

    def step(carry, k):
        p, s = carry
        idx = jax.random.choice(k, n, (batch,), replace=batch > n)
        val, g = jax.value_and_grad(loss)(p, x[idx], y[idx])
        upd, s = opt.update(g, s, p)
        return (optax.apply_updates(p, upd), s), val

    (params, _), history = jax.lax.scan(step, (params, state), jax.random.split(key, n_steps))
    out = eqx.tree_at(lambda q: (q.weights, q.biases), mlp, params, is_leaf=lambda a: a is None)
    return out, history


def fit_mlp(
    key,
    x: Float[ArrayLike, "N n_in"],
    y: Float[ArrayLike, "N n_out"],
    hidden: tuple[int, ...],
    *,
    rank: int | None = None,
    n_steps: int = 2000,
    batch: int = 128,
    learning_rate: float = 1e-3,
    weight_decay: float = 1e-5,
    x_scale_floor: float = 0.0,
) -> Solution:
    """Trains an [`bodyprior.panoman.MLP`][] `x → y` by AdamW on mean squared error (standardised
    outputs), cosine-decayed learning rate, random minibatches; the whole run is one jitted scan.

    **Arguments:** `key`; `x (N, n_in)`, `y (N, n_out)`; `hidden` ReLU layer widths; `rank`: a
    linear bottleneck of this width before the output (low-rank output layer); `n_steps`,
    `batch`, `learning_rate`, `weight_decay`; `x_scale_floor`: the smallest input scale, in the
    units of `x` (inputs are standardised by their training std, at least this; inputs constant in
    training get 1).

    **Returns:** a [`bodyprior.Solution`][] with the MLP and `stats`: `loss` `(n_steps,)` history
    (standardised MSE), `train_rmse` (in units of `y`), `n_parameters`, `seconds`.
    """
    x = jnp.asarray(check_array(x, "x", ("N", None)), jnp.float32)
    y = jnp.asarray(check_array(y, "y", (x.shape[0], None)), jnp.float32)
    hidden = tuple(check_positive_int(h, "hidden") for h in hidden)
    sizes = (
        (x.shape[1], *hidden)
        + ((check_positive_int(rank, "rank"),) if rank else ())
        + (y.shape[1],)
    )
    relu = (True,) * len(hidden) + ((False,) if rank else ()) + (False,)
    bias = (True,) * len(hidden) + ((False,) if rank else ()) + (True,)
    k_init, k_train = jax.random.split(key)
    mlp = _init_mlp(k_init, sizes, relu, bias, x, y, float(x_scale_floor))
    t0 = time.perf_counter()
    mlp, hist = _train(mlp, x, y, k_train, check_positive_int(n_steps, "n_steps"),
                       check_positive_int(batch, "batch"), float(learning_rate),
                       float(weight_decay))  # fmt: skip
    hist = np.asarray(hist)
    pred = jax.vmap(mlp)(x)
    rmse = float(jnp.sqrt(jnp.mean((pred - y) ** 2)))
    ok = bool(np.isfinite(hist).all())
    return Solution(
        mlp,
        RESULTS.successful if ok else RESULTS.nonfinite,
        dict(
            loss=hist,
            train_rmse=rmse,
            n_parameters=mlp.n_parameters,
            seconds=time.perf_counter() - t0,
        ),  # fmt: skip
    )


# --------------------------------------------------------------------------------------------------
# the model


class PanoManModel(eqx.Module):
    """A trained PanoMan model (module docstring). V vertices, E edges, K = K_B + K_F + K_H.

    - `shape_mean` `(V, 3)` m and `shape_basis` `(P, V, 3)` (P = 10, unit-variance PCs scaled by
      their standard deviation: `α ~ N(0, I)`), eq. 2.
    - `mean_lengths`, `mean_angles` `(E,)`: `X̄_L`, `X̄_A` (sums of the three part averages).
    - `components_lengths`, `components_angles` `(K, E)`: `M_L`, `M_A` (body, face, hand rows;
      `part_sizes` static `(K_B, K_F, K_H)`).
    - `neutral_lengths`, `neutral_angles` `(K,)`: the neutral coefficients per part.
    - `correction`: the correction MLP on `(β_LB, β_AB)` or `None`; `correction_edges` `(E_out,)`
      the edges it corrects (lengths then angles in its output).
    - `beta_mlp`: θ `(3·20,)` → `(β_LB, β_AB)`, or `None`.
    - `decoder`: g prepared on `shape_mean` ([`bodyprior.panoman.Decoder`][]; rebuilt at load).
    - `info`: static JSON-able training record (sizes, radii, timings, errors).
    """

    shape_mean: Float[Array, "V 3"]
    shape_basis: Float[Array, "P V 3"]
    mean_lengths: Float[Array, " E"]
    mean_angles: Float[Array, " E"]
    components_lengths: Float[Array, "K E"]
    components_angles: Float[Array, "K E"]
    neutral_lengths: Float[Array, " K"]
    neutral_angles: Float[Array, " K"]
    correction: MLP | None
    correction_edges: Int[Array, " Eo"]
    beta_mlp: MLP | None
    decoder: Decoder
    part_sizes: tuple[int, int, int] = eqx.field(static=True)
    info: str = eqx.field(static=True, default="{}")

    @property
    def topology(self) -> Topology:
        return self.decoder.topology

    @property
    def n_components(self) -> int:
        return int(self.components_lengths.shape[0])

    def part_slice(self, part: str) -> slice:
        """Rows of `part` (`"body"`, `"face"`, `"hand"`) in the component matrices."""
        k = PARTS.index(part)
        start = sum(self.part_sizes[:k])
        return slice(start, start + self.part_sizes[k])

    def neutral(self) -> tuple[Float[Array, " K"], Float[Array, " K"]]:
        """`(β_L, β_A)` of the rest body: every part at its neutral coefficients."""
        return self.neutral_lengths, self.neutral_angles

    def with_part(self, part: str, beta_part_lengths, beta_part_angles):
        """`(β_L, β_A)` `(K,)` with `part`'s coefficients set (each `(K_part,)`) and the other
        parts neutral."""
        s = self.part_slice(part)
        return (
            self.neutral_lengths.at[s].set(beta_part_lengths),
            self.neutral_angles.at[s].set(beta_part_angles),
        )

    def with_body(self, beta_body_lengths, beta_body_angles):
        """`(β_L, β_A)` with the body coefficients set and face and hands neutral."""
        return self.with_part("body", beta_body_lengths, beta_body_angles)

    def shape(self, alpha: Float[ArrayLike, " P"]) -> Float[Array, "V 3"]:
        """`B_S(α)` (eq. 2), metres."""
        return self.shape_mean + jnp.tensordot(jnp.asarray(alpha, self.shape_mean.dtype),
                                               self.shape_basis, axes=1)  # fmt: skip

    def shape_coefficients(self, rest: Float[ArrayLike, "*N V 3"]) -> np.ndarray:
        """Least-squares α of rest meshes `(V, 3)` or `(N, V, 3)` in the shape space (host):
        `(P,)` or `(N, P)`."""
        r = np.asarray(rest, np.float64)
        B = np.asarray(self.shape_basis, np.float64).reshape(self.shape_basis.shape[0], -1)
        c = (r.reshape(-1, B.shape[1]) - np.asarray(self.shape_mean, np.float64).reshape(-1)).T
        alpha = np.linalg.lstsq(B.T, c, rcond=None)[0].T
        return alpha[0] if r.ndim == 2 else alpha

    def motion_coefficients(
        self, vertices: Float[ArrayLike, "V 3"], alpha: Float[ArrayLike, " P"]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Least-squares `(β_L, β_A)` `(K,)` of a posed mesh `(V, 3)` (metres) of shape `α` (host):
        its RLA relative to `B_S(α)` projected onto all K components (eq. 3, no correction).

        The initialisation [`bodyprior.panoman.fit_panoman`][] uses with `init_mesh` (e.g. the IK
        mesh of the LBS model): on held-out frames it decoded to 10–30× less error than the
        paper's β(θ) MLP of the IK pose (docs/results_panoman.md)."""
        from ._rla import rla_encode

        v = check_array(vertices, "vertices", (self.topology.n_vertices, 3))
        a = check_array(alpha, "alpha", (self.shape_basis.shape[0],))
        x = rla_encode(jnp.asarray(v, jnp.float64), self.shape(jnp.asarray(a, jnp.float64)),
                       self.topology)  # fmt: skip
        out = []
        for X, M, mean in ((x.lengths, self.components_lengths, self.mean_lengths),
                           (x.angles, self.components_angles, self.mean_angles)):  # fmt: skip
            M = np.asarray(M, np.float64)
            out.append(_project(M, (np.asarray(X) - np.asarray(mean, np.float64))[None])[0])
        return out[0], out[1]

    def info_dict(self) -> dict:
        return json.loads(self.info)


def model_targets(
    model: PanoManModel,
    beta_lengths,
    beta_angles,
    *,
    correct: bool | ArrayLike = True,
    moving: slice | None = None,
) -> RLA:
    """`X_L(α, β)`, `X_A(α, β)` of eq. 5 (eq. 3 without the correction or with `correct=False`):
    an [`bodyprior.panoman.RLA`][] `(E,)` relative to `B_S(α)`. Traceable, differentiable.

    `correct` may also be a (traced) number: the correction is scaled by it, so a fit with and
    without the MLP shares one compiled program. `moving` (a static slice of component rows, e.g.
    [`bodyprior.panoman.PanoManModel.part_slice`][]) gives the same value but holds the
    coefficients outside it constant: their derivatives are zero, and derivatives with respect to
    the rows inside multiply only those rows of the component matrices (each block of
    [`bodyprior.panoman.fit_panoman`][] moves one part's coefficients; the correction MLP still
    sees all body coefficients)."""
    if moving is not None and not isinstance(moving, slice):
        raise ValueError(
            f"`moving` must be a slice of component rows (e.g. model.part_slice('body')) or None, "
            f"got {type(moving).__name__}."
        )
    bl = jnp.asarray(beta_lengths)
    ba = jnp.asarray(beta_angles)
    dt = model.components_lengths.dtype
    if moving is None:
        L = model.mean_lengths + bl.astype(dt) @ model.components_lengths
        A = model.mean_angles + ba.astype(dt) @ model.components_angles
    else:
        CL, CA = model.components_lengths, model.components_angles
        fixed_l = jax.lax.stop_gradient(bl.at[moving].set(0.0)).astype(dt)
        fixed_a = jax.lax.stop_gradient(ba.at[moving].set(0.0)).astype(dt)
        L = model.mean_lengths + fixed_l @ CL + bl[moving].astype(dt) @ CL[moving]
        A = model.mean_angles + fixed_a @ CA + ba[moving].astype(dt) @ CA[moving]
    if model.correction is not None and not (isinstance(correct, bool) and not correct):
        s = model.part_slice("body")
        r = model.correction(jnp.concatenate([bl[s], ba[s]]).astype(jnp.float32)).astype(dt)
        r = r * jnp.asarray(correct, dt)
        n = model.correction_edges.shape[0]
        L = L.at[model.correction_edges].add(r[:n])
        A = A.at[model.correction_edges].add(r[n:])
    return RLA(L, A)


def _evaluate(model, alpha, bl, ba, correct, align_to):
    ref = model.shape(alpha).astype(jnp.float64)
    dec = decoder_with_reference(model.decoder, ref)
    rla = jax.tree.map(
        lambda a: a.astype(jnp.float64), model_targets(model, bl, ba, correct=correct)
    )
    return _decode(dec, rla, align_to, 1e-8, 25)


_evaluate_jit = eqx.filter_jit(_evaluate)


def evaluate(
    model: PanoManModel,
    alpha: Float[ArrayLike, " P"],
    beta: tuple[ArrayLike, ArrayLike] | None = None,
    *,
    correct: bool = True,
    align_to: Float[ArrayLike, "V 3"] | None = None,
) -> Solution:
    """Vertices of `B_P(α, β)` through g (eqs. 4–5), float64 (needs `jax_enable_x64`).

    **Arguments:** `alpha` `(P,)` shape coefficients; `beta` `(β_L, β_A)` each `(K,)` (default: the
    neutral coefficients, the rest body); `correct`: add the correction MLP (eq. 5; `False` = the
    baseline of eq. 4); `align_to`: optional `(V, 3)` mesh to place the result on rigidly.

    **Returns:** a [`bodyprior.Solution`][] whose `value` is a
    [`bodyprior.panoman.DecodedMesh`][] (`.vertices` `(V, 3)` metres, residual diagnostics).
    Jitted once per model structure; batch with `jax.vmap` over `alpha`/`beta`.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError("evaluate decodes in float64: enable jax_enable_x64 first.")
    P = model.shape_basis.shape[0]
    check_array(alpha, "alpha", (P,))
    if beta is None:
        beta = model.neutral()
    if not (isinstance(beta, (tuple, list)) and len(beta) == 2):
        raise ValueError("`beta` must be a pair (beta_lengths, beta_angles).")
    K = model.n_components
    check_array(beta[0], "beta[0] (lengths)", (K,))
    check_array(beta[1], "beta[1] (angles)", (K,))
    if align_to is not None:
        check_array(align_to, "align_to", (model.topology.n_vertices, 3))
        align_to = jnp.asarray(align_to, jnp.float64)
    flag = jnp.asarray(1.0 if correct else 0.0)
    return _evaluate_jit(model, jnp.asarray(alpha, jnp.float64), jnp.asarray(beta[0]),
                         jnp.asarray(beta[1]), flag, align_to)  # fmt: skip


# --------------------------------------------------------------------------------------------------
# training


def encode_panoman_data(
    data: PanomanData, topology: Topology, *, chunk: int = 64, progress: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """RLA of every mesh of `data` relative to its identity's rest mesh (eq. 1): `(L, A)`, each
    `(N, E)` float32 (relative lengths, angle changes in radians). Expressions are path-unwrapped
    ([`bodyprior.panoman.rla_encode_unwrapped`][]: their targets are linear in the weight,
    panoman_v2 §6.3). Fixed-size chunks: one compile per kind."""
    enc = jax.jit(jax.vmap(lambda v, r: rla_encode(v, r, topology)))
    # 8 path steps: the largest facial-target hinge change (5.99 rad) turns < π per step
    enc_u = jax.jit(jax.vmap(lambda v, r: rla_encode_unwrapped(v, r, topology, n_steps=8)))
    V = np.asarray(data.vertices)
    R = np.asarray(data.rest)
    ident = np.asarray(data.identity)
    kind = np.asarray(data.kind)
    L = np.zeros((V.shape[0], topology.n_edges), np.float32)
    A = np.zeros_like(L)
    for fn, rows in ((enc, np.flatnonzero(kind != 1)), (enc_u, np.flatnonzero(kind == 1))):
        if rows.size == 0:
            continue
        c = min(chunk, rows.size)
        pad = np.concatenate([rows, np.repeat(rows[-1:], (-rows.size) % c)])
        for s in tqdm(range(0, pad.size, c), desc="RLA", disable=not progress):
            e = pad[s : s + c]
            out = fn(jnp.asarray(V[e], jnp.float64), jnp.asarray(R[ident[e]], jnp.float64))
            L[e], A[e] = np.asarray(out.lengths), np.asarray(out.angles)
    return L, A


def _project(M, x):
    """Least-squares coefficients `argmin ‖x − βM‖` for rows of `x` `(N, E)`, `M` `(K, E)`."""
    G = M @ M.T
    G = G + 1e-9 * (np.trace(G) / max(G.shape[0], 1) + 1e-30) * np.eye(G.shape[0])
    return np.linalg.solve(G, M @ x.T).T


def train_panoman(
    data: PanomanData,
    topology: Topology,
    *,
    key,
    n_components: tuple[int, int, int] = (250, 100, 50),
    radii: dict | None = None,
    shape_rest: Float[ArrayLike, "Ns V 3"] | None = None,
    n_shape: int = 10,
    sparsity: float = 2.0,
    splocs_iterations: int = 10,
    correction: bool = True,
    correction_hidden: int = 1500,
    correction_rank: int | None = 256,
    correction_steps: int = 3000,
    beta_hidden: tuple[int, int] = (400, 600),
    beta_steps: int = 3000,
    batch: int = 128,
    chunk: int = 64,
    progress: bool = True,
) -> Solution:
    """Trains PanoMan on `data` (module docstring; paper §4).

    **Arguments:**

    - `data`: a [`bodyprior.panoman.PanomanData`][] holding body, face and hand meshes.
    - `topology`: the meshes' [`bodyprior.Topology`][].
    - `key`: `jax.random` key (MLP initialisation and minibatches).
    - `n_components`: `(K_B, K_F, K_H)` components per part (same for lengths and angles; paper
      250 / 100 / 50).
    - `radii`: support radii per part, `{"body": (0.10, 0.45), "face": (0.01, 0.05),
      "hand": (0.01, 0.04)}` metres by default.
    - `shape_rest`: rest meshes for the shape PCA (default: the data's identities); `n_shape`: P.
    - `sparsity`, `splocs_iterations`: SPLOCS λ and outer iterations.
    - `correction`, `correction_hidden`, `correction_rank`, `correction_steps`: the correction MLP
      (off, width, bottleneck rank or `None` for a full output layer, training steps).
    - `beta_hidden`, `beta_steps`: the β(θ) MLP; `batch`: minibatch size of both.
    - `chunk`: meshes per jitted RLA encoding; `progress`: tqdm bars.

    **Returns:** a [`bodyprior.Solution`][] with the [`bodyprior.panoman.PanoManModel`][] and
    `stats`: `shape_explained` (variance fraction of the P PCs), per part and type the SPLOCS
    `energy` history and seconds, `fit_rla_error` (mean |residual| of the training projection
    per part and type), `correction_rmse_before/after` (RLA units, body training meshes),
    `beta_rmse`, timings.
    """
    _check_topology(topology)
    if not jax.config.jax_enable_x64:
        raise ValueError("train_panoman needs float64 (RLA encoding): enable jax_enable_x64.")
    if not isinstance(data, PanomanData):
        raise ValueError(f"`data` must be a PanomanData, got {type(data).__name__}.")
    if data.vertices.shape[1] != topology.n_vertices:
        raise ValueError(
            f"`data` has {data.vertices.shape[1]} vertices, `topology` {topology.n_vertices}."
        )
    if len(n_components) != 3:
        raise ValueError("`n_components` must be (K_body, K_face, K_hand).")
    n_components = tuple(check_positive_int(k, "n_components") for k in n_components)
    radii = {"body": (0.10, 0.45), "face": (0.01, 0.05), "hand": (0.01, 0.04), **(radii or {})}
    kind = np.asarray(data.kind)
    for i, part in enumerate(PARTS):
        if (kind == i).sum() < 2:
            raise ValueError(f"`data` needs at least 2 {part} meshes, got {(kind == i).sum()}.")
    stats: dict = {"counts": data.counts(), "n_components": list(n_components), "radii": radii}
    t_all = time.perf_counter()

    # eq. 2: shape PCA of rest bodies
    rest_all = np.asarray(data.rest if shape_rest is None else shape_rest, np.float64)
    check_array(rest_all, "shape_rest", (None, topology.n_vertices, 3))
    Xs = rest_all.reshape(rest_all.shape[0], -1)
    mu = Xs.mean(0)
    U, sv, Vt = np.linalg.svd(Xs - mu, full_matrices=False)
    P = min(int(n_shape), Vt.shape[0])
    std = sv[:P] / math.sqrt(max(Xs.shape[0] - 1, 1))
    basis = (Vt[:P] * std[:, None]).reshape(P, -1, 3)
    stats["shape_explained"] = float((sv[:P] ** 2).sum() / max((sv**2).sum(), 1e-300))
    shape_mean = mu.reshape(-1, 3)

    # RLA relative to each mesh's exact rest
    t0 = time.perf_counter()
    XL, XA = encode_panoman_data(data, topology, chunk=chunk, progress=progress)
    stats["encode_s"] = time.perf_counter() - t0

    # six decompositions
    means, comps, stats["splocs"] = {}, {}, {}
    for i, part in enumerate(PARTS):
        sel = kind == i
        for Y, X in (("L", XL), ("A", XA)):
            d_min, d_max = radii[part]
            sol = splocs(X[sel], shape_mean, topology, n_components=n_components[i],
                         d_min=d_min, d_max=d_max, sparsity=sparsity,
                         n_iterations=splocs_iterations, progress=progress)  # fmt: skip
            dec = sol.value
            means[Y, part] = np.asarray(dec.mean[:, 0], np.float64)
            comps[Y, part] = np.asarray(dec.components[:, :, 0], np.float64)
            stats["splocs"][f"{Y}_{part}"] = dict(
                energy=[float(e) for e in np.asarray(sol.stats["energy"])],
                init_s=float(sol.stats["init_s"]),
                iteration_s=[float(s) for s in np.asarray(sol.stats["iteration_s"])],
            )
    ML = np.concatenate([comps["L", p] for p in PARTS])
    MA = np.concatenate([comps["A", p] for p in PARTS])
    mean_L = sum(means["L", p] for p in PARTS)
    mean_A = sum(means["A", p] for p in PARTS)
    sizes = tuple(int(comps["L", p].shape[0]) for p in PARTS)

    # neutral coefficients per part: argmin ‖X̄_YZ + M_YZ β‖
    neutral = {Y: np.concatenate([_project(comps[Y, p], -means[Y, p][None])[0] for p in PARTS])
               for Y in ("L", "A")}  # fmt: skip

    # training projections per part (other parts neutral) and their errors
    offsets = np.cumsum((0,) + sizes)
    beta_hat = {}
    stats["fit_rla_error"] = {}
    for i, part in enumerate(PARTS):
        sel = kind == i
        s = slice(offsets[i], offsets[i + 1])
        for Y, X, M, mean in (("L", XL, ML, mean_L), ("A", XA, MA, mean_A)):
            base = mean + neutral[Y] @ M - neutral[Y][s] @ M[s]
            b = _project(M[s], X[sel] - base)
            beta_hat[Y, part] = b
            res = X[sel] - base - b @ M[s]
            stats["fit_rla_error"][f"{Y}_{part}"] = float(np.abs(res).mean())
            if part == "body":
                beta_hat[Y, "residual"] = res

    # correction MLP on the body coefficients
    k_corr, k_beta = jax.random.split(key)
    corr = None
    sb = slice(offsets[0], offsets[1])
    support = (np.abs(ML[sb]).max(0) > 0) | (np.abs(MA[sb]).max(0) > 0)
    corr_edges = np.flatnonzero(support).astype(np.int32)
    xb = np.concatenate([beta_hat["L", "body"], beta_hat["A", "body"]], 1)
    if correction:
        y = np.concatenate([beta_hat["L", "residual"][:, corr_edges],
                            beta_hat["A", "residual"][:, corr_edges]], 1)  # fmt: skip
        sol = fit_mlp(k_corr, xb, y, (correction_hidden,), rank=correction_rank,
                      n_steps=correction_steps, batch=batch)  # fmt: skip
        corr = sol.value
        pred = np.asarray(jax.vmap(corr)(jnp.asarray(xb, jnp.float32)))
        stats["correction"] = dict(
            rmse_before=float(np.sqrt(np.mean(y**2))),
            rmse_after=float(np.sqrt(np.mean((y - pred) ** 2))),
            n_parameters=sol.stats["n_parameters"],
            seconds=sol.stats["seconds"],
            n_edges=int(corr_edges.size),
        )

    # β(θ): cmu_mb pose of the 20 pose joints → body coefficients
    beta_mlp = None
    if beta_hidden:
        names = load_default_body("cmu_mb").joint_names  # the joint order of `body_pose`
        pose = jnp.asarray(np.asarray(data.body_pose)[kind == 0])
        theta = jax.vmap(lambda p: pose_features(p, names))(pose)
        # input scales ≥ 0.1 rad: joints the retargeted clips barely move (Spine, Neck1: std
        # 0.006–0.03 rad) otherwise turn an IK pose's few degrees there into 10–30 standard
        # deviations, and β(θ_IK) decoded 481 mm from the truth (β(θ_true): 63 mm)
        sol = fit_mlp(k_beta, theta, xb, tuple(beta_hidden), n_steps=beta_steps, batch=batch,
                      x_scale_floor=0.1)  # fmt: skip
        beta_mlp = sol.value
        stats["beta_mlp"] = dict(train_rmse=sol.stats["train_rmse"],
                                 n_parameters=sol.stats["n_parameters"],
                                 seconds=sol.stats["seconds"])  # fmt: skip

    decoder = prepare_decoder(shape_mean, topology)
    stats["total_s"] = time.perf_counter() - t_all
    info = dict(stats, splocs={k: {kk: vv for kk, vv in v.items() if kk != "energy"}
                               for k, v in stats["splocs"].items()})  # fmt: skip
    model = PanoManModel(
        shape_mean=jnp.asarray(shape_mean),
        shape_basis=jnp.asarray(basis),
        mean_lengths=jnp.asarray(mean_L),
        mean_angles=jnp.asarray(mean_A),
        components_lengths=jnp.asarray(ML),
        components_angles=jnp.asarray(MA),
        neutral_lengths=jnp.asarray(neutral["L"]),
        neutral_angles=jnp.asarray(neutral["A"]),
        correction=corr,
        correction_edges=jnp.asarray(corr_edges),
        beta_mlp=beta_mlp,
        decoder=decoder,
        part_sizes=sizes,
        info=json.dumps(info, default=float),
    )
    stats["beta_hat"] = {f"{Y}_{p}": beta_hat[Y, p] for Y in "LA" for p in PARTS}
    return Solution(model, RESULTS.successful, stats)


def pose_features(body_pose: Float[ArrayLike, "J 3"], joint_names: tuple[str, ...]) -> Array:
    """θ of the β MLP: the axis-angle of the 20 pose joints of a `cmu_mb` pose, flattened
    `(60,)`, radians."""
    pj = jnp.asarray([joint_names.index(n) for n in POSE_JOINTS])
    return jnp.asarray(body_pose)[pj].reshape(-1)


# --------------------------------------------------------------------------------------------------
# save / load


def _mlp_arrays(prefix: str, mlp: MLP | None, out: dict, meta: dict):
    if mlp is None:
        meta[prefix] = None
        return
    meta[prefix] = dict(relu=list(mlp.relu), bias=[b is not None for b in mlp.biases])
    for i, (W, b) in enumerate(zip(mlp.weights, mlp.biases)):
        out[f"{prefix}.W{i}"] = np.asarray(W)
        if b is not None:
            out[f"{prefix}.b{i}"] = np.asarray(b)
    for f in ("x_mean", "x_scale", "y_mean", "y_scale"):
        out[f"{prefix}.{f}"] = np.asarray(getattr(mlp, f))


def _mlp_from(prefix: str, z, meta) -> MLP | None:
    m = meta.get(prefix)
    if m is None:
        return None
    n = len(m["relu"])
    Ws = tuple(jnp.asarray(z[f"{prefix}.W{i}"]) for i in range(n))
    bs = tuple(jnp.asarray(z[f"{prefix}.b{i}"]) if m["bias"][i] else None for i in range(n))
    f = {k: jnp.asarray(z[f"{prefix}.{k}"]) for k in ("x_mean", "x_scale", "y_mean", "y_scale")}
    return MLP(Ws, bs, relu=tuple(m["relu"]), **f)


def _model_arrays(model: PanoManModel, float16: bool) -> tuple[dict, dict]:
    """The arrays and metadata of `model`'s file (format `bodyprior.panoman_model` v1)."""
    arrays: dict = {}
    meta = dict(format=FORMAT, format_version=FORMAT_VERSION, part_sizes=list(model.part_sizes),
                info=model.info, float16=bool(float16))  # fmt: skip
    ft = np.float16 if float16 else np.float32
    for name in ("components_lengths", "components_angles"):
        M = np.asarray(getattr(model, name))
        r, c = np.nonzero(M)
        arrays[f"{name}.rows"] = r.astype(np.int32)
        arrays[f"{name}.cols"] = c.astype(np.int32)
        arrays[f"{name}.vals"] = M[r, c].astype(ft)
        arrays[f"{name}.shape"] = np.asarray(M.shape, np.int64)
    for name in ("shape_mean", "shape_basis", "mean_lengths", "mean_angles", "neutral_lengths",
                 "neutral_angles"):  # fmt: skip
        arrays[name] = np.asarray(getattr(model, name), np.float64)
    arrays["correction_edges"] = np.asarray(model.correction_edges, np.int32)
    arrays["faces"] = np.asarray(model.topology.faces, np.int32)
    arrays["anchor_face"] = np.asarray(model.decoder.anchor_face, np.int64)
    _mlp_arrays("correction", model.correction, arrays, meta)
    _mlp_arrays("beta_mlp", model.beta_mlp, arrays, meta)
    if float16:
        for k in list(arrays):
            if k.startswith(("correction.W", "beta_mlp.W")):
                arrays[k] = arrays[k].astype(np.float16)
    return arrays, meta


def _write_npz(path: str | os.PathLike, arrays: dict, meta: dict) -> None:
    arrays = dict(arrays, metadata=np.asarray(json.dumps(meta)))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def _read_npz(path: str | os.PathLike, what: str) -> tuple[dict, dict]:
    path = os.fspath(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            z = dict(z)
        meta = json.loads(str(z.pop("metadata")))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path!r} is not a readable {what} ({e}).") from e
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{path!r} has format {meta.get('format')!r} v{meta.get('format_version')}, expected "
            f"{FORMAT!r} v{FORMAT_VERSION}."
        )
    return z, meta


def save_panoman(model: PanoManModel, path: str | os.PathLike, *, float16: bool = False) -> None:
    """Writes `model` to an `.npz` file atomically (format `bodyprior.panoman_model` v1).

    The component matrices are stored sparse (their non-zeros; SPLOCS components are localized),
    in float16 if `float16` (the error it costs: see `docs/results_panoman.md`). The decoder is
    rebuilt from the topology and the shape mean at load.
    """
    _write_npz(path, *_model_arrays(model, float16))


def load_panoman(path: str | os.PathLike) -> PanoManModel:
    """Reads a model written by [`bodyprior.panoman.save_panoman`][] (or the model part of a
    [`bodyprior.panoman.save_kit`][] file; validated: format, version, shapes; a `ValueError` says
    what is wrong)."""
    z, meta = _read_npz(path, "PanoMan model")
    return _model_from(z, meta, os.fspath(path))


def _model_from(z: dict, meta: dict, path: str) -> PanoManModel:
    topology = Topology.from_faces(z["faces"], allow_boundary=True)
    V, E = topology.n_vertices, topology.n_edges
    mats = {}
    for name in ("components_lengths", "components_angles"):
        K, Ec = (int(s) for s in z[f"{name}.shape"])
        if Ec != E:
            raise ValueError(f"{path!r}: `{name}` has {Ec} edges, the faces give {E}.")
        M = np.zeros((K, E), np.float64)
        M[z[f"{name}.rows"], z[f"{name}.cols"]] = z[f"{name}.vals"].astype(np.float64)
        mats[name] = jnp.asarray(M)
    sizes = tuple(int(s) for s in meta["part_sizes"])
    K = mats["components_lengths"].shape[0]
    if sum(sizes) != K:
        raise ValueError(f"{path!r}: part sizes {sizes} do not add up to {K} components.")
    for name, shp in (("shape_mean", (V, 3)), ("mean_lengths", (E,)), ("mean_angles", (E,)),
                      ("neutral_lengths", (K,)), ("neutral_angles", (K,))):  # fmt: skip
        if z[name].shape != shp:
            raise ValueError(f"{path!r}: `{name}` has shape {z[name].shape}, expected {shp}.")
    shape_mean = z["shape_mean"]
    mlps = {}
    for p in ("correction", "beta_mlp"):
        m = _mlp_from(p, z, meta)
        if m is not None:
            m = eqx.tree_at(lambda q: q.weights, m, tuple(w.astype(jnp.float32) for w in m.weights))
        mlps[p] = m
    return PanoManModel(
        shape_mean=jnp.asarray(shape_mean),
        shape_basis=jnp.asarray(z["shape_basis"]),
        mean_lengths=jnp.asarray(z["mean_lengths"]),
        mean_angles=jnp.asarray(z["mean_angles"]),
        components_lengths=mats["components_lengths"],
        components_angles=mats["components_angles"],
        neutral_lengths=jnp.asarray(z["neutral_lengths"]),
        neutral_angles=jnp.asarray(z["neutral_angles"]),
        correction=mlps["correction"],
        correction_edges=jnp.asarray(z["correction_edges"]),
        beta_mlp=mlps["beta_mlp"],
        decoder=prepare_decoder(shape_mean, topology, anchor_face=int(z["anchor_face"])),
        part_sizes=sizes,
        info=str(meta.get("info", "{}")),
    )
