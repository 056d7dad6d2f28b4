"""``image2sim nav act``: one agent, one episode, a top-down trajectory PNG and the frames.

The episode runs through the evaluation runner (:func:`image2sim.eval.runner.run_episode` on a
:class:`~image2sim.eval.runner.NeuralSimBackend`), so its metrics are the harness's; a recording
backend keeps the map-frame positions and renders a frame at every visited state.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from image2sim.navpolicy.config import NavPolicyConfig
from image2sim.simulator.io.atomic import atomic_path, write_text_atomic


def act_protocol(cfg: NavPolicyConfig, max_steps: int, success_distance: float):
    """The paper's protocol with the policy's camera (pinhole, or the ultra-wide equirectangular
    crop, which the evaluation backend cuts from a full panorama), a step limit and a success radius
    that fits the small procedural rooms (the paper's 3 m would count most starts as successes)."""
    from image2sim.eval.protocols import IMAGE2SIM, CameraSpec

    o = cfg.observation
    return dataclasses.replace(
        IMAGE2SIM,
        name="nav-act",
        max_steps=int(max_steps),
        success_distance_m=float(success_distance),
        ndtw_threshold_m=float(success_distance),
        camera=CameraSpec(o.camera, o.width, o.height, o.hfov_deg, o.vfov_deg),
    )


def make_agent(cfg: NavPolicyConfig, name: str):
    """The runner agent called ``name``: ``image2nav`` (the policy of ``cfg.model``) or a baseline."""
    if name == "image2nav":
        from image2sim.eval.runner import Image2NavAdapter
        from image2sim.navpolicy.agent import Image2NavAgent
        from image2sim.navpolicy.model import build_policy

        policy = build_policy(cfg, seed=cfg.train.seed)
        policy.model.eval()
        return Image2NavAdapter.from_agent(Image2NavAgent(policy, cfg.agent, cfg.system_prompt))
    from image2sim.navpolicy.baselines import make_baseline

    return make_baseline(name)


def task_episodes(
    sim, n: int, seed: int, scene_id: str, min_distance: float = 1.5, marker_name: str | None = None
):
    """Runner episodes from :func:`image2sim.navpolicy.rollout_scenes.sample_tasks` (same instructions as
    DAgger's rollouts: the goal relative to the start pose, naming the goal marker if there is one)."""
    from image2sim.eval.datasets import Instruction, NavEpisode
    from image2sim.navpolicy.rollout_scenes import sample_tasks

    out = []
    rng = np.random.default_rng([seed, 2])
    for t in sample_tasks(sim, n, rng, min_distance, scene_id, marker_name=marker_name):
        path = sim.planner.shortest_path(t.start, t.goal)
        h = t.heading
        out.append(
            NavEpisode(
                episode_id=t.episode_id,
                scene_id=scene_id,
                start_position=np.asarray(sim.navmap.to_world(t.start), float).reshape(3),
                start_rotation=np.array([np.cos(h / 2), 0.0, 0.0, np.sin(h / 2)]),
                start_heading=h,
                goal_position=np.asarray(sim.navmap.to_world(t.goal), float).reshape(3),
                goal_radius=None,
                geodesic_distance=float(path.length),
                reference_path=np.asarray(sim.navmap.to_world(path.waypoints), float).reshape(-1, 3),
                instruction=Instruction(text=t.instruction),
            )
        )
    return out


def topdown_png(sim, positions: np.ndarray, goal: np.ndarray, radius: float, path: Path, title: str) -> Path:
    """Navigable nodes (grey), the trajectory (blue, start green), goal and success radius (red)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nodes = np.asarray(sim.graph.nodes)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=100)
    ax.scatter(nodes[:, 0], nodes[:, 1], s=2, c="0.8", marker="s", linewidths=0)
    ax.plot(positions[:, 0], positions[:, 1], "-", c="tab:blue", lw=1.5)
    ax.plot(positions[0, 0], positions[0, 1], "o", c="tab:green", ms=7, label="start")
    ax.plot(positions[-1, 0], positions[-1, 1], "x", c="tab:blue", ms=7, label="end")
    ax.plot(goal[0], goal[1], "*", c="tab:red", ms=11, label="goal")
    ax.add_patch(plt.Circle((goal[0], goal[1]), radius, fill=False, ec="tab:red", ls="--"))
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return path


def frame_strip(frames: list[np.ndarray], path: Path, n: int = 8, size: int = 128) -> Path:
    """``n`` frames evenly spaced over the episode (first and last included), side by side, each
    scaled to ``size`` pixels high (nearest neighbour: the policy's pixels as it saw them)."""
    from PIL import Image

    if not frames:
        raise ValueError("frame_strip: no frames")
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    tiles = []
    for i in idx:
        f = Image.fromarray(frames[i])
        tiles.append(np.asarray(f.resize((max(1, f.width * size // f.height), size), Image.NEAREST)))
    gap = np.full((size, 4, 3), 255, np.uint8)
    row = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
    with atomic_path(path) as tmp:
        Image.fromarray(row).save(tmp)
    return path


def run_act(
    cfg: NavPolicyConfig,
    agent_name: str,
    out: str | Path,
    scene_seed: int = 1000,
    episode_index: int = 0,
    max_steps: int = 200,
    success_distance: float = 0.5,
    seed: int = 0,
) -> dict:
    """Run ``agent_name`` on episode ``episode_index`` of procedural scene ``scene_seed``; writes
    ``topdown.png``, ``frames/NNNN.png``, ``strip.png`` (8 frames along the episode) and
    ``episode.json`` under ``out``; returns the record."""
    from image2sim.eval.runner import NeuralSimBackend, embodiment_for, run_episode
    from image2sim.navpolicy.rollout_scenes import procedural_simulator
    from PIL import Image

    proto = act_protocol(cfg, max_steps, success_distance)
    marker = cfg.task.active_marker()
    sim = procedural_simulator(scene_seed, "tiny", embodiment_for(proto), goal_marker=marker)
    scene_id = f"procedural-tiny-{scene_seed:03d}"
    episodes = task_episodes(sim, episode_index + 1, scene_seed, scene_id, marker_name=marker and marker.name)
    ep = episodes[episode_index]

    class Recording(NeuralSimBackend):
        """Renders every visited state and keeps map-frame positions."""

        def _obs(self, info, collided, observe):
            o = super()._obs(info, collided, True)
            self.positions.append(np.array(info["position"][0], dtype=np.float64))
            self.frames.append(o.rgb)
            self.collided.append(bool(collided))
            return o

    backend = Recording(sim, proto, scene_id)
    backend.positions, backend.frames, backend.collided = [], [], []
    agent = make_agent(cfg, agent_name)
    result, actions = run_episode(backend, agent, ep, proto, seed)
    outp = Path(out)
    (outp / "frames").mkdir(parents=True, exist_ok=True)
    # Frame i is the observation at visited state i (reset, then after every non-STOP action).
    for i, f in enumerate(backend.frames):
        Image.fromarray(f).save(outp / "frames" / f"{i:04d}.png")
    pos = np.array(backend.positions)
    goal_map = np.asarray(sim.navmap.to_map(ep.goal_position), float).reshape(3)
    m = result.metrics
    title = f"{agent_name} on {ep.episode_id}: success={m.get('success')} spl={m.get('spl', 0) or 0:.2f}"
    png = topdown_png(sim, pos, goal_map, success_distance, outp / "topdown.png", title)
    rec = {
        "agent": agent_name,
        "episode_id": ep.episode_id,
        "instruction": ep.instruction.text,
        "actions": actions,
        "collided": backend.collided[1:],
        "metrics": dict(m),
        "topdown": str(png),
        "strip": str(frame_strip(backend.frames, outp / "strip.png")),
        "frames": len(backend.frames),
    }
    write_text_atomic(outp / "episode.json", json.dumps(rec, indent=2, default=float))
    return rec


def compare_agents(
    cfg: NavPolicyConfig,
    agents: list[str],
    scene_seeds: list[int],
    episodes_per_scene: int = 8,
    max_steps: int = 200,
    success_distance: float = 0.5,
    seed: int = 0,
) -> dict:
    """SR / SPL (with the runner's 95 % intervals) of each agent on the same held-out procedural
    episodes (scenes ``scene_seeds``), through :func:`image2sim.eval.runner.run_episode`."""
    from image2sim.eval.runner import (
        NeuralSimBackend,
        RunnerError,
        embodiment_for,
        episode_seed,
        nav_summary,
        run_episode,
    )
    from image2sim.navpolicy.rollout_scenes import procedural_simulator
    from rich.progress import Progress

    proto = act_protocol(cfg, max_steps, success_distance)
    built = []
    marker = cfg.task.active_marker()
    for s in scene_seeds:
        sim = procedural_simulator(s, "tiny", embodiment_for(proto), goal_marker=marker)
        name = f"procedural-tiny-{s:03d}"
        eps = task_episodes(sim, episodes_per_scene, s, name, marker_name=marker and marker.name)
        built.append((NeuralSimBackend(sim, proto, name), eps))
    out = {}
    with Progress(transient=True) as progress:
        bar = progress.add_task("episodes", total=len(agents) * sum(len(e) for _, e in built))
        for name in agents:
            agent = make_agent(cfg, name)
            results, metrics, unreachable = [], [], []
            for backend, episodes in built:
                for ep in episodes:
                    try:
                        res = run_episode(backend, agent, ep, proto, episode_seed(seed, ep.episode_id))[0]
                        results.append(res)
                        metrics.append(dict(res.metrics))
                    except RunnerError as exc:
                        # The agent ended where the goal is unreachable on the navigation graph (a
                        # pocket the kinematics reach but the graph does not connect): a failure,
                        # counted and named rather than dropped.
                        if " ends at " not in str(exc):
                            raise
                        unreachable.append(ep.episode_id)
                        metrics.append({"success": 0.0, "spl": 0.0, "distance_to_goal": float("inf")})
                    progress.advance(bar)
            try:
                if unreachable:
                    raise ValueError(f"{len(unreachable)} episode(s) ended off the goal's graph component")
                out[name] = nav_summary(results)
            except ValueError as exc:
                out[name] = _sr_spl_only(metrics, str(exc))
                if unreachable:
                    out[name]["unreachable_end_episodes"] = unreachable
    return out


def _sr_spl_only(results: list[dict], why: str) -> dict:
    """SR/SPL with the runner's intervals when the full summary refuses a non-finite metric (an
    episode ended off the navigation graph: its distance to the goal is inf, but success = 0 and
    SPL = 0 are well defined); ``ne`` is then the mean over finite episodes and says how many."""
    from image2sim.eval.runner import bootstrap_ci, wilson_interval

    sr = [float(r["success"]) for r in results]
    spl = [float(r["spl"]) for r in results]
    ne = [float(r["distance_to_goal"]) for r in results]
    finite = [v for v in ne if np.isfinite(v)]
    return {
        "sr": float(np.mean(sr)),
        "spl": float(np.mean(spl)),
        "ne": float(np.mean(finite)) if finite else float("nan"),
        "ne_off_graph_episodes": len(ne) - len(finite),
        "steps": float(np.mean([float(r["steps"]) for r in results if "steps" in r] or [float("nan")])),
        "n_episodes": len(results),
        "sr_ci": list(wilson_interval(sum(sr), len(sr))),
        "spl_ci": list(bootstrap_ci(spl)),
        "note": why,
    }


def comparison_markdown(summary: dict) -> str:
    """A Markdown table of :func:`compare_agents`' output."""
    lines = [
        "| agent | SR [95% CI] | SPL [95% CI] | NE (m) | steps | episodes |",
        "|---|---|---|---|---|---|",
    ]
    for name, s in summary.items():
        # NE marked * when some episodes ended off the navigation graph (mean over the others).
        star = "*" if s.get("ne_off_graph_episodes") else ""
        lines.append(
            f"| {name} | {s['sr']:.3f} [{s['sr_ci'][0]:.3f}, {s['sr_ci'][1]:.3f}] "
            f"| {s['spl']:.3f} [{s['spl_ci'][0]:.3f}, {s['spl_ci'][1]:.3f}] "
            f"| {s['ne']:.2f}{star} | {s['steps']:.1f} | {s['n_episodes']} |"
        )
    return "\n".join(lines) + "\n"
