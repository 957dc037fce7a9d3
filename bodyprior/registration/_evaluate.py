"""Registration quality measures (Pishchulin et al. 2017, §4.2) and their figures.

Two per-vertex errors of a fitted template mesh, both reported in **millimetres**:

- [`bodyprior.registration.fitting_error`][]: the paper's measure, which needs no ground truth. For
  each
  fitted template vertex the nearest scan point is found; if it lies within `max_dist` (50 mm) and
  the vertex normal and the scan point's normal differ by at most `max_angle_deg` (60 deg), the
  Euclidean vertex-to-point distance is the vertex's error, else the vertex has no error (`valid` is
  False). The nearest neighbour is searched over *all* real scan points and gated afterwards, as the
  paper words it ("If this neighbor [is] not further ... than 50 mm and its face normals do not
  deviate more than 60 deg, the ... distance is computed"); `search="compatible"` instead takes the
  nearest point among the compatible ones (what the fitters' data terms use).
- [`bodyprior.registration.gt_error`][]: distance of each fitted vertex to its true corresponding
  vertex,
  which only a simulated scan can provide (CAESAR has no ground-truth correspondence).

Aggregations: [`bodyprior.registration.cumulative_curve`][] (proportion of vertices below each
threshold,
the paper's Figs. 1a/2a, 0-20 mm and 0-50 mm) and [`bodyprior.registration.mean_vertex_error`][]
(the
per-vertex error averaged over scans, Fig. 1b), with figure helpers
[`bodyprior.registration.plot_cumulative_curves`][] (matplotlib Agg) and
[`bodyprior.registration.error_colormap_png`][] (the per-vertex error on the body).

Kernels are written for one mesh and one scan; the `*_batch` forms `vmap` them over a leading axis.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._aot import aot_filter_jit
from .._geometry import vertex_normals
from .._validate import check_array, is_tracer
from ._grid import nearest_within
from ._scan import _empty_scan_message

__all__ = [
    "THRESHOLDS_20MM",
    "THRESHOLDS_50MM",
    "FittingError",
    "cumulative_curve",
    "error_colormap_png",
    "fitting_error",
    "fitting_error_batch",
    "gt_error",
    "mean_vertex_error",
    "plot_cumulative_curves",
]

THRESHOLDS_20MM = np.linspace(0.0, 20.0, 41)
"""Default thresholds of the paper's two cumulative plots, millimetres."""
THRESHOLDS_50MM = np.linspace(0.0, 50.0, 51)


class FittingError(NamedTuple):
    """Per-vertex fitting error of one registration (leading batch axis for the batched form)."""

    error_mm: Float[Array, " V"]
    """Distance to the nearest scan point, millimetres (0 where not `valid`)."""
    valid: Bool[Array, " V"]
    """Whether the nearest scan point passed the distance and normal gates."""
    nearest: Int[Array, " V"]
    """Index of that scan point."""


# --------------------------------------------------------------------------------------------------
# Input handling


def _scan_arrays(scan, name: str = "scan", batched: bool = False):
    """`(points, normals, point_mask)` of a `Scan`-like object (duck-typed: H-scan's `Scan`)."""
    for field in ("points", "normals", "point_mask"):
        if not hasattr(scan, field):
            raise ValueError(
                f"`{name}` must be a bodyprior.registration.Scan (with `points`, `normals`, "
                f"`point_mask`), got {type(scan).__name__} without `{field}`."
            )
    lead = ("N",) if batched else ()
    dims: dict[str, int] = {}
    check_array(scan.points, f"{name}.points", lead + ("P", 3), dims=dims)
    check_array(scan.normals, f"{name}.normals", lead + ("P", 3), dims=dims)
    mask = scan.point_mask
    if not hasattr(mask, "shape"):
        mask = np.asarray(mask)
    if tuple(mask.shape) != tuple(np.shape(scan.points))[:-1]:
        raise ValueError(
            f"`{name}.point_mask` must have shape {tuple(np.shape(scan.points))[:-1]}, got "
            f"{tuple(mask.shape)}."
        )
    if 0 in tuple(np.shape(scan.points)):
        raise ValueError(_empty_scan_message(name, np.shape(scan.points)))
    if not is_tracer(mask) and not batched and not bool(np.any(np.asarray(mask))):
        raise ValueError(_empty_scan_message(name, np.shape(scan.points), masked=True))
    return jnp.asarray(scan.points), jnp.asarray(scan.normals), jnp.asarray(mask, dtype=bool)


