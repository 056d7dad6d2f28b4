"""SemanticAligner: condition C_p -> semantic tokens at H/16, aligned to a backbone's tokens.

Strided ``PanoConv2d`` stages bring the 24-channel condition to H/16, a 1x1 projection sets the
token width, a resolution-agnostic (angle-based) positional encoding is added, and transformer
blocks refine the tokens. When a semantic backbone (DINOv3) is configured, :func:`alignment_loss`
pulls the tokens towards the target panorama's backbone tokens by cosine similarity.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from image2sim.simulator.layers import LayerNorm2d, PanoConv2d, TransformerBlock, sincos_positional_encoding
from image2sim.simulator.renderer.config import CONDITION_CHANNELS, AlignerConfig
from torch import nn

__all__ = ["SemanticAligner", "alignment_loss"]


class SemanticAligner(nn.Module):
    """``(B, 24, H, W)`` condition -> ``(B, token_dim, H/16, W/16)`` tokens (H, W divisible by 16)."""

    def __init__(
        self, cfg: AlignerConfig, in_channels: int = CONDITION_CHANNELS, panoramic: bool = True
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.panoramic = panoramic
        stages: list[nn.Module] = []
        prev = in_channels
        for _i, width in enumerate(cfg.stem_widths):
            stages += [
                PanoConv2d(prev, width, 3, stride=1, panoramic=panoramic),
                LayerNorm2d(width),
                nn.GELU(),
            ]
            # 2x2 stride-2 conv: halves H and W exactly (no padding, so the seam stays aligned).
            stages.append(PanoConv2d(width, width, 2, stride=2, panoramic=panoramic))
            prev = width
        self.stem = nn.Sequential(*stages)
        self.to_tokens = nn.Conv2d(prev, cfg.token_dim, 1)
        self.blocks = nn.ModuleList(
            TransformerBlock(cfg.token_dim, cfg.heads, cfg.mlp_ratio) for _ in range(cfg.depth)
        )
        self.norm = LayerNorm2d(cfg.token_dim)
        self.head = (
            nn.Conv2d(cfg.token_dim, cfg.target_dim, 1)
            if cfg.target_dim is not None and cfg.target_dim != cfg.token_dim
            else nn.Identity()
        )

    def forward(self, condition: torch.Tensor) -> torch.Tensor:
        """Aligned tokens (the SemanticInjector's input)."""
        b, _, h, w = condition.shape
        if h % 16 or w % 16:
            raise ValueError(f"SemanticAligner needs H and W divisible by 16, got {h}x{w}")
        x = self.to_tokens(self.stem(condition))
        pe = sincos_positional_encoding(
            x.shape[-2], x.shape[-1], x.shape[1], self.panoramic, x.dtype, x.device
        )
        x = x + pe.unsqueeze(0)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)

    def project(self, tokens: torch.Tensor) -> torch.Tensor:
        """Map tokens to the semantic backbone's width for the alignment loss."""
        return self.head(tokens)


def alignment_loss(tokens: torch.Tensor, target: torch.Tensor, panoramic: bool = True) -> torch.Tensor:
    """Mean ``1 - cos`` between token maps ``(B, C, h, w)`` and backbone tokens ``(B, C, h', w')``.

    When the grids differ the predicted tokens are resampled to the target grid (bilinear, with
    the panorama seam wrapped so the first and last columns interpolate across it). The backbone
    tokens are constants (no gradient).
    """
    if tokens.shape[:2] != target.shape[:2]:
        raise ValueError(
            f"alignment_loss: tokens {tuple(tokens.shape)} and target {tuple(target.shape)} "
            "differ in batch/channels"
        )
    if tokens.shape[-2:] != target.shape[-2:]:
        tokens = _resize_tokens(tokens, target.shape[-2:], panoramic)
    cos = F.cosine_similarity(tokens.float(), target.detach().float(), dim=1, eps=1e-6)
    return (1.0 - cos).mean()


def _resize_tokens(x: torch.Tensor, size: tuple[int, int], panoramic: bool) -> torch.Tensor:
    """Bilinear resize (pixel-centre aligned); along width the panorama wraps around the seam."""
    if not panoramic:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    x = F.interpolate(x, size=(size[0], x.shape[-1]), mode="bilinear", align_corners=False)
    w, out_w = x.shape[-1], size[1]
    src = (torch.arange(out_w, dtype=torch.float64) + 0.5) * (w / out_w) - 0.5
    left = torch.floor(src)
    frac = (src - left).to(x.dtype).to(x.device)
    i0 = left.long().remainder(w).to(x.device)
    i1 = (i0 + 1).remainder(w)
    return x[..., i0] * (1.0 - frac) + x[..., i1] * frac
