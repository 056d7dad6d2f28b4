"""What refinement does to the observations a policy trains on: the splat at agent poses against the
exact renderer, feed-forward and refined, on the sim-to-real pipeline's kind of house (procedural
preset ``default``, noise tier ``middle``, seeds 0-2, 8 agent poses each at task starts, 128x256
panoramas, identity Gaussians of the ``tiny`` preset). Prints PSNR and depth AbsRel per house and
refinement length (one refinement run read at each), then the means over the houses.

Run from the repository root: ``.venv/bin/python scripts/refined_agent_views.py`` (~4 min on 2 cores).
docs/scenes.md, "Per-scene refinement".
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, "benchmarks")

import numpy as np
import torch
from image2sim.dataengine.procedural.render import render as exact_render
from image2sim.simulator.gaussians import build_scene, tiny
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.refine import RefineConfig, default_refine_steps, refine_gaussians
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.registry import open_capture
from image2sim.simulator.sim import GaussianRenderFn, gaussian_tensors
from scene_density import _fidelity, agent_poses, house

CAMERA = EquirectCamera(128, 256)


def one_house(seed: int, tmp: Path) -> dict[str, tuple[float, float]]:
    """Refinement length ("0", "50", "100" and "default", two steps per frame up to 50) -> (mean PSNR
    dB, mean depth AbsRel) at the house's agent poses."""
    capture, scene = house(tmp, "default", seed, "middle")
    cams = agent_poses("default", seed, 8)
    targets = []
    for pose in cams:
        e = exact_render(scene, CAMERA, pose)
        targets.append((e["rgb"].astype(np.float32) / 255.0, e["depth"].astype(np.float32)))
    gs = build_scene(capture, tiny(), encoder="identity")
    cap = open_capture(capture)
    enc = gs.info["encoding"]
    h, w = enc["height"], enc["width"]
    views = [prepare_frame(cap[f["index"]], h, w, gs.fusion.edge_tolerance) for f in gs.frames]
    default = default_refine_steps(len(gs.frames))
    out: dict[str, tuple[float, float]] = {}

    def score(gaussians, steps: int) -> None:
        fn = GaussianRenderFn(gaussian_tensors(gaussians))
        psnr, absrel = _fidelity([fn(CAMERA, c) for c in cams], targets)
        value = (statistics.fmean(psnr), statistics.fmean(absrel))
        out[str(steps)] = value
        if steps == default:
            out["default"] = value
        print(seed, steps, "(default)" if steps == default else "", [round(v, 4) for v in value], flush=True)

    score(gs.gaussians, 0)
    counts = sorted({default, 50, 100})
    refine_gaussians(
        gs.gaussians,
        views,
        RefineConfig(steps=max(counts)),
        checkpoints=counts,
        on_checkpoint=lambda k, g, _s: score(g, k),
    )
    return out


def main() -> None:
    torch.set_num_threads(2)
    results: dict[str, list[tuple[float, float]]] = {}
    for seed in (0, 1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            for label, value in one_house(seed, Path(tmp)).items():
                results.setdefault(label, []).append(value)
    for label, values in results.items():
        psnr = statistics.fmean(v[0] for v in values)
        absrel = statistics.fmean(v[1] for v in values)
        print(f"refine {label}: PSNR {psnr:.2f} dB, depth AbsRel {absrel:.4f} over {len(values)} houses")


if __name__ == "__main__":
    main()
