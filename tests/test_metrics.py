"""Pairwise distances, generative-model metrics (MMD / COV / 1-NNA / specificity / diversity) and
the DSPP joint limits, against brute-force NumPy references and known cases."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import bodyprior as bp

ORDER = "ZYX"
geo = functools.partial(bp.pose_geodesic_metric, order=ORDER)
geo_jit = jax.jit(geo)


def _np_mvd(a, b):
    return np.linalg.norm(a[:, None] - b[None], axis=-1).mean(-1)


def _np_geo(a, b):
    # scipy's upper-case (intrinsic) orders match bodyprior.euler_to_matrix.
    out = np.zeros((len(a), len(b)))
    for i in range(len(a)):
        for j in range(len(b)):
            ra = Rotation.from_euler(ORDER, a[i])
            rb = Rotation.from_euler(ORDER, b[j])
            out[i, j] = (ra.inv() * rb).magnitude().mean()
    return out


def _np_metrics(gen, ref, d, train=None):
    """Loop-by-loop reference implementation of the definitions."""
    s, r = len(gen), len(ref)
    dgr = np.array([[d(gen[i], ref[j]) for j in range(r)] for i in range(s)])
    mmd = np.mean([min(dgr[i, j] for i in range(s)) for j in range(r)])
    cov = len({int(np.argmin(dgr[i])) for i in range(s)}) / r
    items = [(x, 0) for x in gen] + [(x, 1) for x in ref]
    correct = 0.0
    for i, (x, lab) in enumerate(items):
        best_same = min(d(x, y) for k, (y, ly) in enumerate(items) if k != i and ly == lab)
        best_other = min(d(x, y) for y, ly in items if ly != lab)
        correct += 1.0 if best_same < best_other else (0.5 if best_same == best_other else 0.0)
    div = np.mean([d(gen[i], gen[j]) for i in range(s) for j in range(s) if i != j])
    out = dict(mmd=mmd, coverage=cov, one_nna=correct / len(items), diversity=div)
    if train is not None:
        out["specificity"] = np.mean([min(d(g, t) for t in train) for g in gen])
    return out


def test_pairwise_matches_numpy_both_metrics():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(7, 40, 3)), rng.normal(size=(5, 40, 3))
    got = bp.pairwise_distances(a, b, bp.mean_vertex_distance_metric, chunk_size=3)
    assert got.shape == (7, 5)
    np.testing.assert_allclose(got, _np_mvd(a, b), rtol=1e-12, atol=1e-12)

    p, q = rng.uniform(-2, 2, size=(4, 6, 3)), rng.uniform(-2, 2, size=(3, 6, 3))
    got = bp.pairwise_distances(p, q, geo, chunk_size=2)
    np.testing.assert_allclose(got, _np_geo(p, q), rtol=1e-9, atol=1e-10)


def test_geodesic_known_angles_and_nan_free_gradient():
    e = jnp.zeros((3, 3))
    # Joint 0 turned by 0.7 rad about Z (first ZYX angle), joint 2 by pi about X: mean (0.7+pi)/3.
    f = e.at[0, 0].set(0.7).at[2, 2].set(jnp.pi)
    np.testing.assert_allclose(geo_jit(e, f), (0.7 + np.pi) / 3, rtol=1e-12)
    # Tiny angles are resolved (arccos of the trace would give 0 or noise here).
    np.testing.assert_allclose(geo_jit(e, e.at[1, 1].set(1e-9)), 1e-9 / 3, rtol=1e-6)
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.uniform(-1, 1, (20, 3)))
    grad = jax.jit(jax.value_and_grad(geo))
    v, g = grad(x, x)
    assert float(v) == pytest.approx(0.0, abs=1e-7)
    assert np.all(np.isfinite(g))
    # Away from coincidence the gradient matches finite differences.
    y = x + 0.3
    _, g = grad(y, x)
    eps, k = 1e-6, (4, 1)
    fd = (geo_jit(y.at[k].add(eps), x) - geo_jit(y.at[k].add(-eps), x)) / (2 * eps)
    np.testing.assert_allclose(g[k], fd, rtol=1e-5)


def test_generative_metrics_match_bruteforce():
    rng = np.random.default_rng(2)
    gen, ref = rng.normal(size=(6, 10, 3)), rng.normal(size=(5, 10, 3)) + 0.1
    train = rng.normal(size=(4, 10, 3))
    got = bp.generative_metrics(gen, ref, bp.mean_vertex_distance_metric, train=train, chunk_size=4)
    want = _np_metrics(gen, ref, lambda x, y: np.linalg.norm(x - y, axis=-1).mean(), train)
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-12), k
    assert got["diversity_ref"] == pytest.approx(_np_mvd(ref, ref)[~np.eye(5, dtype=bool)].mean())
    assert all(isinstance(v, float) for v in got.values())


def test_known_cases():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(12, 8, 3))
    mvd = bp.mean_vertex_distance_metric
    # Memorisation: every item's nearest neighbour is its copy in the other set -> 1-NNA = 0.
    m = bp.generative_metrics(x, x, mvd, train=x)
    assert (m["one_nna"], m["mmd"], m["coverage"], m["specificity"]) == (0.0, 0.0, 1.0, 0.0)
    assert m["diversity"] == pytest.approx(m["diversity_ref"])
    # Disjoint, far-apart sets: perfectly separable, and every sample's nearest reference is the one
    # closest to the shifted cloud.
    far = x + np.array([50.0, 0.0, 0.0])
    m = bp.generative_metrics(far, x, mvd)
    assert m["one_nna"] == 1.0 and m["one_nna_gen"] == 1.0 and m["one_nna_ref"] == 1.0
    assert m["coverage"] <= 3 / 12 and m["mmd"] > 40.0
    # Complete ties (all items equal): each classification is a tie and counts 1/2.
    same = np.zeros((3, 8, 3))
    assert bp.generative_metrics(same, same, mvd)["one_nna"] == 0.5
    # Two independent samples of one distribution: 1-NNA near chance.
    a, b = rng.normal(size=(150, 2, 3)), rng.normal(size=(150, 2, 3))
    assert 0.4 < bp.generative_metrics(a, b, mvd, chunk_size=64)["one_nna"] < 0.6
    # Mode collapse (a tight cluster 0.3 away from one reference): one reference covered; only that
    # reference is misclassified (its nearest item is a sample), all samples are recognised.
    col = x[:1] + np.array([0.3, 0.0, 0.0]) + 1e-3 * rng.normal(size=(12, 8, 3))
    m = bp.generative_metrics(col, x, mvd)
    assert m["coverage"] == 1 / 12 and m["one_nna"] == pytest.approx(23 / 24)


@pytest.mark.bad_input
def test_metric_errors():
    a = np.zeros((3, 4, 3))
    mvd = bp.mean_vertex_distance_metric
    with pytest.raises(ValueError, match="`b` items must have shape"):
        bp.pairwise_distances(a, np.zeros((3, 5, 3)), mvd)
    with pytest.raises(ValueError, match="`a` must be a non-empty"):
        bp.pairwise_distances(np.zeros((0, 4, 3)), a, mvd)
    with pytest.raises(ValueError, match="`a` contains NaN"):
        bp.pairwise_distances(_nan(a), a, mvd)
    with pytest.raises(ValueError, match="`metric` must be a callable"):
        bp.pairwise_distances(a, a, "l2")
    with pytest.raises(ValueError, match="`metric` must return a scalar"):
        bp.pairwise_distances(a, a, lambda x, y: x - y)
    with pytest.raises(ValueError, match="`chunk_size` must be a positive int"):
        bp.pairwise_distances(a, a, mvd, chunk_size=0)
    with pytest.raises(ValueError, match="`gen` must hold at least 2"):
        bp.generative_metrics(a[:1], a, mvd)
    with pytest.raises(ValueError, match="`train` items must have shape"):
        bp.generative_metrics(a, a, mvd, train=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"`b` must have shape \(V, 3\)"):
        mvd(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="`order` must be one of"):
        bp.pose_geodesic_metric(np.zeros((2, 3)), np.zeros((2, 3)), order="xyz")


def _nan(a):
    a = a.copy()
    a[0, 0, 0] = np.nan
    return a


# --------------------------------------------------------------------------------------------------
# joint limits


def test_joint_limits_box_and_wraparound():
    rng = np.random.default_rng(4)
    n = 4000
    # Joint 0: middle angle in [-0.5, 0.8], outer angles in [-1, 1] / [0.2, 0.4].
    # Joint 1: first angle around +-pi (a range straddling the cut), others small.
    e = np.zeros((n, 2, 3))
    e[:, 0, 0] = rng.uniform(-1.0, 1.0, n)
    e[:, 0, 1] = rng.uniform(-0.5, 0.8, n)
    e[:, 0, 2] = rng.uniform(0.2, 0.4, n)
    t = np.pi + rng.uniform(-0.3, 0.3, n)
    e[:, 1, 0] = np.arctan2(np.sin(t), np.cos(t))  # in (-pi, pi]: both ends of the circle
    e[:, 1, 1:] = rng.uniform(-0.1, 0.1, (n, 2))
    lim = np.asarray(bp.dspp.joint_limits(e, quantile=0.0, order=ORDER))
    assert lim.shape == (2, 3, 2)
    np.testing.assert_allclose(lim[0], [[-1, 1], [-0.5, 0.8], [0.2, 0.4]], atol=5e-3)
    # One interval of width 0.6 around pi, not the whole circle.
    assert lim[1, 0, 1] - lim[1, 0, 0] == pytest.approx(0.6, abs=5e-3)
    assert np.cos(0.5 * (lim[1, 0, 0] + lim[1, 0, 1])) == pytest.approx(-1.0, abs=1e-4)
    # The training data themselves never violate the quantile-0 limits.
    assert bp.dspp.joint_limit_violation(e, lim, order=ORDER) == 0.0
    # 0.5% quantiles: narrower, and about 1 - (0.99)^6 of the training poses fall outside.
    lim_q = np.asarray(bp.dspp.joint_limits(e, order=ORDER))
    assert np.all(lim_q[..., 0] >= lim[..., 0]) and np.all(lim_q[..., 1] <= lim[..., 1])
    frac = bp.dspp.joint_limit_violation(e, lim_q, order=ORDER)
    assert 0.03 < frac < 0.09

    inside = np.zeros((4, 2, 3))
    inside[:, 0, 2] = 0.3
    inside[:, 1, 0] = np.pi
    bad = inside.copy()
    bad[1, 0, 1] = 1.0  # middle angle of joint 0 above 0.8
    bad[3, 1, 0] = 0.0  # joint 1 turned away from pi
    assert bp.dspp.joint_limit_violation(inside, lim, order=ORDER) == 0.0
    assert bp.dspp.joint_limit_violation(bad, lim, order=ORDER) == 0.5
    # The other Euler triple of the same rotations gives the same verdict (canonicalisation).
    alt = inside + np.array([np.pi, 0.0, np.pi])
    alt[..., 1] = np.pi - inside[..., 1]
    assert bp.dspp.joint_limit_violation(alt, lim, order=ORDER) == 0.0


@pytest.mark.bad_input
def test_joint_limit_errors():
    e = np.zeros((5, 20, 3))
    with pytest.raises(ValueError, match="`quantile` must lie in"):
        bp.dspp.joint_limits(e, quantile=0.5, order=ORDER)
    with pytest.raises(ValueError, match="`euler` must have shape"):
        bp.dspp.joint_limits(np.zeros((5, 20)), order=ORDER)
    with pytest.raises(ValueError, match="at least 2 poses"):
        bp.dspp.joint_limits(e[:1], order=ORDER)
    lim = bp.dspp.joint_limits(e + np.linspace(0, 0.1, 5)[:, None, None], order=ORDER)
    with pytest.raises(ValueError, match=r"`limits` must have shape \(20, 3, 2\)"):
        bp.dspp.joint_limit_violation(e, lim[:10], order=ORDER)
    with pytest.raises(ValueError, match="lower <= upper"):
        bp.dspp.joint_limit_violation(e, np.flip(np.asarray(lim), -1), order=ORDER)


@pytest.mark.bad_input
def test_hausdorff_distance_points_and_faces():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((50, 3))
    b = a.copy()
    assert bp.hausdorff_distance(a, b) == 0.0
    b[7] += np.array([0.0, 0.0, 2.0])  # one point moved far: the Hausdorff distance sees it
    h = bp.hausdorff_distance(a, b)
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)  # brute force
    assert np.isclose(h, max(d.min(1).max(), d.min(0).max()))
    assert h >= np.linalg.norm(a - b[7], axis=1).min() > 0.5
    # relative: divided by b's bounding-box diagonal
    diag = np.linalg.norm(b.max(0) - b.min(0))
    assert np.isclose(bp.hausdorff_distance(a, b, relative=True), h / diag)
    # face centroids join the samples: a triangle vs its own vertices differs by its centroid
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.array([[0, 1, 2]])
    far = np.concatenate([tri, [[1.0 / 3, 1.0 / 3, 0.0]]])  # the vertices and the centroid
    assert np.isclose(bp.hausdorff_distance(far, tri, faces_b=f), 0.0)
    assert bp.hausdorff_distance(far, tri) > 0.4
    with pytest.raises(ValueError, match="faces_b"):
        bp.hausdorff_distance(a, tri, faces_b=np.array([[0, 1, 5]]))
    with pytest.raises(ValueError, match="a"):
        bp.hausdorff_distance(a[:, :2], b)
