"""Renderer training: curriculum stages and freezing, data determinism, exact resume."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import torch

pytest.importorskip("lightning")

from image2sim.simulator.renderer.config import config_to_dict, renderer_config_from_dict  # noqa: E402
from image2sim.simulator.renderer.data import (  # noqa: E402
    DegradeConfig,
    DegradedPanoramaDataset,
    degrade_to_condition,
    permuted_index,
    smooth_test_panorama,
)
from image2sim.simulator.renderer.module import (  # noqa: E402
    FROZEN_IN_STAGE3,
    RendererModule,
    apply_stage,
    fit,
    stage_at,
    stage_weights,
)

H, W = 16, 32


def train_cfg(**curriculum):
    cur = {"stage2_start": 2, "stage3_start": 4, "total_steps": 6, "batch_size": 2, "lr": 1e-3}
    cur.update(curriculum)
    return renderer_config_from_dict(
        {
            "height": H,
            "width": W,
            "aligner": {"stem_widths": [8, 8, 8, 8], "token_dim": 8, "heads": 2, "depth": 1},
            "decoder": {
                "widths": [8, 8, 8, 8],
                "bottleneck_dim": 8,
                "bottleneck_depth": 1,
                "heads": 2,
                "time_dim": 8,
                "kernel_size": 3,
                "prior_hidden": 8,  # the preset's MLP prior path, narrower and fitted for 2 steps
                "prior_fit_steps": 2,
            },
            "curriculum": cur,
        },
        preset="tiny",
    )


def dataset(n=8):
    targets = [smooth_test_panorama(H, W, seed=i) for i in range(3)]
    return DegradedPanoramaDataset(targets, n, DegradeConfig(hole_scale=4))


def test_stage_schedule_and_weights():
    cfg = train_cfg(stage2_start=10, stage3_start=20, total_steps=30)
    assert [stage_at(s, cfg) for s in (0, 9, 10, 19, 20, 29)] == [1, 1, 2, 2, 3, 3]
    w1, w2, w3 = (stage_weights(s, cfg) for s in (1, 2, 3))
    assert (
        w1["distill"] == 0
        and w2["distill"] == 2.0
        and (w1["perc"], w2["perc"], w3["perc"]) == (1.0, 2.0, 4.0)
    )
    assert w1["rec"] == w1["align"] == 0.1
    assert w1["pixel"] == w3["pixel"] == cfg.loss.lambda_pixel
    assert stage_weights(2, cfg, perceptual_available=False)["perc"] == 0.0
    nod = renderer_config_from_dict({**{"ablation": {"no_distill": True}}}, preset="tiny")
    assert stage_weights(2, nod)["distill"] == 0.0


def test_scaled_curriculum_keeps_the_stage_fractions_and_ends_the_schedule():
    from image2sim.simulator.renderer.config import scaled_curriculum, tiny

    c = tiny().curriculum  # 375 / 1125 / 1500: the paper's 1:2:1
    s = scaled_curriculum(c, 300)
    assert (s.stage2_start, s.stage3_start, s.total_steps) == (75, 225, 300)
    assert (s.lr, s.min_lr, s.lambda_distill) == (c.lr, c.min_lr, c.lambda_distill)
    assert scaled_curriculum(c, c.total_steps) == c
    # Every stage keeps at least one step, however short the schedule.
    tiny3 = scaled_curriculum(c, 3)
    assert (tiny3.stage2_start, tiny3.stage3_start, tiny3.total_steps) == (1, 2, 3)
    with pytest.raises(ValueError, match="at least 3 steps"):
        scaled_curriculum(c, 2)
    # The learning rate reaches its floor at the scaled end (the module's cosine reads total_steps).
    cfg = train_cfg(stage2_start=c.stage2_start, stage3_start=c.stage3_start, total_steps=c.total_steps)
    import dataclasses

    short = dataclasses.replace(cfg, curriculum=scaled_curriculum(cfg.curriculum, 30))
    opt = RendererModule(short).configure_optimizers()
    sched = opt["lr_scheduler"]["scheduler"]
    lrs = []
    for _ in range(30):
        lrs.append(opt["optimizer"].param_groups[0]["lr"])
        opt["optimizer"].step()
        sched.step()
    assert lrs[0] == short.curriculum.lr
    assert opt["optimizer"].param_groups[0]["lr"] == pytest.approx(short.curriculum.min_lr)


def test_stage3_freezes_exactly_encoder_aligner_and_bottleneck():
    module = RendererModule(train_cfg())
    renderer = module.renderer
    frozen = set(apply_stage(renderer, 3))
    names = {n for n, _ in renderer.named_parameters()}
    expected = {n for n in names if n.startswith(FROZEN_IN_STAGE3)}
    assert frozen == expected and expected
    trainable = names - frozen
    assert trainable and all(
        n.startswith(
            (
                "decoder.ups",
                "decoder.skips",
                "decoder.dec_blocks",
                "decoder.out_norm",
                "decoder.rgb_head",
                "decoder.depth_head",
                "decoder.prior_filter",
                "decoder.prior_net",
            )
        )
        for n in trainable
    )
    assert any(n.startswith("aligner.") for n in frozen) and any(
        n.startswith("decoder.blocks.") for n in frozen
    )
    assert apply_stage(renderer, 2) == [] and all(p.requires_grad for p in renderer.parameters())


def test_degraded_condition_is_deterministic_and_splat_like():
    rgb, depth = smooth_test_panorama(H, W)
    cfg = DegradeConfig(hole_fraction=(0.4, 0.4), hole_scale=4)
    c1 = degrade_to_condition(rgb, depth, torch.Generator().manual_seed(3), cfg)
    c2 = degrade_to_condition(rgb, depth, torch.Generator().manual_seed(3), cfg)
    assert torch.equal(c1, c2) and c1.shape == (24, H, W) and torch.isfinite(c1).all()
    alpha = c1[20]
    assert 0.25 < (alpha < 0.5).float().mean() < 0.55
    assert torch.all(c1[16:19][:, alpha < 1e-3] == 0)  # nothing projected where alpha ~ 0


def test_data_order_is_a_resumable_sequence_of_permutations():
    from image2sim.simulator.sampling import StepSampler

    def order(start, stop, rank=0, world=1):
        index_of = functools.partial(permuted_index, length=5, seed=1)
        return list(StepSampler(start, stop, rank, world, index_of=index_of))

    full = order(0, 12)
    assert sorted(full[:5]) == list(range(5)) and sorted(full[5:10]) == list(range(5))
    assert order(7, 12) == full[7:]
    # Two ranks read alternate positions of the same global order: together they see every sample
    # of each block once, and each rank resumes at its own share.
    r0, r1 = order(0, 5, 0, 2), order(0, 5, 1, 2)
    assert [x for pair in zip(r0, r1, strict=True) for x in pair] == order(0, 10)
    assert order(2, 5, 1, 2) == r1[2:]
    with pytest.raises(ValueError, match="non-empty"):
        permuted_index(0, 0)


def _record_losses(out_dir, cfg, ds, max_steps, resume=None):
    import lightning as L

    losses = {}

    class Recorder(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            losses[trainer.global_step - 1] = float(outputs["loss"])

    import image2sim.simulator.renderer.module as mod

    original = mod.L.Trainer

    def trainer_with_recorder(*args, **kwargs):
        kwargs["callbacks"] = list(kwargs.get("callbacks", [])) + [Recorder()]
        return original(*args, **kwargs)

    mod.L.Trainer = trainer_with_recorder
    try:
        module = fit(
            cfg, ds, str(out_dir), max_steps=max_steps, resume=resume, checkpoint_every=1, progress=False
        )
    finally:
        mod.L.Trainer = original
    return losses, module


@pytest.mark.slow  # the CSV-log resume test below keeps a fast check of resuming
def test_resume_from_every_step_reproduces_the_uninterrupted_run(tmp_path):
    """A checkpoint after every step (stage 1, the stage-2 start that introduces the teacher, the
    stage-3 freeze): resuming from each gives the uninterrupted losses and final weights exactly.

    Resuming mid-epoch once replayed old batches: Lightning ends the restored epoch early and
    iterates the sampler again, which then started where the loader had been made (issue 23)."""
    cfg, ds = train_cfg(), dataset()
    full, full_module = _record_losses(tmp_path / "full", cfg, ds, max_steps=6)
    assert sorted(full) == list(range(6)) and all(torch.isfinite(torch.tensor(v)) for v in full.values())
    checkpoints = sorted((tmp_path / "full" / "checkpoints").glob("epoch=*-step=*.ckpt"))
    steps = sorted(int(p.stem.split("step=")[1]) for p in checkpoints)
    assert steps == [1, 2, 3, 4, 5, 6]
    for step in range(1, 6):
        ckpt = tmp_path / "full" / "checkpoints" / f"epoch=0-step={step}.ckpt"
        rest, resumed = _record_losses(tmp_path / f"from{step}", cfg, ds, max_steps=6, resume=str(ckpt))
        assert sorted(rest) == list(range(step, 6))
        assert all(rest[s] == full[s] for s in rest), (step, rest, full)
        for (name, a), b in zip(resumed.state_dict().items(), full_module.state_dict().values(), strict=True):
            assert torch.equal(a, b), (step, name)
        # The teacher was introduced at stage 2 and stage 3 froze the backbone in the resumed run too.
        assert bool(resumed.teacher_started)
        assert not any(
            p.requires_grad for n, p in resumed.renderer.named_parameters() if n.startswith("aligner.")
        )


def _csv_rows(run_dir):
    import csv

    files = sorted((run_dir / "logs").glob("version_*/metrics.csv"))
    return files, [row for f in files for row in csv.DictReader(f.open())]


def test_a_resumed_run_continues_its_csv_log_without_gaps_or_duplicates(tmp_path):
    """Killed after step 4 with its last checkpoint at step 2, then resumed: one log with every step
    once, equal to the uninterrupted run's (the rows of steps 2-3 were logged twice before)."""
    cfg, ds = train_cfg(), dataset()
    _record_losses(tmp_path / "full", cfg, ds, max_steps=6)
    _record_losses(tmp_path / "run", cfg, ds, max_steps=4)
    for late in (3, 4):  # as if the process died before checkpointing them
        (tmp_path / "run" / "checkpoints" / f"epoch=0-step={late}.ckpt").unlink()
    with (tmp_path / "run" / "logs" / "version_0" / "metrics.csv").open("a") as f:
        f.write("0.1,2")  # a row torn by the kill
    resume = tmp_path / "run" / "checkpoints" / "epoch=0-step=2.ckpt"
    _record_losses(tmp_path / "run", cfg, ds, max_steps=6, resume=str(resume))
    files, rows = _csv_rows(tmp_path / "run")
    _, full_rows = _csv_rows(tmp_path / "full")
    assert [f.parent.name for f in files] == ["version_0"]
    assert [int(r["step"]) for r in rows] == list(range(6))
    assert [r["train/loss"] for r in rows] == [r["train/loss"] for r in full_rows]


