"""Navigable-map extraction against analytic worlds, procedural ground truth and the real HM3D sample."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.embodiment import ConfigError, Embodiment, NavMapConfig
from image2sim.simulator.navigation.extract import extract_navmap_from_points
from image2sim.simulator.navigation.floors import typical_camera_height
from image2sim.simulator.navigation.navmap import NavMap, NavMapError
from image2sim.simulator.navigation.pointcloud import fit_plane_ransac, rotation_aligning
from image2sim.simulator.navigation.topdown import render_topdown

RADIUS = Embodiment().radius
SPACING = 0.04  # surface sampling: finer than the 0.05 m voxels, coarse enough to be fast


@functools.cache
def world(name: str) -> syn.SyntheticWorld:
    return {
        "box": lambda: syn.box_room(spacing=SPACING),
        "gap": lambda: syn.wall_with_gap(spacing=SPACING),
        "narrow": lambda: syn.wall_with_gap(gap_width=0.25, spacing=SPACING),
        "L": lambda: syn.l_room(spacing=SPACING),
        "stairs": lambda: syn.two_levels_with_stairs(spacing=SPACING),
        "table": lambda: syn.box_room(boxes=[((2.0, 1.5, 0.0), (3.2, 2.3, 0.75))], spacing=SPACING),
    }[name]()


@functools.cache
def navmap(name: str) -> NavMap:
    w = world(name)
    return extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)


def analytic_navigable(w: syn.SyntheticWorld, xy: np.ndarray) -> np.ndarray:
    """Ground truth: floor at the cell centre and the exact obstacle distance >= radius."""
    return np.isfinite(w.floor_height(xy)) & (w.obstacle_distance(xy) >= RADIUS - 1e-9)


def over_box(points: np.ndarray, lo, hi) -> np.ndarray:
    """Which points lie over the box's footprint (x and y strictly inside)."""
    return (
        (points[:, 0] > lo[0]) & (points[:, 0] < hi[0]) & (points[:, 1] > lo[1]) & (points[:, 1] < hi[1])
    )


def iou_against_analytic(name: str) -> float:
    return iou_against_analytic_world(world(name), navmap(name))


def iou_against_analytic_world(w: syn.SyntheticWorld, m: NavMap) -> float:
    lo, hi = w.bounds
    xs = np.arange(lo[0] + 0.025, hi[0], 0.05)
    ys = np.arange(lo[1] + 0.025, hi[1], 0.05)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.column_stack((gx.ravel(), gy.ravel()))
    gt = analytic_navigable(w, xy)
    pred = np.zeros(len(xy), dtype=bool)
    ij = np.floor((m.points[:, :2] - lo + 1e-9) / 0.05).astype(int)
    pred[ij[:, 0] * len(ys) + ij[:, 1]] = True
    return float((gt & pred).sum() / (gt | pred).sum())


@pytest.mark.parametrize("name", ["box", "gap", "L", "table"])
def test_navigable_cells_match_analytic_ground_truth(name):
    assert iou_against_analytic(name) >= 0.97


