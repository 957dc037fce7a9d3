"""Motion-capture poses for DSPP: CMU BVH clips retargeted onto the default body's `cmu_mb` rig.

**Pose representation.** A pose is the local rotation of the 20 rig bones in
[`bodyprior.POSE_JOINTS`][] as Euler angles in the order [`bodyprior.EULER_ORDER`][]
(radians), in bodyprior's kinematics convention: world-aligned axes at the default body's A-pose
rest (Z up, body facing -Y, +X = body's left; docs/architecture.md). The root (`Hips`) orientation
is not part of a pose (as in the paper, which drops the Hips root because it is a global rotation),
so a pose is the body expressed in its pelvis frame; all other rig bones (`LHipJoint`/`RHipJoint`,
toes, fingers, thumbs) stay at rest. `bodyprior.evaluate(body, phen, rig_pose(body, euler))`
shows the pose on the default body.

**Retargeting.** The BVH skeletons and the rig differ in rest posture (CMU: offsets rest close to a
T-pose, Daz: a T-pose; rig: A-pose with bent elbows) and in proportions. For each rig bone `j`
with a mocap counterpart ("driver" `d(j)`) the rig's world rotation is set to

    W_j(t) = G_d(j)(t) C_j

where `G` is the mocap world rotation (converted from the BVH's Y-up/facing-+Z axes to bodyprior's
by `x -> (x, -z, y)`) and `C_j` is a fixed rest-compensation rotation that takes the rig's rest
bone direction `b_j` to the mocap's rest direction `u_j` (both world vectors at rest, where every
frame is world-aligned). `C_j` is built down the tree: `C_j = S(C_a b_j -> u_j) C_a`, with `a` the
nearest ancestor that is the root or a pose bone and `S(x -> y)` the smallest rotation taking
direction `x` to `y`, and `C_root = I` (both skeletons stand upright, facing forward). So at the
mocap's rest pose each rig joint is a pure swing in its parent's frame (an elbow unbends about its
hinge, no twist is introduced), twist comes from the mocap, and posed bone directions match:
`W_j b_j ∥ G_d(j) u_j`. The local rotation of pose bone `j` is `R_j = W_a^T W_j`; rig bones that are
not pose bones stay at the identity, so their mocap rotation is composed into the next pose bone
below. The root frame `W_root` is dropped.

**Joint maps** (rig bone <- mocap driver; its direction is driver -> end in the mocap and rig head
-> rig end point in the rig, by default the head of the rig bone named like the mocap end; left
side shown, the right side mirrors it):

| rig bone | CMU (MotionBuilder names) | end | Daz-friendly | end |
|---|---|---|---|---|
| Hips (root) | Hips | - (C = I) | hip | - (C = I) |
| LHipJoint (not a pose bone) | LHipJoint | LeftUpLeg | lButtock | lThigh |
| LeftUpLeg | LeftUpLeg | LeftLeg | lThigh | lShin |
| LeftLeg | LeftLeg | LeftFoot | lShin | lFoot |
| LeftFoot | LeftFoot | LeftToeBase | lFoot | End Site (rig end: toe tail) |
| LeftToeBase (not a pose bone) | LeftToeBase | End Site | - | - |
| LowerBack | LowerBack | Spine | abdomen | chest (rig end: Spine1 head) |
| Spine | Spine | Spine1 | - (identity: composed into LowerBack) | - |
| Spine1 | Spine1 | Neck1 (rig end: Neck head) | chest | neck (rig end: Neck head) |
| Neck | Neck | Neck1 | neck | head (rig end: Head head) |
| Neck1 | Neck1 | Head | - (identity: composed into Neck) | - |
| Head | Head | End Site (rig end: Head tail) | head | - (no direction: C = C_Neck) |
| LeftShoulder | LeftShoulder | LeftArm | lCollar | lShldr |
| LeftArm | LeftArm | LeftForeArm | lShldr | lForeArm |
| LeftForeArm | LeftForeArm | LeftHand | lForeArm | lHand |
| LeftHand | LeftFingerBase | LeftHandIndex1 (rig end: LeftHandFinger1 head) | lHand | lMid1 |

The CMU hand segment belongs to the zero-offset joint `LeftFingerBase` (CMU's `lhand`; the BVH
`LeftHand` is CMU's `lwrist`), so its world rotation, which includes `LeftHand`'s, drives the rig
hand. Dropped (no data): CMU `LeftHandIndex1`, `LThumb`; Daz fingers, thumbs and eyes. The
3ds-Max-named CMU files are renamed to MotionBuilder names first (`_MAX_TO_MB`, from
shared/data/mocap/SOURCES.md).

**Frames.** Dropped at the start of a clip: frame 0 of MotionBuilder-named CMU files (a synthetic
T-pose added by the conversion); frames 0-7 of Daz-friendly files (the fixed rest pose and a 7-frame
blend from it into the motion: in all 43 acLSTM files the largest per-frame joint-angle change is
14-153 degrees over frames 0-8 and at most 8 degrees from frame 8 to 9). 3ds-Max files start with
motion. Clips are resampled by nearest frame at `fps` (4 in the paper) using the true capture rate
(`frame_rates`: the acLSTM readme gives salsa 60 fps although the headers say 120).

**Corrupt frames.** Poses whose local rotation angle exceeds `_MAX_LOCAL_DEG` at the head, neck or
spine (100 degrees for Head/Neck/Neck1, 120 for LowerBack/Spine/Spine1) are dropped. In the shared
set these are data glitches: the head of CMU 60_06 and of the second half of 60_07 (salsa 06, 07)
is flipped upside down (150-180 degrees, while no other clip exceeds 90), and single frames bend
the lower back by up to 151 degrees (salsa 09). At 4 fps this drops 118 poses of salsa 06 (all)
and 54 of salsa 07.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._body import DefaultBody, evaluate, load_default_body, phenotype_vector, rest_shape
from ._bvh import Bvh, read_bvh
from ._render import contact_sheet, save_png
from ._rotations import (
    axis_angle_to_matrix,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
)
from ._validate import check_array, is_tracer

__all__ = [
    "EULER_ORDER",
    "POSE_JOINTS",
    "PoseSet",
    "find_mocap_dir",
    "load_mocap",
    "pose_euler",
    "render_poses",
    "rig_pose",
    "split_by_clip",
]

#: The 20 `cmu_mb` rig bones of a pose, in rig order: the CMU body joints without the root (Hips),
#: the pelvis-to-hip bones `LHipJoint`/`RHipJoint` (no degrees of freedom in CMU data), the toes
#: (absent from the Daz-friendly clips) and the fingers/thumbs (no mocap data).
POSE_JOINTS: tuple[str, ...] = (
    "LeftUpLeg", "LeftLeg", "LeftFoot",
    "LowerBack", "Spine", "Spine1",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
    "Neck", "Neck1", "Head",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand",
    "RightUpLeg", "RightLeg", "RightFoot",
)  # fmt: skip

#: Euler order of [`bodyprior.PoseSet`][] angles (intrinsic, as
#: [`bodyprior.euler_to_matrix`][]; use `pose_rep="euler_" + EULER_ORDER`). Chosen on the shared
#: CMU clips as the order whose middle angle comes least close to ±90° (gimbal lock).
EULER_ORDER: str = "XYZ"

# BVH axes (Y up, facing +Z, +X = body's left) -> bodyprior axes (Z up, facing -Y, +X = left)
_M = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# 3ds-Max-friendly CMU names -> MotionBuilder-friendly names (shared/data/mocap/SOURCES.md, B)
_MAX_TO_MB = {
    "LeftHip": "LeftUpLeg", "LeftKnee": "LeftLeg", "LeftAnkle": "LeftFoot",
    "LeftToe": "LeftToeBase", "RightHip": "RightUpLeg", "RightKnee": "RightLeg",
    "RightAnkle": "RightFoot",
    "RightToe": "RightToeBase", "lowerback": "LowerBack", "Chest": "Spine", "Chest2": "Spine1",
    "lowerneck": "Neck", "Neck": "Neck1", "LeftCollar": "LeftShoulder", "LeftShoulder": "LeftArm",
    "LeftElbow": "LeftForeArm", "LeftWrist": "LeftHand", "lhand": "LeftFingerBase",
    "LFingers": "LeftHandIndex1", "RightCollar": "RightShoulder", "RightShoulder": "RightArm",
    "RightElbow": "RightForeArm", "RightWrist": "RightHand", "rhand": "RightFingerBase",
    "RFingers": "RightHandIndex1",
}  # fmt: skip

# rig bone -> (mocap driver joint, mocap end point, rig end point); a mocap end "J/end" is J's End
# Site; a rig end ("head"|"tail", bone). Rig bones absent from a table are not driven (identity).
_LEFT_CMU = {
    "LHipJoint": ("LHipJoint", "LeftUpLeg", ("head", "LeftUpLeg")),
    "LeftUpLeg": ("LeftUpLeg", "LeftLeg", ("head", "LeftLeg")),
    "LeftLeg": ("LeftLeg", "LeftFoot", ("head", "LeftFoot")),
    "LeftFoot": ("LeftFoot", "LeftToeBase", ("head", "LeftToeBase")),
    "LeftToeBase": ("LeftToeBase", "LeftToeBase/end", ("tail", "LeftToeBase")),
    "LeftShoulder": ("LeftShoulder", "LeftArm", ("head", "LeftArm")),
    "LeftArm": ("LeftArm", "LeftForeArm", ("head", "LeftForeArm")),
    "LeftForeArm": ("LeftForeArm", "LeftHand", ("head", "LeftHand")),
    "LeftHand": ("LeftFingerBase", "LeftHandIndex1", ("head", "LeftHandFinger1")),
}
_CENTER_CMU = {
    "Hips": ("Hips", None, None),
    "LowerBack": ("LowerBack", "Spine", ("head", "Spine")),
    "Spine": ("Spine", "Spine1", ("head", "Spine1")),
    "Spine1": ("Spine1", "Neck1", ("head", "Neck")),
    "Neck": ("Neck", "Neck1", ("head", "Neck1")),
    "Neck1": ("Neck1", "Head", ("head", "Head")),
    "Head": ("Head", "Head/end", ("tail", "Head")),
}
_LEFT_DAZ = {
    "LHipJoint": ("lButtock", "lThigh", ("head", "LeftUpLeg")),
    "LeftUpLeg": ("lThigh", "lShin", ("head", "LeftLeg")),
    "LeftLeg": ("lShin", "lFoot", ("head", "LeftFoot")),
    "LeftFoot": ("lFoot", "lFoot/end", ("tail", "LeftToeBase")),
    "LeftShoulder": ("lCollar", "lShldr", ("head", "LeftArm")),
    "LeftArm": ("lShldr", "lForeArm", ("head", "LeftForeArm")),
    "LeftForeArm": ("lForeArm", "lHand", ("head", "LeftHand")),
    "LeftHand": ("lHand", "lMid1", ("head", "LeftHandFinger1")),
}
_CENTER_DAZ = {
    "Hips": ("hip", None, None),
    "LowerBack": ("abdomen", "chest", ("head", "Spine1")),
    "Spine1": ("chest", "neck", ("head", "Neck")),
    "Neck": ("neck", "head", ("head", "Head")),
    "Head": ("head", None, None),
}


def _mirror_name(name: str) -> str:
    for a, b in (("Left", "Right"), ("LHip", "RHip"), ("LThumb", "RThumb")):
        if name.startswith(a):
            return b + name[len(a) :]
    if len(name) > 1 and name[0] == "l" and name[1].isupper():  # Daz: lThigh -> rThigh
        return "r" + name[1:]
    return name


def _mirror(table: dict) -> dict:
    out = {}
    for rig, (drv, end, (kind, bone)) in table.items():
        out[_mirror_name(rig)] = (_mirror_name(drv), _mirror_name(end), (kind, _mirror_name(bone)))
    return out


_MAPS = {
    "cmu": {**_CENTER_CMU, **_LEFT_CMU, **_mirror(_LEFT_CMU)},
    "daz": {**_CENTER_DAZ, **_LEFT_DAZ, **_mirror(_LEFT_DAZ)},
}
# joints whose presence identifies each skeleton kind
_KIND_SIGNATURE = {
    "cmu_mb": ("Hips", "LHipJoint", "LeftUpLeg", "LowerBack", "Spine1", "Neck1", "LeftFingerBase"),
    "cmu_3dsmax": ("Hips", "LHipJoint", "LeftHip", "lowerback", "Chest2", "lowerneck", "lhand"),
    "daz": ("hip", "abdomen", "chest", "lButtock", "lThigh", "lCollar", "lMid1", "rMid1"),
}
# kind -> (joint map, index of the first motion frame)
_KIND_INFO = {"cmu_mb": ("cmu", 1), "cmu_3dsmax": ("cmu", 0), "daz": ("daz", 8)}

# largest plausible local rotation angle (degrees) per pose bone; larger ones are data glitches
_MAX_LOCAL_DEG = {"Head": 100.0, "Neck": 100.0, "Neck1": 100.0,
                  "LowerBack": 120.0, "Spine": 120.0, "Spine1": 120.0}  # fmt: skip

#: Default true capture rates (frames per second) by a directory-name substring: the acLSTM
#: readme.txt gives salsa 60 (indian and martial 120, as their headers say).
DEFAULT_FRAME_RATES: dict[str, float] = {"salsa": 60.0}


# --------------------------------------------------------------------------------------------------
# the data container


class PoseSet(eqx.Module):
    """Poses from motion capture, retargeted to the `cmu_mb` rig (see the module docstring).

    **Fields:**

    - `euler`: shape `(N, 20, 3)`, radians, Euler angles in order
      [`bodyprior.EULER_ORDER`][] of the local rotations of `joint_names`.
    - `clip`: shape `(N,)`, int, index into `clip_names` of each pose's clip.
    - `clip_names`: static, one name per clip (`"<folder>/<file stem>"`).
    - `joint_names`: static, [`bodyprior.POSE_JOINTS`][].
    - `fps`: static, the sampling rate (poses per second of motion).
    """

    euler: Float[Array, "N 20 3"]
    clip: Int[Array, " N"]
    clip_names: tuple[str, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True, default=POSE_JOINTS)
    fps: float = eqx.field(static=True, default=4.0)

    def __check_init__(self):
        if not is_tracer(self.euler):
            check_array(self.euler, "euler", (None, len(self.joint_names), 3))
            check_array(self.clip, "clip", (self.euler.shape[0],), integer=True)

    @property
    def n_poses(self) -> int:
        return self.euler.shape[0]

    def subset(self, index) -> PoseSet:
        """The poses at `index` (int array, boolean mask or slice); clip names are kept."""
        if is_tracer(self.euler) or is_tracer(self.clip):
            euler, clip = self.euler[index], self.clip[index]
        else:  # host data: index in NumPy (no compilation per index shape)
            euler = jnp.asarray(np.asarray(self.euler)[index])
            clip = jnp.asarray(np.asarray(self.clip)[index])
        return PoseSet(euler, clip, self.clip_names, self.joint_names, self.fps)

    def poses_per_clip(self) -> np.ndarray:
        """Number of poses of each clip, shape `(len(clip_names),)`."""
        return np.bincount(np.asarray(self.clip), minlength=len(self.clip_names))


# --------------------------------------------------------------------------------------------------
# rig pose <-> Euler


@functools.lru_cache(maxsize=8)
def _pose_index(joint_names: tuple[str, ...]) -> np.ndarray:
    missing = [n for n in POSE_JOINTS if n not in joint_names]
    if missing:
        raise ValueError(
            f"`body` must have the cmu_mb rig (bones {POSE_JOINTS}); missing {missing}. Use "
            "bodyprior.load_default_body('cmu_mb')."
        )
    return np.array([joint_names.index(n) for n in POSE_JOINTS])


def rig_pose(body: DefaultBody, euler: Float[Array, "20 3"]) -> Float[Array, "J 3"]:
    """Axis-angle pose of every rig joint from a DSPP pose.

    **Arguments:**

    - `body`: a [`bodyprior.DefaultBody`][] with the `cmu_mb` rig.
    - `euler`: shape `(20, 3)`, radians, order [`bodyprior.EULER_ORDER`][], joints
      [`bodyprior.POSE_JOINTS`][].

    **Returns:** shape `(J, 3)` axis-angle local rotations in `body.joint_names` order (root and
    non-pose bones zero), for [`bodyprior.evaluate`][]. Jittable, vmappable, differentiable.
    """
    idx = _pose_index(body.joint_names)
    check_array(euler, "euler", (len(POSE_JOINTS), 3))
    euler = jnp.asarray(euler)
    if not jnp.issubdtype(euler.dtype, jnp.floating):
        euler = euler.astype(jnp.result_type(float))
    aa = jax.vmap(lambda e: matrix_to_axis_angle(euler_to_matrix(e, EULER_ORDER)))(euler)
    return jnp.zeros((body.n_joints, 3), aa.dtype).at[idx].set(aa)


def pose_euler(body: DefaultBody, pose: Float[Array, "J 3"]) -> Float[Array, "20 3"]:
    """DSPP pose from an axis-angle rig pose: the inverse of [`bodyprior.rig_pose`][].

    The root and non-pose bones of `pose` are ignored.

    **Arguments:**

    - `body`: a [`bodyprior.DefaultBody`][] with the `cmu_mb` rig.
    - `pose`: shape `(J, 3)`, axis-angle local rotations (radians) in `body.joint_names` order.

    **Returns:** shape `(20, 3)`, radians, Euler angles in [`bodyprior.EULER_ORDER`][].
    """
    idx = _pose_index(body.joint_names)
    check_array(pose, "pose", (body.n_joints, 3))
    pose = jnp.asarray(pose)
    if not jnp.issubdtype(pose.dtype, jnp.floating):
        pose = pose.astype(jnp.result_type(float))
    return jax.vmap(lambda a: matrix_to_euler(axis_angle_to_matrix(a), EULER_ORDER))(pose[idx])


# --------------------------------------------------------------------------------------------------
# retargeting (host side, float64)


def skeleton_kind(bvh: Bvh) -> str:
    """`"cmu_mb"`, `"cmu_3dsmax"` or `"daz"` from the joint names (`ValueError` otherwise)."""
    names = set(bvh.joint_names)
    for kind, sig in _KIND_SIGNATURE.items():
        if all(n in names for n in sig):
            return kind
    raise ValueError(
        "unknown skeleton: expected the CMU MotionBuilder-, 3ds-Max- or Daz-friendly joint names "
        f"(e.g. {_KIND_SIGNATURE['cmu_mb'][:3]}, {_KIND_SIGNATURE['daz'][:3]}), got "
        f"{bvh.joint_names[:6]}..."
    )


def _rename(bvh: Bvh, mapping: Mapping[str, str]) -> Bvh:
    return dataclasses.replace(bvh, joint_names=tuple(mapping.get(n, n) for n in bvh.joint_names))


def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return None if n < 1e-9 else v / n


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector `a` to unit vector `b` (any half turn if opposite)."""
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # antiparallel: half turn about any axis perpendicular to a
        perp = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
        axis, s, c = perp / np.linalg.norm(perp), 0.0, -1.0
    else:
        axis = axis / s
    with jax.enable_x64(True):
        return np.asarray(_aa_to_matrix(jnp.asarray(axis * np.arctan2(s, c))))


