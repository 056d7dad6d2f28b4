"""Typed configuration of the pixel-flow renderer (sizes ``tiny`` and ``paper``).

Every field carries a docstring. :func:`renderer_config_from_dict` / :func:`load_renderer_config`
build a :class:`RendererConfig` from plain data (e.g. YAML), starting from a named preset and
rejecting unknown keys with the dotted path of the offending field.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from image2sim.simulator.config import (
    ConfigError,
    config_to_dict,
    merge_config,
    read_mapping,
    require_at_least,
    require_in_range,
    require_one_of,
)
from image2sim.simulator.gaussians.config import SemanticConfig
from image2sim.simulator.trainer import TrainerConfig, check_trainer_config

__all__ = [
    "AlignerConfig",
    "DecoderConfig",
    "MeanFlowConfig",
    "LossConfig",
    "DistillConfig",
    "AblationConfig",
    "AugmentConfig",
    "CurriculumConfig",
    "TrainerConfig",
    "SemanticConfig",
    "RendererConfig",
    "tiny",
    "paper",
    "PRESETS",
    "renderer_config_from_dict",
    "load_renderer_config",
    "config_to_dict",
]

CONDITION_FEATURES = 16
"""Number of splatted feature channels in the condition C_p."""
CONDITION_CHANNELS = CONDITION_FEATURES + 3 + 1 + 1 + 3
"""C_p = [features (16), RGB (3), depth (1), alpha (1), target ray map (3)] = 24 channels."""
STATE_CHANNELS = 4
"""The flow state is the panoramic RGB-D observation: RGB (3) + normalised depth (1)."""


@dataclass
class AlignerConfig:
    """SemanticAligner: strided PanoConv2d stem to H/16, then transformer blocks on tokens."""

    stem_widths: tuple[int, ...] = (32, 64, 96, 128)
    """Channels after each stride-2 PanoConv2d; four entries reach H/16."""
    token_dim: int = 128
    """Width of the aligned tokens (1024 in the paper, the DINOv3 ViT-L width)."""
    depth: int = 2
    """Number of transformer blocks refining the tokens."""
    heads: int = 4
    """Attention heads per block (token_dim must be divisible by it)."""
    mlp_ratio: float = 4.0
    """Hidden width of the block MLP as a multiple of token_dim."""
    target_dim: int | None = None
    """Channels of the semantic backbone's tokens; a linear head maps token_dim to it when they
    differ. None: the tokens are compared directly (dims must match)."""


@dataclass
class DecoderConfig:
    """RenderingDecoder: conv encoder to H/16, transformer bottleneck, alpha-gated PixelShuffle decoder."""

    widths: tuple[int, ...] = (32, 48, 64, 96)
    """Channels of the four full-to-H/8 levels (H, H/2, H/4, H/8); the bottleneck sits at H/16."""
    blocks_per_level: tuple[int, ...] = (1, 1, 1, 1)
    """PanoBlocks per encoder and per decoder level (H, H/2, H/4, H/8); 0 at the full-resolution
    level keeps CPU training affordable (the JVP multiplies every elementwise op there)."""
    expansion: int = 4
    """Inverted-bottleneck expansion of the PanoBlocks."""
    bottleneck_dim: int = 128
    """Token width of the transformer bottleneck at H/16."""
    bottleneck_depth: int = 2
    """Number of transformer blocks in the bottleneck (8 in the paper)."""
    heads: int = 4
    """Attention heads per bottleneck block."""
    mlp_ratio: float = 4.0
    """Hidden width of the bottleneck MLP as a multiple of bottleneck_dim."""
    time_dim: int = 128
    """Width of each sinusoidal time embedding (t and h = t - r) and of the fused embedding."""
    time_scale: float = 1000.0
    """t and h are multiplied by this before the sinusoidal embedding (DiT convention)."""
    kernel_size: int = 7
    """Depth-wise kernel size of the PanoBlocks."""
    gate_bias: float = 2.0
    """Initial bias of the zero-initialised skip gate (sigmoid(2.0) = 0.88: trust the projection)."""
    depth_bias: float = 0.3
    """Initial bias of the depth head (normalised units) so the ReLU starts in its active range;
    with ``residual_heads`` the depth filled in where nothing was projected (alpha = 0)."""
    residual_heads: bool = True
    """Heads predict corrections around the splatted prior (a deliberate deviation from the
    paper, see docs/renderer.md): RGB = sigmoid(logit(c0) + delta) with c0 = A * prior_rgb +
    (1 - A) * 0.5, depth = ReLU(d0 + delta) with d0 = A * prior_depth + (1 - A) * depth_bias, both
    heads zero-initialised so an untrained network returns the prior where alpha = 1. False: the
    paper's absolute heads (sigmoid / ReLU of the head output)."""
    depth_head: Literal["relu", "log"] = "relu"
    """Output of the depth head. ``relu``: the issue's ReLU of (base + delta), additive in metres.
    ``log``: exp(log(base) + delta), a multiplicative correction of the prior's range. It is
    positive by construction (no dead ReLU) and its gradient is in relative depth error, the
    quantity AbsRel measures; real captures span 0.3-10 m in one panorama (docs/renderer.md)."""
    depth_gate: bool = False
    """With ``residual_heads``: the depth head's correction is scaled by (1 - alpha), so where the
    splat covered a pixel its range is kept and the network generates depth only in holes (the
    paper's "trust the projection where alpha is high" made exact for depth). Off: the correction
    applies everywhere, and on the CPU runs the one-step depth drifted away from an accurate splat
    (docs/renderer.md, "Depth drift")."""
    prior_fill: Literal["grey", "interpolate"] = "grey"
    """What the residual heads start from where alpha < 1: ``grey`` (0.5 and ``depth_bias``) or
    ``interpolate``, the prior's holes filled from their surroundings by normalised convolution
    (``renderer.holefill.fill_holes``, the benchmark's ``splat_fill``), so an untrained renderer
    equals that non-learned baseline and the network learns only what interpolation misses."""
    prior_filter: int = 0
    """With ``residual_heads`` (ignored without): kernel size of a linear convolution of the prior
    itself (its RGB logits and alpha) added to the RGB correction; 0 = none. A direct linear
    path from the blurred splat to the output, so the deconvolution a fixed filter can do is one
    convex step away instead of having to pass the network's bottlenecks (docs/renderer.md,
    "A linear path from the prior")."""
    prior_filter_init: Literal["least_squares", "zeros"] = "least_squares"
    """How ``sim train`` starts the prior filter: ``least_squares`` fits it in closed form to the
    training pairs before the first step (``renderer.prior_filter``; the best linear deconvolution
    of the training splats), ``zeros`` leaves it at zero (the untrained renderer is then the splat)."""
    prior_hidden: int = 0
    """With ``prior_filter`` > 0: width of a nonlinear path beside the linear filter, a per-pixel MLP
    on the same K x K neighbourhood of the prior's logits, alpha and range relative to the centre
    pixel (``renderer.prior_path.PriorNet``); 0 = linear only. It can decide per pixel what the one
    filter cannot: which side of a blended depth edge a pixel belongs to (docs/renderer.md,
    "A nonlinear path from the prior")."""
    prior_fit_steps: int = 0
    """Adam steps that ``sim train`` spends fitting the prior path (linear filter and ``prior_hidden``
    MLP together, after the least-squares start) to random training pixels before the first flow
    step (``renderer.prior_filter.fit_prior_path``); 0 = none. Per-pixel batches from every training
    pair reach in seconds what the flow training's whole-image batches did not in 300 steps."""


