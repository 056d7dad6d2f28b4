"""`sim build-scene` writes a complete scene (Gaussians + navigation map + graph) that `eval nav` reads
(issue 21: a build-scene output used to lack the map, and `eval nav` on it failed with a traceback)."""

from __future__ import annotations

import json


def test_build_scene_output_runs_in_eval_nav(tmp_path, run_main):
    from image2sim.dataengine.procedural import preset, synthesize

    capture = synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=2, progress=False)[0]
    scene = tmp_path / "scenes" / "house"
    code, output = run_main(["sim", "build-scene", str(capture), "--out", str(scene), "--no-ply"])
    assert code == 0, output
    assert (scene / "navmap.npz").is_file() and (scene / "navgraph.npz").is_file()
    assert "graph nodes" in output
    metrics = tmp_path / "nav.json"
    args = ["eval", "nav", "--scenes", str(scene.parent), "--point-goal", "3", "--min-distance", "0.5"]
    args += ["--agent", "random", "--out", str(tmp_path / "run"), "--metrics", str(metrics)]
    code, output = run_main(args)
    assert code == 0, output[-3000:]
    doc = json.loads(metrics.read_text())
    assert "Traceback" not in output and doc  # the headline record exists


def test_no_navigation_leaves_the_map_out(tmp_path, run_main):
    from image2sim.dataengine.procedural import preset, synthesize

    capture = synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=2, progress=False)[0]
    scene = tmp_path / "house"
    code, output = run_main(["sim", "build-scene", str(capture), "--out", str(scene), "--no-navigation"])
    assert code == 0, output
    assert (scene / "gaussians.safetensors").is_file() and not (scene / "navmap.npz").exists()
