"""Rendering benchmark: scores against a slow reference, FPS after warm-up, render.json layout, plot."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import torch
from image2sim.eval.plots import plot_speed_vs_error, speed_points
from image2sim.eval.render_bench import (
    HEADLINE_METHODS,
    RenderBenchConfig,
    benchmark_methods,
    load_renderer,
    method_record,
    run_render_bench,
)
from image2sim.eval.render_samples import NOISE_TIERS, RenderBenchError, tier_samples
from image2sim.eval.results import read_metrics_file

from .test_metrics_files import assert_metrics_only


@pytest.fixture(scope="module")
def held():
    from image2sim.simulator.renderer.data import smooth_test_panorama

    return [smooth_test_panorama(32, 64, seed=i) for i in range(3)]


def _splat_only():
    from dataclasses import replace

    from image2sim.simulator.renderer.config import load_renderer_config

    cfg = load_renderer_config("tiny")
    model = load_renderer(replace(cfg, ablation=replace(cfg.ablation, no_pixel_flow=True)), None)

    def fn(cond, poses):
        out = model.render(cond, steps=1, poses=list(poses))
        return out.rgb, out.depth

    return fn


def _reference_psnr_absrel(pred_rgb, pred_depth, rgb, depth):
    """Slow textbook reference: per-view PSNR and depth AbsRel over valid target pixels, in float64."""
    p, t = pred_rgb.double().numpy(), rgb.double().numpy()
    mse = ((p - t) ** 2).mean()
    psnr = 10 * math.log10(1.0 / mse)
    pd, td = pred_depth.double().numpy().ravel(), depth.double().numpy().ravel()
    valid = td > 0
    return psnr, float(np.mean(np.abs(pd[valid] - td[valid]) / td[valid]))


def test_scores_match_a_slow_reference_and_tiers_order_the_error(held):
    samples = {t: tier_samples(held, t, seed=3, max_views=None) for t in ("none", "high")}
    fn = _splat_only()
    cells = benchmark_methods({"splat_only": fn}, samples, warmup=0, runs=1)
    for tier, ss in samples.items():
        refs = []
        for s in ss:
            rgb, depth = fn(s["condition"][None], torch.eye(4, dtype=torch.float64)[None])
            refs.append(_reference_psnr_absrel(rgb[0], depth[0], s["target_rgb"], s["target_depth"]))
        cell = cells["splat_only"][tier]
        assert cell.num_views == len(held)
        assert cell.metrics["psnr"].mean == pytest.approx(np.mean([r[0] for r in refs]), rel=1e-4)
        assert cell.metrics["abs_rel"].mean == pytest.approx(np.mean([r[1] for r in refs]), rel=1e-4)
        assert cell.metrics["lpips"].mean is None  # no weights configured: n/a, never 0
        # Per-view PSNRs are kept (named tier/index) and match the reference one by one.
        per_view = method_record(cells["splat_only"])["tiers"][tier]["psnr_per_view"]
        assert list(per_view) == [f"{tier}/{s['index']}" for s in ss]
        assert list(per_view.values()) == pytest.approx([r[0] for r in refs], rel=1e-4)
    # More noise and larger holes in the high tier -> a worse splat prior.
    assert cells["splat_only"]["high"].metrics["psnr"].mean < cells["splat_only"]["none"].metrics["psnr"].mean


def test_a_perfect_method_scores_infinite_psnr_and_zero_depth_error(held):
    samples = {"none": tier_samples(held, "none", seed=0, max_views=2)}

    def oracle(cond, poses):
        # Finds the sample by condition identity (the benchmark passes views unchanged).
        s = next(v for v in samples["none"] if torch.equal(v["condition"], cond[0]))
        return s["target_rgb"][None], s["target_depth"][None]

    cells = benchmark_methods({"perfect": oracle}, samples, warmup=0, runs=1)
    rec = method_record(cells["perfect"])
    assert rec["psnr"] is None  # +inf is not a finite headline number: reported as null
    assert cells["perfect"]["none"].metrics["psnr"].mean == math.inf
    assert set(rec["tiers"]["none"]["psnr_per_view"].values()) == {None}  # infinite per view: null
    assert rec["ssim"] == pytest.approx(1.0) and rec["depth_absrel"] == 0.0 and rec["depth_delta1"] == 1.0


def test_fps_excludes_warm_up_calls(held):
    samples = {"none": tier_samples(held, "none", seed=0, max_views=1)}
    calls = {"n": 0}

    def slow_start(cond, poses):
        calls["n"] += 1
        time.sleep(0.25 if calls["n"] <= 2 else 0.002)  # the first two calls pay a one-off cost
        return cond[:, 16:19], cond[:, 19:20]

    warm = benchmark_methods({"m": slow_start}, samples, warmup=2, runs=5)["m"]["none"]
    assert warm.fps > 40  # ~ 1 / 0.002 s minus overhead; with the warm-up timed it would be < 4
    calls["n"] = 0
    cold = benchmark_methods({"m": slow_start}, samples, warmup=0, runs=3)["m"]["none"]
    assert cold.fps < warm.fps  # the median of (0.25, 0.25, 0.002) s: the one-off cost shows
    assert cold.fps < 10


def test_fps_includes_the_condition_splatting_time_when_known(held):
    samples = [dict(s, condition_seconds=0.5) for s in tier_samples(held, "none", seed=0, max_views=1)]

    def instant(cond, poses):
        return cond[:, 16:19], cond[:, 19:20]

    cell = benchmark_methods({"m": instant}, {"none": samples}, warmup=1, runs=3)["m"]["none"]
    assert 1.0 < cell.fps <= 2.0  # end to end: at most 1 / 0.5 s of splatting per frame
    plain = benchmark_methods({"m": instant}, {"none": tier_samples(held, "none", seed=0, max_views=1)})
    assert plain["m"]["none"].fps > 10 * cell.fps
    # Views of two captures with different splatting times: the view-weighted mean counts, not the
    # first capture's (2 views at 0.1 s, 1 at 0.7 s -> 0.3 s per frame).
    views = tier_samples(held, "none", seed=0, max_views=3)
    mixed = [dict(s, condition_seconds=0.1 if k < 2 else 0.7) for k, s in enumerate(views)]
    both = benchmark_methods({"m": instant}, {"none": mixed}, warmup=1, runs=3)["m"]["none"]
    assert 1 / 0.3 * 0.8 < both.fps <= 1 / 0.3


def test_method_record_weights_tiers_by_views(held):
    s_none = tier_samples(held, "none", seed=0, max_views=3)
    s_high = tier_samples(held, "high", seed=0, max_views=1)
    cells = benchmark_methods(
        {"splat_only": _splat_only()}, {"none": s_none, "high": s_high}, warmup=0, runs=1
    )
    c = cells["splat_only"]
    rec = method_record(c)
    expect = (3 * c["none"].metrics["psnr"].mean + 1 * c["high"].metrics["psnr"].mean) / 4
    assert rec["psnr"] == pytest.approx(expect)
    assert rec["n_views"] == 4 and set(rec["tiers"]) == {"none", "high"}
    for key in ("psnr", "ssim", "depth_absrel", "fps", "n_views"):
        assert key in rec


def test_config_validation():
    with pytest.raises(RenderBenchError, match="unknown key"):
        RenderBenchConfig.from_dict({"stepz": [1]})
    with pytest.raises(RenderBenchError, match="tiers"):
        RenderBenchConfig(tiers=["extreme"])
    with pytest.raises(RenderBenchError, match="ablations"):
        RenderBenchConfig(ablations={"no_magic": "x.ckpt"})
    with pytest.raises(RenderBenchError, match="steps"):
        RenderBenchConfig(steps=[0])
    assert set(NOISE_TIERS) == {"none", "middle", "high"}
    with pytest.raises(RenderBenchError, match="not found"):
        from image2sim.simulator.renderer.config import load_renderer_config

        load_renderer(load_renderer_config("tiny"), "/nonexistent.ckpt")


def test_speed_points_and_plot(tmp_path):
    doc = {
        "protocol": {"resolution": [128, 256]},
        "methods": {
            "flow_2step": {"fps": 2.0, "psnr": 25.0},
            "splat_only": {"fps": 500.0, "psnr": 18.0},
            "flow_1step": {"fps": 4.0, "psnr": 24.0},
            "ablation_no_semantic": {"fps": 4.0, "psnr": None},
        },
    }
    pts = speed_points(doc)
    assert [p.method for p in pts] == ["flow_1step", "flow_2step", "splat_only"]
    assert pts[0].steps == 1 and pts[-1].steps is None
    out = plot_speed_vs_error(doc, tmp_path / "plots" / "speed.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="methods"):
        speed_points({})


@pytest.mark.slow
def test_run_render_bench_writes_headline_methods(tmp_path):
    bench = RenderBenchConfig(holdout_every=8, max_views=1, tiers=["middle"], warmup=1, runs=2)
    doc = run_render_bench(bench, tmp_path / "metrics" / "render.json", show_progress=False)
    on_disk = read_metrics_file(tmp_path / "metrics" / "render.json")
    assert on_disk == json.loads(json.dumps(doc))
    for m in HEADLINE_METHODS:
        rec = on_disk["methods"][m]
        for key in ("psnr", "ssim", "depth_absrel", "fps", "n_views"):
            assert key in rec
        assert rec["n_views"] == 1 and rec["fps"] > 0
    assert on_disk["protocol"]["trained"] is False
    # Splat-only involves no network: it is much faster than any flow step count.
    assert on_disk["methods"]["splat_only"]["fps"] > on_disk["methods"]["flow_1step"]["fps"]


def test_cli_render_then_report(tmp_path):
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    out = tmp_path / "metrics" / "render.json"
    res = CliRunner().invoke(
        app,
        [
            "render",
            "--steps",
            "1",
            "--tier",
            "none",
            "--max-views",
            "1",
            "--warmup",
            "0",
            "--runs",
            "1",
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "speed.png"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert_metrics_only(out)  # render.json: numbers only, the protocol in render.protocol.json
    doc = read_metrics_file(out)
    assert set(doc["methods"]) == {"splat_only", "splat_fill", "flow_1step"}
    assert doc["protocol"]["not_evaluated"] == ["flow_2step", "flow_4step", "flow_8step"]
    assert (tmp_path / "speed.png").stat().st_size > 0
    res = CliRunner().invoke(app, ["report", "--render", str(out), "--out-dir", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "rep" / "render.md").read_text()
    assert "| splat_only |" in md and "PSNR↑ (none)" in md and "untrained" in md
    assert (tmp_path / "rep" / "render_speed.png").read_bytes()[:4] == b"\x89PNG"


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    """A tiny procedural capture on disk (4 equirect frames, 64 x 128)."""
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    out = tmp_path_factory.mktemp("captures") / "scene_000"
    write_scene(generate_scene(preset("tiny"), seed=0), out)
    return out


def test_splat_samples_hold_out_the_renderer_split_and_splat_the_other_frames(tiny_capture):
    from image2sim.eval.render_samples import splat_samples
    from image2sim.simulator.renderer.config import CONDITION_FEATURES

    samples = splat_samples([tiny_capture], 32, 64, holdout_every=4)
    assert [s["index"] for s in samples] == [3]  # frames 0-2 build the Gaussians, frame 3 is held out
    s = samples[0]
    cond = s["condition"]
    assert cond.shape == (24, 32, 64) and torch.isfinite(cond).all()
    assert (cond[:CONDITION_FEATURES] == 0).all()  # identity Gaussians carry no features
    alpha = cond[CONDITION_FEATURES + 4]
    assert 0.2 < float(alpha.mean()) <= 1.0  # the neighbouring frames cover much of the held-out view
    # Where the splat covers the view, its expected range agrees with the held-out target's. Measured:
    # 7.6 % median relative error here; the tiny Gaussian preset shows 8.7 % even on a training view.
    covered = (alpha > 0.9) & (s["target_depth"][0] > 0)
    rel = (cond[CONDITION_FEATURES + 3][covered] - s["target_depth"][0][covered]).abs() / s["target_depth"][
        0
    ][covered]
    assert float(rel.median()) < 0.15
    with pytest.raises(RenderBenchError, match="gaussians"):
        RenderBenchConfig(condition_source="gaussians")
    with pytest.raises(RenderBenchError, match="tier_data"):
        RenderBenchConfig(tier_data={"none": ["x"]})


def test_splat_samples_with_sparse_sources_splat_only_every_nth_training_frame(tiny_capture):
    from image2sim.eval.render_samples import splat_condition, splat_samples
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians.config import load_gaussian_config
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.io.registry import open_capture

    sparse = splat_samples([tiny_capture], 32, 64, holdout_every=4, source_every=2)
    dense = splat_samples([tiny_capture], 32, 64, holdout_every=4)
    assert [s["index"] for s in sparse] == [3]  # the same held-out view
    g = build_scene(tiny_capture, load_gaussian_config("tiny"), encoder="identity", frames=[0, 2]).gaussians
    pose = open_capture(tiny_capture)[3].cam_to_world
    torch.testing.assert_close(sparse[0]["condition"], splat_condition(g, EquirectCamera(32, 64), pose))
    assert not torch.equal(sparse[0]["condition"], dense[0]["condition"])
    with pytest.raises(RenderBenchError, match="source_every"):
        RenderBenchConfig(source_every=0)


@pytest.mark.slow
def test_run_render_bench_on_splatted_gaussians(tiny_capture, tmp_path):
    bench = RenderBenchConfig(
        condition_source="gaussians",
        tier_data={"none": [str(tiny_capture)]},
        holdout_every=4,
        steps=[1],
        warmup=0,
        runs=1,
    )
    doc = run_render_bench(bench, tmp_path / "render.json", show_progress=False)
    assert doc["protocol"]["condition_source"].startswith("gaussians")
    assert doc["protocol"]["data"] == [str(tiny_capture)]  # the tier captures, not a placeholder
    assert doc["protocol"]["held_out_views"] == 1
    assert set(doc["methods"]) == {"splat_only", "splat_fill", "flow_1step"}
    assert doc["methods"]["splat_only"]["n_views"] == 1 and doc["methods"]["splat_only"]["psnr"] > 10


@pytest.fixture(scope="module")
def middle_capture(tmp_path_factory):
    """The tiny procedural scene captured at the `middle` noise tier (noisy RGB and depth, jittered poses)."""
    from dataclasses import replace as dc_replace

    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    out = tmp_path_factory.mktemp("captures_middle") / "scene_000"
    write_scene(generate_scene(dc_replace(preset("tiny"), noise="middle"), seed=0), out)
    return out


def test_exact_targets_reproduce_a_noise_free_capture(tiny_capture, tmp_path):
    from image2sim.eval.render_samples import exact_targets
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.renderer.data import load_capture_targets

    capture = open_capture(tiny_capture)
    exact = exact_targets(tiny_capture, [capture[i].cam_to_world for i in range(len(capture))], 32, 64)
    frames = load_capture_targets(tiny_capture, 32, 64)
    assert len(exact) == len(frames) == 4
    for (rgb, depth), (rgb_c, depth_c) in zip(exact, frames, strict=True):
        assert torch.equal(rgb, rgb_c)
        assert torch.allclose(depth, depth_c, atol=1e-3, rtol=0)  # frames store depth in millimetres
    assert exact_targets(tmp_path, [np.eye(4)], 32, 64) is None  # not a procedural capture


def test_middle_tier_views_are_scored_against_exact_ground_truth_not_the_noisy_capture(middle_capture):
    from image2sim.eval.render_samples import exact_targets, splat_samples
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.renderer.data import load_capture_targets

    auto = splat_samples([middle_capture], 32, 64, holdout_every=4)
    captured = splat_samples([middle_capture], 32, 64, holdout_every=4, target="capture")
    assert [s["index"] for s in auto] == [s["index"] for s in captured] == [3]
    assert auto[0]["target_kind"] == "exact" and captured[0]["target_kind"] == "capture"
    frame_rgb, frame_depth = load_capture_targets(middle_capture, 32, 64)[3]
    assert torch.equal(captured[0]["target_rgb"], frame_rgb)
    # The exact target is the noise-free rendering at the queried (stored) pose ...
    pose = open_capture(middle_capture)[3].cam_to_world
    ((rgb, depth),) = exact_targets(middle_capture, [pose], 32, 64)
    assert torch.equal(auto[0]["target_rgb"], rgb) and torch.equal(auto[0]["target_depth"], depth)
    # ... which differs from the noisy captured frame (RGB noise; depth noise and holes).
    assert (auto[0]["target_rgb"] - frame_rgb).abs().max() > 0
    assert (depth > 0).float().mean() >= (frame_depth > 0).float().mean()
    assert not torch.equal(depth, frame_depth)
    with pytest.raises(RenderBenchError, match="target"):
        RenderBenchConfig(condition_source="gaussians", data=["x"], target="noisy")
