"""Tests for the mesh geometry kernels: parity with trimesh / scipy, sign conventions, NaN-free
gradients at degenerate configurations, finite-difference gradients, Laplacian properties, sampling,
closest points, input validation and recompilation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import trimesh
from helpers import assert_jvp_matches_fd
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from bodyprior import Topology
from bodyprior import _geometry as G

ICO = trimesh.creation.icosphere(subdivisions=1)  # 42 vertices, 80 faces
ICO_TOPO = Topology.from_faces(ICO.faces)


def grid(n: int, jitter: float = 0.0, seed: int = 0):
    """Flat (z = 0) CCW grid on [0, 1]², interior vertices jittered in the plane."""
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    v = np.stack([c.ravel() / n, r.ravel() / n, np.zeros(c.size)], axis=1)
    inner = (r.ravel() > 0) & (r.ravel() < n) & (c.ravel() > 0) & (c.ravel() < n)
    v[inner, :2] += jitter / n * rng.uniform(-1, 1, size=(inner.sum(), 2))
    faces = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, i * (n + 1) + j + 1
            d, e = a + n + 1, b + n + 1
            faces += [[a, b, e], [a, e, d]]
    return v, np.array(faces), inner


def deformed_ico(seed: int, scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ICO.vertices * rng.uniform(0.5, 2.0) + scale * rng.normal(size=ICO.vertices.shape)


def edge_lookup(topo):
    lut = {tuple(e): n for n, e in enumerate(np.asarray(topo.edges))}
    return lambda pairs: np.array([lut[tuple(p)] for p in np.sort(pairs, axis=1)])


def all_finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


# ------------------------------------------------------------------------------------------------
# Parity with trimesh
# ------------------------------------------------------------------------------------------------


@settings(deadline=None, max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.0, 0.15))
def test_face_quantities_match_trimesh(seed, scale):
    v = deformed_ico(seed, scale)
    mesh = trimesh.Trimesh(v, ICO.faces, process=False)
    np.testing.assert_allclose(G.face_normals(v, ICO.faces), mesh.face_normals, atol=1e-10)
    np.testing.assert_allclose(G.face_areas(v, ICO.faces), mesh.area_faces, rtol=1e-10)
    np.testing.assert_allclose(jnp.sum(G.vertex_areas(v, ICO.faces)), mesh.area, rtol=1e-10)
    # Area-weighted vertex normals, NumPy reference.
    ref = np.zeros_like(v)
    for c in range(3):
        np.add.at(ref, ICO.faces[:, c], mesh.face_normals * mesh.area_faces[:, None])
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(G.vertex_normals(v, ICO.faces), ref, atol=1e-10)
    lookup = edge_lookup(ICO_TOPO)
    e = lookup(mesh.edges_unique)
    np.testing.assert_allclose(G.edge_lengths(v, ICO_TOPO)[e], mesh.edges_unique_length, rtol=1e-12)


@settings(deadline=None, max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.0, 0.3))
def test_dihedral_magnitude_matches_trimesh(seed, scale):
    v = deformed_ico(seed, scale)
    mesh = trimesh.Trimesh(v, ICO.faces, process=False)
    theta = np.asarray(G.dihedral_angles(v, ICO_TOPO))
    e = edge_lookup(ICO_TOPO)(mesh.face_adjacency_edges)
    np.testing.assert_allclose(np.abs(theta[e]), mesh.face_adjacency_angles, atol=1e-9)
    assert np.all(theta > -np.pi) and np.all(theta <= np.pi)
    # Convexity sign: trimesh's face_adjacency_convex agrees with the sign.
    convex = mesh.face_adjacency_convex
    tilted = np.abs(theta[e]) > 1e-6
    np.testing.assert_array_equal((theta[e] > 0)[tilted], convex[tilted])


def test_dihedral_sign_convex_meshes():
    theta = G.dihedral_angles(ICO.vertices, ICO_TOPO)
    assert bool(jnp.all(theta > 0))
    box = trimesh.creation.box()
    bt = Topology.from_faces(box.faces, allow_boundary=False)
    theta = np.asarray(G.dihedral_angles(box.vertices, bt))
    lengths = np.asarray(G.edge_lengths(box.vertices, bt))
    cube_edge = np.isclose(lengths, 1.0)
    np.testing.assert_allclose(theta[cube_edge], np.pi / 2, atol=1e-12)  # 12 convex right angles
    np.testing.assert_allclose(theta[~cube_edge], 0.0, atol=1e-12)  # flat face diagonals
    assert cube_edge.sum() == 12


def test_dihedral_sign_concave_and_roof():
    # Roof hinge: edge (0, 1) along x, faces tilted down on both sides of the ridge -> convex.
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, -1, -0.3], [0.5, 1, -0.3]])
    faces = np.array([[0, 1, 3], [1, 0, 2]])  # outward normals point up (+z side)
    topo = Topology.from_faces(faces)
    e = edge_lookup(topo)(np.array([[0, 1]]))[0]
    theta = G.dihedral_angles(v, topo)
    expected = 2 * np.arctan2(0.3, 1.0)
    np.testing.assert_allclose(theta[e], expected, atol=1e-12)
    # Valley: same hinge with the ridge pushed down -> concave, negative.
    v[:, 2] *= -1
    np.testing.assert_allclose(G.dihedral_angles(v, topo)[e], -expected, atol=1e-12)
    # Boundary edges are 0.
    assert float(jnp.sum(jnp.abs(jnp.where(topo.interior, 0.0, theta)))) == 0.0


def test_dihedral_invariant_to_labelling():
    rng = np.random.default_rng(3)
    v = deformed_ico(3, 0.2)
    theta = np.asarray(G.dihedral_angles(v, ICO_TOPO))
    # Rotate each face's corners cyclically and permute vertex labels.
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    faces2 = np.roll(inv[ICO.faces], rng.integers(0, 3), axis=1)[rng.permutation(len(ICO.faces))]
    topo2 = Topology.from_faces(faces2)
    theta2 = np.asarray(G.dihedral_angles(v[perm], topo2))
    e2 = edge_lookup(topo2)(inv[np.asarray(ICO_TOPO.edges)])
    np.testing.assert_allclose(theta2[e2], theta, atol=1e-12)
    # Rigid motion invariance.
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    np.testing.assert_allclose(G.dihedral_angles(v @ q.T + 1.0, ICO_TOPO), theta, atol=1e-10)


# ------------------------------------------------------------------------------------------------
# Gradients
# ------------------------------------------------------------------------------------------------


def _scalar_losses(faces, topo):
    # (closest_points_on_mesh gradients at degenerate triangles are checked in the closest-point
    # tests)
    return {
        "dihedral": lambda x: jnp.sum(G.dihedral_angles(x, topo) ** 2 + G.dihedral_angles(x, topo)),
        "normals": lambda x: jnp.sum(G.face_normals(x, faces) * jnp.array([1.0, 2.0, 3.0])),
        "vnormals": lambda x: jnp.sum(G.vertex_normals(x, faces) * jnp.array([1.0, 2.0, 3.0])),
        "areas": lambda x: jnp.sum(G.face_areas(x, faces)) + jnp.sum(G.vertex_areas(x, faces)),
        "lengths": lambda x: jnp.sum(G.edge_lengths(x, topo)),
        "cot": lambda x: jnp.sum(G.cotangent_weights(x, topo)),
    }


def _values_and_grads(faces, topo):
    """One jitted function returning every loss and its gradient (a single compilation per mesh)."""
    losses = _scalar_losses(faces, topo)
    both = lambda x: {k: jax.value_and_grad(f)(x) for k, f in losses.items()}
    return jax.jit(both)


def test_gradients_finite_at_flat_configuration():
    v, faces, _ = grid(3)
    topo = Topology.from_faces(faces)
    for name, out in _values_and_grads(faces, topo)(jnp.asarray(v)).items():
        assert all_finite(out), name
    # Flat: all dihedral angles exactly 0.
    assert float(jnp.max(jnp.abs(G.dihedral_angles(v, topo)))) == 0.0


def test_gradients_finite_with_zero_area_faces():
    v = np.array(ICO.vertices)
    topo = ICO_TOPO
    fn = _values_and_grads(ICO.faces, topo)
    e0, e1 = np.asarray(topo.edges[0])
    v[e1] = v[e0]  # collapse an edge: its two faces have zero area
    areas = G.face_areas(v, ICO.faces)
    assert int(jnp.sum(areas == 0)) == 2
    for name, out in fn(jnp.asarray(v)).items():
        assert all_finite(out), name
    # A fully collapsed triangle (three coincident vertices) too.
    k = int(topo.edge_opposite[0, 0])
    v[k] = v[e0]
    for name, out in fn(jnp.asarray(v)).items():
        assert all_finite(out), name
    assert all_finite(jax.jacrev(lambda x: G.face_normals(x, ICO.faces))(jnp.asarray(v)))


def test_dihedral_and_cot_gradients_match_finite_differences(getkey):
    x = jnp.asarray(deformed_ico(7, 0.1))
    assert_jvp_matches_fd(lambda y: G.dihedral_angles(y, ICO_TOPO), x, getkey)
    assert_jvp_matches_fd(lambda y: G.cotangent_weights(y, ICO_TOPO), x, getkey)
    v, faces, _ = grid(3, jitter=0.5)
    v[:, 2] = 0.05 * np.random.default_rng(1).normal(size=len(v))
    topo = Topology.from_faces(faces)  # open mesh: boundary edges included
    assert_jvp_matches_fd(lambda y: G.cotangent_weights(y, topo), jnp.asarray(v), getkey)
    assert_jvp_matches_fd(lambda y: G.dihedral_angles(y, topo), jnp.asarray(v), getkey)


# ------------------------------------------------------------------------------------------------
# Laplacian
# ------------------------------------------------------------------------------------------------


def test_cotangent_weights_reference():
    v = deformed_ico(11, 0.1)
    w = np.asarray(G.cotangent_weights(v, ICO_TOPO))
    ref = np.zeros(ICO_TOPO.n_edges)
    for e, ((i, j), ks) in enumerate(
        zip(np.asarray(ICO_TOPO.edges), np.asarray(ICO_TOPO.edge_opposite))
    ):
        for k in ks:
            a, b = v[i] - v[k], v[j] - v[k]
            ang = np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
            ref[e] += 0.5 / np.tan(ang)
    np.testing.assert_allclose(w, ref, rtol=1e-9)


def test_cot_laplacian_of_linear_function_vanishes_on_flat_patch():
    v, faces, inner = grid(5, jitter=0.6, seed=2)
    topo = Topology.from_faces(faces)
    w = G.cotangent_weights(v, topo)
    f = v @ np.array([[0.3, -1.0], [2.0, 0.5], [0.0, 0.0]]) + np.array([1.0, -2.0])
    lf = np.asarray(G.laplacian_apply(f, topo, w))
    np.testing.assert_allclose(lf[inner], 0.0, atol=1e-12)
    assert np.abs(lf[~inner]).max() > 1e-3  # boundary vertices do not vanish
    # ... and also for the vertex positions themselves (the mean-curvature normal of a plane).
    np.testing.assert_allclose(np.asarray(G.laplacian_apply(v, topo, w))[inner], 0.0, atol=1e-12)


def test_laplacian_forms_agree():
    v = deformed_ico(5, 0.1)
    for w in (G.cotangent_weights(v, ICO_TOPO), G.uniform_weights(ICO_TOPO)):
        L = G.laplacian_matrix(ICO_TOPO, w)
        np.testing.assert_allclose(L, L.T)
        np.testing.assert_allclose(jnp.sum(L, axis=1), 0.0, atol=1e-12)
        np.testing.assert_allclose(G.laplacian_apply(v, ICO_TOPO, w), L @ v, atol=1e-12)
        x1 = v[:, 0]
        np.testing.assert_allclose(G.laplacian_apply(x1, ICO_TOPO, w), L @ x1, atol=1e-12)
        S = G.laplacian_sparse(ICO_TOPO, w)
        np.testing.assert_allclose(S.toarray(), L, atol=1e-12)
    # Uniform Laplacian: (L x)_i = Σ_{j ∈ N(i)} x_j - valence_i x_i.
    x = np.arange(ICO_TOPO.n_vertices, dtype=float)
    ring, val = np.asarray(ICO_TOPO.one_ring), np.asarray(ICO_TOPO.valence)
    ref = np.array([x[ring[i, : val[i]]].sum() - val[i] * x[i] for i in range(len(x))])
    np.testing.assert_allclose(G.laplacian_apply(x, ICO_TOPO, G.uniform_weights(ICO_TOPO)), ref)


# ------------------------------------------------------------------------------------------------
# Sampling, nearest neighbours, closest points
# ------------------------------------------------------------------------------------------------


def test_sample_surface(getkey):
    # Two triangles with areas 1 : 4.5.
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [3, 0, 1], [0, 3, 1], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    pts, fidx, bary = G.sample_surface(v, faces, 4000, key=getkey())
    assert pts.shape == (4000, 3) and fidx.shape == (4000,) and bary.shape == (4000, 3)
    assert fidx.dtype == jnp.int32
    assert bool(jnp.all(bary >= 0)) and np.allclose(jnp.sum(bary, axis=1), 1.0)
    np.testing.assert_allclose(G.barycentric_points(v, faces, fidx, bary), pts, atol=1e-12)
    frac = float(jnp.mean(fidx == 1))
    assert abs(frac - 4.5 / 5.5) < 0.03
    # Uniform within a triangle: mean of the barycentrics is the centroid (1/3 each).
    np.testing.assert_allclose(jnp.mean(bary, axis=0), 1 / 3, atol=0.02)
    # Differentiable in the vertices.
    g = jax.grad(lambda x: jnp.sum(G.sample_surface(x, faces, 10, key=jr.PRNGKey(1))[0]))(
        jnp.asarray(v)
    )
    assert all_finite(g) and float(jnp.max(jnp.abs(g))) > 0


def test_nearest_neighbors_match_kdtree():
    rng = np.random.default_rng(0)
    points, queries = rng.normal(size=(300, 3)), rng.normal(size=(137, 3))
    idx, sq = G.nearest_neighbors(queries, points, chunk_size=32)  # 137 not a multiple of 32
    dist, ref = cKDTree(points).query(queries)
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_allclose(jnp.sqrt(sq), dist, rtol=1e-12)
    g = jax.grad(lambda p: jnp.sum(G.nearest_neighbors(queries, p, chunk_size=32)[1]))(points)
    assert all_finite(g)


def _closest_reference(q, v, faces):
    tris = v[faces]
    nq, nf = len(q), len(tris)
    cp = trimesh.triangles.closest_point(np.tile(tris, (nq, 1, 1)), np.repeat(q, nf, axis=0))
    d = np.linalg.norm(cp.reshape(nq, nf, 3) - q[:, None], axis=-1)
    best = d.argmin(axis=1)
    return cp.reshape(nq, nf, 3)[np.arange(nq), best], d.min(axis=1)


@settings(deadline=None, max_examples=10)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.0, 0.3))
def test_closest_points_match_trimesh(seed, scale):
    v = deformed_ico(seed, scale)
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(60, 3)) * rng.uniform(0.5, 3.0)
    pts, fidx, bary, dist = G.closest_points_on_mesh(q, v, ICO.faces, chunk_size=16)
    ref_pts, ref_dist = _closest_reference(q, v, ICO.faces)
    np.testing.assert_allclose(dist, ref_dist, atol=1e-9)
    np.testing.assert_allclose(pts, ref_pts, atol=1e-6)
    assert bool(jnp.all(bary >= -1e-12)) and np.allclose(jnp.sum(bary, axis=1), 1.0)
    np.testing.assert_allclose(G.barycentric_points(v, ICO.faces, fidx, bary), pts, atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.norm(pts - q, axis=1), dist, atol=1e-12)


def test_closest_points_of_surface_samples(getkey):
    v = deformed_ico(1, 0.1)
    pts, fidx, bary = G.sample_surface(v, ICO.faces, 50, key=getkey())
    cp, cf, cb, d = G.closest_points_on_mesh(pts, v, ICO.faces)
    np.testing.assert_allclose(d, 0.0, atol=1e-12)
    np.testing.assert_allclose(cp, pts, atol=1e-12)
    g = jax.grad(lambda x: jnp.sum(G.closest_points_on_mesh(pts, x, ICO.faces)[3]))(jnp.asarray(v))
    assert all_finite(g)


def test_closest_points_degenerate_triangle():
    # A zero-area sliver (collinear) next to a real triangle: the result must still be exact.
    v = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    q = np.array([[1.5, 0.5, 0.2], [0.2, 0.2, -1.0], [3.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    pts, _, _, d = G.closest_points_on_mesh(q, v, faces)
    ref_pts, ref_d = _closest_reference(q, v, faces)
    np.testing.assert_allclose(d, ref_d, atol=1e-12)
    np.testing.assert_allclose(pts, ref_pts, atol=1e-12)
    g = jax.grad(lambda x: jnp.sum(G.closest_points_on_mesh(q, x, faces)[3]))(jnp.asarray(v))
    assert all_finite(g)


# ------------------------------------------------------------------------------------------------
# jit / vmap / recompilation
# ------------------------------------------------------------------------------------------------


def test_dihedral_no_recompile_and_vmap():
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(x, topo):
        return G.dihedral_angles(x, topo)

    jf = eqx.filter_jit(f)
    v1, v2 = deformed_ico(1, 0.1), deformed_ico(2, 0.1)
    a1 = jf(jnp.asarray(v1), ICO_TOPO)
    a2 = jf(jnp.asarray(v2), ICO_TOPO)
    np.testing.assert_allclose(a1, G.dihedral_angles(v1, ICO_TOPO), atol=1e-12)
    np.testing.assert_allclose(a2, G.dihedral_angles(v2, ICO_TOPO), atol=1e-12)
    batch = jnp.stack([v1, v2])
    out = jax.vmap(G.dihedral_angles, in_axes=(0, None))(batch, ICO_TOPO)
    np.testing.assert_allclose(out, jnp.stack([a1, a2]), atol=1e-12)


def test_closest_points_no_recompile():
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(q, x):
        return G.closest_points_on_mesh(q, x, ICO.faces, chunk_size=8)[3]

    jf = jax.jit(f)
    rng = np.random.default_rng(0)
    for _ in range(2):
        q, v = rng.normal(size=(20, 3)), deformed_ico(int(rng.integers(100)), 0.1)
        np.testing.assert_allclose(jf(q, v), _closest_reference(q, v, ICO.faces)[1], atol=1e-9)


def test_float32_inputs_stay_float32():
    v = jnp.asarray(deformed_ico(0, 0.1), dtype=jnp.float32)
    assert G.dihedral_angles(v, ICO_TOPO).dtype == jnp.float32
    assert G.cotangent_weights(v, ICO_TOPO).dtype == jnp.float32
    assert G.face_normals(v, ICO.faces).dtype == jnp.float32
    assert G.closest_points_on_mesh(v[:3], v, ICO.faces)[0].dtype == jnp.float32


# ------------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------------


@pytest.mark.bad_input
def test_validation_errors():
    v = np.array(ICO.vertices)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="`vertices` contains NaN"):
        G.face_normals(bad, ICO.faces)
    with pytest.raises(ValueError, match="`vertices` contains NaN"):
        G.dihedral_angles(bad, ICO_TOPO)
    with pytest.raises(ValueError, match=r"`vertices` must have shape \(42, 3\)"):
        G.dihedral_angles(v[:-1], ICO_TOPO)
    with pytest.raises(ValueError, match=r"`vertices` must have shape \(\*, 3\)"):
        G.face_areas(v[:, :2], ICO.faces)
    with pytest.raises(ValueError, match=r"`faces` must lie in \[0, 41\]"):
        G.face_areas(v, ICO.faces + 1)
    with pytest.raises(ValueError, match="`faces` must have an integer dtype"):
        G.vertex_normals(v, ICO.faces.astype(float))
    with pytest.raises(ValueError, match="`topology` must be a bodyprior.Topology"):
        G.edge_lengths(v, ICO.faces)
    with pytest.raises(ValueError, match=r"`weights` must have shape \(120,\)"):
        G.laplacian_apply(v, ICO_TOPO, jnp.ones(3))
    with pytest.raises(ValueError, match="`x` must have shape"):
        G.laplacian_apply(v[:5], ICO_TOPO, G.uniform_weights(ICO_TOPO))
    with pytest.raises(ValueError, match="`queries` contains NaN"):
        G.nearest_neighbors(bad, v)
    with pytest.raises(ValueError, match="`chunk_size` must be a positive"):
        G.closest_points_on_mesh(v, v, ICO.faces, chunk_size=0)
    with pytest.raises(ValueError, match="`face_idx` must lie"):
        G.barycentric_points(v, ICO.faces, np.array([80]), np.ones((1, 3)) / 3)
    with pytest.raises(ValueError, match=r"`bary` must have shape \(N, 3\) with N=2"):
        G.barycentric_points(v, ICO.faces, np.array([0, 1]), np.ones((1, 3)) / 3)
    with pytest.raises(ValueError, match="`n` must be a non-negative"):
        G.sample_surface(v, ICO.faces, 2.5, key=jr.PRNGKey(0))
    # Tracers only get shape checks (no NaN check), and still work under jit.
    out = jax.jit(lambda x: G.face_areas(x, ICO.faces))(jnp.asarray(v))
    assert out.shape == (80,)


def test_mesh_ring_faces_and_candidate_search_match_brute_force():
    v = deformed_ico(3, 0.02)  # a sphere, slightly rough (a rough one can fold: then a distant
    f = np.asarray(ICO.faces)  # face can be the closest)
    nv = v.shape[0]
    r1 = G.mesh_ring_faces(f, nv, 1)
    for i in range(nv):  # ring 1 is exactly the incident faces (padding repeats a member)
        assert set(r1[i]) == set(np.flatnonzero((f == i).any(1)))
    r2 = G.mesh_ring_faces(f, nv, 2)
    assert r2.shape[1] > r1.shape[1] and all(set(r1[i]) <= set(r2[i]) for i in range(nv))
    # queries near each vertex (a slide of a fraction of an edge): ring-2 candidates give the
    # exact brute-force closest points; a wrong candidate set (ring 1 of another vertex) does not
    rng = np.random.default_rng(0)
    q = v + 0.05 * rng.standard_normal(v.shape)
    ref_pts, _, _, ref_d = G.closest_points_on_mesh(q, v, f)
    pts, fidx, bary, d = G.closest_points_on_mesh(q, v, f, candidates=r2)
    np.testing.assert_allclose(d, ref_d, atol=1e-12)
    np.testing.assert_allclose(pts, ref_pts, atol=1e-12)
    assert all(fidx[i] in r2[i] for i in range(nv))
    np.testing.assert_allclose(G.barycentric_points(v, f, fidx, bary), pts, atol=1e-12)
    wrong = np.roll(r1, 7, axis=0)
    assert float(jnp.max(G.closest_points_on_mesh(q, v, f, candidates=wrong)[3] - ref_d)) > 0.05
    # jit/vmap over meshes with the candidates as a traced argument
    jv = jax.jit(jax.vmap(lambda x, y: G.closest_points_on_mesh(x, y, f, candidates=r2)[3]))
    np.testing.assert_allclose(jv(q[None], v[None])[0], ref_d, atol=1e-12)


@pytest.mark.bad_input
def test_candidate_search_bad_input():
    v, f = deformed_ico(0, 0.0), np.asarray(ICO.faces)
    with pytest.raises(ValueError, match="candidates"):
        G.closest_points_on_mesh(v[:3], v, f, candidates=np.zeros((4, 2), np.int32))
    with pytest.raises(ValueError, match="candidates"):
        G.closest_points_on_mesh(v[:3], v, f, candidates=np.full((3, 2), len(f), np.int32))
    with pytest.raises(ValueError, match="rings"):
        G.mesh_ring_faces(f, v.shape[0], 0)
    with pytest.raises(ValueError, match="n_vertices"):
        G.mesh_ring_faces(f, 3, 1)
