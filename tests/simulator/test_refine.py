"""Per-scene refinement (issue 20, item 2): the optimisation lowers the loss it minimises, moves a
misplaced Gaussian towards the truth, prunes what becomes transparent (with its optimiser state),
and is wired into ``sim build-scene --refine-steps``."""

from __future__ import annotations

import json
import math

import pytest
import torch
from image2sim.simulator.gaussians.primitives import FrameInputs, GaussianSet
from image2sim.simulator.gaussians.refine import RefineConfig, frame_loss, refine_gaussians
from image2sim.simulator.geometry.cameras import PinholeCamera

H = W = 24
CAM = PinholeCamera(20.0, 20.0, W / 2, H / 2, H, W)


def gaussians(means, colors, opacities=None, scale=0.15) -> GaussianSet:
    n = len(means)
    means = torch.tensor(means, dtype=torch.float32)
    return GaussianSet(
        means=means,
        scales=torch.full((n, 3), scale),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        opacities=torch.full((n,), 0.9) if opacities is None else torch.tensor(opacities),
        colors=torch.tensor(colors, dtype=torch.float32),
        features=torch.zeros(n, 0),
        footprints=torch.full((n,), 0.01),
        weights=torch.ones(n),
        levels=torch.zeros(n, dtype=torch.int64),
    )


def view_of(target: GaussianSet, pose: torch.Tensor) -> FrameInputs:
    """The frame a camera at ``pose`` sees of ``target`` (the ground truth to refine towards)."""
    with torch.no_grad():
        out = target.render(CAM, pose, background=0.0)
    depth = torch.where(out.alpha > 0.5, out.depth / out.alpha.clamp_min(1e-6), torch.zeros_like(out.depth))
    return FrameInputs(out.rgb.clamp(0, 1), depth, CAM, pose.double(), "f")


def poses() -> list[torch.Tensor]:
    """Three cameras looking along +z (opencv) at the origin from z = -3, shifted sideways."""
    out = []
    for x in (-0.3, 0.0, 0.3):
        p = torch.eye(4)
        p[:3, 3] = torch.tensor([x, 0.0, -3.0])
        out.append(p)
    return out


def test_refinement_lowers_the_loss_and_moves_a_misplaced_gaussian():
    truth = gaussians([[0.0, 0.0, 0.0], [0.6, 0.2, 0.3]], [[0.9, 0.2, 0.1], [0.1, 0.3, 0.9]])
    start = gaussians([[0.12, -0.08, 0.0], [0.6, 0.2, 0.3]], [[0.6, 0.4, 0.3], [0.1, 0.3, 0.9]])
    views = [view_of(truth, p) for p in poses()]
    cfg = RefineConfig(steps=150, views_per_step=3, lr_means=5e-3, lr_colors=5e-2, prune_every=0)
    params = lambda g: {  # noqa: E731
        "means": g.means,
        "log_scales": g.scales.log(),
        "quats": g.quats,
        "opacity_logits": torch.logit(g.opacities),
        "color_logits": torch.logit(g.colors),
    }
    before = sum(float(frame_loss(params(start), start.features, v, cfg.depth_weight)) for v in views)
    refined, log = refine_gaussians(start, views, cfg)
    after = sum(float(frame_loss(params(refined), refined.features, v, cfg.depth_weight)) for v in views)
    assert after < 0.3 * before
    err_before = float((start.means[0] - truth.means[0]).norm())
    err_after = float((refined.means[0] - truth.means[0]).norm())
    assert err_after < 0.3 * err_before
    assert float((refined.colors[0] - truth.colors[0]).abs().max()) < 0.1
    assert log.steps == 150 and len(log.losses) == 150 and all(math.isfinite(x) for x in log.losses)
    assert torch.allclose(refined.quats.norm(dim=-1), torch.ones(2))


def test_an_unseen_floater_is_pruned_with_its_optimiser_state():
    # The second Gaussian floats in front of the first where the truth has nothing: the photometric
    # loss drives its opacity down and pruning removes it; the survivor keeps its bookkeeping.
    truth = gaussians([[0.0, 0.0, 0.0]], [[0.8, 0.8, 0.2]])
    start = gaussians([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]], [[0.8, 0.8, 0.2], [0.1, 0.1, 0.9]], [0.9, 0.5])
    start.weights[0] = 7.0
    views = [view_of(truth, p) for p in poses()]
    cfg = RefineConfig(steps=120, views_per_step=3, lr_opacities=0.2, prune_every=20, prune_opacity=0.05)
    refined, log = refine_gaussians(start, views, cfg)
    assert len(refined) == 1 and log.gaussians_after == 1 and sum(log.pruned) == 1
    assert float(refined.weights[0]) == 7.0
    assert float((refined.means[0] - truth.means[0]).norm()) < 0.05


def test_zero_steps_is_the_identity_and_bad_settings_are_named():
    g = gaussians([[0.0, 0.0, 0.0]], [[0.5, 0.5, 0.5]])
    same, log = refine_gaussians(g, [], RefineConfig(steps=0))
    assert same is g and log.steps == 0
    with pytest.raises(ValueError, match="no frames"):
        refine_gaussians(g, [], RefineConfig(steps=3))
    with pytest.raises(ValueError, match="views_per_step"):
        RefineConfig(views_per_step=0).validate()
    with pytest.raises(ValueError, match="lr_means"):
        RefineConfig(lr_means=float("nan")).validate()


