"""Stage 1 behaviour cloning of Image2Nav with Lightning (+ DeepSpeed ZeRO-2).

The same code path runs on 64 GPUs (``strategy="deepspeed_zero2"``, bf16, gradient checkpointing,
``configs/zero2.json``) and on this 2-core CPU in the tests: Lightning's ``DeepSpeedStrategy`` refuses
CPU, so :class:`CPUDeepSpeedStrategy` overrides only device validation (DeepSpeed itself runs on its
CPU accelerator with gloo).

Data order is a pure function of (seed, global sample position): the shared
:class:`~image2sim.simulator.sampling.StepSampler` starts at the position implied by the restored
``global_step``, so a resumed run sees exactly the batches the uninterrupted run would have seen.
With ``data.shard_weights`` the shards are drawn in the given ratios (:class:`MixtureOrder`), still
as a function of (seed, position) only.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import lightning as L
import numpy as np
import torch
from image2sim.navpolicy.collate import NavCollator, model_inputs
from image2sim.navpolicy.config import NavPolicyConfig, TrainConfig
from image2sim.navpolicy.data import InMemoryNavDataset, NavShardDataset, sample_options
from image2sim.navpolicy.model import (
    GoalHead,
    NavPolicy,
    base_qwen,
    build_policy,
    export_policy,
    tokenizer_corpus,
)
from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder
from image2sim.simulator.sampling import StepSampler
from image2sim.simulator.schedules import warmup_cosine


def repo_file(path: str | Path) -> Path:
    """``path`` as given when absolute or present under the working directory, else under the source
    checkout this module runs from (``configs/zero2.json`` from any directory of a clone). Resolved
    on use, not at import: an installed wheel has no checkout above it."""
    path = Path(path)
    if path.is_absolute() or path.exists():
        return path
    for root in Path(__file__).resolve().parents:
        if (root / "packages" / "navpolicy").is_dir() and (root / path).exists():
            return root / path
    return path


# ------------------------------------------------------------------------------------------ data order


def epoch_permutation(n: int, seed: int, epoch: int) -> np.ndarray:
    """The order of the ``n`` samples in ``epoch`` (deterministic in ``seed`` and ``epoch``)."""
    return np.random.default_rng([seed, epoch, 7919]).permutation(n)


class MixtureOrder:
    """Global sample position -> (group epoch, dataset index) when shard groups are drawn by weight.

    ``sizes[g]`` trajectories of group ``g`` sit at dataset indices ``offsets[g] ..`` (shard order).
    Position ``p`` lies in block ``b = p // BLOCK``; the block's groups are drawn from
    ``default_rng([seed, b, 6271])`` with probabilities ``weights / sum(weights)``, so they depend on
    (seed, p) only. The ``k``-th draw of group ``g`` (counted over all earlier positions) is
    trajectory ``perm[k % n_g]`` of the group's epoch ``e = k // n_g``, a permutation seeded by
    ``(seed, e, g)``: inside a group every trajectory is drawn once before any is drawn twice, as in
    the unweighted order. Counting the draws before a block replays the earlier blocks' group draws
    (no sample is loaded), so any position, e.g. a resume's, is located exactly.
    """

    BLOCK = 4096

    def __init__(self, sizes: list[int], weights: list[float], seed: int) -> None:
        w = np.asarray(weights, dtype=np.float64)
        self.sizes = [int(n) for n in sizes]
        if len(w) != len(self.sizes):
            raise ValueError(
                f"data.shard_weights has {len(w)} entries for {len(self.sizes)} shards (one weight each)"
            )
        if not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"data.shard_weights must be finite, >= 0 and sum to > 0, got {list(weights)}")
        empty = [g for g in range(len(w)) if w[g] > 0 and self.sizes[g] == 0]
        if empty:
            raise ValueError(
                f"data.shard_weights: shard {empty[0]} has a positive weight but no trajectories"
            )
        self.seed = int(seed)
        self.offsets = np.concatenate(([0], np.cumsum(self.sizes)[:-1])).astype(np.int64)
        self.cdf = np.cumsum(w) / w.sum()
        self.last = int(np.flatnonzero(w > 0)[-1])
        self._before = [np.zeros(len(w), np.int64)]  # draws per group before block i
        self._block: tuple[int, np.ndarray, np.ndarray] | None = None
        self._perms: dict[int, tuple[int, np.ndarray]] = {}

    def groups(self, block: int) -> np.ndarray:
        """The group of each position of ``block``."""
        u = np.random.default_rng([self.seed, block, 6271]).random(self.BLOCK)
        return np.minimum(np.searchsorted(self.cdf, u, side="right"), self.last)

    def _draws_before(self, block: int) -> np.ndarray:
        while len(self._before) <= block:
            b = len(self._before) - 1
            self._before.append(self._before[-1] + np.bincount(self.groups(b), minlength=len(self.cdf)))
        return self._before[block]

    def locate(self, position: int) -> tuple[int, int]:
        """(group epoch, dataset index) of a global position."""
        b, o = divmod(int(position), self.BLOCK)
        if self._block is None or self._block[0] != b:
            g = self.groups(b)
            rank = np.empty(self.BLOCK, np.int64)  # draws of the same group earlier in the block
            for k in np.unique(g):
                m = g == k
                rank[m] = np.arange(int(m.sum()))
            self._block = (b, g, rank)
        _, g_of, rank = self._block
        g = int(g_of[o])
        epoch, r = divmod(int(self._draws_before(b)[g] + rank[o]), self.sizes[g])
        cached = self._perms.get(g)
        if cached is None or cached[0] != epoch:
            perm = np.random.default_rng([self.seed, epoch, 7919, g]).permutation(self.sizes[g])
            cached = self._perms[g] = (epoch, perm)
        return epoch, int(self.offsets[g] + cached[1][r])


class PositionDataset(torch.utils.data.Dataset):
    """Maps a global sample position ``p`` to sample ``perm_e[p % n]`` of epoch ``e = p // n``.

    With ``weights`` (one per shard of a :class:`NavShardDataset`) the position is mapped by a
    :class:`MixtureOrder` instead: shards are drawn in those ratios whatever their sizes.
    The per-sample sampling randomness (which observations) is seeded by ``(seed, e, index)``.
    """

    def __init__(
        self,
        base: NavShardDataset | InMemoryNavDataset,
        seed: int,
        weights: list[float] | None = None,
    ) -> None:
        self.base, self.seed = base, seed
        self._perms: dict[int, np.ndarray] = {}
        self.mixture = None
        if weights:
            if not isinstance(base, NavShardDataset):
                raise ValueError("data.shard_weights needs a shard dataset (one weight per shard)")
            self.mixture = MixtureOrder([len(r) for r in base.readers], list(weights), seed)

    def locate(self, position: int) -> tuple[int, int]:
        """(epoch, dataset index) of a global position."""
        if self.mixture is not None:
            return self.mixture.locate(position)
        n = len(self.base)
        epoch = position // n
        if epoch not in self._perms:
            self._perms = {epoch: epoch_permutation(n, self.seed, epoch)}
        return epoch, int(self._perms[epoch][position % n])

    def __len__(self) -> int:
        return 1 << 62  # positions are unbounded; the sampler decides how many are drawn

    def __getitem__(self, position: int):
        epoch, i = self.locate(int(position))
        rng = np.random.default_rng([self.seed, epoch, i]) if self.base.jitter else None
        sample = self.base.item(i, rng)
        sample.episode_id = sample.episode_id or f"#{i}"
        return sample


# ------------------------------------------------------------------------------------ DeepSpeed on CPU

# The op DeepSpeed's CPU accelerator JIT-builds when it starts (its ShareMemCommBuilder).
SHM_COMM_OP = "deepspeed_shm_comm"


def cpu_deepspeed_strategy(config: dict | str | Path, **kwargs):
    """Lightning's DeepSpeed strategy, minimally patched to accept the CPU accelerator.

    Only the device checks change: DeepSpeed's own CPU accelerator (gloo) does the work. Use it for
    tests and CPU smoke runs; GPU runs use the stock ``DeepSpeedStrategy``.
    """
    os.environ.setdefault("DS_ACCELERATOR", "cpu")
    from lightning.pytorch.strategies import DDPStrategy, DeepSpeedStrategy

    class CPUDeepSpeedStrategy(DeepSpeedStrategy):
        def setup_environment(self) -> None:
            DDPStrategy.setup_environment(self)  # skip the CUDA-only check, keep DDP's env setup

        @property
        def root_device(self) -> torch.device:
            return torch.device("cpu", 0)

        def setup_distributed(self) -> None:
            from image2sim.simulator.extensions import build_guard, torch_extension_dir
            from lightning.fabric.utilities.seed import reset_seed

            reset_seed()
            self.set_world_ranks()
            # DeepSpeed's CPU backend JIT-builds its shared-memory op here: a build killed earlier
            # would leave torch's lock file and stall this one forever.
            with build_guard(torch_extension_dir(SHM_COMM_OP)):
                self._init_deepspeed_distributed()

    return CPUDeepSpeedStrategy(config=config, process_group_backend="gloo", **kwargs)


def make_strategy(tc: TrainConfig):
    """The Lightning strategy object/name for ``tc``."""
    if tc.strategy != "deepspeed_zero2":
        return tc.strategy
    import importlib.util

    if importlib.util.find_spec("deepspeed") is None:
        raise ValueError(
            "train.strategy deepspeed_zero2 needs DeepSpeed: pip install 'image2sim-navpolicy[deepspeed]' "
            "(or train with strategy auto / ddp)"
        )
    path = repo_file(tc.deepspeed_config)
    if not path.is_file():
        raise FileNotFoundError(
            f"train.deepspeed_config {tc.deepspeed_config} not found (relative paths are looked up in the "
            "working directory, then in the source checkout)"
        )
    config = json.loads(path.read_text())
    if config.get("zero_optimization", {}).get("stage") != 2:
        raise ValueError(f"{path}: zero_optimization.stage must be 2 for deepspeed_zero2")
    if tc.accelerator == "cpu":
        return cpu_deepspeed_strategy(config)
    from lightning.pytorch.strategies import DeepSpeedStrategy

    return DeepSpeedStrategy(config=config)


# ----------------------------------------------------------------------------------- Lightning module


def action_accuracy(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Greedy next-token accuracy on the labelled (action) positions."""
    pred = logits[:, :-1].argmax(-1)
    tgt = labels[:, 1:]
    mask = tgt != IGNORE_INDEX
    if not mask.any():
        return logits.new_zeros(())
    return (pred[mask] == tgt[mask]).float().mean()


