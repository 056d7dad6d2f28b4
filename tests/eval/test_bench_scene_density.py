"""The Gaussian-density benchmark (``benchmarks/scene_density.py``) in quick mode."""

from __future__ import annotations

import json
import math

import pytest

from tests.eval.bench_loader import benchmark_module

pytest.importorskip("image2sim.navpolicy")
pytest.importorskip("image2sim.dataengine")


@pytest.fixture(scope="module")
def bench():
    with benchmark_module("scene_density.py") as module:
        yield module


def test_quick_run_coarser_fusion_keeps_fewer_gaussians(bench, tmp_path):
    result = bench.main(["--quick", "--factors", "1", "4"], reports=tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene_density.json", "scene_density.md"]
    report = json.loads((tmp_path / "scene_density.json").read_text())
    assert report["benchmark"] == "scene_density" and report["hardware"] and report["poses"] == 2
    rows = report["rows"]
    assert [r["footprint_factor"] for r in rows] == [1.0, 4.0]
    ref, coarse = rows
    assert ref["splat_speedup_vs_default"] == 1.0 and ref["psnr_change_vs_default_db"] == 0.0
    # A coarser voxel fusion keeps fewer Gaussians; fidelity stays a finite PSNR against the exact render.
    assert 0 < coarse["gaussians"] < ref["gaussians"]
    for r in rows:
        assert (
            r["splat_ms_per_frame"] > 0
            and math.isfinite(r["psnr_vs_exact_db"])
            and r["psnr_vs_exact_db"] > 10
        )
        assert 0 <= r["depth_absrel_vs_exact"] < 0.5
    assert result["network_ms_per_frame"] > 0
    assert "footprint_factor" in (tmp_path / "scene_density.md").read_text()


def test_the_default_factor_must_be_measured(bench):
    with pytest.raises(ValueError, match="reference"):
        bench.run(factors=(2.0,), preset_name="tiny", poses=1, repeats=1, pano_height=16)
