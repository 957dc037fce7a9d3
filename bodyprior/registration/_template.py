"""The registration template: the default body's rest mesh as an S-SCAPE template, with its rig.

Every S-SCAPE registration step (landmark alignment, S-SCAPE fitting, NRD, posture normalization,
depth fitting) works on this one template. By default it is the 6,449-vertex decimated topology of
the default body (the S-SCAPE template's vertex count; a vertex subset of the full mesh, so
ground-truth meshes in the full topology restrict to it exactly with `vertices[..., vertex_map, :]`).

The vertex joint regressor of the full body does not carry over to a vertex subset, so it is
refitted here on the host with the asset builder's `joint_regressor` (sum-to-one weights over the
nearest template vertices, least squares over sampled bodies whose joints are known exactly from
the phenotype basis).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Bool, Float, Int

# Bones whose skinned vertices count as "hand" (excluded from fitting data terms, as humanshape
# does).
_HAND_WORDS = ("Hand", "Thumb", "Finger")


class RegistrationTemplate(eqx.Module):
    """The default body's rest mesh and rig, prepared for registration (see module docstring).

    **Fields** (V template vertices, F triangles, J joints, L landmarks):

    - `vertices`: rest template (the base MakeHuman body), shape `(V, 3)`, metres, Z up, facing -Y.
    - `faces`: triangles, shape `(F, 3)`, int32, outward oriented.
    - `vertex_map`: shape `(V,)`, index of each template vertex in the full default-body mesh.
    - `landmark_index`: template vertex of each named landmark, shape `(L,)`.
    - `landmark_error`: distance from each landmark's full-mesh vertex to the template vertex used
      for it on the rest template, shape `(L,)`, metres (0 where the vertex is kept by the
      decimation).
    - `hand_mask`: shape `(V,)`, vertices skinned mostly (weight > 0.5) to hand/finger/thumb bones.
    - `head_mask`: shape `(V,)`, vertices skinned mostly to the head and neck bones.
    - `skin_index`, `skin_weight`: top-k skin weights, shapes `(V, K)`; rows sum to one.
    - `joint_regressor_indices`, `joint_regressor_weights`: sparse joint regressor over the template
      vertices, shapes `(J, M)`; weights of each joint sum to one.
    - `regressor_max_error`: held-out maximum joint error of that regressor over sampled adult
      bodies, metres (a float).
    - `parents`, `joint_names`, `landmark_names`: static.
    """

    vertices: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    vertex_map: Int[Array, " V"]
    landmark_index: Int[Array, " L"]
    landmark_error: Float[Array, " L"]
    hand_mask: Bool[Array, " V"]
    head_mask: Bool[Array, " V"]
    skin_index: Int[Array, "V K"]
    skin_weight: Float[Array, "V K"]
    joint_regressor_indices: Int[Array, "J M"]
    joint_regressor_weights: Float[Array, "J M"]
    regressor_max_error: float = eqx.field(static=True)
    parents: tuple[int, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    landmark_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    def rig_kwargs(self) -> dict:
        """The rig as keyword arguments of [`bodyprior.sscape.learn`][].

        **Example:**
        `bodyprior.sscape.learn(meshes, tmpl.faces, n_components=20, **tmpl.rig_kwargs())`.
        """
        return dict(
            parents=self.parents,
            joint_names=self.joint_names,
            joint_regressor_indices=self.joint_regressor_indices,
            joint_regressor_weights=self.joint_regressor_weights,
            skin_indices=self.skin_index,
            skin_weights=self.skin_weight,
        )

    def restrict(self, full_vertices: Float[Array, "*batch Vfull 3"]) -> Float[Array, "*batch V 3"]:
        """Restricts meshes in the full default-body topology to the template's vertices."""
        return jnp.asarray(full_vertices)[..., self.vertex_map, :]


@functools.lru_cache(maxsize=4)
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

    sidx = np.asarray(body.rig.skin_index)[vertex_map]
    sw = np.asarray(body.rig.skin_weight, np.float64)[vertex_map]
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
    rest_joints = np.asarray(body.rig.head_template, np.float64)
    for j in range(body.n_joints):
        i, w = joint_regressor(template, rest_joints[j], verts[:n_fit], joints[:n_fit, j], k=k)
        e = np.linalg.norm(np.einsum("k,skc->sc", w, verts[n_fit:, i]) - joints[n_fit:, j], axis=1)
        reg_i.append(i)
        reg_w.append(w)
        err.append(float(e.max()))

    return RegistrationTemplate(
        vertices=jnp.asarray(template, body.template.dtype),
        faces=jnp.asarray(faces, jnp.int32),
        vertex_map=jnp.asarray(vertex_map),
        landmark_index=jnp.asarray(lm_index),
        landmark_error=jnp.asarray(lm_error, body.template.dtype),
        hand_mask=jnp.asarray(hand),
        head_mask=jnp.asarray(head),
        skin_index=jnp.asarray(sidx, jnp.int32),
        skin_weight=jnp.asarray(sw / sw.sum(1, keepdims=True), body.template.dtype),
        joint_regressor_indices=jnp.asarray(np.stack(reg_i), jnp.int32),
        joint_regressor_weights=jnp.asarray(np.stack(reg_w), body.template.dtype),
        regressor_max_error=max(err),
        parents=body.parents,
        joint_names=names,
        landmark_names=body.landmark_names,
    )


def registration_template(
    rig: str = "cmu_mb", *, decimated: bool = True, n_fit: int = 300, regressor_size: int = 128
) -> RegistrationTemplate:
    """The registration template of the default body (cached per argument set).

    **Arguments:**

    - `rig`: `"cmu_mb"` (31 bones, default) or `"game_engine"`.
    - `decimated`: use the 6,449-vertex decimated topology (default) or the full 13,380-vertex mesh.
    - `n_fit`: sampled adult bodies used to fit the joint regressor (half as many more check it).
    - `regressor_size`: template vertices per joint in the regressor.

    **Returns:** a [`bodyprior.registration.RegistrationTemplate`][] (its `regressor_max_error` reports
    the held-out joint error of the refitted regressor).
    """
    if rig not in ("cmu_mb", "game_engine"):
        raise ValueError(f"`rig` must be 'cmu_mb' or 'game_engine', got {rig!r}.")
    if not isinstance(n_fit, int) or n_fit < 20:
        raise ValueError(f"`n_fit` must be an int >= 20, got {n_fit!r}.")
    if not isinstance(regressor_size, int) or not 4 <= regressor_size <= 512:
        raise ValueError(f"`regressor_size` must be an int in [4, 512], got {regressor_size!r}.")
    return _build(rig, bool(decimated), n_fit, regressor_size)
