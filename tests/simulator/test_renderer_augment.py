"""Panorama augmentations (renderer.augment) against the physics they claim: a rolled condition is
the splat of the house turned about the vertical axis, a mirrored one the splat of the mirrored
house; the ray map never moves; training with them is deterministic per seed."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.renderer.augment import (
    RAY_CHANNELS,
    augment_panorama_pair,
    sample_panorama_augmentation,
)
from image2sim.simulator.renderer.config import renderer_config_from_dict
from image2sim.simulator.renderer.splat_data import gaussians_condition

H, W = 16, 32


def _gaussians(means: torch.Tensor) -> SimpleNamespace:
    """Isotropic Gaussians (rotation-free footprints) with distinct colours."""
    n = means.shape[0]
    gen = torch.Generator().manual_seed(1)
    return SimpleNamespace(
        means=means,
        scales=torch.full((n, 3), 0.25, dtype=torch.float64),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(n, 4).contiguous(),
        opacities=torch.full((n,), 0.9, dtype=torch.float64),
        colors=torch.rand((n, 3), generator=gen, dtype=torch.float64),
        features=None,
    )


def _scene() -> torch.Tensor:
    """Camera-frame means on a ring around the camera (y down, lon = atan2(x, z)), some above and
    below the horizon, none near the poles."""
    gen = torch.Generator().manual_seed(0)
    lon = torch.rand(60, generator=gen, dtype=torch.float64) * 2 * math.pi - math.pi
    r = 2.0 + 2.0 * torch.rand(60, generator=gen, dtype=torch.float64)
    y = torch.rand(60, generator=gen, dtype=torch.float64) * 2.0 - 1.0
    return torch.stack((r * torch.sin(lon), y, r * torch.cos(lon)), dim=-1)


def _condition(means: torch.Tensor) -> torch.Tensor:
    return gaussians_condition(_gaussians(means), EquirectCamera(H, W), np.eye(4))[None]


def _turned(means: torch.Tensor, columns: int) -> torch.Tensor:
    """The house turned about the vertical axis so that longitudes grow by ``columns`` pixels."""
    a = 2 * math.pi * columns / W
    x, y, z = means.unbind(-1)
    return torch.stack((x * math.cos(a) + z * math.sin(a), y, -x * math.sin(a) + z * math.cos(a)), -1)


@pytest.mark.parametrize("columns", [1, 5, W - 3])
def test_roll_is_the_splat_of_the_turned_house(columns):
    means = _scene()
    base = _condition(means)
    shifts, mirror = torch.tensor([columns]), torch.tensor([False])
    moved, _ = augment_panorama_pair(base, (), shifts, mirror)
    torch.testing.assert_close(moved, _condition(_turned(means, columns)), atol=1e-5, rtol=1e-5)


def test_mirror_is_the_splat_of_the_mirrored_house_and_then_rolls():
    means = _scene()
    mirrored = means * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    base = _condition(means)
    moved, _ = augment_panorama_pair(base, (), torch.tensor([0]), torch.tensor([True]))
    torch.testing.assert_close(moved, _condition(mirrored), atol=1e-5, rtol=1e-5)
    moved, _ = augment_panorama_pair(base, (), torch.tensor([7]), torch.tensor([True]))
    torch.testing.assert_close(moved, _condition(_turned(mirrored, 7)), atol=1e-5, rtol=1e-5)


def test_targets_move_with_the_condition_and_the_ray_map_stays():
    gen = torch.Generator().manual_seed(2)
    cond = torch.rand((3, 24, H, W), generator=gen)
    rgb, depth = torch.rand((3, 3, H, W), generator=gen), torch.rand((3, 1, H, W), generator=gen)
    shifts, mirror = torch.tensor([0, 4, 9]), torch.tensor([False, True, False])
    moved, (rgb2, depth2) = augment_panorama_pair(cond, (rgb, depth), shifts, mirror)
    assert torch.equal(moved[:, RAY_CHANNELS], cond[:, RAY_CHANNELS])
    assert torch.equal(moved[0], cond[0]) and torch.equal(rgb2[0], rgb[0])
    assert torch.equal(rgb2[1], torch.roll(rgb[1].flip(-1), 4, -1))
    assert torch.equal(depth2[2], torch.roll(depth[2], 9, -1))
    assert torch.equal(moved[2, :21], torch.roll(cond[2, :21], 9, -1))
    # the input is not modified in place
    assert not torch.equal(moved, cond)


def test_sampling_is_reproducible_and_checks_its_inputs():
    a = sample_panorama_augmentation(64, W, True, 0.5, torch.Generator().manual_seed(3))
    b = sample_panorama_augmentation(64, W, True, 0.5, torch.Generator().manual_seed(3))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert 0 <= int(a[0].min()) and int(a[0].max()) < W and 0 < int(a[1].sum()) < 64
    shifts, mirror = sample_panorama_augmentation(8, W, False, 0.0, torch.Generator().manual_seed(3))
    assert not bool(shifts.any()) and not bool(mirror.any())
    with pytest.raises(ValueError, match="mirror_probability"):
        sample_panorama_augmentation(2, W, True, 1.5, torch.Generator())
    with pytest.raises(ValueError, match="condition must be"):
        augment_panorama_pair(
            torch.zeros(1, 5, H, W), (), torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.bool)
        )
    with pytest.raises(ValueError, match="augment.mirror_probability"):
        renderer_config_from_dict({"augment": {"mirror_probability": -0.1}})
