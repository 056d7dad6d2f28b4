"""Navigable-area recall and precision of ``sim navmap`` against the exact floor of procedural houses.

Issue 21 asks for extraction defaults that recover more of the floor without losing precision. The
real-scene check uses the paper authors' maps, which are not on this machine; procedural houses have
an exact answer (``gt/navigable.npz``: free floor at least the agent radius from walls and object
footprints). For each house this script writes the same layout and views twice, at noise tier
``none`` and at the scored tier, and measures:

- ``P`` / ``R`` / ``F``: ``navmap_agreement`` of the extracted map (``extract_navmap``, the command's
  defaults unless a variant overrides fields of ``NavMapConfig``) with the exact navigable cells;
- ``seen``: the fraction of exact navigable cells whose floor some pixel of the exact-depth capture
  sees (back-projected within 2 cm of the floor, holes of two cells closed): the recall a method
  bounded by what the views show can reach;
- ``R seen``: recall on those seen cells only: what the extraction loses of the floor it was shown;
- extraction seconds (median of ``--repeats`` after one warm-up) against the default's, same run.

Writes ``reports/navmap_recall.{json,md}``. Run: ``.venv/bin/python benchmarks/navmap_recall.py
[--quick] [--seeds 9200,9201,9202]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report
from scipy import ndimage

_BEFORE_CARVING = {"carve_min_views": 0}
_BEFORE_HOLES = {**_BEFORE_CARVING, "hole_normals": False}
VARIANTS: dict[str, dict] = {
    "default": {},
    "no visibility carving (before 2026-12-07, session 51)": _BEFORE_CARVING,
    "no hole normals (before 2026-12-07)": _BEFORE_HOLES,
    "before 2026-11-28: closing 2, unseen = buffer": {
        **_BEFORE_HOLES,
        "closing_radius_cells": 2,
        "unknown_clearance": None,
    },
    "closing 4 only": {**_BEFORE_HOLES, "unknown_clearance": None},
    "unknown clearance 0 only": {**_BEFORE_HOLES, "closing_radius_cells": 2},
    "before + pixel stride 1": {
        **_BEFORE_HOLES,
        "closing_radius_cells": 2,
        "unknown_clearance": None,
        "pixel_stride": 1,
    },
}
"""Extraction settings compared with the defaults (``NavMapConfig`` field overrides). The variants
of session 30 (2026-11-28) ablate its two changes from the default of their time, which had no
hole normals (session 50) and no visibility carving (session 51). The typical camera height of
session 51 (``floors.typical_camera_height``) has no switch: the rerun after it is its measure."""

FLOOR_TOLERANCE = 0.02
"""A back-projected exact-depth pixel within this height (metres) of the floor plane sees floor."""


def exact_grid(scene: Path) -> tuple[np.ndarray, float, np.ndarray]:
    """(navigable (H, W) bool, cell size, origin (2,)) of a procedural house's ``gt/navigable.npz``."""
    g = np.load(scene / "gt" / "navigable.npz")
    return g["grid"].astype(bool), float(g["resolution"]), np.asarray(g["origin"], dtype=np.float64)


def grid_points(mask: np.ndarray, res: float, origin: np.ndarray) -> np.ndarray:
    """(N, 3) world centres (floor at z = 0) of the ``True`` cells of a ``gt`` grid."""
    iy, ix = np.nonzero(mask)
    return np.column_stack((origin[0] + (ix + 0.5) * res, origin[1] + (iy + 0.5) * res, np.zeros(len(ix))))


def seen_floor(scene: Path, shape: tuple[int, int], res: float, origin: np.ndarray) -> np.ndarray:
    """(H, W) cells of the ``gt`` grid whose floor some pixel of the capture at ``scene`` sees."""
    from image2sim.simulator.gaussians.frames import world_points
    from image2sim.simulator.io import open_capture

    seen = np.zeros(shape, dtype=bool)
    for frame in open_capture(scene):
        depth = torch.as_tensor(np.asarray(frame.depth), dtype=torch.float64).nan_to_num(0.0, 0.0, 0.0)
        pose = torch.as_tensor(np.asarray(frame.cam_to_world), dtype=torch.float64)
        pw = world_points(depth[None, None], frame.camera, pose)[0].reshape(-1, 3).numpy()
        pw = pw[(depth.reshape(-1) > 0).numpy()]
        pw = pw[np.abs(pw[:, 2]) <= FLOOR_TOLERANCE]
        ix = np.floor((pw[:, 0] - origin[0]) / res).astype(np.int64)
        iy = np.floor((pw[:, 1] - origin[1]) / res).astype(np.int64)
        ok = (ix >= 0) & (iy >= 0) & (ix < shape[1]) & (iy < shape[0])
        seen[iy[ok], ix[ok]] = True
    return ndimage.binary_closing(seen, iterations=2)


def write_house(root: Path, seed: int, camera: str, noise: str, preset_name: str = "default") -> Path:
    """One procedural house of preset ``preset_name`` at ``camera`` and noise tier ``noise``."""
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene

    cfg = dataclasses.replace(preset(preset_name), noise=noise)
    cfg = dataclasses.replace(cfg, capture=dataclasses.replace(cfg.capture, camera=camera))
    path = root / f"{camera}_{noise}_{seed}"
    write_scene(generate_scene(cfg, seed=seed), path, progress=False)
    return path


