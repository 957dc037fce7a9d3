"""The shipped PanoMan model and what reconstruction from joints needs beside it.

A [`bodyprior.panoman.PanoManKit`][] is a trained [`bodyprior.panoman.PanoManModel`][]
with the two pieces that reconstruction from sparse constraints (paper §5) fits on the same
training set: the posed **joint regressor** (joint constraints on PanoMan's vertices) and the
**LBS model** on the same shape space (the IK initialisation).
[`bodyprior.panoman.reconstruct`][] runs the whole §5 pipeline on one frame: IK of the LBS model
to the joints and points, then `fit_panoman` from the IK mesh (block coordinate descent face →
body → hand).

**The shipped kit** ([`bodyprior.panoman.default_panoman`][],
`bodyprior/assets/panoman_male.npz`, float16 MLP weights) is the model measured on
docs/results_panoman.md (the reduced run: the full sizes of the issue take hours on 2 cores). It
is trained by [`bodyprior.panoman.build_default_panoman`][] with [`bodyprior.panoman.RECIPE`][]:

- male identities from [`bodyprior.sample_population`][] (10 shape PCs from 1,000 rest bodies);
- H_B: 100 identities × 20 frames of the CMU mocap clips ([`bodyprior.find_mocap_dir`][]), 80 %
  of the clips (whole clips, seed 0; the other 20 % are the results page's test clips), posed by
  twist-distributed skinning; H_F: 20 identities × 39 expressions; H_H: 100 identities × 20
  gestures: 2,000 / 780 / 2,000 meshes on the 6,449-vertex decimated topology;
- K = 150 / 50 / 30 SPLOCS components (body / face / hand), 5 iterations; correction MLP 1,500
  hidden units with a rank-256 output on the body components' edges, β MLP, 3,000 steps each.

Its metadata records that recipe, the checksums of the default-body assets and of every BVH file
it was trained on, the training record and the rebuild command (`python -m
bodyprior.panoman.build_model`, about 8 minutes on 2 cores); the payload checksum is verified on
load.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._body import load_default_body
from .._solution import RESULTS, Solution
from .._topology import Topology
from .._validate import check_array, check_positive_int
from ..registration import template_sources
from ._data import PanomanData, make_panoman_data
from ._fit import (
    JointRegressor,
    LbsModel,
    PanoManSolver,
    fit_joint_regressor,
    fit_lbs,
    fit_panoman,
    make_lbs_model,
)
from ._model import PanoManModel, _model_arrays, _model_from, _read_npz, _write_npz, train_panoman
from ._solve import shell_constraints

__all__ = [
    "RECIPE",
    "PanoManKit",
    "TrainingSplit",
    "build_default_panoman",
    "default_panoman",
    "load_kit",
    "make_kit",
    "make_training_split",
    "reconstruct",
    "save_kit",
    "train_split",
]

KIT_FILE = "panoman_male.npz"
_REBUILD = "rebuild it with `python -m bodyprior.panoman.build_model`"

RECIPE = dict(
    seed=0, sex=0, mesh="decimated", test_fraction=0.2, n_body_ids=100, poses_per_id=20,
    n_face_ids=20, n_hand_ids=100, gestures_per_id=20, n_shape_rest=1000, k=(150, 50, 30),
    splocs_iter=5, mlp_hidden=1500, rank=256, mlp_steps=3000,
)  # fmt: skip
"""The shipped kit's training recipe (the reduced run of `experiments/panoman.py`)."""


# --------------------------------------------------------------------------------------------------
# the training set of a run


