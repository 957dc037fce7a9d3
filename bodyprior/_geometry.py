"""Differentiable geometry kernels on one triangle mesh.

Every function takes the vertices of **one** mesh, shape `(V, 3)` in metres in the world frame;
batch with `jax.vmap`. Connectivity comes either as a raw `(F, 3)` face array or as a
[`bodyprior.Topology`][] (for edge-based quantities). Nothing is jitted here.

Values *and* gradients are NaN-free at degenerate configurations (zero-area faces, coincident
vertices, flat hinges, queries lying exactly on the surface). Square roots, divisions and `atan2`
use the "double where" trick: the unsafe argument is replaced by a harmless constant inside
`jnp.where` before the operation, and the result is selected afterwards, so reverse-mode AD never
meets `0 / 0`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ._topology import Topology
from ._validate import check_array, check_positive_int, check_range, is_tracer

__all__ = [
    "barycentric_points",
    "closest_points_on_mesh",
    "cotangent_weights",
    "cross_section_areas",
    "dihedral_angles",
    "edge_lengths",
    "face_areas",
    "face_normals",
    "laplacian_apply",
    "laplacian_matrix",
    "laplacian_sparse",
    "nearest_neighbors",
    "sample_surface",
    "uniform_weights",
    "vertex_areas",
    "vertex_normals",
]

# Cotangents are computed as cos / max(sin, _MIN_SIN) (both normalised by the edge lengths), so they
# are bounded by about 1 / _MIN_SIN for (near-)degenerate triangles.
_MIN_SIN = 1e-6


# --------------------------------------------------------------------------------------------------
# Input handling and NaN-safe primitives
# --------------------------------------------------------------------------------------------------


def _as_float(x) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _check_vertices(vertices, name: str = "vertices", n: int | None = None) -> Array:
    check_array(vertices, name, (n, 3))
    return _as_float(vertices)


def _check_faces(faces, n_vertices: int, name: str = "faces") -> Array:
    check_array(faces, name, (None, 3), integer=True)
    check_range(faces, name, 0, n_vertices - 1)
    return jnp.asarray(faces)


def _check_topology(topology, vertices, name: str = "vertices") -> Array:
    if not isinstance(topology, Topology):
        raise ValueError(f"`topology` must be a bodyprior.Topology, got {type(topology).__name__}.")
    return _check_vertices(vertices, name, topology.n_vertices)


def _eps(dtype) -> Array:
    """Threshold on squared norms below which a vector is treated as zero.

    `sqrt(finfo.tiny)` (about 1e-19 in float32, 1e-154 in float64): far below any physical squared
    length, while `1 / sqrt(eps)` stays representable so gradients cannot overflow.
    """
    return jnp.asarray(np.sqrt(np.finfo(dtype).tiny), dtype=dtype)


def _safe_norm(x: Float[Array, "... 3"]) -> Float[Array, " ..."]:
    """Euclidean norm over the last axis with value and gradient 0 at the zero vector."""
    sq = jnp.sum(x * x, axis=-1)
    ok = sq > _eps(x.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def _safe_normalize(x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """`x / |x|` over the last axis; the zero vector (and its gradient) maps to zero."""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    ok = sq > _eps(x.dtype)
    return x / jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 1.0)


def _safe_div(num: Array, den: Array) -> Array:
    """`num / den` where `|den|` is above eps, else 0 (gradient-safe)."""
    ok = jnp.abs(den) > _eps(den.dtype)
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _face_cross(vertices: Float[Array, "V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "F 3"]:
    tri = vertices[faces]
    return jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


# --------------------------------------------------------------------------------------------------
# Per-face / per-vertex quantities
# --------------------------------------------------------------------------------------------------


def face_normals(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, "F 3"]:
    """Unit outward normals of the faces.

    The normal of face `(a, b, c)` is `normalize((x_b - x_a) × (x_c - x_a))`, i.e. counter-clockwise
    corners seen from outside give an outward normal (right-hand rule).

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh.
    - `faces`: `(F, 3)` integer vertex indices.

    **Returns:** `(F, 3)` unit normals (dimensionless). Zero-area faces get the zero vector, with
    finite gradients.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    return _safe_normalize(_face_cross(vertices, faces))


