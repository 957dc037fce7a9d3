"""S-SCAPE statistical body model (Pishchulin et al. 2017): the model, evaluation, learning and the
space measures, the S-SCAPE and depth fits, posture normalization, bootstrapping, I/O and the MPII
humanshape format. Scans, the scanner, the registration template, NRD and the error measures are
model-independent and live in `bodyprior.registration`."""

from ._bootstrap import (
    BootstrapPass as BootstrapPass,
)
from ._bootstrap import (
    BootstrapResult as BootstrapResult,
)
from ._bootstrap import (
    GateConfig as GateConfig,
)
from ._bootstrap import (
    GateResult as GateResult,
)
from ._bootstrap import (
    Registration as Registration,
)
from ._bootstrap import (
    body_parts as body_parts,
)
from ._bootstrap import (
    bootstrap as bootstrap,
)
from ._bootstrap import (
    calibrate_gate as calibrate_gate,
)
from ._bootstrap import (
    observed_vertices as observed_vertices,
)
from ._bootstrap import (
    register_sscape_nrd as register_sscape_nrd,
)
from ._bootstrap import (
    registration_gate as registration_gate,
)
from ._default import (
    default_space as default_space,
)
from ._default import (
    space_path as space_path,
)
from ._depth import (
    DepthFit as DepthFit,
)
from ._depth import (
    DepthFitConfig as DepthFitConfig,
)
from ._depth import (
    fit_depth as fit_depth,
)
from ._fit import (
    FitConfig as FitConfig,
)
from ._fit import (
    SScapeFit as SScapeFit,
)
from ._fit import (
    compatible_correspondences as compatible_correspondences,
)
from ._fit import (
    fit_similarity as fit_similarity,
)
from ._fit import (
    fit_sscape as fit_sscape,
)
from ._fit import (
    fit_sscape_batch as fit_sscape_batch,
)
from ._learn import (
    Compactness as Compactness,
)
from ._learn import (
    Generalization as Generalization,
)
from ._learn import (
    Specificity as Specificity,
)
from ._learn import (
    compactness as compactness,
)
from ._learn import (
    generalization as generalization,
)
from ._learn import (
    learn as learn,
)
from ._learn import (
    mean_vertex_distance as mean_vertex_distance,
)
from ._learn import (
    procrustes_align as procrustes_align,
)
from ._learn import (
    reconstruction_error as reconstruction_error,
)
from ._learn import (
    specificity as specificity,
)
from ._model import (
    SScapeModel as SScapeModel,
)
from ._model import (
    evaluate as evaluate,
)
from ._model import (
    rest_joints as rest_joints,
)
from ._model import (
    shape_vertices as shape_vertices,
)
from ._model import (
    truncate as truncate,
)
from ._mpii import (
    MM_TO_M as MM_TO_M,
)
from ._mpii import (
    HumanShapeRig as HumanShapeRig,
)
from ._mpii import (
    humanshape_pose as humanshape_pose,
)
from ._mpii import (
    joint_regressor_from_weights as joint_regressor_from_weights,
)
from ._mpii import (
    load_mpii_humanshape as load_mpii_humanshape,
)
from ._mpii import (
    write_mpii_humanshape as write_mpii_humanshape,
)
from ._posture import (
    LaplacianSolver as LaplacianSolver,
)
from ._posture import (
    PostureRig as PostureRig,
)
from ._posture import (
    learn_normalized as learn_normalized,
)
from ._posture import (
    normalize_posture_nh as normalize_posture_nh,
)
from ._posture import (
    normalize_posture_nh_batch as normalize_posture_nh_batch,
)
from ._posture import (
    normalize_posture_wsx as normalize_posture_wsx,
)
from ._posture import (
    normalize_posture_wsx_batch as normalize_posture_wsx_batch,
)
from ._posture import (
    posture_rig as posture_rig,
)
from ._posture import (
    unpose_lbs as unpose_lbs,
)
from ._serialize import (
    FORMAT_NAME as FORMAT_NAME,
)
from ._serialize import (
    FORMAT_VERSION as FORMAT_VERSION,
)
from ._serialize import (
    load_model as load_model,
)
from ._serialize import (
    save_model as save_model,
)

__all__ = [
    "body_parts",
    "bootstrap",
    "BootstrapPass",
    "BootstrapResult",
    "calibrate_gate",
    "Compactness",
    "compactness",
    "compatible_correspondences",
    "default_space",
    "DepthFit",
    "DepthFitConfig",
    "evaluate",
    "fit_depth",
    "fit_similarity",
    "fit_sscape",
    "fit_sscape_batch",
    "FitConfig",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GateConfig",
    "GateResult",
    "Generalization",
    "generalization",
    "humanshape_pose",
    "HumanShapeRig",
    "joint_regressor_from_weights",
    "LaplacianSolver",
    "learn",
    "learn_normalized",
    "load_model",
    "load_mpii_humanshape",
    "mean_vertex_distance",
    "MM_TO_M",
    "normalize_posture_nh",
    "normalize_posture_nh_batch",
    "normalize_posture_wsx",
    "normalize_posture_wsx_batch",
    "observed_vertices",
    "posture_rig",
    "PostureRig",
    "procrustes_align",
    "reconstruction_error",
    "register_sscape_nrd",
    "Registration",
    "registration_gate",
    "rest_joints",
    "save_model",
    "shape_vertices",
    "space_path",
    "Specificity",
    "specificity",
    "SScapeFit",
    "SScapeModel",
    "truncate",
    "unpose_lbs",
    "write_mpii_humanshape",
]
