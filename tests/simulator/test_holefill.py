"""The renderer's non-learned reference (renderer.holefill): covered pixels untouched, holes filled
from their surroundings, across the panorama seam, at the poles, and with degenerate alpha."""

from __future__ import annotations

import math

import pytest
import torch
from image2sim.simulator.renderer.holefill import fill_holes

H, W = 32, 64


def _smooth(c: int = 3) -> torch.Tensor:
    """A smooth image that wraps in longitude (periodic in u), values in [0.2, 0.8]."""
    v = torch.linspace(0, 1, H)[:, None]
    u = torch.arange(W)[None, :] * 2 * math.pi / W
    chans = [0.5 + 0.2 * torch.sin(u + k) * torch.ones_like(v) + 0.1 * (v - 0.5) for k in range(c)]
    return torch.stack(chans)[None]


def test_covered_pixels_are_unchanged_and_holes_get_their_surroundings():
    img = _smooth()
    alpha = torch.ones(1, 1, H, W)
    alpha[..., 12:18, 20:27] = 0.0
    holed = img * alpha  # what an empty splat shows in the hole
    out = fill_holes(holed, alpha)
    assert torch.equal(out[..., alpha[0, 0] == 1], img[..., alpha[0, 0] == 1])
    hole = alpha[0, 0] == 0
    err_empty = (holed - img)[..., hole].abs().mean()
    err_fill = (out - img)[..., hole].abs().mean()
    assert err_fill < 0.05 < err_empty  # interpolation of a smooth image is close to the truth


def test_partial_alpha_blends_own_value_with_the_surroundings():
    img = torch.full((1, 1, H, W), 0.8)
    alpha = torch.ones(1, 1, H, W)
    alpha[..., 10, 10] = 0.25
    x = img.clone()
    x[..., 10, 10] = 0.0
    out = fill_holes(x, alpha)
    # 0.25 x own value (0) + 0.75 x the neighbourhood mean, which includes the pixel's own weight.
    assert 0.75 * 0.7 < float(out[0, 0, 10, 10]) < 0.75 * 0.8 + 1e-6


