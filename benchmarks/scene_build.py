"""Scene construction benchmark: encoding speed, Gaussians per scene vs frames for both voxel policies,
and the held-out PSNR of the identity renderer for each (speed and size against error).

Data: the HM3D sample (``../shared/data``, read in place) when present, else a procedural capture.
Frames are fused in order of distance to a held-out target frame; after 1, 2, 4, 8, 16 frames the
scene is splatted at the held-out pose(s) and compared with the real panorama there.
Timings: median of several runs after a warm-up; the fusion ratio compares the vectorised
:func:`fuse` with a plain-Python dictionary reference run in the same process, and the best-view
selection's compiled kernel is timed against its torch loop in the same process (the masks must be
equal).
Writes ``reports/scene_build.json`` and ``reports/scene_build.md``.
Run: ``.venv/bin/python benchmarks/scene_build.py [--frames 16] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report
from image2sim.simulator.gaussians import GaussianEncoder, GaussianScene, tiny
from image2sim.simulator.gaussians.encoder import identity_gaussians
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.fusion import cell_sizes, fuse
from image2sim.simulator.gaussians.views import best_view_mask, extent_points, own_geometry, view_map
from image2sim.simulator.io.registry import open_capture

ROOT = Path(__file__).resolve().parents[1]
HM3D = (
    Path(os.environ.get("IMAGE2SIM_SHARED_DATA", ROOT.parent / "shared" / "data"))
    / "hm3d_360"
    / "00000-kfPV7w3FaU5"
)


def median_time(fn, repeats: int) -> float:
    """Median wall seconds of ``repeats`` runs after one warm-up."""
    return time_it(fn, warmup=1, repeats=repeats).wall


def reference_fuse_fixed(means: np.ndarray, colors: np.ndarray, size: float) -> int:
    """Plain-Python voxel averaging (dict of cells) of the fixed policy: the speed reference."""
    cells: dict[tuple, list] = {}
    for p, c in zip(means, colors, strict=True):
        key = (int(np.floor(p[0] / size)), int(np.floor(p[1] / size)), int(np.floor(p[2] / size)))
        acc = cells.setdefault(key, [np.zeros(3), np.zeros(3), 0])
        acc[0] += p
        acc[1] += c
        acc[2] += 1
    return len(cells)


def capture_path(tmp: Path) -> tuple[Path, str]:
    if HM3D.is_dir():
        return HM3D, "HM3D 00000-kfPV7w3FaU5 (86 panoramas, 1024x512)"
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    sc = preset("tiny")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=20, height=128, width=256))
    out = tmp / "procedural"
    if not out.exists():
        write_scene(generate_scene(sc, seed=0), out)
    return out, "procedural tiny scene (20 panoramas, 256x128)"


def best_view_timing(cap, cfg, repeats: int, n_frames: int) -> dict | None:
    """The default selection (``keep_best``'s arguments) of the first ``n_frames`` frames against every
    frame of the capture: median seconds of the torch loop and of the compiled kernel, and whether
    their masks are equal. None when the kernel does not build here."""
    from image2sim.simulator.splatting.backends import cpu_kernel

    if not cpu_kernel.available():
        return None
    h, w, fusion = cfg.encoder.height, cfg.encoder.width, cfg.fusion
    prepared = [prepare_frame(cap[i], h, w, fusion.edge_tolerance) for i in range(len(cap))]
    views = [view_map(f, fusion) for f in prepared]
    calls = []
    for own in range(min(n_frames, len(prepared))):
        g = identity_gaussians(prepared[own], cfg)
        iv, normals = own_geometry(g.means, views[own])
        extent = extent_points(g, fusion.carve_extent) if fusion.carve_extent > 0 else None
        args = (g.means, iv, normals, own, views, fusion.same_surface_tolerance, fusion.interval_step)
        kw = dict(carve_views=fusion.carve_views, owner_cos=fusion.owner_cos, extent=extent)
        calls.append((args, kw))

    def run(backend: str) -> list[torch.Tensor]:
        return [best_view_mask(*a, **kw, backend=backend) for a, kw in calls]

    equal = all(torch.equal(a, b) for a, b in zip(run("torch"), run("cpu"), strict=True))
    t_torch = time_it(lambda: run("torch"), warmup=1, repeats=repeats)
    t_cpu = time_it(lambda: run("cpu"), warmup=1, repeats=repeats)
    return {
        "frames": len(calls),
        "views": len(views),
        "gaussians": sum(len(a[0]) for a, _ in calls),
        "carve_views": fusion.carve_views,
        "torch_s": t_torch.wall,
        "kernel_s": t_cpu.wall,
        "speedup": t_torch.wall / t_cpu.wall,
        "masks_equal": equal,
    }


def best_view_lines(b: dict | None) -> list[str]:
    if b is None:
        return ["The compiled CPU kernel does not build on this machine: not measured."]
    return [
        "| frames x views | Gaussians | `carve_views` | torch loop s | kernel s | speed-up | masks equal |",
        "|---|---|---|---|---|---|---|",
        f"| {b['frames']} x {b['views']} | {b['gaussians']} | {b['carve_views']} | {b['torch_s']:.3f} | "
        f"{b['kernel_s']:.3f} | {b['speedup']:.1f}x | {b['masks_equal']} |",
    ]


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--targets", type=int, nargs="*", default=[0, 40])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--best-view-frames", type=int, default=4, help="frames whose best-view selection is timed"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = tiny()
    h, w = cfg.encoder.height, cfg.encoder.width
    path, source = capture_path(Path("/tmp/image2sim_bench"))
    cap = open_capture(path)
    targets = [t for t in args.targets if t < len(cap)] or [0]
    poses = cap.poses if cap.poses is not None else np.stack([f.cam_to_world for f in cap])
    # Frames in order of distance to the nearest held-out target, so every target gains coverage.
    dist = np.min([np.linalg.norm(poses[:, :3, 3] - poses[t, :3, 3], axis=1) for t in targets], axis=0)
    order = [int(i) for i in np.argsort(dist, kind="stable") if int(i) not in targets][: args.frames]
    frames = {i: prepare_frame(cap[i], h, w) for i in order + targets}

    # --- encoding speed ---------------------------------------------------------------------------
    raw = cap[order[0]]
    t_prepare = median_time(lambda: prepare_frame(raw, h, w), args.repeats)
    f0 = frames[order[0]]
    t_identity = median_time(lambda: identity_gaussians(f0, cfg), args.repeats)
    enc = GaussianEncoder(cfg).eval()
    with torch.no_grad():
        t_learned = median_time(lambda: enc([f0]), args.repeats)
    encoding = {
        "prepare_frame_s": t_prepare,
        "identity_s": t_identity,
        "learned_tiny_s": t_learned,
        "identity_frames_per_s": 1.0 / (t_prepare + t_identity),
        "learned_tiny_frames_per_s": 1.0 / (t_prepare + t_learned),
        "learned_params": sum(p.numel() for p in enc.parameters()),
    }

    # --- fusion speed vs a Python reference --------------------------------------------------------
    g0 = identity_gaussians(f0, cfg)
    fixed = dataclasses.replace(cfg.fusion, policy="fixed", voxel_size=0.05)
    t_fast = median_time(lambda: fuse(g0, fixed), args.repeats)
    m, c = g0.means.double().numpy(), g0.colors.double().numpy()
    t_ref = median_time(lambda: reference_fuse_fixed(m, c, 0.05), 1)
    assert reference_fuse_fixed(m, c, 0.05) == len(fuse(g0, fixed))
    fusion_speed = {
        "points": len(g0),
        "fuse_s": t_fast,
        "python_reference_s": t_ref,
        "speedup": t_ref / t_fast,
    }

    # --- best-view selection: compiled kernel vs the torch loop ----------------------------------------
    best_view_speed = best_view_timing(cap, cfg, args.repeats, args.best_view_frames)

    # --- Gaussians vs frames, held-out PSNR, per policy ---------------------------------------------
    policies = {
        "footprint": cfg.fusion,
        "footprint x2": dataclasses.replace(cfg.fusion, footprint_factor=2.0),
        "fixed 2 cm": dataclasses.replace(cfg.fusion, policy="fixed", voxel_size=0.02),
        "fixed 5 cm": dataclasses.replace(cfg.fusion, policy="fixed", voxel_size=0.05),
    }
    checkpoints = [n for n in (1, 2, 4, 8, 16, 32) if n <= len(order)]
    rows = []
    for name, fusion in policies.items():
        scene = GaussianScene(fusion)
        t_fuse = 0.0
        for n_done, i in enumerate(order, start=1):
            g = identity_gaussians(frames[i], cfg)
            t0 = time.perf_counter()
            scene.integrate(g, frame_id=str(i), index=i)
            t_fuse += time.perf_counter() - t0
            if n_done in checkpoints:
                ps, cov, t_render = [], [], []
                for t in targets:
                    ft = frames[t]
                    t0 = time.perf_counter()
                    out = scene.render(ft.camera, ft.cam_to_world.float())
                    t_render.append(time.perf_counter() - t0)
                    ps.append(psnr(out.rgb[0], ft.rgb[0]))
                    cov.append(float((out.alpha > 0.5).float().mean()))
                rows.append(
                    {
                        "policy": name,
                        "frames": n_done,
                        "gaussians": len(scene),
                        "fuse_s_cumulative": t_fuse,
                        "render_s": statistics.median(t_render),
                        "psnr_db": float(np.mean(ps)),
                        "coverage": float(np.mean(cov)),
                        "psnr_db_per_target": ps,
                        "coverage_per_target": cov,
                    }
                )
                print(rows[-1], flush=True)

    result = {
        "hardware": f"{hardware()}; load average {load_average():.1f} at start",
        "source": source,
        "resolution": f"{w}x{h}",
        "held_out_targets": targets,
        "frame_order": order,
        "repeats": args.repeats,
        "encoding": encoding,
        "fusion_speed": fusion_speed,
        "best_view_speed": best_view_speed,
        "footprint_levels_m": cell_sizes(cfg.fusion),
        "rows": rows,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
    }
    md = [
        "# Scene construction benchmark (`benchmarks/scene_build.py`)",
        "",
        f"- Hardware: {result['hardware']}",
        f"- Data: {source}; encoder input {w}x{h}; held-out targets {targets}; frames fused in order of "
        f"distance to the nearest target: {order}",
        f"- Timings: median of {args.repeats} runs after a warm-up",
        "",
        "## Encoding (per frame)",
        "",
        "| stage | seconds | frames/s |",
        "|---|---|---|",
        f"| read + resize (`prepare_frame`) | {t_prepare:.4f} | |",
        f"| identity Gaussians | {t_identity:.4f} | {encoding['identity_frames_per_s']:.2f} (incl. resize) |",
        f"| learned tiny encoder ({encoding['learned_params'] / 1e6:.2f} M params, no semantic) | "
        f"{t_learned:.4f} | "
        f"{encoding['learned_tiny_frames_per_s']:.2f} (incl. resize) |",
        "",
        "## Fusion speed",
        "",
        "| points | `fuse` (fixed 5 cm) s | plain-Python reference s | speed-up |",
        "|---|---|---|---|",
        f"| {fusion_speed['points']} | {t_fast:.4f} | {t_ref:.3f} | {fusion_speed['speedup']:.1f}x |",
        "",
        "## Best-view selection speed (compiled kernel vs the torch loop, same process)",
        "",
        *best_view_lines(best_view_speed),
        "",
        "## Gaussians vs frames and held-out identity PSNR",
        "",
        "| policy | frames | Gaussians | cumulative fuse s | render s | PSNR dB (mean; per target) | "
        "alpha>0.5 coverage (mean; per target) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        md.append(
            f"| {r['policy']} | {r['frames']} | {r['gaussians']} | {r['fuse_s_cumulative']:.2f} | "
            f"{r['render_s']:.3f} | {r['psnr_db']:.2f}; "
            + ", ".join(f"{p:.2f}" for p in r["psnr_db_per_target"])
            + f" | {r['coverage']:.3f}; "
            + ", ".join(f"{c:.3f}" for c in r["coverage_per_target"])
            + " |"
        )
    write_report("scene_build", rows, {k: v for k, v in result.items() if k != "rows"}, markdown=md)
    print("\n".join(md))


if __name__ == "__main__":
    main()
