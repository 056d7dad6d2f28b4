"""Resampling equirectangular panoramas: perspective views, equirectangular crops, cubemaps.

All views are defined by a direction field in the panorama's camera frame (OpenCV axes, see
:mod:`image2sim.simulator.conventions`), converted to (lon, lat) and looked up with
:func:`sample_equirect`, a ``grid_sample`` wrapper that pads the panorama spherically first
(columns wrap across the +-180 degree seam; rows continue over the poles for even widths), so
bilinear interpolation is continuous everywhere on the sphere.

View orientation: ``yaw`` is the longitude of the view centre (degrees, positive to the right, 0 =
panorama centre column), ``pitch`` its latitude (degrees, positive up). The view has no roll: its
x axis (right) stays horizontal. With forward f = (cos p sin y, -sin p, cos p cos y) the view
axes are right = (cos y, 0, -sin y) and down = f x right.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.geometry.normals import pad_equirect

__all__ = [
    "CUBEMAP_FACES",
    "view_rotation",
    "sample_equirect",
    "perspective_directions",
    "equirect_crop_directions",
    "perspective_from_equirect",
    "equirect_crop",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
]

Angle = float | torch.Tensor

CUBEMAP_FACES: tuple[tuple[str, float, float], ...] = (
    ("front", 0.0, 0.0),
    ("right", 90.0, 0.0),
    ("back", 180.0, 0.0),
    ("left", -90.0, 0.0),
    ("up", 0.0, 90.0),
    ("down", 0.0, -90.0),
)
"""Face order of :func:`equirect_to_cubemap` as (name, yaw, pitch) in degrees. Each face is the
90x90 degree perspective view :func:`perspective_from_equirect` gives for that yaw/pitch; the
side faces are upright, "up" has the front direction at its bottom edge and "down" at its top."""


def _angles(value: Angle, batch: int, dtype: torch.dtype, device, name: str) -> torch.Tensor:
    """A float or a (B,) / scalar tensor of degrees -> (B,) radians."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    if t.ndim == 0:
        t = t.expand(batch)
    elif t.shape != (batch,):
        raise ValueError(f"{name} must be a float or a ({batch},) tensor, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {t.tolist()}")
    return torch.deg2rad(t)


def view_rotation(yaw: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """Rotations (..., 3, 3) taking view-frame directions to the panorama frame; angles in radians.

    Columns are the view's right, down and forward axes expressed in the panorama camera frame.
    """
    cy, sy, cp, sp = torch.cos(yaw), torch.sin(yaw), torch.cos(pitch), torch.sin(pitch)
    zero = torch.zeros_like(yaw)
    right = torch.stack((cy, zero, -sy), dim=-1)
    down = torch.stack((sp * sy, cp, sp * cy), dim=-1)
    forward = torch.stack((cp * sy, -sp, cp * cy), dim=-1)
    return torch.stack((right, down, forward), dim=-1)


def sample_equirect(
    pano: torch.Tensor, lon: torch.Tensor, lat: torch.Tensor, mode: str = "bilinear"
) -> torch.Tensor:
    """Sample panoramas (B, C, H, W) at directions (lon, lat) in radians, each (B, h, w) -> (B, C, h, w).

    Pixel (u, v) of the panorama is longitude 2*pi*u/W - pi and latitude pi/2 - pi*v/H with pixel
    centres at integer + 0.5. The panorama is padded by one pixel spherically
    (:func:`~image2sim.simulator.geometry.normals.pad_equirect`) and sampled by ``grid_sample``
    with ``align_corners=False``, so interpolation wraps across the seam and over the poles.
    ``mode`` is passed to ``grid_sample`` ("bilinear" or "nearest").
    """
    if pano.ndim != 4:
        raise ValueError(f"sample_equirect: pano must be (B, C, H, W), got shape {tuple(pano.shape)}")
    if not pano.is_floating_point():
        raise ValueError(
            f"sample_equirect: pano must be floating point (convert uint8 first), got {pano.dtype}"
        )
    B, _, H, W = pano.shape
    if lon.shape != lat.shape or lon.ndim != 3 or lon.shape[0] not in (1, B):
        raise ValueError(
            f"sample_equirect: lon/lat must both be (B or 1, h, w), got {tuple(lon.shape)} "
            f"and {tuple(lat.shape)} for a batch of {B}"
        )
    u = torch.remainder(lon + math.pi, 2.0 * math.pi) * (W / (2.0 * math.pi))
    v = (0.5 * math.pi - lat) * (H / math.pi)
    padded = pad_equirect(pano, 1)
    # Continuous coordinate u in the original maps to index u - 0.5 + 1 in the padded image;
    # align_corners=False puts index i at normalised 2 (i + 0.5) / size - 1.
    gx = 2.0 * (u + 1.0) / (W + 2) - 1.0
    gy = 2.0 * (v + 1.0) / (H + 2) - 1.0
    grid = torch.stack((gx, gy), dim=-1).to(pano.dtype).expand(B, -1, -1, -1)
    return F.grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=False)


