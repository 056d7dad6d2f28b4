"""Scene -> the renderer's 24-channel condition C_p at a target pose (splat, unpremultiply, concat)."""

from __future__ import annotations

import torch
from image2sim.simulator.gaussians.scene import GaussianScene, SceneError
from image2sim.simulator.geometry.cameras import Camera

__all__ = ["scene_condition"]


def scene_condition(
    scene: GaussianScene, camera: Camera, cam_to_world, backend: str = "auto", min_alpha: float = 1e-3
) -> torch.Tensor:
    """Splat ``scene`` at ``cam_to_world`` ((4, 4) or (B, 4, 4)) and build C_p ``(B, 24, H, W)``.

    RGB and depth are converted to the expected colour/range of the visible surface (not
    premultiplied), features are normalised by alpha the same way; a scene without features (the
    identity baseline) contributes zeros, a wider one is an error.
    """
    from image2sim.simulator.renderer.condition import build_condition, unpremultiply
    from image2sim.simulator.renderer.config import CONDITION_FEATURES

    if scene.feature_dim not in (0, CONDITION_FEATURES):
        raise SceneError(
            f"scene has {scene.feature_dim} feature channels; the renderer expects {CONDITION_FEATURES}"
        )
    out = scene.render(camera, cam_to_world, backend=backend)
    rgb, depth = unpremultiply(out.rgb, out.depth, out.alpha, 0.0, min_alpha)
    b, _, h, w = out.rgb.shape
    if scene.feature_dim:
        ok = out.alpha >= min_alpha
        feats = torch.where(ok, out.features / torch.where(ok, out.alpha, torch.ones_like(out.alpha)), 0.0)
    else:
        feats = out.rgb.new_zeros(b, CONDITION_FEATURES, h, w)
    rays = camera.ray_map(out.rgb.dtype, out.rgb.device)
    return build_condition(feats, rgb, depth, out.alpha, rays)