class TrainingSplit(NamedTuple):
    """What [`bodyprior.panoman.make_training_split`][] returns: `train` / `test`
    ([`bodyprior.panoman.PanomanData`][], disjoint clips and identities), `shape_rest`
    `(N, V, 3)` rest bodies for the shape PCA, `topology`, `vertex_map` `(V,)` (into the full
    mesh), `faces`, the `cmu_mb` `body` (facial actions and local changes) and the `game_engine`
    `hand_body`, the training key `model_key`, and `test_clips`, the names of the held-out
    clips (never trained on)."""

    train: PanomanData | None
    test: PanomanData | None
    shape_rest: np.ndarray | None
    topology: Topology
    vertex_map: np.ndarray
    faces: np.ndarray
    body: object
    hand_body: object
    model_key: jax.Array
    test_clips: tuple[str, ...]


def make_training_split(
    mocap_dir: str | os.PathLike,
    *,
    seed: int = 0,
    sex: int = 0,
    mesh: str = "decimated",
    test_fraction: float = 0.2,
    n_body_ids: int,
    poses_per_id: int,
    n_face_ids: int,
    n_hand_ids: int,
    gestures_per_id: int,
    n_shape_rest: int,
    n_test_ids: int = 0,
    test_poses: int = 0,
    n_expressions: int = 39,
    train: bool = True,
    progress: bool = True,
    **_ignored,
) -> TrainingSplit:
    """The open-data training and test sets of a PanoMan run (panoman_v2 §3), from a seed.

    The mocap clips under `mocap_dir` are split by clip (`test_fraction` of them held out, seed
    `seed`); `train` poses `n_body_ids × poses_per_id` body meshes of training clips on fresh
    identities of sex `sex` (0 male, 1 female), plus `n_face_ids × n_expressions` expressions
    (the first `n_expressions` of [`bodyprior.panoman.expression_set`][], default 39) and
    `n_hand_ids × gestures_per_id` gestures; `test` poses `n_test_ids × test_poses` body meshes of
    the held-out clips on other identities (`None` if `n_test_ids` or `test_poses` is 0).
    `shape_rest`: the first `n_shape_rest` rest bodies of that sex from
    [`bodyprior.sample_population`][]. `mesh`: `"decimated"` (6,449 vertices) or `"full"`
    (13,380). Keys: `jax.random.key(seed)` split into
    train, test, model and shape keys (the experiment and the shipped kit use the same split).
    `train=False` makes only the test set (`train` and `shape_rest` are `None`: to evaluate a
    trained model on its held-out clips). Extra keyword arguments (a recipe's training fields) are
    ignored."""
    from .._mocap import load_mocap, split_by_clip
    from .._population import sample_population
    from ..assets._decimate import load_decimated

    if mesh not in ("decimated", "full"):
        raise ValueError(f"`mesh` must be 'decimated' or 'full', got {mesh!r}.")
    _sex_name(sex)
    if not os.path.isdir(os.fspath(mocap_dir)):
        raise ValueError(f"`mocap_dir`: {os.fspath(mocap_dir)!r} is not a folder of BVH clips.")
    poses = load_mocap(os.fspath(mocap_dir), progress=progress)
    train_poses, test_poses_ = split_by_clip(poses, test_fraction, seed=seed)
    if mesh == "decimated":
        vm, faces = load_decimated()
    else:
        body0 = load_default_body()
        vm, faces = np.arange(body0.n_vertices), np.asarray(body0.faces)
    vm, faces = np.asarray(vm), np.asarray(faces)
    top = Topology.from_faces(faces)
    body = load_default_body("cmu_mb", local_changes=True, facial_actions=True)
    hand_body = load_default_body("game_engine", local_changes=True)
    k_train, k_test, k_model, k_shape = jax.random.split(jax.random.key(seed), 4)
    common = dict(sex=sex, vertex_map=vm, body=body, hand_body=hand_body, progress=progress)
    train_set = None
    if train:
        train_set = make_panoman_data(
            k_train, train_poses, n_body_identities=n_body_ids, poses_per_identity=poses_per_id,
            n_face_identities=n_face_ids, n_expressions=n_expressions,
            n_hand_identities=n_hand_ids, gestures_per_identity=gestures_per_id, **common,
        )  # fmt: skip
    test = None
    if n_test_ids and test_poses:
        test = make_panoman_data(
            k_test, test_poses_, n_body_identities=n_test_ids, poses_per_identity=test_poses,
            n_face_identities=0, n_hand_identities=0, gestures_per_identity=0, **common,
        )  # fmt: skip
    shape_rest = None
    if train:  # shape PCA on many rest bodies of this sex (eq. 2; the paper: SMPL's 10 PCs)
        pop = sample_population(2 * n_shape_rest, key=k_shape, body=body, pose_jitter_deg=0.0,
                                progress=progress)  # fmt: skip
        keep = np.flatnonzero(np.asarray(pop.sex) == sex)[:n_shape_rest]
        shape_rest = np.asarray(pop.vertices)[keep][:, vm]
    held_out = np.unique(np.asarray(test_poses_.clip))
    test_clips = tuple(sorted(str(test_poses_.clip_names[i]) for i in held_out))
    return TrainingSplit(train_set, test, shape_rest, top, vm, faces, body, hand_body, k_model,
                         test_clips)  # fmt: skip


