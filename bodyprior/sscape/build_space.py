"""Rebuilds the shipped S-SCAPE space `bodyprior/assets/sscape_caesar.sscape` from the committed
default-body assets (no network, about a minute on 2 cores): `python -m bodyprior.sscape.build_space
[--out PATH]`. What it learns and from which bodies: `bodyprior.sscape.default_space`."""

from __future__ import annotations

import argparse


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="output file (default: the shipped location)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from ._default import build_default_space

    build_default_space(args.out, progress=not args.no_progress)


if __name__ == "__main__":
    main()
