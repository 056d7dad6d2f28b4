"""Per-image image metrics used by the renderer's training logs and evaluation command.

(The evaluation harness in ``image2sim.eval`` has the reference implementations; the simulator
cannot import it, so these are small self-contained versions with the same definitions.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["psnr_per_image", "ssim_per_image", "abs_rel"]


def psnr_per_image(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """PSNR (dB) per image of ``(B, C, H, W)`` tensors; MSE floored at 1e-10 (identical -> 100 dB)."""
    mse = (pred.double() - target.double()).pow(2).flatten(1).mean(1).clamp_min(1e-10)
    return 10.0 * torch.log10(data_range**2 / mse)


def _gaussian_window(size: int, sigma: float, dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_per_image(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, valid region)
    per image, averaged over channels."""
    x, y = pred.double(), target.double()
    c = x.shape[1]
    win = _gaussian_window(11, 1.5, x.dtype).expand(c, 1, 11, 11).contiguous()

    def filt(z):
        return F.conv2d(z, win, groups=c)

    mx, my = filt(x), filt(y)
    sxx, syy, sxy = filt(x * x) - mx * mx, filt(y * y) - my * my, filt(x * y) - mx * my
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.flatten(1).mean(1)


def abs_rel(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean |pred - gt| / gt over valid (gt > 0) pixels, per image (NaN when none is valid)."""
    valid = target > 0
    rel = torch.where(valid, (pred.double() - target.double()).abs() / target.double().clamp_min(1e-12), 0.0)
    return rel.flatten(1).sum(1) / valid.flatten(1).sum(1)
