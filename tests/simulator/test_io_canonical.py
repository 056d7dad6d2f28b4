"""Canonical capture format: round trips, atomic writes, and every bad-input case of the reader."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.io import CaptureError, Frame, read_canonical, write_capture
from image2sim.simulator.io.canonical import CONVENTIONS, FORMAT_NAME, encode_depth_mm
from scipy.spatial.transform import Rotation


def _frames(n: int = 3, camera=None, semantics: bool = False, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    camera = camera or EquirectCamera(8, 16)
    out = []
    for i in range(n):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=seed + i).as_matrix()
        pose[:3, 3] = rng.normal(size=3)
        depth = rng.uniform(0.3, 9.0, size=(camera.height, camera.width)).astype(np.float32)
        depth[0, 0] = 0.0  # an invalid pixel survives the round trip as 0
        out.append(
            Frame(
                rgb=rng.integers(0, 256, size=(camera.height, camera.width, 3), dtype=np.uint8),
                depth=depth,
                camera=camera,
                cam_to_world=pose,
                semantics=rng.integers(0, 40, size=depth.shape).astype(np.int32) if semantics else None,
                instances=rng.integers(0, 300, size=depth.shape).astype(np.int32) if semantics else None,
                frame_id=f"{i:05d}",
                notes=["a note"] if i == 1 else [],
            )
        )
    return out


@pytest.mark.parametrize("camera", [EquirectCamera(8, 16), PinholeCamera(10.0, 11.0, 6.5, 4.0, 9, 12)])
def test_round_trip(tmp_path: Path, camera) -> None:
    frames = _frames(3, camera, semantics=True)
    out = write_capture(tmp_path / "cap", frames, scene_id="scene-a", metadata={"source": "test"})
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["format"] == FORMAT_NAME and manifest["version"] == 1
    assert manifest["frame_ids"] == ["00000", "00001", "00002"] and manifest["num_frames"] == 3
    assert manifest["conventions"] == CONVENTIONS and manifest["has_semantics"] is True
    assert manifest["camera"] == camera.to_dict() and manifest["metadata"] == {"source": "test"}
    cap = read_canonical(out)
    assert len(cap) == 3 and cap.scene_id == "scene-a" and cap.camera == camera
    for src, got in zip(frames, cap, strict=False):
        np.testing.assert_array_equal(got.rgb, src.rgb)
        np.testing.assert_allclose(got.depth, src.depth, atol=0.5e-3 + 1e-6)
        assert got.depth[0, 0] == 0.0
        np.testing.assert_array_equal(got.cam_to_world, src.cam_to_world)
        np.testing.assert_array_equal(got.semantics, src.semantics)
        np.testing.assert_array_equal(got.instances, src.instances)
        assert got.notes == src.notes
    np.testing.assert_array_equal(cap.poses[2], frames[2].cam_to_world)


def test_default_ids_and_no_semantics(tmp_path: Path) -> None:
    frames = _frames(2)
    for f in frames:
        f.frame_id = ""
    out = write_capture(tmp_path / "c", iter(frames), scene_id="s")  # a generator is fine
    assert not (out / "semantics").exists()
    cap = read_canonical(out)
    assert cap.frame_ids == ["00000", "00001"] and cap[0].semantics is None


def test_extra_runs_inside_tmp_and_lands_atomically(tmp_path: Path) -> None:
    seen = []

    def extra(tmp: Path) -> None:
        seen.append(tmp)
        assert (tmp / "manifest.json").is_file() and tmp != tmp_path / "cap"
        (tmp / "gt").mkdir()
        (tmp / "gt" / "x.txt").write_text("hi")

    out = write_capture(tmp_path / "cap", _frames(1), scene_id="s", extra=extra)
    assert (out / "gt" / "x.txt").read_text() == "hi" and not seen[0].exists()


def test_failure_leaves_nothing(tmp_path: Path) -> None:
    def boom(tmp: Path) -> None:
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_capture(tmp_path / "cap", _frames(2), scene_id="s", extra=boom)
    assert list(tmp_path.iterdir()) == []
    bad = _frames(3)
    bad[2].depth[1, 1] = np.nan
    with pytest.raises(CaptureError, match=r"frame 2 .*non-finite"):
        write_capture(tmp_path / "cap", bad, scene_id="s")
    assert list(tmp_path.iterdir()) == []


def test_overwrite(tmp_path: Path) -> None:
    out = write_capture(tmp_path / "cap", _frames(2), scene_id="first")
    with pytest.raises(FileExistsError):
        write_capture(out, _frames(1), scene_id="second")
    assert read_canonical(out).scene_id == "first"
    write_capture(out, _frames(1), scene_id="second", overwrite=True)
    cap = read_canonical(out)
    assert cap.scene_id == "second" and len(cap) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda fs: setattr(fs[1], "camera", EquirectCamera(4, 8)), "differs from the first frame"),
        (lambda fs: fs[0].depth.__setitem__((2, 2), 70.0), "exceeds the uint16"),
        (lambda fs: fs[0].depth.__setitem__((2, 2), -1.0), "negative"),
        (lambda fs: fs[1].cam_to_world.__setitem__((0, 0), 3.0), "not orthonormal"),
        (lambda fs: fs[1].cam_to_world.__setitem__((1, 3), np.inf), "non-finite"),
        (lambda fs: setattr(fs[1], "rgb", fs[1].rgb[:4]), "size mismatch"),
        (lambda fs: setattr(fs[1], "frame_id", "a/b"), "not a safe file name"),
        (lambda fs: setattr(fs[1], "frame_id", fs[0].frame_id), "duplicate"),
        (lambda fs: setattr(fs[1], "semantics", np.zeros((8, 16), np.int32)), "some frames have semantics"),
        (lambda fs: fs.clear(), "no frames"),
    ],
)
def test_writer_rejects_bad_frames(tmp_path: Path, mutate, match: str) -> None:
    frames = _frames(3)
    mutate(frames)
    with pytest.raises(CaptureError, match=match):
        write_capture(tmp_path / "cap", frames, scene_id="s")
    assert list(tmp_path.iterdir()) == []


def test_encode_depth_rounds_to_millimetres() -> None:
    mm = encode_depth_mm(np.array([[0.0, 1.0004, 1.0006, 65.535]], np.float32), "t")
    assert mm.tolist() == [[0, 1000, 1001, 65535]]
    with pytest.raises(CaptureError, match="below 0.5 mm"):
        encode_depth_mm(np.array([[1e-4]], np.float32), "t")


# --- reader bad input -----------------------------------------------------------------------


@pytest.fixture()
def written(tmp_path: Path) -> Path:
    return write_capture(tmp_path / "cap", _frames(3), scene_id="s")


def _edit_manifest(root: Path, **changes) -> None:
    m = json.loads((root / "manifest.json").read_text())
    m.update(changes)
    (root / "manifest.json").write_text(json.dumps(m))


def test_reader_manifest_errors(written: Path) -> None:
    _edit_manifest(written, version=2)
    with pytest.raises(CaptureError, match=r"manifest.json: unsupported version 2"):
        read_canonical(written)
    _edit_manifest(written, version=1, num_frames=5)
    with pytest.raises(CaptureError, match=r"manifest.json: num_frames = 5"):
        read_canonical(written)
    _edit_manifest(written, num_frames=3, metadata=[1])
    with pytest.raises(CaptureError, match=r"field 'metadata' must be a JSON object"):
        read_canonical(written)
    _edit_manifest(written, metadata={}, has_semantics="yes")
    with pytest.raises(CaptureError, match=r"field 'has_semantics' must be true or false"):
        read_canonical(written)
    _edit_manifest(written, has_semantics=False, format="other")
    with pytest.raises(CaptureError, match=r"field 'format' is 'other'"):
        read_canonical(written)
    _edit_manifest(written, format="image2sim-capture", frame_ids=["00000", "00000", "00002"])
    with pytest.raises(CaptureError, match=r"field 'frame_ids' has duplicates"):
        read_canonical(written)
    _edit_manifest(written, frame_ids=["00000", "00001", "00002"], camera={"model": "fisheye"})
    with pytest.raises(CaptureError, match=r"field 'camera'.*unknown camera model"):
        read_canonical(written)
    (written / "manifest.json").write_text("{not json")
    with pytest.raises(CaptureError, match=r"manifest.json: not valid JSON"):
        read_canonical(written)
    (written / "manifest.json").unlink()
    with pytest.raises(CaptureError, match=r"manifest.json: missing manifest"):
        read_canonical(written)


def test_reader_pose_errors_and_skip(written: Path) -> None:
    pose_file = written / "frames" / "00001_pose.json"
    bad = np.eye(4)
    bad[:3, :3] *= 1.1
    pose_file.write_text(json.dumps({"cam_to_world": bad.tolist()}))
    with pytest.raises(CaptureError, match=r"00001_pose.json: rotation is not orthonormal"):
        read_canonical(written)
    cap = read_canonical(written, strict=False)
    assert cap.frame_ids == ["00000", "00002"] and cap.skipped[0][0] == "00001"
    pose_file.unlink()
    with pytest.raises(CaptureError, match=r"00001_pose.json: missing pose file"):
        read_canonical(written)


def test_reader_image_errors(written: Path) -> None:
    cap = read_canonical(written)
    rgb = written / "frames" / "00000_rgb.png"
    rgb.write_bytes(rgb.read_bytes()[:-30])
    with pytest.raises(CaptureError, match=r"00000_rgb.png: colour PNG is truncated"):
        cap[0]
    (written / "frames" / "00001_depth.png").unlink()
    with pytest.raises(CaptureError, match=r"00001_depth.png: missing depth file"):
        cap[1]
    (written / "frames" / "00002_rgb.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbageIEND\xaeB`\x82")
    with pytest.raises(CaptureError, match=r"00002_rgb.png: cannot decode"):
        cap[2]


def test_depth_confidence_round_trips_and_is_optional(tmp_path: Path) -> None:
    frames = _frames(2, camera=PinholeCamera(10.0, 10.0, 8.0, 4.0, 8, 16))
    conf = np.linspace(0.0, 1.0, 8 * 16, dtype=np.float32).reshape(8, 16)
    frames[0].confidence = conf
    out = write_capture(tmp_path / "cap", frames, scene_id="c")
    assert (out / "frames" / "00000_confidence.png").is_file()
    assert not (out / "frames" / "00001_confidence.png").exists()
    cap = read_canonical(out)
    back = cap[0].confidence
    assert back is not None and back.dtype == np.float32 and back.shape == (8, 16)
    assert np.max(np.abs(back - conf)) <= 0.5 / 255 + 1e-6
    assert cap[1].confidence is None  # absent: None (older captures read as before)
    for bad, match in ((conf * 2.0, "lie in \\[0, 1\\]"), (conf[:4], "confidence is 16x4")):
        frames[0].confidence = bad
        with pytest.raises(CaptureError, match=match):
            write_capture(tmp_path / "bad", frames, scene_id="c")
        assert not (tmp_path / "bad").exists()
    frames[0].confidence = conf
    (out / "frames" / "00000_confidence.png").write_bytes((out / "frames" / "00000_rgb.png").read_bytes())
    with pytest.raises(CaptureError, match="00000_confidence.png: confidence image must be single-channel"):
        read_canonical(out)[0]
