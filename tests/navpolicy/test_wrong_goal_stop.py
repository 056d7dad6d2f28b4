"""Wrong-goal end samples (``data.wrong_goal_stop_probability``): a trajectory's end under an
instruction naming another goal category, trained only against STOP there."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
from image2sim.navpolicy.actions import Action
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.data import GOAL_CATEGORY, InMemoryNavDataset, synthetic_trajectories
from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder
from image2sim.navpolicy.train import stop_unlikelihood, stop_weighted_token_loss, train_bc

CATEGORY_TINT = {"sofa": np.array([255, 60, 60]), "bed": np.array([60, 60, 255])}


def _trajs(n: int = 8, seed: int = 0):
    """Synthetic trajectories alternating between two goal categories in one scene; the last frame
    (where the expert stops) is tinted with the goal's colour, so the view says which goal is there."""
    out = []
    for k, t in enumerate(synthetic_trajectories(n, min_len=6, max_len=12, seed=seed)):
        cat = ("sofa", "bed")[k % 2]
        frames = t.frames.copy()
        frames[-1] = (0.5 * frames[-1] + 0.5 * CATEGORY_TINT[cat]).astype(np.uint8)
        out.append(
            dataclasses.replace(
                t, instruction=f"find the {cat}", frames=frames, scene_id="s0", extra={GOAL_CATEGORY: cat}
            )
        )
    return out


def _ds(trajs, p: float, **kw):
    return InMemoryNavDataset(trajs, 4, 8, seed=0, wrong_goal_stop_probability=p, **kw)


def test_wrong_goal_samples_swap_to_another_category_and_end_at_the_stop():
    trajs = _trajs()
    ds = _ds(trajs, 1.0)
    for i in range(len(trajs)):
        s = ds[i]
        assert s.stop_negative and s.goal_in_view is None
        own = trajs[i].extra[GOAL_CATEGORY]
        assert s.instruction.startswith("find the ") and not s.instruction.endswith(own)
        assert s.steps[-1] == trajs[i].frame_steps[-1]  # cut at the end
        assert int(Action.STOP) in s.targets[-1]
    # Off, or without categories: the regular sample stream, draw for draw.
    plain = InMemoryNavDataset(trajs, 4, 8, seed=0)
    no_cat = [dataclasses.replace(t, extra={}) for t in trajs]
    for i in range(len(trajs)):
        for other in (_ds(trajs, 0.0)[i], _ds(no_cat, 1.0)[i]):
            assert not other.stop_negative
        assert _ds(trajs, 0.0)[i].steps == plain[i].steps
    # A single category leaves nothing to swap to.
    one = [dataclasses.replace(t, extra={GOAL_CATEGORY: "sofa"}) for t in trajs]
    assert not any(_ds(one, 1.0)[i].stop_negative for i in range(len(one)))
    with pytest.raises(ValueError, match="wrong_goal_stop_probability"):
        _ds(trajs, 1.5)


def test_the_rate_of_wrong_goal_samples_follows_the_probability():
    trajs = _trajs(16)
    ds = _ds(trajs, 0.3)
    hits = 0
    for epoch in range(25):
        ds.set_epoch(epoch)
        hits += sum(ds[i].stop_negative for i in range(len(trajs)))
    assert abs(hits / (25 * len(trajs)) - 0.3) < 0.06


