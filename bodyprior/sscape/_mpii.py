"""Reading (and writing) MPII humanshape S-SCAPE model directories.

A humanshape model directory (e.g. `caesar/`, `caesar-norm-wsx/`, `caesar-norm-nh/`, distributed by
MPI for non-commercial use only, **not redistributable**; bodyprior ships none of these files)
holds:

- `model.dat` (ASCII, whitespace separated): header `NV NF NJ NS`; `NV` vertex lines
  `x y z  j_1 w_1 ... j_NS w_NS` (1-based joint ids, padding `1 0`); `NF` face lines (0-based); `NJ`
  joint lines `id  ax ay az  px py pz  parent` (1-based ids, parent 0 = none).
- `evectors.mat`, variable `evectors`: `(nComp, 3 NV)`, row `k` = unit eigenvector `k` with blocked
  coordinates `[x_1..x_NV, y_1..y_NV, z_1..z_NV]`.
- `evalues.mat`, variable `evalues`: `(1, nComp)` variances in mm² (`1/n` normalisation).
- `meanShape.mat`, variable `points`: `(NV, 3)` mean shape (mm).

The files are MATLAB v5 `.mat` files read with `scipy.io.loadmat`; v7.3 (HDF5) files are read with
`h5py` when it is installed, otherwise a `ValueError` says how to convert them.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.io

from .._kinematics import Similarity
from .._rig import Rig
from .._rotations import axis_angle_to_matrix
from .._validate import check_array
from ._model import SScapeModel

MM_TO_M = 1e-3
"""Default unit factor: humanshape files are in millimetres; bodyprior uses metres."""

# Roles of the 25 joints of the released humanshape rig, by 1-based id.
_HS25_NAMES = {
    1: "root", 2: "l_hip_x", 3: "l_hip_y", 4: "l_knee", 5: "l_ankle", 6: "r_hip_x", 7: "r_hip_y",
    8: "r_knee", 9: "r_ankle", 10: "thorax_z", 11: "thorax_x", 12: "neck", 13: "l_shoulder_1",
    14: "l_shoulder_2", 15: "l_shoulder_3", 16: "l_elbow", 17: "l_wrist", 18: "r_shoulder_1",
    19: "r_shoulder_2", 20: "r_shoulder_3", 21: "r_elbow", 22: "r_wrist", 23: "r_hip_z",
    24: "l_hip_z", 25: "thorax_y",
}  # fmt: skip
_HS25_IDS = {name: jid for jid, name in _HS25_NAMES.items()}
# Parent id of each joint id of the released rig (0 = none): the tree those names describe.
_HS25_PARENTS = {
    1: 0, 24: 1, 2: 24, 3: 2, 4: 3, 5: 4, 23: 1, 6: 23, 7: 6, 8: 7, 9: 8, 10: 1, 25: 10, 11: 25,
    12: 11, 13: 11, 14: 13, 15: 14, 16: 15, 17: 16, 18: 11, 19: 18, 20: 19, 21: 20, 22: 21,
}  # fmt: skip


def _is_hs25_tree(parent_ids: np.ndarray) -> bool:
    """Whether 1-based `parent_ids` (indexed by id - 1) are the released 25-joint rig's tree."""
    return parent_ids.shape[0] == 25 and all(
        int(parent_ids[jid - 1]) == p for jid, p in _HS25_PARENTS.items()
    )


class HumanShapeRig(NamedTuple):
    """humanshape rig data that have no place in [`bodyprior.sscape.SScapeModel`][]."""

    ids: np.ndarray
    """humanshape 1-based joint id of each model joint, shape `(J,)`."""
    axes: np.ndarray
    """Unit hinge axis of each model joint (zero for the root), shape `(J, 3)`."""
    file_joint_positions: np.ndarray
    """Joint positions stored in `model.dat` (stale, unused by humanshape), metres, model frame."""
    centroid: np.ndarray
    """File-frame point (metres) moved to the origin by `center=True` (zeros otherwise)."""
    unit_scale: float
    """Factor applied to file lengths (default 1e-3: mm to m)."""


