"""The docs notebooks (`docs/notebooks/*.ipynb`) run end to end in a fresh kernel, as the site shows
them: any cell error fails the test. Each is sized to run in about a minute on 2 cores."""

import importlib.util
from pathlib import Path

import pytest

_NB_DIR = Path(__file__).resolve().parents[1] / "docs" / "notebooks"
_NOTEBOOKS = sorted(p.name for p in _NB_DIR.glob("*.ipynb"))

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("nbclient") is None or importlib.util.find_spec("ipykernel") is None,
    reason="nbclient/ipykernel not installed (the test extra installs them)",
)


def _executor():
    spec = importlib.util.spec_from_file_location("_nb_execute", _NB_DIR / "execute.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_notebook_is_listed_on_the_site():
    nav = (_NB_DIR.parents[1] / "mkdocs.yml").read_text()
    assert len(_NOTEBOOKS) >= 5, _NOTEBOOKS
    for name in _NOTEBOOKS:
        assert f"notebooks/{name}" in nav, f"{name} is not in mkdocs.yml's nav"


def test_stored_notebooks_have_outputs():
    """The site renders stored outputs (mkdocs-jupyter, no execution at build time): every code
    cell of a committed notebook was executed (python docs/notebooks/execute.py)."""
    import nbformat

    for name in _NOTEBOOKS:
        nb = nbformat.read(_NB_DIR / name, as_version=4)
        code = [c for c in nb.cells if c.cell_type == "code" and c.source.strip()]
        assert code, name
        missing = [i for i, c in enumerate(code) if c.get("execution_count") is None]
        assert not missing, f"{name}: code cells {missing} were not executed"
        errors = [o for c in code for o in c.get("outputs", []) if o.get("output_type") == "error"]
        assert not errors, f"{name}: stored outputs contain errors"


# Two notebooks whose every step a faster test of the default suite already checks with assertions
# run only with `-m slow` (CI time): register_scan (the CLI reproducing the library's registration:
# tests/test_cli_jobs.py) and dspp_priors (the shipped priors' samples and the prior in a fit:
# tests/test_dspp_default.py, tests/test_dspp_prior_fit.py). Their stored outputs are checked above.
_SLOW = {"register_scan.ipynb", "dspp_priors.ipynb"}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in _SLOW else n for n in _NOTEBOOKS]
)
def test_notebook_runs(name, tmp_path):
    nb = _executor().execute(_NB_DIR / name, cwd=str(tmp_path), timeout=600)
    code = [c for c in nb.cells if c.cell_type == "code" and c.source.strip()]
    assert all(c.get("execution_count") is not None for c in code)
