"""Pinhole splats against the same Gaussians' panorama: the frustum-clamped Jacobian, before and after.

A pinhole splat linearises the projection at each Gaussian's mean (EWA). For a Gaussian beside the
camera, a few centimetres in front of its plane (a wall the agent passes, the floor under a camera
in a tight room), x/z reaches 10-100 and the unclamped Jacobian gives it a footprint of thousands of
pixels that reaches across the whole view, although none of its mass is in the frustum. Since
2026-11-28 (session 31) the Jacobian is evaluated with x/z and y/z clamped to the frustum widened by
``FRUSTUM_MARGIN`` (``splatting/project.py``: ``frustum_clamped``), as 3DGS and gsplat do.

The yardstick needs no ground truth: the equirectangular projection has no camera plane, so the
same Gaussians splatted into a panorama at the pinhole view's angular resolution and cut to the
pinhole view (``views_from_panorama``, as ``NeuralSimulator`` cuts its views) say what the pinhole
splat should show. Per case and variant: PSNR of the pinhole colour against the cut, depth AbsRel
(median of |d - d_cut| / d_cut over pixels both cover), the share of pixels within 10 % of the cut's
depth, and ms per frame (one thread, median of ``--repeats`` passes after a warm-up):

* ``clamped`` (now): the compiled kernel, ``GaussianRenderFn`` as the simulator calls it;
* ``unclamped`` (before): the torch backend with ``FRUSTUM_MARGIN`` = inf (the compiled kernel has
  the clamp built in; the torch backend is slower, so its time is not the kernel's before-time).

Cases: the HM3D sample's identity Gaussians (the data engine's default 336 px view, skipped without
``../shared``) and a sim2real training house (its ``splat_only`` simulator's 64 px view), at agent
poses (HM3D: capture centres with random headings; house: task starts on its navigation graph).
Writes ``reports/pinhole_views.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/pinhole_views.py [--poses 6] [--repeats 3] [--quick]``.
"""

from __future__ import annotations

import math

import numpy as np
from harness import _table, hardware, load_average, time_it, write_report
from splat_early_finish import HM3D, pinhole_cases, pose_args

NAME = "pinhole_views"


def _cut_reference(tensors: dict, poses: list[np.ndarray], px: int) -> list[dict]:
    """The panorama splat (px / 90 degrees of angular resolution) cut to each pose's pinhole view."""
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.sim import GaussianRenderFn, ObservationSpec, views_from_panorama

    fn = GaussianRenderFn(tensors, min_transmittance=1e-4)
    pano = EquirectCamera(2 * px, 4 * px)
    spec = ObservationSpec(panorama=False, pinhole=True, pinhole_size=px, pinhole_hfov_deg=90.0)
    return [views_from_panorama(fn(pano, pose), spec)["pinhole"] for pose in poses]


def _errors(outs: list[dict], refs: list[dict]) -> dict:
    d_rgb = np.concatenate([(o["rgb"] - r["rgb"]).ravel() for o, r in zip(outs, refs, strict=True)])
    mse = float(np.mean(d_rgb.astype(np.float64) ** 2))
    rel = []
    for o, r in zip(outs, refs, strict=True):
        ok = (r["depth"] > 0) & (o["depth"] > 0) & np.isfinite(o["depth"]) & np.isfinite(r["depth"])
        rel.append(np.abs(o["depth"][ok] - r["depth"][ok]) / r["depth"][ok])
    rel = np.concatenate(rel)
    return {
        "PSNR vs panorama cut dB": float("inf") if mse == 0 else round(-10.0 * math.log10(mse), 2),
        "depth AbsRel (median)": round(float(np.median(rel)), 4),
        "depth within 10 %": round(float((rel < 0.1).mean()), 3),
        "median depth m": round(float(np.median(np.concatenate([o["depth"].ravel() for o in outs]))), 3),
    }


def run_case(name: str, tensors: dict, poses: list[np.ndarray], px: int, repeats: int) -> list[dict]:
    from image2sim.simulator.geometry.cameras import PinholeCamera
    from image2sim.simulator.sim import GaussianRenderFn
    from image2sim.simulator.splatting import project

    camera = PinholeCamera(px / 2, px / 2, px / 2, px / 2, px, px)  # 90 degrees
    refs = _cut_reference(tensors, poses, px)
    rows = []
    for variant, backend in (("clamped", "auto"), ("unclamped", "torch")):
        fn = GaussianRenderFn(tensors, backend=backend)
        outs: list[dict] = []

        def one_pass(fn=fn, outs=outs) -> None:
            outs[:] = [fn(camera, pose) for pose in poses]

        if variant == "clamped":
            timing = time_it(one_pass, warmup=1, repeats=repeats)
        else:  # the projection as it was: no clamp (project.py reads the margin at every call)
            saved, project.FRUSTUM_MARGIN = project.FRUSTUM_MARGIN, math.inf
            try:
                timing = time_it(one_pass, warmup=1, repeats=1)
            finally:
                project.FRUSTUM_MARGIN = saved
        row = {
            "case": name,
            "view": f"pinhole {px}",
            "Gaussians": int(tensors["means"].shape[0]),
            "variant": variant,
            "backend": "cpu kernel" if backend == "auto" else "torch",
            "ms/frame": round(1000.0 * timing.wall / len(poses), 1),
            **_errors(outs, refs),
        }
        rows.append(row)
        print(row, flush=True)
    return rows


def main() -> None:
    args, poses, repeats = pose_args(__doc__, 6, 3, (2, 1), "2 poses, 1 repeat, the procedural house only")
    load_start, hw = load_average(), hardware()
    rows: list[dict] = []
    for name, tensors, cams, px in pinhole_cases(poses, args.seed, args.quick):
        rows += run_case(name, tensors, cams, px, repeats)
    hm3d = HM3D.is_dir() and not args.quick
    meta = {
        "load_average_start": load_start,
        "load_average_end": load_average(),
        "poses": poses,
        "repeats": repeats,
        "hm3d": hm3d,
    }
    lines = [
        "# Pinhole splats against the same Gaussians' panorama (`benchmarks/pinhole_views.py`)",
        "",
        f"- Hardware: {hw}; load average {load_start:.1f} at start, {load_average():.1f} at end.",
        f"- {poses} poses per case; `clamped`: median of {repeats} passes after one warm-up, `unclamped`: "
        "one pass after a warm-up (torch backend, not the kernel's before-time).",
        "- Yardstick: the same Gaussians splatted into a panorama at the view's angular resolution and cut "
        "to the pinhole view. Colour is the simulator's splat-only `normalised` colour; depth is z.",
        "",
        *_table(rows),
        "",
    ]
    write_report(NAME, rows, meta, markdown=lines)


if __name__ == "__main__":
    main()
