"""Lightning training of the pixel-flow renderer with the paper's three-stage curriculum.

* Stage 1 (geometry initialisation, steps [0, stage2_start)): flow without the spatial focus
  weight, no distillation, lambda_perc = curriculum.lambda_perc[0].
* Stage 2 (flow + distillation): the EMA teacher starts as a copy of the student and follows it
  with decay ``distill.ema_decay``; the opacity-adaptive weight W(A) is applied to the flow loss.
* Stage 3 (high-frequency refinement): the decoder's conv encoder, the semantic aligner, the time
  embedding and the transformer bottleneck (with its semantic injectors) are frozen; only the
  upsampling decoder, skips and heads train.

The stage is a pure function of the global step and is re-applied at every step, so resuming
from a checkpoint lands in the right stage with the right modules frozen. Per-step randomness
((r, t), source noise) comes from a generator seeded by (seed, step), and the data order from
:class:`StepSampler`, so an interrupted-and-resumed run reproduces the uninterrupted losses.
"""

from __future__ import annotations

import math
import time

import lightning as L
import torch
from image2sim.simulator.io.atomic import atomic_path, write_json_atomic
from image2sim.simulator.renderer import meanflow as mf
from image2sim.simulator.renderer.augment import augment_panorama_pair, sample_panorama_augmentation
from image2sim.simulator.renderer.config import RendererConfig
from image2sim.simulator.renderer.distill import EMATeacher
from image2sim.simulator.renderer.losses import load_lpips
from image2sim.simulator.renderer.model import PixelFlowRenderer
from torch import nn

__all__ = [
    "stage_at",
    "stage_weights",
    "frozen_prefixes",
    "apply_stage",
    "RendererModule",
    "RendererDataModule",
    "psnr",
]

FROZEN_IN_STAGE3: tuple[str, ...] = (
    "aligner.",
    "decoder.stem.",
    "decoder.enc_blocks.",
    "decoder.downs.",
    "decoder.time_embed.",
    "decoder.injectors.",
    "decoder.blocks.",
)
"""Parameter-name prefixes frozen in stage 3 (encoder, aligner, bottleneck). The paper also
freezes the scene encoder's feature upsampler, which lives outside the renderer."""


def stage_at(step: int, cfg: RendererConfig) -> int:
    """Curriculum stage (1, 2 or 3) of a global step."""
    c = cfg.curriculum
    return 1 if step < c.stage2_start else (2 if step < c.stage3_start else 3)


def stage_weights(stage: int, cfg: RendererConfig, perceptual_available: bool = True) -> dict[str, float]:
    """Loss weights in force in ``stage`` (ablations and a missing LPIPS zero their terms)."""
    c, lo, ab = cfg.curriculum, cfg.loss, cfg.ablation
    return {
        "rec": lo.lambda_rec,
        "align": 0.0 if ab.no_semantic else lo.lambda_align,
        "flow": lo.lambda_flow,
        "distill": 0.0 if ab.no_distill else c.lambda_distill[stage - 1],
        "pixel": lo.lambda_pixel,
        "perc": c.lambda_perc[stage - 1] if perceptual_available else 0.0,
    }


def frozen_prefixes(stage: int) -> tuple[str, ...]:
    """Parameter-name prefixes frozen in ``stage``."""
    return FROZEN_IN_STAGE3 if stage >= 3 else ()


