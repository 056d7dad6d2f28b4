"""Splatted training conditions (renderer.splat_data): parity with a direct splat, leave-target-out,
cache hit/miss, determinism, split and config checks. Captures are tiny analytic box rooms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.canonical import write_capture
from image2sim.simulator.io.records import Frame
from image2sim.simulator.renderer import splat_data as sd
from image2sim.simulator.renderer.condition import ALPHA, DEPTH, RGB

H, W = 32, 64
HALF = np.array([3.0, 2.0, 1.5])  # box room half-extents (x, y, z) around the origin


def _gcfg():
    from image2sim.simulator.gaussians.config import tiny

    g = tiny()
    return dataclasses.replace(g, encoder=dataclasses.replace(g.encoder, height=H, width=W))


def _pose(centre) -> np.ndarray:
    """Camera looking along world +X, Z up (OpenCV camera: x right = -Y, y down = -Z, z fwd = +X)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = centre
    return T


def _box_frame(centre, invalid_left: bool = False, name: str = "") -> Frame:
    """Exact range / colour of the box room seen from ``centre``; optionally no depth on the left half."""
    pose = _pose(np.asarray(centre, dtype=np.float64))
    rays = EquirectCamera(H, W).ray_map(torch.float64).numpy().reshape(3, -1)
    d = pose[:3, :3] @ rays
    c = pose[:3, 3][:, None]
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (HALF[:, None] - c) / d, np.where(d < 0, (-HALF[:, None] - c) / d, np.inf))
    rng = t.min(axis=0)
    hit = c + d * rng
    rgb = np.stack(
        [0.5 + 0.4 * np.sin(2.0 * hit[0]), 0.5 + 0.4 * np.cos(1.7 * hit[1]), 0.3 + 0.2 * hit[2] / 1.5]
    )
    rgb = (np.clip(rgb, 0, 1).T.reshape(H, W, 3) * 255).round().astype(np.uint8)
    depth = rng.reshape(H, W).astype(np.float32)
    if invalid_left:
        depth[:, : W // 2] = 0.0
    return Frame(rgb=rgb, depth=depth, camera=EquirectCamera(H, W), cam_to_world=pose, frame_id=name)


@pytest.fixture(scope="module")
def box_capture(tmp_path_factory):
    centres = [(0.0, 0.0, 0.0), (0.4, 0.1, 0.0), (-0.3, 0.3, 0.1), (0.2, -0.4, 0.0)]
    frames = [_box_frame(c, name=f"{i:05d}") for i, c in enumerate(centres)]
    return write_capture(tmp_path_factory.mktemp("cap") / "box", frames, scene_id="box")


@pytest.fixture(scope="module")
def half_capture(tmp_path_factory):
    """Three frames at one pose: frame 1 sees everything, frames 0 and 2 only the right half."""
    frames = [_box_frame((0, 0, 0), invalid_left=(i != 1), name=f"{i:05d}") for i in range(3)]
    return write_capture(tmp_path_factory.mktemp("cap") / "half", frames, scene_id="half")


def test_condition_matches_a_direct_splat_of_the_other_frames(box_capture):
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.splatting import splat

    cfg = sd.SplatDataConfig(holdout_every=0, fuse_every=1)
    ds = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=_gcfg())
    assert len(ds) == 4 and ds.num_degraded == 0
    for target in (0, 2):
        # Independent path: the scene-building API over the other frames, then a raw splat call.
        others = [i for i in range(4) if i != target]
        g = build_scene(box_capture, _gcfg(), frames=others, fuse_every=1).gaussians
        pose = torch.as_tensor(
            _pose(np.array([(0, 0, 0), (0.4, 0.1, 0), (-0.3, 0.3, 0.1), (0.2, -0.4, 0)][target]))
        )
        out = splat(
            g.means, g.scales, g.quats, g.opacities, g.colors, None, EquirectCamera(H, W), pose.float()
        )
        item = ds[target]
        cond = item["condition"]
        assert cond.shape == (24, H, W) and torch.isfinite(cond).all()
        torch.testing.assert_close(cond[ALPHA][0], out.alpha[0, 0], atol=1e-5, rtol=0)
        seen = out.alpha[0, 0] > 0.05
        torch.testing.assert_close(
            cond[RGB][:, seen], (out.rgb[0] / out.alpha[0])[:, seen], atol=1e-4, rtol=0
        )
        # The target is the frame itself, area-resized (here: same size).
        assert item["target_rgb"].shape == (3, H, W) and item["target_depth"].shape == (1, H, W)
        # A covered pixel's expected range agrees with the exact one (box room, nearby frames).
        covered = (cond[ALPHA][0] > 0.9) & (item["target_depth"][0] > 0)
        rel = (cond[DEPTH][0][covered] - item["target_depth"][0][covered]).abs() / item["target_depth"][0][
            covered
        ]
        assert covered.float().mean() > 0.5 and float(rel.median()) < 0.1


