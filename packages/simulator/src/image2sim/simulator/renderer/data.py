"""Training samples for the renderer: (condition C_p, target RGB-D) pairs.

The renderer takes tensors, so any source that yields ``{"condition": (24, H, W), "target_rgb":
(3, H, W), "target_depth": (1, H, W)}`` works (optionally ``"target_tokens"`` and ``"pose"``).
Two sources live here:

* :class:`ConditionDataset` wraps precomputed conditions (e.g. splats of a scene's Gaussians at
  held-out target panoramas; the splatting pipeline produces them and may cache them per scene).
* :class:`DegradedPanoramaDataset` synthesises a splat-like condition from a target panorama
  (smooth random holes with soft alpha edges, colour/depth noise where observed, features as a
  fixed random projection of the observed RGB-D) so the renderer can be trained and tested
  without the splatting stack. Each sample index gives its own deterministic degradation.

:func:`permuted_index` makes the sample order a pure function of (seed, position), so a resumed run
continues exactly where it stopped (the shared :class:`~image2sim.simulator.sampling.StepSampler`
serves it, split over ranks under DDP).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.renderer.condition import build_condition
from torch.utils.data import Dataset

__all__ = [
    "DegradeConfig",
    "degrade_to_condition",
    "DegradedPanoramaDataset",
    "ConditionDataset",
    "permuted_index",
    "resize_target",
    "load_capture_targets",
]


@dataclass
class DegradeConfig:
    """How a target panorama is degraded into a splat-like condition."""

    hole_fraction: tuple[float, float] = (0.2, 0.5)
    """Range of the fraction of pixels without projection (alpha ~ 0), drawn per sample."""
    hole_scale: int = 8
    """Holes are smooth blobs of about H/hole_scale pixels."""
    edge_sharpness: float = 12.0
    """Slope of the soft alpha edge (higher = harder edges)."""
    rgb_noise: float = 0.05
    """Std of the colour noise where observed (the procedural 'middle' tier)."""
    depth_noise: float = 0.02
    """Relative std of the range noise where observed."""
    seed: int = 0
    """Base seed of the degradations (and of the feature projection)."""


def _wrap_upsample(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear upsampling of a (B, C, h, w) map that wraps in width (no seam in the holes)."""
    h, w = x.shape[-2:]
    padded = torch.cat((x[..., -1:], x, x[..., :1]), dim=-1)
    sx = size[1] / w
    big = F.interpolate(
        padded, size=(size[0], int(round((w + 2) * sx))), mode="bilinear", align_corners=False
    )
    start = int(round(sx))
    return big[..., start : start + size[1]]


