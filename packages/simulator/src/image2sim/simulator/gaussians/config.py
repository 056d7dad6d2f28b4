"""Typed configuration of scene encoding and Gaussian scene construction (presets ``tiny`` / ``paper``).

Every field carries a docstring. :func:`gaussian_config_from_dict` / :func:`load_gaussian_config`
start from a named preset and overlay plain data (e.g. YAML/JSON) with the shared
:mod:`image2sim.simulator.config` mechanism, which rejects unknown keys with the dotted path of the
offending field, so a typo never silently falls back to a default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from image2sim.simulator.config import ConfigError as SharedConfigError
from image2sim.simulator.config import (
    config_to_dict,
    merge_config,
    read_mapping,
    require_at_least,
    require_in_range,
    require_one_of,
)
from image2sim.simulator.trainer import TrainerConfig, check_trainer_config

__all__ = [
    "SemanticConfig",
    "EncoderConfig",
    "FusionConfig",
    "Stage1Config",
    "GaussianConfig",
    "ConfigError",
    "tiny",
    "paper",
    "PRESETS",
    "gaussian_config_from_dict",
    "load_gaussian_config",
    "config_to_dict",
]

FEATURE_DIM = 16
"""Channels of the per-Gaussian scene features (the renderer's condition expects 16)."""


ConfigError = SharedConfigError
"""Invalid Gaussian/encoder configuration (the repository's one config error class)."""


@dataclass
class SemanticConfig:
    """Semantic stream: a frozen DINOv3 ViT (patch tokens at H/patch) or none."""

    backbone: Literal["none", "dinov3"] = "none"
    """``dinov3``: frozen DINOv3 ViT loaded from ``weights``; ``none``: detail stream only (the paper's
    "w/o semantic features" setting, and the CPU default when no weights exist)."""
    weights: str | None = None
    """Local folder with a transformers ``DINOv3ViTModel`` (config.json + safetensors). Never downloaded."""
    dim: int = 1024
    """Channels of the patch tokens (1024 for ViT-L/16). Checked against the loaded model."""
    patch_size: int = 16
    """ViT patch size in pixels; tokens live at H/patch_size x W/patch_size."""
    mean: tuple[float, float, float] = (0.485, 0.456, 0.406)
    """ImageNet normalisation mean applied by the hand-written preprocessing."""
    std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    """ImageNet normalisation standard deviation."""


@dataclass
class EncoderConfig:
    """Detail encoder, feature upsampler and heads of the learned encoder (paper appendix, Stage 1)."""

    height: int = 128
    """Input height in pixels (frames are area-resized to height x width); a multiple of 16."""
    width: int = 256
    """Input width in pixels; a multiple of 16 (2 x height for panoramas)."""
    detail_widths: tuple[int, int, int, int] = (16, 24, 32, 48)
    """Channels of the detail pyramid at H, H/2, H/4, H/8."""
    bottleneck_width: int = 64
    """Channels at H/16, where the semantic tokens (or a strided detail map) enter the upsampler."""
    upsampler_widths: tuple[int, int, int, int] = (48, 32, 24, 16)
    """Channels after each PixelShuffle stage of the FeatureUpsampler (H/8, H/4, H/2, H)."""
    blocks_per_stage: int = 1
    """PanoBlocks after every fusion (detail levels and upsampler stages)."""
    kernel_size: int = 7
    """Depth-wise kernel size of the PanoBlocks."""
    expansion: int = 4
    """Inverted-bottleneck expansion of the PanoBlocks."""
    feature_dim: int = FEATURE_DIM
    """Scene feature channels per Gaussian."""
    depth_scale: float = 10.0
    """Metres per unit of the normalised depth input channel."""
    scale_min: float = 0.002
    """Lower bound of every Gaussian standard deviation, metres."""
    scale_max: float = 0.5
    """Upper bound of every Gaussian standard deviation, metres."""
    scale_init: float = 0.6
    """Initial standard deviation as a multiple of the pixel footprint (the identity baseline's value)."""
    opacity_init: float = 0.95
    """Initial opacity of every Gaussian (the opacity head's bias)."""
    identity_shape: Literal["sphere", "disc"] = "disc"
    """Shape of the ``identity`` encoder's Gaussians: ``disc`` (std scale_init x footprint in the
    surface plane, ``disc_thickness`` times it along the ``point_normals`` normal) or ``sphere``
    (isotropic, the earlier default). Discs stop near surface points from covering farther ones
    at grazing angles: held-out splats +0.74 dB (procedural middle) / +0.99 dB (HM3D sample),
    depth AbsRel 0.082 -> 0.059 / 0.153 -> 0.112, and the tiny renderer trained on disc
    conditions renders one step at 25.60 dB vs 24.97 dB on sphere conditions
    (reports/renderer_tiny.md)."""
    disc_thickness: float = 0.1
    """Std along the normal of a ``disc`` Gaussian, as a fraction of its in-plane std."""


@dataclass
class FusionConfig:
    """How per-pixel Gaussians of many frames are fused into the scene memory (MemoryState)."""

    policy: Literal["footprint", "fixed"] = "footprint"
    """``footprint``: each point is fused at a voxel size that follows its observed pixel footprint
    (range x angular pixel size), quantised to power-of-two levels of ``base_voxel``; where a finer
    level already models a cell, coarser observations of it are dropped. ``fixed``: one voxel size."""
    views: Literal["best", "all"] = "best"
    """Which frames model a surface point before voxel fusion. ``best``: only the frame that sees it
    with the finest sampling interval (near and frontal; see :mod:`~image2sim.simulator.gaussians.views`),
    so each region is represented once, as sharp as its best view; ``all``: every frame that sees it
    (averaged per voxel: blurrier and nearer than the surface as views are added)."""
    same_surface_tolerance: float = 0.02
    """``views: best``: a frame sees the same surface point as a Gaussian when it looks at the side the
    Gaussian faces and its depth there agrees with the Gaussian's distance within this fraction of
    the depth (+ 2 sampling intervals)."""
    interval_step: float = 1.5
    """``views: best``: sampling intervals are compared in steps of this factor (log-quantised); views
    within one step tie and the lower frame index wins, so ownership forms whole patches rather than
    a noise-driven speckle with gaps between its pieces (1: exact comparison)."""
    carve_views: int = 24
    """``views: best``: each frame's Gaussians are also dropped where one of this many nearest frames
    (by camera centre) saw empty space through them (silhouette halos, floaters); 0 disables. 24
    against 8 (the default until 2026-11-29): own-pose gap -0.79 dB on HM3D, -0.02 to -0.19 dB on
    procedural houses, held-out +0.11 to +0.14 dB, build +9 CPU-s on HM3D (docs/scenes.md)."""
    carve_extent: float = 3.0
    """``views: best``: carving also tests the points this many standard deviations out along each
    Gaussian's two largest axes (its splat's reach), not only its centre: a foreground Gaussian whose
    splat reaches across another frame's silhouette onto a background that frame saw is dropped
    (0: the centre only). At 3, against 0: own-pose gap -0.4 to -1.2 dB, held-out -0.05 to +0.30 dB,
    build +27-65 % (docs/scenes.md)."""
    owner_cos: float = 0.5
    """``views: best``: a frame replaces others' Gaussians only where it sees the surface at a viewing
    cosine of at least this (a grazing frame samples a surface in sparse rows, and alone leaves
    gaps between them: a wall seen frontally only by a held-out frame; 0: any frame)."""
    grazing_cos: float = 0.2
    """``views: best``: viewing cosines below this count as this (a pixel's sampling interval is
    footprint / max(cos, grazing_cos)); also used where the surface normal is unknown."""
    voxel_size: float = 0.05
    """Voxel edge of the ``fixed`` policy, metres."""
    base_voxel: float = 0.01
    """Finest voxel edge (level 0) of the ``footprint`` policy, metres."""
    levels: int = 6
    """Number of power-of-two levels of the ``footprint`` policy (level l has edge base_voxel * 2^l)."""
    footprint_factor: float = 1.0
    """Footprint voxel target = this x pixel footprint (1: about one Gaussian per pixel at first sight)."""
    cover_factor: float = 0.5
    """Fused Gaussians get standard deviations of at least this x their voxel edge so merged points
    leave no holes (0 disables the floor)."""
    min_range: float = 0.1
    """Pixels observed closer than this (metres) are dropped."""
    max_range: float = 20.0
    """Pixels observed farther than this (metres) are dropped (depth is unreliable there)."""
    min_opacity: float = 0.01
    """Gaussians with lower opacity are pruned."""
    threads: int = 1
    """torch threads while fusing: its many small gather/unique ops are dominated by thread start-up
    on a shared CPU (measured 30x slower with 2 threads under load); 0 leaves torch's setting."""
    edge_tolerance: float = 0.1
    """When frames are area-resized, a block whose valid depths spread by more than this fraction
    keeps its nearest depth instead of the mean, so no point floats between two surfaces."""


@dataclass
class Stage1Config:
    """Stage-1 (geometry initialisation) training of the encoder."""

    num_sources: int = 3
    """K source frames per sample; the Gaussians of all K are splatted at one held-out target."""
    steps: int = 100
    """Optimisation steps."""
    lr: float = 3e-4
    """AdamW learning rate."""
    weight_decay: float = 0.01
    """AdamW weight decay."""
    w_rgb: float = 1.0
    """Weight of the masked L1 RGB reconstruction."""
    w_depth: float = 0.5
    """Weight of the masked L1 depth reconstruction (depth in units of encoder.depth_scale)."""
    w_align: float = 0.1
    """Weight of the cosine alignment of projected features to the target's DINOv3 tokens (only with a
    semantic backbone)."""
    w_labels: float = 0.0
    """Weight of the category target: a linear head over the splatted features predicts the held-out
    target's per-pixel category (cross-entropy over covered, labelled pixels). Needs captures with
    ``semantics/`` (procedural ones have them). A weights-free semantic target where no DINOv3 is at
    hand, so the features carry what the object is; 0 = off."""
    w_scale: float = 0.01
    """Weight of the scale regulariser (mean log of scale / footprint, squared)."""
    min_alpha: float = 0.5
    """Target pixels with lower splatted alpha are excluded from the reconstruction mask."""
    backend: str = "auto"
    """Splatting backend used in training."""
    seed: int = 0
    """Seed of the sample order."""
    log_every: int = 10
    """Steps between scalar logs."""
    image_every: int = 50
    """Steps between image grids written to the log folder (0 disables)."""
    checkpoint_every: int = 50
    """Steps between resumable checkpoints."""
    wandb: bool = False
    """Log to Weights & Biases (offline unless WANDB_MODE says otherwise); CSV logging is always on."""


@dataclass
class GaussianConfig:
    """Everything that turns posed RGB-D frames into a Gaussian scene."""

    name: str = "tiny"
    """Preset name this config started from (recorded in manifests)."""
    semantic: SemanticConfig = field(default_factory=SemanticConfig)
    """Semantic stream."""
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    """Detail stream, upsampler and heads."""
    fusion: FusionConfig = field(default_factory=FusionConfig)
    """Scene memory fusion and pruning."""
    train: Stage1Config = field(default_factory=Stage1Config)
    """Stage-1 training."""
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    """Hardware and distribution of stage-1 training (one scene sample per device and step). The
    paper does not state its stage-1 hardware: ``paper`` runs on one GPU; set ``devices`` and
    ``strategy: ddp`` for more."""

    def validate(self) -> GaussianConfig:
        """Check value ranges; raises :class:`ConfigError` naming the field."""
        e, f, s = self.encoder, self.fusion, self.semantic
        try:
            check_trainer_config(self.trainer)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        if e.height <= 0 or e.width <= 0 or e.height % 16 or e.width % 16:
            raise ConfigError(
                f"encoder.height/width must be positive multiples of 16, got {e.height}x{e.width}"
            )
        for name in ("detail_widths", "upsampler_widths"):
            widths = getattr(e, name)
            if len(widths) != 4 or any(int(w) <= 0 for w in widths):
                raise ConfigError(f"encoder.{name} needs 4 positive widths, got {widths}")
        if e.bottleneck_width <= 0 or e.feature_dim < 0 or e.blocks_per_stage < 0 or e.expansion < 1:
            raise ConfigError(
                "encoder.bottleneck_width > 0, feature_dim >= 0, blocks_per_stage >= 0, expansion >= 1"
            )
        if e.kernel_size < 1 or e.kernel_size % 2 == 0:
            raise ConfigError(f"encoder.kernel_size must be odd and positive, got {e.kernel_size}")
        if not 0 < e.scale_min < e.scale_max:
            raise ConfigError(f"encoder needs 0 < scale_min < scale_max, got {e.scale_min}, {e.scale_max}")
        require_one_of(self, "encoder.identity_shape", ("sphere", "disc"))
        require_in_range(self, "encoder.disc_thickness", 0, 1, low_open=True)
        if not 0 < e.opacity_init < 1 or e.scale_init <= 0 or e.depth_scale <= 0:
            raise ConfigError(
                "encoder.opacity_init must lie in (0, 1); scale_init and depth_scale must be > 0"
            )
        require_one_of(self, "semantic.backbone", ("none", "dinov3"))
        if s.patch_size <= 0 or s.dim <= 0 or len(s.mean) != 3 or len(s.std) != 3 or min(s.std) <= 0:
            raise ConfigError("semantic.patch_size/dim must be > 0, mean/std 3 values with std > 0")
        require_one_of(self, "fusion.policy", ("footprint", "fixed"))
        if not (f.voxel_size > 0 and f.base_voxel > 0 and f.footprint_factor > 0):
            raise ConfigError("fusion.voxel_size, base_voxel and footprint_factor must be > 0")
        require_in_range(self, "fusion.levels", 1, 24)
        if f.cover_factor < 0 or not 0 <= f.min_range < f.max_range or not 0 <= f.min_opacity < 1:
            raise ConfigError(
                "fusion needs cover_factor >= 0, 0 <= min_range < max_range, 0 <= min_opacity < 1"
            )
        require_at_least(self, ("fusion.carve_views", "fusion.threads", "fusion.carve_extent"), 0)
        require_in_range(self, "fusion.owner_cos", 0, 1)
        require_one_of(self, "fusion.views", ("best", "all"))
        if not (f.same_surface_tolerance > 0 and 0 < f.grazing_cos <= 1 and f.interval_step >= 1):
            raise ConfigError(
                "fusion needs same_surface_tolerance > 0, grazing_cos in (0, 1] and interval_step >= 1, "
                f"got {f.same_surface_tolerance}, {f.grazing_cos}, {f.interval_step}"
            )
        require_in_range(self, "fusion.edge_tolerance", 0, math.inf, low_open=True, high_open=True)
        t = self.train
        if t.num_sources < 1 or t.steps < 0 or t.lr <= 0:
            raise ConfigError("train.num_sources >= 1, steps >= 0 and lr > 0 are required")
        require_at_least(self, ("train.w_labels",), 0)
        return self


def tiny() -> GaussianConfig:
    """CPU preset: no semantic backbone, 128x256 panoramas, small widths."""
    return GaussianConfig(name="tiny").validate()


def paper() -> GaussianConfig:
    """Paper preset: frozen DINOv3 ViT-L/16 (1024-d tokens at H/16), 512x1024 panoramas, paper widths."""
    return GaussianConfig(
        name="paper",
        semantic=SemanticConfig(backbone="dinov3", weights=None, dim=1024, patch_size=16),
        encoder=EncoderConfig(
            height=512,
            width=1024,
            detail_widths=(64, 128, 256, 512),
            bottleneck_width=1024,
            upsampler_widths=(512, 256, 128, 64),
            blocks_per_stage=2,
        ),
        train=Stage1Config(num_sources=4, steps=100_000, lr=1e-4, wandb=True),
        trainer=TrainerConfig(accelerator="gpu"),
    ).validate()


PRESETS = {"tiny": tiny, "paper": paper}
"""Named presets (factories returning fresh configs)."""


def gaussian_config_from_dict(data: dict, preset: str | None = None) -> GaussianConfig:
    """Build a config from plain data over a preset (``data["preset"]`` or ``preset``, default tiny)."""
    data = dict(data)
    name = data.pop("preset", None) or preset or data.get("name") or "tiny"
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r} (expected one of {sorted(PRESETS)})")
    return merge_config(PRESETS[name](), data).validate()


def load_gaussian_config(path_or_name: str | Path) -> GaussianConfig:
    """A preset name (``tiny``/``paper``) or a YAML/JSON file of overrides over its ``preset``."""
    text = str(path_or_name)
    if text in PRESETS:
        return PRESETS[text]()
    path = Path(text)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file (and not a preset name {sorted(PRESETS)})")
    data = read_mapping(path)
    try:
        return gaussian_config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
