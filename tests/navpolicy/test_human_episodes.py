"""Human annotations into the simulator: R2R-CE-format episodes over a captured (procedural) house
become an Image2Nav training shard, and behaviour cloning mixes shards by sample ratio."""

from __future__ import annotations

import gzip
import json
import math
import re

import numpy as np
import pytest
from image2sim.simulator.conventions import Action

from tests.eval.test_datasets import VOCAB, _r2r_episode, _write

OBS = {"height": 16, "width": 16}
UNREACHABLE_ID = 99


# ------------------------------------------------------------------------------------ the fixture


def _r2r_record(sim, eid: int, path_map: np.ndarray, heading: float, text: str) -> dict:
    """A published-layout R2R-CE episode (Habitat frame, Y-up, [x, y, z, w]) whose reference path is
    ``path_map`` (map frame) taken to our world frame and then to Habitat's."""
    from image2sim.simulator.geometry.habitat import habitat_rotation_for_heading, world_to_habitat

    hab = world_to_habitat(sim.navmap.to_world(np.asarray(path_map, float)))
    return _r2r_episode(
        eid,
        scene_id="mp3d/scene_000/scene_000.glb",
        start_position=hab[0].tolist(),
        start_rotation=habitat_rotation_for_heading(heading).tolist(),
        goals=[{"position": hab[-1].tolist(), "radius": 3.0}],
        reference_path=hab.tolist(),
        instruction={"instruction_text": text, "instruction_tokens": [5, 3, 7, 6]},
        info={"geodesic_distance": float(np.linalg.norm(np.diff(path_map, axis=0), axis=1).sum())},
    )


@pytest.fixture(scope="module")
def house(tmp_path_factory):
    """A tiny procedural capture and an R2R-CE split over it: three episodes whose reference paths
    are planner shortest paths between graph nodes, and one whose path leads 30 m out of the house."""
    from image2sim.dataengine.procedural import preset, synthesize
    from image2sim.navpolicy.rollout_scenes import scene_simulator

    root = tmp_path_factory.mktemp("human")
    synthesize(preset("tiny"), root / "captures", scenes=1, seed=0, progress=False)
    sim = scene_simulator(root / "captures" / "scene_000", "exact")
    nodes = np.asarray(sim.graph.nodes)
    pts = nodes[sim.graph.components == np.bincount(sim.graph.components).argmax()]
    rng = np.random.default_rng(0)
    records, texts = [], {}
    while len(records) < 3:
        a, b = pts[rng.integers(len(pts), size=2)]
        path = sim.planner.shortest_path(a, b)
        if not (path.reachable and 1.5 < path.length < 6.0):
            continue
        eid = len(records) + 1
        texts[str(eid)] = f"Walk out of the room, turn at the sofa and stop by door {eid}."
        records.append(
            _r2r_record(sim, eid, path.waypoints, float(rng.uniform(-np.pi, np.pi)), texts[str(eid)])
        )
    far = np.vstack((pts[0], pts[0] + np.array([30.0, 0.0, 0.0])))
    records.append(_r2r_record(sim, UNREACHABLE_ID, far, 0.0, "Walk through the wall into the garden."))
    data = root / "r2r"
    _write(data / "val_seen" / "val_seen.json.gz", {"episodes": records, "instruction_vocab": VOCAB})
    return root / "captures", data, texts


def _convert(house, out, **kw):
    from image2sim.eval.datasets import load_r2r_ce
    from image2sim.navpolicy.config import ObservationConfig
    from image2sim.navpolicy.human import shard_from_episodes

    captures, data, _ = house
    return shard_from_episodes(
        load_r2r_ce(data, "val_seen"), captures, out, "exact", observation=ObservationConfig(**OBS), **kw
    )


# --------------------------------------------------------------------------------- episodes -> shard


