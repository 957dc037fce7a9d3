"""Reading and writing body scans: PLY/OBJ point clouds or meshes, CAESAR `.lnd` landmark files.

Real scans come in millimetres (CAESAR) or metres; bodyprior works in metres. [`read_scan`][]
detects the unit from the body's size (`units="auto"`) and reports what it did in its info
dictionary (no warning: the test suite treats warnings as errors), or takes it explicitly.

CAESAR `.lnd` (humanshape's reader, `sscape.md` §2.2): header lines, then after the line `AUX =` one
line per landmark, `index flagA flagB value x y z name` with coordinates in millimetres; a landmark
is missing when flagA or flagB is -999; the list ends at `END =`.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._io import atomic_open, read_mesh, write_obj, write_ply
from .._validate import as_device_array
from ._scan import Scan, _unit, _vertex_normals_np, check_scan, estimate_normals

__all__ = ["read_scan", "write_scan", "read_lnd", "write_lnd", "detect_units"]

_UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}
_MISSING = -999


@functools.lru_cache(maxsize=1)
def _default_landmark_names() -> tuple[str, ...]:
    from .._body import load_default_body

    return tuple(load_default_body("cmu_mb").landmark_names)


def _canon(name: str) -> str:
    """Spelling-tolerant landmark key: CAESAR files vary in '-', '.', case and spaces."""
    s = re.sub(r"[-.,/]", " ", name.lower())
    return " ".join(s.split())


def _extent(points: np.ndarray) -> float:
    """Largest axis extent, robust to a few stray points (0.1-99.9 percentiles)."""
    lo, hi = np.percentile(points, [0.1, 99.9], axis=0)
    return float(np.max(hi - lo))


def detect_units(points, *, name: str = "units") -> str:
    """Unit of a body point cloud from its size: `"m"` if its largest extent is 1.0-2.3, `"mm"` if
    it is 1000-2300; anything else is a `ValueError` naming `name` (pass the unit explicitly
    then)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ext = _extent(pts)
    if 1.0 <= ext <= 2.3:
        return "m"
    if 1000.0 <= ext <= 2300.0:
        return "mm"
    raise ValueError(
        f"`{name}`: cannot tell the unit of a body {ext:.4g} units tall (expected 1.0-2.3 for "
        f"metres or 1000-2300 for millimetres); pass `{name}` as one of {sorted(_UNIT_SCALE)}."
    )


def _scale_of(units: str, points: np.ndarray, name: str) -> tuple[str, float]:
    if units == "auto":
        units = detect_units(points, name=name)
    if units not in _UNIT_SCALE:
        raise ValueError(f"`{name}` must be 'auto' or one of {sorted(_UNIT_SCALE)}, got {units!r}.")
    return units, _UNIT_SCALE[units]


# --------------------------------------------------------------------------------------------------
# CAESAR .lnd
# --------------------------------------------------------------------------------------------------


def _parse_lnd_line(line: str):
    parts = line.split()
    if len(parts) < 8:
        return None
    try:
        int(float(parts[0]))
        flags = (float(parts[1]), float(parts[2]))
        xyz = [float(x) for x in parts[4:7]]
        float(parts[3])
    except ValueError:
        return None
    name = " ".join(parts[7:]).strip()
    missing = _MISSING in flags
    return name, xyz, missing


def read_lnd(path: str | os.PathLike, *, units: str = "mm") -> tuple[tuple[str, ...], np.ndarray]:
    """Reads a CAESAR `.lnd` landmark file (format in the module docstring).

    **Arguments:**

    - `path`: the `.lnd` file.
    - `units`: unit of its coordinates, `"mm"` (CAESAR, default), `"cm"` or `"m"`.

    **Returns:** `(names, positions)`: the landmark names in file order (trailing spaces stripped)
    and their positions, shape `(L, 3)`, float64, **metres**; rows of missing landmarks are NaN.

    **Raises:** `ValueError` naming the file if it is missing, unreadable or holds no landmark line.
    """
    p = os.fspath(path)
    if units not in _UNIT_SCALE:
        raise ValueError(f"`units` must be one of {sorted(_UNIT_SCALE)}, got {units!r}.")
    if not os.path.isfile(p):
        raise ValueError(f"Cannot read landmarks {p!r}: file does not exist.")
    raw = Path(p).read_bytes().decode("latin-1")  # CAESAR-era files are not always UTF-8
    lines = raw.splitlines()
    start = next((i + 1 for i, ln in enumerate(lines) if ln.strip().upper().startswith("AUX =")), 0)
    names, pos = [], []
    for ln in lines[start:]:
        if ln.strip().upper().startswith("END ="):
            break
        rec = _parse_lnd_line(ln)
        if rec is None:
            continue
        name, xyz, missing = rec
        names.append(name)
        pos.append([np.nan] * 3 if missing else xyz)
    if not names:
        raise ValueError(
            f"Cannot read landmarks {p!r}: no landmark line `index flagA flagB value x y z name`."
        )
    return tuple(names), np.asarray(pos, dtype=np.float64) * _UNIT_SCALE[units]