def test_the_collator_marks_only_the_final_stop_and_drops_the_labels(tiny_policy, tiny_cfg):
    trajs = _trajs()
    col = NavCollator(
        PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt),
        tiny_policy.image_processor,
    )
    neg, pos = _ds(trajs, 1.0)[0], _ds(trajs, 0.0)[1]
    batch = col([neg, pos])
    mask = batch["stop_negative_mask"]
    assert not mask[1].any() and (batch["labels"][1] != IGNORE_INDEX).any()
    assert (batch["labels"][0] == IGNORE_INDEX).all()
    stop_piece = tiny_policy.codec.encode(neg.targets[-1])[list(neg.targets[-1]).index(int(Action.STOP))]
    assert batch["input_ids"][0][mask[0]].tolist() == list(stop_piece)
    # The marked tokens are among what the regular sample labels in its last reply.
    regular = col([dataclasses.replace(neg, stop_negative=False, instruction=trajs[0].instruction)])
    labelled = (regular["labels"][0] != IGNORE_INDEX).nonzero()[:, 0].tolist()
    last_reply = labelled[len(labelled) - sum(len(pc) for pc in tiny_policy.codec.encode(neg.targets[-1])) :]
    assert set(mask[0].nonzero()[:, 0].tolist()) <= set(last_reply)
    assert "stop_negative_mask" not in col([pos])
    # The regular sample's own final STOP is marked for train.stop_weight, at its labelled tokens.
    plus = batch["stop_positive_mask"]
    assert not plus[0].any() and plus[1].any()
    assert (batch["labels"][1][plus[1]] != IGNORE_INDEX).all()
    piece = tiny_policy.codec.encode(pos.targets[-1])[list(pos.targets[-1]).index(int(Action.STOP))]
    assert batch["input_ids"][1][plus[1]].tolist() == list(piece)


def test_stop_weighted_token_loss_matches_a_reference():
    g = torch.Generator().manual_seed(1)
    logits = torch.randn(2, 9, 13, generator=g, dtype=torch.float64)
    labels = torch.randint(0, 13, (2, 9), generator=g)
    labels[0, :3] = IGNORE_INDEX
    labels[1, 7:] = IGNORE_INDEX
    stop = torch.zeros(2, 9, dtype=torch.bool)
    stop[0, 6:8] = True  # a two-token STOP piece
    plain = torch.nn.functional.cross_entropy(logits[:, :-1].reshape(-1, 13), labels[:, 1:].reshape(-1))
    total, count = stop_weighted_token_loss(logits, labels, stop, 1.0)
    assert float(total / count) == pytest.approx(float(plain), rel=1e-6)
    assert count == int((labels[:, 1:] != IGNORE_INDEX).sum())
    # Reference: a loop over the labelled positions, the marked ones counted five times.
    num, den = 0.0, 0.0
    logp = torch.log_softmax(logits, -1)
    for b in range(2):
        for t in range(1, 9):
            if labels[b, t] == IGNORE_INDEX:
                continue
            w = 5.0 if stop[b, t] else 1.0
            num += -w * float(logp[b, t - 1, labels[b, t]])
            den += w
    total, count = stop_weighted_token_loss(logits, labels, stop, 5.0)
    assert float(total) == pytest.approx(num, rel=1e-6) and count == pytest.approx(den)


def test_the_training_loss_weighs_both_stop_decisions_by_stop_weight(tiny_policy, tiny_cfg):
    from image2sim.navpolicy.train import NavBCModule

    trajs = _trajs()
    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.stop_weight = 7.0
    module = NavBCModule(copy.deepcopy(tiny_policy), cfg)
    module.log = lambda *a, **k: None  # outside a Trainer
    batch = module._collate([_ds(trajs, 1.0)[0], _ds(trajs, 0.0)[1], _ds(trajs, 0.0)[2]])
    assert batch["stop_positive_mask"].any()
    out = module(batch)
    total, count = stop_weighted_token_loss(out.logits, batch["labels"], batch["stop_positive_mask"], 7.0)
    wrong, _ = stop_unlikelihood(out.logits, batch["input_ids"], batch["stop_negative_mask"])
    expected = (total + 7.0 * wrong) / (count + 7.0)  # one wrong-goal sample, seven labels' worth
    torch.testing.assert_close(module.training_step(batch, 0), expected)
    # At weight 1 the same batch gives the earlier rule: the token mean plus one label per wrong goal.
    cfg.train.stop_weight = 1.0
    n_tok = int((batch["labels"][:, 1:] != IGNORE_INDEX).sum())
    torch.testing.assert_close(module.training_step(batch, 0), (out.loss * n_tok + wrong) / (n_tok + 1))


def _reference(logits, ids, mask):
    """Slow reference: the full log-softmax, one sample at a time."""
    logp = torch.log_softmax(logits.double(), -1)
    losses, ps = [], []
    for b in range(mask.shape[0]):
        pos = mask[b].nonzero()[:, 0]
        if len(pos) == 0:
            continue
        lp = sum(logp[b, t - 1, ids[b, t]] for t in pos.tolist())
        ps.append(float(torch.exp(lp.detach())))
        losses.append(-torch.log1p(-torch.exp(lp)))
    return torch.stack(losses).mean(), float(np.mean(ps))


