"""Recognition pretraining of the vision tower: labels, metric, learning, loading into a policy."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from image2sim.navpolicy.vision_pretrain import (
    VISION_WEIGHTS,
    VisionPretrainConfig,
    average_precision,
    load_vision_weights,
    pretrain_vision,
    token_labels,
)


def _slow_token_labels(sem, cell, num_classes, min_pixels):
    n, h, w = sem.shape
    out = np.zeros((n, (h // cell) * (w // cell), num_classes), bool)
    for i in range(n):
        for r in range(h // cell):
            for c in range(w // cell):
                block = sem[i, r * cell : (r + 1) * cell, c * cell : (c + 1) * cell]
                for k in range(1, num_classes):
                    out[i, r * (w // cell) + c, k] = (block == k).sum() >= min_pixels
    return out


@pytest.mark.parametrize("cell,min_pixels", [(4, 1), (4, 3), (8, 5)])
def test_token_labels_match_the_slow_reference(cell, min_pixels):
    rng = np.random.default_rng(cell + min_pixels)
    sem = rng.integers(0, 6, size=(3, 16, 24)).astype(np.int16)
    np.testing.assert_array_equal(
        token_labels(sem, cell, 6, min_pixels), _slow_token_labels(sem, cell, 6, min_pixels)
    )


def test_token_labels_threshold_nothing_hit_and_bad_shapes():
    sem = np.zeros((1, 8, 8), np.int16)
    sem[0, :2, 4:6] = 3  # 4 pixels of category 3 in the top-right cell
    lab = token_labels(sem, 4, 5, 4)
    assert lab[0, 1, 3] and lab.sum() == 1  # id 0 (nothing hit) is never a label
    assert not token_labels(sem, 4, 5, 5).any()
    with pytest.raises(ValueError, match="do not tile"):
        token_labels(np.zeros((1, 8, 6), np.int16), 4, 5, 1)
    with pytest.raises(ValueError, match="category ids"):
        token_labels(np.full((1, 8, 8), 7, np.int16), 4, 5, 1)


def test_cells_are_in_the_order_of_the_merged_tokens(tiny_policy):
    """Row k of the labels must describe the pixels that Qwen3-VL merges into token k."""
    from image2sim.navpolicy.collate import patchify_batch
    from image2sim.navpolicy.model import MERGE_SIZE

    proc = tiny_policy.image_processor
    cell = int(proc.patch_size) * MERGE_SIZE
    img = np.zeros((64, 64, 3), np.uint8)
    grid = 64 // cell
    for k in range(grid * grid):
        img[(k // grid) * cell : (k // grid + 1) * cell, (k % grid) * cell : (k % grid + 1) * cell] = 10 * k
    pixels, _ = patchify_batch([img], proc)
    per_token = pixels.reshape(grid * grid, -1)  # 4 patches (one merge window) per token
    values = (per_token * float(proc.image_std[0]) + float(proc.image_mean[0])) * 255.0
    for k in range(grid * grid):
        assert torch.allclose(values[k], torch.full_like(values[k], 10.0 * k), atol=1e-3)


def test_average_precision():
    assert average_precision([0.9, 0.8, 0.7, 0.6], [1, 0, 1, 0]) == pytest.approx((1 + 2 / 3) / 2)
    assert average_precision([0.1, 0.9, 0.5], [1, 0, 0]) == pytest.approx(1 / 3)
    assert average_precision([0.3, 0.2], [1, 1]) == 1.0
    assert math.isnan(average_precision([0.3, 0.2], [0, 0]))


def _toy_views(root: Path, houses: int = 3, per_house: int = 48, size: int = 64) -> Path:
    """Views where category 4..7 is a square of its own colour in one random cell (learnable)."""
    colours = {4: (220, 40, 40), 5: (40, 200, 40), 6: (40, 60, 220), 7: (230, 220, 40)}
    rng = np.random.default_rng(0)
    (root / "views").mkdir(parents=True)
    for h in range(houses):
        rgb = np.full((per_house, size, size, 3), 128, np.uint8)
        sem = np.full((per_house, size, size), 2, np.int16)
        for i in range(per_house):
            for c in rng.choice(list(colours), size=2, replace=False):
                y, x = rng.integers(0, size - 12, size=2)
                rgb[i, y : y + 12, x : x + 12] = colours[int(c)]
                sem[i, y : y + 12, x : x + 12] = int(c)
        np.savez(root / "views" / f"h{h}.npz", rgb=rgb, semantics=sem)
    cats = [
        {"id": i, "name": n}
        for i, n in enumerate(["floor", "wall", "ceiling", "sofa", "lamp", "bed", "desk"], 1)
    ]
    (root / "categories.json").write_text(json.dumps({"categories": cats}))
    manifest = {
        "format": "image2sim-views",
        "version": 1,
        "config": {},
        "scenes": {f"h{h}": per_house for h in range(houses)},
    }
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


def test_pretraining_learns_to_recognise_and_loads_into_a_policy(tiny_cfg, tmp_path):
    from image2sim.navpolicy.model import base_qwen, build_policy

    views = _toy_views(tmp_path / "views")
    cfg = VisionPretrainConfig(
        steps=120, batch_size=16, lr=3e-3, warmup_steps=10, eval_every=10, val_fraction=0.34
    )
    report = pretrain_vision(tiny_cfg, views, tmp_path / "pre", cfg)
    hist = report["history"]
    assert report["val_houses"] == ["h2"] and report["train_views"] == 96
    assert hist[0]["map_objects"] < 0.8 < hist[-1]["map_objects"], hist
    # model.vision_weights loads exactly what was saved, into a fresh policy of the same sizes.
    from safetensors.torch import load_file

    saved = load_file(str(tmp_path / "pre" / VISION_WEIGHTS))
    cfg2 = replace(tiny_cfg, model=replace(tiny_cfg.model, vision_weights=str(tmp_path / "pre")))
    visual = base_qwen(build_policy(cfg2, seed=7).model).model.visual
    for k, v in visual.state_dict().items():
        assert torch.equal(v, saved[k]), k
    assert not any(p.requires_grad for n, p in visual.named_parameters() if n.startswith("blocks."))


def test_probe_only_keeps_the_random_tower(tiny_cfg, tmp_path):
    from image2sim.navpolicy.model import base_qwen, build_policy
    from safetensors.torch import load_file

    views = _toy_views(tmp_path / "views", per_house=8)
    cfg = VisionPretrainConfig(steps=3, batch_size=4, eval_every=3, train_tower=False, seed=5)
    pretrain_vision(tiny_cfg, views, tmp_path / "probe", cfg)
    saved = load_file(str(tmp_path / "probe" / VISION_WEIGHTS))
    init = base_qwen(build_policy(tiny_cfg, seed=5).model).model.visual.state_dict()
    assert all(torch.equal(saved[k], init[k]) for k in init if k.startswith(("blocks.", "patch_embed.")))
    assert not torch.equal(saved["merger.linear_fc2.weight"], init["merger.linear_fc2.weight"])


def test_vision_weights_errors(tiny_cfg, tiny_policy, tmp_path):
    import copy

    from safetensors.torch import save_file

    with pytest.raises(FileNotFoundError, match="pretrain-vision"):
        load_vision_weights(copy.deepcopy(tiny_policy.model), tmp_path / "absent")
    save_file({"patch_embed.proj.weight": torch.zeros(3)}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(ValueError, match="keys differ"):
        load_vision_weights(copy.deepcopy(tiny_policy.model), tmp_path / "bad.safetensors")
    from image2sim.navpolicy.model import base_qwen

    state = {k: v.clone() for k, v in base_qwen(tiny_policy.model).model.visual.state_dict().items()}
    state["merger.linear_fc2.bias"] = torch.zeros(3)
    save_file(state, str(tmp_path / "shape.safetensors"))
    with pytest.raises(ValueError, match="merger.linear_fc2.bias has shape"):
        load_vision_weights(copy.deepcopy(tiny_policy.model), tmp_path / "shape.safetensors")
    views = _toy_views(tmp_path / "v32", houses=2, per_house=2, size=32)
    with pytest.raises(ValueError, match="do not match the policy's observation"):
        pretrain_vision(tiny_cfg, views, tmp_path / "x", VisionPretrainConfig(steps=1))


def test_grounding_questions_ask_every_view_yes_and_no_equally():
    from image2sim.navpolicy.vision_pretrain import grounding_question

    rng = np.random.default_rng(0)
    counts = rng.integers(0, 3, size=(5, 30)) * 15  # pixels of 5 categories in 30 views
    counts[:, 0] = 0  # a view that shows nothing is never asked about
    pool = np.arange(30)
    qs = [grounding_question(counts, pool, 20, rng) for _ in range(6000)]
    assert all(i != 0 for _, i, _ in qs)
    for view in range(1, 30):
        labels = [y for _, i, y in qs if i == view]
        if labels:
            assert abs(np.mean(labels) - 0.5) < 0.2  # the view alone says nothing
    assert abs(np.mean([y for *_, y in qs]) - 0.5) < 0.03
    for c, i, y in qs:
        assert (counts[c, i] >= 20) if y else counts[c, i] == 0
    with pytest.raises(ValueError, match="empty"):
        grounding_question(np.zeros((2, 3), int) + 5, np.arange(3), 20, rng)


def _half_views(root: Path, houses: int = 3, per_house: int = 48) -> Path:
    """Views whose lower half is one category's colour (upper half wall): is the named one in view?"""
    colours = {4: (220, 40, 40), 5: (40, 200, 40), 6: (40, 60, 220), 7: (230, 220, 40)}
    rng = np.random.default_rng(0)
    (root / "views").mkdir(parents=True)
    for h in range(houses):
        rgb = np.full((per_house, 64, 64, 3), 128, np.uint8)
        sem = np.full((per_house, 64, 64), 2, np.int16)
        for i in range(per_house):
            c = int(rng.choice(list(colours)))
            rgb[i, 32:] = colours[c]
            sem[i, 32:] = c
        np.savez(root / "views" / f"h{h}.npz", rgb=rgb, semantics=sem)
    names = ["floor", "wall", "ceiling", "sofa", "lamp", "bed", "desk"]
    cats = [{"id": i, "name": n} for i, n in enumerate(names, 1)]
    (root / "categories.json").write_text(json.dumps({"categories": cats}))
    scenes = {f"h{h}": per_house for h in range(houses)}
    (root / "manifest.json").write_text(
        json.dumps({"format": "image2sim-views", "version": 1, "config": {}, "scenes": scenes})
    )
    return root


@pytest.mark.slow
def test_grounding_pretraining_learns_from_the_view_and_exports_a_policy(tiny_cfg, tmp_path):
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.vision_pretrain import GroundingConfig, pretrain_grounding

    views = _half_views(tmp_path / "views")
    cfg = GroundingConfig(
        steps=200, batch_size=16, lr=3e-3, warmup_steps=5, eval_every=200, val_fraction=0.34
    )
    report = pretrain_grounding(tiny_cfg, views, tmp_path / "ground", cfg)
    first, last = report["history"][0], report["history"][-1]
    # Only the pair (named category, view) answers the question: another view leaves it at chance.
    assert last["val_acc"] > 0.9 and last["val_acc_other_view"] < 0.7, report["history"]
    assert abs(first["val_acc"] - 0.5) < 0.2
    # The export is a policy that behaviour cloning can start from.
    loaded = build_policy(replace(tiny_cfg, model=replace(tiny_cfg.model, source=str(tmp_path / "ground"))))
    assert json.loads((tmp_path / "ground" / "grounding.json").read_text())["final"] == last
    assert loaded.codec.single_token