def _default_faces(n_vertices: int):
    # The default registration template's faces are the decimated topology's (cheap to load; the
    # template itself also fits a joint regressor, which is not needed here).
    from ..assets._decimate import load_decimated

    vertex_map, faces = load_decimated()
    if len(vertex_map) != n_vertices:
        raise ValueError(
            f"`faces` is required for meshes with {n_vertices} vertices (the default registration "
            f"template has {len(vertex_map)})."
        )
    return faces


def _check_options(max_dist, max_angle_deg, search):
    if not (np.isfinite(max_dist) and max_dist > 0):
        raise ValueError(f"`max_dist` must be a positive distance in metres, got {max_dist!r}.")
    if not 0.0 <= float(max_angle_deg) <= 180.0:
        raise ValueError(f"`max_angle_deg` must lie in [0, 180], got {max_angle_deg!r}.")
    if search not in ("nearest", "compatible"):
        raise ValueError(f"`search` must be 'nearest' or 'compatible', got {search!r}.")


# --------------------------------------------------------------------------------------------------
# Kernels (one mesh, one scan)


def _fitting_error_kernel(
    vertices, normals, points, point_normals, point_mask, max_dist, cos_max, search: str
):
    # Exact radius search on a grid (`_grid.py`): a nearest point beyond `max_dist` fails the
    # gate anyway, so the nearest point within `max_dist` decides the paper's measure.
    if search == "nearest":
        idx = nearest_within(vertices, points, point_mask, max_dist)
        found = idx >= 0
        idx = jnp.maximum(idx, 0)
        cos = jnp.sum(normals * point_normals[idx], axis=-1)
        ok = found & (cos >= cos_max)
    else:
        idx = nearest_within(
            vertices, points, point_mask, max_dist, query_normals=normals,
            point_normals=point_normals, cos_max=cos_max,
        )  # fmt: skip
        ok = idx >= 0
        idx = jnp.maximum(idx, 0)
    sq = jnp.sum((vertices - points[idx]) ** 2, axis=-1)
    dist_mm = 1000.0 * jnp.sqrt(jnp.maximum(sq, 0.0))
    return FittingError(jnp.where(ok, dist_mm, 0.0), ok, idx)


@aot_filter_jit
def _fitting_error_jit(vertices, faces, points, pnormals, pmask, max_dist, cos_max, search):
    normals = vertex_normals(vertices, faces)
    return _fitting_error_kernel(
        vertices, normals, points, pnormals, pmask, max_dist, cos_max, search
    )


@eqx.filter_jit
def _fitting_error_batch_jit(
    vertices, faces, points, pnormals, pmask, max_dist, cos_max, search
):
    def one(v, p, pn, pm):
        n = vertex_normals(v, faces)
        return _fitting_error_kernel(v, n, p, pn, pm, max_dist, cos_max, search)

    return jax.vmap(one)(vertices, points, pnormals, pmask)


# --------------------------------------------------------------------------------------------------
# Public API


