"""Exact fixed-radius nearest-point searches on a uniform grid (the registration's correspondences).

Used by NRD's correspondence rules (`_nrd.py`) and the paper's fitting error (`_evaluate.py`). The
scan points are bucketed once per call into cells (sorted int32 cell keys); a query scans the
cells that meet its search ball of `reach` cells, and the candidate runs of all queries, in tiles
of a few slots of one query, are processed in fixed-size chunks, so the work is the number of
candidates, not queries x points. A `rule` callable decides which candidates a query accepts and
returns their squared distances.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

# Grid axes are clamped to this many cells (keys stay < 2^31 in int32); clamping only merges far
# cells, which adds candidates but never loses one, so the radius search stays exact.
_GRID_AXIS = 1024
# Cells per search radius: a radius-r search scans the (2 _REACH + 1)³ cells of size r / _REACH
# around the query (cube side 2.5 r instead of 3 r for cells of size r).
_REACH = 2


class _Grid(eqx.Module):
    lo: Float[Array, " 3"]
    cell: Float[Array, ""]
    dims: Int[Array, " 3"]
    skey: Int[Array, " P"]  # sorted cell keys (masked points last)
    order: Int[Array, " P"]  # point index of each sorted key


def _grid_build(points: Float[Array, "P 3"], mask: Bool[Array, " P"], cell) -> _Grid:
    inf = jnp.asarray(jnp.inf, points.dtype)
    cell = jnp.asarray(cell, points.dtype)
    # One empty cell of margin below and above every point, so that the clamped three-cell rows of
    # a query outside the grid still cover every point within one cell of it.
    lo = jnp.min(jnp.where(mask[:, None], points, inf), axis=0) - cell
    ijk = jnp.clip(jnp.floor((points - lo) / cell), 0, _GRID_AXIS - 2).astype(jnp.int32)
    dims = jnp.max(jnp.where(mask[:, None], ijk, 0), axis=0) + 2
    key = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])
    key = jnp.where(mask, key, jnp.iinfo(jnp.int32).max)
    order = jnp.argsort(key).astype(jnp.int32)
    return _Grid(lo, cell, dims.astype(jnp.int32), key[order], order)


def _rows(reach: int) -> np.ndarray:
    r = range(-reach, reach + 1)
    return np.array([(dy, dz) for dz in r for dy in r], np.int32)


# Candidate slots examined per step of the search loop (bounds memory, not the result), in tiles of
# _WIDTH slots of one query (4 measured fastest of 2/4/8/16 on NRD's searches).
_CHUNK = 1 << 14
_WIDTH = 4


def _grid_search(
    grid: _Grid, centres: Float[Array, "Q 3"], active: Bool[Array, " Q"], rule, reach: int
) -> Int[Array, " Q"]:
    """For each active query, the point minimising `rule`'s squared distance among the points it
    accepts, searched in the cells within `reach` cells (distance `reach * cell`) of `centres[q]`;
    `-1` where there is none. Exact when every accepted point lies within that distance.

    Only the cells that meet the ball of radius `reach * cell` are scanned (each row of cells is
    trimmed to the ball's chord; about 84 of the 125 cells of the cube at `reach = 2`), except on a
    grid clamped at `_GRID_AXIS`, whose far cells are merged and scanned as the whole cube. The
    candidate runs of each query (one contiguous run of sorted keys per row of cells) are laid end
    to end and cut into tiles of `_WIDTH` slots; the tiles of all queries are processed `_CHUNK`
    slots at a time, so the work is the total number of candidates (plus the padding of each
    query's last tile), not queries x the longest run."""
    nq = centres.shape[0]
    if nq == 0:
        return jnp.zeros((0,), jnp.int32)
    rel = (centres - grid.lo) / grid.cell  # query position in cell units
    ijk = jnp.clip(jnp.floor(rel), 0, grid.dims - 1).astype(jnp.int32)
    rows = jnp.asarray(_rows(reach))
    nr = rows.shape[0]
    y = ijk[:, 1:2] + rows[None, :, 0]
    z = ijk[:, 2:3] + rows[None, :, 1]
    inside = (y >= 0) & (y < grid.dims[1]) & (z >= 0) & (z < grid.dims[2]) & active[:, None]
    # Distance (cells) from the query to each row's y-z box; rows beyond the ball are skipped and
    # the others trimmed to the chord. A small slack keeps points on the sphere despite rounding.
    ball = jnp.where(jnp.any(grid.dims >= _GRID_AXIS), jnp.inf, reach * (1.0 + 1e-6))
    dy = jnp.maximum(jnp.maximum(y - rel[:, 1:2], rel[:, 1:2] - (y + 1)), 0.0)
    dz = jnp.maximum(jnp.maximum(z - rel[:, 2:3], rel[:, 2:3] - (z + 1)), 0.0)
    d2 = dy**2 + dz**2
    inside = inside & (d2 <= ball**2)
    half = jnp.sqrt(jnp.maximum(ball**2 - d2, 0.0))
    xa = jnp.clip(jnp.floor(rel[:, 0:1] - half), -1, _GRID_AXIS).astype(jnp.int32)
    xb = jnp.clip(jnp.floor(rel[:, 0:1] + half), -1, _GRID_AXIS).astype(jnp.int32)
    base = grid.dims[0] * (y + grid.dims[1] * z)
    x0 = jnp.maximum(jnp.maximum(ijk[:, 0:1] - reach, 0), xa)
    x1 = jnp.minimum(jnp.minimum(ijk[:, 0:1] + reach, grid.dims[0] - 1), xb)
    inside = inside & (x1 >= x0)
    start = jnp.searchsorted(grid.skey, base + x0, side="left").astype(jnp.int32)
    end = jnp.searchsorted(grid.skey, base + x1, side="right").astype(jnp.int32)
    count = jnp.where(inside, end - start, 0)  # (Q, R)
    # Query-major tiles of _WIDTH slots: the slots of query q are its rows' runs laid end to end,
    # cut into ceil(n_q / _WIDTH) tiles. A tile's query is found by one search per tile, the row of
    # each of its slots by comparing with the query's (R,) running counts; each tile reduces its
    # slots to one candidate before the scatter into the per-query best.
    W = _WIDTH
    lc = jnp.cumsum(count, axis=1)
    lex = lc - count
    n = lc[:, -1]
    ntile = (n + W - 1) // W
    tcum = jnp.cumsum(ntile)
    total = tcum[-1]
    last = grid.order.shape[0] - 1
    tc = _CHUNK // W
    tiles = jnp.arange(tc, dtype=jnp.int32)
    lanes = jnp.arange(W, dtype=jnp.int32)

    def body(state):
        k, best, best_d2 = state
        t = k * tc + tiles
        q = jnp.minimum(jnp.searchsorted(tcum, t, side="right"), nq - 1).astype(jnp.int32)
        j = (t - (tcum[q] - ntile[q]))[:, None] * W + lanes[None, :]  # slot within query (tc, W)
        lcq = lc[q]  # (tc, R) running counts of each tile's query
        r = jnp.minimum(jnp.sum(lcq[:, None, :] <= j[:, :, None], axis=-1), nr - 1)
        off = j - jnp.take_along_axis(lex[q], r, axis=1)
        pi = grid.order[jnp.clip(jnp.take_along_axis(start[q], r, axis=1) + off, 0, last)]
        qb = jnp.broadcast_to(q[:, None], (tc, W))
        ok, d2 = rule(qb.reshape(-1), pi.reshape(-1))
        use = (t < total)[:, None] & (j < lcq[:, -1:]) & ok.reshape(tc, W)
        d2 = jnp.where(use, d2.reshape(tc, W), jnp.inf)
        a = jnp.argmin(d2, axis=1)
        dmin = jnp.take_along_axis(d2, a[:, None], axis=1)[:, 0]
        pmin = jnp.take_along_axis(pi, a[:, None], axis=1)[:, 0]
        best_d2 = best_d2.at[q].min(dmin)
        hit = jnp.isfinite(dmin) & (dmin == best_d2[q])
        best = best.at[jnp.where(hit, q, nq)].set(pmin, mode="drop")
        return k + 1, best, best_d2

    init = (
        jnp.zeros((), jnp.int32),
        jnp.full(nq, -1, jnp.int32),
        jnp.full(nq, jnp.inf, centres.dtype),
    )
    _, best, _ = jax.lax.while_loop(lambda s: s[0] * tc < total, body, init)
    return best


class _WithinRule(eqx.Module):
    """Accepts every point within `sqrt(r2)` of the query (the plain nearest neighbour)."""

    points: Float[Array, "P 3"]
    queries: Float[Array, "Q 3"]
    r2: float

    def __call__(self, qi, pi):
        d2 = jnp.sum((self.queries[qi] - self.points[pi]) ** 2, axis=-1)
        return d2 <= self.r2, d2


class _CompatibleRule(eqx.Module):
    """Accepts points within `sqrt(r2)` whose normal is at most `acos(cos_max)` from the query's
    (scan normals shorter than 0.5 are unknown and match any direction)."""

    points: Float[Array, "P 3"]
    normals: Float[Array, "P 3"]
    queries: Float[Array, "Q 3"]
    qnormals: Float[Array, "Q 3"]
    cos_max: float
    r2: float

    def __call__(self, qi, pi):
        n = self.normals[pi]
        d2 = jnp.sum((self.queries[qi] - self.points[pi]) ** 2, axis=-1)
        dot = jnp.sum(n * self.qnormals[qi], axis=-1)
        unknown = jnp.sum(n * n, axis=-1) < 0.25
        return (d2 <= self.r2) & ((dot >= self.cos_max) | unknown), d2


def nearest_within(
    queries: Float[ArrayLike, "Q 3"],
    points: Float[ArrayLike, "P 3"],
    mask: Bool[ArrayLike, " P"],
    radius: float,
    *,
    query_normals: Float[ArrayLike, "Q 3"] | None = None,
    point_normals: Float[ArrayLike, "P 3"] | None = None,
    cos_max: float | None = None,
) -> Int[Array, " Q"]:
    """Index of the nearest real point within `radius` of every query (`-1` where none); with
    normals and `cos_max`, the nearest *normal-compatible* one. Exact; one grid per call."""
    queries, points, mask = jnp.asarray(queries), jnp.asarray(points), jnp.asarray(mask)
    if cos_max is not None:
        query_normals, point_normals = jnp.asarray(query_normals), jnp.asarray(point_normals)
    grid = _grid_build(points, mask, radius / _REACH)
    active = jnp.ones(queries.shape[0], bool)
    if cos_max is None:
        rule = _WithinRule(points, queries, radius**2)
    else:
        rule = _CompatibleRule(points, point_normals, queries, query_normals, cos_max, radius**2)
    return _grid_search(grid, queries, active, rule, _REACH)
