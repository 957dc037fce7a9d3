"""Registration template: vertex subset, landmarks, masks, refitted joint regressor."""

import jax
import jax.random as jr
import numpy as np
import pytest

import bodyprior as bp


@pytest.fixture(scope="module")
def tmpl():
    return bp.registration.registration_template()


def test_template_is_vertex_subset(tmpl):
    body = bp.load_default_body("cmu_mb")
    vmap, faces = bp.load_decimated()
    assert tmpl.vertices.shape == (6449, 3)
    np.testing.assert_array_equal(np.asarray(tmpl.faces), faces)
    np.testing.assert_allclose(np.asarray(tmpl.vertices), np.asarray(body.template)[vmap])
    np.testing.assert_allclose(np.asarray(tmpl.restrict(body.template)), np.asarray(tmpl.vertices))
    assert len(tmpl.landmark_names) == len(body.landmark_names) == tmpl.landmark_index.shape[0]
    assert float(tmpl.landmark_error.max()) < 0.015
    assert int((np.asarray(tmpl.landmark_error) == 0).sum()) > len(tmpl.landmark_names) // 2


def test_masks_and_skin(tmpl):
    v = np.asarray(tmpl.vertices)
    hand, head = np.asarray(tmpl.hand_mask), np.asarray(tmpl.head_mask)
    assert 200 < hand.sum() < 2000 and 200 < head.sum() < 2500
    assert not (hand & head).any()
    # hands are the lateral extremes of the A-pose body, the head is on top
    assert np.abs(v[hand, 0]).min() > 0.5 * np.abs(v[:, 0]).max()
    assert v[head, 2].min() > np.percentile(v[:, 2], 75)
    np.testing.assert_allclose(np.asarray(tmpl.rig.skin_weights).sum(1), 1.0, atol=1e-6)


def test_template_carries_rig_and_topology(tmpl):
    body = bp.load_default_body("cmu_mb")
    assert isinstance(tmpl.rig, bp.Rig) and isinstance(tmpl.topology, bp.Topology)
    assert tmpl.rig.n_vertices == tmpl.topology.n_vertices == tmpl.n_vertices
    assert tmpl.parents == body.parents and tmpl.joint_names == body.joint_names
    assert tmpl.faces is tmpl.topology.faces
    ref = bp.Topology.from_faces(np.asarray(tmpl.faces), tmpl.n_vertices)
    assert jax.tree_util.tree_structure(ref) == jax.tree_util.tree_structure(tmpl.topology)
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(tmpl.topology)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the skin weights are the full body's, restricted to the kept vertices (then renormalised)
    vm = np.asarray(tmpl.vertex_map)
    np.testing.assert_array_equal(tmpl.rig.skin_indices, np.asarray(body.rig.skin_indices)[vm])
    # the deprecated spelling still reaches learn()
    with pytest.warns(DeprecationWarning, match="rig=template.rig"):
        assert tmpl.rig_kwargs() == {"rig": tmpl.rig}
    with pytest.warns(DeprecationWarning, match="rig=body.rig"):
        assert bp.sscape_rig(body) == {"rig": body.rig}


def test_regressor_recovers_exact_joints(tmpl):
    body = bp.load_default_body("cmu_mb")
    phen, _, _ = bp.sample_phenotypes(16, key=jr.PRNGKey(7))
    verts, joints = jax.vmap(lambda p: bp.rest_shape(body, p))(phen)
    w = np.asarray(tmpl.rig.regressor_weights)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=2e-5)
    pred = np.asarray(jax.vmap(tmpl.rig.regress_joints)(tmpl.restrict(verts)))
    err = np.linalg.norm(pred - np.asarray(joints), axis=-1)
    assert err.max() < 0.01 and tmpl.regressor_max_error < 0.01
    # the rig builds an S-SCAPE model directly
    space = bp.sscape.learn(tmpl.restrict(verts), tmpl.faces, n_components=4, rig=tmpl.rig)
    assert space.mean.shape == (6449, 3) and space.rig is tmpl.rig


def test_bad_arguments():
    with pytest.raises(ValueError, match="`rig`"):
        bp.registration.registration_template("smpl")
    with pytest.raises(ValueError, match="`n_fit`"):
        bp.registration.registration_template(n_fit=3)


def _assert_same_template(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb  # static fields: regressor_max_error, rig parents and names, topology sizes
    for x, y in zip(la, lb):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_precomputed_file_is_the_default(tmpl):
    from bodyprior.registration import _template as T

    # the default call reads the committed file (built from the current assets), not a refit
    assert tmpl is T._load_precomputed("cmu_mb", True, True)
    arrays, meta = T._read_precomputed(T.template_path())
    assert meta["source_checksum"] == str(np.load(bp.assets.asset_path())["checksum"])
    assert (meta["n_fit"], meta["regressor_size"]) == (300, 128)
    assert set(meta["variants"]) == {
        f"{r}.{d}.{x}" for r in ("cmu_mb", "game_engine") for d in ("decimated", "full")
        for x in ("x64", "x32")
    }
    full = bp.registration.registration_template("game_engine", decimated=False)
    assert full.n_vertices == 13380 and full.joint_names == bp.load_default_body(
        "game_engine").joint_names


def test_precomputed_file_checksum_is_verified(tmp_path):
    from bodyprior.registration import _template as T

    src = dict(np.load(T.template_path()))
    src["cmu_mb.decimated.x64.skin_weight"] = src["cmu_mb.decimated.x64.skin_weight"] * 1.0001
    bad = tmp_path / "bad.npz"
    np.savez(bad, **src)
    with pytest.raises(ValueError, match="corrupted"):
        T._read_precomputed(str(bad))


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["cmu_mb", "game_engine"])
@pytest.mark.parametrize("decimated", [True, False])
@pytest.mark.parametrize("x64", [True, False])
def test_precomputed_equals_rebuild(rig, decimated, x64):
    """The committed file holds exactly what the refit gives, in either JAX precision (the fit
    samples its bodies in the current one)."""
    with jax.enable_x64(x64):
        loaded = bp.registration.registration_template(rig, decimated=decimated)
        rebuilt = bp.registration.registration_template(rig, decimated=decimated, precomputed=False)
    assert loaded is not rebuilt
    _assert_same_template(loaded, rebuilt)
