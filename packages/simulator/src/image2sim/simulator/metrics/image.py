"""Image-quality metrics in torch: PSNR, SSIM (Wang et al. 2004), depth AbsRel / RMSE / δ<1.25.

Image tensors are ``(..., C, H, W)`` (a 2-D ``(H, W)`` tensor is one single-channel image); every
metric reduces over ``(C, H, W)`` and returns a float64 tensor with the leading shape (a 0-d tensor
for a single image). Metrics are computed in float64 so that they do not depend on the input dtype.

:func:`psnr`, :func:`ssim`, :func:`depth_metrics` validate their inputs (NaN/inf, empty, shapes) and
are the evaluation definitions. The ``*_per_image`` variants and :func:`abs_rel` are the lenient
forms the renderer's training logs use on ``(B, C, H, W)`` batches: same definitions, but NaN
propagates instead of raising, PSNR is capped at 100 dB and an image without valid depth gives NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "SSIM_K1",
    "SSIM_K2",
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "DepthMetrics",
    "abs_rel",
    "depth_metrics",
    "gaussian_filter_valid",
    "gaussian_kernel_1d",
    "gaussian_window",
    "psnr",
    "psnr_per_image",
    "ssim",
    "ssim_map",
    "ssim_per_image",
]

SSIM_WINDOW = 11
"""Gaussian window size of SSIM (Wang et al. 2004)."""
SSIM_SIGMA = 1.5
"""Gaussian window standard deviation in pixels."""
SSIM_K1 = 0.01
"""Luminance stabiliser: C1 = (K1 * data_range)^2."""
SSIM_K2 = 0.03
"""Contrast stabiliser: C2 = (K2 * data_range)^2."""


def _as_images(x: torch.Tensor, name: str) -> torch.Tensor:
    """Validate an image tensor and return it as float64 ``(..., C, H, W)``."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 2:
        raise ValueError(f"{name}: expected (..., C, H, W) or (H, W), got shape {tuple(x.shape)}")
    if x.ndim == 2:
        x = x[None]
    if x.numel() == 0:
        raise ValueError(f"{name}: is empty (shape {tuple(x.shape)})")
    x = x.detach().to(torch.float64)
    # A finite sum proves every element finite and costs a fraction of an element-wise isfinite;
    # the full check only runs to tell overflow of the sum from a real NaN/inf.
    if not torch.isfinite(x.sum()) and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name}: contains NaN or inf")
    return x


