"""Feed-forward feature-Gaussian encoder (paper appendix, Stage 1) and the ``identity`` baseline.

Learned path::

    input (10 ch: RGB, depth / depth_scale, SurfaceNormalEstimator normals, ray map)
      -> DetailEncoder pyramid at H, H/2, H/4, H/8 (PanoConv2d + PanoBlocks)
      -> bottleneck at H/16 (+ projected frozen DINOv3 patch tokens when configured)
      -> FeatureUpsampler: 4 x (PixelShuffleUpsample, concat skip, 1x1 fuse, PanoBlocks) to H
      -> heads: 16 features, 3 scales (bounded), 4 rotation residual, 1 opacity

Rotation = base rotation whose local z axis is the estimated surface normal (``point_normals``)
composed with a learned residual that starts at identity; scales start at ``scale_init`` x the pixel
footprint (the identity baseline) and stay inside [scale_min, scale_max]; colours are the input
pixels; means are unprojected deterministically from depth and moved to the world with the pose.

``identity`` (no weights): pixel colours, opacity 1, std = scale_init x footprint; by default a disc in
the surface plane (the learned path's base rotation), or an isotropic sphere (``identity_shape``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from image2sim.simulator.gaussians.config import EncoderConfig, FusionConfig, GaussianConfig
from image2sim.simulator.gaussians.frames import pixel_footprint, world_points
from image2sim.simulator.gaussians.primitives import FrameInputs, GaussianSet
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera
from image2sim.simulator.geometry.normals import point_normals, sobel_normals
from image2sim.simulator.geometry.se3 import matrix_to_quat, normalize_quat, quat_multiply
from image2sim.simulator.layers import PanoBlock, PanoConv2d, PixelShuffleUpsample
from torch import nn

__all__ = [
    "encoder_inputs",
    "sanitise_inputs",
    "normal_frame",
    "valid_pixels",
    "identity_gaussians",
    "DetailEncoder",
    "FeatureUpsampler",
    "GaussianHeads",
    "GaussianEncoder",
    "bounded_scales",
]

INPUT_CHANNELS = 10


def encoder_inputs(
    rgb: torch.Tensor, depth: torch.Tensor, camera: Camera, depth_scale: float
) -> torch.Tensor:
    """The 10-channel input (B, 10, H, W): RGB, depth / depth_scale, Sobel normals, unit ray map."""
    circular = isinstance(camera, EquirectCamera)
    normals = sobel_normals(depth, circular=circular)
    rays = camera.ray_map(depth.dtype, depth.device).expand(depth.shape[0], -1, -1, -1)
    return torch.cat((rgb, depth / depth_scale, normals, rays), dim=1)


def sanitise_inputs(rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Non-finite or non-positive depth -> 0 (invalid, as the readers mark missing depth) and
    non-finite colour -> 0. One NaN pixel would otherwise spread through the network's
    normalisation layers into every Gaussian of the frame."""
    depth = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
    return torch.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0), depth


def normal_frame(normals: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) whose third column is the unit normal (..., 3).

    Branchless orthonormal basis of Duff et al. (2017): continuous everywhere except across n_z = 0
    and exact for every unit normal (no singularity at +-z).
    """
    nx, ny, nz = normals.unbind(-1)
    sign = torch.where(nz >= 0, torch.ones_like(nz), -torch.ones_like(nz))
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    b1 = torch.stack((1.0 + sign * nx * nx * a, sign * b, -sign * nx), dim=-1)
    b2 = torch.stack((b, sign + ny * ny * a, -ny), dim=-1)
    return torch.stack((b1, b2, normals), dim=-1)


def valid_pixels(depth: torch.Tensor, fusion: FusionConfig) -> torch.Tensor:
    """Boolean (B, 1, H, W): finite depth inside [min_range, max_range] (metres along the stored depth)."""
    return torch.isfinite(depth) & (depth > 0) & (depth >= fusion.min_range) & (depth <= fusion.max_range)


def _flatten(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> (B*H*W, C)."""
    return x.permute(0, 2, 3, 1).reshape(-1, x.shape[1])


