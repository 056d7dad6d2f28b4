"""Camera models: pixel <-> ray, point -> pixel (+ depth), depth -> points, ray maps, Jacobians.

All maps follow :mod:`image2sim.simulator.conventions` (OpenCV camera frame, pixel centres at
integer + 0.5, panorama depth = range, pinhole depth = z). Functions take and return torch tensors
and keep the input dtype, so float64 round trips are exact to ~1e-12 and float32 is the fast path.
Leading batch dimensions broadcast freely.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

__all__ = ["EquirectCamera", "PinholeCamera", "Camera", "camera_from_dict"]

# Keeps atan2/hypot derivatives finite exactly at the poles (where longitude is undefined).
_POLE_EPS = 1e-12


def _check_map(camera, depth: torch.Tensor) -> None:
    """A clear error instead of a broadcasting failure (or silent broadcast) on a wrong-size map."""
    if depth.ndim < 2 or tuple(depth.shape[-2:]) != (camera.height, camera.width):
        name = type(camera).__name__
        raise ValueError(f"{name}.unproject: depth map of shape {tuple(depth.shape)} does not "
                         f"end in the camera's (H, W) = ({camera.height}, {camera.width})")


def _pixel_grid(height: int, width: int, dtype: torch.dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous coordinates (u, v) of every pixel centre, each (H, W)."""
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return uu, vv


