"""Navigation report tables, DVC metrics, and the `image2sim eval` commands end to end."""

from __future__ import annotations

import json
from pathlib import Path

from image2sim.eval.cli import app
from image2sim.eval.metrics.nav import EpisodeResult, aggregate
from image2sim.eval.protocols import IMAGE2SIM, VLNCE
from image2sim.eval.report import dvc_metrics, nav_table_markdown, read_aggregate, write_nav_report
from image2sim.eval.results import EpisodeLog
from typer.testing import CliRunner


def _report(protocol=VLNCE, n=4):  # noqa: ANN001, ANN202
    rs = [EpisodeResult(str(i), {"distance_to_goal": 1.0 + i, "success": float(i < 3), "spl": 0.5,
                                 "ndtw": None if i == 0 else 0.6, "oracle_success": 1.0}, protocol)
          for i in range(n)]
    return aggregate(rs)


def test_table_layout_counts_and_na() -> None:
    table = nav_table_markdown([("Ours (90°)", _report()), ("Ours (paper)", _report(IMAGE2SIM, 2))])
    lines = table.splitlines()
    header = "|  | NE↓ | OSR↑ | SR↑ | SPL↑ | nDTW↑ | sDTW↑ | TL | Steps | Episodes | Protocol |"
    assert lines[0] == header
    row = lines[2].split(" | ")
    assert row[1:5] == ["2.50", "100.0", "75.0", "50.0"]
    assert row[5] == "60.0 (n=3)"  # one episode had no reference: its count is shown
    assert row[6] == "n/a"  # sDTW never computed -> n/a, not 0
    assert lines[2].endswith("| 4 | vlnce |") and lines[3].endswith("| 2 | image2sim |")
    assert "`vlnce`: 500 steps, 15° turns" in table and "`image2sim`: 300 steps" in table


def test_dvc_metrics_and_round_trip(tmp_path: Path) -> None:
    rep = _report()
    m = dvc_metrics(rep)
    assert m["protocol"] == "vlnce" and m["success"] == 0.75 and m["ndtw_count"] == 3
    paths = write_nav_report(tmp_path / "run", "val_unseen", rep)
    assert json.loads(paths["metrics"].read_text())["spl"] == 0.5
    label, back = read_aggregate(paths["aggregate"])
    assert label == "val_unseen" and back == rep
    assert "| val_unseen |" in paths["table"].read_text()


def test_cli_aggregate_and_report(tmp_path: Path) -> None:
    log = EpisodeLog(tmp_path / "run.jsonl", VLNCE)
    for i in range(3):
        log.append(EpisodeResult(str(i), {"success": float(i > 0), "spl": 0.9}, VLNCE))
    runner = CliRunner()
    res = runner.invoke(app, ["aggregate", str(tmp_path / "run.jsonl"), "--out", str(tmp_path / "agg"),
                              "--label", "random"])
    assert res.exit_code == 0, res.output
    assert "| random |" in res.output and "66.7" in res.output
    agg = str(tmp_path / "agg" / "aggregate.json")
    res = runner.invoke(app, ["report", agg, "--out", str(tmp_path / "t.md")])
    assert res.exit_code == 0, res.output
    assert "| random |" in (tmp_path / "t.md").read_text()
    res = runner.invoke(app, ["protocols"])
    assert res.exit_code == 0 and "rxr-habitat" in res.output and "sliding off" in res.output
