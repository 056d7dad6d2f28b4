"""Navigation runner on a tiny procedural scene: baselines, oracle ground truth, resume after SIGKILL."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from image2sim.eval.metrics.nav import aggregate
from image2sim.eval.protocols import IMAGE2SIM, VLNCE, ProtocolMismatchError
from image2sim.eval.results import read_episode_log, read_metrics_file, read_result_file
from image2sim.eval.runner import (
    AgentSpec,
    BackendUnavailable,
    HabitatBackend,
    NeuralSimBackend,
    RandomAgent,
    RunConfig,
    RunnerError,
    StepObservation,
    bootstrap_ci,
    embodiment_for,
    episode_seed,
    make_agent,
    nav_markdown,
    nav_summary,
    run_episode,
    run_nav,
    sample_point_goal_episodes,
    update_nav_metrics,
    wilson_interval,
)
from image2sim.simulator.conventions import Action

# The tiny procedural rooms are ~2 x 2 m, so the 3 m success radius of the paper would make every
# episode a success at the start: the tests use a copy of the paper's protocol with a 0.5 m radius.
PROTO = dataclasses.replace(
    IMAGE2SIM, name="tiny-test", success_distance_m=0.5, ndtw_threshold_m=0.5, max_steps=200
)
N_EPISODES = 10


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A tiny procedural scene: navigation map + graph on disk under ``<root>/scene_000``."""
    from image2sim.dataengine.procedural import capture_frames, generate_scene, preset
    from image2sim.simulator.navigation import NavGraph, NavMapConfig, extract_navmap
    from image2sim.simulator.sim import NeuralSimulator

    frames, _ = capture_frames(generate_scene(preset("tiny"), seed=0))
    navmap = extract_navmap(frames, embodiment_for(PROTO), NavMapConfig(floor_labels=(1, 10)))
    graph = NavGraph.build(navmap)
    root = tmp_path_factory.mktemp("scenes")
    navmap.save(root / "scene_000" / "navmap.npz")
    graph.save(root / "scene_000" / "navgraph.npz")
    sim = NeuralSimulator(navmap, graph)
    episodes = sample_point_goal_episodes(sim, N_EPISODES, seed=0, min_distance=1.5, scene_id="scene_000")
    return root, sim, episodes


def _summaries(scene, agent: str, **options):
    _, sim, episodes = scene
    backend = NeuralSimBackend(sim, PROTO)
    ag = make_agent(AgentSpec(agent, options))
    results = [run_episode(backend, ag, ep, PROTO, episode_seed(0, ep.episode_id))[0] for ep in episodes]
    return results, nav_summary(results)


def test_oracle_reaches_every_goal_efficiently(scene):
    results, s = _summaries(scene, "oracle")
    assert s["n_episodes"] == N_EPISODES
    assert s["sr"] == 1.0 and s["osr"] == 1.0
    assert s["spl"] >= 0.95
    assert s["ne"] < PROTO.success_distance_m
    # The oracle's nDTW against its own planner path is high (but below 1: smoothing, discrete turns).
    assert 0.6 < s["ndtw"] <= 1.0
    for r, ep in zip(results, scene[2], strict=True):
        # Triangle inequality: a successful path is at least the straight start-goal distance minus the
        # success radius (the grid geodesic itself may exceed what the continuous agent walks).
        straight = float(np.linalg.norm(ep.goal_position - ep.start_position))
        assert r.metrics["path_length"] >= straight - PROTO.success_distance_m


def test_random_and_forward_baselines_are_much_worse(scene):
    _, oracle = _summaries(scene, "oracle")
    _, rnd = _summaries(scene, "random")
    _, fwd = _summaries(scene, "forward", forward_steps=6)
    assert rnd["sr"] <= 0.3 and rnd["spl"] <= oracle["spl"] - 0.5
    assert fwd["sr"] <= 0.3 and fwd["ne"] > oracle["ne"]
    # forward: exactly forward_steps FORWARD actions, then STOP -> 7 steps in every episode.
    assert fwd["steps"] == 7.0