@dataclass(frozen=True)
class EquirectCamera:
    """Equirectangular (360 x 180 degree) camera.

    Pixel (u, v) maps to longitude ``2*pi*u/W - pi`` (0 at the centre column, positive to the
    right) and latitude ``pi/2 - pi*v/H`` (positive up); direction
    ``(cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon))`` in the OpenCV camera frame.
    Depth is Euclidean range.
    """

    height: int
    width: int

    model = "equirect"

    def __post_init__(self) -> None:
        if int(self.height) <= 0 or int(self.width) <= 0:
            raise ValueError(f"EquirectCamera needs positive height/width, got {self.height}x{self.width}")

    # --- angles ---------------------------------------------------------------------------
    def pixel_to_lonlat(self, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lon = 2.0 * math.pi * u / self.width - math.pi
        lat = 0.5 * math.pi - math.pi * v / self.height
        return lon, lat

    def lonlat_to_pixel(self, lon: torch.Tensor, lat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        u = (lon + math.pi) * (self.width / (2.0 * math.pi))
        v = (0.5 * math.pi - lat) * (self.height / math.pi)
        return u, v

    # --- rays -----------------------------------------------------------------------------
    def pixel_to_ray(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Unit camera-frame directions (..., 3) of continuous pixel coordinates."""
        lon, lat = self.pixel_to_lonlat(u, v)
        cl = torch.cos(lat)
        return torch.stack((cl * torch.sin(lon), -torch.sin(lat), cl * torch.cos(lon)), dim=-1)

    def ray_map(self, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
        """Unit ray directions at every pixel centre, (3, H, W) in the camera frame."""
        uu, vv = _pixel_grid(self.height, self.width, dtype, device)
        return self.pixel_to_ray(uu, vv).permute(2, 0, 1).contiguous()

    # --- projection -----------------------------------------------------------------------
    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera-frame points (..., 3) -> (uv (..., 2), range (...), valid (...)).

        ``u`` lies in [0, W) (the seam at lon = +-pi wraps), ``v`` in [0, H]. Points at the
        camera centre (range 0) are invalid.
        """
        x, y, z = points.unbind(-1)
        rng = torch.linalg.vector_norm(points, dim=-1)
        lon = torch.atan2(x, z)
        lat = torch.atan2(-y, torch.sqrt(x * x + z * z))
        u, v = self.lonlat_to_pixel(lon, lat)
        u = torch.remainder(u, float(self.width))
        # remainder(-tiny, W) rounds to exactly W; fold it back so u stays in [0, W).
        u = torch.where(u >= self.width, u - self.width, u)
        return torch.stack((u, v), dim=-1), rng, rng > 0

    def unproject(self, depth: torch.Tensor) -> torch.Tensor:
        """Range maps (..., H, W) -> camera-frame points (..., H, W, 3); invalid pixels give 0."""
        _check_map(self, depth)
        rays = self.ray_map(depth.dtype, depth.device).permute(1, 2, 0)
        return depth.unsqueeze(-1) * rays

    def pixel_jacobian(self, points: torch.Tensor) -> torch.Tensor:
        """d(u, v)/d(x, y, z) at camera-frame points (..., 3) -> (..., 2, 3).

        With rho2 = x^2 + z^2 and r2 = rho2 + y^2:
        dlon/dp = (z, 0, -x)/rho2;  dlat/dp = (x*y/rho, -rho, y*z/rho)/r2 (with lat = atan2(-y, rho)),
        then u = W/(2pi) lon and v = -H/pi lat.
        """
        x, y, z = points.unbind(-1)
        rho2 = (x * x + z * z).clamp_min(_POLE_EPS)
        rho = torch.sqrt(rho2)
        r2 = rho2 + y * y
        zero = torch.zeros_like(x)
        dlon = torch.stack((z / rho2, zero, -x / rho2), dim=-1)
        dlat = torch.stack((x * y / (rho * r2), -rho / r2, y * z / (rho * r2)), dim=-1)
        su = self.width / (2.0 * math.pi)
        sv = -self.height / math.pi
        return torch.stack((su * dlon, sv * dlat), dim=-2)

    def to_dict(self) -> dict:
        return {"model": self.model, "height": int(self.height), "width": int(self.width)}


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera with intrinsics in pixels (centres at integer + 0.5); depth is z."""

    fx: float
    fy: float
    cx: float
    cy: float
    height: int
    width: int

    model = "pinhole"

    def __post_init__(self) -> None:
        if int(self.height) <= 0 or int(self.width) <= 0:
            raise ValueError(f"PinholeCamera needs positive height/width, got {self.height}x{self.width}")
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"PinholeCamera.{name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"PinholeCamera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_fov(cls, hfov_deg: float, vfov_deg: float, height: int, width: int) -> PinholeCamera:
        """Centred pinhole with the given horizontal/vertical fields of view (degrees, < 180)."""
        if not (0 < hfov_deg < 180 and 0 < vfov_deg < 180):
            raise ValueError(f"pinhole FOV must lie in (0, 180) degrees, got {hfov_deg} x {vfov_deg}")
        fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        fy = 0.5 * height / math.tan(math.radians(vfov_deg) / 2)
        return cls(fx, fy, width / 2.0, height / 2.0, height, width)

    @property
    def K(self) -> torch.Tensor:
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64
        )

    def pixel_to_ray(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Unit camera-frame directions (..., 3): normalised K^-1 [u, v, 1]."""
        d = torch.stack(((u - self.cx) / self.fx, (v - self.cy) / self.fy, torch.ones_like(u)), dim=-1)
        return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)

    def ray_map(self, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
        """Unit ray directions at every pixel centre, (3, H, W) in the camera frame."""
        uu, vv = _pixel_grid(self.height, self.width, dtype, device)
        return self.pixel_to_ray(uu, vv).permute(2, 0, 1).contiguous()

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera-frame points (..., 3) -> (uv (..., 2), z (...), valid (...)); valid means z > 0."""
        x, y, z = points.unbind(-1)
        valid = z > 0
        zs = torch.where(valid, z, torch.ones_like(z))
        u = self.fx * x / zs + self.cx
        v = self.fy * y / zs + self.cy
        return torch.stack((u, v), dim=-1), z, valid

    def unproject(self, depth: torch.Tensor) -> torch.Tensor:
        """z-depth maps (..., H, W) -> camera-frame points (..., H, W, 3); invalid pixels give 0."""
        _check_map(self, depth)
        uu, vv = _pixel_grid(self.height, self.width, depth.dtype, depth.device)
        x = (uu - self.cx) / self.fx
        y = (vv - self.cy) / self.fy
        rays = torch.stack((x, y, torch.ones_like(x)), dim=-1)
        return depth.unsqueeze(-1) * rays

    def pixel_jacobian(self, points: torch.Tensor) -> torch.Tensor:
        """d(u, v)/d(x, y, z) -> (..., 2, 3): [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]."""
        x, y, z = points.unbind(-1)
        zero = torch.zeros_like(x)
        return torch.stack(
            (
                torch.stack((self.fx / z, zero, -self.fx * x / (z * z)), dim=-1),
                torch.stack((zero, self.fy / z, -self.fy * y / (z * z)), dim=-1),
            ),
            dim=-2,
        )

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "height": int(self.height),
            "width": int(self.width),
        }


Camera = EquirectCamera | PinholeCamera


def camera_from_dict(data: dict) -> Camera:
    """Inverse of ``camera.to_dict()``; raises ``ValueError`` naming the bad field."""
    if not isinstance(data, dict):
        raise ValueError(f"camera description must be a dict, got {type(data).__name__}")
    if "model" not in data:
        raise ValueError(f"camera description is missing field 'model': {data}")
    model = data["model"]
    if model == "equirect":
        fields = {"height": int, "width": int}
    elif model == "pinhole":
        fields = {"fx": float, "fy": float, "cx": float, "cy": float, "height": int, "width": int}
    else:
        raise ValueError(f"unknown camera model {model!r} (expected 'equirect' or 'pinhole')")
    unknown = sorted(set(data) - set(fields) - {"model"})
    if unknown:
        raise ValueError(f"{model} camera description has unknown field(s) {unknown}: {data}")
    values = {}
    for name, kind in fields.items():
        if name not in data:
            raise ValueError(f"{model} camera description is missing field {name!r}: {data}")
        raw = data[name]
        # bool is an int subclass and a float height (e.g. 2.5) would be truncated silently.
        if isinstance(raw, bool) or not isinstance(raw, numbers.Real) or (kind is int and raw != int(raw)):
            raise ValueError(f"{model} camera field {name!r} must be {kind.__name__}, got {raw!r}")
        values[name] = kind(raw)
    if model == "equirect":
        return EquirectCamera(values["height"], values["width"])
    return PinholeCamera(**values)
