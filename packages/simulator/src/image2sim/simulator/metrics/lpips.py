"""LPIPS (Zhang et al. 2018), VGG16 variant, in plain torch, with weights loaded from local files.

One network for the renderer's perceptual loss (gradients flow to the inputs; parameters are
frozen) and for evaluation. No weights ship with the project and nothing is downloaded:
:func:`lpips_distance` returns ``None`` for a missing model so reports print "n/a" (LPIPS is never
reported as 0), and :func:`load_lpips_or_none` warns once and returns ``None`` for a missing file so
training runs with the perceptual term disabled.

Parameter names follow the reference implementation so its files load unchanged:
``net.slice{1..5}.{i}.weight|bias`` for the VGG16 convolutions (``i`` = index in torchvision's
``vgg16().features``) and ``lin{0..4}.model.1.weight`` for the learned 1×1 heads (the released
``vgg.pth``). A torchvision-style backbone file (``features.{i}.*``, ``classifier.*`` ignored) is
mapped onto the slices. Files: ``.safetensors`` or ``.pt/.pth/.bin`` read with
``torch.load(weights_only=True)`` (no pickle execution).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

__all__ = [
    "LPIPS",
    "LPIPS_CHANNELS",
    "VGG16_LAYERS",
    "LpipsWeightsError",
    "VGG16Taps",
    "load_lpips",
    "load_lpips_or_none",
    "lpips_distance",
    "read_state_dict",
    "unit_normalize",
]

log = logging.getLogger(__name__)

# VGG16 "D" configuration: conv widths, "M" = 2x2 max-pool. Indices below are torchvision's.
VGG16_LAYERS: tuple[int | str, ...] = (
    64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512,
)
"""torchvision's ``vgg16().features`` layout: conv widths and ``"M"`` max-pools (every module counts)."""
# LPIPS taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3: features[0:4], [4:9], [9:16], [16:23], [23:30].
_SLICE_BOUNDS: tuple[tuple[int, int], ...] = ((0, 4), (4, 9), (9, 16), (16, 23), (23, 30))
LPIPS_CHANNELS: tuple[int, ...] = (64, 128, 256, 512, 512)
"""Channels of the five tapped feature maps."""
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10


class LpipsWeightsError(ValueError):
    """A weight file is missing, unreadable, or does not match the network."""


def _vgg16_features() -> list[nn.Module]:
    """torchvision-compatible ``vgg16().features`` layer list (index = parameter-name index)."""
    layers: list[nn.Module] = []
    c_in = 3
    for item in VGG16_LAYERS:
        if item == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(c_in, int(item), kernel_size=3, padding=1), nn.ReLU(inplace=False)]
            c_in = int(item)
    layers.append(nn.MaxPool2d(kernel_size=2, stride=2))  # index 30, never reached by the taps
    return layers


class VGG16Taps(nn.Module):
    """VGG16 convolutional trunk returning the five LPIPS feature maps."""

    def __init__(self) -> None:
        super().__init__()
        layers = _vgg16_features()
        for k, (lo, hi) in enumerate(_SLICE_BOUNDS, start=1):
            block = nn.Sequential()
            for i in range(lo, hi):
                block.add_module(str(i), layers[i])
            setattr(self, f"slice{k}", block)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Feature maps after relu1_2, relu2_2, relu3_3, relu4_3, relu5_3."""
        taps = []
        for k in range(1, len(_SLICE_BOUNDS) + 1):
            x = getattr(self, f"slice{k}")(x)
            taps.append(x)
        return taps


class _LinearHead(nn.Module):
    """Non-negative-by-training 1×1 channel weighting; ``model.1`` keeps the reference's key names."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(p=0.0), nn.Conv2d(channels, 1, kernel_size=1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


def unit_normalize(features: torch.Tensor) -> torch.Tensor:
    """Normalise every pixel's feature vector to unit length (channel dim 1), as LPIPS does."""
    norm = torch.sqrt(torch.sum(features * features, dim=1, keepdim=True))
    return features / (norm + _EPS)


class LPIPS(nn.Module):
    """LPIPS distance: sum over taps of the spatial mean of ``w · (f̂(x) - f̂(y))²``."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.net = VGG16Taps()
        for k, c in enumerate(LPIPS_CHANNELS):
            setattr(self, f"lin{k}", _LinearHead(c))
        self.eval()
        self.requires_grad_(False)

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Distance per image ``(B,)`` for RGB images ``(B, 3, H, W)`` in [0, 1]."""
        if pred.shape != target.shape or pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(f"LPIPS: expected two (B, 3, H, W) tensors of equal shape, got "
                             f"{tuple(pred.shape)} and {tuple(target.shape)}")
        # [0, 1] -> [-1, 1] -> the reference's ImageNet-like scaling.
        x = ((2.0 * pred - 1.0) - self.shift) / self.scale
        y = ((2.0 * target - 1.0) - self.shift) / self.scale
        both = self.net(torch.cat([x, y], dim=0))
        b = pred.shape[0]
        total = pred.new_zeros(b)
        for k, f in enumerate(both):
            d = (unit_normalize(f[:b]) - unit_normalize(f[b:])) ** 2
            total = total + getattr(self, f"lin{k}")(d).mean(dim=(1, 2, 3))
        return total


