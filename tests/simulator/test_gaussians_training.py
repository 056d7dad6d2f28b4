"""Stage-1 geometry training: loss decreases, Lightning run resumes exactly, semantic alignment term,
and a trained checkpoint builds a scene."""

from __future__ import annotations

import csv
import dataclasses
import json

import pytest
import torch
from image2sim.simulator.gaussians import GaussianEncoder, tiny
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.train_geometry import GeometryDataset, stage1_losses, train_stage1
from image2sim.simulator.geometry.cameras import camera_from_dict


def _cfg(**train):
    cfg = tiny()
    return dataclasses.replace(
        cfg,
        encoder=dataclasses.replace(cfg.encoder, height=64, width=128),
        train=dataclasses.replace(cfg.train, num_sources=2, **train),
    )


@pytest.fixture(scope="module")
def procedural(tmp_path_factory):
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.simulator.io.registry import open_capture

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=5))
    out = tmp_path_factory.mktemp("cap") / "scene"
    write_scene(generate_scene(sc, seed=4), out)
    frames = [prepare_frame(f, 64, 128, labels=True) for f in open_capture(out)]
    return out, frames


def test_a_few_steps_reduce_the_reconstruction_loss(procedural):
    _, frames = procedural
    cfg = _cfg()
    torch.manual_seed(0)
    enc = GaussianEncoder(cfg)
    batch = GeometryDataset([frames], 2, 1, seed=0)[0]
    camera = camera_from_dict(json.loads(batch["camera"]))
    opt = torch.optim.AdamW(enc.parameters(), lr=5e-3)

    def recon():
        losses, _ = stage1_losses(enc, batch, camera)
        return losses, losses["rgb"] + cfg.train.w_depth * losses["depth"]

    with torch.no_grad():
        first = float(recon()[1])
    for _ in range(7):
        losses, _ = recon()
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
    with torch.no_grad():
        last = float(recon()[1])
    print(f"stage-1 reconstruction loss {first:.4f} -> {last:.4f}")
    assert last < 0.95 * first


def test_frames_carry_the_captures_categories_at_the_encoder_resolution(procedural):
    """Category ids are resized by nearest sample (never blended into ids that do not exist)."""
    import numpy as np
    from image2sim.simulator.io.registry import open_capture

    out, frames = procedural
    raw = open_capture(out)[0].semantics
    labels = frames[0].labels
    assert raw is not None and labels is not None and labels.shape == (1, 1, 64, 128)
    assert labels.dtype == torch.int64
    assert set(np.unique(labels.numpy())) <= set(np.unique(raw)) and len(np.unique(labels.numpy())) > 3
    assert "tgt_labels" in GeometryDataset([frames], 2, 1, seed=0)[0]
    # Only asked for: fusion and condition builds never read them.
    assert prepare_frame(open_capture(out)[0], 64, 128).labels is None


def test_the_category_target_teaches_the_features_what_the_objects_are(procedural):
    """``train.w_labels``: a linear head over the splatted features learns the target's categories
    (the features are trained through it), and the reconstruction terms stay in the total."""
    from image2sim.simulator.gaussians.train_geometry import label_classes

    _, frames = procedural
    cfg = _cfg(w_labels=1.0)
    torch.manual_seed(0)
    enc = GaussianEncoder(cfg)
    head = torch.nn.Linear(cfg.encoder.feature_dim, label_classes(cfg, [frames]))
    batch = GeometryDataset([frames], 2, 1, seed=0)[0]
    camera = camera_from_dict(json.loads(batch["camera"]))
    opt = torch.optim.AdamW([*enc.parameters(), *head.parameters()], lr=1e-2)
    with torch.no_grad():
        first, _ = stage1_losses(enc, batch, camera, label_head=head)
    for _ in range(12):
        losses, _ = stage1_losses(enc, batch, camera, label_head=head)
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
    with torch.no_grad():
        last, _ = stage1_losses(enc, batch, camera, label_head=head)
    print(
        f"category loss {float(first['labels']):.3f} -> {float(last['labels']):.3f}, "
        f"accuracy {float(first['label_acc']):.2f} -> {float(last['label_acc']):.2f}"
    )
    assert float(last["labels"]) < 0.7 * float(first["labels"])
    assert float(last["label_acc"]) > float(first["label_acc"])
    assert torch.isclose(
        first["total"],
        first["rgb"]
        + cfg.train.w_depth * first["depth"]
        + cfg.train.w_scale * first["scale"]
        + first["labels"],
    )


def test_a_category_target_without_labelled_frames_is_an_error(procedural):
    from image2sim.simulator.gaussians.train_geometry import label_classes

    _, frames = procedural
    unlabelled = [dataclasses.replace(f, labels=None) for f in frames]
    assert label_classes(_cfg(), [unlabelled]) == 0  # no target asked: nothing needed
    assert label_classes(_cfg(w_labels=1.0), [frames]) > 3
    with pytest.raises(ValueError, match="semantics"):
        label_classes(_cfg(w_labels=1.0), [unlabelled])
    with pytest.raises(ValueError, match="w_labels"):
        _cfg(w_labels=-1.0).validate()


def test_dataset_samples_are_deterministic_and_hold_out_the_target(procedural):
    _, frames = procedural
    ds = GeometryDataset([frames], 2, 50, seed=7)
    for i in range(50):
        s, t, src = ds.indices(i)
        assert t not in src and len(src) == 2 and ds.indices(i) == (s, t, src)
    assert len({ds.indices(i)[1] for i in range(50)}) > 1


