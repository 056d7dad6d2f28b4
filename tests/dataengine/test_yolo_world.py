"""The YOLO-World adapter with a fake ``ultralytics`` module: local weights, the paper's filters,
3D grounding against a procedural scene's ground truth, and merging."""

from __future__ import annotations

import json
import sys
import types

import numpy as np
import pytest
from image2sim.dataengine.mining import (
    Detection,
    GTDetector,
    MiningConfig,
    View,
    YoloWorldDetector,
    ground_detection,
    load_categories,
    mine_capture,
    pinhole_views,
)


class _Array:
    """What ``boxes.xyxy`` / ``.conf`` / ``.cls`` offer to the adapter (``tolist``)."""

    def __init__(self, values) -> None:
        self.values = np.asarray(values, dtype=np.float64)

    def tolist(self):
        return self.values.tolist()


class FakeYOLOWorld:
    """Stands in for ``ultralytics.YOLOWorld``: records how it is used and answers ``predict`` with
    the boxes a test script returns for the (RGB) image."""

    created: list = []
    script = staticmethod(lambda rgb: [])
    names: dict = {0: "person", 1: "car"}

    def __init__(self, path: str) -> None:
        self.path = path
        self.classes = None
        self.predict_kwargs = []
        FakeYOLOWorld.created.append(self)

    def set_classes(self, classes) -> None:
        self.classes = list(classes)
        self.names = dict(enumerate(self.classes))

    def predict(self, source, **kwargs):
        self.predict_kwargs.append(kwargs)
        rows = FakeYOLOWorld.script(np.ascontiguousarray(source[..., ::-1]))  # BGR in -> RGB for the script
        xyxy = [r[0] for r in rows] or np.zeros((0, 4))
        boxes = types.SimpleNamespace(
            xyxy=_Array(xyxy), conf=_Array([r[1] for r in rows]), cls=_Array([r[2] for r in rows])
        )
        return [types.SimpleNamespace(boxes=boxes)]


@pytest.fixture
def fake_ultralytics(monkeypatch):
    mod = types.ModuleType("ultralytics")
    mod.YOLOWorld = FakeYOLOWorld
    monkeypatch.setitem(sys.modules, "ultralytics", mod)
    FakeYOLOWorld.created = []
    FakeYOLOWorld.script = staticmethod(lambda rgb: [])
    FakeYOLOWorld.names = {0: "person", 1: "car"}
    return FakeYOLOWorld


@pytest.fixture
def weights(tmp_path):
    path = tmp_path / "yolov8s-worldv2.pt"
    path.write_bytes(b"local checkpoint")
    return path


def test_weights_load_from_the_local_path(fake_ultralytics, weights):
    det = YoloWorldDetector(weights, ["chair", "sofa"])
    (model,) = fake_ultralytics.created
    assert model.path == str(weights)
    assert model.classes == ["chair", "sofa"]  # prompts set from the vocabulary
    # A checkpoint saved with the same classes is used as it is (no text-encoder run).
    fake_ultralytics.names = {0: "chair", 1: "sofa"}
    YoloWorldDetector(weights, ["chair", "sofa"])
    assert fake_ultralytics.created[-1].classes is None
    assert det.weights == weights


