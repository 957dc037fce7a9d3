"""S-SCAPE statistical body model (Pishchulin et al. 2017): model, evaluation, learning, I/O."""

from ._learn import (
    Compactness as Compactness,
    Generalization as Generalization,
    Specificity as Specificity,
    compactness as compactness,
    generalization as generalization,
    learn as learn,
    mean_vertex_distance as mean_vertex_distance,
    procrustes_align as procrustes_align,
    specificity as specificity,
)
from ._model import (
    SScapeModel as SScapeModel,
    evaluate as evaluate,
    rest_joints as rest_joints,
    shape_vertices as shape_vertices,
    truncate as truncate,
)
from ._mpii import (
    MM_TO_M as MM_TO_M,
    HumanShapeRig as HumanShapeRig,
    humanshape_pose as humanshape_pose,
    joint_regressor_from_weights as joint_regressor_from_weights,
    load_mpii_humanshape as load_mpii_humanshape,
    write_mpii_humanshape as write_mpii_humanshape,
)
from ._serialize import (
    FORMAT_NAME as FORMAT_NAME,
    FORMAT_VERSION as FORMAT_VERSION,
    load_model as load_model,
    save_model as save_model,
)
