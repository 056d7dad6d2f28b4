"""Stage-1 training (geometry initialisation) of the Gaussian encoder as a Lightning module.

One sample = one scene, K source frames and a held-out target frame. The encoder turns the sources
into Gaussians (no fusion: everything stays differentiable), they are splatted at the target pose,
and the loss is the paper's masked L1 reconstruction of RGB and depth (+ the cosine alignment of
tokenised projected features to the target's DINOv3 tokens when a semantic backbone is
configured, + with ``train.w_labels`` the cross-entropy of a linear category head over the
splatted features against the target's per-pixel categories, + a scale regulariser). The sample
order is a pure function of (seed, step), so a run resumed from ``last.ckpt`` continues exactly
where it stopped.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from image2sim.simulator.gaussians.config import GaussianConfig, config_to_dict
from image2sim.simulator.gaussians.encoder import GaussianEncoder, pixel_maps_to_gaussians
from image2sim.simulator.gaussians.primitives import FrameInputs, GaussianSet
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, camera_from_dict
from image2sim.simulator.io.atomic import write_json_atomic
from torch.utils.data import DataLoader, Dataset

__all__ = [
    "GeometryDataset",
    "GeometryDataModule",
    "GeometryModule",
    "stage1_losses",
    "train_stage1",
    "load_scene_frames",
    "label_classes",
]


def load_scene_frames(
    path: str | Path, cfg: GaussianConfig, max_frames: int | None = None
) -> list[FrameInputs]:
    """All frames of a capture at the encoder resolution."""
    from image2sim.simulator.gaussians.frames import prepare_frame
    from image2sim.simulator.io.registry import open_capture

    cap = open_capture(path)
    n = len(cap) if max_frames is None else min(len(cap), max_frames)
    e = cfg.encoder
    labels = cfg.train.w_labels > 0
    return [prepare_frame(cap[i], e.height, e.width, cfg.fusion.edge_tolerance, labels) for i in range(n)]


class GeometryDataset(Dataset):
    """``length`` virtual samples over scenes (each a list of :class:`FrameInputs` sharing one camera).

    Sample ``i`` (seeded by ``(seed, i)``) picks a scene, a target frame and K sources drawn from
    the 2K frames nearest to the target (by camera centre), never the target itself.
    """

    def __init__(
        self, scenes: Sequence[Sequence[FrameInputs]], num_sources: int, length: int, seed: int = 0
    ) -> None:
        self.scenes = [list(s) for s in scenes if len(s) >= 2]
        if not self.scenes:
            raise ValueError("GeometryDataset needs at least one scene with >= 2 frames")
        self.k, self.length, self.seed = int(num_sources), int(length), int(seed)

    def __len__(self) -> int:
        return self.length

    def indices(self, index: int) -> tuple[int, int, list[int]]:
        """(scene, target, sources) of sample ``index``."""
        rng = np.random.default_rng([self.seed, int(index)])
        s = int(rng.integers(len(self.scenes)))
        frames = self.scenes[s]
        t = int(rng.integers(len(frames)))
        centres = np.stack([f.cam_to_world[:3, 3].numpy() for f in frames])
        d = np.linalg.norm(centres - centres[t], axis=1)
        d[t] = np.inf
        pool = np.argsort(d, kind="stable")[: min(2 * self.k, len(frames) - 1)]
        k = min(self.k, len(pool))
        return s, t, sorted(int(i) for i in rng.choice(pool, size=k, replace=False))

    def __getitem__(self, index: int) -> dict:
        s, t, src = self.indices(index)
        frames = self.scenes[s]
        tgt = frames[t]
        return {
            "src_rgb": torch.cat([frames[i].rgb for i in src]),
            "src_depth": torch.cat([frames[i].depth for i in src]),
            "src_pose": torch.stack([frames[i].cam_to_world for i in src]),
            "tgt_rgb": tgt.rgb[0],
            "tgt_depth": tgt.depth[0],
            "tgt_pose": tgt.cam_to_world,
            "camera": json.dumps(tgt.camera.to_dict()),
            "index": int(index),
            **({} if tgt.labels is None else {"tgt_labels": tgt.labels[0, 0]}),
        }


def _collate(items: list[dict]) -> dict:
    if len(items) != 1:
        raise ValueError("stage-1 batches hold one scene (batch_size=1)")
    return items[0]


class GeometryDataModule(L.LightningDataModule):
    """Serves :class:`GeometryDataset` samples in step order from the trainer's global step (one
    sample per step), so a resumed run continues with the next unseen sample."""

    def __init__(self, scenes: Sequence[Sequence[FrameInputs]], cfg: GaussianConfig) -> None:
        super().__init__()
        t = cfg.train
        self.dataset = GeometryDataset(scenes, t.num_sources, max(1, t.steps), t.seed)

    def train_dataloader(self) -> DataLoader:
        from image2sim.simulator.sampling import StepSampler

        order = StepSampler.for_trainer(self.trainer, 1, len(self.dataset))
        return DataLoader(self.dataset, batch_size=1, sampler=order, collate_fn=_collate, num_workers=0)


def stage1_losses(
    encoder: GaussianEncoder,
    batch: dict,
    camera: Camera,
    align_head: torch.nn.Module | None = None,
    label_head: torch.nn.Module | None = None,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Loss terms and the splatted target images of one sample (see the module docstring).
    ``label_head`` (features -> category logits) adds the category term when the batch has
    ``tgt_labels``."""
    cfg = encoder.cfg
    t, e = cfg.train, cfg.encoder
    maps = encoder.forward_maps(batch["src_rgb"], batch["src_depth"], camera)
    sets = pixel_maps_to_gaussians(maps, batch["src_rgb"], batch["src_depth"], camera, batch["src_pose"], cfg)
    g = GaussianSet.cat(sets)
    out = g.render(camera, batch["tgt_pose"].to(g.means.dtype), backend=t.backend)
    alpha = out.alpha[0]
    safe = alpha.clamp_min(1e-6)
    pred_rgb, pred_depth = out.rgb[0] / safe, out.depth[0] / safe
    tgt_rgb, tgt_depth = batch["tgt_rgb"], batch["tgt_depth"]
    mask = ((tgt_depth > 0) & (alpha.detach() >= t.min_alpha)).to(alpha.dtype)
    denom = mask.sum().clamp_min(1.0)
    l_rgb = ((pred_rgb - tgt_rgb).abs() * mask).sum() / (3 * denom)
    l_depth = ((pred_depth - tgt_depth).abs() * mask).sum() / (denom * e.depth_scale)
    ref = (g.footprints * e.scale_init).clamp(e.scale_min, e.scale_max)[:, None]
    l_scale = torch.log(g.scales / ref).pow(2).mean() if len(g) else alpha.sum() * 0
    losses = {"rgb": l_rgb, "depth": l_depth, "scale": l_scale}
    total = t.w_rgb * l_rgb + t.w_depth * l_depth + t.w_scale * l_scale
    if encoder.semantic is not None and align_head is not None and out.features.shape[1]:
        tokens = encoder.semantic(tgt_rgb[None])  # (1, D, h, w), frozen
        feats = out.features / safe[None]
        pooled = F.adaptive_avg_pool2d(feats, tokens.shape[-2:])
        proj = align_head(pooled.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
        l_align = (1 - F.cosine_similarity(proj, tokens, dim=1)).mean()
        losses["align"] = l_align
        total = total + t.w_align * l_align
    if label_head is not None and "tgt_labels" in batch and out.features.shape[1]:
        feats = (out.features / safe[None])[0].permute(1, 2, 0)  # (H, W, C)
        labels = batch["tgt_labels"].to(feats.device)
        keep = mask.reshape(labels.shape).bool() & (labels > 0) & (labels < label_head.out_features)
        if keep.any():
            logits = label_head(feats[keep])
            l_labels = F.cross_entropy(logits, labels[keep])
            with torch.no_grad():
                losses["label_acc"] = (logits.argmax(-1) == labels[keep]).float().mean()
        else:  # nothing labelled in view: a zero that keeps the graph
            l_labels = feats.sum() * 0
        losses["labels"] = l_labels
        total = total + t.w_labels * l_labels
    losses["total"] = total
    with torch.no_grad():
        mse = (((pred_rgb - tgt_rgb) ** 2) * mask).sum() / (3 * denom)
        losses["psnr_masked"] = -10 * torch.log10(mse.clamp_min(1e-10))
        losses["coverage"] = (alpha >= t.min_alpha).float().mean()
    images = {"pred_rgb": pred_rgb.detach().clamp(0, 1), "tgt_rgb": tgt_rgb, "alpha": alpha.detach()}
    return losses, images


class GeometryModule(L.LightningModule):
    """Trains :class:`GaussianEncoder` (and the feature->token head of the alignment loss)."""

    def __init__(
        self,
        cfg: GaussianConfig,
        semantic_model: torch.nn.Module | None = None,
        panoramic: bool = True,
        image_dir: str | None = None,
        label_classes: int = 0,
    ) -> None:
        super().__init__()
        from image2sim.simulator.gaussians.semantic import build_semantic

        self.save_hyperparameters(
            {"config": config_to_dict(cfg), "panoramic": bool(panoramic), "label_classes": int(label_classes)}
        )
        self.cfg = cfg
        semantic = build_semantic(cfg.semantic, semantic_model)
        self.encoder = GaussianEncoder(cfg, semantic, panoramic=panoramic)
        self.align_head = (
            torch.nn.Linear(cfg.encoder.feature_dim, semantic.dim)
            if semantic is not None and cfg.encoder.feature_dim
            else None
        )
        # The category head only trains the features; the encoder file leaves it out.
        self.label_head = (
            torch.nn.Linear(cfg.encoder.feature_dim, int(label_classes))
            if cfg.train.w_labels > 0 and cfg.encoder.feature_dim and label_classes > 1
            else None
        )
        self.image_dir = image_dir
        self.history: list[float] = []

    # The frozen DINOv3 is rebuilt from its own folder; checkpoints leave it out (a ViT-L is about
    # 1.2 GB, and every checkpoint is kept) and a resume puts the loaded backbone's weights back.
    _FROZEN_PREFIX = "encoder.semantic."

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        state = checkpoint["state_dict"]
        for key in [k for k in state if k.startswith(self._FROZEN_PREFIX)]:
            del state[key]

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        state = checkpoint["state_dict"]
        for key, value in self.state_dict().items():
            if key.startswith(self._FROZEN_PREFIX):
                state.setdefault(key, value)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        camera = camera_from_dict(json.loads(batch["camera"]))
        losses, images = stage1_losses(self.encoder, batch, camera, self.align_head, self.label_head)
        t = self.cfg.train
        self.log_dict(
            {f"train/{k}": v.detach() for k, v in losses.items()}, on_step=True, prog_bar=False, batch_size=1
        )
        self.history.append(float(losses["total"].detach()))
        step = int(self.global_step)
        if self.image_dir and t.image_every and step % t.image_every == 0 and self.global_rank == 0:
            _write_grid(Path(self.image_dir) / f"step_{step:07d}.png", images)
        return losses["total"]

    def configure_optimizers(self):
        t = self.cfg.train
        params = [p for p in self.parameters() if p.requires_grad]
        return torch.optim.AdamW(params, lr=t.lr, weight_decay=t.weight_decay)


def _write_grid(path: Path, images: dict[str, torch.Tensor]) -> None:
    """Target | prediction | alpha, stacked vertically, as one PNG."""
    from image2sim.simulator.io.images import write_rgb_png

    alpha = images["alpha"].expand(3, -1, -1)
    grid = torch.cat((images["tgt_rgb"], images["pred_rgb"], alpha), dim=1).clamp(0, 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_rgb_png(path, (grid.permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8))


def label_classes(cfg: GaussianConfig, scenes: Sequence[Sequence[FrameInputs]]) -> int:
    """Classes of the category head: the largest category id in the scenes + 1 (0 without
    ``train.w_labels``). A label target without labelled frames is an error, not a silent no-op."""
    if cfg.train.w_labels <= 0:
        return 0
    ids = [int(f.labels.max()) for s in scenes for f in s if f.labels is not None]
    if not ids or max(ids) < 1:
        raise ValueError(
            "train.w_labels > 0 needs captures with per-pixel categories (semantics/<frame>_category.png); "
            "none of the training frames has any"
        )
    return max(ids) + 1


def train_stage1(
    cfg: GaussianConfig,
    out_dir: str | Path,
    captures: Sequence[str | Path] = (),
    scenes: Sequence[Sequence[FrameInputs]] | None = None,
    resume: bool = True,
    semantic_model: torch.nn.Module | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    wandb: str = "",
    wandb_project: str = "image2sim",
) -> dict:
    """Train (or resume) stage 1; writes checkpoints, CSV logs, image grids and the final encoder
    (``encoder.safetensors`` + ``encoder.json``) under ``out_dir``. Returns a summary. W&B is added
    beside the CSV log when ``wandb`` (the params' ``tracking.wandb``: disabled | offline | online)
    asks for it, in ``wandb_project``; without it, ``train.wandb`` means offline W&B."""
    from image2sim.simulator.gaussians.build import save_encoder
    from image2sim.simulator.tracking import csv_logger
    from image2sim.simulator.trainer import resume_checkpoint
    from lightning.pytorch.callbacks import ModelCheckpoint

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if scenes is None:
        if not captures:
            raise ValueError("train_stage1: give capture folders or in-memory scenes")
        scenes = [load_scene_frames(p, cfg, max_frames) for p in captures]
    cams = {json.dumps(f.camera.to_dict()) for s in scenes for f in s}
    panoramic = all(isinstance(f.camera, EquirectCamera) for s in scenes for f in s)
    if len(cams) != 1:
        raise ValueError(
            f"train_stage1: all frames must share one camera at the encoder size, got {len(cams)}"
        )
    write_json_atomic(out / "config.json", config_to_dict(cfg))
    L.seed_everything(cfg.train.seed, workers=True, verbose=False)
    module = GeometryModule(
        cfg,
        semantic_model,
        panoramic=panoramic,
        image_dir=str(out / "images"),
        label_classes=label_classes(cfg, scenes),
    )
    data = GeometryDataModule(scenes, cfg)
    last = out / "checkpoints" / "last.ckpt"
    ckpt_path = resume_checkpoint("last", out) if resume and last.is_file() else None
    loggers = [csv_logger(out, resume=ckpt_path is not None)]
    from image2sim.simulator.tracking import wandb_mode

    mode = wandb_mode(wandb) if wandb else ("offline" if cfg.train.wandb else None)
    if mode is not None:
        from image2sim.simulator.tracking import wandb_logger

        loggers.append(wandb_logger(out, wandb_project, config_to_dict(cfg), mode=mode))
    ckpt = ModelCheckpoint(
        dirpath=str(out / "checkpoints"),
        every_n_train_steps=max(1, cfg.train.checkpoint_every),
        save_last=True,
        save_top_k=-1,
    )
    from image2sim.simulator.trainer import lightning_trainer_args

    trainer = L.Trainer(
        **lightning_trainer_args(cfg.trainer),
        max_steps=cfg.train.steps,
        logger=loggers,
        callbacks=[ckpt],
        enable_progress_bar=progress,
        enable_model_summary=False,
        log_every_n_steps=max(1, cfg.train.log_every),
        num_sanity_val_steps=0,
        limit_val_batches=0,
        gradient_clip_val=1.0,
    )
    trainer.fit(module, datamodule=data, ckpt_path=ckpt_path)
    path = out / "encoder.safetensors"
    if trainer.is_global_zero:  # under DDP every rank gets here with the same weights
        save_encoder(module.encoder, path)
    return {
        "steps": int(trainer.global_step),
        "losses": module.history,
        "encoder": str(path),
        "checkpoint": str(last) if last.is_file() else None,
    }