@pytest.mark.parametrize("scale", [0.1, 1.0, 8.0])
def test_stop_unlikelihood_matches_a_reference_and_stays_finite(scale):
    g = torch.Generator().manual_seed(0)
    logits = (torch.randn(3, 7, 11, generator=g) * scale).requires_grad_()
    ids = torch.randint(0, 11, (3, 7), generator=g)
    mask = torch.zeros(3, 7, dtype=torch.bool)
    mask[0, 5] = True
    mask[2, 3:5] = True  # a two-token STOP piece
    loss, p = stop_unlikelihood(logits, ids, mask)
    ref, ref_p = _reference(logits, ids, mask)
    assert float(loss) == pytest.approx(float(ref), rel=1e-5, abs=1e-6) and float(p) == pytest.approx(
        ref_p, 1e-5
    )
    loss.backward()
    assert torch.isfinite(logits.grad).all() and logits.grad[1].abs().sum() == 0
    assert stop_unlikelihood(logits, ids, None) is None
    assert stop_unlikelihood(logits, ids, torch.zeros_like(mask)) is None
    # P(STOP) -> 1 (the loss would be +inf): capped, gradient finite.
    sure = torch.full((1, 3, 5), -50.0)
    sure[0, 0, 2] = 50.0
    sure.requires_grad_()
    m = torch.zeros(1, 3, dtype=torch.bool)
    m[0, 1] = True
    big, _ = stop_unlikelihood(sure, torch.tensor([[0, 2, 0]]), m)
    big.backward()
    assert torch.isfinite(big) and torch.isfinite(sure.grad).all()


def _p_stop(policy, cfg, sample, instruction) -> float:
    col = NavCollator(
        PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
    )
    batch = col([dataclasses.replace(sample, instruction=instruction, stop_negative=True)])
    policy.model.eval()
    with torch.no_grad():
        from image2sim.navpolicy.collate import model_inputs

        logits = policy.model(**model_inputs(batch)).logits
    return float(stop_unlikelihood(logits, batch["input_ids"], batch["stop_negative_mask"])[1])


@pytest.mark.slow
def test_wrong_goal_samples_make_stop_depend_on_the_instruction(tiny_cfg, tmp_path):
    """The toy task of docs/navpolicy.md: the two goals' trajectory ends differ by the goal's tint, and
    only the instruction says whether this end is the one asked for. Without wrong-goal samples the
    tiny policy stops at any end whatever it is told; with them (1 500 steps: it hedges at P = 0.5
    up to ~800) it stops only where the instruction's goal is."""
    from image2sim.navpolicy.model import build_policy

    trajs = _trajs(8)
    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.batch_size, cfg.train.lr, cfg.train.warmup_steps, cfg.train.checkpoint_every = (
        4,
        3e-3,
        1,
        100_000,
    )
    kw = {"context": (2, 2), "end_cut_probability": 0.5}
    ends = [InMemoryNavDataset(trajs, 4, 8, jitter=False, **kw)[k] for k in (0, 1)]  # a sofa end, a bed end
    result = {}
    for p, steps in ((0.0, 300), (0.3, 1500)):  # the control needs no long run to show it never reads
        cfg.train.max_steps = steps
        policy = build_policy(cfg, seed=0)
        ds = InMemoryNavDataset(trajs, 4, 8, seed=0, wrong_goal_stop_probability=p, **kw)
        train_bc(cfg, tmp_path / f"p{p}", dataset=ds, policy=policy, export=False)
        result[p] = [
            (_p_stop(policy, cfg, end, right), _p_stop(policy, cfg, end, wrong))
            for end, right, wrong in (
                (ends[0], "find the sofa", "find the bed"),
                (ends[1], "find the bed", "find the sofa"),
            )
        ]
    for right, wrong in result[0.0]:
        assert right > 0.8 and wrong > 0.8, result
    for right, wrong in result[0.3]:
        assert right > 0.8 and wrong < 0.2, result
