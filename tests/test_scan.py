"""Virtual laser scanner (holes, noise, outliers, normals, landmarks, density) and scan IO."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import bodyprior as bp
from bodyprior import registration, sscape

# The rest body (A-pose) of the default body: a full-resolution subject without any compile cost.


@pytest.fixture(scope="module")
def body():
    return bp.load_default_body("cmu_mb")


@pytest.fixture(scope="module")
def subject(body):
    v = np.asarray(body.template, np.float64)
    f = np.asarray(body.faces, np.int64)
    return v, f, v[np.asarray(body.landmark_index)], body.landmark_names


@pytest.fixture(scope="module")
def raw(subject):
    """All raw hits (no sub-sampling), exact normals: for coverage statistics."""
    cfg = registration.ScannerConfig(n_points=None, outlier_fraction=0.0, normal_source="mesh")
    return registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(0))


@pytest.fixture(scope="module")
def default_scan(subject):
    return registration.simulate_scan(*subject, key=jr.PRNGKey(1))


def _face_geometry(v, f):
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    return area, cross / (2 * area[:, None]), v[f].mean(1)


def _relative_density(truth, v, f, region):
    """Points per area in `region` (face mask) relative to the whole body."""
    area, _, _ = _face_geometry(v, f)
    face = np.asarray(truth.face)
    cnt = np.bincount(face[face >= 0], minlength=f.shape[0])
    return (cnt[region].sum() / area[region].sum()) / (cnt.sum() / area.sum())


def test_holes_where_real_scanners_have_them(raw, subject, body):
    v, f, _, names = subject
    scan, truth = raw
    area, fn, cen = _face_geometry(v, f)
    zmin, zmax = v[:, 2].min(), v[:, 2].max()
    lm = {n: v[i] for n, i in zip(names, np.asarray(body.landmark_index))}
    soles = (fn[:, 2] < -0.8) & (cen[:, 2] < zmin + 0.03)
    head_top = (fn[:, 2] > 0.9) & (cen[:, 2] > zmax - 0.05)
    crotch = np.linalg.norm(cen - lm["Crotch"], axis=1) < 0.04
    chest = np.linalg.norm(cen - lm["Substernale"], axis=1) < 0.08
    assert soles.sum() > 50 and head_top.sum() > 20 and crotch.sum() > 20
    assert _relative_density(truth, v, f, soles) < 0.1
    assert _relative_density(truth, v, f, head_top) < 0.3
    assert _relative_density(truth, v, f, crotch) < 0.5
    assert _relative_density(truth, v, f, chest) > 0.7
    # raw density is well above the 3 x 6,449 points the paper sub-samples to
    assert scan.n_points > 3 * 3 * 6449


def test_truth_is_on_the_surface_and_noise_matches(default_scan, subject):
    v, f, _, _ = subject
    scan, truth = default_scan
    face, bary = np.asarray(truth.face), np.asarray(truth.bary)
    inl = ~np.asarray(truth.is_outlier)
    assert (face[inl] >= 0).all()
    np.testing.assert_allclose(bary[inl].sum(1), 1.0, atol=1e-12)
    assert bary.min() >= 0
    on_mesh = np.einsum("pk,pkc->pc", bary[inl], v[f[face[inl]]])
    np.testing.assert_allclose(on_mesh, np.asarray(truth.true_points)[inl], atol=1e-12)
    r = np.linalg.norm(np.asarray(scan.points) - np.asarray(truth.true_points), axis=1)[inl]
    rms = np.sqrt(np.mean(r**2))
    assert abs(rms - 0.001) < 0.05 * 0.001, rms


def test_outliers(default_scan):
    scan, truth = default_scan
    out = np.asarray(truth.is_outlier)
    assert scan.n_points == 19347
    assert out.sum() == round(0.02 * scan.n_points)
    # gross range errors are far from their surface point; stray points have no face
    d = np.linalg.norm(np.asarray(scan.points) - np.asarray(truth.true_points), axis=1)
    face = np.asarray(truth.face)
    gross = out & (face >= 0)
    assert gross.sum() > 0.3 * out.sum() and (face[out] == -1).sum() > 0.3 * out.sum()
    assert d[gross].min() >= 0.02 - 1e-12


def test_normals_estimated_from_points(default_scan, subject):
    v, f, _, _ = subject
    scan, truth = default_scan
    n = np.asarray(scan.normals)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
    inl = ~np.asarray(truth.is_outlier)
    _, fn, _ = _face_geometry(v, f)
    cosang = np.sum(n[inl] * fn[np.asarray(truth.face)[inl]], axis=1)
    assert np.median(cosang) > np.cos(np.deg2rad(10.0))
    assert (cosang < 0).mean() < 0.01  # oriented outwards almost everywhere


def test_landmark_noise_and_missing(subject):
    v, f, lm, names = subject
    cfg = registration.ScannerConfig(n_points=2000, landmark_sigma=0.0075, landmark_missing=0.3)
    errs, present = [], []
    for i in range(3):
        scan, _ = registration.simulate_scan(v, f, lm, names, cfg, key=jr.PRNGKey(10 + i))
        m = np.asarray(scan.landmark_mask)
        errs.append((np.asarray(scan.landmarks) - lm)[m])
        present.append(m)
        assert np.all(np.asarray(scan.landmarks)[~m] == 0)
        assert scan.landmark_names == tuple(names)
    e = np.concatenate(errs)
    assert 0.85 * 0.0075 < e.std() < 1.15 * 0.0075
    assert 0.55 < np.concatenate(present).mean() < 0.85


def test_density_and_extra_holes(subject, raw):
    v, f, lm, names = subject
    coarse = registration.ScannerConfig(n_points=None, spacing=0.008, outlier_fraction=0.0)
    s8, _ = registration.simulate_scan(v, f, lm, names, coarse, key=jr.PRNGKey(0))
    ratio = raw[0].n_points / s8.n_points
    assert 3.3 < ratio < 4.7  # hits scale with 1 / spacing^2
    holey, _ = registration.simulate_scan(
        v, f, lm, names, coarse.replace(hole_fraction=0.3), key=jr.PRNGKey(0)
    )
    assert abs(holey.n_points / s8.n_points - 0.7) < 0.005
    small, _ = registration.simulate_scan(
        v, f, lm, names, registration.ScannerConfig(n_points=5000), key=jr.PRNGKey(0)
    )
    assert small.n_points == 5000


def test_reproducible(subject):
    cfg = registration.ScannerConfig(n_points=3000)
    a, _ = registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(3))
    b, _ = registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(3))
    c, _ = registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(4))
    np.testing.assert_array_equal(np.asarray(a.points), np.asarray(b.points))
    assert not np.array_equal(np.asarray(a.points), np.asarray(c.points))


def test_simulate_scans_batches_and_pads(subject, body):
    v, f, _, names = subject
    pop = np.stack([v, v * 1.05])  # a taller subject has more hits
    cfg = registration.ScannerConfig(n_points=None, spacing=0.012)
    scans, truths = registration.simulate_scans(
        pop, f, body.landmark_index, names, cfg, progress=False, key=jr.PRNGKey(0)
    )
    P = scans.points.shape[1]
    assert scans.points.shape == (2, P, 3) and truths.face.shape == (2, P)
    counts = np.asarray(scans.point_mask).sum(1)
    assert counts.max() == P and counts.min() < P
    i = int(np.argmin(counts))
    pad = ~np.asarray(scans.point_mask[i])
    assert (np.asarray(truths.face[i])[pad] == -1).all()
    # padding repeats real points of the same scan
    real = {tuple(p) for p in np.asarray(scans.points[i])[~pad]}
    assert all(tuple(p) in real for p in np.asarray(scans.points[i])[pad])
    registration.check_scan(scans)
    with pytest.raises(ValueError, match="`n_points`"):
        registration.pad_scans([registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(0))[0]], 5)
    with pytest.raises(ValueError, match="`scans`"):
        registration.pad_scans([])


@pytest.mark.bad_input
def test_config_and_input_errors(subject):
    v, f, lm, names = subject
    with pytest.raises(ValueError, match="`noise_sigma`"):
        registration.ScannerConfig(noise_sigma=-0.001)
    with pytest.raises(ValueError, match="`normal_source`"):
        registration.ScannerConfig(normal_source="magic")
    with pytest.raises(ValueError, match="`hole_fraction`"):
        registration.ScannerConfig.hard(hole_fraction=2.0)
    hard = registration.ScannerConfig.hard()
    assert (hard.hole_fraction, hard.noise_sigma, hard.outlier_fraction, hard.landmark_sigma) == (
        0.3,
        0.002,
        0.05,
        0.01,
    )
    with pytest.raises(ValueError, match="`vertices`.*metres"):
        registration.simulate_scan(v * 1000, f, lm * 1000, names, key=jr.PRNGKey(0))
    with pytest.raises(ValueError, match="`landmark_names`"):
        registration.simulate_scan(v, f, lm, names[:3], key=jr.PRNGKey(0))
    with pytest.raises(ValueError, match="`vertices`"):
        registration.simulate_scan(v[:, :2], f, lm, names, key=jr.PRNGKey(0))
    with pytest.raises(ValueError, match="`config`"):
        registration.simulate_scan(v, f, lm, names, {"noise_sigma": 0.001}, key=jr.PRNGKey(0))


def _scan(points, normals=None, mask=None, names=("a", "b")):
    p = jnp.asarray(points)
    n = (
        jnp.asarray(normals)
        if normals is not None
        else jnp.tile(jnp.array([0.0, 0.0, 1.0]), (p.shape[0], 1))
    )
    m = jnp.ones(p.shape[0], bool) if mask is None else jnp.asarray(mask)
    return registration.Scan(
        p, n, m, jnp.zeros((len(names), 3)), jnp.ones(len(names), bool), tuple(names)
    )


@pytest.mark.bad_input
def test_check_scan_errors():
    rng = np.random.default_rng(0)
    body_pts = rng.uniform([-0.3, -0.2, -0.85], [0.3, 0.2, 0.85], (500, 3))
    registration.check_scan(_scan(body_pts))
    with pytest.raises(ValueError, match="empty"):
        registration.check_scan(_scan(body_pts, mask=np.zeros(500, bool)))
    with pytest.raises(ValueError, match="too few points"):
        registration.check_scan(_scan(body_pts[:50]))
    bad = body_pts.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"`scan.points` contains NaN"):
        registration.check_scan(_scan(bad))
    with pytest.raises(ValueError, match="millimetres"):
        registration.check_scan(_scan(body_pts * 1000))
    with pytest.raises(ValueError, match="`scan.normals` must be unit"):
        registration.check_scan(_scan(body_pts, normals=np.ones((500, 3))))
    with pytest.raises(ValueError, match="must be a bodyprior.registration.Scan"):
        registration.check_scan(body_pts)
    with pytest.raises(ValueError, match="`normals` must have the shape"):
        _scan(body_pts, normals=np.ones((499, 3)))
    with pytest.raises(ValueError, match="`landmark_names`"):
        z = jnp.zeros((500, 3))
        registration.Scan(z, z, jnp.ones(500, bool), jnp.zeros((2, 3)), jnp.ones(2, bool), ("a",))


# --------------------------------------------------------------------------------------------------
# IO
# --------------------------------------------------------------------------------------------------

_LND = """SUBJECT_ID = test.ply
SCAN_TYPE  = NO TYPE
AUX_LAND = 4
STANDARD =
AUX =
 1   0   1   45.05   33.25  -25.88  518.00 Sellion
 2 -999 -999   0.00    0.00    0.00    0.00 Rt. Infraorbitale
 3   0   3   85.81   64.56  -40.78  494.00 Rt. Metacarpal Phal. V
 4   0  54  166.04   41.08  167.24 -554.00 Rt. Femoral Lateral Epicn 
