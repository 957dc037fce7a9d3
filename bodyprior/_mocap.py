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
shared/data/mocap/SOURCES.md); files of the 2008 MotionBuilder release (e.g. CMU 01_01), which
call the finger joints `LFingers`/`RFingers`, are kind `cmu_mb2008` (`_MB2008_TO_MB`). Errors about
a missing joint name it as in the user's file.

**Public API.** [`bodyprior.Retargeter`][] (built once per BVH skeleton and body, applied to any
frames), [`bodyprior.retarget`][] (one call: axis-angle rig poses plus optional root orientation and
root translation in metres), [`bodyprior.poses_to_bvh`][] (export rig poses as a BVH of the rig,
kind `"rig"`, which retargets back onto the same body unchanged), [`bodyprior.load_mocap`][] (DSPP
pose sets).

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
import hashlib
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._body import DefaultBody, evaluate, load_default_body, phenotype_vector, rest_shape
from ._bvh import Bvh, read_bvh, write_bvh
from ._render import contact_sheet, save_png
from ._rotations import (
    axis_angle_to_matrix,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
)
from ._store import register_type
from ._validate import check_array, is_tracer

__all__ = [
    "EULER_ORDER",
    "POSE_JOINTS",
    "SKELETON_KINDS",
    "PoseSet",
    "Retargeter",
    "find_mocap_dir",
    "load_mocap",
    "pose_euler",
    "poses_to_bvh",
    "render_poses",
    "retarget",
    "rig_pose",
    "split_by_clip",
]

POSE_JOINTS: tuple[str, ...] = (
    "LeftUpLeg", "LeftLeg", "LeftFoot",
    "LowerBack", "Spine", "Spine1",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
    "Neck", "Neck1", "Head",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand",
    "RightUpLeg", "RightLeg", "RightFoot",
)  # fmt: skip
"""The 20 `cmu_mb` rig bones of a pose, in rig order: the CMU body joints without the root (Hips),
the pelvis-to-hip bones `LHipJoint`/`RHipJoint` (no degrees of freedom in CMU data), the toes
(absent from the Daz-friendly clips) and the fingers/thumbs (no mocap data)."""

EULER_ORDER: str = "XYZ"
"""Euler order of [`bodyprior.PoseSet`][] angles (intrinsic, as [`bodyprior.euler_to_matrix`][];
use `pose_rep="euler_" + EULER_ORDER`). Chosen on the shared CMU clips as the order whose middle
angle comes least close to ±90° (gimbal lock)."""

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


def _self_map(table: dict) -> dict:
    """The joint map of a BVH written from the rig itself ([`bodyprior.poses_to_bvh`][]): each rig
    bone is driven by its own joint, with the same end point (so every rest compensation is I)."""
    out = {}
    for rig, (_, end, rig_end) in table.items():
        if end is None:
            out[rig] = (rig, None, None)
        else:
            kind, bone = rig_end
            out[rig] = (rig, bone if kind == "head" else f"{bone}/end", rig_end)
    return out


_MAPS = {
    "cmu": {**_CENTER_CMU, **_LEFT_CMU, **_mirror(_LEFT_CMU)},
    "daz": {**_CENTER_DAZ, **_LEFT_DAZ, **_mirror(_LEFT_DAZ)},
}
_MAPS["rig"] = _self_map(_MAPS["cmu"])

# The 2008 MotionBuilder-friendly CMU release (e.g. CMU 01_01) names the finger joints of the 2010
# release's hierarchy LFingers/RFingers (shared/data/mocap/SOURCES.md, A)
_MB2008_TO_MB = {"LFingers": "LeftHandIndex1", "RFingers": "RightHandIndex1"}

