"""Camera models: round trips (hypothesis, float64), Jacobians vs finite differences, ray maps, dicts."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera, camera_from_dict

F64 = torch.float64
HALF_PI = 0.5 * math.pi


def circular_diff(a: torch.Tensor, b: torch.Tensor, period: float) -> torch.Tensor:
    """|a - b| on a circle of the given period (u is only defined modulo W)."""
    d = torch.remainder(a - b, period)
    return torch.minimum(d, period - d)


# --- strategies -----------------------------------------------------------------------------

sizes = st.tuples(st.integers(1, 4096), st.integers(1, 8192))
# Latitudes: anywhere, or within 1e-3 rad of either pole (but not on it: longitude is undefined there).
near_pole = st.floats(1e-7, 1e-3).flatmap(lambda d: st.sampled_from([HALF_PI - d, -HALF_PI + d]))
latitudes = st.one_of(st.floats(-HALF_PI + 1e-3, HALF_PI - 1e-3), near_pole)
# Longitudes: anywhere, or within 1e-3 rad of the +-180 degree seam on either side.
near_seam = st.floats(0.0, 1e-3).flatmap(lambda e: st.sampled_from([math.pi - e, -math.pi + e]))
longitudes = st.one_of(st.floats(-math.pi, math.pi), near_seam)


@st.composite
def pinholes(draw) -> PinholeCamera:
    h, w = draw(st.integers(1, 2000)), draw(st.integers(1, 2000))
    fx, fy = draw(st.floats(10.0, 5000.0)), draw(st.floats(10.0, 5000.0))
    cx, cy = draw(st.floats(-0.5 * w, 1.5 * w)), draw(st.floats(-0.5 * h, 1.5 * h))
    return PinholeCamera(fx, fy, cx, cy, h, w)


# --- equirectangular ------------------------------------------------------------------------


def test_equirect_ground_truth_directions():
    cam = EquirectCamera(512, 1024)
    t = lambda *x: torch.tensor(x, dtype=F64)  # noqa: E731
    # Centre of the image is the camera's forward axis; a quarter turn right is +x; top is up (-y).
    cases = [
        ((512.0, 256.0), (0, 0, 1)),
        ((768.0, 256.0), (1, 0, 0)),
        ((256.0, 256.0), (-1, 0, 0)),
        ((0.0, 256.0), (0, 0, -1)),
        ((512.0, 0.0), (0, -1, 0)),
        ((512.0, 512.0), (0, 1, 0)),
    ]
    for (u, v), expected in cases:
        ray = cam.pixel_to_ray(t(u), t(v))
        assert torch.allclose(ray, t(*expected), atol=1e-12), (u, v, ray)


@given(sizes, longitudes, latitudes)
def test_equirect_pixel_ray_pixel_roundtrip(size, lon, lat):
    cam = EquirectCamera(*size)
    u, v = cam.lonlat_to_pixel(torch.tensor(lon, dtype=F64), torch.tensor(lat, dtype=F64))
    ray = cam.pixel_to_ray(u, v)
    assert ray.dtype == F64
    assert abs(float(torch.linalg.vector_norm(ray)) - 1.0) < 1e-14
    uv, rng, valid = cam.project(ray)
    assert bool(valid) and abs(float(rng) - 1.0) < 1e-14
    assert 0.0 <= float(uv[0]) < cam.width
    # Longitude is ill-conditioned by 1/cos(lat) near the poles.
    tol_u = 1e-13 * cam.width / math.cos(lat) + 1e-12 * cam.width
    assert float(circular_diff(uv[0], u, cam.width)) < tol_u
    assert abs(float(uv[1] - v)) < 1e-12 * cam.height + 1e-12


@given(sizes, longitudes, latitudes, st.floats(1e-3, 1e3))
def test_equirect_depth_points_depth_roundtrip(size, lon, lat, depth):
    cam = EquirectCamera(*size)
    u, v = cam.lonlat_to_pixel(torch.tensor(lon, dtype=F64), torch.tensor(lat, dtype=F64))
    point = depth * cam.pixel_to_ray(u, v)
    uv, rng, valid = cam.project(point)
    assert bool(valid)
    assert abs(float(rng) - depth) <= 1e-14 * depth
    assert float(circular_diff(uv[0], u, cam.width)) < 1e-13 * cam.width / math.cos(lat) + 1e-12 * cam.width
    assert abs(float(uv[1] - v)) < 1e-12 * cam.height + 1e-12


@settings(max_examples=40)
@given(st.integers(1, 24), st.integers(1, 48), st.integers(0, 2**31 - 1))
def test_equirect_unproject_project_full_map(h, w, seed):
    cam = EquirectCamera(h, w)
    gen = torch.Generator().manual_seed(seed)
    depth = torch.rand(2, h, w, generator=gen, dtype=F64) * 10 + 0.01
    points = cam.unproject(depth)
    assert points.shape == (2, h, w, 3) and points.dtype == F64
    uv, rng, valid = cam.project(points)
    uu = (torch.arange(w, dtype=F64) + 0.5).expand(h, w)
    vv = (torch.arange(h, dtype=F64) + 0.5)[:, None].expand(h, w)
    assert valid.all()
    assert torch.allclose(rng, depth, rtol=1e-13, atol=0)
    assert circular_diff(uv[..., 0], uu, w).max() < 1e-9
    assert (uv[..., 1] - vv).abs().max() < 1e-9


def test_equirect_unproject_rows_next_to_the_poles():
    # 1800 rows: the top and bottom pixel centres are pi/3600 < 1e-3 rad from the poles.
    cam = EquirectCamera(1800, 6)
    _, lat = cam.pixel_to_lonlat(torch.tensor(0.5, dtype=F64), torch.tensor([0.5, 1799.5], dtype=F64))
    assert float(HALF_PI - lat[0]) < 1e-3 and float(lat[1] + HALF_PI) < 1e-3
    depth = torch.linspace(0.5, 5.0, 1800 * 6, dtype=F64).reshape(1800, 6)
    uv, rng, valid = cam.project(cam.unproject(depth))
    assert valid.all() and torch.allclose(rng, depth, rtol=1e-13, atol=0)
    uu = (torch.arange(6, dtype=F64) + 0.5).expand(1800, 6)
    assert circular_diff(uv[..., 0], uu, 6).max() < 1e-9
    assert (uv[..., 1] - (torch.arange(1800, dtype=F64) + 0.5)[:, None]).abs().max() < 1e-9


def test_equirect_project_u_in_range_and_origin_invalid():
    cam = EquirectCamera(8, 16)
    # Just left of the seam (x -> -0, z < 0): u must not come out as exactly W.
    pts = torch.tensor([[-1e-30, 0.0, -1.0], [1e-30, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=torch.float32)
    uv, rng, valid = cam.project(pts)
    assert (uv[:, 0] >= 0).all() and (uv[:, 0] < 16).all()
    assert valid.tolist() == [True, True, False]


def _fd_jacobian(project_u_v, points: torch.Tensor, eps: float, period_u: float | None) -> torch.Tensor:
    """Central finite differences of (u, v) w.r.t. (x, y, z) -> (..., 2, 3)."""
    cols = []
    for k in range(3):
        step = torch.zeros(3, dtype=points.dtype)
        step[k] = eps
        plus, minus = project_u_v(points + step), project_u_v(points - step)
        diff = plus - minus
        if period_u is not None:  # unwrap u across the seam
            du = torch.remainder(diff[..., 0] + 0.5 * period_u, period_u) - 0.5 * period_u
            diff = torch.stack((du, diff[..., 1]), dim=-1)
        cols.append(diff / (2 * eps))
    return torch.stack(cols, dim=-1)


@settings(max_examples=60)
@given(sizes, longitudes, st.floats(-HALF_PI + 1e-3, HALF_PI - 1e-3), st.floats(0.1, 100.0))
def test_equirect_jacobian_matches_finite_differences(size, lon, lat, depth):
    cam = EquirectCamera(*size)
    u, v = cam.lonlat_to_pixel(torch.tensor(lon, dtype=F64), torch.tensor(lat, dtype=F64))
    p = depth * cam.pixel_to_ray(u, v)
    J = cam.pixel_jacobian(p)
    fd = _fd_jacobian(lambda q: cam.project(q)[0], p, 1e-6 * depth * math.cos(lat), float(cam.width))
    scale = J.abs().max()
    assert torch.allclose(J, fd, atol=1e-5 * float(scale), rtol=0), (J, fd)


def test_equirect_jacobian_is_finite_at_the_pole():
    cam = EquirectCamera(64, 128)
    J = cam.pixel_jacobian(torch.tensor([[0.0, -2.0, 0.0], [0.0, 2.0, 0.0]], dtype=F64))
    assert torch.isfinite(J).all()


# --- pinhole --------------------------------------------------------------------------------


@given(pinholes(), st.floats(-1.0, 2.0), st.floats(-1.0, 2.0), st.floats(1e-3, 1e3))
def test_pinhole_roundtrips(cam, fu, fv, depth):
    u = torch.tensor(fu * cam.width, dtype=F64)
    v = torch.tensor(fv * cam.height, dtype=F64)
    ray = cam.pixel_to_ray(u, v)
    assert abs(float(torch.linalg.vector_norm(ray)) - 1.0) < 1e-14
    uv, z, valid = cam.project(ray)
    assert bool(valid)
    assert torch.allclose(uv, torch.stack((u, v)), rtol=1e-12, atol=1e-9)
    # depth -> point -> depth: depth is z (not range) for a pinhole.
    point = ray * (depth / ray[2])
    uv, z, valid = cam.project(point)
    assert bool(valid) and abs(float(z) - depth) <= 1e-13 * depth
    assert torch.allclose(uv, torch.stack((u, v)), rtol=1e-12, atol=1e-9)


@settings(max_examples=40)
@given(pinholes().filter(lambda c: c.height * c.width <= 40_000), st.integers(0, 2**31 - 1))
def test_pinhole_unproject_project_full_map(cam, seed):
    gen = torch.Generator().manual_seed(seed)
    depth = torch.rand(cam.height, cam.width, generator=gen, dtype=F64) * 10 + 0.01
    uv, z, valid = cam.project(cam.unproject(depth))
    assert valid.all() and torch.allclose(z, depth, rtol=1e-14, atol=0)
    uu = torch.arange(cam.width, dtype=F64) + 0.5
    vv = torch.arange(cam.height, dtype=F64) + 0.5
    assert torch.allclose(uv[..., 0], uu.expand(cam.height, -1), rtol=1e-12, atol=1e-9)
    assert torch.allclose(uv[..., 1], vv[:, None].expand(-1, cam.width), rtol=1e-12, atol=1e-9)


@settings(max_examples=60)
@given(pinholes(), st.floats(-3, 3), st.floats(-3, 3), st.floats(0.1, 100.0))
def test_pinhole_jacobian_matches_finite_differences(cam, x, y, z):
    p = torch.tensor([x * z, y * z, z], dtype=F64)
    J = cam.pixel_jacobian(p)
    fd = _fd_jacobian(lambda q: cam.project(q)[0], p, 1e-6 * z, None)
    assert torch.allclose(J, fd, atol=1e-6 * float(J.abs().max()), rtol=0)


def test_pinhole_behind_camera_is_invalid():
    cam = PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100)
    _, z, valid = cam.project(torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.1, 0.0, 1.0]]))
    assert valid.tolist() == [False, False, True]


def test_pinhole_principal_point_is_forward():
    cam = PinholeCamera(300.0, 200.0, 160.5, 120.5, 240, 320)
    ray = cam.pixel_to_ray(torch.tensor(160.5, dtype=F64), torch.tensor(120.5, dtype=F64))
    assert torch.allclose(ray, torch.tensor([0.0, 0.0, 1.0], dtype=F64))


# --- ray maps, dtypes -----------------------------------------------------------------------


@pytest.mark.parametrize("cam", [EquirectCamera(33, 64), PinholeCamera(40.0, 30.0, 20.0, 17.0, 33, 41)])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_ray_maps_unit_length_and_match_pixel_to_ray(cam, dtype):
    rays = cam.ray_map(dtype)
    assert rays.shape == (3, cam.height, cam.width) and rays.dtype == dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    assert (torch.linalg.vector_norm(rays, dim=0) - 1).abs().max() < tol
    j, i = 7, 5
    ref = cam.pixel_to_ray(torch.tensor(j + 0.5, dtype=F64), torch.tensor(i + 0.5, dtype=F64))
    assert torch.allclose(rays[:, i, j].double(), ref, atol=10 * tol)
    # Back-projecting unit depth gives the ray map for range (equirect) and scaled rays for z (pinhole).
    pts = cam.unproject(torch.ones(cam.height, cam.width, dtype=dtype)).permute(2, 0, 1)
    if isinstance(cam, EquirectCamera):
        assert torch.allclose(pts, rays, atol=tol)
    else:
        assert torch.allclose(pts / pts[2:3], rays / rays[2:3], atol=10 * tol)


def test_float32_stays_float32():
    cam = EquirectCamera(8, 16)
    pts = torch.randn(5, 3)
    uv, rng, _ = cam.project(pts)
    assert uv.dtype == rng.dtype == cam.pixel_jacobian(pts).dtype == torch.float32


# --- dict round trip and errors -------------------------------------------------------------


@pytest.mark.parametrize(
    "cam", [EquirectCamera(512, 1024), PinholeCamera(320.5, 300.25, 160.0, 120.5, 240, 320)]
)
def test_camera_dict_roundtrip(cam):
    data = cam.to_dict()
    assert camera_from_dict(data) == cam
    import json

    assert camera_from_dict(json.loads(json.dumps(data))) == cam


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"height": 2, "width": 4}, "missing field 'model'"),
        ({"model": "fisheye", "height": 2, "width": 4}, "unknown camera model 'fisheye'"),
        ({"model": "equirect", "height": 2}, "missing field 'width'"),
        ({"model": "equirect", "height": 2, "width": 4, "fov": 3}, "unknown field(s) ['fov']"),
        ({"model": "equirect", "height": 2.5, "width": 4}, "'height' must be int"),
        ({"model": "equirect", "height": "2", "width": 4}, "'height' must be int"),
        ({"model": "equirect", "height": True, "width": 4}, "'height' must be int"),
        ({"model": "equirect", "height": 0, "width": 4}, "positive height/width"),
        (
            {"model": "pinhole", "fx": 1.0, "fy": 1.0, "cx": 0.0, "height": 2, "width": 2},
            "missing field 'cy'",
        ),
        (
            {"model": "pinhole", "fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "height": 2, "width": 2},
            "focal lengths must be positive",
        ),
        (
            {
                "model": "pinhole",
                "fx": float("nan"),
                "fy": 1.0,
                "cx": 0.0,
                "cy": 0.0,
                "height": 2,
                "width": 2,
            },
            "fx must be finite",
        ),
        ([1, 2], "must be a dict"),
    ],
)
def test_camera_from_dict_errors(data, message):
    with pytest.raises(ValueError) as err:
        camera_from_dict(data)
    assert message in str(err.value)


@pytest.mark.parametrize("cam", [EquirectCamera(8, 16), PinholeCamera(10.0, 10.0, 8.0, 4.0, 8, 16)])
def test_unproject_rejects_a_wrong_size_map(cam):
    with pytest.raises(ValueError, match=r"does not end in the camera's \(H, W\) = \(8, 16\)"):
        cam.unproject(torch.ones(8, 15))
    with pytest.raises(ValueError, match="does not end"):
        cam.unproject(torch.ones(16))
    assert cam.unproject(torch.ones(2, 8, 16)).shape == (2, 8, 16, 3)
