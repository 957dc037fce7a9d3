"""The embedded default body: asset integrity, phenotype model, posing, population, CLI."""

import json
import os
import shutil

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import assets
from bodyprior._body import _INTERPOLATED


@pytest.fixture(scope="module")
def body():
    return bp.load_default_body("cmu_mb", dtype=np.float64)


def test_asset_contents():
    a = bp.load_asset()
    m = a["metadata"]
    assert m["format"] == "bodyprior.default_body"
    assert a["template_vertices"].shape == (13380, 3)
    assert a["faces"].shape == (26756, 3)
    assert a["faces"].min() == 0 and a["faces"].max() == 13379
    assert len(a["rig_cmu_mb_labels"]) == 31 and len(a["rig_game_engine_labels"]) == 53
    assert len(a["local_labels"]) == 256 and len(a["face_labels"]) == 52
    assert len(a["landmark_names"]) >= 60
    assert m["macro_max_error_m"] < 1e-7
    assert os.path.getsize(assets.asset_path()) < 32 * 2**20
    # Template: metres, Z up, about 1.6-1.7 m tall, facing -Y (nose is the most anterior head
    # point).
    t = a["template_vertices"]
    assert 1.5 < t[:, 2].max() - t[:, 2].min() < 1.8
    # Skin weights: top-k rows sum to one.
    np.testing.assert_allclose(a["rig_cmu_mb_skin_weight"].sum(1), 1.0, atol=1e-6)


def test_asset_checksum_and_format_errors(tmp_path):
    src = assets.asset_path()
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    # Corrupt one array value but keep the stored checksum -> rejected.
    bad = dict(arrays)
    tv = bad["template_vertices"].copy()
    tv[0, 0] += 1e-3
    bad["template_vertices"] = tv
    p = tmp_path / "bad.npz"
    np.savez(p, **bad)
    with pytest.raises(ValueError, match="corrupted"):
        assets.load_asset(str(p))
    # Wrong format name.
    meta = json.loads(str(arrays["metadata"]))
    meta["format"] = "something.else"
    wrong = dict(arrays, metadata=np.array(json.dumps(meta)))
    p2 = tmp_path / "wrong.npz"
    np.savez(p2, **wrong)
    with pytest.raises(ValueError, match="format"):
        assets.load_asset(str(p2))
    # Not a zip at all / missing file.
    p3 = tmp_path / "junk.npz"
    p3.write_bytes(b"not an npz")
    with pytest.raises(ValueError):
        assets.load_asset(str(p3))
    with pytest.raises(ValueError, match="not found"):
        assets.load_asset(str(tmp_path / "missing.npz"))
    # An exact copy loads.
    p4 = tmp_path / "copy.npz"
    shutil.copy(src, p4)
    assert assets.load_asset(str(p4))["faces"].shape == (26756, 3)


@pytest.mark.parametrize("x", [0.0, 0.1, 0.37, 0.5, 0.8, 1.0])
def test_hat_weights(x):
    for feat, (names, lo, hi) in _INTERPOLATED.items():
        p = bp.phenotype_vector(**{feat: np.clip(x, lo, hi)})
        w = np.asarray(
            bp.variation_weights(jnp.asarray(p), tuple(bp.load_asset()["variation_labels"]))
        )
        labels = list(bp.load_asset()["variation_labels"])
        ws = np.array([w[labels.index(n)] for n in names])
        assert np.all(ws >= 0) and abs(ws.sum() - 1) < 1e-12
        anchors = np.linspace(lo, hi, len(names))
        # linear interpolation reproduces x
        assert abs((ws * anchors).sum() - np.clip(x, lo, hi)) < 1e-12


def test_family_coefficients_sum_to_one(body, getkey):
    labels = bp.load_asset()["macro_labels"][bp.load_asset()["macro_nonbreast_index"]]
    fam = np.array([str(s).split(":")[0] for s in labels])
    for _ in range(5):
        p = jax.random.uniform(getkey(), (11,), jnp.float64)
        c = np.asarray(bp.macro_coefficients(body, p))
        for f in ("universal", "race", "height"):
            assert abs(c[fam == f].sum() - 1.0) < 1e-9, f
        # proportions has no baby/newborn targets: its weights sum to 1 - w_baby - w_newborn
        age = float(p[1])
        w_baby = max(0.0, 1 - abs(age - 0.0) * 3)
        assert abs(c[fam == "proportions"].sum() - (1.0 - w_baby)) < 1e-9


