"""Rasterisation backends: each turns depth-sorted screen Gaussians into image planes.

All share one contract (see :func:`image2sim.simulator.splatting.backends.reference.rasterize`):
``rasterize(means2d (M,2), conics (M,3), opacities (M,), values (M,D), background (D,), height,
width, wrap_width, *, t_min=1e-4) -> (image (D,H,W), alpha (1,H,W))`` with the Gaussians already
sorted front to back and culled; a pixel is finished after the Gaussian that takes its transmittance
below ``t_min`` (``splat(..., min_transmittance=...)``). A new device kernel only needs to implement
this function and register itself in :mod:`image2sim.simulator.splatting.api`.
"""
