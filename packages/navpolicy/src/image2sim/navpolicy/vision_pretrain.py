"""Recognition pretraining of the tiny policy's vision tower (``image2sim nav pretrain-vision``).

The paper's Image2Nav sees through a pretrained Qwen3-VL: its vision tower already tells a bed from
a wardrobe, and the navigation training only has to tie those words to actions. The from-scratch
tiny policy has no such prior: its random, frozen tower has to carry the category of a few-pixel
object into 16 tokens, and behaviour cloning alone never taught it to (docs/sim2real.md). This
module gives it the prior the paper takes for granted, on our own data: the vision tower and its
merger learn to say, for every merged token (a 16x16-pixel cell at the tiny sizes), which categories
cover at least ``min_pixels`` of its pixels (multi-label, binary cross-entropy through a linear head
that is thrown away). The views come from ``image2sim data views`` (exact renders of procedural houses
with per-pixel category ids). The weights go to a safetensors file that ``model.vision_weights``
loads into a policy before behaviour cloning, which then keeps the tower frozen as usual.

The pure pieces (labels, average precision) are functions; :func:`pretrain_vision` is the loop.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from image2sim.simulator.config import require_at_least, require_in_range

__all__ = [
    "VisionPretrainConfig",
    "GroundingConfig",
    "pretrain_grounding",
    "token_labels",
    "average_precision",
    "pretrain_vision",
    "load_vision_weights",
    "VISION_WEIGHTS",
]

VISION_WEIGHTS = "vision.safetensors"
"""File name of the pretrained vision tower in a ``nav pretrain-vision`` output folder."""


@dataclass
class VisionPretrainConfig:
    """Recognition pretraining of the vision tower."""

    steps: int = 1500
    """Optimiser steps."""
    batch_size: int = 64
    """Views per step."""
    lr: float = 2e-3
    """Peak AdamW learning rate (linear warm-up, cosine decay to a tenth)."""
    weight_decay: float = 0.01
    """AdamW weight decay."""
    warmup_steps: int = 50
    """Linear warm-up steps."""
    val_fraction: float = 0.1
    """Share of the houses (whole houses, the last ones) held out to score recognition."""
    min_pixels: int = 4
    """A category is present in a token's cell when it covers at least this many pixels."""
    flip: bool = True
    """Random horizontal flips of view and labels."""
    train_tower: bool = True
    """Train the tower; off, only the merger and head train (the random-tower probe baseline)."""
    eval_every: int = 250
    """Score the held-out houses every this many steps (and at the end)."""
    seed: int = 0
    """Seed of the tower's initialisation, the batch order and the flips."""

    def validate(self) -> VisionPretrainConfig:
        where = "pretrain-vision: "
        require_at_least(self, ("steps", "batch_size", "eval_every", "min_pixels"), 1, where)
        require_in_range(self, "val_fraction", 0.0, 1.0, low_open=True, high_open=True, where=where)
        require_in_range(self, "lr", 0.0, math.inf, low_open=True, high_open=True, where=where)
        return self


