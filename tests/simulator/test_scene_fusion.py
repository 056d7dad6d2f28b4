"""Scene construction: footprints, identity Gaussians, voxel fusion (fast vs reference), pruning."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from image2sim.simulator.gaussians import GaussianScene, GaussianSet, tiny
from image2sim.simulator.gaussians.config import FusionConfig
from image2sim.simulator.gaussians.encoder import identity_gaussians
from image2sim.simulator.gaussians.frames import pixel_footprint, prepare_frame, resize_rgbd
from image2sim.simulator.gaussians.fusion import assign_levels, cell_sizes, fuse, prune
from image2sim.simulator.gaussians.primitives import FrameInputs
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera


def _cfg(h=64, w=128, **fusion):
    cfg = tiny()
    return dataclasses.replace(
        cfg,
        encoder=dataclasses.replace(cfg.encoder, height=h, width=w),
        fusion=dataclasses.replace(cfg.fusion, **fusion),
    )


def _random_set(n: int, seed: int, levels_max: int = 0, extent: float = 0.2) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    return GaussianSet(
        means=torch.rand(n, 3, generator=g, dtype=torch.float64) * extent - extent / 3,
        scales=torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.01 + 0.001,
        quats=q,
        opacities=torch.rand(n, generator=g, dtype=torch.float64),
        colors=torch.rand(n, 3, generator=g, dtype=torch.float64),
        features=torch.randn(n, 5, generator=g, dtype=torch.float64),
        footprints=torch.rand(n, generator=g, dtype=torch.float64) * 0.05,
        weights=torch.randint(1, 4, (n,), generator=g).double(),
        levels=torch.randint(0, levels_max + 1, (n,), generator=g),
    )


def _reference_fuse(g: GaussianSet, cfg: FusionConfig) -> dict[str, np.ndarray]:
    """Slow, readable reference of :func:`fuse`: Python dicts over points."""
    sizes = cell_sizes(cfg)
    means = g.means.double().numpy()
    levels = [min(int(v), len(sizes) - 1) for v in g.levels]
    while cfg.policy == "footprint":
        before = list(levels)
        for L in sorted(set(levels))[1:]:
            finest: dict[tuple, int] = {}
            for i, lv in enumerate(levels):
                if lv < L:
                    key = tuple(np.floor(means[i] / sizes[L]).astype(np.int64))
                    finest[key] = min(finest.get(key, L), lv)
            for i, lv in enumerate(list(levels)):
                if lv == L:
                    key = tuple(np.floor(means[i] / sizes[L]).astype(np.int64))
                    if key in finest:
                        levels[i] = finest[key]
        if levels == before:
            break
    groups: dict[tuple, list[int]] = {}
    for i, lv in enumerate(levels):
        key = (lv, *np.floor(means[i] / sizes[lv]).astype(np.int64).tolist())
        groups.setdefault(key, []).append(i)
    out: dict[str, list] = {
        k: [] for k in ("means", "scales", "quats", "colors", "features", "weights", "levels")
    }
    t = {k: v.double().numpy() for k, v in g.tensors().items()}
    for key in sorted(groups):
        idx = groups[key]
        w = t["weights"][idx]

        def avg(a, idx=idx, w=w):
            return (a[idx] * w.reshape(-1, *([1] * (a.ndim - 1)))).sum(0) / w.sum()

        ref = t["quats"][idx[0]]
        q = np.array([t["quats"][i] * (-1 if t["quats"][i] @ ref < 0 else 1) for i in idx])
        qm = (q * w[:, None]).sum(0) / w.sum()
        scales = avg(t["scales"])
        if len(idx) > 1:
            scales = np.maximum(scales, cfg.cover_factor * sizes[key[0]])
        out["means"].append(avg(t["means"]))
        out["scales"].append(scales)
        out["quats"].append(qm / np.linalg.norm(qm))
        out["colors"].append(avg(t["colors"]))
        out["features"].append(avg(t["features"]))
        out["weights"].append(w.sum())
        out["levels"].append(key[0])
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("policy", ["fixed", "footprint"])
def test_fuse_matches_reference(policy):
    cfg = FusionConfig(policy=policy, voxel_size=0.03, base_voxel=0.01, levels=4)
    g = _random_set(400, seed=3, levels_max=3 if policy == "footprint" else 0)
    fast = fuse(g, cfg)
    ref = _reference_fuse(g, cfg)
    assert len(fast) == len(ref["means"]) < 400
    for key in ("means", "scales", "quats", "colors", "features", "weights"):
        np.testing.assert_allclose(getattr(fast, key).numpy(), ref[key], rtol=1e-10, atol=1e-12, err_msg=key)
    np.testing.assert_array_equal(fast.levels.numpy(), ref["levels"])


def test_fuse_is_idempotent_and_weights_add_up():
    cfg = FusionConfig(policy="footprint", base_voxel=0.01, levels=4)
    g = _random_set(500, seed=5, levels_max=3)
    once = fuse(g, cfg)
    twice = fuse(once, cfg)
    assert len(twice) == len(once)
    for key, value in once.tensors().items():
        torch.testing.assert_close(getattr(twice, key), value, rtol=1e-12, atol=1e-12, msg=key)
    assert math.isclose(float(once.weights.sum()), float(g.weights.sum()), rel_tol=1e-12)


def test_finer_level_absorbs_coarse_observations_of_the_same_cell():
    # A fine point and a coarse point inside one coarse cell: the coarse one moves down, no duplicate level.
    cfg = FusionConfig(policy="footprint", base_voxel=0.01, levels=3)
    g = _random_set(2, seed=0)
    g.means[:] = torch.tensor([[0.001, 0.001, 0.001], [0.002, 0.0015, 0.001]], dtype=torch.float64)
    g.levels[:] = torch.tensor([0, 2])
    out = fuse(g, cfg)
    assert len(out) == 1 and int(out.levels[0]) == 0
    # A coarse point whose cell has no fine member stays coarse.
    g.means[1] = torch.tensor([0.045, 0.045, 0.045], dtype=torch.float64)
    out = fuse(g, cfg)
    assert sorted(out.levels.tolist()) == [0, 2]


def test_quaternion_sign_alignment_keeps_opposite_signs_from_cancelling():
    cfg = FusionConfig(policy="fixed", voxel_size=1.0, cover_factor=0.0)
    g = _random_set(2, seed=1)
    g.means[:] = 0.5
    q = torch.tensor([0.6, 0.0, 0.8, 0.0], dtype=torch.float64)
    g.quats[0], g.quats[1] = q, -q
    out = fuse(g, cfg)
    torch.testing.assert_close(out.quats[0], q)


def test_cover_floor_only_for_merged_cells():
    cfg = FusionConfig(policy="fixed", voxel_size=0.1, cover_factor=0.5)
    g = _random_set(3, seed=2)
    g.means[:] = torch.tensor(
        [[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.55, 0.55, 0.55]], dtype=torch.float64
    )
    out = fuse(g, cfg)
    assert len(out) == 2
    assert torch.all(out.scales[0] >= 0.05)  # merged: at least half the voxel edge
    torch.testing.assert_close(out.scales[1], g.scales[2])  # single: untouched


def test_fuse_rejects_nonfinite_and_handles_empty():
    cfg = FusionConfig()
    assert len(fuse(GaussianSet.empty(), cfg)) == 0
    g = _random_set(4, seed=0)
    g.means[1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        fuse(g, cfg)
    g.opacities[:] = 0.5
    pruned = prune(g, cfg)
    assert len(pruned) == 3 and torch.isfinite(pruned.means).all()


def test_prune_drops_low_opacity():
    cfg = FusionConfig(min_opacity=0.5)
    g = _random_set(50, seed=4)
    out = prune(g, cfg)
    assert len(out) == int((g.opacities >= 0.5).sum()) and torch.all(out.opacities >= 0.5)


def test_assign_levels_follow_footprint():
    cfg = FusionConfig(policy="footprint", base_voxel=0.01, levels=5, footprint_factor=1.0)
    foot = torch.tensor([0.001, 0.01, 0.02, 0.039, 0.041, 0.08, 10.0])
    assert assign_levels(foot, cfg).tolist() == [0, 0, 1, 2, 2, 3, 4]
    assert assign_levels(foot, dataclasses.replace(cfg, policy="fixed")).tolist() == [0] * 7


def test_pixel_footprint_ground_truth():
    pano = EquirectCamera(64, 128)
    depth = torch.full((1, 64, 128), 2.0)
    torch.testing.assert_close(pixel_footprint(depth, pano), torch.full_like(depth, 2.0 * math.pi / 64))
    pin = PinholeCamera(100.0, 100.0, 32.0, 32.0, 64, 64)
    torch.testing.assert_close(pixel_footprint(torch.full((64, 64), 3.0), pin), torch.full((64, 64), 0.03))


def test_resize_keeps_nearest_depth_at_edges_and_ignores_invalid():
    rgb = torch.rand(1, 3, 4, 4)
    depth = torch.tensor(
        [[1.0, 1.0, 5.0, 0.0], [1.0, 1.0, 5.0, 5.0], [2.0, 2.1, 0.0, 0.0], [2.0, 2.1, 0.0, 3.0]]
    )
    _, d = resize_rgbd(rgb, depth[None, None], 2, 2, edge_tolerance=0.1)
    torch.testing.assert_close(d[0, 0], torch.tensor([[1.0, 5.0], [2.05, 0.0]]))


def _room_frame(h=32, w=64, centre=(0.0, 0.0, 1.5), half=(2.0, 1.5, 1.25)) -> FrameInputs:
    """Analytic panorama inside an axis-aligned box room (range along each ray to the nearest wall)."""
    cam = EquirectCamera(h, w)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    pose[:3, 3] = torch.tensor(centre, dtype=torch.float64)
    rays_w = torch.einsum("ij,jhw->ihw", pose[:3, :3].float(), cam.ray_map())
    c = torch.tensor(centre, dtype=torch.float32)
    lo = torch.tensor([-half[0], -half[1], 0.0]) - c
    hi = torch.tensor([half[0], half[1], 2 * half[2]]) - c
    t = []
    for i in range(3):
        r = rays_w[i]
        bound = torch.where(r > 0, hi[i], lo[i])
        t.append(
            torch.where(
                r.abs() > 1e-9, bound / r.where(r.abs() > 1e-9, torch.ones_like(r)), torch.full_like(r, 1e9)
            )
        )
    depth = torch.stack(t).amin(0)
    rgb = torch.stack((0.5 + 0.4 * rays_w[0], 0.5 + 0.4 * rays_w[1], 0.5 + 0.4 * rays_w[2])).clamp(0, 1)
    return FrameInputs(rgb[None], depth[None, None], cam, pose, "room")


def test_identity_gaussians_lie_on_the_depth_rays():
    frame = _room_frame()
    cfg = _cfg(32, 64)
    g = identity_gaussians(frame, cfg)
    assert len(g) == 32 * 64 and g.feature_dim == 0
    rays = frame.camera.ray_map().permute(1, 2, 0).reshape(-1, 3).double()
    expect = (rays * frame.depth.reshape(-1, 1).double()) @ frame.cam_to_world[:3, :3].T + frame.cam_to_world[
        :3, 3
    ]
    torch.testing.assert_close(g.means.double(), expect, atol=1e-5, rtol=0)
    sigma = (g.footprints * cfg.encoder.scale_init).clamp(0.002, 0.5)
    # Default shape "disc": the footprint std in the surface plane, a fraction of it along the normal.
    torch.testing.assert_close(g.scales[:, :2], torch.stack((sigma, sigma), -1))
    torch.testing.assert_close(g.scales[:, 2], (sigma * cfg.encoder.disc_thickness).clamp_min(0.002))
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(len(g)))
    assert torch.all(g.opacities == 1)
    sphere = identity_gaussians(
        frame, dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, identity_shape="sphere"))
    )
    torch.testing.assert_close(sphere.scales, sigma[:, None].expand(-1, 3))
    assert torch.all(sphere.quats[:, 0] == 1)
    # Room walls: every point within the box.
    assert float(g.means[:, 2].min()) > -1e-4 and float(g.means[:, 2].max()) < 2.5 + 1e-4


def test_identity_drops_invalid_and_out_of_range_pixels():
    frame = _room_frame()
    frame.depth[0, 0, :4] = 0.0
    frame.depth[0, 0, 4, :3] = float("nan")
    frame.depth[0, 0, 5, :2] = 50.0  # beyond max_range
    g = identity_gaussians(frame, _cfg(32, 64))
    assert len(g) == 32 * 64 - 4 * 64 - 3 - 2
    assert torch.isfinite(g.means).all()


def test_same_frame_twice_does_not_double_the_count():
    frame = _room_frame(64, 128)
    cfg = _cfg()
    scene = GaussianScene(cfg.fusion)
    n1 = scene.integrate(identity_gaussians(frame, cfg))
    n2 = scene.integrate(identity_gaussians(frame, cfg))
    assert n1 == n2 < 64 * 128
    torch.testing.assert_close(scene.gaussians.weights.sum(), torch.tensor(2.0 * 64 * 128))


def test_nearby_frames_share_gaussians():
    cfg = _cfg()
    a, b = _room_frame(64, 128), _room_frame(64, 128, centre=(0.1, 0.05, 1.5))
    s1, s2 = GaussianScene(cfg.fusion), GaussianScene(cfg.fusion)
    count_a = s1.integrate(identity_gaussians(a, cfg))
    count_b = s2.integrate(identity_gaussians(b, cfg))
    s1.integrate(identity_gaussians(b, cfg))
    assert len(s1) < 0.75 * (count_a + count_b)


@pytest.fixture(scope="module")
def procedural_frames():
    from image2sim.dataengine.procedural import capture_frames, generate_scene, preset

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=16))
    frames, _ = capture_frames(generate_scene(sc, seed=1))
    return [prepare_frame(f, 64, 128) for f in frames]


def test_gaussian_count_saturates_with_frames(procedural_frames):
    cfg = _cfg()
    scene = GaussianScene(cfg.fusion)
    counts, pixels = [], 0
    for f in procedural_frames:
        g = identity_gaussians(f, cfg)
        pixels += len(g)
        counts.append(scene.integrate(g))
    inc = np.diff(counts)
    q = len(inc) // 4
    print(f"footprint policy counts vs frames: {counts} (pixels {pixels})")
    assert counts[-1] < 0.3 * pixels
    assert inc[-q:].mean() < 0.7 * inc[:q].mean()  # growth flattens
    # The fixed 2 cm voxel is finer than these 64x128 pixels: it keeps far more Gaussians.
    fixed = GaussianScene(dataclasses.replace(cfg.fusion, policy="fixed", voxel_size=0.02))
    for f in procedural_frames:
        fixed.integrate(identity_gaussians(f, cfg))
    assert len(fixed) > 2 * counts[-1]
