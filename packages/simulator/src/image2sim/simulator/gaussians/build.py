"""Capture -> :class:`GaussianScene`: frame selection, encoding (identity or learned) and fusion.

Learned encoders are stored as ``<name>.safetensors`` (weights) next to ``<name>.json`` (the
:class:`GaussianConfig` they were built with); no pickle anywhere.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from image2sim.simulator.gaussians.config import GaussianConfig, config_to_dict, gaussian_config_from_dict
from image2sim.simulator.gaussians.encoder import GaussianEncoder, identity_gaussians
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.scene import GaussianScene, SceneError
from image2sim.simulator.gaussians.views import keep_best, view_map
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.digest import file_sha256

__all__ = ["save_encoder", "load_encoder", "encoder_file", "build_scene", "nearest_frames", "encode_frames"]


def save_encoder(encoder: GaussianEncoder, path: str | Path) -> Path:
    """Write the encoder's trainable weights (safetensors) and its config (JSON, same stem)."""
    from safetensors.torch import save_file

    path = Path(path).with_suffix(".safetensors")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        k: v.detach().contiguous() for k, v in encoder.state_dict().items() if not k.startswith("semantic.")
    }
    from image2sim.simulator.io.atomic import atomic_path, write_json_atomic

    with atomic_path(path) as tmp:
        save_file(state, str(tmp))
    meta = {"config": config_to_dict(encoder.cfg), "panoramic": encoder.panoramic}
    write_json_atomic(path.with_suffix(".json"), meta)
    return path


def encoder_file(path: str | Path) -> Path:
    """The encoder weights file a checkpoint argument names: the file itself, or the single
    ``.safetensors`` in a folder (``sim train-geometry --out``'s)."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.safetensors"))
        if len(found) != 1:
            raise SceneError(
                f"{path}: expected exactly one encoder .safetensors in the folder, found {len(found)}"
            )
        return found[0]
    return path


def load_encoder(path: str | Path, semantic_model: torch.nn.Module | None = None) -> GaussianEncoder:
    """Inverse of :func:`save_encoder`; the semantic backbone is rebuilt from its config (local weights)."""
    from image2sim.simulator.gaussians.semantic import build_semantic
    from safetensors.torch import load_file

    path = encoder_file(path)
    meta_path = path.with_suffix(".json")
    if not path.is_file() or not meta_path.is_file():
        raise SceneError(f"{path}: encoder checkpoint needs {path.name} and {meta_path.name}")
    meta = json.loads(meta_path.read_text())
    cfg = gaussian_config_from_dict(meta["config"])
    encoder = GaussianEncoder(
        cfg, build_semantic(cfg.semantic, semantic_model), panoramic=bool(meta["panoramic"])
    )
    state = load_file(str(path))
    missing, unexpected = encoder.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("semantic.")]
    if missing or unexpected:
        raise SceneError(
            f"{path}: weights do not match the config (missing {missing[:5]}, unexpected {unexpected[:5]})"
        )
    return encoder.eval()


def nearest_frames(poses: np.ndarray, target: int, k: int) -> list[int]:
    """Indices of the k frames (not ``target``) whose camera centres are nearest to frame ``target``'s."""
    centres = np.asarray(poses)[:, :3, 3]
    d = np.linalg.norm(centres - centres[target], axis=1)
    d[target] = np.inf
    order = np.argsort(d, kind="stable")
    return [int(i) for i in order[: min(k, len(order) - 1)]]


def encode_frames(frames, cfg: GaussianConfig, encoder: GaussianEncoder | None):
    """Per-frame Gaussian sets (identity when ``encoder`` is None) for a list of FrameInputs."""
    if encoder is None:
        return [identity_gaussians(f, cfg) for f in frames]
    with torch.no_grad():
        return encoder(frames)


def _in_order(pool: ThreadPoolExecutor, fn, items, window: int):
    """``map(fn, items)`` over ``pool`` with at most ``window`` results computed ahead of the consumer
    (``Executor.map`` submits everything at once and would hold every frame's Gaussians)."""
    items = iter(items)
    ahead: deque = deque(pool.submit(fn, x) for x in itertools.islice(items, window))
    while ahead:
        result = ahead.popleft().result()
        for x in itertools.islice(items, 1):
            ahead.append(pool.submit(fn, x))
        yield result


