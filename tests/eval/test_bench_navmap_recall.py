"""The navigable-area recall benchmark (``benchmarks/navmap_recall.py``) in quick mode."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from tests.eval.bench_loader import benchmark_module

pytest.importorskip("image2sim.dataengine")


@pytest.fixture(scope="module")
def bench():
    with benchmark_module("navmap_recall.py") as module:
        yield module


def test_quick_run_scores_every_variant_against_the_exact_floor(bench, tmp_path):
    rows = bench.main(["--quick", "--preset", "tiny", "--seeds", "3"], reports=tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["navmap_recall.json", "navmap_recall.md"]
    report = json.loads((tmp_path / "navmap_recall.json").read_text())
    assert report["benchmark"] == "navmap_recall" and report["hardware"] and report["preset"] == "tiny"
    assert [r["variant"] for r in rows] == list(bench.VARIANTS)
    assert [s["variant"] for s in report["summary"]] == list(bench.VARIANTS)
    for r in rows:
        # Exact depth: the extracted map lies on the exact floor, and finds a good part of what it was shown
        # (the tiny preset's 128-pixel-high panoramas sample far floor sparsely).
        assert r["P"] >= 0.9, r
        assert 0.4 <= r["R seen"] <= 1.0, r
        assert 0 < r["seen"] <= 1 and 0 < r["R"] <= 1 and r["extract s"] > 0
    # Unseen space no longer projects the buffer: the defaults keep more of the seen floor than before.
    by_name = {r["variant"]: r for r in rows}
    before = by_name["before 2026-11-28: closing 2, unseen = buffer"]
    assert by_name["default"]["R seen"] > before["R seen"] + 0.1
    # Exact depth has no holes: the hole normals change nothing there, and nothing floats for the
    # visibility carving to drop (a few voxels at most).
    no_carving = by_name["no visibility carving (before 2026-12-07, session 51)"]
    no_holes = by_name["no hole normals (before 2026-12-07)"]
    assert all(no_holes[k] == no_carving[k] for k in ("P", "R", "R seen"))
    assert all(abs(no_carving[k] - by_name["default"][k]) <= 0.01 for k in ("P", "R", "R seen"))
    assert "R seen" in (tmp_path / "navmap_recall.md").read_text()


def test_seen_floor_marks_only_cells_under_the_floor_points(bench, tmp_path):
    """Seen cells of a house's own exact capture lie on its floor (free or obstacle), never far outside."""
    path = bench.write_house(tmp_path, 3, "equirect", "none", "tiny")
    nav, res, origin = bench.exact_grid(path)
    seen = bench.seen_floor(path, nav.shape, res, origin)
    occupancy = np.load(path / "gt" / "navigable.npz")["occupancy"]
    assert seen.any() and (nav & seen).sum() > 0.5 * nav.sum()
    # Closing may bridge a wall one cell wide between two seen floors; nothing far outside the floor is seen.
    far_outside = ndimage.binary_erosion(occupancy == 0, iterations=3)
    assert not (seen & far_outside).any()
