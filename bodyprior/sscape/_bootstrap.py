"""Bootstrapping the registration with learned shape spaces (Pishchulin et al. 2017, §3.3, §4.5).

Register all scans with S-SCAPE + NRD initialised from a space, keep the registrations that pass a
quality gate, learn a new space from them and register every scan again from it; five passes in the
paper (1771, 3253, 3641, 4237, 4301 of 4308 CAESAR scans passed after each).

**The gate** replaces the paper's visual inspection, which it keeps because "low average fitting
errors do not always correspond to good results, since the fitting of localized areas may be
inaccurate". [`bodyprior.sscape.registration_gate`][] therefore checks the paper's fitting error
([`bodyprior.registration.fitting_error`][], nearest scan point within 50 mm and 60 deg) globally
*and*
per body part, ignoring the hands (the paper does not register them):

1. the fraction of (non-hand) template vertices whose fitting error is at most `threshold_mm`
   (10 mm) - vertices without a compatible point count as failures - is at least `min_fraction`;
2. in every body part (the template vertices grouped by their dominant skinning bone, merged into
   `GateConfig.parts`: head/neck, torso, and each upper arm, forearm, thigh, shank, foot), that
   fraction is at least `min_part_fraction`, so a misfit arm or leg cannot hide in a good average;
3. the 99th percentile of the valid errors is at most `max_error_mm` (a maximum-error bound that is
   robust to the few vertices at scan outliers or hole rims);
4. (off by default) the RMS distance of the registration's landmark vertices to the scan's
   landmarks is at most `max_landmark_rms_mm`. The fitting error cannot see vertices sliding
   along the surface; the landmarks can, though only through their placement noise (7.5 mm per
   coordinate in the simulated scans: RMS ~13 mm for a perfect registration, so only slides of
   several millimetres show).

The paper's error is a vertex-to-nearest-*point* distance, so even a perfect registration has
errors of the order of the scan's point spacing, and holes (armpits, crotch, soles, top of the
head) leave vertices without a compatible point; the thresholds therefore depend on the scanner.
[`bodyprior.sscape.calibrate_gate`][] sets them from registrations known to be good (in simulation
the ground-truth meshes of a few calibration scans; with real scans a few checked by eye): the
lowest reference fraction minus 0.05, the lowest reference part fraction minus 0.15, and 1.5 times
the largest reference 99th percentile. The `GateConfig` defaults are a fixed fallback.
`experiments/sscape_spaces.py` reports the calibration (`gate` in its metrics).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float
from tqdm.auto import tqdm

from .._geometry import closest_points_on_mesh, mesh_ring_faces
from .._store import register_type
from .._validate import as_device_array, check_array, check_positive_int
from ..registration import nearest_within
from ..registration._evaluate import fitting_error_batch
from ..registration._template import RegistrationTemplate
from ._learn import learn
from ._model import SScapeModel

__all__ = [
    "BootstrapPass",
    "BootstrapResult",
    "Registration",
    "GateConfig",
    "GateResult",
    "body_parts",
    "calibrate_gate",
    "bootstrap",
    "observed_vertices",
    "register_sscape_nrd",
    "registration_gate",
]

# Body parts by bone-name substrings (first match wins; order matters: "ForeArm" before "Arm").
_PARTS = (
    ("head", ("Head", "Neck")),
    ("left_forearm", ("LeftForeArm",)),
    ("right_forearm", ("RightForeArm",)),
    ("left_upper_arm", ("LeftArm", "LeftShoulder")),
    ("right_upper_arm", ("RightArm", "RightShoulder")),
    ("left_shank", ("LeftLeg",)),
    ("right_shank", ("RightLeg",)),
    ("left_thigh", ("LeftUpLeg", "LHipJoint")),
    ("right_thigh", ("RightUpLeg", "RHipJoint")),
    ("left_foot", ("LeftFoot", "LeftToe")),
    ("right_foot", ("RightFoot", "RightToe")),
    ("torso", ("Hips", "Spine", "LowerBack")),
)


@dataclasses.dataclass(frozen=True)
class GateConfig:
    """Thresholds of [`bodyprior.sscape.registration_gate`][] (see the module docstring).

    **Fields:** `threshold_mm` (10), `min_fraction` (0.85), `min_part_fraction` (0.6),
    `max_error_mm` (25), `max_dist` (0.05 m) and `max_angle_deg` (60) of the fitting error;
    `max_landmark_rms_mm` (inf = off) of the landmark test.
    """

    threshold_mm: float = 10.0
    min_fraction: float = 0.85
    min_part_fraction: float = 0.6
    max_error_mm: float = 25.0
    max_dist: float = 0.05
    max_angle_deg: float = 60.0
    max_landmark_rms_mm: float = float("inf")

    def __post_init__(self):
        for name in ("threshold_mm", "max_error_mm", "max_dist"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"`GateConfig.{name}` must be positive, got {v!r}.")
        for name in ("min_fraction", "min_part_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"`GateConfig.{name}` must lie in [0, 1], got {v!r}.")
        if not self.max_landmark_rms_mm > 0:  # inf allowed (off); NaN and <= 0 refused
            raise ValueError(
                "`GateConfig.max_landmark_rms_mm` must be positive (inf = off), got "
                f"{self.max_landmark_rms_mm!r}."
            )


class GateResult(NamedTuple):
    """Per-registration gate outcome (NumPy arrays with a leading scan axis `N`)."""

    accepted: np.ndarray
    """`(N,)` bool."""
    fraction: np.ndarray
    """`(N,)` fraction of non-hand vertices within `threshold_mm`."""
    worst_part_fraction: np.ndarray
    """`(N,)` the lowest per-part fraction."""
    worst_part: np.ndarray
    """`(N,)` index into `part_names` of that part."""
    p99_mm: np.ndarray
    """`(N,)` 99th percentile of the valid non-hand errors, mm."""
    part_names: tuple[str, ...]
    landmark_rms_mm: np.ndarray | None = None
    """`(N,)` RMS distance of the landmark vertices to the scan's (present, non-hand) landmarks."""


