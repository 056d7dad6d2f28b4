"""Adapter to gsplat's CUDA rasteriser for pinhole cameras (optional extra; CUDA only).

``backend="auto"`` sends pinhole cameras on CUDA tensors here when ``import gsplat`` works. gsplat
projects and rasterises in one call (``gsplat.rasterization``), so this is a *renderer* backend
(see :mod:`image2sim.simulator.splatting.dispatch`). The conversion from this package's
conventions:

* quaternions: both use (w, x, y, z) and normalise internally, passed unchanged; scales are
  standard deviations in metres in both (not log-scales); opacities in [0, 1] (not logits).
* cameras: gsplat takes world-to-camera ``viewmats`` (the inverse of our ``cam_to_world``, inverted
  in float64) and intrinsics ``Ks`` = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] from the
  :class:`PinholeCamera`; both use OpenCV axes (x right, y down, z forward) and pixel centres at
  (i + 0.5, j + 0.5), so ``cx, cy`` carry over as they are.
* dilation: ``eps2d = 0.3`` with ``rasterize_mode="classic"`` is our ``Sigma_2D + 0.3 I`` (no
  antialiasing compensation).
* channels: colours and features go in as one ``(N, 3 + C)`` colour tensor (``sh_degree=None``);
  ``render_mode="RGB+D"`` appends gsplat's accumulated depth ``sum_i w_i z_i``, which is our pinhole
  ``depth`` (not normalised).
* background: applied here to rgb only, ``rgb += (1 - alpha) * background`` (gsplat's
  ``backgrounds`` would also fill the feature and depth channels).
* near / far: ``near_plane`` / ``far_plane`` (gsplat culls on camera z like our pinhole path).
* dtype: gsplat kernels are float32; inputs are cast to float32 and outputs back to the input dtype
  (gradients flow through the casts).

Semantic differences that remain (why ``gsplat`` is not bit-compatible with ``cpu``/``torch``):

* per-Gaussian alpha is clamped to 0.999 in gsplat, 0.99 here;
* termination: gsplat stops *before* a Gaussian that would take T below 1e-4 (that Gaussian does not
  count); here it still counts and the pixel stops after it;
* footprint: gsplat bins and cuts by a 3-sigma radius of the larger eigenvalue of Sigma_2D (a circle);
  here the cut is the 3.5-sigma ellipse d^T Sigma_2D^-1 d <= 3.5^2;
* non-finite inputs are handled by :func:`~image2sim.simulator.splatting.api.splat` before the call
  (culled rows reach gsplat with opacity 0, which it skips).

They are not negligible everywhere: a Gaussian with o exp(-q/2) > 0.99 weighs 0.999 instead of 0.99,
and between 3 and 3.5 sigma along the major axis gsplat drops contributions of alpha up to ~0.011 o
that count here. The exact-parity tests against the dense reference therefore cover the ``cpu`` and
``torch`` backends only; the gsplat path is tested for the arguments it passes (no CUDA here).
"""

from __future__ import annotations

import importlib

import torch
from image2sim.simulator.geometry.cameras import PinholeCamera
from image2sim.simulator.splatting.project import DILATION

__all__ = ["available", "unavailable_reason", "render", "gsplat_arguments"]

_FAR_DEFAULT = 1e10


def _import():
    return importlib.import_module("gsplat")


def available() -> bool:
    """True if ``import gsplat`` works (the package is an optional extra; it needs CUDA to run)."""
    try:
        _import()
    except Exception:  # ImportError, or a broken CUDA build raising at import
        return False
    return True


def unavailable_reason() -> str:
    """Why gsplat cannot be used ("" when it imports)."""
    try:
        _import()
    except Exception as err:
        return f"import gsplat failed: {type(err).__name__}: {err}"
    return ""


def gsplat_arguments(
    means: torch.Tensor,
    scales: torch.Tensor,
    quats: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    features: torch.Tensor,
    camera: PinholeCamera,
    poses: torch.Tensor,
    *,
    near: float,
    far: float | None,
) -> dict:
    """Keyword arguments of ``gsplat.rasterization`` for our inputs (pure; see the module docstring)."""
    if not isinstance(camera, PinholeCamera):
        raise ValueError(f"gsplat backend: only PinholeCamera is supported, got {type(camera).__name__}")
    f32 = torch.float32
    b = poses.shape[0]
    viewmats = torch.linalg.inv(poses.to(torch.float64)).to(f32)
    k = torch.tensor(
        [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
        dtype=f32,
        device=means.device,
    )
    return {
        "means": means.to(f32),
        "quats": quats.to(f32),
        "scales": scales.to(f32),
        "opacities": opacities.to(f32),
        "colors": torch.cat((colors, features), dim=1).to(f32),
        "viewmats": viewmats.to(means.device),
        "Ks": k.expand(b, 3, 3).contiguous(),
        "width": int(camera.width),
        "height": int(camera.height),
        "near_plane": float(near),
        "far_plane": float(far) if far is not None else _FAR_DEFAULT,
        "eps2d": float(DILATION),
        "sh_degree": None,
        "render_mode": "RGB+D",
        "rasterize_mode": "classic",
        "tile_size": 16,
    }


def render(
    means: torch.Tensor,
    scales: torch.Tensor,
    quats: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    features: torch.Tensor,
    camera: PinholeCamera,
    poses: torch.Tensor,
    *,
    near: float,
    far: float | None,
    background: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render B pinhole views with gsplat; returns (rgb, depth, alpha, features), each (B, ., H, W)."""
    gsplat = _import()
    kwargs = gsplat_arguments(
        means, scales, quats, opacities, colors, features, camera, poses, near=near, far=far
    )
    render_colors, render_alphas, _meta = gsplat.rasterization(**kwargs)
    c = features.shape[1]
    b, h, w = poses.shape[0], camera.height, camera.width
    if tuple(render_colors.shape) != (b, h, w, 4 + c) or tuple(render_alphas.shape) != (b, h, w, 1):
        raise RuntimeError(
            f"gsplat backend: rasterization returned colours {tuple(render_colors.shape)} and alphas "
            f"{tuple(render_alphas.shape)}, expected {(b, h, w, 4 + c)} and {(b, h, w, 1)}"
        )
    dtype = means.dtype
    img = render_colors.permute(0, 3, 1, 2).to(dtype)
    alpha = render_alphas.permute(0, 3, 1, 2).to(dtype)
    rgb = img[:, :3] + (1.0 - alpha) * background.to(dtype).reshape(1, 3, 1, 1)
    return rgb, img[:, 3 + c :], alpha, img[:, 3 : 3 + c]
