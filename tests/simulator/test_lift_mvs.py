"""Plane-sweep multi-view stereo (lift.mvs): parity with the per-pixel references, accuracy on
analytic planes and procedural houses against exact depth, and the hard cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from image2sim.simulator.lift import mvs
from image2sim.simulator.lift.mvs import MVSConfig, run_mvs
from image2sim.simulator.lift.types import PinholeView, SparseDepth


def _K(h: int, w: int, hfov_deg: float = 70.0) -> np.ndarray:
    f = 0.5 * w / math.tan(math.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])


def _value_noise(x: np.ndarray, y: np.ndarray, cell: float, seed: int) -> np.ndarray:
    """Smooth random texture in [0, 1]: bilinear interpolation of a random grid of ``cell`` metres."""
    grid = np.random.default_rng(seed).random((256, 256))
    gx, gy = x / cell + 128.0, y / cell + 128.0
    x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
    fx, fy = gx - x0, gy - y0
    x0, y0 = np.clip(x0, 0, 254), np.clip(y0, 0, 254)
    top = grid[y0, x0] * (1 - fx) + grid[y0, x0 + 1] * fx
    bottom = grid[y0 + 1, x0] * (1 - fx) + grid[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _plane_scene(
    centres: list[tuple[float, float, float]],
    *,
    h: int = 96,
    w: int = 128,
    depth0: float = 3.0,
    slope: float = 0.3,
    flat_right: bool = False,
    noise: float = 2.0,
    seed: int = 0,
) -> tuple[list[PinholeView], list[np.ndarray]]:
    """Cameras at ``centres`` looking along world +Z (R = I) at the plane Z = depth0 + slope * X.

    The plane carries value noise (two octaves); with ``flat_right`` its X > 0 half is a flat grey.
    Returns the views (RGB with Gaussian noise of ``noise`` levels) and their exact z-depths.
    """
    K = _K(h, w)
    vv, uu = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    rng = np.random.default_rng(seed + 1)
    views, depths = [], []
    for c in centres:
        c = np.asarray(c, np.float64)
        t = (depth0 + slope * c[0] - c[2]) / (rays[..., 2] - slope * rays[..., 0])
        X, Y = c[0] + t * rays[..., 0], c[1] + t * rays[..., 1]
        tex = 0.65 * _value_noise(X, Y, 0.08, seed) + 0.35 * _value_noise(X, Y, 0.03, seed + 7)
        if flat_right:
            tex = np.where(X > 0, 0.5, tex)
        grey = 40.0 + 180.0 * tex + rng.normal(0.0, noise, tex.shape)
        rgb = np.clip(np.rint(np.repeat(grey[..., None], 3, -1) * [1.0, 0.95, 0.9]), 0, 255).astype(np.uint8)
        pose = np.eye(4)
        pose[:3, 3] = c
        views.append(PinholeView(rgb, K, pose))
        depths.append((t * rays[..., 2]).astype(np.float32))
    return views, depths


def _sparse(depths: list[np.ndarray], k: int = 200, seed: int = 0) -> list[SparseDepth]:
    """SfM-like sparse depths: ``k`` random pixels per view with their exact depth."""
    rng = np.random.default_rng(seed)
    out = []
    for d in depths:
        h, w = d.shape
        idx = rng.choice(h * w, min(k, h * w), replace=False)
        r, c = np.divmod(idx, w)
        ok = d[r, c] > 0
        out.append(SparseDepth(np.stack([c[ok] + 0.5, r[ok] + 0.5], 1), d[r, c][ok].astype(np.float64)))
    return out


def _abs_rel(est, depths, min_conf: float = 0.0) -> tuple[float, float]:
    """AbsRel over confident pixels of all views and the confident fraction of all pixels."""
    err, n, total = 0.0, 0, 0
    for e, gt in zip(est, depths, strict=True):
        m = (e.confidence > min_conf) & (gt > 0)
        assert np.all(e.depth[m] > 0)
        err += float(np.sum(np.abs(e.depth[m] - gt[m]) / gt[m]))
        n += int(m.sum())
        total += gt.size
    return err / max(n, 1), n / total


GRID = [(-0.2, 0.0, 0.0), (0.0, -0.1, 0.0), (0.2, 0.0, 0.0), (0.0, 0.1, 0.0), (0.1, 0.05, 0.1)]


# ----------------------------------------------------------------------------------------- parity


def test_plane_sweep_matches_the_per_pixel_reference():
    views, depths = _plane_scene(GRID[:3], h=10, w=12)
    grays = [mvs.to_gray(v.image) for v in views]
    terms = [mvs._homography_terms(views[0], v) for v in views[1:]]
    inv = mvs.inverse_depth_planes(1.5, 6.0, 6)
    for best_k in (1, 2):
        fast, std = mvs.plane_sweep_cost(grays[0], grays[1:], terms, inv, window=5, best_k=best_k)
        slow, std_ref = mvs.plane_sweep_cost_reference(
            grays[0].double().numpy(),
            [g.double().numpy() for g in grays[1:]],
            [(A.numpy(), b.numpy()) for A, b in terms],
            inv.numpy(),
            window=5,
            best_k=best_k,
        )
        np.testing.assert_allclose(fast.numpy(), slow, atol=2e-4)
        np.testing.assert_allclose(std.numpy(), std_ref, atol=1e-5)
    # Some plane/pixel pairs fall outside a source: the sweep covers them (MAX_COST or fewer sources).
    assert (slow == mvs.MAX_COST).any()


def test_plane_chunks_do_not_change_the_cost():
    views, _ = _plane_scene(GRID[:3], h=24, w=32)
    grays = [mvs.to_gray(v.image) for v in views]
    terms = [mvs._homography_terms(views[0], v) for v in views[1:]]
    inv = mvs.inverse_depth_planes(1.5, 6.0, 16)
    whole, _ = mvs.plane_sweep_cost(grays[0], grays[1:], terms, inv, window=5, best_k=2)
    assert mvs._chunk_planes(16, 2, 24, 32, 0.05) < 16
    chunked, _ = mvs.plane_sweep_cost(grays[0], grays[1:], terms, inv, window=5, best_k=2, max_chunk_mb=0.05)
    assert torch.equal(whole, chunked)
    # A per-pixel inverse depth (P, H, W) (slanted planes, ``plane_ncc``) that is constant per plane
    # gives the fronto-parallel planes' cost.
    maps = inv[:, None, None].expand(16, 24, 32).contiguous()
    per_pixel, _ = mvs.plane_sweep_cost(grays[0], grays[1:], terms, maps, window=5, best_k=2)
    assert torch.equal(whole, per_pixel)


def test_winner_take_all_matches_the_per_pixel_reference():
    rng = np.random.default_rng(3)
    P, h, w = 12, 7, 9
    # Parabola-like cost curves around random minima plus noise, a few flat and edge minima.
    idx = rng.integers(0, P, (h, w))
    planes = np.arange(P)[:, None, None]
    cost = 0.05 + 0.03 * (planes - idx[None] - rng.uniform(-0.4, 0.4, (h, w))[None]) ** 2
    cost = np.minimum(cost, 1.5) + rng.uniform(0, 0.02, (P, h, w))
    cost[:, 0, :3] = 0.9
    std = rng.uniform(0.0, 0.05, (h, w))
    inv = np.linspace(1 / 0.5, 1 / 8.0, P)
    kw = {"min_texture": 0.01, "min_ncc": 0.5, "min_confidence": 0.05}
    d_ref, c_ref = mvs.winner_take_all_reference(cost, inv, std, **kw)
    d, c = mvs.winner_take_all(
        torch.from_numpy(cost).float(), torch.from_numpy(inv), torch.from_numpy(std).float(), **kw
    )
    np.testing.assert_allclose(d.numpy(), d_ref, rtol=1e-5)
    np.testing.assert_allclose(c.numpy(), c_ref, atol=1e-5)
    assert (c_ref == 0).any() and (c_ref > 0).any()


def test_geometric_consistency_matches_the_per_pixel_reference():
    views, depths = _plane_scene(GRID[:3], h=12, w=16)
    rng = np.random.default_rng(0)
    noisy = [d * np.where(rng.random(d.shape) < 0.3, 1.1, 1.0) for d in depths]
    noisy[1][:3] = 0.0
    Ks = [v.K for v in views]
    poses = [v.cam_to_world for v in views]
    neighbours = [[1, 2], [0, 2], [0]]
    kw = {"tolerance": 0.02, "max_reproj_px": 1.0}
    slow = mvs.geometric_consistency_reference(noisy, Ks, poses, neighbours, **kw)
    fast = mvs.geometric_consistency(
        [torch.from_numpy(d) for d in noisy],
        [torch.from_numpy(K) for K in Ks],
        [torch.from_numpy(T) for T in poses],
        neighbours,
        **kw,
    )
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(a.numpy(), b)
    assert slow[0].max() == 2 and (slow[0] < 2).any()


# --------------------------------------------------------------------------------------- accuracy


def test_textured_slanted_plane_is_recovered():
    views, depths = _plane_scene(GRID)
    stats: list[dict] = []
    est = run_mvs(views, _sparse(depths), stats=stats)
    abs_rel, covered = _abs_rel(est, depths)
    assert abs_rel < 0.02, abs_rel
    assert covered > 0.8, covered
    assert all(len(s["sources"]) >= 2 for s in stats)
    for e in est:
        assert e.depth.dtype == np.float32 and e.confidence.dtype == np.float32
        assert e.confidence.min() >= 0 and e.confidence.max() <= 1
        assert np.all((e.depth > 0) == (e.confidence > 0))


def test_textureless_half_gets_no_confidence():
    views, depths = _plane_scene(GRID, flat_right=True)
    est = run_mvs(views, _sparse(depths))
    h, w = depths[0].shape
    K = views[0].K
    for e, v, gt in zip(est, views, depths, strict=True):
        # World X of each pixel on the plane; flat beyond half a window (5 pixels) from the border.
        X = v.cam_to_world[0, 3] + (np.arange(w) + 0.5 - K[0, 2]) / K[0, 0] * gt
        flat = X > 5.0 * gt / K[0, 0]
        assert flat.mean() > 0.3
        assert (e.confidence[flat] > 0).mean() < 0.005, (e.confidence[flat] > 0).mean()
    textured = [(e, gt) for e, gt in zip(est, depths, strict=True)]
    abs_rel, covered = _abs_rel([e for e, _ in textured], [g for _, g in textured])
    assert abs_rel < 0.02 and 0.25 < covered < 0.6


def _scene_plane(depth0: float = 3.0, slope: float = 0.3) -> tuple[np.ndarray, float]:
    """``_plane_scene``'s plane Z = depth0 + slope X as ``normal . x = offset``."""
    n = np.array([-slope, 0.0, 1.0])
    return n / np.linalg.norm(n), depth0 / np.linalg.norm(n)


