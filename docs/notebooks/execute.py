"""Executes the docs notebooks and stores their outputs in place (what the site shows):
`python docs/notebooks/execute.py [NAME.ipynb ...]` (default: every notebook here). Each runs in a
fresh kernel of this Python (`sys.executable`), from a scratch working directory, with JAX's
persistent compilation cache of `bodyprior.cli.cache_dir()` (set `JAX_COMPILATION_CACHE_DIR` to
use another). The test suite executes the same notebooks without writing them
(`tests/test_notebooks.py`)."""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TIMEOUT_S = 600  # per cell


def execute(path: Path, *, cwd: str | None = None, timeout: int = TIMEOUT_S):
    """Runs the notebook at `path` in a fresh kernel of `sys.executable`; returns the executed
    notebook (nothing is written). Raises `nbclient.exceptions.CellExecutionError` on an error."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    env_path = os.environ.get("PATH", "")
    bindir = os.path.dirname(sys.executable)
    # the kernel spec runs `python`: make it this interpreter (venvs that are not activated)
    os.environ["PATH"] = bindir + os.pathsep + env_path
    os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    try:
        with tempfile.TemporaryDirectory(prefix="bodyprior-nb-") as tmp:
            client = NotebookClient(
                nb, timeout=timeout, kernel_name="python3",
                resources={"metadata": {"path": cwd or tmp}},
            )  # fmt: skip
            client.execute()
    finally:
        os.environ["PATH"] = env_path
    return nb


def main(argv=None) -> int:
    import nbformat

    names = (argv if argv is not None else sys.argv[1:]) or sorted(
        p.name for p in HERE.glob("*.ipynb")
    )
    if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
        from bodyprior.cli import cache_dir

        os.environ["JAX_COMPILATION_CACHE_DIR"] = cache_dir()
    for name in names:
        path = HERE / name
        t = time.perf_counter()
        nb = execute(path)
        for cell in nb.cells:  # execution metadata (timestamps) would churn the diff
            cell.get("metadata", {}).pop("execution", None)
        tmp = path.with_suffix(".ipynb.tmp")
        nbformat.write(nb, tmp)
        os.replace(tmp, path)
        print(f"{name}: {time.perf_counter() - t:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
