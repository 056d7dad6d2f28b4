"""`data episodes --detector annotations|none` and captures of any format (issue 21)."""

from __future__ import annotations

import dataclasses
import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest
from image2sim.dataengine.annotate.prompts import STRUCTURES, TONES, AnnotationRequest
from image2sim.dataengine.annotate.template import compose, compose_path
from image2sim.dataengine.chunking import MacroStep, path_features
from image2sim.dataengine.distributed import RunError, find_scenes, run_engine
from image2sim.dataengine.engine_config import EngineConfig
from image2sim.dataengine.episodes import read_extras
from image2sim.dataengine.objects_file import ObjectsFileError, load_objects_file

SHORT = {"min_path_length": 1.0}


@pytest.fixture(scope="module")
def house(tmp_path_factory) -> Path:
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path_factory.mktemp("synth")
    # The default house at a quarter of the capture's resolution: the same layout and objects, and
    # the map these tests need, in a quarter of the time.
    cfg = preset("default")
    cfg = dataclasses.replace(cfg, capture=dataclasses.replace(cfg.capture, height=128, width=256))
    return synthesize(cfg, root, scenes=1, seed=4, progress=False)[0]


def _episodes(out: Path) -> list[dict]:
    with gzip.open(out / "train" / "train.json.gz", "rt") as fh:
        return json.load(fh)["episodes"]


# --- the objects file ------------------------------------------------------------------------------


def test_objects_file_reads_points_boxes_rooms_and_small_items(tmp_path):
    path = tmp_path / "objects.json"
    path.write_text(
        json.dumps(
            {
                "objects": [
                    {"category": "bed", "position": [1, 2, 0.5], "room": "Bed room"},
                    {"category": "Coffee table", "box": {"min": [0, 0, 0], "max": [2, 1, 0.4]}},
                    {"category": "cup", "position": [3, 3, 0.9], "small": True},
                ]
            }
        )
    )
    objs = load_objects_file(path)
    assert [o.category for o in objs] == ["bed", "coffee_table", "cup"]
    assert objs[1].position == [1.0, 0.5, 0.2] and [o.object_id for o in objs] == [1, 2, 3]
    assert objs[0].room_type == "bed_room" and objs[2].small and not objs[0].small


@pytest.mark.parametrize(
    ("objects", "message"),
    [
        ([], r"'objects' must be a non-empty list"),
        ([{"category": "bed"}], r"objects\[0\]: give exactly one of 'position' or 'box'"),
        ([{"category": "bed", "position": [1, 2]}], r"objects\[0\]\.position: expected 3 finite numbers"),
        ([{"category": "bed", "position": [1, 2, "x"]}], r"objects\[0\]\.position"),
        ([{"category": "", "position": [1, 2, 3]}], r"objects\[0\]\.category"),
        ([{"category": "bed", "positon": [1, 2, 3]}], r"objects\[0\]: unknown field\(s\) \['positon'\]"),
        ([{"category": "tv", "box": {"min": [2, 0, 0], "max": [1, 1, 1]}}], r"objects\[0\]\.box: min"),
        ([{"category": "tv", "position": [1, 2, 3], "small": "yes"}], r"objects\[0\]\.small"),
    ],
)
def test_a_bad_objects_file_names_the_object_and_field(tmp_path, objects, message):
    path = tmp_path / "objects.json"
    path.write_text(json.dumps({"objects": objects}))
    with pytest.raises(ObjectsFileError, match=message):
        load_objects_file(path)


def test_a_missing_or_broken_objects_file_is_a_clear_error(tmp_path):
    with pytest.raises(ObjectsFileError, match="objects file not found"):
        load_objects_file(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ObjectsFileError, match="not readable JSON"):
        load_objects_file(tmp_path / "bad.json")


# --- path features and path instructions -----------------------------------------------------------


def _steps(n: int, per: int = 4) -> list[MacroStep]:
    return [MacroStep(k * per, (k + 1) * per, 1.0, 0.0, False, "walk forward") for k in range(n)]


