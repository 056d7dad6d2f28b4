"""Object categories, their box-built shapes, and placement by room type without interpenetration.

Each object is a set of axis-aligned parts in a local frame (x = width, y = depth with the *front*
at -y and the back at +y, z up from the floor or support), rotated by a multiple of 90 degrees about
+Z and translated; the object's oriented 3D box is the local ``[-w/2, w/2] x [-d/2, d/2] x [0, h]``
box under that pose. Quarter-turn yaws keep every part axis-aligned in the world, so the renderer
intersects boxes exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Category",
    "CATEGORIES",
    "CATEGORY_BY_NAME",
    "STRUCTURE_CATEGORIES",
    "WALKABLE_CATEGORY_IDS",
    "ROOM_PROGRAMS",
    "SMALL_BY_ROOM",
    "Part",
    "Surface",
    "SceneObject",
    "build_parts",
    "category_table",
]


@dataclass(frozen=True)
class Category:
    """One semantic category.

    ``placement``: "structure" (floor/wall/ceiling), "wall" (backed against a wall), "center" (near
    the room centre), "free" (anywhere), "mounted" (hung on a wall at ``mount_z``), "surface" (small
    item on a support surface), "companion" (placed next to a parent, e.g. chairs at a table).
    """

    id: int
    name: str
    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]
    placement: str
    shape: str
    material: str
    small: bool = False
    walkable: bool = False
    mount_z: tuple[float, float] = (0.0, 0.0)


def _c(id, name, lo, hi, placement, shape, material, **kw) -> Category:  # noqa: A002 - table shorthand
    return Category(id, name, lo, hi, placement, shape, material, **kw)


STRUCTURE_CATEGORIES = {"floor": 1, "wall": 2, "ceiling": 3}
"""Category ids of the structure (lintels above doors are walls)."""

CATEGORIES: tuple[Category, ...] = (
    _c(1, "floor", (0, 0, 0), (0, 0, 0), "structure", "box", "floor_wood"),
    _c(2, "wall", (0, 0, 0), (0, 0, 0), "structure", "box", "wall_paint"),
    _c(3, "ceiling", (0, 0, 0), (0, 0, 0), "structure", "box", "ceiling"),
    _c(4, "sofa", (1.6, 0.8, 0.75), (2.4, 1.0, 0.95), "wall", "sofa", "fabric"),
    _c(5, "armchair", (0.7, 0.7, 0.75), (0.95, 0.9, 1.0), "free", "sofa", "fabric"),
    _c(6, "coffee_table", (0.8, 0.5, 0.35), (1.3, 0.8, 0.5), "center", "table", "wood"),
    _c(7, "tv_stand", (1.0, 0.35, 0.4), (1.8, 0.5, 0.6), "wall", "cabinet", "wood"),
    _c(8, "tv", (0.9, 0.05, 0.55), (1.5, 0.08, 0.85), "mounted", "panel", "screen", mount_z=(1.1, 1.5)),
    _c(9, "bookshelf", (0.6, 0.28, 1.4), (1.2, 0.4, 2.1), "wall", "shelf", "wood"),
    _c(10, "rug", (1.2, 0.8, 0.01), (2.4, 1.8, 0.02), "center", "box", "carpet", walkable=True),
    _c(11, "plant", (0.35, 0.35, 0.6), (0.6, 0.6, 1.6), "free", "plant", "plant"),
    _c(12, "floor_lamp", (0.3, 0.3, 1.4), (0.45, 0.45, 1.8), "free", "lamp", "metal"),
    _c(13, "painting", (0.4, 0.03, 0.3), (1.2, 0.05, 0.9), "mounted", "framed", "art", mount_z=(1.3, 1.7)),
    _c(14, "dining_table", (1.0, 0.7, 0.72), (1.8, 1.0, 0.78), "center", "table", "wood"),
    _c(15, "chair", (0.4, 0.4, 0.8), (0.5, 0.5, 1.0), "companion", "chair", "wood"),
    _c(16, "kitchen_counter", (0.8, 0.55, 0.86), (2.4, 0.65, 0.92), "wall", "counter", "wood"),
    _c(17, "fridge", (0.6, 0.6, 1.6), (0.8, 0.75, 2.0), "wall", "fridge", "metal"),
    _c(18, "stove", (0.55, 0.55, 0.85), (0.75, 0.65, 0.92), "wall", "stove", "metal"),
    _c(19, "sink", (0.5, 0.4, 0.8), (0.9, 0.55, 0.9), "wall", "vanity", "ceramic"),
    _c(20, "bed", (0.9, 1.9, 0.9), (1.8, 2.15, 1.2), "wall", "bed", "fabric"),
    _c(21, "nightstand", (0.4, 0.35, 0.45), (0.55, 0.45, 0.6), "wall", "cabinet", "wood"),
    _c(22, "wardrobe", (0.8, 0.55, 1.8), (1.8, 0.65, 2.2), "wall", "cabinet", "wood"),
    _c(23, "dresser", (0.8, 0.4, 0.75), (1.4, 0.5, 1.0), "wall", "cabinet", "wood"),
    _c(24, "desk", (1.0, 0.55, 0.72), (1.6, 0.8, 0.77), "wall", "desk", "wood"),
    _c(25, "office_chair", (0.5, 0.5, 0.9), (0.65, 0.65, 1.15), "companion", "office_chair", "plastic"),
    _c(26, "toilet", (0.36, 0.6, 0.7), (0.42, 0.75, 0.85), "wall", "toilet", "ceramic"),
    _c(27, "bathtub", (1.5, 0.7, 0.5), (1.8, 0.85, 0.6), "wall", "tub", "ceramic"),
    _c(28, "washing_machine", (0.58, 0.55, 0.82), (0.62, 0.62, 0.88), "wall", "appliance", "plastic"),
    _c(29, "mirror", (0.4, 0.02, 0.5), (0.9, 0.04, 1.0), "mounted", "framed", "glass", mount_z=(1.3, 1.6)),
    _c(30, "cabinet", (0.5, 0.35, 0.7), (1.2, 0.6, 1.2), "wall", "cabinet", "wood"),
    _c(31, "wall_shelf", (0.6, 0.2, 0.03), (1.2, 0.3, 0.05), "mounted", "box", "wood", mount_z=(1.2, 1.6)),
    _c(32, "shoe_rack", (0.6, 0.3, 0.4), (1.0, 0.35, 0.6), "wall", "shelf", "wood"),
    _c(
        33,
        "clock",
        (0.25, 0.04, 0.25),
        (0.4, 0.06, 0.4),
        "mounted",
        "framed",
        "plastic",
        small=True,
        mount_z=(1.7, 2.0),
    ),
    _c(34, "monitor", (0.45, 0.15, 0.35), (0.7, 0.22, 0.5), "surface", "monitor", "screen", small=True),
    _c(35, "laptop", (0.3, 0.22, 0.2), (0.38, 0.26, 0.25), "surface", "laptop", "metal", small=True),
    _c(36, "table_lamp", (0.15, 0.15, 0.3), (0.3, 0.3, 0.55), "surface", "lamp", "ceramic", small=True),
    _c(37, "vase", (0.08, 0.08, 0.15), (0.18, 0.18, 0.4), "surface", "vase", "ceramic", small=True),
    _c(38, "bowl", (0.12, 0.12, 0.05), (0.3, 0.3, 0.12), "surface", "bowl", "ceramic", small=True),
    _c(39, "book_stack", (0.15, 0.2, 0.05), (0.25, 0.3, 0.2), "surface", "books", "paper", small=True),
    _c(40, "cup", (0.07, 0.07, 0.08), (0.1, 0.1, 0.12), "surface", "cup", "ceramic", small=True),
    _c(41, "small_plant", (0.1, 0.1, 0.15), (0.2, 0.2, 0.35), "surface", "plant", "plant", small=True),
    _c(42, "microwave", (0.45, 0.32, 0.26), (0.55, 0.4, 0.32), "surface", "appliance", "metal", small=True),
    _c(43, "kettle", (0.15, 0.12, 0.2), (0.22, 0.18, 0.28), "surface", "cup", "metal", small=True),
    _c(44, "picture_frame", (0.12, 0.04, 0.15), (0.25, 0.08, 0.3), "surface", "framed", "art", small=True),
    _c(45, "storage_box", (0.2, 0.2, 0.1), (0.45, 0.35, 0.3), "surface", "lidded", "plastic", small=True),
)
"""The category table: id, name, size ranges (width, depth, height in metres), placement rule, shape
builder, material family, "small" flag (long-tail items on surfaces), walkable flag (rugs)."""

CATEGORY_BY_NAME = {c.name: c for c in CATEGORIES}
WALKABLE_CATEGORY_IDS = frozenset([STRUCTURE_CATEGORIES["floor"]] + [c.id for c in CATEGORIES if c.walkable])
"""Category ids an agent may stand on (floor and rugs): use these to find floor pixels in semantics."""
CATEGORY_BY_ID = {c.id: c for c in CATEGORIES}

ROOM_PROGRAMS: dict[str, tuple[tuple[str, int, int], ...]] = {
    "living_room": (
        ("sofa", 1, 1),
        ("coffee_table", 1, 1),
        ("tv_stand", 0, 1),
        ("tv", 0, 1),
        ("armchair", 0, 2),
        ("bookshelf", 0, 1),
        ("cabinet", 0, 1),
        ("plant", 0, 2),
        ("floor_lamp", 0, 1),
        ("painting", 0, 2),
        ("wall_shelf", 0, 1),
        ("clock", 0, 1),
        ("rug", 0, 1),
    ),
    "kitchen": (
        ("kitchen_counter", 1, 2),
        ("fridge", 1, 1),
        ("stove", 0, 1),
        ("dining_table", 0, 1),
        ("cabinet", 0, 1),
        ("plant", 0, 1),
        ("painting", 0, 1),
        ("clock", 0, 1),
        ("wall_shelf", 0, 1),
    ),
    "bedroom": (
        ("bed", 1, 1),
        ("nightstand", 1, 2),
        ("wardrobe", 0, 1),
        ("dresser", 0, 1),
        ("desk", 0, 1),
        ("plant", 0, 1),
        ("floor_lamp", 0, 1),
        ("painting", 0, 2),
        ("mirror", 0, 1),
        ("rug", 0, 1),
    ),
    "bathroom": (
        ("toilet", 1, 1),
        ("sink", 1, 1),
        ("bathtub", 0, 1),
        ("washing_machine", 0, 1),
        ("mirror", 0, 1),
        ("cabinet", 0, 1),
        ("wall_shelf", 0, 1),
        ("plant", 0, 1),
    ),
    "office": (
        ("desk", 1, 2),
        ("bookshelf", 0, 2),
        ("cabinet", 0, 1),
        ("armchair", 0, 1),
        ("plant", 0, 1),
        ("floor_lamp", 0, 1),
        ("painting", 0, 1),
        ("clock", 0, 1),
        ("wall_shelf", 0, 1),
        ("rug", 0, 1),
    ),
    "hallway": (
        ("shoe_rack", 0, 1),
        ("cabinet", 0, 1),
        ("plant", 0, 1),
        ("painting", 0, 2),
        ("mirror", 0, 1),
        ("clock", 0, 1),
    ),
}
"""Furniture per room type: (category, min count, max count), placed in this order (large first)."""

COMPANIONS: dict[str, tuple[str, int, int, str]] = {
    "dining_table": ("chair", 2, 4, "around"),
    "desk": ("office_chair", 1, 1, "front"),
}
"""Objects placed next to a parent: (category, min, max, where)."""

SMALL_BY_ROOM: dict[str, tuple[str, ...]] = {
    "living_room": (
        "vase",
        "book_stack",
        "bowl",
        "small_plant",
        "table_lamp",
        "picture_frame",
        "clock",
        "storage_box",
    ),
    "kitchen": ("microwave", "kettle", "bowl", "cup", "vase", "small_plant", "storage_box"),
    "bedroom": ("table_lamp", "book_stack", "picture_frame", "vase", "clock", "cup"),
    "bathroom": ("small_plant", "cup", "storage_box", "vase", "bowl"),
    "office": ("monitor", "laptop", "book_stack", "cup", "table_lamp", "storage_box", "picture_frame"),
    "hallway": ("vase", "small_plant", "storage_box", "bowl", "picture_frame"),
}
"""Small long-tail items that may go on support surfaces in each room type."""


@dataclass(frozen=True)
class Part:
    """An axis-aligned part in world coordinates; ``slot`` picks the object's material (0..2)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    slot: int


