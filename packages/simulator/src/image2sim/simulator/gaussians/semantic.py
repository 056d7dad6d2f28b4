"""Semantic stream: a frozen DINOv3 ViT (transformers) with hand-written preprocessing, or none.

Preprocessing is written here because the transformers DINOv3 image processor needs torchvision:
resize (bilinear, antialiased) to a multiple of the patch size, then ImageNet mean/std. The model
is loaded only from a local folder (``local_files_only``); nothing is ever downloaded.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from image2sim.simulator.gaussians.config import ConfigError, SemanticConfig
from torch import nn

__all__ = ["DinoV3Backbone", "build_semantic", "preprocess"]


def preprocess(
    rgb: torch.Tensor, patch_size: int, mean, std, size: tuple[int, int] | None = None
) -> torch.Tensor:
    """RGB (B, 3, H, W) in [0, 1] -> normalised pixels at ``size`` (default: H, W rounded to the nearest
    multiple of ``patch_size``, at least one patch)."""
    h, w = rgb.shape[-2:]
    if size is None:
        size = (
            max(patch_size, round(h / patch_size) * patch_size),
            max(patch_size, round(w / patch_size) * patch_size),
        )
    x = rgb
    if tuple(size) != (h, w):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
    m = x.new_tensor(mean).view(1, 3, 1, 1)
    s = x.new_tensor(std).view(1, 3, 1, 1)
    return (x - m) / s


class DinoV3Backbone(nn.Module):
    """Frozen DINOv3 ViT: RGB (B, 3, H, W) -> patch tokens (B, D, H/p, W/p).

    Parameters never require gradients and the module stays in eval mode (``train()`` is a no-op
    for it), so training the encoder cannot change it.
    """

    def __init__(self, model: nn.Module, cfg: SemanticConfig) -> None:
        super().__init__()
        self.model = model
        self.patch_size = int(model.config.patch_size)
        self.num_register_tokens = int(getattr(model.config, "num_register_tokens", 0))
        self.dim = int(model.config.hidden_size)
        self.mean, self.std = tuple(cfg.mean), tuple(cfg.std)
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.model.eval()

    def train(self, mode: bool = True) -> DinoV3Backbone:  # frozen: always eval
        super().train(False)
        return self

    @torch.no_grad()
    def forward(self, rgb: torch.Tensor, size: tuple[int, int] | None = None) -> torch.Tensor:
        x = preprocess(rgb.float(), self.patch_size, self.mean, self.std, size)
        h, w = x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size
        hidden = self.model(pixel_values=x).last_hidden_state
        patches = hidden[:, 1 + self.num_register_tokens :]
        if patches.shape[1] != h * w:
            raise RuntimeError(f"DINOv3 returned {patches.shape[1]} patch tokens, expected {h}x{w}")
        return patches.reshape(x.shape[0], h, w, self.dim).permute(0, 3, 1, 2).to(rgb.dtype).contiguous()


def build_semantic(cfg: SemanticConfig, model: nn.Module | None = None) -> DinoV3Backbone | None:
    """The configured semantic stream: None for ``none``; for ``dinov3`` the given ``model`` (tests pass a
    tiny random ``DINOv3ViTModel``) or ``DINOv3ViTModel.from_pretrained(cfg.weights)`` from a local folder."""
    if cfg.backbone == "none":
        return None
    if model is None:
        if not cfg.weights:
            raise ConfigError(
                "semantic.backbone is 'dinov3' but semantic.weights (a local model folder) is not set"
            )
        from pathlib import Path

        path = Path(cfg.weights)
        if not (path / "config.json").is_file():
            raise ConfigError(
                f"semantic.weights: {path} is not a local transformers model folder (no config.json)"
            )
        from transformers import DINOv3ViTModel

        model = DINOv3ViTModel.from_pretrained(str(path), local_files_only=True)
    backbone = DinoV3Backbone(model, cfg)
    if backbone.dim != cfg.dim:
        raise ConfigError(f"semantic.dim is {cfg.dim} but the DINOv3 model has hidden_size {backbone.dim}")
    if backbone.patch_size != cfg.patch_size:
        raise ConfigError(f"semantic.patch_size is {cfg.patch_size} but the model uses {backbone.patch_size}")
    return backbone
