"""A synthetic population in correspondence: the stand-in for CAESAR (no licensed scans exist here).

Bodies are drawn from a documented phenotype distribution (below), given random local changes for
individual detail, and put in the standard standing posture of the template (A-pose) with small
random
arm/leg/spine jitter, as CAESAR subjects never stand exactly in the template pose.

Distribution (`scheme="caesar"`, the default):

- age in years ~ U(age_range) (default 18-65), mapped to the phenotype age with anny's
  piecewise-linear
  "morphological age" table (years [0, 1, 4, 11, 16, 18, 64, 110] -> [0, .05, .215, .415, .67, .77,
  .83, 1]);
- sex ~ Bernoulli(1/2); gender = sex blended towards the other end by d ~ U(0, 0.1);
- height ~ anny's WHO-calibrated Beta(alpha(age), beta(age)) for the sex (boys/girls tables);
- weight ~ Beta with mean 0.40 + 0.20 (years - 18) / 47 and concentration 6 (BMI rises with age);
- muscle ~ Beta(3, 3); proportions ~ Beta(2, 5) (mostly ideal); ethnicity ~ Dirichlet(1, 1, 1);
- local changes (when the body is loaded with them) ~ N(0, local_sigma^2) clipped to [-1, 1].

`scheme="anny"` instead follows anny's `SimpleShapeDistribution` exactly (U(0,1) gender,
age-conditioned
Betas for height, weight, muscle and proportions — its adult weight/muscle Betas are U-shaped, which
gives
many extreme bodies), restricted to `age_range`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int
from tqdm.auto import tqdm

from ._body import PHENOTYPES, DefaultBody, evaluate, load_default_body
from ._store import register_type
from .assets import load_asset

# Joints jittered for the standing posture, with the standard deviation (degrees) of each axis-angle
# entry.
_JITTER = {
    "LeftArm": 1.0, "RightArm": 1.0, "LeftForeArm": 0.8, "RightForeArm": 0.8,
    "LeftHand": 0.5, "RightHand": 0.5, "LeftShoulder": 0.3, "RightShoulder": 0.3,
    "LeftUpLeg": 0.5, "RightUpLeg": 0.5, "LeftLeg": 0.4, "RightLeg": 0.4,
    "LeftFoot": 0.3, "RightFoot": 0.3, "LowerBack": 0.3, "Spine": 0.3,
    "Spine1": 0.3, "Neck": 0.4, "Neck1": 0.4, "Head": 0.5,
}  # fmt: skip


class Population(eqx.Module):
    """Bodies in correspondence on the default topology, with their ground truth.

    **Fields** (N bodies, V vertices, J joints, C local-change controls):

    - `vertices`: posed bodies, shape `(N, V, 3)`, metres, Z up, facing -Y.
    - `joints`: posed joints, shape `(N, J, 3)`.
    - `phenotypes`: shape `(N, 11)`, order `bodyprior.PHENOTYPES`.
    - `local_changes`: shape `(N, C)` (C = 0 if not used).
    - `poses`: local axis-angle rotations, shape `(N, J, 3)`, radians.
    - `age_years`: shape `(N,)`; `sex`: shape `(N,)`, 0 = male, 1 = female.
    """

    vertices: Float[Array, "N V 3"]
    joints: Float[Array, "N J 3"]
    phenotypes: Float[Array, "N 11"]
    local_changes: Float[Array, "N C"]
    poses: Float[Array, "N J 3"]
    age_years: Float[Array, " N"]
    sex: Int[Array, " N"]

    def __len__(self) -> int:
        return self.vertices.shape[0]


register_type(Population)


def _interp(x, xs, ys):
    return jnp.interp(x, jnp.asarray(xs, x.dtype), jnp.asarray(ys, x.dtype))


def _calib(sex_name: str, dist: str):
    a = load_asset()
    p = f"calib_{sex_name}_conditional_{dist}_distribution_"
    return a[p + "age_anchors"], a[p + "alpha_anchors"], a[p + "beta_anchors"]


def _beta_cond(key, age, sex, dist):
    """Sample anny's age-conditioned Beta for `dist`, boys' table where sex == 0, girls'
    elsewhere."""
    out = []
    for name in ("boys", "girls"):
        ages, al, be = _calib(name, dist)
        out.append(jr.beta(key, _interp(age, ages, al), _interp(age, ages, be)))
    return jnp.where(sex == 0, out[0], out[1])


def sample_phenotypes(n: int, *, key, scheme: str = "caesar", age_range=(18.0, 65.0)):
    """Phenotype vectors `(n, 11)`, ages in years `(n,)` and sexes `(n,)` from the documented
    distribution."""
    a = load_asset()
    morph_years = a["calib_boys_morphological_age_mapping_morphological_age_anchors"]
    morph_age = a["calib_boys_morphological_age_mapping_anny_age_anchors"]
    k = jr.split(key, 10)
    years = jr.uniform(k[0], (n,), minval=age_range[0], maxval=age_range[1])
    age = _interp(years, morph_years, morph_age)
    if scheme == "caesar":
        sex = jr.bernoulli(k[1], 0.5, (n,)).astype(jnp.int32)
        d = jr.uniform(k[2], (n,), maxval=0.1)
        gender = jnp.where(sex == 1, 1.0 - d, d)
        height = _beta_cond(k[3], age, sex, "height")
        mu = jnp.clip(0.40 + 0.20 * (years - 18.0) / 47.0, 0.05, 0.95)
        weight = jr.beta(k[4], 6.0 * mu, 6.0 * (1.0 - mu))
        muscle = jr.beta(k[5], 3.0, 3.0, (n,))
        proportions = jr.beta(k[6], 2.0, 5.0, (n,))
    elif scheme == "anny":
        gender = jr.uniform(k[1], (n,))
        sex = (gender > 0.5).astype(jnp.int32)
        height = _beta_cond(k[3], age, sex, "height")
        weight = _beta_cond(k[4], age, sex, "weight")
        muscle = _beta_cond(k[5], age, sex, "muscle")
        proportions = _beta_cond(k[6], age, sex, "proportions")
    else:
        raise ValueError(f"`scheme` must be 'caesar' or 'anny', got {scheme!r}.")
    eth = jr.dirichlet(k[7], jnp.ones(3), (n,)) if scheme == "caesar" else jnp.full((n, 3), 0.5)
    cols = dict(
        gender=gender, age=age, muscle=muscle, weight=weight, height=height,
        proportions=proportions,
        cupsize=jnp.full((n,), 0.5), firmness=jnp.full((n,), 0.5),
        african=eth[:, 0], asian=eth[:, 1], caucasian=eth[:, 2],
    )  # fmt: skip
    return jnp.stack([cols[p] for p in PHENOTYPES], 1), years, sex


def standing_pose_jitter(
    body: DefaultBody, n: int, scale_deg: float = 4.0, *, key
) -> Float[Array, "n J 3"]:
    """Random axis-angle jitter `(n, J, 3)` around the template posture: N(0, (scale_deg * s_j)^2)
    per axis
    for the limb, spine and head joints (relative scales `s_j` in `_JITTER`), zero elsewhere."""
    s = np.array([_JITTER.get(name, 0.0) for name in body.joint_names])
    return jr.normal(key, (n, body.n_joints, 3)) * jnp.asarray(
        s[None, :, None] * np.deg2rad(scale_deg)
    )


@eqx.filter_jit
def _eval_chunk(body, phen, local, poses):
    def one(p, lc, q):
        return evaluate(body, p, q, local_changes=None if lc.shape[0] == 0 else lc)

    return jax.vmap(one)(phen, local, poses)


def sample_population(
    n: int,
    *,
    key,
    body: DefaultBody | None = None,
    scheme: str = "caesar",
    age_range: tuple[float, float] = (18.0, 65.0),
    pose_jitter_deg: float = 4.0,
    local_sigma: float = 0.15,
    chunk: int = 256,
    progress: bool = True,
) -> Population:
    """Samples `n` adult bodies in correspondence with their ground truth (the CAESAR stand-in).

    **Arguments:**

    - `key`: a `jax.random` key (the result is a deterministic function of it and of the
      precision: with `jax_enable_x64` on, the same key draws other bodies than with it off).
    - `n`: number of bodies (CAESAR: 4,308).
    - `body`: the default body to use; by default `load_default_body("cmu_mb", local_changes=True)`.
      A body loaded without local changes gives bodies without them.
    - `scheme`: `"caesar"` (default) or `"anny"`; see the module docstring.
    - `age_range`: ages in years, within [0, 110].
    - `pose_jitter_deg`: scale of the random posture jitter, degrees (0 = exact template posture).
    - `local_sigma`: standard deviation of the local-change controls.
    - `chunk`: bodies evaluated per jitted call (bounds memory).
    - `progress`: show a tqdm progress bar.

    **Returns:** a [`bodyprior.Population`][].
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"`n` must be a positive int, got {n!r}.")
    lo, hi = age_range
    if not (0.0 <= lo < hi <= 110.0):
        raise ValueError(f"`age_range` must satisfy 0 <= lo < hi <= 110 years, got {age_range!r}.")
    if pose_jitter_deg < 0 or local_sigma < 0:
        raise ValueError("`pose_jitter_deg` and `local_sigma` must be non-negative.")
    if body is None:
        body = load_default_body("cmu_mb", local_changes=True)
    kp, kl, kj = jr.split(key, 3)
    phen, years, sex = sample_phenotypes(n, scheme=scheme, age_range=age_range, key=kp)
    phen = phen.astype(body.template.dtype)
    C = 0 if body.local_basis is None else len(body.local_labels)
    local = jnp.clip(local_sigma * jr.normal(kl, (n, C)), -1.0, 1.0).astype(body.template.dtype)
    poses = standing_pose_jitter(body, n, pose_jitter_deg, key=kj).astype(body.template.dtype)

    chunk = int(min(chunk, n))
    pad = (-n) % chunk
    padded = [
        jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]) if pad else x for x in (phen, local, poses)
    ]
    verts, joints = [], []
    for s in tqdm(
        range(0, n + pad, chunk), desc="sampling bodies", disable=not progress, unit="chunk"
    ):
        v, j = _eval_chunk(body, *(x[s : s + chunk] for x in padded))
        verts.append(v)
        joints.append(j)
    verts = jnp.concatenate(verts)[:n]
    joints = jnp.concatenate(joints)[:n]
    return Population(verts, joints, phen, local, poses, years, sex)
