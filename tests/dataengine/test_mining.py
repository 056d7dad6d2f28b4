"""Object mining: 2D filters, 3D grounding, merging, pinhole views, gt detector on a procedural scene."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from image2sim.dataengine.mining import (
    Detection,
    GTDetector,
    MiningConfig,
    SceneObject,
    View,
    YoloWorldDetector,
    attach_gt_metadata,
    filter_detections,
    ground_detection,
    load_categories,
    load_objects,
    merge_objects,
    mine_capture,
    pinhole_views,
    save_objects,
)


def _flat_view(range_value: float, size: int = 64) -> View:
    """A view looking along +X from (1, 2, 1.5) with fan-shaped unit rays and a constant range."""
    u = (np.arange(size) + 0.5) / size - 0.5
    yy, xx = np.meshgrid(u, u, indexing="ij")
    rays = np.stack([np.ones_like(xx), -xx, -yy], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return View(
        np.zeros((size, size, 3), np.uint8),
        np.full((size, size), range_value),
        rays,
        np.array([1.0, 2.0, 1.5]),
    )


def test_grounding_is_exact_on_a_known_view():
    view = _flat_view(4.0)
    det = Detection((20.0, 30.0, 40.0, 50.0), "chair", 0.9)
    p = ground_detection(view, det, MiningConfig())
    ray = view.rays_world[40, 30]
    np.testing.assert_allclose(p, view.origin + 4.0 * ray, atol=1e-12)


def test_grounding_uses_the_median_of_the_central_patch():
    view = _flat_view(3.0)
    view.range_map[38:43, 28:33] = 2.0  # the central patch sees a nearer surface
    view.range_map[0:20, :] = 50.0  # outside the patch: ignored
    view.range_map[40, 30] = 0.0  # invalid pixels are skipped
    p = ground_detection(
        view, Detection((20.0, 30.0, 40.0, 50.0), "chair", 0.9), MiningConfig(patch_fraction=0.3)
    )
    assert np.linalg.norm(p - view.origin) == pytest.approx(2.0)


def test_grounding_rejects_far_and_invalid():
    det = Detection((20.0, 30.0, 40.0, 50.0), "chair", 0.9)
    assert ground_detection(_flat_view(10.5), det, MiningConfig()) is None
    assert ground_detection(_flat_view(9.9), det, MiningConfig()) is not None
    assert ground_detection(_flat_view(0.0), det, MiningConfig()) is None
    nan = _flat_view(np.nan)
    assert ground_detection(nan, det, MiningConfig()) is None


def test_2d_filters_use_paper_thresholds():
    dets = [
        Detection((0, 0, 20, 15), "a", 0.08),
        Detection((0, 0, 20, 14.9), "b", 0.5),
        Detection((0, 0, 100, 100), "c", 0.0799),
        Detection((5, 5, 0, 0), "d", 1.0),
    ]
    assert [d.category for d in filter_detections(dets, MiningConfig())] == ["a"]


def test_merge_same_category_within_radius():
    pts = [
        ("chair", np.array([0.0, 0, 0]), 0.5, {}),
        ("chair", np.array([0.4, 0, 0]), 0.9, {}),
        ("sofa", np.array([0.1, 0, 0]), 0.7, {}),
        ("chair", np.array([2.0, 0, 0]), 0.3, {}),
        ("chair", np.array([0.2, 0.3, 0]), 0.2, {}),
    ]
    objs = merge_objects(pts, 0.5)
    assert [(o.category, o.sightings) for o in objs] == [("chair", 3), ("sofa", 1), ("chair", 1)]
    np.testing.assert_allclose(objs[0].position, [0.2, 0.1, 0.0])
    assert objs[0].confidence == 0.9
    assert merge_objects([], 0.5) == []
    # Drift: a and b start 0.6 apart; c joins b and pulls its mean within 0.5 of a -> one object.
    drift = [
        ("cup", np.array([0.0, 0, 0]), 1.0, {}),
        ("cup", np.array([0.6, 0, 0]), 1.0, {}),
        ("cup", np.array([0.35, 0, 0]), 1.0, {}),
    ]
    objs = merge_objects(drift, 0.5)
    assert len(objs) == 1 and objs[0].sightings == 3
    np.testing.assert_allclose(objs[0].position, [0.95 / 3, 0, 0])


def test_objects_file_round_trip_and_errors(tmp_path):
    objs = [SceneObject(1, "cup", [1.0, 2.0, 0.5], 3, 0.8, 7, True, "kitchen", 12)]
    path = save_objects(tmp_path / "objects.json", objs, {"detector": "gt"})
    assert load_objects(path) == objs
    (tmp_path / "bad.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="format"):
        load_objects(tmp_path / "bad.json")


def test_yolo_world_needs_local_weights(tmp_path):
    with pytest.raises(FileNotFoundError, match="no download"):
        YoloWorldDetector(tmp_path / "missing.pt", ["chair"])
    w = tmp_path / "w.pt"
    w.write_bytes(b"x")
    try:
        import ultralytics  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="ultralytics"):
            YoloWorldDetector(w, ["chair"])


class _Frame:
    def __init__(self, camera, rgb, depth, pose, sem=None, inst=None):
        self.camera, self.rgb, self.depth, self.cam_to_world = camera, rgb, depth, pose
        self.semantics, self.instances, self.frame_id = sem, inst, "f0"


def test_pinhole_views_look_where_the_panorama_looks():
    """Centre rays of the four yaws are forward, right, back, left of the panorama camera."""
    from image2sim.simulator.conventions import camera_rotation_for_heading
    from image2sim.simulator.geometry.cameras import EquirectCamera

    cam = EquirectCamera(32, 64)
    pose = np.eye(4)
    pose[:3, :3] = camera_rotation_for_heading(0.3)
    pose[:3, 3] = [1, 2, 1.4]
    # Depth encodes the longitude so the sampled range tells which pano column a view pixel came from.
    lon = (np.arange(64) + 0.5) * 2 * np.pi / 64 - np.pi
    depth = np.tile(lon + 4.0, (32, 1)).astype(np.float32)
    frame = _Frame(cam, np.zeros((32, 64, 3), np.uint8), depth, pose)
    views = pinhole_views(frame, MiningConfig(view_size=16))
    assert len(views) == 4
    r = pose[:3, :3]
    for view, axis, want_lon in zip(
        views, (r[:, 2], r[:, 0], -r[:, 2], -r[:, 0]), (0.0, np.pi / 2, np.pi, -np.pi / 2), strict=False
    ):
        centre = view.rays_world[7:9, 7:9].mean(axis=(0, 1))
        np.testing.assert_allclose(centre / np.linalg.norm(centre), axis, atol=1e-9)
        got = view.range_map[7:9, 7:9].mean() - 4.0
        assert (
            math.isclose(abs(math.remainder(got - want_lon, 2 * np.pi)), 0.0, abs_tol=0.1)
            or abs(want_lon) == np.pi
        )


def test_fast_bilinear_matches_reference_across_the_seam():
    from image2sim.dataengine.mining import _remap_bilinear, _sample_bilinear_wrap

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, (16, 32, 3)).astype(np.float32)
    uv = np.stack([rng.uniform(-3, 35, (40, 40)), rng.uniform(0.5, 15.5, (40, 40))], axis=-1)
    uv[0, :, 0] = np.linspace(31.0, 33.0, 40)  # straddle the seam
    np.testing.assert_allclose(_remap_bilinear(img, uv), _sample_bilinear_wrap(img, uv), atol=0.05)


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path_factory.mktemp("mine")
    return synthesize(preset("tiny"), root, scenes=1, seed=5, progress=False)[0]


def test_gt_mining_finds_real_objects_near_their_boxes(tiny_capture):
    from image2sim.simulator.io.registry import open_capture

    cats, small = load_categories(tiny_capture)
    objs, stats = mine_capture(
        open_capture(tiny_capture), GTDetector(cats), MiningConfig(view_size=160), small
    )
    attach_gt_metadata(objs, tiny_capture)
    gt = {o["id"]: o for o in json.loads((tiny_capture / "gt" / "objects.json").read_text())["objects"]}
    assert stats["views"] == 4 * len(open_capture(tiny_capture)) and objs
    inside = 0
    for o in objs:
        rec = gt[o.instance_id]
        assert o.category == rec["category"] and o.small == (rec["category"] in small)
        assert o.room_type == rec["room_type"]
        lo, hi = np.array(rec["aabb"]["min"]) - 0.3, np.array(rec["aabb"]["max"]) + 0.3
        inside += bool(np.all((np.array(o.position) >= lo) & (np.array(o.position) <= hi)))
    assert inside >= 0.7 * len(objs)
    # Same-category objects are at least the merge radius apart.
    for a in objs:
        for b in objs:
            if a is not b and a.category == b.category:
                assert np.linalg.norm(np.subtract(a.position, b.position)) > 0.5 - 1e-9