_aa_to_matrix = jax.jit(axis_angle_to_matrix)


@dataclasses.dataclass(frozen=True)
class _Retarget:
    """Precomputed retargeting of one BVH skeleton (joint names, offsets) onto the rig."""

    rig_index: tuple[int, ...]  # rig bone per pose joint
    driver: tuple[int, ...]  # mocap joint per pose joint, -1 = none
    anchor: tuple[int, ...]  # pose-joint index of the anchor `a`, -1 = root
    root_driver: int
    C: np.ndarray  # (20, 3, 3) rest compensation, bodyprior axes
    C_root: np.ndarray


_RIG_REST_CACHE: dict[int, tuple] = {}


def _rig_rest(body: DefaultBody) -> tuple[np.ndarray, np.ndarray]:
    """Rest heads and tails of the default body (default phenotypes), float64, metres (cached)."""
    hit = _RIG_REST_CACHE.get(id(body))
    if hit is not None and hit[0] is body:
        return hit[1], hit[2]
    with jax.enable_x64(True):
        _, heads = rest_shape(body, phenotype_vector())
        heads = np.asarray(heads, np.float64)
        # tails are fixed template points: move them with their bone head's shape displacement
        tails = np.asarray(body.rig.tail_template, np.float64) + (
            heads - np.asarray(body.rig.head_template, np.float64)
        )
    if len(_RIG_REST_CACHE) >= 4:
        _RIG_REST_CACHE.clear()
    _RIG_REST_CACHE[id(body)] = (body, heads, tails)
    return heads, tails