def _surface_frames(depth: torch.Tensor, camera: Camera, cam_to_world: torch.Tensor) -> torch.Tensor:
    """World rotations (B, H*W, 3, 3) whose local z is the ``point_normals`` surface normal (minus
    the viewing ray where the normal is unknown); ``cam_to_world`` is (4, 4) or (B, 4, 4)."""
    B = depth.shape[0]
    normals = point_normals(depth, camera)
    rays = camera.ray_map(depth.dtype, depth.device).expand(B, -1, -1, -1)
    normals = torch.where(normals.abs().sum(dim=1, keepdim=True) == 0, -rays, normals)
    R_base = normal_frame(normals.permute(0, 2, 3, 1).reshape(B, -1, 3))
    R_pose = cam_to_world[..., :3, :3].to(depth.dtype)
    return (R_pose[:, None] if R_pose.ndim == 3 else R_pose) @ R_base


def identity_gaussians(frame: FrameInputs, cfg: GaussianConfig) -> GaussianSet:
    """The non-learned baseline: one Gaussian per valid pixel, no features.

    Colour = pixel colour, std = ``encoder.scale_init`` x pixel footprint (clamped to the scale
    bounds), opacity 1, mean = depth back-projected into the world. ``encoder.identity_shape``
    ``sphere``: isotropic, identity rotation; ``disc``: that std in the surface plane and
    ``disc_thickness`` times it along the surface normal.
    """
    depth, camera, e = frame.depth, frame.camera, cfg.encoder
    valid = valid_pixels(depth, cfg.fusion)[:, 0].reshape(-1)
    pts = world_points(depth.double(), camera, frame.cam_to_world).reshape(-1, 3).to(depth.dtype)[valid]
    foot = pixel_footprint(depth, camera).reshape(-1)[valid]
    sigma = (foot * e.scale_init).clamp(e.scale_min, e.scale_max)
    n = pts.shape[0]
    if e.identity_shape == "disc":
        quats = matrix_to_quat(_surface_frames(depth, camera, frame.cam_to_world).reshape(-1, 3, 3)[valid])
        thin = (sigma * e.disc_thickness).clamp_min(e.scale_min)
        scales = torch.stack((sigma, sigma, thin), dim=-1)
    else:
        quats = torch.zeros(n, 4, dtype=depth.dtype, device=depth.device)
        quats[:, 0] = 1.0
        scales = sigma[:, None].expand(n, 3).contiguous()
    return GaussianSet(
        means=pts,
        scales=scales,
        quats=quats,
        opacities=torch.ones(n, dtype=depth.dtype, device=depth.device),
        colors=_flatten(frame.rgb)[valid].clamp(0, 1),
        features=torch.zeros(n, 0, dtype=depth.dtype, device=depth.device),
        footprints=foot,
        weights=torch.ones(n, dtype=depth.dtype, device=depth.device),
        levels=torch.zeros(n, dtype=torch.int64, device=depth.device),
    )


def bounded_scales(raw: torch.Tensor, footprint: torch.Tensor, cfg: EncoderConfig) -> torch.Tensor:
    """Scales in (scale_min, scale_max): ``smin + (smax - smin) sigmoid(logit(t0) + raw)`` where t0 puts
    raw = 0 at ``scale_init`` x footprint, so a zero-initialised head reproduces the identity baseline."""
    lo, hi = cfg.scale_min, cfg.scale_max
    t0 = ((footprint * cfg.scale_init - lo) / (hi - lo)).clamp(1e-4, 1 - 1e-4)
    return lo + (hi - lo) * torch.sigmoid(torch.logit(t0) + raw)


def _blocks(channels: int, n: int, cfg: EncoderConfig, panoramic: bool) -> nn.Sequential:
    return nn.Sequential(*[PanoBlock(channels, cfg.kernel_size, cfg.expansion, panoramic) for _ in range(n)])


