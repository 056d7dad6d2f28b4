"""Oracle rollouts of episode plans in the :class:`NeuralSimulator`, stuck truncation and replay.

A rollout resets one agent at the plan's start, lets the :class:`OracleFollower` drive it to the goal
standing point and records every state. Rules (paper appendix): the stuck detector (4-step window,
< 0.1 m net displacement and < 15 degrees of yaw) truncates the rollout at the start of the stuck
window and appends STOP; rollouts with a collision, that do not end within the goal radius, or that
are shorter than ``min_steps`` are dropped with a reason. :func:`replay` re-executes actions from the
start in a fresh simulator (the executability test every written episode passes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from image2sim.simulator.conventions import Action
from image2sim.simulator.navigation.agent import PlacementError

__all__ = [
    "RolloutConfig",
    "Rollout",
    "closest_approach_cut",
    "face_target",
    "rollout_plan",
    "replay",
    "truncate_rollout",
]


@dataclass(frozen=True)
class RolloutConfig:
    """Rollout limits and acceptance rules."""

    max_steps: int = 500
    """Hard cap on actions per episode (the rollout is dropped when reached)."""
    min_steps: int = 8
    """Episodes with fewer actions (STOP included) are dropped."""
    allow_collisions: bool = False
    """Keep rollouts in which a forward step was blocked (wall sliding). Off: every episode is clean."""
    overshoot: float = 1.0
    """A rollout that ends more than this (metres) farther from the goal object than its closest
    approach is cut there and stops there: paths stop at the goal, not past it."""
    face_goal: bool = False
    """Before its final STOP the expert turns in place towards the goal object (to within half a
    turn), so that its last views show what it stops beside. Off: it stops with the heading of its
    last move, which at the data engine's defaults leaves the goal outside the last stored view in
    most episodes (docs/sim2real.md, session 47)."""

    def __post_init__(self) -> None:
        if not self.overshoot >= 0:
            raise ValueError(f"RolloutConfig.overshoot must be >= 0, got {self.overshoot!r}")
        if self.max_steps < 1 or self.min_steps < 1 or self.min_steps > self.max_steps:
            raise ValueError(
                f"RolloutConfig: need 1 <= min_steps <= max_steps, got {self.min_steps}, {self.max_steps}"
            )


@dataclass
class Rollout:
    """A recorded trajectory: T actions and the T + 1 states around them (map frame)."""

    actions: list[int]
    positions: np.ndarray
    """(T + 1, 3) feet positions; row t is the state before action t, the last row the final state."""
    headings: np.ndarray
    """(T + 1,) headings in radians."""
    collided: list[bool]
    """Per action: a forward micro-step was blocked."""
    reason: str = ""
    """"" when accepted, else why it was dropped."""
    truncated_stuck: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.reason

    @property
    def forward_steps(self) -> int:
        return sum(1 for a in self.actions if a == int(Action.MOVE_FORWARD))

    @property
    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions[:, :2], axis=0), axis=1).sum())


def rollout_plan(sim, follower, plan, config: RolloutConfig | None = None) -> Rollout:
    """Drive one agent from ``plan.start`` to ``plan.goal`` with the oracle follower. A start where
    the agent cannot stand is a rejected rollout (reason ``start_blocked``)."""
    cfg = config or RolloutConfig()
    try:
        _, info = sim.reset(np.asarray(plan.start, float)[None], np.array([plan.heading]), observe=False)
    except PlacementError:
        # The graph holds a few nodes whose footprint grazes an obstacle point (the map is a 5 cm grid,
        # the collision check is exact): drop this episode, not the house (2 of 40 houses of seed
        # 3000 lost all their episodes to one such start).
        start = np.asarray(plan.start, float).reshape(1, 3)
        return Rollout([], start, np.array([float(plan.heading)]), [], reason="start_blocked")
    positions = [info["position"][0].copy()]
    headings = [float(info["heading"][0])]
    actions: list[int] = []
    collided: list[bool] = []
    res = follower.reset(positions[0], np.asarray(plan.goal, float))
    if not res.reachable:
        return Rollout([], np.array(positions), np.array(headings), [], reason=f"unplannable: {res.reason}")
    was_collided, stuck_at = False, None
    for _ in range(cfg.max_steps):
        a = int(follower.act(sim.agents[0].state, was_collided))
        _, info = sim.step([a], observe=False)
        actions.append(a)
        positions.append(info["position"][0].copy())
        headings.append(float(info["heading"][0]))
        was_collided = bool(info["collided"][0])
        collided.append(was_collided)
        if a == int(Action.STOP):
            break
        if bool(info["stuck"][0]):
            stuck_at = len(actions)
            break
    else:
        return Rollout(actions, np.array(positions), np.array(headings), collided, reason="max_steps")
    truncated = False
    if stuck_at is not None:
        # Cut the stuck window (it made no progress) and stop where the agent got stuck.
        keep = max(0, stuck_at - int(sim.embodiment.stuck_window))
        actions, collided = actions[:keep] + [int(Action.STOP)], collided[:keep] + [False]
        positions, headings = (
            positions[: keep + 1] + [positions[keep]],
            headings[: keep + 1] + [headings[keep]],
        )
        truncated = True
    r = Rollout(actions, np.array(positions), np.array(headings), collided, truncated_stuck=truncated)
    if not cfg.allow_collisions and any(collided):
        r.reason = "collision"
    elif len(actions) < cfg.min_steps:
        r.reason = "too_short"
    elif np.linalg.norm(r.positions[-1, :2] - np.asarray(plan.goal)[:2]) > plan.goal_radius:
        r.reason = "outside_goal_radius"
    return r


def closest_approach_cut(positions: np.ndarray, target: np.ndarray, overshoot: float) -> int | None:
    """The state index to stop at when the path ends more than ``overshoot`` metres (horizontal) farther
    from ``target`` than its closest approach: the first state at that minimum distance. ``None`` when
    the end is already within ``overshoot`` of it."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    d = np.linalg.norm(p[:, :2] - np.asarray(target, dtype=np.float64)[:2], axis=1)
    if d[-1] - d.min() <= overshoot:
        return None
    return int(np.argmin(d))


