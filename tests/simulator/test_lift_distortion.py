"""Radial lens distortion (lift.distortion): the model's inverse, image undistortion against an analytic
pattern, and structure-from-motion of a procedural house seen through a barrel lens (issue 24)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from image2sim.simulator.lift.distortion import (
    NEGLIGIBLE_PX,
    distort,
    max_displacement_px,
    radial_coefficients,
    undistort,
    undistort_image,
    undistort_pixels,
)

K = np.array([[160.0, 0.0, 160.0], [0.0, 160.0, 120.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("k", [(-0.12, 0.0), (0.08, 0.0), (-0.2, 0.05), (0.0, 0.0)])
def test_undistort_inverts_distort_over_the_whole_frame(k):
    u, v = np.meshgrid(np.linspace(-1.0, 1.0, 41), np.linspace(-0.75, 0.75, 31))
    xy = np.stack([u, v], axis=-1)
    assert np.abs(undistort(distort(xy, k), k) - xy).max() < 1e-9
    uv = xy * 160.0 + K[:2, 2]
    uv_d = distort(xy, k) * 160.0 + K[:2, 2]
    assert np.abs(undistort_pixels(uv_d, K, k) - uv).max() < 1e-7


def test_the_largest_displacement_is_at_the_corners_and_a_tiny_k_is_negligible():
    k = (-0.12, 0.0)
    # Corner (0, 0): normalised (-1, -0.75), r^2 = 1.5625, moved by |k| r^3 f = 0.12 x 1.953 x 160 px.
    assert max_displacement_px(K, k, 240, 320) == pytest.approx(0.12 * 1.5625**1.5 * 160, rel=1e-9)
    assert max_displacement_px(K, (1e-3, 0.0), 240, 320) < NEGLIGIBLE_PX  # what SfM finds without a lens
    assert max_displacement_px(K, (0.0, 0.0), 240, 320) == 0.0


def test_radial_coefficients_of_colmap_cameras():
    assert radial_coefficients("SIMPLE_RADIAL", [200, 160, 120, -0.1]) == (-0.1, 0.0)
    assert radial_coefficients("RADIAL", [200, 160, 120, -0.1, 0.02]) == (-0.1, 0.02)
    assert radial_coefficients("SIMPLE_PINHOLE", [200, 160, 120]) == (0.0, 0.0)
    with pytest.raises(ValueError, match="OPENCV"):
        radial_coefficients("OPENCV", [1, 1, 1, 1, 0, 0, 0, 0])


def _pattern(xy: np.ndarray) -> np.ndarray:
    """A smooth analytic image of normalised pinhole coordinates (straight stripes stay straight)."""
    return (127.5 + 100 * np.sin(9.0 * xy[..., 0]) * np.cos(7.0 * xy[..., 1])).astype(np.float32)


def test_an_image_through_a_barrel_lens_is_undistorted_to_the_pinhole_view():
    k = (-0.15, 0.0)
    u, v = np.meshgrid(np.arange(320) + 0.5, np.arange(240) + 0.5)
    uv = np.stack([u, v], axis=-1)
    xy_d = (uv - K[:2, 2]) / 160.0
    distorted = _pattern(undistort(xy_d, k))[..., None].repeat(3, axis=2)  # what the lens records
    pinhole = _pattern(xy_d)  # what a pinhole camera with K records
    out = undistort_image(distorted, K, k)[..., 0]
    # Barrel distortion pulls the border inwards, so the undistorted frame's corners see past the
    # recorded image: compare where the source lies inside (bilinear resampling error only).
    src = distort(xy_d, k) * 160.0 + K[:2, 2]
    inside = (src[..., 0] > 1) & (src[..., 0] < 319) & (src[..., 1] > 1) & (src[..., 1] < 239)
    assert inside.mean() > 0.9
    assert np.abs(out - pinhole)[inside].mean() < 1.5
    assert np.abs(distorted[..., 0] - pinhole)[inside].mean() > 15  # the lens did bend it


@pytest.mark.slow
def test_sfm_with_a_radial_model_recovers_a_barrel_lens_capture(tmp_path):
    """A procedural house photographed through a barrel lens (k = -0.12): SIMPLE_RADIAL recovers the
    coefficient and the poses; the pinhole model's poses are worse on the same images."""
    from image2sim.simulator.lift.frames import load_frames
    from image2sim.simulator.lift.scale import ate, umeyama
    from image2sim.simulator.lift.sfm import SfmOptions, run_sfm

    from tests.simulator.lift_helpers import WALK, gt_poses, rgb_folder, synth_house

    scene = synth_house(tmp_path / "pin", camera="pinhole", views=20, height=240, width=320, config=WALK)
    folder = rgb_folder(scene, tmp_path / "rgb")
    k = (-0.12, 0.0)
    u, v = np.meshgrid(np.arange(320) + 0.5, np.arange(240) + 0.5)
    src = undistort(np.stack([(u - 160.0) / 160.0, (v - 120.0) / 160.0], axis=-1), k) * 160.0 + K[:2, 2]
    for path in sorted(folder.glob("*.png")):
        img = cv2.imread(str(path))
        bent = cv2.remap(
            img,
            (src[..., 0] - 0.5).astype(np.float32),
            (src[..., 1] - 0.5).astype(np.float32),
            cv2.INTER_LINEAR,
        )
        cv2.imwrite(str(path), bent)
    frames = load_frames(folder)
    truth = gt_poses(scene)
    errors = {}
    for model in ("SIMPLE_RADIAL", "SIMPLE_PINHOLE"):
        result = run_sfm(frames, SfmOptions(camera_model=model, num_threads=1))
        est = np.stack([result.frame_pose(f) for f in result.frame_ids])[:, :3, 3]
        true = np.stack([truth[f] for f in result.frame_ids])[:, :3, 3]
        umeyama(est, true)
        errors[model] = (ate(est, true), len(result.frame_ids), result)
    err, n, radial = errors["SIMPLE_RADIAL"]
    assert radial.stats["undistorted"] and n >= 18
    assert radial.stats["camera"]["params"][3] == pytest.approx(-0.12, abs=0.02)
    assert err < 0.02
    assert errors["SIMPLE_PINHOLE"][0] > 1.5 * err
    # The views are the undistorted frames, and the observations moved with them.
    view = radial.views[0]
    cam = np.linalg.inv(view.cam_to_world)
    p = radial.points[view.point_index] @ cam[:3, :3].T + cam[:3, 3]
    uv = p[:, :2] / p[:, 2:] * radial.K[0, 0] + radial.K[:2, 2]
    assert np.median(np.linalg.norm(uv - view.uv, axis=1)) < 1.0
