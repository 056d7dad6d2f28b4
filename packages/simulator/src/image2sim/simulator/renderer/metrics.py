"""Per-image image metrics used by the renderer's training logs and evaluation command.

Re-exported from :mod:`image2sim.simulator.metrics.image` (their one implementation, shared with
``image2sim.eval``).
"""

from image2sim.simulator.metrics.image import abs_rel, psnr_per_image, ssim_per_image

__all__ = ["psnr_per_image", "ssim_per_image", "abs_rel"]
