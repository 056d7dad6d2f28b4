"""Frames, units and pixel mappings: the single source of truth for Image2Sim.

Everything in the repository converts *to* these conventions at the boundary (readers, writers)
and assumes them everywhere else. ``docs/conventions.md`` explains them with pictures in words.

World
    Z-up, metres, right-handed. Agent heading is the yaw about world +Z (0 = looking along +X,
    counter-clockwise positive, i.e. +90° looks along +Y).
Camera
    OpenCV: x right, y down, z forward. Poses are camera-to-world 4x4 (float64) matrices.
Equirectangular pixel <-> direction
    For a W x H panorama, pixel (u, v) (column, row; continuous, pixel centres at integer + 0.5):
        lon = 2*pi*(u / W) - pi          in [-pi, pi), 0 at the centre column (camera forward),
                                         increasing to the right
        lat = pi/2 - pi*(v / H)          in (-pi/2, pi/2], +90 deg at the top row
    and the camera-frame unit direction is
        d = (cos(lat) sin(lon),  -sin(lat),  cos(lat) cos(lon)).
    The inverse is lon = atan2(x, z), lat = atan2(-y, hypot(x, z)).
Pinhole pixel <-> direction
    u = fx * x / z + cx, v = fy * y / z + cy in continuous pixel coordinates, pixel centres at
    integer + 0.5 (so an OpenCV/ScanNet intrinsic, which puts centres at integers, needs
    cx += 0.5, cy += 0.5 on read; see :func:`opencv_principal_point_to_ours`).
Depth
    Panorama depth is Euclidean range along the ray; pinhole depth is z. Both in metres; 0 = invalid.
Tensors
    Images (B, 3, H, W) float in [0, 1]; depth (B, 1, H, W) float metres.
Quaternions
    (w, x, y, z) inside the code. File formats state their own order.
Actions
    STOP=0, MOVE_FORWARD=1, TURN_LEFT=2, TURN_RIGHT=3.
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])
"""World up axis (Z-up)."""

DEPTH_INVALID = 0.0
"""Depth value that marks an invalid pixel, for range and z-depth alike."""

DEPTH_PNG_SCALE = 1000.0
"""uint16 depth PNGs in the canonical capture format store millimetres (metres * 1000)."""

QUATERNION_ORDER = "wxyz"
"""Order of quaternion components inside the code."""


class Action(IntEnum):
    """Discrete navigation actions; the integer ids are part of every file format."""

    STOP = 0
    MOVE_FORWARD = 1
    TURN_LEFT = 2
    TURN_RIGHT = 3


# Fixed change of camera basis: OpenGL camera (x right, y up, -z forward) -> OpenCV camera.
OPENGL_TO_OPENCV_CAMERA = np.diag([1.0, -1.0, -1.0])


def opengl_to_opencv_cam_to_world(cam_to_world_gl: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world pose whose camera axes are OpenGL to one with OpenCV axes."""
    out = np.array(cam_to_world_gl, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ OPENGL_TO_OPENCV_CAMERA
    return out


# World Y-down (x, y, z) -> our Z-up (x, z, -y); a proper rotation (det = +1).
Y_DOWN_TO_Z_UP_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def opencv_principal_point_to_ours(cx: float, cy: float) -> tuple[float, float]:
    """OpenCV puts pixel centres at integers; ours are at integer + 0.5."""
    return cx + 0.5, cy + 0.5


def heading_to_yaw_matrix(heading: float) -> np.ndarray:
    """3x3 rotation about world +Z by ``heading`` radians."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_rotation_for_heading(heading: float, pitch: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation of an upright OpenCV camera looking along ``heading`` (yaw about +Z).

    At heading 0 the camera looks along world +X with its x axis (right) along world -Y and its
    y axis (down) along world -Z. ``pitch`` (radians, positive up) tilts the optical axis.
    """
    # Columns: camera x, y, z axes expressed in the world, for heading 0, pitch 0.
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cp, sp = math.cos(pitch), math.sin(pitch)
    # Pitch about the camera x axis; positive pitch tilts forward (z) towards up (-y).
    pitch_cam = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return heading_to_yaw_matrix(heading) @ base @ pitch_cam


def heading_of_rotation(cam_to_world_rotation: np.ndarray) -> float:
    """Yaw (radians) of a camera's forward axis projected onto the world XY plane."""
    forward = np.asarray(cam_to_world_rotation)[:3, 2]
    return math.atan2(forward[1], forward[0])
