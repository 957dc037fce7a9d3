"""Rebuilds the shipped PanoMan kit `bodyprior/assets/panoman_male.npz`, or builds the female one
(no network; about 6 minutes on 2 cores):
`python -m bodyprior.panoman.build_model [--sex male|female] [--mocap DIR] [--out FILE]`; the
female kit goes to `bodyprior.panoman.kit_path("female")` (a user data directory), where
`default_panoman(sex="female")` finds it. What it is trained on and how:
`bodyprior.panoman.default_panoman` (module `bodyprior.panoman._default`)."""

from __future__ import annotations

import argparse


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mocap", default=None, help="CMU BVH folder (default: find_mocap_dir())")
    ap.add_argument("--sex", choices=("male", "female"), default="male", help="identities' sex")
    ap.add_argument("--out", default=None, help="output file (default: kit_path(sex))")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._default import _SEX_NAMES, build_default_panoman

    build_default_panoman(
        args.out,
        mocap_dir=args.mocap,
        progress=not args.no_progress,
        sex=_SEX_NAMES.index(args.sex),
    )


if __name__ == "__main__":
    main()
