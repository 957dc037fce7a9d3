"""Reconstruction from sparse constraints (paper §5): the LBS model on PanoMan's shape space (the
SMPL stand-in, used for IK initialisation and as the baseline), the posed joint regressor, and
`fit_panoman` — shell energy plus constraints over vertices and parameters jointly, by block
coordinate descent face → body → hand, initialised by IK → θ → β(θ) → g (§5.3).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._kinematics import forward_kinematics
from .._rotations import axis_angle_to_matrix
from .._skinning import dqs, lbs
from .._solution import RESULTS, Solution
from .._topology import Topology
from .._validate import check_array
from ._data import PanomanData
from ._model import PARTS, PanoManModel, _evaluate_jit, model_targets, pose_features
from ._rla import RLA
from ._solve import (
    ShellConstraints,
    ShellSolver,
    prepare_shell_solver,
    shell_solve,
)

__all__ = [
    "JointRegressor",
    "LbsModel",
    "PanoManFit",
    "PanoManSolver",
    "fit_joint_regressor",
    "fit_lbs",
    "fit_panoman",
    "make_lbs_model",
    "prepare_panoman_solver",
]


class JointRegressor(eqx.Module):
    """Joints as a fixed linear function of the vertices: `J_j = Σ_m w_jm v_{i_jm}` (rows sum
    to 1). `indices`, `weights` `(J, M)`."""

    indices: Int[Array, "J M"]
    weights: Float[Array, "J M"]

    def __call__(self, vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "J 3"]:
        return jnp.einsum("jm,jmd->jd", self.weights, jnp.asarray(vertices)[self.indices])


def fit_joint_regressor(
    vertices: Float[ArrayLike, "N V 3"],
    joints: Float[ArrayLike, "N J 3"],
    *,
    n_neighbors: int = 256,
) -> JointRegressor:
    """Fits a joint regressor on posed meshes with their exact joints (host, least squares).

    Each joint uses the `n_neighbors` vertices nearest to it on the first mesh (256, as the
    default body's rest regressor; 32 gave 16 mm mean held-out error, 256 gave 3.9 mm); its
    weights are the **convex** combination (`w ≥ 0`, `Σ w = 1`: it commutes with rigid motions
    and stays well conditioned) minimising `Σ_n ‖Σ_m w_m v_nm − J_n‖²`, by non-negative least
    squares with the sum as a heavily weighted extra row. Fit on posed generator output, not at rest
    (panoman_v2 §6.11). **Returns:** a [`bodyprior.panoman.JointRegressor`][].
    """
    from scipy.optimize import nnls

    V = np.asarray(vertices, np.float64)
    Jt = np.asarray(joints, np.float64)
    check_array(V, "vertices", ("N", None, 3))
    check_array(Jt, "joints", (V.shape[0], None, 3))
    n_neighbors = int(min(n_neighbors, V.shape[1]))
    idx = np.zeros((Jt.shape[1], n_neighbors), np.int32)
    W = np.zeros((Jt.shape[1], n_neighbors))
    for j in range(Jt.shape[1]):
        near = np.argsort(np.linalg.norm(V[0] - Jt[0, j], axis=1))[:n_neighbors]
        X = V[:, near].transpose(0, 2, 1).reshape(-1, n_neighbors)  # (N·3, M)
        y = Jt[:, j].reshape(-1)
        big = 1e3 * max(np.abs(X).max(), 1.0)
        w, _ = nnls(np.vstack([X, big * np.ones((1, n_neighbors))]), np.append(y, big))
        idx[j], W[j] = near, w / max(w.sum(), 1e-300)
    return JointRegressor(jnp.asarray(idx), jnp.asarray(W))


# --------------------------------------------------------------------------------------------------
# LBS model on the same shape space (the SMPL stand-in)


class LbsModel(eqx.Module):
    """`LBS(B_S(α), FK(θ, J(α)))`: PanoMan's shape space with `cmu_mb` skinning.

    - `shape_mean` `(V, 3)`, `shape_basis` `(P, V, 3)`: as the PanoMan model's (eq. 2).
    - `joint_mean` `(J, 3)`, `joint_basis` `(P, J, 3)`: rest joints linear in α (least squares on
      the training identities' exact rest joints).
    - `skin_indices`, `skin_weights` `(V, K)`: the `cmu_mb` weights on this vertex subset.
    - `parents`: static bone tree; `skinning`: `"lbs"` (the SMPL stand-in) or `"dqs"`
      (dual-quaternion skinning, the paper's other skinning comparison).
    """

    shape_mean: Float[Array, "V 3"]
    shape_basis: Float[Array, "P V 3"]
    joint_mean: Float[Array, "J 3"]
    joint_basis: Float[Array, "P J 3"]
    skin_indices: Int[Array, "V K"]
    skin_weights: Float[Array, "V K"]
    parents: tuple[int, ...] = eqx.field(static=True)
    skinning: str = eqx.field(static=True, default="lbs")

    def __call__(self, alpha, pose, translation):
        """Vertices `(V, 3)` and joints `(J, 3)`; `pose` `(J, 3)` axis-angle, `translation`
        `(3,)` metres."""
        rest = self.shape_mean + jnp.tensordot(alpha, self.shape_basis, axes=1)
        j = self.joint_mean + jnp.tensordot(alpha, self.joint_basis, axes=1)
        R = jax.vmap(axis_angle_to_matrix)(pose)
        A, posed = forward_kinematics(self.parents, R, j, translation)
        skin = dqs if self.skinning == "dqs" else lbs
        return skin(rest, self.skin_indices, self.skin_weights, A), posed


def make_lbs_model(
    model: PanoManModel, data: PanomanData, body, *, skinning: str = "lbs"
) -> LbsModel:
    """The LBS baseline on `model`'s shape space: rest joints regressed on α from the identities of
    `data`; `body` the `cmu_mb` [`bodyprior.DefaultBody`][] (skin weights, bone tree);
    `skinning` `"lbs"` or `"dqs"`."""
    if skinning not in ("lbs", "dqs"):
        raise ValueError(f"`skinning` must be 'lbs' or 'dqs', got {skinning!r}.")
    alpha = model.shape_coefficients(data.rest)
    Jr = np.asarray(data.rest_joints, np.float64).reshape(alpha.shape[0], -1)
    X = np.concatenate([np.ones((alpha.shape[0], 1)), alpha], 1)
    coef = np.linalg.lstsq(X, Jr, rcond=None)[0]
    J = body.n_joints
    vm = np.asarray(data.vertex_map)
    return LbsModel(
        shape_mean=model.shape_mean,
        shape_basis=model.shape_basis,
        joint_mean=jnp.asarray(coef[0].reshape(J, 3)),
        joint_basis=jnp.asarray(coef[1:].reshape(-1, J, 3)),
        skin_indices=jnp.asarray(np.asarray(body.rig.skin_indices)[vm]),
        skin_weights=jnp.asarray(np.asarray(body.rig.skin_weights, np.float64)[vm]),
        parents=body.parents,
        skinning=skinning,
    )


def _lbs_residuals(y, args):
    lbsm, cons, prior = args
    alpha, pose, t = y
    v, j = lbsm(alpha, pose, t)
    rh = jnp.sqrt(cons.handle_weight)[:, None] * (v[cons.handle_index] - cons.handle_position)
    rj = jnp.sqrt(cons.joint_weight)[:, None] * (
        jnp.einsum("jm,jmd->jd", cons.joint_coeffs, j[cons.joint_indices]) - cons.joint_position
    )
    return (rh.ravel(), rj.ravel(), prior[0] * alpha, prior[1] * pose[1:].ravel())


@eqx.filter_jit
def _fit_lbs(lbsm, cons, prior, y0, max_steps):
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10, linear_solver=lx.Normal(lx.Cholesky()))
    return optx.least_squares(_lbs_residuals, solver, y0, (lbsm, cons, prior),
                              max_steps=max_steps, throw=False)  # fmt: skip


def fit_lbs(
    lbs_model: LbsModel,
    constraints: ShellConstraints,
    *,
    alpha_prior: float = 1e-3,
    pose_prior: float = 1e-3,
    max_steps: int = 100,
) -> Solution:
    """IK of the LBS model to constraints (vertex handles; joint constraints whose `joint_indices`
    index **joints** of the skeleton here, one joint per row with coefficient 1).

    Levenberg–Marquardt (optimistix, float64) over `(α, θ, t)` from the mean shape and zero pose
    (translation: the weighted mean offset of the joint, else handle, targets), with small Tikhonov
    priors `alpha_prior`, `pose_prior` on α and the non-root pose. **Returns:** a
    [`bodyprior.Solution`][] with `value` `(α (P,), pose (J, 3), translation (3,))` and `stats`
    `steps`, `vertices`, `joints`, `seconds`.
    """
    P = lbs_model.shape_basis.shape[0]
    J = lbs_model.joint_mean.shape[0]
    # translation start: the weighted mean offset of the joint targets from the mean skeleton's
    # joints, else of the handles from the mean shape's vertices (zero-weight rows, e.g. padding,
    # do not count)
    c = constraints
    groups = [(c.handle_weight, c.handle_position, lbs_model.shape_mean[c.handle_index])]
    if c.joint_indices.shape[0]:
        groups.insert(0, (c.joint_weight, c.joint_position,
                          lbs_model.joint_mean[c.joint_indices[:, 0]]))  # fmt: skip
    trans = np.zeros(3)
    for w, pos, ref in groups:
        w = np.asarray(w)
        if w.size and w.sum() > 0:
            trans = (w[:, None] * (np.asarray(pos) - np.asarray(ref))).sum(0) / w.sum()
            break
    y0 = (jnp.zeros(P), jnp.zeros((J, 3)), jnp.asarray(trans))
    prior = (jnp.sqrt(alpha_prior), jnp.sqrt(pose_prior))
    t0 = time.perf_counter()
    sol = _fit_lbs(lbs_model, constraints, prior, y0, int(max_steps))
    alpha, pose, t = sol.value
    v, j = lbs_model(alpha, pose, t)
    ok = bool(jnp.all(jnp.isfinite(v)))
    return Solution(
        (alpha, pose, t),
        RESULTS.successful if ok else RESULTS.nonfinite,
        dict(
            steps=int(sol.stats["num_steps"]),
            vertices=v,
            joints=j,
            seconds=time.perf_counter() - t0,
        ),  # fmt: skip
    )


# --------------------------------------------------------------------------------------------------
# PanoMan fit


class PanoManFit(eqx.Module):
    """Result of [`bodyprior.panoman.fit_panoman`][]: `vertices` `(V, 3)` m, `alpha` `(P,)`,
    `beta_lengths`, `beta_angles` `(K,)`; `init_vertices` the decoded initialisation."""

    vertices: Float[Array, "V 3"]
    alpha: Float[Array, " P"]
    beta_lengths: Float[Array, " K"]
    beta_angles: Float[Array, " K"]
    init_vertices: Float[Array, "V 3"]


class _Region(eqx.Module):
    """One part's region for a local block solve: the sub-mesh of the faces within two rings of
    the free vertices, with the vertices outside the free set fixed (module of `fit_panoman`)."""

    vertices: Int[Array, " n"]  # full-mesh index of each sub-mesh vertex (ascending)
    edges: Int[Array, " e"]  # full-mesh edge of each sub-mesh edge
    vertex_map: Int[Array, " V"]  # sub-mesh index of each full-mesh vertex, -1 outside
    face_map: Int[Array, " F"]  # sub-mesh index of each full-mesh face, -1 outside
    free: Bool[Array, " n"]
    topology: Topology
    solver: ShellSolver
    n_free: int = eqx.field(static=True)


class _PartRows(eqx.Module):
    """One part's component rows `M_L`, `M_A` `(K_part, E)` in coordinate form (row within the
    part, edge, value of each non-zero): SPLOCS components are local (5-6 % non-zero on the
    default body), so a block's targets and their derivatives read ~18x less than the dense
    rows."""

    rows_l: Int[Array, " nl"]
    cols_l: Int[Array, " nl"]
    vals_l: Array
    rows_a: Int[Array, " na"]
    cols_a: Int[Array, " na"]
    vals_a: Array

    def apply(self, bl, ba, n_edges: int) -> tuple[Array, Array]:
        """`(β_L M_L, β_A M_A)` `(E,)` for part coefficients `(K_part,)` each."""
        L = jax.ops.segment_sum(bl.astype(self.vals_l.dtype)[self.rows_l] * self.vals_l,
                                self.cols_l, n_edges)  # fmt: skip
        A = jax.ops.segment_sum(ba.astype(self.vals_a.dtype)[self.rows_a] * self.vals_a,
                                self.cols_a, n_edges)  # fmt: skip
        return L, A


def _part_rows(model: PanoManModel, part: str) -> _PartRows:
    s = model.part_slice(part)
    out = []
    for C in (model.components_lengths, model.components_angles):
        C = np.asarray(C)[s]
        r, c = np.nonzero(C)
        out += [jnp.asarray(r, jnp.int32), jnp.asarray(c, jnp.int32), jnp.asarray(C[r, c])]
    return _PartRows(*out)


def _fingerprint(model: PanoManModel) -> str:
    """A cheap identity of the model's component matrices (a strided sample's bytes)."""
    import hashlib

    h = hashlib.sha1()
    for C in (model.components_lengths, model.components_angles):
        C = np.asarray(C)
        h.update(str(C.shape).encode())
        h.update(np.ascontiguousarray(C[:, ::97]).tobytes())
    return h.hexdigest()


class PanoManSolver(eqx.Module):
    """What [`bodyprior.panoman.fit_panoman`][] precomputes once per model (host side): the
    whole mesh's [`bodyprior.panoman.ShellSolver`][], each part's component rows in coordinate
    form (the block targets), and, for the parts solved locally, the part's region (sub-mesh,
    fixed rings, edge and vertex maps) with its own solver. Build with
    [`bodyprior.panoman.prepare_panoman_solver`][]."""

    whole: ShellSolver
    regions: tuple  # per part of PARTS: a _Region or None (that part's block moves all vertices)
    rows: tuple  # per part of PARTS: its _PartRows
    rings: int = eqx.field(static=True)
    fingerprint: str = eqx.field(static=True)

    def region(self, part: str):
        return self.regions[PARTS.index(part)]


def _part_support(model: PanoManModel, part: str) -> np.ndarray:
    """`(E,)` bool: edges on which a component of `part` (lengths or angles) is non-zero."""
    s = model.part_slice(part)
    cl = np.asarray(model.components_lengths)[s]
    ca = np.asarray(model.components_angles)[s]
    return (cl != 0).any(0) | (ca != 0).any(0)


def _make_region(top: Topology, support: np.ndarray, rings: int) -> _Region:
    V, F = top.n_vertices, top.n_faces
    faces = np.asarray(top.faces)
    e, opp = np.asarray(top.edges), np.asarray(top.edge_opposite)
    free = np.zeros(V, bool)
    free[e[support].ravel()] = True
    o = opp[support].ravel()
    free[o[o >= 0]] = True  # the hinge stencils of the support edges
    for _ in range(rings):
        free = _grow(free, faces)
    # Every residual that reads a free vertex lives on the faces within two rings of it.
    v1 = _grow(free, faces)
    keep = v1[faces].any(1)
    sub_vertices = np.unique(faces[keep])
    vmap = np.full(V, -1, np.int64)
    vmap[sub_vertices] = np.arange(sub_vertices.size)
    fmap = np.full(F, -1, np.int64)
    fmap[keep] = np.arange(int(keep.sum()))
    sub = Topology.from_faces(vmap[faces[keep]], int(sub_vertices.size))
    se = np.asarray(sub.edges)
    key_full = e[:, 0].astype(np.int64) * V + e[:, 1]
    key_sub = sub_vertices[se[:, 0]].astype(np.int64) * V + sub_vertices[se[:, 1]]
    emap = np.searchsorted(key_full, key_sub)  # full edges are sorted lexicographically
    if not np.array_equal(key_full[emap], key_sub):
        raise AssertionError("region edges not found in the full mesh")
    i32 = lambda a: jnp.asarray(a, jnp.int32)  # noqa: E731
    return _Region(
        i32(sub_vertices), i32(emap), i32(vmap), i32(fmap), jnp.asarray(free[sub_vertices]),
        sub, prepare_shell_solver(sub), int(free.sum()),
    )  # fmt: skip


def _grow(mask: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """`mask` grown by one ring: every vertex of a face that touches it."""
    out = mask.copy()
    out[faces[mask[faces].any(1)].ravel()] = True
    return out


def prepare_panoman_solver(
    model: PanoManModel, *, local: tuple[str, ...] = ("face", "hand"), rings: int = 2
) -> PanoManSolver:
    """Precomputes the [`bodyprior.panoman.PanoManSolver`][] of `model` for
    [`bodyprior.panoman.fit_panoman`][] (host side; reuse it across frames).

    - `local`: the parts whose block moves only its region: the vertices of the hinges on which a
      component of the part is non-zero (its SPLOCS support), grown by `rings` rings; the rest of
      the mesh stays where the previous block left it. The face and hand blocks change only
      their part's targets (the correction MLP reads body coefficients alone), so the rest of
      the mesh has nothing to gain from them beyond what the body block does; their solves then
      run on a sub-mesh (~15 % of the body's vertices each), which the paper's per-iteration
      costs suggest it does too (face 2.5 s, body 11.9 s, hand 1.1 s; Table 1). `()` moves all
      vertices in every block.
    """
    if not isinstance(model, PanoManModel):
        raise ValueError(f"`model` must be a PanoManModel, got {type(model).__name__}.")
    for part in local:
        if part not in PARTS or part == "body":
            raise ValueError(f"`local` entries must be 'face' or 'hand', got {part!r}.")
    if isinstance(rings, bool) or not isinstance(rings, (int, np.integer)) or rings < 0:
        raise ValueError(f"`rings` must be an int >= 0, got {rings!r}.")
    top = model.topology
    regions = tuple(
        _make_region(top, _part_support(model, part), int(rings)) if part in local else None
        for part in PARTS
    )
    rows = tuple(_part_rows(model, part) for part in PARTS)
    return PanoManSolver(prepare_shell_solver(top), regions, rows, int(rings), _fingerprint(model))


class _LocalTargets(eqx.Module):
    """The targets of a face or hand block on its region's edges: `X(β) = X(β⁰) + (β − β⁰) M`
    with `M` the part's component rows on those edges. Exact: eq. 5 is linear in a part's
    coefficients, and the correction MLP reads only the body's."""

    base_lengths: Array
    base_angles: Array
    comp_lengths: Array
    comp_angles: Array
    bl0: Array
    ba0: Array

    def __call__(self, params) -> RLA:
        dt = self.comp_lengths.dtype
        L = self.base_lengths + (params["bl"] - self.bl0).astype(dt) @ self.comp_lengths
        A = self.base_angles + (params["ba"] - self.ba0).astype(dt) @ self.comp_angles
        return RLA(L, A)


def _local_constraints(cons: ShellConstraints, region: _Region, V: Array) -> ShellConstraints:
    """`cons` on the region's sub-mesh, same shapes: handles and surface points outside it get
    weight 0; regressor entries outside it move into the joint target (those vertices are
    fixed)."""
    vm, fm = region.vertex_map, region.face_map
    hi = vm[cons.handle_index]
    ji = vm[cons.joint_indices]
    inside = ji >= 0
    outside_sum = jnp.einsum(
        "jm,jmd->jd", jnp.where(inside, 0.0, cons.joint_coeffs), V[cons.joint_indices]
    )
    sf = fm[cons.surface_face]
    return eqx.tree_at(
        lambda c: (c.handle_index, c.handle_weight, c.joint_indices, c.joint_coeffs,
                   c.joint_position, c.surface_face, c.surface_weight),
        cons,
        (jnp.maximum(hi, 0), jnp.where(hi >= 0, cons.handle_weight, 0.0),
         jnp.maximum(ji, 0), jnp.where(inside, cons.joint_coeffs, 0.0),
         cons.joint_position - outside_sum,
         jnp.maximum(sf, 0), jnp.where(sf >= 0, cons.surface_weight, 0.0)),
    )  # fmt: skip


class _BlockTargets(eqx.Module):
    """`targets(params)` for one whole-mesh block: `X = X_fixed + β_m M_m (+ R(β_B))` with the
    block's part coefficients `β_m` moving (and α for the body block, which only the rest mesh
    reads). `X_fixed` (the mean, the other parts' rows and, outside the body block, the
    correction of the fixed body coefficients) is evaluated once per block; the moving rows are
    applied in coordinate form. Equal to `model_targets` to rounding (tested)."""

    model: PanoManModel  # its shape space (the rest mesh) and, in the body block, the MLP
    alpha: Array
    base_lengths: Array
    base_angles: Array
    rows: _PartRows
    correct: Array  # 1.0 with the correction MLP, 0.0 without (a leaf: one compile for both)
    with_alpha: bool = eqx.field(static=True)  # the body block: α moves, the MLP reads β_m
    start: int = eqx.field(static=True)  # the moving part's first component row

    def __call__(self, params) -> RLA:
        E = self.base_lengths.shape[0]
        dL, dA = self.rows.apply(params["bl"], params["ba"], E)
        L, A = self.base_lengths + dL, self.base_angles + dA
        m = self.model
        if self.with_alpha and m.correction is not None:
            x = jnp.concatenate([params["bl"], params["ba"]]).astype(jnp.float32)
            r = m.correction(x).astype(L.dtype) * jnp.asarray(self.correct, L.dtype)
            n = m.correction_edges.shape[0]
            L = L.at[m.correction_edges].add(r[:n])
            A = A.at[m.correction_edges].add(r[n:])
        return RLA(L, A)

    def rest(self, params):
        return self.model.shape(params["alpha"] if self.with_alpha else self.alpha)

    def weighted_gram(self, params, w):
        """`Jᵀ diag(w) J` `(P, P)` over the flat parameters (`ravel_pytree` order) for the
        targets' Jacobian `J` `(2E, P)` (lengths then angles) and weights `w` `(2E,)`, or
        `None` where the structure does not hold. From the structure: the moving rows `M_m`
        (`M diag(w) Mᵀ`) and, in the body block, the correction's Jacobian
        `y_s W_lastᵀ ∂h/∂β` through its linear last layer `W_last` `(rank, 2 E_out)`. The
        dense Jacobian would be `(P, 2E)` and its Gram 20.8 G multiply-adds on the full body;
        the shell solver's `_param_gram` calls this when a targets object has it."""
        m = self.model
        E = self.base_lengths.shape[0]
        K = params["bl"].shape[0]
        wl, wa = w[:E], w[E:]
        f64 = jnp.float64
        sl = slice(self.start, self.start + K)
        ML = m.components_lengths[sl].astype(f64)
        MA = m.components_angles[sl].astype(f64)
        Gll = (ML * wl) @ ML.T
        Gaa = (MA * wa) @ MA.T
        Gla = jnp.zeros((K, K), f64)
        mlp = m.correction
        if self.with_alpha and mlp is not None:
            if mlp.relu[-1]:
                return None  # no linear last layer: the solver's general path
            x0 = jnp.concatenate([params["bl"], params["ba"]]).astype(jnp.float32)
            Jh = jax.jacfwd(lambda x: _mlp_hidden(mlp, x))(x0).astype(f64)  # (rank, 2K)
            Jh = Jh * jnp.asarray(mlp.y_scale, f64) * jnp.asarray(self.correct, f64)
            ce = m.correction_edges
            n = ce.shape[0]
            W = mlp.weights[-1].astype(f64)  # (rank, 2n)
            UL, UA = W[:, :n], W[:, n:]  # rank x n
            # cross terms M diag(w) U^T (K, rank) and the correction's own U diag(w) U^T
            CL = (ML[:, ce] * wl[ce]) @ UL.T
            CA = (MA[:, ce] * wa[ce]) @ UA.T
            UU = (UL * wl[ce]) @ UL.T + (UA * wa[ce]) @ UA.T
            Jl, Ja = Jh[:, :K], Jh[:, K:]  # (rank, K) each
            Gll = Gll + CL @ Jl + Jl.T @ CL.T + Jl.T @ UU @ Jl
            Gaa = Gaa + CA @ Ja + Ja.T @ CA.T + Ja.T @ UU @ Ja
            Gla = CL @ Ja + Jl.T @ CA.T + Jl.T @ UU @ Ja
        # flat order of the parameter pytree (`ravel_pytree`: the dict's sorted keys)
        pos, off = {}, 0
        for k in sorted(params):
            n = int(np.size(params[k]))
            pos[k], off = np.arange(off, off + n), off + n
        il, ia = pos["bl"], pos["ba"]
        G = jnp.zeros((off, off), f64)
        G = G.at[np.ix_(il, il)].set(Gll).at[np.ix_(ia, ia)].set(Gaa)
        return G.at[np.ix_(il, ia)].set(Gla).at[np.ix_(ia, il)].set(Gla.T)


def _mlp_hidden(mlp, x):
    """The MLP's standardised output before its last (linear) layer: `h` with
    `mlp(x) = y_mean + y_scale · (h W_last + b_last)`."""
    h = (jnp.asarray(x, mlp.x_mean.dtype) - mlp.x_mean) / mlp.x_scale
    for W, b, r in zip(mlp.weights[:-1], mlp.biases[:-1], mlp.relu[:-1]):
        h = h @ W
        if b is not None:
            h = h + b
        if r:
            h = jax.nn.relu(h)
    return h


class _Rest(eqx.Module):
    targets: _BlockTargets

    def __call__(self, params):
        return self.targets.rest(params)


@eqx.filter_jit
def _block_base(model, bl, ba, flag, start: int, stop: int, body: bool) -> RLA:
    """The fixed part of a whole-mesh block's targets: the model's targets with the moving part's
    coefficients zeroed (and, in the body block, without the correction, which the block
    evaluates itself)."""
    s = slice(start, stop)
    c = jnp.zeros_like(flag) if body else flag
    return model_targets(model, bl.at[s].set(0.0), ba.at[s].set(0.0), correct=c)


def fit_panoman(
    model: PanoManModel,
    constraints: ShellConstraints,
    *,
    init: tuple | None = None,
    init_mesh: Float[ArrayLike, "V 3"] | None = None,
    theta: Float[ArrayLike, "J 3"] | None = None,
    joint_names: tuple[str, ...] | None = None,
    blocks: tuple[str, ...] = ("face", "body", "hand"),
    correct: bool = True,
    weight: float = 1e6,
    max_steps: int = 8,
    param_weight: float = 1e-4,
    solver: PanoManSolver | None = None,
    align_to: Float[ArrayLike, "V 3"] | None = None,
    cg_rtol: float = 1e-3,
    cg_max_steps: int = 300,
    start: str | None = None,
    ftol: float = 1e-3,
) -> Solution:
    """Reconstructs a full body from sparse constraints (paper §5; module docstring).

    **Arguments:**

    - `model`: a trained [`bodyprior.panoman.PanoManModel`][].
    - `constraints`: [`bodyprior.panoman.shell_constraints`][] on the model's vertices (handles,
      joints through a regressor, point-to-plane surface points, parameter editing).
    - `init`: `(α, β_L, β_A)` to start from; default α = 0 and β from `theta`.
    - `init_mesh`: `(V, 3)` a posed mesh (e.g. the IK mesh of [`bodyprior.panoman.fit_lbs`][])
      whose RLA projection ([`bodyprior.panoman.PanoManModel.motion_coefficients`][], at `init`'s
      α or 0) replaces the β of `init` / `theta`; it is also the default `align_to`. The paper's
      initialisation is β(θ) of the IK pose; from an IK mesh the projection is far closer (IK
      poses 10–15° per joint off the truth gave β(θ_IK) decodes 247–481 mm off, the projection
      35–60 mm; docs/panoman.md).
    - `theta`: a `cmu_mb` axis-angle pose `(J, 3)` (e.g. from IK, [`bodyprior.panoman.fit_lbs`][],
      or motion data) giving the body β by the β MLP (§5.3); `joint_names` the rig's names.
    - `blocks`: the block order (paper: face, body, hand); each block moves its part's β (the
      body block also α) and the vertices: all of them in the body block, the part's region in
      the face and hand blocks (the sub-meshes of `solver`,
      [`bodyprior.panoman.prepare_panoman_solver`][]); `max_steps` LM iterations per block.
    - `correct`: use the correction MLP (eq. 5); `False` is the eq. 4 baseline.
    - `weight`: λ (eq. 6); `param_weight`: a weak editing prior keeping β near its start.
    - `solver`: [`bodyprior.panoman.prepare_panoman_solver`][]`(model)`, prepared once and reused
      across frames (prepared here if omitted); `prepare_panoman_solver(model, local=())` moves
      all vertices in every block.
    - `align_to`: `(V, 3)` mesh the decoded initialisation is placed on rigidly (e.g. the IK
      mesh); default the decoder's anchor frame.
    - `cg_rtol`, `cg_max_steps`: the inner PCG of each LM iteration
      ([`bodyprior.panoman.shell_solve`][]). Inexact steps: on held-out C1 frames (decimated
      mesh, 5 iterations per block) `1e-3` took 28 s instead of 69 s at `1e-8` with 12.6 / 11.7 mm
      instead of 13.8 / 11.1 mm; `1e-2` stalled (13.9 / 14.1 mm).
    - `start`: the vertices the shell solve starts from: `"decoded"` (the paper: g of the start
      parameters, placed on `align_to`) or `"mesh"` (`init_mesh` itself, with the parameters of
      its projection; needs `init_mesh`). Default: `"mesh"` when `init_mesh` is given, else
      `"decoded"`. From the IK mesh of held-out C1 frames (decimated mesh, K = 150, 5 iterations
      per block) the fits from the mesh ended at 12.0 / 11.5 / 20.1 / 13.8 mm where the decoded
      start's ended at 11.3 / 18.7 / 21.6 / 23.1 mm (its decode is 30–45 mm off the truth, the
      IK mesh 14–22 mm; docs/results_panoman.md). The mesh start inherits what skinning got
      wrong where no constraint undoes it: from an LBS mesh with a 180° wrist twist the fit kept
      the candy wrapper (0.21 of the forearm's cross-section, against 0.79 from β(θ) → g); to
      undo such a collapse, start from `theta` or `init` instead.
    - `ftol`: a block stops when an accepted LM step lowers its energy by at most `ftol · E`
      ([`bodyprior.panoman.shell_solve`][]). On two held-out full-mesh C2 frames (2026-12-08) the
      face and hand blocks' later steps gained < 0.3 % each and moved the vertex error by
      < 0.02 mm; `1e-3` ended them after 2-4 of 5 iterations (`1e-10`, the solver's default,
      runs every iteration).

    **Returns:** a [`bodyprior.Solution`][] with a [`bodyprior.panoman.PanoManFit`][] and `stats`:
    per block `steps` (LM iterations), `cg_steps` (inner PCG iterations, all LM iterations),
    `energy0`, `energy` (a local block's: on its sub-mesh), `seconds`, `free_vertices`;
    `init_s` (β MLP or projection, and g).
    """
    top = model.topology
    K = model.n_components
    P = model.shape_basis.shape[0]
    for b in blocks:
        if b not in PARTS:
            raise ValueError(f"`blocks` entries must be in {PARTS}, got {b!r}.")
    if solver is not None and not (
        isinstance(solver, PanoManSolver)
        and solver.whole.n_vertices == top.n_vertices
        and solver.fingerprint == _fingerprint(model)
    ):
        raise ValueError(
            "`solver` must be prepare_panoman_solver(model) for this model (its component rows "
            f"and regions are the model's), got {type(solver).__name__}"
            + (" of another model." if isinstance(solver, PanoManSolver) else ".")
        )
    if start is None:
        start = "decoded" if init_mesh is None else "mesh"
    if start not in ("decoded", "mesh"):
        raise ValueError(f"`start` must be 'decoded' or 'mesh', got {start!r}.")
    if start == "mesh" and init_mesh is None:
        raise ValueError("`start='mesh'` needs `init_mesh` (V, 3).")
    t0 = time.perf_counter()
    if init is not None:
        alpha, bl, ba = (jnp.asarray(x, jnp.float64) for x in init)
        check_array(alpha, "init[0] (alpha)", (P,))
        check_array(bl, "init[1] (beta_lengths)", (K,))
        check_array(ba, "init[2] (beta_angles)", (K,))
    else:
        alpha = jnp.zeros(P)
        bl, ba = (jnp.asarray(x, jnp.float64) for x in model.neutral())
        if theta is not None:
            if model.beta_mlp is None:
                raise ValueError("`theta` needs a model with a beta MLP.")
            if joint_names is None:
                raise ValueError("`joint_names` (of the cmu_mb rig) is required with `theta`.")
            check_array(theta, "theta", (len(joint_names), 3))
            b = model.beta_mlp(pose_features(theta, joint_names)).astype(jnp.float64)
            kb = model.part_sizes[0]
            bl, ba = model.with_body(b[:kb], b[kb:])
    if init_mesh is not None:
        bl, ba = (jnp.asarray(x) for x in model.motion_coefficients(init_mesh, np.asarray(alpha)))
        if align_to is None:
            align_to = init_mesh
    if start == "decoded":
        align = None if align_to is None else jnp.asarray(align_to, jnp.float64)
        dec = _evaluate_jit(model, alpha, bl, ba, jnp.asarray(1.0 if correct else 0.0), align)
        V = dec.value.vertices
    else:
        V = jnp.asarray(init_mesh, jnp.float64)
    V_init = V
    stats = {"init_s": time.perf_counter() - t0, "blocks": []}
    if solver is None:
        solver = prepare_panoman_solver(model)
    for part in blocks:
        s = model.part_slice(part)
        flag = jnp.asarray(1.0 if correct else 0.0)
        region = solver.region(part)
        params0 = {"bl": bl[s], "ba": ba[s]}
        if part == "body":
            params0["alpha"] = alpha
        # weak editing prior: β of this block near its start (the paper's E_C of eq. 9, λ-scaled)
        flat0 = jnp.concatenate([params0[k] for k in sorted(params0)])
        n = flat0.shape[0]
        cons = eqx.tree_at(
            lambda c: (c.param_index, c.param_value, c.param_weight),
            constraints,
            (jnp.arange(n), flat0, jnp.full(n, param_weight)),
        ) if constraints.param_index.shape[0] == 0 else constraints  # fmt: skip
        tb = time.perf_counter()
        opts = dict(weight=weight, max_steps=max_steps, cg_rtol=cg_rtol, ftol=ftol,
                    cg_max_steps=cg_max_steps, throw=False)  # fmt: skip
        if region is None:
            body = part == "body"
            base = _block_base(model, bl, ba, flag, s.start, s.stop, body)
            tg = _BlockTargets(model, alpha, base.lengths, base.angles,
                               solver.rows[PARTS.index(part)], flag, body, s.start)  # fmt: skip
            sol = shell_solve(tg, _Rest(tg), params0, V, top, cons, solver=solver.whole, **opts)
            V = sol.value.vertices
        else:  # the part's region alone (prepare_panoman_solver)
            e = region.edges
            x0 = model_targets(model, bl, ba, correct=flag)
            lt = _LocalTargets(x0.lengths[e], x0.angles[e], model.components_lengths[s][:, e],
                               model.components_angles[s][:, e], bl[s], ba[s])  # fmt: skip
            rest = jnp.asarray(model.shape(alpha), jnp.float64)[region.vertices]
            sol = shell_solve(lt, rest, params0, V[region.vertices], region.topology,
                              _local_constraints(cons, region, V), solver=region.solver,
                              free=np.asarray(region.free), **opts)  # fmt: skip
            V = V.at[region.vertices].set(sol.value.vertices)
        p = sol.value.params
        bl = bl.at[s].set(p["bl"])
        ba = ba.at[s].set(p["ba"])
        if part == "body":
            alpha = p["alpha"]
        stats["blocks"].append(dict(part=part, steps=int(sol.stats["steps"]),
                                    cg_steps=int(sol.stats["cg_steps"]),
                                    energy0=float(sol.stats["energy0"]),
                                    energy=float(sol.stats["energy"]),
                                    seconds=time.perf_counter() - tb,
                                    free_vertices=top.n_vertices if region is None
                                    else region.n_free))  # fmt: skip
    ok = bool(jnp.all(jnp.isfinite(V)))
    return Solution(
        PanoManFit(V, alpha, bl, ba, V_init),
        RESULTS.successful if ok else RESULTS.nonfinite,
        stats,
    )
