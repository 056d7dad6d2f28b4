"""Image file I/O for capture readers/writers, with errors that name the file and the problem.

OpenCV decodes silently-partial images (a truncated JPEG comes back with a grey bottom and only a
warning on stderr), so before decoding we check that the file ends with its format's end marker
(PNG ``IEND`` chunk, JPEG ``EOI``). Colour arrays are RGB (OpenCV's BGR is swapped here, once).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from image2sim.simulator.io.records import CaptureError

__all__ = [
    "read_depth_uint16",
    "read_rgb",
    "read_uint16",
    "write_rgb_png",
    "write_uint16_png",
    "image_size",
    "probe_first_size",
]

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
_JPEG_MAGIC = b"\xff\xd8"
_JPEG_END = b"\xff\xd9"
MAX_IMAGE_PIXELS = 100_000_000
"""Images declaring more pixels are refused from their header, before anything is decoded (a 1 MB PNG
may declare 32768 x 16384 pixels: 3.5 GB and 13 s to decode). 100 MP covers 12K x 6K panoramas."""
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _read_bytes(path: Path, what: str) -> bytes:
    """Raw file content; a missing or empty file is a :class:`CaptureError`."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing {what} file")
    data = path.read_bytes()
    if not data:
        raise CaptureError(f"{path}: {what} file is empty")
    return data


def _check_complete(path: Path, data: bytes, what: str) -> None:
    """Reject files whose format end marker is missing (truncated downloads/copies)."""
    if data.startswith(_PNG_MAGIC):
        if not data.rstrip(b"\x00").endswith(_PNG_END):
            raise CaptureError(f"{path}: {what} PNG is truncated (no IEND chunk at the end)")
    elif data.startswith(_JPEG_MAGIC):
        # Some writers pad after EOI; tolerate trailing zero bytes only.
        if not data.rstrip(b"\x00").endswith(_JPEG_END):
            raise CaptureError(f"{path}: {what} JPEG is truncated (no end-of-image marker)")


def header_size(data: bytes) -> tuple[int, int] | None:
    """(height, width) declared by a PNG (IHDR) or JPEG (start-of-frame) header, without decoding;
    None for other formats or a header that cannot be parsed."""
    if data.startswith(_PNG_MAGIC) and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[20:24], "big"), int.from_bytes(data[16:20], "big")
    if data.startswith(_JPEG_MAGIC):
        i = 2
        while i + 9 <= len(data):
            if data[i] != 0xFF:
                return None
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in _SOF_MARKERS:
                return int.from_bytes(data[i + 5 : i + 7], "big"), int.from_bytes(data[i + 7 : i + 9], "big")
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
                i += 2
                continue
            i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    return None


def _check_dimensions(path: Path, data: bytes, what: str) -> None:
    size = header_size(data)
    if size is None:
        return
    h, w = size
    if h < 1 or w < 1:
        raise CaptureError(f"{path}: {what} image header declares {w} x {h} pixels")
    if h * w > MAX_IMAGE_PIXELS:
        raise CaptureError(
            f"{path}: {what} image declares {w} x {h} pixels ({h * w / 1e6:.0f} MP), above the "
            f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP limit; refused before decoding"
        )


def _decode(path: Path, what: str, flags: int) -> np.ndarray:
    data = _read_bytes(path, what)
    _check_complete(path, data, what)
    _check_dimensions(path, data, what)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if image is None or image.size == 0:
        raise CaptureError(f"{path}: cannot decode {what} image (unreadable or corrupt file)")
    return image


