"""Plane completion of textureless regions: segments of a view whose confident depth lies on one plane
get that plane's depth where the stereo left them empty.

The plane sweep cannot match plain walls, ceilings and doors (no texture in a 9 x 9 window), yet
their edges (corners, trims, things on them) are usually confident. Indoor surfaces are mostly
planar, so a colour segment whose confident pixels fit one plane is completed by intersecting its
remaining pixel rays with that plane, as textureless-aware MVS methods do with superpixels (e.g.
TAPA-MVS). Filled pixels get :data:`PLANE_FILL_CONFIDENCE`, below every confidence the sweep keeps.

Guards against filling what is not that plane: the segment must hold enough confident pixels, most
of them within ``inlier_tolerance`` (relative) of one plane, spread over a ``min_support_extent``
share of the segment's box; rays nearly parallel to the plane (grazing) and intersections farther
than ``max_depth_ratio`` times the view's confident depth range are not filled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from image2sim.simulator.lift.types import DepthEstimate, PinholeView, options_from_kwargs

__all__ = [
    "PLANE_FILL_CONFIDENCE",
    "PlaneFillConfig",
    "segment_image",
    "fit_plane",
    "fill_planes",
]

PLANE_FILL_CONFIDENCE = 0.03
"""Confidence of depth completed from a segment's plane (:func:`fill_planes`); the floor fill uses
0.02 and the plane sweep keeps only >= 0.05, so the three are told apart."""


@dataclass(frozen=True)
class PlaneFillConfig:
    """Settings of :func:`fill_planes`."""

    segment_sigma: float = 0.5
    """Gaussian smoothing (pixels) before graph segmentation (Felzenszwalb, OpenCV ximgproc)."""
    segment_k: float = 300.0
    """Graph segmentation scale: larger gives larger segments."""
    segment_min_size: int = 100
    """Smallest segment in pixels; smaller ones merge into a neighbour."""
    min_confidence: float = 0.05
    """Pixels at or above this confidence are the planes' support (the sweep's kept pixels)."""
    min_support: int = 30
    """Confident pixels a segment needs before a plane is fitted."""
    min_support_extent: float = 0.3
    """The support must span this share of the segment's box in at least one image axis and a
    tenth of it in the other (a cluster in one corner does not fix a plane far from it)."""
    inlier_tolerance: float = 0.03
    """A support point is on the plane when its distance to it is within this share of its depth."""
    min_support_spread: float = 0.3
    """The plane's inliers must spread in two directions: the second singular value of the centred
    inlier points at least this share of the first. Support along one line (a ceiling seen only
    at its edge with one wall) fits every plane through that line."""
    interpolate_only: bool = True
    """Fill only empty pixels inside the convex hull (in the image) of the plane's inliers: a segment
    may hold a second, unmatched surface beside the matched one (the far side of a doorway in the
    same colour), and extrapolating a plane beyond its support is where it goes wrong."""
    min_inlier_fraction: float = 0.7
    """Share of the support on the plane for the segment to be filled (a segment spanning two
    surfaces, e.g. a wall and a door of the same colour seen at an angle, is refused)."""
    min_ray_angle_deg: float = 10.0
    """Rays closer than this to the plane (grazing) are not filled: their depth is ill-conditioned."""
    max_depth_ratio: float = 1.5
    """Filled depth stays within [min / ratio, max x ratio] of the view's confident depths."""
    ransac_iterations: int = 64
    """Minimal samples drawn per segment (seeded by view and segment: deterministic)."""
    free_space_margin: float = 0.05
    """Visibility check: a filled point seen by another view in front of that view's confident depth
    by more than this share of it lies in space that view sees as empty (a wrong plane)."""
    max_free_space_violations: float = 0.1
    """A segment's fill is dropped when more than this share of its checked points violate free
    space in some other view (a wrong plane is wrong over the whole segment)."""
    free_space_stride: int = 2
    """Check every n-th filled pixel per row and column (speed)."""
    cross_view_support: bool = True
    """Other views' confident depth, projected into a view (nearest surface per pixel) where the view
    itself has none, joins the planes' support: a wall plain in one view is often matched in another."""
    neighbour_views: int = 12
    """Only the views with the nearest camera centres lend support and check free space (cost)."""

    def __post_init__(self) -> None:
        for name in ("segment_sigma", "segment_k", "inlier_tolerance", "max_depth_ratio"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"PlaneFillConfig.{name} must be a positive number, got {v!r}")
        for name in ("min_support_extent", "min_inlier_fraction", "min_confidence", "min_support_spread"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 1):
                raise ValueError(f"PlaneFillConfig.{name} must lie in [0, 1], got {v!r}")
        if not (0 <= self.min_ray_angle_deg < 90):
            raise ValueError(
                f"PlaneFillConfig.min_ray_angle_deg must lie in [0, 90), got {self.min_ray_angle_deg!r}"
            )
        if not (math.isfinite(self.free_space_margin) and self.free_space_margin >= 0):
            raise ValueError(
                f"PlaneFillConfig.free_space_margin must be >= 0, got {self.free_space_margin!r}"
            )
        if not (0 <= self.max_free_space_violations <= 1) or self.free_space_stride < 1:
            raise ValueError(
                "PlaneFillConfig: need max_free_space_violations in [0, 1] and free_space_stride >= 1"
            )
        if self.neighbour_views < 1:
            raise ValueError(f"PlaneFillConfig.neighbour_views must be >= 1, got {self.neighbour_views!r}")
        if self.min_support < 3 or self.segment_min_size < 1 or self.ransac_iterations < 1:
            raise ValueError(
                "PlaneFillConfig: need min_support >= 3, segment_min_size >= 1, ransac_iterations >= 1"
            )

    @classmethod
    def from_kwargs(cls, **kw) -> PlaneFillConfig:
        """Build from keyword arguments; an unknown name is an error that lists the known ones."""
        return options_from_kwargs(cls, kw, "plane-fill")


