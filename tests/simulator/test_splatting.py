"""Splatting: every backend against the dense reference, analytic footprints, gradients, hard cases."""

from __future__ import annotations

import math

import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.splatting import SplatOutput, available_backends, splat
from image2sim.simulator.splatting.backends import reference
from image2sim.simulator.splatting.project import (
    ALPHA_MAX,
    ALPHA_MIN,
    CUTOFF_SIGMA,
    DILATION,
    T_MIN,
    equirect_jacobian,
    project_gaussians,
)

BACKENDS = [b for b in available_backends() if b != "reference"]
EQ = EquirectCamera(24, 48)
PH = PinholeCamera(fx=30.0, fy=28.0, cx=21.0, cy=13.5, height=26, width=40)
EYE = torch.eye(4, dtype=torch.float64)


def make_scene(n: int, c: int, camera, seed: int, dtype=torch.float64, opaque: bool = False):
    """Random Gaussians around (equirect) or in front of (pinhole) an identity camera."""
    g = torch.Generator().manual_seed(seed)
    if isinstance(camera, EquirectCamera):
        d = torch.randn(n, 3, generator=g, dtype=torch.float64)
        means = (
            d / d.norm(dim=1, keepdim=True) * (1.0 + 2.0 * torch.rand(n, 1, generator=g, dtype=torch.float64))
        )
    else:
        means = torch.stack(
            (
                torch.rand(n, generator=g, dtype=torch.float64) * 3 - 1.5,
                torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1.0,
                torch.rand(n, generator=g, dtype=torch.float64) * 3 + 0.8,
            ),
            dim=1,
        )
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.25 + 0.02
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = (0.6, 1.0) if opaque else (0.05, 0.9)
    opac = lo + (hi - lo) * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    feats = torch.randn(n, c, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, scales, quats, opac, colors, feats)]


def planes(out: SplatOutput) -> dict[str, torch.Tensor]:
    return {"rgb": out.rgb, "depth": out.depth, "alpha": out.alpha, "features": out.features}


def loss_of(out: SplatOutput, seed: int = 7) -> torch.Tensor:
    """A random linear functional of every output plane (exercises every output gradient)."""
    g = torch.Generator().manual_seed(seed)
    total = 0.0
    for t in planes(out).values():
        total = total + (torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.dtype) * t).sum()
    return total


def assert_matches_reference(out: SplatOutput, ref: SplatOutput, inputs=None) -> None:
    """Every non-empty output plane within 1e-4 (depth: relative to its range) and, given the
    ``inputs`` that require gradients, every gradient within 1e-3 of its largest magnitude."""
    rng = float(ref.normalized_depth().max())
    for name, want in planes(ref).items():
        if want.numel() == 0:
            continue
        tol = 1e-4 * max(rng, 1.0) if name == "depth" else 1e-4
        assert (planes(out)[name] - want).abs().max() <= tol, name
    if inputs is not None:
        g_ref = torch.autograd.grad(loss_of(ref), inputs)
        g_out = torch.autograd.grad(loss_of(out), inputs)
        for got, want in zip(g_out, g_ref, strict=True):
            assert (got - want).abs().max() <= 1e-3 * want.abs().max().clamp_min(1e-6)


# --- an independent per-pixel oracle (plain Python loops) for the compositing rules -------------


def loop_oracle(means2d, conics, opac, values, bg, height, width, wrap, t_min=T_MIN):
    """Literal transcription of the semantics, one pixel and one Gaussian at a time."""
    d = values.shape[1]
    img = torch.zeros(d, height, width, dtype=torch.float64)
    alpha = torch.zeros(1, height, width, dtype=torch.float64)
    for j in range(height):
        for i in range(width):
            T, acc, asum = 1.0, [0.0] * d, 0.0
            for k in range(means2d.shape[0]):
                dx = i + 0.5 - float(means2d[k, 0])
                if wrap:
                    dx = (dx + wrap / 2) % wrap - wrap / 2
                dy = j + 0.5 - float(means2d[k, 1])
                A, B, C = (float(x) for x in conics[k])
                q = A * dx * dx + 2 * B * dx * dy + C * dy * dy
                if q > CUTOFF_SIGMA**2:
                    continue
                a = min(ALPHA_MAX, float(opac[k]) * math.exp(-0.5 * q))
                if a < ALPHA_MIN:
                    continue
                for c in range(d):
                    acc[c] += a * T * float(values[k, c])
                asum += a * T
                T *= 1 - a
                if T < t_min:
                    break
            for c in range(d):
                img[c, j, i] = acc[c] + (1 - asum) * float(bg[c])
            alpha[0, j, i] = asum
    return img, alpha


