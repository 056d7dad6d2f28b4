"""PLY round trips, resampling against slow references, streaming fusion vs one-shot voxel
downsampling, and the real-data proof that hm3d_360 poses and pixel mappings are right."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from image2sim.simulator.conventions import opengl_to_opencv_cam_to_world
from image2sim.simulator.geometry.voxel import voxel_downsample
from image2sim.simulator.io import open_capture, read_ply, write_ply
from image2sim.simulator.io.fusion import VoxelAccumulator, backproject_frame, fuse_frames, select_indices
from image2sim.simulator.io.ply import PlyError
from image2sim.simulator.io.resample import planar_rel_tol, sample_bilinear, sample_depth, sample_rgb
from scipy.spatial import cKDTree

from .test_io_room import surface_distance, write_hm3d_fixture

# --- PLY ------------------------------------------------------------------------------------


def test_ply_round_trip_and_header(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3))
    cols = rng.integers(0, 256, size=(500, 3), dtype=np.uint8)
    nrm = rng.normal(size=(500, 3))
    path = write_ply(tmp_path / "c.ply", pts, cols, nrm, comment="made by a test")
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header")].decode()
    assert header.startswith(
        "ply\nformat binary_little_endian 1.0\ncomment made by a test\nelement vertex 500\n"
    )
    assert "property float x" in header and "property uchar red" in header and "property float nx" in header
    assert len(raw) == len(header) + len("end_header\n") + 500 * (12 + 12 + 3)
    back = read_ply(path)
    np.testing.assert_allclose(back["points"], pts.astype(np.float32))
    np.testing.assert_array_equal(back["colors"], cols)
    np.testing.assert_allclose(back["normals"], nrm.astype(np.float32))
    assert [p.name for p in tmp_path.iterdir()] == ["c.ply"]  # no temp file left


def test_ply_ascii_reader_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "a.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 0\n"
        "property list uchar int vertex_indices\nend_header\n1 2 3 255 0 0\n4 5 6 0 255 0\n"
    )
    back = read_ply(path)
    assert back["points"].tolist() == [[1, 2, 3], [4, 5, 6]] and back["colors"][1].tolist() == [0, 255, 0]
    good = write_ply(tmp_path / "b.ply", np.zeros((10, 3)), np.zeros((10, 3), np.uint8))
    good.write_bytes(good.read_bytes()[:-5])
    with pytest.raises(PlyError, match=r"b.ply: truncated"):
        read_ply(good)
    with pytest.raises(PlyError, match=r"non-finite"):
        write_ply(tmp_path / "n.ply", np.array([[np.nan, 0, 0]]))
    with pytest.raises(PlyError, match=r"uint8"):
        write_ply(tmp_path / "n.ply", np.zeros((1, 3)), np.zeros((1, 3)))
    empty = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8)))
    assert empty["points"].shape == (0, 3)


# --- resampling -----------------------------------------------------------------------------


def _slow_bilinear(img: np.ndarray, u: float, v: float, wrap: bool) -> np.ndarray:
    """Reference: explicit 4-tap loop in continuous coordinates (centres at +0.5)."""
    h, w = img.shape[:2]
    x, y = u - 0.5, v - 0.5
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    out = 0.0
    for dy in (0, 1):
        for dx in (0, 1):
            wx = (x - x0) if dx else (1 - (x - x0))
            wy = (y - y0) if dy else (1 - (y - y0))
            xi = (x0 + dx) % w if wrap else min(max(x0 + dx, 0), w - 1)
            yi = min(max(y0 + dy, 0), h - 1)
            out = out + wx * wy * img[yi, xi].astype(np.float64)
    return out


@given(st.floats(-3.0, 12.0), st.floats(-2.0, 9.0), st.booleans())
def test_bilinear_matches_slow_reference(u: float, v: float, wrap: bool) -> None:
    img = np.arange(7 * 10 * 3, dtype=np.float64).reshape(7, 10, 3) ** 1.3
    fast = sample_bilinear(img, np.array([u]), np.array([v]), wrap_u=wrap)[0]
    np.testing.assert_allclose(fast, _slow_bilinear(img, u, v, wrap), rtol=1e-12, atol=1e-9)


def test_bilinear_exact_at_centres_and_wraps_the_seam() -> None:
    img = np.random.default_rng(0).random((4, 6))
    vv, uu = np.meshgrid(np.arange(4) + 0.5, np.arange(6) + 0.5, indexing="ij")
    np.testing.assert_allclose(sample_bilinear(img, uu, vv), img)
    # Halfway between the last and first column across the seam.
    got = sample_bilinear(img, np.array([6.0]), np.array([1.5]), wrap_u=True)[0]
    assert got == pytest.approx(0.5 * (img[1, 5] + img[1, 0]))


@pytest.mark.parametrize("wrap", [True, False])
def test_fast_rgb_sampling_matches_reference(wrap: bool) -> None:
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, size=(9, 14, 3), dtype=np.uint8)
    u = rng.uniform(-2.0, 16.0, size=(40, 30))
    v = rng.uniform(-1.0, 10.0, size=(40, 30))
    ref = sample_bilinear(img, u, v, wrap_u=wrap)
    fast = sample_rgb(img, u, v, wrap_u=wrap)
    assert fast.shape == (40, 30, 3) and fast.dtype == np.uint8
    assert np.abs(fast.astype(float) - ref).max() <= 4.5  # remap's 1/32-pixel fixed-point weights
    # Half-pixel offsets (the realsee case) are exact.
    uu, vv = np.meshgrid(np.arange(14) + 1.0, np.arange(9) + 1.0)
    half = sample_rgb(img, uu, vv, wrap_u=wrap)
    assert np.abs(half.astype(float) - sample_bilinear(img, uu, vv, wrap_u=wrap)).max() <= 0.5 + 1e-9


def test_depth_sampling_is_edge_aware() -> None:
    depth = np.array([[1.0, 1.0, 5.0, 5.0], [1.0, 1.02, 5.0, 0.0]], np.float32)
    u = np.array([1.0, 2.0, 2.9, 3.0, 3.5])
    v = np.array([1.0, 1.0, 1.0, 1.5, 1.5])
    out = sample_depth(depth, u, v, rel_tol=0.05)
    assert out[0] == pytest.approx(1.005, abs=1e-6)  # smooth: bilinear mean
    assert out[1] == 1.0  # across the 1 m / 5 m edge: nearest valid tap, never ~3 m in mid-air
    assert out[2] == 5.0
    assert out[3] == 5.0  # the invalid (0) tap is ignored, not averaged in
    assert out[4] == 0.0  # exactly on an invalid pixel centre
    assert sample_depth(np.zeros((2, 2), np.float32), np.array([1.0]), np.array([1.0]))[0] == 0.0
    assert planar_rel_tol(2 * np.pi / 1024) == pytest.approx(
        np.tan(np.radians(75)) * np.sqrt(2) * 2 * np.pi / 1024
    )


# --- fusion ---------------------------------------------------------------------------------


def test_accumulator_equals_one_shot_voxel_downsample() -> None:
    rng = np.random.default_rng(3)
    batches = [rng.uniform(-1, 1, size=(2000, 3)) for _ in range(4)]
    colours = [rng.integers(0, 256, size=(2000, 3), dtype=np.uint8) for _ in range(4)]
    acc = VoxelAccumulator(0.1, chunk_points=2500, merge_rows=3000)  # forces chunking and merges
    for p, c in zip(batches, colours, strict=False):
        acc.add(p, c)
    pts, cols = acc.result()
    ref_pts, ref_attrs = voxel_downsample(
        torch.from_numpy(np.concatenate(batches)),
        0.1,
        {"c": torch.from_numpy(np.concatenate(colours).astype(np.float64))},
    )
    assert len(acc) == len(pts) == ref_pts.shape[0] and acc.num_points == 8000
    order = np.lexsort(pts.T[::-1])
    ref_order = np.lexsort(ref_pts.numpy().T[::-1])
    np.testing.assert_allclose(pts[order], ref_pts.numpy()[ref_order], atol=1e-12)
    np.testing.assert_array_equal(cols[order], np.rint(ref_attrs["c"].numpy()[ref_order]).astype(np.uint8))


def test_select_indices() -> None:
    assert select_indices(10, 3) == [0, 3, 6, 9]
    assert select_indices(10, 2, 2) == [0, 2]
    with pytest.raises(ValueError):
        select_indices(10, 0)


def test_fuse_room_lies_on_walls(tmp_path: Path) -> None:
    cap = open_capture(write_hm3d_fixture(tmp_path / "h", n=4))
    points, colours, n_in = fuse_frames(cap, 0.1)
    assert n_in == 4 * 32 * 64 and 0 < len(points) < n_in
    # Voxel means of points on a wall stay on it, except where a voxel straddles a room corner.
    assert np.quantile(surface_distance(points), 0.9) < 0.01
    keys = np.floor(points / 0.1)
    assert len(np.unique(keys, axis=0)) == len(keys)  # one point per voxel


# --- real data: the proof that poses and pixel mappings are right ------------------------------


def _pair_fraction(frame_a, frame_b, n_query: int, rng: np.random.Generator, radius: float = 0.05) -> float:
    query, _ = backproject_frame(frame_a, rng.choice(frame_a.depth.size, size=n_query, replace=False))
    b, _ = backproject_frame(frame_b)
    lo, hi = query.min(0) - radius, query.max(0) + radius
    b = b[np.all((b >= lo) & (b <= hi), axis=1)]  # the tree only needs b's points near a's
    dist, _ = cKDTree(b).query(query, distance_upper_bound=radius)
    return float(np.mean(dist < radius))


def test_hm3d_neighbouring_views_agree(hm3d_scene_dir: Path) -> None:
    cap = open_capture(hm3d_scene_dir)
    assert cap.format == "hm3d_360" and len(cap) >= 10
    pos = cap.poses[:, :3, 3]
    dists = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    np.fill_diagonal(dists, np.inf)
    nearest = dists.argmin(axis=1)
    eligible = [i for i in range(len(cap)) if 0.05 <= dists[i, nearest[i]] <= 0.5]
    chosen = [eligible[k] for k in np.linspace(0, len(eligible) - 1, 5).astype(int)]
    rng = np.random.default_rng(0)
    fractions = []
    for i in chosen:
        fractions.append(_pair_fraction(cap[i], cap[int(nearest[i])], 4000, rng))
    assert np.mean(fractions) >= 0.95, fractions
    assert min(fractions) >= 0.9, fractions  # occlusion differs per pair; none may be far off
    # Negative control: the unconverted (OpenGL-axes) pose breaks the agreement.
    i = chosen[0]
    wrong = cap[i]
    wrong.cam_to_world = opengl_to_opencv_cam_to_world(wrong.cam_to_world)
    assert _pair_fraction(wrong, cap[int(nearest[i])], 2000, rng) < 0.5