def body_parts(template: RegistrationTemplate) -> tuple[np.ndarray, tuple[str, ...]]:
    """Body-part label of every template vertex, `(V,)` int (`-1` = hands, not judged), and the
    part names (vertices grouped by their dominant skinning bone)."""
    sw = np.asarray(template.rig.skin_weights)
    si = np.asarray(template.rig.skin_indices)
    bone = si[np.arange(si.shape[0]), sw.argmax(1)]
    names = template.joint_names
    bone_part = np.full(len(names), -1)
    for j, n in enumerate(names):
        for p, (_, words) in enumerate(_PARTS):
            if any(n.startswith(w) or n == w for w in words):
                bone_part[j] = p
                break
    label = bone_part[bone]
    label[np.asarray(template.hand_mask)] = -1
    return label, tuple(p for p, _ in _PARTS)


def registration_gate(
    vertices: Float[ArrayLike, "N V 3"],
    scans,
    template: RegistrationTemplate,
    *,
    config: GateConfig = GateConfig(),
    errors=None,
) -> GateResult:
    """Automatic quality gate for registrations (replaces the paper's visual inspection).

    **Arguments:**

    - `vertices`: registrations `(N, V, 3)`, metres, scan frame.
    - `scans`: the batched [`bodyprior.registration.Scan`][] they were fitted to.
    - `template`: the [`bodyprior.registration.RegistrationTemplate`][] (faces, hands, skinning
      for parts).
    - `config`: a [`bodyprior.sscape.GateConfig`][].
    - `errors`: optional precomputed [`bodyprior.registration.FittingError`][] (batched) with the
      same
      `max_dist`/`max_angle_deg`, to avoid recomputing it.

    **Returns:** a [`bodyprior.sscape.GateResult`][].
    """
    if not isinstance(config, GateConfig):
        raise ValueError(f"`config` must be a GateConfig, got {type(config).__name__}.")
    if errors is None:
        errors = fitting_error_batch(
            vertices, scans, faces=template.faces, max_dist=config.max_dist,
            max_angle_deg=config.max_angle_deg,
        )  # fmt: skip
    e = np.asarray(errors.error_mm, np.float64)
    ok = np.asarray(errors.valid, bool)
    if e.ndim != 2 or e.shape[1] != template.n_vertices:
        raise ValueError(
            f"`vertices` must have shape (N, {template.n_vertices}, 3), got {e.shape}."
        )
    label, names = body_parts(template)
    judged = label >= 0
    within = ok & (e <= config.threshold_mm)
    frac = within[:, judged].mean(1)
    present = [p for p in range(len(names)) if np.any(label == p)]
    parts = np.stack([within[:, label == p].mean(1) for p in present], 1)
    worst = np.asarray(present)[parts.argmin(1)]
    worst_frac = parts.min(1)
    p99 = np.array(
        [np.percentile(ei[oi & judged], 99) if np.any(oi & judged) else np.inf
         for ei, oi in zip(e, ok)]
    )  # fmt: skip
    lm_rms = _landmark_rms(np.asarray(vertices, np.float64), scans, template)
    accepted = (
        (frac >= config.min_fraction)
        & (worst_frac >= config.min_part_fraction)
        & (p99 <= config.max_error_mm)
        & (lm_rms <= config.max_landmark_rms_mm)
    )
    return GateResult(accepted, frac, worst_frac, worst, p99, names, lm_rms)


