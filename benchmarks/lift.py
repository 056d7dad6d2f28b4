"""Lifting benchmark (issue 24): RGB-only images -> metric posed RGB-D, seconds against error per stage.

Cases:

- **procedural houses**, rendered by the generator at noise tier ``middle`` with a walking camera and
  surface grain (``surface_detail 0.3``, ``capture.yaw_step_max_deg 25``: what SIFT needs,
  ``docs/lift.md``), pinhole and panorama. Only the colour images go into ``lift``; for RGB the
  ``middle`` tier means Gaussian colour noise (std 2 levels) and a 12 m range limit on the stored
  depth, which lifting never reads (its depth noise, holes and pose jitter touch only the stored
  depth and poses, which lifting ignores; it keeps every view). The same house rendered at tier
  ``none`` (same views: the viewpoint stream does not depend on the tier, checked) is the *exact
  capture*: exact poses and depth, used only for scoring;
- **the HM3D sample** (``../shared/data/hm3d_360/00000-kfPV7w3FaU5``, skipped when absent): its
  panoramas' RGB alone, a documented subset (every ``--hm3d-every``-th frame, 43 of 86 by default,
  at ``--hm3d-width`` 1024, the full resolution), scored against the given poses and the map from
  the given depth of the same frames.

Per case: ``image2sim.simulator.lift.lift`` with ``--depth mvs`` (the CPU plane sweep; no depth-model
weights on this machine; ``--depth mvs+model --depth-model DIR`` tries a depth model) and
``--camera-height`` (the synth config's eye height from the capture's manifest; for HM3D the median
height of the given cameras above the given map's floor). Scores:

- poses: ATE after the Sim(3) (Umeyama) alignment of the lifted camera centres to the exact ones,
  rotation error after that alignment (median and max), scale error ``|1/s - 1|`` of the alignment
  (the lifted capture is already metric: this is the camera-height scale's error);
- depth: AbsRel of the written metric depth against the exact depth on the pixels the method marks
  confident (confidence > 0: MVS zeroes depth and confidence of rejected pixels), pooled over the
  registered frames' pixels, and their fraction of the pixels with exact depth; also on confidence
  >= 0.5, and after removing the scale error (shape alone);
- navigable map: ``extract_navmap`` (the ``sim navmap`` defaults: geometric floor, no labels) of the
  lifted capture, carried into the exact world by the pose alignment's Sim(3), against the map of
  the exact capture (or the given HM3D depth) of the same input frames,
  :func:`image2sim.simulator.navigation.navmap_agreement` (F-score of navigable area);
- seconds per stage from the lift record (frames, SfM, depth, scale, write) and the navmap
  extraction: one run each (minutes per case on 2 shared cores; the load average is recorded).

Writes ``reports/lift.json`` and ``reports/lift.md``.
Run: ``.venv/bin/python benchmarks/lift.py [--quick] [--no-hm3d] [--hm3d-every 2] [--hm3d-width 1024]``
(``--keep DIR`` keeps the houses and lifted captures).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, utc_now, write_report

ROOT = Path(__file__).resolve().parents[1]
HM3D = (
    Path(os.environ.get("IMAGE2SIM_SHARED_DATA", ROOT.parent / "shared" / "data"))
    / "hm3d_360"
    / "00000-kfPV7w3FaU5"
)
TARGETS = {
    "ate_m": ("pose ATE (Sim(3))", "<=", 0.05),
    "rot_max_deg": ("rotation error (max)", "<=", 1.0),
    "scale_error": ("scale error (camera height)", "<=", 0.03),
    "absrel": ("depth AbsRel on confident pixels", "<=", 0.10),
    "coverage": ("confident fraction of pixels", ">=", 0.60),
    "nav_f": ("navigable-area F vs exact capture", ">=", 0.8),
}
HM3D_TARGETS = {
    "ate_m": ("pose ATE vs given poses (Sim(3))", "<=", 0.10),
    "nav_f": ("navigable-area F vs map from given depth", ">=", 0.8),
}
WALK = {"yaw_step_max_deg": 25.0}
LIMITS = [
    "## What limits the missed targets (read from the run of 2026-12-07 21:04Z; recheck when rerunning)",
    "",
    "- **Met everywhere:** pose ATE and rotation (on the registered frames), the camera-height scale "
    "(the floor is the lowest plane standing out from the wall slices beside it, in the sparse SfM "
    "points first), depth AbsRel on confident pixels and, with the plane fill, coverage (66.8 / 62.1 / "
    "64.7 %). Frames left without any valid depth are dropped and named by `lift` (none in this run), "
    "so the reader refuses nothing. **The pinhole house's navigable map now meets the target (F 0.812).**",
    "- **Navigable maps (pinhole F 0.812, panorama 0.685, HM3D 0.301; target 0.8):** session 51 fixed "
    "two faults of the map extraction, not of the lift (docs/navigation.md): the exact map of the "
    "pinhole house had kept a bed top and three table tops as floor (a forward-looking camera's "
    "nearest cell set the capture's camera height; now each camera's lowest surface does: reference "
    "3.35 -> 2.65 m², lifted F 0.693 -> 0.795), and floaters of wrong stereo depth blocked the floor "
    "around them (visibility carving: 0.795 -> 0.812 in this run). The panorama map (P 0.78 / R 0.61; "
    "0.68-0.71 over the last four runs, whose stereo differs run to run) misses floor the sweep does "
    "not see (844 of 1061 missed cells have no lifted floor at all: far floor through doorways, the "
    "oblique band 1-3 m away) and obstacles the lift has no depth for: 59 % of the exact obstacle "
    "pixels between 0.15 and 1.5 m (furniture sides and tops, near walls) have none; exact depth on "
    "those pixels alone lifts its precision to 0.99 (F 0.78). A pretrained depth model (`--depth model`) is "
    "the remaining lever for both (more views alone are not: session 50).",
    "- **HM3D (8 of 43 panoramas registered; F 0.301, 0.802 against the 8 registered frames' own map):** "
    "the sample's panoramas are metres apart over two storeys; SIFT on their cube faces splits them "
    "into several small models and the largest is kept (registered poses within 3 mm of the given "
    "ones). The matches joining the models fall on features no model triangulated (at most 17 "
    "point links between two models), and looser registration places panoramas decimetres wrong on "
    "this subset (docs/lift.md, session 49).",
    "- **Time:** depth (the plane sweep) dominates: 88-260 s per case; the scale stage includes the "
    "floor fill (three plane warps per view): 7-16 s; the plane fill takes 5-15 s.",
]


def house_cases(quick: bool) -> list[dict]:
    """The procedural cases: camera, views, size and walk (the lifting tests' houses, tier middle)."""
    pin = {"camera": "pinhole", "views": 10 if quick else 30, "height": 240, "width": 320}
    pin["capture"] = {**WALK, "spacing_min": 0.25, "spacing_max": 0.5}
    pano = {"camera": "equirect", "views": 5 if quick else 12, "height": 256, "width": 512}
    pano["capture"] = {**WALK, "spacing_min": 0.4, "spacing_max": 0.8}
    return [pin, pano]


def say(stage: str, message: str) -> None:
    print(f"  [{stage}] {message}", file=sys.stderr, flush=True)


def synth_pair(case: dict, seed: int, tmp: Path) -> tuple[Path, Path]:
    """The house at tier ``middle`` (lifting input) and at tier ``none`` (exact poses and depth)."""
    from image2sim.dataengine.procedural import (
        generate_scene,
        preset,
        scene_seed,
        synth_config_from_dict,
        write_scene,
    )

    capture = {
        **case["capture"],
        "views": case["views"],
        "camera": case["camera"],
        "height": case["height"],
        "width": case["width"],
    }
    out = []
    for tier in ("middle", "none"):
        cfg = synth_config_from_dict(
            {"noise": tier, "surface_detail": 0.3, "capture": capture}, base=preset("tiny")
        )
        # scene_seed(seed, 0): the house `image2sim data synth --seed S` writes as scene_000.
        out.append(write_scene(generate_scene(cfg, scene_seed(seed, 0)), tmp / f"{case['camera']}_{tier}"))
    middle, exact = out
    truth = json.loads((middle / "gt" / "poses.json").read_text())["poses"]
    exact_poses = json.loads((exact / "gt" / "poses.json").read_text())["poses"]
    if truth.keys() != exact_poses.keys() or any(
        not np.allclose(truth[k], exact_poses[k], atol=1e-9) for k in truth
    ):
        raise RuntimeError("tiers middle and none sampled different views: no exact capture to score against")
    return middle, exact


def rgb_folder(capture_dir: Path, dest: Path, ids: list[str] | None = None, width: int | None = None) -> Path:
    """The capture's colour images alone as ``dest/<id>.png`` (resized to ``width`` when given)."""
    import cv2

    dest.mkdir(parents=True, exist_ok=True)
    for path in sorted((capture_dir / "frames").glob("*_rgb.png")) or sorted(capture_dir.glob("*_rgb.png")):
        fid = path.name[: -len("_rgb.png")]
        if ids is not None and fid not in ids:
            continue
        if width is None:
            shutil.copy(path, dest / f"{fid}.png")
            continue
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        h = round(img.shape[0] * width / img.shape[1])
        cv2.imwrite(str(dest / f"{fid}.png"), cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA))
    return dest


