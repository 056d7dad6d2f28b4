"""Lens distortion (lift.distortion): the models against OpenCV's, their inverses, the Jacobian against
finite differences, image undistortion against an analytic pattern, and structure-from-motion of
procedural houses seen through a barrel lens and a fisheye (issue 24)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from image2sim.simulator.lift.distortion import (
    NEGLIGIBLE_PX,
    PINHOLE_LENS,
    Lens,
    _brown_jacobian,
    distort,
    lens_of_camera,
    max_displacement_px,
    undistort,
    undistort_image,
    undistort_pixels,
)

K = np.array([[160.0, 0.0, 160.0], [0.0, 160.0, 120.0], [0.0, 0.0, 1.0]])

LENSES = [
    Lens((-0.12,)),
    Lens((0.08,)),
    Lens((-0.2, 0.05)),
    Lens((-0.1, 0.02), (0.004, -0.003)),  # OPENCV: tangential terms (a decentred lens)
    Lens((0.0, 0.0), (0.01, 0.0)),
    Lens((), fisheye=True),  # pure equidistant
    Lens((0.02, -0.01, 0.003, -0.0005), fisheye=True),  # OPENCV_FISHEYE
    PINHOLE_LENS,
]


def _grid() -> np.ndarray:
    u, v = np.meshgrid(np.linspace(-1.0, 1.0, 41), np.linspace(-0.75, 0.75, 31))
    return np.stack([u, v], axis=-1)


@pytest.mark.parametrize("lens", LENSES)
def test_undistort_inverts_distort_over_the_whole_frame(lens):
    xy = _grid()
    assert np.abs(undistort(distort(xy, lens), lens) - xy).max() < 1e-9
    uv = xy * 160.0 + K[:2, 2]
    uv_d = distort(xy, lens) * 160.0 + K[:2, 2]
    assert np.abs(undistort_pixels(uv_d, K, lens) - uv).max() < 1e-7


@pytest.mark.parametrize("lens", [lens for lens in LENSES if not lens.fisheye])
def test_brown_model_matches_opencv_projection(lens):
    """COLMAP's OPENCV model is OpenCV's (k1, k2, p1, p2): cv2.projectPoints is the reference."""
    xy = _grid().reshape(-1, 2)
    points = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    k = lens.radial + (0.0,) * (2 - len(lens.radial))
    coeffs = np.array([k[0], k[1], *lens.tangential, 0.0])
    ref, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, coeffs)
    ours = distort(xy, lens) * 160.0 + K[:2, 2]
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-9


@pytest.mark.parametrize("lens", [lens for lens in LENSES if lens.fisheye])
def test_fisheye_model_matches_opencv_fisheye(lens):
    """COLMAP's OPENCV_FISHEYE is OpenCV's fisheye model: cv2.fisheye.distortPoints is the reference."""
    xy = _grid().reshape(-1, 1, 2)
    D = np.array(lens.radial + (0.0,) * (4 - len(lens.radial)), dtype=np.float64)
    ref = cv2.fisheye.distortPoints(xy.astype(np.float64), K, D)
    ours = distort(xy.reshape(-1, 2), lens) * 160.0 + K[:2, 2]
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6


def test_fisheye_angles_and_rays_a_pinhole_camera_cannot_see():
    lens = Lens((), fisheye=True)
    # Equidistant: a ray at 45 degrees (r = 1) lands at radius pi / 4; the centre stays put.
    assert distort(np.array([[1.0, 0.0], [0.0, 0.0]]), lens) == pytest.approx(
        np.array([[np.pi / 4, 0.0], [0, 0]])
    )
    # Rays at 90 degrees or more from the axis have no pinhole image.
    out = undistort(np.array([[np.pi / 2 + 0.1, 0.0], [0.3, 0.4]]), lens)
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()


@pytest.mark.parametrize("lens", [lens for lens in LENSES if not lens.fisheye])
def test_brown_jacobian_matches_finite_differences(lens):
    xy = _grid()[::5, ::5].reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    a, b, c, d = _brown_jacobian(x, y, lens)
    h = 1e-6
    dx = (distort(xy + [h, 0.0], lens) - distort(xy - [h, 0.0], lens)) / (2 * h)
    dy = (distort(xy + [0.0, h], lens) - distort(xy - [0.0, h], lens)) / (2 * h)
    assert np.abs(a - dx[:, 0]).max() < 1e-7 and np.abs(c - dx[:, 1]).max() < 1e-7
    assert np.abs(b - dy[:, 0]).max() < 1e-7 and np.abs(d - dy[:, 1]).max() < 1e-7


def test_the_largest_displacement_is_at_the_border_and_a_tiny_k_is_negligible():
    lens = Lens((-0.12,))
    # Corner (0, 0): normalised (-1, -0.75), r^2 = 1.5625, moved by |k| r^3 f = 0.12 x 1.953 x 160 px.
    assert max_displacement_px(K, lens, 240, 320) == pytest.approx(0.12 * 1.5625**1.5 * 160, rel=1e-9)
    assert max_displacement_px(K, Lens((1e-3,)), 240, 320) < NEGLIGIBLE_PX  # what SfM finds without a lens
    assert max_displacement_px(K, PINHOLE_LENS, 240, 320) == 0.0
    # A tangential term moves the top edge's midpoint (0, -0.75) by p1 (r^2 + 2 y^2) f = p1 x 1.6875 x 160.
    assert max_displacement_px(K, Lens((), (0.01, 0.0)), 240, 320) >= 0.01 * 1.6875 * 160 - 1e-9
    assert max_displacement_px(K, Lens((), fisheye=True), 240, 320) > NEGLIGIBLE_PX  # never negligible


def test_lenses_of_colmap_cameras():
    assert lens_of_camera("SIMPLE_RADIAL", [200, 160, 120, -0.1]) == Lens((-0.1,))
    assert lens_of_camera("RADIAL", [200, 160, 120, -0.1, 0.02]) == Lens((-0.1, 0.02))
    assert lens_of_camera("OPENCV", [200, 210, 160, 120, -0.1, 0.02, 0.001, 0.002]) == Lens(
        (-0.1, 0.02), (0.001, 0.002)
    )
    assert lens_of_camera("SIMPLE_RADIAL_FISHEYE", [200, 160, 120, 0.1]) == Lens((0.1,), fisheye=True)
    assert lens_of_camera("RADIAL_FISHEYE", [200, 160, 120, 0.1, 0.2]) == Lens((0.1, 0.2), fisheye=True)
    assert lens_of_camera("OPENCV_FISHEYE", [200, 210, 160, 120, 0.1, 0.2, 0.3, 0.4]) == Lens(
        (0.1, 0.2, 0.3, 0.4), fisheye=True
    )
    for model, params in (("SIMPLE_PINHOLE", [200, 160, 120]), ("PINHOLE", [200, 210, 160, 120])):
        assert lens_of_camera(model, params).is_pinhole
    with pytest.raises(ValueError, match="FULL_OPENCV"):
        lens_of_camera("FULL_OPENCV", [1] * 12)
    with pytest.raises(ValueError, match="finite"):
        Lens((float("nan"),))
    with pytest.raises(ValueError, match="tangential"):
        Lens((0.1,), (0.01, 0.0), fisheye=True)


def _pattern(xy: np.ndarray) -> np.ndarray:
    """A smooth analytic image of normalised pinhole coordinates (straight stripes stay straight)."""
    return (127.5 + 100 * np.sin(9.0 * xy[..., 0]) * np.cos(7.0 * xy[..., 1])).astype(np.float32)


@pytest.mark.parametrize(
    "lens", [Lens((-0.15,)), Lens((-0.1, 0.02), (0.006, -0.004)), Lens((0.03,), fisheye=True)]
)
def test_an_image_through_a_lens_is_undistorted_to_the_pinhole_view(lens):
    u, v = np.meshgrid(np.arange(320) + 0.5, np.arange(240) + 0.5)
    uv = np.stack([u, v], axis=-1)
    xy_d = (uv - K[:2, 2]) / 160.0
    recorded = undistort(xy_d, lens)  # the pinhole direction each recorded pixel sees
    distorted = np.nan_to_num(_pattern(recorded))[..., None].repeat(3, axis=2)
    pinhole = _pattern(xy_d)  # what a pinhole camera with K records
    out = undistort_image(distorted, K, lens)[..., 0]
    # The undistorted frame's border may see past the recorded image: compare where the source lies
    # inside (bilinear resampling error only).
    src = distort(xy_d, lens) * 160.0 + K[:2, 2]
    inside = (src[..., 0] > 1) & (src[..., 0] < 319) & (src[..., 1] > 1) & (src[..., 1] < 239)
    assert inside.mean() > 0.6
    assert np.abs(out - pinhole)[inside].mean() < 1.5
    assert np.abs(distorted[..., 0] - pinhole)[inside].mean() > 10  # the lens did bend it


def _through_lens(folder, lens: Lens, K_lens: np.ndarray) -> None:
    """Rewrite the 320x240 pinhole PNGs of ``folder`` (camera ``K``) as a camera with intrinsics
    ``K_lens`` and ``lens`` records them."""
    u, v = np.meshgrid(np.arange(320) + 0.5, np.arange(240) + 0.5)
    rays = undistort(
        np.stack([(u - K_lens[0, 2]) / K_lens[0, 0], (v - K_lens[1, 2]) / K_lens[1, 1]], -1), lens
    )
    src = rays * 160.0 + K[:2, 2]
    for path in sorted(folder.glob("*.png")):
        bent = cv2.remap(
            cv2.imread(str(path)),
            (src[..., 0] - 0.5).astype(np.float32),
            (src[..., 1] - 0.5).astype(np.float32),
            cv2.INTER_LINEAR,
        )
        cv2.imwrite(str(path), bent)


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
    _through_lens(folder, Lens((-0.12,)), K)
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


@pytest.mark.slow
def test_sfm_with_a_fisheye_model_recovers_an_equidistant_lens_capture(tmp_path):
    """The same house through an equidistant fisheye (f = 220 px, k1 = 0.02): OPENCV_FISHEYE recovers
    the lens and the poses, and the written views are pinhole frames whose observations agree with
    the points."""
    from image2sim.simulator.lift.frames import load_frames
    from image2sim.simulator.lift.scale import ate, umeyama
    from image2sim.simulator.lift.sfm import SfmOptions, run_sfm

    from tests.simulator.lift_helpers import WALK, gt_poses, rgb_folder, synth_house

    scene = synth_house(tmp_path / "pin", camera="pinhole", views=20, height=240, width=320, config=WALK)
    folder = rgb_folder(scene, tmp_path / "rgb")
    K_fish = np.array([[220.0, 0.0, 160.0], [0.0, 220.0, 120.0], [0.0, 0.0, 1.0]])
    _through_lens(folder, Lens((0.02,), fisheye=True), K_fish)
    frames = load_frames(folder)
    truth = gt_poses(scene)
    result = run_sfm(frames, SfmOptions(camera_model="OPENCV_FISHEYE", num_threads=1))
    est = np.stack([result.frame_pose(f) for f in result.frame_ids])[:, :3, 3]
    true = np.stack([truth[f] for f in result.frame_ids])[:, :3, 3]
    umeyama(est, true)
    assert len(result.frame_ids) >= 16 and result.stats["undistorted"] and result.distortion.fisheye
    assert result.stats["camera"]["params"][0] == pytest.approx(220.0, rel=0.03)
    assert ate(est, true) < 0.02
    view = result.views[0]
    assert np.isfinite(view.uv).all()
    cam = np.linalg.inv(view.cam_to_world)
    p = result.points[view.point_index] @ cam[:3, :3].T + cam[:3, 3]
    uv = p[:, :2] / p[:, 2:] * result.K[0, 0] + result.K[:2, 2]
    assert np.median(np.linalg.norm(uv - view.uv, axis=1)) < 1.0
