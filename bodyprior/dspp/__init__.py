"""DSPP: deep shape and pose priors (Hu, Shum, Mucherino 2019) — auto-encoders with GANs in their latent
spaces, on the default body's topology and `cmu_mb` rig."""

from ._limits import (
    joint_limit_violation as joint_limit_violation,
    joint_limits as joint_limits,
)
from ._mocap import (
    EULER_ORDER as EULER_ORDER,
    POSE_JOINTS as POSE_JOINTS,
    PoseSet as PoseSet,
    load_mocap as load_mocap,
    pose_euler as pose_euler,
    render_poses as render_poses,
    rig_pose as rig_pose,
    split_by_clip as split_by_clip,
)
