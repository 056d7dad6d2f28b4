"""The README's demo figure on a tiny procedural scene: panels, episode map, atomic PNG, CLI wiring."""

from __future__ import annotations

import json

import numpy as np
import pytest
from image2sim.eval.figure import FigureError, pick_episode, topdown_image


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """Pipeline-shaped outputs of one tiny scene: capture, scene folder (navmap), episode file."""
    from image2sim.dataengine.episodes import episode_record, gt_record, write_episode_files
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.eval.runner import sample_point_goal_episodes
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.navigation import NavGraph, NavMapConfig, extract_navmap
    from image2sim.simulator.sim import NeuralSimulator

    root = tmp_path_factory.mktemp("pipeline")
    capture = root / "data" / "scene_000"
    write_scene(generate_scene(preset("tiny"), seed=0), capture)
    navmap = extract_navmap(open_capture(capture), config=NavMapConfig(floor_labels=(1, 10)))
    scene = root / "scenes" / "scene_000"
    navmap.save(scene / "navmap.npz")
    sim = NeuralSimulator(navmap, NavGraph.build(navmap))
    eps = sample_point_goal_episodes(
        sim, 3, seed=0, min_distance=1.0, scene_id=open_capture(capture).scene_id
    )
    assert eps[0].scene_id != "scene_000"  # folder name and scene id differ, as in the pipeline
    records = [
        episode_record(  # the scene id the data engine writes: the capture manifest's
            e.episode_id,
            open_capture(capture).scene_id,
            e.start_position,
            e.start_heading,
            e.goal_position,
            3.0,
            e.reference_path,
            "Go to the goal.",
            e.geodesic_distance,
        )
        for e in eps
    ]
    gt = {e.episode_id: gt_record(e.reference_path, [0], 0) for e in eps}
    write_episode_files(root / "episodes", "train", records, gt)
    return {"root": root, "capture": capture, "scene": scene, "navmap": navmap, "episodes": eps}


def test_topdown_image_colours_navigable_obstacle_and_unknown_cells(outputs):
    m = outputs["navmap"]
    img = topdown_image(m)
    assert img.shape == (*m.shape2d, 3)
    i, j = m.floor_ij[m.navigable][0]
    assert tuple(img[i, j]) == (0.80, 0.90, 1.00)
    oi, oj = m.obstacle_ij[0]
    floor_cols = {tuple(c) for c in m.floor_ij}
    if (oi, oj) not in floor_cols:
        assert tuple(img[oi, oj]) == (0.55, 0.55, 0.55)
    assert (img == 1.0).all(axis=-1).any()  # unknown space stays white


def test_pick_episode_takes_the_scene_longest_path(outputs):
    eps = outputs["episodes"]
    best = pick_episode(eps, ["scene_000", eps[0].scene_id])
    assert pick_episode(eps, eps[0].scene_id) is best
    lengths = [float(np.linalg.norm(np.diff(e.reference_path, axis=0), axis=1).sum()) for e in eps]
    assert best is eps[int(np.argmax(lengths))]
    with pytest.raises(FigureError, match="scene_999"):
        pick_episode(eps, "scene_999")


@pytest.fixture(scope="module")
def report_run(outputs, tmp_path_factory):
    """``eval report`` with the figure options on the pipeline-shaped outputs (one run, several checks)."""
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    out_dir = tmp_path_factory.mktemp("rep")
    args = ["report", "--out-dir", str(out_dir), "--figure-scene", str(outputs["scene"])]
    args += [
        "--figure-capture",
        str(outputs["capture"]),
        "--figure-episodes",
        str(outputs["root"] / "episodes"),
    ]
    args += ["--holdout-every", "4"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    shown = json.loads(res.output.split("demo_figure.png (", 1)[1].rsplit(")", 1)[0])
    return out_dir, shown


def test_report_writes_the_figure_atomically_from_pipeline_outputs(outputs, report_run):
    import matplotlib.image as mpimg

    out_dir, shown = report_run
    out = out_dir / "demo_figure.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out_dir.iterdir()] == ["demo_figure.png"]  # no temp file left
    img = mpimg.imread(out)
    assert img.shape[0] > 400 and img.shape[1] > 800
    longest = pick_episode(outputs["episodes"], outputs["episodes"][0].scene_id)
    assert shown["episode_id"] == longest.episode_id
    assert shown["path_points"] == len(longest.reference_path)


def test_figure_shows_the_view_and_scores_of_eval_render(outputs, report_run):
    """The figure's held-out view, splat prior and rendering are those ``eval render`` scores."""
    from image2sim.eval.render_bench import RenderBenchConfig, _methods, benchmark_methods
    from image2sim.eval.render_samples import splat_samples
    from image2sim.simulator.renderer.config import load_renderer_config

    _, shown = report_run
    cfg = load_renderer_config("tiny")
    samples = splat_samples([outputs["capture"]], cfg.height, cfg.width, 4, max_views=1)
    assert shown["view_index"] == samples[0]["index"] == 3  # frames 0-2 build the Gaussians
    cells = benchmark_methods(_methods(cfg, RenderBenchConfig(steps=[1])), {"t": samples}, warmup=0, runs=1)
    for name in ("splat_only", "flow_1step"):
        assert shown[f"psnr_{name}"] == pytest.approx(cells[name]["t"].metrics["psnr"].mean, abs=1e-4)
    assert 10.0 < shown["psnr_splat_only"] < 60.0


def test_report_cli_figure_options_are_checked(outputs, tmp_path):
    from image2sim.eval.cli import app
    from typer.testing import CliRunner

    res = CliRunner().invoke(app, ["report", "--figure-scene", str(outputs["scene"])])
    assert res.exit_code != 0 and "--figure-capture" in res.output
    with pytest.raises(FigureError, match="episode file not found"):
        from image2sim.eval.figure import demo_figure_from_outputs

        demo_figure_from_outputs(
            outputs["scene"], outputs["capture"], tmp_path / "none.json.gz", tmp_path / "x.png"
        )
