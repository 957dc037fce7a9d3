"""The PanoMan decoder g (Appendix A): RLA features -> vertex positions.

Given target edge lengths `l*` and interior dihedral angles `ψ*` (an [`bodyprior.panoman.RLA`][]
against a reference mesh), g builds a mesh whose lengths and angles match them in least squares:

1. **Connection maps.** Every face `f` carries an orthonormal frame `R_f = (u_f, v_f, n_f)`
   (columns: first edge direction, in-plane perpendicular, outward normal). Across interior edge
   `e` with faces `s` (holding `i → j`) and `t`, `R_t = R_s Q_e` with
   `Q_e = R_z(φ_s) R_x(θ_e) R_z(−φ_t)`: `φ_s, φ_t` are the polar angles of the edge in the two
   faces' 2-D corner coordinates (five edge lengths) and `θ_e = π − ψ*_e` the signed bending angle
   (one angle). Exact for a real mesh (`panoman.md` §3.3; the appendix's own formula omits the
   in-plane rotations, `panoman_v2.md` §1.9).
2. **Frames** by least squares `min Σ_e ‖R_t − R_s Q_e‖²` with the anchor face's frame fixed (the
   paper prints `‖R_ζ − Q_e R_τ‖`, inconsistent with `Q_e = R_ζ⁻¹ R_τ`; this is the consistent
   form). Solved in *tree-conjugated* variables: frames are first propagated along a breadth-first
   spanning tree of the dual graph from the anchor (`T_f`, exact on integrable input), then
   `R_f = W_f T_f` and `W` solves a connection Laplacian whose maps `H_e = T_s Q_e T_tᵀ` are the
   identity on integrable input — so PCG starts at the solution there and converges in a few
   steps otherwise. Then each frame is projected to SO(3) (Newton's polar iteration, determinant
   kept positive).
3. **Positions** by the Poisson step `min Σ_f Σ_k ‖x_{k+1} − x_k − R_f (p_{k+1} − p_k, 0)‖²` with
   the anchor vertex fixed. Its matrix is the uniform graph Laplacian of the topology — it does not
   depend on the pose nor on the reference — so it is factorised once on the host (sparse LU of
   the anchored matrix, held by the [`bodyprior.panoman.Decoder`][]) and reused for every decode.
4. **Placement.** The anchor face keeps the reference's frame and the anchor vertex its reference
   position: a decoded body stands where the reference's torso stands. `align_to=` instead places
   the result rigidly (Kabsch) onto given vertices.

The anchor is a face near the centroid of the reference (on the default body a lower-torso face),
never vertex 0, which sits at the right eye corner: integrability errors of non-integrable input
grow with dual distance from the anchor, so it belongs at the body's centre.

Both linear solves are wrapped in `jax.lax.custom_linear_solve`: the decoder is differentiable by
the implicit-function theorem, not by unrolling CG. Batch with `jax.vmap`. Float64 required.
"""

from __future__ import annotations

import hashlib
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sps
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from jaxtyping import Array, ArrayLike, Float, Int

from .._geometry import _safe_norm, edge_lengths
from .._kinematics import umeyama
from .._linalg import pcg
from .._solution import RESULTS, Solution, _check
from .._topology import Topology
from .._validate import check_array, check_positive_int
from ._rla import RLA, _check_rla, _check_topology, interior_dihedral_angles, wrap_angle

__all__ = ["DecodedMesh", "Decoder", "nearest_rotation", "prepare_decoder", "rla_decode"]


# --------------------------------------------------------------------------------------------------
# Host-side preparation


