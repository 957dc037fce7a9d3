"""Posture normalization of registered meshes before shape-space learning (Pishchulin et al. 2017,
§3.4).

CAESAR subjects stand in a "standard" posture that still varies, mostly at the arms; PCA over raw
vertex coordinates then learns posture as shape. Two normalizations bring every registration into
one common posture while keeping its body shape. Neither is in the released humanshape code, so the
formulations below follow the paper's two paragraphs and `shared/research/sscape.md` §7; choices
made from memory or for this toolkit are marked *(choice)*.

**NH** (after Neophytou & Hilton 2013, "a skeleton model and Laplacian surface deformation"),
[`bodyprior.sscape.normalize_posture_nh`][]:

1. *Un-pose by the skeleton.* With the mesh's pose `theta` (the S-SCAPE fit's pose, or the true pose
   of a synthetic body) the world joint rotations `G_j` follow from forward kinematics. The rest
   joints are unknown for a registered mesh; they are found by a fixed-point iteration *(choice)*:
   start from the template joint regressor applied to the posed mesh, un-pose, re-regress the rest
   joints from the un-posed mesh, repeat (`n_joint_iter` rounds). The posed root stays where the
   regressor puts it on the posed mesh. Each vertex is un-posed by inverse linear blend skinning,
   `u_i = M_i^{-1} x_i` with `M_i = sum_j w_ij A_j` (exact for a mesh posed by LBS with the same
   weights).
2. *Laplacian surface deformation.* Inverse LBS is reliable where a vertex follows one bone, but
   it leaves artefacts near joints for meshes that were not posed by LBS (real scans). The final
   mesh solves `min_x ||L x - B_i^{-1} delta_i||^2 + omega^2 sum_{a in A} ||x_a - u_a||^2`: the
   posed mesh's Laplacian coordinates `delta = L x_posed`, each carried to the rest posture by its
   vertex's inverse blended linear map, with the inverse-LBS positions as soft anchors on the rigid
   vertices `A` (dominant skin weight `>= anchor_threshold` = 0.8, two thirds of the template;
   `omega` = 10) *(choice: the anchor set and weight, tuned on LBS-posed bodies; NH's own system
   is not reproduced)*. `laplacian=False` stops after
   step 1. The result is in the model's rest frame at the mesh's own scale.

**WSX** (after Wuhrer, Shu & Xi 2012, localized Laplacian coordinates),
[`bodyprior.sscape.normalize_posture_wsx`][]: the local geometry of each mesh `X` is expressed in
per-vertex frames `F_i(X) = [n_i, t_i, n_i x t_i]` (unit vertex normal; tangent projection of the
edge to the vertex's lowest-index neighbour *(choice)*), which makes it invariant to rigid motions
of each one-ring. As the paper does, each mesh is then rebuilt in the posture of the mean shape `Y`
("initializing each shape to the mean shape M and ... optimizing the localized Laplacian
coordinates to be as close as possible to the ones computed on M_i"): the local coordinates are
put back into `Y`'s frames and the mesh is solved by sparse least squares with one anchor vertex
(so `Y`'s proportions are not imposed). *(Choice, measured:)* the localized coordinates are the
one-ring **edge vectors** `F_i(X)^T (x_j - x_i)` rather than their weighted sum per vertex, the
Laplacian coordinate `delta_i`: rebuilding from per-vertex Laplacian coordinates is a bi-Laplacian
system that pins down limb lengths only through tiny tangential components, and on a body posed by
12 deg joint jitter it gave 40-50 mm mean error even with the true rest frames (20-150 mm with the
mean's frames), whereas the edge form (a Poisson system, `sum_e ||x_j - x_i - g_e||^2`) gives
about 10 mm with the mean's frames. Each edge target `g_e` is the edge carried by the rotations
`F_i(Y) F_i(X)^T` of its two end vertices, averaged. `n_iter > 1` re-estimates the frames from the
result (it drifts rather than improves on the bodies measured, so the default is one round). The
result is translated to `Y`'s centroid.

**Solver** *(choice)*: both normal-equation matrices `L^T L + omega^2 P^T P` depend only on the
template (topology, the fixed cotangent weights of the rest template, the anchor set), so each is
factorised **on the host** with SuperLU (`scipy.sparse.linalg.splu`, float64): the NH system once,
when [`bodyprior.sscape.posture_rig`][] builds the [`bodyprior.sscape.PostureRig`][] that carries
it (pass the rig instead of the template to reuse it), the WSX system per call (its anchor vertex
depends on the reference; ~25 ms). Every mesh, and every coordinate, is then one pair of
triangular solves (milliseconds for 6,449 vertices). A Krylov solver (lineax CG) on this
bi-Laplacian system would need thousands of iterations per right-hand side (its condition number
grows like `V^2`) for the same answer. The per-mesh parts (forward kinematics, inverse skinning,
normals, frames, Laplacian coordinates) are jitted JAX kernels for one mesh, `vmap`-ed for batches.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._geometry import cotangent_weights, laplacian_apply, laplacian_sparse, vertex_normals
from .._kinematics import world_transforms
from .._rig import Rig
from .._rotations import rotation_to_matrix
from .._topology import Topology
from .._validate import check_array
from ..registration._template import RegistrationTemplate
from ._model import SScapeModel

__all__ = [
    "PostureRig",
    "LaplacianSolver",
    "posture_rig",
    "unpose_lbs",
    "learn_normalized",
    "normalize_posture_nh",
    "normalize_posture_nh_batch",
    "normalize_posture_wsx",
    "normalize_posture_wsx_batch",
]


# --------------------------------------------------------------------------------------------------
# Rig and host-side solver


class PostureRig(eqx.Module):
    """What posture normalization needs of a template, precomputed once (arrays are leaves).

    Built by [`bodyprior.sscape.posture_rig`][] from a `RegistrationTemplate` or an `SScapeModel`,
    and accepted in place of the template by every function here, so that repeated calls reuse
    it.

    **Fields:** `rest` `(V, 3)` rest template (float64, defines the fixed cotangent weights),
    `topology` (the template's [`bodyprior.Topology`][]; `faces` is `topology.faces`), `weights`
    `(E,)` Laplacian edge weights, `rig` the template's [`bodyprior.Rig`][] in float64 (skin
    weights, joint regressor, bone tree), `neighbor` `(V,)` designated neighbour of each vertex
    (WSX frames); static `nh_solver`, the factorised NH system
    ([`bodyprior.sscape.LaplacianSolver`][]) for the soft-anchor parameters `anchor_threshold`,
    `anchor_weight` (static), or `None`. The jitted kernels never see `nh_solver`, so rigs built
    separately for one template share their compiled programs.
    """

    rest: Float[Array, "V 3"]
    topology: Topology
    weights: Float[Array, " E"]
    rig: Rig
    neighbor: Int[Array, " V"]
    anchor_threshold: float = eqx.field(static=True, default=0.8)
    anchor_weight: float = eqx.field(static=True, default=10.0)
    nh_solver: LaplacianSolver | None = eqx.field(static=True, default=None)

    @property
    def n_vertices(self) -> int:
        return self.rest.shape[0]

    @property
    def faces(self) -> Int[Array, "F 3"]:
        return self.topology.faces

    @property
    def parents(self) -> tuple[int, ...]:
        return self.rig.parents

    def _traced(self) -> PostureRig:
        """The rig without its host-side solver and anchor parameters (the kernels use neither):
        what the jitted kernels take, so that their compiled programs are not keyed by them."""
        return dataclasses.replace(self, nh_solver=None, anchor_threshold=0.0, anchor_weight=0.0)


class LaplacianSolver:
    """Host-side sparse least-squares solver for `min_x ||D x - b||^2 + sum_i omega_i^2 ||x_i -
    c_i||^2`, factorised once (SuperLU on the normal equations, float64). `D` is the rig's
    Laplacian `L` (`operator="laplacian"`, `b` per vertex) or its edge-difference operator
    (`operator="edges"`, `(D x)_e = x_j - x_i` for edge `e = (i, j)`, `b` per edge).

    Not a pytree: it is built and used outside `jit`.

    **Arguments:**

    - `rig`: a [`bodyprior.sscape.PostureRig`][].
    - `anchor_weight`: `(V,)` non-negative soft-anchor weights `omega_i` (zero = free vertex); at
      least one must be positive so that the system is non-singular.
    - `operator`: `"laplacian"` or `"edges"`.
    """

    def __init__(self, rig: PostureRig, anchor_weight, operator: str = "laplacian"):
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        w = np.asarray(anchor_weight, np.float64)
        if w.shape != (rig.n_vertices,) or np.any(w < 0) or not np.any(w > 0):
            raise ValueError(
                f"`anchor_weight` must be ({rig.n_vertices},), non-negative, with a positive entry."
            )
        if operator == "laplacian":
            d = laplacian_sparse(rig.topology, rig.weights).tocsc()
        elif operator == "edges":
            e = np.asarray(rig.topology.edges)
            ne = e.shape[0]
            rows = np.r_[np.arange(ne), np.arange(ne)]
            vals = np.r_[-np.ones(ne), np.ones(ne)]
            d = sp.csr_matrix((vals, (rows, np.r_[e[:, 0], e[:, 1]])), shape=(ne, rig.n_vertices))
        else:
            raise ValueError(f"`operator` must be 'laplacian' or 'edges', got {operator!r}.")
        self.D = d.tocsr()
        self.Dt = d.T.tocsr()
        self.w2 = w**2
        self._lu = spla.splu((self.Dt @ self.D + sp.diags(self.w2)).tocsc())
        self.n_vertices = rig.n_vertices

    def solve(self, b, anchors) -> np.ndarray:
        """Solves for a batch: `b` `(N, R, 3)` (R = V or E rows of `D`) and `anchors` `(N, V, 3)`
        (or unbatched); returns `(N, V, 3)` (or `(V, 3)`), float64."""
        b = np.asarray(b, np.float64)
        c = np.asarray(anchors, np.float64)
        single = b.ndim == 2
        if single:
            b, c = b[None], c[None]
        n, r, _ = b.shape
        v = self.n_vertices
        bt = np.ascontiguousarray(b.transpose(1, 0, 2).reshape(r, 3 * n))
        ct = np.ascontiguousarray(c.transpose(1, 0, 2).reshape(v, 3 * n))
        x = self._lu.solve(self.Dt @ bt + self.w2[:, None] * ct)
        x = x.reshape(v, n, 3).transpose(1, 0, 2)
        return x[0] if single else x


def _nh_anchor_weight(rig: PostureRig, threshold: float, weight: float) -> np.ndarray:
    """NH soft-anchor weights: `weight` on vertices whose largest skin weight reaches
    `threshold`, 0 elsewhere."""
    return np.where(np.asarray(rig.rig.skin_weights).max(1) >= threshold, float(weight), 0.0)


def _check_anchor_parameters(anchor_threshold, anchor_weight) -> tuple[float, float]:
    if not 0.0 < float(anchor_threshold) <= 1.0:
        raise ValueError(f"`anchor_threshold` must lie in (0, 1], got {anchor_threshold!r}.")
    if not float(anchor_weight) > 0:
        raise ValueError(f"`anchor_weight` must be positive, got {anchor_weight!r}.")
    return float(anchor_threshold), float(anchor_weight)


def posture_rig(
    template,
    *,
    weights: str = "cotangent",
    anchor_threshold: float = 0.8,
    anchor_weight: float = 10.0,
    factorize: bool = True,
) -> PostureRig:
    """Posture-normalization rig of a template, built once on the host (pass it in place of the
    template to the normalization functions to reuse it).

    **Arguments:**

    - `template`: a [`bodyprior.registration.RegistrationTemplate`][] (its topology and rig are
      used as they are) or [`bodyprior.sscape.SScapeModel`][] (its mean is the rest mesh; its
      topology is built from `faces` here).
    - `weights`: `"cotangent"` (cotangent weights of the rest template, default) or `"uniform"`.
      They are computed once and used for every mesh, so `L` is one fixed linear operator.
    - `anchor_threshold`, `anchor_weight`: the NH soft anchors the factorised NH system is built
      for (as in [`bodyprior.sscape.normalize_posture_nh_batch`][]; calls with other values
      factorise their own system).
    - `factorize`: factorise the NH system now (about 0.1 s at 6,449 vertices); `False` leaves
      `nh_solver` `None` (e.g. for WSX only, whose system depends on the data's anchor vertex and
      is factorised per call, about 25 ms).
    """
    if weights not in ("cotangent", "uniform"):
        raise ValueError(f"`weights` must be 'cotangent' or 'uniform', got {weights!r}.")
    threshold, weight = _check_anchor_parameters(anchor_threshold, anchor_weight)
    if isinstance(template, RegistrationTemplate):
        rest, rig, topo = template.vertices, template.rig, template.topology
    elif isinstance(template, SScapeModel):
        rest, rig, topo = template.mean, template.rig, None
    else:
        raise ValueError(
            "`template` must be a RegistrationTemplate or an SScapeModel, got "
            f"{type(template).__name__}."
        )
    rest = np.asarray(rest, np.float64)
    if topo is None:
        topo = Topology.from_faces(np.asarray(template.faces, np.int32), rest.shape[0])
    if weights == "cotangent":
        w = jnp.asarray(cotangent_weights(rest, topo), jnp.float64)
    else:
        w = jnp.ones(topo.n_edges, jnp.float64)
    out = PostureRig(
        rest=jnp.asarray(rest),
        topology=topo,
        weights=w,
        rig=rig.astype(jnp.float64),
        neighbor=jnp.asarray(np.asarray(topo.one_ring)[:, 0], jnp.int32),
        anchor_threshold=threshold,
        anchor_weight=weight,
    )
    if factorize:
        solver = LaplacianSolver(out, _nh_anchor_weight(out, threshold, weight), "laplacian")
        out = dataclasses.replace(out, nh_solver=solver)
    return out


def _nh_solver(rig: PostureRig, threshold: float, weight: float) -> LaplacianSolver:
    """The rig's own NH solver if it was built for these anchor parameters, else a new one."""
    if rig.nh_solver is not None and (rig.anchor_threshold, rig.anchor_weight) == (
        threshold,
        weight,
    ):
        return rig.nh_solver
    return LaplacianSolver(rig, _nh_anchor_weight(rig, threshold, weight), "laplacian")


