"""Navigation runner: the episode loop over a simulator backend and an agent, resumable, parallel over
scenes (habitat-lab's *benchmark*).

Split like habitat-lab: :mod:`image2sim.eval.nav_env` holds the backends (the *env*: place the agent,
apply actions, report positions and geodesic distances), :mod:`image2sim.eval.nav_agents` the agents,
:mod:`image2sim.eval.metrics.nav` the measures, :mod:`image2sim.eval.nav_summary` the headline
record with intervals. This module runs them:

* :func:`run_episode` scores one episode with the protocol's measures; :func:`run_scene` appends every
  finished episode to a per-scene JSONL :class:`~image2sim.eval.results.EpisodeLog` (a killed run
  resumes by skipping the episode ids already logged); :func:`run_nav` fans scenes out over processes
  and aggregates the logs.

Seeds: every episode's seed is :func:`episode_seed` ``(run_seed, episode_id)``, a pure function, so an
episode gives the same trajectory whether it runs first, last, in another process or after a resume.
The seed and the action sequence of each episode are written to a per-scene trajectory JSONL.

The names of the three other modules are re-exported here for existing imports.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from image2sim.eval.datasets import NavEpisode
from image2sim.eval.metrics.nav import (
    DEFAULT_MEASURES,
    GOAL_FREE_MEASURES,
    AgentState,
    AggregateReport,
    EpisodeResult,
    Measurements,
    aggregate,
)
from image2sim.eval.nav_agents import (
    AGENTS,
    AgentSpec,
    ForwardAgent,
    Image2NavAdapter,
    Image2NavHttpAdapter,
    NavAgent,
    OracleAgent,
    RandomAgent,
    make_agent,
    needs_goal,
)
from image2sim.eval.nav_env import (
    BackendUnavailable,
    HabitatBackend,
    NeuralSimBackend,
    RunnerError,
    StepObservation,
    check_embodiment,
    embodiment_for,
    load_exact_backend,
    load_scene_backend,
)
from image2sim.eval.nav_summary import (
    bootstrap_ci,
    nav_markdown,
    nav_summary,
    update_nav_metrics,
    wilson_interval,
)
from image2sim.eval.protocols import Protocol
from image2sim.eval.results import (
    EpisodeLog,
    episode_logs,
    read_episode_log,
    read_result_file,
    write_result_file,
)
from image2sim.simulator.config import ConfigError, config_from_dict
from image2sim.simulator.conventions import Action

__all__ = [
    "AGENTS",
    "AgentSpec",
    "BackendUnavailable",
    "ForwardAgent",
    "HabitatBackend",
    "Image2NavAdapter",
    "Image2NavHttpAdapter",
    "NavAgent",
    "NeuralSimBackend",
    "OracleAgent",
    "RandomAgent",
    "RunConfig",
    "RunnerError",
    "StepObservation",
    "bootstrap_ci",
    "check_embodiment",
    "embodiment_for",
    "episode_seed",
    "load_scene_backend",
    "load_exact_backend",
    "make_agent",
    "nav_markdown",
    "needs_goal",
    "nav_summary",
    "run_episode",
    "run_nav",
    "run_nav_results",
    "run_scene",
    "sample_point_goal_episodes",
    "update_nav_metrics",
    "wilson_interval",
]

# ------------------------------------------------------------------------------------------ seeds


def episode_seed(run_seed: int, episode_id: str) -> int:
    """Seed of one episode: a pure function of the run seed and the episode id (order-independent)."""
    return zlib.crc32(f"{int(run_seed)}:{episode_id}".encode()) & 0x7FFFFFFF


# ------------------------------------------------------------------------------------------ episodes


def run_episode(
    backend: Any, agent: Any, episode: NavEpisode, protocol: Protocol, seed: int, poses: list | None = None
) -> tuple[EpisodeResult, list[int]]:
    """Run one episode to STOP or the protocol's step limit; returns its result and the actions.

    ``poses``, when given, receives the agent's ``(position, heading)`` (world frame) at the start and
    after every action, STOP included: what leaderboard submissions report per step.

    An episode without a goal (a test split) runs the goal-free measures only; the others are n/a
    (``None``) in its result, never 0."""
    ms = Measurements(protocol, DEFAULT_MEASURES if episode.has_goal else GOAL_FREE_MEASURES)
    wants = (lambda: getattr(agent, "wants_image", True)) if agent.needs_images else (lambda: False)
    try:
        obs = backend.reset(episode, observe=bool(agent.needs_images))
    except ValueError as err:  # e.g. a start off the navigation map: name the episode and its scene
        raise RunnerError(f"episode {episode.episode_id} (scene {episode.scene_id}): {err}") from err
    _require_finite_distance(obs, episode, "starts")
    if obs.distance_approximate and episode.has_goal:
        raise RunnerError(
            f"episode {episode.episode_id}: the start is not connected to the goal on the navigation graph "
            f"({obs.distance_reason}); fix the episode or the scene's navigation graph"
        )
    agent.reset(episode, backend, seed)
    ms.reset(episode.metric_spec(), AgentState(obs.position, obs.distance_to_goal))

    def record(o: StepObservation) -> None:
        if poses is not None:
            poses.append((np.asarray(o.position, dtype=np.float64).copy(), float(o.heading)))

    record(obs)
    actions: list[int] = []
    for _ in range(protocol.max_steps):
        a = int(agent.act(obs))
        if a not in {int(x) for x in Action}:
            raise RunnerError(f"episode {episode.episode_id}: agent returned action {a!r}")
        actions.append(a)
        if a == int(Action.STOP):
            ms.update(a, AgentState(obs.position, obs.distance_to_goal))
            record(obs)
            break
        obs = backend.step(a, observe=bool(agent.needs_images and wants()))
        ms.update(a, AgentState(obs.position, obs.distance_to_goal))
        record(obs)
    _require_finite_distance(obs, episode, "ends")
    values = dict(ms.values())
    if not episode.has_goal:  # the goal's measures are n/a (None), keeping every episode's keys
        values = {m.uuid: values.get(m.uuid) for m in DEFAULT_MEASURES}
    # Recorded per episode (0/1) so the share of estimated final distances is reported, never hidden.
    values["ne_approximate"] = float(obs.distance_approximate) if episode.has_goal else None
    return EpisodeResult(episode.episode_id, values, protocol), actions


def _require_finite_distance(obs: StepObservation, episode: NavEpisode, when: str) -> None:
    """Raise :class:`RunnerError` naming the episode when the goal distance at its start / end is
    undefined (NE would be infinite; the episode is never dropped silently from the averages).
    Episodes without a goal have no distance to check."""
    if episode.has_goal and not math.isfinite(obs.distance_to_goal):
        raise RunnerError(
            f"episode {episode.episode_id}: the agent {when} at world position "
            f"{np.round(obs.position, 3).tolist()} where the geodesic distance to the goal is undefined "
            f"({obs.distance_reason or 'the backend gave no reason'}); fix the episode or the scene's "
            "navigation graph instead of dropping the episode"
        )


BACKENDS = ("neural", "exact", "habitat")
"""neural: scene folders (navmap, navgraph, Gaussians); exact: procedural captures rendered exactly;
habitat: habitat-sim on the episodes' scene files."""


