"""Mesh connectivity (`Topology`), built and validated once on the host.

Everything here is integer bookkeeping computed in NumPy from the face list: the unique undirected
edges, the two faces on either side of each edge and the vertices opposite it (the "hinge" or
"diamond" `i, j, k, l` used by dihedral angles and cotangent weights), the face -> edge map and
padded one-ring neighbour tables. The result is an `eqx.Module` whose arrays are leaves and whose
counts are static, so geometry kernels can gather with it under `jit`/`vmap`/`grad`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int

from ._validate import as_device_array, check_array, is_tracer

__all__ = ["Topology"]


class Topology(eqx.Module):
    """Connectivity of a triangle mesh: faces, edges, edge -> face adjacency and one-rings.

    Build it with [`bodyprior.Topology.from_faces`][], which validates the mesh (2-manifold edges,
    consistent orientation, indices in range) on the host. All index arrays are `int32`.

    **Edge conventions.** `edges[e] = (i, j)` with `i < j`. For an interior edge, `edge_faces[e, 0]`
    is the face `s` in which the directed edge `i -> j` appears in its counter-clockwise corner
    order and `edge_faces[e, 1]` is the face `t` holding `j -> i`; `edge_opposite[e] = (k, l)` are
    the vertices of `s` and `t` opposite the edge. With outward (CCW) orientation this makes `(x_j -
    x_i)` the edge direction "as oriented in `s`", which fixes the sign of
    [`bodyprior.dihedral_angles`][]. For a boundary edge the single adjacent face is always stored
    in slot 0 (whichever direction it holds the edge in) and slot 1 of `edge_faces`/`edge_opposite`
    is `-1`.

    **Fields:**

    - `faces`: `(F, 3)` vertex indices, counter-clockwise seen from outside.
    - `edges`: `(E, 2)` unique undirected edges, `edges[:, 0] < edges[:, 1]`, sorted
      lexicographically.
    - `edge_faces`: `(E, 2)` adjacent faces (see above), `-1` where missing.
    - `edge_opposite`: `(E, 2)` opposite vertices (see above), `-1` where missing.
    - `interior`: `(E,)` bool, `True` for edges with two adjacent faces.
    - `face_edges`: `(F, 3)` edge index of corner `c -> c + 1 (mod 3)` of each face.
    - `one_ring`: `(V, K)` neighbour vertices of each vertex in ascending index order, padded with
      `-1`; `K` is the maximum valence.
    - `valence`: `(V,)` number of neighbours of each vertex (0 for unreferenced vertices).
    - `n_vertices`, `n_faces`, `n_edges`: static counts `V`, `F`, `E`.
    - `has_boundary`: static bool, whether any edge has a single adjacent face.
    """

    faces: Int[Array, "F 3"]
    edges: Int[Array, "E 2"]
    edge_faces: Int[Array, "E 2"]
    edge_opposite: Int[Array, "E 2"]
    interior: Bool[Array, " E"]
    face_edges: Int[Array, "F 3"]
    one_ring: Int[Array, "V K"]
    valence: Int[Array, " V"]
    n_vertices: int = eqx.field(static=True)
    n_faces: int = eqx.field(static=True)
    n_edges: int = eqx.field(static=True)
    has_boundary: bool = eqx.field(static=True)

    @property
    def boundary_edges(self) -> Bool[Array, " E"]:
        """`(E,)` bool mask of boundary edges (edges with a single adjacent face)."""
        return jnp.logical_not(self.interior)

    @property
    def max_valence(self) -> int:
        """Width `K` of the padded `one_ring` table."""
        return int(self.one_ring.shape[1])

    @classmethod
    def from_faces(
        cls,
        faces,
        n_vertices: int | None = None,
        *,
        allow_boundary: bool = True,
    ) -> Topology:
        """Builds and validates the connectivity of a triangle mesh (host-side, NumPy).

        **Arguments:**

        - `faces`: `(F, 3)` integer array of vertex indices, counter-clockwise seen from outside.
          Must be concrete (not a tracer): topology is static.
        - `n_vertices`: number of vertices `V`; defaults to `faces.max() + 1`. Vertices not
          referenced by any face are allowed (valence 0).
        - `allow_boundary`: if `False`, reject meshes with boundary edges (require a closed
          surface).

        **Returns:** a [`bodyprior.Topology`][].

        **Raises:** `ValueError` (naming `faces` or `n_vertices`) if `faces` is not an `(F, 3)`
        integer array with `F >= 1`, an index lies outside `[0, n_vertices)`, a face repeats a
        vertex, an edge is shared by more than two faces (non-manifold), two faces traverse a shared
        edge in the same direction (inconsistent orientation), or the mesh has a boundary while
        `allow_boundary=False`.
        """
        if is_tracer(faces):
            raise ValueError("`faces` must be a concrete array (topology is static), got a tracer.")
        faces = np.asarray(check_array(faces, "faces", (None, 3), integer=True))
        n_faces = int(faces.shape[0])
        if n_faces == 0:
            raise ValueError("`faces` must contain at least one face, got shape (0, 3).")
        fmin, fmax = int(faces.min()), int(faces.max())
        if n_vertices is None:
            n_vertices = fmax + 1
        if isinstance(n_vertices, bool) or not isinstance(n_vertices, (int, np.integer)):
            raise ValueError(f"`n_vertices` must be an int, got {type(n_vertices).__name__}.")
        n_vertices = int(n_vertices)
        if n_vertices <= 0:
            raise ValueError(f"`n_vertices` must be positive, got {n_vertices}.")
        if fmin < 0 or fmax >= n_vertices:
            bad = int(np.argmax(np.any((faces < 0) | (faces >= n_vertices), axis=1)))
            raise ValueError(
                f"`faces` indices must lie in [0, {n_vertices}) (n_vertices={n_vertices}), "
                f"got values in [{fmin}, {fmax}]; first offending face {bad}: "
                f"{faces[bad].tolist()}."
            )
        faces = faces.astype(np.int64)
        degenerate = (
            (faces[:, 0] == faces[:, 1])
            | (faces[:, 1] == faces[:, 2])
            | (faces[:, 2] == faces[:, 0])
        )
        if degenerate.any():
            bad = int(np.argmax(degenerate))
            raise ValueError(
                f"`faces` has {int(degenerate.sum())} degenerate face(s) with a repeated vertex "
                f"index; first is face {bad}: {faces[bad].tolist()}."
            )

        # Half-edge h = 3 f + c goes from corner c to corner c + 1 of face f; its opposite vertex is
        # corner c + 2.
        src = faces.reshape(-1)
        dst = faces[:, [1, 2, 0]].reshape(-1)
        opp = faces[:, [2, 0, 1]].reshape(-1)
        he_face = np.repeat(np.arange(n_faces), 3)
        lo, hi = np.minimum(src, dst), np.maximum(src, dst)
        forward = src < dst
        keys = lo * n_vertices + hi
        ukeys, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        n_edges = int(ukeys.shape[0])
        edges = np.stack([ukeys // n_vertices, ukeys % n_vertices], axis=1)

        if counts.max() > 2:
            e = int(np.argmax(counts > 2))
            fs = he_face[inverse == e].tolist()
            raise ValueError(
                f"`faces` is not 2-manifold: edge ({edges[e, 0]}, {edges[e, 1]}) is shared by "
                f"{int(counts[e])} faces {fs}; every edge must belong to one or two faces."
            )
        n_forward = np.bincount(inverse, weights=forward, minlength=n_edges).astype(np.int64)
        inconsistent = (counts == 2) & (n_forward != 1)
        if inconsistent.any():
            e = int(np.argmax(inconsistent))
            fs = he_face[inverse == e].tolist()
            i, j = (edges[e, 0], edges[e, 1]) if n_forward[e] == 2 else (edges[e, 1], edges[e, 0])
            raise ValueError(
                f"`faces` is not consistently oriented: faces {fs} both traverse edge "
                f"({edges[e, 0]}, {edges[e, 1]}) in the direction {i} -> {j}; adjacent faces must "
                f"use a shared edge in opposite directions ({int(inconsistent.sum())} such "
                f"edge(s))."
            )
        interior = counts == 2
        if not allow_boundary and not interior.all():
            e = int(np.argmax(~interior))
            raise ValueError(
                f"`faces` must describe a closed surface (allow_boundary=False), but "
                f"{int((~interior).sum())} edge(s) have a single face, e.g. edge "
                f"({edges[e, 0]}, {edges[e, 1]})."
            )

        edge_faces = np.full((n_edges, 2), -1, dtype=np.int64)
        edge_opposite = np.full((n_edges, 2), -1, dtype=np.int64)
        slot = np.where(forward, 0, 1)
        edge_faces[inverse, slot] = he_face
        edge_opposite[inverse, slot] = opp
        # Boundary edges held only as j -> i: move the single face to slot 0.
        move = edge_faces[:, 0] < 0
        edge_faces[move] = edge_faces[move][:, ::-1]
        edge_opposite[move] = edge_opposite[move][:, ::-1]
        face_edges = inverse.reshape(n_faces, 3)

        # Padded one-rings: sort directed (vertex, neighbour) pairs, then place each in its row.
        a = np.concatenate([edges[:, 0], edges[:, 1]])
        b = np.concatenate([edges[:, 1], edges[:, 0]])
        order = np.lexsort((b, a))
        a, b = a[order], b[order]
        valence = np.bincount(a, minlength=n_vertices)
        start = np.concatenate([[0], np.cumsum(valence)[:-1]])
        col = np.arange(a.shape[0]) - start[a]
        one_ring = np.full((n_vertices, max(int(valence.max()), 1)), -1, dtype=np.int64)
        one_ring[a, col] = b

        i32 = lambda x: as_device_array(x, dtype=jnp.int32)
        return cls(
            faces=i32(faces),
            edges=i32(edges),
            edge_faces=i32(edge_faces),
            edge_opposite=i32(edge_opposite),
            interior=as_device_array(interior),
            face_edges=i32(face_edges),
            one_ring=i32(one_ring),
            valence=i32(valence),
            n_vertices=n_vertices,
            n_faces=n_faces,
            n_edges=n_edges,
            has_boundary=bool(not interior.all()),
        )
