"""Plane-sweep multi-view stereo on the CPU, with no learned weights (the lifting fallback).

For every reference view the method

1. picks source views (:func:`select_sources`): the views that see enough of the reference frustum
   (``min_overlap``) from a large enough triangulation angle (``min_angle_deg``), best first by
   overlap times how close the angle comes to ``target_angle_deg``;
2. sweeps fronto-parallel planes, uniform in inverse depth between a near and a far depth taken from
   the view's sparse SfM depths (percentiles, widened by ``range_margin``) or given;
3. warps each source image onto the reference by the plane's homography, ``q = A p + b / d`` with
   ``A = K_s R K_r^-1`` and ``b = K_s t`` (bilinear, border padding), and scores every pixel by the
   zero-mean normalised cross-correlation (ZNCC) of a ``window`` x ``window`` patch, as cost ``1 - ZNCC``;
4. aggregates the sources robustly: the mean of the ``best_k`` lowest costs (an occluded source
   cannot veto a plane; ``docs/lift.md`` has the measurement against the plain mean);
5. takes the lowest-cost plane (winner-take-all), refined by a parabola through its neighbours;
6. gives each pixel a confidence: the best ZNCC times the distinctiveness of the minimum
   (``(c2 - c1) / c2`` with ``c2`` the best cost more than two planes away), zero where the reference
   patch has no texture (grey std below ``min_texture``), the ZNCC is below ``min_ncc``, or the minimum
   lies on the first or last plane;
7. filters by cross-view geometric consistency (:func:`geometric_consistency`): a pixel is kept when
   its depth, carried into a neighbour and back through the neighbour's depth, lands within
   ``geo_max_reproj_px`` pixels and ``geo_tolerance`` relative depth in at least ``geo_min_views``
   neighbours. Rejected pixels get depth 0 and confidence 0.

Images are converted to grey (Rec. 601 luma, [0, 1]). Everything is float32 torch on the CPU; the cost
volume is built in chunks of planes whose size follows ``max_chunk_mb``. ``*_reference`` functions
are slow per-pixel loops that define the same numbers; the tests hold the fast paths to them.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from image2sim.simulator.io.resample import sample_bilinear
from image2sim.simulator.lift.types import DepthEstimate, PinholeView, SparseDepth, options_from_kwargs

__all__ = [
    "MVSConfig",
    "validate_views",
    "validate_sparse",
    "to_gray",
    "depth_range",
    "inverse_depth_planes",
    "select_sources",
    "plane_sweep_cost",
    "plane_sweep_cost_reference",
    "winner_take_all",
    "winner_take_all_reference",
    "geometric_consistency",
    "geometric_consistency_reference",
    "run_mvs",
]

log = logging.getLogger(__name__)

LUMA = (0.299, 0.587, 0.114)
"""Rec. 601 weights of the grey image the photometric cost compares."""
_EPS_VAR = 1e-6
"""Variance floor in the ZNCC denominator (grey levels in [0, 1]; a std of 1e-3)."""
_INVALID = float("inf")
"""Per-source cost where the plane point falls outside the source image or behind it."""
MAX_COST = 2.0
"""Cost of a pixel/plane that no source sees (1 - ZNCC lies in [0, 2])."""


@dataclass
class MVSConfig:
    """Settings of the plane-sweep stereo (``estimate_depth(source="mvs", **fields)``)."""

    num_planes: int = 64
    """Fronto-parallel depth planes, uniform in inverse depth."""
    num_sources: int = 4
    """Source views compared with each reference view (at most)."""
    best_k: int = 2
    """Per pixel and plane, the mean of this many lowest source costs is the plane's cost."""
    window: int = 9
    """Side of the square ZNCC window, pixels (odd)."""
    min_texture: float = 0.01
    """Reference patches whose grey std (in [0, 1]) is below this get confidence 0 (textureless)."""
    min_ncc: float = 0.5
    """Pixels whose best aggregated ZNCC is below this get confidence 0."""
    min_confidence: float = 0.05
    """Pixels whose confidence (ZNCC x distinctiveness) is below this get confidence 0: an ambiguous
    minimum, e.g. along stripes parallel to the baseline."""
    near: float | None = None
    """Nearest plane depth; None: from the sparse depths (``depth_percentiles``, ``range_margin``)."""
    far: float | None = None
    """Farthest plane depth; None: from the sparse depths."""
    depth_percentiles: tuple[float, float] = (2.0, 98.0)
    """Percentiles of the view's sparse depths that set the sweep range."""
    range_margin: float = 0.3
    """The sparse range is widened to [near / (1 + m), far * (1 + m)]."""
    min_sparse_points: int = 20
    """A view with fewer sparse depths takes its range from all views' sparse depths."""
    min_overlap: float = 0.3
    """A source must see at least this fraction of the reference frustum (at its middle depth)."""
    min_angle_deg: float = 1.0
    """A source's triangulation angle at the reference's middle depth must reach this (degrees)."""
    target_angle_deg: float = 8.0
    """Angles up to this count as better; beyond it overlap alone ranks sources."""
    geo_tolerance: float = 0.02
    """Cross-view check: relative depth difference allowed after the round trip."""
    geo_max_reproj_px: float = 1.0
    """Cross-view check: reprojection distance allowed after the round trip, pixels."""
    geo_min_views: int = 1
    """Cross-view check: neighbours that must agree for a pixel to be kept (0 disables the check)."""
    max_chunk_mb: float = 256.0
    """Memory for one chunk of the cost volume's intermediate tensors, MiB."""

    def __post_init__(self) -> None:
        positive_ints = ("num_planes", "num_sources", "best_k", "window", "min_sparse_points")
        for name in positive_ints:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"MVSConfig.{name} must be a positive integer, got {value!r}")
        if self.num_planes < 3:
            raise ValueError(f"MVSConfig.num_planes must be at least 3, got {self.num_planes}")
        if self.window % 2 != 1:
            raise ValueError(f"MVSConfig.window must be odd, got {self.window}")
        if (
            isinstance(self.geo_min_views, bool)
            or not isinstance(self.geo_min_views, int)
            or self.geo_min_views < 0
        ):
            raise ValueError(f"MVSConfig.geo_min_views must be an integer >= 0, got {self.geo_min_views!r}")
        for name in (
            "min_texture",
            "min_ncc",
            "min_confidence",
            "range_margin",
            "min_overlap",
            "min_angle_deg",
        ):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"MVSConfig.{name} must be finite and >= 0, got {value}")
        for name in ("target_angle_deg", "geo_tolerance", "geo_max_reproj_px", "max_chunk_mb"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value <= 0:
                raise ValueError(f"MVSConfig.{name} must be finite and > 0, got {value}")
        lo, hi = self.depth_percentiles
        if not 0 <= lo < hi <= 100:
            raise ValueError(
                f"MVSConfig.depth_percentiles must satisfy 0 <= lo < hi <= 100, got {self.depth_percentiles}"
            )
        for name in ("near", "far"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(float(value)) and float(value) > 0):
                raise ValueError(f"MVSConfig.{name} must be a finite positive depth, got {value}")
        if (self.near is None) != (self.far is None):
            raise ValueError("MVSConfig.near and MVSConfig.far are given together or not at all")
        if self.near is not None and not self.near < self.far:
            raise ValueError(f"MVSConfig.near ({self.near}) must be below MVSConfig.far ({self.far})")

    @classmethod
    def from_kwargs(cls, **kw) -> MVSConfig:
        """Build from keyword arguments; an unknown name is an error that lists the known ones."""
        return options_from_kwargs(cls, kw, "multi-view stereo")


# ---------------------------------------------------------------------------------------------- inputs


def validate_views(views: list[PinholeView]) -> None:
    """Raise ``ValueError`` naming the view and field of the first malformed view."""
    if not isinstance(views, (list, tuple)) or not views:
        raise ValueError("depth estimation needs a non-empty list of PinholeView")
    for i, view in enumerate(views):
        if not isinstance(view, PinholeView):
            raise ValueError(f"view {i}: expected a PinholeView, got {type(view).__name__}")
        image = np.asarray(view.image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"view {i}: image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
        if image.shape[0] < 2 or image.shape[1] < 2:
            raise ValueError(f"view {i}: image of {image.shape[1]}x{image.shape[0]} pixels is too small")
        K = np.asarray(view.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(
                f"view {i}: K must be a finite 3x3 matrix, got shape {K.shape} with {K.tolist()}"
            )
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0):
            raise ValueError(
                f"view {i}: K must be a pinhole intrinsic [[fx,s,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}"
            )
        T = np.asarray(view.cam_to_world, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"view {i}: cam_to_world must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R.T @ R, np.eye(3), atol=1e-4):
            raise ValueError(f"view {i}: cam_to_world must be a rigid transform (orthonormal rotation)")


def validate_sparse(sparse: list[SparseDepth] | None, views: list[PinholeView]) -> list[SparseDepth] | None:
    """Sparse depths per view with non-finite, non-positive or off-image points dropped (logged).

    A list of the wrong length or malformed arrays is an error; a bad point is not (SfM tracks can be).
    """
    if sparse is None:
        return None
    if len(sparse) != len(views):
        raise ValueError(f"sparse depths: got {len(sparse)} entries for {len(views)} views")
    out = []
    for i, (sp, view) in enumerate(zip(sparse, views, strict=True)):
        if sp is None:
            out.append(SparseDepth(np.zeros((0, 2)), np.zeros(0)))
            continue
        if not isinstance(sp, SparseDepth):
            raise ValueError(f"sparse depths of view {i}: expected a SparseDepth, got {type(sp).__name__}")
        uv = np.asarray(sp.uv, dtype=np.float64).reshape(-1, 2) if np.size(sp.uv) else np.zeros((0, 2))
        depth = np.asarray(sp.depth, dtype=np.float64).reshape(-1)
        if uv.shape[0] != depth.shape[0]:
            raise ValueError(f"sparse depths of view {i}: {uv.shape[0]} pixels but {depth.shape[0]} depths")
        h, w = view.image.shape[:2]
        ok = np.all(np.isfinite(uv), axis=1) & np.isfinite(depth) & (depth > 0)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
        if not ok.all():
            log.warning("sparse depths of view %d: dropped %d of %d bad points", i, int((~ok).sum()), ok.size)
        out.append(SparseDepth(uv[ok], depth[ok]))
    return out


def to_gray(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (H, W) float32 grey in [0, 1] (Rec. 601 luma)."""
    rgb = torch.from_numpy(np.ascontiguousarray(image)).to(torch.float32) / 255.0
    return rgb @ torch.tensor(LUMA, dtype=torch.float32)


def depth_range(sparse_depth: np.ndarray, all_depths: np.ndarray, config: MVSConfig) -> tuple[float, float]:
    """(near, far) of a view's sweep: the config's, else its sparse depths' percentiles, widened."""
    if config.near is not None:
        return float(config.near), float(config.far)
    d = sparse_depth if sparse_depth.size >= config.min_sparse_points else all_depths
    if d.size < 2:
        raise ValueError(
            "multi-view stereo needs a depth range: give sparse SfM depths (at least "
            f"{config.min_sparse_points} points in some view) or near= and far="
        )
    lo, hi = np.percentile(d, config.depth_percentiles)
    near = float(lo) / (1.0 + config.range_margin)
    far = float(hi) * (1.0 + config.range_margin)
    if not far > near:
        far = near * 2.0
    return near, far


def inverse_depth_planes(near: float, far: float, num: int) -> torch.Tensor:
    """(num,) float64 inverse depths, uniform from 1/near (plane 0) to 1/far (plane num-1)."""
    return torch.linspace(1.0 / near, 1.0 / far, num, dtype=torch.float64)


def _relative_pose(ref: PinholeView, src: PinholeView) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) taking reference-camera points to source-camera points."""
    T = np.linalg.inv(np.asarray(src.cam_to_world, np.float64)) @ np.asarray(ref.cam_to_world, np.float64)
    return T[:3, :3], T[:3, 3]


def select_sources(views: list[PinholeView], index: int, middle_depth: float, config: MVSConfig) -> list[int]:
    """Source views of view ``index``: enough overlap and angle, best ``config.num_sources`` first.

    Overlap is the fraction of a 9 x 7 grid of reference pixels, placed at ``middle_depth``, that
    lands inside the source image in front of it; the angle is the triangulation angle at the
    reference's central point at that depth.
    """
    ref = views[index]
    h, w = ref.image.shape[:2]
    us, vs = np.meshgrid(np.linspace(0.5, w - 0.5, 9), np.linspace(0.5, h - 0.5, 7))
    pix = np.stack([us.ravel(), vs.ravel(), np.ones(us.size)])
    rays = np.linalg.solve(np.asarray(ref.K, np.float64), pix)
    points = rays * (middle_depth / rays[2])
    centre_ref = np.array([0.0, 0.0, middle_depth])
    scored = []
    for j, src in enumerate(views):
        if j == index:
            continue
        R, t = _relative_pose(ref, src)
        q = np.asarray(src.K, np.float64) @ (R @ points + t[:, None])
        hs, ws = src.image.shape[:2]
        front = q[2] > 1e-9
        u = np.where(front, q[0] / np.where(front, q[2], 1.0), -1.0)
        v = np.where(front, q[1] / np.where(front, q[2], 1.0), -1.0)
        overlap = float(np.mean(front & (u >= 0) & (u <= ws) & (v >= 0) & (v <= hs)))
        # Source centre in the reference frame: -R^T t.
        c_src = -R.T @ t
        a, b = centre_ref, centre_ref - c_src
        cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))
        angle = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
        if overlap >= config.min_overlap and angle >= config.min_angle_deg:
            scored.append((overlap * min(angle / config.target_angle_deg, 1.0), j))
    scored.sort(key=lambda s: (-s[0], s[1]))
    return [j for _, j in scored[: config.num_sources]]


# ----------------------------------------------------------------------------------------- plane sweep


def _pixel_centres(h: int, w: int) -> torch.Tensor:
    """(3, H*W) float64 homogeneous pixel centres ``(u, v, 1)``, row-major."""
    vv, uu = torch.meshgrid(
        torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5, indexing="ij"
    )
    return torch.stack((uu.reshape(-1), vv.reshape(-1), torch.ones(h * w, dtype=torch.float64)))


def _box_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window`` x ``window`` box of (N, H, W) maps, replicating the border."""
    r = window // 2
    padded = F.pad(x.unsqueeze(1), (r, r, r, r), mode="replicate")
    return F.avg_pool2d(padded, window, stride=1).squeeze(1)


def _homography_terms(ref: PinholeView, src: PinholeView) -> tuple[torch.Tensor, torch.Tensor]:
    """``A = K_s R K_r^-1`` (3, 3) and ``b = K_s t`` (3,), float64: source pixel ~ A p + b / depth."""
    R, t = _relative_pose(ref, src)
    Ks = np.asarray(src.K, np.float64)
    A = Ks @ R @ np.linalg.inv(np.asarray(ref.K, np.float64))
    return torch.from_numpy(A), torch.from_numpy(Ks @ t)


def _chunk_planes(num_planes: int, num_sources: int, height: int, width: int, max_mb: float) -> int:
    # Per plane and source: grid (2) + sample + 3 window means + products (~4): ~10 float32 maps.
    per_plane = num_sources * height * width * 4 * 10
    return max(1, min(num_planes, int(max_mb * 2**20 // per_plane)))


def plane_sweep_cost(
    ref_gray: torch.Tensor,
    src_grays: list[torch.Tensor],
    homographies: list[tuple[torch.Tensor, torch.Tensor]],
    inv_depths: torch.Tensor,
    *,
    window: int,
    best_k: int,
    max_chunk_mb: float = 256.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Aggregated cost volume (P, H, W) float32 and the reference patches' grey std (H, W).

    ``homographies[s] = (A, b)`` maps reference pixel centres ``p = (u, v, 1)`` to source ``s`` as
    ``A p + b * inv_depth``; ``inv_depths`` is (P,) for fronto-parallel planes or (P, H, W), a
    per-pixel inverse depth for each of P slanted planes (:func:`plane_ncc`). Per source the cost is
    ``1 - ZNCC`` of the ``window``-sized patches of the reference and of the source warped by the
    plane; a plane point outside the source image or behind it does not count. Per pixel and plane
    the cost is the mean of the ``best_k`` lowest valid source costs (fewer if fewer are valid;
    :data:`MAX_COST` if none is).
    """
    h, w = ref_gray.shape
    S, P = len(src_grays), int(inv_depths.shape[0])
    if S == 0:
        raise ValueError("plane_sweep_cost needs at least one source view")
    ref = ref_gray.to(torch.float32)[None]
    mr = _box_mean(ref, window)
    var_r = (_box_mean(ref * ref, window) - mr * mr).clamp_min(0.0)
    std_r = var_r.sqrt()[0]
    pix = _pixel_centres(h, w)
    cost = torch.empty((P, h, w), dtype=torch.float32)
    chunk = _chunk_planes(P, S, h, w, max_chunk_mb)
    for start in range(0, P, chunk):
        inv = inv_depths[start : start + chunk]
        pc = int(inv.shape[0])
        per_source = torch.full((S, pc, h, w), _INVALID, dtype=torch.float32)
        for s, (src, (A, b)) in enumerate(zip(src_grays, homographies, strict=True)):
            hs, ws = src.shape
            q = (A @ pix)[None] + b[None, :, None] * inv.reshape(pc, 1, -1)  # (pc, 3, HW)
            z = q[:, 2]
            front = z > 1e-12
            zs = torch.where(front, z, torch.ones_like(z))
            u = q[:, 0] / zs
            v = q[:, 1] / zs
            inside = front & (u >= 0) & (u <= ws) & (v >= 0) & (v <= hs)
            grid = torch.stack((2.0 * u / ws - 1.0, 2.0 * v / hs - 1.0), dim=-1).to(torch.float32)
            grid = torch.where(inside[..., None], grid, torch.zeros_like(grid)).reshape(pc, h, w, 2)
            img = src.to(torch.float32)[None, None].expand(pc, 1, hs, ws)
            warped = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[
                :, 0
            ]
            ms = _box_mean(warped, window)
            var_s = (_box_mean(warped * warped, window) - ms * ms).clamp_min(0.0)
            cov = _box_mean(warped * ref, window) - ms * mr
            ncc = cov / torch.sqrt(var_r.clamp_min(_EPS_VAR) * var_s.clamp_min(_EPS_VAR))
            c = (1.0 - ncc).clamp(0.0, MAX_COST)
            per_source[s] = torch.where(inside.reshape(pc, h, w), c, torch.full_like(c, _INVALID))
        cost[start : start + pc] = _best_k_mean(per_source, best_k)
    return cost, std_r


def plane_ncc(
    views: list[PinholeView], index: int, normal: np.ndarray, offset: float, config: MVSConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Photometric support of one world plane ``normal . x = offset`` in view ``index``.

    The plane's own homography (slanted, unlike the sweep's fronto-parallel planes, so a floor seen
    at a grazing angle warps exactly) maps the view onto its source views (:func:`select_sources` at
    the plane's median depth); returns the plane's z-depth (H, W) (0 where the ray misses it), the
    mean ZNCC of the ``config.best_k`` best sources (-1 where none sees the point) and the
    reference patches' grey std, all float32.
    """
    config = config or MVSConfig()
    view = views[index]
    h, w = view.image.shape[:2]
    R, c = np.asarray(view.cam_to_world, np.float64)[:3, :3], np.asarray(view.cam_to_world, np.float64)[:3, 3]
    n_cam = R.T @ np.asarray(normal, np.float64)
    rays = np.linalg.solve(np.asarray(view.K, np.float64), _pixel_centres(h, w).numpy())  # (3, HW), z = 1
    inv = (rays.T @ n_cam) / (float(offset) - float(normal @ c))  # 1 / z-depth of the plane
    hits = inv > 1e-12
    depth = np.where(hits, 1.0 / np.where(hits, inv, 1.0), 0.0).reshape(h, w).astype(np.float32)
    ncc = np.full((h, w), -1.0, dtype=np.float32)
    if not hits.any():
        return depth, ncc, np.zeros((h, w), dtype=np.float32)
    src = select_sources(views, index, float(np.median(depth[depth > 0])), config)
    gray = to_gray(view.image)
    if not src:
        return depth, ncc, np.zeros((h, w), dtype=np.float32)
    cost, std_r = plane_sweep_cost(
        gray,
        [to_gray(views[j].image) for j in src],
        [_homography_terms(view, views[j]) for j in src],
        torch.from_numpy(np.where(hits, inv, 0.0)).reshape(1, h, w),
        window=config.window,
        best_k=config.best_k,
        max_chunk_mb=config.max_chunk_mb,
    )
    ncc = np.where(cost[0].numpy() < MAX_COST, 1.0 - cost[0].numpy(), -1.0).astype(np.float32)
    return depth, ncc, std_r.numpy().astype(np.float32)


def _best_k_mean(per_source: torch.Tensor, best_k: int) -> torch.Tensor:
    """Mean of the ``best_k`` lowest finite values along dim 0 (fewer if fewer; MAX_COST if none)."""
    k = min(best_k, per_source.shape[0])
    low = torch.topk(per_source, k, dim=0, largest=False).values
    finite = torch.isfinite(low)
    n = finite.sum(0)
    total = torch.where(finite, low, torch.zeros_like(low)).sum(0)
    return torch.where(n > 0, total / n.clamp_min(1), torch.full_like(total, MAX_COST))


def plane_sweep_cost_reference(
    ref_gray: np.ndarray,
    src_grays: list[np.ndarray],
    homographies: list[tuple[np.ndarray, np.ndarray]],
    inv_depths: np.ndarray,
    *,
    window: int,
    best_k: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Slow per-pixel definition of :func:`plane_sweep_cost` (float64 loops; tiny images only)."""
    h, w = ref_gray.shape
    r = window // 2
    ref = np.asarray(ref_gray, np.float64)
    cost = np.zeros((len(inv_depths), h, w))
    std_r = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            # The window, with coordinates clamped to the image (border replication).
            ys = np.clip(np.arange(y - r, y + r + 1), 0, h - 1)
            xs = np.clip(np.arange(x - r, x + r + 1), 0, w - 1)
            wy, wx = np.meshgrid(ys, xs, indexing="ij")
            patch_r = ref[wy, wx].ravel()
            std_r[y, x] = patch_r.std()
            for p, inv in enumerate(inv_depths):
                costs = []
                for src, (A, b) in zip(src_grays, homographies, strict=True):
                    hs, ws = src.shape
                    centre = A @ np.array([x + 0.5, y + 0.5, 1.0]) + b * inv
                    if centre[2] <= 1e-12:
                        continue
                    cu, cv = centre[0] / centre[2], centre[1] / centre[2]
                    if not (0 <= cu <= ws and 0 <= cv <= hs):
                        continue
                    q = (
                        A @ np.stack([wx.ravel() + 0.5, wy.ravel() + 0.5, np.ones(wx.size)])
                        + b[:, None] * inv
                    )
                    qz = np.where(q[2] > 1e-12, q[2], 1.0)
                    qu, qv = q[0] / qz, q[1] / qz
                    # Window pixels whose own projection is invalid are sampled at the image centre,
                    # as the fast path does (their grid is zeroed).
                    ok = (q[2] > 1e-12) & (qu >= 0) & (qu <= ws) & (qv >= 0) & (qv <= hs)
                    qu = np.where(ok, qu, ws / 2.0)
                    qv = np.where(ok, qv, hs / 2.0)
                    patch_s = sample_bilinear(np.asarray(src, np.float64), qu, qv)
                    cov = np.mean(patch_r * patch_s) - patch_r.mean() * patch_s.mean()
                    denom = math.sqrt(max(patch_r.var(), _EPS_VAR) * max(patch_s.var(), _EPS_VAR))
                    costs.append(min(max(1.0 - cov / denom, 0.0), MAX_COST))
                best = sorted(costs)[:best_k]
                cost[p, y, x] = float(np.mean(best)) if best else MAX_COST
    return cost, std_r


# ------------------------------------------------------------------------------------ winner-take-all


def winner_take_all(
    cost: torch.Tensor,
    inv_depths: torch.Tensor,
    std_ref: torch.Tensor,
    *,
    min_texture: float,
    min_ncc: float,
    min_confidence: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (H, W) and confidence (H, W) float32 from a cost volume (P, H, W).

    The lowest plane is refined by the parabola through it and its neighbours (offset clamped to
    half a plane). Confidence = best ZNCC x ``(c2 - c1) / c2``, where ``c2`` is the lowest cost more
    than two planes from the minimum; 0 on textureless patches, ZNCC below ``min_ncc``, confidence
    below ``min_confidence``, or a minimum on the first or last plane (the surface may lie outside
    the swept range).
    """
    P = cost.shape[0]
    idx = torch.argmin(cost, dim=0)
    c1 = torch.gather(cost, 0, idx[None])[0]
    im = (idx - 1).clamp(0, P - 1)
    ip = (idx + 1).clamp(0, P - 1)
    cm = torch.gather(cost, 0, im[None])[0]
    cp = torch.gather(cost, 0, ip[None])[0]
    interior = (idx > 0) & (idx < P - 1)
    denom = cm - 2.0 * c1 + cp
    offset = torch.where(
        interior & (denom > 1e-9), 0.5 * (cm - cp) / denom.clamp_min(1e-9), torch.zeros_like(c1)
    )
    offset = offset.clamp(-0.5, 0.5)
    step = float(inv_depths[1] - inv_depths[0])
    inv = float(inv_depths[0]) + (idx.to(torch.float64) + offset.to(torch.float64)) * step
    depth = (1.0 / inv).to(torch.float32)
    planes = torch.arange(P)[:, None, None]
    far_away = (planes - idx[None]).abs() > 2
    c2 = torch.where(far_away, cost, torch.full_like(cost, float("inf"))).min(0).values
    ncc = (1.0 - c1).clamp(0.0, 1.0)
    distinct = torch.where(torch.isfinite(c2), (c2 - c1) / c2.clamp_min(1e-6), torch.ones_like(c1)).clamp(
        0.0, 1.0
    )
    conf = ncc * distinct
    bad = (std_ref < min_texture) | ((1.0 - c1) < min_ncc) | ~interior | (conf < min_confidence)
    conf = torch.where(bad, torch.zeros_like(conf), conf)
    return depth, conf.to(torch.float32)


def winner_take_all_reference(
    cost: np.ndarray,
    inv_depths: np.ndarray,
    std_ref: np.ndarray,
    *,
    min_texture: float,
    min_ncc: float,
    min_confidence: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Slow per-pixel definition of :func:`winner_take_all`."""
    P, h, w = cost.shape
    depth = np.zeros((h, w))
    conf = np.zeros((h, w))
    step = inv_depths[1] - inv_depths[0]
    for y in range(h):
        for x in range(w):
            c = cost[:, y, x]
            i = int(np.argmin(c))
            offset = 0.0
            if 0 < i < P - 1:
                denom = c[i - 1] - 2 * c[i] + c[i + 1]
                if denom > 1e-9:
                    offset = min(max(0.5 * (c[i - 1] - c[i + 1]) / denom, -0.5), 0.5)
            depth[y, x] = 1.0 / (inv_depths[0] + (i + offset) * step)
            others = [c[j] for j in range(P) if abs(j - i) > 2]
            c2 = min(others) if others else math.inf
            distinct = 1.0 if not math.isfinite(c2) else min(max((c2 - c[i]) / max(c2, 1e-6), 0.0), 1.0)
            value = min(max(1.0 - c[i], 0.0), 1.0) * distinct
            ok = std_ref[y, x] >= min_texture and 1.0 - c[i] >= min_ncc and 0 < i < P - 1
            conf[y, x] = value if ok and value >= min_confidence else 0.0
    return depth, conf


# ------------------------------------------------------------------------------- geometric consistency


def _pixel_points(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(H, W) z-depth -> (3, H*W) camera-frame points (float64)."""
    h, w = depth.shape
    return torch.linalg.solve(K, _pixel_centres(h, w)) * depth.reshape(1, -1).to(torch.float64)


def _project(points: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    z = points[2]
    zs = torch.where(z > 1e-12, z, torch.ones_like(z))
    q = K @ points
    return q[0] / zs, q[1] / zs, z


def geometric_consistency(
    depths: list[torch.Tensor],
    Ks: list[torch.Tensor],
    poses: list[torch.Tensor],
    neighbours: list[list[int]],
    *,
    tolerance: float,
    max_reproj_px: float,
) -> list[torch.Tensor]:
    """Per view, the number (H, W) int of neighbours whose depth agrees with the view's depth.

    Depth 0 is invalid. A pixel with depth d goes to world, into neighbour j (its nearest pixel, which
    must hold a valid depth), back to world with j's depth there and into the view again: it agrees
    with j when it lands within ``max_reproj_px`` of where it started and its depth is within
    ``tolerance`` (relative) of d. ``poses`` are camera-to-world (4, 4) float64.
    """
    counts = []
    for i, depth in enumerate(depths):
        h, w = depth.shape
        valid = depth.reshape(-1) > 0
        p_i = _pixel_points(depth, Ks[i])
        world = poses[i][:3, :3] @ p_i + poses[i][:3, 3:4]
        uu, vv, _ = _pixel_centres(h, w)
        count = torch.zeros(h * w, dtype=torch.int32)
        inv_i = torch.linalg.inv(poses[i])
        for j in neighbours[i]:
            dj = depths[j]
            hj, wj = dj.shape
            inv_j = torch.linalg.inv(poses[j])
            p_j = inv_j[:3, :3] @ world + inv_j[:3, 3:4]
            u, v, z = _project(p_j, Ks[j])
            col = torch.floor(u).to(torch.int64)
            row = torch.floor(v).to(torch.int64)
            inside = (z > 1e-12) & (col >= 0) & (col < wj) & (row >= 0) & (row < hj) & valid
            col_c, row_c = col.clamp(0, wj - 1), row.clamp(0, hj - 1)
            d_back = dj[row_c, col_c].to(torch.float64)
            inside &= d_back > 0
            # j's surface point at that pixel (its centre), back into view i.
            pix_j = torch.stack((col_c + 0.5, row_c + 0.5, torch.ones_like(u)))
            q_j = torch.linalg.solve(Ks[j], pix_j) * d_back
            world_j = poses[j][:3, :3] @ q_j + poses[j][:3, 3:4]
            back = inv_i[:3, :3] @ world_j + inv_i[:3, 3:4]
            u2, v2, z2 = _project(back, Ks[i])
            reproj = torch.hypot(u2 - uu, v2 - vv)
            d_i = depth.reshape(-1).to(torch.float64)
            rel = (z2 - d_i).abs() / d_i.clamp_min(1e-12)
            count += (inside & (reproj <= max_reproj_px) & (rel <= tolerance)).to(torch.int32)
        counts.append(count.reshape(h, w))
    return counts


def geometric_consistency_reference(
    depths: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    neighbours: list[list[int]],
    *,
    tolerance: float,
    max_reproj_px: float,
) -> list[np.ndarray]:
    """Slow per-pixel definition of :func:`geometric_consistency`."""
    counts = []
    for i, depth in enumerate(depths):
        h, w = depth.shape
        count = np.zeros((h, w), dtype=np.int32)
        for y in range(h):
            for x in range(w):
                d = depth[y, x]
                if d <= 0:
                    continue
                p = d * np.linalg.solve(Ks[i], [x + 0.5, y + 0.5, 1.0])
                world = poses[i][:3, :3] @ p + poses[i][:3, 3]
                for j in neighbours[i]:
                    pj = np.linalg.solve(poses[j][:3, :3], world - poses[j][:3, 3])
                    if pj[2] <= 1e-12:
                        continue
                    q = Ks[j] @ pj
                    col, row = math.floor(q[0] / pj[2]), math.floor(q[1] / pj[2])
                    hj, wj = depths[j].shape
                    if not (0 <= col < wj and 0 <= row < hj) or depths[j][row, col] <= 0:
                        continue
                    back_j = depths[j][row, col] * np.linalg.solve(Ks[j], [col + 0.5, row + 0.5, 1.0])
                    world_j = poses[j][:3, :3] @ back_j + poses[j][:3, 3]
                    pi = np.linalg.solve(poses[i][:3, :3], world_j - poses[i][:3, 3])
                    qi = Ks[i] @ pi
                    u2, v2 = qi[0] / pi[2], qi[1] / pi[2]
                    if (
                        math.hypot(u2 - (x + 0.5), v2 - (y + 0.5)) <= max_reproj_px
                        and abs(pi[2] - d) / d <= tolerance
                    ):
                        count[y, x] += 1
        counts.append(count)
    return counts


# ---------------------------------------------------------------------------------------------- driver


def run_mvs(
    views: list[PinholeView],
    sparse: list[SparseDepth] | None = None,
    config: MVSConfig | None = None,
    *,
    progress: bool = False,
    stats: list[dict] | None = None,
) -> list[DepthEstimate]:
    """Dense depth and confidence for every view by plane sweep + cross-view filtering.

    Needs at least two views, and a depth range (sparse depths or ``config.near/far``). A view
    without usable source views gets depth 0 and confidence 0 everywhere (logged). ``stats``, when
    given, receives one dict per view: sources, near, far, seconds, confident fraction.
    """
    config = config or MVSConfig()
    validate_views(views)
    if len(views) < 2:
        raise ValueError(
            f"multi-view stereo needs at least 2 overlapping views, got {len(views)}; "
            "use source='model' for a single image"
        )
    sparse = validate_sparse(sparse, views)
    per_view = [sp.depth for sp in sparse] if sparse else [np.zeros(0)] * len(views)
    all_depths = np.concatenate(per_view) if per_view else np.zeros(0)
    grays = [to_gray(v.image) for v in views]
    Ks = [torch.from_numpy(np.asarray(v.K, np.float64)) for v in views]
    poses = [torch.from_numpy(np.asarray(v.cam_to_world, np.float64)) for v in views]

    raw_depth, raw_conf, sources, records = [], [], [], []
    iterator = range(len(views))
    if progress:
        from rich.progress import track

        iterator = track(iterator, description="depth (plane sweep)", total=len(views))
    for i in iterator:
        t0 = time.perf_counter()
        near, far = depth_range(per_view[i], all_depths, config)
        src = select_sources(views, i, math.sqrt(near * far), config)
        sources.append(src)
        h, w = views[i].image.shape[:2]
        if not src:
            log.warning("view %d: no source view overlaps it enough; its depth is left invalid", i)
            raw_depth.append(torch.zeros((h, w)))
            raw_conf.append(torch.zeros((h, w)))
        else:
            inv = inverse_depth_planes(near, far, config.num_planes)
            cost, std_r = plane_sweep_cost(
                grays[i],
                [grays[j] for j in src],
                [_homography_terms(views[i], views[j]) for j in src],
                inv,
                window=config.window,
                best_k=config.best_k,
                max_chunk_mb=config.max_chunk_mb,
            )
            d, c = winner_take_all(
                cost,
                inv,
                std_r,
                min_texture=config.min_texture,
                min_ncc=config.min_ncc,
                min_confidence=config.min_confidence,
            )
            raw_depth.append(torch.where(c > 0, d, torch.zeros_like(d)))
            raw_conf.append(c)
        records.append(
            {"view": i, "sources": src, "near": near, "far": far, "seconds": time.perf_counter() - t0}
        )

    if config.geo_min_views > 0:
        t0 = time.perf_counter()
        counts = geometric_consistency(
            raw_depth,
            Ks,
            poses,
            sources,
            tolerance=config.geo_tolerance,
            max_reproj_px=config.geo_max_reproj_px,
        )
        keep = [n >= config.geo_min_views for n in counts]
        share = (time.perf_counter() - t0) / len(views)
        for rec in records:
            rec["seconds"] += share
    else:
        keep = [d > 0 for d in raw_depth]

    out = []
    for i, (d, c, k) in enumerate(zip(raw_depth, raw_conf, keep, strict=True)):
        depth = torch.where(k, d, torch.zeros_like(d)).numpy().astype(np.float32)
        conf = torch.where(k, c, torch.zeros_like(c)).numpy().astype(np.float32)
        records[i]["confident_fraction"] = float((conf > 0).mean())
        records[i]["raw_fraction"] = float((raw_conf[i] > 0).float().mean())
        out.append(DepthEstimate(depth=depth, confidence=conf))
    if stats is not None:
        stats.extend(records)
    return out
