"""Tests for atomic writes and OBJ/PLY mesh IO."""

import json
import os

import numpy as np
import pytest
import trimesh

from bodyprior import (
    atomic_open,
    atomic_write_bytes,
    atomic_write_json,
    read_mesh,
    write_obj,
    write_ply,
)


def _mesh(nv=50, nf=80, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(nv, 3)), rng.integers(0, nv, size=(nf, 3))


def _leftovers(d):
    return [p for p in os.listdir(d) if p.endswith(".tmp")]


# --------------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------------


def test_atomic_write_bytes_roundtrip_and_overwrite(tmp_path):
    p = tmp_path / "a.bin"
    atomic_write_bytes(p, b"one")
    atomic_write_bytes(p, b"two")
    assert p.read_bytes() == b"two"
    assert _leftovers(tmp_path) == []
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(p).st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_atomic_open_exception_leaves_target_untouched(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("original")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_open(p, "w") as f:
            f.write("partial")
            raise RuntimeError("boom")
    assert p.read_text() == "original"
    assert _leftovers(tmp_path) == []
    q = tmp_path / "new.txt"
    with pytest.raises(RuntimeError):
        with atomic_open(q, "wb") as f:
            f.write(b"x")
            raise RuntimeError
    assert not q.exists()


def test_atomic_open_text_and_bad_mode(tmp_path):
    with atomic_open(tmp_path / "t.txt", "w") as f:
        f.write("héllo\n")
    assert (tmp_path / "t.txt").read_text(encoding="utf-8") == "héllo\n"
    with pytest.raises(ValueError, match="mode"):
        with atomic_open(tmp_path / "x", "a"):
            pass
    with pytest.raises(ValueError, match="does not exist"):
        atomic_write_bytes(tmp_path / "nodir" / "x", b"")


def test_atomic_write_json(tmp_path):
    p = tmp_path / "a.json"
    atomic_write_json(p, {"b": np.float32(1.5), "a": np.arange(3), "c": [1, None]})
    text = p.read_text()
    assert text.index('"a"') < text.index('"b"') and text.endswith("\n")
    assert json.loads(text) == {"a": [0, 1, 2], "b": 1.5, "c": [1, None]}
    assert '\n  "a"' in text  # indent 2


@pytest.mark.parametrize(
    "bad", [float("nan"), float("inf"), np.float64("nan"), np.array([1.0, np.nan])]
)
def test_atomic_write_json_rejects_nan(tmp_path, bad):
    p = tmp_path / "a.json"
    p.write_text("{}")
    with pytest.raises(ValueError, match="NaN or infinite"):
        atomic_write_json(p, {"x": bad})
    assert p.read_text() == "{}"
    assert _leftovers(tmp_path) == []


# --------------------------------------------------------------------------------------------------
# mesh writers / readers
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "fmt,kw,tol",
    [("obj", {}, 1e-8), ("ply", {}, 1e-6), ("ply", {"binary": False}, 1e-6),
     ("ply", {"double": True}, 0.0), ("ply", {"binary": False, "double": True}, 1e-15)],
)  # fmt: skip
def test_mesh_roundtrip(tmp_path, fmt, kw, tol):
    v, f = _mesh()
    p = tmp_path / f"m.{fmt}"
    (write_obj if fmt == "obj" else write_ply)(p, v, f, **kw)
    v2, f2, n2 = read_mesh(p)
    assert v2.dtype == np.float64 and v2.shape == v.shape
    np.testing.assert_allclose(v2, v, atol=tol * 10, rtol=tol)
    np.testing.assert_array_equal(f2, f)
    assert n2 is None


@pytest.mark.parametrize("fmt,kw", [("obj", {}), ("ply", {}), ("ply", {"binary": False})])
def test_normals_and_point_cloud_roundtrip(tmp_path, fmt, kw):
    v, f = _mesh()
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    writer = write_obj if fmt == "obj" else write_ply
    writer(tmp_path / f"n.{fmt}", v, f, normals=n, **kw)
    v2, f2, n2 = read_mesh(tmp_path / f"n.{fmt}")
    np.testing.assert_allclose(n2, n, atol=1e-6)
    np.testing.assert_array_equal(f2, f)
    writer(tmp_path / f"pc.{fmt}", v, **kw)
    v3, f3, n3 = read_mesh(tmp_path / f"pc.{fmt}")
    assert f3 is None and n3 is None
    np.testing.assert_allclose(v3, v, atol=1e-6)


