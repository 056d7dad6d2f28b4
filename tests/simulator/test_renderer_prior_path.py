"""The renderer's nonlinear prior path (``decoder.prior_hidden``, ``renderer.prior_path``) and its fit
on random training pixels (``renderer.prior_filter.fit_prior_path``)."""

from __future__ import annotations

import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.renderer.condition import build_condition
from image2sim.simulator.renderer.model import PixelFlowRenderer
from image2sim.simulator.renderer.prior_filter import _Windows, fit_prior_path
from image2sim.simulator.renderer.prior_path import PriorNet, pad_prior, prior_net_input

from .test_meanflow import H, W, make_batch, small_cfg


def _psnr(x, target):
    return float(-10 * torch.log10((x - target).pow(2).mean()))


@pytest.mark.parametrize("panoramic", [True, False])
def test_windowed_path_equals_the_full_image_path_at_seam_poles_and_corners(panoramic):
    """The fit trains on gathered K x K windows; the decoder runs the convolutions on whole images.
    Both must be the same function of the prior, at the seam and the poles included."""
    torch.manual_seed(0)
    net = PriorNet(5, 8, panoramic=panoramic)
    torch.nn.init.normal_(net.out.weight)
    with torch.no_grad():
        net.in_shift.normal_()
        net.in_scale.uniform_(0.5, 2.0)
    x = torch.randn(2, 5, H, W)
    with torch.no_grad():
        full = net(x)
        padded = pad_prior(net.standardise(x), 2, panoramic)
        image = torch.tensor([0, 1, 1, 0, 1, 0])
        y = torch.tensor([0, H - 1, 3, 0, H - 1, 7])
        col = torch.tensor([0, W - 1, 4, W - 1, 0, 16])
        windowed = net.forward_windows(_Windows(padded, 5)(image, y, col))[:, :, 0, 0]
    torch.testing.assert_close(windowed, full[image, :, y, col], atol=1e-5, rtol=1e-5)
    # the padding itself: longitude wraps on a panorama, the pole rows repeat
    p = pad_prior(x, 2, panoramic)
    assert torch.equal(p[..., 2:-2, 2:-2], x)
    assert torch.equal(p[..., 0, 2:-2], x[..., 0, :]) and torch.equal(p[..., -1, 2:-2], x[..., -1, :])
    if panoramic:
        assert torch.equal(p[..., 2:-2, 0], x[..., W - 2]) and torch.equal(p[..., 2:-2, -1], x[..., 1])
    else:
        assert torch.equal(p[..., 2:-2, 0], x[..., 0])


def test_range_enters_relative_to_the_centre_pixel():
    """Scaling every range by one factor (a room twice as large, seen from twice as far) leaves the
    path's output unchanged: it reads the shape of depth edges, not distances."""
    torch.manual_seed(1)
    net = PriorNet(3, 6)
    torch.nn.init.normal_(net.out.weight)
    logits, alpha = torch.randn(1, 3, H, W), torch.rand(1, 1, H, W)
    depth = torch.rand(1, 1, H, W) * 0.5 + 0.1
    with torch.no_grad():
        near = net(prior_net_input(logits, alpha, depth))
        far = net(prior_net_input(logits, alpha, depth * 2.5))
        flat = net(prior_net_input(logits, alpha, torch.full_like(depth, 0.3)))
    torch.testing.assert_close(near, far, atol=1e-5, rtol=1e-5)
    assert (near - flat).abs().max() > 1e-2  # ... but the shape of the range does matter


def test_an_unfitted_path_adds_nothing_and_the_renderer_uses_relative_range():
    torch.manual_seed(0)
    cond, *_ = make_batch(b=2, alpha=1.0)
    linear = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 5, "prior_hidden": 0})).eval()
    both = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 5, "prior_hidden": 8})).eval()
    assert linear.decoder.prior_net is None and both.decoder.prior_net.inp.weight.shape == (8, 5, 5, 5)
    both.load_state_dict(linear.state_dict(), strict=False)
    noise = torch.randn(2, 4, H, W)
    with torch.no_grad():
        torch.testing.assert_close(
            both.render(cond, 1, noise=noise).rgb, linear.render(cond, 1, noise=noise).rgb
        )
        torch.nn.init.normal_(both.decoder.prior_net.out.weight)
        changed = both.render(cond, 1, noise=noise).rgb
        assert (changed - linear.render(cond, 1, noise=noise).rgb).abs().max() > 1e-3
        scaled = cond.clone()
        scaled[:, 19] *= 3.0
        # heads at zero: the RGB is prior + filter + MLP, and none of them reads absolute range
        torch.testing.assert_close(both.render(scaled, 1, noise=noise).rgb, changed, atol=1e-5, rtol=1e-5)


def _depth_edge_batch(seed=0):
    """Uninformative colour (flat grey splat) over a range map of near and far vertical bands; the
    target is light on the near side of each band edge (2 px wide) and dark elsewhere. Only the
    shape of the range around a pixel tells the two apart, which no filter of colour and alpha
    can read."""
    g = torch.Generator().manual_seed(seed)
    b = 4
    near = torch.zeros(b, 1, H, W, dtype=torch.bool)
    for i in range(b):
        for _ in range(3):
            start = int(torch.randint(0, W - 6, (1,), generator=g))
            near[i, :, :, start : start + int(torch.randint(3, 7, (1,), generator=g))] = True
    depth = torch.where(near, 1.5, 4.0)
    left, right = near.roll(1, -1), near.roll(-1, -1)
    edge_near = near & ~(left & right & near.roll(2, -1) & near.roll(-2, -1))
    target = torch.where(edge_near, 0.8, 0.3).expand(b, 3, H, W).contiguous()
    ones = torch.ones(b, 1, H, W)
    cond = build_condition(
        torch.zeros(b, 16, H, W), ones.expand(b, 3, H, W) * 0.45, depth, ones, EquirectCamera(H, W).ray_map()
    )
    return cond, target


