"""PanoMan model on open data: training set, model, save/load, reconstruction (tiny sizes)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
import bodyprior.panoman as pm

jax.config.update("jax_enable_x64", True)

MOCAP = bp.find_mocap_dir()
needs_data = pytest.mark.skipif(MOCAP is None, reason="shared mocap data not found")


def test_expression_set_is_fixed_and_skips_the_tongue():
    body = bp.load_default_body("cmu_mb", facial_actions=True)
    W = pm.expression_set(body.face_labels, 39, seed=0)
    assert W.shape == (39, 52)
    np.testing.assert_array_equal(W, pm.expression_set(body.face_labels, 39, seed=0))
    assert np.all(W[:, body.face_labels.index("tongueOut")] == 0)
    assert np.all((W >= 0) & (W <= 1))
    assert np.all((W > 0).sum(1) >= 1)
    np.testing.assert_array_equal((W[:12] > 0).sum(1), 1)  # 12 single units


def test_gestures_within_limits_and_fist_closes_towards_the_palm():
    hb = bp.load_default_body("game_engine")
    G = pm.gesture_poses(hb, 20, seed=3)
    assert G.shape == (26, hb.n_joints, 3)
    deg = np.rad2deg(np.linalg.norm(G, axis=-1))
    assert deg.max() <= np.hypot(110.0, 20.0) + 1e-6
    non_finger = [i for i, n in enumerate(hb.joint_names) if n.split("_")[0] not in
                  ("thumb", "index", "middle", "ring", "pinky")]  # fmt: skip
    assert np.all(G[:, non_finger] == 0)
    phen = bp.phenotype_vector()
    _, j0 = bp.rest_shape(hb, phen)
    _, j1 = bp.evaluate(hb, phen, G[1])  # fist
    i1, i2 = hb.joint_names.index("index_01_l"), hb.joint_names.index("index_02_l")
    hand = np.asarray(j0[hb.joint_names.index("hand_l")])
    # the PIP joint moves towards the body midline (palms face it in the A-pose)
    assert abs(float(j1[i2][0])) < abs(float(j0[i2][0])) - 0.005
    np.testing.assert_allclose(j1[i1], j0[i1], atol=1e-6)
    assert hand[0] > 0  # left hand on +x


@pytest.fixture(scope="module")
def trained():
    poses = bp.load_mocap(MOCAP, progress=False)
    train, _ = bp.split_by_clip(poses, 0.2, seed=0)
    vm, faces = bp.load_decimated()
    top = bp.Topology.from_faces(faces)
    data = pm.make_panoman_data(
        jax.random.key(0), train, n_body_identities=4, poses_per_identity=3,
        n_face_identities=2, n_expressions=8, n_hand_identities=3, gestures_per_identity=6,
        sex=1, vertex_map=vm, progress=False,
    )  # fmt: skip
    sol = pm.train_panoman(
        data, top, key=jax.random.key(1), n_components=(6, 4, 4), splocs_iterations=1,
        correction_hidden=32, correction_rank=8, correction_steps=200, beta_steps=50,
        batch=16, progress=False,
    )  # fmt: skip
    return data, top, sol


@needs_data
def test_training_set(trained):
    data, top, _ = trained
    assert data.counts() == {"body": 12, "face": 16, "hand": 18}
    assert np.all(np.asarray(data.sex) == 1)
    v = np.asarray(data.vertices)
    assert v.shape == (46, top.n_vertices, 3) and np.isfinite(v).all()
    kind = np.asarray(data.kind)
    # body meshes move the body, face meshes only the head, gestures only the hands
    disp = np.linalg.norm(v - np.asarray(data.rest)[np.asarray(data.identity)], axis=-1)
    assert disp[kind == 0].max() > 0.1
    assert 0.002 < disp[kind == 1].max() < 0.1
    assert 0.01 < disp[kind == 2].max() < 0.2
    assert np.all(np.asarray(data.clip)[kind == 0] >= 0)
    assert np.all(np.asarray(data.expression)[kind == 1] >= 0)


@needs_data
def test_model_neutral_coefficients_and_mlps(trained):
    data, top, sol = trained
    m = sol.value
    assert m.part_sizes == (6, 4, 4) and m.n_components == 14
    st = sol.stats
    assert st["correction"]["rmse_after"] < st["correction"]["rmse_before"]
    # the rest body: all parts neutral vs all coefficients zero (the mean is a sum of averages)
    rest = np.asarray(data.rest[0], np.float64)
    alpha = m.shape_coefficients(rest)
    v_neutral = np.asarray(pm.evaluate(m, alpha, align_to=rest, correct=False).value.vertices)
    zero = (np.zeros(14), np.zeros(14))
    v_zero = np.asarray(pm.evaluate(m, alpha, zero, align_to=rest, correct=False).value.vertices)
    e_neutral = np.linalg.norm(v_neutral - rest, axis=1).mean()
    e_zero = np.linalg.norm(v_zero - rest, axis=1).mean()
    assert e_neutral < e_zero
    rla = pm.model_targets(m, *m.neutral(), correct=False)
    assert np.abs(np.asarray(rla.lengths)).mean() < np.abs(np.asarray(m.mean_lengths)).mean()
    # `moving`: the same targets; derivatives only for the moving rows (a fit block's β)
    bl, ba = (jnp.asarray(x, jnp.float64) for x in m.with_body(jnp.full(6, 0.3), jnp.full(6, -0.2)))
    body = m.part_slice("body")
    full = pm.model_targets(m, bl, ba)
    part = pm.model_targets(m, bl, ba, moving=body)
    np.testing.assert_allclose(part.concat(), full.concat(), rtol=1e-12, atol=1e-12)

    def jac(moving):
        return jax.jacfwd(lambda b: pm.model_targets(m, b, ba, moving=moving).concat())(bl)

    j_full, j_part = np.asarray(jac(None)), np.asarray(jac(body))
    np.testing.assert_allclose(j_part[:, body], j_full[:, body], rtol=1e-10, atol=1e-12)
    assert not np.any(j_part[:, body.stop :]) and np.any(j_full[:, body.stop :])


@needs_data
@pytest.mark.bad_input
def test_model_targets_bad_moving(trained):
    m = trained[2].value
    with pytest.raises(ValueError, match="moving"):
        pm.model_targets(m, *m.neutral(), moving=(0, 6))


@needs_data
def test_save_load_roundtrip(trained, tmp_path):
    data, top, sol = trained
    m = sol.value
    path = tmp_path / "m.npz"
    pm.save_panoman(m, path)
    m2 = pm.load_panoman(path)
    alpha = np.zeros(m.shape_basis.shape[0])
    beta = m.with_body(jnp.full(6, 0.3), jnp.full(6, -0.2))
    v1 = np.asarray(pm.evaluate(m, alpha, beta).value.vertices)
    v2 = np.asarray(pm.evaluate(m2, alpha, beta).value.vertices)
    np.testing.assert_allclose(v2, v1, atol=2e-5)  # float32 storage of the components
    bad = tmp_path / "bad.npz"
    np.savez(bad, metadata=np.asarray('{"format": "other"}'))
    with pytest.raises(ValueError, match="format"):
        pm.load_panoman(bad)
    with pytest.raises(ValueError, match="alpha"):
        pm.evaluate(m, np.zeros(3))


@needs_data
def test_fit_panoman_lowers_the_error_from_dense_handles(trained):
    data, top, sol = trained
    m = sol.value
    i = 0  # a body training mesh
    gt = np.asarray(data.vertices[i], np.float64)
    rng = np.random.default_rng(0)
    h = rng.choice(top.n_vertices, 300, replace=False)
    cons = pm.shell_constraints(handles=(h, gt[h]))
    fit = pm.fit_panoman(m, cons, theta=np.asarray(data.body_pose[i]),
                         joint_names=bp.load_default_body().joint_names, max_steps=3,
                         align_to=gt, blocks=("body",))  # fmt: skip
    e0 = np.linalg.norm(np.asarray(fit.value.init_vertices) - gt, axis=1).mean()
    e1 = np.linalg.norm(np.asarray(fit.value.vertices) - gt, axis=1).mean()
    assert e1 < 0.5 * e0
    assert fit.stats["blocks"][0]["energy"] < fit.stats["blocks"][0]["energy0"]


@needs_data
def test_local_blocks_move_only_their_region(trained):
    """prepare_panoman_solver: the face and hand blocks move their part's region (the support of
    its components, grown by `rings`) and nothing else; `local=()` moves every vertex."""
    data, top, sol = trained
    m = sol.value
    local = pm.prepare_panoman_solver(m, rings=1)
    assert local.region("body") is None
    region = np.zeros(top.n_vertices, bool)
    for part in ("face", "hand"):
        r = local.region(part)
        assert 0 < r.n_free < r.topology.n_vertices < top.n_vertices
        region[np.asarray(r.vertices)[np.asarray(r.free)]] = True
    i = 0
    gt = np.asarray(data.vertices[i], np.float64)
    alpha = m.shape_coefficients(np.asarray(data.rest[i], np.float64))
    rng = np.random.default_rng(5)
    h = rng.choice(top.n_vertices, 300, replace=False)
    cons = pm.shell_constraints(handles=(h, gt[h] + 0.004 * rng.standard_normal((300, 3))))
    kw = dict(init=(alpha, *m.neutral()), init_mesh=gt, blocks=("face", "hand"), max_steps=2)
    fit = pm.fit_panoman(m, cons, solver=local, **kw)
    moved = np.abs(np.asarray(fit.value.vertices) - gt).max(1) > 0
    assert moved[region].mean() > 0.5
    assert not moved[~region].any()
    for b in fit.stats["blocks"]:
        assert b["energy"] < b["energy0"]
        assert b["free_vertices"] == local.region(b["part"]).n_free
    whole = pm.fit_panoman(m, cons, solver=pm.prepare_panoman_solver(m, local=()), **kw)
    assert (np.abs(np.asarray(whole.value.vertices) - gt).max(1) > 0)[~region].mean() > 0.5


@needs_data
@pytest.mark.parametrize("part", ["body", "face"])
def test_block_targets_and_their_gram_equal_the_dense_ones(trained, part):
    """fit_panoman's whole-mesh block targets (fixed part once, moving rows in coordinate form,
    correction through its last layer) equal `model_targets`, and their structured Gram
    `Jᵀ diag(w) J` equals the dense Jacobian's, with and without the correction MLP."""
    from jax.flatten_util import ravel_pytree

    from bodyprior.panoman import _fit

    _, top, sol = trained
    m = sol.value
    solver = pm.prepare_panoman_solver(m, local=())
    rng = np.random.default_rng(3)
    K, s = m.n_components, m.part_slice(part)
    bl = jnp.asarray(m.neutral_lengths + 0.3 * rng.standard_normal(K))
    ba = jnp.asarray(m.neutral_angles + 0.3 * rng.standard_normal(K))
    alpha = jnp.asarray(rng.standard_normal(m.shape_basis.shape[0]))
    w = jnp.asarray(rng.uniform(0.1, 2.0, 2 * top.n_edges))
    grams = []
    for flag in (1.0, 0.0):
        f = jnp.asarray(flag)
        base = _fit._block_base(m, bl, ba, f, s.start, s.stop, part == "body")
        rows = solver.rows[pm.PARTS.index(part)]
        tg = _fit._BlockTargets(
            m, alpha, base.lengths, base.angles, rows, f, part == "body", s.start
        )
        params = {"bl": bl[s] + 0.1, "ba": ba[s] - 0.1}
        if part == "body":
            params["alpha"] = alpha
        full_l, full_a = bl.at[s].set(params["bl"]), ba.at[s].set(params["ba"])
        ref = pm.model_targets(m, full_l, full_a, correct=f)
        got = tg(params)
        np.testing.assert_allclose(got.lengths, ref.lengths, atol=1e-6)
        np.testing.assert_allclose(got.angles, ref.angles, atol=1e-6)
        p0, unravel = ravel_pytree(params)

        def flat(p):
            x = tg(unravel(p))
            return jnp.concatenate([x.lengths, x.angles]).astype(jnp.float64)

        J = jax.jacfwd(flat)(p0)  # (2E, P)
        G_ref = J.T @ (w[:, None] * J)
        G = tg.weighted_gram(params, w)
        scale = float(jnp.abs(G_ref).max())
        np.testing.assert_allclose(G, G_ref, atol=1e-5 * scale)
        grams.append(G)
    # the body block's correction Jacobian is in the Gram (with the MLP off it is not)
    differ = float(jnp.abs(grams[0] - grams[1]).max()) > 1e-3 * float(jnp.abs(grams[0]).max())
    assert differ == (part == "body")


