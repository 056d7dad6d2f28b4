"""Online DAgger: chunk mixing statistics, schedules, oracle labels at visited states, truncation,
and a tiny end-to-end round on a procedural scene that adds samples and trains on them."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from image2sim.navpolicy.config import ConfigError, DaggerConfig, load_config
from image2sim.navpolicy.dagger import (
    MODEL,
    ORACLE,
    ChunkMixer,
    OracleLabeler,
    dagger_rollout,
    mixing_probability,
    run_dagger,
)
from image2sim.navpolicy.data import ShardReader, make_sample
from image2sim.navpolicy.rollout_scenes import NavTask, goal_instruction, sample_tasks
from image2sim.simulator.conventions import Action

# ------------------------------------------------------------------------------------------ mixing


@pytest.mark.parametrize("p, lo, hi", [(0.3, 4, 32), (0.8, 4, 32), (0.5, 2, 5)])
def test_mixing_statistics_match_the_config(p, lo, hi):
    from scipy.stats import chisquare

    mixer = ChunkMixer(p, lo, hi, np.random.default_rng(123))
    steps = [mixer.next() for _ in range(120_000)]
    chunks = mixer.chunks[:-1]  # the last chunk may be cut by the step budget
    n = len(chunks)
    lengths = np.array([c[1] for c in chunks])
    model = np.array([c[0] == MODEL for c in chunks])
    # Controller per chunk: Bernoulli(p) (4 standard errors).
    assert abs(model.mean() - p) < 4 * math.sqrt(p * (1 - p) / n)
    # Lengths: exactly the integers lo..hi, uniform (chi-square goodness of fit).
    assert lengths.min() == lo and lengths.max() == hi
    counts = np.bincount(lengths - lo, minlength=hi - lo + 1)
    assert chisquare(counts).pvalue > 1e-3
    # Fraction of model-controlled *steps*: lengths are independent of the controller, so it is p too.
    frac = np.mean([s == MODEL for s in steps])
    assert abs(frac - p) < 0.02
    # The per-step sequence is the chunks laid end to end.
    rebuilt = [who for who, k in mixer.chunks for _ in range(k)][: len(steps)]
    assert rebuilt == steps


def test_mixing_extremes_and_bad_arguments():
    rng = np.random.default_rng(0)
    assert {ChunkMixer(0.0, 4, 32, rng).next() for _ in range(500)} == {ORACLE}
    assert {ChunkMixer(1.0, 4, 32, rng).next() for _ in range(500)} == {MODEL}
    with pytest.raises(ValueError, match="chunk range"):
        ChunkMixer(0.5, 5, 4, rng)
    with pytest.raises(ValueError, match="probability"):
        ChunkMixer(1.5, 4, 32, rng)


def test_mixing_schedules():
    c = DaggerConfig(rounds=5, model_probability=0.2, final_model_probability=0.8, schedule="linear")
    assert [round(mixing_probability(c, r), 6) for r in range(5)] == [0.2, 0.35, 0.5, 0.65, 0.8]
    c.schedule = "exponential"
    vals = [mixing_probability(c, r) for r in range(5)]
    assert vals[0] == pytest.approx(0.2) and vals[-1] == pytest.approx(0.8)
    ratios = np.array(vals[1:]) / np.array(vals[:-1])
    assert np.allclose(ratios, ratios[0])  # geometric
    c.schedule = "constant"
    assert {mixing_probability(c, r) for r in range(5)} == {0.2}
    one = DaggerConfig(rounds=1, model_probability=0.3)
    assert mixing_probability(one, 0) == 0.3


def test_dagger_config_is_validated():
    cfg = load_config("tiny", {"dagger": {"chunk_min": 4, "chunk_max": 32, "model_probability": 0.25}})
    assert (cfg.dagger.chunk_min, cfg.dagger.chunk_max, cfg.dagger.model_probability) == (4, 32, 0.25)
    with pytest.raises(ConfigError, match="chunk_min"):
        load_config("tiny", {"dagger": {"chunk_min": 10, "chunk_max": 4}})
    with pytest.raises(ConfigError, match="model_probability"):
        load_config("tiny", {"dagger": {"model_probability": -0.1}})
    with pytest.raises(ConfigError, match="schedule"):
        load_config("tiny", {"dagger": {"schedule": "cosine"}})
    with pytest.raises(ConfigError, match="dagger.bogus"):
        load_config("tiny", {"dagger": {"bogus": 1}})
    assert load_config("tiny").dagger.lr is None  # rounds train at train.lr
    with pytest.raises(ConfigError, match="dagger.lr"):
        load_config("tiny", {"dagger": {"lr": 0.0}})


def test_goal_instruction_is_egocentric():
    s = np.zeros(3)
    # Facing +Y (heading 90 deg): a goal at +Y is ahead, a goal at +X is to the right.
    assert goal_instruction(s, math.pi / 2, np.array([0.0, 2.0, 0.0])) == (
        "Go to the point 2.0 m ahead and 0.0 m to the left, then stop."
    )
    assert "1.5 m to the right" in goal_instruction(s, math.pi / 2, np.array([1.5, 0.0, 0.0]))
    assert "behind you" in goal_instruction(s, 0.0, np.array([-1.0, 0.0, 0.0]))


# --------------------------------------------------------------------------------- scene rollouts


@pytest.fixture(scope="module")
def scene():
    from image2sim.navpolicy.rollout_scenes import procedural_simulator

    sim = procedural_simulator(0, "tiny")
    tasks = sample_tasks(sim, 4, np.random.default_rng(0), 1.2, "tiny-000")
    return sim, tasks


class RandomController:
    """A stand-in policy: two random actions (never STOP) per call; records its calls."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.calls: list[tuple[tuple, list | None]] = []

    def reset(self, instruction: str, seed: int = 0) -> None:
        self.calls = []

    def act(self, rgb, executed=None):
        out = [int(a) for a in self.rng.choice([1, 1, 2, 3], size=2)]
        self.calls.append((rgb.shape, None if executed is None else list(executed)))
        return out


