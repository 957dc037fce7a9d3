"""experiments/dspp_shipped.py (the shipped priors against data they were not trained on), quick."""

import json

import pytest
from helpers import run_script


@pytest.mark.typecheck_off
def test_dspp_shipped_quick(tmp_path):
    run_script("experiments/dspp_shipped.py", "--quick", "--out", tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["mode"] == "quick" and (tmp_path / "samples.png").stat().st_size > 1000
    for k in ("shape_aegan_1nna", "shape_pca_1nna", "pose_aegan_1nna", "pose_pca_1nna"):
        assert 0.0 <= m[k] <= 1.0, (k, m[k])
    # the shipped pose prior is not collapsed: its samples spread like real poses (within 2x)
    assert m["pose_aegan_diversity"] > 0.5 * m["pose_aegan_diversity_ref"]
    assert m["shape_aegan_diversity"] > 0.5 * m["shape_aegan_diversity_ref"]
    assert 0.0 < m["shape_reconstruction_mm"] < 30.0
    assert m["pose_limit_violation_train"] == 0.0  # training poses are inside their own range
