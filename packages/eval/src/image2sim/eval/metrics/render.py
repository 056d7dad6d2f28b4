"""Rendering metrics (PSNR, SSIM, depth AbsRel / RMSE / δ<1.25): re-exported from
:mod:`image2sim.simulator.metrics.image`, their one implementation (shared with the renderer)."""

from image2sim.simulator.metrics.image import (
    SSIM_K1,
    SSIM_K2,
    SSIM_SIGMA,
    SSIM_WINDOW,
    DepthMetrics,
    depth_metrics,
    gaussian_filter_valid,
    gaussian_kernel_1d,
    gaussian_window,
    psnr,
    ssim,
    ssim_map,
)

__all__ = [
    "SSIM_K1",
    "SSIM_K2",
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "DepthMetrics",
    "depth_metrics",
    "gaussian_filter_valid",
    "gaussian_kernel_1d",
    "gaussian_window",
    "psnr",
    "ssim",
    "ssim_map",
]
