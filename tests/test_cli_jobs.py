"""The CLI's jobs (`bodyprior register / learn / pose / render`) against the library calls they
stand for, on files written by the library's own writers."""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import registration, sscape
from bodyprior.cli import main


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    """One simulated laser scan of a sampled body, written as PLY + CAESAR .lnd (millimetres)."""
    d = tmp_path_factory.mktemp("scan")
    body = bp.load_default_body("cmu_mb", local_changes=True)
    pop = bp.sample_population(1, body=body, key=jax.random.PRNGKey(11), progress=False)
    scans, _ = registration.simulate_scans(
        np.asarray(pop.vertices), body.faces, body.landmark_index, body.landmark_names,
        registration.ScannerConfig(n_points=4000), key=jax.random.PRNGKey(12), progress=False,
    )  # fmt: skip
    scan = jax.tree_util.tree_map(lambda a: a[0], scans)
    registration.write_scan(d / "subject.ply", scan, landmarks_path=d / "subject.lnd")
    gt = np.asarray(registration.registration_template().restrict(np.asarray(pop.vertices[0])))
    return d, gt


def test_register_reproduces_the_library(scan_files, tmp_path, capsys):
    d, gt = scan_files
    out = tmp_path / "out"
    argv = ["--no-cache", "register", str(d / "subject.ply"), "--out", str(out), "--components",
            "5", "--max-passes", "2", "--points", "0", "--no-progress", "--json"]  # fmt: skip
    assert main(argv) == 0  # SCAN.lnd found next to the scan
    report = json.loads(capsys.readouterr().out)
    rep = report["scans"][0]
    assert rep["units"] == "m" and rep["landmark_units"] == "mm" and rep["successful"]
    assert rep["points_used"] == rep["points_in_file"]
    assert json.loads((out / "subject.json").read_text()) == rep
    assert os.path.getsize(out / "subject.error.png") > 1000

    # The same registration by the library.
    tmpl = registration.registration_template()
    scan = registration.read_scan(d / "subject.ply", landmarks_path=d / "subject.lnd")
    assert rep["landmarks_used"] == int(np.asarray(scan.landmark_mask).sum()) > 60
    reg = sscape.register_sscape_nrd(
        sscape.default_space(5), registration.pad_scans([scan]), tmpl,
        fit_config=sscape.FitConfig(max_passes=2),
        nrd_config=registration.NRDConfig.preset("anchored"), progress=False,
    )  # fmt: skip
    v, f, _ = bp.read_mesh(out / "subject.registered.ply")
    np.testing.assert_array_equal(f, np.asarray(tmpl.faces))
    np.testing.assert_allclose(v, reg.vertices[0], atol=1e-6)
    fe = registration.fitting_error(jnp.asarray(reg.vertices[0]), scan, faces=tmpl.faces)
    err, valid = np.asarray(fe.error_mm), np.asarray(fe.valid)
    assert rep["fitting_error"]["mean_mm"] == pytest.approx(err[valid].mean(), abs=2e-3)
    assert rep["fitting_error"]["coverage"] == pytest.approx(valid.mean(), abs=1e-4)
    np.testing.assert_allclose(rep["shape_coeffs"], reg.coeffs[0], atol=1e-5)
    # The registration is a body: the true-correspondence error is that of a 5-component fit.
    gt_mm = np.linalg.norm(v - gt, axis=1).mean() * 1e3
    assert gt_mm < 15.0, gt_mm
    assert rep["fitting_error"]["mean_mm"] < rep["sscape_fitting_error"]["mean_mm"]


