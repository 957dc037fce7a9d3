"""The `bodyprior` console script.

- `bodyprior sample --n N --seed S --out DIR`: samples N adult bodies (the CAESAR stand-in), writes
  each as a
  mesh file, a `population.json` with their phenotypes, ages and sexes, and a shaded contact sheet
  PNG.
- `bodyprior info`: prints what the embedded default-body asset holds.
- `bodyprior register SCAN... --out DIR`: registers scans (PLY/OBJ + CAESAR `.lnd`) with the
  shipped S-SCAPE space and the anchored NRD refinement; registered meshes, JSON reports, error
  colour maps.
- `bodyprior learn MESHES... --out MODEL.sscape`: an S-SCAPE space from meshes in correspondence,
  with its compactness / generalization / specificity and a picture of its modes.
- `bodyprior pose BVH --frame N --out DIR`: one mocap frame on the default body (mesh + PNG).
- `bodyprior render MESH --out PNG`: a shaded picture of a mesh file.

Every command keeps JAX's compiled programs in a persistent cache (`$BODYPRIOR_CACHE`, default
`~/.cache/bodyprior/jax`; `--no-cache` turns it off), with the fit and NRD programs exported by
`jax.export` under `exported/`, so a second run skips their tracing and compilation (`register`:
8 s instead of 32 s to the fitted scan on 2 cores).
Exit codes: 0 success, 1 a fit did not converge (results written), 2 bad input (one-line message).
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
        args.n,
        body=body,
        scheme=args.scheme,
        pose_jitter_deg=args.jitter,
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


def cache_dir() -> str:
    """The CLI's persistent JAX compilation cache directory: `$BODYPRIOR_CACHE`, else JAX's own
    `$JAX_COMPILATION_CACHE_DIR` (a notebook or job that already points JAX at a cache shares it
    with the commands it starts), else `$XDG_CACHE_HOME/bodyprior/jax` or
    `~/.cache/bodyprior/jax`."""
    for var in ("BODYPRIOR_CACHE", "JAX_COMPILATION_CACHE_DIR"):
        env = os.environ.get(var)
        if env:
            return os.path.abspath(os.path.expanduser(env))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "bodyprior", "jax")


def enable_compilation_cache(path: str | None = None) -> str:
    """Turns on JAX's persistent compilation cache at `path` (default [`cache_dir`][]): compiled
    programs that took at least 0.5 s to compile are written there and reused by later processes
    with the same JAX version, backend and program. The whole-algorithm entry points that take
    seconds to trace (the batched S-SCAPE fit, NRD, the fitting error) are also exported with
    `jax.export` to `<path>/exported` and loaded from there by later processes, which skips their
    Python tracing and lowering as well (see `bodyprior._aot`; results are identical). The API does
    not do this by itself; call this at the top of a script (`jax_compilation_cache_dir` alone
    gives the compile cache without the exports).

    **Returns:** the directory used.
    """
    import jax

    path = cache_dir() if path is None else os.path.abspath(os.path.expanduser(path))
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    from ._aot import set_export_directory

    set_export_directory(os.path.join(path, "exported"))
    return path


def _job(name: str):
    """The job `name` of `bodyprior._cli_jobs`, imported when it runs."""

    def run(args) -> int:
        from . import _cli_jobs

        return getattr(_cli_jobs, name)(args)

    return run


def _add_jobs(sub) -> None:
    from ._cli_jobs import REGISTER_PRESETS

    r = sub.add_parser(
        "register",
        help="register scans (PLY/OBJ + .lnd) with the shipped S-SCAPE space and NRD refinement",
        description="S-SCAPE fit with the shipped space (bodyprior.sscape.default_space), then the "
        "anchored NRD refinement (bodyprior.sscape.register_sscape_nrd). Writes per scan "
        "STEM.registered.ply (the template mesh in the scan frame, metres), STEM.json (fitting "
        "error, coverage, landmark RMS, units) and STEM.error.png; report.json for all.",
    )
    r.add_argument("scans", nargs="+", help="scan files (.ply/.obj) or directories of them")
    r.add_argument(
        "--landmarks",
        default=None,
        help="CAESAR .lnd file of the (single) scan; default SCAN.lnd next to each scan",
    )
    r.add_argument("--out", required=True, help="output directory")
    r.add_argument(
        "--preset",
        choices=tuple(REGISTER_PRESETS),
        default="default",
        help="default: measured best on simulated scans; caesar: + humanshape's head "
        "rule (dummy heads); paper: humanshape's fit and the paper's NRD",
    )
    r.add_argument("--components", type=int, default=20, help="shape components (default 20)")
    r.add_argument(
        "--model", default=None, help="an .sscape space on the template (default: the shipped one)"
    )
    r.add_argument(
        "--units",
        choices=("auto", "m", "cm", "mm"),
        default="auto",
        help="scan units (default: detected from the body's size)",
    )
    r.add_argument(
        "--points",
        type=int,
        default=19347,
        help="random scan points used (humanshape: 19,347; 0 = all)",
    )
    r.add_argument("--max-passes", type=int, default=None, help="S-SCAPE pose/shape passes")
    r.add_argument("--no-refine", action="store_true", help="S-SCAPE fit only, no NRD")
    r.add_argument("--vmax-mm", type=float, default=20.0, help="top of the error colour map, mm")
    r.add_argument("--json", action="store_true", help="print the report as JSON")
    r.add_argument("--no-progress", action="store_true")
    r.set_defaults(func=_job("cmd_register"))

    le = sub.add_parser("learn", help="learn an S-SCAPE space from meshes in correspondence")
    le.add_argument("meshes", nargs="+", help="mesh files (.ply/.obj) or directories of them")
    le.add_argument("--out", required=True, help="output model file (.sscape)")
    le.add_argument("--components", type=int, default=20, help="components (default 20)")
    le.add_argument("--samples", type=int, default=1000, help="specificity samples")
    le.add_argument("--modes", type=int, default=3, help="components drawn at -3/0/+3 sd")
    le.add_argument("--no-measures", action="store_true", help="skip generalization/specificity")
    le.add_argument("--seed", type=int, default=0)
    le.add_argument("--json", action="store_true", help="print the report as JSON")
    le.add_argument("--no-progress", action="store_true")
    le.set_defaults(func=_job("cmd_learn"))

    po = sub.add_parser(
        "pose",
        help="pose the default body from one BVH frame (skinning, or PanoMan from its joints)",
    )
    po.add_argument("bvh", help="a BVH file (CMU skeletons)")
    po.add_argument("--frame", type=int, default=0, help="frame index (negative from the end)")
    po.add_argument(
        "--phenotype",
        action="append",
        metavar="NAME=VALUE",
        help="phenotype entry, e.g. --phenotype gender=1 --phenotype age=0.7",
    )
    po.add_argument("--no-root-motion", action="store_true", help="drop the root translation")
    po.add_argument("--format", choices=("ply", "obj"), default="ply")
    po.add_argument("--size", type=int, default=512, help="image height in pixels")
    po.add_argument("--out", required=True, help="output directory")
    po.add_argument(
        "--model",
        choices=("skinning", "panoman"),
        default="skinning",
        help="skinning: the default body posed by its rig (full mesh); panoman: the shipped "
        "PanoMan kit reconstructed from the frame's joints (decimated mesh, about a minute)",
    )
    po.add_argument(
        "--kit", default=None, help="PanoMan kit (bodyprior.panoman.save_kit; default: shipped)"
    )
    po.add_argument(
        "--max-steps", type=int, default=5, help="PanoMan: LM iterations per block (default 5)"
    )
    po.add_argument(
        "--blocks",
        default="face,body,hand",
        help="PanoMan: the blocks solved, in order (default face,body,hand; joints alone "
        "constrain mostly the body: 'body' is about a third of the time)",
    )
    po.set_defaults(func=_job("cmd_pose"))

    re_ = sub.add_parser("render", help="render a mesh file to a PNG")
    re_.add_argument("mesh", help="a .ply or .obj mesh")
    re_.add_argument("--out", required=True, help="output PNG")
    re_.add_argument(
        "--view",
        action="append",
        default=None,
        choices=("front", "back", "side", "left", "right", "top"),
        help="view(s), side by side (default front and side)",
    )
    re_.add_argument("--size", type=int, default=512, help="image height in pixels")
    re_.set_defaults(func=_job("cmd_render"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="bodyprior", description="Statistical human body models in JAX."
    )
    ap.add_argument(
        "--no-cache", action="store_true", help="do not use the persistent JAX compilation cache"
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
    _add_jobs(sub)
    args = ap.parse_args(argv)
    if getattr(args, "view", 0) is None:
        args.view = ["front", "side"]
    if not args.no_cache:
        enable_compilation_cache()
    try:
        return args.func(args)
    except ValueError as e:
        print(f"bodyprior {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