def test_a_doorway_is_a_narrow_point_between_open_spaces_and_a_corridor_is_not():
    pos = np.stack((np.arange(25) * 0.25, np.zeros(25), np.zeros(25)), axis=1)
    steps = _steps(6)
    door = np.full(25, 1.0)
    door[11:13] = 0.35  # a 0.7 m passage half-way
    feats = path_features(steps, pos, door)
    assert sum(f.count("doorway") for f in feats) == 1 and "doorway" in feats[2]
    corridor = np.full(25, 1.0)
    corridor[3:22] = 0.4  # 4.75 m of narrow corridor: no doorway
    assert not any(path_features(steps, pos, corridor))
    rising = pos.copy()
    rising[8:, 2] = np.minimum(np.arange(17) * 0.15, 2.0)
    feats = path_features(steps, rising, np.full(25, 1.0))
    assert "stairs_up" in feats[2] and not any("stairs_down" in f for f in feats)


def _path_request(moves, distances, turns, features, tone="neutral", structure="sequential", seed=0):
    n = len(moves)
    return AnnotationRequest(
        "p",
        moves,
        [],
        {},
        [[] for _ in range(n)],
        [None] * n,
        "r2r",
        structure,
        tone,
        seed=seed,
        distances=distances,
        turns=turns,
        features=features,
    )


def test_path_instructions_sum_walks_and_turns_and_name_doorways_and_stairs():
    moves = ["walk forward"] * 3 + ["turn left", "turn left", "walk forward", "walk forward", "stop"]
    req = _path_request(
        moves,
        [1, 1, 1, 0, 0, 1, 1, 0],
        [0, 5, -5, 45, 45, 0, 0, 0],
        [[], [], [], [], [], ["doorway"], [], []],
    )
    text = compose_path(req)
    assert "3 meters" in text and text.count("left") == 1 and "door" in text, text
    assert text.endswith(".") and text[0].isupper()
    # A turn under 30 degrees is not mentioned; a curve of 60+ degrees while walking is.
    quiet = compose_path(
        _path_request(["turn left", "walk forward", "stop"], [0, 4, 0], [20, 0, 0], [[]] * 3)
    )
    assert "left" not in quiet and "4 meters" in quiet
    curve = compose_path(
        _path_request(["walk forward"] * 3 + ["stop"], [1, 1, 1, 0], [-30, -35, 0, 0], [[]] * 4)
    )
    assert "right" in curve
    stairs = compose_path(_path_request(["walk forward", "stop"], [2, 0], [0, 0], [["stairs_down"], []]))
    assert "down the stairs" in stairs or "stairs down" in stairs
    assert compose(req) == text  # compose routes a request without a goal object here


def test_every_path_instruction_is_grammatical():
    """All tones x structures over movement sequences with distances, turns, doorways and stairs."""
    from tests.dataengine.test_annotate import _grammar_problems

    moves = [
        "walk forward",
        "turn left",
        "turn right",
        "walk forward while turning left",
        "turn around to the right",
    ]
    feats = [[], ["doorway"], ["stairs_up"], ["stairs_down"]]
    n, problems = 0, []
    rng = np.random.default_rng(0)
    for structure in STRUCTURES:
        for tone in TONES:
            for seed in range(120):
                k = int(rng.integers(0, 6))
                seq = [moves[int(i)] for i in rng.integers(0, len(moves), k)]
                dist = [0.0 if m.startswith("turn") else float(rng.uniform(0.3, 2.5)) for m in seq]
                turns = [float(rng.uniform(-180, 180)) for _ in seq]
                fs = [feats[int(i)] for i in rng.integers(0, len(feats), k)]
                req = _path_request(
                    seq + ["stop"], dist + [0.0], turns + [0.0], fs + [[]], tone, structure, seed
                )
                text = compose(req)
                n += 1
                problems += [(p, text) for p in _grammar_problems(text)]
    assert n >= 1000 and not problems, problems[:5]


# --- the engine --------------------------------------------------------------------------------------


