"""Recognition views: what the agent sees in a procedural house, with the category of every pixel.

The paper's policy sees through a pretrained Qwen3-VL, which already knows what a sofa looks like.
Ours is tiny and starts from scratch, so a from-scratch vision tower never learns the categories the
instructions name (docs/sim2real.md). These views are the data of a recognition pretraining of that
tower (``image2sim nav pretrain-vision``): the agent's own pinhole view (eye height, upright, a
random heading) from random nodes of the navigation graph, rendered exactly, with the category id of
every pixel from the generator's ground truth.

Layout of ``data views --out OUT``: ``OUT/views/<scene>.npz`` (``rgb`` (N, S, S, 3) uint8,
``semantics`` (N, S, S) int16 category ids, 0 = nothing hit; ``positions`` (N, 3) map-frame feet
positions, ``headings`` (N,)), ``OUT/categories.json`` (the id -> name table) and
``OUT/manifest.json`` (format, size, field of view, seed, scenes). Each scene file is written
atomically and an existing one is kept, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import io
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from image2sim.dataengine.seeding import named_rng

__all__ = ["VIEWS_FORMAT", "ViewsConfig", "render_views", "write_views", "load_views"]

VIEWS_FORMAT = "image2sim-views"


@dataclass(frozen=True)
class ViewsConfig:
    """How many views of each house, and the camera (match the policy's observation)."""

    per_scene: int = 400
    """Views per house."""
    size: int = 64
    """Square image side in pixels (the policy's observation size)."""
    hfov_deg: float = 90.0
    """Horizontal (= vertical) field of view in degrees (the policy's pinhole camera)."""
    seed: int = 0
    """Base seed; each house draws from its own stream (seed, house name)."""

    def validate(self) -> ViewsConfig:
        if self.per_scene < 1:
            raise ValueError(f"views: per_scene must be >= 1, got {self.per_scene}")
        if self.size < 8:
            raise ValueError(f"views: size must be >= 8 pixels, got {self.size}")
        if not 0 < self.hfov_deg < 180:
            raise ValueError(f"views: hfov_deg must lie in (0, 180), got {self.hfov_deg}")
        return self


def render_views(capture_dir: str | Path, config: ViewsConfig) -> dict[str, np.ndarray]:
    """``config.per_scene`` random agent views of one procedural capture's house (module docstring)."""
    from image2sim.dataengine.procedural.exact import capture_navigation, procedural_scene_of
    from image2sim.dataengine.procedural.render import render
    from image2sim.simulator.sim import NeuralSimulator, ObservationSpec

    cfg = config.validate()
    scene = procedural_scene_of(capture_dir)  # raises a clear error for a non-procedural capture

    def render_fn(camera, pose):
        out = render(scene, camera, np.asarray(pose))
        return {"rgb": out["rgb"], "semantics": out["semantics"]}

    navmap, graph = capture_navigation(capture_dir, procedural=True)
    if graph.num_nodes == 0:
        raise ValueError(f"{capture_dir}: the navigation graph is empty, so there is no pose to view from")
    main = graph.largest_component_nodes  # where episodes start
    spec = ObservationSpec(panorama=False, pinhole=True, pinhole_size=cfg.size, pinhole_hfov_deg=cfg.hfov_deg)
    sim = NeuralSimulator(navmap, graph, render_fn, spec)
    rng = named_rng(cfg.seed, Path(capture_dir).name)
    nodes = graph.nodes[rng.choice(main, size=cfg.per_scene)]
    headings = rng.uniform(-np.pi, np.pi, size=cfg.per_scene)
    rgb = np.empty((cfg.per_scene, cfg.size, cfg.size, 3), np.uint8)
    sem = np.empty((cfg.per_scene, cfg.size, cfg.size), np.int16)
    for i, (p, h) in enumerate(zip(nodes, headings, strict=True)):
        obs, _ = sim.reset(p[None], np.array([h]))
        rgb[i] = obs[0]["pinhole"]["rgb"]
        sem[i] = obs[0]["pinhole"]["semantics"]
    return {"rgb": rgb, "semantics": sem, "positions": nodes.astype(np.float64), "headings": headings}


def write_views(scene_dirs, out: str | Path, config: ViewsConfig, progress: bool = False) -> dict:
    """Render the views of every capture in ``scene_dirs`` into ``out`` (module docstring); returns
    the manifest. Houses whose file exists are kept (resume); the manifest and the category table
    are rewritten atomically at the end."""
    from image2sim.dataengine.procedural.objects import category_table
    from image2sim.simulator.io.atomic import write_bytes_atomic, write_json_atomic

    cfg = config.validate()
    out = Path(out)
    folder = out / "views"
    folder.mkdir(parents=True, exist_ok=True)
    manifest_path = out / "manifest.json"
    if manifest_path.is_file():
        old = json.loads(manifest_path.read_text())
        if old.get("config") != asdict(cfg):
            raise ValueError(
                f"{manifest_path}: written with {old.get('config')}, now asked for {asdict(cfg)}; "
                "use another --out or delete the folder"
            )
    dirs = [Path(d) for d in scene_dirs]
    if not dirs:
        raise ValueError("views: no capture folders given")
    names = [d.name for d in dirs]
    if len(set(names)) != len(names):
        raise ValueError(f"views: capture folder names must be unique (they name the files), got {names}")
    iterator = dirs
    if progress:
        from rich.progress import track

        iterator = track(dirs, description="rendering recognition views")
    counts = {}
    for d in iterator:
        path = folder / f"{d.name}.npz"
        if not path.is_file():
            buf = io.BytesIO()
            np.savez_compressed(buf, **render_views(d, cfg))
            write_bytes_atomic(path, buf.getvalue())
        counts[d.name] = cfg.per_scene
    write_json_atomic(out / "categories.json", {"categories": category_table()})
    manifest = {"format": VIEWS_FORMAT, "version": 1, "config": asdict(cfg), "scenes": counts}
    write_json_atomic(manifest_path, manifest)
    return manifest


def load_views(folder: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(rgb (N, S, S, 3) uint8, semantics (N, S, S) int16, manifest) of a ``data views`` folder, the
    houses in the manifest's order."""
    folder = Path(folder)
    path = folder / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{folder}: no manifest.json (not a `image2sim data views` folder)")
    manifest = json.loads(path.read_text())
    if manifest.get("format") != VIEWS_FORMAT:
        raise ValueError(f"{path}: format is {manifest.get('format')!r}, expected {VIEWS_FORMAT!r}")
    rgb, sem = [], []
    for name in manifest["scenes"]:
        with np.load(folder / "views" / f"{name}.npz", allow_pickle=False) as z:
            if z["rgb"].shape[:3] != z["semantics"].shape:
                raise ValueError(
                    f"{folder}/views/{name}.npz: rgb {z['rgb'].shape} and semantics "
                    f"{z['semantics'].shape} disagree"
                )
            rgb.append(z["rgb"])
            sem.append(z["semantics"])
    if not rgb:
        raise ValueError(f"{path}: lists no houses")
    return np.concatenate(rgb), np.concatenate(sem), manifest
