"""Procedural captures: viewpoints, noise tiers, fusion consistency, canonical output + gt/,
determinism, CLI."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from image2sim.dataengine.procedural.capture import (
    apply_depth_noise,
    capture_frames,
    jitter_pose,
    make_camera,
    pose_matrix,
    sample_viewpoints,
    write_scene,
)
from image2sim.dataengine.procedural.config import NOISE_TIERS, CaptureConfig, preset
from image2sim.dataengine.procedural.render import render
from image2sim.dataengine.procedural.scene import generate_scene, seed_streams
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.io import open_capture
from typer.testing import CliRunner

TINY = preset("tiny")


def _with_noise(cfg, noise, **capture):
    return dataclasses.replace(cfg, noise=noise, capture=dataclasses.replace(cfg.capture, **capture))


@pytest.fixture(scope="module")
def tiny_scene():
    return generate_scene(TINY, 4)


# --- viewpoints ---------------------------------------------------------------------------------


def test_viewpoints_follow_the_spacing_rule(tiny_scene):
    scene = tiny_scene
    cap = scene.config.capture
    views = sample_viewpoints(scene, 12, np.random.default_rng(0))
    g = scene.grid
    heights = {v.position[2] for v in views}
    assert len(heights) == 1 and cap.eye_height_min <= heights.pop() <= cap.eye_height_max
    xy = np.array([v.position[:2] for v in views])
    iy, ix = g.world_to_cell(xy)
    assert g.navigable[iy, ix].all()
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert (steps <= cap.spacing_max + 1e-9).all()
    assert (steps >= cap.spacing_min - 1e-9).mean() > 0.8
    # A straight free line between consecutive views (sampled every centimetre).
    for a, b in zip(xy[:-1], xy[1:], strict=False):
        s = np.linspace(0, 1, 200)[:, None]
        ly, lx = g.world_to_cell(a + s * (b - a))
        assert g.navigable[ly, lx].all()


# --- noise tiers ---------------------------------------------------------------------------------


def test_noise_tiers_change_what_they_claim(tiny_scene):
    scene = tiny_scene
    camera = EquirectCamera(64, 128)
    view = sample_viewpoints(scene, 1, np.random.default_rng(1))[0]
    pose = pose_matrix(view)
    clean = render(scene, camera, pose)["depth"]
    assert (clean > 0).all()
    rng = np.random.default_rng(0)
    none = apply_depth_noise(clean, camera, NOISE_TIERS["none"], rng)
    assert np.array_equal(none, clean)
    assert np.array_equal(jitter_pose(pose, NOISE_TIERS["none"], rng), pose)

    middle = apply_depth_noise(clean, camera, NOISE_TIERS["middle"], rng)
    invalid = (middle == 0).mean()
    assert 0.0 < invalid < 0.3
    valid = middle > 0
    rel = (middle[valid] - clean[valid]) / clean[valid]
    assert 0.002 < rel.std() < 0.02  # range-proportional noise of ~0.5 % (+ 2 mm absolute)
    jittered = jitter_pose(pose, NOISE_TIERS["middle"], rng)
    assert 0 < np.linalg.norm(jittered[:3, 3] - pose[:3, 3]) < 0.1

    high = apply_depth_noise(clean, camera, NOISE_TIERS["high"], rng)
    assert (high == 0).mean() >= 0.3
    rows_with_depth = np.nonzero((high > 0).any(axis=1))[0]
    assert (rows_with_depth % NOISE_TIERS["high"].lidar_row_step == 0).all()  # scan lines only
    assert (high[high > 0] <= NOISE_TIERS["high"].max_range * 1.1).all()


def test_high_tier_has_fewer_views_and_sparse_depth():
    cfg = _with_noise(TINY, "high", views=4)
    scene = generate_scene(cfg, 2)
    frames, poses = capture_frames(scene)
    assert len(frames) == 2  # view_fraction 0.5
    assert all((f.depth == 0).mean() >= 0.3 for f in frames)
    assert any(not np.allclose(f.cam_to_world, p) for f, p in zip(frames, poses, strict=False))


# --- fusion consistency ------------------------------------------------------------------------


def _surface_distance(points_a: np.ndarray, depth_b: np.ndarray, camera: EquirectCamera, pose_b: np.ndarray):
    """Distance from world points to view B's depth surface (triangles between neighbouring pixels).

    NaN where the point projects onto a non-planar pixel quad of B (crease, step, object edge) or an
    invalid pixel.
    """
    import torch

    h, w = depth_b.shape
    rot, t = pose_b[:3, :3], pose_b[:3, 3]
    pts_b = camera.unproject(torch.from_numpy(depth_b.astype(np.float64))).numpy() @ rot.T + t
    local = (points_a - t) @ rot
    uv, _, _ = camera.project(torch.from_numpy(local))
    u, v = uv[:, 0].numpy() - 0.5, uv[:, 1].numpy() - 0.5
    iu0 = np.floor(u).astype(int)
    iv0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    fu, fv = u - iu0, np.clip(v - iv0, 0, 1)
    iu0 %= w
    iu1 = (iu0 + 1) % w
    iv1 = iv0 + 1
    d = np.stack([depth_b[iv0, iu0], depth_b[iv0, iu1], depth_b[iv1, iu0], depth_b[iv1, iu1]], axis=1)
    p00, p10, p01, p11 = pts_b[iv0, iu0], pts_b[iv0, iu1], pts_b[iv1, iu0], pts_b[iv1, iu1]
    # B's surface is well defined where its pixel quad is planar (no crease, step or edge inside).
    n_q = np.cross(p10 - p00, p01 - p00)
    n_q /= np.maximum(np.linalg.norm(n_q, axis=1, keepdims=True), 1e-12)
    planar = np.abs(((p11 - p00) * n_q).sum(axis=1)) < 2e-3
    ok = (d > 0).all(axis=1) & planar
    lower = (fu + fv) <= 1.0
    a = np.where(lower[:, None], p00, p11)
    b = np.where(lower[:, None], p10, p01)
    c = np.where(lower[:, None], p01, p10)
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    dist = np.abs(((points_a - a) * n).sum(axis=1))
    return np.where(ok, dist, np.nan)


def _fusion_fraction(frame_a, frame_b) -> tuple[float, float]:
    import torch

    cam = frame_a.camera
    valid = frame_a.depth > 0
    local = cam.unproject(torch.from_numpy(frame_a.depth.astype(np.float64))).numpy()[valid]
    pts = local @ frame_a.cam_to_world[:3, :3].T + frame_a.cam_to_world[:3, 3]
    dist = _surface_distance(pts, frame_b.depth, cam, frame_b.cam_to_world)
    # Overlap: within 2.5 cm of a planar part of B's surface. Points occluded in B lie farther than
    # that (the thinnest occluder, a mirror on its wall, stands >= 3 cm proud of the wall).
    overlap = np.isfinite(dist) & (dist < 0.025)
    return float(overlap.mean()), float((dist[overlap] < 0.01).mean())


def test_fusion_consistency_on_clean_captures():
    cfg = _with_noise(TINY, "none", views=4, height=256, width=512)
    scene = generate_scene(cfg, 9)
    frames, _ = capture_frames(scene)
    for a, b in zip(frames[:-1], frames[1:], strict=False):
        overlap, within = _fusion_fraction(a, b)
        assert overlap > 0.5, "consecutive views should overlap"
        assert within >= 0.995, f"only {within:.4f} of overlapping points within 1 cm"
    # The check can fail: a 3 cm pose error breaks it.
    shifted = dataclasses.replace(frames[1], cam_to_world=frames[1].cam_to_world.copy())
    shifted.cam_to_world[:3, 3] += np.array([0.03, -0.02, 0.0])
    _, within = _fusion_fraction(frames[0], shifted)
    assert within < 0.9


# --- output --------------------------------------------------------------------------------------


def _tree_bytes(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_written_scene_reads_back_and_is_byte_identical(tmp_path):
    cfg = _with_noise(TINY, "middle", views=3)
    scene = generate_scene(cfg, 21)
    out = write_scene(scene, tmp_path / "a")
    write_scene(generate_scene(cfg, 21), tmp_path / "b")
    write_scene(generate_scene(cfg, 22), tmp_path / "c")
    a, b, c = (_tree_bytes(tmp_path / k) for k in "abc")
    assert a == b
    assert a.keys() == c.keys() and a != c
    for name in ("navigable.npz", "objects.json", "rooms.json", "mesh.ply", "poses.json", "categories.json"):
        assert f"gt/{name}" in a

    capture = open_capture(out)
    assert len(capture) == 3
    frame = capture[0]
    assert frame.rgb.shape == (64, 128, 3) and frame.semantics is not None and frame.instances is not None
    frames, poses = capture_frames(scene)
    np.testing.assert_array_equal(frame.rgb, frames[0].rgb)
    np.testing.assert_allclose(frame.depth, frames[0].depth, atol=5e-4 + 1e-6)  # millimetre PNG
    np.testing.assert_array_equal(frame.semantics, frames[0].semantics)
    np.testing.assert_allclose(frame.cam_to_world, frames[0].cam_to_world, atol=1e-12)

    grid = np.load(out / "gt" / "navigable.npz")
    np.testing.assert_array_equal(grid["grid"].astype(bool), scene.grid.navigable)
    assert float(grid["resolution"]) == pytest.approx(0.05)
    assert set(np.unique(grid["components"])) == {0, 1}
    objects = json.loads((out / "gt" / "objects.json").read_text())["objects"]
    assert len(objects) == len(scene.objects)
    assert {"id", "category", "room", "center", "box"} <= objects[0].keys()
    rooms = json.loads((out / "gt" / "rooms.json").read_text())["rooms"]
    assert len(rooms) == len(scene.layout.rooms) and len(rooms[0]["polygon"]) == 4
    true = json.loads((out / "gt" / "poses.json").read_text())["poses"]
    np.testing.assert_allclose(np.asarray(true["00000"]), poses[0])


def test_parallel_synthesis_writes_the_same_scenes_as_sequential(tmp_path):
    """Scene i depends only on (config, seed, i): two worker processes write byte-identical folders."""
    from image2sim.dataengine.procedural.capture import synthesize

    cfg = _with_noise(TINY, "middle", views=2)
    one = synthesize(cfg, tmp_path / "one", scenes=2, seed=7, progress=False)
    two = synthesize(cfg, tmp_path / "two", scenes=2, seed=7, progress=False, workers=2)
    assert [p.name for p in one] == [p.name for p in two] == ["scene_000", "scene_001"]
    assert _tree_bytes(tmp_path / "one") == _tree_bytes(tmp_path / "two")
    with pytest.raises(ValueError, match="workers"):
        synthesize(cfg, tmp_path / "bad", scenes=1, seed=7, workers=0)


def test_pinhole_captures_store_z_depth(tmp_path):
    """The camera model's own unproject (z-depth for pinhole) puts every pixel on the box it hit."""
    import torch

    cfg = _with_noise(TINY, "none", camera="pinhole", height=48, width=64, hfov_deg=90.0)
    camera = make_camera(cfg)
    assert isinstance(camera, PinholeCamera) and camera.fx == pytest.approx(32.0) and camera.cx == 32.0
    scene = generate_scene(cfg, 4)
    view = sample_viewpoints(scene, 1, seed_streams(4)["capture"])[0]
    pose = pose_matrix(view)
    out = render(scene, camera, pose)
    assert (out["depth"] > 0).all()
    local = camera.unproject(torch.from_numpy(out["depth"].astype(np.float64))).numpy().reshape(-1, 3)
    world = local @ pose[:3, :3].T + pose[:3, 3]
    box = out["box"].reshape(-1)
    lo, hi = scene.box_lo[box], scene.box_hi[box]
    tol = 1e-4
    assert np.all((world >= lo - tol) & (world <= hi + tol))
    assert np.all(np.any((np.abs(world - lo) < tol) | (np.abs(world - hi) < tol), axis=1))
    # With range instead of z the points would miss their surfaces (off-axis pixels are farther).
    rng_local = local / np.linalg.norm(local, axis=1, keepdims=True) * out["depth"].reshape(-1, 1)
    wrong = rng_local @ pose[:3, :3].T + pose[:3, 3]
    assert not np.all(np.any((np.abs(wrong - lo) < tol) | (np.abs(wrong - hi) < tol), axis=1))
    # A pinhole capture round-trips through the canonical format with its intrinsics.
    written = open_capture(
        write_scene(
            generate_scene(dataclasses.replace(cfg, capture=dataclasses.replace(cfg.capture, views=2)), 4),
            tmp_path / "pin",
        )
    )
    assert written[0].camera == camera and written[0].depth.shape == (48, 64)