def test_r2r_episodes_become_a_shard_that_replays_to_the_reference_end(house, tmp_path):
    from image2sim.dataengine.rollout import replay
    from image2sim.eval.datasets import load_r2r_ce
    from image2sim.navpolicy.data import ShardReader
    from image2sim.navpolicy.rollout_scenes import scene_simulator, tasks_from_episodes

    captures, data, texts = house
    summary = _convert(house, tmp_path / "human", progress=False)
    assert summary["episodes"] == 4 and summary["written"] == 3
    # The unreachable episode is skipped and reported, with the planner's reason.
    assert summary["skipped"] == {"unreachable": 1}
    (skipped,) = summary["skipped_episodes"]
    assert skipped["episode_id"] == str(UNREACHABLE_ID) and skipped["reason"] == "unreachable"
    assert "off the navigable map" in skipped["detail"]
    assert summary["scenes"] == {"scene_000": {"written": 3, "skipped": 1}}
    assert summary["dataset"] == "r2r-ce" and summary["source"] == "exact"
    assert (tmp_path / "human" / "summary.json").is_file()
    assert not list(tmp_path.glob(".human.*.tmp"))  # the temp folder was renamed into place

    reader = ShardReader(tmp_path / "human")
    assert len(reader) == 3 and reader.manifest["observation"]["height"] == 16
    sim = scene_simulator(captures / "scene_000", "exact")
    episodes = {e.episode_id: e for e in load_r2r_ce(data, "val_seen").episodes}
    for i in range(len(reader)):
        traj = reader[i]
        ep = episodes[traj.episode_id]
        assert traj.instruction == texts[traj.episode_id] == ep.instruction.text
        assert traj.scene_id == "scene_000"
        assert traj.actions[-1] == int(Action.STOP) and int(Action.STOP) not in traj.actions[:-1]
        assert traj.frame_steps == list(range(0, len(traj.actions), 2))
        assert traj.frames.shape == (len(traj.frame_steps), 16, 16, 3)
        assert traj.extra["source"] == "exact" and traj.extra["dataset"] == "r2r-ce"
        assert traj.extra["route"] == "reference_path"
        (task,) = tasks_from_episodes([ep], sim, "scene_000")
        pos, _, _ = replay(sim, task.start, task.heading, traj.actions)
        end = np.linalg.norm(pos[-1, :2] - task.reference_path[-1, :2])
        assert end < 0.5
        assert traj.extra["end_distance_m"] == pytest.approx(end, abs=1e-3)
        # Frame 0 is the start view: the exact renderer at the episode's start pose.
        assert traj.frames[0].std() > 0


def test_a_step_cap_skips_and_counts_instead_of_writing_a_truncated_episode(house, tmp_path):
    from image2sim.navpolicy.data import ShardReader

    _convert(house, tmp_path / "full", progress=False)
    full = ShardReader(tmp_path / "full")
    lengths = sorted(len(full[i].actions) for i in range(len(full)))
    assert lengths[0] < lengths[-1]
    cap = lengths[-1] - 1  # the longest episode no longer fits
    summary = _convert(house, tmp_path / "capped", max_steps=cap, progress=False)
    assert summary["skipped"] == {"max_steps": lengths.count(lengths[-1]), "unreachable": 1}
    assert summary["written"] == sum(n <= cap for n in lengths)
    capped = [e for e in summary["skipped_episodes"] if e["reason"] == "max_steps"]
    assert all(f"after {cap} steps" in e["detail"] for e in capped)
    with pytest.raises(ValueError, match="nothing written"):
        _convert(house, tmp_path / "none", max_steps=1, progress=False)
    assert not (tmp_path / "none").exists() and not list(tmp_path.glob(".none.*.tmp"))


def test_conversion_refuses_missing_scenes_and_existing_output(house, tmp_path):
    from image2sim.eval.datasets import load_r2r_ce
    from image2sim.navpolicy.human import shard_from_episodes

    _, data, _ = house
    eps = load_r2r_ce(data, "val_seen")
    with pytest.raises(FileNotFoundError, match="scene_000"):
        shard_from_episodes(eps, tmp_path, tmp_path / "out", "exact", progress=False)
    with pytest.raises(ValueError, match="renderer"):
        shard_from_episodes(eps, tmp_path, tmp_path / "out", "neural", progress=False)
    (tmp_path / "taken").mkdir()
    with pytest.raises(FileExistsError, match="taken"):
        _convert(house, tmp_path / "taken", progress=False)


# ------------------------------------------------------------------------------------------- the CLI


