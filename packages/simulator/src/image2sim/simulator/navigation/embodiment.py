"""Typed configuration of the navigation substrate: the agent's body and the map/graph/follower knobs.

Defaults follow the seed paper's appendix (radius 0.15 m, eye height 1.25 m, 0.25 m forward steps,
15 degree turns, 0.15 m maximum step height, 0.05 m voxels, 0.3 m neighbour radius, r_safe = 5 x
radius, 4-step stuck window). Every config is a frozen dataclass; ``from_dict`` rejects unknown keys
and names the offending field.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, TypeVar

__all__ = [
    "Embodiment",
    "NavMapConfig",
    "GraphConfig",
    "FollowerConfig",
    "ConfigError",
    "config_from_dict",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is unknown, missing or out of range; the message names the field."""


def config_from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build the dataclass ``cls`` from ``data``; unknown keys raise :class:`ConfigError`.

    ``where`` (e.g. a file name) prefixes error messages so a user knows which file to fix.
    """
    data = dict(data or {})
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - known)
    prefix = f"{where}: " if where else ""
    if unknown:
        raise ConfigError(f"{prefix}unknown {cls.__name__} field(s) {unknown}; known: {sorted(known)}")
    try:
        return cls(**data)  # type: ignore[call-arg]
    except TypeError as err:
        raise ConfigError(f"{prefix}{cls.__name__}: {err}") from None
    except ConfigError as err:
        raise ConfigError(f"{prefix}{err}") from None


def _check_positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ConfigError(f"{type(obj).__name__}.{name} must be a positive finite number, got {value!r}")


def _check_nonnegative(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ConfigError(
                f"{type(obj).__name__}.{name} must be a non-negative finite number, got {value!r}"
            )


class _DictMixin:
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (``from_dict(to_dict())`` round-trips)."""
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
        """Build from a mapping; unknown keys are an error."""
        return config_from_dict(cls, data, where)


@dataclass(frozen=True)
class Embodiment(_DictMixin):
    """The simulated body: size, camera height and the discrete action space (VLN-CE / Habitat)."""

    radius: float = 0.15
    """Agent (cylinder) radius in metres; the footprint must stay this far from obstacles."""
    height: float = 1.5
    """Body height in metres: obstacles between ``max_step_height`` and this height above the feet block."""
    eye_height: float = 1.25
    """Camera height above the feet in metres (observations are rendered from here)."""
    forward_step: float = 0.25
    """Distance of one MOVE_FORWARD action in metres."""
    turn_angle_deg: float = 15.0
    """Rotation of one TURN_LEFT / TURN_RIGHT action in degrees."""
    max_step_height: float = 0.15
    """Largest height change (metres) the feet may climb or descend between neighbouring positions."""
    micro_step: float = 0.05
    """Forward motion is checked in increments of at most this many metres (collision micro-steps)."""
    stuck_window: int = 4
    """Number of recent steps over which stuck detection looks."""
    stuck_min_displacement: float = 0.1
    """Stuck when the net displacement over the window is below this (metres) ..."""
    stuck_min_yaw_deg: float = 15.0
    """... and the total absolute yaw change over the window is below this (degrees)."""
    wall_sliding: bool = True
    """Slide along obstacle boundaries when a forward micro-step is blocked."""

    def __post_init__(self) -> None:
        _check_positive(
            self, "radius", "height", "eye_height", "forward_step", "turn_angle_deg", "micro_step"
        )
        _check_nonnegative(self, "max_step_height", "stuck_min_displacement", "stuck_min_yaw_deg")
        if not isinstance(self.stuck_window, int) or self.stuck_window < 1:
            raise ConfigError(f"Embodiment.stuck_window must be an integer >= 1, got {self.stuck_window!r}")
        if self.max_step_height >= self.height:
            raise ConfigError(
                f"Embodiment.max_step_height ({self.max_step_height}) must be below height ({self.height})"
            )

    @property
    def turn_angle(self) -> float:
        """Turn angle in radians."""
        return math.radians(self.turn_angle_deg)