@dataclass
class MeanFlowConfig:
    """Alpha-gated source, linear path, x-prediction MeanFlow objective and samplers."""

    sigma_small: tuple[float, float] = (0.02, 0.02)
    """Noise scale where the projection is reliable (alpha = 1), per group (RGB, depth)."""
    sigma_large: tuple[float, float] = (1.0, 1.0)
    """Noise scale where nothing was projected (alpha = 0), per group (RGB, depth)."""
    t_eps: float = 1e-2
    """epsilon in u = (z_t - x) / max(t, epsilon); bounds 1/t near the target end of the path."""
    p_r_equals_t: float = 0.5
    """Probability that a training pair has r = t (instantaneous flow matching)."""
    tangent: Literal["target", "model"] = "target"
    """Tangent for dz/dt in the JVP: the conditional velocity z_src - X ("target") or the model's
    own instantaneous velocity u(z_t, t, t) without gradient ("model")."""
    weight_k: float = 4.0
    """Opacity-adaptive weight W(A) = 1 + k (1 - A) of the flow loss (stage-2 spatial focus)."""
    norm_c: float = 1e-3
    """Adaptive loss normalisation loss / sg(loss + c)."""
    norm_power: float = 1.0
    """Power p of the adaptive normalisation loss / sg(loss + c)^p (0 disables it)."""
    depth_scale: float = 10.0
    """Metres per unit of the state's depth channel (state depth = metres / depth_scale)."""
    sample_steps: int = 1
    """Default number of sampler steps at inference (1 = one-step rendering)."""