def test_episode_outcomes_split_every_goal_episode_into_one_ending():
    from image2sim.eval.metrics.nav import EpisodeResult
    from image2sim.eval.nav_summary import OUTCOMES, episode_outcomes

    ids = iter(range(100))

    def result(success, oracle, steps):
        m = {"success": success, "oracle_success": oracle, "steps": steps}
        return EpisodeResult(f"e{next(ids)}", m, PROTO)

    cap = PROTO.max_steps
    rs = [result(1.0, 1.0, 20), result(0.0, 1.0, 30), result(0.0, 0.0, 12), result(0.0, 0.0, 12)]
    rs += [result(0.0, 0.0, cap), result(None, None, 5)]  # the last has no goal: not counted
    got = episode_outcomes(rs)
    assert got == {"success": 0.2, "passed_goal": 0.2, "stopped_short": 0.4, "out_of_steps": 0.2}
    assert set(got) == set(OUTCOMES) and episode_outcomes([result(None, None, 5)]) is None
    summary = nav_summary(rs[:5])
    assert summary["outcomes"]["success"] == pytest.approx(summary["sr"])
    assert "| forward | 20.0 | 20.0 | 40.0 | 20.0 |" in nav_markdown({"agents": {"forward": summary}})


def test_episode_trajectory_is_a_function_of_its_seed(scene):
    _, sim, episodes = scene
    backend = NeuralSimBackend(sim, PROTO)
    ep = episodes[3]
    seed = episode_seed(7, ep.episode_id)
    a1 = run_episode(backend, RandomAgent(), ep, PROTO, seed)
    run_episode(backend, RandomAgent(), episodes[0], PROTO, 123)  # unrelated episode in between
    a2 = run_episode(backend, RandomAgent(), ep, PROTO, seed)
    assert a1[1] == a2[1] and a1[0].metrics == a2[0].metrics
    assert episode_seed(7, "a") == episode_seed(7, "a") != episode_seed(8, "a")


def test_step_limit_ends_an_episode_without_success(scene):
    _, sim, episodes = scene
    short = dataclasses.replace(PROTO, max_steps=3)
    backend = NeuralSimBackend(sim, short)
    res, actions = run_episode(
        backend, make_agent(AgentSpec("forward", {"forward_steps": 50})), episodes[0], short, 0
    )
    assert actions == [int(Action.MOVE_FORWARD)] * 3
    assert res.metrics["steps"] == 3 and res.metrics["success"] == 0.0


def test_backend_refuses_a_map_built_for_another_embodiment(scene):
    _, sim, _ = scene
    with pytest.raises(RunnerError, match="radius"):
        NeuralSimBackend(sim, VLNCE)  # radius 0.1 m, eye 1.5 m vs the map's 0.15 m / 1.25 m


def test_unreachable_goal_is_an_error_naming_the_episode_not_a_silent_drop(scene):
    _, sim, episodes = scene
    backend = NeuralSimBackend(sim, PROTO)
    bad = dataclasses.replace(episodes[0], episode_id="far-goal", goal_position=np.array([80.0, 80.0, 0.0]))
    with pytest.raises(RunnerError, match=r"episode far-goal: the agent starts .*off the navigable map"):
        run_episode(backend, make_agent(AgentSpec("oracle")), bad, PROTO, 0)


class _EndsOffGraphBackend:
    """Walks the scene's episode normally, then reports an undefined goal distance after FORWARD."""

    def reset(self, episode, observe=False):
        return StepObservation(np.zeros(3), 0.0, 4.0)

    def step(self, action, observe=False):
        return StepObservation(np.array([0.25, 0.0, 0.0]), 0.0, np.inf, distance_reason="node 7 is cut off")


def test_an_episode_ending_where_the_distance_is_undefined_raises_with_the_reason(scene):
    ep = scene[2][1]
    agent = make_agent(AgentSpec("forward", {"forward_steps": 1}))
    with pytest.raises(RunnerError, match=rf"episode {ep.episode_id}: the agent ends .*node 7 is cut off"):
        run_episode(_EndsOffGraphBackend(), agent, ep, PROTO, 0)


