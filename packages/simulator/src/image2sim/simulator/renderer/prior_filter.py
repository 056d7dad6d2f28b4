"""Least-squares start for the decoder's linear prior filter (``decoder.prior_filter``), pure functions.

The filter maps the prior's RGB logits and alpha in a K x K neighbourhood to a correction of the
RGB logits. Before any gradient step it can be fitted in closed form to the training pairs: with
``c0`` the prior colour and ``s = c0 (1 - c0)`` the sigmoid's slope there, a small logit
correction ``d`` moves the colour by about ``s d``, so the filter minimising
``sum (s (W x + b) - (target - c0))^2`` per channel is a weighted ridge regression. That is the best
linear deconvolution of the training splats (measured: +0.5 dB over ``splat_fill`` on held-out
views of two protocols, ``scripts/renderer_linear_bound.py``), which a few hundred Adam steps at the
network's learning rate only partly reach (docs/renderer.md, "A linear path from the prior").

:func:`prior_filter_rows` builds exactly the inputs the decoder's ``PanoConv2d`` sees (circular in
longitude, zeros in latitude, ``F.unfold`` order = the convolution's weight layout); the tests
check that ``rows @ [W; b]`` equals the convolution.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
import torch.nn.functional as F
from image2sim.simulator.layers import circular_pad_width
from image2sim.simulator.renderer.condition import ALPHA
from image2sim.simulator.renderer.decoder import prior_base

__all__ = ["prior_filter_rows", "fit_prior_filter"]


def prior_filter_rows(
    condition: torch.Tensor,
    kernel: int,
    depth_scale: float,
    depth_fill: float,
    fill: str = "grey",
    panoramic: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rows (B*H*W, 4*K*K), base logits (B, 3, H, W))``: per pixel the K x K neighbourhood of
    ``[prior logits (3), alpha]`` as the decoder's filter convolution reads it."""
    if kernel < 1 or kernel % 2 == 0:
        raise ValueError(f"prior filter kernel must be odd and positive, got {kernel}")
    logits, _ = prior_base(condition, depth_scale, depth_fill, fill=fill, panoramic=panoramic)
    x = torch.cat((logits, condition[:, ALPHA].clamp(0.0, 1.0).to(logits.dtype)), dim=1)
    k = kernel // 2
    x = circular_pad_width(x, k, k) if panoramic else F.pad(x, (k, k))
    x = F.pad(x, (0, 0, k, k))  # zeros in latitude, as the convolution's own padding
    cols = F.unfold(x, kernel)  # (B, 4 K K, H W)
    return cols.transpose(1, 2).reshape(-1, cols.shape[1]), logits


def fit_prior_filter(
    pairs: Iterable[tuple[torch.Tensor, torch.Tensor]],
    kernel: int,
    depth_scale: float,
    depth_fill: float,
    fill: str = "grey",
    panoramic: bool = True,
    pixels_per_image: int | None = 8192,
    ridge: float = 1e-4,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Fit the filter to ``(condition (B, 24, H, W), target RGB (B, 3, H, W))`` batches.

    Returns ``(weight (3, 4, K, K), bias (3,), pixels used)``. ``pixels_per_image`` random pixels
    of each image enter the normal equations (None: all); ``ridge`` is relative to the mean diagonal
    of each channel's Gram matrix. Accumulates in float64; non-finite rows are skipped.
    """
    n_in = 4 * kernel * kernel + 1
    gram = torch.zeros(3, n_in, n_in, dtype=torch.float64)
    rhs = torch.zeros(3, n_in, dtype=torch.float64)
    used = 0
    for condition, target in pairs:
        rows, logits = prior_filter_rows(condition.float(), kernel, depth_scale, depth_fill, fill, panoramic)
        c0 = torch.sigmoid(logits).permute(0, 2, 3, 1).reshape(-1, 3)
        t = target.float().permute(0, 2, 3, 1).reshape(-1, 3)
        rows = torch.cat((rows, torch.ones_like(rows[:, :1])), dim=1)
        per_image = rows.shape[0] // condition.shape[0]
        if pixels_per_image is not None and pixels_per_image < per_image:
            pick = torch.cat(
                [
                    b * per_image + torch.randperm(per_image, generator=generator)[:pixels_per_image]
                    for b in range(condition.shape[0])
                ]
            )
            rows, c0, t = rows[pick], c0[pick], t[pick]
        ok = torch.isfinite(rows).all(1) & torch.isfinite(t).all(1)
        rows, c0, t = rows[ok].double(), c0[ok].double(), t[ok].double()
        slope = c0 * (1.0 - c0)
        for c in range(3):
            scaled = rows * slope[:, c : c + 1]
            gram[c] += scaled.T @ scaled
            rhs[c] += scaled.T @ (t[:, c] - c0[:, c])
        used += int(ok.sum())
    if used == 0:
        raise ValueError("fit_prior_filter: no finite training pixels")
    solved = []
    for c in range(3):
        lam = ridge * float(gram[c].diagonal().mean()) + 1e-12
        solved.append(torch.linalg.solve(gram[c] + lam * torch.eye(n_in, dtype=torch.float64), rhs[c]))
    w = torch.stack(solved)
    return w[:, :-1].reshape(3, 4, kernel, kernel).float(), w[:, -1].float(), used
