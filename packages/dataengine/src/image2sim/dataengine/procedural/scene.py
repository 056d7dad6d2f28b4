"""``generate_scene(config, seed) -> ProceduralScene``: plan, furniture, materials, lights and GT grid.

Randomness comes from one :class:`numpy.random.SeedSequence` per scene, split into independent
streams (layout, objects, materials, capture), so e.g. changing the number of views never changes
the house. Placement rejects any object whose parts would interpenetrate another object's parts,
that leaves its room, blocks a door, or splits the navigable floor into several components.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from image2sim.dataengine.procedural.config import SynthConfig
from image2sim.dataengine.procedural.gt import (
    FREE,
    OBSTACLE,
    NavGrid,
    floor_mask,
    grid_frame,
    label_components,
    navigable_from_free,
    rasterise_box,
)
from image2sim.dataengine.procedural.layout import Layout, generate_layout
from image2sim.dataengine.procedural.objects import (
    CATEGORY_BY_NAME,
    COMPANIONS,
    ROOM_PROGRAMS,
    SMALL_BY_ROOM,
    STRUCTURE_CATEGORIES,
    Category,
    SceneObject,
    Surface,
    build_parts,
)
from image2sim.dataengine.procedural.textures import MaterialTable, category_hue

__all__ = ["ProceduralScene", "generate_scene", "SceneGenerationError", "seed_streams"]

WALL_MATERIAL = -1
"""``box_material`` marker: the paint of the room the face looks into (resolved at render time)."""

_SECONDARY = {
    "fabric": "wood",
    "wood": "wood",
    "metal": "metal",
    "ceramic": "ceramic",
    "plastic": "metal",
    "plant": "ceramic",
    "screen": "plastic",
    "art": "wood",
    "glass": "wood",
    "paper": "paper",
    "carpet": "carpet",
}
_FLOOR_FAMILY = {"kitchen": "floor_tile", "bathroom": "floor_tile"}
_KIND_CODE = {"floor": 1, "ceiling": 2, "wall": 3, "lintel": 3}


class SceneGenerationError(RuntimeError):
    """The generated scene violates an invariant (should not happen; the message says which)."""


def seed_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators for the parts of a scene, derived from ``seed`` only."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    names = ("layout", "objects", "materials", "capture", "noise")
    children = np.random.SeedSequence(int(seed)).spawn(len(names))
    return {n: np.random.Generator(np.random.PCG64(c)) for n, c in zip(names, children, strict=False)}


@dataclass
class ProceduralScene:
    """A generated indoor scene: exact geometry, semantics, appearance and navigable floor.

    Geometry is a list of axis-aligned boxes (``box_lo``/``box_hi``) with per-box category,
    instance (0 for structure) and material ids; :attr:`mesh` is its triangulation.
    """

    config: SynthConfig
    seed: int
    layout: Layout
    objects: list[SceneObject]
    materials: MaterialTable
    room_wall_material: np.ndarray
    room_floor_material: np.ndarray
    room_ceiling_material: np.ndarray
    light_position: np.ndarray
    """(R, 3) one point light per room, under the ceiling centre."""
    light_color: np.ndarray
    """(R, 3) light colour/intensity per room."""
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_category: np.ndarray
    box_instance: np.ndarray
    box_material: np.ndarray
    box_kind: np.ndarray
    """(N,) 1 floor, 2 ceiling, 3 wall/lintel, 4 object part."""
    grid: NavGrid
    _casters: dict = field(default_factory=dict, repr=False)

    @property
    def scene_id(self) -> str:
        return f"synth-{self.seed:010d}"

    @property
    def mesh(self):
        """The scene as a ``trimesh.Trimesh`` (12 triangles per box) with ``face_attributes``
        ``category`` and ``instance``."""
        import trimesh
        from image2sim.dataengine.procedural.gt import mesh_arrays

        verts, tris = mesh_arrays(self.box_lo, self.box_hi)
        box = np.arange(len(tris)) // 12
        return trimesh.Trimesh(
            vertices=verts,
            faces=tris,
            process=False,
            face_attributes={"category": self.box_category[box], "instance": self.box_instance[box]},
        )

    def caster(self, kind: str | None = None):
        """The (cached) ray caster of ``kind`` (default: the config's ``caster``)."""
        from image2sim.dataengine.procedural.raycast import make_caster

        kind = kind or self.config.caster
        if kind not in self._casters:
            self._casters[kind] = make_caster(kind, self.box_lo, self.box_hi)
        return self._casters[kind]

    def object_by_id(self, instance_id: int) -> SceneObject:
        for obj in self.objects:
            if obj.instance_id == instance_id:
                return obj
        raise KeyError(f"no object with instance id {instance_id}")


# --- placement ---------------------------------------------------------------------------------------


def _overlaps(lo: np.ndarray, hi: np.ndarray, los: np.ndarray, his: np.ndarray, tol: float = 1e-9) -> bool:
    """True if box [lo, hi] overlaps any of the boxes (K, 3) with positive volume."""
    if los.shape[0] == 0:
        return False
    return bool(np.any(np.all((np.minimum(hi, his) - np.maximum(lo, los)) > tol, axis=1)))


class _Placer:
    """Stateful furniture placement for one scene."""

    def __init__(
        self,
        cfg: SynthConfig,
        layout: Layout,
        rng: np.random.Generator,
        mat_rng: np.random.Generator,
        materials: MaterialTable,
    ):
        self.cfg = cfg
        self.layout = layout
        self.rng = rng
        self.mat_rng = mat_rng
        self.materials = materials
        self.res = cfg.capture.grid_resolution
        self.radius = cfg.capture.agent_radius
        self.origin, self.shape = grid_frame(layout, self.res)
        self.floor = floor_mask(layout, self.origin, self.shape, self.res)
        self.obstacle = np.zeros(self.shape, dtype=bool)
        self.objects: list[SceneObject] = []
        self.part_lo = [np.zeros((0, 3)) for _ in layout.rooms]
        self.part_hi = [np.zeros((0, 3)) for _ in layout.rooms]
        self.keepout = [self._keepouts(k) for k in range(len(layout.rooms))]

    def _keepouts(self, room: int) -> tuple[np.ndarray, np.ndarray]:
        """Full-height boxes in front of this room's doors (both sides) that furniture must leave free."""
        t = self.layout.wall_thickness
        c = self.cfg.objects.door_clearance
        los, his = [], []
        for d in self.layout.doors:
            if room not in (d.a, d.b):
                continue
            x0, y0, x1, y1 = d.passage(t)
            if d.axis == 0:
                y0, y1 = y0 - c, y1 + c
                x0, x1 = x0 - 0.05, x1 + 0.05
            else:
                x0, x1 = x0 - c, x1 + c
                y0, y1 = y0 - 0.05, y1 + 0.05
            los.append((x0, y0, 0.0))
            his.append((x1, y1, self.layout.ceiling_height))
        return np.asarray(los, dtype=np.float64).reshape(-1, 3), np.asarray(his, dtype=np.float64).reshape(
            -1, 3
        )

    def navigable(self, obstacle: np.ndarray | None = None) -> np.ndarray:
        free = self.floor & ~(self.obstacle if obstacle is None else obstacle)
        return navigable_from_free(free, self.radius, self.res)

    def _sample_size(self, cat: Category) -> tuple[float, float, float]:
        return tuple(float(self.rng.uniform(a, b)) for a, b in zip(cat.size_min, cat.size_max, strict=False))  # type: ignore[return-value]

    def _materials_for(self, cat: Category) -> tuple[int, int, int]:
        hue = category_hue(cat.id) if self.cfg.objects.category_colours else None
        m0 = self.materials.add(cat.material, self.mat_rng, hue=hue)
        m1 = self.materials.add(_SECONDARY.get(cat.material, cat.material), self.mat_rng)
        m2 = self.materials.add("metal", self.mat_rng)
        return (m0, m1, m2)

    def _wall_pose(self, room: int, fw: float, fd: float, side: int) -> tuple[float, float]:
        """Footprint centre of an object backed against ``side`` (0 bottom, 1 right, 2 top, 3 left)."""
        x0, y0, x1, y1 = self.layout.rooms[room].interior(self.layout.wall_thickness)
        gap = self.cfg.objects.wall_gap
        if side in (0, 2):
            x = float(self.rng.uniform(x0 + fw / 2, max(x0 + fw / 2, x1 - fw / 2)))
            y = y0 + gap + fd / 2 if side == 0 else y1 - gap - fd / 2
        else:
            y = float(self.rng.uniform(y0 + fd / 2, max(y0 + fd / 2, y1 - fd / 2)))
            x = x1 - gap - fw / 2 if side == 1 else x0 + gap + fw / 2
        return x, y

    def _candidate(self, cat: Category, room: int, parent: SceneObject | None, slot: int):
        """One random (size, quarter, base) for ``cat`` following its placement rule."""
        size = self._sample_size(cat)
        w, d, h = size
        x0, y0, x1, y1 = self.layout.rooms[room].interior(self.layout.wall_thickness)
        rule = cat.placement
        if rule in ("wall", "mounted"):
            side = int(self.rng.integers(0, 4))
            quarter = (2, 3, 0, 1)[side]
            fw, fd = (w, d) if quarter % 2 == 0 else (d, w)
            x, y = self._wall_pose(room, fw, fd, side)
            z = 0.0 if rule == "wall" else float(self.rng.uniform(*cat.mount_z)) - h / 2
            return size, quarter, (x, y, z)
        if rule == "companion" and parent is not None:
            plo, phi = parent.aabb
            pc = 0.5 * (plo + phi)
            _, where = COMPANIONS[parent.category.name][2:]
            if where == "front":
                front = np.round(np.array([math.sin(parent.yaw), -math.cos(parent.yaw)]))
                normal = front
            else:
                normal = np.array([(0, -1), (1, 0), (0, 1), (-1, 0)][slot % 4], dtype=np.float64)
            # Chairs face their table: local front (-y) must point along -normal.
            quarter = {(0, -1): 2, (0, 1): 0, (1, 0): 3, (-1, 0): 1}[(int(normal[0]), int(normal[1]))]
            fw, fd = (w, d) if quarter % 2 == 0 else (d, w)
            half = 0.5 * (phi[:2] - plo[:2])
            # Slide partly under the top (chairs tuck in) but never into the parent's parts.
            tuck = float(self.rng.uniform(0.0, 0.5)) * (fd if normal[0] == 0 else fw)
            off = (half[1] + fd / 2 if normal[0] == 0 else half[0] + fw / 2) + 0.02 - tuck
            along = float(self.rng.uniform(-0.25, 0.25)) * (half[0] if normal[0] == 0 else half[1])
            x = pc[0] + normal[0] * off + (along if normal[0] == 0 else 0.0)
            y = pc[1] + normal[1] * off + (along if normal[1] == 0 else 0.0)
            return size, quarter, (float(x), float(y), 0.0)
        quarter = int(self.rng.integers(0, 4))
        fw, fd = (w, d) if quarter % 2 == 0 else (d, w)
        if rule == "center":
            cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
            x = cx + float(self.rng.uniform(-0.25, 0.25)) * (x1 - x0)
            y = cy + float(self.rng.uniform(-0.25, 0.25)) * (y1 - y0)
        else:
            x = float(self.rng.uniform(x0 + fw / 2, max(x0 + fw / 2, x1 - fw / 2)))
            y = float(self.rng.uniform(y0 + fd / 2, max(y0 + fd / 2, y1 - fd / 2)))
        return size, quarter, (x, y, 0.0)

    def _fits(self, room: int, parts_lo: np.ndarray, parts_hi: np.ndarray) -> bool:
        x0, y0, x1, y1 = self.layout.rooms[room].interior(self.layout.wall_thickness)
        lo, hi = parts_lo.min(axis=0), parts_hi.max(axis=0)
        eps = 1e-9
        if lo[0] < x0 - eps or lo[1] < y0 - eps or hi[0] > x1 + eps or hi[1] > y1 + eps:
            return False
        if lo[2] < -eps or hi[2] > self.layout.ceiling_height - 0.05:
            return False
        klo, khi = self.keepout[room]
        if _overlaps(lo, hi, klo, khi):
            return False
        return not any(
            _overlaps(pl, ph, self.part_lo[room], self.part_hi[room])
            for pl, ph in zip(parts_lo, parts_hi, strict=False)
        )

    def _accept(self, cat, room, size, quarter, base, parts, surfaces, support=0) -> SceneObject:
        w, d, h = size
        center = np.array([base[0], base[1], base[2] + h / 2], dtype=np.float64)
        obj = SceneObject(
            instance_id=len(self.objects) + 1,
            category=cat,
            room=room,
            center=center,
            size=size,
            yaw=quarter * math.pi / 2,
            parts=parts,
            surfaces=surfaces,
            materials=self._materials_for(cat),
            support=support,
        )
        self.objects.append(obj)
        plo = np.array([p.lo for p in parts])
        phi = np.array([p.hi for p in parts])
        self.part_lo[room] = np.vstack([self.part_lo[room], plo])
        self.part_hi[room] = np.vstack([self.part_hi[room], phi])
        return obj

    def place(
        self, cat: Category, room: int, parent: SceneObject | None = None, slot: int = 0
    ) -> SceneObject | None:
        """Try to place one object of ``cat`` in ``room``; None after ``placement_attempts`` failures."""
        for _ in range(self.cfg.objects.placement_attempts):
            size, quarter, base = self._candidate(cat, room, parent, slot)
            parts, surfaces = build_parts(cat, size, quarter, base, self.rng)
            plo = np.array([p.lo for p in parts])
            phi = np.array([p.hi for p in parts])
            if not self._fits(room, plo, phi):
                continue
            if not cat.walkable:
                rows, cols = rasterise_box(self.shape, self.origin, self.res, plo.min(0), phi.max(0))
                trial = self.obstacle.copy()
                trial[rows, cols] = True
                _, n = label_components(self.navigable(trial))
                if n != 1:
                    continue
                self.obstacle = trial
            return self._accept(cat, room, size, quarter, base, parts, surfaces)
        return None

    def place_small(
        self, cat: Category, room: int, surface: Surface, support: SceneObject
    ) -> SceneObject | None:
        """Put a small object on ``surface`` (inside its rectangle, under its clearance)."""
        margin = 0.01
        for _ in range(self.cfg.objects.placement_attempts):
            size = self._sample_size(cat)
            w, d, h = size
            if h > surface.clearance - 0.01:
                continue
            quarter = int(self.rng.integers(0, 4))
            fw, fd = (w, d) if quarter % 2 == 0 else (d, w)
            if fw + 2 * margin > surface.x1 - surface.x0 or fd + 2 * margin > surface.y1 - surface.y0:
                continue
            x = float(self.rng.uniform(surface.x0 + margin + fw / 2, surface.x1 - margin - fw / 2))
            y = float(self.rng.uniform(surface.y0 + margin + fd / 2, surface.y1 - margin - fd / 2))
            parts, _ = build_parts(cat, size, quarter, (x, y, surface.z), self.rng)
            plo = np.array([p.lo for p in parts])
            phi = np.array([p.hi for p in parts])
            if not self._fits(room, plo, phi):
                continue
            return self._accept(
                cat, room, size, quarter, (x, y, surface.z), parts, [], support=support.instance_id
            )
        return None

    def furnish(self) -> None:
        ocfg = self.cfg.objects
        for room in self.layout.rooms:
            for name, lo, hi in ROOM_PROGRAMS[room.room_type]:
                n = int(math.floor(self.rng.integers(lo, hi + 1) * ocfg.furniture_scale + self.rng.uniform()))
                if ocfg.furniture_scale > 0 and lo > 0:
                    n = max(n, 1)
                for _ in range(n):
                    obj = self.place(CATEGORY_BY_NAME[name], room.index)
                    if obj is None or name not in COMPANIONS:
                        continue
                    comp, cmin, cmax, _ = COMPANIONS[name]
                    for slot in range(int(self.rng.integers(cmin, cmax + 1))):
                        self.place(CATEGORY_BY_NAME[comp], room.index, parent=obj, slot=slot)
        if ocfg.small_per_surface_max == 0:
            return
        for support in list(self.objects):
            if support.category.walkable:
                continue  # nothing stands on rugs: their footprint stays navigable
            small = SMALL_BY_ROOM[self.layout.rooms[support.room].room_type]
            for surface in support.surfaces:
                if self.rng.uniform() >= ocfg.small_probability:
                    continue
                for _ in range(int(self.rng.integers(1, ocfg.small_per_surface_max + 1))):
                    if support.category.name == "desk" and "monitor" in small and self.rng.uniform() < 0.6:
                        name = ("monitor", "laptop")[int(self.rng.integers(0, 2))]
                    else:
                        name = small[int(self.rng.integers(0, len(small)))]
                    cat = CATEGORY_BY_NAME[name]
                    if cat.placement != "surface":
                        continue
                    self.place_small(cat, support.room, surface, support)


def generate_scene(config: SynthConfig, seed: int) -> ProceduralScene:
    """Generate one scene deterministically from ``config`` and ``seed``."""
    config.validate()
    streams = seed_streams(seed)
    layout = generate_layout(config.layout, streams["layout"])
    materials = MaterialTable()
    mat_rng = streams["materials"]
    n_rooms = len(layout.rooms)
    wall_m = np.array([materials.add("wall_paint", mat_rng) for _ in range(n_rooms)], dtype=np.int64)
    floor_m = np.array(
        [materials.add(_FLOOR_FAMILY.get(r.room_type, "floor_wood"), mat_rng) for r in layout.rooms],
        dtype=np.int64,
    )
    ceil_m = np.array([materials.add("ceiling", mat_rng) for _ in range(n_rooms)], dtype=np.int64)
    light_pos = np.array(
        [[0.5 * (r.x0 + r.x1), 0.5 * (r.y0 + r.y1), layout.ceiling_height - 0.5] for r in layout.rooms]
    )
    warmth = mat_rng.uniform(0.0, 0.15, size=n_rooms)
    intensity = mat_rng.uniform(0.8, 1.1, size=n_rooms)
    light_col = intensity[:, None] * np.stack([np.ones(n_rooms), 1 - 0.4 * warmth, 1 - warmth], axis=1)

    placer = _Placer(config, layout, streams["objects"], mat_rng, materials)
    placer.furnish()

    lo, hi, cat, inst, mat, kind = [], [], [], [], [], []
    for b in layout.boxes:
        lo.append(b.lo)
        hi.append(b.hi)
        key = "wall" if b.kind == "lintel" else b.kind
        cat.append(STRUCTURE_CATEGORIES[key])
        inst.append(0)
        kind.append(_KIND_CODE[b.kind])
        mat.append(
            floor_m[b.room] if b.kind == "floor" else ceil_m[b.room] if b.kind == "ceiling" else WALL_MATERIAL
        )
    for obj in placer.objects:
        for p in obj.parts:
            lo.append(p.lo)
            hi.append(p.hi)
            cat.append(obj.category.id)
            inst.append(obj.instance_id)
            mat.append(obj.materials[p.slot])
            kind.append(4)

    occupancy = np.where(placer.floor, FREE, 0).astype(np.uint8)
    occupancy[placer.floor & placer.obstacle] = OBSTACLE
    navigable = placer.navigable()
    components, n_comp = label_components(navigable)
    if n_comp != 1:
        raise SceneGenerationError(f"scene seed {seed}: navigable floor has {n_comp} components, expected 1")
    grid = NavGrid(
        occupancy,
        navigable,
        components,
        placer.origin,
        config.capture.grid_resolution,
        config.capture.agent_radius,
    )
    return ProceduralScene(
        config=config,
        seed=int(seed),
        layout=layout,
        objects=placer.objects,
        materials=materials,
        room_wall_material=wall_m,
        room_floor_material=floor_m,
        room_ceiling_material=ceil_m,
        light_position=light_pos,
        light_color=light_col,
        box_lo=np.asarray(lo, dtype=np.float64),
        box_hi=np.asarray(hi, dtype=np.float64),
        box_category=np.asarray(cat, dtype=np.int32),
        box_instance=np.asarray(inst, dtype=np.int32),
        box_material=np.asarray(mat, dtype=np.int64),
        box_kind=np.asarray(kind, dtype=np.int8),
        grid=grid,
    )
