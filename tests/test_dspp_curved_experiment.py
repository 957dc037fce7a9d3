"""experiments/dspp_curved.py (issue 15 §2: DSPP on the full-age population), quick mode."""

import json

import pytest
from helpers import run_script


@pytest.mark.typecheck_off
def test_dspp_curved_quick(tmp_path):
    run_script("experiments/dspp_curved.py", "--quick", "--no-progress", "--out", tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["mode"] == "quick"
    for f in ("samples_full_age.png", "samples_adult.png", "heights.png"):
        assert (tmp_path / f).stat().st_size > 1000, f
    for pop in ("full_age", "adult"):
        for g in ("pca", "aegan", "ae_gauss", "train"):
            assert 0.0 <= m[f"{pop}_{g}_1nna"] <= 1.0
            assert 0.0 <= m[f"{pop}_{g}_outlier_frac"] <= 1.0
        # PCA reconstruction error falls with K
        r = [m[f"{pop}_recon_pca{k}_mm"] for k in (8, 16, 32, 64)]
        assert all(a >= b for a, b in zip(r, r[1:])), r
    # the full age range spans children to adults (which of them land in the small quick test split
    # is chance, so check all sampled bodies): ages below 12 and above 65 years, heights over
    # > 0.5 m (quick run: 3.2-88.4 years, 1.06-1.94 m; adults 1.40-2.11 m)
    a_lo, a_hi = m["full_age_age_range_years"]
    assert a_lo < 12.0 and a_hi > 65.0, (a_lo, a_hi)
    ad_lo, ad_hi = m["adult_age_range_years"]
    assert 18.0 - 1e-3 <= ad_lo and ad_hi <= 65.0 + 1e-3, (ad_lo, ad_hi)
    lo, hi = m["full_age_height_range_m"]
    assert hi - lo > 0.5 and m["adult_height_range_m"][0] > lo, (lo, hi, m["adult_height_range_m"])
    assert "full_age_recon_aegan_long_mm" in m and "adult_recon_aegan_long_mm" not in m
    # real training bodies are never outliers against the training set itself
    assert m["full_age_train_outlier_frac"] == 0.0