def test_trim_metrics_csv_keeps_the_rows_before_the_resumed_step(tmp_path):
    from image2sim.simulator.tracking import trim_metrics_csv

    f = tmp_path / "metrics.csv"
    assert trim_metrics_csv(f, 3) == 0 and not f.exists()
    f.write_text("loss,step\n0.5,0\n0.4,1\n0.3,2\n0.35,1\n0.2,3\n")
    assert trim_metrics_csv(f, 2) == 2
    assert f.read_text() == "loss,step\n0.5,0\n0.4,1\n0.35,1\n"
    assert trim_metrics_csv(f, 2) == 0


@pytest.mark.realdata
def test_capture_targets_from_the_real_hm3d_sample(hm3d_scene_dir):
    """Real panoramas load at the renderer's resolution with metric range kept (valid-only mean)."""
    from image2sim.simulator.renderer.data import load_capture_targets

    targets = load_capture_targets(hm3d_scene_dir, 32, 64, max_frames=2)
    assert len(targets) == 2
    rgb, depth = targets[0]
    assert rgb.shape == (3, 32, 64) and depth.shape == (1, 32, 64)
    assert 0 <= rgb.min() and rgb.max() <= 1 and rgb.std() > 0.02
    valid = depth[depth > 0]
    assert valid.numel() > 0.95 * depth.numel() and 0.3 < valid.min() and valid.max() < 9.0
    cond = degrade_to_condition(rgb, depth, torch.Generator().manual_seed(0), DegradeConfig(hole_scale=4))
    assert cond.shape == (24, 32, 64) and torch.isfinite(cond).all()


