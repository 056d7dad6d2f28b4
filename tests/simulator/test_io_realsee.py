"""RealSee3D pixel convention: the reader's default (``half_pixel="centres"``) against the analytic box
room rendered with the format's centre mapping, across views, at the seam and at the poles.

On a real RealSee3D scene (kept outside the repository) reading at pixel centres makes the nearest
views agree to 0.08 mm (median) and the old half-pixel resample to 4.6 mm; the same gap shows here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io import CaptureError, Frame, open_capture
from image2sim.simulator.io.realsee import HALF_PIXEL_MODES, realsee_pixel_direction
from scipy.spatial.transform import Rotation

from .test_io_room import (
    realsee_directions,
    surface_distance,
    write_realsee_fixture,
)

H, W = 64, 128
QUANT = 0.5 / 4000 + 1e-6  # half a step of the fixture's depth quantisation (depth_scale 4000)


def _two_views(root: Path, **kwargs) -> Path:
    """Two viewpoints 0.6 m apart, tilted differently (so latitude errors show too)."""
    views = [
        (np.array([0.2, 0.3, 1.3]), Rotation.from_euler("xyz", [5, 20, -3], degrees=True).as_matrix()),
        (np.array([0.7, 0.0, 1.6]), Rotation.from_euler("xyz", [-4, 70, 6], degrees=True).as_matrix()),
    ]
    return write_realsee_fixture(root, height=H, width=W, viewpoints=views, **kwargs)


def _points(frame: Frame) -> np.ndarray:
    """World points (H, W, 3) float64 of a frame's range map (0 where invalid)."""
    rays = frame.camera.ray_map(torch.float64).permute(1, 2, 0).numpy()
    cam = rays * frame.depth.astype(np.float64)[..., None]
    pose = np.asarray(frame.cam_to_world, dtype=np.float64)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def _cross_view_gaps(a: Frame, b: Frame) -> np.ndarray:
    """Distance of each valid point of view ``a`` to the surface view ``b`` sees there: the plane
    through b's 2x2 pixel neighbours around its projection (quads straddling a room corner, where the
    four points are not coplanar to 5 mm, are left out). Point-to-local-plane, so no interpolation
    of range (and no curvature error) enters."""
    pa = _points(a)[a.depth > 0]
    pb, valid_b = _points(b), b.depth > 0
    pose = np.asarray(b.cam_to_world, dtype=np.float64)
    cam = torch.from_numpy((pa - pose[:3, 3]) @ pose[:3, :3])
    uv, _, ok = b.camera.project(cam)
    u, v = uv[:, 0].numpy() - 0.5, uv[:, 1].numpy() - 0.5
    i0, j0 = np.floor(v).astype(int), np.floor(u).astype(int)
    inside = ok.numpy() & (i0 >= 0) & (i0 + 1 < b.height)
    i0, j0, pa = i0[inside], j0[inside], pa[inside]
    i1, j1 = i0 + 1, (j0 + 1) % b.width
    j0 %= b.width
    q00, q01, q10, q11 = pb[i0, j0], pb[i0, j1], pb[i1, j0], pb[i1, j1]
    all_valid = valid_b[i0, j0] & valid_b[i0, j1] & valid_b[i1, j0] & valid_b[i1, j1]
    n = np.cross(q01 - q00, q10 - q00)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    planar = np.abs(np.sum((q11 - q00) * n, axis=1)) < 5e-3
    keep = all_valid & planar
    return np.abs(np.sum((pa[keep] - q00[keep]) * n[keep], axis=1))


def test_default_reads_centres_and_views_agree_where_resample_does_not(tmp_path: Path) -> None:
    root = _two_views(tmp_path / "rs")
    centres = open_capture(root)
    resample = open_capture(root, half_pixel="resample")
    a, b = centres[0], centres[1]
    # Matches the analytic room: only the 1/4000 m depth quantisation (<= 0.125 mm) is left.
    for frame in (a, b):
        assert surface_distance(_points(frame)[frame.depth > 0]).max() < QUANT
    gaps = np.concatenate([_cross_view_gaps(a, b), _cross_view_gaps(b, a)])
    assert len(gaps) > 0.5 * 2 * H * W
    assert np.median(gaps) < 1e-4 and np.quantile(gaps, 0.99) < 5e-4  # sub-millimetre everywhere
    ra, rb = resample[0], resample[1]
    gaps_r = np.concatenate([_cross_view_gaps(ra, rb), _cross_view_gaps(rb, ra)])
    surf_r = surface_distance(_points(ra)[ra.depth > 0])
    # The half-pixel resample rotates each panorama by half a pixel: millimetres, not micrometres.
    assert np.median(gaps_r) > 20 * np.median(gaps) and np.median(gaps_r) > 1e-3
    assert np.median(surf_r) > 1e-3
    assert np.mean(gaps_r < 0.01) < np.mean(gaps < 0.01)