def _build_retarget(bvh: Bvh, table: Mapping, body: DefaultBody) -> _Retarget:
    names = body.joint_names
    parents = body.parents
    heads, tails = _rig_rest(body)
    rest = bvh.rest_positions() @ _M.T  # mocap rest joint positions, bodyprior axes
    end = (np.asarray(bvh.rest_positions()) + np.nan_to_num(bvh.end_offsets)) @ _M.T
    has_end = ~np.isnan(bvh.end_offsets[:, 0])

    def mocap_point(spec: str) -> np.ndarray:
        if spec.endswith("/end"):
            j = bvh.joint_index(spec[:-4])
            if not has_end[j]:
                raise ValueError(f"joint {spec[:-4]!r} has no End Site")
            return end[j]
        return rest[bvh.joint_index(spec)]

    pose_set = set(POSE_JOINTS)
    C_rig = {0: np.eye(3)}  # rig bone -> C, filled in rig (parents-first) order
    for j in range(1, len(names)):
        a = parents[j]
        while a != 0 and names[a] not in pose_set:
            a = parents[a]
        Ca = C_rig[a]
        entry = table.get(names[j])
        u = b = None
        if entry is not None and entry[1] is not None:
            drv, mend, (kind, bone) = entry
            u = _unit(mocap_point(mend) - rest[bvh.joint_index(drv)])
            rig_end = (heads if kind == "head" else tails)[names.index(bone)]
            b = _unit(rig_end - heads[j])
        C_rig[j] = Ca if u is None or b is None else _swing(Ca @ b, u) @ Ca

    rig_index, driver, anchor = [], [], []
    for n in POSE_JOINTS:
        j = names.index(n)
        rig_index.append(j)
        entry = table.get(n)
        driver.append(-1 if entry is None else bvh.joint_index(entry[0]))
        a = parents[j]
        while a != 0 and names[a] not in pose_set:
            a = parents[a]
        anchor.append(-1 if a == 0 else POSE_JOINTS.index(names[a]))
    return _Retarget(
        rig_index=tuple(rig_index),
        driver=tuple(driver),
        anchor=tuple(anchor),
        root_driver=bvh.joint_index(table["Hips"][0]),
        C=np.stack([C_rig[j] for j in rig_index]),
        C_root=C_rig[0],
    )