@pytest.mark.slow
def test_ddp_on_two_cpu_processes_trains_through_the_stage3_freeze(tmp_path, ddp_subprocess_env):
    """`sim train --devices 2 --strategy ddp` (gloo on CPU) runs the curriculum across the stage-3
    freeze, whose parameters then get no gradients: the run must neither hang nor fail, and the
    checkpoint must hold the final step. It is the code path of the `paper` preset (8 GPUs) at toy
    size; how the ranks split the data is tested with the sampler."""
    import subprocess
    import sys
    from pathlib import Path

    import yaml
    from image2sim.simulator.renderer.config import config_to_dict

    cfg = config_to_dict(train_cfg(total_steps=5, stage2_start=2, stage3_start=3, batch_size=1))
    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    cli = Path(sys.executable).with_name("image2sim")
    args = [sys.executable, str(cli), "sim", "train", "--config", str(cfg_file), "--out", str(out)]
    args += ["--accelerator", "cpu", "--devices", "2", "--strategy", "ddp", "--condition-source", "degraded"]
    args += ["--checkpoint-every", "5", "--grid-every", "0"]
    env = {**ddp_subprocess_env, "PYTHONUNBUFFERED": "1"}
    res = subprocess.run(args, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 5
    assert ckpt["hyper_parameters"]["config"]["trainer"]["devices"] == 2
    metrics = (out / "logs").glob("version_*/metrics.csv")
    rows = [line.split(",") for f in metrics for line in f.read_text().splitlines()]
    assert len(rows) > 1  # rank 0 logged its steps


def test_dinov3_from_a_local_folder_drives_the_alignment_term(tmp_path, tiny_dinov3):
    """With `semantic.backbone: dinov3` the module loads the backbone from its local folder
    (transformers `from_pretrained`, local files only), takes the target panorama's patch tokens as
    the aligner's targets, and the alignment term trains the aligner; checkpoints carry no copy of
    the frozen backbone."""
    import lightning as L

    folder = tmp_path / "dinov3"
    tiny_dinov3(hidden=16, patch_size=4, registers=2).save_pretrained(folder)
    base = train_cfg(total_steps=3, stage2_start=3, stage3_start=3)
    semantic = {"backbone": "dinov3", "weights": str(folder), "dim": 16, "patch_size": 4}
    data = config_to_dict(base)
    cfg = renderer_config_from_dict(
        {**data, "semantic": semantic, "aligner": {**data["aligner"], "target_dim": 16}}
    )
    module = RendererModule(cfg)
    assert module.semantic_backbone is not None and module.semantic_backbone.dim == 16
    assert not any(k.startswith("semantic") for k in module.state_dict())
    before = module.renderer.aligner.head.weight.detach().clone()
    aligns = []

    class Recorder(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            aligns.append(pl_module.last_losses["train/align"])

    trainer = L.Trainer(
        accelerator="cpu",
        max_steps=3,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[Recorder()],
        use_distributed_sampler=False,
    )
    from image2sim.simulator.renderer.module import RendererDataModule

    trainer.fit(module, datamodule=RendererDataModule(dataset(), 2, 3))
    assert len(aligns) == 3 and all(0.0 < a <= 2.0 for a in aligns), aligns
    assert not torch.allclose(module.renderer.aligner.head.weight, before)
    # The backbone itself never trains.
    assert all(not p.requires_grad and p.grad is None for p in module.semantic_backbone.parameters())


def test_semantic_and_ablation_misconfigurations_are_named():
    from image2sim.simulator.config import ConfigError

    base = config_to_dict(train_cfg())
    with pytest.raises(ValueError, match="aligner.target_dim"):
        renderer_config_from_dict({**base, "semantic": {"backbone": "dinov3", "dim": 1024}})
    ok = {**base, "aligner": {**base["aligner"], "target_dim": 1024}, "semantic": {"backbone": "dinov3"}}
    with pytest.raises(ConfigError, match="semantic.weights"):
        RendererModule(renderer_config_from_dict(ok))
    # The semantic ablation needs no backbone at all.
    RendererModule(renderer_config_from_dict({**ok, "ablation": {"no_semantic": True}}))
    with pytest.raises(ValueError, match="nothing to train"):
        RendererModule(renderer_config_from_dict({**base, "ablation": {"no_pixel_flow": True}}))
    no_distill = RendererModule(renderer_config_from_dict({**base, "ablation": {"no_distill": True}}))
    assert no_distill.teacher is None
    assert RendererModule(renderer_config_from_dict(base)).teacher is not None


def test_wandb_offline_run_holds_losses_psnr_and_image_grids(tmp_path, monkeypatch):
    """`sim train --logger wandb` (offline unless the user configured W&B) logs every loss term,
    the one-step PSNR and the prior | one-step | target | alpha grid."""
    pytest.importorskip("wandb")
    tracking = pytest.importorskip("image2sim.eval.tracking")  # the offline-run reader
    import json

    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(tmp_path / var.lower()))
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.chdir(tmp_path)
    module = fit(
        train_cfg(total_steps=2, stage2_start=1, stage3_start=2),
        dataset(),
        str(tmp_path / "run"),
        logger="wandb",
        grid_every=1,
        checkpoint_every=2,
        progress=False,
    )
    # W&B is added beside the CSV log (which every run keeps).
    from lightning.pytorch.loggers import CSVLogger, WandbLogger

    wandb_loggers = [lg for lg in module.loggers if isinstance(lg, WandbLogger)]
    assert len(wandb_loggers) == 1 and any(isinstance(lg, CSVLogger) for lg in module.loggers)
    run = wandb_loggers[0].experiment
    assert run.settings.mode in ("offline", "dryrun")  # dryrun: W&B's internal name for offline
    run_dir = Path(run.dir).parent
    run.finish()
    import wandb

    wandb.teardown()
    records = tracking.read_offline_run(run_dir)
    items = [i for kind, r in records if kind == "history" for i in r.item]
    keys = {i.nested_key[0] if i.nested_key else i.key for i in items}
    expected = {"train/loss", "train/flow", "train/rec", "train/distill", "train/psnr_one_step"}
    assert expected <= keys, sorted(keys)
    grid = "grid/prior|one_step|target|alpha"
    fields = [
        (tuple(i.nested_key[1:]), json.loads(i.value_json)) for i in items if i.nested_key[:1] == [grid]
    ]
    assert fields.count((("_type",), "images/separated")) == 2  # one grid per step
    assert (("width",), 4 * W) in fields and (("height",), H) in fields  # four panels side by side
    files = [f for key, value in fields if key == ("filenames",) for f in value]
    assert len(files) == 2 and all((run_dir / "files" / f).is_file() for f in files), files


def test_training_updates_the_teacher_by_its_ema_formula_after_every_step(tmp_path):
    """Inside training, the teacher starts at stage 2 as the student and then follows
    T_k = d * T_(k-1) + (1 - d) * S_k after every optimiser step (d = distill.ema_decay)."""
    import lightning as L

    data = config_to_dict(train_cfg(total_steps=4, stage2_start=1, stage3_start=4))
    cfg = renderer_config_from_dict({**data, "distill": {**data["distill"], "ema_decay": 0.9}})
    snapshots = []

    def flat(module):
        return torch.cat([p.detach().flatten().clone() for p in module.parameters()])

    class Recorder(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            snapshots.append((flat(pl_module.renderer), flat(pl_module.teacher.module)))

    import image2sim.simulator.renderer.module as mod

    original = mod.L.Trainer
    mod.L.Trainer = lambda *a, **k: original(*a, **{**k, "callbacks": [*k.get("callbacks", []), Recorder()]})
    try:
        fit(cfg, dataset(), str(tmp_path / "run"), checkpoint_every=10, progress=False)
    finally:
        mod.L.Trainer = original
    assert len(snapshots) == 4
    (s0, _), (s1, t1), (s2, t2), (s3, t3) = snapshots
    # Step 1 (first of stage 2) copies the student as it was (s0), then takes one EMA step.
    torch.testing.assert_close(t1, 0.9 * s0 + 0.1 * s1, rtol=1e-5, atol=1e-6)
    for (_, t_prev), (s_next, t_next) in (((s1, t1), (s2, t2)), ((s2, t2), (s3, t3))):
        torch.testing.assert_close(t_next, 0.9 * t_prev + 0.1 * s_next, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(t_next, s_next)  # a lagging average, not a copy
