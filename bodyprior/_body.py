"""The embedded default body: MakeHuman's phenotype shape space, local changes, facial actions and
rigs.

The phenotype model reproduces the MakeHuman macro-target interpolation as anny (0.6.2) implements
it: each
phenotype gets 1-D "hat" weights over its variations, every macro target's coefficient is the
product of
the weights of the variations it names, and the rest mesh is the template plus the weighted sum of
targets.
Joints (bone heads) are means of MakeHuman joint-cube vertices and are carried through the same
linear
map, so they follow the body shape exactly. Posing uses the convention of `docs/architecture.md`
(anny's
`local-ref` parameterisation): local rotations in world-aligned axes at each bone head.

Frame and units: metres, Z up, the body faces -Y, +X is the body's left.
"""

from __future__ import annotations

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._kinematics import forward_kinematics
from ._rig import Rig, RigHolder
from ._rotations import rotation_shape, rotation_to_matrix
from ._skinning import _axis_rotation, swing_twist_angle, twist_lbs
from ._validate import check_array, check_range, is_tracer
from .assets import load_asset

UNIT = 1e-4  # metres per int16 step in the asset

PHENOTYPES = (
    "gender",
    "age",
    "muscle",
    "weight",
    "height",
    "proportions",
    "cupsize",
    "firmness",
    "african",
    "asian",
    "caucasian",
)
"""Phenotype parameters, in the order of a phenotype vector. All lie in [0, 1]: gender 0 = male, 1
= female; age: the MakeHuman targets' anchors -1/3 = newborn, 0 = baby, 1/3 = child, 2/3 =
young, 1 = old; anny's morphological-age table (`bodyprior.age_to_years`, used by
`sample_population`) puts 0 at 0 years, 1/3 at ~8, 2/3 at ~16, 1 at 110 (18 y = 0.77, 64 y =
0.83; negative ages have no years); muscle, weight:
0 = min, 0.5 = average, 1 = max; height: 0 = min, 1 = max; proportions 0 = ideal, 1 = uncommon;
cupsize, firmness: 0 = min, 0.5 = average, 1 = max; african/asian/caucasian: ethnicity weights,
normalised by their sum (all zero = 1/3 each)."""
_INTERPOLATED = {  # feature -> (variations in asset order, first anchor, last anchor)
    "gender": (("male", "female"), 0.0, 1.0),
    "age": (("newborn", "baby", "child", "young", "old"), -1.0 / 3.0, 1.0),
    "muscle": (("minmuscle", "averagemuscle", "maxmuscle"), 0.0, 1.0),
    "weight": (("minweight", "averageweight", "maxweight"), 0.0, 1.0),
    "height": (("minheight", "maxheight"), 0.0, 1.0),
    "proportions": (("idealproportions", "uncommonproportions"), 0.0, 1.0),
    "cupsize": (("mincup", "averagecup", "maxcup"), 0.0, 1.0),
    "firmness": (("minfirmness", "averagefirmness", "maxfirmness"), 0.0, 1.0),
}
RIGS = ("cmu_mb", "game_engine")
# Valid range of each phenotype entry (values outside are rejected; anny would clamp them).
_PHENOTYPE_RANGES = {k: (-1.0 / 3.0, 1.0) if k == "age" else (0.0, 1.0) for k in PHENOTYPES}
_PHENOTYPE_HINTS = {
    "gender": " (0 = male, 1 = female)",
    "age": " (-1/3 = newborn, 0 = baby (0 y), 1/3 = child (~8 y), 2/3 = young (~16 y), "
    "0.77 = 18 y, 0.83 = 64 y, 1 = old (110 y); bodyprior.years_to_age converts)",
    "height": " (0 = min, 1 = max; not a length)",
}


def _range_text(k: str) -> str:
    lo, hi = _PHENOTYPE_RANGES[k]
    return f"[{'-1/3' if k == 'age' else f'{lo:g}'}, {hi:g}]{_PHENOTYPE_HINTS.get(k, '')}"