def _wsx_solver(rig: PostureRig, anchor: int) -> LaplacianSolver:
    w = np.zeros(rig.n_vertices)
    w[anchor] = 1.0
    return LaplacianSolver(rig, w, "edges")


# --------------------------------------------------------------------------------------------------
# Kernels (one mesh)


def _regress(rig: PostureRig, x):
    return rig.rig.regress_joints(x)


def _blend(rig: PostureRig, a):
    """Blended 3x4 skinning transforms `M_i = sum_k w_ik A_{j_ik}`, shape `(V, 3, 4)`."""
    a12 = a[:, :3, :].reshape(a.shape[0], 12)
    m = jnp.einsum("vk,vkc->vc", rig.rig.skin_weights, a12[rig.rig.skin_indices])
    return m.reshape(-1, 3, 4)


def _unpose_known(rig: PostureRig, x, rotations, h, root):
    """Inverse LBS of `x` with rest joints `h` and the posed root joint at `root`."""
    g, t = world_transforms(rig.parents, rotations, h, root - h[0])
    a = jnp.concatenate([g, (t - jnp.einsum("jab,jb->ja", g, h))[:, :, None]], axis=-1)
    m = _blend(rig, a)
    b_inv = jnp.linalg.inv(m[:, :, :3])
    return jnp.einsum("vab,vb->va", b_inv, x - m[:, :, 3]), b_inv


