"""BVH (Biovision Hierarchy) motion files: reader, writer and the `Bvh` container.

Host-side NumPy. A BVH file has a `HIERARCHY` block (one `ROOT`, nested `JOINT`s and `End Site`s in
braces, each with an `OFFSET` and, for joints, a `CHANNELS` list) and a `MOTION` block (`Frames:`,
`Frame Time:`, then one line of channel values per frame).

**Channel convention** (as `yuki-koyama/bvh11` `BvhObject::GetTransformationRelativeToParent` and
Blender's `io_anim_bvh`): a joint's transform relative to its parent is `T(offset)` followed by
its channels *in the order written*, each multiplied on the right; angles are in degrees. So
`CHANNELS 3 Zrotation Yrotation Xrotation` means `R = Rz(z) @ Ry(y) @ Rx(x)` acting on column
vectors, which is [`bodyprior.euler_to_matrix`][]`(radians([z, y, x]), "ZYX")`, and the world
transform of a joint is the product of its ancestors' transforms from the root down. At rest (all
channels zero) every joint frame is aligned with the file's world axes, so offsets are world
vectors at rest.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
from collections.abc import Sequence

import jax
import numpy as np

from ._io import atomic_open
from ._rotations import EULER_ORDERS, euler_to_matrix

__all__ = ["Bvh", "read_bvh", "write_bvh"]

_CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CANONICAL = {c.lower(): c for c in _CHANNEL_NAMES}


@dataclasses.dataclass(frozen=True, eq=False)
class Bvh:
    """One BVH file: skeleton and motion (host NumPy data, immutable).

    Joints are in file (depth-first) order, so every parent precedes its children. End Sites are
    not joints; their offsets are kept in `end_offsets`.

    **Fields:**

    - `joint_names`: `J` joint names, `joint_names[0]` the root.
    - `parents`: `J` parent indices, `-1` for the root.
    - `offsets`: shape `(J, 3)`, each joint's `OFFSET` from its parent (file units, file axes).
    - `channels`: per joint, its channel names in file order (canonical spelling, e.g.
      `"Zrotation"`); may be empty.
    - `end_offsets`: shape `(J, 3)`, the `End Site` offset under each joint, NaN where a joint has
      none.
    - `frame_time`: seconds per frame.
    - `motion`: shape `(F, C)` float64, channel values per frame (degrees for rotations, file
      units for positions), channels ordered joint by joint as in `channels`.
    """

    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_offsets: np.ndarray
    frame_time: float
    motion: np.ndarray

    def __post_init__(self):
        J = len(self.joint_names)
        if J == 0:
            raise ValueError("`joint_names` must name at least one joint, got none.")
        if len(self.parents) != J or len(self.channels) != J:
            raise ValueError(
                f"`parents` and `channels` must have one entry per joint ({J}), got "
                f"{len(self.parents)} and {len(self.channels)}."
            )
        if len(set(self.joint_names)) != J:
            dup = sorted({n for n in self.joint_names if self.joint_names.count(n) > 1})
            raise ValueError(f"`joint_names` must be unique, got duplicates {dup}.")
        if not _is_depth_first(self.parents):
            raise ValueError(
                "`parents` must list a tree in depth-first order (parents[0] == -1, and each "
                "joint's parent is the previous joint or one of its ancestors), got "
                f"{self.parents}."
            )
        for name, chans in zip(self.joint_names, self.channels):
            bad = [c for c in chans if c not in _CHANNEL_NAMES]
            if bad:
                raise ValueError(
                    f"`channels` of joint {name!r} must be among {_CHANNEL_NAMES}, got {bad}."
                )
        offsets = np.asarray(self.offsets, np.float64)
        end = np.asarray(self.end_offsets, np.float64)
        motion = np.asarray(self.motion, np.float64)
        if offsets.shape != (J, 3) or end.shape != (J, 3):
            raise ValueError(
                f"`offsets` and `end_offsets` must have shape ({J}, 3), got {offsets.shape} and "
                f"{end.shape}."
            )
        C = sum(len(c) for c in self.channels)
        if motion.ndim != 2 or motion.shape[1] != C:
            raise ValueError(f"`motion` must have shape (F, {C}), got {motion.shape}.")
        if not (np.all(np.isfinite(offsets)) and np.all(np.isfinite(motion))):
            raise ValueError("`offsets` and `motion` must be finite.")
        if not (np.isfinite(self.frame_time) and self.frame_time > 0):
            raise ValueError(f"`frame_time` must be a positive number, got {self.frame_time}.")
        for arr in (offsets, end, motion):
            arr.setflags(write=False)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "end_offsets", end)
        object.__setattr__(self, "motion", motion)
        object.__setattr__(self, "frame_time", float(self.frame_time))

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def channel_start(self) -> tuple[int, ...]:
        """Index into a motion row of each joint's first channel."""
        return tuple(int(s) for s in np.cumsum([0] + [len(c) for c in self.channels])[:-1])

    def joint_index(self, name: str) -> int:
        """Index of the joint called `name` (`ValueError` if there is none)."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise ValueError(f"No joint named {name!r} in this BVH skeleton.") from None

    def rest_positions(self) -> np.ndarray:
        """Joint positions with all channels zero, shape `(J, 3)`: summed offsets (file units)."""
        pos = np.zeros((self.n_joints, 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos

    def local_rotations(self, frames=None) -> np.ndarray:
        """Per-frame local rotation of every joint, shape `(F, J, 3, 3)` float64.

        The product of the joint's rotation channels in file order (any order, any number; a joint
        without rotation channels gets the identity), see the module docstring.

        **Arguments:**

        - `frames`: optional frame indices (or slice) to evaluate, default all frames.
        """
        motion = self.motion if frames is None else self.motion[frames]
        F, J = motion.shape[0], self.n_joints
        out = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
        starts = self.channel_start
        groups: dict[str, list[tuple[int, list[int]]]] = {}
        for j, chans in enumerate(self.channels):
            rot = [(k, c[0]) for k, c in enumerate(chans) if c.endswith("rotation")]
            if rot:
                groups.setdefault("".join(a for _, a in rot), []).append(
                    (j, [starts[j] + k for k, _ in rot])
                )
        # one conversion per distinct channel order (all joints of that order at once)
        for axes, members in groups.items():
            idx = np.array([cols for _, cols in members])  # (Jg, n)
            ang = np.deg2rad(motion[:, idx]).reshape(-1, len(axes))  # (F * Jg, n)
            R = _rotation_product(ang, axes).reshape(F, len(members), 3, 3)
            out[:, [j for j, _ in members]] = R
        return out

    def local_translations(self, frames=None) -> np.ndarray:
        """Per-frame translation of every joint relative to its parent, shape `(F, J, 3)`.

        `offset` plus the joint's position channels, each expressed in the frame reached by the
        channels written before it (for the usual `Xposition Yposition Zposition` first, simply
        `offset + (x, y, z)`).

        **Arguments:**

        - `frames`: optional frame indices (or slice) to evaluate, default all frames.
        """
        motion = self.motion if frames is None else self.motion[frames]
        F, J = motion.shape[0], self.n_joints
        out = np.broadcast_to(self.offsets, (F, J, 3)).copy()
        starts = self.channel_start
        for j, chans in enumerate(self.channels):
            is_pos = [c.endswith("position") for c in chans]
            if not any(is_pos):
                continue
            last = max(k for k, p in enumerate(is_pos) if p)
            R = np.broadcast_to(np.eye(3), (F, 3, 3))
            for k, c in enumerate(
                chans[: last + 1]
            ):  # rotations after the last position: no effect
                v = motion[:, starts[j] + k]
                if is_pos[k]:
                    out[:, j] += R[:, :, "XYZ".index(c[0])] * v[:, None]
                else:
                    R = R @ _rotation_product(np.deg2rad(v[:, None]), c[0])
        return out

    def root_positions(self, frames=None) -> np.ndarray:
        """Root joint position per frame, shape `(F, 3)`, file units (optional frame indices)."""
        return self.local_translations(frames)[:, 0]

    def with_frame_time(self, frame_time: float) -> Bvh:
        """A copy with another `frame_time` (seconds), e.g. when the header is known to be wrong."""
        return dataclasses.replace(self, frame_time=float(frame_time))


def _is_depth_first(parents: Sequence[int]) -> bool:
    if not parents or parents[0] != -1:
        return False
    path = [0]  # ancestors of the previous joint, root first
    for j, p in enumerate(parents[1:], start=1):
        while path and path[-1] != p:
            path.pop()
        if not path:
            return False
        path.append(j)
    return True


_CHUNK = 8192  # rotations per conversion call: padding to a fixed size compiles each order once


@functools.partial(jax.jit, static_argnums=1)
def _euler_chunk(angles, order):
    return jax.vmap(lambda a: euler_to_matrix(a, order))(angles)


def _rotation_product(angles: np.ndarray, axes: str) -> np.ndarray:
    """`R_{a1}(t1) @ R_{a2}(t2) @ ...` for angles `(N, n)` in radians and axis letters `axes`."""
    N, n = angles.shape
    if n == 3 and axes in EULER_ORDERS:
        factors = [(angles, axes)]
    else:
        # one elementary rotation per channel: the first angle of an order starting with its axis
        factors = []
        for k, a in enumerate(axes):
            pad = np.zeros((N, 3))
            pad[:, 0] = angles[:, k]
            factors.append((pad, next(o for o in EULER_ORDERS if o[0] == a)))
    out = np.broadcast_to(np.eye(3), (N, 3, 3))
    with jax.enable_x64(True):
        for ang, order in factors:
            R = np.empty((N, 3, 3))
            for s in range(0, N, _CHUNK):
                block = ang[s : s + _CHUNK]
                padded = np.zeros((_CHUNK, 3))
                padded[: len(block)] = block
                R[s : s + len(block)] = np.asarray(_euler_chunk(padded, order))[: len(block)]
            out = out @ R
    return out


# --------------------------------------------------------------------------------------------------
# reading


class _Tokens:
    """Whitespace tokens of the hierarchy block, each with its 1-based line number."""

    def __init__(self, path: str, lines: list[str]):
        self.path = path
        self.toks: list[tuple[str, int]] = []
        self.motion_line = None  # index into `lines` of the MOTION keyword
        for i, line in enumerate(lines):
            parts = line.split()
            if parts and parts[0].upper() == "MOTION":
                self.motion_line = i
                break
            self.toks.extend((t, i + 1) for t in parts)
        self.pos = 0
        self.last_line = len(lines)

    def error(self, msg: str, line: int | None = None):
        if line is None:
            line = self.toks[self.pos][1] if self.pos < len(self.toks) else self.last_line
        return ValueError(f"{self.path}:{line}: {msg}")

    def peek(self) -> str | None:
        return self.toks[self.pos][0] if self.pos < len(self.toks) else None

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.toks):
            where = "before MOTION" if self.motion_line is not None else "at end of file"
            raise self.error(f"unexpected end of HIERARCHY {where}: expected {what}.")
        tok = self.toks[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str):
        tok, line = self.next(repr(word))
        if tok != word:
            raise self.error(f"expected {word!r}, got {tok!r}.", line)
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            return float(tok)
        except ValueError:
            raise self.error(f"expected a number ({what}), got {tok!r}.", line) from None


def _parse_offset(t: _Tokens, owner: str) -> np.ndarray:
    t.expect("OFFSET")
    return np.array([t.number(f"OFFSET {c} of {owner}") for c in "xyz"])


def _parse_joint(t: _Tokens, name: str, parent: int, out: dict):
    j = len(out["names"])
    if name in out["names"]:
        raise t.error(f"duplicate joint name {name!r}.")
    out["names"].append(name)
    out["parents"].append(parent)
    out["end"].append(np.full(3, np.nan))
    t.expect("{")
    out["offsets"].append(_parse_offset(t, name))
    chans: tuple[str, ...] = ()
    if t.peek() == "CHANNELS":
        _, line = t.next("CHANNELS")
        n_tok, nline = t.next("channel count")
        try:
            n = int(n_tok)
        except ValueError:
            raise t.error(f"expected a channel count for {name!r}, got {n_tok!r}.", nline) from None
        if not 0 <= n <= 6:
            raise t.error(f"channel count of {name!r} must be in 0..6, got {n}.", nline)
        got = []
        for _ in range(n):
            c, cline = t.next(f"{n} channel names for {name!r}")
            canon = _CANONICAL.get(c.lower())
            if canon is None:
                raise t.error(
                    f"joint {name!r} declares {n} channels but {c!r} is not a channel name "
                    f"(one of {', '.join(_CHANNEL_NAMES)}).",
                    cline,
                )
            got.append(canon)
        if len(set(got)) != len(got):
            raise t.error(f"joint {name!r} repeats a channel: {got}.", line)
        chans = tuple(got)
    out["channels"].append(chans)
    while True:
        tok, line = t.next(f"JOINT, End Site or '}}' closing {name!r}")
        if tok == "}":
            return
        if tok == "JOINT":
            child, _ = t.next("joint name")
            if child in ("{", "}"):
                raise t.error(f"JOINT without a name under {name!r}.", line)
            _parse_joint(t, child, j, out)
        elif tok == "End":
            t.expect("Site")
            if not np.all(np.isnan(out["end"][j])):
                raise t.error(f"joint {name!r} has more than one End Site.", line)
            t.expect("{")
            out["end"][j] = _parse_offset(t, f"End Site of {name!r}")
            t.expect("}")
        else:
            raise t.error(f"expected JOINT, End Site or '}}' in {name!r}, got {tok!r}.", line)


def _parse_text(path: str, text: str, frame_time: float | None) -> Bvh:
    lines = text.splitlines()
    t = _Tokens(path, lines)
    if not t.toks or t.toks[0][0] != "HIERARCHY":
        raise t.error("file must start with HIERARCHY.", t.toks[0][1] if t.toks else 1)
    t.pos = 1
    if t.peek() != "ROOT":
        tok = t.peek()
        raise t.error(
            "no joints: expected ROOT after HIERARCHY" + (f", got {tok!r}." if tok else ".")
        )
    t.next("ROOT")
    name, _ = t.next("root name")
    out = {"names": [], "parents": [], "offsets": [], "channels": [], "end": []}
    _parse_joint(t, name, -1, out)
    if t.peek() is not None:
        tok, line = t.next("")
        msg = (
            "only one ROOT is supported"
            if tok == "ROOT"
            else f"unexpected {tok!r} after the root's '}}'"
        )
        raise t.error(msg + ".", line)
    if t.motion_line is None:
        raise t.error("missing MOTION block.", len(lines))

    # MOTION header: "Frames: N" and "Frame Time: dt" on the next non-empty lines
    i = t.motion_line + 1

    def header(pattern: str, what: str):
        nonlocal i
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise ValueError(f"{path}:{len(lines)}: missing '{what}' line after MOTION.")
        m = re.fullmatch(pattern, lines[i].strip())
        if m is None:
            raise ValueError(
                f"{path}:{i + 1}: expected '{what} <value>', got {lines[i].strip()!r}."
            )
        i += 1
        return m.group(1), i

    n_str, fline = header(r"Frames:\s*(\S+)", "Frames:")
    try:
        n_frames = int(n_str)
        if n_frames < 0:
            raise ValueError
    except ValueError:
        raise ValueError(
            f"{path}:{fline}: frame count must be a non-negative integer, got {n_str!r}."
        ) from None
    dt_str, tline = header(r"Frame\s+Time:\s*(\S+)", "Frame Time:")
    try:
        dt = float(dt_str)
    except ValueError:
        raise ValueError(f"{path}:{tline}: frame time must be a number, got {dt_str!r}.") from None
    if frame_time is not None:
        dt = float(frame_time)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(
                f"`frame_time` must be a positive number of seconds, got {frame_time}."
            )
    elif not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"{path}:{tline}: frame time must be positive, got {dt_str!r}.")

    C = sum(len(c) for c in out["channels"])
    rows = [(k + 1, s) for k, s in enumerate(lines[i:], start=i) if s.strip()]
    if len(rows) != n_frames:
        last = rows[-1][0] if rows else tline
        kind = "truncated motion" if len(rows) < n_frames else "extra motion lines"
        raise ValueError(
            f"{path}:{last}: {kind}: 'Frames: {n_frames}' but {len(rows)} frame lines follow."
        )
    try:
        if n_frames:
            motion = np.loadtxt([s for _, s in rows], dtype=np.float64, ndmin=2, comments=None)
        else:
            motion = np.zeros((0, C))
        ok = motion.shape == (n_frames, C)
    except ValueError:
        ok = False
    if not ok or not np.all(np.isfinite(motion)):
        # slow path, only to name the offending line
        for line_no, s in rows:
            vals = s.split()
            if len(vals) != C:
                raise ValueError(
                    f"{path}:{line_no}: wrong channel count: frame has {len(vals)} values, the "
                    f"hierarchy declares {C} channels."
                )
            for v in vals:
                try:
                    x = float(v)
                except ValueError:
                    raise ValueError(
                        f"{path}:{line_no}: bad number {v!r} in motion data."
                    ) from None
                if not np.isfinite(x):
                    raise ValueError(f"{path}:{line_no}: non-finite value {v!r} in motion data.")
        raise AssertionError("unreachable")  # pragma: no cover
    return Bvh(
        joint_names=tuple(out["names"]),
        parents=tuple(out["parents"]),
        offsets=np.array(out["offsets"]),
        channels=tuple(out["channels"]),
        end_offsets=np.array(out["end"]),
        frame_time=dt,
        motion=motion.reshape(n_frames, C),
    )


def read_bvh(path: str | os.PathLike, *, frame_time: float | None = None) -> Bvh:
    """Reads a BVH file.

    **Arguments:**

    - `path`: the `.bvh` file.
    - `frame_time`: seconds per frame to use instead of the header's `Frame Time` (for files whose
      header is known to be wrong, e.g. CMU salsa clips captured at 60 fps with a 120 fps header);
      `None` keeps the header value.

    **Returns:** a [`bodyprior.Bvh`][].

    **Raises:** `ValueError` naming the file and line for malformed input: a missing `HIERARCHY`,
    `ROOT` (zero joints), brace, `OFFSET` or `MOTION`; unknown channel names or a wrong channel
    count; a frame count that does not match the motion lines (truncated motion); a frame with the
    wrong number of values; a value that is not a finite number.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="strict") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text BVH file ({e}).") from None
    return _parse_text(path, text, frame_time)


