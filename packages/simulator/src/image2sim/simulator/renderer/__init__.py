"""Geometry-aware one-step pixel-flow renderer (paper: "Geometry-Aware One-Step Pixel Flow Rendering").

Takes the 24-channel condition C_p (splatted features, RGB, depth, alpha, target ray map) as a
tensor and returns a clean panoramic RGB-D observation; it does not depend on the splatting code.
"""

from image2sim.simulator.renderer.config import RendererConfig, load_renderer_config, paper, tiny

__all__ = ["RendererConfig", "load_renderer_config", "paper", "tiny", "PixelFlowRenderer", "build_condition"]


def __getattr__(name: str):
    # Lazy: importing the package (e.g. for configs) should not build torch modules.
    if name == "PixelFlowRenderer":
        from image2sim.simulator.renderer.model import PixelFlowRenderer

        return PixelFlowRenderer
    if name == "build_condition":
        from image2sim.simulator.renderer.condition import build_condition

        return build_condition
    raise AttributeError(name)
