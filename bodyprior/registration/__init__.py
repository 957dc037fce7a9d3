"""The model-independent registration and acquisition core.

Everything a statistical body model needs to meet raw data, whatever the model: scan containers and
their checks, the virtual laser scanner with ground truth, PLY/OBJ point clouds and CAESAR `.lnd`
landmark files, the exact fixed-radius grid search, batching over devices (`batch_map`), the
registration template (the default body prepared for registration), NRD non-rigid template
fitting, the error measures with their cumulative curves and colour maps, and the Kinect-like
depth camera. Model families (`bodyprior.sscape`, `bodyprior.dspp`, PanoMan) import this core; it
imports none of them (`docs/architecture.md`).
"""

from ._camera import (
    DEPTH_LANDMARKS as DEPTH_LANDMARKS,
)
from ._camera import (
    DepthCamera as DepthCamera,
)
from ._camera import (
    DepthTruth as DepthTruth,
)
from ._camera import (
    capture_poses as capture_poses,
)
from ._camera import (
    depth_landmarks as depth_landmarks,
)
from ._camera import (
    depth_normals as depth_normals,
)
from ._camera import (
    depth_scan_truth as depth_scan_truth,
)
from ._camera import (
    depth_to_scan as depth_to_scan,
)
from ._camera import (
    kinect_pair as kinect_pair,
)
from ._camera import (
    render_depth as render_depth,
)
from ._camera import (
    simulate_depth_scan as simulate_depth_scan,
)
from ._evaluate import (
    THRESHOLDS_20MM as THRESHOLDS_20MM,
)
from ._evaluate import (
    THRESHOLDS_50MM as THRESHOLDS_50MM,
)
from ._evaluate import (
    FittingError as FittingError,
)
from ._evaluate import (
    cumulative_curve as cumulative_curve,
)
from ._evaluate import (
    error_colormap_png as error_colormap_png,
)
from ._evaluate import (
    fitting_error as fitting_error,
)
from ._evaluate import (
    fitting_error_batch as fitting_error_batch,
)
from ._evaluate import (
    gt_error as gt_error,
)
from ._evaluate import (
    mean_vertex_error as mean_vertex_error,
)
from ._evaluate import (
    plot_cumulative_curves as plot_cumulative_curves,
)
from ._grid import nearest_within as nearest_within
from ._nrd import (
    NRDConfig as NRDConfig,
)
from ._nrd import (
    NRDFit as NRDFit,
)
from ._nrd import (
    NRDPrep as NRDPrep,
)
from ._nrd import (
    nrd as nrd,
)
from ._nrd import (
    nrd_batch as nrd_batch,
)
from ._nrd import (
    prepare_nrd as prepare_nrd,
)
from ._scan import (
    Scan as Scan,
)
from ._scan import (
    ScannerConfig as ScannerConfig,
)
from ._scan import (
    ScanTruth as ScanTruth,
)
from ._scan import (
    check_scan as check_scan,
)
from ._scan import (
    estimate_normals as estimate_normals,
)
from ._scan import (
    pad_scans as pad_scans,
)
from ._scan import (
    simulate_scan as simulate_scan,
)
from ._scan import (
    simulate_scans as simulate_scans,
)
from ._scanio import (
    detect_units as detect_units,
)
from ._scanio import (
    read_lnd as read_lnd,
)
from ._scanio import (
    read_scan as read_scan,
)
from ._scanio import (
    write_lnd as write_lnd,
)
from ._scanio import (
    write_scan as write_scan,
)
from ._shard import batch_map as batch_map
from ._template import (
    RegistrationTemplate as RegistrationTemplate,
)
from ._template import (
    registration_template as registration_template,
)
from ._template import (
    template_sources as template_sources,
)

__all__ = [
    "batch_map",
    "capture_poses",
    "check_scan",
    "cumulative_curve",
    "DEPTH_LANDMARKS",
    "depth_landmarks",
    "depth_normals",
    "depth_scan_truth",
    "depth_to_scan",
    "DepthCamera",
    "DepthTruth",
    "detect_units",
    "error_colormap_png",
    "estimate_normals",
    "fitting_error",
    "fitting_error_batch",
    "FittingError",
    "gt_error",
    "kinect_pair",
    "mean_vertex_error",
    "nearest_within",
    "nrd",
    "nrd_batch",
    "NRDConfig",
    "NRDFit",
    "NRDPrep",
    "pad_scans",
    "plot_cumulative_curves",
    "prepare_nrd",
    "read_lnd",
    "read_scan",
    "registration_template",
    "RegistrationTemplate",
    "render_depth",
    "Scan",
    "ScannerConfig",
    "ScanTruth",
    "simulate_depth_scan",
    "simulate_scan",
    "simulate_scans",
    "template_sources",
    "THRESHOLDS_20MM",
    "THRESHOLDS_50MM",
    "write_lnd",
    "write_scan",
]