def build_scene(
    capture_path: str | Path,
    cfg: GaussianConfig,
    encoder: str | Path | GaussianEncoder = "identity",
    frames: Sequence[int] | None = None,
    progress: bool = False,
    fuse_every: int = 8,
    workers: int = 1,
) -> GaussianScene:
    """Open a capture (any format ``open_capture`` reads), encode the chosen frames and fuse them.

    ``fuse_every`` frames are fused into memory in one pass (1: frame by frame, the incremental
    MemoryState; larger: fewer passes over the growing scene, much faster for long captures).
    ``workers`` > 1 reads, encodes and best-view-selects that many frames at once on threads (torch
    releases the GIL in its ops; each frame is independent given every frame's view map); fusion
    stays in frame order, so the scene is the same as with one.

    Frames are area-resized to ``encoder.height x encoder.width`` of the config (a learned encoder:
    of its checkpoint's config). ``info`` (the manifest) records that resolution and where it came
    from (``encoding``), the encoded camera (``camera``) and the capture's own camera
    (``source.camera``), which ``sim render`` uses by default.
    """
    if fuse_every < 1:
        raise ValueError(f"build_scene: fuse_every must be >= 1, got {fuse_every}")
    from image2sim.simulator.io.registry import open_capture

    capture = open_capture(capture_path)
    indices = list(range(len(capture))) if frames is None else [int(i) for i in frames]
    for i in indices:
        if not 0 <= i < len(capture):
            raise SceneError(
                f"{capture_path}: frame index {i} out of range (capture has {len(capture)} frames)"
            )
    if not indices:
        raise SceneError(f"{capture_path}: no frames selected")
    enc_info: dict = {"kind": "identity", "checkpoint": None, "sha256": None}
    net = None
    if isinstance(encoder, GaussianEncoder):
        net, enc_info = encoder.eval(), {"kind": "learned", "checkpoint": None, "sha256": None}
    elif str(encoder) != "identity":
        net = load_encoder(encoder)
        weights = file_sha256(encoder_file(encoder))
        enc_info = {"kind": "learned", "checkpoint": str(Path(encoder).resolve()), "sha256": weights}
    if net is not None:
        # The checkpoint brings its encoder (sizes, heads); fusion is a scene-building choice from cfg.
        cfg = dataclasses.replace(net.cfg, fusion=cfg.fusion)
    h, w = cfg.encoder.height, cfg.encoder.width
    where = f"config {cfg.name!r}" if net is None else "the encoder checkpoint's config"
    encoding = {"height": h, "width": w, "from": f"encoder.height, encoder.width of {where}"}
    scene = GaussianScene(fusion=cfg.fusion)
    camera = None
    source_camera = capture.camera
    it = indices
    if progress:
        from rich.progress import track

        it = track(indices, description=f"encoding {len(indices)} frames at {w}x{h}")
    views = None
    if workers < 1:
        raise ValueError(f"build_scene: workers must be >= 1, got {workers}")
    pool = ThreadPoolExecutor(workers) if workers > 1 else None

    def run(fn, items):
        return map(fn, items) if pool is None else _in_order(pool, fn, items, 2 * workers)

    try:
        if cfg.fusion.views == "best" and len(indices) > 1:
            # First pass: every frame's depth and sampling intervals, so that each frame's Gaussians
            # can be tested against all the others before anything is fused.
            def view_of(i):
                return view_map(prepare_frame(capture[i], h, w, cfg.fusion.edge_tolerance), cfg.fusion)

            views = list(run(view_of, indices))

        def encoded(k_i):
            k, i = k_i
            frame = capture[i]
            inputs = prepare_frame(frame, h, w, cfg.fusion.edge_tolerance)
            if net is not None and isinstance(inputs.camera, EquirectCamera) != net.panoramic:
                raise SceneError(
                    f"{capture_path}: frame {i} camera does not match the encoder (panoramic={net.panoramic})"
                )
            g = encode_frames([inputs], cfg, net)[0]
            if views is not None:
                g = keep_best(g, k, views, cfg.fusion)
            return frame.camera, inputs, g

        pending = []
        for i, (frame_camera, inputs, g) in zip(it, run(encoded, enumerate(indices)), strict=True):
            source_camera = source_camera or frame_camera
            camera = camera or inputs.camera
            pending.append(g)
            scene.record_frame(inputs.frame_id, i, inputs.cam_to_world)
            if len(pending) >= fuse_every:
                scene.integrate_many(pending)
                pending = []
        scene.integrate_many(pending)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    scene.info = {
        "source": {
            "capture": str(Path(capture_path).resolve()),
            "format": capture.format,
            "scene_id": capture.scene_id,
            "num_frames": len(capture),
            "camera": source_camera.to_dict() if source_camera is not None else None,
        },
        "encoder": enc_info,
        "camera": camera.to_dict() if camera is not None else None,
        "encoding": encoding,
        "config": config_to_dict(cfg),
    }
    return scene