def _reference_oracle(sim, state, goal):
    """The planner's action at ``state``: a brand-new follower planned from there (slow, obvious)."""
    from image2sim.simulator.navigation.agent import Kinematics
    from image2sim.simulator.navigation.follower import OracleFollower

    f = OracleFollower(sim.planner, sim.embodiment, None, Kinematics(sim.world, sim.embodiment))
    f.reset(np.array(state.position), np.asarray(goal, float))
    return int(f.act(state))


def test_oracle_labels_are_the_planners_actions_at_visited_states(scene, tiny_cfg):
    from image2sim.dataengine.rollout import replay
    from image2sim.simulator.navigation.agent import AgentState, Kinematics

    sim, tasks = scene
    task = tasks[0]
    ctrl = RandomController(1)
    mixer = ChunkMixer(0.5, 4, 8, np.random.default_rng(5))
    ep = dagger_rollout(sim, task, ctrl, mixer, tiny_cfg.observation, max_steps=40, stop_on_stuck=False)
    T = len(ep.trajectory.actions)
    assert T >= 8 and len(ep.labels) == T and ep.trajectory.frames.shape == (T, 64, 64, 3)
    assert {MODEL, ORACLE} <= set(ep.controllers)  # both drove
    kin = Kinematics(sim.world, sim.embodiment)
    for t in range(T):
        state = AgentState(ep.positions[t].copy(), float(ep.headings[t]))
        first, second = ep.labels[t]
        assert first == _reference_oracle(sim, state, task.goal)
        nxt, _, _ = kin.apply(state, first)
        assert second == (
            int(Action.STOP) if first == int(Action.STOP) else _reference_oracle(sim, nxt, task.goal)
        )
        if ep.controllers[t] == ORACLE:
            assert ep.trajectory.actions[t] == first  # the oracle executes its own label
    # The recorded states are the ones the executed actions visit (replay in a fresh episode).
    pos, _, _ = replay(sim, task.start, task.heading, ep.trajectory.actions)
    np.testing.assert_allclose(pos, ep.positions, atol=1e-9)
    # The controller was called only in model chunks and told everything executed since its last look.
    assert len(ctrl.calls) >= 1 and ctrl.calls[0][1] is None
    total_told = sum(len(c[1]) for c in ctrl.calls[1:])
    first_call = ep.controllers.index(MODEL)
    assert total_told <= T - first_call
    # Stored labels become the sample's targets; the executed actions its history.
    s = make_sample(ep.trajectory, 32, 64)
    assert s.targets == [tuple(ep.labels[k]) for k in s.steps]
    for j in range(1, len(s.steps)):
        assert list(s.executed[j]) == ep.trajectory.actions[s.steps[j - 1] : s.steps[j]]


