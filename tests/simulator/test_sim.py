"""NeuralSimulator and the Gymnasium-style NavEnv with injected (analytic) renderers."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from image2sim.simulator.conventions import Action
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.embodiment import ConfigError
from image2sim.simulator.navigation.extract import extract_navmap_from_points
from image2sim.simulator.sim import GaussianRenderFn, NavEnv, NeuralSimulator, ObservationSpec


@functools.cache
def navmap():
    w = syn.box_room(spacing=0.04)
    return extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)


class RecordingRenderer:
    """Renders the camera's world-frame ray directions' z (rgb) and a constant depth; records calls."""

    def __init__(self) -> None:
        self.calls = []

    def __call__(self, camera, cam_to_world):
        self.calls.append((camera, np.array(cam_to_world)))
        rays = camera.ray_map().permute(1, 2, 0).numpy()
        world = rays @ np.asarray(cam_to_world)[:3, :3].T
        rgb = np.repeat(((world[..., 2:3] + 1) / 2).astype(np.float32), 3, axis=2)
        u = np.broadcast_to(np.arange(camera.width, dtype=np.float32), (camera.height, camera.width))
        return {"rgb": rgb, "depth": u.copy()}


def test_batch_step_info_and_collisions():
    sim = NeuralSimulator(navmap())
    _, info = sim.reset(np.array([[3.0, 2.0, 0.0], [5.7, 2.0, 0.0]]), np.array([0.0, 0.0]), observe=False)
    assert info["position"].shape == (2, 3) and not info["collided"].any()
    obs, info = sim.step([Action.MOVE_FORWARD, Action.MOVE_FORWARD])
    assert obs == [None, None]  # no render function
    assert info["collided"].tolist() == [False, True]
    assert info["position"][0, 0] == pytest.approx(3.25)
    _, info = sim.step([Action.TURN_LEFT, Action.STOP], observe=False)
    assert info["heading"][0] == pytest.approx(math.radians(15))
    with pytest.raises(ValueError, match="actions"):
        sim.step([1])
    with pytest.raises(ValueError, match="not one of"):
        sim.step([1, 7])


def test_observations_are_selectable_and_posed_at_eye_height():
    r = RecordingRenderer()
    spec = ObservationSpec(
        panorama=True,
        pano_height=32,
        pinhole=True,
        pinhole_size=24,
        ultrawide=True,
        ultrawide_width=40,
        ultrawide_height=26,
    )
    sim = NeuralSimulator(navmap(), render_fn=r, observations=spec)
    obs, _ = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([math.pi / 2]))
    o = obs[0]
    assert o["panorama"]["rgb"].shape == (32, 64, 3)
    assert o["pinhole"]["rgb"].shape == (24, 24, 3)
    assert o["ultrawide"]["rgb"].shape == (26, 40, 3)
    cams = [c for c, _ in r.calls]
    assert isinstance(cams[0], EquirectCamera) and isinstance(cams[1], PinholeCamera)
    pose = r.calls[0][1]
    assert np.allclose(pose[:3, 3], [3.0, 2.0, 1.25])
    assert np.allclose(pose[:3, 2], [0.0, 1.0, 0.0], atol=1e-12)  # looks along the heading (+Y)
    # The ultra-wide crop spans +-90 degrees around the centre column of the panorama.
    u = o["ultrawide"]["depth"]
    assert u[0, 0] == pytest.approx(16, abs=1.0) and u[0, -1] == pytest.approx(47, abs=1.0)
    obs, _ = sim.step([Action.TURN_LEFT], observe=False)
    assert obs is None


def test_gaussian_render_fn_goes_through_splat():
    torch = pytest.importorskip("torch")
    pytest.importorskip("image2sim.simulator.splatting")
    g = {
        "means": torch.tensor([[4.0, 2.0, 1.25]], dtype=torch.float32),
        "scales": torch.full((1, 3), 0.3),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        "opacities": torch.tensor([0.9]),
        "colors": torch.tensor([[1.0, 0.0, 0.0]]),
    }
    sim = NeuralSimulator(
        navmap(), render_fn=GaussianRenderFn(g, backend="torch"), observations=ObservationSpec(pano_height=16)
    )
    obs, _ = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    pano = obs[0]["panorama"]
    assert pano["rgb"].shape == (16, 32, 3)
    centre = pano["rgb"][8, 16]
    assert centre[0] > 0.5 and centre[1] < 0.3  # the red Gaussian straight ahead
    assert pano["depth"][8, 16] == pytest.approx(1.0, abs=0.2)
    assert pano["rgb"][8, 0, 0] < 0.1  # behind the agent: background
    # At the Gaussian's fringe (alpha < 0.5) the default image shows its colour, not a darkened one.
    fringe = (pano["rgb"][..., 0] > 0.9) & (pano["rgb"].sum(-1) < 1.1)
    raw_fn = GaussianRenderFn(g, backend="torch", mode="raw")
    raw = NeuralSimulator(navmap(), render_fn=raw_fn, observations=ObservationSpec(pano_height=16))
    raw_obs, _ = raw.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    raw_red = raw_obs[0]["panorama"]["rgb"][..., 0]
    assert (fringe & (raw_red < 0.5)).any()  # partly covered pixels: raw darkens them towards black
    assert np.allclose(raw_obs[0]["panorama"]["depth"], pano["depth"], atol=1e-5)
    with pytest.raises(ValueError, match="mode must be one of"):
        GaussianRenderFn(g, mode="premultiplied")


def test_nav_env_reward_and_termination():
    sim = NeuralSimulator(navmap())
    env = NavEnv(sim, max_steps=3)
    _, info = env.reset(np.array([2.0, 2.0, 0.0]), 0.0, np.array([4.0, 2.0, 0.0]))
    assert info["distance_to_goal"] == pytest.approx(2.0, abs=0.08)
    _, reward, term, trunc, info = env.step(Action.MOVE_FORWARD)
    assert reward == pytest.approx(0.25 - 0.01, abs=0.02) and not term and not trunc
    env.step(Action.TURN_LEFT)
    _, _, term, trunc, _ = env.step(Action.TURN_RIGHT)
    assert trunc and not term
    env.reset(np.array([3.9, 2.0, 0.0]), 0.0, np.array([4.0, 2.0, 0.0]))
    _, reward, term, _, info = env.step(Action.STOP)
    assert term and info["success"] and reward > 2.0


def test_observation_spec_validation():
    with pytest.raises(ConfigError, match="unknown"):
        ObservationSpec.from_dict({"panorama_size": 3})
    with pytest.raises(ConfigError, match="pinhole_hfov"):
        ObservationSpec(pinhole_hfov_deg=180.0)
