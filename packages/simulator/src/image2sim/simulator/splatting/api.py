"""Public entry point: ``splat`` feature Gaussians into equirectangular or pinhole cameras.

Semantics (shared exactly by every backend; the dense reference in
:mod:`.backends.reference` is the ground truth):

* Inputs: ``means`` (N, 3) world metres, ``scales`` (N, 3) standard deviations in metres,
  ``quats`` (N, 4) (w, x, y, z) (normalised internally), ``opacities`` (N,), ``colors`` (N, 3),
  ``features`` (N, C) (C = 0 allowed, ``None`` means C = 0); ``camera`` an
  :class:`EquirectCamera` or :class:`PinholeCamera`; ``cam_to_world`` (4, 4) or (B, 4, 4).
* Covariance Sigma = R diag(s^2) R^T, moved into the camera frame with cam_to_world^-1. Screen
  covariance by EWA, J W Sigma W^T J^T + 0.3 I, with the perspective Jacobian (pinhole) or the
  analytic (lon, lat) Jacobian scaled to pixels (equirect); see :mod:`.project`.
* Pixel centres at (i + 0.5, j + 0.5). Per pixel the Gaussians are composited front to back by
  camera-space range (pinhole: z), ties by input index; alpha_i = min(0.99, o_i exp(-q/2)) with
  q = d^T Sigma_2D^-1 d; a Gaussian contributes only where q <= 3.5^2 (footprint cut at 3.5 sigma)
  and alpha_i >= 1/255; w_i = alpha_i T_i, T_i = prod_{j<i} (1 - alpha_j); after compositing a
  Gaussian the pixel is finished once T < ``min_transmittance`` (default 1e-4, as 3DGS and gsplat;
  that Gaussian still counts). A larger value is an inference option: what a finished pixel leaves
  out weighs at most T, so every output moves by at most ``min_transmittance`` times the spread of
  the values (colour, depth, features) behind the surface, and nearly opaque scenes render faster
  (``reports/splat_early_finish.md``). The ``renderer``-kind backends (gsplat) always composite to 1e-4.
* Outputs: rgb = sum w_i c_i + (1 - alpha) background, depth = sum w_i rho_i (range for panoramas,
  z for pinhole; *not* normalised, see :meth:`SplatOutput.normalized_depth`), alpha = sum w_i,
  features = sum w_i f_i.
* Culling: depth below ``near`` (includes all points behind a pinhole camera), beyond ``far``,
  opacity below 1/255, footprints off the image. Non-finite inputs raise ``ValueError`` (default)
  or, with ``nonfinite="cull"``, drop the offending Gaussians; ``nonfinite="checked"`` skips the
  per-call scan for a caller that checked its Gaussians once (:func:`check_finite`), as a render
  function does for its scene.
* Equirect: footprints crossing the +-180 degree seam appear on both edges (horizontal offsets are
  wrapped); near the poles the footprint is clamped to at most the full image width.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.splatting.backends import reference as _reference
from image2sim.simulator.splatting.backends import torch_tiles as _torch_tiles
from image2sim.simulator.splatting.culling import FrustumBlocks
from image2sim.simulator.splatting.dispatch import (
    Backend,
    device_type,
    register_backend,
    registered_backends,
)
from image2sim.simulator.splatting.dispatch import get_backend as _get_backend
from image2sim.simulator.splatting.dispatch import resolve_backend as _resolve
from image2sim.simulator.splatting.project import NEAR, T_MIN, projector

__all__ = ["SplatOutput", "splat", "available_backends", "resolve_backend", "check_finite", "NONFINITE_MODES"]


@dataclass
class SplatOutput:
    """Splatted image planes for B cameras."""

    rgb: torch.Tensor
    """(B, 3, H, W) composited colour (plus background where alpha < 1)."""
    depth: torch.Tensor
    """(B, 1, H, W) alpha-weighted depth sum_i w_i rho_i (range for equirect, z for pinhole)."""
    alpha: torch.Tensor
    """(B, 1, H, W) accumulated opacity sum_i w_i."""
    features: torch.Tensor
    """(B, C, H, W) alpha-weighted features (C may be 0)."""
    backend: str = ""
    """Name of the backend that produced this output."""

    def normalized_depth(self) -> torch.Tensor:
        """Expected depth depth / alpha where alpha > 0, else 0 (the invalid-depth marker)."""
        pos = self.alpha > 0
        return torch.where(
            pos,
            self.depth / torch.where(pos, self.alpha, torch.ones_like(self.alpha)),
            torch.zeros_like(self.depth),
        )


RasterizeFn = Callable[..., tuple[torch.Tensor, torch.Tensor]]


def _cpu_kernel_rasterize(*args, **kwargs):
    from image2sim.simulator.splatting.backends import cpu_kernel

    return cpu_kernel.rasterize(*args, **kwargs)


def _cpu_kernel_available() -> bool:
    from image2sim.simulator.splatting.backends import cpu_kernel

    return cpu_kernel.available()


def _cpu_kernel_error() -> str:
    from image2sim.simulator.splatting.backends import cpu_kernel

    return f"compiled CPU kernel: {cpu_kernel.load_error()}"


def _register_builtin_backends() -> None:
    """The built-in dispatch rule (see :mod:`.dispatch`): cpu > torch on CPU; gsplat > torch for
    pinhole cameras on CUDA; torch everywhere else; the dense reference only by name."""
    from image2sim.simulator.splatting.backends import gsplat_adapter

    everything = (EquirectCamera, PinholeCamera)
    builtins = [
        (Backend("reference", "rasterizer", _reference.rasterize, None, everything), ("dense",)),
        (
            Backend("torch", "rasterizer", _torch_tiles.rasterize, None, everything, auto_priority=0),
            ("torch_tiles",),
        ),
        (
            Backend(
                "cpu",
                "rasterizer",
                _cpu_kernel_rasterize,
                frozenset({"cpu"}),
                everything,
                available=_cpu_kernel_available,
                unavailable_reason=_cpu_kernel_error,
                auto_priority=100,
                warn_on_fallback=True,
            ),
            ("cpp", "cpu_kernel"),
        ),
        (
            Backend(
                "gsplat",
                "renderer",
                gsplat_adapter.render,
                frozenset({"cuda"}),
                (PinholeCamera,),
                available=gsplat_adapter.available,
                unavailable_reason=gsplat_adapter.unavailable_reason,
                auto_priority=100,
            ),
            (),
        ),
    ]
    for backend, aliases in builtins:
        register_backend(backend, aliases=aliases, replace=True)


_register_builtin_backends()


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    """Backends usable for tensors on ``device`` on this machine (default CPU; the compiled CPU
    kernel only if it builds/loads, gsplat only on CUDA and only if it imports)."""
    dev = device_type(torch.device(device))
    return [
        b.name for b in registered_backends() if (b.devices is None or dev in b.devices) and b.available()
    ]


def resolve_backend(backend: str, device: torch.device, camera: object | None = None) -> str:
    """Map a requested backend (or ``"auto"``) to a registered name for ``device`` and ``camera``.

    See :func:`image2sim.simulator.splatting.dispatch.resolve_backend`: on CPU the compiled kernel
    (falling back with a warning to ``torch`` if it cannot be built); on CUDA gsplat for pinhole
    cameras when importable, else ``torch``.
    """
    return _resolve(backend, device, camera)


def _check(name: str, t: torch.Tensor, shape: tuple, n: int | None) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"splat: {name} must be a torch.Tensor, got {type(t).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"splat: {name} must be floating point, got {t.dtype}")
    if t.dim() != len(shape) or any(s is not None and t.shape[i] != s for i, s in enumerate(shape)):
        want = (
            "("
            + ", ".join(
                "N" if s is None and i == 0 else ("C" if s is None else str(s)) for i, s in enumerate(shape)
            )
            + ")"
        )
        raise ValueError(f"splat: {name} must have shape {want}, got {tuple(t.shape)}")
    if n is not None and t.shape[0] != n:
        raise ValueError(f"splat: {name} has {t.shape[0]} rows but means has {n}")


def _nonfinite_rows(t: torch.Tensor) -> torch.Tensor | None:
    """Rows of ``t`` with a NaN/inf, or None when every value is finite.

    Fast path: a sum is finite only if every term is (NaN and inf propagate), so one reduction
    clears the common case; a non-finite sum (a bad value, or an overflow) takes the exact test.
    CPU float32/float64 tensors are summed by numpy, single-threaded: a parallel torch reduction
    here would leave torch's OpenMP workers spinning while the compiled kernel runs next, which on
    a shared machine doubled the CPU time per frame.
    """
    d = t.detach()
    if d.numel() == 0:
        return None
    if d.device.type == "cpu" and d.dtype in (torch.float32, torch.float64):
        with np.errstate(all="ignore"):  # overflow / inf - inf only send us to the exact test
            total = float(np.sum(d.numpy()))
    else:
        total = float(d.sum())
    if math.isfinite(total):
        return None
    return ~torch.isfinite(d).reshape(t.shape[0], -1).all(dim=1)


NONFINITE_MODES = ("raise", "cull", "checked")


def check_finite(owner: str, tensors: dict[str, torch.Tensor], hint: str = "") -> None:
    """Raise ``ValueError`` naming ``owner``, the field and the rows (then ``hint``) when any value of
    ``tensors`` (Gaussian fields, one row per Gaussian) is NaN or inf: ``splat``'s default check,
    and the one-off check behind ``splat(..., nonfinite="checked")``."""
    for name, t in tensors.items():
        rows = _nonfinite_rows(t) if len(t) else None
        if rows is not None and rows.any():
            first = int(torch.nonzero(rows)[0])
            raise ValueError(
                f"{owner}: {name} has non-finite values (NaN/inf) in {int(rows.sum())} of {len(t)} "
                f"Gaussians (first at index {first}){hint}"
            )


def splat(
    means: torch.Tensor,
    scales: torch.Tensor,
    quats: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    features: torch.Tensor | None,
    camera: EquirectCamera | PinholeCamera,
    cam_to_world: torch.Tensor,
    *,
    near: float = NEAR,
    far: float | None = None,
    background: torch.Tensor | float | None = None,
    backend: str = "auto",
    nonfinite: str = "raise",
    min_transmittance: float = T_MIN,
    cull: FrustumBlocks | None = None,
    compile_projection: bool = False,
) -> SplatOutput:
    """Render N feature Gaussians into B views of ``camera``; see the module docstring for semantics.

    Differentiable w.r.t. means, scales, quats, opacities, colors, features (and cam_to_world,
    background) with every backend. ``cull``: these Gaussians' spatial blocks
    (:class:`~image2sim.simulator.splatting.culling.FrustumBlocks`); the fused CPU inference path
    skips the blocks a pinhole view cannot see before projecting them. The image is the same with
    or without it; other paths ignore it. ``compile_projection``: project through
    ``torch.compile`` where gradients are needed (:func:`~.project.projector`: the same result,
    ~3.5x faster forward + backward after a one-off compile; for optimisation loops).
    """
    if not isinstance(camera, (EquirectCamera, PinholeCamera)):
        raise TypeError(f"splat: camera must be EquirectCamera or PinholeCamera, got {type(camera).__name__}")
    _check("means", means, (None, 3), None)
    n = means.shape[0]
    if features is None:
        features = means.new_zeros(n, 0)
    _check("scales", scales, (None, 3), n)
    _check("quats", quats, (None, 4), n)
    _check("opacities", opacities, (None,), n)
    _check("colors", colors, (None, 3), n)
    _check("features", features, (None, None), n)
    dtype, device = means.dtype, means.device
    for name, t in (
        ("scales", scales),
        ("quats", quats),
        ("opacities", opacities),
        ("colors", colors),
        ("features", features),
    ):
        if t.dtype != dtype or t.device != device:
            raise TypeError(f"splat: {name} is {t.dtype} on {t.device} but means is {dtype} on {device}")
    if not torch.is_tensor(cam_to_world):
        cam_to_world = torch.as_tensor(cam_to_world)
    if cam_to_world.shape[-2:] != (4, 4) or cam_to_world.dim() not in (2, 3):
        raise ValueError(f"splat: cam_to_world must be (4, 4) or (B, 4, 4), got {tuple(cam_to_world.shape)}")
    if not torch.isfinite(cam_to_world).all():
        raise ValueError("splat: cam_to_world contains NaN or inf")
    if not (near >= 0) or (far is not None and not far > near):
        raise ValueError(f"splat: need 0 <= near < far, got near={near}, far={far}")
    if nonfinite not in NONFINITE_MODES:
        raise ValueError(f"splat: nonfinite must be one of {NONFINITE_MODES}, got {nonfinite!r}")
    if not 0.0 < min_transmittance < 1.0:
        raise ValueError(f"splat: min_transmittance must lie in (0, 1), got {min_transmittance}")
    if cull is not None and cull.count != n:
        raise ValueError(f"splat: cull indexes {cull.count} Gaussians but {n} were given")

    fields = {
        "means": means,
        "scales": scales,
        "quats": quats,
        "opacities": opacities,
        "colors": colors,
        "features": features,
    }
    bad: torch.Tensor | None = None  # rows with a non-finite value (None: every row is finite)
    if nonfinite == "raise":
        check_finite("splat", fields, hint="; pass nonfinite='cull' to drop them")
    elif nonfinite == "cull" and n:
        for t in fields.values():
            rows = _nonfinite_rows(t)
            if rows is not None and rows.any():
                bad = rows if bad is None else bad | rows
    if bad is not None:  # replace culled rows by finite stand-ins so no NaN reaches any gradient
        keep = ~bad
        means = torch.where(keep[:, None], means, torch.zeros_like(means))
        scales = torch.where(keep[:, None], scales, torch.ones_like(scales))
        quats = torch.where(keep[:, None], quats, torch.ones_like(quats))
        opacities = torch.where(keep, opacities, torch.zeros_like(opacities))
        colors = torch.where(keep[:, None], colors, torch.zeros_like(colors))
        features = torch.where(keep[:, None], features, torch.zeros_like(features))

    if background is None:
        bg = torch.zeros(3, dtype=dtype, device=device)
    else:
        bg = torch.as_tensor(background, dtype=dtype, device=device).reshape(-1)
        if bg.numel() == 1:
            bg = bg.expand(3)
        if bg.numel() != 3:
            raise ValueError(f"splat: background must be a scalar or 3 values, got {bg.numel()}")
    c = features.shape[1]
    bg_all = torch.cat((bg, torch.zeros(1 + c, dtype=dtype, device=device)))

    name = resolve_backend(backend, device, camera)
    entry = _get_backend(name)
    poses = cam_to_world.unsqueeze(0) if cam_to_world.dim() == 2 else cam_to_world
    if entry.kind == "renderer":  # does projection and rasterisation itself (e.g. gsplat on CUDA)
        gaussians = (means, scales, quats, opacities, colors, features)
        rgb, depth, alpha, feats = entry.fn(*gaussians, camera, poses, near=near, far=far, background=bg)
        return SplatOutput(rgb=rgb, depth=depth, alpha=alpha, features=feats, backend=name)
    raster = entry.fn
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, scales, quats, opacities, colors, features, bg, cam_to_world)
    )
    images, alphas = [], []
    finite_mask = ~bad if bad is not None else None
    for pose in poses:
        if name == "cpu" and not needs_grad:  # fused C++ project + sort + bin + rasterise
            from image2sim.simulator.splatting.backends.cpu_kernel import render

            gaussians = (means, scales, quats, opacities, colors, features)
            blocks = None
            if cull is not None and isinstance(camera, PinholeCamera):
                blocks = cull.keep(camera, pose, near, far)
            image, alpha = render(
                *gaussians,
                camera,
                pose,
                bg_all,
                near=near,
                far=far,
                finite_mask=finite_mask,
                t_min=min_transmittance,
                blocks=blocks,
            )
            images.append(image)
            alphas.append(alpha)
            continue
        proj = projector(compile_projection and needs_grad)(
            means,
            scales,
            quats,
            opacities,
            camera,
            pose,
            near=near,
            far=far,
            finite_mask=finite_mask,
        )
        if name == "cpu":  # stable radix sort in C++ (same order as the torch ops below)
            from image2sim.simulator.splatting.backends.cpu_kernel import sort_valid

            idx = sort_valid(proj.depths, proj.valid)
        else:
            idx = torch.nonzero(proj.valid).squeeze(1)
            idx = idx[torch.argsort(proj.depths.detach()[idx], stable=True)]
        values = torch.cat((colors, proj.depths.unsqueeze(1), features), dim=1)[idx]
        kwargs = {"radii": proj.radii[idx]} if name in ("torch", "cpu") else {}
        image, alpha = raster(
            proj.means2d[idx],
            proj.conics[idx],
            opacities[idx],
            values,
            bg_all,
            camera.height,
            camera.width,
            proj.wrap_width,
            t_min=min_transmittance,
            **kwargs,
        )
        if idx.numel() == 0:  # keep the output in the autograd graph even when nothing is visible
            image = image + 0.0 * values.sum()
        images.append(image)
        alphas.append(alpha)
    if len(images) == 1:  # no copy for a single camera
        image, alpha = images[0].unsqueeze(0), alphas[0].unsqueeze(0)
    else:
        image, alpha = torch.stack(images), torch.stack(alphas)
    return SplatOutput(
        rgb=image[:, :3], depth=image[:, 3:4], alpha=alpha, features=image[:, 4:], backend=name
    )
