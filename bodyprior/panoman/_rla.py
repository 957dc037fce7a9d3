"""RLA features (PanoMan eq. 1): relative edge lengths and relative dihedral angles.

For a mesh `V` and a reference mesh `r` on the same [`bodyprior.Topology`][] (PanoMan: the rest
shape of the same identity), every edge `e` gets

- `l̂(e) = l(e) / l_r(e) − 1` (dimensionless), and
- `â(e) = ψ(e) − ψ_r(e)` (radians), where `ψ` is the **interior** dihedral angle of the hinge
  ([`bodyprior.panoman.interior_dihedral_angles`][]: `π` for a flat hinge, `< π` for a convex
  fold), as the paper prints it (§4.1, "the inner included angle of its two adjacent triangles").

`ψ = π − θ` with `θ` the signed bending angle of [`bodyprior.dihedral_angles`][], so `â = θ_r − θ`:
this module is the one place where the sign is chosen, and the decoder and the shell energy use
it throughout.

**Angles through ±π.** `ψ` lives on a circle. A single mesh only determines `â` modulo `2π`:
[`bodyprior.panoman.rla_encode`][] returns the wrapped difference in `[−π, π)`. Data made by a
continuous deformation from the reference (the facial targets fold eyelid and lip edges by up to
6 rad) determine the true, unwrapped difference: [`bodyprior.panoman.rla_encode_path`][] sums the
wrapped increments along a path of meshes and [`bodyprior.panoman.rla_encode_unwrapped`][] does so
along the straight vertex path from the reference. [`bodyprior.panoman.fold_mask`][] marks the
hinges whose angle is within `ε` of a fold (`ψ → 0` or `2π`) or whose change is within `ε` of `±π`,
where the angle, or its wrap, is ill-determined (the discrete-shell energy gives them zero bending
weight, as Fröhlich & Botsch do).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._geometry import dihedral_angles, edge_lengths
from .._topology import Topology
from .._validate import check_array, check_positive_int, is_tracer

__all__ = [
    "RLA",
    "fold_mask",
    "interior_dihedral_angles",
    "rla_encode",
    "rla_encode_path",
    "rla_encode_unwrapped",
    "rla_targets",
    "wrap_angle",
]


class RLA(eqx.Module):
    """Relative edge lengths and relative dihedral angles of a mesh against a reference.

    **Fields** (leading batch axes allowed, e.g. after `jax.vmap`):

    - `lengths`: `(E,)` relative edge lengths `l / l_r − 1` (dimensionless).
    - `angles`: `(E,)` relative interior dihedral angles `ψ − ψ_r` in radians (see the module
      docstring for wrapping).

    `E = topology.n_edges`, in the order of `topology.edges`. `RLA.concat()` gives PanoMan's
    `2|E|` feature vector `[X_L; X_A]`.
    """

    lengths: Float[Array, "*b E"]
    angles: Float[Array, "*b E"]

    def concat(self) -> Float[Array, "*b E2"]:
        """`[lengths, angles]` along the last axis (PanoMan's `X = [X_L; X_A]`)."""
        return jnp.concatenate([self.lengths, self.angles], axis=-1)

    @classmethod
    def from_concat(cls, x: Float[ArrayLike, "*b E2"]) -> RLA:
        """Inverse of [`bodyprior.panoman.RLA.concat`][]."""
        x = jnp.asarray(x)
        if x.ndim < 1 or x.shape[-1] % 2:
            raise ValueError(f"`x` must have shape (..., 2E), got shape {tuple(x.shape)}.")
        n = x.shape[-1] // 2
        return cls(x[..., :n], x[..., n:])


def wrap_angle(x: Float[ArrayLike, "*s"]) -> Float[Array, "*s"]:
    """`x` wrapped to `[−π, π)` (radians); gradient 1 everywhere (NaN-free)."""
    x = jnp.asarray(x)
    two_pi = 2.0 * math.pi
    return x - two_pi * jax.lax.stop_gradient(jnp.floor((x + math.pi) / two_pi))


def interior_dihedral_angles(
    vertices: Float[ArrayLike, "V 3"], topology: Topology
) -> Float[Array, " E"]:
    """Interior dihedral angles `ψ = π − θ ∈ [0, 2π)` of every edge (PanoMan's `a(e)`).

    `θ` is [`bodyprior.dihedral_angles`][]' signed bending angle, so `ψ = π` on a flat hinge,
    `ψ < π` on a convex fold (outward normals), `ψ > π` on a concave one. Boundary edges get `π`.

    **Arguments:** `vertices` `(V, 3)` of one mesh (metres); `topology` its
    [`bodyprior.Topology`][].

    **Returns:** `(E,)` radians, NaN-free value and gradient (see `dihedral_angles`).
    """
    return math.pi - dihedral_angles(vertices, topology)


def _check_topology(topology) -> None:
    if not isinstance(topology, Topology):
        raise ValueError(f"`topology` must be a bodyprior.Topology, got {type(topology).__name__}.")


def _check_pair(vertices, reference, topology: Topology):
    _check_topology(topology)
    shape = (topology.n_vertices, 3)
    check_array(vertices, "vertices", shape)
    check_array(reference, "reference", shape)
    return jnp.asarray(vertices), jnp.asarray(reference)


def _lengths_rel(vertices, reference, topology):
    lr = edge_lengths(reference, topology)
    tiny = jnp.finfo(lr.dtype).tiny
    return edge_lengths(vertices, topology) / jnp.maximum(lr, tiny) - 1.0


def rla_encode(
    vertices: Float[ArrayLike, "V 3"], reference: Float[ArrayLike, "V 3"], topology: Topology
) -> RLA:
    """RLA features of one mesh against a reference (PanoMan eq. 1), angles wrapped.

    **Arguments:**

    - `vertices`: `(V, 3)` the mesh (metres), `V = topology.n_vertices`.
    - `reference`: `(V, 3)` the reference mesh (PanoMan: the identity's rest shape), same topology.
    - `topology`: the shared [`bodyprior.Topology`][].

    **Returns:** an [`bodyprior.panoman.RLA`][] with `lengths = l/l_r − 1` and
    `angles = wrap(ψ − ψ_r) ∈ [−π, π)`. Invariant to rigid motions of `vertices`. For a mesh made by
    a continuous deformation that folds hinges past `±π`, use
    [`bodyprior.panoman.rla_encode_unwrapped`][] or [`bodyprior.panoman.rla_encode_path`][].
    Batch with `jax.vmap`.

    **Raises:** `ValueError` for shapes other than `(V, 3)`.
    """
    vertices, reference = _check_pair(vertices, reference, topology)
    return _encode(vertices, reference, topology)


def _encode(vertices, reference, topology):
    a = interior_dihedral_angles(vertices, topology) - interior_dihedral_angles(reference, topology)
    return RLA(_lengths_rel(vertices, reference, topology), wrap_angle(a))


def rla_encode_path(path: Float[ArrayLike, "T V 3"], topology: Topology) -> RLA:
    """RLA of the last mesh of a path against its first, with angles **unwrapped along the path**.

    `â = Σ_k wrap(ψ(path[k+1]) − ψ(path[k]))`: exact as long as no hinge turns by `π` or more
    between consecutive meshes, and then free of the `2π` ambiguity of a single mesh (a hinge folded
    by 6 rad keeps its 6 rad).

    **Arguments:** `path` `(T, V, 3)`, `T ≥ 2`, consecutive meshes of a continuous deformation,
    `path[0]` the reference; `topology` their [`bodyprior.Topology`][].

    **Returns:** an [`bodyprior.panoman.RLA`][] of `path[-1]` against `path[0]`.
    """
    _check_topology(topology)
    check_array(path, "path", (None, topology.n_vertices, 3))
    if path.shape[0] < 2:
        raise ValueError(f"`path` needs at least 2 meshes, got {path.shape[0]}.")
    return _encode_path(jnp.asarray(path), topology)


def _encode_path(path, topology):
    psi = jax.vmap(interior_dihedral_angles, in_axes=(0, None))(path, topology)
    angles = jnp.sum(wrap_angle(jnp.diff(psi, axis=0)), axis=0)
    return RLA(_lengths_rel(path[-1], path[0], topology), angles)


def rla_encode_unwrapped(
    vertices: Float[ArrayLike, "V 3"],
    reference: Float[ArrayLike, "V 3"],
    topology: Topology,
    *,
    n_steps: int = 32,
) -> RLA:
    """RLA with angles unwrapped along the straight vertex path `r + s (V − r)`, `s ∈ [0, 1]`.

    The right encoding for data that are linear in a weight (blend-shape targets such as the facial
    actions, `r + w Δ`): it gives the angle change the deformation actually makes, not its value
    modulo `2π`. Equal to [`bodyprior.panoman.rla_encode`][] wherever no hinge passes through a
    fold on the way.

    **Arguments:** as `rla_encode`, plus `n_steps` (static int ≥ 1): path samples; each step must
    turn every hinge by less than `π` (32 is ample for the facial targets of the default body).
    """
    vertices, reference = _check_pair(vertices, reference, topology)
    n_steps = check_positive_int(n_steps, "n_steps")
    s = jnp.linspace(0.0, 1.0, n_steps + 1, dtype=vertices.dtype)[:, None, None]
    return _encode_path(reference + s * (vertices - reference), topology)


def rla_targets(
    rla: RLA, reference: Float[ArrayLike, "V 3"], topology: Topology
) -> tuple[Float[Array, " E"], Float[Array, " E"]]:
    """Absolute target lengths `l_r (1 + l̂)` (metres) and interior angles `ψ_r + â` (radians, not
    wrapped) of an RLA vector on a reference mesh."""
    _check_topology(topology)
    check_array(reference, "reference", (topology.n_vertices, 3))
    _check_rla(rla, topology)
    reference = jnp.asarray(reference)
    lr = edge_lengths(reference, topology)
    return lr * (1.0 + rla.lengths), interior_dihedral_angles(reference, topology) + rla.angles


def _check_rla(rla, topology: Topology, name: str = "rla"):
    if not isinstance(rla, RLA):
        raise ValueError(f"`{name}` must be a bodyprior.panoman.RLA, got {type(rla).__name__}.")
    check_array(rla.lengths, f"{name}.lengths", (topology.n_edges,))
    check_array(rla.angles, f"{name}.angles", (topology.n_edges,))


def fold_mask(
    rla: RLA,
    reference: Float[ArrayLike, "V 3"],
    topology: Topology,
    *,
    eps: float | Float[ArrayLike, ""] = 0.1,
) -> Bool[Array, " E"]:
    """Hinges whose angle is ill-determined: within `eps` of a fold, or changed by nearly `±π`.

    `True` where the target interior angle `ψ_r + â` (taken modulo `2π`) is within `eps` of `0` or
    `2π` — the two faces folded onto each other — or where `|â| > π − eps`, where the wrapped and
    the unwrapped differences may disagree. The discrete-shell energy zeroes the bending weight of
    these hinges (Fröhlich & Botsch's guard); the decoder uses them like any other.

    **Arguments:** `rla`, `reference` `(V, 3)`, `topology` as [`bodyprior.panoman.rla_targets`][];
    `eps` in radians, `0 < eps < π/2`.

    **Returns:** `(E,)` bool.
    """
    if not is_tracer(eps) and not 0.0 < float(eps) < math.pi / 2:
        raise ValueError(f"`eps` must lie in (0, π/2) radians, got {eps}.")
    _, psi = rla_targets(rla, reference, topology)
    theta = wrap_angle(math.pi - psi)  # signed bending angle of the target, in [−π, π)
    return (jnp.abs(theta) > math.pi - eps) | (jnp.abs(rla.angles) > math.pi - eps)