def _said(res) -> str:
    return re.sub(r"[│╭╮╰╯─\s]+", " ", res.output)  # typer's error box wraps long lines


def test_cli_from_episodes_with_the_exact_source(house, tmp_path):
    from image2sim.navpolicy.cli import app
    from image2sim.navpolicy.data import ShardReader
    from typer.testing import CliRunner

    captures, data, texts = house
    cfg = tmp_path / "obs.yaml"
    cfg.write_text("base: tiny\nobservation:\n  height: 16\n  width: 16\n")
    base = ["from-episodes", "--sim-scenes", str(captures), "--config", str(cfg)]
    r2r = ["--dataset", "r2r-ce", "--dataset-root", str(data), "--split", "val_seen"]
    res = CliRunner().invoke(app, [*base, *r2r, "--source", "exact", "--out", str(tmp_path / "shard")])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output[res.output.index("{") :])
    assert summary["written"] == 3 and summary["skipped"] == {"unreachable": 1}
    reader = ShardReader(tmp_path / "shard")
    assert sorted(reader[i].instruction for i in range(3)) == sorted(texts.values())
    assert reader[0].frames.shape[1:] == (16, 16, 3)

    # --episodes FILE --gt FILE: the dense ground-truth route is followed; RxR-CE's layout by role.
    with gzip.open(data / "val_seen" / "val_seen.json.gz", "rt") as fh:
        doc = json.load(fh)
    gt = {str(e["episode_id"]): {"locations": e["reference_path"]} for e in doc["episodes"]}
    _write(tmp_path / "gt.json.gz", gt)
    episodes = [
        "--episodes",
        str(data / "val_seen" / "val_seen.json.gz"),
        "--gt",
        str(tmp_path / "gt.json.gz"),
    ]
    res = CliRunner().invoke(app, [*base, *episodes, "--source", "exact", "--out", str(tmp_path / "dense")])
    assert res.exit_code == 0, res.output
    dense = ShardReader(tmp_path / "dense")
    assert {dense[i].extra["route"] for i in range(len(dense))} == {"gt_locations"}
    assert dense[0].extra["dataset"] == "val_seen.json.gz"
    for e in doc["episodes"]:
        e["instruction"]["language"] = "en-US"
    _write(tmp_path / "rxr" / "val_seen" / "val_seen_guide.json.gz", {"episodes": doc["episodes"]})
    rxr = ["--dataset", "rxr-ce", "--dataset-root", str(tmp_path / "rxr"), "--split", "val_seen"]
    res = CliRunner().invoke(
        app, [*base, *rxr, "--rxr-role", "guide", "--source", "exact", "--out", str(tmp_path / "rxr_shard")]
    )
    assert res.exit_code == 0, res.output
    rxr_shard = ShardReader(tmp_path / "rxr_shard")
    assert rxr_shard[0].extra["role"] == "guide" and rxr_shard[0].extra["dataset"] == "rxr-ce"
    assert rxr_shard[0].extra["language"] == "en-US"

    # Errors: exit 2 with a message naming the field or the file.
    res = CliRunner().invoke(app, [*base, *r2r, "--source", "exact", "--out", str(tmp_path / "shard")])
    assert res.exit_code == 2 and "--overwrite" in _said(res)
    res = CliRunner().invoke(app, [*base, *r2r, "--out", str(tmp_path / "n")])  # source neural by default
    assert res.exit_code == 2 and "--renderer" in _said(res)
    empty = tmp_path / "no_scenes"
    empty.mkdir()
    res = CliRunner().invoke(
        app,
        [
            "from-episodes",
            "--sim-scenes",
            str(empty),
            *r2r,
            "--source",
            "exact",
            "--out",
            str(tmp_path / "m"),
        ],
    )
    assert res.exit_code == 2 and "scene_000" in _said(res)
    novocab = tmp_path / "novocab" / "val_seen" / "val_seen.json.gz"
    _write(novocab, {"episodes": [_r2r_episode(1)]})
    res = CliRunner().invoke(
        app,
        [*base, "--dataset", "r2r-ce", "--dataset-root", str(tmp_path / "novocab"), "--split", "val_seen"]
        + ["--source", "exact", "--out", str(tmp_path / "v")],
    )
    assert res.exit_code == 2 and "instruction_vocab" in _said(res) and "val_seen.json.gz" in _said(res)
    bad = tmp_path / "bad.json.gz"
    _write(bad, {"episodes": [_r2r_episode(1, start_rotation=[0.0, 0.0])]})
    res = CliRunner().invoke(
        app, [*base, "--episodes", str(bad), "--source", "exact", "--out", str(tmp_path / "b")]
    )
    assert res.exit_code == 2 and "start_rotation" in _said(res) and "bad.json.gz" in _said(res)
    assert not any((tmp_path / name).exists() for name in ("n", "m", "v", "b"))