def test_register_bad_input(scan_files, tmp_path, capsys):
    d, _ = scan_files
    lonely = tmp_path / "lonely.ply"
    lonely.write_bytes((d / "subject.ply").read_bytes())
    assert main(["--no-cache", "register", str(lonely), "--out", str(tmp_path / "o")]) == 2
    assert "has no landmarks" in capsys.readouterr().err
    assert main(["--no-cache", "register", str(tmp_path / "nope.ply"), "--out", "x"]) == 2
    assert "no such file" in capsys.readouterr().err
    bad = tmp_path / "scan.txt"
    bad.write_text("1 2 3\n")
    assert main(["--no-cache", "register", str(bad), "--out", "x"]) == 2
    assert "must end in" in capsys.readouterr().err
    args = ["--no-cache", "register", str(d / "subject.ply"), "--out", "x", "--components", "0"]
    assert main(args) == 2
    assert "--components" in capsys.readouterr().err


def test_learn_writes_a_space_and_its_measures(tmp_path, capsys):
    tmpl = registration.registration_template()
    pop = bp.sample_population(8, key=jax.random.PRNGKey(3), progress=False)
    meshes = np.asarray(tmpl.restrict(np.asarray(pop.vertices)))
    for i, m in enumerate(meshes):
        bp.write_ply(tmp_path / f"m{i}.ply", m, np.asarray(tmpl.faces))
    model_path = tmp_path / "space.sscape"
    argv = ["--no-cache", "learn", str(tmp_path), "--out", str(model_path), "--components", "4",
            "--samples", "20", "--modes", "2", "--json"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    model, info = sscape.load_model(model_path, return_info=True)
    assert model.n_components == 4 and model.rig.joint_names == tmpl.rig.joint_names
    assert info["built_by"] == "bodyprior learn" and len(info["meshes"]) == 8
    ref = sscape.learn(jnp.asarray(meshes), tmpl.faces, n_components=4, rig=tmpl.rig)
    np.testing.assert_allclose(np.asarray(model.stddev), np.asarray(ref.stddev), rtol=1e-5)
    assert report["rig"].startswith("registration template")
    assert set(report["generalization_mm"]) == {"1", "2"} == set(report["specificity_mm"])
    g = report["generalization_mm"]
    assert g["2"] < g["1"]  # more components generalise better
    assert os.path.getsize(report["mode_picture"]) > 1000
    # Meshes not in correspondence are refused.
    bp.write_ply(tmp_path / "odd.ply", meshes[0][:100], np.array([[0, 1, 2]]))
    assert main(["--no-cache", "learn", str(tmp_path), "--out", str(model_path)]) == 2
    assert "not in correspondence" in capsys.readouterr().err


def test_pose_and_render(tmp_path, capsys):
    body = bp.load_default_body("cmu_mb")
    rng = np.random.default_rng(0)
    poses = np.zeros((3, body.n_joints, 3))
    poses[:, 1:] = rng.normal(scale=0.2, size=(3, body.n_joints - 1, 3))
    trans = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05], [0.3, 0.1, 0.0]])
    bp.poses_to_bvh(body, poses, trans, fps=30.0, path=tmp_path / "clip.bvh")
    out = tmp_path / "posed"
    argv = ["--no-cache", "pose", str(tmp_path / "clip.bvh"), "--frame", "-2", "--phenotype",
            "gender=1", "--phenotype", "weight=0.8", "--out", str(out),
            "--size", "128"]  # fmt: skip
    assert main(argv) == 0
    v, f, _ = bp.read_mesh(out / "clip_00001.ply")
    phen = bp.phenotype_vector(gender=1.0, weight=0.8)
    pose, tr = bp.retarget(bp.read_bvh(tmp_path / "clip.bvh"), body, [1],
                           keep_root_rotation=True, keep_root_translation=True)  # fmt: skip
    ref, _ = bp.evaluate(body, phen, pose[0], tr[0])
    np.testing.assert_allclose(v, np.asarray(ref), atol=1e-6)
    np.testing.assert_allclose(tr[0], trans[1], atol=1e-6)  # root motion kept
    meta = json.loads((out / "clip_00001.json").read_text())
    assert meta["frame"] == 1 and meta["phenotypes"]["gender"] == 1.0
    assert main(["--no-cache", "pose", str(tmp_path / "clip.bvh"), "--frame", "3",
                 "--out", str(out)]) == 2  # fmt: skip
    assert "--frame" in capsys.readouterr().err
    assert main(["--no-cache", "pose", str(tmp_path / "clip.bvh"), "--phenotype", "hight=1",
                 "--out", str(out)]) == 2  # fmt: skip
    assert "unknown phenotype" in capsys.readouterr().err

    png = tmp_path / "r.png"
    argv = ["--no-cache", "render", str(out / "clip_00001.ply"), "--out", str(png), "--size", "96"]
    assert main(argv) == 0
    import matplotlib.image

    img = matplotlib.image.imread(str(png))
    assert img.shape[:2] == (96, 2 * 72)  # front and side
    assert img[..., :3].min() < 0.5  # the body is drawn


