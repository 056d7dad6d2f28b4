"""npz_bytes: readable by np.load, byte-identical across runs, the deflate level applied."""

import io
import zipfile
import zlib

import numpy as np
import pytest
from image2sim.simulator.io.npz import FRAMES_LEVEL, npz_bytes


def _frames(seed: int = 0) -> np.ndarray:
    # Smooth gradients plus noise: compressible, but not trivially (as rendered frames are).
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:48, 0:48]
    base = np.stack([x * 5, y * 5, (x + y) * 2], axis=-1)[None].repeat(6, axis=0)
    return (base + rng.integers(0, 3, base.shape)).clip(0, 255).astype(np.uint8)


def test_round_trip_every_array_and_dtype():
    arrays = {
        "rgb": _frames(),
        "depth": np.linspace(0, 3, 30, dtype=np.float32).reshape(5, 6),
        "ids": np.arange(4),
    }
    for level in (None, 0, 1, 6, 9):
        with np.load(io.BytesIO(npz_bytes(arrays, level)), allow_pickle=False) as z:
            assert sorted(z.files) == sorted(arrays)
            for k, v in arrays.items():
                assert z[k].dtype == v.dtype and np.array_equal(z[k], v)


def test_bytes_do_not_depend_on_time_or_argument_order():
    a, b = _frames(0), _frames(1)
    assert npz_bytes({"a": a, "b": b}, 1) == npz_bytes({"b": b, "a": a}, 1)
    names = zipfile.ZipFile(io.BytesIO(npz_bytes({"b": b, "a": a}))).namelist()
    assert names == ["a.npy", "b.npy"]
    assert all(
        i.date_time == (1980, 1, 1, 0, 0, 0)
        for i in zipfile.ZipFile(io.BytesIO(npz_bytes({"a": a}))).infolist()
    )


def test_level_is_applied():
    f = _frames()
    npy = io.BytesIO()
    np.lib.format.write_array(npy, f, allow_pickle=False)
    for level in (0, 1, 6, 9):
        raw = zlib.compressobj(level, zlib.DEFLATED, -15)
        want = len(raw.compress(npy.getvalue()) + raw.flush())
        info = zipfile.ZipFile(io.BytesIO(npz_bytes({"rgb": f}, level))).infolist()[0]
        assert info.compress_type == zipfile.ZIP_DEFLATED and info.compress_size == want, level
    assert len(npz_bytes({"rgb": f}, 1)) != len(npz_bytes({"rgb": f}, 6))  # the levels differ here
    info = zipfile.ZipFile(io.BytesIO(npz_bytes({"rgb": f}, None))).infolist()[0]
    assert info.compress_type == zipfile.ZIP_STORED
    assert 0 <= FRAMES_LEVEL <= 9


def test_default_level_matches_numpy_compression():
    f = _frames()
    buf = io.BytesIO()
    np.savez_compressed(buf, rgb=f)
    # The same deflate stream as numpy's (level 6); only the zip headers differ (time, zip64).
    ours = zipfile.ZipFile(io.BytesIO(npz_bytes({"rgb": f}))).infolist()[0]
    theirs = zipfile.ZipFile(buf).infolist()[0]
    assert (ours.compress_size, ours.CRC) == (theirs.compress_size, theirs.CRC)


@pytest.mark.parametrize("level", [-1, 10, 3.5, True])
def test_bad_level(level):
    with pytest.raises(ValueError, match="level must be 0-9"):
        npz_bytes({"a": np.zeros(2)}, level)