def test_fitted_mlp_path_reads_depth_edges_a_linear_filter_cannot():
    cond, target = _depth_edge_batch()
    results = {}
    for hidden in (0, 16):
        torch.manual_seed(0)
        model = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 5, "prior_hidden": hidden})).eval()
        stats = fit_prior_path(
            model.decoder,
            [(cond, target)],
            steps=300,
            batch_pixels=1024,
            lr=1e-2,
            generator=torch.Generator().manual_seed(0),
        )
        assert stats["images"] == 4 and stats["pixels"] == 4 * H * W
        with torch.no_grad():
            results[hidden] = _psnr(model.render(cond, 1, noise=torch.zeros(4, 4, H, W)).rgb, target)
        assert stats["psnr_end"] > stats["psnr_start"]
    assert results[16] > results[0] + 6.0, results
    # the standardisation was set from the pairs: the alpha channel is constant, its scale floored
    net = model.decoder.prior_net
    assert net.in_scale[3] == pytest.approx(1e-3) and net.in_shift[3] == pytest.approx(1.0)


def test_fit_skips_non_finite_pixels_and_refuses_what_it_cannot_fit():
    cond, target = _depth_edge_batch()
    bad = target.clone()
    bad[0, :, 2, 3] = float("nan")
    cond = cond.clone()
    cond[1, 16:19, 5, 6] = float("inf")  # build_condition would have cleaned this; the fit must too
    model = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 3, "prior_hidden": 4})).eval()
    stats = fit_prior_path(model.decoder, [(cond, bad)], steps=5, batch_pixels=256)
    assert stats["pixels"] < 4 * H * W
    assert all(torch.isfinite(p).all() for p in model.decoder.prior_net.parameters())
    assert all(torch.isfinite(p).all() for p in model.decoder.prior_filter.parameters())
    plain = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 0, "prior_hidden": 0}))
    with pytest.raises(ValueError, match="no prior filter"):
        fit_prior_path(plain.decoder, [(cond, target)], steps=1)
    with pytest.raises(ValueError, match="no training pairs"):
        fit_prior_path(model.decoder, [], steps=1)
    nan = torch.full_like(target, float("nan"))
    with pytest.raises(ValueError, match="no finite"):
        fit_prior_path(model.decoder, [(cond, nan)], steps=1)


def test_sim_train_start_fits_the_path_when_asked_and_config_is_checked():
    from image2sim.simulator.renderer.model import _saved_config
    from image2sim.simulator.renderer.module import init_prior_path

    cond, target = _depth_edge_batch()
    dataset = [{"condition": c, "target_rgb": t} for c, t in zip(cond, target, strict=True)]
    asked = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 3, "prior_hidden": 4, "prior_fit_steps": 3}))
    before = asked.decoder.prior_net.out.weight.clone()
    stats = init_prior_path(asked, dataset, seed=0)
    assert stats is not None and not torch.equal(asked.decoder.prior_net.out.weight, before)
    none = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 3, "prior_hidden": 4, "prior_fit_steps": 0}))
    assert init_prior_path(none, dataset) is None and not none.decoder.prior_net.out.weight.any()
    with pytest.raises(ValueError, match="prior_hidden .* needs decoder.prior_filter"):
        PixelFlowRenderer(small_cfg(decoder={"prior_filter": 0, "prior_hidden": 8}))
    with pytest.raises(ValueError, match=">= 0"):
        PixelFlowRenderer(small_cfg(decoder={"prior_fit_steps": -1}))
    with pytest.raises(ValueError, match="odd"):
        PriorNet(4, 8)
    # a pixel budget: only a random subset of the pairs is loaded, and the fit keeps within it
    loaded = []

    class Counting(list):
        def __getitem__(self, i):
            loaded.append(i)
            return super().__getitem__(i)

    budget = PixelFlowRenderer(
        small_cfg(decoder={"prior_filter": 3, "prior_hidden": 4, "prior_fit_steps": 1})
    )
    stats = init_prior_path(budget, Counting(dataset), seed=0, max_pixels=2 * H * W + 5)
    assert stats["images"] == 2 and len(set(loaded)) == 2 and len(loaded) == 2
    assert fit_prior_path(budget.decoder, [(cond, target)], steps=1, max_pixels=3 * H * W)["images"] == 3
    # files written before the MLP path existed load without it
    assert _saved_config({"decoder": {"prior_filter": 7}})["decoder"]["prior_hidden"] == 0


def test_saved_renderer_keeps_the_fitted_path(tmp_path):
    from image2sim.simulator.renderer.model import load_renderer, save_renderer

    cond, target = _depth_edge_batch()
    model = PixelFlowRenderer(small_cfg(decoder={"prior_filter": 3, "prior_hidden": 4})).eval()
    fit_prior_path(model.decoder, [(cond, target)], steps=20, batch_pixels=256)
    save_renderer(model, tmp_path / "r.safetensors")
    loaded = load_renderer(tmp_path / "r.safetensors").eval()
    torch.testing.assert_close(loaded.decoder.prior_net.in_scale, model.decoder.prior_net.in_scale)
    noise = torch.zeros(4, 4, H, W)
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.render(cond, 1, noise=noise).rgb, model.render(cond, 1, noise=noise).rgb
        )
