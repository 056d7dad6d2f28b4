"""Leaderboard predictions (issue 22): R2R-CE EvalAI JSON and RxR-Habitat jsonl from an eval nav run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from image2sim.eval.submission import (
    SubmissionError,
    r2r_ce_predictions,
    rxr_habitat_predictions,
    write_submission,
)
from image2sim.simulator.geometry.habitat import habitat_rotation_for_heading


def _vlnce_get_info_heading(q_xyzw) -> float:
    """VLN-CE's VLNCEInferenceEnv.get_info, written out: rotate (0, 0, -1) by the inverse agent
    rotation, heading = cartesian_to_polar(-v[2], v[0])[1] = atan2(v[0], -v[2])."""
    x, y, z, w = q_xyzw
    # rotation matrix of the conjugate (inverse) quaternion
    x, y, z = -x, -y, -z
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    v = r @ np.array([0.0, 0.0, -1.0])
    return math.atan2(v[0], -v[2])


TRAJ = {
    "ep1": {
        "positions": [[1.0, 2.0, 0.1], [1.25, 2.0, 0.1], [1.25, 2.0, 0.1]],
        "headings": [0.0, 0.0, math.pi / 2],
        "actions": [1, 2, 0],
    },
    "ep2": {"positions": [[0.0, 0.0, 0.0], [0.0, 0.25, 0.0]], "headings": [1.0, 1.0], "actions": [1]},
}


def test_r2r_ce_predictions_are_in_the_habitat_frame_with_vlnce_headings():
    pred = r2r_ce_predictions(TRAJ)
    assert list(pred) == ["ep1", "ep2"] and len(pred["ep1"]) == 3
    assert pred["ep1"][0]["position"] == [1.0, 0.1, -2.0]  # (x, y, z)_world -> (x, z, -y)_habitat
    assert [s["stop"] for s in pred["ep1"]] == [False, False, True]
    assert not any(s["stop"] for s in pred["ep2"])  # ran out of steps: never stopped
    for h in np.linspace(-3.1, 3.1, 25):
        q = habitat_rotation_for_heading(h)
        got = r2r_ce_predictions({"e": {"positions": [[0, 0, 0]], "headings": [h], "actions": [0]}})
        assert math.isclose(
            math.remainder(got["e"][0]["heading"] - _vlnce_get_info_heading(q), 2 * math.pi), 0, abs_tol=1e-9
        )


def test_rxr_predictions_drop_turns_in_place_and_sort_by_instruction_id(tmp_path):
    lines = rxr_habitat_predictions(TRAJ, {"ep1": "7", "ep2": 3})
    assert [d["instruction_id"] for d in lines] == [3, 7]
    assert lines[1]["path"] == [[1.0, 0.1, -2.0], [1.25, 0.1, -2.0]]
    with pytest.raises(SubmissionError, match="instruction_id"):
        rxr_habitat_predictions(TRAJ, {"ep1": 1})
    path = write_submission(tmp_path / "rxr.jsonl", "rxr-ce", TRAJ, ["ep1", "ep2"], {"ep1": 7, "ep2": 3})
    assert [json.loads(line)["instruction_id"] for line in path.read_text().splitlines()] == [3, 7]


def test_a_submission_missing_an_episode_is_refused(tmp_path):
    with pytest.raises(SubmissionError, match="no trajectory"):
        write_submission(tmp_path / "p.json", "r2r-ce", TRAJ, ["ep1", "ep2", "ep3"])
    assert not (tmp_path / "p.json").exists()
    with pytest.raises(SubmissionError, match="format"):
        write_submission(tmp_path / "p.json", "habitat", TRAJ, ["ep1"])


def test_eval_nav_writes_an_r2r_ce_submission_of_its_run(tmp_path):
    from image2sim.dataengine.procedural import preset, synthesize
    from image2sim.simulator.cli import build_app
    from typer.testing import CliRunner

    synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)
    sub = tmp_path / "predictions.json"
    args = ["eval", "nav", "--backend", "exact", "--scenes", str(tmp_path / "caps"), "--point-goal", "3"]
    args += ["--min-distance", "0.5", "--agent", "oracle", "--out", str(tmp_path / "run")]
    args += ["--metrics", str(tmp_path / "nav.json"), "--submission", str(sub)]
    res = CliRunner().invoke(build_app(), args)
    assert res.exit_code == 0, res.output
    pred = json.loads(sub.read_text())
    assert len(pred) == 3
    for steps in pred.values():
        assert all(set(s) == {"position", "heading", "stop"} and len(s["position"]) == 3 for s in steps)
        assert steps[-1]["stop"] and not any(s["stop"] for s in steps[:-1])  # the oracle stops
    res = CliRunner().invoke(build_app(), [*args[:-2], "--agent", "random", "--submission", str(sub)])
    assert res.exit_code == 2 and "submission" in res.output
