"""Plane completion of textureless segments (lift.planes) on an analytic box room: exact depth where it
fills, nothing where a segment spans two planes or its plane would float in space another view sees."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.lift.planes import (
    PLANE_FILL_CONFIDENCE,
    PlaneFillConfig,
    fill_planes,
    fit_plane,
)
from image2sim.simulator.lift.types import DepthEstimate, PinholeView

H, W = 96, 128
K = np.array([[64.0, 0.0, W / 2], [0.0, 64.0, H / 2], [0.0, 0.0, 1.0]])
# Room [-2, 2] x [-2, 2] x [0, 2.5] (z up): planes as (world normal, offset) of n . x = d.
PLANES = [
    (np.array([1.0, 0, 0]), -2.0),
    (np.array([1.0, 0, 0]), 2.0),
    (np.array([0, 1.0, 0]), -2.0),
    (np.array([0, 1.0, 0]), 2.0),
    (np.array([0, 0, 1.0]), 0.0),
    (np.array([0, 0, 1.0]), 2.5),
]
COLOURS = np.array(
    [[200, 60, 60], [60, 200, 60], [60, 60, 200], [200, 200, 60], [120, 120, 120], [230, 230, 230]]
)


def _pose(position, yaw_deg: float) -> np.ndarray:
    """OpenCV camera (x right, y down, z forward) looking level along yaw (0 = +y) at ``position``."""
    a = np.radians(yaw_deg)
    fwd = np.array([np.sin(a), np.cos(a), 0.0])
    right = np.array([np.cos(a), -np.sin(a), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = position
    return T


def _render(T: np.ndarray, colours=COLOURS):
    """Exact z-depth, plane id and a flat colour per plane for camera ``T``."""
    u = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    rays_c = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((H, W))), axis=-1)
    rays_w = rays_c @ T[:3, :3].T
    o = T[:3, 3]
    best = np.full((H, W), np.inf)
    pid = np.zeros((H, W), dtype=int)
    for k, (n, d) in enumerate(PLANES):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - o @ n) / (rays_w @ n)
        hit = o + t[..., None] * rays_w
        inside = (t > 0) & np.all((hit >= [-2.001, -2.001, -0.001]) & (hit <= [2.001, 2.001, 2.501]), axis=-1)
        better = inside & (t < best)
        best[better], pid[better] = t[better], k
    image = colours[pid].astype(np.uint8)
    return best.astype(np.float32), pid, image  # t along a z = 1 ray is the z-depth


def _sparse_estimate(depth: np.ndarray, rng, keep: float = 0.06) -> DepthEstimate:
    """Confident exact depth at a random ``keep`` share of pixels, nothing elsewhere."""
    mask = rng.random(depth.shape) < keep
    return DepthEstimate(
        depth=np.where(mask, depth, 0.0).astype(np.float32),
        confidence=np.where(mask, 0.6, 0.0).astype(np.float32),
    )


def test_fit_plane_recovers_a_plane_through_outliers():
    rng = np.random.default_rng(0)
    n_true = np.array([0.2, -0.3, 0.93])
    n_true /= np.linalg.norm(n_true)
    xy = rng.uniform(-1, 1, (300, 2))
    z = (2.0 - n_true[0] * xy[:, 0] - n_true[1] * xy[:, 1]) / n_true[2]
    pts = np.column_stack([xy, z])
    pts[:90] += rng.normal(0, 0.5, (90, 3))  # 30 % outliers
    n, d, inliers = fit_plane(pts, 0.005, np.random.default_rng(1), 64)
    # Outliers that happen to lie within the tolerance join the refit: exact to ~1e-4, not to rounding.
    assert abs(abs(n @ n_true) - 1) < 1e-6 and d * np.sign(n @ n_true) == pytest.approx(2.0, abs=1e-3)
    assert inliers[90:].all() and inliers[:90].mean() < 0.1
    assert fit_plane(pts[:2], 0.01, rng) is None
    assert fit_plane(np.array([[0, 0, 1.0], [1, 1, 1], [2, 2, 1]]), 0.01, rng) is None  # collinear


def test_textureless_walls_are_completed_with_their_exact_depth():
    rng = np.random.default_rng(0)
    poses = [_pose([0.3, -1.0, 1.5], 10), _pose([-0.5, -0.8, 1.4], -35)]
    views, ests, truths = [], [], []
    for T in poses:
        depth, _, image = _render(T)
        views.append(PinholeView(image, K, T))
        truths.append(depth)
        ests.append(_sparse_estimate(depth, rng))
    out, stats = fill_planes(views, ests)
    for est, new, truth in zip(ests, out, truths, strict=True):
        kept = est.depth > 0
        assert np.array_equal(new.depth[kept], est.depth[kept])  # never changes existing depth
        assert np.array_equal(new.confidence[kept], est.confidence[kept])
        filled = ~kept & (new.depth > 0)
        assert filled.mean() > 0.8, stats
        assert np.all(new.confidence[filled] == np.float32(PLANE_FILL_CONFIDENCE))
        rel = np.abs(new.depth[filled] - truth[filled]) / truth[filled]
        assert np.percentile(rel, 99) < 1e-3, stats
    assert stats["pixels"] > 0 and stats["free_space"] == 0


def test_a_segment_spanning_two_planes_is_not_filled():
    """Back wall and floor in one colour: one segment whose support lies on two planes."""
    colours = COLOURS.copy()
    colours[4] = colours[3]  # floor = the wall at y = +2
    T = _pose([0.0, -1.5, 1.5], 0)
    depth, pid, image = _render(T, colours)
    est = _sparse_estimate(depth, np.random.default_rng(1))
    (new,), stats = fill_planes([PinholeView(image, K, T)], [est], PlaneFillConfig(cross_view_support=False))
    both = (pid == 3) | (pid == 4)
    assert stats["not_planar"] >= 1
    assert not ((new.depth > 0) & (est.depth <= 0) & both).any()
    # The other walls are still completed.
    assert ((new.depth > 0) & (est.depth <= 0) & ~both).mean() > 0.2


def test_a_plane_floating_in_space_another_view_sees_is_refused():
    """Support of one wall corrupted onto a plane 0.6 m in front of it: the second view sees the true
    wall behind the filled points, so the segment is dropped."""
    rng = np.random.default_rng(2)
    T0, T1 = _pose([0.0, -1.0, 1.5], 0), _pose([1.0, -1.2, 1.5], -20)
    d0, pid0, im0 = _render(T0)
    d1, _, im1 = _render(T1)
    e0 = _sparse_estimate(d0, rng)
    wall = (pid0 == 3) & (e0.depth > 0)  # the wall at y = +2, seen along +y: z-depth = 2 - (-1) = 3
    e0.depth[wall] = e0.depth[wall] - 0.6
    e1 = DepthEstimate(depth=d1.copy(), confidence=np.full(d1.shape, 0.6, np.float32))  # sees all
    views = [PinholeView(im0, K, T0), PinholeView(im1, K, T1)]
    cfg = PlaneFillConfig(cross_view_support=False)
    (new0, _), stats = fill_planes(views, [e0, e1], cfg)
    assert stats["free_space"] >= 1
    assert not ((new0.depth > 0) & (e0.depth <= 0) & (pid0 == 3)).any()
    # Without the check the wrong plane would have been written.
    loose = PlaneFillConfig(cross_view_support=False, max_free_space_violations=1.0)
    (bad0, _), _ = fill_planes(views, [e0, e1], loose)
    assert ((bad0.depth > 0) & (e0.depth <= 0) & (pid0 == 3)).any()


def _back_wall_view():
    """A view facing the wall at y = +2 squarely, that wall (plane id 3) and its pixel mask."""
    T = _pose([0.0, -1.0, 1.2], 0)
    depth, pid, image = _render(T)
    return T, depth, image, pid == 3


def test_support_along_one_line_fixes_no_plane():
    """Confident depth only along a diagonal of the wall: every plane through that 3D line fits it."""
    T, depth, image, wall = _back_wall_view()
    rows, cols = np.nonzero(wall)
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    line = np.zeros_like(wall)
    for k in range(200):
        line[r0 + (r1 - r0) * k // 199, c0 + (c1 - c0) * k // 199] = True
    est = DepthEstimate(
        depth=np.where(line, depth, 0).astype(np.float32),
        confidence=np.where(line, 0.6, 0).astype(np.float32),
    )
    (new,), stats = fill_planes([PinholeView(image, K, T)], [est])
    assert stats["line_support"] == 1 and not ((new.depth > 0) & ~line & wall).any()


def test_a_plane_is_not_extrapolated_beyond_its_support():
    """Support on the left half of the wall only: the right half stays empty (and is filled, exactly,
    when extrapolation is allowed)."""
    T, depth, image, wall = _back_wall_view()
    cols = np.nonzero(wall)[1]
    left = wall & (np.arange(W)[None, :] < (cols.min() + cols.max()) // 2)
    sup = left & (np.random.default_rng(3).random(left.shape) < 0.2)
    est = DepthEstimate(
        depth=np.where(sup, depth, 0).astype(np.float32), confidence=np.where(sup, 0.6, 0).astype(np.float32)
    )
    (new,), _ = fill_planes([PinholeView(image, K, T)], [est])
    right = wall & ~left
    assert ((new.depth > 0) & left & ~sup).mean() > 0.5 * (left & ~sup).mean()
    assert not ((new.depth > 0) & right)[:, (np.nonzero(right)[1].min() + 3) :].any()
    (far,), _ = fill_planes([PinholeView(image, K, T)], [est], PlaneFillConfig(interpolate_only=False))
    filled = (far.depth > 0) & right
    assert filled.sum() > 0.9 * right.sum()
    assert np.abs(far.depth[filled] - depth[filled]).max() < 1e-3 * depth[filled].max()


def test_bad_inputs():
    T = _pose([0.0, -1.0, 1.5], 0)
    depth, _, image = _render(T)
    est = DepthEstimate(depth=np.full_like(depth, np.nan), confidence=np.zeros_like(depth))
    (new,), stats = fill_planes([PinholeView(image, K, T)], [est])  # NaN depth: nothing to fit to
    assert stats["pixels"] == 0 and np.array_equal(np.isnan(new.depth), np.isnan(est.depth))
    assert fill_planes([], []) == ([], {k: 0 for k in stats})
    with pytest.raises(ValueError, match="views but"):
        fill_planes([PinholeView(image, K, T)], [])
    with pytest.raises(ValueError, match="unknown plane-fill option"):
        PlaneFillConfig.from_kwargs(tolerance=0.1)
    for bad in ({"inlier_tolerance": 0.0}, {"min_inlier_fraction": 1.5}, {"min_ray_angle_deg": 90.0}):
        with pytest.raises(ValueError, match="PlaneFillConfig"):
            PlaneFillConfig(**bad)


def test_cube_faces_of_one_panorama_do_not_crowd_out_the_neighbours():
    """Faces sharing a centre split the sphere: none lends support to another, so the nearest-view
    list skips them; a same-centre view that overlaps (rotated 30 degrees) is kept."""
    from image2sim.simulator.lift.planes import _neighbours

    size = 32
    Kf = np.array([[size / 2, 0, size / 2], [0, size / 2, size / 2], [0, 0, 1.0]])  # 90 degrees
    img = np.zeros((size, size, 3), np.uint8)
    faces = [_pose([0.0, 0.0, 1.5], yaw) for yaw in (0, 90, 180, 270)]
    for pitch in (90, -90):  # up and down: rotate the level camera about its x axis
        T = _pose([0.0, 0.0, 1.5], 0)
        a = np.radians(pitch)
        rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        T[:3, :3] = T[:3, :3] @ rx
        faces.append(T)
    views = [PinholeView(img, Kf, T) for T in faces]
    views.append(PinholeView(img, Kf, _pose([0.0, 0.0, 1.5], 30)))  # same centre, overlaps face 0
    views.append(PinholeView(img, Kf, _pose([1.0, 0.0, 1.5], 0)))  # another panorama's face
    centres = np.stack([v.cam_to_world[:3, 3] for v in views])
    assert _neighbours(0, views, centres, 12) == [6, 7]
    assert _neighbours(1, views, centres, 12) == [6, 7]  # 90 + 30 degrees: overlaps the rotated view
    assert _neighbours(2, views, centres, 12) == [
        7
    ]  # opposite face 0: disjoint from both at 0 and 30 degrees
