"""Tests for the headless renderer: images are checked by content, never by hash."""


import jax.numpy as jnp
import matplotlib
import matplotlib.image
import numpy as np
import pytest
import trimesh

from bodyprior import (
    contact_sheet,
    figure_with_colorbar,
    mesh_bounds,
    render_mesh,
    render_vertex_colors,
    save_png,
)

BG = np.array([255, 255, 255], dtype=np.uint8)


def _sphere(radius=1.0, centre=(0.0, 0.0, 0.0), sub=4):
    m = trimesh.creation.icosphere(subdivisions=sub)
    return m.vertices * radius + np.asarray(centre), m.faces


def _mask(img, bg=BG):
    return np.any(img != bg, axis=-1)


def _asym():
    """A unit sphere with a small sphere on its +X side and a tiny one in front (-Y)."""
    v1, f1 = _sphere(1.0, sub=3)
    v2, f2 = _sphere(0.3, (1.2, 0.0, 0.5), sub=2)
    v3, f3 = _sphere(0.2, (0.0, -1.1, -0.3), sub=2)
    v = np.concatenate([v1, v2, v3])
    f = np.concatenate([f1, f2 + len(v1), f3 + len(v1) + len(v2)])
    return v, f


def test_sphere_renders_as_disc_of_analytic_radius():
    v, f = _sphere(2.0)
    h = w = 200
    img = render_mesh(v, f, size=(h, w), antialias=1)
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    m = _mask(img)
    expected = 0.5 * w * (1 - 2 * 0.04)  # the camera fits the sphere's extent with a 4% margin
    assert abs(np.sqrt(m.sum() / np.pi) - expected) < 2.0
    rows, cols = np.nonzero(m)
    assert abs(rows.mean() - h / 2 + 0.5) < 1.0 and abs(cols.mean() - w / 2 + 0.5) < 1.0
    # Background everywhere outside the disc (plus a 2-pixel band).
    yy, xx = np.mgrid[:h, :w] + 0.5
    outside = np.hypot(yy - h / 2, xx - w / 2) > expected + 2
    assert np.all(img[outside] == BG)
    assert not np.any(np.all(img[~outside & m] == BG, axis=-1))


def test_background_and_color_respected():
    v, f = _sphere()
    img = render_mesh(v, f, size=(64, 80), background=(0.0, 0.0, 0.0), color=(1.0, 0.0, 0.0))
    assert img.shape == (64, 80, 3)
    assert np.all(img[0, 0] == 0) and np.all(img[-1, -1] == 0)
    centre = img[32, 40].astype(int)
    assert centre[0] > 100 and centre[1] == 0 and centre[2] == 0


def test_surface_facing_light_is_brighter():
    v, f = _sphere()
    for light, brighter_right in [((1.0, 0.0, 0.0), True), ((-1.0, 0.0, 0.0), False)]:
        img = render_mesh(v, f, size=(100, 100), light_dir=light).astype(float).mean(axis=-1)
        m = _mask(render_mesh(v, f, size=(100, 100), light_dir=light))
        left = img[:, :50][m[:, :50]].mean()
        right = img[:, 50:][m[:, 50:]].mean()
        assert (right > left + 30) == brighter_right and (left > right + 30) != brighter_right
    # A face turned towards the default light (camera side) is brighter than one at grazing angle.
    img = render_mesh(v, f, size=(100, 100)).astype(float).mean(axis=-1)
    assert (
        img[40, 55] > img[50, 5 + np.argmax(_mask(render_mesh(v, f, size=(100, 100)))[50, 5:])] + 20
    )


def test_front_back_mirror_x():
    v, f = _asym()
    size = (120, 160)
    front = _mask(render_mesh(v, f, view="front", size=size, antialias=1))
    back = _mask(render_mesh(v, f, view="back", size=size, antialias=1))
    assert np.mean(front != back[:, ::-1]) < 0.005
    assert np.mean(front != front[:, ::-1]) > 0.02  # the mesh really is asymmetric in X


BOX = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])


def _blob_centre(view, centre, size=(100, 100)):
    """Image (row, col) centroid of a small sphere at world `centre`, with a fixed camera box."""
    v, f = _sphere(0.3, centre, sub=2)
    m = _mask(render_mesh(v, f, view=view, size=size, fit=BOX, antialias=1))
    rows, cols = np.nonzero(m)
    return rows.mean() + 0.5 - size[0] / 2, cols.mean() + 0.5 - size[1] / 2


