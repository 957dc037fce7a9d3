"""Benchmark: PanoMan's core (bodyprior.panoman); today the decoder g (RLA -> vertices), against
a scipy reference decoder. (The shell Gauss–Newton iteration and the SPLOCS outer iteration of
issue 13 will join this file when they are built.)

Both sides do the same work in the same run, in float64: decode the RLA vectors of posed default
bodies (full 13,380 vertices / 40,134 edges and the 6,449-vertex decimated mesh beside it;
`--quick`: the decimated mesh only) and of a non-integrable blend of two of them. The peer is the
reference algorithm of `shared/research/panoman.md` §3.5 as measured there (0.8–1.8 s per decode):
connection maps from the same lengths and angles, frames by sparse least squares (normal equations,
SuperLU, factored per call), SVD projection to SO(3), positions by the Poisson least squares
(SuperLU, factored per call), anchored at the same face and vertex. It is written here from the
formulas (NumPy/SciPy), not imported from the library, so that the library's shortcuts (pose-
independent factors, the tree-conjugated frame solve) are measured against the plain method.

Reported per mesh: `decode_s` (median seconds per decode over repeats, warm; compile time
separately; the issue's goal is ≤ 0.05 s on the full body), `decode_s_b16` (per body in a
`jax.vmap` batch of 16), the peer's time and the ratio, and the accuracy of both: max vertex
error after rigid alignment on exact input (m), and the max relative length residual on the blend.

Usage: `python benchmarks/panoman_core.py --json out/panoman_core.json [--repeats 5] [--quick]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla

import bodyprior as bp
from bodyprior import panoman as pm

# ------------------------------------------------------------------------------ reference (peer)


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1
    return R


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0], R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = 1, c, -s, s, c
    return R


def reference_decode(lengths, psi, faces, edge_faces, face_edges, interior, anchor_face, n_v):
    """Plain g: frame LS + SVD projection + Poisson LS, both factored per call (SuperLU)."""
    F = faces.shape[0]
    l01, l12, l20 = (lengths[face_edges[:, k]] for k in range(3))
    c = (l01**2 + l20**2 - l12**2) / (2 * l01 * l20)
    h = (l01 + l12 + l20) * (-l01 + l12 + l20) * (l01 - l12 + l20) * (l01 + l12 - l20)
    s = np.sqrt(np.maximum(h, 1e-30)) / (2 * l01 * l20)
    P = np.zeros((F, 3, 2))
    P[:, 1, 0], P[:, 2, 0], P[:, 2, 1] = l01, l20 * c, l20 * s
    inner = np.flatnonzero(interior)
    fs, ft = edge_faces[inner, 0], edge_faces[inner, 1]
    ks = np.argmax(face_edges[fs] == inner[:, None], axis=1)
    kt = np.argmax(face_edges[ft] == inner[:, None], axis=1)
    vs = P[fs, (ks + 1) % 3] - P[fs, ks]
    vt = -(P[ft, (kt + 1) % 3] - P[ft, kt])
    Q = (
        _rz(np.arctan2(vs[:, 1], vs[:, 0]))
        @ _rx(np.pi - psi[inner])
        @ _rz(-np.arctan2(vt[:, 1], vt[:, 0]))
    )
    ne = inner.size
    rows, cols, vals = [], [], []
    for a in range(3):
        r = 3 * np.arange(ne) + a
        rows.append(r), cols.append(3 * ft + a), vals.append(np.ones(ne))
        for b in range(3):
            rows.append(r), cols.append(3 * fs + b), vals.append(-Q[:, b, a])
    A = sps.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * ne, 3 * F)
    )
    fixed = 3 * anchor_face + np.arange(3)
    free = np.setdiff1d(np.arange(3 * F), fixed)
    Af, Ax = A[:, free], A[:, fixed]
    Y = np.zeros((3 * F, 3))
    Y[fixed] = np.eye(3)
    lu = spla.splu((Af.T @ Af).tocsc())
    Y[free] = lu.solve(Af.T @ (-(Ax @ np.eye(3))))
    Fr = Y.reshape(F, 3, 3).transpose(0, 2, 1)
    U, _, Vt = np.linalg.svd(Fr)
    D = np.ones((F, 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    Fr = (U * D[:, None, :]) @ Vt
    rr, cc, vv, B = [], [], [], []
    for k in range(3):
        a, b = faces[:, k], faces[:, (k + 1) % 3]
        g = np.einsum("fij,fj->fi", Fr[:, :, :2], P[:, (k + 1) % 3] - P[:, k])
        idx = k * F + np.arange(F)
        rr += [idx, idx]
        cc += [b, a]
        vv += [np.ones(F), -np.ones(F)]
        B.append(g)
    G = sps.csr_matrix((np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc))), (3 * F, n_v))
    v0 = faces[anchor_face, 0]
    keep = np.setdiff1d(np.arange(n_v), [v0])
    Gf = G[:, keep]
    X = np.zeros((n_v, 3))
    X[keep] = spla.splu((Gf.T @ Gf).tocsc()).solve(Gf.T @ np.concatenate(B))
    return X


# --------------------------------------------------------------------------------------- runner


def _kabsch_err(x, y):
    x, y = np.asarray(x), np.asarray(y)
    return float(np.abs(np.asarray(bp.umeyama(x, y, with_scale=False).apply(x)) - y).max())


def _median(fn, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def bench_decode(rest, posed, faces, repeats: int) -> dict:
    top = bp.Topology.from_faces(faces, rest.shape[0])

    t = time.perf_counter()
    dec = pm.prepare_decoder(rest, top)
    prepare_s = time.perf_counter() - t
    rlas = [pm.rla_encode(p, rest, top) for p in posed]
    blend = pm.RLA(
        0.5 * (rlas[0].lengths + rlas[1].lengths), 0.5 * (rlas[0].angles + rlas[1].angles)
    )

    def ours(r):
        sol = pm.rla_decode(r, None, top, decoder=dec, throw=False)
        return jax.block_until_ready(sol)

    t = time.perf_counter()
    ours(rlas[0])
    compile_s = time.perf_counter() - t
    ours_s = _median(lambda: ours(rlas[0]), repeats)
    batch = jax.tree.map(lambda a: jnp.stack([a] * 16), rlas[0])
    ours_b = jax.jit(
        jax.vmap(lambda r: pm.rla_decode(r, None, top, decoder=dec, throw=False).value.vertices)
    )
    jax.block_until_ready(ours_b(batch))
    ours_b16 = _median(lambda: jax.block_until_ready(ours_b(batch)), max(1, repeats // 2)) / 16
    ours_blend = ours(blend)
    ours_blend_s = _median(lambda: ours(blend), max(1, repeats // 2))

    args = (
        np.asarray(top.faces),
        np.asarray(top.edge_faces),
        np.asarray(top.face_edges),
        np.asarray(top.interior),
        dec.anchor_face,
        top.n_vertices,
    )

    def peer(r):
        lengths = np.asarray(dec.ref_lengths) * (1 + np.asarray(r.lengths))
        psi = np.asarray(dec.ref_angles) + np.asarray(r.angles)
        return reference_decode(lengths, psi, *args)

    peer_s = _median(lambda: peer(rlas[0]), repeats)
    peer_x = peer(rlas[0])
    peer_blend = peer(blend)
    peer_blend_s = _median(lambda: peer(blend), max(1, repeats // 2))

    def rel_len_residual(x, r):
        target = np.asarray(dec.ref_lengths) * (1 + np.asarray(r.lengths))
        return float(np.abs(np.asarray(bp.edge_lengths(jnp.asarray(x), top)) / target - 1).max())

    return {
        "n_vertices": int(top.n_vertices),
        "n_edges": int(top.n_edges),
        "anchor_face": int(dec.anchor_face),
        "tree_depth": int(dec.tree_depth),
        "prepare_s": prepare_s,
        "compile_s": compile_s,
        "decode_s": ours_s,
        "decode_s_b16": ours_b16,
        "peer_decode_s": peer_s,
        "decode_speedup": peer_s / ours_s,
        "bodyprior_exact_err_m": _kabsch_err(ours(rlas[0]).value.vertices, posed[0]),
        "peer_exact_err_m": _kabsch_err(peer_x, posed[0]),
        "bodyprior_blend_s": ours_blend_s,
        "peer_blend_s": peer_blend_s,
        "blend_speedup": peer_blend_s / ours_blend_s,
        "bodyprior_blend_frame_cg_steps": int(ours_blend.stats["frame_cg_steps"]),
        "bodyprior_blend_max_rel_length_residual": rel_len_residual(
            ours_blend.value.vertices, blend
        ),
        "peer_blend_max_rel_length_residual": rel_len_residual(peer_blend, blend),
    }


def bench_panoman_core(quick: bool, repeats: int) -> dict:
    body = bp.load_default_body(dtype=np.float64)
    faces = np.asarray(body.faces)
    rng = np.random.default_rng(0)
    pose = lambda: np.concatenate([np.zeros((1, 3)), 0.3 * rng.standard_normal((30, 3))])  # noqa: E731
    rest = np.asarray(bp.evaluate(body, bp.phenotype_vector())[0])
    posed = [np.asarray(bp.evaluate(body, bp.phenotype_vector(), pose())[0]) for _ in range(2)]
    vmap_, dfaces = bp.load_decimated()
    out = {"decimated": bench_decode(rest[vmap_], [p[vmap_] for p in posed], dfaces, repeats)}
    if not quick:
        out["full"] = bench_decode(rest, posed, faces, repeats)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="decimated mesh, 3 repeats (seconds)")
    a = ap.parse_args(argv)
    repeats = 3 if a.quick else a.repeats
    res = {
        "benchmark": "panoman_core",
        "mode": "quick" if a.quick else "full",
        "repeats": repeats,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "jax": jax.__version__,
        **bench_panoman_core(a.quick, repeats),
    }
    os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
    bp.atomic_write_json(a.json, res)
    json.dump(res, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
