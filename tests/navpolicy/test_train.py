"""Behaviour cloning: loss goes down, resume is exact, DeepSpeed ZeRO-2 steps on CPU."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.config import load_config
from image2sim.navpolicy.data import InMemoryNavDataset, make_sample, synthetic_trajectories
from image2sim.navpolicy.prompting import PromptBuilder
from image2sim.navpolicy.train import (
    PositionDataset,
    action_accuracy,
    epoch_permutation,
    train_bc,
    warmup_cosine,
)
from image2sim.simulator.config import ConfigError
from image2sim.simulator.sampling import StepSampler


def _cfg(tiny_cfg, steps: int):
    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.max_steps = steps
    cfg.train.checkpoint_every = 3
    cfg.train.batch_size = 2
    cfg.train.lr = 3e-3
    cfg.train.warmup_steps = 1
    cfg.data.max_observations = 4
    cfg.data.max_action_labels = 8
    return cfg


@pytest.fixture(scope="module")
def trajs():
    return synthetic_trajectories(12, min_len=6, max_len=24, seed=0)


def test_schedule_and_sampler_units():
    assert warmup_cosine(0, 4, 10, 0.1) == pytest.approx(0.25)
    assert warmup_cosine(4, 4, 10, 0.1) == pytest.approx(1.0)
    assert warmup_cosine(10, 4, 10, 0.1) == pytest.approx(0.1)
    assert warmup_cosine(7, 4, 10, 0.1) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    # Two ranks split the global order; a restart at step k continues where the first run stopped.
    r0, r1 = list(StepSampler(0, 5, 0, 2)), list(StepSampler(0, 5, 1, 2))
    assert sorted(r0 + r1) == list(range(10))
    assert list(StepSampler(3, 5, 0, 1)) == [3, 4]
    ds = PositionDataset(InMemoryNavDataset(synthetic_trajectories(5, 3, 5, 4, 4)), seed=1)
    order = [ds.locate(p)[1] for p in range(10)]
    assert sorted(order[:5]) == list(range(5)) and sorted(order[5:]) == list(range(5))
    assert order[:5] == epoch_permutation(5, 1, 0).tolist()
    logits = torch.zeros(1, 3, 4)
    logits[0, 0, 2] = 1.0
    assert action_accuracy(logits, torch.tensor([[-100, 2, -100]])) == 1.0


def _heldout_loss(policy, cfg, trajs) -> float:
    col = NavCollator(
        PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
    )
    batch = col([make_sample(t, 4, 8, None) for t in trajs])
    policy.model.eval()
    with torch.no_grad():
        return float(policy.model(**batch).loss)


def test_bc_reduces_the_loss(tiny_cfg, trajs, tmp_path):
    from image2sim.navpolicy.model import build_policy

    cfg = _cfg(tiny_cfg, 25)
    policy = build_policy(cfg, seed=0)
    held = synthetic_trajectories(4, min_len=6, max_len=24, seed=99)
    before = _heldout_loss(policy, cfg, held)
    res = train_bc(
        cfg, tmp_path / "run", dataset=InMemoryNavDataset(trajs, 4, 8), policy=policy, export=False
    )
    after = _heldout_loss(policy, cfg, held)
    assert res.global_step == 25
    assert after < 0.6 * before, (before, after)
    assert np.mean(res.module.losses[-5:]) < np.mean(res.module.losses[:5])
    saved = load_config(tmp_path / "run" / "config.yaml")
    assert saved.to_dict() == cfg.to_dict()
    assert (tmp_path / "run" / "logs" / "version_0" / "metrics.csv").is_file()


def test_a_wall_clock_cap_stops_training_early_and_still_exports(tiny_cfg, trajs, tmp_path):
    """``train.max_minutes``: a time-boxed run (a lent GPU's minutes) stops at the cap, keeps a
    checkpoint and exports a loadable policy; 0 (the default) means no cap; negative is refused."""
    cfg = _cfg(tiny_cfg, 10_000)
    cfg.train.max_minutes = 0.05  # 3 s: far fewer than 10 000 steps on any machine
    res = train_bc(cfg, tmp_path / "run", dataset=InMemoryNavDataset(trajs, 4, 8), export=True)
    assert 0 < res.global_step < 10_000
    assert res.last_checkpoint is not None and res.export_dir is not None
    assert (res.export_dir / "model.safetensors").is_file()
    bad = copy.deepcopy(cfg)
    bad.train.max_minutes = -1.0
    with pytest.raises(ConfigError, match="train.max_minutes"):
        bad.validate()


def test_resume_continues_with_the_same_step_and_data(tiny_cfg, trajs, tmp_path):
    cfg = _cfg(tiny_cfg, 6)
    full = train_bc(cfg, tmp_path / "full", dataset=InMemoryNavDataset(trajs, 4, 8), export=False)
    first = train_bc(
        cfg, tmp_path / "split", dataset=InMemoryNavDataset(trajs, 4, 8), export=False, max_steps=3
    )
    assert first.global_step == 3 and first.last_checkpoint is not None
    second = train_bc(
        cfg, tmp_path / "split", dataset=InMemoryNavDataset(trajs, 4, 8), export=True, resume="last"
    )
    assert second.global_step == 6
    # The resumed module's history (restored from the checkpoint) covers the whole run.
    assert second.module.seen == full.module.seen and second.module.seen[:3] == first.module.seen
    assert len(second.module.losses) == 6 and second.module.losses[:3] == first.module.losses
    np.testing.assert_allclose(second.module.losses, full.module.losses, rtol=1e-4)
    a = dict(full.module.model.named_parameters())
    for n, p in second.module.model.named_parameters():
        torch.testing.assert_close(p, a[n], rtol=1e-4, atol=1e-6)
    assert (second.export_dir / "model.safetensors").is_file()


def test_deepspeed_starts_past_a_lock_left_by_a_killed_op_build(tmp_path, monkeypatch):
    """DeepSpeed's CPU backend JIT-builds an op when it starts; a build killed earlier leaves torch's
    lock file, on which every later start waited forever. The strategy starts through the guard."""
    pytest.importorskip("deepspeed")
    from image2sim.navpolicy.train import SHM_COMM_OP, cpu_deepspeed_strategy

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    stale = tmp_path / "ext" / SHM_COMM_OP / "lock"
    stale.parent.mkdir(parents=True)
    stale.write_text("")
    strategy = cpu_deepspeed_strategy({"zero_optimization": {"stage": 2}})
    seen = []
    monkeypatch.setattr(type(strategy), "set_world_ranks", lambda self: None)
    monkeypatch.setattr(
        type(strategy), "_init_deepspeed_distributed", lambda self: seen.append(stale.exists())
    )
    strategy.setup_distributed()
    assert seen == [False]


@pytest.mark.slow
def test_deepspeed_zero2_on_cpu_matches_plain_adamw(tiny_cfg, trajs, tmp_path, monkeypatch):
    """One process of DeepSpeed ZeRO-2 (CPU accelerator, gloo) through the Lightning strategy.

    DeepSpeed JIT-builds an op when it starts (about a minute): here into a fresh folder holding the
    lock file of a killed build, which used to stall the run forever.
    """
    from image2sim.navpolicy.train import SHM_COMM_OP

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    (tmp_path / "ext" / SHM_COMM_OP).mkdir(parents=True)
    (tmp_path / "ext" / SHM_COMM_OP / "lock").write_text("")
    cfg = _cfg(tiny_cfg, 3)
    plain = train_bc(cfg, tmp_path / "plain", dataset=InMemoryNavDataset(trajs, 4, 8), export=False)
    cfg.train.strategy = "deepspeed_zero2"
    ds = train_bc(cfg, tmp_path / "ds", dataset=InMemoryNavDataset(trajs, 4, 8), export=True)
    assert ds.global_step == 3
    assert ds.module.seen == plain.module.seen
    np.testing.assert_allclose(ds.module.losses, plain.module.losses, rtol=1e-3)
    # It really ran DeepSpeed ZeRO stage 2 (a plain run would match the losses too), and saved a
    # DeepSpeed checkpoint: a folder of sharded states, not a single file.
    strategy = ds.module.trainer.strategy
    assert "DeepSpeed" in type(strategy).__name__ and strategy.config["zero_optimization"]["stage"] == 2
    assert (tmp_path / "ds" / "checkpoints" / "last.ckpt").is_dir()
    assert (ds.export_dir / "model.safetensors").is_file()


@pytest.mark.parametrize("kind", ["missing", "garbage", "not_lightning"])
def test_a_bad_resume_checkpoint_is_refused_before_the_run_writes_anything(tiny_cfg, tmp_path, kind):
    import torch
    from image2sim.simulator.trainer import CheckpointError

    path = tmp_path / f"{kind}.ckpt"
    if kind == "garbage":
        path.write_bytes(b"garbage")
    elif kind == "not_lightning":
        torch.save({"weight": torch.zeros(2)}, path)
    expected = {"missing": "not found", "garbage": "not a readable", "not_lightning": "not from Lightning"}
    expected = expected[kind]
    with pytest.raises(CheckpointError, match=expected):
        train_bc(tiny_cfg, tmp_path / "run", dataset=None, resume=str(path))
    assert not (tmp_path / "run").exists()


def test_validation_on_held_out_shards_is_logged_and_does_not_touch_training(tiny_cfg, trajs, tmp_path):
    """data.val_shards: val/loss and val/action_acc every val_every steps, on the same samples each
    time (scored with the weights of that step); training losses are those of a run without it."""
    import csv

    from image2sim.navpolicy.data import write_shard

    val = write_shard(tmp_path / "val", synthetic_trajectories(6, min_len=6, max_len=24, seed=7))
    cfg = _cfg(tiny_cfg, 6)
    plain = train_bc(cfg, tmp_path / "plain", dataset=InMemoryNavDataset(trajs, 4, 8), export=False)
    cfg.data.val_shards = [str(val)]
    cfg.train.val_every, cfg.train.val_batches = 3, 2
    run = train_bc(cfg, tmp_path / "val_run", dataset=InMemoryNavDataset(trajs, 4, 8), export=False)
    assert run.module.losses == plain.module.losses
    rows = list(csv.DictReader(open(tmp_path / "val_run" / "logs" / "version_0" / "metrics.csv")))
    scored = [(int(r["step"]), float(r["val/loss"])) for r in rows if r.get("val/loss")]
    assert [s for s, _ in scored] == [2, 5]  # after steps 3 and 6 (0-based step index)
    assert all(math.isfinite(v) for _, v in scored) and scored[0][1] != scored[1][1]
    accs = [float(r["val/action_acc"]) for r in rows if r.get("val/action_acc")]
    assert len(accs) == 2 and all(0.0 <= a <= 1.0 for a in accs)
    # The validation set is a fixed draw: its loss under the final weights equals a fresh scoring.
    module = run.module
    module.model.eval()
    with torch.no_grad():
        again = [float(module(b).loss) for b in module.val_dataloader()]
    assert len(again) == 2 and float(np.mean(again)) == pytest.approx(scored[-1][1], rel=1e-5)
    with pytest.raises(Exception, match="val_every"):
        bad = copy.deepcopy(cfg)
        bad.train.val_every = 0
        bad.validate()


def test_an_episodes_output_folder_stands_for_the_shards_it_lists(tmp_path):
    """`nav train --shard <data episodes --out>` trains on every shard of its shards.json, in order
    (scene shards and approach shards); a shard folder stays itself."""
    import json

    from image2sim.navpolicy.train_cli import expand_shard_folders

    out = tmp_path / "episodes"
    for rel in ("scenes/a/shard", "scenes/a/approach", "scenes/b/shard"):
        (out / rel).mkdir(parents=True)
        (out / rel / "manifest.json").write_text("{}")
    (out / "shards.json").write_text(
        json.dumps({"shards": ["scenes/a/shard", "scenes/a/approach", "scenes/b/shard"]})
    )
    plain = out / "scenes" / "b" / "shard"
    got = expand_shard_folders([out, plain])
    assert got == [out / "scenes/a/shard", out / "scenes/a/approach", plain, plain]
    assert expand_shard_folders([]) == []


def test_repo_file_resolves_from_any_directory_and_reports_missing_files(tmp_path, monkeypatch):
    """Relative config paths (train.deepspeed_config) work from any working directory of a clone,
    and nothing is resolved at import (an installed wheel has no checkout above it)."""
    from image2sim.navpolicy.train import TrainConfig, make_strategy, repo_file

    monkeypatch.chdir(tmp_path)
    found = repo_file("configs/zero2.json")
    assert found.is_file() and found.is_absolute() and found.parent.name == "configs"
    (tmp_path / "local.json").write_text("{}")
    assert repo_file("local.json") == Path("local.json")  # the working directory comes first
    assert repo_file(tmp_path / "x.json") == tmp_path / "x.json"
    assert not repo_file("configs/absent.json").exists()
    pytest.importorskip("deepspeed")
    with pytest.raises(FileNotFoundError, match="deepspeed_config configs/absent.json"):
        make_strategy(TrainConfig(strategy="deepspeed_zero2", deepspeed_config="configs/absent.json"))


def test_a_tokenizer_learned_on_the_training_instructions_is_exported(tiny_cfg, tmp_path):
    """``model.tiny.tokenizer_corpus: instructions``: BC builds the tiny tokenizer on its shards'
    instructions, the export carries it, and the reloaded policy tokenizes the task's words whole.
    Without any instructions the policy is refused, and unknown corpora are config errors."""
    from image2sim.navpolicy.data import shard_instructions, write_shard
    from image2sim.navpolicy.model import build_policy, tokenizer_corpus
    from image2sim.navpolicy.tokenizer import load_tokenizer

    trajs = synthetic_trajectories(6, min_len=6, max_len=12, seed=3)
    goals = ["toilet", "bookshelf", "armchair"]
    for k, t in enumerate(trajs):
        t.instruction = f"Find the {goals[k % 3]} in the bathroom and stop next to the {goals[k % 3]}."
    shard = write_shard(tmp_path / "shard", trajs)
    assert shard_instructions([shard]) == [t.instruction for t in trajs]
    cfg = _cfg(tiny_cfg, 2)
    cfg.model.tiny.tokenizer_corpus = "instructions"
    cfg.model.tiny.tokenizer_vocab_size = 768
    cfg.data.shards = [str(shard)]
    assert tokenizer_corpus(cfg) == [t.instruction for t in trajs]
    res = train_bc(cfg, tmp_path / "run")
    tok = load_tokenizer(res.export_dir)
    assert all(len(tok(" " + g)["input_ids"]) == 1 for g in goals)
    reloaded = copy.deepcopy(cfg)
    reloaded.model.source = str(res.export_dir)
    assert build_policy(reloaded).tokenizer.get_vocab() == tok.get_vocab()
    # `nav tokenizer --config` shows the tokenizer such a config trains with.
    import json

    import yaml
    from image2sim.navpolicy.cli import app
    from typer.testing import CliRunner

    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    shown = CliRunner().invoke(app, ["tokenizer", "--config", str(tmp_path / "cfg.yaml")])
    assert shown.exit_code == 0, shown.output
    assert json.loads(shown.output)["vocab_size"] == len(tok)
    empty = copy.deepcopy(cfg)
    empty.data.shards = []
    with pytest.raises(ValueError, match="tokenizer_corpus"):
        build_policy(empty, corpus=tokenizer_corpus(empty))
    empty.model.tiny.tokenizer_corpus = "wikipedia"
    with pytest.raises(ConfigError, match="model.tiny.tokenizer_corpus"):
        empty.validate()
