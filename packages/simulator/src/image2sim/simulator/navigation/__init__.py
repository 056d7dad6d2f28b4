"""Navigation substrate: navigable map, collision-aware voxel graph, planner, kinematic agent, follower.

Public API (imported lazily so ``image2sim --help`` stays light)::

    from image2sim.simulator.navigation import extract_navmap, NavGraph, Planner, Agent, OracleFollower
    navmap = extract_navmap(capture)            # .points: (M, 3) navigable cell centres (world)
    graph = NavGraph.build(navmap)              # directed, collision-aware costs
    path = Planner(graph).shortest_path(start, goal)
"""

import importlib

_EXPORTS = {
    "embodiment": ("ConfigError", "Embodiment", "FollowerConfig", "GraphConfig", "NavMapConfig"),
    "navmap": ("NavMap", "NavMapError", "navmap_agreement"),
    "extract": ("extract_navmap", "extract_navmap_from_gaussians", "extract_navmap_from_points"),
    "topdown": ("render_topdown",),
    "graph": ("NavGraph",),
    "planner": ("DistanceField", "PathResult", "Planner"),
    "agent": (
        "Agent",
        "AgentState",
        "CollisionWorld",
        "Kinematics",
        "StepInfo",
        "StuckDetector",
        "wrap_angle",
    ),
    "follower": ("OracleFollower", "smooth_path"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