@pytest.mark.parametrize("wrap", [0.0, 12.0])
@pytest.mark.parametrize("t_min", [T_MIN, 0.05])
def test_dense_reference_matches_loop_oracle(wrap, t_min):
    g = torch.Generator().manual_seed(3)
    m = 7
    means2d = torch.rand(m, 2, generator=g, dtype=torch.float64) * torch.tensor([12.0, 8.0])
    means2d[0, 0] = 0.2  # straddles the seam when wrapping
    cov = torch.rand(m, 3, generator=g, dtype=torch.float64) * torch.tensor([6.0, 1.0, 6.0]) + torch.tensor(
        [0.5, -0.5, 0.5]
    )
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = torch.stack((cov[:, 2] / det, -cov[:, 1] / det, cov[:, 0] / det), dim=1)
    opac = torch.rand(m, generator=g, dtype=torch.float64) * 0.5 + 0.5
    opac[1] = 1.0  # exercises the 0.99 clamp and early termination
    values = torch.randn(m, 4, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.1, 0.2, 0.3, 0.0], dtype=torch.float64)
    want = loop_oracle(means2d, conics, opac, values, bg, 8, 12, wrap, t_min)
    got = reference.rasterize(means2d, conics, opac, values, bg, 8, 12, wrap, t_min)
    for w, h in zip(want, got, strict=True):
        torch.testing.assert_close(h, w, atol=1e-12, rtol=0)


# --- parity of every backend with the dense reference --------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
@pytest.mark.parametrize("c", [0, 3, 16])
@pytest.mark.parametrize("seed", [0, 1])
def test_backend_matches_reference_values(backend, camera, c, seed):
    scene = make_scene(60, c, camera, seed, dtype=torch.float32, opaque=seed == 1)
    bg = torch.tensor([0.2, 0.5, 0.9])
    ref = splat(*scene, camera, EYE, background=bg, backend="reference")
    out = splat(*scene, camera, EYE, background=bg, backend=backend)
    assert out.backend == backend
    assert ref.alpha.max() > 0.5  # the scene is not empty
    rng = float(ref.normalized_depth().max())
    for name, want in planes(ref).items():
        got = planes(out)[name]
        assert got.shape == want.shape
        tol = 1e-4 * max(rng, 1.0) if name == "depth" else 1e-4
        if want.numel() == 0:
            continue
        assert (got - want).abs().max() <= tol, (name, float((got - want).abs().max()))


# --- min_transmittance: the inference option that finishes pixels earlier ------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
@pytest.mark.parametrize("grad", [False, True], ids=["fused", "training"])
def test_backends_match_reference_at_a_larger_min_transmittance(backend, camera, grad):
    scene = make_scene(80, 3, camera, 4, dtype=torch.float32, opaque=True)
    if grad:
        scene = [t.requires_grad_() for t in scene]
    bg = torch.tensor([0.2, 0.5, 0.9])
    with torch.set_grad_enabled(grad):
        ref = splat(*scene, camera, EYE, background=bg, backend="reference", min_transmittance=0.02)
        out = splat(*scene, camera, EYE, background=bg, backend=backend, min_transmittance=0.02)
    assert_matches_reference(out, ref, scene if grad else None)


