"""Known object sizes as the metric scale of a lifted capture (``data lift --object-size``).

A user who knows one length in the scene (a door 2.0 m high, a table 1.6 m long) names its two ends
as pixels of one input image: ``FRAME:X0,Y0:X1,Y1=METRES`` (0-based pixel column and row as an image
viewer shows them; the centre of that pixel is used). Each end is lifted to the reconstruction along
its pixel's ray, at the dense depth the depth stage found around it: the confident depths within a
few pixels of where the ray meets the frame's views (the frame itself, or the cube faces of a
panorama), fitted as a plane (inverse depth affine in the pixel) and read at the ray. The ratio of the
stated metres to the reconstructed length is the scale.

Uncertainty of one length, relative (1 sigma): the ends' depth spread about their planes (1.4826 x
the median absolute deviation) and one pixel of localisation each, along and across the ray, over the
length. Several lengths combine in log space weighted by their inverse variances; when they disagree
more than their uncertainties allow (reduced chi-square > 1), the uncertainty grows by its square root.

Pure functions over the stage's views and depth estimates: no I/O.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from image2sim.simulator.lift.types import DepthEstimate, PinholeView

__all__ = ["ObjectSize", "ObjectLength", "parse_object_size", "measure_object", "scale_from_lengths"]

WINDOW_RADII_PX = (2, 4, 8)
"""Half-sizes of the windows searched, in turn, for confident depth around an end's pixel."""
MIN_CONFIDENCE = 0.5
"""Depth at or above this confidence counts (the sweep's confident pixels)."""

_NUMBER = r"[^,:=\s]+"
_PATTERN = re.compile(
    rf"^(?P<frame>[^:]+):(?P<x0>{_NUMBER}),(?P<y0>{_NUMBER}):(?P<x1>{_NUMBER}),(?P<y1>{_NUMBER})=(?P<m>{_NUMBER})$"
)


@dataclass(frozen=True)
class ObjectSize:
    """A stated length between two pixels of one input image."""

    frame_id: str
    a: tuple[float, float]
    """First end: pixel column, row (0-based; the pixel's centre is used)."""
    b: tuple[float, float]
    metres: float

    def label(self) -> str:
        return f"{self.frame_id}:{self.a[0]:g},{self.a[1]:g}:{self.b[0]:g},{self.b[1]:g}={self.metres:g}"


@dataclass(frozen=True)
class ObjectLength:
    """One stated length as measured in the reconstruction."""

    size: ObjectSize
    length: float
    """Distance between the lifted ends, reconstruction units."""
    uncertainty: float
    """Relative (1-sigma) uncertainty of ``length``."""
    ends: np.ndarray
    """(2, 3) lifted ends, reconstruction coordinates."""

    @property
    def scale(self) -> float:
        return self.size.metres / self.length

    def record(self) -> dict:
        return {
            "object": self.size.label(),
            "length_reconstruction": float(self.length),
            "scale": float(self.scale),
            "uncertainty": float(self.uncertainty),
        }


def parse_object_size(text: str) -> ObjectSize:
    """``FRAME:X0,Y0:X1,Y1=METRES`` -> :class:`ObjectSize`; ``ValueError`` naming the text otherwise."""
    m = _PATTERN.match(text.strip())
    if m is None:
        raise ValueError(
            f"--object-size {text!r}: expected FRAME:X0,Y0:X1,Y1=METRES (pixel column,row of both ends "
            "in that input image, and the length between them), e.g. img_003:120,40:120,300=2.0"
        )
    try:
        x0, y0, x1, y1, metres = (float(m[k]) for k in ("x0", "y0", "x1", "y1", "m"))
    except ValueError as exc:
        raise ValueError(f"--object-size {text!r}: not a number ({exc})") from exc
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1, metres)):
        raise ValueError(f"--object-size {text!r}: every number must be finite")
    if metres <= 0:
        raise ValueError(f"--object-size {text!r}: the length must be positive, got {metres:g} m")
    if (x0, y0) == (x1, y1):
        raise ValueError(f"--object-size {text!r}: both ends are the same pixel")
    return ObjectSize(m["frame"], (x0, y0), (x1, y1), metres)


def _ray(camera, cam_to_world: np.ndarray, xy: tuple[float, float]) -> np.ndarray:
    """Unit world direction through the centre of pixel ``xy`` of a frame's camera: a (3, 3) pinhole
    intrinsics matrix, or ``(height, width)`` of an equirect panorama."""
    u, v = xy[0] + 0.5, xy[1] + 0.5
    if isinstance(camera, tuple):
        import torch
        from image2sim.simulator.geometry.cameras import EquirectCamera

        d = EquirectCamera(*camera).pixel_to_ray(
            torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64)
        )
        d = d.numpy()
    else:
        d = np.linalg.solve(camera, np.array([u, v, 1.0]))
    d = cam_to_world[:3, :3] @ d
    return d / np.linalg.norm(d)