def open_lifted(out: Path):
    """The lifted capture's readable frames by id, the ids (and poses) of every frame written, and
    the frames the reader refuses (a frame whose depth the stereo left empty: the strict reader
    calls a depth image without one valid pixel corrupt)."""
    from image2sim.simulator.io.records import CaptureError
    from image2sim.simulator.io.registry import open_capture

    cap = open_capture(out)
    frames, refused = {}, []
    for i, fid in enumerate(cap.frame_ids):
        try:
            frames[fid] = cap[i]
        except CaptureError as exc:
            refused.append(f"{fid}: {str(exc).rsplit(': ', 1)[-1]}")
    ids = list(cap.frame_ids)
    return frames, ids, np.asarray(cap.poses, dtype=np.float64), refused


def pose_scores(est: np.ndarray, true: np.ndarray) -> dict:
    """ATE, rotation errors and scale error of lifted poses (N, 4, 4) against true ones, and the
    Sim(3) ``(s, R, t)`` taking the lifted world into the true one."""
    from image2sim.simulator.lift.scale import ate, rotation_errors_deg, umeyama

    s, R, t = umeyama(est[:, :3, 3], true[:, :3, 3])
    rot = rotation_errors_deg(est[:, :3, :3], true[:, :3, :3], R)
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))
    return {
        "ate_m": ate(est[:, :3, 3], true[:, :3, 3]),
        "rot_median_deg": float(np.median(rot)),
        "rot_max_deg": float(rot.max()),
        "scale_error": float(abs(1.0 / s - 1.0)),
        "gravity_error_deg": tilt,
        "sim3": (s, R, t),
    }


