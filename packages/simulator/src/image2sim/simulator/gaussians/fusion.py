"""Fusion of Gaussians into the scene memory: footprint-adaptive (or fixed) voxel averaging.

Policy ``footprint``: every Gaussian gets a voxel level l (edge ``base_voxel * 2^l``) from its
observed pixel footprint (range x angular pixel size); the grids are nested (a level-(l+1) cell is
the union of 8 level-l cells). A Gaussian whose level-l cell already holds a finer one is moved
down to the finest level present there, so a surface seen close up keeps its detail, a distant
re-observation of it merges into the fine Gaussians instead of adding a coarse duplicate, and no
gap opens where the level changes inside one frame. Then all Gaussians are averaged per
(level, cell) with their weights (quaternions sign-aligned to each cell's first member and
renormalised). The count therefore tracks the observed surface at its observed detail and
saturates as frames repeat views. Policy ``fixed``: level 0 with edge ``voxel_size``.
"""

from __future__ import annotations

import torch
from image2sim.simulator.gaussians.config import FusionConfig
from image2sim.simulator.gaussians.primitives import GaussianSet
from image2sim.simulator.geometry.voxel import voxel_keys
from image2sim.simulator.lifetime import torch_threads

__all__ = ["cell_sizes", "assign_levels", "fuse", "prune"]


def cell_sizes(cfg: FusionConfig) -> list[float]:
    """Voxel edge of every level, metres."""
    if cfg.policy == "fixed":
        return [float(cfg.voxel_size)]
    return [float(cfg.base_voxel) * 2.0**level for level in range(cfg.levels)]


def assign_levels(footprints: torch.Tensor, cfg: FusionConfig) -> torch.Tensor:
    """Initial level per Gaussian: nearest power of two of footprint_factor x footprint / base_voxel."""
    if cfg.policy == "fixed":
        return torch.zeros(footprints.shape, dtype=torch.int64, device=footprints.device)
    target = (footprints.double() * cfg.footprint_factor / cfg.base_voxel).clamp_min(1e-30)
    return torch.round(torch.log2(target)).clamp(0, cfg.levels - 1).to(torch.int64)


def _keys_at(points: torch.Tensor, size: float) -> torch.Tensor:
    return voxel_keys(points.double(), size)