def _unpose_kernel(rig: PostureRig, x, rotations, n_joint_iter: int):
    root = _regress(rig, x)[0]  # posed root position: the hip region moves with the root

    def unpose(h):
        return _unpose_known(rig, x, rotations, h, root)

    h = _regress(rig, x)
    # Fixed point h <- regress(unpose(x; h)); the error shrinks ~7x per round on the test bodies.
    h = jax.lax.fori_loop(0, n_joint_iter, lambda _, h: _regress(rig, unpose(h)[0]), h)
    return unpose(h)


def _frames(rig: PostureRig, x):
    n = vertex_normals(x, rig.faces)
    e = x[rig.neighbor] - x
    t = e - jnp.sum(e * n, -1, keepdims=True) * n
    t = t / jnp.maximum(jnp.linalg.norm(t, axis=-1, keepdims=True), 1e-12)
    return jnp.stack([n, t, jnp.cross(n, t)], axis=-1)  # (V, 3, 3), columns = frame axes


def _delta(rig: PostureRig, x):
    return laplacian_apply(x, rig.topology, rig.weights)


def _edge_targets(rig: PostureRig, x, frames_x, frames_ref):
    """WSX edge targets: each edge vector of `x`, carried from `x`'s local frames to the reference
    frames, averaged over the edge's two end vertices. Shape `(E, 3)`."""
    e = rig.topology.edges
    d = x[e[:, 1]] - x[e[:, 0]]
    r = jnp.einsum("vab,vcb->vac", frames_ref, frames_x)  # F_ref F_x^T, a rotation per vertex
    return 0.5 * (jnp.einsum("eab,eb->ea", r[e[:, 0]], d) + jnp.einsum("eab,eb->ea", r[e[:, 1]], d))