def test_plane_ncc_supports_the_true_plane_only():
    views, depths = _plane_scene(GRID)
    normal, offset = _scene_plane()
    depth, ncc, std = mvs.plane_ncc(views, 0, normal, offset)
    np.testing.assert_allclose(depth, depths[0], rtol=1e-5)
    assert np.median(ncc[4:-4, 4:-4]) > 0.9 and (std > 0.01).mean() > 0.9
    _, off_ncc, _ = mvs.plane_ncc(views, 0, normal, offset - 1.0)
    assert np.median(off_ncc[4:-4, 4:-4]) < 0.5


def test_fill_floor_fills_textured_pixels_of_the_plane_only():
    """Pixels without depth get the plane's depth where the plane explains the images (textured, and
    better than the plane 10 % nearer or farther); a plain half, a wrong plane and pixels that
    already have depth are left alone."""
    from image2sim.simulator.lift.capture import FLOOR_FILL_CONFIDENCE, fill_floor
    from image2sim.simulator.lift.types import DepthEstimate

    views, depths = _plane_scene(GRID, flat_right=True)
    normal, offset = _scene_plane()
    empty = [DepthEstimate(np.zeros_like(d), np.zeros_like(d)) for d in depths]
    kept = empty[1]
    kept.depth[:, :10], kept.confidence[:, :10] = 7.0, 0.9  # already has (wrong) depth: kept
    filled, n = fill_floor(views, empty, normal, offset)
    K = views[0].K
    w = depths[0].shape[1]
    shares = []
    for est, view, gt in zip(filled, views, depths, strict=True):
        X = view.cam_to_world[0, 3] + (np.arange(w) + 0.5 - K[0, 2]) / K[0, 0] * gt
        flat = X > 5.0 * gt / K[0, 0]
        new = est.confidence == np.float32(FLOOR_FILL_CONFIDENCE)
        assert not (new & flat).any()  # a plain patch proves nothing
        np.testing.assert_allclose(est.depth[new], gt[new], rtol=1e-5)
        shares.append(new[~flat].mean())
    # Baselines of 0.1-0.2 m at 3 m: the planes 10 % nearer and farther often match nearly as well.
    assert np.mean(shares) > 0.3 and min(shares) > 0
    assert np.all(filled[1].depth[:, :10] == 7.0) and np.all(filled[1].confidence[:, :10] == np.float32(0.9))
    assert n == sum(int((e.confidence == np.float32(FLOOR_FILL_CONFIDENCE)).sum()) for e in filled)
    _, wrong = fill_floor(views, empty, normal, offset - 0.4)
    assert wrong < 0.02 * n