def face_target(r: Rollout, target: np.ndarray, turn_angle: float) -> Rollout:
    """``r`` with in-place turns (``turn_angle`` radians each, left = counter-clockwise) inserted
    before its final STOP, the fewest that point its heading at ``target`` (map frame, horizontal)
    to within half a turn. Turns move nobody, so positions repeat; headings follow the simulator's
    wrapping (:func:`~image2sim.simulator.navigation.agent.wrap_angle`)."""
    from image2sim.simulator.navigation.agent import wrap_angle

    if not r.actions or int(r.actions[-1]) != int(Action.STOP):
        raise ValueError("face_target needs a rollout that ends in STOP")
    if not turn_angle > 0:
        raise ValueError(f"turn_angle must be > 0, got {turn_angle!r}")
    end = r.positions[-1]
    offset = np.asarray(target, dtype=np.float64).reshape(-1)[:2] - end[:2]
    if float(np.hypot(*offset)) < 1e-9:  # standing on the target: any heading faces it
        return r
    error = wrap_angle(math.atan2(offset[1], offset[0]) - float(r.headings[-1]))
    n = int(round(abs(error) / turn_angle))
    if n == 0:
        return r
    sign = 1.0 if error > 0 else -1.0
    action = int(Action.TURN_LEFT if error > 0 else Action.TURN_RIGHT)
    heads, h = [], float(r.headings[-1])
    for _ in range(n):
        h = wrap_angle(h + sign * turn_angle)
        heads.append(h)
    keep = len(r.actions) - 1  # states 0..keep, then the turns, then STOP's repeated final state
    return Rollout(
        [int(a) for a in r.actions[:-1]] + [action] * n + [int(Action.STOP)],
        np.concatenate((r.positions[: keep + 1], np.repeat(end[None], n + 1, axis=0))),
        np.concatenate((r.headings[: keep + 1], heads, heads[-1:])),
        list(r.collided[:-1]) + [False] * (n + 1),
        truncated_stuck=r.truncated_stuck,
        extra=dict(r.extra) | {"face_goal_turns": n},
    )


def truncate_rollout(r: Rollout, k: int) -> Rollout:
    """``r`` stopped at state ``k``: its first ``k`` actions, then STOP."""
    if not 0 <= k < len(r.positions):
        raise ValueError(f"cannot cut a rollout of {len(r.positions)} states at state {k}")
    return Rollout(
        [int(a) for a in r.actions[:k]] + [int(Action.STOP)],
        np.concatenate((r.positions[: k + 1], r.positions[k : k + 1])),
        np.concatenate((r.headings[: k + 1], r.headings[k : k + 1])),
        list(r.collided[:k]) + [False],
        truncated_stuck=r.truncated_stuck,
        extra=dict(r.extra),
    )


def replay(sim, start: np.ndarray, heading: float, actions) -> tuple[np.ndarray, np.ndarray, list[bool]]:
    """Re-execute ``actions`` from (start, heading) -> (positions (T + 1, 3), headings, collided flags)."""
    _, info = sim.reset(np.asarray(start, float)[None], np.array([heading]), observe=False)
    pos, head, col = [info["position"][0].copy()], [float(info["heading"][0])], []
    for a in actions:
        _, info = sim.step([int(a)], observe=False)
        pos.append(info["position"][0].copy())
        head.append(float(info["heading"][0]))
        col.append(bool(info["collided"][0]))
    return np.array(pos), np.array(head), col
