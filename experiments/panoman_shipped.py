"""The shipped PanoMan kit (`bp.panoman.default_panoman()`), measured on its held-out clips.

The kit was trained by `python -m bodyprior.panoman.build_model` with `pm.RECIPE`, the reduced run
of docs/results_panoman.md; it records its recipe, so this script rebuilds that run's **test set**
(`pm.make_training_split(..., train=False)`: the held-out clips on fresh identities, the same
keys; `--test-ids` × `--test-poses` frames, 4 × 2 as the results page) and measures:

1. **Reconstruction** with `pm.reconstruct` (IK of the kit's LBS model, then `fit_panoman` from
   the IK mesh, `--fit-steps` LM iterations per block) from C1 (the 31 `cmu_mb` joints + 10 torso
   points) and C2 (C1 + 70 face points + 42 hand keypoints), the constraint sets of
   `experiments/panoman.py`: per-vertex error against the ground truth (mean and max per frame,
   mm), PanoMan against its own IK mesh (the LBS fit) and against the eq. 4 baseline (the same
   pipeline without the correction MLP, `correct=False`), paired differences with 95 % bootstrap
   intervals over frames.
2. **Twist**: `experiments/panoman.py`'s 180° wrist-twist test on the first test identity with
   `--twist-steps` LM iterations per block: minimum forearm cross-section area ratio (goal ≥ 0.8).
3. The float16 storage cost recorded by the builder, and load / reconstruction times.

Usage: `python experiments/panoman_shipped.py --out out/panoman_shipped [--quick]` (full: 8
frames, C1 and C2, 20 twist iterations, ~15 minutes on 2 cores; `--quick`: 1 frame, C1, 2 twist
iterations). `--kit FILE` measures another kit (`pm.save_kit`). Writes `metrics.json` and
`reconstruction.png` to `--out`.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import bodyprior as bp  # noqa: E402
import bodyprior.panoman as pm  # noqa: E402

QUICK = dict(test_ids=1, test_poses=1, csets=("c1",), fit_steps=2, twist_steps=2)
FULL = dict(test_ids=4, test_poses=2, csets=("c1", "c2"), fit_steps=5, twist_steps=20)


def _experiment():
    """experiments/panoman.py as a module (its constraint sets and twist test)."""
    spec = importlib.util.spec_from_file_location(
        "panoman_experiment", Path(__file__).with_name("panoman.py")
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="1 frame, C1, 2 twist iterations")
    p.add_argument("--kit", default=None, help="a kit file (default: the shipped one)")
    p.add_argument("--mocap", default=None, help="CMU BVH folder (default ../shared/data/mocap)")
    p.add_argument("--test-ids", type=int, default=None)
    p.add_argument("--test-poses", type=int, default=None)
    p.add_argument("--fit-steps", type=int, default=None)
    p.add_argument("--twist-steps", type=int, default=None)
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    a = parse_args(argv)
    cfg = dict(QUICK if a.quick else FULL)
    for k in ("test_ids", "test_poses", "fit_steps", "twist_steps"):
        if getattr(a, k) is not None:
            cfg[k] = getattr(a, k)
    os.makedirs(a.out, exist_ok=True)
    exp = _experiment()
    T: dict = {}
    t = time.perf_counter()
    kit = pm.load_kit(a.kit) if a.kit else pm.default_panoman()
    T["load_s"] = time.perf_counter() - t
    info = kit.info_dict()
    recipe = dict(info.get("recipe", pm.RECIPE))
    mocap = a.mocap or bp.find_mocap_dir()
    if mocap is None:
        raise SystemExit("CMU mocap not found: pass --mocap or set BODYPRIOR_MOCAP_DIR.")
    t = time.perf_counter()
    recipe.update(n_test_ids=cfg["test_ids"], test_poses=cfg["test_poses"])
    split = pm.make_training_split(mocap, train=False, progress=not a.no_progress, **recipe)
    test, vm, faces, body = split.test, split.vertex_map, split.faces, split.body
    if not np.array_equal(vm, np.asarray(kit.vertex_map)):
        raise SystemExit("the kit's vertices are not the recipe's mesh.")
    T["data_s"] = time.perf_counter() - t
    metrics: dict = {"config": {**cfg, "kit": a.kit or "shipped", "recipe": recipe},
                     "kit_counts": info.get("data", {}).get("counts"),
                     "float16_cost_mm": info.get("float16_cost_mm")}  # fmt: skip
    rng = np.random.default_rng(recipe.get("seed", 0))  # as experiments/panoman.py draws them
    sets = exp.constraint_sets(body, split.hand_body, vm, np.asarray(test.rest[0]), rng)

    # ------------------------------------------------------------ reconstruction, C1 / C2
    solver = pm.prepare_panoman_solver(kit.model)
    tb = np.flatnonzero(np.asarray(test.kind) == 0)
    rec: dict = {}
    shown = {}
    seconds = []
    for i in tb:
        gt = np.asarray(test.vertices[i], np.float64)
        gj = np.asarray(test.joints[i], np.float64)
        for cs in cfg["csets"]:
            idx = sets[cs]
            tk = time.perf_counter()
            r = pm.reconstruct(kit, gj, (idx, gt[idx]), max_steps=cfg["fit_steps"],
                               solver=solver)  # fmt: skip
            seconds.append(time.perf_counter() - tk)
            # the eq. 4 baseline: the same pipeline without the correction MLP
            rb = pm.reconstruct(kit, gj, (idx, gt[idx]), max_steps=cfg["fit_steps"],
                                solver=solver, correct=False)  # fmt: skip
            for name, v in (("lbs", r.stats["ik"]["vertices"]), ("panoman", r.value.vertices),
                            ("baseline", rb.value.vertices)):  # fmt: skip
                rec.setdefault(cs, {}).setdefault(name, []).append(exp._err_mm(v, gt))
            if cs == "c1" and not shown:
                shown = {"truth": gt, "LBS (IK)": np.asarray(r.stats["ik"]["vertices"]),
                         "PanoMan": np.asarray(r.value.vertices)}  # fmt: skip
    rng_ci = np.random.default_rng(0)
    for cs, rows in rec.items():
        for name, v in rows.items():
            v = np.asarray(v)
            metrics[f"recon_{cs}_mean_mm_{name}"] = float(v[:, 0].mean())
            metrics[f"recon_{cs}_max_mm_{name}"] = float(v[:, 1].mean())
        d = np.asarray(rows["panoman"])[:, 0] - np.asarray(rows["lbs"])[:, 0]
        metrics[f"recon_{cs}_ci95"] = {
            name: exp._bootstrap_ci(np.asarray(v)[:, 0], rng_ci) for name, v in rows.items()
        }
        metrics[f"recon_{cs}_ci95"]["panoman_minus_lbs"] = exp._bootstrap_ci(d, rng_ci)
        db = np.asarray(rows["panoman"])[:, 0] - np.asarray(rows["baseline"])[:, 0]
        metrics[f"recon_{cs}_ci95"]["panoman_minus_baseline"] = exp._bootstrap_ci(db, rng_ci)
    metrics["recon_frames"] = int(len(tb))
    # the first call compiles; the rest are warm
    metrics["reconstruct_s"] = {"first": seconds[0],
                                "warm_median": float(np.median(seconds[1:])) if len(seconds) > 1
                                else None}  # fmt: skip
    T["recon_s"] = time.perf_counter() - t

    # ------------------------------------------------------------ twist
    t = time.perf_counter()
    twist = exp.twist180(kit.model, kit.regressor, body, vm, faces,
                         np.asarray(test.phenotypes[0]), np.asarray(test.local_changes[0]),
                         sets["torso"], 10, solver, cfg["twist_steps"], rng)  # fmt: skip
    metrics["twist180"] = twist
    for name in twist:
        metrics[f"twist180_min_area_ratio_{name}"] = twist[name]["min_area_ratio"]
    T["twist_s"] = time.perf_counter() - t

    # ------------------------------------------------------------ figure
    errs = {k: 1e3 * np.linalg.norm(v - shown["truth"], axis=1) for k, v in shown.items()
            if k != "truth"}  # fmt: skip
    box = bp.mesh_bounds(*shown.values())
    row = [bp.render_mesh(v, faces, fit=box, size=(360, 270), antialias=1) for v in shown.values()]
    row += [
        bp.render_vertex_colors(shown[k], faces, e, vmin=0.0, vmax=40.0, fit=box, size=(360, 270),
                                antialias=1)
        for k, e in errs.items()
    ]  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = list(shown) + [f"{k} error, 0-40 mm\n(mean {e.mean():.1f})" for k, e in errs.items()]
    fig, axes = plt.subplots(1, len(row), figsize=(2.6 * len(row), 2.6))
    for ax, img, title in zip(axes, row, titles):
        ax.imshow(img)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.suptitle("shipped PanoMan kit, first held-out frame, C1 (31 joints + 10 torso points)",
                 fontsize=9)  # fmt: skip
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "reconstruction.png"), dpi=110)
    plt.close(fig)
    T["total_s"] = sum(T.values())
    metrics["timing_s"] = T
    bp.atomic_write_json(os.path.join(a.out, "metrics.json"), metrics)
    return metrics


if __name__ == "__main__":
    out = main()
    print(json.dumps({k: v for k, v in out.items() if not isinstance(v, dict)}, indent=1))
