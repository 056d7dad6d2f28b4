"""The 24-channel condition C_p and the RGB-D flow state, and conversions between them.

Channel layout of C_p (fixed; every consumer slices with the constants here):
``[0:16]`` splatted features, ``[16:19]`` RGB in [0, 1], ``[19]`` depth in metres (range, 0 =
invalid), ``[20]`` alpha in [0, 1], ``[21:24]`` target ray map (unit directions, camera frame).
RGB and depth are the *expected* colour and range of the visible surface (not premultiplied by
alpha; the source state multiplies by alpha itself): convert a compositing splatter's output
with :func:`unpremultiply`.
The flow state is ``[RGB, depth / depth_scale]`` (4 channels).
"""

from __future__ import annotations

import torch
from image2sim.simulator.renderer.config import CONDITION_CHANNELS, CONDITION_FEATURES

__all__ = [
    "FEATURES",
    "RGB",
    "DEPTH",
    "ALPHA",
    "RAYS",
    "build_condition",
    "unpremultiply",
    "prior_state",
    "condition_alpha",
    "to_state",
    "from_state",
]

FEATURES = slice(0, CONDITION_FEATURES)
RGB = slice(CONDITION_FEATURES, CONDITION_FEATURES + 3)
DEPTH = slice(CONDITION_FEATURES + 3, CONDITION_FEATURES + 4)
ALPHA = slice(CONDITION_FEATURES + 4, CONDITION_FEATURES + 5)
RAYS = slice(CONDITION_FEATURES + 5, CONDITION_CHANNELS)


def _check(name: str, x: torch.Tensor, channels: int, ref: torch.Tensor | None) -> None:
    if x.dim() != 4 or x.shape[1] != channels:
        raise ValueError(f"build_condition: {name} must be (B, {channels}, H, W), got {tuple(x.shape)}")
    if ref is not None and (x.shape[0] != ref.shape[0] or x.shape[-2:] != ref.shape[-2:]):
        raise ValueError(
            f"build_condition: {name} {tuple(x.shape)} does not match features {tuple(ref.shape)}"
        )


def build_condition(
    features: torch.Tensor, rgb: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, ray_map: torch.Tensor
) -> torch.Tensor:
    """Concatenate the splat outputs and the target ray map into C_p ``(B, 24, H, W)``.

    ``ray_map`` may be ``(3, H, W)`` (e.g. ``EquirectCamera(h, w).ray_map()``) and is broadcast over
    the batch. Non-finite values (NaN/inf from degenerate splats) are replaced by 0 and alpha is
    clamped to [0, 1], so one bad Gaussian cannot poison the network.
    """
    _check("features", features, CONDITION_FEATURES, None)
    _check("rgb", rgb, 3, features)
    _check("depth", depth, 1, features)
    _check("alpha", alpha, 1, features)
    if ray_map.dim() == 3:
        ray_map = ray_map.unsqueeze(0).expand(features.shape[0], -1, -1, -1)
    _check("ray_map", ray_map, 3, features)
    cond = torch.cat((features, rgb, depth, alpha.clamp(0.0, 1.0), ray_map.to(features.dtype)), dim=1)
    return torch.nan_to_num(cond, nan=0.0, posinf=0.0, neginf=0.0)


def without_features(condition: torch.Tensor) -> torch.Tensor:
    """``condition`` with its projected feature channels zeroed (a copy): the renderer's
    "w/o semantic features" ablation, and what identity Gaussians give anyway."""
    out = condition.clone()
    out[:, FEATURES] = 0
    return out


def unpremultiply(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    background: float = 0.0,
    min_alpha: float = 1e-3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composited ``rgb = sum w c + (1 - alpha) bg`` and weighted ``depth = sum w rho`` ->
    expected colour and range ``(rgb - (1 - alpha) bg) / alpha``, ``depth / alpha``; 0 where
    ``alpha < min_alpha`` (nothing reliable was projected there)."""
    a = alpha.clamp(0.0, 1.0)
    ok = a >= min_alpha
    safe = torch.where(ok, a, torch.ones_like(a))
    colour = ((rgb - (1.0 - a) * background) / safe).clamp(0.0, 1.0)
    return torch.where(ok, colour, torch.zeros_like(colour)), torch.where(
        ok, depth / safe, torch.zeros_like(depth)
    )


def condition_alpha(condition: torch.Tensor) -> torch.Tensor:
    """Alpha channel ``(B, 1, H, W)`` of C_p."""
    return condition[:, ALPHA]


def to_state(rgb: torch.Tensor, depth: torch.Tensor, depth_scale: float) -> torch.Tensor:
    """RGB ``(B, 3, H, W)`` and metric depth ``(B, 1, H, W)`` -> flow state ``(B, 4, H, W)``."""
    return torch.cat((rgb, depth / depth_scale), dim=1)


def from_state(state: torch.Tensor, depth_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Flow state -> (RGB, metric depth)."""
    return state[:, :3], state[:, 3:4] * depth_scale


def prior_state(condition: torch.Tensor, depth_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(projected state X~, alpha) from C_p."""
    return to_state(condition[:, RGB], condition[:, DEPTH], depth_scale), condition[:, ALPHA]