def phenotype_vector(**values: float) -> np.ndarray:
    """A phenotype vector, shape `(11,)`, from keyword values; unspecified entries are 0.5 (anny's
    default).

    Every entry lies in [0, 1] except `age`, in [-1/3, 1] (see [`bodyprior.PHENOTYPES`][]). `gender`
    0 is
    male and 1 is female (at `age=2/3`, gender 0 is ~14 cm taller, gender 1 has more breast and
    hip).

    **Example:** `phenotype_vector(gender=1.0, age=0.7, weight=0.8)` (a woman, somewhat older than a
    young
    adult, somewhat heavy).

    **Raises:** `ValueError` naming the entry for an unknown name or a value outside the entry's
    range.
    """
    unknown = set(values) - set(PHENOTYPES)
    if unknown:
        raise ValueError(f"unknown phenotype(s) {sorted(unknown)}; expected some of {PHENOTYPES}.")
    for k, v in values.items():
        x = float(v)
        lo, hi = _PHENOTYPE_RANGES[k]
        if not lo <= x <= hi:  # NaN fails too
            raise ValueError(f"`{k}` must lie in {_range_text(k)}, got {x}.")
    return np.array([float(values.get(k, 0.5)) for k in PHENOTYPES])


def variation_weights(
    phenotypes: Float[ArrayLike, " 11"], variation_labels: tuple[str, ...]
) -> Float[Array, " M"]:
    """Per-variation weights (anny's `phenotype_blendshape_weights` before the product rule).

    Interpolated features get piecewise-linear hat weights over evenly spaced anchors (values are
    clamped to
    the anchor range, as anny does without extrapolation); the ethnicity weights are normalised by
    their sum.
    """
    p = dict(zip(PHENOTYPES, phenotypes))
    out = {}
    for feat, (names, lo, hi) in _INTERPOLATED.items():
        n = len(names)
        x = jnp.clip(p[feat], lo, hi)
        anchors = jnp.linspace(lo, hi, n, dtype=x.dtype)
        spacing = (hi - lo) / (n - 1)
        w = jnp.clip(1.0 - jnp.abs(x - anchors) / spacing, 0.0, 1.0)
        out.update(zip(names, w))
    race = jnp.stack([p["african"], p["asian"], p["caucasian"]])
    total = race.sum()
    ok = total > 0
    race_w = jnp.where(ok, race / jnp.where(ok, total, 1.0), 1.0 / 3.0)
    out.update(zip(("african", "asian", "caucasian"), race_w))
    return jnp.stack([out[k] for k in variation_labels])


class BonePlacement(eqx.Module):
    """Where the default body's bones sit: MakeHuman's joint placement, linear in the body shape.

    Bone heads are the joints (the rest joints of [`bodyprior.rest_shape`][]): means of MakeHuman
    joint-cube vertices, carried through the same linear map as the mesh, so they follow the body
    shape exactly. Bones are in the order of the body's [`bodyprior.Rig`][] (`body.rig`).

    **Fields** (J bones; R, Rb, L, A as the shape bases of [`bodyprior.DefaultBody`][]):

    - `name`: static, the rig's name (`"cmu_mb"` or `"game_engine"`).
    - `head_template`: bone heads of the base body, shape `(J, 3)`, metres.
    - `head_basis`, `head_breast`, `head_local`, `head_face`: head displacement of every basis
      direction, shapes `(R, J, 3)` etc. (`None` where that basis was not loaded).
    - `tail_template`: bone tails of the base body, shape `(J, 3)`, metres.
    - `roll`: bone roll, shape `(J,)`, radians.
    """

    name: str = eqx.field(static=True)
    head_template: Float[Array, "J 3"]
    head_basis: Float[Array, "R J 3"]
    head_breast: Float[Array, "Rb J 3"] | None
    head_local: Float[Array, "L J 3"] | None
    head_face: Float[Array, "A J 3"] | None
    tail_template: Float[Array, "J 3"]
    roll: Float[Array, " J"]


