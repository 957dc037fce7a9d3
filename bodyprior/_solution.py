"""One result convention for every fitter and trainer (after optimistix's `Solution`/`RESULTS`).

Every fitter (`bodyprior.sscape.fit_sscape`, `fit_sscape_batch`, `fit_depth`,
`bodyprior.registration.nrd`, `nrd_batch`, `bodyprior.dspp.fit_shape_space_to_landmarks`,
`fit_latent_to_landmarks`) and every trainer (`bodyprior.dspp.train_shape_prior`,
`train_pose_prior`, `train_geometry_gan`) returns a [`bodyprior.Solution`][]: `value` (the fitted
thing), `result` (a [`bodyprior.RESULTS`][] item), `stats` (a dict of arrays) and `aux`, and takes
`throw: bool = True`.

**What counts as a failure** (the one rule, applied by every fitter): a solution failed exactly
when `result != RESULTS.successful`, and `throw=True` raises then. `result` is not successful when

- values are non-finite (`RESULTS.nonfinite`; a trainer's loss: `RESULTS.nonfinite_loss`);
- a solver failed outright (diverged or met a singular system: `RESULTS.solver_failed`, or the
  optimistix item of the solve);
- a solve that promises a tolerance stopped at its step limit without meeting it
  (`RESULTS.max_steps_reached` / `nonlinear_max_steps_reached`): NRD's per-round linear solve to
  `cg_rtol`, the DSPP landmark fits' Levenberg-Marquardt solve to `rtol`/`atol`.

Using up an *iteration budget* is not a failure: the pass/round schedules of the S-SCAPE fit, the
depth fit and NRD (`max_passes`, `max_rounds`), the Levenberg-Marquardt step limits of the solves
inside an S-SCAPE or depth pass (each is a truncated step that the next pass continues from) and
a trainer's `n_steps`. Whether an outer loop met its stopping test is `stats["converged"]`.

Batched fitters return one `result` per item (`result` of shape `(B,)`, like every other leaf);
with `throw=True` they raise once, naming the failed items. The check is
[`bodyprior.Solution`][]'s own (`_check`): on concrete results (the public entry points, after
their jitted call) it raises a `RuntimeError` naming the items; under an outer trace it threads
`result.error_if` onto the value (optimistix's mechanism).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import numpy as np
import optimistix as optx

__all__ = ["RESULTS", "Solution"]


class RESULTS(optx.RESULTS):  # pyright: ignore
    """Outcome of a fit or a training run: `optimistix.RESULTS` (and so `lineax.RESULTS`) plus the
    items below. An `equinox.Enumeration`: compare with `==`, read the message with
    `RESULTS[result]`, promote an optimistix result with `RESULTS.promote(sol.result)`."""

    solver_failed = "A Levenberg-Marquardt solve failed (diverged or hit a singular system)."
    nonfinite_loss = (
        "Training stopped at a non-finite loss; lower `learning_rate` or check the data."
    )


class Solution(eqx.Module):
    """The result of a fitter or a trainer (see the module docstring for what counts as failure).

    **Fields:**

    - `value`: the fitted thing (a Module: e.g. `bodyprior.sscape.SScapeFit`,
      `bodyprior.registration.NRDFit`, `bodyprior.dspp.ShapeFit`, a trained prior).
    - `result`: a [`bodyprior.RESULTS`][] item (shape `(B,)` for batched fitters).
    - `stats`: dict of arrays (steps, passes/rounds, final costs; per fitter's docstring).
    - `aux`: anything else (a trainer's `TrainLog`), else `None`.
    """

    value: Any
    result: RESULTS
    stats: dict
    aux: Any = None

    @property
    def failed(self):
        """Bool array (shape of `result`): the items whose `result` is not successful."""
        return self.result != RESULTS.successful


def _check(sol: Solution, throw: bool, what: str) -> Solution:
    """The one `throw=` rule: raise (or thread an error onto `sol.value`) if `sol.failed`."""
    if not throw:
        return sol
    if sol.result.is_traced():
        value = sol.result.error_if(sol.value, sol.failed)
        return Solution(value, sol.result, sol.stats, sol.aux)
    failed = np.asarray(sol.failed)
    if not failed.any():
        return sol
    bad = np.flatnonzero(failed.reshape(-1))
    # Public equinox API only: index the item's array leaf, then `RESULTS[item]` is its message.
    def item(i: int):
        return jax.tree.map(lambda v: np.asarray(np.asarray(v).reshape(-1)[i]), sol.result)

    msgs = {RESULTS[item(int(i))] for i in bad}
    if failed.ndim == 0:
        where = ""
    else:
        shown = bad[:20].tolist()
        more = f" and {bad.size - 20} more" if bad.size > 20 else ""
        where = f" for {bad.size} of {failed.size} item(s) (indices {shown}{more})"
    raise RuntimeError(
        f"{what} failed{where}: {' / '.join(sorted(msgs))} Pass `throw=False` to inspect "
        "`solution.result`."
    )

