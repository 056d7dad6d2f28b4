"""Renderer training pairs from REAL splats: (splat of the other frames' Gaussians at a pose, frame).

What the paper trains on: for a target frame of a capture, the condition C_p is the projection of
the scene's Gaussians at the target pose, where the scene is built WITHOUT the target frame, so the
renderer learns to fill exactly the holes and artefacts a held-out view has.

Leave-target-out construction (why not "fuse once and drop the target's Gaussians"): fusion
voxel-averages Gaussians of all frames into shared cells, so after fusion a cell mixes the target's
observation with the others' and there is no per-frame index left to remove. Dropping the target
before fusion is the only exact way. It is also cheap: every training frame is *encoded* once
(identity Gaussians, per-frame sets kept in memory), and per target only the fusion of the other
frames' sets is redone, with ``fuse_every`` frames per pass (the batched fusion of
``build-scene --fuse-every``). With ``neighbours = k > 0`` only the k nearest other training frames
(by camera centre) are fused, which bounds the cost on long captures. The held-out frames of the
capture (the split of ``sim train`` / ``eval render``) never enter any scene, so the training
conditions look like the evaluation ones: eval splats ALL training frames at a held-out pose,
training splats all training frames but one at that one's pose.

Conditions are cached per capture as safetensors under ``cache_dir``; the file name is a hash of
the capture content (manifest bytes when the capture has one, poses and the resized target
images), the Gaussian config, the renderer resolution, the target and source lists and this
module's format version, so a second run with the same inputs loads instead of rebuilding, and any
change rebuilds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

__all__ = [
    "SplatDataConfig",
    "SplatDataError",
    "splat_data_config_from_dict",
    "holdout_split",
    "source_frames",
    "gaussians_condition",
    "encode_capture",
    "leave_one_out_gaussians",
    "capture_conditions",
    "conditions_cache_key",
    "SplatConditionDataset",
    "TRAINING_RECORD",
    "training_record",
    "write_training_record",
    "find_training_record",
    "protocol_mismatches",
]

TRAINING_RECORD = "training_data.json"
"""File name of a run's record of its training conditions, next to ``config.json`` in the run
folder (``sim train --out``)."""

CACHE_VERSION = 2
"""Bumped whenever the cached conditions would change for the same inputs."""


class SplatDataError(ValueError):
    """Bad splat-data configuration or capture (the message names the field / file)."""


@dataclass
class SplatDataConfig:
    """How splatted training conditions are built."""

    gaussian_config: str = "tiny"
    """Gaussian preset name or YAML file (the identity encoder's sizes; fusion settings come from it)."""
    encoder: str = "identity"
    """``identity`` (pixel colours, no features) or a stage-1 encoder checkpoint (``sim
    train-geometry``'s ``encoder.safetensors`` or its folder): its feature Gaussians, whose 16
    feature channels reach the renderer's condition (the paper's semantic grounding path)."""
    holdout_every: int = 8
    """Every n-th frame (counted over all captures in order) is held out: never a target, never a
    source (0: none held out). Same split as ``sim train --holdout-every`` and ``eval render``."""
    neighbours: int = 0
    """Sources per target: 0 = all other source frames of the capture; k > 0 = the k nearest."""
    source_every: int = 1
    """Only every n-th training frame is a source (its Gaussians enter the scenes); every training
    frame is still a target. 1 = a dense capture (all training frames are sources); n > 1 = a sparse
    capture with holes and disocclusions, the regime the renderer is for. Same rule as
    ``eval render --source-every`` (:func:`source_frames`)."""
    fuse_every: int = 8
    """Frames fused per pass when building a target's scene (1 = frame by frame)."""
    degraded_fraction: float = 0.0
    """Fraction of the dataset made of synthetic degradations of the training targets (0: none)."""
    degraded_seed: int = 0
    """Seed of those degradations."""
    cache_dir: str | None = None
    """Folder of the per-capture condition caches (None: no cache)."""
    max_frames: int | None = None
    """Use at most this many frames per capture (None: all)."""

    def validate(self) -> SplatDataConfig:
        if self.holdout_every < 0:
            raise SplatDataError(f"holdout_every must be >= 0, got {self.holdout_every}")
        if self.neighbours < 0:
            raise SplatDataError(f"neighbours must be >= 0, got {self.neighbours}")
        if self.source_every < 1:
            raise SplatDataError(f"source_every must be >= 1, got {self.source_every}")
        if self.fuse_every < 1:
            raise SplatDataError(f"fuse_every must be >= 1, got {self.fuse_every}")
        if not 0.0 <= self.degraded_fraction < 1.0:
            raise SplatDataError(f"degraded_fraction must be in [0, 1), got {self.degraded_fraction}")
        if self.max_frames is not None and self.max_frames < 1:
            raise SplatDataError(f"max_frames must be >= 1 or None, got {self.max_frames}")
        return self


def splat_data_config_from_dict(data: dict[str, Any]) -> SplatDataConfig:
    """Build a :class:`SplatDataConfig` from a mapping; unknown keys are an error."""
    known = {f.name for f in dataclasses.fields(SplatDataConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SplatDataError(f"splat data config: unknown key(s) {unknown}; known: {sorted(known)}")
    return SplatDataConfig(**data).validate()


def holdout_split(
    lengths: Sequence[int], holdout_every: int, start_index: int = 0
) -> list[tuple[list[int], list[int]]]:
    """Per capture ``(held_out, training)`` frame indices for captures of ``lengths`` frames.

    Frame ``i`` of a capture whose first frame has global index ``k`` is held out when
    ``(k + i) % holdout_every == holdout_every - 1`` (global counting over the captures in order):
    the split of ``sim train`` (``renderer.cli._split``) and ``eval render``.
    """
    out, k = [], int(start_index)
    for n in lengths:
        held = [i for i in range(n) if holdout_every and (k + i) % holdout_every == holdout_every - 1]
        hs = set(held)
        out.append((held, [i for i in range(n) if i not in hs]))
        k += n
    return out


def source_frames(train: Sequence[int], source_every: int) -> list[int]:
    """The training frames whose Gaussians build the scenes: every ``source_every``-th of ``train``
    (in order, from the first). One rule for training conditions and evaluation."""
    if source_every < 1:
        raise SplatDataError(f"source_every must be >= 1, got {source_every}")
    return [int(i) for i in list(train)[::source_every]]


def gaussians_condition(gaussians: Any, camera: Any, cam_to_world: Any) -> torch.Tensor:
    """The 24-channel condition ``(24, H, W)`` of a Gaussian set splatted at one pose.

    Expected colour / range come from :func:`~image2sim.simulator.renderer.condition.unpremultiply`;
    features are the set's when it carries the renderer's 16 channels, else zeros (identity
    Gaussians carry none).
    """
    from image2sim.simulator.renderer.condition import build_condition, unpremultiply
    from image2sim.simulator.renderer.config import CONDITION_FEATURES
    from image2sim.simulator.splatting import splat

    g = gaussians
    pose = torch.as_tensor(np.asarray(cam_to_world), dtype=g.means.dtype)
    feats = g.features if g.features is not None and g.features.shape[-1] == CONDITION_FEATURES else None
    with torch.no_grad():
        out = splat(g.means, g.scales, g.quats, g.opacities, g.colors, feats, camera, pose, background=0.0)
    rgb, depth = unpremultiply(out.rgb, out.depth, out.alpha, background=0.0)
    f = (
        out.features
        if feats is not None
        else rgb.new_zeros(rgb.shape[0], CONDITION_FEATURES, *rgb.shape[-2:])
    )
    return build_condition(
        f.float(), rgb.float(), depth.float(), out.alpha.float(), camera.ray_map(torch.float32)
    )[0]


def encode_capture(
    capture: Any, indices: Sequence[int], gcfg: Any, encoder: Any = None
) -> tuple[dict[int, Any], dict[int, Any]]:
    """Gaussians of the given frames of an open capture, ``{frame index: GaussianSet}`` (identity,
    or ``encoder``'s feature Gaussians at its own resolution), and with ``fusion.views: best`` their
    view maps (``{frame index: ViewMap}``; empty otherwise)."""
    from image2sim.simulator.gaussians.build import encode_frames
    from image2sim.simulator.gaussians.frames import prepare_frame
    from image2sim.simulator.gaussians.views import view_map

    ecfg = gcfg if encoder is None else dataclasses.replace(encoder.cfg, fusion=gcfg.fusion)
    h, w = ecfg.encoder.height, ecfg.encoder.width
    sets, views = {}, {}
    for i in indices:
        inputs = prepare_frame(capture[i], h, w, gcfg.fusion.edge_tolerance)
        sets[int(i)] = encode_frames([inputs], ecfg, encoder)[0]
        if gcfg.fusion.views == "best":
            views[int(i)] = view_map(inputs, gcfg.fusion)
    return sets, views


def leave_one_out_gaussians(
    sets: dict[int, Any],
    sources: Sequence[int],
    fusion: Any,
    fuse_every: int,
    views: dict[int, Any] | None = None,
) -> Any:
    """Fuse ``sets[i]`` for ``i in sources`` (in that order, ``fuse_every`` per pass) into one scene
    memory, exactly as ``build_scene(frames=sources, fuse_every=...)`` would (with ``views``, each
    source first keeps only what no other source sees better); returns the fused set."""
    from image2sim.simulator.gaussians.scene import GaussianScene
    from image2sim.simulator.gaussians.views import select_best_views

    if not sources:
        raise SplatDataError("leave_one_out_gaussians: no source frames")
    scene = GaussianScene(fusion=fusion)
    order = list(sources)
    chosen = [sets[i] for i in order]
    if views and fusion.views == "best" and len(order) > 1:
        chosen = select_best_views(chosen, [views[i] for i in order], fusion)
    for s in range(0, len(order), fuse_every):
        scene.integrate_many(chosen[s : s + fuse_every])
    if scene.gaussians is None or not len(scene.gaussians):
        raise SplatDataError(f"sources {order}: fusion left no Gaussians (all depth invalid?)")
    return scene.gaussians


def _sources_for(
    target: int, sources: Sequence[int], poses: dict[int, np.ndarray], neighbours: int
) -> list[int]:
    others = [i for i in sources if i != target]
    if neighbours <= 0 or neighbours >= len(others):
        return others
    centres = np.stack([np.asarray(poses[i])[:3, 3] for i in others])
    d = np.linalg.norm(centres - np.asarray(poses[target])[:3, 3], axis=1)
    keep = sorted(int(others[j]) for j in np.argsort(d, kind="stable")[:neighbours])
    return keep


def conditions_cache_key(
    capture_path: str | Path,
    targets: Sequence[tuple[torch.Tensor, torch.Tensor]],
    poses: Sequence[np.ndarray],
    gcfg_dict: dict,
    height: int,
    width: int,
    target_list: Sequence[int],
    sources: Sequence[Sequence[int]],
    fuse_every: int,
    encoder: str = "identity",
) -> str:
    """Hex digest identifying one capture's conditions (content, config, encoder, resolution,
    targets); ``encoder`` is :func:`encoder_digest` of the encoder used."""
    h = hashlib.sha256()
    manifest = Path(capture_path) / "manifest.json"
    if manifest.is_file():
        h.update(manifest.read_bytes())
    for rgb, depth in targets:
        h.update(rgb.numpy().tobytes())
        h.update(depth.numpy().tobytes())
    for p in poses:
        h.update(np.asarray(p, dtype=np.float64).tobytes())
    meta = {
        "version": CACHE_VERSION,
        "encoder": encoder,
        "gaussians": gcfg_dict,
        "resolution": [int(height), int(width)],
        "targets": [int(t) for t in target_list],
        "sources": [[int(s) for s in src] for src in sources],
        "fuse_every": int(fuse_every),
    }
    h.update(json.dumps(meta, sort_keys=True).encode())
    return h.hexdigest()[:24]


def _encoder(spec: str):
    """None for ``identity``, else the stage-1 encoder loaded from ``spec`` (a file or its folder)."""
    if spec == "identity":
        return None
    from image2sim.simulator.gaussians.build import load_encoder

    return load_encoder(spec)


def encoder_digest(spec: str) -> str:
    """``identity``, or the SHA-256 of the encoder's weights (cache keys and training records)."""
    if spec == "identity":
        return "identity"
    from image2sim.simulator.gaussians.build import encoder_file
    from image2sim.simulator.io.digest import file_sha256

    path = encoder_file(spec)
    if not path.is_file():
        raise SplatDataError(
            f"{spec}: encoder checkpoint not found (expected a .safetensors file or its folder)"
        )
    return file_sha256(path)


def capture_conditions(
    capture_path: str | Path,
    height: int,
    width: int,
    train: Sequence[int],
    cfg: SplatDataConfig,
    gcfg: Any,
    targets: Sequence[tuple[torch.Tensor, torch.Tensor]] | None = None,
    progress: bool = False,
) -> tuple[torch.Tensor, bool]:
    """Leave-target-out conditions ``(len(train), 24, height, width)`` of one capture and whether
    they came from the cache. ``targets`` are the capture's resized frames (for the cache key)."""
    from image2sim.simulator.gaussians.config import config_to_dict
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.io.registry import open_capture
    from safetensors.torch import load_file, save_file

    capture = open_capture(capture_path)
    train = [int(i) for i in train]
    if len(train) < 2:
        raise SplatDataError(
            f"{capture_path}: {len(train)} training frame(s); leave-target-out needs at least 2"
        )
    poses = {i: np.asarray(capture[i].cam_to_world, dtype=np.float64) for i in train}
    candidates = source_frames(train, cfg.source_every)
    if len(candidates) < 2:
        raise SplatDataError(
            f"{capture_path}: {len(candidates)} source frame(s) with source_every={cfg.source_every}; "
            "leave-target-out needs at least 2"
        )
    sources = [_sources_for(t, candidates, poses, cfg.neighbours) for t in train]
    cache_file = None
    if cfg.cache_dir is not None:
        key = conditions_cache_key(
            capture_path,
            [targets[i] for i in train] if targets is not None else [],
            [poses[i] for i in train],
            config_to_dict(gcfg),
            height,
            width,
            train,
            sources,
            cfg.fuse_every,
            encoder_digest(cfg.encoder),
        )
        cache_file = Path(cfg.cache_dir) / f"{Path(capture_path).name}-{key}.safetensors"
        if cache_file.is_file():
            cond = load_file(str(cache_file))["conditions"]
            if cond.shape != (len(train), 24, height, width):
                raise SplatDataError(f"{cache_file}: cached conditions have shape {tuple(cond.shape)}")
            return cond, True
    sets, views = encode_capture(capture, candidates, gcfg, _encoder(cfg.encoder))
    camera = EquirectCamera(height, width)
    it = list(zip(train, sources, strict=True))
    if progress:
        from rich.progress import track

        it = track(it, description=f"splatting {Path(capture_path).name} ({len(train)} targets)")
    conds = []
    for t, src in it:
        g = leave_one_out_gaussians(sets, src, gcfg.fusion, cfg.fuse_every, views)
        conds.append(gaussians_condition(g, camera, poses[t]))
    cond = torch.stack(conds).contiguous()
    if cache_file is not None:
        from image2sim.simulator.io.atomic import atomic_path

        with atomic_path(cache_file) as tmp:
            save_file(
                {"conditions": cond},
                str(tmp),
                metadata={"capture": str(capture_path), "targets": json.dumps(train)},
            )
    return cond, False


def _build_conditions(jobs: list[tuple], workers: int, progress: bool) -> list[tuple[torch.Tensor, bool]]:
    """:func:`capture_conditions` of every job (its positional arguments), in order."""
    if workers <= 1:
        return [capture_conditions(*job, progress=progress) for job in jobs]
    from image2sim.simulator.lifetime import spawn_pool

    with spawn_pool(workers) as pool:
        futures = [pool.submit(capture_conditions, *job) for job in jobs]
        if progress:
            from concurrent.futures import as_completed

            from rich.progress import track

            label = f"splatting {len(jobs)} captures ({workers} processes)"
            for _ in track(as_completed(futures), total=len(futures), description=label):
                pass
        return [f.result() for f in futures]


@dataclass
class _Source:
    path: str
    frames: list[int] = field(default_factory=list)
    cached: bool = False


class SplatConditionDataset(Dataset):
    """(splat of the other training frames at a training frame's pose, that frame) pairs.

    Items: ``{"condition": (24, H, W), "target_rgb": (3, H, W), "target_depth": (1, H, W),
    "index": i, "source": "splat"|"degraded"}``. With ``degraded_fraction = f > 0`` another
    ``round(N f / (1 - f))`` synthetic degradations of the same training targets are appended.
    """

    def __init__(
        self,
        captures: Sequence[str | Path],
        height: int,
        width: int,
        cfg: SplatDataConfig | None = None,
        gaussian_config: Any = None,
        progress: bool = False,
        workers: int = 1,
    ) -> None:
        """``workers`` > 1 builds the captures' conditions in that many spawned processes, one capture
        each (leave-target-out fusion is single-threaded, so one process per core is what uses the
        machine); the conditions are the same as in one process."""
        from image2sim.simulator.gaussians.config import load_gaussian_config
        from image2sim.simulator.renderer.data import load_capture_targets

        self.cfg = (cfg or SplatDataConfig()).validate()
        if not captures:
            raise SplatDataError("SplatConditionDataset needs at least one capture")
        gcfg = (
            gaussian_config if gaussian_config is not None else load_gaussian_config(self.cfg.gaussian_config)
        )
        self.gaussian_config = gcfg
        """The resolved Gaussian config the conditions were built with."""
        all_targets = [load_capture_targets(p, height, width, self.cfg.max_frames) for p in captures]
        split = holdout_split([len(t) for t in all_targets], self.cfg.holdout_every)
        if int(workers) < 1:
            raise SplatDataError(f"workers must be >= 1, got {workers}")
        jobs = [
            (path, height, width, train, self.cfg, gcfg, targets)
            for path, targets, (_, train) in zip(captures, all_targets, split, strict=True)
        ]
        built = _build_conditions(jobs, min(int(workers), len(jobs)), progress)
        conds, rgbs, depths = [], [], []
        self.sources: list[_Source] = []
        for (path, _, _, train, _, _, targets), (cond, cached) in zip(jobs, built, strict=True):
            conds.append(cond)
            rgbs += [targets[i][0] for i in train]
            depths += [targets[i][1] for i in train]
            self.sources.append(_Source(str(path), list(train), cached))
        self.conditions = torch.cat(conds)
        self.target_rgb = torch.stack(rgbs)
        self.target_depth = torch.stack(depths)
        n = len(self.conditions)
        f = self.cfg.degraded_fraction
        self.num_degraded = int(round(n * f / (1.0 - f))) if f > 0 else 0
        self.degraded = None
        if self.num_degraded:
            from image2sim.simulator.renderer.data import DegradeConfig, DegradedPanoramaDataset

            self.degraded = DegradedPanoramaDataset(
                list(zip(rgbs, depths, strict=True)),
                self.num_degraded,
                DegradeConfig(seed=self.cfg.degraded_seed),
            )

    @property
    def num_splat(self) -> int:
        return int(len(self.conditions))

    def __len__(self) -> int:
        return self.num_splat + self.num_degraded

    def __getitem__(self, index: int) -> dict:
        index = int(index)
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} samples")
        if index >= self.num_splat:
            item = dict(self.degraded[index - self.num_splat])
            item.update(index=index, source="degraded")
            return item
        return {
            "condition": self.conditions[index],
            "target_rgb": self.target_rgb[index],
            "target_depth": self.target_depth[index],
            "index": index,
            "source": "splat",
        }


def training_record(
    captures: Sequence[str | Path], cfg: SplatDataConfig, gaussian_config: Any
) -> dict[str, Any]:
    """What the conditions of a training run were made of: the captures, the splat-data settings
    (split, sparsity) and the resolved Gaussian config. A renderer is only meaningful on conditions
    built the same way, so ``eval render`` compares its own protocol against this record."""
    from image2sim.simulator.gaussians.config import config_to_dict

    return {
        "condition_source": "splat",
        "captures": [str(c) for c in captures],
        "splat_data": dataclasses.asdict(cfg),
        "gaussians": config_to_dict(gaussian_config),
        "encoder_sha256": encoder_digest(cfg.encoder),
    }


def write_training_record(run_dir: str | Path, record: dict[str, Any]) -> Path:
    """Write ``record`` as ``run_dir/training_data.json`` (atomic); returns the path."""
    from image2sim.simulator.io.atomic import write_json_atomic

    path = Path(run_dir) / TRAINING_RECORD
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_json_atomic(path, record)


def find_training_record(checkpoint: str | Path) -> dict[str, Any] | None:
    """The training record of the run a checkpoint belongs to (``<run>/checkpoints/x.ckpt`` or
    ``<run>/x``; an exported renderer folder carries its own), or None when there is none (older
    runs, weights saved without it)."""
    ckpt = Path(checkpoint)
    for folder in ((ckpt,) if ckpt.is_dir() else ()) + (ckpt.parent, ckpt.parent.parent):
        path = folder / TRAINING_RECORD
        if path.is_file():
            try:
                return json.loads(path.read_text())
            except json.JSONDecodeError as exc:
                raise SplatDataError(f"{path}: not valid JSON ({exc})") from exc
    return None


def protocol_mismatches(
    record: dict[str, Any], gaussian_config: Any, source_every: int, holdout_every: int
) -> list[str]:
    """How an evaluation's conditions differ from the ones a renderer was trained on, one line per
    difference (empty: same Gaussian config, sparsity and split)."""
    from image2sim.simulator.gaussians.config import config_to_dict

    if record.get("condition_source") != "splat":
        return [f"trained on {record.get('condition_source')!r} conditions, evaluated on splats"]
    out = []
    trained, now = record.get("gaussians", {}), config_to_dict(gaussian_config)

    def flat(d: dict, prefix: str = "") -> dict[str, Any]:
        items: dict[str, Any] = {}
        for k, v in d.items():
            items.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return items

    a, b = flat(trained), flat(now)
    # Stage-1 training settings (``train.*``, ``trainer.*``) do not change the Gaussians a scene is
    # built with, and older records lack some of them: they are not protocol differences.
    ignored = ("name", "train.", "trainer.")
    for key in sorted(set(a) | set(b)):
        if not key.startswith(ignored) and a.get(key) != b.get(key):
            out.append(f"gaussians.{key}: trained {a.get(key)!r}, evaluated {b.get(key)!r}")
    sd = record.get("splat_data", {})
    for key, value in (("source_every", source_every), ("holdout_every", holdout_every)):
        if key in sd and sd[key] != value:
            out.append(f"{key}: trained {sd[key]}, evaluated {value}")
    return out