# -------------------------------------------------------------------------------------- hard cases


def test_a_single_view_is_a_clear_error():
    views, depths = _plane_scene(GRID[:1])
    with pytest.raises(ValueError, match="at least 2"):
        run_mvs(views, _sparse(depths))


@pytest.mark.parametrize("field", ["K", "cam_to_world"])
def test_non_finite_cameras_are_rejected_naming_the_view(field):
    views, depths = _plane_scene(GRID[:3])
    bad = getattr(views[1], field).copy()
    bad[0, 2] = np.nan
    setattr(views[1], field, bad)
    with pytest.raises(ValueError, match=f"view 1: {field}"):
        run_mvs(views, _sparse(depths))


def test_non_finite_sparse_points_are_dropped_and_a_missing_range_is_an_error():
    views, depths = _plane_scene(GRID[:3])
    sparse = _sparse(depths)
    clean = run_mvs(views, sparse)
    spoiled = []
    for sp in sparse:
        uv, d = sp.uv.copy(), sp.depth.copy()
        uv[:5, 0] = np.inf
        d[5:10] = np.nan
        d[10:15] = -1.0
        spoiled.append(SparseDepth(np.concatenate([uv, [[1e6, 3.0]]]), np.concatenate([d, [2.0]])))
    est = run_mvs(views, spoiled)
    assert _abs_rel(est, depths)[0] < 0.03
    assert abs(_abs_rel(est, depths)[1] - _abs_rel(clean, depths)[1]) < 0.05
    with pytest.raises(ValueError, match="depth range"):
        run_mvs(views, None)
    # A given range needs no sparse depths.
    ranged = run_mvs(views, None, MVSConfig(near=1.5, far=6.0))
    assert _abs_rel(ranged, depths)[0] < 0.03


