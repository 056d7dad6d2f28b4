"""The documented objects file of ``data episodes --detector annotations``: goal objects a person
annotated, instead of mined ones.

Format (JSON, world frame of the capture as ``image2sim`` reads it: z up, metres)::

    {
      "objects": [
        {"category": "bed", "position": [2.1, 0.4, 0.5], "room": "bedroom"},
        {"category": "tv", "box": {"min": [4.0, 1.0, 0.6], "max": [4.9, 1.1, 1.2]}},
        {"category": "cup", "position": [1.0, 2.0, 0.9], "small": true}
      ]
    }

Each object has a ``category`` (the word instructions use; ``_`` reads as a space) and either a
``position`` (a point, e.g. its centre) or a 3D ``box`` (axis-aligned, its centre is used). Optional:
``room`` (room type, named by instructions), ``small`` (a small, manipulable item: the episode's goal
radius is the sampling config's ``small_radius`` instead of ``large_radius``). Unknown keys are
refused, so a misspelt field is an error rather than silently ignored.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from image2sim.dataengine.mining import SceneObject

__all__ = ["ObjectsFileError", "load_objects_file", "objects_file_for"]

_KEYS = {"category", "position", "box", "room", "small"}


class ObjectsFileError(ValueError):
    """The objects file is missing or malformed (the message names the file, object and field)."""


def _point(value, where: str) -> list[float]:
    if not (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise ObjectsFileError(f"{where}: expected 3 finite numbers [x, y, z], got {value!r}")
    return [float(v) for v in value]


def load_objects_file(path: str | Path) -> list[SceneObject]:
    """Read and check an objects file; object ids are 1..N in file order."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ObjectsFileError(f"{path}: objects file not found") from None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ObjectsFileError(f"{path}: not readable JSON ({err})") from None
    items = doc.get("objects") if isinstance(doc, dict) else None
    if not isinstance(items, list) or not items:
        raise ObjectsFileError(f"{path}: field 'objects' must be a non-empty list")
    out = []
    for i, item in enumerate(items):
        where = f"{path}: objects[{i}]"
        if not isinstance(item, dict):
            raise ObjectsFileError(f"{where}: expected an object, got {type(item).__name__}")
        unknown = sorted(set(item) - _KEYS)
        if unknown:
            raise ObjectsFileError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(_KEYS)}")
        category = item.get("category")
        if not isinstance(category, str) or not category.strip():
            raise ObjectsFileError(f"{where}.category: expected a non-empty string, got {category!r}")
        if ("position" in item) == ("box" in item):
            raise ObjectsFileError(f"{where}: give exactly one of 'position' or 'box'")
        if "position" in item:
            position = _point(item["position"], f"{where}.position")
        else:
            box = item["box"]
            if not isinstance(box, dict) or set(box) != {"min", "max"}:
                raise ObjectsFileError(f"{where}.box: expected {{'min': [x, y, z], 'max': [x, y, z]}}")
            lo, hi = _point(box["min"], f"{where}.box.min"), _point(box["max"], f"{where}.box.max")
            if any(a > b for a, b in zip(lo, hi, strict=True)):
                raise ObjectsFileError(f"{where}.box: min {lo} exceeds max {hi}")
            position = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
        room = item.get("room")
        if room is not None and (not isinstance(room, str) or not room.strip()):
            raise ObjectsFileError(f"{where}.room: expected a non-empty string, got {room!r}")
        small = item.get("small", False)
        if not isinstance(small, bool):
            raise ObjectsFileError(f"{where}.small: expected true or false, got {small!r}")
        out.append(
            SceneObject(
                object_id=i + 1,
                category=category.strip().lower().replace(" ", "_"),
                position=position,
                small=small,
                room_type=None if room is None else room.strip().lower().replace(" ", "_"),
            )
        )
    return out


def objects_file_for(objects: str | Path | None, scene_name: str, capture_dir: Path) -> Path:
    """The objects file of one scene: ``objects`` is a file (one scene), a folder holding
    ``<scene name>.json``, or None for ``<capture>/objects_annotations.json``."""
    if objects is None:
        return Path(capture_dir) / "objects_annotations.json"
    objects = Path(objects)
    return objects / f"{scene_name}.json" if objects.is_dir() else objects
