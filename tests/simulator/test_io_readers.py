"""Capture readers against ground truth (analytic room rendered in each format's own conventions),
the registry, and every bad-input case of issue 2 item 7."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from image2sim.simulator.conventions import opengl_to_opencv_cam_to_world
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.io import (
    Capture,
    CaptureError,
    available_formats,
    detect_format,
    open_capture,
    register_format,
    write_capture,
)
from image2sim.simulator.io.fusion import backproject_frame
from image2sim.simulator.io.hm3d360 import hm3d_pixel_direction_gl, hm3d_pose_to_cam_to_world
from image2sim.simulator.io.realsee import (
    realsee_index_pixel_direction,
    realsee_pixel_direction,
    realsee_pose_to_cam_to_world,
)
from scipy.spatial.transform import Rotation

from .test_io_room import (
    FACE_COLOURS,
    face_of,
    surface_distance,
    write_hm3d_fixture,
    write_pinhole_fixture,
    write_realsee_fixture,
)


def _surface_errors(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
    """Distances to the room surface and colour-matches-face flags of every valid pixel."""
    dists, matches = [], []
    for frame in capture:
        points, colours = backproject_frame(frame)
        dists.append(surface_distance(points))
        expected = FACE_COLOURS[face_of(points)].astype(int)
        matches.append(np.abs(colours.astype(int) - expected).max(axis=1) < 40)
    return np.concatenate(dists), np.concatenate(matches)


# --- pixel mappings equal ours ----------------------------------------------------------------


def test_hm3d_mapping_equals_ours_exactly() -> None:
    h, w = 16, 32
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    d_cv = hm3d_pixel_direction_gl(u, v, h, w) * np.array([1.0, -1.0, -1.0])  # OpenGL -> OpenCV axes
    ours = EquirectCamera(h, w).pixel_to_ray(torch.from_numpy(u + 0.5), torch.from_numpy(v + 0.5)).numpy()
    np.testing.assert_allclose(d_cv, ours, atol=1e-12)


def test_realsee_mapping_equals_ours_exactly() -> None:
    """Realsee samples sit on pixel centres: its pixel index (u, v) looks where our (u + .5, v + .5)
    does; the index mapping of ``half_pixel="resample"`` is half a pixel off (tests/simulator/
    test_io_realsee.py has the reader-level checks)."""
    h, w = 16, 32
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    theirs = realsee_pixel_direction(u, v, h, w)
    cam = EquirectCamera(h, w)
    at_centre = cam.pixel_to_ray(torch.from_numpy(u + 0.5), torch.from_numpy(v + 0.5)).numpy()
    np.testing.assert_allclose(theirs, at_centre, atol=1e-12)
    index = realsee_index_pixel_direction(u, v, h, w)
    at_index = cam.pixel_to_ray(torch.from_numpy(u * 1.0), torch.from_numpy(v * 1.0)).numpy()
    np.testing.assert_allclose(index, at_index, atol=1e-12)
    assert np.min(np.linalg.norm(index - at_centre, axis=-1)[1:]) > 0.04


@given(
    st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3),
)
def test_hm3d_pose_conversion_matches_scipy(q: list[float], t: list[float]) -> None:
    q_xyzw = np.array(q) / np.linalg.norm(q)
    pose = hm3d_pose_to_cam_to_world(np.array([*t, *q_xyzw]), "p")
    r_gl = Rotation.from_quat(q_xyzw).as_matrix()
    # OpenCV camera axes in the world: x = GL x, y = -GL y (down), z = -GL z (forward).
    np.testing.assert_allclose(pose[:3, :3], r_gl * np.array([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], t)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)


def test_realsee_world_conversion_maps_up_to_up() -> None:
    pose = np.eye(4)
    pose[:3, 3] = [1.0, -2.0, 3.0]  # Y-down: 2 m *above* the origin
    ours = realsee_pose_to_cam_to_world(pose, "p")
    np.testing.assert_allclose(ours[:3, 3], [1.0, 3.0, 2.0])
    # An identity Realsee camera: its down axis (+y, world-down) must point down in ours (-Z), and
    # its forward axis (Realsee world +z) becomes our +Y, since (x, y, z) -> (x, z, -y).
    np.testing.assert_allclose(ours[:3, 1], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(ours[:3, 2], [0.0, 1.0, 0.0])


# --- ground truth through each reader ---------------------------------------------------------


def test_hm3d_reader_ground_truth(tmp_path: Path) -> None:
    cap = open_capture(write_hm3d_fixture(tmp_path / "hm3d"))
    assert cap.format == "hm3d_360" and len(cap) == 3 and cap.camera == EquirectCamera(32, 64)
    frame = cap[1]
    assert frame.rgb.shape == (32, 64, 3) and frame.depth.dtype == np.float32 and frame.frame_id == "00001"
    dist, match = _surface_errors(cap)
    assert dist.max() < 2e-3  # millimetre depth quantisation + 9-decimal poses
    assert match.mean() > 0.97
    np.testing.assert_array_equal(cap.poses[1], frame.cam_to_world)


def test_hm3d_reader_rejects_unconverted_pose(tmp_path: Path) -> None:
    """Negative control: treating the OpenGL pose as OpenCV puts points far off the walls."""
    cap = open_capture(write_hm3d_fixture(tmp_path / "hm3d"))
    frame = cap[0]
    frame.cam_to_world = opengl_to_opencv_cam_to_world(frame.cam_to_world)  # the flip is an involution
    points, _ = backproject_frame(frame)
    assert np.median(surface_distance(points)) > 0.1


@pytest.mark.parametrize("rgb_scale", [1, 2, 2.5, 0.5])
def test_realsee_reader_ground_truth(tmp_path: Path, rgb_scale: float) -> None:
    cap = open_capture(write_realsee_fixture(tmp_path / "rs", rgb_scale=rgb_scale, height=64, width=128))
    assert cap.format == "realsee" and cap.frame_ids == ["vp00", "vp01", "vp02"]
    frame = cap[0]
    assert frame.rgb.shape == (64, 128, 3) and "half_pixel=centres" in frame.notes[0]
    assert ("colour" in frame.notes[0]) == (rgb_scale != 1)
    dist, match = _surface_errors(cap)
    # Depth is used as stored: only the 1/4000 m quantisation (and float32 back-projection) remain.
    assert dist.max() < 2e-4
    assert match.mean() > (0.85 if rgb_scale < 1 else 0.9)  # colour coarser than depth blurs face edges


def test_realsee_resample_reads_index_convention_data(tmp_path: Path) -> None:
    """``half_pixel="resample"`` is right for data written at integer pixel indices, and reading such
    data as centres (the default) is measurably wrong."""
    root = write_realsee_fixture(tmp_path / "rs", height=64, width=128, convention="index")
    cap = open_capture(root, half_pixel="resample")
    assert "half_pixel=resample" in cap[0].notes[0] and "half a pixel" in cap[0].notes[0]
    fixed, match = _surface_errors(cap)
    # Residual: interpolating range between 2.8-degree samples (curvature) and the clamped bottom row.
    assert np.median(fixed) < 0.003 and np.quantile(fixed, 0.95) < 0.02 and match.mean() > 0.9
    raw, _ = _surface_errors(open_capture(root))
    assert np.median(raw) > 5 * np.median(fixed) and np.median(raw) > 0.01


@pytest.mark.parametrize("with_colour_k", [True, False])
def test_pinhole_reader_ground_truth(tmp_path: Path, with_colour_k: bool) -> None:
    root = write_pinhole_fixture(tmp_path / "scan", write_colour_intrinsics=with_colour_k)
    cap = open_capture(root)
    assert cap.format == "pinhole_dir" and cap.frame_ids == ["0", "1", "2"]
    assert cap.camera == PinholeCamera(22.0, 21.0, 15.7, 12.2, 24, 32)  # principal point + 0.5
    frame = cap[0]
    assert frame.rgb.shape == (24, 32, 3) and "resampled to the depth grid" in frame.notes[0]
    dist, match = _surface_errors(cap)
    assert dist.max() < 2e-3
    assert match.mean() > 0.9


def test_pinhole_reader_same_size_needs_no_resampling(tmp_path: Path) -> None:
    root = write_pinhole_fixture(tmp_path / "scan", colour_hw=(24, 32), write_colour_intrinsics=False)
    frame = open_capture(root)[0]
    assert frame.notes == []


def test_pinhole_nonfinite_pose_is_skipped_and_reported(tmp_path: Path) -> None:
    root = write_pinhole_fixture(tmp_path / "scan", n=4)
    (root / "pose" / "2.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4))
    for strict in (True, False):
        cap = open_capture(root, strict=strict)
        assert cap.frame_ids == ["0", "1", "3"]
        assert cap.skipped[0][0] == "2" and "non-finite" in cap.skipped[0][1] and "2.txt" in cap.skipped[0][1]


# --- registry ----------------------------------------------------------------------------------


def test_detection_and_unknown_format(tmp_path: Path) -> None:
    assert detect_format(write_hm3d_fixture(tmp_path / "a", n=1)) == "hm3d_360"
    assert detect_format(write_realsee_fixture(tmp_path / "b", n=1)) == "realsee"
    assert detect_format(write_pinhole_fixture(tmp_path / "c", n=1)) == "pinhole_dir"
    out = write_capture(tmp_path / "d", open_capture(tmp_path / "a"), scene_id="a")
    assert detect_format(out) == "image2sim"
    assert list(available_formats())[:4] == ["image2sim", "hm3d_360", "realsee", "pinhole_dir"]
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hello")
    with pytest.raises(CaptureError, match=r"junk: unknown capture format; known formats: image2sim"):
        open_capture(tmp_path / "junk")
    with pytest.raises(CaptureError, match=r"unknown capture format 'colmap'"):
        open_capture(tmp_path / "a", format="colmap")
    with pytest.raises(CaptureError, match=r"nope: no such file"):
        open_capture(tmp_path / "nope")
    with pytest.raises(CaptureError, match=r"does not accept option"):
        open_capture(tmp_path / "a", half_pixel="ignore")


def test_register_custom_format(tmp_path: Path) -> None:
    base = write_hm3d_fixture(tmp_path / "x", n=1)

    def reader(path, *, strict=True):
        cap = open_capture(path, "hm3d_360", strict=strict)
        cap.format = "custom_test"
        return cap

    register_format("custom_test", reader, lambda p: (Path(p) / "CUSTOM").exists(), "test format")
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_format("custom_test", reader, lambda p: False)
        assert open_capture(base, "custom_test").format == "custom_test"
    finally:
        from image2sim.simulator.io import registry

        registry._FORMATS.pop("custom_test")


# --- bad input: every case names the file and the problem --------------------------------------


def test_hm3d_missing_file(tmp_path: Path) -> None:
    root = write_hm3d_fixture(tmp_path / "h")
    (root / "00001_depth.png").unlink()
    with pytest.raises(CaptureError, match=r"00001_depth.png: missing file"):
        open_capture(root)
    cap = open_capture(root, strict=False)
    assert cap.frame_ids == ["00000", "00002"] and cap.skipped[0][0] == "00001"


@pytest.mark.parametrize(
    "pose_text, match",
    [
        ("0 0 1 0 0 0 2", r"quaternion norm is 2"),
        ("0 0 1 nan 0 0 1", r"quaternion contains non-finite"),
        ("inf 0 1 0 0 0 1", r"translation contains non-finite"),
        ("0 0 1 0 0 1", r"pose file must hold 7 numbers"),
        ("0 0 1 0 0 x 1", r"pose file contains a non-number"),
    ],
)
def test_hm3d_bad_pose(tmp_path: Path, pose_text: str, match: str) -> None:
    root = write_hm3d_fixture(tmp_path / "h", n=2)
    (root / "00001_pose.txt").write_text(pose_text)
    with pytest.raises(CaptureError, match=r"00001_pose.txt: " + match):
        open_capture(root)


def test_hm3d_image_problems(tmp_path: Path) -> None:
    root = write_hm3d_fixture(tmp_path / "h", n=3)
    cap = open_capture(root)
    data = (root / "00000_rgb.png").read_bytes()
    (root / "00000_rgb.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(CaptureError, match=r"00000_rgb.png: colour PNG is truncated"):
        cap[0]
    import cv2

    cv2.imwrite(str(root / "00001_depth.png"), np.full((16, 32), 1000, np.uint16))
    with pytest.raises(
        CaptureError, match=r"00001_rgb.png: rgb/depth size mismatch: rgb is 64x32, depth is 32x16"
    ):
        cap[1]
    cv2.imwrite(str(root / "00002_depth.png"), np.zeros((32, 64), np.uint8))
    with pytest.raises(CaptureError, match=r"00002_depth.png: depth image must be 16-bit"):
        cap[2]
    (root / "00002_rgb.png").write_bytes(b"")
    with pytest.raises(CaptureError, match=r"00002_rgb.png: colour file is empty"):
        cap[2]


def test_hm3d_not_equirect(tmp_path: Path) -> None:
    root = write_hm3d_fixture(tmp_path / "h", n=1, height=32, width=48)
    with pytest.raises(CaptureError, match=r"00000_rgb.png: not an equirectangular panorama: 48x32"):
        open_capture(root)


@pytest.mark.parametrize(
    "matrix, match",
    [
        (np.diag([1.0, 1.0, 1.2, 1.0]), "not orthonormal"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant -1"),
        (np.full((4, 4), np.nan), "non-finite"),
    ],
)
def test_realsee_bad_extrinsics(tmp_path: Path, matrix: np.ndarray, match: str) -> None:
    root = write_realsee_fixture(tmp_path / "r", n=2)
    np.savetxt(root / "viewpoints" / "vp01" / "extrinsics.txt", matrix)
    with pytest.raises(CaptureError, match=r"vp01/extrinsics.txt: .*" + match):
        open_capture(root)
    assert open_capture(root, strict=False).frame_ids == ["vp00"]


def test_realsee_missing_pieces(tmp_path: Path) -> None:
    root = write_realsee_fixture(tmp_path / "r", n=2)
    (root / "viewpoints" / "vp01" / "depth_scale.txt").write_text("0")
    with pytest.raises(CaptureError, match=r"vp01/depth_scale.txt: depth scale must be a positive"):
        open_capture(root)
    (root / "viewpoints" / "vp01" / "panoImage_1600.jpg").unlink()
    with pytest.raises(CaptureError, match=r"vp01/panoImage_1600.jpg: missing file"):
        open_capture(root)
    (root / "viewpoints.txt").write_text("vp00\nvp07\n")
    with pytest.raises(CaptureError, match=r"vp07: missing viewpoint folder"):
        open_capture(root)


def test_realsee_truncated_jpeg(tmp_path: Path) -> None:
    root = write_realsee_fixture(tmp_path / "r", n=1)
    path = root / "viewpoints" / "vp00" / "panoImage_1600.jpg"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(CaptureError, match=r"panoImage_1600.jpg: colour JPEG is truncated"):
        open_capture(root)[0]


def test_pinhole_bad_inputs(tmp_path: Path) -> None:
    root = write_pinhole_fixture(tmp_path / "p", n=3)
    np.savetxt(root / "pose" / "1.txt", np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(CaptureError, match=r"pose/1.txt: rotation is not orthonormal"):
        open_capture(root)
    assert open_capture(root, strict=False).frame_ids == ["0", "2"]
    np.savetxt(root / "pose" / "1.txt", np.eye(4))
    (root / "color" / "2.jpg").unlink()
    with pytest.raises(CaptureError, match=r"color/2.jpg: missing colour file"):
        open_capture(root, strict=True)
    (root / "intrinsic" / "intrinsic_depth.txt").write_text("1 0 0\n0 -1 0\n0 0 1\n")
    with pytest.raises(CaptureError, match=r"intrinsic_depth.txt: focal lengths must be positive"):
        open_capture(root, format="pinhole_dir")


def test_pinhole_aspect_mismatch_without_colour_intrinsics(tmp_path: Path) -> None:
    root = write_pinhole_fixture(tmp_path / "p", n=1, colour_hw=(24, 64), write_colour_intrinsics=False)
    with pytest.raises(
        CaptureError, match=r"color/0.jpg: colour 64x24 and depth 32x24 differ in aspect ratio"
    ):
        open_capture(root)[0]
