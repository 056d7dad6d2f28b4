"""Renderer losses other than the flow and distillation terms.

* :func:`reconstruction_loss`  L1 on RGB plus L1 on valid (> 0) depth
* :func:`relative_depth_error` per-image mean squared relative depth error over valid pixels
* :func:`saturation_penalty`   squared excess of a colour estimate outside [0, 1]
* :class:`LPIPS`               LPIPS (VGG16 + learned linear heads), re-exported from
                               :mod:`image2sim.simulator.metrics.lpips`; weights are read from a
                               user-supplied file, never downloaded
* :func:`load_lpips`           builds LPIPS from a configured path, or warns once and returns None
                               (the caller then sets lambda_perc = 0); alias of
                               :func:`~image2sim.simulator.metrics.lpips.load_lpips_or_none`
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from image2sim.simulator.metrics.lpips import LPIPS, LPIPS_CHANNELS, VGG16_LAYERS
from image2sim.simulator.metrics.lpips import load_lpips_or_none as load_lpips

__all__ = [
    "reconstruction_loss",
    "relative_depth_error",
    "saturation_penalty",
    "LPIPS",
    "load_lpips",
    "VGG16_LAYERS",
    "LPIPS_CHANNELS",
]


def reconstruction_loss(
    pred_rgb: torch.Tensor,
    pred_depth: torch.Tensor,
    target_rgb: torch.Tensor,
    target_depth: torch.Tensor,
    rgb_weight: float = 1.0,
    depth_weight: float = 1.0,
) -> torch.Tensor:
    """``rgb_weight * mean|dRGB| + depth_weight * mean_{valid}|dD|``; depth is compared only
    where the target is valid (> 0 and finite), and an image without valid depth contributes 0."""
    rgb = (pred_rgb.float() - target_rgb.float()).abs().mean()
    valid = (target_depth > 0) & torch.isfinite(target_depth)
    diff = (pred_depth.float() - torch.where(valid, target_depth, 0).float()).abs() * valid
    depth = diff.sum() / valid.sum().clamp_min(1)
    return rgb_weight * rgb + depth_weight * depth


def relative_depth_error(pred_depth: torch.Tensor, target_depth: torch.Tensor) -> torch.Tensor:
    """Per image ``(B,)``: mean over valid target pixels (> 0, finite) of ``((pred - target) /
    target)^2`` (the squared counterpart of AbsRel); an image without valid depth gives 0."""
    valid = (target_depth > 0) & torch.isfinite(target_depth)
    ref = torch.where(valid, target_depth, torch.ones_like(target_depth)).float()
    err = ((pred_depth.float() - ref) / ref).pow(2) * valid
    return err.flatten(1).sum(1) / valid.flatten(1).sum(1).clamp_min(1)


def saturation_penalty(x: torch.Tensor, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
    """mean(relu(low - x)^2 + relu(x - high)^2): zero inside the valid colour range."""
    x = x.float()
    return (F.relu(low - x).pow(2) + F.relu(x - high).pow(2)).mean()
