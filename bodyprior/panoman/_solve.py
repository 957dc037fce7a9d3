"""PanoMan's reconstruction solver (paper §5.1–5.3): Levenberg–Marquardt on the discrete-shell
energy plus constraint energies, with the vertices and the model parameters unknown jointly.

    E(V, p) = Σ_e s_e(V, p)² + Σ_e b_e(V, p)² + λ E_C(V, p)                          (eq. 6)

`s`, `b` are [`bodyprior.panoman.shell_residuals`][] of `V` against the targets `targets(p)`
(PanoMan: `X(α, β)`, eq. 5) on the rest mesh `rest` (an array, or a callable of `p`: PanoMan's
`B_S(α)`). `E_C` sums, each term with its own per-item weights ([`ShellConstraints`][]):

- parameter editing (eqs. 9–10): `Σ w_k (p_k − p̂_k)²` over chosen entries of the flat parameter
  vector;
- vertex handles (eq. 11): `Σ w_k ‖v_k − v̂_k‖²` (metres);
- joint positions through a sparse vertex regressor (a [`bodyprior.Rig`][]'s): `Σ w_j ‖Σ_m
  c_jm v_{i_jm} − Ĵ_j‖²`;
- surface points, point-to-plane: `Σ w_k (n_k · (Σ_a b_ka v_{f_k,a} − y_k))²` for scan points `y`
  with normals `n` matched to barycentric points of faces `f` (correspondences fixed during a
  solve; re-match and call again for ICP).

**Linear algebra** (measured on the default body, `docs/benchmarks.md`): each iteration solves `(JᵀJ
+ μ D) δ = −Jᵀr` by PCG on the whole system (vertices and parameters; matrix-free products: the
shell rows' vertex block from their explicit Jacobian rows, the rest from `jax.linearize` of the
parameter and constraint parts) preconditioned by an exact sparse LDLᵀ factorisation of the shell +
handle + surface + joint block (qdldl, AMD ordering, symbolic analysis once per topology and set of
joint-regressor vertices; on the host) and a dense Cholesky of the parameter block's Gram matrix
(computed once per solve at the start, exact for targets linear in `p`; parameters the rest mesh
does not read go through the targets alone, `_param_gram`). The vertex–parameter coupling is the
low-rank part the PCG resolves. (Until 2026-12-07 the joint rows entered the factorisation by
their diagonal alone and the PCG resolved their couplings too: 248 PCG steps in the body block
of a C2 frame where the exact joint rows need ~60.) Plain block-Jacobi PCG needs ~6,800 steps
for a 1e-2 residual reduction on the decimated body, the factorisation 0.19 s (0.46 s full body):
the factorisation won.

`D` is the diagonal of the preconditioned blocks (Marquardt scaling); `μ` follows Nielsen's rule.
A step the linear model predicts to gain but that raises `E` is tried at 1/2 and 1/4 of its length
(one batched evaluation) before it is rejected; after a rejection the factorisation of the same
vertices (less damped) is reused as the preconditioner.
An iteration budget ending is not a failure (`stats["converged"]` says whether the stopping test
was met); non-finite values are (`RESULTS.nonfinite`).
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._solution import RESULTS, Solution, _check
from .._topology import Topology
from .._validate import check_array, check_positive_int, is_tracer
from ._rla import RLA, _check_topology
from ._shell import _BENDING, _jacobian_rows, _residuals, _shell_terms

__all__ = ["ShellConstraints", "ShellFit", "ShellSolver", "prepare_shell_solver", "shell_solve"]


# --------------------------------------------------------------------------------------------------
# Constraints


class ShellConstraints(eqx.Module):
    """The constraint energies `E_C` of a solve (module docstring), as arrays: new values with the
    same sizes do not recompile. Build with [`bodyprior.panoman.shell_constraints`][].

    **Fields** (`C` edited parameters, `H` handles, `J` joints with `M` regressor entries each,
    `S` surface points; any of them may be 0):

    - `param_index` `(C,)` into the flat parameter vector (`jax.flatten_util.ravel_pytree`
      order), `param_value` `(C,)`, `param_weight` `(C,)`.
    - `handle_index` `(H,)` vertices, `handle_position` `(H, 3)` metres, `handle_weight` `(H,)`.
    - `joint_indices`, `joint_coeffs` `(J, M)`: the regressor; `joint_position` `(J, 3)`,
      `joint_weight` `(J,)`.
    - `surface_face` `(S,)`, `surface_bary` `(S, 3)`, `surface_point`, `surface_normal` `(S, 3)`
      (unit normals), `surface_weight` `(S,)`.
    """

    param_index: Int[Array, " C"]
    param_value: Float[Array, " C"]
    param_weight: Float[Array, " C"]
    handle_index: Int[Array, " H"]
    handle_position: Float[Array, "H 3"]
    handle_weight: Float[Array, " H"]
    joint_indices: Int[Array, "J M"]
    joint_coeffs: Float[Array, "J M"]
    joint_position: Float[Array, "J 3"]
    joint_weight: Float[Array, " J"]
    surface_face: Int[Array, " S"]
    surface_bary: Float[Array, "S 3"]
    surface_point: Float[Array, "S 3"]
    surface_normal: Float[Array, "S 3"]
    surface_weight: Float[Array, " S"]


def shell_constraints(
    *,
    params: tuple[ArrayLike, ArrayLike] | tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    handles: tuple[ArrayLike, ArrayLike] | tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
    joints: tuple | None = None,
    surface: tuple | None = None,
) -> ShellConstraints:
    """Builds [`bodyprior.panoman.ShellConstraints`][]; each group is optional and its weights
    default to 1.

    **Arguments:**

    - `params`: `(index (C,), value (C,)[, weight (C,)])`: editing constraints on entries of the
      flat parameter vector (eqs. 9–10).
    - `handles`: `(index (H,), position (H, 3)[, weight (H,)])`: vertex handles (eq. 11), metres.
    - `joints`: `(indices (J, M), coeffs (J, M), position (J, 3)[, weight (J,)])`: joint targets
      through a sparse regressor (e.g. `rig.regressor_indices`, `rig.regressor_weights`).
    - `surface`: `(face (S,), bary (S, 3), point (S, 3), normal (S, 3)[, weight (S,)])`:
      point-to-plane targets.

    Raises `ValueError` on mismatched shapes or negative weights.
    """

    def group(val, names, shapes, name):
        if val is None:
            return [
                np.zeros(
                    s,
                    np.int32
                    if n.endswith("index") or n.endswith("indices") or n == "face"
                    else np.float64,
                )
                for n, s in zip(names, shapes)
            ]
        if not isinstance(val, tuple) or len(val) not in (len(names) - 1, len(names)):
            raise ValueError(
                f"`{name}` must be a tuple ({', '.join(names[:-1])}[, {names[-1]}]), got "
                f"{type(val).__name__} of length {len(val) if isinstance(val, tuple) else '?'}."
            )
        arrs = [np.asarray(a) for a in val]
        n = arrs[0].shape[0] if arrs[0].ndim else -1
        if len(arrs) == len(names) - 1:
            arrs.append(np.ones(n))
        out = []
        for a, nm, s in zip(arrs, names, shapes):
            want = tuple(n if d == 0 else d for d in s)
            if a.shape != want:
                raise ValueError(f"`{name}` {nm} must have shape {want}, got {a.shape}.")
            out.append(a)
        if np.any(out[-1] < 0) or not np.all(np.isfinite(out[-1])):
            raise ValueError(f"`{name}` weights must be finite and >= 0.")
        return out

    pi, pv, pw = group(params, ("index", "value", "weight"), ((0,), (0,), (0,)), "params")
    hi, hp, hw = group(handles, ("index", "position", "weight"), ((0,), (0, 3), (0,)), "handles")
    if joints is not None and isinstance(joints, tuple) and len(joints) >= 1:
        m = np.asarray(joints[0]).shape[-1] if np.asarray(joints[0]).ndim == 2 else 1
    else:
        m = 1
    ji, jc, jp, jw = group(
        joints,
        ("indices", "coeffs", "position", "weight"),
        ((0, m), (0, m), (0, 3), (0,)),
        "joints",
    )
    sf, sb, sp, sn, sw = group(
        surface,
        ("face", "bary", "point", "normal", "weight"),
        ((0,), (0, 3), (0, 3), (0, 3), (0,)),
        "surface",
    )
    i32 = lambda a: jnp.asarray(a, jnp.int32)  # noqa: E731
    f64 = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    return ShellConstraints(
        i32(pi),
        f64(pv),
        f64(pw),
        i32(hi),
        f64(hp),
        f64(hw),
        i32(ji),
        f64(jc),
        f64(jp),
        f64(jw),
        i32(sf),
        f64(sb),
        f64(sp),
        f64(sn),
        f64(sw),
    )


def _check_constraints(c: ShellConstraints, n_vertices: int, n_faces: int, n_params: int):
    if not isinstance(c, ShellConstraints):
        raise ValueError(
            f"`constraints` must be a ShellConstraints (see shell_constraints), got "
            f"{type(c).__name__}."
        )
    for name, arr, hi in (
        ("param_index", c.param_index, n_params),
        ("handle_index", c.handle_index, n_vertices),
        ("joint_indices", c.joint_indices, n_vertices),
        ("surface_face", c.surface_face, n_faces),
    ):
        if is_tracer(arr) or arr.size == 0:
            continue
        a = np.asarray(arr)
        if a.min() < 0 or a.max() >= hi:
            raise ValueError(
                f"`constraints.{name}` must lie in [0, {hi}), got [{a.min()}, {a.max()}]."
            )


# --------------------------------------------------------------------------------------------------
# The host factorisation (sparse LDLᵀ, fixed pattern)


_POOL = 4  # numeric factors kept alive at once (one per vmapped item of an iteration)
_STEP_FRACTIONS = (1.0, 0.5, 0.25)  # of the Gauss-Newton step, tried longest first


class _Pattern:
    """One sparsity pattern of `A_s` (upper CSC) and where each product lands in its data."""

    def __init__(self, indptr, indices, keys, bend_pos, stretch_pos, face_pos, diag_pos,
                 joint=None):  # fmt: skip
        self.indptr, self.indices, self.keys = indptr, indices, keys
        self.nnz = keys.size
        self.bend_pos, self.stretch_pos, self.face_pos = bend_pos, stretch_pos, face_pos
        self.diag_pos = diag_pos
        # joint rows: data[pos] += c[j, a] c[j, b] (3 coordinates each), or None
        self.joint = joint


class _HostFactor:
    """Host side of the preconditioner: the upper-triangular CSC pattern of the shell + handle +
    surface + joint block `A_s` (3V × 3V), the maps that scatter per-row Jacobian products into
    it, and a pool of qdldl factorisations (AMD ordering and symbolic analysis reused by
    `update` while the pattern stays). The joint rows couple the vertices of each joint's
    regressor, so their pattern depends on the constraints: one extended pattern per set of
    regressor vertices, built on first use and kept (`_MAX_PATTERNS`). A factor is found by the
    id its factor call returned, so the solves of one iteration use theirs, also under `vmap`
    (up to `_POOL` items)."""

    _MAX_PATTERNS = 8

    def __init__(self, stencils: np.ndarray, faces: np.ndarray, n_vertices: int, key: tuple):
        import scipy.sparse as sps

        self.key = key
        n = self.n = 3 * n_vertices
        dof = 3 * stencils[:, :, None] + np.arange(3)  # (E, 4, 3): stencil vertex dofs
        dof_b = dof.reshape(-1, 12)  # bend rows: slots 0..3
        dof_s = dof[:, :2].reshape(-1, 6)  # stretch rows: slots 0, 1
        dof_f = (3 * faces[:, :, None] + np.arange(3)).reshape(-1, 9)  # surface rows
        pairs = [np.broadcast_arrays(d[:, :, None], d[:, None, :]) for d in (dof_b, dof_s, dof_f)]
        diag = np.arange(n)
        rows = np.concatenate([p[0].ravel() for p in pairs] + [diag])
        cols = np.concatenate([p[1].ravel() for p in pairs] + [diag])
        up = rows <= cols
        pat = sps.csc_matrix((np.ones(int(up.sum())), (rows[up], cols[up])), shape=(n, n))
        pat.sum_duplicates()
        pat.sort_indices()
        # Column-major sort keys of the stored entries: data position by binary search.
        keys = pat.indices.astype(np.int64) + n * np.repeat(
            np.arange(n, dtype=np.int64), np.diff(pat.indptr)
        )

        def position(ii, jj):  # upper entry (ii <= jj) of each product, else -1
            return np.where(ii <= jj, np.searchsorted(keys, ii.astype(np.int64) + n * jj), -1)

        # JᵀJ's upper entry (i, j) is Σ_r J_ri J_rj: each product with i <= j is added once.
        self.base = _Pattern(pat.indptr, pat.indices, keys, *(position(*p) for p in pairs),
                             position(diag, diag))  # fmt: skip
        self._patterns: dict = {}
        self._lock = threading.Lock()
        self._ids = itertools.count(0)
        self._slots: list[Any] = [None] * _POOL  # (pattern, qdldl.Solver)
        self._slot_id = [-1] * _POOL
        self._slot_key: list[int | None] = [None] * _POOL  # hash of the inputs (not damping)
        self._slot_diag: list[Any] = [None] * _POOL

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, _HostFactor) and self.key == other.key

    def pattern(self, joint_index, joint_coef) -> _Pattern:
        """The pattern with the joint rows' couplings (the regressor entries with a non-zero
        coefficient) added to the base one."""
        ji = np.asarray(joint_index, np.int64).reshape(-1, np.shape(joint_index)[-1])
        live = np.asarray(joint_coef).reshape(ji.shape) != 0
        if not live.any():
            return self.base
        key = (np.where(live, ji, -1).tobytes(), ji.shape)
        pat = self._patterns.get(key)
        if pat is not None:
            return pat
        n, base = self.n, self.base
        j, a, b, i_a, i_b = [], [], [], [], []
        for jj in range(ji.shape[0]):
            m = np.flatnonzero(live[jj])
            aa, bb = np.meshgrid(m, m, indexing="ij")
            aa, bb = aa.ravel(), bb.ravel()
            va, vb = ji[jj, aa], ji[jj, bb]
            keep = va <= vb  # upper triangle by vertex (each coordinate the same)
            j.append(np.full(int(keep.sum()), jj))
            a.append(aa[keep])
            b.append(bb[keep])
            i_a.append(va[keep])
            i_b.append(vb[keep])
        j, a, b, i_a, i_b = (np.concatenate(x) for x in (j, a, b, i_a, i_b))
        # coordinate d of vertex pair (i_a, i_b): dofs 3 i_a + d, 3 i_b + d
        d = np.arange(3)
        ra = (3 * i_a[:, None] + d).ravel()
        cb = (3 * i_b[:, None] + d).ravel()
        new = np.union1d(base.keys, ra + n * cb)
        remap = np.searchsorted(new, base.keys)
        rows = (new % n).astype(np.int32)
        counts = np.bincount(new // n, minlength=n)
        indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        moved = lambda pos: np.where(pos >= 0, remap[np.maximum(pos, 0)], -1)  # noqa: E731
        jpos = np.searchsorted(new, ra + n * cb)
        pat = _Pattern(indptr, rows, new, moved(base.bend_pos), moved(base.stretch_pos),
                       moved(base.face_pos), moved(base.diag_pos),
                       (jpos, np.repeat(j, 3), np.repeat(a, 3), np.repeat(b, 3)))  # fmt: skip
        if len(self._patterns) >= self._MAX_PATTERNS:
            self._patterns.pop(next(iter(self._patterns)))
        self._patterns[key] = pat
        return pat

    def assemble(self, jb, js, surf_face, surf_coef, diag_add, joint_index, joint_coef):
        """`(pattern, data)` of `A_s` (upper CSC) from bend / stretch row Jacobians `(E, 12)` /
        `(E, 6)`, surface rows `(S, 9)` on faces `surf_face`, a diagonal addition `(3V,)` and
        joint rows (regressor vertices `(J, M)`, coefficients `√(λ w_j) c_jm` `(J, M)`)."""
        pat = self.pattern(joint_index, joint_coef)
        jb, js = np.asarray(jb).reshape(-1, 12), np.asarray(js).reshape(-1, 6)
        data = np.zeros(pat.nnz)
        for j, pos in ((jb, pat.bend_pos), (js, pat.stretch_pos)):
            m = pos >= 0
            data += np.bincount(
                pos[m], weights=(j[:, :, None] * j[:, None, :])[m], minlength=pat.nnz
            )
        sf = np.asarray(surf_face)
        if sf.size:
            c = np.asarray(surf_coef).reshape(-1, 9)
            pos = pat.face_pos[sf]
            m = pos >= 0
            data += np.bincount(
                pos[m], weights=(c[:, :, None] * c[:, None, :])[m], minlength=pat.nnz
            )
        if pat.joint is not None:
            pos, jj, a, b = pat.joint
            c = np.asarray(joint_coef).reshape(np.shape(joint_index)[-2:])
            data += np.bincount(pos, weights=c[jj, a] * c[jj, b], minlength=pat.nnz)
        data[pat.diag_pos] += np.asarray(diag_add)
        return pat, data

    def matrix(self, pat: _Pattern, data):
        import scipy.sparse as sps

        return sps.csc_matrix((data, pat.indices, pat.indptr), shape=(self.n, self.n))

    def factor(self, jb, js, surf_face, surf_coef, diag_add, joint_index, joint_coef, damping):
        """Factors `A_s + damping · diag(A_s)` (plus a 1e-12 relative ridge); returns
        `(id, diag(A_s))`.

        When `A_s` is one a live factorisation was made of (an LM iteration after a rejected
        step: same vertices, more damping), that factorisation is returned instead: its smaller
        damping makes it a preconditioner of the new system as good as a new one (the PCG's
        product carries the true damping), and a refactorisation costs ~0.6 s on the full body.
        """
        import qdldl

        args = [np.ascontiguousarray(np.asarray(x)) for x in
                (jb, js, surf_face, surf_coef, diag_add, joint_index, joint_coef)]  # fmt: skip
        key = hash(b"".join(a.tobytes() for a in args))
        with self._lock:
            for k in range(_POOL):
                if self._slot_key[k] == key and self._slots[k] is not None:
                    return np.int64(self._slot_id[k]), self._slot_diag[k]
        pat, data = self.assemble(*args)
        d = data[pat.diag_pos].copy()
        data[pat.diag_pos] += float(damping) * d + 1e-12 * max(float(d.mean()), 1e-300)
        A = self.matrix(pat, data)
        with self._lock:
            fid = next(self._ids)
            k = fid % _POOL
            slot = self._slots[k]
            if slot is None or slot[0] is not pat:
                self._slots[k] = (pat, qdldl.Solver(A, upper=True))
            else:
                slot[1].update(A, upper=True)
            self._slot_id[k] = fid
            self._slot_key[k] = key
            self._slot_diag[k] = d
        return np.int64(fid), d

    def solve(self, fid, r):
        k = int(fid) % _POOL
        with self._lock:
            if self._slot_id[k] != int(fid):
                raise RuntimeError(
                    f"shell_solve: more than {_POOL} factorisations alive at once (a vmap over "
                    f"more than {_POOL} bodies); solve in chunks of at most {_POOL}."
                )
            return self._slots[k][1].solve(np.asarray(r, np.float64))


class ShellSolver(eqx.Module):
    """What [`bodyprior.panoman.shell_solve`][] precomputes once per topology (host side): hinge
    stencils and the sparse factorisation's pattern and maps. Build with
    [`bodyprior.panoman.prepare_shell_solver`][]."""

    stencils: Int[Array, "E 4"]
    host: _HostFactor = eqx.field(static=True)

    @property
    def n_vertices(self) -> int:
        return int(self.host.n // 3)


def prepare_shell_solver(topology: Topology) -> ShellSolver:
    """Precomputes the [`bodyprior.panoman.ShellSolver`][] for meshes of `topology` (any rest
    shape, targets and constraint values)."""
    import hashlib

    _check_topology(topology)
    faces = np.asarray(topology.faces)
    e, opp = np.asarray(topology.edges), np.asarray(topology.edge_opposite)
    interior = np.asarray(topology.interior)
    st = np.stack([e[:, 0], e[:, 1], opp[:, 0], np.where(interior, opp[:, 1], e[:, 0])], 1)
    V = int(topology.n_vertices)
    key = (V, int(e.shape[0]), hashlib.sha1(faces.astype(np.int64).tobytes()).hexdigest())
    host = _HostFactor(st, faces, V, key)
    return ShellSolver(jnp.asarray(st, jnp.int32), host)


# --------------------------------------------------------------------------------------------------
# The problem


class ShellFit(eqx.Module):
    """The reconstructed mesh and parameters of [`bodyprior.panoman.shell_solve`][].

    - `vertices` `(V, 3)` metres; `params` the parameters (same pytree as `params0`).
    - `energy`: the total `E` (eq. 6) at the solution; `shell_energy` its `E_S + E_B` part and
      `constraint_energy` `λ E_C`.
    - `stretch`, `bend` `(E,)`: the shell residuals at the solution
      ([`bodyprior.panoman.shell_residuals`][]).
    """

    vertices: Float[Array, "V 3"]
    params: Any
    energy: Float[Array, ""]
    shell_energy: Float[Array, ""]
    constraint_energy: Float[Array, ""]
    stretch: Float[Array, " E"]
    bend: Float[Array, " E"]


class _Config(eqx.Module):
    """Solve settings. The numbers are array leaves, so a new weight, tolerance, damping or step
    budget reuses the compiled solve; only `bending` and `cg_max_steps` are structure."""

    bending: str = eqx.field(static=True)
    bending_stiffness: Array
    fold_eps: Array
    weight: Array
    max_steps: Array
    ftol: Array
    cg_rtol: Array
    damping: Array
    cg_max_steps: int = eqx.field(static=True)


def _parts(V, p, targets, rest, cons: ShellConstraints, topology, cfg: _Config, unravel):
    """Residual groups `(stretch, bend, constraint rows)` at vertices `V` and flat params `p`."""
    pt = unravel(p)
    rla = targets(pt)
    r0 = rest(pt) if callable(rest) else rest
    s, b = _residuals(V, r0, rla, topology, cfg.bending, cfg.bending_stiffness, cfg.fold_eps)
    lam = cfg.weight
    sq = lambda w: jnp.sqrt(lam * w)  # noqa: E731
    rp = sq(cons.param_weight) * (p[cons.param_index] - cons.param_value)
    rh = sq(cons.handle_weight)[:, None] * (V[cons.handle_index] - cons.handle_position)
    joints = jnp.einsum("jm,jmd->jd", cons.joint_coeffs, V[cons.joint_indices])
    rj = sq(cons.joint_weight)[:, None] * (joints - cons.joint_position)
    fv = V[topology.faces[cons.surface_face]]  # (S, 3, 3)
    pts = jnp.einsum("sa,sad->sd", cons.surface_bary, fv)
    rs = sq(cons.surface_weight) * jnp.sum(cons.surface_normal * (pts - cons.surface_point), -1)
    return s, b, jnp.concatenate([rp, rh.ravel(), rj.ravel(), rs])


def _leaves_read(fn, params0) -> list[bool]:
    """Static: which leaves of the pytree `params0` the callable `fn` reads (dead-code analysis of
    its jaxpr); every leaf where that cannot be told."""
    leaves, treedef = jax.tree.flatten(params0)
    try:
        from jax.interpreters import partial_eval as pe

        closed = jax.make_jaxpr(lambda *ls: fn(jax.tree.unflatten(treedef, ls)))(*leaves)
        _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
        used = [bool(u) for u in used]
        return used if len(used) == len(leaves) else [True] * len(leaves)
    except Exception:  # noqa: BLE001 - an optimisation only: fall back to the general path
        return [True] * len(leaves)


def _param_gram(targets, rest, params0, p0, V0, cons, topology, cfg, unravel):
    """`J_pᵀ J_p` at `(V0, p0)`: the Gram of the residuals' Jacobian with respect to the flat
    parameters (the parameter block of the preconditioner).

    The constraint rows other than parameter editing do not depend on `p`; the editing rows add
    `λ w` on the diagonal. A stretch (bend) residual reads only its own edge's length (angle)
    target, so for parameters the rest mesh does not read (static leaf analysis) a shell column is
    `D · ∂X/∂p_j` with `D` the diagonal of `∂(s, b)/∂X`: one Jacobian of the targets alone. Only
    the parameters the rest mesh reads (PanoMan: the 10 shape coefficients) go through the whole
    shell residual. (The plain `jacfwd` of every residual row over every parameter took 18 s for
    PanoMan's 510-parameter body block on the full mesh.) A targets object with a method
    `weighted_gram(params, w) -> (P, P) | None` (`Jᵀ diag(w) J` of its own Jacobian over the
    flat parameters) supplies the block of those parameters from its structure (PanoMan's block
    targets: sparse rows and a low-rank correction; the dense `(P, 2E)` Jacobian and its Gram
    cost 1.3 s of the full body's block solve)."""
    P = p0.shape[0]
    leaves = jax.tree.leaves(params0)
    sizes = [int(np.size(x)) for x in leaves]
    if callable(rest):
        read = np.repeat(np.asarray(_leaves_read(rest, params0), bool), sizes)
    else:
        read = np.zeros(P, bool)
    ir, io = np.flatnonzero(read), np.flatnonzero(~read)
    eye = jnp.eye(P, dtype=p0.dtype)

    def rest_of(pt):
        return rest(pt) if callable(rest) else rest

    def shell(r0, x):  # (2E,) stretch and bend rows at V0 for a rest mesh and targets
        s, b = _residuals(V0, r0, x, topology, cfg.bending, cfg.bending_stiffness, cfg.fold_eps)
        return jnp.concatenate([s, b])

    cols = []
    if ir.size:  # through the whole shell residual
        def shell_of_p(p):
            pt = unravel(p)
            return shell(rest_of(pt), targets(pt))

        cols.append(jax.vmap(lambda t: jax.jvp(shell_of_p, (p0,), (t,))[1])(eye[ir]))
    lam = cfg.weight
    if io.size:  # D · ∂X/∂p
        pt0 = unravel(p0)
        r0 = rest_of(pt0)
        x0 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), targets(pt0))
        _, dsb = jax.jvp(lambda x: shell(r0, x), (x0,), (jax.tree.map(jnp.ones_like, x0),))

        def tflat(p):
            x = targets(unravel(p))
            return jnp.concatenate([jnp.asarray(x.lengths, jnp.float64),
                                    jnp.asarray(x.angles, jnp.float64)])  # fmt: skip

        gram = getattr(targets, "weighted_gram", None)
        Gt = gram(pt0, dsb * dsb) if gram is not None else None
        if Gt is not None:
            # The targets' own structured Gram `Jᵀ diag(D²) J` for the io block; the cross
            # block from one VJP of the targets per rest-read column.
            G = jnp.zeros((P, P), p0.dtype).at[np.ix_(io, io)].set(Gt[np.ix_(io, io)])
            if ir.size:
                Jr = cols[0]  # (|ir|, 2E)
                _, vjp = jax.vjp(tflat, p0)
                cross = jax.vmap(lambda c: vjp(dsb * c)[0])(Jr)[:, io]  # (|ir|, |io|)
                G = G.at[np.ix_(ir, io)].set(cross).at[np.ix_(io, ir)].set(cross.T)
                G = G.at[np.ix_(ir, ir)].set(Jr @ Jr.T)
            return G.at[cons.param_index, cons.param_index].add(lam * cons.param_weight)
        tcols = jax.vmap(lambda t: jax.jvp(tflat, (p0,), (t,))[1])(eye[io])  # (|io|, 2E)
        cols.append(tcols * dsb)
    Jt = jnp.concatenate(cols, 0)  # (P, 2E), rows in the order ir, io
    order = np.argsort(np.concatenate([ir, io]))
    Jt = Jt[order]
    G = Jt @ Jt.T
    return G.at[cons.param_index, cons.param_index].add(lam * cons.param_weight)


