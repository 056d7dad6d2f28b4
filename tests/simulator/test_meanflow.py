"""MeanFlow maths: ground truth, JVP vs finite differences, numerical stability on hard cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.renderer import meanflow as mf
from image2sim.simulator.renderer.condition import build_condition
from image2sim.simulator.renderer.config import renderer_config_from_dict
from image2sim.simulator.renderer.distill import EMATeacher
from image2sim.simulator.renderer.losses import relative_depth_error
from image2sim.simulator.renderer.model import PixelFlowRenderer

H, W = 16, 32  # smallest panorama the H/16 bottleneck allows: keeps the JVP tests fast


def small_cfg(**overrides):
    """The tiny preset shrunk further so a JVP + backward takes well under a second."""
    base = {
        "height": H,
        "width": W,
        "aligner": {"stem_widths": [8, 8, 12, 16], "token_dim": 16, "heads": 2, "depth": 1},
        "decoder": {
            "widths": [8, 8, 12, 16],
            "bottleneck_dim": 16,
            "bottleneck_depth": 1,
            "heads": 2,
            "time_dim": 16,
            "kernel_size": 3,
            "prior_hidden": 8,  # the preset's MLP prior path, narrower
            "prior_fit_steps": 2,
        },
    }
    for key, value in overrides.items():
        base.setdefault(key, {}).update(value) if isinstance(value, dict) else base.__setitem__(key, value)
    return renderer_config_from_dict(base, preset="tiny")


def make_batch(b=2, alpha=None, depth=None, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn(b, 16, H, W, generator=g)
    rgb = torch.rand(b, 3, H, W, generator=g)
    d = torch.rand(b, 1, H, W, generator=g) * 5 if depth is None else torch.full((b, 1, H, W), float(depth))
    a = torch.rand(b, 1, H, W, generator=g) if alpha is None else torch.full((b, 1, H, W), float(alpha))
    cond = build_condition(feats, rgb, d, a, EquirectCamera(H, W).ray_map()).to(dtype)
    target_rgb = torch.rand(b, 3, H, W, generator=g).to(dtype)
    target_depth = (torch.rand(b, 1, H, W, generator=g) * 5).to(dtype) if depth is None else d.to(dtype)
    noise = torch.randn(b, 4, H, W, generator=g).to(dtype)
    return cond, target_rgb, target_depth, noise


# --- pure formulas ---------------------------------------------------------------------------
def test_alpha_gated_source_ground_truth_per_group():
    prior = torch.tensor([0.2, 0.4, 0.6, 0.3]).view(1, 4, 1, 1).expand(1, 4, 1, 2).clone()
    alpha = torch.tensor([[[[1.0, 0.25]]]])
    noise = torch.ones(1, 4, 1, 2)
    z = mf.alpha_gated_source(prior, alpha, noise, sigma_small=(0.1, 0.01), sigma_large=(1.0, 2.0))
    # alpha = 1: prior + sigma_small; alpha = 0.25: 0.25 prior + (0.25 s + 0.75 l)
    exp_rgb = [[0.2 + 0.1, 0.25 * 0.2 + 0.025 + 0.75]]
    assert torch.allclose(z[0, 0], torch.tensor(exp_rgb), atol=1e-6)
    assert torch.allclose(z[0, 3], torch.tensor([[0.3 + 0.01, 0.25 * 0.3 + 0.0025 + 1.5]]), atol=1e-6)
    # alpha outside [0, 1] is clamped
    z_hi = mf.alpha_gated_source(prior, alpha * 0 + 3.0, noise, (0.1, 0.01), (1.0, 2.0))
    assert torch.allclose(z_hi, prior + torch.tensor([0.1, 0.1, 0.1, 0.01]).view(1, 4, 1, 1))
    with pytest.raises(ValueError):
        mf.alpha_gated_source(prior, alpha, noise[:, :3], (0.1, 0.01), (1.0, 2.0))


def test_path_endpoints_velocity_and_average_velocity():
    x, z = torch.randn(3, 4, 2, 2), torch.randn(3, 4, 2, 2)
    t = torch.tensor([0.0, 0.3, 1.0])
    zt = mf.interpolate(x, z, t)
    assert torch.equal(zt[0], x[0]) and torch.equal(zt[2], z[2])
    h = 1e-3
    fd = (mf.interpolate(x, z, t + h) - mf.interpolate(x, z, t - h)) / (2 * h)
    assert torch.allclose(fd, mf.target_velocity(x, z), atol=1e-3)
    # The exact conditional average velocity on [0, t] is v; x-prediction with x = X recovers it.
    u = mf.average_velocity(zt[1:2], x[1:2], t[1:2], eps=1e-2)
    assert torch.allclose(u, (z - x)[1:2], atol=1e-5)


def test_compound_velocity_stops_gradient_of_dudt():
    u = torch.randn(2, 4, 1, 1, requires_grad=True)
    dudt = torch.randn(2, 4, 1, 1, requires_grad=True)
    V = mf.compound_velocity(u, dudt, torch.tensor([0.5, 0.9]), torch.tensor([0.5, 0.1]))
    assert torch.allclose(V[0], u[0]) and torch.allclose(V[1], u[1] + 0.8 * dudt[1], atol=1e-6)
    V.sum().backward()
    assert dudt.grad is None and torch.equal(u.grad, torch.ones_like(u))


def test_total_derivative_matches_central_differences_analytic():
    """u = (z - x(z, r, t)) / t with a smooth nonlinear x: JVP vs central differences (float64)."""
    torch.manual_seed(0)
    a = torch.randn(1, 4, 3, 3, dtype=torch.float64)

    def x_fn(z, r, t):
        tb, rb = t.view(-1, 1, 1, 1), r.view(-1, 1, 1, 1)
        return torch.tanh(a * z) * (1 + tb**2) + torch.sin(3 * tb - rb) * z**2

    z = torch.randn(2, 4, 3, 3, dtype=torch.float64)
    v = torch.randn_like(z)
    t, r = torch.tensor([0.7, 0.2], dtype=torch.float64), torch.tensor([0.1, 0.2], dtype=torch.float64)
    u, dudt = mf.total_derivative(x_fn, z, r, t, v, eps=1e-3)

    def u_of(s):
        return mf.average_velocity(z + s * v, x_fn(z + s * v, r, t + s), t + s, 1e-3)

    h = 1e-6
    fd = (u_of(h) - u_of(-h)) / (2 * h)
    assert torch.allclose(u, u_of(0.0), atol=1e-12)
    assert torch.allclose(dudt, fd, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("depth_head", ["relu", "log"])
def test_total_derivative_through_the_decoder_matches_finite_differences(depth_head):
    torch.manual_seed(0)
    model = PixelFlowRenderer(small_cfg(decoder={"depth_head": depth_head})).double()
    for p in model.parameters():  # move zero-initialised layers off zero so every path is active
        p.data.add_(0.05 * torch.randn_like(p))
    cond, rgb, depth, noise = make_batch(dtype=torch.float64)
    tokens = model.tokens(cond)
    z = torch.randn(2, 4, H, W, dtype=torch.float64)
    v = torch.randn_like(z)
    t = torch.tensor([0.6, 0.35], dtype=torch.float64)
    r = torch.tensor([0.2, 0.35], dtype=torch.float64)

    def x_fn(z_, r_, t_):
        return model.predict(z_, cond, r_, t_, tokens).x

    u, dudt = mf.total_derivative(x_fn, z, r, t, v, eps=1e-2)
    h = 1e-6

    def u_of(s):
        return mf.average_velocity(z + s * v, x_fn(z + s * v, r, t + s), t + s, 1e-2)

    fd = (u_of(h) - u_of(-h)) / (2 * h)
    err = (dudt - fd).abs().max() / fd.abs().max()
    assert err < 1e-5, err


def test_opacity_weight_and_adaptive_normalisation():
    a = torch.tensor([0.0, 0.5, 1.0, 2.0, -1.0])
    assert torch.allclose(mf.opacity_weight(a, 4.0), torch.tensor([5.0, 3.0, 1.0, 1.0, 5.0]))
    loss = torch.tensor([1e-8, 1.0, 1e12], requires_grad=True)
    out = mf.adaptive_normalise(loss, c=1e-3)
    assert torch.allclose(out, (loss / (loss + 1e-3)).detach())
    out.sum().backward()
    assert torch.allclose(loss.grad, 1.0 / (loss.detach() + 1e-3))  # stop-gradient on the denominator
    assert mf.adaptive_normalise(loss, 1e-3, power=0.0) is loss


def test_sample_time_pairs_distribution():
    g = torch.Generator().manual_seed(0)
    r, t = mf.sample_time_pairs(20000, 0.3, generator=g)
    assert ((t >= 0) & (t < 1)).all() and (r <= t).all() and (r >= 0).all()
    frac_equal = (r == t).float().mean().item()
    assert abs(frac_equal - 0.3) < 0.02
    assert abs(t.mean().item() - 0.5) < 0.01
    # r = t * U(0, 1) when not equal: r / t is uniform with mean 1/2
    ratio = r[r != t] / t[r != t]
    assert abs(ratio.mean().item() - 0.5) < 0.01
    r1, t1 = mf.sample_time_pairs(100, 1.0, generator=g)
    assert torch.equal(r1, t1)


def test_samplers_recover_the_target_with_the_oracle_and_follow_euler_in_average_velocity():
    torch.manual_seed(0)
    x_true, z_src = torch.rand(2, 4, 3, 5), torch.randn(2, 4, 3, 5)

    def oracle(z, r, t):  # the single-sample posterior mean is the target itself
        return x_true

    assert torch.allclose(mf.sample_one_step(oracle, z_src), x_true, atol=1e-6)
    for n in (2, 4, 8):
        assert torch.allclose(mf.sample_n_steps(oracle, z_src, n), x_true, atol=1e-5)
    calls = []

    def recording(z, r, t):
        calls.append((float(t[0]), float(r[0])))
        return 0.5 * z

    out = mf.sample_n_steps(recording, z_src, 4)
    assert calls == [(1.0, 0.75), (0.75, 0.5), (0.5, 0.25), (0.25, 0.0)]
    z = z_src.clone()  # x = z / 2 -> u = z / (2t), z_r = z (1 - (t - r) / (2t))
    for t_, r_ in calls:
        z = z * (1 - (t_ - r_) / (2 * t_))
    assert torch.allclose(out, z, atol=1e-6)
    with pytest.raises(ValueError):
        mf.sample_n_steps(oracle, z_src, 0)
    with pytest.raises(ValueError):
        mf.sample_n_steps(oracle, z_src, 1, times=[1.0, 0.5, 0.7])


def test_pose_noise_is_deterministic_per_pose():
    pose_a = np.eye(4)
    pose_b = np.eye(4)
    pose_b[0, 3] = 0.5
    n1 = mf.pose_noise([pose_a, pose_b], (4, 3, 5))
    n2 = mf.pose_noise(np.stack([pose_b, pose_a]), (4, 3, 5))
    assert torch.equal(n1[0], n2[1]) and torch.equal(n1[1], n2[0])
    assert not torch.allclose(n1[0], n1[1])
    # Rounding below 0.1 mm and -0.0 do not change the noise; the base seed does.
    pose_c = pose_a.copy()
    pose_c[1, 3] = -1e-7
    assert torch.equal(mf.pose_noise([pose_c], (2, 2)), mf.pose_noise([pose_a], (2, 2)))
    assert not torch.equal(mf.pose_noise([pose_a], (2, 2), base_seed=1), mf.pose_noise([pose_a], (2, 2)))
    assert mf.pose_noise([torch.eye(4, dtype=torch.float64)], (2, 2)).equal(mf.pose_noise([pose_a], (2, 2)))
    with pytest.raises(ValueError):
        mf.pose_seed(np.full((4, 4), np.nan))
    with pytest.raises(ValueError):
        mf.pose_seed(np.eye(3))


# --- numerical stability of the full objective --------------------------------------------------
def _losses_and_grads(model, teacher, cond, rgb, depth, noise, r, t, autocast=False):
    """Every term of the objective, the alignment term included (random backbone tokens on a grid
    other than the aligner's, so the resampling path runs too)."""
    model.zero_grad(set_to_none=True)
    tokens = torch.randn(
        cond.shape[0], model.cfg.aligner.token_dim, 3, 5, generator=torch.Generator().manual_seed(1)
    )
    with mf.maybe_autocast(autocast):
        out = model.losses(cond, rgb, depth, noise, r, t, teacher=teacher, target_tokens=tokens)
        total = out["flow"] + out["rec"] + out["distill"] + out["align"] + out["pixel"]
    total.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    return out, total, grads


@pytest.fixture(scope="module", params=["relu", "log"])
def stability_model(request):
    torch.manual_seed(0)
    cfg = small_cfg(loss={"pixel_depth_weight": 1.0}, decoder={"depth_head": request.param})
    model = PixelFlowRenderer(cfg)
    teacher = EMATeacher(model)
    return model, teacher


@pytest.mark.parametrize("r_mode", ["equal", "zero"])
def test_loss_and_grads_finite_at_extreme_times(stability_model, r_mode):
    """t in {0, 1e-8, 1e-3, 1} in one batch (the adaptive normalisation is per sample, so one
    non-finite sample would poison the total and every gradient)."""
    model, teacher = stability_model
    cond, rgb, depth, noise = make_batch(b=4)
    t = torch.tensor([0.0, 1e-8, 1e-3, 1.0])
    r = t.clone() if r_mode == "equal" else torch.zeros(4)
    out, total, grads = _losses_and_grads(model, teacher.module, cond, rgb, depth, noise, r, t)
    assert torch.isfinite(total)
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert out["flow"].item() > 0 and 0 < out["align"].item() <= 2


@pytest.mark.parametrize("case", ["alpha0", "alpha1", "depth0", "bf16"])
def test_loss_and_grads_finite_on_degenerate_conditions(stability_model, case):
    model, teacher = stability_model
    kwargs = {"alpha0": {"alpha": 0.0}, "alpha1": {"alpha": 1.0}, "depth0": {"depth": 0.0}, "bf16": {}}[case]
    cond, rgb, depth, noise = make_batch(**kwargs)
    t = torch.tensor([0.9, 1e-3])
    r = torch.tensor([0.0, 1e-3])
    out, total, grads = _losses_and_grads(
        model, teacher.module, cond, rgb, depth, noise, r, t, autocast=case == "bf16"
    )
    assert torch.isfinite(total) and all(torch.isfinite(g).all() for g in grads)
    assert 0 < out["align"].item() <= 2
    pred_rgb = out["x_one_step"][:, :3]
    if case == "depth0":  # no valid depth: only RGB enters the reconstruction term
        assert torch.allclose(out["rec"], (pred_rgb - rgb).abs().mean(), atol=1e-6)
    # pixel term = e / sg(e + c) per sample for the RGB MSE and the depth's relative error
    c = model.cfg.loss.pixel_norm_c
    mse = (pred_rgb.float() - rgb.float()).pow(2).flatten(1).mean(1)
    pred_depth = out["x_one_step"][:, 3:] * model.cfg.meanflow.depth_scale
    rel = relative_depth_error(pred_depth, depth)
    if case == "depth0":
        assert torch.equal(rel, torch.zeros_like(rel))
    expected = (mse / (mse + c)).mean() + (rel / (rel + c)).mean()
    assert torch.allclose(out["pixel"], expected, atol=1e-2 if case == "bf16" else 1e-5)


def test_relative_depth_error_matches_its_formula_and_skips_invalid_pixels():
    target = torch.tensor([[[[2.0, 4.0], [0.0, float("nan")]]], [[[0.0, 0.0], [0.0, 0.0]]]])
    pred = torch.tensor([[[[3.0, 4.0], [7.0, 7.0]]], [[[1.0, 1.0], [1.0, 1.0]]]])
    err = relative_depth_error(pred, target)
    assert torch.allclose(err, torch.tensor([(0.5**2 + 0.0) / 2, 0.0]))
    assert torch.equal(relative_depth_error(target.nan_to_num(1.0), target.nan_to_num(1.0)), torch.zeros(2))


def test_nan_and_inf_in_splat_outputs_are_sanitised():
    cond, *_ = make_batch()
    feats = torch.randn(2, 16, H, W)
    feats[0, 0, 0, 0] = float("nan")
    rgb = torch.rand(2, 3, H, W)
    rgb[1, 1, 2, 3] = float("inf")
    c = build_condition(
        feats, rgb, torch.rand(2, 1, H, W), torch.rand(2, 1, H, W) * 2, EquirectCamera(H, W).ray_map()
    )
    assert torch.isfinite(c).all() and c[:, 20].max() <= 1.0
    with pytest.raises(ValueError):
        build_condition(
            feats[:, :8], rgb, torch.rand(2, 1, H, W), torch.rand(2, 1, H, W), EquirectCamera(H, W).ray_map()
        )


def test_model_tangent_option_runs_and_differs_from_target_tangent():
    torch.manual_seed(0)
    cond, rgb, depth, noise = make_batch()
    t, r = torch.tensor([0.7, 0.4]), torch.tensor([0.1, 0.0])
    losses = {}
    for tangent in ("target", "model"):
        torch.manual_seed(1)
        model = PixelFlowRenderer(small_cfg(meanflow={"tangent": tangent}))
        out = model.losses(cond, rgb, depth, noise, r, t)
        out["flow"].backward()
        losses[tangent] = out["flow_raw"].item()
        assert np.isfinite(losses[tangent])
    assert losses["target"] != losses["model"]


@pytest.mark.parametrize("tangent", ["target", "model"])
def test_interpolated_prior_runs_through_the_jvp_with_holes(tangent):
    """prior_fill='interpolate' (hole filling inside the residual base) under forward-mode AD: loss
    and gradients finite with an all-zero, a half and an all-one alpha."""
    for alpha in (0.0, 0.5, 1.0):
        torch.manual_seed(0)
        cond, rgb, depth, noise = make_batch(alpha=alpha)
        model = PixelFlowRenderer(
            small_cfg(decoder={"prior_fill": "interpolate"}, meanflow={"tangent": tangent})
        )
        out = model.losses(cond, rgb, depth, noise, torch.tensor([0.2, 0.0]), torch.tensor([0.7, 1e-8]))
        total = out["flow"] + out["rec"] + out["pixel"]
        total.backward()
        assert torch.isfinite(total)
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_flow_loss_alone_trains_every_parameter_through_the_jvp_primal():
    """u from torch.func.jvp keeps its autograd graph: the aligner (whose tokens enter the JVP as
    captured tensors) and every decoder parameter receive gradient from the flow term alone."""
    torch.manual_seed(0)
    model = PixelFlowRenderer(small_cfg())
    for p in model.parameters():  # off the zero inits, which block some paths at initialisation
        p.data.add_(0.05 * torch.randn_like(p))
    cond, rgb, depth, noise = make_batch()
    out = model.losses(cond, rgb, depth, noise, torch.tensor([0.2, 0.1]), torch.tensor([0.7, 0.5]))
    out["flow"].backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert missing == []


def test_saturation_penalty_enters_the_flow_term_through_the_implied_clean_colour():
    """flow = normalised flow loss + loss.saturation * penalty(z_t - t * V): the difference between
    two weights is exactly the penalty of the colour the compound velocity implies."""
    import dataclasses

    torch.manual_seed(0)
    model = PixelFlowRenderer(small_cfg())
    with torch.no_grad():  # away from the residual heads' identity start, so colours overshoot
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    cond, rgb, depth, noise = make_batch(b=2)
    t, r = torch.tensor([0.9, 0.6]), torch.tensor([0.2, 0.6])
    flows = []
    for weight in (0.0, 5.0):
        model.cfg = dataclasses.replace(
            model.cfg, loss=dataclasses.replace(model.cfg.loss, saturation=weight)
        )
        with torch.no_grad():
            flows.append(model.losses(cond, rgb, depth, noise, r, t)["flow"])
    # Reference: the implied colour from the same model pieces, computed by hand.
    m = model.cfg.meanflow
    from image2sim.simulator.renderer.losses import saturation_penalty
    from image2sim.simulator.renderer.model import prior_state, to_state

    target = to_state(rgb, depth.clamp_min(0), m.depth_scale)
    prior, alpha = prior_state(cond, m.depth_scale)
    z_src = mf.alpha_gated_source(prior, alpha, noise, m.sigma_small, m.sigma_large)
    z_t = mf.interpolate(target, z_src, t)
    tokens = model.tokens(cond)

    def x_fn(z, r_, t_):
        return model.predict(z, cond, r_, t_, tokens).x

    u, dudt = mf.total_derivative(x_fn, z_t, r, t, mf.target_velocity(target, z_src), m.t_eps)
    V = mf.compound_velocity(u, dudt, t, r)
    penalty = saturation_penalty(z_t[:, :3] - t.view(-1, 1, 1, 1) * V[:, :3])
    assert penalty > 0  # a random model implies colours outside [0, 1]
    torch.testing.assert_close(flows[1] - flows[0], 5.0 * penalty, rtol=1e-4, atol=1e-6)