@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
@pytest.mark.parametrize("t_min", [1e-2, 0.1])
def test_min_transmittance_moves_every_output_by_at_most_its_bound(camera, t_min):
    """A finished pixel leaves out Gaussians whose weights sum to less than T < t_min, and the
    background's share shrinks by as much: each plane moves by at most t_min times the spread of its
    values (the background counted as one of them)."""
    scene = make_scene(120, 4, camera, 5, dtype=torch.float64, opaque=True)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    exact = splat(*scene, camera, EYE, background=bg, backend="reference")
    early = splat(*scene, camera, EYE, background=bg, backend="reference", min_transmittance=t_min)
    means, _, _, _, colors, feats = scene
    rng = means.norm(dim=1).max()  # depth values lie in [0, max range]; background depth is 0
    spread = {
        "rgb": torch.maximum(colors.max(0).values, bg) - torch.minimum(colors.min(0).values, bg),
        "depth": rng.reshape(1),
        "alpha": torch.ones(1, dtype=torch.float64),
        "features": feats.max(0).values.clamp_min(0) - feats.min(0).values.clamp_max(0),
    }
    moved = 0.0
    for name, want in planes(exact).items():
        diff = (planes(early)[name] - want).abs().amax(dim=(0, 2, 3))  # per channel
        assert (diff <= t_min * spread[name] + 1e-12).all(), (name, diff, t_min * spread[name])
        moved = max(moved, float(diff.max()))
    assert moved > 0.0  # the option changed something: the scene has pixels that finish early


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_backend_gradients_match_reference(backend, camera, dtype):
    scene = [t.requires_grad_() for t in make_scene(40, 5, camera, seed=2, dtype=dtype, opaque=True)]
    bg = torch.tensor([0.3, 0.1, 0.7], dtype=dtype, requires_grad=True)
    grads = {}
    for b in ("reference", backend):
        out = splat(*scene, camera, EYE, background=bg, backend=b)
        grads[b] = torch.autograd.grad(loss_of(out), scene + [bg])
    names = ["means", "scales", "quats", "opacities", "colors", "features", "background"]
    for name, got, want in zip(names, grads[backend], grads["reference"], strict=True):
        assert torch.isfinite(got).all(), name
        rel = (got - want).abs().max() / want.abs().max().clamp_min(1e-12)
        assert rel <= 1e-3, (name, float(rel))
        assert want.abs().max() > 0, name  # the gradient is not trivially zero


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize(
    "camera", [EquirectCamera(5, 10), PinholeCamera(6.0, 6.0, 4.0, 3.0, 6, 8)], ids=["equirect", "pinhole"]
)
def test_gradcheck_float64(backend, camera):
    g = torch.Generator().manual_seed(5)
    if isinstance(camera, EquirectCamera):
        means = torch.tensor([[0.3, -0.2, 1.5], [-1.2, 0.3, -0.4], [0.1, 0.1, 1.8]], dtype=torch.float64)
    else:
        means = torch.tensor([[0.1, -0.1, 1.5], [-0.3, 0.2, 2.0], [0.2, 0.1, 2.5]], dtype=torch.float64)
    scales = torch.tensor([[0.3, 0.2, 0.25], [0.4, 0.3, 0.2], [0.35, 0.3, 0.3]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64)
    opac = torch.tensor([0.7, 0.5, 0.8], dtype=torch.float64)
    colors = torch.rand(3, 3, generator=g, dtype=torch.float64)
    feats = torch.randn(3, 2, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    inputs = tuple(t.requires_grad_() for t in (means, scales, quats, opac, colors, feats, bg))

    def fn(*args):
        out = splat(*args[:6], camera, EYE, background=args[6], backend=backend)
        return out.rgb, out.depth, out.alpha, out.features

    # Full Jacobians for the ground truth; random projections (fast mode) for the other backends,
    # whose full gradients are compared with the reference in test_backend_gradients_match_reference.
    fast = backend != "reference"
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=fast)


# --- analytic footprints ---------------------------------------------------------------------------


def _closed_form(dx, dy, var_u, var_v, opacity):
    q = dx * dx / var_u + dy * dy / var_v
    a = torch.clamp(opacity * torch.exp(-0.5 * q), max=ALPHA_MAX)
    return torch.where((q <= CUTOFF_SIGMA**2) & (a >= ALPHA_MIN), a, torch.zeros_like(a))


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_pinhole_axis_aligned_gaussian_has_expected_footprint(backend):
    cam = PinholeCamera(fx=100.0, fy=80.0, cx=32.0, cy=24.0, height=48, width=64)
    z, sx, sy = 2.0, 0.1, 0.06
    means = torch.tensor([[0.0, 0.0, z]], dtype=torch.float64)
    scales = torch.tensor([[sx, sy, 0.3]], dtype=torch.float64)  # z extent is invisible on the axis
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    out = splat(
        means,
        scales,
        quats,
        torch.tensor([0.8], dtype=torch.float64),
        torch.tensor([[1.0, 0.5, 0.25]], dtype=torch.float64),
        None,
        cam,
        EYE,
        backend=backend,
    )
    var_u = (cam.fx * sx / z) ** 2 + DILATION
    var_v = (cam.fy * sy / z) ** 2 + DILATION
    v, u = torch.meshgrid(
        torch.arange(48, dtype=torch.float64) + 0.5,
        torch.arange(64, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    want = _closed_form(u - cam.cx, v - cam.cy, var_u, var_v, 0.8)
    torch.testing.assert_close(out.alpha[0, 0], want, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.depth[0, 0], want * z, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.rgb[0, 1], want * 0.5, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.normalized_depth()[0, 0][want > 0], torch.full_like(want[want > 0], z))
    assert out.features.shape == (1, 0, 48, 64)


def test_pinhole_off_axis_centre():
    cam = PinholeCamera(fx=100.0, fy=100.0, cx=32.0, cy=32.0, height=64, width=64)
    means = torch.tensor([[0.2, -0.1, 2.0]], dtype=torch.float64)  # -> (u, v) = (42, 27)
    out = splat(
        means,
        torch.full((1, 3), 0.03, dtype=torch.float64),
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.tensor([0.9], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64),
        None,
        cam,
        EYE,
    )
    a = out.alpha[0, 0]
    v, u = torch.meshgrid(
        torch.arange(64.0, dtype=torch.float64) + 0.5,
        torch.arange(64.0, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    centre = ((a * u).sum() / a.sum(), (a * v).sum() / a.sum())
    assert abs(float(centre[0]) - 42.0) < 1e-6 and abs(float(centre[1]) - 27.0) < 1e-6


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_equirect_isotropic_gaussian_ahead(backend):
    cam = EquirectCamera(64, 128)
    r, s = 2.0, 0.08
    means = torch.tensor([[0.0, 0.0, r]], dtype=torch.float64)
    out = splat(
        means,
        torch.full((1, 3), s, dtype=torch.float64),
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.tensor([0.7], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64),
        None,
        cam,
        EYE,
        backend=backend,
    )
    var_u = (cam.width / (2 * math.pi) * s / r) ** 2 + DILATION
    var_v = (cam.height / math.pi * s / r) ** 2 + DILATION
    v, u = torch.meshgrid(
        torch.arange(64, dtype=torch.float64) + 0.5,
        torch.arange(128, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    want = _closed_form(u - 64.0, v - 32.0, var_u, var_v, 0.7)
    torch.testing.assert_close(out.alpha[0, 0], want, atol=1e-10, rtol=0)
    torch.testing.assert_close(out.depth[0, 0], want * r, atol=1e-10, rtol=0)


def test_equirect_jacobian_matches_camera_and_finite_differences():
    cam = EquirectCamera(32, 64)
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(50, 3, generator=g, dtype=torch.float64)
    uv, jac = equirect_jacobian(pts, cam)
    torch.testing.assert_close(jac, cam.pixel_jacobian(pts), atol=1e-9, rtol=1e-9)
    want_uv, _, _ = cam.project(pts)
    torch.testing.assert_close(uv, want_uv, atol=1e-9, rtol=0)
    eps = 1e-6
    for k in range(3):
        dp = torch.zeros(3, dtype=torch.float64)
        dp[k] = eps
        (up, _), (um, _) = equirect_jacobian(pts + dp, cam), equirect_jacobian(pts - dp, cam)
        diff = up - um
        diff[:, 0] = (diff[:, 0] + cam.width / 2) % cam.width - cam.width / 2  # seam
        torch.testing.assert_close(diff / (2 * eps), jac[:, :, k], atol=1e-4, rtol=1e-5)


# --- hard cases ----------------------------------------------------------------------------------


def _one(mean, scale=0.1, opacity=0.8, dtype=torch.float64, c=2):
    return [
        torch.tensor([mean], dtype=dtype),
        torch.full((1, 3), scale, dtype=dtype),
        torch.tensor([[0.9, 0.1, -0.2, 0.3]], dtype=dtype),
        torch.tensor([opacity], dtype=dtype),
        torch.tensor([[0.9, 0.4, 0.1]], dtype=dtype),
        torch.ones(1, c, dtype=dtype),
    ]


def _assert_finite_with_grads(scene, camera, pose=EYE, backend="reference", **kw):
    scene = [t.clone().requires_grad_() for t in scene]
    out = splat(*scene, camera, pose, backend=backend, **kw)
    for name, t in planes(out).items():
        assert torch.isfinite(t).all(), name
    grads = torch.autograd.grad(loss_of(out), scene, allow_unused=True)
    for g in grads:
        assert g is None or torch.isfinite(g).all()
    return out, grads


def _yaw_pose(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    pose = torch.eye(4, dtype=torch.float64)
    # rotation about the camera y axis (down): turns the camera to the right for positive angles
    pose[:3, :3] = torch.tensor(
        [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64
    )
    return pose


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_seam_gaussian_matches_rotated_copy(backend):
    cam = EquirectCamera(24, 48)  # 30 degrees = 4 pixels
    scene = _one([0.0, 0.1, -2.0], scale=0.25)  # lon = 180 degrees: centred on the seam
    on_seam, _ = _assert_finite_with_grads(scene, cam, backend=backend)
    away, _ = _assert_finite_with_grads(scene, cam, pose=_yaw_pose(-30.0), backend=backend)
    a = on_seam.alpha[0, 0]
    assert a[:, 0].max() > 0.1 and a[:, -1].max() > 0.1  # visible on both edges
    torch.testing.assert_close(on_seam.alpha, torch.roll(away.alpha, shifts=-4, dims=-1), atol=1e-9, rtol=0)
    torch.testing.assert_close(on_seam.rgb, torch.roll(away.rgb, shifts=-4, dims=-1), atol=1e-9, rtol=0)
    assert torch.roll(away.alpha, shifts=-4, dims=-1)[0, 0, :, 0].max() > 0.1


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize("where", ["zenith", "nadir"])
def test_pole_gaussians_are_finite_and_span_the_width(backend, where):
    cam = EquirectCamera(16, 32)
    y = -2.0 if where == "zenith" else 2.0  # camera y points down
    out, grads = _assert_finite_with_grads(_one([0.0, y, 0.0], scale=0.2), cam, backend=backend)
    row = out.alpha[0, 0, 0 if where == "zenith" else -1].detach()
    # On the pole the longitude is undefined: the footprint wraps around it and covers the pole row
    # uniformly (no peak at an arbitrary longitude, which made the gradients blow up nearby).
    assert row.min() > 0.5 and float(row.max() - row.min()) < 1e-6
    assert any(float(g.abs().sum()) > 0 for g in grads)
    ref = splat(*_one([0.0, y, 0.0], scale=0.2), cam, EYE, backend="reference")
    torch.testing.assert_close(out.alpha, ref.alpha, atol=1e-9, rtol=0)
    # Slightly off the pole: still finite and still clamped to the full width.
    _assert_finite_with_grads(_one([1e-9, y, -1e-9], scale=0.2), cam, backend=backend)


POLE_GRADIENT_BOUND = 1e4
"""|dL/dmean| for a unit-scale Gaussian 2 m from the camera, L = the sum of every output plane: about
1.7e3 anywhere; it grew as ~5e-6/rho near a pole (4.9e23 at rho = 1e-29 m) before (issue 23)."""


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("where", ["zenith", "nadir"])
@pytest.mark.parametrize("shape", ["isotropic", "rotated_anisotropic"])
def test_gradients_stay_bounded_as_a_gaussian_approaches_a_pole(backend, dtype, where, shape):
    cam = EquirectCamera(32, 64)
    y = -2.0 if where == "zenith" else 2.0
    scales = [1.0, 1.0, 1.0] if shape == "isotropic" else [1.0, 0.3, 0.6]
    quat = [1.0, 0.0, 0.0, 0.0] if shape == "isotropic" else [0.9, 0.1, -0.2, 0.3]
    for rho in (1.0, 1e-2, 1e-4, 1e-6, 1e-9, 1e-12, 1e-20, 1e-29, 1e-31, 1e-45, 0.0):
        for dx, dz in ((1.0, 0.0), (0.6, -0.8)):
            mean = torch.tensor([[rho * dx, y, rho * dz]], dtype=dtype, requires_grad=True)
            out = splat(
                mean,
                torch.tensor([scales], dtype=dtype),
                torch.tensor([quat], dtype=dtype),
                torch.tensor([0.8], dtype=dtype),
                torch.tensor([[0.9, 0.4, 0.1]], dtype=dtype),
                torch.ones(1, 2, dtype=dtype),
                cam,
                torch.eye(4, dtype=dtype),
                backend=backend,
            )
            loss = sum(t.sum() for t in planes(out).values())
            (grad,) = torch.autograd.grad(loss, mean)
            assert torch.isfinite(grad).all() and grad.abs().max() <= POLE_GRADIENT_BOUND, (rho, grad)


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize(
    "camera",
    [EquirectCamera(16, 32), PinholeCamera(10.0, 10.0, 8.0, 8.0, 16, 16)],
    ids=["equirect", "pinhole"],
)
def test_gaussian_one_millimetre_from_camera(backend, camera):
    scene = _one([0.0, 0.0, 1e-3], scale=0.01)
    out, _ = _assert_finite_with_grads(scene, camera, backend=backend)
    assert out.alpha.max() == 0  # culled by near = 0.05
    out, _ = _assert_finite_with_grads(scene, camera, backend=backend, near=0.0)
    assert out.alpha.max() > 0.5  # fills the view when not culled


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize(
    "camera",
    [EquirectCamera(16, 32), PinholeCamera(10.0, 10.0, 8.0, 8.0, 16, 16)],
    ids=["equirect", "pinhole"],
)
@pytest.mark.parametrize("scale", [1e-8, 1e3])
def test_extreme_scales(backend, camera, scale):
    out, _ = _assert_finite_with_grads(_one([0.1, 0.05, 2.0], scale=scale), camera, backend=backend)
    if scale > 1:
        if isinstance(camera, PinholeCamera):
            assert out.alpha.min() > 0.7  # covers the whole view
        else:  # u extent clamped to the full width, v extent covers every row
            assert (out.alpha > 0).sum(dim=-1).min() >= camera.width - 2
            assert out.alpha[..., camera.width // 2].min() > 0.7
    else:
        assert 0 < (out.alpha > 0).sum() <= 16  # a dot: only the 0.3 px^2 dilation is left (radius < 2 px)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "camera",
    [EquirectCamera(16, 32), PinholeCamera(10.0, 10.0, 8.0, 8.0, 16, 16)],
    ids=["equirect", "pinhole"],
)
@pytest.mark.parametrize("scale", [3e17, 1e18, 1e19, 1e30, 1e38])
def test_backends_agree_on_absurd_scales(backend, camera, scale):
    """A metres-to-light-years Gaussian is a uniform veil in the reference; the compiled kernel once
    dropped it (a >= 9.2e18 px footprint overflowed int64 in its row range, issue 23)."""
    scene = [t.float() for t in _one([0.1, 0.05, 2.0], scale=scale)]
    scene += [t.float() for t in _one([0.3, -0.1, 3.0], scale=0.2, opacity=0.6)]
    scene = [torch.cat((a, b)).requires_grad_() for a, b in zip(scene[:6], scene[6:], strict=True)]
    ref = splat(*scene, camera, EYE.float(), backend="reference")
    out = splat(*scene, camera, EYE.float(), backend=backend)
    # The veil covers the view in the reference (a panorama's u extent is clamped to the width).
    covered = ref.alpha if isinstance(camera, PinholeCamera) else ref.alpha[..., camera.width // 2]
    assert covered.min() > 0.7
    for name, t in planes(out).items():
        torch.testing.assert_close(t, planes(ref)[name], atol=1e-5, rtol=1e-5, msg=name)
    for g, g_ref in zip(
        torch.autograd.grad(loss_of(out), scene, allow_unused=True),
        torch.autograd.grad(loss_of(ref), scene, allow_unused=True),
        strict=True,
    ):
        if g_ref is not None:
            assert g is not None and torch.isfinite(g).all()
            torch.testing.assert_close(g, g_ref, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_opacity_zero_and_one(backend):
    cam = PinholeCamera(10.0, 10.0, 8.5, 8.5, 16, 16)  # the mean projects onto a pixel centre
    out, _ = _assert_finite_with_grads(_one([0.0, 0.0, 2.0], opacity=0.0), cam, backend=backend)
    assert out.alpha.max() == 0
    out, _ = _assert_finite_with_grads(_one([0.0, 0.0, 2.0], scale=0.5, opacity=1.0), cam, backend=backend)
    assert abs(float(out.alpha.detach().max()) - ALPHA_MAX) < 1e-12


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
def test_empty_scene(backend, camera):
    scene = [t[:0] for t in make_scene(3, 4, camera, 0)]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = splat(*scene, camera, torch.stack([EYE, EYE]), background=bg, backend=backend)
    assert out.rgb.shape == (2, 3, camera.height, camera.width) and out.features.shape[1] == 4
    assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0 and out.features.abs().sum() == 0
    torch.testing.assert_close(out.rgb[1, :, 3, 5], bg)


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_all_behind_pinhole(backend):
    scene = make_scene(20, 3, PH, 0)
    scene[0] = scene[0] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    out, grads = _assert_finite_with_grads(scene, PH, backend=backend)
    assert out.alpha.max() == 0
    assert all(g is None or g.abs().max() == 0 for g in grads)


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
def test_float32_magnitude_1e4(backend, camera):
    offset = torch.tensor([1e4, -1e4, 1e4], dtype=torch.float64)
    scene64 = make_scene(30, 3, camera, 4)
    scene64[0] = scene64[0] + offset
    scene64[5] = scene64[5] * 1e4
    pose = EYE.clone()
    pose[:3, 3] = offset
    scene32 = [t.float() for t in scene64]
    out32, _ = _assert_finite_with_grads(scene32, camera, pose=pose, backend=backend)
    out64 = splat(*scene64, camera, pose, backend="reference")
    assert out64.alpha.max() > 0.3
    # float32 rounding of the means (ulp ~1e-3 at 1e4) moves footprints by a fraction of a pixel
    assert (out32.alpha.double() - out64.alpha).abs().mean() < 2e-2
    # and a far-away float32 scene (magnitude 1e4 from the camera) stays finite too
    far = [t.clone() for t in scene32]
    far[0] = far[0] - offset.float() + 1e4
    far[1] = far[1] * 1e3
    _assert_finite_with_grads(far, camera, backend=backend, far=None)


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
def test_batched_cameras_equal_separate_calls(backend):
    scene = make_scene(30, 3, EQ, 6)
    poses = torch.stack([EYE, _yaw_pose(40.0), _yaw_pose(-75.0)])
    poses[2, :3, 3] = torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64)
    batched = splat(*scene, EQ, poses, backend=backend)
    for b in range(3):
        single = splat(*scene, EQ, poses[b], backend=backend)
        for name, t in planes(single).items():
            torch.testing.assert_close(planes(batched)[name][b : b + 1], t, atol=0, rtol=0)


def test_nonfinite_inputs_raise_or_cull():
    scene = make_scene(10, 3, PH, 0)
    for idx, name in enumerate(["means", "scales", "quats", "opacities", "colors", "features"]):
        bad = [t.clone() for t in scene]
        bad[idx].view(-1)[2] = float("nan") if idx % 2 else float("inf")
        with pytest.raises(ValueError, match=name):
            splat(*bad, PH, EYE)
    bad = [t.clone() for t in scene]
    bad[0][4, 1] = float("nan")
    culled = splat(*bad, PH, EYE, nonfinite="cull", backend="reference")
    keep = torch.arange(10) != 4
    want = splat(*[t[keep] for t in scene], PH, EYE, backend="reference")
    torch.testing.assert_close(culled.rgb, want.rgb)
    with pytest.raises(ValueError, match="cam_to_world"):
        splat(*scene, PH, torch.full((4, 4), float("nan"), dtype=torch.float64))


def test_checked_gaussians_render_the_same_and_a_render_function_checks_once():
    """``nonfinite="checked"`` skips the per-call scan only: the same image on finite input. A render
    function checks its scene once, when it is made, and names the field."""
    from image2sim.simulator.sim import GaussianRenderFn

    scene = make_scene(20, 3, PH, 0)
    for backend in ("reference", *BACKENDS):
        a = splat(*scene, PH, EYE, backend=backend)
        b = splat(*scene, PH, EYE, backend=backend, nonfinite="checked")
        for name, t in planes(a).items():
            torch.testing.assert_close(planes(b)[name], t, atol=0, rtol=0)
    with pytest.raises(ValueError, match="nonfinite must be one of"):
        splat(*scene, PH, EYE, nonfinite="ignore")
    names = ("means", "scales", "quats", "opacities", "colors")
    fields = dict(zip(names, scene[:5], strict=True))
    GaussianRenderFn(fields)  # finite: fine
    bad = {k: v.clone() for k, v in fields.items()}
    bad["scales"][7, 0] = float("inf")
    with pytest.raises(ValueError, match=r"GaussianRenderFn: scales has non-finite .* 1 of 20 .*index 7"):
        GaussianRenderFn(bad)


def test_bad_arguments_are_named():
    scene = make_scene(5, 3, PH, 0)
    with pytest.raises(ValueError, match="scales"):
        splat(scene[0], scene[1][:, :2], *scene[2:], PH, EYE)
    with pytest.raises(ValueError, match="opacities"):
        splat(*scene[:3], scene[3][:4], *scene[4:], PH, EYE)
    with pytest.raises(ValueError, match="backend"):
        splat(*scene, PH, EYE, backend="nope")
    with pytest.raises(ValueError, match="cam_to_world"):
        splat(*scene, PH, torch.eye(3))
    with pytest.raises(TypeError, match="camera"):
        splat(*scene, "pinhole", EYE)
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="min_transmittance"):
            splat(*scene, PH, EYE, min_transmittance=bad)


def test_far_culling_and_projection_validity():
    means = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 5.0], [0.0, 0.0, -2.0]], dtype=torch.float64)
    ones = torch.ones(3, 3, dtype=torch.float64) * 0.1
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    proj = project_gaussians(means, ones, quats, torch.full((3,), 0.5, dtype=torch.float64), PH, EYE, far=3.0)
    assert proj.valid.tolist() == [True, False, False]
    proj = project_gaussians(means, ones, quats, torch.full((3,), 0.5, dtype=torch.float64), EQ, EYE, far=3.0)
    assert proj.valid.tolist() == [True, False, True]


def test_auto_falls_back_with_warning_when_kernel_disabled(monkeypatch):
    monkeypatch.setenv("IMAGE2SIM_DISABLE_CPU_KERNEL", "1")
    scene = make_scene(10, 3, PH, 0)
    with pytest.warns(RuntimeWarning, match="torch"):
        out = splat(*scene, PH, EYE, backend="auto")
    assert out.backend == "torch"


def test_auto_uses_compiled_kernel_when_available():
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    out = splat(*make_scene(5, 1, PH, 0), PH, EYE)
    assert out.backend == "cpu"


# --- projection internals ------------------------------------------------------------------------


@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
def test_projected_covariance_matches_textbook_ewa(camera):
    """The fast L L^T form equals J W Sigma W^T J^T + 0.3 I computed the readable way."""
    from image2sim.simulator.splatting.project import covariance_3d, world_to_camera

    means, scales, quats, opac, _, _ = make_scene(25, 0, camera, 9)
    pose = _yaw_pose(20.0)
    pose[:3, 3] = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    proj = project_gaussians(means, scales, quats, opac, camera, pose)
    p, cov_cam = world_to_camera(means, covariance_3d(scales, quats), pose)
    jac = camera.pixel_jacobian(p)
    want = jac @ cov_cam @ jac.transpose(-1, -2) + DILATION * torch.eye(2, dtype=torch.float64)
    v = proj.valid
    assert v.sum() > 10
    if isinstance(camera, EquirectCamera):  # away from the poles the width clamp is inactive
        v = v & (want[:, 0, 0].sqrt() * CUTOFF_SIGMA < camera.width / 2)
    got = proj.cov2d[v]
    torch.testing.assert_close(
        got, torch.stack((want[v, 0, 0], want[v, 0, 1], want[v, 1, 1]), -1), rtol=1e-9, atol=1e-9
    )
    uv, _, _ = camera.project(p)
    torch.testing.assert_close(proj.means2d[v], uv[v], rtol=0, atol=1e-9)
    inv = torch.linalg.inv(want[v])
    torch.testing.assert_close(
        proj.conics[v], torch.stack((inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]), -1), rtol=1e-8, atol=1e-10
    )


@pytest.mark.parametrize("wrap", [0.0, 48.0])
def test_compiled_binning_matches_torch_binning(wrap):
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    from image2sim.simulator.splatting.backends import cpu_kernel, torch_tiles

    g = torch.Generator().manual_seed(1)
    means2d = torch.rand(200, 2, generator=g, dtype=torch.float64) * torch.tensor([48.0, 24.0])
    radii = torch.rand(200, 2, generator=g, dtype=torch.float64) * 12
    radii[0] = torch.tensor([24.0, 3.0])  # spans the full width
    off_t, ids_t = torch_tiles.bin_gaussians(means2d, radii, 24, 48, wrap, tile=8)
    off_c, ids_c = cpu_kernel.bin_gaussians(means2d, radii, 24, 48, wrap, tile=8)
    assert torch.equal(off_t, off_c) and torch.equal(ids_t, ids_c)
    if wrap:
        n_tx = 6
        assert (off_t[1:] - off_t[:-1]).sum() == ids_t.numel()
        tiles_of_0 = [t for t in range(n_tx * 3) if 0 in ids_t[off_t[t] : off_t[t + 1]].tolist()]
        assert len({t % n_tx for t in tiles_of_0}) == n_tx  # every column of tiles, no duplicates


@pytest.mark.parametrize("backend", ["reference", *BACKENDS])
@pytest.mark.parametrize("grad", [False, True], ids=["inference", "training"])
def test_gaussian_beside_a_pinhole_camera_does_not_fog_the_view(backend, grad):
    """A Gaussian 2 m to the side, 6 cm in front of the camera's plane: none of its mass is in the
    90-degree frustum, so the view stays empty. The unclamped EWA Jacobian (x/z = 33) gave it a
    footprint of ~5 000 px that covered the whole image with alpha up to 0.3 (HM3D views were fog)."""
    cam = PinholeCamera.from_fov(90.0, 90.0, 64, 64)
    means = torch.tensor([[2.0, 0.0, 0.06], [-1.5, 0.8, 0.08], [0.0, 0.0, 2.0]], dtype=torch.float64)
    scales = torch.full((3, 3), 0.05, dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    opac = torch.ones(3, dtype=torch.float64)
    colors = torch.eye(3, dtype=torch.float64)
    if grad:
        means.requires_grad_()
    out = splat(means[:2], scales[:2], quats[:2], opac[:2], colors[:2], None, cam, EYE, backend=backend)
    assert float(out.alpha.max()) == 0.0
    # The one in view renders as before, beside the other two.
    alone = splat(means[2:], scales[2:], quats[2:], opac[2:], colors[2:], None, cam, EYE, backend=backend)
    both = splat(means, scales, quats, opac, colors, None, cam, EYE, backend=backend)
    assert float(alone.alpha.max()) > 0.5
    torch.testing.assert_close(both.rgb, alone.rgb, atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    "camera",
    [EquirectCamera(64, 128), PinholeCamera(50.0, 50.0, 32.0, 32.0, 64, 64)],
    ids=["equirect", "pinhole"],
)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_inference_projection_matches_torch_projection(camera, dtype):
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    from image2sim.simulator.splatting.backends import cpu_kernel

    g = torch.Generator().manual_seed(0)
    n = 500
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2
    means[0] = torch.tensor([0.1, -2.0, -0.3])  # zenith of the camera at (0.1, 0.2, -0.3)
    means[1] = torch.tensor([0.1, 0.2, -2.3])  # on the seam
    means[2] = torch.tensor([0.1, 0.2, -0.3])  # at the camera centre
    # Anisotropic Gaussians inside the pole blend (cos(lat) from 0 to 0.2) above and below the camera.
    cos_lat = torch.linspace(0.0, 0.2, 40, dtype=torch.float64)
    lon = torch.linspace(0.0, 6.0, 40, dtype=torch.float64)
    sign = torch.where(torch.arange(40) % 2 == 0, -1.0, 1.0).double()
    sin_lat = (1 - cos_lat**2).sqrt()
    ring = torch.stack((cos_lat * torch.sin(lon), sign * sin_lat, cos_lat * torch.cos(lon)), 1)
    means[10:50] = ring * 1.5 + torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3
    scales[3], scales[4] = 1e3, 1e-8
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = torch.rand(n, generator=g, dtype=torch.float64)
    opac[10:50] = 0.5
    # In front of the camera (most inside a pinhole's frustum) and beside it, just past its plane,
    # where the pinhole Jacobian is evaluated at the widened frustum's edge (frustum_clamped).
    ahead = torch.rand(150, 3, generator=g, dtype=torch.float64) * 2 - 1
    means[50:200] = ahead * torch.tensor([1.5, 1.5, 1.0], dtype=torch.float64) + torch.tensor([0.1, 0.2, 2.2])
    means[200:260, 2] = -0.3 + 0.05 + torch.rand(60, generator=g, dtype=torch.float64) * 0.3
    args = [t.to(dtype) for t in (means, scales, quats, opac)]
    pose = EYE.clone()
    pose[:3, 3] = torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)
    mask = torch.ones(n, dtype=torch.bool)
    mask[7] = False
    want = project_gaussians(*args, camera, pose, far=5.0, finite_mask=mask)
    got = cpu_kernel.project(*args, camera, pose, far=5.0, finite_mask=mask)
    assert torch.equal(got.valid, want.valid) and 100 < int(want.valid.sum()) < n
    tol = 1e-9 if dtype == torch.float64 else 1e-5
    for field in ("means2d", "conics", "depths", "radii", "cov2d"):
        w, h = getattr(want, field), getattr(got, field)
        assert ((h - w).abs() / w.abs().clamp_min(1.0)).max() <= tol, field


def test_inference_and_training_paths_agree():
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    scene = make_scene(40, 4, EQ, 3, dtype=torch.float32)
    with torch.no_grad():
        fused = splat(*scene, EQ, _yaw_pose(10.0), backend="cpu")
    trained = splat(*[t.clone().requires_grad_() for t in scene], EQ, _yaw_pose(10.0), backend="cpu")
    for name, t in planes(fused).items():
        torch.testing.assert_close(t, planes(trained)[name].detach(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_depth_sort_is_stable_and_matches_torch(dtype):
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    from image2sim.simulator.splatting.backends import cpu_kernel

    g = torch.Generator().manual_seed(3)
    depths = (torch.randint(1, 40, (3000,), generator=g).to(dtype) * 0.125).contiguous()  # many ties
    depths[::7] = torch.rand(depths[::7].shape, generator=g).to(dtype) * 1e4
    valid = torch.rand(3000, generator=g) > 0.2
    want = torch.nonzero(valid).squeeze(1)
    want = want[torch.argsort(depths[want], stable=True)]
    assert torch.equal(cpu_kernel.sort_valid(depths, valid), want)


@pytest.mark.parametrize("grad", [False, True], ids=["fused", "training"])
@pytest.mark.parametrize("width", [80, 77], ids=["whole_tiles", "partial_tile"])
def test_compiled_kernel_matches_reference_at_the_image_border(grad, width):
    """Small Gaussians crowded around a pinhole image's border, most of their means outside it with
    part of their footprint inside: the compiled kernel skips pixel chunks that a footprint box
    misses and (inference) culls Gaussians whose footprint bound misses the image before their
    covariance; both must change nothing against the dense reference."""
    if "cpu" not in BACKENDS:
        pytest.skip("compiled kernel unavailable on this machine")
    cam = PinholeCamera(fx=40.0, fy=40.0, cx=width / 2, cy=24.0, height=48, width=width)
    g = torch.Generator().manual_seed(3)
    n = 400
    z = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
    # Pixel positions up to 6 px beyond each edge (footprints of 1-8 px reach into the image).
    u = torch.rand(n, generator=g, dtype=torch.float64) * (width + 12) - 6
    v = torch.rand(n, generator=g, dtype=torch.float64) * 60 - 6
    means = torch.stack(((u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z), 1)
    scales = (0.005 + 0.05 * torch.rand(n, 3, generator=g, dtype=torch.float64)) * z[:, None]
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = 0.3 + 0.7 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    scene = [t.float() for t in (means, scales, quats, opac, colors)]
    if grad:
        scene = [t.requires_grad_() for t in scene]
    with torch.set_grad_enabled(grad):
        ref = splat(*scene, None, cam, EYE, backend="reference")
        out = splat(*scene, None, cam, EYE, backend="cpu")
    edge = torch.zeros(48, width, dtype=torch.bool)
    edge[:4], edge[-4:], edge[:, :4], edge[:, -4:] = True, True, True, True
    assert float(ref.alpha[0, 0][edge].mean()) > 0.3  # the border is covered
    assert_matches_reference(out, ref, scene if grad else None)
