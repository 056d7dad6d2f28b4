"""Normals: the paper's Sobel estimator (slow reference parity, ramps, seam) and true point normals
on analytic planes and spheres for pinhole and equirectangular cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.geometry.normals import (
    SurfaceNormalEstimator,
    hole_normals,
    pad_equirect,
    point_normals,
    sobel_kernels,
    sobel_normals,
)

F64 = torch.float64


# --- slow references (explicit loops, written from the paper's description) ----------------------


def ref_source_index(i: int, j: int, H: int, W: int, circular: bool) -> tuple[int, int]:
    """Which pixel of the image a (possibly out-of-range) index (i, j) reads."""
    if not circular:
        return min(max(i, 0), H - 1), min(max(j, 0), W - 1)
    if i < 0 or i >= H:
        if W % 2 == 0:  # continue over the pole: reflect the row and turn half way round
            i = -1 - i if i < 0 else 2 * H - 1 - i
            j = j + W // 2
        else:
            i = min(max(i, 0), H - 1)
    return i, j % W


def ref_sobel_normals(depth: np.ndarray, circular: bool) -> np.ndarray:
    """The paper's estimator, one pixel at a time: avg3 -> 5x5 Sobel / 48 -> (-gx, -gy, 0.5) / norm."""
    H, W = depth.shape
    smooth = np.zeros_like(depth)
    for i in range(H):
        for j in range(W):
            total = 0.0
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    si, sj = ref_source_index(i + di, j + dj, H, W, circular)
                    total += depth[si, sj]
            smooth[i, j] = total / 9.0
    binomial = [1, 4, 6, 4, 1]
    derivative = [-1, -2, 0, 2, 1]
    out = np.zeros((3, H, W))
    for i in range(H):
        for j in range(W):
            gx = gy = 0.0
            for a in range(5):
                for b in range(5):
                    si, sj = ref_source_index(i + a - 2, j + b - 2, H, W, circular)
                    gx += binomial[a] * derivative[b] * smooth[si, sj]
                    gy += derivative[a] * binomial[b] * smooth[si, sj]
            n = np.array([-gx / 48.0, -gy / 48.0, 0.5])
            out[:, i, j] = n / np.linalg.norm(n)
    return out


# --- sobel_normals -----------------------------------------------------------------------------


def test_sobel_kernels_are_the_5x5_sobel_over_48():
    su, sv = sobel_kernels(F64)
    assert su[2].tolist() == pytest.approx([-6 / 48, -12 / 48, 0.0, 12 / 48, 6 / 48])
    assert torch.equal(sv, su.t())
    assert float(su.abs().sum()) == pytest.approx(2.0)  # 48 / 48 on each side


@settings(max_examples=12)
@given(st.integers(5, 9), st.integers(5, 10), st.booleans(), st.integers(0, 2**31 - 1))
def test_sobel_normals_matches_slow_reference(h, w, circular, seed):
    depth = np.random.default_rng(seed).uniform(0.2, 5.0, size=(h, w))
    ours = sobel_normals(torch.from_numpy(depth)[None, None], circular=circular)[0].numpy()
    assert np.allclose(ours, ref_sobel_normals(depth, circular), atol=1e-12)


def test_sobel_normals_on_a_linear_ramp():
    H, W, a, b = 20, 30, 0.03, -0.05
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    depth = (2.0 + a * u + b * v)[None, None]
    n = sobel_normals(depth)
    # Average pooling keeps a ramp; the 1/48 Sobel gives 128/48 times the slope per pixel.
    expected = torch.tensor([-a * 128 / 48, -b * 128 / 48, 0.5], dtype=F64)
    expected = expected / expected.norm()
    interior = n[0, :, 3:-3, 3:-3]
    assert torch.allclose(interior, expected[:, None, None].expand_as(interior), atol=1e-13)
    assert torch.allclose(n.norm(dim=1), torch.ones(1, H, W, dtype=F64))


@pytest.mark.parametrize("circular", [False, True])
def test_sobel_normals_constant_depth_points_along_z(circular):
    n = sobel_normals(torch.full((2, 1, 8, 16), 3.0), circular=circular)
    assert n.dtype == torch.float32 and n.shape == (2, 3, 8, 16)
    # Exact up to float32 rounding of the 3x3 mean.
    assert torch.allclose(n, torch.tensor([0.0, 0.0, 1.0])[None, :, None, None].expand_as(n), atol=1e-6)


