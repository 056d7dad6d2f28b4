"""Train a small monocular depth prior on posed RGB-D captures, for ``lift --depth model`` / ``mvs+model``.

No pretrained depth weights can be downloaded on every machine this project runs on, yet the
lift's plane sweep leaves textureless and far floor without depth (docs/lift.md). This module
trains a transformers Depth Anything (``DepthAnythingForDepthEstimation``, a small DINOv2
backbone and DPT head built from a config, random start) on any RGB-D captures the registry reads,
and saves it as a folder :func:`~image2sim.simulator.lift.depth.load_depth_model` loads. The
prior is *relative*: it is trained, as MiDaS and Depth Anything are, to predict inverse depth up to
a per-image scale and shift, which the lift fits to each view's own SfM and stereo depths.

Training views are pinhole crops: a pinhole frame gives random square crops; a panorama gives
pinhole views at random yaw, pitch and field of view (colour bilinear, range nearest so no depth is
blended across an edge, converted to z-depth). The loss (:func:`ssi_loss`) aligns each prediction
to the target's inverse depth by least squares on the valid pixels and takes the mean absolute
error relative to the target's mean inverse depth, plus a term that makes the output grow as things
come nearer (the sign the lift's alignment assumes).

Measured here (docs/lift.md): 25 CPU minutes on 36 procedural houses give a prior that errs by
about 17 % in inverse depth, too much to complete the lift's floor; it is a tool for longer
training (a GPU), and the shape a pretrained model's use takes.

What it learns is the captures' world: trained on procedural houses, it knows procedural houses.
It is a prior for captures like its training captures, not a general depth model.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from image2sim.simulator.io.atomic import atomic_dir
from image2sim.simulator.lift.types import options_from_kwargs
from image2sim.simulator.schedules import warmup_cosine

__all__ = [
    "DepthPriorConfig",
    "build_depth_prior",
    "ssi_loss",
    "ViewPool",
    "train_depth_prior",
]

ARCHITECTURES = {
    "depth_anything": {"multiple": 14, "mean": (0.485, 0.456, 0.406), "std": (0.229, 0.224, 0.225)},
    "glpn": {"multiple": 32, "mean": (0.0, 0.0, 0.0), "std": (1.0, 1.0, 1.0)},
}
"""The transformers depth models a prior can be: the side multiple their image processor resizes to,
and the colour normalisation it applies after scaling to [0, 1] (Depth Anything: ImageNet's; GLPN:
none). Training normalises the crops the same way."""


@dataclass
class DepthPriorConfig:
    """Model size and training schedule of a depth prior (:func:`train_depth_prior`)."""

    architecture: str = "depth_anything"
    """``depth_anything`` (a DINOv2 ViT with patch 14 and a DPT head) or ``glpn`` (a hierarchical
    SegFormer encoder with strides 4-32 and a light decoder at full resolution)."""
    image_size: int = 140
    """Training crop side in pixels, and the processor's resize height (a multiple of 14 for
    ``depth_anything``, of 32 for ``glpn``)."""
    hidden_size: int = 64
    """Width of the DINOv2 backbone."""
    layers: int = 4
    """Backbone transformer layers, at least 4 (the DPT head reads the last four)."""
    heads: int = 4
    """Attention heads of the backbone."""
    steps: int = 2000
    """Optimiser steps."""
    batch_size: int = 16
    """Training views per step."""
    lr: float = 1e-3
    """Peak AdamW learning rate (linear warm-up over 5 % of the steps, cosine decay to 5 %)."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    hfov_min_deg: float = 60.0
    """Narrowest horizontal field of view of a view cut from a panorama, degrees."""
    hfov_max_deg: float = 100.0
    """Widest horizontal field of view of a view cut from a panorama, degrees."""
    level_fraction: float = 0.5
    """Share of panorama views at pitch 0 (level cameras, as pinhole captures and side cube faces)."""
    vertical_fraction: float = 0.2
    """Share of panorama views straight up or down (the cube's top and bottom faces)."""
    max_pitch_deg: float = 60.0
    """The other views draw their pitch uniformly from +-this."""
    colour_noise: float = 2.0
    """Std of Gaussian colour noise added to the crops, in 0..255 levels (capture sensor noise)."""
    min_valid_fraction: float = 0.5
    """A training view with fewer valid depth pixels is drawn again."""
    frames_per_capture: int = 0
    """At most this many frames of each capture are loaded (0: all)."""
    seed: int = 0
    """Seed of the initial weights and of the view sampling."""

    def __post_init__(self) -> None:
        from image2sim.simulator.config import require_at_least, require_in_range, require_one_of

        require_one_of(self, "architecture", sorted(ARCHITECTURES))
        multiple = ARCHITECTURES[self.architecture]["multiple"]
        if self.image_size < 2 * multiple or self.image_size % multiple:
            raise ValueError(
                f"image_size must be a multiple of {multiple} and >= {2 * multiple} for {self.architecture}, "
                f"got {self.image_size}"
            )
        require_at_least(self, ("hidden_size", "heads", "steps", "batch_size"), 1)
        require_at_least(self, "layers", 4)  # the DPT head reads the last four
        if self.hidden_size % self.heads:
            raise ValueError(f"hidden_size ({self.hidden_size}) must be a multiple of heads ({self.heads})")
        if not (0 < self.hfov_min_deg <= self.hfov_max_deg < 180):
            raise ValueError(
                f"need 0 < hfov_min_deg <= hfov_max_deg < 180, got {self.hfov_min_deg}, {self.hfov_max_deg}"
            )
        fractions = (self.level_fraction, self.vertical_fraction)
        if min(fractions) < 0 or sum(fractions) > 1:
            raise ValueError("level_fraction and vertical_fraction must be >= 0 and sum to at most 1")
        require_in_range(self, "lr", 0.0, math.inf, low_open=True, high_open=True)
        require_in_range(self, "min_valid_fraction", 0.0, 1.0, high_open=True)

    @classmethod
    def from_dict(cls, data: dict) -> DepthPriorConfig:
        """The config from field values; an unknown name is an error listing the known ones."""
        return options_from_kwargs(cls, dict(data), "depth-prior")


