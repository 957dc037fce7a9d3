"""NRD: non-rigid template fitting, one affine transform per vertex (Pishchulin et al. 2017, §3.1).

Every template vertex `p_i` gets a 3x4 affine transform `A_i`; the deformed vertex is
`A_i [p_i; 1]`. For fixed correspondences the energy of the paper's eqs. (1)-(4),

    E(A) = α E_d + β E_s + γ E_l
    E_d = (1 / N_valid) Σ_i w_i ‖A_i p̃_i − q_i‖²         (q_i: closest compatible scan point)
    E_s = (1 / N_nb)    Σ_i Σ_{j ∈ N(i)} ‖A_i − A_j‖_F²   (one-ring N(i), N_nb = Σ_i |N(i)|)
    E_l = (1 / N_lm)    Σ_l ‖A_{k(l)} p̃_{k(l)} − b_l‖²    (b_l: scan landmark of vertex k(l))

is quadratic in the transforms. Each round of the weight schedule recomputes the correspondences
from the current deformed template and then minimises `E` for them.

**Schedule** (paper §3.1; humanshape `NRD.m`, `nrdWidx = 3`). Round 0: `α = 0, β = 1e6,
γ = 1e-3` (landmarks and smoothness only). Then data rounds with `α = 1`, after each of which
`β := 0.25 β` (body and hands) and `γ := 0.25 γ`, until `β <= 1e3`: data rounds at β = 1e6,
2.5e5, 6.25e4, 1.56e4, 3.9e3, six solves in all. As in humanshape the loop also stops early when
the mean matched distance changes by at most `err_tol_mm`. "NRD CW" keeps the weights constant
and runs until that criterion (or `max_rounds`). The head's smoothness weight decays by
`head_smooth_decay` per round (1 = humanshape: the head stays stiff; 0.25 = the paper's text).

**Units and frame.** The API is in metres; internally the problem is solved in millimetres, in a
frame centred at the centroid of the initial vertices, because the weights are humanshape's
numbers for millimetres and a centred template: `‖A_i − A_j‖_F²` mixes the unitless linear part
with the translation part, so the same weights mean another energy in other units or with a
distant origin. Energies and data terms are reported in mm². The normalisations `1/N_valid`,
`1/N_nb`, `1/N_lm` are humanshape's; the paper's sums carry none, but its weights are only
meaningful with them. Returned transforms act on homogeneous initial vertices in metres, scan
frame: `vertices = transforms @ [init_vertices; 1]`.

**Correspondences** (recomputed in JAX every data round, from the deformed template and its
area-weighted vertex normals):

- body vertices: the closest scan point whose normal is at most `max_angle_deg` (60°) from the
  vertex normal, valid if it is within `max_dist_mm` (20 mm). This is the paper's "closest
  compatible point" and the rule of `bodyprior.sscape.compatible_correspondences` (tested equal);
  humanshape takes the plain nearest point and then gates it, which drops a vertex whenever the
  nearest point lies on a facing surface (e.g. the torso beside an arm);
- head vertices (humanshape `getNNheadAndBody`): a plane through three template vertices on the
  neck boundary of the `Head` bone's region, carried along with the deformation, splits template
  and scan. Head vertices above it (within `template.head_mask`) take the closest scan point above
  the plane within `head_max_dist_mm` (50 mm) whose displacement lies in a `head_cone_deg` (30°)
  cone around the outward vertex normal: the head can only be pushed outwards (hair, caps, holes);
- hand vertices (`template.hand_mask`): `α = γ = 0` (paper §4.1); smoothness only.

Both are exact radius searches on a uniform grid of the scan points built once per call (sorted
cell keys; the candidate runs of all queries processed in fixed-size chunks, so the work is the
number of candidates). The head search scans only the smallest ball around its cone. Compared
with a brute-force `V x P` search a round's search at 13,380 vertices and 40k points costs ~40 ms
of CPU instead of seconds.

**Solver.** For fixed correspondences the minimiser solves the normal equations `H X = R` with
one `4V x 4V` matrix `H = blockdiag(d_i p̃_i p̃_iᵀ) + L_w ⊗ I_4` for the three rows of all `A_i`
(`d_i`: data plus landmark weight of vertex `i`; `L_w`: the smoothness-weighted graph Laplacian).
It is solved matrix-free by preconditioned conjugate gradients in float64, warm-started from the
previous round, with a two-level preconditioner: block Jacobi (the 4x4 diagonal blocks, inverted
in closed form by Sherman-Morrison) plus an additive coarse correction on per-patch constant
transforms (`n_patches` connected patches built on the host; the coarse matrix is assembled and
inverted through its Cholesky factor in JAX every round, so that each step's coarse solve is one
matrix product). On the last round of the full-resolution benchmark (`benchmarks/nrd.py`, warm
start, `cg_rtol = 1e-2`): the two-level PCG converges in 23 steps (25 ms), block-Jacobi PCG in
20 (19 ms), but over the whole schedule block Jacobi alone needs ~4.7x the steps (779 vs 164 per
scan, 4 scans): the first rounds start far from their minimum and need the coarse level. Optimistix
Gauss-Newton with `lineax.Normal(lineax.CG)` (unpreconditioned CG on the same `H`, two residual
passes per step) makes no progress in 300 steps (1.5 s): `H` spans
many orders of magnitude (mm translations against unitless linear parts, and smooth modes of
`L_w` that only the data term pins). The energy is quadratic, so one exact
linear solve per round is the Gauss-Newton step; the PCG is that step with a usable
preconditioner.

**humanshape quirks** (research note sscape.md §3.6), decided:

1. Smoothness gradient half the true one: *fixed*; we minimise the stated energy exactly.
2. Landmark gradients overwritten when two landmarks share a vertex: *fixed* (accumulated).
3. Scan confidence indexed with subsample indices into the full-resolution array: *fixed* by
   using none (our scans carry no confidence: `c_i = 1`, which is what the bug amounts to for
   all-ones confidence).
4. 4-D homogeneous residual in the convergence test: *reproduced* (identical to the 3-D one).
5. L-BFGS-B truncated at 100 iterations per round: *fixed*; each round is solved to `cg_rtol`. The
   truncated original is reproduced in `benchmarks/nrd.py` (scipy L-BFGS-B, 100 iterations), which
   ends at a higher energy.

Also decided: the 20 mm body gate is the paper's (humanshape's code uses 50 mm); feet are not
excluded (humanshape drops its `idxFoot` vertices; the simulated scanner's soles are holes, which
the normal test handles); stage-0 correspondences are not computed (humanshape computes and
ignores them); vertex normals are area-weighted, not the first incident face's. A scan point on
the vertex itself counts as inside the head cone.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._aot import aot_filter_jit
from .._geometry import vertex_normals
from .._linalg import pcg
from .._solution import RESULTS, Solution, _check
from .._store import register_type
from .._validate import as_device_array, check_array, named_preset
from ._grid import _REACH, _CompatibleRule, _Grid, _grid_build, _grid_search
from ._scan import check_scan
from ._template import RegistrationTemplate

__all__ = ["NRDConfig", "NRDFit", "NRDPrep", "nrd", "nrd_batch", "prepare_nrd"]

_MM = 1000.0  # metres -> millimetres


# --------------------------------------------------------------------------------------------------
# Configuration and result


class NRDConfig(eqx.Module):
    """Weights, schedule, correspondence rules and solver settings of
    [`bodyprior.registration.nrd`][].

    All fields are Python scalars (static under `jit`); defaults follow the paper and humanshape.

    **Fields:**

    - `data_weight`: `α` of the data rounds (round 0 uses `α = 0`).
    - `smooth_weight`: `β` of rounds 0 and 1.
    - `landmark_weight`: `γ` of rounds 0 and 1.
    - `decay`: factor applied to `β` (body and hands) and `γ` after every data round.
    - `head_smooth_decay`: factor applied to the head's `β` after every data round (humanshape: 1).
    - `min_smooth_weight`: the schedule stops once `β <= min_smooth_weight`.
    - `constant_weights`: NRD CW - no decay; rounds run until the mean distance converges.
    - `max_rounds`: cap on the number of data rounds (the decay schedule needs 5 with the defaults).
    - `err_tol_mm`: stop when the mean matched distance changes by at most this (mm).
    - `max_dist_mm`, `max_angle_deg`: body compatibility gate (distance, normal angle).
    - `head_rule`: use humanshape's head rule (else head vertices follow the body rule).
    - `head_max_dist_mm`, `head_cone_deg`: the head rule's radius and cone half-angle.
    - `cg_rtol`: a round's solve stops when its preconditioned residual is this fraction of the one
      at its (warm) start: the energy gap to the round's minimum shrinks by about `cg_rtol²`.
      The default 1e-2 leaves ~1e-4 of each round's gap; 1e-3 and 1e-4 took 2.3x and 3.6x the
      steps with the same final energies and errors (6 simulated scans, `docs/benchmarks.md`).
    - `cg_max_steps`: conjugate-gradient steps per round at most.
    - `n_patches`: patches of the coarse preconditioner (0 = block Jacobi only). 32 and 64 ran
      equally fast on the full-resolution template; 128 (a 512 x 512 coarse inverse per round)
      took ~20 % longer, block Jacobi alone ~70 % longer.

    Beyond the paper (all off by default, which is the paper's energy; `NRDConfig.preset`):

    - `point_to_plane`: `λ` in [0, 1]: the data term of a vertex becomes
      `(y − q)ᵀ [(1 − λ) I + λ n nᵀ] (y − q)` with `n` the matched scan point's normal, so that
      with `λ → 1` a vertex is not pulled onto its scan *sample* (spacing ~10 mm at 19k points)
      but onto the surface through it, and no longer slides along the surface to reach it.
    - `tangent_weight`: `τ >= 0`: adds `τ / V_d Σ_i ‖(I − n⁰_i n⁰_iᵀ)(y_i − y⁰_i)‖²` over the
      data vertices (`y⁰`, `n⁰`: the initial vertices and their normals, mm²): motion along the
      initial surface costs like data error, motion along its normal is free. With an S-SCAPE
      initialisation this keeps the model's correspondence along featureless limbs, which the
      scan cannot see.
    - `landmark_decay`: factor applied to `γ` after every data round (None = `decay`, the
      paper; 1.0 keeps the landmarks at full weight).
    """

    data_weight: float = 1.0
    smooth_weight: float = 1e6
    landmark_weight: float = 1e-3
    decay: float = 0.25
    head_smooth_decay: float = 1.0
    min_smooth_weight: float = 1e3
    constant_weights: bool = False
    max_rounds: int = 10
    err_tol_mm: float = 1e-3
    max_dist_mm: float = 20.0
    max_angle_deg: float = 60.0
    head_rule: bool = True
    head_max_dist_mm: float = 50.0
    head_cone_deg: float = 30.0
    cg_rtol: float = 1e-2
    cg_max_steps: int = 2000
    n_patches: int = 64
    point_to_plane: float = 0.0
    tangent_weight: float = 0.0
    landmark_decay: float | None = None

    @classmethod
    def preset(cls, name: str, **overrides) -> NRDConfig:
        """A named configuration, with any field overridden by keyword.

        - `"paper"`: the paper's energy and schedule (humanshape `NRD.m`); equal to `NRDConfig()`.
          Measured on simulated scans it lowers the distance to the scan and *raises* the true
          correspondence error of an S-SCAPE initialisation (docs/results_sscape.md).
        - `"paper_cw"`: NRD CW, the paper's constant-weight variant.
        - `"anchored"`: the refinement of a model fit (S-SCAPE + NRD) that lowers the true error:
          the paper's schedule with a point-to-plane data term (`point_to_plane=0.9`), a
          tangential-motion penalty relative to the initialisation (`tangent_weight=1`) and a
          10 mm gate (`max_dist_mm`; the fit starts within millimetres, so farther points are
          other surfaces). Chosen on 8 simulated scans of a tuning seed (docs/results_sscape.md):
          true error 7.09 mm (S-SCAPE fit) -> 8.25 (paper) / 6.18 (anchored). Keeping the
          landmarks at full weight (`landmark_decay=1`) changed nothing there (6.42 both). Not
          meant for NRD from the static template: the tangent term anchors to the start. Without
          humanshape's head rule (`head_rule=False`; the scans have real heads); pass
          `head_rule=True` for CAESAR scans, whose heads are dummies.
        - `"caesar"`: `"anchored"` with the head rule, for CAESAR-like scans.
        """
        table = {
            "paper": {},
            "paper_cw": dict(constant_weights=True),
            "anchored": dict(
                point_to_plane=0.9, tangent_weight=1.0, max_dist_mm=10.0, head_rule=False
            ),
            "caesar": dict(point_to_plane=0.9, tangent_weight=1.0, max_dist_mm=10.0),
        }
        return named_preset(cls, table, name, overrides)

    def __check_init__(self):
        positive = dict(
            smooth_weight=self.smooth_weight,
            max_dist_mm=self.max_dist_mm,
            head_max_dist_mm=self.head_max_dist_mm,
            cg_rtol=self.cg_rtol,
        )
        for name, v in positive.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"`NRDConfig.{name}` must be a positive finite number, got {v!r}.")
        nonneg = dict(
            data_weight=self.data_weight,
            landmark_weight=self.landmark_weight,
            min_smooth_weight=self.min_smooth_weight,
            err_tol_mm=self.err_tol_mm,
        )
        nonneg["tangent_weight"] = self.tangent_weight
        for name, v in nonneg.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"`NRDConfig.{name}` must be a finite number >= 0, got {v!r}.")
        v = self.point_to_plane
        if not (isinstance(v, (int, float)) and 0 <= v <= 1):
            raise ValueError(f"`NRDConfig.point_to_plane` must lie in [0, 1], got {v!r}.")
        v = self.landmark_decay
        if v is not None and not (isinstance(v, (int, float)) and 0 < v <= 1):
            raise ValueError(
                f"`NRDConfig.landmark_decay` must be None or lie in (0, 1], got {v!r}."
            )
        for name in ("decay", "head_smooth_decay"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 1):
                raise ValueError(f"`NRDConfig.{name}` must lie in (0, 1], got {v!r}.")
        for name in ("max_angle_deg", "head_cone_deg"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 180):
                raise ValueError(f"`NRDConfig.{name}` must lie in (0, 180] degrees, got {v!r}.")
        for name, lo in (("max_rounds", 1), ("cg_max_steps", 1), ("n_patches", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"`NRDConfig.{name}` must be an int >= {lo}, got {v!r}.")
        if not self.constant_weights and self.decay == 1.0:
            raise ValueError(
                "`NRDConfig.decay` = 1 never reaches `min_smooth_weight`; use "
                "`constant_weights=True` for NRD CW."
            )

    @property
    def n_data_rounds(self) -> int:
        """Number of data rounds the schedule allows (before the early-stopping test)."""
        if self.constant_weights:
            return self.max_rounds
        n, beta = 0, self.smooth_weight
        while beta > self.min_smooth_weight and n < self.max_rounds:
            n, beta = n + 1, beta * self.decay
        return max(n, 1)


class NRDFit(eqx.Module):
    """The deformed template of [`bodyprior.registration.nrd`][] for one scan (the `value` of its
    [`bodyprior.Solution`][]; a leading batch axis from `nrd_batch`).

    **Fields:**

    - `vertices`: deformed template, shape `(V, 3)`, metres, scan frame.
    - `transforms`: per-vertex affine transforms, shape `(V, 3, 4)`, acting on `[init_vertices; 1]`
      in metres.
    - `valid`: shape `(V,)`, vertices with a compatible scan point in the last round.
    - `matches`: shape `(V,)`, index of that scan point (`-1` where not valid).
    """

    vertices: Float[Array, "V 3"]
    transforms: Float[Array, "V 3 4"]
    valid: Bool[Array, " V"]
    matches: Int[Array, " V"]


# --------------------------------------------------------------------------------------------------
# Host-side preparation (smoothness groups, head plane, coarse patches), built once per template


register_type(NRDFit, "bodyprior.registration.NRDFit")


class NRDPrep(eqx.Module):
    """A registration template prepared for NRD: the host-side bookkeeping of
    [`bodyprior.registration.nrd`][], computed once by [`bodyprior.registration.prepare_nrd`][] and
    passed in place of the template (`nrd(init, scan, prep)`), so that repeated calls skip it.

    Arrays are leaves, sizes static. **Fields:** `template` (the
    [`bodyprior.registration.RegistrationTemplate`][] it was built from, with its topology);
    `nbr` `(V, K)` one-rings padded with the vertex itself and `nbr_mask`; `group` `(V,)`
    smoothness group (0 body, 1 head, 2 hand); `data_ok` `(V,)` (not a hand vertex); `head_cand`
    `(H,)` head-rule candidates; `anchors` `(3,)` template vertices spanning the head/body plane and
    static `plane_sign`; `patch` `(V,)` coarse-preconditioner patch of every vertex; static
    `n_patches` (patches built), `requested_patches` (the `NRDConfig.n_patches` it serves) and
    `n_nb` (`sum_i |N(i)|`, each undirected edge twice).
    """

    template: RegistrationTemplate
    nbr: Int[Array, "V K"]
    nbr_mask: Bool[Array, "V K"]
    group: Int[Array, " V"]
    data_ok: Bool[Array, " V"]
    head_cand: Int[Array, " H"]
    anchors: Int[Array, " 3"]
    patch: Int[Array, " V"]
    plane_sign: float = eqx.field(static=True)
    n_patches: int = eqx.field(static=True)
    requested_patches: int = eqx.field(static=True)
    n_nb: int = eqx.field(static=True)

    @property
    def faces(self) -> Int[Array, "F 3"]:
        return self.template.faces


def _head_plane(verts, edges, head_bone, head_mask):
    """Three vertices on the neck boundary of the head-bone region (the head/body plane)."""
    if head_bone.sum() < 3 or (~head_bone).sum() < 1:
        return np.zeros(3, np.int32), 1.0, False
    cut = head_bone[edges[:, 0]] != head_bone[edges[:, 1]]
    ends = edges[cut].reshape(-1)
    ring = np.unique(ends[head_bone[ends]])
    if len(ring) < 3:
        return np.zeros(3, np.int32), 1.0, False
    x = verts[ring]
    c = x.mean(0)
    _, _, vt = np.linalg.svd(x - c)
    u, w, n = vt
    near = np.abs((x - c) @ n) <= np.percentile(np.abs((x - c) @ n), 50)
    cand = ring[near]
    pu, pw = (verts[cand] - c) @ u, (verts[cand] - c) @ w
    a, b = cand[np.argmax(pu)], cand[np.argmin(pu)]
    third = cand[np.argmax(np.abs(pw))]
    anchors = np.array([a, b, third], np.int32)
    p1, p2, p3 = verts[anchors]
    normal = np.cross(p2 - p1, p3 - p1)
    if np.linalg.norm(normal) < 1e-12:
        return np.zeros(3, np.int32), 1.0, False
    sign = 1.0 if (verts[head_bone].mean(0) - p1) @ normal > 0 else -1.0
    return anchors, sign, True


def _patches(verts, edges, n_patches):
    """Connected patches: farthest-point seeds, then each vertex to its geodesically nearest
    seed."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    n = verts.shape[0]
    k = int(min(n_patches, n))
    seeds = [0]
    d = np.linalg.norm(verts - verts[0], axis=1)
    for _ in range(k - 1):
        s = int(np.argmax(d))
        seeds.append(s)
        d = np.minimum(d, np.linalg.norm(verts - verts[s], axis=1))
    length = np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1) + 1e-12
    g = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    _, _, src = dijkstra(g, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    # Vertices unreachable from every seed (other components) get the Euclidean-nearest seed.
    far = src < 0
    if far.any():
        dd = np.linalg.norm(verts[far][:, None] - verts[seeds][None], axis=-1)
        src[far] = np.asarray(seeds)[dd.argmin(1)]
    lookup = np.full(n, -1, np.int64)
    lookup[np.asarray(seeds)] = np.arange(k)
    return lookup[src].astype(np.int32), k


def prepare_nrd(template: RegistrationTemplate, *, n_patches: int = 64) -> NRDPrep:
    """Prepares `template` for [`bodyprior.registration.nrd`][] once (host side, tens of ms for
    the 6,449-vertex template): smoothness groups from the hand/head masks, the head/body plane
    from the `Head` bone's skin weights, and `n_patches` connected patches for the coarse
    preconditioner (farthest-point seeds grown along edges).

    **Arguments:**

    - `template`: a [`bodyprior.registration.RegistrationTemplate`][].
    - `n_patches`: the `NRDConfig.n_patches` of the calls it will serve (0 = block Jacobi only).

    **Returns:** an [`bodyprior.registration.NRDPrep`][], accepted wherever `nrd`/`nrd_batch`
    take a template (with an `NRDConfig` of the same `n_patches`).
    """
    if not isinstance(template, RegistrationTemplate):
        raise ValueError(
            f"`template` must be a RegistrationTemplate, got {type(template).__name__}."
        )
    if isinstance(n_patches, bool) or not isinstance(n_patches, (int, np.integer)) or n_patches < 0:
        raise ValueError(f"`n_patches` must be a non-negative int, got {n_patches!r}.")
    return _prepare(template, int(n_patches))


def _prepare(tmpl: RegistrationTemplate, n_patches: int) -> NRDPrep:
    verts = np.asarray(tmpl.vertices, np.float64)
    topo = tmpl.topology
    edges = np.asarray(topo.edges)
    ring = np.asarray(topo.one_ring)
    mask = ring >= 0
    nbr = np.where(mask, ring, np.arange(verts.shape[0])[:, None]).astype(np.int32)
    hand = np.asarray(tmpl.hand_mask, bool)
    head = np.asarray(tmpl.head_mask, bool) & ~hand
    group = np.where(hand, 2, np.where(head, 1, 0)).astype(np.int32)
    # The head-bone region (without the neck) defines the plane, as humanshape's three vertices do.
    sidx = np.asarray(tmpl.rig.skin_indices)
    sw = np.asarray(tmpl.rig.skin_weights, np.float64)
    is_head_bone = np.array([n == "Head" for n in tmpl.joint_names])
    head_bone = (sw * is_head_bone[sidx]).sum(1) > 0.5
    if not head_bone.any():
        head_bone = head
    anchors, sign, ok = _head_plane(verts, edges, head_bone & head, head)
    head_cand = np.nonzero(head)[0].astype(np.int32) if ok else np.zeros(0, np.int32)
    if n_patches > 0:
        patch, k = _patches(verts, edges, n_patches)
    else:
        patch, k = np.zeros(verts.shape[0], np.int32), 0
    return NRDPrep(
        template=tmpl,
        nbr=as_device_array(nbr),
        nbr_mask=as_device_array(mask),
        group=as_device_array(group),
        data_ok=as_device_array(~hand),
        head_cand=as_device_array(head_cand),
        anchors=as_device_array(anchors),
        patch=as_device_array(patch),
        plane_sign=float(sign),
        n_patches=int(k),
        requested_patches=int(n_patches),
        n_nb=int(mask.sum()),
    )


# --------------------------------------------------------------------------------------------------
# Exact radius search on a uniform grid of the scan points


class _HeadRule(eqx.Module):
    """humanshape's head rule: a head scan point within `sqrt(r2)` whose displacement from vertex
    `q` lies in the cone of half-angle `acos(cos_cone)` around the outward vertex normal."""

    points: Float[Array, "P 3"]
    above: Bool[Array, " P"]
    queries: Float[Array, "Q 3"]
    qnormals: Float[Array, "Q 3"]
    cos_cone: float
    r2: float

    def __call__(self, qi, pi):
        delta = self.points[pi] - self.queries[qi]
        d2 = jnp.sum(delta**2, axis=-1)
        out = jnp.sum(delta * self.qnormals[qi], axis=-1)
        dist = jnp.sqrt(jnp.maximum(d2, 0.0))
        # a point on the vertex itself has no direction: it counts as inside the cone
        in_cone = (out >= self.cos_cone * dist) | (d2 <= 1e-12)
        return self.above[pi] & (d2 <= self.r2) & in_cone, d2


def _cone_ball(radius: float, half_angle_deg: float) -> tuple[float, float]:
    """Offset `c` along the axis and radius `ρ` of the smallest ball containing the cone sector
    {x : |x| <= radius, angle(x, axis) <= half_angle} (apex at 0): the head rule's search region."""
    a = math.radians(half_angle_deg)
    if a >= math.pi / 2:
        return 0.0, radius
    # the ball through the apex and the rim circle (radius cos a, radius sin a) on the axis
    c = radius / (2 * math.cos(a))
    if c > radius:  # wide cones: the rim circle's own ball is smaller and contains the apex
        return radius * math.cos(a), radius * math.sin(a)
    return c, c


def _grids(points, pmask, cfg: NRDConfig, prep: NRDPrep) -> tuple[_Grid, _Grid | None]:
    """The body grid (cells of `max_dist / _REACH`) and, with the head rule, the head grid."""
    grid_b = _grid_build(points, pmask, cfg.max_dist_mm / _REACH)
    if not (cfg.head_rule and prep.head_cand.shape[0] > 0):
        return grid_b, None
    ball = _cone_ball(cfg.head_max_dist_mm, cfg.head_cone_deg)[1]
    return grid_b, _grid_build(points, pmask, ball / _REACH)


def _correspond(prep: NRDPrep, cfg: NRDConfig, y, grids, points, normals, pmask):
    """Compatible scan point of every deformed template vertex (all in mm); `(idx, valid)`."""
    grid_b, grid_h = grids
    vn = vertex_normals(y, prep.faces)
    body_active = prep.data_ok
    if grid_h is not None:
        a = y[prep.anchors]
        n = prep.plane_sign * jnp.cross(a[1] - a[0], a[2] - a[0])
        hq = y[prep.head_cand]
        is_head = (hq - a[0]) @ n > 0
        body_active = body_active.at[prep.head_cand].set(~is_head & body_active[prep.head_cand])
    cos_max = math.cos(math.radians(cfg.max_angle_deg))
    body = _CompatibleRule(points, normals, y, vn, cos_max, cfg.max_dist_mm**2)
    idx = _grid_search(grid_b, y, body_active, body, _REACH)
    if grid_h is not None:
        above = pmask & ((points - a[0]) @ n > 0)
        hn = vn[prep.head_cand]
        cone = math.cos(math.radians(cfg.head_cone_deg))
        head = _HeadRule(points, above, hq, hn, cone, cfg.head_max_dist_mm**2)
        # Search the smallest ball around the cone instead of the whole head radius (~5x fewer
        # candidates); distances are still measured from the vertex, so the result is exact.
        offset, _ = _cone_ball(cfg.head_max_dist_mm, cfg.head_cone_deg)
        hidx = _grid_search(grid_h, hq + offset * hn, is_head, head, _REACH)
        idx = idx.at[prep.head_cand].set(jnp.where(is_head, hidx, idx[prep.head_cand]))
    valid = (idx >= 0) & prep.data_ok
    return jnp.where(valid, idx, -1), valid


# --------------------------------------------------------------------------------------------------
# The quadratic energy of one round and its normal equations (everything in mm, centred frame)


class _Round(eqx.Module):
    """Weights and targets of one round; `E(X)` for `X = (A_i)ᵀ`, shape `(V, 4, 3)`."""

    wd: Float[Array, " V"]  # α w_i / N_valid
    q: Float[Array, "V 3"]  # matched scan points (zero where w_i = 0)
    wl: Float[Array, " L"]  # γ / N_lm for used landmarks, else 0
    lm_v: Int[Array, " L"]  # template vertex of each landmark
    b: Float[Array, "L 3"]  # scan landmarks
    ws: Float[Array, " V"]  # β_g(i) / N_nb: weight of the directed pairs (i, j ∈ N(i))
    # Anisotropic terms (NRDConfig.point_to_plane / tangent_weight), None for the paper's energy:
    md: Float[Array, "V 3 3"] | None = None  # data metric (replaces wd_i I when given)
    mt: Float[Array, "V 3 3"] | None = None  # tangent-motion metric, about y0
    y0: Float[Array, "V 3"] | None = None  # initial vertices (mm, centred)


def _apply(ph: Float[Array, "V 4"], X: Float[Array, "V 4 3"]) -> Float[Array, "V 3"]:
    # Four fused multiply-adds: XLA:CPU runs the equivalent batched einsum 2.5x slower.
    y = ph[:, 0, None] * X[:, 0]
    for k in range(1, ph.shape[1]):
        y = y + ph[:, k, None] * X[:, k]
    return y


def _energy(X, ph, rnd: _Round, prep: NRDPrep) -> tuple[Array, tuple[Array, ...]]:
    """`E = α E_d + β E_s + γ E_l (+ τ E_t)` (weights folded into `rnd`) and its weighted terms
    `(E_d, E_s, E_l, E_t)`."""
    y = _apply(ph, X)
    if rnd.md is None:
        e_d = jnp.sum(rnd.wd * jnp.sum((y - rnd.q) ** 2, axis=-1))
    else:
        u = y - rnd.q
        e_d = jnp.einsum("vi,vij,vj->", u, rnd.md, u)
    e_t = jnp.zeros((), X.dtype)
    if rnd.mt is not None:
        u = y - rnd.y0
        e_t = jnp.einsum("vi,vij,vj->", u, rnd.mt, u)
    e_s = jnp.zeros((), X.dtype)
    for k in range(prep.nbr.shape[1]):  # one row gather per slot: XLA fuses these (5x a 4-D gather)
        sq = jnp.sum((X - X[prep.nbr[:, k]]) ** 2, axis=(-2, -1))
        e_s = e_s + jnp.sum(rnd.ws * prep.nbr_mask[:, k] * sq)
    e_l = jnp.sum(rnd.wl * jnp.sum((y[rnd.lm_v] - rnd.b) ** 2, axis=-1))
    return e_d + e_s + e_l + e_t, (e_d, e_s, e_l, e_t)


class _System(eqx.Module):
    """Normal equations `H X = R` of one round (`∇E / 2 = H X − R`), with the preconditioner."""

    ph: Float[Array, "V 4"]
    d: Float[Array, " V"]  # data + landmark weight per vertex: blockdiag(d_i p̃_i p̃_iᵀ)
    rhs: Float[Array, "V 4 3"]
    w: Float[Array, "V K"]  # symmetric edge weights of L_w over the padded one-ring
    deg: Float[Array, " V"]
    nbr: Int[Array, "V K"]
    patch: Int[Array, " V"]
    coarse_inv: Array | None  # inverse of the coarse matrix (4 n_patches square), symmetric
    # Anisotropic vertex blocks p̃ p̃ᵀ ⊗ M_i (None: M_i = d_i I): M_i, and M_i = U diag(lam) Uᵀ.
    m: Float[Array, "V 3 3"] | None = None
    m_vec: Float[Array, "V 3 3"] | None = None
    m_val: Float[Array, "V 3"] | None = None

    def mv(self, X):
        y = _apply(self.ph, X)
        lap = self.deg[:, None, None] * X
        for k in range(self.nbr.shape[1]):  # per-slot row gathers, fused by XLA
            lap = lap - self.w[:, k, None, None] * X[self.nbr[:, k]]
        if self.m is not None:
            return self.ph[:, :, None] * jnp.einsum("vij,vj->vi", self.m, y)[:, None, :] + lap
        return (self.d[:, None] * self.ph)[:, :, None] * y[:, None, :] + lap

    def precondition(self, r):
        # Block Jacobi: (d p̃ p̃ᵀ + deg I)⁻¹ by Sherman-Morrison; with M_i, per eigenvector of M_i
        # (in the rotated columns r U the block is diag_k(λ_k p̃ p̃ᵀ + deg I)).
        deg = jnp.maximum(self.deg, jnp.finfo(r.dtype).tiny)
        sq = jnp.sum(self.ph**2, axis=-1)
        if self.m is not None:
            ru = jnp.einsum("vaj,vjk->vak", r, self.m_vec)
            pr = _apply(self.ph, ru)  # (V, 3): p̃ᵀ r U
            s = self.m_val / (deg[:, None] + self.m_val * sq[:, None])
            zu = (ru - self.ph[:, :, None] * (s * pr)[:, None, :]) / deg[:, None, None]
            z = jnp.einsum("vak,vjk->vaj", zu, self.m_vec)
        else:
            pr = _apply(self.ph, r)
            s = self.d / (deg + self.d * sq)
            z = (r - (s[:, None] * self.ph)[:, :, None] * pr[:, None, :]) / deg[:, None, None]
        if self.coarse_inv is not None:
            n = self.coarse_inv.shape[0] // 4
            rc = jax.ops.segment_sum(r, self.patch, num_segments=n).reshape(4 * n, 3)
            zc = (self.coarse_inv @ rc).reshape(n, 4, 3)
            z = z + zc[self.patch]
        return z


def _system(rnd: _Round, ph, prep: NRDPrep, coarse: bool) -> _System:
    V = ph.shape[0]
    d_lm = jax.ops.segment_sum(rnd.wl, rnd.lm_v, num_segments=V)
    t_lm = jax.ops.segment_sum(rnd.wl[:, None] * rnd.b, rnd.lm_v, num_segments=V)
    m = m_vec = m_val = None
    if rnd.md is None and rnd.mt is None:
        d = rnd.wd + d_lm
        target = rnd.wd[:, None] * rnd.q + t_lm
    else:
        eye = jnp.eye(3, dtype=ph.dtype)
        md = rnd.wd[:, None, None] * eye if rnd.md is None else rnd.md
        m = md + d_lm[:, None, None] * eye
        target = jnp.einsum("vij,vj->vi", md, rnd.q) + t_lm
        if rnd.mt is not None:
            m = m + rnd.mt
            target = target + jnp.einsum("vij,vj->vi", rnd.mt, rnd.y0)
        m_val, m_vec = jnp.linalg.eigh(m)
        m_val = jnp.maximum(m_val, 0.0)
        d = jnp.trace(m, axis1=1, axis2=2) / 3.0  # isotropic stand-in for the coarse level
    rhs = ph[:, :, None] * target[:, None, :]
    w = (rnd.ws[:, None] + rnd.ws[prep.nbr]) * prep.nbr_mask
    deg = jnp.sum(w, axis=1)
    coarse_inv = None
    if coarse and prep.n_patches > 0:
        n = prep.n_patches
        dat = jax.ops.segment_sum(d[:, None, None] * ph[:, :, None] * ph[:, None, :], prep.patch, n)
        pi = jnp.broadcast_to(prep.patch[:, None], w.shape)
        W = jnp.zeros((n, n), ph.dtype).at[pi, prep.patch[prep.nbr]].add(w)
        lap = jnp.diag(jnp.sum(W, axis=1)) - W
        eye4 = jnp.eye(4, dtype=ph.dtype)
        C = lap[:, None, :, None] * eye4[None, :, None, :]
        C = C + jnp.eye(n, dtype=ph.dtype)[:, None, :, None] * dat[:, :, None, :]
        C = C.reshape(4 * n, 4 * n)
        # A relative ridge keeps the factor finite when a round constrains no global affine map
        # (no data and no landmarks); it only affects the preconditioner, not the solution.
        C = C + 1e-10 * jnp.mean(jnp.diag(C)) * jnp.eye(4 * n, dtype=ph.dtype)
        # The explicit inverse (once per round, ~3 ms at 256 x 256, ~12 ms at 512 x 512) makes the
        # coarse solve of each CG step one matrix product instead of two triangular solves.
        chol = jnp.linalg.cholesky(C)
        inv = jax.scipy.linalg.cho_solve((chol, True), jnp.eye(4 * n, dtype=ph.dtype))
        coarse_inv = 0.5 * (inv + inv.T)  # exactly symmetric, as PCG needs
    return _System(ph, d, rhs, w, deg, prep.nbr, prep.patch, coarse_inv, m, m_vec, m_val)


def _pcg(sys: _System, x0, rtol: float, max_steps: int):
    """[`bodyprior._linalg.pcg`][] on one round's system: the 3 rows of A as independent
    recursions when the vertex blocks are isotropic (`d_i I`), one coupled recursion otherwise."""
    if sys.m is None:
        return pcg(sys.mv, sys.precondition, sys.rhs, x0, rtol=rtol, max_steps=max_steps)
    mv = lambda x: sys.mv(x[..., 0])[..., None]  # noqa: E731
    pre = lambda x: sys.precondition(x[..., 0])[..., None]  # noqa: E731
    x, steps, res = pcg(mv, pre, sys.rhs[..., None], x0[..., None], rtol=rtol, max_steps=max_steps)
    return x[..., 0], steps, res


# --------------------------------------------------------------------------------------------------
# The schedule: one jitted call for all rounds


def _schedule(cfg: NRDConfig):
    """Per-round `(α, β_body, β_head, β_hand, γ)` as NumPy arrays, round 0 first."""
    n = cfg.n_data_rounds
    k = np.arange(n, dtype=np.float64)
    decay = 1.0 if cfg.constant_weights else cfg.decay
    head_decay = 1.0 if cfg.constant_weights else cfg.head_smooth_decay
    beta = np.concatenate([[cfg.smooth_weight], cfg.smooth_weight * decay**k])
    beta_head = np.concatenate([[cfg.smooth_weight], cfg.smooth_weight * head_decay**k])
    lm_decay = decay if cfg.landmark_decay is None or cfg.constant_weights else cfg.landmark_decay
    gamma = np.concatenate([[cfg.landmark_weight], cfg.landmark_weight * lm_decay**k])
    alpha = np.concatenate([[0.0], np.full(n, cfg.data_weight)])
    return alpha, beta, beta_head, gamma


def _run(
    init, prep: NRDPrep, lm_v, lm_use, points, normals, pmask, landmarks, lmask, cfg: NRDConfig
):
    dtype = init.dtype
    V = init.shape[0]
    alpha, beta, beta_head, gamma = (jnp.asarray(a, dtype) for a in _schedule(cfg))
    n_rounds = alpha.shape[0]
    centre = jnp.mean(init, axis=0)
    ph = jnp.concatenate([(init - centre) * _MM, jnp.ones((V, 1), dtype)], axis=1)
    q_all = (points - centre) * _MM
    b = (landmarks - centre) * _MM
    coarse = prep.n_patches > 0
    grids = _grids(q_all, pmask, cfg, prep)

    lm_on = lm_use & lmask
    n_lm = jnp.maximum(jnp.sum(lm_on), 1).astype(dtype)
    n_nb = float(max(prep.n_nb, 1))

    eye = jnp.eye(3, dtype=dtype)
    if cfg.tangent_weight > 0:
        # Tangent planes of the initial surface, data vertices only (hands: smoothness only).
        n0 = vertex_normals(ph[:, :3], prep.faces)
        n_data = jnp.maximum(jnp.sum(prep.data_ok), 1).astype(dtype)
        wt = cfg.tangent_weight * prep.data_ok.astype(dtype) / n_data
        mt = wt[:, None, None] * (eye - n0[:, :, None] * n0[:, None, :])

    def round_data(r, idx, valid):
        nv = jnp.sum(valid)
        wd = alpha[r] * valid / jnp.maximum(nv, 1).astype(dtype)
        q = jnp.where(valid[:, None], q_all[jnp.maximum(idx, 0)], 0.0)
        wl = gamma[r] * lm_on / n_lm
        per_group = jnp.stack([beta[r], beta_head[r], beta[r]]) / n_nb
        extra = {}
        if cfg.point_to_plane > 0:
            nq = jnp.where(valid[:, None], normals[jnp.maximum(idx, 0)], 0.0)
            lam = cfg.point_to_plane
            extra["md"] = wd[:, None, None] * (
                (1.0 - lam) * eye + lam * nq[:, :, None] * nq[:, None, :]
            )
        if cfg.tangent_weight > 0:
            # Off in round 0 (no data term yet): the landmarks and smoothness place the template.
            extra.update(mt=jnp.where(alpha[r] > 0, 1.0, 0.0) * mt, y0=ph[:, :3])
        return _Round(wd, q, wl, lm_v, b, per_group[prep.group], **extra), nv

    def solve(r, X, idx, valid):
        rnd, nv = round_data(r, idx, valid)
        X, steps, res = _pcg(_system(rnd, ph, prep, coarse), X, cfg.cg_rtol, cfg.cg_max_steps)
        e, _ = _energy(X, ph, rnd, prep)
        y = _apply(ph, X)
        dist = jnp.sqrt(jnp.sum((y - rnd.q) ** 2, axis=-1))
        nvf = jnp.maximum(nv, 1).astype(dtype)
        err = jnp.sum(jnp.where(valid, dist, 0.0)) / nvf
        data = jnp.sum(jnp.where(valid, dist**2, 0.0)) / nvf
        return X, (e, data, err, nv, steps, res)

    nan = jnp.full(n_rounds, jnp.nan, dtype)
    stats = dict(
        energy=nan,
        data_term=nan,
        mean_distance_mm=nan,
        n_valid=jnp.full(n_rounds, -1, jnp.int32),
        cg_steps=jnp.full(n_rounds, -1, jnp.int32),
        cg_residual=nan,
    )

    def record(stats, r, vals):
        e, data, err, nv, steps, res = vals
        new = dict(
            energy=e,
            data_term=data,
            mean_distance_mm=err,
            n_valid=nv,
            cg_steps=steps,
            cg_residual=res,
        )
        return {k: stats[k].at[r].set(new[k].astype(stats[k].dtype)) for k in stats}

    X0 = jnp.broadcast_to(jnp.eye(4, 3, dtype=dtype), (V, 4, 3))
    no_idx = jnp.full(V, -1, jnp.int32)
    no_valid = jnp.zeros(V, bool)
    # Round 0: landmarks and smoothness only (its correspondences would be unused).
    X, vals = solve(0, X0, no_idx, no_valid)
    stats = record(stats, 0, vals)
    stats["mean_distance_mm"] = stats["mean_distance_mm"].at[0].set(jnp.nan)
    stats["data_term"] = stats["data_term"].at[0].set(jnp.nan)

    def cond(s):
        r, _, err_prev, err, *_ = s
        return (r < n_rounds) & ~(jnp.abs(err_prev - err) <= cfg.err_tol_mm)

    def body(s):
        r, X, _, err, _, _, stats = s
        idx, valid = _correspond(prep, cfg, _apply(ph, X), grids, q_all, normals, pmask)
        X, vals = solve(r, X, idx, valid)
        return r + 1, X, err, vals[2], idx, valid, record(stats, r, vals)

    inf = jnp.asarray(jnp.inf, dtype)
    init_state = (jnp.ones((), jnp.int32), X, inf, -inf, no_idx, no_valid, stats)
    r, X, _, _, idx, valid, stats = jax.lax.while_loop(cond, body, init_state)

    y = _apply(ph, X)
    A = jnp.swapaxes(X, 1, 2)  # (V, 3, 4) = [L | t] in the centred mm frame
    lin = A[:, :, :3]
    t = A[:, :, 3] / _MM + centre - lin @ centre
    transforms = jnp.concatenate([lin, t[:, :, None]], axis=2)
    failed = jnp.any((stats["cg_steps"] >= cfg.cg_max_steps) & (stats["cg_residual"] > cfg.cg_rtol))
    result = RESULTS.where(failed, RESULTS.max_steps_reached, RESULTS.successful)
    result = RESULTS.where(jnp.all(jnp.isfinite(y)), result, RESULTS.nonfinite)
    fit = NRDFit(vertices=y / _MM + centre, transforms=transforms, valid=valid, matches=idx)
    stats = dict(
        stats,
        smooth_weight=jnp.where(jnp.arange(n_rounds) < r, beta, jnp.nan),
        landmark_weight=jnp.where(jnp.arange(n_rounds) < r, gamma, jnp.nan),
        rounds=r,
        num_steps=jnp.sum(jnp.maximum(stats["cg_steps"], 0)),
    )
    return Solution(fit, result, stats)


@aot_filter_jit
def _nrd_jit(init, prep, lm_v, lm_use, scan_arrays, cfg):
    return _run(init, prep, lm_v, lm_use, *scan_arrays, cfg)


@eqx.filter_jit
def _nrd_batch_jit(init, prep, lm_v, lm_use, scan_arrays, cfg):
    fn = lambda x, s: _run(x, prep, lm_v, lm_use, *s, cfg)
    return jax.vmap(fn)(init, scan_arrays)


def _nrd_kernel(replicated, item):
    """Per-scan kernel of `nrd_batch` for `batch_map` (several devices or processes)."""
    prep, lm_v, lm_use, cfg = replicated
    init, scan_arrays = item
    return _run(init, prep, lm_v, lm_use, *scan_arrays, cfg)


# --------------------------------------------------------------------------------------------------
# Public entry points


def _scan_arrays(scan, batched: bool):
    """Validated `(points, normals, point_mask, landmarks, landmark_mask)` of a `Scan`."""
    check_scan(scan, min_points=1, name="scans" if batched else "scan")
    want = 3 if batched else 2
    if scan.points.ndim != want:
        kind = "a batch of scans (leading axis B)" if batched else "one scan (no batch axis)"
        raise ValueError(
            f"`scan` must be {kind}: `scan.points` of shape {'(B, P, 3)' if batched else '(P, 3)'}"
            f", got shape {tuple(scan.points.shape)}."
        )
    arrays = (
        jnp.asarray(scan.points),
        jnp.asarray(scan.normals),
        jnp.asarray(scan.point_mask, bool),
        jnp.where(
            jnp.asarray(scan.landmark_mask, bool)[..., None], jnp.asarray(scan.landmarks), 0.0
        ),
        jnp.asarray(scan.landmark_mask, bool),
    )
    return arrays


def _template_and_prep(template, config) -> tuple[RegistrationTemplate, NRDPrep]:
    """`template` (a RegistrationTemplate, prepared here, or an NRDPrep) -> (template, prep)."""
    if not isinstance(config, NRDConfig):
        raise ValueError(f"`config` must be an NRDConfig, got {type(config).__name__}.")
    if isinstance(template, NRDPrep):
        if template.requested_patches != config.n_patches:
            raise ValueError(
                f"`template` is an NRDPrep built for n_patches={template.requested_patches} but "
                f"`config.n_patches` is {config.n_patches}; build it with "
                f"prepare_nrd(template, n_patches={config.n_patches})."
            )
        return template.template, template
    if not isinstance(template, RegistrationTemplate):
        raise ValueError(
            "`template` must be a RegistrationTemplate or an NRDPrep, got "
            f"{type(template).__name__}."
        )
    return template, _prepare(template, config.n_patches)


def _check_inputs(init_vertices, template, config, batched: bool):
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "NRD solves its normal equations in float64: enable it first with "
            "`jax.config.update('jax_enable_x64', True)`."
        )
    lead = ("B",) if batched else ()
    init = check_array(init_vertices, "init_vertices", (*lead, template.n_vertices, 3))
    return jnp.asarray(init, jnp.float64)


