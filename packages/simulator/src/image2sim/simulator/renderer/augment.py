"""Panorama training augmentations that keep a (condition, target) pair consistent (pure functions).

An equirectangular panorama turned about the vertical axis is the same capture seen by a camera
with another yaw: its columns shift circularly. Mirrored left-right it is a capture of the mirrored
house. Both are exact for every channel of the condition except the target ray map, which is a
property of the camera and not of the scene: rotating or mirroring the *scene content* while the ray
map stays put is the same as observing the rotated / mirrored house from the original camera. So
the ray map channels are left untouched and everything else (features, RGB, range, alpha, targets)
moves together. Range is invariant under both, so depth needs no other change.

Why: a capture holds tens of panoramas, and the renderer's training pairs are its frames (the demo
trains on 27). Rolls and mirrors give every pair W x 2 variants without rendering anything, and
they exist for real captures as much as for procedural ones.
"""

from __future__ import annotations

import torch
from image2sim.simulator.renderer.config import CONDITION_CHANNELS

__all__ = ["RAY_CHANNELS", "sample_panorama_augmentation", "augment_panorama_pair"]

RAY_CHANNELS = slice(CONDITION_CHANNELS - 3, CONDITION_CHANNELS)
"""The condition's target ray map (camera frame): fixed by the camera, never moved."""


def sample_panorama_augmentation(
    batch: int, width: int, roll: bool, mirror_probability: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample column shifts in [0, width) (zeros without ``roll``) and mirror flags."""
    if not 0.0 <= float(mirror_probability) <= 1.0:
        raise ValueError(f"mirror_probability must lie in [0, 1], got {mirror_probability}")
    shifts = (
        torch.randint(0, int(width), (batch,), generator=generator)
        if roll
        else torch.zeros(batch, dtype=torch.long)
    )
    mirror = torch.rand(batch, generator=generator) < float(mirror_probability)
    return shifts, mirror


def _move(x: torch.Tensor, shifts: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """Mirror (columns reversed) where flagged, then roll each sample by its shift along width."""
    x = torch.where(mirror.view(-1, *([1] * (x.dim() - 1))), x.flip(-1), x)
    if not bool((shifts != 0).any()):
        return x
    width = x.shape[-1]
    cols = (torch.arange(width, device=x.device).view(1, width) - shifts.view(-1, 1).to(x.device)) % width
    index = cols.view(x.shape[0], *([1] * (x.dim() - 2)), width).expand_as(x)
    return torch.gather(x, -1, index)


def augment_panorama_pair(
    condition: torch.Tensor,
    targets: tuple[torch.Tensor, ...],
    shifts: torch.Tensor,
    mirror: torch.Tensor,
) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """Roll / mirror a batch of conditions ``(B, 24, H, W)`` and its per-pixel targets (each
    ``(B, C, H, W)``) together; the condition's ray map stays as it is (see the module docstring).

    Column ``j`` of a sample rolled by ``s`` holds what column ``(j - s) mod W`` held, as
    ``torch.roll(x, s, dims=-1)`` would; a mirrored sample is reversed along width before rolling.
    """
    if condition.dim() != 4 or condition.shape[1] != CONDITION_CHANNELS:
        raise ValueError(f"condition must be (B, {CONDITION_CHANNELS}, H, W), got {tuple(condition.shape)}")
    b = condition.shape[0]
    if shifts.shape != (b,) or mirror.shape != (b,):
        raise ValueError(
            f"shifts and mirror need shape ({b},), got {tuple(shifts.shape)}, {tuple(mirror.shape)}"
        )
    for t in targets:
        if t.shape[0] != b or t.shape[-1] != condition.shape[-1]:
            raise ValueError(
                f"target of shape {tuple(t.shape)} does not match condition {tuple(condition.shape)}"
            )
    moved = _move(condition, shifts, mirror)
    moved[:, RAY_CHANNELS] = condition[:, RAY_CHANNELS]
    return moved, tuple(_move(t, shifts, mirror) for t in targets)
