"""The goal head travels with the policy (export, reload, behaviour cloning) and ``agent.stop_gate``
lets STOP through only where the head says the instruction's goal is in view."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from image2sim.navpolicy.agent import BatchedImage2NavAgent, Image2NavAgent, last_image_position
from image2sim.navpolicy.data import GOAL_IN_VIEW, InMemoryNavDataset, synthetic_trajectories
from image2sim.navpolicy.model import GOAL_HEAD_FILE, GoalHead, base_qwen, build_policy
from image2sim.simulator.conventions import Action


def _with_head(policy, bias: float = 0.0, seed: int = 0):
    pol = copy.copy(policy)
    torch.manual_seed(seed)
    pol.goal_head = GoalHead(int(base_qwen(policy.model).config.text_config.hidden_size))
    with torch.no_grad():
        pol.goal_head.linear.bias.fill_(bias)
    return pol


def _stop_loving(policy):
    """A copy whose language model always prefers STOP (runner-up LEFT)."""
    pol = copy.deepcopy(policy)
    bias = torch.zeros(pol.model.lm_head.out_features)
    for t in {*pol.codec.first[Action.STOP], *pol.codec.following[Action.STOP]}:
        bias[t] = 100.0
    bias[pol.codec.first[Action.TURN_LEFT][0]] = 50.0
    pol.model.lm_head.register_forward_hook(lambda m, i, o: o + bias)
    return pol


def _agent(policy, cfg, gate, reuse=True):
    acfg = copy.deepcopy(cfg.agent)
    acfg.stop_gate, acfg.reuse_cache = gate, reuse
    return Image2NavAgent(policy, acfg, cfg.system_prompt)


def test_goal_head_file_round_trip_and_refusals(tmp_path):
    head = GoalHead(16, layer=-2)
    head.save(tmp_path / "h.safetensors")
    back = GoalHead.load(tmp_path / "h.safetensors")
    assert back.layer == -2
    x = torch.randn(5, 16)
    torch.testing.assert_close(back(x), head(x))
    (tmp_path / "bad.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(Exception, match="bad.safetensors|header|deserial"):
        GoalHead.load(tmp_path / "bad.safetensors")
    from safetensors.torch import save_file

    save_file({"weight": torch.zeros(2, 16), "bias": torch.zeros(2)}, str(tmp_path / "two.safetensors"))
    with pytest.raises(ValueError, match="two.safetensors"):
        GoalHead.load(tmp_path / "two.safetensors")
    with pytest.raises(ValueError, match="negative"):
        GoalHead(16, layer=0)


def test_gate_probability_is_the_head_on_the_newest_images_last_token(tiny_policy, tiny_cfg):
    # Reference: the whole prompt through the model, the head at the last image token by hand. The
    # streaming agent (cached prefix, only new tokens fed) must read the same state.
    pol = _with_head(tiny_policy, seed=1)
    frames = synthetic_trajectories(1, 12, 12, seed=11)[0].frames
    fast, slow = _agent(pol, tiny_cfg, 0.5, reuse=True), _agent(pol, tiny_cfg, 0.5, reuse=False)
    for a in (fast, slow):
        a.reset("find the sofa")
    for f in frames:
        assert fast.act(f) == slow.act(f)
        pf, ps = fast.history[-1].goal_probability, slow.history[-1].goal_probability
        assert pf is not None and abs(pf - ps) < 1e-5
    assert any(h.reused_tokens > 0 for h in fast.history)
    # By hand, for the last step of the slow agent.
    _, enc = slow._context()[0], slow.prompts.encode(slow.instruction, slow._context()[1], True)
    ids, mm = list(enc.input_ids), list(enc.mm_token_type_ids)
    idx = slow._context()[0]
    grids = torch.cat([slow._image(k)[1] for k in idx])
    rope = slow._rope(ids, mm, grids)
    pos = torch.cat([torch.arange(len(ids)).view(1, 1, -1), rope[:, None]], 0)
    with torch.no_grad():
        out = slow.qwen(
            input_ids=torch.tensor([ids]),
            mm_token_type_ids=torch.tensor([mm]),
            position_ids=pos,
            pixel_values=torch.cat([slow._image(k)[0] for k in idx]),
            image_grid_thw=grids,
            output_hidden_states=True,
        )
        j = last_image_position(mm)
        assert mm[j] == 1 and all(t != 1 for t in mm[j + 1 :])
        want = float(torch.sigmoid(pol.goal_head(out.hidden_states[-1][0, j])))
    assert abs(slow.history[-1].goal_probability - want) < 1e-5


@pytest.mark.parametrize(("bias", "stops"), [(100.0, True), (-100.0, False)])
def test_gate_opens_and_closes_stop(tiny_policy, tiny_cfg, bias, stops):
    pol = _with_head(_stop_loving(tiny_policy), bias=bias)
    frames = synthetic_trajectories(1, 3, 3, seed=12)[0].frames
    agent = _agent(pol, tiny_cfg, 0.5)
    agent.reset("find the sofa")
    acts = agent.act(frames[0])
    info = agent.history[-1]
    assert (acts[0] == Action.STOP) is stops and info.stop_allowed is stops
    assert info.goal_probability == pytest.approx(1.0 if stops else 0.0, abs=1e-6)
    if not stops:
        assert acts[0] == Action.TURN_LEFT
    # Without the gate the same policy stops whatever its head says.
    plain = _agent(pol, tiny_cfg, None)
    plain.reset("find the sofa")
    assert plain.act(frames[0])[0] == Action.STOP and plain.history[-1].goal_probability is None


def test_gate_needs_a_head(tiny_policy, tiny_cfg):
    with pytest.raises(ValueError, match="agent.stop_gate.*goal head"):
        _agent(tiny_policy, tiny_cfg, 0.5)
    from image2sim.navpolicy.config import ConfigError, from_dict

    with pytest.raises(ConfigError, match="agent.stop_gate"):
        from_dict({"agent": {"stop_gate": 1.5}})


def test_batched_gate_equals_independent_agents(tiny_policy, tiny_cfg):
    # Rows padded differently (episodes of different lengths, one sitting out): each row's head reads
    # its own newest image, and the gate decides per row as the single agent's does.
    pol = _with_head(_stop_loving(tiny_policy), seed=2)
    trajs = synthetic_trajectories(3, 6, 10, seed=13)
    instructions = ["find the sofa", "go to the bed in the room on the left", "x"]
    # A gate in the middle of the head's outputs, so that it opens for some steps and not others.
    probe = _agent(pol, tiny_cfg, 0.0)
    probe.reset(instructions[0])
    ps = [probe.act(f) and probe.history[-1].goal_probability for f in trajs[0].frames]
    gate = float(np.median(ps))
    acfg = copy.deepcopy(tiny_cfg.agent)
    acfg.stop_gate = gate
    batched = BatchedImage2NavAgent(pol, acfg, tiny_cfg.system_prompt, 3)
    singles = [Image2NavAgent(pol, acfg, tiny_cfg.system_prompt) for _ in range(3)]
    for i in range(3):
        batched.reset(i, instructions[i])
        singles[i].reset(instructions[i])
    allowed = set()
    for t in range(10):
        obs = [
            tr.frames[t] if t < len(tr.frames) and not (i == 1 and t % 4 == 2) else None
            for i, tr in enumerate(trajs)
        ]
        got = batched.act(obs)
        for i in range(3):
            if obs[i] is None:
                continue
            want = singles[i].act(obs[i])
            hb, hs = batched.agents[i].history[-1], singles[i].history[-1]
            assert got[i] == want and hb.stop_allowed == hs.stop_allowed
            assert abs(hb.goal_probability - hs.goal_probability) < 1e-5
            allowed.add(hs.stop_allowed)
    assert allowed == {True, False}  # the gate did both
    with pytest.raises(ValueError, match="allow_stop"):
        batched.act([None] * 3, allow_stop=[True])


def _labelled(trajs):
    for t in trajs:
        t.extra = {GOAL_IN_VIEW: [int(t.actions[s] == int(Action.MOVE_FORWARD)) for s in t.frame_steps]}
    return trajs


def test_head_is_exported_reloaded_and_trained_on(tiny_cfg, tmp_path):
    from image2sim.navpolicy.train import NavBCModule, train_bc

    trajs = _labelled(synthetic_trajectories(6, min_len=6, max_len=12, seed=14))
    cfg = copy.deepcopy(tiny_cfg)
    cfg.train.goal_aux_weight = 1.0
    cfg.train.max_steps, cfg.train.batch_size, cfg.train.warmup_steps = 4, 2, 1
    cfg.train.checkpoint_every = 100
    cfg.data.max_observations, cfg.data.max_action_labels = 4, 8
    data = InMemoryNavDataset(trajs, 4, 8)
    res = train_bc(cfg, tmp_path / "a", dataset=data, policy=build_policy(cfg, seed=0), export=True)
    assert (res.export_dir / GOAL_HEAD_FILE).is_file()
    assert "goal_head.safetensors" in (res.export_dir / "README.md").read_text()  # the card says so
    trained = res.module.goal_head
    cfg2 = copy.deepcopy(cfg)
    cfg2.model.source = str(res.export_dir)
    reloaded = build_policy(cfg2)
    x = torch.randn(3, trained.linear.in_features)
    torch.testing.assert_close(reloaded.goal_head(x), trained(x))
    # Behaviour cloning from the export trains that head on (warm start), not a new one.
    module = NavBCModule(reloaded, cfg2)
    assert module.goal_head is reloaded.goal_head
    cfg2.train.goal_aux_layer = -2
    with pytest.raises(ValueError, match="goal_aux_layer"):
        NavBCModule(build_policy(cfg2), cfg2)
    # Without the grounding loss the head would not follow the model: it is dropped from the export.
    cfg3 = copy.deepcopy(cfg2)
    cfg3.train.goal_aux_weight, cfg3.train.goal_aux_layer = 0.0, -1
    res3 = train_bc(cfg3, tmp_path / "b", dataset=data, policy=build_policy(cfg3), export=True)
    assert not (res3.export_dir / GOAL_HEAD_FILE).exists()
    assert "goal_head.safetensors" not in (res3.export_dir / "README.md").read_text()


def test_near_end_labels_count_the_forward_moves_left():
    from image2sim.navpolicy.data import Trajectory, frame_goal_labels, make_sample

    F, L, S = int(Action.MOVE_FORWARD), int(Action.TURN_LEFT), int(Action.STOP)
    actions = [F, F, L, F, F, F, L, L, F, S]  # forward moves left from step t: 6 5 4 4 3 2 1 1 1 0
    frames = np.zeros((5, 8, 8, 3), np.uint8)
    traj = Trajectory(
        "find the sofa", actions, frames, [0, 2, 4, 6, 9], extra={GOAL_IN_VIEW: [0, 0, 1, 1, 0]}
    )
    assert frame_goal_labels(traj, "near_end", 3) == [0, 0, 1, 1, 1]
    assert frame_goal_labels(traj, "near_end", 0) == [0, 0, 0, 0, 1]
    assert frame_goal_labels(traj, "in_view") == [0, 0, 1, 1, 0]
    unfinished = Trajectory("x", actions[:-1], frames[:4], [0, 2, 4, 6])
    assert (
        frame_goal_labels(unfinished, "near_end") is None and frame_goal_labels(unfinished, "in_view") is None
    )
    with pytest.raises(ValueError, match="goal label"):
        frame_goal_labels(traj, "nearby")
    sample = make_sample(traj, 5, 10, None, goal_label="near_end", near_end_forward_steps=3)
    assert sample.goal_in_view == [0, 0, 1, 1, 1]


def test_goal_label_reaches_the_dataset_and_is_validated(tiny_cfg):
    from image2sim.navpolicy.config import ConfigError, from_dict
    from image2sim.navpolicy.data import sample_options

    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.goal_label, cfg.data.near_end_forward_steps = "near_end", 4
    trajs = synthetic_trajectories(3, min_len=8, max_len=12, seed=15)  # they end in STOP, no in-view labels
    data = InMemoryNavDataset(trajs, **(sample_options(cfg) | {"jitter": False}))
    from image2sim.navpolicy.data import frame_goal_labels

    for i, t in enumerate(trajs):
        labels = dict(zip(t.frame_steps, frame_goal_labels(t, "near_end", 4), strict=True))
        s = data[i]
        assert s.goal_in_view == [labels[k] for k in s.steps] and s.goal_in_view[-1] == 1
    with pytest.raises(ConfigError, match="data.goal_label"):
        from_dict({"data": {"goal_label": "nearby"}})
    with pytest.raises(ConfigError, match="near_end_forward_steps"):
        from_dict({"data": {"near_end_forward_steps": -1}})
