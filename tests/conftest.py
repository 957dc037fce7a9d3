"""Shared test configuration.

x64 is switched on for the whole suite: solver and finite-difference gradient tests need float64,
and
library code must behave identically under both precisions (it never hard-codes a dtype).
"""

import os

# One host device: batched entry points compile once per device, so extra host devices would only
# multiply compile time here; multi-device runs are tested in their own processes.
os.environ.setdefault("MPLBACKEND", "Agg")

import tempfile  # noqa: E402

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

jax.config.update("jax_enable_x64", True)

# One persistent compilation cache for the whole run, shared by both xdist workers and the
# experiment/benchmark subprocesses (they inherit the environment variable, which JAX reads): a
# program that several processes compile (the S-SCAPE fit, NRD, ...) is compiled once per run.
# Fresh per run (the controller creates it before the workers start), so no state carries over.
_CACHE = os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", tempfile.mkdtemp(prefix="bodyprior-test-jax-cache-")
)
jax.config.update("jax_compilation_cache_dir", _CACHE)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1.0")
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

# Property tests compile on their first example: no per-example deadline anywhere (a deadline
# measures the machine's load, not the code), so the suite gives the same verdict idle or loaded.
settings.register_profile("bodyprior", deadline=None)
settings.load_profile("bodyprior")


@pytest.fixture
def getkey():
    """Returns a function that hands out fresh, deterministic PRNG keys."""
    key = jr.PRNGKey(0)

    def _getkey():
        nonlocal key
        key, sub = jr.split(key)
        return sub

    return _getkey


@pytest.fixture(autouse=True)
def _bad_input_unchecked(request):
    """Tests marked `bad_input` feed wrong shapes and types on purpose, to check the library's own
    `ValueError`s (what a user sees). The suite type-checks the package at run time
    (`--jaxtyping-packages` in pyproject.toml), which would reject such input first, so these tests
    run with the run-time checks switched off (jaxtyping reads the switch at every call).

    Tests marked `typecheck_off` (the end-to-end experiment runs, whose library calls the unit
    tests already type-check) also run without them: the checks cost ~30 % of their time."""
    node = request.node
    if (
        node.get_closest_marker("bad_input") is None
        and node.get_closest_marker("typecheck_off") is None
    ):
        yield
        return
    import jaxtyping

    old = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", old)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drops JAX's compiled programs after every test module.

    One pytest process compiles thousands of XLA programs; kept all session long, their memory and
    code mappings grew until an XLA compile segfaulted late in the suite. Modules rarely share
    programs, so the recompiles this causes are few."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()


# Worker-seconds per test file on an idle 2-core machine (clean-clone runs, 2026-12-07), for
# the order in which the two xdist workers take files (`--dist loadfile --no-loadscope-reorder`):
# longest first, so that the run does not end with one worker alone on a long file. Only the order
# depends on these numbers; files not listed go last, in collection order.
_FILE_SECONDS = {
    "test_panoman_model.py": 180, "test_notebooks.py": 170, "test_depth.py": 130,
    "test_sscape_registration_experiment.py": 110,
    "test_cli_jobs.py": 80, "test_sscape_fit.py": 80,
    "test_dspp_experiment.py": 80, "test_panoman_solve.py": 65, "test_body.py": 60,
    "test_nrd.py": 55, "test_panoman_rla.py": 50,
    "test_distributed.py": 50,
    "test_dspp_curved_experiment.py": 40, "test_dspp.py": 35, "test_dspp_default.py": 35,
    "test_geometry.py": 35, "test_dspp_prior_fit.py": 35, "test_dspp_shipped_experiment.py": 30,
    "test_sscape.py": 30, "test_scan.py": 30, "test_bootstrap.py": 30, "test_benchmarks.py": 15,
    "test_panoman_default.py": 12,
}  # fmt: skip


def pytest_collection_modifyitems(config, items):
    from pathlib import Path

    def cost(item):
        return -_FILE_SECONDS.get(Path(str(item.fspath)).name, 0)

    items.sort(key=cost)  # stable: tests keep their order within a file
