"""Visibility carving of floating voxels in a posed depth capture.

A voxel that holds a real surface cannot be seen through: every view whose ray passes it ends at it
or before it. Wrong depth (a mismatched stereo pixel, a plane fill extrapolated past its wall, a
flying pixel at a depth edge) puts points where other views see free space, and each such floater
blocks the agent's buffer around it (a wrong patch of floor is a level plateau in the air). A voxel
is dropped when at least ``min_views`` views, and more than ``ratio`` times as many views as put a
point in it, see beyond it: the smallest depth in a ``(2 window + 1)^2`` window around the
projection of its mean point (holes ignored) lies farther than its own depth by
``max(margin, margin_rel x depth)``.
The window keeps thin obstacles (legs, poles) whose voxel centre projects just beside them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["DepthView", "see_through_counts", "see_through_counts_reference", "floater_mask"]


@dataclass(frozen=True)
class DepthView:
    """One view for carving: depth (H, W) in the camera's convention (z for pinhole, range for
    equirect; 0 = none), its camera model (``project``) and its camera-to-world pose (4, 4)."""

    depth: np.ndarray
    camera: object
    cam_to_world: np.ndarray


def see_through_counts(
    centres: np.ndarray, views: list[DepthView], *, margin: float, margin_rel: float, window: int
) -> np.ndarray:
    """(N,) int: per world point, the number of views that see beyond it (module docstring)."""
    count = np.zeros(len(centres), dtype=np.int64)
    if not len(centres):
        return count
    pts = torch.from_numpy(np.asarray(centres, dtype=np.float64))
    k = 2 * window + 1
    for view in views:
        pose = torch.from_numpy(np.asarray(view.cam_to_world, dtype=np.float64))
        uv, d, valid = view.camera.project((pts - pose[:3, 3]) @ pose[:3, :3])
        depth = torch.from_numpy(np.asarray(view.depth, dtype=np.float64))
        h, w = depth.shape
        nearest = -F.max_pool2d(
            -torch.where(depth > 0, depth, torch.full_like(depth, np.inf))[None, None], k, 1, window
        )[0, 0]
        col = torch.floor(uv[..., 0]).to(torch.int64)
        row = torch.floor(uv[..., 1]).to(torch.int64)
        inside = valid & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        seen = nearest[row.clamp(0, h - 1), col.clamp(0, w - 1)]
        beyond = seen > d + torch.clamp(d * margin_rel, min=margin)
        count += (inside & beyond & torch.isfinite(seen)).numpy()
    return count


def see_through_counts_reference(
    centres: np.ndarray, views: list[DepthView], *, margin: float, margin_rel: float, window: int
) -> np.ndarray:
    """Slow per-point, per-view definition of :func:`see_through_counts`."""
    count = np.zeros(len(centres), dtype=np.int64)
    for n, c in enumerate(np.asarray(centres, dtype=np.float64)):
        for view in views:
            pose = np.asarray(view.cam_to_world, dtype=np.float64)
            local = torch.from_numpy((c - pose[:3, 3]) @ pose[:3, :3])
            uv, d, valid = view.camera.project(local)
            if not bool(valid):
                continue
            u, v, d = int(np.floor(float(uv[0]))), int(np.floor(float(uv[1]))), float(d)
            h, w = view.depth.shape
            if not (0 <= u < w and 0 <= v < h):
                continue
            patch = view.depth[max(v - window, 0) : v + window + 1, max(u - window, 0) : u + window + 1]
            seen = patch[patch > 0]
            if seen.size and seen.min() > d + max(margin, margin_rel * d):
                count[n] += 1
    return count


def floater_mask(
    points: np.ndarray,
    supporting_views: np.ndarray,
    views: list[DepthView],
    *,
    min_views: int,
    ratio: float,
    margin: float = 0.1,
    margin_rel: float = 0.05,
    window: int = 1,
) -> np.ndarray:
    """(N,) bool: which voxels to drop, given one surface point per voxel (the mean of its points:
    a voxel's centre may lie centimetres off its surface, which a grazing view sees as a gap of
    decimetres) and how many views put a point in it (``supporting_views``)."""
    through = see_through_counts(points, views, margin=margin, margin_rel=margin_rel, window=window)
    return (through >= min_views) & (through > ratio * np.asarray(supporting_views))
