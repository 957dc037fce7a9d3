"""Body reconstruction from a front and a back depth image (paper §6, after Helten et al. 2013).

A Kinect-like depth camera (`DepthCamera`: pinhole, 512x424 pixels, Kinect v2 depth intrinsics
fx = fy = 365 px, principal point at the image centre) renders the exact first-hit depth of a mesh
with the shared z-buffer of `bodyprior/_render.py` (perspective: `1 / z` is affine in screen space,
so the per-pixel depth is the exact ray/triangle intersection at the pixel centre), plus axial noise
that grows with the square of the depth, as Kinect depth noise does. `depth_to_scan` back-projects
the valid pixels to a world-frame [`bodyprior.sscape.Scan`][] with normals from the (edge-aware
smoothed) depth-image gradients. The pixel -> (face, barycentric) ground truth is kept in a separate
`DepthTruth` for evaluation only.

Camera frame (OpenCV): x to the image right, y to the image bottom, z along the optical axis.
Pixel `(i, j)` (row, column) covers `[j, j + 1] x [i, i + 1]` in image coordinates `(u, v)`, so
its centre is `(j + 0.5, i + 0.5)` and the principal point `(W / 2, H / 2)` is the image centre.
Depth is `z` (distance along the optical axis, as Kinect reports it), metres; 0 means no return.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int

from .._geometry import vertex_normals
from .._kinematics import Similarity
from .._render import _rasterize_screen
from .._validate import check_array
from ._fit import (
    _MM,
    FitConfig,
    FitResult,
    _bounded,
    _correspondences,
    _lm_solve,
    _prepare,
    _umeyama_masked,
)
from ._grid import nearest_within
from ._model import SScapeModel, evaluate, shape_vertices
from ._scan import Scan, ScanTruth, check_scan
from ._template import RegistrationTemplate

# Kinect v2 depth camera (512 x 424): focal length ~365 px for both axes (the factory calibration
# of the device reads 365-366 px; principal point near the centre).
KINECT_WIDTH = 512
KINECT_HEIGHT = 424
KINECT_FOCAL = 365.0


def _vec3(x, name) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"`{name}` must be a finite (3,) vector, got {x!r}.")
    return a


class DepthCamera(eqx.Module):
    """A pinhole depth camera placed by an eye position and a look-at target (world Z up).

    **Arguments** (constructor):

    - `eye`: camera centre, shape `(3,)`, world frame, metres.
    - `target`: a point on the optical axis, shape `(3,)`; must differ from `eye`.
    - `up`: world direction that appears upwards in the image, shape `(3,)` (default `+Z`); must not
      be parallel to the viewing direction.
    - `width`, `height`: image size in pixels (default 512 x 424, Kinect v2 depth).
    - `fx`, `fy`: focal lengths in pixels (default 365, Kinect v2 depth).
    - `cx`, `cy`: principal point in image coordinates (default the image centre).

    **Fields:** `eye (3,)`; `rotation (3, 3)`, world -> camera (rows: camera x = image right,
    camera y = image down, camera z = viewing direction, in world coordinates); static `width`,
    `height`, `fx`, `fy`, `cx`, `cy`.
    """

    eye: Float[Array, 3]
    rotation: Float[Array, "3 3"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    fx: float = eqx.field(static=True)
    fy: float = eqx.field(static=True)
    cx: float = eqx.field(static=True)
    cy: float = eqx.field(static=True)

    def __init__(
        self,
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        *,
        width: int = KINECT_WIDTH,
        height: int = KINECT_HEIGHT,
        fx: float = KINECT_FOCAL,
        fy: float = KINECT_FOCAL,
        cx: float | None = None,
        cy: float | None = None,
    ):
        eye, target, up = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
        fwd = target - eye
        if np.linalg.norm(fwd) < 1e-9:
            raise ValueError("`target` must differ from `eye`.")
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-6 * max(np.linalg.norm(up), 1e-300):
            raise ValueError("`up` must not be parallel to the viewing direction `target - eye`.")
        right = right / np.linalg.norm(right)
        down = np.cross(fwd, right)
        for name, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 8192:
                raise ValueError(f"`{name}` must be an int in [1, 8192], got {v!r}.")
        for name, v in (("fx", fx), ("fy", fy)):
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"`{name}` must be a positive focal length in pixels, got {v!r}.")
        self.eye = jnp.asarray(eye)
        self.rotation = jnp.asarray(np.stack([right, down, fwd]))
        self.width, self.height = int(width), int(height)
        self.fx, self.fy = float(fx), float(fy)
        self.cx = float(width) / 2 if cx is None else float(cx)
        self.cy = float(height) / 2 if cy is None else float(cy)

    @property
    def size(self) -> tuple[int, int]:
        """`(height, width)` in pixels."""
        return self.height, self.width

    def to_camera(self, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        """World points `(N, 3)` -> camera-frame points `(N, 3)` (z = depth)."""
        return (jnp.asarray(points) - self.eye) @ self.rotation.T

    def to_world(self, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        """Camera-frame points `(N, 3)` -> world points `(N, 3)`."""
        return jnp.asarray(points) @ self.rotation + self.eye

    def project(self, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        """World points `(N, 3)` -> `(u, v, z)`: image coordinates (pixels) and depth (metres)."""
        c = self.to_camera(points)
        z = c[:, 2]
        safe = jnp.where(jnp.abs(z) > 1e-12, z, 1.0)
        return jnp.stack(
            [self.fx * c[:, 0] / safe + self.cx, self.fy * c[:, 1] / safe + self.cy, z], 1
        )

    def backproject(self, u, v, z) -> Float[Array, "N 3"]:
        """Pixel coordinates `u`, `v` and depth `z` (metres), each `(N,)` -> world `(N, 3)`."""
        u, v, z = (jnp.asarray(a) for a in (u, v, z))
        c = jnp.stack([(u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z], -1)
        return self.to_world(c)

    def pixel_points(self, depth: Float[Array, "H W"]) -> Float[Array, "H W 3"]:
        """Back-projects every pixel centre of a depth image to the world, shape `(H, W, 3)`."""
        h, w = self.size
        ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        pts = self.backproject(jj.ravel() + 0.5, ii.ravel() + 0.5, jnp.asarray(depth).ravel())
        return pts.reshape(h, w, 3)


def kinect_pair(
    center=(0.0, 0.0, 0.0), *, distance: float = 2.4, camera_height: float | None = None
) -> tuple[DepthCamera, DepthCamera]:
    """A front and a back Kinect-like camera looking horizontally at a body standing at `center`.

    The body faces -Y (world convention), so the front camera sits at `center - distance * Y` and
    the back camera at `center + distance * Y` (equivalently: the subject turns around in front of
    one camera, as in Helten et al.). `camera_height` is the camera's Z (default `center`'s Z).
    At 2.4 m the 60-degree vertical field of view spans about 2.8 m, enough for raised arms.
    """
    c = _vec3(center, "center")
    if not np.isfinite(distance) or distance <= 0:
        raise ValueError(f"`distance` must be positive, got {distance!r}.")
    z = c[2] if camera_height is None else float(camera_height)
    front = DepthCamera([c[0], c[1] - distance, z], [c[0], c[1], z])
    back = DepthCamera([c[0], c[1] + distance, z], [c[0], c[1], z])
    return front, back


class DepthTruth(eqx.Module):
    """Ground truth of a rendered depth image (evaluation only; never passed to a fitter).

    **Fields:** `face (H, W)` int32 index of the mesh triangle seen at each pixel (-1 = none);
    `bary (H, W, 3)` barycentric coordinates of the hit point in that triangle (3-D, perspective
    correct); `true_depth (H, W)` noise-free depth in metres (0 = no return, including pixels
    dropped by the range and incidence limits).
    """

    face: Int[Array, "H W"]
    bary: Float[Array, "H W 3"]
    true_depth: Float[Array, "H W"]


def render_depth(
    vertices,
    faces,
    camera: DepthCamera,
    *,
    key=None,
    noise_sigma: float = 0.0015,
    near: float = 0.5,
    far: float = 4.5,
    max_incidence_deg: float | None = 80.0,
) -> tuple[np.ndarray, DepthTruth]:
    """Renders a Kinect-like depth image of one triangle mesh (host-side NumPy z-buffer).

    The noise-free depth at each pixel is the exact depth of the first triangle hit by the ray
    through the pixel centre. Noise is axial and Gaussian with standard deviation
    `sigma(z) = noise_sigma * z**2` (metres, z in metres): the quadratic growth of structured-light
    depth noise measured by Khoshelham & Elberink (2012) for the Kinect that Helten et al. used
    (about 1.4-1.6 mm at 1 m; 8.6 mm at 2.4 m with the default). Pixels whose surface is seen at
    more than `max_incidence_deg` from its normal return nothing (as a Kinect loses grazing
    surfaces), as do depths outside `[near, far]` (Kinect v2 range 0.5-4.5 m).

    **Arguments:**

    - `vertices`: `(V, 3)` mesh vertices, world frame, metres. `faces`: `(F, 3)` triangles.
      Triangles with a vertex closer than `near` (or behind the camera) are skipped.
    - `camera`: a [`bodyprior.sscape.DepthCamera`][].
    - `key`: `jax.random` key for the noise; `None` = no noise.
    - `noise_sigma`: noise coefficient in metres at 1 m depth (>= 0).
    - `near`, `far`: valid depth range, metres.
    - `max_incidence_deg`: in `(0, 90]` or `None` (keep every hit).

    **Returns:** `(depth, truth)`: `depth` float64 `(H, W)` metres (0 = no return) and a
    [`bodyprior.sscape.DepthTruth`][].
    """
    from .._render import _check_mesh

    if not isinstance(camera, DepthCamera):
        raise ValueError(f"`camera` must be a DepthCamera, got {type(camera).__name__}.")
    vertices, faces = _check_mesh(vertices, faces)
    if not (np.isfinite(noise_sigma) and noise_sigma >= 0):
        raise ValueError(
            f"`noise_sigma` must be a non-negative float (metres), got {noise_sigma!r}."
        )
    if not (0 < near < far):
        raise ValueError(f"`near` and `far` must satisfy 0 < near < far, got {near!r}, {far!r}.")
    if max_incidence_deg is not None and not 0 < max_incidence_deg <= 90:
        raise ValueError(
            f"`max_incidence_deg` must be in (0, 90] or None, got {max_incidence_deg!r}."
        )
    h, w = camera.size
    R, eye = np.asarray(camera.rotation), np.asarray(camera.eye)
    cam = (vertices - eye) @ R.T
    z = cam[:, 2]
    keep = np.all(z[faces] > near, axis=1)
    sub = faces[keep]
    safe = np.where(z > 1e-9, z, 1.0)
    sx = camera.fx * cam[:, 0] / safe + camera.cx
    sy = camera.fy * cam[:, 1] / safe + camera.cy
    tri, lam = _rasterize_screen(sx, sy, 1.0 / safe, sub, (h, w))
    hit = tri >= 0
    face = np.full((h, w), -1, np.int64)
    face[hit] = np.nonzero(keep)[0][tri[hit]]
    # Screen-space barycentrics -> 3-D ones (perspective-correct): b_k ∝ l_k / z_k.
    zk = z[faces[face[hit]]]
    q = lam[hit] / zk
    inv_depth = q.sum(1)
    bary = np.zeros((h, w, 3))
    bary[hit] = q / inv_depth[:, None]
    true_depth = np.zeros((h, w))
    true_depth[hit] = 1.0 / inv_depth
    valid = hit & (true_depth >= near) & (true_depth <= far)
    if max_incidence_deg is not None:
        tri_w = vertices[faces[face[hit]]]
        n = np.cross(tri_w[:, 1] - tri_w[:, 0], tri_w[:, 2] - tri_w[:, 0])
        p = np.einsum("pk,pkc->pc", bary[hit], tri_w)
        ray = p - eye
        cosang = np.abs(np.sum(n * ray, 1)) / np.maximum(
            np.linalg.norm(n, axis=1) * np.linalg.norm(ray, axis=1), 1e-30
        )
        ok = np.zeros((h, w), bool)
        ok[hit] = cosang >= np.cos(np.deg2rad(max_incidence_deg)) - 1e-12
        valid &= ok
    face[~valid] = -1
    bary[~valid] = 0.0
    true_depth[~valid] = 0.0
    depth = true_depth.copy()
    if key is not None and noise_sigma > 0:
        eps = np.asarray(jr.normal(key, (h, w), dtype=jnp.float32), np.float64)
        depth[valid] += noise_sigma * true_depth[valid] ** 2 * eps[valid]
    truth = DepthTruth(
        face=jnp.asarray(face, jnp.int32),
        bary=jnp.asarray(bary),
        true_depth=jnp.asarray(true_depth),
    )
    return depth, truth


def _check_depth(depth, camera: DepthCamera, name: str = "depth") -> np.ndarray:
    if not isinstance(camera, DepthCamera):
        raise ValueError(f"`camera` must be a DepthCamera, got {type(camera).__name__}.")
    d = np.asarray(check_array(depth, name, (camera.height, camera.width)), np.float64)
    if np.any(d < 0):
        raise ValueError(f"`{name}` must be >= 0 (metres; 0 = no return), got min {d.min()}.")
    if d.max(initial=0.0) > 100.0:
        raise ValueError(
            f"`{name}` looks like millimetres (max {d.max():.1f}); depth images are in metres."
        )
    return d


def _shift(a: np.ndarray, di: int, dj: int, fill) -> np.ndarray:
    """`out[i, j] = a[i + di, j + dj]` with `fill` outside the image."""
    h, w = a.shape[:2]
    out = np.full_like(a, fill)
    i0, i1 = max(0, -di), min(h, h - di)
    j0, j1 = max(0, -dj), min(w, w - dj)
    if i1 > i0 and j1 > j0:
        out[i0:i1, j0:j1] = a[i0 + di : i1 + di, j0 + dj : j1 + dj]
    return out


def depth_normals(
    depth, camera: DepthCamera, *, radius: int = 2, max_jump: float = 0.03
) -> np.ndarray:
    """Unit normals of a depth image, facing the camera, shape `(H, W, 3)`, world frame.

    Each pixel's normal is that of the least-squares plane through the back-projected points of its
    `(2 radius + 1)^2` window (smallest principal axis of their covariance), using only the valid
    neighbours whose depth is within `max_jump` metres of the centre pixel's, so arms in front of
    the torso are not blended with it. This is the depth-gradient normal, smoothed: for a plane it
    is exact at every pixel, including the image border and silhouettes (a plain central-difference
    gradient of the noisy depth has errors of tens of degrees at Kinect noise levels). Pixels
    without a return, or with fewer than 3 neighbours, get a zero normal.
    """
    d = _check_depth(depth, camera)
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 1:
        raise ValueError(f"`radius` must be a positive int, got {radius!r}.")
    valid = d > 0
    p = np.asarray(camera.pixel_points(d))
    centre = p[valid].mean(0) if valid.any() else np.zeros(3)
    q = np.where(valid[..., None], p - centre, 0.0)  # centred: no cancellation in the covariance
    n = np.zeros(d.shape)
    s1 = np.zeros(d.shape + (3,))
    s2 = np.zeros(d.shape + (3, 3))
    for di in range(-radius, radius + 1):
        for dj in range(-radius, radius + 1):
            ds = _shift(d, di, dj, 0.0)
            ok = valid & (ds > 0) & (np.abs(ds - d) <= max_jump)
            qs = np.where(ok[..., None], _shift(q, di, dj, 0.0), 0.0)
            n += ok
            s1 += qs
            s2 += qs[..., :, None] * qs[..., None, :]
    good = valid & (n >= 3)
    m = s1[good] / n[good][:, None]
    cov = s2[good] / n[good][:, None, None] - m[:, :, None] * m[:, None, :]
    _, vecs = np.linalg.eigh(cov)
    nrm = vecs[:, :, 0]
    to_cam = np.asarray(camera.eye) - p[good]
    nrm = np.where((np.sum(nrm * to_cam, -1) < 0)[:, None], -nrm, nrm)
    out = np.zeros(d.shape + (3,))
    out[good] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    return out


def _select_pixels(valid: np.ndarray, n_points: int | None, seed: int) -> np.ndarray:
    idx = np.flatnonzero(valid)
    if n_points is not None and idx.size > n_points:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(idx, n_points, replace=False))
    return idx


def depth_to_scan(
    depth,
    camera: DepthCamera,
    *,
    n_points: int | None = None,
    seed: int = 0,
    landmarks=None,
    landmark_mask=None,
    landmark_names: tuple[str, ...] = (),
    normal_radius: int = 2,
    max_jump: float = 0.03,
):
    """Back-projects the valid pixels of a depth image to a world-frame [`bodyprior.sscape.Scan`][].

    **Arguments:**

    - `depth`: `(H, W)` depth image in metres (0 = no return), e.g. from
      [`bodyprior.sscape.render_depth`][]; foreground only (segment the background away first).
    - `camera`: the [`bodyprior.sscape.DepthCamera`][] that took it.
    - `n_points`: fixed point count `P` of the scan: more valid pixels are sub-sampled at random
      (`seed`), fewer are padded (`point_mask` False). `None` = exactly the valid pixels.
    - `landmarks`, `landmark_mask`, `landmark_names`: optional landmarks `(L, 3)` (world, metres),
      presence mask `(L,)` and names; default none (`L = 0`).
    - `normal_radius`, `max_jump`: smoothing of the normal estimate, see
      [`bodyprior.sscape.depth_normals`][].

    **Returns:** a `Scan` whose points are in raster order of the selected pixels; normals face the
    camera. Use [`bodyprior.sscape.depth_scan_truth`][] with the same `n_points`/`seed` for the
    matching ground truth.
    """
    d = _check_depth(depth, camera)
    if n_points is not None and (
        isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or n_points < 1
    ):
        raise ValueError(f"`n_points` must be a positive int or None, got {n_points!r}.")
    valid = d > 0
    if not valid.any():
        raise ValueError("`depth` has no valid pixel (all zero): nothing to back-project.")
    idx = _select_pixels(valid, n_points, seed)
    normals = depth_normals(d, camera, radius=normal_radius, max_jump=max_jump).reshape(-1, 3)
    h, w = camera.size
    ii, jj = np.divmod(idx, w)
    pts = np.asarray(camera.backproject(jj + 0.5, ii + 0.5, d.reshape(-1)[idx]))
    nrm = normals[idx]
    # Pixels whose normal could not be estimated (isolated returns) fall back to the view ray.
    bad = np.linalg.norm(nrm, axis=1) < 0.5
    if bad.any():
        ray = np.asarray(camera.eye) - pts[bad]
        nrm[bad] = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    # Padding rows repeat real points cyclically with point_mask False (as `pad_scans` does).
    p = idx.size if n_points is None else int(n_points)
    order = np.arange(p) % idx.size
    points, nrms = pts[order], nrm[order]
    mask = np.arange(p) < idx.size
    names = tuple(str(s) for s in landmark_names)
    if landmarks is None:
        if names:
            raise ValueError("`landmark_names` given without `landmarks`.")
        lms = np.zeros((0, 3))
        lmask = np.zeros((0,), bool)
    else:
        lms = np.asarray(check_array(landmarks, "landmarks", ("L", 3), finite=False), np.float64)
        lmask = (
            np.isfinite(lms).all(1)
            if landmark_mask is None
            else np.asarray(check_array(landmark_mask, "landmark_mask", (lms.shape[0],)), bool)
        )
        if len(names) != lms.shape[0]:
            raise ValueError(
                f"`landmark_names` must name each of the {lms.shape[0]} landmarks, "
                f"got {len(names)}."
            )
        lms = np.where(lmask[:, None], np.nan_to_num(lms), 0.0)
    dt = jnp.result_type(float)
    return Scan(
        points=jnp.asarray(points, dt),
        normals=jnp.asarray(nrms, dt),
        point_mask=jnp.asarray(mask),
        landmarks=jnp.asarray(lms, dt),
        landmark_mask=jnp.asarray(lmask),
        landmark_names=names,
    )


def depth_scan_truth(truth: DepthTruth, depth, camera: DepthCamera, *, n_points=None, seed=0):
    """The `ScanTruth` matching [`bodyprior.sscape.depth_to_scan`][] called with the same
    `depth`, `camera`, `n_points` and `seed` (evaluation only).

    `face`/`bary` locate each scan point on the rendered mesh, `true_points` is the noise-free hit
    point (world), `is_outlier` is False for every pixel (depth noise only). Padding rows have
    `face` -1 and repeat real `true_points`, as [`bodyprior.sscape.pad_scans`][] pads.
    """
    d = _check_depth(depth, camera)
    idx = _select_pixels(d > 0, n_points, seed)
    h, w = camera.size
    ii, jj = np.divmod(idx, w)
    td = np.asarray(truth.true_depth).reshape(-1)[idx]
    tp = np.asarray(camera.backproject(jj + 0.5, ii + 0.5, td))
    p = idx.size if n_points is None else int(n_points)
    face = np.full(p, -1, np.int32)
    bary = np.zeros((p, 3))
    face[: idx.size] = np.asarray(truth.face).reshape(-1)[idx]
    bary[: idx.size] = np.asarray(truth.bary).reshape(-1, 3)[idx]
    true_points = tp[np.arange(p) % idx.size]
    return ScanTruth(
        face=jnp.asarray(face),
        bary=jnp.asarray(bary),
        is_outlier=jnp.zeros(p, bool),
        true_points=jnp.asarray(true_points),
    )


# --------------------------------------------------------------------------------------------------
# Simulated capture: posed subjects, manual landmarks, front/back scans
# --------------------------------------------------------------------------------------------------

#: The 14 landmarks placed on each depth image (the paper placed 14 landmarks by hand on every depth
#: scan of Helten et al.'s data; which ones is not stated; these are joints a person can click on a
#: depth image from the front and from the back).
DEPTH_LANDMARKS = (
    "Vertex", "Rt. Acromion", "Lt. Acromion", "Rt. Radiale", "Lt. Radiale", "Rt. Radial Styloid",
    "Lt. Radial Styloid", "Rt. Trochanterion", "Lt. Trochanterion", "Rt. Femoral Lateral Epicn",
    "Lt. Femoral Lateral Epicn", "Rt. Lateral Malleolus", "Lt. Lateral Malleolus", "Crotch",
)  # fmt: skip


def depth_landmarks(
    key,
    landmark_positions,
    landmark_names,
    *,
    subset: tuple[str, ...] = DEPTH_LANDMARKS,
    sigma: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulated manual landmarks of one depth image: the `subset` of the true landmark positions
    plus isotropic N(0, `sigma`^2) placement noise per coordinate; the others are missing.

    **Arguments:** `key` (`jax.random` key); `landmark_positions` `(L, 3)` true positions on the
    posed body; `landmark_names` (`L` names); `subset` (names to place); `sigma` metres.

    **Returns:** `(landmarks (L, 3), landmark_mask (L,))` (0 where missing), for
    [`bodyprior.sscape.depth_to_scan`][].
    """
    names = tuple(str(s) for s in landmark_names)
    lm = np.asarray(check_array(landmark_positions, "landmark_positions", (len(names), 3)))
    missing = [s for s in subset if s not in names]
    if missing:
        raise ValueError(f"`subset` names unknown landmarks: {missing}.")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"`sigma` must be a non-negative float (metres), got {sigma!r}.")
    mask = np.array([s in subset for s in names])
    noise = np.asarray(jr.normal(key, lm.shape, dtype=jnp.float32), np.float64) * sigma
    return np.where(mask[:, None], lm + noise, 0.0), mask


