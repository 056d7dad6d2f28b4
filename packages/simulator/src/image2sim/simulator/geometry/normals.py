"""Surface normals from depth maps.

Two estimators with different jobs:

* :func:`sobel_normals` is the paper's ``SurfaceNormalEstimator`` (appendix, Stage 1): a cheap,
  image-space geometric prior fed to the encoder. Depth is smoothed by a 3x3 average pool, its
  gradients are taken with 5x5 Sobel filters scaled by 1/48, and ``(-dD/du, -dD/dv, 0.5)`` is
  L2-normalised. It is *not* a metric normal (it ignores the camera model); the constant z-bias
  damps lateral noise on flat regions.
* :func:`point_normals` gives true camera-frame surface normals: the depth map is back-projected
  to a point map, smoothed by the same 3x3 average, differentiated by the same 5x5 Sobel filters
  along u and v (two tangents) and crossed. For a plane this is exact (averages and differences of
  coplanar points stay in the plane), whatever the camera model. Normals face the camera; pixels
  whose 7x7 receptive field touches invalid depth get 0. Navigation uses these to find floors.
* :func:`hole_normals` completes those zeros where depth has holes (stereo, sensors): a valid
  pixel whose window touched a hole gets the normal of a plane fitted (PCA) to its valid,
  depth-consistent neighbours, when they are planar.

Border handling: images are edge-replicated; panoramas (``circular=True`` / an
:class:`EquirectCamera`) wrap across the longitude seam and, for even widths, continue across the
poles (row -1-k at column u is row k at column u + W/2, the true spherical neighbour), see
:func:`pad_equirect`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera

__all__ = [
    "sobel_kernels",
    "pad_equirect",
    "pad_image",
    "sobel_normals",
    "point_normals",
    "hole_normals",
    "SurfaceNormalEstimator",
]

SOBEL_SCALE = 1.0 / 48.0
"""The paper's scale of the 5x5 Sobel filters (sum of |weights| on one side of the kernel)."""

Z_BIAS = 0.5
"""The paper's constant z component appended before normalisation."""

_SMOOTH = 1  # 3x3 average pool -> 1 pixel of padding
_SOBEL = 2  # 5x5 Sobel -> 2 pixels of padding