@dataclass(frozen=True)
class NavMapConfig(_DictMixin):
    """Navigable-area extraction (floor candidates, cleaning, levels)."""

    voxel_size: float = 0.05
    """Voxel / 2D grid cell size in metres for downsampling, floors and the navigation graph."""
    normal_z_min: float = 0.5
    """Floor candidates need an upward unit normal with z-component at least this."""
    floor_labels: tuple[int, ...] = ()
    """Semantic category ids counted as floor (e.g. floor, rug); empty = purely geometric floors."""
    max_range: float = 10.0
    """Depth beyond this many metres is ignored when back-projecting captures (noisy far returns)."""
    pixel_stride: int = 2
    """Back-project every n-th pixel in each image direction (speed; the 0.05 m voxels are coarser)."""
    hole_normals: bool = True
    """Pixels whose Sobel receptive field (7x7 on the strided grid) touches missing depth get the
    normal of a plane fitted to their valid neighbours
    (:func:`~image2sim.simulator.geometry.normals.hole_normals`) instead of none; False: the
    paper's estimator alone, under which such pixels are never floor (most of a stereo capture's
    floor, whose depth has holes)."""
    carve_min_views: int = 3
    """Captures only: a voxel's points are dropped as a floater when at least this many views, and
    more than ``carve_ratio`` times as many as put a point in it, see beyond its mean point
    (:mod:`~image2sim.simulator.navigation.carving`); 0 disables. Wrong stereo depth leaves such
    floaters next to the floor, each blocking the agent's buffer around it (session 51: the lift
    benchmark's pinhole map F 0.795 -> 0.822); exact depth gives the same maps."""
    carve_ratio: float = 2.0
    """See ``carve_min_views``."""
    outlier_radius: float = 0.1
    """Radius (metres) of the radius outlier removal applied to obstacle voxels."""
    outlier_min_neighbors: int = 2
    """Obstacle voxels with fewer other obstacle voxels within ``outlier_radius`` are dropped."""
    safety_buffer: float | None = None
    """Navigable cells keep at least this clearance (metres) to obstacles; None = agent radius."""
    unknown_clearance: float | None = 0.0
    """Clearance (metres) navigable cells on a storey's plane keep to columns with no floor at any
    height (unseen space); None = the safety buffer. Drops (floor at another height, and unseen
    columns within a buffer of one) and every cell off a storey's plane (treads, ramps) keep the
    safety buffer. Unseen space counts as an obstacle standing ``safety_buffer - this`` farther out
    than it is. 0 (the default) is the paper's rule, where only obstacles project the buffer: +5
    points of recall on procedural panoramas, precision 0.96 -> 0.95 (``benchmarks/navmap_recall.py``);
    None was the default before 2026-11-28 (session 30)."""
    closing_radius_cells: int = 4
    """Radius (cells) of the disk used by the morphological closing that fills floor holes (2 before
    2026-11-28, session 30)."""
    min_level_area: float = 2.0
    """A height cluster of floor cells becomes a storey when its area is at least this (m^2)."""
    level_tolerance: float = 0.1
    """Floor cells within this height (metres) of a storey's plane belong to the storey's plane."""
    min_component_area: float = 1.0
    """Without camera positions, connected floor components smaller than this (m^2) are dropped."""
    camera_support_radius: float = 1.0
    """A camera seeds the floor component of the nearest floor cell within this horizontal radius."""
    min_camera_height: float = 0.3
    """Seed floor cells must lie at least this far below the camera (metres)."""
    align_gravity: bool = True
    """Rotate the cloud so the RANSAC ground normal is +Z when it is tilted by more than 0.5 degrees."""
    max_tilt_deg: float = 20.0
    """Tilts larger than this are treated as a failed fit and not corrected."""
    ransac_iterations: int = 200
    """RANSAC iterations for plane fitting."""
    ransac_threshold: float = 0.02
    """RANSAC inlier distance in metres."""
    seed: int = 0
    """Random seed of RANSAC (extraction is deterministic)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "floor_labels", tuple(int(v) for v in self.floor_labels))
        _check_positive(
            self, "voxel_size", "max_range", "outlier_radius", "min_level_area", "level_tolerance"
        )
        _check_positive(self, "camera_support_radius", "max_tilt_deg", "ransac_threshold")
        _check_nonnegative(self, "min_component_area", "min_camera_height", "outlier_min_neighbors")
        if not -1.0 <= self.normal_z_min <= 1.0:
            raise ConfigError(f"NavMapConfig.normal_z_min must lie in [-1, 1], got {self.normal_z_min}")
        for name in ("safety_buffer", "unknown_clearance"):
            if getattr(self, name) is not None:
                _check_nonnegative(self, name)
        _check_nonnegative(self, "carve_min_views", "carve_ratio")
        for name in ("pixel_stride", "ransac_iterations"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"NavMapConfig.{name} must be >= 1, got {getattr(self, name)!r}")
        if int(self.closing_radius_cells) < 0:
            raise ConfigError(
                f"NavMapConfig.closing_radius_cells must be >= 0, got {self.closing_radius_cells!r}"
            )


@dataclass(frozen=True)
class GraphConfig(_DictMixin):
    """Traversable voxel graph and its collision-aware directed edge costs."""

    neighbor_radius: float = 0.3
    """Candidate neighbours of a node lie within this distance (metres, KD-tree query)."""
    w_safe: float = 1.0
    """Weight of the clearance penalty w_safe * (max(0, (r_safe - c_j) / r_safe))^2."""
    r_safe_factor: float = 5.0
    """r_safe = r_safe_factor x agent radius."""
    w_collision: float = 1.0
    """Slope of the soft linear penetration penalty w_collision * max(0, (radius - c_j) / radius)."""
    march_step: float = 0.025
    """Spacing (metres) of the ray-march samples along a candidate edge."""
    max_snap_distance: float = 1.0
    """Points farther than this (metres, horizontally) from every node do not snap to the graph."""
    chunk_edges: int = 200_000
    """Candidate edges ray-marched per vectorised chunk (bounds peak memory)."""

    def __post_init__(self) -> None:
        _check_positive(self, "neighbor_radius", "r_safe_factor", "march_step", "max_snap_distance")
        _check_nonnegative(self, "w_safe", "w_collision")
        if int(self.chunk_edges) < 1:
            raise ConfigError(f"GraphConfig.chunk_edges must be >= 1, got {self.chunk_edges!r}")


@dataclass(frozen=True)
class FollowerConfig(_DictMixin):
    """Oracle follower: path smoothing and lookahead pure pursuit over discrete actions."""

    smoothing_window: int = 5
    """Moving-average window (points) applied to the planner's waypoints; 1 disables smoothing."""
    lookahead: float = 0.5
    """Pure-pursuit lookahead distance along the smoothed path in metres."""
    stop_radius: float = 0.2
    """Emit STOP once the agent is within this horizontal distance (metres) of the goal."""
    replan_distance: float = 0.5
    """Replan when the agent is farther than this (metres) from the current path."""
    turn_tolerance_deg: float | None = None
    """Turn while the heading error exceeds this (degrees); None = half the embodiment's turn angle."""
    slide_when_cycling: int = 0
    """0 = never take a step the kinematics predicts to collide (collision-free oracle). n > 0 = once
    the agent has been blocked n times at the same spot without path progress, accept a colliding
    (wall-sliding) step that still gets closer to the target: breaks avoidance loops next to thin
    obstacles on real scans (the HM3D staircase's newel post) at the price of a few collisions."""

    def __post_init__(self) -> None:
        if not isinstance(self.slide_when_cycling, int) or self.slide_when_cycling < 0:
            raise ConfigError(
                f"FollowerConfig.slide_when_cycling must be an integer >= 0, got {self.slide_when_cycling!r}"
            )
        if int(self.smoothing_window) < 1:
            raise ConfigError(f"FollowerConfig.smoothing_window must be >= 1, got {self.smoothing_window!r}")
        _check_positive(self, "lookahead", "stop_radius", "replan_distance")
        if self.turn_tolerance_deg is not None:
            _check_positive(self, "turn_tolerance_deg")
