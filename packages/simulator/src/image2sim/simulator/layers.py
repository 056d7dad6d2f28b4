"""Shared neural building blocks for panoramic (equirectangular) and pinhole feature maps.

Every block here works on channels-first tensors ``(B, C, H, W)`` and is written with plain
differentiable tensor ops so that it supports reverse *and* forward-mode automatic
differentiation (``torch.func.jvp``) on CPU. That matters for the MeanFlow renderer, whose
training objective needs a Jacobian-vector product through the whole network: the CPU flash
kernel behind ``F.scaled_dot_product_attention`` has no forward-mode rule, and the fused
``F.layer_norm`` costs ~30x its forward under ``jvp``; explicit formulas avoid both.

Panorama convention (see :mod:`image2sim.simulator.conventions`): width is longitude and wraps
around (column 0 is the right neighbour of column W-1), height is latitude and does not wrap,
so convolutions pad circularly along W and with zeros along H. Pinhole maps use zeros on all
sides (``panoramic=False``).

Blocks
    :class:`PanoConv2d`            convolution with seam-aware padding
    :class:`LayerNorm2d`           LayerNorm over channels at every pixel
    :class:`GRN`                   ConvNeXt-V2 global response normalisation
    :class:`PanoBlock`             depth-wise PanoConv + ConvNeXt-V2 inverted bottleneck with GRN
    :class:`PixelShuffleUpsample`  sub-pixel x2 (or xr) upsampling, ICNR-initialised
    :class:`TransformerBlock`      pre-norm attention + MLP over a feature map's pixels, optional
                                   AdaLN-Zero conditioning on a vector
    :func:`attention`              multi-head attention written out (forward-mode AD safe)
    :func:`sincos_positional_encoding`  resolution-agnostic 2-D encoding from angles
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "circular_pad_width",
    "PanoConv2d",
    "LayerNorm2d",
    "GRN",
    "PanoBlock",
    "PixelShuffleUpsample",
    "attention",
    "TransformerBlock",
    "sincos_positional_encoding",
]


def _pair(value: int | tuple[int, int]) -> tuple[int, int]:
    return (value, value) if isinstance(value, int) else (int(value[0]), int(value[1]))


def circular_pad_width(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """Pad the last (width) axis circularly: the panorama seam joins column W-1 to column 0.

    Written with slicing + ``cat`` (rather than ``F.pad(mode="circular")``) so that every AD mode
    supports it; ``left``/``right`` may exceed W (the map is tiled as often as needed).
    """
    if left < 0 or right < 0:
        raise ValueError(f"circular padding must be non-negative, got ({left}, {right})")
    if left == 0 and right == 0:
        return x
    width = x.shape[-1]
    if width == 0:
        raise ValueError("cannot pad an empty width axis circularly")
    if left > width or right > width:  # rare: tile first so one wrap suffices
        reps = max(left, right) // width + 1
        x = torch.cat([x] * (2 * reps + 1), dim=-1)
        start = reps * width - left
        return x[..., start : start + width + left + right]
    parts = [x[..., width - left :]] if left else []
    parts.append(x)
    if right:
        parts.append(x[..., :right])
    return torch.cat(parts, dim=-1)


class PanoConv2d(nn.Conv2d):
    """``nn.Conv2d`` with panorama-aware "same" padding.

    Padding is ``dilation * (kernel - 1) // 2`` on each side (so a stride-1 odd kernel keeps the
    size and a stride-s kernel of size s maps H -> H/s): circular along width (longitude wraps)
    and zeros along height when ``panoramic`` is True (default), zeros everywhere when False.
    Weights, groups, bias and ``state_dict`` layout are those of ``nn.Conv2d``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int | tuple[int, int] = 3,
        stride: int | tuple[int, int] = 1,
        dilation: int | tuple[int, int] = 1,
        groups: int = 1,
        bias: bool = True,
        panoramic: bool = True,
    ) -> None:
        kh, kw = _pair(kernel_size)
        dh, dw = _pair(dilation)
        pad_h = dh * (kh - 1) // 2
        pad_w = dw * (kw - 1) // 2
        # Zero padding is the convolution's own; only a panorama's circular width padding is
        # copied (no faster measurably than a separate F.pad, but one copy fewer).
        super().__init__(
            in_channels,
            out_channels,
            kernel_size,
            stride=stride,
            padding=(pad_h, 0) if panoramic else (pad_h, pad_w),
            dilation=dilation,
            groups=groups,
            bias=bias,
        )
        self.panoramic = bool(panoramic)
        self.pad_w = pad_w  # the circular part; the zero part is self.padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.panoramic:
            x = circular_pad_width(x, self.pad_w, self.pad_w)
        return super().forward(x)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", panoramic={self.panoramic}"