def face_areas(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, " F"]:
    """Areas of the faces.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh (metres).
    - `faces`: `(F, 3)` integer vertex indices.

    **Returns:** `(F,)` areas in square metres (`½ |(x_b - x_a) × (x_c - x_a)|`); the gradient is
    finite (zero) at zero area.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    return 0.5 * _safe_norm(_face_cross(vertices, faces))


def vertex_normals(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, "V 3"]:
    """Area-weighted unit vertex normals.

    The normal of vertex `v` is `normalize(Σ_f A_f n_f)` over the faces `f` incident to `v`, with
    `A_f n_f` half the (unnormalised) cross product of face `f`.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh.
    - `faces`: `(F, 3)` integer vertex indices.

    **Returns:** `(V, 3)` unit normals; vertices with no incident face of non-zero area (or whose
    weighted normals cancel) get the zero vector.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    cross = _face_cross(vertices, faces)
    acc = jnp.zeros_like(vertices)
    for c in range(3):
        acc = acc.at[faces[:, c]].add(cross)
    return _safe_normalize(acc)


def vertex_areas(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, " V"]:
    """Barycentric (lumped) vertex areas: one third of the area of every incident face.

    This is the diagonal of the lumped mass matrix; it sums to the total surface area.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh (metres).
    - `faces`: `(F, 3)` integer vertex indices.

    **Returns:** `(V,)` areas in square metres.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    third = 0.5 * _safe_norm(_face_cross(vertices, faces)) / 3.0
    acc = jnp.zeros(vertices.shape[0], dtype=vertices.dtype)
    for c in range(3):
        acc = acc.at[faces[:, c]].add(third)
    return acc


# --------------------------------------------------------------------------------------------------
# Edge quantities
# --------------------------------------------------------------------------------------------------


def edge_lengths(vertices: Float[ArrayLike, "V 3"], topology: Topology) -> Float[Array, " E"]:
    """Lengths of the unique undirected edges `topology.edges`.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh (metres), `V = topology.n_vertices`.
    - `topology`: the mesh's [`bodyprior.Topology`][].

    **Returns:** `(E,)` lengths `|x_j - x_i|` in metres (gradient 0 where an edge has zero length).
    """
    vertices = _check_topology(topology, vertices)
    e = topology.edges
    return _safe_norm(vertices[e[:, 1]] - vertices[e[:, 0]])


def dihedral_angles(vertices: Float[ArrayLike, "V 3"], topology: Topology) -> Float[Array, " E"]:
    """Signed dihedral angles of the edges (the bending angle of each hinge).

    For interior edge `e = (i, j)` with faces `s` (holding the directed edge `i -> j`) and `t`
    (holding `j -> i`) and opposite vertices `k ∈ s`, `l ∈ t` (see [`bodyprior.Topology`][]):

    - `n_s = normalize((x_j - x_i) × (x_k - x_i))`, `n_t = normalize((x_i - x_j) × (x_l - x_j))` are
      the outward unit normals, `d = normalize(x_j - x_i)` the edge direction as oriented in `s`;
    - `θ_e = atan2((n_s × n_t) · d, n_s · n_t) ∈ (-π, π]`, the angle that rotates `n_s` into `n_t`
      about `d`.

    So `θ = 0` for a flat hinge, `θ > 0` for a **convex** fold (a closed convex surface has all
    angles positive) and `θ < 0` for a concave one; `|θ|` is the angle between the two face normals,
    i.e. `π` minus the interior (solid-side) dihedral angle. The value does not depend on which face
    is called `s`. This is the discrete-shells convention (Fröhlich & Botsch, scikit-shapes,
    GOAST). PanoMan prints the *interior* angle `ψ = π − θ` instead:
    [`bodyprior.panoman.interior_dihedral_angles`][], so its relative angle is `−(θ − θ_r)`.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh, `V = topology.n_vertices`.
    - `topology`: the mesh's [`bodyprior.Topology`][].

    **Returns:** `(E,)` angles in radians. Boundary edges, and hinges with a zero-area face, get
    `0`; value and gradient are NaN-free there and at flat hinges.
    """
    vertices = _check_topology(topology, vertices)
    st = _hinge_stencils(topology)
    x = vertices[st]
    return _hinge_angles(x[:, 0], x[:, 1], x[:, 2], x[:, 3], topology.interior)


def _hinge_stencils(topology: Topology) -> Int[Array, "E 4"]:
    """`(i, j, k, l)` per edge: its two vertices and the opposite vertices of faces `s` and `t`
    (see [`bodyprior.dihedral_angles`][]); a boundary edge has `l = i` (its angle is 0)."""
    e, opp = topology.edges, topology.edge_opposite
    m = jnp.where(topology.interior, opp[:, 1], e[:, 0])
    return jnp.stack([e[:, 0], e[:, 1], opp[:, 0], m], axis=1)


def _hinge_angles(xi, xj, xk, xl, interior):
    """The signed bending angle of hinges given by their four stencil points (`... 3` each) and
    an `interior` mask: the kernel of [`bodyprior.dihedral_angles`][]."""
    d = _safe_normalize(xj - xi)
    n_s = _safe_normalize(jnp.cross(xj - xi, xk - xi))
    n_t = _safe_normalize(jnp.cross(xi - xj, xl - xj))
    y = jnp.sum(jnp.cross(n_s, n_t) * d, axis=-1)
    x = jnp.sum(n_s * n_t, axis=-1)
    # For unit normals and a unit edge direction perpendicular to both, (y, x) = (sin θ, cos θ); a
    # degenerate hinge has a zero normal and x = y = 0.
    ok = interior & (x * x + y * y > 0.25)
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)


def cotangent_weights(vertices: Float[ArrayLike, "V 3"], topology: Topology) -> Float[Array, " E"]:
    """Cotangent Laplacian edge weights `w_ij = ½ (cot α_ij + cot β_ij)`.

    `α_ij`, `β_ij` are the angles opposite edge `(i, j)` in its two faces; boundary edges get only
    the one term `½ cot α_ij`. Weights are negative across obtuse angles. For (near-)degenerate
    triangles the cotangent is bounded: it is computed as `cos / max(sin, 1e-6)`, so `|cot| ≲ 1e6`,
    and value and gradient stay finite even for coincident vertices.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh, `V = topology.n_vertices`.
    - `topology`: the mesh's [`bodyprior.Topology`][].

    **Returns:** `(E,)` dimensionless weights, aligned with `topology.edges`.
    """
    vertices = _check_topology(topology, vertices)
    e, opp = topology.edges, topology.edge_opposite
    xi, xj = vertices[e[:, 0]], vertices[e[:, 1]]

    def half_cot(k):
        xk = vertices[jnp.maximum(k, 0)]
        a, b = xi - xk, xj - xk
        la, lb = _safe_norm(a), _safe_norm(b)
        scale = la * lb
        cos = jnp.sum(a * b, axis=-1)
        sin = _safe_norm(jnp.cross(a, b))
        den = jnp.maximum(sin, _MIN_SIN * scale)
        return jnp.where(k >= 0, 0.5 * _safe_div(cos, den), 0.0)

    return half_cot(opp[:, 0]) + half_cot(opp[:, 1])


def uniform_weights(topology: Topology) -> Float[Array, " E"]:
    """Uniform ("graph") Laplacian edge weights: ones, aligned with `topology.edges`.

    **Arguments:**

    - `topology`: the mesh's [`bodyprior.Topology`][].

    **Returns:** `(E,)` ones in the default float dtype.
    """
    if not isinstance(topology, Topology):
        raise ValueError(f"`topology` must be a bodyprior.Topology, got {type(topology).__name__}.")
    return jnp.ones(topology.n_edges, dtype=jnp.result_type(float))


def _check_weights(weights, topology: Topology) -> Array:
    if not isinstance(topology, Topology):
        raise ValueError(f"`topology` must be a bodyprior.Topology, got {type(topology).__name__}.")
    check_array(weights, "weights", (topology.n_edges,))
    return _as_float(weights)


def laplacian_apply(
    x: Float[ArrayLike, " V *d"], topology: Topology, weights: Float[ArrayLike, " E"]
) -> Float[Array, " V *d"]:
    """Applies the edge-weighted graph Laplacian: `(L x)_i = Σ_{j ∈ N(i)} w_ij (x_j - x_i)`.

    With this sign `L` is negative semi-definite for non-negative weights (`xᵀ L x ≤ 0`) and
    `L x = 0` for constant `x`. With [`bodyprior.cotangent_weights`][] `(L x)_i` is the integrated
    (area-weighted) Laplace-Beltrami operator at vertex `i`; divide by
    [`bodyprior.vertex_areas`][] for pointwise values. It vanishes at interior vertices of a flat
    patch for `x` linear.

    **Arguments:**

    - `x`: `(V,)` or `(V, d)` per-vertex values (e.g. vertex positions).
    - `topology`: the mesh's [`bodyprior.Topology`][].
    - `weights`: `(E,)` edge weights, e.g. [`bodyprior.cotangent_weights`][] or
      [`bodyprior.uniform_weights`][].

    **Returns:** an array shaped like `x`.
    """
    weights = _check_weights(weights, topology)
    if not hasattr(x, "shape"):
        x = np.asarray(x)
    if x.ndim not in (1, 2) or x.shape[0] != topology.n_vertices:
        raise ValueError(
            f"`x` must have shape ({topology.n_vertices},) or ({topology.n_vertices}, d), "
            f"got shape {tuple(x.shape)}."
        )
    check_array(x, "x", (topology.n_vertices,) + (None,) * (x.ndim - 1))
    x = _as_float(x)
    i, j = topology.edges[:, 0], topology.edges[:, 1]
    w = weights.reshape((-1,) + (1,) * (x.ndim - 1))
    flux = w * (x[j] - x[i])
    seg = jnp.concatenate([i, j])
    return jax.ops.segment_sum(
        jnp.concatenate([flux, -flux]), seg, num_segments=topology.n_vertices
    )


def laplacian_matrix(topology: Topology, weights: Float[ArrayLike, " E"]) -> Float[Array, "V V"]:
    """Dense Laplacian matrix `L` with `L @ x == laplacian_apply(x, topology, weights)`.

    `L_ij = L_ji = w_ij` for each edge, `L_ii = -Σ_j w_ij`. Differentiable in `weights`; `O(V²)`
    memory, so meant for small meshes and tests (see [`bodyprior.laplacian_sparse`][] for large
    ones).

    **Arguments:**

    - `topology`: the mesh's [`bodyprior.Topology`][].
    - `weights`: `(E,)` edge weights.

    **Returns:** `(V, V)` symmetric matrix.
    """
    weights = _check_weights(weights, topology)
    i, j = topology.edges[:, 0], topology.edges[:, 1]
    n = topology.n_vertices
    L = jnp.zeros((n, n), dtype=weights.dtype)
    L = L.at[i, j].add(weights).at[j, i].add(weights)
    return L.at[i, i].add(-weights).at[j, j].add(-weights)


def laplacian_sparse(topology: Topology, weights: Float[ArrayLike, " E"]):
    """Host-side `scipy.sparse` Laplacian for direct solvers (same entries as `laplacian_matrix`).

    **Arguments:**

    - `topology`: the mesh's [`bodyprior.Topology`][].
    - `weights`: `(E,)` concrete edge weights (not a tracer).

    **Returns:** a `(V, V)` `scipy.sparse.csr_matrix` (float64) with `L_ij = w_ij`, `L_ii = -Σ_j
    w_ij`.
    """
    import scipy.sparse as sp

    if is_tracer(weights):
        raise ValueError(
            "`weights` must be concrete for laplacian_sparse (host-side), got a tracer."
        )
    w = np.asarray(_check_weights(weights, topology), dtype=np.float64)
    e = np.asarray(topology.edges)
    n = topology.n_vertices
    diag = np.zeros(n)
    np.add.at(diag, e[:, 0], -w)
    np.add.at(diag, e[:, 1], -w)
    rows = np.concatenate([e[:, 0], e[:, 1], np.arange(n)])
    cols = np.concatenate([e[:, 1], e[:, 0], np.arange(n)])
    vals = np.concatenate([w, w, diag])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


# --------------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------------


def barycentric_points(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    face_idx: Int[ArrayLike, " N"],
    bary: Float[ArrayLike, "N 3"],
) -> Float[Array, "N 3"]:
    """Points given by face indices and barycentric coordinates.

    Point `n` is `Σ_c bary[n, c] x_{faces[face_idx[n], c]}`.

    **Arguments:**

    - `vertices`: `(V, 3)` vertex positions of one mesh.
    - `faces`: `(F, 3)` integer vertex indices.
    - `face_idx`: `(N,)` integer face indices in `[0, F)`.
    - `bary`: `(N, 3)` barycentric coordinates (weights of the three corners, usually summing to 1).

    **Returns:** `(N, 3)` points, differentiable in `vertices` and `bary`.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    dims: dict[str, int] = {}
    check_array(face_idx, "face_idx", ("N",), integer=True, dims=dims)
    check_range(face_idx, "face_idx", 0, faces.shape[0] - 1)
    check_array(bary, "bary", ("N", 3), dims=dims)
    tri = vertices[faces[jnp.asarray(face_idx)]]
    return jnp.einsum("nc,ncd->nd", _as_float(bary).astype(tri.dtype), tri)


