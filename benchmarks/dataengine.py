"""Benchmark the navigation data engine on tiny procedural scenes.

Measures (median of several runs after one warm-up, each run from an empty output folder so the
navigation map, graph and object database are rebuilt every time):
  * episodes per second per core with the template annotator, without rendering and with rendering
    (exact procedural renderer, pinhole observations), in-process on one core (torch limited to 1
    thread);
  * the Ray speed-up of 2 workers over 1 on the same scenes with rendering (Ray started and its workers
    warmed up before timing, so start-up is not counted; the reference is the 1-worker time measured
    in the same run).

Writes ``reports/dataengine.json`` and ``reports/dataengine.md``.
Run: ``.venv/bin/python benchmarks/dataengine.py [--quick]``.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
from pathlib import Path

from harness import hardware, load_average, time_it, write_report


def _runs(fn, repeats: int) -> list[float]:
    """Wall seconds of ``repeats`` runs after one warm-up (imports, caches of the first scene)."""
    return list(time_it(fn, warmup=1, repeats=repeats).walls)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--per-scene", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="2 scenes, 1 repeat (smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.repeats = 2, 1

    import torch

    torch.set_num_threads(1)
    from image2sim.dataengine.distributed import run_engine
    from image2sim.dataengine.pipeline import EngineConfig
    from image2sim.dataengine.procedural import preset, synthesize

    hw = f"{hardware()}; load average {load_average():.1f} at start"
    work = Path(tempfile.mkdtemp(prefix="bench_dataengine_"))
    try:
        scenes = work / "scenes"
        synthesize(preset("tiny"), scenes, scenes=args.scenes, seed=0, progress=False)
        counts: dict[str, int] = {}

        def local(render: str):
            def fn():
                out = work / f"out_{render}"
                shutil.rmtree(out, ignore_errors=True)
                cfg = EngineConfig(per_scene=args.per_scene, render=render, obs_height=96)
                s = run_engine(scenes, out, cfg, executor="local", progress=False)
                assert not s["failed"], s["failed"]
                counts[render] = s["episodes"]

            return fn

        rows = []
        for render in ("none", "procedural"):
            times = _runs(local(render), args.repeats)
            med = statistics.median(times)
            rows.append(
                {
                    "setting": f"local, 1 core, render={render}",
                    "episodes": counts[render],
                    "median_s": med,
                    "episodes_per_s_per_core": counts[render] / med,
                    "runs_s": [round(t, 3) for t in times],
                }
            )

        import ray

        ray_rows = {}
        for workers in (1, 2):
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
            try:

                def fn(workers=workers):
                    out = work / f"out_ray{workers}"
                    shutil.rmtree(out, ignore_errors=True)
                    # With rendering: enough work per scene that task overheads do not dominate.
                    cfg = EngineConfig(per_scene=args.per_scene, render="procedural", obs_height=96)
                    s = run_engine(scenes, out, cfg, executor="ray", workers=workers, progress=False)
                    assert not s["failed"], s["failed"]
                    counts[f"ray{workers}"] = s["episodes"]

                times = _runs(fn, args.repeats)
            finally:
                ray.shutdown()
            med = statistics.median(times)
            ray_rows[workers] = med
            rows.append(
                {
                    "setting": f"ray, {workers} worker(s), render=procedural",
                    "episodes": counts[f"ray{workers}"],
                    "median_s": med,
                    "episodes_per_s_per_core": counts[f"ray{workers}"] / med / workers,
                    "runs_s": [round(t, 3) for t in times],
                }
            )
        speedup = ray_rows[1] / ray_rows[2]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report = {
        "hardware": hw,
        "scenes": args.scenes,
        "per_scene_planned": args.per_scene,
        "repeats": args.repeats,
        "rows": rows,
        "ray_speedup_2_over_1": speedup,
        "target_speedup": 1.8,
    }
    lines = [
        "# Data engine benchmark",
        "",
        f"Hardware: {hw}. {args.scenes} tiny procedural scenes (`preset('tiny')`), {args.per_scene} episodes "
        f"planned per scene, template annotator; median of {args.repeats} runs after one warm-up, each "
        f"from an "
        "empty output folder (navigation map, graph and object mining included).",
        "",
        "| setting | episodes | median s | episodes / s / core | runs (s) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['setting']} | {r['episodes']} | {r['median_s']:.2f} | "
            f"{r['episodes_per_s_per_core']:.2f} | "
            f"{', '.join(str(t) for t in r['runs_s'])} |"
        )
    lines += [
        "",
        f"Ray speed-up, 2 workers over 1 (same run, Ray start-up excluded): **{speedup:.2f}x** "
        "(target >= 1.8x; the machine is shared, see the load average above).",
    ]
    write_report("dataengine", rows, {k: v for k, v in report.items() if k != "rows"}, markdown=lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
