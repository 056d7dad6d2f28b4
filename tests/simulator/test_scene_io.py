"""Scene artifact: safetensors + manifest round trip (bit-exact renders), 3DGS PLY, CLI, real data."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from image2sim.simulator.gaussians import GaussianScene, GaussianSet, tiny
from image2sim.simulator.gaussians.build import build_scene, nearest_frames
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.scene import SH_C0, SceneError, read_gaussian_ply
from image2sim.simulator.geometry.cameras import EquirectCamera


def _scene(n=300, feat=4, seed=0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    gs = GaussianSet(
        means=torch.randn(n, 3, generator=g) * 2 + torch.tensor([0.0, 0.0, 1.0]),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 0.02,
        quats=q / q.norm(dim=1, keepdim=True),
        opacities=torch.rand(n, generator=g) * 0.9 + 0.05,
        colors=torch.rand(n, 3, generator=g),
        features=torch.randn(n, feat, generator=g),
        footprints=torch.rand(n, generator=g) * 0.05,
        weights=torch.ones(n),
        levels=torch.randint(0, 3, (n,), generator=g),
    )
    return GaussianScene(gaussians=gs, info={"camera": EquirectCamera(32, 64).to_dict()})


def test_save_load_reproduces_renders_bit_exactly(tmp_path):
    scene = _scene()
    cam, pose = EquirectCamera(32, 64), torch.eye(4)
    before = scene.render(cam, pose, backend="torch")
    scene.save(tmp_path / "scene")
    loaded = GaussianScene.load(tmp_path / "scene")
    after = loaded.render(cam, pose, backend="torch")
    for key in ("rgb", "depth", "alpha", "features"):
        assert torch.equal(getattr(before, key), getattr(after, key)), key
    for key, value in scene.gaussians.tensors().items():
        assert torch.equal(getattr(loaded.gaussians, key), value), key
    manifest = json.loads((tmp_path / "scene" / "manifest.json").read_text())
    assert manifest["counts"]["gaussians"] == 300 and manifest["counts"]["feature_dim"] == 4
    assert manifest["fusion"]["policy"] == "footprint" and "conventions" in manifest
    lo, hi = manifest["bounds"]["min"], manifest["bounds"]["max"]
    assert np.allclose(lo, scene.gaussians.means.amin(0)) and np.allclose(hi, scene.gaussians.means.amax(0))
    assert [p.name for p in (tmp_path).iterdir()] == ["scene"]  # no temp folder left behind


def test_save_refuses_to_overwrite_and_load_names_bad_files(tmp_path):
    scene = _scene()
    scene.save(tmp_path / "s")
    with pytest.raises(SceneError, match="already exists"):
        scene.save(tmp_path / "s")
    scene.save(tmp_path / "s", overwrite=True)
    manifest = json.loads((tmp_path / "s" / "manifest.json").read_text())
    manifest["fusion"]["polcy"] = "fixed"
    (tmp_path / "s" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SceneError, match="manifest.json.*fusion.polcy"):
        GaussianScene.load(tmp_path / "s")
    (tmp_path / "s" / "manifest.json").write_text('{"format": "something-else", "version": 1}')
    with pytest.raises(SceneError, match="manifest.json.*format"):
        GaussianScene.load(tmp_path / "s")
    with pytest.raises(SceneError, match="missing"):
        GaussianScene.load(tmp_path / "nowhere")


def test_ply_round_trip_and_standard_layout(tmp_path):
    scene = _scene(feat=3)
    path = scene.export_ply(tmp_path / "g.ply")
    header = path.read_bytes().split(b"end_header")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert props[:17] == [
        "x",
        "y",
        "z",
        "nx",
        "ny",
        "nz",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    assert props[17:] == ["feat_0", "feat_1", "feat_2"]
    back = read_gaussian_ply(path)
    g = scene.gaussians
    for key in ("means", "scales", "quats", "opacities", "colors", "features"):
        torch.testing.assert_close(getattr(back, key), getattr(g, key), rtol=1e-5, atol=1e-5, msg=key)
    # Stored encodings: SH DC colour, logit opacity, log scale.
    from image2sim.simulator.io.ply import read_ply

    raw = read_ply(path)
    np.testing.assert_allclose(raw["f_dc_0"], (g.colors[:, 0].numpy() - 0.5) / SH_C0, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(raw["scale_1"], np.log(g.scales[:, 1].numpy()), rtol=1e-5, atol=1e-5)
    o = g.opacities.double().numpy()
    np.testing.assert_allclose(raw["opacity"], np.log(o / (1 - o)), rtol=1e-4, atol=1e-4)
    # A renderer sees the same scene from the PLY (float32 round trip of logit/log encodings).
    cam = EquirectCamera(32, 64)
    a = scene.render(cam, torch.eye(4), backend="torch")
    b = GaussianScene.from_ply(path).render(cam, torch.eye(4), backend="torch")
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-4, rtol=0)


def test_ply_with_opacity_one_and_no_features(tmp_path):
    scene = _scene(feat=0)
    scene.gaussians.opacities[:] = 1.0
    back = read_gaussian_ply(scene.export_ply(tmp_path / "g.ply"))
    assert back.feature_dim == 0 and torch.all(back.opacities > 0.9999)


def test_ply_rejects_non_gaussian_files(tmp_path):
    from image2sim.simulator.io.ply import write_ply

    write_ply(tmp_path / "pts.ply", np.zeros((3, 3)))
    with pytest.raises(SceneError, match="missing properties"):
        read_gaussian_ply(tmp_path / "pts.ply")


@pytest.fixture(scope="module")
def procedural_capture(tmp_path_factory):
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=5))
    out = tmp_path_factory.mktemp("cap") / "scene_000"
    write_scene(generate_scene(sc, seed=2), out)
    return out


def test_cli_build_scene_and_render(procedural_capture, tmp_path):
    from image2sim.simulator.cli import sim_app
    from image2sim.simulator.io.images import read_rgb
    from typer.testing import CliRunner

    runner = CliRunner()
    scene_dir = tmp_path / "scene"
    res = runner.invoke(
        sim_app, ["build-scene", str(procedural_capture), "--out", str(scene_dir), "--frames", "0-2"]
    )
    assert res.exit_code == 0, res.output
    manifest = json.loads((scene_dir / "manifest.json").read_text())
    assert [f["index"] for f in manifest["frames"]] == [0, 1, 2]
    assert manifest["encoder"]["kind"] == "identity" and (scene_dir / "gaussians.ply").is_file()
    from image2sim.simulator.gaussians.refine import default_refine_steps

    assert manifest["refine"]["steps"] == default_refine_steps(3) == 6  # the default path refines
    assert manifest["refine"]["loss_last"] < manifest["refine"]["loss_first"]
    res = runner.invoke(
        sim_app,
        [
            "render",
            str(scene_dir),
            "--frame",
            "4",
            "--out",
            str(tmp_path / "p.png"),
            "--height",
            "32",
            "--width",
            "64",
        ],
    )
    assert res.exit_code == 0, res.output
    assert read_rgb(tmp_path / "p.png").shape == (32, 64, 3)
    assert (tmp_path / "p_depth.png").is_file() and (tmp_path / "p_alpha.png").is_file()
    res = runner.invoke(
        sim_app, ["render", str(scene_dir), "--pose", "0 0 1.4 1 0 0", "--out", str(tmp_path / "q.png")]
    )
    assert res.exit_code == 2 and "7 numbers" in res.output
    res = runner.invoke(sim_app, ["build-scene", str(procedural_capture), "--out", str(scene_dir)])
    assert res.exit_code == 2 and "already exists" in res.output


def test_identity_render_reproduces_a_source_view(procedural_capture):
    cfg = tiny()
    cfg = dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, height=64, width=128))
    scene = build_scene(procedural_capture, cfg, frames=[0])
    from image2sim.simulator.io.registry import open_capture

    f = prepare_frame(open_capture(procedural_capture)[0], 64, 128)
    out = scene.render(f.camera, f.cam_to_world.float())
    mask = (f.depth > 0) & (out.alpha > 0.5)
    err = (out.rgb - f.rgb).abs()[mask.expand_as(out.rgb)].mean()
    assert float(mask.float().mean()) > 0.95 and float(err) < 0.06


@pytest.mark.realdata
def test_real_hm3d_identity_held_out_view(hm3d_scene_dir):
    from image2sim.simulator.io.registry import open_capture

    cap = open_capture(hm3d_scene_dir)
    target = 0
    sources = nearest_frames(cap.poses, target, 4)
    cfg = tiny()
    scene = build_scene(hm3d_scene_dir, cfg, frames=sources)
    f = prepare_frame(cap[target], cfg.encoder.height, cfg.encoder.width)
    out = scene.render(f.camera, f.cam_to_world.float())
    mse = float(((out.rgb - f.rgb) ** 2).mean())
    psnr = -10 * np.log10(mse)
    coverage = float((out.alpha > 0.5).float().mean())
    print(
        f"HM3D identity: target {target} from {sources}: {len(scene)} Gaussians, PSNR {psnr:.2f} dB, "
        f"alpha>0.5 coverage {coverage:.3f}"
    )
    assert psnr > 18.0 and coverage > 0.9


def test_batched_fusion_matches_incremental(procedural_capture):
    cfg = tiny()
    cfg = dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, height=64, width=128))
    one = build_scene(procedural_capture, cfg, fuse_every=1)
    many = build_scene(procedural_capture, cfg, fuse_every=3)
    assert one.frames == many.frames and [f["index"] for f in one.frames] == [0, 1, 2, 3, 4]
    assert abs(len(one) - len(many)) < 0.1 * len(one)
    torch.testing.assert_close(one.gaussians.weights.sum(), many.gaussians.weights.sum())
    with pytest.raises(ValueError, match="fuse_every"):
        build_scene(procedural_capture, cfg, fuse_every=0)


def test_building_frames_on_threads_gives_the_same_scene(procedural_capture):
    """``workers`` > 1 reads, encodes and best-view-selects frames on threads, a few ahead of fusion;
    fusion keeps frame order, so every tensor and the manifest are those of one worker."""
    cfg = tiny()
    cfg = dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, height=64, width=128))
    one = build_scene(procedural_capture, cfg)
    three = build_scene(procedural_capture, cfg, workers=3)
    assert len(one) > 0
    for name in ("means", "scales", "quats", "opacities", "colors", "weights"):
        assert torch.equal(getattr(one.gaussians, name), getattr(three.gaussians, name)), name
    assert one.info == three.info
    with pytest.raises(ValueError, match="workers"):
        build_scene(procedural_capture, cfg, workers=0)


def test_scene_condition_for_the_renderer():
    from image2sim.simulator.gaussians.condition import scene_condition
    from image2sim.simulator.renderer.condition import ALPHA, DEPTH, FEATURES, RGB

    scene = _scene(feat=16)
    cam = EquirectCamera(32, 64)
    cond = scene_condition(scene, cam, torch.eye(4), backend="torch")
    out = scene.render(cam, torch.eye(4), backend="torch")
    assert cond.shape == (1, 24, 32, 64)
    torch.testing.assert_close(cond[:, ALPHA], out.alpha)
    ok = out.alpha > 0.1
    torch.testing.assert_close(cond[:, DEPTH][ok], (out.depth / out.alpha)[ok])
    torch.testing.assert_close(
        (cond[:, RGB] * out.alpha)[ok.expand(-1, 3, -1, -1)], out.rgb[ok.expand(-1, 3, -1, -1)]
    )
    torch.testing.assert_close(
        (cond[:, FEATURES] * out.alpha)[ok.expand(-1, 16, -1, -1)], out.features[ok.expand(-1, 16, -1, -1)]
    )
    assert torch.all(scene_condition(_scene(feat=0), cam, torch.eye(4), backend="torch")[:, FEATURES] == 0)
    with pytest.raises(SceneError, match="feature channels"):
        scene_condition(_scene(feat=3), cam, torch.eye(4), backend="torch")


def test_scene_manifest_paths_are_relative_and_the_scene_moves(procedural_capture, tmp_path):
    """The manifest names its source capture relative to itself (issue 22: relocatable outputs);
    in memory, and after the folder and its capture move together, it resolves to the capture."""
    import shutil

    root = tmp_path / "work"
    capture = root / "captures" / "scene_000"
    shutil.copytree(procedural_capture, capture)
    scene = build_scene(capture, tiny(), frames=[0, 1])
    out = scene.save(root / "scenes" / "scene_000")
    stored = json.loads((out / "manifest.json").read_text())["source"]["capture"]
    assert stored == "../../captures/scene_000"
    moved = tmp_path / "elsewhere"
    shutil.move(str(root), str(moved))
    loaded = GaussianScene.load(moved / "scenes" / "scene_000")
    assert Path(loaded.info["source"]["capture"]).resolve() == (moved / "captures" / "scene_000").resolve()
    # A manifest written before paths were relative (absolute) still reads as it is.
    man = moved / "scenes" / "scene_000" / "manifest.json"
    old = json.loads(man.read_text())
    old["source"]["capture"] = "/somewhere/absolute"
    man.write_text(json.dumps(old))
    assert GaussianScene.load(man.parent).info["source"]["capture"] == "/somewhere/absolute"