class DefaultBody(RigHolder):
    """The embedded MakeHuman default body (CC0), as a JAX PyTree.

    Build it with [`bodyprior.load_default_body`][]. Arrays are leaves; labels and the bone tree are
    static.

    **Fields** (V = 13,380 vertices, F = 26,756 triangles, R = rank of the phenotype basis):

    - `template`: rest vertices of the base body, shape `(V, 3)`, metres.
    - `faces`: triangles, shape `(F, 3)`, counter-clockwise seen from outside.
    - `macro_masks`, `macro_coef`, `basis`: the 408 non-breast phenotype targets, each expressed
      exactly as
      `macro_coef[t] @ basis` (basis shape `(R, V * 3)`); `macro_masks[t]` names its variations.
    - `breast_*`: the 216 breast targets (only if loaded with `breast=True`; otherwise cupsize and
      firmness are fixed at 0.5, where these targets have zero weight — anny's default).
    - `local_basis`: local-change targets, shape `(2 C, V * 3)` (positive, negative per control), if
      loaded.
    - `face_basis`: the 52 facial-action targets, shape `(52, V * 3)`, if loaded.
    - `rig`: the skinned skeleton ([`bodyprior.Rig`][]): bone tree and names, skin weights, and the
      vertex joint regressor (joints as a fixed linear function of the surface, as S-SCAPE needs).
    - `bones`: MakeHuman's placement of the bone heads and tails ([`bodyprior.BonePlacement`][]).
    - `landmark_index`: template vertex of each named landmark.
    """

    template: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    macro_masks: Float[Array, "T M"]
    macro_coef: Float[Array, "T R"]
    basis: Float[Array, "R V3"]
    breast_masks: Float[Array, "Tb M"] | None
    breast_coef: Float[Array, "Tb Rb"] | None
    breast_basis: Float[Array, "Rb V3"] | None
    local_basis: Float[Array, "L V3"] | None
    face_basis: Float[Array, "A V3"] | None
    rig: Rig
    bones: BonePlacement
    landmark_index: Int[Array, " N"]
    variation_labels: tuple[str, ...] = eqx.field(static=True)
    local_labels: tuple[str, ...] = eqx.field(static=True)
    face_labels: tuple[str, ...] = eqx.field(static=True)
    landmark_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def n_vertices(self) -> int:
        return self.template.shape[0]


def _dense_sparse(ptr, idx, val, n_vertices) -> np.ndarray:
    T = len(ptr) - 1
    out = np.zeros((T, n_vertices, 3), np.float32)
    rows = np.repeat(np.arange(T), np.diff(ptr))
    out[rows, idx.astype(np.int64)] = val.astype(np.float32) * UNIT
    return out.reshape(T, -1)


def _normalized(w) -> np.ndarray:
    w = w.astype(np.float64)
    return w / w.sum(1, keepdims=True)


