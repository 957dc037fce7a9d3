"""Rebuilds the shipped DSPP priors `bodyprior/assets/dspp_shape.dspp` and `dspp_pose.dspp` (no
network; about 6 minutes each on 2 cores): `python -m bodyprior.dspp.build_priors [--which
shape|pose|both] [--mocap DIR] [--out-dir DIR]`. What they are trained on and how:
`bodyprior.dspp.default_shape_prior` / `default_pose_prior` (module `bodyprior.dspp._default`)."""

from __future__ import annotations

import argparse
import os


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--which", choices=("shape", "pose", "both"), default="both")
    ap.add_argument("--mocap", default=None, help="CMU BVH folder (default: find_mocap_dir())")
    ap.add_argument("--out-dir", default=None, help="output folder (default: the shipped location)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from ._default import PRIOR_FILES, build_default_pose_prior, build_default_shape_prior

    def out(kind):
        return None if args.out_dir is None else os.path.join(args.out_dir, PRIOR_FILES[kind])

    if args.which in ("shape", "both"):
        build_default_shape_prior(out("shape"), progress=not args.no_progress)
    if args.which in ("pose", "both"):
        build_default_pose_prior(out("pose"), mocap_dir=args.mocap, progress=not args.no_progress)


if __name__ == "__main__":
    main()
