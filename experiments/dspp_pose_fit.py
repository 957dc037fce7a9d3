"""Does the DSPP pose prior help a pose fitter with sparse input? (issue 15 §6)

Task: recover the full body pose (the 20 DSPP joints' Euler angles) of held-out CMU mocap poses on
the default body (`cmu_mb` rig, mean phenotype, root fixed at the origin with zero rotation) from
3-D positions of a few points, observed with Gaussian noise (`--noise-mm` per coordinate, default
10 mm). Two observation sets:

- `sparse`: five "tracker" points, the top of the head (tail of `Head`), both wrists (heads of
  `LeftHand`/`RightHand`) and both ankles (heads of `LeftFoot`/`RightFoot`): 15 numbers for 60
  unknowns, as VR/IMU trackers give;
- `joints`: every rig joint head plus the tails of the head, hands and toes: twist about each bone
  and the leaf bones' own rotations stay unobserved;
- `depth`: a single frontal depth view: the body's mesh (13,380 vertices, LBS on the same rig)
  rendered by `bodyprior.registration.render_depth` (Kinect v2 intrinsics, 2.5 m in front of the
  body, axial noise 1.5 mm x z^2, about 9 mm here, grazing pixels dropped) and back-projected to
  `--depth-points` points (`depth_to_scan`); no correspondences are given. The fit is a
  multi-start ICP: of `--depth-starts` candidates (the mean pose and random training poses) the
  `--depth-top` nearest to the view (symmetric chamfer distance) each get one round, the best
  continues; each round pairs every observed point with its nearest visible model vertex and
  `--model-points` surface-spread model vertices with their nearest observed points, then takes LM
  steps on that symmetric point-to-vertex residual (`--icp-rounds` rounds of
  `--max-steps / --icp-rounds` steps: the same LM budget as the other sets). The back of the body,
  and whatever the front hides, is unseen.

Fitters (optimistix Levenberg-Marquardt, float64, vmapped over poses, from the mean training
pose): `none` (the data term and a tiny ridge, 1e-4 rad^-2, that keeps unobserved angles finite);
`gaussian` (a full-covariance Gaussian of the 60 training Euler angles, `w · ||L⁻¹(e − μ)||²`);
`dspp` (the trained AE-GAN pose prior as a residual, `bodyprior.dspp.pose_prior_residual`: the
latent discriminator's score `w · softplus(-D(E(e)))` plus `w_r ·` the mean squared distance to the
auto-encoder's manifold, rad²); `dspp_gaussian` (both, each at the weights chosen for it alone).
Data residuals are in units of the noise.
Every weight is chosen on validation poses (from validation clips) by the mean per-joint geodesic
error; the test poses (test clips) are used once.

Data: every BVH clip under `--mocap` at 4 poses/s, split by whole clips (`split_by_clip`, 20 %
test), the training clips split again (10 % validation clips). The pose prior is trained here on
the training clips with the library's default preset (`train_pose_prior`, "pose", with the
collapse monitor on the validation clips) unless `--prior` gives a trained `.dspp` file.

Errors: mean per-joint geodesic angle (degrees) over the 20 pose joints, and the mean position
error (mm) of all 31 rig joint heads and the 5 tails, both against the true pose. The generator of
the depth images is the fitted LBS model itself (this compares priors, not body models).

Outputs in `--out`: `metrics.json` and `pose_fit.png` (test errors per method and observation
set). Usage: `python experiments/dspp_pose_fit.py --out out/pose_fit` (full, ~18 min on 2 cores
with training) or `--quick` (minutes); the tests run `--quick --tiny`.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import bodyprior as bp  # noqa: E402
from bodyprior import dspp  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MOCAP = REPO.parent / "shared" / "data" / "mocap"

SIZES = {
    "full": dict(n_val=64, n_test=128, mocap=None, prior_steps=100_000, prior_batch=64,
                 depth_val=16, depth_test=64, grid_w=(1.0, 10.0), grid_wr=(0.0, 100.0, 1000.0),
                 grid_g=(0.3, 1.0, 3.0)),
    "quick": dict(n_val=32, n_test=64, mocap=None, prior_steps=20_000, prior_batch=64,
                  depth_val=8, depth_test=16, grid_w=(1.0, 10.0), grid_wr=(0.0, 1000.0),
                  grid_g=(0.3, 1.0)),
    "tiny": dict(n_val=4, n_test=4, mocap=("cmu_3dsmax-friendly_yuki-koyama-bvh11",),
                 prior_steps=200, prior_batch=16, grid_w=(1.0,), grid_wr=(100.0,),
                 grid_g=(1.0,), depth_points=100),
}  # fmt: skip
DEPTH_DISTANCE = 2.5  # m, camera in front of the body (-Y), looking at its bounding-box centre
TINY_NET = dict(latent_dim=16, noise_dim=16, ae_hidden=(64,), generator_hidden=(64,),
                discriminator_hidden=(64,))  # fmt: skip
TRACKERS = (("Head", "tail"), ("LeftHand", "head"), ("RightHand", "head"),
            ("LeftFoot", "head"), ("RightFoot", "head"))  # fmt: skip
TAILS = ("Head", "LeftHand", "RightHand", "LeftToeBase", "RightToeBase")
METHODS = ("none", "gaussian", "dspp", "dspp_gaussian")
RIDGE = 1e-4  # rad^-2 on every angle (all methods): unobserved angles stay finite


def _log(msg: str) -> None:
    print(f"[pose_fit {time.strftime('%H:%M:%S')}] {msg}", flush=True)


class Skeleton(eqx.Module):
    """The default body's `cmu_mb` rig at the mean phenotype: Euler pose -> posed points."""

    heads: jax.Array  # (J, 3) rest joint heads
    tails: jax.Array  # (J, 3) rest bone tails
    parents: tuple[int, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)

    def kinematics(self, euler):
        """Skinning transforms `(J, 4, 4)` and posed joint heads `(J, 3)` of an Euler pose `(20, 3)`
        (the rotations of `bodyprior.rig_pose`: the 20 pose joints, every other bone at rest)."""
        idx = np.array([self.joint_names.index(n) for n in bp.POSE_JOINTS])
        Rp = jax.vmap(lambda e: bp.euler_to_matrix(e, bp.EULER_ORDER))(euler)
        J = len(self.joint_names)
        R = jnp.broadcast_to(jnp.eye(3, dtype=Rp.dtype), (J, 3, 3)).at[idx].set(Rp)
        return bp.forward_kinematics(self.parents, R, self.heads, jnp.zeros(3, R.dtype))

    def all_points(self, euler):
        """Posed joint heads and then bone tails, shape `(2J, 3)`, metres."""
        A, t = self.kinematics(euler)
        tails = t + jnp.einsum("jab,jb->ja", A[:, :3, :3], self.tails - self.heads)
        return jnp.concatenate([t, tails])

    def points(self, euler, obs):
        """The observed points `(M, 3)` of an observation set `(index (M,), mask (M,))`."""
        return self.all_points(euler)[obs[0]]