def test_oracle_only_rollout_reaches_the_goal(scene, tiny_cfg):
    sim, tasks = scene
    for task in tasks[:2]:
        ep = dagger_rollout(
            sim, task, None, ChunkMixer(0.0, 4, 32, np.random.default_rng(0)), tiny_cfg.observation
        )
        assert ep.end == "stop" and set(ep.controllers) == {ORACLE}
        assert ep.distance_to_goal < 0.5
        assert ep.trajectory.actions == [lab[0] for lab in ep.labels]


def _magenta(frames: np.ndarray) -> np.ndarray:
    """Per frame: does it hold goal-marker pixels (saturated red + blue, no green)?"""
    f = frames.astype(np.int32)
    return ((f[..., 0] > 100) & (f[..., 2] > 100) & (f[..., 1] < 20)).any(axis=(1, 2))


def test_goal_marker_is_seen_on_the_way_and_named_in_the_instruction(scene, tiny_cfg):
    """With ``task.goal_marker`` the rollout's frames show the pillar (the oracle turns towards it)
    while the same scene without the marker has no such pixels; the runner's backend places it at
    the evaluation episode's goal."""
    from image2sim.eval.runner import NeuralSimBackend, embodiment_for
    from image2sim.navpolicy.act import act_protocol, task_episodes
    from image2sim.navpolicy.rollout_scenes import procedural_scenes
    from image2sim.simulator.markers import GoalMarker

    assert goal_instruction(np.zeros(3), 0.0, np.array([2.0, 0.0, 0.0]), "magenta pillar") == (
        "Go to the magenta pillar 2.0 m ahead and 0.0 m to the left, then stop next to it."
    )
    (marked,) = procedural_scenes(1, 2, seed=0, min_distance=1.2, goal_marker=GoalMarker())
    plain_sim, plain_tasks = scene
    assert all("magenta pillar" in t.instruction for t in marked.tasks)
    mixer = ChunkMixer(0.0, 4, 32, np.random.default_rng(0))
    ep = dagger_rollout(marked.sim, marked.tasks[0], None, mixer, tiny_cfg.observation)
    seen = _magenta(ep.trajectory.frames)
    assert ep.end == "stop" and seen.mean() > 0.5
    mixer = ChunkMixer(0.0, 4, 32, np.random.default_rng(0))
    plain = dagger_rollout(plain_sim, plain_tasks[0], None, mixer, tiny_cfg.observation)
    assert not _magenta(plain.trajectory.frames).any()

    proto = act_protocol(tiny_cfg, 50, 0.5)
    backend = NeuralSimBackend(marked.sim, proto, "marked")
    assert embodiment_for(proto) is not None
    (episode,) = task_episodes(marked.sim, 1, 0, "marked", marker_name="magenta pillar")
    backend.reset(episode, observe=True)
    np.testing.assert_allclose(marked.sim.render_fn.goal, episode.goal_position)


class _StuckAfter:
    """Proxy simulator whose stuck detector 'fires' after ``k`` steps."""

    def __init__(self, sim, k: int) -> None:
        self.sim, self.k, self.n = sim, k, 0

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def reset(self, *a, **kw):
        self.n = 0
        return self.sim.reset(*a, **kw)

    def step(self, actions, observe=True):
        obs, info = self.sim.step(actions, observe)
        self.n += 1
        info = dict(info, stuck=np.array([self.n >= self.k]))
        return obs, info


def test_stuck_and_step_cap_truncate_and_are_logged(scene, tiny_cfg):
    sim, tasks = scene
    ctrl = RandomController(2)
    ep = dagger_rollout(
        _StuckAfter(sim, 6),
        tasks[1],
        ctrl,
        ChunkMixer(1.0, 4, 32, np.random.default_rng(0)),
        tiny_cfg.observation,
    )
    assert ep.end == "stuck" and len(ep.trajectory.actions) == 6 and ep.log()["truncated"]
    ep2 = dagger_rollout(
        sim,
        tasks[1],
        ctrl,
        ChunkMixer(1.0, 4, 32, np.random.default_rng(0)),
        tiny_cfg.observation,
        max_steps=5,
    )
    assert ep2.end == "max_steps" and len(ep2.trajectory.actions) == 5
    assert ep2.log()["model_steps"] == 5
    # Not stopping on stuck: the proxy's flag is ignored.
    ep3 = dagger_rollout(
        _StuckAfter(sim, 2),
        tasks[1],
        ctrl,
        ChunkMixer(1.0, 4, 32, np.random.default_rng(0)),
        tiny_cfg.observation,
        max_steps=5,
        stop_on_stuck=False,
    )
    assert ep3.end == "max_steps"


