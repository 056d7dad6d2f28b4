"""Kinematic agent: discrete actions, micro-stepped collision checks, wall sliding, stuck detection.

The agent is a vertical cylinder (``Embodiment.radius``, ``Embodiment.height``) whose feet stand on a
floor cell of the :class:`NavMap` (map frame). A forward motion is split into micro-steps; each one
is accepted only if (a) the target column has a floor within ``max_step_height`` of the current feet
height (feet snap to it: stairs work, drops/holes/unknown space are rejected) and (b) no obstacle
point in the body band (feet + step height, feet + body height] lies strictly within the radius
(KD-tree query). A blocked micro-step slides along the obstacle boundary: the obstacle normal points
from the centroid of the obstructing points to the agent, the slide direction is the tangent picked
by the sign of the cross product of heading and normal, and the motion is the heading's projection
onto it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from image2sim.simulator.conventions import Action
from image2sim.simulator.navigation.embodiment import Embodiment
from image2sim.simulator.navigation.navmap import HEIGHT_TOLERANCE, NavMap
from scipy.spatial import cKDTree

__all__ = [
    "AgentState",
    "StepInfo",
    "CollisionWorld",
    "Kinematics",
    "StuckDetector",
    "Agent",
    "PlacementError",
    "wrap_angle",
]

_EPS = 1e-9
_HEAD_ON = math.sin(math.radians(5.0))
"""Below 5 degrees of incidence a wall counts as head-on: no slide (the normal from a voxelised
surface's centroid is only accurate to a few degrees)."""


class PlacementError(ValueError):
    """The agent cannot stand where it was placed: no floor within the step height, or obstacle points
    inside its footprint."""


def wrap_angle(a: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


@dataclass
class AgentState:
    """Feet position (3,) in the map frame and heading (yaw about +Z, radians, 0 = +X)."""

    position: np.ndarray
    heading: float

    def copy(self) -> AgentState:
        return AgentState(np.array(self.position, dtype=np.float64), float(self.heading))

    @property
    def direction(self) -> np.ndarray:
        return np.array([math.cos(self.heading), math.sin(self.heading)])


@dataclass
class StepInfo:
    """What one action did."""

    collided: bool
    """A forward micro-step was blocked (whether or not sliding then moved the agent)."""
    slid: bool
    """Wall sliding moved the agent during this step."""
    stuck: bool
    """The stuck detector fired after this step."""
    displacement: float
    """Horizontal distance moved (metres)."""


class CollisionWorld:
    """Static collision geometry of a navigation map: floor columns and body-band obstacle points."""

    def __init__(self, navmap: NavMap) -> None:
        self.navmap = navmap
        self.embodiment = navmap.embodiment
        self.obstacles = np.asarray(navmap.obstacle_xyz, dtype=np.float64)
        self._tree = cKDTree(self.obstacles[:, :2]) if len(self.obstacles) else None
        ny = navmap.shape2d[1]
        # Feet may stand on floor cells and on support cells (floor seen under an obstacle voxel):
        # the column of a stair riser holds only support (the riser covers the tread edge), and
        # without it every riser would be a one-cell hole that no forward micro-step can cross.
        # The graph already counts support as floor for its unknown-space test.
        ij = np.concatenate((navmap.floor_ij, navmap.support_ij.reshape(-1, 2)))
        zs = np.concatenate((navmap.floor_z, navmap.support_z.reshape(-1)))
        keys = ij[:, 0] * ny + ij[:, 1]
        order = np.argsort(keys, kind="stable")
        self._keys = keys[order]
        self._floor_z = zs[order]
        self._ny = ny

    def floor_height(self, xy: np.ndarray, z_ref: float) -> float:
        """Floor (or support) height of the column under ``xy`` closest to ``z_ref`` within the max
        step (NaN if none)."""
        ij = self.navmap.xy_to_ij(np.asarray(xy, dtype=np.float64).reshape(1, 2))[0]
        nx, ny = self.navmap.shape2d
        if not (0 <= ij[0] < nx and 0 <= ij[1] < ny):
            return float("nan")
        key = ij[0] * self._ny + ij[1]
        lo, hi = np.searchsorted(self._keys, [key, key + 1])
        if lo == hi:
            return float("nan")
        z = self._floor_z[lo:hi]
        dz = np.abs(z - z_ref)
        best = int(np.argmin(dz))
        return (
            float(z[best]) if dz[best] <= self.embodiment.max_step_height + HEIGHT_TOLERANCE else float("nan")
        )

    def footprint_obstacles(self, xy: np.ndarray, floor_z: float, radius: float | None = None) -> np.ndarray:
        """Indices of obstacle points strictly inside the footprint disc and in the body band."""
        if self._tree is None:
            return np.zeros(0, dtype=np.int64)
        r = self.embodiment.radius if radius is None else radius
        idx = np.asarray(self._tree.query_ball_point(np.asarray(xy, float)[:2], r=r), dtype=np.int64)
        if len(idx) == 0:
            return idx
        p = self.obstacles[idx]
        d = np.linalg.norm(p[:, :2] - np.asarray(xy, float)[:2], axis=1)
        emb = self.embodiment
        band = (p[:, 2] > floor_z + emb.max_step_height + HEIGHT_TOLERANCE) & (
            p[:, 2] <= floor_z + emb.height
        )
        return idx[band & (d < r - _EPS)]

    def check(self, xy: np.ndarray, z_ref: float) -> tuple[bool, float, np.ndarray]:
        """Can the agent stand at ``xy`` coming from feet height ``z_ref``? -> (ok, floor z, blocking ids)."""
        z = self.floor_height(xy, z_ref)
        if not math.isfinite(z):
            return False, z, np.zeros(0, dtype=np.int64)
        hits = self.footprint_obstacles(xy, z)
        return len(hits) == 0, z, hits


class Kinematics:
    """Applies discrete actions to an :class:`AgentState` in a :class:`CollisionWorld`."""

    def __init__(self, world: CollisionWorld, embodiment: Embodiment | None = None) -> None:
        self.world = world
        self.embodiment = embodiment or world.embodiment

    def apply(self, state: AgentState, action: int) -> tuple[AgentState, bool, bool]:
        """New state after ``action`` -> (state, collided, slid). STOP leaves the state unchanged."""
        action = Action(int(action))
        new = state.copy()
        if action == Action.TURN_LEFT:
            new.heading = wrap_angle(state.heading + self.embodiment.turn_angle)
            return new, False, False
        if action == Action.TURN_RIGHT:
            new.heading = wrap_angle(state.heading - self.embodiment.turn_angle)
            return new, False, False
        if action == Action.STOP:
            return new, False, False
        return self._forward(new)

    def _forward(self, state: AgentState) -> tuple[AgentState, bool, bool]:
        emb = self.embodiment
        n = max(1, int(math.ceil(emb.forward_step / emb.micro_step - 1e-9)))
        delta = emb.forward_step / n
        h = state.direction
        pos = state.position.copy()
        collided = slid = False
        for _ in range(n):
            target = pos[:2] + delta * h
            ok, z, hits = self.world.check(target, pos[2])
            if ok:
                pos = np.array([target[0], target[1], z])
                continue
            collided = True
            if not emb.wall_sliding or len(hits) == 0:
                break  # no floor (drop / hole / unknown) or sliding disabled: stop here
            moved = self._slide(pos, h, delta, hits)
            if moved is None:
                break
            pos = moved
            slid = True
        state.position = pos
        return state, collided, slid

    def _slide(self, pos: np.ndarray, h: np.ndarray, delta: float, hits: np.ndarray) -> np.ndarray | None:
        """One micro-step along the boundary of the obstructing points, or None when that is blocked too."""
        centroid = self.world.obstacles[hits, :2].mean(axis=0)
        normal = pos[:2] - centroid
        norm = float(np.linalg.norm(normal))
        if norm < _EPS:
            return None
        normal /= norm
        cross = h[0] * normal[1] - h[1] * normal[0]
        # Tangent perpendicular to the normal on the side the heading points to.
        tangent = -math.copysign(1.0, cross) * np.array([-normal[1], normal[0]])
        along = float(h @ tangent)
        if along <= _HEAD_ON:  # head-on: nothing to slide along
            return None
        target = pos[:2] + delta * along * tangent
        ok, z, _ = self.world.check(target, pos[2])
        if not ok:
            return None
        return np.array([target[0], target[1], z])


class StuckDetector:
    """Stuck when, over the last ``window`` steps, the net displacement and the total yaw are both small."""

    def __init__(self, embodiment: Embodiment) -> None:
        self.window = int(embodiment.stuck_window)
        self.min_disp = float(embodiment.stuck_min_displacement)
        self.min_yaw = math.radians(embodiment.stuck_min_yaw_deg)
        self._states: deque[tuple[np.ndarray, float]] = deque(maxlen=self.window + 1)

    def reset(self, state: AgentState) -> None:
        self._states.clear()
        self._states.append((state.position[:2].copy(), float(state.heading)))

    def update(self, state: AgentState) -> bool:
        """Record the state after a step; True when the window is full and the agent is stuck."""
        self._states.append((state.position[:2].copy(), float(state.heading)))
        if len(self._states) < self.window + 1:
            return False
        p0, _ = self._states[0]
        disp = float(np.linalg.norm(self._states[-1][0] - p0))
        states = list(self._states)
        yaw = sum(abs(wrap_angle(b[1] - a[1])) for a, b in zip(states[:-1], states[1:], strict=True))
        return disp < self.min_disp and yaw < self.min_yaw - 1e-9


class Agent:
    """One agent: state, kinematics and stuck detector."""

    def __init__(self, world: CollisionWorld, embodiment: Embodiment | None = None) -> None:
        self.kinematics = Kinematics(world, embodiment)
        self.embodiment = self.kinematics.embodiment
        self.world = world
        self.stuck_detector = StuckDetector(self.embodiment)
        self.state = AgentState(np.zeros(3), 0.0)

    def reset(self, position: np.ndarray, heading: float = 0.0) -> AgentState:
        """Place the agent; the feet snap to the floor under ``position``. Raises if it cannot stand there."""
        p = np.asarray(position, dtype=np.float64).reshape(3)
        ok, z, hits = self.world.check(p[:2], p[2])
        if not ok:
            why = (
                "no floor within the step height"
                if not math.isfinite(z)
                else f"{len(hits)} obstacle points in the footprint"
            )
            raise PlacementError(f"cannot place the agent at {np.round(p, 3).tolist()}: {why}")
        self.state = AgentState(np.array([p[0], p[1], z]), wrap_angle(float(heading)))
        self.stuck_detector.reset(self.state)
        return self.state.copy()

    def step(self, action: int) -> StepInfo:
        before = self.state.position[:2].copy()
        self.state, collided, slid = self.kinematics.apply(self.state, action)
        stuck = self.stuck_detector.update(self.state)
        disp = float(np.linalg.norm(self.state.position[:2] - before))
        return StepInfo(collided, slid, stuck, disp)

    @property
    def camera_position(self) -> np.ndarray:
        return self.state.position + np.array([0.0, 0.0, self.embodiment.eye_height])
