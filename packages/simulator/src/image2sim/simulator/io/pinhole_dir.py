"""Reader for ``pinhole_dir``: the folder layout ScanNet's ``SensReader`` exporter writes.

Layout: ``color/<i>.jpg`` (or ``.png``), ``depth/<i>.png`` (uint16 z-depth, millimetres by default),
``pose/<i>.txt`` (4x4 camera-to-world, OpenCV camera, world as recorded), ``intrinsic/
intrinsic_depth.txt`` (4x4, OpenCV principal point) and optionally ``intrinsic/intrinsic_color.txt``.

Conversions:

* Intrinsics: OpenCV puts pixel centres at integers, we put them at +0.5, so ``cx, cy += 0.5``
  (:func:`~image2sim.simulator.conventions.opencv_principal_point_to_ours`).
* Colour and depth may differ in resolution (ScanNet: 1296x968 colour, 640x480 depth). Frames live
  on the **depth** grid: each depth pixel centre is mapped through the depth intrinsics to a ray
  and through the colour intrinsics to a colour pixel (the exporter's two cameras share a centre
  and orientation), or, without ``intrinsic_color.txt``, by the size ratio; colour is sampled
  bilinearly after an area pre-shrink to avoid aliasing. ``Frame.notes`` records it.
* Poses with inf/NaN entries (ScanNet marks lost tracking that way) are reported in
  ``Capture.skipped`` and never read, in strict mode too; other bad poses raise (strict) or skip.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from image2sim.simulator.conventions import opencv_principal_point_to_ours
from image2sim.simulator.geometry.cameras import PinholeCamera
from image2sim.simulator.io.images import probe_first_size, read_depth_uint16, read_rgb
from image2sim.simulator.io.records import Capture, CaptureError, Frame
from image2sim.simulator.io.resample import sample_rgb
from image2sim.simulator.io.validation import check_pose, read_matrix_txt

__all__ = ["FORMAT", "is_pinhole_dir", "read_pinhole_dir", "read_intrinsics"]

FORMAT = "pinhole_dir"
_COLOUR_EXTS = (".jpg", ".jpeg", ".png")


def is_pinhole_dir(path: Path) -> bool:
    """A folder with ``color/``, ``depth/``, ``pose/`` and ``intrinsic/intrinsic_depth.txt``."""
    path = Path(path)
    return (
        all((path / d).is_dir() for d in ("color", "depth", "pose"))
        and (path / "intrinsic" / "intrinsic_depth.txt").is_file()
    )


def read_intrinsics(path: Path) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in our convention from a 4x4 (or 3x3) OpenCV intrinsic matrix file."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing intrinsics file")
    n = len(path.read_text(encoding="utf-8", errors="replace").split())
    k = read_matrix_txt(path, (3, 3) if n == 9 else (4, 4), "intrinsics")
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if not np.all(np.isfinite(k[:3, :3])):
        raise CaptureError(f"{path}: intrinsics contain non-finite values")
    if fx <= 0 or fy <= 0:
        raise CaptureError(f"{path}: focal lengths must be positive, got fx={fx}, fy={fy}")
    cx, cy = opencv_principal_point_to_ours(cx, cy)
    return float(fx), float(fy), float(cx), float(cy)


def _sort_key(stem: str):
    return (0, int(stem), "") if stem.isdigit() else (1, 0, stem)


def _colour_path(root: Path, stem: str) -> Path | None:
    for ext in _COLOUR_EXTS:
        p = root / "color" / f"{stem}{ext}"
        if p.is_file():
            return p
    return None


@lru_cache(maxsize=8)
def _colour_coords(depth_k: tuple, colour_k: tuple, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous colour-image coordinates of every depth pixel centre (shared camera centre)."""
    fx, fy, cx, cy = depth_k
    gx, gy, gcx, gcy = colour_k
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid((u - cx) / fx * gx + gcx, (v - cy) / fy * gy + gcy)
    return uu, vv