def _fitting_error_args(vertices, scan, faces, max_dist, max_angle_deg, search, batched: bool):
    """Host checks shared by `fitting_error(_batch)`; the jitted kernels' positional arguments."""
    dims: dict[str, int] = {}
    lead = ("N",) if batched else ()
    check_array(vertices, "vertices", lead + ("V", 3), dims=dims)
    name = "scans" if batched else "scan"
    pts, nrm, mask = _scan_arrays(scan, name, batched=batched)
    if batched and pts.shape[0] != dims["N"]:
        raise ValueError(f"`scans` must hold {dims['N']} scans (one per mesh), got {pts.shape[0]}.")
    _check_options(max_dist, max_angle_deg, search)
    faces = _default_faces(dims["V"]) if faces is None else faces
    check_array(faces, "faces", (None, 3), integer=True)
    v = jnp.asarray(vertices)
    cos_max = float(np.cos(np.deg2rad(max_angle_deg)))
    return (
        v, jnp.asarray(faces, jnp.int32), pts.astype(v.dtype), nrm.astype(v.dtype), mask,
        float(max_dist), cos_max, search,
    )  # fmt: skip


def fitting_error(
    vertices: Float[ArrayLike, "V 3"],
    scan,
    *,
    faces: Int[ArrayLike, "F 3"] | None = None,
    max_dist: float = 0.05,
    max_angle_deg: float = 60.0,
    search: str = "nearest",
) -> FittingError:
    """The paper's fitting error of one registered mesh against its scan (§4.2), millimetres.

    For each vertex of the fitted mesh, the nearest real scan point (`point_mask` True) is found
    (exact radius search on a uniform grid: a nearest point beyond `max_dist` fails the gate
    anyway); the vertex is `valid` when that point is within `max_dist` and the angle
    between the mesh's area-weighted vertex normal and the point's normal is at most
    `max_angle_deg`. With `search="compatible"` the nearest point *among the normal-compatible
    ones* is taken instead (then only the distance gate can fail). Jitted (compiles once per shape
    and option set); cost ~`O(V + P)` for surface-like clouds.

    **Arguments:**

    - `vertices`: fitted mesh `(V, 3)`, metres, in the scan's frame.
    - `scan`: a [`bodyprior.registration.Scan`][] (`points (P, 3)`, unit `normals (P, 3)`,
      `point_mask (P,)`).
    - `faces`: triangles `(F, 3)` of the mesh, for its normals; default: the registration
      template's faces (then `V` must be its vertex count).
    - `max_dist`: distance gate, metres (paper: 50 mm).
    - `max_angle_deg`: normal gate, degrees (paper: 60).
    - `search`: `"nearest"` (paper, default) or `"compatible"`.

    **Returns:** a [`bodyprior.registration.FittingError`][] `(error_mm (V,), valid (V,), nearest
    (V,))`.
    """
    args = _fitting_error_args(vertices, scan, faces, max_dist, max_angle_deg, search, False)
    return _fitting_error_jit(*args)


def fitting_error_batch(
    vertices: Float[ArrayLike, "N V 3"],
    scans,
    *,
    faces: Int[ArrayLike, "F 3"] | None = None,
    max_dist: float = 0.05,
    max_angle_deg: float = 60.0,
    search: str = "nearest",
) -> FittingError:
    """[`bodyprior.registration.fitting_error`][] for `N` meshes and their `N` scans (vmapped).

    `scans` is a batched `Scan` (leaves with a leading `N` axis, padded point clouds); split very
    large batches on the host. **Returns:** a `FittingError` whose
    fields have a leading `N` axis.
    """
    args = _fitting_error_args(vertices, scans, faces, max_dist, max_angle_deg, search, True)
    return _fitting_error_batch_jit(*args)


def gt_error(
    vertices: Float[ArrayLike, "*batch V 3"], true_vertices: Float[ArrayLike, "*batch V 3"]
) -> Float[Array, "*batch V"]:
    """Per-vertex distance to the true corresponding vertex, millimetres.

    Both meshes are in the same frame and vertex order (e.g. a registration in the scan frame and
    the restricted ground-truth body, [`bodyprior.registration.RegistrationTemplate.restrict`][]).
    Works
    on one mesh `(V, 3)` or any leading batch shape.

    **Returns:** `1000 * ||vertices - true_vertices||` per vertex, shape `(*batch, V)`.
    """
    if not hasattr(vertices, "shape"):
        vertices = np.asarray(vertices)
    if not hasattr(true_vertices, "shape"):
        true_vertices = np.asarray(true_vertices)
    if vertices.ndim < 2 or vertices.shape[-1] != 3:
        raise ValueError(f"`vertices` must have shape (*batch, V, 3), got {tuple(vertices.shape)}.")
    if tuple(true_vertices.shape) != tuple(vertices.shape):
        raise ValueError(
            f"`true_vertices` must have the shape of `vertices` {tuple(vertices.shape)}, got "
            f"{tuple(true_vertices.shape)}."
        )
    check_array(vertices, "vertices", (None,) * vertices.ndim)
    check_array(true_vertices, "true_vertices", (None,) * vertices.ndim)
    d = jnp.asarray(vertices) - jnp.asarray(true_vertices)
    return 1000.0 * jnp.sqrt(jnp.sum(d * d, axis=-1))


