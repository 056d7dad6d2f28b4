"""Point-cloud helpers of navigable-area extraction (:mod:`.extract`): RANSAC planes, the rotation
that aligns the ground with +Z, PCA normals, radius outliers, and packed voxel keys with their
weighted reduction and per-height column masks. Pure numpy / scipy functions."""

from __future__ import annotations

import numpy as np
from image2sim.simulator.navigation.navmap import NavMapError
from scipy.spatial import cKDTree

__all__ = [
    "band_columns",
    "estimate_normals_pca",
    "fit_plane_ransac",
    "pack_keys",
    "radius_outlier_mask",
    "rotation_aligning",
    "unpack_keys",
    "voxel_reduce",
]


def fit_plane_ransac(
    points: np.ndarray, threshold: float, iterations: int, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane ``n . p + d = 0`` through (N, 3) points, refined by least squares on the inliers.

    Returns ``(n, d, inliers)`` with ``n`` a unit normal oriented towards +Z (n_z >= 0).
    Raises :class:`NavMapError` for fewer than 3 points or fully degenerate input.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise NavMapError(f"plane fit needs at least 3 points of shape (N, 3), got {pts.shape}")
    n_pts = len(pts)
    triples = rng.integers(0, n_pts, size=(iterations, 3))
    a, b, c = pts[triples[:, 0]], pts[triples[:, 1]], pts[triples[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    if not ok.any():
        raise NavMapError("plane fit: all sampled point triples are collinear")
    normals = normals[ok] / norms[ok, None]
    ds = -np.einsum("ij,ij->i", normals, a[ok])
    # Score all hypotheses on a subsample so the cost stays bounded on big clouds.
    sample = pts if n_pts <= 20000 else pts[rng.choice(n_pts, 20000, replace=False)]
    scores = (np.abs(sample @ normals.T + ds) < threshold).sum(axis=0)
    best = int(np.argmax(scores))
    inliers = np.abs(pts @ normals[best] + ds[best]) < threshold
    if inliers.sum() >= 3:
        centre = pts[inliers].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[inliers] - centre, full_matrices=False)
        n = vt[-1]
        d = -float(n @ centre)
    else:
        n, d = normals[best], float(ds[best])
    if n[2] < 0:
        n, d = -n, -d
    inliers = np.abs(pts @ n + d) < threshold
    return n, d, inliers


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3x3) taking unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Opposite vectors: rotate by pi about any axis perpendicular to a.
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - c) / (s * s))


def estimate_normals_pca(points: np.ndarray, k: int = 12, viewpoints: np.ndarray | None = None) -> np.ndarray:
    """Unit normals of an (N, 3) cloud from the smallest PCA axis of each point's k nearest neighbours.

    Orientation: towards the nearest of ``viewpoints`` (M, 3) when given, otherwise upwards
    (n_z >= 0) -- without viewpoints a ceiling cannot be told from a floor.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3))
    k = int(min(k, len(pts)))
    tree = cKDTree(pts)
    _, idx = tree.query(pts, k=k)
    idx = idx.reshape(len(pts), k)
    out = np.empty_like(pts)
    for start in range(0, len(pts), 100_000):  # bounded memory: (chunk, k, 3) at a time
        nb = pts[idx[start : start + 100_000]]
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred)
        _, vecs = np.linalg.eigh(cov)
        out[start : start + 100_000] = vecs[:, :, 0]
    if viewpoints is not None and len(viewpoints):
        vp = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3)
        _, nearest = cKDTree(vp).query(pts)
        flip = np.einsum("ij,ij->i", out, vp[nearest] - pts) < 0
    else:
        flip = out[:, 2] < 0
    out[flip] *= -1.0
    return out


def radius_outlier_mask(points: np.ndarray, radius: float, min_neighbors: int) -> np.ndarray:
    """True for points with at least ``min_neighbors`` *other* points within ``radius``."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0 or min_neighbors <= 0:
        return np.ones(len(pts), dtype=bool)
    counts = cKDTree(pts).query_ball_point(pts, r=radius, return_length=True)
    return (np.asarray(counts) - 1) >= min_neighbors


_KEY_BITS = 20
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """Integer voxel indices (N, 3) in [-2^19, 2^19) -> one int64 key each (fast 1D ``np.unique``)."""
    m = np.int64(1 << _KEY_BITS)
    q = ijk.astype(np.int64) + _KEY_OFFSET
    if len(q) and (q.min() < 0 or q.max() >= m):
        raise NavMapError(f"voxel indices exceed +-{_KEY_OFFSET} cells: the scene is implausibly large")
    return (q[:, 0] * m + q[:, 1]) * m + q[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    m = np.int64(1 << _KEY_BITS)
    return np.column_stack((keys // (m * m), (keys // m) % m, keys % m)) - _KEY_OFFSET


def voxel_reduce(
    ijk: np.ndarray, values: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group rows by integer voxel ``ijk`` (N, 3): unique voxels, weighted mean values, summed weights."""
    if len(ijk) == 0:
        return ijk.reshape(0, 3).astype(np.int64), values.reshape(0, values.shape[1]), weights.reshape(0)
    uniq, inverse = np.unique(pack_keys(ijk), return_inverse=True)
    inverse = inverse.reshape(-1)
    wsum = np.bincount(inverse, weights=weights, minlength=len(uniq))
    means = (
        np.stack(
            [
                np.bincount(inverse, weights=values[:, c] * weights, minlength=len(uniq))
                for c in range(values.shape[1])
            ],
            axis=1,
        )
        / wsum[:, None]
    )
    return unpack_keys(uniq), means, wsum


def band_columns(
    obstacle_ij: np.ndarray, obstacle_z: np.ndarray, lo: float, hi: float, shape2d: tuple[int, int]
) -> np.ndarray:
    """2D mask of columns holding an obstacle voxel whose height lies in (lo, hi]."""
    mask = np.zeros(shape2d, dtype=bool)
    sel = (obstacle_z > lo) & (obstacle_z <= hi)
    mask[obstacle_ij[sel, 0], obstacle_ij[sel, 1]] = True
    return mask