def sample_surface(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"], n: int, *, key: PRNGKeyArray
) -> tuple[Float[Array, "n 3"], Int[Array, " n"], Float[Array, "n 3"]]:
    """Samples `n` points uniformly (area-weighted) on the surface.

    Faces are drawn with probability proportional to their area, then a uniform point in the
    triangle (square-root-free reflection of a uniform point in the unit square). The points are a
    reparameterised, differentiable function of `vertices` (for fixed `key`).

    **Arguments:**

    - `key`: a `jax.random` key.
    - `vertices`: `(V, 3)` vertex positions of one mesh; the total area must be positive.
    - `faces`: `(F, 3)` integer vertex indices.
    - `n`: number of samples (static Python int).

    **Returns:** `(points, face_idx, bary)`: `(n, 3)` points, `(n,)` int32 face indices, `(n, 3)`
    barycentric coordinates with `points == barycentric_points(vertices, faces, face_idx, bary)`.
    """
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"`n` must be a non-negative Python int, got {n!r}.")
    n = int(n)
    areas = jax.lax.stop_gradient(0.5 * _safe_norm(_face_cross(vertices, faces)))
    kf, kb = jax.random.split(key)
    face_idx = jax.random.choice(kf, faces.shape[0], (n,), p=areas / jnp.sum(areas)).astype(
        jnp.int32
    )
    uv = jax.random.uniform(kb, (n, 2), dtype=vertices.dtype)
    flip = jnp.sum(uv, axis=-1, keepdims=True) > 1.0
    uv = jnp.where(flip, 1.0 - uv, uv)
    bary = jnp.concatenate([1.0 - jnp.sum(uv, axis=-1, keepdims=True), uv], axis=-1)
    tri = vertices[faces[face_idx]]
    return jnp.einsum("nc,ncd->nd", bary, tri), face_idx, bary