def cumulative_curve(
    errors_mm,
    thresholds_mm=THRESHOLDS_20MM,
    *,
    valid=None,
    invalid: str = "fail",
) -> np.ndarray:
    """Proportion of vertices whose error is at most each threshold (paper Figs. 1a, 2a).

    All vertices of all meshes are pooled. Vertices with `valid == False` (no compatible scan point)
    count as failures at every threshold with `invalid="fail"` (default: a registration cannot gain
    by drifting away from the scan), or are left out with `invalid="exclude"`.

    **Arguments:**

    - `errors_mm`: per-vertex errors, any shape (e.g. `(N, V)`), millimetres.
    - `thresholds_mm`: thresholds `(T,)`, millimetres; default 0-20 mm in 0.5 mm steps
      (`THRESHOLDS_50MM` is 0-50 mm in 1 mm steps).
    - `valid`: optional bool mask shaped like `errors_mm`.
    - `invalid`: `"fail"` or `"exclude"`.

    **Returns:** NumPy `(T,)` proportions in `[0, 1]` (multiply by 100 for the paper's percent).
    """
    e = np.asarray(errors_mm, dtype=np.float64)
    t = np.asarray(thresholds_mm, dtype=np.float64)
    if t.ndim != 1 or t.size < 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"`thresholds_mm` must be a finite 1-D array, got shape {t.shape}.")
    if invalid not in ("fail", "exclude"):
        raise ValueError(f"`invalid` must be 'fail' or 'exclude', got {invalid!r}.")
    if valid is None:
        ok = np.isfinite(e)
    else:
        ok = np.asarray(valid, dtype=bool)
        if ok.shape != e.shape:
            raise ValueError(
                f"`valid` must have the shape of `errors_mm` {e.shape}, got {ok.shape}."
            )
        ok = ok & np.isfinite(e)
    if np.any(e[ok] < 0):
        raise ValueError("`errors_mm` must be non-negative.")
    vals = np.sort(e[ok].ravel())
    n = vals.size if invalid == "exclude" else e.size
    if n == 0:
        return np.zeros_like(t)
    return np.searchsorted(vals, t, side="right") / n


def mean_vertex_error(errors_mm, valid=None) -> np.ndarray:
    """Per-vertex error averaged over meshes (paper Fig. 1b), millimetres.

    **Arguments:**

    - `errors_mm`: `(N, V)` per-vertex errors.
    - `valid`: optional `(N, V)` mask; each vertex is averaged over the meshes where it is valid.

    **Returns:** NumPy `(V,)`; NaN for a vertex never valid.
    """
    e = np.asarray(errors_mm, dtype=np.float64)
    if e.ndim != 2:
        raise ValueError(f"`errors_mm` must have shape (N, V), got {e.shape}.")
    ok = np.ones_like(e, bool) if valid is None else np.asarray(valid, bool)
    if ok.shape != e.shape:
        raise ValueError(f"`valid` must have shape {e.shape}, got {ok.shape}.")
    cnt = ok.sum(0)
    s = np.where(ok, e, 0.0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, s / np.maximum(cnt, 1), np.nan)


# --------------------------------------------------------------------------------------------------
# Figures


