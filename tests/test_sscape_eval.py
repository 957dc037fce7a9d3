"""Registration quality measures: the paper's fitting error, ground-truth error, cumulative curves
and figures (bodyprior/registration/_evaluate.py)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import pytest
from _toybody import tube_mesh

import bodyprior as bp
from bodyprior.registration import (
    THRESHOLDS_20MM,
    cumulative_curve,
    error_colormap_png,
    fitting_error,
    fitting_error_batch,
    gt_error,
    mean_vertex_error,
    plot_cumulative_curves,
)


class _Scan(NamedTuple):  # the three fields the measures read (duck-typed like bodyprior's Scan)
    points: np.ndarray
    normals: np.ndarray
    point_mask: np.ndarray


def _scene(seed=0):
    verts, faces = tube_mesh(12, 20, radius=0.1, height=1.0)
    normals = np.asarray(bp.vertex_normals(verts, faces))
    rng = np.random.default_rng(seed)
    n = verts.shape[0]
    # Scan points near the surface, some far away, some with flipped normals, plus padding.
    pts = verts[rng.integers(0, n, 3 * n)] + 0.01 * rng.standard_normal((3 * n, 3))
    nrm = normals[rng.integers(0, n, 3 * n)]
    nrm[::7] *= -1.0
    pts[5::11] += 0.2
    pad = 40
    pts = np.concatenate([pts, np.zeros((pad, 3))])
    nrm = np.concatenate([nrm, np.tile([[0.0, 0.0, 1.0]], (pad, 1))])
    mask = np.arange(len(pts)) < 3 * n
    return verts, faces, normals, _Scan(pts, nrm, mask)


def _brute(verts, normals, scan, max_dist, max_angle, compatible):
    pts, nrm, mask = scan
    cos_max = np.cos(np.deg2rad(max_angle))
    err, ok = np.zeros(len(verts)), np.zeros(len(verts), bool)
    for i, (v, n) in enumerate(zip(verts, normals)):
        d = np.linalg.norm(pts - v, axis=1)
        cand = mask & ((nrm @ n) >= cos_max) if compatible else mask
        if not cand.any():
            continue
        j = np.flatnonzero(cand)[np.argmin(d[cand])]
        ok[i] = d[j] <= max_dist and nrm[j] @ n >= cos_max
        err[i] = 1000 * d[j] if ok[i] else 0.0
    return err, ok


@pytest.mark.parametrize("search", ["nearest", "compatible"])
def test_fitting_error_matches_brute_force(search):
    verts, faces, normals, scan = _scene()
    fe = fitting_error(verts, scan, faces=faces, max_dist=0.02, search=search)
    err, ok = _brute(verts, normals, scan, 0.02, 60.0, search == "compatible")
    np.testing.assert_array_equal(np.asarray(fe.valid), ok)
    np.testing.assert_allclose(np.asarray(fe.error_mm), err, atol=1e-9)
    assert 0.2 < ok.mean() < 0.99  # both gates and passes are exercised
    assert not np.any(np.asarray(fe.nearest) >= int(scan.point_mask.sum()))  # never padding


def test_fitting_error_batch_equals_single():
    verts, faces, _, scan = _scene()
    shifted = verts + np.array([0.0, 0.0, 0.004])
    batch = _Scan(*(np.stack([a, a]) for a in scan))
    fb = fitting_error_batch(np.stack([verts, shifted]), batch, faces=faces)
    for k, v in enumerate((verts, shifted)):
        f1 = fitting_error(v, scan, faces=faces)
        np.testing.assert_allclose(np.asarray(fb.error_mm[k]), np.asarray(f1.error_mm), atol=1e-9)
        np.testing.assert_array_equal(np.asarray(fb.valid[k]), np.asarray(f1.valid))


def test_fitting_error_exact_on_own_vertices():
    verts, faces, normals, _ = _scene()
    scan = _Scan(verts, normals, np.ones(len(verts), bool))
    fe = fitting_error(verts, scan, faces=faces)
    assert bool(np.all(fe.valid)) and float(np.max(fe.error_mm)) < 1e-9


@pytest.mark.bad_input
def test_fitting_error_bad_input():
    verts, faces, normals, scan = _scene()
    with pytest.raises(ValueError, match="Scan"):
        fitting_error(verts, object(), faces=faces)
    with pytest.raises(ValueError, match=r"scan.normals"):
        fitting_error(verts, _Scan(scan.points, scan.normals[:-1], scan.point_mask), faces=faces)
    with pytest.raises(ValueError, match="no real points"):
        fitting_error(verts, _Scan(scan.points, scan.normals, scan.point_mask * False), faces=faces)
    with pytest.raises(ValueError, match="max_angle_deg"):
        fitting_error(verts, scan, faces=faces, max_angle_deg=200)
    with pytest.raises(ValueError, match="faces"):
        fitting_error(verts, scan)  # not the template's vertex count and no faces


@pytest.mark.bad_input
def test_gt_error_and_mean_vertex_error():
    a = np.zeros((2, 4, 3))
    b = a.copy()
    b[0, 1] = [0.003, 0.004, 0.0]
    b[1, 2, 2] = -0.01
    e = np.asarray(gt_error(a, b))
    np.testing.assert_allclose(e, [[0, 5, 0, 0], [0, 0, 10, 0]], atol=1e-12)
    valid = np.array([[True, True, True, False], [True, False, True, False]])
    np.testing.assert_allclose(mean_vertex_error(e, valid), [0, 5, 5, np.nan])
    with pytest.raises(ValueError, match="true_vertices"):
        gt_error(a, b[:, :3])


def test_cumulative_curve_matches_brute_force():
    rng = np.random.default_rng(1)
    e = rng.gamma(2.0, 4.0, (5, 300))
    valid = rng.random((5, 300)) > 0.1
    t = np.linspace(0, 50, 26)
    got = cumulative_curve(e, t, valid=valid)
    want = np.array([np.sum((e <= x) & valid) / e.size for x in t])
    np.testing.assert_allclose(got, want)
    got_ex = cumulative_curve(e, t, valid=valid, invalid="exclude")
    want_ex = np.array([np.sum((e <= x) & valid) / valid.sum() for x in t])
    np.testing.assert_allclose(got_ex, want_ex)
    assert np.all(np.diff(got) >= 0) and got_ex[-1] > got[-1]
    with pytest.raises(ValueError, match="invalid"):
        cumulative_curve(e, t, invalid="x")


def test_figures_written(tmp_path):
    verts, faces, _, scan = _scene()
    fe = fitting_error(verts + 0.003, scan, faces=faces)
    err = np.where(np.asarray(fe.valid), np.asarray(fe.error_mm), np.nan)
    p = tmp_path / "err.png"
    error_colormap_png(p, jnp.asarray(verts), faces, err, vmax=20.0, title="test")
    c = tmp_path / "cum.png"
    curve = cumulative_curve(fe.error_mm, valid=fe.valid)
    plot_cumulative_curves({"a": curve, "b": 0.5 * curve}, THRESHOLDS_20MM, c, inset=(5, 15))
    for f in (p, c):
        data = f.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and 5_000 < len(data) < 400_000
    with pytest.raises(ValueError, match="errors_mm"):
        error_colormap_png(p, verts, faces, err[:-1])


def test_reconstruction_error_held_out():
    from _toybody import make_toy_model

    from bodyprior.sscape import reconstruction_error

    model = make_toy_model(4)
    rng = np.random.default_rng(3)
    c = rng.normal(size=4)
    inside = np.asarray(model.shape_vertices(c))
    rot = np.asarray(bp.axis_angle_to_matrix(jnp.array([0.0, 0.2, 0.4])))
    moved = inside @ rot.T + np.array([0.3, 0.0, -0.1])
    outside = inside + 0.01 * rng.normal(size=inside.shape)
    e = reconstruction_error(model, np.stack([moved, outside]), [0, 2, 4]) / 1e3  # mm -> m
    assert e.shape == (2, 3)
    assert e[0, 2] < 1e-9 and e[0, 0] > 1e-3  # in the span: exact with all components
    assert np.all(np.diff(e[0]) <= 1e-12) and e[1, 2] > 5e-3  # noise off the span remains
    with pytest.raises(ValueError, match="n_components"):
        reconstruction_error(model, moved[None], [5])
