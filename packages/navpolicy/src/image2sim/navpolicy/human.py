"""Human instruction annotations (R2R-CE / RxR-CE) rolled out in simulators of captured scenes.

The paper's "base" training rows (Table 3) mix human-annotated instructions with generated data. The
human episodes come as VLN-CE files (:mod:`image2sim.eval.datasets` reads them into our Z-up world);
:func:`shard_from_episodes` turns them into Image2Nav training shards:

1. the episodes are grouped by scene (``<scenes_root>/<scene_id stem>``) and each scene's simulator
   is opened once (:func:`~image2sim.navpolicy.rollout_scenes.scene_simulator`: ``neural``, ``splat_only``
   or ``exact`` observations);
2. per episode, the :class:`~image2sim.simulator.navigation.follower.ReferencePathFollower` drives
   the agent from the episode's start pose along its dense ground-truth route (``gt_locations``) or,
   without one, its reference path, with the simulator's kinematics, and STOPs at the route's end;
3. an episode whose follower does not get there is skipped and counted with its reason
   (``start_not_navigable``, ``unreachable``, ``stopped_away``, ``stuck``, ``max_steps``,
   ``replay_mismatch``, ``missing_scene``); none is dropped silently;
4. the kept actions are replayed with rendering on at every ``frame_stride``-th step (the data
   engine's :func:`~image2sim.dataengine.frames.observation_steps`) and written, with the human
   instruction, as one shard (format ``image2sim-navshard`` v1), atomically: into a temp folder beside
   the target that is renamed into place at the end.

Each trajectory's ``extra`` records ``source``, ``dataset``, ``end_distance_m`` (horizontal distance
of the final position to the route's end), ``route`` (``gt_locations`` or ``reference_path``) and the
episode's start pose. The shard mixes with generated shards in behaviour cloning by sample ratios
(``data.shard_weights``, ``nav train --shard-weight``).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from image2sim.navpolicy.config import ObservationConfig
from image2sim.navpolicy.data import ShardWriter, Trajectory
from image2sim.simulator.conventions import Action
from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling, write_text_atomic

__all__ = ["SKIP_REASONS", "ReferenceRollout", "follow_reference", "shard_from_episodes"]

SKIP_REASONS = (
    "missing_scene",
    "start_not_navigable",
    "unreachable",
    "stopped_away",
    "stuck",
    "max_steps",
    "replay_mismatch",
)
"""Why an episode is not converted: its scene folder is absent (with ``missing_scenes="skip"``), the
agent cannot stand at its start, the planner finds no path from the start to the route, the follower
stopped farther than ``end_tolerance`` from the route's end (it lost the route on the way), the
simulator's stuck detector fired, the step cap was reached, or replaying the actions did not end where
the rollout did."""


@dataclass
class ReferenceRollout:
    """The oracle's rollout of one episode along its route (map frame)."""

    actions: list[int]
    """Executed action ids; the last is STOP when the follower finished."""
    positions: np.ndarray
    """(T + 1, 3) feet positions: row t before action t, the last row the final state."""
    headings: np.ndarray
    """(T + 1,) headings (radians)."""
    end: str
    """``stop``, ``stuck``, ``max_steps``, or ``start_not_navigable`` / ``unreachable`` (no step)."""
    end_distance: float
    """Horizontal distance (metres) of the final position to the route's end."""
    collisions: int = 0
    """Forward steps the kinematics blocked (wall sliding)."""
    detail: str = ""
    """Why the rollout failed, in words (empty on success)."""


