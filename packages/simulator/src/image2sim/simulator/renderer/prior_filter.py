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

:func:`fit_prior_path` then trains the whole prior path, this filter and the per-pixel MLP beside
it (``decoder.prior_hidden``, :mod:`~image2sim.simulator.renderer.prior_path`), with Adam on random
training tiles: what the single filter cannot do is nonlinear (docs/renderer.md, "A nonlinear path
from the prior").
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
import torch.nn.functional as F
from image2sim.simulator.layers import circular_pad_width
from image2sim.simulator.renderer.condition import ALPHA
from image2sim.simulator.renderer.decoder import prior_base
from image2sim.simulator.renderer.prior_path import pad_prior
from image2sim.simulator.schedules import warmup_cosine

__all__ = ["FIT_MAX_PIXELS", "prior_filter_rows", "fit_prior_filter", "fit_prior_path"]

FIT_MAX_PIXELS = 1 << 23
"""Pixels of training pairs :func:`fit_prior_path` holds at most (8.4 M: 256 pairs at 128 x 256, 16 at
512 x 1024; with their padded inputs about 0.6 GB of float32)."""


def _pad_as_filter(x: torch.Tensor, k: int, panoramic: bool) -> torch.Tensor:
    """The filter's own padding (``PanoConv2d``): circular in width on a panorama, zeros otherwise
    and in latitude."""
    x = circular_pad_width(x, k, k) if panoramic else F.pad(x, (k, k))
    return F.pad(x, (0, 0, k, k))


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
    cols = F.unfold(_pad_as_filter(x, k, panoramic), kernel)  # (B, 4 K K, H W)
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


class _Windows:
    """``size x size`` windows of a ``(B, C, H', W')`` stack, gathered as rows of a pixel-major
    table (one ``index_select`` of contiguous C-vectors; indexing the channel-first tensor
    directly was 60 % of a fit step)."""

    def __init__(self, stack: torch.Tensor, size: int) -> None:
        b, c, hp, wp = stack.shape
        self.table = stack.permute(0, 2, 3, 1).reshape(-1, c).contiguous()
        self.size, self.channels, self.hp, self.wp = size, c, hp, wp
        offsets = torch.arange(size)
        self.offsets = (offsets[:, None] * wp + offsets[None]).reshape(-1)  # row-major

    def __call__(self, image: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``(N, C, size, size)`` windows whose top-left corners are ``(image, y, x)``."""
        corner = (image * self.hp + y) * self.wp + x
        rows = self.table.index_select(0, (corner[:, None] + self.offsets[None]).reshape(-1))
        return rows.reshape(-1, self.size, self.size, self.channels).permute(0, 3, 1, 2)


def fit_prior_path(
    decoder,
    pairs: Iterable[tuple[torch.Tensor, torch.Tensor]],
    steps: int,
    batch_pixels: int = 8192,
    lr: float = 1e-3,
    max_pixels: int = FIT_MAX_PIXELS,
    tile: int = 16,
    generator: torch.Generator | None = None,
) -> dict:
    """Train ``decoder``'s prior path (``prior_filter`` and ``prior_net``, from their current
    values) on random pixels of ``(condition, target RGB)`` batches: the MSE of
    ``sigmoid(base logits + filter + MLP)`` against the target; Adam, 5 % linear warm-up, cosine decay.

    Each step reads about ``batch_pixels`` pixels as ``tile x tile`` crops at random places of
    random images (the padded windows around them are gathered, so no full-image forward is
    needed; the tests check that the windowed and the full-image path agree). Non-finite pixels
    are left out of the loss. Pairs beyond ``max_pixels`` pixels in all are dropped (a random
    subset is kept; :func:`~image2sim.simulator.renderer.module.init_prior_path` draws it before
    loading them). Also sets ``prior_net``'s input standardisation from the pairs. Returns
    ``{"images", "pixels", "psnr_start", "psnr_end"}``: the PSNR of the prior path on a fixed set
    of training tiles (four batches' worth, drawn once), before and after the fit.
    """
    conv, net = decoder.prior_filter, decoder.prior_net
    if conv is None:
        raise ValueError("fit_prior_path: the decoder has no prior filter (decoder.prior_filter = 0)")
    k = conv.kernel_size[0] // 2
    lin_in, net_in, targets, logits = [], [], [], []
    for condition, target in pairs:
        with torch.no_grad():
            lg, _, x4, x5 = decoder.prior_path_inputs(condition.float())
        if x5 is None:  # no MLP beside the filter: only the filter is fitted
            x5 = torch.zeros_like(x4[:, :1])
        lin_in.append(x4)
        net_in.append(x5)
        logits.append(lg)
        targets.append(target.float())
    if not lin_in:
        raise ValueError("fit_prior_path: no training pairs")
    x4, x5, lg, tgt = (torch.cat(t) for t in (lin_in, net_in, logits, targets))
    keep_images = max(1, max_pixels // (x4.shape[-2] * x4.shape[-1]))
    if x4.shape[0] > keep_images:
        keep = torch.randperm(x4.shape[0], generator=generator)[:keep_images]
        x4, x5, lg, tgt = x4[keep], x5[keep], lg[keep], tgt[keep]
    n_img, _, h, w = x4.shape
    finite = torch.isfinite(x5).all(1) & torch.isfinite(tgt).all(1) & torch.isfinite(x4).all(1)
    if not finite.any():
        raise ValueError("fit_prior_path: no finite training pixels")
    x4, x5, lg, tgt = (torch.nan_to_num(t) for t in (x4, x5, lg, tgt))
    tile = min(tile, h, w)
    size = tile + 2 * k
    lin_windows = _Windows(_pad_as_filter(x4, k, decoder.panoramic), size)
    pixels = _Windows(torch.cat((lg, tgt, finite[:, None].to(lg.dtype)), dim=1), tile)
    params = list(conv.parameters())
    if net is not None:
        with torch.no_grad():
            sample = x5.permute(1, 0, 2, 3)[:, finite]
            net.in_shift.copy_(sample.mean(1))
            net.in_scale.copy_(sample.std(1).clamp_min(1e-3))
            net_windows = _Windows(pad_prior(net.standardise(x5), k, decoder.panoramic), size)
        params += list(net.parameters())
    opt = torch.optim.Adam(params, lr=lr)
    warm = max(1, steps // 20)

    # Linear warm-up over 5 % of the steps, then cosine to zero.
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: warmup_cosine(step, warm, steps, 0.0))
    n_tiles = max(1, batch_pixels // (tile * tile))

    def draw(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return (
            torch.randint(0, n_img, (n,), generator=generator),
            torch.randint(0, h - tile + 1, (n,), generator=generator),
            torch.randint(0, w - tile + 1, (n,), generator=generator),
        )

    def loss_on(image: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        corr = F.conv2d(lin_windows(image, y, x), conv.weight, conv.bias)
        if net is not None:
            corr = corr + net.forward_windows(net_windows(image, y, x))
        at = pixels(image, y, x)
        mask = at[:, 6:7]
        err = (torch.sigmoid(at[:, :3] + corr) - at[:, 3:6]).pow(2) * mask
        return err.sum() / (3.0 * mask.sum()).clamp_min(1.0)

    # A fixed set of tiles (4 batches' worth) scores the path before and after the fit.
    held = draw(4 * n_tiles)
    with torch.no_grad():
        start = float(loss_on(*held))
    for _ in range(steps):
        loss = loss_on(*draw(n_tiles))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        end = float(loss_on(*held))
    for p in params:
        p.grad = None

    def to_psnr(mse: float) -> float:
        return -10.0 * math.log10(max(mse, 1e-10))

    return {
        "images": int(n_img),
        "pixels": int(finite.sum()),
        "psnr_start": to_psnr(start),
        "psnr_end": to_psnr(end),
    }
