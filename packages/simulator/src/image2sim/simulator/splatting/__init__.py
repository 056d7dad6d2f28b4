"""Differentiable feature-Gaussian splatting into equirectangular and pinhole cameras.

``splat(...) -> SplatOutput`` is the single entry point every renderer path calls; backends:
``reference`` (dense, ground truth), ``torch`` (tile-binned, any device), ``cpu`` (compiled C++
kernel with OpenMP, hand-written backward), ``gsplat`` (pinhole cameras on CUDA, optional extra),
``auto`` (best available; the rule and the registry a new kernel joins are in :mod:`.dispatch`).
"""

from image2sim.simulator.splatting.api import SplatOutput, available_backends, splat

__all__ = ["SplatOutput", "splat", "available_backends"]
