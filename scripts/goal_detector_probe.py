"""Can a small CNN tell, from one 64 px view, that the *named* goal category is in view?

A factorised detector: one logit per goal category from a small convolutional network; the gate's
probability for an episode is the logit of the episode's goal category, so the category cannot be
ignored (the learned goal heads of session 47 ignored the instruction). Trained on the data engine
shards' ``goal_in_view`` labels (each frame labelled for its own episode's goal category only),
scored on shards of other houses: AUC of the own category's probability, and how the probability of
positive frames changes when another category is asked for (the instruction test).

    .venv/bin/python scripts/goal_detector_probe.py --train outputs/sim2real/episodes/exact/scenes/*/shard \\
        --test <held-out shards> --out detector/   # writes detector.safetensors + metrics.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn


class GoalDetector(nn.Module):
    """Per-category "goal in view" logits from one RGB view (N, 3, H, W) in [0, 1]."""

    def __init__(self, categories: list[str], width: int = 32) -> None:
        super().__init__()
        self.categories = list(categories)
        w = width
        layers, c_in = [], 3
        for c_out in (w, 2 * w, 4 * w, 4 * w):
            layers += [
                nn.Conv2d(c_in, c_out, 3, stride=2, padding=1),
                nn.BatchNorm2d(c_out),
                nn.ReLU(inplace=True),
            ]
            layers += [nn.Conv2d(c_out, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
            c_in = c_out
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(c_in * 2, len(categories))

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        f = self.features(rgb * 2.0 - 1.0)
        pooled = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3))], dim=1)
        return self.head(pooled)


def as_batch(frames: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) uint8 views -> (N, 3, H, W) float in [0, 1], the detector's input."""
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float() / 255.0


def load_detector(folder: str | Path) -> GoalDetector:
    """The detector a run of this script saved in ``folder`` (``detector.safetensors``, its
    categories and width in the metadata), in eval mode."""
    from safetensors import safe_open
    from safetensors.torch import load_model

    path = Path(folder) / "detector.safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (write it with scripts/goal_detector_probe.py)")
    with safe_open(str(path), "pt") as f:
        meta = f.metadata() or {}
    if "categories" not in meta or "width" not in meta:
        raise ValueError(f"{path}: metadata lacks 'categories' and 'width'")
    model = GoalDetector(json.loads(meta["categories"]), int(meta["width"]))
    load_model(model, str(path))
    return model.eval()


def load_frames(shards: list[str], categories: list[str] | None = None):
    from image2sim.navpolicy.data import ShardReader

    imgs, cats, labels, is_end = [], [], [], []
    for s in shards:
        r = ShardReader(s)
        for i, rec in enumerate(r.records):
            extra = rec.get("extra") or {}
            seen, cat = extra.get("goal_in_view"), extra.get("goal_category")
            if seen is None or not cat:
                continue
            f = r.frames(i)
            imgs.append(f)
            cats += [cat] * len(f)
            labels += [int(v) for v in seen]
            is_end += [0] * (len(f) - 1) + [1]
    names = sorted(set(cats)) if categories is None else categories
    index = {c: k for k, c in enumerate(names)}
    keep = np.array([c in index for c in cats])
    x = np.concatenate(imgs)[keep]
    c = np.array([index[c] for c in cats if c in index])
    return names, x, c, np.array(labels)[keep], np.array(is_end)[keep]


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (rank statistic; ties count half)."""
    from scipy.stats import rankdata

    pos, neg = labels == 1, labels == 0
    if not pos.any() or not neg.any():
        return float("nan")
    r = rankdata(scores)
    return float((r[pos].sum() - pos.sum() * (pos.sum() + 1) / 2) / (pos.sum() * neg.sum()))


@torch.no_grad()
def probabilities(model: GoalDetector, x: np.ndarray, batch: int = 512) -> np.ndarray:
    model.eval()
    out = []
    for k in range(0, len(x), batch):
        out.append(torch.sigmoid(model(as_batch(x[k : k + batch]))).numpy())
    return np.concatenate(out)


def evaluate(model, x, c, y, end, rng) -> dict:
    p = probabilities(model, x)
    own = p[np.arange(len(c)), c]
    other_c = (c + rng.integers(1, p.shape[1], len(c))) % p.shape[1]
    other = p[np.arange(len(c)), other_c]
    pos = y == 1
    return {
        "frames": int(len(y)),
        "positive_rate": float(y.mean()),
        "auc_own": auc(own, y),
        "positives_p_own": float(own[pos].mean()),
        "positives_p_other": float(other[pos].mean()),
        "negatives_p_own": float(own[~pos].mean()),
        "ends": int(end.sum()),
        "ends_positive_rate": float(y[end == 1].mean()),
        "ends_p_own": float(own[end == 1].mean()),
        "ends_p_other": float(other[end == 1].mean()),
        "auc_own_vs_other_on_positives": auc(
            np.concatenate([own[pos], other[pos]]), np.concatenate([np.ones(pos.sum()), np.zeros(pos.sum())])
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", nargs="+", required=True)
    ap.add_argument("--test", nargs="+", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    names, x, c, y, end = load_frames(args.train)
    _, xt, ct, yt, endt = load_frames(args.test, names)
    print(f"train {len(y)} frames ({y.mean():.3f} positive), {len(names)} categories; test {len(yt)}")
    model = GoalDetector(names, args.width)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.steps)
    pos_weight = torch.tensor((1 - y.mean()) / max(y.mean(), 1e-6)).clamp(max=10.0)
    t0 = time.time()
    for step in range(args.steps):
        model.train()
        idx = rng.integers(0, len(y), args.batch)
        img = as_batch(x[idx])
        if rng.random() < 0.5:
            img = img.flip(3)  # a mirrored room holds the same objects
        logits = model(img)[torch.arange(args.batch), torch.from_numpy(c[idx])]
        loss = nn.functional.binary_cross_entropy_with_logits(
            logits, torch.from_numpy(y[idx]).float(), pos_weight=pos_weight
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 500 == 0 or step == args.steps - 1:
            print(f"step {step} loss {loss.item():.4f} ({time.time() - t0:.0f} s)", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from safetensors.torch import save_model

    save_model(
        model,
        str(out / "detector.safetensors"),
        metadata={"categories": json.dumps(names), "width": str(args.width)},
    )
    res = {
        "train": evaluate(model, x, c, y, end, rng),
        "test": evaluate(model, xt, ct, yt, endt, rng),
        "params": sum(p.numel() for p in model.parameters()),
        "seconds": time.time() - t0,
        "args": vars(args),
        "categories": names,
    }
    (out / "metrics.json").write_text(json.dumps(res, indent=2))
    print(json.dumps({k: res[k] for k in ("train", "test", "params", "seconds")}, indent=2))


if __name__ == "__main__":
    main()