class DetailEncoder(nn.Module):
    """Detail stream: the 10-channel input -> feature pyramid at H, H/2, H/4, H/8."""

    def __init__(self, cfg: EncoderConfig, panoramic: bool = True) -> None:
        super().__init__()
        w = cfg.detail_widths
        self.stem = nn.Sequential(PanoConv2d(INPUT_CHANNELS, w[0], 3, panoramic=panoramic), nn.GELU())
        self.downs = nn.ModuleList(
            nn.Sequential(PanoConv2d(w[i - 1], w[i], 3, stride=2, panoramic=panoramic), nn.GELU())
            for i in range(1, 4)
        )
        self.levels = nn.ModuleList(_blocks(w[i], cfg.blocks_per_stage, cfg, panoramic) for i in range(4))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = [self.levels[0](self.stem(x))]
        for down, blocks in zip(self.downs, self.levels[1:], strict=True):
            feats.append(blocks(down(feats[-1])))
        return feats


class FeatureUpsampler(nn.Module):
    """Fuses the H/16 bottleneck (semantic tokens and/or strided detail) with the detail pyramid
    over four PixelShuffle stages (H/8, H/4, H/2, H), each followed by PanoBlocks."""

    def __init__(self, cfg: EncoderConfig, semantic_dim: int | None, panoramic: bool = True) -> None:
        super().__init__()
        w, u, bw = cfg.detail_widths, cfg.upsampler_widths, cfg.bottleneck_width
        self.detail_down = PanoConv2d(w[3], bw, 3, stride=2, panoramic=panoramic)
        self.semantic_proj = nn.Conv2d(semantic_dim, bw, 1) if semantic_dim else None
        self.bottleneck = _blocks(bw, cfg.blocks_per_stage, cfg, panoramic)
        ins = (bw, *u[:3])
        skips = (w[3], w[2], w[1], w[0])
        self.ups = nn.ModuleList(PixelShuffleUpsample(ins[i], u[i], 2, panoramic=panoramic) for i in range(4))
        self.fuse = nn.ModuleList(nn.Conv2d(u[i] + skips[i], u[i], 1) for i in range(4))
        self.blocks = nn.ModuleList(_blocks(u[i], cfg.blocks_per_stage, cfg, panoramic) for i in range(4))

    def forward(self, pyramid: list[torch.Tensor], tokens: torch.Tensor | None) -> torch.Tensor:
        x = self.detail_down(pyramid[3])
        if self.semantic_proj is not None:
            if tokens is None:
                raise ValueError("FeatureUpsampler was built with a semantic stream but got no tokens")
            if tokens.shape[-2:] != x.shape[-2:]:
                tokens = F.interpolate(tokens, size=x.shape[-2:], mode="bilinear", align_corners=False)
            x = x + self.semantic_proj(tokens)
        x = self.bottleneck(x)
        for up, fuse, blocks, skip in zip(self.ups, self.fuse, self.blocks, pyramid[::-1], strict=True):
            x = blocks(fuse(torch.cat((up(x), skip), dim=1)))
        return x


class GaussianHeads(nn.Module):
    """1x1 heads: features (C), scale logits (3), rotation residual (4), opacity logit (1).

    Scale, rotation and opacity heads start at zero weights so the initial Gaussians are the
    identity baseline's (footprint-sized, normal-aligned, opacity ``opacity_init``)."""

    def __init__(self, channels: int, cfg: EncoderConfig) -> None:
        super().__init__()
        self.features = nn.Conv2d(channels, cfg.feature_dim, 1) if cfg.feature_dim else None
        self.geometry = nn.Conv2d(channels, 8, 1)
        nn.init.zeros_(self.geometry.weight)
        nn.init.zeros_(self.geometry.bias)
        self.opacity_bias = math.log(cfg.opacity_init / (1 - cfg.opacity_init))

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        g = self.geometry(x)
        b, _, h, w = x.shape
        feats = self.features(x) if self.features is not None else x.new_zeros(b, 0, h, w)
        return {
            "features": feats,
            "scale": g[:, 0:3],
            "rotation": g[:, 3:7],
            "opacity": g[:, 7:8] + self.opacity_bias,
        }


