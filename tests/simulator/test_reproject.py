"""Panorama resampling against a first-principles numpy reference, plus exact-crop, seam and
direction ground truths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.geometry.reproject import (
    CUBEMAP_FACES,
    cubemap_to_equirect,
    equirect_crop,
    equirect_to_cubemap,
    perspective_from_equirect,
    sample_equirect,
)

F64 = torch.float64


# --- first-principles reference (numpy) ----------------------------------------------------------


def ref_rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """View -> panorama frame: tilt the optical axis up by pitch (about x), then turn right by yaw (y)."""
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    # OpenCV axes: y points down, so "up" is -y; Rx(p) takes (0, 0, 1) to (0, -sin p, cos p).
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    # Ry(y) takes (0, 0, 1) to (sin y, 0, cos y): longitude y, to the right.
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    return ry @ rx


def ref_pinhole_rays(hfov, vfov, h, w) -> np.ndarray:
    fx = (w / 2) / math.tan(math.radians(hfov) / 2)
    fy = (h / 2) / math.tan(math.radians(vfov) / 2)
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack(((jj - w / 2) / fx, (ii - h / 2) / fy, np.ones_like(jj)), axis=-1)


def ref_crop_rays(hfov, vfov, h, w) -> np.ndarray:
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    lon = math.radians(hfov) * (jj / w - 0.5)
    lat = math.radians(vfov) * (0.5 - ii / h)
    return np.stack((np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)), axis=-1)


def ref_lookup(pano: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Bilinear lookup of (C, H, W) at camera-frame directions (h, w, 3) -> (C, h, w)."""
    C, H, W = pano.shape
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    lon = np.arctan2(x, z)
    lat = np.arctan2(-y, np.hypot(x, z))
    u = (lon + math.pi) / (2 * math.pi) * W
    v = (math.pi / 2 - lat) / math.pi * H
    # Pixel centres sit at +0.5: the integer grid of samples is at u - 0.5.
    gx, gy = u - 0.5, v - 0.5
    x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
    tx, ty = gx - x0, gy - y0

    def read(i, j):
        # Beyond a pole the sphere continues on the meridian half a turn away.
        over = (i < 0) | (i >= H)
        i = np.where(i < 0, -1 - i, np.where(i >= H, 2 * H - 1 - i, i))
        j = np.where(over, j + W // 2, j) % W
        return pano[:, i, j]

    return (
        (1 - ty) * (1 - tx) * read(y0, x0)
        + (1 - ty) * tx * read(y0, x0 + 1)
        + ty * (1 - tx) * read(y0 + 1, x0)
        + ty * tx * read(y0 + 1, x0 + 1)
    )


def random_pano(h=64, w=128, c=3, seed=0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(1, c, h, w, generator=gen, dtype=F64)


# --- parity with the reference -------------------------------------------------------------------

VIEWS = [
    (0.0, 0.0, 90.0, 90.0, 48, 48),
    (180.0, 0.0, 90.0, 90.0, 40, 40),  # centred on the seam
    (-170.0, 10.0, 120.0, 60.0, 30, 50),
    (37.0, 80.0, 100.0, 100.0, 40, 40),  # the north pole is inside the view
    (-95.0, -89.0, 60.0, 90.0, 36, 24),  # looking almost straight down
    (12.5, -20.0, 170.0, 150.0, 33, 65),
]


@pytest.mark.parametrize(("yaw", "pitch", "hfov", "vfov", "h", "w"), VIEWS)
def test_perspective_matches_first_principles(yaw, pitch, hfov, vfov, h, w):
    pano = random_pano()
    ours = perspective_from_equirect(pano, yaw, pitch, hfov, vfov, h, w)
    rays = ref_pinhole_rays(hfov, vfov, h, w) @ ref_rotation(yaw, pitch).T
    assert ours.shape == (1, 3, h, w) and ours.dtype == F64
    assert np.allclose(ours[0].numpy(), ref_lookup(pano[0].numpy(), rays), atol=1e-10)


@pytest.mark.parametrize(
    ("yaw", "pitch", "hfov", "vfov", "h", "w"),
    [
        (0.0, 0.0, 180.0, 118.0, 34, 51),
        (170.0, 30.0, 200.0, 100.0, 20, 40),
        (-45.0, 0.0, 360.0, 180.0, 32, 64),
    ],
)
def test_equirect_crop_matches_first_principles(yaw, pitch, hfov, vfov, h, w):
    pano = random_pano(seed=1)
    ours = equirect_crop(pano, yaw, pitch, hfov, vfov, h, w)
    rays = ref_crop_rays(hfov, vfov, h, w) @ ref_rotation(yaw, pitch).T
    assert np.allclose(ours[0].numpy(), ref_lookup(pano[0].numpy(), rays), atol=1e-10)


HALF_PI = 0.5 * math.pi
near_pole = st.floats(0.0, 0.05).flatmap(lambda d: st.sampled_from([HALF_PI - d, -HALF_PI + d]))
near_seam = st.floats(0.0, 0.05).flatmap(lambda e: st.sampled_from([math.pi - e, -math.pi + e]))
lons = st.one_of(st.floats(-math.pi, math.pi), near_seam)
lats = st.one_of(st.floats(-HALF_PI, HALF_PI), near_pole)


@settings(max_examples=60)
@given(
    st.lists(st.tuples(lons, lats), min_size=1, max_size=20), st.sampled_from([(8, 16), (9, 14), (16, 32)])
)
def test_sample_equirect_matches_reference_anywhere_on_the_sphere(directions, size):
    """Random directions, many within a few pixels of the seam or the poles (the hard cases)."""
    pano = random_pano(*size, seed=len(directions))
    lon = torch.tensor([d[0] for d in directions], dtype=F64)[None, None]
    lat = torch.tensor([d[1] for d in directions], dtype=F64)[None, None]
    ours = sample_equirect(pano, lon, lat)[0, :, 0].numpy()
    lo, la = lon[0].numpy(), lat[0].numpy()  # (1, n)
    rays = np.stack((np.cos(la) * np.sin(lo), -np.sin(la), np.cos(la) * np.cos(lo)), axis=-1)
    assert np.allclose(ours, ref_lookup(pano[0].numpy(), rays)[:, 0], atol=1e-9)


def test_sample_equirect_at_pixel_centres_is_identity():
    pano = random_pano(16, 32)
    cam = EquirectCamera(16, 32)
    uu = torch.arange(32, dtype=F64) + 0.5
    vv = torch.arange(16, dtype=F64) + 0.5
    lon, lat = cam.pixel_to_lonlat(uu[None, :].expand(16, 32), vv[:, None].expand(16, 32))
    out = sample_equirect(pano, lon[None], lat[None])
    assert torch.allclose(out, pano, atol=1e-12)


# --- ground truths -------------------------------------------------------------------------------


def test_zero_pitch_crop_is_an_exact_slice_and_wraps_the_seam():
    pano = random_pano(64, 128)
    # 180 x 90 degrees at 64 x 32: output pixel centres land exactly on panorama pixel centres.
    crop = equirect_crop(pano, 0.0, 0.0, 180.0, 90.0, 32, 64)
    assert torch.allclose(crop, pano[..., 16:48, 32:96], atol=1e-12)
    # Centred on the seam: the right half of the panorama followed by its left half.
    seam = equirect_crop(pano, 180.0, 0.0, 180.0, 90.0, 32, 64)
    expected = torch.cat((pano[..., 16:48, 96:], pano[..., 16:48, :32]), dim=-1)
    assert torch.allclose(seam, expected, atol=1e-12)


def test_view_across_the_seam_equals_view_of_rolled_panorama():
    pano = random_pano(64, 128)
    rolled = torch.roll(pano, 64, dims=-1)  # lon = pi now sits at the centre column
    a = perspective_from_equirect(pano, 180.0, 5.0, 90.0, 90.0, 40, 40)
    b = perspective_from_equirect(rolled, 0.0, 5.0, 90.0, 90.0, 40, 40)
    assert torch.allclose(a, b, atol=1e-9)


def ray_pano(h=256, w=512) -> torch.Tensor:
    """A panorama whose three channels are the unit direction of each pixel (a smooth signal)."""
    return EquirectCamera(h, w).ray_map(F64)[None]


@pytest.mark.parametrize(
    ("yaw", "pitch", "direction"),
    [
        (0.0, 0.0, (0, 0, 1)),
        (90.0, 0.0, (1, 0, 0)),
        (-90.0, 0.0, (-1, 0, 0)),
        (180.0, 0.0, (0, 0, -1)),
        (0.0, 60.0, (0, -math.sin(math.pi / 3), 0.5)),
        (45.0, -30.0, (0.6123724, 0.5, 0.6123724)),
    ],
)
def test_view_centre_looks_at_yaw_pitch(yaw, pitch, direction):
    # yaw positive to the right, pitch positive up (OpenCV: up is -y).
    view = perspective_from_equirect(ray_pano(), yaw, pitch, 60.0, 60.0, 31, 31)
    centre = view[0, :, 15, 15]
    assert torch.allclose(centre, torch.tensor(direction, dtype=F64), atol=2e-4)
    # The view is upright: its right-hand edge is to the right of its centre, not rolled.
    left, right = view[0, :, 15, 0], view[0, :, 15, 30]
    up_axis = torch.tensor([0.0, -1.0, 0.0], dtype=F64)
    assert abs(float(torch.dot(right - left, up_axis))) < 1e-3


def test_paper_views_shapes_and_content():
    pano = ray_pano()
    pinhole = perspective_from_equirect(pano, 30.0, 0.0, 90.0, 90.0, 336, 336)
    assert pinhole.shape == (1, 3, 336, 336)
    ultra = perspective_from_equirect(pano, 30.0, 0.0, 180.0, 118.0, 336, 512)
    assert ultra.shape == (1, 3, 336, 512)
    # >= 180 degrees is an equirectangular crop: its corners are +-90 degrees of longitude away.
    assert torch.equal(ultra, equirect_crop(pano, 30.0, 0.0, 180.0, 118.0, 336, 512))
    lon = torch.atan2(ultra[0, 0], ultra[0, 2])
    assert math.degrees(float(lon[168, 0])) == pytest.approx(30.0 - 90.0 + 90.0 / 512, abs=0.05)
    # The pinhole's corner pixels look 45 degrees (minus half a pixel) off-axis horizontally.
    lon_p = torch.atan2(pinhole[0, 0], pinhole[0, 2])
    assert math.degrees(float(lon_p[168, 335] - lon_p[168, 0])) == pytest.approx(90.0, abs=0.5)


def test_cubemap_faces_order_and_content():
    pano = ray_pano(128, 256)
    cube = equirect_to_cubemap(pano, 24)
    assert cube.shape == (1, 6, 3, 24, 24)
    expected = {
        "front": (0, 0, 1),
        "right": (1, 0, 0),
        "back": (0, 0, -1),
        "left": (-1, 0, 0),
        "up": (0, -1, 0),
        "down": (0, 1, 0),
    }
    for k, (name, yaw, pitch) in enumerate(CUBEMAP_FACES):
        face = cube[0, k]
        centre = face[:, 11:13, 11:13].mean(dim=(1, 2))
        assert torch.allclose(centre / centre.norm(), torch.tensor(expected[name], dtype=F64), atol=2e-3), (
            name
        )
        assert torch.allclose(face, perspective_from_equirect(pano, yaw, pitch, 90, 90, 24, 24)[0])
    # "up" has the front direction (+z) along its bottom edge, "down" along its top edge.
    assert cube[0, 4, 2, -1].mean() > 0.5 and cube[0, 5, 2, 0].mean() > 0.5

    # Adjacent faces meet edge to edge: the boundary pixels on both sides are one pixel apart.
    def gap(a: torch.Tensor, b: torch.Tensor) -> float:
        a, b = a / a.norm(dim=0), b / b.norm(dim=0)
        return math.degrees(float(torch.acos((a * b).sum(0).clamp(-1, 1)).max()))

    pixel = 90.0 / 24
    front, right, back, left, up, down = cube[0]
    assert gap(front[:, :, -1], right[:, :, 0]) < 1.2 * pixel
    assert gap(right[:, :, -1], back[:, :, 0]) < 1.2 * pixel
    assert gap(left[:, :, -1], front[:, :, 0]) < 1.2 * pixel
    assert gap(up[:, -1, :], front[:, 0, :]) < 1.2 * pixel
    assert gap(front[:, -1, :], down[:, 0, :]) < 1.2 * pixel


def test_cubemap_round_trip_converges():
    pano = ray_pano(128, 256)
    errors = []
    for face in (32, 64, 128):
        back = cubemap_to_equirect(equirect_to_cubemap(pano, face), 128, 256)
        assert back.shape == pano.shape
        errors.append(float((back - pano).abs().max()))
    # Edge clamping holds the outer half pixel of each face: first-order in the face pixel size.
    assert errors[0] < 0.02 and errors[1] < errors[0] / 1.8 and errors[2] < errors[1] / 1.8, errors


def test_cubemap_to_equirect_reads_the_right_face():
    # Constant faces 0..5: every panorama pixel shows the index of the face its direction hits.
    cube = torch.arange(6, dtype=F64).reshape(1, 6, 1, 1, 1).expand(1, 6, 1, 8, 8)
    pano = cubemap_to_equirect(cube, 64, 128, mode="nearest")[0, 0]
    cam = EquirectCamera(64, 128)
    rays = cam.ray_map(F64)
    axes = torch.tensor([[0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, -1, 0], [0, 1, 0]], dtype=F64)
    expected = torch.einsum("kc,chw->khw", axes, rays).argmax(dim=0)
    assert torch.equal(pano.long(), expected)
    with pytest.raises(ValueError, match=r"\(B, 6, C, F, F\)"):
        cubemap_to_equirect(torch.zeros(1, 5, 3, 8, 8), 16, 32)


def test_batched_yaw_pitch_tensors():
    pano = torch.cat((random_pano(seed=2), random_pano(seed=3)))
    yaw = torch.tensor([10.0, -120.0])
    pitch = torch.tensor([0.0, 45.0])
    out = perspective_from_equirect(pano, yaw, pitch, 80.0, 70.0, 20, 24)
    for b in range(2):
        single = perspective_from_equirect(
            pano[b : b + 1], float(yaw[b]), float(pitch[b]), 80.0, 70.0, 20, 24
        )
        assert torch.allclose(out[b : b + 1], single, atol=1e-12)


def test_float32_gradient_and_nearest():
    pano = random_pano().float().requires_grad_(True)
    out = perspective_from_equirect(pano, 170.0, 0.0, 90.0, 90.0, 16, 16)
    assert out.dtype == torch.float32
    ref = perspective_from_equirect(pano.detach().double(), 170.0, 0.0, 90.0, 90.0, 16, 16)
    assert torch.allclose(out.double(), ref, atol=1e-5)
    out.sum().backward()
    assert pano.grad is not None and float(pano.grad.sum()) == pytest.approx(16 * 16 * 3, rel=1e-4)
    near = perspective_from_equirect(pano.detach(), 0.0, 0.0, 90.0, 90.0, 16, 16, mode="nearest")
    assert set(near.flatten().tolist()) <= set(pano.detach().flatten().tolist())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"hfov": 0.0}, "FOV"),
        ({"vfov": 181.0}, "vfov <= 180"),
        ({"hfov": 361.0}, "hfov <= 360"),
        ({"yaw": float("nan")}, "yaw must be finite"),
        ({"yaw": torch.zeros(3)}, r"yaw must be a float or a \(1,\) tensor"),
        ({"height": 0}, "output size must be positive"),
    ],
)
def test_errors(kwargs, message):
    args = {"yaw": 0.0, "pitch": 0.0, "hfov": 90.0, "vfov": 90.0, "height": 8, "width": 8} | kwargs
    with pytest.raises(ValueError, match=message):
        perspective_from_equirect(random_pano(), **args)


def test_bad_panoramas():
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        perspective_from_equirect(torch.zeros(3, 8, 16), 0.0, 0.0, 90.0, 90.0, 4, 4)
    with pytest.raises(ValueError, match="floating point"):
        perspective_from_equirect(torch.zeros(1, 3, 8, 16, dtype=torch.uint8), 0.0, 0.0, 90.0, 90.0, 4, 4)
