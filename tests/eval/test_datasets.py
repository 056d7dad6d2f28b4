"""Episode loaders on fixtures in the published VLN-CE schemas, malformed files, frame conversion."""

from __future__ import annotations

import copy
import gzip
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from image2sim.eval.datasets import (
    EpisodeFileError,
    load_image2sim_episodes,
    load_r2r_ce,
    load_reverie_ce,
    load_rxr_ce,
)
from image2sim.simulator.geometry.habitat import (
    HABITAT_TO_WORLD,
    habitat_heading,
    habitat_quaternion_to_world,
    habitat_rotation_for_heading,
    habitat_to_world,
    world_to_habitat,
)
from image2sim.simulator.geometry.se3 import quat_to_matrix


def _yaw_xyzw(theta: float) -> list[float]:
    """Habitat rotation about +Y by theta as [x, y, z, w]."""
    return [0.0, math.sin(theta / 2), 0.0, math.cos(theta / 2)]


def _write(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wt", encoding="utf-8") as f:
        json.dump(obj, f)


def _r2r_episode(eid: int, **over: Any) -> dict[str, Any]:
    ep = {
        "episode_id": eid,
        "trajectory_id": 4,
        "scene_id": "mp3d/7y3sRwLe3Va/7y3sRwLe3Va.glb",
        "start_position": [1.0, 0.17, -2.0],
        "start_rotation": _yaw_xyzw(0.5),
        "info": {"geodesic_distance": 6.4},
        "goals": [{"position": [4.0, 0.17, -6.0], "radius": 3.0}],
        "instruction": {
            "instruction_text": "Walk past the sofa and stop.",
            "instruction_tokens": [5, 9, 2, 0],
        },
        "reference_path": [[1.0, 0.17, -2.0], [2.5, 0.17, -4.0], [4.0, 0.17, -6.0]],
    }
    ep.update(over)
    return ep


VOCAB = {
    "word_list": ["<PAD>", "<UNK>", "and", "the", "past", "walk", "stop", "sofa", ".", "walk"],
    "word2idx_dict": {},
    "itos": [],
    "stoi": {},
    "num_vocab": 10,
    "UNK_INDEX": 1,
    "PAD_INDEX": 0,
}


def _gt(eids: list[int]) -> dict[str, Any]:
    return {
        str(e): {
            "locations": [[1.0, 0.17, -2.0], [1.0, 0.17, -2.25], [1.25, 0.17, -2.5]],
            "forward_steps": 2,
            "actions": [1, 3, 1, 0],
        }
        for e in eids
    }


@pytest.fixture
def r2r_root(tmp_path: Path) -> Path:
    root = tmp_path / "R2R_VLNCE_v1-3_preprocessed"
    _write(
        root / "val_seen" / "val_seen.json.gz",
        {"episodes": [_r2r_episode(1), _r2r_episode(2)], "instruction_vocab": VOCAB},
    )
    _write(root / "val_seen" / "val_seen_gt.json.gz", _gt([1, 2]))
    _write(root / "test" / "test.json.gz", {"episodes": [_r2r_episode(7)], "instruction_vocab": VOCAB})
    return root


# ---------------------------------------------------------------------------------------------- frames


def test_habitat_to_world_worked_example() -> None:
    np.testing.assert_array_equal(habitat_to_world([1.0, 2.0, 3.0]), [1.0, -3.0, 2.0])
    # Habitat up (+Y) is our up (+Z); Habitat's agent forward (-Z) is our +Y.
    np.testing.assert_array_equal(habitat_to_world([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(habitat_to_world([0.0, 0.0, -1.0]), [0.0, 1.0, 0.0])
    assert np.linalg.det(HABITAT_TO_WORLD) == pytest.approx(1.0)  # proper rotation, no mirror
    np.testing.assert_array_equal(habitat_to_world(np.eye(3)), HABITAT_TO_WORLD.T)


@given(arrays(np.float64, st.tuples(st.integers(1, 5), st.just(3)), elements=st.floats(-1e3, 1e3)))
def test_frame_round_trip(p: np.ndarray) -> None:
    np.testing.assert_array_equal(world_to_habitat(habitat_to_world(p)), p)
    np.testing.assert_allclose(habitat_to_world(p), p @ HABITAT_TO_WORLD.T)


@given(arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_quaternion_conversion_is_conjugation(q: np.ndarray) -> None:
    q = q / np.linalg.norm(q)  # [x, y, z, w]
    r_h = quat_to_matrix(torch.tensor([q[3], q[0], q[1], q[2]], dtype=torch.float64)).numpy()
    r_w = quat_to_matrix(torch.from_numpy(habitat_quaternion_to_world(q))).numpy()
    np.testing.assert_allclose(r_w, HABITAT_TO_WORLD @ r_h @ HABITAT_TO_WORLD.T, atol=1e-12)


@given(st.floats(-math.pi, math.pi))
def test_habitat_rotation_for_heading_inverts_habitat_heading(heading: float) -> None:
    q = habitat_rotation_for_heading(heading)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    h = habitat_heading(q)
    assert math.cos(h - heading) == pytest.approx(1.0, abs=1e-12)
    # Worked example: heading +90 deg (our +Y) is Habitat's identity (looking along its -Z).
    np.testing.assert_allclose(habitat_rotation_for_heading(math.pi / 2), [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("theta", [0.0, 0.5, -2.0, math.pi / 2, math.pi])
def test_heading_of_habitat_yaw(theta: float) -> None:
    # Identity: the agent looks along Habitat -Z = our +Y -> heading +90 deg; a CCW yaw adds to it.
    expected = math.atan2(math.sin(math.pi / 2 + theta), math.cos(math.pi / 2 + theta))
    got = habitat_heading(_yaw_xyzw(theta))
    assert math.atan2(math.sin(got - expected), math.cos(got - expected)) == pytest.approx(0.0, abs=1e-12)
    w = habitat_quaternion_to_world(_yaw_xyzw(theta))
    expected_q = np.abs([math.cos(theta / 2), 0, 0, math.sin(theta / 2)])
    np.testing.assert_allclose(np.abs(w), expected_q, atol=1e-12)


# ---------------------------------------------------------------------------------------------- R2R / REVERIE


def test_load_r2r_ce(r2r_root: Path) -> None:
    ds = load_r2r_ce(r2r_root, "val_seen")
    assert ds.name == "r2r-ce" and len(ds) == 2 and ds.vocab[5] == "walk"
    ep = ds.by_id["1"]
    np.testing.assert_allclose(ep.start_position, [1.0, 2.0, 0.17])
    np.testing.assert_allclose(ep.goal_position, [4.0, 6.0, 0.17])
    np.testing.assert_allclose(ep.reference_path[1], [2.5, 4.0, 0.17])
    assert ep.start_heading == pytest.approx(math.pi / 2 + 0.5)
    assert ep.geodesic_distance == 6.4 and ep.goal_radius == 3.0 and ep.trajectory_id == "4"
    assert ep.instruction.tokens == (5, 9, 2, 0) and ep.scene_name == "7y3sRwLe3Va"
    np.testing.assert_allclose(ep.gt_locations[1], [1.0, 2.25, 0.17])
    assert ep.gt_actions == (1, 3, 1, 0)
    assert ep.ndtw_reference is ep.gt_locations
    spec = ep.metric_spec()
    assert spec.episode_id == "1" and spec.reference_path is ep.gt_locations
    assert ds.scenes() == ["7y3sRwLe3Va"]
    # Test split: no gt file, so no gt (unless required).
    test = load_r2r_ce(r2r_root, "test")
    t0 = test.episodes[0]
    assert t0.gt_locations is None and t0.ndtw_reference is t0.reference_path
    with pytest.raises(EpisodeFileError, match="test_gt.json.gz: ground-truth file not found"):
        load_r2r_ce(r2r_root, "test", with_gt=True)


def test_reverie_ce_needs_no_vocab(tmp_path: Path) -> None:
    root = tmp_path / "REVERIE_CE"
    _write(root / "val_unseen" / "val_unseen.json.gz", {"episodes": [_r2r_episode(3)]})
    ds = load_reverie_ce(root, "val_unseen")
    assert ds.name == "reverie-ce" and ds.vocab is None and len(ds) == 1
    with pytest.raises(EpisodeFileError, match="top level: field 'instruction_vocab': missing"):
        load_r2r_ce(root, "val_unseen")


# ---------------------------------------------------------------------------------------------- RxR


def _rxr_episode(eid: int, language: str) -> dict[str, Any]:
    ep = _r2r_episode(eid)
    ep["instruction"] = {
        "instruction_id": str(100 + eid),
        "instruction_text": "Go left.",
        "language": language,
        "annotator_id": "7",
        "edit_distance": 0.07,
        "timed_instruction": [
            {"word": "Go", "start_time": 0.5, "end_time": 0.8},
            {"word": "left.", "start_time": math.nan, "end_time": math.nan},
        ],
        "instruction_tokens": ["Go", "left", "."],
    }
    return ep


def test_load_rxr_ce_roles_and_languages(tmp_path: Path) -> None:
    root = tmp_path / "RxR_VLNCE_v0"
    _write(
        root / "val_unseen" / "val_unseen_guide.json.gz",
        {"episodes": [_rxr_episode(1, "en-US"), _rxr_episode(2, "hi-IN")]},
    )
    _write(root / "val_unseen" / "val_unseen_guide_gt.json.gz", _gt([1, 2]))
    _write(root / "val_unseen" / "val_unseen_follower.json.gz", {"episodes": [_rxr_episode(3, "en-IN")]})
    _write(root / "val_unseen" / "val_unseen_follower_gt.json.gz", _gt([3]))
    guide = load_rxr_ce(root, "val_unseen")
    assert [e.episode_id for e in guide.episodes] == ["1", "2"] and guide.episodes[0].role == "guide"
    ins = guide.by_id["1"].instruction
    assert (ins.instruction_id, ins.language, ins.annotator_id) == ("101", "en-US", "7")
    assert ins.edit_distance == 0.07
    assert ins.timed_instruction[0].start_time == 0.5 and ins.timed_instruction[1].start_time is None
    assert ins.tokens is None  # RxR tokens are words, not vocabulary ids
    both = load_rxr_ce(root, "val_unseen", roles=("guide", "follower"), languages=["en-US", "en-IN"])
    assert sorted(both.by_id) == ["1", "3"] and both.by_id["3"].role == "follower"
    with pytest.raises(ValueError, match="roles"):
        load_rxr_ce(root, "val_unseen", roles=("narrator",))


# ---------------------------------------------------------------------------------------------- malformed


def _r2r_with(tmp_path: Path, episodes: list[Any], gt: Any = None) -> Path:
    root = tmp_path / "bad"
    _write(root / "s" / "s.json.gz", {"episodes": episodes, "instruction_vocab": VOCAB})
    if gt is not None:
        _write(root / "s" / "s_gt.json.gz", gt)
    return root


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda e: e.pop("goals"), r"episode 5: field 'goals': missing"),
        (lambda e: e.update(goals={"position": [0, 0, 0]}), r"episode 5: field 'goals': expected a list"),
        (lambda e: e.update(goals=[], reference_path=[[0, "x", 0]]), r"field 'reference_path\[0\]'"),
        (lambda e: e.update(start_position="here"), r"episode 5: field 'start_position': expected list"),
        (lambda e: e.update(start_position=[1, 2]), r"episode 5: field 'start_position': expected a list"),
        (lambda e: e.update(start_rotation=[0, 0, 0, 2]), r"episode 5: field 'start_rotation': .*norm"),
        (lambda e: e["goals"][0].pop("position"), r"episode 5: field 'goals\[0\].position': missing"),
        (
            lambda e: e["instruction"].pop("instruction_text"),
            r"episode 5: field 'instruction.instruction_text': missing",
        ),
        (
            lambda e: e.update(reference_path=[[0, 0, 0], [1, "x", 0]]),
            r"episode 5: field 'reference_path\[1\]'",
        ),
        (lambda e: e.update(info={"geodesic_distance": -1}), r"episode 5: field 'info.geodesic_distance'"),
        (lambda e: e.update(episode_id=True), r"field 'episode_id': expected a number, got a bool"),
        (
            lambda e: e["instruction"].update(instruction_tokens=[1, 2.5]),
            r"episode 5: field 'instruction.instruction_tokens'",
        ),
    ],
)
def test_malformed_episode_names_file_episode_and_field(tmp_path: Path, mutate: Any, message: str) -> None:
    ep = copy.deepcopy(_r2r_episode(5))
    mutate(ep)
    root = _r2r_with(tmp_path, [ep])
    with pytest.raises(EpisodeFileError, match=rf"s.json.gz: .*{message}"):
        load_r2r_ce(root, "s")


def test_test_splits_without_goals_load_with_the_goal_unknown(tmp_path: Path) -> None:
    """R2R-CE / RxR-CE test splits: ``"goals": []``, no reference path, no gt file (issue 22)."""
    root = tmp_path / "r2r"
    test = [_r2r_episode(1, goals=[]), _r2r_episode(2, goals=None, reference_path=None)]
    del test[0]["reference_path"], test[0]["info"]
    _write(root / "test" / "test.json.gz", {"episodes": test, "instruction_vocab": VOCAB})
    ds = load_r2r_ce(root, "test")
    assert [e.has_goal for e in ds.episodes] == [False, False]
    for e in ds.episodes:
        assert e.goal_position is None and e.goal_radius is None and e.reference_path.shape == (0, 3)
        assert e.ndtw_reference is None and e.metric_spec().reference_path is None
    np.testing.assert_allclose(ds.episodes[0].start_position, [1.0, 2.0, 0.17])
    assert ds.by_id["2"].geodesic_distance == 6.4
    rxr = tmp_path / "rxr"
    ep = _r2r_episode(3, goals=[], reference_path=[])
    ep["instruction"] = {"instruction_text": "Go.", "instruction_id": 77, "language": "en-US"}
    _write(rxr / "test_challenge" / "test_challenge_guide.json.gz", {"episodes": [ep]})
    (e,) = load_rxr_ce(rxr, "test_challenge").episodes
    assert not e.has_goal and e.instruction.instruction_id == "77" and e.role == "guide"


def test_malformed_files(tmp_path: Path) -> None:
    root = _r2r_with(tmp_path, [_r2r_episode(1), _r2r_episode(2)], gt=_gt([1]))
    with pytest.raises(EpisodeFileError, match=r"s_gt.json.gz: episode 2: missing \(listed in"):
        load_r2r_ce(root, "s")
    root = _r2r_with(tmp_path, [_r2r_episode(1)], gt={"1": {"locations": "nowhere"}})
    with pytest.raises(EpisodeFileError, match=r"s_gt.json.gz: episode 1: field 'locations': expected list"):
        load_r2r_ce(root, "s")
    root = _r2r_with(tmp_path, [_r2r_episode(1)], gt={"1": {"locations": [[0, 0, 0]], "actions": ["STOP"]}})
    with pytest.raises(EpisodeFileError, match="episode 1: field 'actions'"):
        load_r2r_ce(root, "s")
    root = _r2r_with(tmp_path, [_r2r_episode(1)], gt={"1": {"locations": [[0, 0, 0]], "actions": [1, 7, -1]}})
    with pytest.raises(
        EpisodeFileError, match=r"episode 1: field 'actions': action ids must be 0..3.*\[-1, 7\]"
    ):
        load_r2r_ce(root, "s")
    root = _r2r_with(tmp_path, [_r2r_episode(1), _r2r_episode(1)])
    with pytest.raises(EpisodeFileError, match="episode 1: duplicate episode id"):
        load_r2r_ce(root, "s", with_gt=False)
    (root / "s" / "s.json.gz").write_bytes(b"\x1f\x8b not really gzip")
    with pytest.raises(EpisodeFileError, match="s.json.gz: cannot read gzipped JSON"):
        load_r2r_ce(root, "s")
    with pytest.raises(EpisodeFileError, match="file not found"):
        load_r2r_ce(root, "nope")
    _write(root / "t" / "t.json.gz", {"episodes": "all of them", "instruction_vocab": VOCAB})
    with pytest.raises(EpisodeFileError, match="top level: field 'episodes': expected list"):
        load_r2r_ce(root, "t")


def test_own_episodes_in_world_frame(tmp_path: Path) -> None:
    ep = _r2r_episode(
        1,
        start_position=[1.0, 2.0, 0.5],
        start_rotation=[math.cos(0.3), 0, 0, math.sin(0.3)],  # wxyz: yaw 0.6 about +Z
        goals=[{"position": [3.0, 4.0, 0.5]}],
        reference_path=[[1.0, 2.0, 0.5], [3.0, 4.0, 0.5]],
    )
    path = tmp_path / "episodes.json.gz"
    _write(path, {"frame": "image2sim-z-up", "quaternion_order": "wxyz", "episodes": [ep]})
    ds = load_image2sim_episodes(path)
    e = ds.episodes[0]
    np.testing.assert_array_equal(e.start_position, [1.0, 2.0, 0.5])
    assert e.start_heading == pytest.approx(0.6) and e.goal_radius is None
    _write(path, {"frame": "y-down", "episodes": [ep]})
    with pytest.raises(EpisodeFileError, match="field 'frame'"):
        load_image2sim_episodes(path)
