"""Procedural indoor scenes with exact ground truth: the embedded default data source.

Public API::

    from image2sim.dataengine.procedural import preset, generate_scene, render, write_scene
    scene = generate_scene(preset("tiny"), seed=0)          # plan, objects, navigable grid, materials
    out = render(scene, camera, cam_to_world)                # rgb, depth, semantics, instances
    write_scene(scene, "data/synthetic/scene_000")           # canonical capture + gt/

CLI: ``image2sim data synth --scenes 8 --views 24 --noise none --seed 0 --out data/synthetic``.
"""

import importlib

# Lazy exports: `image2sim data --help` imports this package's CLI without loading numpy/torch/scipy.
_EXPORTS = {
    "capture": (
        "Viewpoint",
        "capture_frames",
        "make_camera",
        "pose_matrix",
        "sample_viewpoints",
        "scene_seed",
        "synthesize",
        "write_scene",
    ),
    "config": (
        "NOISE_TIERS",
        "PRESETS",
        "CaptureConfig",
        "ConfigError",
        "LayoutConfig",
        "NoiseConfig",
        "ObjectConfig",
        "SynthConfig",
        "preset",
        "synth_config_from_dict",
    ),
    "objects": ("CATEGORIES", "CATEGORY_BY_NAME", "STRUCTURE_CATEGORIES", "WALKABLE_CATEGORY_IDS"),
    "render": ("render",),
    "scene": ("ProceduralScene", "generate_scene"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
