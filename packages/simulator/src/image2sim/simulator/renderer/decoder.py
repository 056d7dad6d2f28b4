"""RenderingDecoder: x_theta(z_t, r, t | C_p, tokens) for the pixel-flow renderer.

Shape of the network (paper appendix, "Stage 3: Pixel Flow Rendering Decoder")::

    [C_p, z_t] --PanoConv--> L0 (H) --> L1 (H/2) --> L2 (H/4) --> L3 (H/8) --> bottleneck (H/16)
                   PanoBlocks at each level, skips e_0..e_3 kept
    bottleneck: + angle positional encoding; N x [SemanticInjector(tokens) -> TransformerBlock
                (AdaLN-Zero on DualTimeEmbedding(t, h = t - r))]
    decoder:    PixelShuffle x2 -> AlphaGatedSkip(e_k, alpha_k) -> PanoBlocks, k = 3..0
    heads:      RGB (sigmoid), depth (ReLU, or exp with ``depth_head="log"``; in state units =
                metres / depth_scale); with ``residual_heads`` (default) both are corrections
                around the splatted prior, see :func:`prior_base`

All components are forward-mode-AD safe (see :mod:`image2sim.simulator.layers`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from image2sim.simulator.layers import (
    LayerNorm2d,
    PanoBlock,
    PanoConv2d,
    PixelShuffleUpsample,
    TransformerBlock,
    sincos_positional_encoding,
)
from image2sim.simulator.renderer.condition import ALPHA, DEPTH, RGB
from image2sim.simulator.renderer.config import CONDITION_CHANNELS, STATE_CHANNELS, DecoderConfig
from image2sim.simulator.renderer.prior_path import PriorNet, prior_net_input
from torch import nn

__all__ = [
    "timestep_embedding",
    "DualTimeEmbedding",
    "SemanticInjector",
    "AlphaPyramid",
    "AlphaGatedSkip",
    "prior_base",
    "DecoderOutput",
    "RenderingDecoder",
    "LOG_DEPTH_RANGE",
]

LOG_DEPTH_RANGE = (1e-6, 1e2)
"""State-depth bounds of the ``log`` depth head (10 µm to 1 km at depth_scale 10): the base is floored
at the lower one before the log, and the log-depth is clamped to both so exp cannot overflow."""
_LOG_DEPTH_BOUNDS = (math.log(LOG_DEPTH_RANGE[0]), math.log(LOG_DEPTH_RANGE[1]))


def timestep_embedding(
    t: torch.Tensor, dim: int, scale: float = 1000.0, max_period: float = 10000.0
) -> torch.Tensor:
    """Sinusoidal embedding ``(B, dim)`` of times ``(B,)``: ``[cos(s t f_i), sin(s t f_i)]`` with
    geometric frequencies ``f_i = max_period^(-i / (dim/2))``. Smooth in t (JVP-friendly)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = (scale * t.float())[:, None] * freqs[None, :]
    return torch.cat((torch.cos(args), torch.sin(args)), dim=-1).to(t.dtype)