@pytest.mark.parametrize("ext", ["ply", "obj"])
def test_reads_trimesh_exports_in_order(tmp_path, ext):
    m = trimesh.creation.icosphere(2)
    p = tmp_path / f"s.{ext}"
    m.export(p)
    v, f, _ = read_mesh(p)
    np.testing.assert_allclose(v, m.vertices, atol=1e-6)
    np.testing.assert_array_equal(f, m.faces)
    pc = trimesh.PointCloud(m.vertices)
    pc.export(tmp_path / "pc.ply")
    v, f, _ = read_mesh(tmp_path / "pc.ply")
    assert f is None and v.shape == m.vertices.shape


def test_trimesh_reads_our_files(tmp_path):
    v, f = _mesh()
    write_ply(tmp_path / "m.ply", v, f)
    write_obj(tmp_path / "m.obj", v, f)
    for name in ("m.ply", "m.obj"):
        tm = trimesh.load(tmp_path / name, process=False)
        np.testing.assert_allclose(tm.vertices, v, atol=1e-6)
        np.testing.assert_array_equal(tm.faces, f)


def test_obj_polygons_slashes_negative_indices(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text(
        "# quad + tri\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4//1 -3//1 -1//1\n"
    )
    v, f, n = read_mesh(p)
    assert v.shape == (4, 3) and n is None  # one normal for four vertices is not per-vertex
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3], [0, 1, 3]])


def test_binary_ply_quads_big_endian_and_extra_props(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=">f4")
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        b"property float z\nproperty uchar red\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n"
    )
    vrec = np.zeros(4, dtype=[("xyz", ">f4", 3), ("r", "u1")])
    vrec["xyz"] = v
    face = np.array([4], "u1").tobytes() + np.array([0, 1, 2, 3], ">i4").tobytes()
    (tmp_path / "q.ply").write_bytes(header + vrec.tobytes() + face)
    v2, f2, _ = read_mesh(tmp_path / "q.ply")
    np.testing.assert_allclose(v2, v)
    np.testing.assert_array_equal(f2, [[0, 1, 2], [0, 2, 3]])


_BAD_FILES = [
    ("empty.obj", "", r"empty\.obj.*empty"),
    ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", r"nan\.obj.*NaN"),
    ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"range\.obj.*face indices"),
    ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"zero\.obj.*1-based"),
    ("bad.ply", "not a ply", r"bad\.ply.*not a PLY"),
    ("x.stl", "solid", r"x\.stl.*extension"),
    ("nov.obj", "# nothing\n", r"nov\.obj.*no 'v' lines"),
]


@pytest.mark.parametrize(("name", "text", "match"), _BAD_FILES, ids=[b[0] for b in _BAD_FILES])
def test_read_errors_name_the_file(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=match):
        read_mesh(tmp_path / name)


def test_read_errors_missing_and_truncated(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.ply.*does not exist"):
        read_mesh(tmp_path / "missing.ply")
    v, f = _mesh()
    write_ply(tmp_path / "trunc.ply", v, f)
    raw = (tmp_path / "trunc.ply").read_bytes()
    (tmp_path / "trunc.ply").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"trunc\.ply.*truncated"):
        read_mesh(tmp_path / "trunc.ply")


def test_writer_validation(tmp_path):
    v, f = _mesh()
    with pytest.raises(ValueError, match="`vertices` must have shape"):
        write_ply(tmp_path / "a.ply", v[:, :2], f)
    with pytest.raises(ValueError, match="`faces` must index"):
        write_obj(tmp_path / "a.obj", v, f + 100)
    with pytest.raises(ValueError, match="`faces` must have an integer dtype"):
        write_obj(tmp_path / "a.obj", v, f.astype(float))
    with pytest.raises(ValueError, match="NaN"):
        write_ply(tmp_path / "a.ply", np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="`normals` must have shape"):
        write_ply(tmp_path / "a.ply", v, f, normals=v[:3])
    assert not any(tmp_path.iterdir())


def test_write_body_sized(tmp_path):
    # Body-sized meshes through the vectorised writers (speed is a benchmark matter, not a test's:
    # typical ~2 ms PLY, ~15 ms OBJ on the project machine).
    v, f = _mesh(13_000, 27_000)
    write_ply(tmp_path / "b.ply", v, f)
    write_obj(tmp_path / "b.obj", v, f)
    for name in ("b.ply", "b.obj"):
        v2, f2, _ = read_mesh(tmp_path / name)
        np.testing.assert_allclose(v2, v, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(f2, f)