def capture_poses(key, joint_names, rest_joints, n: int, *, jitter_deg: float = 4.0) -> np.ndarray:
    """Random non-trivial standing poses for depth capture, axis-angle `(n, J, 3)` (world axes).

    Each pose spreads both arms sideways and up from the A-pose by U(15, 60) degrees
    (independently per arm), bends the elbows forward by U(0, 40) degrees, spreads the legs by
    U(0, 8) degrees, turns the body about the vertical by U(-10, 10) degrees, and adds
    N(0, `jitter_deg`) jitter on the spine, neck, head, shoulders, arms and legs (the
    population's posture jitter scale).

    **Arguments:** `key`; `joint_names` (`J` names, the `cmu_mb` rig); `rest_joints` `(J, 3)` rest
    joint positions (arm directions are taken from them); `n`.
    """
    names = list(joint_names)
    need = ["Hips", "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm",
            "RightHand", "LeftUpLeg", "RightUpLeg"]  # fmt: skip
    if any(s not in names for s in need):
        raise ValueError(f"`joint_names` must contain {need} (the cmu_mb rig).")
    rj = np.asarray(check_array(rest_joints, "rest_joints", (len(names), 3)), np.float64)
    ks = jr.split(key, 8)

    def u(k, lo, hi, shape=(n,)):
        return np.asarray(jr.uniform(k, shape, minval=lo, maxval=hi), np.float64)

    J = len(names)
    pose = np.zeros((n, J, 3))
    jit_names = ("LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head", "LeftShoulder",
                 "RightShoulder", "LeftArm", "RightArm", "LeftForeArm", "RightForeArm",
                 "LeftUpLeg", "RightUpLeg", "LeftLeg", "RightLeg")  # fmt: skip
    jit = np.asarray(jr.normal(ks[0], (n, J, 3)), np.float64) * np.deg2rad(jitter_deg)
    for j, name in enumerate(names):
        if name in jit_names:
            pose[:, j] += jit[:, j]
    raise_l, raise_r = np.deg2rad(u(ks[1], 15, 60)), np.deg2rad(u(ks[2], 15, 60))
    elbow = np.deg2rad(u(ks[3], 0, 40, (n, 2)))
    legs = np.deg2rad(u(ks[4], 0, 8, (n, 2)))
    turn = np.deg2rad(u(ks[5], -10, 10))
    ix = names.index
    # Sideways raise: about world +Y (the body faces -Y; the left arm is at +X).
    pose[:, ix("LeftArm"), 1] += -raise_l
    pose[:, ix("RightArm"), 1] += raise_r
    for side, col in (("Left", 0), ("Right", 1)):
        a = rj[ix(f"{side}Hand")] - rj[ix(f"{side}ForeArm")]
        axis = np.cross(a, [0.0, -1.0, 0.0])  # rotating the forearm towards -Y (forwards)
        axis /= np.linalg.norm(axis)
        pose[:, ix(f"{side}ForeArm")] += elbow[:, col, None] * axis
    pose[:, ix("LeftUpLeg"), 1] += -legs[:, 0]
    pose[:, ix("RightUpLeg"), 1] += legs[:, 1]
    pose[:, ix("Hips"), 2] += turn
    return pose