# ------------------------------------------------------------------------------------------ loading

_TORCHVISION_FEATURE = re.compile(r"^features\.(\d+)\.(weight|bias)$")


def _slice_of(index: int) -> int | None:
    for k, (lo, hi) in enumerate(_SLICE_BOUNDS, start=1):
        if lo <= index < hi:
            return k
    return None


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a flat ``name -> tensor`` mapping from a safetensors or torch (weights-only) file."""
    path = Path(path)
    if not path.is_file():
        raise LpipsWeightsError(f"{path}: weight file not found")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            data: Any = load_file(str(path), device="cpu")
        elif path.suffix in (".pt", ".pth", ".bin"):
            data = torch.load(path, map_location="cpu", weights_only=True)
        else:
            raise LpipsWeightsError(
                f"{path}: unsupported suffix {path.suffix!r} (use .safetensors, .pt, .pth, .bin)"
            )
    except LpipsWeightsError:
        raise
    except Exception as exc:  # corrupt file, pickle refused by weights_only, ...
        raise LpipsWeightsError(f"{path}: cannot read weights ({type(exc).__name__}: {exc})") from exc
    if not isinstance(data, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in data.items()
    ):
        raise LpipsWeightsError(f"{path}: expected a flat mapping of parameter names to tensors")
    return dict(data)


def _canonical_key(key: str) -> str | None:
    """Map a file key onto this module's names; ``None`` = a known extra to ignore."""
    m = _TORCHVISION_FEATURE.match(key)
    if m:
        k = _slice_of(int(m.group(1)))
        return None if k is None else f"net.slice{k}.{m.group(1)}.{m.group(2)}"
    if key.startswith("classifier.") or key.startswith("scaling_layer.") or key in ("shift", "scale"):
        return None  # torchvision's classifier; constants we hold as buffers
    return key


def load_lpips(weights: str | Path, backbone_weights: str | Path | None = None) -> LPIPS:
    """Build :class:`LPIPS` from the head weights (or a full state dict) plus an optional backbone file.

    Every parameter must come from exactly one file with the right shape; unknown keys are errors.
    """
    model = LPIPS()
    expected = model.state_dict()
    merged: dict[str, tuple[torch.Tensor, Path]] = {}
    for file in (weights, backbone_weights):
        if file is None:
            continue
        for key, tensor in read_state_dict(file).items():
            name = _canonical_key(key)
            if name is None:
                continue
            if name not in expected:
                raise LpipsWeightsError(f"{file}: unexpected parameter {key!r} for LPIPS-VGG16")
            if name in merged:
                raise LpipsWeightsError(f"{file}: parameter {name!r} also given by {merged[name][1]}")
            if tuple(tensor.shape) != tuple(expected[name].shape):
                raise LpipsWeightsError(f"{file}: parameter {key!r} has shape {tuple(tensor.shape)}, "
                                        f"expected {tuple(expected[name].shape)}")
            merged[name] = (tensor, Path(file))
    missing = sorted(set(expected) - set(merged))
    if missing:
        files = [str(f) for f in (weights, backbone_weights) if f is not None]
        raise LpipsWeightsError(f"{files}: missing {len(missing)} LPIPS parameter(s), e.g. {missing[:4]}")
    model.load_state_dict({k: v.to(expected[k].dtype) for k, (v, _) in merged.items()}, strict=True)
    return model


@torch.no_grad()
def lpips_distance(pred: torch.Tensor, target: torch.Tensor, model: LPIPS | None) -> torch.Tensor | None:
    """LPIPS per image ``(B,)`` (float64), or ``None`` (n/a) when ``model`` is ``None``."""
    if model is None:
        return None
    if pred.ndim == 3:
        pred, target = pred[None], target[None]
        return model(pred.float(), target.float()).to(torch.float64)[0]
    return model(pred.float(), target.float()).to(torch.float64)


_warned: set[str] = set()


def load_lpips_or_none(path: str | Path | None) -> LPIPS | None:
    """:func:`load_lpips` from ``path``, or ``None`` after one warning per path when no file is there.

    The renderer then trains with ``lambda_perc = 0``. A file that exists but is malformed raises
    :class:`LpipsWeightsError`: a wrong file is a configuration error, not a reason to silently train
    without the perceptual term.
    """
    if path is None or not Path(path).is_file():
        key = str(path)
        if key not in _warned:
            _warned.add(key)
            log.warning(
                "LPIPS weights not found at %s: the perceptual loss is disabled (lambda_perc = 0). "
                "Supply a .safetensors file with VGG16 'features.*' (or 'net.slice*') and LPIPS "
                "'lin*.model.1.weight' tensors.",
                path,
            )
        return None
    return load_lpips(path)
