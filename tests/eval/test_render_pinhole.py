"""Pinhole-input variant of the rendering benchmark: six 90° views per panorama as the input captures."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from image2sim.eval.render_bench import RenderBenchConfig, render_markdown, run_render_bench
from image2sim.eval.render_samples import RenderBenchError, pinhole_faces, splat_samples
from image2sim.eval.results import read_metrics_file


@pytest.fixture(scope="module")
def procedural(tmp_path_factory):
    """A tiny procedural scene and its capture on disk (4 equirect frames, 64 x 128)."""
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    scene = generate_scene(preset("tiny"), seed=0)
    out = tmp_path_factory.mktemp("captures") / "scene_000"
    write_scene(scene, out)
    return scene, out


def test_faces_match_exact_pinhole_renders_of_the_scene(procedural):
    """Each face equals the procedural scene rendered by a 90° pinhole at the face's pose (exact
    ground truth), up to resampling the panorama: same geometry (z-depth) and colour."""
    from image2sim.dataengine.procedural.render import render
    from image2sim.simulator.geometry.cameras import PinholeCamera
    from image2sim.simulator.io.registry import open_capture

    scene, path = procedural
    frame = open_capture(path)[1]
    faces = pinhole_faces(frame, 32)
    assert [f.frame_id.rsplit("_", 1)[1] for f in faces] == ["front", "right", "back", "left", "up", "down"]
    for face in faces:
        assert face.camera == PinholeCamera.from_fov(90.0, 90.0, 32, 32)
        assert face.rgb.shape == (32, 32, 3) and face.rgb.dtype == np.uint8 and face.depth.shape == (32, 32)
        rot = face.cam_to_world[:3, :3]
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        np.testing.assert_array_equal(face.cam_to_world[:3, 3], frame.cam_to_world[:3, 3])
        exact = render(scene, face.camera, face.cam_to_world)
        valid = (face.depth > 0) & (exact["depth"] > 0)
        assert valid.mean() > 0.9
        rel = np.abs(face.depth[valid] - exact["depth"][valid]) / exact["depth"][valid]
        # Nearest-neighbour range samples of a 64 x 128 panorama (2.8° pixels): small median error;
        # a face whose pose or depth conversion were wrong (range for z, a wrong axis) is off by 10-40 %.
        assert float(np.median(rel)) < 0.03, face.frame_id
        err = face.rgb.astype(np.float64) - exact["rgb"].astype(np.float64)
        psnr = 10 * np.log10(255.0**2 / np.mean(err**2))
        assert psnr > 17.0, (face.frame_id, psnr)


def test_faces_need_a_panorama(procedural):
    from image2sim.simulator.io.registry import open_capture

    face = pinhole_faces(open_capture(procedural[1])[0], 16)[0]
    with pytest.raises(RenderBenchError, match="panorama"):
        pinhole_faces(face, 16)


def test_pinhole_input_conditions_cover_the_held_out_panorama(procedural):
    from image2sim.simulator.renderer.config import CONDITION_FEATURES

    _, path = procedural
    pano = splat_samples([path], 32, 64, holdout_every=4)
    pin = splat_samples([path], 32, 64, holdout_every=4, input_views="pinhole6")
    # The same held-out panorama targets; only the inputs differ.
    assert [s["index"] for s in pin] == [s["index"] for s in pano] == [3]
    assert torch.equal(pin[0]["target_rgb"], pano[0]["target_rgb"])
    cond = pin[0]["condition"]
    assert cond.shape == (24, 32, 64) and torch.isfinite(cond).all()
    alpha = cond[CONDITION_FEATURES + 4]
    assert 0.2 < float(alpha.mean()) <= 1.0
    covered = (alpha > 0.9) & (pin[0]["target_depth"][0] > 0)
    target = pin[0]["target_depth"][0][covered]
    rel = (cond[CONDITION_FEATURES + 3][covered] - target).abs() / target
    assert float(rel.median()) < 0.15
    assert not torch.equal(cond, pano[0]["condition"])  # really built from other inputs
    with pytest.raises(RenderBenchError, match="input_views"):
        splat_samples([path], 32, 64, holdout_every=4, input_views="fisheye")


def test_config_validation_of_input_views():
    with pytest.raises(RenderBenchError, match="input_views"):
        RenderBenchConfig(condition_source="gaussians", data=["x"], input_views="cube")
    with pytest.raises(RenderBenchError, match="condition_source 'gaussians'"):
        RenderBenchConfig(input_views="pinhole6")
    assert RenderBenchConfig(condition_source="gaussians", data=["x"], input_views="pinhole6").input_views


def test_cli_render_with_pinhole_inputs(procedural, tmp_path):
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    _, path = procedural
    out = tmp_path / "render.json"
    args = ["render", "--condition-source", "gaussians", "--tier-data", f"none={path}"]
    args += ["--input-views", "pinhole6", "--holdout-every", "4", "--steps", "1"]
    args += ["--warmup", "0", "--runs", "1", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    # Without --plot the speed plot lands beside --out, not in the working directory's plots/.
    assert (tmp_path / "render_speed.png").read_bytes()[:4] == b"\x89PNG"
    doc = read_metrics_file(out)
    assert doc["protocol"]["input_views"] == "pinhole6"
    assert "six 90° pinhole views" in doc["protocol"]["condition_source"]
    assert doc["protocol"]["held_out_views"] == 1
    assert set(doc["methods"]) == {"splat_only", "splat_fill", "flow_1step"}
    assert doc["methods"]["splat_only"]["n_views"] == 1 and doc["methods"]["splat_only"]["psnr"] > 10
    assert "six 90° pinhole views" in render_markdown(doc)
    # The API gives the same document fields.
    bench = RenderBenchConfig.from_dict(
        {
            "condition_source": "gaussians",
            "tier_data": {"none": [str(path)]},
            "input_views": "pinhole6",
            "holdout_every": 4,
            "steps": [1],
            "warmup": 0,
            "runs": 1,
        }
    )
    api = run_render_bench(bench, tmp_path / "api.json", show_progress=False)
    assert api["methods"]["splat_only"]["psnr"] == pytest.approx(doc["methods"]["splat_only"]["psnr"])
