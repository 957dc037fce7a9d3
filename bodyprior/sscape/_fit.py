"""Fitting an S-SCAPE space to a raw scan (the humanshape "init" stage, sscape.md §2).

Per scan, in one jitted call:

1. **Similarity** from the landmarks present in the scan (Umeyama/Horn on the model mean's landmark
   vertices; humanshape `rigidAlignTemplate2Scan.m`).
2. **Pose from landmarks**, shape fixed (humanshape `fitPose.m`): Levenberg-Marquardt over the joint
   rotations, the global translation and (optionally) the scale.
3. **Alternating pose and shape fits** to compatible nearest neighbours (humanshape
   `fitPoseShape.m`): each pass fits the pose (+ translation, scale) to the current correspondences,
   recomputes them, fits the shape (+ scale), recomputes them, and stops when the data term changes
   by less than `rtol` (relative) or the mean distance by less than `atol_mm` (humanshape's 1e-3 mm
   rule), or after `max_passes` passes. A pass that raises the data term is undone and ends the
   loop, so the recorded data term never increases. The pass loop is a `lax.while_loop`.

Correspondences (humanshape, sscape.md §2.5): template -> scan only (each model vertex takes a scan
point; sscape.md describes no scan -> template term at this stage). A pair is compatible when the
normals are within `max_angle_deg` (60 degrees); unlike humanshape, the search returns the *nearest
compatible* point over the whole cloud (a masked argmin, not "the nearest point, dropped if its
normal disagrees"), so a vertex next to a thin structure seen from the other side still finds the
right surface. Pairs farther than `max_dist` (humanshape has no gate at this stage; NRD uses 50 mm)
and hand vertices (`template.hand_mask`, "do not register open to closed hands") are invalid.

Objective (units chosen so that the numbers read as millimetres): with `d_i` the distance of vertex
`i` to its compatible scan point and `E` the non-hand vertices,

    data term = (1 / |E|) sum_{i in E} min(d_i, max_dist)^2                    [mm^2]

i.e. a truncated quadratic, so dropping a vertex never lowers it (a vertex without a valid partner
costs `max_dist^2`). The solvers minimise its valid part, in least-squares form (humanshape sums
unsquared distances; squared distances give a Gauss-Newton structure and the gate removes the
outliers an L1 sum would tolerate), plus

- `pose_prior * |theta_j|^2` per non-root joint (mm^2 per rad^2; keeps joints without data, e.g.
  the toes' twist, at rest),
- `shape_prior * |c|^2` (mm^2 per standard deviation^2; 0 = humanshape),
- the optional `shape_residual(rest_vertices)` vector (the DSPP prior hook), added unscaled.

Shape coefficients `c` are in standard deviations and bounded to `[-b, b]` (`b = coeff_bound`, 3 as
in humanshape) by the smooth reparameterisation `c = b tanh(u / b)` (identity near 0, unconstrained
`u`), not by clipping.

Parameters: `pose` `(J, 3)` axis-angle per joint (local, world-aligned rest axes; NaN-free at zero,
`bodyprior.axis_angle_to_matrix`), the global similarity (rotation from step 1; translation and log
scale refined; joint 0's rotation carries the orientation correction). The fitted mesh is exactly
`similarity.apply(evaluate(model, coeffs, pose)[0])`. Joints named in `frozen_joints` (default: the
wrists, fingers and thumbs, as humanshape fixes the wrists) stay at their initial rotation.

Solver: optimistix `LevenbergMarquardt` with forward-mode Jacobians (~100 pose and ~20 shape
unknowns against ~20k residuals) and the damped normal equations solved by Cholesky. Float64 is
required (`jax_enable_x64`): the normal equations square the condition number.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._geometry import vertex_normals
from .._kinematics import Similarity, umeyama
from .._solution import RESULTS, Solution, _check
from .._store import register_type
from .._validate import as_device_array, check_array, is_tracer, named_preset
from ..registration._grid import nearest_within
from ..registration._scan import Scan, check_scan
from ..registration._template import RegistrationTemplate
from ._model import SScapeModel, evaluate, shape_vertices

__all__ = [
    "FitConfig",
    "SScapeFit",
    "compatible_correspondences",
    "fit_similarity",
    "fit_sscape",
    "fit_sscape_batch",
]

# Joints frozen by default: wrists and fingers (humanshape fixes the wrists; hand vertices carry no
# data term, so these rotations are unobservable apart from hand landmarks).
_HAND_WORDS = ("Hand", "Thumb", "Finger")
_MM = 1000.0  # residuals are scaled to millimetres so that solver tolerances read in mm


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Settings of [`bodyprior.sscape.fit_sscape`][] (hashable; static under jit).

    **Fields** (lengths in metres, thresholds of the pass loop in millimetres):

    - `max_passes`: maximum number of pose/shape passes (default 10).
    - `schedule`: `"joint"` (default: per pass one solve over pose and shape together) or
      `"alternate"` (humanshape: per pass a pose solve, new correspondences, a shape solve). On a
      simulated scan of a body inside the space, alternation was still moving after 10 passes
      (4.1 mm mean true error) where the joint schedule converged in 7 (1.4 mm), 2.4x faster:
      pose, scale and shape are strongly coupled and alternation zig-zags between them.
    - `rtol`: stop when the data term changes by at most this fraction in one pass (1e-3).
    - `atol_mm`: or when the mean valid distance changes by at most this many mm (1e-3, humanshape).
    - `max_dist`: distance gate for correspondences (0.05 m).
    - `max_angle_deg`: maximum angle between model and scan normals (60, humanshape).
    - `point_to_plane`: fraction `a` of the data residual measured along the scan normal:
      `a (n_q . (x - q))^2 + (1 - a) |x - q|^2` (0.9; 0 = humanshape's point-to-point).
    - `coeff_bound`: shape coefficients are bounded to `[-b, b]` standard deviations (3).
    - `fit_scale`: refine the global scale (humanshape does); else keep the landmark similarity's.
    - `pose_prior`: weight of `|theta_j|^2` per non-root joint, mm^2 per rad^2 (100; humanshape's
      code uses 1).
    - `shape_prior`: weight of `|c|^2`, mm^2 per squared standard deviation (0.0 = humanshape).
    - `landmark_weight`: weight of the mean squared landmark distance in the surface passes
      (0.3; 0.0 = humanshape: landmarks are used only for the similarity and the first pose). On
      the simulated laser scans, `landmark_weight=0.3` with `pose_prior=100` cut the fit's mean
      true-correspondence error from 10.4 to 7.1 mm (vertices slide along featureless limbs
      without them; `docs/results_sscape.md`), so these are the defaults;
      `FitConfig.preset("humanshape")` restores humanshape's 0 and 1.
    - `frozen_joints`: names of joints kept at their initial rotation; `None` = every joint whose
      name contains "Hand", "Thumb" or "Finger".
    - `landmark_steps`, `pose_steps`, `shape_steps`: Levenberg-Marquardt step limits per solve.
    - `solver_rtol`, `solver_atol`: Levenberg-Marquardt tolerances (parameters in m/rad, objective
      in mm^2).
    - `exclude_hands`: exclude `template.hand_mask` vertices from the data term (True, humanshape).
    """

    max_passes: int = 10
    schedule: str = "joint"
    rtol: float = 1e-3
    atol_mm: float = 1e-3
    max_dist: float = 0.05
    max_angle_deg: float = 60.0
    point_to_plane: float = 0.9
    coeff_bound: float = 3.0
    fit_scale: bool = True
    pose_prior: float = 100.0
    shape_prior: float = 0.0
    landmark_weight: float = 0.3
    frozen_joints: tuple[str, ...] | None = None
    landmark_steps: int = 100
    pose_steps: int = 20
    shape_steps: int = 20
    solver_rtol: float = 1e-6
    solver_atol: float = 1e-6
    exclude_hands: bool = True

    @classmethod
    def preset(cls, name: str, **overrides) -> FitConfig:
        """A named configuration, with any field overridden by keyword.

        - `"default"`: `FitConfig()`, the measured best on simulated laser scans (landmark term 0.3,
          pose prior 100; `docs/results_sscape.md`).
        - `"humanshape"`: humanshape's fit (`landmark_weight=0`, `pose_prior=1`): landmarks only
          for the similarity and the first pose.
        """
        table = {"default": {}, "humanshape": dict(landmark_weight=0.0, pose_prior=1.0)}
        return named_preset(cls, table, name, overrides)

    def __post_init__(self):
        for name in ("max_passes", "landmark_steps", "pose_steps", "shape_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"`FitConfig.{name}` must be a positive int, got {v!r}.")
        for name in ("rtol", "atol_mm", "max_dist", "coeff_bound", "solver_rtol", "solver_atol"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"`FitConfig.{name}` must be a positive number, got {v!r}.")
        for name in ("pose_prior", "shape_prior", "landmark_weight"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"`FitConfig.{name}` must be a non-negative number, got {v!r}.")
        if self.schedule not in ("alternate", "joint"):
            raise ValueError(
                f"`FitConfig.schedule` must be 'alternate' or 'joint', got {self.schedule!r}."
            )
        if not 0.0 <= self.point_to_plane < 1.0:
            raise ValueError(
                f"`FitConfig.point_to_plane` must lie in [0, 1), got {self.point_to_plane!r}."
            )
        if not 0.0 < self.max_angle_deg <= 180.0:
            raise ValueError(
                f"`FitConfig.max_angle_deg` must lie in (0, 180], got {self.max_angle_deg!r}."
            )
        if self.frozen_joints is not None:
            if isinstance(self.frozen_joints, str) or not all(
                isinstance(n, str) for n in self.frozen_joints
            ):
                raise ValueError(
                    "`FitConfig.frozen_joints` must be a tuple of joint names or None."
                )
            object.__setattr__(self, "frozen_joints", tuple(self.frozen_joints))


class SScapeFit(eqx.Module):
    """The fitted body of [`bodyprior.sscape.fit_sscape`][]: the `value` of its
    [`bodyprior.Solution`][] (batched: every leaf has a leading scan axis).

    **Fields** (V vertices, J joints, K components):

    - `coeffs`: shape coefficients, shape `(K,)`, standard deviations, within `±coeff_bound`.
    - `pose`: local joint rotations, axis-angle, shape `(J, 3)`, radians.
    - `similarity`: global [`bodyprior.Similarity`][] from the model frame to the scan frame.
    - `vertices`: fitted posed mesh in the scan frame, shape `(V, 3)`, metres;
      `similarity.apply(evaluate(model, coeffs, pose)[0])`.
    - `rest_vertices`: shaped, unposed mesh in the model frame, shape `(V, 3)`, metres.
    """

    coeffs: Float[Array, " K"]
    pose: Float[Array, "J 3"]
    similarity: Similarity
    vertices: Float[Array, "V 3"]
    rest_vertices: Float[Array, "V 3"]


# --------------------------------------------------------------------------------------------------
# Correspondences
# --------------------------------------------------------------------------------------------------


register_type(SScapeFit, "bodyprior.sscape.SScapeFit")


def _compatible_search(
    queries: Float[Array, "Q 3"],
    query_normals: Float[Array, "Q 3"],
    points: Float[Array, "P 3"],
    point_normals: Float[Array, "P 3"],
    point_mask: Bool[Array, " P"],
    cos_min: float,
    chunk_size: int,
) -> tuple[Int[Array, " Q"], Bool[Array, " Q"]]:
    """Nearest scan point whose normal is within the angle, for every query (exact brute force).

    The search runs in float32 on coordinates centred at the cloud's mean (the pairwise squared
    distance is written coordinate by coordinate, so XLA fuses it into the argmin without
    materialising the `(chunk, P)` distance block and without the cancellation of the
    `|a|^2 + |b|^2 - 2ab` expansion). Scan normals of length < 0.5 (unknown) match any direction.
    Not differentiated (the caller recomputes distances from the chosen pairs).
    """
    queries = jax.lax.stop_gradient(queries)
    query_normals = jax.lax.stop_gradient(query_normals)
    m = point_mask.astype(points.dtype)
    centre = jnp.sum(points * m[:, None], 0) / jnp.maximum(jnp.sum(m), 1.0)
    p = (points - centre).astype(jnp.float32)
    pn = point_normals.astype(jnp.float32)
    unknown = jnp.sum(pn * pn, -1) < 0.25
    px, py, pz = p[:, 0], p[:, 1], p[:, 2]
    nx, ny, nz = pn[:, 0], pn[:, 1], pn[:, 2]
    inf = jnp.float32(jnp.inf)

    def one(args):
        q, qn = args
        q = q.astype(jnp.float32)
        qn = qn.astype(jnp.float32)
        d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
        cos = nx * qn[0] + ny * qn[1] + nz * qn[2]
        ok = point_mask & ((cos >= cos_min) | unknown)
        d2 = jnp.where(ok, d2, inf)
        i = jnp.argmin(d2)
        return i.astype(jnp.int32), d2[i] < inf

    q = queries - centre
    return jax.lax.map(one, (q, query_normals), batch_size=min(chunk_size, queries.shape[0]))


_compatible_search_jit = jax.jit(_compatible_search, static_argnums=(5, 6))


def _correspondences(verts, normals, scan_points, scan_normals, scan_mask, exclude, cfg):
    """(idx, weight, distance) of every vertex; weight 1 for a valid pair, else 0.

    The nearest compatible scan point within `cfg.max_dist` (exact grid radius search, the same as
    NRD's body rule): a nearer compatible point beyond the gate would be invalid anyway, so this is
    the brute-force rule "nearest compatible point, then gate" for every valid pair, at ~1/6 of its
    time (6,449 vertices x 19,347 points: 63 vs 407 ms). Invalid pairs get index 0."""
    cos_min = float(np.cos(np.deg2rad(cfg.max_angle_deg)))
    verts_s = jax.lax.stop_gradient(verts)
    found = nearest_within(
        verts_s,
        scan_points,
        scan_mask,
        cfg.max_dist,
        query_normals=jax.lax.stop_gradient(normals),
        point_normals=scan_normals,
        cos_max=cos_min,
    )
    valid = (found >= 0) & ~exclude
    idx = jnp.maximum(found, 0)
    diff = verts - scan_points[idx]
    sq = jnp.sum(diff * diff, -1)
    dist = jnp.sqrt(jnp.where(valid, sq, 0.0))
    return idx, valid.astype(verts.dtype), jax.lax.stop_gradient(dist)


def compatible_correspondences(
    verts: Float[ArrayLike, "V 3"],
    normals: Float[ArrayLike, "V 3"],
    scan: Scan,
    *,
    max_dist: float = 0.05,
    max_angle_deg: float = 60.0,
    exclude_mask: Bool[ArrayLike, " V"] | None = None,
) -> tuple[Int[Array, " V"], Float[Array, " V"]]:
    """Template -> scan correspondences: the nearest compatible scan point of every vertex.

    A scan point is compatible with vertex `i` when it is a real point (`scan.point_mask`) and the
    angle between its normal and the vertex normal is at most `max_angle_deg` (scan normals shorter
    than 0.5 count as unknown and match any direction). The search is exact (a grid radius search
    of `max_dist`, in the inputs' dtype): a vertex whose nearest point faces the other way takes
    the nearest point that does not, instead of being dropped. The pair is valid when a compatible
    point exists within `max_dist` and the vertex is not in `exclude_mask`.

    Jittable and vmappable (one mesh and one scan; `jax.vmap` for batches); not differentiated
    (recompute distances from `scan.points[idx]` for a differentiable residual).

    **Arguments:**

    - `verts`: model vertices, shape `(V, 3)`, metres, in the scan's frame.
    - `normals`: their unit normals, shape `(V, 3)` (e.g. `bodyprior.vertex_normals`).
    - `scan`: a [`bodyprior.registration.Scan`][] (one scan).
    - `max_dist`: distance gate, metres (default 0.05).
    - `max_angle_deg`: normal compatibility angle, degrees (default 60).
    - `exclude_mask`: optional bool `(V,)`, vertices never valid (e.g. `template.hand_mask`).

    **Returns:** `(idx, weight)`: `(V,)` int32 index into `scan.points` (0 for invalid pairs) and
    `(V,)` float weight, 1.0 for a valid pair and 0.0 otherwise.
    """
    if not isinstance(scan, Scan):
        raise ValueError(
            f"`scan` must be a bodyprior.registration.Scan, got {type(scan).__name__}."
        )
    dims: dict[str, int] = {}
    check_array(verts, "verts", ("V", 3), dims=dims)
    check_array(normals, "normals", ("V", 3), dims=dims)
    check_array(scan.points, "scan.points", ("P", 3), dims=dims, finite=False)
    check_array(scan.normals, "scan.normals", ("P", 3), dims=dims, finite=False)
    check_array(scan.point_mask, "scan.point_mask", ("P",), dims=dims, finite=False)
    if exclude_mask is None:
        exclude_mask = jnp.zeros((dims["V"],), bool)
    check_array(exclude_mask, "exclude_mask", ("V",), dims=dims, finite=False)
    if not (np.isfinite(max_dist) and max_dist > 0):
        raise ValueError(f"`max_dist` must be a positive number of metres, got {max_dist!r}.")
    if not 0.0 < max_angle_deg <= 180.0:
        raise ValueError(f"`max_angle_deg` must lie in (0, 180], got {max_angle_deg!r}.")
    verts = jnp.asarray(verts)
    cfg = FitConfig(max_dist=float(max_dist), max_angle_deg=float(max_angle_deg))
    idx, w, _ = _correspondences(
        verts,
        jnp.asarray(normals, verts.dtype),
        jnp.asarray(scan.points, verts.dtype),
        jnp.asarray(scan.normals, verts.dtype),
        jnp.asarray(scan.point_mask, bool),
        jnp.asarray(exclude_mask, bool),
        cfg,
    )
    return idx, w


# --------------------------------------------------------------------------------------------------
# Similarity from landmarks
# --------------------------------------------------------------------------------------------------


def _umeyama_masked(src, dst, mask):
    mask = mask.astype(src.dtype)
    return umeyama(src * mask[:, None], jnp.where(mask[:, None] > 0, dst, 0.0), weights=mask)


def fit_similarity(template_landmarks: Float[ArrayLike, "L 3"], scan: Scan) -> Similarity:
    """Similarity `x -> s R x + t` taking template landmarks onto the scan's present landmarks.

    Umeyama/Horn least squares over the landmarks with `scan.landmark_mask` True (humanshape
    `rigidAlignTemplate2Scan.m`; the scan is not moved, the template is).

    **Arguments:**

    - `template_landmarks`: template positions of the scan's landmarks, in the scan's landmark
      order, shape `(L, 3)`, metres (e.g. `model.mean[vertex_of_each_scan_landmark]`).
    - `scan`: a [`bodyprior.registration.Scan`][] (one scan) with at least 4 present landmarks.

    **Returns:** a [`bodyprior.Similarity`][].
    """
    if not isinstance(scan, Scan):
        raise ValueError(
            f"`scan` must be a bodyprior.registration.Scan, got {type(scan).__name__}."
        )
    dims: dict[str, int] = {}
    check_array(template_landmarks, "template_landmarks", ("L", 3), dims=dims)
    check_array(scan.landmarks, "scan.landmarks", ("L", 3), dims=dims, finite=False)
    check_array(scan.landmark_mask, "scan.landmark_mask", ("L",), dims=dims, finite=False)
    if not is_tracer(scan.landmark_mask):
        n = int(np.asarray(scan.landmark_mask).sum())
        if n < 4:
            raise ValueError(f"`scan` must have at least 4 present landmarks, got {n}.")
    src = jnp.asarray(template_landmarks)
    return _umeyama_masked(
        src, jnp.asarray(scan.landmarks, src.dtype), jnp.asarray(scan.landmark_mask)
    )


# --------------------------------------------------------------------------------------------------
# The fit kernel (one scan; pure, jittable, vmappable)
# --------------------------------------------------------------------------------------------------


class _Static(eqx.Module):
    """Host-prepared, per-template constants of a fit (arrays are leaves, counts static)."""

    lm_vertex: Int[Array, " L"]  # template vertex of every scan landmark (0 if unknown)
    lm_known: Bool[Array, " L"]  # the template knows this landmark name
    exclude: Bool[Array, " V"]
    free: tuple[int, ...] = eqx.field(static=True)  # joints whose rotation is fitted


def _bounded(u, b):
    return b * jnp.tanh(u / b)


def _lm_solve(rtol: float, atol: float):
    """`solve(fn, y0, args, steps) -> (value, failed, num_steps)`: Levenberg-Marquardt, no throw.

    Normal equations + Cholesky: the unknowns are few (~100) and the residuals many (~20k); XLA's
    CPU QR of a 20k x 100 Jacobian costs ~60x more than forming and factoring `JᵀJ` (float64; the
    damping keeps it SPD). Running out of steps is not a failure (an iteration budget: the passes
    iterate anyway; `bodyprior._solution`)."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))

    def solve(fn, y0, args, steps):
        sol = optx.least_squares(fn, solver, y0, args, max_steps=steps, throw=False)
        ok = (sol.result == optx.RESULTS.successful) | (
            sol.result == optx.RESULTS.nonlinear_max_steps_reached
        )
        return sol.value, ~ok, sol.stats["num_steps"]

    return solve


def _pass_loop(
    step: Callable,
    measure: Callable,
    params0,
    corr0,
    term0: Float[Array, ""],
    mean0: Float[Array, ""],
    bad0: Bool[Array, ""],
    steps0: Int[Array, ""],
    *,
    max_passes: int,
    rtol: float,
    atol_mm: float,
    undo_worse: bool,
    dtype,
):
    """The pass loop shared by the S-SCAPE fit and the depth fit (a `lax.while_loop`).

    Each pass runs `step(params, corr) -> (params, failed, n_steps)` (the pass's Levenberg-Marquardt
    solves for fixed correspondences) and then `measure(params) -> (corr, data_term, mean_mm)`
    (new correspondences and the data term they give). The loop stops when the data term changes
    by at most `rtol` (relative) or the mean distance by at most `atol_mm`, after `max_passes`
    passes, or when a solve failed or the data term is not finite. With `undo_worse`, a pass that
    raised the data term is undone (parameters and correspondences) and ends the loop, so the
    recorded data term never increases.

    **Returns:** `(passes, params, corr, data_term (N,), mean_distance_mm (N,), converged,
    failed, n_steps)` with `N = max_passes + 1` (entry 0: `term0`; NaN after the last pass).
    """
    nan = jnp.full((max_passes + 1,), jnp.nan, dtype)

    def cond(state):
        i, *_, done, bad, _ = state
        return (i < max_passes) & ~done & ~bad

    def body(state):
        i, params, corr, hist, dhist, done, bad, steps = state
        new, bad_step, n = step(params, corr)
        new_corr, term, mean_d = measure(new)
        prev, prev_d = hist[i], dhist[i]
        if undo_worse:
            # A pass that raised the data term (re-gated correspondences, the point-to-plane
            # blend) is undone and ends the loop: the recorded data term never increases.
            worse = term > prev
            new, new_corr = jax.tree_util.tree_map(
                lambda a, b_: jnp.where(worse, a, b_), (params, corr), (new, new_corr)
            )
            term, mean_d = jnp.where(worse, prev, term), jnp.where(worse, prev_d, mean_d)
            done = worse
        else:
            done = False
        done = done | (jnp.abs(prev - term) <= rtol * prev) | (jnp.abs(prev_d - mean_d) <= atol_mm)
        bad = bad | bad_step | ~jnp.isfinite(term)
        hist = hist.at[i + 1].set(term)
        dhist = dhist.at[i + 1].set(mean_d)
        return i + 1, new, new_corr, hist, dhist, done, bad, steps + n

    state = (
        jnp.asarray(0),
        params0,
        corr0,
        nan.at[0].set(term0),
        nan.at[0].set(mean0),
        jnp.asarray(False),
        bad0 | ~jnp.isfinite(term0),
        jnp.asarray(steps0),
    )
    return jax.lax.while_loop(cond, body, state)


def _unbounded(c, b):
    return b * jnp.arctanh(jnp.clip(c / b, -0.999, 0.999))


def _fit_one(
    model: SScapeModel,
    scan: Scan,
    st: _Static,
    init_coeffs,
    init_pose,
    init_sim: Similarity | None,
    cfg: FitConfig,
    shape_residual: Callable | None,
) -> Solution:
    dtype = model.mean.dtype
    faces = model.faces
    free = np.asarray(st.free, np.int32)
    nonroot = free[free != 0]
    b = cfg.coeff_bound
    K = model.n_components

    points = jnp.asarray(scan.points, dtype)
    mask = jnp.asarray(scan.point_mask, bool)
    points = jnp.where(mask[:, None], points, 0.0)
    snormals = jnp.where(mask[:, None], jnp.asarray(scan.normals, dtype), 0.0)
    present = jnp.asarray(scan.landmark_mask, bool) & st.lm_known
    lm_target = jnp.where(present[:, None], jnp.asarray(scan.landmarks, dtype), 0.0)
    n_lm = jnp.maximum(jnp.sum(present), 1).astype(dtype)
    lm_w = present.astype(dtype)
    n_elig = jnp.maximum(jnp.sum(~st.exclude), 1).astype(dtype)
    del_max2 = (cfg.max_dist * _MM) ** 2

    # -- similarity -------------------------------------------------------------------------------
    if init_sim is None:
        sim0 = _umeyama_masked(model.mean[st.lm_vertex], lm_target, present)
    else:
        sim0 = init_sim
    R0 = sim0.rotation

    def mesh(coeffs, pose, t, ls, subset=None):
        sim = Similarity(R0, t, ls)
        verts, _ = evaluate(model, coeffs, pose, sim, subset=subset)
        return verts

    def full_pose(base, pose_free):
        return base.at[free].set(pose_free)

    def pose_prior(pose_free):
        if cfg.pose_prior == 0 or nonroot.size == 0:
            return ()
        sel = np.searchsorted(free, nonroot)
        return (np.sqrt(cfg.pose_prior) * pose_free[sel],)

    def lm_res(x_lm, weight):
        r = x_lm - lm_target
        return (_MM * jnp.sqrt(weight / n_lm) * lm_w[:, None]) * r

    a = cfg.point_to_plane

    def data_res(x, corr):
        idx, w = corr
        diff = x - points[idx]
        scale = _MM * jnp.sqrt(w / n_elig)
        if a == 0:
            return scale[:, None] * diff
        plane = jnp.sum(diff * snormals[idx], -1)
        return (np.sqrt(a) * scale * plane, (np.sqrt(1.0 - a) * scale)[:, None] * diff)

    solve = _lm_solve(cfg.solver_rtol, cfg.solver_atol)

    # -- one Levenberg-Marquardt solve over a subset of the unknowns -----------------------------
    # `pose`: joint rotations + translation (+ scale); `shape`: coefficients (+ scale); both for the
    # joint schedule. Frozen unknowns come in through `args`; `w_lm` (None = no landmark term) and
    # `use_data` are Python constants of the call site.
    def make_fn(fit_pose, fit_shape, w_lm, use_data):
        def fn(y, args):
            u_fixed, pose_fixed, t_fixed, ls_fixed, corr = args
            pose = full_pose(pose_fixed, y["pose"]) if fit_pose else pose_fixed
            t = y["t"] if fit_pose else t_fixed
            ls = y["ls"] if cfg.fit_scale else ls_fixed
            coeffs = _bounded(y["u"] if fit_shape else u_fixed, b)
            if use_data:
                x = mesh(coeffs, pose, t, ls)
                x_lm = x[st.lm_vertex]
            else:  # landmarks only: skin just the landmark vertices (~80x cheaper Jacobians)
                x_lm = mesh(coeffs, pose, t, ls, subset=st.lm_vertex)
            res = [lm_res(x_lm, w_lm)] if w_lm is not None else []
            if use_data:
                res.append(data_res(x, corr))
            if fit_pose:
                res.extend(pose_prior(y["pose"]))
            if fit_shape:
                if cfg.shape_prior > 0:
                    res.append(np.sqrt(cfg.shape_prior) * coeffs)
                if shape_residual is not None:
                    res.append(jnp.asarray(shape_residual(shape_vertices(model, coeffs)), dtype))
            return tuple(res)

        return fn

    def stage(fit_pose, fit_shape, w_lm, use_data, steps, u, pose, t, ls, corr):
        y0 = {}
        if fit_pose:
            y0["pose"], y0["t"] = pose[free], t
        if fit_shape:
            y0["u"] = u
        if cfg.fit_scale:
            y0["ls"] = ls
        fn = make_fn(fit_pose, fit_shape, w_lm, use_data)
        y, bad, n = solve(fn, y0, (u, pose, t, ls, corr), steps)
        if fit_pose:
            pose, t = full_pose(pose, y["pose"]), y["t"]
        if fit_shape:
            u = y["u"]
        if cfg.fit_scale:
            ls = y["ls"]
        return u, pose, t, ls, bad, n

    # -- correspondences and the data term ---------------------------------------------------
    def correspond(x):
        idx, w, dist = _correspondences(
            x, vertex_normals(x, faces), points, snormals, mask, st.exclude, cfg
        )
        d_mm = dist * _MM
        elig = (~st.exclude).astype(dtype)
        term = jnp.sum(elig * jnp.where(w > 0, d_mm**2, del_max2)) / n_elig
        mean_d = jnp.sum(w * d_mm) / jnp.maximum(jnp.sum(w), 1.0)
        return (idx, w), term, mean_d

    # -- stage 1: pose from landmarks -------------------------------------------------------
    if K == 0:
        u0 = jnp.zeros((0,), dtype)
    else:
        u0 = _unbounded(jnp.asarray(init_coeffs, dtype), b)
    pose0 = jnp.asarray(init_pose, dtype)
    t0, ls0 = sim0.translation, sim0.log_scale
    dummy_corr = (jnp.zeros(model.n_vertices, jnp.int32), jnp.zeros(model.n_vertices, dtype))
    _, pose1, t1, ls1, bad0, steps0 = stage(
        True, False, 1.0, False, cfg.landmark_steps, u0, pose0, t0, ls0, dummy_corr
    )
    corr1, term1, mean1 = correspond(mesh(_bounded(u0, b), pose1, t1, ls1))

    w_lm = cfg.landmark_weight if cfg.landmark_weight > 0 else None

    def step(params, corr):
        u, pose, t, ls = params
        if cfg.schedule == "joint":
            u, pose, t, ls, bad, n = stage(
                True, True, w_lm, True, cfg.pose_steps, u, pose, t, ls, corr
            )
        else:
            u, pose, t, ls, bad1, n1 = stage(
                True, False, w_lm, True, cfg.pose_steps, u, pose, t, ls, corr
            )
            corr, _, _ = correspond(mesh(_bounded(u, b), pose, t, ls))
            u, pose, t, ls, bad2, n2 = stage(
                False, True, w_lm, True, cfg.shape_steps, u, pose, t, ls, corr
            )
            bad, n = bad1 | bad2, n1 + n2
        return (u, pose, t, ls), bad, n

    def measure(params):
        u, pose, t, ls = params
        return correspond(mesh(_bounded(u, b), pose, t, ls))

    passes, (u, pose, t, ls), corr, hist, dhist, done, bad, steps = _pass_loop(
        step, measure, (u0, pose1, t1, ls1), corr1, term1, mean1, bad0, steps0,
        max_passes=cfg.max_passes, rtol=cfg.rtol, atol_mm=cfg.atol_mm, undo_worse=True,
        dtype=dtype,
    )  # fmt: skip

    coeffs = _bounded(u, b)
    sim = Similarity(R0, t, ls)
    verts, _ = evaluate(model, coeffs, pose, sim)
    rest = shape_vertices(model, coeffs)
    lm_err = jnp.linalg.norm(verts[st.lm_vertex] - lm_target, axis=-1) * _MM
    finite = (
        jnp.all(jnp.isfinite(verts)) & jnp.all(jnp.isfinite(coeffs)) & jnp.all(jnp.isfinite(pose))
    )
    result = RESULTS.where(bad, RESULTS.solver_failed, RESULTS.successful)
    result = RESULTS.where(finite, result, RESULTS.nonfinite)
    _, w = corr
    stats = {
        "data_term": hist,
        "mean_distance_mm": dhist,
        "passes": passes,
        "converged": done,
        "final_mean_distance_mm": dhist[passes],
        "valid_fraction": jnp.sum(w) / n_elig,
        "landmark_rms_mm": jnp.sqrt(jnp.sum(lm_w * lm_err**2) / n_lm),
        "num_steps": steps,
    }
    return Solution(SScapeFit(coeffs, pose, sim, verts, rest), result, stats)


@eqx.filter_jit
def _fit_single(model, scan, st, init_coeffs, init_pose, init_sim, cfg, shape_residual):
    return _fit_one(model, scan, st, init_coeffs, init_pose, init_sim, cfg, shape_residual)


def _fit_kernel(replicated, item):
    """Per-scan kernel of the batch map; `replicated` = (model, st, cfg, shape_residual)."""
    model, st, cfg, shape_residual = replicated
    scan, init_coeffs, init_pose, init_sim = item
    return _fit_one(model, scan, st, init_coeffs, init_pose, init_sim, cfg, shape_residual)


# --------------------------------------------------------------------------------------------------
# Host-side validation and preparation
# --------------------------------------------------------------------------------------------------


def _check_scan_fields(scan: Scan, batched: bool):
    lead = ("B",) if batched else ()
    dims: dict[str, int] = {}
    check_array(scan.points, "scan.points", (*lead, "P", 3), dims=dims, finite=False)
    check_array(scan.normals, "scan.normals", (*lead, "P", 3), dims=dims, finite=False)
    check_array(scan.point_mask, "scan.point_mask", (*lead, "P"), dims=dims, finite=False)
    check_array(scan.landmarks, "scan.landmarks", (*lead, "L", 3), dims=dims, finite=False)
    check_array(scan.landmark_mask, "scan.landmark_mask", (*lead, "L"), dims=dims, finite=False)
    check_scan(scan, min_points=1, name="scans" if batched else "scan")
    return dims


def _prepare(model, scan, template, config, shape_residual, init, batched: bool):
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    if not isinstance(template, RegistrationTemplate):
        raise ValueError(
            f"`template` must be a RegistrationTemplate, got {type(template).__name__}."
        )
    if not isinstance(config, FitConfig):
        raise ValueError(f"`config` must be a FitConfig, got {type(config).__name__}.")
    if not isinstance(scan, Scan):
        raise ValueError(
            f"`scan` must be a bodyprior.registration.Scan, got {type(scan).__name__}."
        )
    if shape_residual is not None and not callable(shape_residual):
        raise ValueError(
            f"`shape_residual` must be a callable (rest_vertices (V, 3)) -> (R,) or None, got "
            f"{type(shape_residual).__name__}."
        )
    if model.n_vertices != template.n_vertices:
        raise ValueError(
            f"`model` has {model.n_vertices} vertices but `template` has {template.n_vertices}: "
            "the model must be learned on the template's topology (`template.restrict(...)`)."
        )
    if tuple(model.faces.shape) != tuple(template.faces.shape):
        raise ValueError(
            f"`model.faces` has shape {tuple(model.faces.shape)} but `template.faces` has "
            f"{tuple(template.faces.shape)}: model and template must share the topology."
        )
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "S-SCAPE fitting runs its least-squares solves in float64: enable it first with "
            "`jax.config.update('jax_enable_x64', True)`."
        )
    dims = _check_scan_fields(scan, batched)

    # Landmark names -> template vertices (host side; names are static).
    names = tuple(scan.landmark_names)
    tpos = {n: i for i, n in enumerate(template.landmark_names)}
    lm_index = np.asarray(template.landmark_index)
    known = np.array([n in tpos for n in names], bool)
    vertex = np.array([lm_index[tpos[n]] if n in tpos else 0 for n in names], np.int32)
    if not is_tracer(scan.landmark_mask):
        present = np.asarray(scan.landmark_mask, bool).reshape(-1, len(names)) & known
        counts = present.sum(1)
        if counts.min() < 4:
            bad = int(np.argmin(counts))
            where = f" (scan {bad} of the batch)" if batched else ""
            raise ValueError(
                f"`scan` must have at least 4 present landmarks known to the template, got "
                f"{int(counts.min())}{where}."
            )

    # Frozen joints.
    if config.frozen_joints is None:
        frozen = {n for n in model.joint_names if any(w in n for w in _HAND_WORDS)}
    else:
        unknown = [n for n in config.frozen_joints if n not in model.joint_names]
        if unknown:
            raise ValueError(
                f"`config.frozen_joints` names joints the model does not have: {unknown}; joints "
                f"are {list(model.joint_names)}."
            )
        frozen = set(config.frozen_joints)
    free = tuple(j for j, n in enumerate(model.joint_names) if n not in frozen)
    if not free:
        raise ValueError("`config.frozen_joints` freezes every joint; at least one must be free.")
    exclude = (
        np.asarray(template.hand_mask, bool)
        if config.exclude_hands
        else np.zeros(template.n_vertices, bool)
    )
    st = _Static(as_device_array(vertex), as_device_array(known), as_device_array(exclude), free)
    model = _as_float64(model)

    # Initial parameters.
    dtype = jnp.float64
    K, J = model.n_components, model.n_joints
    lead = (dims["B"],) if batched else ()
    if init is None:
        coeffs = jnp.zeros((*lead, K), dtype)
        pose = jnp.zeros((*lead, J, 3), dtype)
        sim = None
    else:
        if isinstance(init, Solution):
            init = init.value
        if not isinstance(init, SScapeFit):
            raise ValueError(
                f"`init` must be an SScapeFit (or its Solution) or None, got {type(init).__name__}."
            )
        pose = jnp.asarray(check_array(init.pose, "init.pose", (*lead, J, 3)), dtype)
        c = check_array(init.coeffs, "init.coeffs", (*lead, None))
        c = jnp.asarray(c, dtype)[..., :K]
        if c.shape[-1] < K:
            c = jnp.concatenate([c, jnp.zeros((*lead, K - c.shape[-1]), dtype)], -1)
        coeffs = jnp.clip(c, -config.coeff_bound, config.coeff_bound)
        sim = init.similarity
        check_array(sim.rotation, "init.similarity.rotation", (*lead, 3, 3))
    if sim is not None:
        sim = _as_float64(sim)
    return model, st, coeffs, pose, sim


def _as_float64(tree):
    def cast(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating):
            return x.astype(jnp.float64)
        return x

    return jax.tree_util.tree_map(cast, tree)


# --------------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------------


def fit_sscape(
    model: SScapeModel,
    scan: Scan,
    template: RegistrationTemplate,
    *,
    config: FitConfig = FitConfig(),
    shape_residual: Callable[[Float[ArrayLike, "V 3"]], Float[ArrayLike, " R"]] | None = None,
    init: SScapeFit | Solution | None = None,
    throw: bool = True,
) -> Solution:
    """Fits an S-SCAPE space to one scan: similarity, pose from landmarks, then alternating pose
    and shape fits to compatible nearest neighbours (see the module docstring; sscape.md §2).

    One jitted call (compiled once per model/scan shape and config); float64 recommended
    (`jax.config.update("jax_enable_x64", True)`).

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][] on the template's topology (e.g.
      `learn(template.restrict(pop.vertices), template.faces, n_components=K,
      rig=template.rig)`).
    - `scan`: one [`bodyprior.registration.Scan`][] (metres); at least 4 of its present landmarks
      must be
      named in `template.landmark_names`.
    - `template`: the [`bodyprior.registration.RegistrationTemplate`][] (landmark vertices, hand
      mask).
    - `config`: a [`bodyprior.sscape.FitConfig`][].
    - `shape_residual`: optional `rest_vertices (V, 3) -> (R,)` residual vector added (unscaled)
      to the shape solves, whose data part is in millimetres (objective in mm^2). Must be
      jittable; an `eqx.Module` or a plain function.
    - `init`: optional previous [`bodyprior.sscape.SScapeFit`][] (or its `Solution`) to start
      from (its similarity, pose and coefficients, truncated or zero-padded to this model's K);
      the landmark pose stage still runs, starting from it.
    - `throw`: raise if the fit failed (`result` not `RESULTS.successful`: `solver_failed` or
      `nonfinite`); otherwise inspect `sol.result`. Using all `max_passes` is not a failure
      (`stats["converged"]` is False then; the rule is [`bodyprior.Solution`][]'s).

    **Returns:** a [`bodyprior.Solution`][]: `value` an [`bodyprior.sscape.SScapeFit`][];
    `result` a [`bodyprior.RESULTS`][]; `stats` a dict of arrays (N = `max_passes + 1`):
    `data_term` `(N,)` (mm^2, after the landmark stage and after each pass; NaN after the last
    pass), `mean_distance_mm` `(N,)` (mean over valid vertices), `passes` (int), `converged`
    (bool: the pass loop met its stopping test), `final_mean_distance_mm`, `valid_fraction` (of
    the non-hand vertices), `landmark_rms_mm` (present landmarks), `num_steps` (total LM steps).

    **Raises:** `ValueError` (before tracing) for a wrong model/template/scan/config, a model whose
    vertex count or faces differ from the template's, fewer than 4 usable landmarks, or NaN points.
    """
    model, st, coeffs, pose, sim = _prepare(
        model, scan, template, config, shape_residual, init, False
    )
    sol = _fit_single(model, scan, st, coeffs, pose, sim, config, shape_residual)
    return _check(sol, bool(throw), "S-SCAPE fit")


def fit_sscape_batch(
    model: SScapeModel,
    scans: Scan,
    template: RegistrationTemplate,
    *,
    config: FitConfig = FitConfig(),
    shape_residual: Callable[[Float[ArrayLike, "V 3"]], Float[ArrayLike, " R"]] | None = None,
    init: SScapeFit | Solution | None = None,
    devices=None,
    chunk_size: int | None = None,
    progress: bool = True,
    strategy: str | None = None,
    throw: bool = True,
) -> Solution:
    """Fits many scans: `vmap` of the single-scan fit, spread over devices, in chunks.

    The scans (padded to a common point count, `point_mask` False on padding; see
    [`bodyprior.registration.pad_scans`][]) are cut into chunks of `chunk_size` scans; every device
    fits
    its own slice of each chunk: on accelerators one jitted call per chunk whose scan axis is split
    over `devices` with `jax.sharding` (`Mesh` + `NamedSharding(mesh, PartitionSpec("scan"))`,
    compiled once), on CPUs one call per device (compiled once per device; the partitioned program
    deadlocks on host CPU devices). A tqdm bar counts the scans. See
    [`bodyprior.registration.batch_map`][] (`strategy`) and multi-process `jax.distributed`
    clusters.

    **Arguments:** as [`bodyprior.sscape.fit_sscape`][], plus

    - `scans`: a batched [`bodyprior.registration.Scan`][] (leading axis B).
    - `init`: optional batched `SScapeFit` or its `Solution` (leading axis B).
    - `devices`: devices to shard over (default: all of `jax.devices()`).
    - `chunk_size`: scans per jitted call, rounded up to a multiple of the device count (default:
      4 per device, at most B rounded up).
    - `progress`: show a progress bar.
    - `strategy`: `"spmd"`, `"per_device"` or `None` (by platform); see `batch_map`.
    - `throw`: raise naming the failed scans (after all chunks ran); with `False` inspect the
      per-scan `sol.result` (shape `(B,)`).

    **Returns:** a batched [`bodyprior.Solution`][] (every leaf, `result` included, with a leading
    axis B; NumPy-backed leaves on the host).
    """
    from ..registration._shard import batch_map

    model, st, coeffs, pose, sim = _prepare(
        model, scans, template, config, shape_residual, init, True
    )
    sol = batch_map(
        _fit_kernel,
        (model, st, config, shape_residual),
        (scans, coeffs, pose, sim),
        devices=devices,
        chunk_size=chunk_size,
        progress=progress,
        desc="fitting S-SCAPE",
        strategy=strategy,
    )
    return _check(sol, bool(throw), "S-SCAPE fit")