def test_detector_none_makes_path_episodes_that_replay_and_stay_valid(house, tmp_path):
    out = tmp_path / "none"
    cfg = EngineConfig(detector="none", render="none", per_scene=8, seed=1)
    summary = run_engine(house.parent, out, cfg, progress=False)
    assert summary["episodes"] >= 6, summary
    eps = _episodes(out)
    extras = read_extras(out / "train" / "train.json.gz")
    for e in eps:
        assert extras[e["episode_id"]]["goal_object"] == {} and e["info"]["geodesic_distance"] >= 3.0
        assert e["goals"][0]["radius"] == 3.0
        text = e["instruction"]["instruction_text"]
        assert "stop" in text or "wait" in text
    done = json.loads((out / "scenes" / house.name / "done.json").read_text())
    assert done["objects"] == 0 and "collision" not in done.get("plan_stats", {})


def test_detector_none_renders_its_shards_at_the_default_stride(house, tmp_path):
    """Path episodes have no goal object: their shards are written without goal-in-view labels (a
    render of them once failed on the missing goal position), one frame per two steps by default."""
    from image2sim.navpolicy.data import ShardReader

    out = tmp_path / "none_rendered"
    cfg = EngineConfig(detector="none", render="procedural", obs_height=16, per_scene=3, seed=1)
    summary = run_engine(house.parent, out, cfg, progress=False)
    assert summary["episodes"] >= 2 and summary["shards"] == 1, summary
    reader = ShardReader(out / "scenes" / house.name / "shard")
    assert len(reader) == summary["episodes"]
    for i in range(len(reader)):
        t = reader[i]
        assert list(t.frame_steps) == list(range(0, len(t.actions), 2))
        assert t.frames.shape[1:] == (16, 16, 3) and "goal_in_view" not in t.extra


def test_detector_annotations_names_the_annotated_objects(house, tmp_path):
    gt = json.loads((house / "gt" / "objects.json").read_text())
    items = gt["objects"] if isinstance(gt, dict) else gt
    chosen = [o for o in items if o.get("category") in ("bed", "sofa", "fridge", "tv", "toilet")][:4]
    assert chosen, "the procedural house has no large goal object"
    path = tmp_path / "objects_annotations.json"
    path.write_text(
        json.dumps(
            {
                "objects": [
                    {"category": o["category"], "box": o["aabb"], "room": o["room_type"]} for o in chosen
                ]
            }
        )
    )
    out = tmp_path / "ann"
    cfg = EngineConfig(detector="annotations", objects=str(path), render="none", per_scene=6, seed=2)
    summary = run_engine(house.parent, out, cfg, progress=False)
    assert summary["episodes"] >= 3, summary
    names = {o["category"] for o in chosen}
    extras = read_extras(out / "train" / "train.json.gz")
    for e in _episodes(out):
        assert extras[e["episode_id"]]["goal_object"]["category"] in names


def test_detector_none_refuses_vlm_annotators():
    with pytest.raises(ValueError, match="template annotator"):
        EngineConfig(detector="none", annotator="openai")
    with pytest.raises(ValueError, match="detector must be one of"):
        EngineConfig(detector="owl")


def test_raw_captures_are_scenes_and_other_folders_get_a_message(tmp_path):
    from tests.simulator.test_io_room import write_hm3d_fixture

    raw = write_hm3d_fixture(tmp_path / "raw" / "house_a", n=3)
    assert find_scenes(raw) == [raw]
    assert find_scenes(raw.parent) == [raw]
    (tmp_path / "empty" / "notes").mkdir(parents=True)
    with pytest.raises(RunError, match="data inspect"):
        find_scenes(tmp_path / "empty")


@pytest.mark.slow
@pytest.mark.realdata
def test_the_hm3d_sample_yields_50_path_episodes(hm3d_scene_dir, tmp_path):
    summary = run_engine(
        hm3d_scene_dir, tmp_path / "out", EngineConfig(detector="none", render="none"), progress=False
    )
    assert summary["episodes"] >= 50, summary
    for e in _episodes(tmp_path / "out"):
        assert e["info"]["geodesic_distance"] >= 3.0 and not math.isnan(e["info"]["geodesic_distance"])


def test_asking_for_more_plans_keeps_the_first_ones(house):
    """Plan i depends only on plans 0..i-1, so the pipeline's oversampling (plans drawn 1.5x over the
    wanted count, failures replaced) can only add episodes, never lose the ones a smaller run had."""
    from image2sim.dataengine.scene_assets import resolve_scene, scene_navigation
    from image2sim.dataengine.trajectories import SamplingConfig, sample_path_plans, sample_plans
    from image2sim.simulator.sim import NeuralSimulator

    cache = house.parent / "plans_cache"
    cache.mkdir(exist_ok=True)
    navmap, graph = scene_navigation(resolve_scene(house), cache)
    cfg = SamplingConfig()
    few, _ = sample_path_plans(graph, 4, cfg, np.random.default_rng(5))
    more, _ = sample_path_plans(graph, 7, cfg, np.random.default_rng(5))
    assert len(few) == 4 and len(more) == 7
    for a, b in zip(few, more, strict=False):
        assert np.array_equal(a.start, b.start) and np.array_equal(a.goal, b.goal) and a.heading == b.heading
    gt = json.loads((house / "gt" / "objects.json").read_text())["objects"]
    from image2sim.dataengine.mining import SceneObject

    objs = [
        SceneObject(o["id"], o["category"], o["center"], small=o["small"])
        for o in gt
        if not o.get("walkable") and o["category"] not in ("floor", "wall", "ceiling", "rug")
    ]
    planner = NeuralSimulator(navmap, graph).planner
    few, _ = sample_plans(graph, planner, objs, 3, cfg, np.random.default_rng(6), navmap.to_map)
    more, _ = sample_plans(graph, planner, objs, 6, cfg, np.random.default_rng(6), navmap.to_map)
    assert len(few) == 3
    for a, b in zip(few, more, strict=False):
        assert np.array_equal(a.start, b.start) and a.goal_object == b.goal_object


@pytest.mark.slow
def test_rendering_a_scene_over_two_workers_gives_the_same_shard(tmp_path):
    """One scene on a 2-worker run renders its episodes in 2 processes (parallel inside the scene);
    the shard is byte-for-byte the one a single process writes."""
    from image2sim.dataengine.pipeline import process_scene
    from image2sim.dataengine.procedural import preset, synthesize

    cap = synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)[0]
    cfg = EngineConfig(per_scene=4, obs_height=24, seed=3, render="gaussians", sampling=SHORT)
    one = process_scene(cap, tmp_path / "one", cfg, render_workers=1)
    two = process_scene(cap, tmp_path / "two", cfg, render_workers=2)
    assert one["episodes"] == two["episodes"] >= 2
    shard_one, shard_two = (tmp_path / d / "scenes" / cap.name / "shard" for d in ("one", "two"))
    files = sorted(p.name for p in (shard_one / "frames").iterdir())
    assert files == sorted(p.name for p in (shard_two / "frames").iterdir()) and files
    for name in files:
        with np.load(shard_one / "frames" / name) as a, np.load(shard_two / "frames" / name) as b:
            assert np.array_equal(a["rgb"], b["rgb"])
    assert (shard_one / "trajectories.jsonl").read_text() == (shard_two / "trajectories.jsonl").read_text()


def test_a_failing_background_gaussian_build_stops_the_scene_with_its_error(tmp_path):
    """With two workers the Gaussians build in a process of their own while the map and rollouts
    are made; an error there (here a bad Gaussian config) reaches the caller by name, and the scene
    writes no shard."""
    from image2sim.dataengine.pipeline import process_scene
    from image2sim.dataengine.procedural import preset, synthesize

    cap = synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)[0]
    bad = {"fusion": {"footprint_factor": -1.0}}
    cfg = EngineConfig(per_scene=2, obs_height=24, seed=3, render="gaussians", sampling=SHORT, gaussians=bad)
    with pytest.raises(RuntimeError, match="building the scene's Gaussians failed: .*footprint_factor"):
        process_scene(cap, tmp_path / "out", cfg, render_workers=2)
    assert not (tmp_path / "out" / "scenes" / cap.name / "shard").exists()
    assert not (tmp_path / "out" / "scenes" / cap.name / "gaussians").exists()


@pytest.mark.parametrize("render_workers, inside", [(1, None), (2, 1)])
def test_with_render_workers_the_scene_runs_its_own_torch_ops_on_one_thread(
    tmp_path, monkeypatch, render_workers, inside
):
    """The render workers and the Gaussians' build hold the cores, so the scene's own process keeps
    to one torch thread while they run (two oversubscribed a 2-core machine: the HM3D command took
    159 s instead of 149); one worker leaves the count alone, and it is restored after."""
    import types

    import torch
    from image2sim.dataengine import pipeline

    seen = []
    monkeypatch.setattr(pipeline, "resolve_scene", lambda d: types.SimpleNamespace(name="s"))
    monkeypatch.setattr(pipeline.GaussianPrebuild, "start", classmethod(lambda cls, *a: None))
    monkeypatch.setattr(pipeline, "_run_scene", lambda *a: seen.append(torch.get_num_threads()) or {})
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        pipeline.process_scene(tmp_path, tmp_path / "out", EngineConfig(), render_workers=render_workers)
        assert seen == [inside or 2] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_second_run_copies_scene_assets_from_the_content_keyed_cache(tmp_path, monkeypatch):
    """`--cache`: the first run builds the map, graph and Gaussians and stores them by the capture's
    content; a run into another folder copies them (nothing rebuilt) and writes the same episodes;
    an edited capture gets a new key."""
    import image2sim.dataengine.procedural.exact as exact
    from image2sim.dataengine.asset_cache import content_key
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path / "caps"
    cap = synthesize(preset("tiny"), root, scenes=1, seed=0, progress=False)[0]
    cfg = EngineConfig(per_scene=3, obs_height=24, seed=3, render="gaussians", sampling=SHORT)
    cache = tmp_path / "assets"
    run_engine(root, tmp_path / "a", cfg, progress=False, asset_cache=cache, workers=1)
    assert len(list(cache.iterdir())) == 2  # navigation + gaussians entries
    built = []
    real = exact.capture_navigation
    monkeypatch.setattr(exact, "capture_navigation", lambda *a, **k: (built.append(1), real(*a, **k))[1])
    run_engine(root, tmp_path / "b", cfg, progress=False, asset_cache=cache, workers=1)
    assert built == []  # copied, not rebuilt
    assert (tmp_path / "a" / "train" / "train.json.gz").read_bytes() == (
        tmp_path / "b" / "train" / "train.json.gz"
    ).read_bytes()
    key = content_key(cap, "navigation", "procedural=True")
    (cap / "frames" / "00000_pose.json").write_text((cap / "frames" / "00000_pose.json").read_text() + " ")
    assert content_key(cap, "navigation", "procedural=True") != key


def test_refined_scene_gaussians_are_recorded_and_keyed_apart(tmp_path):
    """``refine_steps``: the Gaussians the engine builds are refined (recorded in their manifest; -1
    resolves to two steps per frame), and the content-keyed cache keeps them apart from the
    feed-forward build of the same capture."""
    import json

    from image2sim.dataengine.procedural import preset, synthesize
    from image2sim.dataengine.scene_assets import resolve_scene, scene_gaussians

    cap = synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)[0]
    inputs = resolve_scene(cap)
    cache = tmp_path / "assets"
    manifests = {}
    for steps in (0, 2, -1):
        folder = scene_gaussians(inputs, tmp_path / f"run{steps}", str(cache), refine_steps=steps)
        manifests[steps] = json.loads((folder / "manifest.json").read_text())
    frames = len(manifests[0]["frames"])
    assert "refine" not in manifests[0]
    assert manifests[2]["refine"]["steps"] == 2
    assert manifests[-1]["refine"]["steps"] == min(50, 2 * frames)
    assert len(list(cache.iterdir())) == 3  # three keys: nothing reused across refinement settings
