"""Benchmark procedural scene synthesis: ray casters, a 512x1024 RGB-D+semantics panorama, a whole scene.

Casters compared in the same process on the same rays (first hit against every box of a default
scene): Embree through ``embreex`` (triangles), the tile-culled numpy slab test, and the brute-force
numpy slab test (every ray against every box; measured on a 128x256 panorama because it is slow,
and reported per million rays). The process is pinned to one core (``sched_setaffinity``) so Embree's
thread pool and numpy both run single-threaded, as the target ("< 1 s per panorama on one core")
asks. Timings are medians of several runs after a warm-up; the machine's load average is recorded
because the machine is shared.

Writes ``reports/bench_synth.json`` and ``reports/bench_synth.md``.
Run: ``.venv/bin/python benchmarks/synth.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path


def pin_one_core() -> str:
    """Restrict this process (and the thread pools it starts later) to one CPU core."""
    try:
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
        return f"pinned to core {core}"
    except (AttributeError, OSError):
        return "not pinned (sched_setaffinity unavailable)"


PINNED = pin_one_core()
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

from harness import hardware, time_it, utc_now, write_report  # noqa: E402
from image2sim.dataengine.procedural.capture import pose_matrix, sample_viewpoints, write_scene  # noqa: E402
from image2sim.dataengine.procedural.config import preset  # noqa: E402
from image2sim.dataengine.procedural.raycast import BoxCaster, EmbreeCaster, embree_available  # noqa: E402
from image2sim.dataengine.procedural.render import camera_rays, render  # noqa: E402
from image2sim.dataengine.procedural.scene import generate_scene, seed_streams  # noqa: E402
from image2sim.simulator.geometry.cameras import EquirectCamera  # noqa: E402


def hardware_pinned() -> str:
    """The harness hardware string plus the core pinning and the numpy version."""
    return f"{hardware()}; {PINNED}; numpy {np.__version__}"


CPU_TIMES: list[float] = []
"""CPU seconds (process time, all threads) of the runs of the most recent :func:`timeit` call."""


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, list[float]]:
    """Median wall time (s) of ``repeats`` runs after one warm-up, and all the runs.

    The process CPU time of each run is kept in :data:`CPU_TIMES`: on a shared, loaded machine it is
    the better measure of what one core needs (wall time includes waiting for other jobs).
    """
    t = time_it(fn, warmup=1, repeats=repeats)
    CPU_TIMES[:] = t.cpus
    return t.wall, list(t.walls)


def cpu() -> float:
    return statistics.median(CPU_TIMES)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and a smaller whole-scene run")
    args = parser.parse_args()
    repeats = 3 if args.quick else 5
    load_before = os.getloadavg()

    cfg = preset("default")
    results: dict = {"cases": []}

    gen_s, gen_runs = timeit(lambda: generate_scene(cfg, 0), repeats)
    scene = generate_scene(cfg, 0)
    results["scene"] = {
        "seed": 0,
        "rooms": len(scene.layout.rooms),
        "objects": len(scene.objects),
        "boxes": int(scene.box_lo.shape[0]),
    }
    results["cases"].append(
        {
            "case": "generate_scene (default preset: plan, furniture, GT grid)",
            "seconds": gen_s,
            "cpu_seconds": cpu(),
            "runs": gen_runs,
        }
    )

    view = sample_viewpoints(scene, 1, seed_streams(0)["capture"])[0]
    pose = pose_matrix(view)
    pano = EquirectCamera(512, 1024)
    origin, dirs, _ = camera_rays(pano, pose)

    casters = {"numpy (tile-culled slab test)": BoxCaster(scene.box_lo, scene.box_hi, cull=True)}
    if embree_available():
        casters = {"embree (embreex, triangles)": EmbreeCaster(scene.box_lo, scene.box_hi), **casters}
    cast_times = {}
    for name, caster in casters.items():
        s, runs = timeit(lambda c=caster: c.cast(origin, dirs, (512, 1024)), repeats)
        cast_times[name] = cpu()
        results["cases"].append(
            {
                "case": f"first-hit cast 512x1024 rays: {name}",
                "seconds": s,
                "cpu_seconds": cpu(),
                "runs": runs,
            }
        )
    small = EquirectCamera(128, 256)
    o_s, d_s, _ = camera_rays(small, pose)
    brute = BoxCaster(scene.box_lo, scene.box_hi, cull=False)
    s, runs = timeit(lambda: brute.cast(o_s, d_s), max(1, repeats // 2))
    brute_per_pano = cpu() * (512 * 1024) / (128 * 256)
    results["cases"].append(
        {
            "case": "first-hit cast 128x256 rays: numpy brute force (all rays x all boxes)",
            "seconds": s,
            "cpu_seconds": cpu(),
            "runs": runs,
            "extrapolated_512x1024_cpu_seconds": brute_per_pano,
        }
    )
    cast_times["numpy brute force (extrapolated)"] = brute_per_pano

    fastest = min(cast_times, key=cast_times.get)
    results["caster_ratio_vs_fastest"] = {k: v / cast_times[fastest] for k, v in cast_times.items()}
    results["chosen_caster"] = fastest

    for kind in (["embree"] if embree_available() else []) + ["numpy"]:
        s, runs = timeit(lambda k=kind: render(scene, pano, pose, caster=k), repeats)
        results["cases"].append(
            {
                "case": f"render 512x1024 panorama RGB-D + semantics + instances ({kind})",
                "seconds": s,
                "cpu_seconds": cpu(),
                "runs": runs,
            }
        )

    views = 6 if args.quick else 24
    scene_cfg = preset("default")
    import dataclasses

    scene_cfg = dataclasses.replace(scene_cfg, capture=dataclasses.replace(scene_cfg.capture, views=views))
    with tempfile.TemporaryDirectory() as tmp:
        c0 = time.process_time()
        t0 = time.perf_counter()
        write_scene(generate_scene(scene_cfg, 1), Path(tmp) / "scene")
        whole = time.perf_counter() - t0
        whole_cpu = time.process_time() - c0
    results["cases"].append(
        {
            "case": f"whole scene: generate + {views} panoramas 512x1024 + write capture and gt/ (1 run)",
            "seconds": whole,
            "cpu_seconds": whole_cpu,
            "runs": [whole],
            "per_view_cpu_seconds": whole_cpu / views,
        }
    )

    results["hardware"] = hardware_pinned()
    results["date"] = utc_now()
    results["load_average_before_after"] = [list(load_before), list(os.getloadavg())]
    results["target"] = "< 1 s per 512x1024 RGB-D+semantics panorama on one core"
    results["timing_note"] = (
        "seconds = median wall time; cpu_seconds = median process CPU time (all threads, "
        "process pinned to one core); the caster comparison uses CPU time"
    )
    lines = [
        "# Procedural synthesis benchmark",
        "",
        f"Hardware: {results['hardware']}  ",
        f"Date: {results['date']}; "
        f"load average before/after: {load_before[0]:.1f} / {os.getloadavg()[0]:.1f} "
        "(shared machine: other jobs inflate every figure)  ",
        f"Scene: default preset seed 0, {results['scene']['rooms']} rooms, "
        f"{results['scene']['objects']} objects, "
        f"{results['scene']['boxes']} boxes. Median of {repeats} runs after a warm-up unless stated.",
        "",
        "| case | wall s | CPU s (one core) |",
        "|---|---:|---:|",
    ]
    for case in results["cases"]:
        extra = ""
        if "extrapolated_512x1024_cpu_seconds" in case:
            extra = f" (x16 -> {case['extrapolated_512x1024_cpu_seconds']:.2f} s per 512x1024)"
        lines.append(f"| {case['case']} | {case['seconds']:.3f} | {case['cpu_seconds']:.3f}{extra} |")
    lines += [
        "",
        f"Fastest caster (CPU time): **{fastest}** "
        '(`caster="auto"` uses Embree when embreex is importable, else the culled numpy caster). '
        "CPU time relative to it:",
        "",
    ]
    lines += [f"- {k}: {v:.1f}x" for k, v in results["caster_ratio_vs_fastest"].items()]
    lines.append("")
    meta = {k: v for k, v in results.items() if k != "cases"}
    write_report("bench_synth", results["cases"], meta, markdown=lines, rows_key="cases")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