def mocap_world_rotations(bvh: Bvh, frames=None) -> np.ndarray:
    """World rotations of every BVH joint in bodyprior axes, shape `(F, J, 3, 3)` (float64)."""
    L = bvh.local_rotations(frames)
    G = np.empty_like(L)
    for j, p in enumerate(bvh.parents):
        G[:, j] = L[:, j] if p < 0 else G[:, p] @ L[:, j]
    return _M @ G @ _M.T


def retarget_matrices(bvh: Bvh, body: DefaultBody, frames=None, *, _cache=None) -> np.ndarray:
    """Local rotation matrices of the 20 pose bones, shape `(F, 20, 3, 3)`, for BVH frames.

    **Arguments:**

    - `bvh`: a CMU (MotionBuilder or 3ds-Max names) or Daz-friendly [`bodyprior.Bvh`][].
    - `body`: the default body with the `cmu_mb` rig.
    - `frames`: optional frame indices (default all).

    **Returns:** rotation matrices in bodyprior's convention (see the module docstring).
    """
    kind = skeleton_kind(bvh)
    if kind == "cmu_3dsmax":
        bvh = _rename(bvh, _MAX_TO_MB)
    # the rest compensation depends only on the skeleton (names and offsets), not on the motion
    key = (kind, bvh.joint_names, bvh.offsets.tobytes(), bvh.end_offsets.tobytes())
    rt = None if _cache is None else _cache.get(key)
    if rt is None:
        rt = _build_retarget(bvh, _MAPS[_KIND_INFO[kind][0]], body)
        if _cache is not None:
            _cache[key] = rt
    G = mocap_world_rotations(bvh, frames)
    F = G.shape[0]
    W = np.empty((F, len(POSE_JOINTS), 3, 3))
    W_root = G[:, rt.root_driver] @ rt.C_root
    R = np.empty_like(W)
    for k in range(len(POSE_JOINTS)):
        Wa = W_root if rt.anchor[k] < 0 else W[:, rt.anchor[k]]
        if rt.driver[k] < 0:
            W[:, k] = Wa  # no counterpart: rigid with its parent (identity local rotation)
            R[:, k] = np.eye(3)
        else:
            W[:, k] = G[:, rt.driver[k]] @ rt.C[k]
            R[:, k] = np.swapaxes(Wa, -1, -2) @ W[:, k]
    return R