@eqx.filter_jit
def _nh_prepare(rig: PostureRig, x, rotations, n_joint_iter: int):
    def one(xi, ri):
        u, b_inv = _unpose_kernel(rig, xi, ri, n_joint_iter)
        b = jnp.einsum("vab,vb->va", b_inv, _delta(rig, xi))
        return u, b

    return jax.vmap(one)(x, rotations)


@eqx.filter_jit
def _nh_prepare_known(rig: PostureRig, x, rotations, rest_joints):
    def one(xi, ri, hi):
        # With known rest joints the posed root follows from them and the pose (zero root shift).
        u, b_inv = _unpose_known(rig, xi, ri, hi, hi[0])
        return u, jnp.einsum("vab,vb->va", b_inv, _delta(rig, xi))

    return jax.vmap(one)(x, rotations, rest_joints)


@eqx.filter_jit
def _wsx_frames(rig: PostureRig, x):
    return jax.vmap(lambda xi: _frames(rig, xi))(x)


@eqx.filter_jit
def _wsx_rhs(rig: PostureRig, x, frames_x, current):
    def one(xi, fi, ci):
        return _edge_targets(rig, xi, fi, _frames(rig, ci))

    return jax.vmap(one)(x, frames_x, current)


# --------------------------------------------------------------------------------------------------
# Public API


