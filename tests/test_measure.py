"""Phenotypes from height / weight / age (bodyprior._measure)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import bodyprior as bp


@pytest.fixture(scope="module")
def body():
    return bp.load_default_body("cmu_mb")


def test_measure_matches_trimesh(body):
    p = bp.phenotype_vector(gender=1.0, weight=0.8)
    m = bp.measure(body, p)
    v, _ = bp.rest_shape(body, p)
    mesh = trimesh.Trimesh(np.asarray(v, float), np.asarray(body.faces), process=False)
    assert mesh.is_watertight
    assert float(m.volume_m3) == pytest.approx(mesh.volume, rel=1e-5)
    assert float(m.mass_kg) == pytest.approx(bp.BODY_DENSITY * mesh.volume, rel=1e-5)
    assert float(m.height_m) == pytest.approx(np.ptp(mesh.vertices[:, 2]), abs=1e-6)
    assert float(m.bmi) == pytest.approx(float(m.mass_kg) / float(m.height_m) ** 2)


def test_age_table_round_trip():
    for years in (0.0, 1.0, 10.0, 18.0, 25.0, 64.0, 90.0, 110.0):
        assert bp.age_to_years(bp.years_to_age(years)) == pytest.approx(years, abs=1e-9)
    assert bp.years_to_age(18.0) == pytest.approx(0.77)
    with pytest.raises(ValueError, match="years"):
        bp.years_to_age(-1.0)
    with pytest.raises(ValueError, match="age"):
        bp.age_to_years(-0.2)


@pytest.mark.parametrize(
    "kw",
    [
        dict(height_m=1.80, weight_kg=80.0, age_years=35.0, gender=0.0),
        dict(height_m=1.80, weight_kg=110.0, age_years=50.0, gender=0.0),  # BMI 34
        dict(height_m=1.62, weight_kg=48.0, age_years=22.0, gender=1.0),  # BMI 18.3
        dict(height_m=1.70, weight_kg=62.0, age_years=40.0, gender=1.0, muscle=0.5),
        dict(height_m=1.25, age_years=8.0, gender=0.0),
    ],
)
def test_phenotypes_from_measurements_hit_the_targets(body, kw):
    p = bp.phenotypes_from_measurements(body=body, **kw)
    m = bp.measure(body, p)
    assert float(m.height_m) == pytest.approx(kw["height_m"], abs=1e-4)
    if "weight_kg" in kw:
        assert float(m.mass_kg) == pytest.approx(kw["weight_kg"], abs=1e-2)
    i = bp.PHENOTYPES.index
    assert p[i("age")] == pytest.approx(bp.years_to_age(kw["age_years"]))
    assert p[i("gender")] == kw["gender"]
    if "muscle" in kw or "weight_kg" not in kw:
        assert p[i("muscle")] == kw.get("muscle", 0.5)
    assert np.all((p >= 0.0) & (p <= 1.0))


def test_heavier_means_more_weight_phenotype(body):
    ps = [bp.phenotypes_from_measurements(height_m=1.75, weight_kg=w, body=body)
          for w in (60.0, 75.0, 95.0)]  # fmt: skip
    w = [p[bp.PHENOTYPES.index("weight")] for p in ps]
    assert w[0] < w[1] < w[2]


def test_out_of_reach_and_bad_input(body):
    with pytest.raises(ValueError, match="out of reach.*masses"):
        bp.phenotypes_from_measurements(height_m=1.9, weight_kg=40.0, body=body)
    with pytest.raises(ValueError, match="muscle. fixed"):
        bp.phenotypes_from_measurements(height_m=1.75, weight_kg=75.0, muscle=0.5, body=body)
    with pytest.raises(ValueError, match="height_m"):
        bp.phenotypes_from_measurements(height_m=175.0, body=body)  # centimetres
    with pytest.raises(ValueError, match="weight_kg"):
        bp.phenotypes_from_measurements(height_m=1.75, weight_kg=0.5, body=body)
    with pytest.raises(ValueError, match="age_years"):
        bp.phenotypes_from_measurements(height_m=1.75, age=0.5, body=body)
    with pytest.raises(ValueError, match="solved for"):
        bp.phenotypes_from_measurements(height_m=1.75, height=0.5, body=body)
    with pytest.raises(ValueError, match="unknown phenotype"):
        bp.phenotypes_from_measurements(height_m=1.75, hight=0.5, body=body)
