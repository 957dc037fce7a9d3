"""Body reconstruction from a front and a back depth image (S-SCAPE paper §6, after Helten et al.
2013): one S-SCAPE shape and two poses fitted to the two scans of
`bodyprior.registration.depth_to_scan` (the depth camera lives in the registration core).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._geometry import vertex_normals
from .._kinematics import Similarity
from .._solution import RESULTS, Solution, _check
from .._validate import named_preset
from ..registration._grid import nearest_within
from ..registration._scan import Scan, check_scan
from ..registration._template import RegistrationTemplate
from ._fit import (
    _MM,
    FitConfig,
    _bounded,
    _correspondences,
    _lm_solve,
    _pass_loop,
    _prepare,
    _umeyama_masked,
)
from ._model import SScapeModel, evaluate, shape_vertices

# --------------------------------------------------------------------------------------------------
# Fitting one shape and two poses to a front and a back depth scan (Helten et al.; sscape.md §4, §8)
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DepthFitConfig:
    """Settings of [`bodyprior.sscape.fit_depth`][] (hashable; static under jit).

    **Fields:**

    - `fit`: a [`bodyprior.sscape.FitConfig`][] giving the gates (`max_dist`, `max_angle_deg`), the
      shape bound (`coeff_bound`), the priors (`pose_prior`, `shape_prior`, `landmark_weight`), the
      frozen joints, `fit_scale`, the solver tolerances, `landmark_steps` (stage 1) and
      `chunk_size`, with the meanings they have in [`bodyprior.sscape.fit_sscape`][]; its pass
      settings are not used.
    - `max_rounds`: maximum rounds of the joint stage (default 8); each round is a pose solve per
      image, new correspondences, one shared shape (+ scale) solve, new correspondences.
    - `rtol`, `atol_mm`: stop when the joint data term changes by at most `rtol` (relative) or its
      mean distance by at most `atol_mm` in one round.
    - `scan_weight`: weight of the scan -> model term relative to the model -> scan term (1.0);
      0 gives the model -> scan term alone (the per-scan S-SCAPE objective).
    - `pose_steps`, `shape_steps`: Levenberg-Marquardt step limits per solve of the joint stage.
    - `joint`: solve the shared shape, both poses and the scale together in one Levenberg-Marquardt
      solve per round (`pose_steps + shape_steps` steps; default) instead of humanshape's
      alternation of per-image pose solves and a shared shape solve (`False`), which converges
      much more slowly: pose and shape are strongly coupled through the limb lengths.
    - `point_to_plane`: the model -> scan residual is the distance to the depth point's tangent
      plane (default) instead of to the point: a sub-sampled depth image has ~1-2 cm between
      points, so point-to-point distances stay ~1 cm at the true surface and bias the fit.

    The default `fit` carries a Gaussian shape prior, `shape_prior = 1` mm² per squared standard
    deviation (humanshape and the paper: none, `DepthFitConfig.preset("paper")`). Two depth images
    see one side of the body each and 2,048 noisy points per view; without the prior more
    components fit the noise and the posture instead of the shape (measured on the NH space of
    1,000 bodies, two subjects: rest-shape error 9.9 / 15.9 / 20.3 mm at K = 10 / 20 / 50 without,
    9.8 / 9.8 / 9.5 mm with it; docs/results_sscape.md).
    """

    fit: FitConfig = FitConfig.preset("humanshape", shape_prior=1.0)
    max_rounds: int = 8
    rtol: float = 1e-3
    atol_mm: float = 1e-3
    scan_weight: float = 1.0
    pose_steps: int = 10
    shape_steps: int = 10
    joint: bool = True
    point_to_plane: bool = True

    @classmethod
    def preset(cls, name: str, **overrides) -> DepthFitConfig:
        """A named configuration, with any field overridden by keyword: `"default"`
        (`DepthFitConfig()`, shape prior 1 mm²/σ²) or `"paper"`
        (`fit=FitConfig.preset("humanshape")`: humanshape's fit, no shape prior, as the paper).
        An explicit `fit=` is used as given."""
        return named_preset(
            cls, {"default": {}, "paper": {"fit": FitConfig.preset("humanshape")}}, name, overrides
        )

    def __post_init__(self):
        if not isinstance(self.fit, FitConfig):
            raise ValueError(
                f"`DepthFitConfig.fit` must be a FitConfig, got {type(self.fit).__name__}."
            )
        for name in ("max_rounds", "pose_steps", "shape_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"`DepthFitConfig.{name}` must be a positive int, got {v!r}.")
        for name in ("rtol", "atol_mm"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"`DepthFitConfig.{name}` must be a positive number, got {v!r}.")
        if not (np.isfinite(self.scan_weight) and self.scan_weight >= 0):
            raise ValueError(
                "`DepthFitConfig.scan_weight` must be a non-negative number, got "
                f"{self.scan_weight!r}."
            )


class DepthFit(eqx.Module):
    """The fitted body of [`bodyprior.sscape.fit_depth`][] (the `value` of its
    [`bodyprior.Solution`][]): one shape, a pose per image (0 front, 1 back).

    **Fields** (V vertices, J joints, K components):

    - `coeffs`: the shared shape coefficients, shape `(K,)`, standard deviations.
    - `poses`: per-image local joint rotations, axis-angle, shape `(2, J, 3)`.
    - `similarities`: per-image [`bodyprior.Similarity`][] model -> world (leaves with a leading
      axis 2; both have the same, shared, scale).
    - `vertices`: fitted posed meshes in the world frame of each image, shape `(2, V, 3)`, metres.
    - `rest_vertices`: the shaped, unposed mesh in the model frame (unscaled), shape `(V, 3)`;
      multiply by `scale` for the subject's size.
    - `scale`: the shared global scale, shape `()`.
    - `init_vertices`: the meshes after stage 1 (mean shape, landmark poses), shape `(2, V, 3)`.
    """

    coeffs: Float[Array, " K"]
    poses: Float[Array, "2 J 3"]
    similarities: Similarity
    vertices: Float[Array, "2 V 3"]
    rest_vertices: Float[Array, "V 3"]
    scale: Float[Array, ""]
    init_vertices: Float[Array, "2 V 3"]


def _fit_depth_kernel(model: SScapeModel, scans: Scan, st, pose0, cfg: DepthFitConfig):
    fc = cfg.fit
    dtype = model.mean.dtype
    faces = model.faces
    free = np.asarray(st.free, np.int32)
    nonroot_sel = np.searchsorted(free, free[free != 0])
    b = fc.coeff_bound
    cos_min = float(np.cos(np.deg2rad(fc.max_angle_deg)))
    V, K = model.n_vertices, model.n_components

    points = jnp.asarray(scans.points, dtype)
    mask = jnp.asarray(scans.point_mask, bool)
    points = jnp.where(mask[..., None], points, 0.0)
    snormals = jnp.where(mask[..., None], jnp.asarray(scans.normals, dtype), 0.0)
    n_pts = jnp.maximum(jnp.sum(mask, -1), 1).astype(dtype)  # (2,)
    present = jnp.asarray(scans.landmark_mask, bool) & st.lm_known[None]
    lm_target = jnp.where(present[..., None], jnp.asarray(scans.landmarks, dtype), 0.0)
    lm_w = present.astype(dtype)
    n_lm = jnp.maximum(jnp.sum(present, -1), 1).astype(dtype)
    n_elig = jnp.maximum(jnp.sum(~st.exclude), 1).astype(dtype)
    dmax2 = (fc.max_dist * _MM) ** 2
    sw = float(cfg.scan_weight)

    solve = _lm_solve(fc.solver_rtol, fc.solver_atol)

    def mesh(coeffs, pose, t, ls, Rk):
        return evaluate(model, coeffs, pose, Similarity(Rk, t, ls))[0]

    def lm_res(x, tgt, w, n, weight):
        return (_MM * jnp.sqrt(weight / n) * w[:, None]) * (x[st.lm_vertex] - tgt)

    def pose_prior(pose_free):
        if fc.pose_prior > 0 and nonroot_sel.size:
            return (np.sqrt(fc.pose_prior) * pose_free[nonroot_sel],)
        return ()

    # Stage 1, per image (vmapped): similarity from the landmarks (Umeyama on the model mean's
    # landmark vertices, as fit_sscape), then pose + translation + scale from the landmarks with the
    # shape at the mean (humanshape fitPose).
    zero_c = jnp.zeros((K,), dtype)

    def lm_fn(y, args):
        base, Rk, tgt, w, n = args
        pose = base.at[free].set(y["pose"])
        x = mesh(zero_c, pose, y["t"], y["ls"], Rk)
        return (lm_res(x, tgt, w, n, 1.0), *pose_prior(y["pose"]))

    def init_view(base, tgt, w, n):
        sim = _umeyama_masked(model.mean[st.lm_vertex], tgt, w > 0)
        y0 = {"pose": base[free], "t": sim.translation, "ls": sim.log_scale}
        y, bad, k = solve(lm_fn, y0, (base, sim.rotation, tgt, w, n), fc.landmark_steps)
        return base.at[free].set(y["pose"]), y["t"], y["ls"], sim.rotation, bad, k

    poses0, ts0, ls_k, R, bad0, steps0 = jax.vmap(init_view)(pose0, lm_target, lm_w, n_lm)
    ls0 = jnp.mean(ls_k)  # one subject, one scale (sscape.md §4 step 3b)

    # Correspondences of one image: model -> scan (H-fit's compatible search, hands excluded) and
    # scan -> model (each real depth point to the nearest compatible, i.e. camera-facing, model
    # vertex; pairs landing on a hand vertex are dropped so that hand points do not pull the wrist).
    def correspond(x, pts, nrm, msk):
        vn = vertex_normals(x, faces)
        idx_m, w_m, d_m = _correspondences(x, vn, pts, nrm, msk, st.exclude, fc)
        # the nearest compatible vertex within the gate (grid radius search over the vertices)
        found = nearest_within(
            pts, x, jnp.ones((V,), bool), fc.max_dist,
            query_normals=nrm, point_normals=vn, cos_max=cos_min,
        )  # fmt: skip
        idx_s = jnp.maximum(found, 0)
        d_s = jax.lax.stop_gradient(jnp.linalg.norm(pts - x[idx_s], axis=-1))
        w_s = ((found >= 0) & msk & ~st.exclude[idx_s]).astype(dtype)
        corr = (idx_m, w_m, idx_s, w_s, jax.lax.stop_gradient(vn[idx_s]))
        elig = (~st.exclude).astype(dtype)
        term_m = jnp.sum(elig * jnp.where(w_m > 0, (d_m * _MM) ** 2, dmax2)) / n_elig
        mf = msk.astype(dtype)
        n_real = jnp.maximum(jnp.sum(mf), 1.0)
        term_s = jnp.sum(mf * jnp.where(w_s > 0, (d_s * _MM) ** 2, dmax2)) / n_real
        info = dict(
            term=term_m + sw * term_s,
            mean_m=jnp.sum(w_m * d_m) / jnp.maximum(jnp.sum(w_m), 1.0) * _MM,
            mean_s=jnp.sum(w_s * d_s) / jnp.maximum(jnp.sum(w_s), 1.0) * _MM,
            n_m=jnp.sum(w_m),
            n_s=jnp.sum(w_s),
            frac_s=jnp.sum(w_s) / n_real,
        )
        return corr, info

    correspond_all = jax.vmap(correspond)

    def data_res(x, corr, pts, npts, nrm):
        idx_m, w_m, idx_s, w_s, n_s = corr
        if cfg.point_to_plane:
            d = jnp.sum(nrm[idx_m] * (x - pts[idx_m]), -1)
            res = [_MM * jnp.sqrt(w_m / n_elig) * d]
        else:
            res = [(_MM * jnp.sqrt(w_m / n_elig))[:, None] * (x - pts[idx_m])]
        if sw > 0:
            plane = jnp.sum(n_s * (pts - x[idx_s]), -1)
            res.append(_MM * jnp.sqrt(sw * w_s / npts) * plane)
        return res

    # Stage 2a: per-image pose (+ translation) with the shared shape and scale fixed (vmapped).
    def pose_fn(y, args):
        coeffs, base, ls, Rk, corr, pts, nrm, npts, tgt, w, n = args
        pose = base.at[free].set(y["pose"])
        x = mesh(coeffs, pose, y["t"], ls, Rk)
        res = data_res(x, corr, pts, npts, nrm)
        if fc.landmark_weight > 0:
            res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
        return (*res, *pose_prior(y["pose"]))

    def pose_solve_one(coeffs, pose, t, ls, Rk, corr, pts, nrm, npts, tgt, w, n):
        y0 = {"pose": pose[free], "t": t}
        args = (coeffs, pose, ls, Rk, corr, pts, nrm, npts, tgt, w, n)
        y, bad, k = solve(pose_fn, y0, args, cfg.pose_steps)
        return pose.at[free].set(y["pose"]), y["t"], bad, k

    def pose_solve(coeffs, poses, ts, ls, corr):
        return jax.vmap(pose_solve_one, in_axes=(None, 0, 0, None, 0, 0, 0, 0, 0, 0, 0, 0))(
            coeffs, poses, ts, ls, R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm
        )

    # Stage 2b: the shared shape (+ the shared scale) with both poses fixed, one solve.
    def shape_fn(y, args):
        poses, ts, ls_fixed, corr = args
        coeffs = _bounded(y["u"], b)
        ls = y["ls"] if fc.fit_scale else ls_fixed

        def one(pose, t, Rk, c, pts, nrm, npts, tgt, w, n):
            x = mesh(coeffs, pose, t, ls, Rk)
            res = data_res(x, c, pts, npts, nrm)
            if fc.landmark_weight > 0:
                res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
            return tuple(res)

        res = jax.vmap(one)(poses, ts, R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm)
        if fc.shape_prior > 0:
            res = (*res, np.sqrt(fc.shape_prior) * coeffs)
        return res

    def shape_solve(u, poses, ts, ls, corr):
        y0 = {"u": u}
        if fc.fit_scale:
            y0["ls"] = ls
        y, bad, k = solve(shape_fn, y0, (poses, ts, ls, corr), cfg.shape_steps)
        return y["u"], y["ls"] if fc.fit_scale else ls, bad, k

    # Stage 2 (joint=True): everything at once, one Levenberg-Marquardt solve per round.
    def joint_fn(y, args):
        base, corr = args
        coeffs = _bounded(y["u"], b)
        poses = base.at[:, free].set(y["pose"])

        def one(pose, t, Rk, c, pts, nrm, npts, tgt, w, n):
            x = mesh(coeffs, pose, t, y["ls"], Rk)
            res = data_res(x, c, pts, npts, nrm)
            if fc.landmark_weight > 0:
                res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
            return tuple(res)

        res = jax.vmap(one)(poses, y["t"], R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm)
        res = (*res, *pose_prior(y["pose"].swapaxes(0, 1)))
        if fc.shape_prior > 0:
            res = (*res, np.sqrt(fc.shape_prior) * coeffs)
        return res

    def joint_solve(u, poses, ts, ls, corr):
        y0 = {"u": u, "pose": poses[:, free], "t": ts, "ls": ls}
        y, bad, k = solve(joint_fn, y0, (poses, corr), cfg.pose_steps + cfg.shape_steps)
        ls = y["ls"] if fc.fit_scale else ls
        return y["u"], poses.at[:, free].set(y["pose"]), y["t"], ls, bad, k

    def meshes(u, poses, ts, ls):
        return jax.vmap(mesh, in_axes=(None, 0, 0, None, 0))(_bounded(u, b), poses, ts, ls, R)

    def measure(u, poses, ts, ls):
        corr, info = correspond_all(meshes(u, poses, ts, ls), points, snormals, mask)
        n_tot = jnp.maximum(jnp.sum(info["n_m"] + info["n_s"]), 1.0)
        mean_d = jnp.sum(info["mean_m"] * info["n_m"] + info["mean_s"] * info["n_s"]) / n_tot
        return corr, jnp.sum(info["term"]), mean_d, info

    u0 = jnp.zeros((K,), dtype)
    init_vertices = meshes(u0, poses0, ts0, ls0)
    corr0, term0, mean0, _ = measure(u0, poses0, ts0, ls0)

    def step(params, corr):
        u, poses, ts, ls = params
        if cfg.joint:
            u, poses, ts, ls, bad, k = joint_solve(u, poses, ts, ls, corr)
        else:
            poses, ts, bad1, k1 = pose_solve(_bounded(u, b), poses, ts, ls, corr)
            corr, _, _, _ = measure(u, poses, ts, ls)
            u, ls, bad2, k2 = shape_solve(u, poses, ts, ls, corr)
            bad, k = jnp.any(bad1) | bad2, jnp.sum(k1) + k2
        return (u, poses, ts, ls), bad, k

    rounds, (u, poses, ts, ls), corr, hist, dhist, done, bad, steps = _pass_loop(
        step, lambda p: measure(*p)[:3], (u0, poses0, ts0, ls0), corr0, term0, mean0,
        jnp.any(bad0), jnp.sum(steps0), max_passes=cfg.max_rounds, rtol=cfg.rtol,
        atol_mm=cfg.atol_mm, undo_worse=False, dtype=dtype,
    )  # fmt: skip
    coeffs = _bounded(u, b)
    verts = meshes(u, poses, ts, ls)
    _, _, _, info = measure(u, poses, ts, ls)
    finite = jnp.all(jnp.isfinite(verts)) & jnp.all(jnp.isfinite(coeffs))
    result = RESULTS.where(bad, RESULTS.solver_failed, RESULTS.successful)
    result = RESULTS.where(finite, result, RESULTS.nonfinite)
    lm_err = jnp.linalg.norm(verts[:, st.lm_vertex] - lm_target, axis=-1) * _MM
    stats = {
        "data_term": hist,
        "mean_distance_mm": dhist,
        "rounds": rounds,
        "converged": done,
        "model_to_scan_mm": info["mean_m"],
        "scan_to_model_mm": info["mean_s"],
        "valid_fraction": info["frac_s"],
        "landmark_rms_mm": jnp.sqrt(jnp.sum(lm_w * lm_err**2, -1) / n_lm),
        "num_steps": steps,
    }
    fit = DepthFit(
        coeffs=coeffs,
        poses=poses,
        similarities=Similarity(R, ts, jnp.broadcast_to(ls, (2,))),
        vertices=verts,
        rest_vertices=shape_vertices(model, coeffs),
        scale=jnp.exp(ls),
        init_vertices=init_vertices,
    )
    return Solution(fit, result, stats)


@eqx.filter_jit
def _fit_depth_jit(model, scans, st, pose0, cfg):
    return _fit_depth_kernel(model, scans, st, pose0, cfg)


def fit_depth(
    model: SScapeModel,
    front_scan: Scan,
    back_scan: Scan,
    template: RegistrationTemplate,
    *,
    config: DepthFitConfig = DepthFitConfig(),
    throw: bool = True,
) -> Solution:
    """Fits one S-SCAPE shape and a pose per image to a front and a back depth scan.

    The procedure of the paper's §6 (after Helten et al. 2013; humanshape `fitPoseShapeJoint`,
    sscape.md §4, §8), in one jitted call:

    1. **Per-image initialisation** (vmapped over the two images): the similarity from the image's
       landmarks (Umeyama on the model mean's landmark vertices, as in
       [`bodyprior.sscape.fit_sscape`][]), then pose, translation and scale from the landmarks with
       the shape at the mean (humanshape `fitPose`). The paper's step 1 runs a full S-SCAPE fit per
       image and averages the two shapes; here the shared shape starts at the mean and is fitted
       by step 2 only (one shape from both images from the start; it also avoids compiling the
       per-scan fitter a second time).
    2. **Joint fit.** Starting from the two poses and the mean of the two scales, rounds of: new
       correspondences, then one Levenberg-Marquardt solve over the shared shape, both poses and
       translations and the shared scale (`config.joint=True`; with `False`, humanshape
       `fitPoseShapeJoint`'s alternation: a pose solve per image with the shape fixed, new
       correspondences, one shared shape + scale solve with the poses fixed); until the data term
       stops changing (`lax.while_loop`).

    A depth image sees one side of the body, so the data term has two directions per image:
    **model -> scan** (each non-hand model vertex to its nearest *compatible* depth point, normals
    within `max_angle_deg`, distance gated by `max_dist`; back-facing vertices find no compatible
    point and drop out, which is the visibility test) and **scan -> model** (each depth point to the
    nearest compatible model vertex, i.e. a vertex facing the camera, point-to-plane with that
    vertex's normal, same gates; pairs on hand vertices dropped), the latter weighted by
    `scan_weight` and normalised by the number of depth points. Both are squared distances in mm,
    solved by optimistix Levenberg-Marquardt with a normal-equation Cholesky linear solver (the
    Jacobians are tall and thin); run in float64 (`jax_enable_x64`).

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][] on `template`'s topology.
    - `front_scan`, `back_scan`: one [`bodyprior.registration.Scan`][] each (e.g. from
      [`bodyprior.registration.depth_to_scan`][]), world frame, metres, normals facing their camera,
      each
      with at least 4 landmarks known to `template` (the paper placed 14 by hand). They are padded
      to a common point count if needed.
    - `template`: the [`bodyprior.registration.RegistrationTemplate`][].
    - `config`: a [`bodyprior.sscape.DepthFitConfig`][].
    - `throw`: raise if a solve failed or the result is not finite (`result` not
      `RESULTS.successful`); otherwise inspect `sol.result`. Using all `max_rounds` is not a
      failure (`stats["converged"]` is False then; the rule is [`bodyprior.Solution`][]'s).

    **Returns:** a [`bodyprior.Solution`][]: `value` a [`bodyprior.sscape.DepthFit`][]; `stats`
    a dict (N = `max_rounds + 1`): `data_term` `(N,)` (mm^2: sum over both images of the model ->
    scan truncated quadratic plus `scan_weight` times the scan -> model one; after the start and
    after each round, NaN after the last), `mean_distance_mm` `(N,)` (mean valid distance, both
    directions and images), `rounds`, `converged`, `model_to_scan_mm` `(2,)`, `scan_to_model_mm`
    `(2,)` (final mean valid distances per image), `valid_fraction` `(2,)` (scan points with a
    valid model partner), `landmark_rms_mm` `(2,)`, `num_steps` (total LM steps).

    **Raises:** `ValueError` (before tracing) for a wrong model/template/config, scans that are not
    `Scan`s, have different landmark names, NaN points, or fewer than 4 usable landmarks.
    """
    from ..registration._scan import pad_scans

    if not isinstance(config, DepthFitConfig):
        raise ValueError(f"`config` must be a DepthFitConfig, got {type(config).__name__}.")
    for name, sc in (("front_scan", front_scan), ("back_scan", back_scan)):
        if not isinstance(sc, Scan):
            raise ValueError(
                f"`{name}` must be a bodyprior.registration.Scan, got {type(sc).__name__}."
            )
        if np.ndim(sc.points) != 2:
            raise ValueError(
                f"`{name}` must be one (unbatched) scan, got points of shape {np.shape(sc.points)}."
            )
        check_scan(sc, min_points=1, name=name)
    if front_scan.landmark_names != back_scan.landmark_names:
        raise ValueError("`front_scan` and `back_scan` must have the same `landmark_names`.")
    if isinstance(template, RegistrationTemplate):
        known = np.array([n in template.landmark_names for n in front_scan.landmark_names], bool)
        for name, sc in (("front_scan", front_scan), ("back_scan", back_scan)):
            count = int((np.asarray(sc.landmark_mask, bool).reshape(-1) & known).sum())
            if count < 4:
                raise ValueError(
                    f"`{name}` must have at least 4 present landmarks known to the template "
                    f"(the paper placed 14 by hand on each depth image), got {count}."
                )
    scans = pad_scans([front_scan, back_scan])
    model, st, _, pose, _ = _prepare(model, scans, template, config.fit, None, None, True)
    sol = _fit_depth_jit(model, scans, st, pose, config)
    return _check(sol, bool(throw), "depth fit")
