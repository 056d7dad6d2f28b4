"""Gaussians -> screen: camera-frame means/covariances, EWA screen covariances, conics, footprints.

Every backend rasterises the output of :func:`project_gaussians`, so the projection is shared,
differentiable through torch autograd, and computed in float64 (cast back to the input dtype at
the end): float32 inputs of magnitude 1e4, scales of 1e3 and near-singular 2x2 covariances then
stay finite and positive definite.

Screen covariance (EWA): ``Sigma_2D = J W Sigma W^T J^T + 0.3 I`` with ``W`` the world-to-camera
rotation and ``J`` the 2x3 pixel Jacobian of the camera at the camera-frame mean.

* Pinhole: ``J`` is :meth:`PinholeCamera.pixel_jacobian` (perspective Jacobian), evaluated at the
  mean with x/z and y/z clamped to the image's tangent range widened by :data:`FRUSTUM_MARGIN`
  (as 3DGS and gsplat do; :func:`frustum_clamped`). The linearisation is only valid near the mean's
  line of sight: a Gaussian beside the camera, a few centimetres in front of its plane (a wall
  passed at 0.3 m), has x/z of 10-100 and an unclamped footprint of thousands of pixels that
  fogged whole views although none of its mass is in the frustum.
* Equirect: ``J`` is the analytic Jacobian of (longitude, latitude) scaled to pixels; it equals
  :meth:`EquirectCamera.pixel_jacobian` away from the poles but is written in the (lon, lat)
  tangent basis so it stays defined *at* the poles (within cos(lat) <= 1e-9 the longitude is set
  to 0 with no gradient). The longitude row grows like 1/cos(lat): near a pole the u-variance is
  huge, the profile nearly flat across the width, as the true projection of a Gaussian on the pole
  is. Pixels take the wrapped horizontal offset (see :func:`wrap_offset`) and footprint boxes are at
  most the full width. Within cos(lat) < :data:`POLE_BLEND_COS` the v-variance and the cross term
  are blended towards their longitude average (:func:`_pole_blend`), so that nothing depends on the
  mean's longitude at the pole and the gradients of the means stay bounded there.

Every backend (the compiled kernel's fused inference projection too) follows these rules, so they
agree at the poles, the seam and extreme scales.
"""

from __future__ import annotations

import math
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

__all__ = [
    "CUTOFF_SIGMA",
    "DILATION",
    "ALPHA_MIN",
    "ALPHA_MAX",
    "T_MIN",
    "NEAR",
    "FRUSTUM_MARGIN",
    "ProjectedGaussians",
    "quat_to_rotmat",
    "covariance_3d",
    "world_to_camera",
    "equirect_jacobian",
    "frustum_clamped",
    "project_gaussians",
    "projector",
    "wrap_offset",
]