def segment_image(image: np.ndarray, config: PlaneFillConfig | None = None) -> np.ndarray:
    """(H, W) int32 segment ids of an (H, W, 3) uint8 image (graph segmentation on colour)."""
    import cv2

    cfg = config or PlaneFillConfig()
    seg = cv2.ximgproc.segmentation.createGraphSegmentation(
        cfg.segment_sigma, cfg.segment_k, cfg.segment_min_size
    )
    return seg.processImage(np.ascontiguousarray(image[..., ::-1])).astype(np.int32)


def _plane_of(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Plane ``n . x = d`` (unit n) through three points, None when they are (nearly) collinear."""
    n = np.cross(p[1] - p[0], p[2] - p[0])
    norm = float(np.linalg.norm(n))
    scale = float(np.linalg.norm(p[1] - p[0]) * np.linalg.norm(p[2] - p[0]))
    if not norm > 1e-9 * max(scale, 1e-300):
        return None
    n = n / norm
    return n, float(n @ p[0])


def fit_plane(
    points: np.ndarray, tolerance: float, rng: np.random.Generator, iterations: int = 64
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC plane through camera-frame points (M, 3) -> (unit normal n, offset d, inlier mask),
    ``n . x = d``; a point is an inlier when its distance is within ``tolerance`` x its z-depth. The
    best sample's inliers are refitted by least squares (smallest singular vector). None when no
    sample defines a plane."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 3 or not np.isfinite(pts).all():
        return None
    tol = tolerance * np.abs(pts[:, 2])
    best, best_count = None, -1
    for _ in range(iterations):
        plane = _plane_of(pts[rng.choice(len(pts), 3, replace=False)])
        if plane is None:
            continue
        n, d = plane
        count = int((np.abs(pts @ n - d) <= tol).sum())
        if count > best_count:
            best, best_count = plane, count
    if best is None:
        return None
    n, d = best
    inl = np.abs(pts @ n - d) <= tol
    if inl.sum() >= 3:
        q = pts[inl]
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        n2 = vt[-1]
        if n2 @ n < 0:
            n2 = -n2
        d2 = float(n2 @ c)
        inl2 = np.abs(pts @ n2 - d2) <= tol
        if inl2.sum() >= inl.sum():
            n, d, inl = n2, d2, inl2
    return n, d, inl


def fill_planes(
    views: list[PinholeView],
    estimates: list[DepthEstimate],
    config: PlaneFillConfig | None = None,
    *,
    confidence: float = PLANE_FILL_CONFIDENCE,
) -> tuple[list[DepthEstimate], dict]:
    """Complete each view's empty pixels from the plane of their colour segment's confident depth.

    Returns the new estimates and statistics (``pixels`` filled, ``segments`` filled, and the
    segments refused per reason). Pixels that already have depth are never changed.
    """
    cfg = config or PlaneFillConfig()
    if len(views) != len(estimates):
        raise ValueError(f"fill_planes: {len(views)} views but {len(estimates)} depth estimates")
    cos_min = math.sin(math.radians(cfg.min_ray_angle_deg))  # |n . ray| / |ray| >= sin(angle)
    stats = {
        "pixels": 0,
        "segments": 0,
        "few_support": 0,
        "narrow_support": 0,
        "not_planar": 0,
        "line_support": 0,
        "outside_support": 0,
        "free_space": 0,
    }
    # Pass 1: per view, candidate fills (flat pixel indices, depths) per segment.
    confident = [_confident_depth(e, cfg) for e in estimates]
    projected: list[np.ndarray | None] = [None] * len(views)
    centres = (
        np.stack([np.asarray(v.cam_to_world, dtype=np.float64)[:3, 3] for v in views]) if views else None
    )
    near = [_neighbours(i, views, centres, cfg.neighbour_views) for i in range(len(views))]
    candidates: list[list[tuple[np.ndarray, np.ndarray]]] = []
    for i, (view, est) in enumerate(zip(views, estimates, strict=True)):
        support = confident[i]
        projected[i] = _projected_depth(i, views, confident, near[i])
        if cfg.cross_view_support:
            support = np.where(support > 0, support, projected[i])
        candidates.append(_segment_fills(i, view, est, support, cfg, cos_min, stats))
    # Pass 2: drop segments whose plane puts points where other views see empty space.
    out = []
    for i, est in enumerate(estimates):
        depth = np.asarray(est.depth, dtype=np.float32).copy()
        conf = np.asarray(est.confidence, dtype=np.float32).copy()
        for idx, z in candidates[i]:
            if _violates_free_space(i, views, confident, near[i], idx, z, cfg, projected[i]):
                stats["free_space"] += 1
                continue
            depth.ravel()[idx] = z.astype(np.float32)
            conf.ravel()[idx] = np.float32(confidence)
            stats["pixels"] += len(idx)
            stats["segments"] += 1
        out.append(est if not candidates[i] else DepthEstimate(depth=depth, confidence=conf))
    return out, stats


def _neighbours(i: int, views: list[PinholeView], centres: np.ndarray, k: int) -> list[int]:
    """The ``k`` views with camera centres nearest view ``i``'s whose fields of view can overlap it.
    Cube faces of one panorama share a centre and split the sphere: they never see the same point,
    so they are skipped rather than taking the places of views that can."""
    dist = np.linalg.norm(centres - centres[i], axis=1)
    out = []
    for j in np.argsort(dist, kind="stable"):
        j = int(j)
        if j == i:
            continue
        if dist[j] <= 1e-9 * max(float(dist.max()), 1e-300) and _disjoint_fields(views[i], views[j]):
            continue
        out.append(j)
        if len(out) == k:
            break
    return out


def _disjoint_fields(a: PinholeView, b: PinholeView) -> bool:
    """Whether two views at one centre see disjoint directions: no ray through a 9 x 9 grid of ``b``'s
    pixel centres (its borders included) lands inside ``a``'s image. Adjacent cube faces touch only
    along an edge, which lands on the border of the other face, not inside it."""
    hb, wb = b.image.shape[:2]
    Kb = np.asarray(b.K, dtype=np.float64)
    u = np.linspace(0.5, wb - 0.5, 9)
    v = np.linspace(0.5, hb - 0.5, 9)
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - Kb[0, 2]) / Kb[0, 0], (vv - Kb[1, 2]) / Kb[1, 1], np.ones_like(uu)], -1).reshape(
        -1, 3
    )
    Ra = np.asarray(a.cam_to_world, dtype=np.float64)[:3, :3]
    Rb = np.asarray(b.cam_to_world, dtype=np.float64)[:3, :3]
    d = rays @ (Ra.T @ Rb).T  # b's rays in a's camera frame
    ha, wa = a.image.shape[:2]
    Ka = np.asarray(a.K, dtype=np.float64)
    front = d[:, 2] > 1e-9
    if not front.any():
        return True
    pu = Ka[0, 0] * d[front, 0] / d[front, 2] + Ka[0, 2]
    pv = Ka[1, 1] * d[front, 1] / d[front, 2] + Ka[1, 2]
    margin = 1.0  # pixels: rays on the shared edge fall on the border, not inside
    inside = (pu > margin) & (pu < wa - margin) & (pv > margin) & (pv < ha - margin)
    return not inside.any()


def _confident_depth(est: DepthEstimate, cfg: PlaneFillConfig) -> np.ndarray:
    depth = np.asarray(est.depth, dtype=np.float32)
    ok = np.isfinite(depth) & (depth > 0) & (np.asarray(est.confidence) >= cfg.min_confidence)
    return np.where(ok, depth, 0.0).astype(np.float32)


def _pixel_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(H, W, 3) rays K^-1 [u, v, 1] at pixel centres (z = 1)."""
    u = (np.arange(w) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(h) + 0.5 - K[1, 2]) / K[1, 1]
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), axis=-1)