class _HostLU:
    """Sparse LU of an anchored graph Laplacian (its anchor row and column removed), applied on
    the host through `jax.pure_callback`.

    Hashed and compared by content (`key`: which graph, the topology's faces, the anchor), so that
    two decoders of the same topology and anchor share one compiled program.
    """

    def __init__(self, lap: sps.spmatrix, anchor: int, key: tuple, pairs=None):
        n = lap.shape[0]
        self.anchor = anchor
        self.pairs = pairs  # the graph's edges (dual graph: the faces s, t of each interior edge)
        self.degree = np.asarray(lap.diagonal())
        self.keep = np.setdiff1d(np.arange(n), [anchor])
        self.n = n
        self.lu = spla.splu(sps.csr_matrix(lap)[self.keep][:, self.keep].tocsc())
        self._key = key

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _HostLU) and self._key == other._key

    def solve_host(self, b: ArrayLike) -> np.ndarray:
        """`b`: `(..., n - 1, k)` -> same shape (all leading items in one multi-column solve)."""
        b = np.asarray(b, np.float64)
        lead, k = b.shape[:-2], b.shape[-1]
        m = b.reshape(-1, self.n - 1, k).transpose(1, 0, 2).reshape(self.n - 1, -1)
        x = self.lu.solve(m)
        return x.reshape(self.n - 1, -1, k).transpose(1, 0, 2).reshape(*lead, self.n - 1, k)

    def frame_solve_host(self, H: ArrayLike, b: ArrayLike, x0: ArrayLike, need) -> np.ndarray:
        """Direct solve of the anchored frame system `(N X)_f = deg_f X_f − Σ_{t=f} H_eᵀ X_s −
        Σ_{s=f} H_e X_t` (this factor's graph must be the dual graph; `H`: `(Ei, 3, 3)`, `b`:
        `(F, 3, 3)`, last axis the independent columns) if `need`, else `x0` unchanged."""
        if not bool(need):
            return np.asarray(x0, np.float64)
        H, b = np.asarray(H, np.float64), np.asarray(b, np.float64)
        s, t = self.pairs
        F = self.n
        free = np.ones(F, bool)
        free[self.anchor] = False
        both = free[s] & free[t]
        a3 = np.arange(3)
        rows, cols, vals = [], [], []

        def block(r_face, c_face, M):  # rows 3 r + i, cols 3 c + j, value M[:, i, j]
            rows.append((3 * r_face[:, None, None] + a3[None, :, None]).repeat(3, 2).ravel())
            cols.append((3 * c_face[:, None, None] + a3[None, None, :]).repeat(3, 1).ravel())
            vals.append(M.ravel())

        block(t[both], s[both], -np.swapaxes(H[both], 1, 2))
        block(s[both], t[both], -H[both])
        diag = np.where(free, self.degree, 1.0).repeat(3)
        N = sps.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), (3 * F, 3 * F)
        ) + sps.diags(diag)
        x = spla.splu(N.tocsc()).solve(b.reshape(3 * F, 3))
        return x.reshape(F, 3, 3)

    def solve(self, b: Array) -> Array:
        """Traceable solve of `b` `(..., n - 1, k)` (vmappable: one host call per batch)."""
        shape = jax.ShapeDtypeStruct(b.shape, b.dtype)
        return jax.pure_callback(self.solve_host, shape, b, vmap_method="expand_dims")


def _laplacian(i: np.ndarray, j: np.ndarray, n: int) -> sps.csr_matrix:
    """Graph Laplacian with one unit weight per listed pair (repeated pairs add up)."""
    adj = sps.coo_matrix((np.ones(i.size), (i, j)), shape=(n, n)).tocsr()
    adj = adj + adj.T
    return (sps.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj).tocsr()


class Decoder(eqx.Module):
    """Everything g precomputes for one reference mesh (see the module docstring).

    Build it with [`bodyprior.panoman.prepare_decoder`][]; pass it to
    [`bodyprior.panoman.rla_decode`][] as `decoder=` to decode many RLA vectors of one reference
    without preparing again (about 0.1–0.3 s on the default body, most of it the sparse LU).

    **Fields:**

    - `topology`: the [`bodyprior.Topology`][] (closed or with boundary; boundary edges carry no
      connection and count in the Poisson step only).
    - `ref_lengths`, `ref_angles`: `(E,)` reference edge lengths (m) and interior angles (rad).
    - `anchor_face`, `anchor_vertex`: static ints; the anchor vertex is the first corner of the
      anchor face.
    - `anchor_frame`: `(3, 3)` the anchor face's reference frame (columns `u, v, n`).
    - `anchor_position`: `(3,)` the anchor vertex's reference position (m).
    - `inner`: `(Ei,)` interior edge indices; `corner_s`, `corner_t`: `(Ei,)` the corner at which
      the edge starts in face `s` / `t`.
    - `tree_parent`, `tree_edge`, `tree_flip`: `(F,)` the breadth-first dual spanning tree (parent
      face, the interior-edge slot joining them, whether the face is the edge's `s`);
      `tree_depth`: static int.
    - `degree`: `(F,)` interior edges per face.
    - `frame_rounding`: `(3,)` the preconditioned squared norm of `degree ⊗ I` (the size of the
      terms that cancel in the frame residual; sets PCG's rounding floor).
    - `fans`: `(V, K, 2)` for each vertex, the interior-edge slots and directions around its fan
      in rotational order (`-1` padded; holonomy diagnostic); `fan_ok`: `(V,)` bool, closed fans.
    """

    topology: Topology
    ref_lengths: Float[Array, " E"]
    ref_angles: Float[Array, " E"]
    anchor_frame: Float[Array, "3 3"]
    anchor_position: Float[Array, " 3"]
    inner: Int[Array, " Ei"]
    corner_s: Int[Array, " Ei"]
    corner_t: Int[Array, " Ei"]
    tree_parent: Int[Array, " F"]
    tree_edge: Int[Array, " F"]
    tree_flip: Array
    degree: Float[Array, " F"]
    fans: Int[Array, "V K 2"]
    fan_ok: Array
    frame_rounding: Float[Array, " 3"]
    anchor_face: int = eqx.field(static=True)
    anchor_vertex: int = eqx.field(static=True)
    tree_depth: int = eqx.field(static=True)
    poisson: _HostLU = eqx.field(static=True)
    dual: _HostLU = eqx.field(static=True)


