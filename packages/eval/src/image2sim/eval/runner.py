"""Navigation runner: episode loop over a simulator backend and an agent, resumable, parallel over scenes.

Pieces (small and separately testable):

* **Backends** (:class:`NeuralSimBackend`; :class:`HabitatBackend` behind an import guard) place the
  agent at an episode's start, apply discrete actions and report world-frame positions and the
  geodesic distance to the goal.
* **Agents**: the baselines ``random`` (VLN-CE's random action distribution), ``forward`` (N forward
  steps then STOP), ``oracle`` (the shortest-path follower of :mod:`image2sim.simulator.navigation`)
  and ``image2nav`` (navpolicy's streaming agent, imported lazily inside the adapter);
  ``image2nav_http`` is the same adapter driving a policy server (``image2sim nav serve``).
* :func:`run_episode` scores one episode with the protocol's measures
  (:mod:`image2sim.eval.metrics.nav`); :func:`run_scene` appends every finished episode to a per-scene
  JSONL :class:`~image2sim.eval.results.EpisodeLog` (a killed run resumes by skipping the episode ids
  already logged); :func:`run_nav` fans scenes out over processes and aggregates the logs.
* :func:`nav_summary` turns an aggregate into the headline record of ``metrics/nav.json`` (``sr``,
  ``spl``, ``ne``, ``osr``, ``ndtw``, ``n_episodes`` and 95 % intervals ``sr_ci`` (Wilson) and
  ``spl_ci`` (percentile bootstrap)).

Seeds: every episode's seed is :func:`episode_seed` ``(run_seed, episode_id)``, a pure function, so an
episode gives the same trajectory whether it runs first, last, in another process or after a resume.
The seed and the action sequence of each episode are written to a per-scene trajectory JSONL.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any
from typing import Protocol as TypingProtocol

import numpy as np
from image2sim.eval.datasets import (
    NavEpisode,
    habitat_heading,
    habitat_rotation_for_heading,
    habitat_to_world,
    world_to_habitat,
)
from image2sim.eval.metrics.nav import (
    DEFAULT_MEASURES,
    AgentState,
    AggregateReport,
    EpisodeResult,
    Measurements,
    aggregate,
)
from image2sim.eval.protocols import Protocol
from image2sim.eval.results import EpisodeLog, read_episode_log, read_result_file, write_result_file
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
    "nav_summary",
    "run_episode",
    "run_nav",
    "run_nav_results",
    "run_scene",
    "sample_point_goal_episodes",
    "update_nav_metrics",
    "wilson_interval",
]


class RunnerError(RuntimeError):
    """The run cannot proceed as configured (message names the scene / episode / field)."""

    cli_exit_code = 2  # bad input: the CLI's error boundary answers it with one line, status 2


class BackendUnavailable(ImportError):
    """An optional simulator backend is not installed."""


# ------------------------------------------------------------------------------------------ seeds


def episode_seed(run_seed: int, episode_id: str) -> int:
    """Seed of one episode: a pure function of the run seed and the episode id (order-independent)."""
    return zlib.crc32(f"{int(run_seed)}:{episode_id}".encode()) & 0x7FFFFFFF


# ------------------------------------------------------------------------------------------ backends


@dataclass
class StepObservation:
    """What a backend reports after reset and after every action (world frame)."""

    position: np.ndarray
    """(3,) feet position, world metres (Z-up)."""
    heading: float
    """Heading in radians (map frame yaw; equal to world yaw without gravity correction)."""
    distance_to_goal: float
    """Geodesic distance to the goal in metres (inf when off the graph / unreachable)."""
    distance_reason: str = ""
    """Why ``distance_to_goal`` is inf or approximate ("" when it is an exact graph distance)."""
    distance_approximate: bool = False
    """``distance_to_goal`` is the planner's upper-bound estimate for a position the navigation graph
    does not connect to the goal (see ``DistanceField.approximate``), not a graph distance."""
    collided: bool = False
    """The last action hit an obstacle."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 observation when the backend renders and the agent asked for it."""


class Backend(TypingProtocol):
    """Minimal simulator interface the runner needs."""

    def reset(self, episode: NavEpisode, observe: bool) -> StepObservation: ...

    def step(self, action: int, observe: bool) -> StepObservation: ...


def embodiment_for(protocol: Protocol, base: Any | None = None):
    """The simulator :class:`Embodiment` implied by ``protocol`` (other fields from ``base``)."""
    from image2sim.simulator.navigation.embodiment import Embodiment

    b = base or Embodiment()
    kw = b.to_dict()
    kw.update(
        radius=protocol.agent_radius_m,
        eye_height=protocol.eye_height_m,
        forward_step=protocol.forward_step_m,
        turn_angle_deg=protocol.turn_angle_deg,
        wall_sliding=protocol.allow_sliding,
    )
    kw["height"] = max(kw["height"], protocol.agent_height_m)
    return Embodiment(**kw)