def _projected_depth(
    i: int, views: list[PinholeView], confident: list[np.ndarray], others: list[int], stride: int = 2
) -> np.ndarray:
    """View ``i``'s z-depth of the ``others``' confident pixels (every ``stride``-th), nearest per pixel."""
    h, w = confident[i].shape
    inv = np.linalg.inv(np.asarray(views[i].cam_to_world, dtype=np.float64))
    K = np.asarray(views[i].K, dtype=np.float64)
    zbuf = np.full(h * w, np.inf)
    for j in others:
        other = views[j]
        d = confident[j][::stride, ::stride].astype(np.float64)
        r, c = np.nonzero(d > 0)
        if not len(r):
            continue
        z = d[r, c]
        Kj = np.asarray(other.K, dtype=np.float64)
        cam = np.stack(
            [(c * stride + 0.5 - Kj[0, 2]) / Kj[0, 0] * z, (r * stride + 0.5 - Kj[1, 2]) / Kj[1, 1] * z, z],
            axis=1,
        )
        T = np.asarray(other.cam_to_world, dtype=np.float64)
        p = (cam @ T[:3, :3].T + T[:3, 3]) @ inv[:3, :3].T + inv[:3, 3]
        front = p[:, 2] > 1e-6
        p = p[front]
        u = np.floor(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        np.minimum.at(zbuf, v[inside] * w + u[inside], p[inside, 2])
    return np.where(np.isfinite(zbuf), zbuf, 0.0).reshape(h, w).astype(np.float32)


def _segment_fills(
    i: int,
    view: PinholeView,
    est: DepthEstimate,
    support: np.ndarray,
    cfg: PlaneFillConfig,
    cos_min: float,
    stats: dict,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Candidate fills of one view: per accepted segment (flat indices of its empty pixels, depths).
    ``support``: z-depth the planes are fitted to (0 = none)."""
    depth = np.asarray(est.depth, dtype=np.float32)
    h, w = depth.shape
    good = support > 0
    empty = ~(np.isfinite(depth) & (depth > 0))
    if good.sum() < cfg.min_support or not empty.any():
        return []
    lo = float(support[good].min()) / cfg.max_depth_ratio
    hi = float(support[good].max()) * cfg.max_depth_ratio
    rays = _pixel_rays(np.asarray(view.K, dtype=np.float64), h, w).reshape(-1, 3)
    labels = segment_image(np.asarray(view.image), cfg).ravel()
    flat_depth, flat_good, flat_empty = support.ravel(), good.ravel(), empty.ravel()
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    fills = []
    for seg_pixels in np.split(order, bounds):
        if not flat_empty[seg_pixels].any():
            continue
        sup = seg_pixels[flat_good[seg_pixels]]
        if len(sup) < cfg.min_support:
            stats["few_support"] += 1
            continue
        rows, cols = np.divmod(seg_pixels, w)
        srows, scols = np.divmod(sup, w)
        ext = sorted(((np.ptp(srows) + 1) / (np.ptp(rows) + 1), (np.ptp(scols) + 1) / (np.ptp(cols) + 1)))
        if ext[1] < cfg.min_support_extent or ext[0] < 0.1 * cfg.min_support_extent:
            stats["narrow_support"] += 1
            continue
        pts = rays[sup] * flat_depth[sup, None]
        rng = np.random.default_rng([i, int(labels[seg_pixels[0]])])
        fit = fit_plane(pts, cfg.inlier_tolerance, rng, cfg.ransac_iterations)
        if fit is None or fit[2].mean() < cfg.min_inlier_fraction:
            stats["not_planar"] += 1
            continue
        n, d, inliers = fit
        q = pts[inliers] - pts[inliers].mean(axis=0)
        sv = np.linalg.svd(q, compute_uv=False)
        if not sv[1] >= cfg.min_support_spread * sv[0]:
            stats["line_support"] += 1
            continue
        holes = seg_pixels[flat_empty[seg_pixels]]
        if cfg.interpolate_only:
            holes = holes[_inside_hull(sup[inliers], holes, w)]
            if not len(holes):
                stats["outside_support"] += 1
                continue
        r = rays[holes]
        denom = r @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            z = d / denom
        ok = np.isfinite(z) & (np.abs(denom) >= cos_min * np.linalg.norm(r, axis=1)) & (z >= lo) & (z <= hi)
        if ok.any():
            fills.append((holes[ok], z[ok]))
    return fills


def _inside_hull(support: np.ndarray, pixels: np.ndarray, width: int) -> np.ndarray:
    """Which ``pixels`` (flat indices) lie in the image-plane convex hull of the ``support`` pixels."""
    from scipy.spatial import ConvexHull, Delaunay, QhullError

    sr, sc = np.divmod(support, width)
    pts = np.column_stack([sc, sr]).astype(np.float64)
    try:
        hull = pts[ConvexHull(pts).vertices]
        tri = Delaunay(hull)
    except (QhullError, ValueError):  # collinear support: no area to interpolate in
        return np.zeros(len(pixels), dtype=bool)
    pr, pc = np.divmod(pixels, width)
    return tri.find_simplex(np.column_stack([pc, pr]).astype(np.float64), tol=0.5) >= 0


def _violates_free_space(
    i: int,
    views: list[PinholeView],
    confident: list[np.ndarray],
    others: list[int],
    idx: np.ndarray,
    z: np.ndarray,
    cfg: PlaneFillConfig,
    projected: np.ndarray,
) -> bool:
    """Whether more than ``max_free_space_violations`` of a segment's filled points (view ``i``'s flat
    pixel indices ``idx`` at z-depths ``z``) contradict what the ``others`` see confidently: a point in
    front of another view's depth lies in space that view sees empty, and a point behind another
    view's confident surface (``projected`` into view ``i``) would be hidden by it."""
    h, w = confident[i].shape
    rows, cols = np.divmod(idx, w)
    keep = (rows % cfg.free_space_stride == 0) & (cols % cfg.free_space_stride == 0)
    if not keep.any():
        keep[:] = True
    rows, cols, z = rows[keep], cols[keep], z[keep].astype(np.float64)
    seen_here = projected[rows, cols].astype(np.float64)
    hidden = (seen_here > 0) & (seen_here < z * (1.0 - cfg.free_space_margin))
    K = np.asarray(views[i].K, dtype=np.float64)
    cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0] * z, (rows + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
    T = np.asarray(views[i].cam_to_world, dtype=np.float64)
    world = cam @ T[:3, :3].T + T[:3, 3]
    violated = hidden.copy()
    for j in others:
        other = views[j]
        inv = np.linalg.inv(np.asarray(other.cam_to_world, dtype=np.float64))
        p = world @ inv[:3, :3].T + inv[:3, 3]
        front = p[:, 2] > 1e-6
        if not front.any():
            continue
        Kj = np.asarray(other.K, dtype=np.float64)
        hj, wj = confident[j].shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.floor(Kj[0, 0] * p[:, 0] / p[:, 2] + Kj[0, 2]).astype(np.int64, copy=False)
            v = np.floor(Kj[1, 1] * p[:, 1] / p[:, 2] + Kj[1, 2]).astype(np.int64, copy=False)
        inside = front & (u >= 0) & (u < wj) & (v >= 0) & (v < hj)
        if not inside.any():
            continue
        seen = confident[j][v[inside], u[inside]]
        bad = (seen > 0) & (p[inside, 2] < seen * (1.0 - cfg.free_space_margin))
        violated[np.flatnonzero(inside)[bad]] = True
    return bool(violated.mean() > cfg.max_free_space_violations)
