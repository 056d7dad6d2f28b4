"""Stage 2 of Image2Nav: online DAgger inside the :class:`~image2sim.simulator.sim.NeuralSimulator`.

One rollout alternates control in chunks: each chunk is driven by the model (probability
``p``, the *mixing probability* of the round) or by the oracle, and lasts a uniformly random number
of steps in ``[chunk_min, chunk_max]`` (4-32 by default). Every visited state is observed and
labelled with the oracle's next two actions *at that state* (the planner's shortest path from the
state, followed by pure pursuit: :class:`OracleLabeler`), whoever drives. The executed actions are
the trajectory's ``actions``; the labels go to ``extra["oracle_labels"]``, which
:func:`image2sim.navpolicy.data.make_sample` uses as targets, so DAgger data trains through the same
collator, prompt and Lightning module as behaviour cloning.

:func:`run_dagger` alternates collection and training: round ``r`` rolls out episodes with the
current policy at ``p_r`` (``constant``/``linear``/``exponential`` schedule between
``model_probability`` and ``final_model_probability``), appends them to the aggregated dataset (and
writes them as a shard under ``round_rr/shard``), then trains ``train_steps_per_round`` steps on
everything aggregated so far. Episodes end on STOP, on the step cap (``max_steps``) or when the
simulator's stuck detector fires (``stuck``); every episode is logged to ``episodes.jsonl``.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from image2sim.navpolicy.config import DaggerConfig, NavPolicyConfig, ObservationConfig
from image2sim.navpolicy.data import Trajectory
from image2sim.simulator.conventions import Action

MODEL, ORACLE = "model", "oracle"


# ----------------------------------------------------------------------------------------- mixing


def mixing_probability(cfg: DaggerConfig, round_index: int) -> float:
    """Probability that a chunk is model-controlled in ``round_index`` (0-based) of ``cfg.rounds``.

    ``constant``: ``model_probability`` always. ``linear``: straight line from ``model_probability``
    (round 0) to ``final_model_probability`` (last round). ``exponential``: geometric interpolation
    between the two (both must be > 0; a zero end falls back to linear).
    """
    p0, p1 = float(cfg.model_probability), float(cfg.final_model_probability)
    if cfg.schedule == "constant" or cfg.rounds <= 1:
        return p0
    t = min(max(round_index, 0), cfg.rounds - 1) / (cfg.rounds - 1)
    if cfg.schedule == "exponential" and p0 > 0 and p1 > 0:
        return float(p0 * (p1 / p0) ** t)
    return float(p0 + (p1 - p0) * t)


class ChunkMixer:
    """Per-step controller choice in chunks: ``next()`` returns ``"model"`` or ``"oracle"``.

    A chunk draws its controller (model with probability ``p``) and its length (uniform integer in
    ``[lo, hi]``) from ``rng``; ``chunks`` lists every drawn ``(controller, length)``.
    """

    def __init__(self, p: float, lo: int, hi: int, rng: np.random.Generator) -> None:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"mixing probability must lie in [0, 1], got {p}")
        if not 1 <= lo <= hi:
            raise ValueError(f"chunk range must satisfy 1 <= lo <= hi, got [{lo}, {hi}]")
        self.p, self.lo, self.hi, self.rng = float(p), int(lo), int(hi), rng
        self.chunks: list[tuple[str, int]] = []
        self._left = 0

    def new_chunk(self) -> tuple[str, int]:
        """Draw the next chunk (controller, length)."""
        who = MODEL if self.rng.random() < self.p else ORACLE
        n = int(self.rng.integers(self.lo, self.hi + 1))
        self.chunks.append((who, n))
        self._left = n
        return who, n

    def next(self) -> str:
        """Controller of the next step."""
        if self._left == 0:
            self.new_chunk()
        self._left -= 1
        return self.chunks[-1][0]


# ------------------------------------------------------------------------------------------ oracle


class OracleLabeler:
    """The oracle's actions at arbitrary states of one episode (stateless per query).

    ``action(state)`` plans the shortest path from ``state`` to the goal and returns the follower's
    pure-pursuit action there (a fresh :class:`OracleFollower`, so the label depends on the state
    only, never on what was executed before). ``labels(state)`` adds the second action: the
    oracle's action at the state its first action leads to (kinematics applied without stepping
    the simulator); after STOP the second label is STOP.
    """

    def __init__(self, sim, goal: np.ndarray, follower_config=None) -> None:
        from image2sim.simulator.navigation.agent import Kinematics

        self.sim = sim
        self.goal = np.asarray(goal, dtype=np.float64).reshape(3)
        self.kinematics = Kinematics(sim.world, sim.embodiment)
        self.follower_config = follower_config

    def action(self, state) -> int:
        from image2sim.simulator.navigation.follower import OracleFollower

        f = OracleFollower(self.sim.planner, self.sim.embodiment, self.follower_config, self.kinematics)
        f.reset(state.position, self.goal)
        return int(f.act(state))

    def labels(self, state) -> tuple[int, int]:
        first = self.action(state)
        if first == int(Action.STOP):
            return first, int(Action.STOP)
        nxt, _, _ = self.kinematics.apply(state, first)
        return first, self.action(nxt)


# --------------------------------------------------------------------------------------- rollouts


@dataclass
class NavTask:
    """One point-goal episode on a scene (map frame)."""

    episode_id: str
    start: np.ndarray
    """(3,) feet position."""
    heading: float
    """Start heading (radians, yaw about +Z)."""
    goal: np.ndarray
    """(3,) goal feet position."""
    instruction: str
    scene_id: str = ""


class Controller(Protocol):
    """What drives model chunks: :class:`~image2sim.navpolicy.agent.Image2NavAgent` fits."""

    def reset(self, instruction: str, seed: int = 0) -> None: ...

    def act(self, rgb: np.ndarray, executed: list[int] | None = None) -> list: ...


def render_observation(sim, obs: ObservationConfig) -> np.ndarray:
    """The policy's (H, W, 3) uint8 observation of agent 0 through ``sim.render_fn``."""
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    if sim.render_fn is None:
        raise ValueError("the simulator has no render function: DAgger needs observations")
    pose = sim.camera_pose(0)
    if obs.camera == "pinhole":
        out = sim.render_fn(PinholeCamera.from_fov(obs.hfov_deg, obs.vfov_deg, obs.height, obs.width), pose)
        rgb = np.asarray(out["rgb"], dtype=np.float32)
        return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    from image2sim.navpolicy.data import observation_from_panorama

    h = max(obs.height, obs.width // 2)
    pano = np.asarray(sim.render_fn(EquirectCamera(h, 2 * h), pose)["rgb"], dtype=np.float32)
    return observation_from_panorama(np.clip(pano * 255.0 + 0.5, 0, 255).astype(np.uint8), 0.0, obs)


@dataclass
class DaggerEpisode:
    """One mixed-control rollout: the trajectory (frames at every visited state) and its log."""

    trajectory: Trajectory
    controllers: list[str]
    """Who chose each executed action (``model`` / ``oracle``)."""
    labels: list[tuple[int, int]]
    """Oracle's next two actions at each visited state."""
    positions: np.ndarray
    """(T + 1, 3) visited feet positions (map frame)."""
    headings: np.ndarray
    """(T + 1,) headings."""
    end: str
    """``stop``, ``stuck`` (truncated by the stuck detector) or ``max_steps`` (truncated)."""
    distance_to_goal: float
    """Geodesic distance of the final position to the goal (metres)."""
    chunks: list[tuple[str, int]] = field(default_factory=list)

    def log(self) -> dict:
        steps = len(self.controllers)
        return {
            "episode_id": self.trajectory.episode_id,
            "scene_id": self.trajectory.scene_id,
            "steps": steps,
            "end": self.end,
            "truncated": self.end != "stop",
            "model_steps": sum(c == MODEL for c in self.controllers),
            "label_agreement": (
                float(
                    np.mean(
                        [a == lab[0] for a, lab in zip(self.trajectory.actions, self.labels, strict=True)]
                    )
                )
                if steps
                else None
            ),
            "distance_to_goal": self.distance_to_goal,
            "model_stop_overrides": self.trajectory.extra.get("model_stop_overrides", 0),
            "chunks": [list(c) for c in self.chunks],
        }


def dagger_rollout(
    sim,
    task: NavTask,
    controller: Controller | None,
    mixer: ChunkMixer,
    obs: ObservationConfig,
    max_steps: int = 200,
    stop_on_stuck: bool = True,
    seed: int = 0,
    follower_config=None,
    observe: Callable | None = None,
    override_model_stop: bool = False,
) -> DaggerEpisode:
    """Roll out ``task`` with control alternating between ``controller`` and the oracle.

    The controller is asked for two actions whenever it drives and its action queue is empty; it is
    told the actions executed since it last looked (oracle chunks included), so its context matches
    what :func:`make_sample` builds from the recorded trajectory. Leaving a model chunk drops the
    queued action. ``controller=None`` is allowed only with ``mixer.p == 0``. With
    ``override_model_stop`` a model STOP the oracle disagrees with executes the oracle's action
    instead (counted in ``extra["model_stop_overrides"]``).
    """
    if controller is None and mixer.p > 0:
        raise ValueError("dagger_rollout: a model probability > 0 needs a controller")
    observe = observe or (lambda s: render_observation(s, obs))
    labeler = OracleLabeler(sim, task.goal, follower_config)
    _, info = sim.reset(np.asarray(task.start, float)[None], np.array([task.heading]), observe=False)
    if controller is not None:
        controller.reset(task.instruction, seed=seed)
    frames, actions, labels, who = [], [], [], []
    positions, headings = [info["position"][0].copy()], [float(info["heading"][0])]
    queue: list[int] = []
    executed: list[int] | None = None  # None until the controller has seen its first frame
    end, overrides = "max_steps", 0
    for _ in range(max_steps):
        state = sim.agents[0].state.copy()
        rgb = observe(sim)
        lab = labeler.labels(state)
        c = mixer.next()
        if c == MODEL:
            if not queue:
                queue = [int(a) for a in controller.act(rgb, executed=executed)]
                executed = []
            a = queue.pop(0)
            if override_model_stop and a == int(Action.STOP) and lab[0] != int(Action.STOP):
                a, queue, overrides = lab[0], [], overrides + 1
        else:
            queue = []
            a = lab[0]
        frames.append(rgb)
        actions.append(a)
        labels.append(lab)
        who.append(c)
        if executed is not None:
            executed.append(a)
        _, info = sim.step([a], observe=False)
        positions.append(info["position"][0].copy())
        headings.append(float(info["heading"][0]))
        if a == int(Action.STOP):
            end = "stop"
            break
        if stop_on_stuck and bool(info["stuck"][0]):
            end = "stuck"
            break
    dist = float(sim.planner.distance_field(task.goal)(positions[-1]))
    traj = Trajectory(
        instruction=task.instruction,
        actions=actions,
        frames=np.stack(frames),
        frame_steps=list(range(len(actions))),
        episode_id=task.episode_id,
        scene_id=task.scene_id,
        extra={
            "oracle_labels": [list(x) for x in labels],
            "controllers": who,
            "end": end,
            "model_stop_overrides": overrides,
            "start": [float(v) for v in task.start],
            "heading": float(task.heading),
            "goal": [float(v) for v in task.goal],
        },
    ).validate(f"dagger episode {task.episode_id}")
    return DaggerEpisode(
        traj, who, labels, np.array(positions), np.array(headings), end, dist, list(mixer.chunks)
    )


# ------------------------------------------------------------------------------------------ tasks


def goal_instruction(start: np.ndarray, heading: float, goal: np.ndarray) -> str:
    """An egocentric point-goal instruction (the goal relative to the start pose, metres)."""
    d = np.asarray(goal, float)[:2] - np.asarray(start, float)[:2]
    c, s = math.cos(heading), math.sin(heading)
    ahead, left = c * d[0] + s * d[1], -s * d[0] + c * d[1]
    fb = f"{abs(ahead):.1f} m {'ahead' if ahead >= 0 else 'behind you'}"
    lr = f"{abs(left):.1f} m to the {'left' if left >= 0 else 'right'}"
    return f"Go to the point {fb} and {lr}, then stop."


def sample_tasks(
    sim,
    n: int,
    rng: np.random.Generator,
    min_distance: float = 1.0,
    scene_id: str = "scene",
    max_tries: int = 5000,
) -> list[NavTask]:
    """``n`` start/goal pairs on graph nodes of one component, at least ``min_distance`` apart
    (geodesic), with uniform start headings; raises ``ValueError`` if too few are found."""
    nodes = np.asarray(sim.graph.nodes, dtype=np.float64)
    out: list[NavTask] = []
    for _ in range(max_tries):
        if len(out) >= n:
            break
        i, j = rng.integers(0, len(nodes), size=2)
        d, _ = sim.planner.geodesic_distance(nodes[i], nodes[j])
        if not (math.isfinite(d) and d >= min_distance):
            continue
        h = float(rng.uniform(-math.pi, math.pi))
        out.append(
            NavTask(
                f"{scene_id}-{len(out):04d}",
                nodes[i],
                h,
                nodes[j],
                goal_instruction(nodes[i], h, nodes[j]),
                scene_id,
            )
        )
    if len(out) < n:
        raise ValueError(
            f"{scene_id}: found only {len(out)} of {n} start/goal pairs >= {min_distance} m apart"
        )
    return out


def procedural_simulator(seed: int = 0, preset: str = "tiny", embodiment=None):
    """A :class:`NeuralSimulator` on a procedural scene of the data engine (exact renderer).

    The embedded default data source: no files needed. Imports :mod:`image2sim.dataengine` lazily.
    """
    from image2sim.dataengine.procedural import capture_frames, generate_scene
    from image2sim.dataengine.procedural import preset as synth_preset
    from image2sim.dataengine.procedural.render import render
    from image2sim.simulator.navigation import NavGraph, NavMapConfig, extract_navmap
    from image2sim.simulator.sim import NeuralSimulator

    scene = generate_scene(synth_preset(preset), seed=seed)
    frames, _ = capture_frames(scene)
    navmap = extract_navmap(frames, embodiment, NavMapConfig(floor_labels=(1, 10)))

    def render_fn(camera, pose):
        out = render(scene, camera, np.asarray(pose))
        return {"rgb": out["rgb"].astype(np.float32) / 255.0, "depth": out["depth"]}

    return NeuralSimulator(navmap, NavGraph.build(navmap), render_fn)


# ------------------------------------------------------------------------------------ the loop


@dataclass
class DaggerScene:
    """A simulator (with a render function) and the tasks to draw episodes from."""

    sim: object
    tasks: list[NavTask]
    name: str = "scene"


@dataclass
class DaggerResult:
    out_dir: Path
    episodes: list[dict]
    """Per-episode logs (also in ``episodes.jsonl``)."""
    dataset_sizes: list[int]
    """Aggregated trajectories after each round."""
    losses: list[list[float]]
    """Training losses per round."""
    export_dir: Path | None
    seen: list[list[str]] = field(default_factory=list)
    """Episode ids trained on in each round (flattened over batches)."""


def _append_jsonl(path: Path, rec: dict) -> None:
    # Append-only log: one line per finished episode, flushed so a crash keeps what was logged.
    with open(path, "a") as fh:
        fh.write(json.dumps(rec) + "\n")
        fh.flush()


def run_dagger(
    cfg: NavPolicyConfig,
    scenes: Sequence[DaggerScene],
    out_dir: str | Path,
    policy=None,
    base_trajectories: Sequence[Trajectory] = (),
    export: bool = True,
) -> DaggerResult:
    """Online DAgger: per round, collect ``episodes_per_round`` mixed rollouts with the current
    policy, add them to the aggregated dataset, train on it; finally export the merged weights.

    Args:
        cfg: run config (``cfg.dagger`` for the loop, ``cfg.train`` for the optimiser settings).
        scenes: where episodes come from (tasks are drawn round-robin over scenes, shuffled by seed).
        out_dir: run folder: ``episodes.jsonl``, ``round_rr/shard`` (collected data), ``round_rr/train``;
            an earlier run's rounds and log there are replaced.
        policy: the policy to improve (e.g. the BC export); default a fresh one from ``cfg``.
        base_trajectories: trajectories the aggregated dataset starts with (BC data).
    """
    from image2sim.navpolicy.agent import Image2NavAgent
    from image2sim.navpolicy.data import InMemoryNavDataset, ShardWriter
    from image2sim.navpolicy.model import build_policy, export_policy
    from image2sim.navpolicy.train import train_bc
    from rich.progress import Progress

    dc = cfg.dagger
    if not scenes or not any(s.tasks for s in scenes):
        raise ValueError("run_dagger: no scenes with tasks")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from image2sim.simulator.config import save_config

    save_config(cfg, out / "config.yaml")
    log_path = out / "episodes.jsonl"
    # A run starts from scratch (no resume): clear what an earlier run left in this folder.
    log_path.unlink(missing_ok=True)
    for stale in out.glob("round_*"):
        shutil.rmtree(stale)
    policy = policy or build_policy(cfg, seed=cfg.train.seed)
    pool = [(s, t) for s in scenes for t in s.tasks]
    order = np.random.default_rng([dc.seed, 1]).permutation(len(pool))
    aggregated = list(base_trajectories)
    logs, sizes, losses, seen = [], [], [], []
    k = 0
    for r in range(dc.rounds):
        p = mixing_probability(dc, r)
        policy.model.eval()
        agent = Image2NavAgent(policy, cfg.agent, cfg.system_prompt)
        collected = []
        # One progress display per collection phase: Lightning shows its own bar while training.
        with Progress(transient=True) as progress:
            bar = progress.add_task(f"DAgger round {r} rollouts (p={p:.2f})", total=dc.episodes_per_round)
            for e in range(dc.episodes_per_round):
                scene, task = pool[order[k % len(pool)]]
                k += 1
                mixer = ChunkMixer(p, dc.chunk_min, dc.chunk_max, np.random.default_rng([dc.seed, r, e]))
                ep = dagger_rollout(
                    scene.sim,
                    task,
                    agent,
                    mixer,
                    cfg.observation,
                    dc.max_steps,
                    dc.stop_on_stuck,
                    seed=e,
                    override_model_stop=dc.override_model_stop,
                )
                ep.trajectory.episode_id = f"r{r:02d}-{task.episode_id}"
                rec = {"round": r, "model_probability": p, **ep.log()}
                _append_jsonl(log_path, rec)
                logs.append(rec)
                collected.append(ep.trajectory)
                progress.advance(bar)
        with ShardWriter(out / f"round_{r:02d}" / "shard", {**cfg.observation.__dict__}) as w:
            for t in collected:
                w.add(t)
        aggregated.extend(collected)
        sizes.append(len(aggregated))
        if dc.train_steps_per_round > 0:
            rc = copy.deepcopy(cfg)
            rc.train.max_steps = dc.train_steps_per_round
            rc.train.seed = cfg.train.seed + r
            rc.train.checkpoint_every = max(rc.train.checkpoint_every, dc.train_steps_per_round)
            ds = InMemoryNavDataset(
                aggregated,
                cfg.data.max_observations,
                cfg.data.max_action_labels,
                cfg.data.jitter,
                rc.train.seed,
            )
            res = train_bc(rc, out / f"round_{r:02d}" / "train", dataset=ds, export=False, policy=policy)
            losses.append(list(res.module.losses))
            seen.append([i for batch in res.module.seen for i in batch])
        else:
            losses.append([])
            seen.append([])
    export_dir = export_policy(policy, out / "export") if export else None
    summary = {"dataset_sizes": sizes, "losses": losses, "episodes": len(logs)}
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(out / "summary.json")
    return DaggerResult(out, logs, sizes, losses, export_dir, seen)


def procedural_scenes(
    n_scenes: int, tasks_per_scene: int, seed: int = 0, preset: str = "tiny", min_distance: float = 1.0
) -> list[DaggerScene]:
    """``n_scenes`` procedural scenes (seeds ``seed..seed+n-1``) with sampled point-goal tasks."""
    out = []
    for i in range(n_scenes):
        sim = procedural_simulator(seed + i, preset)
        name = f"procedural-{preset}-{seed + i:03d}"
        tasks = sample_tasks(sim, tasks_per_scene, np.random.default_rng([seed, i]), min_distance, name)
        out.append(DaggerScene(sim, tasks, name))
    return out