@pytest.mark.parametrize(
    "view,centre,sign_row,sign_col",
    [
        ("front", (1, 0, 0), 0, +1),  # body's left (+X) on the image's right
        ("front", (0, 0, 1), -1, 0),  # Z up
        ("back", (1, 0, 0), 0, -1),
        ("side", (0, -1, 0), 0, -1),  # camera at +X: the body's front (-Y) is on the left
        ("left", (0, 0, 1), -1, 0),
        ("right", (0, -1, 0), 0, +1),
        ("top", (1, 0, 0), 0, +1),
        ("top", (0, -1, 0), +1, 0),  # top view: the front (-Y) at the bottom
        ((90, 0), (0, -1, 0), 0, -1),
    ],
)  # fmt: skip
def test_view_orientation(view, centre, sign_row, sign_col):
    dr, dc = _blob_centre(view, centre)
    for d, sign in ((dr, sign_row), (dc, sign_col)):
        if sign == 0:
            assert abs(d) < 1.0
        else:
            assert d * sign > 15  # 1 m off-centre = 23 px with the 4 m box in 100 px


def test_degenerate_triangles_do_not_raise():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [2, 0, 0], [0.5, 0, 0.5]], dtype=float)
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 1], [0, 4, 4]])  # one real, three zero-area
    img = render_mesh(v, f, size=(50, 50))
    assert _mask(img).any()
    flat = render_mesh(v, f[1:], size=(50, 50))  # only degenerate triangles: blank image
    assert not _mask(flat).any()
    empty = render_mesh(v, np.zeros((0, 3), dtype=int), size=(10, 10))
    assert np.all(empty == 255)
    one_point = render_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), size=(10, 10))
    assert np.all(one_point == 255)


def test_shared_fit_keeps_relative_scale():
    v1, f = _sphere(1.0)
    v2 = v1 * 0.5
    fit = mesh_bounds(v1, v2)
    np.testing.assert_allclose(fit, [[-1, -1, -1], [1, 1, 1]], atol=1e-6)
    r1 = np.sqrt(_mask(render_mesh(v1, f, size=(100, 100), fit=fit, antialias=1)).sum() / np.pi)
    r2 = np.sqrt(_mask(render_mesh(v2, f, size=(100, 100), fit=fit, antialias=1)).sum() / np.pi)
    assert abs(r1 / r2 - 2.0) < 0.08
    r_own = np.sqrt(_mask(render_mesh(v2, f, size=(100, 100), antialias=1)).sum() / np.pi)
    assert abs(r_own - r1) < 1.5  # without `fit`, each mesh fills the frame


def test_accepts_jax_arrays():
    v, f = _sphere(sub=2)
    a = render_mesh(jnp.asarray(v), jnp.asarray(f), size=(40, 40))
    b = render_mesh(v, f, size=(40, 40))
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1


def test_save_png_roundtrip(tmp_path):
    v, f = _sphere(sub=2)
    img = render_mesh(v, f, size=(48, 36))
    p = tmp_path / "s.png"
    save_png(p, img)
    back = matplotlib.image.imread(p)
    assert back.shape[:2] == (48, 36) and back.shape[2] in (3, 4)
    np.testing.assert_array_equal(np.round(back[..., :3] * 255).astype(np.uint8), img)
    save_png(tmp_path / "f.png", img / 255.0)
    assert matplotlib.image.imread(tmp_path / "f.png").shape[:2] == (48, 36)
    with pytest.raises(ValueError, match="image"):
        save_png(tmp_path / "bad.png", img[..., 0])
    assert not (tmp_path / "bad.png").exists()


def test_contact_sheet_layout_labels_and_scale():
    v, f = _sphere(sub=2)
    stack = np.stack([v, 0.5 * v, 0.25 * v])
    sheet = contact_sheet(
        stack, f, ncols=2, labels=["a", "b", "c"], cell_size=(60, 50), label_height=12
    )
    assert sheet.shape == (2 * (60 + 12), 2 * 50, 3) and sheet.dtype == np.uint8
    label_strip = sheet[60:72, :50]
    assert _mask(label_strip).any()  # text drawn under the first cell
    assert not _mask(sheet[72 + 60 :, 50:]).any()  # the unused fourth cell stays blank
    h1 = _mask(sheet[:60, :50]).any(axis=1).sum()
    h2 = _mask(sheet[:60, 50:]).any(axis=1).sum()
    assert abs(h1 / h2 - 2.0) < 0.2  # same_scale keeps heights comparable
    own = contact_sheet([(v, f), (0.5 * v, f)], same_scale=False, cell_size=(60, 50))
    assert own.shape == (60, 100, 3)
    assert abs(_mask(own[:, :50]).sum() - _mask(own[:, 50:]).sum()) < 10
    with pytest.raises(ValueError, match="labels"):
        contact_sheet(stack, f, labels=["a"])
    with pytest.raises(ValueError, match="faces"):
        contact_sheet(list(stack))