def _face_frames(x: Float[Array, "F 3 3"]) -> Float[Array, "F 3 3"]:
    """Frames `(u, v, n)` (columns) of triangles given as corner positions `(F, 3 corners, 3)`."""
    e0 = x[:, 1] - x[:, 0]
    nrm = jnp.cross(e0, x[:, 2] - x[:, 0])
    u = e0 / _safe_norm(e0)[:, None]
    n = nrm / _safe_norm(nrm)[:, None]
    return jnp.stack([u, jnp.cross(n, u), n], axis=-1)


def prepare_decoder(
    reference: Float[ArrayLike, "V 3"], topology: Topology, *, anchor_face: int | None = None
) -> Decoder:
    """Precompute the decoder g for one reference mesh (host, once).

    **Arguments:**

    - `reference`: `(V, 3)` reference vertices (metres), the mesh the RLA is relative to.
    - `topology`: its [`bodyprior.Topology`][]; must be connected (one dual component).
    - `anchor_face`: the face whose frame (and first corner) is held fixed; default: the face whose
      centroid is nearest the centroid of the reference's vertices (a lower-torso face on the
      default body — never vertex 0's face, at the right eye corner).

    **Returns:** a [`bodyprior.panoman.Decoder`][].

    **Raises:** `ValueError` for a bad shape, an out-of-range anchor or a disconnected mesh.
    """
    _check_topology(topology)
    check_array(reference, "reference", (topology.n_vertices, 3))
    ref = np.asarray(reference, np.float64)
    faces = np.asarray(topology.faces, np.int64)
    F, V = topology.n_faces, topology.n_vertices
    if anchor_face is None:
        cen = ref[faces].mean(axis=1)
        anchor_face = int(np.argmin(np.sum((cen - ref.mean(axis=0)) ** 2, axis=1)))
    anchor_face = int(anchor_face)
    if not 0 <= anchor_face < F:
        raise ValueError(f"`anchor_face` must lie in [0, {F}), got {anchor_face}.")
    anchor_vertex = int(faces[anchor_face, 0])

    ef = np.asarray(topology.edge_faces, np.int64)
    fe = np.asarray(topology.face_edges, np.int64)
    inner = np.flatnonzero(np.asarray(topology.interior))
    s, t = ef[inner, 0], ef[inner, 1]
    edge_slot = np.full(topology.n_edges, -1, np.int64)
    edge_slot[inner] = np.arange(inner.size)
    corner_s = np.argmax(fe[s] == inner[:, None], axis=1)
    corner_t = np.argmax(fe[t] == inner[:, None], axis=1)

    # Dual graph and its breadth-first spanning tree from the anchor face.
    dual = sps.coo_matrix((np.arange(1, inner.size + 1), (s, t)), shape=(F, F)).tocsr()
    dual = dual + dual.T
    n_comp, _ = csgraph.connected_components(dual, directed=False)
    if n_comp != 1:
        raise ValueError(
            f"`topology` must be connected across interior edges; it has {n_comp} components."
        )
    order, pred = csgraph.breadth_first_order(dual, anchor_face, directed=False)
    parent = np.where(pred < 0, anchor_face, pred).astype(np.int64)
    # the interior-edge slot joining each face to its parent (stored in the dual matrix, 1-based)
    tree_edge = np.zeros(F, np.int64)
    nz = np.flatnonzero(pred >= 0)
    tree_edge[nz] = np.asarray(dual[nz, parent[nz]]).ravel() - 1
    tree_flip = np.zeros(F, bool)  # True: the face is the edge's s (its frame is R_parent Q^T)
    tree_flip[nz] = s[tree_edge[nz]] == nz
    depth = np.zeros(F, np.int64)
    for f in order[1:]:
        depth[f] = depth[parent[f]] + 1
    degree = np.bincount(np.concatenate([s, t]), minlength=F).astype(np.float64)

    fans, fan_ok = _fans(faces, fe, V, int(topology.max_valence), edge_slot, s)

    fkey = (V, hashlib.sha1(faces.tobytes()).hexdigest())
    dual_lu = _HostLU(_laplacian(s, t, F), anchor_face, ("dual", fkey, anchor_face), (s, t))
    scale = np.broadcast_to(degree[:, None, None] * np.eye(3), (F, 3, 3)).reshape(F, 9)
    keep_f = dual_lu.keep
    z = dual_lu.solve_host(scale[keep_f][None])[0]
    rounding = (scale[keep_f] * z).reshape(-1, 3, 3).sum(axis=(0, 1)) + 1.0  # + anchor's identity
    corners = jnp.asarray(ref[faces[anchor_face]])[None]
    frame = _face_frames(corners)[0]
    return Decoder(
        topology=topology,
        ref_lengths=edge_lengths(jnp.asarray(ref), topology),
        ref_angles=interior_dihedral_angles(jnp.asarray(ref), topology),
        anchor_frame=frame,
        anchor_position=jnp.asarray(ref[anchor_vertex]),
        inner=jnp.asarray(inner, jnp.int32),
        corner_s=jnp.asarray(corner_s, jnp.int32),
        corner_t=jnp.asarray(corner_t, jnp.int32),
        tree_parent=jnp.asarray(parent, jnp.int32),
        tree_edge=jnp.asarray(tree_edge, jnp.int32),
        tree_flip=jnp.asarray(tree_flip),
        degree=jnp.asarray(degree),
        fans=jnp.asarray(fans, jnp.int32),
        fan_ok=jnp.asarray(fan_ok),
        anchor_face=anchor_face,
        anchor_vertex=anchor_vertex,
        tree_depth=int(depth.max()),
        poisson=_HostLU(
            _laplacian(faces.ravel(), np.roll(faces, -1, axis=1).ravel(), V),
            anchor_vertex,
            ("poisson", fkey, anchor_vertex),
        ),
        dual=dual_lu,
        frame_rounding=jnp.asarray(rounding),
    )