def test_sobel_normals_circular_is_roll_equivariant():
    gen = torch.Generator().manual_seed(3)
    depth = torch.rand(1, 1, 16, 32, generator=gen, dtype=F64) + 1
    base = sobel_normals(depth, circular=True)
    for k in (1, 5, 31):
        rolled = sobel_normals(torch.roll(depth, k, dims=-1), circular=True)
        assert torch.allclose(rolled, torch.roll(base, k, dims=-1), atol=1e-14)
    # Without the flag the seam columns see replicated edges instead, so they differ.
    assert not torch.allclose(sobel_normals(depth)[..., 0], base[..., 0])


def test_surface_normal_estimator_module_is_the_function():
    depth = torch.rand(2, 1, 8, 16) + 0.5
    module = SurfaceNormalEstimator(circular=True)
    assert list(module.parameters()) == [] and "circular=True" in repr(module)
    assert torch.equal(module(depth), sobel_normals(depth, circular=True))


def test_pad_equirect_matches_index_reference():
    for H, W in ((4, 6), (5, 7)):
        x = torch.arange(H * W, dtype=F64).reshape(1, 1, H, W)
        padded = pad_equirect(x, 2)
        assert padded.shape == (1, 1, H + 4, W + 4)
        for i in range(-2, H + 2):
            for j in range(-2, W + 2):
                si, sj = ref_source_index(i, j, H, W, True)
                assert padded[0, 0, i + 2, j + 2] == x[0, 0, si, sj], (H, W, i, j)
    with pytest.raises(ValueError, match="exceeds"):
        pad_equirect(torch.zeros(1, 1, 2, 8), 3)


def test_sobel_normals_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        sobel_normals(torch.ones(8, 8))
    with pytest.raises(ValueError, match="floating"):
        sobel_normals(torch.ones(1, 1, 8, 8, dtype=torch.int32))


# --- point_normals: analytic scenes ------------------------------------------------------------


def plane_depth(camera, normal: torch.Tensor, offset: float, max_depth: float = 40.0) -> torch.Tensor:
    """Depth of the plane {X : normal . X = offset} seen by ``camera`` (0 where it is not hit)."""
    rays = camera.ray_map(F64)  # (3, H, W) unit
    t = offset / torch.einsum("c,chw->hw", normal, rays)  # range along the unit ray
    if isinstance(camera, PinholeCamera):
        t = t * rays[2]  # range -> z-depth
    t = torch.where((t > 0) & (t < max_depth), t, torch.zeros_like(t))
    return t[None, None]


def sphere_depth(camera: EquirectCamera, centre: torch.Tensor, radius: float) -> torch.Tensor:
    """Range from an origin inside the sphere |X - centre| = radius, along every ray."""
    rays = camera.ray_map(F64)
    b = torch.einsum("c,chw->hw", centre, rays)
    t = b + torch.sqrt(b * b - centre.dot(centre) + radius * radius)
    return t[None, None]


def angle_error(n: torch.Tensor, expected: torch.Tensor, mask: torch.Tensor) -> float:
    cos = (n * expected).sum(dim=1)[mask[:, 0]].clamp(-1, 1)
    return float(torch.acos(cos).max())


def ref_valid_mask(depth: np.ndarray, circular: bool) -> np.ndarray:
    """A pixel is valid iff every depth in its 7x7 (3x3 then 5x5, padded) receptive field is > 0."""
    H, W = depth.shape
    good = depth > 0
    first = np.zeros_like(good)
    for i in range(H):
        for j in range(W):
            first[i, j] = all(
                good[ref_source_index(i + a, j + b, H, W, circular)] for a in (-1, 0, 1) for b in (-1, 0, 1)
            )
    out = np.zeros_like(good)
    for i in range(H):
        for j in range(W):
            out[i, j] = all(
                first[ref_source_index(i + a, j + b, H, W, circular)]
                for a in range(-2, 3)
                for b in range(-2, 3)
            )
    return out


PINHOLE = PinholeCamera(60.0, 55.0, 32.5, 23.0, 48, 64)
EQUIRECT = EquirectCamera(48, 96)


