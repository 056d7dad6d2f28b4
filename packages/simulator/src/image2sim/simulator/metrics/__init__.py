"""Image-quality metrics shared by the renderer (training logs, perceptual loss) and ``image2sim.eval``.

They live in the simulator because it is the lowest package both need (``simulator`` may not import
``eval``); ``image2sim.eval.metrics`` re-exports them.

* :mod:`.image`  PSNR, SSIM (Wang et al. 2004), depth AbsRel / RMSE / δ<1.25, per-image variants
* :mod:`.lpips`  LPIPS-VGG16 network, weight loading from local files, the n/a and warn-once helpers
"""

from image2sim.simulator.metrics.image import (
    DepthMetrics,
    abs_rel,
    depth_metrics,
    psnr,
    psnr_per_image,
    ssim,
    ssim_map,
    ssim_per_image,
)

__all__ = [
    "DepthMetrics",
    "abs_rel",
    "depth_metrics",
    "psnr",
    "psnr_per_image",
    "ssim",
    "ssim_map",
    "ssim_per_image",
]


def __getattr__(name: str):
    # LPIPS builds torch.nn modules; load it only when asked for.
    if name in ("LPIPS", "LpipsWeightsError", "load_lpips", "load_lpips_or_none", "lpips_distance"):
        from image2sim.simulator.metrics import lpips

        return getattr(lpips, name)
    raise AttributeError(name)