def follow_reference(sim, task, max_steps: int = 500, follower_config=None) -> ReferenceRollout:
    """Drive agent 0 of ``sim`` from ``task.start`` along ``task.reference_path`` (map frame) with the
    :class:`ReferencePathFollower` and the simulator's kinematics until it STOPs at the route's end,
    the stuck detector fires or ``max_steps`` actions were taken. No observation is rendered."""
    from image2sim.simulator.navigation.agent import Kinematics
    from image2sim.simulator.navigation.follower import ReferencePathFollower

    route = task.reference_path
    if route is None or len(route) == 0:
        route = np.asarray(task.goal, np.float64).reshape(1, 3)
    route = np.asarray(route, np.float64)
    start = np.asarray(task.start, np.float64).reshape(3)
    try:
        _, info = sim.reset(start[None], np.array([task.heading]), observe=False)
    except ValueError as exc:
        d = float(np.linalg.norm(start[:2] - route[-1, :2]))
        return ReferenceRollout(
            [], start[None], np.array([task.heading]), "start_not_navigable", d, detail=str(exc)
        )
    positions, headings = [info["position"][0].copy()], [float(info["heading"][0])]
    follower = ReferencePathFollower(
        sim.planner, route, sim.embodiment, follower_config, Kinematics(sim.world, sim.embodiment)
    )
    plan = follower.reset(positions[0])
    if not plan.reachable:
        d = float(np.linalg.norm(positions[0][:2] - route[-1, :2]))
        return ReferenceRollout(
            [], np.array(positions), np.array(headings), "unreachable", d, detail=plan.reason
        )
    actions: list[int] = []
    collided, collisions, end = False, 0, "max_steps"
    for _ in range(int(max_steps)):
        a = int(follower.act(sim.agents[0].state, collided))
        _, info = sim.step([a], observe=False)
        actions.append(a)
        positions.append(info["position"][0].copy())
        headings.append(float(info["heading"][0]))
        collided = bool(info["collided"][0])
        collisions += int(collided)
        if a == int(Action.STOP):
            end = "stop"
            break
        if bool(info["stuck"][0]):
            end = "stuck"
            break
    d = float(np.linalg.norm(positions[-1][:2] - route[-1, :2]))
    return ReferenceRollout(actions, np.array(positions), np.array(headings), end, d, collisions)


def _skip_reason(r: ReferenceRollout, end_tolerance: float) -> str:
    if r.end in ("start_not_navigable", "unreachable", "stuck", "max_steps"):
        return r.end
    if r.end_distance > end_tolerance:
        return "stopped_away"
    return ""


def _render_replay(sim, task, actions, steps, obs: ObservationConfig):
    """Re-execute ``actions`` from the task's start, rendering the observation at ``steps``; returns
    (frames, final position)."""
    from image2sim.navpolicy.rollout_scenes import render_observation

    wanted = set(steps)
    sim.reset(np.asarray(task.start, np.float64)[None], np.array([task.heading]), observe=False)
    frames = []
    for t, a in enumerate(actions):
        if t in wanted:
            frames.append(render_observation(sim, obs))
        sim.step([int(a)], observe=False)
    return np.stack(frames), sim.agents[0].state.position.copy()


def _episode_extra(ep, source: str, dataset: str, route: str, r: ReferenceRollout) -> dict:
    extra = {
        "source": source,
        "dataset": dataset,
        "end_distance_m": round(float(r.end_distance), 4),
        "route": route,
        "episode_scene_id": ep.scene_id,
        "start": [float(v) for v in np.asarray(ep.start_position, float)],
        "heading": float(ep.start_heading),
        "collisions": int(r.collisions),
    }
    if getattr(ep, "trajectory_id", None) is not None:
        extra["trajectory_id"] = ep.trajectory_id
    if getattr(ep, "role", None) is not None:
        extra["role"] = ep.role
    for key in ("instruction_id", "language"):
        value = getattr(ep.instruction, key, None)
        if value is not None:
            extra[key] = value
    return extra


@dataclass
class _Options:
    source: str
    dataset: str
    observation: ObservationConfig
    frame_stride: int
    max_steps: int
    end_tolerance: float
    follower_config: object = None


