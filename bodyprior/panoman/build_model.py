"""Rebuilds the shipped PanoMan kit `bodyprior/assets/panoman_male.npz` (no network; about 8
minutes on 2 cores): `python -m bodyprior.panoman.build_model [--mocap DIR] [--out FILE]`. What it
is trained on and how: `bodyprior.panoman.default_panoman` (module `bodyprior.panoman._default`)."""

from __future__ import annotations

import argparse


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mocap", default=None, help="CMU BVH folder (default: find_mocap_dir())")
    ap.add_argument("--out", default=None, help="output file (default: the shipped location)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._default import build_default_panoman

    build_default_panoman(args.out, mocap_dir=args.mocap, progress=not args.no_progress)


if __name__ == "__main__":
    main()