def perspective_directions(
    hfov: float, vfov: float, height: int, width: int, dtype=torch.float32, device=None
) -> torch.Tensor:
    """Unit view-frame rays (h, w, 3) of a centred pinhole with the given FOVs (degrees, < 180)."""
    if not (0 < hfov < 180 and 0 < vfov < 180):
        raise ValueError(f"a pinhole view needs 0 < FOV < 180 degrees, got {hfov} x {vfov}")
    fx = 0.5 * width / math.tan(math.radians(hfov) / 2)
    fy = 0.5 * height / math.tan(math.radians(vfov) / 2)
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    d = torch.stack(((uu - 0.5 * width) / fx, (vv - 0.5 * height) / fy, torch.ones_like(uu)), dim=-1)
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)


def equirect_crop_directions(
    hfov: float, vfov: float, height: int, width: int, dtype=torch.float32, device=None
) -> torch.Tensor:
    """Unit view-frame rays (h, w, 3) of an equirectangular window hfov x vfov degrees wide.

    Output pixel (j + 0.5, i + 0.5) has local longitude hfov * ((j + 0.5)/w - 1/2) and latitude
    vfov * (1/2 - (i + 0.5)/h); with yaw/pitch 0 this is a plain crop of the panorama.
    """
    if not (0 < hfov <= 360 and 0 < vfov <= 180):
        raise ValueError(
            f"an equirectangular crop needs 0 < hfov <= 360 and 0 < vfov <= 180, got {hfov} x {vfov}"
        )
    u = (torch.arange(width, dtype=dtype, device=device) + 0.5) / width
    v = (torch.arange(height, dtype=dtype, device=device) + 0.5) / height
    lon = math.radians(hfov) * (u - 0.5)
    lat = math.radians(vfov) * (0.5 - v)
    lat, lon = torch.meshgrid(lat, lon, indexing="ij")
    cl = torch.cos(lat)
    return torch.stack((cl * torch.sin(lon), -torch.sin(lat), cl * torch.cos(lon)), dim=-1)


def _check_size(height: int, width: int) -> None:
    if int(height) <= 0 or int(width) <= 0:
        raise ValueError(f"output size must be positive, got {height}x{width}")


@lru_cache(maxsize=16)
def _cached_rays(kind: str, hfov: float, vfov: float, height: int, width: int, device: str) -> torch.Tensor:
    """View-frame ray grids are reused across calls (the simulator renders the same view every step).

    Returned tensors are shared: callers must not modify them in place.
    """
    make = perspective_directions if kind == "pinhole" else equirect_crop_directions
    return make(hfov, vfov, height, width, torch.float64, torch.device(device))


def _render(pano: torch.Tensor, rays: torch.Tensor, yaw: Angle, pitch: Angle, mode: str) -> torch.Tensor:
    """Rotate view rays (h, w, 3) by each batch element's yaw/pitch and sample the panorama."""
    if pano.ndim != 4:
        raise ValueError(f"pano must be (B, C, H, W), got shape {tuple(pano.shape)}")
    B = pano.shape[0]
    # Directions are built in float64 so float32 panoramas still get accurate lookups at the seam.
    R = view_rotation(
        _angles(yaw, B, torch.float64, pano.device, "yaw"),
        _angles(pitch, B, torch.float64, pano.device, "pitch"),
    )
    d = torch.einsum("bij,hwj->bhwi", R, rays)
    x, y, z = d.unbind(-1)
    lon = torch.atan2(x, z)
    lat = torch.atan2(-y, torch.sqrt(x * x + z * z))
    return sample_equirect(pano, lon, lat, mode=mode)


def equirect_crop(
    pano: torch.Tensor,
    yaw: Angle,
    pitch: Angle,
    hfov: float,
    vfov: float,
    height: int,
    width: int,
    mode: str = "bilinear",
) -> torch.Tensor:
    """An equirectangular window (B, C, height, width) of hfov x vfov degrees centred at (yaw, pitch).

    The window's own longitude/latitude grid (:func:`equirect_crop_directions`) is rotated to the
    view centre, so with pitch 0 it is an exact (resampled) crop; with pitch != 0 the window is
    tilted like a camera, not shifted in latitude. Angles in degrees; yaw/pitch may be floats or
    (B,) tensors.
    """
    _check_size(height, width)
    rays = _cached_rays("crop", float(hfov), float(vfov), int(height), int(width), str(pano.device))
    return _render(pano, rays, yaw, pitch, mode)


