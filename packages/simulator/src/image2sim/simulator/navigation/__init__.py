"""Navigation substrate: navigable map, collision-aware voxel graph, planner, kinematic agent, follower."""

from image2sim.simulator.navigation.embodiment import (
    ConfigError,
    Embodiment,
    FollowerConfig,
    GraphConfig,
    NavMapConfig,
)
from image2sim.simulator.navigation.navmap import (
    NavMap,
    NavMapError,
    extract_navmap,
    extract_navmap_from_points,
)

__all__ = [
    "ConfigError",
    "Embodiment",
    "FollowerConfig",
    "GraphConfig",
    "NavMapConfig",
    "NavMap",
    "NavMapError",
    "extract_navmap",
    "extract_navmap_from_points",
]
