"""Benchmark the geometry hot paths against straightforward numpy references run in the same process.

Writes ``reports/bench_geometry.json`` and ``reports/bench_geometry.md`` (median of several timed
runs after one warm-up; hardware string included). Run: ``.venv/bin/python benchmarks/bench_geometry.py``.
Numbers depend on machine load: the ratio column compares against a reference timed in the same run.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

import numpy as np
import torch
from harness import hardware, time_it, utc_now, write_report
from image2sim.simulator.geometry import (
    EquirectCamera,
    equirect_to_cubemap,
    perspective_from_equirect,
    point_normals,
    sobel_normals,
    voxel_downsample,
)


def timeit(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time in seconds of ``repeats`` runs after one warm-up run."""
    return time_it(fn, warmup=1, repeats=repeats).wall


# --- numpy references ---------------------------------------------------------------------------


def numpy_perspective(pano: np.ndarray, yaw: float, pitch: float, hfov: float, vfov: float, h: int, w: int):
    """Per-pixel direction -> (lon, lat) -> bilinear lookup (seam wrap, clamped rows), vectorised numpy."""
    C, H, W = pano.shape
    fx = (w / 2) / math.tan(math.radians(hfov) / 2)
    fy = (h / 2) / math.tan(math.radians(vfov) / 2)
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack(((jj - w / 2) / fx, (ii - h / 2) / fy, np.ones_like(jj)), axis=-1)
    y, p = math.radians(yaw), math.radians(pitch)
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    d = d @ (ry @ rx).T
    lon = np.arctan2(d[..., 0], d[..., 2])
    lat = np.arctan2(-d[..., 1], np.hypot(d[..., 0], d[..., 2]))
    gx = (lon + math.pi) / (2 * math.pi) * W - 0.5
    gy = np.clip((math.pi / 2 - lat) / math.pi * H - 0.5, 0, H - 1)
    x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
    tx, ty = gx - x0, gy - y0
    y1 = np.minimum(y0 + 1, H - 1)
    x0w, x1w = x0 % W, (x0 + 1) % W
    return (
        (1 - ty) * (1 - tx) * pano[:, y0, x0w]
        + (1 - ty) * tx * pano[:, y0, x1w]
        + ty * (1 - tx) * pano[:, y1, x0w]
        + ty * tx * pano[:, y1, x1w]
    )


def scipy_sobel_normals(depth: np.ndarray) -> np.ndarray:
    """The paper's estimator with scipy.ndimage (seam wrap, edge rows replicated)."""
    from scipy import ndimage

    smooth = ndimage.uniform_filter(depth, size=3, mode=("nearest", "wrap"))
    binomial, derivative = np.array([1.0, 4, 6, 4, 1]), np.array([-1.0, -2, 0, 2, 1]) / 48.0
    # Separable 5x5 Sobel: rows (axis 0) replicate at the edges, columns (axis 1) wrap.
    gu = ndimage.correlate1d(
        ndimage.correlate1d(smooth, binomial, axis=0, mode="nearest"), derivative, axis=1, mode="wrap"
    )
    gv = ndimage.correlate1d(
        ndimage.correlate1d(smooth, derivative, axis=0, mode="nearest"), binomial, axis=1, mode="wrap"
    )
    n = np.stack((-gu, -gv, np.full_like(gu, 0.5)))
    return n / np.sqrt((n * n).sum(axis=0))


