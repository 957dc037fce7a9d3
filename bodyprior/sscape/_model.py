"""The S-SCAPE model container and its forward evaluation.

S-SCAPE (Pishchulin et al. 2017, after Jain et al. 2010) is a PCA shape space over the vertices of a
fixed template, rigged with linear blend skinning. Joint positions are not stored: they are a fixed
linear function of the *shaped* rest vertices (humanshape ties each joint to the surface region
shared by two adjacent body segments), so they follow the body shape exactly.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._kinematics import Similarity, forward_kinematics
from .._rig import Rig, RigHolder, _float_leaf, _int_leaf
from .._rotations import euler_to_matrix, rotation_to_matrix
from .._skinning import lbs
from .._validate import check_array, is_tracer

_REP_SHAPES = {
    "axis_angle": (3,),
    "matrix": (3, 3),
    "quaternion": (4,),
    "sixd": (6,),
}


class SScapeModel(RigHolder):
    """An S-SCAPE body model: a PCA shape space over a rigged template mesh.

    Arrays are leaves; the kinematic tree and joint names (in `rig`) are static.

    **Fields:**

    - `mean`: mean rest shape, shape `(V, 3)`, metres.
    - `basis`: principal directions, shape `(K, V, 3)`, orthonormal in the flattened `(V*3,)` space.
    - `stddev`: standard deviation of the training data along each direction, shape `(K,)`, metres.
    - `explained_variance`: fraction of the total training variance explained by each component,
      shape `(K,)` (sums to at most one; less after truncation).
    - `faces`: triangles, shape `(F, 3)`, int32, 0-based, outward oriented.
    - `rig`: the [`bodyprior.Rig`][] over the `V` vertices: bone tree (`parents[0] == -1`), joint
      names, top-k skin weights (rows sum to one) and the sparse joint regressor (joint `j` sits at
      `sum_m w[j, m] * vertices[idx[j, m]]`).

    The rig's parts are also readable under their former field names (`parents`, `joint_names`,
    `skin_indices`, `skin_weights`, `joint_regressor_indices`, `joint_regressor_weights`).
    """

    mean: Float[Array, "V 3"] = eqx.field(converter=_float_leaf)
    basis: Float[Array, "K V 3"] = eqx.field(converter=_float_leaf)
    stddev: Float[Array, " K"] = eqx.field(converter=_float_leaf)
    explained_variance: Float[Array, " K"] = eqx.field(converter=_float_leaf)
    faces: Int[Array, "F 3"] = eqx.field(converter=_int_leaf)
    rig: Rig

    def __check_init__(self):
        dims: dict[str, int] = {}
        check_array(self.mean, "mean", ("V", 3), dims=dims, finite=False)
        check_array(self.basis, "basis", ("K", "V", 3), dims=dims, finite=False)
        check_array(self.stddev, "stddev", ("K",), dims=dims, finite=False)
        check_array(self.explained_variance, "explained_variance", ("K",), dims=dims, finite=False)
        check_array(self.faces, "faces", (None, 3), integer=True)
        if not isinstance(self.rig, Rig):
            raise ValueError(f"`rig` must be a bodyprior.Rig, got {type(self.rig).__name__}.")
        n_vertices = dims["V"]
        if self.rig.n_vertices != n_vertices:
            raise ValueError(
                f"`rig` must skin the model's {n_vertices} vertices, got skin weights for "
                f"{self.rig.n_vertices}."
            )
        if not is_tracer(self.faces) and self.faces.size:
            f = np.asarray(self.faces)  # on the host: no device program per check
            if int(f.min()) < 0 or int(f.max()) >= n_vertices:
                raise ValueError(
                    f"`faces` must hold indices in [0, {n_vertices - 1}], got [{int(f.min())}, "
                    f"{int(f.max())}]."
                )

    @property
    def skin_indices(self) -> Int[Array, "V Kw"]:
        return self.rig.skin_indices

    @property
    def skin_weights(self) -> Float[Array, "V Kw"]:
        return self.rig.skin_weights

    @property
    def joint_regressor_indices(self) -> Int[Array, "J M"]:
        return self.rig.regressor_indices

    @property
    def joint_regressor_weights(self) -> Float[Array, "J M"]:
        return self.rig.regressor_weights

    @property
    def n_vertices(self) -> int:
        return self.mean.shape[0]

    @property
    def n_components(self) -> int:
        return self.basis.shape[0]

    def shape_vertices(self, shape_coeffs) -> Float[Array, "V 3"]:
        """Method form of [`bodyprior.sscape.shape_vertices`][]."""
        return shape_vertices(self, shape_coeffs)

    def rest_joints(self, vertices) -> Float[Array, "J 3"]:
        """Method form of [`bodyprior.sscape.rest_joints`][]."""
        return rest_joints(self, vertices)

    def evaluate(
        self,
        shape_coeffs,
        pose,
        transform=None,
        root_translation=None,
        *,
        pose_rep: str = "axis_angle",
    ):
        """Method form of [`bodyprior.sscape.evaluate`][]."""
        return evaluate(self, shape_coeffs, pose, transform, root_translation, pose_rep=pose_rep)

    def truncate(self, n_components: int) -> SScapeModel:
        """Method form of [`bodyprior.sscape.truncate`][]."""
        return truncate(self, n_components)


def _check_model(model):
    if not isinstance(model, SScapeModel):
        raise ValueError(f"`model` must be an SScapeModel, got {type(model).__name__}.")


def _check_shape_coeffs(model: SScapeModel, shape_coeffs):
    shape_coeffs = check_array(shape_coeffs, "shape_coeffs", (None,))
    if shape_coeffs.shape[0] > model.n_components:
        raise ValueError(
            f"`shape_coeffs` must have at most {model.n_components} entries (the model's number of "
            f"components), got {shape_coeffs.shape[0]}."
        )
    return shape_coeffs


def shape_vertices(
    model: SScapeModel, shape_coeffs: Float[ArrayLike, " Kp"]
) -> Float[Array, "V 3"]:
    """Rest-pose vertices of a body shape.

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][].
    - `shape_coeffs`: shape coefficients in units of standard deviations, shape `(K',)` with
      `K' <= model.n_components`; the first `K'` components are used.

    **Returns:** `mean + sum_k c_k stddev_k basis_k`, shape `(V, 3)`.
    """
    _check_model(model)
    c = _check_shape_coeffs(model, shape_coeffs)
    k = c.shape[0]
    if k == 0:
        return model.mean
    scaled = jnp.asarray(c) * model.stddev[:k]
    return model.mean + jnp.tensordot(scaled, model.basis[:k], axes=1)


def rest_joints(model: SScapeModel, vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "J 3"]:
    """Joint rest positions regressed from (shaped) rest vertices, shape `(J, 3)`.

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][].
    - `vertices`: rest vertices, shape `(V, 3)`.
    """
    _check_model(model)
    check_array(vertices, "vertices", (model.n_vertices, 3))
    return model.rig.regress_joints(vertices)


def _pose_to_matrices(pose, pose_rep: str, n_joints: int):
    if pose_rep.startswith("euler_"):
        order = pose_rep[len("euler_") :]
        check_array(pose, "pose", (n_joints, 3))
        return jax.vmap(lambda a: euler_to_matrix(a, order))(jnp.asarray(pose))
    if pose_rep not in _REP_SHAPES:
        raise ValueError(
            f"`pose_rep` must be one of {sorted(_REP_SHAPES)} or 'euler_<ORDER>' (e.g. "
            f"'euler_ZYX'), "
            f"got {pose_rep!r}."
        )
    check_array(pose, "pose", (n_joints, *_REP_SHAPES[pose_rep]))
    return jax.vmap(lambda x: rotation_to_matrix(x, pose_rep))(jnp.asarray(pose))


def evaluate(
    model: SScapeModel,
    shape_coeffs: Float[ArrayLike, " Kp"],
    pose: Array,
    transform: Similarity | None = None,
    root_translation: Float[ArrayLike, " 3"] | None = None,
    *,
    pose_rep: str = "axis_angle",
    subset: Int[ArrayLike, " S"] | None = None,
) -> tuple[Float[Array, "V 3"], Float[Array, "J 3"]]:
    """Shapes, poses and places one body.

    Rest vertices come from [`bodyprior.sscape.shape_vertices`][], joints from the regressor
    applied to them, then forward kinematics (the convention of `docs/architecture.md`: local
    rotations in world-aligned rest axes) and linear blend skinning; the global similarity
    `transform` is applied last, to vertices and joints alike (`x -> s R x + t`).

    Pure; jit/vmap/grad it from outside (`pose_rep` must be static, e.g. via `eqx.filter_jit`).
    Written for one body: `jax.vmap` over coefficients/poses for batches.

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][].
    - `shape_coeffs`: shape `(K',)`, `K' <= K`, in standard deviations.
    - `pose`: per-joint local rotations, `(J, 3)` axis-angle by default; `(J, 3, 3)` for
      `pose_rep="matrix"`, `(J, 4)` wxyz for `"quaternion"`, `(J, 6)` for `"sixd"`, `(J, 3)` angles
      for `"euler_<ORDER>"` (e.g. `"euler_ZYX"`, the order string is passed to `euler_to_matrix`).
    - `transform`: optional global `Similarity`, applied after skinning.
    - `root_translation`: shape `(3,)`, default zeros; moves the root joint before `transform`.
    - `pose_rep`: rotation representation of `pose` (static).
    - `subset`: optional int `(S,)` vertex indices: skin only these (e.g. landmark vertices; the
      joints still come from the whole shaped mesh), returning `(S, 3)` posed vertices equal to
      the full result's rows at a fraction of the cost (a fitter's landmark stage).

    **Returns:** `(vertices, joints)`: posed vertices `(V, 3)` (or `(S, 3)`) and posed joints
    `(J, 3)`.
    """
    _check_model(model)
    c = _check_shape_coeffs(model, shape_coeffs)
    if not isinstance(pose_rep, str):
        raise ValueError(f"`pose_rep` must be a string, got {type(pose_rep).__name__}.")
    rotations = _pose_to_matrices(pose, pose_rep, model.n_joints)
    if root_translation is None:
        root_translation = jnp.zeros((3,), dtype=model.mean.dtype)
    else:
        root_translation = jnp.asarray(check_array(root_translation, "root_translation", (3,)))
    if transform is not None and not isinstance(transform, Similarity):
        raise ValueError(
            f"`transform` must be a Similarity or None, got {type(transform).__name__}."
        )

    rest = shape_vertices(model, c)
    joints = rest_joints(model, rest)
    transforms, posed_joints = forward_kinematics(
        model.parents, rotations, joints, root_translation
    )
    if subset is None:
        posed = model.rig.skin(rest, transforms)
    else:
        subset = jnp.asarray(check_array(subset, "subset", ("S",)))
        if not jnp.issubdtype(subset.dtype, jnp.integer):
            raise ValueError(f"`subset` must hold integer vertex indices, got {subset.dtype}.")
        rig = model.rig
        posed = lbs(rest[subset], rig.skin_indices[subset], rig.skin_weights[subset], transforms)
    if transform is not None:
        posed = transform.apply(posed)
        posed_joints = transform.apply(posed_joints)
    return posed, posed_joints


def truncate(model: SScapeModel, n_components: int) -> SScapeModel:
    """Keeps the first `n_components` principal components (host-side, outside jit).

    **Arguments:**

    - `model`: an [`bodyprior.sscape.SScapeModel`][].
    - `n_components`: integer in `[0, model.n_components]`.

    **Returns:** a new model whose `basis`, `stddev` and `explained_variance` are truncated.
    """
    _check_model(model)
    if isinstance(n_components, bool) or not isinstance(n_components, (int, np.integer)):
        raise ValueError(f"`n_components` must be an int, got {type(n_components).__name__}.")
    n = int(n_components)
    if not 0 <= n <= model.n_components:
        raise ValueError(f"`n_components` must lie in [0, {model.n_components}], got {n}.")
    return eqx.tree_at(
        lambda m: (m.basis, m.stddev, m.explained_variance),
        model,
        (model.basis[:n], model.stddev[:n], model.explained_variance[:n]),
    )