def test_point_normals_frontal_plane_pinhole():
    depth = torch.full((1, 1, 48, 64), 2.5, dtype=F64)
    n = point_normals(depth, PINHOLE)
    expected = torch.tensor([0.0, 0.0, -1.0], dtype=F64)[None, :, None, None].expand_as(n)
    assert torch.allclose(n, expected, atol=1e-12)  # borders included: replicated points stay coplanar


@pytest.mark.parametrize("camera", [PINHOLE, EQUIRECT], ids=["pinhole", "equirect"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_normals_tilted_plane_is_exact(camera, seed):
    gen = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=F64), dim=0)
    if isinstance(camera, PinholeCamera):
        normal[2] = abs(normal[2]) + 0.5  # make sure the plane faces the pinhole
        normal = normal / normal.norm()
    offset = 1.5
    depth = plane_depth(camera, normal, offset)
    n = point_normals(depth, camera)
    valid = n.norm(dim=1, keepdim=True) > 0
    assert valid.sum() > 0.1 * camera.height * camera.width
    # The camera (origin) has normal . X = 0 < offset, so the camera-facing normal is -normal.
    expected = (-normal)[None, :, None, None].expand_as(n)
    assert torch.allclose(n[valid.expand_as(n)], expected[valid.expand_as(n)], atol=1e-9)
    # Zeros exactly where the receptive field touches a pixel that sees no plane.
    circular = isinstance(camera, EquirectCamera)
    assert np.array_equal(valid[0, 0].numpy(), ref_valid_mask(depth[0, 0].numpy(), circular))