def numpy_voxel(points: np.ndarray, colours: np.ndarray, size: float):
    keys = np.floor(points / size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    out = np.zeros((len(counts), 3))
    col = np.zeros((len(counts), 3))
    np.add.at(out, inverse, points)
    np.add.at(col, inverse, colours)
    return out / counts[:, None], col / counts[:, None]


def main() -> None:
    # One thread by default: numpy references are single-threaded, and on a shared 2-core machine
    # torch's thread synchronisation dominates under load. Override with BENCH_THREADS.
    torch.set_num_threads(int(os.environ.get("BENCH_THREADS", "1")))
    rng = np.random.default_rng(0)
    results = []

    pano_np = rng.random((3, 512, 1024), dtype=np.float32)
    pano = torch.from_numpy(pano_np)[None]
    for name, hfov, vfov, h, w in (
        ("perspective 90x90 336x336", 90.0, 90.0, 336, 336),
        ("ultra-wide 180x118 512x336 (equirect crop)", 180.0, 118.0, 336, 512),
    ):
        view = (30.0, 10.0, hfov, vfov, h, w)
        ours = timeit(lambda v=view: perspective_from_equirect(pano, *v), 7)
        ref = None
        if hfov < 180:
            ref = timeit(lambda v=view: numpy_perspective(pano_np, *v), 5)
        results.append(
            {
                "case": f"{name} from 1024x512 pano, float32",
                "seconds": ours,
                "reference": "numpy bilinear lookup" if ref else None,
                "reference_seconds": ref,
            }
        )

    ours = timeit(lambda: equirect_to_cubemap(pano, 256), 5)
    results.append(
        {
            "case": "equirect_to_cubemap 1024x512 -> 6x256x256",
            "seconds": ours,
            "reference": None,
            "reference_seconds": None,
        }
    )

    depth = torch.from_numpy(rng.uniform(0.5, 8.0, size=(1, 1, 512, 1024)).astype(np.float32))
    cam = EquirectCamera(512, 1024)
    depth_np = depth[0, 0].numpy()
    results.append(
        {
            "case": "sobel_normals 1024x512 (circular), float32",
            "seconds": timeit(lambda: sobel_normals(depth, circular=True), 7),
            "reference": "scipy.ndimage filters",
            "reference_seconds": timeit(lambda: scipy_sobel_normals(depth_np), 5),
        }
    )
    results.append(
        {
            "case": "point_normals 1024x512 equirect, float32",
            "seconds": timeit(lambda: point_normals(depth, cam), 7),
            "reference": None,
            "reference_seconds": None,
        }
    )

    n = 1_000_000
    pts_np = rng.uniform(-5, 5, size=(n, 3))
    col_np = rng.random((n, 3))
    pts, col = torch.from_numpy(pts_np), torch.from_numpy(col_np)
    ours = timeit(lambda: voxel_downsample(pts, 0.05, {"rgb": col}), 5)
    ref = timeit(lambda: numpy_voxel(pts_np, col_np, 0.05), 3)
    results.append(
        {
            "case": "voxel_downsample 1M points + rgb, 5 cm, float64",
            "seconds": ours,
            "reference": "numpy unique(axis=0) + add.at",
            "reference_seconds": ref,
        }
    )

    for r in results:
        r["speedup_vs_reference"] = (
            (r["reference_seconds"] / r["seconds"]) if r["reference_seconds"] else None
        )
    meta = {"hardware": hardware(), "statistic": "median wall time, 1 warm-up", "date_utc": utc_now()}
    report = {**meta, "results": results}

    lines = [
        "# Geometry benchmarks",
        "",
        f"Hardware: {report['hardware']}  ",
        f"Measured {report['date_utc']}, "
        f"{report['statistic']} (machine shared with other jobs: expect noise).",
        "",
        "| case | ours (ms) | reference | reference (ms) | speed-up |",
        "|---|---:|---|---:|---:|",
    ]
    for r in results:
        ref_ms = f"{1e3 * r['reference_seconds']:.1f}" if r["reference_seconds"] else "–"
        speed = f"{r['speedup_vs_reference']:.1f}x" if r["speedup_vs_reference"] else "–"
        lines.append(
            f"| {r['case']} | {1e3 * r['seconds']:.1f} | {r['reference'] or '–'} | {ref_ms} | {speed} |"
        )
    meta = {"benchmark": "geometry", **meta}
    write_report("bench_geometry", results, meta, markdown=lines, rows_key="results")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