def apply_stage(renderer: nn.Module, stage: int) -> list[str]:
    """Set ``requires_grad`` for ``stage``; returns the names of the frozen parameters."""
    prefixes = frozen_prefixes(stage)
    frozen = []
    for name, p in renderer.named_parameters():
        freeze = name.startswith(prefixes)
        p.requires_grad_(not freeze)
        if freeze:
            frozen.append(name)
    return frozen


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean PSNR (dB) of images in [0, 1] over the batch."""
    mse = (pred.float() - target.float()).pow(2).flatten(1).mean(1).clamp_min(1e-10)
    return (-10.0 * torch.log10(mse)).mean()


class RendererModule(L.LightningModule):
    """Renderer + EMA teacher + curriculum; AdamW with a cosine schedule (per step)."""

    def __init__(
        self,
        cfg: RendererConfig,
        seed: int = 0,
        lpips_path: str | None = None,
        grid_every: int = 0,
        semantic_model: nn.Module | None = None,
    ) -> None:
        """``semantic_model``: an already built DINOv3 model for ``cfg.semantic`` (tests pass a tiny
        random one); by default it is loaded from ``cfg.semantic.weights``."""
        super().__init__()
        if cfg.ablation.no_pixel_flow:
            raise ValueError(
                "ablation.no_pixel_flow is the splat-only renderer and has nothing to train: "
                "evaluate it directly (`eval render` scores splat-only on every run)"
            )
        self.cfg = cfg
        self.seed = int(seed)
        self.grid_every = int(grid_every)
        self.renderer = PixelFlowRenderer(cfg)
        self.teacher = (
            None
            if cfg.ablation.no_distill or cfg.ablation.no_pixel_flow
            else EMATeacher(self.renderer, cfg.distill.ema_decay)
        )
        self.register_buffer("teacher_started", torch.zeros((), dtype=torch.bool))
        self.perceptual = load_lpips(lpips_path or cfg.loss.lpips_weights)
        backbone = None
        if cfg.semantic.backbone != "none" and not cfg.ablation.no_semantic:
            from image2sim.simulator.gaussians.semantic import build_semantic

            backbone = build_semantic(cfg.semantic, semantic_model)
        # Frozen and loaded from its own folder: kept out of the registered submodules so that
        # checkpoints do not carry a copy of the backbone (about 1.2 GB for ViT-L).
        object.__setattr__(self, "semantic_backbone", backbone)
        self.current_stage = 0
        self.save_hyperparameters({"config": __import__("dataclasses").asdict(cfg), "seed": seed})

    # --- helpers -------------------------------------------------------------------------------
    def _step_generator(self, step: int) -> torch.Generator:
        """Per-(seed, step, rank) randomness; one process gets the single-rank stream exactly."""
        world = self.trainer.world_size if self._trainer is not None else 1
        rank = self.global_rank if self._trainer is not None else 0
        return torch.Generator().manual_seed((self.seed * 1_000_003 + int(step)) * world + rank)

    def _enter_stage(self, stage: int) -> None:
        if stage != self.current_stage:
            apply_stage(self.renderer, stage)
            self.current_stage = stage

    # --- Lightning hooks ------------------------------------------------------------------------
    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        step = int(self.global_step)
        stage = stage_at(step, self.cfg)
        self._enter_stage(stage)
        cond, rgb, depth = batch["condition"], batch["target_rgb"], batch["target_depth"]
        b = cond.shape[0]
        gen = self._step_generator(step)
        target_tokens = batch.get("target_tokens")
        aug = self.cfg.augment
        if aug.yaw_roll or aug.mirror_probability > 0:
            if target_tokens is not None:
                raise ValueError(
                    "augment.yaw_roll / mirror_probability cannot move precomputed target_tokens: "
                    "let the semantic backbone compute them, or turn the augmentation off"
                )
            shifts, mirror = sample_panorama_augmentation(
                b, cond.shape[-1], aug.yaw_roll, aug.mirror_probability, gen
            )
            cond, (rgb, depth) = augment_panorama_pair(cond, (rgb, depth), shifts, mirror)
        if target_tokens is None and self.semantic_backbone is not None:
            target_tokens = self.semantic_backbone(rgb)
        r, t = mf.sample_time_pairs(b, self.cfg.meanflow.p_r_equals_t, generator=gen)
        noise = torch.randn((b, 4, *cond.shape[-2:]), generator=gen)
        r, t, noise = r.to(cond), t.to(cond), noise.to(cond)
        weights = stage_weights(stage, self.cfg, self.perceptual is not None)
        teacher = None
        if self.teacher is not None and stage >= 2 and weights["distill"] > 0:
            if not bool(self.teacher_started):
                # The teacher is introduced at stage 2 as a copy of the current student.
                self.teacher.update(self.renderer, decay=0.0)
                self.teacher_started.fill_(True)
            teacher = self.teacher.module
        out = self.renderer.losses(
            cond,
            rgb,
            depth,
            noise,
            r,
            t,
            teacher=teacher,
            target_tokens=target_tokens,
            perceptual=self.perceptual if weights["perc"] > 0 else None,
            spatial_focus=stage >= 2,
        )
        total = sum(weights[k] * out[k] for k in weights)
        terms = ("flow", "flow_raw", "rec", "align", "distill", "pixel", "perc")
        log = {f"train/{k}": out[k].detach() for k in terms}
        log["train/loss"] = total.detach()
        log["train/stage"] = float(stage)
        log["train/psnr_one_step"] = psnr(out["x_one_step"][:, :3], rgb)
        self.log_dict(log, prog_bar=False, on_step=True, on_epoch=False, batch_size=b)
        self.last_losses = {k: float(v) for k, v in log.items()}
        if self.grid_every and step % self.grid_every == 0 and self.global_rank == 0:
            self._log_grid(cond, out["x_one_step"], rgb, step)
        return total

    def on_fit_start(self) -> None:
        # The backbone is not a registered submodule (see __init__), so Lightning does not move it.
        if self.semantic_backbone is not None:
            self.semantic_backbone.to(self.device)

    def optimizer_step(self, *args, **kwargs) -> None:
        super().optimizer_step(*args, **kwargs)
        # EMA right after the student's update, inside the step: checkpoint callbacks (which run
        # in on_train_batch_end, before the module's hook) then always see the updated teacher.
        if self.teacher is not None and bool(self.teacher_started):
            self.teacher.update(self.renderer)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.current_stage = 0  # re-apply freezing for the restored step at the next batch

    def configure_optimizers(self):
        c = self.cfg.curriculum
        params = [p for p in self.renderer.parameters()]
        opt = torch.optim.AdamW(params, lr=c.lr, weight_decay=c.weight_decay)
        total = max(1, c.total_steps)
        floor = c.min_lr / c.lr

        def cosine(step: int) -> float:
            progress = min(1.0, step / total)
            return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, cosine)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def _log_grid(self, cond: torch.Tensor, x: torch.Tensor, rgb: torch.Tensor, step: int) -> None:
        """prior | one-step | target | alpha for the first sample, to W&B and as a PNG in the CSV log."""
        from image2sim.simulator.renderer.condition import ALPHA, RGB

        row = (
            torch.cat((cond[0, RGB], x[0, :3].clamp(0, 1), rgb[0], cond[0, ALPHA].expand(3, -1, -1)), dim=-1)
            .detach()
            .float()
            .cpu()
        )
        image = (row.permute(1, 2, 0).numpy() * 255).round().astype("uint8")
        # Loggers that take images get the grid (W&B, beside the CSV log); the CSV log's folder
        # gets it as a PNG.
        for logger in self.loggers:
            if hasattr(logger, "log_image"):
                logger.log_image(key="grid/prior|one_step|target|alpha", images=[image], step=step)
            elif getattr(logger, "log_dir", None):
                from pathlib import Path

                from PIL import Image

                out = Path(logger.log_dir) / "grids"
                out.mkdir(parents=True, exist_ok=True)
                with atomic_path(out / f"step_{step:07d}.png") as tmp:
                    Image.fromarray(image).save(tmp, format="PNG")


class RendererDataModule(L.LightningDataModule):
    """Serves a map-style dataset in :class:`StepSampler` order from the trainer's global step, so a
    resumed run (whose checkpoint restores the step) continues with the next unseen batch."""

    def __init__(
        self, dataset, batch_size: int, total_steps: int, seed: int = 0, num_workers: int = 0
    ) -> None:
        super().__init__()
        self.dataset = dataset
        self.batch_size = int(batch_size)
        self.total_steps = int(total_steps)
        self.seed = int(seed)
        self.num_workers = int(num_workers)

    def train_dataloader(self):
        import functools

        from image2sim.simulator.renderer.data import permuted_index
        from image2sim.simulator.sampling import StepSampler
        from torch.utils.data import DataLoader

        sampler = StepSampler.for_trainer(
            self.trainer,
            self.batch_size,
            self.total_steps * self.batch_size,
            index_of=functools.partial(permuted_index, length=len(self.dataset), seed=self.seed),
        )
        return DataLoader(
            self.dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
            drop_last=True,
        )


def _training_pairs(dataset, batch: int = 4, indices: list[int] | None = None):
    """``(condition, target RGB)`` batches of a renderer dataset (of its items ``indices``), in order."""
    indices = list(range(len(dataset))) if indices is None else indices
    for start in range(0, len(indices), batch):
        items = [dataset[i] for i in indices[start : start + batch]]
        yield (
            torch.stack([it["condition"] for it in items]),
            torch.stack([it["target_rgb"] for it in items]),
        )


def init_prior_filter(
    renderer: PixelFlowRenderer,
    dataset,
    seed: int = 0,
    batch: int = 4,
    pixels_per_image: int | None = 8192,
) -> int | None:
    """Fit the decoder's linear prior filter to ``dataset``'s (condition, target) pairs in closed
    form (``renderer.prior_filter``; ``pixels_per_image`` random pixels of each, None: all);
    returns the pixels used, or None when the renderer has no filter or its config asks for a zero
    start."""
    decoder = renderer.decoder
    dcfg = renderer.cfg.decoder
    if decoder is None or decoder.prior_filter is None or dcfg.prior_filter_init != "least_squares":
        return None
    from image2sim.simulator.renderer.prior_filter import fit_prior_filter

    weight, bias, used = fit_prior_filter(
        _training_pairs(dataset, batch),
        int(dcfg.prior_filter),
        renderer.cfg.meanflow.depth_scale,
        dcfg.depth_bias,
        fill=dcfg.prior_fill,
        panoramic=decoder.panoramic,
        pixels_per_image=pixels_per_image,
        generator=torch.Generator().manual_seed(int(seed)),
    )
    with torch.no_grad():
        decoder.prior_filter.weight.copy_(weight)
        decoder.prior_filter.bias.copy_(bias)
    return used


def init_prior_path(
    renderer: PixelFlowRenderer, dataset, seed: int = 0, max_pixels: int | None = None
) -> dict | None:
    """Fit the decoder's prior path (linear filter + ``prior_hidden`` MLP) to random pixels of
    ``dataset``'s pairs for ``decoder.prior_fit_steps`` Adam steps (``renderer.prior_filter.
    fit_prior_path``); None when the renderer has no prior filter or the config asks for no steps.
    Only a random subset of at most ``max_pixels`` pixels (default ``FIT_MAX_PIXELS``) is loaded."""
    decoder = renderer.decoder
    steps = int(renderer.cfg.decoder.prior_fit_steps)
    if decoder is None or decoder.prior_filter is None or steps == 0:
        return None
    from image2sim.simulator.renderer.prior_filter import FIT_MAX_PIXELS, fit_prior_path

    max_pixels = FIT_MAX_PIXELS if max_pixels is None else int(max_pixels)
    generator = torch.Generator().manual_seed(int(seed) + 1)
    keep = max(1, max_pixels // (renderer.cfg.height * renderer.cfg.width))
    indices = None
    if len(dataset) > keep:
        indices = sorted(torch.randperm(len(dataset), generator=generator)[:keep].tolist())
    pairs = _training_pairs(dataset, indices=indices)
    return fit_prior_path(decoder, pairs, steps, max_pixels=max_pixels, generator=generator)


def fit(
    cfg: RendererConfig,
    dataset,
    out_dir: str,
    max_steps: int | None = None,
    seed: int = 0,
    resume: str | None = None,
    bf16: bool = False,
    logger: str = "csv",
    checkpoint_every: int = 500,
    grid_every: int = 0,
    progress: bool = True,
    wandb: str = "",
    wandb_project: str = "image2sim",
) -> RendererModule:
    """Train (or resume) the renderer; checkpoints and logs under ``out_dir``.

    Logs go to CSV (``logs/version_N/metrics.csv``), and to W&B as well when ``wandb`` (the params'
    ``tracking.wandb``: disabled | offline | online, see ``tracking.wandb_mode``) asks for it, in
    project ``wandb_project``; ``logger="wandb"`` (the older switch) means offline W&B.
    Hardware and distribution come from ``cfg.trainer`` (``bf16=True`` overrides its precision).
    Under DDP every rank runs this function; each reads its own share of the step-indexed data
    order, rank 0 writes checkpoints, logs and image grids.
    """
    import dataclasses
    from pathlib import Path

    from lightning.pytorch.callbacks import ModelCheckpoint

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "config.json", dataclasses.asdict(cfg))
    steps = max_steps if max_steps is not None else cfg.curriculum.total_steps
    L.seed_everything(seed, workers=True, verbose=False)
    module = RendererModule(cfg, seed=seed, grid_every=grid_every)
    if resume is None:  # a resumed run restores the filter from its checkpoint
        start = time.perf_counter()
        used = init_prior_filter(module.renderer, dataset, seed)
        if used is not None:
            print(
                f"prior filter ({cfg.decoder.prior_filter}x{cfg.decoder.prior_filter}): least-squares "
                f"start from {used} training pixels in {time.perf_counter() - start:.1f} s"
            )
        start = time.perf_counter()
        fitted = init_prior_path(module.renderer, dataset, seed)
        if fitted is not None:
            d = cfg.decoder
            print(
                f"prior path ({d.prior_filter}x{d.prior_filter}, MLP width {d.prior_hidden}): "
                f"{d.prior_fit_steps} steps on {fitted['pixels']} pixels of {fitted['images']} pairs, "
                f"training PSNR {fitted['psnr_start']:.2f} -> {fitted['psnr_end']:.2f} dB "
                f"in {time.perf_counter() - start:.1f} s"
            )
    data = RendererDataModule(dataset, cfg.curriculum.batch_size, cfg.curriculum.total_steps, seed)
    from image2sim.simulator.tracking import csv_logger, wandb_logger, wandb_mode

    log = [csv_logger(out, resume=resume is not None)]  # always: the pipeline's loss curve reads it
    mode = wandb_mode(wandb) if wandb else ("offline" if logger == "wandb" else None)
    if mode is not None:
        log.append(wandb_logger(out, wandb_project, dataclasses.asdict(cfg), mode=mode))
    ckpt = ModelCheckpoint(
        dirpath=str(out / "checkpoints"), every_n_train_steps=checkpoint_every, save_last=True, save_top_k=-1
    )
    from image2sim.simulator.trainer import lightning_trainer_args

    trainer = L.Trainer(
        **lightning_trainer_args(cfg.trainer, "bf16-mixed" if bf16 else None),
        max_steps=steps,
        gradient_clip_val=cfg.curriculum.grad_clip,
        logger=log,
        callbacks=[ckpt],
        enable_progress_bar=progress,
        enable_model_summary=False,
        log_every_n_steps=1,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        deterministic=False,
    )
    trainer.fit(module, datamodule=data, ckpt_path=resume)
    return module
