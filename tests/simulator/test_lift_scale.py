"""Metric scale, gravity and the Sim(3) scoring helpers of the lifting pipeline (issue 24)."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.conventions import camera_rotation_for_heading
from image2sim.simulator.lift.scale import (
    ScaleError,
    ate,
    camera_up_mean,
    estimate_metric_frame,
    find_floor,
    rotation_errors_deg,
    scale_error,
    umeyama,
)
from scipy.spatial.transform import Rotation


def _random_sim(seed):
    rng = np.random.default_rng(seed)
    return (
        float(rng.uniform(0.2, 5.0)),
        Rotation.random(random_state=seed).as_matrix(),
        rng.normal(size=3) * 3,
    )


def test_umeyama_recovers_a_known_similarity_and_scores_are_zero_on_it():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    s, R, t = _random_sim(1)
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert s2 == pytest.approx(s, rel=1e-10) and np.allclose(R2, R) and np.allclose(t2, t)
    assert ate(src, dst) < 1e-10
    _, R_se3, _ = umeyama(src, src @ R.T + t, with_scale=False)
    assert np.allclose(R_se3, R)
    rots = Rotation.random(5, random_state=2).as_matrix()
    assert np.allclose(rotation_errors_deg(rots, np.einsum("ij,njk->nik", R, rots), R), 0.0, atol=1e-5)
    assert scale_error(dst, dst) < 1e-12
    assert scale_error(1.03 * dst, dst) == pytest.approx(0.03, rel=1e-9)


def test_scores_measure_known_errors():
    rng = np.random.default_rng(3)
    true = rng.normal(size=(50, 3))
    noisy = true + rng.normal(scale=0.01, size=true.shape)
    assert 0.005 < ate(noisy, true) < 0.02
    tilt = Rotation.from_euler("x", 2.0, degrees=True).as_matrix()
    rots = Rotation.random(4, random_state=4).as_matrix()
    assert np.allclose(rotation_errors_deg(np.einsum("ij,njk->nik", tilt, rots), rots), 2.0)
    with pytest.raises(ValueError, match="umeyama needs"):
        umeyama(true[:2], true[:2])


def _room(seed=0, eye=1.45, n_cams=12):
    """A 5 x 4 x 2.6 m room: floor, ceiling and wall points, a table top, level cameras at ``eye``."""
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(0, 5, 150), rng.uniform(0, 4, 150), np.zeros(150)]
    ceiling = np.c_[rng.uniform(0, 5, 300), rng.uniform(0, 4, 300), np.full(300, 2.6)]
    walls = []
    for x in (0.0, 5.0):
        walls.append(np.c_[np.full(800, x), rng.uniform(0, 4, 800), rng.uniform(0, 2.6, 800)])
    for y in (0.0, 4.0):
        walls.append(np.c_[rng.uniform(0, 5, 800), np.full(800, y), rng.uniform(0, 2.6, 800)])
    table = np.c_[rng.uniform(1, 2, 200), rng.uniform(1, 2, 200), np.full(200, 0.75)]
    points = np.concatenate([floor, ceiling, table, *walls])
    points = points + rng.normal(scale=0.003, size=points.shape)
    poses = []
    for _ in range(n_cams):
        T = np.eye(4)
        T[:3, :3] = camera_rotation_for_heading(rng.uniform(-np.pi, np.pi))
        T[:3, 3] = [rng.uniform(1, 4), rng.uniform(1, 3), eye]
        poses.append(T)
    return np.stack(poses), points


def _to_reconstruction(poses, points, sim):
    s, R, t = sim
    out = []
    for T in poses:
        U = np.eye(4)
        U[:3, :3] = R @ T[:3, :3]
        U[:3, 3] = s * R @ T[:3, 3] + t
        out.append(U)
    return np.stack(out), s * points @ R.T + t


def test_camera_height_recovers_scale_gravity_and_the_floor():
    poses, points = _room()
    rec_poses, rec_points = _to_reconstruction(poses, points, _random_sim(5))
    result = estimate_metric_frame(rec_poses, rec_points, camera_height=1.45)
    metric = np.stack([result.transform.apply_pose(T) for T in rec_poses])
    assert result.method == "camera_height"
    assert np.allclose(metric[:, 2, 3], 1.45, atol=0.01)  # floor at z = 0, cameras at their height
    assert scale_error(metric[:, :3, 3], poses[:, :3, 3]) < 0.01
    assert np.degrees(np.arccos(np.clip(-metric[:, 2, 1], -1, 1))).max() < 0.5  # cameras level again
    assert 0 < result.uncertainty < 0.01
    assert np.allclose(metric[0, :2, 3], 0.0) and metric[0, 1, 2] == pytest.approx(0.0, abs=1e-9)
    floor = find_floor(rec_points, rec_poses, camera_up_mean(rec_poses))
    assert floor is not None and len(floor.inliers) >= 140  # the floor, not the table top above it


def test_baseline_scale_and_its_errors():
    poses, points = _room(seed=1)
    rec_poses, rec_points = _to_reconstruction(poses, points, _random_sim(6))
    ids = [f"f{i}" for i in range(len(poses))]
    true = float(np.linalg.norm(poses[0, :3, 3] - poses[3, :3, 3]))
    result = estimate_metric_frame(
        rec_poses, rec_points, frame_ids=ids, baseline=true, baseline_frames=("f0", "f3")
    )
    metric = np.stack([result.transform.apply_pose(T) for T in rec_poses])
    assert result.method == "baseline" and scale_error(metric[:, :3, 3], poses[:, :3, 3]) < 1e-9
    with pytest.raises(ScaleError, match=r"--baseline-frames \['nope'\] not among the registered frames"):
        estimate_metric_frame(
            rec_poses, rec_points, frame_ids=ids, baseline=1.0, baseline_frames=("f0", "nope")
        )
    with pytest.raises(ScaleError, match="not both"):
        estimate_metric_frame(rec_poses, rec_points, camera_height=1.0, baseline=1.0)
    ceiling = rec_points[150:450]  # nothing below the cameras: no floor
    with pytest.raises(ScaleError, match="--camera-height needs the floor"):
        estimate_metric_frame(rec_poses, ceiling, camera_height=1.4)