@functools.lru_cache(maxsize=8)
def _load_default_body_cached(
    rig: str, breast: bool, local_changes: bool, facial_actions: bool, dtype: str
):
    a = load_asset()
    dt = np.dtype(dtype)
    V = a["template_vertices"].shape[0]
    basis = np.concatenate(
        [a["macro_basis_int"].astype(np.float64) * UNIT, a["macro_basis_extra"].astype(np.float64)],
        0,
    )
    basis_points = np.concatenate([a["macro_basis_int_points"], a["macro_basis_extra_points"]], 0)
    nb = a["macro_nonbreast_index"]
    head = a[f"rig_{rig}_head_point"]
    tail = a[f"rig_{rig}_tail_point"]

    breast_masks = breast_coef = breast_basis = head_breast = None
    if breast:
        bi = a["breast_index"]
        sup = a["breast_support"]
        bb = np.zeros((len(a["breast_basis_int"]), V, 3))
        bb[:, sup] = a["breast_basis_int"].astype(np.float64) * UNIT
        breast_masks = a["macro_masks"][bi].astype(dt)
        breast_coef = a["breast_coef"].astype(dt)
        breast_basis = bb.reshape(len(bb), -1).astype(dt)
        head_breast = a["breast_basis_points"][:, head].astype(dt)
    local_basis = head_local = None
    if local_changes:
        local_basis = _dense_sparse(a["local_ptr"], a["local_idx"], a["local_val"], V).astype(dt)
        head_local = a["local_points"][:, head].astype(dt)
    face_basis = head_face = None
    if facial_actions:
        face_basis = _dense_sparse(a["face_ptr"], a["face_idx"], a["face_val"], V).astype(dt)
        head_face = a["face_points"][:, head].astype(dt)

    r = Rig(
        parents=tuple(int(p) for p in a[f"rig_{rig}_parents"]),
        joint_names=tuple(str(s) for s in a[f"rig_{rig}_labels"]),
        skin_indices=jnp.asarray(a[f"rig_{rig}_skin_index"], jnp.int32),
        skin_weights=jnp.asarray(_normalized(a[f"rig_{rig}_skin_weight"]), dt),
        regressor_indices=jnp.asarray(a[f"rig_{rig}_regressor_index"], jnp.int32),
        regressor_weights=jnp.asarray(a[f"rig_{rig}_regressor_weight"], dt),
    )
    bones = BonePlacement(
        name=rig,
        head_template=jnp.asarray(a["template_points"][head], dt),
        head_basis=jnp.asarray(basis_points[:, head], dt),
        head_breast=None if head_breast is None else jnp.asarray(head_breast),
        head_local=None if head_local is None else jnp.asarray(head_local),
        head_face=None if head_face is None else jnp.asarray(head_face),
        tail_template=jnp.asarray(a["template_points"][tail], dt),
        roll=jnp.asarray(a[f"rig_{rig}_roll"], dt),
    )
    return DefaultBody(
        template=jnp.asarray(a["template_vertices"], dt),
        faces=jnp.asarray(a["faces"], jnp.int32),
        macro_masks=jnp.asarray(a["macro_masks"][nb], dt),
        macro_coef=jnp.asarray(a["macro_coef"], dt),
        basis=jnp.asarray(basis.reshape(len(basis), -1), dt),
        breast_masks=None if breast_masks is None else jnp.asarray(breast_masks),
        breast_coef=None if breast_coef is None else jnp.asarray(breast_coef),
        breast_basis=None if breast_basis is None else jnp.asarray(breast_basis),
        local_basis=None if local_basis is None else jnp.asarray(local_basis),
        face_basis=None if face_basis is None else jnp.asarray(face_basis),
        rig=r,
        bones=bones,
        landmark_index=jnp.asarray(a["landmark_index"], jnp.int32),
        variation_labels=tuple(str(s) for s in a["variation_labels"]),
        local_labels=tuple(str(s) for s in a["local_labels"]),
        face_labels=tuple(str(s) for s in a["face_labels"]),
        landmark_names=tuple(str(s) for s in a["landmark_names"]),
    )


def load_default_body(
    rig: str = "cmu_mb",
    *,
    breast: bool = False,
    local_changes: bool = False,
    facial_actions: bool = False,
    dtype=np.float32,
) -> DefaultBody:
    """Loads the embedded default body (no network; cached per argument set).

    **Arguments:**

    - `rig`: `"cmu_mb"` (31 bones, the CMU motion-capture skeleton; default) or `"game_engine"` (53
      bones,
      with fingers).
    - `breast`: also load the 216 breast targets so that `cupsize` and `firmness` act (else they are
      fixed at 0.5, where those targets have zero weight, as in anny's default phenotype set).
    - `local_changes`: load the 256 local-change controls (≈ 80 MB as dense float32).
    - `facial_actions`: load the 52 ARKit-named facial-action targets.
    - `dtype`: floating dtype of the arrays.

    **Returns:** a [`bodyprior.DefaultBody`][].
    """
    if rig not in RIGS:
        raise ValueError(f"`rig` must be one of {RIGS}, got {rig!r}.")
    return _load_default_body_cached(
        rig, bool(breast), bool(local_changes), bool(facial_actions), np.dtype(dtype).name
    )


# ------------------------------------------------------------------------------------------------
# kernels (one body; vmap for batches)


def target_weights(
    variation_w: Float[ArrayLike, " M"], masks: Float[ArrayLike, "T M"]
) -> Float[Array, " T"]:
    """MakeHuman's product rule: a target's weight is the product of the weights of the variations
    it names."""
    return jnp.prod(variation_w * masks + (1.0 - masks), axis=-1)


