"""DSPP: deep shape and pose priors (Hu, Shum, Mucherino 2019) — auto-encoders with GANs in their latent
spaces, on the default body's topology and `cmu_mb` rig."""

from ._limits import (
    joint_limit_violation as joint_limit_violation,
    joint_limits as joint_limits,
)
