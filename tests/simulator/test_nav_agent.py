"""Kinematic agent: collisions, wall sliding, stuck detection, stairs and drops."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.conventions import Action
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.agent import Agent, CollisionWorld, wrap_angle
from image2sim.simulator.navigation.embodiment import Embodiment
from image2sim.simulator.navigation.extract import extract_navmap_from_points

SPACING = 0.04
F, L, R, S = int(Action.MOVE_FORWARD), int(Action.TURN_LEFT), int(Action.TURN_RIGHT), int(Action.STOP)


@functools.cache
def world(name: str):
    w = {
        "box": lambda: syn.box_room(spacing=SPACING),
        "stairs": lambda: syn.two_levels_with_stairs(spacing=SPACING),
        "rooms": lambda: syn.rooms_grid(2, 2, seed=1, furniture=2),
    }[name]()
    m = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    return w, m, CollisionWorld(m)


def agent_at(name: str, x: float, y: float, z: float, heading_deg: float, **emb) -> Agent:
    _, m, cw = world(name)
    a = Agent(cw, Embodiment(**emb) if emb else None)
    a.reset(np.array([x, y, z]), math.radians(heading_deg))
    return a


def footprint_clear(cw: CollisionWorld, agent: Agent) -> bool:
    p = agent.state.position
    return len(cw.footprint_obstacles(p[:2], p[2])) == 0


def test_head_on_wall_blocks_without_sliding():
    a = agent_at("box", 5.70, 2.0, 0.0, 0.0)
    info = a.step(F)
    # Micro-steps of 0.05 m reach x = 5.85 (0.15 m from the wall at x = 6), the next one is blocked.
    assert info.collided and not info.slid
    assert a.state.position[0] == pytest.approx(5.85, abs=1e-9)
    assert a.state.position[1] == pytest.approx(2.0, abs=1e-12)
    info = a.step(F)
    assert info.collided and info.displacement == 0.0


def test_free_forward_step_is_exact():
    a = agent_at("box", 2.0, 2.0, 0.0, 30.0)
    info = a.step(F)
    assert not info.collided and info.displacement == pytest.approx(0.25)
    assert np.allclose(
        a.state.position[:2], [2.0 + 0.25 * math.cos(math.pi / 6), 2.0 + 0.25 * math.sin(math.pi / 6)]
    )


def test_glancing_wall_slides_along_it():
    a = agent_at("box", 5.70, 2.0, 0.0, 30.0)
    info = a.step(F)
    assert info.collided and info.slid
    x, y = a.state.position[:2]
    assert x <= 5.85 + 1e-9  # never closer than the radius to the wall at x = 6
    # Three free micro-steps reach y = 2.075; the two blocked ones slide along +y (the wall tangent on
    # the heading's side) by about 0.05 * sin(30 deg) each.
    assert x > 5.82
    assert y > 2.075 + 0.02
    assert footprint_clear(world("box")[2], a)


def test_corner_blocks_and_stays_clear():
    a = agent_at("box", 5.60, 3.60, 0.0, 45.0)
    for _ in range(3):
        info = a.step(F)
    assert info.collided and info.displacement < 1e-6
    x, y = a.state.position[:2]
    assert 6.0 - x >= 0.15 - 1e-9 and 4.0 - y >= 0.15 - 1e-9


def test_stuck_fires_exactly_after_the_window():
    a = agent_at("box", 5.85, 2.0, 0.0, 0.0)
    flags = [a.step(F).stuck for _ in range(5)]
    assert flags == [False, False, False, True, True]
    assert not a.step(L).stuck  # 15 degrees of yaw in the window: not stuck
    # Turning back and forth: 4 x 15 degrees, not stuck although the agent does not move.
    b = agent_at("box", 3.0, 2.0, 0.0, 0.0)
    assert [b.step(x).stuck for x in (L, R, L, R, L)] == [False] * 5
    # Small moves that add up to less than 0.1 m with no turn: stuck.
    c = agent_at("box", 3.0, 2.0, 0.0, 0.0, forward_step=0.02, micro_step=0.02)
    assert [c.step(F).stuck for _ in range(4)] == [False, False, False, True]


def test_turns_wrap_heading_and_stop_does_nothing():
    a = agent_at("box", 3.0, 2.0, 0.0, 180.0)
    for _ in range(30):
        a.step(L)
        assert -math.pi < a.state.heading <= math.pi
    p = a.state.position.copy()
    info = a.step(S)
    assert not info.collided and np.array_equal(a.state.position, p)
    assert a.state.heading == pytest.approx(wrap_angle(math.pi + 30 * math.radians(15)))


def test_agent_climbs_stairs_and_feet_follow_treads():
    a = agent_at("stairs", 1.5, 0.6, 0.0, 0.0)
    zs = [a.state.position[2]]
    for _ in range(40):
        a.step(F)
        zs.append(a.state.position[2])
    assert zs[-1] == pytest.approx(1.2, abs=0.01)
    assert np.abs(np.diff(zs)).max() <= 0.15 + 0.011
    assert footprint_clear(world("stairs")[2], a)


def test_agent_does_not_walk_off_a_drop():
    x_s = 4.0 - 8 * 0.3 / 2
    a = agent_at("stairs", x_s + 0.4, 2.5, 1.2, 180.0)
    for _ in range(4):
        info = a.step(F)
    assert info.collided
    assert a.state.position[2] == pytest.approx(1.2, abs=0.01)
    assert a.state.position[0] >= x_s - 0.05


def test_reset_rejects_blocked_or_unsupported_positions():
    _, _, cw = world("box")
    with pytest.raises(ValueError, match="obstacle"):
        Agent(cw).reset(np.array([5.9, 2.0, 0.0]))
    with pytest.raises(ValueError, match="no floor"):
        Agent(cw).reset(np.array([20.0, 2.0, 0.0]))


@settings(max_examples=25, deadline=None)
@given(
    start=st.integers(0, 10_000),
    heading=st.floats(-math.pi, math.pi),
    actions=st.lists(st.sampled_from([F, F, F, L, R]), min_size=1, max_size=60),
)
def test_random_actions_never_penetrate_and_flags_are_consistent(start, heading, actions):
    _, m, cw = world("rooms")
    pts = m.map_points
    agent = Agent(cw)
    agent.reset(pts[start % len(pts)], heading)
    emb = agent.embodiment
    for act in actions:
        before = agent.state.copy()
        info = agent.step(act)
        p = agent.state.position
        assert footprint_clear(cw, agent)
        assert -math.pi < agent.state.heading <= math.pi
        assert np.isfinite(p).all() and cw.floor_height(p[:2], p[2]) == pytest.approx(p[2])
        if act == F:
            free_target = before.position[:2] + emb.forward_step * before.direction
            reached = np.allclose(p[:2], free_target, atol=1e-9)
            assert info.collided != reached
            assert info.displacement <= emb.forward_step + 1e-9
        else:
            assert not info.collided and np.array_equal(p, before.position)


@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_wrap_angle_range(a):
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-6) and math.isclose(
        math.sin(w), math.sin(a), abs_tol=1e-6
    )