def stop_unlikelihood(
    logits: torch.Tensor, input_ids: torch.Tensor, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Unlikelihood of STOP on wrong-goal end samples: ``-log(1 - P(STOP))`` averaged over the samples
    with a marked STOP, where P(STOP) is the product of the probabilities the model gives the STOP
    piece's tokens (``mask``, (B, L) True at their positions; each token is predicted by the logits of
    the position before it). Returns (loss, mean P(STOP)), or None when nothing is marked. Only the
    marked rows are put through the softmax, so the cost does not grow with the vocabulary x length."""
    if mask is None or not bool(mask.any()):
        return None
    b, t = mask[:, 1:].nonzero(as_tuple=True)  # token t + 1 predicted at position t
    logp = torch.log_softmax(logits[b, t].float(), dim=-1).gather(-1, input_ids[b, t + 1].unsqueeze(-1))
    per_sample = torch.zeros(mask.shape[0], dtype=logp.dtype, device=logp.device).index_add(0, b, logp[:, 0])
    marked = torch.unique(b)
    p_stop = per_sample[marked].exp()
    # The (1 - 1e-6) caps the loss at ~13.8 where P(STOP) rounds to 1, keeping its gradient finite.
    return -torch.log1p(-p_stop * (1.0 - 1e-6)).mean(), p_stop.mean().detach()


def stop_weighted_token_loss(
    logits: torch.Tensor, labels: torch.Tensor, stop_mask: torch.Tensor | None, weight: float
) -> tuple[torch.Tensor, float]:
    """(sum, count) of the next-token cross-entropy over the labelled positions, where the tokens
    marked in ``stop_mask`` ((B, L), the expert's STOP piece) count ``weight`` times: their ratio is
    the action loss with the STOP decision weighted. At ``weight`` 1 (or no mask) the ratio is the
    plain token mean the model's own loss computes."""
    tgt = labels[:, 1:]
    known = tgt != IGNORE_INDEX
    ce = torch.nn.functional.cross_entropy(logits[:, :-1][known].float(), tgt[known], reduction="none")
    w = torch.ones_like(ce)
    if stop_mask is not None:
        w = torch.where(stop_mask[:, 1:][known], torch.full_like(ce, float(weight)), w)
    return (w * ce).sum(), float(w.sum())


class NavBCModule(L.LightningModule):
    """Behaviour cloning: cross-entropy on the action tokens of interleaved image/action prompts."""

    def __init__(self, policy: NavPolicy, cfg: NavPolicyConfig, dataset=None) -> None:
        super().__init__()
        self.model = policy.model
        self.policy = policy
        self.cfg = cfg
        self.dataset = dataset
        self.collator = NavCollator(
            PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
        )
        self.seen: list[list[str]] = []
        """Episode ids per training batch (lets tests check the data order across resumes); restored
        from the checkpoint on a resume, so it covers the whole run."""
        self.losses: list[float] = []
        """Training loss per step, whole run (restored from the checkpoint on a resume)."""
        self.goal_head = None
        if cfg.train.goal_aux_weight > 0:
            self.goal_head = policy.goal_head or GoalHead(
                int(base_qwen(policy.model).config.text_config.hidden_size), cfg.train.goal_aux_layer
            )
            if self.goal_head.layer != cfg.train.goal_aux_layer:
                raise ValueError(
                    f"train.goal_aux_layer={cfg.train.goal_aux_layer}, but the goal head of "
                    f"{cfg.model.source} reads hidden state {self.goal_head.layer}: set them alike"
                )
        # The export carries the head only when it trained with this language model: one the
        # source had, left untrained while the model moves, would no longer read its states.
        policy.goal_head = self.goal_head

    def train_dataloader(self):
        tc = self.cfg.train
        if self.dataset is None:
            self.dataset = NavShardDataset(
                self.cfg.data.shards,
                seed=tc.seed,
                max_trajectories=self.cfg.data.max_trajectories,
                cache_frames=self.cfg.data.cache_frames,
                shuffle_instructions=self.cfg.data.shuffle_instructions,
                **sample_options(self.cfg),
            )
        per_step = tc.batch_size * tc.accumulate_grad_batches
        sampler = StepSampler.for_trainer(self.trainer, per_step, tc.max_steps * per_step)
        # Sample ratios apply to the shards of data.shards (a DAgger buffer draws every trajectory).
        weights = self.cfg.data.shard_weights if isinstance(self.dataset, NavShardDataset) else None
        return torch.utils.data.DataLoader(
            PositionDataset(self.dataset, tc.seed, weights),
            batch_size=tc.batch_size,
            sampler=sampler,
            collate_fn=self._collate,
            num_workers=self.cfg.data.num_workers,
        )

    def val_dataloader(self):
        """``val_batches`` batches of ``data.val_shards``: a fixed draw of trajectories, each sampled
        with the generator of (seed, epoch 0, index), so every validation scores the same samples and
        the curve moves only with the weights."""
        tc, shards = self.cfg.train, self.cfg.data.val_shards
        if not shards:
            return []
        opts = sample_options(self.cfg) | {"wrong_goal_stop_probability": 0.0}  # labelled samples only
        val = NavShardDataset(shards, seed=tc.seed, cache_frames=self.cfg.data.cache_frames, **opts)
        count = min(len(val), tc.val_batches * tc.batch_size)
        order = epoch_permutation(len(val), tc.seed, 0)[:count]
        return torch.utils.data.DataLoader(
            torch.utils.data.Subset(val, order.tolist()),
            batch_size=tc.batch_size,
            shuffle=False,
            collate_fn=self._collate,
            num_workers=self.cfg.data.num_workers,
        )

    def validation_step(self, batch, batch_idx):
        out = self(batch)
        bsz = batch["input_ids"].shape[0]
        self.log("val/loss", out.loss, batch_size=bsz, on_epoch=True, on_step=False)
        acc = action_accuracy(out.logits.detach(), batch["labels"])
        self.log("val/action_acc", acc, batch_size=bsz, on_epoch=True, on_step=False)
        goal = self.goal_loss(batch, out)
        if goal is not None:
            self.log("val/goal_acc", goal[1], batch_size=bsz, on_epoch=True, on_step=False)

    def _collate(self, samples):
        batch = self.collator(samples)
        batch["episode_ids"] = [s.episode_id for s in samples]
        return batch

    def forward(self, batch):
        inputs = model_inputs(batch)
        if self.goal_head is not None and "goal_in_view" in batch:
            inputs["output_hidden_states"] = True
        return self.model(**inputs)

    def goal_loss(self, batch, out) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(binary cross-entropy, accuracy) of the grounding head on the batch's labelled images, or
        None (head off, or no labels)."""
        if self.goal_head is None or "goal_in_view" not in batch:
            return None
        ends, y = batch["image_end"], batch["goal_in_view"]
        if len(ends) != len(y):
            raise ValueError(f"{len(y)} goal_in_view labels for {len(ends)} images in the batch")
        known = y >= 0
        if not bool(known.any()):
            return None
        h = self.goal_head.state_at(out.hidden_states, ends[known, 0], ends[known, 1])
        logits = self.goal_head(h)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, y[known])
        acc = ((logits.detach() > 0).float() == y[known]).float().mean()
        return loss, acc

    def training_step(self, batch, batch_idx):
        out = self(batch)
        bsz = batch["input_ids"].shape[0]
        self.seen.append(list(batch["episode_ids"]))
        # Wrong-goal samples carry no labels: a batch of only those has no action loss (its mean is NaN).
        n_tok = int((batch["labels"][:, 1:] != IGNORE_INDEX).sum())
        stop_weight = self.cfg.train.stop_weight
        if stop_weight != 1.0 and n_tok and "stop_positive_mask" in batch:
            total, count = stop_weighted_token_loss(
                out.logits, batch["labels"], batch["stop_positive_mask"], stop_weight
            )
        else:
            total, count = (out.loss * n_tok, float(n_tok)) if n_tok else (out.logits.sum() * 0.0, 0.0)
        wrong = stop_unlikelihood(out.logits, batch["input_ids"], batch.get("stop_negative_mask"))
        if wrong is not None:
            # Each wrong-goal sample counts as stop_weight more labels of the token mean, so its
            # "not STOP" weighs what the expert's STOP label weighs (not a whole sample's labels).
            n_neg = int(batch["stop_negative_mask"].any(1).sum()) * stop_weight
            total, count = total + wrong[0] * n_neg, count + n_neg
            self.log("train/wrong_goal_stop_loss", wrong[0], batch_size=bsz)
            self.log("train/wrong_goal_p_stop", wrong[1], batch_size=bsz)
        loss = total / count if count > 0 else out.logits.sum() * 0.0
        action_loss = loss  # the action part, before the auxiliary grounding loss
        goal = self.goal_loss(batch, out)
        if goal is not None:
            loss = loss + self.cfg.train.goal_aux_weight * goal[0]
            self.log("train/goal_loss", goal[0], batch_size=bsz)
            self.log("train/goal_acc", goal[1], batch_size=bsz)
        self.losses.append(float(action_loss.detach()))
        self.log("train/loss", out.loss, prog_bar=True, batch_size=bsz)
        self.log("train/action_acc", action_accuracy(out.logits.detach(), batch["labels"]), batch_size=bsz)
        return loss

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # The loss and batch history travel with the weights: a resumed run reports the whole run.
        checkpoint["image2nav_history"] = {"losses": list(self.losses), "seen": [list(b) for b in self.seen]}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        hist = checkpoint.get("image2nav_history")
        if hist is not None:
            self.losses = [float(v) for v in hist["losses"]]
            self.seen = [list(b) for b in hist["seen"]]

    def configure_optimizers(self):
        tc = self.cfg.train
        params = [p for p in self.model.parameters() if p.requires_grad]
        if self.goal_head is not None:
            params += list(self.goal_head.parameters())
        if not params:
            raise RuntimeError("no trainable parameters (check model.freeze_vision / lora settings)")
        opt = torch.optim.AdamW(params, lr=tc.lr, weight_decay=tc.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda s: warmup_cosine(s, tc.warmup_steps, tc.max_steps, tc.min_lr_ratio)
        )
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


# ---------------------------------------------------------------------------------------- entry point


@dataclass
class TrainResult:
    """What :func:`train_bc` produced."""

    out_dir: Path
    """Run folder (config, logs, checkpoints)."""
    module: NavBCModule
    """The trained module (its ``losses``/``seen`` record the run)."""
    global_step: int
    """Optimizer steps done in total (including before a resume)."""
    last_checkpoint: Path | None
    """Resumable checkpoint (file, or folder for DeepSpeed)."""
    export_dir: Path | None
    """The Hugging Face export (merged weights, adapter with LoRA, chat template, card), when exported."""


def train_bc(
    cfg: NavPolicyConfig,
    out_dir: str | Path,
    dataset=None,
    resume: str | Path | None = None,
    export: bool = True,
    max_steps: int | None = None,
    policy: NavPolicy | None = None,
) -> TrainResult:
    """Run (or resume) behaviour cloning; writes ``config.yaml``, CSV logs, checkpoints, export.

    Args:
        cfg: the run config (``cfg.data.shards`` is used when ``dataset`` is None).
        out_dir: run folder.
        dataset: optional in-memory dataset (``InMemoryNavDataset``) instead of shards.
        resume: checkpoint to resume from (``"last"`` = ``out_dir/checkpoints/last.ckpt``).
        export: write merged weights to ``out_dir/export`` at the end.
        max_steps: stop after this global step (the LR schedule still uses ``cfg.train.max_steps``);
            lets a test interrupt a run and resume it.
        policy: an already built policy (default: built from ``cfg`` with ``cfg.train.seed``).
    """
    from image2sim.simulator.tracking import csv_logger
    from image2sim.simulator.trainer import resume_checkpoint
    from lightning.pytorch.callbacks import ModelCheckpoint

    tc = cfg.train
    out = Path(out_dir)
    ckpt_path = resume_checkpoint(resume, out)  # checked before anything is written
    out.mkdir(parents=True, exist_ok=True)
    from image2sim.simulator.config import save_config

    save_config(cfg, out / "config.yaml")

    L.seed_everything(tc.seed, workers=True, verbose=False)
    policy = policy or build_policy(cfg, seed=tc.seed, corpus=tokenizer_corpus(cfg, dataset))
    policy.model.train()
    module = NavBCModule(policy, cfg, dataset)
    loggers = [csv_logger(out, resume=resume is not None)]
    if tc.wandb:
        from image2sim.simulator.tracking import wandb_logger, wandb_mode

        mode = wandb_mode(tc.wandb_mode)
        if mode is not None:
            loggers.append(wandb_logger(out, tc.wandb_project, cfg.to_dict(), mode=mode))
    ckpt = ModelCheckpoint(
        dirpath=str(out / "checkpoints"),
        every_n_train_steps=tc.checkpoint_every,
        save_last=True,
        save_top_k=-1,
        filename="step{step:06d}",
        auto_insert_metric_name=False,
    )
    strategy = make_strategy(tc)
    trainer = L.Trainer(
        accelerator=tc.accelerator,
        devices=tc.devices,
        num_nodes=tc.num_nodes,
        strategy=strategy,
        precision=tc.precision,
        max_steps=max_steps if max_steps is not None else tc.max_steps,
        max_time=timedelta(minutes=tc.max_minutes) if tc.max_minutes > 0 else None,
        accumulate_grad_batches=tc.accumulate_grad_batches,
        gradient_clip_val=tc.grad_clip if tc.grad_clip > 0 else None,
        log_every_n_steps=tc.log_every,
        logger=loggers,
        callbacks=[ckpt],
        enable_progress_bar=True,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=tc.val_batches if cfg.data.val_shards else 0,
        val_check_interval=tc.val_every if cfg.data.val_shards else None,
        check_val_every_n_epoch=None if cfg.data.val_shards else 1,
        use_distributed_sampler=False,  # StepSampler already splits positions across ranks
        default_root_dir=str(out),
    )
    trainer.fit(module, ckpt_path=ckpt_path)
    last = out / "checkpoints" / "last.ckpt"
    export_dir = None
    if export and trainer.is_global_zero:
        export_dir = export_policy(policy, out / "export", cfg)
    return TrainResult(out, module, int(trainer.global_step), last if last.exists() else None, export_dir)
