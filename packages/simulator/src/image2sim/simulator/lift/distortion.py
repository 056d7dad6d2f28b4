"""Radial lens distortion of COLMAP's ``SIMPLE_RADIAL`` and ``RADIAL`` cameras, and its removal.

Phone and action-camera lenses bend straight lines; a pinhole model of such frames leaves pose and
depth errors that grow towards the image border. Structure-from-motion estimates the distortion with
the frames' poses (``SfmOptions.camera_model``), and the lift then works on undistorted frames: each
image is resampled to the pinhole camera with the same focal length and principal point, and the
sparse observations are moved to where that pinhole camera sees them. The written capture is a plain
pinhole capture, so every later stage (depth, scale, Gaussians, maps) is unchanged.

COLMAP's model on normalised coordinates ``x = (u - cx) / f`` (pixel centres at +0.5):
``x_d = x (1 + k1 r^2 + k2 r^4)``, ``r^2 = |x|^2`` (``SIMPLE_RADIAL``: k2 = 0).

Pure numpy / OpenCV functions; no state.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "RADIAL_MODELS",
    "NEGLIGIBLE_PX",
    "max_displacement_px",
    "radial_coefficients",
    "distort",
    "undistort",
    "undistort_pixels",
    "undistort_image",
]

RADIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL")
"""COLMAP camera models with radial distortion that the lift removes."""


NEGLIGIBLE_PX = 0.5
"""Distortion that moves no pixel of the frame by more than this is left alone: resampling would blur
the image more than the model bends it (a distortion-free lens estimated with a radial model gets
|k| ~ 3e-4 to 1e-3, up to ~0.3 px at the corners of a 320x240 frame)."""


def max_displacement_px(K: np.ndarray, k: tuple[float, float], height: int, width: int) -> float:
    """The largest distance, in pixels, between where the lens and the pinhole camera ``K`` put a
    point seen at the frame's corners (the radial model's largest displacement inside the frame)."""
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [float(width), float(height)]])
    moved = _to_pixels(distort(_normalise(corners, K), k), K)
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def radial_coefficients(model: str, params) -> tuple[float, float]:
    """(k1, k2) of a COLMAP camera's parameter list; (0, 0) for the pinhole models."""
    p = [float(x) for x in params]
    if model == "SIMPLE_RADIAL":
        return p[3], 0.0
    if model == "RADIAL":
        return p[3], p[4]
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return 0.0, 0.0
    raise ValueError(f"camera model {model!r} has no radial coefficients here (known: {RADIAL_MODELS})")


def distort(xy: np.ndarray, k: tuple[float, float]) -> np.ndarray:
    """Normalised undistorted coordinates (..., 2) -> distorted ones."""
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    return xy * (1.0 + k[0] * r2 + k[1] * r2 * r2)


def undistort(xy_d: np.ndarray, k: tuple[float, float], iterations: int = 12) -> np.ndarray:
    """Distorted normalised coordinates (..., 2) -> undistorted ones: the radius solves
    ``r (1 + k1 r^2 + k2 r^4) = r_d`` by Newton's method from ``r = r_d`` (exact to round-off within
    the lens's monotonic range); the direction is unchanged."""
    xy_d = np.asarray(xy_d, dtype=np.float64)
    r_d = np.linalg.norm(xy_d, axis=-1, keepdims=True)
    r = r_d.copy()
    for _ in range(iterations):
        r2 = r * r
        f = r * (1.0 + k[0] * r2 + k[1] * r2 * r2) - r_d
        df = 1.0 + 3.0 * k[0] * r2 + 5.0 * k[1] * r2 * r2
        r = r - f / np.where(np.abs(df) > 1e-12, df, 1e-12)
    return np.where(r_d > 0, xy_d * (r / np.where(r_d > 0, r_d, 1.0)), 0.0)


def _normalise(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates -> normalised camera coordinates of the pinhole camera ``K``."""
    return (np.asarray(uv, dtype=np.float64) - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def _to_pixels(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates -> pixel coordinates of the pinhole camera ``K``."""
    return xy * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


def undistort_pixels(uv: np.ndarray, K: np.ndarray, k: tuple[float, float]) -> np.ndarray:
    """Pixel coordinates (..., 2) of the distorted image -> where the pinhole camera ``K`` sees them."""
    return _to_pixels(undistort(_normalise(uv, K), k), K)


def undistort_image(image: np.ndarray, K: np.ndarray, k: tuple[float, float]) -> np.ndarray:
    """The distorted ``image`` (H, W, C) resampled to the pinhole camera ``K`` of the same size
    (bilinear; pixels whose source lies outside the image are black)."""
    import cv2

    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    src = _to_pixels(distort(_normalise(np.stack([u, v], axis=-1), K), k), K)
    map_x = (src[..., 0] - 0.5).astype(np.float32)  # OpenCV's pixel centres are at integers
    map_y = (src[..., 1] - 0.5).astype(np.float32)
    return cv2.remap(image, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
