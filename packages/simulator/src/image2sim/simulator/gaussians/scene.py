"""``GaussianScene``: the persistent scene memory (the paper's MemoryState) and its on-disk artifact.

Folder layout written by :meth:`GaussianScene.save`::

    gaussians.safetensors   means, scales, quats, opacities, colors, features, footprints, weights, levels
    manifest.json           format/version, source capture (+ its camera), frames used (+ poses),
                            encoder (kind, checkpoint, sha256), camera (the encoded input camera),
                            encoding (its resolution and the config fields it came from), fusion
                            policy, conventions, counts, bounds

:meth:`export_ply` writes the standard 3D Gaussian Splatting vertex layout (x y z, nx ny nz,
f_dc_0..2, opacity as a logit, scale_0..2 as logs, rot_0..3 = w x y z, then feat_0..C-1), which
common Gaussian viewers open; :meth:`from_ply` reads it back.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from image2sim.simulator.gaussians.config import FusionConfig
from image2sim.simulator.gaussians.fusion import fuse, level_histogram, prune
from image2sim.simulator.gaussians.primitives import GaussianSet
from image2sim.simulator.geometry.cameras import Camera, camera_from_dict
from image2sim.simulator.io.atomic import atomic_dir
from image2sim.simulator.io.paths import relative_to_file, resolve_from_file

__all__ = ["GaussianScene", "SceneError", "SCENE_FORMAT", "SH_C0"]

SCENE_FORMAT = "image2sim-gaussian-scene"
SCENE_VERSION = 1
SH_C0 = 0.28209479177387814
"""Zeroth spherical-harmonic constant: 3DGS stores colour c as f_dc = (c - 0.5) / SH_C0."""
CONVENTIONS = {
    "world": "z-up metres",
    "quaternion": "wxyz, local-to-world",
    "scales": "standard deviations in metres",
    "opacity": "[0, 1] (PLY: logit)",
    "colors": "RGB [0, 1] (PLY: SH DC)",
}
_TENSORS = ("means", "scales", "quats", "opacities", "colors", "features", "footprints", "weights", "levels")


class SceneError(ValueError):
    """A bad scene folder or PLY; the message names the file and the problem."""


@dataclass
class GaussianScene:
    """Fused feature Gaussians of one scene plus provenance.

    Grows with :meth:`integrate` (fuse a new frame's Gaussians into memory); renders with
    :meth:`render`; persists with :meth:`save` / :meth:`load`.
    """

    fusion: FusionConfig = field(default_factory=FusionConfig)
    """Voxel policy and pruning thresholds used by :meth:`integrate`."""
    gaussians: GaussianSet | None = None
    """The fused Gaussians (None until the first frame)."""
    frames: list[dict] = field(default_factory=list)
    """Frames integrated so far: {"index", "frame_id", "cam_to_world"}."""
    info: dict[str, Any] = field(default_factory=dict)
    """Provenance for the manifest: source capture, encoder, camera, config name."""

    def __len__(self) -> int:
        return 0 if self.gaussians is None else len(self.gaussians)

    @property
    def feature_dim(self) -> int:
        return 0 if self.gaussians is None else self.gaussians.feature_dim

    def integrate(
        self,
        new: GaussianSet,
        frame_id: str = "",
        index: int | None = None,
        cam_to_world: torch.Tensor | np.ndarray | None = None,
    ) -> int:
        """Fuse one frame's Gaussians into memory (levels from their footprints); returns the new count."""
        self.integrate_many([new])
        self.record_frame(frame_id, index, cam_to_world)
        return len(self)

    def integrate_many(self, sets: list[GaussianSet]) -> int:
        """Fuse several frames' Gaussians in one pass (one fusion over memory + all of them, so the
        cost per frame drops by the batch size); frames are recorded with :meth:`record_frame`."""
        from image2sim.simulator.gaussians.fusion import assign_levels
        from image2sim.simulator.lifetime import torch_threads

        if not sets:
            return len(self)
        with torch_threads(self.fusion.threads):
            new = prune(GaussianSet.cat([s.detach() for s in sets]), self.fusion)
            new = GaussianSet(**{**new.tensors(), "levels": assign_levels(new.footprints, self.fusion)})
            merged = new if self.gaussians is None else GaussianSet.cat([self.gaussians, new])
            self.gaussians = prune(fuse(merged, self.fusion), self.fusion)
        return len(self)

    def record_frame(
        self,
        frame_id: str = "",
        index: int | None = None,
        cam_to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        """Add a frame to the provenance list written into the manifest."""
        pose = None if cam_to_world is None else np.asarray(cam_to_world, dtype=np.float64).tolist()
        self.frames.append({"index": index, "frame_id": frame_id, "cam_to_world": pose})

    def bounds(self) -> tuple[list[float], list[float]]:
        """Axis-aligned (min, max) of the means; zeros for an empty scene."""
        if not len(self):
            return [0.0] * 3, [0.0] * 3
        m = self.gaussians.means
        return m.amin(0).tolist(), m.amax(0).tolist()

    def render(self, camera: Camera, cam_to_world, **kwargs):
        """Splat the scene into ``camera`` at ``cam_to_world``; returns a ``SplatOutput``."""
        if self.gaussians is None:
            raise SceneError("render: the scene is empty")
        return self.gaussians.render(camera, cam_to_world, **kwargs)

    # ------------------------------------------------------------------ persistence
    def manifest(self) -> dict:
        g = self.gaussians
        lo, hi = self.bounds()
        return {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "source": self.info.get("source", {}),
            "frames": self.frames,
            "encoder": self.info.get("encoder", {"kind": "unknown"}),
            "camera": self.info.get("camera"),
            "encoding": self.info.get("encoding"),
            "config": self.info.get("config"),
            "fusion": {k: v for k, v in config_to_dict_fusion(self.fusion).items()},
            "conventions": CONVENTIONS,
            "counts": {
                "gaussians": len(self),
                "feature_dim": self.feature_dim,
                "frames": len(self.frames),
                "per_voxel_size": level_histogram(g.levels, self.fusion) if g is not None else {},
            },
            "bounds": {"min": lo, "max": hi},
            **({"refine": self.info["refine"]} if self.info.get("refine") else {}),
        }

    def save(self, folder: str | Path, overwrite: bool = False) -> Path:
        """Write ``gaussians.safetensors`` + ``manifest.json`` atomically (temp folder + rename)."""
        from safetensors.torch import save_file

        folder = Path(folder)
        if folder.exists() and not overwrite:
            raise SceneError(f"{folder}: already exists (pass overwrite=True to replace it)")
        if self.gaussians is None:
            raise SceneError(f"{folder}: refusing to save an empty scene")
        with atomic_dir(folder) as tmp:
            tensors = {k: getattr(self.gaussians, k).contiguous() for k in _TENSORS}
            save_file(tensors, str(tmp / "gaussians.safetensors"), metadata={"format": SCENE_FORMAT})
            manifest = _relocatable(self.manifest(), folder / "manifest.json", relative_to_file)
            (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
            for child in tmp.iterdir():  # safetensors creates its file 0600; scenes are shared artifacts
                child.chmod(0o644)
            tmp.chmod(0o755)
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> GaussianScene:
        """Read a scene folder written by :meth:`save` (bit-exact tensors)."""
        from safetensors.torch import load_file

        folder = Path(folder)
        man_path, st_path = folder / "manifest.json", folder / "gaussians.safetensors"
        for p in (man_path, st_path):
            if not p.is_file():
                raise SceneError(f"{p}: missing (not a Gaussian scene folder)")
        try:
            manifest = json.loads(man_path.read_text())
        except json.JSONDecodeError as exc:
            raise SceneError(f"{man_path}: invalid JSON ({exc})") from None
        if manifest.get("format") != SCENE_FORMAT:
            raise SceneError(
                f"{man_path}: field 'format' is {manifest.get('format')!r}, expected {SCENE_FORMAT!r}"
            )
        if manifest.get("version") != SCENE_VERSION:
            raise SceneError(f"{man_path}: unsupported version {manifest.get('version')!r}")
        tensors = load_file(str(st_path))
        missing = [k for k in _TENSORS if k not in tensors]
        if missing:
            raise SceneError(f"{st_path}: missing tensors {missing}")
        try:
            gaussians = GaussianSet(**{k: tensors[k] for k in _TENSORS})
        except ValueError as exc:
            raise SceneError(f"{st_path}: {exc}") from None
        from image2sim.simulator.config import ConfigError, config_from_dict

        try:
            fusion = config_from_dict(FusionConfig, manifest.get("fusion", {}), "fusion")
        except ConfigError as exc:
            raise SceneError(f"{man_path}: {exc}") from None
        manifest = _relocatable(manifest, man_path, lambda v, holder: str(resolve_from_file(v, holder)))
        info = {k: manifest.get(k) for k in ("source", "encoder", "camera", "encoding", "config", "refine")}
        return cls(fusion=fusion, gaussians=gaussians, frames=list(manifest.get("frames", [])), info=info)

    def camera(self) -> Camera | None:
        """The input camera recorded at build time: the resolution frames were encoded at (None when
        unknown)."""
        cam = self.info.get("camera")
        return camera_from_dict(cam) if cam else None

    def source_camera(self) -> Camera | None:
        """The source capture's own camera (manifest ``source.camera``; None for scenes built before
        it was recorded, or not built from a capture)."""
        cam = (self.info.get("source") or {}).get("camera")
        return camera_from_dict(cam) if cam else None

    # ------------------------------------------------------------------ 3DGS PLY
    def export_ply(self, path: str | Path) -> Path:
        """Write the standard 3DGS PLY layout (+ feat_* channels), binary little-endian, atomically."""
        if self.gaussians is None:
            raise SceneError(f"{path}: refusing to export an empty scene")
        return write_gaussian_ply(path, self.gaussians)

    @classmethod
    def from_ply(cls, path: str | Path, fusion: FusionConfig | None = None) -> GaussianScene:
        """Read a 3DGS PLY (ours or another tool's, SH degree 0 used) into a scene."""
        return cls(
            fusion=fusion or FusionConfig(),
            gaussians=read_gaussian_ply(path),
            info={"source": {"ply": str(path)}},
        )


_STORED_PATHS = (("source", "capture"), ("encoder", "checkpoint"))
"""Manifest paths stored relative to the manifest (relocatable outputs) and absolute in memory."""


def _relocatable(manifest: dict, holder: Path, convert) -> dict:
    """``manifest`` with the :data:`_STORED_PATHS` converted by ``convert(value, holder)``."""
    out = dict(manifest)
    for section, key in _STORED_PATHS:
        part = out.get(section)
        if isinstance(part, dict) and isinstance(part.get(key), str) and part[key]:
            out[section] = {**part, key: convert(part[key], holder)}
    return out


def config_to_dict_fusion(cfg: FusionConfig) -> dict:
    import dataclasses

    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-7, 1 - 1e-7)
    return np.log(p) - np.log1p(-p)


# The 3DGS PLY's per-Gaussian properties after the position and normal (features follow as feat_i).
_PLY_GAUSSIAN_FIELDS = (
    *(f"f_dc_{i}" for i in range(3)),
    "opacity",
    *(f"scale_{i}" for i in range(3)),
    *(f"rot_{i}" for i in range(4)),
)


def write_gaussian_ply(path: str | Path, g: GaussianSet) -> Path:
    """3DGS vertex layout: x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3 feat_0..C-1 (float32)."""
    path = Path(path)
    n, c = len(g), g.feature_dim
    names = ["x", "y", "z", "nx", "ny", "nz", *_PLY_GAUSSIAN_FIELDS] + [f"feat_{i}" for i in range(c)]
    data = np.zeros(n, dtype=np.dtype([(k, "<f4") for k in names]))
    t = {k: v.detach().cpu().double().numpy() for k, v in g.tensors().items()}
    if not np.isfinite(t["means"]).all():
        raise SceneError(f"{path}: Gaussian means contain NaN/inf")
    for i, k in enumerate("xyz"):
        data[k] = t["means"][:, i]
    for i in range(3):
        data[f"f_dc_{i}"] = (t["colors"][:, i] - 0.5) / SH_C0
        data[f"scale_{i}"] = np.log(np.maximum(t["scales"][:, i], 1e-12))
    data["opacity"] = _logit(t["opacities"])
    for i in range(4):
        data[f"rot_{i}"] = t["quats"][:, i]
    for i in range(c):
        data[f"feat_{i}"] = t["features"][:, i]
    from image2sim.simulator.io.ply import write_ply_vertices

    return write_ply_vertices(path, data, comment="image2sim gaussian scene (3DGS layout)")


def read_gaussian_ply(path: str | Path) -> GaussianSet:
    """Parse a 3DGS PLY into a :class:`GaussianSet` (weights 1, level 0, footprint = mean scale)."""
    from image2sim.simulator.io.ply import PlyError, read_ply

    path = Path(path)
    try:
        cols = read_ply(path)
    except PlyError as exc:
        raise SceneError(str(exc)) from None
    missing = [k for k in _PLY_GAUSSIAN_FIELDS if k not in cols]
    if missing:
        raise SceneError(f"{path}: not a 3D Gaussian Splatting PLY, missing properties {missing}")
    n = cols["points"].shape[0]
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    colors = np.stack([cols[f"f_dc_{i}"].astype(np.float64) * SH_C0 + 0.5 for i in range(3)], 1).clip(0, 1)
    scales = np.exp(np.stack([cols[f"scale_{i}"].astype(np.float64) for i in range(3)], 1))
    quats = np.stack([cols[f"rot_{i}"].astype(np.float64) for i in range(4)], 1)
    quats /= np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-30)
    opac = 1.0 / (1.0 + np.exp(-cols["opacity"].astype(np.float64)))
    feat_names = sorted((k for k in cols if k.startswith("feat_")), key=lambda k: int(k.split("_")[1]))
    feats = np.stack([cols[k] for k in feat_names], 1) if feat_names else np.zeros((n, 0))
    return GaussianSet(
        means=f32(cols["points"]),
        scales=f32(scales),
        quats=f32(quats),
        opacities=f32(opac),
        colors=f32(colors),
        features=f32(feats),
        footprints=f32(scales.mean(1)),
        weights=torch.ones(n),
        levels=torch.zeros(n, dtype=torch.int64),
    )
