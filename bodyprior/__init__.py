"""bodyprior: statistical human body models in JAX (S-SCAPE, PanoMan, DSPP) on one MakeHuman
topology.

Public API. Implementation lives in private modules; model families are subpackages
(`bodyprior.sscape`). Units are metres and radians; the world frame is Z up, the body facing -Y.
"""

from . import registration as registration  # noqa: I001  (the core before the families)
from . import dspp as dspp
from . import sscape as sscape
from . import panoman as panoman
from ._body import (
    PHENOTYPES as PHENOTYPES,
    TWIST_SEGMENTS as TWIST_SEGMENTS,
    BonePlacement as BonePlacement,
    DefaultBody as DefaultBody,
    evaluate as evaluate,
    landmarks as landmarks,
    load_default_body as load_default_body,
    macro_coefficients as macro_coefficients,
    phenotype_vector as phenotype_vector,
    regress_joints as regress_joints,
    rest_shape as rest_shape,
    target_weights as target_weights,
    sscape_rig as sscape_rig,
    variation_weights as variation_weights,
)
from ._rig import Rig as Rig
from ._bvh import Bvh as Bvh, read_bvh as read_bvh, write_bvh as write_bvh
from ._geometry import (
    barycentric_points as barycentric_points,
    closest_points_on_mesh as closest_points_on_mesh,
    cotangent_weights as cotangent_weights,
    cross_section_areas as cross_section_areas,
    dihedral_angles as dihedral_angles,
    edge_lengths as edge_lengths,
    face_areas as face_areas,
    face_normals as face_normals,
    laplacian_apply as laplacian_apply,
    laplacian_matrix as laplacian_matrix,
    laplacian_sparse as laplacian_sparse,
    nearest_neighbors as nearest_neighbors,
    sample_surface as sample_surface,
    uniform_weights as uniform_weights,
    vertex_areas as vertex_areas,
    vertex_normals as vertex_normals,
)
from ._io import (
    atomic_open as atomic_open,
    atomic_write_bytes as atomic_write_bytes,
    atomic_write_json as atomic_write_json,
    read_mesh as read_mesh,
    write_obj as write_obj,
    write_ply as write_ply,
)
from ._kinematics import (
    Similarity as Similarity,
    forward_kinematics as forward_kinematics,
    kinematic_levels as kinematic_levels,
    umeyama as umeyama,
    validate_parents as validate_parents,
    world_transforms as world_transforms,
)
from ._metrics import (
    generative_metrics as generative_metrics,
)
from ._metrics import (
    hausdorff_distance as hausdorff_distance,
    mean_vertex_distance_metric as mean_vertex_distance_metric,
    pairwise_distances as pairwise_distances,
    pose_geodesic_metric as pose_geodesic_metric,
)
from ._mocap import (
    EULER_ORDER as EULER_ORDER,
    POSE_JOINTS as POSE_JOINTS,
    SKELETON_KINDS as SKELETON_KINDS,
    PoseSet as PoseSet,
    Retargeter as Retargeter,
    find_mocap_dir as find_mocap_dir,
    load_mocap as load_mocap,
    pose_euler as pose_euler,
    poses_to_bvh as poses_to_bvh,
    render_poses as render_poses,
    retarget as retarget,
    rig_pose as rig_pose,
    split_by_clip as split_by_clip,
)
from ._measure import (
    BODY_DENSITY as BODY_DENSITY,
    Measurements as Measurements,
    age_to_years as age_to_years,
    measure as measure,
    mesh_measurements as mesh_measurements,
    phenotypes_from_measurements as phenotypes_from_measurements,
    years_to_age as years_to_age,
)
from ._population import (
    Population as Population,
    sample_phenotypes as sample_phenotypes,
    sample_population as sample_population,
    standing_pose_jitter as standing_pose_jitter,
)
from ._render import (
    contact_sheet as contact_sheet,
    figure_with_colorbar as figure_with_colorbar,
    mesh_bounds as mesh_bounds,
    render_mesh as render_mesh,
    render_vertex_colors as render_vertex_colors,
    save_png as save_png,
)
from ._rotations import (
    EULER_ORDERS as EULER_ORDERS,
    ROTATION_REPS as ROTATION_REPS,
    axis_angle_to_matrix as axis_angle_to_matrix,
    axis_angle_to_quaternion as axis_angle_to_quaternion,
    euler_to_matrix as euler_to_matrix,
    matrix_to_axis_angle as matrix_to_axis_angle,
    matrix_to_euler as matrix_to_euler,
    matrix_to_quaternion as matrix_to_quaternion,
    matrix_to_rotation as matrix_to_rotation,
    matrix_to_sixd as matrix_to_sixd,
    project_to_rotation as project_to_rotation,
    quaternion_conjugate as quaternion_conjugate,
    quaternion_multiply as quaternion_multiply,
    quaternion_to_axis_angle as quaternion_to_axis_angle,
    quaternion_to_matrix as quaternion_to_matrix,
    rotation_shape as rotation_shape,
    rotation_to_matrix as rotation_to_matrix,
    sixd_to_matrix as sixd_to_matrix,
)
from ._solution import RESULTS as RESULTS, Solution as Solution
from ._store import load as load, register_type as register_type, save as save
from ._skinning import (
    dense_weights_to_topk as dense_weights_to_topk,
    dqs as dqs,
    lbs as lbs,
    swing_twist_angle as swing_twist_angle,
    twist_lbs as twist_lbs,
    transform_to_dual_quaternion as transform_to_dual_quaternion,
)
from ._topology import Topology as Topology
from .assets import load_asset as load_asset
from .assets._decimate import load_decimated as load_decimated

__version__ = "0.1.0"