def test_model_stop_override(scene, tiny_cfg):
    sim, tasks = scene

    class Stopper(RandomController):
        def act(self, rgb, executed=None):
            return [int(Action.STOP), int(Action.STOP)]

    mixer = ChunkMixer(1.0, 4, 32, np.random.default_rng(0))
    ep = dagger_rollout(sim, tasks[0], Stopper(), mixer, tiny_cfg.observation)
    assert ep.end == "stop" and len(ep.trajectory.actions) == 1  # faithful: a model STOP ends it
    mixer = ChunkMixer(1.0, 4, 32, np.random.default_rng(0))
    ep = dagger_rollout(sim, tasks[0], Stopper(), mixer, tiny_cfg.observation, override_model_stop=True)
    assert ep.end == "stop" and ep.distance_to_goal < 0.5  # the oracle's actions were executed
    assert ep.trajectory.extra["model_stop_overrides"] == len(ep.trajectory.actions) - 1


def test_oracle_labeler_is_stateless(scene):
    from image2sim.simulator.navigation.agent import AgentState

    sim, tasks = scene
    lab = OracleLabeler(sim, tasks[2].goal)
    s = AgentState(np.array(tasks[2].start), 0.3)
    a = lab.labels(s)
    lab.labels(AgentState(np.array(tasks[3].start), -1.0))  # unrelated query in between
    assert lab.labels(s) == a


# ------------------------------------------------------------------------------------ end to end


def test_tiny_dagger_run_adds_samples_and_trains_on_them(scene, tiny_cfg, tiny_policy, tmp_path):
    sim, tasks = scene
    from image2sim.navpolicy.rollout_scenes import RolloutScene

    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.max_observations, cfg.data.max_action_labels = 6, 12
    cfg.train.batch_size, cfg.train.warmup_steps, cfg.train.lr = 1, 1, 3e-3
    cfg.dagger = DaggerConfig(
        rounds=2,
        episodes_per_round=1,
        train_steps_per_round=2,
        max_steps=16,
        model_probability=0.5,
        chunk_min=4,
        lr=1e-3,
    )
    policy = copy.deepcopy(tiny_policy)
    before = {k: v.clone() for k, v in policy.model.state_dict().items()}
    res = run_dagger(cfg, [RolloutScene(sim, tasks, "tiny-000")], tmp_path / "dagger", policy=policy)
    # Each round adds its episodes to the aggregated data and trains on the data so far.
    assert res.dataset_sizes == [1, 2]
    assert [len(x) for x in res.losses] == [2, 2] and all(math.isfinite(v) for x in res.losses for v in x)
    assert set(res.seen[0]) == {res.episodes[0]["episode_id"]}
    assert set(res.seen[1]) <= {e["episode_id"] for e in res.episodes}
    changed = [k for k, v in policy.model.state_dict().items() if not torch.equal(v, before[k])]
    assert changed and not any("visual.blocks" in k or "patch_embed" in k for k in changed)
    # Logs and shards on disk.
    lines = [json.loads(x) for x in (tmp_path / "dagger" / "episodes.jsonl").read_text().splitlines()]
    assert [x["round"] for x in lines] == [0, 1] and all(
        x["end"] in ("stop", "stuck", "max_steps") for x in lines
    )
    assert lines[0]["model_probability"] == 0.5 and lines[1]["model_probability"] == 0.9
    for r in range(2):
        reader = ShardReader(tmp_path / "dagger" / f"round_{r:02d}" / "shard")
        t = reader[0]
        assert len(t.extra["oracle_labels"]) == len(t.actions) == lines[r]["steps"]
    assert (res.export_dir / "config.json").is_file()
    # Each round trains at dagger.lr (its own warm-up cosine); the run's train.lr is untouched.
    for r in range(2):
        assert load_config(tmp_path / "dagger" / f"round_{r:02d}" / "train" / "config.yaml").train.lr == 1e-3
    assert load_config(tmp_path / "dagger" / "config.yaml").train.lr == 3e-3


def test_dagger_needs_tasks(tiny_cfg, tmp_path):
    with pytest.raises(ValueError, match="no scenes"):
        run_dagger(tiny_cfg, [], tmp_path)