class LayerNorm2d(nn.Module):
    """LayerNorm over the channel axis of ``(B, C, H, W)``, independently at every pixel.

    ``y = (x - mean_c x) / sqrt(var_c x + eps) * weight + bias`` with a biased variance, which
    equals ``F.layer_norm`` on the channels-last view (checked by the tests) but is composed of
    primitive ops, which keeps forward-mode AD cheap.
    """

    def __init__(self, channels: int, eps: float = 1e-6, affine: bool = True) -> None:
        super().__init__()
        self.channels = int(channels)
        self.eps = float(eps)
        if affine:
            self.weight = nn.Parameter(torch.ones(channels))
            self.bias = nn.Parameter(torch.zeros(channels))
        else:
            self.register_parameter("weight", None)
            self.register_parameter("bias", None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(dim=1, keepdim=True)
        centred = x - mean
        var = centred.pow(2).mean(dim=1, keepdim=True)
        y = centred * torch.rsqrt(var + self.eps)
        if self.weight is not None:
            y = y * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)
        return y

    def extra_repr(self) -> str:
        return f"{self.channels}, eps={self.eps}, affine={self.weight is not None}"


class GRN(nn.Module):
    """Global Response Normalisation (ConvNeXt-V2), channels-first.

    ``G_c = ||x_c||_2`` over the spatial axes, ``N_c = G_c / (mean_c G + eps)``,
    ``y = gamma * (x * N) + beta + x``. gamma and beta start at zero (identity at init). The norm
    is ``sqrt(sum x^2 + eps^2)`` so an all-zero map (e.g. an empty splat) has finite gradients.
    """

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.eps = float(eps)
        self.gamma = nn.Parameter(torch.zeros(1, channels, 1, 1))
        self.beta = nn.Parameter(torch.zeros(1, channels, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gx = torch.sqrt(x.pow(2).sum(dim=(2, 3), keepdim=True) + self.eps * self.eps)
        nx = gx / (gx.mean(dim=1, keepdim=True) + self.eps)
        return self.gamma * (x * nx) + self.beta + x


class PanoBlock(nn.Module):
    """ConvNeXt-V2 block on a panorama: residual of
    depth-wise ``PanoConv2d`` (k x k) -> LayerNorm2d -> 1x1 expand (x ``expansion``) -> GELU ->
    GRN -> 1x1 project back. Keeps shape ``(B, C, H, W)``.
    """

    def __init__(
        self, channels: int, kernel_size: int = 7, expansion: int = 4, panoramic: bool = True
    ) -> None:
        super().__init__()
        hidden = int(channels * expansion)
        self.dwconv = PanoConv2d(channels, channels, kernel_size, groups=channels, panoramic=panoramic)
        self.norm = LayerNorm2d(channels)
        self.pwconv1 = nn.Conv2d(channels, hidden, 1)
        self.act = nn.GELU()
        self.grn = GRN(hidden)
        self.pwconv2 = nn.Conv2d(hidden, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.pwconv2(self.grn(self.act(self.pwconv1(self.norm(self.dwconv(x))))))
        return x + y


class PixelShuffleUpsample(nn.Module):
    """Sub-pixel upsampling by ``scale``: ``PanoConv2d`` to ``out * scale^2`` channels, then
    ``pixel_shuffle``. The convolution is ICNR-initialised (every sub-pixel starts with the same
    kernel) so the initial output is a nearest-neighbour upsampling without checkerboard.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        scale: int = 2,
        kernel_size: int = 3,
        panoramic: bool = True,
    ) -> None:
        super().__init__()
        if scale < 1:
            raise ValueError(f"PixelShuffleUpsample scale must be >= 1, got {scale}")
        self.scale = int(scale)
        self.conv = PanoConv2d(in_channels, out_channels * scale * scale, kernel_size, panoramic=panoramic)
        self._icnr_init(out_channels)

    @torch.no_grad()
    def _icnr_init(self, out_channels: int) -> None:
        base = torch.empty(out_channels, *self.conv.weight.shape[1:])
        nn.init.kaiming_normal_(base, nonlinearity="linear")
        # pixel_shuffle reads channel c*s^2 + k for output channel c, sub-pixel k.
        self.conv.weight.copy_(base.repeat_interleave(self.scale * self.scale, dim=0))
        if self.conv.bias is not None:
            self.conv.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.pixel_shuffle(self.conv(x), self.scale)


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Scaled dot-product attention ``softmax(q k^T / sqrt(d)) v`` over ``(..., N, d)`` tensors.

    Written out explicitly (the "math" path) because the CPU fused kernel of
    ``F.scaled_dot_product_attention`` raises under forward-mode AD. The softmax is computed in
    at least float32 so half/bf16 autocast cannot overflow the logits.
    """
    scale = 1.0 / math.sqrt(q.shape[-1])
    logits = torch.matmul(q, k.transpose(-2, -1)) * scale
    if logits.dtype in (torch.float16, torch.bfloat16):
        logits = logits.float()
    weights = torch.softmax(logits, dim=-1).to(v.dtype)
    return torch.matmul(weights, v)


class TransformerBlock(nn.Module):
    """Pre-norm transformer block over the pixels of a ``(B, C, H, W)`` map.

    ``x + gate1 * Attn(mod(LN(x))) ; x + gate2 * MLP(mod(LN(x)))``. Without ``cond_dim`` the
    modulation is the identity and the gates are 1. With ``cond_dim`` it is AdaLN-Zero (DiT):
    a zero-initialised linear map of the conditioning vector gives per-channel shift, scale and
    gate for both branches, so the block starts as the identity and learns how much to use the
    condition (here: the MeanFlow time embedding).
    """

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, cond_dim: int | None = None) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"TransformerBlock: dim {dim} is not divisible by heads {heads}")
        self.dim, self.heads = int(dim), int(heads)
        self.norm1 = LayerNorm2d(dim, affine=cond_dim is None)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = LayerNorm2d(dim, affine=cond_dim is None)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))
        self.cond_dim = cond_dim
        if cond_dim is not None:
            self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 6 * dim))
            nn.init.zeros_(self.modulation[1].weight)
            nn.init.zeros_(self.modulation[1].bias)

    def _attend(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        tokens = x.flatten(2).transpose(1, 2)  # (B, N, C)
        q, k, v = self.qkv(tokens).view(b, h * w, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = attention(q, k, v).transpose(1, 2).reshape(b, h * w, c)
        return self.proj(out).transpose(1, 2).reshape(b, c, h, w)

    def _mlp(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        return self.mlp(x.flatten(2).transpose(1, 2)).transpose(1, 2).reshape(b, c, h, w)

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None = None) -> torch.Tensor:
        if self.cond_dim is None:
            if cond is not None:
                raise ValueError("TransformerBlock was built without cond_dim but got a condition")
            x = x + self._attend(self.norm1(x))
            return x + self._mlp(self.norm2(x))
        if cond is None:
            raise ValueError(f"TransformerBlock expects a (B, {self.cond_dim}) condition")
        mods = self.modulation(cond)[:, :, None, None].chunk(6, dim=1)
        shift1, scale1, gate1, shift2, scale2, gate2 = mods
        x = x + gate1 * self._attend(self.norm1(x) * (1 + scale1) + shift1)
        return x + gate2 * self._mlp(self.norm2(x) * (1 + scale2) + shift2)


def sincos_positional_encoding(
    height: int, width: int, dim: int, panoramic: bool = True, dtype: torch.dtype = torch.float32, device=None
) -> torch.Tensor:
    """Resolution-agnostic 2-D sinusoidal positional encoding, ``(dim, height, width)``.

    Positions are *angles of pixel centres*, not grid indices, so the same direction gets the same
    code at any resolution (the official code pins one grid size). Half of the channels encode
    the horizontal coordinate, half the vertical one, each as sin/cos pairs with frequencies
    ``1 .. dim/4``:

    * panoramic: longitude ``lon`` in [-pi, pi) with *integer* frequencies, so the code is
      exactly periodic across the seam, and latitude ``lat`` with frequencies applied to
      ``2 * lat`` (period 2*pi covering [-pi/2, pi/2] without aliasing);
    * pinhole: normalised coordinates in [-1, 1] mapped to [-pi, pi).

    ``dim`` must be a positive multiple of 4.
    """
    if dim <= 0 or dim % 4:
        raise ValueError(f"positional encoding dim must be a positive multiple of 4, got {dim}")
    if height <= 0 or width <= 0:
        raise ValueError(f"positional encoding needs a non-empty grid, got {height}x{width}")
    u = (torch.arange(width, dtype=torch.float64, device=device) + 0.5) / width
    v = (torch.arange(height, dtype=torch.float64, device=device) + 0.5) / height
    horiz = 2.0 * math.pi * u - math.pi  # lon, or pinhole x in [-pi, pi)
    vert = (0.5 * math.pi - math.pi * v) * 2.0 if panoramic else 2.0 * math.pi * v - math.pi
    freqs = torch.arange(1, dim // 4 + 1, dtype=torch.float64, device=device)
    ph = horiz[None, :] * freqs[:, None]  # (dim/4, W)
    pv = vert[None, :] * freqs[:, None]  # (dim/4, H)
    enc_h = torch.cat((ph.sin(), ph.cos()), 0)[:, None, :].expand(-1, height, -1)
    enc_v = torch.cat((pv.sin(), pv.cos()), 0)[:, :, None].expand(-1, -1, width)
    return torch.cat((enc_h, enc_v), 0).to(dtype).contiguous()