def _landmark_rms(vertices: np.ndarray, scans, template: RegistrationTemplate) -> np.ndarray:
    """`(N,)` RMS distance (mm) of each registration's landmark vertices to its scan's landmarks
    (matched by name as NRD matches them; missing, unknown and hand landmarks left out; NaN
    without any)."""
    v_idx, use = (np.asarray(a) for a in template.landmark_vertices(scans.landmark_names))
    mask = np.asarray(scans.landmark_mask, bool).reshape(vertices.shape[0], -1) & use[None]
    lms = np.asarray(scans.landmarks, np.float64).reshape(vertices.shape[0], -1, 3)
    d2 = np.sum((vertices[:, v_idx] - lms) ** 2, axis=-1)
    n = mask.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, 1e3 * np.sqrt(np.sum(np.where(mask, d2, 0.0), 1) / n), np.nan)


def calibrate_gate(
    reference_meshes: Float[ArrayLike, "N V 3"],
    scans,
    template: RegistrationTemplate,
    *,
    fraction_margin: float = 0.05,
    part_margin: float = 0.15,
    error_factor: float = 1.5,
    landmark_factor: float | None = None,
    base: GateConfig = GateConfig(),
) -> GateConfig:
    """Gate thresholds calibrated on registrations known to be good.

    The paper's fitting error is a vertex-to-nearest-*point* distance, so even a perfect
    registration has errors of the order of the scan's point spacing (about 10 mm at 19,347 points
    on an adult body) and holes leave vertices without a compatible point. The gate's thresholds
    therefore depend on the scanner; this sets them from `reference_meshes` that are correct
    registrations of `scans` (in simulation: the ground-truth meshes; with real scans: a few
    registrations checked by eye): `min_fraction` = the lowest reference fraction within
    `threshold_mm` minus `fraction_margin`, `min_part_fraction` = the lowest reference part fraction
    minus `part_margin`, `max_error_mm` = the largest reference 99th percentile times
    `error_factor`, and with `landmark_factor` (e.g. 1.1) `max_landmark_rms_mm` = the largest
    reference landmark RMS times it (None: `base`'s, off by default). Only the thresholds come
    from the references; the registrations being judged are never compared with them.

    **Returns:** a [`bodyprior.sscape.GateConfig`][] (other fields from `base`).
    """
    g = registration_gate(reference_meshes, scans, template, config=base)
    extra = {}
    if landmark_factor is not None:
        if not (np.isfinite(landmark_factor) and landmark_factor > 0):
            raise ValueError(f"`landmark_factor` must be positive, got {landmark_factor!r}.")
        extra["max_landmark_rms_mm"] = float(np.nanmax(g.landmark_rms_mm) * landmark_factor)
    return dataclasses.replace(
        base,
        min_fraction=float(np.clip(g.fraction.min() - fraction_margin, 0.0, 1.0)),
        min_part_fraction=float(np.clip(g.worst_part_fraction.min() - part_margin, 0.0, 1.0)),
        max_error_mm=float(g.p99_mm.max() * error_factor),
        **extra,
    )


# --------------------------------------------------------------------------------------------------
# Registration and the bootstrapping loop