@dataclass(frozen=True)
class Surface:
    """A horizontal support rectangle at height ``z`` with free ``clearance`` above it (world)."""

    z: float
    x0: float
    y0: float
    x1: float
    y1: float
    clearance: float


@dataclass
class SceneObject:
    """A placed object with its exact geometry and ground truth."""

    instance_id: int
    category: Category
    room: int
    center: np.ndarray
    """Centre of the oriented box (world, metres)."""
    size: tuple[float, float, float]
    """Oriented box extents (width along local x, depth along local y, height)."""
    yaw: float
    """Rotation about +Z of the local frame (radians, a multiple of pi/2)."""
    parts: list[Part]
    surfaces: list[Surface] = field(default_factory=list)
    materials: tuple[int, int, int] = (0, 0, 0)
    support: int = 0
    """Instance id of the object this one stands on (0 = floor or wall)."""

    @property
    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds (equal to the oriented box for quarter-turn yaws)."""
        lo = np.min([p.lo for p in self.parts], axis=0)
        hi = np.max([p.hi for p in self.parts], axis=0)
        return lo, hi

    def corners(self) -> np.ndarray:
        """The 8 corners (8, 3) of the oriented box in the world."""
        w, d, h = self.size
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = []
        for z in (0.0, h):
            for x, y in ((-w / 2, -d / 2), (w / 2, -d / 2), (w / 2, d / 2), (-w / 2, d / 2)):
                out.append(
                    (
                        self.center[0] + c * x - s * y,
                        self.center[1] + s * x + c * y,
                        self.center[2] - h / 2 + z,
                    )
                )
        return np.asarray(out)

    def to_json(self, room_types: list[str]) -> dict:
        return {
            "id": int(self.instance_id),
            "category": self.category.name,
            "category_id": int(self.category.id),
            "small": bool(self.category.small),
            "walkable": bool(self.category.walkable),
            "room": int(self.room),
            "room_type": room_types[self.room],
            "support": int(self.support),
            "center": [float(v) for v in self.center],
            "box": {
                "center": [float(v) for v in self.center],
                "size": [float(v) for v in self.size],
                "yaw": float(self.yaw),
                "corners": [[float(v) for v in row] for row in self.corners()],
            },
            "aabb": {"min": [float(v) for v in self.aabb[0]], "max": [float(v) for v in self.aabb[1]]},
            "materials": [int(m) for m in self.materials],
        }


def category_table() -> list[dict]:
    """JSON-friendly category table (what ``gt/categories.json`` stores)."""
    return [
        {
            "id": c.id,
            "name": c.name,
            "size_min": list(c.size_min),
            "size_max": list(c.size_max),
            "placement": c.placement,
            "shape": c.shape,
            "small": c.small,
            "walkable": c.walkable,
        }
        for c in CATEGORIES
    ]


# --- shape builders (local frame) ---------------------------------------------------------------

_Local = tuple[float, float, float, float, float, float, int]  # x0, y0, z0, x1, y1, z1, slot
_LocalSurface = tuple[float, float, float, float, float, float]  # z, x0, y0, x1, y1, clearance


def _shape_box(w, d, h, rng):
    return [(-w / 2, -d / 2, 0.0, w / 2, d / 2, h, 0)], [(h, -w / 2, -d / 2, w / 2, d / 2, 0.4)]


def _shape_cabinet(w, d, h, rng):
    plinth = min(0.08, 0.2 * h)
    parts = [
        (-w / 2 + 0.03, -d / 2 + 0.05, 0.0, w / 2 - 0.03, d / 2, plinth, 1),
        (-w / 2, -d / 2 + 0.02, plinth, w / 2, d / 2, h, 0),
    ]
    doors = 1 if w < 0.7 else 2
    for k in range(doors):
        cx = (
            -w / 2 + (k + 0.5) * w / doors + (0.12 if k == 0 and doors == 2 else -0.12 if doors == 2 else 0.0)
        )
        parts.append(
            (
                cx - 0.06,
                -d / 2,
                plinth + 0.6 * (h - plinth) - 0.015,
                cx + 0.06,
                -d / 2 + 0.02,
                plinth + 0.6 * (h - plinth) + 0.015,
                2,
            )
        )
    return parts, [(h, -w / 2, -d / 2 + 0.02, w / 2, d / 2, 0.45)]


def _shape_counter(w, d, h, rng):
    parts, _ = _shape_cabinet(w, d - 0.0, h - 0.04, rng)
    parts.append((-w / 2, -d / 2 + 0.02, h - 0.04, w / 2, d / 2, h, 1))
    return parts, [(h, -w / 2, -d / 2 + 0.02, w / 2, d / 2, 0.45)]


def _shape_table(w, d, h, rng):
    top, leg, inset = 0.04, float(rng.uniform(0.04, 0.07)), 0.03
    parts = [(-w / 2, -d / 2, h - top, w / 2, d / 2, h, 0)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x = sx * (w / 2 - inset - leg / 2)
            y = sy * (d / 2 - inset - leg / 2)
            parts.append((x - leg / 2, y - leg / 2, 0.0, x + leg / 2, y + leg / 2, h - top, 1))
    return parts, [(h, -w / 2, -d / 2, w / 2, d / 2, 0.5)]


def _shape_desk(w, d, h, rng):
    top, side = 0.035, 0.03
    parts = [(-w / 2, -d / 2, h - top, w / 2, d / 2, h, 0)]
    for sx in (-1, 1):
        x0 = w / 2 - side if sx > 0 else -w / 2
        parts.append((x0, -d / 2 + 0.05, 0.0, x0 + side, d / 2, h - top, 1))
    parts.append((-w / 2 + side, d / 2 - 0.02, h - top - 0.3, w / 2 - side, d / 2, h - top, 1))
    return parts, [(h, -w / 2, -d / 2, w / 2, d / 2, 0.6)]


def _shape_chair(w, d, h, rng):
    seat = float(rng.uniform(0.42, 0.48))
    leg = 0.04
    parts = [(-w / 2, -d / 2, seat - 0.04, w / 2, d / 2, seat, 0)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - leg / 2), sy * (d / 2 - leg / 2)
            parts.append((x - leg / 2, y - leg / 2, 0.0, x + leg / 2, y + leg / 2, seat - 0.04, 1))
    parts.append((-w / 2, d / 2 - 0.04, seat, w / 2, d / 2, h, 0))
    return parts, []


def _shape_office_chair(w, d, h, rng):
    seat = float(rng.uniform(0.45, 0.52))
    parts = [
        (-w / 2, -0.03, 0.0, w / 2, 0.03, 0.06, 1),
        (-0.03, -d / 2, 0.0, 0.03, d / 2, 0.06, 1),
        (-0.03, -0.03, 0.06, 0.03, 0.03, seat - 0.07, 1),
        (-w / 2 + 0.03, -d / 2 + 0.03, seat - 0.07, w / 2 - 0.03, d / 2 - 0.08, seat, 0),
        (-w / 2 + 0.06, d / 2 - 0.08, seat - 0.02, w / 2 - 0.06, d / 2 - 0.02, h, 0),
    ]
    return parts, []


def _shape_sofa(w, d, h, rng):
    base = float(rng.uniform(0.38, 0.45))
    arm = float(rng.uniform(0.12, 0.22))
    arm_h = min(h, base + float(rng.uniform(0.18, 0.28)))
    back = float(rng.uniform(0.15, 0.25))
    parts = [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2, base, 0),
        (-w / 2 + arm, d / 2 - back, base, w / 2 - arm, d / 2, h, 0),
        (-w / 2, -d / 2, base, -w / 2 + arm, d / 2, arm_h, 1),
        (w / 2 - arm, -d / 2, base, w / 2, d / 2, arm_h, 1),
    ]
    return parts, []


def _shape_bed(w, d, h, rng):
    frame = float(rng.uniform(0.25, 0.32))
    mattress = frame + float(rng.uniform(0.15, 0.22))
    head = 0.06
    parts = [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2 - head, frame, 1),
        (-w / 2 + 0.02, -d / 2 + 0.02, frame, w / 2 - 0.02, d / 2 - head, mattress, 0),
        (-w / 2, d / 2 - head, 0.0, w / 2, d / 2, h, 1),
        (-w / 2 + 0.12, d / 2 - head - 0.45, mattress, w / 2 - 0.12, d / 2 - head - 0.05, mattress + 0.1, 2),
    ]
    return parts, []


def _shape_shelf(w, d, h, rng):
    side, board, back = 0.025, 0.025, 0.015
    parts = [
        (-w / 2, -d / 2, 0.0, -w / 2 + side, d / 2, h, 0),
        (w / 2 - side, -d / 2, 0.0, w / 2, d / 2, h, 0),
        (-w / 2 + side, d / 2 - back, 0.0, w / 2 - side, d / 2, h, 1),
    ]
    levels = max(2, int(h / float(rng.uniform(0.3, 0.42))))
    zs = [i * (h - board) / (levels - 1) for i in range(levels)] if levels > 1 else [0.0]
    surfaces = []
    for i, z in enumerate(zs):
        parts.append((-w / 2 + side, -d / 2, z, w / 2 - side, d / 2 - back, z + board, 0))
        clear = (zs[i + 1] - z - board) if i + 1 < len(zs) else 0.35
        surfaces.append((z + board, -w / 2 + side, -d / 2, w / 2 - side, d / 2 - back, clear))
    return parts, surfaces


def _shape_lamp(w, d, h, rng):
    shade = float(rng.uniform(0.2, 0.35)) * h
    pole = max(0.02, 0.12 * min(w, d))
    parts = [
        (-w / 2 * 0.7, -d / 2 * 0.7, 0.0, w / 2 * 0.7, d / 2 * 0.7, 0.03 * h + 0.005, 1),
        (-pole / 2, -pole / 2, 0.03 * h + 0.005, pole / 2, pole / 2, h - shade, 1),
        (-w / 2, -d / 2, h - shade, w / 2, d / 2, h, 0),
    ]
    return parts, []


def _shape_plant(w, d, h, rng):
    pot = float(rng.uniform(0.2, 0.35)) * h
    parts = [(-w * 0.3, -d * 0.3, 0.0, w * 0.3, d * 0.3, pot, 1)]
    levels = int(rng.integers(1, 4))
    z = pot
    for k in range(levels):
        f = 1.0 - 0.25 * k
        top = pot + (h - pot) * (k + 1) / levels
        parts.append((-w / 2 * f, -d / 2 * f, z, w / 2 * f, d / 2 * f, top, 0))
        z = top
    return parts, []


def _shape_panel(w, d, h, rng):
    return [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2 - 0.01, h, 0),
        (-w / 2 + 0.02, d / 2 - 0.01, 0.02, w / 2 - 0.02, d / 2, h - 0.02, 1),
    ], []


def _shape_framed(w, d, h, rng):
    border = min(0.05, 0.12 * min(w, h))
    parts = [
        (-w / 2, -d / 2 + 0.008, 0.0, w / 2, d / 2, h, 1),
        (-w / 2 + border, -d / 2, border, w / 2 - border, -d / 2 + 0.008, h - border, 0),
    ]
    return parts, []


def _shape_fridge(w, d, h, rng):
    split = float(rng.uniform(0.55, 0.7)) * h
    parts = [
        (-w / 2, -d / 2 + 0.03, 0.0, w / 2, d / 2, split - 0.005, 0),
        (-w / 2, -d / 2 + 0.03, split + 0.005, w / 2, d / 2, h, 0),
        (-w / 2, -d / 2 + 0.03, split - 0.005, w / 2, d / 2 - 0.02, split + 0.005, 1),
        (w / 2 - 0.08, -d / 2, split - 0.35, w / 2 - 0.05, -d / 2 + 0.03, split - 0.05, 2),
        (w / 2 - 0.08, -d / 2, split + 0.05, w / 2 - 0.05, -d / 2 + 0.03, split + 0.4, 2),
    ]
    return parts, []


def _shape_stove(w, d, h, rng):
    parts = [(-w / 2, -d / 2, 0.0, w / 2, d / 2, h - 0.012, 0)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * w / 4, sy * d / 4
            r = 0.08 if sx * sy > 0 else 0.06
            parts.append((x - r, y - r, h - 0.012, x + r, y + r, h, 2))
    return parts, []


def _shape_vanity(w, d, h, rng):
    top = 0.04
    basin = (-w * 0.3, -d * 0.35, h - 0.12, w * 0.3, d * 0.25, h - 0.12 + 0.02)
    parts = [
        (-w / 2, -d / 2 + 0.02, 0.0, w / 2, d / 2, h - 0.12 - top, 1),
        (-w / 2, -d / 2 + 0.02, h - 0.12 - top, w / 2, d / 2, h - 0.12, 0),
        (*basin, 0),
        (-0.02, d / 2 - 0.1, h - 0.12, 0.02, d / 2 - 0.05, h, 2),
    ]
    return parts, []


def _shape_toilet(w, d, h, rng):
    seat = float(rng.uniform(0.38, 0.44))
    tank = 0.18
    parts = [
        (-w * 0.3, -d / 2 + 0.12, 0.0, w * 0.3, d / 2 - tank, seat - 0.06, 0),
        (-w / 2, -d / 2, seat - 0.06, w / 2, d / 2 - tank, seat, 0),
        (-w / 2, d / 2 - tank, 0.1, w / 2, d / 2, h, 1),
    ]
    return parts, []


def _shape_tub(w, d, h, rng):
    rim, bottom = 0.07, 0.1
    parts = [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2, bottom, 0),
        (-w / 2, -d / 2, bottom, w / 2, -d / 2 + rim, h, 0),
        (-w / 2, d / 2 - rim, bottom, w / 2, d / 2, h, 0),
        (-w / 2, -d / 2 + rim, bottom, -w / 2 + rim, d / 2 - rim, h, 0),
        (w / 2 - rim, -d / 2 + rim, bottom, w / 2, d / 2 - rim, h, 0),
    ]
    return parts, []


def _shape_appliance(w, d, h, rng):
    door = 0.55 * min(w, h)
    parts = [
        (-w / 2, -d / 2 + 0.02, 0.0, w / 2, d / 2, h, 0),
        (-door / 2, -d / 2, h * 0.45 - door / 2, door / 2, -d / 2 + 0.02, h * 0.45 + door / 2, 2),
    ]
    return parts, [(h, -w / 2, -d / 2 + 0.02, w / 2, d / 2, 0.3)]


def _shape_monitor(w, d, h, rng):
    panel = 0.03
    parts = [
        (-w * 0.18, -d / 2, 0.0, w * 0.18, d / 2, 0.02, 1),
        (-0.025, -0.025 + d * 0.2, 0.02, 0.025, 0.025 + d * 0.2, 0.35 * h, 1),
        (-w / 2, -panel / 2, 0.3 * h, w / 2, panel / 2, h, 0),
    ]
    return parts, []


def _shape_laptop(w, d, h, rng):
    parts = [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2 - 0.012, 0.02, 0),
        (-w / 2, d / 2 - 0.012, 0.0, w / 2, d / 2, h, 1),
    ]
    return parts, []


def _shape_vase(w, d, h, rng):
    neck = float(rng.uniform(0.5, 0.8))
    return [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2, neck * h, 0),
        (-w * 0.25, -d * 0.25, neck * h, w * 0.25, d * 0.25, h, 0),
    ], []


def _shape_bowl(w, d, h, rng):
    t = max(0.01, 0.1 * min(w, d))
    return [
        (-w / 2, -d / 2, 0.0, w / 2, d / 2, t, 0),
        (-w / 2, -d / 2, t, w / 2, -d / 2 + t, h, 0),
        (-w / 2, d / 2 - t, t, w / 2, d / 2, h, 0),
        (-w / 2, -d / 2 + t, t, -w / 2 + t, d / 2 - t, h, 0),
        (w / 2 - t, -d / 2 + t, t, w / 2, d / 2 - t, h, 0),
    ], []


def _shape_books(w, d, h, rng):
    n = int(rng.integers(2, 6))
    parts = []
    z = 0.0
    for k in range(n):
        fw = float(rng.uniform(0.75, 1.0))
        fd = float(rng.uniform(0.75, 1.0))
        ox = float(rng.uniform(-(1 - fw), 1 - fw)) * w / 2
        oy = float(rng.uniform(-(1 - fd), 1 - fd)) * d / 2
        top = h * (k + 1) / n
        parts.append((ox - fw * w / 2, oy - fd * d / 2, z, ox + fw * w / 2, oy + fd * d / 2, top, k % 3))
        z = top
    # The first book spans the full footprint so the oriented box is tight.
    parts[0] = (-w / 2, -d / 2, 0.0, w / 2, d / 2, parts[0][5], parts[0][6])
    return parts, []


def _shape_cup(w, d, h, rng):
    handle = 0.25 * w
    return [
        (-w / 2, -d / 2, 0.0, w / 2 - handle, d / 2, h, 0),
        (w / 2 - handle, -d * 0.1, 0.3 * h, w / 2, d * 0.1, 0.8 * h, 1),
    ], []


def _shape_lidded(w, d, h, rng):
    return [
        (-w / 2 + 0.01, -d / 2 + 0.01, 0.0, w / 2 - 0.01, d / 2 - 0.01, h - 0.03, 0),
        (-w / 2, -d / 2, h - 0.03, w / 2, d / 2, h, 1),
    ], []


SHAPES: dict[str, Callable] = {
    "box": _shape_box,
    "cabinet": _shape_cabinet,
    "counter": _shape_counter,
    "table": _shape_table,
    "desk": _shape_desk,
    "chair": _shape_chair,
    "office_chair": _shape_office_chair,
    "sofa": _shape_sofa,
    "bed": _shape_bed,
    "shelf": _shape_shelf,
    "lamp": _shape_lamp,
    "plant": _shape_plant,
    "panel": _shape_panel,
    "framed": _shape_framed,
    "fridge": _shape_fridge,
    "stove": _shape_stove,
    "vanity": _shape_vanity,
    "toilet": _shape_toilet,
    "tub": _shape_tub,
    "appliance": _shape_appliance,
    "monitor": _shape_monitor,
    "laptop": _shape_laptop,
    "vase": _shape_vase,
    "bowl": _shape_bowl,
    "books": _shape_books,
    "cup": _shape_cup,
    "lidded": _shape_lidded,
}
"""Shape builders: ``(w, d, h, rng) -> (local parts, local support surfaces)``."""


def _rotate_xy(x: float, y: float, quarter: int) -> tuple[float, float]:
    """Exact rotation of (x, y) by ``quarter`` * 90 degrees counter-clockwise."""
    for _ in range(quarter % 4):
        x, y = -y, x
    return x, y


def _local_box_to_world(
    x0, y0, x1, y1, quarter: int, cx: float, cy: float
) -> tuple[float, float, float, float]:
    a = _rotate_xy(x0, y0, quarter)
    b = _rotate_xy(x1, y1, quarter)
    return (min(a[0], b[0]) + cx, min(a[1], b[1]) + cy, max(a[0], b[0]) + cx, max(a[1], b[1]) + cy)


def build_parts(
    category: Category,
    size: tuple[float, float, float],
    quarter: int,
    base: tuple[float, float, float],
    rng: np.random.Generator,
) -> tuple[list[Part], list[Surface]]:
    """World parts and support surfaces of ``category`` with ``size`` at ``base`` (footprint centre,
    bottom z)."""
    w, d, h = size
    local_parts, local_surfaces = SHAPES[category.shape](w, d, h, rng)
    cx, cy, z0 = base
    parts = []
    for x0, y0, zl0, x1, y1, zl1, slot in local_parts:
        wx0, wy0, wx1, wy1 = _local_box_to_world(x0, y0, x1, y1, quarter, cx, cy)
        parts.append(Part((wx0, wy0, z0 + zl0), (wx1, wy1, z0 + zl1), slot))
    surfaces = []
    for z, x0, y0, x1, y1, clearance in local_surfaces:
        wx0, wy0, wx1, wy1 = _local_box_to_world(x0, y0, x1, y1, quarter, cx, cy)
        surfaces.append(Surface(z0 + z, wx0, wy0, wx1, wy1, clearance))
    return parts, surfaces