@dataclass
class RunConfig:
    """One navigation evaluation run (one agent, one protocol, many scenes)."""

    agent: str = "oracle"
    """Agent registry name: random, forward, oracle, image2nav, image2nav_http."""
    agent_options: dict = field(default_factory=dict)
    """Agent constructor options (e.g. {"forward_steps": 20})."""
    seed: int = 0
    """Run seed; episode seeds derive from it and the episode id (:func:`episode_seed`)."""
    workers: int = 1
    """Scene-level processes (1 = in this process)."""
    max_episodes_per_scene: int | None = None
    """Evaluate at most this many episodes per scene (file order), None = all."""
    backend: str = "neural"
    """``neural``: scene folders ``<scenes_root>/<scene name>`` with navmap.npz + navgraph.npz;
    ``exact``: procedural captures ``<scenes_root>/<scene name>`` rendered exactly; ``habitat``:
    habitat-sim on the scene files ``<scenes_root>/<episode scene_id>``."""

    def __post_init__(self) -> None:
        if self.agent not in AGENTS:
            raise RunnerError(f"RunConfig.agent: unknown agent {self.agent!r}; known: {sorted(AGENTS)}")
        if self.backend not in BACKENDS:
            raise RunnerError(f"RunConfig.backend: expected one of {BACKENDS}, got {self.backend!r}")
        if int(self.workers) < 1:
            raise RunnerError(f"RunConfig.workers must be >= 1, got {self.workers}")
        if self.max_episodes_per_scene is not None and int(self.max_episodes_per_scene) < 1:
            raise RunnerError("RunConfig.max_episodes_per_scene must be >= 1 or None")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "run config") -> RunConfig:
        """Build from a mapping with the shared config mechanism; unknown keys, wrong types and invalid
        values are a :class:`RunnerError` naming the field."""
        try:
            return config_from_dict(cls, data)
        except ConfigError as err:
            raise RunnerError(f"{where}: {err}") from err


