"""lift.depth: the estimate_depth entry point, the robust alignment of a depth model to sparse SfM
depths, and the transformers wiring (a tiny random Depth Anything saved to a folder, no network)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from image2sim.simulator.lift.depth import (
    align_prediction,
    estimate_depth,
    fit_alignment,
    load_depth_model,
)
from image2sim.simulator.lift.types import PinholeView, SparseDepth

H, W = 40, 52


# ------------------------------------------------------------------------------------------ fitting


def _relative_data(n: int, scale: float, shift: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    pred = np.random.default_rng(seed).uniform(0.1, 2.0, n)
    return pred, 1.0 / (scale * pred + shift)


def test_fit_recovers_scale_and_shift_exactly():
    pred, depth = _relative_data(200, 2.5, 0.3)
    fit = fit_alignment(pred, depth, space="inverse")
    assert fit.scale == pytest.approx(2.5, rel=1e-10) and fit.shift == pytest.approx(0.3, rel=1e-9)
    assert fit.inlier_fraction == 1.0 and fit.residual < 1e-12
    np.testing.assert_allclose(fit.apply(pred), depth, rtol=1e-10)
    metric = fit_alignment(pred, 1.7 * pred, space="depth")
    assert metric.scale == pytest.approx(1.7, rel=1e-12) and metric.shift == 0.0


@pytest.mark.parametrize("space", ["inverse", "depth"])
def test_fit_is_robust_to_30_percent_outliers(space):
    rng = np.random.default_rng(1)
    pred = rng.uniform(0.1, 2.0, 300)
    depth = 1.0 / (0.8 * pred + 0.2) if space == "inverse" else 3.0 * pred
    outliers = rng.random(300) < 0.3
    depth = np.where(outliers, rng.uniform(0.3, 12.0, 300), depth)
    fit = fit_alignment(pred, depth, space=space, seed=4)
    if space == "inverse":
        assert fit.scale == pytest.approx(0.8, rel=1e-6) and fit.shift == pytest.approx(0.2, rel=1e-6)
    else:
        assert fit.scale == pytest.approx(3.0, rel=1e-6)
    # The clean points are all inliers; the outliers that happen to fall near the curve may be too.
    assert fit.inliers[~outliers].all()
    assert fit.inliers[outliers].mean() < 0.15
    # With 2 % noise on the inliers the fit stays within 1 %.
    noisy = depth * np.where(outliers, 1.0, 1.0 + 0.02 * rng.standard_normal(300))
    fit = fit_alignment(pred, noisy, space=space, seed=4)
    assert fit.scale == pytest.approx(0.8 if space == "inverse" else 3.0, rel=0.01)
    assert fit.inliers[~outliers].mean() > 0.95


def test_fit_is_deterministic_and_refuses_bad_input():
    pred, depth = _relative_data(50, 1.0, 0.5)
    depth[::3] = 7.0
    a, b = fit_alignment(pred, depth), fit_alignment(pred, depth)
    assert (a.scale, a.shift) == (b.scale, b.shift) and np.array_equal(a.inliers, b.inliers)
    with pytest.raises(ValueError, match="at least 2 finite"):
        fit_alignment(np.array([1.0, np.nan]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="space"):
        fit_alignment(pred, depth, space="log")


def test_align_prediction_confidence_follows_the_fit_and_edges():
    pred = np.full((H, W), 0.5)
    pred[:, W // 2 :] = 1.5  # a depth step down the middle
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, W, 80), rng.uniform(0, H, 80)], 1)
    at = np.where(uv[:, 0] < W // 2, 0.5, 1.5)
    # Points near the step sample a bilinear mix: keep away from it.
    keep = np.abs(uv[:, 0] - W // 2) > 1.5
    good = SparseDepth(uv[keep], 1.0 / (2.0 * at[keep] + 0.1))
    est, fit = align_prediction(pred, good, metric=False)
    np.testing.assert_allclose(est.depth, 1.0 / (2.0 * pred + 0.1), rtol=1e-6)
    assert fit is not None and fit.inlier_fraction == 1.0
    assert est.confidence[:, : W // 2 - 2].min() > 0.99
    assert est.confidence[:, W // 2 - 1 : W // 2 + 1].max() < 0.01
    # Half the points wrong: the same depth, lower confidence.
    spoiled = SparseDepth(good.uv, np.where(np.arange(good.depth.size) % 2 == 0, good.depth, 5.0))
    est2, fit2 = align_prediction(pred, spoiled, metric=False)
    assert 0.4 < fit2.inlier_fraction < 0.6
    assert est2.confidence.max() < 0.6
    # Too few points: a relative model has no depth.
    est3, fit3 = align_prediction(pred, SparseDepth(uv[:3], np.ones(3)), metric=False)
    assert fit3 is None and not est3.depth.any() and not est3.confidence.any()


# -------------------------------------------------------------------------------- model wiring


def _save_tiny_model(folder, metric: bool = False) -> None:
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
    from transformers.models.dpt.image_processing_pil_dpt import DPTImageProcessorPil

    backbone = Dinov2Config(
        image_size=56,
        patch_size=14,
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        out_indices=[1, 2, 3, 4],
        reshape_hidden_states=False,
    )
    config = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 32, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        depth_estimation_type="metric" if metric else "relative",
        max_depth=10,
        initializer_range=0.2,
    )
    torch.manual_seed(0)
    model = DepthAnythingForDepthEstimation(config)
    if not metric:
        # Random heads end in a ReLU that is mostly 0: lift them so the output varies everywhere.
        with torch.no_grad():
            model.head.conv3.weight.mul_(0.005)
            model.head.conv3.bias.fill_(1.0)
    model.save_pretrained(folder)
    DPTImageProcessorPil(
        do_resize=True,
        size={"height": 56, "width": 56},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        do_pad=False,
    ).save_pretrained(folder)


def _views(n: int = 2) -> list[PinholeView]:
    rng = np.random.default_rng(5)
    K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    views = []
    for i in range(n):
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        views.append(PinholeView(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), K, pose))
    return views


def _sparse_from(pred: np.ndarray, depth_of, k: int = 60, seed: int = 0) -> SparseDepth:
    """Sparse depths at pixel centres whose value ``depth_of(pred)`` follows the model's output."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(pred.size, k, replace=False)
    r, c = np.divmod(idx, pred.shape[1])
    return SparseDepth(np.stack([c + 0.5, r + 0.5], 1), depth_of(pred[r, c].astype(np.float64)))