@needs_data
@pytest.mark.bad_input
def test_panoman_solver_bad_input(trained):
    _, top, sol = trained
    m = sol.value
    with pytest.raises(ValueError, match="local"):
        pm.prepare_panoman_solver(m, local=("body",))
    with pytest.raises(ValueError, match="rings"):
        pm.prepare_panoman_solver(m, rings=-1)
    cons = pm.shell_constraints(handles=(np.array([0]), np.zeros((1, 3))))
    with pytest.raises(ValueError, match="prepare_panoman_solver"):
        pm.fit_panoman(m, cons, solver=pm.prepare_shell_solver(top))
    other = eqx.tree_at(lambda x: x.components_lengths, m, m.components_lengths * 1.5)
    with pytest.raises(ValueError, match="another model"):
        pm.fit_panoman(other, cons, solver=pm.prepare_panoman_solver(m, local=()))


@needs_data
def test_motion_coefficients_recover_a_model_mesh(trained):
    data, top, sol = trained
    m = sol.value
    alpha = m.shape_coefficients(np.asarray(data.rest[1], np.float64))
    rng = np.random.default_rng(3)
    beta = (np.asarray(m.neutral()[0]) + 0.3 * rng.standard_normal(m.n_components),
            np.asarray(m.neutral()[1]) + 0.3 * rng.standard_normal(m.n_components))  # fmt: skip
    v = np.asarray(pm.evaluate(m, alpha, beta, correct=False).value.vertices)
    # the decoded mesh's RLA is the model's targets only up to g's least-squares residual
    bl, ba = m.motion_coefficients(v, alpha)
    v2 = np.asarray(pm.evaluate(m, alpha, (bl, ba), correct=False, align_to=v).value.vertices)
    e2 = np.linalg.norm(v2 - v, axis=1).mean()
    v0 = np.asarray(pm.evaluate(m, alpha, correct=False, align_to=v).value.vertices)
    e0 = np.linalg.norm(v0 - v, axis=1).mean()
    assert e2 < 0.5 * e0  # measured 0.32 (g is least squares: the projection is not exact)
    # init_mesh, start="decoded": the fit starts from the projection (and is placed on the mesh)
    h = rng.choice(top.n_vertices, 50, replace=False)
    cons = pm.shell_constraints(handles=(h, v[h]))
    fit = pm.fit_panoman(m, cons, init_mesh=v, init=(alpha, *m.neutral()), max_steps=1,
                         blocks=("body",), correct=False, start="decoded")  # fmt: skip
    e_init = np.linalg.norm(np.asarray(fit.value.init_vertices) - v, axis=1).mean()
    np.testing.assert_allclose(e_init, e2, rtol=1e-3)  # the same projection, placed on `v`
    # the default with init_mesh: the solve starts from the mesh itself, with the projection's β
    fit_m = pm.fit_panoman(m, cons, init_mesh=v, init=(alpha, *m.neutral()), max_steps=1,
                           blocks=("body",), correct=False)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(fit_m.value.init_vertices), v)
    e_fit = np.linalg.norm(np.asarray(fit_m.value.vertices) - v, axis=1).mean()
    assert e_fit < 0.5 * e2  # it starts on the truth; the shell pulls it only part way to g
    with pytest.raises(ValueError, match="start"):
        pm.fit_panoman(m, cons, start="mesh")
    with pytest.raises(ValueError, match="start"):
        pm.fit_panoman(m, cons, init_mesh=v, start="ik")


