"""Occlusion-aware visibility of mined objects (the annotators' anti-hallucination allow-list).

An object counts as visible from a viewpoint when both hold:

1. **in view**: its position lies within ``max_distance`` of the eye and projects into the view the
   annotators see at a macro-step start, the forward ultra-wide view (180 degrees horizontally,
   118 degrees vertically, centred on the heading);
2. **not occluded**: the first occupied voxel of the scene's 3D occupancy met on the segment from
   the eye to the object lies within ``tolerance`` metres of the object (its own surface), or there
   is none. This is the depth test "the first surface along the ray through the object's pixel is
   the object, not something closer", done as a ray march through the occupancy so that it needs
   no rendering.

The occupancy is the navigation map's obstacle voxels (walls, furniture: everything above the floor
that the capture saw), dilated by one voxel so that a thin, sparsely sampled wall has no gaps a ray
could slip through. Everything here is in the navigation map frame (z up).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "NearConfig",
    "Occupancy",
    "VisibilityConfig",
    "in_view",
    "near_categories",
    "visible_categories",
    "visible_mask",
]


@dataclass(frozen=True)
class VisibilityConfig:
    """What "visible" means for the allow-list."""

    max_distance: float = 3.5
    """Objects farther than this (metres, from the eye) are not named."""
    hfov_deg: float = 180.0
    """Horizontal field of view of the annotation view (degrees, centred on the heading)."""
    vfov_deg: float = 118.0
    """Vertical field of view of the annotation view (degrees, centred on the horizon)."""
    tolerance: float = 0.3
    """The first occupied voxel on the ray may lie this far (metres) from the object's position and
    still count as the object's own surface."""
    occlusion: bool = True
    """False = the old distance + field-of-view test only (no occlusion)."""

    def __post_init__(self) -> None:
        for name in ("max_distance", "hfov_deg", "vfov_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"VisibilityConfig.{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0):
            raise ValueError(f"VisibilityConfig.tolerance must be >= 0, got {self.tolerance!r}")


@dataclass(frozen=True)
class Occupancy:
    """A boolean voxel grid: ``occupied[i, j, k]`` covers ``origin + voxel * ([i, j, k], [i, j, k] + 1)``."""

    origin: np.ndarray
    """(3,) corner of voxel (0, 0, 0) in metres."""
    voxel: float
    occupied: np.ndarray
    """(nx, ny, nz) bool."""

    @classmethod
    def from_voxels(
        cls, ijk: np.ndarray, origin: np.ndarray, voxel: float, dilate: int = 1, shape=None
    ) -> Occupancy:
        """Occupied integer voxels ``ijk`` (N, 3) of the grid at ``origin``, dilated by ``dilate`` voxels
        (26-neighbourhood). ``shape`` defaults to the extent of ``ijk``."""
        if not (math.isfinite(voxel) and voxel > 0):
            raise ValueError(f"Occupancy: voxel must be a positive number, got {voxel!r}")
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        pad = max(0, int(dilate))
        lo = (ijk.min(axis=0) if len(ijk) else np.zeros(3, dtype=np.int64)) - pad
        lo = np.minimum(lo, 0) if shape is not None else lo
        hi = ijk.max(axis=0) + 1 + pad if len(ijk) else np.ones(3, dtype=np.int64)
        if shape is not None:
            hi = np.maximum(hi, np.asarray(shape, dtype=np.int64) + pad)
        grid = np.zeros(tuple(int(v) for v in hi - lo), dtype=bool)
        q = ijk - lo
        grid[q[:, 0], q[:, 1], q[:, 2]] = True
        if pad and len(ijk):
            from scipy.ndimage import binary_dilation

            grid = binary_dilation(grid, structure=np.ones((3, 3, 3), dtype=bool), iterations=pad)
        return cls(np.asarray(origin, dtype=np.float64) + lo * voxel, float(voxel), grid)

    @classmethod
    def from_points(cls, points: np.ndarray, voxel: float, dilate: int = 1) -> Occupancy:
        """Voxels (of a grid anchored at 0) holding at least one of ``points`` (N, 3), dilated."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        return cls.from_voxels(np.floor(pts / voxel).astype(np.int64), np.zeros(3), voxel, dilate)

    @classmethod
    def from_navmap(cls, navmap, dilate: int = 1) -> Occupancy:
        """The obstacle voxels of a :class:`~image2sim.simulator.navigation.NavMap` (map frame)."""
        vs = float(navmap.voxel_size)
        ij = np.asarray(navmap.obstacle_ij, dtype=np.int64).reshape(-1, 2)
        z = np.asarray(navmap.obstacle_xyz, dtype=np.float64).reshape(-1, 3)[:, 2]
        k = np.floor((z - navmap.origin[2]) / vs).astype(np.int64)
        return cls.from_voxels(np.column_stack((ij, k)), navmap.origin, vs, dilate)

    def is_occupied(self, points: np.ndarray) -> np.ndarray:
        """(N,) True where a point lies in an occupied voxel (outside the grid = free)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = np.floor((p - self.origin) / self.voxel).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.occupied.shape)), axis=1)
        out = np.zeros(len(p), dtype=bool)
        q = ijk[inside]
        out[inside] = self.occupied[q[:, 0], q[:, 1], q[:, 2]]
        return out

    def mutually_visible(self, a: np.ndarray, b: np.ndarray, own_extent: float) -> bool:
        """True when the segment between two objects' centres a and b (sampled every half voxel) is free
        but for their own bodies: an unbroken run of occupied samples starting at either end and ending
        within ``own_extent`` metres of it."""
        a = np.asarray(a, dtype=np.float64).reshape(3)
        b = np.asarray(b, dtype=np.float64).reshape(3)
        length = float(np.linalg.norm(b - a))
        s = np.append(np.arange(0.0, length, 0.5 * self.voxel), length)
        pts = a + (s / max(length, 1e-12))[:, None] * (b - a)
        occ = self.is_occupied(pts)
        lo, hi = 0, len(s)
        while lo < hi and occ[lo] and s[lo] <= own_extent:  # a's own body
            lo += 1
        while hi > lo and occ[hi - 1] and length - s[hi - 1] <= own_extent:  # b's own body
            hi -= 1
        return not occ[lo:hi].any()

    def segments_clear(self, eye: np.ndarray, targets: np.ndarray, tolerance: float) -> np.ndarray:
        """(N,) True where the first occupied voxel met on the segment eye -> target (sampled every half
        voxel, so none is skipped) lies within ``tolerance`` metres of the target, or there is none:
        the first surface the ray meets is the object's own."""
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
        out = np.ones(len(targets), dtype=bool)
        step = 0.5 * self.voxel
        for n, t in enumerate(targets):
            d = t - eye
            length = float(np.linalg.norm(d))
            if length <= tolerance:
                continue
            s = np.append(np.arange(0.0, length, step), length)
            pts = eye + (s / length)[:, None] * d
            hit = np.flatnonzero(self.is_occupied(pts))
            if hit.size:
                out[n] = float(np.linalg.norm(pts[hit[0]] - t)) <= tolerance
        return out