_CHUNK = 8192


@functools.partial(jax.jit, static_argnums=1)
def _matrix_to_euler_chunk(R, order):
    return jax.vmap(lambda m: matrix_to_euler(m, order))(R)


def _to_euler(R: np.ndarray, order: str = EULER_ORDER) -> np.ndarray:
    """`(..., 3, 3)` rotation matrices -> `(..., 3)` Euler angles, float64 (fixed-size chunks)."""
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 3))
    with jax.enable_x64(True):
        for s in range(0, len(flat), _CHUNK):
            block = flat[s : s + _CHUNK]
            padded = np.broadcast_to(np.eye(3), (_CHUNK, 3, 3)).copy()
            padded[: len(block)] = block
            out[s : s + len(block)] = np.asarray(_matrix_to_euler_chunk(padded, order))[
                : len(block)
            ]
    return out.reshape(*R.shape[:-2], 3)


# --------------------------------------------------------------------------------------------------
# loading


def find_mocap_dir() -> Path | None:
    """The shared CMU mocap folder, or `None` if absent.

    `$BODYPRIOR_MOCAP_DIR` if set (returned only if it is a directory), else `../shared/data/mocap`
    next to the repository checkout (where CI and the project machines keep it).
    """
    env = os.environ.get("BODYPRIOR_MOCAP_DIR")
    if env:
        return Path(env) if Path(env).is_dir() else None
    candidate = Path(__file__).resolve().parents[3] / "shared" / "data" / "mocap"
    return candidate if candidate.is_dir() else None