class SkinnedMesh(eqx.Module):
    """The default body's mesh at the base shape on the `cmu_mb` rig (the depth set's model)."""

    rest: jax.Array  # (V, 3) rest vertices, metres (the base body, whose joints `Skeleton` holds)
    skin_indices: jax.Array  # (V, K) int32
    skin_weights: jax.Array  # (V, K)
    faces: jax.Array  # (F, 3) int32
    sample: jax.Array  # (S,) int32: the vertices of the model-to-data term

    def vertices(self, skel: Skeleton, euler, rows=None):
        """Posed vertices `(V, 3)` (or the `rows` `(P,)` of them), LBS, metres."""
        A, _ = skel.kinematics(euler)
        if rows is None:
            return bp.lbs(self.rest, self.skin_indices, self.skin_weights, A)
        return bp.lbs(self.rest[rows], self.skin_indices[rows], self.skin_weights[rows], A)


def _nearest(points, candidates, allowed):
    """Index `(P,)` of the nearest `allowed` `(C,)` row of `candidates` `(C, 3)` to each of
    `points` `(P, 3)`."""
    d2 = (candidates * candidates).sum(1)[None, :] - 2.0 * points @ candidates.T
    return jnp.argmin(jnp.where(allowed[None, :], d2, jnp.inf), axis=1)


VIS_BIN_PX = 4  # visibility test: depth-buffer bins of 4 x 4 pixels
VIS_TOL = 0.03  # m: a vertex is visible within 3 cm of its bin's nearest vertex


