"""Result files and resumable episode logs: protocol in every file, atomic writes, torn-line recovery."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
from image2sim.eval.metrics.nav import EpisodeResult, aggregate
from image2sim.eval.protocols import IMAGE2SIM, VLNCE, ProtocolMismatchError
from image2sim.eval.results import (
    EpisodeLog,
    ResultFileError,
    read_episode_log,
    read_result_file,
    write_aggregate,
    write_result_file,
)


def _results(n: int, protocol=VLNCE) -> list[EpisodeResult]:  # noqa: ANN001
    return [EpisodeResult(str(i), {"success": float(i % 2), "ndtw": None if i == 0 else 0.1 * i}, protocol)
            for i in range(n)]


def test_result_file_round_trip(tmp_path: Path) -> None:
    path = write_result_file(tmp_path / "out" / "r.json", IMAGE2SIM, {"score": 1.5, "seed": 3})
    protocol, payload = read_result_file(path)
    assert protocol == IMAGE2SIM and payload == {"score": 1.5, "seed": 3}
    assert json.loads(path.read_text())["protocol"]["max_steps"] == 300
    assert not list(path.parent.glob("*.tmp"))  # temp file renamed away
    with pytest.raises(ValueError, match="reserved key"):
        write_result_file(tmp_path / "x.json", VLNCE, {"protocol": "mine"})
    with pytest.raises(ValueError):  # NaN is not JSON; it must be dealt with before writing
        write_result_file(tmp_path / "nan.json", VLNCE, {"score": math.nan})
    assert not (tmp_path / "nan.json").exists() and not list(tmp_path.glob(".nan.json.*"))


def test_result_file_errors(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text('{"format": "something-else"}')
    with pytest.raises(ResultFileError, match="a.json: not an 'image2sim-eval-result' file"):
        read_result_file(tmp_path / "a.json")
    doc = {"format": "image2sim-eval-result", "version": 1, "protocol": {**VLNCE.to_dict(), "extra": 1}}
    (tmp_path / "b.json").write_text(json.dumps(doc))
    with pytest.raises(ResultFileError, match=r"b.json: protocol: unknown field\(s\) \['extra'\]"):
        read_result_file(tmp_path / "b.json")
    (tmp_path / "c.json").write_text("{")
    with pytest.raises(ResultFileError, match="c.json: cannot read"):
        read_result_file(tmp_path / "c.json")


def test_write_aggregate(tmp_path: Path) -> None:
    report = aggregate(_results(4))
    path = write_aggregate(tmp_path / "agg.json", report, {"split": "val_seen"})
    protocol, payload = read_result_file(path)
    assert protocol == VLNCE and payload["num_episodes"] == 4 and payload["split"] == "val_seen"
    ndtw_sem = 0.1 / math.sqrt(3)  # values 0.1, 0.2, 0.3: sample std 0.1
    expected = {"mean": pytest.approx(0.2), "count": 3, "missing": 1, "sem": pytest.approx(ndtw_sem)}
    assert payload["metrics"]["ndtw"] == expected


def test_episode_log_resume_matches_uninterrupted(tmp_path: Path) -> None:
    rs = _results(6)
    full = EpisodeLog(tmp_path / "full.jsonl", VLNCE)
    for r in rs:
        full.append(r)
    # "Killed" after three episodes with a torn fourth line, then resumed in a new process.
    part = EpisodeLog(tmp_path / "part.jsonl", VLNCE)
    for r in rs[:3]:
        part.append(r)
    with open(tmp_path / "part.jsonl", "a") as f:
        f.write('{"episode_id": "3", "metr')
    with pytest.warns(UserWarning, match="torn last line"):
        read_episode_log(tmp_path / "part.jsonl")
    with pytest.warns(UserWarning, match="dropping a torn last line"):
        resumed = EpisodeLog(tmp_path / "part.jsonl", VLNCE)
    assert resumed.done_ids() == {"0", "1", "2"}
    for r in rs:
        if r.episode_id not in resumed.done_ids():
            resumed.append(r)
    assert resumed.aggregate() == full.aggregate()
    protocol, back = read_episode_log(tmp_path / "part.jsonl")
    assert protocol == VLNCE and [r.episode_id for r in back] == [str(i) for i in range(6)]


def test_episode_log_refuses_other_protocols_and_bad_lines(tmp_path: Path) -> None:
    log = EpisodeLog(tmp_path / "log.jsonl", VLNCE)
    with pytest.raises(ProtocolMismatchError, match="episode 0 was run under protocol 'image2sim'"):
        log.append(_results(1, IMAGE2SIM)[0])
    with pytest.raises(ProtocolMismatchError, match="refusing to append"):
        EpisodeLog(tmp_path / "log.jsonl", dataclasses.replace(VLNCE, success_distance_m=2.0))
    with pytest.raises(ValueError, match="episode x: metric 'ndtw' is nan"):
        log.append(EpisodeResult("x", {"ndtw": math.nan}, VLNCE))
    log.append(_results(1)[0])
    with open(tmp_path / "log.jsonl", "a") as f:
        f.write("garbage\n")
    log.append(_results(2)[1])
    with pytest.raises(ResultFileError, match=r"log.jsonl:3: malformed episode line"):
        read_episode_log(tmp_path / "log.jsonl")
    (tmp_path / "empty.jsonl").write_text("")
    with pytest.raises(ResultFileError, match="empty episode log"):
        read_episode_log(tmp_path / "empty.jsonl")
