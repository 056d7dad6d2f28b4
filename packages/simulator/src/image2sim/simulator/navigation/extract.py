"""Navigable-area extraction: posed RGB-D (or a world point cloud) -> :class:`~.navmap.NavMap`.

Pipeline (seed paper, appendix "Navigable Area Extraction and Denoising"):

1. floor candidates: semantic floor labels when given, and upward normals (n_z >= 0.5; the 5x5 Sobel
   estimator of :func:`image2sim.simulator.geometry.normals.point_normals` for captures);
2. RANSAC ground plane -> gravity alignment (rotate so the ground normal is +Z; skipped when the
   tilt is below 0.5 degrees, the usual case for Z-up captures);
3. 0.05 m voxels; floor voxels stacked in a column within one voxel merge into one *floor cell*;
4. floor components: cells connected where neighbouring heights differ by at most the maximum step
   height; components under the capture cameras are kept (tabletops, ceilings seen as floors and
   other islands are dropped and become obstacles);
5. storeys by height clustering, one RANSAC plane per storey; morphological closing of each storey's
   2D floor mask fills occlusion holes, the filled cells are re-projected onto the storey plane;
6. radius outlier removal of obstacle voxels; per floor-height band, the clearance is the distance
   to the obstacle columns (obstacles between the step height and the body height above that floor)
   and to unsupported columns (:func:`.clearance.floor_clearance`); cells with clearance >= the
   safety buffer (default: the agent radius) are navigable. ``NavMapConfig.unknown_clearance``
   (default 0: the paper's rule, where only obstacles project the buffer; None: the buffer) sets how
   near a storey's floor may come to unseen columns; drops and floor off a storey's plane (treads)
   keep the buffer to every unsupported column.

Everything is expressed in the *map frame*: the gravity-aligned world (identical to the world frame
when ``rotation`` is the identity, i.e. for Z-up captures). :attr:`NavMap.points` is returned in world
coordinates.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from image2sim.simulator.navigation.clearance import disk, floor_clearance
from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
from image2sim.simulator.navigation.navmap import HEIGHT_TOLERANCE, NavMap, NavMapError
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "extract_navmap",
    "extract_navmap_from_points",
    "extract_navmap_from_gaussians",
    "fit_plane_ransac",
    "rotation_aligning",
    "estimate_normals_pca",
    "radius_outlier_mask",
]


# ----------------------------------------------------------------------------------------------
# Small pure helpers
# ----------------------------------------------------------------------------------------------


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


def _pack_keys(ijk: np.ndarray) -> np.ndarray:
    """Integer voxel indices (N, 3) in [-2^19, 2^19) -> one int64 key each (fast 1D ``np.unique``)."""
    m = np.int64(1 << _KEY_BITS)
    q = ijk.astype(np.int64) + _KEY_OFFSET
    if len(q) and (q.min() < 0 or q.max() >= m):
        raise NavMapError(f"voxel indices exceed +-{_KEY_OFFSET} cells: the scene is implausibly large")
    return (q[:, 0] * m + q[:, 1]) * m + q[:, 2]


def _unpack_keys(keys: np.ndarray) -> np.ndarray:
    m = np.int64(1 << _KEY_BITS)
    return np.column_stack((keys // (m * m), (keys // m) % m, keys % m)) - _KEY_OFFSET


def _voxel_reduce(
    ijk: np.ndarray, values: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group rows by integer voxel ``ijk`` (N, 3): unique voxels, weighted mean values, summed weights."""
    if len(ijk) == 0:
        return ijk.reshape(0, 3).astype(np.int64), values.reshape(0, values.shape[1]), weights.reshape(0)
    uniq, inverse = np.unique(_pack_keys(ijk), return_inverse=True)
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
    return _unpack_keys(uniq), means, wsum


def _band_columns(
    obstacle_ij: np.ndarray, obstacle_z: np.ndarray, lo: float, hi: float, shape2d: tuple[int, int]
) -> np.ndarray:
    """2D mask of columns holding an obstacle voxel whose height lies in (lo, hi]."""
    mask = np.zeros(shape2d, dtype=bool)
    sel = (obstacle_z > lo) & (obstacle_z <= hi)
    mask[obstacle_ij[sel, 0], obstacle_ij[sel, 1]] = True
    return mask


