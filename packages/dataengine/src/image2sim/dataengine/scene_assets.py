"""The assets of one scene for the data engine: where its files are, its navigation map and graph, its
object database and the render function its observations come from.

Each is taken from the scene folder when it holds it, else from this run's cache
(``{out}/scenes/{name}/``), else from the content-keyed asset cache shared across runs, else built
from the capture and stored in both (:mod:`.asset_cache`). :mod:`.pipeline` runs the task on them.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from image2sim.dataengine.mining import MiningConfig
from image2sim.simulator.config import config_from_dict
from image2sim.simulator.io.paths import resolve_from_file

if TYPE_CHECKING:
    from image2sim.dataengine.engine_config import EngineConfig

DETECTORS = ("gt", "yolo-world", "annotations", "none")


@dataclass
class SceneInputs:
    """Resolved inputs of one scene."""

    name: str
    scene_id: str
    capture_dir: Path
    scene_dir: Path
    """The folder given on the command line (capture or built scene)."""
    procedural: bool
    gaussian_dir: Path | None


def scene_name(path: Path) -> str:
    return Path(path).name


def resolve_scene(path: str | Path) -> SceneInputs:
    """Identify a capture folder or a built scene folder (see the module docstring)."""
    path = Path(path)
    man_path = path / "manifest.json"
    if not man_path.is_file():  # a capture of another format, read in place
        from image2sim.simulator.io.registry import open_capture

        cap = open_capture(path)  # raises CaptureError naming the folder when no reader knows it
        return SceneInputs(path.name, str(cap.scene_id or path.name), path, path, False, None)
    man = json.loads(man_path.read_text())
    gaussian_dir = None
    if (path / "gaussians.safetensors").is_file():
        src = (man.get("source") or {}).get("capture")
        # Relative to the manifest (relocatable scene folders), or absolute (older scenes).
        capture_dir = resolve_from_file(src, man_path) if src else None
        if capture_dir is None or not (capture_dir / "manifest.json").is_file():
            raise FileNotFoundError(
                f"{man_path}: field 'source.capture' ({src!r}) does not point at a capture"
            )
        gaussian_dir = path
        man = json.loads((capture_dir / "manifest.json").read_text())
    else:
        capture_dir = path
    meta = man.get("metadata") or {}
    procedural = meta.get("generator") == "image2sim.dataengine.procedural"
    return SceneInputs(
        path.name, str(man.get("scene_id") or path.name), capture_dir, path, procedural, gaussian_dir
    )


# ---------------------------------------------------------------------------------------- assets


def scene_navigation(inputs: SceneInputs, cache: Path, asset_cache: str | None = None):
    """The scene's map and graph: a built scene's own, else this run's (``cache``), else copied from
    the content-keyed ``asset_cache``, else extracted from the capture (and stored in both)."""
    from image2sim.dataengine.asset_cache import cached, content_key
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.navigation.graph import NavGraph

    folder = inputs.scene_dir
    if (folder / "navmap.npz").is_file() and (folder / "navgraph.npz").is_file():
        return NavMap.load(folder / "navmap.npz"), NavGraph.load(folder / "navgraph.npz")

    def build() -> None:
        from image2sim.dataengine.procedural.exact import capture_navigation

        navmap, graph = capture_navigation(inputs.capture_dir, inputs.procedural)
        navmap.save(cache / "navmap.npz")
        graph.save(cache / "navgraph.npz")

    def key() -> str:
        return content_key(inputs.capture_dir, "navigation", f"procedural={inputs.procedural}")

    cached(asset_cache, key, ["navmap.npz", "navgraph.npz"], cache, build)
    return NavMap.load(cache / "navmap.npz"), NavGraph.load(cache / "navgraph.npz")


def scene_objects(inputs: SceneInputs, cache: Path, cfg: EngineConfig):
    """The scene's object database: the scene folder's or this run's ``objects.json``, else mined
    from the capture with ``cfg.detector`` (``none``: no objects) and stored in ``cache``."""
    from image2sim.dataengine import mining

    for folder in (inputs.scene_dir, cache):
        if (folder / "objects.json").is_file():
            try:
                return mining.load_objects(folder / "objects.json")
            except ValueError:
                if folder == inputs.scene_dir:
                    continue  # a foreign objects.json (e.g. a GT file): mine our own
                raise
    if cfg.detector == "none":
        return []
    if cfg.detector == "annotations":
        from image2sim.dataengine.objects_file import load_objects_file, objects_file_for

        objs = load_objects_file(objects_file_for(cfg.objects, inputs.name, inputs.capture_dir))
        mining.save_objects(cache / "objects.json", objs, {"detector": "annotations"})
        return objs
    from image2sim.simulator.io.registry import open_capture

    mcfg = config_from_dict(MiningConfig, cfg.mining, "mining")
    cap = open_capture(inputs.capture_dir)
    small: set[str] = set()
    if cfg.detector == "gt":
        cats, small = mining.load_categories(inputs.capture_dir)
        det = mining.GTDetector(cats)
    elif cfg.detector == "yolo-world":
        if not cfg.detector_weights:
            raise ValueError("detector yolo-world needs detector_weights (a local file)")
        if (inputs.capture_dir / "gt" / "categories.json").is_file():
            cats, small = mining.load_categories(inputs.capture_dir)
            vocab = sorted(set(cats.values()) - {"floor", "wall", "ceiling", "rug"})
        else:
            vocab, small = list(mining.DEFAULT_VOCABULARY), set(mining.DEFAULT_SMALL)
        det = mining.YoloWorldDetector(cfg.detector_weights, vocab)
    else:
        raise ValueError(f"unknown detector {cfg.detector!r}; known: {DETECTORS}")
    objs, stats = mining.mine_capture(cap, det, mcfg, small)
    mining.attach_gt_metadata(objs, inputs.capture_dir)
    mining.save_objects(
        cache / "objects.json", objs, {"detector": det.name, "stats": stats, "config": asdict(mcfg)}
    )
    return objs


def scene_gaussians(
    inputs: SceneInputs,
    cache: Path,
    asset_cache: str | None = None,
    gaussians: dict | None = None,
    workers: int = 1,
    refine_steps: int = 0,
) -> Path:
    """The folder of the scene's Gaussians: a built scene's own, else this run's (``cache``), else
    copied from the content-keyed ``asset_cache``, else built from the capture with the identity
    encoder and ``gaussians`` (plain data over a preset; None or empty: ``tiny``; ``workers``
    frames at a time), refined ``refine_steps`` steps against the capture (0: feed-forward; -1:
    :func:`~image2sim.simulator.gaussians.refine.default_refine_steps`), and stored."""
    if inputs.gaussian_dir is not None:
        return inputs.gaussian_dir
    from image2sim.dataengine.asset_cache import cached, content_key
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians.config import config_to_dict, gaussian_config_from_dict

    folder = cache / "gaussians"
    # The key names the whole Gaussian config, so a cache built under other fusion settings
    # (e.g. before best-view selection) is never reused.
    gcfg = gaussian_config_from_dict(gaussians or {})
    config = json.dumps(config_to_dict(gcfg), sort_keys=True)
    refined = f" refine {refine_steps}" if refine_steps else ""  # feed-forward keys stay as they were

    def build() -> None:
        scene = build_scene(inputs.capture_dir, gcfg, encoder="identity", workers=workers)
        if refine_steps:
            from image2sim.simulator.gaussians.refine import refine_scene_steps
            from image2sim.simulator.io.registry import open_capture

            refine_scene_steps(scene, open_capture(inputs.capture_dir), refine_steps)
        scene.save(folder, overwrite=True)

    cached(
        asset_cache,
        lambda: content_key(inputs.capture_dir, "gaussians", f"identity {config}{refined}"),
        ["gaussians"],
        cache,
        build,
    )
    return folder


def scene_render_fn(
    inputs: SceneInputs,
    cache: Path,
    mode: str,
    renderer: str | None = None,
    asset_cache: str | None = None,
    device: str = "cpu",
    gaussians: dict | None = None,
    refine_steps: int = 0,
):
    """(render function or None, mode actually used). ``device``: where Gaussian scenes render (cpu or
    cuda); the exact procedural renderer always runs on the CPU. ``gaussians``, ``refine_steps``: the
    Gaussian config of scenes built from a capture (plain data over a preset; None or empty: ``tiny``)
    and their refinement (:func:`scene_gaussians`)."""
    if renderer is not None and mode == "auto":
        mode = "gaussians"
    if mode == "auto":
        mode = "gaussians"  # training data comes from the neural simulator unless asked otherwise
    if mode == "none":
        return None, mode
    if mode == "procedural":
        if not inputs.procedural:
            raise ValueError(f"{inputs.capture_dir}: render=procedural needs a procedural capture")
        from image2sim.dataengine.procedural.exact import exact_render_fn

        return exact_render_fn(inputs.capture_dir, instances=True), mode
    from image2sim.simulator.gaussians import GaussianScene
    from image2sim.simulator.sim import gaussian_render_fn

    g = GaussianScene.load(
        scene_gaussians(inputs, cache, asset_cache, gaussians, refine_steps=refine_steps)
    ).gaussians
    # Panoramic with a renderer: the simulator cuts the pinhole / ultra-wide views out of the panorama.
    fn = gaussian_render_fn(g, renderer, device=device)
    return fn, ("gaussians+pixel-flow" if renderer is not None else mode)
