"""Analytic point-cloud worlds with exact ground truth, for tests, benchmarks and demos.

Surfaces are sampled on a regular lattice (``spacing`` metres) with normals facing the free side, so
every world can be fed straight into
:func:`image2sim.simulator.navigation.extract.extract_navmap_from_points`. Each world also carries its
exact free-floor predicate so tests can compare a navigable map against ground truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "SyntheticWorld",
    "plane_patch",
    "solid_box",
    "box_room",
    "l_room",
    "wall_with_gap",
    "two_levels_with_stairs",
    "rooms_grid",
]


@dataclass
class SyntheticWorld:
    """A sampled world: points (N, 3), normals (N, 3), cameras (C, 3) and ground-truth helpers.

    ``floor_height(xy)`` returns the walkable floor height below each (x, y) (NaN where there is
    none); ``obstacle_distance(xy, z)`` the exact horizontal distance to the nearest body-height
    obstacle for an agent standing at floor height ``z``.
    """

    points: np.ndarray
    normals: np.ndarray
    camera_positions: np.ndarray
    floor_height: Callable[[np.ndarray], np.ndarray]
    obstacle_distance: Callable[[np.ndarray], np.ndarray]
    boxes: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Axis-aligned solid obstacles (lo, hi) inside the walls."""
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    """(lo, hi) of the walkable interior in x, y."""