def _pack(levels: torch.Tensor, keys: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """(level, kx, ky, kz) -> one int64 per row when the extent allows (else the stacked (N, 4) rows)."""
    rows = torch.cat((levels[:, None], keys), dim=1)
    if rows.shape[0] == 0:
        return rows[:, 0], True
    lo = rows.amin(dim=0)
    span = rows.amax(dim=0) - lo + 1
    total = 1
    for s in span.tolist():
        total *= int(s)
    if total >= 2**62:
        return rows, False
    rel = rows - lo
    packed = rel[:, 0]
    for axis in range(1, 4):
        packed = packed * int(span[axis]) + rel[:, axis]
    return packed, True


def _unique(levels: torch.Tensor, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    packed, flat = _pack(levels, keys)
    if flat:
        _, inverse, counts = torch.unique(packed, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = torch.unique(packed, dim=0, return_inverse=True, return_counts=True)
    return inverse, counts


def _settle_levels(means: torch.Tensor, levels: torch.Tensor, sizes: list[float]) -> torch.Tensor:
    """Move each Gaussian down to the finest level present in its cell, until nothing moves.

    One ascending sweep is not enough: a Gaussian moved from level 2 to 0 can land in the level-1
    cell of a Gaussian the sweep already passed. Levels only decrease (to levels already present),
    so the loop terminates (usually after two sweeps); the fixpoint makes :func:`fuse` idempotent.
    The cell grouping of every level is computed once (one ``unique`` per level); a sweep is then
    one ``scatter_reduce`` per level.
    """
    levels = levels.clone()
    present = sorted(set(levels.tolist())) if levels.numel() else []
    if len(present) < 2:
        return levels
    zeros = torch.zeros_like(levels)
    groups = {}
    for L in present[1:]:
        inverse, counts = _unique(zeros, _keys_at(means, sizes[L]))
        groups[L] = (inverse, counts.shape[0])
    while True:
        moved = False
        for L in present[1:]:
            inverse, m = groups[L]
            # Coarser members count as L, which is neutral for the minimum.
            best = torch.full((m,), L, dtype=torch.int64, device=levels.device)
            best.scatter_reduce_(0, inverse, levels.clamp_max(L), reduce="amin", include_self=True)
            new = best[inverse]
            move = (levels == L) & (new < L)
            if bool(move.any()):
                levels = torch.where(move, new, levels)
                moved = True
        if not moved:
            return levels


def fuse(gaussians: GaussianSet, cfg: FusionConfig) -> GaussianSet:
    """Voxel-average a set of Gaussians (already-fused ones keep their levels and weights).

    Means, scales, opacities, colours, features and footprints are weight-averaged per cell,
    weights add up, quaternions are sign-aligned and renormalised; fused standard deviations are
    floored at ``cover_factor`` x the cell edge so merged points leave no holes. Deterministic:
    the output is ordered by (level, cell key).
    """
    with torch_threads(cfg.threads):
        return _fuse(gaussians, cfg)


def _fuse(gaussians: GaussianSet, cfg: FusionConfig) -> GaussianSet:
    n = len(gaussians)
    if n == 0:
        return gaussians
    g = gaussians.detach()
    dev = g.means.device
    if not torch.isfinite(g.means).all():
        raise ValueError("fuse: Gaussian means contain NaN/inf; drop them before fusion")
    sizes = cell_sizes(cfg)
    levels = g.levels.clamp(0, len(sizes) - 1)
    if cfg.policy == "footprint":
        levels = _settle_levels(g.means, levels, sizes)
    size_of = torch.tensor(sizes, dtype=torch.float64, device=dev)[levels]
    keys = torch.floor(g.means.double() / size_of[:, None]).to(torch.int64)
    inverse, counts = _unique(levels, keys)
    m = counts.shape[0]
    w = g.weights.double()
    wsum = torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, inverse, w)

    def mean_of(values: torch.Tensor) -> torch.Tensor:
        v = values.double().reshape(n, -1)
        acc = torch.zeros(m, v.shape[1], dtype=torch.float64, device=dev).index_add_(
            0, inverse, v * w[:, None]
        )
        return (acc / wsum[:, None]).reshape(m, *values.shape[1:]).to(values.dtype)

    first = torch.full((m,), n, dtype=torch.int64, device=dev)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=dev), reduce="amin", include_self=True)
    q = g.quats
    ref = q[first][inverse]
    sign = torch.where((q * ref).sum(dim=1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)
    qm = mean_of(q * sign).double()
    qm = (qm / torch.linalg.vector_norm(qm, dim=1, keepdim=True).clamp_min(1e-300)).to(q.dtype)
    out_levels = torch.zeros(m, dtype=torch.int64, device=dev).scatter_(0, inverse, levels)
    scales = mean_of(g.scales)
    if cfg.cover_factor > 0:
        floor = (torch.tensor(sizes, dtype=torch.float64, device=dev)[out_levels] * cfg.cover_factor).to(
            scales.dtype
        )
        # Only merged cells need the floor: a single observation keeps its own (e.g. learned) scale.
        floor = torch.where(counts > 1, floor, torch.zeros_like(floor))
        scales = torch.maximum(scales, floor[:, None])
    return GaussianSet(
        means=mean_of(g.means),
        scales=scales,
        quats=qm,
        opacities=mean_of(g.opacities),
        colors=mean_of(g.colors),
        features=mean_of(g.features),
        footprints=mean_of(g.footprints),
        weights=wsum.to(g.weights.dtype),
        levels=out_levels,
    )


def prune(gaussians: GaussianSet, cfg: FusionConfig) -> GaussianSet:
    """Drop Gaussians with opacity below ``min_opacity`` or any non-finite value."""
    keep = gaussians.opacities >= cfg.min_opacity
    for t in gaussians.tensors().values():
        if t.is_floating_point() and t.numel():
            keep &= torch.isfinite(t.reshape(t.shape[0], -1)).all(dim=1)
    return gaussians.index(keep)


def level_histogram(levels: torch.Tensor, cfg: FusionConfig) -> dict[str, int]:
    """Gaussian count per voxel edge (millimetres as keys, for manifests)."""
    sizes = cell_sizes(cfg)
    counts = torch.bincount(levels, minlength=len(sizes)).tolist() if levels.numel() else [0] * len(sizes)
    return {f"{sizes[i] * 1000:.4g}mm": int(c) for i, c in enumerate(counts) if c}