def test_a_view_without_overlap_gets_no_depth():
    views, depths = _plane_scene(GRID[:3])
    away = PinholeView(views[0].image.copy(), views[0].K, views[0].cam_to_world.copy())
    away.cam_to_world[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # turned around: looks along world -Z
    sparse = _sparse(depths) + [SparseDepth(np.zeros((0, 2)), np.zeros(0))]
    stats: list[dict] = []
    est = run_mvs([*views, away], sparse, stats=stats)
    assert stats[3]["sources"] == [] and 3 not in sum((s["sources"] for s in stats), [])
    assert not est[3].depth.any() and not est[3].confidence.any()
    assert _abs_rel(est[:3], depths)[0] < 0.03


def test_config_errors_name_the_option():
    with pytest.raises(ValueError, match="window must be odd"):
        MVSConfig(window=8)
    with pytest.raises(ValueError, match=r"unknown multi-view stereo option\(s\) \['planes'\]"):
        MVSConfig.from_kwargs(planes=3)
    with pytest.raises(ValueError, match="near and MVSConfig.far"):
        MVSConfig(near=1.0)


# ------------------------------------------------------------------------------- procedural houses


def _house_sequence(
    seed: int, n: int = 5, h: int = 120, w: int = 160, noise: float = 2.0, surface_detail: float = 0.0
):
    """A hand-held-like pinhole sequence in procedural house ``seed`` (default preset), exact poses.

    Five upright 90-degree views 0.15 m apart along a line across the heading, alternately 0.1 m
    above and below 1.4 m (a purely horizontal baseline cannot match horizontal stripes), from the
    first navigable spot (seeded) whose middle view sees at least 1 m deep. Returns the views (RGB
    with ``noise`` levels of Gaussian noise, like the ``middle`` tier), exact depths and the
    noise-free grey images. ``surface_detail`` is the generator's fine albedo grain (0: as synthesised
    by default).
    """
    import dataclasses

    from image2sim.dataengine.procedural.config import preset
    from image2sim.dataengine.procedural.render import render
    from image2sim.dataengine.procedural.scene import generate_scene
    from image2sim.simulator.conventions import camera_rotation_for_heading

    scene = generate_scene(dataclasses.replace(preset("default"), surface_detail=surface_detail), seed)
    grid, nav = scene.grid, scene.grid.navigable
    iy, ix = np.nonzero(nav)
    rng = np.random.default_rng(0)
    K = _K(h, w, 90.0)
    for _ in range(200):
        k = rng.integers(iy.size)
        centre = grid.cell_centers(iy[k : k + 1], ix[k : k + 1])[0]
        yaw = rng.uniform(-math.pi, math.pi)
        right = np.array([math.sin(yaw), -math.cos(yaw)])
        xy = centre + ((np.arange(n) - (n - 1) / 2) * 0.15)[:, None] * right
        cy, cx = grid.world_to_cell(xy)
        if (
            not np.all((cy >= 0) & (cy < nav.shape[0]) & (cx >= 0) & (cx < nav.shape[1]))
            or not nav[cy, cx].all()
        ):
            continue
        views, depths, clean = [], [], []
        for i, p in enumerate(xy):
            pose = np.eye(4)
            pose[:3, :3] = camera_rotation_for_heading(yaw)
            pose[:3, 3] = (p[0], p[1], 1.4 + (0.1 if i % 2 else -0.1))
            out = render(scene, _pinhole(K, h, w), pose)
            rgb = np.clip(np.rint(out["rgb"] + rng.normal(0.0, noise, out["rgb"].shape)), 0, 255).astype(
                np.uint8
            )
            views.append(PinholeView(rgb, K, pose))
            depths.append(out["depth"])
            clean.append(mvs.to_gray(out["rgb"]))
        mid = depths[n // 2]
        if np.median(mid[mid > 0]) >= 1.0:
            return views, depths, clean
    raise AssertionError(f"house {seed}: no sequence found")


def _pinhole(K: np.ndarray, h: int, w: int):
    from image2sim.simulator.geometry.cameras import PinholeCamera

    return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], h, w)


