"""The Habitat / VLN-CE frame and ours, in one place: points, rotations and headings.

Habitat (and every VLN-CE / R2R-CE / RxR-CE file) is Y-up with the agent looking along its -Z and
quaternions ``[x, y, z, w]``; our world is Z-up, heading 0 = +X, quaternions ``(w, x, y, z)``.
The data engine writes its episode files in the Habitat frame with these functions and the
evaluation's loaders read them back with the same ones.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "HABITAT_TO_WORLD",
    "habitat_heading",
    "habitat_quaternion_to_world",
    "habitat_rotation_for_heading",
    "habitat_to_world",
    "quat_multiply_wxyz",
    "quat_to_matrix_wxyz",
    "unit_quaternion",
    "world_heading",
    "world_to_habitat",
]

# (x, y, z)_habitat -> (x, -z, y)_world: rotation about +X by +90 degrees.
HABITAT_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_Q_HABITAT_TO_WORLD = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])  # wxyz


def habitat_to_world(points: Any) -> np.ndarray:
    """Habitat Y-up points ``(..., 3)`` -> our Z-up world: ``(x, y, z) -> (x, -z, y)``."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points: expected (..., 3), got shape {p.shape}")
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def world_to_habitat(points: Any) -> np.ndarray:
    """Inverse of :func:`habitat_to_world`: ``(x, y, z) -> (x, z, -y)``."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points: expected (..., 3), got shape {p.shape}")
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def quat_multiply_wxyz(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_to_matrix_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit (w, x, y, z) quaternion."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def unit_quaternion(q: Any, where: str) -> np.ndarray:
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (4,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: expected 4 finite numbers, got {q!r}")
    n = float(np.linalg.norm(arr))
    if abs(n - 1.0) > 1e-3:
        raise ValueError(f"{where}: quaternion norm is {n:.6f}, expected 1")
    return arr / n


def habitat_quaternion_to_world(q_xyzw: Any) -> np.ndarray:
    """A Habitat rotation ``[x, y, z, w]`` as the same physical rotation in our world, ``(w, x, y, z)``.

    Conjugation by the frame change: ``q_world = q_c ⊗ q_habitat ⊗ q_c*`` with ``q_c`` the +90°
    rotation about X, so a yaw about Habitat's +Y becomes the same yaw about our +Z.
    """
    x, y, z, w = unit_quaternion(q_xyzw, "rotation")
    qc = _Q_HABITAT_TO_WORLD
    qc_inv = qc * np.array([1.0, -1.0, -1.0, -1.0])
    out = quat_multiply_wxyz(quat_multiply_wxyz(qc, np.array([w, x, y, z])), qc_inv)
    return out if out[0] >= 0 else -out  # canonical sign


def habitat_rotation_for_heading(heading: float) -> np.ndarray:
    """The upright Habitat agent rotation ``[x, y, z, w]`` whose :func:`habitat_heading` is ``heading``.

    Habitat's identity agent looks along its -Z, our +Y (heading +90°), so the rotation is a yaw of
    ``heading - 90°`` about Habitat's +Y.
    """
    half = (float(heading) - math.pi / 2.0) / 2.0
    return np.array([0.0, math.sin(half), 0.0, math.cos(half)])


def habitat_heading(q_xyzw: Any) -> float:
    """Heading (yaw about +Z, 0 = +X, CCW positive) in our world of a Habitat agent rotation.

    A Habitat agent looks along its local -Z; that direction is rotated into Habitat's world, mapped
    to ours and projected onto the floor plane.
    """
    r = quat_to_matrix_wxyz(habitat_quaternion_to_world(q_xyzw))
    forward = r @ (HABITAT_TO_WORLD @ np.array([0.0, 0.0, -1.0]))
    return math.atan2(forward[1], forward[0])


def world_heading(q_wxyz: Any) -> float:
    """Heading of a rotation already in our world: the image of +X projected onto the floor."""
    r = quat_to_matrix_wxyz(unit_quaternion(q_wxyz, "rotation"))
    return math.atan2(r[1, 0], r[0, 0])
