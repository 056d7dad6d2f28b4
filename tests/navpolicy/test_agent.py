"""Streaming agent: KV-cache reuse equals full recomputation; context selection; parsing fallback."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from image2sim.navpolicy.agent import Image2NavAgent, select_context_frames
from image2sim.navpolicy.data import synthetic_trajectories
from image2sim.simulator.conventions import Action


@given(n=st.integers(0, 400), sparse=st.integers(0, 30), dense=st.integers(1, 10))
def test_select_context_frames(n, sparse, dense):
    idx = select_context_frames(n, sparse, dense)
    assert idx == sorted(set(idx)) and all(0 <= i < n for i in idx)
    if n <= sparse + dense:
        assert idx == list(range(n))
        return
    assert idx[-dense:] == list(range(n - dense, n))  # the dense window is complete
    hist = idx[:-dense]
    assert len(hist) <= sparse
    if sparse:
        assert hist[0] == 0
        steps = np.diff(hist + [n - dense])
        # Uniform grid: one stride (the last gap may be shorter), and not more than twice too sparse.
        stride = steps[0] if len(steps) else 1
        assert all(s == stride for s in steps[:-1]) and steps[-1] <= stride
        assert len(hist) * 2 > min(sparse, n - dense) or stride == 1


def _run_episode(policy, cfg, frames, reuse: bool, constrained: bool = True):
    acfg = copy.deepcopy(cfg.agent)
    acfg.reuse_cache, acfg.constrained = reuse, constrained
    agent = Image2NavAgent(policy, acfg, cfg.system_prompt)
    agent.reset("walk to the white wall and stop", seed=0)
    actions = [agent.act(f) for f in frames]
    return actions, agent


def test_streaming_equals_recomputation_over_60_steps(tiny_policy, tiny_cfg):
    frames = synthetic_trajectories(1, 60, 60, seed=3)[0].frames
    assert len(frames) == 60
    fast, a1 = _run_episode(tiny_policy, tiny_cfg, frames, reuse=True)
    slow, a2 = _run_episode(tiny_policy, tiny_cfg, frames, reuse=False)
    assert fast == slow
    assert all(len(a) == 2 and all(isinstance(x, Action) for x in a) for a in fast)
    for h1, h2 in zip(a1.history, a2.history, strict=True):
        assert h1.generated_ids == h2.generated_ids and h1.context_tokens == h2.context_tokens
        for l1, l2 in zip(h1.step_logits, h2.step_logits, strict=True):
            torch.testing.assert_close(l1, l2, rtol=1e-4, atol=1e-4)
    # The cache was really reused: everything while the context only grows, the prefix afterwards.
    reused = [h.reused_tokens for h in a1.history]
    assert reused[0] == 0 and all(r > 0 for r in reused[1:])
    assert all(h.reused_tokens == 0 for h in a2.history)
    growing = tiny_cfg.agent.sparse_frames + tiny_cfg.agent.dense_frames
    for k in range(1, growing):
        prev = a1.history[k - 1]
        # Previous context + the two generated action tokens were cached (minus the last, never fed).
        assert reused[k] >= prev.context_tokens + 1
    assert sum(reused) > 0.5 * sum(h.context_tokens for h in a1.history)


def test_context_matches_training_layout(tiny_policy, tiny_cfg):
    frames = synthetic_trajectories(1, 12, 12, seed=4)[0].frames
    _, agent = _run_episode(tiny_policy, tiny_cfg, frames[:3], reuse=True)
    idx, turns = agent._context()
    assert idx == [0, 1, 2]
    assert turns[0].executed == () and turns[1].executed == agent.replies[0][: len(turns[1].executed)]
    assert turns[0].target == agent.replies[0] and turns[-1].target is None


def test_unconstrained_decoding_falls_back_when_unparsable(tiny_policy, tiny_cfg):
    frames = synthetic_trajectories(1, 5, 5, seed=6)[0].frames
    pol = copy.deepcopy(tiny_policy)
    # Make the model always emit a non-action token ("a") by biasing the LM head's output.
    a_id = pol.tokenizer("a", add_special_tokens=False)["input_ids"][0]
    bias = torch.zeros(pol.model.lm_head.out_features)
    bias[a_id] = 100.0
    pol.model.lm_head.register_forward_hook(lambda m, i, o: o + bias)
    acts, agent = _run_episode(pol, tiny_cfg, frames, reuse=True, constrained=False)
    fb = Action(tiny_cfg.agent.fallback_action)
    assert acts == [[fb, fb]] * len(frames)
    assert all(h.fallback for h in agent.history)
    assert len(agent.history[0].generated_ids) == tiny_cfg.agent.max_new_tokens
    # Constrained decoding on the same model still yields valid actions (never a fallback).
    acts_c, agent_c = _run_episode(pol, tiny_cfg, frames, reuse=True, constrained=True)
    assert not any(h.fallback for h in agent_c.history)


def test_unconstrained_parses_emitted_actions(tiny_policy, tiny_cfg):
    frames = synthetic_trajectories(1, 4, 4, seed=7)[0].frames
    pol = copy.deepcopy(tiny_policy)
    codec = pol.codec
    im_end = pol.tokenizer.convert_tokens_to_ids("<|im_end|>")
    seq = [codec.first[Action.TURN_LEFT][0], codec.following[Action.MOVE_FORWARD][0], im_end]
    state = {"i": 0}

    def force(module, inputs, out):
        # Emit LEFT, FORWARD, <|im_end|> in turn, whatever the context (prefill starts a new reply).
        bias = torch.zeros_like(out)
        bias[..., seq[state["i"] % 3]] = 100.0
        state["i"] += 1
        return out + bias

    pol.model.lm_head.register_forward_hook(force)
    acts, agent = _run_episode(pol, tiny_cfg, frames, reuse=True, constrained=False)
    assert acts == [[Action.TURN_LEFT, Action.MOVE_FORWARD]] * len(frames)
    assert not any(h.fallback for h in agent.history)


@pytest.mark.parametrize("executed", [None, [1, 1, 2]])
def test_executed_actions_reach_the_prompt(tiny_policy, tiny_cfg, executed):
    frames = synthetic_trajectories(1, 3, 3, seed=8)[0].frames
    agent = Image2NavAgent(tiny_policy, tiny_cfg.agent, tiny_cfg.system_prompt)
    agent.reset("x")
    first = agent.act(frames[0])
    agent.act(frames[1], executed=executed)
    want = tuple(int(a) for a in (executed if executed is not None else first))
    if executed is None and Action.STOP in first:
        want = want[: want.index(int(Action.STOP)) + 1]
    assert agent.executed[1] == want
    _, turns = agent._context()
    assert turns[1].executed == want


def test_batched_agents_equal_independent_agents(tiny_policy, tiny_cfg):
    from image2sim.navpolicy.agent import BatchedImage2NavAgent

    trajs = synthetic_trajectories(3, 8, 16, seed=5)
    instructions = ["go left", "find the white wall and stop there, please", "x"]
    batched = BatchedImage2NavAgent(tiny_policy, tiny_cfg.agent, tiny_cfg.system_prompt, 3)
    singles = [Image2NavAgent(tiny_policy, tiny_cfg.agent, tiny_cfg.system_prompt) for _ in range(3)]
    for i in range(3):
        batched.reset(i, instructions[i])
        singles[i].reset(instructions[i])
    all_actions = set()
    for t in range(16):
        # Episodes of different lengths; agent 1 sits out some steps: rows are padded differently.
        obs = [
            tr.frames[t] if t < len(tr.frames) and not (i == 1 and t % 5 == 3) else None
            for i, tr in enumerate(trajs)
        ]
        got = batched.act(obs)
        for i in range(3):
            if obs[i] is None:
                assert got[i] is None
                continue
            assert got[i] == singles[i].act(obs[i])
            all_actions.add(tuple(got[i]))
            for a, b in zip(
                batched.agents[i].history[-1].step_logits, singles[i].history[-1].step_logits, strict=True
            ):
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    assert len(all_actions) > 1  # the comparison is not between constant outputs
    with pytest.raises(ValueError, match="expected 3 observations"):
        batched.act([None])


def test_stop_can_be_withheld(tiny_policy, tiny_cfg):
    # A policy biased to say STOP: with allow_stop=False it returns its best other action instead.
    frames = synthetic_trajectories(1, 3, 3, seed=9)[0].frames
    pol = copy.deepcopy(tiny_policy)
    bias = torch.zeros(pol.model.lm_head.out_features)
    for t in {*pol.codec.first[Action.STOP], *pol.codec.following[Action.STOP]}:
        bias[t] = 100.0
    bias[pol.codec.first[Action.TURN_LEFT][0]] = 50.0  # the runner-up once STOP is out
    pol.model.lm_head.register_forward_hook(lambda m, i, o: o + bias)
    agent = Image2NavAgent(pol, tiny_cfg.agent, tiny_cfg.system_prompt)
    agent.reset("find the sofa")
    assert agent.act(frames[0])[0] == Action.STOP
    agent.reset("find the sofa")
    for f in frames:
        acts = agent.act(f, allow_stop=False)
        assert Action.STOP not in acts and acts[0] == Action.TURN_LEFT


def test_unconstrained_stop_withheld_falls_back(tiny_policy, tiny_cfg):
    frames = synthetic_trajectories(1, 2, 2, seed=9)[0].frames
    pol = copy.deepcopy(tiny_policy)
    im_end = pol.tokenizer.convert_tokens_to_ids("<|im_end|>")
    seq = [pol.codec.first[Action.STOP][0], pol.codec.following[Action.MOVE_FORWARD][0], im_end]
    state = {"i": 0}

    def force(module, inputs, out):  # emit "STOP FORWARD" then end, whatever the context
        bias = torch.zeros_like(out)
        bias[..., seq[state["i"] % 3]] = 100.0
        state["i"] += 1
        return out + bias

    pol.model.lm_head.register_forward_hook(force)
    acfg = copy.deepcopy(tiny_cfg.agent)
    acfg.constrained = False
    agent = Image2NavAgent(pol, acfg, tiny_cfg.system_prompt)
    agent.reset("find the sofa")
    assert agent.act(frames[0]) == [Action.STOP, Action.MOVE_FORWARD] and not agent.history[-1].fallback
    assert agent.act(frames[1], allow_stop=False) == [Action(acfg.fallback_action), Action.MOVE_FORWARD]
    assert agent.history[-1].fallback