def _build_glpn(cfg: DepthPriorConfig):
    from transformers import GLPNConfig, GLPNForDepthEstimation

    w = cfg.hidden_size
    widths = [max(8, w // 4), max(8, w // 2), w, 2 * w]
    heads = [max(1, min(cfg.heads, c // 16)) for c in widths]
    config = GLPNConfig(
        num_encoder_blocks=4,
        depths=[1, 1, max(1, cfg.layers - 3), 1],
        sr_ratios=[8, 4, 2, 1],
        hidden_sizes=widths,
        patch_sizes=[7, 3, 3, 3],
        strides=[4, 2, 2, 2],
        num_attention_heads=heads,
        mlp_ratios=[2, 2, 2, 2],
        decoder_hidden_size=max(16, w // 2),
        max_depth=10,
        head_in_index=-1,
    )
    torch.manual_seed(cfg.seed)
    return GLPNForDepthEstimation(config)


def build_depth_prior(cfg: DepthPriorConfig):
    """A randomly initialised relative depth model of ``cfg``'s architecture and size."""
    if cfg.architecture == "glpn":
        return _build_glpn(cfg)
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    layers = int(cfg.layers)
    backbone = Dinov2Config(
        image_size=cfg.image_size,
        patch_size=14,
        hidden_size=cfg.hidden_size,
        num_hidden_layers=layers,
        num_attention_heads=cfg.heads,
        intermediate_size=4 * cfg.hidden_size,
        out_indices=[layers - 3 + i for i in range(4)],
        reshape_hidden_states=False,
    )
    w = cfg.hidden_size
    config = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=w,
        neck_hidden_sizes=[w // 4, w // 2, w, w],
        fusion_hidden_size=w // 2,
        head_hidden_size=max(8, w // 8),
        depth_estimation_type="relative",
        # transformers' default (0.02) leaves the DPT neck's output ~1e-4 and the head's spread at
        # float32 rounding; 0.1 starts the head with an output that varies.
        initializer_range=0.1,
    )
    torch.manual_seed(cfg.seed)
    model = DepthAnythingForDepthEstimation(config)
    # The head ends in a ReLU: from a random start most outputs are 0 and the loss has no gradient.
    # Start every output near 1 so that it trains.
    with torch.no_grad():
        model.head.conv3.bias.fill_(1.0)
    return model


def save_processor(folder: Path, cfg: DepthPriorConfig) -> None:
    """The image processor the lift's :class:`DepthModel` runs, normalising as training did.

    Depth Anything: resize to ``image_size`` high keeping the aspect ratio (multiples of 14),
    ImageNet normalisation. GLPN: its processor keeps the image size (rounded down to multiples of
    32) and only scales to [0, 1]; a view is seen at its own resolution.
    """
    if cfg.architecture == "glpn":
        from transformers.models.glpn.image_processing_pil_glpn import GLPNImageProcessorPil

        GLPNImageProcessorPil(do_resize=True, size_divisor=32, do_rescale=True).save_pretrained(folder)
        return
    from transformers.models.dpt.image_processing_pil_dpt import DPTImageProcessorPil

    image_size = cfg.image_size
    norm = ARCHITECTURES[cfg.architecture]

    DPTImageProcessorPil(
        do_resize=True,
        size={"height": image_size, "width": image_size},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        do_pad=False,
        image_mean=list(norm["mean"]),
        image_std=list(norm["std"]),
    ).save_pretrained(folder)


# ------------------------------------------------------------------------------------------ the loss


def ssi_loss(pred: torch.Tensor, depth: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Scale-and-shift-invariant loss of predicted inverse depth against z-depth (0 = invalid).

    ``pred`` and ``depth`` are (B, H, W). Per image, ``s, t`` minimise ``sum (s pred + t - 1/z)^2``
    over the valid pixels (closed form, differentiable); the image's loss is
    ``mean |s pred + t - 1/z| / mean(1/z)`` plus ``max(0, -corr(pred, 1/z))``. The second term fixes
    the sign: the output must grow as things come nearer (disparity-like, as Depth Anything's relative
    output, and as the lift's alignment assumes: a positive scale). The loss is the mean over images;
    images with fewer than 2 valid pixels, or a prediction without spread there, add 0.
    """
    if pred.shape != depth.shape or pred.ndim != 3:
        raise ValueError(
            f"pred and depth must both be (B, H, W), got {tuple(pred.shape)}, {tuple(depth.shape)}"
        )
    valid = (depth > 0) & torch.isfinite(depth)
    m = valid.to(pred.dtype)
    disp = torch.where(
        valid, 1.0 / torch.where(valid, depth, torch.ones_like(depth)), torch.zeros_like(depth)
    )
    n = m.sum((1, 2))
    count = n.clamp(min=1)[:, None, None]
    mean_x = (m * pred).sum((1, 2), keepdim=True) / count
    mean_y = (m * disp).sum((1, 2), keepdim=True) / count
    dx = m * (pred - mean_x)  # centred sums: no cancellation when the prediction barely varies
    var = (dx * dx).sum((1, 2))
    cov = (dx * (disp - mean_y)).sum((1, 2))
    usable = (n >= 2) & (var > eps * eps * n)
    s = torch.where(usable, cov / torch.where(usable, var, torch.ones_like(var)), torch.zeros_like(var))
    t = mean_y[:, 0, 0] - s * mean_x[:, 0, 0]
    err = (m * (s[:, None, None] * pred + t[:, None, None] - disp).abs()).sum((1, 2))
    var_y = (m * (disp - mean_y) ** 2).sum((1, 2))
    corr = cov / torch.sqrt(torch.where(usable, var, torch.ones_like(var)) * var_y.clamp(min=eps * eps))
    per_image = err / n.clamp(min=1) / mean_y[:, 0, 0].clamp(min=eps) + torch.relu(-corr)
    return torch.where(usable, per_image, torch.zeros_like(per_image)).mean()


# ---------------------------------------------------------------------------------------- the views


class ViewPool:
    """RGB-D frames in memory, and random pinhole training views of them.

    ``frames`` are ``(rgb (H, W, 3) uint8, depth (H, W) metres, 0 = invalid, camera)``. Panoramas
    (``EquirectCamera``, depth = range) give views at random yaw, pitch and field of view; pinhole
    frames (z-depth) give random square crops resized to ``image_size`` (their own field of view).
    """

    def __init__(self, frames, cfg: DepthPriorConfig) -> None:
        from image2sim.simulator.geometry.cameras import EquirectCamera

        self.cfg = cfg
        self.panoramas: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.pinholes: list[tuple[np.ndarray, np.ndarray]] = []
        for rgb, depth, camera in frames:
            rgb = np.asarray(rgb)
            depth = np.asarray(depth, np.float32)
            if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != depth.shape:
                raise ValueError(
                    f"a frame needs (H, W, 3) colour and (H, W) depth, got {rgb.shape}, {depth.shape}"
                )
            if isinstance(camera, EquirectCamera):
                colour = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float()
                self.panoramas.append((colour, torch.from_numpy(depth)[None]))
            else:
                self.pinholes.append((rgb, depth))
        if not len(self):
            raise ValueError("no frames to train a depth prior on")
        self.rng = np.random.default_rng(cfg.seed)

    @classmethod
    def from_captures(
        cls, captures: Sequence[str | Path], cfg: DepthPriorConfig, progress: bool = True
    ) -> ViewPool:
        """Every frame (or the first ``cfg.frames_per_capture``) of captures the registry reads."""
        from image2sim.simulator.io.registry import open_capture

        if not captures:
            raise ValueError("no captures given to train a depth prior on")
        items = []
        for path in captures:
            cap = open_capture(path)
            n = len(cap) if cfg.frames_per_capture <= 0 else min(len(cap), cfg.frames_per_capture)
            if n == 0:
                raise ValueError(f"{path}: the capture has no frames")
            items += [(cap, i) for i in range(n)]
        if progress:
            from rich.progress import track

            items = track(items, description="loading frames", total=len(items))

        def frames():
            for cap, i in items:
                frame = cap[i]
                yield frame.rgb, frame.depth, frame.camera

        return cls(frames(), cfg)

    def __len__(self) -> int:
        return len(self.panoramas) + len(self.pinholes)

    def _panorama_view(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        from image2sim.simulator.geometry.reproject import perspective_directions, perspective_from_equirect

        cfg, rng = self.cfg, self.rng
        rgb, rng_depth = self.panoramas[index]
        size = cfg.image_size
        hfov = float(rng.uniform(cfg.hfov_min_deg, cfg.hfov_max_deg))
        yaw = float(rng.uniform(-180.0, 180.0))
        u = rng.random()
        if u < cfg.level_fraction:
            pitch = 0.0
        elif u < cfg.level_fraction + cfg.vertical_fraction:
            pitch = float(rng.choice([-90.0, 90.0]))
        else:
            pitch = float(rng.uniform(-cfg.max_pitch_deg, cfg.max_pitch_deg))
        colour = perspective_from_equirect(rgb[None], yaw, pitch, hfov, hfov, size, size, mode="bilinear")[0]
        ranges = perspective_from_equirect(
            rng_depth[None], yaw, pitch, hfov, hfov, size, size, mode="nearest"
        )
        ray_z = perspective_directions(hfov, hfov, size, size, dtype=ranges.dtype)[..., 2]
        z = (ranges[0, 0] * ray_z).numpy()
        return colour.permute(1, 2, 0).clamp(0, 255).numpy(), z

    def _pinhole_view(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        rgb, depth = self.pinholes[index]
        h, w = depth.shape
        side = int(self.rng.integers(max(14, int(0.6 * min(h, w))), min(h, w) + 1))
        y0 = int(self.rng.integers(0, h - side + 1))
        x0 = int(self.rng.integers(0, w - side + 1))
        size = self.cfg.image_size
        colour = cv2.resize(rgb[y0 : y0 + side, x0 : x0 + side], (size, size), interpolation=cv2.INTER_AREA)
        z = cv2.resize(depth[y0 : y0 + side, x0 : x0 + side], (size, size), interpolation=cv2.INTER_NEAREST)
        return colour.astype(np.float32), z

    def sample(self, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``batch`` normalised images (B, 3, S, S) and their z-depths (B, S, S), 0 = invalid."""
        cfg = self.cfg
        images, depths = [], []
        while len(images) < batch:
            for _ in range(20):
                k = int(self.rng.integers(0, len(self)))
                if k < len(self.panoramas):
                    colour, z = self._panorama_view(k)
                else:
                    colour, z = self._pinhole_view(k - len(self.panoramas))
                valid = np.isfinite(z) & (z > 0)
                if valid.mean() >= cfg.min_valid_fraction:
                    break
            z = np.where(valid, z, 0.0).astype(np.float32)
            if cfg.colour_noise > 0:
                colour = colour + self.rng.normal(0.0, cfg.colour_noise, colour.shape)
            colour = np.clip(colour, 0, 255) / 255.0
            norm = ARCHITECTURES[cfg.architecture]
            colour = (colour - np.asarray(norm["mean"])) / np.asarray(norm["std"])
            images.append(torch.from_numpy(colour.astype(np.float32)).permute(2, 0, 1))
            depths.append(torch.from_numpy(z))
        return torch.stack(images), torch.stack(depths)


# --------------------------------------------------------------------------------------- training


def train_depth_prior(
    captures: Sequence[str | Path],
    out: str | Path,
    cfg: DepthPriorConfig | None = None,
    *,
    val_captures: Sequence[str | Path] = (),
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Train a depth prior on ``captures`` and save it to ``out`` (a folder ``load_depth_model`` reads).

    Returns the training record, also written to ``out/depth_prior.json``: the config, the loss of
    the last tenth of the steps, wall time, parameters, and (with ``val_captures``) the loss on 64
    fixed views of those captures before and after training. ``out`` is written whole or not at all
    (a temporary folder renamed into place); an existing ``out`` is an error.
    """
    cfg = cfg or DepthPriorConfig()
    out = Path(out)
    if out.exists():
        raise ValueError(f"{out} exists: choose a new folder for the depth prior")
    say = log or (lambda message: None)
    torch.manual_seed(cfg.seed)
    pool = ViewPool.from_captures(captures, cfg, progress=progress)
    val = None
    if val_captures:
        val_cfg = DepthPriorConfig(**{**asdict(cfg), "seed": cfg.seed + 10_007})
        val_pool = ViewPool.from_captures(val_captures, val_cfg, progress=False)
        val = val_pool.sample(64)
    model = build_depth_prior(cfg)
    params = sum(p.numel() for p in model.parameters())
    say(f"depth prior: {params:,} parameters, {len(pool)} frames ({len(pool.panoramas)} panoramas)")

    def val_loss() -> float | None:
        if val is None:
            return None
        model.eval()
        with torch.no_grad():
            loss = sum(
                float(ssi_loss(model(pixel_values=val[0][i : i + 16]).predicted_depth, val[1][i : i + 16]))
                for i in range(0, 64, 16)
            )
        model.train()
        return loss / 4

    before = val_loss()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    warm = max(1, cfg.steps // 20)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: warmup_cosine(step, warm, cfg.steps, 0.05))
    model.train()
    losses: list[float] = []
    t0 = time.perf_counter()
    steps = range(cfg.steps)
    if progress:
        from rich.progress import track

        steps = track(steps, description="training depth prior", total=cfg.steps)
    for step in steps:
        images, depths = pool.sample(cfg.batch_size)
        loss = ssi_loss(model(pixel_values=images).predicted_depth, depths)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"depth prior: non-finite loss at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if (step + 1) % max(1, cfg.steps // 10) == 0:
            say(f"step {step + 1}/{cfg.steps}: loss {np.mean(losses[-max(1, cfg.steps // 10) :]):.4f}")
    seconds = time.perf_counter() - t0
    tail = losses[-max(1, cfg.steps // 10) :]
    record = {
        "config": asdict(cfg),
        "captures": [str(c) for c in captures],
        "val_captures": [str(c) for c in val_captures],
        "frames": len(pool),
        "parameters": params,
        "train_seconds": seconds,
        "loss_first_tenth": float(np.mean(losses[: max(1, cfg.steps // 10)])),
        "loss_last_tenth": float(np.mean(tail)),
        "val_loss_before": before,
        "val_loss_after": val_loss(),
        "views_seen": cfg.steps * cfg.batch_size,
    }
    with atomic_dir(out) as tmp:
        model.eval()
        model.save_pretrained(tmp, safe_serialization=True)
        save_processor(tmp, cfg)
        (tmp / "depth_prior.json").write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return record
