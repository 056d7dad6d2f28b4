"""The tiny Qwen3-VL policy: interleaved multi-image forward/backward, frozen tower, LoRA, export."""

from __future__ import annotations

import copy

import pytest
import torch
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.config import ConfigError, load_config, paper_config
from image2sim.navpolicy.data import make_sample, synthetic_trajectories
from image2sim.navpolicy.model import (
    base_qwen,
    build_policy,
    enable_checkpointing,
    export_policy,
    trainable_summary,
)
from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder


def _grads(model):
    return {n: (None if p.grad is None else p.grad.detach().clone()) for n, p in model.named_parameters()}


def test_forward_backward_interleaved_images(tiny_policy, batch):
    model = copy.deepcopy(tiny_policy.model)
    model.train()
    assert batch["image_grid_thw"].shape[0] == 12  # 6 images per sample, interleaved with text
    out = model(**batch)
    assert torch.isfinite(out.loss)
    # The loss is the mean cross-entropy over the action tokens only (reference computed by hand).
    logits = out.logits[:, :-1].float()
    tgt = batch["labels"][:, 1:]
    mask = tgt != IGNORE_INDEX
    ref = torch.nn.functional.cross_entropy(logits[mask], tgt[mask])
    torch.testing.assert_close(out.loss, ref, rtol=1e-5, atol=1e-6)
    assert int(mask.sum()) == 2 * 12
    out.loss.backward()
    g = _grads(model)
    vis = {n: v for n, v in g.items() if n.startswith("model.visual.")}
    tower = {
        n: v for n, v in vis.items() if not n.startswith(("model.visual.merger.", "model.visual.deepstack"))
    }
    assert tower and all(v is None for v in tower.values()), "the vision tower must get no gradient"
    merger = [v for n, v in vis.items() if n.startswith("model.visual.merger.")]
    assert merger and all(v is not None and v.abs().sum() > 0 for v in merger)
    lm = [v for n, v in g.items() if n.startswith("model.language_model.layers.")]
    assert lm and all(v is not None for v in lm)
    s = trainable_summary(model)
    assert s["vision_tower_trainable"] == 0 and 0 < s["trainable"] < s["total"]


def test_images_are_wired_into_the_loss(tiny_policy, batch):
    model = copy.deepcopy(tiny_policy.model).eval()
    with torch.no_grad():
        base = model(**batch).loss
        # Image tokens' pixels influence the loss only through the action predictions; changing the
        # pixels must change it, proving images are wired in (and not ignored).
        other = dict(batch, pixel_values=batch["pixel_values"].flip(0))
        assert not torch.allclose(model(**other).loss, base)


def test_gradient_checkpointing_matches_plain(tiny_policy, tiny_cfg, batch):
    plain = copy.deepcopy(tiny_policy.model).train()
    ckpt = copy.deepcopy(tiny_policy.model).train()
    enable_checkpointing(ckpt)
    assert ckpt.is_activation_checkpointing if hasattr(ckpt, "is_activation_checkpointing") else True
    l1, l2 = plain(**batch).loss, ckpt(**batch).loss
    l1.backward()
    l2.backward()
    torch.testing.assert_close(l1, l2)
    g1, g2 = _grads(plain), _grads(ckpt)
    for n in g1:
        if g1[n] is not None:
            torch.testing.assert_close(g1[n], g2[n], rtol=1e-4, atol=1e-6)


def test_lora_trains_only_adapters_and_merges_back(tiny_cfg, batch):
    from transformers import Qwen3VLForConditionalGeneration

    cfg = copy.deepcopy(tiny_cfg)
    cfg.model.lora.enabled = True
    cfg.model.lora.r = 4
    cfg.model.lora.dropout = 0.0
    pol = build_policy(cfg, seed=0)
    trainable = {n for n, p in pol.model.named_parameters() if p.requires_grad}
    assert trainable and all(
        ("lora_" in n) or (".visual.merger." in n) or (".visual.deepstack" in n) for n in trainable
    )
    assert any("language_model" in n and "lora_" in n for n in trainable)
    assert not any(".visual." in n and "lora_" in n for n in trainable)
    frozen_before = {n: p.detach().clone() for n, p in pol.model.named_parameters() if not p.requires_grad}
    opt = torch.optim.SGD([p for p in pol.model.parameters() if p.requires_grad], lr=0.5)
    for _ in range(2):
        opt.zero_grad()
        pol.model(**batch).loss.backward()
        opt.step()
    for n, p in pol.model.named_parameters():
        if not p.requires_grad:
            assert torch.equal(p, frozen_before[n]), n
    pol.model.eval()
    with torch.no_grad():
        adapted = pol.model(**batch).logits
        merged = pol.model.merge_and_unload()
        assert type(merged) is Qwen3VLForConditionalGeneration
        assert not any("lora_" in n for n, _ in merged.named_parameters())
        torch.testing.assert_close(merged(**batch).logits, adapted, rtol=1e-4, atol=1e-5)