# --------------------------------------------------------------------------------------------------
# Nearest neighbours and closest points (brute force, chunked)
# --------------------------------------------------------------------------------------------------


def nearest_neighbors(
    queries: Float[ArrayLike, "Q 3"], points: Float[ArrayLike, "P 3"], *, chunk_size: int = 1024
) -> tuple[Int[Array, " Q"], Float[Array, " Q"]]:
    """Nearest point of `points` for every query (exact brute force).

    Cost `O(Q · P)` time; memory `O(chunk_size · P)`: the queries are processed `chunk_size` at a
    time with `jax.lax.map(..., batch_size=chunk_size)`. The search itself is not differentiated;
    the returned squared distances are recomputed from the chosen pairs, so they are differentiable
    in `queries` and `points`. Jittable (all shapes static).

    **Arguments:**

    - `queries`: `(Q, 3)` query points.
    - `points`: `(P, 3)` candidate points, `P >= 1`.
    - `chunk_size`: number of queries per block (static).

    **Returns:** `(indices, sq_distances)`: `(Q,)` int32 index of the nearest point (the lowest
    index on ties) and `(Q,)` squared Euclidean distances.
    """
    queries = _check_vertices(queries, "queries")
    points = _check_vertices(points, "points")
    if points.shape[0] == 0:
        raise ValueError("`points` must contain at least one point, got shape (0, 3).")
    chunk_size = check_positive_int(chunk_size, "chunk_size")
    dtype = jnp.result_type(queries, points)
    queries, points = queries.astype(dtype), points.astype(dtype)
    if queries.shape[0] == 0:
        return jnp.zeros((0,), jnp.int32), jnp.zeros((0,), dtype)
    idx = _nn_search(jax.lax.stop_gradient(queries), jax.lax.stop_gradient(points), chunk_size)
    return idx, jnp.sum((queries - points[idx]) ** 2, axis=-1)