def test_a_hole_on_the_seam_is_filled_from_both_sides_only_when_panoramic():
    img = torch.zeros(1, 1, H, W)
    img[..., : W // 2] = 1.0  # right half 0: the seam (u = 0 | u = W-1) separates 1 from 0
    alpha = torch.ones(1, 1, H, W)
    alpha[..., 8:24, :2] = 0.0  # hole at the left edge, next to the seam
    out_pano = fill_holes(img * alpha, alpha, panoramic=True)
    out_flat = fill_holes(img * alpha, alpha, panoramic=False)
    pano = float(out_pano[0, 0, 8:24, 0].mean())
    flat = float(out_flat[0, 0, 8:24, 0].mean())
    # Across the seam lie zeros: the panoramic fill mixes them in, the flat fill sees only ones.
    assert flat > 0.95 and pano < flat - 0.1


def test_a_hole_at_the_pole_row_is_filled():
    img = _smooth()
    alpha = torch.ones(1, 1, H, W)
    alpha[..., :3, :] = 0.0  # the whole top cap is empty
    out = fill_holes(img * alpha, alpha)
    assert torch.isfinite(out).all()
    assert float((out - img)[..., :3, :].abs().mean()) < 0.06


@pytest.mark.parametrize("fill", [0.0, float("nan")])
def test_degenerate_inputs(fill):
    img = _smooth()
    none = torch.full((1, 1, H, W), fill)
    out = fill_holes(img, none)  # nothing covered anywhere (NaN alpha counts as 0): image returned
    assert torch.equal(out, img)
    bad = img.clone()
    bad[..., 0, 0] = float("inf")
    alpha = torch.ones(1, 1, H, W)
    alpha[..., 0, 0] = 0.0
    assert torch.isfinite(fill_holes(bad, alpha)).all()
    odd = fill_holes(torch.rand(2, 4, 7, 9), torch.rand(2, 1, 7, 9))  # no pyramid level: unchanged
    assert odd.shape == (2, 4, 7, 9)
    with pytest.raises(ValueError, match="alpha"):
        fill_holes(img, torch.ones(1, 2, H, W))
    with pytest.raises(ValueError, match="does not match"):
        fill_holes(img, torch.ones(1, 1, H, W // 2))


def test_splat_modes_from_a_composite_with_gaps():
    """A surface of known colour and range seen through gaps (alpha 0.3-1) and one empty block:
    raw darkens the gaps towards the black background; normalised returns the surface's own colour
    and range wherever anything was projected and 0 in the empty block; filled also completes the
    empty block from its surroundings; normalised depth equals the splat's depth / alpha."""
    from image2sim.simulator.renderer.holefill import splat_rgbd

    colour, rng = _smooth(), 2.0 + _smooth(1)
    alpha = 0.3 + 0.7 * torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(0))
    alpha[..., 10:14, 20:26] = 0.0
    composite, weighted = colour * alpha, rng * alpha  # over background 0
    raw, raw_depth = splat_rgbd(composite, weighted, alpha, "raw")
    assert torch.equal(raw, composite.clamp(0, 1))
    norm, norm_depth = splat_rgbd(composite, weighted, alpha, "normalised")
    seen = (alpha > 0).expand_as(colour)
    assert torch.allclose(norm[seen], colour[seen], atol=1e-6)
    assert torch.allclose(norm_depth[alpha > 0], rng[alpha > 0], atol=1e-5)
    assert torch.allclose(raw_depth, norm_depth, atol=1e-5)
    assert not norm[..., 10:14, 20:26].any() and not norm_depth[..., 10:14, 20:26].any()
    err = lambda x: float((x - colour)[seen].pow(2).mean())  # noqa: E731
    assert err(norm) < 1e-10 < err(raw)
    filled, filled_depth = splat_rgbd(composite, weighted, alpha, "filled")
    hole = (slice(None), slice(None), slice(10, 14), slice(20, 26))
    assert (
        float((filled - colour)[hole].abs().max()) < 0.1
        and float((filled_depth - rng)[hole].abs().max()) < 0.1
    )
    # Over a grey background the composite is un-mixed with that background.
    grey, _ = splat_rgbd(composite + (1 - alpha) * 0.5, weighted, alpha, "normalised", background=0.5)
    assert torch.allclose(grey[seen], colour[seen], atol=1e-5)
    with pytest.raises(ValueError, match="splat mode"):
        splat_rgbd(composite, weighted, alpha, "premultiplied")


def test_filled_mode_is_eval_renders_splat_fill():
    """One concept, one place: the simulator's filled image is the benchmark's splat_fill of the same
    splat (the condition's unpremultiplied channels filled by fill_condition)."""
    from image2sim.simulator.renderer.condition import build_condition, unpremultiply
    from image2sim.simulator.renderer.holefill import fill_condition, splat_rgbd

    g = torch.Generator().manual_seed(1)
    alpha = torch.rand(1, 1, H, W, generator=g)
    alpha[..., 5:9, :8] = 0.0
    composite, weighted = (
        torch.rand(1, 3, H, W, generator=g) * alpha,
        (1 + torch.rand(1, 1, H, W, generator=g)) * alpha,
    )
    rgb, depth = unpremultiply(composite, weighted, alpha)
    cond = build_condition(torch.zeros(1, 16, H, W), rgb, depth, alpha, torch.zeros(1, 3, H, W))
    ref_rgb, ref_depth = fill_condition(cond)
    out_rgb, out_depth = splat_rgbd(composite, weighted, alpha, "filled")
    assert torch.allclose(out_rgb, ref_rgb.clamp(0, 1)) and torch.allclose(out_depth, ref_depth.clamp_min(0))