def token_labels(semantics: np.ndarray, cell: int, num_classes: int, min_pixels: int) -> np.ndarray:
    """(N, (S/cell)^2, num_classes) bool: category c covers >= ``min_pixels`` pixels of a token's
    ``cell`` x ``cell`` block, blocks in row-major order (the order of Qwen3-VL's merged tokens).
    Id 0 (nothing hit) is never a label."""
    sem = np.asarray(semantics)
    n, h, w = sem.shape
    if h % cell or w % cell:
        raise ValueError(f"views of {h}x{w} pixels do not tile into {cell}-pixel token cells")
    if sem.size and (sem.min() < 0 or sem.max() >= num_classes):
        raise ValueError(f"category ids must lie in [0, {num_classes}), got [{sem.min()}, {sem.max()}]")
    gh, gw = h // cell, w // cell
    rows = np.arange(h) // cell
    cols = np.arange(w) // cell
    token = (rows[:, None] * gw + cols[None, :])[None]  # (1, H, W)
    flat = (np.arange(n)[:, None, None] * (gh * gw) + token) * num_classes + sem.astype(np.int64)
    counts = np.bincount(flat.ravel(), minlength=n * gh * gw * num_classes)
    labels = counts.reshape(n, gh * gw, num_classes) >= min_pixels
    labels[..., 0] = False
    return labels


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision of one class (area under the precision-recall steps; nan without positives)."""
    y = np.asarray(labels, bool).ravel()
    if not y.any():
        return float("nan")
    order = np.argsort(-np.asarray(scores, np.float64).ravel(), kind="stable")
    hits = y[order]
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float(precision[hits].mean())


def load_vision_weights(model: torch.nn.Module, path: str | Path) -> None:
    """Load a ``pretrain-vision`` file into ``model``'s vision tower (incl. its mergers); every key and
    shape must match, else the error names the first difference."""
    from image2sim.navpolicy.model import base_qwen
    from safetensors.torch import load_file

    p = Path(path)
    if p.is_dir():
        p = p / VISION_WEIGHTS
    if not p.is_file():
        raise FileNotFoundError(
            f"model.vision_weights: {p} not found (write it with `image2sim nav pretrain-vision`)"
        )
    state = load_file(str(p))
    visual = base_qwen(model).model.visual
    own = visual.state_dict()
    missing = sorted(set(own) - set(state))
    extra = sorted(set(state) - set(own))
    if missing or extra:
        raise ValueError(
            f"model.vision_weights {p}: keys differ from this model's vision tower "
            f"(missing {missing[:3]}, unexpected {extra[:3]}): pretrained with other model.tiny sizes?"
        )
    for k, v in state.items():
        if tuple(v.shape) != tuple(own[k].shape):
            raise ValueError(
                f"model.vision_weights {p}: {k} has shape {tuple(v.shape)}, this model's is "
                f"{tuple(own[k].shape)}: pretrained with other model.tiny sizes?"
            )
    visual.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()})


def _split_by_house(manifest: dict, val_fraction: float) -> tuple[np.ndarray, np.ndarray, list[str]]:
    names = list(manifest["scenes"])
    counts = [int(manifest["scenes"][n]) for n in names]
    if len(names) < 2:
        raise ValueError("pretrain-vision needs views of >= 2 houses (the last ones score recognition)")
    n_val = min(len(names) - 1, max(1, round(val_fraction * len(names))))
    bounds = np.cumsum([0, *counts])
    cut = int(bounds[len(names) - n_val])
    return np.arange(cut), np.arange(cut, int(bounds[-1])), names[len(names) - n_val :]


def pretrain_vision(
    policy_config,
    views: str | Path,
    out_dir: str | Path,
    config: VisionPretrainConfig | None = None,
    progress: bool = False,
) -> dict:
    """Train the vision tower of ``policy_config``'s model to recognise the categories of ``views``
    (a ``data views`` folder); writes ``out_dir/vision.safetensors`` and ``out_dir/pretrain.json``
    (config, the policy's tiny sizes, held-out mean average precision over the object categories at
    every evaluation) and returns the latter."""
    from image2sim.dataengine.procedural.views import load_views
    from image2sim.navpolicy.collate import patchify_batch
    from image2sim.navpolicy.model import MERGE_SIZE, base_qwen, build_policy, tokenizer_corpus
    from image2sim.simulator.io.atomic import atomic_dir
    from image2sim.simulator.schedules import warmup_cosine

    cfg = (config or VisionPretrainConfig()).validate()
    rgb, sem, manifest = load_views(views)
    table = json.loads((Path(views) / "categories.json").read_text())["categories"]
    num_classes = max(int(c["id"]) for c in table) + 1
    objects = [int(c["id"]) for c in table if c["name"] not in ("floor", "wall", "ceiling")]
    policy = build_policy(policy_config, seed=cfg.seed, corpus=tokenizer_corpus(policy_config))
    processor = policy.image_processor
    size = rgb.shape[1]
    if patchify_batch([rgb[0]], processor) is None:
        raise ValueError(
            f"views of {size}x{size} pixels do not match the policy's observation "
            f"({policy_config.observation.height}x{policy_config.observation.width}): render them "
            "with `data views --size` equal to observation.height"
        )
    visual = base_qwen(policy.model).model.visual.float()
    cell = int(processor.patch_size) * MERGE_SIZE
    labels = token_labels(sem, cell, num_classes, cfg.min_pixels)
    train_idx, val_idx, val_houses = _split_by_house(manifest, cfg.val_fraction)
    head = torch.nn.Linear(visual.merger.linear_fc2.out_features, num_classes)
    for name, p in visual.named_parameters():
        p.requires_grad_(cfg.train_tower or name.startswith(("merger.", "deepstack_merger_list.")))
    params = [p for p in visual.parameters() if p.requires_grad] + list(head.parameters())
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: warmup_cosine(s, cfg.warmup_steps, cfg.steps, 0.1)
    )
    gen = np.random.default_rng(cfg.seed)
    grid = size // cell

    def logits_of(images: np.ndarray) -> torch.Tensor:
        pixels, thw = patchify_batch(list(images), processor)
        merged = visual(pixels, grid_thw=thw).pooler_output  # (N * tokens, width)
        return head(merged).reshape(len(images), grid * grid, num_classes)

    def evaluate() -> dict:
        visual.eval()
        scores = []
        with torch.no_grad():
            for i in range(0, len(val_idx), 256):
                scores.append(torch.sigmoid(logits_of(rgb[val_idx[i : i + 256]])).numpy())
        visual.train()
        s = np.concatenate(scores)
        y = labels[val_idx]
        ap = {c: average_precision(s[..., c], y[..., c]) for c in objects}
        known = [v for v in ap.values() if not math.isnan(v)]
        return {"map_objects": float(np.mean(known)) if known else float("nan"), "classes": len(known)}

    history = []
    t0 = time.perf_counter()
    steps = range(cfg.steps)
    if progress:
        from rich.progress import track

        steps = track(steps, description="pretraining the vision tower")
    loss_avg = None
    for step in steps:
        idx = gen.choice(train_idx, size=min(cfg.batch_size, len(train_idx)), replace=False)
        images, y = rgb[idx], labels[idx]
        if cfg.flip:
            flip = gen.random(len(idx)) < 0.5
            images = np.where(flip[:, None, None, None], images[:, :, ::-1], images)
            y_grid = y.reshape(len(idx), grid, grid, num_classes)
            y = np.where(flip[:, None, None, None], y_grid[:, :, ::-1], y_grid).reshape(y.shape)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            logits_of(np.ascontiguousarray(images)), torch.from_numpy(y).float()
        )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        loss_avg = loss.item() if loss_avg is None else 0.98 * loss_avg + 0.02 * loss.item()
        if (step + 1) % cfg.eval_every == 0 or step + 1 == cfg.steps:
            history.append(
                {"step": step + 1, "loss": loss_avg, **evaluate(), "seconds": time.perf_counter() - t0}
            )
    from safetensors.torch import save_file

    report = {
        "config": asdict(cfg),
        "views": str(views),
        "train_views": int(len(train_idx)),
        "val_views": int(len(val_idx)),
        "val_houses": val_houses,
        "token_cell_pixels": cell,
        "tiny": asdict(policy_config.model.tiny),
        "history": history,
        "final": history[-1] if history else {},
        "seconds": time.perf_counter() - t0,
    }
    with atomic_dir(out_dir) as tmp:
        state = {k: v.detach().contiguous() for k, v in visual.state_dict().items()}
        save_file(state, str(tmp / VISION_WEIGHTS), metadata={"format": "image2sim-vision-tower"})
        (tmp / "pretrain.json").write_text(json.dumps(report, indent=1))
    return report


# ------------------------------------------------------------------------------ stage 2: grounding


@dataclass
class GroundingConfig:
    """Grounding pretraining: is the object the instruction names in this view?"""

    steps: int = 2400
    """Optimiser steps."""
    batch_size: int = 32
    """Questions per step."""
    lr: float = 2e-3
    """AdamW learning rate (constant after a linear warm-up)."""
    warmup_steps: int = 50
    """Linear warm-up steps."""
    min_pixels: int = 20
    """A category is in view when it covers at least this many pixels; absent when it covers none."""
    val_fraction: float = 0.1
    """Share of the houses (the last ones) held out to score grounding."""
    val_questions: int = 400
    """Held-out questions scored at every evaluation."""
    eval_every: int = 200
    """Score the held-out houses every this many steps (and at the end)."""
    seed: int = 0
    """Seed of the questions and of the head's initialisation."""

    def validate(self) -> GroundingConfig:
        where = "pretrain-grounding: "
        names = ("steps", "batch_size", "eval_every", "min_pixels", "val_questions")
        require_at_least(self, names, 1, where)
        require_in_range(self, "val_fraction", 0.0, 1.0, low_open=True, high_open=True, where=where)
        require_in_range(self, "lr", 0.0, math.inf, low_open=True, high_open=True, where=where)
        return self