def test_shipped_space():
    tmpl = registration.registration_template()
    model, info = sscape.default_space(20, return_info=True)
    assert model.n_components == 20 and model.n_vertices == tmpl.n_vertices
    assert model.rig.joint_names == tmpl.rig.joint_names
    assert info["population"]["n_bodies"] == 2000 and info["n_components"] == 50
    cum = info["explained_variance_cumulative"]
    assert 0.95 < cum[9] < cum[19] < cum[49] <= 1.0
    np.testing.assert_allclose(np.cumsum(np.asarray(model.explained_variance))[-1], cum[19], 1e-5)
    assert sscape.default_space(50).n_components == 50
    for bad in (0, 51):
        with pytest.raises(ValueError, match="n_components"):
            sscape.default_space(bad)
    # A held-out body of the same population is reconstructed to a few millimetres.
    pop = bp.sample_population(4, pose_jitter_deg=0.0, key=jax.random.PRNGKey(99), progress=False)
    x = np.asarray(tmpl.restrict(np.asarray(pop.vertices)), np.float64)
    err = np.asarray(sscape.reconstruction_error(model, jnp.asarray(x), (5, 20)))
    assert err.shape[-1] == 2 and np.all(err[..., 1] < err[..., 0]) and np.all(err[..., 1] < 6.0)


def test_presets_and_model_info(tmp_path):
    assert sscape.FitConfig.preset("default") == sscape.FitConfig()
    hs = sscape.FitConfig.preset("humanshape", max_passes=3)
    assert (hs.landmark_weight, hs.pose_prior, hs.max_passes) == (0.0, 1.0, 3)
    with pytest.raises(ValueError, match="name"):
        sscape.FitConfig.preset("caesar")
    a, c = (registration.NRDConfig.preset(n) for n in ("anchored", "caesar"))
    assert not a.head_rule and c.head_rule
    assert a == registration.NRDConfig.preset("caesar", head_rule=False)
    model = sscape.default_space(3)
    sscape.save_model(tmp_path / "m.sscape", model, info={"who": "test", "n": [1, 2]})
    m2, info = sscape.load_model(tmp_path / "m.sscape", return_info=True)
    assert info == {"who": "test", "n": [1, 2]}
    np.testing.assert_array_equal(np.asarray(m2.basis), np.asarray(model.basis))
    sscape.save_model(tmp_path / "n.sscape", model)
    assert sscape.load_model(tmp_path / "n.sscape", return_info=True)[1] == {}
    with pytest.raises(ValueError, match="info"):
        sscape.save_model(tmp_path / "x.sscape", model, info={"a": object()})


@pytest.mark.bad_input
def test_shipped_space_bad_input():
    for bad in (2.5, True, "20"):
        with pytest.raises(ValueError, match="n_components"):
            sscape.default_space(bad)


def test_cache_dir_precedence(monkeypatch, tmp_path):
    from bodyprior.cli import cache_dir

    monkeypatch.setenv("BODYPRIOR_CACHE", str(tmp_path / "a"))
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "b"))
    assert cache_dir() == str(tmp_path / "a")
    monkeypatch.delenv("BODYPRIOR_CACHE")
    assert cache_dir() == str(tmp_path / "b")  # JAX's own variable: shared with the caller
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert cache_dir() == str(tmp_path / "x" / "bodyprior" / "jax")
