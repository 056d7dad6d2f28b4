"""The canonical capture format (``image2sim``): writer and lazy reader.

Layout of a capture folder ``<dir>``::

    manifest.json                 {"format": "image2sim-capture", "version": 1, "scene_id",
                                   "num_frames", "frame_ids", "camera", "conventions",
                                   "has_semantics", "metadata"}
    frames/<id>_rgb.png           (H, W, 3) 8-bit RGB
    frames/<id>_depth.png         (H, W) uint16 millimetres (range for equirect, z for pinhole), 0 = invalid
    frames/<id>_pose.json         {"cam_to_world": 4x4 nested list} (+ "notes": [...] when a reader left any)
    frames/<id>_confidence.png    optional (H, W) uint8 depth confidence, 0..255 for [0, 1]
    semantics/<id>_category.png   optional (H, W) uint16 category ids
    semantics/<id>_instance.png   optional (H, W) uint16 instance ids

:func:`write_capture` builds everything in a hidden temporary sibling folder, lets the caller add
files there (``extra``), and renames it into place, so a reader never sees a half-written capture.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from image2sim.simulator.conventions import DEPTH_PNG_SCALE
from image2sim.simulator.geometry.cameras import camera_from_dict
from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling
from image2sim.simulator.io.images import (
    read_depth_uint16,
    read_rgb,
    read_uint8,
    read_uint16,
    write_rgb_png,
    write_uint8_png,
    write_uint16_png,
)
from image2sim.simulator.io.records import Capture, CaptureError, Frame
from image2sim.simulator.io.validation import check_depth, check_pose, check_same_size

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "CONVENTIONS",
    "write_capture",
    "read_canonical",
    "is_canonical",
    "encode_depth_mm",
    "encode_confidence",
]

FORMAT_NAME = "image2sim-capture"
FORMAT_VERSION = 1
CONVENTIONS = {
    "world": "z-up metres",
    "camera": "opencv",
    "pose": "camera-to-world",
    "depth": "range (equirect) / z (pinhole), uint16 millimetres, 0 = invalid",
}
MAX_DEPTH_M = 65535 / DEPTH_PNG_SCALE
"""Largest depth a uint16 millimetre PNG can hold (65.535 m)."""

_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")
_MANIFEST_KEYS = (
    "format",
    "version",
    "scene_id",
    "num_frames",
    "frame_ids",
    "camera",
    "conventions",
    "has_semantics",
    "metadata",
)


def encode_depth_mm(depth: np.ndarray, source: str) -> np.ndarray:
    """Metres (0 = invalid) -> uint16 millimetres, rounding to the nearest millimetre.

    Depth beyond 65.535 m cannot be stored and is an error rather than a silent clip. Positive
    depth below 0.5 mm would round to 0 (= invalid) and is an error too.
    """
    d = check_depth(depth, source)
    mm = np.rint(d.astype(np.float64) * DEPTH_PNG_SCALE)
    if mm.size and float(mm.max()) > 65535:
        raise CaptureError(
            f"{source}: depth {float(d.max()):.3f} m exceeds the uint16 millimetre range ({MAX_DEPTH_M} m)"
        )
    if np.any((d > 0) & (mm == 0)):
        raise CaptureError(f"{source}: positive depth below 0.5 mm would be stored as 0 (invalid)")
    return mm.astype(np.uint16)


def encode_confidence(confidence: np.ndarray, source: str) -> np.ndarray:
    """Confidence in [0, 1] -> uint8 0..255 (rounded); NaN or values outside [0, 1] are errors."""
    c = np.asarray(confidence)
    if c.ndim != 2 or not np.issubdtype(c.dtype, np.floating):
        raise CaptureError(f"{source}: confidence must be (H, W) floats in [0, 1], got {c.shape} {c.dtype}")
    if not np.all(np.isfinite(c)) or (c.size and (float(c.min()) < 0.0 or float(c.max()) > 1.0)):
        raise CaptureError(f"{source}: confidence must be finite and lie in [0, 1]")
    return np.rint(c.astype(np.float64) * 255.0).astype(np.uint8)


def _check_confidence_size(confidence: np.ndarray, depth: np.ndarray, source) -> None:
    if confidence.shape[:2] != depth.shape[:2]:
        raise CaptureError(
            f"{source}: confidence is {confidence.shape[1]}x{confidence.shape[0]} but depth is "
            f"{depth.shape[1]}x{depth.shape[0]} (WxH)"
        )


def _label_to_uint16(labels: np.ndarray, source: str) -> np.ndarray:
    lab = np.asarray(labels)
    if lab.ndim != 2 or not np.issubdtype(lab.dtype, np.integer):
        raise CaptureError(f"{source}: label image must be (H, W) integers, got {lab.shape} {lab.dtype}")
    if lab.size and (int(lab.min()) < 0 or int(lab.max()) > 65535):
        raise CaptureError(
            f"{source}: label ids must lie in [0, 65535], got [{int(lab.min())}, {int(lab.max())}]"
        )
    return lab.astype(np.uint16)


def _frame_name(frame: Frame, index: int, seen: set[str]) -> str:
    name = frame.frame_id or f"{index:05d}"
    if not _SAFE_ID.match(name):
        raise CaptureError(
            f"frame {index}: frame_id {name!r} is not a safe file name (letters, digits, _ . -)"
        )
    if name in seen:
        raise CaptureError(f"frame {index}: duplicate frame_id {name!r}")
    seen.add(name)
    return name


def _write_frame(tmp: Path, name: str, frame: Frame, index: int) -> None:
    source = f"frame {index} ({name!r})"
    if not isinstance(frame, Frame):
        raise CaptureError(f"{source}: expected a Frame, got {type(frame).__name__}")
    check_same_size(frame.rgb, frame.depth, source)
    if frame.confidence is not None:
        _check_confidence_size(np.asarray(frame.confidence), frame.depth, f"{source} confidence")
    cam = frame.camera
    if (cam.height, cam.width) != tuple(frame.depth.shape):
        raise CaptureError(
            f"{source}: camera is {cam.width}x{cam.height} but depth is "
            f"{frame.depth.shape[1]}x{frame.depth.shape[0]}"
        )
    pose = check_pose(frame.cam_to_world, f"{source} cam_to_world")
    write_rgb_png(tmp / "frames" / f"{name}_rgb.png", np.asarray(frame.rgb))
    write_uint16_png(tmp / "frames" / f"{name}_depth.png", encode_depth_mm(frame.depth, f"{source} depth"))
    pose_doc: dict = {"cam_to_world": pose.tolist()}
    if frame.notes:
        pose_doc["notes"] = list(frame.notes)
    (tmp / "frames" / f"{name}_pose.json").write_text(json.dumps(pose_doc) + "\n", encoding="utf-8")
    if frame.confidence is not None:
        write_uint8_png(
            tmp / "frames" / f"{name}_confidence.png",
            encode_confidence(frame.confidence, f"{source} confidence"),
        )
    if frame.semantics is not None:
        write_uint16_png(
            tmp / "semantics" / f"{name}_category.png",
            _label_to_uint16(frame.semantics, f"{source} semantics"),
        )
    if frame.instances is not None:
        write_uint16_png(
            tmp / "semantics" / f"{name}_instance.png",
            _label_to_uint16(frame.instances, f"{source} instances"),
        )


def write_capture(
    out_dir: str | Path,
    frames: Iterable[Frame],
    *,
    scene_id: str,
    metadata: dict | None = None,
    extra: Callable[[Path], None] | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Write ``frames`` as a canonical capture at ``out_dir`` (atomically) and return its path.

    All frames must share one camera model. ``has_semantics`` is true when every frame carries
    ``semantics``; a mix of frames with and without is an error. ``extra(tmp_dir)`` runs after the
    frames are written and before the rename, so callers can add e.g. a ``gt/`` folder atomically.
    With ``overwrite`` an existing ``out_dir`` is replaced (only after the new one is complete);
    otherwise it is a :class:`FileExistsError`. On any error nothing is left behind.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise FileExistsError(f"{out_dir}: already exists (pass overwrite=True to replace it)")
    meta = dict(metadata or {})
    try:
        json.dumps(meta)
    except (TypeError, ValueError) as err:
        raise CaptureError(f"metadata for {out_dir} is not JSON-serialisable: {err}") from None
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_temps(out_dir)
    tmp = temp_sibling(out_dir, ".tmp")
    tmp.mkdir()
    try:
        (tmp / "frames").mkdir()
        (tmp / "semantics").mkdir()
        names: list[str] = []
        camera = None
        semantic_flags: list[bool] = []
        seen: set[str] = set()
        iterator = _progress_iter(frames, progress, f"writing {out_dir.name}")
        for index, frame in enumerate(iterator):
            name = _frame_name(frame, index, seen)
            if camera is None:
                camera = frame.camera
            elif frame.camera != camera:
                raise CaptureError(
                    f"frame {index} ({name!r}): camera {frame.camera.to_dict()} differs from "
                    "the first frame's "
                    f"{camera.to_dict()} (a capture has one camera)"
                )
            _write_frame(tmp, name, frame, index)
            names.append(name)
            semantic_flags.append(frame.semantics is not None)
        if not names:
            raise CaptureError(f"{out_dir}: no frames to write")
        if any(semantic_flags) and not all(semantic_flags):
            missing = [n for n, f in zip(names, semantic_flags, strict=False) if not f]
            raise CaptureError(
                f"{out_dir}: some frames have semantics and some do not (missing in {missing[:5]})"
            )
        if not any(semantic_flags) and not any((tmp / "semantics").iterdir()):
            (tmp / "semantics").rmdir()
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "scene_id": str(scene_id),
            "num_frames": len(names),
            "frame_ids": names,
            "camera": camera.to_dict(),
            "conventions": dict(CONVENTIONS),
            "has_semantics": all(semantic_flags),
            "metadata": meta,
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
        if extra is not None:
            extra(tmp)
        _move_into_place(tmp, out_dir, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _move_into_place(tmp: Path, out_dir: Path, overwrite: bool) -> None:
    """Rename ``tmp`` to ``out_dir``; an existing target is moved aside first, then deleted."""
    if out_dir.exists():
        if not overwrite:
            raise FileExistsError(f"{out_dir}: appeared while writing (pass overwrite=True to replace it)")
        trash = temp_sibling(out_dir, ".old")
        os.replace(out_dir, trash)
        try:
            os.replace(tmp, out_dir)
        except BaseException:
            os.replace(trash, out_dir)
            raise
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(tmp, out_dir)


def _progress_iter(items: Iterable, enabled: bool, description: str):
    if not enabled:
        yield from items
        return
    from rich.progress import track

    total = len(items) if hasattr(items, "__len__") else None  # type: ignore[arg-type]
    yield from track(items, description=description, total=total, transient=False)


# --- reader ----------------------------------------------------------------------------------


def is_canonical(path: Path) -> bool:
    """True when ``path`` is a folder with a manifest that declares the canonical format."""
    manifest = Path(path) / "manifest.json"
    if not manifest.is_file():
        return False
    try:
        return json.loads(manifest.read_text(encoding="utf-8")).get("format") == FORMAT_NAME
    except (ValueError, AttributeError, UnicodeDecodeError):
        return False


def _load_manifest(path: Path) -> dict:
    mpath = path / "manifest.json"
    if not mpath.is_file():
        raise CaptureError(f"{mpath}: missing manifest file")
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as err:
        raise CaptureError(f"{mpath}: not valid JSON ({err})") from None
    if not isinstance(manifest, dict):
        raise CaptureError(f"{mpath}: top level must be a JSON object")
    missing = [k for k in _MANIFEST_KEYS if k not in manifest]
    if missing:
        raise CaptureError(f"{mpath}: missing field(s) {missing}")
    if manifest["format"] != FORMAT_NAME:
        raise CaptureError(f"{mpath}: field 'format' is {manifest['format']!r}, expected {FORMAT_NAME!r}")
    if manifest["version"] != FORMAT_VERSION:
        raise CaptureError(
            f"{mpath}: unsupported version {manifest['version']!r} (this reader knows {FORMAT_VERSION})"
        )
    if not isinstance(manifest["metadata"], dict):
        raise CaptureError(f"{mpath}: field 'metadata' must be a JSON object")
    if not isinstance(manifest["has_semantics"], bool):
        raise CaptureError(f"{mpath}: field 'has_semantics' must be true or false")
    ids = manifest["frame_ids"]
    if not isinstance(ids, list) or not all(isinstance(i, str) and _SAFE_ID.match(i) for i in ids):
        raise CaptureError(f"{mpath}: field 'frame_ids' must be a list of safe file-name strings")
    if len(set(ids)) != len(ids):
        raise CaptureError(f"{mpath}: field 'frame_ids' has duplicates")
    if manifest["num_frames"] != len(ids):
        raise CaptureError(f"{mpath}: num_frames = {manifest['num_frames']} but frame_ids lists {len(ids)}")
    try:
        manifest["camera"] = camera_from_dict(manifest["camera"])
    except (ValueError, TypeError) as err:
        raise CaptureError(f"{mpath}: field 'camera': {err}") from None
    return manifest


def _read_pose_json(path: Path) -> tuple[np.ndarray, list[str]]:
    if not path.is_file():
        raise CaptureError(f"{path}: missing pose file")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        pose = np.array(doc["cam_to_world"], dtype=np.float64)
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as err:
        raise CaptureError(f"{path}: cannot read 'cam_to_world' ({type(err).__name__}: {err})") from None
    return check_pose(pose, path), list(doc.get("notes", []))


def read_canonical(path: str | Path, *, strict: bool = True) -> Capture:
    """Open a canonical capture. Poses are read and checked now; images load lazily per frame.

    With ``strict=False`` frames whose pose file is missing or bad, or whose colour or depth file is
    missing, are listed in ``Capture.skipped`` instead of raising (strict: the first one raises).
    """
    root = Path(path)
    manifest = _load_manifest(root)
    camera = manifest["camera"]
    has_sem = bool(manifest["has_semantics"])
    ids, poses, notes, skipped = [], [], {}, []
    for fid in manifest["frame_ids"]:
        try:
            pose, frame_notes = _read_pose_json(root / "frames" / f"{fid}_pose.json")
            for kind in ("rgb", "depth"):  # cheap now; decoding stays lazy
                if not (root / "frames" / f"{fid}_{kind}.png").is_file():
                    raise CaptureError(f"{root / 'frames' / f'{fid}_{kind}.png'}: missing {kind} file")
        except CaptureError as err:
            if strict:
                raise
            skipped.append((fid, str(err)))
            continue
        ids.append(fid)
        poses.append(pose)
        notes[fid] = frame_notes
    pose_of = dict(zip(ids, poses, strict=False))

    def load(fid: str) -> Frame:
        frames = root / "frames"
        rgb = read_rgb(frames / f"{fid}_rgb.png")
        depth_path = frames / f"{fid}_depth.png"
        depth = read_depth_uint16(depth_path).astype(np.float32) / np.float32(DEPTH_PNG_SCALE)
        check_same_size(rgb, depth, frames / f"{fid}_rgb.png")
        if depth.shape != (camera.height, camera.width):
            raise CaptureError(
                f"{depth_path}: image is {depth.shape[1]}x{depth.shape[0]} but the manifest camera is "
                f"{camera.width}x{camera.height}"
            )
        confidence = None
        conf_path = frames / f"{fid}_confidence.png"
        if conf_path.exists():
            confidence = read_uint8(conf_path, "confidence").astype(np.float32) / np.float32(255.0)
            _check_confidence_size(confidence, depth, conf_path)
        semantics = instances = None
        if has_sem:
            sem_path = root / "semantics" / f"{fid}_category.png"
            semantics = read_uint16(sem_path, "semantic category").astype(np.int32)
            check_same_size(semantics[..., None], depth, sem_path)
            inst_path = root / "semantics" / f"{fid}_instance.png"
            if inst_path.exists():
                instances = read_uint16(inst_path, "instance").astype(np.int32)
                check_same_size(instances[..., None], depth, inst_path)
        return Frame(
            rgb=rgb,
            depth=depth,
            camera=camera,
            cam_to_world=pose_of[fid].copy(),
            semantics=semantics,
            instances=instances,
            frame_id=fid,
            notes=list(notes[fid]),
            confidence=confidence,
        )

    if not ids:
        raise CaptureError(f"{root}: no usable frames" + (f" ({len(skipped)} skipped)" if skipped else ""))
    return Capture(
        root,
        "image2sim",
        ids,
        load,
        scene_id=str(manifest["scene_id"]),
        skipped=skipped,
        metadata=dict(manifest["metadata"]),
        poses=np.stack(poses),
        camera=camera,
    )
