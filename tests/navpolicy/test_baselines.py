"""Baselines behind the runner's agent interface: one implementation each, forward-then-turn
behaviour, and ``nav act`` (one episode -> top-down PNG + frames) through the evaluation runner."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from image2sim.simulator.conventions import Action

F, L, R, S = (int(Action.MOVE_FORWARD), int(Action.TURN_LEFT), int(Action.TURN_RIGHT), int(Action.STOP))


def _obs(collided: bool) -> SimpleNamespace:
    return SimpleNamespace(collided=collided, rgb=None)


def test_one_implementation_per_baseline():
    import image2sim.eval.runner as runner
    from image2sim.navpolicy import baselines

    # random / forward / oracle are the runner's classes, not copies.
    assert baselines.RandomAgent is runner.RandomAgent
    assert baselines.ForwardAgent is runner.ForwardAgent
    assert baselines.OracleAgent is runner.OracleAgent
    assert type(baselines.make_baseline("random")) is runner.RandomAgent
    # forward_turn lives in navpolicy; the runner's registry builds navpolicy's class.
    agent = runner.make_agent(runner.AgentSpec("forward_turn", {"min_turns": 3, "max_turns": 3}))
    assert type(agent) is baselines.ForwardTurnAgent and agent.min_turns == 3
    with pytest.raises(ValueError, match="unknown baseline"):
        baselines.make_baseline("teleport")


def test_forward_until_collision_then_turn():
    from image2sim.navpolicy.baselines import ForwardTurnAgent

    agent = ForwardTurnAgent(min_turns=2, max_turns=5)
    agent.reset(None, None, seed=3)
    seq = [agent.act(_obs(False)) for _ in range(4)]
    assert seq == [F] * 4
    first = agent.act(_obs(True))  # the last forward step collided
    assert first in (L, R)
    turns = [first]
    while True:
        a = agent.act(_obs(False))
        if a == F:
            break
        turns.append(a)
    assert 2 <= len(turns) <= 5 and set(turns) == {first}  # one direction per collision
    assert agent.act(_obs(False)) == F
    # Same seed -> same episode; over many collisions both directions and all counts occur.
    dirs, counts = set(), set()
    for seed in range(40):
        agent.reset(None, None, seed)
        t = [agent.act(_obs(True))] + [agent.act(_obs(False)) for _ in range(6)]
        k = t.index(F)
        dirs.add(t[0])
        counts.add(k)
    assert dirs == {L, R} and counts == {2, 3, 4, 5}


def test_forward_turn_stop_after_and_validation():
    from image2sim.navpolicy.baselines import ForwardTurnAgent

    agent = ForwardTurnAgent(stop_after=3)
    agent.reset(None, None, 0)
    assert [agent.act(_obs(False)) for _ in range(5)] == [F, F, F, S, S]
    with pytest.raises(ValueError, match="min_turns"):
        ForwardTurnAgent(min_turns=4, max_turns=2)
    with pytest.raises(ValueError, match="stop_after"):
        ForwardTurnAgent(stop_after=-1)


@pytest.fixture(scope="module")
def act_runs(tmp_path_factory):
    """``nav act`` for the oracle and forward_turn on the same episode (one scene build each)."""
    from image2sim.navpolicy.act import run_act
    from image2sim.navpolicy.config import tiny_config

    root = tmp_path_factory.mktemp("act")
    cfg = tiny_config()
    return root, {
        name: run_act(cfg, name, root / name, scene_seed=0, episode_index=1, max_steps=60)
        for name in ("oracle", "forward_turn")
    }


def test_nav_act_writes_topdown_png_frames_and_metrics(act_runs):
    from PIL import Image

    root, runs = act_runs
    oracle, fwd = runs["oracle"], runs["forward_turn"]
    assert oracle["episode_id"] == fwd["episode_id"]
    assert oracle["metrics"]["success"] == 1.0 and oracle["actions"][-1] == S
    assert fwd["metrics"]["success"] == 0.0 and S not in fwd["actions"]  # never stops on its own
    assert len(fwd["actions"]) == 60
    for name, rec in runs.items():
        png = Image.open(rec["topdown"])
        assert png.size[0] > 100 and png.size[1] > 100
        frames = sorted((root / name / "frames").glob("*.png"))
        assert len(frames) == rec["frames"]
        # one frame per visited state: the start plus every action that was stepped (not STOP)
        assert rec["frames"] == 1 + sum(a != S for a in rec["actions"])
        assert np.asarray(Image.open(frames[0])).shape == (64, 64, 3)
        assert json.loads((root / name / "episode.json").read_text())["actions"] == rec["actions"]
        # the strip: min(8, frames) tiles of 128 px (64 px frames scaled 2x) with 4 px gaps,
        # the first tile equal to the first frame
        strip = np.asarray(Image.open(rec["strip"]))
        k = min(8, rec["frames"])
        assert strip.shape == (128, k * 128 + (k - 1) * 4, 3)
        np.testing.assert_array_equal(strip[::2, :128:2], np.asarray(Image.open(frames[0])))


def test_forward_turn_turns_after_every_collision_in_the_simulator(act_runs):
    # collided[i]: action i hit an obstacle (reported by the runner's backend in the observation).
    _, runs = act_runs
    acts, col = runs["forward_turn"]["actions"], runs["forward_turn"]["collided"]
    assert len(col) == len(acts) and any(col), "a 60-step walk in 2 m rooms must hit a wall"
    for i in range(1, len(acts)):
        turn_starts = acts[i] in (L, R) and acts[i - 1] == F
        assert turn_starts == (acts[i - 1] == F and col[i - 1]), f"step {i}"
    # Turns never collide; only forward steps do.
    assert all(acts[i] == F for i in range(len(acts)) if col[i])


def test_compare_counts_an_unreachable_end_as_a_named_failure(tiny_cfg, monkeypatch):
    """An episode the runner refuses because the agent ended where the goal is unreachable on the
    graph is a failure (success 0, SPL 0) that the summary names, not a crash and not a drop."""
    import image2sim.eval.runner as runner
    from image2sim.navpolicy.act import compare_agents

    real = runner.run_episode

    def flaky(backend, agent, ep, proto, seed, poses=None):
        res = real(backend, agent, ep, proto, seed, poses)
        if ep.episode_id.endswith("0001"):
            raise runner.RunnerError(
                f"episode {ep.episode_id}: the agent ends at world position [0, 0, 0] ..."
            )
        return res

    clean = compare_agents(tiny_cfg, ["oracle"], [1000], episodes_per_scene=3, max_steps=150)["oracle"]
    assert clean["sr"] == 1.0 and "unreachable_end_episodes" not in clean
    monkeypatch.setattr(runner, "run_episode", flaky)
    s = compare_agents(tiny_cfg, ["oracle"], [1000], episodes_per_scene=3, max_steps=150)["oracle"]
    assert s["unreachable_end_episodes"] == ["procedural-tiny-1000-0001"]
    assert s["n_episodes"] == 3 and s["sr"] == pytest.approx(2 / 3) and s["ne_off_graph_episodes"] == 1
    assert 0 < s["spl"] < clean["spl"]

    def broken(*a, **kw):
        raise runner.RunnerError("episode x: agent returned action 9")

    monkeypatch.setattr(runner, "run_episode", broken)
    with pytest.raises(runner.RunnerError, match="action 9"):
        compare_agents(tiny_cfg, ["oracle"], [1000], episodes_per_scene=1, max_steps=10)
