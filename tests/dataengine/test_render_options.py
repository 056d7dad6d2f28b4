"""Observation rendering options of the data engine (renderer checkpoints need Gaussian rendering)."""

from __future__ import annotations

import pytest
from image2sim.dataengine.engine_config import EngineConfig


def test_renderer_needs_gaussian_rendering():
    with pytest.raises(ValueError, match="render=gaussians"):
        EngineConfig(renderer="r.safetensors", render="procedural")
    with pytest.raises(ValueError, match="render=gaussians"):
        EngineConfig(renderer="r.safetensors", render="none")
    assert EngineConfig(renderer="r.safetensors").render == "auto"
    EngineConfig(renderer="r.safetensors", render="gaussians", view="ultrawide")


@pytest.mark.parametrize(
    "field, value",
    [
        ("render", "magic"),
        ("view", "fisheye"),
        ("detector", "sonar"),
        ("per_scene", 0),
        ("obs_height", 4),
        ("frame_stride", 0),
        ("goal_view_distance", 0.0),
        ("goal_view_distance", float("nan")),
        ("device", "tpu"),
        ("refine_steps", -2),
    ],
)
def test_invalid_options_are_rejected(field, value):
    with pytest.raises(ValueError, match=f"EngineConfig.{field} must"):
        EngineConfig(**{field: value})


def test_unknown_config_keys_are_rejected():
    with pytest.raises(ValueError, match="unknown config key"):
        EngineConfig.from_dict({"per_scen": 3})
    assert EngineConfig.from_dict(EngineConfig(per_scene=3).to_dict()).per_scene == 3


class _PanoramicRecorder:
    """A panoramic render function (like the pixel-flow renderer) that records the cameras it gets."""

    panoramic = True

    def __init__(self) -> None:
        self.cameras = []

    def __call__(self, camera, cam_to_world):
        import numpy as np

        self.cameras.append(camera)
        return {
            "rgb": np.full((camera.height, camera.width, 3), 0.5, np.float32),
            "depth": np.ones((camera.height, camera.width), np.float32),
        }


@pytest.mark.parametrize(
    "view, obs_height, pano_height", [("pinhole", 64, 128), ("pinhole", 48, 96), ("ultrawide", 64, 98)]
)
def test_panoramic_renderers_render_at_the_stored_views_angular_resolution(view, obs_height, pano_height):
    """A 64 px, 90 degree pinhole view spans a quarter of a 256-wide panorama, so the data engine asks
    a panoramic renderer for a 128x256 panorama (the tiny renderer's training size), not the
    simulator's default 256x512, and DAgger's observations (navpolicy) ask for the same one."""
    import numpy as np
    from image2sim.dataengine.frames import observation_spec
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.navigation import synthetic as syn
    from image2sim.simulator.navigation.extract import extract_navmap_from_points
    from image2sim.simulator.sim import NeuralSimulator

    w = syn.box_room(spacing=0.08)
    navmap = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    cfg = EngineConfig(view=view, obs_height=obs_height)
    engine = _PanoramicRecorder()
    sim = NeuralSimulator(navmap, render_fn=engine, observations=observation_spec(cfg))
    obs, _ = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    (camera,) = engine.cameras
    assert isinstance(camera, EquirectCamera)
    assert (camera.height, camera.width) == (pano_height, 2 * pano_height)
    assert obs[0][view]["rgb"].shape[0] == obs_height
    if view == "pinhole":
        from image2sim.navpolicy.config import ObservationConfig
        from image2sim.navpolicy.rollout_scenes import render_observation

        dagger = _PanoramicRecorder()
        sim.render_fn = dagger
        frame = render_observation(sim, ObservationConfig(height=obs_height, width=obs_height))
        assert frame.shape == (obs_height, obs_height, 3)
        assert (dagger.cameras[0].height, dagger.cameras[0].width) == (camera.height, camera.width)