def test_navtask_from_sample_tasks_are_far_enough(scene):
    sim, tasks = scene
    for t in tasks:
        assert isinstance(t, NavTask)
        d, _ = sim.planner.geodesic_distance(t.start, t.goal)
        assert d >= 1.2


def test_cli_dagger_refuses_a_missing_init_folder(tmp_path):
    from image2sim.navpolicy.cli import app
    from typer.testing import CliRunner

    res = CliRunner().invoke(
        app, ["train", "--stage", "dagger", "--init", str(tmp_path / "nope"), "--out", str(tmp_path)]
    )
    assert res.exit_code == 2 and "no such model folder" in res.output
    res = CliRunner().invoke(app, ["train", "--stage", "rl", "--out", str(tmp_path)])
    assert res.exit_code != 0


def test_rerun_in_the_same_folder_replaces_the_rounds(scene, tiny_cfg, tiny_policy, tmp_path):
    from image2sim.navpolicy.rollout_scenes import RolloutScene

    sim, tasks = scene
    cfg = copy.deepcopy(tiny_cfg)
    cfg.dagger = DaggerConfig(rounds=1, episodes_per_round=1, train_steps_per_round=0, max_steps=6)
    for _ in range(2):
        res = run_dagger(
            cfg, [RolloutScene(sim, tasks)], tmp_path, policy=copy.deepcopy(tiny_policy), export=False
        )
    assert res.dataset_sizes == [1] and res.losses == [[]]
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 1


# ------------------------------------------------------------------------------------------ resume


class Crash(RuntimeError):
    """Stands in for a killed process."""


def _resume_cfg(tiny_cfg):
    cfg = copy.deepcopy(tiny_cfg)
    cfg.data.max_observations, cfg.data.max_action_labels = 4, 8
    cfg.train.batch_size, cfg.train.warmup_steps, cfg.train.lr = 1, 1, 3e-3
    cfg.train.checkpoint_every = 2
    cfg.dagger = DaggerConfig(
        rounds=2, episodes_per_round=3, train_steps_per_round=4, max_steps=10, model_probability=0.5
    )
    return cfg


def _shard_content(root):
    reader = ShardReader(root)
    return [
        (t.episode_id, t.actions, t.extra["oracle_labels"], t.frames.tobytes())
        for t in (reader[i] for i in range(len(reader)))
    ]