CUTOFF_SIGMA = 3.5
"""A Gaussian's footprint is the ellipse d^T Sigma_2D^-1 d <= CUTOFF_SIGMA^2."""
DILATION = 0.3
"""Low-pass dilation added to the diagonal of every screen covariance (pixels^2)."""
ALPHA_MIN = 1.0 / 255.0
"""Contributions with alpha below this are skipped."""
ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped to at most this value."""
T_MIN = 1e-4
"""A pixel is finished once its transmittance drops below this (the last Gaussian still counts)."""

NEAR = 0.05
"""Default near plane (metres): nearer points, and everything behind a pinhole camera, are culled."""

FRUSTUM_MARGIN = 0.3
"""A pinhole Jacobian is evaluated with x/z clamped to [-cx/fx - m t, (W - cx)/fx + m t] (t = the
half-width's tangent W / (2 fx), m this margin; y alike): the mean's projection is unchanged, only
its footprint's linearisation point moves to the frustum's widened edge (3DGS's 1.3 tan(fov/2))."""

POLE_BLEND_COS = 0.1
"""Within this cos(latitude) of a pole (about 5.7 degrees) an equirect screen covariance is blended
towards its longitude average (see :func:`_pole_blend`)."""
_POLE_COS = 1e-9
"""Within this cos(latitude) (= rho / r) of a pole the longitude is undefined: it is set to 0 with no
gradient, and 1/cos(lat) is capped there. Relative, not absolute: a float32 mean resolves about
1e-7 of its range, and the longitude's gradient (1/rho) times the rounding left in the other terms
grew without bound below this (issue 23)."""


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians for one camera (all tensors have length N, the input count).

    Culled Gaussians keep harmless finite placeholder values and ``valid = False``; rasterisers
    must ignore them.
    """

    means2d: torch.Tensor
    """(N, 2) continuous pixel coordinates (u, v) of the projected mean; u in [0, W) for equirect."""
    conics: torch.Tensor
    """(N, 3) (A, B, C) of the inverse screen covariance [[A, B], [B, C]]."""
    cov2d: torch.Tensor
    """(N, 3) (a, b, c) of the dilated (and, for equirect, clamped) screen covariance."""
    depths: torch.Tensor
    """(N,) sort and depth-map key: camera-frame range (equirect) or z (pinhole)."""
    radii: torch.Tensor
    """(N, 2) detached half-extents (pixels) of the 3.5-sigma footprint's bounding box."""
    valid: torch.Tensor
    """(N,) bool: survives culling (near/far/behind, non-finite, opacity, off-image)."""
    wrap_width: float
    """Image width for horizontal wrap-around (equirect) or 0.0 (pinhole: no wrap)."""


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), normalised here, -> (N, 3, 3) rotation matrices."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def covariance_3d(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """World covariances R diag(s^2) R^T, (N, 3, 3), from standard deviations and quaternions."""
    rot = quat_to_rotmat(quats)
    rs = rot * scales.unsqueeze(-2)  # R @ diag(s)
    return rs @ rs.transpose(-1, -2)


def world_to_camera(
    means: torch.Tensor, cov: torch.Tensor, cam_to_world: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World means (N, 3) and covariances (N, 3, 3) into the camera frame of a 4x4 camera-to-world.

    The camera translation is subtracted before rotating, so large world coordinates near the
    camera lose no precision.
    """
    rot = cam_to_world[:3, :3]
    t = cam_to_world[:3, 3]
    # p_cam = R^T (m - t)  <=>  row form (m - t) @ R
    p = (means - t) @ rot
    c = rot.transpose(0, 1) @ cov @ rot
    return p, c


def equirect_jacobian(points: torch.Tensor, camera: EquirectCamera) -> tuple[torch.Tensor, torch.Tensor]:
    """Pole-safe d(u, v)/d(x, y, z) at camera-frame points (N, 3) -> (uv (N, 2), J (N, 2, 3)).

    With d = (cos lat sin lon, -sin lat, cos lat cos lon):
    du/dp = W/(2 pi) * (cos lon, 0, -sin lon) / (r cos lat),
    dv/dp = -H/pi * (-sin lat sin lon, -cos lat, -sin lat cos lon) / r.
    ``u`` is wrapped into [0, W). Gradients are finite at the poles (double-``where`` guards).
    """
    x, y, z = points.unbind(-1)
    rho2 = x * x + z * z
    at_pole = rho2 <= (_POLE_COS * _POLE_COS) * (rho2 + y * y)
    xs = torch.where(at_pole, torch.zeros_like(x), x)
    zs = torch.where(at_pole, torch.ones_like(z), z)
    lon = torch.atan2(xs, zs)
    rho = torch.sqrt(torch.where(at_pole, torch.ones_like(rho2), rho2))
    rho = torch.where(at_pole, torch.zeros_like(rho), rho)
    lat = torch.atan2(-y, rho)
    r = torch.sqrt(rho2 + y * y)
    su = camera.width / (2.0 * math.pi)
    sv = -camera.height / math.pi
    cl, sl = torch.cos(lat), torch.sin(lat)
    co, so = torch.cos(lon), torch.sin(lon)
    zero = torch.zeros_like(x)
    ju = torch.stack((co, zero, -so), dim=-1) * (su / (r * cl.clamp_min(_POLE_COS))).unsqueeze(-1)
    jv = torch.stack((-sl * so, -cl, -sl * co), dim=-1) * (sv / r).unsqueeze(-1)
    u = torch.remainder((lon + math.pi) * su, float(camera.width))
    v = (0.5 * math.pi - lat) * (camera.height / math.pi)
    return torch.stack((u, v), dim=-1), torch.stack((ju, jv), dim=-2)


def frustum_clamped(points: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
    """Camera-frame points (N, 3) with z > 0, moved along x and y to the frustum widened by
    :data:`FRUSTUM_MARGIN` (z unchanged): where a pinhole Jacobian is evaluated. Points inside the
    widened frustum are returned as they are; outside it the clamp passes no gradient to x or y."""
    x, y, z = points.unbind(-1)
    tx, ty = 0.5 * camera.width / camera.fx, 0.5 * camera.height / camera.fy
    lo_x, hi_x = (
        -camera.cx / camera.fx - FRUSTUM_MARGIN * tx,
        (camera.width - camera.cx) / camera.fx + FRUSTUM_MARGIN * tx,
    )
    lo_y, hi_y = (
        -camera.cy / camera.fy - FRUSTUM_MARGIN * ty,
        (camera.height - camera.cy) / camera.fy + FRUSTUM_MARGIN * ty,
    )
    return torch.stack(((x / z).clamp(lo_x, hi_x) * z, (y / z).clamp(lo_y, hi_y) * z, z), dim=-1)


def _pole_blend(
    points: torch.Tensor,
    rot_wc: torch.Tensor,
    rs: torch.Tensor,
    b: torch.Tensor,
    c: torch.Tensor,
    camera: EquirectCamera,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Near a pole, the EWA screen covariance's (b, c) blended towards their longitude average.

    At the pole the v-variance c of an anisotropic Gaussian is its spread along the meridian of the
    mean's longitude, an arbitrary direction there: the image jumps with the longitude, whose gradient
    is 1/rho, so float32 gradients of the means grew without bound (issue 23). Within cos(lat) <
    :data:`POLE_BLEND_COS`, c moves to its average over longitudes, ``(H/pi)^2 / r^2 (sin^2 lat (Sxx +
    Szz) / 2 + cos^2 lat Syy)``, and b to 0, with weight ``1 - cos^2(lat) / POLE_BLEND_COS^2``: the
    longitude's influence vanishes like rho^2 and the gradient stays bounded. Isotropic Gaussians are
    unchanged (their c does not depend on the longitude), and with ``t <= 1`` the blend keeps the
    covariance positive semi-definite (``a c' - b'^2 >= t (a c - b^2)``). The camera-frame ``R S``
    (Sigma_cam = its square) is formed only for the Gaussians inside the cap, the few of a panorama.
    """
    x, y, z = points.unbind(-1)
    r2 = (points * points).sum(-1)
    cos2 = (x * x + z * z) / r2
    near = torch.nonzero(cos2 < POLE_BLEND_COS * POLE_BLEND_COS).squeeze(-1)
    if near.numel() == 0:
        return b, c
    cos2_n, r2_n = cos2[near], r2[near]
    t = cos2_n / (POLE_BLEND_COS * POLE_BLEND_COS)
    m_cam = rot_wc.transpose(0, 1) @ rs[near]
    sxx, syy, szz = ((m_cam * m_cam).sum(-1)).unbind(-1)
    c_avg = (camera.height / math.pi) ** 2 / r2_n * ((1.0 - cos2_n) * 0.5 * (sxx + szz) + cos2_n * syy)
    b = b.index_copy(0, near, b[near] * t)
    c = c.index_copy(0, near, c_avg + t * (c[near] - c_avg))
    return b, c


def wrap_offset(du: torch.Tensor, wrap_width: float) -> torch.Tensor:
    """Horizontal pixel offset folded into [-W/2, W/2) for panoramas (identity when W == 0)."""
    if wrap_width <= 0:
        return du
    half = 0.5 * wrap_width
    return du - wrap_width * torch.floor((du + half) / wrap_width)


def project_gaussians(
    means: torch.Tensor,
    scales: torch.Tensor,
    quats: torch.Tensor,
    opacities: torch.Tensor,
    camera: EquirectCamera | PinholeCamera,
    cam_to_world: torch.Tensor,
    *,
    near: float = NEAR,
    far: float | None = None,
    finite_mask: torch.Tensor | None = None,
) -> ProjectedGaussians:
    """Project N world Gaussians into one camera (differentiable w.r.t. all tensor inputs).

    Culling (``valid = False``): depth (range or z) below ``near`` (this includes everything
    behind a pinhole camera), depth above ``far``, ``finite_mask`` False, opacity below
    :data:`ALPHA_MIN` (it could never reach the alpha threshold), a non-finite or non-positive
    definite screen covariance, or a footprint box that misses the image.
    """
    out_dtype = means.dtype
    dt = torch.float64
    n = means.shape[0]
    m = means.to(dt)
    c2w = cam_to_world.to(dtype=dt, device=means.device)
    rot_wc = c2w[:3, :3]
    # Camera-frame means; the translation is subtracted first so large coordinates keep precision.
    p = (m - c2w[:3, 3]) @ rot_wc
    # R diag(s): Sigma = (R S)(R S)^T, so Sigma_2D = L L^T with L = J R_cw R S (no 3x3 products).
    rs = quat_to_rotmat(quats.to(dt)) * scales.to(dt).unsqueeze(-2)

    equirect = isinstance(camera, EquirectCamera)
    depth = torch.linalg.vector_norm(p, dim=-1) if equirect else p[:, 2]
    valid = torch.isfinite(depth) & (depth > 0) & (depth >= near)
    if far is not None:
        valid = valid & (depth <= far)
    if finite_mask is not None:
        valid = valid & finite_mask
    valid = valid & (opacities.detach().to(dt) >= ALPHA_MIN)

    # Culled points get a safe stand-in so no inf/NaN reaches values or gradients.
    safe_point = torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=means.device)
    p_s = torch.where(valid.unsqueeze(-1), p, safe_point)

    if equirect:
        uv, jac = equirect_jacobian(p_s, camera)
    else:
        uv, _, _ = camera.project(p_s)
        jac = camera.pixel_jacobian(frustum_clamped(p_s, camera))
    k = (jac.reshape(-1, 3) @ rot_wc.transpose(0, 1)).reshape(n, 2, 3)  # J R_cw
    el = (k.unsqueeze(-1) * rs.unsqueeze(1)).sum(2)  # (N, 2, 3) = J R_cw R S
    el = torch.where(valid[:, None, None], el, torch.zeros_like(el))
    cov2 = torch.stack(
        ((el[:, 0] * el[:, 0]).sum(-1), (el[:, 0] * el[:, 1]).sum(-1), (el[:, 1] * el[:, 1]).sum(-1)), dim=-1
    )
    b, c = cov2[:, 1], cov2[:, 2]
    if equirect:
        b, c = _pole_blend(p_s, rot_wc, rs, b, c, camera)
    a = cov2[:, 0] + DILATION
    c = c + DILATION
    det = a * c - b * b
    ok = torch.isfinite(a) & torch.isfinite(b) & torch.isfinite(c) & (det > 0)
    valid = valid & ok
    one = torch.ones_like(a)
    zero = torch.zeros_like(a)
    a = torch.where(valid, a, one)
    b = torch.where(valid, b, zero)
    c = torch.where(valid, c, one)
    det = a * c - b * b
    conics = torch.stack((c / det, -b / det, a / det), dim=-1)
    cov2d = torch.stack((a, b, c), dim=-1)
    radii = CUTOFF_SIGMA * torch.sqrt(torch.stack((a, c), dim=-1).detach())
    if equirect:  # a box wider than the panorama covers every column: no wider is needed
        radii = torch.stack((radii[:, 0].clamp(max=float(camera.width)), radii[:, 1]), dim=-1)

    # Footprint boxes that miss the image are culled (rows always; columns only for pinhole).
    uvd = uv.detach()
    on_image = (uvd[:, 1] + radii[:, 1] > 0) & (uvd[:, 1] - radii[:, 1] < camera.height)
    if not equirect:
        on_image = on_image & (uvd[:, 0] + radii[:, 0] > 0) & (uvd[:, 0] - radii[:, 0] < camera.width)
    valid = valid & on_image & torch.isfinite(uvd).all(dim=-1)
    uv = torch.where(valid.unsqueeze(-1), uv, torch.zeros_like(uv))
    depth = torch.where(valid, depth, torch.zeros_like(depth))

    return ProjectedGaussians(
        means2d=uv.to(out_dtype),
        conics=conics.to(out_dtype),
        cov2d=cov2d.to(out_dtype),
        depths=depth.to(out_dtype),
        radii=radii.to(out_dtype),
        valid=valid,
        wrap_width=float(camera.width) if equirect else 0.0,
    )


_compiled_lock = threading.Lock()
_compiled: Callable[..., ProjectedGaussians] | None = None
_compile_failed: str | None = None


def _compiled_projection(*args, **kwargs) -> ProjectedGaussians:
    """:func:`project_gaussians` through ``torch.compile`` (inductor), or eager after a failed compile."""
    global _compiled, _compile_failed
    if _compile_failed is None:
        with _compiled_lock:
            if _compiled is None:
                _compiled = torch.compile(project_gaussians, dynamic=True)
        try:
            return _compiled(*args, **kwargs)
        except Exception as err:  # no C++ compiler, an inductor bug ...: eager gives the same result
            first_line = str(err).strip().splitlines()[0] if str(err).strip() else ""
            _compile_failed = f"{type(err).__name__}: {first_line}"
            warnings.warn(
                f"compiled projection unavailable ({_compile_failed}); projecting eagerly",
                RuntimeWarning,
                stacklevel=2,
            )
    return project_gaussians(*args, **kwargs)


def projector(compiled: bool) -> Callable[..., ProjectedGaussians]:
    """The differentiable projection: :func:`project_gaussians` itself, or (``compiled``) the same
    function through ``torch.compile`` with dynamic shapes.

    The compiled one fuses the float64 element-wise chain and its backward into generated C++ loops:
    on a 2-core CPU, forward + backward of 630 k Gaussians into a 256x128 panorama take 0.35 s
    against 1.16 s eagerly (same values; gradients within 1e-10 relative;
    ``benchmarks/refine_step.py``), after a one-off compile of ~30 s (cached on disk by inductor).
    That pays for long optimisations such as per-scene refinement, not for single renders. If
    compiling fails, it warns once and projects
    eagerly.
    """
    return _compiled_projection if compiled else project_gaussians
