"""Score finished trajectories of dataset episodes (glue between loaders, measures and runners).

The geodesic distance comes in as a callable, so this module needs no simulator: a runner passes
its navigation graph's distance, tests pass the Euclidean distance of an open floor.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from image2sim.eval.datasets import NavEpisode
from image2sim.eval.metrics.nav import (
    DEFAULT_MEASURES,
    AgentState,
    EpisodeResult,
    Measure,
    evaluate_episode,
)
from image2sim.eval.protocols import Protocol

GeodesicFn = Callable[[np.ndarray, np.ndarray], float]
"""``distance(position, goal) -> metres`` in our world frame (``inf`` when unreachable)."""


def euclidean_geodesic(position: np.ndarray, goal: np.ndarray) -> float:
    """Straight-line distance: the geodesic distance on an obstacle-free floor."""
    return float(np.linalg.norm(np.asarray(position, dtype=np.float64) - np.asarray(goal, dtype=np.float64)))


def score_trajectory(
    episode: NavEpisode,
    positions: Any,
    actions: Sequence[int],
    geodesic: GeodesicFn,
    protocol: Protocol,
    measures: Sequence[type[Measure]] = DEFAULT_MEASURES,
) -> EpisodeResult:
    """Metrics of one episode from its visited positions ``(T+1, 3)`` and actions ``(T,)``.

    ``positions[0]`` is the start (it must coincide with the episode's start position to within
    1 cm, which catches frame mix-ups); nDTW uses :attr:`NavEpisode.ndtw_reference`.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) == 0:
        raise ValueError(f"episode {episode.episode_id}: positions must be (T+1, 3), got shape {pos.shape}")
    offset = float(np.linalg.norm(pos[0] - episode.start_position))
    if offset > 0.01:
        raise ValueError(
            f"episode {episode.episode_id}: trajectory starts {offset:.3f} m from the episode's start "
            f"{episode.start_position.tolist()} (frame mix-up?)"
        )
    states = [AgentState(p, geodesic(p, episode.goal_position)) for p in pos]
    return evaluate_episode(episode.metric_spec(), states, list(actions), protocol, measures)
