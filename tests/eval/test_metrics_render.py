"""PSNR / SSIM / depth metrics: hand-computed values, properties, scikit-image parity; FPS timing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.eval.metrics.render import (
    SSIM_K1,
    SSIM_K2,
    depth_metrics,
    gaussian_filter_valid,
    gaussian_kernel_1d,
    gaussian_window,
    psnr,
    ssim,
    ssim_map,
)
from image2sim.eval.metrics.timing import measure_fps


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------------------------------------- PSNR

def test_psnr_hand_computed() -> None:
    a = torch.full((3, 8, 8), 0.5)
    b = torch.full((3, 8, 8), 0.6)
    assert psnr(a, b).item() == pytest.approx(20.0)  # MSE 0.01 -> 10 log10(1 / 0.01)
    assert psnr(a * 255, b * 255, data_range=255.0).item() == pytest.approx(20.0)
    assert psnr(a, a).item() == math.inf
    # Half the pixels off by 0.2, half exact: MSE = 0.02 -> 16.9897 dB.
    c = a.clone()
    c[:, :4] += 0.2
    assert psnr(c, a).item() == pytest.approx(10 * math.log10(1 / 0.02))


def test_psnr_batch_and_mask() -> None:
    x = _rand(4, 3, 16, 16)
    y = _rand(4, 3, 16, 16, seed=1)
    batch = psnr(x, y)
    assert batch.shape == (4,)
    for i in range(4):
        assert batch[i].item() == pytest.approx(psnr(x[i], y[i]).item())
    # Errors outside the mask do not count.
    y2 = x.clone()
    y2[..., :8] = 1.0 - y2[..., :8]
    mask = torch.zeros(4, 1, 16, 16, dtype=torch.bool)
    mask[..., 8:] = True
    assert torch.all(psnr(y2, x, mask=mask) == math.inf)
    y2[..., 8:] += 0.1
    assert psnr(y2, x, mask=mask)[0].item() == pytest.approx(20.0)
    with pytest.raises(ValueError, match=r"mask: selects no pixel in image \[2\]"):
        m = mask.clone()
        m[2] = False
        psnr(x, y, mask=m)


def test_psnr_rejects_bad_inputs() -> None:
    x = _rand(3, 8, 8)
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(x, x[:, :4])
    bad = x.clone()
    bad[0, 0, 0] = math.nan
    with pytest.raises(ValueError, match="pred: contains NaN"):
        psnr(bad, x)
    bad[0, 0, 0] = math.inf
    with pytest.raises(ValueError, match="target: contains NaN or inf"):
        psnr(x, bad)
    # Huge but finite values overflow the fast finite-sum check; they must not be rejected.
    huge = torch.full((1, 4, 4), 1e308, dtype=torch.float64)
    assert psnr(huge, huge).item() == math.inf
    with pytest.raises(ValueError, match="data_range"):
        psnr(x, x, data_range=0.0)
    with pytest.raises(TypeError, match="mask: expected a bool"):
        psnr(x, x, mask=torch.ones(1, 8, 8))


# ---------------------------------------------------------------------------------------------- SSIM

def test_gaussian_window() -> None:
    w = gaussian_window()
    assert w.shape == (11, 11) and w.sum().item() == pytest.approx(1.0)
    assert torch.allclose(w, w.T) and w.argmax().item() == 5 * 11 + 5
    assert (w[5, 5] / w[5, 6]).item() == pytest.approx(math.exp(1 / (2 * 1.5**2)))


def test_separable_filter_matches_2d_convolution() -> None:
    x = _rand(4, 23, 31).double()
    fast = gaussian_filter_valid(x, gaussian_kernel_1d())
    slow = torch.nn.functional.conv2d(x[:, None], gaussian_window()[None, None])[:, 0]
    assert fast.shape == (4, 13, 21)
    assert torch.allclose(fast, slow, atol=1e-14, rtol=0)


def test_ssim_constant_images_hand_computed() -> None:
    # Zero variance everywhere: SSIM = (2ab + C1) / (a^2 + b^2 + C1) (structure term is C2/C2 = 1).
    a, b = 0.3, 0.7
    c1 = SSIM_K1**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    f64 = torch.float64
    got = ssim(torch.full((1, 20, 20), a, dtype=f64), torch.full((1, 20, 20), b, dtype=f64)).item()
    assert got == pytest.approx(expected, rel=1e-12)


def test_ssim_structure_term_hand_computed() -> None:
    # x = m + s, y = m - s with a checkerboard s of amplitude d and equal local means:
    # luminance term 1, contrast-structure term (2 cov + C2) / (vx + vy + C2) = (-2v + C2) / (2v + C2).
    h = w = 32
    i, j = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    s = ((i + j) % 2).double() * 2 - 1  # +-1 checkerboard
    d = 0.1
    x, y = 0.5 + d * s, 0.5 - d * s
    m = ssim_map(x[None], y[None])[0]
    # Local variance of a +-d checkerboard under the window: d^2 minus the squared local mean of s.
    win = gaussian_window().double()
    c2 = SSIM_K2**2
    for (r, c) in [(0, 0), (3, 7), (m.shape[0] - 1, m.shape[1] - 1)]:
        patch = s[r:r + 11, c:c + 11]
        mu_s = (win * patch).sum()
        v = d * d * (1 - mu_s**2)
        mx, my = 0.5 + d * mu_s, 0.5 - d * mu_s
        lum = (2 * mx * my + SSIM_K1**2) / (mx**2 + my**2 + SSIM_K1**2)
        expected = lum * (-2 * v + c2) / (2 * v + c2)
        assert m[r, c].item() == pytest.approx(expected.item(), rel=1e-10)


def test_ssim_properties() -> None:
    x = _rand(2, 3, 32, 40)
    y = _rand(2, 3, 32, 40, seed=1)
    assert torch.allclose(ssim(x, x), torch.ones(2, dtype=torch.float64))
    assert torch.allclose(ssim(x, y), ssim(y, x))
    noisy = [ssim(x, (x + s * torch.randn(x.shape, generator=torch.Generator().manual_seed(2))).clamp(0, 1))
             for s in (0.01, 0.05, 0.2)]
    assert noisy[0][0] > noisy[1][0] > noisy[2][0]
    # Mean over channels: channel-wise SSIMs average to the image SSIM.
    per_channel = torch.stack([ssim(x[:, c:c + 1], y[:, c:c + 1]) for c in range(3)], dim=-1).mean(-1)
    assert torch.allclose(ssim(x, y), per_channel)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(x[..., :10, :], y[..., :10, :])


@settings(max_examples=15)
@given(st.integers(11, 40), st.integers(11, 40), st.sampled_from([1.0, 255.0]), st.integers(0, 2**16))
def test_ssim_matches_skimage(h: int, w: int, data_range: float, seed: int) -> None:
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(seed)
    x = rng.random((3, h, w)) * data_range
    y = np.clip(x + rng.normal(0, 0.1 * data_range, x.shape), 0, data_range)
    ref = skm.structural_similarity(
        x, y, channel_axis=0, data_range=data_range, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False,
    )
    got = ssim(torch.from_numpy(x), torch.from_numpy(y), data_range=data_range).item()
    assert got == pytest.approx(ref, abs=1e-10)


def test_psnr_matches_skimage() -> None:
    skm = pytest.importorskip("skimage.metrics")
    x = _rand(3, 20, 30).numpy().astype(np.float64)
    y = _rand(3, 20, 30, seed=3).numpy().astype(np.float64)
    ref = skm.peak_signal_noise_ratio(y, x, data_range=1.0)
    assert psnr(torch.from_numpy(x), torch.from_numpy(y)).item() == pytest.approx(ref, rel=1e-12)


# ---------------------------------------------------------------------------------------------- depth

def test_depth_metrics_hand_computed_with_invalid_pixels() -> None:
    target = torch.tensor([[2.0, 4.0], [0.0, 1.0]])  # 0 = invalid
    pred = torch.tensor([[2.0, 5.0], [123.0, 1.2]], dtype=torch.float64)
    m = depth_metrics(pred, target)
    assert m.count.item() == 3
    assert m.abs_rel.item() == pytest.approx((0 + 0.25 + 0.2) / 3)
    assert m.rmse.item() == pytest.approx(math.sqrt((0 + 1 + 0.04) / 3))
    assert m.delta1.item() == pytest.approx(2 / 3)  # ratios 1, 1.25 (not < 1.25), 1.2
    # A mask narrows the valid set; NaN/inf outside the valid set are ignored.
    target2 = torch.tensor([[2.0, math.nan], [math.inf, 1.0]])
    pred2 = torch.tensor([[2.0, math.nan], [5.0, 1.0]])
    mask = torch.tensor([[True, True], [True, False]])
    m2 = depth_metrics(pred2, target2, mask=mask)
    assert m2.count.item() == 1 and m2.abs_rel.item() == 0.0 and m2.delta1.item() == 1.0


def test_depth_metrics_batch_and_errors() -> None:
    t = _rand(3, 1, 8, 8) + 0.5
    p = t * 1.1
    m = depth_metrics(p, t)
    assert m.abs_rel.shape == (3,)
    assert torch.allclose(m.abs_rel, torch.full((3,), 0.1, dtype=torch.float64))
    assert torch.all(m.delta1 == 1.0)
    # Non-positive predictions never pass the delta test.
    assert depth_metrics(torch.zeros(8, 8), t[0, 0]).delta1.item() == 0.0
    t0 = t.clone()
    t0[1] = 0.0
    with pytest.raises(ValueError, match=r"image \[1\] has no valid target pixel"):
        depth_metrics(p, t0)
    p_bad = p.clone()
    p_bad[2, 0, 3, 4] = math.inf
    with pytest.raises(ValueError, match=r"pred is NaN/inf on a valid pixel at index \[2, 0, 3, 4\]"):
        depth_metrics(p_bad, t)


# ---------------------------------------------------------------------------------------------- FPS

def test_fps_excludes_warmup() -> None:
    # A fake clock: each call advances time by the next duration; warm-up calls are 100 s each.
    durations = iter([100.0, 100.0] + [0.5, 0.25, 0.5, 1.0, 0.5])
    now = [0.0]
    pending = [0.0]

    def fn() -> None:
        pending[0] = next(durations)
        now[0] += pending[0]

    result = measure_fps(fn, warmup=2, runs=5, frames_per_call=2, clock=lambda: now[0])
    assert result.seconds == (0.5, 0.25, 0.5, 1.0, 0.5)
    assert result.median_seconds == 0.5 and result.fps == pytest.approx(4.0)
    assert "logical CPUs" in result.hardware
    with pytest.raises(ValueError, match="runs >= 1"):
        measure_fps(fn, runs=0)
