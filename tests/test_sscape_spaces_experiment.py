"""The shape-space experiment (experiments/sscape_spaces.py) in its --quick mode."""

from __future__ import annotations

import importlib.util
import json
import os

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))


def _load():
    path = os.path.join(HERE, "..", "experiments", "sscape_spaces.py")
    spec = importlib.util.spec_from_file_location("sscape_spaces", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# ~80 s on the previous machine, 132 s on this session's: with it the clean-clone suite took 1,026 s
# (15-min budget), so it stays opt-in (pytest -m slow).
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::UserWarning")
def test_quick_run_writes_metrics_and_figures(tmp_path):
    mod = _load()
    mod.main(["--quick", "--out", str(tmp_path), "--no-progress"])
    m = json.loads((tmp_path / "metrics.json").read_text())
    boot = m["bootstrapping"]
    # "frozen" (default): at most n_passes, fewer once no scan is left to add
    assert 1 <= len(boot["accepted_per_pass"]) <= m["sizes"]["n_passes"]
    assert all(0 <= a <= boot["n_scans"] for a in boot["accepted_per_pass"])
    for p in boot["passes"]:
        assert 0.0 < p["gt_error_mm_mean"] < 50.0
    by_size = m["training_size"]["by_size"]
    assert set(by_size) == {"10", "20", "40", "all"}
    # More training meshes generalize better to held-out meshes (at the largest common M).
    assert by_size["all"]["generalization_mm"][-1] < by_size["10"]["generalization_mm"][-1]
    post = m["posture"]["ground_truth_pool"]
    assert set(post) == {"none", "NH", "WSX"}
    # Normalization brings the posed bodies much closer to their true rest-posture shapes.
    assert (
        post["NH"]["normalized_vs_true_rest_mm"] < 0.5 * post["none"]["normalized_vs_true_rest_mm"]
    )
    for name in ("bootstrap_fitting_error", "bootstrap_gt_error", "size_generalization",
                 "posture_gt", "pca_modes"):  # fmt: skip
        assert (tmp_path / f"{name}.png").stat().st_size > 5_000