def train_split(split: TrainingSplit, *, k, splocs_iter, mlp_hidden, rank, mlp_steps,
                progress: bool = True, **_ignored) -> Solution:  # fmt: skip
    """[`bodyprior.panoman.train_panoman`][] on `split.train` with a recipe's training fields
    (`k` components per part, SPLOCS iterations, correction MLP hidden units and output rank, MLP
    steps for both MLPs)."""
    return train_panoman(
        split.train, split.topology, key=split.model_key, n_components=tuple(k),
        shape_rest=split.shape_rest, splocs_iterations=splocs_iter, correction_hidden=mlp_hidden,
        correction_rank=rank, correction_steps=mlp_steps, beta_steps=mlp_steps, progress=progress,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------------
# the kit


class PanoManKit(eqx.Module):
    """A trained PanoMan model with what reconstruction needs (module docstring).

    - `model`: the [`bodyprior.panoman.PanoManModel`][] (vertices `(V, 3)` in metres).
    - `regressor`: the posed joint regressor `(J, M)` of the `cmu_mb` joints on the model's
      vertices ([`bodyprior.panoman.fit_joint_regressor`][] on the training body meshes).
    - `lbs`: the LBS model on the model's shape space ([`bodyprior.panoman.make_lbs_model`][]),
      the IK initialisation.
    - `vertex_map` `(V,)`: the model's vertices in the full 13,380-vertex default mesh.
    - `joint_names`: the `cmu_mb` joint names, in the order of `joints` arguments; `info`: JSON
      provenance (recipe, data checksums, training record).
    """

    model: PanoManModel
    regressor: JointRegressor
    lbs: LbsModel
    vertex_map: Int[Array, " V"]
    joint_names: tuple[str, ...] = eqx.field(static=True)
    info: str = eqx.field(static=True, default="{}")

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def info_dict(self) -> dict:
        return json.loads(self.info)


def make_kit(
    model: PanoManModel, data: PanomanData, body=None, *, info: dict | None = None
) -> PanoManKit:
    """The kit of `model` trained on `data`: the joint regressor fitted on its body meshes and
    their exact joints, the LBS model's rest joints regressed on α from its identities. `body`:
    the `cmu_mb` [`bodyprior.DefaultBody`][] (loaded if omitted); `info`: provenance to record."""
    if body is None:
        body = load_default_body("cmu_mb")
    sel = np.flatnonzero(np.asarray(data.kind) == 0)
    if sel.size == 0:
        raise ValueError("`data` has no body meshes (kind 0) to fit the joint regressor on.")
    reg = fit_joint_regressor(np.asarray(data.vertices)[sel], np.asarray(data.joints)[sel])
    lbsm = make_lbs_model(model, data, body)
    return PanoManKit(
        model=model,
        regressor=reg,
        lbs=lbsm,
        vertex_map=jnp.asarray(np.asarray(data.vertex_map), jnp.int32),
        joint_names=tuple(body.joint_names),
        info=json.dumps(info or {}, default=float),
    )


def _payload_checksum(arrays: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(a.dtype.str.encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_kit(kit: PanoManKit, path: str | os.PathLike, *, float16: bool = True) -> None:
    """Writes `kit` to one `.npz` file atomically: the model as
    [`bodyprior.panoman.save_panoman`][] writes it (so `load_panoman` reads the model part), plus
    the regressor and the LBS model, the provenance and a payload checksum. `float16`: MLP weights
    and component values in float16 (the shipped kit)."""
    arrays, meta = _model_arrays(kit.model, float16)
    lb = kit.lbs
    arrays.update({
        "kit.regressor_indices": np.asarray(kit.regressor.indices, np.int32),
        "kit.regressor_weights": np.asarray(kit.regressor.weights, np.float64),
        "kit.joint_mean": np.asarray(lb.joint_mean, np.float64),
        "kit.joint_basis": np.asarray(lb.joint_basis, np.float64),
        "kit.skin_indices": np.asarray(lb.skin_indices, np.int32),
        "kit.skin_weights": np.asarray(lb.skin_weights, np.float64),
        "kit.parents": np.asarray(lb.parents, np.int32),
        "kit.vertex_map": np.asarray(kit.vertex_map, np.int32),
    })  # fmt: skip
    meta["kit"] = dict(joint_names=list(kit.joint_names), info=kit.info,
                       payload_sha256=_payload_checksum(arrays))  # fmt: skip
    _write_npz(path, arrays, meta)


def load_kit(path: str | os.PathLike) -> PanoManKit:
    """Reads a kit written by [`bodyprior.panoman.save_kit`][] (validated: format, version,
    payload checksum, shapes; a `ValueError` says what is wrong)."""
    path = os.fspath(path)
    z, meta = _read_npz(path, "PanoMan kit")
    km = meta.get("kit")
    if km is None:
        raise ValueError(
            f"{path!r} holds a model without a kit (written by save_panoman): load it with "
            "load_panoman, or write it with save_kit."
        )
    if _payload_checksum(z) != km.get("payload_sha256"):
        raise ValueError(f"{path!r} is corrupted: its payload checksum does not match.")
    try:
        model = _model_from(z, meta, path)
        names = tuple(km["joint_names"])
        J, V = len(names), model.topology.n_vertices
        shapes = {"kit.joint_mean": (J, 3), "kit.parents": (J,), "kit.vertex_map": (V,)}
        for k, shp in shapes.items():
            if z[k].shape != shp:
                raise ValueError(f"{path!r}: `{k}` has shape {z[k].shape}, expected {shp}.")
        lbs = LbsModel(
            shape_mean=model.shape_mean,
            shape_basis=model.shape_basis,
            joint_mean=jnp.asarray(z["kit.joint_mean"]),
            joint_basis=jnp.asarray(z["kit.joint_basis"]),
            skin_indices=jnp.asarray(z["kit.skin_indices"]),
            skin_weights=jnp.asarray(z["kit.skin_weights"]),
            parents=tuple(int(p) for p in z["kit.parents"]),
        )
        reg = JointRegressor(jnp.asarray(z["kit.regressor_indices"]),
                             jnp.asarray(z["kit.regressor_weights"]))  # fmt: skip
    except KeyError as e:
        raise ValueError(f"{path!r} is not a complete PanoMan kit: missing {e}.") from e
    return PanoManKit(model, reg, lbs, jnp.asarray(z["kit.vertex_map"]), names,
                      info=str(km.get("info", "{}")))  # fmt: skip


_SEX_NAMES = ("male", "female")  # index = the `sex` code of the population and the recipe


def _sex_name(sex: int) -> str:
    """The name of the `sex` code 0 / 1 (`ValueError` otherwise)."""
    if sex not in (0, 1):
        raise ValueError(f"`sex` must be 0 (male) or 1 (female), got {sex!r}.")
    return _SEX_NAMES[int(sex)]


def _check_sex(sex: str) -> str:
    if sex not in _SEX_NAMES:
        raise ValueError(f"`sex` must be 'male' or 'female', got {sex!r}.")
    return sex


def kit_path(sex: str = "male") -> str:
    """Path of the PanoMan kit of `sex`: the male kit ships with the package
    (`bodyprior/assets/panoman_male.npz`); the female kit (the same recipe on female identities) is
    built on the user's machine by `python -m bodyprior.panoman.build_model --sex female` into
    `$BODYPRIOR_DATA` (default `$XDG_DATA_HOME/bodyprior` or `~/.local/share/bodyprior`) as
    `panoman_female.npz`: a second 23 MiB asset in every install and in the repository's history
    for a model that a command rebuilds in ~6 minutes."""
    if _check_sex(sex) == "male":
        from ..assets import asset_path

        return os.path.join(os.path.dirname(asset_path()), KIT_FILE)
    root = os.environ.get("BODYPRIOR_DATA") or os.path.join(
        os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share"),
        "bodyprior",
    )
    return os.path.join(os.path.abspath(os.path.expanduser(root)), "panoman_female.npz")


def default_panoman(
    *, sex: str = "male", return_info: bool = False
) -> PanoManKit | tuple[PanoManKit, dict]:
    """The default PanoMan kit of `sex` (module docstring): a model on the 6,449-vertex decimated
    topology with its joint regressor and LBS initialiser; `"male"` ships, `"female"` is built once
    by `python -m bodyprior.panoman.build_model --sex female` (see
    [`bodyprior.panoman.kit_path`][]).
    `return_info=True` also returns its provenance dict. Loading takes about 2 s (the decoder's
    factorisation).

    **Raises:** `ValueError` if `sex` is not `"male"` / `"female"`, or the file is missing or
    corrupted (the message gives the command that builds it)."""
    path = kit_path(sex)
    if not os.path.exists(path):
        if sex == "male":
            raise ValueError(f"the shipped PanoMan kit is missing at {path!r}; {_REBUILD}.")
        raise ValueError(
            f"no female PanoMan kit at {path!r}: build it once (about 6 minutes on 2 cores) with "
            "`python -m bodyprior.panoman.build_model --sex female`."
        )
    kit = load_kit(path)
    info = kit.info_dict()
    if info.get("sources") not in (None, template_sources()):
        warnings.warn(
            f"{path!r} was trained on other default-body assets than the installed ones; "
            f"{_REBUILD}.",
            stacklevel=2,
        )
    return (kit, info) if return_info else kit


def build_default_panoman(
    path: str | None = None, *, mocap_dir=None, progress: bool = True, log=print, **overrides
) -> dict:
    """Trains the shipped kit with [`bodyprior.panoman.RECIPE`][] (`overrides`: its fields, for
    quick checks) on the CMU clips under `mocap_dir` (default [`bodyprior.find_mocap_dir`][]) and
    writes it atomically to `path` (default: [`bodyprior.panoman.kit_path`][] of the recipe's
    sex: the shipped location for `sex=0`), float16. **Returns:** the provenance dict.

    **Raises:** `ValueError` if no mocap folder is found or an override is not a recipe field."""
    from .._mocap import find_mocap_dir, mocap_checksums

    bad = sorted(set(overrides) - set(RECIPE))
    if bad:
        raise ValueError(f"unknown recipe fields {bad}; the recipe has {sorted(RECIPE)}.")
    recipe = dict(RECIPE, **overrides)
    sex = _sex_name(recipe["sex"])
    root = mocap_dir if mocap_dir is not None else find_mocap_dir()
    if root is None or not os.path.isdir(os.fspath(root)):
        raise ValueError(
            "`mocap_dir`: no CMU mocap folder found; pass --mocap DIR or set $BODYPRIOR_MOCAP_DIR."
        )
    path = os.path.abspath(path or kit_path(sex))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    t0 = time.perf_counter()
    split = make_training_split(root, progress=progress, **recipe)
    sol = train_split(split, progress=progress, **recipe)
    info = {
        "built_by": "bodyprior.panoman.build_default_panoman "
        "(python -m bodyprior.panoman.build_model [--mocap DIR])",
        "recipe": {k: (list(v) if isinstance(v, tuple) else v) for k, v in recipe.items()},
        "data": {"counts": split.train.counts(), "n_vertices": split.topology.n_vertices,
                 "bvh": mocap_checksums(root), "test_clips": list(split.test_clips)},  # fmt: skip
        "training": {k: sol.stats[k] for k in ("shape_explained", "fit_rla_error", "correction",
                                               "beta_mlp")},  # fmt: skip
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "sources": template_sources(),
    }
    info["build_seconds"] = round(time.perf_counter() - t0, 1)  # training; the kit fit is seconds
    kit = make_kit(sol.value, split.train, split.body, info=info)
    save_kit(kit, path, float16=True)
    # what float16 storage costs: eq. 5 decoded at the projections of 4 training body meshes by
    # the trained (float32) model and by the stored one
    info["float16_cost_mm"] = _float16_cost(sol.value, load_kit(path).model, split.train)
    save_kit(make_kit(sol.value, split.train, split.body, info=info), path, float16=True)
    log(f"{path}: PanoMan kit, {split.train.counts()} meshes, K = {tuple(recipe['k'])} "
        f"({info['build_seconds']} s, {os.path.getsize(path) / 2**20:.1f} MiB)")  # fmt: skip
    return info


def _float16_cost(model: PanoManModel, stored: PanoManModel, data: PanomanData, n: int = 4):
    from ._model import evaluate

    body = np.flatnonzero(np.asarray(data.kind) == 0)
    idx = body[:: max(1, body.size // n)][:n]
    d = []
    for i in idx:
        v = np.asarray(data.vertices[i], np.float64)
        alpha = model.shape_coefficients(np.asarray(data.rest[int(data.identity[i])], np.float64))
        beta = model.motion_coefficients(v, alpha)
        a = np.asarray(evaluate(model, alpha, beta, align_to=v).value.vertices)
        b = np.asarray(evaluate(stored, alpha, beta, align_to=v).value.vertices)
        d.append(1e3 * np.linalg.norm(a - b, axis=1))
    d = np.concatenate(d)
    return {"meshes": int(len(idx)), "mean": round(float(d.mean()), 4),
            "max": round(float(d.max()), 4)}  # fmt: skip


# --------------------------------------------------------------------------------------------------
# reconstruction of one frame


def reconstruct(
    kit: PanoManKit,
    joints: Float[ArrayLike, "J 3"] | None = None,
    points: tuple[ArrayLike, ArrayLike] | None = None,
    *,
    joint_weights: Float[ArrayLike, " J"] | None = None,
    max_steps: int = 5,
    correct: bool = True,
    blocks: tuple[str, ...] = ("face", "body", "hand"),
    solver: PanoManSolver | None = None,
) -> Solution:
    """A full body from sparse 3-D constraints (paper §5), as docs/results_panoman.md measures it.

    1. IK: the kit's LBS model ([`bodyprior.panoman.fit_lbs`][]) fitted to the joints (exact FK
       joints of the `cmu_mb` skeleton) and the points;
    2. [`bodyprior.panoman.fit_panoman`][] from the IK mesh (its RLA projection's β, the IK α),
       the joints through the kit's posed regressor, `max_steps` LM iterations per block.

    **Arguments:**

    - `joints`: `(J, 3)` metres, the `cmu_mb` joints in `kit.joint_names` order (world frame:
      Z up, the body facing −Y); `joint_weights` `(J,)` ≥ 0 (0 drops a joint; default all 1).
    - `points`: `(index (H,), position (H, 3))`, vertex handles on the model's vertices (indices
      into its `V` vertices, metres), e.g. markers or feature points.
    - `correct`: with the correction MLP (eq. 5); `False` is the eq. 4 baseline. `blocks`,
      `solver`: as `fit_panoman` (pass a prepared solver to reuse it across frames).

    At least one of `joints` and `points` is needed. **Returns:** a [`bodyprior.Solution`][] whose
    `value` is a [`bodyprior.panoman.PanoManFit`][] (vertices `(V, 3)` m) and `stats` are
    `fit_panoman`'s plus `ik` (`alpha`, `pose` `(J, 3)` axis-angle, `translation`, `vertices`,
    `joints`, `steps`, `seconds`). On held-out frames of the reduced run (31 joints + 10 torso
    points) the mean vertex error was 14.8 mm against 17.5 mm for the IK mesh alone.
    """
    if not isinstance(kit, PanoManKit):
        raise ValueError(f"`kit` must be a PanoManKit (pm.default_panoman()), got {type(kit)}.")
    check_positive_int(max_steps, "max_steps")
    J, V = kit.n_joints, kit.model.topology.n_vertices
    if joints is None and points is None:
        raise ValueError("reconstruct needs `joints` (J, 3) and/or `points` (index, position).")
    if points is not None:
        if not isinstance(points, (tuple, list)) or len(points) != 2:
            raise ValueError("`points` must be a pair (index (H,), position (H, 3)).")
        hidx = np.asarray(points[0])
        if hidx.ndim != 1 or not np.issubdtype(hidx.dtype, np.integer):
            raise ValueError(f"`points[0]` must be integer vertex indices (H,), got {hidx.shape}.")
        if hidx.size and (hidx.min() < 0 or hidx.max() >= V):
            raise ValueError(f"`points[0]` indices must lie in [0, {V}).")
        hpos = check_array(np.asarray(points[1], np.float64), "points[1]", (hidx.size, 3))
        if joints is None and hidx.size == 0:
            raise ValueError("`points` is empty and no `joints` are given: nothing to fit.")
    else:
        hidx, hpos = np.zeros(0, np.int32), np.zeros((0, 3))
    if joints is not None:
        gj = check_array(np.asarray(joints, np.float64), "joints", (J, 3))
        jw = np.ones(J) if joint_weights is None else np.asarray(joint_weights, np.float64)
        check_array(jw, "joint_weights", (J,))
        if np.any(jw < 0):
            raise ValueError("`joint_weights` must be >= 0.")
    else:
        gj, jw = np.zeros((J, 3)), np.zeros(J)
    gjw = gj * (jw > 0)[:, None]
    handles = (hidx, hpos) if hidx.size else None
    cl = shell_constraints(handles=handles,
                           joints=(np.arange(J)[:, None], np.ones((J, 1)), gjw, jw))  # fmt: skip
    ik = fit_lbs(kit.lbs, cl)
    alpha0, pose0, trans0 = ik.value
    cp = shell_constraints(
        handles=handles,
        joints=(np.asarray(kit.regressor.indices), np.asarray(kit.regressor.weights), gjw, jw),
    )
    v_ik = np.asarray(ik.stats["vertices"])
    fit = fit_panoman(
        kit.model, cp, init=(np.asarray(alpha0), *kit.model.neutral()), init_mesh=v_ik,
        correct=correct, solver=solver, max_steps=max_steps, blocks=blocks,
    )  # fmt: skip
    stats = dict(fit.stats)
    stats["ik"] = dict(alpha=alpha0, pose=pose0, translation=trans0, vertices=ik.stats["vertices"],
                       joints=ik.stats["joints"], steps=ik.stats["steps"],
                       seconds=ik.stats["seconds"])  # fmt: skip
    result = fit.result if ik.result == RESULTS.successful else ik.result
    return Solution(fit.value, result, stats)