def simulate_depth_scan(
    key,
    vertices,
    faces,
    camera: DepthCamera,
    landmark_positions,
    landmark_names,
    *,
    n_points: int | None = 8192,
    noise_sigma: float = 0.0015,
    landmark_sigma: float = 0.01,
    landmark_subset: tuple[str, ...] = DEPTH_LANDMARKS,
    max_incidence_deg: float | None = 80.0,
):
    """One simulated depth capture: render, back-project, place the manual landmarks.

    **Arguments:** `key`; the posed true body `vertices (V, 3)` / `faces (F, 3)` (full resolution);
    `camera`; true `landmark_positions (L, 3)` and `landmark_names`; `n_points` (fixed scan size,
    see [`bodyprior.sscape.depth_to_scan`][]); `noise_sigma`, `max_incidence_deg` (see
    [`bodyprior.sscape.render_depth`][]); `landmark_sigma`, `landmark_subset` (see
    [`bodyprior.sscape.depth_landmarks`][]).

    **Returns:** `(scan, truth, depth)`: the `Scan`, its `ScanTruth` (evaluation only) and the
    noisy depth image `(H, W)`.
    """
    k_noise, k_lm, k_sub = jr.split(key, 3)
    depth, dtruth = render_depth(
        vertices, faces, camera, key=k_noise, noise_sigma=noise_sigma,
        max_incidence_deg=max_incidence_deg,
    )  # fmt: skip
    lms, lmask = depth_landmarks(
        k_lm, landmark_positions, landmark_names, subset=landmark_subset, sigma=landmark_sigma
    )
    seed = int(jr.randint(k_sub, (), 0, 2**31 - 1))
    scan = depth_to_scan(
        depth, camera, n_points=n_points, seed=seed, landmarks=lms, landmark_mask=lmask,
        landmark_names=tuple(landmark_names),
    )  # fmt: skip
    truth = depth_scan_truth(dtruth, depth, camera, n_points=n_points, seed=seed)
    return scan, truth, depth


