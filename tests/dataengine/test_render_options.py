"""Observation rendering options of the data engine (renderer checkpoints need Gaussian rendering)."""

from __future__ import annotations

import pytest
from image2sim.dataengine.pipeline import EngineConfig


def test_renderer_needs_gaussian_rendering():
    with pytest.raises(ValueError, match="render=gaussians"):
        EngineConfig(renderer="r.safetensors", render="procedural")
    with pytest.raises(ValueError, match="render=gaussians"):
        EngineConfig(renderer="r.safetensors", render="none")
    assert EngineConfig(renderer="r.safetensors").render == "auto"
    EngineConfig(renderer="r.safetensors", render="gaussians", view="ultrawide")


@pytest.mark.parametrize(
    "field, value", [("render", "magic"), ("view", "fisheye"), ("per_scene", 0), ("obs_height", 4)]
)
def test_invalid_options_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        EngineConfig(**{field: value})


def test_unknown_config_keys_are_rejected():
    with pytest.raises(ValueError, match="unknown config key"):
        EngineConfig.from_dict({"per_scen": 3})
    assert EngineConfig.from_dict(EngineConfig(per_scene=3).to_dict()).per_scene == 3
