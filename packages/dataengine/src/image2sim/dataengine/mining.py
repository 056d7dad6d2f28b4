"""Global object mining and 3D grounding (paper appendix, "Global Object Mining and 3D Grounding").

Pipeline: pinhole views (90 degrees) are cut out of every capture frame at four yaws, so the views
sit at the capture positions spread over the navigable area; a :class:`Detector` returns 2D boxes;
boxes pass the paper's filters (confidence >= 0.08, area >= 300 px); each kept box is grounded in 3D
from the median range of its central patch along the ray through the box centre; detections farther
than 10 m are rejected; same-category detections within 0.5 m are merged into one object with a
sighting count. The per-scene database is ``objects.json``.

Detectors: ``gt`` reads boxes from the capture's instance/semantic maps (procedural scenes, labelled
datasets); ``yolo-world`` wraps an Ultralytics YOLO-World checkpoint loaded from a local path
(optional dependency, never downloaded).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from image2sim.simulator.config import config_from_dict
from image2sim.simulator.io.atomic import write_text_atomic

__all__ = [
    "Detection",
    "SceneObject",
    "MiningConfig",
    "Detector",
    "GTDetector",
    "YoloWorldDetector",
    "View",
    "pinhole_views",
    "ground_detection",
    "filter_detections",
    "merge_objects",
    "mine_capture",
    "save_objects",
    "load_objects",
    "load_categories",
]

OBJECTS_FORMAT = "image2sim-objects"


@dataclass(frozen=True)
class MiningConfig:
    """Mining filters and view layout (defaults = the paper's values)."""

    min_confidence: float = 0.08
    """Detections below this confidence are dropped."""
    min_box_area: float = 300.0
    """Boxes smaller than this many pixels (w x h) are dropped."""
    max_depth: float = 10.0
    """Grounded detections farther than this many metres from the camera are rejected."""
    merge_radius: float = 0.5
    """Same-category detections within this distance (metres) are one object."""
    patch_fraction: float = 0.3
    """Side of the central patch whose median range grounds a box, as a fraction of the box side."""
    view_size: int = 336
    """Pinhole view size in pixels (square)."""
    view_hfov_deg: float = 90.0
    """Pinhole view field of view in degrees."""
    yaws_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    """Yaw offsets of the pinhole views cut from each panorama (degrees, relative to the frame)."""

    def __post_init__(self) -> None:
        for name in ("min_box_area", "max_depth", "merge_radius", "patch_fraction", "view_hfov_deg"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"MiningConfig.{name} must be a positive number, got {v!r}")
        if not 0 <= self.min_confidence <= 1:
            raise ValueError(f"MiningConfig.min_confidence must lie in [0, 1], got {self.min_confidence!r}")
        if int(self.view_size) < 8:
            raise ValueError(f"MiningConfig.view_size must be >= 8, got {self.view_size!r}")

    @classmethod
    def from_dict(cls, data: dict) -> MiningConfig:
        """Build from a mapping with the shared config mechanism: unknown keys and wrong types raise
        :class:`~image2sim.simulator.config.ConfigError` (a ``ValueError``) naming the field."""
        return config_from_dict(cls, data)


@dataclass(frozen=True)
class Detection:
    """One 2D detection in a view: box (x0, y0, x1, y1) in pixels, category name, confidence."""

    box: tuple[float, float, float, float]
    category: str
    confidence: float
    instance_id: int | None = None
    """Source instance when the detector knows it (gt)."""

    @property
    def area(self) -> float:
        x0, y0, x1, y1 = self.box
        return max(0.0, x1 - x0) * max(0.0, y1 - y0)


@dataclass
class SceneObject:
    """A mined object: category, 3D position (world, metres), sightings and provenance."""

    object_id: int
    category: str
    position: list[float]
    sightings: int = 1
    confidence: float = 1.0
    support: int = 0
    """Instance id of the object it stands on (0 = floor/wall/unknown)."""
    small: bool = False
    """Small, manipulable item (goal radius 1.5 m) vs a large object (3.0 m)."""
    room_type: str | None = None
    instance_id: int | None = None
    """Source instance id when the detector knows it (gt)."""


@dataclass
class View:
    """A pinhole view cut out of a capture frame: image, range map, optional labels, pose."""

    rgb: np.ndarray
    """(H, W, 3) uint8."""
    range_map: np.ndarray
    """(H, W) float metres along the unit ray (0 = invalid)."""
    rays_world: np.ndarray
    """(H, W, 3) unit ray directions in the world frame."""
    origin: np.ndarray
    """(3,) camera centre in the world frame."""
    semantics: np.ndarray | None = None
    instances: np.ndarray | None = None
    frame_id: str = ""


class Detector(Protocol):
    """Anything that turns a :class:`View` into 2D detections."""

    name: str

    def detect(self, view: View) -> list[Detection]: ...


class GTDetector:
    """Boxes of every labelled object instance visible in the view (confidence 1)."""

    name = "gt"

    def __init__(self, categories: dict[int, str], structure_ids: Iterable[int] = (0, 1, 2, 3)) -> None:
        self.categories = dict(categories)
        self.structure = set(int(i) for i in structure_ids)

    def detect(self, view: View) -> list[Detection]:
        if view.instances is None or view.semantics is None:
            raise ValueError(f"gt detector: view {view.frame_id!r} has no instance/semantic maps")
        out = []
        inst = view.instances
        for iid in np.unique(inst):
            if iid <= 0:
                continue
            ys, xs = np.nonzero(inst == iid)
            cat = int(np.bincount(view.semantics[ys, xs].astype(np.int64)).argmax())
            if cat in self.structure or cat not in self.categories:
                continue
            box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
            out.append(Detection(box, self.categories[cat], 1.0, int(iid)))
        return out


DEFAULT_VOCABULARY = (
    "sofa", "armchair", "coffee_table", "tv", "bookshelf", "plant", "floor_lamp", "painting",
    "dining_table", "chair", "kitchen_counter", "fridge", "stove", "sink", "bed", "nightstand",
    "wardrobe", "dresser", "desk", "toilet", "bathtub", "washing_machine", "mirror", "cabinet",
    "monitor", "laptop", "table_lamp", "vase", "bowl", "cup", "microwave", "kettle", "clock",
)  # fmt: skip
"""Open-vocabulary prompts used when a scene has no category table (indoor goal objects)."""

DEFAULT_SMALL = frozenset(
    {"vase", "bowl", "cup", "laptop", "table_lamp", "kettle", "microwave", "clock", "plant", "monitor"}
)
"""Small, manipulable categories of :data:`DEFAULT_VOCABULARY` (goal radius 1.5 m, not 3.0 m)."""


class YoloWorldDetector:
    """Open-vocabulary detection with a local YOLO-World checkpoint (``pip install ultralytics``).

    Nothing is downloaded: ``weights`` must be an existing file, checked before the optional
    dependency is imported. The checkpoint's class names are kept when they already equal
    ``vocabulary`` (a checkpoint saved after ``set_classes``); otherwise ``set_classes(vocabulary)``
    re-embeds the prompts, which needs Ultralytics' CLIP text encoder in its local cache.
    ``predict`` runs with confidence 0 so that the paper's filters (:func:`filter_detections`) decide.
    """

    name = "yolo-world"

    def __init__(self, weights: str | Path, vocabulary: Sequence[str]) -> None:
        weights = Path(weights)
        if not weights.is_file():
            raise FileNotFoundError(
                f"yolo-world: weights file {weights} not found (no download is attempted; "
                "pass the path of a local YOLO-World .pt checkpoint)"
            )
        self.vocabulary = [str(v) for v in vocabulary]
        if not self.vocabulary:
            raise ValueError("yolo-world: the vocabulary (class prompts) is empty")
        try:
            from ultralytics import YOLOWorld  # type: ignore[import-not-found]
        except ImportError as err:
            raise ImportError(
                "yolo-world detector needs the optional 'ultralytics' package (pip install ultralytics)"
            ) from err
        self.weights = weights
        self.model = YOLOWorld(str(weights))
        names = getattr(self.model, "names", None)
        current = [names[k] for k in sorted(names)] if isinstance(names, dict) else list(names or [])
        if current != self.vocabulary:
            self.model.set_classes(self.vocabulary)

    def detect(self, view: View) -> list[Detection]:
        # Ultralytics takes numpy images as BGR (OpenCV order).
        res = self.model.predict(view.rgb[..., ::-1].copy(), verbose=False, conf=0.0)[0]
        boxes = res.boxes
        out = []
        for xyxy, c, k in zip(boxes.xyxy.tolist(), boxes.conf.tolist(), boxes.cls.tolist(), strict=True):
            k = int(k)
            if not 0 <= k < len(self.vocabulary):
                raise ValueError(
                    f"yolo-world: class index {k} outside the vocabulary of {len(self.vocabulary)}"
                )
            out.append(Detection(tuple(float(v) for v in xyxy), self.vocabulary[k], float(c)))
        return out


# ----------------------------------------------------------------------------------------- views


def _yaw_rotation(yaw: float) -> np.ndarray:
    """Rotation of the camera frame about its own -y axis (up in OpenCV) by ``yaw`` (positive = right)."""
    c, s = math.cos(yaw), math.sin(yaw)
    # OpenCV camera: x right, y down, z forward; turning right moves z towards +x.
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def pinhole_views(frame, config: MiningConfig) -> list[View]:
    """Pinhole views of a capture frame: four yaws of an equirect panorama, or the pinhole frame itself.

    Colour is resampled bilinearly; range, semantics and instances by nearest neighbour (labels and
    depth must not be blended across edges).
    """
    import torch
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    pose = np.asarray(frame.cam_to_world, dtype=np.float64)
    depth = np.asarray(frame.depth, dtype=np.float32)
    sem = getattr(frame, "semantics", None)
    inst = getattr(frame, "instances", None)
    if isinstance(frame.camera, PinholeCamera):
        rays = frame.camera.ray_map(dtype=torch.float64).permute(1, 2, 0).numpy()  # unit rays (H, W, 3)
        rng_map = depth / rays[..., 2]  # pinhole depth is z; range = z / cos(angle to the axis)
        rays_w = rays @ pose[:3, :3].T
        return [
            View(
                np.asarray(frame.rgb),
                rng_map,
                rays_w,
                pose[:3, 3].copy(),
                None if sem is None else np.asarray(sem),
                None if inst is None else np.asarray(inst),
                str(frame.frame_id),
            )
        ]
    if not isinstance(frame.camera, EquirectCamera):
        raise ValueError(f"mining: unsupported camera {type(frame.camera).__name__}")
    s = int(config.view_size)
    pano_cam = frame.camera
    views = []
    for yaw_deg in config.yaws_deg:
        rays_c, uv = _view_lookup(
            int(pano_cam.height), int(pano_cam.width), s, float(config.view_hfov_deg), float(yaw_deg)
        )
        rgb = _remap_bilinear(np.asarray(frame.rgb, dtype=np.float32), uv)
        iu = np.floor(uv[..., 0]).astype(np.int64) % pano_cam.width
        iv = np.clip(np.floor(uv[..., 1]).astype(np.int64), 0, pano_cam.height - 1)
        views.append(
            View(
                np.clip(rgb + 0.5, 0, 255).astype(np.uint8),
                depth[iv, iu].astype(np.float64),
                rays_c @ pose[:3, :3].T,
                pose[:3, 3].copy(),
                None if sem is None else np.asarray(sem)[iv, iu],
                None if inst is None else np.asarray(inst)[iv, iu],
                f"{frame.frame_id}@{yaw_deg:g}",
            )
        )
    return views


@functools.lru_cache(maxsize=32)
def _view_lookup(pano_h: int, pano_w: int, size: int, hfov_deg: float, yaw_deg: float):
    """Unit rays (size, size, 3) of a yawed pinhole view in the panorama camera frame and their panorama uv.

    Cached: the lookup depends only on the sizes, the field of view and the yaw, not on the frame.
    """
    import torch
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    cam = PinholeCamera.from_fov(hfov_deg, hfov_deg, size, size)
    base = cam.ray_map(dtype=torch.float64).permute(1, 2, 0).numpy()  # unit rays (s, s, 3)
    rays_c = base @ _yaw_rotation(math.radians(yaw_deg)).T
    uv, _, _ = EquirectCamera(pano_h, pano_w).project(torch.from_numpy(rays_c.reshape(-1, 3)))
    rays_c.setflags(write=False)
    uv = uv.numpy().reshape(size, size, 2)
    uv.setflags(write=False)
    return rays_c, uv


def _remap_bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Fast path of :func:`_sample_bilinear_wrap` (OpenCV remap, wrapping columns by padding)."""
    import cv2

    h, w = img.shape[:2]
    padded = np.concatenate((img[:, -1:], img, img[:, :1]), axis=1)  # one wrapped column each side
    mx = (np.mod(uv[..., 0] - 0.5, w) + 1.0).astype(np.float32)
    my = np.clip(uv[..., 1] - 0.5, 0, h - 1).astype(np.float32)
    return cv2.remap(padded, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _sample_bilinear_wrap(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of (H, W, C) at continuous pixel coordinates (pixel centres at +0.5), wrapping in u.

    Readable reference for :func:`_remap_bilinear` (parity-tested)."""
    h, w = img.shape[:2]
    x = uv[..., 0] - 0.5
    y = np.clip(uv[..., 1] - 0.5, 0, h - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    y1 = np.minimum(y0 + 1, h - 1)
    x0w, x1w = x0 % w, (x0 + 1) % w
    top = img[y0, x0w] * (1 - fx) + img[y0, x1w] * fx
    bot = img[y1, x0w] * (1 - fx) + img[y1, x1w] * fx
    return top * (1 - fy) + bot * fy


# ------------------------------------------------------------------------------------ grounding


def filter_detections(dets: Sequence[Detection], config: MiningConfig) -> list[Detection]:
    """The paper's 2D filters: confidence and box area."""
    return [d for d in dets if d.confidence >= config.min_confidence and d.area >= config.min_box_area]


def ground_detection(view: View, det: Detection, config: MiningConfig) -> np.ndarray | None:
    """World position of a box: median valid range of its central patch along the box-centre ray.

    Returns None when the patch has no valid range or the range exceeds ``max_depth``.
    """
    x0, y0, x1, y1 = det.box
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    hw = max(0.5, 0.5 * config.patch_fraction * (x1 - x0))
    hh = max(0.5, 0.5 * config.patch_fraction * (y1 - y0))
    h, w = view.range_map.shape
    c0, c1 = int(max(0, math.floor(cx - hw))), int(min(w, math.ceil(cx + hw)))
    r0, r1 = int(max(0, math.floor(cy - hh))), int(min(h, math.ceil(cy + hh)))
    patch = view.range_map[r0:r1, c0:c1]
    vals = patch[np.isfinite(patch) & (patch > 0)]
    if vals.size == 0:
        return None
    d = float(np.median(vals))
    if d > config.max_depth:
        return None
    ray = view.rays_world[min(h - 1, int(cy)), min(w - 1, int(cx))]
    return view.origin + d * ray


def merge_objects(points: Sequence[tuple[str, np.ndarray, float, dict]], radius: float) -> list[SceneObject]:
    """Same-category merging: a detection joins the nearest object within ``radius`` (running mean), then
    objects that drifted within ``radius`` of each other are merged.

    ``points`` holds (category, position, confidence, extra fields) in detection order.
    """
    objs: list[SceneObject] = []
    sums: list[np.ndarray] = []
    for cat, p, conf, extra in points:
        p = np.asarray(p, dtype=np.float64)
        best, best_d = -1, radius
        for k, o in enumerate(objs):
            if o.category != cat:
                continue
            dist = float(np.linalg.norm(np.asarray(o.position) - p))
            if dist <= best_d:
                best, best_d = k, dist
        if best < 0:
            objs.append(SceneObject(len(objs) + 1, cat, p.tolist(), 1, float(conf), **extra))
            sums.append(p.copy())
        else:
            o = objs[best]
            sums[best] += p
            o.sightings += 1
            o.position = (sums[best] / o.sightings).tolist()
            o.confidence = max(o.confidence, float(conf))
    # Running means drift: merge objects whose means came within the radius until none do, so the
    # result never holds two same-category objects closer than ``radius``.
    merged = True
    while merged:
        merged = False
        for a in range(len(objs)):
            for b in range(a + 1, len(objs)):
                if (
                    objs[a].category == objs[b].category
                    and np.linalg.norm(np.subtract(objs[a].position, objs[b].position)) <= radius
                ):
                    sums[a] += sums[b]
                    objs[a].sightings += objs[b].sightings
                    objs[a].position = (sums[a] / objs[a].sightings).tolist()
                    objs[a].confidence = max(objs[a].confidence, objs[b].confidence)
                    del objs[b], sums[b]
                    merged = True
                    break
            if merged:
                break
    for k, o in enumerate(objs):
        o.object_id = k + 1
    return objs


def load_categories(capture_dir: str | Path) -> tuple[dict[int, str], set[str]]:
    """Category id -> name and the set of small categories from ``gt/categories.json``."""
    path = Path(capture_dir) / "gt" / "categories.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the gt detector needs the scene's category table")
    data = json.loads(path.read_text())["categories"]
    return {int(c["id"]): str(c["name"]) for c in data}, {str(c["name"]) for c in data if c.get("small")}


def mine_capture(
    capture,
    detector: Detector,
    config: MiningConfig | None = None,
    small_categories: Iterable[str] = (),
    progress: bool = False,
) -> tuple[list[SceneObject], dict]:
    """Detect, filter, ground and merge over every frame of a capture -> (objects, statistics)."""
    cfg = config or MiningConfig()
    small = set(small_categories)
    found: list[tuple[str, np.ndarray, float, dict]] = []
    stats = {"views": 0, "detections": 0, "after_2d_filters": 0, "grounded": 0}
    frames = range(len(capture))
    if progress:
        from rich.progress import track

        frames = track(frames, description="mining objects")
    for i in frames:
        for view in pinhole_views(capture[i], cfg):
            stats["views"] += 1
            dets = detector.detect(view)
            stats["detections"] += len(dets)
            dets = filter_detections(dets, cfg)
            stats["after_2d_filters"] += len(dets)
            for det in dets:
                p = ground_detection(view, det, cfg)
                if p is None:
                    continue
                stats["grounded"] += 1
                extra: dict = {"small": det.category in small, "instance_id": det.instance_id}
                found.append((det.category, p, det.confidence, extra))
    objects = merge_objects(found, cfg.merge_radius)
    stats["objects"] = len(objects)
    return objects, stats


def attach_gt_metadata(objects: list[SceneObject], capture_dir: str | Path) -> None:
    """Fill support and room type from ``gt/objects.json`` for objects with a known instance id."""
    path = Path(capture_dir) / "gt" / "objects.json"
    if not path.is_file():
        return
    by_id = {int(o["id"]): o for o in json.loads(path.read_text())["objects"]}
    for o in objects:
        rec = by_id.get(o.instance_id or -1)
        if rec is not None:
            o.support = int(rec.get("support", 0))
            o.room_type = rec.get("room_type")


def save_objects(path: str | Path, objects: Sequence[SceneObject], meta: dict | None = None) -> Path:
    """Write the object database atomically as JSON."""
    path = Path(path)
    doc = {
        "format": OBJECTS_FORMAT,
        "version": 1,
        "frame": "image2sim-z-up",
        **(meta or {}),
        "objects": [asdict(o) for o in objects],
    }
    write_text_atomic(path, json.dumps(doc, indent=1))
    return path


def load_objects(path: str | Path) -> list[SceneObject]:
    """Read an object database written by :func:`save_objects`."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read object database ({err})") from None
    if doc.get("format") != OBJECTS_FORMAT:
        raise ValueError(f"{path}: field 'format' is {doc.get('format')!r}, expected {OBJECTS_FORMAT!r}")
    out = []
    for i, o in enumerate(doc.get("objects", [])):
        try:
            out.append(SceneObject(**o))
        except TypeError as err:
            raise ValueError(f"{path}: objects[{i}]: {err}") from None
    return out
