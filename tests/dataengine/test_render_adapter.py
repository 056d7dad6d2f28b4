"""Pixel-flow renderer glue of the data engine: condition from a splat, deterministic output, guards."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from image2sim.dataengine.pipeline import EngineConfig, PixelFlowAdapter


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    from image2sim.simulator.renderer import tiny
    from image2sim.simulator.renderer.model import PixelFlowRenderer, load_renderer, save_renderer

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("r") / "renderer.safetensors"
    save_renderer(PixelFlowRenderer(tiny()), path)
    return load_renderer(path)


def _splat(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    return SimpleNamespace(
        rgb=torch.rand(1, 3, h, w, generator=g),
        depth=3 * torch.rand(1, 1, h, w, generator=g),
        alpha=torch.rand(1, 1, h, w, generator=g),
        features=torch.randn(1, 16, h, w, generator=g),
    )


def test_adapter_matches_direct_condition_and_render(renderer):
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.renderer.condition import build_condition

    out = _splat(16, 32)
    got = PixelFlowAdapter(renderer, seed=3)(out)
    cond = build_condition(out.features, out.rgb, out.depth, out.alpha, EquirectCamera(16, 32).ray_map())
    with torch.no_grad():
        want = renderer.render(cond, generator=torch.Generator().manual_seed(3)).rgb
    assert got.shape == (1, 3, 16, 32)
    torch.testing.assert_close(got, want)  # fresh generator per call: the same splat renders the same image


def test_adapter_refuses_non_panoramic_splats(renderer):
    with pytest.raises(ValueError, match="panoramic"):
        PixelFlowAdapter(renderer)(_splat(16, 16))


def test_renderer_option_needs_ultrawide_gaussians():
    with pytest.raises(ValueError, match="ultrawide"):
        EngineConfig(renderer="r.safetensors")
    with pytest.raises(ValueError, match="ultrawide"):
        EngineConfig(renderer="r.safetensors", view="ultrawide", render="procedural")
    EngineConfig(renderer="r.safetensors", view="ultrawide")