@pytest.fixture(scope="module")
def tiny_relative(tmp_path_factory):
    folder = tmp_path_factory.mktemp("depth_relative")
    _save_tiny_model(folder)
    return folder


def test_tiny_depth_model_loads_offline_and_is_deterministic(tiny_relative, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    model = load_depth_model(tiny_relative)
    assert not model.metric
    views = _views()
    pred = model.predict(views[0].image)
    assert pred.shape == (H, W) and pred.dtype == np.float32 and np.isfinite(pred).all() and pred.std() > 0
    np.testing.assert_array_equal(pred, load_depth_model(tiny_relative).predict(views[0].image))

    preds = [model.predict(v.image) for v in views]
    scales, shifts = (0.7, 1.3), (0.25, 0.1)
    sparse = [
        _sparse_from(p, lambda x, s=s, t=t: 1.0 / (s * x + t), seed=i)
        for i, (p, s, t) in enumerate(zip(preds, scales, shifts, strict=True))
    ]
    stats: list[dict] = []
    est = estimate_depth(
        views, source="model", model_dir=str(tiny_relative), sparse=sparse, progress=False, stats=stats
    )
    again = estimate_depth(views, source="model", model_dir=str(tiny_relative), sparse=sparse, progress=False)
    for e, e2, p, s, t, rec in zip(est, again, preds, scales, shifts, stats, strict=True):
        assert e.depth.shape == (H, W) and e.depth.dtype == np.float32 and e.confidence.dtype == np.float32
        assert np.array_equal(e.depth, e2.depth) and np.array_equal(e.confidence, e2.confidence)
        np.testing.assert_allclose(e.depth, 1.0 / (s * p.astype(np.float64) + t), rtol=1e-5)
        assert rec["scale"] == pytest.approx(s, rel=1e-6) and rec["shift"] == pytest.approx(t, rel=1e-6)
        assert rec["inliers"] == rec["points"] == 60
        assert 0 <= e.confidence.min() and e.confidence.max() <= 1 and e.confidence.max() > 0.9


def test_metric_model_gets_a_scale_only_fit(tmp_path):
    _save_tiny_model(tmp_path, metric=True)
    model = load_depth_model(tmp_path)
    assert model.metric
    views = _views()
    preds = [model.predict(v.image) for v in views]
    sparse = [_sparse_from(p, lambda x: 0.5 * x, seed=i) for i, p in enumerate(preds)]
    stats: list[dict] = []
    est = estimate_depth(
        views, source="model", model_dir=tmp_path, sparse=sparse, progress=False, stats=stats
    )
    for e, p, rec in zip(est, preds, stats, strict=True):
        assert rec["scale"] == pytest.approx(0.5, rel=1e-9) and rec["shift"] == 0.0
        ok = p > 0
        np.testing.assert_allclose(e.depth[ok], 0.5 * p[ok], rtol=1e-5)
    # Without sparse depths a metric model is used as it is.
    raw = estimate_depth(views, source="model", model_dir=tmp_path, progress=False)
    np.testing.assert_allclose(raw[0].depth, np.where(preds[0] > 0, preds[0], 0), rtol=1e-6)


def test_model_source_errors_are_clear(tiny_relative, tmp_path):
    views = _views()
    with pytest.raises(ValueError, match="needs model_dir"):
        estimate_depth(views, source="model", progress=False)
    with pytest.raises(ValueError, match="has no config.json"):
        estimate_depth(views, source="model", model_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="does not exist"):
        estimate_depth(views, source="model", model_dir=tmp_path / "absent", progress=False)
    with pytest.raises(ValueError, match="needs sparse SfM depths"):
        estimate_depth(views, source="model", model_dir=tiny_relative, progress=False)
    with pytest.raises(ValueError, match=r"unknown depth-model option\(s\) \['planes'\]"):
        estimate_depth(views, source="model", model_dir=tiny_relative, planes=3, progress=False)
    with pytest.raises(ValueError, match="unknown depth source 'lidar'"):
        estimate_depth(views, source="lidar", progress=False)
    with pytest.raises(ValueError, match="only used by source='model'"):
        estimate_depth(views, model_dir=tiny_relative, progress=False)
    with pytest.raises(ValueError, match="non-empty list"):
        estimate_depth([], progress=False)
    bad = _views()
    bad[1].cam_to_world[1, 1] = math.inf
    with pytest.raises(ValueError, match="view 1: cam_to_world"):
        estimate_depth(bad, source="model", model_dir=tiny_relative, progress=False)
    with pytest.raises(ValueError, match="2 entries for 3 views"):
        estimate_depth(_views(3), sparse=[None, None], progress=False)


def test_a_fit_that_leaves_the_scale_free_is_not_used():
    """Points on one surface facing the camera share one depth: any scale fits them, so the view
    keeps no depth (a ceiling seen straight up gave a constant depth to a whole cube face)."""
    rng = np.random.default_rng(3)
    pred = rng.uniform(1.0, 5.0, (H, W))
    sp = _sparse_from(pred, lambda x: np.full_like(x, 2.0) + 1e-3 * rng.standard_normal(x.shape), k=80)
    est, fit = align_prediction(pred, sp, metric=False)
    assert fit is not None and fit.spread < 0.1 and not fit.usable
    assert not est.depth.any() and not est.confidence.any()
    # A spread of depths that grows with the output fixes it.
    good = _sparse_from(pred, lambda x: 1.0 / (0.5 * x + 0.1), k=80)
    est, fit = align_prediction(pred, good, metric=False)
    assert fit.usable and fit.spread > 0.5 and est.depth.all()
    # A metric model's scale-only fit is fixed by any one depth.
    est, fit = align_prediction(pred, sp, metric=True)
    assert fit.usable and est.depth.any()
