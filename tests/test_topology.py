"""Tests for `Topology`: construction, edge/hinge conventions, one-rings and validation errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from bodyprior import Topology


def grid_faces(n: int) -> np.ndarray:
    """CCW (normal +z) triangulation of an (n+1) x (n+1) vertex grid, vertex id = r * (n+1) + c."""
    faces = []
    for r in range(n):
        for c in range(n):
            a, b = r * (n + 1) + c, r * (n + 1) + c + 1
            d, e = a + n + 1, b + n + 1
            faces += [[a, b, e], [a, e, d]]
    return np.array(faces)


def check_invariants(topo: Topology, faces: np.ndarray):
    faces = np.asarray(faces)
    edges = np.asarray(topo.edges)
    ef = np.asarray(topo.edge_faces)
    eo = np.asarray(topo.edge_opposite)
    interior = np.asarray(topo.interior)
    assert edges.dtype == np.int32 and ef.dtype == np.int32
    assert (edges[:, 0] < edges[:, 1]).all()
    assert len({tuple(e) for e in edges}) == len(edges) == topo.n_edges
    directed = {}
    for f, face in enumerate(faces):
        for c in range(3):
            directed[(face[c], face[(c + 1) % 3])] = (f, face[(c + 2) % 3])
    for e, (i, j) in enumerate(edges):
        if interior[e]:
            assert directed[(i, j)] == (ef[e, 0], eo[e, 0])
            assert directed[(j, i)] == (ef[e, 1], eo[e, 1])
        else:
            assert ef[e, 1] == -1 and eo[e, 1] == -1
            assert directed.get((i, j), directed.get((j, i))) == (ef[e, 0], eo[e, 0])
    fe = np.asarray(topo.face_edges)
    for f, face in enumerate(faces):
        for c in range(3):
            assert tuple(edges[fe[f, c]]) == tuple(sorted((face[c], face[(c + 1) % 3])))
    ring, val = np.asarray(topo.one_ring), np.asarray(topo.valence)
    for v in range(topo.n_vertices):
        nbrs = sorted({int(j) for e in edges for j in e if v in e and j != v})
        assert ring[v, : val[v]].tolist() == nbrs
        assert (ring[v, val[v] :] == -1).all()


def test_closed_icosphere():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    topo = Topology.from_faces(mesh.faces, allow_boundary=False)
    assert (topo.n_vertices, topo.n_faces, topo.n_edges) == (42, 80, 120)
    assert not topo.has_boundary and bool(jnp.all(topo.interior))
    assert not bool(jnp.any(topo.boundary_edges))
    assert topo.max_valence == 6
    check_invariants(topo, mesh.faces)


def test_open_grid_and_unreferenced_vertex():
    faces = grid_faces(3)
    topo = Topology.from_faces(faces, n_vertices=17)  # vertex 16 unused
    assert topo.has_boundary
    assert int(jnp.sum(topo.boundary_edges)) == 12
    assert topo.n_edges == 33
    assert int(topo.valence[16]) == 0 and bool(jnp.all(topo.one_ring[16] == -1))
    check_invariants(topo, faces)
    with pytest.raises(ValueError, match="closed surface"):
        Topology.from_faces(faces, allow_boundary=False)


def test_boundary_edge_held_backwards_is_in_slot_0():
    # Edge (0, 2) of face [0, 1, 2] is traversed 2 -> 0 only.
    topo = Topology.from_faces(np.array([[0, 1, 2]]))
    e = [tuple(x) for x in np.asarray(topo.edges)].index((0, 2))
    assert np.asarray(topo.edge_faces)[e].tolist() == [0, -1]
    assert np.asarray(topo.edge_opposite)[e].tolist() == [1, -1]


def test_is_pytree_with_static_counts():
    topo = Topology.from_faces(grid_faces(2))

    @eqx.filter_jit
    def f(t):
        return jnp.sum(t.edges) + t.n_edges

    assert int(f(topo)) == int(np.asarray(topo.edges).sum()) + topo.n_edges
    leaves = jax.tree_util.tree_leaves(topo)
    assert all(isinstance(x, jax.Array) for x in leaves)


def test_error_non_manifold():
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(
        ValueError, match=r"`faces` is not 2-manifold: edge \(0, 1\) is shared by 3"
    ):
        Topology.from_faces(faces)


def test_error_inconsistent_orientation():
    faces = grid_faces(2).copy()
    faces[3] = faces[3, ::-1]
    with pytest.raises(ValueError, match="`faces` is not consistently oriented"):
        Topology.from_faces(faces)


def test_error_index_out_of_range():
    with pytest.raises(ValueError, match=r"`faces` indices must lie in \[0, 3\)"):
        Topology.from_faces(np.array([[0, 1, 3]]), n_vertices=3)
    with pytest.raises(ValueError, match=r"`faces` indices must lie"):
        Topology.from_faces(np.array([[0, 1, -1]]))


def test_error_degenerate_face():
    with pytest.raises(ValueError, match="`faces` has 1 degenerate face"):
        Topology.from_faces(np.array([[0, 1, 2], [2, 1, 1]]))


@pytest.mark.parametrize(
    "faces, match",
    [
        (np.zeros((4, 4), dtype=int), r"`faces` must have shape \(\*, 3\)"),
        (np.zeros((4, 3)), "`faces` must have an integer dtype"),
        (np.zeros((0, 3), dtype=int), "at least one face"),
    ],
)
def test_error_bad_faces_array(faces, match):
    with pytest.raises(ValueError, match=match):
        Topology.from_faces(faces)


@pytest.mark.bad_input
def test_error_bad_n_vertices():
    with pytest.raises(ValueError, match="`n_vertices` must be an int"):
        Topology.from_faces(np.array([[0, 1, 2]]), n_vertices=3.0)


def test_error_tracer_faces():
    with pytest.raises(ValueError, match="`faces` must be a concrete array"):
        jax.jit(lambda f: Topology.from_faces(f).edges)(jnp.array([[0, 1, 2]]))