def _gauss_newton_product(parts, u, nV, stencils, jb, js):
    """`z ↦ JᵀJ z` at `u = (V, p)` for the residual `parts(V, p) = (s, b, c)`, with the shell rows'
    vertex block from their explicit Jacobian rows (`js` `(E, 6)` over the edge's two vertices,
    `jb` `(E, 12)` over the hinge stencil `stencils` `(E, 4)`: 18 multiply-adds per edge each way)
    and everything else (the shell rows' parameter block, the constraint rows) through
    linearisations of those parts alone. Equal to the product through the whole linearised
    residual (tested), at a fraction of its cost: that one re-runs the linearised hinge geometry
    (~21 ms per product on the full body)."""
    V0, p0 = u[: 3 * nV].reshape(nV, 3), u[3 * nV :]
    E = stencils.shape[0]
    jb3, js3 = jb.reshape(E, 4, 3), js.reshape(E, 2, 3)
    P = p0.shape[0]
    if P:
        _, sp = jax.linearize(lambda p: jnp.concatenate(parts(V0, p)[:2]), p0)
        spT = jax.linear_transpose(sp, p0)
    _, cvp = jax.linearize(lambda V, p: parts(V, p)[2], V0, p0)
    cvpT = jax.linear_transpose(cvp, V0, p0)

    def product(z):
        zV, zp = z[: 3 * nV].reshape(nV, 3), z[3 * nV :]
        g = zV[stencils]  # (E, 4, 3)
        y_s = jnp.einsum("ead,ead->e", js3, g[:, :2])
        y_b = jnp.einsum("ead,ead->e", jb3, g)
        if P:
            ysb = sp(zp)
            y_s, y_b = y_s + ysb[:E], y_b + ysb[E:]
        y_c = cvp(zV, zp)
        outV = (
            jnp.zeros((nV, 3), z.dtype)
            .at[stencils[:, :2]].add(js3 * y_s[:, None, None])
            .at[stencils].add(jb3 * y_b[:, None, None])
        )  # fmt: skip
        cV, cp = cvpT(y_c)
        outV = outV + cV
        outp = cp
        if P:
            (sp_t,) = spT(jnp.concatenate([y_s, y_b]))
            outp = outp + sp_t
        return jnp.concatenate([outV.ravel(), outp])

    return product


