"""Leaderboard predictions (issue 22): R2R-CE EvalAI JSON and RxR-Habitat jsonl from an eval nav run."""

from __future__ import annotations

import gzip
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


# ----------------------------------------------------------------------- test splits without goals


def _check_r2r_ce_submission(pred, episodes) -> None:
    """The R2R-CE EvalAI predictions format (what VLN-CE's ``inference.py`` writes): one entry per
    episode id of the split, each a non-empty list of ``{"position": [x, y, z], "heading": float,
    "stop": bool}`` in the Habitat frame, starting at the episode's start, at most one stop (last)."""
    assert isinstance(pred, dict) and sorted(pred) == sorted(str(e["episode_id"]) for e in episodes)
    for ep in episodes:
        steps = pred[str(ep["episode_id"])]
        assert isinstance(steps, list) and steps
        for s in steps:
            assert set(s) == {"position", "heading", "stop"} and isinstance(s["stop"], bool)
            assert len(s["position"]) == 3 and all(isinstance(v, float) for v in s["position"])
            assert isinstance(s["heading"], float) and -math.pi <= s["heading"] <= math.pi
        assert not any(s["stop"] for s in steps[:-1])
        np.testing.assert_allclose(steps[0]["position"], ep["start_position"], atol=1e-4)


def _goalless_test_split(tmp_path, n: int = 3):
    """A procedural capture and an R2R-CE-style ``test`` split on it without goals, reference paths or
    gt file, plus the same episodes as an RxR-CE ``test_challenge_guide`` file with instruction ids."""
    from image2sim.dataengine.episodes import episode_record, vocab_block
    from image2sim.dataengine.procedural import preset, synthesize
    from image2sim.eval.protocols import get_protocol
    from image2sim.eval.runner import load_exact_backend, sample_point_goal_episodes

    synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)
    (scene,) = sorted(p for p in (tmp_path / "caps").iterdir() if p.is_dir())
    sim = load_exact_backend(scene, get_protocol("image2sim")).sim
    episodes = []
    for i, e in enumerate(sample_point_goal_episodes(sim, n, seed=1, min_distance=0.5, scene_id=scene.name)):
        rec = episode_record(
            str(i),
            scene.name,
            e.start_position,
            e.start_heading,
            e.goal_position,
            3.0,
            e.reference_path,
            "Walk ahead and stop.",
            1.0,
        )
        rec.update(
            goals=[], instruction={"instruction_text": "Walk ahead and stop.", "instruction_tokens": [2, 3]}
        )
        del rec["reference_path"], rec["info"]
        episodes.append(rec)
    root = tmp_path / "data"
    for name, doc in {
        "test/test.json.gz": {
            "episodes": episodes,
            "instruction_vocab": vocab_block(["<PAD>", "<UNK>", "walk", "ahead"]),
        },
        "test_challenge/test_challenge_guide.json.gz": {
            "episodes": [
                {**e, "instruction": {**e["instruction"], "instruction_id": 100 - i, "language": "en-US"}}
                for i, e in enumerate(episodes)
            ]
        },
    }.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(gzip.compress(json.dumps(doc).encode()))
    return scene.parent, root, episodes


def test_eval_nav_submits_a_test_split_without_goals_and_refuses_the_oracle(tmp_path, run_main):
    from image2sim.eval.results import read_metrics_file
    from image2sim.simulator.cli import build_app
    from typer.testing import CliRunner

    scenes, root, episodes = _goalless_test_split(tmp_path)
    base = ["eval", "nav", "--backend", "exact", "--scenes", str(scenes), "--dataset-root", str(root)]
    sub, metrics = tmp_path / "predictions.json", tmp_path / "nav.json"
    args = [*base, "--dataset", "r2r-ce", "--split", "test", "--agent", "forward", "--forward-steps", "3"]
    args += ["--out", str(tmp_path / "run"), "--metrics", str(metrics), "--submission", str(sub)]
    res = CliRunner().invoke(build_app(), args)
    assert res.exit_code == 0, res.output
    pred = json.loads(sub.read_text())
    _check_r2r_ce_submission(pred, episodes)
    assert all(len(steps) == 5 and steps[-1]["stop"] for steps in pred.values())  # start, 3 forward, STOP
    text = metrics.read_text()
    assert "NaN" not in text and "Infinity" not in text
    row = read_metrics_file(metrics)["agents"]["forward"]
    for key in ("sr", "spl", "ne", "osr", "ndtw", "sdtw", "sr_ci", "spl_ci", "ne_approximate"):
        assert row[key] is None, key  # n/a, never 0
    assert row["steps"] == 4.0 and row["path_length"] > 0 and row["n_episodes"] == len(episodes)
    assert "n/a" in res.output and "no goal" in res.output

    rxr = tmp_path / "rxr.jsonl"
    args = [*base, "--dataset", "rxr-ce", "--split", "test_challenge", "--agent", "random"]
    args += ["--out", str(tmp_path / "run_rxr"), "--metrics", str(tmp_path / "rxr.json")]
    res = CliRunner().invoke(build_app(), [*args, "--submission", str(rxr), "--submission-format", "rxr-ce"])
    assert res.exit_code == 0, res.output
    lines = [json.loads(line) for line in rxr.read_text().splitlines()]
    assert [d["instruction_id"] for d in lines] == sorted(100 - i for i in range(len(episodes)))
    for d in lines:
        assert set(d) == {"instruction_id", "path"} and all(len(p) == 3 for p in d["path"])

    oracle = tmp_path / "oracle"
    args = [
        *base,
        "--dataset",
        "r2r-ce",
        "--split",
        "test",
        "--agent",
        "oracle",
        "--out",
        str(oracle / "run"),
    ]
    args += ["--metrics", str(oracle / "nav.json"), "--submission", str(oracle / "p.json")]
    code, output = run_main(args)  # through the CLI's error boundary: one line, status 2
    assert code == 2, output
    assert "'oracle'" in output and "without a goal" in output and "shortest path" in output
    assert "Traceback" not in output
    assert not oracle.exists()  # refused before anything is written
