"""experiments/shipped_space.py at its quick size (slow: two S-SCAPE + NRD compilations)."""

import importlib.util
import json
import os
import sys

import pytest

_PATH = os.path.join(os.path.dirname(__file__), "..", "experiments", "shipped_space.py")


def _load():
    spec = importlib.util.spec_from_file_location("shipped_space", _PATH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["shipped_space"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
@pytest.mark.typecheck_off
def test_shipped_space_quick(tmp_path):
    m = _load().main(["--quick", "--out", str(tmp_path), "--no-progress"])
    assert json.loads((tmp_path / "metrics.json").read_text())["runs"].keys() == m["runs"].keys()
    assert (tmp_path / "gt_error.png").stat().st_size > 1000
    for k in ("10", "20"):
        r = m["runs"][f"default_k{k}"]
        assert r["successful"] == 3
        # the refinement lowers the true error and brings the mesh to the scan
        assert r["refined_gt_error_mm"] < r["sscape_gt_error_mm"] < 15.0
        assert r["refined_fit_error_mm"] < r["sscape_fit_error_mm"]
    rec = m["space_reconstruction_mm"]
    assert rec["20"] < rec["10"] < 10.0
