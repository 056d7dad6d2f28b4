"""Feed-forward feature-Gaussian scene construction (paper appendix, Stage 1).

Public API::

    from image2sim.simulator.gaussians import tiny, build_scene, GaussianScene
    scene = build_scene("captures/scene_000", tiny(), encoder="identity")   # or a trained checkpoint
    scene.save("scenes/scene_000"); scene.export_ply("scenes/scene_000.ply")
    out = GaussianScene.load("scenes/scene_000").render(camera, cam_to_world)

CLI: ``image2sim sim build-scene <capture> --encoder identity --out <scene>`` and
``image2sim sim render <scene> --frame 3 --out pano.png``.
"""

import importlib

_EXPORTS = {
    "config": (
        "GaussianConfig",
        "SemanticConfig",
        "EncoderConfig",
        "FusionConfig",
        "Stage1Config",
        "ConfigError",
        "tiny",
        "paper",
        "PRESETS",
        "gaussian_config_from_dict",
        "load_gaussian_config",
        "config_to_dict",
    ),
    "primitives": ("GaussianSet", "FrameInputs"),
    "frames": ("prepare_frame", "pixel_footprint", "resize_rgbd", "world_points"),
    "encoder": (
        "GaussianEncoder",
        "DetailEncoder",
        "FeatureUpsampler",
        "GaussianHeads",
        "identity_gaussians",
        "encoder_inputs",
    ),
    "semantic": ("DinoV3Backbone", "build_semantic"),
    "fusion": ("fuse", "prune", "assign_levels", "cell_sizes"),
    "scene": ("GaussianScene", "SceneError"),
    "condition": ("scene_condition",),
    "build": ("build_scene", "save_encoder", "load_encoder", "nearest_frames", "encode_frames"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    # Lazy: `image2sim --help` and config-only users should not import torch modules.
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
