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

A run is resumable: every collected episode is saved as soon as it ends, ``dagger_state.json``
records the round, phase, task cursor, shards, logs, losses and RNG states, each round's training
writes Lightning checkpoints (model + optimizer + scheduler) every ``train.checkpoint_every`` steps,
and the weights after each round go to ``checkpoints/round_rr.safetensors``. Running again with the
same arguments continues without re-collecting or losing an episode (see :func:`run_dagger`).
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from image2sim.navpolicy.config import DaggerConfig, NavPolicyConfig, ObservationConfig
from image2sim.navpolicy.data import Trajectory
from image2sim.navpolicy.rollout_scenes import NavTask, RolloutScene, render_observation
from image2sim.simulator.conventions import Action
from image2sim.simulator.io.atomic import atomic_path, write_text_atomic

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
    """The oracle's actions at arbitrary states of one episode.

    Point-goal episodes (no reference path) are labelled statelessly: ``action(state)`` plans the
    shortest path from ``state`` to the goal and returns the follower's pure-pursuit action there (a
    fresh :class:`OracleFollower`, so the label depends on the state only, never on what was
    executed before). ``labels(state)`` adds the second action: the oracle's action at the state
    its first action leads to (kinematics applied without stepping the simulator); after STOP the
    second label is STOP. Instruction episodes (a reference path) are labelled by the episode's
    :class:`ReferencePathFollower` (see :meth:`labels`).
    """

    def __init__(self, sim, goal: np.ndarray, follower_config=None, reference_path=None) -> None:
        from image2sim.simulator.navigation.agent import Kinematics

        self.sim = sim
        self.goal = np.asarray(goal, dtype=np.float64).reshape(3)
        self.kinematics = Kinematics(sim.world, sim.embodiment)
        self.follower_config = follower_config
        self.reference_path = None if reference_path is None else np.asarray(reference_path, np.float64)
        self._follower = None

    def action(self, state) -> int:
        """The shortest-path oracle's action at ``state`` (a fresh plan: depends on the state only)."""
        from image2sim.simulator.navigation.follower import OracleFollower

        f = OracleFollower(self.sim.planner, self.sim.embodiment, self.follower_config, self.kinematics)
        f.reset(state.position, self.goal)
        return int(f.act(state))

    def _reference_follower(self, state):
        from image2sim.simulator.navigation.follower import ReferencePathFollower

        if self._follower is None:
            self._follower = ReferencePathFollower(
                self.sim.planner,
                self.reference_path,
                self.sim.embodiment,
                self.follower_config,
                self.kinematics,
            )
            self._follower.reset(np.asarray(state.position, np.float64), self.goal)
        return self._follower

    def labels(self, state) -> tuple[int, int]:
        """The oracle's next two actions at ``state``.

        Without a reference path: the shortest-path oracle, planned afresh at each state. With one:
        one :class:`ReferencePathFollower` per episode, queried at every visited state; it keeps its
        plan while the agent stays within ``replan_distance`` of it and rejoins the reference path
        (never behind the progress made) when the agent has left it. Its plan is the expensive part,
        so it is not redone per state; the second label asks a copy, so the lookahead leaves the
        episode's follower untouched.
        """
        if self.reference_path is None:
            first = self.action(state)
            if first == int(Action.STOP):
                return first, int(Action.STOP)
            nxt, _, _ = self.kinematics.apply(state, first)
            return first, self.action(nxt)
        f = self._reference_follower(state)
        first = int(f.act(state))
        if first == int(Action.STOP):
            return first, int(Action.STOP)
        nxt, _, _ = self.kinematics.apply(state, first)
        look = copy.copy(f)
        look._blocked_at = list(f._blocked_at)
        return first, int(look.act(nxt))


# --------------------------------------------------------------------------------------- rollouts


