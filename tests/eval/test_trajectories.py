"""End to end without a simulator: load a VLN-CE-schema episode, score trajectories on an open floor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from image2sim.eval.datasets import load_r2r_ce
from image2sim.eval.metrics.nav import EpisodeResult, aggregate
from image2sim.eval.protocols import VLNCE
from image2sim.eval.trajectories import euclidean_geodesic, score_trajectory
from image2sim.simulator.conventions import Action

from tests.eval.test_datasets import VOCAB, _r2r_episode, _write

F, L, R, S = Action.MOVE_FORWARD, Action.TURN_LEFT, Action.TURN_RIGHT, Action.STOP


@pytest.fixture
def episode(tmp_path: Path):  # noqa: ANN201
    # Habitat frame: start at the origin, goal 5 m ahead along -Z (our +Y), dense gt every 0.25 m.
    gt = [[0.0, 0.0, -0.25 * k] for k in range(21)]
    ep = _r2r_episode(
        1,
        start_position=[0.0, 0.0, 0.0],
        goals=[{"position": [0.0, 0.0, -5.0], "radius": 3.0}],
        reference_path=[[0.0, 0.0, 0.0], [0.0, 0.0, -2.5], [0.0, 0.0, -5.0]],
        info={"geodesic_distance": 5.0},
    )
    root = tmp_path / "r2r"
    _write(root / "s" / "s.json.gz", {"episodes": [ep], "instruction_vocab": VOCAB})
    gt_entry = {"locations": gt, "actions": [1] * 20 + [0], "forward_steps": 20}
    _write(root / "s" / "s_gt.json.gz", {"1": gt_entry})
    return load_r2r_ce(root, "s").episodes[0]


def _walk(direction: np.ndarray, n_forward: int, turns: int = 1) -> tuple[np.ndarray, list[int]]:
    pos = [np.zeros(3)] * (turns + 1)
    actions = [L] * turns
    for k in range(1, n_forward + 1):
        pos.append(direction * 0.25 * k)
        actions.append(F)
    pos.append(pos[-1])
    actions.append(S)
    return np.stack(pos), actions


def test_oracle_follower_scores_perfectly(episode) -> None:  # noqa: ANN001
    pos, actions = _walk(np.array([0.0, 1.0, 0.0]), 20)
    res = score_trajectory(episode, pos, actions, euclidean_geodesic, VLNCE).metrics
    assert res["success"] == 1.0 and res["oracle_success"] == 1.0
    assert res["distance_to_goal"] == pytest.approx(0.0, abs=1e-12)
    assert res["spl"] == pytest.approx(1.0) and res["path_length"] == pytest.approx(5.0)
    assert res["ndtw"] == pytest.approx(1.0) and res["sdtw"] == pytest.approx(1.0)
    assert res["steps"] == 22


def test_wrong_way_and_early_stop(episode) -> None:  # noqa: ANN001
    wrong_pos, wrong_act = _walk(np.array([0.0, -1.0, 0.0]), 10)
    early_pos, early_act = _walk(np.array([0.0, 1.0, 0.0]), 10)  # stops 2.5 m short: inside 3 m
    wrong = score_trajectory(episode, wrong_pos, wrong_act, euclidean_geodesic, VLNCE)
    early = score_trajectory(episode, early_pos, early_act, euclidean_geodesic, VLNCE)
    assert wrong.metrics["success"] == 0.0 and wrong.metrics["distance_to_goal"] == pytest.approx(7.5)
    assert wrong.metrics["ndtw"] < 0.5 and wrong.metrics["spl"] == 0.0
    assert early.metrics["success"] == 1.0 and early.metrics["spl"] == pytest.approx(1.0)
    assert 0.5 < early.metrics["ndtw"] < 1.0
    rep = aggregate([wrong, EpisodeResult("2", early.metrics, early.protocol)])
    assert rep.metrics["success"].mean == 0.5 and rep.metrics["success"].count == 2


def test_frame_mixup_is_caught(episode) -> None:  # noqa: ANN001
    pos, actions = _walk(np.array([0.0, 1.0, 0.0]), 4)
    with pytest.raises(ValueError, match="episode 1: trajectory starts 2.000 m from"):
        score_trajectory(episode, pos + np.array([0.0, 0.0, 2.0]), actions, euclidean_geodesic, VLNCE)