# ----------------------------------------------------------------------------------------------
# Extraction
# ----------------------------------------------------------------------------------------------


def extract_navmap_from_points(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    camera_positions: np.ndarray | None = None,
    embodiment: Embodiment | None = None,
    config: NavMapConfig | None = None,
    weights: np.ndarray | None = None,
) -> NavMap:
    """Navigable map of a world point cloud (N, 3) in metres, Z roughly up.

    Args:
        points: (N, 3) world points (non-finite rows are dropped).
        normals: (N, 3) unit normals facing the observer; None = PCA normals oriented towards the
            nearest camera (or upwards without cameras).
        labels: (N,) semantic category ids; with ``config.floor_labels`` only those count as floor.
        camera_positions: (C, 3) capture camera centres; they seed the kept floor components.
        embodiment: agent body (default: the paper's).
        config: extraction settings (default: the paper's).
        weights: (N,) per-point weights (e.g. counts of pre-merged points); default 1.
    """
    emb = embodiment or Embodiment()
    cfg = config or NavMapConfig()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise NavMapError(f"points must have shape (N, 3), got {pts.shape}")
    keep = np.isfinite(pts).all(axis=1)
    cams = None if camera_positions is None else np.asarray(camera_positions, dtype=np.float64).reshape(-1, 3)
    if normals is None:
        nrm = estimate_normals_pca(pts[keep], viewpoints=cams)
        full = np.zeros_like(pts)
        full[keep] = nrm
        nrm = full
    else:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise NavMapError(f"normals must match points {pts.shape}, got {nrm.shape}")
    floor = nrm[:, 2] >= cfg.normal_z_min
    if labels is not None and cfg.floor_labels:
        lab = np.asarray(labels).reshape(-1)
        if len(lab) != len(pts):
            raise NavMapError(f"labels must have one entry per point ({len(pts)}), got {len(lab)}")
        floor &= np.isin(lab, cfg.floor_labels)
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    return _build_navmap(pts[keep], floor[keep], w[keep], cams, emb, cfg)


def extract_navmap_from_gaussians(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opacities: np.ndarray | None = None,
    camera_positions: np.ndarray | None = None,
    embodiment: Embodiment | None = None,
    config: NavMapConfig | None = None,
    min_opacity: float = 0.1,
) -> NavMap:
    """Navigable map of a Gaussian scene: each Gaussian is a point whose normal is its thinnest axis.

    ``quats`` are (w, x, y, z); normals face the nearest camera (upwards without cameras). Gaussians
    with opacity below ``min_opacity`` are ignored (floaters).
    """
    mu = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    w, x, y, z = q.T
    # Rotation matrices of the quaternions; column k is the Gaussian's k-th axis.
    rot = np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)), axis=1),
            np.stack((2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)), axis=1),
            np.stack((2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)), axis=1),
        ),
        axis=2,
    )
    thin = np.argmin(np.asarray(scales, dtype=np.float64).reshape(-1, 3), axis=1)
    nrm = rot[np.arange(len(mu)), :, thin]
    keep = (
        np.ones(len(mu), dtype=bool)
        if opacities is None
        else np.asarray(opacities).reshape(-1) >= min_opacity
    )
    cams = None if camera_positions is None else np.asarray(camera_positions, dtype=np.float64).reshape(-1, 3)
    if cams is not None and len(cams):
        _, nearest = cKDTree(cams).query(mu)
        flip = np.einsum("ij,ij->i", nrm, cams[nearest] - mu) < 0
    else:
        flip = nrm[:, 2] < 0
    nrm[flip] *= -1.0
    return extract_navmap_from_points(mu[keep], nrm[keep], None, cams, embodiment, config)