def _closest_bary(p: Float[Array, "*b 3"], a, b, c) -> Float[Array, "... 3"]:
    """Barycentric coordinates of the point of triangle `abc` closest to `p` (branch-free).

    Ericson, *Real-Time Collision Detection* (2005), §5.1.5 `ClosestPtPointTriangle`: Voronoi-region
    tests for the three vertices, three edges and the interior, evaluated for all regions and
    selected with `jnp.where` (earlier regions take precedence, as in the branching original). All
    divisions are guarded, so gradients stay finite for degenerate triangles.
    """
    ab, ac = b - a, c - a
    dot = lambda u, v: jnp.sum(u * v, axis=-1)
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    zero, one = jnp.zeros_like(d1), jnp.ones_like(d1)
    # Denominators: d1 - d3 = |ab|², d2 - d6 = |ac|², (d4 - d3) + (d5 - d6) = |bc|², va + vb + vc =
    # |ab × ac|²; each is >= 0 and zero only for coincident vertices / zero area.
    v_ab = jnp.clip(_safe_div(d1, d1 - d3), 0.0, 1.0)
    w_ac = jnp.clip(_safe_div(d2, d2 - d6), 0.0, 1.0)
    w_bc = jnp.clip(_safe_div(d4 - d3, (d4 - d3) + (d5 - d6)), 0.0, 1.0)
    den = va + vb + vc
    v_in, w_in = _safe_div(vb, den), _safe_div(vc, den)

    stack = lambda u, v, w: jnp.stack([u, v, w], axis=-1)
    out = stack(1.0 - v_in - w_in, v_in, w_in)  # interior
    regions = [  # applied from lowest to highest precedence
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), stack(zero, 1.0 - w_bc, w_bc)),  # edge BC
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), stack(1.0 - w_ac, zero, w_ac)),  # edge AC
        ((d6 >= 0) & (d5 <= d6), stack(zero, zero, one)),  # vertex C
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), stack(1.0 - v_ab, v_ab, zero)),  # edge AB
        ((d3 >= 0) & (d4 <= d3), stack(zero, one, zero)),  # vertex B
        ((d1 <= 0) & (d2 <= 0), stack(one, zero, zero)),  # vertex A
    ]
    for cond, bary in regions:
        out = jnp.where(cond[..., None], bary, out)
    return out