def sobel_kernels(dtype: torch.dtype = torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The 5x5 Sobel kernels (S_u, S_v), each (5, 5), scaled by 1/48.

    S_u = outer([1, 4, 6, 4, 1], [-1, -2, 0, 2, 1]) / 48 responds positively to values increasing
    with the column u (cross-correlation, as ``F.conv2d`` computes); S_v = S_u^T for the row v.
    On a linear ramp f = a*u the response is (128/48) * a.
    """
    smooth = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=dtype, device=device)
    diff = torch.tensor([-1.0, -2.0, 0.0, 2.0, 1.0], dtype=dtype, device=device)
    su = torch.outer(smooth, diff) * SOBEL_SCALE
    return su, su.t().contiguous()


def pad_equirect(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad equirectangular maps (B, C, H, W) by ``pad`` pixels on every side, spherically.

    Columns wrap around the longitude seam. Rows continue over the poles when W is even: the row
    -1-k above the top is row k shifted by half a turn (W/2 columns), which is where the great
    circle through the pole continues; the same for the bottom. For odd W (no pixel half a turn
    away) rows are edge-replicated instead. Requires pad <= W and pad <= H.
    """
    if pad == 0:
        return x
    H, W = x.shape[-2:]
    if pad > W or pad > H:
        raise ValueError(f"pad_equirect: pad {pad} exceeds the map size {H}x{W}")
    # One allocation and slice copies: several times faster than chains of cat/roll on big panoramas.
    out = x.new_empty((*x.shape[:-2], H + 2 * pad, W + 2 * pad))
    out[..., pad : pad + H, pad : pad + W] = x
    out[..., pad : pad + H, :pad] = x[..., W - pad :]
    out[..., pad : pad + H, pad + W :] = x[..., :pad]
    if W % 2 == 0:
        # Over a pole: row -1-k is row k half a turn away (the padded columns included, so the
        # corners are true neighbours too).
        cols = torch.remainder(torch.arange(W + 2 * pad, device=x.device) - pad + W // 2, W)
        src = torch.cat((x[..., :pad, :], x[..., H - pad :, :]), dim=-2)
        turned = src.index_select(-1, cols)
        out[..., :pad, :] = turned[..., :pad, :].flip(-2)
        out[..., pad + H :, :] = turned[..., pad:, :].flip(-2)
    else:
        out[..., :pad, :] = out[..., pad : pad + 1, :]
        out[..., pad + H :, :] = out[..., pad + H - 1 : pad + H, :]
    return out


def pad_image(x: torch.Tensor, pad: int, circular: bool) -> torch.Tensor:
    """Pad (B, C, H, W) maps: spherical (:func:`pad_equirect`) if ``circular`` else edge-replicate."""
    if circular:
        return pad_equirect(x, pad)
    return F.pad(x, (pad, pad, pad, pad), mode="replicate")


def _channel_norm(x: torch.Tensor) -> torch.Tensor:
    """L2 norm over the channel dimension of (B, 3, H, W), keepdim.

    Written out because ``linalg.vector_norm(dim=1)`` is a strided reduction that is ~50x slower
    on CPU for image-shaped tensors.
    """
    return torch.sqrt((x * x).sum(dim=1, keepdim=True))


def _cross_channels(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the channel dimension of (B, 3, H, W) tensors (faster than linalg.cross)."""
    ax, ay, az = a[:, 0:1], a[:, 1:2], a[:, 2:3]
    bx, by, bz = b[:, 0:1], b[:, 1:2], b[:, 2:3]
    return torch.cat((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim=1)


def _check_depth(depth: torch.Tensor, name: str) -> None:
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ValueError(f"{name}: depth must be (B, 1, H, W), got shape {tuple(depth.shape)}")
    if not depth.is_floating_point():
        raise ValueError(f"{name}: depth must be a floating-point tensor, got {depth.dtype}")


def _taps(x: torch.Tensor, weights: tuple[float, ...], dim: int, size: int) -> torch.Tensor:
    """Valid 1-D correlation along ``dim`` as a sum of shifted slices (zero taps skipped)."""
    out = None
    for k, w in enumerate(weights):
        if w == 0:
            continue
        term = x.narrow(dim, k, size) * w
        out = term if out is None else out + term
    return out


def _smooth_and_sobel(x: torch.Tensor, circular: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """3x3 average pool then the two 5x5 Sobel filters, per channel; returns (d/du, d/dv), same size.

    Both filters are separable (box3 x box3; binomial5 x derivative5), so they run as 1-D passes
    of shifted-slice sums: the same numbers as the 2-D kernels of :func:`sobel_kernels` (the parity
    test checks it against a pixel loop) at a fraction of the cost of a grouped ``conv2d`` on CPU.
    """
    H, W = x.shape[-2:]
    padded = pad_image(x, _SMOOTH, circular)
    box = (1.0, 1.0, 1.0)
    smoothed = _taps(_taps(padded, box, -2, H), box, -1, W) / 9.0
    padded = pad_image(smoothed, _SOBEL, circular)
    binomial, derivative = (1.0, 4.0, 6.0, 4.0, 1.0), (-1.0, -2.0, 0.0, 2.0, 1.0)
    gu = _taps(_taps(padded, binomial, -2, H), derivative, -1, W) * SOBEL_SCALE
    gv = _taps(_taps(padded, derivative, -2, H), binomial, -1, W) * SOBEL_SCALE
    return gu, gv


def sobel_normals(depth: torch.Tensor, circular: bool = False) -> torch.Tensor:
    """The paper's surface-normal estimator: depth (B, 1, H, W) -> unit "normals" (B, 3, H, W).

    ``n = normalize(-S_u * avg3(D), -S_v * avg3(D), 0.5)`` with the 1/48-scaled 5x5 Sobel filters
    of :func:`sobel_kernels`. Gradients are in depth units per pixel (times 128/48), so the output
    is an image-space feature, not a metric normal (use :func:`point_normals` for that). Invalid
    (zero) depth is not masked, exactly as in the paper. ``circular=True`` pads panoramas
    spherically (seam wrap, pole continuation for even W); otherwise borders are edge-replicated.
    """
    _check_depth(depth, "sobel_normals")
    gu, gv = _smooth_and_sobel(depth, circular)
    n = torch.cat((-gu, -gv, torch.full_like(gu, Z_BIAS)), dim=1)
    return n / _channel_norm(n)  # >= 0.5, never zero


def point_normals(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Camera-frame unit surface normals (B, 3, H, W) from depth (B, 1, H, W), facing the camera.

    The depth is back-projected with ``camera`` (range for an :class:`EquirectCamera`, z for a
    pinhole), the point map is smoothed by a 3x3 average, the 5x5 Sobel filters give the tangents
    dP/du and dP/dv, and n = dP/du x dP/dv is normalised and flipped so that n . P < 0 (towards
    the camera). A pixel gets n = 0 when any depth in its 7x7 receptive field is 0 or non-finite,
    or when the tangents are degenerate. Panoramas are padded spherically (see
    :func:`pad_equirect`).
    """
    _check_depth(depth, "point_normals")
    B, _, H, W = depth.shape
    if (H, W) != (camera.height, camera.width):
        raise ValueError(f"point_normals: depth is {H}x{W} but the camera is {camera.height}x{camera.width}")
    circular = isinstance(camera, EquirectCamera)
    valid, clean, points = _point_map(depth, camera)
    tu, tv = _smooth_and_sobel(points, circular)
    n = _cross_channels(tu, tv)
    norm = _channel_norm(n)
    # Degenerate tangents (e.g. all points equal) give no normal; the threshold is relative to the
    # tangent lengths so it is scale-free.
    scale = _channel_norm(tu) * _channel_norm(tv)
    ok = norm > 1e3 * torch.finfo(depth.dtype).eps * scale
    n = n / norm.clamp_min(torch.finfo(depth.dtype).tiny)
    facing = (n * points).sum(dim=1, keepdim=True)
    n = torch.where(facing > 0, -n, n)
    # Invalid if any input of the 3x3-then-5x5 receptive field is invalid (padded the same way).
    keep = ok & torch.isfinite(n).all(dim=1, keepdim=True)
    if not bool(valid.all()):
        invalid = (~valid).to(depth.dtype)
        invalid = F.max_pool2d(pad_image(invalid, _SMOOTH, circular), kernel_size=3, stride=1)
        invalid = F.max_pool2d(pad_image(invalid, _SOBEL, circular), kernel_size=5, stride=1)
        keep = keep & (invalid == 0)
    return torch.where(keep, n, torch.zeros_like(n))


def _point_map(depth: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(valid (B, 1, H, W), depth with 0 where invalid, camera-frame points (B, 3, H, W))."""
    valid = torch.isfinite(depth) & (depth > 0)
    clean = torch.where(valid, depth, torch.zeros_like(depth))
    return valid, clean, camera.unproject(clean[:, 0]).permute(0, 3, 1, 2)


def hole_normals(
    depth: torch.Tensor,
    camera: Camera,
    normals: torch.Tensor | None = None,
    radius: int = 2,
    min_valid: int = 8,
    max_rel_depth: float = 0.1,
    planarity: float = 0.05,
) -> torch.Tensor:
    """:func:`point_normals`, completed at valid pixels whose receptive field touched a hole.

    Such a pixel (its normal is 0 in ``normals``, computed here when None) gets the smallest
    principal axis of the camera-frame points of its ``(2 radius + 1)^2`` window (inside the image;
    across the seam and poles of a panorama) that have depth
    within ``max_rel_depth`` of its own (the other side of a depth edge is left out), oriented
    towards the camera; it stays 0 with fewer than ``min_valid`` such points or when they are not
    planar (smallest eigenvalue above ``planarity`` x the middle one). On a plane the result is
    exact. Stereo depth with holes would otherwise lose every normal within 3 pixels of a hole:
    on a lifted capture most floor pixels (docs/navigation.md).
    """
    n = point_normals(depth, camera) if normals is None else normals
    valid = torch.isfinite(depth) & (depth > 0)
    need = valid & (n.abs().sum(dim=1, keepdim=True) == 0)
    if not bool(need.any()):
        return n
    B, _, H, W = depth.shape
    circular = isinstance(camera, EquirectCamera)
    _, clean, points = _point_map(depth, camera)
    k = 2 * radius + 1
    # Panoramas continue across the seam and the poles; beyond a pinhole image there is no depth
    # (replicated border points would count twice and look planar).
    pad = (lambda x: pad_equirect(x, radius)) if circular else (lambda x: F.pad(x, (radius,) * 4))
    window_points = F.unfold(pad(points), k).view(B, 3, k * k, H, W)
    window_depth = F.unfold(pad(clean), k).view(B, k * k, H, W)
    b, _, v, u = need.nonzero(as_tuple=True)
    p = window_points[b, :, :, v, u]  # (M, 3, K)
    d = window_depth[b, :, v, u]  # (M, K)
    centre = clean[b, 0, v, u][:, None]
    w = ((d > 0) & ((d - centre).abs() <= max_rel_depth * centre)).to(p.dtype)
    count = w.sum(dim=1)
    mean = (p * w[:, None]).sum(dim=2) / count.clamp_min(1.0)[:, None]
    centred = (p - mean[:, :, None]) * w[:, None]
    evals, evecs = torch.linalg.eigh((centred @ centred.transpose(1, 2)).double())
    normal = evecs[:, :, 0].to(p.dtype)
    normal = torch.where((normal * points[b, :, v, u]).sum(dim=1, keepdim=True) > 0, -normal, normal)
    ok = (count >= min_valid) & (evals[:, 0] <= planarity * evals[:, 1])
    out = n.clone()
    out[b, :, v, u] = torch.where(ok[:, None], normal, torch.zeros_like(normal))
    return out


class SurfaceNormalEstimator(torch.nn.Module):
    """The paper's ``SurfaceNormalEstimator`` as a parameter-free module wrapping :func:`sobel_normals`.

    ``circular`` selects panorama padding (seam wrap + pole continuation) for equirectangular inputs.
    """

    def __init__(self, circular: bool = False) -> None:
        super().__init__()
        self.circular = bool(circular)

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        """depth (B, 1, H, W) -> unit normals (B, 3, H, W)."""
        return sobel_normals(depth, circular=self.circular)

    def extra_repr(self) -> str:
        return f"circular={self.circular}"