class _EndsApproximatelyBackend(_EndsOffGraphBackend):
    """Ends where the graph does not reach the goal but the planner could estimate the distance."""

    def __init__(self, start_approx: bool = False):
        self.start_approx = start_approx

    def reset(self, episode, observe=False):
        return StepObservation(np.zeros(3), 0.0, 4.0, distance_approximate=self.start_approx)

    def step(self, action, observe=False):
        return StepObservation(
            np.array([0.25, 0.0, 0.0]),
            0.0,
            3.8,
            distance_reason="approximate: cut off",
            distance_approximate=True,
        )


def test_an_estimated_final_distance_counts_and_is_flagged_but_an_estimated_start_is_an_error(scene):
    ep = scene[2][1]
    agent = make_agent(AgentSpec("forward", {"forward_steps": 1}))
    result, _ = run_episode(_EndsApproximatelyBackend(), agent, ep, PROTO, 0)
    assert result.metrics["ne_approximate"] == 1.0
    assert result.metrics["distance_to_goal"] == pytest.approx(3.8)
    summary = nav_summary([result])
    assert summary["ne_approximate"] == 1.0 and summary["ne"] == pytest.approx(3.8)
    assert "planner's estimate" in nav_markdown({"agents": {"forward": summary}})
    with pytest.raises(RunnerError, match=rf"episode {ep.episode_id}: the start is not connected"):
        run_episode(_EndsApproximatelyBackend(start_approx=True), agent, ep, PROTO, 0)


def test_habitat_backend_is_import_guarded(monkeypatch):
    monkeypatch.setitem(sys.modules, "habitat_sim", None)  # as if habitat-sim were not installed
    with pytest.raises(BackendUnavailable, match="habitat-sim"):
        HabitatBackend("scene.glb", VLNCE)


def test_run_config_rejects_unknown_keys_and_agents():
    with pytest.raises(RunnerError, match="unknown key"):
        RunConfig.from_dict({"agent": "oracle", "wokers": 2})
    with pytest.raises(RunnerError, match="unknown agent"):
        RunConfig(agent="teleport")
    with pytest.raises(RunnerError, match="bad options"):
        make_agent(AgentSpec("forward", {"steps": 3}))


