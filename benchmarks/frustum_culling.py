"""Pinhole views with and without block frustum culling (``splatting/culling.py``), same images.

A pinhole view of a room-scale scene sees a small part of it, yet the fused CPU splat projects every
Gaussian to cull it. ``FrustumBlocks`` (built once per scene) culls spatial blocks of 64 Gaussians
against a conservative bound of the kernel's own cull, and the kernel skips their Gaussians before
transforming them. Per case: ms per view for ``GaussianRenderFn`` as the simulator and the data
engine call it (one thread), with the blocks (``blocks``, now) and without (``no blocks``, the same
kernel with the block cull switched off); the two run interleaved, pass by pass, and each takes the
median of ``--repeats`` passes over the poses after a warm-up. Also: the share of Gaussians in kept
blocks, the share the splat itself keeps (reference projection), the blocks' build time, and
whether every image is bit-identical.

Cases: the HM3D sample's identity Gaussians (the data engine's 336 px view; cameras at capture
centres, random headings; skipped without ``../shared``) and a sim2real training house (64 px).
Writes ``reports/frustum_culling.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/frustum_culling.py [--poses 12] [--repeats 5] [--quick]``.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch
from harness import _table, hardware, load_average, write_report
from splat_early_finish import HM3D, pinhole_cases, pose_args

NAME = "frustum_culling"


def run_case(name: str, tensors: dict, poses: list[np.ndarray], px: int, repeats: int) -> dict:
    from image2sim.simulator.geometry.cameras import PinholeCamera
    from image2sim.simulator.sim import GaussianRenderFn
    from image2sim.simulator.splatting.culling import FrustumBlocks
    from image2sim.simulator.splatting.project import project_gaussians

    camera = PinholeCamera(px / 2, px / 2, px / 2, px / 2, px, px)  # 90 degrees
    t0 = time.perf_counter()
    blocks = FrustumBlocks(tensors["means"], tensors["scales"])
    build_s = time.perf_counter() - t0
    with_blocks = GaussianRenderFn(tensors)
    with_blocks._blocks = blocks
    without = GaussianRenderFn(tensors)
    without._cull = lambda camera: None
    outs = {"blocks": [], "no blocks": []}
    walls = {"blocks": [], "no blocks": []}
    for rep in range(repeats + 1):  # the first pass of each is the warm-up
        for variant, fn in (("blocks", with_blocks), ("no blocks", without)):
            t0 = time.perf_counter()
            images = [fn(camera, pose) for pose in poses]
            if rep:
                walls[variant].append(time.perf_counter() - t0)
            outs[variant] = images
    identical = all(
        np.array_equal(a["rgb"], b["rgb"]) and np.array_equal(a["depth"], b["depth"])
        for a, b in zip(outs["blocks"], outs["no blocks"], strict=True)
    )
    kept, visible = [], []
    for pose in poses:
        k = blocks.keep(camera, pose)
        kept.append(1.0 if k is None else float(k[1][k[0]].float().mean()))
        p = torch.as_tensor(pose, dtype=tensors["means"].dtype)
        proj = project_gaussians(
            tensors["means"], tensors["scales"], tensors["quats"], tensors["opacities"], camera, p
        )
        visible.append(float(proj.valid.float().mean()))
    ms = {v: 1000.0 * statistics.median(w) / len(poses) for v, w in walls.items()}
    row = {
        "case": name,
        "view": f"pinhole {px}",
        "Gaussians": int(tensors["means"].shape[0]),
        "blocks": len(blocks.radii),
        "build s": round(build_s, 2),
        "in kept blocks": round(float(np.median(kept)), 3),
        "splat keeps": round(float(np.median(visible)), 3),
        "ms/view blocks": round(ms["blocks"], 1),
        "ms/view no blocks": round(ms["no blocks"], 1),
        "speed-up": round(ms["no blocks"] / ms["blocks"], 2),
        "identical": identical,
        "passes ms/view": {v: [round(1000.0 * w / len(poses), 1) for w in ws] for v, ws in walls.items()},
    }
    print(row, flush=True)
    return row


def main() -> None:
    args, poses, repeats = pose_args(__doc__, 12, 5, (2, 1), "2 poses, 1 repeat, the procedural house only")
    load_start, hw = load_average(), hardware()
    rows = [run_case(*case, repeats) for case in pinhole_cases(poses, args.seed, args.quick)]
    hm3d = HM3D.is_dir() and not args.quick
    meta = {
        "load_average_start": load_start,
        "load_average_end": load_average(),
        "poses": poses,
        "repeats": repeats,
        "hm3d": hm3d,
    }
    lines = [
        "# Pinhole views with and without block frustum culling (`benchmarks/frustum_culling.py`)",
        "",
        f"- Hardware: {hw}; load average {load_start:.1f} at start, {load_average():.1f} at end.",
        f"- {poses} poses per case, one thread; ms/view: median of {repeats} passes after a warm-up, the "
        "two variants interleaved pass by pass. `no blocks` is the same kernel with the block cull off.",
        "- `in kept blocks`: share of the Gaussians the kernel still transforms; `splat keeps`: share the "
        "splat itself keeps (reference projection: in front, footprint on the image). Medians over poses.",
        "",
        *_table(rows),
        "",
    ]
    write_report(NAME, rows, meta, markdown=lines)


if __name__ == "__main__":
    main()
