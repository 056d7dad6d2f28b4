"""Benchmark ``splat``: ms per frame per backend, forward and forward+backward, plus peak memory.

Scenes are Gaussians on the walls, floor and ceiling of a 8 x 6 x 3 m room around the camera (sizes
set so the surfaces are covered, as in a lifted capture), float32, 16 feature channels.

Cases
* headline (the issue's targets): 100k Gaussians into a 256x512 panorama, forward and
  forward+backward, compiled ``cpu`` backend and ``torch`` backend in the same run (the torch
  backend takes tens of seconds per frame here, so it may run fewer timed repeats:
  ``--torch-repeats``, recorded per row); the verdict on the targets (>= 20 frames/s forward,
  >= 30x torch) is written into the JSON, by wall clock and by CPU time.
* pinhole: 20k Gaussians into a 256x256 90-degree pinhole view, cpu and torch backends.
* dense: the dense reference only on a small case (it is O(pixels x Gaussians)).
* grid (the issue): N in {10k, 100k, 1M} x {128x256, 256x512, 512x1024} panoramas for the compiled
  backend (1M: forward only, to bound the run time on a shared machine); the torch backend on
  the 10k 256x512 cases; ratio torch / cpu in the same run.
* Forward runs under ``torch.no_grad()`` (inference: the fused C++ projection); forward+backward
  uses the differentiable torch projection and the kernel's hand-written backward.
* memory: peak RSS of a fresh process doing one forward+backward with the compiled backend, to
  show linear growth in N and in pixels.

Timing: median of ``--repeats`` (>= 5) runs after one warm-up; the CPU model, thread count and the
load average (the machine is shared) are recorded. Writes ``reports/splatting.json`` and
``reports/splatting.md``. Run: ``.venv/bin/python benchmarks/splatting.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from harness import REPORTS, hardware, time_it, utc_now, write_report, write_text_atomic
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.splatting import available_backends, splat
from rich.progress import Progress

ROOT = Path(__file__).resolve().parents[1]


def room_scene(n: int, seed: int = 0, channels: int = 16) -> list[torch.Tensor]:
    """N Gaussians on the six faces of an 8 x 6 x 3 m room centred on the origin (camera at 1.5 m)."""
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([8.0, 6.0, 3.0])
    areas = torch.tensor([6 * 3, 6 * 3, 8 * 3, 8 * 3, 8 * 6, 8 * 6], dtype=torch.float32)
    face = torch.multinomial(areas, n, replacement=True, generator=g)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * size
    axis = face // 2
    side = (face % 2).float() * 2 - 1
    pts[torch.arange(n), axis] = side * size[axis] / 2
    pts[:, 2] += 1.5 - 0.0  # camera at height 1.5 above the floor centre -> floor at z = -1.5
    pts[:, 2] -= 1.5
    spacing = math.sqrt(float(areas.sum()) / n)
    scales = spacing * (0.4 + 0.4 * torch.rand(n, 3, generator=g))
    scales[torch.arange(n), axis] *= 0.1  # flat on the surface
    quats = torch.randn(n, 4, generator=g)
    opac = 0.3 + 0.7 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    feats = torch.randn(n, channels, generator=g)
    return [pts, scales, quats, opac, colors, feats]


def upright_pose() -> torch.Tensor:
    """Camera at the origin looking along world +X, upright (OpenCV axes, world Z up)."""
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    return pose


def time_case(scene, camera, backend: str, backward: bool, repeats: int) -> dict:
    """Median seconds per frame (one warm-up) of forward or forward+backward."""
    pose = upright_pose()
    if backward:
        inputs = [t.clone().requires_grad_() for t in scene]
    else:
        inputs = scene

    def run():
        if backward:
            out = splat(*inputs, camera, pose, backend=backend)
            loss = out.rgb.sum() + out.depth.sum() + out.alpha.sum() + out.features.sum()
            loss.backward()
            for t in inputs:
                t.grad = None
            return out
        with torch.no_grad():
            return splat(*inputs, camera, pose, backend=backend)

    out = run()  # the warm-up; its output gives the mean alpha
    t = time_it(run, warmup=0, repeats=repeats)
    return {
        "ms": 1000 * t.wall,
        "ms_min": 1000 * min(t.walls),
        "cpu_ms": 1000 * t.cpu,
        "runs": repeats,
        "mean_alpha": float(out.alpha.detach().mean()),
    }


_MEM_CHILD = r"""
import json, sys, torch
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from splatting import room_scene, upright_pose
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.splatting import splat


