"""S-SCAPE statistical body model (Pishchulin et al. 2017): model, evaluation, learning, I/O."""

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
from ._serialize import (
    FORMAT_NAME as FORMAT_NAME,
)
from ._template import (
    RegistrationTemplate as RegistrationTemplate,
)
from ._template import (
    registration_template as registration_template,
)
from ._fit import (
    FitConfig as FitConfig,
    FitResult as FitResult,
    SScapeFit as SScapeFit,
    compatible_correspondences as compatible_correspondences,
    fit_similarity as fit_similarity,
    fit_sscape as fit_sscape,
    fit_sscape_batch as fit_sscape_batch,
)
from ._shard import batch_map as batch_map
from ._nrd import (
    NRDConfig as NRDConfig,
    NRDResult as NRDResult,
    nrd as nrd,
    nrd_batch as nrd_batch,
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
from ._evaluate import (
    THRESHOLDS_20MM as THRESHOLDS_20MM,
    THRESHOLDS_50MM as THRESHOLDS_50MM,
    FittingError as FittingError,
    cumulative_curve as cumulative_curve,
    error_colormap_png as error_colormap_png,
    fitting_error as fitting_error,
    fitting_error_batch as fitting_error_batch,
    gt_error as gt_error,
    mean_vertex_error as mean_vertex_error,
    plot_cumulative_curves as plot_cumulative_curves,
    reconstruction_error as reconstruction_error,
)
from ._posture import (
    LaplacianSolver as LaplacianSolver,
    PostureRig as PostureRig,
    learn_normalized as learn_normalized,
    normalize_posture_nh as normalize_posture_nh,
    normalize_posture_nh_batch as normalize_posture_nh_batch,
    normalize_posture_wsx as normalize_posture_wsx,
    normalize_posture_wsx_batch as normalize_posture_wsx_batch,
    posture_rig as posture_rig,
    unpose_lbs as unpose_lbs,
)
from ._bootstrap import (
    BootstrapPass as BootstrapPass,
    BootstrapResult as BootstrapResult,
    GateConfig as GateConfig,
    GateResult as GateResult,
    Registration as Registration,
    body_parts as body_parts,
    calibrate_gate as calibrate_gate,
    bootstrap as bootstrap,
    register_sscape_nrd as register_sscape_nrd,
    registration_gate as registration_gate,
)
from ._scan import (
    Scan as Scan,
    ScannerConfig as ScannerConfig,
    ScanTruth as ScanTruth,
    check_scan as check_scan,
    estimate_normals as estimate_normals,
    pad_scans as pad_scans,
    simulate_scan as simulate_scan,
    simulate_scans as simulate_scans,
)
from ._scanio import (
    detect_units as detect_units,
    read_lnd as read_lnd,
    read_scan as read_scan,
    write_lnd as write_lnd,
    write_scan as write_scan,
)
from ._depth import (
    DEPTH_LANDMARKS as DEPTH_LANDMARKS,
    DepthCamera as DepthCamera,
    DepthFit as DepthFit,
    DepthFitConfig as DepthFitConfig,
    DepthTruth as DepthTruth,
    capture_poses as capture_poses,
    depth_landmarks as depth_landmarks,
    depth_normals as depth_normals,
    depth_scan_truth as depth_scan_truth,
    depth_to_scan as depth_to_scan,
    fit_depth as fit_depth,
    kinect_pair as kinect_pair,
    render_depth as render_depth,
    simulate_depth_scan as simulate_depth_scan,
)
