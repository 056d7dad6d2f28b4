"""Oracle follower: smoothed planner waypoints -> lookahead pure pursuit -> discrete actions."""

from __future__ import annotations

import math

import numpy as np
from image2sim.simulator.conventions import Action
from image2sim.simulator.navigation.agent import AgentState, Kinematics, wrap_angle
from image2sim.simulator.navigation.embodiment import Embodiment, FollowerConfig
from image2sim.simulator.navigation.navmap import HEIGHT_TOLERANCE
from image2sim.simulator.navigation.planner import PathResult, Planner

__all__ = ["smooth_path", "pure_pursuit_action", "OracleFollower", "ReferencePathFollower"]


def smooth_path(waypoints: np.ndarray, window: int = 5) -> np.ndarray:
    """Centred moving average of (P, 3) waypoints; the end points are kept exactly.

    Near the ends the window shrinks symmetrically so the start and goal do not move.
    """
    pts = np.asarray(waypoints, dtype=np.float64)
    if window <= 1 or len(pts) < 3:
        return pts.copy()
    half = window // 2
    out = pts.copy()
    csum = np.vstack((np.zeros((1, pts.shape[1])), np.cumsum(pts, axis=0)))
    n = len(pts)
    idx = np.arange(n)
    h = np.minimum(np.minimum(idx, n - 1 - idx), half)
    out = (csum[idx + h + 1] - csum[idx - h]) / (2 * h + 1)[:, None]
    return out


def pure_pursuit_action(state: AgentState, target_xy: np.ndarray, turn_tolerance: float) -> int:
    """Turn towards ``target_xy`` while the heading error exceeds ``turn_tolerance``, else go forward."""
    d = np.asarray(target_xy, float)[:2] - state.position[:2]
    err = wrap_angle(math.atan2(d[1], d[0]) - state.heading)
    if err > turn_tolerance:
        return int(Action.TURN_LEFT)
    if err < -turn_tolerance:
        return int(Action.TURN_RIGHT)
    return int(Action.MOVE_FORWARD)


