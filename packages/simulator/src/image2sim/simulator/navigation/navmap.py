"""The navigable map of one scene (:class:`NavMap`: storage, queries, ``.npz`` round trip) and the
agreement of two maps' navigable cells (:func:`navmap_agreement`).

Maps are made by :mod:`image2sim.simulator.navigation.extract` and drawn by
:mod:`image2sim.simulator.navigation.topdown`. Everything is expressed in the *map frame*: the
gravity-aligned world (identical to the world frame when ``rotation`` is the identity, i.e. for Z-up
captures). :attr:`NavMap.points` is returned in world coordinates.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from image2sim.simulator.io.atomic import atomic_open
from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
from scipy.spatial import cKDTree

__all__ = ["HEIGHT_TOLERANCE", "NavMap", "NavMapError", "navmap_agreement"]

NAVMAP_FORMAT_VERSION = 1

HEIGHT_TOLERANCE = 0.01
"""Slack (metres) on every step-height comparison: a tread edge exactly one step up stays climbable
despite voxel averaging and float rounding."""


class NavMapError(ValueError):
    """The input cannot yield a navigable map; the message says what is missing and where."""


# ----------------------------------------------------------------------------------------------
# The map
# ----------------------------------------------------------------------------------------------


@dataclass
class NavMap:
    """Navigable floor of one scene on a 0.05 m grid (map frame = gravity-aligned world).

    Attributes:
        voxel_size: cell size in metres.
        origin: (3,) map-frame position of the corner of voxel (0, 0, 0).
        shape: (nx, ny, nz) voxel-grid extent.
        floor_ij: (F, 2) int column of every floor cell (a column may hold several, e.g. storeys).
        floor_z: (F,) floor height of each cell in metres.
        floor_level: (F,) storey index of each cell (nearest storey height).
        floor_filled: (F,) True for cells created by the hole-filling closing.
        clearance: (F,) horizontal distance (m) to the nearest blocked column (obstacle in the body
            band above this floor height, or unsupported/unknown floor).
        navigable: (F,) clearance >= safety buffer.
        obstacle_ij: (O, 2) int columns of obstacle voxels (after outlier removal).
        obstacle_xyz: (O, 3) mean position of the points of each obstacle voxel.
        support_ij: (S, 2) columns of floor seen directly under obstacles (wall bases, risers): they
            count as support for the unknown-space test but are not floor cells.
        support_z: (S,) heights of those.
        level_heights: (L,) storey heights.
        level_planes: (L, 4) storey planes (a, b, c, d) with a x + b y + c z + d = 0, c > 0.
        rotation: (3, 3) map_from_world rotation (identity when no gravity correction was applied).
        embodiment: the body used for the clearance/step tests.
        config: the extraction config.
        notes: remarks from the extraction (fallbacks taken, counts dropped).
    """

    voxel_size: float
    origin: np.ndarray
    shape: tuple[int, int, int]
    floor_ij: np.ndarray
    floor_z: np.ndarray
    floor_level: np.ndarray
    floor_filled: np.ndarray
    clearance: np.ndarray
    navigable: np.ndarray
    obstacle_ij: np.ndarray
    obstacle_xyz: np.ndarray
    support_ij: np.ndarray
    support_z: np.ndarray
    level_heights: np.ndarray
    level_planes: np.ndarray
    rotation: np.ndarray
    embodiment: Embodiment
    config: NavMapConfig
    notes: list[str] = field(default_factory=list)

    # --- derived geometry -----------------------------------------------------------------
    @property
    def shape2d(self) -> tuple[int, int]:
        return (int(self.shape[0]), int(self.shape[1]))

    def cell_xy(self, ij: np.ndarray) -> np.ndarray:
        """Map-frame (x, y) centres of integer columns (N, 2)."""
        return self.origin[:2] + (np.asarray(ij, dtype=np.float64) + 0.5) * self.voxel_size

    def xy_to_ij(self, xy: np.ndarray) -> np.ndarray:
        """Integer columns containing map-frame (x, y) positions (N, 2); may lie outside the grid."""
        return np.floor((np.asarray(xy, dtype=np.float64) - self.origin[:2]) / self.voxel_size).astype(
            np.int64
        )

    @property
    def floor_points(self) -> np.ndarray:
        """(F, 3) map-frame centres of all floor cells (navigable or not) at floor height."""
        return np.column_stack((self.cell_xy(self.floor_ij), self.floor_z))

    @property
    def map_points(self) -> np.ndarray:
        """(M, 3) map-frame centres of the navigable cells at floor height."""
        return self.floor_points[self.navigable]

    @property
    def points(self) -> np.ndarray:
        """(M, 3) world-frame centres of the navigable cells at floor height (public contract)."""
        return self.to_world(self.map_points)

    @property
    def levels(self) -> np.ndarray:
        """(M,) storey index of each row of :attr:`points`."""
        return self.floor_level[self.navigable]

    @property
    def obstacle_z(self) -> np.ndarray:
        """(O,) mean height of each obstacle voxel."""
        return self.obstacle_xyz[:, 2]

    @property
    def obstacle_points(self) -> np.ndarray:
        """(O, 3) map-frame obstacle positions (mean of the points of each obstacle voxel)."""
        return self.obstacle_xyz

    def to_world(self, p: np.ndarray) -> np.ndarray:
        """Map-frame points (..., 3) -> world frame."""
        return np.asarray(p, dtype=np.float64) @ self.rotation  # R^T p for row vectors

    def to_map(self, p: np.ndarray) -> np.ndarray:
        """World-frame points (..., 3) -> map frame."""
        return np.asarray(p, dtype=np.float64) @ self.rotation.T

    @property
    def num_levels(self) -> int:
        return int(len(self.level_heights))

    def navigable_area(self, level: int | None = None) -> float:
        """Navigable area in m^2 (of one storey when ``level`` is given)."""
        sel = self.navigable if level is None else (self.navigable & (self.floor_level == level))
        return float(sel.sum()) * self.voxel_size**2

    @property
    def safety_buffer(self) -> float:
        buf = self.config.safety_buffer
        return self.embodiment.radius if buf is None else float(buf)

    @property
    def unknown_clearance(self) -> float:
        """Clearance navigable cells keep to columns without floor (``NavMapConfig.unknown_clearance``)."""
        buf = self.config.unknown_clearance
        return self.safety_buffer if buf is None else min(float(buf), self.safety_buffer)

    # --- per-height-band blocked masks (the body-band view of the 3D occupancy) --------------
    def height_bins(self) -> tuple[np.ndarray, np.ndarray]:
        """Floor-height bins used for the body-band masks: (bin heights (B,), bin of each cell (F,))."""
        k = np.floor((self.floor_z - self.origin[2]) / self.voxel_size).astype(np.int64)
        uniq, inv = np.unique(k, return_inverse=True)
        heights = np.bincount(inv.reshape(-1), weights=self.floor_z) / np.bincount(inv.reshape(-1))
        return heights, inv.reshape(-1)

    def band_obstacles(self, floor_height: float) -> np.ndarray:
        """Boolean selector of obstacle voxels in the body band (floor + max step, floor + height]."""
        emb = self.embodiment
        z = self.obstacle_z
        return (z > floor_height + emb.max_step_height + HEIGHT_TOLERANCE) & (z <= floor_height + emb.height)

    def unsupported_mask(self, floor_height: float) -> np.ndarray:
        """(nx, ny) columns without a floor within the maximum step height of ``floor_height``."""
        support = np.zeros(self.shape2d, dtype=bool)
        tol = self.embodiment.max_step_height + HEIGHT_TOLERANCE
        near = np.abs(self.floor_z - floor_height) <= tol
        support[self.floor_ij[near, 0], self.floor_ij[near, 1]] = True
        near = np.abs(self.support_z - floor_height) <= tol
        support[self.support_ij[near, 0], self.support_ij[near, 1]] = True
        return ~support

    def blocked_mask(self, floor_height: float) -> np.ndarray:
        """(nx, ny) columns an agent standing at ``floor_height`` may not occupy.

        Blocked = an obstacle voxel in the body band (floor + max step, floor + height] or no floor
        within the maximum step height (unknown space, drops, holes).
        """
        blocked = self.unsupported_mask(floor_height)
        sel = self.band_obstacles(floor_height)
        blocked[self.obstacle_ij[sel, 0], self.obstacle_ij[sel, 1]] = True
        return blocked

    def bin_keys(self) -> np.ndarray:
        """(B,) sorted integer height index k = floor((z - origin_z) / voxel) of each height bin."""
        return np.unique(np.floor((self.floor_z - self.origin[2]) / self.voxel_size).astype(np.int64))

    def blocked_stack(self) -> tuple[np.ndarray, np.ndarray]:
        """Blocked masks of every height bin: (bin keys (B,) as in :meth:`bin_keys`, masks (B, nx, ny))."""
        heights, _ = self.height_bins()
        masks = (
            np.stack([self.blocked_mask(float(h)) for h in heights])
            if len(heights)
            else np.zeros((0,) + self.shape2d, dtype=bool)
        )
        return self.bin_keys(), masks

    # --- persistence ----------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write an ``.npz`` (no pickle) atomically; returns the path.

        Every field :meth:`load` reads is stored losslessly (float64), so a job that resumes from a
        saved map computes exactly what the uninterrupted job computed from the fresh one. Only
        ``points``, derived and kept for viewers, is float32."""
        path = Path(path)
        meta = {
            "format_version": NAVMAP_FORMAT_VERSION,
            "voxel_size": self.voxel_size,
            "shape": list(self.shape),
            "embodiment": self.embodiment.to_dict(),
            "config": {**self.config.to_dict(), "floor_labels": list(self.config.floor_labels)},
            "notes": self.notes,
        }
        arrays = {
            "meta_json": np.array(json.dumps(meta)),
            "origin": self.origin,
            "floor_ij": self.floor_ij.astype(np.int32),
            "floor_z": self.floor_z.astype(np.float64),
            "floor_level": self.floor_level.astype(np.int16),
            "floor_filled": self.floor_filled,
            "clearance": self.clearance.astype(np.float64),
            "navigable": self.navigable,
            "obstacle_ij": self.obstacle_ij.astype(np.int32),
            "obstacle_xyz": self.obstacle_xyz.astype(np.float64),
            "support_ij": self.support_ij.astype(np.int32),
            "support_z": self.support_z.astype(np.float64),
            "level_heights": self.level_heights,
            "level_planes": self.level_planes,
            "rotation": self.rotation,
            "points": self.points.astype(np.float32),
        }
        with atomic_open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> NavMap:
        """Read a map written by :meth:`save`; errors name the file and the missing field."""
        path = Path(path)
        if not path.is_file():
            raise NavMapError(f"{path}: navigation map file not found")
        with np.load(path, allow_pickle=False) as data:
            try:
                meta = json.loads(str(data["meta_json"]))
                if meta.get("format_version") != NAVMAP_FORMAT_VERSION:
                    raise NavMapError(
                        f"{path}: unsupported navmap format_version {meta.get('format_version')!r}"
                    )
                return cls(
                    voxel_size=float(meta["voxel_size"]),
                    origin=np.asarray(data["origin"], dtype=np.float64),
                    shape=tuple(int(v) for v in meta["shape"]),  # type: ignore[arg-type]
                    floor_ij=data["floor_ij"].astype(np.int64),
                    floor_z=data["floor_z"].astype(np.float64),
                    floor_level=data["floor_level"].astype(np.int64),
                    floor_filled=data["floor_filled"].astype(bool),
                    clearance=data["clearance"].astype(np.float64),
                    navigable=data["navigable"].astype(bool),
                    obstacle_ij=data["obstacle_ij"].astype(np.int64),
                    obstacle_xyz=data["obstacle_xyz"].astype(np.float64),
                    support_ij=data["support_ij"].astype(np.int64),
                    support_z=data["support_z"].astype(np.float64),
                    level_heights=np.asarray(data["level_heights"], dtype=np.float64),
                    level_planes=np.asarray(data["level_planes"], dtype=np.float64),
                    rotation=np.asarray(data["rotation"], dtype=np.float64),
                    embodiment=Embodiment.from_dict(meta["embodiment"], where=str(path)),
                    config=NavMapConfig.from_dict(meta["config"], where=str(path)),
                    notes=list(meta.get("notes", [])),
                )
            except KeyError as err:
                raise NavMapError(f"{path}: navmap file is missing field {err.args[0]!r}") from None

    def summary(self) -> dict:
        """Counts and areas, JSON-ready."""
        return {
            "navigable_cells": int(self.navigable.sum()),
            "floor_cells": int(len(self.floor_z)),
            "filled_cells": int(self.floor_filled.sum()),
            "obstacle_voxels": int(len(self.obstacle_z)),
            "levels": [
                {"height": float(h), "navigable_area_m2": self.navigable_area(i)}
                for i, h in enumerate(self.level_heights)
            ],
            "navigable_area_m2": self.navigable_area(),
            "gravity_correction_deg": float(
                math.degrees(math.acos(max(-1.0, min(1.0, float(self.rotation[2, 2])))))
            ),
            "notes": list(self.notes),
        }