def test_cli_synth_writes_scenes_and_rejects_bad_options(tmp_path):
    from image2sim.dataengine.cli import app

    runner = CliRunner()
    result = runner.invoke(
        app,
        [
            "synth",
            "--preset",
            "tiny",
            "--scenes",
            "2",
            "--views",
            "2",
            "--noise",
            "none",
            "--seed",
            "0",
            "--out",
            str(tmp_path / "syn"),
        ],
    )
    assert result.exit_code == 0, result.output
    for i in range(2):
        scene_dir = tmp_path / "syn" / f"scene_{i:03d}"
        assert (scene_dir / "manifest.json").is_file() and (scene_dir / "gt" / "mesh.ply").is_file()
        assert len(open_capture(scene_dir)) == 2
    a = (tmp_path / "syn" / "scene_000" / "frames" / "00000_rgb.png").read_bytes()
    b = (tmp_path / "syn" / "scene_001" / "frames" / "00000_rgb.png").read_bytes()
    assert a != b  # scenes of one run are different
    bad = runner.invoke(app, ["synth", "--preset", "tiny", "--noise", "loud", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "noise tier" in bad.output
    assert not (tmp_path / "x").exists()
    again = runner.invoke(
        app, ["synth", "--preset", "tiny", "--scenes", "1", "--views", "2", "--out", str(tmp_path / "syn")]
    )
    assert again.exit_code != 0  # existing output is not overwritten without --overwrite


def test_capture_config_views_are_independent_of_the_layout():
    a = generate_scene(_with_noise(TINY, "none", views=2), 5)
    b = generate_scene(dataclasses.replace(TINY, capture=CaptureConfig(views=7, height=64, width=128)), 5)
    np.testing.assert_array_equal(a.box_lo, b.box_lo)


def _bfs_reference(nav: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Plain queue-based breadth-first search (the readable reference)."""
    from collections import deque

    dist = np.full(nav.shape, np.inf)
    dist[start] = 0
    queue = deque([start])
    while queue:
        r, c = queue.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < nav.shape[0] and 0 <= cc < nav.shape[1] and nav[rr, cc] and dist[rr, cc] == np.inf:
                dist[rr, cc] = dist[r, c] + 1
                queue.append((rr, cc))
    return dist


def test_geodesic_distance_matches_breadth_first_search():
    from image2sim.dataengine.procedural.capture import geodesic_distance

    rng = np.random.default_rng(0)
    nav = rng.random((30, 40)) < 0.7
    nav[5, 7] = True
    np.testing.assert_array_equal(geodesic_distance(nav, (5, 7)), _bfs_reference(nav, (5, 7)))
    assert np.isinf(geodesic_distance(nav & False, (5, 7))).all()  # start not navigable


def test_captures_tour_several_rooms():
    from image2sim.dataengine.procedural.config import LayoutConfig

    cfg = dataclasses.replace(
        TINY,
        layout=LayoutConfig(rooms_min=4, rooms_max=4, room_size_min=2.6, room_size_max=3.6),
        capture=dataclasses.replace(TINY.capture, views=16),
    )
    scene = generate_scene(cfg, 3)
    views = sample_viewpoints(scene, 16, np.random.default_rng(0))
    rooms = scene.layout.room_at(np.array([v.position[:2] for v in views]))
    assert len(set(rooms.tolist())) >= 3
    steps = np.linalg.norm(np.diff([v.position[:2] for v in views], axis=0), axis=1)
    assert (steps <= cfg.capture.spacing_max + 1e-9).all()


def test_inspect_and_fuse_read_synthetic_scenes_without_special_cases(tmp_path):
    from image2sim.dataengine.cli import app

    runner = CliRunner()
    cfg_file = tmp_path / "synth.json"
    cfg_file.write_text(json.dumps({"capture": {"views": 3, "height": 32, "width": 64}, "noise": "middle"}))
    made = runner.invoke(
        app,
        [
            "synth",
            "--preset",
            "tiny",
            "--config",
            str(cfg_file),
            "--scenes",
            "1",
            "--out",
            str(tmp_path / "syn"),
        ],
    )
    assert made.exit_code == 0, made.output
    scene_dir = tmp_path / "syn" / "scene_000"
    manifest = json.loads((scene_dir / "manifest.json").read_text())
    assert manifest["metadata"]["noise"] == "middle" and manifest["num_frames"] == 3
    inspected = runner.invoke(app, ["inspect", str(scene_dir)])
    assert inspected.exit_code == 0, inspected.output
    fused = runner.invoke(app, ["fuse", str(scene_dir), "--out", str(tmp_path / "cloud.ply")])
    assert fused.exit_code == 0, fused.output
    assert (tmp_path / "cloud.ply").stat().st_size > 1000
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"capture": {"viewz": 3}}))
    rejected = runner.invoke(
        app, ["synth", "--preset", "tiny", "--config", str(bad), "--out", str(tmp_path / "y")]
    )
    assert rejected.exit_code == 2 and "viewz" in rejected.output


def test_walking_camera_bounds_the_turn_between_views_and_leaves_positions_alone(tiny_scene):
    walk = generate_scene(_with_noise(TINY, "none", yaw_step_max_deg=20.0), 4)
    free = sample_viewpoints(tiny_scene, 12, np.random.default_rng(0))
    views = sample_viewpoints(walk, 12, np.random.default_rng(0))
    assert [v.position for v in views] == [v.position for v in free]
    yaw = np.array([v.yaw for v in views])
    turn = np.abs((np.diff(yaw) + np.pi) % (2 * np.pi) - np.pi)
    assert turn.max() <= np.radians(20.0) + 1e-9
    assert np.all((yaw >= -np.pi) & (yaw < np.pi))


def test_surface_detail_adds_fine_grain_and_zero_changes_nothing():
    cfg = _with_noise(TINY, "none", camera="pinhole", height=48, width=64)
    scene = generate_scene(cfg, 4)
    grainy = generate_scene(dataclasses.replace(cfg, surface_detail=0.3), 4)
    pose = pose_matrix(sample_viewpoints(scene, 1, np.random.default_rng(1))[0])
    cam = make_camera(cfg)
    plain, detail = render(scene, cam, pose), render(grainy, cam, pose)
    assert np.array_equal(plain["depth"], detail["depth"])
    diff = detail["rgb"].astype(float) - plain["rgb"].astype(float)
    assert 2.0 < np.abs(diff).mean() < 40.0
    with pytest.raises(Exception, match="surface_detail"):
        dataclasses.replace(cfg, surface_detail=1.5).validate()