def test_rest_shape_is_plausible_and_linear(body):
    male, mj = bp.rest_shape(body, bp.phenotype_vector(gender=0.0, age=2 / 3))
    female, _ = bp.rest_shape(body, bp.phenotype_vector(gender=1.0, age=2 / 3))
    hm = float(male[:, 2].max() - male[:, 2].min())
    hf = float(female[:, 2].max() - female[:, 2].min())
    assert 1.6 < hf < hm < 2.0
    # Joints: hips below the head, root first.
    names = body.joint_names
    assert names[0] == "Hips" and mj[names.index("Head"), 2] > mj[0, 2]
    # The shape is affine in the macro coefficients: midpoint of coefficient vectors -> midpoint
    # mesh.
    p1, p2 = bp.phenotype_vector(weight=0.2), bp.phenotype_vector(weight=0.4)
    v1, v2 = bp.rest_shape(body, p1)[0], bp.rest_shape(body, p2)[0]
    vm = bp.rest_shape(body, bp.phenotype_vector(weight=0.3))[0]
    np.testing.assert_allclose(vm, 0.5 * (v1 + v2), atol=1e-9)


def test_zero_pose_gives_rest_and_rigid_commutes(body, getkey):
    p = bp.phenotype_vector(gender=0.3, age=0.8, weight=0.6)
    rest, joints = bp.rest_shape(body, p)
    v, j = bp.evaluate(body, p, jnp.zeros((31, 3)))
    np.testing.assert_allclose(v, rest, atol=1e-10)
    np.testing.assert_allclose(j, joints, atol=1e-10)
    # Rotating the root about its joint and translating = a rigid motion of the whole posed body.
    pose = 0.3 * jax.random.normal(getkey(), (31, 3), jnp.float64)
    v0, _ = bp.evaluate(body, p, pose.at[0].set(0.0))
    aa = jnp.array([0.2, -0.5, 0.9])
    t = jnp.array([0.1, 0.2, -0.3])
    v1, _ = bp.evaluate(body, p, pose.at[0].set(aa), t)
    R = bp.axis_angle_to_matrix(aa)
    expect = (v0 - joints[0]) @ R.T + joints[0] + t
    np.testing.assert_allclose(v1, expect, atol=1e-9)
    # DQS agrees with LBS for a rigid (root-only) motion.
    v2, _ = bp.evaluate(body, p, jnp.zeros((31, 3)).at[0].set(aa), t, skinning="dqs")
    np.testing.assert_allclose(v2, (rest - joints[0]) @ R.T + joints[0] + t, atol=1e-9)


def test_evaluate_grad_vmap_and_no_recompile(body, getkey):
    p = jnp.asarray(bp.phenotype_vector())
    pose = 0.2 * jax.random.normal(getkey(), (31, 3), jnp.float64)

    def loss(p, pose):
        v, _ = bp.evaluate(body, p, pose)
        return jnp.sum(v**2)

    gp, gq = jax.grad(loss, argnums=(0, 1))(p, pose.at[5].set(0.0))  # a zero rotation included
    assert np.all(np.isfinite(gp)) and np.all(np.isfinite(gq))
    # Finite differences on one pose entry and one phenotype entry.
    eps = 1e-6
    for arg, idx in ((1, (3, 1)), (0, (4,))):  # height 0.5 is not a hat-function kink
        args = [p, pose]
        d = jnp.zeros_like(args[arg]).at[idx].set(eps)
        fd = (
            loss(*[a + d if i == arg else a for i, a in enumerate(args)])
            - loss(*[a - d if i == arg else a for i, a in enumerate(args)])
        ) / (2 * eps)
        g = jax.grad(loss, argnums=arg)(p, pose)[idx]
        assert abs(float(g) - float(fd)) < 1e-4 * max(1.0, abs(float(fd)))

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def batch(ps, poses):
        return jax.vmap(lambda a, b: bp.evaluate(body, a, b))(ps, poses)

    ps = jnp.tile(p, (4, 1))
    poses = jnp.zeros((4, 31, 3))
    v1, _ = batch(ps, poses)
    v2, _ = batch(ps.at[:, 3].set(0.9), poses + 0.1)
    assert v1.shape == (4, 13380, 3) and not np.allclose(v1, v2)