def read_rgb(path: Path, what: str = "colour") -> np.ndarray:
    """Read an 8-bit colour (or greyscale, expanded) image as (H, W, 3) uint8 RGB."""
    image = _decode(path, what, cv2.IMREAD_UNCHANGED)
    if image.dtype != np.uint8:
        raise CaptureError(f"{path}: {what} image must be 8-bit, got {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise CaptureError(f"{path}: {what} image has unsupported shape {image.shape}")
    return np.ascontiguousarray(image[:, :, 2::-1])  # BGR(A) -> RGB, alpha dropped


def _read_single(path: Path, what: str, dtype: type) -> np.ndarray:
    image = _decode(path, what, cv2.IMREAD_UNCHANGED)
    if image.ndim != 2:
        raise CaptureError(f"{path}: {what} image must be single-channel, got shape {image.shape}")
    if image.dtype != dtype:
        bits = 8 * np.dtype(dtype).itemsize
        raise CaptureError(
            f"{path}: {what} image must be {bits}-bit ({np.dtype(dtype).name}), got {image.dtype}"
        )
    return image


def read_uint16(path: Path, what: str = "depth") -> np.ndarray:
    """Read a single-channel 16-bit PNG as (H, W) uint16."""
    return _read_single(path, what, np.uint16)


def read_uint8(path: Path, what: str = "confidence") -> np.ndarray:
    """Read a single-channel 8-bit PNG as (H, W) uint8."""
    return _read_single(path, what, np.uint8)


def read_depth_uint16(path: Path) -> np.ndarray:
    """A 16-bit depth PNG as (H, W) uint16, refusing degenerate frames: every pixel 0 (no valid depth
    at all) or every pixel 65535 (saturated, or not a depth image). Either would be ingested as an
    empty or a wall-everywhere frame and build a scene silently without it."""
    raw = read_uint16(path, "depth")
    if not raw.any():
        raise CaptureError(f"{path}: depth image has no valid pixel (every value is 0)")
    if (raw == np.iinfo(np.uint16).max).all():
        raise CaptureError(f"{path}: depth image is saturated (every value is 65535): not a depth map")
    return raw


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """(height, width) of an image file; PNGs are answered from the header, others decoded."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: missing {what} file")
    with path.open("rb") as fh:
        head = fh.read(65536)  # PNG IHDR is at byte 16; a JPEG's frame header follows its EXIF/tables
    size = header_size(head)
    if size is not None:
        _check_dimensions(path, head, what)
        return size
    image = _decode(path, what, cv2.IMREAD_UNCHANGED)
    return int(image.shape[0]), int(image.shape[1])


def probe_first_size(
    ids: list[str], path_of, what: str, strict: bool, skipped: list[tuple[str, str]]
) -> tuple[list[str], tuple[int, int]]:
    """Size of the first readable image among ``ids`` (``path_of(id) -> Path``).

    Strict: the first frame's problem raises. Otherwise unreadable leading frames move to
    ``skipped`` and the remaining ids are returned with the size.
    """
    for k, fid in enumerate(ids):
        try:
            return ids[k:], image_size(path_of(fid), what)
        except CaptureError as err:
            if strict:
                raise
            skipped.append((fid, str(err)))
    first = path_of(ids[0]) if ids else Path(".")
    reason = skipped[-1][1] if skipped else "no frames"
    raise CaptureError(
        f"{first.parent}: no readable {what} image among {len(ids)} frames (last problem: {reason})"
    )


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) uint8 RGB as PNG."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise CaptureError(f"{path}: rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1])):
        raise CaptureError(f"{path}: OpenCV could not write the PNG")


def _write_single(path: Path, image: np.ndarray, dtype: type) -> None:
    image = np.asarray(image)
    if image.dtype != dtype or image.ndim != 2:
        raise CaptureError(f"{path}: expected (H, W) {np.dtype(dtype).name}, got {image.shape} {image.dtype}")
    if not cv2.imwrite(str(path), image):
        raise CaptureError(f"{path}: OpenCV could not write the PNG")


def write_uint16_png(path: Path, image: np.ndarray) -> None:
    """Write (H, W) uint16 as a 16-bit greyscale PNG."""
    _write_single(path, image, np.uint16)


def write_uint8_png(path: Path, image: np.ndarray) -> None:
    """Write (H, W) uint8 as an 8-bit greyscale PNG."""
    _write_single(path, image, np.uint8)
