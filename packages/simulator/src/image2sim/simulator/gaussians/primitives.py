"""A set of 3D feature Gaussians (world frame) and the per-frame inputs they are built from."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from image2sim.simulator.geometry.cameras import Camera

__all__ = ["GaussianSet", "FrameInputs", "GAUSSIAN_FIELDS"]

GAUSSIAN_FIELDS = ("means", "scales", "quats", "opacities", "colors", "features")
"""Tensor fields every Gaussian set carries, in :func:`image2sim.simulator.splatting.splat` order."""


@dataclass
class GaussianSet:
    """N Gaussians in world coordinates (Z-up metres), the arguments of ``splat``.

    ``footprints`` (N,) is the metric pixel footprint each Gaussian was observed with (used by the
    footprint voxel policy); ``weights`` (N,) how many pixels were averaged into it; ``levels`` (N,)
    the voxel level it lives at (int64; 0 for unfused per-pixel Gaussians).
    """

    means: torch.Tensor
    """(N, 3) world positions, metres."""
    scales: torch.Tensor
    """(N, 3) standard deviations along the local axes, metres."""
    quats: torch.Tensor
    """(N, 4) unit (w, x, y, z) rotations local -> world."""
    opacities: torch.Tensor
    """(N,) opacities in [0, 1]."""
    colors: torch.Tensor
    """(N, 3) RGB in [0, 1]."""
    features: torch.Tensor
    """(N, C) scene features (C may be 0)."""
    footprints: torch.Tensor
    """(N,) metric pixel footprint at observation, metres."""
    weights: torch.Tensor
    """(N,) number of fused observations (float)."""
    levels: torch.Tensor
    """(N,) int64 voxel level."""

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {
            "means": (n, 3),
            "scales": (n, 3),
            "quats": (n, 4),
            "opacities": (n,),
            "colors": (n, 3),
            "footprints": (n,),
            "weights": (n,),
            "levels": (n,),
        }
        for name, shape in shapes.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"GaussianSet.{name} must have shape {shape}, got {tuple(t.shape)}")
        if self.features.ndim != 2 or self.features.shape[0] != n:
            raise ValueError(f"GaussianSet.features must be (N={n}, C), got {tuple(self.features.shape)}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def feature_dim(self) -> int:
        return int(self.features.shape[1])

    def tensors(self) -> dict[str, torch.Tensor]:
        """All fields by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def index(self, idx: torch.Tensor) -> GaussianSet:
        """Subset by a boolean mask or index tensor."""
        return GaussianSet(**{k: v[idx] for k, v in self.tensors().items()})

    def detach(self) -> GaussianSet:
        return GaussianSet(**{k: v.detach() for k, v in self.tensors().items()})

    @staticmethod
    def cat(sets: list[GaussianSet]) -> GaussianSet:
        """Concatenate sets with equal feature widths."""
        if not sets:
            raise ValueError("GaussianSet.cat needs at least one set")
        dims = {s.feature_dim for s in sets}
        if len(dims) != 1:
            raise ValueError(f"GaussianSet.cat: feature widths differ {sorted(dims)}")
        return GaussianSet(**{k: torch.cat([getattr(s, k) for s in sets]) for k in sets[0].tensors()})

    @staticmethod
    def empty(feature_dim: int = 0, dtype: torch.dtype = torch.float32) -> GaussianSet:
        z = lambda *s: torch.zeros(*s, dtype=dtype)  # noqa: E731
        return GaussianSet(
            z(0, 3),
            z(0, 3),
            z(0, 4),
            z(0),
            z(0, 3),
            z(0, feature_dim),
            z(0),
            z(0),
            torch.zeros(0, dtype=torch.int64),
        )

    def render(self, camera: Camera, cam_to_world, **kwargs):
        """Splat these Gaussians into ``camera`` at ``cam_to_world`` (4, 4) or (B, 4, 4); see ``splat``."""
        from image2sim.simulator.splatting import splat

        pose = torch.as_tensor(cam_to_world, dtype=self.means.dtype)
        return splat(
            self.means,
            self.scales,
            self.quats,
            self.opacities,
            self.colors,
            self.features,
            camera,
            pose,
            **kwargs,
        )


@dataclass
class FrameInputs:
    """One posed RGB-D frame as tensors at the encoder resolution."""

    rgb: torch.Tensor
    """(1, 3, H, W) colour in [0, 1]."""
    depth: torch.Tensor
    """(1, 1, H, W) metres (range for panoramas, z for pinhole), 0 = invalid."""
    camera: Camera
    """Camera model at this resolution."""
    cam_to_world: torch.Tensor
    """(4, 4) float64 camera-to-world pose."""
    frame_id: str = ""
    """Identifier of the source frame."""
    labels: torch.Tensor | None = None
    """(1, 1, H, W) int64 category ids at this resolution (0 = unknown), from the capture's
    ``semantics/``; None when the capture has none. Stage 1's label target reads them."""