def score_capture(path: Path, seen: np.ndarray, variants: dict[str, dict], repeats: int) -> list[dict]:
    """One row per variant: agreement with the exact map, recall on seen cells, extraction seconds."""
    from image2sim.simulator.io import open_capture
    from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
    from image2sim.simulator.navigation.extract import extract_navmap
    from image2sim.simulator.navigation.navmap import navmap_agreement

    nav, res, origin = exact_grid(path)
    exact_all = grid_points(nav, res, origin)
    exact_seen = grid_points(nav & seen, res, origin)
    rows = []
    for name, overrides in variants.items():
        cfg = NavMapConfig(**overrides)
        capture = open_capture(path)
        maps = []
        timing = time_it(
            lambda c=cfg, cap=capture, out=maps: out.append(extract_navmap(cap, Embodiment(), c)),
            warmup=1,
            repeats=repeats,
        )
        points = maps[-1].points
        agree = navmap_agreement(points, exact_all, res)
        agree_seen = navmap_agreement(points, exact_seen, res)
        rows.append(
            {
                "variant": name,
                "P": round(agree["precision"], 3),
                "R": round(agree["recall"], 3),
                "F": round(agree["f_score"], 3),
                "seen": round(float((nav & seen).sum() / max(nav.sum(), 1)), 3),
                "R seen": round(agree_seen["recall"], 3),
                "area m2": round(agree["area_a"], 1),
                "exact area m2": round(agree["area_b"], 1),
                "extract s": round(timing.wall, 2),
            }
        )
    return rows


def main(argv: list[str] | None = None, reports: Path | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one house, panoramas, tier none, one timed run")
    ap.add_argument("--preset", default="default", help="procedural preset of the houses (default or tiny)")
    ap.add_argument("--seeds", default="9200,9201,9202", help="house seeds, comma-separated")
    ap.add_argument("--noise", default="middle", help="noise tier scored beside the exact tier")
    ap.add_argument("--repeats", type=int, default=2, help="timed extractions after one warm-up")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")][: 1 if args.quick else None]
    cameras = ["equirect"] if args.quick else ["equirect", "pinhole"]
    repeats = 1 if args.quick else args.repeats
    tiers = ["none"] if args.quick else ["none", args.noise]
    hw = f"{hardware()}; load average {load_average():.1f} at start"
    t0 = time.perf_counter()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="navmap-recall-") as tmp:
        for camera in cameras:
            for seed in seeds:
                exact = write_house(Path(tmp), seed, camera, "none", args.preset)
                nav, res, origin = exact_grid(exact)
                seen = seen_floor(exact, nav.shape, res, origin)
                for tier in tiers:
                    path = (
                        exact if tier == "none" else write_house(Path(tmp), seed, camera, tier, args.preset)
                    )
                    for row in score_capture(path, seen, VARIANTS, repeats):
                        row = {"camera": camera, "seed": seed, "tier": tier, **row}
                        rows.append(row)
                        print(json.dumps(row), flush=True)
    summary = summarise(rows)
    hw += f", {load_average():.1f} at end; whole run {time.perf_counter() - t0:.0f} s"
    lines = [
        "# Navigable-area recall against the exact floor of procedural houses "
        "(`benchmarks/navmap_recall.py`)",
        "",
        f"- Hardware: {hw}.",
        f"- Houses: `data synth` preset `{args.preset}`, written at tier `none` and at the scored "
        "tier with the same layout and views. Exact map: `gt/navigable.npz` (free floor at least the "
        "agent radius + half a cell from walls and object footprints, 0.05 m cells).",
        "- `seen`: exact navigable cells whose floor a pixel of the tier-`none` capture sees (within "
        f"{FLOOR_TOLERANCE * 100:.0f} cm of the floor; holes of two cells closed). `R seen`: recall on "
        "those cells. `extract s`: median of the timed runs after one warm-up.",
        "",
        "## Mean over houses",
        "",
        "| camera | tier | variant | P | R | F | seen | R seen | extract s |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {s['camera']} | {s['tier']} | {s['variant']} | {s['P']} | {s['R']} | {s['F']} | {s['seen']} | "
        f"{s['R seen']} | {s['extract s']} |"
        for s in summary
    ]
    cols = list(rows[0])
    lines += ["", "## Per house", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    meta = {
        "hardware": hw,
        "preset": args.preset,
        "variants": VARIANTS,
        "floor_tolerance_m": FLOOR_TOLERANCE,
        "summary": summary,
    }
    paths = write_report("navmap_recall", rows, meta, markdown=lines, reports=reports)
    print(f"wrote {paths[0]} and {paths[1]}")
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Mean of every score over the houses of each (camera, tier, variant), in first-seen order."""
    keys: dict[tuple, list[dict]] = {}
    for r in rows:
        keys.setdefault((r["camera"], r["tier"], r["variant"]), []).append(r)
    out = []
    for (camera, tier, variant), group in keys.items():
        mean = {k: round(statistics.fmean(g[k] for g in group), 3) for k in ("P", "R", "F", "seen", "R seen")}
        mean["extract s"] = round(statistics.fmean(g["extract s"] for g in group), 2)
        out.append({"camera": camera, "tier": tier, "variant": variant, "houses": len(group), **mean})
    return out


if __name__ == "__main__":
    main()
