"""Frames -> encoder inputs: resizing without flying points, pixel footprints, back-projection."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from image2sim.simulator.gaussians.primitives import FrameInputs
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, PinholeCamera
from image2sim.simulator.io.records import Frame

__all__ = ["resize_camera", "resize_rgbd", "prepare_frame", "pixel_footprint", "world_points"]


def resize_camera(camera: Camera, height: int, width: int) -> Camera:
    """The same camera at another resolution (pinhole intrinsics scale with the image; with pixel
    centres at integer + 0.5, cx scales exactly by width ratio)."""
    if isinstance(camera, EquirectCamera):
        return EquirectCamera(height, width)
    sx, sy = width / camera.width, height / camera.height
    return PinholeCamera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, height, width)


def resize_rgbd(
    rgb: torch.Tensor, depth: torch.Tensor, height: int, width: int, edge_tolerance: float = 0.1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-resize rgb (B, 3, h, w) and depth (B, 1, h, w) to (height, width).

    Colour is box-averaged. Depth is averaged over the *valid* pixels of each block only (an invalid
    0 never drags a mean down); a block whose valid depths spread by more than ``edge_tolerance`` of
    their mean straddles an occlusion edge, and keeps its nearest depth instead of a mean that would
    float between the two surfaces. Blocks with fewer than half valid pixels become invalid (0).
    """
    if rgb.shape[-2:] == (height, width):
        return rgb, depth
    valid = (depth > 0) & torch.isfinite(depth)
    clean = torch.where(valid, depth, torch.zeros_like(depth))
    rgb_s = F.adaptive_avg_pool2d(rgb, (height, width))
    vf = valid.to(depth.dtype)
    num = F.adaptive_avg_pool2d(clean * vf, (height, width))
    den = F.adaptive_avg_pool2d(vf, (height, width))
    mean = num / den.clamp_min(1e-12)
    big = torch.finfo(depth.dtype).max
    dmax = F.adaptive_max_pool2d(torch.where(valid, clean, torch.full_like(clean, -big)), (height, width))
    dmin = -F.adaptive_max_pool2d(torch.where(valid, -clean, torch.full_like(clean, -big)), (height, width))
    edge = (dmax - dmin) > edge_tolerance * mean
    out = torch.where(edge, dmin, mean)
    return rgb_s, torch.where(den >= 0.5, out, torch.zeros_like(out))


def prepare_frame(
    frame: Frame, height: int, width: int, edge_tolerance: float = 0.1, labels: bool = False
) -> FrameInputs:
    """A :class:`Frame` (uint8 RGB, float depth, pose) -> :class:`FrameInputs` at ``height x width``.

    ``labels``: also resize the frame's per-pixel categories (when it has them) into
    ``FrameInputs.labels``; only stage-1 training with a label target reads them, so fusion and
    condition builds skip the work."""
    rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb)).permute(2, 0, 1)[None].float() / 255.0
    depth = torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32))[None, None]
    rgb, depth = resize_rgbd(rgb, depth, height, width, edge_tolerance)
    pose = torch.as_tensor(np.asarray(frame.cam_to_world, dtype=np.float64))
    categories = None
    if labels and frame.semantics is not None:  # ids are categorical: nearest sample, never a blend
        sem = torch.from_numpy(np.ascontiguousarray(frame.semantics, dtype=np.float32))[None, None]
        categories = F.interpolate(sem, size=(height, width), mode="nearest-exact").long()
    return FrameInputs(
        rgb.contiguous(),
        depth.contiguous(),
        resize_camera(frame.camera, height, width),
        pose,
        frame.frame_id,
        categories,
    )


def pixel_footprint(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Metric size of each pixel on the observed surface, (..., H, W) like ``depth``.

    Panoramas: range x the latitudinal pixel angle pi/H (the longitudinal one, 2*pi*cos(lat)/W, is
    never larger for W = 2H, so neighbouring points are at most this far apart). Pinhole: z /
    sqrt(fx fy), the pixel spacing on a fronto-parallel plane.
    """
    if isinstance(camera, EquirectCamera):
        return depth * (math.pi / camera.height)
    return depth / math.sqrt(camera.fx * camera.fy)


def world_points(depth: torch.Tensor, camera: Camera, cam_to_world: torch.Tensor) -> torch.Tensor:
    """Depth (B, 1, H, W) -> world points (B, H, W, 3) with poses (B, 4, 4) (or one (4, 4))."""
    pts = camera.unproject(depth[:, 0])  # (B, H, W, 3) camera frame
    pose = cam_to_world.to(depth.dtype)
    if pose.ndim == 2:
        pose = pose.expand(depth.shape[0], 4, 4)
    R, t = pose[:, :3, :3], pose[:, :3, 3]
    return torch.einsum("bij,bhwj->bhwi", R, pts) + t[:, None, None, :]
