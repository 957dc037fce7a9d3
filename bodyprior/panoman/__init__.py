"""PanoMan (Wang et al., ACM TOG 2021): a body model in relative edge lengths and dihedral angles.

This subpackage holds PanoMan's machinery on bodyprior's core (it imports the core only):

- **RLA features** (paper eq. 1): [`bodyprior.panoman.rla_encode`][] and its path-unwrapped
  variants, in an [`bodyprior.panoman.RLA`][] container, with the fold mask of hinges near `±π`.
- **The decoder g** (Appendix A): [`bodyprior.panoman.rla_decode`][] with a per-reference
  [`bodyprior.panoman.Decoder`][] — exact on integrable input, least squares with residual and
  holonomy diagnostics otherwise, differentiable and batched.
- **The discrete-shell energy** (eqs. 6–8): [`bodyprior.panoman.shell_residuals`][] /
  [`bodyprior.panoman.shell_energy`][] (stretch as printed, F&B or printed bending weight, wrapped
  angles, fold guard), and its Levenberg–Marquardt solver [`bodyprior.panoman.shell_solve`][]
  over vertices and model parameters jointly, with editing, handle, joint and point-to-plane
  constraints ([`bodyprior.panoman.shell_constraints`][]).
- **The model and reconstruction** (§3–5): [`bodyprior.panoman.train_panoman`][] on the
  open-data training set ([`bodyprior.panoman.make_training_split`][]), a
  [`bodyprior.panoman.PanoManKit`][] (model, joint regressor, LBS initialiser) and
  [`bodyprior.panoman.reconstruct`][] (IK then [`bodyprior.panoman.fit_panoman`][]); a trained
  kit ships: [`bodyprior.panoman.default_panoman`][].
- **Sparse localized components** (Neumann et al. 2013, as PanoMan decomposes its RLA, §4.2):
  [`bodyprior.panoman.splocs`][] on per-edge scalars or per-vertex vectors, support maps from
  mesh distances in metres, signed weights, monotone energy; [`bodyprior.panoman.Splocs`][] with
  [`bodyprior.panoman.splocs_project`][] / [`bodyprior.panoman.splocs_reconstruct`][].

Angles follow the paper: `â = ψ − ψ_r` with `ψ` the interior dihedral angle
([`bodyprior.panoman.interior_dihedral_angles`][], `π − bodyprior.dihedral_angles`).
Kernels work on one mesh; batch with `jax.vmap`. Units: metres and radians.
"""

from ._data import CANONICAL_GESTURES as CANONICAL_GESTURES
from ._data import KINDS as KINDS
from ._data import PanomanData as PanomanData
from ._data import expression_set as expression_set
from ._data import gesture_poses as gesture_poses
from ._data import make_panoman_data as make_panoman_data
from ._decode import (
    DecodedMesh as DecodedMesh,
)
from ._decode import (
    Decoder as Decoder,
)
from ._decode import decoder_with_reference as decoder_with_reference
from ._decode import (
    nearest_rotation as nearest_rotation,
)
from ._decode import (
    prepare_decoder as prepare_decoder,
)
from ._decode import (
    rla_decode as rla_decode,
)
from ._default import RECIPE as RECIPE
from ._default import PanoManKit as PanoManKit
from ._default import TrainingSplit as TrainingSplit
from ._default import build_default_panoman as build_default_panoman
from ._default import default_panoman as default_panoman
from ._default import kit_path as kit_path
from ._default import load_kit as load_kit
from ._default import make_kit as make_kit
from ._default import make_training_split as make_training_split
from ._default import reconstruct as reconstruct
from ._default import save_kit as save_kit
from ._default import train_split as train_split
from ._fit import JointRegressor as JointRegressor
from ._fit import LbsModel as LbsModel
from ._fit import PanoManFit as PanoManFit
from ._fit import PanoManSolver as PanoManSolver
from ._fit import fit_joint_regressor as fit_joint_regressor
from ._fit import fit_lbs as fit_lbs
from ._fit import fit_panoman as fit_panoman
from ._fit import make_lbs_model as make_lbs_model
from ._fit import prepare_panoman_solver as prepare_panoman_solver
from ._model import MLP as MLP
from ._model import PARTS as PARTS
from ._model import PanoManModel as PanoManModel
from ._model import encode_panoman_data as encode_panoman_data
from ._model import evaluate as evaluate
from ._model import fit_mlp as fit_mlp
from ._model import load_panoman as load_panoman
from ._model import model_targets as model_targets
from ._model import pose_features as pose_features
from ._model import save_panoman as save_panoman
from ._model import train_panoman as train_panoman
from ._rla import (
    RLA as RLA,
)
from ._rla import (
    fold_mask as fold_mask,
)
from ._rla import (
    interior_dihedral_angles as interior_dihedral_angles,
)
from ._rla import (
    rla_encode as rla_encode,
)
from ._rla import (
    rla_encode_path as rla_encode_path,
)
from ._rla import (
    rla_encode_unwrapped as rla_encode_unwrapped,
)
from ._rla import (
    rla_targets as rla_targets,
)
from ._rla import (
    wrap_angle as wrap_angle,
)
from ._shell import shell_energy as shell_energy
from ._shell import shell_residuals as shell_residuals
from ._solve import ShellConstraints as ShellConstraints
from ._solve import ShellFit as ShellFit
from ._solve import ShellSolver as ShellSolver
from ._solve import prepare_shell_solver as prepare_shell_solver
from ._solve import shell_constraints as shell_constraints
from ._solve import shell_solve as shell_solve
from ._splocs import Splocs as Splocs
from ._splocs import splocs as splocs
from ._splocs import splocs_project as splocs_project
from ._splocs import splocs_reconstruct as splocs_reconstruct

__all__ = [
    "RECIPE",
    "PanoManKit",
    "TrainingSplit",
    "build_default_panoman",
    "default_panoman",
    "kit_path",
    "load_kit",
    "make_kit",
    "make_training_split",
    "reconstruct",
    "save_kit",
    "train_split",
    "JointRegressor",
    "LbsModel",
    "PanoManFit",
    "PanoManSolver",
    "fit_joint_regressor",
    "fit_lbs",
    "fit_panoman",
    "make_lbs_model",
    "prepare_panoman_solver",
    "KINDS",
    "MLP",
    "PARTS",
    "PanoManModel",
    "PanomanData",
    "decoder_with_reference",
    "encode_panoman_data",
    "evaluate",
    "expression_set",
    "fit_mlp",
    "gesture_poses",
    "load_panoman",
    "make_panoman_data",
    "model_targets",
    "pose_features",
    "save_panoman",
    "train_panoman",
    "RLA",
    "DecodedMesh",
    "Decoder",
    "ShellConstraints",
    "ShellFit",
    "ShellSolver",
    "Splocs",
    "fold_mask",
    "interior_dihedral_angles",
    "nearest_rotation",
    "prepare_decoder",
    "prepare_shell_solver",
    "rla_decode",
    "rla_encode",
    "rla_encode_path",
    "rla_encode_unwrapped",
    "rla_targets",
    "shell_energy",
    "shell_constraints",
    "shell_residuals",
    "shell_solve",
    "splocs",
    "splocs_project",
    "splocs_reconstruct",
    "wrap_angle",
]