def test_wilson_interval_textbook_values():
    # Wilson 95 % for 8/10 from the closed form by hand: centre 0.99208/1.38415 = 0.71674,
    # half-width 1.96 * sqrt(0.016 + 0.009604) / 1.38415 = 0.22658 -> [0.4902, 0.9433].
    lo, hi = wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-4) and hi == pytest.approx(0.9433, abs=1e-4)
    lo, hi = wilson_interval(10, 10)
    assert hi == 1.0 and lo == pytest.approx(0.7225, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    assert wilson_interval(0, 7)[0] == 0.0


def test_bootstrap_ci_brackets_the_mean_and_is_seeded():
    x = np.random.default_rng(0).uniform(size=50)
    lo, hi = bootstrap_ci(x, seed=1)
    assert lo < x.mean() < hi
    assert bootstrap_ci(x, seed=1) == (lo, hi)
    assert bootstrap_ci(np.ones(5)) == (1.0, 1.0)
    with pytest.raises(ValueError, match="non-finite"):
        bootstrap_ci([1.0, float("nan")])


def test_nav_metrics_file_keys_and_protocol_guard(tmp_path, scene):
    results, s = _summaries(scene, "oracle")
    path = update_nav_metrics(tmp_path / "nav.json", PROTO, "oracle", s)
    _, r = _summaries(scene, "random")
    update_nav_metrics(path, PROTO, "random", r)
    doc = read_metrics_file(path)
    assert doc["protocol"]["name"] == "tiny-test"
    assert set(doc["agents"]) == {"oracle", "random"}
    for agent in doc["agents"].values():
        for key in ("sr", "spl", "ne", "osr", "ndtw", "n_episodes", "sr_ci", "spl_ci"):
            assert key in agent
        assert agent["sr_ci"][0] <= agent["sr"] <= agent["sr_ci"][1]
        assert agent["spl_ci"][0] <= agent["spl"] <= agent["spl_ci"][1]
    with pytest.raises(ProtocolMismatchError):
        update_nav_metrics(path, IMAGE2SIM, "forward", r)


_CHILD = textwrap.dedent(
    """
    import sys, time
    from image2sim.eval.runner import *
    from image2sim.eval.protocols import Protocol
    import json
    root, out, proto = sys.argv[1], sys.argv[2], Protocol.from_dict(json.loads(sys.argv[3]))
    backend = load_scene_backend(root + "/scene_000", proto)
    eps = sample_point_goal_episodes(backend.sim, N, seed=0, min_distance=1.5, scene_id="scene_000")

    class Slow(RandomAgent):
        def reset(self, episode, backend, seed):
            time.sleep(0.25)  # long enough to be killed between episodes
            super().reset(episode, backend, seed)

    log = out + "/random/scene_000.jsonl"
    run_scene(backend, eps, proto, RunConfig(agent="random", seed=5), log, agent=Slow())
    """
).replace("N,", f"{N_EPISODES},")


def test_sigkill_and_resume_gives_the_uninterrupted_aggregate(scene, tmp_path):
    root, _, episodes = scene
    killed = tmp_path / "killed"
    log = killed / "random" / "scene_000.jsonl"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(root), str(killed), json.dumps(PROTO.to_dict())],
        env=env,
        stderr=subprocess.PIPE,
    )
    deadline = time.time() + 120
    while time.time() < deadline:
        n = len(log.read_text().splitlines()) - 1 if log.exists() else 0
        if n >= 3:
            break
        if proc.poll() is not None:
            pytest.fail(f"child exited early: {proc.stderr.read().decode()[-2000:]}")
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    _, partial = read_episode_log(log)
    assert 3 <= len(partial) < N_EPISODES, "the kill should land mid-run"
    cfg = RunConfig(agent="random", seed=5)
    resumed = run_nav(episodes, root, PROTO, cfg, killed, show_progress=False)
    fresh = run_nav(episodes, root, PROTO, cfg, tmp_path / "fresh", show_progress=False)
    assert resumed.num_episodes == fresh.num_episodes == N_EPISODES
    assert resumed.to_dict() == fresh.to_dict()
    # Every episode appears once in the resumed log; a second call runs nothing new.
    _, logged = read_episode_log(log)
    assert sorted(r.episode_id for r in logged) == sorted(e.episode_id for e in episodes)
    again = run_nav(episodes, root, PROTO, cfg, killed, show_progress=False)
    assert again.to_dict() == fresh.to_dict()
    proto, manifest = read_result_file(killed / "random" / "run.json")
    assert proto == PROTO and manifest["config"]["seed"] == 5 and "crc32" in manifest["seed_rule"]


def test_a_resume_keeps_one_trajectory_line_per_episode(scene, tmp_path):
    """Killed between an episode's trajectory line and its result line (and mid-write of another
    line): the resume reruns that episode and leaves exactly the uninterrupted run's trajectories."""
    root, _, episodes = scene
    cfg = RunConfig(agent="random", seed=5)
    run_nav(episodes, root, PROTO, cfg, tmp_path / "fresh", show_progress=False)
    run_nav(episodes, root, PROTO, cfg, tmp_path / "killed", show_progress=False)
    log = tmp_path / "killed" / "random" / "scene_000.jsonl"
    traj = log.with_name(log.name + ".traj.jsonl")
    fresh_traj = (tmp_path / "fresh" / "random" / traj.name).read_text()
    lines = log.read_text().splitlines(keepends=True)
    log.write_text("".join(lines[:-1]))  # the last episode's result never got written
    with traj.open("a") as f:
        f.write('{"episode_id": "torn')
    run_nav(episodes, root, PROTO, cfg, tmp_path / "killed", show_progress=False)
    ids = [json.loads(line)["episode_id"] for line in traj.read_text().splitlines()]
    assert sorted(ids) == sorted(e.episode_id for e in episodes)
    assert sorted(traj.read_text().splitlines()) == sorted(fresh_traj.splitlines())