def _pose_matrices(pose, n_joints: int, name: str = "pose"):
    pose = jnp.asarray(pose)
    if pose.shape[-2:] == (3, 3):
        return pose
    return jax.vmap(jax.vmap(lambda r: rotation_to_matrix(r, "axis_angle")))(pose)


def _check_meshes(meshes, rig: PostureRig, name: str):
    dims: dict[str, int] = {}
    check_array(meshes, name, ("N", rig.n_vertices, 3), dims=dims)
    return jnp.asarray(meshes, jnp.float64), dims["N"]


def unpose_lbs(
    vertices: Float[ArrayLike, "V 3"], pose, template, *, n_joint_iter: int = 6
) -> Float[Array, "V 3"]:
    """Inverse linear blend skinning of one posed mesh (NH step 1, see the module docstring).

    **Arguments:**

    - `vertices`: posed mesh `(V, 3)`, metres, in the model frame (global similarity removed).
    - `pose`: its pose, `(J, 3)` axis-angle (or `(J, 3, 3)` matrices), the convention of
      [`bodyprior.sscape.evaluate`][].
    - `template`: `RegistrationTemplate` or `SScapeModel` (rig), or a `PostureRig`.
    - `n_joint_iter`: rounds of the rest-joint fixed point.

    **Returns:** the un-posed mesh `(V, 3)`, float64.
    """
    rig = template if isinstance(template, PostureRig) else posture_rig(template, factorize=False)
    x, _ = _check_meshes(jnp.asarray(vertices)[None], rig, "vertices")
    nj = len(rig.parents)
    check_array(pose, "pose", (nj, 3) if np.ndim(pose) == 2 else (nj, 3, 3))
    r = _pose_matrices(jnp.asarray(pose, jnp.float64)[None], len(rig.parents))
    u, _ = _nh_prepare(rig._traced(), x, r, int(n_joint_iter))
    return u[0]