# --------------------------------------------------------------------------------------------------
# low-level readers


def _read_mat(path: str, var: str) -> np.ndarray:
    if not os.path.isfile(path):
        raise ValueError(f"Missing humanshape file {path!r}.")
    with open(path, "rb") as f:
        head = f.read(512)
    if head.startswith(b"\x89HDF") or b"MATLAB 7.3" in head[:128]:
        try:
            import h5py  # type: ignore
        except ImportError:
            raise ValueError(
                f"{path!r} is a MATLAB v7.3 (HDF5) file; install h5py to read it, or re-save it "
                "in MATLAB "
                "with save(..., '-v7')."
            ) from None
        try:
            with h5py.File(path, "r") as hf:
                if var not in hf:
                    raise ValueError(
                        f"{path!r} has no variable {var!r} (found {sorted(hf.keys())})."
                    )
                # HDF5 stores MATLAB arrays transposed
                return np.asarray(hf[var], dtype=np.float64).T
        except OSError as e:
            raise ValueError(f"Could not read {path!r} as HDF5: {e}") from e
    try:
        data = scipy.io.loadmat(path, variable_names=[var])
    except NotImplementedError as e:
        raise ValueError(
            f"{path!r}: unsupported .mat version ({e}); re-save with save(..., '-v7')."
        ) from e
    except Exception as e:  # noqa: BLE001 - scipy raises several types for malformed files
        raise ValueError(f"Could not read {path!r} as a MATLAB .mat file: {e}") from e
    if var not in data:
        raise ValueError(f"{path!r} has no variable {var!r}.")
    arr = np.asarray(data[var])
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{path!r}: variable {var!r} must be numeric, got dtype {arr.dtype}.")
    return arr.astype(np.float64)