def plot_cumulative_curves(
    curves: Mapping[str, np.ndarray],
    thresholds_mm,
    path: str | os.PathLike,
    *,
    title: str | None = None,
    xlabel: str = "error threshold [mm]",
    ylabel: str = "vertices below threshold [%]",
    inset: tuple[float, float] | None = None,
) -> None:
    """Plots cumulative error curves (proportion in `[0, 1]`, shown in percent) to a PNG.

    **Arguments:**

    - `curves`: label -> `(T,)` proportions (e.g. from
      [`bodyprior.registration.cumulative_curve`][]).
    - `thresholds_mm`: the shared thresholds `(T,)`.
    - `path`: output PNG (written atomically).
    - `title`, `xlabel`, `ylabel`: texts.
    - `inset`: optional `(lo, hi)` threshold range for a close-up inset (the paper's Fig. 2a).
    """
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .._io import atomic_open

    t = np.asarray(thresholds_mm, dtype=np.float64)
    if not curves:
        raise ValueError("`curves` must hold at least one curve.")
    for k, c in curves.items():
        if np.shape(c) != t.shape:
            raise ValueError(f"curve {k!r} must have shape {t.shape}, got {np.shape(c)}.")
    fig = Figure(figsize=(5.6, 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for label, c in curves.items():
        ax.plot(t, 100.0 * np.asarray(c), label=label, lw=1.6)
    ax.set_xlim(t[0], t[-1])
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(loc="lower right", fontsize=8)
    if inset is not None:
        lo, hi = float(inset[0]), float(inset[1])
        sel = (t >= lo) & (t <= hi)
        if sel.sum() >= 2:
            ins = ax.inset_axes((0.42, 0.32, 0.33, 0.33))
            ymin = min(100.0 * np.asarray(c)[sel].min() for c in curves.values())
            for c in curves.values():
                ins.plot(t[sel], 100.0 * np.asarray(c)[sel], lw=1.2)
            ins.set_xlim(lo, hi)
            ins.set_ylim(max(ymin - 1.0, 0.0), 100.0)
            ins.tick_params(labelsize=6)
            ins.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def error_colormap_png(
    path: str | os.PathLike,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    errors_mm,
    *,
    vmax: float = 20.0,
    views: Sequence = ("front", "back"),
    title: str | None = None,
    cmap: str = "jet",
    size: tuple[int, int] = (400, 200),
) -> None:
    """Per-vertex error (mm) as a colour map on a body, front and back side by side, with a colour
    bar (paper Fig. 1b). NaN errors (never-valid vertices) are drawn at `vmax`.

    **Arguments:**

    - `path`: output PNG (written atomically).
    - `vertices`, `faces`: the body to draw on (e.g. the template or a fitted mesh), metres.
    - `errors_mm`: `(V,)` per-vertex error, millimetres.
    - `vmax`: top of the colour range, millimetres (bottom is 0).
    - `views`: views of [`bodyprior.render_vertex_colors`][] placed side by side.
    - `title`, `cmap`, `size`: figure title, colormap, `(height, width)` of each view.
    """
    from .._render import figure_with_colorbar, mesh_bounds, render_vertex_colors

    v = np.asarray(check_array(vertices, "vertices", ("V", 3)), dtype=np.float64)
    e = np.asarray(errors_mm, dtype=np.float64)
    if e.shape != (v.shape[0],):
        raise ValueError(f"`errors_mm` must have shape ({v.shape[0]},), got {e.shape}.")
    if not (np.isfinite(vmax) and vmax > 0):
        raise ValueError(f"`vmax` must be positive, got {vmax!r}.")
    e = np.where(np.isfinite(e), e, vmax)
    box = mesh_bounds(v)
    imgs = [
        render_vertex_colors(
            v, faces, e, cmap=cmap, vmin=0.0, vmax=vmax, view=view, size=size, fit=box
        )
        for view in views
    ]
    figure_with_colorbar(
        np.concatenate(imgs, axis=1), vmin=0.0, vmax=vmax, cmap=cmap, label="error [mm]",
        title=title, path=path,
    )  # fmt: skip