def _fans(faces, fe, V, K, edge_slot, s_of_slot):
    """For each vertex, the interior edges around it in rotational order, with the direction in
    which the walk crosses each (`1`: from the edge's `s` to its `t`)."""
    F = faces.shape[0]
    nxt = {}
    # half-edge (a -> b) -> face and corner of a
    for f in range(F):
        for c in range(3):
            nxt[(faces[f, c], faces[f, (c + 1) % 3])] = (f, c)
    fans = np.full((V, K, 2), -1, np.int64)
    ok = np.zeros(V, bool)
    start = {}
    for f in range(F):
        for c in range(3):
            start.setdefault(int(faces[f, c]), (f, c))
    for v, (f, c) in start.items():
        f0, k = f, 0
        closed = False
        while k < K:
            # leave face f across its edge (prev corner -> v), i.e. corner c+2 -> c
            prev = faces[f, (c + 2) % 3]
            e = fe[f, (c + 2) % 3]
            slot = edge_slot[e]
            nb = nxt.get((v, prev))
            if slot < 0 or nb is None:
                break
            fans[v, k] = (slot, 1 if s_of_slot[slot] == f else 0)
            k += 1
            f, c = nb
            if f == f0:
                closed = True
                break
        ok[v] = closed
    return fans, ok


# --------------------------------------------------------------------------------------------------
# Kernels (one mesh)