def write_lnd(
    path: str | os.PathLike,
    names: Sequence[str],
    positions,
    mask=None,
    *,
    subject_id: str = "bodyprior",
) -> None:
    """Writes a CAESAR `.lnd` landmark file atomically (coordinates in millimetres).

    **Arguments:**

    - `path`: destination.
    - `names`: `L` landmark names.
    - `positions`: shape `(L, 3)`, metres. NaN rows are written as missing.
    - `mask`: optional `(L,)` bool, False = missing (written with flags -999 and zero coordinates).
    - `subject_id`: written in the `SUBJECT_ID =` header line.
    """
    names = [str(n) for n in names]
    pos = np.asarray(positions, dtype=np.float64)
    if pos.shape != (len(names), 3):
        raise ValueError(f"`positions` must have shape ({len(names)}, 3), got {pos.shape}.")
    present = np.all(np.isfinite(pos), axis=1)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (len(names),) or m.dtype != np.bool_:
            raise ValueError(
                f"`mask` must be a bool array of shape ({len(names)},), got {m.shape}."
            )
        present &= m
    if any(("\n" in n or not n.strip()) for n in names):
        raise ValueError("`names` must be non-empty single-line strings.")
    head = [
        f"SUBJECT_ID = {subject_id}",
        "SCAN_TYPE  = NO TYPE",
        "STUDY_NAME = bodyprior",
        "LAND_STUDY = bodyprior",
        "STD_LAND = 0",
        f"AUX_LAND = {len(names)}",
        "STANDARD =",
        "AUX =",
    ]
    rows = []
    for i, (n, ok) in enumerate(zip(names, present), start=1):
        if ok:
            x, y, z = pos[i - 1] * 1000.0
            rows.append(f"{i:2d}   0 {i:3d}    0.00 {x:.3f} {y:.3f} {z:.3f} {n}")
        else:
            rows.append(f"{i:2d} {_MISSING} {_MISSING}    0.00 0.000 0.000 0.000 {n}")
    with atomic_open(path, "w", encoding="latin-1") as fh:
        fh.write("\n".join(head + rows + ["END ="]) + "\n")


# --------------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------------