@needs_data
@pytest.mark.bad_input
def test_motion_coefficients_bad_input(trained):
    _, top, sol = trained
    m = sol.value
    alpha = np.zeros(m.shape_basis.shape[0])
    with pytest.raises(ValueError, match="vertices"):
        m.motion_coefficients(np.zeros((10, 3)), alpha)
    with pytest.raises(ValueError, match="alpha"):
        m.motion_coefficients(np.zeros((top.n_vertices, 3)), alpha[:3])


@needs_data
def test_lbs_model_ik_recovers_its_own_mesh_and_dqs(trained):
    data, top, sol = trained
    m = sol.value
    body = bp.load_default_body("cmu_mb")
    lbsm = pm.make_lbs_model(m, data, body)
    dqsm = pm.make_lbs_model(m, data, body, skinning="dqs")
    J = body.n_joints
    rng = np.random.default_rng(0)
    alpha = 0.5 * rng.standard_normal(m.shape_basis.shape[0])
    pose = np.asarray(data.body_pose[2], np.float64)
    t = np.array([0.1, -0.2, 0.05])
    v, j = (np.asarray(x) for x in lbsm(jnp.asarray(alpha), jnp.asarray(pose), jnp.asarray(t)))
    h = rng.choice(top.n_vertices, 40, replace=False)
    rows = (np.arange(J)[:, None], np.ones((J, 1)))
    ik = pm.fit_lbs(lbsm, pm.shell_constraints(handles=(h, v[h]), joints=(*rows, j)))
    assert np.linalg.norm(np.asarray(ik.stats["vertices"]) - v, axis=1).mean() < 5e-3
    # zero-weight joint rows (padding) neither pull nor set the start: handles alone
    jw = np.zeros(J)
    far = pm.shell_constraints(handles=(h, v[h]), joints=(*rows, 0 * j + 5.0, jw))
    ik0 = pm.fit_lbs(lbsm, far)
    assert np.linalg.norm(np.asarray(ik0.stats["vertices"]) - v, axis=1).mean() < 0.01
    # DQS: the rest pose equals LBS, a posed body differs (no candy-wrapper)
    z = jnp.zeros((J, 3))
    np.testing.assert_allclose(np.asarray(dqsm(jnp.asarray(alpha), z, jnp.asarray(t))[0]),
                               np.asarray(lbsm(jnp.asarray(alpha), z, jnp.asarray(t))[0]),
                               atol=1e-6)  # fmt: skip
    vd = np.asarray(dqsm(jnp.asarray(alpha), jnp.asarray(pose), jnp.asarray(t))[0])
    assert 1e-4 < np.linalg.norm(vd - v, axis=1).mean() < 0.02
    with pytest.raises(ValueError, match="skinning"):
        pm.make_lbs_model(m, data, body, skinning="lbs2")


