"""Block frustum culling (splatting/culling.py): conservative against the splat's own cull, so a culled
render is the same image bit for bit, and it does cull."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import PinholeCamera
from image2sim.simulator.splatting import splat
from image2sim.simulator.splatting.backends import cpu_kernel
from image2sim.simulator.splatting.culling import FrustumBlocks
from image2sim.simulator.splatting.project import project_gaussians

needs_kernel = pytest.mark.skipif(not cpu_kernel.available(), reason="compiled CPU kernel unavailable")


def _scene(n: int, seed: int, spread: float = 6.0, big: float = 0.0):
    """Gaussians all around the origin (in front of, beside and behind any camera there), mostly
    small, a few large (``big``: their largest scale), random orientations."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2 * spread
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.7 - 3.5)
    if big:
        scales[: max(1, n // 50)] = big
    quats = torch.randn(n, 4, generator=g)
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g)
    return means, scales, quats, opac, colors


def _pose(rng: np.random.Generator, spread: float = 2.0) -> torch.Tensor:
    """A camera-to-world with a random position and a random rotation."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = rng.uniform(-spread, spread, 3)
    return torch.tensor(pose, dtype=torch.float32)


CAMERAS = [
    PinholeCamera.from_fov(90.0, 90.0, 48, 48),
    PinholeCamera.from_fov(60.0, 40.0, 30, 52),
    PinholeCamera(fx=40.0, fy=55.0, cx=5.0, cy=33.0, height=36, width=44),  # off-centre principal point
]


@pytest.mark.parametrize("block_size", [1, 7, 64])
@pytest.mark.parametrize("cam", CAMERAS, ids=["square90", "wide", "offcentre"])
def test_every_gaussian_the_splat_keeps_is_in_a_kept_block(cam, block_size):
    """Against the reference projection's cull (near plane, footprint box off the image): no
    Gaussian it keeps may be in a culled block; large Gaussians beside the frustum included."""
    means, scales, quats, opac, _ = _scene(3000, seed=block_size, big=0.8)
    blocks = FrustumBlocks(means, scales, block_size)
    rng = np.random.default_rng(block_size)
    culled_any = 0
    for _ in range(12):
        pose = _pose(rng)
        valid = project_gaussians(means, scales, quats, opac, cam, pose).valid
        kept = blocks.keep(cam, pose)
        if kept is None:
            continue
        block_of, keep = kept
        in_kept_block = keep[block_of]
        assert not (valid & ~in_kept_block).any(), "a block holding a visible Gaussian was culled"
        culled_any += int((~in_kept_block).sum())
    assert culled_any > 0  # and it does cull


def _room(n: int, seed: int):
    """Small Gaussians on the six faces of a 10 x 3 x 10 m box around the origin (a room's surfaces)."""
    g = torch.Generator().manual_seed(seed)
    half = torch.tensor([5.0, 1.5, 5.0])
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * half
    axis = torch.randint(0, 3, (n,), generator=g)
    side = torch.randint(0, 2, (n,), generator=g).float() * 2 - 1
    means[torch.arange(n), axis] = side * half[axis]
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 3.5)
    return means, scales, torch.randn(n, 4, generator=g), torch.full((n,), 0.8)


def test_culling_drops_most_of_a_room_around_the_camera():
    """A 90-degree view from inside a room sees about a fifth of its surfaces; blocks of 64 keep
    at most 25 % of the Gaussians more than the splat itself keeps (their spheres reach past the
    frustum; measured 14-21 %), blocks of one Gaussian (the per-Gaussian bound) at most 5 %."""
    means, scales, quats, opac = _room(40000, seed=3)
    blocks, single = FrustumBlocks(means, scales), FrustumBlocks(means, scales, 1)
    cam = PinholeCamera.from_fov(90.0, 90.0, 64, 64)
    for seed in range(4):
        pose = _pose(np.random.default_rng(seed), spread=0.5)
        visible = float(project_gaussians(means, scales, quats, opac, cam, pose).valid.float().mean())
        kept = [
            float(keep[block_of].float().mean())
            for block_of, keep in (b.keep(cam, pose) for b in (blocks, single))
        ]
        assert visible < 0.3 and kept[0] < visible + 0.25 and kept[1] < visible + 0.05, (visible, kept)


@needs_kernel
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_culled_render_is_the_same_image_bit_for_bit(seed):
    means, scales, quats, opac, colors = _scene(4000, seed=seed, big=0.5)
    blocks = FrustumBlocks(means, scales)
    rng = np.random.default_rng(seed)
    for cam in CAMERAS:
        for _ in range(4):
            pose = _pose(rng)
            args = (means, scales, quats, opac, colors, None, cam, pose)
            with torch.no_grad():
                plain = splat(*args, backend="cpu")
                culled = splat(*args, backend="cpu", cull=blocks)
            for name in ("rgb", "depth", "alpha"):
                assert torch.equal(getattr(plain, name), getattr(culled, name)), name


@needs_kernel
def test_hard_cases_empty_behind_nonfinite_and_inside_a_block():
    cam = PinholeCamera.from_fov(90.0, 90.0, 24, 24)
    # Empty scene.
    empty = FrustumBlocks(torch.zeros(0, 3), torch.zeros(0, 3))
    assert empty.keep(cam, torch.eye(4)) is None
    z = torch.zeros(0, 3)
    with torch.no_grad():
        out = splat(z, z, torch.zeros(0, 4), torch.zeros(0), z, None, cam, torch.eye(4), cull=empty)
    assert float(out.alpha.abs().max()) == 0.0
    # Everything behind the camera (+z is forward): every block culled but the non-finite one, and
    # the image is the background, as without culling.
    means, scales, quats, opac, colors = _scene(500, seed=5, spread=1.0)
    means[:, 2] -= 3.0
    blocks = FrustumBlocks(means, scales, 16)
    block_of, keep = blocks.keep(cam, torch.eye(4))
    assert not keep[:-1].any() and keep[-1]
    # Non-finite means and scales: in the always-kept block, never dropped by the cull.
    means[0] = float("nan")
    scales[1, 2] = float("inf")
    blocks = FrustumBlocks(means, scales, 16)
    block_of, keep = blocks.keep(cam, torch.eye(4))
    assert keep[block_of[0]] and keep[block_of[1]]
    args = (means, scales, quats, opac, colors, None, cam, torch.eye(4))
    with torch.no_grad():
        a = splat(*args, backend="cpu", nonfinite="cull")
        b = splat(*args, backend="cpu", nonfinite="cull", cull=blocks)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)
    # The camera inside a block's sphere: that block is kept.
    means, scales, *_ = _scene(64, seed=6, spread=0.3)
    one = FrustumBlocks(means, scales, 64)
    assert one.keep(cam, torch.eye(4)) is None


