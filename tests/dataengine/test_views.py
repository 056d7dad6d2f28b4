"""Recognition views (``data views``): the agent's own observations with exact per-pixel categories."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from image2sim.dataengine.procedural.views import ViewsConfig, load_views, render_views, write_views

CFG = ViewsConfig(per_scene=6, size=32, seed=1)


@pytest.fixture(scope="module")
def houses(tmp_path_factory) -> Path:
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path_factory.mktemp("synth")
    synthesize(preset("tiny"), root, scenes=2, seed=0, progress=False)
    return root


def test_views_are_what_the_agent_observes_with_the_houses_categories(houses):
    from image2sim.dataengine.procedural.exact import capture_navigation, exact_render_fn, procedural_scene_of
    from image2sim.simulator.sim import NeuralSimulator, ObservationSpec

    cap = houses / "scene_000"
    v = render_views(cap, CFG)
    assert v["rgb"].shape == (6, 32, 32, 3) and v["rgb"].dtype == np.uint8
    assert v["semantics"].shape == (6, 32, 32) and v["semantics"].dtype == np.int16
    navmap, graph = capture_navigation(cap, procedural=True)
    # Poses are nodes of the graph's largest component.
    comp = graph.components
    main = set(np.nonzero(comp == np.bincount(comp).argmax())[0].tolist())
    for p in v["positions"]:
        j = int(np.argmin(np.linalg.norm(graph.nodes - p, axis=1)))
        assert j in main and np.allclose(graph.nodes[j], p, atol=1e-5)
    # The data engine's observation path (NeuralSimulator over the exact renderer) gives the same image.
    spec = ObservationSpec(panorama=False, pinhole=True, pinhole_size=32)
    sim = NeuralSimulator(navmap, graph, exact_render_fn(cap), spec)
    for i in (0, 5):
        obs, _ = sim.reset(v["positions"][i][None].astype(np.float64), np.array([v["headings"][i]]))
        seen = np.clip(obs[0]["pinhole"]["rgb"] * 255.0 + 0.5, 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(seen, v["rgb"][i])
    # Every label is a surface of this house (structure or one of its objects), 0 only where nothing is hit.
    house = set(np.unique(procedural_scene_of(cap).box_category).tolist())
    assert set(np.unique(v["semantics"]).tolist()) - {0} <= house


def test_write_views_resumes_is_deterministic_and_refuses_other_settings(houses, tmp_path):
    dirs = [houses / "scene_000", houses / "scene_001"]
    out = tmp_path / "views"
    write_views(dirs[:1], out, CFG)
    first = (out / "views" / "scene_000.npz").stat().st_mtime_ns
    manifest = write_views(dirs, out, CFG)  # resumes: the first house is kept, the second added
    assert (out / "views" / "scene_000.npz").stat().st_mtime_ns == first
    assert manifest["scenes"] == {"scene_000": 6, "scene_001": 6}
    rgb, sem, m = load_views(out)
    assert rgb.shape == (12, 32, 32, 3) and sem.shape == (12, 32, 32)
    assert any(c["name"] == "sofa" for c in json.loads((out / "categories.json").read_text())["categories"])
    again = render_views(dirs[1], CFG)
    np.testing.assert_array_equal(again["rgb"], rgb[6:])
    other = render_views(dirs[1], ViewsConfig(per_scene=6, size=32, seed=2))
    assert not np.array_equal(other["rgb"], rgb[6:])
    with pytest.raises(ValueError, match="written with"):
        write_views(dirs, out, ViewsConfig(per_scene=7, size=32, seed=1))


def test_bad_inputs_get_clear_errors(houses, tmp_path):
    with pytest.raises(ValueError, match="per_scene"):
        ViewsConfig(per_scene=0).validate()
    with pytest.raises(ValueError, match="hfov"):
        ViewsConfig(hfov_deg=180).validate()
    fake = tmp_path / "real"
    fake.mkdir()
    (fake / "manifest.json").write_text(json.dumps({"metadata": {}}))
    with pytest.raises(ValueError, match="not a procedural capture"):
        render_views(fake, CFG)
    with pytest.raises(FileNotFoundError, match="not a `image2sim data views` folder"):
        load_views(tmp_path)


def test_views_cli_refuses_non_procedural_captures(houses, tmp_path, run_main):
    root = tmp_path / "caps"
    (root / "real").mkdir(parents=True)
    (root / "real" / "manifest.json").write_text(json.dumps({"metadata": {}}))
    code, text = run_main(["data", "views", "--scenes", str(root), "--out", str(tmp_path / "o")])
    assert code != 0 and "not procedural captures" in text
    code, text = run_main(
        [
            "data",
            "views",
            "--scenes",
            str(houses),
            "--out",
            str(tmp_path / "v"),
            "--per-scene",
            "2",
            "--size",
            "16",
        ]
    )
    assert code == 0, text
    assert "4 views of 2 houses" in text