class Controller(Protocol):
    """What drives model chunks: :class:`~image2sim.navpolicy.agent.Image2NavAgent` fits."""

    def reset(self, instruction: str, seed: int = 0) -> None: ...

    def act(self, rgb: np.ndarray, executed: list[int] | None = None) -> list: ...


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
    observe_every: int = 1,
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
    labeler = OracleLabeler(sim, task.goal, follower_config, task.reference_path)
    _, info = sim.reset(np.asarray(task.start, float)[None], np.array([task.heading]), observe=False)
    sim.set_goal(sim.navmap.to_world(np.asarray(task.goal, float).reshape(3)))
    if controller is not None:
        controller.reset(task.instruction, seed=seed)
    frames, frame_steps, actions, labels, who = [], [], [], [], []
    positions, headings = [info["position"][0].copy()], [float(info["heading"][0])]
    queue: list[int] = []
    executed: list[int] | None = None  # None until the controller has seen its first frame
    end, overrides = "max_steps", 0
    for t in range(max_steps):
        state = sim.agents[0].state.copy()
        lab = labeler.labels(state)
        c = mixer.next()
        rgb = None
        if t % max(int(observe_every), 1) == 0 or (c == MODEL and not queue):
            rgb = observe(sim)
            frames.append(rgb)
            frame_steps.append(t)
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
        frame_steps=frame_steps,
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


# ------------------------------------------------------------------------------------ the loop


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


STATE_FILE = "dagger_state.json"
STATE_VERSION = 1


def run_fingerprint(
    cfg: NavPolicyConfig, scenes: Sequence[RolloutScene], base_trajectories, model=None
) -> str:
    """Hash of what defines a DAgger run (config, scenes' tasks, the BC data's episodes and the
    starting weights of ``model``): a resumed run must present the same, or its state is not reused
    (e.g. a retrained BC export at the same path starts a new DAgger run)."""
    h = hashlib.sha256(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode())
    if model is not None:
        import torch

        for name, t in sorted(model.state_dict().items()):
            h.update(name.encode())
            h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    for s in scenes:
        for t in s.tasks:
            rec = [s.name, t.episode_id, [float(v) for v in t.start], float(t.heading)]
            rec += [[float(v) for v in t.goal], t.instruction]
            if t.reference_path is not None:
                rec.append(np.round(np.asarray(t.reference_path, float), 4).tolist())
            h.update(json.dumps(rec).encode())
    h.update(json.dumps([[t.episode_id, len(t.actions)] for t in base_trajectories]).encode())
    return h.hexdigest()


def rng_states() -> dict:
    """Python, NumPy (legacy global) and torch CPU generator states as JSON-safe data."""
    import random

    import torch

    py = random.getstate()
    name, keys, pos, has_gauss, gauss = np.random.get_state()
    return {
        "python": [py[0], list(py[1]), py[2]],
        "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(gauss)],
        "torch": torch.get_rng_state().tolist(),
    }