@dataclass
class LossConfig:
    """Loss weights of the full objective (per-stage weights live in CurriculumConfig)."""

    lambda_rec: float = 0.1
    """Weight of the reconstruction loss (L1 of the denoised prediction vs the target)."""
    lambda_align: float = 0.1
    """Weight of the semantic alignment (cosine) loss."""
    lambda_flow: float = 1.0
    """Weight of the MeanFlow loss."""
    saturation: float = 0.2
    """Coefficient of the saturation penalty on the flow's implied clean RGB (paper: 0.2)."""
    lpips_weights: str | None = None
    """Path of user-supplied LPIPS (VGG16 + linear heads) weights (.safetensors); None or missing:
    one warning and lambda_perc = 0. Nothing is ever downloaded."""
    rgb_weight_in_rec: float = 1.0
    """Relative weight of RGB in the reconstruction loss."""
    depth_weight_in_rec: float = 1.0
    """Relative weight of (valid) depth in the reconstruction loss."""
    lambda_pixel: float = 0.0
    """Weight of the pixel-fidelity term: the one-step RGB's mean squared error, adaptively
    normalised like the flow loss (mse / sg(mse + pixel_norm_c), i.e. a log-MSE / PSNR gradient).
    0 in the paper preset, whose sharpness comes from LPIPS (lambda_perc 1-4). Where no LPIPS
    weights exist (every CPU run here) the L1 reconstruction at lambda_rec 0.1 alone leaves the
    one-step output at the blurred prior (measured in reports/renderer_tiny.md); the tiny preset
    sets this term instead."""
    pixel_depth_weight: float = 0.0
    """Weight, inside the pixel term, of the one-step depth's squared relative error over valid
    pixels (normalised the same way). It trades RGB gain for depth: at 1.0, after 400 tiny steps,
    depth AbsRel 0.056 instead of 0.091 but +0.11 instead of +1.42 dB over splat-only."""
    pixel_norm_c: float = 1e-4
    """c of the pixel term's normalisation mse / sg(mse + c) (a 22 dB image has mse ~ 6e-3)."""


@dataclass
class DistillConfig:
    """Momentum self-distillation from an EMA teacher fed the privileged (ground-truth) source."""

    ema_decay: float = 0.999
    """Teacher update theta_T <- decay * theta_T + (1 - decay) * theta_S."""
    beta: float = 0.1
    """Weight of the squared-L2 term next to the cosine term."""
    level_weights: tuple[float, ...] = (4.0, 3.0, 2.0, 1.0)
    """Unnormalised weights per decoder level, deepest (H/8) first; normalised to sum to 1."""
    normalise_features: bool = False
    """Take the squared-L2 term between per-pixel channel-normalised features (zero mean, unit
    variance over channels; the cosine term is scale-free already). False: the paper's raw
    features, whose L2 grows with the activations: a wider tiny model with full-resolution blocks
    reached a distillation loss of 1e4 at the stage-2 boundary on HM3D and diverged
    (reports/renderer_tiny.md)."""


@dataclass
class AblationConfig:
    """Switches of the paper's Table 4."""

    no_pixel_flow: bool = False
    """Splat only: the renderer returns the projected RGB-D prior without any network."""
    no_semantic: bool = False
    """No SemanticAligner / SemanticInjector and no alignment loss."""
    no_alpha_gate: bool = False
    """Plain additive skips instead of AlphaGatedSkip."""
    no_distill: bool = False
    """No EMA teacher and no distillation loss."""