def test_point_normals_floor_in_a_panorama_points_up():
    # Floor 1.2 m below an equirect camera (OpenCV: +y is down): the normal facing the camera is -y.
    depth = plane_depth(EQUIRECT, torch.tensor([0.0, 1.0, 0.0], dtype=F64), 1.2)
    n = point_normals(depth, EQUIRECT)
    valid = n.norm(dim=1) > 0
    assert valid[0, -1].all()  # the bottom row (next to the nadir) is valid thanks to pole padding
    assert torch.allclose(n[:, 1][valid], torch.full((int(valid.sum()),), -1.0, dtype=F64), atol=1e-9)
    assert not valid[0, : EQUIRECT.height // 2].any()  # the upper hemisphere sees no floor


def test_point_normals_inside_a_centred_sphere_is_minus_ray():
    camera = EquirectCamera(64, 128)
    depth = sphere_depth(camera, torch.zeros(3, dtype=F64), 3.0)
    n = point_normals(depth, camera)
    rays = camera.ray_map(F64)[None]
    mask = torch.ones(1, 1, 64, 128, dtype=torch.bool)
    # Every pixel including the pole rows and the seam; the residual is the O(h^2) smoothing bias.
    assert angle_error(n, -rays, mask) < 2e-3


def test_point_normals_off_centre_sphere_converges():
    body, pole = [], []
    centre = torch.tensor([0.4, -0.3, 0.5], dtype=F64)
    for h in (32, 64, 128):
        camera = EquirectCamera(h, 2 * h)
        depth = sphere_depth(camera, centre, 2.0)
        n = point_normals(depth, camera)
        points = camera.unproject(depth[:, 0]).permute(0, 3, 1, 2)
        expected = (centre[None, :, None, None] - points) / 2.0
        rows = torch.zeros(1, 1, h, 2 * h, dtype=torch.bool)
        rows[..., 4:-4, :] = True
        body.append(angle_error(n, expected, rows))
        pole.append(angle_error(n, expected, ~rows))
    # Away from the poles the estimate is second-order accurate: halving the pixel size cuts the
    # error by about 4. Next to the poles dP/du itself vanishes like the pixel size, so the
    # smoothing bias is first order there: about 2x per halving.
    assert body[1] < body[0] / 3.5 and body[2] < body[1] / 3.5, body
    assert pole[1] < pole[0] / 1.8 and pole[2] < pole[1] / 1.8, pole
    assert body[-1] < 1e-3 and pole[-1] < 6e-3


def test_point_normals_invalid_depth_gives_zero_not_nan():
    depth = torch.full((1, 1, 48, 96), 2.0)
    depth[0, 0, 10, 20] = 0.0
    depth[0, 0, 30, 50] = float("nan")
    depth[0, 0, 40, 0] = float("inf")
    n = point_normals(depth, EQUIRECT)
    assert n.dtype == torch.float32 and torch.isfinite(n).all()
    valid = n.norm(dim=1)[0] > 0
    assert np.array_equal(valid.numpy(), ref_valid_mask(np.nan_to_num(depth[0, 0].numpy(), posinf=0.0), True))
    assert (
        not valid[40, 93:].any() and not valid[40, :4].any()
    )  # the hole at column 0 spreads across the seam
    assert torch.allclose(n[0, :, valid], -EQUIRECT.ray_map()[:, valid], atol=3e-3)  # sphere of radius 2


def test_point_normals_all_invalid_and_errors():
    n = point_normals(torch.zeros(2, 1, 48, 64), PINHOLE)
    assert torch.equal(n, torch.zeros(2, 3, 48, 64))
    with pytest.raises(ValueError, match="camera is 48x64"):
        point_normals(torch.ones(1, 1, 40, 64), PINHOLE)
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        point_normals(torch.ones(48, 64), PINHOLE)


def test_point_normals_float32_plane():
    normal = torch.tensor([0.3, 0.8, -0.2], dtype=F64)
    normal = normal / normal.norm()
    depth = plane_depth(EQUIRECT, normal, 1.0, max_depth=10.0).float()
    n = point_normals(depth, EQUIRECT)
    valid = n.norm(dim=1, keepdim=True) > 0
    err = (n - (-normal.float())[None, :, None, None]).abs()[valid.expand_as(n)].max()
    assert float(err) < 1e-4
    assert not math.isnan(float(n.sum()))


@pytest.mark.realdata
def test_point_normals_find_the_floor_in_a_real_panorama(hm3d_scene_dir):
    """HM3D panoramas are upright, 1.5 m above the floor: near the nadir the normals point up (-y)."""
    import cv2

    raw = cv2.imread(str(hm3d_scene_dir / "00000_depth.png"), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16
    depth = torch.from_numpy(raw.astype(np.float32) / 1000.0)[None, None]
    camera = EquirectCamera(*raw.shape)
    n = point_normals(depth, camera)
    _, lat = camera.pixel_to_lonlat(torch.tensor(0.5), torch.arange(camera.height) + 0.5)
    rows = lat < math.radians(-70)
    near_nadir = n[0, :, rows]  # (3, rows, W)
    valid = near_nadir.norm(dim=0) > 0
    assert valid.float().mean() > 0.9
    up = near_nadir[1][valid] < -0.95
    assert up.float().mean() > 0.95, float(up.float().mean())  # measured 0.987 on frame 00000


# --- hole_normals: completing point_normals next to missing depth ----------------------------------


def ref_hole_normals(
    depth: np.ndarray, camera, base: np.ndarray, radius=2, min_valid=8, rel=0.1, planar=0.05
):
    """One pixel at a time: the PCA normal of the valid, depth-consistent window points of every
    valid pixel whose ``base`` normal is 0 (the same padding as the images)."""
    H, W = depth.shape
    circular = isinstance(camera, EquirectCamera)
    good = np.isfinite(depth) & (depth > 0)
    clean = np.where(good, depth, 0.0)
    pts = camera.unproject(torch.from_numpy(clean)[None]).numpy()[0]  # (H, W, 3)
    out = base.copy()
    for i in range(H):
        for j in range(W):
            if not good[i, j] or np.abs(base[:, i, j]).sum() > 0:
                continue
            window = [
                ref_source_index(i + a, j + b, H, W, circular)
                for a in range(-radius, radius + 1)
                for b in range(-radius, radius + 1)
                if circular or (0 <= i + a < H and 0 <= j + b < W)  # nothing beyond a pinhole image
            ]
            near = [
                pts[si, sj]
                for si, sj in window
                if clean[si, sj] > 0 and abs(clean[si, sj] - clean[i, j]) <= rel * clean[i, j]
            ]
            out[:, i, j] = 0.0
            if len(near) < min_valid:
                continue
            q = np.array(near) - np.mean(near, axis=0)
            evals, evecs = np.linalg.eigh(q.T @ q)
            if evals[0] > planar * evals[1]:
                continue
            n = evecs[:, 0]
            out[:, i, j] = -n if n @ pts[i, j] > 0 else n
    return out


def holed(depth: torch.Tensor, fraction: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.where(torch.rand(depth.shape, generator=gen, dtype=depth.dtype) < fraction, 0.0, depth)


@pytest.mark.parametrize("camera", [PINHOLE, EQUIRECT], ids=["pinhole", "equirect"])
@pytest.mark.parametrize("seed", [0, 1])
def test_hole_normals_on_a_holed_plane_are_exact_and_keep_the_sobel_ones(camera, seed):
    gen = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=F64), dim=0)
    if isinstance(camera, PinholeCamera):
        normal[2] = abs(normal[2]) + 0.5
        normal = normal / normal.norm()
    plane = plane_depth(camera, normal, 1.5)
    depth = holed(plane, 0.05, seed)
    base = point_normals(depth, camera)
    n = hole_normals(depth, camera, base)
    seen = (depth > 0)[:, 0]
    had = base.norm(dim=1) > 0
    got = n.norm(dim=1) > 0
    assert torch.equal(n[:, :, had[0]], base[:, :, had[0]])  # the Sobel normals stay as they were
    # 5 % holes leave the Sobel estimator few pixels; the fitted planes cover nearly all the rest
    # where the plane is not seen at a grazing angle (there, neighbours differ by > 10 % in depth).
    facing = seen & (plane[:, 0] < 3.0)
    assert had[seen].float().mean() < 0.5 and got[facing].float().mean() > 0.9
    expected = (-normal)[None, :, None, None].expand_as(n)
    assert torch.allclose(n.permute(0, 2, 3, 1)[got], expected.permute(0, 2, 3, 1)[got], atol=1e-9)
    assert not got[~seen].any()  # no normal where there is no depth


@pytest.mark.parametrize("camera", [PINHOLE, EQUIRECT], ids=["pinhole", "equirect"])
def test_hole_normals_match_the_slow_reference(camera):
    # A floor and a wall a depth edge apart, holes, and one noisy patch: every branch of the rule.
    H, W = camera.height, camera.width
    floor = plane_depth(camera, torch.tensor([0.0, 1.0, 0.0], dtype=F64), 1.2)[0, 0]
    wall = plane_depth(camera, torch.tensor([0.3, 0.0, 1.0], dtype=F64), 2.0)[0, 0]
    depth = torch.where((floor > 0) & ((wall == 0) | (floor < wall)), floor, wall)
    gen = torch.Generator().manual_seed(3)
    depth[H // 4 : H // 4 + 6, W // 3 : W // 3 + 8] *= 1 + 0.3 * torch.rand(6, 8, generator=gen, dtype=F64)
    depth = holed(depth[None, None], 0.08, 4)
    base = point_normals(depth, camera)
    fast = hole_normals(depth, camera, base)
    slow = ref_hole_normals(depth[0, 0].numpy(), camera, base[0].numpy())
    assert np.allclose(fast[0].numpy(), slow, atol=1e-9)
    completed = (fast.norm(dim=1) > 0) & (base.norm(dim=1) == 0)
    refused = (fast.norm(dim=1) == 0) & (depth[:, 0] > 0)
    assert completed.sum() > 50 and refused.sum() > 5  # both outcomes are exercised


def test_hole_normals_refuse_a_rough_window_and_survive_bad_values():
    gen = torch.Generator().manual_seed(0)
    # +-5 % noise at 2 m: every neighbour is depth-consistent, none lies on a plane (a 0.2 m thick
    # slab across a 0.17 m window)
    rough = 2.0 * (1.0 + 0.1 * (torch.rand(1, 1, 48, 64, generator=gen, dtype=F64) - 0.5))
    rough = holed(rough, 0.2, 1)
    assert not point_normals(rough, PINHOLE).any()
    completed = int((hole_normals(rough, PINHOLE).norm(dim=1) > 0).sum())
    assert completed <= 0.002 * int((rough > 0).sum())  # a chance plane of few border points at most
    depth = plane_depth(PINHOLE, torch.tensor([0.0, 0.6, 0.8], dtype=F64), 1.5).float()
    depth[0, 0, 10, 20] = float("nan")
    depth[0, 0, 30, 40] = float("inf")
    depth[0, 0, 5, 5] = -1.0
    n = hole_normals(depth, PINHOLE)
    assert n.dtype == torch.float32 and torch.isfinite(n).all()
    around = n.norm(dim=1)[0, 9:12, 19:22] > 0
    assert around.sum() == 8 and not around[1, 1]  # around the NaN (from the plane there), not on it
    assert torch.equal(hole_normals(torch.zeros(1, 1, 48, 64), PINHOLE), torch.zeros(1, 3, 48, 64))