def test_vertex_colors_follow_colormap():
    v, f = _sphere()
    vals = v[:, 2]
    img = render_vertex_colors(
        v, f, vals, vmin=-1, vmax=1, size=(100, 100), shading=0.0, antialias=1
    )
    cm = matplotlib.colormaps["viridis"]
    radius_px = 50 * (1 - 2 * 0.04)
    for row in (6, 30, 50, 70, 93):  # front-most point at column 50 has z = height above centre
        z = (50 - (row + 0.5)) / radius_px
        np.testing.assert_allclose(img[row, 50] / 255, cm((z + 1) / 2)[:3], atol=0.03)
    assert np.all(img[0, 0] == 255)
    flat = render_vertex_colors(v, f, vals, size=(50, 50), per_face=True, cmap="magma")
    assert flat.shape == (50, 50, 3)
    with pytest.raises(ValueError, match="`values`"):
        render_vertex_colors(v, f, vals[:-1])
    with pytest.raises(ValueError, match="vmin"):
        render_vertex_colors(v, f, vals, vmin=1, vmax=0)


def test_figure_with_colorbar(tmp_path):
    v, f = _sphere(sub=2)
    img = render_vertex_colors(v, f, v[:, 2], size=(80, 60))
    fig = figure_with_colorbar(
        img, vmin=-1, vmax=1, label="error [mm]", title="t", path=tmp_path / "c.png"
    )
    assert isinstance(fig, matplotlib.figure.Figure)
    out = matplotlib.image.imread(tmp_path / "c.png")
    assert out.shape[0] >= 80 and out.shape[1] > 60


def test_input_validation():
    v, f = _sphere(sub=1)
    with pytest.raises(ValueError, match="`view`"):
        render_mesh(v, f, view="diagonal")
    with pytest.raises(ValueError, match="`size`"):
        render_mesh(v, f, size=(0, 10))
    with pytest.raises(ValueError, match="`faces` must index"):
        render_mesh(v, f + len(v))
    with pytest.raises(ValueError, match="`vertices` contains NaN"):
        render_mesh(np.full_like(v, np.nan), f)
    with pytest.raises(ValueError, match="`color`"):
        render_mesh(v, f, color=(2, 0, 0))
    with pytest.raises(ValueError, match="`fit`"):
        render_mesh(v, f, fit=np.zeros(3))
    with pytest.raises(ValueError, match="`light_dir`"):
        render_mesh(v, f, light_dir=(0, 0, 0))
    with pytest.raises(ValueError, match="`antialias`"):
        render_mesh(v, f, antialias=0)


def _toy_body():
    """~27k triangles of ellipsoids arranged like a standing body (1.8 m, facing -Y)."""
    spec = [((0, 0, 1.65), (0.09, 0.1, 0.12), 4), ((0, 0, 1.25), (0.18, 0.12, 0.3), 4),
            ((0, 0, 0.9), (0.17, 0.11, 0.12), 4), ((-0.1, 0, 0.5), (0.07, 0.07, 0.42), 4),
            ((0.1, 0, 0.5), (0.07, 0.07, 0.42), 4), ((-0.3, 0, 1.2), (0.05, 0.05, 0.3), 3),
            ((0.3, 0, 1.2), (0.05, 0.05, 0.3), 3)]  # fmt: skip
    vs, fs, off = [], [], 0
    for centre, radii, sub in spec:
        m = trimesh.creation.icosphere(subdivisions=sub)
        vs.append(m.vertices * np.asarray(radii) + np.asarray(centre))
        fs.append(m.faces + off)
        off += len(m.vertices)
    return np.concatenate(vs), np.concatenate(fs)


def test_render_body_sized_mesh():
    # The docstring quotes ~0.1 s (antialias=1) / ~0.3 s (antialias=2) for the 26.8k-face body;
    # timing is not asserted here (it depends on the machine's load).
    v, f = _toy_body()
    assert f.shape[0] > 26_000
    img = render_mesh(v, f)
    assert 0.1 < _mask(img).mean() < 0.5