def test_target_frame_gaussians_are_excluded(half_capture):
    cfg = sd.SplatDataConfig(holdout_every=0, fuse_every=1)
    ds = sd.SplatConditionDataset([half_capture], H, W, cfg, gaussian_config=_gcfg())
    # Away from the poles, where all longitudes meet and the right half's ceiling/floor Gaussians
    # legitimately cover the left half's columns too.
    interior_left = (slice(8, H - 8), slice(6, W // 2 - 6))
    interior_right = (slice(8, H - 8), slice(W // 2 + 6, W - 6))
    # Target 1 is the only frame that saw the left half: its condition has nothing there.
    a1 = ds[1]["condition"][ALPHA][0]
    assert float(a1[interior_left].max()) < 1e-3
    assert float(a1[interior_right].min()) > 0.9
    # Targets 0 and 2 have frame 1 among their sources, so the left half is covered for them.
    for t in (0, 2):
        assert float(ds[t]["condition"][ALPHA][0][interior_left].min()) > 0.9


def test_cache_hit_and_miss(box_capture, tmp_path, monkeypatch):
    cfg = sd.SplatDataConfig(holdout_every=0, cache_dir=str(tmp_path / "cache"))
    first = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=_gcfg())
    assert [s.cached for s in first.sources] == [False]
    files = sorted((tmp_path / "cache").glob("*.safetensors"))
    assert len(files) == 1 and not list((tmp_path / "cache").glob(".*tmp*"))

    def no_rebuild(*args, **kwargs):
        raise AssertionError("a cache hit must not re-encode frames")

    monkeypatch.setattr(sd, "encode_capture", no_rebuild)
    second = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=_gcfg())
    assert [s.cached for s in second.sources] == [True]
    assert torch.equal(first.conditions, second.conditions)
    monkeypatch.undo()
    # Another Gaussian config or another target list is a miss (a new file).
    g = _gcfg()
    g = dataclasses.replace(g, fusion=dataclasses.replace(g.fusion, base_voxel=0.02))
    third = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=g)
    split = dataclasses.replace(cfg, holdout_every=4)
    fourth = sd.SplatConditionDataset([box_capture], H, W, split, gaussian_config=_gcfg())
    assert [s.cached for s in third.sources + fourth.sources] == [False, False]
    assert len(list((tmp_path / "cache").glob("*.safetensors"))) == 3
    assert len(fourth) == 3  # frame 3 held out


def test_deterministic_and_split_matches_sim_train(box_capture, half_capture):
    from image2sim.simulator.renderer.cli import _split

    cfg = sd.SplatDataConfig(holdout_every=3)
    a = sd.SplatConditionDataset([box_capture, half_capture], H, W, cfg, gaussian_config=_gcfg())
    b = sd.SplatConditionDataset([box_capture, half_capture], H, W, cfg, gaussian_config=_gcfg())
    assert torch.equal(a.conditions, b.conditions)
    # One capture per spawned process: the same conditions, targets and sources, in capture order.
    c = sd.SplatConditionDataset([box_capture, half_capture], H, W, cfg, gaussian_config=_gcfg(), workers=2)
    assert torch.equal(a.conditions, c.conditions) and torch.equal(a.target_rgb, c.target_rgb)
    assert [s.frames for s in c.sources] == [s.frames for s in a.sources]
    # Global counting over captures: frames 2 (box) and 1 (half, global 5) are held out.
    assert [s.frames for s in a.sources] == [[0, 1, 3], [0, 2]]
    lengths = [4, 3, 9, 1]
    split = sd.holdout_split(lengths, 4)
    flat = list(range(sum(lengths)))
    train, held = _split(flat, 4)
    offsets = np.cumsum([0] + lengths[:-1])
    assert [o + i for o, (h, _) in zip(offsets, split, strict=True) for i in h] == held
    assert [o + i for o, (_, t) in zip(offsets, split, strict=True) for i in t] == train
    assert sd.holdout_split([5], 0) == [([], [0, 1, 2, 3, 4])]


def test_degraded_mix_and_neighbours(box_capture):
    cfg = sd.SplatDataConfig(holdout_every=0, degraded_fraction=0.5, neighbours=1)
    ds = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=_gcfg())
    assert ds.num_splat == 4 and ds.num_degraded == 4 and len(ds) == 8
    assert [ds[i]["source"] for i in (0, 3, 4, 7)] == ["splat", "splat", "degraded", "degraded"]
    assert ds[5]["condition"].shape == (24, H, W)
    with pytest.raises(IndexError):
        ds[8]
    poses = {
        i: _pose(np.array(c))
        for i, c in enumerate([(0, 0, 0), (0.4, 0.1, 0), (-0.3, 0.3, 0.1), (0.2, -0.4, 0)])
    }
    assert sd._sources_for(0, [0, 1, 2, 3], poses, 1) == [1]  # distances 0.41 < 0.44 < 0.45
    assert sd._sources_for(0, [0, 1, 2, 3], poses, 2) == [1, 2]
    assert sd._sources_for(0, [0, 1, 2, 3], poses, 0) == [1, 2, 3]


