"""Speed against error of ``splat``'s ``min_transmittance``: how early a pixel may stop compositing.

3DGS and gsplat finish a pixel once its transmittance T falls below 1e-4. What a pixel finished at
T < t leaves out weighs less than t, so every output moves by at most t times the spread of the
values behind it (``tests/simulator/test_splatting.py`` checks the bound). A tile of the CPU kernel
stops only when all its pixels are finished, and on fused real scenes a few pixels per tile stay
between 1e-4 and 1e-3 to the end of the list, so a larger t lets most tiles stop at the first
surface instead of walking every Gaussian behind it.

Cases (the simulator's observations, through :class:`~image2sim.simulator.sim.GaussianRenderFn`,
splat-only ``normalised`` colour, one thread):

* ``procedural``: one house as the sim2real pipeline captures its training houses (preset
  ``default``, tier ``middle``, Gaussians of ``configs/gaussians/coarse.yaml``) at ``--poses`` agent
  poses on its navigation graph: the 128x256 panorama the pixel-flow renderer conditions on, and the
  64 px pinhole view of the ``splat_only`` simulator;
* ``hm3d``: the HM3D sample (skipped when ``../shared`` is absent), identity Gaussians at the data
  engine's default config, at ``--poses`` capture camera positions with random headings: the data
  engine's 336 px pinhole view and the 128x256 panorama.

Per case and threshold: ms per frame (median of ``--repeats`` passes over all poses after one
warm-up pass, divided by the poses), the speed-up against 1e-4 measured in the same run, and the
error against the 1e-4 image: largest colour change, PSNR of the change, the share of 8-bit colour
values that change, and the largest change of the (normalised) depth in metres.
Writes ``reports/splat_early_finish.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/splat_early_finish.py [--poses 8] [--repeats 5] [--quick]``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report

NAME = "splat_early_finish"
REFERENCE = 1e-4
THRESHOLDS = (1e-4, 1e-3, 2e-3, 4e-3, 1e-2)
ROOT = Path(__file__).resolve().parents[1]
HM3D = ROOT.parent / "shared" / "data" / "hm3d_360" / "00000-kfPV7w3FaU5"


def _procedural(work: Path, poses: int, seed: int):
    """(tensor dict, camera-to-world poses) of the sim2real pipeline's kind of training house."""
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians.config import load_gaussian_config
    from image2sim.simulator.sim import gaussian_tensors
    from scene_density import agent_poses, house

    capture, _ = house(work, "default", seed, "middle")
    cfg = load_gaussian_config(ROOT / "configs" / "gaussians" / "coarse.yaml")
    g = build_scene(capture, cfg, encoder="identity").gaussians
    return gaussian_tensors(g), agent_poses("default", seed, poses)


def _hm3d(poses: int, seed: int):
    """(tensor dict, poses) of the HM3D sample: the data engine's identity Gaussians, cameras at the
    capture's camera positions with random headings."""
    from image2sim.simulator.conventions import camera_rotation_for_heading
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians.config import gaussian_config_from_dict
    from image2sim.simulator.io import open_capture
    from image2sim.simulator.sim import gaussian_tensors

    g = build_scene(HM3D, gaussian_config_from_dict({}), encoder="identity").gaussians
    centres = [np.asarray(f.cam_to_world, dtype=np.float64)[:3, 3] for f in open_capture(HM3D)]
    rng = np.random.default_rng(seed)
    out = []
    for i in rng.choice(len(centres), size=min(poses, len(centres)), replace=False):
        pose = np.eye(4)
        pose[:3, :3] = camera_rotation_for_heading(float(rng.uniform(-math.pi, math.pi)))
        pose[:3, 3] = centres[i]
        out.append(pose)
    return gaussian_tensors(g), out