class Registration(NamedTuple):
    """Registrations of a batch of scans (NumPy, leading axis `N`)."""

    vertices: np.ndarray
    """`(N, V, 3)` registered template meshes, metres, scan frame."""
    poses: np.ndarray
    """`(N, J, 3)` axis-angle poses of the S-SCAPE fits (for NH posture normalization)."""
    similarities: object
    """Batched `Similarity` of the S-SCAPE fits (model frame -> scan frame)."""
    fit_vertices: np.ndarray | None = None
    """`(N, V, 3)` the S-SCAPE fits before the refinement, metres, scan frame."""
    coeffs: np.ndarray | None = None
    """`(N, K)` shape coefficients of the S-SCAPE fits, standard deviations."""
    successful: np.ndarray | None = None
    """`(N,)` bool: both the S-SCAPE fit and NRD returned `RESULTS.successful`."""


register_type(Registration, "bodyprior.sscape.Registration")


def register_sscape_nrd(
    model: SScapeModel,
    scans,
    template: RegistrationTemplate,
    *,
    fit_config=None,
    nrd_config=None,
    progress: bool = True,
) -> Registration:
    """S-SCAPE + NRD registration of a batch of scans: `fit_sscape_batch` with `model`, then `nrd`
    initialised from each fit (per scan, one jitted call each, compiled once).

    `nrd_config=None` is `NRDConfig.preset("anchored")`, the refinement that keeps the S-SCAPE
    fit's correspondence (the paper's schedule, `NRDConfig()`, lowers the distance to the scan and
    raises the true error: docs/results_sscape.md).

    **Returns:** a `Registration` `(vertices, poses, similarities)`.
    """
    from ..registration._nrd import NRDConfig, nrd, prepare_nrd
    from ._fit import FitConfig, fit_sscape_batch

    fit_config = FitConfig() if fit_config is None else fit_config
    nrd_config = NRDConfig.preset("anchored") if nrd_config is None else nrd_config
    sol = fit_sscape_batch(
        model, scans, template, config=fit_config, progress=progress, throw=False
    )
    fits = sol.value
    ok = ~np.asarray(sol.failed).reshape(-1)
    n = scans.points.shape[0]
    out = []
    prep = prepare_nrd(template, n_patches=nrd_config.n_patches)  # once for all scans
    for i in tqdm(range(n), desc="NRD", disable=not progress, unit="scan"):
        scan_i = jax.tree_util.tree_map(lambda a: a[i], scans)
        r = nrd(as_device_array(fits.vertices[i]), scan_i, prep, config=nrd_config, throw=False)
        out.append(np.asarray(r.value.vertices))
        ok[i] &= not bool(r.failed)
    return Registration(
        np.stack(out), np.asarray(fits.pose), fits.similarity, np.asarray(fits.vertices),
        np.asarray(fits.coeffs), ok,
    )  # fmt: skip


class BootstrapPass(NamedTuple):
    """One pass of [`bodyprior.sscape.bootstrap`][]."""

    model: SScapeModel
    """The space the pass's registrations were initialised from."""
    registration: Registration
    gate: GateResult
    n_accepted: int


class BootstrapResult(NamedTuple):
    passes: tuple[BootstrapPass, ...]
    model: SScapeModel
    """The space learned from the last pass's accepted registrations."""

    @property
    def accepted_per_pass(self) -> list[int]:
        return [p.n_accepted for p in self.passes]


def _resampler(faces, cand):
    """`(ref (N, V, 3), verts (N, V, 3)) -> (N, V, 3)`: the closest points on each `verts` surface
    to its `ref` vertices, over the candidate faces `cand` of each vertex (jitted once)."""

    def one(ref, verts):
        return closest_points_on_mesh(ref, verts, faces, candidates=cand)[0]

    return jax.jit(jax.vmap(one))


def _learn_from(meshes, tmpl, n_components):
    k = int(min(n_components, meshes.shape[0] - 1))
    return learn(jnp.asarray(meshes), tmpl.faces, n_components=k, rig=tmpl.rig)


@functools.partial(jax.jit, static_argnames="radius")
def _near_scan(vertices, points, mask, radius):
    return jax.vmap(lambda v, p, m: nearest_within(v, p, m, radius) >= 0)(vertices, points, mask)