def test_sparse_sources_build_every_target_from_every_nth_training_frame(box_capture):
    from image2sim.simulator.gaussians import build_scene

    assert sd.source_frames([0, 1, 3, 4, 5], 2) == [0, 3, 5]
    assert sd.source_frames([0, 1, 3], 1) == [0, 1, 3]
    with pytest.raises(sd.SplatDataError, match="source_every"):
        sd.source_frames([0, 1], 0)
    cfg = sd.SplatDataConfig(holdout_every=0, fuse_every=1, source_every=2)
    ds = sd.SplatConditionDataset([box_capture], H, W, cfg, gaussian_config=_gcfg())
    assert len(ds) == 4  # every training frame stays a target; only frames 0 and 2 are sources
    centres = [(0, 0, 0), (0.4, 0.1, 0), (-0.3, 0.3, 0.1), (0.2, -0.4, 0)]
    for target, sources in ((1, [0, 2]), (3, [0, 2]), (0, [2]), (2, [0])):
        g = build_scene(box_capture, _gcfg(), frames=sources, fuse_every=1).gaussians
        direct = sd.gaussians_condition(g, EquirectCamera(H, W), _pose(np.array(centres[target])))
        torch.testing.assert_close(ds[target]["condition"], direct, atol=1e-5, rtol=0)
    # Fewer sources than the leave-target-out construction needs is an error naming the setting.
    with pytest.raises(sd.SplatDataError, match="source_every=4"):
        sd.SplatConditionDataset(
            [box_capture], H, W, dataclasses.replace(cfg, source_every=4), gaussian_config=_gcfg()
        )
    with pytest.raises(sd.SplatDataError, match="source_every"):
        sd.SplatDataConfig(source_every=0).validate()


def test_config_errors(box_capture):
    with pytest.raises(sd.SplatDataError, match="unknown key"):
        sd.splat_data_config_from_dict({"holdout": 3})
    with pytest.raises(sd.SplatDataError, match="degraded_fraction"):
        sd.splat_data_config_from_dict({"degraded_fraction": 1.0})
    with pytest.raises(sd.SplatDataError, match="fuse_every"):
        sd.SplatDataConfig(fuse_every=0).validate()
    with pytest.raises(sd.SplatDataError, match="at least 2"):
        sd.SplatConditionDataset(
            [box_capture], H, W, sd.SplatDataConfig(max_frames=1), gaussian_config=_gcfg()
        )
    with pytest.raises(sd.SplatDataError, match="at least one capture"):
        sd.SplatConditionDataset([], H, W)
    with pytest.raises(sd.SplatDataError, match="workers"):
        sd.SplatConditionDataset(
            [box_capture], H, W, sd.SplatDataConfig(), gaussian_config=_gcfg(), workers=0
        )