SKELETON_KINDS: dict[str, str] = {
    "rig": "bodyprior cmu_mb rig (written by bodyprior.poses_to_bvh)",
    "cmu_mb2008": "CMU MotionBuilder-friendly, 2008 names (LFingers/RFingers)",
    "cmu_mb": "CMU MotionBuilder-friendly",
    "cmu_3dsmax": "CMU 3ds-Max-friendly",
    "daz": "CMU Daz-friendly",
}
"""The BVH skeleton kinds that [`bodyprior.retarget`][] and [`bodyprior.load_mocap`][] read, by the
name [`bodyprior.Retargeter`][] gives them."""
# joints whose presence identifies each skeleton kind, checked in this order
_KIND_SIGNATURE = {
    "rig": ("Hips", "LHipJoint", "LeftUpLeg", "LowerBack", "Spine1", "Neck1", "LeftFingerBase",
            "LeftHandFinger1", "RightHandFinger1"),
    "cmu_mb2008": ("Hips", "LHipJoint", "LeftUpLeg", "LowerBack", "Spine1", "Neck1",
                   "LeftFingerBase", "LFingers"),
    "cmu_mb": ("Hips", "LHipJoint", "LeftUpLeg", "LowerBack", "Spine1", "Neck1", "LeftFingerBase"),
    "cmu_3dsmax": ("Hips", "LHipJoint", "LeftHip", "lowerback", "Chest2", "lowerneck", "lhand"),
    "daz": ("hip", "abdomen", "chest", "lButtock", "lThigh", "lCollar", "lMid1", "rMid1"),
}  # fmt: skip
# CMU ASF length unit in metres: (1/0.45) * 2.54 / 100 (shared/data/mocap/SOURCES.md, A)
_CMU_UNIT = (1.0 / 0.45) * 2.54 / 100.0
# kind -> (joint map, index of the first motion frame, renaming of the file's joints to the map's
# names, metres per BVH length unit)
_KIND_INFO = {
    "rig": ("rig", 0, {}, 0.01),
    "cmu_mb2008": ("cmu", 1, _MB2008_TO_MB, _CMU_UNIT),
    "cmu_mb": ("cmu", 1, {}, _CMU_UNIT),
    "cmu_3dsmax": ("cmu", 0, _MAX_TO_MB, _CMU_UNIT),
    "daz": ("daz", 8, {}, 0.01),
}

# largest plausible local rotation angle (degrees) per pose bone; larger ones are data glitches
_MAX_LOCAL_DEG = {"Head": 100.0, "Neck": 100.0, "Neck1": 100.0,
                  "LowerBack": 120.0, "Spine": 120.0, "Spine1": 120.0}  # fmt: skip

DEFAULT_FRAME_RATES: dict[str, float] = {"salsa": 60.0}
"""Default true capture rates (frames per second) by a directory-name substring: the acLSTM
readme.txt gives salsa 60 (indian and martial 120, as their headers say)."""


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


register_type(PoseSet)


def _pose_index(joint_names: tuple[str, ...]) -> np.ndarray:
    missing = [n for n in POSE_JOINTS if n not in joint_names]
    if missing:
        raise ValueError(
            f"`body` must have the cmu_mb rig (bones {POSE_JOINTS}); missing {missing}. Use "
            "bodyprior.load_default_body('cmu_mb')."
        )
    return np.array([joint_names.index(n) for n in POSE_JOINTS])


def rig_pose(body: DefaultBody, euler: Float[ArrayLike, "20 3"]) -> Float[Array, "J 3"]:
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


def pose_euler(body: DefaultBody, pose: Float[ArrayLike, "J 3"]) -> Float[Array, "20 3"]:
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
    """The skeleton kind of `bvh` from its joint names: a key of `SKELETON_KINDS`.

    `"rig"` (a file written by [`bodyprior.poses_to_bvh`][] from the `cmu_mb` rig),
    `"cmu_mb2008"`, `"cmu_mb"`, `"cmu_3dsmax"` or `"daz"`; `ValueError` for any other skeleton.
    """
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


def _rig_rest(body: DefaultBody) -> tuple[np.ndarray, np.ndarray]:
    """Rest heads and tails of the default body (default phenotypes), float64, metres, `(J, 3)`."""
    with jax.enable_x64(True):
        _, heads = rest_shape(body, phenotype_vector())
        heads = np.asarray(heads, np.float64)
        # tails are fixed template points: move them with their bone head's shape displacement
        tails = np.asarray(body.bones.tail_template, np.float64) + (
            heads - np.asarray(body.bones.head_template, np.float64)
        )
    return heads, tails


def _check_bvh(bvh) -> None:
    if not isinstance(bvh, Bvh):
        raise ValueError(f"`bvh` must be a bodyprior.Bvh, got {type(bvh).__name__}.")


