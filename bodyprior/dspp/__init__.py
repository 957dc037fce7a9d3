"""DSPP: deep shape and pose priors (Hu, Shum, Mucherino 2019) — auto-encoders with GANs in their latent
spaces, on the default body's topology and `cmu_mb` rig."""

from ._fitting import (
    PriorResidual as PriorResidual,
    ShapeFit as ShapeFit,
    fit_latent_to_landmarks as fit_latent_to_landmarks,
    fit_shape_space_to_landmarks as fit_shape_space_to_landmarks,
    latent_statistics as latent_statistics,
    pose_prior_residual as pose_prior_residual,
    shape_prior_residual as shape_prior_residual,
)
from ._limits import (
    joint_limit_violation as joint_limit_violation,
    joint_limits as joint_limits,
)
from ._mocap import (
    EULER_ORDER as EULER_ORDER,
    POSE_JOINTS as POSE_JOINTS,
    PoseSet as PoseSet,
    find_mocap_dir as find_mocap_dir,
    load_mocap as load_mocap,
    pose_euler as pose_euler,
    render_poses as render_poses,
    rig_pose as rig_pose,
    split_by_clip as split_by_clip,
)
from ._checkpoint import (
    load_prior as load_prior,
    save_prior as save_prior,
)
from ._nets import (
    DSPPConfig as DSPPConfig,
    GeometryGAN as GeometryGAN,
    PosePrior as PosePrior,
    ShapePrior as ShapePrior,
    init_aegan as init_aegan,
    init_geometry_gan as init_geometry_gan,
    spectral_norms as spectral_norms,
)
from ._sample import (
    PCA_MODES as PCA_MODES,
    PCAPrior as PCAPrior,
    fit_pca_prior as fit_pca_prior,
    sample as sample,
)
from ._train import (
    TrainLog as TrainLog,
    plot_train_log as plot_train_log,
    train_geometry_gan as train_geometry_gan,
    train_pose_prior as train_pose_prior,
    train_shape_prior as train_shape_prior,
)
