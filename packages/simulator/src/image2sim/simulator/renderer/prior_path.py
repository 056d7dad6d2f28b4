"""A small nonlinear path from the splatted prior to the RGB correction (``decoder.prior_hidden``).

The decoder's linear prior filter (``decoder.prior_filter``) is the best single deconvolution of
the training splats. What it cannot do is decide per pixel: whether a blended depth edge belongs
to the near or the far surface, or how much texture a blurred patch had. :class:`PriorNet` is a
per-pixel MLP on the same K x K neighbourhood of the (hole-filled) prior, written as convolutions:
a K x K convolution of ``[RGB logits (3), alpha, log range]`` to ``hidden`` channels, GELU, a 1 x 1
convolution, GELU, and a zero-initialised 1 x 1 convolution to 3 logit corrections.

Range enters relative to the centre pixel (``log d_j - log d_centre``), so the path sees the shape
of the depth edge and not the room's size: with absolute log range it fitted the training houses'
distances and lost 0.5 dB on held-out views of the demo (docs/renderer.md). The relative form is
exact and cheap: ``sum_j w_j (l_j - l_c) = conv(l) - l_c sum_j w_j``.

Padding is circular in longitude and replicates the edge rows in latitude (a relative range of 0
beyond the poles instead of a jump to zero). Everything depends on the condition only, so the
path adds nothing to the MeanFlow JVP tangent.

:meth:`PriorNet.forward_windows` applies the same layers to gathered windows of the padded input
(the output of their interior); the fit (``renderer.prior_filter.fit_prior_path``) trains on
random training tiles that way, and the tests check it against the full-image forward at the seam
and the poles.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from image2sim.simulator.layers import circular_pad_width
from torch import nn

__all__ = ["PRIOR_NET_INPUTS", "prior_net_input", "pad_prior", "PriorNet"]

PRIOR_NET_INPUTS = 5
"""Input channels of :class:`PriorNet`: prior RGB logits (3), alpha, log range (state units)."""

_LOG_RANGE_FLOOR = 1e-3
"""State-depth floor before the log (1 cm at depth_scale 10): empty pixels have range 0."""


def prior_net_input(base_logits: torch.Tensor, alpha: torch.Tensor, base_depth: torch.Tensor) -> torch.Tensor:
    """``(B, 5, H, W)`` = ``[logits (3), alpha, log(max(depth, 1e-3))]`` from the decoder's prior
    (:func:`~image2sim.simulator.renderer.decoder.prior_base`) and the condition's alpha."""
    log_range = torch.log(base_depth.clamp_min(_LOG_RANGE_FLOOR)).to(base_logits.dtype)
    return torch.cat((base_logits, alpha.clamp(0.0, 1.0).to(base_logits.dtype), log_range), dim=1)


def _replicate_height(x: torch.Tensor, k: int) -> torch.Tensor:
    """Repeat the first and last rows ``k`` times (slicing + cat: every AD mode supports it)."""
    if k == 0:
        return x
    top = x[..., :1, :].expand(*x.shape[:-2], k, x.shape[-1])
    bottom = x[..., -1:, :].expand(*x.shape[:-2], k, x.shape[-1])
    return torch.cat((top, x, bottom), dim=-2)


def pad_prior(x: torch.Tensor, k: int, panoramic: bool = True) -> torch.Tensor:
    """Pad by ``k`` on every side: circular in width for panoramas (replicate otherwise), replicate
    in height."""
    if panoramic:
        x = circular_pad_width(x, k, k)
    elif k:
        left = x[..., :1].expand(*x.shape[:-1], k)
        right = x[..., -1:].expand(*x.shape[:-1], k)
        x = torch.cat((left, x, right), dim=-1)
    return _replicate_height(x, k)


class PriorNet(nn.Module):
    """Per-pixel MLP on the K x K neighbourhood of the prior (see the module docstring)."""

    def __init__(self, kernel: int, hidden: int, panoramic: bool = True) -> None:
        super().__init__()
        if kernel < 1 or kernel % 2 == 0:
            raise ValueError(f"PriorNet: kernel must be odd and positive, got {kernel}")
        if hidden < 1:
            raise ValueError(f"PriorNet: hidden must be positive, got {hidden}")
        self.kernel = int(kernel)
        self.panoramic = bool(panoramic)
        self.inp = nn.Conv2d(PRIOR_NET_INPUTS, hidden, self.kernel)
        self.mid = nn.Conv2d(hidden, hidden, 1)
        self.out = nn.Conv2d(hidden, 3, 1)
        nn.init.zeros_(self.out.weight)  # the untrained path adds nothing
        nn.init.zeros_(self.out.bias)
        # Input standardisation, set from the training pairs by the fit (shift, scale per channel).
        self.register_buffer("in_shift", torch.zeros(PRIOR_NET_INPUTS))
        self.register_buffer("in_scale", torch.ones(PRIOR_NET_INPUTS))

    def standardise(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.in_shift.view(1, -1, 1, 1).to(x.dtype)) / self.in_scale.view(1, -1, 1, 1).to(x.dtype)

    def _head(self, h: torch.Tensor, centre_log_range: torch.Tensor) -> torch.Tensor:
        # relative range: subtract the centre's share of the range taps (see the module docstring)
        taps = self.inp.weight[:, PRIOR_NET_INPUTS - 1].sum(dim=(1, 2)).view(1, -1, 1, 1)
        h = F.gelu(h - centre_log_range * taps)
        return self.out(F.gelu(self.mid(h)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` = :func:`prior_net_input` ``(B, 5, H, W)`` -> RGB logit correction ``(B, 3, H, W)``."""
        xs = self.standardise(x)
        h = self.inp(pad_prior(xs, self.kernel // 2, self.panoramic))
        return self._head(h, xs[:, PRIOR_NET_INPUTS - 1 :])

    def forward_windows(self, windows: torch.Tensor) -> torch.Tensor:
        """``windows (N, 5, S, S)`` of the standardised, :func:`pad_prior`-padded input -> the
        forward's output on their ``S - 2k`` interior pixels ``(N, 3, S - 2k, S - 2k)``."""
        k = self.kernel // 2
        h = self.inp(windows)
        return self._head(
            h, windows[:, PRIOR_NET_INPUTS - 1 :, k : windows.shape[-2] - k, k : windows.shape[-1] - k]
        )
