"""Benchmark the navigation data engine on tiny procedural scenes.

Measures (median of several runs after one warm-up, each run from an empty output folder so the
navigation map, graph and object database are rebuilt every time):
  * episodes per second per core with the template annotator, without rendering and with rendering
    (exact procedural renderer, pinhole observations), in-process on one core (torch limited to 1
    thread);
  * the Ray speed-up of 2 workers over 1 on the same scenes with rendering. One local Ray instance
    (2 CPUs) is started and both workers are warmed up before any timing, so Ray start-up and worker
    start-up are not counted; the 1-worker pass keeps one task in flight, the 2-worker pass two. The
    1- and 2-worker runs alternate so that a change in the shared machine's load hits both alike.

Because the machine is shared, every run also records: the driver's CPU seconds, every task's wall
and CPU seconds (from the worker, per process), the machine-wide busy CPU seconds from /proc/stat
(so the CPU used by other processes is known), and the 1-minute load average before and after. From
these the report splits each run's lost core-seconds into "task waiting for a CPU" (task wall - task
CPU: contention with other processes) and "worker idle" (workers x wall - sum of task walls: serial
driver work, scheduling and the tail of the last scene), and gives a CPU-time-based speed-up
(the speed-up had every task got a whole core: sum of task CPU over 1 worker / critical-path CPU).

Writes ``reports/dataengine.json`` and ``reports/dataengine.md``.
Run: ``.venv/bin/python benchmarks/dataengine.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
from pathlib import Path

from harness import hardware, load_average, time_it, write_report

SHORT_PATHS = {"min_path_length": 1.0}
"""Tiny houses are smaller than the task's 3 m minimum path (every bucket infeasible: 0-3 episodes
of 64 planned); this throughput benchmark lets 1 m paths through so that the engine has work."""


def _machine_busy_s() -> float:
    """Busy CPU seconds of the whole machine since boot (all cores, /proc/stat); NaN where absent."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except OSError:
        return float("nan")
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def _autogroup(pid: int | str = "self") -> str | None:
    """The scheduler autogroup of a process (Linux; None elsewhere). With autogroup scheduling on, the
    kernel shares the CPUs fairly between groups (sessions), not between processes."""
    try:
        return Path(f"/proc/{pid}/autogroup").read_text().split()[0]
    except (OSError, IndexError):
        return None


def _autogroup_enabled() -> bool | None:
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return None