class GaussianEncoder(nn.Module):
    """Dual-stream encoder: frames -> per-pixel feature Gaussians in the world.

    ``semantic`` is a frozen backbone module (see :mod:`.semantic`) returning (B, D, H/16, W/16)
    tokens, or None for the detail-only setting.
    """

    def __init__(
        self, cfg: GaussianConfig, semantic: nn.Module | None = None, panoramic: bool = True
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.panoramic = bool(panoramic)
        e = cfg.encoder
        self.semantic = semantic
        sdim = getattr(semantic, "dim", None) if semantic is not None else None
        self.detail = DetailEncoder(e, panoramic)
        self.upsampler = FeatureUpsampler(e, sdim, panoramic)
        self.heads = GaussianHeads(e.upsampler_widths[3], e)

    def trainable_parameters(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def forward_maps(self, rgb: torch.Tensor, depth: torch.Tensor, camera: Camera) -> dict[str, torch.Tensor]:
        """Per-pixel raw head outputs for (B, 3, H, W) / (B, 1, H, W) inputs."""
        return self._maps(*sanitise_inputs(rgb, depth), camera)

    def _maps(self, rgb: torch.Tensor, depth: torch.Tensor, camera: Camera) -> dict[str, torch.Tensor]:
        """:meth:`forward_maps` of inputs already passed through :func:`sanitise_inputs`."""
        e = self.cfg.encoder
        if (rgb.shape[-2], rgb.shape[-1]) != (e.height, e.width):
            raise ValueError(
                f"GaussianEncoder expects {e.height}x{e.width} inputs, got {tuple(rgb.shape[-2:])}"
            )
        x = encoder_inputs(rgb, depth, camera, e.depth_scale)
        tokens = self.semantic(rgb) if self.semantic is not None else None
        return self.heads(self.upsampler(self.detail(x), tokens))

    def forward(self, frames: list[FrameInputs]) -> list[GaussianSet]:
        """Gaussians of every valid pixel of each frame (frames must share one camera)."""
        if not frames:
            return []
        camera = frames[0].camera
        rgb, depth = sanitise_inputs(torch.cat([f.rgb for f in frames]), torch.cat([f.depth for f in frames]))
        poses = torch.stack([f.cam_to_world for f in frames])
        maps = self._maps(rgb, depth, camera)
        return pixel_maps_to_gaussians(maps, rgb, depth, camera, poses, self.cfg)


def pixel_maps_to_gaussians(
    maps: dict[str, torch.Tensor],
    rgb: torch.Tensor,
    depth: torch.Tensor,
    camera: Camera,
    poses: torch.Tensor,
    cfg: GaussianConfig,
) -> list[GaussianSet]:
    """Head outputs -> one :class:`GaussianSet` per batch element (valid pixels only)."""
    e = cfg.encoder
    B = rgb.shape[0]
    dtype = rgb.dtype
    valid = valid_pixels(depth, cfg.fusion)[:, 0].reshape(B, -1)
    means = world_points(depth.double(), camera, poses).to(dtype).reshape(B, -1, 3)
    foot = pixel_footprint(depth, camera).reshape(B, -1)
    scales = bounded_scales(_flatten(maps["scale"]).reshape(B, -1, 3), foot[..., None], e)
    opac = torch.sigmoid(maps["opacity"]).reshape(B, -1)
    # Base rotation: local z along the metric surface normal, -ray where unknown.
    q_base = matrix_to_quat(_surface_frames(depth, camera, poses))
    residual = _flatten(maps["rotation"]).reshape(B, -1, 4)
    q_res = normalize_quat(residual + residual.new_tensor([1.0, 0.0, 0.0, 0.0]))
    quats = normalize_quat(quat_multiply(q_base, q_res))
    feats = maps["features"]
    feats = feats.permute(0, 2, 3, 1).reshape(B, -1, feats.shape[1])
    colors = rgb.permute(0, 2, 3, 1).reshape(B, -1, 3).clamp(0, 1)
    out = []
    for b in range(B):
        m = valid[b]
        n = int(m.sum())
        out.append(
            GaussianSet(
                means=means[b][m],
                scales=scales[b][m],
                quats=quats[b][m],
                opacities=opac[b][m],
                colors=colors[b][m],
                features=feats[b][m],
                footprints=foot[b][m],
                weights=torch.ones(n, dtype=dtype, device=rgb.device),
                levels=torch.zeros(n, dtype=torch.int64, device=depth.device),
            )
        )
    return out