def depth_scores(lifted: dict, ids: list[str], truth_of: Callable[[str], np.ndarray], s: float) -> dict:
    """AbsRel of the lifted metric depth against ``truth_of(frame_id)`` (exact depth of the lifted
    frame's size), pooled over pixels; ``s`` the pose alignment's scale (for the shape-only AbsRel)."""
    from image2sim.simulator.lift.planes import PLANE_FILL_CONFIDENCE

    num = {"conf": 0.0, "conf05": 0.0, "plane": 0.0, "aligned": 0.0}
    cnt = {"conf": 0, "conf05": 0, "plane": 0}
    valid_px = 0
    for fid in ids:
        truth = truth_of(fid).astype(np.float64)
        if fid not in lifted:  # no depth at all: every pixel uncovered
            valid_px += int((truth > 0).sum())
            continue
        frame = lifted[fid]
        depth = frame.depth.astype(np.float64)
        conf = frame.confidence if frame.confidence is not None else (depth > 0).astype(np.float32)
        ok = truth > 0
        valid_px += int(ok.sum())
        # Confidence is stored as uint8 (0..255): the plane fill's 0.03 reads back as 8 / 255.
        plane = np.abs(conf - round(PLANE_FILL_CONFIDENCE * 255) / 255) < 0.25 / 255
        for key, m in (
            ("conf", ok & (depth > 0) & (conf > 0)),
            ("conf05", ok & (depth > 0) & (conf >= 0.5)),
            ("plane", ok & (depth > 0) & plane),
        ):
            rel = np.abs(depth[m] - truth[m]) / truth[m]
            num[key] += float(rel.sum())
            cnt[key] += int(m.sum())
            if key == "conf":
                num["aligned"] += float((np.abs(depth[m] * s - truth[m]) / truth[m]).sum())

    def ratio(a: float, b: int) -> float | None:
        return a / b if b else None

    return {
        "absrel": ratio(num["conf"], cnt["conf"]),
        "coverage": cnt["conf"] / max(valid_px, 1),
        "absrel_conf05": ratio(num["conf05"], cnt["conf05"]),
        "coverage_conf05": cnt["conf05"] / max(valid_px, 1),
        "absrel_plane": ratio(num["plane"], cnt["plane"]),
        "coverage_plane": cnt["plane"] / max(valid_px, 1),
        "absrel_scale_removed": ratio(num["aligned"], cnt["conf"]),
    }


