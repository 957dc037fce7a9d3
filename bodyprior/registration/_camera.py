"""A Kinect-like depth camera: rendering, back-projection to scans, simulated depth captures.

The acquisition half of body reconstruction from depth images (S-SCAPE paper §6, after Helten et al.
2013; the fit itself is `bodyprior.sscape.fit_depth`). A Kinect-like depth camera (`DepthCamera`:
pinhole, 512x424 pixels, Kinect v2 depth intrinsics fx = fy = 365 px, principal point at the image
centre) renders the exact first-hit depth of a mesh with the shared z-buffer of
`bodyprior/_render.py` (perspective: `1 / z` is affine in screen space, so the per-pixel depth is
the exact ray/triangle intersection at the pixel centre), plus axial noise that grows with the
square of the depth, as Kinect depth noise does. `depth_to_scan` back-projects the valid pixels to a
world-frame [`bodyprior.registration.Scan`][] with normals from the (edge-aware smoothed)
depth-image gradients. The pixel -> (face, barycentric) ground truth is kept in a separate
`DepthTruth` for evaluation only.

Camera frame (OpenCV): x to the image right, y to the image bottom, z along the optical axis. Pixel
`(i, j)` (row, column) covers `[j, j + 1] x [i, i + 1]` in image coordinates `(u, v)`, so its centre
is `(j + 0.5, i + 0.5)` and the principal point `(W / 2, H / 2)` is the image centre. Depth is `z`
(distance along the optical axis, as Kinect reports it), metres; 0 means no return.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._render import _rasterize_screen
from .._validate import check_array
from ._scan import Scan, ScanTruth

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

    eye: Float[Array, " 3"]
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

    def to_camera(self, points: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
        """World points `(N, 3)` -> camera-frame points `(N, 3)` (z = depth)."""
        return (jnp.asarray(points) - self.eye) @ self.rotation.T

    def to_world(self, points: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
        """Camera-frame points `(N, 3)` -> world points `(N, 3)`."""
        return jnp.asarray(points) @ self.rotation + self.eye

    def project(self, points: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
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

    def pixel_points(self, depth: Float[ArrayLike, "H W"]) -> Float[Array, "H W 3"]:
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
    - `camera`: a [`bodyprior.registration.DepthCamera`][].
    - `key`: `jax.random` key for the noise; `None` = no noise.
    - `noise_sigma`: noise coefficient in metres at 1 m depth (>= 0).
    - `near`, `far`: valid depth range, metres.
    - `max_incidence_deg`: in `(0, 90]` or `None` (keep every hit).

    **Returns:** `(depth, truth)`: `depth` float64 `(H, W)` metres (0 = no return) and a
    [`bodyprior.registration.DepthTruth`][].
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
    """Back-projects the valid pixels of a depth image to a world-frame
    [`bodyprior.registration.Scan`][].

    **Arguments:**

    - `depth`: `(H, W)` depth image in metres (0 = no return), e.g. from
      [`bodyprior.registration.render_depth`][]; foreground only (segment the background away
      first).
    - `camera`: the [`bodyprior.registration.DepthCamera`][] that took it.
    - `n_points`: fixed point count `P` of the scan: more valid pixels are sub-sampled at random
      (`seed`), fewer are padded (`point_mask` False). `None` = exactly the valid pixels.
    - `landmarks`, `landmark_mask`, `landmark_names`: optional landmarks `(L, 3)` (world, metres),
      presence mask `(L,)` and names; default none (`L = 0`).
    - `normal_radius`, `max_jump`: smoothing of the normal estimate, see
      [`bodyprior.registration.depth_normals`][].

    **Returns:** a `Scan` whose points are in raster order of the selected pixels; normals face the
    camera. Use [`bodyprior.registration.depth_scan_truth`][] with the same `n_points`/`seed` for
    the
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
    """The `ScanTruth` matching [`bodyprior.registration.depth_to_scan`][] called with the same
    `depth`, `camera`, `n_points` and `seed` (evaluation only).

    `face`/`bary` locate each scan point on the rendered mesh, `true_points` is the noise-free hit
    point (world), `is_outlier` is False for every pixel (depth noise only). Padding rows have
    `face` -1 and repeat real `true_points`, as [`bodyprior.registration.pad_scans`][] pads.
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

DEPTH_LANDMARKS = (
    "Vertex", "Rt. Acromion", "Lt. Acromion", "Rt. Radiale", "Lt. Radiale", "Rt. Radial Styloid",
    "Lt. Radial Styloid", "Rt. Trochanterion", "Lt. Trochanterion", "Rt. Femoral Lateral Epicn",
    "Lt. Femoral Lateral Epicn", "Rt. Lateral Malleolus", "Lt. Lateral Malleolus", "Crotch",
)  # fmt: skip
"""The 14 landmarks placed on each depth image (the paper placed 14 landmarks by hand on every
depth scan of Helten et al.'s data; which ones is not stated; these are joints a person can
click on a depth image from the front and from the back)."""


def depth_landmarks(
    landmark_positions,
    landmark_names,
    *,
    key,
    subset: tuple[str, ...] = DEPTH_LANDMARKS,
    sigma: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulated manual landmarks of one depth image: the `subset` of the true landmark positions
    plus isotropic N(0, `sigma`^2) placement noise per coordinate; the others are missing.

    **Arguments:** `key` (`jax.random` key); `landmark_positions` `(L, 3)` true positions on the
    posed body; `landmark_names` (`L` names); `subset` (names to place); `sigma` metres.

    **Returns:** `(landmarks (L, 3), landmark_mask (L,))` (0 where missing), for
    [`bodyprior.registration.depth_to_scan`][].
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


def capture_poses(
    joint_names, rest_joints, n: int, *, key, jitter_deg: float = 4.0
) -> np.ndarray:
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
    vertices,
    faces,
    camera: DepthCamera,
    landmark_positions,
    landmark_names,
    *,
    key,
    n_points: int | None = 8192,
    noise_sigma: float = 0.0015,
    landmark_sigma: float = 0.01,
    landmark_subset: tuple[str, ...] = DEPTH_LANDMARKS,
    max_incidence_deg: float | None = 80.0,
):
    """One simulated depth capture: render, back-project, place the manual landmarks.

    **Arguments:** `key`; the posed true body `vertices (V, 3)` / `faces (F, 3)` (full resolution);
    `camera`; true `landmark_positions (L, 3)` and `landmark_names`; `n_points` (fixed scan size,
    see [`bodyprior.registration.depth_to_scan`][]); `noise_sigma`, `max_incidence_deg` (see
    [`bodyprior.registration.render_depth`][]); `landmark_sigma`, `landmark_subset` (see
    [`bodyprior.registration.depth_landmarks`][]).

    **Returns:** `(scan, truth, depth)`: the `Scan`, its `ScanTruth` (evaluation only) and the
    noisy depth image `(H, W)`.
    """
    k_noise, k_lm, k_sub = jr.split(key, 3)
    depth, dtruth = render_depth(
        vertices, faces, camera, key=k_noise, noise_sigma=noise_sigma,
        max_incidence_deg=max_incidence_deg,
    )  # fmt: skip
    lms, lmask = depth_landmarks(
        landmark_positions, landmark_names, subset=landmark_subset, sigma=landmark_sigma, key=k_lm
    )
    seed = int(jr.randint(k_sub, (), 0, 2**31 - 1))
    scan = depth_to_scan(
        depth, camera, n_points=n_points, seed=seed, landmarks=lms, landmark_mask=lmask,
        landmark_names=tuple(landmark_names),
    )  # fmt: skip
    truth = depth_scan_truth(dtruth, depth, camera, n_points=n_points, seed=seed)
    return scan, truth, depth
