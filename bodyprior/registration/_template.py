"""The registration template: the default body's rest mesh as an S-SCAPE template, with its rig.

Every S-SCAPE registration step (landmark alignment, S-SCAPE fitting, NRD, posture normalization,
depth fitting) works on this one template. By default it is the 6,449-vertex decimated topology of
the default body (the S-SCAPE template's vertex count; a vertex subset of the full mesh, so
ground-truth meshes in the full topology restrict to it exactly with
`vertices[..., vertex_map, :]`). The template carries its rig ([`bodyprior.Rig`][]) and its
[`bodyprior.Topology`][], so nothing downstream rebuilds them.

The vertex joint regressor of the full body does not carry over to a vertex subset, so it is
refitted here on the host with the asset builder's `joint_regressor` (sum-to-one weights over the
nearest template vertices, least squares over sampled bodies whose joints are known exactly from
the phenotype basis). That refit takes tens of seconds, so the templates of the default arguments
(both rigs, decimated or not, `n_fit=300`, `regressor_size=128`) are built once and committed as
`bodyprior/assets/registration_template.npz` (format `bodyprior.registration_template`, with the
checksums of the assets it was built from and a sha256 checksum of its arrays, verified on load).
Rebuild it with `python -m bodyprior.assets.build --template` after changing the default-body or
decimated asset, or the code below.
"""

from __future__ import annotations

import functools
import json
import os
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._rig import Rig, RigHolder
from .._topology import Topology
from .._validate import as_device_array

# Bones whose skinned vertices count as "hand" (excluded from fitting data terms, as humanshape
# does).
_HAND_WORDS = ("Hand", "Thumb", "Finger")


class RegistrationTemplate(RigHolder):
    """The default body's rest mesh and rig, prepared for registration (see module docstring).

    **Fields** (V template vertices, F triangles, J joints, L landmarks):

    - `vertices`: rest template (the base MakeHuman body), shape `(V, 3)`, metres, Z up, facing -Y.
    - `topology`: the mesh's [`bodyprior.Topology`][] (faces, edges, one-rings), built and
      validated once with the template; `faces` is `topology.faces`, `(F, 3)` int32, outward
      oriented.
    - `vertex_map`: shape `(V,)`, index of each template vertex in the full default-body mesh.
    - `landmark_index`: template vertex of each named landmark, shape `(L,)`.
    - `landmark_error`: distance from each landmark's full-mesh vertex to the template vertex used
      for it on the rest template, shape `(L,)`, metres (0 where the vertex is kept by the
      decimation).
    - `hand_mask`: shape `(V,)`, vertices skinned mostly (weight > 0.5) to hand/finger/thumb bones.
    - `head_mask`: shape `(V,)`, vertices skinned mostly to the head and neck bones.
    - `rig`: the [`bodyprior.Rig`][] over the template vertices: bone tree and names, top-k skin
      weights (rows sum to one) and the sparse joint regressor refitted for these vertices
      (weights of each joint sum to one).
    - `regressor_max_error`: held-out maximum joint error of that regressor over sampled adult
      bodies, metres (a float).
    - `landmark_names`: static.
    """

    vertices: Float[Array, "V 3"]
    topology: Topology
    vertex_map: Int[Array, " V"]
    landmark_index: Int[Array, " L"]
    landmark_error: Float[Array, " L"]
    hand_mask: Bool[Array, " V"]
    head_mask: Bool[Array, " V"]
    rig: Rig
    regressor_max_error: float = eqx.field(static=True)
    landmark_names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        if not isinstance(self.topology, Topology):
            raise ValueError(
                f"`topology` must be a bodyprior.Topology (`Topology.from_faces(faces, V)`), got "
                f"{type(self.topology).__name__}."
            )
        if not isinstance(self.rig, Rig):
            raise ValueError(f"`rig` must be a bodyprior.Rig, got {type(self.rig).__name__}.")
        n = self.vertices.shape[0]
        for name, m in (("topology", self.topology.n_vertices), ("rig", self.rig.n_vertices)):
            if m != n:
                raise ValueError(f"`{name}` must have the template's {n} vertices, got {m}.")

    @property
    def faces(self) -> Int[Array, "F 3"]:
        return self.topology.faces

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    def rig_kwargs(self) -> dict:
        """Deprecated: pass `rig=template.rig` to [`bodyprior.sscape.learn`][] instead.

        **Returns:** `{"rig": self.rig}`, so `learn(..., **tmpl.rig_kwargs())` still works (with a
        `DeprecationWarning`).
        """
        warnings.warn(
            "`RegistrationTemplate.rig_kwargs()` is deprecated: pass `rig=template.rig` to "
            "`bodyprior.sscape.learn`.",
            DeprecationWarning,
            stacklevel=2,
        )
        return {"rig": self.rig}

    def restrict(
        self, full_vertices: Float[ArrayLike, "*batch Vfull 3"]
    ) -> Float[Array, "*batch V 3"]:
        """Restricts meshes in the full default-body topology to the template's vertices."""
        return jnp.asarray(full_vertices)[..., self.vertex_map, :]

    def landmark_vertices(self, names) -> tuple[Int[Array, " L"], Bool[Array, " L"]]:
        """Template vertex of each landmark of `names` (e.g. a scan's `landmark_names`) and
        whether a fitter may use it: `(index (L,), usable (L,))`; unknown names and landmarks on
        hand vertices are not usable (their index is 0)."""
        where = {n: i for i, n in enumerate(self.landmark_names)}
        lm_idx = np.asarray(self.landmark_index)
        hand = np.asarray(self.hand_mask, bool)
        v = np.array([lm_idx[where[n]] if n in where else 0 for n in names], np.int32)
        use = np.array([n in where for n in names], bool) & ~hand[v]
        return as_device_array(v), as_device_array(use)


