"""Navigable-area extraction: posed RGB-D (or a world point cloud) -> :class:`~.navmap.NavMap`.

Pipeline (seed paper, appendix "Navigable Area Extraction and Denoising"):

1. floor candidates: semantic floor labels when given, and upward normals (n_z >= 0.5; the 5x5 Sobel
   estimator of :func:`image2sim.simulator.geometry.normals.point_normals` for captures, completed
   next to depth holes by :func:`~image2sim.simulator.geometry.normals.hole_normals`);
2. RANSAC ground plane -> gravity alignment (rotate so the ground normal is +Z; skipped when the
   tilt is below 0.5 degrees, the usual case for Z-up captures);
3. 0.05 m voxels; floor voxels stacked in a column within one voxel merge into one *floor cell*;
4. floor components: cells connected where neighbouring heights differ by at most the maximum step
   height; components under the capture cameras are kept (tabletops, ceilings seen as floors and
   other islands are dropped and become obstacles); without camera support, the large components,
   less those standing a step to a body height above another (beds, tables);
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
from image2sim.simulator.navigation.carving import DepthView, floater_mask
from image2sim.simulator.navigation.clearance import floor_clearance
from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
from image2sim.simulator.navigation.floors import (
    cluster_levels,
    covered_from_above,
    fill_holes,
    floor_components,
    merge_floor_columns,
    select_components,
)
from image2sim.simulator.navigation.navmap import NavMap, NavMapError
from image2sim.simulator.navigation.pointcloud import (
    estimate_normals_pca,
    fit_plane_ransac,
    pack_keys,
    radius_outlier_mask,
    rotation_aligning,
    voxel_reduce,
)
from scipy.spatial import cKDTree

__all__ = [
    "extract_navmap",
    "extract_navmap_from_points",
    "extract_navmap_from_gaussians",
]


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
    from image2sim.simulator.geometry.normals import hole_normals, point_normals

    emb = embodiment or Embodiment()
    cfg = config or NavMapConfig()
    vox = cfg.voxel_size
    acc_keys, acc_vals, acc_w, acc_view, cams, views = [], [], [], [], [], []
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
            estimator = hole_normals if cfg.hole_normals else point_normals
            nrm_s = estimator(d_t[None, None], small_camera)[0].permute(1, 2, 0).numpy()
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
            if cfg.carve_min_views:
                views.append(DepthView(_nearest_per_block(depth, s, valid.shape, cfg), small_camera, pose))
            # Pre-merge per frame: key = (voxel ijk, floor flag) in a fixed world lattice.
            ijk = np.floor(p_w / vox).astype(np.int64)
            key = np.column_stack((ijk[:, 0], ijk[:, 1], ijk[:, 2] * 2 + is_floor))
            uk, mean, wsum = voxel_reduce(key, p_w, np.ones(len(p_w)))
            acc_keys.append((uk[:, 2] % 2).astype(bool))
            acc_vals.append(mean)
            acc_w.append(wsum)
            acc_view.append(np.full(len(mean), len(cams) - 1))
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
    notes: list[str] = []
    if cfg.carve_min_views and len(views) > 1:
        keep = _carve_floaters(pts, np.concatenate(acc_view), views, cfg, notes)
        pts, floor, w = pts[keep], floor[keep], w[keep]
    return _build_navmap(pts, floor, w, np.asarray(cams), emb, cfg, notes)


def _nearest_per_block(
    depth: np.ndarray, stride: int, shape: tuple[int, int], cfg: NavMapConfig
) -> np.ndarray:
    """(h, w) float32: the nearest valid depth of each ``stride`` x ``stride`` block of pixels (0
    where none), on the strided grid: carving then sees an obstacle thinner than the stride that
    the strided samples miss (a table leg between them)."""
    import torch
    import torch.nn.functional as F

    ok = np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_range)
    far = torch.from_numpy(np.where(ok, depth, np.inf).astype(np.float32))[None, None]
    near = -F.max_pool2d(-far, stride, stride, ceil_mode=True)[0, 0].numpy()[: shape[0], : shape[1]]
    return np.where(np.isfinite(near), near, 0.0).astype(np.float32)


def _carve_floaters(
    pts: np.ndarray, view_of: np.ndarray, views: list, cfg: NavMapConfig, notes: list[str]
) -> np.ndarray:
    """Which of the per-view pre-merged points to keep: points in voxels that other views see
    through are dropped, floor candidates as well as obstacles (a wrong-depth patch of floor is a
    level plateau in the air) (:func:`~image2sim.simulator.navigation.carving.floater_mask`)."""
    # The same grouping as voxel_reduce (one packed int64 key per voxel, not a row-wise unique),
    # keeping the inverse to map the verdict back to the points.
    keys, inverse = np.unique(pack_keys(np.floor(pts / cfg.voxel_size).astype(np.int64)), return_inverse=True)
    inverse = inverse.reshape(-1)
    # Views that put a point in each voxel (a view may hold a floor and an obstacle point there).
    pairs = np.unique(inverse * len(views) + view_of)
    support = np.bincount(pairs // len(views), minlength=len(keys))
    count = np.bincount(inverse, minlength=len(keys))[:, None]
    mean = np.stack([np.bincount(inverse, pts[:, k], len(keys)) for k in range(3)], axis=1) / count
    drop = floater_mask(mean, support, views, min_views=int(cfg.carve_min_views), ratio=cfg.carve_ratio)
    if drop.any():
        notes.append(f"visibility carving dropped {int(drop.sum())} of {len(keys)} voxels")
    return ~drop[inverse]


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
    notes: list[str] | None = None,
) -> NavMap:
    """Core of the extraction on points already classified as floor candidates or not."""
    notes = [] if notes is None else notes
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
    f_ijk, f_mean, f_w = voxel_reduce(ijk[floor], pts[floor], weights[floor])
    o_ijk, o_mean, o_w = voxel_reduce(ijk[~floor], pts[~floor], weights[~floor])

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
    covered = covered_from_above(f_ijk, o_ijk, 2)
    support_ij, support_z = f_ijk[covered, :2], f_mean[covered, 2]
    if covered.any():
        o_ijk = np.concatenate((o_ijk, f_ijk[covered]))
        o_mean = np.concatenate((o_mean, f_mean[covered]))
        o_w = np.concatenate((o_w, f_w[covered]))
        f_ijk, f_mean, f_w = f_ijk[~covered], f_mean[~covered], f_w[~covered]
    if len(f_ijk) == 0:
        raise NavMapError("every floor candidate lies directly under an obstacle: no floor to navigate")

    # 3. Floor cells: floor voxels stacked within one voxel in a column merge.
    cell_of_voxel, c_ij, c_z = merge_floor_columns(f_ijk, f_mean[:, 2], f_w, shape)

    # 4. Components connected within the step height; keep those under cameras (or large ones).
    comp = floor_components(c_ij, c_z, emb.max_step_height)
    keep_comp = select_components(comp, c_ij, c_z, cams, lo, vox, cfg, notes, emb)
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
    level_heights = cluster_levels(c_z, vox, cfg.min_level_area, 2.0 * cfg.level_tolerance + vox)
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
    filled_ij, filled_z, filled_level = fill_holes(
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