def _convert(sim, ep, task, o: _Options) -> Trajectory | tuple[str, str]:
    """One episode as a trajectory, or ``(skip reason, detail)``."""
    from image2sim.dataengine.frames import observation_steps

    r = follow_reference(sim, task, o.max_steps, o.follower_config)
    reason = _skip_reason(r, o.end_tolerance)
    if reason:
        return reason, r.detail or (
            f"ended {r.end_distance:.2f} m from the route's end after {len(r.actions)} steps"
        )
    steps = observation_steps(len(r.actions), o.frame_stride)
    frames, final = _render_replay(sim, task, r.actions, steps, o.observation)
    if np.abs(final - r.positions[-1]).max() > 1e-6:
        return "replay_mismatch", "replaying the actions ended elsewhere than the rollout"
    route = "gt_locations" if getattr(ep, "gt_locations", None) is not None else "reference_path"
    return Trajectory(
        instruction=ep.instruction.text,
        actions=list(r.actions),
        frames=frames,
        frame_steps=steps,
        episode_id=str(ep.episode_id),
        scene_id=task.scene_id,
        extra=_episode_extra(ep, o.source, o.dataset, route, r),
    )


def shard_from_episodes(
    episodes,
    scenes_root: str | Path,
    out_dir: str | Path,
    source: str = "neural",
    renderer=None,
    observation: ObservationConfig | None = None,
    frame_stride: int = 2,
    max_steps: int = 500,
    *,
    dataset: str | None = None,
    end_tolerance: float = 0.5,
    follower_config=None,
    missing_scenes: str = "error",
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Roll out instruction episodes along their routes and write them as one training shard.

    Args:
        episodes: :class:`~image2sim.eval.datasets.NavEpisode` records (world frame), or an
            ``EpisodeDataset`` (its ``name`` becomes the default ``dataset``).
        scenes_root: folder of scene folders named by the episodes' ``scene_id`` stem.
        out_dir: the shard folder to write (published atomically at the end).
        source: ``neural`` (built scenes + ``renderer``), ``splat_only`` or ``exact`` (procedural
            captures rendered exactly), as in :func:`~image2sim.navpolicy.rollout_scenes.scene_simulator`.
        renderer: pixel-flow renderer weights (path or module) for ``neural``; loaded once.
        observation: the policy's observation (camera, size, FOV); default ``ObservationConfig()``.
        frame_stride: store the observation of every ``frame_stride``-th step (2 = what the streaming
            agent sees); the actions of every step are stored.
        max_steps: step cap per episode (reaching it skips the episode as ``max_steps``).
        dataset: dataset name recorded per trajectory (default: the dataset's, else ``episodes``).
        end_tolerance: an episode whose follower stops farther (horizontally, metres) from the
            route's end is skipped as ``stopped_away``.
        follower_config: :class:`~image2sim.simulator.navigation.embodiment.FollowerConfig`.
        missing_scenes: ``error`` (default: ``FileNotFoundError`` naming the folder) or ``skip``
            (the scene's episodes are counted as ``missing_scene``).
        overwrite: replace an existing ``out_dir`` (default: ``FileExistsError``).
        progress: show a progress bar.

    Returns:
        A summary: ``episodes``, ``written``, ``skipped`` (reason -> count), ``skipped_episodes``
        (``episode_id``, ``scene``, ``reason``, ``detail``), ``scenes`` (per scene written/skipped),
        ``end_distance_m`` (mean/max over written), ``steps`` (mean/max), ``frames``, ``source``,
        ``dataset``, ``frame_stride`` and ``out``; also written to ``<out_dir>/summary.json``.

    Raises:
        ValueError: bad arguments, no episodes, or no episode could be converted (nothing written).
        FileNotFoundError: a scene folder is missing (``missing_scenes="error"``).
        FileExistsError: ``out_dir`` exists and ``overwrite`` is off.
    """
    from image2sim.navpolicy.rollout_scenes import SOURCES, scene_simulator, tasks_from_episodes
    from rich.progress import Progress

    if dataset is None:
        dataset = getattr(episodes, "name", None) or "episodes"
    eps = list(getattr(episodes, "episodes", episodes))
    obs = observation or ObservationConfig()
    if source not in SOURCES:
        raise ValueError(f"observation source must be one of {SOURCES}, got {source!r}")
    if source == "neural" and renderer is None:
        raise ValueError(
            "source 'neural' needs pixel-flow renderer weights (--renderer); "
            "use source 'splat_only' for splatted Gaussians without the learned renderer"
        )
    if int(frame_stride) < 1 or int(max_steps) < 1:
        raise ValueError(f"frame_stride and max_steps must be >= 1, got {frame_stride}, {max_steps}")
    if not (math.isfinite(end_tolerance) and end_tolerance > 0):
        raise ValueError(f"end_tolerance must be a positive number of metres, got {end_tolerance}")
    if missing_scenes not in ("error", "skip"):
        raise ValueError(f"missing_scenes must be 'error' or 'skip', got {missing_scenes!r}")
    if not eps:
        raise ValueError("no episodes to convert")
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; choose another folder or overwrite it")
    groups: dict[str, list] = {}
    for ep in eps:
        groups.setdefault(ep.scene_name, []).append(ep)
    root = Path(scenes_root)
    missing = sorted(name for name in groups if not (root / name).is_dir())
    if missing and missing_scenes == "error":
        raise FileNotFoundError(
            f"scene folder {root / missing[0]} not found ({len(missing)} of {len(groups)} scenes the "
            f"episodes name are missing: {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''})"
        )
    model = renderer
    if source == "neural" and isinstance(renderer, (str, Path)):
        from image2sim.simulator.renderer.model import load_renderer

        model = load_renderer(renderer)  # once for all scenes

    skipped: dict[str, int] = {}
    skipped_eps: list[dict] = []
    per_scene: dict[str, dict] = {}
    end_dists: list[float] = []
    lengths: list[int] = []
    n_frames = 0

    def skip(ep, name: str, reason: str, detail: str = "") -> None:
        skipped[reason] = skipped.get(reason, 0) + 1
        per_scene[name]["skipped"] += 1
        skipped_eps.append({"episode_id": ep.episode_id, "scene": name, "reason": reason, "detail": detail})

    opts = _Options(source, dataset, obs, int(frame_stride), int(max_steps), end_tolerance, follower_config)
    out.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_temps(out)
    tmp = temp_sibling(out, ".tmp")
    try:
        writer = ShardWriter(tmp, {**obs.__dict__})
        with Progress(transient=True, disable=not progress) as bar_display:
            bar = bar_display.add_task(f"{dataset} -> shard ({source})", total=len(eps))
            for name, scene_eps in sorted(groups.items()):
                per_scene[name] = {"written": 0, "skipped": 0}
                if name in missing:
                    for ep in scene_eps:
                        skip(ep, name, "missing_scene", f"{root / name} not found")
                        bar_display.advance(bar)
                    continue
                sim = scene_simulator(root / name, source, model)
                tasks = tasks_from_episodes(scene_eps, sim, name)
                for ep, task in zip(scene_eps, tasks, strict=True):
                    done = _convert(sim, ep, task, opts)
                    if isinstance(done, tuple):
                        skip(ep, name, *done)
                    else:
                        writer.add(done)
                        per_scene[name]["written"] += 1
                        end_dists.append(done.extra["end_distance_m"])
                        lengths.append(len(done.actions))
                        n_frames += len(done.frame_steps)
                    bar_display.advance(bar)
                del sim
        written = sum(s["written"] for s in per_scene.values())
        if written == 0:
            first = skipped_eps[0]
            raise ValueError(
                f"no episode reached the end of its route, nothing written (skipped: {skipped}; first: "
                f"episode {first['episode_id']}: {first['reason']}, {first['detail']})"
            )
        writer.close()
        summary = {
            "out": str(out),
            "dataset": dataset,
            "source": source,
            "frame_stride": int(frame_stride),
            "episodes": len(eps),
            "written": written,
            "skipped": dict(sorted(skipped.items())),
            "skipped_episodes": skipped_eps,
            "scenes": per_scene,
            "end_distance_m": {"mean": float(np.mean(end_dists)), "max": float(np.max(end_dists))},
            "steps": {"mean": float(np.mean(lengths)), "max": int(np.max(lengths))},
            "frames": n_frames,
        }
        write_text_atomic(tmp / "summary.json", json.dumps(summary, indent=2))
        if out.exists():  # overwrite (checked above)
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return summary