def _append_jsonl(path: Path, obj: Any) -> None:
    line = json.dumps(obj, separators=(",", ":")) + "\n"
    with open(path, "a", encoding="utf-8") as f:
        f.write(line)
        f.flush()
        os.fsync(f.fileno())


def _keep_trajectories_of(traj_path: Path, done: set[str]) -> None:
    """Rewrite ``traj_path`` (atomically, only when needed) to one line per logged episode.

    The trajectory line is appended just before the episode's result; a kill between the two left a
    line for an episode the resume runs again, and so a duplicate (issue 23). Torn lines go too."""
    if not traj_path.is_file():
        return
    kept, seen, changed = [], set(), False
    for line in traj_path.read_text(encoding="utf-8").splitlines(keepends=True):
        try:
            episode_id = json.loads(line)["episode_id"] if line.endswith("\n") else None
        except (json.JSONDecodeError, KeyError, TypeError):
            episode_id = None
        if episode_id in done and episode_id not in seen:
            kept.append(line)
            seen.add(episode_id)
        else:
            changed = True
    if changed:
        from image2sim.simulator.io.atomic import write_text_atomic

        write_text_atomic(traj_path, "".join(kept))


def run_scene(
    backend: Any,
    episodes: Sequence[NavEpisode],
    protocol: Protocol,
    config: RunConfig,
    log_path: str | Path,
    progress: Callable[[int], None] | None = None,
    agent: Any | None = None,
) -> int:
    """Run the scene's episodes not yet in ``log_path``; returns how many ran now.

    Each finished episode is appended (flushed + fsynced) to the JSONL log and its seed and actions
    to ``<log>.traj.jsonl``, so killing the process loses at most the episode in flight.
    """
    log = EpisodeLog(log_path, protocol)
    done = log.done_ids()
    traj_path = Path(str(log_path) + ".traj.jsonl")
    _keep_trajectories_of(traj_path, done)
    agent = agent if agent is not None else make_agent(AgentSpec(config.agent, config.agent_options))
    ran = 0
    for ep in episodes:
        if ep.episode_id in done:
            continue
        seed = episode_seed(config.seed, ep.episode_id)
        poses: list = []
        result, actions = run_episode(backend, agent, ep, protocol, seed, poses)
        line = {"episode_id": ep.episode_id, "seed": seed, "actions": actions}
        line["positions"] = [[round(float(v), 5) for v in p] for p, _ in poses]  # world, z up
        line["headings"] = [round(h, 6) for _, h in poses]  # radians about +z, 0 = +x
        _append_jsonl(traj_path, line)
        log.append(result)
        done.add(ep.episode_id)
        ran += 1
        if progress is not None:
            progress(1)
    return ran


def observation_size(config: RunConfig) -> tuple[int, int] | None:
    """The input size an image agent declares (``observation_size(options)``), if any."""
    cls = AGENTS.get(config.agent)
    get = getattr(cls, "observation_size", None)
    return get(config.agent_options) if get is not None else None


