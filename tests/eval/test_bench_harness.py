"""The shared benchmark harness (``benchmarks/harness.py``) and the timing loop under it."""

from __future__ import annotations

import importlib.util
import json
import statistics
import sys
from pathlib import Path

import pytest
from image2sim.eval.metrics.timing import measure_fps, time_calls

HARNESS = Path(__file__).resolve().parents[2] / "benchmarks" / "harness.py"


@pytest.fixture(scope="module")
def harness():
    name = "bench_harness_under_test"
    spec = importlib.util.spec_from_file_location(name, HARNESS)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve their module through sys.modules
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(name, None)


class FakeClock:
    """Each call of the timed function advances time by the next scripted duration."""

    def __init__(self, durations):
        self.now, self.durations = 0.0, list(durations)

    def __call__(self) -> float:
        return self.now

    def work(self) -> None:
        self.now += self.durations.pop(0)


def test_time_calls_skips_warmup_and_times_each_call():
    clock = FakeClock([100.0, 100.0, 0.3, 0.1, 0.2])  # two slow warm-up calls, then three timed
    walls, cpus = time_calls(clock.work, warmup=2, runs=3, clock=clock)
    assert walls == pytest.approx([0.3, 0.1, 0.2])
    assert len(cpus) == 3 and all(c >= 0 for c in cpus)
    assert clock.durations == []  # exactly warmup + runs calls
    with pytest.raises(ValueError, match="runs >= 1"):
        time_calls(clock.work, warmup=0, runs=0)
    with pytest.raises(ValueError, match="warmup >= 0"):
        time_calls(clock.work, warmup=-1, runs=1)


def test_measure_fps_still_uses_the_median_of_timed_calls():
    clock = FakeClock([9.0, 0.5, 0.25, 1.0])
    m = measure_fps(clock.work, warmup=1, runs=3, frames_per_call=2, clock=clock)
    assert m.median_seconds == pytest.approx(0.5) and m.fps == pytest.approx(4.0)
    assert m.seconds == pytest.approx((0.5, 0.25, 1.0))


def test_time_it_medians_and_call_count(harness):
    calls = []
    t = harness.time_it(lambda: calls.append(sum(range(2000))), warmup=2, repeats=5)
    assert len(calls) == 7 and t.repeats == 5 and t.warmup == 2
    assert t.wall == statistics.median(t.walls) and t.cpu == statistics.median(t.cpus)
    assert all(w > 0 for w in t.walls)


def test_write_report_json_markdown_and_no_temp_files(harness, tmp_path):
    rows = [{"case": "a", "ms": 1.5, "extra": [1, 2]}, {"case": "b", "ms": None, "ratio": 2.0}]
    json_path, md_path = harness.write_report("demo", rows, {"statistic": "median"}, reports=tmp_path)
    report = json.loads(json_path.read_text())
    assert report["benchmark"] == "demo" and report["statistic"] == "median"
    assert report["hardware"] and report["date_utc"].endswith("Z")
    assert report["rows"] == rows
    md = md_path.read_text().splitlines()
    assert md[0] == "# demo"
    # Union of scalar columns in first-seen order; list-valued cells stay out of the table.
    assert "| case | ms | ratio |" in md
    assert "| b | – | 2 |" in md
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.json", "demo.md"]


def test_write_report_custom_markdown_meta_override_and_rows_key(harness, tmp_path):
    meta = {"benchmark": "legacy", "hardware": "given", "date_utc": "2000-01-01T00:00:00Z"}
    json_path, md_path = harness.write_report(
        "custom", [], meta, markdown=["# mine", "text"], reports=tmp_path, rows_key="cases"
    )
    report = json.loads(json_path.read_text())
    assert (report["benchmark"], report["hardware"], report["cases"]) == ("legacy", "given", [])
    assert "rows" not in report
    assert md_path.read_text() == "# mine\ntext\n"


def test_write_text_atomic_keeps_the_old_file_when_writing_fails(harness, tmp_path):
    target = tmp_path / "r.json"
    harness.write_text_atomic(target, "old")

    with pytest.raises(TypeError):
        harness.write_text_atomic(target, 123)  # not text: the write fails midway
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]