def read_pinhole_dir(path: str | Path, *, strict: bool = True, depth_scale: float = 1000.0) -> Capture:
    """Open a ScanNet-style export folder; poses are parsed and checked now, images load lazily.

    ``depth_scale``: depth PNG units per metre (1000 = millimetres). With ``strict=False`` frames
    with a missing file or a bad pose go to ``Capture.skipped`` instead of raising.
    """
    root = Path(path)
    if not is_pinhole_dir(root):
        raise CaptureError(
            f"{root}: not a pinhole_dir folder (needs color/, depth/, pose/, intrinsic/intrinsic_depth.txt)"
        )
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise CaptureError(f"pinhole_dir option depth_scale={depth_scale}: must be positive")
    depth_k = read_intrinsics(root / "intrinsic" / "intrinsic_depth.txt")
    colour_k_path = root / "intrinsic" / "intrinsic_color.txt"
    colour_k = read_intrinsics(colour_k_path) if colour_k_path.is_file() else None
    stems = sorted((p.stem for p in (root / "depth").glob("*.png")), key=_sort_key)
    ids, poses, skipped = [], [], []
    for stem in stems:
        pose_path = root / "pose" / f"{stem}.txt"
        try:
            if _colour_path(root, stem) is None:
                raise CaptureError(f"{root / 'color' / (stem + '.jpg')}: missing colour file")
            raw_pose = read_matrix_txt(pose_path, (4, 4), "pose")
        except CaptureError as err:
            if strict:
                raise
            skipped.append((stem, str(err)))
            continue
        if not np.all(np.isfinite(raw_pose)):
            # ScanNet writes -inf poses where tracking was lost: a known, expected gap, not an error.
            skipped.append((stem, f"{pose_path}: pose contains non-finite values (inf/NaN)"))
            continue
        try:
            pose = check_pose(raw_pose, pose_path)
        except CaptureError as err:
            if strict:
                raise
            skipped.append((stem, str(err)))
            continue
        ids.append(stem)
        poses.append(pose)
    if not ids:
        raise CaptureError(
            f"{root}: no usable pinhole_dir frames" + (f" ({len(skipped)} skipped)" if skipped else "")
        )
    pose_of = dict(zip(ids, poses, strict=False))
    ids, (height, width) = probe_first_size(
        ids, lambda f: root / "depth" / f"{f}.png", "depth", strict, skipped
    )
    camera = PinholeCamera(*depth_k, height, width)
    scale = np.float32(depth_scale)

    def load(fid: str) -> Frame:
        depth_path = root / "depth" / f"{fid}.png"
        colour_path = _colour_path(root, fid)
        if colour_path is None:
            raise CaptureError(f"{root / 'color' / (fid + '.jpg')}: missing colour file")
        depth = read_depth_uint16(depth_path).astype(np.float32) / scale
        if depth.shape != (height, width):
            raise CaptureError(
                f"{depth_path}: image is {depth.shape[1]}x{depth.shape[0]}, other frames are {width}x{height}"
            )
        rgb = read_rgb(colour_path)
        notes = []
        ch, cw = rgb.shape[:2]
        ck = colour_k
        if ck is None:
            if (ch, cw) != (height, width) and abs(cw / width - ch / height) > 0.02 * cw / width:
                raise CaptureError(
                    f"{colour_path}: colour {cw}x{ch} and depth {width}x{height} differ in aspect ratio and "
                    f"{colour_k_path} is missing, so they cannot be registered"
                )
            ck = (
                depth_k[0] * cw / width,
                depth_k[1] * ch / height,
                depth_k[2] * cw / width,
                depth_k[3] * ch / height,
            )
            how = "by the size ratio (no intrinsic_color.txt)"
        else:
            how = "through intrinsic_color/intrinsic_depth"
        if (ch, cw) != (height, width) or not np.allclose(ck, depth_k, rtol=0, atol=1e-9):
            # Area pre-shrink when colour is much larger, so bilinear taps do not alias.
            shrink = min(cw / width, ch / height)
            if shrink > 1.5:
                new_w, new_h = round(cw / shrink), round(ch / shrink)
                sx, sy = new_w / cw, new_h / ch
                rgb = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_AREA)
                ck = (ck[0] * sx, ck[1] * sy, ck[2] * sx, ck[3] * sy)
            uu, vv = _colour_coords(depth_k, tuple(ck), height, width)
            rgb = sample_rgb(rgb, uu, vv, wrap_u=False)
            notes.append(f"colour {cw}x{ch} resampled to the depth grid {width}x{height} {how} (bilinear)")
        return Frame(
            rgb=rgb, depth=depth, camera=camera, cam_to_world=pose_of[fid].copy(), frame_id=fid, notes=notes
        )

    return Capture(
        root, FORMAT, ids, load, skipped=skipped, poses=np.stack([pose_of[i] for i in ids]), camera=camera
    )