@pytest.mark.bad_input
def test_phenotype_ranges_are_checked_per_entry(body):
    """Regression: phenotype_vector accepted gender=1.5 / height=180, evaluate's range error named
    no entry (and used age's bound for all), and under jit nothing was checked."""
    male_female = r"`gender` must lie in \[0, 1\] \(0 = male, 1 = female\), got 1.5"
    with pytest.raises(ValueError, match=male_female):
        bp.phenotype_vector(gender=1.5)
    with pytest.raises(ValueError, match=r"`height` must lie in \[0, 1\].*got 180"):
        bp.phenotype_vector(height=180)
    with pytest.raises(ValueError, match=r"`age` must lie in \[-1/3, 1\]"):
        bp.phenotype_vector(age=-0.5)
    with pytest.raises(ValueError, match="`weight`"):
        bp.phenotype_vector(weight=float("nan"))
    assert bp.phenotype_vector(age=-1 / 3, gender=0.0)[1] == -1 / 3  # the ends are valid
    p = np.asarray(bp.phenotype_vector())
    height = r"`phenotypes\[4\]` \(height\) must lie in \[0, 1\].*got 1.2"
    with pytest.raises(ValueError, match=height):
        bp.evaluate(body, _with(p, 4, 1.2))
    # gender's own bound is 0, not age's -1/3
    with pytest.raises(ValueError, match=r"`phenotypes\[0\]` \(gender\) must lie in \[0, 1\]"):
        bp.rest_shape(body, _with(p, 0, -0.2))
    rest = eqx.filter_jit(lambda q: bp.rest_shape(body, q)[0])
    assert np.isfinite(np.asarray(rest(jnp.asarray(p)))).all()
    with pytest.raises((ValueError, RuntimeError), match=r"`phenotypes\[3\]` \(weight\)"):
        jax.block_until_ready(rest(jnp.asarray(_with(p, 3, 1.5))))


def _with(p, i, x):
    q = np.array(p, dtype=np.float64)
    q[i] = x
    return q


@pytest.mark.bad_input
def test_bad_inputs(body):
    with pytest.raises(ValueError, match="phenotypes"):
        bp.rest_shape(body, np.zeros(10))
    with pytest.raises(ValueError, match="phenotypes"):
        bp.rest_shape(body, np.full(11, np.nan))
    with pytest.raises(ValueError, match="phenotypes"):
        bp.rest_shape(body, np.full(11, 1.5))
    with pytest.raises(ValueError, match="local_changes"):
        bp.rest_shape(body, bp.phenotype_vector(), local_changes=np.zeros(256))
    with pytest.raises(ValueError, match="pose"):
        bp.evaluate(body, bp.phenotype_vector(), np.zeros((30, 3)))
    with pytest.raises(ValueError, match="rig"):
        bp.load_default_body("mixamo")
    with pytest.raises(ValueError, match="unknown phenotype"):
        bp.phenotype_vector(bmi=0.3)


def test_local_changes_and_face():
    b = bp.load_default_body(local_changes=True, facial_actions=True)
    p = bp.phenotype_vector()
    v0, _ = bp.rest_shape(b, p)
    i = b.local_labels.index(next(s for s in b.local_labels if "nose" in s))
    x = np.zeros(len(b.local_labels), np.float32)
    x[i] = 1.0
    v1, _ = bp.rest_shape(b, p, local_changes=x)
    moved = np.linalg.norm(np.asarray(v1 - v0), axis=1) > 1e-5
    assert 0 < moved.sum() < 2000  # local: only part of the body moves
    f = np.zeros(52, np.float32)
    f[b.face_labels.index("jawOpen")] = 1.0
    v2, _ = bp.rest_shape(b, p, facial_actions=f)
    assert np.abs(np.asarray(v2 - v0)).max() > 5e-3


def test_regressed_joints_follow_shape(body, getkey):
    for _ in range(3):
        p = jax.random.uniform(getkey(), (11,), jnp.float64, 0.0, 1.0).at[1].set(0.7)
        v, j = bp.rest_shape(body, p)
        err = np.linalg.norm(np.asarray(bp.regress_joints(body, v) - j), axis=1)
        assert err.max() < 0.012  # metres; the build log reports the held-out error


def test_rig_and_bone_placement(body):
    """The default body holds one `bp.Rig` (tree, names, skin, regressor) and MakeHuman's
    `bp.BonePlacement` (bone heads/tails/roll) beside it."""
    rig, bones = body.rig, body.bones
    assert isinstance(rig, bp.Rig) and isinstance(bones, bp.BonePlacement)
    assert rig.n_joints == 31 and rig.n_vertices == body.n_vertices and bones.name == "cmu_mb"
    assert body.parents == rig.parents and body.joint_names[0] == rig.joint_names[0] == "Hips"
    assert bones.head_template.shape == bones.tail_template.shape == (31, 3)
    np.testing.assert_allclose(np.asarray(rig.skin_weights).sum(1), 1.0, atol=1e-6)
    # rest joints at the base body are the bone heads; the regressor reproduces them closely
    v, j = bp.rest_shape(body, bp.phenotype_vector())
    np.testing.assert_array_equal(bp.regress_joints(body, v), rig.regress_joints(v))
    assert float(jnp.abs(rig.regress_joints(v) - j).max()) < 0.012
    ge = bp.load_default_body("game_engine")
    assert ge.rig.n_joints == 53 and ge.bones.name == "game_engine"