def _rz(phi):
    c, s = jnp.cos(phi), jnp.sin(phi)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack(
        [jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2
    )


def _rx(a):
    c, s = jnp.cos(a), jnp.sin(a)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack(
        [jnp.stack([o, z, z], -1), jnp.stack([z, c, -s], -1), jnp.stack([z, s, c], -1)], -2
    )


def _local_corners(lengths, face_edges):
    """2-D corner coordinates `(F, 3, 2)` of each face from its three target lengths, and the
    number of faces whose lengths violate the triangle inequality (guarded: clamped to a sliver)."""
    l01, l12, l20 = (lengths[face_edges[:, k]] for k in range(3))
    c = (l01**2 + l20**2 - l12**2) / (2 * l01 * l20)
    h = (l01 + l12 + l20) * (-l01 + l12 + l20) * (l01 - l12 + l20) * (l01 + l12 - l20)
    floor = 1e-12 * (l01 * l20) ** 2  # a sliver, sin α0 ≈ 5e-7
    bad = h < floor
    s = jnp.sqrt(jnp.maximum(h, floor)) / (2 * l01 * l20)
    c = jnp.clip(c, -1.0, 1.0)
    z = jnp.zeros_like(l01)
    p = jnp.stack(
        [jnp.stack([z, z], -1), jnp.stack([l01, z], -1), jnp.stack([l20 * c, l20 * s], -1)], -2
    )
    return p, jnp.sum(bad)


def _connections(dec: Decoder, lengths, psi):
    """Connection maps `Q` `(Ei, 3, 3)` of the interior edges (`R_t = R_s Q`) and the corners."""
    top = dec.topology
    p, n_bad = _local_corners(lengths, top.face_edges)
    ef = top.edge_faces[dec.inner]
    s, t = ef[:, 0], ef[:, 1]
    ks, kt = dec.corner_s, dec.corner_t
    vs = p[s, (ks + 1) % 3] - p[s, ks]
    vt = -(p[t, (kt + 1) % 3] - p[t, kt])
    phs = jnp.arctan2(vs[:, 1], vs[:, 0])
    pht = jnp.arctan2(vt[:, 1], vt[:, 0])
    theta = math.pi - psi[dec.inner]
    Q = _rz(phs) @ _rx(theta) @ _rz(-pht)
    return Q, p, n_bad


def _tree_frames(dec: Decoder, Q):
    """Frames propagated along the dual spanning tree, by pointer doubling (log2 depth steps)."""
    C = Q[dec.tree_edge]
    C = jnp.where(dec.tree_flip[:, None, None], jnp.swapaxes(C, -1, -2), C)
    is_root = jnp.arange(C.shape[0]) == dec.anchor_face
    C = jnp.where(is_root[:, None, None], jnp.eye(3, dtype=Q.dtype), C)
    anc = dec.tree_parent
    # invariant: R_f = R_anc[f] @ C_f
    for _ in range(max(1, math.ceil(math.log2(dec.tree_depth + 1)))):
        C = C[anc] @ C
        anc = anc[anc]
    return dec.anchor_frame @ C


def _det3(m):
    return jnp.sum(m[..., 0, :] * jnp.cross(m[..., 1, :], m[..., 2, :]), axis=-1)


def _inv_t3(m):
    """`m⁻ᵀ` of 3×3 matrices in closed form (cofactor matrix / determinant): no LAPACK call, so
    it vectorises over many small matrices and differentiates cleanly."""
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    cof = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2)
    return cof / _det3(m)[..., None, None]


def nearest_rotation(m: Float[ArrayLike, "*b 3 3"], *, n_iter: int = 12) -> Float[Array, "*b 3 3"]:
    """The rotation nearest to each `3×3` matrix, by Newton's polar iteration `X ← (X + X⁻ᵀ)/2`
    with closed-form inverses (no LAPACK call: it vectorises over many small matrices).

    Differentiable with NaN-free gradients also where singular values coincide (an exact rotation
    as input), unlike an SVD. For `det(m) < 0` the polar factor `O` is a reflection; the nearest
    rotation is then `O (I − 2 v vᵀ)` with `v` the singular vector of the smallest singular value
    (found by inverse iteration on `Oᵀ m`), returned without gradient (a guard: the decoder's
    frames are near-rotations except on strongly non-integrable input).

    **Arguments:** `m` `(..., 3, 3)`, full rank; `n_iter` static Newton steps (scaled Newton
    converges quadratically; 12 reach float64 round-off for condition numbers up to ~1e8).
    """
    m = jnp.asarray(m)
    x = m
    for _ in range(n_iter):
        # Higham's Frobenius-norm scaling: convergence in a few steps from any conditioning
        y = _inv_t3(x)
        g = jnp.sqrt(jnp.sqrt(jnp.sum(y * y, axis=(-2, -1)) / jnp.sum(x * x, axis=(-2, -1))))
        x = 0.5 * (g[..., None, None] * x + y / g[..., None, None])
    neg = _det3(m) < 0

    def reflected():
        o = jax.lax.stop_gradient(x)
        sym = jnp.swapaxes(o, -1, -2) @ jax.lax.stop_gradient(m)
        sym = 0.5 * (sym + jnp.swapaxes(sym, -1, -2))
        inv = jnp.swapaxes(_inv_t3(sym), -1, -2)
        v = jnp.broadcast_to(jnp.array([0.6, 0.48, 0.64], m.dtype), m.shape[:-1])
        for _ in range(30):
            v = (inv @ v[..., None])[..., 0]
            v = v / jnp.linalg.norm(v, axis=-1, keepdims=True)
        fix = o @ (jnp.eye(3, dtype=m.dtype) - 2.0 * v[..., :, None] * v[..., None, :])
        return jnp.where(neg[..., None, None], fix, x)

    # the guard's work only when some matrix needs it (always, under vmap)
    return jax.lax.cond(jnp.any(neg), reflected, lambda: x)


