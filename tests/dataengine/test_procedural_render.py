"""Ray-cast rendering of procedural scenes against analytic ground truth and between casters."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from image2sim.dataengine.procedural.config import LayoutConfig, ObjectConfig, preset
from image2sim.dataengine.procedural.raycast import BoxCaster, embree_available
from image2sim.dataengine.procedural.render import render
from image2sim.dataengine.procedural.scene import generate_scene
from image2sim.simulator.conventions import camera_rotation_for_heading
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

CASTERS = ["numpy", "numpy-brute"] + (["embree"] if embree_available() else [])
FLOOR, WALL, CEILING = 1, 2, 3

EMPTY_ROOM = dataclasses.replace(
    preset("tiny"),
    layout=dataclasses.replace(preset("tiny").layout, rooms_min=1, rooms_max=1),
    objects=ObjectConfig(furniture_scale=0.0),
)


def _pose(x: float, y: float, z: float, yaw: float, pitch: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = camera_rotation_for_heading(yaw, pitch)
    pose[:3, 3] = (x, y, z)
    return pose


def _world_rays(camera, pose):
    rays = camera.ray_map(torch.float64).permute(1, 2, 0).reshape(-1, 3).numpy()
    return rays, rays @ pose[:3, :3].T


def _analytic_room(o, dirs, interior, height):
    """Distance to the inside of the box room, the axis of the plane hit, and whether it is a tie."""
    x0, y0, x1, y1 = interior
    lo = np.array([x0, y0, 0.0])
    hi = np.array([x1, y1, height])
    with np.errstate(divide="ignore"):
        t_axes = np.where(dirs > 0, (hi - o) / dirs, (lo - o) / dirs)
    t_axes = np.where(np.abs(dirs) < 1e-15, np.inf, t_axes)
    order = np.sort(t_axes, axis=1)
    return order[:, 0], np.argmin(t_axes, axis=1), (order[:, 1] - order[:, 0]) < 1e-6


@pytest.mark.parametrize("caster", CASTERS)
@pytest.mark.parametrize("model", ["equirect", "pinhole"])
def test_depth_and_labels_match_the_analytic_room(caster, model):
    scene = generate_scene(EMPTY_ROOM, 5)
    room = scene.layout.rooms[0]
    interior = room.interior(scene.layout.wall_thickness)
    height = scene.layout.ceiling_height
    camera = EquirectCamera(32, 64) if model == "equirect" else PinholeCamera(40.0, 38.0, 33.0, 23.5, 48, 64)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x = rng.uniform(interior[0] + 0.3, interior[2] - 0.3)
        y = rng.uniform(interior[1] + 0.3, interior[3] - 0.3)
        pose = _pose(x, y, rng.uniform(1.25, 1.6), rng.uniform(-math.pi, math.pi), rng.uniform(-0.6, 0.6))
        out = render(scene, camera, pose, caster=caster)
        rays_cam, dirs = _world_rays(camera, pose)
        t, axis, tie = _analytic_room(pose[:3, 3], dirs, interior, height)
        expected = t if model == "equirect" else t * rays_cam[:, 2]
        np.testing.assert_allclose(out["depth"].reshape(-1), expected, atol=1e-4, rtol=0)
        sem = np.where(axis < 2, WALL, np.where(dirs[:, 2] > 0, CEILING, FLOOR))
        got = out["semantics"].reshape(-1)
        assert np.array_equal(got[~tie], sem[~tie])
        assert (out["instances"] == 0).all()


@pytest.fixture(scope="module")
def furnished():
    cfg = dataclasses.replace(
        preset("tiny"),
        layout=LayoutConfig(rooms_min=2, rooms_max=3, room_size_min=2.6, room_size_max=4.0),
        objects=ObjectConfig(furniture_scale=1.2, small_per_surface_max=3, small_probability=1.0),
    )
    return generate_scene(cfg, 11)


def _views(scene, n, seed=0):
    iy, ix = np.nonzero(scene.grid.navigable)
    rng = np.random.default_rng(seed)
    pick = rng.choice(iy.size, n, replace=False)
    xy = scene.grid.cell_centers(iy[pick], ix[pick])
    return [_pose(p[0], p[1], 1.4, rng.uniform(-math.pi, math.pi)) for p in xy]


def _on_box_surface(p, lo, hi, tol=1e-4):
    inside = np.all((p >= lo - tol) & (p <= hi + tol), axis=-1)
    on_face = np.any((np.abs(p - lo) <= tol) | (np.abs(p - hi) <= tol), axis=-1)
    return inside & on_face


def test_object_pixels_lie_on_their_object(furnished):
    scene = furnished
    camera = EquirectCamera(64, 128)
    n_object_pixels = 0
    for pose in _views(scene, 3):
        out = render(scene, camera, pose)
        _, dirs = _world_rays(camera, pose)
        depth = out["depth"].reshape(-1).astype(np.float64)
        points = pose[:3, 3] + depth[:, None] * dirs
        inst = out["instances"].reshape(-1)
        sem = out["semantics"].reshape(-1)
        for k in np.unique(inst[inst > 0]):
            obj = scene.object_by_id(int(k))
            sel = inst == k
            n_object_pixels += int(sel.sum())
            assert (sem[sel] == obj.category.id).all()
            on_any = np.zeros(int(sel.sum()), dtype=bool)
            for part in obj.parts:
                on_any |= _on_box_surface(points[sel], np.asarray(part.lo), np.asarray(part.hi))
            assert on_any.all(), (
                f"{obj.category.name}: {int((~on_any).sum())} pixels off the object's surface"
            )
    assert n_object_pixels > 100


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
def test_embree_and_numpy_casters_agree_with_the_brute_force_reference(furnished):
    scene = furnished
    camera = EquirectCamera(48, 96)
    ref = BoxCaster(scene.box_lo, scene.box_hi, cull=False)
    for pose in _views(scene, 3, seed=1):
        rays_cam, dirs = _world_rays(camera, pose)
        t_ref, box_ref, _ = ref.cast(pose[:3, 3], dirs)
        assert (box_ref >= 0).all()
        for kind in ("numpy", "embree"):
            t, box, _ = scene.caster(kind).cast(pose[:3, 3], dirs, (camera.height, camera.width))
            np.testing.assert_allclose(t, t_ref, atol=1e-7, rtol=0)
            # Different boxes only where two surfaces are hit at the same distance (coplanar faces).
            assert (box == box_ref).mean() > 0.99


def test_yaw_rotation_rolls_the_panorama(furnished):
    """A camera turned by k pixel columns of yaw sees the same panorama rolled by k columns (seam wraps)."""
    scene = furnished
    camera = EquirectCamera(32, 64)
    base = _views(scene, 1, seed=2)[0]
    k = 5
    # Camera x (right) points along -heading-left; turning right by dlon shifts content to the left.
    turned = base.copy()
    yaw = math.atan2(base[1, 2], base[0, 2])
    turned[:3, :3] = camera_rotation_for_heading(yaw - 2 * math.pi * k / camera.width)
    a = render(scene, camera, base)
    b = render(scene, camera, turned)
    rolled = np.roll(a["depth"], -k, axis=1)
    close = np.abs(rolled - b["depth"]) < 1e-4
    assert close.mean() > 0.99
    assert (np.roll(a["semantics"], -k, axis=1) == b["semantics"]).mean() > 0.99


def test_poles_see_ceiling_and_floor(furnished):
    scene = furnished
    camera = EquirectCamera(32, 64)
    for pose in _views(scene, 2, seed=3):
        out = render(scene, camera, pose)
        h = scene.layout.ceiling_height
        z = pose[2, 3]
        # Top row is within 2.9 deg of straight up: ceiling (or an object hanging above, never here).
        assert (out["semantics"][0] == CEILING).all()
        np.testing.assert_allclose(out["depth"][0], (h - z) / math.cos(math.pi / 64), rtol=1e-5)
        bottom = out["semantics"][-1]
        assert np.isin(bottom, [FLOOR, 10]).all()  # floor or a rug


def test_render_is_deterministic_and_rejects_bad_poses(furnished):
    camera = EquirectCamera(16, 32)
    pose = _views(furnished, 1, seed=4)[0]
    a = render(furnished, camera, pose)
    b = render(furnished, camera, pose)
    for key in ("rgb", "depth", "semantics", "instances"):
        assert np.array_equal(a[key], b[key])
    assert a["rgb"].dtype == np.uint8 and a["depth"].dtype == np.float32 and a["semantics"].dtype == np.int32
    bad = pose.copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        render(furnished, camera, bad)


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
def test_embree_misses_are_recast_exactly(furnished):
    """Rays Embree reports as misses (float32 edge leaks) are re-cast by the exact slab test."""
    from image2sim.dataengine.procedural.raycast import EmbreeCaster

    scene = furnished
    caster = EmbreeCaster(scene.box_lo, scene.box_hi)
    camera = EquirectCamera(16, 32)
    pose = _views(scene, 1, seed=5)[0]
    _, dirs = _world_rays(camera, pose)
    t_ok, box_ok, _ = caster.cast(pose[:3, 3], dirs)
    real_run = caster._scene.run

    def leaky_run(origins, directions, *args, **kwargs):
        tri = np.array(real_run(origins, directions, *args, **kwargs))
        tri[::3] = -1
        return tri

    caster._scene = type("Leaky", (), {"run": staticmethod(leaky_run)})()
    t, box, _ = caster.cast(pose[:3, 3], dirs)
    assert (box >= 0).all()
    np.testing.assert_allclose(t, t_ok, atol=1e-9)


def test_rays_that_leave_the_house_are_invalid_not_nan(furnished):
    """A camera outside the house: rays that hit nothing get depth 0, label 0 and black colour."""
    camera = EquirectCamera(16, 32)
    x0, y0, x1, y1 = furnished.layout.bounds()
    pose = _pose(x0 - 3.0, 0.5 * (y0 + y1), 1.4, 0.0)
    out = render(furnished, camera, pose)
    miss = out["box"] < 0
    assert miss.any() and (~miss).any()
    assert np.isfinite(out["depth"]).all()
    assert (
        (out["depth"][miss] == 0).all()
        and (out["semantics"][miss] == 0).all()
        and (out["rgb"][miss] == 0).all()
    )
    assert (out["semantics"][~miss] == WALL).mean() > 0.5  # the outside of the exterior walls
    empty = BoxCaster(furnished.box_lo, furnished.box_hi).cast(np.zeros(3), np.zeros((0, 3)))
    assert all(a.size == 0 for a in empty)