def _bvh_files(paths_or_dirs) -> list[Path]:
    if isinstance(paths_or_dirs, (str, os.PathLike)):
        paths_or_dirs = [paths_or_dirs]
    files: list[Path] = []
    for p in paths_or_dirs:
        p = Path(p)
        if p.is_dir():
            files.extend(sorted(q for q in p.rglob("*") if q.suffix.lower() == ".bvh"))
        elif p.is_file():
            files.append(p)
        else:
            raise ValueError(f"`paths_or_dirs`: {str(p)!r} is neither a file nor a directory.")
    if not files:
        raise ValueError(
            f"`paths_or_dirs`: no .bvh files found in {list(map(str, paths_or_dirs))}."
        )
    return files


def motion_frames(
    bvh: Bvh, kind: str, source_fps: float, fps: float, min_duration: float
) -> np.ndarray:
    """Indices of the frames sampled at `fps` from the first motion frame (empty if too short)."""
    start = _KIND_INFO[kind][1]
    n = bvh.n_frames - start
    duration = (n - 1) / source_fps if n > 0 else 0.0
    if n <= 0 or duration < min_duration:
        return np.zeros(0, np.int64)
    times = np.arange(0.0, duration + 1e-9, 1.0 / fps)
    return start + np.minimum(np.rint(times * source_fps).astype(np.int64), n - 1)