def _landmark_scale(lm: np.ndarray, pts_m: np.ndarray) -> tuple[str, float]:
    """Picks the unit that puts the landmarks on the (metric) scan: least median distance."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts_m)
    ok = np.all(np.isfinite(lm), axis=1)
    best = None
    for u, s in _UNIT_SCALE.items():
        d = float(np.median(tree.query(lm[ok] * s)[0])) if ok.any() else 0.0
        if best is None or d < best[2]:
            best = (u, s, d)
    return best[0], best[1]


def read_scan(
    path: str | os.PathLike,
    *,
    landmarks_path: str | os.PathLike | None = None,
    units: str = "auto",
    landmark_units: str = "auto",
    landmark_names: Sequence[str] | None = None,
    n_points: int | None = None,
    seed: int = 42,
    min_points: int = 100,
    return_info: bool = False,
):
    """Reads a real scan (PLY/OBJ point cloud or mesh, optional CAESAR `.lnd`) as a
    [`bodyprior.registration.Scan`][] in metres.

    **Arguments:**

    - `path`: a `.ply` or `.obj` file (see [`bodyprior.read_mesh`][]); faces are optional.
    - `landmarks_path`: optional `.lnd` file.
    - `units`: `"auto"` (default: a body 1.0-2.3 units tall is metres, 1000-2300 millimetres,
      anything else a `ValueError` naming `units`), or `"m"`, `"cm"`, `"mm"`.
    - `landmark_units`: unit of the `.lnd` coordinates, or `"auto"`: the unit that puts the
      landmarks closest to the scan's surface.
    - `landmark_names`: the landmark order of the returned scan (default: the default body's 77
      CAESAR names, the order fitters expect). File names are matched case- and
      punctuation-insensitively; names not in the file are missing.
    - `n_points`: randomly sub-sample to this many points without replacement (humanshape: 19,347
      with seed 42); `None` keeps all.
    - `seed`: NumPy seed of that sub-sample.
    - `min_points`: fewer points is an error.
    - `return_info`: also return a dictionary of what was done (`units`, `scale`, `landmark_units`,
      `normals` = `"file"`, `"mesh"` or `"estimated"`, `n_points_file`, `unmatched_landmarks`).

    **Returns:** the scan (all `point_mask` True), or `(scan, info)` with `return_info=True`.

    **Raises:** `ValueError` naming the file or argument for unreadable files, an empty or NaN-laden
    cloud, too few points, or an undetectable unit.
    """
    verts, faces, normals = read_mesh(path)
    unit, scale = _scale_of(units, verts, "units")
    pts = verts * scale
    info: dict = dict(units=unit, scale=scale, n_points_file=int(pts.shape[0]))
    if normals is not None and np.all(np.linalg.norm(normals, axis=1) > 1e-12):
        nrm, src = _unit(normals), "file"
    elif faces is not None:
        nrm, src = _vertex_normals_np(pts, faces), "mesh"
        loose = np.linalg.norm(nrm, axis=1) < 0.5  # vertices in no face
        if loose.any():
            nrm[loose] = estimate_normals(pts, k=12)[loose]
    else:
        nrm, src = None, "estimated"
    if n_points is not None:
        if not isinstance(n_points, int) or n_points < 1:
            raise ValueError(f"`n_points` must be None or a positive int, got {n_points!r}.")
        if pts.shape[0] > n_points:
            sel = np.sort(np.random.default_rng(seed).choice(pts.shape[0], n_points, replace=False))
            pts = pts[sel]
            nrm = None if nrm is None else nrm[sel]
    if pts.shape[0] < min_points:
        raise ValueError(
            f"`path`: the scan has too few points ({pts.shape[0]} < min_points = {min_points})."
        )
    if nrm is None:
        nrm = estimate_normals(pts, k=12)
    info["normals"] = src
    names = tuple(
        _default_landmark_names() if landmark_names is None else (str(n) for n in landmark_names)
    )
    L = len(names)
    lpos = np.zeros((L, 3))
    lmask = np.zeros(L, dtype=bool)
    info["unmatched_landmarks"] = []
    if landmarks_path is not None:
        fnames, fpos = read_lnd(landmarks_path, units="m")
        if landmark_units == "auto":
            lu, ls = _landmark_scale(fpos, pts)
        else:
            lu, ls = _scale_of(landmark_units, fpos, "landmark_units")
        info["landmark_units"] = lu
        where = {_canon(n): i for i, n in enumerate(names)}
        for n, q in zip(fnames, fpos):
            i = where.get(_canon(n))
            if i is None:
                info["unmatched_landmarks"].append(n)
            elif np.all(np.isfinite(q)):
                lpos[i] = q * ls
                lmask[i] = True
    scan = Scan(
        points=as_device_array(pts),
        normals=as_device_array(nrm),
        point_mask=as_device_array(np.ones(pts.shape[0], dtype=bool)),
        landmarks=as_device_array(lpos),
        landmark_mask=as_device_array(lmask),
        landmark_names=names,
    )
    check_scan(scan, min_points=min_points, name="scan")
    return (scan, info) if return_info else scan


def write_scan(
    path: str | os.PathLike,
    scan: Scan,
    *,
    landmarks_path: str | os.PathLike | None = None,
    binary: bool = True,
) -> None:
    """Writes one (unbatched) scan's real points and normals as a PLY or OBJ point cloud (by
    extension, metres), and optionally its landmarks as a CAESAR `.lnd` file (millimetres; missing
    landmarks flagged -999). Both files are written atomically.
    """
    check_scan(scan, min_points=1)
    if scan.points.ndim != 2:
        raise ValueError(
            f"`scan` must be unbatched (points (P, 3)), got shape {tuple(scan.points.shape)}."
        )
    m = np.asarray(scan.point_mask)
    pts = np.asarray(scan.points, np.float64)[m]
    nrm = np.asarray(scan.normals, np.float64)[m]
    ext = Path(os.fspath(path)).suffix.lower()
    if ext == ".ply":
        write_ply(path, pts, None, nrm, binary=binary, double=True)
    elif ext == ".obj":
        write_obj(path, pts, None, normals=nrm)
    else:
        raise ValueError(f"`path` must end in .ply or .obj, got {ext!r}.")
    if landmarks_path is not None:
        write_lnd(
            landmarks_path,
            scan.landmark_names,
            np.asarray(scan.landmarks),
            np.asarray(scan.landmark_mask),
        )