def set_rng_states(states: dict) -> None:
    """Restore what :func:`rng_states` captured."""
    import random

    import torch

    py = states["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    name, keys, pos, has_gauss, gauss = states["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(torch.tensor(states["torch"], dtype=torch.uint8))


def _read_shard(root: Path) -> list[Trajectory]:
    from image2sim.navpolicy.data import ShardReader

    reader = ShardReader(root)
    return [reader[i] for i in range(len(reader))]


def _load_state(path: Path, fingerprint: str) -> dict | None:
    if not path.is_file():
        return None
    try:
        state = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable DAgger state ({exc}); remove it or start fresh") from exc
    if state.get("version") != STATE_VERSION:
        raise ValueError(f"{path}: DAgger state version {state.get('version')} is not {STATE_VERSION}")
    if state.get("fingerprint") != fingerprint:
        raise ValueError(
            f"{path}: written by a DAgger run with other arguments (config, scenes, tasks, BC data or "
            "starting weights); "
            "resume with the same arguments, use another output folder, or start fresh (--fresh)"
        )
    return state


def _pending_episodes(folder: Path) -> tuple[list[Trajectory], list[dict]]:
    """The episodes of an interrupted collection phase: ``eNNN/`` shards whose ``eNNN.json`` log
    exists (written last), contiguous from 0; anything after the first gap is removed."""
    trajs, logs = [], []
    e = 0
    while (folder / f"e{e:04d}.json").is_file() and (folder / f"e{e:04d}" / "manifest.json").is_file():
        logs.append(json.loads((folder / f"e{e:04d}.json").read_text()))
        trajs.extend(_read_shard(folder / f"e{e:04d}"))
        e += 1
    if folder.is_dir():
        for p in folder.iterdir():
            stem = p.name.split(".")[0]
            if not (stem.startswith("e") and stem[1:].isdigit() and int(stem[1:]) < e):
                shutil.rmtree(p) if p.is_dir() else p.unlink()
    return trajs, logs


def run_dagger(
    cfg: NavPolicyConfig,
    scenes: Sequence[RolloutScene],
    out_dir: str | Path,
    policy=None,
    base_trajectories: Sequence[Trajectory] = (),
    export: bool = True,
    resume: bool = True,
) -> DaggerResult:
    """Online DAgger: per round, collect ``episodes_per_round`` mixed rollouts with the current
    policy, add them to the aggregated dataset, train on it; finally export the merged weights.

    Resumable: ``dagger_state.json`` (written atomically after every episode phase and round)
    holds the round, the phase (collect / train), the task cursor, the finished rounds' shards,
    episode logs, losses and the RNG states; ``checkpoints/round_rr.safetensors`` the weights after
    round ``r``; a round's training writes Lightning checkpoints (model + optimizer + scheduler +
    loss history) every ``train.checkpoint_every`` steps; each collected episode is saved at once
    (``round_rr/episodes/eNNN``). Calling again with the same arguments continues where the
    previous call stopped, without re-collecting or losing an episode; a completed run returns its
    recorded result (and exports again).

    Args:
        cfg: run config (``cfg.dagger`` for the loop, ``cfg.train`` for the optimiser settings).
        scenes: where episodes come from (tasks are drawn round-robin over scenes, shuffled by seed).
        out_dir: run folder: ``episodes.jsonl``, ``round_rr/shard`` (collected data), ``round_rr/train``,
            ``checkpoints/``, ``dagger_state.json``, ``summary.json``, ``export/``.
        policy: the policy to improve (e.g. the BC export); default a fresh one from ``cfg``. On a
            resume pass the same starting policy: the saved weights replace it.
        base_trajectories: trajectories the aggregated dataset starts with (BC data).
        resume: continue the run recorded in ``out_dir`` (its arguments must match, else
            ``ValueError``); False discards it and starts over.
    """
    from image2sim.navpolicy.agent import Image2NavAgent
    from image2sim.navpolicy.data import InMemoryNavDataset, ShardWriter, sample_options
    from image2sim.navpolicy.model import build_policy, export_policy, tokenizer_corpus
    from image2sim.navpolicy.train import train_bc
    from image2sim.simulator.config import save_config
    from rich.progress import Progress
    from safetensors.torch import load_model, save_model

    dc = cfg.dagger
    if not scenes or not any(s.tasks for s in scenes):
        raise ValueError("run_dagger: no scenes with tasks")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state_path, log_path = out / STATE_FILE, out / "episodes.jsonl"
    policy = policy or build_policy(cfg, seed=cfg.train.seed, corpus=tokenizer_corpus(cfg))
    fingerprint = run_fingerprint(cfg, scenes, base_trajectories, policy.model)
    state = _load_state(state_path, fingerprint) if resume else None
    if state is None:  # a fresh run: clear what an earlier run left in this folder
        state_path.unlink(missing_ok=True)
        log_path.unlink(missing_ok=True)
        for stale in [*out.glob("round_*"), out / "checkpoints"]:
            if stale.is_dir():
                shutil.rmtree(stale)
        state = {
            "version": STATE_VERSION,
            "fingerprint": fingerprint,
            "round": 0,
            "phase": "collect",
            "next_task": 0,
            "weights": None,
            "shards": [],
            "episodes": [],
            "dataset_sizes": [],
            "losses": [],
            "seen": [],
        }
    else:
        set_rng_states(state["rng"])
    save_config(cfg, out / "config.yaml")
    if state["weights"]:
        load_model(policy.model, str(out / state["weights"]))

    def commit() -> None:
        state["rng"] = rng_states()
        write_text_atomic(state_path, json.dumps(state))

    pool = [(s, t) for s in scenes for t in s.tasks]
    order = np.random.default_rng([dc.seed, 1]).permutation(len(pool))
    aggregated = list(base_trajectories)
    for rel in state["shards"]:
        aggregated.extend(_read_shard(out / rel))
    while state["round"] < dc.rounds:
        r = state["round"]
        rdir = out / f"round_{r:02d}"
        p = mixing_probability(dc, r)
        if state["phase"] == "collect":
            pending = rdir / "episodes"
            collected, logs = _pending_episodes(pending)
            # The log is a view of the saved episodes: rebuild it (drops lines of unsaved ones).
            write_text_atomic(log_path, "".join(json.dumps(x) + "\n" for x in state["episodes"] + logs))
            policy.model.eval()
            agent = Image2NavAgent(policy, cfg.agent, cfg.system_prompt)
            # One progress display per collection phase: Lightning shows its own bar while training.
            with Progress(transient=True) as progress:
                bar = progress.add_task(
                    f"DAgger round {r} rollouts (p={p:.2f})", total=dc.episodes_per_round, completed=len(logs)
                )
                for e in range(len(logs), dc.episodes_per_round):
                    scene, task = pool[order[(state["next_task"] + e) % len(pool)]]
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
                        observe_every=dc.observe_every,
                    )
                    ep.trajectory.episode_id = f"r{r:02d}-{task.episode_id}"
                    rec = {"round": r, "model_probability": p, **ep.log()}
                    with ShardWriter(pending / f"e{e:04d}", {**cfg.observation.__dict__}) as w:
                        w.add(ep.trajectory)
                    write_text_atomic(pending / f"e{e:04d}.json", json.dumps(rec))  # episode saved
                    _append_jsonl(log_path, rec)
                    collected.append(ep.trajectory)
                    logs.append(rec)
                    progress.advance(bar)
            shard = rdir / "shard"
            if shard.exists():  # a half-written shard of an interrupted merge
                shutil.rmtree(shard)
            with ShardWriter(shard, {**cfg.observation.__dict__}) as w:
                for t in collected:
                    w.add(t)
            # Train on what the shard holds, so a resumed run sees exactly the same data.
            aggregated.extend(_read_shard(shard))
            state["shards"].append(str(shard.relative_to(out)))
            state["episodes"].extend(logs)
            state["dataset_sizes"].append(len(aggregated))
            state["next_task"] += dc.episodes_per_round
            state["phase"] = "train"
            commit()
            shutil.rmtree(pending, ignore_errors=True)
        shutil.rmtree(rdir / "episodes", ignore_errors=True)  # merged into the shard already
        if dc.train_steps_per_round > 0:
            rc = copy.deepcopy(cfg)
            rc.train.max_steps = dc.train_steps_per_round
            rc.train.lr = cfg.train.lr if dc.lr is None else dc.lr
            rc.train.seed = cfg.train.seed + r
            rc.train.checkpoint_every = max(1, min(rc.train.checkpoint_every, dc.train_steps_per_round))
            ds = InMemoryNavDataset(aggregated, seed=rc.train.seed, **sample_options(cfg))
            tdir = rdir / "train"
            last = tdir / "checkpoints" / "last.ckpt"
            res = train_bc(
                rc, tdir, dataset=ds, export=False, policy=policy, resume="last" if last.exists() else None
            )
            state["losses"].append(list(res.module.losses))
            state["seen"].append([i for batch in res.module.seen for i in batch])
            weights = out / "checkpoints" / f"round_{r:02d}.safetensors"
            weights.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(weights) as tmp:
                save_model(policy.model, str(tmp))
            state["weights"] = str(weights.relative_to(out))
        else:
            state["losses"].append([])
            state["seen"].append([])
        state["round"], state["phase"] = r + 1, "collect"
        commit()
    data = [*cfg.data.shards, *(out / rel for rel in state["shards"])]  # BC shards + the rounds'
    export_dir = export_policy(policy, out / "export", cfg, data=data) if export else None
    sizes, losses = state["dataset_sizes"], state["losses"]
    summary = {"dataset_sizes": sizes, "losses": losses, "episodes": len(state["episodes"])}
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2))
    return DaggerResult(out, list(state["episodes"]), sizes, losses, export_dir, state["seen"])
