"""The inputs of ``image2sim data lift``: a folder of images or a video, as RGB frames with ids.

* A folder: every ``.png``/``.jpg``/``.jpeg`` file (any case) is a frame; ids are the file stems,
  in natural order (``img2`` before ``img10``). All frames must have one size.
* A video (anything OpenCV's ``VideoCapture`` opens): frames are sampled at ``fps`` per second of
  video, blurred ones are rejected (variance of the Laplacian below ``blur_ratio`` times the median
  of their sampled neighbours), and redundant ones (median feature displacement since the last kept
  frame below ``min_motion`` of the image diagonal) too; ids are ``f000000``, ``f000001``, ... in
  the order kept.
* Panoramas: a 2:1 image is an equirectangular panorama unless ``panorama=False`` says otherwise;
  ``panorama=True`` refuses images that are not 2:1.

Every rejected frame is listed in :attr:`FrameSet.rejected` with its reason.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "IMAGE_SUFFIXES",
    "FrameSet",
    "LiftInputError",
    "natural_key",
    "is_equirect_size",
    "sharpness",
    "feature_motion",
    "load_frames",
    "load_image_folder",
    "load_video",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class LiftInputError(ValueError):
    """Bad input to the lifting pipeline; the message names the input and the problem."""


@dataclass
class FrameSet:
    """RGB frames to lift.

    Attributes:
        ids: frame ids (file stems, or ``f000000``... for video), unique and file-name safe.
        images: (H, W, 3) uint8 RGB per frame, all of one size.
        source: the folder or video they came from.
        panorama: True for equirectangular panoramas (W = 2H).
        rejected: ``(id, reason)`` for every frame left out (blur, redundancy, unreadable).
        fps: frames per second sampled from a video (None for a folder).
    """

    ids: list[str]
    images: list[np.ndarray]
    source: Path
    panorama: bool
    rejected: list[tuple[str, str]] = field(default_factory=list)
    fps: float | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the frames."""
        return int(self.images[0].shape[0]), int(self.images[0].shape[1])


