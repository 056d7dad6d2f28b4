"""Stairs seen through a capture (issue 21, item 4): panoramic depth of a box world goes through
``extract_navmap`` (Sobel normals, riser nosings blended into the treads, riser support columns), not
through the exact analytic normals of ``synthetic.two_levels_with_stairs``.

Two storeys joined by a straight flight: risers just below the paper's 0.15 m step height connect the
storeys with the default embodiment, risers just above it do not, and table- and bed-height plateaus
beside the flight never become navigable.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.records import Frame
from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
from image2sim.simulator.navigation.extract import extract_navmap
from image2sim.simulator.navigation.graph import NavGraph, joined_storeys
from image2sim.simulator.navigation.navmap import NavMap
from scipy.spatial import cKDTree

pytest.importorskip("image2sim.dataengine.procedural")
from image2sim.dataengine.procedural.raycast import BoxCaster  # noqa: E402 (optional package)

ROOM = (8.0, 4.0)
"""Room extent in x, y (metres); the flight runs along +x across y in [0, STAIR_WIDTH]."""
STAIR_WIDTH = 1.2
TREAD = 0.28
FURNITURE = {"table": (0.3, 0.75), "bed": (1.6, 0.45)}
"""Solid boxes on the lower storey, before the flight: name -> (x of the near side, top height);
each spans 0.9 m in x and y 2.6 .. 3.6."""

# OpenCV camera looking along +x in the Z-up world: right = -y, down = -z, forward = +x.
_CAM_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _stair_world(riser: float, level: float = 1.2) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Boxes (lo, hi) of a two-storey room joined by a flight of ``riser`` steps, its capture cameras
    and the upper storey's exact height (a whole number of risers)."""
    n = int(round(level / riser))
    level = n * riser
    lx, ly = ROOM
    xs = lx / 2 - n * TREAD / 2  # first riser
    xe = xs + (n - 1) * TREAD  # last riser: the upper storey starts here
    top = level + 3.0
    boxes = [
        ((-0.1, -0.1, -0.1), (lx + 0.1, ly + 0.1, 0.0)),  # lower floor slab
        ((xe, 0.0, 0.0), (lx, ly, level)),  # the upper storey (its top is the floor)
        ((xs, STAIR_WIDTH, 0.0), (xe, ly, level)),  # beside the flight: a vertical face
        ((-0.2, -0.2, 0.0), (0.0, ly + 0.2, top)),  # four walls
        ((lx, -0.2, 0.0), (lx + 0.2, ly + 0.2, top)),
        ((-0.2, -0.2, 0.0), (lx + 0.2, 0.0, top)),
        ((-0.2, ly, 0.0), (lx + 0.2, ly + 0.2, top)),
    ]
    boxes += [((x0, 2.6, 0.0), (x0 + 0.9, 3.6, top_z)) for x0, top_z in FURNITURE.values()]
    for s in range(1, n):
        x0 = xs + (s - 1) * TREAD
        boxes.append(((x0, 0.0, 0.0), (x0 + TREAD, STAIR_WIDTH, s * riser)))
    lo, hi = (np.array(v, dtype=np.float64) for v in zip(*boxes, strict=True))
    # Like a real walk-through: cameras 1.5 m above the floor in both storeys, at the foot, half-way
    # up and at the head of the flight (HM3D's capture has two over its treads).
    mid = 0.5 * STAIR_WIDTH
    feet = [
        (1.0, 1.0, 0.0),
        (2.5, 2.0, 0.0),
        (1.0, 1.8, 0.0),
        (xs - 0.4, mid, 0.0),
        (0.5 * (xs + xe), mid, level / 2),
        (xe + 0.4, mid, level),
        (xe + 1.0, 2.0, level),
        (lx - 0.6, 1.0, level),
    ]
    cams = np.array(feet) + [0.0, 0.0, 1.5]
    return lo, hi, cams, level