@dataclass
class AugmentConfig:
    """Training augmentations of the (condition, target) panorama pairs (``renderer.augment``)."""

    yaw_roll: bool = False
    """Turn every training pair about the vertical axis by a random whole number of columns (the
    condition's ray map stays put): W variants of each panorama, exact for real captures too."""
    mirror_probability: float = 0.0
    """Probability of mirroring a training pair left-right (a capture of the mirrored house)."""


@dataclass
class CurriculumConfig:
    """Three-stage schedule (stage boundaries in optimiser steps) and per-stage loss weights."""

    stage2_start: int = 100_000
    """First step of stage 2 (flow + distillation with spatial focus)."""
    stage3_start: int = 300_000
    """First step of stage 3 (high-frequency refinement, backbone frozen)."""
    total_steps: int = 400_000
    """Total optimiser steps."""
    lambda_perc: tuple[float, float, float] = (1.0, 2.0, 4.0)
    """Perceptual-loss weight per stage."""
    lambda_distill: tuple[float, float, float] = (0.0, 2.0, 2.0)
    """Distillation weight per stage (0 in stage 1: no teacher yet)."""
    lr: float = 1e-4
    """AdamW learning rate."""
    min_lr: float = 1e-6
    """Cosine schedule floor."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    grad_clip: float = 1.0
    """Gradient-norm clip."""
    batch_size: int = 2
    """Per-device batch size."""


def scaled_curriculum(curriculum: CurriculumConfig, steps: int) -> CurriculumConfig:
    """``curriculum`` compressed or stretched to ``steps`` optimiser steps: both stage boundaries
    keep their fraction of the schedule and the cosine learning rate reaches its floor at the new
    end. Stopping a long schedule early (``sim train --max-steps``) instead leaves the model at a
    high learning rate in stage 1, without the teacher or the refinement stage."""
    if int(steps) < 3:
        raise ValueError(f"a three-stage curriculum needs at least 3 steps, got {steps}")
    total = max(1, curriculum.total_steps)
    s2 = min(max(1, round(curriculum.stage2_start * steps / total)), steps - 2)
    s3 = min(max(s2 + 1, round(curriculum.stage3_start * steps / total)), steps - 1)
    return dataclasses.replace(curriculum, stage2_start=s2, stage3_start=s3, total_steps=int(steps))


@dataclass
class RendererConfig:
    """Complete pixel-flow renderer configuration."""

    name: str = "tiny"
    """Preset name this configuration started from."""
    height: int = 128
    """Panorama height in pixels (width = 2 * height); must be divisible by 16."""
    width: int = 256
    """Panorama width in pixels; must be divisible by 16."""
    aligner: AlignerConfig = field(default_factory=AlignerConfig)
    """SemanticAligner."""
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    """RenderingDecoder."""
    meanflow: MeanFlowConfig = field(default_factory=MeanFlowConfig)
    """MeanFlow maths."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss weights."""
    distill: DistillConfig = field(default_factory=DistillConfig)
    """Self-distillation."""
    ablation: AblationConfig = field(default_factory=AblationConfig)
    """Table-4 ablation switches."""
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    """Training schedule."""
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    """Training augmentations (off by default)."""
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    """Hardware and distribution of training."""
    semantic: SemanticConfig = field(default_factory=SemanticConfig)
    """Frozen backbone (DINOv3 from a local folder) whose patch tokens of the target panorama are the
    aligner's targets in training (L_align). ``none``: no alignment term unless the samples carry
    ``target_tokens``. The same section as the scene encoder's."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when the configuration is inconsistent."""
        if self.height <= 0 or self.width <= 0 or self.height % 16 or self.width % 16:
            raise ValueError(
                f"renderer height/width must be positive multiples of 16, got {self.height}x{self.width}"
            )
        if len(self.decoder.widths) != 4:
            raise ValueError(f"decoder.widths needs 4 levels (H..H/8), got {self.decoder.widths}")
        if len(self.decoder.blocks_per_level) != 4 or min(self.decoder.blocks_per_level) < 0:
            raise ValueError(
                f"decoder.blocks_per_level needs 4 non-negative counts, got {self.decoder.blocks_per_level}"
            )
        if len(self.aligner.stem_widths) != 4:
            raise ValueError(f"aligner.stem_widths needs 4 stride-2 stages, got {self.aligner.stem_widths}")
        if self.decoder.bottleneck_dim % self.decoder.heads:
            raise ValueError("decoder.bottleneck_dim must be divisible by decoder.heads")
        if self.decoder.depth_head not in ("relu", "log"):
            raise ValueError(f"decoder.depth_head must be 'relu' or 'log', got {self.decoder.depth_head!r}")
        if self.decoder.depth_head == "log" and self.decoder.depth_bias <= 0:
            raise ValueError(
                "decoder.depth_head 'log' needs depth_bias > 0 (the range of empty pixels), "
                f"got {self.decoder.depth_bias}"
            )
        pf = self.decoder.prior_filter
        if pf < 0 or (pf and pf % 2 == 0):
            raise ValueError(f"decoder.prior_filter must be 0 or an odd kernel size, got {pf}")
        if self.decoder.prior_hidden < 0 or self.decoder.prior_fit_steps < 0:
            raise ValueError(
                "decoder.prior_hidden and decoder.prior_fit_steps must be >= 0, got "
                f"{self.decoder.prior_hidden} and {self.decoder.prior_fit_steps}"
            )
        if self.decoder.prior_hidden and not pf:
            raise ValueError(
                f"decoder.prior_hidden ({self.decoder.prior_hidden}) needs decoder.prior_filter > 0 "
                "(its kernel size)"
            )
        if self.decoder.prior_filter_init not in ("least_squares", "zeros"):
            raise ValueError(
                "decoder.prior_filter_init must be 'least_squares' or 'zeros', "
                f"got {self.decoder.prior_filter_init!r}"
            )
        if self.decoder.prior_fill not in ("grey", "interpolate"):
            raise ValueError(
                f"decoder.prior_fill must be 'grey' or 'interpolate', got {self.decoder.prior_fill!r}"
            )
        if self.aligner.token_dim % self.aligner.heads:
            raise ValueError("aligner.token_dim must be divisible by aligner.heads")
        if self.decoder.bottleneck_dim % 4 or self.aligner.token_dim % 4 or self.decoder.time_dim % 2:
            raise ValueError("bottleneck_dim and token_dim must be multiples of 4, time_dim even")
        if len(self.distill.level_weights) != 4 or any(w < 0 for w in self.distill.level_weights):
            raise ValueError(
                f"distill.level_weights needs 4 non-negative values, got {self.distill.level_weights}"
            )
        if sum(self.distill.level_weights) <= 0:
            raise ValueError("distill.level_weights must not all be zero")
        require_in_range(
            self, ("distill.ema_decay", "meanflow.p_r_equals_t", "augment.mirror_probability"), 0.0, 1.0
        )
        mf = self.meanflow
        if len(mf.sigma_small) != 2 or len(mf.sigma_large) != 2:
            raise ValueError("meanflow.sigma_small/sigma_large need (rgb, depth) pairs")
        if min(*mf.sigma_small, *mf.sigma_large) < 0:
            raise ValueError("meanflow sigmas must be non-negative")
        if not mf.t_eps > 0:
            raise ValueError(f"meanflow.t_eps must be positive, got {mf.t_eps}")
        require_one_of(self, "meanflow.tangent", ("target", "model"))
        if mf.depth_scale <= 0:
            raise ValueError(f"meanflow.depth_scale must be positive, got {mf.depth_scale}")
        require_at_least(self, ("meanflow.sample_steps", "curriculum.batch_size"), 1)
        cur = self.curriculum
        if not 0 <= cur.stage2_start <= cur.stage3_start <= cur.total_steps:
            raise ValueError("curriculum needs 0 <= stage2_start <= stage3_start <= total_steps")
        sem = self.semantic
        require_one_of(self, "semantic.backbone", ("none", "dinov3"))
        token_out = self.aligner.target_dim or self.aligner.token_dim
        if sem.backbone != "none" and token_out != sem.dim:
            raise ValueError(
                f"semantic.dim is {sem.dim} but the aligner's tokens have {token_out} channels: "
                "set aligner.target_dim to the backbone's hidden size"
            )
        check_trainer_config(self.trainer, "trainer")


