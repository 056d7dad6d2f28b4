"""Behaviour of the shared building blocks in image2sim.simulator.layers."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from image2sim.simulator.layers import (
    GRN,
    LayerNorm2d,
    PanoBlock,
    PanoConv2d,
    PixelShuffleUpsample,
    TransformerBlock,
    attention,
    circular_pad_width,
    sincos_positional_encoding,
)
from torch.nn.attention import SDPBackend, sdpa_kernel


@pytest.mark.parametrize("left,right", [(0, 0), (1, 2), (3, 3), (5, 0), (9, 11)])
def test_circular_pad_matches_reference(left, right):
    x = torch.randn(2, 3, 4, 5)
    ref = torch.cat([x[..., (j - left) % 5 : (j - left) % 5 + 1] for j in range(5 + left + right)], dim=-1)
    assert torch.equal(circular_pad_width(x, left, right), ref)
    if left <= 5 and right <= 5:
        assert torch.equal(circular_pad_width(x, left, right), F.pad(x, (left, right, 0, 0), mode="circular"))


def test_circular_pad_rejects_bad_input():
    with pytest.raises(ValueError):
        circular_pad_width(torch.zeros(1, 1, 2, 3), -1, 0)
    with pytest.raises(ValueError):
        circular_pad_width(torch.zeros(1, 1, 2, 0), 1, 1)


@pytest.mark.parametrize("k,stride,shift", [(3, 1, 5), (7, 1, 1), (2, 2, 4), (3, 2, 6)])
def test_panoconv_is_equivariant_to_rotation_about_the_vertical(k, stride, shift):
    """Rolling a panorama in longitude rolls the output (no seam): the defining property."""
    torch.manual_seed(0)
    conv = PanoConv2d(3, 4, k, stride=stride).double()
    x = torch.randn(1, 3, 8, 16, dtype=torch.float64)
    y = conv(x)
    y_rolled = conv(torch.roll(x, shifts=shift, dims=-1))
    assert torch.allclose(torch.roll(y, shifts=shift // stride, dims=-1), y_rolled, atol=1e-12)


@pytest.mark.parametrize(
    "k,stride,dilation,groups",
    [(3, 1, 1, 1), (7, 1, 1, 2), (2, 2, 1, 1), (3, 2, 1, 2), (3, 1, 2, 1), (1, 1, 1, 1)],
)
def test_panoconv_matches_explicitly_padded_reference_in_value_and_jvp(k, stride, dilation, groups):
    """The zero padding is the convolution's own (no padded copy): the same values, and the same
    forward-mode derivative, as padding explicitly (circular along W, zeros along H) and convolving
    unpadded; pinhole maps are zero-padded on all sides."""
    torch.manual_seed(0)
    x = torch.randn(2, 4, 9, 14, dtype=torch.float64)
    tangent = torch.randn_like(x)
    p = dilation * (k - 1) // 2
    for panoramic in (True, False):
        conv = PanoConv2d(4, 6, k, stride=stride, dilation=dilation, groups=groups, panoramic=panoramic)
        conv = conv.double()

        def reference(v, conv=conv, panoramic=panoramic):
            v = F.pad(v, (p, p, 0, 0), mode="circular") if panoramic else F.pad(v, (p, p, 0, 0))
            v = F.pad(v, (0, 0, p, p))
            return F.conv2d(v, conv.weight, conv.bias, stride=stride, dilation=dilation, groups=groups)

        y, dy = torch.func.jvp(conv, (x,), (tangent,))
        y_ref, dy_ref = torch.func.jvp(reference, (x,), (tangent,))
        assert y.shape == y_ref.shape
        assert torch.allclose(y, y_ref, atol=1e-12)
        assert torch.allclose(dy, dy_ref, atol=1e-12)


def test_panoconv_height_is_zero_padded_and_pinhole_matches_conv2d():
    torch.manual_seed(0)
    conv = PanoConv2d(2, 3, 3).double()
    x = torch.randn(1, 2, 6, 10, dtype=torch.float64)
    ref = F.conv2d(F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1)), conv.weight, conv.bias)
    assert torch.allclose(conv(x), ref, atol=1e-12)
    pin = PanoConv2d(2, 3, 3, panoramic=False).double()
    pin.load_state_dict(conv.state_dict())
    assert torch.allclose(pin(x), F.conv2d(x, conv.weight, conv.bias, padding=1), atol=1e-12)
    assert not torch.allclose(pin(x), conv(x))  # the seam columns differ


def test_layernorm2d_matches_functional_layer_norm():
    torch.manual_seed(0)
    ln = LayerNorm2d(5)
    with torch.no_grad():
        ln.weight.uniform_(0.5, 2.0)
        ln.bias.normal_()
    x = torch.randn(2, 5, 3, 4) * 10 + 3
    ref = F.layer_norm(x.permute(0, 2, 3, 1), (5,), ln.weight, ln.bias, ln.eps).permute(0, 3, 1, 2)
    assert torch.allclose(ln(x), ref, atol=1e-5)


def test_grn_matches_formula_and_has_finite_grads_on_zeros():
    torch.manual_seed(0)
    grn = GRN(4).double()
    with torch.no_grad():
        grn.gamma.normal_()
        grn.beta.normal_()
    x = torch.randn(2, 4, 3, 5, dtype=torch.float64)
    gx = x.pow(2).sum(dim=(2, 3), keepdim=True).sqrt()
    nx = gx / (gx.mean(dim=1, keepdim=True) + 1e-6)
    ref = grn.gamma * (x * nx) + grn.beta + x
    assert torch.allclose(grn(x), ref, atol=1e-8)
    zeros = torch.zeros(1, 4, 3, 5, dtype=torch.float64, requires_grad=True)
    grn(zeros).sum().backward()
    assert torch.isfinite(zeros.grad).all()
    assert torch.isfinite(grn.gamma.grad).all()


def test_panoblock_keeps_shape_and_seam_equivariance():
    torch.manual_seed(0)
    block = PanoBlock(8, kernel_size=5).double()
    x = torch.randn(1, 8, 6, 12, dtype=torch.float64)
    y = block(x)
    assert y.shape == x.shape
    assert torch.allclose(torch.roll(y, 3, -1), block(torch.roll(x, 3, -1)), atol=1e-10)


def test_pixel_shuffle_upsample_icnr_starts_as_nearest_neighbour():
    torch.manual_seed(0)
    up = PixelShuffleUpsample(4, 3, scale=2)
    x = torch.randn(1, 4, 5, 8)
    y = up(x)
    assert y.shape == (1, 3, 10, 16)
    # ICNR: all four sub-pixels of each 2x2 block start identical.
    blocks = y.unfold(2, 2, 2).unfold(3, 2, 2)
    assert torch.allclose(blocks, blocks[..., :1, :1].expand_as(blocks), atol=1e-6)


def test_attention_matches_sdpa_and_supports_jvp():
    torch.manual_seed(0)
    q, k, v = (torch.randn(2, 3, 7, 8, dtype=torch.float64) for _ in range(3))
    with sdpa_kernel([SDPBackend.MATH]):
        ref = F.scaled_dot_product_attention(q, k, v)
    assert torch.allclose(attention(q, k, v), ref, atol=1e-10)
    tq = torch.randn_like(q)
    _, jv = torch.func.jvp(lambda a: attention(a, k, v), (q,), (tq,))
    h = 1e-6
    fd = (attention(q + h * tq, k, v) - attention(q - h * tq, k, v)) / (2 * h)
    assert torch.allclose(jv, fd, atol=1e-6)


def test_transformer_block_jvp_matches_finite_differences():
    torch.manual_seed(0)
    block = TransformerBlock(16, 4, cond_dim=8).double()
    with torch.no_grad():  # leave AdaLN-Zero so the conditioning path is exercised
        block.modulation[1].weight.normal_(std=0.1)
    x = torch.randn(2, 16, 3, 4, dtype=torch.float64)
    c = torch.randn(2, 8, dtype=torch.float64)
    tx, tc = torch.randn_like(x), torch.randn_like(c)
    _, jv = torch.func.jvp(block, (x, c), (tx, tc))
    h = 1e-5
    fd = (block(x + h * tx, c + h * tc) - block(x - h * tx, c - h * tc)) / (2 * h)
    assert torch.allclose(jv, fd, atol=1e-6, rtol=1e-5)


def test_transformer_block_adaln_zero_is_identity_at_init_and_validates_condition():
    block = TransformerBlock(8, 2, cond_dim=4)
    x = torch.randn(1, 8, 2, 3)
    assert torch.equal(block(x, torch.randn(1, 4)), x)
    with pytest.raises(ValueError):
        block(x)
    with pytest.raises(ValueError):
        TransformerBlock(8, 2)(x, torch.randn(1, 4))
    with pytest.raises(ValueError):
        TransformerBlock(10, 4)


def test_positional_encoding_is_resolution_agnostic_and_periodic():
    dim = 16
    coarse = sincos_positional_encoding(4, 8, dim, dtype=torch.float64)
    fine = sincos_positional_encoding(12, 24, dim, dtype=torch.float64)
    # The centre of coarse pixel j is the centre of fine pixel 3j + 1 (same angles -> same code).
    assert torch.allclose(coarse, fine[:, 1::3, 1::3], atol=1e-12)
    # Integer longitude frequencies: the code is periodic across the seam. Column j at lon and the
    # (virtual) column j + W at lon + 2 pi agree, so the horizontal half is exactly 2 pi periodic.
    w = 8
    lon = 2 * math.pi * (torch.arange(w, dtype=torch.float64) + 0.5) / w - math.pi
    f = torch.arange(1, dim // 4 + 1, dtype=torch.float64)
    shifted = torch.cat(
        (torch.sin((lon[None] + 2 * math.pi) * f[:, None]), torch.cos((lon[None] + 2 * math.pi) * f[:, None]))
    )
    assert torch.allclose(coarse[: dim // 2, 0], shifted, atol=1e-12)
    # Distinct positions get distinct codes.
    flat = coarse.flatten(1).T
    assert torch.cdist(flat, flat).add(torch.eye(32, dtype=torch.float64)).min() > 1e-3
    with pytest.raises(ValueError):
        sincos_positional_encoding(4, 8, 6)