def in_view(eye: np.ndarray, heading: float, targets: np.ndarray, config: VisibilityConfig) -> np.ndarray:
    """(N,) True where the targets lie within the distance and the field of view of a camera at
    ``eye`` looking along ``heading`` (radians about +z, 0 = +x), horizon level."""
    v = np.asarray(targets, dtype=np.float64).reshape(-1, 3) - np.asarray(eye, dtype=np.float64)
    dist = np.linalg.norm(v, axis=1)
    fwd = v[:, 0] * math.cos(heading) + v[:, 1] * math.sin(heading)
    side = -v[:, 0] * math.sin(heading) + v[:, 1] * math.cos(heading)
    azimuth = np.abs(np.arctan2(side, fwd))
    elevation = np.abs(np.arctan2(v[:, 2], np.hypot(fwd, side)))
    eps = 1e-9
    return (
        (dist <= config.max_distance)
        & (azimuth <= math.radians(config.hfov_deg) / 2 + eps)
        & (elevation <= math.radians(config.vfov_deg) / 2 + eps)
    )


def visible_mask(
    positions: np.ndarray,
    eye: np.ndarray,
    heading: float,
    occupancy: Occupancy | None,
    config: VisibilityConfig | None = None,
) -> np.ndarray:
    """(N,) True where a target (``positions`` (N, 3), same frame as ``eye`` and the occupancy) is
    visible from ``eye`` (see the module docstring); ``occupancy=None`` skips the occlusion test."""
    cfg = config or VisibilityConfig()
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    ok = in_view(eye, heading, pos, cfg)
    if cfg.occlusion and occupancy is not None and ok.any():
        idx = np.nonzero(ok)[0]
        ok[idx] = occupancy.segments_clear(eye, pos[idx], cfg.tolerance)
    return ok


