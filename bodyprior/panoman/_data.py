"""PanoMan's training set on the default body, from open data (panoman_v2 §3).

The paper trains on DFAUST/SURREAL body poses, FaceWarehouse expressions and MANO gestures; none is
open here, so [`bodyprior.panoman.make_panoman_data`][] builds their stand-ins on population
identities (`sample_population` at the exact rest posture):

- **H_B body poses**: CMU motion capture retargeted to `cmu_mb`
  ([`bodyprior.load_mocap`][]), root orientation dropped, posed by **twist-distributed skinning**
  (`evaluate(..., skinning="twist")`), not plain LBS, so the data carry no candy-wrapper collapse.
- **H_F facial expressions**: the same 39 expression vectors of the 51 facial-action targets with
  body support (`tongueOut` has none) on every identity: 12 single units at weight 1 and 27 sparse
  combinations (3–6 units, weights U(0.3, 1), left/right mirrored with p = ½), drawn once from a
  fixed seed, as the paper transfers the same 39 FaceWarehouse expressions.
- **H_H hand gestures**: `game_engine` finger rotations within anatomical limits (MCP −20…90°
  flexion and ±20° abduction, PIP 0…110°, DIP ⅔ PIP; thumb CMC ±40°, MCP 0…60°, IP −10…80°): six
  canonical gestures (flat, fist, point, OK, pinch, spread) and random ones, body at rest (LBS:
  the rig's knuckle artefacts enter the data, as MANO's do).

Each mesh has one kind of motion; its RLA is relative to its identity's exact rest mesh.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int
from tqdm.auto import tqdm

from .._body import DefaultBody, evaluate, load_default_body, phenotype_vector, rest_shape
from .._mocap import PoseSet, rig_pose
from .._population import sample_phenotypes
from .._validate import check_array, check_positive_int

__all__ = [
    "CANONICAL_GESTURES",
    "KINDS",
    "PanomanData",
    "expression_set",
    "gesture_poses",
    "make_panoman_data",
]

KINDS = ("body", "face", "hand")  # kind codes 0, 1, 2
FINGERS = ("thumb", "index", "middle", "ring", "pinky")
CANONICAL_GESTURES = ("flat", "fist", "point", "ok", "pinch", "spread")


class PanomanData(eqx.Module):
    """Meshes of H = H_B ∪ H_F ∪ H_H with their labels (N meshes, I identities, V vertices).

    - `vertices` `(N, V, 3)` float32, metres: the posed/expressive meshes.
    - `identity` `(N,)` int: row of `rest` each mesh is relative to; `kind` `(N,)` int: index into
      `KINDS` (0 body pose, 1 expression, 2 gesture).
    - `body_pose` `(N, J, 3)`: `cmu_mb` axis-angle pose of body meshes (zeros for others), radians.
    - `clip` `(N,)` int: mocap clip of body meshes, `-1` otherwise (names in `clip_names`).
    - `expression` `(N,)` int: row of `expression_weights`, `-1` for non-face meshes;
      `expression_weights` `(X, 52)` facial-action weights.
    - `hand_pose` `(N, Jg, 3)`: `game_engine` axis-angle pose of gesture meshes (zeros otherwise).
    - `joints` `(N, J, 3)`: the exact `cmu_mb` joints of every mesh (forward kinematics; the rest
      joints for expressions and gestures, whose body is at rest), metres.
    - `rest` `(I, V, 3)`: the identities' exact rest meshes; `rest_joints` `(I, J, 3)` their rest
      `cmu_mb` joints; `phenotypes` `(I, 11)`,
      `local_changes` `(I, C)`, `sex` `(I,)` (0 male, 1 female).
    - `vertex_map`: `(V,)` indices into the full default body's vertices (the identity map on
      the full mesh; the decimated topology's `vertex_map` otherwise).
    """

    vertices: Float[Array, "N V 3"]
    identity: Int[Array, " N"]
    kind: Int[Array, " N"]
    body_pose: Float[Array, "N J 3"]
    clip: Int[Array, " N"]
    expression: Int[Array, " N"]
    expression_weights: Float[Array, "X A"]
    hand_pose: Float[Array, "N Jg 3"]
    joints: Float[Array, "N J 3"]
    rest: Float[Array, "I V 3"]
    rest_joints: Float[Array, "I J 3"]
    phenotypes: Float[Array, "I 11"]
    local_changes: Float[Array, "I C"]
    sex: Int[Array, " I"]
    vertex_map: Int[Array, " V"]
    clip_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def n_meshes(self) -> int:
        return int(self.vertices.shape[0])

    def counts(self) -> dict[str, int]:
        """Meshes per kind, e.g. `{"body": 6000, "face": 3900, "hand": 6000}`."""
        k = np.asarray(self.kind)
        return {name: int((k == i).sum()) for i, name in enumerate(KINDS)}

    def subset(self, index) -> PanomanData:
        """The meshes at `index` (host index array or mask); identities are kept."""
        index = np.asarray(index)
        return eqx.tree_at(
            lambda d: tuple(getattr(d, f) for f in _PER_MESH),
            self,
            tuple(jnp.asarray(np.asarray(getattr(self, f))[index]) for f in _PER_MESH),
        )


_PER_MESH = ("vertices", "identity", "kind", "body_pose", "clip", "expression", "hand_pose",
             "joints")  # fmt: skip


# --------------------------------------------------------------------------------------------------
# expressions


_MIRROR = (("Left", "Right"), ("Right", "Left"))


def expression_set(face_labels: tuple[str, ...], n: int = 39, *, seed: int = 0) -> np.ndarray:
    """The fixed expression vectors of H_F: `(n, A)` weights in [0, 1] over `face_labels`.

    The first `min(12, n)` are single units at weight 1 (spread over brows, eyes, cheeks, jaw and
    mouth); the rest are sparse combinations of 3–6 units with weights U(0.3, 1), each unit
    mirrored to its left/right partner with probability ½. `tongueOut` (no body-vertex support) is
    never used. Deterministic in `seed`.
    """
    n = check_positive_int(n, "n")
    A = len(face_labels)
    usable = [i for i, name in enumerate(face_labels) if name != "tongueOut"]
    index = {name: i for i, name in enumerate(face_labels)}
    singles = [
        "browInnerUp",
        "browDownLeft",
        "eyeBlinkLeft",
        "eyeWideRight",
        "cheekPuff",
        "cheekSquintLeft",
        "jawOpen",
        "jawLeft",
        "mouthSmileLeft",
        "mouthFunnel",
        "mouthPucker",
        "mouthFrownRight",
    ]
    singles = [index[s] for s in singles if s in index]
    rng = np.random.default_rng(seed)
    W = np.zeros((n, A), np.float64)
    for k in range(n):
        if k < len(singles):
            W[k, singles[k]] = 1.0
            continue
        units = rng.choice(usable, size=int(rng.integers(3, 7)), replace=False)
        for u in units:
            w = rng.uniform(0.3, 1.0)
            W[k, u] = max(W[k, u], w)
            name = face_labels[u]
            if rng.random() < 0.5:
                for a, b in _MIRROR:
                    if a in name and name.replace(a, b) in index:
                        m = index[name.replace(a, b)]
                        W[k, m] = max(W[k, m], w)
    return W


# --------------------------------------------------------------------------------------------------
# hand gestures

# (low, high) degrees per joint: MCP flexion/abduction, PIP flexion; DIP = 2/3 PIP. Thumb: CMC,
# MCP, IP flexion (CMC also abducts).
_LIMITS = {
    "mcp_flex": (-20.0, 90.0),
    "mcp_abd": (-20.0, 20.0),
    "pip": (0.0, 110.0),
    "thumb_cmc": (-40.0, 40.0),
    "thumb_mcp": (0.0, 60.0),
    "thumb_ip": (-10.0, 80.0),
}


def _gesture_angles(name: str) -> dict[str, tuple[float, float, float, float]]:
    """Per finger `(flex_1, abd_1, flex_2, flex_3)` degrees of a canonical gesture."""
    straight = (0.0, 0.0, 0.0, 0.0)
    curled = (85.0, 0.0, 100.0, 67.0)
    thumb_in = (30.0, 0.0, 45.0, 50.0)
    g = {f: straight for f in FINGERS}
    if name == "fist":
        g = {f: curled for f in FINGERS}
        g["thumb"] = thumb_in
    elif name == "point":
        g = {f: curled for f in FINGERS}
        g["index"] = straight
        g["thumb"] = thumb_in
    elif name == "ok":
        g["index"] = (45.0, 0.0, 65.0, 43.0)
        g["thumb"] = (25.0, 0.0, 30.0, 35.0)
    elif name == "pinch":
        g["index"] = (35.0, 0.0, 45.0, 30.0)
        g["middle"] = (60.0, 0.0, 80.0, 53.0)
        g["ring"] = (70.0, 0.0, 90.0, 60.0)
        g["pinky"] = (75.0, 0.0, 95.0, 63.0)
        g["thumb"] = (20.0, 0.0, 30.0, 30.0)
    elif name == "spread":
        g = {f: (0.0, 18.0, 0.0, 0.0) for f in FINGERS}
    elif name != "flat":
        raise ValueError(f"unknown gesture {name!r}; expected one of {CANONICAL_GESTURES}.")
    return g


def _random_angles(rng: np.random.Generator) -> dict[str, tuple[float, float, float, float]]:
    g = {}
    for f in FINGERS:
        if f == "thumb":
            g[f] = (
                rng.uniform(*_LIMITS["thumb_cmc"]),
                rng.uniform(-15.0, 15.0),
                rng.uniform(*_LIMITS["thumb_mcp"]),
                rng.uniform(*_LIMITS["thumb_ip"]),
            )
        else:
            pip = rng.uniform(*_LIMITS["pip"])
            g[f] = (
                rng.uniform(*_LIMITS["mcp_flex"]),
                rng.uniform(*_LIMITS["mcp_abd"]),
                pip,
                2.0 / 3.0 * pip,
            )
    return g


def _hand_frames(hand_body: DefaultBody, joints: np.ndarray):
    """Per hand side: palm normal (pointing out of the palm) and per-finger abduction signs."""
    names = hand_body.joint_names
    idx = {n: i for i, n in enumerate(names)}
    frames = {}
    for side in ("l", "r"):
        hand = joints[idx[f"hand_{side}"]]
        index1, pinky1 = joints[idx[f"index_01_{side}"]], joints[idx[f"pinky_01_{side}"]]
        middle1 = joints[idx[f"middle_01_{side}"]]
        n = np.cross(index1 - pinky1, middle1 - hand)
        n /= np.linalg.norm(n)
        # A-pose palms face the body's midline (x = 0): orient n out of the palm, towards it
        if np.dot(n, -np.sign(hand[0]) * np.array([1.0, 0.0, 0.0])) < 0:
            n = -n
        frames[side] = (n, middle1)
    return frames


def gesture_poses(
    hand_body: DefaultBody,
    n_random: int,
    *,
    seed: int,
    canonical: bool = True,
    rest_joints: np.ndarray | None = None,
) -> np.ndarray:
    """Finger poses of the `game_engine` rig: `(G, Jg, 3)` axis-angle, radians (both hands alike).

    The six `CANONICAL_GESTURES` (if `canonical`) and then `n_random` random gestures within the
    module's joint limits. Flexion turns each phalanx about `bone × palm normal` (towards the
    palm), abduction about the palm normal (away from the middle finger), both in the rest frame
    of `rest_joints` (default: the default body's).
    """
    if rest_joints is None:
        rest_joints = np.asarray(rest_shape(hand_body, phenotype_vector())[1], np.float64)
    joints = np.asarray(rest_joints, np.float64)
    idx = {n: i for i, n in enumerate(hand_body.joint_names)}
    rng = np.random.default_rng(seed)
    specs = [_gesture_angles(g) for g in (CANONICAL_GESTURES if canonical else ())]
    specs += [_random_angles(rng) for _ in range(int(n_random))]
    frames = _hand_frames(hand_body, joints)
    out = np.zeros((len(specs), hand_body.n_joints, 3))
    for side in ("l", "r"):
        n, middle1 = frames[side]
        for f in FINGERS:
            bones = [idx[f"{f}_0{k}_{side}"] for k in (1, 2, 3)]
            tips = [bones[1], bones[2], None]
            for k, (b, t) in enumerate(zip(bones, tips)):
                d = joints[t] if t is not None else joints[b] + (joints[b] - joints[bones[k - 1]])
                d = d - joints[b]
                d /= np.linalg.norm(d)
                flex_axis = np.cross(d, n)
                flex_axis /= np.linalg.norm(flex_axis)
                away = joints[bones[0]] - middle1
                sign = np.sign(np.dot(np.cross(n, d), away)) if f != "middle" else 1.0
                for g, spec in enumerate(specs):
                    flex = np.deg2rad(spec[f][0 if k == 0 else k + 1])
                    abd = np.deg2rad(spec[f][1]) * sign if k == 0 else 0.0
                    out[g, b] = flex * flex_axis + abd * n
    return out


# --------------------------------------------------------------------------------------------------
# the set


def _sample_identities(key, n: int, sex: int | None, n_local: int, local_sigma: float):
    """`n` phenotype vectors (of one sex if given) and local-change controls."""
    kp, kl = jax.random.split(key)
    want = n if sex is None else 2 * n + 16
    phen, _, sexes = sample_phenotypes(want, key=kp)
    phen, sexes = np.asarray(phen), np.asarray(sexes)
    if sex is not None:
        keep = np.flatnonzero(sexes == sex)
        while keep.size < n:  # astronomically rare: Bernoulli(1/2) sexes
            kp, sub = jax.random.split(kp)
            p2, _, s2 = sample_phenotypes(want, key=sub)
            phen, sexes = np.concatenate([phen, p2]), np.concatenate([sexes, s2])
            keep = np.flatnonzero(sexes == sex)
        phen, sexes = phen[keep[:n]], sexes[keep[:n]]
    local = np.clip(local_sigma * np.asarray(jax.random.normal(kl, (n, n_local))), -1.0, 1.0)
    return phen.astype(np.float32), local.astype(np.float32), sexes.astype(np.int32)


@eqx.filter_jit
def _posed_chunk(body, phen, local, pose, face, skinning: str):
    def one(p, lc, q, fa):
        return evaluate(
            body,
            p,
            q,
            local_changes=None if lc.shape[0] == 0 else lc,
            facial_actions=None if fa.shape[0] == 0 else fa,
            skinning=skinning,
        )

    return jax.vmap(one)(phen, local, pose, face)


def _evaluate_many(body, phen, local, pose, face, skinning, vertex_map, chunk, desc, progress):
    n = phen.shape[0]
    out, outj = [], []
    chunk = min(chunk, n)
    pad = (-n) % chunk
    arrays = [np.concatenate([a, np.repeat(a[-1:], pad, 0)]) if pad else a for a in
              (phen, local, pose, face)]  # fmt: skip
    for s in tqdm(range(0, n + pad, chunk), desc=desc, disable=not progress, unit="chunk"):
        v, j = _posed_chunk(body, *(jnp.asarray(a[s : s + chunk]) for a in arrays), skinning)
        out.append(np.asarray(v)[:, vertex_map])
        outj.append(np.asarray(j))
    return np.concatenate(out)[:n].astype(np.float32), np.concatenate(outj)[:n]


def make_panoman_data(
    key,
    poses: PoseSet,
    *,
    n_body_identities: int = 300,
    poses_per_identity: int = 20,
    n_face_identities: int = 100,
    n_expressions: int = 39,
    n_hand_identities: int = 300,
    gestures_per_identity: int = 20,
    sex: int | None = None,
    vertex_map=None,
    body: DefaultBody | None = None,
    hand_body: DefaultBody | None = None,
    local_sigma: float = 0.15,
    expression_seed: int = 0,
    chunk: int = 64,
    progress: bool = True,
) -> PanomanData:
    """Builds H = H_B ∪ H_F ∪ H_H on population identities (module docstring).

    **Arguments:**

    - `key`: `jax.random` key (identities, pose draws and random gestures follow from it).
    - `poses`: the [`bodyprior.PoseSet`][] the body poses are drawn from (e.g. the train clips
      of [`bodyprior.split_by_clip`][]); each identity gets `poses_per_identity` distinct poses.
    - `n_body_identities`, `poses_per_identity`: H_B size (paper ≈ 6,000 per sex).
    - `n_face_identities`, `n_expressions`: H_F (paper 100 × 39 = 3,900); the face identities are
      the first body identities, as in the paper.
    - `n_hand_identities`, `gestures_per_identity`: H_H (paper 6,000); 6 canonical gestures + the
      rest random, per identity. Hand identities beyond the body ones are drawn fresh.
    - `sex`: 0 male, 1 female, `None` both (mixed model).
    - `vertex_map`: optional `(V',)` vertex subset (the decimated topology's); default all.
    - `body`, `hand_body`: `cmu_mb` body with local changes and facial actions, and the
      `game_engine` body with local changes (loaded if omitted).
    - `local_sigma`: std of the identities' local-change controls; `expression_seed`: the fixed
      expression vectors (the same for train and test sets).
    - `chunk`: meshes per jitted evaluation; `progress`: tqdm bars.

    **Returns:** a [`bodyprior.panoman.PanomanData`][] (float32 meshes; metres).
    """
    for name, v in (
        ("n_body_identities", n_body_identities),
        ("poses_per_identity", poses_per_identity),
        ("n_face_identities", n_face_identities),
        ("n_expressions", n_expressions),
        ("n_hand_identities", n_hand_identities),
        ("gestures_per_identity", gestures_per_identity),
        ("chunk", chunk),
    ):
        if not (isinstance(v, (int, np.integer)) and v >= 0):
            raise ValueError(f"`{name}` must be a non-negative int, got {v!r}.")
    if sex not in (None, 0, 1):
        raise ValueError(f"`sex` must be 0 (male), 1 (female) or None, got {sex!r}.")
    if not isinstance(poses, PoseSet):
        raise ValueError(f"`poses` must be a bodyprior.PoseSet, got {type(poses).__name__}.")
    if poses_per_identity > poses.n_poses:
        raise ValueError(
            f"`poses_per_identity` ({poses_per_identity}) exceeds the {poses.n_poses} poses given."
        )
    if n_face_identities > n_body_identities:
        raise ValueError("`n_face_identities` must not exceed `n_body_identities`.")
    if gestures_per_identity and gestures_per_identity < len(CANONICAL_GESTURES):
        raise ValueError(
            f"`gestures_per_identity` must be 0 or ≥ {len(CANONICAL_GESTURES)} (the canonical "
            f"gestures), got {gestures_per_identity}."
        )
    if body is None:
        body = load_default_body("cmu_mb", local_changes=True, facial_actions=True)
    if body.face_basis is None or body.local_basis is None:
        raise ValueError("`body` must be loaded with local_changes=True and facial_actions=True.")
    if hand_body is None:
        hand_body = load_default_body("game_engine", local_changes=True)
    if hand_body.bones.name != "game_engine":
        raise ValueError("`hand_body` must have the game_engine rig (fingers).")
    V_full = body.n_vertices
    vertex_map = np.arange(V_full) if vertex_map is None else np.asarray(vertex_map, np.int64)
    check_array(vertex_map, "vertex_map", (None,), integer=True)

    k_id, k_hand_id, k_pose, k_gest = jax.random.split(key, 4)
    n_id = max(n_body_identities, 1)
    C = len(body.local_labels)
    phen, local, sexes = _sample_identities(k_id, n_id, sex, C, local_sigma)
    extra = max(n_hand_identities - n_body_identities, 0)
    if extra:
        p2, l2, s2 = _sample_identities(k_hand_id, extra, sex, C, local_sigma)
        phen, local, sexes = (np.concatenate(x) for x in ((phen, p2), (local, l2), (sexes, s2)))
    n_ids = phen.shape[0]
    Jb, Jg = body.n_joints, hand_body.n_joints
    zero_face = np.zeros((n_ids, 0), np.float32)
    rest, rest_joints = _evaluate_many(
        body, phen, local, np.zeros((n_ids, Jb, 3), np.float32), zero_face, "lbs", vertex_map,
        chunk, "rest bodies", progress,
    )  # fmt: skip

    parts = []  # (vertices, identity, kind, body_pose, clip, expression, hand_pose)
    # H_B
    if n_body_identities and poses_per_identity:
        rng = np.random.default_rng(np.asarray(jax.random.key_data(k_pose)).ravel()[-1].item())
        pick = np.stack(
            [rng.choice(poses.n_poses, poses_per_identity, replace=False)
             for _ in range(n_body_identities)]
        )  # fmt: skip
        ids = np.repeat(np.arange(n_body_identities), poses_per_identity)
        euler = np.asarray(poses.euler)[pick.ravel()]
        aa = np.array(jax.jit(jax.vmap(lambda e: rig_pose(body, e)))(jnp.asarray(euler)))
        aa[:, 0] = 0.0  # root orientation dropped (paper)
        aa = aa.astype(np.float32)
        v, jb = _evaluate_many(
            body, phen[ids], local[ids], aa, np.zeros((ids.size, 0), np.float32), "twist",
            vertex_map, chunk, "H_B body poses", progress,
        )  # fmt: skip
        clips = np.asarray(poses.clip)[pick.ravel()]
        parts.append((v, ids, 0, aa, clips, -1, None, jb))
    # H_F
    W = expression_set(body.face_labels, max(n_expressions, 1), seed=expression_seed)
    if n_face_identities and n_expressions:
        ids = np.repeat(np.arange(n_face_identities), n_expressions)
        ex = np.tile(np.arange(n_expressions), n_face_identities)
        v, _ = _evaluate_many(
            body, phen[ids], local[ids], np.zeros((ids.size, Jb, 3), np.float32),
            W[ex].astype(np.float32), "lbs", vertex_map, chunk, "H_F expressions", progress,
        )  # fmt: skip
        parts.append((v, ids, 1, None, -1, ex, None, rest_joints[ids]))
    # H_H
    if n_hand_identities and gestures_per_identity:
        seed = int(np.asarray(jax.random.key_data(k_gest)).ravel()[-1])
        n_rand = gestures_per_identity - len(CANONICAL_GESTURES)
        G = np.concatenate(
            [gesture_poses(hand_body, n_rand, seed=seed + i) for i in range(n_hand_identities)]
        ).astype(np.float32)
        ids = np.repeat(np.arange(n_hand_identities), gestures_per_identity)
        v, _ = _evaluate_many(
            hand_body, phen[ids], local[ids], G, np.zeros((ids.size, 0), np.float32), "lbs",
            vertex_map, chunk, "H_H gestures", progress,
        )  # fmt: skip
        parts.append((v, ids, 2, None, -1, -1, G, rest_joints[ids]))
    if not parts:
        raise ValueError("the requested set is empty: every size is 0.")

    def col(i, fill_shape, dtype):
        out = []
        for p in parts:
            n = p[0].shape[0]
            val = p[i]
            if val is None:
                out.append(np.zeros((n, *fill_shape), dtype))
            elif np.ndim(val) == 0:
                out.append(np.full((n, *fill_shape), val, dtype))
            else:
                out.append(np.asarray(val, dtype))
        return jnp.asarray(np.concatenate(out))

    return PanomanData(
        vertices=col(0, (len(vertex_map), 3), np.float32),
        identity=col(1, (), np.int32),
        kind=col(2, (), np.int32),
        body_pose=col(3, (Jb, 3), np.float32),
        clip=col(4, (), np.int32),
        expression=col(5, (), np.int32),
        expression_weights=jnp.asarray(W, jnp.float32),
        hand_pose=col(6, (Jg, 3), np.float32),
        joints=col(7, (Jb, 3), np.float32),
        rest=jnp.asarray(rest),
        rest_joints=jnp.asarray(rest_joints, jnp.float32),
        phenotypes=jnp.asarray(phen),
        local_changes=jnp.asarray(local),
        sex=jnp.asarray(sexes),
        vertex_map=jnp.asarray(vertex_map, jnp.int32),
        clip_names=tuple(poses.clip_names),
    )