def observed_vertices(vertices, scans, radius: float = 0.02) -> np.ndarray:
    """`(N, V)` bool: registration vertices within `radius` metres of a real (unpadded) point of
    their scan; the others lie over holes of the scan and were filled in by the fitter's prior.

    `vertices` `(N, V, 3)` metres in the scan frame; `scans` the batched
    [`bodyprior.registration.Scan`][]. Exact ([`bodyprior.registration.nearest_within`][], one
    compile per batch shape and radius)."""
    v = np.asarray(vertices, np.float64)
    check_array(v, "vertices", ("N", None, 3))
    pts = np.asarray(scans.points, np.float64)
    if pts.ndim != 3 or pts.shape[0] != v.shape[0]:
        raise ValueError(
            f"`scans` must be a batch of {v.shape[0]} scans (points (N, P, 3)), got points of "
            f"shape {pts.shape}."
        )
    if not radius > 0:
        raise ValueError(f"`radius` must be > 0 metres, got {radius!r}.")
    return np.asarray(_near_scan(v, pts, np.asarray(scans.point_mask, bool), float(radius)))


def bootstrap(
    init_model: SScapeModel,
    scans,
    template: RegistrationTemplate,
    *,
    n_passes: int = 5,
    n_components: int = 20,
    gate: GateConfig = GateConfig(),
    register: Callable[[SScapeModel, object], Registration] | None = None,
    fit_config=None,
    nrd_config=None,
    progress: bool = True,
    callback: Callable[[int, BootstrapPass], None] | None = None,
    correspondence: str = "frozen",
    rings: int = 3,
) -> BootstrapResult:
    """Bootstrapped registration (paper §3.3, §4.5): up to `n_passes` rounds of "register every
    scan from the current space, gate, learn a new space from the accepted registrations".

    Pass 0 registers from `init_model`; pass `r > 0` from the space learned on pass `r - 1`'s
    accepted registrations (Procrustes + PCA, [`bodyprior.sscape.learn`][], the template's rig,
    `min(n_components, n_accepted - 1)` components). If fewer than 2 registrations pass, the
    previous space is kept. Every scan is registered in every pass (rejected ones get another
    chance from the better space, as in the paper).

    **Correspondence.** Each pass's space has a different mean, and registering from it slides the
    template along every body's surface a little (a drift the fitting error cannot see, as it
    measures only distances to the scan). Over passes the slides accumulate: with the paper's
    plain loop (`correspondence="none"`) the true error of 20 simulated scans rose 6.53 -> 7.19 ->
    7.71 -> 8.04 mm over 4 passes, nearly all of it tangential, while the distance to the scans
    stayed the same. With `correspondence="first_accepted"` a scan's first accepted registration
    fixes its correspondence: each later registration of the scan is re-sampled at the closest
    points on its surface to that registration's vertices (candidate faces within `rings`
    edge-rings of each vertex, [`bodyprior.mesh_ring_faces`][]); the correspondence stops sliding,
    but the surfaces still got ~0.1 mm worse per pass on 60 scans (each space learned from
    registrations fits the next time a little worse than the one before).

    With `correspondence="frozen"` (default) a scan's first accepted registration is final: later
    passes register every scan (one batched call) but keep the accepted ones as they were, so
    bootstrapping only adds scans (the paper's purpose: the 1771 of 4308 scans that its first
    space registers grow to 4301) and the true error of a registration can never rise. The loop
    then stops at its fixed point: once every scan is accepted, or after a pass `r >= 1` that
    accepts no new scan (the next space would be learned from the same registrations as this
    pass's, and the next pass would repeat it). `accepted_per_pass` may be shorter than
    `n_passes`.

    **Arguments:**

    - `init_model`: the initial space (learned on a separate, smaller data set).
    - `scans`: batched [`bodyprior.registration.Scan`][].
    - `template`: the [`bodyprior.registration.RegistrationTemplate`][].
    - `n_passes`: passes (paper: 5).
    - `n_components`: components of the learned spaces.
    - `gate`: a [`bodyprior.sscape.GateConfig`][].
    - `register`: `(model, scans) -> Registration`; default
      [`bodyprior.sscape.register_sscape_nrd`][] with `fit_config`/`nrd_config`.
    - `progress`: progress bars.
    - `callback`: called as `callback(r, pass)` after each pass (e.g. to log or checkpoint).
    - `correspondence`: `"frozen"` (keep each scan's first accepted registration; stop at the
      fixed point), `"first_accepted"` (re-sample later registrations onto the scan's first
      accepted one), or `"none"` (the paper's loop); above.
    - `rings`: edge-rings of candidate faces of the re-sampling (the largest slide it can undo is
      about `rings` edge lengths: 3 rings ~ 4 cm on the decimated template).

    **Returns:** a [`bodyprior.sscape.BootstrapResult`][] (`accepted_per_pass` is the paper's list).
    """
    if isinstance(n_passes, bool) or not isinstance(n_passes, int) or n_passes < 1:
        raise ValueError(f"`n_passes` must be a positive int, got {n_passes!r}.")
    if not isinstance(init_model, SScapeModel):
        raise ValueError(f"`init_model` must be an SScapeModel, got {type(init_model).__name__}.")
    if init_model.n_vertices != template.n_vertices:
        raise ValueError(
            f"`init_model` has {init_model.n_vertices} vertices, the template "
            f"{template.n_vertices}."
        )
    if correspondence not in ("frozen", "first_accepted", "none"):
        raise ValueError(
            "`correspondence` must be 'frozen', 'first_accepted' or 'none', got "
            f"{correspondence!r}."
        )
    rings = check_positive_int(rings, "rings")
    if register is None:

        def register(model, s):
            return register_sscape_nrd(
                model, s, template, fit_config=fit_config, nrd_config=nrd_config, progress=progress
            )

    model = init_model
    passes = []
    freeze = correspondence == "frozen"
    keep = correspondence == "first_accepted"
    if keep:
        cand = jnp.asarray(mesh_ring_faces(template.faces, template.n_vertices, rings))
        resample = _resampler(jnp.asarray(template.faces), cand)
    anchor, kept, has = None, None, None  # first accepted vertices / registrations; (N,) set
    for r in range(n_passes):  # host loop over passes; each stage is a jitted batched call
        reg = register(model, scans)
        if has is None:
            has = np.zeros(np.asarray(reg.vertices).shape[0], bool)
        if keep:
            v = np.asarray(reg.vertices)
            if anchor is None:
                anchor = v.copy()
            else:  # every row re-sampled (one compile), kept where the scan has an anchor
                moved = np.asarray(resample(jnp.asarray(anchor), jnp.asarray(v)))
                v = np.where(has[:, None, None], moved, v)
                reg = reg._replace(vertices=v)
        if freeze and kept is not None:  # accepted scans keep their first accepted registration
            reg = _take_rows(has, kept, reg)
        g = registration_gate(reg.vertices, scans, template, config=gate)
        new = np.asarray(g.accepted, bool) & ~has
        if keep:
            anchor[new] = np.asarray(reg.vertices)[new]
        if freeze:
            kept = reg if kept is None else _take_rows(new, reg, kept)
        has |= new
        p = BootstrapPass(model, reg, g, int(g.accepted.sum()))
        passes.append(p)
        if callback is not None:
            callback(r, p)
        if p.n_accepted >= 2:
            model = _learn_from(reg.vertices[g.accepted], template, n_components)
        if freeze and (has.all() or (r >= 1 and not new.any())):
            break  # the fixed point: another pass would repeat this one
    return BootstrapResult(tuple(passes), model)


def _take_rows(mask, a, b):
    """Registration with the rows (scans) of `a` where `mask` `(N,)`, else those of `b`. A field
    whose rows differ in shape (`coeffs` of spaces with different component counts) or that one
    side lacks becomes `None`."""

    def pick(x, y):
        if x is None or y is None:
            return None
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            return None
        return np.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x, y)

    out = {}
    for f in Registration._fields:
        x, y = getattr(a, f), getattr(b, f)
        if f == "similarities" and x is not None and y is not None:
            out[f] = jax.tree_util.tree_map(pick, x, y)
        else:
            out[f] = pick(x, y)
    return Registration(**out)