def pose_args(doc: str, poses: int, repeats: int, quick: tuple[int, int], quick_help: str):
    """(args, poses, repeats) of a per-pose splat benchmark's command line (``--poses --repeats --seed
    --quick``; ``quick``: its poses and repeats). Sets torch to one thread, as the simulator runs."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--poses", type=int, default=poses)
    ap.add_argument("--repeats", type=int, default=repeats)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    args = ap.parse_args()
    torch.set_num_threads(1)
    return (args, *quick) if args.quick else (args, args.poses, args.repeats)


def pinhole_cases(poses: int, seed: int, quick: bool):
    """(name, tensors, poses, view px) of the pinhole benchmarks' scenes: a sim2real training house
    (its simulator's 64 px view), then the HM3D sample (the data engine's 336 px view; not when
    ``quick`` or without ``../shared``)."""
    with tempfile.TemporaryDirectory(prefix="bench_pinhole_") as tmp:
        tensors, cams = _procedural(Path(tmp), poses, seed)
        yield "procedural (sim2real house)", tensors, cams, 64
    if HM3D.is_dir() and not quick:
        tensors, cams = _hm3d(poses, seed)
        yield "HM3D sample", tensors, cams, 336


def _errors(outs: list[dict], refs: list[dict]) -> dict:
    """Largest colour change, PSNR of the change, share of changed 8-bit values, largest depth change."""
    d_rgb = np.concatenate([(o["rgb"] - r["rgb"]).ravel() for o, r in zip(outs, refs, strict=True)])
    q = np.concatenate(
        [
            (np.round(o["rgb"] * 255) != np.round(r["rgb"] * 255)).ravel()
            for o, r in zip(outs, refs, strict=True)
        ]
    )
    d_depth = max(float(np.nanmax(np.abs(o["depth"] - r["depth"]))) for o, r in zip(outs, refs, strict=True))
    mse = float(np.mean(d_rgb.astype(np.float64) ** 2))
    return {
        "max colour change": float(np.abs(d_rgb).max()),
        "PSNR of change dB": float("inf") if mse == 0 else -10.0 * math.log10(mse),
        "8-bit values changed %": 100.0 * float(q.mean()),
        "max depth change m": d_depth,
    }


def run_case(name: str, tensors: dict, cams: list[np.ndarray], camera, view: str, repeats: int) -> list[dict]:
    from image2sim.simulator.sim import GaussianRenderFn

    rows: list[dict] = []
    ref_outs: list[dict] = []
    ref_ms = None
    for t in THRESHOLDS:
        fn = GaussianRenderFn(tensors, min_transmittance=t)
        outs: list[dict] = []

        def one_pass(fn=fn, outs=outs) -> None:
            outs[:] = [fn(camera, pose) for pose in cams]

        timing = time_it(one_pass, warmup=1, repeats=repeats)
        ms = 1000.0 * timing.wall / len(cams)
        if t == REFERENCE:
            ref_outs, ref_ms = list(outs), ms
        row = {
            "case": name,
            "view": view,
            "Gaussians": int(tensors["means"].shape[0]),
            "min_transmittance": t,
            "ms/frame": round(ms, 1),
            "speed-up vs 1e-4": round(ref_ms / ms, 2),
            **_errors(outs, ref_outs),
        }
        rows.append(row)
        print(row, flush=True)
    return rows


def main() -> None:
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

    args, poses, repeats = pose_args(__doc__, 8, 5, (3, 2), "3 poses, 2 repeats, procedural only")
    load_start, hw = load_average(), hardware()
    pano = EquirectCamera(128, 256)

    def pinhole(px: int) -> PinholeCamera:
        return PinholeCamera(px / 2, px / 2, px / 2, px / 2, px, px)  # 90 degrees

    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_early_finish_") as tmp:
        tensors, cams = _procedural(Path(tmp), poses, args.seed)
        rows += run_case("procedural (sim2real house)", tensors, cams, pano, "panorama 128x256", repeats)
        rows += run_case("procedural (sim2real house)", tensors, cams, pinhole(64), "pinhole 64", repeats)
    if HM3D.is_dir() and not args.quick:
        tensors, cams = _hm3d(poses, args.seed)
        rows += run_case("HM3D sample", tensors, cams, pinhole(336), "pinhole 336", repeats)
        rows += run_case("HM3D sample", tensors, cams, pano, "panorama 128x256", repeats)
    meta = {
        "load_average_start": load_start,
        "load_average_end": load_average(),
        "poses": poses,
        "repeats": repeats,
        "thresholds": list(THRESHOLDS),
        "hm3d": HM3D.is_dir() and not args.quick,
    }
    from harness import _table

    lines = [
        "# Speed against error of `splat`'s `min_transmittance` (`benchmarks/splat_early_finish.py`)",
        "",
        f"- Hardware: {hw}; load average {load_start:.1f} at start, {load_average():.1f} at end.",
        f"- {poses} poses per case, median of {repeats} passes after one warm-up; the errors compare each "
        "threshold's images with the 1e-4 images of the same run (splat-only `normalised` colour, as the "
        "simulator returns it; depth normalised, metres).",
        "- The simulator's observations use `OBSERVATION_MIN_TRANSMITTANCE` (`simulator/sim.py`); metrics "
        "(`eval render`) and training splat at 1e-4.",
        "",
        *_table(rows),
        "",
    ]
    write_report(NAME, rows, meta, markdown=lines)


if __name__ == "__main__":
    main()
