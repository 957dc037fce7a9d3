"""Semi-public internals for the benchmarks and experiments (the role of `equinox.internal`).

The benchmarks compare the library with a peer on the library's own building blocks (the NRD
benchmark hands scipy L-BFGS-B the very round systems `nrd` solves; the fit-search benchmark swaps
the S-SCAPE fit's correspondence search for the brute-force reference). Those blocks are private;
this module re-exports them under stable-looking names so that scripts outside the package import
public names and `bodyprior.internal` only, never a `bodyprior.<x>._<y>` module.

**No stability guarantee**: anything here may change or disappear in any release. Nothing inside
the package imports this module (tests/test_layout.py checks that); it is the one core module
allowed to import model families' private modules. See README.md.
"""

import contextlib
from collections.abc import Callable, Iterator

import jax

from .._solution import _check as check_solution
from ..dspp._train import _aegan_cycle as dspp_aegan_cycle
from ..dspp._train import _init_state as dspp_init_state
from ..panoman._splocs import _Sites as PanomanSplocsSites
from ..registration._nrd import _apply as nrd_apply
from ..registration._nrd import _correspond as nrd_correspond
from ..registration._nrd import _energy as nrd_energy
from ..registration._nrd import _grids as nrd_grids
from ..registration._nrd import _pcg as nrd_pcg
from ..registration._nrd import _prepare as nrd_prepare
from ..registration._nrd import _Round as NRDRound
from ..registration._nrd import _scan_arrays as nrd_scan_arrays
from ..registration._nrd import _schedule as nrd_schedule
from ..registration._nrd import _system as nrd_system
from ..sscape import _fit as _sscape_fit
from ..sscape._fit import _compatible_search_jit as sscape_compatible_search_brute_force
from ..sscape._fit import _correspondences as sscape_fit_correspondences

__all__ = [
    "NRDRound",
    "PanomanSplocsSites",
    "check_solution",
    "dspp_aegan_cycle",
    "dspp_init_state",
    "nrd_apply",
    "nrd_correspond",
    "nrd_energy",
    "nrd_grids",
    "nrd_pcg",
    "nrd_prepare",
    "nrd_scan_arrays",
    "nrd_schedule",
    "nrd_system",
    "sscape_compatible_search_brute_force",
    "sscape_fit_correspondences",
    "swap_sscape_fit_correspondences",
]


@contextlib.contextmanager
def swap_sscape_fit_correspondences(fn: Callable) -> Iterator[None]:
    """Inside the block, `bodyprior.sscape.fit_sscape` (and everything else that calls the fit's
    correspondence rule) uses `fn` instead of [`sscape_fit_correspondences`][]; JAX's caches are
    cleared on entry and on exit so that no program traced with the other rule is reused.

    `fn(verts, normals, scan_points, scan_normals, scan_mask, exclude, cfg) -> (idx, weight,
    distance)` with the signature and meaning of `sscape_fit_correspondences`. Not thread-safe.
    """
    old = _sscape_fit._correspondences
    _sscape_fit._correspondences = fn
    jax.clear_caches()
    try:
        yield
    finally:
        _sscape_fit._correspondences = old
        jax.clear_caches()
