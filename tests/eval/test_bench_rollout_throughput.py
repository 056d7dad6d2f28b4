"""The rollout-throughput benchmark (``benchmarks/rollout_throughput.py``) in quick mode."""

from __future__ import annotations

import json
import math

import pytest

from tests.eval.bench_loader import benchmark_module

pytest.importorskip("image2sim.navpolicy")
pytest.importorskip("image2sim.dataengine")


@pytest.fixture(scope="module")
def bench():
    """The benchmark script as a module."""
    with benchmark_module("rollout_throughput.py") as module:
        yield module


def test_quick_run_writes_finite_positive_rates(bench, tmp_path):
    result = bench.main(["--quick", "--steps", "2"], reports=tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rollout_throughput.json", "rollout_throughput.md"]
    report = json.loads((tmp_path / "rollout_throughput.json").read_text())
    assert report["benchmark"] == "rollout_throughput" and report["hardware"]
    assert report["date_utc"].endswith("Z") and report["reference"] == "exact"
    assert math.isfinite(report["load_average_start"]) and report["threads"] == 1
    assert report["steps_per_episode"] == 2 and report["batches"] == [1, 2]
    assert report["scene"]["gaussians"] > 0 and "untrained" in report["scene"]["neural_renderer"]["weights"]
    rows = report["rows"]
    assert [(r["renderer"], r["batch"]) for r in rows] == [
        (name, b) for b in (1, 2) for name in ("exact", "splat_only", "neural")
    ]
    for r in rows:
        assert r["agent_steps_per_episode"] == 2 * r["batch"]
        for key in (
            "steps_per_s",
            "steps_per_cpu_s",
            "render_ms_per_step",
            "policy_ms_per_step",
            "sim_step_ms_per_step",
            "speed_vs_exact",
            "render_speed_vs_exact",
        ):
            assert math.isfinite(r[key]) and r[key] > 0, (r["renderer"], r["batch"], key, r[key])
        assert sum(r["action_fractions"].values()) == pytest.approx(1.0, abs=0.01)
        assert ("Batched" in r["agent"]) == (r["batch"] > 1)
    assert all(r["speed_vs_exact"] == 1.0 for r in rows if r["renderer"] == "exact")
    assert set(report["ratios_steps_per_s"]) == {"splat_only/exact", "neural/exact"}
    assert set(report["ratios_steps_per_s"]["neural/exact"]) == {"B=1", "B=2"}
    md = (tmp_path / "rollout_throughput.md").read_text()
    assert md.startswith("# Rollout throughput") and "| renderer | B | steps/s | vs exact |" in md
    assert md.count("\n| neural |") == 2
    assert result["rows"] == rows


def test_the_exact_reference_is_required(bench):
    with pytest.raises(ValueError, match="reference"):
        bench.run(rows=("neural",))