# The two searches below are the only jitted code in this module. They are integer-valued and never
# differentiated (their inputs are stop-gradient'ed), and `lax.map` called eagerly re-traces and
# re-compiles its body on every call; a module-level `jit` with a static `chunk_size` compiles once
# per shape. Inside a user's `jit` they are simply inlined.


@functools.partial(jax.jit, static_argnums=2)
def _nn_search(
    queries: Float[Array, "Q 3"], points: Float[Array, "P 3"], chunk_size: int
) -> Int[Array, " Q"]:
    def one(q):
        return jnp.argmin(jnp.sum((points - q) ** 2, axis=-1)).astype(jnp.int32)

    return jax.lax.map(one, queries, batch_size=min(chunk_size, queries.shape[0]))


@functools.partial(jax.jit, static_argnums=2)
def _face_search(
    queries: Float[Array, "Q 3"], tri: Float[Array, "F 3 3"], chunk_size: int
) -> Int[Array, " Q"]:
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def one(q):
        bary = _closest_bary(q, a, b, c)
        pts = bary[:, 0:1] * a + bary[:, 1:2] * b + bary[:, 2:3] * c
        return jnp.argmin(jnp.sum((pts - q) ** 2, axis=-1)).astype(jnp.int32)

    return jax.lax.map(one, queries, batch_size=min(chunk_size, queries.shape[0]))


@jax.jit
def _candidate_search(
    queries: Float[Array, "Q 3"], tri: Float[Array, "F 3 3"], candidates: Int[Array, "Q K"]
) -> Int[Array, " Q"]:
    t = tri[candidates]  # (Q, K, 3, 3)
    q = queries[:, None]
    bary = _closest_bary(q, t[..., 0, :], t[..., 1, :], t[..., 2, :])
    pts = jnp.einsum("qkc,qkcd->qkd", bary, t)
    best = jnp.argmin(jnp.sum((pts - q) ** 2, axis=-1), axis=1)
    return jnp.take_along_axis(candidates, best[:, None], axis=1)[:, 0].astype(jnp.int32)


