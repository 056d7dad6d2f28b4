"""The exact procedural renderer of a procedural capture: the "real world" with ground truth.

A procedural capture records its generator config and seed (``manifest.json`` ``metadata``), so the
house regenerates bit-identically and renders exactly (mesh ray casting, no reconstruction) from
any pose. The sim-to-real experiment trains in neural simulators built from a capture of the house
and evaluates here (``image2sim eval nav --backend exact``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["is_procedural_capture", "procedural_scene_of", "exact_render_fn", "capture_navigation"]

GENERATOR = "image2sim.dataengine.procedural"
FLOOR_LABELS = (1, 10)
"""Procedural semantic ids an agent stands on: floor and rug."""


def _metadata(capture_dir: Path) -> dict:
    path = Path(capture_dir) / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{capture_dir}: no manifest.json (not a capture folder)")
    try:
        return json.loads(path.read_text()).get("metadata") or {}
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc


def is_procedural_capture(capture_dir: str | Path) -> bool:
    """Whether the capture was written by the procedural generator (its house can be regenerated)."""
    return _metadata(Path(capture_dir)).get("generator") == GENERATOR


def procedural_scene_of(capture_dir: str | Path):
    """The house a procedural capture was taken of, regenerated from its recorded config and seed."""
    from image2sim.dataengine.procedural import generate_scene, preset, synth_config_from_dict

    meta = _metadata(Path(capture_dir))
    if meta.get("generator") != GENERATOR or "config" not in meta or "seed" not in meta:
        raise ValueError(
            f"{capture_dir}: not a procedural capture (manifest.json metadata lacks generator "
            f"{GENERATOR!r}, config and seed); the exact renderer needs one written by `image2sim data synth`"
        )
    return generate_scene(synth_config_from_dict(meta["config"], base=preset("default")), int(meta["seed"]))


def exact_render_fn(capture_dir: str | Path, instances: bool = False):
    """A render function ``fn(camera, cam_to_world) -> {"rgb" (H, W, 3) float in [0, 1], "depth"}``
    of the regenerated house (``instances`` adds the instance-id image)."""
    from image2sim.dataengine.procedural.render import render

    scene = procedural_scene_of(capture_dir)

    def fn(camera, pose):
        out = render(scene, camera, np.asarray(pose))
        res = {"rgb": out["rgb"].astype(np.float32) / 255.0, "depth": out["depth"]}
        if instances:
            res["instances"] = out["instances"]
        return res

    return fn


def capture_navigation(capture_dir: str | Path, procedural: bool | None = None, embodiment=None):
    """Navigation map and graph extracted from a capture (procedural captures: floor and rug labels
    are the standable surfaces), as the data engine builds them."""
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.navigation import NavGraph, NavMapConfig, extract_navmap

    if procedural is None:
        procedural = is_procedural_capture(capture_dir)
    labels = FLOOR_LABELS if procedural else ()
    navmap = extract_navmap(open_capture(capture_dir), embodiment, NavMapConfig(floor_labels=labels))
    return navmap, NavGraph.build(navmap)