def normalize_posture_nh_batch(
    meshes: Float[ArrayLike, "N V 3"],
    poses,
    template,
    *,
    similarities=None,
    laplacian: bool = True,
    anchor_threshold: float = 0.8,
    anchor_weight: float = 10.0,
    n_joint_iter: int = 6,
    rest_joints=None,
    weights: str = "cotangent",
) -> Float[np.ndarray, "N V 3"]:
    """NH posture normalization of `N` registered meshes to the rest (zero) posture.

    **Arguments:**

    - `meshes`: registrations `(N, V, 3)`, metres (in the scan frame if `similarities` is given).
    - `poses`: their poses `(N, J, 3)` axis-angle (e.g. `SScapeFit.pose`), or `(N, J, 3, 3)`.
    - `template`: `RegistrationTemplate` or `SScapeModel` whose rig the poses refer to.
    - `similarities`: optional batched `Similarity` (e.g. `SScapeFit.similarity`) mapping the model
      frame to each scan; it is undone first (rotation and translation; the scale is kept, so the
      result has the subject's real size).
    - `laplacian`: run the Laplacian surface deformation (step 2); `False` = inverse LBS only.
    - `anchor_threshold`: vertices whose largest skin weight reaches this are soft anchors.
    - `anchor_weight`: `omega`, relative to the Laplacian term.
    - `n_joint_iter`: rounds of the rest-joint fixed point.
    - `rest_joints`: optional known rest joints `(N, J, 3)` in the model frame (e.g. the S-SCAPE
      fit's); then the fixed point is skipped. With the template regressor (held-out joint error
      ~4 mm on sampled bodies) inverse LBS leaves 1-4 mm; with the true joints it is exact.
    - `weights`: Laplacian weights, `"cotangent"` (of the rest template) or `"uniform"`.

    **Returns:** normalized meshes `(N, V, 3)`, float64 NumPy, in the model's rest frame.
    """
    threshold, weight = _check_anchor_parameters(anchor_threshold, anchor_weight)
    if isinstance(template, PostureRig):
        rig = template
    else:
        rig = posture_rig(template, weights=weights, anchor_threshold=threshold,
                          anchor_weight=weight, factorize=bool(laplacian))  # fmt: skip
    x, n = _check_meshes(meshes, rig, "meshes")
    j = len(rig.parents)
    if np.ndim(poses) == 3:
        check_array(poses, "poses", (n, j, 3))
    else:
        check_array(poses, "poses", (n, j, 3, 3))
    scale = np.ones(n)
    if similarities is not None:
        rot = jnp.asarray(similarities.rotation, jnp.float64)
        tr = jnp.asarray(similarities.translation, jnp.float64)
        if rot.shape != (n, 3, 3) or tr.shape != (n, 3):
            raise ValueError(f"`similarities` must be a batched Similarity of {n} transforms.")
        scale = np.asarray(jnp.exp(jnp.asarray(similarities.log_scale, jnp.float64))).reshape(n)
        x = jnp.einsum("nvb,nba->nva", x - tr[:, None], rot) / scale[:, None, None]
    r = _pose_matrices(jnp.asarray(poses, jnp.float64), j)
    if rest_joints is None:
        u, b = _nh_prepare(rig._traced(), x, r, int(n_joint_iter))
    else:
        check_array(rest_joints, "rest_joints", (n, j, 3))
        u, b = _nh_prepare_known(rig._traced(), x, r, jnp.asarray(rest_joints, jnp.float64))
    if laplacian:
        solver = _nh_solver(rig, threshold, weight)
        out = solver.solve(np.asarray(b), np.asarray(u))
    else:
        out = np.asarray(u)
    return out * scale[:, None, None]


def normalize_posture_nh(
    vertices: Float[ArrayLike, "V 3"], pose, template, *, similarity=None, **kw
):
    """NH posture normalization of one mesh; see [`bodyprior.sscape.normalize_posture_nh_batch`][]
    for the arguments (`similarity` is one `Similarity`). **Returns:** `(V, 3)` float64."""
    sims = None
    if similarity is not None:
        sims = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], similarity)
    return normalize_posture_nh_batch(
        jnp.asarray(vertices)[None], jnp.asarray(pose)[None], template, similarities=sims, **kw
    )[0]


def _anchor_vertex(reference: np.ndarray) -> int:
    # The vertex nearest to the reference centroid: a torso vertex, away from the limbs.
    return int(np.argmin(np.linalg.norm(reference - reference.mean(0), axis=1)))