@functools.lru_cache(maxsize=8)
def _cached_build(rig: str, decimated: bool, n_fit: int, k: int, x64: bool) -> RegistrationTemplate:
    # `x64` keys the cache only: the regressor fit samples its bodies in the current JAX precision.
    return _build(rig, decimated, n_fit, k)


def _build(rig: str, decimated: bool, n_fit: int, k: int) -> RegistrationTemplate:
    from .._body import load_default_body, rest_shape
    from .._population import sample_phenotypes
    from .._stats import joint_regressor
    from ..assets._decimate import load_decimated

    body = load_default_body(rig)
    full_template = np.asarray(body.template, np.float64)
    if decimated:
        vertex_map, faces = load_decimated()
    else:
        vertex_map = np.arange(body.n_vertices, dtype=np.int32)
        faces = np.asarray(body.faces, np.int32)
    vertex_map = np.asarray(vertex_map, np.int32)
    template = full_template[vertex_map]

    # Landmarks: the kept vertex itself, else the nearest kept vertex on the rest template.
    lm_full = full_template[np.asarray(body.landmark_index)]
    d = np.linalg.norm(lm_full[:, None, :] - template[None, :, :], axis=-1)
    lm_index = d.argmin(1).astype(np.int32)
    lm_error = d[np.arange(len(lm_index)), lm_index]

    sidx = np.asarray(body.rig.skin_indices)[vertex_map]
    sw = np.asarray(body.rig.skin_weights, np.float64)[vertex_map]
    names = body.joint_names

    def mass(pred) -> np.ndarray:
        bones = np.array([pred(n) for n in names])
        return (sw * bones[sidx]).sum(1)

    hand = mass(lambda n: any(w in n for w in _HAND_WORDS)) > 0.5
    head = mass(lambda n: n in ("Head", "Neck", "Neck1")) > 0.5

    # Joint regressor over the template vertices, fitted on adult bodies with exact joints.
    phen, _, _ = sample_phenotypes(n_fit + n_fit // 2, key=jr.PRNGKey(1234))
    verts, joints = jax.jit(jax.vmap(lambda p: rest_shape(body, p)))(phen)
    verts = np.asarray(verts, np.float64)[:, vertex_map]
    joints = np.asarray(joints, np.float64)
    reg_i, reg_w, err = [], [], []
    rest_joints = np.asarray(body.bones.head_template, np.float64)
    for j in range(body.n_joints):
        i, w = joint_regressor(template, rest_joints[j], verts[:n_fit], joints[:n_fit, j], k=k)
        e = np.linalg.norm(np.einsum("k,skc->sc", w, verts[n_fit:, i]) - joints[n_fit:, j], axis=1)
        reg_i.append(i)
        reg_w.append(w)
        err.append(float(e.max()))

    return RegistrationTemplate(
        vertices=jnp.asarray(template, body.template.dtype),
        topology=Topology.from_faces(np.asarray(faces, np.int32), len(vertex_map)),
        vertex_map=jnp.asarray(vertex_map),
        landmark_index=jnp.asarray(lm_index),
        landmark_error=jnp.asarray(lm_error, body.template.dtype),
        hand_mask=jnp.asarray(hand),
        head_mask=jnp.asarray(head),
        rig=Rig(
            parents=body.parents,
            joint_names=names,
            skin_indices=jnp.asarray(sidx, jnp.int32),
            skin_weights=jnp.asarray(sw / sw.sum(1, keepdims=True), body.template.dtype),
            regressor_indices=jnp.asarray(np.stack(reg_i), jnp.int32),
            regressor_weights=jnp.asarray(np.stack(reg_w), body.template.dtype),
        ),
        regressor_max_error=max(err),
        landmark_names=body.landmark_names,
    )


def registration_template(
    rig: str = "cmu_mb",
    *,
    decimated: bool = True,
    n_fit: int = 300,
    regressor_size: int = 128,
    precomputed: bool = True,
) -> RegistrationTemplate:
    """The registration template of the default body (cached per argument set).

    **Arguments:**

    - `rig`: `"cmu_mb"` (31 bones, default) or `"game_engine"`.
    - `decimated`: use the 6,449-vertex decimated topology (default) or the full 13,380-vertex mesh.
    - `n_fit`: sampled adult bodies used to fit the joint regressor (half as many more check it).
    - `regressor_size`: template vertices per joint in the regressor.
    - `precomputed`: with the default `n_fit` and `regressor_size`, read the template from the
      committed `bodyprior/assets/registration_template.npz` (well under a second; bit-identical
      to a rebuild in the current `jax_enable_x64` mode, since the regressor fit samples its bodies
      in that precision and the file holds both). `False`, or other arguments, fit the joint
      regressor here (tens of seconds).

    **Returns:** a [`bodyprior.registration.RegistrationTemplate`][] (its `regressor_max_error`
    reports the held-out joint error of the refitted regressor). Templates are cached per argument
    set (and `jax_enable_x64` mode) for the process, so every call returns the same object.

    **Raises:** `ValueError` for bad arguments or a corrupted precomputed file. A precomputed file
    built from other assets than the current ones is ignored with a warning (and the template fitted
    here).
    """
    if rig not in ("cmu_mb", "game_engine"):
        raise ValueError(f"`rig` must be 'cmu_mb' or 'game_engine', got {rig!r}.")
    if not isinstance(n_fit, int) or n_fit < 20:
        raise ValueError(f"`n_fit` must be an int >= 20, got {n_fit!r}.")
    if not isinstance(regressor_size, int) or not 4 <= regressor_size <= 512:
        raise ValueError(f"`regressor_size` must be an int in [4, 512], got {regressor_size!r}.")
    x64 = bool(jax.config.jax_enable_x64)
    if precomputed and (n_fit, regressor_size) == (_N_FIT, _REGRESSOR_SIZE):
        tmpl = _load_precomputed(rig, bool(decimated), x64)
        if tmpl is not None:
            return tmpl
    return _cached_build(rig, bool(decimated), n_fit, regressor_size, x64)


# --------------------------------------------------------------------------------------------------
# The precomputed templates of the default arguments (bodyprior/assets/registration_template.npz)

TEMPLATE_NAME = "registration_template.npz"
TEMPLATE_FORMAT = "bodyprior.registration_template"
TEMPLATE_FORMAT_VERSION = 1
_N_FIT, _REGRESSOR_SIZE = 300, 128
_VARIANTS = tuple(
    (r, d, x) for r in ("cmu_mb", "game_engine") for d in (True, False) for x in (True, False)
)
# The file's arrays of each variant (the names of the template's fields before it held a Rig and a
# Topology; the file format is unchanged) and how to read each from a template.
_FILE_ARRAYS = {
    "vertices": lambda t: t.vertices,
    "faces": lambda t: t.faces,
    "vertex_map": lambda t: t.vertex_map,
    "landmark_index": lambda t: t.landmark_index,
    "landmark_error": lambda t: t.landmark_error,
    "hand_mask": lambda t: t.hand_mask,
    "head_mask": lambda t: t.head_mask,
    "skin_index": lambda t: t.rig.skin_indices,
    "skin_weight": lambda t: t.rig.skin_weights,
    "joint_regressor_indices": lambda t: t.rig.regressor_indices,
    "joint_regressor_weights": lambda t: t.rig.regressor_weights,
}
_REBUILD = "rebuild it with `python -m bodyprior.assets.build --template`"


def template_path() -> str:
    """Path of the committed precomputed registration templates."""
    from ..assets import asset_path

    return os.path.join(os.path.dirname(asset_path()), TEMPLATE_NAME)


def _variant(rig: str, decimated: bool, x64: bool) -> str:
    return f"{rig}.{'decimated' if decimated else 'full'}.{'x64' if x64 else 'x32'}"


def template_sources() -> dict:
    """Checksums of the embedded assets a registration template is built from (the default
    body, the decimation): `{"source_checksum", "decimated_checksum"}`. Files derived from a
    template (spaces, priors) record them so that a load can tell whether the body changed."""
    from ..assets import _checksum, asset_path
    from ..assets._decimate import load_decimated

    with np.load(asset_path(), allow_pickle=False) as z:
        body = str(z["checksum"])
    vertex_map, faces = load_decimated()
    return {
        "source_checksum": body,
        "decimated_checksum": _checksum({"vertex_map": vertex_map, "faces": faces}),
    }


def write_precomputed(path: str | None = None, log=print) -> dict:
    """Fits the templates of the default arguments (both rigs, decimated and full, each with
    `jax_enable_x64` on and off) and writes them
    atomically to `path` (default: [`template_path`][]); this is what
    `python -m bodyprior.assets.build --template` runs (about a minute per rig).

    **Returns:** the file's metadata (provenance, per-variant `regressor_max_error`).
    """
    from ..assets import _checksum
    from ..assets.build import write_npz_atomic

    path = os.path.abspath(path or template_path())
    arrays: dict[str, np.ndarray] = {}
    variants = {}
    for rig, dec, x64 in _VARIANTS:
        t0 = time.perf_counter()
        with jax.enable_x64(x64):
            tmpl = _build(rig, dec, _N_FIT, _REGRESSOR_SIZE)
        name = _variant(rig, dec, x64)
        for f, get in _FILE_ARRAYS.items():
            arrays[f"{name}.{f}"] = np.asarray(get(tmpl))
        variants[name] = {
            "rig": rig,
            "decimated": dec,
            "x64": x64,
            "n_vertices": tmpl.n_vertices,
            "regressor_max_error": tmpl.regressor_max_error,
            "parents": list(tmpl.parents),
            "joint_names": list(tmpl.joint_names),
            "landmark_names": list(tmpl.landmark_names),
            "build_seconds": round(time.perf_counter() - t0, 2),
        }
        log(f"{name}: {tmpl.n_vertices} vertices, regressor max error "
            f"{tmpl.regressor_max_error * 1e3:.2f} mm ({variants[name]['build_seconds']} s)")
    meta = {
        "format": TEMPLATE_FORMAT,
        "format_version": TEMPLATE_FORMAT_VERSION,
        "built_by": "bodyprior.registration._template.write_precomputed "
        "(python -m bodyprior.assets.build --template)",
        "n_fit": _N_FIT,
        "regressor_size": _REGRESSOR_SIZE,
        "phenotype_seed": 1234,
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        **template_sources(),
        "variants": variants,
    }
    arrays["checksum"] = np.array(_checksum(arrays))
    arrays["metadata"] = np.array(json.dumps(meta))
    write_npz_atomic(path, arrays)
    _read_precomputed.cache_clear()
    _load_precomputed.cache_clear()
    return meta


@functools.lru_cache(maxsize=2)
def _read_precomputed(path: str) -> tuple[dict, dict] | None:
    """The file's validated arrays and metadata; `None` (with a warning) when it was built from
    other assets; `ValueError` when it is unreadable, of another format or corrupted."""
    from ..assets import _checksum

    if not os.path.exists(path):
        warnings.warn(f"precomputed registration templates not found at {path!r}; {_REBUILD}.",
                      stacklevel=3)
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("metadata")))
        want = str(arrays.pop("checksum"))
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"{path!r} is not a readable registration-template file ({e}); "
                         f"{_REBUILD}.") from e
    if (meta.get("format"), meta.get("format_version")) != (
        TEMPLATE_FORMAT, TEMPLATE_FORMAT_VERSION
    ):
        raise ValueError(f"{path!r} has format {meta.get('format')!r} "
                         f"v{meta.get('format_version')}; {_REBUILD}.")
    if _checksum(arrays) != want:
        raise ValueError(f"{path!r} is corrupted (checksum mismatch); {_REBUILD}.")
    src = template_sources()
    if any(meta.get(k) != v for k, v in src.items()):
        warnings.warn(f"{path!r} was built from other default-body/decimated assets; fitting the "
                      f"registration template instead (slow); {_REBUILD}.", stacklevel=3)
        return None
    return arrays, meta


