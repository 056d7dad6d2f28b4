"""Gaussian density against splat speed and fidelity: how many Gaussians a simulator scene needs.

The neural simulator's per-frame cost on the sim2real pipeline's houses is dominated by splatting the
panorama the pixel-flow renderer conditions on, and the splat's cost follows the number of Gaussians.
The voxel fusion's ``fusion.footprint_factor`` sets the density (1 = about one Gaussian per capture
pixel's footprint, the default; 2 and 4 fuse coarser). This benchmark measures, on one procedural
house captured as the sim2real pipeline captures its training houses (``preset('default')``, noise
tier ``middle``), for each factor:

* Gaussians, and the ``build_scene`` time (one run: indicative);
* splat time per frame: the panorama the renderer conditions on (``--pano-height``, default 128x256:
  the tiny renderer's size for 64 px views), at ``--poses`` agent poses (``rollout_scenes.sample_tasks``
  starts on the house's navigation graph), median of ``--repeats`` passes over all poses after one
  warm-up pass, divided by the number of poses;
* fidelity against the exact procedural renderer at the same poses: PSNR of the splatted colour and
  AbsRel of the splatted range on pixels where the exact range is valid (means over poses);
* the ratio of each factor's splat time to the default's, measured in the same run.

The pixel-flow network's time at the same panorama size is measured once for context (an untrained
``PixelFlowRenderer(tiny())``: its speed does not depend on the weights or on the density). With
``--renderer <weights>`` (e.g. the sim2real pipeline's ``outputs/sim2real/renderer``) every factor also
gets the neural frame: splat + one pixel-flow step of those weights, its time per frame and its PSNR
and AbsRel against the exact render (the renderer was trained on scenes of one density; this shows
what it makes of the others). Writes ``reports/scene_density.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/scene_density.py [--factors 1 2 4] [--renderer PATH] [--quick]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report

NAME = "scene_density"
REFERENCE_FACTOR = 1.0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def _timed_pass(fn, camera, cams: list[np.ndarray], repeats: int):
    """Time ``repeats`` passes of ``fn`` over every pose (one warm-up); the timing and the last
    pass's observations."""
    outs: list[dict] = []

    def one_pass() -> None:
        outs[:] = [fn(camera, pose) for pose in cams]

    return time_it(one_pass, warmup=1, repeats=repeats), outs


def _fidelity(outs: list[dict], targets: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list, list]:
    """Per pose: PSNR of the colour, and AbsRel of the range where both ranges are valid."""
    psnr, absrel = [], []
    for out, (rgb, depth) in zip(outs, targets, strict=True):
        psnr.append(_psnr(out["rgb"], rgb))
        valid = (depth > 0) & np.isfinite(depth) & (out["depth"] > 0)
        absrel.append(float(np.mean(np.abs(out["depth"][valid] - depth[valid]) / depth[valid])))
    return psnr, absrel


def house(work: Path, preset_name: str, seed: int, noise: str):
    """The capture (noise tier ``noise``) and the exact scene of one procedural house."""
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    cfg = dataclasses.replace(preset(preset_name), noise=noise)
    scene = generate_scene(cfg, seed=seed)
    capture = write_scene(scene, work / "capture")
    return capture, scene


def agent_poses(preset_name: str, seed: int, n: int) -> list[np.ndarray]:
    """Camera-to-world poses of ``n`` agents at task starts on the house's navigation graph."""
    from image2sim.navpolicy.rollout_scenes import procedural_simulator, sample_tasks

    sim = procedural_simulator(seed, preset_name)
    tasks = sample_tasks(sim, n, np.random.default_rng(seed), scene_id="bench")
    sim.reset(np.stack([t.start for t in tasks]), np.array([t.heading for t in tasks]), observe=False)
    return [np.asarray(sim.camera_pose(i), dtype=np.float64) for i in range(n)]


