"""The lifting benchmark (``benchmarks/lift.py``) in quick mode, pinhole house only."""

from __future__ import annotations

import json
import math

import pytest

from tests.eval.bench_loader import benchmark_module

pytest.importorskip("pycolmap")
pytest.importorskip("image2sim.dataengine")


@pytest.fixture(scope="module")
def bench():
    """The benchmark script as a module."""
    with benchmark_module("lift.py") as module:
        yield module


@pytest.mark.slow  # a 10-view house: synthesis, SfM and plane-sweep depth, ~30 s on 2 shared cores
def test_quick_run_writes_scored_rows(bench, tmp_path):
    bench.main(["--quick", "--only", "pinhole"], reports=tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lift.json", "lift.md"]
    report = json.loads((tmp_path / "lift.json").read_text())
    assert report["benchmark"] == "lift" and report["hardware"] and report["date_utc"].endswith("Z")
    (row,) = report["rows"]
    text = (tmp_path / "lift.md").read_text()
    assert row["kind"] == "pinhole"
    if "error" in row:
        # 10 views thinned from a walk see the floor barely: when no floor plane stands out from the
        # walls, the camera-height scale is refused (not guessed), and the row says so.
        assert "no well-supported horizontal plane" in row["error"] and "--baseline" in row["error"], row
        assert "failed: ScaleError" in text
    else:
        assert row["registered"] >= 3 and row["input_frames"] == 10
        keys = ("sfm_s", "depth_s", "scale_s", "write_s", "navmap_s", "ate_m", "rot_max_deg", "scale_error")
        for key in keys:
            assert math.isfinite(row[key]) and row[key] >= 0, key
        assert 0 < row["coverage"] <= 1 and math.isfinite(row["absrel"])
        assert 0 <= row["nav_f"] <= 1
        assert row["frames_refused_by_reader"] == []  # frames without depth are left out by lift
    # Quality is the full run's business: 10 views are too few for reliable SfM (one measured run
    # misregistered a view by 27 degrees), so only the report's shape is checked here.
    assert {c["key"] for c in report["checks"]} == set(bench.TARGETS)
    assert "## Targets" in text and "## Per stage" in text
    # --render-only rewrites the Markdown from the JSON (after the notes are edited), running nothing.
    (tmp_path / "lift.md").unlink()
    bench.main(["--render-only"], reports=tmp_path)
    assert (tmp_path / "lift.md").read_text() == text


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("nope=1", "unknown multi-view stereo option"),
        ("best_k", "NAME=VALUE with a JSON value"),
        ("best_k=one", "NAME=VALUE with a JSON value"),
        ("best_k=0", "best_k must be a positive integer"),
    ],
)
def test_bad_mvs_options_stop_before_any_work(bench, tmp_path, capsys, item, message):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--quick", "--only", "pinhole", "--mvs", item], reports=tmp_path)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # no report written