# --------------------------------------------------------------------------------------------------
# Fitting one shape and two poses to a front and a back depth scan (Helten et al.; sscape.md §4, §8)
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DepthFitConfig:
    """Settings of [`bodyprior.sscape.fit_depth`][] (hashable; static under jit).

    **Fields:**

    - `fit`: a [`bodyprior.sscape.FitConfig`][] giving the gates (`max_dist`, `max_angle_deg`), the
      shape bound (`coeff_bound`), the priors (`pose_prior`, `shape_prior`, `landmark_weight`), the
      frozen joints, `fit_scale`, the solver tolerances, `landmark_steps` (stage 1) and
      `chunk_size`, with the meanings they have in [`bodyprior.sscape.fit_sscape`][]; its pass
      settings are not used.
    - `max_rounds`: maximum rounds of the joint stage (default 8); each round is a pose solve per
      image, new correspondences, one shared shape (+ scale) solve, new correspondences.
    - `rtol`, `atol_mm`: stop when the joint data term changes by at most `rtol` (relative) or its
      mean distance by at most `atol_mm` in one round.
    - `scan_weight`: weight of the scan -> model term relative to the model -> scan term (1.0);
      0 gives the model -> scan term alone (the per-scan S-SCAPE objective).
    - `pose_steps`, `shape_steps`: Levenberg-Marquardt step limits per solve of the joint stage.
    - `joint`: solve the shared shape, both poses and the scale together in one Levenberg-Marquardt
      solve per round (`pose_steps + shape_steps` steps; default) instead of humanshape's
      alternation of per-image pose solves and a shared shape solve (`False`), which converges
      much more slowly: pose and shape are strongly coupled through the limb lengths.
    - `point_to_plane`: the model -> scan residual is the distance to the depth point's tangent
      plane (default) instead of to the point: a sub-sampled depth image has ~1-2 cm between
      points, so point-to-point distances stay ~1 cm at the true surface and bias the fit.
    """

    fit: FitConfig = FitConfig()
    max_rounds: int = 8
    rtol: float = 1e-3
    atol_mm: float = 1e-3
    scan_weight: float = 1.0
    pose_steps: int = 10
    shape_steps: int = 10
    joint: bool = True
    point_to_plane: bool = True

    def __post_init__(self):
        if not isinstance(self.fit, FitConfig):
            raise ValueError(
                f"`DepthFitConfig.fit` must be a FitConfig, got {type(self.fit).__name__}."
            )
        for name in ("max_rounds", "pose_steps", "shape_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"`DepthFitConfig.{name}` must be a positive int, got {v!r}.")
        for name in ("rtol", "atol_mm"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"`DepthFitConfig.{name}` must be a positive number, got {v!r}.")
        if not (np.isfinite(self.scan_weight) and self.scan_weight >= 0):
            raise ValueError(
                "`DepthFitConfig.scan_weight` must be a non-negative number, got "
                f"{self.scan_weight!r}."
            )


class DepthFit(eqx.Module):
    """Result of [`bodyprior.sscape.fit_depth`][]: one shape, a pose per image (0 front, 1 back).

    **Fields** (V vertices, J joints, K components, N = `max_rounds + 1`):

    - `coeffs`: the shared shape coefficients, shape `(K,)`, standard deviations.
    - `poses`: per-image local joint rotations, axis-angle, shape `(2, J, 3)`.
    - `similarities`: per-image [`bodyprior.Similarity`][] model -> world (leaves with a leading
      axis 2; both have the same, shared, scale).
    - `vertices`: fitted posed meshes in the world frame of each image, shape `(2, V, 3)`, metres.
    - `rest_vertices`: the shaped, unposed mesh in the model frame (unscaled), shape `(V, 3)`;
      multiply by `scale` for the subject's size.
    - `scale`: the shared global scale, shape `()`.
    - `init_vertices`: the meshes after stage 1 (mean shape, landmark poses), shape `(2, V, 3)`.
    - `result`: a [`bodyprior.sscape.FitResult`][] (`max_passes_reached` = the joint stage used all
      `max_rounds`; not an error).
    - `stats`: dict: `data_term` `(N,)` (mm^2: sum over both images of the model -> scan truncated
      quadratic plus `scan_weight` times the scan -> model one; after the start and after each
      round, NaN after the last), `mean_distance_mm` `(N,)` (mean valid distance, both directions
      and images), `rounds`, `converged`, `model_to_scan_mm` `(2,)`, `scan_to_model_mm` `(2,)`
      (final mean valid distances per image), `valid_fraction` `(2,)` (scan points with a valid
      model partner), `landmark_rms_mm` `(2,)`, `solver_steps`.
    """

    coeffs: Float[Array, " K"]
    poses: Float[Array, "2 J 3"]
    similarities: Similarity
    vertices: Float[Array, "2 V 3"]
    rest_vertices: Float[Array, "V 3"]
    scale: Float[Array, ""]
    init_vertices: Float[Array, "2 V 3"]
    result: FitResult
    stats: dict


def _fit_depth_kernel(model: SScapeModel, scans: Scan, st, pose0, cfg: DepthFitConfig):
    fc = cfg.fit
    dtype = model.mean.dtype
    faces = model.faces
    free = np.asarray(st.free, np.int32)
    nonroot_sel = np.searchsorted(free, free[free != 0])
    b = fc.coeff_bound
    cos_min = float(np.cos(np.deg2rad(fc.max_angle_deg)))
    V, K = model.n_vertices, model.n_components

    points = jnp.asarray(scans.points, dtype)
    mask = jnp.asarray(scans.point_mask, bool)
    points = jnp.where(mask[..., None], points, 0.0)
    snormals = jnp.where(mask[..., None], jnp.asarray(scans.normals, dtype), 0.0)
    n_pts = jnp.maximum(jnp.sum(mask, -1), 1).astype(dtype)  # (2,)
    present = jnp.asarray(scans.landmark_mask, bool) & st.lm_known[None]
    lm_target = jnp.where(present[..., None], jnp.asarray(scans.landmarks, dtype), 0.0)
    lm_w = present.astype(dtype)
    n_lm = jnp.maximum(jnp.sum(present, -1), 1).astype(dtype)
    n_elig = jnp.maximum(jnp.sum(~st.exclude), 1).astype(dtype)
    dmax2 = (fc.max_dist * _MM) ** 2
    sw = float(cfg.scan_weight)

    solve = _lm_solve(fc.solver_rtol, fc.solver_atol)

    def mesh(coeffs, pose, t, ls, Rk):
        return evaluate(model, coeffs, pose, Similarity(Rk, t, ls))[0]

    def lm_res(x, tgt, w, n, weight):
        return (_MM * jnp.sqrt(weight / n) * w[:, None]) * (x[st.lm_vertex] - tgt)

    def pose_prior(pose_free):
        if fc.pose_prior > 0 and nonroot_sel.size:
            return (np.sqrt(fc.pose_prior) * pose_free[nonroot_sel],)
        return ()

    # Stage 1, per image (vmapped): similarity from the landmarks (Umeyama on the model mean's
    # landmark vertices, as fit_sscape), then pose + translation + scale from the landmarks with the
    # shape at the mean (humanshape fitPose).
    zero_c = jnp.zeros((K,), dtype)

    def lm_fn(y, args):
        base, Rk, tgt, w, n = args
        pose = base.at[free].set(y["pose"])
        x = mesh(zero_c, pose, y["t"], y["ls"], Rk)
        return (lm_res(x, tgt, w, n, 1.0), *pose_prior(y["pose"]))

    def init_view(base, tgt, w, n):
        sim = _umeyama_masked(model.mean[st.lm_vertex], tgt, w > 0)
        y0 = {"pose": base[free], "t": sim.translation, "ls": sim.log_scale}
        y, bad, k = solve(lm_fn, y0, (base, sim.rotation, tgt, w, n), fc.landmark_steps)
        return base.at[free].set(y["pose"]), y["t"], y["ls"], sim.rotation, bad, k

    poses0, ts0, ls_k, R, bad0, steps0 = jax.vmap(init_view)(pose0, lm_target, lm_w, n_lm)
    ls0 = jnp.mean(ls_k)  # one subject, one scale (sscape.md §4 step 3b)

    # Correspondences of one image: model -> scan (H-fit's compatible search, hands excluded) and
    # scan -> model (each real depth point to the nearest compatible, i.e. camera-facing, model
    # vertex; pairs landing on a hand vertex are dropped so that hand points do not pull the wrist).
    def correspond(x, pts, nrm, msk):
        vn = vertex_normals(x, faces)
        idx_m, w_m, d_m = _correspondences(x, vn, pts, nrm, msk, st.exclude, fc)
        # the nearest compatible vertex within the gate (grid radius search over the vertices)
        found = nearest_within(
            pts, x, jnp.ones((V,), bool), fc.max_dist,
            query_normals=nrm, point_normals=vn, cos_max=cos_min,
        )  # fmt: skip
        idx_s = jnp.maximum(found, 0)
        d_s = jax.lax.stop_gradient(jnp.linalg.norm(pts - x[idx_s], axis=-1))
        w_s = ((found >= 0) & msk & ~st.exclude[idx_s]).astype(dtype)
        corr = (idx_m, w_m, idx_s, w_s, jax.lax.stop_gradient(vn[idx_s]))
        elig = (~st.exclude).astype(dtype)
        term_m = jnp.sum(elig * jnp.where(w_m > 0, (d_m * _MM) ** 2, dmax2)) / n_elig
        mf = msk.astype(dtype)
        n_real = jnp.maximum(jnp.sum(mf), 1.0)
        term_s = jnp.sum(mf * jnp.where(w_s > 0, (d_s * _MM) ** 2, dmax2)) / n_real
        info = dict(
            term=term_m + sw * term_s,
            mean_m=jnp.sum(w_m * d_m) / jnp.maximum(jnp.sum(w_m), 1.0) * _MM,
            mean_s=jnp.sum(w_s * d_s) / jnp.maximum(jnp.sum(w_s), 1.0) * _MM,
            n_m=jnp.sum(w_m),
            n_s=jnp.sum(w_s),
            frac_s=jnp.sum(w_s) / n_real,
        )
        return corr, info

    correspond_all = jax.vmap(correspond)

    def data_res(x, corr, pts, npts, nrm):
        idx_m, w_m, idx_s, w_s, n_s = corr
        if cfg.point_to_plane:
            d = jnp.sum(nrm[idx_m] * (x - pts[idx_m]), -1)
            res = [_MM * jnp.sqrt(w_m / n_elig) * d]
        else:
            res = [(_MM * jnp.sqrt(w_m / n_elig))[:, None] * (x - pts[idx_m])]
        if sw > 0:
            plane = jnp.sum(n_s * (pts - x[idx_s]), -1)
            res.append(_MM * jnp.sqrt(sw * w_s / npts) * plane)
        return res

    # Stage 2a: per-image pose (+ translation) with the shared shape and scale fixed (vmapped).
    def pose_fn(y, args):
        coeffs, base, ls, Rk, corr, pts, nrm, npts, tgt, w, n = args
        pose = base.at[free].set(y["pose"])
        x = mesh(coeffs, pose, y["t"], ls, Rk)
        res = data_res(x, corr, pts, npts, nrm)
        if fc.landmark_weight > 0:
            res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
        return (*res, *pose_prior(y["pose"]))

    def pose_solve_one(coeffs, pose, t, ls, Rk, corr, pts, nrm, npts, tgt, w, n):
        y0 = {"pose": pose[free], "t": t}
        args = (coeffs, pose, ls, Rk, corr, pts, nrm, npts, tgt, w, n)
        y, bad, k = solve(pose_fn, y0, args, cfg.pose_steps)
        return pose.at[free].set(y["pose"]), y["t"], bad, k

    def pose_solve(coeffs, poses, ts, ls, corr):
        return jax.vmap(pose_solve_one, in_axes=(None, 0, 0, None, 0, 0, 0, 0, 0, 0, 0, 0))(
            coeffs, poses, ts, ls, R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm
        )

    # Stage 2b: the shared shape (+ the shared scale) with both poses fixed, one solve.
    def shape_fn(y, args):
        poses, ts, ls_fixed, corr = args
        coeffs = _bounded(y["u"], b)
        ls = y["ls"] if fc.fit_scale else ls_fixed

        def one(pose, t, Rk, c, pts, nrm, npts, tgt, w, n):
            x = mesh(coeffs, pose, t, ls, Rk)
            res = data_res(x, c, pts, npts, nrm)
            if fc.landmark_weight > 0:
                res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
            return tuple(res)

        res = jax.vmap(one)(poses, ts, R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm)
        if fc.shape_prior > 0:
            res = (*res, np.sqrt(fc.shape_prior) * coeffs)
        return res

    def shape_solve(u, poses, ts, ls, corr):
        y0 = {"u": u}
        if fc.fit_scale:
            y0["ls"] = ls
        y, bad, k = solve(shape_fn, y0, (poses, ts, ls, corr), cfg.shape_steps)
        return y["u"], y["ls"] if fc.fit_scale else ls, bad, k

    # Stage 2 (joint=True): everything at once, one Levenberg-Marquardt solve per round.
    def joint_fn(y, args):
        base, corr = args
        coeffs = _bounded(y["u"], b)
        poses = base.at[:, free].set(y["pose"])

        def one(pose, t, Rk, c, pts, nrm, npts, tgt, w, n):
            x = mesh(coeffs, pose, t, y["ls"], Rk)
            res = data_res(x, c, pts, npts, nrm)
            if fc.landmark_weight > 0:
                res.append(lm_res(x, tgt, w, n, fc.landmark_weight))
            return tuple(res)

        res = jax.vmap(one)(poses, y["t"], R, corr, points, snormals, n_pts, lm_target, lm_w, n_lm)
        res = (*res, *pose_prior(y["pose"].swapaxes(0, 1)))
        if fc.shape_prior > 0:
            res = (*res, np.sqrt(fc.shape_prior) * coeffs)
        return res

    def joint_solve(u, poses, ts, ls, corr):
        y0 = {"u": u, "pose": poses[:, free], "t": ts, "ls": ls}
        y, bad, k = solve(joint_fn, y0, (poses, corr), cfg.pose_steps + cfg.shape_steps)
        ls = y["ls"] if fc.fit_scale else ls
        return y["u"], poses.at[:, free].set(y["pose"]), y["t"], ls, bad, k

    def meshes(u, poses, ts, ls):
        return jax.vmap(mesh, in_axes=(None, 0, 0, None, 0))(_bounded(u, b), poses, ts, ls, R)

    def measure(u, poses, ts, ls):
        corr, info = correspond_all(meshes(u, poses, ts, ls), points, snormals, mask)
        n_tot = jnp.maximum(jnp.sum(info["n_m"] + info["n_s"]), 1.0)
        mean_d = jnp.sum(info["mean_m"] * info["n_m"] + info["mean_s"] * info["n_s"]) / n_tot
        return corr, jnp.sum(info["term"]), mean_d, info

    u0 = jnp.zeros((K,), dtype)
    init_vertices = meshes(u0, poses0, ts0, ls0)
    corr0, term0, mean0, _ = measure(u0, poses0, ts0, ls0)
    nan = jnp.full((cfg.max_rounds + 1,), jnp.nan, dtype)

    def cond(s):
        i, *_, done, bad, _ = s
        return (i < cfg.max_rounds) & ~done & ~bad

    def body(s):
        i, u, poses, ts, ls, corr, hist, dhist, done, bad, steps = s
        if cfg.joint:
            u, poses, ts, ls, bad2, k2 = joint_solve(u, poses, ts, ls, corr)
            bad1, k1 = jnp.asarray(False), jnp.asarray(0)
        else:
            poses, ts, bad1, k1 = pose_solve(_bounded(u, b), poses, ts, ls, corr)
            corr, _, _, _ = measure(u, poses, ts, ls)
            u, ls, bad2, k2 = shape_solve(u, poses, ts, ls, corr)
        corr, term, mean_d, _ = measure(u, poses, ts, ls)
        prev, prev_d = hist[i], dhist[i]
        done = (jnp.abs(prev - term) <= cfg.rtol * prev) | (jnp.abs(prev_d - mean_d) <= cfg.atol_mm)
        bad = bad | jnp.any(bad1) | bad2 | ~jnp.isfinite(term)
        hist, dhist = hist.at[i + 1].set(term), dhist.at[i + 1].set(mean_d)
        return i + 1, u, poses, ts, ls, corr, hist, dhist, done, bad, steps + jnp.sum(k1) + k2

    state = (
        jnp.asarray(0), u0, poses0, ts0, ls0, corr0, nan.at[0].set(term0), nan.at[0].set(mean0),
        jnp.asarray(False), jnp.any(bad0) | ~jnp.isfinite(term0), jnp.sum(steps0),
    )  # fmt: skip
    rounds, u, poses, ts, ls, corr, hist, dhist, done, bad, steps = jax.lax.while_loop(
        cond, body, state
    )
    coeffs = _bounded(u, b)
    verts = meshes(u, poses, ts, ls)
    _, _, _, info = measure(u, poses, ts, ls)
    finite = jnp.all(jnp.isfinite(verts)) & jnp.all(jnp.isfinite(coeffs))
    result = FitResult.where(done, FitResult.successful, FitResult.max_passes_reached)
    result = FitResult.where(bad, FitResult.solver_failed, result)
    result = FitResult.where(finite, result, FitResult.nonfinite)
    lm_err = jnp.linalg.norm(verts[:, st.lm_vertex] - lm_target, axis=-1) * _MM
    stats = {
        "data_term": hist,
        "mean_distance_mm": dhist,
        "rounds": rounds,
        "converged": done,
        "model_to_scan_mm": info["mean_m"],
        "scan_to_model_mm": info["mean_s"],
        "valid_fraction": info["frac_s"],
        "landmark_rms_mm": jnp.sqrt(jnp.sum(lm_w * lm_err**2, -1) / n_lm),
        "solver_steps": steps,
    }
    return DepthFit(
        coeffs=coeffs,
        poses=poses,
        similarities=Similarity(R, ts, jnp.broadcast_to(ls, (2,))),
        vertices=verts,
        rest_vertices=shape_vertices(model, coeffs),
        scale=jnp.exp(ls),
        init_vertices=init_vertices,
        result=result,
        stats=stats,
    )


@eqx.filter_jit
def _fit_depth_jit(model, scans, st, pose0, cfg, throw):
    fit = _fit_depth_kernel(model, scans, st, pose0, cfg)
    if throw:
        failed = (fit.result == FitResult.solver_failed) | (fit.result == FitResult.nonfinite)
        fit = fit.result.error_if(fit, failed)
    return fit


def fit_depth(
    model: SScapeModel,
    front_scan: Scan,
    back_scan: Scan,
    tmpl: RegistrationTemplate,
    *,
    config: DepthFitConfig = DepthFitConfig(),
    throw: bool = True,
) -> DepthFit:
    """Fits one S-SCAPE shape and a pose per image to a front and a back depth scan.

    The procedure of the paper's §6 (after Helten et al. 2013; humanshape `fitPoseShapeJoint`,
    sscape.md §4, §8), in one jitted call:

    1. **Per-image initialisation** (vmapped over the two images): the similarity from the image's
       landmarks (Umeyama on the model mean's landmark vertices, as in
       [`bodyprior.sscape.fit_sscape`][]), then pose, translation and scale from the landmarks with
       the shape at the mean (humanshape `fitPose`). The paper's step 1 runs a full S-SCAPE fit per
       image and averages the two shapes; here the shared shape starts at the mean and is fitted
       by step 2 only (one shape from both images from the start; it also avoids compiling the
       per-scan fitter a second time).
    2. **Joint fit.** Starting from the two poses and the mean of the two scales, rounds of: new
       correspondences, then one Levenberg-Marquardt solve over the shared shape, both poses and
       translations and the shared scale (`config.joint=True`; with `False`, humanshape
       `fitPoseShapeJoint`'s alternation: a pose solve per image with the shape fixed, new
       correspondences, one shared shape + scale solve with the poses fixed); until the data term
       stops changing (`lax.while_loop`).

    A depth image sees one side of the body, so the data term has two directions per image:
    **model -> scan** (each non-hand model vertex to its nearest *compatible* depth point, normals
    within `max_angle_deg`, distance gated by `max_dist`; back-facing vertices find no compatible
    point and drop out, which is the visibility test) and **scan -> model** (each depth point to the
    nearest compatible model vertex, i.e. a vertex facing the camera, point-to-plane with that
    vertex's normal, same gates; pairs on hand vertices dropped), the latter weighted by
    `scan_weight` and normalised by the number of depth points. Both are squared distances in mm,
    solved by optimistix Levenberg-Marquardt with a normal-equation Cholesky linear solver (the
    Jacobians are tall and thin); run in float64 (`jax_enable_x64`).

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][] on `tmpl`'s topology.
    - `front_scan`, `back_scan`: one [`bodyprior.sscape.Scan`][] each (e.g. from
      [`bodyprior.sscape.depth_to_scan`][]), world frame, metres, normals facing their camera, each
      with at least 4 landmarks known to `tmpl` (the paper placed 14 by hand). They are padded to a
      common point count if needed.
    - `tmpl`: the [`bodyprior.sscape.RegistrationTemplate`][].
    - `config`: a [`bodyprior.sscape.DepthFitConfig`][].
    - `throw`: raise if a solve failed or the result is not finite; otherwise inspect `result`.

    **Returns:** a [`bodyprior.sscape.DepthFit`][].

    **Raises:** `ValueError` (before tracing) for a wrong model/template/config, scans that are not
    `Scan`s, have different landmark names, NaN points, or fewer than 4 usable landmarks.
    """
    from ._scan import pad_scans

    if not isinstance(config, DepthFitConfig):
        raise ValueError(f"`config` must be a DepthFitConfig, got {type(config).__name__}.")
    for name, sc in (("front_scan", front_scan), ("back_scan", back_scan)):
        if not isinstance(sc, Scan):
            raise ValueError(f"`{name}` must be a bodyprior.sscape.Scan, got {type(sc).__name__}.")
        if np.ndim(sc.points) != 2:
            raise ValueError(
                f"`{name}` must be one (unbatched) scan, got points of shape {np.shape(sc.points)}."
            )
        check_scan(sc, min_points=1, name=name)
    if front_scan.landmark_names != back_scan.landmark_names:
        raise ValueError("`front_scan` and `back_scan` must have the same `landmark_names`.")
    if isinstance(tmpl, RegistrationTemplate):
        known = np.array([n in tmpl.landmark_names for n in front_scan.landmark_names], bool)
        for name, sc in (("front_scan", front_scan), ("back_scan", back_scan)):
            count = int((np.asarray(sc.landmark_mask, bool).reshape(-1) & known).sum())
            if count < 4:
                raise ValueError(
                    f"`{name}` must have at least 4 present landmarks known to the template "
                    f"(the paper placed 14 by hand on each depth image), got {count}."
                )
    scans = pad_scans([front_scan, back_scan])
    model, st, _, pose, _ = _prepare(model, scans, tmpl, config.fit, None, None, True)
    return _fit_depth_jit(model, scans, st, pose, config, bool(throw))