def test_build_scene_refine_steps_records_the_refinement(tmp_path):
    import dataclasses

    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.simulator.cli import sim_app
    from typer.testing import CliRunner

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=3))
    cap = tmp_path / "scene_000"
    write_scene(generate_scene(sc, seed=2), cap)
    out = tmp_path / "scene"
    res = CliRunner().invoke(
        sim_app,
        ["build-scene", str(cap), "--out", str(out), "--no-navigation", "--no-ply", "--refine-steps", "3"],
    )
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    info = manifest["refine"]
    assert info["steps"] == 3 and info["frames"] == 3 and info["gaussians_after"] <= info["gaussians_before"]
    assert "refined 3 steps" in res.output
    res = CliRunner().invoke(
        sim_app,
        ["build-scene", str(cap), "--out", str(out), "--no-navigation", "--no-ply", "--refine-steps", "0"]
        + ["--overwrite"],
    )
    assert res.exit_code == 0, res.output
    assert "refine" not in json.loads((out / "manifest.json").read_text()) and "refined" not in res.output


def test_checkpoints_read_one_run_without_changing_it():
    """``on_checkpoint`` sees the set at each requested count, in order, with growing seconds, and the
    run it reads is the same run as without the callback (same final Gaussians)."""
    truth = gaussians([[0.0, 0.0, 0.0], [0.6, 0.2, 0.3]], [[0.9, 0.2, 0.1], [0.1, 0.3, 0.9]])
    start = gaussians([[0.12, -0.08, 0.0], [0.6, 0.2, 0.3]], [[0.6, 0.4, 0.3], [0.1, 0.3, 0.9]])
    views = [view_of(truth, p) for p in poses()]
    cfg = RefineConfig(steps=12, lr_means=5e-3, prune_every=5)
    seen = []
    checked, _ = refine_gaussians(
        start, views, cfg, checkpoints=[4, 12, 99, 0], on_checkpoint=lambda k, g, s: seen.append((k, g, s))
    )
    plain, _ = refine_gaussians(start, views, cfg)
    assert [k for k, _, _ in seen] == [4, 12]  # counts outside 1..steps are ignored
    assert seen[0][2] <= seen[1][2]
    assert torch.equal(seen[1][1].means, checked.means)
    assert torch.equal(checked.means, plain.means) and torch.equal(checked.colors, plain.colors)
    assert not torch.equal(seen[0][1].means, checked.means)  # the 4-step set is not the final one


def test_compile_projection_is_chosen_by_work_and_validated(monkeypatch):
    import image2sim.simulator.gaussians.refine as refine_mod

    calls = []
    real = refine_mod.frame_loss
    monkeypatch.setattr(refine_mod, "frame_loss", lambda *a: calls.append(a[4]) or real(*a[:4]))
    start = gaussians([[0.0, 0.0, 0.0]], [[0.5, 0.5, 0.5]])
    views = [view_of(start, poses()[1])]
    refine_gaussians(start, views, RefineConfig(steps=2))
    monkeypatch.setattr(refine_mod, "COMPILE_WORK", 2)
    refine_gaussians(start, views, RefineConfig(steps=2))
    refine_gaussians(start, views, RefineConfig(steps=2, compile_projection="never"))
    assert calls == [False, False, True, True, False, False]
    with pytest.raises(ValueError, match="compile_projection must be auto, always or never"):
        RefineConfig(compile_projection="yes").validate()


def test_build_scene_refines_two_steps_per_frame_up_to_fifty_by_default():
    from image2sim.simulator.gaussians.refine import (
        DEFAULT_MAX_STEPS,
        DEFAULT_STEPS_PER_FRAME,
        default_refine_steps,
    )

    assert (DEFAULT_STEPS_PER_FRAME, DEFAULT_MAX_STEPS) == (2, 50)
    assert [default_refine_steps(n) for n in (0, 1, 10, 25, 26, 86)] == [0, 2, 20, 50, 50, 50]


def test_refine_scene_prepares_only_the_frames_it_reads(tmp_path, monkeypatch):
    """A refinement of N steps decodes at most N of the capture's frames (each once), not all."""
    import dataclasses

    import image2sim.simulator.gaussians.refine as refine_mod
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.simulator.gaussians import build_scene, tiny
    from image2sim.simulator.io.registry import open_capture

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=6))
    cap = tmp_path / "scene_000"
    write_scene(generate_scene(sc, seed=1), cap)
    scene = build_scene(cap, tiny())
    prepared = []
    real = refine_mod.prepare_frame
    monkeypatch.setattr(refine_mod, "prepare_frame", lambda f, *a: prepared.append(f.frame_id) or real(f, *a))
    log = refine_mod.refine_scene(
        scene, open_capture(cap), None, RefineConfig(steps=2, compile_projection="never")
    )
    assert log.steps == 2 and len(prepared) == 2 and len(set(prepared)) == 2
    assert scene.info["refine"]["frames"] == 6
