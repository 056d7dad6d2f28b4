"""Samples of the rendering benchmark (``render_bench``): held-out targets and their conditions.

* :func:`tier_samples`: the renderer's own degradations of the held-out panoramas at a noise tier
  (:data:`NOISE_TIERS`), the ``degraded`` condition source;
* :func:`splat_samples`: conditions splatted from Gaussians built of the other frames (the
  ``gaussians`` source), with targets from the capture or the exact procedural renderer
  (:func:`exact_targets`); :func:`splat_condition` is the 24-channel condition of one pose;
* :func:`pinhole_faces`: a panorama as six 90-degree pinhole views (the ``pinhole6`` input).

Split from ``render_bench`` (which runs the methods on these samples, scores and reports them).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from image2sim.eval.metrics.timing import measure_fps

__all__ = [
    "INPUT_VIEWS",
    "NOISE_TIERS",
    "RenderBenchError",
    "exact_targets",
    "pinhole_faces",
    "splat_condition",
    "splat_samples",
    "tier_samples",
]

NOISE_TIERS: Mapping[str, Mapping[str, Any]] = {
    # Clean projections: holes only (what splatting a perfect reconstruction leaves).
    "none": {"rgb_noise": 0.0, "depth_noise": 0.0, "hole_fraction": (0.2, 0.5)},
    # The renderer's default degradation (its docstring: the procedural 'middle' tier).
    "middle": {"rgb_noise": 0.05, "depth_noise": 0.02, "hole_fraction": (0.2, 0.5)},
    # Twice the noise and larger holes.
    "high": {"rgb_noise": 0.10, "depth_noise": 0.05, "hole_fraction": (0.35, 0.65)},
}
"""DegradeConfig overrides per noise tier."""

INPUT_VIEWS = ("pano", "pinhole6")
"""What the Gaussians are built from: the panoramas, or six 90° pinhole (cubemap) views of each."""


class RenderBenchError(ValueError):
    """Bad benchmark configuration (message names the field)."""


def tier_samples(held: list, tier: str, seed: int, max_views: int | None) -> list[dict]:
    """Conditions of the held-out targets under one noise tier (the renderer's degradations)."""
    from image2sim.simulator.renderer.data import DegradeConfig, DegradedPanoramaDataset

    n = len(held) if max_views is None else min(len(held), int(max_views))
    dcfg = DegradeConfig(seed=seed, **dict(NOISE_TIERS[tier]))
    ds = DegradedPanoramaDataset(held[:n], n, dcfg)
    return [ds[i] for i in range(n)]


def splat_condition(scene_gaussians: Any, camera: Any, cam_to_world: Any) -> torch.Tensor:
    """The 24-channel condition ``(24, H, W)`` of a Gaussian set splatted at one pose.

    One place for training and evaluation: the renderer's training conditions use the same
    :func:`~image2sim.simulator.renderer.splat_data.gaussians_condition`.
    """
    from image2sim.simulator.renderer.splat_data import gaussians_condition

    return gaussians_condition(scene_gaussians, camera, cam_to_world)


PROCEDURAL_GENERATOR = "image2sim.dataengine.procedural"
"""``metadata.generator`` of procedural captures (their scene can be re-rendered exactly)."""


def exact_targets(
    capture_path: str | Path, poses: Sequence[Any], height: int, width: int
) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
    """Noise-free ``(rgb (3, H, W), depth (1, H, W))`` of a procedural capture's scene at ``poses``
    (camera-to-world), resized like the capture's frames; None when the capture is not procedural.

    The scene is regenerated from the manifest's seed and config (deterministic), then rendered
    without any noise tier: exact colour and depth at exactly the queried pose, which is what a
    simulator asked for that pose should produce. Needs ``image2sim-dataengine``.
    """
    import json

    from image2sim.simulator.renderer.data import resize_target

    manifest = Path(capture_path) / "manifest.json"
    if not manifest.is_file():
        return None
    meta = json.loads(manifest.read_text()).get("metadata") or {}
    if meta.get("generator") != PROCEDURAL_GENERATOR:
        return None
    try:
        from image2sim.dataengine.procedural.capture import make_camera
        from image2sim.dataengine.procedural.config import synth_config_from_dict
        from image2sim.dataengine.procedural.render import render
        from image2sim.dataengine.procedural.scene import generate_scene
    except ImportError as err:
        raise RenderBenchError(
            f"{manifest}: exact targets of a procedural capture need image2sim-dataengine ({err})"
        ) from err
    if "config" not in meta or "seed" not in meta:
        raise RenderBenchError(f"{manifest}: procedural metadata lacks 'config' or 'seed'")
    cfg = synth_config_from_dict(meta["config"])
    scene = generate_scene(cfg, int(meta["seed"]))
    camera = make_camera(cfg)
    out = []
    for pose in poses:
        frame = render(scene, camera, np.asarray(pose, dtype=np.float64))
        out.append(resize_target(frame["rgb"], frame["depth"], height, width))
    return out


def pinhole_faces(frame: Any, face_size: int) -> list[Any]:
    """Six 90° pinhole frames (cubemap faces, :data:`CUBEMAP_FACES` order) of one panorama frame.

    Colour is sampled bilinearly; depth with nearest neighbours (no mixing across depth edges, 0 =
    invalid stays 0) and converted from the panorama's range to the pinhole's z-depth (range times
    the cosine to the optical axis). Face ``k`` has pose ``cam_to_world · R_k`` with ``R_k`` the
    face's :func:`view_rotation` (its right, down, forward axes in the panorama camera frame), and
    camera ``PinholeCamera.from_fov(90, 90, F, F)``, whose rays match the faces' sampling rays.
    """
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
    from image2sim.simulator.geometry.reproject import (
        CUBEMAP_FACES,
        equirect_to_cubemap,
        perspective_directions,
        view_rotation,
    )
    from image2sim.simulator.io.records import Frame

    if not isinstance(frame.camera, EquirectCamera):
        raise RenderBenchError(f"frame {frame.frame_id!r}: pinhole faces need a panorama, got {frame.camera}")
    f = int(face_size)
    rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb)).permute(2, 0, 1)[None].float()
    depth = torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32))[None, None]
    rgb_faces = equirect_to_cubemap(rgb, f)[0]  # (6, 3, F, F)
    range_faces = equirect_to_cubemap(depth, f, mode="nearest")[0, :, 0]  # (6, F, F)
    cos_axis = perspective_directions(90.0, 90.0, f, f, dtype=torch.float32)[..., 2]  # (F, F)
    camera = PinholeCamera.from_fov(90.0, 90.0, f, f)
    pose = np.asarray(frame.cam_to_world, dtype=np.float64)
    out = []
    for k, (name, yaw, pitch) in enumerate(CUBEMAP_FACES):
        rot = view_rotation(
            torch.tensor(math.radians(yaw), dtype=torch.float64),
            torch.tensor(math.radians(pitch), dtype=torch.float64),
        ).numpy()
        face_pose = pose.copy()
        face_pose[:3, :3] = pose[:3, :3] @ rot
        out.append(
            Frame(
                rgb=rgb_faces[k].round().clamp(0, 255).to(torch.uint8).permute(1, 2, 0).numpy(),
                depth=(range_faces[k] * cos_axis).numpy().astype(np.float32),
                camera=camera,
                cam_to_world=face_pose,
                frame_id=f"{frame.frame_id}_{name}",
            )
        )
    return out


