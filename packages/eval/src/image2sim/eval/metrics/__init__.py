"""Evaluation metrics: navigation (numpy), rendering (torch), LPIPS (optional weights), FPS."""

from image2sim.eval.metrics.lpips import LPIPS, LpipsConfig, build_lpips, load_lpips, lpips_distance
from image2sim.eval.metrics.nav import (
    IncrementalNDTW,
    aggregate,
    dtw,
    evaluate_episode,
    ndtw,
    path_length,
    sdtw,
    spl,
    summarize_records,
)
from image2sim.eval.metrics.render import DepthMetrics, depth_metrics, psnr, ssim
from image2sim.eval.metrics.timing import FpsMeasurement, hardware_string, measure_fps

__all__ = [
    "LPIPS",
    "IncrementalNDTW",
    "DepthMetrics",
    "FpsMeasurement",
    "LpipsConfig",
    "aggregate",
    "build_lpips",
    "depth_metrics",
    "dtw",
    "evaluate_episode",
    "hardware_string",
    "load_lpips",
    "lpips_distance",
    "measure_fps",
    "ndtw",
    "path_length",
    "psnr",
    "sdtw",
    "spl",
    "ssim",
    "summarize_records",
]
