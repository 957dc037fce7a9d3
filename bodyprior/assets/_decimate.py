"""Vertex-subset decimation of the default body (host-side NumPy, runs once at asset build).

`decimate_subset` simplifies a triangle mesh with quadric-error-metric (Garland-Heckbert)
*half-edge* collapses: collapsing `u -> v` deletes `u` and keeps `v` at its original position, so
every surviving vertex is one of the input vertices and a body in the full topology maps to the
decimated one with `vertices[..., vertex_map, :]`.

`python -m bodyprior.assets._decimate` decimates the embedded default body to the S-SCAPE template's
6,449 vertices and writes `default_body_decimated.npz` next to `default_body.npz` (which it does not
touch). `load_decimated()` reads it back and checks that it was built from the current default body.
"""

from __future__ import annotations

import heapq
import json
import os
import tempfile
import time

import numpy as np

from . import asset_path

DECIMATED_NAME = "default_body_decimated.npz"
DECIMATED_FORMAT = "bodyprior.default_body_decimated"
DECIMATED_FORMAT_VERSION = 1
PAPER_VERTEX_COUNT = 6449  # vertices of the S-SCAPE template

_BOUNDARY_WEIGHT = 1000.0  # weight of the perpendicular constraint planes along boundary edges
_MIN_NORMAL_COS = 0.0  # reject a collapse turning any surviving face by more than 90 degrees
_MIN_COMPACTNESS = (
    0.03  # reject a collapse creating a sliver (4*sqrt(3)*area / sum of squared edges)
)


def decimated_path() -> str:
    """Path of the committed decimated-topology asset."""
    return os.path.join(os.path.dirname(__file__), DECIMATED_NAME)


