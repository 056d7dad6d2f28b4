"""The grounding auxiliary (``train.goal_aux_weight``): per-frame goal_in_view labels travel from the
shard record to the image they describe, and the head's loss is what the training step adds."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.data import (
    GOAL_IN_VIEW,
    InMemoryNavDataset,
    NavShardDataset,
    ShardError,
    make_sample,
    synthetic_trajectories,
    write_shard,
)
from image2sim.navpolicy.prompting import PromptBuilder
from image2sim.simulator.conventions import Action


def _labelled(trajs):
    """goal_in_view = 1 on frames whose action is FORWARD (its tint is visible in the frame)."""
    out = []
    for t in copy.deepcopy(trajs):
        t.extra = {GOAL_IN_VIEW: [int(t.actions[s] == int(Action.MOVE_FORWARD)) for s in t.frame_steps]}
        out.append(t.validate())
    return out


@pytest.fixture(scope="module")
def trajs():
    return _labelled(synthetic_trajectories(10, min_len=6, max_len=20, seed=3))


def test_labels_follow_their_frames_into_the_batch(tiny_policy, tiny_cfg, trajs):
    col = NavCollator(
        PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt),
        tiny_policy.image_processor,
    )
    rng = np.random.default_rng(0)
    samples = [make_sample(t, 4, 8, rng, context=(2, 2)) for t in trajs[:3]]
    plain = synthetic_trajectories(1, min_len=6, max_len=8, seed=9)[0]  # no labels
    samples.append(make_sample(plain, 4, 8, rng))
    for s, t in zip(samples[:3], trajs, strict=False):
        assert s.goal_in_view == [t.extra[GOAL_IN_VIEW][t.frame_steps.index(k)] for k in s.steps]
    batch = col(samples)
    mm, ends = batch["mm_token_type_ids"], batch["image_end"]
    n_images = sum(len(s.observations) for s in samples)
    assert ends.shape == (n_images, 2) and len(batch["goal_in_view"]) == n_images
    for row, pos in ends.tolist():  # the last token of an image run
        assert mm[row, pos] == 1 and (pos + 1 == mm.shape[1] or mm[row, pos + 1] == 0)
    want = [v for s in samples[:3] for v in s.goal_in_view] + [-1.0] * len(samples[3].observations)
    assert batch["goal_in_view"].tolist() == want
    # Without any labelled sample the batch is exactly the plain one.
    assert "goal_in_view" not in col(samples[3:]) and "image_end" not in col(samples[3:])


def test_bad_labels_are_refused_and_borrowed_instructions_drop_them(trajs, tmp_path):
    bad = copy.deepcopy(trajs[0])
    bad.extra = {GOAL_IN_VIEW: [1] * (len(bad.frame_steps) + 1)}
    with pytest.raises(ShardError, match="goal_in_view"):
        bad.validate("rec")
    bad.extra = {GOAL_IN_VIEW: [2] * len(bad.frame_steps)}
    with pytest.raises(ShardError, match="goal_in_view"):
        bad.validate("rec")
    shard = write_shard(tmp_path / "s", trajs)
    assert NavShardDataset([shard]).trajectory(0).extra[GOAL_IN_VIEW] == trajs[0].extra[GOAL_IN_VIEW]
    shuffled = NavShardDataset([shard], shuffle_instructions=True)
    assert all(GOAL_IN_VIEW not in shuffled.trajectory(i).extra for i in range(len(shuffled)))


def head_loss_by_hand(module, batch, out, layer: int) -> torch.Tensor:
    """The grounding loss written out: the head on hidden state ``layer`` at each image's last token."""
    h = out.hidden_states[layer][batch["image_end"][:, 0], batch["image_end"][:, 1]]
    logits = module.goal_head.linear(h).squeeze(-1)
    return torch.nn.functional.binary_cross_entropy_with_logits(logits, batch["goal_in_view"])


