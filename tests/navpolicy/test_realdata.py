"""Real HM3D panoramas through the policy's observation settings, collator and model."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.config import ObservationConfig
from image2sim.navpolicy.data import Trajectory, make_sample, observation_from_panorama
from image2sim.navpolicy.model import make_image_processor
from image2sim.navpolicy.prompting import PromptBuilder


def _pano(scene_dir, k: int) -> np.ndarray:
    import cv2

    bgr = cv2.imread(str(scene_dir / f"{k:05d}_rgb.png"), cv2.IMREAD_COLOR)
    assert bgr is not None
    return np.ascontiguousarray(bgr[..., ::-1])


@pytest.mark.realdata
@pytest.mark.parametrize(
    "obs",
    [
        ObservationConfig(camera="pinhole", height=64, width=64, hfov_deg=90.0, vfov_deg=90.0),
        ObservationConfig(camera="equirect", height=64, width=96, hfov_deg=180.0, vfov_deg=118.0),
    ],
    ids=["pinhole-90", "ultrawide-180x118"],
)
def test_real_panoramas_train_step(hm3d_scene_dir, tiny_policy, tiny_cfg, obs):
    pano = _pano(hm3d_scene_dir, 0)
    H, W = pano.shape[:2]
    views = [observation_from_panorama(pano, yaw, obs) for yaw in (0.0, 15.0, 30.0, 45.0)]
    assert all(v.shape == (obs.height, obs.width, 3) and v.dtype == np.uint8 for v in views)
    # Yaw 0 looks at the panorama centre: the central pixel of the view is the central pixel there.
    c = views[0][obs.height // 2 - 1 : obs.height // 2 + 1, obs.width // 2 - 1 : obs.width // 2 + 1].mean(
        (0, 1)
    )
    ref = pano[H // 2 - 2 : H // 2 + 2, W // 2 - 2 : W // 2 + 2].mean((0, 1))
    assert np.abs(c - ref).max() < 40
    assert not np.array_equal(views[0], views[1])  # turning changes the view
    traj = Trajectory("walk into the kitchen and stop", [3, 3, 3, 0], np.stack(views), [0, 1, 2, 3])
    pol = copy.copy(tiny_policy)
    pol.image_processor = make_image_processor(obs, tiny_cfg.model.tiny.patch_size)
    col = NavCollator(PromptBuilder(pol.tokenizer, pol.codec, tiny_cfg.system_prompt), pol.image_processor)
    batch = col([make_sample(traj)])
    grid = batch["image_grid_thw"]
    assert grid.shape == (4, 3) and int(grid[0, 1]) * 8 == obs.height and int(grid[0, 2]) * 8 == obs.width
    model = copy.deepcopy(pol.model).train()
    out = model(**batch)
    out.loss.backward()
    assert torch.isfinite(out.loss)