def status(key):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(key)


n, h, w = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
scene = [t.requires_grad_() for t in room_scene(n)]
cam, pose = EquirectCamera(h, w), upright_pose()
with torch.no_grad():
    splat(*scene, EquirectCamera(8, 16), pose, backend="cpu")  # load the extension first
base = status("VmRSS")
Path("/proc/self/clear_refs").write_text("5")  # reset the high-water mark (VmHWM) to the current RSS
with torch.no_grad():
    splat(*scene, cam, pose, backend="cpu")
fwd = status("VmHWM")
Path("/proc/self/clear_refs").write_text("5")
out = splat(*scene, cam, pose, backend="cpu")
(out.rgb.sum() + out.features.sum() + out.depth.sum()).backward()
print(json.dumps({"baseline_rss_mb": base, "peak_forward_mb": fwd, "peak_rss_mb": status("VmHWM")}))
"""


def peak_memory(n: int, h: int, w: int) -> dict:
    """Peak RSS (MB, VmHWM) of a fresh process above its baseline (scene built, extension loaded)
    for one inference forward and for one forward+backward."""
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(_MEM_CHILD)
    try:
        res = subprocess.run(
            [sys.executable, f.name, str(Path(__file__).parent), str(n), str(h), str(w)],
            capture_output=True,
            text=True,
            check=True,
        )
    finally:
        os.unlink(f.name)
    data = json.loads(res.stdout.strip().splitlines()[-1])
    data["splat_mb"] = data["peak_rss_mb"] - data["baseline_rss_mb"]
    data["splat_forward_mb"] = data["peak_forward_mb"] - data["baseline_rss_mb"]
    return data


READING = [
    "How to read this (the machine is a shared 2-core VM; other jobs ran throughout, see the load",
    "averages):",
    "",
    "* Wall clock is what a user of this machine saw at that moment; with a load average well above 2",
    "  the two worker threads rarely get both cores, so wall figures understate the kernel.",
    "* CPU time / threads is the wall time the same work needs when its threads are not preempted;",
    "  it is the figure to compare with the 20 frames/s target on an idle 2-core CPU, but it is a",
    "  projection, not a measurement of an idle machine.",
    "* forward+backward (training path) runs torch autograd ops for the projection around the",
    "  kernel; torch's OpenMP workers spin between those ops, so under load its CPU time at 2",
    "  threads is inflated and noisy. The single-thread table below has no such spinning.",
    "* The torch backend is inflated the same way at 2 threads (compare its 2-thread CPU ms with",
    "  the single-thread table), so the 2-thread ratios overstate the gain; the single-thread",
    "  ratio is the conservative one and is listed as its own target row.",
    "",
]


def _targets_markdown(t: dict) -> list[str]:
    if "wall_fps" not in t:
        return []
    yes = {True: "met", False: "NOT met"}
    lines = [
        f"## Targets ({t['case']}, {t['threads']} threads)",
        "",
        "| target | by wall clock (under this machine's load) | by CPU time / threads (unpreempted) |",
        "|---|---|---|",
        f"| >= {t['fps_target']:.0f} frames/s | {t['wall_fps']:.1f} fps: {yes[t['fps_met_wall']]} | "
        f"{t['cpu_time_fps']:.1f} fps ({t['cpu_ms_per_frame']:.1f} CPU ms/frame): "
        f"{yes[t['fps_met_cpu_time']]} |",
    ]
    if "speedup_wall" in t:
        lines.append(
            f"| >= {t['speedup_target']:.0f}x the torch backend | {t['speedup_wall']:.1f}x: "
            f"{yes[t['speedup_met_wall']]} | {t['speedup_cpu_time']:.1f}x: {yes[t['speedup_met_cpu_time']]} |"
        )
    if "speedup_single_thread_cpu_time" in t:
        lines.append(
            f"| >= {t['speedup_target']:.0f}x the torch backend, one thread each (no spinning) | – | "
            f"{t['speedup_single_thread_cpu_time']:.1f}x: {yes[t['speedup_met_single_thread']]} |"
        )
    if "forward_backward_speedup_wall" in t:
        lines.append(
            f"| forward+backward vs torch (no target) | {t['forward_backward_speedup_wall']:.1f}x | "
            f"{t['forward_backward_speedup_cpu_time']:.1f}x |"
        )
    return [*lines, ""]


def render_markdown(report: dict) -> str:
    """Markdown tables of a report dict (as written to splat.json)."""
    lines = [
        "# splat benchmark",
        "",
        f"{report['date']} · {report['hardware']} · load average before/after "
        f"{report['load_average_before'][0]:.1f} / {report['load_average_after'][0]:.1f} (shared machine)",
        "",
        "ms/frame is wall clock (median); CPU ms is the process CPU time per frame (all threads), which",
        "is far less sensitive to the other jobs on this machine.",
        "",
        f"Runs: {report.get('note', '')}.",
        "",
        *_targets_markdown(report.get("targets", {})),
        *READING,
        "| group | N | camera | HxW | backend | pass | runs | ms/frame (median) | frames/s | CPU ms "
        "| vs torch | vs dense |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["cases"]:
        vs_t = f"{r['speedup_vs_torch']:.1f}x" if "speedup_vs_torch" in r and r["backend"] != "torch" else ""
        vs_d = (
            f"{r['speedup_vs_dense_reference']:.1f}x"
            if "speedup_vs_dense_reference" in r and r["backend"] != "reference"
            else ""
        )
        lines.append(
            f"| {r['group']} | {r['n']:,} | {r['camera']} | {r['height']}x{r['width']} | {r['backend']} | "
            f"{r['pass']} | {r['runs']} | {r['ms']:.1f} | {1000 / r['ms']:.1f} | {r['cpu_ms']:.1f} | "
            f"{vs_t} | {vs_d} |"
        )
    memory = report.get("memory", [])
    if memory:
        lines += [
            "",
            "Peak memory of a fresh process above its baseline (scene built, extension loaded), compiled",
            "backend, from /proc VmHWM reset before each pass:",
            "",
            "| N | HxW | baseline RSS MB | forward (no grad) MB | forward+backward MB |",
            "|---|---|---|---|---|",
        ]
        for m in memory:
            lines.append(
                f"| {m['n']:,} | {m['height']}x{m['width']} | {m['baseline_rss_mb']:.0f} | "
                f"{m.get('splat_forward_mb', float('nan')):.0f} | {m['splat_mb']:.0f} |"
            )
    single = report.get("single_thread", [])
    if single:
        lines += [
            "",
            "Single thread (`torch.set_num_threads(1)`), process CPU time per frame (median): the",
            "figure least affected by the other jobs on this machine.",
            "",
            "| N | HxW | backend | pass | CPU ms/frame | frames/s per core | vs torch |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in single:
            vs = f"{r['cpu_speedup_vs_torch']:.1f}x" if "cpu_speedup_vs_torch" in r else ""
            lines.append(
                f"| {r['n']:,} | {r['height']}x{r['width']} | {r['backend']} | {r['pass']} | "
                f"{r['cpu_ms']:.1f} | {1000 / r['cpu_ms']:.1f} | {vs} |"
            )
    return "\n".join(lines) + "\n"


def single_thread_rows(repeats: int, torch_repeats: int) -> list[dict]:
    """One-thread process-CPU time of the headline panorama cases, cpu vs torch backend."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        cam = EquirectCamera(256, 512)
        for n, bw in ((20_000, False), (100_000, False), (20_000, True)):
            scene = room_scene(n)
            for be in ("cpu", "torch"):
                res = time_case(
                    scene, cam, be, bw, torch_repeats if (be == "torch" and n >= 100_000) else repeats
                )
                rows.append(
                    {
                        "n": n,
                        "height": 256,
                        "width": 512,
                        "backend": be,
                        "pass": "forward+backward" if bw else "forward",
                        **res,
                    }
                )
                print(
                    f"single-thread N={n} {be} {rows[-1]['pass']}: CPU {res['cpu_ms']:.1f} ms",
                    file=sys.stderr,
                    flush=True,
                )
            rows[-2]["cpu_speedup_vs_torch"] = rows[-1]["cpu_ms"] / rows[-2]["cpu_ms"]
    finally:
        torch.set_num_threads(threads)
    return rows