def plausible(R: np.ndarray) -> np.ndarray:
    """Which poses (local rotations `(F, 20, 3, 3)`) respect `_MAX_LOCAL_DEG`, shape `(F,)` bool."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))  # (F, 20)
    limit = np.array([_MAX_LOCAL_DEG.get(n, 180.0) for n in POSE_JOINTS])
    return np.all(angle <= limit, axis=-1)


def _source_fps(path: Path, bvh: Bvh, frame_rates: Mapping[str, float]) -> float:
    for key, rate in frame_rates.items():
        if any(key in part for part in path.parent.parts):
            return float(rate)
    rate = 1.0 / bvh.frame_time
    # headers hold rounded frame times (".0083333" = 120 fps): snap to a whole rate within 0.01%
    return float(round(rate)) if abs(rate - round(rate)) < 1e-4 * rate else rate


def load_mocap(
    paths_or_dirs: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    fps: float = 4.0,
    progress: bool = True,
    body: DefaultBody | None = None,
    frame_rates: Mapping[str, float] | None = None,
    min_duration: float = 1.0,
    drop_implausible: bool = True,
    info: dict | None = None,
) -> PoseSet:
    """Loads CMU BVH clips, retargets them to the `cmu_mb` rig and samples poses at `fps`.

    Reads the three CMU skeleton kinds (MotionBuilder names, 3ds-Max names, the 43-joint
    Daz-friendly one; see the module docstring and shared/data/README.md). Rest/T-pose frames are
    dropped; files with less than `min_duration` seconds of motion (the 3-frame template
    `standard.bvh`, the 3-frame `02_06_first3frames.bvh` excerpt) are skipped.

    **Arguments:**

    - `paths_or_dirs`: a `.bvh` file, a directory (searched recursively) or a list of them.
    - `fps`: poses per second of motion (the paper samples at 4).
    - `progress`: show a tqdm bar over files.
    - `body`: the rig to retarget to; default `bodyprior.load_default_body("cmu_mb")` at the
      default phenotypes.
    - `frame_rates`: true capture rates by directory-name substring, overriding the BVH header;
      default [`DEFAULT_FRAME_RATES` (`{"salsa": 60.0}`).
    - `min_duration`: seconds of motion below which a file is skipped.
    - `drop_implausible`: drop poses with impossible head/neck/spine rotations (corrupt frames, see
      the module docstring).
    - `info`: optional dict, filled with one entry per file (`str(path)` -> dict with `kind`,
      `frames`, `source_fps`, `poses`, `dropped`, `skipped`).

    **Returns:** a [`bodyprior.PoseSet`][], clips in sorted file order.

    **Raises:** `ValueError` for a missing path, no BVH files, a malformed file (file and line), an
    unknown skeleton, or when no file has enough motion.
    """
    from tqdm.auto import tqdm

    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"`fps` must be a positive number, got {fps}.")
    files = _bvh_files(paths_or_dirs)
    if body is None:
        body = load_default_body("cmu_mb")
    _pose_index(body.joint_names)
    rates = DEFAULT_FRAME_RATES if frame_rates is None else dict(frame_rates)
    eulers, clips, names, cache = [], [], [], {}
    for path in tqdm(files, desc="mocap", unit="file", disable=not progress):
        bvh = read_bvh(path)
        try:
            kind = skeleton_kind(bvh)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        src_fps = _source_fps(path, bvh, rates)
        frames = motion_frames(bvh, kind, src_fps, fps, min_duration)
        entry = dict(kind=kind, frames=bvh.n_frames, source_fps=src_fps, poses=0, dropped=0)
        if info is not None:
            info[str(path)] = entry
        entry["skipped"] = frames.size == 0
        if frames.size == 0:
            continue
        try:
            R = retarget_matrices(bvh, body, frames, _cache=cache)
        except ValueError as e:  # e.g. a joint of the map missing: name the file
            raise ValueError(f"{path}: {e}") from None
        if drop_implausible:
            keep = plausible(R)
            entry["dropped"] = int((~keep).sum())
            R = R[keep]
        entry["poses"] = len(R)
        if len(R) == 0:
            continue
        eulers.append(_to_euler(R))
        clips.append(np.full(len(R), len(names), np.int32))
        names.append(f"{path.parent.name}/{path.stem}")
    if not eulers:
        raise ValueError(f"`paths_or_dirs`: none of the {len(files)} BVH files has enough motion.")
    if len(set(names)) != len(names):  # same folder/stem in different trees: use full paths
        names = [str(p) for p in files]  # pragma: no cover
    return PoseSet(
        euler=jnp.asarray(np.concatenate(eulers)),
        clip=jnp.asarray(np.concatenate(clips)),
        clip_names=tuple(names),
        joint_names=POSE_JOINTS,
        fps=float(fps),
    )


def split_by_clip(
    poses: PoseSet, test_fraction: float = 0.2, *, seed: int = 0
) -> tuple[PoseSet, PoseSet]:
    """Splits poses into train and test sets by whole clips (never by frame).

    Clips are shuffled with `seed` and moved to the test set one by one until it holds at least
    `test_fraction` of the poses (at least one clip, and at least one clip stays in train).

    **Arguments:**

    - `poses`: a [`bodyprior.PoseSet`][] with at least two non-empty clips.
    - `test_fraction`: target fraction of poses in the test set, in (0, 1).
    - `seed`: shuffling seed.

    **Returns:** `(train, test)` PoseSets; both keep all `clip_names`.
    """
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"`test_fraction` must lie in (0, 1), got {test_fraction}.")
    counts = poses.poses_per_clip()
    present = np.flatnonzero(counts)
    if len(present) < 2:
        raise ValueError(f"`poses` must hold at least two non-empty clips, got {len(present)}.")
    order = np.random.default_rng(seed).permutation(present)
    target = test_fraction * poses.n_poses
    test_clips, n = [], 0
    for c in order[:-1]:
        if n >= target:
            break
        test_clips.append(c)
        n += counts[c]
    is_test = np.isin(np.asarray(poses.clip), test_clips)
    return poses.subset(np.flatnonzero(~is_test)), poses.subset(np.flatnonzero(is_test))


# --------------------------------------------------------------------------------------------------
# pictures


@eqx.filter_jit
def _posed_vertices(body, phen, euler):
    return jax.vmap(lambda e: evaluate(body, phen, rig_pose(body, e))[0])(euler)


def render_poses(
    body: DefaultBody,
    euler: Float[Array, "n 20 3"],
    path: str | os.PathLike,
    *,
    labels: Sequence[str] | None = None,
    ncols: int | None = None,
    view="front",
    cell_size: tuple[int, int] = (256, 192),
) -> np.ndarray:
    """Renders DSPP poses on the default body (default phenotypes) as a contact-sheet PNG.

    **Arguments:**

    - `body`: the default body with the `cmu_mb` rig.
    - `euler`: shape `(n, 20, 3)`, radians, order [`bodyprior.EULER_ORDER`][].
    - `path`: PNG file to write (atomically).
    - `labels`, `ncols`, `view`, `cell_size`: as [`bodyprior.contact_sheet`][].

    **Returns:** the image, `uint8` of shape `(H, W, 3)`.

    !!! example

        `docs/img/mocap_poses.png` (5 evenly spaced poses of CMU 131_01, salsa 01 and martial 05):

        ```python
        ps = load_mocap(mocap / "cmu_daz-friendly_papagina-acLSTM/salsa_couple/01.bvh")
        idx = np.linspace(4, ps.n_poses - 3, 5).round().astype(int)
        render_poses(body, np.asarray(ps.euler)[idx], "salsa.png", ncols=5, cell_size=(240, 170))
        ```
    """
    check_array(euler, "euler", (None, len(POSE_JOINTS), 3))
    phen = jnp.asarray(phenotype_vector(), body.template.dtype)
    verts = np.asarray(_posed_vertices(body, phen, jnp.asarray(euler, body.template.dtype)))
    img = contact_sheet(
        verts, np.asarray(body.faces), labels=labels, ncols=ncols, view=view, cell_size=cell_size
    )
    save_png(path, img)
    return img
