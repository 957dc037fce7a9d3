"""PanoMan's discrete-shell energy (paper eqs. 6–8): residuals of a mesh against RLA targets.

For unknown vertices `V`, a shaped rest mesh `r` (PanoMan: `B_S(α)`) and RLA targets `X = (l̂*, â*)`
(PanoMan: `X̄ + M β + R(β)`, eq. 5), with `l_e` / `A_e` the rest edge length and the summed area of
the two triangles at `e` on `r`:

- stretch (eq. 7, identical to Fröhlich & Botsch):
  `s_e = (l_e(V) − l*_e) / l_e = l_e(V)/l_e − 1 − l̂*_e`;
- bending: `b_e = √k_b · w_e · wrap(ψ_e(V) − ψ*_e)` with `ψ* = ψ(r) + â*` and, by default
  (`bending="fb"`), the Fröhlich–Botsch / Grinspun weight `w_e = l_e / √A_e` (dimensionless,
  median 1.4–1.6 on every part of the default body). `bending="printed"` is the paper's eq. 8
  with its bracket moved to make it vanish at the target (`panoman_v2.md` §1.6 reading (b)):
  `w_e = l_e / A_e` (units 1/m; 22× stiffer on the head and hands than on the trunk, and
  dependent on the length unit).

`E = Σ s_e² + Σ b_e²` (eq. 6 without the constraint term). The angle residual is wrapped, and hinges
whose target is within `fold_eps` of a fold or whose change is within `fold_eps` of `±π`
([`bodyprior.panoman.fold_mask`][]) get zero bending weight (the F&B guard); boundary edges carry no
bending term. All of it is a differentiable function of `V`, of the rest mesh and of the targets, so
shape and motion parameters can be unknowns jointly with the vertices.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._geometry import _hinge_angles, _hinge_stencils, _safe_norm, edge_lengths, face_areas
from .._topology import Topology
from .._validate import check_array
from ._rla import RLA, _check_rla, _check_topology, fold_mask, interior_dihedral_angles, wrap_angle

__all__ = ["shell_energy", "shell_residuals"]

_BENDING = ("fb", "printed")


def _check(vertices, rest, rla, topology, bending, bending_stiffness, fold_eps):
    _check_topology(topology)
    check_array(vertices, "vertices", (topology.n_vertices, 3))
    check_array(rest, "rest", (topology.n_vertices, 3))
    _check_rla(rla, topology)
    if bending not in _BENDING:
        raise ValueError(f"`bending` must be one of {_BENDING}, got {bending!r}.")
    if not isinstance(bending_stiffness, (int, float)) or not bending_stiffness >= 0:
        raise ValueError(f"`bending_stiffness` must be a number >= 0, got {bending_stiffness!r}.")
    if not 0.0 < float(fold_eps) < math.pi / 2:
        raise ValueError(f"`fold_eps` must lie in (0, π/2) radians, got {fold_eps}.")


def shell_residuals(
    vertices: Float[ArrayLike, "V 3"],
    rest: Float[ArrayLike, "V 3"],
    rla: RLA,
    topology: Topology,
    *,
    bending: str = "fb",
    bending_stiffness: float = 1.0,
    fold_eps: float = 0.1,
) -> tuple[Float[Array, " E"], Float[Array, " E"]]:
    """Stretch and bending residuals of `vertices` against RLA targets on `rest` (module docstring).

    **Arguments:**

    - `vertices`: `(V, 3)` the deformed mesh (metres).
    - `rest`: `(V, 3)` the rest mesh the targets are relative to (PanoMan: `B_S(α)`); its edge
      lengths and hinge areas weight the residuals.
    - `rla`: the targets, an [`bodyprior.panoman.RLA`][] with `(E,)` leaves.
    - `topology`: the shared [`bodyprior.Topology`][].
    - `bending`: `"fb"` (weight `l/√A`, default) or `"printed"` (`l/A`).
    - `bending_stiffness`: `k_b ≥ 0`, the bending term's factor in the energy.
    - `fold_eps`: radians; hinges within it of a fold get zero bending weight.

    **Returns:** `(stretch, bend)`, each `(E,)`: dimensionless (`"printed"` bend in 1/m). Both are
    0 when `vertices` realise the targets exactly (e.g. `rla = rla_encode(vertices, rest, ...)`),
    up to a rigid motion. NaN-free values and gradients at flat, folded and zero-area hinges
    (zero-area hinges get zero bending weight).
    """
    _check(vertices, rest, rla, topology, bending, bending_stiffness, fold_eps)
    return _residuals(
        jnp.asarray(vertices),
        jnp.asarray(rest),
        rla,
        topology,
        bending,
        bending_stiffness,
        fold_eps,
    )


def _shell_terms(rest, rla, topology, bending, bending_stiffness, fold_eps):
    """What the residuals take from the rest mesh and the targets (neither depends on the
    deformed vertices): the safe rest lengths `(E,)`, the bending coefficients
    `√k_b · w_e` `(E,)` (0 on boundary, zero-area and fold-guarded hinges) and the target
    interior angles `ψ* = ψ(r) + â` `(E,)`."""
    lr = edge_lengths(rest, topology)
    tiny = jnp.finfo(lr.dtype).tiny
    lr_safe = jnp.maximum(lr, tiny)
    areas = face_areas(rest, topology.faces)
    ef = topology.edge_faces
    a_e = areas[ef[:, 0]] + jnp.where(topology.interior, areas[jnp.maximum(ef[:, 1], 0)], 0.0)
    ok = topology.interior & (a_e > 0) & ~fold_mask(rla, rest, topology, eps=fold_eps)
    a_safe = jnp.where(ok, a_e, 1.0)
    w = lr / (jnp.sqrt(a_safe) if bending == "fb" else a_safe)
    coef = jnp.where(ok, jnp.sqrt(bending_stiffness) * w, 0.0)
    psi_target = interior_dihedral_angles(rest, topology) + rla.angles
    return lr_safe, coef, psi_target


def _residuals(vertices, rest, rla, topology, bending, bending_stiffness, fold_eps):
    lr_safe, coef, psi_target = _shell_terms(
        rest, rla, topology, bending, bending_stiffness, fold_eps
    )
    stretch = edge_lengths(vertices, topology) / lr_safe - 1.0 - rla.lengths
    d = wrap_angle(interior_dihedral_angles(vertices, topology) - psi_target)
    return stretch, coef * d


def _jacobian_rows(vertices, lr_safe, coef, topology):
    """The explicit vertex Jacobian rows of the residuals `(s, b)` of `_residuals` (the
    deformed vertices only; rest mesh and targets held): stretch `(E, 6)` over the edge's two
    vertices `(i, j)`, bend `(E, 12)` over its hinge stencil `(i, j, k, l)` (as
    `bodyprior.dihedral_angles`; coordinates fastest). Per-edge gradients of the same kernels
    the residuals evaluate, so equal to the residuals' Jacobian to rounding: `∂s_e/∂x =
    ∂l_e/∂x / l_e`, `∂b_e/∂x = −√k_b w_e ∂θ_e/∂x` (`ψ = π − θ`, the wrap has slope 1)."""
    st = _hinge_stencils(topology)
    x = vertices[st]  # (E, 4, 3)

    def length(xi, xj):
        return _safe_norm(xj - xi)

    def angle(x4, interior):
        return _hinge_angles(x4[0], x4[1], x4[2], x4[3], interior)

    gi, gj = jax.vmap(jax.grad(length, argnums=(0, 1)))(x[:, 0], x[:, 1])
    js = jnp.concatenate([gi, gj], -1) / lr_safe[:, None]
    jb = jax.vmap(jax.grad(angle))(x, topology.interior).reshape(-1, 12) * (-coef)[:, None]
    return js, jb


def shell_energy(
    vertices: Float[ArrayLike, "V 3"],
    rest: Float[ArrayLike, "V 3"],
    rla: RLA,
    topology: Topology,
    **kwargs,
) -> Float[Array, ""]:
    """`E = Σ stretch² + Σ bend²` of [`bodyprior.panoman.shell_residuals`][] (same arguments)."""
    s, b = shell_residuals(vertices, rest, rla, topology, **kwargs)
    return jnp.sum(s * s) + jnp.sum(b * b)