def _solve(
    targets, rest, params0, vertices0, cons, topology, solver: ShellSolver, cfg: _Config, free
):
    p0, unravel = ravel_pytree(params0)
    p0 = jnp.asarray(p0, jnp.float64)
    V0 = jnp.asarray(vertices0, jnp.float64)
    nV, P, E = V0.shape[0], p0.shape[0], topology.n_edges
    host = solver.host

    def split(u):
        return u[: 3 * nV].reshape(nV, 3), u[3 * nV :]

    def parts(V, p):
        # Fixed vertices (`free` False) read their start position: their Jacobian columns are
        # zero, so the step never moves them.
        if free is not None:
            V = jnp.where(free[:, None], V, V0)
        return _parts(V, p, targets, rest, cons, topology, cfg, unravel)

    def resid(u):
        s, b, c = parts(*split(u))
        return jnp.concatenate([s, b, c])

    u0 = jnp.concatenate([V0.ravel(), p0])

    # Parameter-block Gram (once per solve, exact for targets linear in p).
    if P:
        Gp = _param_gram(targets, rest, params0, p0, V0, cons, topology, cfg, unravel)
        dGp = jnp.diag(Gp)
    else:
        Gp = jnp.zeros((0, 0))
        dGp = jnp.zeros((0,))

    # Constant (linear) constraint parts of the sparse block.
    lam = cfg.weight
    diag_add = jnp.zeros((nV, 3)).at[cons.handle_index].add(lam * cons.handle_weight[:, None])
    # joint rows, exact in the factorisation (their couplings extend its pattern)
    joint_coef = jnp.sqrt(lam * cons.joint_weight)[:, None] * cons.joint_coeffs
    if free is not None:  # fixed vertices: a unit diagonal keeps the factor regular
        diag_add = diag_add + jnp.where(free[:, None], 0.0, 1.0)
    diag_add = diag_add.ravel()
    surf_coef = (
        jnp.sqrt(lam * cons.surface_weight)[:, None, None]
        * cons.surface_bary[:, :, None]
        * cons.surface_normal[:, None, :]
    )  # (S, 3 vertices, 3)

    st = solver.stencils
    free_slot = None if free is None else free[st][:, :, None]  # (E, 4, 1)

    factor_shape = (
        jax.ShapeDtypeStruct((), jnp.int64),
        jax.ShapeDtypeStruct((3 * nV,), jnp.float64),
    )

    def factor(jb, js, mu):
        return jax.pure_callback(
            host.factor,
            factor_shape,
            jb,
            js,
            cons.surface_face,
            surf_coef,
            diag_add,
            cons.joint_indices,
            joint_coef,
            mu,
            vmap_method="sequential",
        )

    def host_solve(fid, r):
        return jax.pure_callback(
            host.solve,
            jax.ShapeDtypeStruct((3 * nV,), jnp.float64),
            fid,
            r,
            vmap_method="sequential",
        )

    def energy(u):
        r = resid(u)
        return jnp.sum(r * r)

    def step(state):
        k, u, f, mu, nu, n_cg, n_acc, _, _ = state
        r, jvp = jax.linearize(resid, u)
        (g,) = jax.linear_transpose(jvp, u)(r)
        # The shell rows' explicit vertex Jacobian rows (per-edge gradients; fixed vertices'
        # slots zero, as their columns are).
        Vu, pu = split(u)
        if free is not None:
            Vu = jnp.where(free[:, None], Vu, V0)
        pt = unravel(pu)
        lr_safe, coef, _ = _shell_terms(
            rest(pt) if callable(rest) else rest, targets(pt), topology, cfg.bending,
            cfg.bending_stiffness, cfg.fold_eps,
        )  # fmt: skip
        js, jb = _jacobian_rows(Vu, lr_safe, coef, topology)
        if free is not None:
            js = jnp.where(free_slot[:, :2], js.reshape(E, 2, 3), 0.0).reshape(E, 6)
            jb = jnp.where(free_slot, jb.reshape(E, 4, 3), 0.0).reshape(E, 12)
        fid, dA = factor(jb, js, mu)
        dA = jnp.maximum(dA, 0.0)
        damp = mu * jnp.concatenate([dA, dGp])
        if P:
            Gd = Gp + jnp.diag(mu * dGp + 1e-12 * (jnp.mean(dGp) + 1e-300))
            cho = jax.scipy.linalg.cho_factor(Gd)

        gn = _gauss_newton_product(parts, u, nV, st, jb, js)

        def matvec(z):
            z = z[:, 0]
            return (gn(z) + damp * z)[:, None]

        def precondition(z):
            z = z[:, 0]
            zv = host_solve(fid, z[: 3 * nV])
            zp = jax.scipy.linalg.cho_solve(cho, z[3 * nV :]) if P else z[3 * nV :]
            return jnp.concatenate([zv, zp])[:, None]

        delta, steps, _ = _pcg(matvec, precondition, -g[:, None], cfg)
        delta = delta[:, 0]
        jd = jvp(delta)
        # Backtracking along the Gauss-Newton step: the full step and its halves (one batched
        # residual evaluation). The shell rows are far from linear over a step that turns the
        # hinges; a shorter step along the same direction often lowers E where the full one
        # does not, which costs one evaluation instead of a whole rejected iteration.
        ts = jnp.asarray(_STEP_FRACTIONS)
        f_t = jax.vmap(lambda t: energy(u + t * delta))(ts)
        pred_t = f - jax.vmap(lambda t: jnp.sum((r + t * jd) ** 2))(ts)
        rho_t = (f - f_t) / jnp.where(pred_t > 0, pred_t, 1.0)
        ok_t = jnp.isfinite(f_t) & (pred_t > 0) & (rho_t > 1e-4)
        i = jnp.argmax(ok_t)  # the longest accepted step (the first, if none is)
        t, f_new, pred, rho, ok = ts[i], f_t[i], pred_t[i], rho_t[i], ok_t[i]
        u_new = u + t * delta
        # Nielsen's rule on the full step; a shortened one keeps μ (×2 per halving: the region
        # the linear model holds in was smaller than the step)
        mu_ok = jnp.where(
            i == 0, mu * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), mu * 2.0**i
        )
        conv = ok & ((f - f_new) <= cfg.ftol * f)
        conv = conv | (pred <= 1e-30 * jnp.maximum(f, 1e-300)) | (f <= 1e-28)
        return (
            k + 1,
            jnp.where(ok, u_new, u),
            jnp.where(ok, f_new, f),
            jnp.where(ok, mu_ok, mu * nu),
            jnp.where(ok, 2.0, 2.0 * nu),
            n_cg + steps,
            n_acc + ok.astype(jnp.int32),
            conv,
            jnp.isfinite(f_new) | ok,
        )

    def cond(state):
        k, *_, conv, _ = state
        return (k < cfg.max_steps) & ~conv

    f0 = energy(u0)
    z = jnp.zeros((), jnp.int32)
    init = (
        z,
        u0,
        f0,
        jnp.asarray(cfg.damping),
        jnp.asarray(2.0),
        z,
        z,
        jnp.asarray(False),
        jnp.asarray(True),
    )
    k, u, f, mu, _, n_cg, n_acc, conv, _ = jax.lax.while_loop(cond, step, init)
    V, p = split(u)
    if free is not None:
        V = jnp.where(free[:, None], V, V0)
    s, b, c = _parts(V, p, targets, rest, cons, topology, cfg, unravel)
    es = jnp.sum(s * s) + jnp.sum(b * b)
    fit = ShellFit(V, unravel(p), es + jnp.sum(c * c), es, jnp.sum(c * c), s, b)
    finite = jnp.all(jnp.isfinite(V)) & jnp.all(jnp.isfinite(p)) & jnp.isfinite(f)
    result = RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite)
    stats = {
        "steps": k,
        "accepted_steps": n_acc,
        "cg_steps": n_cg,
        "energy0": f0,
        "energy": f,
        "damping": mu,
        "converged": conv,
    }
    return Solution(fit, result, stats)


