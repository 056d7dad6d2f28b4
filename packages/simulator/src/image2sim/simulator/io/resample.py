"""Resampling images onto our pixel grid when a source format's grid differs.

Coordinates here are continuous pixel coordinates of the *source* image in our convention (pixel
centres at integer + 0.5). Colour is sampled bilinearly. Depth is sampled "edge-aware": where the
valid neighbours agree (relative spread <= ``rel_tol``) their bilinear average is used, otherwise
the nearest valid neighbour, so no point is invented in mid-air between a foreground and a
background surface ("flying pixels"). :func:`planar_rel_tol` picks ``rel_tol`` from the angular
pixel size so that any plane seen at up to 75 degrees incidence still counts as smooth.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["bilinear_taps", "sample_bilinear", "sample_rgb", "sample_depth", "planar_rel_tol"]


def planar_rel_tol(angular_step: float, max_incidence_deg: float = 75.0) -> float:
    """Relative depth spread of a 2x2 pixel neighbourhood on a plane seen at ``max_incidence_deg``.

    Along a ray at incidence alpha on a plane, d(log r)/d(theta) = tan(alpha); across a pixel diagonal
    (angle ``sqrt(2) * angular_step`` radians) the spread is about that times tan(alpha).
    """
    return float(np.tan(np.radians(max_incidence_deg)) * np.sqrt(2.0) * angular_step)


def bilinear_taps(coord: np.ndarray, size: int, wrap: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (i0, i1) and weight of i1 for continuous coordinates along one axis of ``size`` pixels.

    ``wrap`` makes the axis periodic (panorama longitude); otherwise indices clamp to the border.
    """
    x = np.asarray(coord, dtype=np.float64) - 0.5
    i0 = np.floor(x)
    frac = x - i0
    i0 = i0.astype(np.int64)
    i1 = i0 + 1
    if wrap:
        i0 %= size
        i1 %= size
    else:
        i0 = np.clip(i0, 0, size - 1)
        i1 = np.clip(i1, 0, size - 1)
    return i0, i1, frac


def _gather(image: np.ndarray, u: np.ndarray, v: np.ndarray, wrap_u: bool):
    """Four neighbours of each sample and their bilinear weights: ((4, ...) values, (4, ...) weights)."""
    h, w = image.shape[:2]
    u0, u1, fu = bilinear_taps(u, w, wrap_u)
    v0, v1, fv = bilinear_taps(v, h, False)
    values = np.stack([image[v0, u0], image[v0, u1], image[v1, u0], image[v1, u1]])
    weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv])
    return values, weights


def sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray, *, wrap_u: bool = False) -> np.ndarray:
    """Bilinearly sample an (H, W) or (H, W, C) image at continuous coords (u, v) (any equal shapes).

    Returns float64 values of shape ``u.shape (+ (C,))``.
    """
    values, weights = _gather(np.asarray(image), u, v, wrap_u)
    if values.ndim > weights.ndim:
        weights = weights[..., None]
    return np.sum(values.astype(np.float64) * weights, axis=0)


def sample_rgb(image: np.ndarray, u: np.ndarray, v: np.ndarray, *, wrap_u: bool = False) -> np.ndarray:
    """Bilinear sampling of a uint8 image (same taps as :func:`sample_bilinear`), via ``cv2.remap``.

    OpenCV's remap is ~30x faster than the numpy gather but cannot wrap one axis and clamp the
    other, so the seam is handled by padding one wrapped column on each side and clamping with
    ``BORDER_REPLICATE``. Its fixed-point weights (1/32 steps) can differ from exact bilinear by one
    grey level.
    """
    image = np.ascontiguousarray(image)
    x = np.asarray(u, dtype=np.float64)
    if wrap_u:
        width = image.shape[1]
        image = np.concatenate([image[:, -1:], image, image[:, :1]], axis=1)
        x = np.mod(x, width) + 1.0  # shift into the padded image
    map_x = (x - 0.5).astype(np.float32)
    map_y = (np.asarray(v, dtype=np.float64) - 0.5).astype(np.float32)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(*np.shape(u), *image.shape[2:])


def sample_depth(
    depth: np.ndarray, u: np.ndarray, v: np.ndarray, *, wrap_u: bool = False, rel_tol: float = 0.05
) -> np.ndarray:
    """Edge-aware depth sampling (0 = invalid in and out); returns float32 of shape ``u.shape``."""
    values, weights = _gather(np.asarray(depth, dtype=np.float32), u, v, wrap_u)
    valid = (values > 0) & (weights > 0)  # zero-weight taps (exact hits, clamped borders) do not vote
    w = np.where(valid, weights, 0.0)
    wsum = w.sum(axis=0)
    mean = np.divide((w * values).sum(axis=0), wsum, out=np.zeros_like(wsum), where=wsum > 0)
    big = np.where(valid, values, -np.inf).max(axis=0)
    small = np.where(valid, values, np.inf).min(axis=0)
    smooth = big <= small * (1.0 + rel_tol)
    # Nearest valid neighbour = the valid tap with the largest bilinear weight.
    nearest_idx = np.argmax(np.where(valid, weights + 1.0, 0.0), axis=0)
    nearest = np.take_along_axis(values, nearest_idx[None], axis=0)[0]
    out = np.where(smooth, mean, nearest)
    return np.where(valid.any(axis=0), out, 0.0).astype(np.float32)
