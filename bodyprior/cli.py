"""The `bodyprior` console script.

- `bodyprior sample --n N --seed S --out DIR`: samples N adult bodies (the CAESAR stand-in), writes
  each as a
  mesh file, a `population.json` with their phenotypes, ages and sexes, and a shaded contact sheet
  PNG.
- `bodyprior info`: prints what the embedded default-body asset holds.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def _cmd_info(args) -> int:
    from .assets import asset_path, load_asset

    a = load_asset()
    meta = a["metadata"]
    print(f"asset: {asset_path()} ({os.path.getsize(asset_path()) / 2**20:.2f} MiB)")
    print(
        f"source: {meta['source']['package']} ({meta['source']['wheel_sha256'][:16]}…), "
        f"{meta['licence']}"
    )
    print(f"units: {meta['units']}")
    for k, v in meta["counts"].items():
        print(f"  {k:>16}: {v}")
    for name, r in meta["rigs"].items():
        print(
            f"  rig {name}: {r['bones']} bones, top-{r['skin_top_k']} skin weights, "
            "vertex joint regressor "
            f"max error {r['regressor_max_error_m'] * 1e3:.1f} mm"
        )
    t = a["template_vertices"]
    print(f"template height: {t[:, 2].max() - t[:, 2].min():.3f} m")
    if args.verbose:
        print("landmarks:", ", ".join(str(s) for s in a["landmark_names"]))
        print("local changes:", ", ".join(str(s) for s in a["local_labels"]))
        print("facial actions:", ", ".join(str(s) for s in a["face_labels"]))
    return 0


def _cmd_sample(args) -> int:
    import jax
    from tqdm.auto import tqdm

    from ._body import PHENOTYPES, load_default_body
    from ._io import atomic_write_json, write_obj, write_ply
    from ._population import sample_population
    from ._render import contact_sheet, save_png

    if args.n < 1:
        print("error: --n must be >= 1", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    t0 = time.time()
    body = load_default_body("cmu_mb", local_changes=not args.no_local_changes)
    pop = sample_population(
        args.n, body=body, scheme=args.scheme, pose_jitter_deg=args.jitter,
        key=jax.random.PRNGKey(args.seed),
    )
    verts = np.asarray(pop.vertices)
    faces = np.asarray(body.faces)
    t_sample = time.time() - t0
    width = len(str(args.n - 1))
    for i in tqdm(range(args.n), desc=f"writing {args.format.upper()}", unit="body"):
        path = os.path.join(args.out, f"body_{i:0{width}d}.{args.format}")
        (write_ply if args.format == "ply" else write_obj)(path, verts[i], faces)
    heights = verts[..., 2].max(1) - verts[..., 2].min(1)
    records = [
        dict(
            file=f"body_{i:0{width}d}.{args.format}",
            sex="female" if int(pop.sex[i]) else "male",
            age_years=round(float(pop.age_years[i]), 2),
            height_m=round(float(heights[i]), 4),
            phenotypes={
                k: round(float(v), 5) for k, v in zip(PHENOTYPES, np.asarray(pop.phenotypes[i]))
            },
        )
        for i in range(args.n)
    ]
    atomic_write_json(
        os.path.join(args.out, "population.json"),
        dict(
            seed=args.seed,
            n=args.n,
            scheme=args.scheme,
            units="metres, Z up, facing -Y",
            bodies=records,
        ),
    )
    k = min(args.n, args.sheet)
    labels = [
        f"{r['sex'][0].upper()} {r['age_years']:.0f}y {r['height_m']:.2f}m" for r in records[:k]
    ]
    sheet = contact_sheet(verts[:k], faces, ncols=min(k, 8), labels=labels, cell_size=(320, 160))
    save_png(os.path.join(args.out, "contact_sheet.png"), sheet)
    print(
        f"{args.n} bodies in {t_sample:.1f} s (total {time.time() - t0:.1f} s) -> {args.out}; "
        f"heights {heights.min():.2f}-{heights.max():.2f} m; contact sheet of {k}: "
        f"{os.path.join(args.out, 'contact_sheet.png')}"
    )
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="bodyprior", description="Statistical human body models in JAX."
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sample", help="sample adult bodies from the default body's phenotype space")
    s.add_argument("--n", type=int, default=16, help="number of bodies (default 16)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--out", default="out/sample", help="output directory")
    s.add_argument("--format", choices=("ply", "obj"), default="ply")
    s.add_argument(
        "--scheme", choices=("caesar", "anny"), default="caesar", help="phenotype distribution"
    )
    s.add_argument("--jitter", type=float, default=4.0, help="posture jitter scale, degrees")
    s.add_argument("--sheet", type=int, default=16, help="bodies on the contact sheet (default 16)")
    s.add_argument("--no-local-changes", action="store_true", help="skip the random local changes")
    s.set_defaults(func=_cmd_sample)
    i = sub.add_parser("info", help="describe the embedded default-body asset")
    i.add_argument("-v", "--verbose", action="store_true")
    i.set_defaults(func=_cmd_info)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