def macro_coefficients(
    body: DefaultBody, phenotypes: Float[ArrayLike, " 11"]
) -> Float[Array, " T"]:
    """Weights of the 408 non-breast phenotype targets (product rule over variation weights)."""
    w = variation_weights(phenotypes, body.variation_labels).astype(body.macro_masks.dtype)
    return target_weights(w, body.macro_masks)


def _shape_terms(body: DefaultBody, phenotypes, local_changes, facial_actions):
    """(coefficient vector, basis) pairs whose products add up to the rest displacement."""
    p = jnp.asarray(phenotypes, body.template.dtype)
    terms = [(macro_coefficients(body, p) @ body.macro_coef, body.basis, body.bones.head_basis)]
    if body.breast_basis is not None:
        cb = target_weights(
            variation_weights(p, body.variation_labels).astype(p.dtype), body.breast_masks
        )
        terms.append((cb @ body.breast_coef, body.breast_basis, body.bones.head_breast))
    if local_changes is not None:
        x = jnp.asarray(local_changes, p.dtype)
        # control x in [-1, 1]: weight max(x, 0) on the positive target, max(-x, 0) on the negative
        # one
        c = jnp.stack([jnp.maximum(x, 0.0), jnp.maximum(-x, 0.0)], -1).reshape(-1)
        terms.append((c, body.local_basis, body.bones.head_local))
    if facial_actions is not None:
        terms.append((jnp.asarray(facial_actions, p.dtype), body.face_basis, body.bones.head_face))
    return terms


def _check_phenotypes(phenotypes):
    """Each entry within its own range: a `ValueError` on the host, `eqx.error_if` when traced."""
    check_array(phenotypes, "phenotypes", (len(PHENOTYPES),))
    lo = np.array([_PHENOTYPE_RANGES[k][0] for k in PHENOTYPES])
    hi = np.array([_PHENOTYPE_RANGES[k][1] for k in PHENOTYPES])
    messages = tuple(
        f"`phenotypes[{i}]` ({k}) must lie in {_range_text(k)}." for i, k in enumerate(PHENOTYPES)
    )
    if is_tracer(phenotypes):
        p = jnp.asarray(phenotypes)
        bad = (p < jnp.asarray(lo, p.dtype)) | (p > jnp.asarray(hi, p.dtype))
        return eqx.branched_error_if(p, jnp.any(bad), jnp.argmax(bad), messages)
    a = np.asarray(phenotypes, np.float64)
    bad = np.flatnonzero((a < lo) | (a > hi))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{messages[i][:-1]}, got {a[i]}.")
    return phenotypes


def _check_shape_inputs(body: DefaultBody, phenotypes, local_changes, facial_actions):
    """Validates the shape inputs; returns `phenotypes` (carrying the range check when traced)."""
    phenotypes = _check_phenotypes(phenotypes)
    if local_changes is not None:
        if body.local_basis is None:
            raise ValueError(
                "`local_changes` given but the body was loaded without them: "
                "use load_default_body(local_changes=True)."
            )
        check_array(local_changes, "local_changes", (len(body.local_labels),))
        check_range(local_changes, "local_changes", -1.0, 1.0)
    if facial_actions is not None:
        if body.face_basis is None:
            raise ValueError(
                "`facial_actions` given but the body was loaded without them: "
                "use load_default_body(facial_actions=True)."
            )
        check_array(facial_actions, "facial_actions", (len(body.face_labels),))
        check_range(facial_actions, "facial_actions", 0.0, 1.0)
    return phenotypes