def run(
    *,
    factors: Sequence[float] = (1.0, 2.0, 4.0),
    preset_name: str = "default",
    seed: int = 0,
    noise: str = "middle",
    poses: int = 8,
    pano_height: int = 128,
    repeats: int = 5,
    threads: int = 1,
    renderer: str | None = None,
) -> tuple[list[dict], dict, list[str]]:
    from image2sim.dataengine.procedural.render import render as exact_render
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians import tiny as gaussians_tiny
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.renderer.config import tiny as renderer_tiny
    from image2sim.simulator.renderer.model import PixelFlowRenderer
    from image2sim.simulator.sim import GaussianRenderFn, PixelFlowRenderFn, gaussian_tensors, load_pixel_flow

    if REFERENCE_FACTOR not in [float(f) for f in factors]:
        raise ValueError(f"factors must include the reference {REFERENCE_FACTOR}, got {list(factors)}")
    if poses < 1 or repeats < 1 or pano_height < 8:
        raise ValueError("poses and repeats must be >= 1 and pano_height >= 8")
    torch.set_num_threads(threads)
    load_start, hw = load_average(), hardware()
    camera = EquirectCamera(pano_height, 2 * pano_height)
    trained = load_pixel_flow(renderer) if renderer else None
    if trained is not None and int(trained.cfg.height) != pano_height:
        raise ValueError(
            f"--renderer {renderer} renders {trained.cfg.height} rows: "
            f"pass --pano-height {trained.cfg.height}"
        )
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_density_") as tmp:
        capture, scene = house(Path(tmp), preset_name, seed, noise)
        cams = agent_poses(preset_name, seed, poses)
        exact = [exact_render(scene, camera, pose) for pose in cams]
        targets = [(e["rgb"].astype(np.float32) / 255.0, e["depth"].astype(np.float32)) for e in exact]
        network_ms = None
        for factor in sorted(float(f) for f in factors):
            base = gaussians_tiny()
            cfg = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, footprint_factor=factor))
            t0 = time.perf_counter()
            gs = build_scene(capture, cfg, encoder="identity")
            build_s = time.perf_counter() - t0
            tensors = gaussian_tensors(gs.gaussians)
            t, outs = _timed_pass(GaussianRenderFn(tensors), camera, cams, repeats)
            psnr, absrel = _fidelity(outs, targets)
            if network_ms is None:
                torch.manual_seed(0)
                flow = PixelFlowRenderFn(tensors, PixelFlowRenderer(renderer_tiny()))
                cond = flow.condition(camera, cams[0])
                net = time_it(
                    lambda cond=cond, flow=flow: flow.model.render(cond, steps=1), warmup=1, repeats=repeats
                )
                network_ms = 1e3 * net.wall
            rows.append(
                {
                    "footprint_factor": factor,
                    "gaussians": int(tensors["means"].shape[0]),
                    "build_s": round(build_s, 2),
                    "splat_ms_per_frame": round(1e3 * t.wall / poses, 1),
                    "splat_cpu_ms_per_frame": round(1e3 * t.cpu / poses, 1),
                    "psnr_vs_exact_db": round(statistics.fmean(psnr), 2),
                    "depth_absrel_vs_exact": round(statistics.fmean(absrel), 4),
                }
            )
            if trained is not None:
                tn, n_outs = _timed_pass(PixelFlowRenderFn(tensors, trained), camera, cams, repeats)
                n_psnr, n_absrel = _fidelity(n_outs, targets)
                rows[-1].update(
                    neural_ms_per_frame=round(1e3 * tn.wall / poses, 1),
                    neural_psnr_vs_exact_db=round(statistics.fmean(n_psnr), 2),
                    neural_depth_absrel_vs_exact=round(statistics.fmean(n_absrel), 4),
                )
    ref = next(r for r in rows if r["footprint_factor"] == REFERENCE_FACTOR)
    for r in rows:
        if "neural_ms_per_frame" in r:
            r["neural_speedup_vs_default"] = round(ref["neural_ms_per_frame"] / r["neural_ms_per_frame"], 2)
        r["splat_speedup_vs_default"] = round(ref["splat_ms_per_frame"] / r["splat_ms_per_frame"], 2)
        r["psnr_change_vs_default_db"] = round(r["psnr_vs_exact_db"] - ref["psnr_vs_exact_db"], 2)
        r["gaussians_vs_default"] = round(r["gaussians"] / ref["gaussians"], 3)
    meta = {
        "hardware": hw,
        "house": f"procedural preset {preset_name!r}, seed {seed}, capture noise tier {noise!r}",
        "panorama": f"{pano_height}x{2 * pano_height}",
        "poses": poses,
        "repeats": repeats,
        "threads": threads,
        "network_ms_per_frame": round(network_ms, 1) if network_ms is not None else None,
        "load_average_start": round(load_start, 2),
        "load_average_end": round(load_average(), 2),
        "reference": f"footprint_factor {REFERENCE_FACTOR} (the default), same run",
        "renderer": renderer,
    }
    return rows, meta, markdown(rows, meta)


