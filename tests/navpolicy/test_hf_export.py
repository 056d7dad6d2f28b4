"""Hugging Face conventions of a policy export: Auto* loading, the LoRA adapter through peft, the chat
template that reproduces the policy's prompt, and the model card."""

from __future__ import annotations

import copy
import json

import pytest
import torch
import yaml
from image2sim.navpolicy.collate import NavCollator, image_token_counts
from image2sim.navpolicy.data import make_sample, synthetic_trajectories
from image2sim.navpolicy.model import ADAPTER_DIR, build_policy, export_policy
from image2sim.navpolicy.prompting import PromptBuilder, Turn, chat_template


@pytest.fixture(scope="module")
def lora_export(tiny_cfg, batch, tmp_path_factory):
    """A LoRA policy trained two SGD steps (adapters and projectors move), exported; with its logits."""
    cfg = copy.deepcopy(tiny_cfg)
    cfg.model.lora.enabled, cfg.model.lora.r, cfg.model.lora.dropout = True, 4, 0.0
    pol = build_policy(cfg, seed=0)
    opt = torch.optim.SGD([p for p in pol.model.parameters() if p.requires_grad], lr=0.5)
    for _ in range(2):
        opt.zero_grad()
        pol.model(**batch).loss.backward()
        opt.step()
    pol.model.eval()
    with torch.no_grad():
        adapted = pol.model(**batch).logits
    out = export_policy(pol, tmp_path_factory.mktemp("lora") / "export", cfg)
    return out, adapted, cfg


def test_export_loads_with_the_auto_classes(lora_export, batch):
    from transformers import AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer

    out, adapted, _ = lora_export
    model = AutoModelForImageTextToText.from_pretrained(str(out), local_files_only=True).eval()
    assert type(model).__name__ == "Qwen3VLForConditionalGeneration"
    with torch.no_grad():
        torch.testing.assert_close(model(**batch).logits, adapted, rtol=1e-4, atol=1e-5)
    tok = AutoTokenizer.from_pretrained(str(out), local_files_only=True)
    assert tok.chat_template == chat_template()
    assert AutoImageProcessor.from_pretrained(str(out), local_files_only=True).patch_size > 0


def test_the_adapter_loads_with_peft_and_matches_the_merged_model(lora_export, tiny_cfg, batch):
    from peft import PeftModel

    out, adapted, _ = lora_export
    assert (out / ADAPTER_DIR / "adapter_config.json").is_file()
    assert (out / ADAPTER_DIR / "adapter_model.safetensors").is_file()
    # The base: the frozen weights training started from (same seed, no LoRA).
    base = build_policy(tiny_cfg, seed=0).model
    with torch.no_grad():
        before = base.eval()(**batch).logits.clone()
    peft_model = PeftModel.from_pretrained(base, str(out / ADAPTER_DIR)).eval()
    with torch.no_grad():
        logits = peft_model(**batch).logits
    torch.testing.assert_close(logits, adapted, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(logits, before, atol=1e-3), "the adapter must change the base's outputs"


def test_no_adapter_without_lora(tiny_policy, tmp_path):
    pol = copy.copy(tiny_policy)
    out = export_policy(pol, tmp_path / "export")
    assert not (out / ADAPTER_DIR).exists() and (out / "README.md").is_file()


@pytest.mark.parametrize("generation", [False, True])
def test_chat_template_reproduces_the_policy_prompt(tiny_policy, tiny_cfg, generation):
    """Messages from PromptBuilder.messages through the saved template (and the processor, which
    expands each image's pad) give exactly the ids PromptBuilder.encode / the collator build."""
    from image2sim.navpolicy.model import make_processor

    traj = synthetic_trajectories(1, 10, 10, seed=1)[0]
    sample = make_sample(traj, 4, 8)
    builder = PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt)
    tok = copy.deepcopy(tiny_policy.tokenizer)
    tok.chat_template = chat_template()
    grid = NavCollator(builder, tiny_policy.image_processor)([sample])["image_grid_thw"]
    counts = image_token_counts(grid, tiny_policy.image_processor.merge_size)
    turns = [
        Turn(s, counts[j], tuple(sample.executed[j]), tuple(sample.targets[j]))
        for j, s in enumerate(sample.steps)
    ]
    if generation:  # the agent's prompt: the last observation awaits the reply
        turns[-1] = Turn(turns[-1].frame_key, turns[-1].num_image_tokens, turns[-1].executed, None)
    ids = builder.encode(sample.instruction, turns, add_generation_prompt=generation).input_ids
    assert any(t.executed for t in turns)  # the Executed: line is exercised
    messages = builder.messages(sample.instruction, turns, add_generation_prompt=generation)
    text = tok.apply_chat_template(messages, tokenize=False, add_generation_prompt=generation)
    expected = tiny_policy.tokenizer.decode(ids)
    while "<|image_pad|>" * 2 in expected:
        expected = expected.replace("<|image_pad|>" * 2, "<|image_pad|>")
    assert text == expected
    ref = make_processor(tiny_policy)(text=[text], images=list(sample.observations), return_tensors="pt")
    assert ref["input_ids"][0].tolist() == list(ids)