def target_verdict(rows: list[dict], threads: int) -> dict:
    """The issue's targets on the headline case (100k, 256x512 panorama, forward), judged twice.

    * wall: the measured median wall time (what a user sees on this machine, under its load);
    * cpu: process CPU time per frame divided by the thread count, i.e. the wall time the same
      work takes when the threads are not preempted by other jobs (the ideal idle 2-core figure).
    """

    def pick(be: str, ps: str) -> dict | None:
        for r in rows:
            if (r["group"], r["backend"], r["pass"]) == ("headline", be, ps):
                return r
        return None

    out: dict = {
        "case": "100k Gaussians, equirect 256x512, forward",
        "fps_target": 20.0,
        "speedup_target": 30.0,
    }
    cpu, tor = pick("cpu", "forward"), pick("torch", "forward")
    if cpu is None:
        return out
    out["threads"] = threads
    out["wall_fps"] = 1000.0 / cpu["ms"]
    out["cpu_ms_per_frame"] = cpu["cpu_ms"]
    out["cpu_time_fps"] = 1000.0 * threads / cpu["cpu_ms"]
    out["fps_met_wall"] = out["wall_fps"] >= 20.0
    out["fps_met_cpu_time"] = out["cpu_time_fps"] >= 20.0
    if tor is not None:
        out["speedup_wall"] = tor["ms"] / cpu["ms"]
        out["speedup_cpu_time"] = tor["cpu_ms"] / cpu["cpu_ms"]
        out["speedup_met_wall"] = out["speedup_wall"] >= 30.0
        out["speedup_met_cpu_time"] = out["speedup_cpu_time"] >= 30.0
    for ps in ("forward+backward",):
        c, t = pick("cpu", ps), pick("torch", ps)
        if c is not None and t is not None:
            out["forward_backward_speedup_wall"] = t["ms"] / c["ms"]
            out["forward_backward_speedup_cpu_time"] = t["cpu_ms"] / c["cpu_ms"]
    return out