def test_resume_with_other_result_settings_is_refused(scene, tmp_path):
    """A second call into the same folder with another seed or agent option would skip every logged
    episode and report the old run's numbers as the new one's: it is refused, naming the field."""
    root, _, episodes = scene
    out = tmp_path / "out"
    run_nav(episodes[:2], root, PROTO, RunConfig(agent="random", seed=0), out, show_progress=False)
    with pytest.raises(RunnerError, match=r"seed: logged 0, now 9"):
        run_nav(episodes[:2], root, PROTO, RunConfig(agent="random", seed=9), out, show_progress=False)
    opts = RunConfig(agent="random", seed=0, agent_options={"probabilities": [0.25, 0.25, 0.25, 0.25]})
    with pytest.raises(RunnerError, match="agent_options"):
        run_nav(episodes[:2], root, PROTO, opts, out, show_progress=False)
    # Settings that do not change an episode's result may differ; the same run resumes as before.
    same = RunConfig(agent="random", seed=0, workers=2)
    again = run_nav(episodes[:2], root, PROTO, same, out, show_progress=False)
    assert again.num_episodes == 2


@pytest.mark.slow
def test_parallel_scenes_match_serial(scene, tmp_path):
    root, _, episodes = scene
    # Two "scenes" (a copy of the same maps) so the pool really fans out.
    import shutil

    shutil.copytree(root / "scene_000", tmp_path / "scenes" / "scene_000")
    shutil.copytree(root / "scene_000", tmp_path / "scenes" / "scene_001")
    eps = episodes[:3] + [
        dataclasses.replace(e, episode_id="b" + e.episode_id, scene_id="scene_001") for e in episodes[:3]
    ]
    serial = run_nav(
        eps, tmp_path / "scenes", PROTO, RunConfig(agent="oracle"), tmp_path / "s", show_progress=False
    )
    par = run_nav(
        eps,
        tmp_path / "scenes",
        PROTO,
        RunConfig(agent="oracle", workers=2),
        tmp_path / "p",
        show_progress=False,
    )
    assert serial.to_dict() == par.to_dict()
    assert aggregate(read_episode_log(tmp_path / "p" / "oracle" / "scene_001.jsonl")[1]).num_episodes == 3
    with pytest.raises(RunnerError, match="not found"):
        bad = [dataclasses.replace(episodes[0], scene_id="nowhere")]
        run_nav(bad, tmp_path / "scenes", PROTO, RunConfig(), tmp_path / "x", show_progress=False)