def rest_shape(
    body: DefaultBody,
    phenotypes: Float[ArrayLike, " 11"],
    local_changes: Float[ArrayLike, " C"] | None = None,
    facial_actions: Float[ArrayLike, " A"] | None = None,
) -> tuple[Float[Array, "V 3"], Float[Array, "J 3"]]:
    """Rest (unposed) vertices and joints of one body.

    **Arguments:**

    - `body`: the [`bodyprior.DefaultBody`][].
    - `phenotypes`: shape `(11,)`, order [`bodyprior.PHENOTYPES`][], values in [0, 1] (age in [-1/3,
      1],
      down to newborns); `gender` 0 = male, 1 = female; see [`bodyprior.phenotype_vector`][]. An
      entry
      outside its range raises a `ValueError` naming it (under `jit`, a runtime `eqx.error_if`
      error).
    - `local_changes`: optional, shape `(C,)`, in [-1, 1] (needs `local_changes=True` at load).
    - `facial_actions`: optional, shape `(52,)`, in [0, 1] (needs `facial_actions=True` at load).

    **Returns:** `(vertices (V, 3), joints (J, 3))`, metres, A-pose rest frame (Z up, facing -Y).
    """
    phenotypes = _check_shape_inputs(body, phenotypes, local_changes, facial_actions)
    terms = _shape_terms(body, phenotypes, local_changes, facial_actions)
    disp = sum(c @ B for c, B, _ in terms)
    jdisp = sum(jnp.einsum("r,rjc->jc", c, Bj) for c, _, Bj in terms)
    return body.template + disp.reshape(-1, 3), body.bones.head_template + jdisp


def pose_matrices(pose, n_joints: int, pose_rep: str):
    """Validates a per-joint pose in representation `pose_rep` and converts it to `(J, 3, 3)`
    matrices."""
    shape = rotation_shape(pose_rep)
    check_array(pose, "pose", (n_joints, *shape))
    return jax.vmap(lambda x: rotation_to_matrix(x, pose_rep))(jnp.asarray(pose))


def evaluate(
    body: DefaultBody,
    phenotypes: Float[ArrayLike, " 11"],
    pose: Float[ArrayLike, "J ..."] | None = None,
    root_translation: Float[ArrayLike, " 3"] | None = None,
    *,
    local_changes: Float[ArrayLike, " C"] | None = None,
    facial_actions: Float[ArrayLike, " A"] | None = None,
    pose_rep: str = "axis_angle",
    skinning: str = "lbs",
) -> tuple[Float[Array, "V 3"], Float[Array, "J 3"]]:
    """Shapes and poses one default body: rest shape from phenotypes, then forward kinematics and
    skinning.

    **Arguments:**

    - `body`, `phenotypes`, `local_changes`, `facial_actions`: as [`bodyprior.rest_shape`][].
    - `pose`: per-joint local rotations in world-aligned axes at rest (anny's `local-ref`), shape
      `(J, *rotation_shape(pose_rep))`; `None` = rest pose. Joint order: `body.joint_names`.
    - `root_translation`: shape `(3,)`, metres, added to the root joint (`None` = 0).
    - `pose_rep`: `"axis_angle"` (default), `"matrix"`, `"quaternion"`, `"sixd"` or
      `"euler_<ORDER>"`.
    - `skinning`: `"lbs"` (linear blend), `"dqs"` (dual quaternion) or `"twist"`
      (twist-distributed LBS: the twist of each upper arm, forearm (with the wrist's twist moved
      onto it), thigh and shank about its rest axis turns linearly along the segment instead of
      at the joint, rigid per cross-section; [`bodyprior.twist_lbs`][], `TWIST_SEGMENTS`).

    **Returns:** `(vertices (V, 3), joints (J, 3))`, metres, world frame. Jittable, vmappable,
    differentiable in every array argument.
    """
    if skinning not in ("lbs", "dqs", "twist"):
        raise ValueError(f"`skinning` must be 'lbs', 'dqs' or 'twist', got {skinning!r}.")
    verts, joints = rest_shape(body, phenotypes, local_changes, facial_actions)
    J = body.n_joints
    if pose is None:
        R = jnp.broadcast_to(jnp.eye(3, dtype=verts.dtype), (J, 3, 3))
    else:
        R = pose_matrices(pose, J, pose_rep).astype(verts.dtype)
    if root_translation is None:
        t = jnp.zeros(3, verts.dtype)
    else:
        check_array(root_translation, "root_translation", (3,))
        t = jnp.asarray(root_translation, verts.dtype)
    if skinning == "twist":
        return _twist_skin(body, verts, joints, R, t)
    A, posed_joints = forward_kinematics(body.parents, R, joints, t)
    return body.rig.skin(verts, A, method=skinning), posed_joints