@pytest.mark.slow
def test_renderer_eval_scores_splatted_conditions_like_eval_render(box_capture, tmp_path):
    """`sim renderer-eval` (default) runs the render benchmark on Gaussian-splat conditions, not on
    synthetic degradations: its numbers are those of `eval render --condition-source gaussians`."""
    pytest.importorskip("image2sim.eval.render_bench")

    from image2sim.eval.render_bench import RenderBenchConfig, run_render_bench
    from image2sim.simulator.cli import sim_app
    from image2sim.simulator.renderer.model import PixelFlowRenderer, save_renderer
    from typer.testing import CliRunner

    from .test_meanflow import small_cfg

    torch.manual_seed(0)
    cfg = small_cfg(height=H, width=W)
    weights = tmp_path / "r.safetensors"
    save_renderer(PixelFlowRenderer(cfg), weights)
    args = ["renderer-eval", str(weights), "--data", str(box_capture), "--holdout-every", "4", "--steps", "1"]
    result = CliRunner().invoke(sim_app, [*args, "--report", str(tmp_path / "rep")])
    assert result.exit_code == 0, result.output
    from image2sim.eval.results import read_metrics_file

    doc = read_metrics_file(tmp_path / "rep.json")
    assert doc["protocol"]["condition_source"].startswith("gaussians")
    assert doc["protocol"]["held_out_views"] == 1  # frame 3; frames 0-2 build the Gaussians
    assert set(doc["methods"]) == {"splat_only", "splat_fill", "flow_1step"}
    assert (tmp_path / "rep.md").read_text().startswith("# Renderer evaluation")
    import yaml
    from image2sim.simulator.renderer.config import config_to_dict

    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(yaml.safe_dump(config_to_dict(cfg)))
    bench = RenderBenchConfig(
        renderer_config=str(cfg_file),
        checkpoint=str(weights),
        data=[str(box_capture)],
        holdout_every=4,
        steps=[1],
        condition_source="gaussians",
    )
    ref = run_render_bench(bench, tmp_path / "ref.json", show_progress=False)
    for m in ("splat_only", "flow_1step"):
        assert doc["methods"][m]["psnr"] == pytest.approx(ref["methods"][m]["psnr"], abs=1e-9)


def test_training_record_is_found_from_a_checkpoint_and_names_every_protocol_difference(tmp_path):
    gcfg = _gcfg()
    cfg = sd.SplatDataConfig(source_every=2, holdout_every=4)
    record = sd.training_record(["cap/a"], cfg, gcfg)
    sd.write_training_record(tmp_path / "run", record)
    (tmp_path / "run" / "checkpoints").mkdir()
    for ckpt in ("run/checkpoints/last.ckpt", "run/weights.safetensors"):
        assert sd.find_training_record(tmp_path / ckpt) == record
    assert sd.find_training_record(tmp_path / "elsewhere" / "x.ckpt") is None
    assert sd.protocol_mismatches(record, gcfg, source_every=2, holdout_every=4) == []
    sharp = dataclasses.replace(gcfg, encoder=dataclasses.replace(gcfg.encoder, scale_init=0.3))
    lines = sd.protocol_mismatches(record, sharp, source_every=1, holdout_every=4)
    assert len(lines) == 2
    assert lines[0].startswith("gaussians.encoder.scale_init: trained") and "0.3" in lines[0]
    assert lines[1] == "source_every: trained 2, evaluated 1"
    # Stage-1 training settings do not shape the conditions; records from before the trainer
    # section existed are not flagged either.
    older = {**record, "gaussians": {k: v for k, v in record["gaussians"].items() if k != "trainer"}}
    other_training = dataclasses.replace(gcfg, train=dataclasses.replace(gcfg.train, steps=7, lr=0.5))
    assert sd.protocol_mismatches(older, other_training, source_every=2, holdout_every=4) == []
    degraded = {"condition_source": "degraded", "captures": []}
    assert sd.protocol_mismatches(degraded, gcfg, 1, 4) == [
        "trained on 'degraded' conditions, evaluated on splats"
    ]
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / sd.TRAINING_RECORD).write_text("{not json")
    with pytest.raises(sd.SplatDataError, match="training_data.json"):
        sd.find_training_record(tmp_path / "bad" / "x.ckpt")