def _scene_task(task: dict) -> tuple[str, int]:
    """Worker entry point (top level so it pickles): load the scene and run its episodes (in a pool
    worker, :func:`~image2sim.simulator.lifetime.spawn_pool` has set torch to one thread)."""
    protocol = Protocol.from_dict(task["protocol"])
    config = RunConfig(**task["config"])
    if config.backend == "habitat":
        backend = HabitatBackend(task["scene_dir"], protocol)
        try:
            n = run_scene(backend, task["episodes"], protocol, config, task["log"])
        finally:
            backend.close()
        return task["scene"], n
    render = bool(getattr(AGENTS[config.agent], "needs_images", False))
    load = load_exact_backend if config.backend == "exact" else load_scene_backend
    backend = load(task["scene_dir"], protocol, render=render)
    backend.render_at(observation_size(config))
    n = run_scene(backend, task["episodes"], protocol, config, task["log"])
    return task["scene"], n


RESULT_SETTINGS = ("agent", "agent_options", "seed", "backend")
"""RunConfig fields that change an episode's result: a resumed run must keep them (``workers`` and
``max_episodes_per_scene`` only change how many episodes run and where)."""


def _refuse_resume_with_other_settings(out: Path, config: RunConfig) -> None:
    """Raise when ``out`` already logs episodes of a run with other result-changing settings: resuming
    would silently keep the old episodes and mix them with new ones."""
    previous_file = out / "run.json"
    if not previous_file.is_file() or not episode_logs(out):
        return
    _, manifest = read_result_file(previous_file)
    before = manifest.get("config", {})
    now = json.loads(json.dumps(asdict(config)))  # as run.json holds it (tuples become lists)
    changed = [
        f"{k}: logged {before.get(k)!r}, now {now[k]!r}" for k in RESULT_SETTINGS if before.get(k) != now[k]
    ]
    if changed:
        raise RunnerError(
            f"{out} already holds episodes of a run with other settings ({'; '.join(changed)}); "
            "resuming would mix them. Use another --out, or delete the folder to start over"
        )


def _refuse_goal_agent_without_goals(episodes: Sequence[NavEpisode], agent: str) -> None:
    """Raise :class:`RunnerError` before anything is written when ``agent`` needs the goal and some
    episodes have none (a test split)."""
    why = needs_goal(agent)
    goalless = [ep.episode_id for ep in episodes if not ep.has_goal]
    if why and goalless:
        raise RunnerError(
            f"agent {agent!r} cannot run on episodes without a goal ({len(goalless)} of {len(episodes)}, "
            f"e.g. episode {goalless[0]}: a test split): {why}; use an agent that does not see the goal "
            "(random, forward, image2nav)"
        )


def _group_by_scene(episodes: Iterable[NavEpisode], limit: int | None) -> dict[str, list[NavEpisode]]:
    groups: dict[str, list[NavEpisode]] = {}
    for ep in episodes:
        groups.setdefault(ep.scene_name, []).append(ep)
    if limit is not None:
        groups = {k: v[: int(limit)] for k, v in groups.items()}
    return groups


def run_nav(
    episodes: Sequence[NavEpisode],
    scenes_root: str | Path,
    protocol: Protocol,
    config: RunConfig,
    out_dir: str | Path,
    show_progress: bool = True,
) -> AggregateReport:
    """:func:`run_nav_results`, aggregated (means with episode counts)."""
    return aggregate(run_nav_results(episodes, scenes_root, protocol, config, out_dir, show_progress))