class DecodedMesh(eqx.Module):
    """What [`bodyprior.panoman.rla_decode`][] returns as `Solution.value`.

    **Fields:**

    - `vertices`: `(V, 3)` decoded positions (metres).
    - `length_residual`: `(E,)` relative length error `l(x)/l* − 1` of the decoded mesh.
    - `angle_residual`: `(E,)` wrapped interior-angle error `ψ(x) − ψ*` (radians).
    - `holonomy`: `(V,)` rotation angle (radians) of the product of the target connection maps
      around each vertex's fan: `0` for integrable input (the discrete Gauss–Codazzi condition);
      `0` also at vertices without a closed fan (boundary).
    - `frames`: `(F, 3, 3)` the face frames used (columns `u, v, n`).
    """

    vertices: Float[Array, "V 3"]
    length_residual: Float[Array, " E"]
    angle_residual: Float[Array, " E"]
    holonomy: Float[Array, " V"]
    frames: Float[Array, "F 3 3"]


def _holonomy(dec: Decoder, Q):
    slot, fwd = dec.fans[..., 0], dec.fans[..., 1]
    Qs = Q[jnp.maximum(slot, 0)]
    Qs = jnp.where((fwd == 1)[..., None, None], Qs, jnp.swapaxes(Qs, -1, -2))
    eye = jnp.eye(3, dtype=Q.dtype)
    Qs = jnp.where((slot >= 0)[..., None, None], Qs, eye)
    P = jnp.broadcast_to(eye, Qs.shape[:1] + (3, 3))
    for k in range(Qs.shape[1]):
        P = P @ Qs[:, k]
    c = 0.5 * (jnp.trace(P, axis1=-2, axis2=-1) - 1.0)
    w = jnp.stack([P[:, 2, 1] - P[:, 1, 2], P[:, 0, 2] - P[:, 2, 0], P[:, 1, 0] - P[:, 0, 1]], -1)
    ang = jnp.arctan2(0.5 * _safe_norm(w), c)
    return jnp.where(dec.fan_ok, ang, 0.0)


def _frame_system(dec: Decoder, H):
    """Normal operator of `Σ_e ‖W_t − W_s H_e‖²` in the layout `X_f = W_fᵀ` (last axis: the 3
    independent world rows), with the anchor face held at the identity."""
    ef = dec.topology.edge_faces[dec.inner]
    s, t = ef[:, 0], ef[:, 1]
    F = dec.degree.shape[0]
    free = (jnp.arange(F) != dec.anchor_face).astype(H.dtype)[:, None, None]
    Ht = jnp.swapaxes(H, -1, -2)

    def couple(Y):
        out = jnp.zeros_like(Y)
        out = out.at[t].add(Ht @ Y[s])
        return out.at[s].add(H @ Y[t])

    def matvec(X):
        return free * (dec.degree[:, None, None] * X - couple(free * X)) + (1 - free) * X

    eye = jnp.broadcast_to(jnp.eye(3, dtype=H.dtype), (F, 3, 3))
    rhs = free * couple((1 - free) * eye) + (1 - free) * eye
    keep = jnp.asarray(dec.dual.keep)

    def precondition(r):
        # The operator with every H_e = I is the scalar dual-graph Laplacian (x I_3): its exact
        # inverse (pose-independent, factored once) is the preconditioner, so PCG needs only a
        # few steps when the maps are near the identity (near-integrable input).
        z = dec.dual.solve(r.reshape(F, 9)[keep]).reshape(-1, 3, 3)
        return jnp.zeros_like(r).at[keep].set(z).at[dec.anchor_face].set(r[dec.anchor_face])

    return matvec, precondition, rhs, eye