def _visible(cam, V, faces):
    """Which vertices `(V,)` the camera sees: facing it, and within `VIS_TOL` of the nearest
    vertex in their `VIS_BIN_PX`-pixel bin of a coarse depth buffer (jittable occlusion test)."""
    N = bp.vertex_normals(V, faces)
    facing = jnp.sum(N * (cam.eye - V), axis=1) > 0
    c = cam.to_camera(V)
    z = jnp.maximum(c[:, 2], 1e-6)
    h, w = cam.size
    bw, bh = -(-w // VIS_BIN_PX), -(-h // VIS_BIN_PX)
    u = jnp.clip(((cam.fx * c[:, 0] / z + cam.cx) // VIS_BIN_PX).astype(jnp.int32), 0, bw - 1)
    v = jnp.clip(((cam.fy * c[:, 1] / z + cam.cy) // VIS_BIN_PX).astype(jnp.int32), 0, bh - 1)
    b = v * bw + u
    zmin = jax.ops.segment_min(jnp.where(facing, z, jnp.inf), b, num_segments=bw * bh)
    return facing & (z <= zmin[b] + VIS_TOL)


def _correspondences(skel, mesh, cam, e, points, mask):
    """Both directions of the depth set's ICP at pose `e`: for every observed point its nearest
    visible model vertex `(P,)`; for every sampled model vertex its nearest observed point `(S,)`,
    and whether that vertex is visible `(S,)` (`_visible`)."""
    V = mesh.vertices(skel, e)
    vis = _visible(cam, V, mesh.faces)
    rows = _nearest(points, V, vis)
    back = _nearest(V[mesh.sample], points, mask > 0)
    return rows, back, vis[mesh.sample].astype(V.dtype)


def skinned_mesh(body, n_sample: int) -> SkinnedMesh:
    """The `SkinnedMesh` of a `cmu_mb` default body, float64, with `n_sample` vertices for the
    model-to-data term, spread evenly over the rest surface (farthest-point sampling, host)."""
    rest = np.asarray(body.template, np.float64)
    chosen = [int(np.argmax(rest[:, 2]))]
    d = np.linalg.norm(rest - rest[chosen[0]], axis=1)
    for _ in range(min(n_sample, len(rest)) - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(rest - rest[chosen[-1]], axis=1))
    sample = np.asarray(chosen, np.int32)
    return SkinnedMesh(jnp.asarray(body.template, jnp.float64), body.rig.skin_indices,
                       jnp.asarray(body.rig.skin_weights, jnp.float64),
                       jnp.asarray(body.faces, jnp.int32), jnp.asarray(sample))  # fmt: skip


def depth_camera(mesh: SkinnedMesh):
    """The frontal Kinect v2 camera of the depth set: `DEPTH_DISTANCE` m in front of (-Y) the rest
    body's bounding-box centre, looking at it."""
    rest = np.asarray(mesh.rest)
    c = 0.5 * (rest.min(0) + rest.max(0))
    return bp.registration.DepthCamera(c - np.array([0.0, DEPTH_DISTANCE, 0.0]), c)


def depth_views(skel, mesh, faces, euler, n_points, key, progress=False):
    """Single depth views of the posed meshes: points `(n, P, 3)` and their mask `(n, P)`, world
    frame, metres. Rendered with Kinect noise (`render_depth` defaults), `P = n_points` pixels
    sampled per view (seeded by the view's index)."""
    from tqdm.auto import tqdm

    cam = depth_camera(mesh)
    verts = np.asarray(jax.jit(jax.vmap(lambda e: mesh.vertices(skel, e)))(jnp.asarray(euler)))
    pts, masks = [], []
    for i in tqdm(range(len(verts)), desc="depth views", disable=not progress):
        depth, _ = bp.registration.render_depth(verts[i], faces, cam, key=jr.fold_in(key, i))
        scan = bp.registration.depth_to_scan(depth, cam, n_points=n_points, seed=i)
        pts.append(np.asarray(scan.points))
        masks.append(np.asarray(scan.point_mask, np.float64))
    return jnp.asarray(np.stack(pts)), jnp.asarray(np.stack(masks))


def _observation_sets(names):
    """`{name: (index (M,), mask (M,))}` into `Skeleton.all_points`, padded to one size `M` (one
    compilation for both sets; padding rows have mask 0)."""
    idx, J = {n: i for i, n in enumerate(names)}, len(names)
    sparse = [idx[n] + (J if part == "tail" else 0) for n, part in TRACKERS]
    joints = list(range(J)) + [J + idx[n] for n in TAILS]
    M = max(len(sparse), len(joints))
    return {k: (jnp.asarray(v + [0] * (M - len(v)), jnp.int32),
                jnp.asarray([1.0] * len(v) + [0.0] * (M - len(v))))
            for k, v in (("sparse", sparse), ("joints", joints))}  # fmt: skip


def _gaussian(train):
    x = train.reshape(len(train), -1).astype(np.float64)
    mu = x.mean(0)
    cov = np.cov(x, rowvar=False) + 1e-4 * np.eye(x.shape[1])
    Linv = np.linalg.inv(np.linalg.cholesky(cov))
    return jnp.asarray(mu.reshape(20, 3)), jnp.asarray(Linv)


def _prior_terms(e, mu, Linv, wg, pr):
    """The ridge, Gaussian and DSPP residuals of an Euler pose (shared by every observation set)."""
    return [np.sqrt(RIDGE) * e.reshape(-1), jnp.sqrt(wg) * (Linv @ (e - mu).reshape(-1)), pr(e)]


def _fit_all(skel, obs, targets, sigma, mu, Linv, prior_res, w_g, start, max_steps):
    """LM fits of all `targets` `(n, M, 3)`. Observation sets, weights and the prior are arrays
    (one compilation for every method, weight and set)."""

    def residual(e, args):
        tgt, wg, pr = args
        d = (skel.points(e, obs) - tgt) / sigma * obs[1][:, None]
        return jnp.concatenate([d.reshape(-1), *_prior_terms(e, mu, Linv, wg, pr)])

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)

    def one(tgt):
        sol = optx.least_squares(residual, solver, start, args=(tgt, w_g, prior_res),
                                 max_steps=max_steps, throw=False)  # fmt: skip
        return sol.value

    return jax.vmap(one)(targets)


_fit_jit = eqx.filter_jit(_fit_all)


def start_poses(train, mean, k: int, seed: int = 0):
    """`k` candidate start poses `(k, 20, 3)` for the depth set: the mean training pose and `k - 1`
    training poses drawn at random (`seed`)."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(train), min(k - 1, len(train)), replace=False)
    return np.concatenate([np.asarray(mean)[None], np.asarray(train)[pick]])


def _chamfer(skel, mesh, cam, e, points, mask):
    """Symmetric mean squared distance (m^2) between observed points and the visible sampled
    model vertices at pose `e` (picks the depth set's start pose)."""
    V = mesh.vertices(skel, e)
    Vs = V[mesh.sample]
    front = _visible(cam, V, mesh.faces)[mesh.sample]
    d2 = jnp.sum(points**2, 1)[:, None] + jnp.sum(Vs**2, 1)[None, :] - 2.0 * points @ Vs.T
    to_model = jnp.min(jnp.where(front[None, :], d2, jnp.inf), axis=1)
    to_data = jnp.min(jnp.where(mask[:, None] > 0, d2, jnp.inf), axis=0)
    fw = front.astype(d2.dtype)
    return jnp.sum(to_model * mask) / jnp.maximum(mask.sum(), 1.0) + jnp.sum(
        jnp.where(front, to_data, 0.0)
    ) / jnp.maximum(fw.sum(), 1.0)


def _fit_depth_all(skel, mesh, cam, targets, masks, starts, sigma, mu, Linv, prior_res, w_g,
                   rounds, steps):  # fmt: skip
    """ICP-style LM fits of single depth views `targets` `(n, P, 3)` (mask `(n, P)`) seen by
    `cam` (a `DepthCamera`), from `starts` `(n, k, 20, 3)` (`pick_starts`). Each round takes the
    correspondences of `_correspondences` at the current pose (all poses in one `lax.map`), then
    `steps` LM steps on the symmetric point-to-vertex residual with those correspondences fixed
    (the model-to-data half weighted to the same total as the data-to-model half: it pulls limbs
    that no observed point is nearest to). The first round runs from each of the `k` starts; the
    one nearest the view after it (`_chamfer`) goes on for `rounds - 1` more."""

    def residual(e, args):
        tgt, m, (rows, back, front), wg, pr = args
        d = (mesh.vertices(skel, e, rows) - tgt) / sigma * m[:, None]
        scale = jnp.sqrt(m.sum() / jnp.maximum(front.sum(), 1.0))
        b = (mesh.vertices(skel, e, mesh.sample) - tgt[back]) / sigma * (scale * front)[:, None]
        return jnp.concatenate([d.reshape(-1), b.reshape(-1), *_prior_terms(e, mu, Linv, wg, pr)])

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)

    def lm(e, tgt, m, corr):
        sol = optx.least_squares(residual, solver, e, args=(tgt, m, corr, w_g, prior_res),
                                 max_steps=steps, throw=False)  # fmt: skip
        return sol.value

    def one_round(E, _, targets, masks):
        corr = jax.lax.map(lambda a: _correspondences(skel, mesh, cam, *a), (E, targets, masks))
        return jax.vmap(lm)(E, targets, masks, corr), None

    n, k = starts.shape[:2]
    # round 1 from each of the k starts of every view; keep the best by chamfer distance
    rep = lambda x: jnp.repeat(x, k, axis=0)  # noqa: E731
    E1, _ = one_round(starts.reshape(n * k, *starts.shape[2:]), None, rep(targets), rep(masks))
    score = jax.lax.map(lambda a: _chamfer(skel, mesh, cam, *a), (E1, rep(targets), rep(masks)))
    best = jnp.argmin(score.reshape(n, k), axis=1)
    E = E1.reshape(n, k, *starts.shape[2:])[jnp.arange(n), best]
    E, _ = jax.lax.scan(lambda E, _: one_round(E, None, targets, masks), E, None, length=rounds - 1)
    return E


@eqx.filter_jit
def pick_starts(skel, mesh, cam, candidates, targets, masks, top: int):
    """For each depth view `targets` `(n, P, 3)` (mask `(n, P)`), the `top` candidate poses of
    `candidates` `(k, 20, 3)` with the smallest `_chamfer` distance to it: `(n, top, 20, 3)`."""

    def pick(a):
        tgt, m = a
        c = jax.lax.map(lambda e: _chamfer(skel, mesh, cam, e, tgt, m), candidates, batch_size=16)
        return candidates[jnp.argsort(c)[:top]]

    return jax.lax.map(pick, (targets, masks))


_fit_depth_jit = eqx.filter_jit(_fit_depth_all)


def _errors(skel, est, truth, all_points):
    """Mean per-joint geodesic angle (deg) and mean point error (mm), per pose."""
    ang = np.asarray(jax.vmap(bp.pose_geodesic_metric)(jnp.asarray(est), jnp.asarray(truth)))
    p_est = jax.vmap(lambda e: skel.points(e, all_points))(jnp.asarray(est))
    p_tru = jax.vmap(lambda e: skel.points(e, all_points))(jnp.asarray(truth))
    mm = 1e3 * np.asarray(jnp.linalg.norm(p_est - p_tru, axis=-1)).mean(1)  # no padding here
    return np.degrees(ang), mm


def run(args) -> dict:
    mode = "tiny" if args.tiny else ("quick" if args.quick else "full")
    S = SIZES[mode]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    progress = not args.no_progress
    paths = [Path(args.mocap) / s for s in S["mocap"]] if S["mocap"] else [Path(args.mocap)]
    poses = bp.load_mocap([str(p) for p in paths], fps=4.0, progress=progress)
    train, test = bp.split_by_clip(poses, 0.2, seed=args.seed)
    train, val = bp.split_by_clip(train, 0.1, seed=args.seed)
    tr, va, te = (np.asarray(p.euler, np.float64) for p in (train, val, test))
    rng = np.random.default_rng(args.seed)
    va = va[rng.choice(len(va), min(S["n_val"], len(va)), replace=False)]
    te = te[rng.choice(len(te), min(S["n_test"], len(te)), replace=False)]
    _log(f"{len(tr)} train / {len(va)} validation / {len(te)} test poses")

    t0 = time.perf_counter()
    if args.prior:
        prior = dspp.load_prior(args.prior)
        if not isinstance(prior, dspp.PosePrior):
            raise SystemExit(f"--prior: {args.prior} is not a DSPP pose prior")
        best = None
    else:
        net = TINY_NET if mode == "tiny" else {}
        cfg = dspp.DSPPConfig.preset("pose", n_steps=S["prior_steps"], batch_size=S["prior_batch"],
                                     steps_per_call=min(5000, S["prior_steps"]),
                                     monitor_every=min(5000, S["prior_steps"]), **net)  # fmt: skip
        sol = dspp.train_pose_prior(tr.astype(np.float32), key=jr.PRNGKey(args.seed), config=cfg,
                                    validation=np.asarray(val.euler, np.float32),
                                    progress=progress)  # fmt: skip
        prior, best = sol.value, int(sol.stats["best_step"])
        dspp.save_prior(out / "pose_prior.dspp", prior)
    t_prior = time.perf_counter() - t0

    body = bp.load_default_body("cmu_mb")
    skel = Skeleton(jnp.asarray(body.bones.head_template, jnp.float64),
                    jnp.asarray(body.bones.tail_template, jnp.float64), tuple(body.parents),
                    tuple(body.joint_names))  # fmt: skip
    sets = _observation_sets(body.joint_names)
    mesh = skinned_mesh(body, args.model_points)
    faces = np.asarray(body.faces)
    cam = depth_camera(mesh)
    n_depth = S.get("depth_points", args.depth_points)
    mu, Linv = _gaussian(tr)
    candidates = jnp.asarray(start_poses(tr, mu, args.depth_starts, args.seed))
    sigma = args.noise_mm * 1e-3
    zero_L = jnp.zeros_like(Linv)

    def observe(e_true, obs, key):
        if obs == "depth":
            pts, masks = depth_views(skel, mesh, faces, e_true, n_depth, key, progress)
            return pts, masks, pick_starts(skel, mesh, cam, candidates, pts, masks, args.depth_top)
        clean = jax.vmap(lambda e: skel.points(e, obs))(jnp.asarray(e_true))
        return clean + sigma * jr.normal(key, clean.shape, clean.dtype)

    grids = {
        "none": [dict()],
        "gaussian": [dict(w_g=g) for g in S["grid_g"]],
        "dspp": [dict(w=w, w_r=r) for w, r in itertools.product(S["grid_w"], S["grid_wr"])],
    }  # fmt: skip

    prior64 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, prior
    )

    def fit(method, hp, targets, obs):
        w_g = hp.get("w_g", 0.0)
        # methods without the DSPP term carry it at weight 0 (same residual structure)
        pr = dspp.pose_prior_residual(prior64, hp.get("w", 0.0),
                                      reconstruction_weight=hp.get("w_r", 0.0),
                                      reconstruction=True)  # fmt: skip
        L = Linv if w_g > 0 else zero_L
        if obs == "depth":
            return np.asarray(_fit_depth_jit(skel, mesh, cam, *targets, sigma, mu, L, pr,
                                             jnp.asarray(w_g), args.icp_rounds,
                                             args.max_steps // args.icp_rounds))  # fmt: skip
        return np.asarray(_fit_jit(skel, obs, targets, sigma, mu, L, pr, jnp.asarray(w_g),
                                   mu, args.max_steps))  # fmt: skip

    J = len(body.joint_names)
    all_points = (jnp.asarray(list(range(J)) + [J + body.joint_names.index(n) for n in TAILS]),
                  None)  # fmt: skip
    metrics: dict = {"mode": mode, "seed": args.seed, "noise_mm": args.noise_mm,
                     "n_train": int(len(tr)), "n_val": int(len(va)), "n_test": int(len(te)),
                     "prior_best_step": best, "observations": {k: int(v[1].sum()) for k, v in
                                                               sets.items()}}  # fmt: skip
    metrics["observations"]["depth"] = n_depth
    metrics["depth_setup"] = dict(
        camera_distance_m=DEPTH_DISTANCE, icp_rounds=args.icp_rounds,
        lm_steps_per_round=args.max_steps // args.icp_rounds, model_points=int(mesh.sample.size),
        start_candidates=int(candidates.shape[0]), starts_fitted=args.depth_top,
        n_val=int(len(va[: S.get("depth_val", len(va))])),
        n_test=int(len(te[: S.get("depth_test", len(te))])),
    )  # fmt: skip
    sets["depth"] = "depth"
    key = jr.PRNGKey(1000 + args.seed)
    t0 = time.perf_counter()
    for s_i, (sname, which) in enumerate(sets.items()):
        va_s = va[: S.get("depth_val", len(va))] if sname == "depth" else va
        te_s = te[: S.get("depth_test", len(te))] if sname == "depth" else te
        tgt_val = observe(va_s, which, jr.fold_in(key, 2 * s_i))
        tgt_test = observe(te_s, which, jr.fold_in(key, 2 * s_i + 1))
        for method in METHODS:
            if method == "dspp_gaussian":  # the two priors at their own chosen weights
                grids[method] = [{**metrics[f"{sname}_dspp"]["weights"],
                                  **metrics[f"{sname}_gaussian"]["weights"]}]  # fmt: skip
            scores = []
            for hp in grids[method]:
                ang, _ = _errors(skel, fit(method, hp, tgt_val, which), va_s, all_points)
                scores.append(float(ang.mean()))
            hp = grids[method][int(np.argmin(scores))]
            ang, mm = _errors(skel, fit(method, hp, tgt_test, which), te_s, all_points)
            metrics[f"{sname}_{method}"] = dict(
                angle_deg_mean=float(ang.mean()), angle_deg_median=float(np.median(ang)),
                point_mm_mean=float(mm.mean()), weights=hp, validation_angle_deg=scores,
                per_pose_angle_deg=ang.round(3).tolist(),
            )  # fmt: skip
            _log(f"{sname:6s} {method:13s} {ang.mean():6.2f} deg {mm.mean():6.1f} mm  {hp}")
        base = np.asarray(metrics[f"{sname}_gaussian"]["per_pose_angle_deg"])
        for method in ("dspp", "dspp_gaussian"):
            d = np.asarray(metrics[f"{sname}_{method}"]["per_pose_angle_deg"]) - base
            metrics[f"{sname}_{method}"]["vs_gaussian_deg"] = dict(
                mean=float(d.mean()), sem=float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1
                else float("nan"), better_fraction=float((d < 0).mean()),
            )  # fmt: skip
    metrics["timings_s"] = dict(prior=t_prior, fits=time.perf_counter() - t0,
                                total=time.perf_counter() - t_start)  # fmt: skip
    _plot(out / "pose_fit.png", metrics, list(sets))
    bp.atomic_write_json(out / "metrics.json", metrics)
    return metrics


def _plot(path, metrics, set_names):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3), dpi=100)
    FigureCanvasAgg(fig)
    for k, (key, label) in enumerate(
        (
            ("angle_deg_mean", "mean joint angle error [deg]"),
            ("point_mm_mean", "mean joint position error [mm]"),
        )
    ):
        ax = fig.add_subplot(1, 2, k + 1)
        x = np.arange(len(set_names))
        for m_i, m in enumerate(METHODS):
            ax.bar(x + 0.2 * (m_i - 1.5), [metrics[f"{s}_{m}"][key] for s in set_names], 0.2,
                   label=m)  # fmt: skip
        ax.set_xticks(x, set_names)
        ax.set_ylabel(label, fontsize=8)
        ax.tick_params(labelsize=8)
        if k == 0:
            ax.legend(fontsize=7)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with bp.atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="small run (minutes)")
    ap.add_argument("--tiny", action="store_true", help="with --quick: the test suite's size")
    ap.add_argument("--prior", default=None, help="a trained DSPP pose prior (.dspp)")
    ap.add_argument("--mocap", default=str(DEFAULT_MOCAP))
    ap.add_argument("--noise-mm", type=float, default=10.0)
    ap.add_argument("--max-steps", type=int, default=60, help="LM steps per fit")
    ap.add_argument(
        "--depth-points",
        type=int,
        default=1000,
        help="points sampled from each depth view (full and quick modes)",
    )
    ap.add_argument(
        "--model-points",
        type=int,
        default=1000,
        help="depth set: model vertices of the model-to-data term",
    )
    ap.add_argument(
        "--depth-starts",
        type=int,
        default=256,
        help="depth set: candidate start poses (the nearest to each view is fitted)",
    )
    ap.add_argument(
        "--depth-top",
        type=int,
        default=4,
        help="depth set: the nearest candidates fitted for one round each (the best continues)",
    )
    ap.add_argument(
        "--icp-rounds",
        type=int,
        default=5,
        help="depth set: correspondence rounds (divides --max-steps)",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if not Path(args.mocap).is_dir():
        ap.error(f"--mocap: no such directory {args.mocap}")
    if not args.noise_mm > 0:
        ap.error("--noise-mm must be positive")
    if args.depth_points < 1 or args.icp_rounds < 1 or args.max_steps % args.icp_rounds:
        ap.error("--depth-points and --icp-rounds must be positive, --icp-rounds must divide "
                 "--max-steps")  # fmt: skip
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
