"""Score rendered views against held-out targets and summarise them (no renderer needed here).

:func:`score_views` turns a batch of predictions into per-view metric records (PSNR, SSIM, LPIPS or
``None`` when no LPIPS weights are configured, and depth AbsRel / RMSE / δ<1.25 when depth is
given); :func:`summarize_views` averages them with the same no-silent-drop rules as navigation
results. The rendering benchmark runner feeds these; tables are built by
:func:`image2sim.eval.report.render_table_markdown`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from image2sim.eval.metrics.lpips import LPIPS, lpips_distance
from image2sim.eval.metrics.nav import MetricSummary, summarize_records
from image2sim.eval.metrics.render import depth_metrics, psnr, ssim

RENDER_METRICS = ("lpips", "psnr", "ssim", "abs_rel", "rmse", "delta1")
"""Keys of a per-view record (depth keys only when depth was scored)."""


def score_views(
    view_ids: Sequence[str],
    pred: torch.Tensor,
    target: torch.Tensor,
    *,
    pred_depth: torch.Tensor | None = None,
    target_depth: torch.Tensor | None = None,
    lpips_model: LPIPS | None = None,
    data_range: float = 1.0,
) -> list[tuple[str, dict[str, float | None]]]:
    """Per-view metric records for RGB ``(B, 3, H, W)`` in [0, 1] and optional depth ``(B, 1, H, W)``."""
    if pred.ndim != 4 or pred.shape[1] != 3:
        raise ValueError(f"pred: expected (B, 3, H, W), got {tuple(pred.shape)}")
    if len(view_ids) != pred.shape[0]:
        raise ValueError(f"view_ids: {len(view_ids)} ids for a batch of {pred.shape[0]} views")
    if (pred_depth is None) != (target_depth is None):
        raise ValueError("pred_depth and target_depth must be given together")
    p = psnr(pred, target, data_range=data_range)
    s = ssim(pred, target, data_range=data_range)
    lp = lpips_distance(pred, target, lpips_model)
    dm = None if pred_depth is None else depth_metrics(pred_depth, target_depth)
    out = []
    for i, vid in enumerate(view_ids):
        rec: dict[str, float | None] = {
            "lpips": None if lp is None else float(lp[i]),
            "psnr": float(p[i]),
            "ssim": float(s[i]),
        }
        if dm is not None:
            rec.update(abs_rel=float(dm.abs_rel[i]), rmse=float(dm.rmse[i]), delta1=float(dm.delta1[i]))
        out.append((str(vid), rec))
    return out


@dataclass(frozen=True)
class RenderCell:
    """Summary of one method under one setting (noise tier, resolution...)."""

    metrics: dict[str, MetricSummary]
    """Metric -> mean with view count (LPIPS mean is ``None`` = n/a without weights)."""
    num_views: int
    """Views scored."""
    fps: float | None = None
    """Frames per second from :func:`image2sim.eval.metrics.timing.measure_fps`, if measured."""
    hardware: str | None = field(default=None)
    """Hardware string of the FPS measurement."""
    psnr_per_view: dict[str, float | None] = field(default_factory=dict)
    """View name -> its PSNR (None where infinite), so reports can show medians and outliers."""


def summarize_views(
    records: Sequence[tuple[str, dict[str, float | None]]],
    fps: float | None = None,
    hardware: str | None = None,
) -> RenderCell:
    """Average per-view records (PSNR may be +inf for a perfect view; NaN is an error naming the view)."""
    metrics = summarize_records(records, allow_inf={"psnr"}, kind="view")
    per_view = {}
    for name, m in records:
        v = m.get("psnr")
        per_view[name] = float(v) if v is not None and math.isfinite(v) else None
    return RenderCell(metrics, len(records), fps, hardware, per_view)