def nav_scores(lifted_dir: Path, lifted_frames: list, reference_frames, sim3) -> dict:
    """F-score of the lifted capture's navigable map (carried by ``sim3``) against the reference's."""
    from image2sim.simulator.navigation import NavMapError, extract_navmap, navmap_agreement

    t0 = time.perf_counter()
    try:
        lifted = extract_navmap(lifted_frames)
    except NavMapError as exc:
        return {"navmap_s": time.perf_counter() - t0, "nav_f": 0.0, "nav_error": str(exc)}
    navmap_s = time.perf_counter() - t0
    s, R, t = sim3
    pts = s * lifted.points @ R.T + t
    agree = navmap_agreement(pts, extract_navmap(reference_frames).points, lifted.voxel_size)
    # Against the map of the registered frames alone: pose and depth quality without registration.
    registered = set(json.loads((lifted_dir / "manifest.json").read_text())["frame_ids"])
    own = extract_navmap([f for f in reference_frames if f.frame_id in registered]).points
    agree_registered = navmap_agreement(pts, own, lifted.voxel_size)
    return {
        "nav_f_registered_frames": agree_registered["f_score"],
        "navmap_s": navmap_s,
        "nav_f": agree["f_score"],
        "nav_precision": agree["precision"],
        "nav_recall": agree["recall"],
        "nav_area_lifted_m2": agree["area_a"],
        "nav_area_reference_m2": agree["area_b"],
    }


