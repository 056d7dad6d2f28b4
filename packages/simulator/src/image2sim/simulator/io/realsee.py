"""Reader for ``realsee`` scenes (RealSee3D-style panoramic RGB-D viewpoints).

Layout: ``viewpoints.txt`` (one id per line) and ``viewpoints/<id>/`` with ``panoImage_1600.jpg``
(equirect colour), ``depth_image.png`` (uint16 range; metres = value / ``depth_scale.txt``, 0 =
invalid; ``depth_scale.txt`` is looked up in the viewpoint folder, then the scene folder) and
``extrinsics.txt`` (4x4 row-major camera-to-world).

Conversions:

* World: Realsee is Y-down; ours is Z-up: (x, y, z) -> (x, z, -y), i.e. ``T_ours = M @ T_realsee``
  with ``M = Y_DOWN_TO_Z_UP_WORLD`` (a proper rotation). The camera frame (x right, y down,
  z forward) already is OpenCV, so nothing changes on the camera side.
* Pixels (default ``half_pixel="centres"``): pixel (u, v) of a Realsee panorama is the sample at
  ``lon = ((u + 0.5)/W - 0.5) 2 pi``, ``lat = ((v + 0.5)/H - 0.5) pi`` (latitude positive down),
  i.e. its samples already sit on our pixel centres and the images are used as stored (no
  resampling, so no blur and no invented depth). Measured on a real RealSee3D scene (kept outside
  the repository): read this way, the depth of the nearest viewpoints agrees to 0.08 mm (median;
  81 % of points within 1 cm); read with the integer-index mapping below, to 4.6 mm (71 %).
  Colour larger than the depth image is area-averaged onto the depth grid (``cv2.INTER_AREA``:
  each depth pixel averages exactly the colour area it covers, so centres stay centres); smaller
  colour is sampled bilinearly at ``((j + 0.5) W_c / W, (i + 0.5) H_c / H)``, wrapping across the
  seam. Each frame's ``notes`` say which.
* ``half_pixel="resample"`` is for data written with the *index* convention ``lon = (u/W - 0.5)
  2 pi``, ``lat = (v/H - 0.5) pi`` (samples half a pixel left/up of our centres): colour and depth
  are resampled onto our grid (the grid of the depth image): our pixel centre ``(j + 0.5, i + 0.5)``
  reads the source at index ``(j + 0.5) W_src / W`` (wrapping across the seam) and
  ``(i + 0.5) H_src / H`` (clamped at the bottom pole). Colour is bilinear; depth is edge-aware
  (:func:`image2sim.simulator.io.resample.sample_depth`). On true RealSee3D data this rotates
  every panorama by half a pixel and blurs it (the measurement above).
* ``half_pixel="ignore"`` (the earlier name for "read as stored") is accepted as ``"centres"``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from image2sim.simulator.conventions import Y_DOWN_TO_Z_UP_WORLD
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.images import probe_first_size, read_depth_uint16, read_rgb
from image2sim.simulator.io.records import Capture, CaptureError, Frame
from image2sim.simulator.io.resample import planar_rel_tol, sample_depth, sample_rgb
from image2sim.simulator.io.validation import (
    check_equirect_size,
    check_pose,
    read_matrix_txt,
)

__all__ = [
    "FORMAT",
    "colour_to_grid",
    "HALF_PIXEL_MODES",
    "is_realsee",
    "read_realsee",
    "realsee_pose_to_cam_to_world",
    "realsee_pixel_direction",
    "realsee_index_pixel_direction",
]

FORMAT = "realsee"
RGB_NAME = "panoImage_1600.jpg"
DEPTH_NAME = "depth_image.png"
EXTRINSICS_NAME = "extrinsics.txt"
DEPTH_SCALE_NAME = "depth_scale.txt"
HALF_PIXEL_MODES = ("centres", "resample")
"""``half_pixel`` values: ``centres`` (default, the format's true mapping) and ``resample``."""
_HALF_PIXEL_ALIASES = {"ignore": "centres", "centers": "centres"}


def realsee_pixel_direction(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """The format's mapping: pixel index (u, v) -> unit direction (..., 3) in its camera frame.

    Samples sit on pixel centres: ``lon = ((u + 0.5)/W - 0.5) 2 pi``, ``lat = ((v + 0.5)/H - 0.5) pi``
    (latitude positive down, camera x right, y down, z forward), identical to our
    ``EquirectCamera.pixel_to_ray(u + 0.5, v + 0.5)``.
    """
    u = np.asarray(u, dtype=np.float64) + 0.5
    v = np.asarray(v, dtype=np.float64) + 0.5
    return realsee_index_pixel_direction(u, v, height, width)


def realsee_index_pixel_direction(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """The *index* convention ``half_pixel="resample"`` assumes: ``lon = (u/W - 0.5) 2 pi``,
    ``lat = (v/H - 0.5) pi`` at pixel index (u, v), half a pixel left/up of the true centres."""
    lon = (np.asarray(u, dtype=np.float64) / width - 0.5) * 2.0 * np.pi
    lat = (np.asarray(v, dtype=np.float64) / height - 0.5) * np.pi
    return np.stack((np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)), axis=-1)


def realsee_pose_to_cam_to_world(extrinsics: np.ndarray, source: str | Path) -> np.ndarray:
    """Realsee camera-to-world (Y-down world) -> ours (Z-up world), checked."""
    pose = check_pose(extrinsics, source)
    world = np.eye(4)
    world[:3, :3] = Y_DOWN_TO_Z_UP_WORLD
    return check_pose(world @ pose, source)


def is_realsee(path: Path) -> bool:
    """A folder with ``viewpoints.txt`` and a ``viewpoints/`` subfolder."""
    path = Path(path)
    return (path / "viewpoints.txt").is_file() and (path / "viewpoints").is_dir()


def _read_depth_scale(root: Path, vp_dir: Path) -> float:
    path = vp_dir / DEPTH_SCALE_NAME
    if not path.is_file():
        path = root / DEPTH_SCALE_NAME
    if not path.is_file():
        raise CaptureError(f"{vp_dir / DEPTH_SCALE_NAME}: missing depth scale file (also not in {root})")
    scale = float(read_matrix_txt(path, (1,), "depth scale")[0])
    if not np.isfinite(scale) or scale <= 0:
        raise CaptureError(f"{path}: depth scale must be a positive finite number, got {scale}")
    return scale


def _half_pixel_mode(half_pixel: str) -> str:
    mode = _HALF_PIXEL_ALIASES.get(half_pixel, half_pixel) if isinstance(half_pixel, str) else half_pixel
    if mode not in HALF_PIXEL_MODES:
        raise CaptureError(
            f"realsee option half_pixel={half_pixel!r}: expected 'centres' (default: samples on pixel "
            "centres, images used as stored) or 'resample' (data written at integer pixel indices, "
            "resampled by half a pixel)"
        )
    return mode


@lru_cache(maxsize=8)
def _source_coords(dst_h: int, dst_w: int, src_h: int, src_w: int) -> tuple[np.ndarray, np.ndarray]:
    """``resample`` mode: continuous source coordinates (u, v) (centres at +0.5) read by each pixel
    of our grid, for a source written with the index convention."""
    j = np.arange(dst_w, dtype=np.float64) + 0.5
    i = np.arange(dst_h, dtype=np.float64) + 0.5
    index_u = j * (src_w / dst_w)  # Realsee pixel index with the same longitude as our centre j + 0.5
    index_v = i * (src_h / dst_h)
    uu, vv = np.meshgrid(index_u + 0.5, index_v + 0.5)  # index -> continuous coordinate
    return uu, vv


@lru_cache(maxsize=8)
def _centre_coords(dst_h: int, dst_w: int, src_h: int, src_w: int) -> tuple[np.ndarray, np.ndarray]:
    """``centres`` mode: source coordinates with the same direction as our pixel centres."""
    uu, vv = np.meshgrid(
        (np.arange(dst_w, dtype=np.float64) + 0.5) * (src_w / dst_w),
        (np.arange(dst_h, dtype=np.float64) + 0.5) * (src_h / dst_h),
    )
    return uu, vv


def colour_to_grid(rgb: np.ndarray, height: int, width: int) -> tuple[np.ndarray, str | None]:
    """Colour whose samples sit on pixel centres -> the ``height x width`` grid, centres kept.

    Same size: unchanged (note None). Larger: area average (``cv2.INTER_AREA``; each output pixel
    averages exactly the source area it covers, also for non-integer ratios, so it never needs the
    seam). Smaller (or mixed): bilinear at ``((j + 0.5) W_c / W, (i + 0.5) H_c / H)``, wrapping in
    longitude. Returns the image and a note saying what was done.
    """
    src_h, src_w = rgb.shape[:2]
    if (src_h, src_w) == (height, width):
        return rgb, None
    if src_h >= height and src_w >= width:
        out = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
        how = "area-averaged"
    else:
        uu, vv = _centre_coords(height, width, src_h, src_w)
        out = sample_rgb(rgb, uu, vv, wrap_u=True)
        how = "bilinearly upsampled"
    return np.ascontiguousarray(out), f"colour {how} from {src_w}x{src_h} to {width}x{height} (centres kept)"


def read_realsee(path: str | Path, *, strict: bool = True, half_pixel: str = "centres") -> Capture:
    """Open a Realsee scene folder; poses are parsed and checked now, images load lazily.

    ``half_pixel``: ``"centres"`` (default: the format's samples sit on our pixel centres; images
    are used as stored, colour resized to the depth grid if it differs) or ``"resample"`` (data
    written at integer pixel indices; see the module docstring). ``"ignore"`` is an old name for
    ``"centres"``; any other value is a :class:`CaptureError`.
    With ``strict=False`` viewpoints with a missing file or a bad pose/scale go to ``Capture.skipped``.
    """
    half_pixel = _half_pixel_mode(half_pixel)
    root = Path(path)
    list_path = root / "viewpoints.txt"
    if not list_path.is_file():
        raise CaptureError(f"{list_path}: missing viewpoint list")
    vp_ids = [line.strip() for line in list_path.read_text(encoding="utf-8", errors="replace").splitlines()]
    vp_ids = [v for v in vp_ids if v]
    if len(set(vp_ids)) != len(vp_ids):
        raise CaptureError(f"{list_path}: duplicate viewpoint ids")
    ids, poses, scales, skipped = [], [], {}, []
    for vid in vp_ids:
        vp_dir = root / "viewpoints" / vid
        try:
            if not vp_dir.is_dir():
                raise CaptureError(f"{vp_dir}: missing viewpoint folder (listed in {list_path.name})")
            for name in (RGB_NAME, DEPTH_NAME):
                if not (vp_dir / name).is_file():
                    raise CaptureError(f"{vp_dir / name}: missing file")
            ext_path = vp_dir / EXTRINSICS_NAME
            pose = realsee_pose_to_cam_to_world(read_matrix_txt(ext_path, (4, 4), "extrinsics"), ext_path)
            scales[vid] = _read_depth_scale(root, vp_dir)
        except CaptureError as err:
            if strict:
                raise
            skipped.append((vid, str(err)))
            continue
        ids.append(vid)
        poses.append(pose)
    if not ids:
        raise CaptureError(
            f"{root}: no usable realsee viewpoints" + (f" ({len(skipped)} skipped)" if skipped else "")
        )
    pose_of = dict(zip(ids, poses, strict=False))
    ids, (height, width) = probe_first_size(
        ids, lambda v: root / "viewpoints" / v / DEPTH_NAME, "depth", strict, skipped
    )
    check_equirect_size(height, width, root / "viewpoints" / ids[0] / DEPTH_NAME)
    camera = EquirectCamera(height, width)

    def load(vid: str) -> Frame:
        vp_dir = root / "viewpoints" / vid
        rgb = read_rgb(vp_dir / RGB_NAME)
        raw = read_depth_uint16(vp_dir / DEPTH_NAME)
        check_equirect_size(*rgb.shape[:2], vp_dir / RGB_NAME)
        if raw.shape != (height, width):
            raise CaptureError(
                f"{vp_dir / DEPTH_NAME}: image is {raw.shape[1]}x{raw.shape[0]}, "
                f"other viewpoints are {width}x{height}"
            )
        depth = raw.astype(np.float32) / np.float32(scales[vid])
        if half_pixel == "resample":
            src_h, src_w = rgb.shape[:2]
            uu, vv = _source_coords(height, width, height, width)
            depth = sample_depth(depth, uu, vv, wrap_u=True, rel_tol=planar_rel_tol(2 * np.pi / width))
            cu, cv = _source_coords(height, width, src_h, src_w)
            rgb = sample_rgb(rgb, cu, cv, wrap_u=True)
            note = (
                "half_pixel=resample: resampled by half a pixel onto our pixel-centre grid (source taken "
                f"to sample at integer indices): depth edge-aware, colour bilinear from {src_w}x{src_h} "
                f"to {width}x{height}"
            )
        else:
            rgb, colour_note = colour_to_grid(rgb, height, width)
            note = "half_pixel=centres: samples read on our pixel centres as stored (no resampling)"
            if colour_note:
                note += f"; {colour_note}"
        return Frame(
            rgb=rgb, depth=depth, camera=camera, cam_to_world=pose_of[vid].copy(), frame_id=vid, notes=[note]
        )

    return Capture(
        root, FORMAT, ids, load, skipped=skipped, poses=np.stack([pose_of[i] for i in ids]), camera=camera
    )