def test_missing_weights_fail_clearly_before_importing_ultralytics(fake_ultralytics, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing\.pt.*no download"):
        YoloWorldDetector(tmp_path / "missing.pt", ["chair"])
    with pytest.raises(FileNotFoundError, match="not found"):
        YoloWorldDetector(tmp_path, ["chair"])  # a folder is not a checkpoint
    assert fake_ultralytics.created == []


def test_missing_package_and_empty_vocabulary_fail_clearly(monkeypatch, weights):
    monkeypatch.setitem(sys.modules, "ultralytics", None)  # import raises ImportError
    with pytest.raises(ImportError, match="pip install ultralytics"):
        YoloWorldDetector(weights, ["chair"])
    with pytest.raises(ValueError, match="vocabulary"):
        YoloWorldDetector(weights, [])


def test_detect_passes_bgr_at_confidence_zero_and_names_classes(fake_ultralytics, weights):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB
    seen = []

    def script(img):
        seen.append(img.copy())
        return [((1, 2, 5, 6), 0.42, 1), ((0, 0, 8, 8), 0.05, 0)]

    fake_ultralytics.script = staticmethod(script)
    det = YoloWorldDetector(weights, ["chair", "sofa"])
    view = View(rgb, np.ones((8, 8)), np.zeros((8, 8, 3)), np.zeros(3))
    out = det.detect(view)
    assert out == [
        Detection((1.0, 2.0, 5.0, 6.0), "sofa", 0.42),
        Detection((0.0, 0.0, 8.0, 8.0), "chair", 0.05),
    ]
    np.testing.assert_array_equal(seen[0], rgb)  # the model got BGR, which the script flipped back
    assert fake_ultralytics.created[0].predict_kwargs == [{"verbose": False, "conf": 0.0}]
    fake_ultralytics.script = staticmethod(lambda img: [((0, 0, 4, 4), 0.9, 7)])
    with pytest.raises(ValueError, match="class index 7"):
        det.detect(view)


# ---------------------------------------------------------------- a procedural scene as ground truth


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    from image2sim.dataengine.procedural import preset, synthesize

    return synthesize(preset("tiny"), tmp_path_factory.mktemp("yolo"), scenes=1, seed=5, progress=False)[0]


def _gt_boxes(capture, cats, cfg):
    """Per view (keyed by its RGB bytes): the boxes of the objects projected into it (their instance
    masks), as the gt detector sees them."""
    gt = GTDetector(cats)
    table = {}
    for i in range(len(capture)):
        for view in pinhole_views(capture[i], cfg):
            table[view.rgb.tobytes()] = (view, gt.detect(view))
    return table


def test_mining_with_yolo_world_applies_the_paper_filters_and_grounds_like_the_truth(
    fake_ultralytics, weights, capture_dir
):
    from image2sim.simulator.io.registry import open_capture

    cfg = MiningConfig(view_size=160)
    cap = open_capture(capture_dir)
    cats, small = load_categories(capture_dir)
    vocab = sorted(set(cats.values()))
    table = _gt_boxes(cap, cats, cfg)

    def script(rgb):
        """Each true box at confidence 0.5, plus distractors the filters must drop: the same box at
        confidence 0.07, and a 14 x 21 px (294 px^2) box at confidence 0.9."""
        rows = []
        for d in table[rgb.tobytes()][1]:
            k = vocab.index(d.category)
            x0, y0, x1, y1 = d.box
            cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
            rows += [(d.box, 0.5, k), (d.box, 0.07, k), ((cx - 7, cy - 10.5, cx + 7, cy + 10.5), 0.9, k)]
        return rows

    fake_ultralytics.script = staticmethod(script)
    objs, stats = mine_capture(cap, YoloWorldDetector(weights, vocab), cfg, small)
    ref, ref_stats = mine_capture(cap, GTDetector(cats), cfg, small)
    true_boxes = [d for _, dets in table.values() for d in dets]
    big = [d for d in true_boxes if d.area >= 300]
    assert stats["detections"] == 3 * len(true_boxes)
    assert stats["after_2d_filters"] == len(big) == ref_stats["after_2d_filters"]
    # The same boxes, grounded and merged: the same object database as the gt detector's.
    assert stats["grounded"] == ref_stats["grounded"] and len(objs) == len(ref) > 0
    for a, b in zip(objs, ref, strict=True):
        assert (a.category, a.sightings, a.small) == (b.category, b.sightings, b.small)
        np.testing.assert_allclose(a.position, b.position, atol=1e-9)
        assert a.confidence == 0.5
    # 3D grounding against the ground truth: every grounded box lies on (or next to) its object.
    gt = {o["id"]: o for o in json.loads((capture_dir / "gt" / "objects.json").read_text())["objects"]}
    dists = []
    for view, dets in table.values():
        for d in dets:
            if d.area < 300:
                continue
            p = ground_detection(view, d, cfg)
            if p is None:
                continue
            lo, hi = np.array(gt[d.instance_id]["aabb"]["min"]), np.array(gt[d.instance_id]["aabb"]["max"])
            dists.append(float(np.linalg.norm(np.maximum(0, np.maximum(lo - p, p - hi)))))
    assert len(dists) >= 10
    assert np.median(dists) <= 0.02 and np.mean(np.array(dists) <= 0.1) >= 0.8, dists
    # Merging: same-category objects end up more than 0.5 m apart; sightings add up to the grounded boxes.
    assert sum(o.sightings for o in objs) == stats["grounded"]
    for a in objs:
        for b in objs:
            if a is not b and a.category == b.category:
                assert np.linalg.norm(np.subtract(a.position, b.position)) > 0.5


def test_a_far_box_is_rejected_by_its_central_depth(fake_ultralytics, weights, capture_dir):
    """The same true box grounds at the object; with the view's range scaled so the central patch
    lies beyond 10 m it is rejected, just inside 10 m it is kept."""
    from image2sim.simulator.io.registry import open_capture

    cfg = MiningConfig(view_size=160)
    cap = open_capture(capture_dir)
    cats, _ = load_categories(capture_dir)
    vocab = sorted(set(cats.values()))
    view, dets = max(_gt_boxes(cap, cats, cfg).values(), key=lambda t: max((d.area for d in t[1]), default=0))
    box = max(dets, key=lambda d: d.area)
    fake_ultralytics.script = staticmethod(lambda rgb: [(box.box, 0.3, vocab.index(box.category))])
    (det,) = YoloWorldDetector(weights, vocab).detect(view)
    p = ground_detection(view, det, cfg)
    d = float(np.linalg.norm(p - view.origin))
    for scale, kept in ((10.2 / d, False), (9.8 / d, True)):
        far = View(view.rgb, view.range_map * scale, view.rays_world, view.origin)
        assert (ground_detection(far, det, cfg) is not None) == kept


def test_engine_mines_with_yolo_world_over_the_scene_vocabulary(
    fake_ultralytics, weights, capture_dir, tmp_path
):
    """The engine's yolo-world path: prompts are the scene's object categories (no structure), and
    the object database it writes says which detector made it."""
    from image2sim.dataengine.engine_config import EngineConfig
    from image2sim.dataengine.scene_assets import resolve_scene, scene_objects
    from image2sim.simulator.io.registry import open_capture

    cats, _ = load_categories(capture_dir)
    mcfg = MiningConfig(view_size=160)
    table = _gt_boxes(open_capture(capture_dir), cats, mcfg)
    vocab = sorted(set(cats.values()) - {"floor", "wall", "ceiling", "rug"})
    fake_ultralytics.script = staticmethod(
        lambda rgb: [(d.box, 0.6, vocab.index(d.category)) for d in table[rgb.tobytes()][1]]
    )
    cfg = EngineConfig(detector="yolo-world", detector_weights=str(weights), mining={"view_size": 160})
    objs = scene_objects(resolve_scene(capture_dir), tmp_path, cfg)
    assert fake_ultralytics.created[0].classes == vocab and "wall" not in vocab and "chair" in vocab
    assert objs and {o.category for o in objs} <= set(vocab)
    doc = json.loads((tmp_path / "objects.json").read_text())
    assert doc["detector"] == "yolo-world" and len(doc["objects"]) == len(objs)
