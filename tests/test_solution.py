"""The one `throw=` rule of `bodyprior.Solution` (bodyprior/_solution.py), on hand-made results."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bodyprior as bp
from bodyprior.internal import check_solution

R = bp.RESULTS


def _batch(ok):
    return jax.vmap(lambda p: R.where(p, R.successful, R.solver_failed))(jnp.asarray(ok))


def test_success_passes_through_unchanged():
    sol = bp.Solution(jnp.arange(3.0), _batch([True, True, True]), {"n": 1}, None)
    out = check_solution(sol, True, "fit")
    assert out is sol
    assert not np.asarray(out.failed).any()


def test_batch_failure_names_items_and_message():
    sol = bp.Solution(jnp.zeros(4), _batch([True, False, True, False]), {}, None)
    with pytest.raises(RuntimeError, match=r"fit failed for 2 of 4 item\(s\) \(indices \[1, 3\]\)"):
        check_solution(sol, True, "fit")
    with pytest.raises(RuntimeError, match="Levenberg-Marquardt solve failed"):
        check_solution(sol, True, "fit")
    # throw=False: per-item results as data, nothing raised
    out = check_solution(sol, False, "fit")
    np.testing.assert_array_equal(np.asarray(out.failed), [False, True, False, True])


def test_scalar_failure_message():
    sol = bp.Solution(jnp.zeros(()), R.nonfinite_loss, {}, None)
    with pytest.raises(RuntimeError, match="^train failed: Training stopped at a non-finite loss"):
        check_solution(sol, True, "train")


def test_traced_failure_raises_at_run_time():
    @eqx.filter_jit
    def run(ok):
        res = R.where(ok, R.successful, R.max_steps_reached)
        return check_solution(bp.Solution(jnp.ones(2), res, {}, None), True, "solve").value

    np.testing.assert_array_equal(np.asarray(run(True)), [1.0, 1.0])
    with pytest.raises(Exception, match="maximum number of solver steps"):
        jax.block_until_ready(run(False))