def _local_depth(z: np.ndarray, du: np.ndarray, dv: np.ndarray) -> tuple[float, float]:
    """Depth at offset (0, 0) and its spread from a window's depths at pixel offsets (du, dv).

    A plane's inverse depth is affine in the pixel coordinates, so 1/z is fitted as a + b du + c dv
    (robustly: refitted once without points beyond 3 MADs); the spread is the residuals' MAD, not the
    slope of a tilted surface. With fewer than 6 points: the median and its MAD."""
    if len(z) < 6:
        return _median_spread(z)
    A = np.stack([np.ones_like(du), du, dv], axis=1)
    inv = 1.0 / z
    keep = np.ones(len(z), dtype=bool)
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(A[keep], inv[keep], rcond=None)
        res = inv - A @ coef
        mad = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = np.abs(res) <= 3 * mad + 1e-12 * abs(coef[0])
    inv0 = float(coef[0])
    if not inv0 > 0:  # a fit through the window's edge of a surface: fall back to the median
        return _median_spread(z)
    return 1.0 / inv0, mad / inv0**2


def _median_spread(z: np.ndarray) -> tuple[float, float]:
    """Median and robust standard deviation (1.4826 x MAD) of depths."""
    med = float(np.median(z))
    return med, 1.4826 * float(np.median(np.abs(z - med)))


def _lift_end(
    ray: np.ndarray, views: Sequence[tuple[PinholeView, DepthEstimate]], what: str
) -> tuple[np.ndarray, float, float]:
    """(point, range spread sigma, range) of the surface along ``ray`` from the views' depth."""
    for radius in WINDOW_RADII_PX:
        for view, est in views:
            R, c = view.cam_to_world[:3, :3], view.cam_to_world[:3, 3]
            d_cam = R.T @ ray
            if d_cam[2] <= 1e-6:
                continue
            uv = view.K @ (d_cam / d_cam[2])
            h, w = est.depth.shape
            iu, iv = int(np.floor(uv[0])), int(np.floor(uv[1]))
            if not (0 <= iu < w and 0 <= iv < h):
                continue
            win = np.s_[max(0, iv - radius) : iv + radius + 1, max(0, iu - radius) : iu + radius + 1]
            z, conf = est.depth[win], est.confidence[win]
            ok = (z > 0) & np.isfinite(z) & (conf >= MIN_CONFIDENCE)
            if not ok.any():
                continue
            rows, cols = np.nonzero(ok)
            zc, sigma_z = _local_depth(
                z[ok].astype(np.float64),
                cols + win[1].start + 0.5 - uv[0],
                rows + win[0].start + 0.5 - uv[1],
            )
            rng = zc / d_cam[2]
            return c + rng * ray, sigma_z / d_cam[2], rng
    raise ValueError(
        f"{what}: no confident depth within {WINDOW_RADII_PX[-1]} px of this pixel (the depth stage "
        "could not match it: pick an end on a textured surface, e.g. a corner or an edge's end)"
    )


def measure_object(
    size: ObjectSize,
    camera,
    cam_to_world: np.ndarray,
    views: Sequence[tuple[PinholeView, DepthEstimate]],
    focal_px: float,
) -> ObjectLength:
    """Lift both ends of ``size`` and measure it.

    ``camera``: the frame's (3, 3) pinhole intrinsics, or ``(height, width)`` of its equirect image;
    ``cam_to_world``: the frame's pose in reconstruction units; ``views``: the frame's views with their
    depth estimates (one for a pinhole frame, the six cube faces of a panorama); ``focal_px``: the
    views' focal length (one pixel of localisation error is range / focal)."""
    ends, var = [], 0.0
    for name, xy in (("first end", size.a), ("second end", size.b)):
        point, sigma, rng = _lift_end(
            _ray(camera, cam_to_world, xy), views, f"--object-size {size.label()}: {name}"
        )
        ends.append(point)
        var += sigma**2 + 2 * (rng / focal_px) ** 2
    length = float(np.linalg.norm(ends[1] - ends[0]))
    if length <= 0:
        raise ValueError(f"--object-size {size.label()}: both ends lift to the same point")
    return ObjectLength(size, length, math.sqrt(var) / length, np.stack(ends))


def scale_from_lengths(lengths: Sequence[ObjectLength]) -> tuple[float, float]:
    """(scale, relative 1-sigma uncertainty) from one or more measured lengths (module docstring)."""
    if not lengths:
        raise ValueError("no object sizes to take the scale from")
    logs = np.array([math.log(x.scale) for x in lengths])
    u = np.maximum(np.array([x.uncertainty for x in lengths]), 1e-9)
    w = 1.0 / u**2
    mean = float(np.sum(w * logs) / np.sum(w))
    unc = math.sqrt(1.0 / float(np.sum(w)))
    if len(lengths) > 1:
        chi2 = float(np.sum(w * (logs - mean) ** 2)) / (len(lengths) - 1)
        unc *= math.sqrt(max(1.0, chi2))
    return math.exp(mean), unc