def normalize_posture_wsx_batch(
    meshes: Float[ArrayLike, "N V 3"],
    template,
    *,
    reference: Float[ArrayLike, "V 3"] | None = None,
    n_iter: int = 1,
    weights: str = "cotangent",
) -> Float[np.ndarray, "N V 3"]:
    """WSX posture normalization of `N` meshes into the posture of a reference (default: their
    mean after rigid Procrustes alignment, the paper's mean shape `M`).

    **Arguments:**

    - `meshes`: registrations `(N, V, 3)`, metres, any rigid placement.
    - `template`: `RegistrationTemplate` or `SScapeModel` (topology, fixed Laplacian weights).
    - `reference`: `(V, 3)` mesh whose posture is imposed; default: the Procrustes mean of `meshes`.
    - `n_iter`: fixed-point rounds (frames re-estimated from the current result each round).
    - `weights`: `"cotangent"` (of the rest template) or `"uniform"`.

    **Returns:** normalized meshes `(N, V, 3)`, float64 NumPy, in the reference's frame, centred at
    the reference's centroid.
    """
    if isinstance(template, PostureRig):
        rig = template
    else:
        rig = posture_rig(template, weights=weights, factorize=False)
    x, n = _check_meshes(meshes, rig, "meshes")
    if isinstance(n_iter, bool) or not isinstance(n_iter, (int, np.integer)) or n_iter < 1:
        raise ValueError(f"`n_iter` must be a positive int, got {n_iter!r}.")
    if reference is None:
        from ._learn import procrustes_align

        aligned, _ = procrustes_align(x)
        y = np.asarray(aligned, np.float64).mean(0)
    else:
        check_array(reference, "reference", (rig.n_vertices, 3))
        y = np.asarray(reference, np.float64)
    solver = _wsx_solver(rig, _anchor_vertex(y))
    rig = rig._traced()
    frames_x = _wsx_frames(rig, x)
    anchors = np.broadcast_to(y, (n, *y.shape))
    cur = jnp.broadcast_to(jnp.asarray(y), (n, *y.shape))
    for _ in range(int(n_iter)):  # host loop over rounds: one jitted call + one solve each
        b = _wsx_rhs(rig, x, frames_x, cur)
        cur = jnp.asarray(solver.solve(np.asarray(b), anchors))
    out = np.asarray(cur)
    return out - out.mean(1, keepdims=True) + y.mean(0)


def normalize_posture_wsx(
    vertices: Float[ArrayLike, "V 3"], template, *, reference: Float[ArrayLike, "V 3"], **kw
) -> Float[np.ndarray, "V 3"]:
    """WSX posture normalization of one mesh into the posture of `reference`; see
    [`bodyprior.sscape.normalize_posture_wsx_batch`][]. **Returns:** `(V, 3)` float64."""
    return normalize_posture_wsx_batch(
        jnp.asarray(vertices)[None], template, reference=reference, **kw
    )[0]


def learn_normalized(
    meshes: Float[ArrayLike, "N V 3"],
    template,
    method: str,
    *,
    poses=None,
    similarities=None,
    n_components: int | None = None,
    **kw,
) -> tuple[SScapeModel, np.ndarray]:
    """Normalizes a training set (`method` = `"none"`, `"nh"` or `"wsx"`) and learns its S-SCAPE
    space with [`bodyprior.sscape.learn`][] and the rig of `template` (a `RegistrationTemplate`, or
    an `SScapeModel` whose rig and frame are reused).

    **Returns:** `(model, normalized_meshes (N, V, 3))`. `"nh"` needs `poses` (and optionally
    `similarities`); extra keywords go to the normalization.
    """
    from ._learn import learn

    if method == "none":
        norm = np.asarray(meshes, np.float64)
    elif method == "nh":
        if poses is None:
            raise ValueError("`poses` is required for method='nh'.")
        norm = normalize_posture_nh_batch(meshes, poses, template, similarities=similarities, **kw)
    elif method == "wsx":
        norm = normalize_posture_wsx_batch(meshes, template, **kw)
    else:
        raise ValueError(f"`method` must be 'none', 'nh' or 'wsx', got {method!r}.")
    if isinstance(template, SScapeModel):
        model = learn(
            jnp.asarray(norm), template.faces, n_components=n_components, template=template
        )
    else:
        model = learn(
            jnp.asarray(norm), template.faces, n_components=n_components, rig=template.rig
        )
    return model, norm