GROUNDING_TEMPLATES = (
    "Go to the {}.",
    "Find the {} and stop there.",
    "Walk to the {}.",
    "Please stop at the {}.",
)
"""Instruction wordings of the grounding questions (the category's name with spaces)."""


def grounding_question(counts: np.ndarray, pool: np.ndarray, min_pixels: int, rng) -> tuple[int, int, int]:
    """(category row, view index, label) of one question over the views in ``pool``: a view first
    (one that shows some category with >= ``min_pixels`` pixels and lacks another), then with
    probability 1/2 a category it shows (label 1), else one it does not show at all (0). Every view
    is thus asked about as often with answer yes as with no, so the view alone (e.g. how cluttered it
    is) says nothing about the answer: only the view *and* the named category together do. A
    category's word alone still carries a prior (a painting is on most walls); the blind control of
    :func:`pretrain_grounding` (another view) measures it. ``counts``: (C, N) pixels of each category
    row in each view."""
    present = counts[:, pool] >= min_pixels
    absent = counts[:, pool] == 0
    usable = pool[present.any(axis=0) & absent.any(axis=0)]
    if not len(usable):
        raise ValueError("no view shows one category and lacks another: are the views empty?")
    i = int(rng.choice(usable))
    label = int(rng.random() < 0.5)
    rows = np.nonzero(counts[:, i] >= min_pixels if label else counts[:, i] == 0)[0]
    return int(rng.choice(rows)), i, label