def _frame_index(frames, n_frames: int) -> np.ndarray:
    """`frames` (None, slice, 1-D int indices in [-F, F), or an (F,) bool mask) -> int64 indices."""
    if frames is None:
        return np.arange(n_frames)
    if isinstance(frames, slice):
        return np.arange(n_frames)[frames]
    if is_tracer(frames):
        raise ValueError("`frames` must be concrete indices (host data), got a tracer.")
    idx = np.asarray(frames)
    if idx.dtype == np.bool_:
        if idx.shape != (n_frames,):
            raise ValueError(
                f"`frames`: a boolean mask must have shape ({n_frames},) (one entry per frame of "
                f"`bvh`), got shape {idx.shape}."
            )
        return np.flatnonzero(idx)
    if idx.size == 0 and idx.ndim == 1:
        return np.zeros(0, np.int64)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(
            "`frames` must be None, a slice, a 1-D array of integer frame indices or a boolean "
            f"mask, got shape {idx.shape} and dtype {idx.dtype}."
        )
    idx = idx.astype(np.int64)
    bad = (idx < -n_frames) | (idx >= n_frames)
    if bad.any():
        raise ValueError(
            f"`frames` must index the {n_frames} frames of `bvh` (in [-{n_frames}, {n_frames})), "
            f"got {int(idx[bad][0])}."
        )
    return np.where(idx < 0, idx + n_frames, idx)


