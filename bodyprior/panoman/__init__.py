"""PanoMan (Wang et al., ACM TOG 2021): a body model in relative edge lengths and dihedral angles.

This subpackage holds PanoMan's machinery on bodyprior's core (it imports the core only):

- **RLA features** (paper eq. 1): [`bodyprior.panoman.rla_encode`][] and its path-unwrapped
  variants, in an [`bodyprior.panoman.RLA`][] container, with the fold mask of hinges near `±π`.
- **The decoder g** (Appendix A): [`bodyprior.panoman.rla_decode`][] with a per-reference
  [`bodyprior.panoman.Decoder`][] — exact on integrable input, least squares with residual and
  holonomy diagnostics otherwise, differentiable and batched.
- **The discrete-shell energy** (eqs. 6–8): [`bodyprior.panoman.shell_residuals`][] /
  [`bodyprior.panoman.shell_energy`][] (stretch as printed, F&B or printed bending weight, wrapped
  angles, fold guard). Its Gauss–Newton solver with constraints is not built yet.

Angles follow the paper: `â = ψ − ψ_r` with `ψ` the interior dihedral angle
([`bodyprior.panoman.interior_dihedral_angles`][], `π − bodyprior.dihedral_angles`).
Kernels work on one mesh; batch with `jax.vmap`. Units: metres and radians.
"""

from ._decode import (
    DecodedMesh as DecodedMesh,
)
from ._decode import (
    Decoder as Decoder,
)
from ._decode import (
    nearest_rotation as nearest_rotation,
)
from ._decode import (
    prepare_decoder as prepare_decoder,
)
from ._decode import (
    rla_decode as rla_decode,
)
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

__all__ = [
    "RLA",
    "DecodedMesh",
    "Decoder",
    "fold_mask",
    "interior_dihedral_angles",
    "nearest_rotation",
    "prepare_decoder",
    "rla_decode",
    "rla_encode",
    "rla_encode_path",
    "rla_encode_unwrapped",
    "rla_targets",
    "shell_energy",
    "shell_residuals",
    "wrap_angle",
]