def extract_navmap(
    capture: Iterable,
    embodiment: Embodiment | None = None,
    config: NavMapConfig | None = None,
    progress: bool = False,
) -> NavMap:
    """Navigable map of a :class:`~image2sim.simulator.io.records.Capture` (any iterable of Frames).

    Frames are back-projected with their camera's ``unproject`` and pose; normals come from the
    5x5 Sobel estimator (``point_normals``); frames carrying ``semantics`` use ``config.floor_labels``.
    Points are pre-merged into 0.05 m voxels per frame so memory stays bounded.
    """
    import torch
    from image2sim.simulator.geometry.normals import point_normals

    emb = embodiment or Embodiment()
    cfg = config or NavMapConfig()
    vox = cfg.voxel_size
    acc_keys, acc_vals, acc_w, cams = [], [], [], []
    ray_cache: dict = {}
    frames = capture
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task(
            "back-projecting frames", total=len(capture) if hasattr(capture, "__len__") else None
        )
    try:
        for frame in frames:
            depth = np.asarray(frame.depth, dtype=np.float32)
            unit_points, small_camera, off = _strided_rays(frame.camera, cfg.pixel_stride, ray_cache)
            s = cfg.pixel_stride
            depth_s = np.ascontiguousarray(
                depth[off::s, off::s][: unit_points.shape[0], : unit_points.shape[1]]
            )
            d_t = torch.from_numpy(np.where(np.isfinite(depth_s), depth_s, 0.0).astype(np.float32))
            # Normals on the strided grid (the paper's 5x5 Sobel estimator); points from exact rays.
            nrm_s = point_normals(d_t[None, None], small_camera)[0].permute(1, 2, 0).numpy()
            pts_s = depth_s[..., None] * unit_points
            valid = np.isfinite(depth_s) & (depth_s > 0) & (depth_s <= cfg.max_range)
            pose = np.asarray(frame.cam_to_world, dtype=np.float64)
            p_w = pts_s[valid].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            n_w = nrm_s[valid].astype(np.float64) @ pose[:3, :3].T
            is_floor = n_w[:, 2] >= cfg.normal_z_min
            sem = getattr(frame, "semantics", None)
            if sem is not None and cfg.floor_labels:
                sem_s = np.asarray(sem)[off::s, off::s][: unit_points.shape[0], : unit_points.shape[1]]
                is_floor &= np.isin(sem_s[valid], cfg.floor_labels)
            cams.append(pose[:3, 3])
            # Pre-merge per frame: key = (voxel ijk, floor flag) in a fixed world lattice.
            ijk = np.floor(p_w / vox).astype(np.int64)
            key = np.column_stack((ijk[:, 0], ijk[:, 1], ijk[:, 2] * 2 + is_floor))
            uk, mean, wsum = _voxel_reduce(key, p_w, np.ones(len(p_w)))
            acc_keys.append((uk[:, 2] % 2).astype(bool))
            acc_vals.append(mean)
            acc_w.append(wsum)
            if bar is not None:
                bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()
    if not acc_vals:
        raise NavMapError("capture has no frames: cannot extract a navigable map")
    pts = np.concatenate(acc_vals)
    floor = np.concatenate(acc_keys)
    w = np.concatenate(acc_w)
    return _build_navmap(pts, floor, w, np.asarray(cams), emb, cfg)


def _strided_rays(camera, stride: int, cache: dict):
    """Depth-1 points (h, w, 3) at every ``stride``-th pixel centre (offset ``stride // 2``), the
    camera model of that strided grid (for normals) and the offset; cached per camera."""
    import torch
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    key = (camera, stride)
    if key not in cache:
        off = stride // 2
        h = len(range(off, camera.height, stride))
        w = len(range(off, camera.width, stride))
        v = torch.arange(h, dtype=torch.float64) * stride + off + 0.5
        u = torch.arange(w, dtype=torch.float64) * stride + off + 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        rays = camera.pixel_to_ray(uu, vv)
        if isinstance(camera, PinholeCamera):
            rays = rays / rays[..., 2:3]  # pinhole depth is z: scale rays to z = 1
            small = PinholeCamera(
                camera.fx / stride,
                camera.fy / stride,
                (camera.cx - off - 0.5) / stride + 0.5,
                (camera.cy - off - 0.5) / stride + 0.5,
                h,
                w,
            )
        elif isinstance(camera, EquirectCamera):
            small = EquirectCamera(h, w)  # half-pixel shift for even strides: negligible for normals
        else:
            raise NavMapError(f"unsupported camera model {type(camera).__name__}")
        cache[key] = (rays.numpy().astype(np.float32), small, off)
    return cache[key]


