"""Voxel-grid downsampling of point clouds with per-voxel attribute averaging.

Vectorised: one ``torch.unique`` to group points by voxel, then ``index_add_`` sums; no Python loop
over points. Voxels are the half-open cubes [k*s, (k+1)*s) per axis, keyed by floor(p / s).
The output is ordered by voxel key (lexicographic in (ix, iy, iz)), so it is deterministic.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

__all__ = ["voxel_keys", "voxel_groups", "voxel_downsample"]


def _check_points(points: torch.Tensor, voxel_size: float, name: str) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name}: points must be (N, 3), got shape {tuple(points.shape)}")
    if not points.is_floating_point():
        raise ValueError(f"{name}: points must be floating point, got {points.dtype}")
    if not (float(voxel_size) > 0 and float(voxel_size) < float("inf")):
        raise ValueError(f"{name}: voxel_size must be a positive finite number, got {voxel_size}")
    bad = ~torch.isfinite(points).all(dim=1)
    if bad.any():
        raise ValueError(
            f"{name}: {int(bad.sum())} of {points.shape[0]} points are NaN/inf (first at row "
            f"{int(bad.nonzero()[0, 0])}); filter them before downsampling"
        )


def voxel_keys(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Integer voxel coordinates floor(points / voxel_size), (N, 3) int64."""
    _check_points(points, voxel_size, "voxel_keys")
    scaled = torch.floor(points / voxel_size)
    if scaled.numel() and float(scaled.abs().amax()) >= 2.0**52:
        raise ValueError(
            f"voxel_keys: coordinates up to {float(points.abs().amax()):.3g} are too large for "
            f"voxel_size {voxel_size} (more than 2^52 voxels per axis)"
        )
    return scaled.to(torch.int64)


def voxel_groups(points: torch.Tensor, voxel_size: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Group points by voxel: (keys (M, 3) int64 sorted, inverse (N,) int64 in [0, M), counts (M,)).

    The three int64 coordinates are packed into one int64 (relative to their minimum) when the
    grid's extent allows it, which makes ``torch.unique`` several times faster than ``dim=0``.
    """
    keys = voxel_keys(points, voxel_size)
    if keys.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=points.device)
        return keys, empty, empty
    lo = keys.amin(dim=0)
    span = keys.amax(dim=0) - lo + 1
    ny, nz = int(span[1]), int(span[2])
    if int(span[0]) * ny * nz < 2**62:
        rel = keys - lo
        packed = (rel[:, 0] * ny + rel[:, 1]) * nz + rel[:, 2]
        uniq, inverse, counts = torch.unique(packed, sorted=True, return_inverse=True, return_counts=True)
        ux = uniq // (ny * nz)
        uy = (uniq // nz) % ny
        uz = uniq % nz
        return torch.stack((ux, uy, uz), dim=1) + lo, inverse, counts
    uniq, inverse, counts = torch.unique(keys, dim=0, sorted=True, return_inverse=True, return_counts=True)
    return uniq, inverse, counts


def _mean_per_group(values: torch.Tensor, inverse: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Per-group mean of values (N, ...) in float64 (accurate for large float32/int clouds)."""
    acc = torch.zeros((counts.shape[0], *values.shape[1:]), dtype=torch.float64, device=values.device)
    acc.index_add_(0, inverse, values.to(torch.float64))
    return acc / counts.reshape(-1, *([1] * (values.ndim - 1))).to(torch.float64)


def _cast_back(mean: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Float64 means back to the attribute dtype: round integers, majority vote for bools."""
    if dtype == torch.bool:
        return mean >= 0.5
    if dtype.is_floating_point or dtype.is_complex:
        return mean.to(dtype)
    return torch.round(mean).to(dtype)


def voxel_downsample(
    points: torch.Tensor,
    voxel_size: float,
    attributes: Mapping[str, torch.Tensor] | None = None,
    quaternion_keys: Sequence[str] = (),
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Average points (N, 3) and every attribute (N, ...) per voxel of edge ``voxel_size``.

    Returns ``(points (M, 3), attributes)`` with M <= N voxels, ordered by voxel key; dtypes are
    preserved (sums run in float64; integer attributes are rounded, bools take the majority).
    Attributes named in ``quaternion_keys`` must be (N, 4); before averaging, each quaternion is
    sign-aligned to its voxel's reference (the first point of the voxel in input order) because q
    and -q are the same rotation, and the mean is renormalised to unit length.
    Raises ``ValueError`` for NaN/inf points, bad shapes or unknown quaternion keys.
    """
    _check_points(points, voxel_size, "voxel_downsample")
    attributes = dict(attributes or {})
    N = points.shape[0]
    for key, value in attributes.items():
        if not isinstance(value, torch.Tensor) or value.ndim < 1 or value.shape[0] != N:
            shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(
                f"voxel_downsample: attribute {key!r} must be a tensor with {N} rows, got {shape}"
            )
    for key in quaternion_keys:
        if key not in attributes:
            raise ValueError(
                f"voxel_downsample: quaternion key {key!r} is not among the attributes {sorted(attributes)}"
            )
        q = attributes[key]
        if q.ndim != 2 or q.shape[1] != 4 or not q.is_floating_point():
            raise ValueError(
                f"voxel_downsample: quaternion attribute {key!r} must be floating (N, 4), "
                f"got {tuple(q.shape)} {q.dtype}"
            )

    _, inverse, counts = voxel_groups(points, voxel_size)
    out_points = _mean_per_group(points, inverse, counts).to(points.dtype)
    out_attrs: dict[str, torch.Tensor] = {}
    first = None
    if quaternion_keys:
        # Index of the first point of every voxel: the per-voxel sign reference.
        order = torch.arange(N, device=points.device)
        first = torch.full((counts.shape[0],), N, dtype=torch.int64, device=points.device)
        first.scatter_reduce_(0, inverse, order, reduce="amin", include_self=True)
    for key, value in attributes.items():
        if key in quaternion_keys:
            ref = value[first][inverse]
            sign = torch.where((value * ref).sum(dim=1, keepdim=True) < 0, -1.0, 1.0).to(value.dtype)
            mean = _mean_per_group(value * sign, inverse, counts)
            # Aligned to the reference, every summand has a non-negative dot product with it, so the
            # mean has length >= 1/count * |ref| > 0 for unit inputs: the division is safe.
            mean = mean / torch.linalg.vector_norm(mean, dim=1, keepdim=True).clamp_min(1e-300)
            out_attrs[key] = mean.to(value.dtype)
        else:
            out_attrs[key] = _cast_back(_mean_per_group(value, inverse, counts), value.dtype)
    return out_points, out_attrs
