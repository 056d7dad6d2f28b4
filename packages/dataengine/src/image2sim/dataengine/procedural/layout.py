"""Floor plans: rectangular rooms and corridors joined by door openings, walls with thickness.

All plan coordinates are integer multiples of :data:`UNIT` (5 cm) while the plan is built, so that
shared walls are found by exact comparison and the 5 cm ground-truth grid lines up with every room
boundary. Walls are centred on room boundaries; a room's *interior* is its centreline rectangle
shrunk by half the wall thickness. Geometry is returned as axis-aligned boxes (see
:class:`StructureBox`), which the ray caster and the mesh exporter share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from image2sim.dataengine.procedural.config import LayoutConfig

__all__ = [
    "UNIT",
    "ROOM_TYPES",
    "Room",
    "Door",
    "StructureBox",
    "Layout",
    "generate_layout",
    "LayoutError",
]

UNIT = 0.05
"""Plan coordinates are integer multiples of this length (metres)."""

ROOM_TYPES = ("living_room", "kitchen", "bedroom", "bathroom", "office", "hallway")
"""Room types, in the order of their ids (``rooms.json`` stores the name)."""

FLOOR_THICKNESS = 0.1
"""Thickness of floor and ceiling slabs, metres (only their inner faces are ever seen)."""

_DOOR_MARGIN = 0.1
"""Minimum distance between a door opening and the wall corner it sits next to, metres."""


class LayoutError(RuntimeError):
    """The generator could not build a plan satisfying the config (e.g. rooms too large to connect)."""


@dataclass(frozen=True)
class Room:
    """A rectangular room; ``x0 < x1``, ``y0 < y1`` are wall centrelines in metres."""

    index: int
    room_type: str
    x0: float
    y0: float
    x1: float
    y1: float

    def interior(self, wall_thickness: float) -> tuple[float, float, float, float]:
        """Inner wall faces ``(x0, y0, x1, y1)``: the centreline rectangle shrunk by half a wall."""
        h = 0.5 * wall_thickness
        return (self.x0 + h, self.y0 + h, self.x1 - h, self.y1 - h)

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def polygon(self, wall_thickness: float) -> list[list[float]]:
        """Interior polygon, counter-clockwise, as ``[[x, y], ...]``."""
        x0, y0, x1, y1 = self.interior(wall_thickness)
        return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


@dataclass(frozen=True)
class Door:
    """A door opening in the wall between rooms ``a`` and ``b``.

    ``axis`` is the axis the wall runs along (0: a wall along x at ``y = line``; 1: along y at
    ``x = line``); the opening spans ``[lo, hi]`` along that axis, from the floor to the door height.
    """

    a: int
    b: int
    axis: int
    line: float
    lo: float
    hi: float

    @property
    def width(self) -> float:
        return self.hi - self.lo

    def passage(self, wall_thickness: float) -> tuple[float, float, float, float]:
        """Footprint ``(x0, y0, x1, y1)`` of the opening through the wall."""
        h = 0.5 * wall_thickness
        if self.axis == 0:
            return (self.lo, self.line - h, self.hi, self.line + h)
        return (self.line - h, self.lo, self.line + h, self.hi)


@dataclass(frozen=True)
class StructureBox:
    """An axis-aligned structural box: ``kind`` is "floor", "ceiling", "wall" or "lintel"."""

    kind: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    room: int
    """Room index for floors/ceilings; -1 for walls (shared by the rooms on both sides)."""


@dataclass
class Layout:
    """A generated floor plan with its structural geometry."""

    rooms: list[Room]
    doors: list[Door]
    wall_thickness: float
    ceiling_height: float
    door_height: float
    boxes: list[StructureBox]

    def bounds(self) -> tuple[float, float, float, float]:
        """Outer footprint ``(x0, y0, x1, y1)`` including the outer half of exterior walls."""
        h = 0.5 * self.wall_thickness
        return (
            min(r.x0 for r in self.rooms) - h,
            min(r.y0 for r in self.rooms) - h,
            max(r.x1 for r in self.rooms) + h,
            max(r.y1 for r in self.rooms) + h,
        )

    def room_at(self, xy: np.ndarray) -> np.ndarray:
        """Index of the room whose centreline rectangle contains each point (N, 2); -1 outside.

        Points on a shared boundary go to the lower room index (deterministic tie-break).
        """
        xy = np.asarray(xy, dtype=np.float64)
        out = np.full(xy.shape[:-1], -1, dtype=np.int64)
        for room in reversed(self.rooms):
            inside = (
                (xy[..., 0] >= room.x0)
                & (xy[..., 0] <= room.x1)
                & (xy[..., 1] >= room.y0)
                & (xy[..., 1] <= room.y1)
            )
            out[inside] = room.index
        return out


# --- plan construction (integer units) -------------------------------------------------------------

_Rect = tuple[int, int, int, int]


def _units(metres: float) -> int:
    return int(round(metres / UNIT))


def _bsp_plan(rng: np.random.Generator, n: int, smin: int, smax: int) -> list[_Rect] | None:
    """Split a rectangle into ``n`` rooms with every side in ``[smin, smax]`` units, or None."""
    if n == 1:
        return [(0, 0, int(rng.integers(smin, smax + 1)), int(rng.integers(smin, smax + 1)))]
    side = rng.uniform(smin, min(smax, 1.6 * smin))
    aspect = rng.uniform(1.0, 2.0)
    area = n * side * side
    w = max(smin, int(round(math.sqrt(area * aspect))))
    d = max(smin, int(round(area / w)))
    rects: list[_Rect] = [(0, 0, w, d)]
    while len(rects) < n:
        order = sorted(
            range(len(rects)), key=lambda i: -((rects[i][2] - rects[i][0]) * (rects[i][3] - rects[i][1]))
        )
        for i in order:
            x0, y0, x1, y1 = rects[i]
            along_x = (x1 - x0) >= (y1 - y0)
            length = (x1 - x0) if along_x else (y1 - y0)
            if length >= 2 * smin:
                cut = int(rng.integers(smin, length - smin + 1))
                if along_x:
                    rects[i : i + 1] = [(x0, y0, x0 + cut, y1), (x0 + cut, y0, x1, y1)]
                else:
                    rects[i : i + 1] = [(x0, y0, x1, y0 + cut), (x0, y0 + cut, x1, y1)]
                break
        else:
            return None
    if any(max(r[2] - r[0], r[3] - r[1]) > smax for r in rects):
        return None
    return rects


def _corridor_plan(rng: np.random.Generator, n: int, smin: int, smax: int, cw: int) -> list[_Rect]:
    """A corridor (first rect) with the other ``n - 1`` rooms in rows on both of its long sides."""
    top = (n - 1 + 1) // 2
    rows: list[list[_Rect]] = []
    lengths = []
    for row, count in enumerate((top, n - 1 - top)):
        x = 0
        rects = []
        for _ in range(count):
            w = int(rng.integers(smin, smax + 1))
            d = int(rng.integers(smin, smax + 1))
            rects.append((x, cw, x + w, cw + d) if row == 0 else (x, -d, x + w, 0))
            x += w
        rows.append(rects)
        lengths.append(x)
    return [(0, 0, max(lengths), cw)] + rows[0] + rows[1]


def _shared_segment(a: _Rect, b: _Rect) -> tuple[int, int, int, int] | None:
    """``(axis, line, lo, hi)`` of the boundary shared by rects ``a`` and ``b`` (units), or None."""
    for axis in (0, 1):
        # axis 0: boundary along x at y = line; compare a's top with b's bottom and vice versa.
        lo_i, hi_i = (0, 2) if axis == 0 else (1, 3)
        n_lo, n_hi = (1, 3) if axis == 0 else (0, 2)
        for first, second in ((a, b), (b, a)):
            if first[n_hi] == second[n_lo]:
                lo = max(first[lo_i], second[lo_i])
                hi = min(first[hi_i], second[hi_i])
                if hi > lo:
                    return axis, first[n_hi], lo, hi
    return None


def _assign_types(rng: np.random.Generator, rects: list[_Rect], corridor: bool) -> list[str]:
    """Room types: the corridor is a hallway, the largest room a living room, the smallest a bathroom."""
    n = len(rects)
    types = [""] * n
    rooms = list(range(1, n)) if corridor else list(range(n))
    if corridor:
        types[0] = "hallway"
    by_area = sorted(rooms, key=lambda i: (-(rects[i][2] - rects[i][0]) * (rects[i][3] - rects[i][1]), i))
    if not by_area:
        return types
    types[by_area[0]] = "living_room"
    rest = by_area[1:]
    if len(rest) >= 2:
        types[rest[-1]] = "bathroom"
        rest = rest[:-1]
    pool = ["kitchen", "bedroom", "office", "bedroom", "bathroom", "office", "bedroom"]
    if rest:
        types[rest[0]] = "kitchen"
        for i, room in enumerate(rest[1:]):
            types[room] = pool[1 + (i + int(rng.integers(0, 3))) % (len(pool) - 1)]
    return types


def _choose_doors(
    rng: np.random.Generator, rects: list[_Rect], cfg: LayoutConfig, corridor: bool
) -> list[Door] | None:
    """Doors on a random spanning tree of the room adjacency graph (+ extra ones); None if disconnected."""
    t = cfg.wall_thickness
    need = cfg.door_width_min + t + 2 * _DOOR_MARGIN
    edges = []
    for i in range(len(rects)):
        for j in range(i + 1, len(rects)):
            seg = _shared_segment(rects[i], rects[j])
            if seg is not None and (seg[3] - seg[2]) * UNIT >= need:
                # Corridor edges first so rooms open onto the hallway when they can.
                weight = rng.uniform() - (1.0 if corridor and i == 0 else 0.0)
                edges.append((weight, i, j, seg))
    edges.sort(key=lambda e: e[0])
    parent = list(range(len(rects)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    chosen = []
    for _weight, i, j, seg in edges:
        ri, rj = find(i), find(j)
        if ri != rj:
            parent[ri] = rj
            chosen.append((i, j, seg))
        elif rng.uniform() < cfg.extra_door_probability:
            chosen.append((i, j, seg))
    if len({find(i) for i in range(len(rects))}) != 1:
        return None
    doors = []
    for i, j, (axis, line, lo, hi) in chosen:
        span = (hi - lo) * UNIT - t - 2 * _DOOR_MARGIN
        width = _units(rng.uniform(cfg.door_width_min, min(cfg.door_width_max, span)))
        slack_lo = lo + math.ceil((0.5 * t + _DOOR_MARGIN) / UNIT - 1e-9)
        slack_hi = hi - math.ceil((0.5 * t + _DOOR_MARGIN) / UNIT - 1e-9) - width
        if slack_hi < slack_lo:
            width = slack_hi - slack_lo + width
            slack_hi = slack_lo
        start = int(rng.integers(slack_lo, slack_hi + 1))
        doors.append(Door(i, j, axis, line * UNIT, start * UNIT, (start + width) * UNIT))
    doors.sort(key=lambda d: (d.a, d.b, d.axis, d.line, d.lo))
    return doors


def _merge(intervals: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[list[int]] = []
    for lo, hi in sorted(intervals):
        if out and lo <= out[-1][1]:
            out[-1][1] = max(out[-1][1], hi)
        else:
            out.append([lo, hi])
    return [(a, b) for a, b in out]


def _structure(
    rects: list[_Rect], doors: list[Door], t: float, height: float, door_height: float
) -> list[StructureBox]:
    """Floor and ceiling slabs per room, wall pieces between door openings, lintels over doors."""
    boxes: list[StructureBox] = []
    for k, (x0, y0, x1, y1) in enumerate(rects):
        boxes.append(
            StructureBox("floor", (x0 * UNIT, y0 * UNIT, -FLOOR_THICKNESS), (x1 * UNIT, y1 * UNIT, 0.0), k)
        )
    for k, (x0, y0, x1, y1) in enumerate(rects):
        boxes.append(
            StructureBox(
                "ceiling", (x0 * UNIT, y0 * UNIT, height), (x1 * UNIT, y1 * UNIT, height + FLOOR_THICKNESS), k
            )
        )
    lines: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for x0, y0, x1, y1 in rects:
        for key, iv in (((0, y0), (x0, x1)), ((0, y1), (x0, x1)), ((1, x0), (y0, y1)), ((1, x1), (y0, y1))):
            lines.setdefault(key, []).append(iv)
    h = 0.5 * t
    for (axis, line), intervals in sorted(lines.items()):
        cuts = sorted(
            (_units(d.lo), _units(d.hi)) for d in doors if d.axis == axis and _units(d.line) == line
        )
        for lo, hi in _merge(intervals):
            pieces = []
            start, start_open = lo, False
            for c0, c1 in cuts:
                if c1 <= lo or c0 >= hi:
                    continue
                pieces.append((start, c0, start_open, True))
                start, start_open = c1, True
            pieces.append((start, hi, start_open, False))
            for a, b, a_door, b_door in pieces:
                # Extend wall ends by half a thickness to close corners, but not at door jambs.
                a_m = a * UNIT - (0.0 if a_door else h)
                b_m = b * UNIT + (0.0 if b_door else h)
                if b_m - a_m <= 1e-9:
                    continue
                boxes.append(_wall_box("wall", axis, line * UNIT, a_m, b_m, h, 0.0, height))
        for c0, c1 in cuts:
            boxes.append(_wall_box("lintel", axis, line * UNIT, c0 * UNIT, c1 * UNIT, h, door_height, height))
    return boxes


def _wall_box(
    kind: str, axis: int, line: float, a: float, b: float, h: float, z0: float, z1: float
) -> StructureBox:
    if axis == 0:
        return StructureBox(kind, (a, line - h, z0), (b, line + h, z1), -1)
    return StructureBox(kind, (line - h, a, z0), (line + h, b, z1), -1)


def generate_layout(cfg: LayoutConfig, rng: np.random.Generator, max_tries: int = 200) -> Layout:
    """A random connected floor plan following ``cfg`` (deterministic for a given ``rng`` state)."""
    smin, smax, cw = _units(cfg.room_size_min), _units(cfg.room_size_max), _units(cfg.corridor_width)
    for _ in range(max_tries):
        n = int(rng.integers(cfg.rooms_min, cfg.rooms_max + 1))
        corridor = n >= 3 and rng.uniform() < cfg.corridor_probability
        rects = _corridor_plan(rng, n, smin, smax, cw) if corridor else _bsp_plan(rng, n, smin, smax)
        if rects is None:
            continue
        doors = _choose_doors(rng, rects, cfg, corridor) if n > 1 else []
        if doors is None:
            continue
        height = _units(rng.uniform(cfg.ceiling_height_min, cfg.ceiling_height_max)) * UNIT
        types = _assign_types(rng, rects, corridor)
        rooms = [
            Room(k, types[k], r[0] * UNIT, r[1] * UNIT, r[2] * UNIT, r[3] * UNIT) for k, r in enumerate(rects)
        ]
        boxes = _structure(rects, doors, cfg.wall_thickness, height, cfg.door_height)
        return Layout(rooms, doors, cfg.wall_thickness, height, cfg.door_height, boxes)
    raise LayoutError(
        f"could not build a connected plan of {cfg.rooms_min}-{cfg.rooms_max} rooms with sides "
        f"{cfg.room_size_min}-{cfg.room_size_max} m in {max_tries} tries; widen layout.room_size_max"
    )