END =
 5   0   5    1.00    1.00    1.00    1.00 Lt. Tragion
"""


def test_read_lnd_caesar_format(tmp_path):
    p = tmp_path / "s.lnd"
    p.write_text(_LND)
    names, pos = registration.read_lnd(p)
    assert names == (
        "Sellion",
        "Rt. Infraorbitale",
        "Rt. Metacarpal Phal. V",
        "Rt. Femoral Lateral Epicn",
    )
    np.testing.assert_allclose(pos[0], [0.03325, -0.02588, 0.518])
    assert np.isnan(pos[1]).all()
    np.testing.assert_allclose(pos[3], [0.04108, 0.16724, -0.554])
    with pytest.raises(ValueError, match="no landmark line"):
        (tmp_path / "e.lnd").write_text("AUX =\nEND =\n")
        registration.read_lnd(tmp_path / "e.lnd")
    with pytest.raises(ValueError, match="does not exist"):
        registration.read_lnd(tmp_path / "nope.lnd")


@pytest.mark.parametrize("ext", [".ply", ".obj"])
def test_scan_round_trip(tmp_path, default_scan, ext):
    scan, _ = default_scan
    p, lp = tmp_path / f"s{ext}", tmp_path / "s.lnd"
    registration.write_scan(p, scan, landmarks_path=lp)
    back, info = registration.read_scan(p, landmarks_path=lp, return_info=True)
    tol = 1e-12 if ext == ".ply" else 1e-8
    np.testing.assert_allclose(np.asarray(back.points), np.asarray(scan.points), atol=tol)
    np.testing.assert_allclose(np.asarray(back.normals), np.asarray(scan.normals), atol=1e-8)
    np.testing.assert_array_equal(np.asarray(back.landmark_mask), np.asarray(scan.landmark_mask))
    m = np.asarray(scan.landmark_mask)
    np.testing.assert_allclose(
        np.asarray(back.landmarks)[m], np.asarray(scan.landmarks)[m], atol=1e-6
    )
    assert back.landmark_names == scan.landmark_names
    assert info["units"] == "m" and info["normals"] == "file" and info["landmark_units"] == "mm"


def test_read_scan_units_and_normals(tmp_path, subject, default_scan):
    v, f, lm, names = subject
    # A mesh scan and landmarks in millimetres: detected, converted, normals from the faces.
    bp.write_ply(tmp_path / "mm.ply", v * 1000.0, f)
    registration.write_lnd(tmp_path / "mm.lnd", names, lm)  # .lnd is always millimetres
    scan, info = registration.read_scan(
        tmp_path / "mm.ply", landmarks_path=tmp_path / "mm.lnd", return_info=True
    )
    assert info["units"] == "mm" and info["scale"] == 0.001 and info["normals"] == "mesh"
    np.testing.assert_allclose(np.asarray(scan.points), v, atol=1e-6)
    assert np.asarray(scan.landmark_mask).all()
    np.testing.assert_allclose(np.asarray(scan.landmarks), lm, atol=1e-6)
    # A point cloud without normals (here a simulated scan, in mm) gets estimated outward normals.
    scan, truth = default_scan
    bp.write_ply(tmp_path / "pc.ply", np.asarray(scan.points) * 1000.0)
    pc, info = registration.read_scan(tmp_path / "pc.ply", units="mm", return_info=True)
    assert info["normals"] == "estimated"
    np.testing.assert_allclose(np.asarray(pc.points), np.asarray(scan.points), atol=1e-6)
    _, fn, _ = _face_geometry(v, f)
    inl = ~np.asarray(truth.is_outlier)
    cos = np.sum(np.asarray(pc.normals)[inl] * fn[np.asarray(truth.face)[inl]], axis=1)
    assert (cos > 0).mean() > 0.97
    sub = registration.read_scan(tmp_path / "pc.ply", units="mm", n_points=4000, seed=1)
    assert sub.n_points == 4000
    # Sizes that are neither metres nor millimetres are refused, naming `units`.
    bp.write_ply(tmp_path / "cm.ply", v * 100.0)
    with pytest.raises(ValueError, match="`units`"):
        registration.read_scan(tmp_path / "cm.ply")
    assert registration.read_scan(tmp_path / "cm.ply", units="cm").n_points == v.shape[0]
    with pytest.raises(ValueError, match="`units` must be"):
        registration.read_scan(tmp_path / "cm.ply", units="inch")


def test_read_scan_errors(tmp_path):
    (tmp_path / "empty.ply").write_text("")
    with pytest.raises(ValueError, match="empty"):
        registration.read_scan(tmp_path / "empty.ply")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv nan 1 1\nv 0 1.7 0\n")
    with pytest.raises(ValueError, match="NaN"):
        registration.read_scan(tmp_path / "nan.obj")
    rng = np.random.default_rng(0)
    bp.write_ply(tmp_path / "few.ply", rng.uniform(0, 1.7, (40, 3)))
    with pytest.raises(ValueError, match="too few points"):
        registration.read_scan(tmp_path / "few.ply", units="m")
    with pytest.raises(ValueError, match=r"\.ply or \.obj"):
        registration.write_scan(tmp_path / "x.xyz", _scan(rng.uniform(-0.8, 0.8, (200, 3))))


# --------------------------------------------------------------------------------------------------
# Robustness of the registration on hard scans (issue §8)
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tmpl():
    return registration.registration_template()


@pytest.fixture(scope="module")
def size_space(tmpl):
    """A one-component space (body size) that contains the rest template exactly."""
    v = jnp.asarray(tmpl.vertices, jnp.float64)
    c = v.mean(0)
    meshes = jnp.stack([c + (v - c) * s for s in (0.95, 1.0, 1.05)])
    return sscape.learn(meshes, tmpl.faces, n_components=1, rig=tmpl.rig)


def test_registration_survives_hard_scans(subject, tmpl, size_space):
    """30 % holes, 2 mm noise, 5 % outliers, 10 mm landmark noise, 15 % landmarks missing: the
    S-SCAPE fit and NRD finish, and stay close to the ground truth (the scanned body is the
    template). NRD without the head rule (made for CAESAR's dummy heads)."""
    cfg = registration.ScannerConfig.hard()
    scan, truth = registration.simulate_scan(*subject, cfg, key=jr.PRNGKey(5))
    assert 0.7 < float(np.asarray(scan.landmark_mask).mean()) < 0.95
    sol = sscape.fit_sscape(
        size_space, scan, tmpl, config=sscape.FitConfig(max_passes=3), throw=False
    )
    assert bool(sol.result == bp.RESULTS.successful)  # max passes count as success
    fit = sol.value
    gt = jnp.asarray(tmpl.vertices, jnp.float64)
    e_fit = np.asarray(registration.gt_error(fit.vertices, gt))
    assert np.isfinite(e_fit).all() and e_fit.mean() < 15.0, e_fit.mean()
    res = registration.nrd(
        fit.vertices, scan, tmpl, config=registration.NRDConfig(head_rule=False), throw=False
    )
    e_nrd = np.asarray(registration.gt_error(res.value.vertices, gt))
    # bounded, not garbage (measured: 12.3 mm mean; a failed registration is far beyond 20 mm)
    assert np.isfinite(e_nrd).all() and e_nrd.mean() < 15.0, e_nrd.mean()
    assert (e_nrd < 10.0).mean() > 0.5, (e_nrd < 10.0).mean()


@pytest.mark.bad_input
def test_registration_rejects_bad_scans(subject, tmpl, size_space):
    scan, _ = registration.simulate_scan(
        *subject, registration.ScannerConfig(n_points=500), key=jr.PRNGKey(6)
    )
    mm = eqx.tree_at(
        lambda s: (s.points, s.landmarks), scan, (scan.points * 1000, scan.landmarks * 1000)
    )
    nan = eqx.tree_at(lambda s: s.points, scan, scan.points.at[3, 0].set(jnp.nan))
    empty = eqx.tree_at(lambda s: s.point_mask, scan, jnp.zeros_like(scan.point_mask))
    init = jnp.asarray(tmpl.vertices, jnp.float64)
    for bad, msg in ((mm, "millimetres"), (nan, "NaN"), (empty, "empty")):
        with pytest.raises(ValueError, match=msg):
            sscape.fit_sscape(size_space, bad, tmpl)
        with pytest.raises(ValueError, match=msg):
            registration.nrd(init, bad, tmpl)


@pytest.mark.bad_input
def test_zero_point_scan_rejected_by_every_entry_point(subject, tmpl, size_space):
    """Regression: a scan with P = 0 points failed inside numpy ("cannot reshape array of size 0
    into shape (0,3)"); every entry point taking scans names the argument and what it expects."""
    scan, _ = registration.simulate_scan(
        *subject, registration.ScannerConfig(n_points=500), key=jr.PRNGKey(6)
    )
    zero = registration.Scan(
        jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros((0,), bool), scan.landmarks,
        scan.landmark_mask, scan.landmark_names,
    )  # fmt: skip
    zeros = jax.tree_util.tree_map(lambda x: x[None], zero)
    init = jnp.asarray(tmpl.vertices, jnp.float64)

    def msg(name):
        return rf"`{name}` is empty: no real points \(`{name}.points` has shape \(0, 3\)\); expect"

    calls = [
        ("scan", lambda: registration.check_scan(zero, min_points=1)),
        ("scan", lambda: sscape.fit_sscape(size_space, zero, tmpl)),
        ("scan", lambda: registration.nrd(init, zero, tmpl)),
        ("scan", lambda: registration.fitting_error(init, zero, faces=tmpl.faces)),
        ("front_scan", lambda: sscape.fit_depth(size_space, zero, scan, tmpl)),
    ]
    for name, call in calls:
        with pytest.raises(ValueError, match=msg(name)):
            call()
    batched = r"`scans` is empty: no real points \(`scans.points` has shape \(1, 0, 3\)\)"
    with pytest.raises(ValueError, match=batched):
        sscape.fit_sscape_batch(size_space, zeros, tmpl)
    with pytest.raises(ValueError, match=batched):
        registration.nrd_batch(init[None], zeros, tmpl)
    with pytest.raises(ValueError, match=r"`scans` is empty"):
        registration.fitting_error_batch(init[None], zeros, faces=tmpl.faces)