def check_embodiment(embodiment: Any, protocol: Protocol, where: str = "scene") -> None:
    """Raise :class:`RunnerError` when the simulator's body/actions differ from the protocol's."""
    pairs = {
        "forward_step": (embodiment.forward_step, protocol.forward_step_m),
        "turn_angle_deg": (embodiment.turn_angle_deg, protocol.turn_angle_deg),
        "radius": (embodiment.radius, protocol.agent_radius_m),
        "eye_height": (embodiment.eye_height, protocol.eye_height_m),
        "wall_sliding": (embodiment.wall_sliding, protocol.allow_sliding),
    }
    bad = {
        k: v
        for k, v in pairs.items()
        if (v[0] != v[1] if isinstance(v[0], bool) else abs(v[0] - v[1]) > 1e-9)
    }
    if bad:
        detail = ", ".join(f"{k}: simulator {a!r} vs protocol {b!r}" for k, (a, b) in bad.items())
        raise RunnerError(
            f"{where}: the navigation map was built for another embodiment than protocol "
            f"{protocol.name!r} ({detail}); rebuild it with eval.runner.embodiment_for(protocol)"
        )


def equirect_crop(cam: Any) -> tuple[Any, tuple[slice, slice] | None]:
    """The full panorama to render for an equirectangular protocol camera, and the centred crop
    that is the observation (None for a full 360 x 180 view).

    The ultra-wide setting (512 x 336 at 180 deg x 118 deg) is the middle of a 1024 x 512 panorama:
    the same angular resolution, longitude 0 (straight ahead) at the centre column, the horizon at
    the centre row.
    """
    from image2sim.simulator.geometry.cameras import EquirectCamera

    if not (0 < cam.hfov_deg <= 360 and 0 < cam.vfov_deg <= 180):
        raise RunnerError(
            f"equirect camera: fov must lie in (0, 360] x (0, 180], got {cam.hfov_deg} x {cam.vfov_deg}"
        )
    # Same parity as the crop, so the crop sits exactly in the middle (the fov moves < 0.4 deg).
    full_w = cam.width + 2 * round((cam.width * 360.0 / cam.hfov_deg - cam.width) / 2)
    full_h = cam.height + 2 * round((cam.height * 180.0 / cam.vfov_deg - cam.height) / 2)
    if (full_w, full_h) == (cam.width, cam.height):
        return EquirectCamera(cam.height, cam.width), None
    top, left = (full_h - cam.height) // 2, (full_w - cam.width) // 2
    return EquirectCamera(full_h, full_w), (slice(top, top + cam.height), slice(left, left + cam.width))