# ----------------------------------------------------------------------------------------------
# Comparing two maps
# ----------------------------------------------------------------------------------------------


def navmap_agreement(
    a: np.ndarray, b: np.ndarray, cell: float, *, height_tolerance: float = 0.5
) -> dict[str, float]:
    """Navigable-area agreement of map ``a`` (estimate) with map ``b`` (reference).

    ``a`` and ``b`` are (N, 3) world centres of navigable cells of side ``cell`` metres
    (:attr:`NavMap.points`), in one world frame; the two lattices may be shifted or rotated
    against each other (a map from a lifted capture after its Sim(3) alignment). A cell of one
    map counts as covered by the other when the other has a cell centre within ``0.75 * cell``
    horizontally (every point of a square lattice of any rotation lies within ``cell / sqrt(2)``
    of one of its centres) and ``height_tolerance`` metres vertically (storeys stay apart).
    Cells are equal-area, so the counts are areas: ``precision`` = covered fraction of ``a``,
    ``recall`` = covered fraction of ``b``, ``f_score`` their harmonic mean (0 when either map is
    empty), ``area_a`` / ``area_b`` in m^2.
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a finite positive size in metres, got {cell}")

    def covered(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        if not len(src) or not len(ref):
            return np.zeros(len(src), dtype=bool)
        near = cKDTree(ref[:, :2]).query_ball_point(src[:, :2], r=0.75 * cell)
        return np.array(
            [
                bool(len(ix)) and bool((np.abs(ref[ix, 2] - p[2]) <= height_tolerance).any())
                for p, ix in zip(src, near, strict=True)
            ],
            dtype=bool,
        )

    precision = float(covered(a, b).mean()) if len(a) else 0.0
    recall = float(covered(b, a).mean()) if len(b) else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "precision": precision,
        "recall": recall,
        "f_score": f,
        "area_a": len(a) * cell * cell,
        "area_b": len(b) * cell * cell,
    }