def lift_case(
    name: str, images: Path, out: Path, camera_height: float, depth_kw: dict, depth: tuple[str, str | None]
) -> dict:
    from image2sim.simulator.lift.capture import LiftOptions, lift
    from image2sim.simulator.lift.depth import estimate_depth
    from image2sim.simulator.lift.frames import LiftInputError

    print(f"{name}: lifting {images}", file=sys.stderr, flush=True)

    def depth_fn(views, **kw):
        return estimate_depth(views, **kw, **depth_kw)

    t0 = time.perf_counter()
    try:
        rep = lift(
            images,
            out,
            LiftOptions(camera_height=camera_height, depth_source=depth[0], depth_model=depth[1]),
            progress=say,
            depth_fn=depth_fn if depth_kw else None,
        )
    except (LiftInputError, ValueError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}", "total_s": time.perf_counter() - t0}
    timings = json.loads((out / "manifest.json").read_text())["metadata"]["lift"]["timings_s"]
    sfm = rep.sfm.stats
    return {
        "registered": len(rep.sfm.frame_ids),
        "input_frames": len(rep.frames),
        "camera_height_m": camera_height,
        "scale_uncertainty": rep.scale.uncertainty,
        "sfm_s": timings["sfm"],
        "sfm_extract_s": sfm.get("extract_s"),
        "sfm_match_s": sfm.get("match_s"),
        "sfm_map_s": sfm.get("map_s"),
        "sfm_points": sfm.get("points"),
        "reprojection_px": sfm.get("mean_reprojection_error_px"),
        "depth_s": timings["depth"],
        "scale_s": timings["scale"],
        "write_s": timings["write"],
        "frames_s": timings["frames"],
        "planes_s": timings.get("planes", 0.0),
        "floor_fill_px": rep.record.get("floor_fill", {}).get("pixels"),
        "plane_fill_px": rep.record.get("plane_fill", {}).get("pixels"),
        "dropped_no_depth": [
            d["frame_id"] for d in rep.record["dropped"] if d["reason"].startswith("no valid depth")
        ],
        "total_s": time.perf_counter() - t0,
    }


def run_house(case: dict, seed: int, tmp: Path, depth_kw: dict, depth: tuple[str, str | None]) -> dict:
    from image2sim.simulator.io.registry import open_capture

    kind = "panorama" if case["camera"] == "equirect" else "pinhole"
    name = f"procedural {kind} {case['width']}x{case['height']}, {case['views']} views"
    row: dict = {"case": name, "kind": kind, "seed": seed}
    t0 = time.perf_counter()
    middle, exact_dir = synth_pair(case, seed, tmp)
    row["synth_s"] = time.perf_counter() - t0
    meta = json.loads((middle / "manifest.json").read_text())["metadata"]
    images = rgb_folder(middle, tmp / f"{kind}_rgb")
    out = tmp / f"{kind}_lifted"
    row.update(lift_case(name, images, out, float(meta["eye_height"]), depth_kw, depth))
    if "error" in row:
        return row
    lifted, ids, est, row["frames_refused_by_reader"] = open_lifted(out)
    truth = json.loads((middle / "gt" / "poses.json").read_text())["poses"]
    true = np.stack([np.asarray(truth[f], dtype=np.float64) for f in ids])
    poses = pose_scores(est, true)
    sim3 = poses.pop("sim3")
    row.update(poses)
    exact = open_capture(exact_dir)
    index = {fid: i for i, fid in enumerate(exact.frame_ids)}
    row.update(depth_scores(lifted, ids, lambda fid: exact[index[fid]].depth, sim3[0]))
    row.update(nav_scores(out, list(lifted.values()), exact, sim3))
    return row


def run_hm3d(tmp: Path, every: int, width: int, depth_kw: dict, depth: tuple[str, str | None]) -> dict:
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.navigation import extract_navmap

    given = open_capture(HM3D)
    keep = list(range(0, len(given), every))
    ids = [given.frame_ids[i] for i in keep]
    nth = f"{every}{'nd' if every == 2 else 'th'}"
    name = f"HM3D 00000-kfPV7w3FaU5, every {nth} panorama ({len(ids)} of {len(given)}), {width}x{width // 2}"
    row: dict = {"case": name, "kind": "hm3d", "frames_used": ids}
    frames = [given[i] for i in keep]
    # Camera height from the given data: cameras above the given map's floor (the README says 1.5 m).
    ref_map = extract_navmap(frames)
    cams = np.stack([f.cam_to_world[:3, 3] for f in frames])
    floor = ref_map.points
    heights = []
    for c in cams:
        below = floor[(np.hypot(*(floor[:, :2] - c[:2]).T) < 0.5) & (floor[:, 2] < c[2])]
        if len(below):
            heights.append(c[2] - below[:, 2].max())
    camera_height = float(np.median(heights))
    images = rgb_folder(HM3D, tmp / "hm3d_rgb", ids=set(ids), width=width)
    out = tmp / "hm3d_lifted"
    row.update(lift_case(name, images, out, camera_height, depth_kw, depth))
    if "error" in row:
        return row
    lifted, lifted_ids, est, row["frames_refused_by_reader"] = open_lifted(out)
    pose_of = dict(zip(given.frame_ids, given.poses, strict=True))
    true = np.stack([pose_of[f] for f in lifted_ids])
    poses = pose_scores(est, true)
    sim3 = poses.pop("sim3")
    row.update(poses)
    # The given depth (rendered, noise-free) at the lifted size: nearest neighbour, no depth blended.
    import cv2

    by_id = dict(zip(ids, frames, strict=True))
    camera = next(iter(lifted.values())).camera
    size = (camera.width, camera.height)
    row.update(
        depth_scores(
            lifted,
            lifted_ids,
            lambda fid: cv2.resize(by_id[fid].depth, size, interpolation=cv2.INTER_NEAREST),
            sim3[0],
        )
    )
    row.update(nav_scores(out, list(lifted.values()), frames, sim3))
    return row


