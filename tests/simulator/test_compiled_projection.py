"""The compiled differentiable projection (``splat(..., compile_projection=True)``,
:func:`image2sim.simulator.splatting.project.projector`): the same values and gradients as the eager
:func:`project_gaussians` (its reference), at the poles and the seam of a panorama and outside a
pinhole frustum; and an eager fallback with a warning when compiling fails."""

from __future__ import annotations

import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.splatting import project as project_mod
from image2sim.simulator.splatting.project import project_gaussians, projector

EQ = EquirectCamera(32, 64)
PH = PinholeCamera(30.0, 30.0, 32.0, 24.0, 48, 64)


def hard_gaussians(n: int = 200, seed: int = 0):
    """Random Gaussians around the origin plus hard cases: straight above and below (the poles), on
    the panorama's seam (-z), beside a pinhole camera's plane, elongated and tiny ones."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2.0
    means[0] = torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64)  # a pole
    means[1] = torch.tensor([1e-4, -2.0, 0.0], dtype=torch.float64)  # near the other pole
    means[2] = torch.tensor([0.3, 2.5, 0.05], dtype=torch.float64)  # inside the pole blend cap
    means[3] = torch.tensor([1e-6, 0.0, -2.0], dtype=torch.float64)  # on the seam
    means[4] = torch.tensor([3.0, 0.0, 0.06], dtype=torch.float64)  # beside the pinhole's plane
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3 + 1e-3
    scales[5] = torch.tensor([2.0, 1e-4, 1e-4], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = torch.rand(n, generator=g, dtype=torch.float64)
    return means, scales, quats, opac


def _project_and_grads(fn, camera, args):
    leaves = [a.clone().requires_grad_() for a in args[:3]]
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    proj = fn(*leaves, args[3], camera, pose)
    g = torch.Generator().manual_seed(1)
    outputs = (proj.means2d, proj.conics, proj.depths)
    weights = [torch.randn(t.shape, generator=g, dtype=t.dtype) for t in outputs]
    loss = sum((w * t).sum() for w, t in zip(weights, outputs, strict=True))
    grads = torch.autograd.grad(loss, leaves)
    return proj, grads


@pytest.mark.slow  # one inductor compile per camera model (~20-35 s each on 2 cores)
@pytest.mark.parametrize("camera", [EQ, PH], ids=["equirect", "pinhole"])
def test_compiled_projection_matches_the_eager_reference(camera):
    args = hard_gaussians()
    want, want_g = _project_and_grads(project_gaussians, camera, args)
    got, got_g = _project_and_grads(projector(True), camera, args)
    assert project_mod._compile_failed is None, project_mod._compile_failed
    assert torch.equal(got.valid, want.valid) and int(want.valid.sum()) > 30
    for name in ("means2d", "conics", "cov2d", "depths", "radii"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=1e-9, atol=1e-9, msg=name)
    for a, b in zip(got_g, want_g, strict=True):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9 * float(b.abs().max()))
    # N changes (pruning) without a new compile's failure or a different answer
    small = [a[:57] for a in args]
    want, want_g = _project_and_grads(project_gaussians, camera, small)
    got, got_g = _project_and_grads(projector(True), camera, small)
    torch.testing.assert_close(got.means2d, want.means2d, rtol=1e-9, atol=1e-9)
    for a, b in zip(got_g, want_g, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9 * float(b.abs().max()))


def test_a_failed_compile_warns_once_and_projects_eagerly(monkeypatch):
    def broken(fn, **kwargs):
        def raise_(*a, **k):
            raise RuntimeError("no C++ compiler\nmore detail")

        return raise_

    monkeypatch.setattr(project_mod, "_compiled", None)
    monkeypatch.setattr(project_mod, "_compile_failed", None)
    monkeypatch.setattr(torch, "compile", broken)
    args = hard_gaussians(20)
    want, _ = _project_and_grads(project_gaussians, EQ, args)
    with pytest.warns(
        RuntimeWarning, match=r"compiled projection unavailable .RuntimeError: no C\+\+ compiler"
    ):
        got, grads = _project_and_grads(projector(True), EQ, args)
    assert torch.equal(got.means2d, want.means2d) and all(torch.isfinite(g).all() for g in grads)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the second call neither retries nor warns again
        projector(True)(*args, EQ, torch.eye(4, dtype=torch.float64))
    assert projector(False) is project_gaussians