@needs_data
def test_kit_save_load_and_reconstruct(trained, tmp_path):
    data, top, sol = trained
    m = sol.value
    body = bp.load_default_body("cmu_mb")
    kit = pm.make_kit(m, data, body, info={"note": "test"})
    assert kit.n_joints == body.n_joints and kit.info_dict() == {"note": "test"}
    path = tmp_path / "kit.npz"
    pm.save_kit(kit, path, float16=False)
    kit2 = pm.load_kit(path)
    np.testing.assert_array_equal(np.asarray(kit2.regressor.indices), kit.regressor.indices)
    np.testing.assert_allclose(np.asarray(kit2.lbs.joint_basis), kit.lbs.joint_basis)
    assert kit2.lbs.parents == kit.lbs.parents and kit2.joint_names == kit.joint_names
    # the model part is a plain model file; a plain model file is not a kit
    assert pm.load_panoman(path).part_sizes == m.part_sizes
    pm.save_panoman(m, tmp_path / "m.npz")
    with pytest.raises(ValueError, match="save_kit"):
        pm.load_kit(tmp_path / "m.npz")
    # a flipped payload value fails the checksum
    with np.load(path) as z:
        arrays = dict(z)
    arrays["kit.joint_mean"] = arrays["kit.joint_mean"] + 1e-3
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match="corrupted"):
        pm.load_kit(tmp_path / "bad.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="readable"):
        pm.load_kit(tmp_path / "junk.npz")

    # reconstruct a training body frame from its exact joints and 20 surface points
    i = 1
    gt = np.asarray(data.vertices[i], np.float64)
    gj = np.asarray(data.joints[i], np.float64)
    pts = np.random.default_rng(0).choice(top.n_vertices, 20, replace=False)
    rec = pm.reconstruct(kit2, gj, (pts, gt[pts]), max_steps=2, blocks=("body",))
    assert rec.result == bp.RESULTS.successful
    e_ik = np.linalg.norm(np.asarray(rec.stats["ik"]["vertices"]) - gt, axis=1).mean()
    e = np.linalg.norm(np.asarray(rec.value.vertices) - gt, axis=1).mean()
    np.testing.assert_array_equal(np.asarray(rec.value.init_vertices),
                                  np.asarray(rec.stats["ik"]["vertices"]))  # fmt: skip
    assert e < 0.05 and e_ik < 0.05, (e, e_ik)
    # the points alone (no joints) also work; bad input names the argument
    rec_p = pm.reconstruct(kit2, points=(pts, gt[pts]), max_steps=2, blocks=("body",))
    assert np.isfinite(np.asarray(rec_p.value.vertices)).all()
    with pytest.raises(ValueError, match="joints"):
        pm.reconstruct(kit2)
    with pytest.raises(ValueError, match="joints"):
        pm.reconstruct(kit2, gj[:5])
    with pytest.raises(ValueError, match="points"):
        pm.reconstruct(kit2, gj, (pts, gt[pts][:3]))
    with pytest.raises(ValueError, match="points"):
        pm.reconstruct(kit2, gj, (np.array([top.n_vertices]), gt[:1]))
    with pytest.raises(ValueError, match="joints"):
        pm.reconstruct(kit2, gj * np.nan)


@needs_data
def test_cli_pose_with_a_panoman_kit(trained, tmp_path, capsys):
    """`bodyprior pose --model panoman --kit FILE`: the kit reconstructed from a BVH frame's joints
    (the shipped kit is exercised by the notebook; a tiny kit keeps this test quick)."""
    import json

    from bodyprior.cli import main

    data, top, sol = trained
    body = bp.load_default_body("cmu_mb")
    kit_path = tmp_path / "kit.npz"
    pm.save_kit(pm.make_kit(sol.value, data, body), kit_path)
    poses = np.asarray(data.body_pose[:2], np.float64)
    bp.poses_to_bvh(body, poses, np.zeros((2, 3)), fps=30.0, path=tmp_path / "clip.bvh")
    out = tmp_path / "posed"
    argv = ["--no-cache", "pose", str(tmp_path / "clip.bvh"), "--frame", "1", "--model",
            "panoman", "--kit", str(kit_path), "--max-steps", "2", "--blocks", "body", "--out",
            str(out), "--size", "96"]  # fmt: skip
    assert main(argv) == 0
    v, f, _ = bp.read_mesh(out / "clip_00001.ply")
    assert v.shape == (top.n_vertices, 3) and f.shape[0] == top.n_faces
    meta = json.loads((out / "clip_00001.json").read_text())
    assert meta["model"] == "panoman" and meta["n_vertices"] == top.n_vertices
    assert [b["part"] for b in meta["blocks"]] == ["body"]
    # the result follows the frame's joints (the tiny model: within a few cm)
    assert meta["joint_residual_mm"]["mean"] < 40.0, meta["joint_residual_mm"]
    assert (out / "clip_00001.png").stat().st_size > 500
    assert main(argv[:-8] + ["--max-steps", "0", "--out", str(out)]) == 2
    assert "--max-steps" in capsys.readouterr().err
    assert main(argv[:-8] + ["--blocks", "body,legs", "--out", str(out)]) == 2
    assert "--blocks" in capsys.readouterr().err