def natural_key(name: str) -> list:
    """Sort key that orders digit runs by value: ``img2`` < ``img10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def is_equirect_size(height: int, width: int) -> bool:
    """True for a 2:1 image (within one pixel): the shape of an equirectangular panorama."""
    return abs(width - 2 * height) <= 1


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: low for blurred frames."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def feature_motion(a: np.ndarray, b: np.ndarray, max_corners: int = 300) -> float:
    """Median displacement (pixels) of corners tracked from ``a`` to ``b`` by pyramidal Lucas-Kanade.

    Returns ``inf`` when nothing can be tracked (no corners, or tracking lost): such a pair is never
    called redundant.
    """
    import cv2

    ga = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY)
    gb = cv2.cvtColor(np.ascontiguousarray(b), cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(ga, maxCorners=max_corners, qualityLevel=0.01, minDistance=7)
    if corners is None or len(corners) < 8:
        return float("inf")
    moved, status, _ = cv2.calcOpticalFlowPyrLK(ga, gb, corners, None)
    ok = status.reshape(-1) == 1
    if ok.sum() < 8:
        return float("inf")
    return float(np.median(np.linalg.norm((moved - corners).reshape(-1, 2)[ok], axis=1)))


def _decide_panorama(size: tuple[int, int], panorama: bool | None, source: Path) -> bool:
    h, w = size
    if panorama is None:
        return is_equirect_size(h, w)
    if panorama and not is_equirect_size(h, w):
        raise LiftInputError(f"{source}: --panorama needs 2:1 equirectangular images, the frames are {w}x{h}")
    return bool(panorama)


def _subsample(n: int, max_frames: int | None) -> list[int]:
    """``max_frames`` indices spread evenly over ``range(n)`` (all of them when fewer)."""
    if max_frames is None or n <= max_frames:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, max_frames)})


def load_image_folder(
    folder: Path, *, panorama: bool | None = None, max_frames: int | None = None
) -> FrameSet:
    """Frames from the images in ``folder`` (see the module docstring)."""
    from image2sim.simulator.io.images import read_rgb
    from image2sim.simulator.io.records import CaptureError

    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise LiftInputError(f"{folder}: no images (.png, .jpg, .jpeg) in this folder")
    files.sort(key=lambda p: natural_key(p.stem))
    stems = [p.stem for p in files]
    dupes = sorted({s for s in stems if stems.count(s) > 1})
    if dupes:
        raise LiftInputError(f"{folder}: two images share the frame id(s) {dupes[:5]} (e.g. a.png and a.jpg)")
    bad = [s for s in stems if not re.match(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$", s)]
    if bad:
        raise LiftInputError(
            f"{folder}: file name(s) {bad[:5]} cannot be frame ids (letters, digits, _ . - only)"
        )
    keep = _subsample(len(files), max_frames)
    images, size = [], None
    for i in keep:
        try:
            img = read_rgb(files[i], "image")
        except CaptureError as err:
            raise LiftInputError(str(err)) from None
        if size is None:
            size = img.shape[:2]
        elif img.shape[:2] != size:
            raise LiftInputError(
                f"{files[i]}: image is {img.shape[1]}x{img.shape[0]} but {files[keep[0]].name} is "
                f"{size[1]}x{size[0]} (all frames need one size)"
            )
        images.append(img)
    pano = _decide_panorama(size, panorama, folder)
    skipped = [
        (stems[i], f"left out by --max-frames {max_frames}") for i in range(len(files)) if i not in set(keep)
    ]
    return FrameSet([stems[i] for i in keep], images, folder, pano, rejected=skipped)


def load_video(
    path: Path,
    *,
    fps: float = 2.0,
    max_frames: int | None = None,
    panorama: bool | None = None,
    blur_ratio: float = 0.3,
    blur_window: int = 2,
    min_motion: float = 0.01,
) -> FrameSet:
    """Frames sampled from a video file (see the module docstring)."""
    import cv2

    path = Path(path)
    if fps <= 0:
        raise LiftInputError(f"{path}: --fps must be positive, got {fps}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise LiftInputError(f"{path}: OpenCV cannot open this video")
    try:
        native = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if not np.isfinite(native) or native <= 0:
            native = 30.0
        step = max(1.0, native / fps)
        sampled: list[tuple[int, np.ndarray]] = []
        index, next_take = 0, 0.0
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            if index >= next_take - 1e-9:
                sampled.append((index, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)))
                next_take += step
            index += 1
    finally:
        cap.release()
    if not sampled:
        raise LiftInputError(f"{path}: no frame could be decoded from this video")
    rejected: list[tuple[str, str]] = []
    sharp = np.array([sharpness(img) for _, img in sampled])
    candidates = []
    for k, (frame_index, img) in enumerate(sampled):
        lo, hi = max(0, k - blur_window), min(len(sampled), k + blur_window + 1)
        neighbours = np.concatenate([sharp[lo:k], sharp[k + 1 : hi]])
        if neighbours.size and sharp[k] < blur_ratio * float(np.median(neighbours)):
            rejected.append(
                (
                    f"video frame {frame_index}",
                    f"blurred: Laplacian variance {sharp[k]:.1f} < {blur_ratio} x neighbours' median "
                    f"{float(np.median(neighbours)):.1f}",
                )
            )
            continue
        candidates.append((frame_index, img))
    h, w = candidates[0][1].shape[:2]
    threshold = min_motion * float(np.hypot(h, w))
    kept = [candidates[0]]
    for frame_index, img in candidates[1:]:
        motion = feature_motion(kept[-1][1], img)
        if motion < threshold:
            rejected.append(
                (f"video frame {frame_index}", f"redundant: moved {motion:.2f} px < {threshold:.2f} px")
            )
            continue
        kept.append((frame_index, img))
    keep = _subsample(len(kept), max_frames)
    for i in range(len(kept)):
        if i not in set(keep):
            rejected.append((f"video frame {kept[i][0]}", f"left out by --max-frames {max_frames}"))
    kept = [kept[i] for i in keep]
    pano = _decide_panorama((h, w), panorama, path)
    ids = [f"f{i:06d}" for i in range(len(kept))]
    return FrameSet(ids, [img for _, img in kept], path, pano, rejected=rejected, fps=fps)


def load_frames(
    source: str | Path,
    *,
    panorama: bool | None = None,
    fps: float = 2.0,
    max_frames: int | None = None,
) -> FrameSet:
    """Frames from an image folder or a video file; errors name ``source`` and the problem."""
    source = Path(source)
    if not source.exists():
        raise LiftInputError(f"{source}: no such folder or video file")
    if source.is_dir():
        return load_image_folder(source, panorama=panorama, max_frames=max_frames)
    return load_video(source, fps=fps, max_frames=max_frames, panorama=panorama)