def test_lightning_run_logs_checkpoints_and_resumes(procedural, tmp_path):
    _, frames = procedural
    cfg = _cfg(steps=2, log_every=1, image_every=1, checkpoint_every=1)
    out = tmp_path / "run"
    r1 = train_stage1(cfg, out, scenes=[frames], progress=False)
    assert r1["steps"] == 2 and (out / "checkpoints" / "last.ckpt").is_file()
    assert (out / "encoder.safetensors").is_file() and (out / "encoder.json").is_file()
    assert sorted(p.name for p in (out / "images").iterdir()) == ["step_0000000.png", "step_0000001.png"]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 2
    cfg4 = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=4))
    r2 = train_stage1(cfg4, out, scenes=[frames], progress=False)
    assert r2["steps"] == 4 and len(r2["losses"]) == 2  # resumed: only steps 2 and 3 ran
    # ... and exactly as the uninterrupted run: same samples (data position restored), same weights.
    full = train_stage1(cfg4, tmp_path / "full", scenes=[frames], progress=False)
    assert full["losses"][:2] == pytest.approx(r1["losses"], rel=1e-6)
    assert r2["losses"] == pytest.approx(full["losses"][2:], rel=1e-5)
    rows = []
    for f in (out / "logs").rglob("metrics.csv"):
        rows += list(csv.DictReader(f.open()))
    assert any(r.get("train/rgb") for r in rows)


def test_semantic_alignment_term_with_tiny_dinov3(procedural, tiny_dinov3):
    from image2sim.simulator.gaussians.train_geometry import GeometryModule

    _, frames = procedural
    cfg = _cfg()
    cfg = dataclasses.replace(cfg, semantic=dataclasses.replace(cfg.semantic, backbone="dinov3", dim=32))
    dino = tiny_dinov3(hidden=32, registers=2)
    module = GeometryModule(cfg, dino)
    batch = GeometryDataset([frames], 2, 1)[0]
    losses, _ = stage1_losses(
        module.encoder, batch, camera_from_dict(json.loads(batch["camera"])), module.align_head
    )
    assert "align" in losses and 0 <= float(losses["align"]) <= 2
    losses["total"].backward()
    assert module.align_head.weight.grad is not None
    assert all(p.grad is None for p in module.encoder.semantic.parameters())


def test_checkpoints_leave_the_frozen_dinov3_out_and_resume_with_it(procedural, tiny_dinov3, tmp_path):
    _, frames = procedural
    cfg = _cfg(steps=1, checkpoint_every=1)
    cfg = dataclasses.replace(cfg, semantic=dataclasses.replace(cfg.semantic, backbone="dinov3", dim=32))
    dino = tiny_dinov3(hidden=32, registers=2)
    out = tmp_path / "run"
    train_stage1(cfg, out, scenes=[frames], semantic_model=dino, progress=False)
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    keys = list(ckpt["state_dict"])
    assert keys and not any(k.startswith("encoder.semantic.") for k in keys)
    assert any(k.startswith("align_head.") for k in keys)  # the trained parts are all there
    cfg2 = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=2))
    r2 = train_stage1(cfg2, out, scenes=[frames], semantic_model=dino, progress=False)
    assert r2["steps"] == 2 and len(r2["losses"]) == 1  # resumed (strict load) with the backbone


def test_trained_checkpoint_builds_a_scene(procedural, tmp_path):
    from image2sim.simulator.gaussians.build import build_scene, save_encoder

    capture, _ = procedural
    enc = GaussianEncoder(_cfg())
    path = save_encoder(enc, tmp_path / "enc.safetensors")
    scene = build_scene(capture, enc.cfg, encoder=path, frames=[0, 1])
    enc_info = scene.manifest()["encoder"]
    assert enc_info["kind"] == "learned" and len(enc_info["sha256"]) == 64
    assert scene.feature_dim == 16 and len(scene) > 1000


def test_cli_train_geometry_without_data_names_the_missing_argument(tmp_path):
    from image2sim.simulator.cli import sim_app
    from typer.testing import CliRunner

    result = CliRunner().invoke(sim_app, ["train-geometry", "--out", str(tmp_path / "run")])
    assert result.exit_code == 2 and "capture folder" in result.output, result.output
    assert not (tmp_path / "run").exists()  # nothing written


@pytest.mark.slow
def test_train_geometry_with_ddp_on_two_cpu_processes(procedural, tmp_path, ddp_subprocess_env):
    """`sim train-geometry --devices 2 --strategy ddp` (gloo on CPU): the code path of GPU scale-out.
    Both ranks train, rank 0 writes the checkpoint and the encoder once."""
    import subprocess
    import sys
    from pathlib import Path

    from image2sim.simulator.gaussians.config import config_to_dict

    capture, _ = procedural
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps(config_to_dict(_cfg(steps=3, checkpoint_every=3, image_every=0))))
    out = tmp_path / "run"
    cli = Path(sys.executable).with_name("image2sim")
    args = [sys.executable, str(cli), "sim", "train-geometry", str(capture), "--out", str(out)]
    args += ["--config", str(cfg_file), "--accelerator", "cpu", "--devices", "2", "--strategy", "ddp"]
    env = ddp_subprocess_env
    res = subprocess.run(args, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "GLOBAL_RANK: 1" in res.stderr + res.stdout  # two processes really ran
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 3
    assert (out / "encoder.safetensors").is_file() and not list(out.glob(".*tmp*"))
