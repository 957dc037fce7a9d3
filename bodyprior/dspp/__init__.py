"""DSPP: deep shape and pose priors (Hu, Shum, Mucherino 2019) — auto-encoders with GANs in their
latent
spaces, on the default body's topology and `cmu_mb` rig."""

from ._checkpoint import (
    load_prior as load_prior,
)
from ._checkpoint import (
    save_prior as save_prior,
)
from ._default import (
    default_pose_prior as default_pose_prior,
)
from ._default import (
    default_shape_prior as default_shape_prior,
)
from ._fitting import (
    PriorResidual as PriorResidual,
)
from ._fitting import (
    ShapeFit as ShapeFit,
)
from ._fitting import (
    fit_latent_to_landmarks as fit_latent_to_landmarks,
)
from ._fitting import (
    fit_shape_space_to_landmarks as fit_shape_space_to_landmarks,
)
from ._fitting import (
    latent_statistics as latent_statistics,
)
from ._fitting import (
    pose_prior_residual as pose_prior_residual,
)
from ._fitting import (
    shape_prior_residual as shape_prior_residual,
)
from ._limits import (
    joint_limit_violation as joint_limit_violation,
)
from ._limits import (
    joint_limits as joint_limits,
)
from ._nets import (
    DSPPConfig as DSPPConfig,
)
from ._nets import (
    GeometryGAN as GeometryGAN,
)
from ._nets import (
    PosePrior as PosePrior,
)
from ._nets import (
    ShapePrior as ShapePrior,
)
from ._nets import (
    init_aegan as init_aegan,
)
from ._nets import (
    init_geometry_gan as init_geometry_gan,
)
from ._nets import (
    spectral_norms as spectral_norms,
)
from ._sample import (
    PCA_MODES as PCA_MODES,
)
from ._sample import (
    PCAPrior as PCAPrior,
)
from ._sample import (
    fit_pca_prior as fit_pca_prior,
)
from ._sample import (
    sample as sample,
)
from ._train import (
    TrainLog as TrainLog,
)
from ._train import (
    plot_train_log as plot_train_log,
)
from ._train import (
    train_geometry_gan as train_geometry_gan,
)
from ._train import (
    train_pose_prior as train_pose_prior,
)
from ._train import (
    train_shape_prior as train_shape_prior,
)

__all__ = [
    "default_pose_prior",
    "default_shape_prior",
    "DSPPConfig",
    "fit_latent_to_landmarks",
    "fit_pca_prior",
    "fit_shape_space_to_landmarks",
    "GeometryGAN",
    "init_aegan",
    "init_geometry_gan",
    "joint_limit_violation",
    "joint_limits",
    "latent_statistics",
    "load_prior",
    "PCA_MODES",
    "PCAPrior",
    "plot_train_log",
    "pose_prior_residual",
    "PosePrior",
    "PriorResidual",
    "sample",
    "save_prior",
    "shape_prior_residual",
    "ShapeFit",
    "ShapePrior",
    "spectral_norms",
    "train_geometry_gan",
    "train_pose_prior",
    "train_shape_prior",
    "TrainLog",
]