def test_seam_and_poles_read_exactly(tmp_path: Path) -> None:
    # The format's first/last columns straddle the seam symmetrically, its first/last rows the poles.
    d = realsee_pixel_direction(np.array([0, W - 1, 0, 0]), np.array([H // 2, H // 2, 0, H - 1]), H, W)
    lon = np.arctan2(d[:, 0], d[:, 2])
    np.testing.assert_allclose(lon[:2], [-np.pi + np.pi / W, np.pi - np.pi / W], atol=1e-12)
    np.testing.assert_allclose(d[2:, 1], [-np.cos(np.pi / (2 * H)), np.cos(np.pi / (2 * H))], atol=1e-12)
    np.testing.assert_allclose(realsee_directions(H, W), realsee_pixel_direction(*_grid(), H, W), atol=1e-12)

    root = _two_views(tmp_path / "rs")
    frame = open_capture(root)[0]
    pts, valid = _points(frame), frame.depth > 0
    border = {
        "seam u=0": (slice(None), 0),
        "seam u=W-1": (slice(None), W - 1),
        "top pole row": (0, slice(None)),
        "bottom pole row": (H - 1, slice(None)),
    }
    for name, idx in border.items():
        dist = surface_distance(pts[idx][valid[idx]])
        assert len(dist) == len(pts[idx]) and dist.max() < QUANT, (name, dist.max())
    # The resample is half a pixel off at the seam too (at the bottom row its clamp happens to read
    # the right sample, so the poles do not separate the two modes).
    old = open_capture(root, half_pixel="resample")[0]
    pts_old = _points(old)
    for name in ("seam u=0", "seam u=W-1"):
        idx = border[name]
        assert np.median(surface_distance(pts_old[idx][old.depth[idx] > 0])) > 5e-4, name
    # Across the seam, neighbouring columns see neighbouring surface points (no gap, no overlap).
    frame = open_capture(root)[0]
    pts = _points(frame)
    step_in = np.linalg.norm(pts[H // 2, 1] - pts[H // 2, 0])
    step_seam = np.linalg.norm(pts[H // 2, 0] - pts[H // 2, W - 1])
    assert step_seam == pytest.approx(step_in, rel=0.2)


def _grid() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    return u, v


@pytest.mark.parametrize("scale", [2, 2.5, 0.5])
def test_colour_resize_keeps_pixel_centres(tmp_path: Path, scale: float) -> None:
    """Colour of another size is brought onto the depth grid without a shift: a smooth colour
    pattern of direction, written at the colour's own centres, reads back as the pattern at our
    depth-grid centres (0.4-0.9 grey levels off; after a half-colour-pixel shift 1.7-11)."""
    h, w = 32, 64
    root = write_realsee_fixture(tmp_path / "rs", n=1, height=h, width=w)

    def pattern(dirs: np.ndarray) -> np.ndarray:
        lon = np.arctan2(dirs[..., 0], dirs[..., 2])
        lat = np.arcsin(np.clip(dirs[..., 1], -1, 1))
        return np.stack([128 + 100 * np.sin(lon), 128 + 100 * np.cos(lon), 128 + 100 * np.sin(2 * lat)], -1)

    ch, cw = int(round(h * scale)), int(round(w * scale))
    colour = np.clip(np.rint(pattern(realsee_directions(ch, cw))), 0, 255).astype(np.uint8)
    path = root / "viewpoints" / "vp00" / "panoImage_1600.jpg"
    jpeg = [
        cv2.IMWRITE_JPEG_QUALITY,
        100,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
    ]
    assert cv2.imwrite(str(path), colour[:, :, ::-1], jpeg)  # no chroma subsampling: ~0.4 grey levels
    frame = open_capture(root)[0]
    assert frame.rgb.shape == (h, w, 3) and f"from {cw}x{ch} to {w}x{h}" in frame.notes[0]
    want = pattern(EquirectCamera(h, w).ray_map(torch.float64).permute(1, 2, 0).numpy())
    err = np.abs(frame.rgb.astype(float) - want)
    assert err.mean() < 1.0, err.mean()  # upsampling clamps at the poles: ~10 levels on the pole rows
    # The check sees a half-colour-pixel shift (what the index convention would introduce).
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    off = 0.5 * w / cw
    cam = EquirectCamera(h, w)
    shifted = pattern(cam.pixel_to_ray(torch.from_numpy(u - off), torch.from_numpy(v - off)).numpy())
    assert np.abs(frame.rgb.astype(float) - shifted).mean() > 2 * err.mean()


def test_half_pixel_option_values(tmp_path: Path) -> None:
    root = write_realsee_fixture(tmp_path / "rs", n=1)
    assert HALF_PIXEL_MODES == ("centres", "resample")
    default = open_capture(root)[0]
    for old_name in ("ignore", "centers"):  # "ignore" (earlier name) and the US spelling read the same
        frame = open_capture(root, half_pixel=old_name)[0]
        np.testing.assert_array_equal(frame.depth, default.depth)
        np.testing.assert_array_equal(frame.rgb, default.rgb)
    with pytest.raises(CaptureError, match=r"half_pixel='shift': expected 'centres' .* or 'resample'"):
        open_capture(root, half_pixel="shift")