def markdown(rows: list[dict], meta: dict) -> list[str]:
    cols = [
        "footprint_factor",
        "gaussians",
        "gaussians_vs_default",
        "build_s",
        "splat_ms_per_frame",
        "splat_speedup_vs_default",
        "psnr_vs_exact_db",
        "psnr_change_vs_default_db",
        "depth_absrel_vs_exact",
    ]
    if rows and "neural_ms_per_frame" in rows[0]:
        cols += [
            "neural_ms_per_frame",
            "neural_speedup_vs_default",
            "neural_psnr_vs_exact_db",
            "neural_depth_absrel_vs_exact",
        ]
    lines = [
        "# Gaussian density against splat speed and fidelity (`benchmarks/scene_density.py`)",
        "",
        f"- Hardware: {meta['hardware']}; load average {meta['load_average_start']} at start, "
        f"{meta['load_average_end']} at end.",
        f"- House: {meta['house']}; identity Gaussians (`gaussians.tiny()`, best-view selection), "
        f"`fusion.footprint_factor` varied.",
        f"- Splat: the {meta['panorama']} panorama the pixel-flow renderer conditions on, at "
        f"{meta['poses']} agent poses; median of {meta['repeats']} passes after one warm-up, per frame. "
        "Fidelity: splatted colour and range against the exact procedural renderer at the same poses.",
        f"- The pixel-flow network at the same size (one step, untrained weights, density-independent): "
        f"{meta['network_ms_per_frame']} ms per frame.",
        *(
            [f"- Neural rows: splat + one pixel-flow step of `{meta['renderer']}`, timed the same way."]
            if meta.get("renderer")
            else []
        ),
        "",
        "| " + " | ".join(cols) + " |",
        "|" + "---|" * len(cols),
    ]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    return lines


def main(argv: Sequence[str] | None = None, reports: str | Path | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--factors", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    ap.add_argument("--preset", default="default", help="procedural house preset (sim2real: default)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", default="middle", help="capture noise tier (sim2real: middle)")
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--pano-height", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--renderer", default=None, help="pixel-flow weights: add the neural frame per factor")
    ap.add_argument("--quick", action="store_true", help="tiny house, 2 poses, 2 repeats (smoke test)")
    args = ap.parse_args(argv)
    if args.quick:
        args.preset, args.poses, args.repeats, args.pano_height = "tiny", 2, 2, 32
    rows, meta, md = run(
        factors=args.factors,
        preset_name=args.preset,
        seed=args.seed,
        noise=args.noise,
        poses=args.poses,
        pano_height=args.pano_height,
        repeats=args.repeats,
        threads=args.threads,
        renderer=args.renderer,
    )
    write_report(NAME, rows, meta, markdown=md, reports=reports)
    print("\n".join(md))
    return {"rows": rows, **meta}


if __name__ == "__main__":
    main()
