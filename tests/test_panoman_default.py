"""The shipped PanoMan kit (`bodyprior/assets/panoman_male.npz`): provenance, size, consistency.
Reconstruction with it runs in the PanoMan notebook (tests/test_notebooks.py) and in
`experiments/panoman_shipped.py` (`-m slow`: tests/test_panoman_shipped_experiment.py)."""

import os

import jax
import numpy as np
import pytest

import bodyprior as bp
import bodyprior.panoman as pm

jax.config.update("jax_enable_x64", True)


def test_shipped_kit_provenance_and_consistency():
    path = pm._default.kit_path()
    assert os.path.getsize(path) <= 32 * 2**20
    kit, info = pm.default_panoman(return_info=True)
    m = kit.model
    recipe = info["recipe"]
    assert tuple(recipe["k"]) == m.part_sizes
    assert {k: recipe[k] for k in pm.RECIPE} == {
        k: list(v) if isinstance(v, tuple) else v for k, v in pm.RECIPE.items()
    }
    assert info["data"]["counts"] == {"body": 2000, "face": 780, "hand": 2000}
    assert info["data"]["bvh"]["n_files"] >= 40 and len(info["data"]["test_clips"]) >= 1
    assert info["sources"] == bp.registration.template_sources()
    assert info["float16_cost_mm"]["max"] < 1.0  # float16 storage moves no vertex by 1 mm
    assert m.topology.n_vertices == kit.vertex_map.shape[0] == 6449
    assert kit.joint_names == bp.load_default_body("cmu_mb").joint_names
    # the LBS model and the regressor agree on the mean body's rest joints (both were fitted to
    # the same identities' exact joints)
    alpha = np.zeros(m.shape_basis.shape[0])
    v, j = kit.lbs(alpha, np.zeros((kit.n_joints, 3)), np.zeros(3))
    np.testing.assert_allclose(np.asarray(v), np.asarray(m.shape_mean), atol=1e-9)
    d = np.linalg.norm(np.asarray(kit.regressor(v)) - np.asarray(j), axis=1)
    assert d.mean() < 0.01, d


@pytest.mark.bad_input
def test_reconstruct_validates_before_fitting():
    kit = pm.default_panoman()
    with pytest.raises(ValueError, match="joints"):
        pm.reconstruct(kit, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="joint_weights"):
        pm.reconstruct(kit, np.zeros((kit.n_joints, 3)), joint_weights=-np.ones(kit.n_joints))
    with pytest.raises(ValueError, match="max_steps"):
        pm.reconstruct(kit, np.zeros((kit.n_joints, 3)), max_steps=0)
    with pytest.raises(ValueError, match="nothing to fit"):
        pm.reconstruct(kit, points=(np.zeros(0, int), np.zeros((0, 3))))
    with pytest.raises(ValueError, match="PanoManKit"):
        pm.reconstruct(kit.model, np.zeros((kit.n_joints, 3)))
    with pytest.raises(ValueError, match="recipe"):
        pm.build_default_panoman("/nonexistent/x.npz", n_bodies=3)


@pytest.mark.bad_input
def test_female_kit_location_and_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("BODYPRIOR_DATA", str(tmp_path / "data"))
    assert pm.kit_path("female") == str(tmp_path / "data" / "panoman_female.npz")
    assert pm.kit_path() == pm.kit_path("male") == pm._default.kit_path()
    with pytest.raises(ValueError, match="build_model --sex female"):
        pm.default_panoman(sex="female")
    with pytest.raises(ValueError, match="`sex`"):
        pm.default_panoman(sex="f")
    with pytest.raises(ValueError, match="`sex`"):
        pm.build_default_panoman(None, sex=2)
    # a kit written there is what default_panoman(sex="female") loads (here: the male one)
    os.makedirs(tmp_path / "data")
    with open(pm.kit_path("male"), "rb") as src, open(pm.kit_path("female"), "wb") as dst:
        dst.write(src.read())
    assert pm.default_panoman(sex="female").model.part_sizes == pm.RECIPE["k"]