def tiny() -> RendererConfig:
    """CPU-sized renderer at 128 x 256 (~0.65 M parameters), 1500-step curriculum."""
    return RendererConfig(
        name="tiny",
        height=128,
        width=256,
        aligner=AlignerConfig(stem_widths=(16, 32, 48, 64), token_dim=64, depth=2, heads=4),
        decoder=DecoderConfig(
            widths=(16, 24, 32, 48),
            blocks_per_level=(0, 0, 1, 1),
            expansion=2,
            bottleneck_dim=64,
            bottleneck_depth=2,
            heads=4,
            time_dim=64,
            # Ungated, the one-step depth drifted from an accurate splat on every CPU run (AbsRel
            # 0.07-0.22 against the splat's 0.035 on procedural houses); gated it stays at the splat
            # and RGB gains (docs/renderer.md, "Depth drift and the curriculum length").
            depth_gate=True,
            # A 7x7 linear path from the filled prior, started by least squares on the training
            # pairs: on the demo's held-out views +0.57 dB over splat_fill where the network alone
            # was -0.07 dB (docs/renderer.md, "A linear path from the prior").
            prior_filter=7,
            prior_fill="interpolate",
            # ... and a per-pixel MLP beside it, fitted for 3000 Adam steps on random training
            # tiles before the flow training (about 30 s on one core): the one-step renderer then
            # renders the demo's held-out views 1.4 dB above splat_fill; width 64 gained 0.07 dB
            # more at 3x the MLP's cost (docs/renderer.md, "A nonlinear path from the prior").
            prior_hidden=32,
            prior_fit_steps=3000,
        ),
        # The paper's 1:2:1 stage proportions in 1500 steps (`make train-sim-tiny`, issue budget
        # 60 min on 2 cores): measured 28 min with one thread on a shared 2-core machine
        # (reports/renderer_tiny.md); a busier machine is slower.
        curriculum=CurriculumConfig(
            stage2_start=375, stage3_start=1125, total_steps=1500, lr=2e-3, min_lr=1e-5
        ),
        # No LPIPS weights on CPU: the pixel-fidelity term takes the perceptual term's role
        # (weight 4 = the paper's final lambda_perc). Measured on held-out procedural views after
        # 400 steps: one step +1.42 dB over splat-only with it, +0.40 dB at weight 1, +0.18 dB
        # without (reports/renderer_tiny.md).
        loss=LossConfig(lambda_pixel=4.0),
    )