def test_interrupted_dagger_resumes_with_the_same_data_and_losses(
    scene, tiny_cfg, tiny_policy, tmp_path, monkeypatch
):
    """Killed once inside a round's training and once inside a collection phase, a rerun with the
    same arguments ends with exactly the uninterrupted run's episodes, shards, losses and weights,
    without collecting any episode twice."""
    import image2sim.navpolicy.dagger as dagger_mod
    from image2sim.navpolicy.dagger import STATE_FILE
    from image2sim.navpolicy.data import synthetic_trajectories
    from image2sim.navpolicy.rollout_scenes import RolloutScene
    from image2sim.navpolicy.train import NavBCModule

    sim, tasks = scene
    cfg = _resume_cfg(tiny_cfg)
    base = synthetic_trajectories(2, 6, 10, cfg.observation.height, cfg.observation.width, seed=0)
    scenes = [RolloutScene(sim, tasks, "tiny-000")]

    def run(folder, **kw):
        return run_dagger(
            cfg, scenes, folder, policy=copy.deepcopy(tiny_policy), base_trajectories=base, **kw
        )

    full = run(tmp_path / "full", export=False)

    rollouts = []
    real_rollout, real_step = dagger_mod.dagger_rollout, NavBCModule.training_step

    def counting_rollout(*a, crash_at=None, **kw):
        if crash_at is not None and len(rollouts) == crash_at:
            raise Crash("killed during collection")
        ep = real_rollout(*a, **kw)
        rollouts.append(ep.trajectory.episode_id)
        return ep

    steps = []

    def crashing_step(self, batch, batch_idx):
        if len(steps) == 3:  # third step of round 0 (a checkpoint exists at step 2)
            raise Crash("killed during training")
        steps.append(batch_idx)
        return real_step(self, batch, batch_idx)

    split = tmp_path / "split"
    monkeypatch.setattr(dagger_mod, "dagger_rollout", counting_rollout)
    monkeypatch.setattr(NavBCModule, "training_step", crashing_step)
    with pytest.raises(Crash, match="training"):
        run(split, export=False)
    assert json.loads((split / STATE_FILE).read_text())["phase"] == "train"
    monkeypatch.setattr(NavBCModule, "training_step", real_step)
    # Second life: finish round 0's training from its step-2 checkpoint, die after 1 of round 1's episodes.
    monkeypatch.setattr(dagger_mod, "dagger_rollout", lambda *a, **kw: counting_rollout(*a, crash_at=4, **kw))
    with pytest.raises(Crash, match="collection"):
        run(split, export=False)
    state = json.loads((split / STATE_FILE).read_text())
    assert (state["round"], state["phase"]) == (1, "collect") and len(state["losses"][0]) == 4
    assert (split / "round_01" / "episodes" / "e0000.json").is_file()
    monkeypatch.setattr(dagger_mod, "dagger_rollout", counting_rollout)
    resumed = run(split, export=True)

    # Every episode collected exactly once, in the uninterrupted order.
    assert rollouts == [e["episode_id"].split("-", 1)[1] for e in full.episodes]  # drop the round tag
    assert resumed.episodes == full.episodes
    assert (split / "episodes.jsonl").read_text() == (tmp_path / "full" / "episodes.jsonl").read_text()
    assert resumed.dataset_sizes == full.dataset_sizes == [5, 8]
    for r in range(2):
        rel = f"round_{r:02d}/shard"
        assert _shard_content(split / rel) == _shard_content(tmp_path / "full" / rel)
    assert not (split / "round_01" / "episodes").exists()
    # The same batches and losses, and the same final weights.
    assert resumed.seen == full.seen
    assert [len(x) for x in resumed.losses] == [4, 4]
    np.testing.assert_allclose(np.array(resumed.losses), np.array(full.losses), rtol=1e-5, atol=1e-7)
    from safetensors.torch import load_file

    a = load_file(tmp_path / "full" / "checkpoints" / "round_01.safetensors")
    b = load_file(split / "checkpoints" / "round_01.safetensors")
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
    assert (resumed.export_dir / "model.safetensors").is_file()
    # A finished run called again collects nothing more and reports the same result.
    again = run(split, export=False)
    assert again.losses == resumed.losses and len(rollouts) == 6


def test_dagger_resume_refuses_other_arguments(scene, tiny_cfg, tiny_policy, tmp_path):
    from image2sim.navpolicy.rollout_scenes import RolloutScene

    sim, tasks = scene
    cfg = copy.deepcopy(tiny_cfg)
    cfg.dagger = DaggerConfig(rounds=1, episodes_per_round=1, train_steps_per_round=0, max_steps=4)
    run_dagger(cfg, [RolloutScene(sim, tasks)], tmp_path, policy=copy.deepcopy(tiny_policy), export=False)
    other = copy.deepcopy(cfg)
    other.dagger.max_steps = 5
    with pytest.raises(ValueError, match="dagger_state.json.*other arguments"):
        run_dagger(
            other, [RolloutScene(sim, tasks)], tmp_path, policy=copy.deepcopy(tiny_policy), export=False
        )
    res = run_dagger(
        other,
        [RolloutScene(sim, tasks)],
        tmp_path,
        policy=copy.deepcopy(tiny_policy),
        export=False,
        resume=False,
    )
    assert res.dataset_sizes == [1] and len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 1


def test_nav_act_runs_the_ultra_wide_setting(scene, tiny_cfg):
    """`nav act` with an equirectangular observation (the paper's 180 x 118 deg setting, here at
    64 x 42 pixels) observes the centred crop of a full panorama at the configured size."""
    import copy

    from image2sim.eval.runner import NeuralSimBackend
    from image2sim.navpolicy.act import act_protocol, task_episodes

    cfg = copy.deepcopy(tiny_cfg)
    cfg.observation.camera, cfg.observation.width, cfg.observation.height = "equirect", 64, 42
    cfg.observation.hfov_deg, cfg.observation.vfov_deg = 180.0, 118.0
    proto = act_protocol(cfg, 50, 0.5)
    assert proto.camera.kind == "equirect" and (proto.camera.width, proto.camera.height) == (64, 42)
    sim, _ = scene
    (episode,) = task_episodes(sim, 1, 0, "plain")
    obs = NeuralSimBackend(sim, proto, "plain").reset(episode, observe=True)
    assert obs.rgb.shape == (42, 64, 3) and obs.rgb.dtype == np.uint8