class DualTimeEmbedding(nn.Module):
    """Embeds the integration time t and the step h = t - r sinusoidally and fuses them with an
    MLP into one conditioning vector ``(B, dim)`` (injected AdaLN-style into the bottleneck)."""

    def __init__(self, dim: int, scale: float = 1000.0) -> None:
        super().__init__()
        self.dim = int(dim)
        self.scale = float(scale)
        self.mlp = nn.Sequential(nn.Linear(2 * dim, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, t: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        emb = torch.cat(
            (timestep_embedding(t, self.dim, self.scale), timestep_embedding(t - r, self.dim, self.scale)),
            dim=-1,
        )
        return self.mlp(emb)


class SemanticInjector(nn.Module):
    """SPADE-like modulation: ``LayerNorm(F) * (1 + gamma) + beta`` with ``gamma, beta`` from the
    aligned tokens through SiLU and a 1x1 conv (zero-initialised: pure LayerNorm at init).
    Tokens on a different grid are resized to F's grid (bilinear)."""

    def __init__(self, channels: int, token_dim: int) -> None:
        super().__init__()
        self.norm = LayerNorm2d(channels, affine=False)
        self.act = nn.SiLU()
        self.to_mod = nn.Conv2d(token_dim, 2 * channels, 1)
        nn.init.zeros_(self.to_mod.weight)
        nn.init.zeros_(self.to_mod.bias)

    def forward(self, x: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
        if tokens.shape[-2:] != x.shape[-2:]:
            tokens = F.interpolate(tokens, size=x.shape[-2:], mode="bilinear", align_corners=False)
        gamma, beta = self.to_mod(self.act(tokens)).chunk(2, dim=1)
        return self.norm(x) * (1.0 + gamma) + beta


class AlphaPyramid(nn.Module):
    """Multi-scale alpha ``[A, pool(A), pool^2(A), ...]`` by repeated 2x2 average pooling."""

    def __init__(self, levels: int) -> None:
        super().__init__()
        self.levels = int(levels)

    def forward(self, alpha: torch.Tensor) -> list[torch.Tensor]:
        out = [alpha]
        for _ in range(self.levels - 1):
            out.append(F.avg_pool2d(out[-1], 2))
        return out


class AlphaGatedSkip(nn.Module):
    """Alpha-gated skip connection.

    Adapter ``F'_enc = GELU(LayerNorm(PanoConv1x1(F_enc)))``; gate
    ``g = sigmoid(W_gate [F_dec, F'_enc, alpha])`` with W_gate zero-initialised and bias
    ``gate_bias`` (2.0 -> g = 0.88 everywhere at init: trust the projection); output
    ``g * F'_enc + (1 - g) * F_dec``. With ``gated=False`` (ablation ``no_alpha_gate``) the output
    is the plain skip ``F'_enc + F_dec``.
    """

    def __init__(
        self,
        enc_channels: int,
        dec_channels: int,
        gate_bias: float = 2.0,
        gated: bool = True,
        panoramic: bool = True,
    ) -> None:
        super().__init__()
        self.adapter = nn.Sequential(
            PanoConv2d(enc_channels, dec_channels, 1, panoramic=panoramic),
            LayerNorm2d(dec_channels),
            nn.GELU(),
        )
        self.gated = bool(gated)
        if self.gated:
            self.gate = nn.Conv2d(2 * dec_channels + 1, dec_channels, 1)
            nn.init.zeros_(self.gate.weight)
            nn.init.constant_(self.gate.bias, float(gate_bias))
        self.last_gate: torch.Tensor | None = None

    def forward(self, dec: torch.Tensor, enc: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        enc = self.adapter(enc)
        if not self.gated:
            return enc + dec
        g = torch.sigmoid(self.gate(torch.cat((dec, enc, alpha.to(dec.dtype)), dim=1)))
        return g * enc + (1.0 - g) * dec

    def gate_values(self, dec: torch.Tensor, enc: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """The gate map g (for inspection and tests)."""
        if not self.gated:
            raise RuntimeError("this skip was built with gated=False (no_alpha_gate)")
        return torch.sigmoid(self.gate(torch.cat((dec, self.adapter(enc), alpha.to(dec.dtype)), dim=1)))


def prior_base(
    condition: torch.Tensor,
    depth_scale: float,
    depth_fill: float,
    eps: float = 1e-3,
    fill: str = "grey",
    panoramic: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """What the residual heads correct: RGB logits of ``c0 = A * prior + (1 - A) * 0.5`` (clamped
    to ``[eps, 1 - eps]``) and the state depth ``A * prior / depth_scale + (1 - A) * depth_fill``.

    Where alpha = 1 this is the splatted prior itself (splat-only), where alpha = 0 a neutral grey
    at ``depth_fill``; the network only has to generate where the projection is missing or wrong.
    With ``fill="interpolate"`` the (1 - A) part is the prior's surroundings instead
    (:func:`~image2sim.simulator.renderer.holefill.fill_holes`; grey / ``depth_fill`` only where
    nothing at all was projected). Depends on the condition only (no z, r, t), so it adds nothing
    to the JVP tangent.
    """
    if fill == "interpolate":
        from image2sim.simulator.renderer.holefill import fill_condition

        c0, d0 = fill_condition(condition, depth_scale, panoramic, depth_default=depth_fill)
    else:
        a = condition[:, ALPHA].clamp(0.0, 1.0)
        c0 = a * condition[:, RGB] + (1.0 - a) * 0.5
        d0 = a * condition[:, DEPTH] / depth_scale + (1.0 - a) * depth_fill
    c0 = c0.clamp(eps, 1.0 - eps)
    return torch.log(c0) - torch.log1p(-c0), d0


@dataclass
class DecoderOutput:
    """Prediction of the decoder."""

    x: torch.Tensor
    """Denoised state x_theta ``(B, 4, H, W)``: RGB in (0, 1), depth >= 0 in state units."""
    features: list[torch.Tensor]
    """Decoder feature maps after each skip level, deepest (H/8) first (distillation levels)."""
    rgb_logits: torch.Tensor
    """Pre-sigmoid RGB ``(B, 3, H, W)``."""


class RenderingDecoder(nn.Module):
    """UNet-style x-prediction network over ``[C_p, z_t]`` (see module docstring)."""

    def __init__(
        self,
        cfg: DecoderConfig,
        token_dim: int | None,
        gated_skips: bool = True,
        panoramic: bool = True,
        depth_scale: float = 10.0,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.panoramic = panoramic
        w = list(cfg.widths)
        nb = cfg.blocks_per_level
        self.stem = PanoConv2d(CONDITION_CHANNELS + STATE_CHANNELS, w[0], 3, panoramic=panoramic)
        self.enc_blocks = nn.ModuleList(
            nn.Sequential(*[PanoBlock(w[i], cfg.kernel_size, cfg.expansion, panoramic) for _ in range(nb[i])])
            for i in range(4)
        )
        outs = w[1:] + [cfg.bottleneck_dim]
        self.downs = nn.ModuleList(
            nn.Sequential(LayerNorm2d(w[i]), PanoConv2d(w[i], outs[i], 2, stride=2, panoramic=panoramic))
            for i in range(4)
        )
        self.time_embed = DualTimeEmbedding(cfg.time_dim, cfg.time_scale)
        self.injectors = (
            nn.ModuleList(
                SemanticInjector(cfg.bottleneck_dim, token_dim) for _ in range(cfg.bottleneck_depth)
            )
            if token_dim is not None
            else None
        )
        self.blocks = nn.ModuleList(
            TransformerBlock(cfg.bottleneck_dim, cfg.heads, cfg.mlp_ratio, cond_dim=cfg.time_dim)
            for _ in range(cfg.bottleneck_depth)
        )
        ins = [cfg.bottleneck_dim] + w[:0:-1]  # inputs of the up stages, deepest first
        self.ups = nn.ModuleList(
            PixelShuffleUpsample(ins[j], w[3 - j], 2, panoramic=panoramic) for j in range(4)
        )
        self.skips = nn.ModuleList(
            AlphaGatedSkip(w[3 - j], w[3 - j], cfg.gate_bias, gated_skips, panoramic) for j in range(4)
        )
        self.dec_blocks = nn.ModuleList(
            nn.Sequential(
                *[PanoBlock(w[3 - j], cfg.kernel_size, cfg.expansion, panoramic) for _ in range(nb[3 - j])]
            )
            for j in range(4)
        )
        self.pyramid = AlphaPyramid(4)
        self.out_norm = LayerNorm2d(w[0])
        self.rgb_head = PanoConv2d(w[0], 3, 3, panoramic=panoramic)
        self.depth_head = PanoConv2d(w[0], 1, 3, panoramic=panoramic)
        self.residual = bool(cfg.residual_heads)
        self.depth_fill = float(cfg.depth_bias)
        self.prior_fill = str(cfg.prior_fill)
        self.log_depth = cfg.depth_head == "log"
        self.depth_gate = bool(cfg.depth_gate) and self.residual
        self.depth_scale = float(depth_scale)
        # A linear path from the prior (RGB logits + alpha) to the RGB correction; zero at start.
        self.prior_filter = (
            PanoConv2d(4, 3, int(cfg.prior_filter), panoramic=panoramic)
            if self.residual and cfg.prior_filter
            else None
        )
        if self.prior_filter is not None:
            nn.init.zeros_(self.prior_filter.weight)
            nn.init.zeros_(self.prior_filter.bias)
        # ... and a per-pixel MLP beside it (its output layer starts at zero too).
        self.prior_net = (
            PriorNet(int(cfg.prior_filter), int(cfg.prior_hidden), panoramic=panoramic)
            if self.prior_filter is not None and cfg.prior_hidden
            else None
        )
        nn.init.zeros_(self.rgb_head.bias)
        if self.residual:  # corrections start at 0: the untrained network returns the prior
            for head in (self.rgb_head, self.depth_head):
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)
        else:
            bias = math.log(cfg.depth_bias) if self.log_depth else cfg.depth_bias
            nn.init.constant_(self.depth_head.bias, bias)

    def prior_path_inputs(
        self, condition: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """``(base logits, base depth, prior filter input or None, PriorNet input or None)``: the
        residual heads' prior (:func:`prior_base`) and what the prior path reads of it (the fit of
        that path, ``renderer.prior_filter.fit_prior_path``, reads the same)."""
        base_logits, base_depth = prior_base(
            condition, self.depth_scale, self.depth_fill, fill=self.prior_fill, panoramic=self.panoramic
        )
        if self.prior_filter is None:
            return base_logits, base_depth, None, None
        alpha = condition[:, ALPHA].clamp(0.0, 1.0).to(base_logits.dtype)
        filter_in = torch.cat((base_logits, alpha), dim=1)
        net_in = prior_net_input(base_logits, alpha, base_depth) if self.prior_net is not None else None
        return base_logits, base_depth, filter_in, net_in

    def forward(
        self,
        z: torch.Tensor,
        condition: torch.Tensor,
        r: torch.Tensor,
        t: torch.Tensor,
        tokens: torch.Tensor | None = None,
    ) -> DecoderOutput:
        """z: state ``(B, 4, H, W)``; condition ``(B, 24, H, W)``; r, t ``(B,)``; tokens or None."""
        b, _, h, w = z.shape
        if h % 16 or w % 16:
            raise ValueError(f"RenderingDecoder needs H and W divisible by 16, got {h}x{w}")
        if condition.shape[0] != b or condition.shape[-2:] != z.shape[-2:]:
            raise ValueError(f"condition {tuple(condition.shape)} does not match state {tuple(z.shape)}")
        if (tokens is None) != (self.injectors is None):
            raise ValueError("tokens must be given exactly when the decoder has semantic injectors")
        alphas = self.pyramid(condition[:, ALPHA])
        x = self.stem(torch.cat((condition, z), dim=1))
        skips = []
        for blocks, down in zip(self.enc_blocks, self.downs, strict=False):
            x = blocks(x)
            skips.append(x)
            x = down(x)
        temb = self.time_embed(t, r)
        x = x + sincos_positional_encoding(
            x.shape[-2], x.shape[-1], x.shape[1], self.panoramic, x.dtype, x.device
        )
        for i, block in enumerate(self.blocks):
            if self.injectors is not None:
                x = self.injectors[i](x, tokens)
            x = block(x, temb)
        features = []
        for j in range(4):
            level = 3 - j
            x = self.ups[j](x)
            x = self.skips[j](x, skips[level], alphas[level])
            x = self.dec_blocks[j](x)
            features.append(x)
        x = self.out_norm(x)
        rgb_logits = self.rgb_head(x)
        depth = self.depth_head(x)
        if self.residual:
            base_logits, base_depth, filter_in, net_in = self.prior_path_inputs(condition)
            rgb_logits = rgb_logits + base_logits
            if filter_in is not None:
                rgb_logits = rgb_logits + self.prior_filter(filter_in)
            if net_in is not None:
                rgb_logits = rgb_logits + self.prior_net(net_in)
            if self.log_depth:
                base_depth = torch.log(base_depth.clamp_min(LOG_DEPTH_RANGE[0]))
            if self.depth_gate:  # keep the splat's range where it covered the pixel
                depth = depth * (1.0 - condition[:, ALPHA].clamp(0.0, 1.0))
            depth = depth + base_depth
        depth = torch.exp(depth.clamp(*_LOG_DEPTH_BOUNDS)) if self.log_depth else F.relu(depth)
        return DecoderOutput(torch.cat((torch.sigmoid(rgb_logits), depth), dim=1), features, rgb_logits)
