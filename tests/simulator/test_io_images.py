"""Image headers are checked before decoding: declared sizes, parity with the decoder, bombs refused."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from image2sim.simulator.io.images import (
    MAX_IMAGE_PIXELS,
    header_size,
    image_size,
    read_rgb,
    read_uint16,
)
from image2sim.simulator.io.records import CaptureError


def _png_declaring(width: int, height: int) -> bytes:
    """A tiny, valid-looking 16-bit greyscale PNG whose header declares ``width x height``: one
    compressed row of zeros, enough for a decoder to start allocating the declared size."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    raw = zlib.compress(b"\x00" * (1 + 2 * min(width, 4096)))

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")


@pytest.mark.parametrize("ext,shape", [(".png", (37, 53, 3)), (".jpg", (41, 29, 3)), (".png", (16, 24))])
def test_header_size_matches_the_decoder(ext, shape):
    rng = np.random.default_rng(0)
    dtype = np.uint16 if len(shape) == 2 else np.uint8
    img = rng.integers(0, 255, size=shape).astype(dtype)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    data = buf.tobytes()
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert header_size(data) == decoded.shape[:2]


def test_a_decompression_bomb_is_refused_from_its_header(tmp_path):
    bomb = tmp_path / "depth.png"
    bomb.write_bytes(_png_declaring(32768, 16384))
    assert bomb.stat().st_size < 100_000 and 32768 * 16384 > MAX_IMAGE_PIXELS
    for read in (read_uint16, read_rgb, image_size):
        with pytest.raises(CaptureError, match=r"depth.png.*32768 x 16384.*refused before decoding"):
            read(bomb)


def test_a_header_declaring_no_pixels_is_refused(tmp_path):
    p = tmp_path / "rgb.png"
    p.write_bytes(_png_declaring(0, 10))
    with pytest.raises(CaptureError, match="declares 0 x 10"):
        read_rgb(p)


def test_unknown_formats_have_no_header_size():
    assert header_size(b"GIF89a....") is None and header_size(b"") is None
    assert header_size(b"\xff\xd8\x00\x00") is None  # a JPEG start without a frame header


@pytest.mark.parametrize("value,why", [(0, "no valid pixel"), (65535, "saturated")])
def test_degenerate_depth_is_refused(tmp_path, value, why):
    from image2sim.simulator.io.images import read_depth_uint16, write_uint16_png

    p = tmp_path / "depth.png"
    write_uint16_png(p, np.full((8, 16), value, dtype=np.uint16))
    with pytest.raises(CaptureError, match=f"depth.png.*{why}"):
        read_depth_uint16(p)
    ok = np.full((8, 16), value, dtype=np.uint16)
    ok[3, 4] = 1000
    write_uint16_png(p, ok)
    np.testing.assert_array_equal(read_depth_uint16(p), ok)  # one valid pixel is a (poor) depth map
