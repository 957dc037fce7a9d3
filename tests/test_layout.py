"""The package layout rule (docs/architecture.md), checked on the import statements of every module.

- The core (`bodyprior/_*.py`, `bodyprior/assets/`, `bodyprior/registration/`; the command-line
  app `bodyprior/cli.py` and its jobs `bodyprior/_cli_jobs.py` excepted) imports no model family.
- A model family (`bodyprior/sscape/`, `bodyprior/dspp/`, `bodyprior/panoman/`) may import the core
  and another family's public names, never another family's private modules.
- Exception: `bodyprior/internal/` is a semi-public re-export shim for the benchmarks and
  experiments (as `equinox.internal`): it may import any private module, families' included, and
  in exchange no module of the package imports it.
"""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "bodyprior"
FAMILIES = ("sscape", "dspp", "panoman")


def _modules():
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
            package = parts
        else:
            package = parts[:-1]
        yield path, parts, package


def _imports(path: Path, package: list[str]):
    """Absolute dotted names of everything `path` imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            yield node.lineno, mod
            for a in node.names:  # `from . import sscape` imports a subpackage
                yield node.lineno, f"{mod}.{a.name}"


def _family(dotted: list[str]) -> str | None:
    return (
        dotted[1]
        if len(dotted) > 1 and dotted[0] == "bodyprior" and dotted[1] in FAMILIES
        else None
    )


def _violations():
    out = []
    for path, parts, package in _modules():
        if parts[:2] == ["bodyprior", "internal"]:
            continue  # the re-export shim (module docstring); checked by the rule below instead
        own = _family(parts)
        app = parts in (["bodyprior", "cli"], ["bodyprior", "_cli_jobs"])
        is_core = own is None and not app and parts != ["bodyprior"]
        for line, name in _imports(path, package):
            target = name.split(".")
            if target[:2] == ["bodyprior", "internal"]:
                out.append(f"{path.relative_to(PKG.parent)}:{line} imports {name} (the shim)")
                continue
            fam = _family(target)
            if fam is None:
                continue
            where = f"{path.relative_to(PKG.parent)}:{line} imports {name}"
            if is_core:
                out.append(f"core module {where}")
            elif own is not None and fam != own and any(p.startswith("_") for p in target[2:]):
                out.append(f"family {own}: {where} (another family's private module)")
    return out


def test_layout_rule_holds():
    bad = _violations()
    assert not bad, "\n".join(bad)


def test_layout_checker_sees_violations(tmp_path):
    """The checker itself: a planted wrong-way import in a core module and a cross-family private
    import are both reported."""
    fake = tmp_path / "bodyprior"
    (fake / "registration").mkdir(parents=True)
    (fake / "dspp").mkdir()
    (fake / "__init__.py").write_text("from . import sscape as sscape\n")
    (fake / "_metrics.py").write_text("from .dspp._mocap import EULER_ORDER\n")
    (fake / "registration" / "__init__.py").write_text("from ..sscape import learn\n")
    (fake / "dspp" / "_fit.py").write_text(
        "from ..sscape._model import SScapeModel\nfrom ..sscape import shape_vertices\n"
    )
    globals()["PKG"] = fake
    try:
        bad = _violations()
    finally:
        globals()["PKG"] = Path(__file__).resolve().parents[1] / "bodyprior"
    assert any("_metrics.py:1" in b for b in bad)
    assert any("registration/__init__.py:1" in b for b in bad)
    assert any("dspp/_fit.py:1" in b for b in bad)
    assert not any("dspp/_fit.py:2" in b for b in bad), bad
    assert not any(b.startswith("core module bodyprior/__init__") for b in bad), bad


def test_layout_internal_is_the_exception(tmp_path):
    """`bodyprior/internal/` may import families' private modules; importing it from inside the
    package is reported."""
    fake = tmp_path / "bodyprior"
    (fake / "internal").mkdir(parents=True)
    (fake / "internal" / "__init__.py").write_text("from ..sscape._fit import _correspondences\n")
    (fake / "_metrics.py").write_text("from .internal import nrd_apply\n")
    globals()["PKG"] = fake
    try:
        bad = _violations()
    finally:
        globals()["PKG"] = Path(__file__).resolve().parents[1] / "bodyprior"
    assert not any("internal/__init__.py" in b for b in bad), bad
    assert any("_metrics.py:1" in b for b in bad), bad


@pytest.mark.parametrize("family", ["sscape", "dspp"])
def test_families_are_packages(family):
    assert (PKG / family / "__init__.py").is_file()