# ------------------------------------------------------------------------------- mixing by ratios


@pytest.fixture
def two_shards(tmp_path):
    """A large shard (40 trajectories) and a small one (4)."""
    from image2sim.navpolicy.data import synthetic_trajectories, write_shard

    big = write_shard(tmp_path / "big", synthetic_trajectories(40, 3, 6, 4, 4, seed=1))
    small = write_shard(tmp_path / "small", synthetic_trajectories(4, 3, 6, 4, 4, seed=2))
    return big, small


def test_shard_weights_draw_the_requested_ratio_whatever_the_sizes(two_shards):
    from image2sim.navpolicy.data import NavShardDataset
    from image2sim.navpolicy.train import MixtureOrder, PositionDataset

    ds = NavShardDataset(list(two_shards))
    n = 10_000  # spans three blocks of the order
    assert n > 2 * MixtureOrder.BLOCK
    plain = [PositionDataset(ds, 0).locate(p)[1] >= 40 for p in range(4400)]
    assert np.mean(plain) == pytest.approx(4 / 44, abs=0.01)  # no weights: by size
    weighted = PositionDataset(ds, 0, weights=[1.0, 3.0])
    located = [weighted.locate(p) for p in range(n)]
    small = np.array([i >= 40 for _, i in located])
    assert small.mean() == pytest.approx(0.75, abs=0.02)  # 1 : 3 as asked, not 40 : 4
    # Inside a shard every trajectory is drawn once before any is drawn twice.
    first_small = [i for _, i in located if i >= 40][:4]
    first_big = [i for _, i in located if i < 40][:40]
    assert sorted(first_small) == [40, 41, 42, 43] and sorted(first_big) == list(range(40))
    # A pure function of (seed, position): a fresh order (a resumed run) locates any position alike.
    fresh = PositionDataset(ds, 0, weights=[1.0, 3.0])
    for p in (9_999, 4_096, 4_095, 17, 8_500, 0):
        assert fresh.locate(p) == located[p]
    other_seed = PositionDataset(ds, 1, weights=[1.0, 3.0])
    assert [other_seed.locate(p) for p in range(50)] != located[:50]
    # A zero weight never draws its shard.
    assert all(PositionDataset(ds, 0, weights=[1.0, 0.0]).locate(p)[1] < 40 for p in range(500))


def test_empty_shard_weights_keep_todays_order(two_shards):
    from image2sim.navpolicy.data import NavShardDataset
    from image2sim.navpolicy.train import PositionDataset, epoch_permutation

    ds = NavShardDataset(list(two_shards))
    for weights in (None, []):
        order = PositionDataset(ds, 3, weights=weights)
        for p in range(0, 200, 7):
            epoch = p // 44
            assert order.locate(p) == (epoch, int(epoch_permutation(44, 3, epoch)[p % 44]))


def test_bad_shard_weights_raise_naming_the_field(two_shards):
    from image2sim.navpolicy.config import ConfigError, load_config
    from image2sim.navpolicy.data import NavShardDataset
    from image2sim.navpolicy.train import PositionDataset

    shards = [str(s) for s in two_shards]
    for weights in ([1.0], [1.0, 2.0, 3.0], [1.0, -1.0], [0.0, 0.0], [math.inf, 1.0], [math.nan, 1.0]):
        with pytest.raises(ConfigError, match=r"data\.shard_weights"):
            load_config("tiny", {"data": {"shards": shards, "shard_weights": weights}})
    assert load_config("tiny", {"data": {"shards": shards, "shard_weights": [3, 1]}}).data.shard_weights == [
        3.0,
        1.0,
    ]
    with pytest.raises(ValueError, match=r"data\.shard_weights"):
        PositionDataset(NavShardDataset(shards), 0, weights=[1.0])


