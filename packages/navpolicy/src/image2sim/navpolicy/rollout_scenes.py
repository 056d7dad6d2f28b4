"""Where a policy acts in closed loop: simulators, the observations they render and the tasks on them.

- :func:`scene_simulator` opens one scene folder with an observation source (:data:`SOURCES`:
  ``neural``, ``splat_only``, ``exact``); :func:`procedural_simulator` builds a procedural scene with
  no files at all (the embedded default).
- :func:`render_observation` is the policy's view of agent 0 through the simulator's render function.
- Tasks (:class:`NavTask`) come from generated instruction episodes (:func:`tasks_from_episodes`,
  :func:`episode_scenes`) or are sampled point goals (:func:`sample_tasks`, :func:`procedural_scenes`).

Online DAgger (:mod:`image2sim.navpolicy.dagger`), ``nav act`` and the human-episode loader roll out
here; the evaluation runner has its own environment (:mod:`image2sim.eval.nav_env`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from image2sim.navpolicy.config import ObservationConfig


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
    reference_path: np.ndarray | None = None
    """(P, 3) route the instruction describes (map frame); the oracle follows it when given, else it
    takes the shortest path to ``goal``."""


def render_observation(sim, obs: ObservationConfig) -> np.ndarray:
    """The policy's (H, W, 3) uint8 observation of agent 0 through ``sim.render_fn``."""
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    if sim.render_fn is None:
        raise ValueError("the simulator has no render function: DAgger needs observations")
    pose = sim.camera_pose(0)
    if obs.camera == "pinhole" and getattr(sim.render_fn, "panoramic", False):
        # A panoramic renderer (the pixel-flow renderer): render the panorama at the pinhole view's
        # angular resolution and cut the view out of it, as NeuralSimulator.observe does.
        from image2sim.simulator.sim import ObservationSpec, panorama_height_for, views_from_panorama

        h = panorama_height_for(obs.width, obs.hfov_deg)
        pano = sim.render_fn(EquirectCamera(h, 2 * h), pose)
        spec = ObservationSpec(
            panorama=False, pinhole=True, pinhole_size=obs.height, pinhole_hfov_deg=obs.hfov_deg
        )
        rgb = np.asarray(views_from_panorama(pano, spec)["pinhole"]["rgb"], dtype=np.float32)
        return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if obs.camera == "pinhole":
        out = sim.render_fn(PinholeCamera.from_fov(obs.hfov_deg, obs.vfov_deg, obs.height, obs.width), pose)
        rgb = np.asarray(out["rgb"], dtype=np.float32)
        return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    from image2sim.navpolicy.data import observation_from_panorama

    h = max(obs.height, obs.width // 2)
    pano = np.asarray(sim.render_fn(EquirectCamera(h, 2 * h), pose)["rgb"], dtype=np.float32)
    return observation_from_panorama(np.clip(pano * 255.0 + 0.5, 0, 255).astype(np.uint8), 0.0, obs)


@dataclass
class RolloutScene:
    """A simulator (with a render function) and the tasks to draw episodes from."""

    sim: object
    tasks: list[NavTask]
    name: str = "scene"


# ------------------------------------------------------------------------------------------ tasks


def goal_instruction(
    start: np.ndarray, heading: float, goal: np.ndarray, marker_name: str | None = None
) -> str:
    """An egocentric point-goal instruction (the goal relative to the start pose, metres); with
    ``marker_name`` the goal is also named as the visible marker standing on it."""
    d = np.asarray(goal, float)[:2] - np.asarray(start, float)[:2]
    c, s = math.cos(heading), math.sin(heading)
    ahead, left = c * d[0] + s * d[1], -s * d[0] + c * d[1]
    fb = f"{abs(ahead):.1f} m {'ahead' if ahead >= 0 else 'behind you'}"
    lr = f"{abs(left):.1f} m to the {'left' if left >= 0 else 'right'}"
    if marker_name:
        return f"Go to the {marker_name} {fb} and {lr}, then stop next to it."
    return f"Go to the point {fb} and {lr}, then stop."


def sample_tasks(
    sim,
    n: int,
    rng: np.random.Generator,
    min_distance: float = 1.0,
    scene_id: str = "scene",
    max_tries: int = 5000,
    marker_name: str | None = None,
) -> list[NavTask]:
    """``n`` start/goal pairs on graph nodes of one component, at least ``min_distance`` apart
    (geodesic), with uniform start headings; raises ``ValueError`` if too few are found.
    ``marker_name``: the goal carries a visible marker of that name (see :func:`goal_instruction`)."""
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
                goal_instruction(nodes[i], h, nodes[j], marker_name),
                scene_id,
            )
        )
    if len(out) < n:
        raise ValueError(
            f"{scene_id}: found only {len(out)} of {n} start/goal pairs >= {min_distance} m apart"
        )
    return out


