"""experiments/sscape_registration.py end to end at its smallest size (`--tiny`)."""

import importlib.util
import json
import os

import pytest

_PATH = os.path.join(os.path.dirname(__file__), "..", "experiments", "sscape_registration.py")


def _load():
    spec = importlib.util.spec_from_file_location("sscape_registration", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.typecheck_off
def test_registration_experiment_tiny(tmp_path):
    exp = _load()
    out = tmp_path / "reg"
    # --tiny with fewer bodies and 5 components (the smallest run that still exercises every stage;
    # the suite's time is mostly compilation, which does not shrink with the sizes)
    m = exp.main(
        ["--tiny", "--components", "5", "--n-init", "10", "--n-train", "8", "--n-test", "2",
         "--out", str(out), "--seed", "0", "--no-progress"]
    )  # fmt: skip
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["nrd_gt_error_mm_mean"] == pytest.approx(m["nrd_gt_error_mm_mean"])
    for key in (
        "nrd_gt_error_mm_mean",
        "nrd_frac_below_10mm",
        "sscape_only_gt_error_mm_mean",
        "sscape_nrd_gt_error_mm_mean",
        "generalization_mm_at_20",
        "specificity_mm_at_20",
    ):
        assert key in m and m[key] == m[key], key  # present and not NaN
    # Sensible ranges. NRD refines the S-SCAPE fit by the paper's measure (closer to the scan) and
    # the S-SCAPE initialisation beats the static template by the ground truth; the ground-truth
    # error of S-SCAPE + NRD is NOT below S-SCAPE alone on these scans (NRD slides vertices along
    # the surface; see docs/results_sscape.md), so that is not asserted.
    meth = m["methods"]
    assert meth["sscape_nrd"]["fit_error_mm_mean"] < meth["sscape_only"]["fit_error_mm_mean"]
    assert m["sscape_nrd_gt_error_mm_mean"] < m["nrd_gt_error_mm_mean"]
    assert m["sscape_nrd_gt_error_mm_mean"] < 15.0
    assert 0.0 < m["nrd_frac_below_10mm"] <= 1.0
    assert meth["sscape_nrd"]["fit_error_mm_mean"] < 5.0
    # the anchored refinement lowers the true error of the S-SCAPE fit it starts from, where the
    # paper's schedule raises it, and stays close to the scan (the true meshes' own paper's error
    # is the floor a truthful registration can reach)
    assert m["sscape_nrd_anchored_gt_error_mm_mean"] < m["sscape_only_gt_error_mm_mean"]
    assert m["sscape_nrd_anchored_gt_error_mm_mean"] < m["sscape_nrd_gt_error_mm_mean"]
    assert (
        meth["sscape_nrd_anchored"]["fit_error_mm_mean"] < meth["sscape_only"]["fit_error_mm_mean"]
    )
    assert 2.0 < m["truth_fit_error_mm_mean"] < 10.0
    # A space learned from registrations generalizes (mm) and is specific about as well as one
    # learned from the true meshes of the same scans (keys say 20; the value is at --components)
    assert 0.5 < m["generalization_mm_at_20"] < 1.2 * m["gt_space_generalization_mm_at_20"]
    assert 1.0 < m["specificity_mm_at_20"] < 1.2 * m["gt_space_specificity_mm_at_20"]
    for name in (
        "cumulative_fit_20mm.png",
        "cumulative_gt_50mm.png",
        "mean_error_gt_sscape_nrd.png",
        "mean_error_gt_sscape_nrd_anchored.png",
        "space_quality.png",
        "scan_coverage.png",
    ):
        assert (out / name).stat().st_size > 1000, name