def _poisson_solve(dec: Decoder, rhs):
    """Anchored uniform-Laplacian solve `L x = rhs` (rows of the free vertices), host LU."""
    fac = dec.poisson
    keep = jnp.asarray(fac.keep)
    top = dec.topology
    e = top.edges
    w = jnp.where(top.interior, 2.0, 1.0).astype(rhs.dtype)
    V = top.n_vertices

    def matvec(x):  # L restricted to the free vertices
        full = jnp.zeros((V, 3), x.dtype).at[keep].set(x)
        d = full[e[:, 1]] - full[e[:, 0]]
        out = jnp.zeros_like(full).at[e[:, 1]].add(w[:, None] * d).at[e[:, 0]].add(-w[:, None] * d)
        return out[keep]

    return jax.lax.custom_linear_solve(matvec, rhs, lambda _, b: fac.solve(b), symmetric=True)


def _decode(dec: Decoder, rla: RLA, align_to, frame_rtol, frame_max_steps):
    top = dec.topology
    dtype = dec.ref_lengths.dtype
    tiny = 1e-6 * dec.ref_lengths
    lengths = jnp.maximum(dec.ref_lengths * (1.0 + rla.lengths), tiny)
    psi = dec.ref_angles + rla.angles
    Q, p, n_bad = _connections(dec, lengths, psi)

    # Frames: tree propagation, then the least-squares correction W (identity if integrable).
    T = _tree_frames(dec, Q)
    ef = top.edge_faces[dec.inner]
    H = T[ef[:, 0]] @ Q @ jnp.swapaxes(T[ef[:, 1]], -1, -2)
    matvec, precond, rhs, eye = _frame_system(dec, H)

    def solve(mv, b):
        # rounding level: the residual is a difference of O(degree) terms of the start
        x, k, ratio = pcg(
            mv,
            precond,
            b,
            eye,
            rtol=frame_rtol,
            max_steps=frame_max_steps,
            rounding_level=dec.frame_rounding.astype(b.dtype),
        )
        # Far from integrable the maps H_e stray from I and the Laplacian preconditioner weakens:
        # past the PCG budget, one sparse direct solve of the same system on the host. (A host
        # callback that checks the flag itself, not `lax.cond`: under `vmap` a cond runs both
        # branches for every item.)
        need = ratio > frame_rtol
        shape = jax.ShapeDtypeStruct(b.shape, b.dtype)
        x = jax.pure_callback(
            dec.dual.frame_solve_host, shape, H, b, x, need, vmap_method="sequential"
        )
        return x, (k, jnp.where(need, jnp.zeros_like(ratio), ratio))

    X, (steps, ratio) = jax.lax.custom_linear_solve(
        matvec, rhs, solve, symmetric=True, has_aux=True
    )
    frames = nearest_rotation(jnp.swapaxes(X, -1, -2) @ T)

    # Positions: Poisson step with the anchor vertex fixed, then placement.
    faces = top.faces
    V = top.n_vertices
    div = jnp.zeros((V, 3), dtype)
    for k in range(3):
        a, b = faces[:, k], faces[:, (k + 1) % 3]
        g = frames[:, :, :2] @ (p[:, (k + 1) % 3] - p[:, k])[..., None]
        div = div.at[b].add(g[..., 0]).at[a].add(-g[..., 0])
    keep = jnp.asarray(dec.poisson.keep)
    x = jnp.zeros((V, 3), dtype).at[keep].set(_poisson_solve(dec, div[keep]))
    x = x + dec.anchor_position
    if align_to is not None:
        x = umeyama(x, align_to, with_scale=False).apply(x)

    l_out = edge_lengths(x, top)
    psi_out = interior_dihedral_angles(x, top)
    mesh = DecodedMesh(
        vertices=x,
        length_residual=l_out / lengths - 1.0,
        angle_residual=jnp.where(top.interior, wrap_angle(psi_out - psi), 0.0),
        holonomy=_holonomy(dec, Q),
        frames=frames,
    )
    # The frame solve always ends at its tolerance (PCG, else the direct solve): only
    # non-finite values fail.
    result = RESULTS.where(jnp.all(jnp.isfinite(x)), RESULTS.successful, RESULTS.nonfinite)
    stats = dict(frame_cg_steps=steps, frame_cg_ratio=ratio, n_guarded_faces=n_bad)
    return Solution(mesh, result, stats)


_decode_jit = eqx.filter_jit(_decode)