def degrade_to_condition(
    rgb: torch.Tensor, depth: torch.Tensor, generator: torch.Generator, cfg: DegradeConfig
) -> torch.Tensor:
    """Splat-like condition ``(24, H, W)`` from a target ``rgb (3, H, W)``, ``depth (1, H, W)``."""
    _, h, w = rgb.shape
    lo = (max(1, cfg.hole_scale // 2), max(2, cfg.hole_scale))
    field_lo = torch.rand(1, 1, *lo, generator=generator)
    field = _wrap_upsample(field_lo, (h, w))[0]
    frac = float(
        cfg.hole_fraction[0]
        + (cfg.hole_fraction[1] - cfg.hole_fraction[0]) * torch.rand(1, generator=generator)
    )
    thr = torch.quantile(field.flatten(), frac)
    alpha = torch.sigmoid((field - thr) * cfg.edge_sharpness * lo[1])
    alpha = alpha * (depth > 0)
    noisy_rgb = (rgb + cfg.rgb_noise * torch.randn(rgb.shape, generator=generator)).clamp(0, 1)
    noisy_depth = (depth * (1 + cfg.depth_noise * torch.randn(depth.shape, generator=generator))).clamp_min(0)
    observed = (alpha > 1e-3).to(rgb.dtype)
    prior_rgb, prior_depth = noisy_rgb * observed, noisy_depth * observed
    proj = torch.randn(16, 5, generator=torch.Generator().manual_seed(cfg.seed + 7919))
    feats = (
        torch.tanh(torch.einsum("fc,chw->fhw", proj, torch.cat((prior_rgb, prior_depth / 5, alpha), 0)))
        * alpha
    )
    rays = EquirectCamera(h, w).ray_map(rgb.dtype)
    return build_condition(feats[None], prior_rgb[None], prior_depth[None], alpha[None], rays)[0]


class DegradedPanoramaDataset(Dataset):
    """``len = num_samples`` virtual samples over the given targets; sample ``i`` uses target
    ``i mod N`` and a degradation seeded by ``(cfg.seed, i)``."""

    def __init__(
        self,
        targets: Sequence[tuple[torch.Tensor, torch.Tensor]],
        num_samples: int,
        cfg: DegradeConfig | None = None,
    ) -> None:
        if not targets:
            raise ValueError("DegradedPanoramaDataset needs at least one target panorama")
        self.targets = list(targets)
        self.num_samples = int(num_samples)
        self.cfg = cfg or DegradeConfig()

    def __len__(self) -> int:
        return self.num_samples

    def __getitem__(self, index: int) -> dict:
        rgb, depth = self.targets[index % len(self.targets)]
        gen = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + int(index))
        return {
            "condition": degrade_to_condition(rgb, depth, gen, self.cfg),
            "target_rgb": rgb,
            "target_depth": depth,
            "index": int(index),
        }


class ConditionDataset(Dataset):
    """Precomputed ``(condition, target_rgb, target_depth)`` triples (e.g. cached splats)."""

    def __init__(
        self, conditions: torch.Tensor, target_rgb: torch.Tensor, target_depth: torch.Tensor
    ) -> None:
        if not (len(conditions) == len(target_rgb) == len(target_depth)):
            raise ValueError("conditions and targets differ in length")
        self.conditions, self.target_rgb, self.target_depth = conditions, target_rgb, target_depth

    def __len__(self) -> int:
        return len(self.conditions)

    def __getitem__(self, index: int) -> dict:
        return {
            "condition": self.conditions[index],
            "target_rgb": self.target_rgb[index],
            "target_depth": self.target_depth[index],
            "index": int(index),
        }


def permuted_index(position: int, length: int, seed: int = 0) -> int:
    """Dataset index at global sample ``position``: each block of ``length`` positions is a
    permutation seeded by ``(seed, block)``, so the order is deterministic and resumable anywhere
    (the ``index_of`` of :class:`~image2sim.simulator.sampling.StepSampler`)."""
    if length <= 0:
        raise ValueError("the renderer's data order needs a non-empty dataset")
    block, offset = divmod(int(position), int(length))
    perm = torch.randperm(length, generator=torch.Generator().manual_seed(int(seed) * 7_919 + block))
    return int(perm[offset])


def resize_target(
    rgb: np.ndarray, depth: np.ndarray, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 ``(h, w, 3)`` colour and metric ``(h, w)`` depth -> area-resized ``(3, H, W)`` in [0, 1]
    and ``(1, H, W)`` metres. Depth is averaged over valid source pixels only (an invalid 0 never
    drags a mean down); a pixel that is mostly invalid stays 0."""
    rgb_t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float()[None] / 255.0
    depth_t = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None, None]
    rgb_s = F.adaptive_avg_pool2d(rgb_t, (height, width))
    valid = (depth_t > 0).float()
    num = F.adaptive_avg_pool2d(depth_t * valid, (height, width))
    den = F.adaptive_avg_pool2d(valid, (height, width))
    depth_s = torch.where(den > 0.5, num / den.clamp_min(1e-6), torch.zeros_like(num))
    return rgb_s[0].contiguous(), depth_s[0].contiguous()


def load_capture_targets(
    path, height: int, width: int, max_frames: int | None = None
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Target panoramas of a capture (any format ``open_capture`` reads), area-resized to
    ``height x width``: list of ``(rgb (3, H, W) in [0, 1], depth (1, H, W) metres)``. Depth is
    averaged over valid source pixels only (an invalid 0 never drags a mean down)."""
    from image2sim.simulator.io.registry import open_capture

    capture = open_capture(path)
    n = len(capture) if max_frames is None else min(len(capture), max_frames)
    out = []
    for i in range(n):
        frame = capture[i]
        if frame.camera.model != "equirect":
            raise ValueError(f"{path}: frame {i} is {frame.camera.model}; the renderer trains on panoramas")
        out.append(resize_target(frame.rgb, frame.depth, height, width))
    if not out:
        raise ValueError(f"{path}: capture has no frames")
    return out


def smooth_test_panorama(height: int, width: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth procedural panorama (room-like range, banded colours) for tests and demos."""
    g = torch.Generator().manual_seed(seed)
    rays = EquirectCamera(height, width).ray_map()
    x, y, z = rays
    # Box room 8 x 6 x 3 m around the camera: range to the nearest wall plane along each ray.
    half = torch.tensor([4.0, 1.5, 3.0]) + 0.5 * torch.rand(3, generator=g)
    t = torch.stack([half[i] / rays[i].abs().clamp_min(1e-6) for i in range(3)]).amin(0)
    phase = torch.rand(3, generator=g) * 2 * math.pi
    lon = torch.atan2(x, z)
    rgb = torch.stack([0.5 + 0.35 * torch.sin(3 * lon + phase[i] + 2 * y) for i in range(3)])
    return rgb, t[None]