# Limb segments of the twist-distributed skinning: (bone, child whose head ends the segment, child
# whose twist about the segment axis moves onto the segment or None). The wrist's twist moves to
# the forearm (CMU puts forearm pronation in the wrist channel, panoman_v2 §6.10).
def _limb_segments(sides, arm, forearm, hand, thigh, shank, foot):
    """The four twist segments per side; the bone names are `str.format` patterns of the side."""
    return tuple(
        seg
        for side in sides
        for seg in (
            (arm.format(side), forearm.format(side), None),
            (forearm.format(side), hand.format(side), hand.format(side)),
            (thigh.format(side), shank.format(side), None),
            (shank.format(side), foot.format(side), None),
        )
    )


TWIST_SEGMENTS: dict[str, tuple[tuple[str, str, str | None], ...]] = {
    "cmu_mb": _limb_segments(
        ("Left", "Right"), "{}Arm", "{}ForeArm", "{}Hand", "{}UpLeg", "{}Leg", "{}Foot"
    ),
    "game_engine": _limb_segments(
        ("l", "r"), "upperarm_{}", "lowerarm_{}", "hand_{}", "thigh_{}", "calf_{}", "foot_{}"
    ),
}


def _twist_skin(body: DefaultBody, verts, joints, R, t):
    """Twist-distributed skinning (panoman_v2 §3.2 G3): per limb segment the twist about the rest
    axis is a rotation ramp along the bone, the swing is LBS; see [`bodyprior.twist_lbs`][]."""
    name = body.bones.name
    if name not in TWIST_SEGMENTS:
        raise ValueError(
            f"`skinning='twist'` needs a rig in {sorted(TWIST_SEGMENTS)}, got {name!r}."
        )
    index = {n: i for i, n in enumerate(body.joint_names)}
    bones, heads, axes, lengths, angles = [], [], [], [], []
    for bone, child, absorb in TWIST_SEGMENTS[name]:
        b, c = index[bone], index[child]
        d = joints[c] - joints[b]
        L = jnp.linalg.norm(d)
        a = d / L
        if absorb is not None:  # R_b <- R_b T_c, R_c <- T_c^T R_c: the child's world is unchanged
            k = index[absorb]
            Tc = _axis_rotation(a, swing_twist_angle(R[k], a))
            R = R.at[b].set(R[b] @ Tc).at[k].set(Tc.T @ R[k])
        bones.append(b)
        heads.append(joints[b])
        axes.append(a)
        lengths.append(L)
        angles.append(swing_twist_angle(R[b], a))
    A, posed_joints = forward_kinematics(body.parents, R, joints, t)
    rig = body.rig
    v = twist_lbs(
        verts,
        rig.skin_indices,
        rig.skin_weights,
        A,
        np.asarray(bones, np.int32),
        jnp.stack(heads),
        jnp.stack(axes),
        jnp.stack(lengths),
        jnp.stack(angles),
    )
    return v, posed_joints


def landmarks(body: DefaultBody, vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "N 3"]:
    """Positions of the named landmarks (`body.landmark_names`) on a mesh in the default
    topology."""
    return vertices[body.landmark_index]


def regress_joints(body: DefaultBody, vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "J 3"]:
    """Joints as a fixed linear function of the body vertices alone (the S-SCAPE convention).

    Fitted at asset build time so that, over the phenotype space, it reproduces the MakeHuman
    joint-cube
    positions; see the asset build log for its residual. Prefer [`bodyprior.rest_shape`][] for exact
    joints
    when the phenotypes are known.
    """
    if not is_tracer(vertices):
        check_array(vertices, "vertices", (body.n_vertices, 3))
    return body.rig.regress_joints(vertices)


def sscape_rig(body: DefaultBody) -> dict:
    """Deprecated: pass `rig=body.rig` to [`bodyprior.sscape.learn`][] instead.

    **Returns:** `{"rig": body.rig}`, so the old spelling `learn(..., **sscape_rig(body))` still
    works (with a `DeprecationWarning`).
    """
    warnings.warn(
        "`bodyprior.sscape_rig(body)` is deprecated: pass `rig=body.rig` to "
        "`bodyprior.sscape.learn`.",
        DeprecationWarning,
        stacklevel=2,
    )
    return {"rig": body.rig}
