"""Per-view render scoring, summaries with view counts, and the Table-1 style table."""

from __future__ import annotations

import math

import pytest
import torch
from image2sim.eval.metrics.lpips import LPIPS
from image2sim.eval.metrics.nav import AggregationError
from image2sim.eval.metrics.render import psnr, ssim
from image2sim.eval.render_scores import score_views, summarize_views
from image2sim.eval.report import render_table_markdown


def _images(b: int = 3, h: int = 16, w: int = 24, seed: int = 0) -> torch.Tensor:
    return torch.rand(b, 3, h, w, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_score_views_records() -> None:
    x, y = _images(), _images(seed=1)
    depth_t = torch.rand(3, 1, 16, 24, dtype=torch.float64) + 1.0
    recs = score_views(["a", "b", "c"], x, y, pred_depth=depth_t * 1.1, target_depth=depth_t)
    assert [r[0] for r in recs] == ["a", "b", "c"]
    a = recs[0][1]
    assert a["lpips"] is None  # no weights configured: n/a, not 0
    assert a["psnr"] == pytest.approx(psnr(x[0], y[0]).item())
    assert a["ssim"] == pytest.approx(ssim(x[0], y[0]).item())
    assert a["abs_rel"] == pytest.approx(0.1) and a["delta1"] == 1.0
    plain = score_views(["a", "b", "c"], x, y)
    assert set(plain[0][1]) == {"lpips", "psnr", "ssim"}
    with pytest.raises(ValueError, match="2 ids for a batch of 3"):
        score_views(["a", "b"], x, y)
    with pytest.raises(ValueError, match="together"):
        score_views(["a", "b", "c"], x, y, pred_depth=depth_t)


def test_score_views_with_lpips_model() -> None:
    torch.manual_seed(0)
    model = LPIPS()
    for name, p in model.named_parameters():
        if name.startswith("lin"):
            p.data.abs_()
    x = _images(2)
    recs = score_views(["a", "b"], x, x.clone(), lpips_model=model)
    assert recs[0][1]["lpips"] == 0.0 and recs[0][1]["psnr"] == math.inf and recs[0][1]["ssim"] == 1.0


def test_summaries_and_table() -> None:
    x, y = _images(), _images(seed=1)
    cell = summarize_views(score_views(["a", "b", "c"], x, y), fps=45.6, hardware="test cpu")
    assert cell.num_views == 3 and cell.metrics["psnr"].count == 3
    assert cell.metrics["lpips"].mean is None and cell.metrics["lpips"].missing == 3
    perfect = summarize_views(score_views(["a"], x[:1], x[:1]))
    assert perfect.metrics["psnr"].mean == math.inf  # allowed for PSNR, reported as such
    with pytest.raises(AggregationError, match="view b: metric 'ssim' is nan"):
        summarize_views([("a", {"ssim": 0.5}), ("b", {"ssim": math.nan})])
    with pytest.raises(AggregationError, match="view a: appears more than once"):
        summarize_views([("a", {"ssim": 0.5}), ("a", {"ssim": 0.4})])
    table = render_table_markdown([("Pixel flow (1 step)", {"none": cell}), ("Splat only", {"high": cell})],
                                  ["none", "high"])
    lines = table.splitlines()
    none_group = "LPIPS↓ (none) | PSNR↑ (none) | SSIM↑ (none) | FPS↑ (none)"
    assert lines[0].startswith(f"|  | {none_group} | LPIPS↓ (high)")
    first = lines[2].split(" | ")
    assert first[1] == "n/a" and first[4] == "45.6" and first[5:] == ["–", "–", "–", "– |"]
    assert f"{cell.metrics['psnr'].mean:.2f}" in lines[2]
    assert "FPS hardware: test cpu" in table