def _makespan_cpu(task_cpus: list[float], workers: int) -> float:
    """Critical path in CPU seconds if the tasks (in submission order) ran greedily on ``workers``
    idle cores: what the wall time would be with no contention and no driver overhead."""
    free = [0.0] * workers
    for c in task_cpus:
        k = free.index(min(free))
        free[k] += c
    return max(free)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--per-scene", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="2 scenes, 1 repeat (smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.repeats = 2, 1

    import torch

    torch.set_num_threads(1)
    from image2sim.dataengine.distributed import WORKER_ENV, run_engine
    from image2sim.dataengine.engine_config import EngineConfig
    from image2sim.dataengine.procedural import preset, synthesize

    load_start = load_average()
    hw = f"{hardware()}; load average {load_start:.1f} at start"
    work = Path(tempfile.mkdtemp(prefix="bench_dataengine_"))
    try:
        scenes = work / "scenes"
        synthesize(preset("tiny"), scenes, scenes=args.scenes, seed=0, progress=False)
        counts: dict[str, int] = {}

        def local(render: str):
            def fn():
                out = work / f"out_{render}"
                shutil.rmtree(out, ignore_errors=True)
                cfg = EngineConfig(
                    per_scene=args.per_scene, render=render, obs_height=96, sampling=SHORT_PATHS
                )
                s = run_engine(scenes, out, cfg, executor="local", progress=False)
                assert not s["failed"], s["failed"]
                counts[render] = s["episodes"]

            return fn

        rows = []
        for render in ("none", "procedural"):
            t = time_it(local(render), warmup=1, repeats=args.repeats)
            med = statistics.median(t.walls)
            rows.append(
                {
                    "setting": f"local, 1 core, render={render}",
                    "episodes": counts[render],
                    "median_s": med,
                    "median_cpu_s": statistics.median(t.cpus),
                    "episodes_per_s_per_core": counts[render] / med,
                    "runs_s": [round(x, 3) for x in t.walls],
                }
            )

        import ray

        # With rendering: enough work per scene that task overheads do not dominate.
        cfg = EngineConfig(per_scene=args.per_scene, render="procedural", obs_height=96, sampling=SHORT_PATHS)
        runs: dict[int, list[dict]] = {1: [], 2: []}

        def ray_run(workers: int) -> dict:
            out = work / f"out_ray{workers}"
            shutil.rmtree(out, ignore_errors=True)
            rec: dict = {"load_before": load_average(), "busy0": _machine_busy_s()}
            result: dict = {}

            def fn():
                result.update(run_engine(scenes, out, cfg, executor="ray", workers=workers, progress=False))

            t = time_it(fn, warmup=0, repeats=1)
            machine = _machine_busy_s() - rec.pop("busy0")
            assert not result["failed"], result["failed"]
            tasks = [result["tasks"][s.name] for s in sorted(scenes.iterdir()) if s.is_dir()]
            task_cpu = sum(x["cpu_s"] for x in tasks)
            task_wall = sum(x["wall_s"] for x in tasks)
            per_pid: dict[str, float] = {}
            for x in tasks:
                per_pid[str(x["pid"])] = per_pid.get(str(x["pid"]), 0.0) + x["cpu_s"]
            core_s = workers * t.wall
            rec.update(
                {
                    "wall_s": t.wall,
                    "driver_cpu_s": t.cpu,
                    "task_cpu_s": task_cpu,
                    "task_wall_s": task_wall,
                    "cpu_s_per_worker_pid": {k: round(v, 3) for k, v in per_pid.items()},
                    "torch_threads_in_tasks": sorted({x["torch_threads"] for x in tasks}),
                    "omp_threads_in_tasks": sorted({x["omp_num_threads"] for x in tasks}),
                    "machine_busy_cpu_s": machine,
                    "other_processes_cpu_s": machine - task_cpu - t.cpu,
                    "cpu_efficiency": task_cpu / core_s,
                    "lost_waiting_for_cpu_core_s": task_wall - task_cpu,
                    "lost_worker_idle_core_s": core_s - task_wall,
                    "cpu_makespan_s": _makespan_cpu([x["cpu_s"] for x in tasks], workers),
                    "load_after": load_average(),
                    "episodes": result["episodes"],
                }
            )
            return rec

        ray.init(
            num_cpus=2, include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": WORKER_ENV}
        )
        try:
            ray_run(2)  # warm-up: starts both workers and imports everything in them (not timed)
            for _ in range(args.repeats):
                for workers in (1, 2):
                    runs[workers].append(ray_run(workers))
            # Read while the workers are alive (they end with Ray).
            worker_pids = sorted({p for w in (1, 2) for r in runs[w] for p in r["cpu_s_per_worker_pid"]})
            groups = {"driver": _autogroup(), **{f"worker {p}": _autogroup(p) for p in worker_pids}}
        finally:
            ray.shutdown()
        med = {w: statistics.median(r["wall_s"] for r in runs[w]) for w in (1, 2)}
        for w in (1, 2):
            rs = runs[w]
            rows.append(
                {
                    "setting": f"ray, {w} worker(s), render=procedural",
                    "episodes": rs[0]["episodes"],
                    "median_s": med[w],
                    "median_task_cpu_s": statistics.median(r["task_cpu_s"] for r in rs),
                    "median_cpu_efficiency": statistics.median(r["cpu_efficiency"] for r in rs),
                    "episodes_per_s_per_core": rs[0]["episodes"] / med[w] / w,
                    "runs_s": [round(r["wall_s"], 3) for r in rs],
                    "runs": rs,
                }
            )
        speedup = med[1] / med[2]
        # Per pair (runs of the same repeat were back to back): wall speed-up and CPU-based speed-up.
        pairs = list(zip(runs[1], runs[2], strict=True))
        pair_speedups = [a["wall_s"] / b["wall_s"] for a, b in pairs]
        cpu_speedups = [a["task_cpu_s"] / b["cpu_makespan_s"] for a, b in pairs]
        cpu_speedup = statistics.median(cpu_speedups)
        load_end = load_average()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report = {
        "hardware": hw,
        "scenes": args.scenes,
        "per_scene_planned": args.per_scene,
        "repeats": args.repeats,
        "load_average_start": load_start,
        "load_average_end": load_end,
        "ray_speedup_2_over_1": speedup,
        "ray_speedup_per_pair": pair_speedups,
        "ray_cpu_time_speedup_2_over_1": cpu_speedup,
        "ray_cpu_time_speedup_per_pair": cpu_speedups,
        "target_speedup": 1.8,
        "worker_env": WORKER_ENV,
        "sched_autogroup_enabled": _autogroup_enabled(),
        "autogroups": groups,
    }
    lines = [
        "# Data engine benchmark",
        "",
        f"Hardware: {hw}; load average {load_end:.1f} at the end. {args.scenes} tiny procedural scenes "
        f"(`preset('tiny')`), {args.per_scene} episodes planned per scene, template annotator, "
        "paths from 1 m (`sampling.min_path_length`: tiny houses are below the task's 3 m); median of "
        f"{args.repeats} runs after one warm-up, each from an empty output folder (navigation map, graph "
        "and object mining included).",
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
        "Ray runs (1- and 2-worker runs alternate; one Ray instance, workers warmed up, one thread per "
        "worker: torch and " + ", ".join(f"{k}={v}" for k, v in WORKER_ENV.items()) + "):",
        "",
        "| workers | wall s | driver CPU s | task CPU s | task wall s | CPU efficiency | "
        "waiting for CPU (core-s) | worker idle (core-s) | other processes' CPU s | load before / after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for w in (1, 2):
        for r in runs[w]:
            lines.append(
                f"| {w} | {r['wall_s']:.2f} | {r['driver_cpu_s']:.2f} | {r['task_cpu_s']:.2f} | "
                f"{r['task_wall_s']:.2f} | {r['cpu_efficiency']:.2f} | "
                f"{r['lost_waiting_for_cpu_core_s']:.2f} | {r['lost_worker_idle_core_s']:.2f} | "
                f"{r['other_processes_cpu_s']:.1f} | {r['load_before']:.1f} / {r['load_after']:.1f} |"
            )
    lines += [
        "",
        f"Ray speed-up, 2 workers over 1 (median wall times, Ray and worker start-up excluded): "
        f"**{speedup:.2f}x** (target >= 1.8x; per back-to-back pair: "
        f"{', '.join(f'{x:.2f}' for x in pair_speedups)}).",
        "",
        f"CPU-time-based speed-up (1-worker task CPU / 2-worker critical path in task CPU, i.e. what the "
        f"wall-clock speed-up would be if every task had a whole core): **{cpu_speedup:.2f}x** "
        f"(per pair: {', '.join(f'{x:.2f}' for x in cpu_speedups)}). CPU efficiency = task CPU / "
        "(workers x wall); 'waiting for CPU' is task wall - task CPU (the tasks were runnable but other "
        "processes had the cores), 'worker idle' is workers x wall - task wall (driver, scheduling, the "
        "last scene's tail). The machine is shared: read the wall-clock figures with the load averages.",
    ]
    worker_groups = {g for k, g in groups.items() if k != "driver"}
    if report["sched_autogroup_enabled"] and len(worker_groups) == 1 and None not in worker_groups:
        lines += [
            "",
            f"Scheduler: autogroup scheduling is on and every Ray worker is in one autogroup "
            f"({next(iter(worker_groups))}; the driver: {groups['driver']}). The kernel divides the cores "
            "fairly between autogroups (sessions), not between processes: when other sessions keep both "
            "cores busy, the workers together get about one group's share whether there are 1 or 2 of "
            "them (compare the CPU efficiencies: 1 worker x efficiency vs 2 workers x efficiency), so "
            "the wall-clock speed-up then measures the machine's load, not the engine. The CPU-time-based "
            "figure does not depend on that share.",
        ]
    write_report("dataengine", rows, report, markdown=lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
