"""The DSPP experiment end to end, in its smallest mode (`--quick --tiny`: 120 bodies, 3 mocap
clips, a few hundred cycles of small networks; about a minute of CPU)."""

import json
import os
from pathlib import Path

import pytest
from helpers import run_script

REPO = Path(__file__).resolve().parents[1]
MOCAP = REPO.parent / "shared" / "data" / "mocap"

REQUIRED = (
    "shape_1nna_aegan", "shape_1nna_geomgan", "shape_1nna_pca", "shape_cov_aegan",
    "shape_mmd_aegan", "pose_1nna_aegan", "pose_1nna_geomgan", "pose_1nna_pca",
    "pose_joint_limit_violation_aegan",
)  # fmt: skip
METHODS = ("aegan", "geomgan", "pca", "pca3sigma", "pcauniform", "train")


@pytest.mark.skipif(not MOCAP.is_dir(), reason="needs ../shared/data/mocap")
def test_dspp_experiment_tiny(tmp_path):
    out = tmp_path / "dspp"
    env = {**os.environ, "JAX_ENABLE_X64": "0"}
    run_script("experiments/dspp.py", "--quick", "--tiny", "--out", out, "--seed", "1",
               "--no-progress", "--mocap", MOCAP, env=env)  # fmt: skip
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "tiny" and m["seed"] == 1
    for k in REQUIRED:
        assert k in m, k
    for dom in ("shape", "pose"):
        for meth in METHODS:
            assert 0.0 <= m[f"{dom}_1nna_{meth}"] <= 1.0
            assert 0.0 < m[f"{dom}_cov_{meth}"] <= 1.0
            for q in ("mmd", "specificity", "diversity"):
                assert m[f"{dom}_{q}_{meth}"] >= 0.0
    for meth in (*METHODS, "test"):
        assert 0.0 <= m[f"pose_joint_limit_violation_{meth}"] <= 1.0
    # real training poses are inside the training range by definition
    assert m["pose_joint_limit_violation_train"] == 0.0
    # sanity of the units: shapes differ by centimetres (mm), poses by degrees
    assert 5.0 < m["shape_diversity_ref"] < 500.0 and 1.0 < m["pose_diversity_ref"] < 90.0
    # the +-3 sigma PCA corners are further from real bodies than Gaussian PCA samples
    assert m["shape_mmd_pca3sigma"] > m["shape_mmd_pca"]
    # the paper's recipe is trained and measured next to the presets (poses)
    for meth in ("aegan_paper", "geomgan_paper"):
        assert 0.0 <= m[f"pose_1nna_{meth}"] <= 1.0 and m[f"pose_diversity_{meth}"] >= 0.0
    assert m["config"]["aegan_pose"]["disc_input_gain"] == 20.0
    assert m["config"]["aegan_pose_paper"]["disc_input_gain"] == 1.0
    # the collapse monitor ran on the validation split and chose a monitored cycle
    for job in ("aegan_shape", "aegan_pose", "geomgan_pose", "aegan_pose_paper"):
        assert m[f"best_step_{job}"] in m[f"monitor_step_{job}"]
        assert all(0.0 <= v <= 1.0 for v in m[f"monitor_1nna_{job}"])
    assert m["pose_n_val"] > 0 and m["shape_n_val"] > 0
    # the pose rows' 1-NNA over repeated draws: the first is the table's, the mean is theirs
    for meth in (*METHODS, "aegan_paper", "geomgan_paper"):
        draws = m[f"pose_1nna_draws_{meth}"]
        assert len(draws) == 5 and draws[0] == m[f"pose_1nna_{meth}"]
        assert abs(m[f"pose_1nna_mean_{meth}"] - sum(draws) / 5) < 1e-12
        assert m[f"pose_1nna_sd_{meth}"] >= 0.0
    for name in ("loss_aegan_shape", "loss_geomgan_shape", "loss_aegan_pose", "loss_geomgan_pose",
                 "loss_aegan_pose_paper", "shape_samples", "pose_samples"):  # fmt: skip
        png = out / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert (out / "aegan_shape.dspp").exists() and (out / "checkpoints").is_dir()
