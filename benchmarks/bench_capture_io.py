"""Benchmark the capture I/O hot paths against straightforward references run in the same process.

Cases: back-projecting one 1024x512 panorama (ours: cached unit-depth map + dense float32 torch;
reference: numpy float64 gather-then-transform), fusing 8 frames (ours: streaming per-voxel sums;
reference: one-shot ``voxel_downsample`` of all points concatenated, which must hold them all), the
Realsee half-pixel resampling of a 1600x800 colour panorama (ours: numpy bilinear; reference:
``cv2.remap``), and reading one frame of the real HM3D sample when ``../shared/data`` exists.

Writes ``reports/bench_capture_io.json`` and ``.md`` (median of several runs after one warm-up,
hardware string). Run: ``.venv/bin/python benchmarks/bench_capture_io.py``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch
from harness import hardware, time_it, utc_now, write_report
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.geometry.voxel import voxel_downsample
from image2sim.simulator.io import Frame, open_capture
from image2sim.simulator.io.fusion import VoxelAccumulator, backproject_frame
from image2sim.simulator.io.realsee import _source_coords
from image2sim.simulator.io.resample import sample_rgb

ROOT = Path(__file__).resolve().parents[1]
HM3D = (
    Path(os.environ.get("IMAGE2SIM_SHARED_DATA", ROOT.parent / "shared" / "data"))
    / "hm3d_360"
    / "00000-kfPV7w3FaU5"
)


def timeit(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time (s) of ``repeats`` runs after one warm-up."""
    return time_it(fn, warmup=1, repeats=repeats).wall


def synthetic_frames(n: int, h: int = 512, w: int = 1024, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    cam = EquirectCamera(h, w)
    frames = []
    for i in range(n):
        depth = rng.uniform(0.5, 6.0, size=(h, w)).astype(np.float32)
        depth[rng.random((h, w)) < 0.01] = 0
        pose = np.eye(4)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        pose[:3, :3] = q * np.sign(np.linalg.det(q))
        pose[:3, 3] = rng.uniform(-2, 2, size=3)
        rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        frames.append(Frame(rgb=rgb, depth=depth, camera=cam, cam_to_world=pose, frame_id=str(i)))
    return frames


def reference_backproject(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """numpy float64: ray map from scratch, gather valid pixels, then rotate/translate."""
    rays = frame.camera.ray_map(torch.float64).permute(1, 2, 0).reshape(-1, 3).numpy()
    depth = frame.depth.reshape(-1)
    idx = np.flatnonzero(depth > 0)
    pts = rays[idx] * depth[idx, None].astype(np.float64)
    pose = frame.cam_to_world
    return pts @ pose[:3, :3].T + pose[:3, 3], frame.rgb.reshape(-1, 3)[idx]


def main() -> None:
    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    rows = []
    source = "real HM3D frames" if HM3D.is_dir() else "synthetic frames"
    frames = list(open_capture(HM3D)[:8]) if HM3D.is_dir() else synthetic_frames(8)

    ours = timeit(lambda: backproject_frame(frames[0]), 5)
    ref = timeit(lambda: reference_backproject(frames[0]), 5)
    a, _ = backproject_frame(frames[0])
    b, _ = reference_backproject(frames[0])
    err = float(np.abs(a - b).max())
    rows.append(
        {
            "case": f"backproject 1024x512 equirect ({source})",
            "ours_ms": ours * 1e3,
            "reference": "numpy float64 gather + transform",
            "reference_ms": ref * 1e3,
            "note": f"max |diff| {err:.2e} m",
        }
    )

    def fuse_stream():
        acc = VoxelAccumulator(0.05)
        for f in frames:
            acc.add(*backproject_frame(f))
        return acc.result()

    def fuse_oneshot():
        pts, cols = zip(*(backproject_frame(f) for f in frames), strict=False)
        return voxel_downsample(
            torch.from_numpy(np.concatenate(pts)),
            0.05,
            {"rgb": torch.from_numpy(np.concatenate(cols).astype(np.float32))},
        )

    ours = timeit(fuse_stream, 3)
    ref = timeit(fuse_oneshot, 3)
    n_vox = len(fuse_stream()[0])
    rows.append(
        {
            "case": f"fuse 8 frames, 5 cm voxels ({source}; {n_vox} voxels)",
            "ours_ms": ours * 1e3,
            "reference": "one-shot voxel_downsample of all points",
            "reference_ms": ref * 1e3,
            "note": "streaming keeps only per-voxel sums in memory",
        }
    )

    rgb = np.random.default_rng(1).integers(0, 256, size=(800, 1600, 3), dtype=np.uint8)
    uu, vv = _source_coords(800, 1600, 800, 1600)
    map_x, map_y = (uu - 0.5).astype(np.float32), (vv - 0.5).astype(np.float32)
    ours = timeit(lambda: sample_rgb(rgb, uu, vv, wrap_u=True), 5)
    ref = timeit(lambda: cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP), 5)
    rows.append(
        {
            "case": "realsee half-pixel resample, 1600x800 rgb",
            "ours_ms": ours * 1e3,
            "reference": "cv2.remap bilinear (wraps rows too)",
            "reference_ms": ref * 1e3,
            "note": "ours wraps longitude only and clamps latitude",
        }
    )

    if HM3D.is_dir():
        cap = open_capture(HM3D)
        ours = timeit(lambda: cap[0], 5)
        rows.append(
            {
                "case": "hm3d_360 frame read (rgb + depth PNG 1024x512, checks)",
                "ours_ms": ours * 1e3,
                "reference": "–",
                "reference_ms": None,
                "note": "",
            }
        )

    report = {"hardware": hardware(), "measured": utc_now(), "method": "median wall time after 1 warm-up"}
    lines = [
        "# Capture I/O benchmarks",
        "",
        f"Hardware: {report['hardware']}  ",
        f"Measured {report['measured']}, median wall time, 1 warm-up "
        "(machine shared with other jobs: expect noise).",
        "",
        "| case | ours (ms) | reference | reference (ms) | speed-up | note |",
        "|---|---:|---|---:|---:|---|",
    ]
    for r in rows:
        ref_ms = "–" if r["reference_ms"] is None else f"{r['reference_ms']:.1f}"
        speed = "–" if r["reference_ms"] is None else f"{r['reference_ms'] / r['ours_ms']:.1f}x"
        lines.append(
            f"| {r['case']} | {r['ours_ms']:.1f} | {r['reference']} | {ref_ms} | {speed} | {r['note']} |"
        )
    write_report("bench_capture_io", rows, report, markdown=lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
