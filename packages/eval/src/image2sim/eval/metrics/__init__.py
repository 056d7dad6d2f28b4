"""Evaluation metrics: navigation (numpy) and rendering (torch)."""

from image2sim.eval.metrics.nav import (
    aggregate,
    dtw,
    evaluate_episode,
    ndtw,
    path_length,
    sdtw,
    spl,
)

__all__ = ["aggregate", "dtw", "evaluate_episode", "ndtw", "path_length", "sdtw", "spl"]
