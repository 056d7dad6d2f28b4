"""LPIPS configuration for evaluation: where the weights live, and building the network from it.

The network, weight loading and :func:`lpips_distance` live in :mod:`image2sim.simulator.metrics.lpips`
(shared with the renderer's perceptual loss) and are re-exported here so existing imports keep working.
Without configured weights LPIPS is reported as "n/a", never as 0.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from image2sim.simulator.config import config_from_dict
from image2sim.simulator.metrics.lpips import (
    LPIPS,
    LPIPS_CHANNELS,
    LpipsWeightsError,
    VGG16Taps,
    load_lpips,
    lpips_distance,
    read_state_dict,
    unit_normalize,
)

__all__ = [
    "LPIPS",
    "LPIPS_CHANNELS",
    "LpipsConfig",
    "LpipsWeightsError",
    "VGG16Taps",
    "build_lpips",
    "load_lpips",
    "lpips_distance",
    "read_state_dict",
    "unit_normalize",
]


@dataclass(frozen=True)
class LpipsConfig:
    """Where LPIPS weights live. Both ``None`` (the default) means LPIPS is reported as n/a."""

    weights: str | None = None
    """Head weights (the released ``vgg.pth`` layout) or a full LPIPS state dict."""
    backbone_weights: str | None = None
    """Optional separate VGG16 trunk weights (``features.*`` or ``net.slice*`` names)."""

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LpipsConfig:
        """Build from a mapping with the shared config mechanism: unknown keys and wrong types raise
        :class:`~image2sim.simulator.config.ConfigError` (a ``ValueError``) naming the field."""
        return config_from_dict(cls, data, "lpips")


def build_lpips(config: LpipsConfig) -> LPIPS | None:
    """The configured network, or ``None`` when no weights are configured."""
    if config.weights is None:
        if config.backbone_weights is not None:
            raise LpipsWeightsError("lpips config: backbone_weights given without weights (the linear heads)")
        return None
    return load_lpips(config.weights, config.backbone_weights)