def test_population(getkey):
    b = bp.load_default_body(local_changes=True)
    pop = bp.sample_population(40, body=b, progress=False, chunk=16, key=jax.random.PRNGKey(3))
    assert pop.vertices.shape == (40, 13380, 3) and len(pop) == 40
    h = np.asarray(pop.vertices[..., 2].max(1) - pop.vertices[..., 2].min(1))
    assert np.all((h > 1.4) & (h < 2.15))
    sex = np.asarray(pop.sex)
    assert 0 < sex.sum() < 40  # both sexes present
    assert np.all((pop.age_years >= 18) & (pop.age_years <= 65))
    assert h[sex == 0].mean() > h[sex == 1].mean()  # men taller on average
    pop2 = bp.sample_population(40, body=b, progress=False, chunk=8, key=jax.random.PRNGKey(3))
    np.testing.assert_allclose(pop.vertices, pop2.vertices, atol=1e-5)  # reproducible from the seed
    with pytest.raises(ValueError, match="age_range"):
        bp.sample_population(3, body=b, age_range=(30, 20), key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="n"):
        bp.sample_population(0, body=b, key=jax.random.PRNGKey(0))


def test_cli(tmp_path, capsys):
    from bodyprior.cli import main

    assert (
        main(
            [
                "--no-cache",
                "sample",
                "--n",
                "3",
                "--seed",
                "1",
                "--out",
                str(tmp_path),
                "--no-local-changes",
            ]
        )
        == 0
    )
    files = sorted(os.listdir(tmp_path))
    assert "contact_sheet.png" in files and "population.json" in files
    assert len([f for f in files if f.endswith(".ply")]) == 3
    v, f, _ = bp.read_mesh(str(tmp_path / "body_0.ply"))
    assert v.shape == (13380, 3) and f.shape == (26756, 3)
    meta = json.loads((tmp_path / "population.json").read_text())
    assert len(meta["bodies"]) == 3
    import matplotlib.image

    img = matplotlib.image.imread(str(tmp_path / "contact_sheet.png"))
    assert img.ndim == 3 and img.shape[0] > 100
    assert main(["--no-cache", "info"]) == 0
    assert "vertices" in capsys.readouterr().out


def test_sscape_space_from_population():
    """An S-SCAPE space learned from the population, with the default body's rig, reconstructs
    held-out
    bodies and poses like the body it came from."""
    b = bp.load_default_body()
    pop = bp.sample_population(
        48, body=b, pose_jitter_deg=0.0, progress=False, key=jax.random.PRNGKey(7)
    )
    train, test = pop.vertices[:40], pop.vertices[40:]
    space = bp.sscape.learn(train, b.faces, n_components=20, rig=b.rig)
    assert space.n_joints == 31 and space.n_components == 20
    # Held-out bodies (rigidly aligned to the mean) are reconstructed from 20 components to a few
    # mm.
    aligned, _ = bp.sscape.procrustes_align(
        jnp.concatenate([space.mean[None], test]), reference=space.mean
    )
    d = (aligned[1:] - space.mean).reshape(len(test), -1)
    B = space.basis.reshape(space.n_components, -1)
    recon = (d @ B.T) @ B
    err = np.linalg.norm(np.asarray(recon - d).reshape(len(test), -1, 3), axis=-1).mean()
    assert err < 0.006
    # The mean posed with the body's rig: zero pose is the mean; bending an elbow moves only that
    # arm.
    v0, _ = bp.sscape.evaluate(space, jnp.zeros(20), jnp.zeros((31, 3)))
    np.testing.assert_allclose(v0, space.mean, atol=1e-5)
    pose = jnp.zeros((31, 3)).at[b.joint_names.index("LeftForeArm")].set(jnp.array([0.0, 0.0, 1.0]))
    v1, _ = bp.sscape.evaluate(space, jnp.zeros(20), pose)
    moved = np.linalg.norm(np.asarray(v1 - v0), axis=1) > 1e-3
    assert 0 < moved.sum() < 2500 and np.all(np.asarray(v0)[moved, 0] > 0.1)  # +X = the body's left
