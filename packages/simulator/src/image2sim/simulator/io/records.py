"""Typed records shared by every capture reader: :class:`Frame` and :class:`Capture`."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from image2sim.simulator.geometry.cameras import Camera


class CaptureError(ValueError):
    """Bad capture input. The message names the file (or field) and the problem."""


@dataclass
class Frame:
    """One posed RGB-D frame in Image2Sim conventions.

    Attributes:
        rgb: (H, W, 3) uint8 colour image.
        depth: (H, W) float32 metres; range for panoramas, z for pinhole; 0 = invalid.
        camera: the camera model of ``rgb``/``depth``.
        cam_to_world: (4, 4) float64 camera-to-world pose (OpenCV camera, Z-up world).
        semantics: optional (H, W) int32 category ids (0 = unknown/background).
        instances: optional (H, W) int32 instance ids (0 = none).
        frame_id: identifier of the frame inside its capture (file stem, viewpoint id, ...).
        notes: reader remarks about this frame (e.g. "colour resampled to the depth grid").
        confidence: optional (H, W) float32 in [0, 1], how far ``depth`` can be trusted per pixel
            (lifted captures: ``image2sim data lift``); None when the capture has none.
    """

    rgb: np.ndarray
    depth: np.ndarray
    camera: Camera
    cam_to_world: np.ndarray
    semantics: np.ndarray | None = None
    instances: np.ndarray | None = None
    frame_id: str = ""
    notes: list[str] = field(default_factory=list)
    confidence: np.ndarray | None = None

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    @property
    def position(self) -> np.ndarray:
        return self.cam_to_world[:3, 3]


class Capture(Sequence):
    """A lazily loaded sequence of :class:`Frame`s; ``capture[i]`` reads frame ``i`` from disk.

    Readers build it from a list of frame ids and a loader; ``skipped`` lists ``(frame_id, reason)``
    for frames the reader found unusable while indexing (e.g. non-finite poses). Readers that
    parse poses while indexing pass ``poses`` ((N, 4, 4) float64, our conventions) so that tools
    can use them without decoding images; ``camera`` is the shared camera when known up front.
    """

    def __init__(
        self,
        root: Path,
        format: str,
        frame_ids: Sequence[str],
        loader: Callable[[str], Frame],
        *,
        scene_id: str | None = None,
        skipped: Sequence[tuple[str, str]] = (),
        metadata: dict | None = None,
        poses: np.ndarray | None = None,
        camera: Camera | None = None,
    ) -> None:
        self.root = Path(root)
        self.format = format
        self.frame_ids = list(frame_ids)
        self._loader = loader
        self.scene_id = scene_id or self.root.name
        self.skipped = list(skipped)
        self.metadata = dict(metadata or {})
        self.poses = None if poses is None else np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if self.poses is not None and len(self.poses) != len(self.frame_ids):
            raise ValueError(f"{len(self.poses)} poses for {len(self.frame_ids)} frames ({self.root})")
        self.camera = camera

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame index {index} out of range for capture of {n} frames ({self.root})")
        return self._loader(self.frame_ids[index % n])

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return (
            f"Capture(format={self.format!r}, scene={self.scene_id!r}, frames={len(self)}, "
            f"root='{self.root}')"
        )