def test_model_card_front_matter_lineage_and_metrics(tiny_policy, tiny_cfg, tmp_path):
    from image2sim.navpolicy.card import RUN_FILE, update_model_card
    from image2sim.navpolicy.data import write_shard

    shard = tmp_path / "shard"
    write_shard(shard, synthetic_trajectories(3, 4, 6, seed=2))
    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.shards = [str(shard)]
    metrics = tmp_path / "nav.json"
    metrics.write_text(json.dumps({"protocol": {"max_steps": 300}, "agents": {"image2nav": {"sr": 0.25}}}))
    out = export_policy(copy.copy(tiny_policy), tmp_path / "export", cfg, metrics=metrics)
    card = (out / "README.md").read_text()
    _, front, body = card.split("---\n", 2)
    meta = yaml.safe_load(front)
    assert meta["library_name"] == "transformers" and meta["pipeline_tag"] == "image-text-to-text"
    assert "image2nav" in meta["tags"] and "base_model" not in meta  # tiny: from scratch
    params = sum(p.numel() for p in tiny_policy.model.parameters())
    assert f"{params:,}" in body
    import hashlib

    digest = hashlib.sha256((shard / "trajectories.jsonl").read_bytes()).hexdigest()
    assert str(shard) in body and digest[:16] in body and "| 3 |" in body
    assert "`agents.image2nav.sr` | 0.25" in body and "max_steps" not in body
    assert "## Intended use and limitations" in body
    run = json.loads((out / RUN_FILE).read_text())
    assert run["data"][0]["sha256"]["trajectories.jsonl"] == digest
    # Metrics after the fact (eval nav runs after training): the card is rebuilt from the run record.
    metrics.write_text(json.dumps({"agents": {"image2nav": {"sr": 0.5, "spl": 0.4}}}))
    from image2sim.simulator import cli

    with pytest.raises(SystemExit) as info:
        cli.main(["nav", "card", str(out), "--metrics", str(metrics)])
    assert info.value.code == 0
    again = (out / "README.md").read_text()
    assert "`agents.image2nav.spl` | 0.4" in again and digest[:16] in again
    # --out: the card beside the export (the pipeline's policy_card stage), nulls shown as n/a.
    metrics.write_text(json.dumps({"agents": {"image2nav": {"sr": None, "steps": 12.0}}}))
    elsewhere = tmp_path / "policy_card" / "README.md"
    with pytest.raises(SystemExit) as info:
        cli.main(["nav", "card", str(out), "--metrics", str(metrics), "--out", str(elsewhere)])
    assert info.value.code == 0
    assert (out / "README.md").read_text() == again  # the export is left as it was
    card = elsewhere.read_text()
    assert "`agents.image2nav.sr` | n/a" in card and "`agents.image2nav.steps` | 12" in card
    with pytest.raises(FileNotFoundError, match="missing.json"):
        update_model_card(out, tmp_path / "missing.json")
    with pytest.raises(FileNotFoundError, match=RUN_FILE):
        update_model_card(tmp_path, metrics)