class NeuralSimBackend:
    """:class:`~image2sim.simulator.sim.NeuralSimulator` as a runner backend (one agent).

    Episodes are in the world frame; the simulator works in the navigation map's frame
    (``navmap.to_map`` / ``to_world``). The geodesic distance comes from one distance field per
    episode (a single Dijkstra from the goal).
    """

    def __init__(self, sim: Any, protocol: Protocol, name: str = "scene") -> None:
        check_embodiment(sim.embodiment, protocol, name)
        self.sim = sim
        self.protocol = protocol
        self.name = name
        self.field = None
        self._last_pos: np.ndarray | None = None
        self._last_dist, self._last_reason, self._last_approx = float("inf"), "", False
        cam = protocol.camera
        self._camera = None
        self._crop: tuple[slice, slice] | None = None
        if sim.render_fn is not None:
            from image2sim.simulator.geometry.cameras import PinholeCamera

            if cam.kind == "pinhole":
                self._camera = PinholeCamera.from_fov(cam.hfov_deg, cam.vfov_deg, cam.height, cam.width)
            else:
                self._camera, self._crop = equirect_crop(cam)

    @property
    def planner(self):
        return self.sim.planner

    def render_at(self, size: tuple[int, int] | None) -> None:
        """Render pinhole observations at ``(height, width)`` instead of the protocol camera's pixel
        size, keeping its field of view: an agent whose input is smaller (a 64 px policy under a
        336 px protocol) then gets its own resolution rendered directly instead of paying for pixels
        it would only downsample. ``None`` or a non-pinhole protocol keeps the protocol's camera."""
        cam = self.protocol.camera
        if size is None or self._camera is None or cam.kind != "pinhole":
            return
        from image2sim.simulator.geometry.cameras import PinholeCamera

        h, w = (int(v) for v in size)
        if h < cam.height or w < cam.width:
            self._camera = PinholeCamera.from_fov(cam.hfov_deg, cam.vfov_deg, h, w)

    def _heading_to_map(self, heading: float) -> float:
        d = self.sim.navmap.rotation @ np.array([math.cos(heading), math.sin(heading), 0.0])
        return float(math.atan2(d[1], d[0]))

    def _obs(self, info: dict, collided: bool, observe: bool) -> StepObservation:
        pos_map = info["position"][0]
        rgb = None
        if observe:
            if self._camera is None:
                raise RunnerError(f"{self.name}: the agent needs images but the scene has no render function")
            out = self.sim.render_fn(self._camera, self.sim.camera_pose(0))
            rgb = np.clip(np.asarray(out["rgb"], np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
            if self._crop is not None:
                rgb = rgb[self._crop[0], self._crop[1]]
        # Turns do not move the agent: reuse the last distance instead of another graph snap.
        if self._last_pos is None or not np.array_equal(pos_map, self._last_pos):
            self._last_pos = np.array(pos_map, dtype=np.float64)
            self._last_dist, self._last_reason = self.field.query(pos_map)
            self._last_approx = False
            if not math.isfinite(self._last_dist) and self.field.goal_node >= 0:
                # The agent walked here from a connected start, so the goal is reachable even though
                # the conservative graph does not connect this spot: estimate instead of aborting.
                self._last_dist, self._last_reason = self.field.approximate(pos_map)
                self._last_approx = math.isfinite(self._last_dist)
        return StepObservation(
            position=np.asarray(self.sim.navmap.to_world(pos_map), dtype=np.float64).reshape(3),
            heading=float(info["heading"][0]),
            distance_to_goal=self._last_dist,
            distance_reason=self._last_reason,
            distance_approximate=self._last_approx,
            collided=collided,
            rgb=rgb,
        )

    def reset(self, episode: NavEpisode, observe: bool = False) -> StepObservation:
        start = np.asarray(self.sim.navmap.to_map(episode.start_position), dtype=np.float64).reshape(3)
        goal = np.asarray(self.sim.navmap.to_map(episode.goal_position), dtype=np.float64).reshape(3)
        self.goal_map = goal
        self.field = self.sim.planner.distance_field(goal)
        self.sim.set_goal(np.asarray(episode.goal_position, dtype=np.float64).reshape(3))
        self._last_pos, self._last_dist, self._last_reason, self._last_approx = None, float("inf"), "", False
        _, info = self.sim.reset(
            start[None], np.array([self._heading_to_map(episode.start_heading)]), observe=False
        )
        return self._obs(info, False, observe)

    def step(self, action: int, observe: bool = False) -> StepObservation:
        _, info = self.sim.step([int(action)], observe=False)
        return self._obs(info, bool(info["collided"][0]), observe)

    def agent_state(self):
        """The simulator's kinematic state of the agent (map frame), for privileged agents."""
        return self.sim.agents[0].state


def import_habitat_sim() -> Any:
    """``habitat_sim``, or :class:`BackendUnavailable` saying how to get it."""
    try:
        import habitat_sim
    except ImportError as exc:
        raise BackendUnavailable(
            "the Habitat backend needs habitat-sim (conda install habitat-sim -c aihabitat); "
            "use the NeuralSimulator backend (--backend neural) otherwise"
        ) from exc
    return habitat_sim


def _quat_xyzw(q: Any) -> np.ndarray:
    """Habitat rotation (a numpy-quaternion ``quaternion`` or ``[x, y, z, w]`` coefficients)."""
    if all(hasattr(q, k) for k in ("x", "y", "z", "w")):
        return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    return np.asarray(q, dtype=np.float64).reshape(4)


class HabitatBackend:
    """habitat-sim as a runner backend, for users who have it (no Linux wheel on PyPI; never a hard
    dependency, imported only when this class is instantiated).

    One ``habitat_sim.Simulator`` per scene file, configured from the protocol: agent height and
    radius, sliding, the discrete action space (``move_forward`` by ``forward_step_m``,
    ``turn_left`` / ``turn_right`` by ``turn_angle_deg``) and one RGB sensor ``"rgb"`` at the
    protocol's camera (pinhole: resolution and HFOV; equirect: ``EquirectangularSensorSpec``) at the
    agent's height. Episodes are in our Z-up world and are converted to Habitat's Y-up frame
    (:func:`~image2sim.eval.datasets.world_to_habitat`; the start rotation is the upright one of the
    episode's heading); positions and headings come back the same way. The geodesic distance is the
    pathfinder's shortest path length (``habitat_sim.ShortestPath``); inf with a reason when none.
    """

    ACTIONS = {
        int(Action.MOVE_FORWARD): "move_forward",
        int(Action.TURN_LEFT): "turn_left",
        int(Action.TURN_RIGHT): "turn_right",
    }
    """Our action ids -> habitat-sim action names (STOP ends the episode in the runner)."""

    def __init__(self, scene: str | Path, protocol: Protocol, gpu_device_id: int = 0) -> None:
        hs = import_habitat_sim()
        self.hs, self.protocol, self.name = hs, protocol, Path(scene).stem
        if not Path(scene).is_file():
            raise RunnerError(f"Habitat scene file {scene} not found")
        self.sim = hs.Simulator(self.configuration(hs, scene, protocol, gpu_device_id))
        if not self.sim.pathfinder.is_loaded:
            raise RunnerError(f"{scene}: habitat-sim loaded no navmesh (geodesic distances need one)")
        self.agent = self.sim.initialize_agent(0)
        self.goal_habitat: np.ndarray | None = None
        self._last: tuple[np.ndarray, float, str] | None = None

    @staticmethod
    def configuration(hs: Any, scene: str | Path, protocol: Protocol, gpu_device_id: int = 0) -> Any:
        """The ``habitat_sim.Configuration`` implementing ``protocol`` for one scene."""
        sim_cfg = hs.SimulatorConfiguration()
        sim_cfg.scene_id = str(scene)
        sim_cfg.gpu_device_id = int(gpu_device_id)
        sim_cfg.allow_sliding = bool(protocol.allow_sliding)
        cam = protocol.camera
        if cam.kind == "pinhole":
            sensor = hs.CameraSensorSpec()
            sensor.hfov = float(cam.hfov_deg)
        else:
            sensor = hs.EquirectangularSensorSpec()
        sensor.uuid = "rgb"
        sensor.sensor_type = hs.SensorType.COLOR
        sensor.resolution = [int(cam.height), int(cam.width)]
        sensor.position = [0.0, protocol.eye_height_m, 0.0]
        agent_cfg = hs.agent.AgentConfiguration()
        agent_cfg.height = float(protocol.agent_height_m)
        agent_cfg.radius = float(protocol.agent_radius_m)
        agent_cfg.sensor_specifications = [sensor]
        amounts = {
            "move_forward": float(protocol.forward_step_m),
            "turn_left": float(protocol.turn_angle_deg),
            "turn_right": float(protocol.turn_angle_deg),
        }
        agent_cfg.action_space = {
            name: hs.agent.ActionSpec(name, hs.agent.ActuationSpec(amount=amount))
            for name, amount in amounts.items()
        }
        return hs.Configuration(sim_cfg, [agent_cfg])

    def geodesic_distance(self, position_habitat: np.ndarray) -> tuple[float, str]:
        """Pathfinder shortest-path length from a Habitat-frame position to the goal, and a reason if inf."""
        path = self.hs.ShortestPath()
        path.requested_start = np.asarray(position_habitat, dtype=np.float32)
        path.requested_end = np.asarray(self.goal_habitat, dtype=np.float32)
        found = bool(self.sim.pathfinder.find_path(path))
        d = float(path.geodesic_distance)
        if not found or not math.isfinite(d):
            where = np.round(habitat_to_world_point(position_habitat), 3).tolist()
            return float("inf"), f"habitat's pathfinder found no path from world {where} to the goal"
        return d, ""

    def _obs(self, observations: Mapping[str, Any] | None, collided: bool) -> StepObservation:
        state = self.agent.get_state()
        pos_h = np.asarray(state.position, dtype=np.float64).reshape(3)
        if self._last is None or not np.array_equal(pos_h, self._last[0]):
            self._last = (pos_h, *self.geodesic_distance(pos_h))
        rgb = None
        if observations is not None:
            rgb = np.ascontiguousarray(np.asarray(observations["rgb"])[..., :3], dtype=np.uint8)
        return StepObservation(
            position=habitat_to_world_point(pos_h),
            heading=habitat_heading(_quat_xyzw(state.rotation)),
            distance_to_goal=self._last[1],
            distance_reason=self._last[2],
            collided=collided,
            rgb=rgb,
        )

    def reset(self, episode: NavEpisode, observe: bool = False) -> StepObservation:
        self.goal_habitat = world_to_habitat(episode.goal_position)
        state = self.hs.AgentState()
        state.position = world_to_habitat(episode.start_position)
        # From the heading (the start_rotation of Habitat-file and of our own episodes differ in
        # which body axis looks forward; the heading is the same quantity in both).
        state.rotation = habitat_rotation_for_heading(episode.start_heading)  # [x, y, z, w]
        self.agent.set_state(state)
        self._last = None
        return self._obs(self.sim.get_sensor_observations() if observe else None, False)

    def step(self, action: int, observe: bool = False) -> StepObservation:
        name = self.ACTIONS.get(int(action))
        if name is None:
            raise RunnerError(f"{self.name}: action {action!r} is not a movement (STOP ends the episode)")
        observations = self.sim.step(name)
        return self._obs(observations if observe else None, bool(observations.get("collided", False)))

    def close(self) -> None:
        self.sim.close()


def habitat_to_world_point(p: Any) -> np.ndarray:
    """One Habitat-frame point as a (3,) world point (:func:`~image2sim.eval.datasets.habitat_to_world`)."""
    return habitat_to_world(np.asarray(p, dtype=np.float64).reshape(3))


def load_scene_backend(scene_dir: str | Path, protocol: Protocol, render: bool = False) -> NeuralSimBackend:
    """A :class:`NeuralSimBackend` from a scene folder holding ``navmap.npz`` and ``navgraph.npz``.

    With ``render``, observations come from a Gaussian scene in the folder (``gaussians.safetensors``
    here or under ``gaussians/``) through :class:`~image2sim.simulator.sim.GaussianRenderFn`.
    """
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.navigation.graph import NavGraph
    from image2sim.simulator.sim import NeuralSimulator

    scene_dir = Path(scene_dir)
    for name in ("navmap.npz", "navgraph.npz"):
        if not (scene_dir / name).is_file():
            raise RunnerError(
                f"{scene_dir}: missing {name} (run `image2sim sim navmap` or the data engine first)"
            )
    navmap = NavMap.load(scene_dir / "navmap.npz")
    graph = NavGraph.load(scene_dir / "navgraph.npz")
    render_fn = None
    if render:
        folder = next(
            (f for f in (scene_dir, scene_dir / "gaussians") if (f / "gaussians.safetensors").is_file()), None
        )
        if folder is None:
            raise RunnerError(f"{scene_dir}: the agent needs images but there is no gaussians.safetensors")
        from image2sim.simulator.gaussians import GaussianScene
        from image2sim.simulator.sim import GaussianRenderFn

        g = GaussianScene.load(folder).gaussians
        render_fn = GaussianRenderFn(
            {k: getattr(g, k) for k in ("means", "scales", "quats", "opacities", "colors")}
        )
    return NeuralSimBackend(NeuralSimulator(navmap, graph, render_fn), protocol, scene_dir.name)


def load_exact_backend(capture_dir: str | Path, protocol: Protocol, render: bool = False) -> NeuralSimBackend:
    """A :class:`NeuralSimBackend` on a procedural capture's house with the *exact* renderer: the
    "real world" of the sim-to-real experiment (``--backend exact``).

    The navigation map and graph come from the folder when it holds them (``navmap.npz`` +
    ``navgraph.npz``), else they are extracted from the capture as the data engine does; observations
    are the regenerated house rendered exactly (:mod:`image2sim.dataengine.procedural.exact`; the
    data engine is imported only here).
    """
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.navigation.graph import NavGraph
    from image2sim.simulator.sim import NeuralSimulator

    capture_dir = Path(capture_dir)
    try:
        from image2sim.dataengine.procedural.exact import (
            capture_navigation,
            exact_render_fn,
            is_procedural_capture,
        )
    except ImportError as exc:  # pragma: no cover - the monorepo installs it
        raise BackendUnavailable("--backend exact needs the image2sim-dataengine package") from exc
    try:
        if not is_procedural_capture(capture_dir):
            raise RunnerError(
                f"{capture_dir}: --backend exact needs a procedural capture (written by `image2sim data "
                "synth`); use --backend neural for built scenes"
            )
        render_fn = exact_render_fn(capture_dir) if render else None
    except (FileNotFoundError, ValueError) as exc:
        raise RunnerError(str(exc)) from exc
    if (capture_dir / "navmap.npz").is_file() and (capture_dir / "navgraph.npz").is_file():
        navmap, graph = NavMap.load(capture_dir / "navmap.npz"), NavGraph.load(capture_dir / "navgraph.npz")
    else:
        navmap, graph = capture_navigation(capture_dir, procedural=True)
    return NeuralSimBackend(NeuralSimulator(navmap, graph, render_fn), protocol, capture_dir.name)


# ------------------------------------------------------------------------------------------ agents


class NavAgent(TypingProtocol):
    """An agent: ``reset`` per episode, then ``act`` once per step (one action id)."""

    needs_images: bool

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None: ...

    def act(self, obs: StepObservation) -> int: ...


@dataclass
class RandomAgent:
    """VLN-CE's random baseline: i.i.d. actions from the R2R-CE training action distribution."""

    probabilities: tuple[float, float, float, float] = (0.02, 0.68, 0.15, 0.15)
    """P(STOP), P(FORWARD), P(LEFT), P(RIGHT) (VLN-CE, Krantz et al. 2020, Sec. 5 'Random')."""
    needs_images: bool = False

    def __post_init__(self) -> None:
        p = np.asarray(self.probabilities, dtype=np.float64)
        if p.shape != (4,) or (p < 0).any() or not math.isclose(float(p.sum()), 1.0, abs_tol=1e-9):
            raise ValueError(
                f"RandomAgent.probabilities must be 4 non-negative numbers summing to 1, "
                f"got {self.probabilities}"
            )
        self._p = p
        self._rng = np.random.default_rng(0)

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        self._rng = np.random.default_rng(seed)

    def act(self, obs: StepObservation) -> int:
        return int(self._rng.choice(4, p=self._p))


@dataclass
class ForwardAgent:
    """Blind baseline: ``forward_steps`` MOVE_FORWARD actions, then STOP."""

    forward_steps: int = 37
    """Forward actions before STOP. 37 follows the hand-crafted baseline of VLN-CE (Krantz et al. 2020),
    which first turns to a random heading; this agent keeps the start heading (fully deterministic)."""
    needs_images: bool = False

    def __post_init__(self) -> None:
        if int(self.forward_steps) < 0:
            raise ValueError(f"ForwardAgent.forward_steps must be >= 0, got {self.forward_steps}")
        self._t = 0

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        self._t = 0

    def act(self, obs: StepObservation) -> int:
        self._t += 1
        return int(Action.MOVE_FORWARD) if self._t <= self.forward_steps else int(Action.STOP)


@dataclass
class OracleAgent:
    """Privileged shortest-path follower (:class:`~image2sim.simulator.navigation.OracleFollower`)."""

    follower: dict = field(default_factory=dict)
    """:class:`FollowerConfig` overrides (smoothing_window, lookahead, stop_radius, ...)."""
    needs_images: bool = False

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        from image2sim.simulator.navigation import FollowerConfig, OracleFollower

        if not isinstance(backend, NeuralSimBackend):
            raise RunnerError("the oracle agent needs the NeuralSimulator backend (planner access)")
        self.backend = backend
        cfg = FollowerConfig.from_dict(self.follower, "oracle.follower")
        self._f = OracleFollower(backend.planner, backend.sim.embodiment, cfg)
        self._f.reset(backend.agent_state().position, backend.goal_map)

    def act(self, obs: StepObservation) -> int:
        return int(self._f.act(self.backend.agent_state(), obs.collided))


class Image2NavAdapter:
    """navpolicy's streaming Image2Nav agent (two actions per model call) as a runner agent.

    navpolicy is imported here and only here (lazily), so ``image2sim.eval`` works without it.
    ``model``: an exported policy folder or ``"tiny"`` (an untrained tiny model, for plumbing runs).
    """

    needs_images = True

    def __init__(self, model: str = "tiny", config: str = "tiny") -> None:
        try:
            from image2sim.navpolicy.agent import Image2NavAgent
            from image2sim.navpolicy.config import load_config
            from image2sim.navpolicy.model import build_policy
        except ImportError as exc:
            raise RunnerError(f"the image2nav agent needs image2sim-navpolicy installed ({exc})") from exc
        cfg = load_config(config, {"model": {"source": model}} if model != "tiny" else None)
        self._init(Image2NavAgent(build_policy(cfg, seed=0), cfg.agent, cfg.system_prompt))

    def _init(self, agent: Any) -> None:
        self._agent = agent
        self._queue: list[int] = []
        self._executed: list[int] | None = None

    @classmethod
    def from_agent(cls, agent: Any) -> Image2NavAdapter:
        """Wrap an already built streaming agent (``reset(instruction, seed)``, ``act(rgb, executed)``)."""
        self = cls.__new__(cls)
        self._init(agent)
        return self

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        import torch

        torch.manual_seed(seed)
        self._agent.reset(episode.instruction.text, seed=seed)
        self._queue, self._executed = [], None

    def act(self, obs: StepObservation) -> int:
        if not self._queue:
            if obs.rgb is None:
                raise RunnerError("image2nav: no image in the observation")
            self._queue = [int(a) for a in self._agent.act(obs.rgb, executed=self._executed)]
            self._executed = []
        a = self._queue.pop(0)
        self._executed.append(a)
        if a == int(Action.STOP):
            self._queue = []
        return a

    @staticmethod
    def observation_size(options: Mapping[str, Any]) -> tuple[int, int] | None:
        """The policy's pinhole input size (height, width) from its config, or None."""
        from image2sim.navpolicy.config import load_config

        model = options.get("model", "tiny")
        cfg = load_config(
            options.get("config", "tiny"), {"model": {"source": model}} if model != "tiny" else None
        )
        obs = cfg.observation
        return (obs.height, obs.width) if obs.camera == "pinhole" else None

    @property
    def wants_image(self) -> bool:
        """An image is needed at the next step only when the action queue is empty."""
        return not self._queue


class Image2NavHttpAdapter(Image2NavAdapter):
    """Image2Nav behind a policy server (``image2sim nav serve``): the same two-action adapter, its
    streaming agent a :class:`~image2sim.navpolicy.client.RemoteAgent` (one server session per
    episode). ``token_env`` names the environment variable holding the bearer token (never the token
    itself, so run records do not hold it)."""

    needs_images = True

    def __init__(self, server: str, token_env: str = "", timeout_s: float = 60.0) -> None:
        self._init(_remote_agent(server, token_env, timeout_s))

    @staticmethod
    def observation_size(options: Mapping[str, Any]) -> tuple[int, int] | None:
        """The served policy's pinhole input size (height, width), asked from the server."""
        client = _remote_agent(options["server"], options.get("token_env", ""), 60.0).client
        try:
            obs = client.info()["observation"]
        finally:
            client.close()
        return (int(obs["height"]), int(obs["width"])) if obs.get("camera") == "pinhole" else None


def _remote_agent(server: str, token_env: str, timeout_s: float) -> Any:
    try:
        from image2sim.navpolicy.client import PolicyClient, RemoteAgent, token_from_env
    except ImportError as exc:
        raise RunnerError(f"the image2nav_http agent needs image2sim-navpolicy installed ({exc})") from exc
    try:
        token = token_from_env(token_env)
    except ValueError as exc:
        raise RunnerError(str(exc)) from exc
    return RemoteAgent(PolicyClient(server, token=token, timeout_s=timeout_s))


@dataclass(frozen=True)
class AgentSpec:
    """A picklable agent description: registry name + constructor options."""

    name: str
    """``random``, ``forward``, ``oracle`` or ``image2nav``."""
    options: Mapping[str, Any] = field(default_factory=dict)
    """Keyword arguments of the agent class."""


AGENTS: dict[str, Callable[..., Any]] = {
    "random": RandomAgent,
    "forward": ForwardAgent,
    "oracle": OracleAgent,
    "image2nav": Image2NavAdapter,
    "image2nav_http": Image2NavHttpAdapter,
}
"""Agent registry."""


def _forward_turn_agent(**options: Any) -> Any:
    """navpolicy's forward-until-collision-then-turn baseline (one implementation, imported lazily)."""
    try:
        from image2sim.navpolicy.baselines import ForwardTurnAgent
    except ImportError as exc:
        raise RunnerError(f"the forward_turn agent needs image2sim-navpolicy installed ({exc})") from exc
    return ForwardTurnAgent(**options)


AGENTS["forward_turn"] = _forward_turn_agent


def make_agent(spec: AgentSpec) -> Any:
    """Build an agent from its spec; unknown names and options are errors naming them."""
    if spec.name not in AGENTS:
        raise RunnerError(f"unknown agent {spec.name!r}; known: {sorted(AGENTS)}")
    try:
        return AGENTS[spec.name](**dict(spec.options))
    except TypeError as exc:
        raise RunnerError(f"agent {spec.name!r}: bad options {dict(spec.options)} ({exc})") from exc


# ------------------------------------------------------------------------------------------ episodes


def run_episode(
    backend: Any, agent: Any, episode: NavEpisode, protocol: Protocol, seed: int
) -> tuple[EpisodeResult, list[int]]:
    """Run one episode to STOP or the protocol's step limit; returns its result and the actions."""
    ms = Measurements(protocol, DEFAULT_MEASURES)
    wants = (lambda: getattr(agent, "wants_image", True)) if agent.needs_images else (lambda: False)
    try:
        obs = backend.reset(episode, observe=bool(agent.needs_images))
    except ValueError as err:  # e.g. a start off the navigation map: name the episode and its scene
        raise RunnerError(f"episode {episode.episode_id} (scene {episode.scene_id}): {err}") from err
    _require_finite_distance(obs, episode, "starts")
    if obs.distance_approximate:
        raise RunnerError(
            f"episode {episode.episode_id}: the start is not connected to the goal on the navigation graph "
            f"({obs.distance_reason}); fix the episode or the scene's navigation graph"
        )
    agent.reset(episode, backend, seed)
    ms.reset(episode.metric_spec(), AgentState(obs.position, obs.distance_to_goal))
    actions: list[int] = []
    for _ in range(protocol.max_steps):
        a = int(agent.act(obs))
        if a not in {int(x) for x in Action}:
            raise RunnerError(f"episode {episode.episode_id}: agent returned action {a!r}")
        actions.append(a)
        if a == int(Action.STOP):
            ms.update(a, AgentState(obs.position, obs.distance_to_goal))
            break
        obs = backend.step(a, observe=bool(agent.needs_images and wants()))
        ms.update(a, AgentState(obs.position, obs.distance_to_goal))
    _require_finite_distance(obs, episode, "ends")
    values = dict(ms.values())
    # Recorded per episode (0/1) so the share of estimated final distances is reported, never hidden.
    values["ne_approximate"] = float(obs.distance_approximate)
    return EpisodeResult(episode.episode_id, values, protocol), actions


def _require_finite_distance(obs: StepObservation, episode: NavEpisode, when: str) -> None:
    """Raise :class:`RunnerError` naming the episode when the goal distance at its start / end is
    undefined (NE would be infinite; the episode is never dropped silently from the averages)."""
    if not math.isfinite(obs.distance_to_goal):
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
        result, actions = run_episode(backend, agent, ep, protocol, seed)
        _append_jsonl(traj_path, {"episode_id": ep.episode_id, "seed": seed, "actions": actions})
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
    """Worker entry point (top level so it pickles): load the scene and run its episodes."""
    if task.get("worker"):
        import torch

        torch.set_num_threads(1)  # one process per core; never changes the caller's setting in-process
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
    logged = [p for p in out.glob("*.jsonl") if not p.name.endswith(".traj.jsonl")]
    if not previous_file.is_file() or not logged:
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
            import multiprocessing as mp

            from image2sim.simulator.lifetime import die_with_parent

            # spawn: torch and OpenMP do not survive fork reliably. Workers end with this process.
            with ProcessPoolExecutor(
                min(config.workers, len(tasks)),
                mp_context=mp.get_context("spawn"),
                initializer=die_with_parent,
                initargs=(os.getpid(),),
            ) as pool:
                for _ in pool.map(_scene_task, [{**t, "worker": True} for t in tasks]):
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


# ------------------------------------------------------------------------------------------ summaries


def wilson_interval(successes: float, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) for n = 0."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At p = 0 / p = 1 the bound is exactly 0 / 1; rounding would put it a hair inside.
    lo = 0.0 if successes <= 0 else max(0.0, centre - half)
    hi = 1.0 if successes >= n else min(1.0, centre + half)
    return (lo, hi)


def bootstrap_ci(
    values: Sequence[float], n_boot: int = 2000, seed: int = 0, level: float = 0.95
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean (seeded, so it is reproducible)."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) == 0:
        raise ValueError("bootstrap_ci: no values")
    if not np.all(np.isfinite(x)):
        raise ValueError("bootstrap_ci: non-finite values")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), size=(n_boot, len(x)))
    means = x[idx].mean(axis=1)
    a = (1.0 - level) / 2.0
    return (float(np.quantile(means, a)), float(np.quantile(means, 1.0 - a)))


def nav_summary(results: Sequence[EpisodeResult], ci_seed: int = 0) -> dict[str, Any]:
    """Headline record of one agent for ``metrics/nav.json``.

    ``sr``, ``spl``, ``ne``, ``osr``, ``ndtw`` (None when no episode has a reference path), ``sdtw``,
    ``path_length``, ``steps``, ``n_episodes``, ``sr_ci`` (Wilson 95 %) and ``spl_ci`` (bootstrap 95 %).
    """
    report = aggregate(results)
    m = report.metrics

    def mean(k: str) -> float | None:
        s = m.get(k)
        return None if s is None or s.mean is None else float(s.mean)

    sr_vals = [float(r.metrics["success"]) for r in results]
    spl_vals = [float(r.metrics["spl"]) for r in results]
    return {
        "sr": mean("success"),
        "spl": mean("spl"),
        "ne": mean("distance_to_goal"),
        "osr": mean("oracle_success"),
        "ndtw": mean("ndtw"),
        "sdtw": mean("sdtw"),
        "path_length": mean("path_length"),
        "steps": mean("steps"),
        "n_episodes": report.num_episodes,
        "ne_approximate": mean("ne_approximate"),
        "sr_ci": list(wilson_interval(sum(sr_vals), len(sr_vals))),
        "spl_ci": list(bootstrap_ci(spl_vals, seed=ci_seed)),
        "ci_method": {"sr_ci": "wilson 95%", "spl_ci": "percentile bootstrap 95%, 2000 resamples"},
    }


def update_nav_metrics(path: str | Path, protocol: Protocol, agent: str, summary: Mapping[str, Any]) -> Path:
    """Insert/replace one agent's summary in ``metrics/nav.json`` (atomic; same protocol enforced)."""
    from image2sim.eval.protocols import ProtocolMismatchError

    path = Path(path)
    agents: dict[str, Any] = {}
    if path.is_file():
        existing, payload = read_result_file(path)
        if existing != protocol:
            raise ProtocolMismatchError(
                f"{path}: holds results of protocol {existing.name!r}; refusing to add {agent!r} under "
                f"{protocol.name!r} (write to another file)"
            )
        agents = dict(payload.get("agents", {}))
    agents[agent] = dict(summary)
    return write_result_file(path, protocol, {"agents": agents})


def nav_markdown(doc: Mapping[str, Any]) -> str:
    """Table-2 layout of a nav.json document: one row per agent, rates in percent with 95 % CIs."""
    agents = doc.get("agents") or {}
    if not agents:
        raise RunnerError("navigation metrics document has no 'agents'")

    def pct(v: Any) -> str:
        return "n/a" if v is None else f"{100 * v:.1f}"

    def ci(v: Any) -> str:
        return "" if not v else f" [{100 * v[0]:.1f}, {100 * v[1]:.1f}]"

    lines = [
        "| Agent | NE↓ | OSR↑ | SR↑ (95% CI) | SPL↑ (95% CI) | nDTW↑ | Episodes |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, a in agents.items():
        ne = "n/a" if a.get("ne") is None else f"{a['ne']:.2f}"
        lines.append(
            f"| {name} | {ne} | {pct(a.get('osr'))} | {pct(a.get('sr'))}{ci(a.get('sr_ci'))} | "
            f"{pct(a.get('spl'))}{ci(a.get('spl_ci'))} | {pct(a.get('ndtw'))} | {a.get('n_episodes')} |"
        )
    proto = doc.get("protocol") or {}
    text = "\n".join(lines) + "\n"
    approx = {n: a["ne_approximate"] for n, a in agents.items() if a.get("ne_approximate")}
    if approx:
        shares = ", ".join(f"{n} {100 * v:.1f}%" for n, v in approx.items())
        text += (
            f"\nEpisodes ending where the navigation graph does not reach the goal ({shares}) use the "
            "planner's estimate (nearest goal-connected node + straight offset) for NE and success.\n"
        )
    if proto:
        from image2sim.eval.report import describe_protocol

        p = Protocol.from_dict(proto)
        text += f"\nProtocol `{p.name}`: {describe_protocol(p)}\n"
    return text
