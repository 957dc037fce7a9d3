"""The grid radius search (`bodyprior.registration._grid`) equals brute force, including points on
the
search sphere, queries outside the grid and grids clamped at `_GRID_AXIS` cells per axis."""

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from bodyprior.registration._grid import _GRID_AXIS, nearest_within  # noqa: E402


def _brute(queries, points, mask, radius, qn=None, pn=None, cos_max=None):
    out = np.full(len(queries), -1)
    for i, q in enumerate(queries):
        d = np.linalg.norm(points - q, axis=1)
        ok = mask & (d <= radius)
        if cos_max is not None:
            unknown = np.sum(pn * pn, axis=1) < 0.25
            ok &= ((pn @ qn[i]) >= cos_max) | unknown
        if ok.any():
            out[i] = np.flatnonzero(ok)[np.argmin(d[ok])]
    return out


def _check(queries, points, mask, radius, **kw):
    got = np.asarray(nearest_within(queries, points, mask, radius, **kw))
    ref = _brute(queries, points, mask, radius, kw.get("query_normals"),
                 kw.get("point_normals"), kw.get("cos_max"))  # fmt: skip
    np.testing.assert_array_equal(got >= 0, ref >= 0)
    hit = ref >= 0
    d_got = np.linalg.norm(points[got[hit]] - queries[hit], axis=1)
    d_ref = np.linalg.norm(points[ref[hit]] - queries[hit], axis=1)
    np.testing.assert_allclose(d_got, d_ref, rtol=0, atol=1e-12)  # ties may pick either point
    return hit.mean()


@pytest.mark.parametrize("clamped", [False, True])
def test_nearest_within_equals_brute_force(clamped):
    rng = np.random.default_rng(3)
    radius = 0.02
    points = rng.uniform(-0.1, 0.1, (3000, 3))
    queries = rng.uniform(-0.13, 0.13, (400, 3))  # some outside the points' box
    # Isolated queries (6 radii apart) whose only points lie just inside and just outside their
    # search sphere, in random directions: the ball culling must keep the one and drop the other.
    g = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lone = 0.2 + 6 * radius * g + rng.uniform(-radius, radius, g.shape)
    u, w = (rng.normal(size=lone.shape) for _ in range(2))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    points = np.concatenate(
        [points, lone + radius * (1 - 1e-9) * u, lone + radius * (1 + 1e-7) * w]
    )
    queries = np.concatenate([queries, lone])
    if clamped:  # one far point makes the grid longer than _GRID_AXIS cells
        points = np.concatenate([points, [[radius / 2 * 3 * _GRID_AXIS, 0.0, 0.0]]])
        queries = np.concatenate([queries, points[-1:] + 0.001])
    mask = rng.random(len(points)) > 0.1
    mask[3000:] = True
    frac = _check(queries, points, mask, radius)
    assert 0.2 < frac < 1.0
    normals = rng.normal(size=points.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[::13] = 0.0  # unknown normals match any direction
    qn = rng.normal(size=queries.shape)
    qn /= np.linalg.norm(qn, axis=1, keepdims=True)
    frac = _check(queries, points, mask, radius, query_normals=qn, point_normals=normals,
                  cos_max=0.5)  # fmt: skip
    assert 0.1 < frac < 1.0