def mesh_ring_faces(faces: Int[ArrayLike, "F 3"], n_vertices: int, rings: int) -> np.ndarray:
    """The faces within `rings` edge-rings of every vertex (host, NumPy), for the `candidates` of
    [`bodyprior.closest_points_on_mesh`][].

    Ring 1 of vertex `i` is the faces incident to `i`; ring `r + 1` adds the faces incident to
    any vertex of ring `r`. Rows are padded to the longest by repeating their first face.

    **Arguments:** `faces (F, 3)`; `n_vertices` `V`; `rings >= 1`.

    **Returns:** `(V, K)` int32 face indices (an isolated vertex gets face 0).
    """
    import scipy.sparse as sp

    f = np.asarray(faces)
    check_array(f, "faces", (None, 3), integer=True)
    n_vertices = check_positive_int(n_vertices, "n_vertices")
    rings = check_positive_int(rings, "rings")
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise ValueError(f"`faces` must index `n_vertices` = {n_vertices} vertices.")
    nf = f.shape[0]
    inc = sp.csr_matrix(
        (np.ones(3 * nf, bool), (f.reshape(-1), np.repeat(np.arange(nf), 3))),
        shape=(n_vertices, nf),
    )  # vertex x face incidence
    reach = inc.astype(np.int32)
    vf = (inc @ inc.T).astype(bool).astype(np.int32)  # vertices sharing a face (incl. self)
    for _ in range(rings - 1):
        reach = (vf @ reach).astype(bool).astype(np.int32)
    reach = reach.tocsr()
    reach.sort_indices()
    counts = np.diff(reach.indptr)
    out = np.zeros((n_vertices, max(int(counts.max(initial=0)), 1)), np.int32)
    filled = counts > 0
    out[filled] = reach.indices[reach.indptr[:-1][filled]][:, None]  # pad with the first face
    rows = np.repeat(np.arange(n_vertices), counts)
    out[rows, np.arange(reach.nnz) - np.repeat(reach.indptr[:-1], counts)] = reach.indices
    return out


def closest_points_on_mesh(
    queries: Float[ArrayLike, "Q 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    chunk_size: int = 64,
    candidates: Int[ArrayLike, "Q K"] | None = None,
) -> tuple[Float[Array, "Q 3"], Int[Array, " Q"], Float[Array, "Q 3"], Float[Array, " Q"]]:
    """Closest point on a triangle mesh for every query (exact brute force over all faces, or
    over each query's own candidate faces).

    For each query the exact closest point on every triangle is computed (Ericson's branch-free
    Voronoi-region routine) and the nearest one is kept. Cost `O(Q · F)` time; memory `O(chunk_size
    · F)`: queries are processed `chunk_size` at a time with `jax.lax.map(...,
    batch_size=chunk_size)`. With `candidates` only the `K` faces listed for each query are
    searched (`O(Q · K)`, no chunking): exact when the closest face is among them, e.g. for a
    query near vertex `i` of a mesh of the same topology and
    [`bodyprior.mesh_ring_faces`][]`(faces, V, rings)[i]`. The search is not differentiated; the
    outputs are then recomputed for the chosen faces, so points, barycentrics and distances are
    differentiable in `queries` and `vertices` (for a fixed face assignment). Jittable (all
    shapes static).

    **Arguments:**

    - `queries`: `(Q, 3)` query points.
    - `vertices`: `(V, 3)` vertex positions of one mesh.
    - `faces`: `(F, 3)` integer vertex indices, `F >= 1`.
    - `chunk_size`: number of queries per block (static).
    - `candidates`: optional `(Q, K)` face indices in `[0, F)` to search per query (repeats allowed,
      as padding).

    **Returns:** `(points, face_idx, bary, distances)`: `(Q, 3)` closest points on the surface,
    `(Q,)` int32 index of the face they lie on (the lowest index on ties), `(Q, 3)` barycentric
    coordinates in that face, and `(Q,)` unsigned Euclidean distances (gradient 0 for a query
    exactly on the surface).
    """
    queries = _check_vertices(queries, "queries")
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, vertices.shape[0])
    if faces.shape[0] == 0:
        raise ValueError("`faces` must contain at least one face, got shape (0, 3).")
    chunk_size = check_positive_int(chunk_size, "chunk_size")
    dtype = jnp.result_type(queries, vertices)
    queries, vertices = queries.astype(dtype), vertices.astype(dtype)
    nq = queries.shape[0]
    if nq == 0:
        z = jnp.zeros((0, 3), dtype)
        return z, jnp.zeros((0,), jnp.int32), z, jnp.zeros((0,), dtype)
    tri = jax.lax.stop_gradient(vertices)[faces]
    if candidates is None:
        fidx = _face_search(jax.lax.stop_gradient(queries), tri, chunk_size)
    else:
        if not is_tracer(candidates):
            check_array(candidates, "candidates", (nq, None), integer=True)
            c = np.asarray(candidates)
            if c.shape[1] == 0 or c.min() < 0 or c.max() >= faces.shape[0]:
                raise ValueError(
                    f"`candidates` must hold at least one face index in [0, {faces.shape[0]}) "
                    f"per query, got shape {c.shape} and range [{c.min(initial=0)}, "
                    f"{c.max(initial=0)}]."
                )
        fidx = _candidate_search(jax.lax.stop_gradient(queries), tri, jnp.asarray(candidates))
    t = vertices[faces[fidx]]
    bary = _closest_bary(queries, t[:, 0], t[:, 1], t[:, 2])
    pts = jnp.einsum("qc,qcd->qd", bary, t)
    return pts, fidx, bary, _safe_norm(queries - pts)