@functools.lru_cache(maxsize=8)
def _load_precomputed(rig: str, decimated: bool, x64: bool) -> RegistrationTemplate | None:
    read = _read_precomputed(template_path())
    if read is None:
        return None
    arrays, meta = read
    name = _variant(rig, decimated, x64)
    info = meta["variants"][name]
    a = {f: as_device_array(arrays[f"{name}.{f}"]) for f in _FILE_ARRAYS}
    return RegistrationTemplate(
        vertices=a["vertices"],
        topology=Topology.from_faces(np.asarray(a["faces"]), a["vertices"].shape[0]),
        vertex_map=a["vertex_map"],
        landmark_index=a["landmark_index"],
        landmark_error=a["landmark_error"],
        hand_mask=a["hand_mask"],
        head_mask=a["head_mask"],
        rig=Rig(
            parents=tuple(int(p) for p in info["parents"]),
            joint_names=tuple(str(n) for n in info["joint_names"]),
            skin_indices=a["skin_index"],
            skin_weights=a["skin_weight"],
            regressor_indices=a["joint_regressor_indices"],
            regressor_weights=a["joint_regressor_weights"],
        ),
        regressor_max_error=float(info["regressor_max_error"]),
        landmark_names=tuple(str(n) for n in info["landmark_names"]),
    )
