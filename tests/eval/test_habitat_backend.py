"""HabitatBackend's logic against a small fake ``habitat_sim`` (habitat-sim cannot be installed here).

The fake implements the part of habitat-sim's API the adapter uses, with Habitat's conventions: Y-up,
the agent looks along its local -Z, ``turn_left`` is a positive yaw about +Y, rotations are
numpy-quaternion-like objects (``.x .y .z .w``) and accepted as ``[x, y, z, w]`` coefficients. Its
world is one flat square room (x, z in [-HALF, HALF]) whose pathfinder returns straight-line
lengths; goals outside the room have no path.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import types

import numpy as np
import pytest
from image2sim.eval.datasets import Instruction, NavEpisode
from image2sim.eval.protocols import RXR_HABITAT, VLNCE
from image2sim.eval.runner import (
    BackendUnavailable,
    ForwardAgent,
    HabitatBackend,
    RunConfig,
    RunnerError,
    run_episode,
    run_nav_results,
)
from image2sim.simulator.conventions import Action
from image2sim.simulator.geometry.habitat import world_to_habitat

HALF = 4.0


class _Quat:
    def __init__(self, x: float, y: float, z: float, w: float) -> None:
        self.x, self.y, self.z, self.w = x, y, z, w


def _yaw(q) -> float:
    x, y, z, w = (q.x, q.y, q.z, q.w) if hasattr(q, "w") else tuple(np.asarray(q, float))
    assert abs(x) < 1e-9 and abs(z) < 1e-9, "the fake supports yaw-only rotations"
    return 2.0 * math.atan2(y, w)


def make_fake_habitat_sim() -> types.ModuleType:
    hs = types.ModuleType("habitat_sim")
    agent_mod = types.ModuleType("habitat_sim.agent")
    hs.agent = agent_mod
    hs.SensorType = types.SimpleNamespace(COLOR="COLOR", DEPTH="DEPTH")
    hs.created = []

    class Spec(types.SimpleNamespace):
        pass

    class CameraSensorSpec(Spec):
        kind = "pinhole"

    class EquirectangularSensorSpec(Spec):
        kind = "equirect"

    hs.SimulatorConfiguration = Spec
    hs.CameraSensorSpec = CameraSensorSpec
    hs.EquirectangularSensorSpec = EquirectangularSensorSpec
    agent_mod.AgentConfiguration = Spec
    agent_mod.ActuationSpec = lambda amount: types.SimpleNamespace(amount=amount)
    agent_mod.ActionSpec = lambda name, actuation: types.SimpleNamespace(name=name, actuation=actuation)

    class Configuration:
        def __init__(self, sim_cfg, agents):
            self.sim_cfg, self.agents = sim_cfg, agents

    hs.Configuration = Configuration

    class AgentState:
        def __init__(self):
            self.position = np.zeros(3)
            self.rotation = _Quat(0.0, 0.0, 0.0, 1.0)

    hs.AgentState = AgentState

    class ShortestPath:
        def __init__(self):
            self.requested_start = self.requested_end = None
            self.geodesic_distance = math.inf

    hs.ShortestPath = ShortestPath

    def inside(p) -> bool:
        return abs(p[0]) <= HALF and abs(p[2]) <= HALF

    class PathFinder:
        is_loaded = True

        def find_path(self, path) -> bool:
            a, b = np.asarray(path.requested_start, float), np.asarray(path.requested_end, float)
            if not (inside(a) and inside(b)):
                path.geodesic_distance = math.inf
                return False
            path.geodesic_distance = float(np.linalg.norm((b - a)[[0, 2]]))
            return True

    class Agent:
        def __init__(self, cfg, sim):
            self.cfg, self.sim = cfg, sim
            self.position, self.yaw = np.zeros(3), 0.0
            self.set_states = []

        def set_state(self, state):
            self.set_states.append(state)
            self.position = np.asarray(state.position, float).copy()
            self.yaw = _yaw(state.rotation)

        def get_state(self):
            s = AgentState()
            s.position = self.position.copy()
            s.rotation = _Quat(0.0, math.sin(self.yaw / 2), 0.0, math.cos(self.yaw / 2))
            return s

    class Simulator:
        def __init__(self, cfg):
            self.config = cfg
            self.pathfinder = PathFinder()
            self.agent = None
            self.closed = False
            hs.created.append(self)

        def initialize_agent(self, agent_id):
            assert agent_id == 0
            self.agent = Agent(self.config.agents[0], self)
            return self.agent

        def get_sensor_observations(self):
            h, w = self.config.agents[0].sensor_specifications[0].resolution
            return {"rgb": np.full((h, w, 4), 200, np.uint8)}

        def step(self, name):
            a = self.agent
            amount = a.cfg.action_space[name].actuation.amount
            collided = False
            if name == "move_forward":
                new = a.position + amount * np.array([-math.sin(a.yaw), 0.0, -math.cos(a.yaw)])
                if not inside(new):
                    collided = True
                    slide = self.config.sim_cfg.allow_sliding
                    new = np.clip(new, -HALF, HALF) if slide else a.position
                a.position = new
            elif name == "turn_left":
                a.yaw += math.radians(amount)
            elif name == "turn_right":
                a.yaw -= math.radians(amount)
            else:
                raise KeyError(name)
            obs = self.get_sensor_observations()
            obs["collided"] = collided
            return obs

        def close(self):
            self.closed = True

    hs.Simulator = Simulator
    return hs


@pytest.fixture
def fake_hs(monkeypatch):
    hs = make_fake_habitat_sim()
    monkeypatch.setitem(sys.modules, "habitat_sim", hs)
    monkeypatch.setitem(sys.modules, "habitat_sim.agent", hs.agent)
    return hs


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "mp3d" / "fake" / "fake.glb"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"glTF")
    return path


def episode(start, heading, goal, eid="ep-1") -> NavEpisode:
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    return NavEpisode(
        episode_id=eid,
        scene_id="mp3d/fake/fake.glb",
        start_position=start,
        start_rotation=np.array([math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)]),
        start_heading=heading,
        goal_position=goal,
        goal_radius=3.0,
        geodesic_distance=float(np.linalg.norm(goal - start)),
        reference_path=np.stack([start, goal]),
        instruction=Instruction(text="Walk ahead."),
    )


def test_without_habitat_sim_the_backend_is_unavailable(monkeypatch, scene_file):
    monkeypatch.setitem(sys.modules, "habitat_sim", None)  # import raises ImportError
    with pytest.raises(BackendUnavailable, match="habitat-sim"):
        HabitatBackend(scene_file, VLNCE)


@pytest.mark.parametrize("protocol", [VLNCE, RXR_HABITAT])
def test_configuration_follows_the_protocol(fake_hs, scene_file, protocol):
    backend = HabitatBackend(scene_file, protocol)
    cfg = fake_hs.created[-1].config
    assert cfg.sim_cfg.scene_id == str(scene_file) and cfg.sim_cfg.allow_sliding is protocol.allow_sliding
    (agent,) = cfg.agents
    assert agent.height == protocol.agent_height_m and agent.radius == protocol.agent_radius_m
    amounts = {k: v.actuation.amount for k, v in agent.action_space.items()}
    assert amounts == {
        "move_forward": protocol.forward_step_m,
        "turn_left": protocol.turn_angle_deg,
        "turn_right": protocol.turn_angle_deg,
    }
    (sensor,) = agent.sensor_specifications
    cam = protocol.camera
    assert sensor.kind == "pinhole" and sensor.uuid == "rgb" and sensor.sensor_type == "COLOR"
    assert sensor.resolution == [cam.height, cam.width] and sensor.hfov == cam.hfov_deg
    assert sensor.position == [0.0, protocol.eye_height_m, 0.0]
    if protocol.name == "vlnce":  # Habitat's default RGB sensor height on R2R-CE's 1.5 m agent
        assert (protocol.eye_height_m, protocol.agent_height_m) == (1.25, 1.5)
    assert backend.name == "fake"


def test_reset_and_steps_round_trip_through_the_habitat_frame(fake_hs, scene_file):
    backend = HabitatBackend(scene_file, VLNCE)
    heading = math.radians(30.0)
    ep = episode([1.0, -0.5, 0.0], heading, [3.0, 2.0, 0.0])
    obs = backend.reset(ep, observe=True)
    sent = backend.agent.set_states[-1]
    np.testing.assert_allclose(sent.position, world_to_habitat(ep.start_position))
    # A world yaw about +Z is the same yaw about Habitat's +Y; Habitat's identity looks along our +Y.
    assert _yaw(sent.rotation) == pytest.approx(heading - math.pi / 2)
    np.testing.assert_allclose(obs.position, ep.start_position, atol=1e-12)
    assert obs.heading == pytest.approx(heading)
    assert obs.distance_to_goal == pytest.approx(np.linalg.norm(ep.goal_position - ep.start_position))
    assert obs.rgb.shape == (224, 224, 3) and obs.rgb.dtype == np.uint8
    # MOVE_FORWARD goes forward_step_m along the heading in our world; turns change the heading only.
    obs = backend.step(int(Action.MOVE_FORWARD))
    expected = ep.start_position + 0.25 * np.array([math.cos(heading), math.sin(heading), 0.0])
    np.testing.assert_allclose(obs.position, expected, atol=1e-9)
    assert obs.rgb is None and not obs.collided
    assert obs.distance_to_goal == pytest.approx(np.linalg.norm(ep.goal_position - expected))
    obs = backend.step(int(Action.TURN_LEFT))
    assert obs.heading == pytest.approx(heading + math.radians(15.0))
    obs = backend.step(int(Action.TURN_RIGHT))
    obs = backend.step(int(Action.TURN_RIGHT))
    assert obs.heading == pytest.approx(heading - math.radians(15.0))
    np.testing.assert_allclose(obs.position, expected, atol=1e-9)
    with pytest.raises(RunnerError, match="STOP"):
        backend.step(int(Action.STOP))


def test_collisions_slide_or_stop_as_the_protocol_says(fake_hs, scene_file):
    # 10 cm from the wall x = HALF, heading 45 degrees into it.
    ep = episode([HALF - 0.1, 0.0, 0.0], math.pi / 4, [0.0, 0.0, 0.0])
    for protocol, slides in ((VLNCE, True), (RXR_HABITAT, False)):
        backend = HabitatBackend(scene_file, protocol)
        assert fake_hs.created[-1].config.sim_cfg.allow_sliding is slides
        start = backend.reset(ep).position
        obs = backend.step(int(Action.MOVE_FORWARD))
        assert obs.collided
        along = protocol.forward_step_m * math.sin(math.pi / 4)
        if slides:  # the fake slides along the wall: x stops at the wall, y keeps its share
            np.testing.assert_allclose(obs.position, [HALF, along, 0.0], atol=1e-9)
        else:
            np.testing.assert_allclose(obs.position, start, atol=1e-9)


def test_episode_through_the_runner_and_unreachable_goals(fake_hs, scene_file):
    backend = HabitatBackend(scene_file, VLNCE)
    ep = episode([0.0, 0.0, 0.0], math.pi / 2, [0.0, 2.0, 0.0])  # 8 forward steps straight ahead
    result, actions = run_episode(backend, ForwardAgent(forward_steps=8), ep, VLNCE, seed=0)
    assert actions == [int(Action.MOVE_FORWARD)] * 8 + [int(Action.STOP)]
    assert result.metrics["distance_to_goal"] == pytest.approx(0.0, abs=1e-9)
    assert result.metrics["success"] == 1.0 and result.metrics["path_length"] == pytest.approx(2.0)
    assert result.metrics["spl"] == pytest.approx(1.0)
    far = episode([0.0, 0.0, 0.0], 0.0, [50.0, 0.0, 0.0], eid="far")
    obs = backend.reset(far)
    assert obs.distance_to_goal == math.inf and "no path" in obs.distance_reason
    with pytest.raises(RunnerError, match="episode far: the agent starts .*no path"):
        run_episode(backend, ForwardAgent(forward_steps=1), far, VLNCE, seed=0)


def test_run_nav_with_the_habitat_backend_loads_the_episode_scene_file(fake_hs, scene_file, tmp_path):
    root = scene_file.parents[2]
    eps = [
        episode([0.0, 0.0, 0.0], math.pi / 2, [0.0, 2.0, 0.0], eid="a"),
        episode([1.0, 0.0, 0.0], math.pi, [-1.0, 0.0, 0.0], eid="b"),
    ]
    cfg = RunConfig(agent="forward", agent_options={"forward_steps": 8}, backend="habitat")
    results = run_nav_results(eps, root, VLNCE, cfg, tmp_path / "run", show_progress=False)
    assert [r.episode_id for r in results] == ["a", "b"]
    assert all(r.metrics["success"] == 1.0 for r in results)
    assert fake_hs.created[-1].config.sim_cfg.scene_id == str(scene_file)
    assert fake_hs.created[-1].closed
    missing = [dataclasses.replace(eps[0], scene_id="mp3d/nope/nope.glb")]
    with pytest.raises(RunnerError, match="nope.glb not found"):
        run_nav_results(missing, root, VLNCE, cfg, tmp_path / "run2", show_progress=False)
    with pytest.raises(RunnerError, match="backend"):
        RunConfig(backend="isaac")
