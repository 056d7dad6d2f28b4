"""Records shared by the lifting stages (``image2sim data lift``): views in, depth out.

The SfM side (``lift.sfm``) produces :class:`PinholeView` s and, per view, :class:`SparseDepth`
(the reconstruction's 3D points seen by that view); the depth side (``lift.depth``) turns them into
:class:`DepthEstimate` s. Everything follows docs/conventions.md: OpenCV camera, camera-to-world
poses, pixel centres at +0.5, z-depth for pinhole views, 0 = invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, TypeVar

import numpy as np

__all__ = ["PinholeView", "SparseDepth", "DepthEstimate", "options_from_kwargs"]

T = TypeVar("T")


@dataclass
class PinholeView:
    """One posed pinhole image of a reconstruction.

    Attributes:
        image: (H, W, 3) uint8 RGB.
        K: (3, 3) intrinsics, pixel centres at +0.5.
        cam_to_world: (4, 4) float64 camera-to-world pose (OpenCV camera), in reconstruction units.
    """

    image: np.ndarray
    K: np.ndarray
    cam_to_world: np.ndarray


@dataclass
class SparseDepth:
    """The sparse reconstruction's points as seen by one view.

    Attributes:
        uv: (k, 2) float pixel coordinates of the observations (pixel centres at +0.5).
        depth: (k,) z-depth of the observed 3D points in that view (reconstruction units).
    """

    uv: np.ndarray
    depth: np.ndarray


@dataclass
class DepthEstimate:
    """Dense depth for one view.

    Attributes:
        depth: (H, W) float32 z-depth in reconstruction units, 0 = invalid.
        confidence: (H, W) float32 in [0, 1].
    """

    depth: np.ndarray
    confidence: np.ndarray


def options_from_kwargs(cls: type[T], kw: dict[str, Any], what: str) -> T:
    """The settings dataclass ``cls`` from keyword options; an unknown name is an error naming ``what``
    (e.g. "multi-view stereo") and listing the known ones."""
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(kw) - known)
    if unknown:
        raise ValueError(f"unknown {what} option(s) {unknown}; known: {sorted(known)}")
    return cls(**kw)
