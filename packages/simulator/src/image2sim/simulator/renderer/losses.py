"""Renderer losses other than the flow and distillation terms.

* :func:`reconstruction_loss`  L1 on RGB plus L1 on valid (> 0) depth
* :func:`saturation_penalty`   squared excess of a colour estimate outside [0, 1]
* :class:`LPIPS`               LPIPS (VGG16 + learned linear heads) in plain torch; weights are
                               read from a user-supplied file, never downloaded
* :func:`load_lpips`           builds LPIPS from a configured path, or warns once and returns None
                               (the caller then sets lambda_perc = 0)
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "reconstruction_loss",
    "saturation_penalty",
    "LPIPS",
    "load_lpips",
    "VGG16_LAYERS",
    "LPIPS_CHANNELS",
]

log = logging.getLogger(__name__)

# torchvision's vgg16().features layout: conv indices, 'M' = max-pool (indices count every module).
VGG16_LAYERS: tuple = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
LPIPS_CHANNELS: tuple[int, ...] = (64, 128, 256, 512, 512)
_TAPS = (3, 8, 15, 22, 29)  # module indices of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3


def reconstruction_loss(
    pred_rgb: torch.Tensor,
    pred_depth: torch.Tensor,
    target_rgb: torch.Tensor,
    target_depth: torch.Tensor,
    rgb_weight: float = 1.0,
    depth_weight: float = 1.0,
) -> torch.Tensor:
    """``rgb_weight * mean|dRGB| + depth_weight * mean_{valid}|dD|``; depth is compared only
    where the target is valid (> 0 and finite), and an image without valid depth contributes 0."""
    rgb = (pred_rgb.float() - target_rgb.float()).abs().mean()
    valid = (target_depth > 0) & torch.isfinite(target_depth)
    diff = (pred_depth.float() - torch.where(valid, target_depth, 0).float()).abs() * valid
    depth = diff.sum() / valid.sum().clamp_min(1)
    return rgb_weight * rgb + depth_weight * depth


def saturation_penalty(x: torch.Tensor, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
    """mean(relu(low - x)^2 + relu(x - high)^2): zero inside the valid colour range."""
    x = x.float()
    return (F.relu(low - x).pow(2) + F.relu(x - high).pow(2)).mean()


class LPIPS(nn.Module):
    """Learned Perceptual Image Patch Similarity with a VGG16 trunk (Zhang et al. 2018).

    Weights come from one ``.safetensors`` file with torchvision VGG16 names
    (``features.{i}.weight/bias``) and the official LPIPS linear heads (``lin{k}.model.1.weight``,
    k = 0..4); see :meth:`load_weights`. Inputs are images in [0, 1], ``(B, 3, H, W)``; output is
    the per-image distance ``(B,)``. Parameters are frozen.
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        prev = 3
        for item in VGG16_LAYERS:
            if item == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(prev, int(item), 3, padding=1), nn.ReLU(inplace=False)]
                prev = int(item)
        self.features = nn.Sequential(*layers)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def state_dict_names(self) -> list[str]:
        """Names expected in a weight file."""
        names = [
            f"features.{i}.{p}"
            for i, m in enumerate(self.features)
            if isinstance(m, nn.Conv2d)
            for p in ("weight", "bias")
        ]
        return names + [f"lin{k}.model.1.weight" for k in range(len(self.lins))]

    def load_weights(self, path: str | Path) -> None:
        """Load a ``.safetensors`` (or ``.pt/.pth`` via ``torch.load(weights_only=True)``) file."""
        path = Path(path)
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            data = load_file(str(path))
        else:
            data = torch.load(path, map_location="cpu", weights_only=True)
        missing = [n for n in self.state_dict_names() if n not in data]
        if missing:
            raise ValueError(f"LPIPS weights {path}: missing {len(missing)} tensors, e.g. {missing[:3]}")
        with torch.no_grad():
            for i, m in enumerate(self.features):
                if isinstance(m, nn.Conv2d):
                    self._copy(m.weight, data[f"features.{i}.weight"], path, f"features.{i}.weight")
                    self._copy(m.bias, data[f"features.{i}.bias"], path, f"features.{i}.bias")
            for k, lin in enumerate(self.lins):
                self._copy(lin.weight, data[f"lin{k}.model.1.weight"], path, f"lin{k}.model.1.weight")

    @staticmethod
    def _copy(dst: torch.Tensor, src: torch.Tensor, path: Path, name: str) -> None:
        if tuple(src.shape) != tuple(dst.shape):
            raise ValueError(
                f"LPIPS weights {path}: {name} has shape {tuple(src.shape)}, expected {tuple(dst.shape)}"
            )
        dst.copy_(src.to(dst.dtype))

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, m in enumerate(self.features):
            x = m(x)
            if i in _TAPS:
                out.append(x)
                if i == _TAPS[-1]:
                    break
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        xa = ((a * 2.0 - 1.0) - self.shift) / self.scale
        xb = ((b * 2.0 - 1.0) - self.shift) / self.scale
        total = a.new_zeros(a.shape[0])
        for fa, fb, lin in zip(self._taps(xa), self._taps(xb), self.lins, strict=False):
            na = fa * torch.rsqrt(fa.pow(2).sum(1, keepdim=True) + 1e-20)
            nb = fb * torch.rsqrt(fb.pow(2).sum(1, keepdim=True) + 1e-20)
            total = total + lin((na - nb).pow(2)).mean(dim=(1, 2, 3))
        return total


_warned: set[str] = set()


def load_lpips(path: str | Path | None) -> LPIPS | None:
    """LPIPS with weights from ``path``; None (after one warning per path) when no file is there.

    A file that exists but is malformed raises: a wrong file is a configuration error, not a
    reason to silently train without the perceptual term.
    """
    if path is None or not Path(path).is_file():
        key = str(path)
        if key not in _warned:
            _warned.add(key)
            log.warning(
                "LPIPS weights not found at %s: the perceptual loss is disabled (lambda_perc = 0). "
                "Supply a .safetensors file with torchvision VGG16 'features.*' and LPIPS 'lin*' tensors.",
                path,
            )
        return None
    model = LPIPS()
    model.load_weights(path)
    return model