def _panoramas(lo: np.ndarray, hi: np.ndarray, cams: np.ndarray, height: int = 256) -> list[Frame]:
    """Exact equirectangular range images of the boxes from each camera (yaw 0, upright)."""
    cam = EquirectCamera(height, 2 * height)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5,
        torch.arange(2 * height, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    dirs = cam.pixel_to_ray(u, v).reshape(-1, 3).numpy() @ _CAM_AXES.T
    caster = BoxCaster(lo, hi)
    frames = []
    for k, c in enumerate(cams):
        t, _, _ = caster.cast(c, dirs, (height, 2 * height))
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = _CAM_AXES, c
        depth = np.nan_to_num(t, nan=0.0).reshape(height, 2 * height).astype(np.float32)
        frames.append(Frame(np.zeros(depth.shape + (3,), np.uint8), depth, cam, pose, frame_id=str(k)))
    return frames


@functools.cache
def _built(riser: float, step: float = Embodiment().max_step_height) -> tuple[NavMap, NavGraph, float]:
    """Map (every pixel, a body climbing ``step``; default: the paper's) and graph of the world with
    ``riser`` steps."""
    lo, hi, cams, level = _stair_world(riser)
    emb = Embodiment(max_step_height=step)
    m = extract_navmap(_panoramas(lo, hi, cams), emb, NavMapConfig(pixel_stride=1))
    return m, NavGraph.build(m), level


def _plateau_cells(m: NavMap, name: str) -> np.ndarray:
    """Navigable cells above the footprint of furniture box ``name`` and off the floor."""
    x0, _ = FURNITURE[name]
    p = m.map_points
    over = (p[:, 0] > x0) & (p[:, 0] < x0 + 0.9) & (p[:, 1] > 2.6) & (p[:, 1] < 3.6)
    return over & (p[:, 2] > 0.1)


def test_steps_just_below_the_step_height_connect_the_storeys_by_default():
    m, g, level = _built(0.14)
    assert Embodiment().max_step_height == 0.15  # the paper's agent
    np.testing.assert_allclose(np.sort(m.level_heights), [0.0, level], atol=0.02)
    assert joined_storeys(g, m.level_heights, m.config.level_tolerance) == [(0, 1)]
    # The flight itself is navigable: every one of its 8 treads holds graph nodes.
    lane = (g.nodes[:, 1] > 0.2) & (g.nodes[:, 1] < STAIR_WIDTH - 0.2) & (g.nodes[:, 2] > 0.07)
    lane &= g.nodes[:, 2] < level - 0.07
    treads = np.unique(np.round(g.nodes[lane, 2] / 0.14).astype(int))
    assert treads.tolist() == list(range(1, 9)), treads


def test_a_step_above_the_step_height_keeps_the_storeys_apart():
    m, g, level = _built(0.17)  # 0.17 m > 0.15 m + the 1 cm height tolerance
    np.testing.assert_allclose(np.sort(m.level_heights), [0.0, level], atol=0.02)
    assert joined_storeys(g, m.level_heights, m.config.level_tolerance) == []
    between = (g.nodes[:, 2] > 0.1) & (g.nodes[:, 2] < level - 0.1)
    assert not between.any()  # no tread is reachable, so none is kept as navigable floor
    # The same capture with a body that climbs 0.2 m: the flight joins them (the world is sound).
    m, g, _ = _built(0.17, step=0.2)
    assert joined_storeys(g, m.level_heights, m.config.level_tolerance) == [(0, 1)]


@pytest.mark.parametrize("riser", [0.14, 0.17])
def test_furniture_plateaus_are_not_navigable(riser):
    m, _, _ = _built(riser)
    for name in FURNITURE:
        assert not _plateau_cells(m, name).any(), name
    # The floor around them is: the test would pass vacuously on an empty map.
    assert m.navigable_area(0) > 5.0


def test_depth_holes_keep_the_floor_with_hole_normals():
    # Stereo and sensors leave holes: 5 % of the panoramas' pixels lose their depth. The Sobel
    # window of every pixel within 3 strided pixels of a hole has no normal (at the default stride 2
    # that is most pixels), so without
    # NavMapConfig.hole_normals that floor is lost; with it the map stays the hole-free one.
    lo, hi, cams, _ = _stair_world(0.14)
    frames = _panoramas(lo, hi, cams)
    rng = np.random.default_rng(0)
    holed = [
        Frame(
            f.rgb,
            np.where(rng.random(f.depth.shape) < 0.05, 0.0, f.depth).astype(np.float32),
            f.camera,
            f.cam_to_world,
            frame_id=f.frame_id,
        )
        for f in frames
    ]

    def cells(m: NavMap) -> set:
        return set(map(tuple, np.floor(m.points[:, :2] / m.voxel_size).astype(int).tolist()))

    full = cells(extract_navmap(frames))
    iou = {}
    for on in (False, True):
        m = extract_navmap(holed, config=NavMapConfig(hole_normals=on))
        iou[on] = len(full & cells(m)) / len(full | cells(m))
        assert not any(_plateau_cells(m, name).any() for name in FURNITURE)
    assert iou[True] >= 0.85 and iou[True] > iou[False] + 0.5, iou  # measured: 0.89 vs 0.20


def test_floating_wrong_depth_is_carved_and_the_floor_comes_back():
    # Wrong depth (a mismatched stereo patch) puts a blob of points 0.6 m above the floor in one
    # panorama; the other views see the floor through it. Without carving the blob is an obstacle
    # whose buffer cuts the floor around it; with it (the default) the map is the clean one.
    lo, hi, cams, _ = _stair_world(0.14)
    frames = _panoramas(lo, hi, cams)
    f = frames[1]
    pose = f.cam_to_world
    pts = f.camera.unproject(torch.from_numpy(f.depth)).numpy() @ pose[:3, :3].T + pose[:3, 3]
    blob = (np.abs(pts[..., 0] - 1.5) < 0.4) & (np.abs(pts[..., 1] - 2.0) < 0.4)
    blob &= np.abs(pts[..., 2]) < 0.01
    assert blob.sum() > 200
    shrink = np.where(blob, 0.6, 1.0).astype(np.float32)  # 0.6 of the range: 0.6 m above the floor
    frames[1] = Frame(f.rgb, f.depth * shrink, f.camera, pose, frame_id=f.frame_id)
    floater = pose[:3, 3] + 0.6 * (pts[blob] - pose[:3, 3])

    def cells(m: NavMap) -> set:
        return set(map(tuple, np.floor(m.points[:, :2] / m.voxel_size).astype(int).tolist()))

    clean = cells(extract_navmap(_panoramas(lo, hi, cams)))
    near, _ = cKDTree(floater[:, :2]).query((np.array(sorted(clean)) + 0.5) * 0.05)
    under = {c for c, d in zip(sorted(clean), near, strict=True) if d < 0.1}
    assert len(under) > 50
    off = extract_navmap(frames, config=NavMapConfig(carve_min_views=0))
    on = extract_navmap(frames)
    assert len(under & cells(off)) < 0.5 * len(under)  # the floater blocks the floor under it
    assert len(under & cells(on)) >= 0.95 * len(under)
    assert len(clean ^ cells(on)) <= 0.02 * len(clean)
    assert any("visibility carving" in n for n in on.notes)
    assert not any(_plateau_cells(on, name).any() for name in FURNITURE)


def test_carving_leaves_exact_depth_alone():
    lo, hi, cams, _ = _stair_world(0.14)
    frames = _panoramas(lo, hi, cams)
    on, off = extract_navmap(frames), extract_navmap(frames, config=NavMapConfig(carve_min_views=0))
    np.testing.assert_array_equal(np.sort(on.points, axis=0), np.sort(off.points, axis=0))