def _read_model_dat(path: str):
    if not os.path.isfile(path):
        raise ValueError(f"Missing humanshape file {path!r}.")
    with open(path) as f:
        tokens = f.read().split()
    try:
        nums = np.asarray([float(t) for t in tokens], dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{path!r}: non-numeric entry in model.dat ({e}).") from e
    if nums.size < 4:
        raise ValueError(f"{path!r}: model.dat must start with the header 'NV NF NJ NS'.")
    header = nums[:4]
    if np.any(header != np.round(header)) or np.any(header < 1):
        raise ValueError(
            f"{path!r}: header 'NV NF NJ NS' must hold positive integers, got {header}."
        )
    nv, nf, nj, ns = (int(h) for h in header)
    need = 4 + nv * (3 + 2 * ns) + nf * 3 + nj * 8
    if nums.size < need:
        raise ValueError(
            f"{path!r}: model.dat is truncated: header NV={nv} NF={nf} NJ={nj} NS={ns} needs "
            f"{need} numbers, "
            f"file has {nums.size}."
        )
    o = 4
    vblock = nums[o : o + nv * (3 + 2 * ns)].reshape(nv, 3 + 2 * ns)
    o += nv * (3 + 2 * ns)
    faces = nums[o : o + nf * 3].reshape(nf, 3)
    o += nf * 3
    joints = nums[o : o + nj * 8].reshape(nj, 8)
    verts = vblock[:, :3]
    pairs = vblock[:, 3:].reshape(nv, ns, 2)
    skin_ids, skin_w = pairs[..., 0], pairs[..., 1]
    for name, arr in (
        ("faces", faces),
        ("skin joint ids", skin_ids),
        ("joint ids/parents", joints[:, [0, 7]]),
    ):
        if np.any(arr != np.round(arr)):
            raise ValueError(f"{path!r}: {name} must be integers.")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= nv:
        raise ValueError(f"{path!r}: face indices must lie in [0, {nv - 1}] (0-based).")
    ids = joints[:, 0].astype(np.int64)
    if sorted(ids.tolist()) != list(range(1, nj + 1)):
        raise ValueError(f"{path!r}: joint ids must be 1..{nj}, got {sorted(ids.tolist())}.")
    skin_ids = skin_ids.astype(np.int64)
    if skin_ids.min() < 1 or skin_ids.max() > nj:
        raise ValueError(f"{path!r}: skin joint ids must lie in [1, {nj}] (1-based).")
    if np.any(skin_w < 0) or np.any(~np.isfinite(skin_w)):
        raise ValueError(f"{path!r}: skin weights must be finite and non-negative.")
    order = np.argsort(ids)
    joints = joints[order]
    return dict(
        verts=verts,
        faces=faces,
        skin_ids=skin_ids,
        skin_w=skin_w,
        axes=joints[:, 1:4],
        positions=joints[:, 4:7],
        parent_ids=joints[:, 7].astype(np.int64),
    )


# --------------------------------------------------------------------------------------------------
# rig mapping


def _joint_order(parent_ids: np.ndarray) -> list[int]:
    """Depth-first preorder (children by ascending id) of 1-based ids; validates the tree."""
    nj = parent_ids.shape[0]
    roots = [i + 1 for i in range(nj) if parent_ids[i] == 0]
    if len(roots) != 1:
        raise ValueError(
            f"model.dat: the joint tree must have exactly one root (parent 0), got ids {roots}."
        )
    children: dict[int, list[int]] = {i: [] for i in range(1, nj + 1)}
    for i in range(nj):
        p = int(parent_ids[i])
        if p != 0:
            if not 1 <= p <= nj or p == i + 1:
                raise ValueError(f"model.dat: joint {i + 1} has invalid parent id {p}.")
            children[p].append(i + 1)
    order, stack = [], [roots[0]]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(sorted(children[j], reverse=True))
    if len(order) != nj:
        raise ValueError("model.dat: the joint tree contains a cycle or unreachable joints.")
    return order


def joint_regressor_from_weights(dense_w: np.ndarray, parent_ids: np.ndarray) -> np.ndarray:
    """humanshape's surface-tied joint regressor (`updateJntPos`), dense `(NJ, NV)`, rows by id.

    Joint `i` is tied to the segment `d(i)`: `i` itself if it carries skin weight, else the first
    weighted joint down its single-child chain. With `p` the nearest weighted ancestor of `d(i)`,
    the joint is the centroid of the vertices weighted by `min(W[:, d], W[:, p])` (the skin shared
    by the two segments); the root segment uses its own weights. For the released 25-joint rig this
    reproduces the table of `updateJntPos` exactly (e.g. hip ids 2, 3, 24 -> `c(3, 1)`).
    """
    nv, nj = dense_w.shape
    weighted = dense_w.sum(axis=0) > 0
    children: dict[int, list[int]] = {i: [] for i in range(1, nj + 1)}
    for i in range(nj):
        if parent_ids[i]:
            children[int(parent_ids[i])].append(i + 1)
    reg = np.zeros((nj, nv))
    for i in range(1, nj + 1):
        d = i
        while not weighted[d - 1]:
            if len(children[d]) != 1:
                raise ValueError(
                    f"model.dat: joint {i} carries no skin weight and has no single-child chain "
                    "to a "
                    "weighted segment, so its surface position is undefined."
                )
            d = children[d][0]
        p = int(parent_ids[d - 1])
        while p and not weighted[p - 1]:
            p = int(parent_ids[p - 1])
        w = dense_w[:, d - 1] if p == 0 else np.minimum(dense_w[:, d - 1], dense_w[:, p - 1])
        if w.sum() <= 0:
            raise ValueError(
                f"model.dat: segments {d} and {p} share no skinned vertices, so joint {i} is "
                "undefined."
            )
        reg[i - 1] = w / w.sum()
    return reg


def _sparse_rows(dense: np.ndarray):
    nnz = (dense > 0).sum(axis=1)
    m = max(int(nnz.max()), 1)
    order = np.argsort(-dense, axis=1, kind="stable")[:, :m]
    weights = np.take_along_axis(dense, order, axis=1)
    order = np.where(weights > 0, order, 0)
    return order.astype(np.int32), weights


# --------------------------------------------------------------------------------------------------
# public API


def load_mpii_humanshape(
    directory: str | os.PathLike,
    *,
    n_components: int | None = None,
    unit_scale: float = MM_TO_M,
    center: bool = True,
    return_rig: bool = False,
) -> SScapeModel | tuple[SScapeModel, HumanShapeRig]:
    """Loads an MPII humanshape S-SCAPE model directory as an [`bodyprior.sscape.SScapeModel`][].

    Mapping (Pishchulin et al. 2017; humanshape `CTMesh-30DOF.cpp`):

    - Units: lengths are multiplied by `unit_scale` (default `1e-3`, mm to m); the file frame (z up,
      x = subject's left, facing -y) already matches bodyprior's.
    - Mean: `meanShape.mat` `points` (full precision; the `model.dat` vertex block is the same mean
      printed with `%f`). With `center=True` (humanshape's `centerModel`) the centroid of the
      `model.dat` vertices is subtracted, so the global rotation of a humanshape pose is about the
      origin.
    - Basis: `evectors` rows reshaped from blocked `[x.., y.., z..]` to `(V, 3)`; already unit.
      `stddev = sqrt(evalues) * unit_scale`. humanshape's `evalues` use `1/n`, so these are ML
      standard deviations (those from [`bodyprior.sscape.learn`][] use `1/(n-1)`). A humanshape
      shape vector `beta` (mm) equals `c * sqrt(evalues)` for our coefficients `c`.
      `explained_variance` is relative to the sum of all `evalues` in the file.
    - Joints: one model joint per humanshape joint id (25 for the released rig), ordered
      depth-first from the root (children by ascending id); `joint_names` are the joint roles for
      the released 25-joint rig (`"root"`, `"l_hip_z"`, ...; used when the file's joint tree is
      that rig's) and `"joint<id>"` otherwise; the ids are in the returned rig. Joint positions
      are recomputed from the surface as humanshape does
      ([`bodyprior.sscape.joint_regressor_from_weights`][]); those stored in the file are ignored.
    - Skin weights: the `NS` influence pairs are accumulated per joint and stored top-k sparse.

    Pose: humanshape's kinematics (product of exponentials of rest-frame twists) is the same as
    bodyprior's convention, so a humanshape pose vector maps exactly via
    [`bodyprior.sscape.humanshape_pose`][]: joint `i` gets axis-angle `theta_i * axis_i`, the global
    rotation/translation/scale become a `Similarity`. What cannot be represented in the model
    itself: the one-degree-of-freedom hinge constraint (each model joint accepts a full 3-DoF
    rotation, a superset; the hinge axes are kept only in the returned rig), and the humanshape
    root joint's dummy angle (entry 7, no effect). humanshape's optional dual-quaternion path is
    unused by it and not mapped (bodyprior evaluates with LBS, as humanshape does).

    **Arguments:**

    - `directory`: folder with `model.dat`, `evectors.mat`, `evalues.mat` and optionally
      `meanShape.mat` (otherwise the `model.dat` vertices are the mean).
    - `n_components`: keep the first components only (default: all in the file).
    - `unit_scale`: length factor applied to the files (default mm to m).
    - `center`: subtract the template centroid (humanshape's frame).
    - `return_rig`: also return a [`bodyprior.sscape.HumanShapeRig`][].

    **Returns:** the model, or `(model, rig)`.

    **Raises:** `ValueError` for missing or malformed files and inconsistent sizes.
    """
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise ValueError(f"`directory`: {directory!r} is not a directory.")
    dat = _read_model_dat(os.path.join(directory, "model.dat"))
    nv = dat["verts"].shape[0]
    nj = dat["axes"].shape[0]
    evectors = _read_mat(os.path.join(directory, "evectors.mat"), "evectors")
    evalues = _read_mat(os.path.join(directory, "evalues.mat"), "evalues").ravel()
    if evectors.ndim != 2 or evectors.shape[1] != 3 * nv:
        raise ValueError(
            f"evectors.mat: `evectors` must have shape (nComp, {3 * nv}) (3 x {nv} vertices), got "
            f"{evectors.shape}."
        )
    n_file = evectors.shape[0]
    if evalues.shape[0] < n_file:
        raise ValueError(
            f"evalues.mat: `evalues` has {evalues.shape[0]} entries, evectors has {n_file} rows."
        )
    evalues = evalues[:n_file]
    if not (np.all(np.isfinite(evectors)) and np.all(np.isfinite(evalues))) or np.any(evalues < 0):
        raise ValueError("evectors.mat/evalues.mat must be finite with non-negative eigenvalues.")
    norms = np.linalg.norm(evectors, axis=1)
    if np.any(np.abs(norms - 1) > 1e-3):
        raise ValueError(
            f"evectors.mat: eigenvectors must have unit norm, got norms in [{norms.min()}, "
            f"{norms.max()}]."
        )
    mean_path = os.path.join(directory, "meanShape.mat")
    if os.path.exists(mean_path):
        mean = _read_mat(mean_path, "points")
        if mean.shape != (nv, 3):
            raise ValueError(
                f"meanShape.mat: `points` must have shape ({nv}, 3), got {mean.shape}."
            )
    else:
        mean = dat["verts"]
    k = n_file if n_components is None else int(n_components)
    if not 0 <= k <= n_file:
        raise ValueError(f"`n_components` must lie in [0, {n_file}], got {n_components}.")
    if not unit_scale > 0:
        raise ValueError(f"`unit_scale` must be positive, got {unit_scale}.")

    centroid = dat["verts"].mean(axis=0) if center else np.zeros(3)
    mean = (mean - centroid) * unit_scale
    basis = evectors[:k].reshape(k, 3, nv).transpose(0, 2, 1)
    stddev = np.sqrt(evalues[:k]) * unit_scale
    total = evalues.sum()
    explained = evalues[:k] / total if total > 0 else np.zeros(k)

    order = _joint_order(dat["parent_ids"])  # model index -> id
    index_of = {jid: n for n, jid in enumerate(order)}
    parents = tuple(
        -1 if dat["parent_ids"][jid - 1] == 0 else index_of[int(dat["parent_ids"][jid - 1])]
        for jid in order
    )
    hs25 = _is_hs25_tree(dat["parent_ids"])
    names = tuple(_HS25_NAMES[jid] if hs25 else f"joint{jid}" for jid in order)

    dense_w = np.zeros((nv, nj))
    np.add.at(
        dense_w,
        (np.repeat(np.arange(nv), dat["skin_ids"].shape[1]), dat["skin_ids"].ravel() - 1),
        dat["skin_w"].ravel(),
    )
    if np.any(dense_w.sum(axis=1) <= 0):
        raise ValueError("model.dat: every vertex needs a positive total skin weight.")
    reg = joint_regressor_from_weights(dense_w, dat["parent_ids"])
    perm = np.asarray([jid - 1 for jid in order])
    reg_idx, reg_w = _sparse_rows(reg[perm])
    dense_w = dense_w[:, perm] / dense_w.sum(axis=1, keepdims=True)
    skin_idx, skin_w = _sparse_rows(dense_w)

    model = SScapeModel(
        mean=mean,
        basis=basis,
        stddev=stddev,
        explained_variance=explained,
        faces=dat["faces"],
        rig=Rig(
            parents=parents,
            joint_names=names,
            skin_indices=skin_idx,
            skin_weights=skin_w,
            regressor_indices=reg_idx,
            regressor_weights=reg_w,
        ),
    )
    if not return_rig:
        return model
    axes = dat["axes"][perm]
    an = np.linalg.norm(axes, axis=1, keepdims=True)
    axes = np.where(an > 1e-8, axes / np.where(an > 1e-8, an, 1.0), 0.0)
    rig = HumanShapeRig(
        ids=np.asarray(order),
        axes=axes,
        file_joint_positions=(dat["positions"][perm] - centroid) * unit_scale,
        centroid=centroid * unit_scale,
        unit_scale=float(unit_scale),
    )
    return model, rig


def humanshape_pose(rig: HumanShapeRig, pose_vector) -> tuple[jnp.ndarray, Similarity]:
    """Converts a humanshape pose vector to `(pose, transform)` for [`bodyprior.sscape.evaluate`][].

    The humanshape vector has `6 + NJ` entries (31 for the released rig), optionally followed by a
    global scale (32 entries): axis-angle global rotation (1:3), translation in file units (4:6),
    then one angle per joint id (entry `6 + id`, 1-based). Joint `j` gets axis-angle
    `theta_{id_j} * axis_j`; the global part becomes `Similarity(s, Rod(r), s * t * unit_scale)`
    (humanshape rotates about the template centroid, the origin of a `center=True` model, and scales
    the posed points last). Differentiable; no validation of joint limits.

    **Returns:** `(pose (J, 3) axis-angle, transform)`.
    """
    nj = rig.ids.shape[0]
    p = check_array(pose_vector, "pose_vector", (None,))
    if p.shape[0] not in (6 + nj, 7 + nj):
        raise ValueError(
            f"`pose_vector` must have {6 + nj} or {7 + nj} entries (with scale), got {p.shape[0]}."
        )
    p = jnp.asarray(p)
    theta = p[6 + rig.ids - 1]
    pose = theta[:, None] * jnp.asarray(rig.axes, dtype=p.dtype)
    s = p[6 + nj] if p.shape[0] == 7 + nj else jnp.ones((), p.dtype)
    transform = Similarity(axis_angle_to_matrix(p[:3]), s * p[3:6] * rig.unit_scale, jnp.log(s))
    return pose, transform


def _default_ids(names: tuple[str, ...]) -> np.ndarray:
    """humanshape ids implied by joint names: the released rig's roles, `"joint<id>"`, else
    model index + 1."""
    nj = len(names)
    if nj == 25 and set(names) == set(_HS25_IDS):
        return np.asarray([_HS25_IDS[n] for n in names])
    if all(n.startswith("joint") and n[5:].isdigit() for n in names):
        ids = [int(n[5:]) for n in names]
        if sorted(ids) == list(range(1, nj + 1)):
            return np.asarray(ids)
    return np.arange(1, nj + 1)


def write_mpii_humanshape(
    directory: str | os.PathLike,
    model: SScapeModel,
    *,
    axes=None,
    ids=None,
    unit_scale: float = MM_TO_M,
) -> None:
    """Writes `model` as a humanshape model directory (`model.dat`, `evectors.mat`, `evalues.mat`,
    `meanShape.mat`, MATLAB v5), the format read by [`bodyprior.sscape.load_mpii_humanshape`][].

    Joint `j` is written with the humanshape id `ids[j]`. By default the ids follow the joint
    names, so that a model read by `load_mpii_humanshape` reads back with the same ids, names and
    joint order: the released rig's roles (`"root"`, `"l_hip_z"`, ...; all 25) map to their
    humanshape ids, names `"joint<id>"` to `id`, and any other naming to model index + 1 (the
    reader then names joints `"joint<id>"`, or by role if the tree is the released rig's). The
    reader orders joints depth-first from the root (children by ascending id), so the model's
    joint order must be that order of the written ids. The `NS` influence pairs are the model's
    sparse skin weights (zero-weight slots written as humanshape's `1 0` padding; weights written
    to full precision). Written joint positions are the mean's rest joints (humanshape ignores
    them). The model's joint regressor is **not** stored: humanshape recomputes joints from
    skin-weight overlaps, so a reloaded model has that regressor. `evalues` are
    `(stddev / unit_scale)**2`.

    **Arguments:**

    - `directory`: output folder (created if missing).
    - `model`: the model to export.
    - `axes`: optional hinge axes `(J, 3)` (e.g. `rig.axes` of a loaded model); default zeros.
    - `ids`: optional humanshape 1-based joint ids `(J,)`, a permutation of `1..J` (e.g.
      `rig.ids` of a loaded model); default from the joint names, as above.
    - `unit_scale`: metres per file unit (default 1e-3: files in mm).

    **Raises:** `ValueError` for a wrong `model`, `axes` or `ids`, or a joint order that would not
    read back unchanged.
    """
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")
    nj, nv = model.n_joints, model.n_vertices
    axes = (
        np.zeros((nj, 3))
        if axes is None
        else np.asarray(check_array(axes, "axes", (nj, 3)), np.float64)
    )
    if ids is None:
        ids = _default_ids(tuple(model.joint_names))
    else:
        ids = np.asarray(check_array(ids, "ids", (nj,), integer=True)).astype(np.int64)
        if sorted(ids.tolist()) != list(range(1, nj + 1)):
            raise ValueError(
                f"`ids` must be a permutation of 1..{nj} (humanshape's 1-based joint ids), got "
                f"{ids.tolist()}."
            )
    if any(p >= j for j, p in enumerate(model.parents) if j > 0):
        raise ValueError(
            "`model.parents` must list parents before children to be written as model.dat."
        )
    parent_ids = np.zeros(nj, np.int64)  # indexed by id - 1, as in model.dat
    for j, p in enumerate(model.parents):
        parent_ids[ids[j] - 1] = 0 if p < 0 else ids[p]
    if _joint_order(parent_ids) != ids.tolist():
        raise ValueError(
            "The model's joint order is not the depth-first order (children by ascending id) of "
            f"its humanshape ids {ids.tolist()}, so it would not read back in the same order; "
            "pass `ids` that number the joints in that order."
        )
    directory = os.fspath(directory)
    os.makedirs(directory, exist_ok=True)
    mean = np.asarray(model.mean, np.float64) / unit_scale
    basis = np.asarray(model.basis, np.float64)
    k = basis.shape[0]
    skin_idx = np.asarray(model.skin_indices)
    skin_w = np.asarray(model.skin_weights, np.float64)
    skin_ids = np.where(skin_w > 0, ids[skin_idx], 1)
    skin_w = np.where(skin_w > 0, skin_w, 0.0)
    joints = np.asarray(model.rest_joints(model.mean), np.float64) / unit_scale
    faces = np.asarray(model.faces)
    lines = [f"{nv} {faces.shape[0]} {nj} {skin_idx.shape[1]}"]
    for v in range(nv):
        pairs = " ".join(
            f"{skin_ids[v, i]} {float(skin_w[v, i])!r}" for i in range(skin_idx.shape[1])
        )
        lines.append(f"{mean[v, 0]:f} {mean[v, 1]:f} {mean[v, 2]:f} {pairs}")
    lines += [f"{a} {b} {c}" for a, b, c in faces]
    for j in np.argsort(ids):
        a, q = axes[j], joints[j]
        lines.append(
            f"{ids[j]} {float(a[0])!r} {float(a[1])!r} {float(a[2])!r} "
            f"{q[0]:f} {q[1]:f} {q[2]:f} {parent_ids[ids[j] - 1]}"
        )
    with open(os.path.join(directory, "model.dat"), "w") as f:
        f.write("\n".join(lines) + "\n")
    evectors = basis.transpose(0, 2, 1).reshape(k, 3 * nv)
    evalues = (np.asarray(model.stddev, np.float64) / unit_scale) ** 2
    scipy.io.savemat(os.path.join(directory, "evectors.mat"), {"evectors": evectors})
    scipy.io.savemat(os.path.join(directory, "evalues.mat"), {"evalues": evalues[None, :]})
    scipy.io.savemat(os.path.join(directory, "meanShape.mat"), {"points": mean})
