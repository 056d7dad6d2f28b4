"""Dense reference rasteriser: every Gaussian against every pixel, pure torch, no tiles.

Slow (memory and time O(pixels x Gaussians)) and written to be read: this is the ground truth the
tiled and compiled backends are tested against, and it supports autograd for every input.
"""

from __future__ import annotations

import torch
from image2sim.simulator.splatting.project import ALPHA_MAX, ALPHA_MIN, CUTOFF_SIGMA, T_MIN, wrap_offset

__all__ = ["rasterize", "composite"]


def composite(
    dx: torch.Tensor,
    dy: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    t_min: float = T_MIN,
) -> torch.Tensor:
    """Blending weights w (..., P, K) of K depth-sorted Gaussians at P pixels.

    ``dx``/``dy`` (..., P, K) are pixel-minus-mean offsets (already wrapped); ``conics`` (..., 1, K, 3)
    or broadcastable, ``opacities`` (..., 1, K). Implements the splatting semantics exactly:
    footprint cut at 3.5 sigma, alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255,
    w_i = alpha_i T_i, and a pixel stops after the Gaussian that brings T below ``t_min``
    (default 1e-4).
    """
    a, b, c = conics.unbind(-1)
    q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
    alpha = torch.clamp(opacities * torch.exp(-0.5 * q), max=ALPHA_MAX)
    keep = (q <= CUTOFF_SIGMA * CUTOFF_SIGMA) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    # Exclusive cumulative product: transmittance in front of each Gaussian.
    trans = torch.cumprod(
        torch.cat((torch.ones_like(one_minus[..., :1]), one_minus[..., :-1]), dim=-1), dim=-1
    )
    counted = trans.detach() >= t_min
    return torch.where(counted, alpha * trans, torch.zeros_like(alpha))


def rasterize(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    values: torch.Tensor,
    background: torch.Tensor,
    height: int,
    width: int,
    wrap_width: float,
    t_min: float = T_MIN,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense front-to-back compositing of M sorted Gaussians carrying D values each.

    Returns ``image`` (D, H, W) = sum_i w_i values_i + (1 - alpha) background and ``alpha``
    (1, H, W) = sum_i w_i.
    """
    dtype, device = means2d.dtype, means2d.device
    d = values.shape[1]
    if means2d.shape[0] == 0:
        alpha = torch.zeros(1, height, width, dtype=dtype, device=device)
        image = background.reshape(d, 1, 1).expand(d, height, width) + 0.0 * values.sum()
        return image.contiguous(), alpha
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    px = uu.reshape(-1, 1)
    py = vv.reshape(-1, 1)
    dx = wrap_offset(px - means2d[:, 0], wrap_width)
    dy = py - means2d[:, 1]
    w = composite(dx, dy, conics, opacities, t_min)  # (P, M)
    alpha = w.sum(dim=-1)
    image = w @ values + (1.0 - alpha).unsqueeze(-1) * background
    return image.transpose(0, 1).reshape(d, height, width), alpha.reshape(1, height, width)