# --------------------------------------------------------------------------------------------------
# writing


def write_bvh(path: str | os.PathLike, bvh: Bvh, *, precision: int = 10) -> None:
    """Writes `bvh` as a BVH file, atomically (see [`bodyprior.atomic_open`][]).

    Tab-indented hierarchy; motion values with `precision` significant digits (`17` round-trips
    float64 exactly). [`bodyprior.read_bvh`][] reads the result back to the same `Bvh`.

    **Arguments:**

    - `path`: destination file (its directory must exist).
    - `bvh`: a [`bodyprior.Bvh`][].
    - `precision`: significant digits for offsets and motion values, 1..17.
    """
    if not isinstance(bvh, Bvh):
        raise ValueError(f"`bvh` must be a bodyprior.Bvh, got {type(bvh).__name__}.")
    if not (isinstance(precision, int) and 1 <= precision <= 17):
        raise ValueError(f"`precision` must be an int in 1..17, got {precision!r}.")
    fmt = f"%.{precision}g"
    children: list[list[int]] = [[] for _ in bvh.joint_names]
    for j, p in enumerate(bvh.parents[1:], start=1):
        children[p].append(j)
    out = ["HIERARCHY"]

    def vec(v: Sequence[float] | np.ndarray) -> str:
        return " ".join(fmt % x for x in v)

    def emit(j: int, depth: int):
        ind = "\t" * depth
        out.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {bvh.joint_names[j]}")
        out.append(ind + "{")
        out.append(f"{ind}\tOFFSET {vec(bvh.offsets[j])}")
        ch = bvh.channels[j]
        if ch:
            out.append(f"{ind}\tCHANNELS {len(ch)} {' '.join(ch)}")
        for c in children[j]:
            emit(c, depth + 1)
        if not np.all(np.isnan(bvh.end_offsets[j])):
            e = vec(bvh.end_offsets[j])
            out.extend([f"{ind}\tEnd Site", ind + "\t{", f"{ind}\t\tOFFSET {e}", ind + "\t}"])
        out.append(ind + "}")

    emit(0, 0)  # depth-first, children in index order: re-reading gives the same joint order
    out += ["MOTION", f"Frames: {bvh.n_frames}", f"Frame Time: {bvh.frame_time:.17g}"]
    body = "\n".join(out) + "\n"
    with atomic_open(path, "w") as f:
        f.write(body)
        if bvh.n_frames:
            np.savetxt(f, bvh.motion, fmt=fmt, delimiter=" ")
