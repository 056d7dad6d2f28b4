"""Lens distortion of COLMAP's radial, OpenCV and fisheye cameras, and its removal.

Phone and action-camera lenses bend straight lines; a pinhole model of such frames leaves pose and
depth errors that grow towards the image border. Structure-from-motion estimates the distortion with
the frames' poses (``SfmOptions.camera_model``), and the lift then works on undistorted frames: each
image is resampled to the pinhole camera with the same focal length and principal point, and the
sparse observations are moved to where that pinhole camera sees them. The written capture is a plain
pinhole capture, so every later stage (depth, scale, Gaussians, maps) is unchanged.

COLMAP's models on normalised pinhole coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)`` (pixel
centres at +0.5), ``r^2 = x^2 + y^2``:

* Brown-Conrady (``SIMPLE_RADIAL``: k1; ``RADIAL``: k1, k2; ``OPENCV``: k1, k2, p1, p2):
  ``x_d = x s + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``y_d = y s + p1 (r^2 + 2 y^2) + 2 p2 x y``,
  ``s = 1 + k1 r^2 + k2 r^4``.
* Fisheye, equidistant (``SIMPLE_RADIAL_FISHEYE``: k1; ``RADIAL_FISHEYE``: k1, k2;
  ``OPENCV_FISHEYE``: k1..k4): ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 +
  k3 theta^6 + k4 theta^8)``, ``(x_d, y_d) = (x, y) theta_d / r``. Rays at 90 degrees or more from the
  axis have no pinhole image: their undistorted coordinates are NaN.

Pure numpy / OpenCV functions over a frozen :class:`Lens`; no state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "FISHEYE_MODELS",
    "LENS_MODELS",
    "NEGLIGIBLE_PX",
    "PINHOLE_LENS",
    "Lens",
    "lens_of_camera",
    "max_displacement_px",
    "initial_camera_params",
    "distort",
    "undistort",
    "undistort_pixels",
    "undistort_image",
]

_BROWN = {"SIMPLE_RADIAL": (1, False), "RADIAL": (2, False), "OPENCV": (2, True)}
"""Brown-Conrady models: (radial coefficients, tangential terms), after fx, fy / f, cx, cy."""
_FISHEYE = {"SIMPLE_RADIAL_FISHEYE": 1, "RADIAL_FISHEYE": 2, "OPENCV_FISHEYE": 4}
"""Equidistant fisheye models: radial coefficients on theta, after fx, fy / f, cx, cy."""
FISHEYE_MODELS = tuple(_FISHEYE)
"""COLMAP's equidistant fisheye camera models."""
LENS_MODELS = (*_BROWN, *_FISHEYE)
"""COLMAP camera models with lens distortion that the lift removes."""
_SEPARATE_FOCALS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
"""Models whose parameters start fx, fy, cx, cy (the others: f, cx, cy)."""


NEGLIGIBLE_PX = 0.5
"""Distortion that moves no pixel of the frame by more than this is left alone: resampling would blur
the image more than the model bends it (a distortion-free lens estimated with a radial model gets
|k| ~ 3e-4 to 1e-3, up to ~0.3 px at the corners of a 320x240 frame)."""


@dataclass(frozen=True)
class Lens:
    """A lens's mapping of normalised pinhole coordinates (see the module docstring)."""

    radial: tuple[float, ...] = ()
    """Brown-Conrady: k1, k2 on r^2, r^4; fisheye: k1..k4 on theta^2..theta^8 (missing ones are 0)."""
    tangential: tuple[float, float] = (0.0, 0.0)
    """p1, p2 of the OpenCV model (Brown-Conrady only)."""
    fisheye: bool = False
    """Equidistant fisheye projection (theta_d = theta (1 + ...)) instead of Brown-Conrady."""

    def __post_init__(self) -> None:
        if len(self.radial) > (4 if self.fisheye else 2):
            raise ValueError(f"Lens: {len(self.radial)} radial coefficients for a {self._kind} lens")
        if self.fisheye and any(self.tangential):
            raise ValueError("Lens: a fisheye lens has no tangential coefficients")
        if not all(np.isfinite([*self.radial, *self.tangential])):
            raise ValueError(f"Lens: coefficients must be finite, got {self.radial} {self.tangential}")

    @property
    def _kind(self) -> str:
        return "fisheye" if self.fisheye else "Brown-Conrady"

    @property
    def is_pinhole(self) -> bool:
        """True when the lens maps every point to itself (Brown-Conrady with all coefficients 0)."""
        return not self.fisheye and not any(self.radial) and not any(self.tangential)

    def _k(self, n: int) -> tuple[float, ...]:
        return tuple(self.radial) + (0.0,) * (n - len(self.radial))


PINHOLE_LENS = Lens()
"""The identity lens (pinhole camera models; nothing to undistort)."""


def lens_of_camera(model: str, params) -> Lens:
    """The :class:`Lens` of a COLMAP camera's model name and parameter list (the pinhole models give
    the identity lens)."""
    p = [float(x) for x in params]
    start = 4 if model in _SEPARATE_FOCALS else 3
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return PINHOLE_LENS
    if model in _BROWN:
        n, tangential = _BROWN[model]
        extra = p[start:]
        return Lens(tuple(extra[:n]), tuple(extra[n : n + 2]) if tangential else (0.0, 0.0))
    if model in _FISHEYE:
        return Lens(tuple(p[start : start + _FISHEYE[model]]), fisheye=True)
    raise ValueError(f"camera model {model!r} is not one the lift can undistort (known: {LENS_MODELS})")


