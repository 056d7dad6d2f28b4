"""Checks on poses and images read from capture files.

Every check raises :class:`CaptureError` whose message starts with the offending file (or field)
and says what is wrong, so bad input never turns into a NaN somewhere downstream.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from image2sim.simulator.io.records import CaptureError

__all__ = [
    "ROTATION_TOL",
    "QUATERNION_NORM_TOL",
    "check_rotation",
    "check_pose",
    "check_quaternion",
    "check_depth",
    "check_same_size",
    "check_equirect_size",
    "read_matrix_txt",
]

ROTATION_TOL = 1e-3
"""Max |R^T R - I| entry and |det R - 1| accepted for a rotation (files store ~6 decimals)."""

QUATERNION_NORM_TOL = 1e-3
"""Max | |q| - 1 | accepted for a stored quaternion before it is renormalised."""


def check_rotation(rotation: np.ndarray, source: str | Path, tol: float = ROTATION_TOL) -> np.ndarray:
    """Return ``rotation`` as float64 (3, 3) after checking it is finite, orthonormal and proper."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise CaptureError(f"{source}: rotation must be 3x3, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise CaptureError(f"{source}: rotation contains non-finite values (inf/NaN)")
    ortho_err = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if ortho_err > tol:
        raise CaptureError(
            f"{source}: rotation is not orthonormal (max |R^T R - I| = {ortho_err:.3g} > {tol:g})"
        )
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > tol:
        raise CaptureError(f"{source}: rotation has determinant {det:.6g} (a reflection, expected +1)")
    return r


def check_pose(pose: np.ndarray, source: str | Path, tol: float = ROTATION_TOL) -> np.ndarray:
    """Return a float64 (4, 4) rigid transform after checking shape, finiteness, last row, rotation."""
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4):
        raise CaptureError(f"{source}: pose must be 4x4, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise CaptureError(f"{source}: pose contains non-finite values (inf/NaN)")
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise CaptureError(f"{source}: pose last row must be [0, 0, 0, 1], got {t[3].tolist()}")
    check_rotation(t[:3, :3], source, tol)
    return t


def check_quaternion(q: np.ndarray, source: str | Path, tol: float = QUATERNION_NORM_TOL) -> np.ndarray:
    """Return the unit-normalised quaternion after checking it is finite and near unit norm.

    The component order is whatever the caller uses; only the norm is checked here.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,):
        raise CaptureError(f"{source}: quaternion must have 4 components, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise CaptureError(f"{source}: quaternion contains non-finite values (inf/NaN)")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > tol:
        raise CaptureError(f"{source}: quaternion norm is {norm:.6g}, too far from 1 (tolerance {tol:g})")
    return q / norm


def check_depth(depth: np.ndarray, source: str | Path) -> np.ndarray:
    """Return depth as float32 (H, W) after checking it is finite and non-negative."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise CaptureError(f"{source}: depth must be (H, W), got shape {d.shape}")
    d = d.astype(np.float32, copy=False)
    if not np.all(np.isfinite(d)):
        raise CaptureError(f"{source}: depth contains non-finite values (inf/NaN); use 0 for invalid")
    if np.any(d < 0):
        raise CaptureError(f"{source}: depth contains negative values (min {float(d.min()):.4g})")
    return d


def check_same_size(rgb: np.ndarray, depth: np.ndarray, source: str | Path) -> None:
    """Colour and depth must share one pixel grid."""
    if tuple(rgb.shape[:2]) != tuple(depth.shape[:2]):
        raise CaptureError(
            f"{source}: rgb/depth size mismatch: rgb is {rgb.shape[1]}x{rgb.shape[0]}, "
            f"depth is {depth.shape[1]}x{depth.shape[0]} (WxH)"
        )


def check_equirect_size(height: int, width: int, source: str | Path) -> None:
    """An equirectangular panorama spans 360 x 180 degrees, so W = 2H."""
    if width != 2 * height:
        raise CaptureError(
            f"{source}: not an equirectangular panorama: {width}x{height} (WxH), expected W = 2H"
        )


def read_matrix_txt(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray:
    """Parse a whitespace-separated text matrix of exactly ``shape`` (row-major) as float64.

    Non-finite entries are returned as they are (callers decide whether that means "skip").
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing {what} file")
    text = path.read_text(encoding="utf-8", errors="replace")
    try:
        values = [float(tok) for tok in text.split()]
    except ValueError as err:
        raise CaptureError(f"{path}: {what} file contains a non-number ({err})") from None
    expected = math.prod(shape)
    if len(values) != expected:
        raise CaptureError(f"{path}: {what} file must hold {expected} numbers {shape}, found {len(values)}")
    return np.array(values, dtype=np.float64).reshape(shape)