def _plane_quadrics(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex sums of area-weighted face quadrics `(V, 4, 4)`, plus boundary planes."""
    V = len(vertices)
    p0, p1, p2 = (vertices[faces[:, c]] for c in range(3))
    n = np.cross(p1 - p0, p2 - p0)
    dbl_area = np.linalg.norm(n, axis=1)
    nu = n / np.maximum(dbl_area, 1e-300)[:, None]
    plane = np.concatenate([nu, -np.einsum("fi,fi->f", nu, p0)[:, None]], axis=1)
    K = 0.5 * dbl_area[:, None, None] * plane[:, :, None] * plane[:, None, :]
    Q = np.zeros((V, 4, 4))
    for c in range(3):
        np.add.at(Q, faces[:, c], K)
    # Boundary edges (directed, without a twin): plane through the edge, perpendicular to its face.
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    keys = set(map(tuple, directed.tolist()))
    is_bnd = np.array([(b, a) not in keys for a, b in directed.tolist()], dtype=bool)
    for (a, b), f in zip(directed[is_bnd], owner[is_bnd]):
        e = vertices[b] - vertices[a]
        length = np.linalg.norm(e)
        m = np.cross(e, nu[f])
        mn = np.linalg.norm(m)
        if mn == 0.0:
            continue
        m /= mn
        pl = np.append(m, -m @ vertices[a])
        Kb = _BOUNDARY_WEIGHT * length * length * np.outer(pl, pl)
        Q[a] += Kb
        Q[b] += Kb
    return Q


def mirror_map(vertices: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Index of each vertex's mirror image across x = 0 (an involution); raises if inexact."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(vertices).query(vertices * np.array([-1.0, 1.0, 1.0]))
    if d.max() > tol or not np.array_equal(idx[idx], np.arange(len(vertices))):
        raise ValueError(f"mesh is not left-right symmetric (max mirror mismatch {d.max():.3g}).")
    return idx.astype(np.int64)


def decimate_subset(
    vertices: np.ndarray,
    faces: np.ndarray,
    target_vertices: int,
    *,
    symmetric: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Quadric-error half-edge-collapse decimation whose vertices are a subset of the input's.

    **Arguments:**

    - `vertices`: `(V, 3)` float positions.
    - `faces`: `(F, 3)` consistently oriented manifold triangles (boundaries allowed).
    - `target_vertices`: number of vertices to keep (stops early if no valid collapse remains; with
      `symmetric=True` the count changes by 2 per mirrored pair and 1 per midplane collapse).
    - `symmetric`: keep left-right (x -> -x) symmetry by collapsing in mirrored pairs; midplane
      vertices collapse only onto midplane vertices.

    Every collapse must satisfy the link condition, keep valences >= 3 (2 on a boundary), move
    boundary vertices only along boundary edges, and neither turn a surviving face by more than 90
    degrees nor make it degenerate/sliver.

    **Returns:** `(vertex_map, faces)`: `(V',)` int32 sorted original indices of the kept vertices
    and `(F', 3)` int32 triangles indexing into `vertex_map` (orientation preserved).
    """
    P = np.asarray(vertices, dtype=np.float64)
    Fa = np.array(faces, dtype=np.int64)
    V = len(P)
    if P.ndim != 2 or P.shape[1] != 3 or Fa.ndim != 2 or Fa.shape[1] != 3:
        raise ValueError("vertices must be (V, 3) and faces (F, 3).")
    if not 3 <= target_vertices <= V:
        raise ValueError(f"target_vertices must be in [3, {V}], got {target_vertices}.")
    mirror = mirror_map(P) if symmetric else np.arange(V)
    Q = _plane_quadrics(P, Fa)
    Ph = np.concatenate([P, np.ones((V, 1))], axis=1)

    vf: list[set[int]] = [set() for _ in range(V)]
    for f, tri in enumerate(Fa.tolist()):
        for a in tri:
            vf[a].add(f)
    face_alive = np.ones(len(Fa), dtype=bool)
    alive = np.zeros(V, dtype=bool)
    alive[np.unique(Fa)] = True
    n_alive = int(alive.sum())
    directed = set()
    for a, b, c in Fa.tolist():
        directed.update(((a, b), (b, c), (c, a)))
    boundary = np.zeros(V, dtype=bool)
    for a, b in directed:
        if (b, a) not in directed:
            boundary[a] = boundary[b] = True
    version = np.zeros(V, dtype=np.int64)

    def neighbours(a: int) -> set[int]:
        s = set()
        for f in vf[a]:
            s.update(Fa[f].tolist())
        s.discard(a)
        return s

    def cost(u: int, v: int) -> float:
        h = Ph[v]
        return float(h @ (Q[u] + Q[v]) @ h)

    def check(u: int, v: int) -> bool:
        if not (alive[u] and alive[v]) or u == v:
            return False
        ef = vf[u] & vf[v]
        if not ef or len(ef) > 2:
            return False
        if boundary[u] and (len(ef) != 1 or not boundary[v]):
            return False  # boundary vertices move only along boundary edges
        opp = set()
        for f in ef:
            opp.update(Fa[f].tolist())
        opp -= {u, v}
        nu, nv = neighbours(u), neighbours(v)
        if (nu & nv) != opp:
            return False  # link condition
        new_val_v = len(nu | nv) - 2
        if new_val_v < (2 if boundary[v] else 3):
            return False
        for o in opp:
            if len(neighbours(o)) - 1 < (2 if boundary[o] else 3):
                return False
        pv = P[v]
        for f in vf[u] - ef:
            tri = Fa[f]
            q = P[tri]
            n0 = np.cross(q[1] - q[0], q[2] - q[0])
            q = q.copy()
            q[tri == u] = pv
            e0, e1, e2 = q[1] - q[0], q[2] - q[0], q[2] - q[1]
            n1 = np.cross(e0, e1)
            a1 = np.linalg.norm(n1)
            ssq = e0 @ e0 + e1 @ e1 + e2 @ e2
            if ssq <= 0.0 or a1 <= 1e-12 * ssq:
                return False
            if n0 @ n1 <= _MIN_NORMAL_COS * np.linalg.norm(n0) * a1:
                return False
            if 2.0 * np.sqrt(3.0) * a1 < _MIN_COMPACTNESS * ssq:
                return False
        return True

    def apply(u: int, v: int):
        """Collapses u -> v; returns an undo record."""
        ef = vf[u] & vf[v]
        touched = set()
        for f in ef:
            touched.update(Fa[f].tolist())
        touched |= {u, v}
        undo = {
            "vf": {a: set(vf[a]) for a in touched},
            "rows": {f: Fa[f].copy() for f in vf[u]},
            "dead": list(ef),
        }
        for f in ef:
            face_alive[f] = False
            for a in Fa[f].tolist():
                vf[a].discard(f)
        for f in vf[u]:
            Fa[f][Fa[f] == u] = v
        vf[v] |= vf[u]
        vf[u] = set()
        Q[v] += Q[u]
        alive[u] = False
        return undo

    def push_around(a: int):
        for b in neighbours(a):
            for x, y in ((a, b), (b, a)):
                if x <= mirror[x] and (mirror[x] != x or mirror[y] == y) and y != mirror[x]:
                    heapq.heappush(heap, (cost(x, y), x, y, version[x], version[y]))

    # Initial candidates: vectorized costs over all directed edges with a canonical source.
    d = np.array(sorted(directed), dtype=np.int64)
    d = np.concatenate([d, d[:, ::-1]])
    d = np.unique(d, axis=0)
    src, dst = d[:, 0], d[:, 1]
    keep = (
        (src <= mirror[src]) & ((mirror[src] != src) | (mirror[dst] == dst)) & (dst != mirror[src])
    )
    src, dst = src[keep], dst[keep]
    h = Ph[dst]
    c0 = np.einsum("ei,eij,ej->e", h, Q[src] + Q[dst], h)
    heap = [(float(c), int(a), int(b), 0, 0) for c, a, b in zip(c0, src, dst)]
    heapq.heapify(heap)

    while n_alive > target_vertices and heap:
        c, u, v, vu, vv = heapq.heappop(heap)
        if not (alive[u] and alive[v]) or version[u] != vu or version[v] != vv:
            continue
        single = mirror[u] == u or not symmetric
        if not single and n_alive - 2 < target_vertices:
            continue  # only a midplane (single) collapse fits the remaining budget
        if not check(u, v):
            continue
        qv_before = Q[v].copy()
        undo = apply(u, v)
        done = [(u, v)]
        if not single:
            mu, mv = int(mirror[u]), int(mirror[v])
            if check(mu, mv):
                apply(mu, mv)
                done.append((mu, mv))
            else:
                # Roll the first collapse back.
                for a, s in undo["vf"].items():
                    vf[a] = s
                for f, row in undo["rows"].items():
                    Fa[f] = row
                for f in undo["dead"]:
                    face_alive[f] = True
                Q[v] = qv_before
                alive[u] = True
                continue
        n_alive -= len(done)
        ring = set()
        for _, y in done:
            ring.add(y)
            ring |= neighbours(y)
        for a in ring:
            version[a] += 1
        for a in ring:
            push_around(a)

    keep_v = np.flatnonzero(alive)
    remap = -np.ones(V, dtype=np.int64)
    remap[keep_v] = np.arange(len(keep_v))
    out = remap[Fa[face_alive]]
    if (out < 0).any():
        raise RuntimeError("internal error: a surviving face references a removed vertex.")
    return keep_v.astype(np.int32), out.astype(np.int32)


def _surface_distances(
    vertices, faces, vertex_map, dec_faces, n_samples: int = 20000, seed: int = 0
):
    """Distances (m): full vertices -> decimated surface, decimated samples -> full surface."""
    import trimesh

    import bodyprior as bp

    dec_v = np.asarray(vertices)[vertex_map]
    _, _, _, d_full = bp.closest_points_on_mesh(vertices, dec_v, dec_faces, chunk_size=256)
    mesh = trimesh.Trimesh(dec_v, dec_faces, process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    _, _, _, d_dec = bp.closest_points_on_mesh(pts, vertices, faces, chunk_size=256)
    return np.asarray(d_full), np.asarray(d_dec)


def _source_checksum() -> str:
    with np.load(asset_path(), allow_pickle=False) as z:
        return str(z["checksum"])


def load_decimated(path: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Loads the decimated topology of the default body.

    **Returns:** `(vertex_map, faces)`: `(V',)` int32 sorted indices into the default body's
    vertices and `(F', 3)` int32 triangles indexing into `vertex_map`; map a body with
    `vertices[..., vertex_map, :]`.

    **Raises:** `ValueError` if the file is missing, malformed, or was built from a different
    default-body asset (rebuild with `python -m bodyprior.assets._decimate`).
    """
    path = os.path.abspath(path or decimated_path())
    rebuild = "rebuild it with `python -m bodyprior.assets._decimate`"
    if not os.path.exists(path):
        raise ValueError(f"decimated asset not found at {path!r}; {rebuild}.")
    try:
        with np.load(path, allow_pickle=False) as z:
            vertex_map, faces, meta = z["vertex_map"], z["faces"], json.loads(str(z["metadata"]))
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"{path!r} is not a readable decimated asset ({e}); {rebuild}.") from e
    if (
        meta.get("format") != DECIMATED_FORMAT
        or meta.get("format_version") != DECIMATED_FORMAT_VERSION
    ):
        raise ValueError(
            f"{path!r} has format {meta.get('format')!r} v{meta.get('format_version')}; {rebuild}."
        )
    if meta.get("source_checksum") != _source_checksum():
        raise ValueError(
            f"{path!r} was built from a different default-body asset (checksum mismatch); "
            f"{rebuild}."
        )
    n_src = int(meta.get("source_vertices", -1))
    if (
        vertex_map.ndim != 1
        or faces.ndim != 2
        or faces.shape[1] != 3
        or vertex_map.dtype != np.int32
        or faces.dtype != np.int32
        or len(vertex_map) == 0
        or vertex_map[0] < 0
        or vertex_map[-1] >= n_src
        or not (np.diff(vertex_map) > 0).all()
        or faces.min() < 0
        or faces.max() >= len(vertex_map)
    ):
        raise ValueError(f"{path!r} has malformed vertex_map/faces; {rebuild}.")
    vertex_map.setflags(write=False)
    faces.setflags(write=False)
    return vertex_map, faces


def main(target: int = PAPER_VERTEX_COUNT) -> None:
    import bodyprior as bp

    asset = bp.load_asset()
    verts = np.asarray(asset["template_vertices"], dtype=np.float64)
    faces = np.asarray(asset["faces"])
    t0 = time.perf_counter()
    vertex_map, dec_faces = decimate_subset(verts, faces, target, symmetric=True)
    runtime = time.perf_counter() - t0
    d_full, d_dec = _surface_distances(verts, faces, vertex_map, dec_faces)
    meta = {
        "format": DECIMATED_FORMAT,
        "format_version": DECIMATED_FORMAT_VERSION,
        "source_asset": os.path.basename(asset_path()),
        "source_checksum": _source_checksum(),
        "source_vertices": int(len(verts)),
        "source_faces": int(len(faces)),
        "method": "QEM half-edge collapse (vertex subset), mirrored pairs, "
        "link/valence/normal/sliver checks",
        "target_vertices": int(target),
        "achieved_vertices": int(len(vertex_map)),
        "achieved_faces": int(len(dec_faces)),
        "template_to_decimated_mean_mm": float(d_full.mean() * 1e3),
        "template_to_decimated_max_mm": float(d_full.max() * 1e3),
        "decimated_to_template_mean_mm": float(d_dec.mean() * 1e3),
        "decimated_to_template_max_mm": float(d_dec.max() * 1e3),
        "hausdorff_mm": float(max(d_full.max(), d_dec.max()) * 1e3),
        "build_seconds": round(runtime, 2),
    }
    out = decimated_path()
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(out), suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(
                fh, vertex_map=vertex_map, faces=dec_faces, metadata=np.array(json.dumps(meta))
            )
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    print(json.dumps(meta, indent=1))


if __name__ == "__main__":
    main()