def _build_navmap(
    pts: np.ndarray,
    floor: np.ndarray,
    weights: np.ndarray,
    cams: np.ndarray | None,
    emb: Embodiment,
    cfg: NavMapConfig,
) -> NavMap:
    """Core of the extraction on points already classified as floor candidates or not."""
    notes: list[str] = []
    vox = cfg.voxel_size
    rng = np.random.default_rng(cfg.seed)
    if len(pts) == 0:
        raise NavMapError("no finite points: cannot extract a navigable map")
    if floor.sum() < 3:
        raise NavMapError(
            f"only {int(floor.sum())} floor-candidate points (upward normals"
            + (f" with labels {list(cfg.floor_labels)}" if cfg.floor_labels else "")
            + "): no floor to navigate"
        )

    # 1. Gravity: the dominant upward plane's normal becomes +Z.
    rotation = np.eye(3)
    if cfg.align_gravity:
        fp = pts[floor]
        if len(fp) > 50000:
            fp = fp[rng.choice(len(fp), 50000, replace=False)]
        n, _, _ = fit_plane_ransac(fp, cfg.ransac_threshold, cfg.ransac_iterations, rng)
        tilt = math.degrees(math.acos(min(1.0, abs(float(n[2])))))
        if 0.5 < tilt <= cfg.max_tilt_deg:
            rotation = rotation_aligning(n, np.array([0.0, 0.0, 1.0]))
            pts = pts @ rotation.T
            if cams is not None:
                cams = cams @ rotation.T
            notes.append(
                f"gravity corrected by {tilt:.2f} deg (RANSAC ground normal {np.round(n, 4).tolist()})"
            )
        elif tilt > cfg.max_tilt_deg:
            notes.append(f"RANSAC ground normal tilted {tilt:.1f} deg > max_tilt_deg: not corrected")

    # 2. Voxel lattice (one voxel margin so the border is always unknown space).
    lo = np.floor(pts.min(axis=0) / vox) * vox - vox
    hi = pts.max(axis=0)
    shape = tuple(int(v) for v in np.floor((hi - lo) / vox).astype(np.int64) + 2)
    ijk = np.floor((pts - lo) / vox).astype(np.int64)
    ijk = np.minimum(ijk, np.array(shape) - 1)
    f_ijk, f_mean, f_w = _voxel_reduce(ijk[floor], pts[floor], weights[floor])
    o_ijk, o_mean, o_w = _voxel_reduce(ijk[~floor], pts[~floor], weights[~floor])

    # Obstacle denoising: radius outlier removal on voxel centres (before obstacles judge floors).
    if len(o_ijk):
        inlier = radius_outlier_mask(o_ijk * vox, cfg.outlier_radius, int(cfg.outlier_min_neighbors))
        if (~inlier).any():
            notes.append(
                f"radius outlier removal dropped {int((~inlier).sum())} of {len(inlier)} obstacle voxels"
            )
        o_ijk, o_mean, o_w = o_ijk[inlier], o_mean[inlier], o_w[inlier]
    # Floor candidates with an obstacle voxel right above them (within 2 voxels) belong to a vertical
    # surface whose normals the Sobel window blended with a floor's (sides of beds, risers): they
    # would otherwise form ramps joining the floor to furniture tops.
    covered = _covered_from_above(f_ijk, o_ijk, 2)
    support_ij, support_z = f_ijk[covered, :2], f_mean[covered, 2]
    if covered.any():
        o_ijk = np.concatenate((o_ijk, f_ijk[covered]))
        o_mean = np.concatenate((o_mean, f_mean[covered]))
        o_w = np.concatenate((o_w, f_w[covered]))
        f_ijk, f_mean, f_w = f_ijk[~covered], f_mean[~covered], f_w[~covered]
    if len(f_ijk) == 0:
        raise NavMapError("every floor candidate lies directly under an obstacle: no floor to navigate")

    # 3. Floor cells: floor voxels stacked within one voxel in a column merge.
    cell_of_voxel, c_ij, c_z = _merge_floor_columns(f_ijk, f_mean[:, 2], f_w, shape)

    # 4. Components connected within the step height; keep those under cameras (or large ones).
    comp = _floor_components(c_ij, c_z, emb.max_step_height)
    keep_comp = _select_components(comp, c_ij, c_z, cams, lo, vox, cfg, notes)
    keep_cell = np.isin(comp, keep_comp)
    if not keep_cell.any():
        raise NavMapError("no floor component survived (no camera above a floor and none large enough)")
    # Rejected floor (tabletops, ceilings mistaken for floors, islands) are obstacles.
    rejected_vox = ~keep_cell[cell_of_voxel]
    o_ijk = np.concatenate((o_ijk, f_ijk[rejected_vox]))
    o_mean = np.concatenate((o_mean, f_mean[rejected_vox]))
    o_w = np.concatenate((o_w, f_w[rejected_vox]))
    c_ij, c_z = c_ij[keep_cell], c_z[keep_cell]

    obstacle_ij, obstacle_z = o_ijk[:, :2], o_mean[:, 2]
    obstacle_xyz = o_mean

    # 6. Storeys, planes, hole filling.
    level_heights = _cluster_levels(c_z, vox, cfg.min_level_area, 2.0 * cfg.level_tolerance + vox)
    level_planes = np.zeros((len(level_heights), 4))
    for li, h in enumerate(level_heights):
        member = np.abs(c_z - h) <= cfg.level_tolerance
        xyz = np.column_stack((lo[:2] + (c_ij[member] + 0.5) * vox, c_z[member]))
        if len(xyz) >= 3:
            n, d, _ = fit_plane_ransac(xyz, cfg.ransac_threshold, cfg.ransac_iterations, rng)
            if n[2] < 0.9:  # a storey plane must be near horizontal after alignment
                n, d = np.array([0.0, 0.0, 1.0]), -h
        else:
            n, d = np.array([0.0, 0.0, 1.0]), -h
        level_planes[li] = (*n, d)
    c_level = np.argmin(np.abs(c_z[:, None] - level_heights[None, :]), axis=1)
    filled_ij, filled_z, filled_level = _fill_holes(
        c_ij, c_z, c_level, level_heights, level_planes, obstacle_ij, obstacle_z, lo, vox, shape, emb, cfg
    )
    floor_ij = np.concatenate((c_ij, filled_ij)).astype(np.int64)
    floor_z = np.concatenate((c_z, filled_z))
    floor_level = np.concatenate((c_level, filled_level)).astype(np.int64)
    floor_filled = np.concatenate((np.zeros(len(c_z), bool), np.ones(len(filled_z), bool)))

    navmap = NavMap(
        voxel_size=vox,
        origin=lo,
        shape=shape,  # type: ignore[arg-type]
        floor_ij=floor_ij,
        floor_z=floor_z,
        floor_level=floor_level,
        floor_filled=floor_filled,
        clearance=np.zeros(len(floor_z)),
        navigable=np.zeros(len(floor_z), dtype=bool),
        obstacle_ij=obstacle_ij.astype(np.int64),
        obstacle_xyz=obstacle_xyz,
        support_ij=support_ij.astype(np.int64),
        support_z=support_z,
        level_heights=level_heights,
        level_planes=level_planes,
        rotation=rotation,
        embodiment=emb,
        config=cfg,
        notes=notes,
    )
    # 7. Clearance; cells with clearance >= the safety buffer are navigable.
    navmap.clearance = floor_clearance(navmap)
    navmap.navigable = navmap.clearance >= navmap.safety_buffer - 1e-9
    if not navmap.navigable.any():
        notes.append("no floor cell has the required clearance: the map has no navigable cell")
    return navmap