def perspective_from_equirect(
    pano: torch.Tensor,
    yaw: Angle,
    pitch: Angle,
    hfov: float,
    vfov: float,
    height: int,
    width: int,
    mode: str = "bilinear",
) -> torch.Tensor:
    """A view (B, C, height, width) of panoramas (B, C, H, W) looking at (yaw, pitch), in degrees.

    For hfov < 180 and vfov < 180 this is a centred pinhole camera (fx = width / (2 tan(hfov/2)),
    likewise fy), e.g. the paper's 90 x 90 degree 336 x 336 view. A pinhole cannot see 180 degrees
    or more, so when either FOV is >= 180 the view is an equirectangular crop instead
    (:func:`equirect_crop`), e.g. the paper's "ultra-wide" 180 x 118 degree 512 x 336 view.
    Bilinear sampling wraps across the seam and continues over the poles.
    """
    _check_size(height, width)
    if hfov >= 180 or vfov >= 180:
        return equirect_crop(pano, yaw, pitch, hfov, vfov, height, width, mode=mode)
    rays = _cached_rays("pinhole", float(hfov), float(vfov), int(height), int(width), str(pano.device))
    return _render(pano, rays, yaw, pitch, mode)


def equirect_to_cubemap(pano: torch.Tensor, face_size: int, mode: str = "bilinear") -> torch.Tensor:
    """Panoramas (B, C, H, W) -> cubemaps (B, 6, C, F, F) in the order of :data:`CUBEMAP_FACES`.

    Faces are front, right, back, left, up, down, each the 90-degree pinhole view of that
    direction. Pixel centres sit at +0.5, so face edges are half a pixel outside the sampled rays
    and adjacent faces do not duplicate samples.
    """
    _check_size(face_size, face_size)
    rays = _cached_rays("pinhole", 90.0, 90.0, int(face_size), int(face_size), str(pano.device))
    faces = []
    for _, yaw, pitch in CUBEMAP_FACES:
        faces.append(_render(pano, rays, yaw, pitch, mode))
    return torch.stack(faces, dim=1)


def cubemap_to_equirect(cube: torch.Tensor, height: int, width: int, mode: str = "bilinear") -> torch.Tensor:
    """Cubemaps (B, 6, C, F, F) in :data:`CUBEMAP_FACES` order -> panoramas (B, C, height, width).

    Every panorama pixel reads the face whose axis is closest to its direction (largest view-frame
    z), at that face's pinhole coordinates. Faces are sampled independently with edge clamping, so
    the outermost half pixel of each face is held constant rather than blended with its
    neighbour: a round trip through :func:`equirect_to_cubemap` is accurate to the interpolation
    error of the face resolution, not exact.
    """
    if cube.ndim != 5 or cube.shape[1] != 6 or cube.shape[-1] != cube.shape[-2]:
        raise ValueError(f"cubemap_to_equirect: cube must be (B, 6, C, F, F), got shape {tuple(cube.shape)}")
    if not cube.is_floating_point():
        raise ValueError(f"cubemap_to_equirect: cube must be floating point, got {cube.dtype}")
    _check_size(height, width)
    B, _, C, F_, _ = cube.shape
    rays = EquirectCamera(int(height), int(width)).ray_map(torch.float64, cube.device).permute(1, 2, 0)
    yaws = torch.tensor([f[1] for f in CUBEMAP_FACES], dtype=torch.float64, device=cube.device)
    pitches = torch.tensor([f[2] for f in CUBEMAP_FACES], dtype=torch.float64, device=cube.device)
    R = view_rotation(torch.deg2rad(yaws), torch.deg2rad(pitches))  # (6, 3, 3) view -> pano
    local = torch.einsum("kji,hwj->khwi", R, rays)  # R^T d: directions in each face's frame
    best = local[..., 2].argmax(dim=0)  # (h, w)
    out = cube.new_zeros((B, C, int(height), int(width)))
    for k in range(6):
        x, y, z = local[k].unbind(-1)
        zs = z.clamp_min(1e-12)
        # 90-degree pinhole: u = F/2 (x/z + 1); align_corners=False normalises to x/z directly.
        grid = torch.stack((x / zs, y / zs), dim=-1).clamp(-2.0, 2.0).to(cube.dtype)
        sampled = F.grid_sample(
            cube[:, k], grid.expand(B, -1, -1, -1), mode=mode, padding_mode="border", align_corners=False
        )
        out = torch.where((best == k)[None, None], sampled, out)
    return out