def plane_patch(origin, u, v, normal, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points of the parallelogram ``origin + s u + t v`` (s, t in [0, 1]) on a lattice, with ``normal``."""
    origin, u, v = (np.asarray(a, dtype=np.float64) for a in (origin, u, v))
    nu = max(2, int(np.ceil(np.linalg.norm(u) / spacing)) + 1)
    nv = max(2, int(np.ceil(np.linalg.norm(v) / spacing)) + 1)
    s, t = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    pts = origin + s.reshape(-1, 1) * u + t.reshape(-1, 1) * v
    n = np.asarray(normal, dtype=np.float64)
    return pts, np.broadcast_to(n / np.linalg.norm(n), pts.shape).copy()


def solid_box(lo, hi, spacing: float, skip_bottom: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Surface samples of an axis-aligned solid box with outward normals (bottom face optional)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    dx, dy, dz = hi - lo
    faces = [
        ((lo[0], lo[1], hi[2]), (dx, 0, 0), (0, dy, 0), (0, 0, 1)),
        ((lo[0], lo[1], lo[2]), (0, dy, 0), (0, 0, dz), (-1, 0, 0)),
        ((hi[0], lo[1], lo[2]), (0, dy, 0), (0, 0, dz), (1, 0, 0)),
        ((lo[0], lo[1], lo[2]), (dx, 0, 0), (0, 0, dz), (0, -1, 0)),
        ((lo[0], hi[1], lo[2]), (dx, 0, 0), (0, 0, dz), (0, 1, 0)),
    ]
    if not skip_bottom:
        faces.append(((lo[0], lo[1], lo[2]), (dx, 0, 0), (0, dy, 0), (0, 0, -1)))
    parts = [plane_patch(o, u, v, n, spacing) for o, u, v, n in faces]
    return np.concatenate([p for p, _ in parts]), np.concatenate([n for _, n in parts])


def _room_shell(lo, hi, height: float, spacing: float, z0: float = 0.0, ceiling: bool = True):
    """Floor, four inward walls and (optionally) a ceiling of an axis-aligned room."""
    (x0, y0), (x1, y1) = lo, hi
    dx, dy = x1 - x0, y1 - y0
    faces = [
        ((x0, y0, z0), (dx, 0, 0), (0, dy, 0), (0, 0, 1)),
        ((x0, y0, z0), (0, dy, 0), (0, 0, height), (1, 0, 0)),
        ((x1, y0, z0), (0, dy, 0), (0, 0, height), (-1, 0, 0)),
        ((x0, y0, z0), (dx, 0, 0), (0, 0, height), (0, 1, 0)),
        ((x0, y1, z0), (dx, 0, 0), (0, 0, height), (0, -1, 0)),
    ]
    if ceiling:
        faces.append(((x0, y0, z0 + height), (dx, 0, 0), (0, dy, 0), (0, 0, -1)))
    return [plane_patch(o, u, v, n, spacing) for o, u, v, n in faces]


def _box_distance(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Horizontal distance from points to an axis-aligned rectangle (0 inside)."""
    d = np.maximum(np.maximum(lo[:2] - xy, 0.0), np.maximum(xy - hi[:2], 0.0))
    return np.linalg.norm(d, axis=-1)


def _interior_distance(xy: np.ndarray, lo, hi) -> np.ndarray:
    """Distance from interior points to the boundary of the rectangle [lo, hi] (negative outside)."""
    xy = np.asarray(xy, float)
    return np.minimum.reduce([xy[:, 0] - lo[0], hi[0] - xy[:, 0], xy[:, 1] - lo[1], hi[1] - xy[:, 1]])


def box_room(
    size_x: float = 6.0,
    size_y: float = 4.0,
    height: float = 2.5,
    spacing: float = 0.025,
    boxes: list[tuple[tuple, tuple]] | None = None,
) -> SyntheticWorld:
    """An empty (or box-furnished) rectangular room [0, size_x] x [0, size_y] with a ceiling."""
    lo, hi = np.zeros(2), np.array([size_x, size_y])
    parts = _room_shell(lo, hi, height, spacing)
    solids = [(np.asarray(a, float), np.asarray(b, float)) for a, b in (boxes or [])]
    for a, b in solids:
        parts.append(solid_box(a, b, spacing))
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([n for _, n in parts])

    def floor_height(xy):
        xy = np.atleast_2d(xy)
        inside = _interior_distance(xy, lo, hi) > 0
        for a, b in solids:
            inside &= ~((_box_distance(xy, a, b) == 0) & (b[2] > 0.15))
        return np.where(inside, 0.0, np.nan)

    def obstacle_distance(xy):
        xy = np.atleast_2d(xy)
        d = _interior_distance(xy, lo, hi)
        for a, b in solids:
            if b[2] > 0.15 and a[2] < 1.5:  # inside the body band
                d = np.minimum(d, _box_distance(xy, a, b))
        return d

    cams = np.array([[size_x / 2, size_y / 2, 1.5]])
    return SyntheticWorld(pts, nrm, cams, floor_height, obstacle_distance, solids, (lo, hi))


def wall_with_gap(
    size_x: float = 6.0,
    size_y: float = 4.0,
    gap_width: float = 0.9,
    wall_thickness: float = 0.1,
    spacing: float = 0.025,
) -> SyntheticWorld:
    """A room split at x = size_x / 2 by a wall with a centred door gap of ``gap_width``."""
    xm = size_x / 2
    y_gap0, y_gap1 = size_y / 2 - gap_width / 2, size_y / 2 + gap_width / 2
    t = wall_thickness / 2
    boxes = [((xm - t, 0.0, 0.0), (xm + t, y_gap0, 2.5)), ((xm - t, y_gap1, 0.0), (xm + t, size_y, 2.5))]
    world = box_room(size_x, size_y, 2.5, spacing, boxes=boxes)
    world.camera_positions = np.array([[size_x / 4, size_y / 2, 1.5], [3 * size_x / 4, size_y / 2, 1.5]])
    return world


def l_room(
    size: float = 6.0, arm: float = 2.5, height: float = 2.5, spacing: float = 0.025
) -> SyntheticWorld:
    """An L-shaped room: the square [0, size]^2 minus the corner [arm, size] x [arm, size]."""
    lo, hi = np.zeros(2), np.array([size, size])
    cut_lo, cut_hi = np.array([arm, arm, 0.0]), np.array([size, size, height])
    parts = _room_shell(lo, hi, height, spacing, ceiling=False)
    # Replace the full floor by the L: keep floor samples outside the cut-out corner.
    floor_pts, floor_n = parts[0]
    keep = ~((floor_pts[:, 0] > arm) & (floor_pts[:, 1] > arm))
    parts[0] = (floor_pts[keep], floor_n[keep])
    parts.append(solid_box(cut_lo, cut_hi, spacing))  # the corner is solid (walls of the L)
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([n for _, n in parts])

    def floor_height(xy):
        xy = np.atleast_2d(xy)
        inside = (_interior_distance(xy, lo, hi) > 0) & (_box_distance(xy, cut_lo, cut_hi) > 0)
        return np.where(inside, 0.0, np.nan)

    def obstacle_distance(xy):
        xy = np.atleast_2d(xy)
        return np.minimum(_interior_distance(xy, lo, hi), _box_distance(xy, cut_lo, cut_hi))

    cams = np.array([[arm / 2, arm / 2, 1.5], [arm / 2, size - 0.8, 1.5], [size - 0.8, arm / 2, 1.5]])
    return SyntheticWorld(pts, nrm, cams, floor_height, obstacle_distance, [(cut_lo, cut_hi)], (lo, hi))


def two_levels_with_stairs(
    size_x: float = 8.0,
    size_y: float = 4.0,
    level_height: float = 1.2,
    riser: float = 0.15,
    tread: float = 0.3,
    stair_width: float = 1.2,
    spacing: float = 0.025,
) -> SyntheticWorld:
    """A low floor (z = 0, x < x_s) and a raised floor (z = level_height, x > x_e) joined by stairs.

    The stairs run along +x across ``y in [0, stair_width]``; the rest of the boundary between the
    two floors is a vertical drop (a cliff the agent must not walk off). No ceiling; walls 3 m high.
    """
    n_steps = int(round(level_height / riser))
    x_s = size_x / 2 - n_steps * tread / 2  # first riser
    x_e = x_s + (n_steps - 1) * tread  # last riser (top of the last step is the upper floor)
    parts = _room_shell(np.zeros(2), np.array([size_x, size_y]), level_height + 3.0, spacing, ceiling=False)
    fp, fn = parts[0]
    keep = fp[:, 0] < x_s
    parts[0] = (fp[keep], fn[keep])
    # Upper floor: a solid block from x_e to size_x (its top is the upper floor).
    parts.append(solid_box((x_e, 0.0, 0.0), (size_x, size_y, level_height), spacing))
    # Steps 1 .. n-1 as solid blocks across the stair lane; beside the lane, a vertical wall.
    for s in range(1, n_steps):
        x0 = x_s + (s - 1) * tread
        parts.append(solid_box((x0, 0.0, 0.0), (x0 + tread, stair_width, s * riser), spacing))
    # Beside the stairs: a pit? No -- a solid wall block between the stair lane and the far wall,
    # so the lower floor ends at x_s for y > stair_width (a vertical face of the upper storey).
    parts.append(solid_box((x_s, stair_width, 0.0), (x_e, size_y, level_height), spacing))
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([n for _, n in parts])

    def floor_height(xy):
        xy = np.atleast_2d(xy)
        out = np.full(len(xy), np.nan)
        inside = _interior_distance(xy, (0, 0), (size_x, size_y)) > 0
        low = inside & (xy[:, 0] < x_s)
        high = inside & ((xy[:, 0] > x_e) | ((xy[:, 0] >= x_s) & (xy[:, 1] > stair_width)))
        out[low] = 0.0
        out[high] = level_height
        stair = inside & (xy[:, 0] >= x_s) & (xy[:, 0] <= x_e) & (xy[:, 1] < stair_width)
        step = np.clip(np.floor((xy[stair, 0] - x_s) / tread) + 1, 1, n_steps - 1)
        out[stair] = step * riser
        return out

    def obstacle_distance(xy):  # exact only for the two flat storeys away from the stairs
        xy = np.atleast_2d(xy)
        return _interior_distance(xy, (0, 0), (size_x, size_y))

    cams = np.array([[x_s / 2, size_y / 2, 1.5], [(x_e + size_x) / 2, size_y / 2, level_height + 1.5]])
    world = SyntheticWorld(
        pts, nrm, cams, floor_height, obstacle_distance, [], (np.zeros(2), np.array([size_x, size_y]))
    )
    return world


def rooms_grid(
    nx: int,
    ny: int,
    room: float = 4.0,
    door: float = 1.0,
    height: float = 2.5,
    spacing: float = 0.05,
    seed: int = 0,
    furniture: int = 1,
) -> SyntheticWorld:
    """An ``nx`` x ``ny`` grid of square rooms joined by doors, with random furniture boxes.

    Area grows as ``nx * ny * room^2`` (benchmark scaling).
    """
    rng = np.random.default_rng(seed)
    sx, sy = nx * room, ny * room
    t = 0.05
    boxes = []
    for i in range(1, nx):  # interior walls at x = i * room with a door per room row
        for j in range(ny):
            y0, y1 = j * room, (j + 1) * room
            c = (y0 + y1) / 2
            boxes += [
                ((i * room - t, y0, 0.0), (i * room + t, c - door / 2, height)),
                ((i * room - t, c + door / 2, 0.0), (i * room + t, y1, height)),
            ]
    for j in range(1, ny):
        for i in range(nx):
            x0, x1 = i * room, (i + 1) * room
            c = (x0 + x1) / 2
            boxes += [
                ((x0, j * room - t, 0.0), (c - door / 2, j * room + t, height)),
                ((c + door / 2, j * room - t, 0.0), (x1, j * room + t, height)),
            ]
    for i in range(nx):
        for j in range(ny):
            for _ in range(furniture):
                w, d = rng.uniform(0.4, 1.0, size=2)
                x = i * room + rng.uniform(0.3, room - 0.3 - w)
                y = j * room + rng.uniform(0.3, room - 0.3 - d)
                if abs(x + w / 2 - (i + 0.5) * room) < 0.8 and abs(y + d / 2 - (j + 0.5) * room) < 0.8:
                    continue  # keep each room's centre (and its camera) free
                boxes.append(((x, y, 0.0), (x + w, y + d, rng.uniform(0.4, 1.2))))
    world = box_room(sx, sy, height, spacing, boxes=boxes)
    world.camera_positions = np.array(
        [[(i + 0.5) * room, (j + 0.5) * room, 1.5] for i in range(nx) for j in range(ny)]
    )
    return world