def verdicts(row: dict, targets: dict) -> list[dict]:
    out = []
    for key, (label, op, bound) in targets.items():
        value = row.get(key)
        met = None if value is None else (value <= bound if op == "<=" else value >= bound)
        out.append(
            {
                "case": row["case"],
                "registered": f"{row.get('registered', 0)} / {row.get('input_frames', '?')}",
                "key": key,
                "target": label,
                "bound": f"{op} {bound:g}",
                "value": value,
                "met": met,
            }
        )
    return out


def fmt(key: str, value) -> str:
    if value is None:
        return "–"
    if key in ("ate_m",):
        return f"{value * 100:.2f} cm"
    if key == "scale_error":
        return f"{value * 100:.2f} %"
    if key == "coverage":
        return f"{value * 100:.1f} %"
    if key.endswith("_deg"):
        return f"{value:.2f}°"
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)


def depth_text(meta: dict) -> str:
    """The depth source in words (reports written before `--depth` existed used the plane sweep)."""
    source = meta.get("depth_source", "mvs")
    text = f"`{source}` (CPU plane sweep{meta['depth_note']}"
    if source == "mvs":
        return text + ")"
    if source == "model":
        text = "`model` ("
    return text + f"; depth model `{meta.get('depth_model')}`, aligned per view)"