def run_nav_results(
    episodes: Sequence[NavEpisode],
    scenes_root: str | Path,
    protocol: Protocol,
    config: RunConfig,
    out_dir: str | Path,
    show_progress: bool = True,
) -> list[EpisodeResult]:
    """Evaluate ``config.agent`` on ``episodes``; scenes are looked up as ``scenes_root/<scene_name>``.

    Logs go to ``out_dir/<agent>/<scene>.jsonl`` (one per scene, so parallel workers never share a
    file) and ``out_dir/<agent>/run.json`` records the configuration and seed rule. Rerunning the
    same call resumes: finished episodes are skipped. Returns the aggregate over every episode of the
    given list (from the logs, so a resumed run aggregates exactly like an uninterrupted one).
    Returns the per-episode results of ``episodes`` read back from the logs, in scene order.
    """
    scenes_root, out = Path(scenes_root), Path(out_dir) / config.agent
    _refuse_goal_agent_without_goals(episodes, config.agent)
    out.mkdir(parents=True, exist_ok=True)
    groups = _group_by_scene(episodes, config.max_episodes_per_scene)
    if not groups:
        raise RunnerError("no episodes to evaluate")
    scene_paths = {name: scenes_root / name for name in groups}
    if config.backend == "habitat":  # habitat-sim loads the scene file the episodes name
        scene_paths = {name: scenes_root / eps[0].scene_id for name, eps in groups.items()}
    for name, path in scene_paths.items():
        if not (path.is_file() if config.backend == "habitat" else path.is_dir()):
            raise RunnerError(f"scene {name!r}: {path} not found (episodes reference it)")
    _refuse_resume_with_other_settings(out, config)
    manifest = {
        "config": asdict(config),
        "seed_rule": "episode_seed = crc32(f'{seed}:{episode_id}') & 0x7fffffff",
        "scenes": sorted(groups),
        "episodes": sum(len(v) for v in groups.values()),
    }
    write_result_file(out / "run.json", protocol, manifest)
    tasks = [
        {
            "scene": name,
            "scene_dir": str(scene_paths[name]),
            "episodes": eps,
            "protocol": protocol.to_dict(),
            "config": asdict(config),
            "log": str(out / f"{name}.jsonl"),
        }
        for name, eps in sorted(groups.items())
    ]
    total = sum(len(t["episodes"]) for t in tasks)
    bar = None
    if show_progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task_id = bar.add_task(f"{config.agent}: scenes", total=len(tasks))
    try:
        if config.workers == 1 or len(tasks) == 1:
            for t in tasks:
                _scene_task(t)
                if bar is not None:
                    bar.advance(task_id)
        else:
            from image2sim.simulator.lifetime import spawn_pool

            with spawn_pool(min(config.workers, len(tasks))) as pool:
                for _ in pool.map(_scene_task, tasks):
                    if bar is not None:
                        bar.advance(task_id)
    finally:
        if bar is not None:
            bar.stop()
    wanted = {ep.episode_id for eps in groups.values() for ep in eps}
    results: list[EpisodeResult] = []
    for t in tasks:
        _, rs = read_episode_log(t["log"])
        results += [r for r in rs if r.episode_id in wanted]
    if len(results) != total:
        raise RunnerError(f"expected {total} episode results in the logs under {out}, found {len(results)}")
    return results


# ----------------------------------------------------------------------------- episodes from a planner


def sample_point_goal_episodes(
    sim: Any, n: int, seed: int = 0, min_distance: float = 1.0, scene_id: str = "scene", max_tries: int = 2000
) -> list[NavEpisode]:
    """Point-goal episodes on a scene's navigation graph (for smoke runs when no dataset exists).

    Start and goal are navigable nodes of one connected component at least ``min_distance`` metres
    apart (geodesic); the reference path is the planner's shortest path (world frame); the heading is
    uniform. Raises :class:`RunnerError` when fewer than ``n`` such pairs are found.
    """
    from image2sim.eval.datasets import Instruction

    rng = np.random.default_rng(seed)
    graph, planner, navmap = sim.graph, sim.planner, sim.navmap
    pts = np.asarray(graph.nodes, dtype=np.float64)  # map frame
    out: list[NavEpisode] = []
    for _ in range(max_tries):
        if len(out) >= n:
            break
        i, j = rng.integers(0, len(pts), size=2)
        res = planner.shortest_path(pts[i], pts[j])
        if not res.reachable or not res.length >= min_distance:
            continue
        heading = float(rng.uniform(-math.pi, math.pi))
        ref = np.asarray(navmap.to_world(res.waypoints), dtype=np.float64).reshape(-1, 3)
        out.append(
            NavEpisode(
                episode_id=f"{scene_id}-{len(out):04d}",
                scene_id=scene_id,
                start_position=np.asarray(navmap.to_world(pts[i]), dtype=np.float64).reshape(3),
                start_rotation=np.array([math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)]),
                start_heading=heading,
                goal_position=np.asarray(navmap.to_world(pts[j]), dtype=np.float64).reshape(3),
                goal_radius=None,
                geodesic_distance=float(res.length),
                reference_path=ref,
                instruction=Instruction(text="Go to the goal."),
            )
        )
    if len(out) < n:
        raise RunnerError(
            f"{scene_id}: found only {len(out)} of {n} start/goal pairs >= {min_distance} m apart"
        )
    return out