def rla_decode(
    rla: RLA,
    reference: Float[ArrayLike, "V 3"] | None,
    topology: Topology,
    *,
    decoder: Decoder | None = None,
    align_to: Float[ArrayLike, "V 3"] | None = None,
    frame_rtol: float = 1e-8,
    frame_max_steps: int = 25,
    throw: bool = True,
) -> Solution:
    """Decode RLA features into vertex positions (PanoMan's g, Appendix A).

    **Arguments:**

    - `rla`: an [`bodyprior.panoman.RLA`][] with `(E,)` leaves, as
      [`bodyprior.panoman.rla_encode`][] returns (angles wrapped or unwrapped: g uses them
      through sines and cosines). Lengths `l̂ ≤ −1` are clamped to `1e-6 l_r`, and faces whose
      target lengths violate the triangle inequality are decoded as slivers
      (`stats["n_guarded_faces"]` counts them).
    - `reference`: `(V, 3)` the mesh the RLA is relative to (metres). May be `None` when `decoder`
      is given.
    - `topology`: the shared [`bodyprior.Topology`][].
    - `decoder`: a [`bodyprior.panoman.Decoder`][] of this reference from
      [`bodyprior.panoman.prepare_decoder`][]; default: prepared here (host work each call).
    - `align_to`: optional `(V, 3)` vertices to place the result onto rigidly (Kabsch); default:
      the anchor face keeps the reference's frame and position.
    - `frame_rtol`, `frame_max_steps`: PCG tolerance (preconditioned residual, relative to the
      tree-propagated start) and step budget of the frame solve; past the budget the same system
      is solved directly on the host (sparse LU; `stats["frame_cg_ratio"]` is then 0). Exact
      input takes 0 steps, near-integrable input a few.
    - `throw`: raise if the result is not successful (non-finite values).

    **Returns:** a [`bodyprior.Solution`][] with `value` a [`bodyprior.panoman.DecodedMesh`][]
    (vertices, per-edge length and angle residuals, per-vertex holonomy, frames) and `stats`
    `frame_cg_steps`, `frame_cg_ratio`, `n_guarded_faces`.

    Exact on integrable input (the RLA of a real mesh): the vertices come back up to a rigid motion
    to about 1e-12 m on the default body. On non-integrable input (e.g. a blend of two RLA vectors)
    it returns the least-squares mesh of the two steps above and the residuals say how far from
    the targets it is. Jitted once per topology, anchor and dtype; differentiable (implicit
    function), batch with `jax.vmap` (over `rla` and `align_to`, `decoder` unbatched).

    **Raises:** `ValueError` before tracing for bad shapes or types; without `jax_enable_x64`.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "rla_decode solves in float64: enable it first with "
            "`jax.config.update('jax_enable_x64', True)`."
        )
    _check_topology(topology)
    _check_rla(rla, topology)
    if decoder is None:
        if reference is None:
            raise ValueError("`reference` is required when no `decoder` is given.")
        decoder = prepare_decoder(reference, topology)
    elif not isinstance(decoder, Decoder):
        raise ValueError(f"`decoder` must be a bodyprior.panoman.Decoder, got {type(decoder)}.")
    elif (
        decoder.topology.n_edges != topology.n_edges
        or decoder.topology.n_vertices != topology.n_vertices
    ):
        raise ValueError("`decoder` was prepared for another topology.")
    if align_to is not None:
        check_array(align_to, "align_to", (topology.n_vertices, 3))
        align_to = jnp.asarray(align_to, jnp.float64)
    frame_max_steps = check_positive_int(frame_max_steps, "frame_max_steps")
    if not float(frame_rtol) > 0:
        raise ValueError(f"`frame_rtol` must be > 0, got {frame_rtol}.")
    rla = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), rla)
    sol = _decode_jit(decoder, rla, align_to, float(frame_rtol), frame_max_steps)
    return _check(sol, throw, "rla_decode")


def decoder_with_reference(decoder: Decoder, reference: Float[ArrayLike, "V 3"]) -> Decoder:
    """The same decoder for another reference mesh of its topology (traceable, differentiable).

    Everything [`bodyprior.panoman.prepare_decoder`][] derives from the topology (dual tree, fans,
    the two sparse factorisations) is kept; the reference lengths, angles and the anchor's frame
    and position are recomputed from `reference` `(V, 3)` (metres). This is how PanoMan decodes
    relative to the shaped rest `B_S(α)` of every `α` (eq. 4) without host work per shape.
    """
    ref = jnp.asarray(reference, decoder.ref_lengths.dtype)
    top = decoder.topology
    corners = ref[top.faces[decoder.anchor_face]][None]
    return eqx.tree_at(
        lambda d: (d.ref_lengths, d.ref_angles, d.anchor_frame, d.anchor_position),
        decoder,
        (
            edge_lengths(ref, top),
            interior_dihedral_angles(ref, top),
            _face_frames(corners)[0],
            ref[decoder.anchor_vertex],
        ),
    )
