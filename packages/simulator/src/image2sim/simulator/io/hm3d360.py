"""Reader for the ``hm3d_360`` panorama layout (HM3D captures rendered with habitat-sim).

Per frame ``NNNNN``: ``NNNNN_rgb.png`` (W x H equirect, W = 2H), ``NNNNN_depth.png`` (uint16 Euclidean
range in millimetres, 0 = invalid) and ``NNNNN_pose.txt`` (``tx ty tz qx qy qz qw``, camera-to-world,
quaternion scalar-last, world Z-up, camera axes OpenGL: +x right, +y up, -z forward).

Their pixel mapping: pixel (u, v) (integer indices) has the OpenGL-camera direction
``(-sin(phi) sin(theta), cos(phi), sin(phi) cos(theta))`` with ``theta = 2 pi (u + 0.5) / W`` and
``phi = pi (v + 0.5) / H``. With ``lon = theta - pi`` and ``lat = pi/2 - phi`` this is
``(cos(lat) sin(lon), sin(lat), -cos(lat) cos(lon))``, which the OpenGL -> OpenCV axis flip
``diag(1, -1, -1)`` turns into exactly our equirect direction at the pixel centre ``(u + 0.5, v + 0.5)``.
So images are used as they are; only the pose changes (``opengl_to_opencv_cam_to_world``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from image2sim.simulator.conventions import opengl_to_opencv_cam_to_world
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.geometry.se3 import quat_to_matrix, quat_xyzw_to_wxyz
from image2sim.simulator.io.images import probe_first_size, read_depth_uint16, read_rgb
from image2sim.simulator.io.records import Capture, CaptureError, Frame
from image2sim.simulator.io.validation import (
    check_equirect_size,
    check_pose,
    check_quaternion,
    check_same_size,
    read_matrix_txt,
)

__all__ = ["FORMAT", "is_hm3d_360", "read_hm3d_360", "hm3d_pose_to_cam_to_world", "hm3d_pixel_direction_gl"]

FORMAT = "hm3d_360"
DEPTH_SCALE = 1000.0
"""Depth PNG units per metre (millimetres)."""

_SUFFIXES = {"rgb": "_rgb.png", "depth": "_depth.png", "pose": "_pose.txt"}


def hm3d_pixel_direction_gl(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """The format's own mapping: integer pixel (u, v) -> unit direction (..., 3) in its OpenGL camera."""
    theta = 2.0 * np.pi * (np.asarray(u, dtype=np.float64) + 0.5) / width
    phi = np.pi * (np.asarray(v, dtype=np.float64) + 0.5) / height
    return np.stack((-np.sin(phi) * np.sin(theta), np.cos(phi), np.sin(phi) * np.cos(theta)), axis=-1)


def hm3d_pose_to_cam_to_world(values: np.ndarray, source: str | Path) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` (OpenGL camera) -> our 4x4 camera-to-world (OpenCV camera), checked."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.shape != (7,):
        raise CaptureError(f"{source}: pose must be 7 numbers 'tx ty tz qx qy qz qw', got {values.size}")
    if not np.all(np.isfinite(values[:3])):
        raise CaptureError(f"{source}: translation contains non-finite values (inf/NaN)")
    quat_xyzw = check_quaternion(values[3:], source)
    pose_gl = np.eye(4)
    q_wxyz = quat_xyzw_to_wxyz(torch.from_numpy(quat_xyzw))  # the file is scalar-last, our code scalar-first
    pose_gl[:3, :3] = quat_to_matrix(q_wxyz).numpy()
    pose_gl[:3, 3] = values[:3]
    return check_pose(opengl_to_opencv_cam_to_world(pose_gl), source)


def _stems(root: Path) -> dict[str, dict[str, Path]]:
    stems: dict[str, dict[str, Path]] = {}
    for kind, suffix in _SUFFIXES.items():
        for path in root.glob(f"*{suffix}"):
            stems.setdefault(path.name[: -len(suffix)], {})[kind] = path
    return stems


def is_hm3d_360(path: Path) -> bool:
    """A folder holding at least one ``*_pose.txt`` with a matching ``*_rgb.png``."""
    path = Path(path)
    if not path.is_dir():
        return False
    return any(
        (p.with_name(p.name[: -len("_pose.txt")] + "_rgb.png")).is_file() for p in path.glob("*_pose.txt")
    )


def read_hm3d_360(path: str | Path, *, strict: bool = True) -> Capture:
    """Open an ``hm3d_360`` scene folder. Poses are parsed and checked now, images load lazily.

    With ``strict=False`` frames with a missing file or a bad pose are listed in ``Capture.skipped``
    instead of raising.
    """
    root = Path(path)
    if not root.is_dir():
        raise CaptureError(f"{root}: not a directory")
    ids, poses, skipped = [], [], []
    for stem, files in sorted(_stems(root).items()):
        try:
            missing = [root / f"{stem}{sfx}" for kind, sfx in _SUFFIXES.items() if kind not in files]
            if missing:
                raise CaptureError(f"{missing[0]}: missing file (frame {stem!r} has only {sorted(files)})")
            pose = hm3d_pose_to_cam_to_world(read_matrix_txt(files["pose"], (7,), "pose"), files["pose"])
        except CaptureError as err:
            if strict:
                raise
            skipped.append((stem, str(err)))
            continue
        ids.append(stem)
        poses.append(pose)
    if not ids:
        raise CaptureError(
            f"{root}: no usable hm3d_360 frames" + (f" ({len(skipped)} skipped)" if skipped else "")
        )
    pose_of = dict(zip(ids, poses, strict=False))
    ids, (height, width) = probe_first_size(ids, lambda f: root / f"{f}_rgb.png", "colour", strict, skipped)
    check_equirect_size(height, width, root / f"{ids[0]}_rgb.png")
    camera = EquirectCamera(height, width)

    def load(fid: str) -> Frame:
        rgb_path, depth_path = root / f"{fid}_rgb.png", root / f"{fid}_depth.png"
        rgb = read_rgb(rgb_path)
        depth = read_depth_uint16(depth_path).astype(np.float32) / np.float32(DEPTH_SCALE)
        check_same_size(rgb, depth, rgb_path)
        if depth.shape != (camera.height, camera.width):
            raise CaptureError(
                f"{depth_path}: image is {depth.shape[1]}x{depth.shape[0]}, "
                f"other frames are {camera.width}x{camera.height}"
            )
        return Frame(rgb=rgb, depth=depth, camera=camera, cam_to_world=pose_of[fid].copy(), frame_id=fid)

    return Capture(
        root, FORMAT, ids, load, skipped=skipped, poses=np.stack([pose_of[i] for i in ids]), camera=camera
    )
