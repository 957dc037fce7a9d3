"""Helpers shared by the test modules: finite-difference checks and the script runner.

(Template and toy-body builders live in `tests/_toybody.py`.)
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def central_difference(f, x, v, h: float = 1e-6):
    """Directional derivative of `f` at `x` along `v` by central differences, `O(h²)`."""
    return (f(x + h * v) - f(x - h * v)) / (2 * h)


def assert_jvp_matches_fd(f, x, getkey, *, n_dirs: int = 3, h: float = 1e-6, rtol: float = 1e-6):
    """`jax.jvp(f)` along `n_dirs` random directions equals central differences (float64)."""
    for _ in range(n_dirs):
        u = jr.normal(getkey(), x.shape, dtype=x.dtype)
        _, jvp = jax.jvp(f, (x,), (u,))
        fd = central_difference(f, x, u, h)
        np.testing.assert_allclose(jvp, fd, rtol=rtol, atol=rtol * float(jnp.max(jnp.abs(fd))))


def run_script(script: str, *args: str, env: dict | None = None, timeout: float = 1800):
    """Runs `ROOT/script` with this interpreter, the repository on `PYTHONPATH`, and returns the
    completed process after asserting exit code 0 (showing the tail of its output otherwise).
    The timeout is a hang guard only: nothing here depends on how fast the machine is."""
    e = dict(os.environ if env is None else env)
    e.setdefault("MPLBACKEND", "Agg")
    e["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [e.get("PYTHONPATH")] if p])
    proc = subprocess.run(
        [sys.executable, str(ROOT / script), *map(str, args)],
        cwd=ROOT,
        env=e,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc
