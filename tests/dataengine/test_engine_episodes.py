"""End-to-end data engine on tiny procedural scenes: replay, schema, loaders, shards, resume."""

from __future__ import annotations

import gzip
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from image2sim.dataengine.distributed import merge_outputs, run_engine
from image2sim.dataengine.engine_config import EngineConfig
from image2sim.dataengine.episodes import EpisodeSchemaError, validate_episode_doc
from image2sim.simulator.conventions import Action

# Tiny houses (~3 m^2) hold no 3 m path: these tests of the mechanics allow shorter episodes.
SHORT = {"min_path_length": 1.0}
CFG = dict(per_scene=6, obs_height=32, seed=3, sampling=SHORT)


@pytest.fixture(scope="module")
def scenes_root(tmp_path_factory) -> Path:
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path_factory.mktemp("synth")
    synthesize(preset("tiny"), root, scenes=2, seed=0, progress=False)
    return root


@pytest.fixture(scope="module")
def full_run(scenes_root, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("engine") / "out"
    summary = run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", progress=False)
    return out, summary


def _read(path: Path):
    with gzip.open(path, "rt") as fh:
        return json.load(fh)


def test_run_produces_episodes_for_every_scene(full_run):
    out, summary = full_run
    assert summary["failed"] == {}
    assert summary["scenes_done"] == 2
    assert summary["episodes"] >= 4, summary
    doc = _read(out / "train" / "train.json.gz")
    # scene_id is the scene folder's name, so `<scenes dir>/<scene_id>` finds it (eval nav --scenes).
    assert {e["scene_id"] for e in doc["episodes"]} == {"scene_000", "scene_001"}
    for n in ("scene_000", "scene_001"):
        done = json.loads((out / "scenes" / n / "done.json").read_text())
        assert done["scene"] == n and done["scene_id"].startswith("synth-")  # the capture's own id


def test_every_episode_replays_to_its_recorded_end_without_collision(full_run):
    """Re-execute the gt actions from the loader's start pose in a fresh simulator."""
    from image2sim.eval.datasets import load_image2sim_episodes
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.sim import NeuralSimulator

    out, _ = full_run
    ds = load_image2sim_episodes(out / "train" / "train.json.gz", out / "train" / "train_gt.json.gz")
    sims = {}
    for ep in ds.episodes:
        name = ep.episode_id.rsplit("-", 1)[0]
        if name not in sims:
            sims[name] = NeuralSimulator(NavMap.load(out / "scenes" / name / "navmap.npz"))
        sim = sims[name]
        nm = sim.navmap
        start = nm.to_map(ep.start_position)
        d = nm.to_map(np.array([math.cos(ep.start_heading), math.sin(ep.start_heading), 0.0]))
        _, info = sim.reset(start[None], np.array([math.atan2(d[1], d[0])]), observe=False)
        for a in ep.gt_actions:
            _, info = sim.step([a], observe=False)
            assert not info["collided"][0], f"{ep.episode_id}: collision on replay"
        final = nm.to_world(info["position"][0])
        assert np.abs(final - ep.gt_locations[-1]).max() <= 1e-6, ep.episode_id
        assert ep.gt_actions[-1] == int(Action.STOP)
        assert np.linalg.norm(final[:2] - ep.goal_position[:2]) <= ep.goal_radius + 1e-9
        assert len(ep.gt_locations) == len(ep.gt_actions) + 1


def test_episode_file_schema_and_loader_round_trip(full_run):
    from image2sim.dataengine.episodes import read_extras
    from image2sim.eval.datasets import load_image2sim_episodes
    from image2sim.simulator.geometry.habitat import habitat_heading, habitat_to_world

    out, _ = full_run
    doc = _read(out / "train" / "train.json.gz")
    gt = _read(out / "train" / "train_gt.json.gz")
    extras = read_extras(out / "train" / "train.json.gz")
    validate_episode_doc(doc, gt)
    assert doc["frame"] == "habitat-y-up" and doc["quaternion_order"] == "xyzw"
    assert not (out / "train" / "train_extras.json.gz").exists()  # tools glob *.json.gz: not a sidecar
    ds = load_image2sim_episodes(out / "train" / "train.json.gz", out / "train" / "train_gt.json.gz")
    assert len(ds) == len(doc["episodes"]) == len(extras)
    vocab = doc["instruction_vocab"]["word_list"]
    for raw, ep in zip(doc["episodes"], ds.episodes, strict=True):
        assert ep.episode_id == raw["episode_id"]
        np.testing.assert_allclose(ep.start_position, habitat_to_world(raw["start_position"]), atol=1e-9)
        np.testing.assert_allclose(ep.goal_position, habitat_to_world(raw["goals"][0]["position"]), atol=1e-9)
        assert math.isclose(ep.start_heading, habitat_heading(raw["start_rotation"]), abs_tol=1e-9)
        assert ep.instruction.text == raw["instruction"]["instruction_text"]
        tokens = raw["instruction"]["instruction_tokens"]
        assert len(tokens) == 200 and tokens[-1] == 0  # padded like R2R-CE
        words = [vocab[t] for t in tokens if t != 0]
        assert "".join(words) == "".join(raw["instruction"]["instruction_text"].lower().split())
        assert extras[raw["episode_id"]]["style"] in ("r2r", "reverie", "demand")
        assert gt[raw["episode_id"]]["forward_steps"] == sum(
            1 for a in gt[raw["episode_id"]]["actions"] if a == 1
        )


# An independent replica of how VLN-CE reads an episode file (``VLNCEDatasetV1.from_json``): every
# record is passed as keyword arguments to its episode class (habitat's Episode + NavigationEpisode +
# VLNExtendedEpisode), the instruction to ExtendedInstructionData, each goal to NavigationGoal.
_VLNCE_EPISODE = dict.fromkeys(
    "episode_id scene_id scene_dataset_config additional_obj_config_paths start_position start_rotation "
    "info goals start_room shortest_paths reference_path instruction trajectory_id".split()
)
_VLNCE_INSTRUCTION = dict.fromkeys(
    "instruction_text instruction_id language annotator_id edit_distance timed_instruction "
    "instruction_tokens split".split()
)


def _vlnce_kwargs(template: dict, record: dict, what: str) -> dict:
    unexpected = set(record) - set(template)
    if unexpected:
        raise TypeError(f"{what}.__init__() got an unexpected keyword argument {sorted(unexpected)[0]!r}")
    return {**template, **record}


def _vlnce_from_json(text: str, scenes_dir: str) -> list[dict]:
    import os

    doc = json.loads(text)
    word_list = doc["instruction_vocab"]["word_list"]
    assert isinstance(word_list, list)
    episodes = []
    for raw in doc["episodes"]:
        ep = _vlnce_kwargs(_VLNCE_EPISODE, raw, "VLNExtendedEpisode")
        ep["scene_id"] = os.path.join(scenes_dir, ep["scene_id"])
        ep["instruction"] = _vlnce_kwargs(_VLNCE_INSTRUCTION, ep["instruction"], "ExtendedInstructionData")
        goal = {"position": None, "radius": None}
        ep["goals"] = [_vlnce_kwargs(goal, g, "NavigationGoal") for g in ep["goals"]]
        episodes.append(ep)
    return episodes


def _assert_upright_on_the_floor(ep: dict) -> None:
    """A loaded record's start rotation is a yaw about Habitat's +Y and its start snaps onto the
    navigation graph of ``<scene_id>`` (the engine's scene folder)."""
    from image2sim.simulator.geometry.habitat import habitat_to_world
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.navigation.graph import NavGraph

    scene = Path(ep["scene_id"])
    x, y, z, w = ep["start_rotation"]
    assert abs(x) < 1e-9 and abs(z) < 1e-9 and math.isclose(y * y + w * w, 1.0)  # a yaw about +Y
    navmap, graph = NavMap.load(scene / "navmap.npz"), NavGraph.load(scene / "navgraph.npz")
    start = navmap.to_map(habitat_to_world(ep["start_position"]))
    node, offset = graph.snap(np.asarray(start)[None])
    assert node[0] >= 0 and offset[0] < 0.3  # on the navigable floor


def test_vlnce_reads_the_engine_files_and_the_agent_stands_upright_on_the_floor(full_run):
    out, _ = full_run
    with gzip.open(out / "train" / "train.json.gz", "rt") as fh:
        episodes = _vlnce_from_json(fh.read(), str(out / "scenes"))
    assert episodes
    for ep in episodes:
        scene = Path(ep["scene_id"])
        assert (scene / "navmap.npz").is_file()  # `<scenes dir>/<scene_id>` is the engine's scene folder
        _assert_upright_on_the_floor(ep)
        assert len(ep["instruction"]["instruction_tokens"]) == 200


# An independent replica of VLN-CE's RxR-CE loader (``RxRVLNCEDatasetV1``): for each role of the
# config, ``DATA_PATH.format(split=..., role=...)`` must exist and is read by ``from_json``, which
# passes every record to VLNExtendedEpisode(**record) (no vocabulary is read), the instruction to
# ExtendedInstructionData(**instruction) and sets its ``split``; episodes are then kept by
# ``instruction.language``. VLNExtendedEpisode requires reference_path and instruction, habitat's
# NavigationEpisode goals.
_RXR_DATA_PATH = "{root}/{split}/{split}_{role}.json.gz"


def _rxr_dataset(root: Path, split: str, roles: list[str], languages: list[str], scenes_dir: str) -> list:
    paths = [_RXR_DATA_PATH.format(root=root, split=split, role=role) for role in roles]
    assert set(roles) <= {"guide", "follower"}
    if not all(os.path.exists(p) for p in paths):  # check_config_paths_exist
        raise FileNotFoundError(f"RxR-CE: missing {[p for p in paths if not os.path.exists(p)]}")
    episodes = []
    for path in paths:
        with gzip.open(path, "rt") as fh:
            doc = json.loads(fh.read())
        for raw in doc["episodes"]:
            ep = _vlnce_kwargs(_VLNCE_EPISODE, raw, "VLNExtendedEpisode")
            for required in ("reference_path", "instruction", "goals"):
                assert ep[required] is not None, f"{required} must not be None"
            ep["scene_id"] = os.path.join(scenes_dir, ep["scene_id"])
            ep["instruction"] = _vlnce_kwargs(
                _VLNCE_INSTRUCTION, ep["instruction"], "ExtendedInstructionData"
            )
            assert ep["instruction"]["instruction_text"] is not None
            ep["instruction"]["split"] = split
            ep["goals"] = [
                _vlnce_kwargs({"position": None, "radius": None}, g, "NavigationGoal") for g in ep["goals"]
            ]
            episodes.append(ep)
    return [ep for ep in episodes if ep["instruction"]["language"] in set(languages)]


def test_rxr_ce_guide_files_are_read_by_the_rxr_loader_and_by_eval_nav(
    full_run, scenes_root, tmp_path, run_main
):
    """`data episodes --format rxr-ce` (here merging a finished run again) writes the guide role's
    files; RxR-CE's loader reads them unmodified, and so do our loader and `eval nav --dataset rxr-ce`."""
    from image2sim.eval.datasets import load_rxr_ce

    ref, _ = full_run
    out = tmp_path / "out"
    shutil.copytree(ref, out)
    args = ["data", "episodes", "--scenes", str(scenes_root), "--out", str(out), "--per-scene", "6"]
    args += ["--obs-height", "32", "--seed", "3", "--sampling", "min_path_length=1.0", "--workers", "1"]
    code, output = run_main([*args, "--format", "rxr-ce", "--language", "en-IN"])
    assert code == 0, output
    assert '"skipped": 2' in output  # nothing re-ran: only the merge wrote the new layout
    split = out / "train"
    assert (split / "train_guide_gt.json.gz").is_file() and (split / "train_guide_extras.json").is_file()
    r2r = _read(split / "train.json.gz")["episodes"]
    doc, gt = _read(split / "train_guide.json.gz"), _read(split / "train_guide_gt.json.gz")
    validate_episode_doc(doc, gt, fmt="rxr-ce")
    assert "instruction_vocab" not in doc

    episodes = _rxr_dataset(out, "train", ["guide"], ["en-IN"], str(out / "scenes"))
    assert [e["episode_id"] for e in episodes] == [e["episode_id"] for e in r2r]
    ids = [e["instruction"]["instruction_id"] for e in episodes]
    assert all(i.isdigit() for i in ids) and len(set(ids)) == len(ids)
    for ep, raw in zip(episodes, r2r, strict=True):
        ins = ep["instruction"]
        assert ins["language"] == "en-IN" and ins["annotator_id"] == "image2sim-template"
        assert ins["instruction_text"] == raw["instruction"]["instruction_text"] and ins["split"] == "train"
        assert ins["instruction_tokens"] is None and ep["start_rotation"] == raw["start_rotation"]
        _assert_upright_on_the_floor(ep)
    assert _rxr_dataset(out, "train", ["guide"], ["en-US"], str(out / "scenes")) == []
    with pytest.raises(FileNotFoundError, match="train_follower"):
        _rxr_dataset(out, "train", ["guide", "follower"], ["en-IN"], str(out / "scenes"))

    ds = load_rxr_ce(out, "train", languages=["en-IN"])
    assert len(ds) == len(episodes) and all(
        e.role == "guide" and e.gt_locations is not None for e in ds.episodes
    )
    assert [e.instruction.instruction_id for e in ds.episodes] == ids
    sub = tmp_path / "rxr.jsonl"
    args = ["eval", "nav", "--scenes", str(out / "scenes"), "--dataset", "rxr-ce", "--dataset-root", str(out)]
    args += ["--split", "train", "--language", "en-IN", "--agent", "oracle", "--out", str(tmp_path / "run")]
    args += [
        "--metrics",
        str(tmp_path / "nav.json"),
        "--submission",
        str(sub),
        "--submission-format",
        "rxr-ce",
    ]
    code, output = run_main(args)
    assert code == 0, output[-3000:]
    nav = json.loads((tmp_path / "nav.json").read_text())["agents"]["oracle"]
    assert nav["n_episodes"] == len(episodes) and nav["sr"] is not None
    lines = [json.loads(line) for line in sub.read_text().splitlines()]
    assert sorted(d["instruction_id"] for d in lines) == sorted(int(i) for i in ids)


def test_rxr_ce_schema_refuses_r2r_fields_and_bad_layouts(full_run):
    from image2sim.dataengine.episodes import check_episode_layout

    out, _ = full_run
    doc = _read(out / "train" / "train.json.gz")
    with pytest.raises(EpisodeSchemaError, match="no vocabulary"):
        validate_episode_doc(doc, fmt="rxr-ce")
    del doc["instruction_vocab"]
    with pytest.raises(EpisodeSchemaError, match="instruction_id"):
        validate_episode_doc(doc, fmt="rxr-ce")
    with pytest.raises(ValueError, match="episode format"):
        check_episode_layout("rxr")
    with pytest.raises(ValueError, match="language"):
        check_episode_layout("rxr-ce", "english")


def test_schema_validator_rejects_broken_documents(full_run):
    out, _ = full_run
    doc = _read(out / "train" / "train.json.gz")
    gt = _read(out / "train" / "train_gt.json.gz")
    bad = json.loads(json.dumps(doc))
    bad["episodes"][0]["start_rotation"] = [1.0, 1.0, 0.0, 0.0]
    with pytest.raises(EpisodeSchemaError, match="start_rotation"):
        validate_episode_doc(bad, gt)
    bad = json.loads(json.dumps(doc))
    bad["episodes"][0]["start_rotation"] = [0.6, 0.0, 0.0, 0.8]  # unit, but the agent lies on its side
    with pytest.raises(EpisodeSchemaError, match="upright"):
        validate_episode_doc(bad, gt)
    bad = json.loads(json.dumps(doc))
    bad["episodes"][0]["style"] = "r2r"  # VLN-CE's loader: TypeError: unexpected keyword argument 'style'
    with pytest.raises(EpisodeSchemaError, match="sidecar"):
        validate_episode_doc(bad, gt)
    bad = json.loads(json.dumps(doc))
    bad["episodes"][1]["episode_id"] = bad["episodes"][0]["episode_id"]
    with pytest.raises(EpisodeSchemaError, match="unique"):
        validate_episode_doc(bad)
    bad_gt = json.loads(json.dumps(gt))
    first = doc["episodes"][0]["episode_id"]
    bad_gt[first]["actions"] = bad_gt[first]["actions"][:-1] + [1]
    with pytest.raises(EpisodeSchemaError, match="STOP"):
        validate_episode_doc(doc, bad_gt)
    # Too short for the run's minimum path length (it would start inside the success radius).
    shortest = min(e["info"]["geodesic_distance"] for e in doc["episodes"])
    validate_episode_doc(doc, gt, min_geodesic=shortest)
    with pytest.raises(EpisodeSchemaError, match="below the minimum path length"):
        validate_episode_doc(doc, gt, min_geodesic=shortest + 0.5)


def test_navpolicy_dataset_reads_the_shards(full_run):
    from image2sim.navpolicy.data import NavShardDataset

    out, summary = full_run
    from image2sim.dataengine.distributed import read_shard_list

    stored = json.loads((out / "shards.json").read_text())["shards"]
    assert stored == ["scenes/scene_000/shard", "scenes/scene_001/shard"]  # relative to shards.json
    shards = read_shard_list(out)
    assert len(shards) == 2 and all((s / "manifest.json").is_file() for s in shards)
    ds = NavShardDataset(shards, max_observations=8, max_action_labels=16, jitter=False)
    assert len(ds) == summary["episodes"]
    gt = _read(out / "train" / "train_gt.json.gz")
    for i in range(len(ds)):
        traj = ds.readers[ds.index[i][0]][ds.index[i][1]]
        assert traj.actions == gt[traj.episode_id]["actions"]
        assert traj.frames.shape[1:] == (32, 32, 3)
        assert list(traj.frame_steps) == list(range(0, len(traj.actions), 2))  # the default stride
        sample = ds[i]
        assert sample.observations.shape[0] == len(sample.steps) <= 8
    # Frames differ along a trajectory with forward motion (no frozen rendering).
    traj = ds.readers[0][0]
    assert np.abs(traj.frames[0].astype(int) - traj.frames[-1].astype(int)).max() > 0


def test_approach_episodes_go_to_their_own_shard_and_leave_the_episodes_unchanged(
    scenes_root, full_run, tmp_path
):
    from image2sim.dataengine.distributed import read_shard_list
    from image2sim.navpolicy.data import ShardReader

    ref, ref_summary = full_run
    out = tmp_path / "approach"
    cfg = EngineConfig(**CFG, approach={"views": 30, "min_length": 0.5, "switch": True})
    summary = run_engine(scenes_root, out, cfg, executor="local", progress=False)
    # The regular episodes are those of the run without approach episodes (their own random stream).
    assert _read(out / "train" / "train.json.gz") == _read(ref / "train" / "train.json.gz")
    assert summary["episodes"] == ref_summary["episodes"]
    made = 0
    for name in ("scene_000", "scene_001"):
        done = json.loads((out / "scenes" / name / "done.json").read_text())
        made += done["approach_episodes"]
        if done["approach_episodes"]:
            reader = ShardReader(out / "scenes" / name / "approach")
            assert len(reader) == done["approach_episodes"]
            for i in range(len(reader)):
                t = reader[i]
                assert t.episode_id.startswith(f"{name}-a") and t.actions[-1] == int(Action.STOP)
                assert len(t.frames) == len(range(0, len(t.actions), cfg.frame_stride))
    assert made > 0, "no approach episode in either tiny house"
    listed = [p.name for p in read_shard_list(out)]
    assert listed.count("approach") == sum(
        (out / "scenes" / n / "approach" / "manifest.json").is_file() for n in ("scene_000", "scene_001")
    )
    ids = {e["episode_id"] for e in _read(out / "train" / "train.json.gz")["episodes"]}
    assert not any("-a" in i.split("scene_00")[1] for i in ids)


def test_interrupted_run_resumes_without_loss_or_duplicates(scenes_root, full_run, tmp_path, monkeypatch):
    import image2sim.dataengine.distributed as dist

    ref_out, _ = full_run
    out = tmp_path / "out"
    cfg = EngineConfig(**CFG)
    # First attempt: the second scene "crashes" (e.g. the worker was killed) after the first finished.
    real = dist.process_scene
    calls = []

    def flaky(scene, out_dir, config, **kw):
        calls.append(Path(scene).name)
        if Path(scene).name == "scene_001":
            raise KeyboardInterrupt("killed")
        return real(scene, out_dir, config, **kw)

    monkeypatch.setattr(dist, "process_scene", flaky)
    with pytest.raises(KeyboardInterrupt):  # in-process (workers=1): the patch reaches the scene task
        run_engine(scenes_root, out, cfg, executor="local", workers=1, progress=False)
    assert (out / "scenes" / "scene_000" / "done.json").is_file()
    assert not (out / "scenes" / "scene_001" / "done.json").is_file()
    # Restart with the same arguments: only the unfinished scene runs.
    calls.clear()
    monkeypatch.setattr(
        dist, "process_scene", lambda s, o, c, **kw: (calls.append(Path(s).name), real(s, o, c, **kw))[1]
    )
    summary = run_engine(scenes_root, out, cfg, executor="local", progress=False)
    assert calls == ["scene_001"] and summary["skipped"] == 1
    got = _read(out / "train" / "train.json.gz")["episodes"]
    ref = _read(ref_out / "train" / "train.json.gz")["episodes"]
    ids = [e["episode_id"] for e in got]
    assert len(ids) == len(set(ids))  # no duplicates
    assert ids == [e["episode_id"] for e in ref]  # nothing lost
    assert [e["instruction"]["instruction_text"] for e in got] == [
        e["instruction"]["instruction_text"] for e in ref
    ]
    # A third run is a no-op and merging again changes nothing.
    before = (out / "train" / "train.json.gz").read_bytes()
    calls.clear()
    run_engine(scenes_root, out, cfg, executor="local", progress=False)
    assert calls == [] and (out / "train" / "train.json.gz").read_bytes() == before


@pytest.mark.slow  # test_detectors keeps a fast check of the content-keyed cache
def test_restart_from_cached_scene_assets_reproduces_the_uninterrupted_run(scenes_root, full_run, tmp_path):
    """A job killed after a scene's navigation map, graph and objects were cached, but before its
    episodes, restarts from those files; its episodes must equal the uninterrupted run's (the
    SIGKILL test hits this state only sometimes, depending on when the kill lands)."""
    ref_out, _ = full_run
    out = tmp_path / "out"
    cached = out / "scenes" / "scene_001"
    cached.mkdir(parents=True)
    for name in ("navmap.npz", "navgraph.npz", "objects.json"):
        shutil.copy2(ref_out / "scenes" / "scene_001" / name, cached / name)
    run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", progress=False)
    got = _read(out / "train" / "train.json.gz")["episodes"]
    assert got == _read(ref_out / "train" / "train.json.gz")["episodes"]


def test_scene_failure_is_reported_and_other_scenes_finish(scenes_root, tmp_path):
    root = tmp_path / "scenes"
    shutil.copytree(scenes_root, root)
    (root / "scene_001" / "gt" / "categories.json").unlink()  # the gt detector cannot run here
    summary = run_engine(root, tmp_path / "out", EngineConfig(**CFG), executor="local", progress=False)
    assert list(summary["failed"]) == ["scene_001"]
    assert "categories.json" in summary["failed"]["scene_001"]
    assert summary["scenes_done"] == 1 and summary["episodes"] > 0
    assert json.loads((tmp_path / "out" / "failures.json").read_text()).keys() == {"scene_001"}


def test_restart_with_other_arguments_is_refused(scenes_root, full_run):
    from image2sim.dataengine.distributed import RunError

    out, _ = full_run
    with pytest.raises(RunError, match="per_scene"):
        run_engine(
            scenes_root, out, EngineConfig(**{**CFG, "per_scene": 7}), executor="local", progress=False
        )
    merge_outputs(out, ["scene_000", "scene_001"], "train")  # still consistent after the refusal


def test_the_gaussian_config_sets_the_density_of_the_simulated_scenes(scenes_root, full_run, tmp_path):
    """``gaussians`` (``data episodes --gaussian-config``) is the config of the identity scenes the
    engine builds: a coarser fusion gives fewer Gaussians; the default is the tiny preset, which is
    what the run above built; a run restarted with another one is refused."""
    import dataclasses

    from image2sim.dataengine.distributed import RunError
    from image2sim.dataengine.scene_assets import resolve_scene, scene_render_fn
    from image2sim.simulator.gaussians import GaussianScene, tiny
    from image2sim.simulator.gaussians.config import config_to_dict

    base = tiny()
    coarse = config_to_dict(
        dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, footprint_factor=4.0))
    )
    inputs = resolve_scene(scenes_root / "scene_000")
    counts = {}
    for name, gaussians in (("default", {}), ("coarse", coarse)):
        fn, mode = scene_render_fn(inputs, tmp_path / name, "gaussians", gaussians=gaussians)
        assert fn is not None and mode == "gaussians"
        counts[name] = len(GaussianScene.load(tmp_path / name / "gaussians").gaussians.means)
    out, _ = full_run
    built = len(GaussianScene.load(out / "scenes" / "scene_000" / "gaussians").gaussians.means)
    assert built == counts["default"]
    assert 0 < counts["coarse"] < counts["default"] / 2
    with pytest.raises(RunError, match="gaussians"):
        run_engine(scenes_root, out, EngineConfig(**CFG, gaussians=coarse), executor="local", progress=False)


def test_a_run_written_before_a_config_field_existed_resumes(scenes_root, full_run):
    """A run manifest without a field added since (here ``gaussians``) reads it as the default, which
    is what that run did: resuming is not refused."""
    from image2sim.dataengine.distributed import RUN_FILE

    out, _ = full_run
    path = out / RUN_FILE
    saved = path.read_text()
    doc = json.loads(saved)
    doc["config"].pop("gaussians")
    try:
        path.write_text(json.dumps(doc))
        summary = run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", progress=False)
        assert summary["scenes_done"] == 2 and not summary["failed"]
    finally:
        path.write_text(saved)


def test_the_render_device_is_validated_and_a_run_may_resume_on_another(scenes_root, full_run):
    """``device`` says where frames render, not what is written: a finished run resumed with another
    device is not refused (it skips its finished scenes); a device torch does not know is an error."""
    for bad in ("gpu0", "tpu", "cuda:x"):
        with pytest.raises(ValueError, match="EngineConfig.device"):
            EngineConfig(**CFG, device=bad)
    EngineConfig(**CFG, device="cuda:1")  # valid on any machine; rendering on it needs CUDA
    out, _ = full_run
    cuda = EngineConfig(**CFG, device="cuda")
    summary = run_engine(scenes_root, out, cuda, executor="local", progress=False)
    assert summary["scenes_done"] == 2 and not summary["failed"]


def test_a_second_run_on_the_same_folder_is_refused_while_one_runs(scenes_root, tmp_path):
    """Two runs on one --out used to interleave (a race left seed-0 and seed-1 scenes in one file)."""
    import fcntl

    from image2sim.dataengine.distributed import RunError

    out = tmp_path / "out"
    out.mkdir()
    with open(out / ".run.lock", "a") as held:  # another run holds the folder
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(RunError, match="another run is writing to this folder"):
            run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", progress=False)
        assert not (out / "run.json").exists()  # nothing written by the refused run
    summary = run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", workers=1, progress=False)
    assert summary["scenes_done"] == 2  # released: the next run proceeds


def test_local_process_pool_matches_one_process(scenes_root, full_run, tmp_path):
    """The default executor runs scenes in 2 spawned processes; the files equal a 1-process run."""
    ref_out, ref = full_run  # executor local, workers 2 (the default)
    assert len({t["pid"] for t in ref["tasks"].values()}) == 2  # two worker processes did the scenes
    out = tmp_path / "one"
    run_engine(scenes_root, out, EngineConfig(**CFG), executor="local", workers=1, progress=False)
    for name in ("train.json.gz", "train_gt.json.gz"):
        assert _read(out / "train" / name) == _read(ref_out / "train" / name)


@pytest.mark.slow
def test_sigkill_and_restart_loses_and_duplicates_nothing(scenes_root, full_run, tmp_path):
    """A real kill: SIGKILL the CLI process once the first scene is done, then rerun the same command."""
    import os
    import signal
    import subprocess
    import sys
    import time

    ref_out, _ = full_run
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-c",
        "from image2sim.simulator.cli import main; main()",
        "data",
        "episodes",
        "--scenes",
        str(scenes_root),
        "--out",
        str(out),
        "--per-scene",
        str(CFG["per_scene"]),
        "--obs-height",
        str(CFG["obs_height"]),
        "--seed",
        str(CFG["seed"]),
        "--executor",
        "local",
        "--workers",
        "1",  # one scene after the other: the kill lands between them
        "--sampling",
        f"min_path_length={SHORT['min_path_length']}",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not (out / "scenes" / "scene_000" / "done.json").is_file():
            assert proc.poll() is None, "the run ended before it could be interrupted"
            assert time.monotonic() < deadline
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not (out / "train" / "train.json.gz").is_file()  # killed before the merge
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    got = _read(out / "train" / "train.json.gz")["episodes"]
    ref = _read(ref_out / "train" / "train.json.gz")["episodes"]
    assert [e["episode_id"] for e in got] == [e["episode_id"] for e in ref]
    assert got == ref
    assert not list((out / "scenes").glob("*/.shard.*.tmp"))


