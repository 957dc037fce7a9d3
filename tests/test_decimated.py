"""Tests for the decimated (vertex-subset) default-body topology `default_body_decimated.npz`."""

import numpy as np
import pytest

import bodyprior as bp
from bodyprior.assets._decimate import decimate_subset, load_decimated, mirror_map


@pytest.fixture(scope="module")
def decimated():
    return load_decimated()


@pytest.fixture(scope="module")
def template():
    a = bp.load_asset()
    return np.asarray(a["template_vertices"], dtype=np.float64), np.asarray(a["faces"])


def _boundary_loops(faces: np.ndarray) -> int:
    directed = {
        (a, b) for f in faces.tolist() for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))
    }
    nxt = {a: b for a, b in directed if (b, a) not in directed}
    loops, seen = 0, set()
    for start in nxt:
        if start in seen:
            continue
        loops += 1
        v = start
        while v not in seen:
            seen.add(v)
            v = nxt[v]
    return loops


def test_vertex_map_and_faces(decimated, template):
    vm, faces = decimated
    V, _ = template
    assert vm.dtype == np.int32 and faces.dtype == np.int32
    assert vm.ndim == 1 and faces.ndim == 2 and faces.shape[1] == 3
    assert vm.min() >= 0 and vm.max() < len(V)
    assert (np.diff(vm) > 0).all()  # sorted and unique
    assert faces.min() >= 0 and faces.max() < len(vm)
    assert len(np.unique(faces)) == len(vm)  # every kept vertex is used
    assert abs(len(vm) - 6449) <= 1


def test_topology_manifold_oriented(decimated, template):
    vm, faces = decimated
    _, F = template
    bp.Topology.from_faces(
        faces, n_vertices=len(vm)
    )  # raises if non-manifold / inconsistently oriented
    assert _boundary_loops(faces) == _boundary_loops(F)

    # Same Euler characteristic as the full mesh (topology preserved).
    def euler(fc, nv):
        e = np.unique(
            np.sort(np.concatenate([fc[:, [0, 1]], fc[:, [1, 2]], fc[:, [2, 0]]]), axis=1), axis=0
        )
        return nv - len(e) + len(fc)

    assert euler(faces, len(vm)) == euler(F, len(np.unique(F)))


def test_mirror_symmetric(decimated, template):
    vm, _ = decimated
    V, _ = template
    m = mirror_map(V)
    assert np.array_equal(np.sort(m[vm]), vm)


def test_sampled_body_faces_nondegenerate(decimated):
    vm, faces = decimated
    body = np.asarray(bp.rest_shape(bp.load_default_body(), bp.phenotype_vector(gender=1.0))[0])[vm]
    q = body[faces]
    areas = 0.5 * np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), axis=1)
    assert np.isfinite(areas).all()
    assert areas.min() > 1e-9


def test_surface_distance(decimated, template):
    vm, faces = decimated
    V, _ = template
    idx = np.random.default_rng(0).choice(len(V), 1500, replace=False)
    _, _, _, d = bp.closest_points_on_mesh(V[idx], V[vm], faces, chunk_size=250)
    d = np.asarray(d)
    assert d.mean() < 3e-3
    assert d.max() < 10e-3


def test_decimate_subset_small_symmetric():
    # An icosphere is symmetric about x = 0: decimation keeps a symmetric vertex subset and
    # a closed manifold.
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    vm, f = decimate_subset(V, F, 80, symmetric=True)
    assert abs(len(vm) - 80) <= 1
    bp.Topology.from_faces(f, n_vertices=len(vm), allow_boundary=False)
    m = mirror_map(V)
    assert np.array_equal(np.sort(m[vm]), vm)
    assert np.array_equal(V[vm], V[np.sort(vm)])


def test_load_rejects_wrong_source(tmp_path, decimated):
    import json

    vm, faces = decimated
    meta = {
        "format": "bodyprior.default_body_decimated",
        "format_version": 1,
        "source_checksum": "0" * 64,
        "source_vertices": 13380,
    }
    p = tmp_path / "bad.npz"
    np.savez(p, vertex_map=vm, faces=faces, metadata=np.array(json.dumps(meta)))
    with pytest.raises(ValueError, match="rebuild"):
        load_decimated(str(p))