def initial_camera_params(model: str, f: float, width: int, height: int) -> str:
    """COLMAP's parameter string for ``model`` with focal length ``f``, the principal point at the
    centre and no distortion (the same tables as :func:`lens_of_camera`)."""
    focal = f"{f},{f}" if model in _SEPARATE_FOCALS else f"{f}"
    n, tangential = _BROWN.get(model, (_FISHEYE.get(model, 0), False))
    zeros = ["0"] * (n + (2 if tangential else 0))
    return ",".join([focal, f"{width / 2}", f"{height / 2}", *zeros])


def distort(xy: np.ndarray, lens: Lens) -> np.ndarray:
    """Normalised undistorted (pinhole) coordinates (..., 2) -> where the lens images them."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    if lens.fisheye:
        k1, k2, k3, k4 = lens._k(4)
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        # theta_d / r -> 1 as r -> 0 (the centre is a fixed point).
        ratio = np.where(r > 1e-12, theta_d / np.where(r > 1e-12, r, 1.0), 1.0)
        return xy * ratio[..., None]
    k1, k2 = lens._k(2)
    p1, p2 = lens.tangential
    s = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _brown_jacobian(x, y, lens: Lens):
    """d(x_d, y_d) / d(x, y) of the Brown-Conrady model: (a, b, c, d) = [[a, b], [c, d]]."""
    k1, k2 = lens._k(2)
    p1, p2 = lens.tangential
    r2 = x * x + y * y
    s = 1.0 + r2 * (k1 + k2 * r2)
    g = 2.0 * k1 + 4.0 * k2 * r2  # ds/dx = g x, ds/dy = g y
    cross = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    return (
        s + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x,
        cross,
        cross,
        s + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x,
    )


def undistort(xy_d: np.ndarray, lens: Lens, iterations: int = 20) -> np.ndarray:
    """Distorted normalised coordinates (..., 2) -> undistorted ones, by Newton's method from the
    distorted point (exact to round-off within the lens's monotonic range). Fisheye: the angle solves
    ``theta_d(theta) = r_d`` in 1-D and the direction is kept; rays at or past 90 degrees give NaN."""
    xy_d = np.asarray(xy_d, dtype=np.float64)
    if lens.is_pinhole:
        return xy_d.copy()
    if lens.fisheye:
        k1, k2, k3, k4 = lens._k(4)
        r_d = np.linalg.norm(xy_d, axis=-1)
        theta = r_d.copy()
        for _ in range(iterations):
            t2 = theta * theta
            f = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - r_d
            df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
            theta = theta - f / np.where(np.abs(df) > 1e-12, df, 1e-12)
        with np.errstate(invalid="ignore"):
            r = np.where(theta < np.pi / 2 - 1e-9, np.tan(np.clip(theta, 0.0, np.pi / 2 - 1e-9)), np.nan)
        ratio = np.where(r_d > 1e-12, r / np.where(r_d > 1e-12, r_d, 1.0), 1.0)
        return xy_d * ratio[..., None]
    x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
    for _ in range(iterations):
        fx, fy = np.moveaxis(distort(np.stack([x, y], axis=-1), lens) - xy_d, -1, 0)
        a, b, c, d = _brown_jacobian(x, y, lens)
        det = a * d - b * c
        det = np.where(np.abs(det) > 1e-12, det, 1e-12)
        x, y = x - (d * fx - b * fy) / det, y - (a * fy - c * fx) / det
    return np.stack([x, y], axis=-1)


def _normalise(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates -> normalised camera coordinates of the pinhole camera ``K``."""
    return (np.asarray(uv, dtype=np.float64) - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def _to_pixels(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates -> pixel coordinates of the pinhole camera ``K``."""
    return xy * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


def max_displacement_px(K: np.ndarray, lens: Lens, height: int, width: int) -> float:
    """The largest distance, in pixels, between where the lens and the pinhole camera ``K`` put a
    point seen on the frame's border (corners and edge midpoints: a tangential or higher-order term
    can move an edge more than a corner)."""
    w, h = float(width), float(height)
    border = np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, 0], [w / 2, h], [0, h / 2], [w, h / 2]])
    moved = _to_pixels(distort(_normalise(border, K), lens), K)
    return float(np.max(np.linalg.norm(moved - border, axis=1)))


def undistort_pixels(uv: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """Pixel coordinates (..., 2) of the distorted image -> where the pinhole camera ``K`` sees them
    (NaN for fisheye rays the pinhole camera cannot see)."""
    return _to_pixels(undistort(_normalise(uv, K), lens), K)


def undistort_image(image: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """The distorted ``image`` (H, W, C) resampled to the pinhole camera ``K`` of the same size
    (bilinear; pixels whose source lies outside the image are black)."""
    import cv2

    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    src = _to_pixels(distort(_normalise(np.stack([u, v], axis=-1), K), lens), K)
    map_x = (src[..., 0] - 0.5).astype(np.float32)  # OpenCV's pixel centres are at integers
    map_y = (src[..., 1] - 0.5).astype(np.float32)
    return cv2.remap(image, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