def _pcg(matvec, precondition, rhs, cfg):
    from .._linalg import pcg

    return pcg(
        matvec, precondition, rhs, jnp.zeros_like(rhs), rtol=cfg.cg_rtol, max_steps=cfg.cg_max_steps
    )


_solve_jit = eqx.filter_jit(_solve)


def shell_solve(
    targets: Callable[[Any], RLA],
    rest: Float[ArrayLike, "V 3"] | Callable[[Any], Array],
    params0: Any,
    vertices0: Float[ArrayLike, "V 3"],
    topology: Topology,
    constraints: ShellConstraints | None = None,
    *,
    solver: ShellSolver | None = None,
    weight: float = 1e6,
    bending: str = "fb",
    bending_stiffness: float = 1.0,
    fold_eps: float = 0.1,
    max_steps: int = 30,
    ftol: float = 1e-10,
    cg_rtol: float = 1e-8,
    cg_max_steps: int = 300,
    damping: float = 1e-4,
    free: Bool[ArrayLike, " V"] | None = None,
    throw: bool = True,
) -> Solution:
    """Minimises `E(V, p)` (module docstring) over the vertices and the parameters jointly by
    Levenberg–Marquardt in float64 (requires `jax_enable_x64`).

    **Arguments:**

    - `targets`: `targets(params) -> RLA`, the RLA targets as a differentiable function of the
      parameters (PanoMan: `X(α, β)`). Pass an `equinox.Module` (or a `jax.tree_util.Partial`)
      to keep its arrays out of the compiled program: a new plain closure recompiles.
    - `rest`: `(V, 3)` the rest mesh the targets are relative to, or a callable of the
      parameters returning it (PanoMan: `B_S(α)`).
    - `params0`: the initial parameters, any pytree of float arrays (may be empty: `()`, for a
      vertex-only deformation).
    - `vertices0`: `(V, 3)` initial vertices (metres; PanoMan §5.3 starts from the decoded
      targets [`bodyprior.panoman.rla_decode`][], aligned to the constraints).
    - `topology`: the mesh's [`bodyprior.Topology`][].
    - `constraints`: a [`bodyprior.panoman.ShellConstraints`][] (default: none; the shell energy
      alone then fixes the shape up to a rigid motion, which the damping pins to the start).
    - `solver`: [`bodyprior.panoman.prepare_shell_solver`][]`(topology)`, prepared once and
      reused (built here if omitted).
    - `weight`: `λ` of eq. 6 (default 1e6: a 1 mm handle error costs as much as a unit relative
      stretch; the paper prints no value). Constraint residuals are in metres (handles, joints,
      surface) or parameter units (editing).
    - `bending`, `bending_stiffness`, `fold_eps`: as in [`bodyprior.panoman.shell_residuals`][].
    - `max_steps`: iteration budget (not a failure when it ends); `ftol`: stop when an accepted
      step lowers `E` by at most `ftol · E`; `cg_rtol`, `cg_max_steps`: the inner PCG;
      `damping`: the initial `μ`.
    - `free`: `(V,)` bool, the vertices that move (default all); the others stay at
      `vertices0` (their rows and columns of the system are decoupled). A solve on a region of a
      larger mesh passes the region's sub-mesh with its outer rings fixed
      ([`bodyprior.panoman.fit_panoman`][]'s face and hand blocks).
    - `throw`: raise on a failed solve (non-finite values).

    **Returns:** a [`bodyprior.Solution`][] with a [`bodyprior.panoman.ShellFit`][] and `stats`
    `steps`, `accepted_steps`, `cg_steps` (total inner PCG steps), `energy0`, `energy`,
    `damping`, `converged`.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "shell_solve needs float64: set jax.config.update('jax_enable_x64', True)."
        )
    _check_topology(topology)
    shape = (topology.n_vertices, 3)
    check_array(vertices0, "vertices0", shape)
    if not callable(rest):
        check_array(rest, "rest", shape)
        rest = jnp.asarray(rest, jnp.float64)
    if not callable(targets):
        raise ValueError(
            f"`targets` must be a callable params -> RLA, got {type(targets).__name__}."
        )
    p_flat, _ = ravel_pytree(params0)
    if constraints is None:
        constraints = shell_constraints()
    _check_constraints(constraints, topology.n_vertices, topology.n_faces, int(p_flat.shape[0]))
    if bending not in _BENDING:
        raise ValueError(f"`bending` must be one of {_BENDING}, got {bending!r}.")
    if not 0.0 < float(fold_eps) < math.pi / 2:
        raise ValueError(f"`fold_eps` must lie in (0, π/2) radians, got {fold_eps}.")
    for name, val in (
        ("weight", weight),
        ("bending_stiffness", bending_stiffness),
        ("ftol", ftol),
        ("cg_rtol", cg_rtol),
        ("damping", damping),
    ):
        if not isinstance(val, (int, float)) or not val >= 0:
            raise ValueError(f"`{name}` must be a number >= 0, got {val!r}.")
    check_positive_int(max_steps, "max_steps")
    check_positive_int(cg_max_steps, "cg_max_steps")
    if solver is None:
        solver = prepare_shell_solver(topology)
    elif not isinstance(solver, ShellSolver) or solver.n_vertices != topology.n_vertices:
        raise ValueError("`solver` must be prepare_shell_solver(topology) for this topology.")
    if free is not None:
        if is_tracer(free):
            raise ValueError("`free` must be a concrete (V,) bool array, got a tracer.")
        free = np.asarray(free)
        if free.shape != (topology.n_vertices,) or free.dtype != np.bool_:
            raise ValueError(
                f"`free` must be a ({topology.n_vertices},) bool array, got {free.dtype} "
                f"{free.shape}."
            )
        free = None if free.all() else jnp.asarray(free)
    f64 = lambda v: jnp.asarray(float(v), jnp.float64)  # noqa: E731
    cfg = _Config(
        bending,
        f64(bending_stiffness),
        f64(fold_eps),
        f64(weight),
        jnp.asarray(int(max_steps)),
        f64(ftol),
        f64(cg_rtol),
        f64(damping),
        int(cg_max_steps),
    )
    sol = _solve_jit(targets, rest, params0, vertices0, constraints, topology, solver, cfg, free)
    return _check(sol, throw, "shell_solve")