def _pair(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    p, t = _as_images(pred, "pred"), _as_images(target, "target")
    if p.shape != t.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    return p, t


def _check_range(data_range: float) -> float:
    if not (math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range: must be a finite positive number, got {data_range!r}")
    return float(data_range)


def _as_mask(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Broadcast a boolean mask (``(..., 1 or C, H, W)`` or ``(H, W)``) to ``like``'s shape."""
    m = mask if mask.ndim != 2 else mask[None]
    if m.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor, got {m.dtype}")
    try:
        return torch.broadcast_to(m, like.shape)
    except RuntimeError:
        shapes = f"{tuple(mask.shape)} does not broadcast to {tuple(like.shape)}"
        raise ValueError(f"mask: shape {shapes}") from None


def psnr(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, data_range: float = 1.0
) -> torch.Tensor:
    """Peak signal-to-noise ratio ``10 log10(data_range^2 / MSE)`` in dB per image.

    With ``mask`` the MSE is taken over the selected pixels (all channels) only; an image whose mask
    selects nothing is an error. Identical images give ``+inf``.
    """
    data_range = _check_range(data_range)
    p, t = _pair(pred, target)
    diff = p - t
    sq = diff.mul_(diff).flatten(-3)  # one flat reduction is faster than over three dims
    if mask is None:
        mse = sq.mean(dim=-1)
    else:
        m = _as_mask(mask, p).to(torch.float64).flatten(-3)
        n = m.sum(dim=-1)
        if bool((n == 0).any()):
            bad = torch.nonzero(n == 0)[0].tolist()
            raise ValueError(f"mask: selects no pixel in image {bad}")
        mse = (sq * m).sum(dim=-1) / n
    return 10.0 * torch.log10(data_range**2 / mse)


def gaussian_kernel_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Normalised 1-D Gaussian kernel (float64)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return g / g.sum()


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Normalised 2-D Gaussian window ``(size, size)`` (outer product of the 1-D kernel), float64."""
    g = gaussian_kernel_1d(size, sigma)
    return g[:, None] * g[None, :]


def gaussian_filter_valid(x: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Separable filtering of the last two dims with a 1-D ``kernel``, valid region only.

    Written as weighted sums of shifted views: on CPU, float64 ``conv2d`` with an 11×11 kernel is
    an order of magnitude slower than these 2 × 11 in-place multiply-adds.
    """
    k = kernel.numel()
    weights = kernel.tolist()
    w_out = x.shape[-1] - k + 1
    rows = x[..., 0:w_out] * weights[0]
    for i in range(1, k):
        rows.add_(x[..., i : i + w_out], alpha=weights[i])
    h_out = x.shape[-2] - k + 1
    out = rows[..., 0:h_out, :] * weights[0]
    for i in range(1, k):
        out.add_(rows[..., i : i + h_out, :], alpha=weights[i])
    return out


def ssim_map(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Local SSIM ``(..., C, H-10, W-10)``: 11×11 Gaussian σ 1.5 statistics, valid region only.

    Population (biased) local variances, as in Wang et al.'s reference code; the output covers the
    positions where the whole window lies inside the image (no padding artefacts).
    """
    data_range = _check_range(data_range)
    p, t = _pair(pred, target)
    return _ssim_map_f64(p, t, data_range)


def _ssim_map_f64(p: torch.Tensor, t: torch.Tensor, data_range: float) -> torch.Tensor:
    """:func:`ssim_map` on float64 tensors of equal shape ``(..., C, H, W)`` (no NaN/inf check)."""
    h, w = p.shape[-2:]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"ssim: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {h}x{w}")
    lead = p.shape[:-2]
    x = p.reshape(-1, h, w)
    y = t.reshape(-1, h, w)
    # One filtering pass over the five stacked moments.
    stats = gaussian_filter_valid(torch.stack([x, y, x * x, y * y, x * y]), gaussian_kernel_1d())
    mx, my, exx, eyy, exy = stats.unbind(dim=0)
    vx, vy, cxy = exx - mx * mx, eyy - my * my, exy - mx * my
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.reshape(*lead, *s.shape[-2:])


def ssim(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM per image (Wang et al. 2004), averaged over the valid region and then over channels."""
    return ssim_map(pred, target, data_range).mean(dim=(-3, -2, -1))


@dataclass(frozen=True)
class DepthMetrics:
    """Per-image depth errors over valid pixels (target > 0 and finite, and inside the mask)."""

    abs_rel: torch.Tensor
    """mean(|pred - target| / target)."""
    rmse: torch.Tensor
    """sqrt(mean((pred - target)^2)) in metres."""
    delta1: torch.Tensor
    """Fraction of pixels with max(pred/target, target/pred) < threshold (1.25); pred <= 0 never counts."""
    count: torch.Tensor
    """Number of valid pixels per image."""


def depth_metrics(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    delta_threshold: float = 1.25,
) -> DepthMetrics:
    """AbsRel, RMSE and δ<``delta_threshold`` per image on valid pixels.

    Depth is ``(..., 1, H, W)`` or ``(H, W)`` in metres with 0 marking invalid pixels (see
    :mod:`image2sim.simulator.conventions`). A valid pixel is one where the target is finite and > 0
    and ``mask`` (if given) is true. A non-finite prediction on a valid pixel, or an image without any
    valid pixel, is an error naming the image index.
    """
    for name, x in (("pred", pred), ("target", target)):
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if pred.shape != target.shape:
        raise ValueError(f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    p = pred.detach().to(torch.float64)
    t = target.detach().to(torch.float64)
    if p.ndim == 2:
        p, t = p[None], t[None]
    if p.ndim < 3 or p.numel() == 0:
        raise ValueError(f"depth: expected (..., 1, H, W) or (H, W), got shape {tuple(pred.shape)}")
    valid = torch.isfinite(t) & (t > 0)
    if mask is not None:
        valid = valid & _as_mask(mask, p)
    dims = (-3, -2, -1)
    count = valid.sum(dim=dims)
    if bool((count == 0).any()):
        raise ValueError(f"depth: image {torch.nonzero(count == 0)[0].tolist()} has no valid target pixel")
    bad = valid & ~torch.isfinite(p)
    if bool(bad.any()):
        raise ValueError(f"depth: pred is NaN/inf on a valid pixel at index {torch.nonzero(bad)[0].tolist()}")
    # Zero out invalid pixels so that NaN/0 there cannot leak into the sums.
    t_safe = torch.where(valid, t, torch.ones_like(t))
    p_safe = torch.where(valid, p, torch.ones_like(p))
    err = p_safe - t_safe
    n = count.to(torch.float64)
    abs_rel = torch.where(valid, err.abs() / t_safe, 0.0).sum(dim=dims) / n
    rmse = torch.sqrt(torch.where(valid, err * err, 0.0).sum(dim=dims) / n)
    # max(p/t, t/p); a non-positive prediction is infinitely wrong.
    ratio = torch.where(
        p_safe > 0, torch.maximum(p_safe / t_safe, t_safe / p_safe.clamp_min(1e-300)), math.inf
    )
    delta1 = (valid & (ratio < delta_threshold)).sum(dim=dims).to(torch.float64) / n
    return DepthMetrics(abs_rel, rmse, delta1, count)


# ------------------------------------------------------------------ lenient per-image forms (training logs)


def _batch_f64(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Detached float64 copies of two ``(B, C, H, W)`` tensors of equal shape."""
    if pred.ndim != 4 or pred.shape != target.shape:
        shapes = f"{tuple(pred.shape)} and {tuple(target.shape)}"
        raise ValueError(f"expected two (B, C, H, W) tensors of equal shape, got {shapes}")
    return pred.detach().to(torch.float64), target.detach().to(torch.float64)


def psnr_per_image(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """PSNR (dB) per image of ``(B, C, H, W)`` tensors; MSE floored at 1e-10 (identical -> 100 dB
    for ``data_range`` 1) so that training logs stay finite. NaN inputs give NaN."""
    data_range = _check_range(data_range)
    p, t = _batch_f64(pred, target)
    mse = (p - t).pow(2).flatten(1).mean(1).clamp_min(1e-10)
    return 10.0 * torch.log10(data_range**2 / mse)


def ssim_per_image(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """:func:`ssim` per image of ``(B, C, H, W)`` tensors (mean over channels and the valid region);
    NaN inputs give NaN instead of raising."""
    data_range = _check_range(data_range)
    p, t = _batch_f64(pred, target)
    return _ssim_map_f64(p, t, data_range).mean(dim=(-3, -2, -1))


def abs_rel(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean ``|pred - gt| / gt`` over valid (gt > 0) pixels per image of ``(B, 1, H, W)`` depth
    (NaN for an image without a valid pixel; :func:`depth_metrics` raises there instead)."""
    p, t = _batch_f64(pred, target)
    valid = t > 0
    rel = torch.where(valid, (p - t).abs() / t.clamp_min(1e-12), 0.0)
    return rel.flatten(1).sum(1) / valid.flatten(1).sum(1)
