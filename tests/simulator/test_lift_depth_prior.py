"""lift.depth_prior (a depth prior trained on RGB-D captures) and the ``mvs+model`` depth source.

The loss is checked against its definition (exact zero on an affine map of inverse depth, finite
differences, masking, degenerate images); training views against analytic panoramas; the trainer
end to end on a tiny procedural house (a folder ``load_depth_model`` reads); the fusion against a
plane scene whose right half has no texture, with an oracle model.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.geometry.reproject import perspective_directions
from image2sim.simulator.lift import depth as depth_mod
from image2sim.simulator.lift.depth import (
    MODEL_FILL_CONFIDENCE,
    estimate_depth,
    fill_from_model,
    load_depth_model,
    stereo_fit_points,
)
from image2sim.simulator.lift.depth_prior import (
    DepthPriorConfig,
    ViewPool,
    build_depth_prior,
    ssi_loss,
    train_depth_prior,
)
from image2sim.simulator.lift.types import DepthEstimate, SparseDepth

from tests.simulator.test_lift_mvs import _plane_scene, _sparse

# ------------------------------------------------------------------------------------------ the loss


def _depths(b: int = 3, h: int = 9, w: int = 11, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.5 + 4.0 * torch.rand(b, h, w, generator=g, dtype=torch.float64)).requires_grad_(False)


def test_ssi_loss_is_zero_on_any_increasing_affine_map_of_inverse_depth():
    z = _depths()
    for scale, shift in ((1.0, 0.0), (3.5, -0.2), (0.01, 7.0)):
        assert float(ssi_loss(scale / z + shift, z)) == pytest.approx(0.0, abs=1e-10)
    # A decreasing map fits as well, but the sign term (-corr = 1) refuses it.
    assert float(ssi_loss(-2.0 / z + 7.0, z)) == pytest.approx(1.0, abs=1e-10)
    assert float(ssi_loss(z, z)) > 0.9  # depth is not inverse depth


def test_ssi_loss_matches_its_definition_and_finite_differences():
    z = _depths(b=2)
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(z.shape, generator=g, dtype=torch.float64, requires_grad=True)
    loss = ssi_loss(pred, z)
    expected = 0.0
    for p, d in zip(pred.detach().numpy(), z.numpy(), strict=True):
        x, y = p.ravel(), 1.0 / d.ravel()
        A = np.stack([x, np.ones_like(x)], 1)
        (s, t), *_ = np.linalg.lstsq(A, y, rcond=None)
        expected += np.mean(np.abs(s * x + t - y)) / np.mean(y) + max(0.0, -np.corrcoef(x, y)[0, 1])
    assert float(loss.detach()) == pytest.approx(expected / 2, rel=1e-9)
    assert torch.autograd.gradcheck(lambda p: ssi_loss(p, z), (pred,), eps=1e-6, atol=1e-5)


def test_ssi_loss_ignores_invalid_pixels_and_degenerate_images():
    z = _depths(b=2)
    pred = torch.rand(z.shape, dtype=torch.float64)
    masked = z.clone()
    masked[0, :3] = 0.0
    masked[0, 3, :2] = float("nan")
    masked[0, 3, 2:4] = float("inf")
    changed = pred.clone()
    changed[0, :3] = 1e6
    changed[0, 3, :4] = -5.0
    assert float(ssi_loss(pred, masked)) == pytest.approx(float(ssi_loss(changed, masked)), rel=1e-12)
    # An image with one valid pixel, or a constant prediction, adds 0 and nothing is NaN.
    lonely = z.clone()
    lonely[1] = 0.0
    lonely[1, 0, 0] = 2.0
    flat = pred.clone().requires_grad_(True)
    loss = ssi_loss(flat, lonely)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(flat.grad).all()
    assert float(loss.detach()) == pytest.approx(float(ssi_loss(pred[:1], z[:1])) / 2, rel=1e-12)
    assert float(ssi_loss(torch.ones_like(z), z)) == 0.0
    with pytest.raises(ValueError, match=r"\(B, H, W\)"):
        ssi_loss(pred[0], z[0])


# ---------------------------------------------------------------------------------------- the views


def test_panorama_views_carry_z_depth_of_the_view():
    """A panorama at constant range r: every view's z-depth is r * (the view ray's z component)."""
    H, W, r = 64, 128, 2.5
    rgb = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = np.full((H, W), r, np.float32)
    cfg = DepthPriorConfig(image_size=28, colour_noise=0.0, hfov_min_deg=70, hfov_max_deg=70)
    pool = ViewPool([(rgb, depth, EquirectCamera(H, W))], cfg)
    for _ in range(5):
        colour, z = pool._panorama_view(0)
        assert colour.shape == (28, 28, 3) and 0 <= colour.min() and colour.max() <= 255
        ray_z = perspective_directions(70.0, 70.0, 28, 28, dtype=torch.float32)[..., 2].numpy()
        np.testing.assert_allclose(z, r * ray_z, rtol=1e-6)
    images, depths = pool.sample(4)
    assert images.shape == (4, 3, 28, 28) and depths.shape == (4, 28, 28)
    assert images.dtype == torch.float32 and (depths > 0).all()


def test_pinhole_crops_and_invalid_depth():
    h, w = 30, 40
    rgb = np.full((h, w, 3), 100, np.uint8)
    depth = np.full((h, w), 3.0, np.float32)
    depth[:, :5] = 0.0
    cfg = DepthPriorConfig(image_size=28, colour_noise=0.0, min_valid_fraction=0.0)
    pool = ViewPool([(rgb, depth, PinholeCamera.from_fov(60.0, 46.8, h, w))], cfg)
    images, depths = pool.sample(6)
    valid = depths > 0
    assert torch.all(depths[valid] == 3.0) and valid.float().mean() > 0.5
    expected = (100 / 255 - torch.tensor([0.485, 0.456, 0.406])) / torch.tensor([0.229, 0.224, 0.225])
    torch.testing.assert_close(images[0, :, 5, 5], expected.float(), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="no frames"):
        ViewPool([], cfg)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) colour and \(H, W\) depth"):
        ViewPool([(rgb, depth[:10], None)], cfg)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("image_size", 30, "multiple of 14"),
        ("hidden_size", 30, "multiple of heads"),
        ("hfov_max_deg", 190, "hfov_max_deg < 180"),
        ("level_fraction", 0.9, "sum to at most 1"),
        ("steps", 0, "steps must be >= 1"),
        ("layers", 2, "layers must be >= 4"),
    ],
)
def test_config_errors_name_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        DepthPriorConfig(**{field: value})
    with pytest.raises(ValueError, match=r"unknown depth-prior option\(s\) \['size'\]"):
        DepthPriorConfig.from_dict({"size": 3})


SMALL = {
    "depth_anything": {"image_size": 28, "hidden_size": 16, "heads": 2, "layers": 4},
    "glpn": {"architecture": "glpn", "image_size": 64, "hidden_size": 16, "heads": 1, "layers": 4},
}


@pytest.mark.parametrize("arch", sorted(SMALL))
def test_a_fresh_prior_varies_and_learns_one_view(arch):
    """The random start has output spread (Depth Anything's final ReLU does not zero it), and training
    lowers the loss on a fixed batch: the gradient reaches the output."""
    cfg = DepthPriorConfig(**SMALL[arch], seed=3)
    size = cfg.image_size
    model = build_depth_prior(cfg)
    rgb = np.random.default_rng(1).integers(0, 256, (32, 64, 3), dtype=np.uint8)
    depth = (1.0 + np.linspace(0, 3, 64)[None, :] * np.ones((32, 1))).astype(np.float32)
    pool = ViewPool([(rgb, depth, EquirectCamera(32, 64))], cfg)
    images, depths = pool.sample(4)
    out = model(pixel_values=images).predicted_depth
    assert out.shape == (4, size, size) and float(out.detach().std()) > 1e-4
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    first = float(ssi_loss(out.detach(), depths))
    for _ in range(40):
        loss = ssi_loss(model(pixel_values=images).predicted_depth, depths)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.8 * first


# ------------------------------------------------------------------------------------------ training


@pytest.fixture(scope="module")
def tiny_house(tmp_path_factory):
    from tests.simulator.lift_helpers import PANO_WALK, synth_house

    tmp = tmp_path_factory.mktemp("prior_house")
    return synth_house(tmp / "h", camera="equirect", views=2, height=32, width=64, config=PANO_WALK)


@pytest.mark.parametrize("arch", sorted(SMALL))
def test_train_depth_prior_writes_a_folder_the_lift_loads(arch, tiny_house, tmp_path, monkeypatch):
    house = tiny_house
    cfg = DepthPriorConfig(**SMALL[arch], steps=3, batch_size=2)
    out = tmp_path / "prior"
    lines: list[str] = []
    record = train_depth_prior([house], out, cfg, val_captures=[house], progress=False, log=lines.append)
    assert record["frames"] == 2 and record["views_seen"] == 6 and record["parameters"] > 0
    assert np.isfinite(record["loss_last_tenth"]) and np.isfinite(record["val_loss_after"])
    assert json.loads((out / "depth_prior.json").read_text())["config"]["steps"] == 3
    assert any("parameters" in line for line in lines)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".prior")] == []
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    model = load_depth_model(out)
    assert not model.metric
    pred = model.predict(np.random.default_rng(0).integers(0, 256, (70, 100, 3), dtype=np.uint8))
    assert pred.shape == (70, 100) and np.isfinite(pred).all() and pred.std() > 0
    with pytest.raises(ValueError, match="exists"):
        train_depth_prior([house], out, cfg, progress=False)


# --------------------------------------------------------------------------------- mvs + model fusion


def test_fill_from_model_keeps_stereo_and_ranks_model_pixels_below_it():
    stereo = DepthEstimate(
        np.array([[2.0, 0.0], [0.0, 3.0]], np.float32), np.array([[0.9, 0.0], [0.0, 0.06]], np.float32)
    )
    model = DepthEstimate(np.array([[9.0, 4.0], [0.0, 9.0]], np.float32), np.full((2, 2), 1.0, np.float32))
    fused, filled = fill_from_model(stereo, model)
    assert filled == 1
    np.testing.assert_array_equal(fused.depth, [[2.0, 4.0], [0.0, 3.0]])
    np.testing.assert_allclose(fused.confidence, [[0.9, MODEL_FILL_CONFIDENCE], [0.0, 0.06]])
    assert MODEL_FILL_CONFIDENCE < 0.5


def test_stereo_fit_points_joins_sfm_and_confident_stereo_pixels():
    depth = np.zeros((4, 5), np.float32)
    conf = np.zeros((4, 5), np.float32)
    depth[1, 2], conf[1, 2] = 2.0, 0.8
    depth[3, 4], conf[3, 4] = 5.0, 0.1  # not confident enough to join
    sfm = SparseDepth(np.array([[0.5, 0.5]]), np.array([7.0]))
    pts = stereo_fit_points(sfm, DepthEstimate(depth, conf), seed=0)
    np.testing.assert_array_equal(pts.uv, [[0.5, 0.5], [2.5, 1.5]])
    np.testing.assert_array_equal(pts.depth, [7.0, 2.0])
    depth[:] = 1.0
    conf[:] = 1.0
    assert stereo_fit_points(None, DepthEstimate(depth, conf), seed=0, max_points=7).depth.size == 7


class _OracleModel:
    """A relative 'network' (the :class:`DepthModel` interface) that returns 2/z + 0.3 of the view it
    is shown, found by its pixels."""

    metric = False

    def __init__(self, views, depths):
        self.truth = {v.image.tobytes(): d for v, d in zip(views, depths, strict=True)}

    def predict(self, image):
        return (2.0 / self.truth[np.asarray(image).tobytes()] + 0.3).astype(np.float32)


def test_mvs_plus_model_fills_the_textureless_half_from_the_aligned_model(monkeypatch):
    views, depths = _plane_scene([(-0.1, 0, 0), (0.0, 0, 0), (0.1, 0, 0)], flat_right=True)
    sparse = _sparse(depths)
    oracle = _OracleModel(views, depths)
    monkeypatch.setattr(depth_mod, "load_depth_model", lambda *a, **k: oracle)
    kw = {"sparse": sparse, "num_planes": 48, "progress": False}
    stereo = estimate_depth(views, source="mvs", **kw)
    stats: list[dict] = []
    fused = estimate_depth(views, source="mvs+model", model_dir="oracle", stats=stats, **kw)
    for s, f, d, rec in zip(stereo, fused, depths, stats, strict=True):
        had = s.depth > 0
        np.testing.assert_array_equal(f.depth[had], s.depth[had])
        np.testing.assert_array_equal(f.confidence[had], s.confidence[had])
        new = (~had) & (f.depth > 0)
        assert rec["model_filled_px"] == int(new.sum()) > 0.3 * d.size
        # The fit's points are stereo depths (48 planes) of the left half; the fill extrapolates it.
        rel = np.abs(f.depth[new] / d[new] - 1)
        assert np.median(rel) < 0.02 and rel.max() < 0.04
        assert f.confidence[new].max() <= MODEL_FILL_CONFIDENCE + 1e-6
        assert rec["model_scale"] == pytest.approx(0.5, rel=0.05)
    with pytest.raises(ValueError, match="needs model_dir"):
        estimate_depth(views, source="mvs+model", **kw)
    with pytest.raises(ValueError, match=r"unknown multi-view stereo option"):
        estimate_depth(views, source="mvs+model", model_dir="oracle", planes=3, **kw)