class Retargeter(eqx.Module):
    """The retargeting of one BVH skeleton onto a body's `cmu_mb` rig, precomputed on the host.

    Build it once per (BVH skeleton, body) with [`bodyprior.Retargeter.from_bvh`][] and apply it to
    any frames of any [`bodyprior.Bvh`][] with that skeleton (same joint names and offsets, e.g.
    every clip of one CMU subject, or every Daz-friendly clip); the method is in the module
    docstring. [`bodyprior.retarget`][] does both in one call. Host NumPy, float64.

    **Fields:**

    - `C`: shape `(20, 3, 3)`, the rest-compensation rotation of each pose bone
      ([`bodyprior.POSE_JOINTS`][] order), bodyprior axes.
    - `C_root`: shape `(3, 3)`, the root's rest compensation (the identity).
    - `rig_heads`: shape `(J, 3)`, metres, the rig's rest joints (default phenotypes), world frame.
    - `bvh_offsets`: shape `(Jb, 3)`, the BVH skeleton's `OFFSET`s (file units and axes), to check
      that a `Bvh` it is applied to has this skeleton.
    - `kind`: static, the skeleton kind (a key of `SKELETON_KINDS`).
    - `bvh_joint_names`: static, the BVH skeleton's joint names, as in its file.
    - `rig_joint_names`: static, the body's rig bones (`body.joint_names`).
    - `rig_index`, `driver`, `anchor`, `root_driver`: static joint map: the rig bone of each pose
      bone, its driving BVH joint (-1: none, kept at rest), its anchor pose bone (-1: the root),
      and the BVH joint that drives the root.
    - `unit`: static, metres per BVH length unit (for root translations).
    """

    C: Float[np.ndarray, "20 3 3"]
    C_root: Float[np.ndarray, "3 3"]
    rig_heads: Float[np.ndarray, "J 3"]
    bvh_offsets: Float[np.ndarray, "Jb 3"]
    kind: str = eqx.field(static=True)
    bvh_joint_names: tuple[str, ...] = eqx.field(static=True)
    rig_joint_names: tuple[str, ...] = eqx.field(static=True)
    rig_index: tuple[int, ...] = eqx.field(static=True)
    driver: tuple[int, ...] = eqx.field(static=True)
    anchor: tuple[int, ...] = eqx.field(static=True)
    root_driver: int = eqx.field(static=True)
    unit: float = eqx.field(static=True)

    @classmethod
    def from_bvh(cls, bvh: Bvh, body: DefaultBody, *, unit: float | None = None) -> Retargeter:
        """Precomputes the retargeting of `bvh`'s skeleton onto `body`'s rig.

        Only the skeleton of `bvh` (joint names, offsets, End Sites) is used, not its motion.

        **Arguments:**

        - `bvh`: a [`bodyprior.Bvh`][] of one of the kinds in `SKELETON_KINDS` (CMU with
          MotionBuilder names of 2008 or 2010, 3ds-Max names, Daz-friendly, or a file written by
          [`bodyprior.poses_to_bvh`][]).
        - `body`: a [`bodyprior.DefaultBody`][] with the `cmu_mb` rig; its rest joints at the
          default phenotypes are the target.
        - `unit`: metres per BVH length unit, for root translations; default by kind: CMU
          `(1 / 0.45) * 2.54 / 100 = 0.05644` (CMU ASF units), Daz-friendly and `"rig"` files
          `0.01` (centimetres).

        **Returns:** a [`bodyprior.Retargeter`][].

        **Raises:** `ValueError` for an unknown skeleton, a joint of the joint map missing from
        `bvh` (named as in the file), a body without the `cmu_mb` rig, or a bad `unit`.
        """
        _check_bvh(bvh)
        _pose_index(body.joint_names)
        heads, tails = _rig_rest(body)
        return _build_retargeter(bvh, body, heads, tails, unit)

    @property
    def first_motion_frame(self) -> int:
        """Index of the first frame of real motion in files of this kind (1 for CMU MotionBuilder
        files, whose frame 0 is a synthetic T-pose; 8 for Daz-friendly files; else 0)."""
        return _KIND_INFO[self.kind][1]

    def _check_skeleton(self, bvh) -> None:
        _check_bvh(bvh)
        same = bvh.joint_names == self.bvh_joint_names and np.allclose(
            bvh.offsets, self.bvh_offsets, rtol=1e-9, atol=1e-12
        )
        if not same:
            raise ValueError(
                "`bvh` must have the skeleton this Retargeter was built for (same joint names and "
                f"offsets; built for {self.bvh_joint_names[:3]}..., got "
                f"{bvh.joint_names[:3]}...); build another with Retargeter.from_bvh(bvh, body)."
            )

    def _rotations(self, bvh: Bvh, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pose-bone local rotations `(F, 20, 3, 3)`, rig root world rotation `(F, 3, 3)`)."""
        G = mocap_world_rotations(bvh, frames)
        F = G.shape[0]
        W = np.empty((F, len(POSE_JOINTS), 3, 3))
        W_root = G[:, self.root_driver] @ self.C_root
        R = np.empty_like(W)
        for k in range(len(POSE_JOINTS)):
            Wa = W_root if self.anchor[k] < 0 else W[:, self.anchor[k]]
            if self.driver[k] < 0:
                W[:, k] = Wa  # no counterpart: rigid with its parent (identity local rotation)
                R[:, k] = np.eye(3)
            else:
                W[:, k] = G[:, self.driver[k]] @ self.C[k]
                R[:, k] = np.swapaxes(Wa, -1, -2) @ W[:, k]
        return R, W_root

    def local_matrices(self, bvh: Bvh, frames=None) -> Float[np.ndarray, "F 20 3 3"]:
        """Local rotation matrices of the 20 pose bones ([`bodyprior.POSE_JOINTS`][] order) at
        `frames` of `bvh`, shape `(F, 20, 3, 3)`, float64, bodyprior axes (the DSPP pose; the root
        orientation is dropped). `frames` as in `Retargeter.__call__`."""
        self._check_skeleton(bvh)
        return self._rotations(bvh, _frame_index(frames, bvh.n_frames))[0]

    def __call__(
        self,
        bvh: Bvh,
        frames=None,
        *,
        keep_root_rotation: bool = False,
        keep_root_translation: bool = False,
    ) -> tuple[Float[np.ndarray, "F J 3"], Float[np.ndarray, "F 3"]]:
        """Retargets frames of `bvh` onto the rig.

        **Arguments:**

        - `bvh`: a [`bodyprior.Bvh`][] with the skeleton this Retargeter was built for.
        - `frames`: which frames: `None` (all), a slice, a 1-D integer array of frame indices
          (any order, repeats allowed, negative counts from the end) or a boolean mask of shape
          `(bvh.n_frames,)`. Frame `k` is at time `k * bvh.frame_time` seconds; note the rest frames
          at the start of some kinds (`first_motion_frame`).
        - `keep_root_rotation`: also pose the root (`Hips`) with the mocap's root orientation;
          otherwise the root stays at rest (the body seen in its pelvis frame, as DSPP poses).
        - `keep_root_translation`: return the mocap root's position; otherwise zeros.

        **Returns:** `(pose, root_translation)`, NumPy float64:

        - `pose`: shape `(F, J, 3)`, axis-angle local rotations (radians) in `body.joint_names`
          order, bodyprior's kinematics convention (world-aligned axes at rest; for
          [`bodyprior.evaluate`][]). Bones outside [`bodyprior.POSE_JOINTS`][] are zero, the root
          too unless `keep_root_rotation`.
        - `root_translation`: shape `(F, 3)`, metres, bodyprior's world frame (Z up, the mocap's
          rest facing direction is -Y): `unit * position - rig_heads[0]`, where `position` is the
          BVH root position (its `OFFSET` plus position channels) converted to bodyprior axes. So
          `evaluate(body, phenotype_vector(), pose[k], root_translation[k])` puts the rig root
          where the mocap root is, in the capture's absolute coordinates (the capture's floor
          height and horizontal origin); subtract `root_translation[0]` for
          motion relative to the first frame. The body's proportions are not taken into account
          (a body smaller than the mocap subject floats or sinks by the difference in leg length).

        **Raises:** `ValueError` if `bvh` has another skeleton, or `frames` is out of range or not
        an index.
        """
        self._check_skeleton(bvh)
        idx = _frame_index(frames, bvh.n_frames)
        R, W_root = self._rotations(bvh, idx)
        pose = np.zeros((len(idx), len(self.rig_joint_names), 3))
        pose[:, list(self.rig_index)] = _from_matrices(R, "axis_angle")
        if keep_root_rotation:
            pose[:, 0] = _from_matrices(W_root, "axis_angle")
        if keep_root_translation:
            trans = self.unit * (bvh.root_positions(idx) @ _M.T) - self.rig_heads[0]
        else:
            trans = np.zeros((len(idx), 3))
        return pose, trans


def _build_retargeter(
    bvh: Bvh, body: DefaultBody, heads: np.ndarray, tails: np.ndarray, unit: float | None
) -> Retargeter:
    kind = skeleton_kind(bvh)
    table_name, _, renaming, default_unit = _KIND_INFO[kind]
    table = _MAPS[table_name]
    if unit is None:
        unit = default_unit
    elif not (isinstance(unit, (int, float, np.floating)) and np.isfinite(unit) and unit > 0):
        raise ValueError(f"`unit` must be a positive number of metres per BVH unit, got {unit!r}.")
    names = body.joint_names
    parents = body.parents
    mapped = tuple(renaming.get(n, n) for n in bvh.joint_names)  # the joint map's names
    as_in_file = {v: k for k, v in renaming.items()}

    def index(name: str, rig_bone: str) -> int:
        try:
            return mapped.index(name)
        except ValueError:
            raise ValueError(
                f"No joint named {as_in_file.get(name, name)!r} in this BVH skeleton (a "
                f"{SKELETON_KINDS[kind]} skeleton; rig bone {rig_bone!r} is retargeted from it)."
            ) from None

    rest = bvh.rest_positions() @ _M.T  # mocap rest joint positions, bodyprior axes
    end = (np.asarray(bvh.rest_positions()) + np.nan_to_num(bvh.end_offsets)) @ _M.T
    has_end = ~np.isnan(bvh.end_offsets[:, 0])

    def mocap_point(spec: str, rig_bone: str) -> np.ndarray:
        if spec.endswith("/end"):
            j = index(spec[:-4], rig_bone)
            if not has_end[j]:
                raise ValueError(f"joint {bvh.joint_names[j]!r} has no End Site")
            return end[j]
        return rest[index(spec, rig_bone)]

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
            drv, mend, (kind_end, bone) = entry
            u = _unit(mocap_point(mend, names[j]) - rest[index(drv, names[j])])
            rig_end = (heads if kind_end == "head" else tails)[names.index(bone)]
            b = _unit(rig_end - heads[j])
        C_rig[j] = Ca if u is None or b is None else _swing(Ca @ b, u) @ Ca

    rig_index, driver, anchor = [], [], []
    for n in POSE_JOINTS:
        j = names.index(n)
        rig_index.append(j)
        entry = table.get(n)
        driver.append(-1 if entry is None else index(entry[0], n))
        a = parents[j]
        while a != 0 and names[a] not in pose_set:
            a = parents[a]
        anchor.append(-1 if a == 0 else POSE_JOINTS.index(names[a]))
    return Retargeter(
        C=np.stack([C_rig[j] for j in rig_index]),
        C_root=C_rig[0],
        rig_heads=np.asarray(heads, np.float64),
        bvh_offsets=np.asarray(bvh.offsets),
        kind=kind,
        bvh_joint_names=bvh.joint_names,
        rig_joint_names=names,
        rig_index=tuple(rig_index),
        driver=tuple(driver),
        anchor=tuple(anchor),
        root_driver=index(table["Hips"][0], names[0]),
        unit=float(unit),
    )


def mocap_world_rotations(bvh: Bvh, frames=None) -> np.ndarray:
    """World rotations of every BVH joint in bodyprior axes, shape `(F, J, 3, 3)` (float64)."""
    L = bvh.local_rotations(frames)
    G = np.empty_like(L)
    for j, p in enumerate(bvh.parents):
        G[:, j] = L[:, j] if p < 0 else G[:, p] @ L[:, j]
    return _M @ G @ _M.T


def retarget_matrices(bvh: Bvh, body: DefaultBody, frames=None) -> np.ndarray:
    """Local rotation matrices of the 20 pose bones, shape `(F, 20, 3, 3)`, for BVH frames:
    `Retargeter.from_bvh(bvh, body).local_matrices(bvh, frames)`."""
    return Retargeter.from_bvh(bvh, body).local_matrices(bvh, frames)


def retarget(
    bvh: Bvh,
    body: DefaultBody,
    frames=None,
    *,
    keep_root_rotation: bool = False,
    keep_root_translation: bool = False,
    unit: float | None = None,
) -> tuple[Float[np.ndarray, "F J 3"], Float[np.ndarray, "F 3"]]:
    """Retargets frames of a BVH clip onto the body's `cmu_mb` rig.

    `Retargeter.from_bvh(bvh, body, unit=unit)(bvh, frames, ...)`; build the
    [`bodyprior.Retargeter`][] once instead when retargeting several clips of one skeleton.

    **Arguments:**

    - `bvh`: a [`bodyprior.Bvh`][] (see `SKELETON_KINDS` for the skeletons it may have).
    - `body`: a [`bodyprior.DefaultBody`][] with the `cmu_mb` rig.
    - `frames`, `keep_root_rotation`, `keep_root_translation`: as
      `Retargeter.__call__`; default all frames, root at rest, zero translation.
    - `unit`: metres per BVH length unit (default by skeleton kind, see
      [`bodyprior.Retargeter.from_bvh`][]).

    **Returns:** `(pose (F, J, 3), root_translation (F, 3))`: axis-angle rig pose (radians,
    `body.joint_names` order) and root translation (metres, bodyprior world frame), NumPy float64.

    !!! example

        ```python
        bvh = bp.read_bvh("01_01.bvh")
        pose, trans = bp.retarget(bvh, body, slice(1, None), keep_root_rotation=True,
                                  keep_root_translation=True)
        verts, joints = bp.evaluate(body, bp.phenotype_vector(), pose[0], trans[0])
        ```
    """
    rt = Retargeter.from_bvh(bvh, body, unit=unit)
    return rt(
        bvh,
        frames,
        keep_root_rotation=keep_root_rotation,
        keep_root_translation=keep_root_translation,
    )


_EXPORT_UNIT = 0.01
"""Metres per length unit of the BVH files [`bodyprior.poses_to_bvh`][] writes (centimetres)."""
_ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
_JOINT_CHANNELS = ("Zrotation", "Yrotation", "Xrotation")  # R = Rz @ Ry @ Rx, as CMU's files


def poses_to_bvh(
    body: DefaultBody,
    poses: Float[np.ndarray, "F J 3"],
    root_translation: Float[np.ndarray, "F 3"] | None = None,
    *,
    fps: float,
    path: str | os.PathLike | None = None,
    precision: int = 10,
) -> Bvh:
    """Writes rig poses as a BVH clip whose skeleton is the body's rig.

    The skeleton is the rig at rest (default phenotypes): one joint per rig bone with the rig's bone
    names and tree, `OFFSET`s from the rest joints, an `End Site` at the tail of each leaf bone;
    BVH axes (Y up, facing +Z: bodyprior's `(x, y, z)` is written `(x, z, -y)`) in centimetres. The
    root has channels `Xposition Yposition Zposition Zrotation Yrotation Xrotation`, every other
    joint `Zrotation Yrotation Xrotation`. Reading the file back
    ([`bodyprior.read_bvh`][]) and retargeting it onto the same body
    ([`bodyprior.retarget`][] with `keep_root_rotation=True, keep_root_translation=True`) gives
    back the poses' rotations of the root and the pose bones ([`bodyprior.POSE_JOINTS`][]) and the
    root translation. (Rotations of the other rig bones are written too, but the retargeting keeps
    those bones at rest.)

    **Arguments:**

    - `body`: a [`bodyprior.DefaultBody`][] (rig depth-first, as the default rigs).
    - `poses`: shape `(F, J, 3)`, axis-angle local rotations (radians) in `body.joint_names` order
      (as [`bodyprior.evaluate`][] and [`bodyprior.retarget`][]).
    - `root_translation`: optional shape `(F, 3)`, metres, bodyprior world frame, as for
      [`bodyprior.evaluate`][] (the root joint is at its rest position plus this); default zeros.
    - `fps`: frames per second of the clip (the file's `Frame Time` is `1 / fps`).
    - `path`: optional `.bvh` file to write (atomically, with [`bodyprior.write_bvh`][]).
    - `precision`: significant digits written for offsets and channel values, 1..17.

    **Returns:** the clip as a [`bodyprior.Bvh`][] (what the file holds, before rounding).

    **Raises:** `ValueError` for `poses` or `root_translation` of the wrong shape or not finite, or
    a `fps` that is not a positive number.
    """
    J = body.n_joints
    poses = np.asarray(check_array(poses, "poses", (None, J, 3)), np.float64)
    F = poses.shape[0]
    if root_translation is None:
        trans = np.zeros((F, 3))
    else:
        trans = np.asarray(check_array(root_translation, "root_translation", (F, 3)), np.float64)
    if isinstance(fps, bool) or not (
        isinstance(fps, (int, float, np.number)) and np.isfinite(fps) and fps > 0
    ):
        raise ValueError(f"`fps` must be a positive number of frames per second, got {fps!r}.")
    heads, tails = _rig_rest(body)
    parents = body.parents
    to_file = lambda x: (x @ _M) / _EXPORT_UNIT  # noqa: E731  bodyprior axes, m -> BVH axes, cm
    offsets = np.array([heads[j] - (heads[p] if p >= 0 else 0.0) for j, p in enumerate(parents)])
    is_leaf = np.ones(J, bool)
    is_leaf[[p for p in parents if p >= 0]] = False
    end = np.where(is_leaf[:, None], tails - heads, np.nan)
    # local rotations in BVH axes: M^T R M, as Euler angles Z, Y, X (degrees)
    R = _to_matrices(poses.reshape(-1, 3), "axis_angle").reshape(F, J, 3, 3)
    angles = np.degrees(_to_euler(_M.T @ R @ _M, "ZYX"))  # (F, J, 3)
    motion = np.concatenate([to_file(trans)[:, None, :], angles], axis=1).reshape(F, -1)
    channels = (_ROOT_CHANNELS,) + (_JOINT_CHANNELS,) * (J - 1)
    bvh = Bvh(
        joint_names=body.joint_names,
        parents=parents,
        offsets=to_file(offsets),
        channels=channels,
        end_offsets=to_file(end),
        frame_time=1.0 / float(fps),
        motion=motion,
    )
    if path is not None:
        write_bvh(path, bvh, precision=precision)
    return bvh


_CHUNK = 8192


@functools.partial(jax.jit, static_argnums=1)
def _matrix_to_euler_chunk(R, order):
    return jax.vmap(lambda m: matrix_to_euler(m, order))(R)


@functools.partial(jax.jit, static_argnums=1)
def _matrix_chunk(x, rep):
    if rep == "axis_angle":
        return jax.vmap(axis_angle_to_matrix)(x)
    raise AssertionError(rep)  # pragma: no cover


@functools.partial(jax.jit, static_argnums=1)
def _from_matrix_chunk(R, rep):
    if rep == "axis_angle":
        return jax.vmap(matrix_to_axis_angle)(R)
    raise AssertionError(rep)  # pragma: no cover


def _chunked(fn, x: np.ndarray, arg, pad: np.ndarray, out_shape: tuple[int, ...]) -> np.ndarray:
    """`fn(x, arg)` over the leading axis of `x` in fixed-size chunks (one compile per shape),
    float64; `pad` fills the last chunk."""
    out = np.empty((x.shape[0], *out_shape))
    with jax.enable_x64(True):
        for s in range(0, len(x), _CHUNK):
            block = x[s : s + _CHUNK]
            padded = np.broadcast_to(pad, (_CHUNK, *pad.shape)).copy()
            padded[: len(block)] = block
            out[s : s + len(block)] = np.asarray(fn(padded, arg))[: len(block)]
    return out


def _to_euler(R: np.ndarray, order: str = EULER_ORDER) -> np.ndarray:
    """`(..., 3, 3)` rotation matrices -> `(..., 3)` Euler angles, float64 (fixed-size chunks)."""
    out = _chunked(_matrix_to_euler_chunk, R.reshape(-1, 3, 3), order, np.eye(3), (3,))
    return out.reshape(*R.shape[:-2], 3)


def _from_matrices(R: np.ndarray, rep: str) -> np.ndarray:
    """`(..., 3, 3)` rotation matrices -> `(..., 3)` axis-angle, float64."""
    out = _chunked(_from_matrix_chunk, R.reshape(-1, 3, 3), rep, np.eye(3), (3,))
    return out.reshape(*R.shape[:-2], 3)


def _to_matrices(x: np.ndarray, rep: str) -> np.ndarray:
    """`(N, 3)` axis-angle -> `(N, 3, 3)` rotation matrices, float64."""
    return _chunked(_matrix_chunk, x, rep, np.zeros(3), (3, 3))


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
    candidate = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"  # ../shared
    return candidate if candidate.is_dir() else None


def mocap_checksums(root: str | os.PathLike) -> dict:
    """SHA-256 of every `.bvh` file under `root` (recursively), summarised for provenance records
    of things trained on them: `{"n_files", "sha256_of_list"}` (the hash of the sorted
    `relative/path:sha256` lines)."""
    root = Path(root)
    files = sorted(p for p in root.rglob("*.bvh") if p.is_file())
    per = {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}
    total = hashlib.sha256("".join(f"{k}:{v}\n" for k, v in per.items()).encode()).hexdigest()
    return {"n_files": len(per), "sha256_of_list": total}


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
    heads, tails = _rig_rest(body)
    retargeters: dict = {}  # one per skeleton (joint names, offsets, End Sites) in this call
    eulers, clips, names = [], [], []
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
        key = (bvh.joint_names, bvh.offsets.tobytes(), bvh.end_offsets.tobytes())
        try:
            rt = retargeters.get(key)
            if rt is None:
                rt = retargeters[key] = _build_retargeter(bvh, body, heads, tails, None)
            R = rt.local_matrices(bvh, frames)
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
    return jax.vmap(lambda p, e: evaluate(body, p, rig_pose(body, e))[0])(phen, euler)


def render_poses(
    body: DefaultBody,
    euler: Float[ArrayLike, "n 20 3"],
    path: str | os.PathLike,
    *,
    labels: Sequence[str] | None = None,
    ncols: int | None = None,
    view="front",
    cell_size: tuple[int, int] = (256, 192),
    phenotypes: Float[ArrayLike, "*n 11"] | None = None,
) -> np.ndarray:
    """Renders DSPP poses on the default body as a contact-sheet PNG.

    **Arguments:**

    - `body`: the default body with the `cmu_mb` rig.
    - `euler`: shape `(n, 20, 3)`, radians, order [`bodyprior.EULER_ORDER`][].
    - `path`: PNG file to write (atomically).
    - `labels`, `ncols`, `view`, `cell_size`: as [`bodyprior.contact_sheet`][].
    - `phenotypes`: the body's phenotypes, `(11,)` for all poses or `(n, 11)` one per pose
      (e.g. from [`bodyprior.phenotypes_from_measurements`][]); default the average body,
      `phenotype_vector()`.

    **Returns:** the image, `uint8` of shape `(H, W, 3)`.

    !!! example

        `docs/img/mocap_poses.png` (5 evenly spaced poses of CMU 131_01, salsa 01 and martial 05):

        ```python
        ps = load_mocap(mocap / "cmu_daz-friendly_papagina-acLSTM/salsa_couple/01.bvh")
        idx = np.linspace(4, ps.n_poses - 3, 5).round().astype(int)
        render_poses(body, np.asarray(ps.euler)[idx], "salsa.png", ncols=5, cell_size=(240, 170))
        ```
    """
    euler = check_array(euler, "euler", (None, len(POSE_JOINTS), 3))
    n = euler.shape[0]
    if phenotypes is None:
        phen = np.broadcast_to(phenotype_vector(), (n, 11))
    else:
        phen = np.asarray(phenotypes, np.float64)
        if phen.shape == (11,):
            phen = np.broadcast_to(phen, (n, 11))
        check_array(phen, "phenotypes", (n, 11))
    phen = jnp.asarray(phen, body.template.dtype)
    verts = np.asarray(_posed_vertices(body, phen, jnp.asarray(euler, body.template.dtype)))
    img = contact_sheet(
        verts, np.asarray(body.faces), labels=labels, ncols=ncols, view=view, cell_size=cell_size
    )
    save_png(path, img)
    return img
