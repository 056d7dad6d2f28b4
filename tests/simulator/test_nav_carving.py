"""Visibility carving of floating obstacle voxels: the fast counts against the per-point reference,
and the rule on a wall seen by several views."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.navigation.carving import (
    DepthView,
    floater_mask,
    see_through_counts,
    see_through_counts_reference,
)

# OpenCV camera looking along +x in a Z-up world.
_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _pose(centre) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = _AXES, centre
    return pose


def _wall_views(camera, xs=(0.0, 0.0, 0.0, 0.0), ys=(-0.3, -0.1, 0.1, 0.3)) -> list[DepthView]:
    """Views from x = 0 looking at the wall x = 3 (z-depth 3 for pinhole, range for equirect)."""
    views = []
    for x, y in zip(xs, ys, strict=True):
        h, w = camera.height, camera.width
        vv, uu = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
        import torch

        ray = camera.pixel_to_ray(torch.from_numpy(uu), torch.from_numpy(vv)).numpy()
        forward = ray[..., 2]
        t = np.where(forward > 0.05, (3.0 - x) / np.maximum(forward, 1e-9), 0.0)  # range to the wall
        depth = t * forward if isinstance(camera, PinholeCamera) else t
        views.append(DepthView(depth.astype(np.float32), camera, _pose((x, y, 1.5))))
    return views


@pytest.mark.parametrize("camera", [PinholeCamera(40.0, 40.0, 32.0, 24.0, 48, 64), EquirectCamera(32, 64)])
@pytest.mark.parametrize("window", [0, 1])
def test_fast_counts_match_the_reference_with_holes(camera, window):
    rng = np.random.default_rng(3)
    views = _wall_views(camera)
    holed = [
        DepthView(np.where(rng.random(v.depth.shape) < 0.2, 0.0, v.depth), v.camera, v.cam_to_world)
        for v in views
    ]
    pts = np.column_stack((rng.uniform(-1, 4, 300), rng.uniform(-2, 2, 300), rng.uniform(0, 3, 300)))
    kw = dict(margin=0.1, margin_rel=0.05, window=window)
    fast = see_through_counts(pts, holed, **kw)
    np.testing.assert_array_equal(fast, see_through_counts_reference(pts, holed, **kw))
    assert fast.max() == len(views) and fast.min() == 0  # both outcomes occur


def test_a_floater_in_front_of_a_wall_is_dropped_and_the_wall_kept():
    cam = PinholeCamera(40.0, 40.0, 32.0, 24.0, 48, 64)
    views = _wall_views(cam)
    floater = [1.5, 0.0, 1.5]  # 1.5 m in front of the wall
    wall = [3.0, 0.0, 1.5]
    behind = [3.5, 0.0, 1.5]  # occluded: never seen beyond
    voxels = np.array([floater, wall, behind])
    drop = floater_mask(voxels, np.array([1, 4, 1]), views, min_views=3, ratio=2.0)
    assert drop.tolist() == [True, False, False]
    # A floater that as many views put points in as see through it stays (ratio), and so does one
    # fewer views than min_views see through.
    assert not floater_mask(voxels[:1], np.array([2]), views, min_views=3, ratio=2.0)[0]
    assert not floater_mask(voxels[:1], np.array([1]), views[:2], min_views=3, ratio=2.0)[0]


def test_no_points_and_all_holes_count_nothing():
    cam = PinholeCamera(40.0, 40.0, 32.0, 24.0, 48, 64)
    views = [DepthView(np.zeros((48, 64), np.float32), cam, _pose((0.0, 0.0, 1.5)))]
    assert see_through_counts(np.zeros((0, 3)), views, margin=0.1, margin_rel=0.05, window=1).shape == (0,)
    assert (
        see_through_counts(np.array([[1.0, 0.0, 1.5]]), views, margin=0.1, margin_rel=0.05, window=1)[0] == 0
    )