def test_training_adds_the_heads_loss_and_learns_it(tiny_cfg, trajs, tmp_path):
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.train import NavBCModule, train_bc

    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.goal_aux_weight = 0.5
    cfg.train.max_steps, cfg.train.batch_size, cfg.train.lr, cfg.train.warmup_steps = 30, 4, 3e-3, 1
    cfg.train.checkpoint_every = 100
    cfg.data.max_observations, cfg.data.max_action_labels = 4, 8
    policy = build_policy(cfg, seed=0)
    module = NavBCModule(policy, cfg)
    batch = module._collate([make_sample(t, 4, 8, None) for t in trajs[:4]])
    out = module(batch)
    bce, _ = module.goal_loss(batch, out)
    torch.testing.assert_close(bce, head_loss_by_hand(module, batch, out, layer=-1))
    module.log = lambda *a, **k: None  # outside a Trainer
    module.seen, module.losses = [], []
    total = module.training_step(batch, 0)
    torch.testing.assert_close(total, out.loss + 0.5 * bce)
    res = train_bc(cfg, tmp_path / "run", dataset=InMemoryNavDataset(trajs, 4, 8), policy=policy, export=True)
    import csv

    rows = [r for r in csv.DictReader(open(tmp_path / "run" / "logs" / "version_0" / "metrics.csv"))]
    goal = [float(r["train/goal_loss"]) for r in rows if r.get("train/goal_loss")]
    assert len(goal) == 30 and np.mean(goal[-5:]) < np.mean(goal[:5]), goal
    from safetensors import safe_open

    with safe_open(str(res.export_dir / "model.safetensors"), "pt") as f:
        assert not any("goal_head" in k for k in f.keys())  # the head is its own file, not the model's
    assert (res.export_dir / "goal_head.safetensors").is_file()


def test_without_the_weight_there_is_no_head(tiny_cfg, tiny_policy):
    from image2sim.navpolicy.config import ConfigError, from_dict
    from image2sim.navpolicy.train import NavBCModule

    assert NavBCModule(copy.deepcopy(tiny_policy), tiny_cfg).goal_head is None
    with pytest.raises(ConfigError, match="goal_aux_weight"):
        from_dict({"train": {"goal_aux_weight": -1.0}})


def test_the_head_can_read_a_state_that_later_tokens_attend_to(tiny_cfg, trajs):
    """``goal_aux_layer=-2`` reads the output of the layer before the last: the loss then trains no
    weight of the last layer (whose output at the image's last token no later token can read), and
    an index past the embeddings, or a non-negative one, is refused by name."""
    from image2sim.navpolicy.config import ConfigError, from_dict
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.train import NavBCModule

    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.goal_aux_weight, cfg.train.goal_aux_layer = 1.0, -2
    cfg.data.max_observations, cfg.data.max_action_labels = 4, 8
    module = NavBCModule(build_policy(cfg, seed=0), cfg)
    batch = module._collate([make_sample(t, 4, 8, None) for t in trajs[:4]])
    out = module(batch)
    bce, _ = module.goal_loss(batch, out)
    torch.testing.assert_close(bce, head_loss_by_hand(module, batch, out, layer=-2))
    bce.backward()
    layers = module.model.model.language_model.layers
    last = [p.grad for p in layers[-1].parameters() if p.requires_grad]
    first = [p.grad for p in layers[0].parameters() if p.requires_grad]
    assert all(g is None or float(g.abs().max()) == 0.0 for g in last)
    assert any(g is not None and float(g.abs().max()) > 0.0 for g in first)

    cfg.train.goal_aux_layer = -(len(layers) + 1)  # the embeddings: not a layer's output
    module = NavBCModule(build_policy(cfg, seed=0), cfg)
    with pytest.raises(ValueError, match="goal_aux_layer"):
        module.goal_loss(batch, module(batch))
    with pytest.raises(ConfigError, match="goal_aux_layer"):
        from_dict({"train": {"goal_aux_layer": 0}})