def _dtype_cast(init, arrays):
    dtype = init.dtype
    pts, nrm, pm, lms, lmm = arrays
    return (pts.astype(dtype), nrm.astype(dtype), pm, lms.astype(dtype), lmm)


def nrd(
    init_vertices: Float[ArrayLike, "V 3"],
    scan,
    template: RegistrationTemplate | NRDPrep,
    *,
    config: NRDConfig = NRDConfig(),
    throw: bool = True,
) -> Solution:
    """Non-rigid template fitting (NRD) of the template to one scan (see the module docstring).

    The whole schedule (all rounds, correspondences recomputed in each) is one jitted call; calls
    with the same shapes and config do not recompile. Run in float64 (`jax_enable_x64`): the
    normal equations are far too ill-conditioned for float32 conjugate gradients.

    **Arguments:**

    - `init_vertices`: the template mesh to deform, shape `(V, 3)`, metres, in the scan frame and
      in correspondence with `template` (`V = template.n_vertices`). "NRD": the static template
      aligned to the scan by the landmark similarity
      (`fit_similarity(...).apply(template.vertices)`); "S-SCAPE + NRD": `SScapeFit.vertices`.
      The transforms start at the identity on it.
    - `scan`: a [`bodyprior.registration.Scan`][] (points, unit normals, masks, landmarks in
      metres); landmarks are matched to the template's by name, missing ones are ignored.
    - `template`: the [`bodyprior.registration.RegistrationTemplate`][] (faces, landmarks,
      hand/head masks), prepared for NRD on the fly, or one prepared once with
      [`bodyprior.registration.prepare_nrd`][] (an [`bodyprior.registration.NRDPrep`][] built for
      `config.n_patches`), which skips that step in repeated calls.
    - `config`: an [`bodyprior.registration.NRDConfig`][]; `NRDConfig(constant_weights=True)` is
      NRD CW.
    - `throw`: raise if the result is not `RESULTS.successful`: a round's linear solve hit
      `cg_max_steps` without reaching `cg_rtol` (`max_steps_reached`), or non-finite vertices
      (else inspect `sol.result`). Using all rounds of the schedule is not a failure (the rule is
      [`bodyprior.Solution`][]'s).

    **Returns:** a [`bodyprior.Solution`][]: `value` an [`bodyprior.registration.NRDFit`][];
    `stats` a dict of per-round arrays with `R = 1 + config.n_data_rounds` entries (round 0 =
    landmarks and smoothness only; rounds not run, after an early stop, hold NaN, `-1` for
    integers): `energy` (`E` at each round's solution, mm², humanshape-normalised), `data_term`
    (`E_d`, mean squared matched distance, mm²), `mean_distance_mm` (mean matched distance after
    each round, humanshape's `err`), `n_valid` (matched vertices; 0 in round 0), `smooth_weight`,
    `landmark_weight` (body `β` and `γ` of each round), `cg_steps` (conjugate-gradient steps),
    `cg_residual` (final relative preconditioned residual of each round's solve); and scalars
    `rounds` (rounds run, including round 0) and `num_steps` (CG steps in all).

    **Raises:** `ValueError` for inputs of the wrong shape/type, non-finite values, or a scan
    without valid points.
    """
    template, prep = _template_and_prep(template, config)
    init = _check_inputs(init_vertices, template, config, batched=False)
    arrays = _scan_arrays(scan, batched=False)
    lm_v, lm_use = template.landmark_vertices(scan.landmark_names)
    sol = _nrd_jit(init, prep, lm_v, lm_use, _dtype_cast(init, arrays), config)
    return _check(sol, bool(throw), "NRD")