def markdown(rows: list[dict], checks: list[dict], meta: dict) -> list[str]:
    lines = [
        "# Lifting RGB-only captures: error against seconds per stage (`benchmarks/lift.py`)",
        "",
        f"- Hardware: {meta['hardware']}; load average {meta['load_average']:.1f} at start "
        f"(2 cores shared with other jobs); {meta['date_utc']}.",
        f"- {meta['mode']}. Depth: {depth_text(meta)}; pycolmap SIFT, "
        "2 threads; torch 1 thread. Times: one run per case (minutes each), indicative under the load.",
        "- Procedural houses: `preset tiny`, noise tier `middle` (for RGB: colour noise std 2 levels; its "
        "depth noise, holes and pose jitter touch only the stored depth and poses, which lifting ignores), "
        "`surface_detail 0.3`, walking camera (`yaw_step_max_deg 25`). Scored against the same house "
        "at tier `none` (exact poses and depth). `--camera-height` = the capture's recorded eye height.",
        "- Depth AbsRel: written metric depth vs exact, pooled over pixels with confidence > 0 "
        "(MVS zeroes the rest; this includes the floor-plane fill, confidence 0.02, and the plane fill of "
        "textureless segments, confidence 0.03); coverage = those "
        "pixels / pixels with exact depth, registered frames (a frame left out for lack of depth counts "
        "as uncovered).",
        "- Navigable F: `extract_navmap` defaults (as `sim navmap`) on the lifted capture, carried into "
        "the exact world by the pose Sim(3), vs the exact capture's map (HM3D: the given depth and "
        "poses of the same frames); `navmap_agreement`, 0.05 m cells.",
        "",
        "## Targets",
        "",
        "| case | registered | target | bound | measured | met |",
        "|---|---|---|---|---|---|",
    ]
    for c in checks:
        met = "–" if c["met"] is None else ("yes" if c["met"] else "**no**")
        lines.append(
            f"| {c['case']} | {c['registered']} | {c['target']} | {c['bound']} | "
            f"{fmt(c['key'], c['value'])} | {met} |"
        )
    lines += [
        "",
        "## Per stage: seconds and error",
        "",
        "| case | registered | SfM s (extract / match / map) | ATE | rot median / max | scale err "
        "(± est.) | depth s | AbsRel (conf>0) | coverage | AbsRel / cov. (conf≥0.5) | AbsRel / cov. "
        "(plane fill) | AbsRel scale removed | scale s | planes s | write s | navmap s | nav F (P / R) "
        "| nav F vs registered frames' map |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | failed: {r['error']} |" + " |" * 16)
            continue
        sfm = f"{r['sfm_s']:.1f} ({r['sfm_extract_s']:.1f} / {r['sfm_match_s']:.1f} / {r['sfm_map_s']:.1f})"
        lines.append(
            f"| {r['case']} | {r['registered']} / {r['input_frames']} | {sfm} | {fmt('ate_m', r['ate_m'])} | "
            f"{r['rot_median_deg']:.2f}° / {r['rot_max_deg']:.2f}° | {fmt('scale_error', r['scale_error'])} "
            f"(± {r['scale_uncertainty'] * 100:.1f} %) | {r['depth_s']:.0f} | {fmt('absrel', r['absrel'])} | "
            f"{fmt('coverage', r['coverage'])} | {fmt('absrel', r['absrel_conf05'])} / "
            f"{fmt('coverage', r['coverage_conf05'])} | {fmt('absrel', r.get('absrel_plane'))} / "
            f"{fmt('coverage', r.get('coverage_plane'))} | {fmt('absrel', r['absrel_scale_removed'])} | "
            f"{r['scale_s']:.1f} | {r.get('planes_s', 0.0):.1f} | {r['write_s']:.1f} | {r['navmap_s']:.1f} | "
            f"{r['nav_f']:.3f} ({r.get('nav_precision', 0):.3f} / {r.get('nav_recall', 0):.3f}) | "
            f"{fmt('f', r.get('nav_f_registered_frames'))} |"
        )
    lines.append("")
    for r in rows:
        if "error" not in r:
            no_depth = ", ".join(r.get("dropped_no_depth") or []) or "none"
            lines.append(
                f"- {r['case']}: frames left out for lack of any valid depth: {no_depth}; "
                f"pixels given the floor plane's depth (floor fill): {r.get('floor_fill_px', '–')}; "
                f"pixels completed from their segment's plane (plane fill): {r.get('plane_fill_px', '–')}; "
                f"frames the capture reader refused: {len(r.get('frames_refused_by_reader') or [])}."
            )
    lines += ["", *meta.get("notes", [])]
    if not meta.get("quick"):
        lines += ["", *LIMITS]
    return lines


