"""Benchmark the evaluation metrics against references timed in the same process.

* exact DTW: row-wise (cumsum + running min) vs anti-diagonal vs a pure-Python double loop;
* episode nDTW: the incremental measure vs recomputing DTW from scratch after every step;
* SSIM / PSNR: ours (torch) vs scikit-image with matching settings;
* LPIPS-VGG16 forward (random weights; speed does not depend on the values).

Writes ``reports/bench_eval_metrics.json`` and ``.md`` (median of several timed runs after warm-up,
hardware string included). Run: ``.venv/bin/python benchmarks/bench_eval_metrics.py [--quick]``.
Absolute numbers depend on machine load; the ratio column compares against a reference timed in
the same run.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report
from image2sim.eval.metrics.lpips import LPIPS
from image2sim.eval.metrics.nav import (
    IncrementalNDTW,
    dtw_from_costs,
    dtw_from_costs_antidiagonal,
    ndtw,
    pairwise_distances,
)
from image2sim.eval.metrics.render import psnr, ssim


def python_dtw(cost: np.ndarray) -> float:
    """Textbook O(nm) double loop in pure Python (the reference)."""
    rows = cost.tolist()
    n, m = len(rows), len(rows[0])
    inf = math.inf
    prev = [inf] * (m + 1)
    prev[0] = 0.0
    for i in range(n):
        cur = [inf] * (m + 1)
        ci = rows[i]
        for j in range(1, m + 1):
            best = prev[j] if prev[j] < cur[j - 1] else cur[j - 1]
            if prev[j - 1] < best:
                best = prev[j - 1]
            cur[j] = ci[j - 1] + best
        if i == 0:
            cur[0] = inf
        prev = cur
        prev[0] = inf
    return prev[m]


def walk(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.cumsum(rng.normal(0, 0.25, size=(n, 3)), axis=0)


def seconds(fn: Callable[[], Any], warmup: int, runs: int) -> float:
    """Median wall seconds of ``runs`` timed calls after ``warmup`` untimed ones."""
    return time_it(fn, warmup=warmup, repeats=runs).wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer runs and smaller images")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (default 1: the numpy/scipy references are single-threaded)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    runs = 3 if args.quick else 7
    rng = np.random.default_rng(0)
    rows: list[dict[str, Any]] = []

    def add(name: str, size: str, ours: float, ref_name: str, ref: float | None) -> None:
        rows.append({"case": name, "size": size, "seconds": ours, "reference": ref_name,
                     "reference_seconds": ref, "speedup": None if ref is None else ref / ours})
        print(f"{name:32s} {size:18s} {ours * 1e3:9.3f} ms  vs {ref_name}: "
              f"{'-' if ref is None else f'{ref * 1e3:.3f} ms'}")

    # DTW of one episode-sized pair (agent path 300 points, dense reference 80 points).
    for n, m in ((300, 80), (500, 200)):
        cost = pairwise_distances(walk(n, rng), walk(m, rng))
        assert math.isclose(dtw_from_costs(cost), python_dtw(cost), rel_tol=1e-12)
        assert math.isclose(dtw_from_costs_antidiagonal(cost), python_dtw(cost), rel_tol=1e-12)
        ref = seconds(lambda c=cost: python_dtw(c), 1, runs)
        size = f"{n}x{m}"
        rowwise = seconds(lambda c=cost: dtw_from_costs(c), 2, runs)
        add("dtw row-wise (ours)", size, rowwise, "pure Python", ref)
        anti = seconds(lambda c=cost: dtw_from_costs_antidiagonal(c), 2, runs)
        add("dtw anti-diagonal", size, anti, "pure Python", ref)

    # Episode nDTW: update after every one of T steps.
    path, reference = walk(300, rng), walk(80, rng)

    def incremental() -> float:
        acc = IncrementalNDTW(reference)
        for p in path:
            acc.append(p)
        return acc.value

    def recompute() -> float:
        value = 0.0
        for t in range(1, len(path) + 1):
            value = ndtw(path[:t], reference)
        return value

    assert math.isclose(incremental(), recompute(), rel_tol=1e-12)
    add("episode nDTW incremental", "T=300, m=80", seconds(incremental, 1, runs),
        "recompute each step", seconds(recompute, 1, max(3, runs // 2)))

    # Rendering metrics on a panorama.
    h, w = (256, 512) if args.quick else (512, 1024)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(3, h, w, generator=g, dtype=torch.float64)
    y = (x + 0.05 * torch.randn(3, h, w, generator=g, dtype=torch.float64)).clamp(0, 1)
    try:
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity

        xn, yn = x.numpy(), y.numpy()
        ref_ssim = seconds(lambda: structural_similarity(xn, yn, channel_axis=0, data_range=1.0,
                                                         gaussian_weights=True, sigma=1.5,
                                                         use_sample_covariance=False), 1, runs)
        ref_psnr = seconds(lambda: peak_signal_noise_ratio(yn, xn, data_range=1.0), 1, runs)
        ref_name = "scikit-image"
    except ImportError:
        ref_ssim = ref_psnr = None
        ref_name = "n/a (scikit-image missing)"
    add("ssim (torch, float64)", f"3x{h}x{w}", seconds(lambda: ssim(x, y), 1, runs), ref_name, ref_ssim)
    add("psnr (torch, float64)", f"3x{h}x{w}", seconds(lambda: psnr(x, y), 1, runs), ref_name, ref_psnr)

    # LPIPS forward (random weights).
    lh, lw = (128, 256) if args.quick else (256, 512)
    model = LPIPS()
    xi, yi = torch.rand(1, 3, lh, lw, generator=g), torch.rand(1, 3, lh, lw, generator=g)
    with torch.no_grad():
        add("lpips-vgg16 forward", f"1x3x{lh}x{lw}", seconds(lambda: model(xi, yi), 1, max(3, runs // 2)),
            "-", None)

    load = load_average()  # shared machines: context
    load = None if math.isnan(load) else load
    result = {"benchmark": "eval_metrics", "hardware": hardware(), "runs": runs,
              "load_average_1min": load, "statistic": "median seconds after warm-up", "rows": rows}
    lines = [
        "# Evaluation metrics benchmark",
        "",
        f"Hardware: {result['hardware']}. Median of {runs} timed runs after warm-up "
        "(`benchmarks/bench_eval_metrics.py`). "
        f"1-min load average at the end: {'n/a' if load is None else f'{load:.1f}'} "
        "(absolute times on a shared machine are noisy; compare the ratios).",
        "",
        "| case | size | ours (ms) | reference | reference (ms) | speed-up |",
        "|---|---|---:|---|---:|---:|",
    ]
    for r in rows:
        ref_ms = "–" if r["reference_seconds"] is None else f"{r['reference_seconds'] * 1e3:.2f}"
        speed = "–" if r["speedup"] is None else f"{r['speedup']:.1f}×"
        ours_ms = f"{r['seconds'] * 1e3:.2f}"
        lines.append(f"| {r['case']} | {r['size']} | {ours_ms} | {r['reference']} | {ref_ms} | {speed} |")
    meta = {k: v for k, v in result.items() if k != "rows"}
    paths = write_report("bench_eval_metrics", rows, meta, markdown=lines)
    print(f"wrote {paths[0]} and {paths[1]}")


if __name__ == "__main__":
    main()
