"""Procedural scenes: config validation, layouts, object placement and ground-truth consistency."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.dataengine.procedural.config import (
    CaptureConfig,
    ConfigError,
    LayoutConfig,
    ObjectConfig,
    SynthConfig,
    preset,
    synth_config_from_dict,
)
from image2sim.dataengine.procedural.gt import OBSTACLE, rasterise_box
from image2sim.dataengine.procedural.layout import ROOM_TYPES
from image2sim.dataengine.procedural.objects import CATEGORIES, CATEGORY_BY_NAME, ROOM_PROGRAMS, SMALL_BY_ROOM
from image2sim.dataengine.procedural.scene import generate_scene

# Medium scenes: several rooms (corridor or BSP) but small enough to generate quickly.
MEDIUM = dataclasses.replace(
    preset("default"),
    layout=LayoutConfig(rooms_min=3, rooms_max=5, room_size_min=2.6, room_size_max=4.5),
    capture=CaptureConfig(views=4, height=32, width=64),
)


@pytest.fixture(scope="module")
def medium_scenes():
    return [generate_scene(MEDIUM, seed) for seed in (1, 2, 3)]


# --- config --------------------------------------------------------------------------------------


def test_presets_validate_and_round_trip():
    for name in ("default", "tiny"):
        cfg = preset(name)
        assert synth_config_from_dict(cfg.to_dict(), base=cfg) == cfg


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ({"layout": {"rooms_min": 0}}, "rooms_min"),
        ({"layout": {"rooms_max": 9}}, "rooms_max"),
        ({"layout": {"room_size_min": -1.0}}, "room_size_min"),
        ({"layout": {"wall_thickness": -0.1}}, "wall_thickness"),
        ({"layout": {"ceiling_height_min": float("nan")}}, "finite"),
        ({"capture": {"eye_height_max": 3.0}}, "eye_height_max"),
        ({"capture": {"eye_height_min": -1.0}}, "eye height"),
        ({"capture": {"views": 0}}, "views"),
        ({"capture": {"camera": "fisheye"}}, "camera"),
        ({"noise": "extreme"}, "noise tier"),
        ({"caster": "optix"}, "caster"),
        ({"layout": {"rooms": 3}}, "unknown key"),
        ({"colour": 1}, "unknown key"),
        ({"layout": {"rooms_min": "three"}}, "integer"),
        ({"layout": {"door_width_min": 0.2}}, "agent diameter"),
        ({"layout": {"door_height": 2.8}}, "door_height"),
    ],
)
def test_invalid_configs_are_rejected_with_the_field_named(override, fragment):
    with pytest.raises(ConfigError, match=fragment):
        synth_config_from_dict(override)


def test_unknown_preset_is_rejected():
    with pytest.raises(ConfigError, match="preset"):
        preset("huge")


# --- categories ----------------------------------------------------------------------------------


def test_category_table():
    ids = [c.id for c in CATEGORIES]
    assert len(set(ids)) == len(ids)
    objects = [c for c in CATEGORIES if c.placement != "structure"]
    assert len(objects) >= 30
    assert {c.name for c in CATEGORIES if c.placement == "structure"} == {"floor", "wall", "ceiling"}
    for name in (
        "sofa",
        "bed",
        "table_lamp",
        "chair",
        "cabinet",
        "bookshelf",
        "tv",
        "plant",
        "floor_lamp",
        "fridge",
        "sink",
        "toilet",
        "bathtub",
        "desk",
        "washing_machine",
        "mirror",
        "painting",
        "rug",
        "vase",
        "laptop",
        "clock",
        "bowl",
        "book_stack",
    ):
        assert name in CATEGORY_BY_NAME, name
    for c in objects:
        assert all(0 < a <= b for a, b in zip(c.size_min, c.size_max, strict=False)), c.name
    assert sum(c.small for c in objects) >= 8
    for program in ROOM_PROGRAMS.values():
        assert all(name in CATEGORY_BY_NAME for name, _, _ in program)
    for names in SMALL_BY_ROOM.values():
        assert all(name in CATEGORY_BY_NAME for name in names)


# --- layouts -------------------------------------------------------------------------------------


def test_same_seed_same_scene_different_seed_different_layout():
    a = generate_scene(MEDIUM, 7)
    b = generate_scene(MEDIUM, 7)
    c = generate_scene(MEDIUM, 8)
    for name in ("box_lo", "box_hi", "box_category", "box_instance", "box_material"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.grid.navigable, b.grid.navigable)
    assert a.layout.rooms == b.layout.rooms
    assert a.layout.rooms != c.layout.rooms


def test_layout_rooms_doors_and_types(medium_scenes):
    for scene in medium_scenes:
        lay = scene.layout
        assert MEDIUM.layout.rooms_min <= len(lay.rooms) <= MEDIUM.layout.rooms_max
        assert all(r.room_type in ROOM_TYPES for r in lay.rooms)
        # Rooms do not overlap (positive area) and lie on the 5 cm plan grid.
        for r, s in itertools.combinations(lay.rooms, 2):
            assert min(r.x1, s.x1) - max(r.x0, s.x0) <= 1e-9 or min(r.y1, s.y1) - max(r.y0, s.y0) <= 1e-9
        # Door openings: within the shared wall of their two rooms, wide enough for the agent.
        for d in lay.doors:
            a, b = lay.rooms[d.a], lay.rooms[d.b]
            assert d.width >= MEDIUM.layout.door_width_min - 0.025 - 1e-9
            if d.axis == 0:
                assert {round(a.y0, 6), round(a.y1, 6)} & {round(b.y0, 6), round(b.y1, 6)} == {
                    round(d.line, 6)
                }
                assert max(a.x0, b.x0) < d.lo < d.hi < min(a.x1, b.x1)
            else:
                assert {round(a.x0, 6), round(a.x1, 6)} & {round(b.x0, 6), round(b.x1, 6)} == {
                    round(d.line, 6)
                }
                assert max(a.y0, b.y0) < d.lo < d.hi < min(a.y1, b.y1)
        assert len(lay.doors) >= len(lay.rooms) - 1


def test_corridor_plans_have_a_hallway():
    cfg = dataclasses.replace(
        MEDIUM, layout=dataclasses.replace(MEDIUM.layout, corridor_probability=1.0, rooms_min=4)
    )
    scene = generate_scene(cfg, 0)
    assert scene.layout.rooms[0].room_type == "hallway"
    assert sum(r.room_type == "hallway" for r in scene.layout.rooms) == 1


# --- ground truth ------------------------------------------------------------------------------


def test_objects_lie_inside_their_room_and_do_not_interpenetrate(medium_scenes):
    for scene in medium_scenes:
        lay = scene.layout
        assert len(scene.objects) > 5
        for obj in scene.objects:
            x0, y0, x1, y1 = lay.rooms[obj.room].interior(lay.wall_thickness)
            corners = obj.corners()
            assert np.all(corners[:, 0] >= x0 - 1e-9) and np.all(corners[:, 0] <= x1 + 1e-9), (
                obj.category.name
            )
            assert np.all(corners[:, 1] >= y0 - 1e-9) and np.all(corners[:, 1] <= y1 + 1e-9), (
                obj.category.name
            )
            assert np.all(corners[:, 2] >= -1e-9) and np.all(corners[:, 2] <= lay.ceiling_height + 1e-9)
            # Every part lies inside the object's oriented box (= its AABB for quarter-turn yaws).
            lo, hi = corners.min(0), corners.max(0)
            for p in obj.parts:
                assert np.all(np.asarray(p.lo) >= lo - 1e-9) and np.all(np.asarray(p.hi) <= hi + 1e-9), (
                    obj.category.name
                )
        for a, b in itertools.combinations(scene.objects, 2):
            for p, q in itertools.product(a.parts, b.parts):
                overlap = np.minimum(p.hi, q.hi) - np.maximum(p.lo, q.lo)
                assert not np.all(overlap > 1e-9), (
                    f"{a.category.name} {a.instance_id} intersects {b.category.name}"
                )


def test_small_objects_rest_on_a_surface_of_their_support(medium_scenes):
    seen = 0
    for scene in medium_scenes:
        for obj in scene.objects:
            if obj.support == 0:
                continue
            seen += 1
            support = scene.object_by_id(obj.support)
            assert obj.category.small
            assert support.room == obj.room
            bottom = obj.aabb[0][2]
            assert any(abs(bottom - s.z) < 1e-9 for s in support.surfaces)
    assert seen > 0


def test_navigable_cells_avoid_objects_and_walls(medium_scenes):
    for scene in medium_scenes:
        g = scene.grid
        lay = scene.layout
        for obj in scene.objects:
            if obj.category.walkable:
                continue
            lo, hi = obj.aabb
            rows, cols = rasterise_box(g.navigable.shape, g.origin, g.resolution, lo, hi)
            assert not g.navigable[rows, cols].any(), obj.category.name
            assert np.all(g.occupancy[rows, cols] != 1), obj.category.name
        # Every navigable cell centre is on floor: in a room interior or a door passage.
        iy, ix = np.nonzero(g.navigable)
        xy = g.cell_centers(iy, ix)
        rects = [r.interior(lay.wall_thickness) for r in lay.rooms] + [
            d.passage(lay.wall_thickness) for d in lay.doors
        ]
        inside = np.zeros(len(xy), dtype=bool)
        for x0, y0, x1, y1 in rects:
            inside |= (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        assert inside.all()
        assert (g.occupancy[g.navigable] == 1).all()


def test_one_navigable_component_and_doors_connect_rooms(medium_scenes):
    for scene in medium_scenes:
        g = scene.grid
        lay = scene.layout
        assert g.num_components == 1
        for room in lay.rooms:
            x0, y0, x1, y1 = room.interior(lay.wall_thickness)
            r0, c0 = g.world_to_cell(np.array([x0, y0]))
            r1, c1 = g.world_to_cell(np.array([x1, y1]))
            assert g.navigable[r0 : r1 + 1, c0 : c1 + 1].any(), f"room {room.index} has no navigable floor"
        for d in lay.doors:
            x0, y0, x1, y1 = d.passage(lay.wall_thickness)
            iy, ix = g.world_to_cell(np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)]))
            assert g.components[iy, ix] == 1, f"door between rooms {d.a} and {d.b} is blocked"


def test_obstacles_are_rasterised_conservatively():
    scene = generate_scene(preset("tiny"), 3)
    g = scene.grid
    blocked = [o for o in scene.objects if not o.category.walkable and o.support == 0]
    assert blocked
    for obj in blocked:
        lo, hi = obj.aabb
        rows, cols = rasterise_box(g.occupancy.shape, g.origin, g.resolution, lo, hi)
        cells = g.occupancy[rows, cols]
        assert cells.size > 0 and np.all(cells != 1)
        assert np.any(cells == OBSTACLE)


def test_empty_rooms_when_furniture_scale_is_zero():
    cfg = dataclasses.replace(preset("tiny"), objects=ObjectConfig(furniture_scale=0.0))
    scene = generate_scene(cfg, 0)
    assert scene.objects == []
    assert (scene.box_instance == 0).all()


def test_seed_must_be_a_non_negative_integer():
    with pytest.raises(ValueError, match="seed"):
        generate_scene(preset("tiny"), -1)
    assert isinstance(SynthConfig().validate(), SynthConfig)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1), rooms=st.integers(min_value=1, max_value=8))
def test_invariants_hold_for_any_seed_and_room_count(seed, rooms):
    cfg = dataclasses.replace(
        preset("default"),
        layout=dataclasses.replace(preset("default").layout, rooms_min=rooms, rooms_max=rooms),
        objects=ObjectConfig(furniture_scale=0.5, small_per_surface_max=1),
    )
    scene = generate_scene(cfg, seed)
    lay = scene.layout
    assert len(lay.rooms) == rooms
    assert scene.grid.num_components == 1
    assert len(lay.doors) >= rooms - 1
    for obj in scene.objects:
        x0, y0, x1, y1 = lay.rooms[obj.room].interior(lay.wall_thickness)
        lo, hi = obj.aabb
        assert x0 - 1e-9 <= lo[0] and hi[0] <= x1 + 1e-9 and y0 - 1e-9 <= lo[1] and hi[1] <= y1 + 1e-9
        if not obj.category.walkable:
            rows, cols = rasterise_box(
                scene.grid.navigable.shape, scene.grid.origin, scene.grid.resolution, lo, hi
            )
            assert not scene.grid.navigable[rows, cols].any()