def procedural_simulator(seed: int = 0, preset: str = "tiny", embodiment=None, goal_marker=None):
    """A :class:`NeuralSimulator` on a procedural scene of the data engine (exact renderer).

    The embedded default data source: no files needed. Imports :mod:`image2sim.dataengine` lazily.
    ``goal_marker`` (a :class:`~image2sim.simulator.markers.GoalMarker`) draws it at the goal given
    to ``sim.set_goal``.
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

    if goal_marker is not None:
        from image2sim.simulator.markers import MarkedRenderFn

        return NeuralSimulator(navmap, NavGraph.build(navmap), MarkedRenderFn(render_fn, goal_marker))
    return NeuralSimulator(navmap, NavGraph.build(navmap), render_fn)


def procedural_scenes(
    n_scenes: int,
    tasks_per_scene: int,
    seed: int = 0,
    preset: str = "tiny",
    min_distance: float = 1.0,
    goal_marker=None,
) -> list[RolloutScene]:
    """``n_scenes`` procedural scenes (seeds ``seed..seed+n-1``) with sampled point-goal tasks
    (with a visible ``goal_marker`` at each goal when given)."""
    out = []
    name_of_marker = goal_marker.name if goal_marker is not None else None
    for i in range(n_scenes):
        sim = procedural_simulator(seed + i, preset, goal_marker=goal_marker)
        name = f"procedural-{preset}-{seed + i:03d}"
        rng = np.random.default_rng([seed, i])
        tasks = sample_tasks(sim, tasks_per_scene, rng, min_distance, name, marker_name=name_of_marker)
        out.append(RolloutScene(sim, tasks, name))
    return out


# ------------------------------------------------------------- generated instruction episodes


SOURCES = ("neural", "splat_only", "exact")
"""Where DAgger observations come from: ``neural`` = built scene folders rendered by the pixel-flow
renderer over their Gaussians (the product), ``splat_only`` = the same Gaussians splatted without the
learned renderer, ``exact`` = procedural captures rendered exactly (an upper bound, chosen explicitly)."""


def tasks_from_episodes(episodes, sim, scene_id: str = "") -> list[NavTask]:
    """DAgger tasks from instruction episodes (``image2sim.eval.datasets.NavEpisode``-like records in
    the world frame: ``episode_id``, ``start_position``, ``start_heading``, ``goal_position``,
    ``reference_path`` or dense ``gt_locations``, ``instruction.text``), in ``sim``'s map frame.
    The oracle follows the dense ground-truth route when the episode has one, else its reference
    path."""
    nav = sim.navmap
    out = []
    for ep in episodes:
        ref_world = ep.gt_locations if getattr(ep, "gt_locations", None) is not None else ep.reference_path
        ref = np.asarray(nav.to_map(np.asarray(ref_world, np.float64).reshape(-1, 3)), np.float64)
        d = nav.rotation @ np.array([math.cos(ep.start_heading), math.sin(ep.start_heading), 0.0])
        out.append(
            NavTask(
                str(ep.episode_id),
                np.asarray(nav.to_map(np.asarray(ep.start_position, np.float64)), np.float64).reshape(3),
                float(math.atan2(d[1], d[0])),
                np.asarray(nav.to_map(np.asarray(ep.goal_position, np.float64)), np.float64).reshape(3),
                ep.instruction.text,
                scene_id or ep.scene_name,
                ref if len(ref) else None,
            )
        )
    return out


def scene_simulator(folder: str | Path, source: str = "neural", renderer=None, device: str = "cpu"):
    """A :class:`NeuralSimulator` for DAgger rollouts from one scene folder.

    ``neural``: a built scene (``sim build-scene``: Gaussians + navigation map and graph) rendered by
    the pixel-flow renderer ``renderer`` (weights path; required); ``splat_only``: the same scene
    splatted, no learned renderer; ``exact``: a procedural capture rendered exactly (the navigation
    map and graph from the folder when present, else extracted as the data engine does). ``device``:
    where Gaussian scenes render (cpu or cuda); the exact renderer runs on the CPU.
    """
    from image2sim.simulator.sim import NeuralSimulator

    folder = Path(folder)
    if source not in SOURCES:
        raise ValueError(f"observation source must be one of {SOURCES}, got {source!r}")
    if source == "exact":
        from image2sim.dataengine.procedural.exact import capture_navigation, exact_render_fn
        from image2sim.simulator.navigation import NavMap
        from image2sim.simulator.navigation.graph import NavGraph

        if (folder / "navmap.npz").is_file() and (folder / "navgraph.npz").is_file():
            navmap, graph = NavMap.load(folder / "navmap.npz"), NavGraph.load(folder / "navgraph.npz")
        else:
            navmap, graph = capture_navigation(folder, procedural=True)
        return NeuralSimulator(navmap, graph, exact_render_fn(folder))
    # A built scene holds its Gaussians; the data engine's scene cache (<out>/scenes/<name>) holds them
    # under gaussians/ beside the navigation map and graph.
    gdir = next((f for f in (folder, folder / "gaussians") if (f / "gaussians.safetensors").is_file()), None)
    for name, ok in (
        ("gaussians.safetensors", gdir is not None),
        ("navmap.npz", (folder / "navmap.npz").is_file()),
        ("navgraph.npz", (folder / "navgraph.npz").is_file()),
    ):
        if not ok:
            raise FileNotFoundError(
                f"{folder}: missing {name}; source {source!r} needs a built scene folder "
                "(`image2sim sim build-scene` plus its navigation map and graph, or the data engine's "
                "<out>/scenes/<name> after --render gaussians)"
            )
    if source == "neural" and renderer is None:
        raise ValueError(
            "source 'neural' needs pixel-flow renderer weights (--renderer); "
            "use --source splat_only for splatted Gaussians without the learned renderer"
        )
    from image2sim.simulator.gaussians import GaussianScene
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.navigation.graph import NavGraph
    from image2sim.simulator.sim import gaussian_render_fn

    g = GaussianScene.load(gdir).gaussians
    if g is None:
        raise ValueError(f"{gdir}: the Gaussian scene is empty")
    render_fn = gaussian_render_fn(g, renderer if source == "neural" else None, device=device)
    return NeuralSimulator(
        NavMap.load(folder / "navmap.npz"), NavGraph.load(folder / "navgraph.npz"), render_fn
    )


def episode_scenes(
    episodes,
    scenes_root: str | Path,
    source: str = "neural",
    renderer=None,
    goal_marker=None,
    device: str = "cpu",
) -> list[RolloutScene]:
    """One :class:`RolloutScene` per scene the episodes name (``<scenes_root>/<scene name>``, the
    episode's ``scene_id`` stem), with the episodes as tasks (see :func:`tasks_from_episodes`);
    ``device``: where Gaussian scenes render (see :func:`scene_simulator`)."""
    groups: dict[str, list] = {}
    for ep in episodes:
        groups.setdefault(ep.scene_name, []).append(ep)
    if not groups:
        raise ValueError("no episodes to roll out")
    model = None
    if source == "neural" and renderer is not None:
        from image2sim.simulator.renderer.model import load_renderer

        model = load_renderer(renderer) if isinstance(renderer, (str, Path)) else renderer  # load once
    out = []
    for name, eps in sorted(groups.items()):
        folder = Path(scenes_root) / name
        if not folder.is_dir():
            raise FileNotFoundError(f"scene {name!r}: {folder} not found (episodes reference it)")
        sim = scene_simulator(folder, source, model, device=device)
        if goal_marker is not None:
            from image2sim.simulator.markers import MarkedRenderFn

            sim.render_fn = MarkedRenderFn(sim.render_fn, goal_marker)
        out.append(RolloutScene(sim, tasks_from_episodes(eps, sim, name), name))
    return out