@pytest.mark.slow
def test_ray_executor_matches_local(scenes_root, full_run, tmp_path):
    out_ref, _ = full_run
    summary = run_engine(
        scenes_root, tmp_path / "ray", EngineConfig(**CFG), executor="ray", workers=2, progress=False
    )
    assert summary["failed"] == {}
    a = _read(out_ref / "train" / "train.json.gz")["episodes"]
    b = _read(tmp_path / "ray" / "train" / "train.json.gz")["episodes"]
    assert a == b
    # Each task ran in a worker pinned to one thread (no oversubscription), and reports its timings.
    tasks = summary["tasks"]
    assert sorted(tasks) == ["scene_000", "scene_001"]
    for t in tasks.values():
        assert t["torch_threads"] == 1 and t["omp_num_threads"] == "1"
        assert 0 < t["cpu_s"] and 0 < t["wall_s"] and t["pid"] != os.getpid()


def test_shard_frames_are_labelled_goal_in_view(full_run):
    """Each stored frame of an object-goal episode says whether its goal object is in view; the
    labels are those of the frames' own poses (replayed here), not of neighbouring steps."""
    from image2sim.dataengine.visibility import Occupancy, VisibilityConfig, goal_in_view
    from image2sim.simulator.navigation import NavMap
    from image2sim.simulator.sim import NeuralSimulator

    out, _ = full_run
    extras = json.loads((out / "train" / "train_extras.json").read_text())
    cfg = EngineConfig(**CFG)
    view = VisibilityConfig(max_distance=cfg.goal_view_distance, hfov_deg=90.0, vfov_deg=90.0)
    labels = []
    for scene in ("scene_000", "scene_001"):
        navmap = NavMap.load(out / "scenes" / scene / "navmap.npz")
        occ = Occupancy.from_navmap(navmap)
        sim = NeuralSimulator(navmap)
        eye = np.array([0.0, 0.0, navmap.embodiment.eye_height])
        for line in (out / "scenes" / scene / "shard" / "trajectories.jsonl").read_text().splitlines():
            rec = json.loads(line)
            seen = rec["extra"]["goal_in_view"]
            assert len(seen) == len(rec["frame_steps"]) and set(seen) <= {0, 1}
            # the goal's category, which the policy's wrong-goal end samples swap instructions by
            assert rec["extra"]["goal_category"] == extras[rec["episode_id"]]["goal_object"]["category"]
            start = navmap.to_map(np.asarray(rec["extra"]["start_world"]))
            sim.reset(start[None], np.array([rec["extra"]["heading_world"]]), observe=False)
            pos, head = [start], [rec["extra"]["heading_world"]]
            for a in rec["actions"][:-1]:
                _, info = sim.step([a], observe=False)
                pos.append(info["position"][0])
                head.append(float(info["heading"][0]))
            steps = rec["frame_steps"]
            goal = navmap.to_map(np.asarray(extras[rec["episode_id"]]["goal_object"]["position"]))
            want = goal_in_view(goal, np.asarray(pos)[steps] + eye, np.asarray(head)[steps], occ, view)
            assert seen == [int(v) for v in want], rec["episode_id"]
            labels += seen
    assert 0 in labels and 1 in labels