def nrd_batch(
    init_vertices: Float[ArrayLike, "B V 3"],
    scans,
    template: RegistrationTemplate | NRDPrep,
    *,
    config: NRDConfig = NRDConfig(),
    devices=None,
    chunk_size: int | None = None,
    progress: bool = False,
    strategy: str | None = None,
    throw: bool = True,
) -> Solution:
    """[`bodyprior.registration.nrd`][] for a batch of scans at once.

    On one device of one process: one jitted `jax.vmap` call over the whole batch. With several
    devices (`devices`, or more than one in `jax.devices()`), a `strategy`, or several
    `jax.distributed` processes: the per-scan fit through [`bodyprior.registration.batch_map`][]
    (chunks spread over the devices; every process takes its share of the batch and the results are
    gathered to every process; see its module docstring).

    **Arguments:** as `nrd`, with a leading batch axis `B` on `init_vertices` and on every array of
    `scans` (padded point clouds; padding has `point_mask = False`), plus `devices`, `chunk_size`,
    `progress` and `strategy` as in `batch_map` (used only on the multi-device path).

    **Returns:** a [`bodyprior.Solution`][] whose arrays have a leading axis `B` (`result` too:
    one per scan). With `throw=True` it raises once, naming the failed scans; with `False`, one
    failed scan leaves the others' results usable.
    """
    template, prep = _template_and_prep(template, config)
    init = _check_inputs(init_vertices, template, config, batched=True)
    arrays = _scan_arrays(scans, batched=True)
    if arrays[0].shape[0] != init.shape[0]:
        raise ValueError(
            f"`init_vertices` has {init.shape[0]} meshes but `scans` has "
            f"{arrays[0].shape[0]} scans."
        )
    lm_v, lm_use = template.landmark_vertices(scans.landmark_names)
    arrays = _dtype_cast(init, arrays)
    n_dev = len(jax.devices()) if devices is None else len(list(devices))
    if strategy is None and n_dev == 1 and jax.process_count() == 1:
        sol = _nrd_batch_jit(init, prep, lm_v, lm_use, arrays, config)
    else:
        from ._shard import batch_map

        sol = batch_map(
            _nrd_kernel,
            (prep, lm_v, lm_use, config),
            (init, arrays),
            devices=devices,
            chunk_size=chunk_size,
            progress=progress,
            desc="NRD",
            strategy=strategy,
        )
    return _check(sol, bool(throw), "NRD")