def _covered_from_above(f_ijk: np.ndarray, o_ijk: np.ndarray, n_above: int) -> np.ndarray:
    """True for floor voxels that have an obstacle voxel 1..n_above voxels above in their column."""
    if len(f_ijk) == 0 or len(o_ijk) == 0:
        return np.zeros(len(f_ijk), dtype=bool)
    okeys = np.sort(_pack_keys(o_ijk))
    out = np.zeros(len(f_ijk), dtype=bool)
    for dk in range(1, n_above + 1):
        q = _pack_keys(f_ijk + np.array([0, 0, dk]))
        pos = np.clip(np.searchsorted(okeys, q), 0, len(okeys) - 1)
        out |= okeys[pos] == q
    return out


def _merge_floor_columns(
    f_ijk: np.ndarray, f_z: np.ndarray, f_w: np.ndarray, shape: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge floor voxels of one column whose k differ by <= 1 into cells (weighted mean height).

    Returns (cell index of every voxel, cell columns (C, 2), cell heights (C,)).
    """
    if len(f_ijk) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.int64), np.zeros(0)
    col = f_ijk[:, 0] * shape[1] + f_ijk[:, 1]
    order = np.lexsort((f_ijk[:, 2], col))
    col_s, k_s = col[order], f_ijk[order, 2]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (col_s[1:] != col_s[:-1]) | (k_s[1:] - k_s[:-1] > 1)
    cell_sorted = np.cumsum(new) - 1
    cell = np.empty(len(order), dtype=np.int64)
    cell[order] = cell_sorted
    n_cells = int(cell_sorted[-1]) + 1
    wsum = np.bincount(cell, weights=f_w, minlength=n_cells)
    z = np.bincount(cell, weights=f_z * f_w, minlength=n_cells) / wsum
    ij = np.zeros((n_cells, 2), dtype=np.int64)
    ij[cell] = f_ijk[:, :2]
    return cell, ij, z


def _floor_components(
    c_ij: np.ndarray, c_z: np.ndarray, max_step: float, planar_tol: float = 0.03, bridge: int = 3
) -> np.ndarray:
    """Connected-component id of every floor cell.

    Cells whose 8-neighbours (within the step height) all lie within ``planar_tol`` in height are
    *planar*. Planar cells connect when they lie within ``bridge`` cells (Chebyshev) of each other
    and their heights differ by at most ``max_step``: this crosses the two non-planar cells around a
    stair riser, but not the steep "ramps" that blended normals leave on the sides of beds and
    tables (those would chain the floor to furniture tops in steps below ``max_step``). Each
    non-planar cell then joins the component of its planar neighbour closest in height.
    """
    n = len(c_z)
    if n == 0:
        return np.zeros(0, np.int64)
    step = max(max_step + HEIGHT_TOLERANCE, 1e-6)
    # Chebyshev ball in (i, j, z * bridge / step): |di|, |dj| <= bridge and |dz| <= step.
    coords = np.column_stack((c_ij.astype(np.float64), c_z * (bridge / step)))
    pairs = cKDTree(coords).query_pairs(r=bridge + 1e-9, p=np.inf, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    cheb = np.abs(c_ij[a] - c_ij[b]).max(axis=1)
    dz = np.abs(c_z[a] - c_z[b])
    adjacent = cheb <= 1
    spread = np.zeros(n)
    np.maximum.at(spread, a[adjacent], dz[adjacent])
    np.maximum.at(spread, b[adjacent], dz[adjacent])
    planar = spread <= planar_tol
    both = planar[a] & planar[b]
    adj = coo_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    labels = labels.astype(np.int64)
    # Non-planar cells take the label of the planar neighbour (<= 2 cells) closest in height.
    labels[~planar] = n + np.flatnonzero(~planar)  # singletons unless attached below
    near = (cheb <= 2) & (planar[a] != planar[b])
    src = np.where(planar[a[near]], a[near], b[near])
    dst = np.where(planar[a[near]], b[near], a[near])
    order = np.argsort(-dz[near], kind="stable")  # the smallest |dz| is written last and wins
    labels[dst[order]] = labels[src[order]]
    return labels


def _select_components(
    comp: np.ndarray,
    c_ij: np.ndarray,
    c_z: np.ndarray,
    cams: np.ndarray | None,
    origin: np.ndarray,
    vox: float,
    cfg: NavMapConfig,
    notes: list[str],
) -> np.ndarray:
    """Component ids to keep: those supporting a capture camera, else all large enough."""
    xy = origin[:2] + (c_ij + 0.5) * vox
    if cams is not None and len(cams):
        tree = cKDTree(xy)
        cands = []
        for cam in cams:
            cand = np.asarray(tree.query_ball_point(cam[:2], r=cfg.camera_support_radius), dtype=np.int64)
            cands.append(cand[c_z[cand] <= cam[2] - cfg.min_camera_height])
        # Pass 1: the nearest floor below each camera gives the typical camera height of the capture.
        first = [
            c[np.argmin(np.linalg.norm(xy[c] - cam[:2], axis=1))]
            for c, cam in zip(cands, cams, strict=True)
            if len(c)
        ]
        heights = [
            cam[2] - c_z[f]
            for f, cam in zip(first, [cm for c, cm in zip(cands, cams, strict=True) if len(c)], strict=True)
        ]
        typical = float(np.median(heights)) if heights else None
        # Pass 2: prefer cells at that height below the camera (on stairs the nearest cell may be
        # another flight); fall back to the nearest cell.
        seeds = []
        for cand, cam in zip(cands, cams, strict=True):
            if not len(cand):
                continue
            d = np.linalg.norm(xy[cand] - cam[:2], axis=1)
            if typical is not None:
                ok = np.abs(cam[2] - c_z[cand] - typical) <= 0.3
                if ok.any():
                    cand, d = cand[ok], d[ok]
            seeds.append(comp[cand[np.argmin(d)]])
        missing = len(cams) - len(seeds)
        if missing:
            notes.append(
                f"{missing} of {len(cams)} cameras have no floor below within {cfg.camera_support_radius} m"
            )
        if seeds:
            return np.unique(seeds)
        notes.append("no camera lies above a floor: kept components by area instead")
    area = np.bincount(comp) * vox * vox
    keep = np.flatnonzero(area >= cfg.min_component_area)
    if len(keep) == 0 and len(area):
        keep = np.array([int(np.argmax(area))])
    return keep


def _cluster_levels(c_z: np.ndarray, vox: float, min_area: float, min_separation: float) -> np.ndarray:
    """Storey heights from a height histogram of floor cells (peaks >= min_area, >= min_separation apart)."""
    lo = float(c_z.min())
    bins = np.floor((c_z - lo) / vox).astype(np.int64)
    area = np.bincount(bins).astype(np.float64) * vox * vox
    # Sum over 3 neighbouring bins so a floor straddling a bin edge counts once, whole.
    smooth = np.convolve(area, np.ones(3), mode="same")
    order = np.argsort(-smooth, kind="stable")
    peaks: list[int] = []
    for b in order:
        if smooth[b] < min_area:
            break
        if all(abs(int(b) - p) * vox >= min_separation for p in peaks):
            peaks.append(int(b))
    if not peaks:  # a small scene: its single most populated height is the storey
        peaks = [int(order[0])]
    heights = []
    for p in sorted(peaks):
        sel = np.abs(bins - p) <= 1
        heights.append(float(np.median(c_z[sel])))
    return np.asarray(heights)


def _fill_holes(
    c_ij: np.ndarray,
    c_z: np.ndarray,
    c_level: np.ndarray,
    level_heights: np.ndarray,
    level_planes: np.ndarray,
    obstacle_ij: np.ndarray,
    obstacle_z: np.ndarray,
    origin: np.ndarray,
    vox: float,
    shape: tuple[int, ...],
    emb: Embodiment,
    cfg: NavMapConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Morphological closing of each storey's floor mask; new cells lie on the storey plane.

    Cells are not added in columns that already hold a floor within a body height of the storey
    (stairs, the storey itself) nor where an obstacle stands in the storey's body band.
    """
    r = int(cfg.closing_radius_cells)
    shape2d = (int(shape[0]), int(shape[1]))
    empty = (np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64))
    if r <= 0 or len(level_heights) == 0:
        return empty
    out_ij, out_z, out_l = [], [], []
    struct = disk(r)
    for li, h in enumerate(level_heights):
        a, b, c, d = level_planes[li]
        member = (c_level == li) & (np.abs(c_z - h) <= cfg.level_tolerance)
        if not member.any():
            continue
        mask = np.zeros(shape2d, dtype=bool)
        mask[c_ij[member, 0], c_ij[member, 1]] = True
        closed = ndimage.binary_closing(np.pad(mask, r), structure=struct)[r:-r, r:-r]
        near = np.abs(c_z - h) < emb.height
        occupied = np.zeros(shape2d, dtype=bool)
        occupied[c_ij[near, 0], c_ij[near, 1]] = True
        occupied |= _band_columns(
            obstacle_ij, obstacle_z, h + emb.max_step_height + HEIGHT_TOLERANCE, h + emb.height, shape2d
        )
        new = closed & ~mask & ~occupied
        ij = np.argwhere(new)
        if len(ij) == 0:
            continue
        xy = origin[:2] + (ij + 0.5) * vox
        z = -(d + a * xy[:, 0] + b * xy[:, 1]) / c
        out_ij.append(ij)
        out_z.append(z)
        out_l.append(np.full(len(ij), li, dtype=np.int64))
    if not out_ij:
        return empty
    return np.concatenate(out_ij), np.concatenate(out_z), np.concatenate(out_l)