def main(argv: Sequence[str] | None = None, reports: str | Path | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: 10 pinhole views, 5 panoramas, no HM3D")
    ap.add_argument(
        "--seed", type=int, default=0, help="synth seed of the house (0: the lifting tests' house)"
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="keep the houses and lifted captures in this folder"
    )
    ap.add_argument("--no-hm3d", action="store_true", help="skip the HM3D sample")
    ap.add_argument("--hm3d-every", type=int, default=2, help="keep every N-th HM3D panorama")
    ap.add_argument("--hm3d-width", type=int, default=1024, help="HM3D panoramas downsampled to this width")
    ap.add_argument("--num-planes", type=int, default=None, help="MVS planes (default: the MVS default)")
    ap.add_argument(
        "--depth",
        choices=("mvs", "mvs+model", "model"),
        default="mvs",
        help="depth source (model sources need --depth-model)",
    )
    ap.add_argument(
        "--depth-model",
        type=Path,
        default=None,
        help="local transformers depth model folder (e.g. from `image2sim data train-depth-prior`)",
    )
    ap.add_argument(
        "--mvs",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an MVSConfig field for the plane sweep, VALUE in JSON (repeatable; e.g. best_k=1)",
    )
    ap.add_argument("--only", choices=("pinhole", "panorama", "hm3d"), nargs="+", help="run only these")
    ap.add_argument(
        "--render-only",
        action="store_true",
        help="rewrite reports/lift.md from reports/lift.json (after editing the notes), running nothing",
    )
    args = ap.parse_args(argv)
    if args.render_only:
        folder = Path(reports) if reports is not None else ROOT / "reports"
        doc = json.loads((folder / "lift.json").read_text(encoding="utf-8"))
        rows = doc.pop("rows")
        write_report("lift", rows, doc, markdown=markdown(rows, doc["checks"], doc), reports=reports)
        return {**doc, "rows": rows}
    if args.depth != "mvs" and args.depth_model is None:
        ap.error(f"--depth {args.depth} needs --depth-model DIR")
    depth = (args.depth, None if args.depth_model is None else str(args.depth_model.resolve()))
    torch.set_num_threads(1)
    depth_kw = {} if args.num_planes is None else {"num_planes": args.num_planes}
    if args.quick and args.num_planes is None:
        depth_kw = {"num_planes": 24}
    for item in args.mvs:
        name, _, value = item.partition("=")  # no "=": an empty value, which is not JSON
        try:
            depth_kw[name] = json.loads(value)
        except json.JSONDecodeError:
            ap.error(f"--mvs takes NAME=VALUE with a JSON value, got {item!r}")
    if args.mvs:
        from image2sim.simulator.lift.mvs import MVSConfig

        try:
            MVSConfig.from_kwargs(**depth_kw)
        except (TypeError, ValueError) as exc:
            ap.error(f"--mvs: {exc}")
    only = set(args.only or ("pinhole", "panorama", "hm3d"))
    load = load_average()
    rows: list[dict] = []
    notes: list[str] = []
    with tempfile.TemporaryDirectory(prefix="image2sim-bench-lift-") as tmp_name:
        tmp = Path(tmp_name) if args.keep is None else args.keep
        tmp.mkdir(parents=True, exist_ok=True)
        for case in house_cases(args.quick):
            kind = "panorama" if case["camera"] == "equirect" else "pinhole"
            if kind in only:
                rows.append(run_house(case, args.seed, tmp, depth_kw, depth))
                print(json.dumps(rows[-1], default=str), file=sys.stderr, flush=True)
        if "hm3d" in only and not args.quick and not args.no_hm3d:
            if HM3D.is_dir():
                rows.append(run_hm3d(tmp, args.hm3d_every, args.hm3d_width, depth_kw, depth))
                print(json.dumps(rows[-1], default=str), file=sys.stderr, flush=True)
            else:
                notes.append(f"- HM3D sample absent ({HM3D}): its row is skipped.")
    checks = []
    for r in rows:
        checks += verdicts(r, HM3D_TARGETS if r["kind"] == "hm3d" else TARGETS)
    meta = {
        "hardware": hardware(),
        "date_utc": utc_now(),
        "load_average": load,
        "mode": "Quick smoke run" if args.quick else "Full run",
        "quick": args.quick,
        "depth_note": f", {depth_kw}" if depth_kw else ", default MVSConfig",
        "depth_options": depth_kw,
        "depth_source": depth[0],
        "depth_model": depth[1],
        "statistic": "one run per case; errors pooled over frames/pixels",
        "notes": notes,
        "checks": checks,
    }
    write_report("lift", rows, meta, markdown=markdown(rows, checks, meta), reports=reports)
    return {**meta, "rows": rows}


if __name__ == "__main__":
    main()
