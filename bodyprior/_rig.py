"""The rig: one skinned skeleton Module shared by every body model and template.

A [`bodyprior.Rig`][] is what skinning and joint regression need of a body in a fixed topology: the
kinematic tree (`parents`, `joint_names`, static), sparse top-k skin weights per vertex and a sparse
linear joint regressor (each joint a fixed weighted sum of vertices, the S-SCAPE convention). The
default body ([`bodyprior.DefaultBody`][]`.rig`), S-SCAPE models
([`bodyprior.sscape.SScapeModel`][]`.rig`), the registration template
([`bodyprior.registration.RegistrationTemplate`][]`.rig`) and the posture-normalization rig
([`bodyprior.sscape.PostureRig`][]`.rig`) all hold one, and [`bodyprior.sscape.learn`][] takes one
(`rig=`).

Pure kernels for one body; `jax.vmap` for batches.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._kinematics import validate_parents
from ._skinning import dqs, lbs
from ._validate import as_device_array, check_array, is_tracer

__all__ = ["Rig"]


def _int_leaf(x):
    return as_device_array(x, dtype=jnp.int32)


def _float_leaf(x):
    return as_device_array(x)


class Rig(eqx.Module):
    """A skinned skeleton over a fixed mesh topology: bone tree, skin weights, joint regressor.

    Arrays are leaves (indices converted to `int32`, weights keep their dtype); the tree and the
    names are static. Validated at construction (shapes agree, `parents` is a tree with one root,
    indices in range), with a `ValueError` naming the field.

    **Fields** (V vertices, J joints, K influences per vertex, M vertices per joint):

    - `parents`: static tuple of `J` parent indices, `parents[0] == -1`.
    - `joint_names`: static tuple of `J` joint (bone) names.
    - `skin_indices`, `skin_weights`: top-K skinning weights, shapes `(V, K)`; vertex `v` follows
      joint `skin_indices[v, k]` with weight `skin_weights[v, k]` (rows sum to one; padding
      entries have weight 0).
    - `regressor_indices`, `regressor_weights`: sparse joint regressor, shapes `(J, M)`; joint `j`
      sits at `sum_m regressor_weights[j, m] * vertices[regressor_indices[j, m]]` (padding entries
      have weight 0).
    """

    skin_indices: Int[Array, "V K"] = eqx.field(converter=_int_leaf)
    skin_weights: Float[Array, "V K"] = eqx.field(converter=_float_leaf)
    regressor_indices: Int[Array, "J M"] = eqx.field(converter=_int_leaf)
    regressor_weights: Float[Array, "J M"] = eqx.field(converter=_float_leaf)
    parents: tuple[int, ...] = eqx.field(
        static=True, converter=lambda p: tuple(int(i) for i in p)
    )
    joint_names: tuple[str, ...] = eqx.field(
        static=True, converter=lambda n: tuple(str(s) for s in n)
    )

    def __check_init__(self):
        dims: dict[str, int] = {}
        check_array(self.skin_indices, "skin_indices", ("V", "K"), dims=dims, integer=True)
        check_array(self.skin_weights, "skin_weights", ("V", "K"), dims=dims, finite=False)
        check_array(
            self.regressor_indices, "regressor_indices", ("J", "M"), dims=dims, integer=True
        )
        check_array(self.regressor_weights, "regressor_weights", ("J", "M"), dims=dims,
                    finite=False)  # fmt: skip
        n_joints, n_vertices = dims["J"], dims["V"]
        for name, seq in (("parents", self.parents), ("joint_names", self.joint_names)):
            if len(seq) != n_joints:
                raise ValueError(
                    f"`{name}` must have {n_joints} entries (one per regressor row), got "
                    f"{len(seq)}."
                )
        validate_parents(self.parents)
        for name, arr, hi in (
            ("regressor_indices", self.regressor_indices, n_vertices),
            ("skin_indices", self.skin_indices, n_joints),
        ):
            if is_tracer(arr) or not arr.size:
                continue
            a = np.asarray(arr)  # on the host: no device program per check
            lo, top = int(a.min()), int(a.max())
            if lo < 0 or top >= hi:
                raise ValueError(f"`{name}` must hold indices in [0, {hi - 1}], got [{lo}, {top}].")

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    @property
    def n_vertices(self) -> int:
        return self.skin_indices.shape[0]

    def regress_joints(self, vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "J 3"]:
        """Joint positions as the fixed linear function of `vertices` `(V, 3)`; shape `(J, 3)`,
        in the units and frame of `vertices`."""
        return jnp.einsum(
            "jm,jmd->jd", self.regressor_weights, jnp.asarray(vertices)[self.regressor_indices]
        )

    def skin(
        self,
        vertices: Float[ArrayLike, "V 3"],
        transforms: Float[ArrayLike, "J 4 4"],
        *,
        method: str = "lbs",
    ) -> Float[Array, "V 3"]:
        """Skins rest `vertices` `(V, 3)` by per-joint world transforms `(J, 4, 4)` (those of
        [`bodyprior.forward_kinematics`][]): `method` `"lbs"` (linear blend, default) or `"dqs"`
        (dual quaternion). **Returns:** posed vertices `(V, 3)`."""
        if method not in ("lbs", "dqs"):
            raise ValueError(f"`method` must be 'lbs' or 'dqs', got {method!r}.")
        fn = lbs if method == "lbs" else dqs
        return fn(vertices, self.skin_indices, self.skin_weights, transforms)

    def astype(self, dtype) -> Rig:
        """The same rig with its weights in floating `dtype` (indices stay `int32`)."""
        return Rig(
            skin_indices=self.skin_indices,
            skin_weights=jnp.asarray(self.skin_weights, dtype),
            regressor_indices=self.regressor_indices,
            regressor_weights=jnp.asarray(self.regressor_weights, dtype),
            parents=self.parents,
            joint_names=self.joint_names,
        )


class RigHolder(eqx.Module):
    """Base of the Modules that carry a [`bodyprior.Rig`][] as their `rig` field (the default body,
    the S-SCAPE model, the registration template): the skeleton's counts and names, read from
    it."""

    rig: eqx.AbstractVar[Rig]

    @property
    def n_joints(self) -> int:
        """Number of joints `J`."""
        return self.rig.n_joints

    @property
    def parents(self) -> tuple[int, ...]:
        """Parent index of each joint (`-1` for the root)."""
        return self.rig.parents

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names, in joint order."""
        return self.rig.joint_names