def test_export_reloads_with_from_pretrained(tiny_policy, tiny_cfg, batch, tmp_path):
    from transformers import Qwen3VLForConditionalGeneration

    out = export_policy(tiny_policy, tmp_path / "export")
    assert (out / "model.safetensors").is_file() and (out / "preprocessor_config.json").is_file()
    again = Qwen3VLForConditionalGeneration.from_pretrained(str(out), local_files_only=True).eval()
    with torch.no_grad():
        torch.testing.assert_close(again(**batch).logits, tiny_policy.model.eval()(**batch).logits)
    cfg = copy.deepcopy(tiny_cfg)
    cfg.model.source = str(out)
    pol = build_policy(cfg)
    assert pol.codec == tiny_policy.codec
    assert trainable_summary(pol.model)["vision_tower_trainable"] == 0
    assert base_qwen(pol.model) is pol.model


def test_hub_ids_are_refused(tiny_cfg):
    cfg = copy.deepcopy(tiny_cfg)
    cfg.model.source = "Qwen/Qwen3-VL-4B-Instruct"
    with pytest.raises(FileNotFoundError, match="hub ids are refused"):
        build_policy(cfg)


def test_configs_are_strict(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("base: tiny\ntrain:\n  max_steps: 3\n  lr: 1\nmodel:\n  lora: {enabled: true}\n")
    cfg = load_config(p)
    assert cfg.train.max_steps == 3 and cfg.train.lr == 1.0 and cfg.model.lora.enabled
    p.write_text("train:\n  max_stepz: 3\n")
    with pytest.raises(ConfigError, match=r"unknown config key\(s\) \['train.max_stepz'\]"):
        load_config(p)
    p.write_text("train:\n  max_steps: three\n")
    with pytest.raises(ConfigError, match="train.max_steps: expected int"):
        load_config(p)
    with pytest.raises(ConfigError, match="mrope_section"):
        load_config("tiny", {"model": {"tiny": {"mrope_section": [1, 1, 1]}}})
    paper = paper_config()
    assert (paper.observation.height, paper.observation.width) == (336, 336)
    assert (paper.data.max_observations, paper.data.max_action_labels) == (32, 64)
    assert paper.data.observation_stride == 2  # observations where the streaming agent observes
    assert paper.train.strategy == "deepspeed_zero2" and paper.model.gradient_checkpointing
    assert paper.train.devices * paper.train.num_nodes == 64  # the paper's 64 GPUs: 8 nodes x 8
    assert load_config("paper").to_dict() == paper.to_dict()
    wide = load_config("paper-wide").observation
    got = (wide.camera, wide.width, wide.height, wide.hfov_deg, wide.vfov_deg)
    assert got == ("equirect", 512, 336, 180, 118)
    with pytest.raises(ConfigError, match="fallback_action"):
        load_config("tiny", {"agent": {"fallback_action": 7}})
    with pytest.raises(ConfigError, match="observation.camera"):
        load_config("tiny", {"observation": {"camera": "fisheye"}})


def test_collator_matches_the_qwen3vl_processor(tiny_policy, tiny_cfg):
    """Our id-level prompt building equals the stock processor on the same chat text and images."""
    from image2sim.navpolicy.model import make_processor

    sample = make_sample(synthetic_trajectories(1, 10, 10, seed=1)[0], 4, 8)
    col = NavCollator(
        PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt),
        tiny_policy.image_processor,
    )
    ours = col([sample])
    text = tiny_policy.tokenizer.decode(ours["input_ids"][0])
    pad = "<|image_pad|>"
    while pad * 2 in text:  # the processor expands one placeholder per image itself
        text = text.replace(pad * 2, pad)
    assert text.count(pad) == 4
    ref = make_processor(tiny_policy)(text=[text], images=list(sample.observations), return_tensors="pt")
    assert torch.equal(ref["input_ids"], ours["input_ids"])
    assert torch.equal(ref["mm_token_type_ids"].long(), ours["mm_token_type_ids"])
    assert torch.equal(ref["pixel_values"], ours["pixel_values"])
    assert torch.equal(ref["image_grid_thw"], ours["image_grid_thw"])