def pretrain_grounding(
    policy_config,
    views: str | Path,
    out_dir: str | Path,
    config: GroundingConfig | None = None,
    progress: bool = False,
) -> dict:
    """Train ``policy_config``'s policy (its trainable parts: language model and mergers; set
    ``model.vision_weights`` to start from a recognition-pretrained tower) to answer, at the last
    token of one view, whether the object its instruction names is in that view, through the
    grounding head of ``train.goal_aux_weight``. Writes the policy as an export to ``out_dir`` (start
    behaviour cloning from it with ``model.source: <out_dir>``) with ``grounding.json``: held-out
    accuracy at each evaluation, with the right view and with another view (the blind control)."""
    import copy

    from image2sim.dataengine.procedural.views import load_views
    from image2sim.navpolicy.data import NavSample
    from image2sim.navpolicy.model import build_policy, export_policy, tokenizer_corpus
    from image2sim.navpolicy.train import NavBCModule

    cfg = (config or GroundingConfig()).validate()
    rgb, sem, manifest = load_views(views)
    table = json.loads((Path(views) / "categories.json").read_text())["categories"]
    objects = [c for c in table if c["name"] not in ("floor", "wall", "ceiling")]
    names = [c["name"].replace("_", " ") for c in objects]
    counts = np.stack([(sem == int(c["id"])).sum(axis=(1, 2)) for c in objects])
    train_idx, val_idx, val_houses = _split_by_house(manifest, cfg.val_fraction)
    pcfg = copy.deepcopy(policy_config)
    pcfg.train.goal_aux_weight = max(pcfg.train.goal_aux_weight, 1.0)  # the module builds its head
    torch.manual_seed(cfg.seed)
    policy = build_policy(pcfg, seed=cfg.seed, corpus=tokenizer_corpus(pcfg))
    module = NavBCModule(policy, pcfg)
    rng = np.random.default_rng(cfg.seed)

    def sample(c: int, i: int, label: int, wording: int, view: int | None = None) -> NavSample:
        text = GROUNDING_TEMPLATES[wording % len(GROUNDING_TEMPLATES)].format(names[c])
        image = rgb[i if view is None else view][None]
        return NavSample(text, image, [0], [()], [(0, 0)], goal_in_view=[label])

    vrng = np.random.default_rng([cfg.seed, 1])
    val_q = [
        (*grounding_question(counts, val_idx, cfg.min_pixels, vrng), k) for k in range(cfg.val_questions)
    ]
    others = vrng.permutation(len(val_q))
    val_own = [sample(c, i, y, k) for c, i, y, k in val_q]
    val_other = [
        sample(c, i, y, k, view=val_q[int(j)][1]) for (c, i, y, k), j in zip(val_q, others, strict=True)
    ]

    def accuracy(samples) -> float:
        module.eval()
        hits = 0.0
        with torch.no_grad():
            for k in range(0, len(samples), 50):
                batch = module._collate(samples[k : k + 50])
                hits += float(module.goal_loss(batch, module(batch))[1]) * len(batch["goal_in_view"])
        module.train()
        return hits / len(samples)

    params = [p for p in module.model.parameters() if p.requires_grad] + list(module.goal_head.parameters())
    opt = torch.optim.AdamW(params, lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / max(1, cfg.warmup_steps)))
    history = [{"step": 0, "val_acc": accuracy(val_own), "val_acc_other_view": accuracy(val_other)}]
    t0 = time.perf_counter()
    steps = range(cfg.steps)
    if progress:
        from rich.progress import track

        steps = track(steps, description="grounding pretraining")
    module.train()
    loss_avg = None
    for step in steps:
        qs = [grounding_question(counts, train_idx, cfg.min_pixels, rng) for _ in range(cfg.batch_size)]
        batch = module._collate([sample(c, i, y, int(rng.integers(1 << 30))) for c, i, y in qs])
        loss, _ = module.goal_loss(batch, module(batch))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        loss_avg = loss.item() if loss_avg is None else 0.95 * loss_avg + 0.05 * loss.item()
        if (step + 1) % cfg.eval_every == 0 or step + 1 == cfg.steps:
            history.append(
                {
                    "step": step + 1,
                    "loss": loss_avg,
                    "val_acc": accuracy(val_own),
                    "val_acc_other_view": accuracy(val_other),
                    "seconds": time.perf_counter() - t0,
                }
            )
    report = {
        "config": asdict(cfg),
        "views": str(views),
        "val_houses": val_houses,
        "history": history,
        "final": history[-1],
        "seconds": time.perf_counter() - t0,
    }
    policy.model.eval()
    export_policy(policy, out_dir, pcfg)
    (Path(out_dir) / "grounding.json").write_text(json.dumps(report, indent=1))
    return report