def goal_in_view(
    goal: np.ndarray,
    eyes: np.ndarray,
    headings: np.ndarray,
    occupancy: Occupancy | None,
    config: VisibilityConfig | None = None,
) -> np.ndarray:
    """(N,) True where the ``goal`` position (3,) is visible (:func:`visible_mask`) from eye ``eyes[i]``
    (N, 3) looking along ``headings[i]``: the per-frame labels of Image2Nav's grounding loss."""
    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    heads = np.asarray(headings, dtype=np.float64).reshape(-1)
    if len(eyes) != len(heads):
        raise ValueError(f"goal_in_view: {len(eyes)} eyes but {len(heads)} headings")
    target = np.asarray(goal, dtype=np.float64).reshape(1, 3)
    return np.array(
        [
            bool(visible_mask(target, e, float(h), occupancy, config)[0])
            for e, h in zip(eyes, heads, strict=True)
        ],
        dtype=bool,
    )


def visible_categories(
    objects: Sequence,
    positions: np.ndarray,
    eye: np.ndarray,
    heading: float,
    occupancy: Occupancy | None,
    config: VisibilityConfig | None = None,
) -> list[str]:
    """Sorted unique categories of ``objects`` visible from ``eye`` (:func:`visible_mask`)."""
    ok = visible_mask(positions, eye, heading, occupancy, config)
    return sorted({objects[i].category for i in np.nonzero(ok)[0]})


@dataclass(frozen=True)
class NearConfig:
    """When an instruction may say "the goal near the X" (a spatial relation that must hold)."""

    max_distance: float = 2.5
    """Centre-to-centre distance (metres) within which two objects are "near"."""
    max_height_difference: float = 1.0
    """Larger vertical offsets mean another storey (or a shelf far above): never "near"."""
    own_extent: float = 1.0
    """How far (metres) from its centre an object's own body may block the line between the two."""

    def __post_init__(self) -> None:
        for name in ("max_distance", "max_height_difference", "own_extent"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"NearConfig.{name} must be a positive number, got {v!r}")


def near_categories(
    goal_index: int,
    objects: Sequence,
    positions: np.ndarray,
    occupancy: Occupancy | None,
    config: NearConfig | None = None,
) -> list[str]:
    """Sorted categories of the objects "near" ``objects[goal_index]``: within ``max_distance``, on the
    same storey (``max_height_difference``) and mutually visible (no wall between them; skipped when
    ``occupancy`` is None). The goal's own category is never its own landmark."""
    cfg = config or NearConfig()
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    goal = pos[goal_index]
    goal_cat = objects[goal_index].category
    out = set()
    for i, p in enumerate(pos):
        if i == goal_index or objects[i].category == goal_cat:
            continue
        if abs(p[2] - goal[2]) > cfg.max_height_difference or np.linalg.norm(p - goal) > cfg.max_distance:
            continue
        if occupancy is not None and not occupancy.mutually_visible(goal, p, cfg.own_extent):
            continue
        out.add(objects[i].category)
    return sorted(out)