class OracleFollower:
    """Plans with a :class:`Planner`, smooths the waypoints and emits discrete actions (pure pursuit)."""

    def __init__(
        self,
        planner: Planner,
        embodiment: Embodiment | None = None,
        config: FollowerConfig | None = None,
        kinematics: Kinematics | None = None,
    ) -> None:
        """``kinematics`` (optional) lets the oracle predict a forward step: a step that would collide
        is replaced by a turn towards the target (the oracle knows the simulator)."""
        self.planner = planner
        self.kinematics = kinematics
        self._blocked_turn: int | None = None
        self._blocked_at: list[np.ndarray] = []
        self._cycling = False
        self.embodiment = embodiment or planner.graph.embodiment
        self.config = config or FollowerConfig()
        tol = self.config.turn_tolerance_deg
        self.turn_tolerance = (
            math.radians(tol) if tol is not None else 0.5 * self.embodiment.turn_angle + 1e-6
        )
        self.goal: np.ndarray | None = None
        self.path: np.ndarray = np.zeros((0, 3))
        self._arc: np.ndarray = np.zeros(0)  # cumulative length of ``path`` (set with it: _follow)
        self.result: PathResult | None = None
        self._progress = 0

    def reset(self, start: np.ndarray, goal: np.ndarray) -> PathResult:
        """Plan from ``start`` to ``goal`` (map frame feet positions)."""
        self.goal = np.asarray(goal, dtype=np.float64).reshape(3)
        return self._plan(np.asarray(start, dtype=np.float64).reshape(3))

    def _plan(self, start: np.ndarray) -> PathResult:
        assert self.goal is not None
        self.result = self.planner.shortest_path(start, self.goal)
        self._follow(self.result.waypoints if self.result.reachable else np.zeros((0, 3)))
        return self.result

    def _follow(self, waypoints: np.ndarray) -> None:
        """Start following ``waypoints`` (smoothed) from their beginning."""
        self.path = smooth_path(waypoints, self.config.smoothing_window) if len(waypoints) else waypoints
        seg = np.linalg.norm(np.diff(self.path, axis=0), axis=1)
        self._arc = np.concatenate(([0.0], np.cumsum(seg)))
        self._progress = 0
        self._blocked_at, self._cycling = [], False

    def act(self, state: AgentState, collided: bool = False) -> int:
        """Next action for the agent in ``state``; STOP within ``stop_radius`` or when no path exists."""
        if self.goal is None:
            raise RuntimeError("OracleFollower.act called before reset(start, goal)")
        pos = state.position
        if self._arrived(pos):
            return int(Action.STOP)
        if len(self.path) == 0:
            return int(Action.STOP)
        dist = np.linalg.norm(self.path[:, :2] - pos[:2], axis=1)
        nearest = self._nearest_ahead(dist)
        if collided or dist[nearest] > self.config.replan_distance:
            if not self._plan(pos).reachable:
                return int(Action.STOP)
            dist = np.linalg.norm(self.path[:, :2] - pos[:2], axis=1)
            nearest = self._nearest_ahead(dist)
        if nearest > self._progress:
            self._blocked_at, self._cycling = [], False
        self._progress = nearest
        target = self._target(pos, dist, nearest)
        if self._blocked_turn is not None and self.kinematics is not None:
            # Blocked last time: keep turning the same way until a forward step is free, then take
            # it. Handing control back to pursuit while still blocked makes the agent dither
            # left/right on the spot (seen at the foot of the HM3D staircase next to the newel post).
            if not self._forward_blocked(state, target):
                self._blocked_turn = None
                return int(Action.MOVE_FORWARD)
            return self._blocked_turn
        action = pure_pursuit_action(state, target[:2], self.turn_tolerance)
        if action == Action.MOVE_FORWARD and self.kinematics is not None:
            if self._forward_blocked(state, target):
                # Blocked again where it was blocked before (no path progress since): a cycle.
                n = self.config.slide_when_cycling
                self._cycling = (
                    n > 0 and sum(np.linalg.norm(p - pos[:2]) < 0.05 for p in self._blocked_at) >= n - 1
                )
                self._blocked_at.append(pos[:2].copy())
                # Keep turning the same way until the forward step is free (no left/right dithering).
                if self._blocked_turn is None:
                    d = target[:2] - pos[:2]
                    err = wrap_angle(math.atan2(d[1], d[0]) - state.heading)
                    self._blocked_turn = int(Action.TURN_LEFT if err >= 0 else Action.TURN_RIGHT)
                return self._blocked_turn
        self._blocked_turn = None
        return action

    def _arrived(self, pos: np.ndarray) -> bool:
        """Within ``stop_radius`` of the goal (horizontally)."""
        assert self.goal is not None
        return bool(np.linalg.norm(self.goal[:2] - pos[:2]) <= self.config.stop_radius)

    def _forward_blocked(self, state: AgentState, target: np.ndarray) -> bool:
        """Would MOVE_FORWARD collide? Once avoidance cycles (blocked ``config.slide_when_cycling``
        times at the same spot without path progress), a colliding step that still gets closer to
        the target (wall sliding) is accepted: the graph's column model and the agent's point
        footprint disagree by a few centimetres next to thin obstacles (posts, railings), and pure
        avoidance then loops."""
        assert self.kinematics is not None
        new, would_collide, _ = self.kinematics.apply(state, Action.MOVE_FORWARD)
        if not would_collide:
            return False
        if not self._cycling:
            return True
        before = np.linalg.norm(target[:2] - state.position[:2])
        after = np.linalg.norm(target[:2] - new.position[:2])
        return not after < before - 0.25 * self.embodiment.micro_step

    def _nearest_ahead(self, dist: np.ndarray) -> int:
        """Nearest path point at or after the progress made so far, searched only over the next
        ``lookahead + replan_distance`` metres *of path*. Progress is monotone, so loops back to passed
        points cannot trap the agent; the window keeps a path that turns back on itself (a detour
        out to a point and back) from being skipped where its two legs run side by side."""
        arc = self._arc
        window = self.config.lookahead + self.config.replan_distance
        end = int(np.searchsorted(arc, arc[self._progress] + window, side="right"))
        return self._progress + int(np.argmin(dist[self._progress : max(end, self._progress + 1)]))

    def _target(self, pos: np.ndarray, dist: np.ndarray, nearest: int) -> np.ndarray:
        """Farthest path point within the lookahead (metres along the path from the nearest point)
        that the agent sees through navigable cells.

        Plain pure pursuit cuts corners (door frames); requiring line of sight over navigable cells
        (clearance >= radius) keeps the straight-line motion collision-free. Measuring the lookahead
        along the path, not from the agent, keeps the target from jumping to a later part of the
        path that happens to lie near (the way back of a detour).
        """
        arc = self._arc
        beyond = np.flatnonzero(arc[nearest:] - arc[nearest] >= self.config.lookahead)
        last = nearest + int(beyond[0]) if len(beyond) else len(self.path) - 1
        for j in range(last, nearest, -1):
            if self._line_of_sight(pos, self.path[j]):
                return self.path[j]
        return self.path[min(nearest + 1, len(self.path) - 1)]

    def _line_of_sight(self, a: np.ndarray, b: np.ndarray) -> bool:
        graph = self.planner.graph
        n = max(2, int(np.ceil(np.linalg.norm(b[:2] - a[:2]) / (0.5 * graph.voxel_size))) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        idx, off = graph.snap(a + (b - a) * t)
        if not ((idx >= 0).all() and (off <= 0.75 * graph.voxel_size).all()):
            return False
        # On stairs a straight line can cut across a flight from the side: the floor under it must
        # change by at most a step between consecutive samples (otherwise the agent would be blocked
        # by a riser and the oracle would turn in place forever).
        z = graph.nodes[idx, 2]
        if len(z) > 1 and np.abs(np.diff(z)).max() > self.embodiment.max_step_height + HEIGHT_TOLERANCE:
            return False
        # Discrete turns leave up to half a turn of heading error: keep that much lateral margin.
        margin = self.config.lookahead * math.sin(self.turn_tolerance)
        return bool((graph.clearance[idx[1:]] >= self.embodiment.radius + margin).all())


class ReferencePathFollower(OracleFollower):
    """The oracle of instruction episodes: follows a *reference path* (the route the instruction
    describes) instead of the shortest path to its end.

    From any state it rejoins the reference path at the nearest point not behind the progress made
    so far (3D distance, so the storey counts), a little ahead of it (``rejoin_ahead`` metres), by the
    planner's shortest path, and then follows the reference points to their end (the goal). Leaving
    the path by more than ``config.replan_distance`` or colliding rejoins again (the parent's pure
    pursuit, line-of-sight targets and blocked-step handling are unchanged). A rejoin point the
    planner cannot reach falls back to the shortest path to the goal.
    """

    def __init__(
        self,
        planner: Planner,
        reference_path: np.ndarray,
        embodiment: Embodiment | None = None,
        config: FollowerConfig | None = None,
        kinematics: Kinematics | None = None,
        rejoin_ahead: float = 0.5,
    ) -> None:
        super().__init__(planner, embodiment, config, kinematics)
        ref = np.asarray(reference_path, dtype=np.float64)
        if ref.ndim != 2 or ref.shape[1] != 3 or len(ref) == 0:
            raise ValueError(f"reference_path must be a non-empty (P, 3) array, got shape {ref.shape}")
        if not np.isfinite(ref).all():
            raise ValueError("reference_path holds NaN/inf points")
        self.reference = ref
        self.rejoin_ahead = float(rejoin_ahead)
        self.reference_progress = 0
        """Index of the reference point the agent last rejoined at (monotone over an episode)."""

    def reset(self, start: np.ndarray, goal: np.ndarray | None = None) -> PathResult:
        """Follow the reference path from ``start``; ``goal`` defaults to its last point."""
        self.goal = self.reference[-1].copy() if goal is None else np.asarray(goal, float).reshape(3)
        self.reference_progress = 0
        return self._plan(np.asarray(start, dtype=np.float64).reshape(3))

    def rejoin_index(self, position: np.ndarray) -> int:
        """Reference index to head for from ``position``: the nearest point at or after the progress
        made so far, moved ``rejoin_ahead`` metres further along the path."""
        ref = self.reference
        d = np.linalg.norm(ref[self.reference_progress :] - np.asarray(position, float)[None], axis=1)
        j = self.reference_progress + int(np.argmin(d))
        self.reference_progress = j
        seg = np.linalg.norm(np.diff(ref[j:], axis=0), axis=1)
        ahead = np.flatnonzero(np.cumsum(seg) >= self.rejoin_ahead)
        return j + 1 + int(ahead[0]) if len(ahead) else len(ref) - 1

    def _arrived(self, pos: np.ndarray) -> bool:
        """Near the goal *and* at the end of the route: a reference path may pass its own end
        earlier (a loop, a detour that comes back), and stopping there would skip the rest."""
        if not super()._arrived(pos):
            return False
        if len(self.path) == 0:
            return True
        dist = np.linalg.norm(self.path[:, :2] - pos[:2], axis=1)
        remaining = self._arc[-1] - self._arc[self._nearest_ahead(dist)]
        return bool(remaining <= self.config.lookahead + self.config.stop_radius)

    def _plan(self, start: np.ndarray) -> PathResult:
        assert self.goal is not None
        k = self.rejoin_index(start)
        head = self.planner.shortest_path(start, self.reference[k])
        if not head.reachable:
            return super()._plan(start)
        pts = np.vstack((head.waypoints, self.reference[k + 1 :], self.goal[None]))
        length = head.length + float(
            np.linalg.norm(np.diff(pts[len(head.waypoints) - 1 :], axis=0), axis=1).sum()
        )
        self.result = PathResult(pts, head.nodes, length, head.cost, "")
        self._follow(pts)
        return self.result