def _pinhole_input_scene(path: str | Path, frames: Sequence[int], gcfg: Any) -> Any:
    """Identity Gaussians of the cubemap faces of ``frames`` of a panorama capture.

    Faces are written as a temporary canonical capture (the scene builder reads captures) at the
    panoramas' equatorial angular resolution: face side = half the encoder height (pixels per
    degree of a ``H x 2H`` panorama), rounded to the encoder's multiple of 16.
    """
    import tempfile

    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.io.canonical import write_capture
    from image2sim.simulator.io.registry import open_capture

    face = max(16, int(round(gcfg.encoder.height / 2 / 16)) * 16)
    fcfg = replace(gcfg, encoder=replace(gcfg.encoder, height=face, width=face))
    capture = open_capture(path)
    with tempfile.TemporaryDirectory(prefix="pinhole6-") as tmp:
        faces = [fv for i in frames for fv in pinhole_faces(capture[i], face)]
        cube = write_capture(Path(tmp) / "faces", faces, scene_id=f"{capture.scene_id}-pinhole6")
        return build_scene(cube, fcfg, encoder="identity")


def splat_samples(
    captures: Sequence[str | Path],
    height: int,
    width: int,
    holdout_every: int,
    gaussian_config: str = "tiny",
    max_views: int | None = None,
    start_index: int = 0,
    encoder: str = "identity",
    target: str = "auto",
    input_views: str = "pano",
    source_every: int = 1,
    warmup: int = 1,
    runs: int = 3,
) -> list[dict]:
    """Held-out views of ``captures`` with conditions splatted from Gaussians of the other frames.

    Each sample carries ``condition_seconds``: the median time of splatting its capture's condition
    (after ``warmup`` calls, over ``runs``), which end-to-end FPS adds to a method's time.

    Frame ``k`` (counted over the captures in order, from ``start_index``) is held out when
    ``k % holdout_every == holdout_every - 1``: the split of ``sim train`` / ``sim renderer-eval``.
    Each capture's Gaussians are built (``encoder``: identity or a stage-1 checkpoint) from its own
    non-held-out frames only.
    Targets follow ``target`` (see :attr:`RenderBenchConfig.target`); each sample records its
    ``target_kind`` (``exact`` or ``capture``). With ``input_views="pinhole6"`` the Gaussians are
    built from six 90° pinhole views of each training panorama instead (:func:`pinhole_faces`).
    With ``source_every = n > 1`` only every n-th training frame builds them (a sparse capture).
    """
    if input_views not in INPUT_VIEWS:
        raise RenderBenchError(f"input_views must be one of {list(INPUT_VIEWS)}, got {input_views!r}")
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians.config import load_gaussian_config
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.renderer.data import load_capture_targets
    from image2sim.simulator.renderer.splat_data import holdout_split, source_frames

    gcfg = load_gaussian_config(gaussian_config)
    camera = EquirectCamera(height, width)
    samples: list[dict] = []
    k = start_index
    for path in captures:
        targets = load_capture_targets(path, height, width)
        ((held, train),) = holdout_split([len(targets)], holdout_every, start_index=k)
        base, k = k, k + len(targets)
        if not held:
            continue
        if not train:
            raise RenderBenchError(f"{path}: every frame is held out; no frames left to build Gaussians from")
        sources = source_frames(train, source_every)
        if input_views == "pinhole6":
            scene = _pinhole_input_scene(path, sources, gcfg)
        else:
            scene = build_scene(path, gcfg, encoder=encoder, frames=sources)
        capture = open_capture(path)
        exact = None
        if target != "capture":
            exact = exact_targets(path, [capture[i].cam_to_world for i in held], height, width)
            if exact is None and target == "exact":
                raise RenderBenchError(f"{path}: target 'exact' needs a procedural capture")
        # Splatting is part of every method's frame time: time it once per capture (median after
        # warm-up) so the reported FPS is end to end (splat + network), not the network alone.
        pose0 = capture[held[0]].cam_to_world
        splat_timing = measure_fps(
            lambda g=scene.gaussians, p=pose0: splat_condition(g, camera, p), warmup=warmup, runs=runs
        )
        for j, i in enumerate(held):
            if max_views is not None and len(samples) >= max_views:
                return samples
            rgb, depth = targets[i] if exact is None else exact[j]
            cond = splat_condition(scene.gaussians, camera, capture[i].cam_to_world)
            samples.append(
                {
                    "condition": cond,
                    "target_rgb": rgb,
                    "target_depth": depth,
                    "index": base + i,
                    "condition_seconds": 1.0 / splat_timing.fps,
                    "target_kind": "capture" if exact is None else "exact",
                }
            )
    return samples