def test_cli_nav_then_report(scene, tmp_path):
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    root, _, _ = scene
    proto_file = tmp_path / "proto.json"
    proto_file.write_text(json.dumps(PROTO.to_dict()))
    metrics = tmp_path / "metrics" / "nav.json"
    args = [
        "nav",
        "--scenes",
        str(root),
        "--point-goal",
        "4",
        "--agent",
        "oracle",
        "--agent",
        "forward",
        "--forward-steps",
        "3",
        "--protocol",
        str(proto_file),
        "--out",
        str(tmp_path / "run"),
        "--metrics",
        str(metrics),
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    doc = json.loads(metrics.read_text())
    assert set(doc["agents"]) == {"oracle", "forward"}
    assert doc["agents"]["oracle"]["sr"] == 1.0 and doc["agents"]["oracle"]["n_episodes"] == 4
    assert doc["agents"]["forward"]["steps"] == 4.0
    res = CliRunner().invoke(app, ["report", "--nav", str(metrics), "--out-dir", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    table = (tmp_path / "rep" / "nav.md").read_text()
    assert "| oracle | " in table and "100.0 [" in table and "tiny-test" in table


class _ScriptedStreamingAgent:
    """Stands in for navpolicy's Image2NavAgent: replies with fixed action pairs, records its inputs."""

    def __init__(self, replies):
        self.replies = [list(r) for r in replies]
        self.calls = []

    def reset(self, instruction, seed=0):
        self.instruction, self.calls, self._k = instruction, [], 0

    def act(self, rgb, executed=None):
        self.calls.append((rgb.shape, rgb.dtype, None if executed is None else list(executed)))
        reply = self.replies[self._k]
        self._k += 1
        return reply


def test_image2nav_adapter_executes_action_pairs_and_observes_only_when_needed(scene):
    from image2sim.eval.runner import Image2NavAdapter
    from image2sim.simulator.sim import NeuralSimulator

    _, sim, episodes = scene
    rendered = []

    def render_fn(camera, pose):
        rendered.append(pose[:3, 3].copy())
        return {
            "rgb": np.full((camera.height, camera.width, 3), 0.25, np.float32),
            "depth": np.ones((camera.height, camera.width), np.float32),
        }

    obs_sim = NeuralSimulator(sim.navmap, sim.graph, render_fn)
    F, L, S = int(Action.MOVE_FORWARD), int(Action.TURN_LEFT), int(Action.STOP)
    fake = _ScriptedStreamingAgent([[F, L], [F, S]])
    adapter = Image2NavAdapter.from_agent(fake)
    res, actions = run_episode(NeuralSimBackend(obs_sim, PROTO), adapter, episodes[0], PROTO, 1)
    assert actions == [F, L, F, S]
    assert fake.instruction == episodes[0].instruction.text
    # Two model calls, each on a fresh 336x336 uint8 image (the protocol camera); the second is told
    # which actions were executed since the first.
    assert fake.calls == [((336, 336, 3), np.uint8, None), ((336, 336, 3), np.uint8, [F, L])]
    assert len(rendered) == 2  # no rendering while the queued second action is executed
    assert res.metrics["steps"] == 4.0
    with pytest.raises(RunnerError, match="render function"):
        run_episode(NeuralSimBackend(sim, PROTO), Image2NavAdapter.from_agent(fake), episodes[0], PROTO, 1)


def test_image2nav_adapter_can_withhold_stop(scene):
    # A subclass's stop_allowed() reaches the streaming agent as allow_stop=False; agents without the
    # keyword (remote ones) are called as before while STOP is allowed.
    from image2sim.eval.runner import Image2NavAdapter
    from image2sim.simulator.sim import NeuralSimulator

    _, sim, episodes = scene

    class Obeying(_ScriptedStreamingAgent):
        def act(self, rgb, executed=None, allow_stop=True):
            self.allowed = [*getattr(self, "allowed", []), allow_stop]
            self._k %= len(self.replies)  # the script repeats
            reply = super().act(rgb, executed)
            return [Action.TURN_LEFT if (a == Action.STOP and not allow_stop) else a for a in reply]

    class FarFromGoal(Image2NavAdapter):
        def stop_allowed(self, obs):
            return obs.distance_to_goal < 0.5

    def render_fn(camera, pose):
        return {
            "rgb": np.zeros((camera.height, camera.width, 3), np.float32),
            "depth": np.ones((camera.height, camera.width), np.float32),
        }

    backend = NeuralSimBackend(NeuralSimulator(sim.navmap, sim.graph, render_fn), PROTO)
    F, L, S = int(Action.MOVE_FORWARD), int(Action.TURN_LEFT), int(Action.STOP)
    agent = Obeying([[S, F], [F, S]])
    res, actions = run_episode(backend, FarFromGoal.from_agent(agent), episodes[0], PROTO, 1)
    assert actions[:4] == [L, F, F, L] and agent.allowed[:2] == [False, False]
    assert S not in actions and len(actions) == PROTO.max_steps  # never near enough to be let stop
    plain = _ScriptedStreamingAgent([[F, S]])  # no allow_stop keyword: never passed when allowed
    _, actions = run_episode(backend, Image2NavAdapter.from_agent(plain), episodes[0], PROTO, 1)
    assert actions == [F, S]


@pytest.mark.slow
def test_image2nav_adapter_runs_the_tiny_navpolicy_model(scene):
    pytest.importorskip("image2sim.navpolicy")
    from image2sim.eval.runner import Image2NavAdapter
    from image2sim.simulator.sim import NeuralSimulator

    _, sim, episodes = scene
    small = dataclasses.replace(
        PROTO, max_steps=4, camera=dataclasses.replace(PROTO.camera, width=64, height=64)
    )

    def render_fn(camera, pose):
        return {
            "rgb": np.full((camera.height, camera.width, 3), 0.5, np.float32),
            "depth": np.ones((camera.height, camera.width), np.float32),
        }

    backend = NeuralSimBackend(NeuralSimulator(sim.navmap, sim.graph, render_fn), small)
    res, actions = run_episode(backend, Image2NavAdapter(), episodes[0], small, 0)
    assert 1 <= len(actions) <= 4 and res.metrics["steps"] == len(actions)


def _write_vlnce_file(path, episodes, instruction=None, vocab=None):
    """A world-frame VLN-CE-schema episode file (the data engine's layout) for ``episodes``."""
    import gzip

    doc = {
        "frame": "image2sim-z-up",
        "quaternion_order": "wxyz",
        "episodes": [
            {
                "episode_id": e.episode_id,
                "scene_id": "procedural/scene_000.glb",
                "start_position": e.start_position.tolist(),
                "start_rotation": e.start_rotation.tolist(),
                "goals": [{"position": e.goal_position.tolist(), "radius": 3.0}],
                "reference_path": e.reference_path.tolist(),
                "instruction": instruction or {"instruction_text": "walk to the goal"},
                "info": {"geodesic_distance": e.geodesic_distance},
            }
            for e in episodes
        ],
    }
    if vocab is not None:
        doc["instruction_vocab"] = {"word_list": list(vocab)}
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wt", encoding="utf-8") as f:
        json.dump(doc, f)
    return path


def test_cli_nav_reads_a_vlnce_schema_episode_file(scene, tmp_path):
    """The data engine's layout: world-frame VLN-CE json.gz, scenes found by the scene_id stem."""
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    root, _, episodes = scene
    # Every episode of the fixture, as test_oracle_reaches_every_goal_efficiently: the oracle follows the
    # planner's clearance-penalised path, so one short episode alone can fall below the SPL bound.
    path = _write_vlnce_file(tmp_path / "val_seen.json.gz", episodes)
    proto_file = tmp_path / "proto.json"
    proto_file.write_text(json.dumps({"protocol": PROTO.to_dict()}))  # a result-file style record works too
    metrics = tmp_path / "nav.json"
    res = CliRunner().invoke(
        app,
        [
            "nav",
            "--scenes",
            str(root),
            "--episodes",
            str(path),
            "--agent",
            "oracle",
            "--protocol",
            str(proto_file),
            "--out",
            str(tmp_path / "run"),
            "--metrics",
            str(metrics),
        ],
    )
    assert res.exit_code == 0, res.output
    oracle = json.loads(metrics.read_text())["agents"]["oracle"]
    assert oracle["n_episodes"] == N_EPISODES and oracle["sr"] == 1.0 and oracle["spl"] >= 0.95


def test_cli_nav_reads_the_published_benchmark_layouts(scene, tmp_path):
    """`eval nav --dataset r2r-ce|rxr-ce|reverie-ce --dataset-root R --split S` goes through each
    benchmark's own loader: R2R-CE refuses a file without its vocabulary, RxR-CE filters roles."""
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    root, _, episodes = scene

    def write(path, with_vocab):
        instruction = {"instruction_text": "walk to the goal", "language": "en-US"}
        vocab = ["walk", "to", "the", "goal"] if with_vocab else None
        _write_vlnce_file(path, episodes[:2], instruction, vocab)

    proto_file = tmp_path / "proto.json"
    proto_file.write_text(json.dumps({"protocol": PROTO.to_dict()}))

    def run(dataset, data_root, *extra):
        args = ["nav", "--scenes", str(root), "--dataset", dataset, "--dataset-root", str(data_root)]
        args += ["--split", "val_seen", "--agent", "oracle", "--protocol", str(proto_file)]
        args += ["--out", str(tmp_path / f"run_{dataset}"), "--metrics", str(tmp_path / f"{dataset}.json")]
        return CliRunner().invoke(app, args + list(extra))

    write(tmp_path / "r2r" / "val_seen" / "val_seen.json.gz", with_vocab=True)
    res = run("r2r-ce", tmp_path / "r2r")
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "r2r-ce.json").read_text())["agents"]["oracle"]["n_episodes"] == 2
    write(tmp_path / "novocab" / "val_seen" / "val_seen.json.gz", with_vocab=False)
    res = run("r2r-ce", tmp_path / "novocab")
    assert res.exit_code == 2 and "instruction_vocab" in res.output
    assert run("reverie-ce", tmp_path / "novocab").exit_code == 0  # REVERIE-CE has no vocabulary
    write(tmp_path / "rxr" / "val_seen" / "val_seen_guide.json.gz", with_vocab=False)
    res = run("rxr-ce", tmp_path / "rxr", "--language", "te-IN")
    said = re.sub(r"[│╭╮╰╯─\s]+", " ", res.output)  # the error box wraps long lines
    assert res.exit_code == 2 and "no episodes" in said, said  # no Telugu episodes: said so
    assert run("rxr-ce", tmp_path / "rxr", "--language", "en-US").exit_code == 0


def test_ultra_wide_observation_is_the_centred_180_by_118_degree_crop(scene):
    """The `image2sim-180` camera (512 x 336 at 180 x 118 deg) is the middle of a full panorama with
    the same angular resolution: its edges sit at longitude +-90 deg and latitude +-59 deg, and the
    agent receives exactly 336 x 512 pixels, centred on the heading."""
    import math

    import torch
    from image2sim.eval.nav_env import equirect_crop
    from image2sim.eval.protocols import PROTOCOLS
    from image2sim.simulator.sim import NeuralSimulator

    wide = PROTOCOLS["image2sim-180"]
    full, (rows, cols) = equirect_crop(wide.camera)
    assert (full.height, full.width) == (512, 1024) and (rows.stop - rows.start, cols.stop - cols.start) == (
        336,
        512,
    )
    lon, lat = full.pixel_to_lonlat(
        torch.tensor([float(cols.start), float(cols.stop)]),
        torch.tensor([float(rows.start), float(rows.stop)]),
    )
    assert torch.allclose(torch.rad2deg(lon), torch.tensor([-90.0, 90.0]))
    assert torch.allclose(torch.rad2deg(lat), torch.tensor([59.0, -59.0]), atol=0.2)
    full360, crop = equirect_crop(dataclasses.replace(wide.camera, hfov_deg=360.0, vfov_deg=180.0))
    assert crop is None and (full360.height, full360.width) == (336, 512)

    _, sim, episodes = scene

    def lon_image(camera, pose):  # red = longitude of the pixel, so the crop's position shows
        u = torch.arange(camera.width, dtype=torch.float32) + 0.5
        lon_u, _ = camera.pixel_to_lonlat(u, torch.zeros_like(u))
        red = ((lon_u + math.pi) / (2 * math.pi)).numpy()
        rgb = np.zeros((camera.height, camera.width, 3), np.float32)
        rgb[..., 0] = red
        return {"rgb": rgb, "depth": np.ones((camera.height, camera.width), np.float32)}

    proto = dataclasses.replace(wide, success_distance_m=0.5, ndtw_threshold_m=0.5)
    backend = NeuralSimBackend(NeuralSimulator(sim.navmap, sim.graph, lon_image), proto)
    obs = backend.reset(episodes[0], observe=True)
    assert obs.rgb.shape == (336, 512, 3)
    red = obs.rgb[0, :, 0].astype(float) / 255.0
    assert abs(red[0] - 0.25) < 0.01 and abs(red[-1] - 0.75) < 0.01  # -90 deg ... +90 deg


def test_an_off_map_start_names_the_episode_and_its_scene(scene):
    _, sim, episodes = scene
    far = dataclasses.replace(
        episodes[0], episode_id="far-away", start_position=np.array([1000.0, 1000.0, 0.0])
    )
    with pytest.raises(RunnerError, match=r"episode far-away \(scene scene_000\): cannot place the agent"):
        run_episode(NeuralSimBackend(sim, PROTO), RandomAgent(), far, PROTO, seed=0)
