"""The PanoMan experiment end to end in `--quick` mode (decimated mesh, a few dozen meshes; about
6 minutes on 2 cores, so it is marked slow:
`python -m pytest -m slow tests/test_panoman_experiment.py`).
The model pieces it uses are tested at tiny sizes in test_panoman_model.py."""

import json
from pathlib import Path

import pytest
from helpers import run_script

REPO = Path(__file__).resolve().parents[1]
MOCAP = REPO.parent / "shared" / "data" / "mocap"

KEYS = (
    "fig7_body_vertex_err_mm_at_k", "recon_c1_mean_mm_panoman", "recon_c1_mean_mm_baseline",
    "recon_c1_mean_mm_lbs", "recon_c2_mean_mm_panoman", "recon_c2_mean_mm_lbs",
    "recon_c3_mean_mm_panoman", "recon_c1_mean_mm_dqs", "recon_c1_hausdorff_bbox_panoman",
    "twist180_min_area_ratio_panoman", "twist180_min_area_ratio_lbs", "fit_total_s_mean",
)  # fmt: skip


@pytest.mark.slow
@pytest.mark.skipif(not MOCAP.is_dir(), reason="needs ../shared/data/mocap")
def test_panoman_experiment_quick(tmp_path):
    out = tmp_path / "panoman"
    run_script("experiments/panoman.py", "--quick", "--out", out, "--no-progress",
               "--mocap", MOCAP)  # fmt: skip
    m = json.loads((out / "metrics.json").read_text())
    for k in KEYS:
        assert k in m, k
    # the ground-truth generator keeps the forearm; LBS collapses it
    assert m["twist180_min_area_ratio_ground_truth"] > 0.85
    assert m["twist180_min_area_ratio_lbs"] < 0.3
    for cs in ("c1", "c2", "c3"):
        for name in ("panoman", "baseline", "lbs", "dqs"):
            assert 0.0 < m[f"recon_{cs}_mean_mm_{name}"] < 300.0
            assert 0.0 < m[f"recon_{cs}_hausdorff_bbox_{name}"] < 0.5
    for cs in ("c1", "c2", "c3"):  # bootstrap intervals over frames: mean inside its interval
        for name, (mean, lo, hi) in m[f"recon_{cs}_ci95"].items():
            assert lo <= mean <= hi, (cs, name)
        ci = m[f"recon_{cs}_ci95"]
        assert ci["panoman"][0] == pytest.approx(m[f"recon_{cs}_mean_mm_panoman"])
    # more constraints, less error (C2 ⊃ C1 for every method)
    assert m["recon_c2_mean_mm_lbs"] <= m["recon_c1_mean_mm_lbs"] + 1.0
    assert (out / "panoman_fig7_fig18.png").stat().st_size > 1000
    assert (out / "panoman_model.npz").stat().st_size > 1000
