"""Scene fidelity benchmark (issue 20): fused identity scenes against their best view, error against time.

For each capture (the HM3D sample from ``../shared/data`` when present, and procedural houses with
noise tier ``middle``) and each fusion variant:

- **held-out**: every 8th frame is left out, the scene is built from the others
  (``build_scene``, the ``tiny`` config at 256x128, the weights-free default path) and splatted at
  the held-out poses: PSNR against the panorama, depth AbsRel on pixels with alpha > 0.5;
- **own pose**: frames kept in the scene are rendered at their own pose, against the single-frame
  scene of the same frame rendered there (the sharpest that frame can give), both scored on the
  pixels the single-frame scene covers (depth holes leave it empty elsewhere);
- **size**: Gaussians, Gaussians per frame, and Gaussians as frames are added (they must saturate);
- **time**: scene build seconds (one run: the quality columns are the point; timings are indicative).

Variants: ``all`` (every frame's Gaussians voxel-averaged: the earlier default), ``best`` (each surface
point from the frame that sees it best, :mod:`image2sim.simulator.gaussians.views`), each with round
or footprint-ellipse identity discs. No learned renderer is involved. ``best + refine N``: the ``best``
scene after N steps of per-scene refinement against its source frames
(:mod:`image2sim.simulator.gaussians.refine`), with the refinement's seconds: error against time.

Writes ``reports/scene_fidelity.json`` and ``reports/scene_fidelity.md``.
Run: ``.venv/bin/python benchmarks/scene_fidelity.py [--houses 2] [--refine 50,200]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch
from harness import hardware, load_average, utc_now, write_report
from image2sim.simulator.config import config_from_dict, parse_overrides
from image2sim.simulator.gaussians import tiny
from image2sim.simulator.gaussians.build import build_scene
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.refine import RefineConfig, refine_scene
from image2sim.simulator.io.registry import open_capture
from image2sim.simulator.renderer.holefill import splat_rgbd

ROOT = Path(__file__).resolve().parents[1]
HM3D = (
    Path(os.environ.get("IMAGE2SIM_SHARED_DATA", ROOT.parent / "shared" / "data"))
    / "hm3d_360"
    / "00000-kfPV7w3FaU5"
)
VARIANTS = {"all (before)": "all", "best (default)": "best"}
MODES = ("raw", "normalised")
"""Splat image modes scored (:func:`~image2sim.simulator.renderer.holefill.splat_rgbd`)."""


def config_for(views: str):
    cfg = tiny()
    return dataclasses.replace(cfg, fusion=dataclasses.replace(cfg.fusion, views=views))


def score(scene, capture, frames: list[int], cfg, masks=None) -> tuple[dict, list[float], list]:
    """PSNR (dB) per splat image mode (``raw``: the composite over black, what ``sim render`` wrote
    until 2026-11-27; ``normalised``: the composite divided by alpha, its default since) and depth
    AbsRel of ``scene`` splatted at each frame's pose, against that frame, and the covered pixels
    (alpha > 0.5). ``masks`` (one per frame) restricts the PSNR to them."""
    h, w = cfg.encoder.height, cfg.encoder.width
    psnrs: dict[str, list[float]] = {mode: [] for mode in MODES}
    absrels, covered = [], []
    for k, i in enumerate(frames):
        inputs = prepare_frame(capture[i], h, w, cfg.fusion.edge_tolerance)
        out = scene.render(inputs.camera, inputs.cam_to_world, background=0.0)
        for mode in MODES:
            rgb, _ = splat_rgbd(out.rgb, out.depth, out.alpha, mode, panoramic=True)
            err = ((rgb[0] - inputs.rgb[0]) ** 2).mean(0)
            mse = float(err[masks[k]].mean()) if masks is not None else float(err.mean())
            psnrs[mode].append(-10 * math.log10(max(mse, 1e-12)))
        depth = (out.depth / out.alpha.clamp_min(1e-6))[0, 0]
        gt = inputs.depth[0, 0]
        m = (gt > 0) & (out.alpha[0, 0] > 0.5)
        absrels.append(float(((depth[m] - gt[m]).abs() / gt[m]).mean()) if bool(m.any()) else float("nan"))
        covered.append(out.alpha[0, 0] > 0.5)
    return psnrs, absrels, covered


def _psnr_columns(prefix: str, psnrs: dict[str, list[float]]) -> dict:
    return {
        f"{prefix}_psnr": round(statistics.fmean(psnrs["normalised"]), 2),
        f"{prefix}_psnr_raw": round(statistics.fmean(psnrs["raw"]), 2),
    }


def surface_area(scene, cell: float = 0.05) -> float:
    """Observed surface area, m^2: occupied cells of a ``cell``-metre grid x cell^2 (an estimate that
    counts each surface once however many frames saw it; oblique surfaces count up to sqrt(3)x)."""
    keys = torch.floor(scene.gaussians.means.double() / cell).to(torch.int64)
    return max(1, torch.unique(keys, dim=0).shape[0]) * cell * cell


def procedural_captures(tmp: Path, seeds: list[int], sparse_house: bool = True) -> list[tuple[str, Path]]:
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    sc = dataclasses.replace(preset("default"), noise="middle")
    out = []
    for seed in seeds:
        path = tmp / f"house_{seed}"
        write_scene(generate_scene(sc, seed=seed), path)
        out.append((f"procedural middle, seed {seed}", path))
    if not sparse_house:
        return out
    # The demo's regime: clean depth, 12 panoramas per house, so some walls are seen frontally only by
    # a held-out frame (the case of fusion.owner_cos).
    sparse = dataclasses.replace(preset("default"), noise="none")
    sparse = dataclasses.replace(sparse, capture=dataclasses.replace(sparse.capture, views=12))
    path = tmp / "sparse"
    write_scene(generate_scene(sparse, seed=9100), path)
    out.append(("procedural none, 12 panoramas, seed 9100", path))
    return out


def run_capture(
    name: str, path: Path, refine_steps: list[int], refine_cfg_base: RefineConfig | None = None
) -> list[dict]:
    refine_cfg_base = refine_cfg_base or RefineConfig()
    capture = open_capture(path)
    n = len(capture)
    held = list(range(0, n, 8))
    sources = [i for i in range(n) if i not in held]
    own = [i for i in sources if i % 8 == 3][:6]
    rows = []
    single_cfg = config_for("all")
    # The single-frame scene of each own-pose frame, scored on the pixels it covers (a capture's depth
    # holes leave it empty there); the fused scenes are scored on the same pixels.
    single: dict[str, list[float]] = {mode: [] for mode in MODES}
    masks = []
    for i in own:
        one = build_scene(path, single_cfg, frames=[i])
        _, _, cov = score(one, capture, [i], single_cfg)
        p, _, _ = score(one, capture, [i], single_cfg, cov)
        for mode in MODES:
            single[mode].extend(p[mode])
        masks.append(cov[0])

    def own_columns(op: dict[str, list[float]]) -> dict:
        return {
            **_psnr_columns("own", op),
            **_psnr_columns("single_frame_own", single),
            "own_gap_db": round(
                statistics.fmean(single["normalised"]) - statistics.fmean(op["normalised"]), 2
            ),
            "own_gap_db_raw": round(statistics.fmean(single["raw"]) - statistics.fmean(op["raw"]), 2),
        }

    for variant, views in VARIANTS.items():
        cfg = config_for(views)
        t0 = time.perf_counter()
        scene = build_scene(path, cfg, frames=sources, fuse_every=8)
        build_s = time.perf_counter() - t0
        hp, ha, _ = score(scene, capture, held, cfg)
        op, oa, _ = score(scene, capture, own, cfg, masks)
        growth = []
        for k in (len(sources) // 4, len(sources) // 2, len(sources)):
            if k >= 1:
                part = (
                    scene if k == len(sources) else build_scene(path, cfg, frames=sources[:k], fuse_every=8)
                )
                growth.append((k, len(part), round(len(part) / surface_area(part), 1)))
        row = {
            "capture": name,
            "variant": variant,
            "frames": len(sources),
            "gaussians": len(scene),
            "gaussians_per_frame": round(len(scene) / len(sources)),
            "growth": growth,
            "build_s": round(build_s, 2),
            "refine_s": 0.0,
            **_psnr_columns("heldout", hp),
            "heldout_absrel": round(statistics.fmean(ha), 3),
            **own_columns(op),
            "own_absrel": round(statistics.fmean(oa), 3),
            "heldout_frames": held,
        }
        rows.append(row)
        print(rows[-1], flush=True)
        if views != "best":
            continue
        if refine_steps:
            rows.extend(
                refined_rows(
                    scene,
                    capture,
                    sources,
                    (held, own, masks, own_columns),
                    cfg,
                    row,
                    refine_steps,
                    refine_cfg_base,
                )
            )
    return rows


def refined_rows(scene, capture, sources, scored, cfg, row, refine_steps, refine_cfg_base) -> list[dict]:
    """One refinement run of ``scene``, scored at each count of ``refine_steps`` (the optimiser's
    state carries on between counts); ``scored`` = (held-out frames, own-pose frames, their masks,
    the own-pose columns' function)."""
    held, own, masks, own_columns = scored
    rows: list[dict] = []

    def at_count(steps: int, gaussians, seconds: float) -> None:
        scene.gaussians = gaussians
        hp, ha, _ = score(scene, capture, held, cfg)
        op, oa, _ = score(scene, capture, own, cfg, masks)
        rows.append(
            {
                **row,
                "variant": f"best + refine {steps}",
                "gaussians": len(scene),
                "gaussians_per_frame": round(len(scene) / len(sources)),
                "growth": [],
                "refine_s": round(seconds, 1),
                **_psnr_columns("heldout", hp),
                "heldout_absrel": round(statistics.fmean(ha), 3),
                **own_columns(op),
                "own_absrel": round(statistics.fmean(oa), 3),
            }
        )
        print(rows[-1], flush=True)

    refine_cfg = dataclasses.replace(refine_cfg_base, steps=max(refine_steps))
    refine_scene(scene, capture, sources, refine_cfg, checkpoints=refine_steps, on_checkpoint=at_count)
    return rows


def _refine_config(overrides: list[str]) -> RefineConfig:
    """``RefineConfig`` with ``--refine-set FIELD=VALUE`` overrides (``steps`` comes from --refine)."""
    fields = parse_overrides(overrides, "--refine-set")
    if "steps" in fields:
        raise SystemExit("--refine-set steps=...: the step counts come from --refine")
    return config_from_dict(RefineConfig, fields, "RefineConfig").validate()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--houses", type=int, default=2, help="procedural houses (noise tier middle)")
    ap.add_argument(
        "--refine",
        default="50,200",
        help="refinement step counts of the best scene, comma-separated ('' = none)",
    )
    ap.add_argument(
        "--refine-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a RefineConfig field (float or int), e.g. lr_means=1e-3; repeatable",
    )
    ap.add_argument("--skip-hm3d", action="store_true", help="procedural houses only (a quick run)")
    ap.add_argument(
        "--seeds",
        default="",
        help="seeds of the procedural middle-tier houses, comma-separated (default: 9000.. for --houses)",
    )
    ap.add_argument("--skip-sparse", action="store_true", help="leave out the 12-panorama house (seed 9100)")
    ap.add_argument(
        "--report",
        default="scene_fidelity",
        help="report name under reports/ (a partial run: another name keeps the full report)",
    )
    args = ap.parse_args()
    seeds = [int(v) for v in args.seeds.split(",") if v.strip()] or [9000 + i for i in range(args.houses)]
    refine_steps = sorted(int(v) for v in args.refine.split(",") if v.strip())
    refine_cfg = _refine_config(args.refine_set)
    torch.set_num_threads(1)
    load = load_average()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        captures = (
            [("HM3D 00000-kfPV7w3FaU5 (86 panoramas)", HM3D)] if HM3D.is_dir() and not args.skip_hm3d else []
        )
        captures += procedural_captures(Path(tmp), seeds, sparse_house=not args.skip_sparse)
        for name, path in captures:
            rows.extend(run_capture(name, path, refine_steps, refine_cfg))
    lines = [
        "# Scene fidelity: fused identity scenes against their best view (`benchmarks/scene_fidelity.py`)",
        "",
        f"- Hardware: {hardware()}; load average {load:.1f} at start; {utc_now()}",
        "- Config `tiny` (encoding 256x128), `build_scene(..., fuse_every=8)`, identity encoder, splat only.",
        "- Held-out: every 8th frame left out of the scene. Own pose: up to 6 frames of the scene, each",
        "  against the single-frame scene of that frame at its pose, on the pixels that one covers.",
        "- Growth: scenes of the first quarter, half and all source frames; Gaussians per m2 of observed",
        "  surface (occupied 5 cm cells x 25 cm2). Build time: one run (indicative).",
        "- `best + refine N`: the best scene after N refinement steps (one source frame per step, RGB L1 +",
        "  0.5 x relative depth error, Adam at `RefineConfig`'s learning rates, pruning under opacity 0.02",
        "  every 50 steps); one run read at each N (the optimiser's state carries on); refine s = its time",
        "  up to N, including a projection compile where Gaussians x steps >= 2e7. `sim build-scene`",
        "  refines 50 steps by default.",
        "- PSNR of the splat as `sim render` writes it: `normalised` (its default since 2026-11-27: the",
        "  composite divided by alpha, so gaps between Gaussians are not darkened towards black; also",
        "  the splat-only simulator's image and `eval render`'s `splat_only`), and in brackets `raw`",
        "  (the composite over black, what `sim render` and the simulator showed before). The issue's",
        "  baseline, today's identity scenes, is `all (before)` rendered `raw`.",
        "",
        "| capture | variant | Gaussians (per frame) | growth: frames: Gaussians (per m² of surface) "
        "| build s | refine s | held-out PSNR dB (raw) | held-out depth AbsRel "
        "| own-pose PSNR dB (single frame; gap) (raw: gap) "
        "| own-pose AbsRel |",
        "|---|---|---|---|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        growth = ", ".join(f"{k}: {g} ({m})" for k, g, m in r["growth"])
        lines.append(
            f"| {r['capture']} | {r['variant']} | {r['gaussians']} ({r['gaussians_per_frame']}) | {growth} | "
            f"{r['build_s']} | {r['refine_s']} | {r['heldout_psnr']} ({r['heldout_psnr_raw']}) | "
            f"{r['heldout_absrel']} | {r['own_psnr']} ({r['single_frame_own_psnr']}; {r['own_gap_db']}) "
            f"(raw: {r['own_gap_db_raw']}) | {r['own_absrel']} |"
        )
    write_report(
        args.report,
        rows,
        {"statistic": "mean over frames; build time one run", "load_average": load},
        markdown=lines,
    )


if __name__ == "__main__":
    main()
