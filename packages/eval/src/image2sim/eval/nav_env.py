"""Navigation environments for the evaluation runner: simulator backends that place the agent at an
episode's start, apply discrete actions and report world-frame positions and the geodesic distance to
the goal (habitat-lab's *env*).

* :class:`NeuralSimBackend` over a :class:`~image2sim.simulator.sim.NeuralSimulator` built from a
  scene folder (:func:`load_scene_backend`) or from a procedural capture's exact renderer
  (:func:`load_exact_backend`);
* :class:`HabitatBackend`, behind an import guard (habitat-sim is optional).

The agents are in :mod:`image2sim.eval.nav_agents`, the episode loop in :mod:`image2sim.eval.runner`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from typing import Protocol as TypingProtocol

import numpy as np
from image2sim.eval.datasets import NavEpisode
from image2sim.eval.protocols import Protocol
from image2sim.simulator.conventions import Action
from image2sim.simulator.geometry.habitat import (
    habitat_heading,
    habitat_rotation_for_heading,
    habitat_to_world,
    world_to_habitat,
)

__all__ = [
    "BackendUnavailable",
    "HabitatBackend",
    "NeuralSimBackend",
    "RunnerError",
    "StepObservation",
    "check_embodiment",
    "embodiment_for",
    "equirect_crop",
    "habitat_to_world_point",
    "import_habitat_sim",
    "load_exact_backend",
    "load_scene_backend",
]


class RunnerError(RuntimeError):
    """The run cannot proceed as configured (message names the scene / episode / field)."""

    cli_exit_code = 2  # bad input: the CLI's error boundary answers it with one line, status 2


class BackendUnavailable(ImportError):
    """An optional simulator backend is not installed."""


# ------------------------------------------------------------------------------------------ backends


@dataclass
class StepObservation:
    """What a backend reports after reset and after every action (world frame)."""

    position: np.ndarray
    """(3,) feet position, world metres (Z-up)."""
    heading: float
    """Heading in radians (map frame yaw; equal to world yaw without gravity correction)."""
    distance_to_goal: float | None
    """Geodesic distance to the goal in metres (inf when off the graph / unreachable; None when the
    episode has no goal, as on a test split)."""
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
        if self.field is None:  # no goal (test split): there is no distance to report
            self._last_dist, self._last_reason = None, "the episode has no goal"
        elif self._last_pos is None or not np.array_equal(pos_map, self._last_pos):
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
        self.goal_map, self.field = None, None
        if episode.has_goal:
            self.goal_map = np.asarray(self.sim.navmap.to_map(episode.goal_position), np.float64).reshape(3)
            self.field = self.sim.planner.distance_field(self.goal_map)
        self.sim.set_goal(None if not episode.has_goal else np.asarray(episode.goal_position, np.float64))
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
    (:func:`~image2sim.simulator.geometry.habitat.world_to_habitat`; the start rotation is the
    upright one of the episode's heading); positions and headings come back the same way. The
    geodesic distance is the pathfinder's shortest path length (``habitat_sim.ShortestPath``); inf
    with a reason when none.
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
        self._last: tuple[np.ndarray, float | None, str] | None = None

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
        if self.goal_habitat is None:  # no goal (test split)
            self._last = (pos_h, None, "the episode has no goal")
        elif self._last is None or not np.array_equal(pos_h, self._last[0]):
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
        self.goal_habitat = world_to_habitat(episode.goal_position) if episode.has_goal else None
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
    """One Habitat-frame point as a (3,) world point (:func:`habitat_to_world`)."""
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
        from image2sim.simulator.sim import GaussianRenderFn, gaussian_tensors

        tensors = gaussian_tensors(GaussianScene.load(folder).gaussians)
        tensors.pop("features", None)  # the agent sees colours: splatting feature channels is wasted work
        render_fn = GaussianRenderFn(tensors)
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
