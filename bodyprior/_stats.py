"""Host-side (NumPy, float64) statistics shared by the asset builder, the registration core and the
model families: deterministic PCA and the sum-to-one vertex joint regressor."""

from __future__ import annotations

import numpy as np
import scipy.linalg


def pca_host(x: np.ndarray):
    """PCA of `(N, D)` data in float64: returns mean, components `(R, D)`, singular values
    `(R,)`."""
    mu = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mu, full_matrices=False)
    r = max(min(x.shape[0] - 1, x.shape[1]), 0)
    vt, s = vt[:r], s[:r]
    # Deterministic signs: the largest-magnitude entry of each component is positive.
    pivot = np.argmax(np.abs(vt), axis=1)
    signs = np.sign(vt[np.arange(r), pivot])
    signs[signs == 0] = 1.0
    return mu, vt * signs[:, None], s


def joint_regressor(
    template: np.ndarray,
    point: np.ndarray,
    verts: np.ndarray,
    points: np.ndarray,
    k: int = 256,
    ridge=1e-6,
):
    """Weights w over the k template vertices nearest to a joint point such that sum_i w_i v_i
    reproduces the joint point over a sample of bodies (least squares with sum w = 1, so the map
    commutes with translations and rotations).

    verts: (S, V, 3) sampled rest meshes; points: (S, 3) the joint point on each.
    Returns (indices (k,) int32, weights (k,)).
    """
    nn = np.argsort(np.linalg.norm(template - point, axis=1))[:k]
    A = np.transpose(verts[:, nn], (0, 2, 1)).reshape(-1, k)
    b = points.reshape(-1)
    w0 = np.full(k, 1.0 / k)
    N = scipy.linalg.null_space(np.ones((1, k)))
    Az = A @ N
    z = np.linalg.solve(Az.T @ Az + ridge * np.eye(k - 1), Az.T @ (b - A @ w0))
    return nn.astype(np.int32), w0 + N @ z
