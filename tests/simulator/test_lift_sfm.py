"""Structure-from-motion of RGB-only procedural houses against their exact poses (issue 24)."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.lift.frames import load_frames
from image2sim.simulator.lift.scale import ate, rotation_errors_deg, umeyama
from image2sim.simulator.lift.sfm import SfmError, SfmOptions, run_sfm

from tests.simulator.lift_helpers import PANO_WALK, WALK, gt_poses, rgb_folder, synth_house


@pytest.fixture(scope="module")
def pinhole_house(tmp_path_factory):
    return synth_house(
        tmp_path_factory.mktemp("pin"), camera="pinhole", views=24, height=240, width=320, config=WALK
    )


def _scores(result, truth):
    est = np.stack([result.frame_pose(f) for f in result.frame_ids])
    true = np.stack([truth[f] for f in result.frame_ids])
    s, R, t = umeyama(est[:, :3, 3], true[:, :3, 3])
    return (
        ate(est[:, :3, 3], true[:, :3, 3]),
        rotation_errors_deg(est[:, :3, :3], true[:, :3, :3], R).max(),
        s,
    )


def test_pinhole_house_poses_and_intrinsics_match_the_truth(pinhole_house, tmp_path):
    frames = load_frames(rgb_folder(pinhole_house, tmp_path / "rgb"))
    assert not frames.panorama and len(frames) == 24
    result = run_sfm(frames)
    assert result.frame_ids == frames.ids and result.dropped == []
    err, rot, _ = _scores(result, gt_poses(pinhole_house))
    # The default pinhole model: nothing to undistort; pairs with general geometry were matched.
    assert result.stats["camera"]["model"] == "SIMPLE_PINHOLE" and not result.stats["undistorted"]
    assert result.stats["rotation_pair_share"] < 0.95 and sum(result.stats["pair_geometry"].values()) > 20
    # Measured 2.6 mm and 0.27 degrees (2026-11-26); the targets are 5 cm and 1 degree.
    assert err < 0.02 and rot < 0.6
    f_true = 0.5 * 320 / np.tan(np.radians(45.0))
    assert abs(result.K[0, 0] / f_true - 1) < 0.01
    assert np.allclose(result.K[:2, 2], [160.0, 120.0])
    # Every view's sparse depth agrees with its pose: the points lie in front at the observed pixels.
    view = result.views[0]
    sparse = view.sparse_depth(result.points)
    assert len(sparse.depth) > 50 and (sparse.depth > 0).all()
    cam = np.linalg.inv(view.cam_to_world)
    p = result.points[view.point_index] @ cam[:3, :3].T + cam[:3, 3]
    uv = p[:, :2] / p[:, 2:] * result.K[0, 0] + result.K[:2, 2]
    assert np.median(np.linalg.norm(uv - sparse.uv, axis=1)) < 1.0


@pytest.mark.slow
def test_an_unordered_folder_beyond_the_exhaustive_cap_is_paired_by_retrieval(pinhole_house, tmp_path):
    """Frames renamed into a shuffled order, more than ``exhaustive_max``: auto picks retrieval (not
    the sequential matcher, which needs file order), matches far fewer pairs than exhaustive and
    still reconstructs the walk."""
    import shutil

    src = rgb_folder(pinhole_house, tmp_path / "rgb")
    shuffled = tmp_path / "shuffled"
    shuffled.mkdir()
    order = np.random.default_rng(5).permutation(24)
    for new, old in enumerate(order):
        shutil.copy(src / f"{old:05d}.png", shuffled / f"img_{new:02d}.png")
    frames = load_frames(shuffled)
    # 8 neighbours: with 5, one CI machine registered 18 frames (its SIFT features differ in the
    # last bits); this machine registered all 24 at 5 and 8 neighbours, seeds 0-3 (2026-11-27).
    result = run_sfm(frames, SfmOptions(exhaustive_max=10, retrieval_neighbours=8, vocabulary=128))
    assert result.stats["matcher"] == "retrieval"
    assert 24 * 8 / 2 <= result.stats["retrieval_pairs"] <= 24 * 8 < 24 * 23 / 2
    assert len(result.frame_ids) >= 20
    truth = {f"img_{new:02d}": gt_poses(pinhole_house)[f"{old:05d}"] for new, old in enumerate(order)}
    err, rot, _ = _scores(result, truth)
    assert err < 0.02 and rot < 0.6


@pytest.mark.parametrize("mapper", ["incremental", pytest.param("global", marks=pytest.mark.slow)])
def test_panorama_house_is_reconstructed_as_a_rig_of_cube_faces(tmp_path, mapper):
    scene = synth_house(
        tmp_path / "pano", camera="equirect", views=10, height=256, width=512, config=PANO_WALK
    )
    frames = load_frames(rgb_folder(scene, tmp_path / "rgb"))
    assert frames.panorama
    result = run_sfm(frames, SfmOptions(mapper=mapper))
    assert result.stats["mapper"] == mapper
    assert len(result.frame_ids) == 10 and len(result.views) == 60
    err, rot, _ = _scores(result, gt_poses(scene))
    # Measured 1.3 mm and 0.13 degrees on 12 panoramas (2026-11-26).
    assert err < 0.02 and rot < 0.6
    assert result.stats["rig_centre_spread_max"] < 1e-6
    assert result.stats["rig_rotation_residual_deg_max"] < 1e-3


@pytest.mark.slow  # the pinhole house test above keeps the fast SfM check
def test_unregistrable_frame_is_dropped_and_named(pinhole_house, tmp_path):
    """A noise image among the frames is dropped and named; the real frames stay one reconstruction.
    The noise is an extra frame: replacing a frame of the walk instead cut the sequence in two
    whenever its neighbours happened not to match each other (seen once in CI: 4 of 9 registered)."""
    folder = rgb_folder(pinhole_house, tmp_path / "rgb", ids=[f"{i:05d}" for i in range(10)])
    rng = np.random.default_rng(0)
    import cv2

    cv2.imwrite(str(folder / "00010.png"), rng.integers(0, 256, size=(240, 320, 3), dtype=np.uint8))
    result = run_sfm(load_frames(folder))
    assert "00010" not in result.frame_ids and len(result.frame_ids) >= 9
    assert [d for d, _ in result.dropped] == ["00010"]


def test_too_few_frames_and_unrelated_images_are_clear_errors(pinhole_house, tmp_path):
    two = rgb_folder(pinhole_house, tmp_path / "two", ids=["00000", "00001"])
    with pytest.raises(SfmError, match=r"two: too few frames for structure-from-motion: 2"):
        run_sfm(load_frames(two))
    noise = tmp_path / "noise"
    noise.mkdir()
    import cv2

    rng = np.random.default_rng(1)
    for i in range(4):
        cv2.imwrite(str(noise / f"n{i}.png"), rng.integers(0, 256, size=(120, 160, 3), dtype=np.uint8))
    with pytest.raises(
        SfmError, match=r"noise: (structure-from-motion found no reconstruction|too few registered)"
    ):
        run_sfm(load_frames(noise))


@pytest.mark.slow
def test_a_camera_that_only_rotates_is_refused(tmp_path):
    still = {
        "surface_detail": 0.3,
        "capture": {"spacing_min": 0.0, "spacing_max": 0.01, "yaw_step_max_deg": 20.0},
    }
    scene = synth_house(tmp_path / "rot", camera="pinhole", views=8, height=240, width=320, config=still)
    centres = np.stack([p[:3, 3] for p in gt_poses(scene).values()])
    assert np.ptp(centres, axis=0).max() == 0.0  # one position, eight headings
    # One thread: COLMAP's multi-threaded verification and mapping are not reproducible run to run.
    # Under load, a 2-thread run once registered this capture with a spurious baseline (a rare false
    # negative of the check, recorded in docs/lift.md); this test pins the reproducible path.
    # With a radial lens model the capture reconstructs with a spurious small spread (0.049, wrong focal
    # and k); every verified pair being rotation-like refuses it all the same.
    frames = load_frames(rgb_folder(scene, tmp_path / "rot" / "rgb"))
    for model in ("SIMPLE_RADIAL", "SIMPLE_PINHOLE"):
        with pytest.raises(SfmError, match=r"rot/rgb: the cameras barely move .* only rotates"):
            run_sfm(frames, SfmOptions(num_threads=1, camera_model=model))
