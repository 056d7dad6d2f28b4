"""Backend dispatch: the ``auto`` rule, the registry, and the gsplat adapter's arguments.

No CUDA here: a fake ``gsplat`` module stands in sys.modules and the device check is monkeypatched
to report ``cuda`` for CPU tensors. What is tested is what the adapter passes and how it assembles
the result, not that gsplat renders.
"""

from __future__ import annotations

import sys
import types

import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.splatting import dispatch, splat
from image2sim.simulator.splatting.api import available_backends, resolve_backend

PH = PinholeCamera(fx=30.0, fy=28.0, cx=21.0, cy=13.5, height=26, width=40)
EQ = EquirectCamera(24, 48)


def _scene(n: int = 6, c: int = 4, dtype=torch.float32):
    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) + torch.tensor(
        [-0.5, -0.5, 2.0], dtype=torch.float64
    )
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.2 + 0.05
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.5 + 0.3
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    feats = torch.randn(n, c, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, scales, quats, opac, colors, feats)]


def _pose(tx: float = 0.3) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    c, s = 0.8, 0.6  # a yaw so the inverse is not the transpose of the identity
    pose[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    pose[:3, 3] = torch.tensor([tx, -0.2, 0.1], dtype=torch.float64)
    return pose


@pytest.fixture
def fake_cuda(monkeypatch):
    """Dispatch sees every tensor as living on a CUDA device."""
    monkeypatch.setattr(dispatch, "device_type", lambda device: "cuda")


@pytest.fixture
def fake_gsplat(monkeypatch):
    """A stand-in ``gsplat`` module whose ``rasterization`` records its arguments and returns known planes."""
    calls: list[dict] = []

    def rasterization(**kwargs):
        calls.append(kwargs)
        b = kwargs["viewmats"].shape[0]
        h, w = kwargs["height"], kwargs["width"]
        ch = kwargs["colors"].shape[1] + 1  # RGB+D: colour channels then depth
        colours = torch.arange(ch, dtype=torch.float32).reshape(1, 1, 1, ch) + 10.0 * torch.arange(
            b, dtype=torch.float32
        ).reshape(b, 1, 1, 1)
        colours = colours.expand(b, h, w, ch).clone()
        alphas = torch.full((b, h, w, 1), 0.25)
        return colours, alphas, {}

    module = types.ModuleType("gsplat")
    module.rasterization = rasterization
    monkeypatch.setitem(sys.modules, "gsplat", module)
    return calls


def test_auto_on_cpu_is_the_compiled_kernel_or_torch():
    name = resolve_backend("auto", torch.device("cpu"), PH)
    assert name == ("cpu" if "cpu" in available_backends() else "torch")
    assert "gsplat" not in available_backends("cpu")


def test_auto_on_cuda_sends_pinhole_to_gsplat_and_panoramas_to_torch(fake_cuda, fake_gsplat):
    assert resolve_backend("auto", torch.device("cpu"), PH) == "gsplat"
    assert resolve_backend("auto", torch.device("cpu"), EQ) == "torch"
    with pytest.raises(ValueError, match="PinholeCamera"):
        resolve_backend("gsplat", torch.device("cpu"), EQ)
    with pytest.raises(ValueError, match="cpu"):  # the compiled kernel never takes CUDA tensors
        resolve_backend("cpu", torch.device("cpu"), PH)


def test_auto_on_cuda_without_gsplat_uses_torch_silently(fake_cuda, monkeypatch, recwarn):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat -> ImportError
    assert resolve_backend("auto", torch.device("cpu"), PH) == "torch"
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    with pytest.raises(ValueError, match="unavailable"):
        resolve_backend("gsplat", torch.device("cpu"), PH)


def test_gsplat_adapter_passes_our_conventions(fake_cuda, fake_gsplat):
    means, scales, quats, opac, colors, feats = _scene(c=4)
    poses = torch.stack((_pose(0.3), _pose(-0.1)))
    bg = torch.tensor([0.2, 0.5, 0.9])
    out = splat(means, scales, quats, opac, colors, feats, PH, poses, near=0.1, far=7.5, background=bg)
    assert out.backend == "gsplat"
    (kw,) = fake_gsplat
    # Gaussians: same tensors, quaternions in (w, x, y, z) order, un-normalised, linear scales/opacities
    assert torch.equal(kw["means"], means) and torch.equal(kw["quats"], quats)
    assert torch.equal(kw["scales"], scales) and torch.equal(kw["opacities"], opac)
    assert torch.equal(kw["colors"], torch.cat((colors, feats), dim=1))
    # cameras: world-to-camera view matrices and pixel-centre intrinsics of the PinholeCamera
    want_view = torch.linalg.inv(poses).float()
    torch.testing.assert_close(kw["viewmats"], want_view, atol=1e-6, rtol=0)
    want_k = torch.tensor([[30.0, 0.0, 21.0], [0.0, 28.0, 13.5], [0.0, 0.0, 1.0]])
    assert kw["Ks"].shape == (2, 3, 3) and torch.equal(kw["Ks"][1], want_k)
    assert (kw["width"], kw["height"]) == (40, 26)
    # semantics: + 0.3 dilation without compensation, accumulated z depth, near/far planes
    assert kw["eps2d"] == pytest.approx(0.3) and kw["rasterize_mode"] == "classic"
    assert kw["render_mode"] == "RGB+D" and kw["sh_degree"] is None
    assert (kw["near_plane"], kw["far_plane"]) == (0.1, 7.5)
    assert "backgrounds" not in kw  # the background is composited here, on rgb only
    # output assembly: channels 0-2 rgb (+ (1 - alpha) bg), 3..3+C features, last depth
    assert out.rgb.shape == (2, 3, 26, 40) and out.features.shape == (2, 4, 26, 40)
    assert out.depth.shape == (2, 1, 26, 40) and out.alpha.shape == (2, 1, 26, 40)
    for b in range(2):
        base = 10.0 * b
        torch.testing.assert_close(out.rgb[b, :, 0, 0], base + torch.tensor([0.0, 1.0, 2.0]) + 0.75 * bg)
        torch.testing.assert_close(out.features[b, :, 5, 7], base + torch.tensor([3.0, 4.0, 5.0, 6.0]))
        assert float(out.depth[b, 0, 3, 3]) == base + 7.0
    assert torch.all(out.alpha == 0.25)


def test_gsplat_adapter_float64_and_no_far(fake_cuda, fake_gsplat):
    scene = [t.requires_grad_() for t in _scene(c=0, dtype=torch.float64)]
    out = splat(*scene, PH, _pose(), near=0.05)
    (kw,) = fake_gsplat
    assert kw["means"].dtype == torch.float32 and kw["colors"].shape == (6, 3)
    assert kw["far_plane"] >= 1e9
    assert out.rgb.dtype == torch.float64 and out.features.shape == (1, 0, 26, 40)


def test_a_registered_gpu_kernel_is_picked_without_touching_callers(fake_cuda):
    """A panorama GPU rasteriser registered with a higher priority than torch wins ``auto`` on CUDA."""
    from image2sim.simulator.splatting.backends import torch_tiles

    calls = []

    def fake_kernel(*args, **kwargs):
        calls.append(args)
        return torch_tiles.rasterize(*args, **kwargs)

    dispatch.register_backend(
        dispatch.Backend(
            "fake_equirect_gpu",
            "rasterizer",
            fake_kernel,
            frozenset({"cuda"}),
            (EquirectCamera,),
            auto_priority=50,
        )
    )
    try:
        scene = _scene()
        out = splat(*scene, EQ, torch.eye(4, dtype=torch.float64))
        assert out.backend == "fake_equirect_gpu" and len(calls) == 1
        ref = splat(*scene, EQ, torch.eye(4, dtype=torch.float64), backend="torch")
        torch.testing.assert_close(out.rgb, ref.rgb)
        assert resolve_backend("auto", torch.device("cpu"), PH) == "torch"  # pinhole: not its camera
    finally:
        dispatch.unregister_backend("fake_equirect_gpu")
    assert resolve_backend("auto", torch.device("cpu"), EQ) == "torch"


def test_registry_rejects_bad_entries():
    with pytest.raises(ValueError, match="kind"):
        dispatch.register_backend(dispatch.Backend("x", "painter", lambda: None))
    with pytest.raises(ValueError, match="already registered"):
        dispatch.register_backend(dispatch.Backend("torch", "rasterizer", lambda: None))
    with pytest.raises(ValueError, match="unknown backend"):
        dispatch.get_backend("no_such_backend")