@pytest.mark.parametrize("name", ["box", "gap", "L", "table", "stairs"])
def test_navigable_cells_are_safe_and_on_the_floor(name):
    w, m = world(name), navmap(name)
    pts = m.points
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 100
    # Every navigable cell centre has a floor at the reported height ...
    assert np.allclose(w.floor_height(pts[:, :2]), pts[:, 2], atol=m.embodiment.max_step_height + 0.011)
    # ... and the agent's footprint fits there (no obstacle point of the body band within the radius).
    from image2sim.simulator.navigation.agent import CollisionWorld

    cw = CollisionWorld(m)
    mp = m.map_points
    for p in mp[:: max(1, len(mp) // 400)]:
        ok, z, _ = cw.check(p[:2], p[2])
        assert ok and z == pytest.approx(p[2], abs=1e-9)


def test_tabletop_is_an_obstacle_not_floor():
    m = navmap("table")
    top = over_box(m.points, (2.0, 1.5), (3.2, 2.3))
    assert not top.any()
    assert np.all(np.abs(m.points[:, 2]) < 0.02)
    assert m.num_levels == 1


@pytest.mark.parametrize("cameras", ["none", "unsupported"])
def test_a_bed_is_not_floor_when_no_camera_stands_above_the_floor(cameras):
    # A forward-looking capture rarely sees the floor within a metre below its cameras: the
    # components are then kept by area, and a bed (3.2 m^2 at 0.5 m) passes that test.
    bed_lo, bed_hi = (1.5, 1.0, 0.0), (3.5, 2.6, 0.5)
    w = syn.box_room(boxes=[(bed_lo, bed_hi)], spacing=SPACING)
    # "unsupported": cameras outside the room's floor (none has a floor cell within a metre below)
    cams = None if cameras == "none" else np.array([[-2.0, -2.0, 1.5], [8.0, -2.0, 1.5]])
    m = extract_navmap_from_points(w.points, w.normals, camera_positions=cams)
    assert not over_box(m.points, bed_lo, bed_hi).any()
    assert np.all(np.abs(m.points[:, 2]) < 0.02)
    assert m.num_levels == 1
    assert any("furniture tops" in n for n in m.notes)
    assert iou_against_analytic_world(w, m) >= 0.97


@pytest.mark.parametrize("over_bed_height", [1.5, 1.75])
def test_a_bed_beside_forward_looking_cameras_is_not_floor(over_bed_height):
    # A walking pinhole capture sees no floor at its cameras' feet: within a camera's reach the
    # nearest cell is often the bed beside it. Three cameras stand beside the bed with the floor
    # within 0.9 m of them unseen (a ring of floor still within reach), one stands over the bed
    # with no floor within its reach at all: the bed must not become floor. Raised 0.25 m above
    # the others, that camera's drop to the bed (1.25 m) must not count as the typical 1.5 m
    # either (it did within a 0.3 m band, session 52).
    bed_lo, bed_hi = (1.5, 1.0, 0.0), (3.5, 2.6, 0.5)
    w = syn.box_room(boxes=[(bed_lo, bed_hi)], spacing=SPACING)
    cams = np.array([[1.2, 1.8, 1.5], [2.5, 0.7, 1.5], [3.8, 1.8, 1.5], [2.5, 1.8, over_bed_height]])
    seen = np.ones(len(w.points), dtype=bool)
    on_floor = np.abs(w.points[:, 2]) < 1e-6
    for cam, r in zip(cams, (0.9, 0.9, 0.9, 1.2), strict=True):
        seen &= ~(on_floor & (np.linalg.norm(w.points[:, :2] - cam[:2], axis=1) < r))
    m = extract_navmap_from_points(w.points[seen], w.normals[seen], camera_positions=cams)
    assert not over_box(m.points, bed_lo, bed_hi).any()
    assert np.all(np.abs(m.points[:, 2]) < 0.02)
    assert m.navigable_area() > 10.0


def test_typical_camera_height_is_the_drop_to_the_lowest_surface_within_reach():
    z = np.array([0.0] * 6 + [0.5] * 40 + [0.75] * 30 + [-0.3])  # floor, bed, table, one stray cell
    cams = np.array([[0.0, 0.0, 1.5]] * 3)
    cands = [np.arange(46), np.arange(6, 76), np.arange(0, 6)]  # floor + bed, bed + table, floor
    assert typical_camera_height(cands, cams, z, 0.05) == pytest.approx(1.5)
    # With the stray cell below the floor (fewer than min_cells) the floor still wins.
    assert typical_camera_height([np.arange(77)], cams[:1], z, 0.05) == pytest.approx(1.5)
    assert typical_camera_height([np.zeros(0, dtype=np.int64)], cams[:1], z, 0.05) is None
    # A camera whose few cells lie decimetres apart shows no surface: it says nothing (it crashed
    # the extraction of a pinhole capture of procedural house 9202 at tier middle, session 52).
    scattered = np.array([0.0, 0.3, 0.6, 0.9, 1.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert typical_camera_height([np.arange(5)], cams[:1], scattered, 0.05) is None
    two = [np.arange(5), np.arange(5, 10)]  # the scattered camera and one over a floor
    assert typical_camera_height(two, cams[:2], scattered, 0.05) == pytest.approx(1.5)


def test_storeys_a_body_height_apart_stay_without_camera_support():
    # Two large floors 2.6 m apart are storeys, not a floor and a table: both are kept.
    a = syn.box_room(size_x=6.0, size_y=4.0, spacing=SPACING)
    b = syn.box_room(size_x=6.0, size_y=4.0, spacing=SPACING)
    pts = np.concatenate((a.points, b.points + np.array([8.0, 0.0, 2.6])))
    nrm = np.concatenate((a.normals, b.normals))
    m = extract_navmap_from_points(pts, nrm, camera_positions=None)
    assert m.num_levels == 2
    assert np.allclose(sorted(m.level_heights), [0.0, 2.6], atol=0.02)


def test_narrow_gap_has_no_navigable_cell_inside():
    m = navmap("narrow")
    in_gap = np.abs(m.points[:, 0] - 3.0) < 0.1
    assert not in_gap.any()


def test_two_levels_found_and_cliff_buffered():
    m = navmap("stairs")
    assert m.num_levels == 2
    assert np.allclose(sorted(m.level_heights), [0.0, 1.2], atol=0.02)
    for lvl in range(2):
        assert m.navigable_area(lvl) > 5.0
    # Upper storey cells near the drop at x = x_s (beside the stairs) keep the radius from the edge.
    upper = m.points[m.points[:, 2] > 1.1]
    x_s = 4.0 - 8 * 0.3 / 2
    beside = upper[(upper[:, 1] > 1.2 + RADIUS + 0.05)]
    assert beside[:, 0].min() >= x_s + RADIUS - 0.05 - 1e-9


def test_gravity_is_corrected_and_points_stay_in_world_frame():
    w = world("box")
    tilt = rotation_aligning(
        np.array([0.0, 0.0, 1.0]), np.array([math.sin(math.radians(5)), 0.0, math.cos(math.radians(5))])
    )
    pts = w.points @ tilt.T
    nrm = w.normals @ tilt.T
    cams = w.camera_positions @ tilt.T
    m = extract_navmap_from_points(pts, nrm, camera_positions=cams)
    assert abs(m.summary()["gravity_correction_deg"] - 5.0) < 0.2
    up = tilt @ np.array([0.0, 0.0, 1.0])
    # World-frame navigable points lie on the tilted floor plane through the origin.
    assert np.abs(m.points @ up).max() < 0.03
    assert abs(m.navigable_area() - navmap("box").navigable_area()) / navmap("box").navigable_area() < 0.08


def test_occlusion_hole_is_filled_on_the_plane():
    w = world("box")
    hole = (
        (np.abs(w.points[:, 0] - 3.0) < 0.08)
        & (np.abs(w.points[:, 1] - 2.0) < 0.08)
        & (w.points[:, 2] < 0.01)
    )
    m = extract_navmap_from_points(w.points[~hole], w.normals[~hole], camera_positions=w.camera_positions)
    assert m.floor_filled.sum() > 0
    filled = m.floor_points[m.floor_filled]
    assert np.abs(filled[:, 2]).max() < 0.01
    assert np.all(np.abs(filled[:, :2] - [3.0, 2.0]).max(axis=1) < 0.15)
    assert m.navigable_area() == pytest.approx(navmap("box").navigable_area(), abs=0.01)


def test_isolated_obstacle_noise_is_removed():
    w = world("box")
    rng = np.random.default_rng(0)
    noise = np.column_stack((rng.uniform(1, 5, 30), rng.uniform(1, 3, 30), rng.uniform(0.3, 1.2, 30)))
    m = extract_navmap_from_points(
        np.vstack((w.points, noise)),
        np.vstack((w.normals, np.tile([1.0, 0, 0], (30, 1)))),
        camera_positions=w.camera_positions,
    )
    assert m.navigable_area() == pytest.approx(navmap("box").navigable_area(), abs=0.01)
    assert any("outlier" in n for n in m.notes)


def test_pca_normals_without_given_normals():
    w = syn.box_room(3.0, 2.0, spacing=SPACING)
    ref = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    m = extract_navmap_from_points(w.points, None, camera_positions=w.camera_positions)
    assert abs(m.navigable_area() - ref.navigable_area()) < 0.1 * ref.navigable_area()


def test_semantic_floor_labels_restrict_floor():
    w = world("box")
    labels = np.where(w.normals[:, 2] > 0.9, 1, 2)
    labels[(w.points[:, 0] < 3.0) & (w.points[:, 2] < 0.01)] = (
        7  # left half of the floor is "rug" (not floor)
    )
    m = extract_navmap_from_points(
        w.points, w.normals, labels, w.camera_positions, config=NavMapConfig(floor_labels=(1,))
    )
    # The rug's columns hold no floor: no cell centre lies on it (the boundary cell straddles x = 3).
    assert m.points[:, 0].min() >= 3.0 - 0.5 * m.voxel_size - 1e-9
    # Counted as unseen space with the safety buffer, they also keep the agent's radius away.
    buffered = extract_navmap_from_points(
        w.points,
        w.normals,
        labels,
        w.camera_positions,
        config=NavMapConfig(floor_labels=(1,), unknown_clearance=None),
    )
    assert buffered.points[:, 0].min() > 3.0 + RADIUS - m.voxel_size


def test_save_load_round_trip(tmp_path):
    m = navmap("stairs")
    path = m.save(tmp_path / "navmap.npz")
    back = NavMap.load(path)
    assert np.allclose(back.points, m.points, atol=1e-5)
    # Every stored field comes back bit for bit: a job resuming from a saved map must compute what
    # the uninterrupted job computed from the fresh one (float32 storage once broke that).
    import dataclasses

    for field in dataclasses.fields(NavMap):
        a, b = getattr(m, field.name), getattr(back, field.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), field.name
        else:
            assert a == b, field.name
    assert back.embodiment == m.embodiment and back.config == m.config
    img = render_topdown(back)
    assert img.dtype == np.uint8 and img.ndim == 3


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(NavMapError, match="not found"):
        NavMap.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "bad.npz", x=np.zeros(2))
    with pytest.raises(NavMapError, match="bad.npz"):
        NavMap.load(tmp_path / "bad.npz")


def test_degenerate_inputs_raise_clear_errors():
    with pytest.raises(NavMapError, match="no finite points|floor"):
        extract_navmap_from_points(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(NavMapError, match=r"\(N, 3\)"):
        extract_navmap_from_points(np.zeros((5, 2)))
    wall = syn.plane_patch((0, 0, 0), (3, 0, 0), (0, 0, 2), (0, 1, 0), 0.05)
    with pytest.raises(NavMapError, match="floor"):
        extract_navmap_from_points(*wall)
    nan_pts = world("box").points.copy()
    nan_pts[::50] = np.nan
    m = extract_navmap_from_points(
        nan_pts, world("box").normals, camera_positions=world("box").camera_positions
    )
    assert np.isfinite(m.points).all()


def test_configs_reject_unknown_and_bad_fields():
    with pytest.raises(ConfigError, match="unknown"):
        NavMapConfig.from_dict({"voxel": 0.1})
    with pytest.raises(ConfigError, match="radius"):
        Embodiment(radius=-1.0)
    assert Embodiment.from_dict(Embodiment().to_dict()) == Embodiment()
    emb = Embodiment()
    assert (emb.radius, emb.eye_height, emb.forward_step, emb.turn_angle_deg, emb.max_step_height) == (
        0.15,
        1.25,
        0.25,
        15.0,
        0.15,
    )


def test_ransac_plane_recovers_plane_with_outliers():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-2, 2, (500, 2))
    n_true = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    z = -(n_true[0] * xy[:, 0] + n_true[1] * xy[:, 1] - 0.3) / n_true[2]
    pts = np.column_stack((xy, z))
    pts[:100] += rng.normal(0, 0.5, (100, 3))
    n, d, inl = fit_plane_ransac(pts, 0.01, 200, rng)
    # A few noisy outliers fall inside the 1 cm band and nudge the least-squares refit.
    assert np.allclose(n, n_true, atol=2e-3) and d == pytest.approx(-0.3, abs=2e-3)
    assert inl[100:].all()


# ---------------------------------------------------------------------------------------------
# Procedural scenes: exact navigable grid at 0.05 m.
# ---------------------------------------------------------------------------------------------


def procedural_iou(seed: int) -> float:
    proc = pytest.importorskip("image2sim.dataengine.procedural")
    from image2sim.simulator.navigation.extract import extract_navmap

    base = proc.preset("tiny")
    cfg = dataclasses.replace(
        base, capture=dataclasses.replace(base.capture, views=16, height=128, width=256)
    )
    scene = proc.generate_scene(cfg, seed=seed)
    frames, _ = proc.capture_frames(scene)
    m = extract_navmap(frames, config=NavMapConfig(pixel_stride=1))
    g = scene.grid
    h, w = g.navigable.shape
    ix = np.floor((m.points[:, 0] - g.origin[0]) / g.resolution).astype(int)
    iy = np.floor((m.points[:, 1] - g.origin[1]) / g.resolution).astype(int)
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    pred = np.zeros((h, w), dtype=bool)
    pred[iy[inside], ix[inside]] = True
    assert inside.mean() > 0.99  # nothing navigable outside the scene
    return float((pred & g.navigable).sum() / (pred | g.navigable).sum())


@pytest.mark.slow  # ~10 s idle, > 60 s on the shared 2-core machine (scene rendering + normals)
def test_procedural_navigable_iou():
    ious = [procedural_iou(seed) for seed in (0, 1, 2)]
    # Per scene the captures miss a few occluded corners; the mean is the contract.
    assert np.mean(ious) >= 0.9, ious
    assert min(ious) >= 0.85, ious


# ---------------------------------------------------------------------------------------------
# Real data: HM3D panoramas of a two-storey house.
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_hm3d_cameras_stand_above_navigable_floor(hm3d_scene_dir, capsys):
    # The paper's body (0.15 m step). The capture stood its cameras 1.5 m above the floor: 84 on the two
    # storeys and 2 on treads of the staircase (feet at -1.46 m and -0.71 m). Risers there are 0.20 m,
    # so for this body a tread is an island 0.22 m deep, narrower than its 0.30 m footprint: those two
    # cameras stand above extracted floor that is honestly not navigable. Every storey camera stands
    # above navigable floor. (With a body that climbs the risers all 86 do: test_nav_stairs.py.)
    from image2sim.simulator.io import open_capture
    from image2sim.simulator.navigation.extract import extract_navmap

    cap = open_capture(hm3d_scene_dir)
    m = extract_navmap(cap, config=NavMapConfig(pixel_stride=4))
    cams = m.to_map(np.array([f.cam_to_world[:3, 3] for f in cap]))

    def nearest_below(pts: np.ndarray, c: np.ndarray) -> tuple[float, float]:
        """Horizontal distance to the nearest cell below the camera and that cell's height."""
        below = pts[(pts[:, 2] < c[2] - 0.3) & (pts[:, 2] > c[2] - 2.5)]
        if not len(below):
            return np.inf, np.nan
        d = np.linalg.norm(below[:, :2] - c[:2], axis=1)
        return float(d.min()), float(below[np.argmin(d), 2])

    floor_d, floor_z = np.array([nearest_below(m.floor_points, c) for c in cams]).T
    nav_d = np.array([nearest_below(m.map_points, c)[0] for c in cams])
    heights = np.sort(m.level_heights)
    assert len(heights) == 2 and heights[1] - heights[0] > 2.0
    feet = cams[:, 2] - 1.5
    # A camera is on a storey when the floor right under it lies at a storey's height.
    on_storey = np.abs(floor_z[:, None] - heights[None, :]).min(axis=1) < 0.1
    assert on_storey.sum() == 84
    assert floor_d.max() < 0.3, floor_d  # every camera, stairs included, stands above extracted floor
    assert nav_d[on_storey].max() < 0.3, np.sort(nav_d[on_storey])[-3:]
    assert (nav_d[~on_storey] >= 0.3).all()  # the two on treads: not navigable for a 0.15 m step
    with capsys.disabled():
        for lvl, h in enumerate(m.level_heights):
            print(f"\nHM3D storey {lvl} at z={h:.2f} m: navigable {m.navigable_area(lvl):.1f} m^2")
        print(
            f"cameras above navigable floor: {int((nav_d < 0.3).sum())} of {len(cams)}; on stair treads "
            f"(feet {np.round(feet[~on_storey], 2).tolist()}): floor within {floor_d[~on_storey].max():.2f} m"
        )


def test_gaussian_scene_input_matches_point_input():
    from image2sim.simulator.navigation.extract import extract_navmap_from_gaussians

    w = syn.box_room(3.0, 2.0, spacing=SPACING)
    # Flat Gaussians lying in each surface: quaternion (w, x, y, z) turning +z onto the normal (the
    # half-way quaternion (1 + n_z, -n_y, n_x, 0)); +z -> -z is a half turn about x. Thin along z.
    n = w.normals
    q = np.column_stack((1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))))
    q[n[:, 2] < -0.999] = (0.0, 1.0, 0.0, 0.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales = np.tile([0.03, 0.03, 0.002], (len(n), 1))
    m = extract_navmap_from_gaussians(w.points, q, scales, np.full(len(n), 0.9), w.camera_positions)
    ref = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    assert m.navigable_area() == pytest.approx(ref.navigable_area(), rel=0.02)
