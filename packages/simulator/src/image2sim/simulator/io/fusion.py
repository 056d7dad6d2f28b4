"""Back-project capture frames into the world and fuse them into one voxel-averaged coloured cloud.

Fusion streams: chunks of frames are reduced to per-voxel sums (position, colour, count) with
:func:`image2sim.simulator.geometry.voxel.voxel_groups`, and the sums are merged across chunks by
voxel key. The result equals :func:`~image2sim.simulator.geometry.voxel.voxel_downsample` of all
points at once (the mean of every voxel over every frame), without holding every point in memory.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch
from image2sim.simulator.geometry.cameras import Camera
from image2sim.simulator.geometry.voxel import voxel_groups
from image2sim.simulator.io.records import Capture, Frame

__all__ = ["backproject_frame", "fuse_frames", "select_indices", "VoxelAccumulator"]

_KEY_BITS = 21  # per axis; +-2^20 voxels = +-52 km at 5 cm
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


@lru_cache(maxsize=4)
def _unit_depth_points(camera: Camera) -> torch.Tensor:
    """Camera-frame points at depth 1 for every pixel, (H*W, 3) float32, row-major pixels.

    Unprojection is linear in depth for both camera models (range x unit ray; z x K^-1 ray), so
    one cached map per camera turns every frame's back-projection into a multiply-add.
    """
    ones = torch.ones((camera.height, camera.width), dtype=torch.float64)
    return camera.unproject(ones).reshape(-1, 3).to(torch.float32)


def backproject_frame(frame: Frame, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) float32 and colours (N, 3) uint8 of the valid (depth > 0) pixels.

    ``pixels`` optionally restricts to flat pixel indices (row-major); invalid ones are dropped.
    float32 is ample here (1 micrometre at 10 m) and keeps the hot path fast.
    """
    depth = torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32).reshape(-1))
    rays = _unit_depth_points(frame.camera)
    colours = np.asarray(frame.rgb).reshape(-1, 3)
    if pixels is not None:
        pixels = torch.as_tensor(np.asarray(pixels), dtype=torch.int64)
        depth, rays, colours = depth[pixels], rays[pixels], colours[pixels.numpy()]
    valid = depth > 0
    pose = torch.from_numpy(np.asarray(frame.cam_to_world, dtype=np.float32))
    # Transform every pixel, then mask: dense ops beat gathering rows first.
    world = torch.addmm(pose[:3, 3], rays * depth[:, None], pose[:3, :3].T)
    valid_np = valid.numpy()
    return world[valid].numpy(), colours[valid_np]


def _pack(keys: torch.Tensor) -> torch.Tensor:
    """(M, 3) int64 voxel keys -> (M,) int64, injective while every |key| < 2^20."""
    if keys.numel() and int(keys.abs().amax()) >= _KEY_OFFSET:
        raise ValueError(f"fusion: voxel coordinates exceed +-{_KEY_OFFSET} voxels; use a larger voxel size")
    k = keys + _KEY_OFFSET
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


class VoxelAccumulator:
    """Running per-voxel sums of position and colour; add point batches, then :meth:`result`.

    Raw points are buffered up to ``chunk_points`` and reduced together (one grouping pass per
    chunk is several times cheaper than one per frame); per-voxel sums are merged whenever their
    rows exceed ``merge_rows``. Memory stays bounded by the chunk plus the voxel count.
    """

    def __init__(self, voxel_size: float, chunk_points: int = 4_000_000, merge_rows: int = 4_000_000) -> None:
        if not (float(voxel_size) > 0 and np.isfinite(voxel_size)):
            raise ValueError(f"voxel_size must be a positive finite number, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.chunk_points = int(chunk_points)
        self.merge_rows = int(merge_rows)
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_points = 0
        self._keys: list[torch.Tensor] = []
        self._sums: list[torch.Tensor] = []  # (M, 7): sum x, y, z, r, g, b, count
        self.num_points = 0

    def add(self, points: np.ndarray, colors: np.ndarray) -> None:
        """Add world points (N, 3) and colours (N, 3) uint8."""
        points, colors = np.asarray(points), np.asarray(colors)
        if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
            raise ValueError(f"points and colours must both be (N, 3), got {points.shape} and {colors.shape}")
        if len(points) == 0:
            return
        self._pending.append((points, colors))
        self._pending_points += len(points)
        self.num_points += len(points)
        if self._pending_points >= self.chunk_points:
            self._reduce_pending()

    def _reduce_pending(self) -> None:
        if not self._pending:
            return
        pts = torch.from_numpy(np.concatenate([p for p, _ in self._pending]).astype(np.float64, copy=False))
        cols = torch.from_numpy(np.concatenate([c for _, c in self._pending]).astype(np.float64))
        self._pending, self._pending_points = [], 0
        keys, inverse, counts = voxel_groups(pts, self.voxel_size)
        sums = torch.zeros((keys.shape[0], 7), dtype=torch.float64)
        sums[:, :3].index_add_(0, inverse, pts)
        sums[:, 3:6].index_add_(0, inverse, cols)
        sums[:, 6] = counts.to(torch.float64)
        self._keys.append(_pack(keys))
        self._sums.append(sums)
        if sum(len(k) for k in self._keys) > self.merge_rows:
            self._merge()

    def _merge(self) -> None:
        self._reduce_pending()
        if len(self._keys) <= 1:
            return
        keys = torch.cat(self._keys)
        sums = torch.cat(self._sums)
        uniq, inverse = torch.unique(keys, sorted=True, return_inverse=True)
        merged = torch.zeros((uniq.shape[0], 7), dtype=torch.float64)
        merged.index_add_(0, inverse, sums)
        self._keys, self._sums = [uniq], [merged]

    def __len__(self) -> int:
        self._merge()
        return int(self._keys[0].shape[0]) if self._keys else 0

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (M, 3) float64 voxel means, colours (M, 3) uint8 rounded means), ordered by voxel key."""
        self._merge()
        if not self._keys:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        sums = self._sums[0]
        mean = sums[:, :6] / sums[:, 6:7]
        colors = torch.clamp(torch.round(mean[:, 3:6]), 0, 255).to(torch.uint8)
        return mean[:, :3].numpy(), colors.numpy()


def select_indices(n: int, stride: int = 1, max_frames: int | None = None) -> list[int]:
    """Frame indices ``0, stride, 2*stride, ...`` capped at ``max_frames``."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    idx = list(range(0, n, stride))
    return idx[:max_frames] if max_frames is not None else idx


def fuse_frames(
    capture: Capture | Sequence[Frame],
    voxel_size: float,
    indices: Sequence[int] | None = None,
    *,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Fuse frames (all, or ``indices``) into ``(points (M, 3), colours (M, 3) uint8, input point count)``."""
    indices = list(range(len(capture))) if indices is None else list(indices)
    acc = VoxelAccumulator(voxel_size)

    def step(i: int) -> None:
        points, colors = backproject_frame(capture[i])
        acc.add(points, colors)

    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        columns = (TextColumn("fusing"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        with Progress(*columns) as bar:
            task = bar.add_task("fuse", total=len(indices))
            for i in indices:
                step(i)
                bar.advance(task)
    else:
        for i in indices:
            step(i)
    points, colors = acc.result()
    return points, colors, acc.num_points