def test_sim_train_records_its_conditions_and_eval_render_flags_a_different_protocol(box_capture, tmp_path):
    """`sim train` writes training_data.json next to config.json; the render benchmark reads it from
    the checkpoint's run and lists (and logs) every way its own conditions differ."""
    pytest.importorskip("image2sim.eval.render_bench")
    import json

    import yaml
    from image2sim.eval.render_bench import RenderBenchConfig, render_markdown, run_render_bench
    from image2sim.simulator.cli import sim_app
    from image2sim.simulator.renderer.config import config_to_dict
    from typer.testing import CliRunner

    from .test_meanflow import small_cfg

    cfg = config_to_dict(small_cfg(height=H, width=W))
    cfg["curriculum"].update(stage2_start=1, stage3_start=1, total_steps=1)
    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    args = ["train", "--config", str(cfg_file), "--data", str(box_capture), "--out", str(run)]
    args += ["--holdout-every", "0", "--source-every", "2", "--splat-cache", str(tmp_path / "cache")]
    result = CliRunner().invoke(sim_app, [*args, "--steps", "2"])
    assert result.exit_code != 0 and "at least 3 steps" in result.output
    result = CliRunner().invoke(sim_app, [*args, "--steps", "3"])
    assert result.exit_code == 0, result.output
    # --steps scales the whole curriculum: the saved config ends its schedule there.
    saved = json.loads((run / "config.json").read_text())["curriculum"]
    assert (saved["stage2_start"], saved["stage3_start"], saved["total_steps"]) == (1, 2, 3)
    assert (run / "checkpoints" / "last.ckpt").is_file()
    record = json.loads((run / sd.TRAINING_RECORD).read_text())
    assert record["captures"] == [str(box_capture)]
    assert record["splat_data"]["source_every"] == 2 and record["gaussians"]["encoder"]["scale_init"] > 0
    bench = RenderBenchConfig(
        renderer_config=str(cfg_file),
        checkpoint=str(run / "checkpoints" / "last.ckpt"),
        data=[str(box_capture)],
        holdout_every=4,
        steps=[1],
        condition_source="gaussians",
        warmup=0,
        runs=1,
    )
    doc = run_render_bench(bench, tmp_path / "render.json", show_progress=False)
    mismatches = doc["protocol"]["training_data"]["mismatches"]
    assert mismatches == ["source_every: trained 2, evaluated 1", "holdout_every: trained 0, evaluated 4"]
    assert "conditions differ from the checkpoint's training**: source_every" in render_markdown(doc)


def test_learned_encoder_features_reach_the_condition(box_capture, tmp_path):
    """With a stage-1 encoder checkpoint the conditions carry its 16 feature channels (identity
    conditions carry zeros there), the cache key and the training record name the encoder, and a
    missing checkpoint is an error naming it."""
    from image2sim.simulator.gaussians.build import save_encoder
    from image2sim.simulator.gaussians.encoder import GaussianEncoder
    from image2sim.simulator.renderer.condition import FEATURES

    torch.manual_seed(0)
    encoder = GaussianEncoder(_gcfg(), None, panoramic=True)
    ckpt = save_encoder(encoder, tmp_path / "encoder" / "encoder.safetensors")
    base = sd.SplatDataConfig(holdout_every=0, cache_dir=str(tmp_path / "cache"))
    identity = sd.SplatConditionDataset([box_capture], H, W, base, gaussian_config=_gcfg())
    learned_cfg = dataclasses.replace(base, encoder=str(ckpt.parent))
    learned = sd.SplatConditionDataset([box_capture], H, W, learned_cfg, gaussian_config=_gcfg())
    covered = learned.conditions[:, ALPHA] > 0.5
    assert float(identity.conditions[:, FEATURES].abs().max()) == 0.0
    assert float(learned.conditions[:, FEATURES].abs().amax(dim=1, keepdim=True)[covered].min()) > 0
    assert len(list((tmp_path / "cache").glob("*.safetensors"))) == 2  # two keys, two cache files
    record = sd.training_record([box_capture], learned_cfg, _gcfg())
    assert record["encoder_sha256"] == sd.encoder_digest(str(ckpt)) != "identity"
    with pytest.raises(sd.SplatDataError, match="encoder checkpoint not found"):
        sd.SplatConditionDataset(
            [box_capture],
            H,
            W,
            dataclasses.replace(base, encoder=str(tmp_path / "none")),
            gaussian_config=_gcfg(),
        )