def cross_section_areas(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    origin: Float[ArrayLike, " 3"],
    axis: Float[ArrayLike, " 3"],
    offsets: Float[ArrayLike, " T"],
    *,
    radius: float = 0.08,
) -> np.ndarray:
    """Areas of the mesh's cross-sections by planes normal to `axis` (host, NumPy).

    Plane `k` passes through `origin + offsets[k] · axis`; the slice is the closed polyline where
    the triangles cross it, kept where its segments lie within `radius` of the axis point (so that
    other limbs or the torso cut by the same plane do not count). The area is `|Σ ½ (p − c) × (q −
    c) · axis|` over the oriented segments `p → q` (exact for a closed slice around the axis
    point `c`).

    **Arguments:** `vertices (V, 3)` m; `faces (F, 3)` consistently oriented; `origin (3,)` m;
    `axis (3,)` (normalised here); `offsets (T,)` m along the axis; `radius` m.

    **Returns:** `(T,)` areas in m² (0 where the plane misses the mesh near the axis).
    """
    x = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    check_array(x, "vertices", (None, 3))
    check_array(f, "faces", (None, 3), integer=True)
    o = np.asarray(origin, np.float64).reshape(3)
    a = np.asarray(axis, np.float64).reshape(3)
    n = np.linalg.norm(a)
    if not n > 0:
        raise ValueError("`axis` must be a non-zero 3-vector.")
    a = a / n
    out = []
    for off in np.atleast_1d(np.asarray(offsets, np.float64)):
        c = o + off * a
        d = (x - c) @ a
        di = d[f]  # (F, 3)
        cross = (di > 0).any(1) & (di <= 0).any(1)
        fc, dc = f[cross], di[cross]
        entry = np.zeros((len(fc), 3))
        exit_ = np.zeros((len(fc), 3))
        for k in range(3):
            i, j = k, (k + 1) % 3
            pi, pj = x[fc[:, i]], x[fc[:, j]]
            denom = dc[:, i] - dc[:, j]
            lam = np.divide(dc[:, i], denom, out=np.zeros_like(denom), where=denom != 0)
            p = pi + lam[:, None] * (pj - pi)
            ex = (dc[:, i] > 0) & (dc[:, j] <= 0)
            en = (dc[:, i] <= 0) & (dc[:, j] > 0)
            exit_[ex] = p[ex]
            entry[en] = p[en]
        mid = 0.5 * (entry + exit_) - c
        near = np.linalg.norm(mid - np.outer(mid @ a, a), axis=1) < radius
        u, w = entry[near] - c, exit_[near] - c
        area = abs(0.5 * float(np.sum(np.cross(u, w) @ a)))
        out.append(area)
    return np.asarray(out)