def test_bad_inputs_are_refused():
    means, scales, quats, opac, colors = _scene(10, seed=7)
    with pytest.raises(ValueError, match="must be \\(N, 3\\)"):
        FrustumBlocks(means[:, :2], scales)
    with pytest.raises(ValueError, match="block_size"):
        FrustumBlocks(means, scales, 0)
    cam = PinholeCamera.from_fov(90.0, 90.0, 16, 16)
    with pytest.raises(ValueError, match="cull indexes 9 Gaussians but 10"):
        splat(
            means,
            scales,
            quats,
            opac,
            colors,
            None,
            cam,
            torch.eye(4),
            cull=FrustumBlocks(means[:9], scales[:9]),
        )


@needs_kernel
def test_the_kernel_refuses_block_ids_outside_the_keep_table():
    means, scales, quats, opac, colors = _scene(10, seed=8)
    cam = PinholeCamera.from_fov(90.0, 90.0, 16, 16)
    bg = torch.zeros(4)
    block_of = torch.full((10,), 5, dtype=torch.int64)
    with pytest.raises(RuntimeError, match="outside block_keep"):
        cpu_kernel.render(
            means,
            scales,
            quats,
            opac,
            colors,
            means.new_zeros(10, 0),
            cam,
            torch.eye(4),
            bg,
            blocks=(block_of, torch.ones(3, dtype=torch.bool)),
        )


@needs_kernel
def test_the_render_function_culls_pinhole_views_only_and_renders_the_same():
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.sim import GaussianRenderFn

    means, scales, quats, opac = _room(3000, seed=9)
    g = {"means": means, "scales": scales, "quats": quats, "opacities": opac, "colors": torch.rand(3000, 3)}
    fn = GaussianRenderFn(g, backend="cpu")
    fn(EquirectCamera(16, 32), np.eye(4))
    assert fn._blocks is None  # a panorama sees everything: no blocks built
    cam = PinholeCamera.from_fov(90.0, 90.0, 32, 32)
    pose = _pose(np.random.default_rng(9), spread=0.5).numpy()
    obs = fn(cam, pose)
    assert fn._blocks is not None and fn._blocks.keep(cam, pose) is not None  # it did cull
    plain = GaussianRenderFn(g, backend="cpu")
    plain._cull = lambda camera: None
    ref = plain(cam, pose)
    assert np.array_equal(obs["rgb"], ref["rgb"]) and np.array_equal(obs["depth"], ref["depth"])