def paper() -> RendererConfig:
    """The paper's renderer at 512 x 1024: 1024-d aligned tokens, an 8-block bottleneck, 400k steps."""
    return RendererConfig(
        name="paper",
        height=512,
        width=1024,
        aligner=AlignerConfig(
            stem_widths=(64, 128, 256, 512), token_dim=1024, depth=2, heads=16, target_dim=1024
        ),
        decoder=DecoderConfig(
            widths=(64, 128, 256, 512),
            blocks_per_level=(2, 2, 2, 2),
            bottleneck_dim=768,
            bottleneck_depth=8,
            heads=12,
            time_dim=256,
        ),
        curriculum=CurriculumConfig(),
        trainer=TrainerConfig(accelerator="gpu", devices=8, strategy="ddp", precision="bf16-mixed"),
        semantic=SemanticConfig(backbone="dinov3", weights=None, dim=1024, patch_size=16),
    )


PRESETS: dict[str, typing.Callable[[], RendererConfig]] = {"tiny": tiny, "paper": paper}


def renderer_config_from_dict(data: dict | None, preset: str | None = None) -> RendererConfig:
    """Build a config from ``data`` on top of ``preset`` (default: ``data['name']`` or ``tiny``);
    unknown keys and wrong types raise :class:`ConfigError` naming the dotted field."""
    data = dict(data or {})
    name = preset or data.get("name", "tiny")
    if name not in PRESETS:
        raise ConfigError(f"unknown renderer preset {name!r}; choose from {sorted(PRESETS)}")
    data.setdefault("name", name)
    return merge_config(PRESETS[name](), data)


def load_renderer_config(path_or_name: str | Path) -> RendererConfig:
    """A preset name (``tiny``/``paper``) or a YAML/JSON file with a mapping of overrides."""
    if str(path_or_name) in PRESETS:
        return PRESETS[str(path_or_name)]()
    path = Path(path_or_name)
    if not path.is_file():
        raise FileNotFoundError(
            f"renderer config {path} does not exist (and is not one of {sorted(PRESETS)})"
        )
    data = read_mapping(path)
    try:
        return renderer_config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