def test_bc_draws_by_shard_weights_and_the_cli_sets_them(two_shards, tmp_path):
    """`nav train --shard A --shard-weight 1 --shard B --shard-weight 3` trains on the weighted order
    (the episodes of every batch are those MixtureOrder locates), and a count mismatch is refused."""
    import torch
    from image2sim.navpolicy.cli import app
    from image2sim.navpolicy.data import NavShardDataset
    from image2sim.navpolicy.train import PositionDataset
    from image2sim.simulator.config import read_mapping
    from typer.testing import CliRunner

    big, small = two_shards
    cfg = tmp_path / "small.yaml"
    cfg.write_text(
        "base: tiny\ndata:\n  max_observations: 2\n  max_action_labels: 4\ntrain:\n  batch_size: 2\n"
    )
    shards = ["--shard", str(big), "--shard", str(small)]
    res = CliRunner().invoke(app, ["train", *shards, "--shard-weight", "1", "--config", str(cfg)])
    assert res.exit_code == 2 and "data.shard_weights" in _said(res)
    out = tmp_path / "run"
    args = ["train", *shards, "--shard-weight", "1", "--shard-weight", "3", "--config", str(cfg)]
    res = CliRunner().invoke(app, [*args, "--max-steps", "3", "--out", str(out), "--threads", "1"])
    assert res.exit_code == 0, res.output
    assert read_mapping(out / "config.yaml")["data"]["shard_weights"] == [1.0, 3.0]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    seen = [e for batch in ckpt["image2nav_history"]["seen"] for e in batch]
    ds = NavShardDataset([big, small])

    def episodes(order) -> list[str]:
        out = []
        for p in range(6):  # 3 steps x batch 2
            r, j = ds.index[order.locate(p)[1]]
            out.append(ds.readers[r][j].episode_id)
        return out

    assert seen == episodes(PositionDataset(ds, 0, weights=[1.0, 3.0]))
    assert seen != episodes(PositionDataset(ds, 0))  # not the unweighted order
    res = CliRunner().invoke(app, ["train", "--stage", "dagger", *args[1:], "--out", str(tmp_path / "d")])
    assert res.exit_code == 2 and "behaviour cloning" in _said(res)


def test_cli_set_overrides_reach_the_saved_config_and_bad_ones_are_usage_errors(two_shards, tmp_path):
    """`nav train --set KEY=VALUE` overrides any config field (checked like the YAML's keys)."""
    from image2sim.navpolicy.cli import app
    from image2sim.simulator.config import read_mapping
    from typer.testing import CliRunner

    big, _ = two_shards
    cfg = tmp_path / "small.yaml"
    cfg.write_text(
        "base: tiny\ndata:\n  max_observations: 2\n  max_action_labels: 4\ntrain:\n  batch_size: 2\n"
    )
    args = ["train", "--shard", str(big), "--config", str(cfg), "--threads", "1"]
    out = tmp_path / "run"
    sets = ["--set", "train.seed=3", "--set", "data.shuffle_instructions=true", "--set", "train.batch_size=1"]
    res = CliRunner().invoke(app, [*args, *sets, "--max-steps", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    saved = read_mapping(out / "config.yaml")
    assert (
        saved["train"]["seed"] == 3 and saved["train"]["batch_size"] == 1 and saved["train"]["max_steps"] == 1
    )
    assert saved["data"]["shuffle_instructions"] is True and saved["data"]["max_observations"] == 2
    for bad, said in (
        ("train.seed", "KEY=VALUE"),
        ("train.nope=1", "train.nope"),
        ("train.seed=x", "train.seed"),
    ):
        res = CliRunner().invoke(app, [*args, "--set", bad, "--out", str(tmp_path / "bad")])
        assert res.exit_code == 2 and said in _said(res), (bad, _said(res))
    assert not (tmp_path / "bad").exists()