def add_single_thread_verdict(targets: dict, single: list[dict]) -> dict:
    """The speed-up target judged on the single-thread CPU times (no OpenMP spinning on either side)."""
    rows = {(r["n"], r["backend"], r["pass"]): r for r in single}
    cpu, tor = rows.get((100_000, "cpu", "forward")), rows.get((100_000, "torch", "forward"))
    if cpu is not None and tor is not None:
        targets["speedup_single_thread_cpu_time"] = tor["cpu_ms"] / cpu["cpu_ms"]
        targets["speedup_met_single_thread"] = targets["speedup_single_thread_cpu_time"] >= 30.0
    return targets


def memory_rows() -> list[dict]:
    """Peak memory for N in {10k, 100k, 1M} at 256x512 and 100k at three resolutions."""
    rows = []
    for n, h, w in (
        (10_000, 256, 512),
        (100_000, 256, 512),
        (1_000_000, 256, 512),
        (100_000, 128, 256),
        (100_000, 512, 1024),
    ):
        rows.append({"n": n, "height": h, "width": w, **peak_memory(n, h, w)})
        print(f"memory N={n} {h}x{w}: {rows[-1]}", file=sys.stderr, flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--torch-repeats",
        type=int,
        default=3,
        help="timed runs of the torch backend at N >= 100k (tens of seconds each; recorded per row)",
    )
    ap.add_argument("--quick", action="store_true", help="headline cases only")
    ap.add_argument("--memory-only", action="store_true", help="only (re)measure peak memory, merge it in")
    ap.add_argument(
        "--single-thread-only",
        action="store_true",
        help="only (re)measure the single-thread section and merge it into reports/splatting.json",
    )
    args = ap.parse_args()
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5")
    if args.torch_repeats < 1:
        raise SystemExit("--torch-repeats must be >= 1")
    if args.memory_only:
        report = json.loads((REPORTS / "splatting.json").read_text())
        report["memory"] = memory_rows()
        report["memory_git_commit"] = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        write_text_atomic(REPORTS / "splatting.json", json.dumps(report, indent=2) + "\n")
        write_text_atomic(REPORTS / "splatting.md", render_markdown(report))
        print(render_markdown(report))
        return
    if args.single_thread_only:
        report = json.loads((REPORTS / "splatting.json").read_text())
        report["single_thread"] = single_thread_rows(args.repeats, args.torch_repeats)
        report["single_thread_date"] = utc_now()
        report["single_thread_git_commit"] = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        write_text_atomic(REPORTS / "splatting.json", json.dumps(report, indent=2) + "\n")
        write_text_atomic(REPORTS / "splatting.md", render_markdown(report))
        print(render_markdown(report))
        return
    backends = available_backends()
    if "cpu" not in backends:
        raise SystemExit("compiled CPU backend unavailable; nothing to benchmark against")
    load_before = os.getloadavg()

    pano = EquirectCamera(256, 512)
    pin = PinholeCamera.from_fov(90.0, 90.0, 256, 256)
    plan: list[tuple[str, int, object, str, bool]] = []
    for be in ("cpu", "torch"):
        for bw in (False, True):
            plan.append(("headline", 100_000, pano, be, bw))
    for be in ("cpu", "torch"):
        for bw in (False, True):
            plan.append(("pinhole", 20_000, pin, be, bw))
    plan += [
        ("dense", 2_000, EquirectCamera(64, 128), be, bw)
        for be in ("cpu", "torch", "reference")
        for bw in (False, True)
    ]
    if not args.quick:
        for n in (10_000, 100_000, 1_000_000):
            for h, w in ((128, 256), (256, 512), (512, 1024)):
                for bw in (False, True) if n <= 100_000 else (False,):  # 1M: forward only (time)
                    plan.append(("grid", n, EquirectCamera(h, w), "cpu", bw))
        plan.append(("grid", 10_000, EquirectCamera(256, 512), "torch", True))
        plan.append(("grid", 10_000, EquirectCamera(256, 512), "torch", False))

    scenes: dict[int, list[torch.Tensor]] = {}
    rows = []
    with Progress() as progress:
        task = progress.add_task("splat benchmark", total=len(plan))
        for group, n, cam, be, bw in plan:
            scene = scenes.setdefault(n, room_scene(n))
            reps = args.torch_repeats if (be == "torch" and n >= 100_000) else args.repeats
            load = os.getloadavg()[0]
            res = time_case(scene, cam, be, bw, reps)
            res["load_average_1min"] = load
            rows.append(
                {
                    "group": group,
                    "n": n,
                    "camera": cam.model,
                    "height": cam.height,
                    "width": cam.width,
                    "backend": be,
                    "pass": "forward+backward" if bw else "forward",
                    **res,
                }
            )
            progress.advance(task)
            print(
                f"{group} N={n} {cam.model} {cam.height}x{cam.width} {be} {rows[-1]['pass']}: "
                f"{res['ms']:.1f} ms (CPU {res['cpu_ms']:.1f} ms)",
                file=sys.stderr,
                flush=True,
            )

    # ratios against the torch backend (and the dense reference) measured in this run
    def find(group, n, model, h, w, be, ps):
        for r in rows:
            if (r["group"], r["n"], r["camera"], r["height"], r["width"], r["backend"], r["pass"]) == (
                group,
                n,
                model,
                h,
                w,
                be,
                ps,
            ):
                return r
        return None

    for r in rows:
        t = find(r["group"], r["n"], r["camera"], r["height"], r["width"], "torch", r["pass"])
        if t is not None:
            r["speedup_vs_torch"] = t["ms"] / r["ms"]
            r["cpu_speedup_vs_torch"] = t["cpu_ms"] / r["cpu_ms"]
        d = find(r["group"], r["n"], r["camera"], r["height"], r["width"], "reference", r["pass"])
        if d is not None:
            r["speedup_vs_dense_reference"] = d["ms"] / r["ms"]

    memory = [] if args.quick else memory_rows()
    targets = target_verdict(rows, torch.get_num_threads())

    report = {
        "benchmark": "splatting",
        "date": utc_now(),
        "hardware": hardware(),
        "git_commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip(),
        "threads": torch.get_num_threads(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "note": "shared 2-core machine: other jobs ran concurrently (see load averages); medians of "
        f"{args.repeats} runs after one warm-up ({args.torch_repeats} for the torch backend at N >= 100k, "
        "see each row's runs); float32, 16 feature channels",
        "targets": targets,
        "cases": rows,
        "memory": memory,
        "single_thread": [] if args.quick else single_thread_rows(args.repeats, args.torch_repeats),
    }
    add_single_thread_verdict(report["targets"], report["single_thread"])
    meta = {k: v for k, v in report.items() if k != "cases"}
    write_report("splatting", rows, meta, markdown=render_markdown(report), rows_key="cases")
    print(render_markdown(report))


if __name__ == "__main__":
    main()
