"""A small synthetic skinned body for tests: a closed tube along +Z split into a chain of segments.

The tube has `n_rings` rings of `n_around` vertices plus two cap vertices (closed, genus 0, outward
faces). Joint `j` (a chain, `parents = (-1, 0, 1, ...)`) sits at the centroid of the ring at the
bottom of segment `j`, so joints follow the body shape exactly. Skin weights blend smoothly between
adjacent segments (at most two influences per vertex). `make_toy_model` adds an orthonormal PCA
basis of smooth deformations (bulges, stretches, bends), all deterministic from `seed`.
"""

from __future__ import annotations

import numpy as np

import bodyprior as bp
from bodyprior.sscape import SScapeModel


def tube_mesh(n_around: int = 12, n_rings: int = 30, radius: float = 0.1, height: float = 1.0):
    """Vertices `(n_rings * n_around + 2, 3)` and faces of a closed tube; cap centres come last."""
    theta = 2 * np.pi * np.arange(n_around) / n_around
    z = np.linspace(0.0, height, n_rings)
    ring = np.stack([radius * np.cos(theta), radius * np.sin(theta)], axis=-1)
    verts = np.concatenate(
        [np.concatenate([ring, np.full((n_around, 1), zi)], axis=1) for zi in z], axis=0
    )
    bottom = n_rings * n_around
    top = bottom + 1
    verts = np.concatenate(
        [verts, [[0.0, 0.0, -0.02 * height]], [[0.0, 0.0, 1.02 * height]]], axis=0
    )
    faces = []
    for r in range(n_rings - 1):
        for i in range(n_around):
            a = r * n_around + i
            b = r * n_around + (i + 1) % n_around
            c = (r + 1) * n_around + i
            d = (r + 1) * n_around + (i + 1) % n_around
            faces += [[a, b, d], [a, d, c]]
    last = (n_rings - 1) * n_around
    for i in range(n_around):
        faces.append([bottom, (i + 1) % n_around, i])
        faces.append([top, last + i, last + (i + 1) % n_around])
    return verts.astype(np.float64), np.asarray(faces, dtype=np.int32)


def toy_rig(
    n_around: int = 12, n_rings: int = 30, n_joints: int = 4, height: float = 1.0
) -> bp.Rig:
    """Rig of the tube: a chain of `n_joints` joints, each regressed from its ring's `n_around`
    vertices, two skin influences per vertex."""
    n_vertices = n_rings * n_around + 2
    # Joint j's ring: evenly spaced, joint 0 at the bottom ring.
    joint_rings = np.round(np.linspace(0, n_rings - 1, n_joints + 1)[:-1]).astype(int)
    reg_idx = np.stack([r * n_around + np.arange(n_around) for r in joint_rings]).astype(np.int32)
    reg_w = np.full(reg_idx.shape, 1.0 / n_around)
    # Smooth weights from ring height: segment j spans [ring_j, ring_{j+1}); blend over one ring
    # gap.
    ring_of_vertex = np.concatenate([np.repeat(np.arange(n_rings), n_around), [0, n_rings - 1]])
    pos = ring_of_vertex.astype(np.float64)
    skin_idx = np.zeros((n_vertices, 2), np.int32)
    skin_w = np.zeros((n_vertices, 2))
    blend = max(1.0, 0.5 * (n_rings - 1) / n_joints)
    for v in range(n_vertices):
        seg = int(np.searchsorted(joint_rings, pos[v], side="right") - 1)
        skin_idx[v, 0] = seg
        skin_w[v, 0] = 1.0
        if seg > 0:  # blend with the parent segment just above the joint
            t = (pos[v] - joint_rings[seg]) / blend
            if t < 1.0:
                w = 0.5 + 0.5 * t  # 0.5 at the joint ring, 1 one blend length above it
                w = w * w * (3 - 2 * w)
                skin_idx[v] = (seg, seg - 1)
                skin_w[v] = (w, 1 - w)
    parents = tuple([-1] + list(range(n_joints - 1)))
    names = tuple(["root"] + [f"joint{j}" for j in range(1, n_joints)])
    return bp.Rig(
        parents=parents,
        joint_names=names,
        skin_indices=skin_idx,
        skin_weights=skin_w,
        regressor_indices=reg_idx,
        regressor_weights=reg_w,
    )


def toy_basis(verts: np.ndarray, n_components: int, seed: int = 0):
    """An orthonormal `(K, V, 3)` basis of smooth, centroid-free deformations of the tube."""
    rng = np.random.default_rng(seed)
    z = verts[:, 2]
    zn = (z - z.min()) / (z.max() - z.min())
    xy = verts[:, :2]
    fields = []
    for k in range(max(n_components, 1) + 3):
        freq = 1 + k // 3
        phase = rng.uniform(0, 2 * np.pi)
        kind = k % 3
        if kind == 0:  # radial bulge
            f = np.concatenate(
                [xy * np.sin(np.pi * freq * zn + phase)[:, None], np.zeros_like(z)[:, None]], 1
            )
        elif kind == 1:  # vertical stretch
            f = np.zeros_like(verts)
            f[:, 2] = np.cos(np.pi * freq * zn + phase)
        else:  # sideways bend
            f = np.zeros_like(verts)
            d = rng.normal(size=2)
            f[:, :2] = np.sin(np.pi * freq * zn + phase)[:, None] * d
        f = f + 0.05 * rng.normal(size=f.shape) * np.abs(f).max()
        f = f - f.mean(axis=0)
        fields.append(f.reshape(-1))
    # Keep the deformations orthogonal to the rigid motions at the mean (3 translations, 3
    # infinitesimal rotations), so that rigid alignment cannot absorb any shape variation.
    centred = verts - verts.mean(axis=0)
    rigid = [np.tile(np.eye(3)[a], (verts.shape[0], 1)).reshape(-1) for a in range(3)]
    rigid += [np.cross(np.eye(3)[a], centred).reshape(-1) for a in range(3)]
    q, _ = np.linalg.qr(np.stack(rigid + fields, axis=1))
    return q[:, 6 : 6 + n_components].T.reshape(n_components, -1, 3)


def make_toy_model(
    n_components: int = 5,
    *,
    n_around: int = 12,
    n_rings: int = 30,
    n_joints: int = 4,
    seed: int = 0,
) -> SScapeModel:
    """A synthetic S-SCAPE model on the tube (362 vertices and 4 joints by default)."""
    verts, faces = tube_mesh(n_around, n_rings)
    rig = toy_rig(n_around, n_rings, n_joints)
    basis = toy_basis(verts, n_components, seed)
    stddev = 0.05 * 0.6 ** np.arange(n_components)
    var = stddev**2
    explained = var / (var.sum() * 1.1)
    return SScapeModel(
        mean=verts,
        basis=basis,
        stddev=stddev,
        explained_variance=explained,
        faces=faces,
        rig=rig,
    )