@pytest.mark.parametrize("seed", [3, pytest.param(8, marks=pytest.mark.slow)])
def test_procedural_house_depth_against_exact_depth(seed):
    """Measured (docs/lift.md, 160x120, middle-tier colour noise): house 3 AbsRel 0.086 on 22 % of
    pixels, house 8 0.058 on 52 %; textureless (plain wall) pixels are never confident. The issue's
    60 % coverage is out of reach here: plain walls have no texture to match (docs/lift.md)."""
    views, depths, clean = _house_sequence(seed)
    est = run_mvs(views, _sparse(depths))
    abs_rel, covered = _abs_rel(est, depths)
    assert abs_rel <= 0.10, abs_rel
    assert covered >= (0.18 if seed == 3 else 0.45), covered
    plain_confident, plain = 0, 0
    for e, grey in zip(est, clean, strict=True):
        g = grey[None]
        std = (mvs._box_mean(g * g, 9) - mvs._box_mean(g, 9) ** 2).clamp_min(0).sqrt()[0].numpy()
        flat = std < 0.003
        plain += int(flat.sum())
        plain_confident += int((e.confidence[flat] > 0).sum())
    assert plain > 500 and plain_confident <= 0.01 * plain


@pytest.mark.slow
def test_procedural_house_with_surface_grain_meets_the_issue_target():
    """With the generator's fine grain (``surface_detail: 0.3``, as the lift tests use) the issue's
    target holds: AbsRel <= 0.10 on confident pixels covering >= 60 % (measured 0.032 on 74 %)."""
    views, depths, _ = _house_sequence(3, surface_detail=0.3)
    abs_rel, covered = _abs_rel(run_mvs(views, _sparse(depths)), depths)
    assert abs_rel <= 0.10 and covered >= 0.60, (abs_rel, covered)
